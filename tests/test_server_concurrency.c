/* test_server_concurrency: the real shapematchd (SM_SERVER_BIN, --port 0, temp --data-dir)
 * under concurrent clients and at its limits, with small synthetic shapes and k1 = 30:
 *   1. 8 client threads (one connection each) x 25 pipelined requests (PING, HAS, MATCH,
 *      DISTANCE; 4 in flight): every response arrives exactly once with its request id
 *      and the right content (maps / distances equal a local reference);
 *   2. single-flight through STATS: 8 clients PREPARE the same new variant of z at once ->
 *      bases_computed grows by exactly one preparation (2 bases), singleflight_waits >= 1;
 *   3. limits, each on its own daemon (same data dir): --queue 1 --threads 1 flood (BUSY
 *      with retry_after_ms, none lost, STATS busy equals the BUSY answers seen);
 *      --max-inflight 2 (LIMIT_EXCEEDED, detail 2); --max-conns 2 (GOAWAY
 *      TOO_MANY_CONNECTIONS, the others keep working); --token (missing / wrong ->
 *      UNAUTHORIZED, right -> accepted); --cache-mb 1 (cache_evictions > 0, requests still
 *      right, bases reloaded from disk);
 *   4. each daemon still answers afterwards and exits 0 on SIGTERM;
 *   6. a cold pair (daemon P, --threads 2): one MATCH of two new shapes prepares them at
 *      once (STATS prepares_concurrent_max 2, each computed once); a MATCH whose x is not
 *      stored and whose y is new still names x (NOT_FOUND, detail 0);
 *   5. the buffer budget and hostile peers (daemon I, --buffer-budget-mb 16 --max-conns 40):
 *      non-reading PING pipeliners stop being read (STATS read_pauses) while the daemon's
 *      buffered bytes stay under the budget and a good client's PING is answered, then
 *      every pipelined PING is answered exactly once, in order, when they read; partial
 *      uploads are charged as their bytes arrive and freed when they go, and past the
 *      budget the greediest is closed with GOAWAY OVERLOADED; a flood of connections
 *      that never say HELLO fills --max-conns, and a good client still gets in (the
 *      oldest of the flood is evicted with TOO_MANY_CONNECTIONS).
 * Worker threads never use CHECK/REQUIRE (not thread-safe): they count failures in their
 * own context; the main thread checks them. Every socket read has a timeout; alarm()
 * bounds the whole program. */
#include <arpa/inet.h>
#include <cblas.h>
#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/time.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "sm_distance.h"
#include "sm_match.h"
#include "sm_meshio.h"
#include "sm_proto.h"
#include "sm_sha256.h"
#include "sm_synth.h"
#include "sm_test.h"
#include "sm_test_daemon.h"
#include "sm_test_wire.h"


#define K 30
#define IO_TIMEOUT_S 120
#define NCLIENTS 8
#define NREQ 25
#define WINDOW 4

typedef struct shape {
  uint8_t *drc;
  size_t len;
  uint8_t id[32];
  sm_mesh *mesh;
} shape;

static int g_port;
/* Read-only after setup, shared by the client threads. */
static shape g_x, g_y, g_z;
static int32_t *g_ref_map;
static sm_distance_parts g_ref_d;    /* MATCH with WANT_DISTANCE: the map it returns */
static sm_distance_parts g_ref_dist; /* DISTANCE: the distance's own maps (LB basis) */

/* ------------------------------------------------------------------ daemon */

static void on_alarm(int sig) {
  (void)sig;
  static const char m[] = "test_server_concurrency: global timeout\n";
  ssize_t w = write(2, m, sizeof m - 1);
  (void)w;
  if (g_pid > 0) kill(g_pid, SIGKILL);
  _exit(1);
}

/* The common flags of every daemon this test starts; extra (space-separated) adds to them.
 * PUT's background preparation is off: the checks count what the requests compute. */
static int start_daemon(const char *extra) {
  return start_daemon_with("--default-k 30 --drain-ms 5000 --prepare-on-put 0", extra);
}

/* ------------------------------------------------------------------ wire */

/* -1 on failure (thread-safe: no REQUIRE). */
static int connect_to(int port) { return wire_connect(port, IO_TIMEOUT_S); }

/* Request kinds. */
enum { R_PING, R_HAS, R_MATCH, R_DIST, R_PREP, R_STATS };

typedef struct req {
  int kind;
  const shape *a;  /* HAS/PREPARE id, MATCH/DISTANCE x */
  const shape *b;  /* MATCH/DISTANCE y */
  uint64_t opaque; /* PING */
  int k;           /* PREPARE k_lb = k_elastic (0 = default) */
} req;

/* Encodes r with request id rid at out (cap bytes); returns the length or -1. */
static ptrdiff_t enc_req(uint8_t *out, size_t cap, uint32_t rid, const req *r) {
  sm_proto_header h = req_hdr(rid);
  switch (r->kind) {
  case R_PING: {
    sm_proto_ping q = {r->opaque};
    return sm_proto_enc_ping(out, cap, &h, 0, &q);
  }
  case R_HAS: {
    sm_proto_id_req q;
    memcpy(q.id, r->a->id, 32);
    return sm_proto_enc_id_req(out, cap, &h, SM_OP_HAS_SHAPE, &q);
  }
  case R_MATCH:
  case R_DIST: {
    sm_proto_match_req q;
    memset(&q, 0, sizeof q);
    memcpy(q.x, r->a->id, 32);
    memcpy(q.y, r->b->id, 32);
    q.k1 = K;
    q.flags = r->kind == R_MATCH
                  ? SM_MATCH_F_WANT_YX | SM_MATCH_F_WANT_DISTANCE | SM_MATCH_F_SINGLE_START
                  : SM_MATCH_F_SINGLE_START;
    return sm_proto_enc_match_req(out, cap, &h, r->kind == R_MATCH ? SM_OP_MATCH : SM_OP_DISTANCE,
                                  &q);
  }
  case R_PREP: {
    sm_proto_prepare_req q;
    memset(&q, 0, sizeof q);
    memcpy(q.id, r->a->id, 32);
    q.k_lb = q.k_elastic = (uint16_t)r->k;
    return sm_proto_enc_prepare_req(out, cap, &h, &q);
  }
  case R_STATS:
    h.opcode = SM_OP_STATS;
    return sm_proto_enc_empty(out, cap, &h);
  }
  return -1;
}

static int send_req(int fd, uint32_t rid, const req *r) {
  uint8_t buf[512];
  ptrdiff_t n = enc_req(buf, sizeof buf, rid, r);
  if (n <= 0) return -1;
  return send_all(fd, buf, (size_t)n);
}

static const char *kind_name(int k) {
  static const char *n[] = {"PING", "HAS", "MATCH", "DISTANCE", "PREPARE", "STATS"};
  return n[k];
}

/* Checks an OK response's content against the reference; 0 = right. Prints why not. */
static int verify_ok(const req *r, const frame *f, uint32_t rid) {
  static const uint8_t ops[] = {SM_OP_PING, SM_OP_HAS_SHAPE, SM_OP_MATCH, SM_OP_DISTANCE,
                                SM_OP_PREPARE, SM_OP_STATS};
  if (f->h.request_id != rid || f->h.opcode != ops[r->kind] || !(f->h.flags & SM_PROTO_F_RESPONSE) ||
      (f->h.flags & SM_PROTO_F_MORE) || f->h.status != SM_ST_OK) {
    fprintf(stderr, "  %s rid %u: got rid %u opcode %u flags %x status %s\n", kind_name(r->kind),
            rid, f->h.request_id, f->h.opcode, f->h.flags, sm_proto_status_name(f->h.status));
    return -1;
  }
  switch (r->kind) {
  case R_PING: {
    sm_proto_ping p;
    if (sm_proto_dec_ping(f->body, f->body_len, &p) || p.opaque != r->opaque) {
      fprintf(stderr, "  PING rid %u: wrong opaque\n", rid);
      return -1;
    }
    return 0;
  }
  case R_HAS: {
    sm_proto_has_resp h;
    if (sm_proto_dec_has_resp(f->body, f->body_len, &h) || !(h.flags & SM_HAS_STORED) ||
        h.n_vertices != (uint32_t)r->a->mesh->nv || h.n_faces != (uint32_t)r->a->mesh->nf) {
      fprintf(stderr, "  HAS rid %u: wrong answer\n", rid);
      return -1;
    }
    return 0;
  }
  case R_MATCH: {
    sm_proto_match_resp m;
    if (sm_proto_dec_match_resp(1, f->body, f->body_len, &m) || /* hello_tok offers 1 only */
        m.map_xy.count != (uint32_t)r->a->mesh->nv || !(m.flags & SM_MATCH_R_HAS_DISTANCE) ||
        m.map_yx.count != (uint32_t)r->b->mesh->nv) {
      fprintf(stderr, "  MATCH rid %u: bad response layout\n", rid);
      return -1;
    }
    uint32_t diff = 0;
    for (uint32_t i = 0; i < m.map_xy.count; i++) diff += sm_proto_i32_at(&m.map_xy, i) != g_ref_map[i];
    if (diff || fabs(m.dist.total - g_ref_d.total) > 1e-12) {
      fprintf(stderr, "  MATCH rid %u: map differs at %u vertices, total %.17g vs %.17g\n", rid,
              diff, m.dist.total, g_ref_d.total);
      return -1;
    }
    return 0;
  }
  case R_DIST: {
    sm_proto_distance_resp d;
    if (sm_proto_dec_distance_resp(f->body, f->body_len, &d) ||
        fabs(d.dist.total - g_ref_dist.total) > 1e-12) {
      fprintf(stderr, "  DISTANCE rid %u: wrong total\n", rid);
      return -1;
    }
    return 0;
  }
  case R_PREP: {
    sm_proto_prepare_resp p;
    if (sm_proto_dec_prepare_resp(f->body, f->body_len, &p) ||
        (r->k && (p.k_lb != r->k || p.k_elastic != r->k))) {
      fprintf(stderr, "  PREPARE rid %u: wrong answer\n", rid);
      return -1;
    }
    return 0;
  }
  }
  return 0;
}

/* Prints an error frame's message (diagnostics). */
static void print_error(const char *what, const frame *f) {
  sm_proto_error e;
  if (f->h.status && !sm_proto_dec_error(f->body, f->body_len, &e))
    fprintf(stderr, "  %s -> %s: %.*s\n", what, sm_proto_status_name(f->h.status), (int)e.msg_len,
            e.msg);
}

/* One request, one response (no other request in flight); returns the status or -1. */
static int call(int fd, uint32_t rid, const req *r, int verify) {
  if (send_req(fd, rid, r)) return -1;
  frame f;
  if (recv_frame(fd, &f)) return -1;
  int st = f.h.status;
  if (f.h.request_id != rid) st = -1;
  if (st == 0 && verify && verify_ok(r, &f, rid)) st = -1;
  if (st > 0 && st != SM_ST_BUSY) print_error(kind_name(r->kind), &f);
  frame_free(&f);
  return st;
}

/* One request answered by an error: its status (-1 if none) and detail. */
static int call_err(int fd, uint32_t rid, const req *r, uint32_t *detail) {
  if (send_req(fd, rid, r)) return -1;
  frame f;
  if (recv_frame(fd, &f)) return -1;
  int st = f.h.request_id == rid ? f.h.status : -1;
  sm_proto_error e;
  if (st > 0 && !sm_proto_dec_error(f.body, f.body_len, &e)) *detail = e.detail;
  else st = -1;
  frame_free(&f);
  return st;
}

/* HELLO with an optional token; returns the response status (0 OK) or -1 (no answer). */
static int hello_tok(int fd, const char *tok, sm_proto_hello_resp *out) {
  sm_proto_hello_req q;
  memset(&q, 0, sizeof q);
  q.min_version = q.max_version = 1;
  q.token = (const uint8_t *)tok;
  q.token_len = tok ? (uint16_t)strlen(tok) : 0;
  sm_proto_header h = req_hdr(100000);
  uint8_t buf[512];
  ptrdiff_t n = sm_proto_enc_hello_req(buf, sizeof buf, &h, &q);
  if (n <= 0 || send_all(fd, buf, (size_t)n)) return -1;
  frame f;
  if (recv_frame(fd, &f)) return -1;
  int st = f.h.status;
  if (st == 0) {
    sm_proto_hello_resp r;
    if (f.h.opcode != SM_OP_HELLO || sm_proto_dec_hello_resp(f.body, f.body_len, &r)) st = -1;
    else if (out) *out = r;
  } else if (f.h.opcode != SM_OP_GOAWAY) {
    st = -1;
  }
  frame_free(&f);
  return st;
}

static int open_client(void) {
  int fd = connect_to(g_port);
  if (fd < 0) return -1;
  if (hello_tok(fd, NULL, NULL) != 0) {
    close(fd);
    return -1;
  }
  return fd;
}

/* Value of a STATS counter (UINT64_MAX if absent or on error). */
static uint64_t stat_of(int fd, const char *name) {
  static uint32_t rid = 200000;
  req r = {R_STATS, NULL, NULL, 0, 0};
  if (send_req(fd, ++rid, &r)) return UINT64_MAX;
  frame f;
  if (recv_frame(fd, &f)) return UINT64_MAX;
  uint64_t v = UINT64_MAX;
  sm_proto_stats_resp s;
  if (f.h.status == 0 && f.h.request_id == rid && !sm_proto_dec_stats_resp(f.body, f.body_len, &s))
    for (uint32_t i = 0; i < s.count; i++) {
      sm_proto_stat st;
      if (!sm_proto_stat_at(&s, i, &st) && !strcmp(st.name, name)) v = st.value;
    }
  frame_free(&f);
  return v;
}

/* 1 if the peer closed (EOF) within the read timeout. */
static int peer_closed(int fd) {
  uint8_t b;
  for (;;) {
    ssize_t r = recv(fd, &b, 1, 0);
    if (r < 0 && errno == EINTR) continue;
    return r == 0 || (r < 0 && errno == ECONNRESET);
  }
}

static uint16_t put(int fd, const shape *s) {
  sm_proto_put_req q;
  memset(&q, 0, sizeof q);
  memcpy(q.id, s->id, 32);
  q.draco = s->drc;
  q.draco_len = (uint32_t)s->len;
  sm_proto_header h = req_hdr(300000);
  size_t cap = s->len + 256;
  uint8_t *buf = malloc(cap);
  REQUIRE(buf);
  ptrdiff_t n = sm_proto_enc_put_req(buf, cap, &h, &q);
  REQUIRE(n > 0 && send_all(fd, buf, (size_t)n) == 0);
  free(buf);
  frame f;
  REQUIRE(recv_frame(fd, &f) == 0);
  uint16_t st = f.h.status;
  print_error("PUT", &f);
  frame_free(&f);
  return st;
}

/* ------------------------------------------------------------------ data */

static void make_blob(shape *s, int subdiv, unsigned seed, const double stretch[3]) {
  sm_error err;
  sm_mesh *m = NULL;
  REQUIRE(sm_synth_blob(subdiv, 0.2, seed, stretch, &m, &err) == 0);
  REQUIRE(sm_draco_encode(m, 0, &s->drc, &s->len, &err) == 0);
  sm_mesh_destroy(m);
  sm_sha256(s->drc, s->len, s->id);
  REQUIRE(sm_draco_decode(s->drc, s->len, NULL, &s->mesh, &err) == 0);
}

/* The reference MATCH (map and distance of its map) and, with dist_only, the reference
 * DISTANCE (sm_distance_match_opts: the maps a DISTANCE computes). */
static void local_match_ex(const shape *x, const shape *y, int32_t **map, sm_distance_parts *d,
                           int dist_only) {
  sm_shape_opts so;
  sm_shape_opts_default(&so);
  so.k_lb = so.k_elastic = K;
  sm_shape *sx = NULL, *sy = NULL;
  sm_error err;
  REQUIRE(sm_shape_prepare(x->mesh, &so, &sx, &err) == 0);
  REQUIRE(sm_shape_prepare(y->mesh, &so, &sy, &err) == 0);
  sm_match_opts mo;
  sm_match_opts_default(&mo);
  mo.k1 = K;
  mo.multi_start = 0;
  mo.want_yx = 1;
  if (dist_only) sm_distance_match_opts(&mo);
  sm_match_result r;
  REQUIRE(sm_match(sx, sy, &mo, &r, &err) == 0);
  if (map) {
    *map = malloc((size_t)sx->mesh->n_input * 4);
    sm_match_to_input(sx, sy, r.T, *map);
  }
  REQUIRE(sm_shape_distance(sx, sy, r.T, r.T_yx, d, &err) == 0);
  sm_match_result_free(&r);
  sm_shape_destroy(sx);
  sm_shape_destroy(sy);
}

static void local_match(const shape *x, const shape *y, int32_t **map, sm_distance_parts *d) {
  local_match_ex(x, y, map, d, 0);
}


/* ------------------------------------------------------------------ 1. pipelined clients */

typedef struct tctx {
  int idx;
  int fails;
  int answered, ok, busy, limit;
  pthread_barrier_t *bar;
} tctx;

#define TFAIL(t, ...)                                                                \
  do {                                                                               \
    (t)->fails++;                                                                    \
    fprintf(stderr, "client %d: ", (t)->idx);                                        \
    fprintf(stderr, __VA_ARGS__);                                                    \
    fputc('\n', stderr);                                                             \
  } while (0)

static void *pipeline_client(void *arg) {
  tctx *t = arg;
  int fd = open_client();
  if (fd < 0) {
    TFAIL(t, "connect/HELLO failed");
    return NULL;
  }
  /* Request ids are distinct across clients, so a response routed to the wrong
   * connection is caught by its id as well as by its content. */
  uint32_t base = (uint32_t)t->idx * 1000u + 1u;
  req rq[NREQ];
  int seen[NREQ] = {0};
  int sent = 0, got = 0;
  while (got < NREQ) {
    while (sent < NREQ && sent - got < WINDOW) {
      req *r = &rq[sent];
      memset(r, 0, sizeof *r);
      r->kind = (sent + t->idx) % 4; /* R_PING, R_HAS, R_MATCH, R_DIST */
      r->a = &g_x;
      r->b = &g_y;
      if (r->kind == R_HAS && (sent & 1)) r->a = &g_y;
      r->opaque = (uint64_t)t->idx << 32 | (uint64_t)(base + (uint32_t)sent);
      if (send_req(fd, base + (uint32_t)sent, r)) {
        TFAIL(t, "send failed");
        goto out;
      }
      sent++;
    }
    frame f;
    if (recv_frame(fd, &f)) {
      TFAIL(t, "recv failed after %d responses", got);
      goto out;
    }
    got++;
    uint32_t i = f.h.request_id - base;
    if (f.h.request_id < base || i >= (uint32_t)sent) {
      TFAIL(t, "response with unexpected request id %u", f.h.request_id);
    } else if (seen[i]++) {
      TFAIL(t, "second response for request id %u", f.h.request_id);
    } else if (verify_ok(&rq[i], &f, f.h.request_id)) {
      print_error(kind_name(rq[i].kind), &f);
      TFAIL(t, "wrong response for request id %u", f.h.request_id);
    } else {
      t->ok++;
    }
    frame_free(&f);
  }
  for (int i = 0; i < NREQ; i++)
    if (seen[i] != 1) TFAIL(t, "request id %u answered %d times", base + (uint32_t)i, seen[i]);
  /* Nothing extra is pending: the next frame is the answer to a fresh PING. */
  req p = {R_PING, NULL, NULL, 0xabcdef00u + (uint64_t)t->idx, 0};
  if (call(fd, base + 999u, &p, 1) != 0) TFAIL(t, "final PING");
out:
  close(fd);
  return NULL;
}

/* ------------------------------------------------------------------ 2. single-flight */

static void *prepare_client(void *arg) {
  tctx *t = arg;
  int fd = open_client();
  if (fd < 0) TFAIL(t, "connect/HELLO failed");
  pthread_barrier_wait(t->bar); /* every client connected: send together */
  if (fd < 0) return NULL;
  /* z (the biggest shape): its computation outlasts the dispatch of the 8 requests. */
  req r = {R_PREP, &g_z, NULL, 0, 26};
  if (call(fd, 7, &r, 1) != 0) TFAIL(t, "PREPARE k=26 failed");
  close(fd);
  return NULL;
}

/* ------------------------------------------------------------------ 3. BUSY flood */

#define FLOOD 12

static void *flood_client(void *arg) {
  tctx *t = arg;
  int fd = open_client();
  if (fd < 0) TFAIL(t, "connect/HELLO failed");
  pthread_barrier_wait(t->bar);
  if (fd < 0) return NULL;
  /* All FLOOD requests in one write: the loop sees them in one read. */
  uint8_t buf[FLOOD * 256];
  size_t len = 0;
  req r = {R_DIST, &g_x, &g_y, 0, 0};
  for (int i = 0; i < FLOOD; i++) {
    ptrdiff_t n = enc_req(buf + len, sizeof buf - len, (uint32_t)i + 1, &r);
    if (n <= 0) {
      TFAIL(t, "encode");
      close(fd);
      return NULL;
    }
    len += (size_t)n;
  }
  if (send_all(fd, buf, len)) TFAIL(t, "send");
  int seen[FLOOD] = {0};
  uint32_t retry_max = 0;
  int busy_ids[FLOOD], nb = 0;
  for (int k = 0; k < FLOOD; k++) {
    frame f;
    if (recv_frame(fd, &f)) {
      TFAIL(t, "recv failed after %d responses", k);
      break;
    }
    uint32_t i = f.h.request_id - 1;
    if (i >= FLOOD || seen[i]++) {
      TFAIL(t, "unexpected or duplicate request id %u", f.h.request_id);
    } else if (f.h.status == SM_ST_BUSY) {
      sm_proto_error e;
      if (sm_proto_dec_error(f.body, f.body_len, &e) || e.retry_after_ms == 0)
        TFAIL(t, "BUSY without retry_after_ms");
      else if (e.retry_after_ms > retry_max)
        retry_max = e.retry_after_ms;
      t->busy++;
      busy_ids[nb++] = (int)i;
    } else if (verify_ok(&r, &f, f.h.request_id)) {
      print_error("DISTANCE", &f);
      TFAIL(t, "request id %u: neither BUSY nor a right answer", f.h.request_id);
    } else {
      t->ok++;
    }
    frame_free(&f);
  }
  t->answered = 0;
  for (int i = 0; i < FLOOD; i++) t->answered += seen[i] == 1;
  /* Retrying a BUSY request (after retry_after_ms, one at a time) succeeds eventually. */
  pthread_barrier_wait(t->bar);
  if (nb) {
    int st = -1;
    for (int tries = 0; tries < 200 && st != 0; tries++) {
      st = call(fd, 100u + (uint32_t)busy_ids[0] + 1000u * (uint32_t)tries, &r, 1);
      if (st == SM_ST_BUSY) {
        t->busy++;
        sleep_us((long)retry_max * 1000);
      } else if (st != 0) {
        break;
      }
    }
    if (st != 0) TFAIL(t, "retry of a BUSY request failed (%d)", st);
  }
  close(fd);
  return NULL;
}

static void run_threads(void *(*fn)(void *), tctx *t, int n, pthread_barrier_t *bar) {
  pthread_t th[NCLIENTS];
  for (int i = 0; i < n; i++) {
    memset(&t[i], 0, sizeof t[i]);
    t[i].idx = i;
    t[i].bar = bar;
    REQUIRE(pthread_create(&th[i], NULL, fn, &t[i]) == 0);
  }
  for (int i = 0; i < n; i++) pthread_join(th[i], NULL);
}

/* ------------------------------------------------------------------ fan-out helpers */

/* A DISTANCE request body (payload without the frame header) into out (256 bytes);
 * k1 = K and SINGLE_START when tuned, else the server defaults (what QUERY uses). */
static uint32_t dist_body(uint8_t *out, const shape *a, const shape *b, int tuned) {
  sm_proto_match_req q;
  memset(&q, 0, sizeof q);
  memcpy(q.x, a->id, 32);
  memcpy(q.y, b->id, 32);
  if (tuned) {
    q.k1 = K;
    q.flags = SM_MATCH_F_SINGLE_START;
  }
  sm_proto_header h = req_hdr(1);
  uint8_t buf[512];
  ptrdiff_t n = sm_proto_enc_match_req(buf, sizeof buf, &h, SM_OP_DISTANCE, &q);
  REQUIRE(n > SM_PROTO_HEADER_LEN && n - SM_PROTO_HEADER_LEN <= 256);
  memcpy(out, buf + SM_PROTO_HEADER_LEN, (size_t)n - SM_PROTO_HEADER_LEN);
  return (uint32_t)(n - SM_PROTO_HEADER_LEN);
}

/* One DISTANCE request; its total, or -1. */
static double dist_single(int fd, uint32_t rid, const shape *a, const shape *b, int tuned) {
  sm_proto_match_req q;
  memset(&q, 0, sizeof q);
  memcpy(q.x, a->id, 32);
  memcpy(q.y, b->id, 32);
  if (tuned) {
    q.k1 = K;
    q.flags = SM_MATCH_F_SINGLE_START;
  }
  sm_proto_header h = req_hdr(rid);
  uint8_t buf[512];
  ptrdiff_t n = sm_proto_enc_match_req(buf, sizeof buf, &h, SM_OP_DISTANCE, &q);
  REQUIRE(n > 0 && send_all(fd, buf, (size_t)n) == 0);
  frame f;
  REQUIRE(recv_frame(fd, &f) == 0);
  double d = -1;
  sm_proto_distance_resp r;
  if (f.h.request_id == rid && f.h.status == 0 && !sm_proto_dec_distance_resp(f.body, f.body_len, &r))
    d = r.dist.total;
  else
    print_error("DISTANCE", &f);
  frame_free(&f);
  return d;
}

/* Sends a BATCH of n DISTANCE items (pairs[i][0] -> pairs[i][1], tuned). */
static void send_dist_batch(int fd, uint32_t rid, const shape *(*pairs)[2], uint32_t n) {
  sm_proto_batch_item *it = calloc(n, sizeof *it);
  uint8_t(*bodies)[256] = calloc(n, 256);
  REQUIRE(it && bodies);
  for (uint32_t i = 0; i < n; i++) {
    it[i].opcode = SM_OP_DISTANCE;
    it[i].len = dist_body(bodies[i], pairs[i][0], pairs[i][1], 1);
    it[i].payload = bodies[i];
  }
  sm_proto_batch_req b = {it, NULL, 0, n};
  sm_proto_header h = req_hdr(rid);
  size_t cap = 64 + (size_t)n * 300;
  uint8_t *buf = malloc(cap);
  REQUIRE(buf);
  ptrdiff_t len = sm_proto_enc_batch_req(buf, cap, &h, &b);
  REQUIRE(len > 0 && send_all(fd, buf, (size_t)len) == 0);
  free(buf);
  free(it);
  free(bodies);
}

/* Reads a BATCH's answers until its final frame. seen[i] counts item i's frames;
 * dist[i] receives an OK item's total, status[i] its status. Frames for other request
 * ids go to *other (CANCEL answers), counted. Returns 0 and the final frame's counts. */
static int read_batch(int fd, uint32_t rid, uint32_t n, int *seen, double *dist, int *status,
                      sm_proto_batch_done *done, int *other) {
  for (;;) {
    frame f;
    if (recv_frame(fd, &f)) return -1;
    if (f.h.request_id != rid) {
      if (other) (*other)++;
      frame_free(&f);
      continue;
    }
    if (f.h.opcode != SM_OP_BATCH) {
      frame_free(&f);
      return -1;
    }
    if (!(f.h.flags & SM_PROTO_F_MORE)) {
      int rc = f.h.status == 0 && !sm_proto_dec_batch_done(f.body, f.body_len, done) ? 0 : -1;
      frame_free(&f);
      return rc;
    }
    sm_proto_batch_item_resp ir;
    if (sm_proto_dec_batch_item_resp(f.body, f.body_len, &ir) || ir.index >= n) {
      frame_free(&f);
      return -1;
    }
    seen[ir.index]++;
    status[ir.index] = f.h.status;
    sm_proto_distance_resp r;
    if (f.h.status == 0 && ir.opcode == SM_OP_DISTANCE && !sm_proto_dec_distance_resp(ir.payload, ir.len, &r))
      dist[ir.index] = r.dist.total;
    frame_free(&f);
  }
}

/* QUERY; returns the status; hits (ids + distances, at most 16) and n_considered. */
static int query(int fd, uint32_t rid, const shape *q, int k, int mode, uint8_t ids[][32],
                 double *d, uint32_t *n_hits, uint32_t *considered) {
  sm_proto_query_req m;
  memset(&m, 0, sizeof m);
  memcpy(m.id, q->id, 32);
  m.k = (uint16_t)k;
  m.mode = (uint8_t)mode;
  sm_proto_header h = req_hdr(rid);
  uint8_t buf[256];
  ptrdiff_t n = sm_proto_enc_query_req(buf, sizeof buf, &h, &m);
  REQUIRE(n > 0 && send_all(fd, buf, (size_t)n) == 0);
  frame f;
  REQUIRE(recv_frame(fd, &f) == 0);
  int st = f.h.request_id == rid ? f.h.status : -1;
  sm_proto_query_resp r;
  if (st == 0 && !sm_proto_dec_query_resp(f.body, f.body_len, &r) && r.count <= 16) {
    *n_hits = r.count;
    *considered = r.n_considered;
    for (uint32_t i = 0; i < r.count; i++) {
      sm_proto_hit hit;
      sm_proto_hit_at(&r, i, &hit);
      memcpy(ids[i], hit.id, 32);
      d[i] = hit.distance;
    }
  } else if (st == 0) {
    st = -1;
  } else {
    print_error("QUERY", &f);
  }
  frame_free(&f);
  return st;
}

/* Writes a config file at g_dir/name. */
static void write_conf(const char *name, const char *text, char *path, size_t cap) {
  snprintf(path, cap, "%s/%s", g_dir, name);
  FILE *f = fopen(path, "w");
  REQUIRE(f);
  fputs(text, f);
  REQUIRE(fclose(f) == 0);
}

/* 1 if the daemon's log contains s. */
static int log_has(const char *s) {
  FILE *f = fopen(g_log, "r");
  if (!f) return 0;
  char line[2048];
  int found = 0;
  while (!found && fgets(line, sizeof line, f)) found = strstr(line, s) != NULL;
  fclose(f);
  return found;
}

/* ------------------------------------------------------------------ main */

/* ------------------------------------------------------------------ 5. budget */

#define BUDGET_MB 16

/* Sends buf[*off..len) without blocking until the daemon stops taking bytes: no progress
 * for stall_ms (its socket buffers are full because it stopped reading). Returns 0 when
 * it stalled, 1 when everything was sent, -1 on error (e.g. closed by the daemon). */
static int send_until_stall(int fd, const uint8_t *buf, size_t len, size_t *off, int stall_ms) {
  while (*off < len) {
    ssize_t w = send(fd, buf + *off, len - *off, MSG_NOSIGNAL | MSG_DONTWAIT);
    if (w > 0) {
      *off += (size_t)w;
      continue;
    }
    if (w < 0 && errno == EINTR) continue;
    if (w < 0 && errno != EAGAIN && errno != EWOULDBLOCK) return -1;
    struct pollfd p = {fd, POLLOUT, 0};
    int r = poll(&p, 1, stall_ms);
    if (r == 0) return 0;
    if (r < 0 && errno != EINTR) return -1;
  }
  return 1;
}

/* Polls STATS until name <= (below=1) or >= (below=0) v; returns the last value. The
 * daemon sees closes and bytes asynchronously: this waits for a state, bounded. */
static uint64_t wait_stat(int fd, const char *name, uint64_t v, int below) {
  uint64_t x = UINT64_MAX;
  for (int i = 0; i < 600; i++) {
    x = stat_of(fd, name);
    if (x != UINT64_MAX && (below ? x <= v : x >= v)) break;
    sleep_us(20000);
  }
  return x;
}

/* A GOAWAY with the given status arrives (after any other frames). */
static int got_goaway(int fd, uint16_t status, uint32_t *detail) {
  frame f;
  while (recv_frame(fd, &f) == 0) {
    int hit = f.h.opcode == SM_OP_GOAWAY;
    int ok = hit && f.h.status == status;
    sm_proto_error e;
    if (ok && detail && !sm_proto_dec_error(f.body, f.body_len, &e)) *detail = e.detail;
    frame_free(&f);
    if (hit) return ok;
  }
  return 0;
}

static void test_pipeliners(int good) {
  enum { NPIPE = 8, NPING = 1 << 18 }; /* 8 MiB of PINGs each: more than any buffer */
  size_t flen = SM_PROTO_HEADER_LEN + 8;
  uint8_t *buf = malloc(NPING * flen);
  REQUIRE(buf);
  for (uint32_t i = 0; i < NPING; i++) {
    req r = {R_PING, NULL, NULL, 0xabc00000000ull + i, 0};
    REQUIRE(enc_req(buf + i * flen, flen, i + 1, &r) == (ptrdiff_t)flen);
  }
  int fds[NPIPE];
  size_t sent[NPIPE];
  uint64_t pauses0 = stat_of(good, "read_pauses");
  for (int i = 0; i < NPIPE; i++) {
    int small = 16384; /* the client's receive buffer: the daemon's answers pile up fast */
    fds[i] = socket(AF_INET, SOCK_STREAM, 0);
    REQUIRE(fds[i] >= 0);
    setsockopt(fds[i], SOL_SOCKET, SO_RCVBUF, &small, sizeof small);
    struct sockaddr_in a = {.sin_family = AF_INET, .sin_port = htons((uint16_t)g_port)};
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    REQUIRE(connect(fds[i], (struct sockaddr *)&a, sizeof a) == 0);
    struct timeval tv = {IO_TIMEOUT_S, 0};
    setsockopt(fds[i], SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    REQUIRE(hello_tok(fds[i], NULL, NULL) == 0);
    sent[i] = 0;
  }
  for (int i = 0; i < NPIPE; i++) /* stalls: the daemon stopped reading them */
    CHECK_MSG(send_until_stall(fds[i], buf, NPING * flen, &sent[i], 1000) == 0,
              "pipeliner %d: the daemon took all %zu bytes", i, sent[i]);
  uint64_t used = stat_of(good, "buffered_bytes"), peak = stat_of(good, "buffered_peak");
  uint64_t pauses = stat_of(good, "read_pauses");
  fprintf(stderr, "pipeliners: sent %zu..%zu bytes each; buffered %llu, peak %llu, pauses +%llu\n",
          sent[0], sent[NPIPE - 1], (unsigned long long)used, (unsigned long long)peak,
          (unsigned long long)(pauses - pauses0));
  CHECK(used <= (uint64_t)BUDGET_MB << 20 && peak <= (uint64_t)BUDGET_MB << 20);
  CHECK(pauses != UINT64_MAX && pauses >= pauses0 + NPIPE);
  req p = {R_PING, NULL, NULL, 77, 0};
  CHECK(call(good, 1, &p, 1) == 0); /* answered meanwhile */
  /* Now they read: every complete PING answered exactly once, in order (the rest of the
   * buffer is sent as answers are read, so the daemon resumes and finishes them all). */
  for (int i = 0; i < NPIPE; i++) {
    uint32_t want = 1, nping = (uint32_t)NPING;
    int bad = 0;
    while (want <= nping && !bad) {
      if (sent[i] < NPING * flen) (void)send_until_stall(fds[i], buf, NPING * flen, &sent[i], 0);
      frame f;
      if (recv_frame(fds[i], &f)) {
        bad = 1;
        break;
      }
      sm_proto_ping q;
      bad = f.h.status || f.h.request_id != want || sm_proto_dec_ping(f.body, f.body_len, &q) ||
            q.opaque != 0xabc00000000ull + want - 1;
      frame_free(&f);
      want++;
    }
    CHECK_MSG(!bad && want == nping + 1, "pipeliner %d: answer %u wrong or missing", i, want);
    close(fds[i]);
  }
  free(buf);
  used = wait_stat(good, "buffered_bytes", 256u << 10, 1);
  CHECK_MSG(used <= 256u << 10, "buffered_bytes %llu after the pipeliners left",
            (unsigned long long)used);
}

/* One connection that declares a PUT_SHAPE of `declared` payload bytes and sends `part`. */
static int partial_upload(size_t declared, size_t part, size_t *sent) {
  int fd = connect_to(g_port);
  if (fd < 0 || hello_tok(fd, NULL, NULL) != 0) return -1;
  uint8_t *b = calloc(1, SM_PROTO_HEADER_LEN + part);
  if (!b) return -1;
  sm_proto_header h = req_hdr(5);
  h.version = 1; /* hello_tok offers version 1 only */
  h.opcode = SM_OP_PUT_SHAPE;
  h.payload_len = (uint32_t)declared;
  sm_proto_write_header(b, &h);
  *sent = 0;
  (void)send_until_stall(fd, b, SM_PROTO_HEADER_LEN + part, sent, 1000);
  free(b);
  return fd;
}

static void test_partial_uploads(int good) {
  size_t sent = 0, declared = 15u << 20;
  uint64_t base = stat_of(good, "buffered_bytes");
  /* 1. charged as the bytes arrive, not when declared; freed when the peer goes */
  int fd = partial_upload(declared, 3u << 20, &sent);
  REQUIRE(fd >= 0);
  CHECK(sent == SM_PROTO_HEADER_LEN + (3u << 20));
  uint64_t used = wait_stat(good, "buffered_bytes", base + (3u << 20), 0);
  fprintf(stderr, "partial upload of 3 of 15 MiB: buffered %llu (base %llu)\n",
          (unsigned long long)used, (unsigned long long)base);
  CHECK(used >= base + (3u << 20) && used < base + (8u << 20));
  close(fd);
  used = wait_stat(good, "buffered_bytes", base + (64u << 10), 1);
  CHECK_MSG(used <= base + (64u << 10), "buffered %llu after the upload went", (unsigned long long)used);
  /* 2. four of 6 MiB each do not fit in 16 MiB: the greediest go with OVERLOADED */
  enum { NUP = 4 };
  int fds[NUP];
  uint64_t shed0 = stat_of(good, "shed_overloaded");
  for (int i = 0; i < NUP; i++) {
    fds[i] = partial_upload(declared, 6u << 20, &sent);
    REQUIRE(fds[i] >= 0);
  }
  uint64_t shed = wait_stat(good, "shed_overloaded", shed0 + 1, 0);
  uint64_t peak = stat_of(good, "buffered_peak");
  fprintf(stderr, "4 partial uploads of 6 MiB: shed %llu, peak %llu\n",
          (unsigned long long)(shed - shed0), (unsigned long long)peak);
  CHECK(shed != UINT64_MAX && shed >= shed0 + 1);
  CHECK(peak <= (uint64_t)BUDGET_MB << 20);
  req p = {R_PING, NULL, NULL, 78, 0};
  CHECK(call(good, 2, &p, 1) == 0);
  int n_goaway = 0;
  for (int i = 0; i < NUP; i++) {
    if ((int)(shed - shed0) > n_goaway) {
      struct timeval tv = {1, 0}; /* the survivors get nothing: do not wait long on them */
      setsockopt(fds[i], SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
      uint32_t detail = 0;
      if (got_goaway(fds[i], SM_ST_OVERLOADED, &detail)) {
        n_goaway++;
        CHECK(detail > 0); /* the KiB it held */
      }
    }
    close(fds[i]);
  }
  CHECK(n_goaway == (int)(shed - shed0));
  used = wait_stat(good, "buffered_bytes", base + (64u << 10), 1);
  CHECK_MSG(used <= base + (64u << 10), "buffered %llu after the uploads went", (unsigned long long)used);
}

static void test_flood(int good, int max_conns) {
  enum { EXTRA = 16 };
  int fds[64 + EXTRA], n = 0, rejected = 0;
  REQUIRE(max_conns + EXTRA <= 64 + EXTRA);
  uint64_t idle0 = stat_of(good, "shed_idle");
  CHECK(wait_stat(good, "connections", 1, 1) == 1); /* earlier tests' peers are gone */
  /* max_conns - 1 connections that never say HELLO (the good one holds a slot), then more:
   * those are refused, since no flood connection is old enough to be evicted yet. */
  for (int i = 0; i < max_conns - 1; i++) {
    fds[n] = connect_to(g_port);
    REQUIRE(fds[n] >= 0);
    n++;
  }
  (void)wait_stat(good, "connections", (uint64_t)max_conns, 0);
  for (int i = 0; i < EXTRA; i++) {
    int c = connect_to(g_port);
    REQUIRE(c >= 0);
    rejected += got_goaway(c, SM_ST_TOO_MANY_CONNECTIONS, NULL);
    close(c);
  }
  CHECK(rejected == EXTRA);
  /* Once the flood is older than the HELLO grace, a good client gets in. */
  sleep_us(1200000);
  int c = open_client();
  CHECK(c >= 0);
  req p = {R_PING, NULL, NULL, 79, 0};
  if (c >= 0) CHECK(call(c, 1, &p, 1) == 0);
  CHECK(call(good, 3, &p, 1) == 0); /* the busy good client was not evicted */
  CHECK(stat_of(good, "shed_idle") == idle0 + 1);
  CHECK(got_goaway(fds[0], SM_ST_TOO_MANY_CONNECTIONS, NULL)); /* the oldest went */
  for (int i = 0; i < n; i++) close(fds[i]);
  if (c >= 0) close(c);
}

int main(void) {
  signal(SIGPIPE, SIG_IGN);
  signal(SIGALRM, on_alarm);
  atexit(kill_daemon);
  alarm(560);
  openblas_set_num_threads(1);
  snprintf(g_dir, sizeof g_dir, "%s/test_server_concurrency.XXXXXX", SM_TEST_TMP);
  REQUIRE(mkdtemp(g_dir) != NULL);

  double st1[3] = {1, 1, 1}, st2[3] = {1.3, 0.9, 1}, st3[3] = {0.8, 1.2, 1.1};
  make_blob(&g_x, 3, 7, st1);
  make_blob(&g_y, 3, 8, st2);
  make_blob(&g_z, 4, 9, st3); /* bigger: fills the 1 MB cache */
  fprintf(stderr, "shapes: blobs, x %d, y %d, z %d vertices\n", g_x.mesh->nv, g_y.mesh->nv,
          g_z.mesh->nv);
  local_match(&g_x, &g_y, &g_ref_map, &g_ref_d);
  local_match_ex(&g_x, &g_y, NULL, &g_ref_dist, 1);
  tctx t[NCLIENTS];
  pthread_barrier_t bar;

  /* ---------------- daemon A: concurrency and single-flight */
  g_port = start_daemon("--threads 4");
  REQUIRE(g_port > 0);
  int fd = open_client();
  REQUIRE(fd >= 0);
  CHECK(put(fd, &g_x) == SM_ST_OK);
  CHECK(put(fd, &g_y) == SM_ST_OK);
  CHECK(put(fd, &g_z) == SM_ST_OK);

  /* 1. 8 clients x 25 pipelined requests (cold cache: the first MATCHes also race to
   * prepare x and y). */
  run_threads(pipeline_client, t, NCLIENTS, NULL);
  {
    int fails = 0, ok = 0;
    for (int i = 0; i < NCLIENTS; i++) fails += t[i].fails, ok += t[i].ok;
    CHECK(fails == 0);
    CHECK(ok == NCLIENTS * NREQ);
  }
  CHECK(stat_of(fd, "bases_computed") == 4); /* x and y, default k, once each */
  CHECK(stat_of(fd, "inflight") == 0);

  /* 2. single-flight: 8 clients PREPARE z with a new k at once. */
  {
    uint64_t c0 = stat_of(fd, "bases_computed"), w0 = stat_of(fd, "singleflight_waits");
    REQUIRE(pthread_barrier_init(&bar, NULL, NCLIENTS) == 0);
    run_threads(prepare_client, t, NCLIENTS, &bar);
    pthread_barrier_destroy(&bar);
    int fails = 0;
    for (int i = 0; i < NCLIENTS; i++) fails += t[i].fails;
    CHECK(fails == 0);
    uint64_t c1 = stat_of(fd, "bases_computed"), w1 = stat_of(fd, "singleflight_waits");
    CHECK_MSG(c1 == c0 + 2, "bases_computed %llu -> %llu", (unsigned long long)c0,
              (unsigned long long)c1);
    CHECK_MSG(w1 >= w0 + 1 && w1 != UINT64_MAX, "singleflight_waits %llu -> %llu",
              (unsigned long long)w0, (unsigned long long)w1);
  }
  /* 4. still serving; z's default bases go to disk for daemon F. */
  {
    req d = {R_DIST, &g_x, &g_y, 0, 0};
    CHECK(call(fd, 1, &d, 1) == 0);
    req pz = {R_PREP, &g_z, NULL, 0, 0};
    CHECK(call(fd, 2, &pz, 1) == 0);
  }
  close(fd);
  CHECK(stop_daemon() == 0);

  /* ---------------- daemon P: --threads 2, a cold pair prepared at once */
  g_port = start_daemon("--threads 2");
  REQUIRE(g_port > 0);
  {
    /* New shapes (nothing on disk), large enough that each preparation lasts long
     * enough for the idle worker to take the other one. */
    shape a, b, ghost;
    double sa[3] = {1, 0.8, 0.9}, sb[3] = {0.9, 1.1, 0.8};
    make_blob(&a, 4, 21, sa);
    make_blob(&b, 4, 22, sb);
    ghost = g_x;
    ghost.id[0] ^= 0x5a; /* an id never stored */
    fd = open_client();
    REQUIRE(fd >= 0);
    CHECK(put(fd, &a) == SM_ST_OK);
    CHECK(put(fd, &b) == SM_ST_OK);
    uint64_t c0 = stat_of(fd, "bases_computed");
    uint32_t detail = 99;
    req bad = {R_DIST, &ghost, &a, 0, 0};
    CHECK(call_err(fd, 1, &bad, &detail) == SM_ST_NOT_FOUND);
    CHECK_MSG(detail == 0, "missing x reported with detail %u", detail);
    req m = {R_DIST, &a, &b, 0, 0};
    CHECK(call(fd, 2, &m, 0) == SM_ST_OK);
    uint64_t c1 = stat_of(fd, "bases_computed"), conc = stat_of(fd, "prepares_concurrent_max");
    fprintf(stderr, "cold pair: bases_computed %llu -> %llu, prepares_concurrent_max %llu\n",
            (unsigned long long)c0, (unsigned long long)c1, (unsigned long long)conc);
    CHECK(c1 == c0 + 4); /* each basis once: what a's cancelled run finished is on disk */
    CHECK(conc == 2);
    /* Dropped: the QUERY checks below count every stored shape of the data dir. */
    for (int i = 0; i < 2; i++) {
      sm_proto_header h = req_hdr(10 + (uint32_t)i);
      sm_proto_id_req q;
      memcpy(q.id, (i ? &b : &a)->id, 32);
      uint8_t buf[128];
      ptrdiff_t n = sm_proto_enc_id_req(buf, sizeof buf, &h, SM_OP_DROP_SHAPE, &q);
      frame f;
      REQUIRE(n > 0 && send_all(fd, buf, (size_t)n) == 0 && recv_frame(fd, &f) == 0);
      CHECK(f.h.status == SM_ST_OK);
      frame_free(&f);
    }
    close(fd);
    sm_mesh_destroy(a.mesh), free(a.drc);
    sm_mesh_destroy(b.mesh), free(b.drc);
  }
  CHECK(stop_daemon() == 0);

  /* ---------------- daemon B: --queue 1 --threads 1, 4 clients flood DISTANCE */
  g_port = start_daemon("--queue 1 --threads 1");
  REQUIRE(g_port > 0);
  {
    enum { NF = 4 };
    REQUIRE(pthread_barrier_init(&bar, NULL, NF) == 0);
    run_threads(flood_client, t, NF, &bar);
    pthread_barrier_destroy(&bar);
    int fails = 0, ok = 0, busy = 0, answered = 0;
    for (int i = 0; i < NF; i++)
      fails += t[i].fails, ok += t[i].ok, busy += t[i].busy, answered += t[i].answered;
    fprintf(stderr, "flood: %d answered, %d OK, %d BUSY (incl. retries)\n", answered, ok, busy);
    CHECK(fails == 0);
    CHECK(answered == NF * FLOOD);
    CHECK(ok >= 1);
    CHECK(busy >= 1);
    fd = open_client();
    REQUIRE(fd >= 0);
    CHECK(stat_of(fd, "busy") == (uint64_t)busy);
    req d = {R_DIST, &g_x, &g_y, 0, 0};
    CHECK(call(fd, 1, &d, 1) == 0);
    req p = {R_PING, NULL, NULL, 42, 0};
    CHECK(call(fd, 2, &p, 1) == 0);
    close(fd);
  }
  CHECK(stop_daemon() == 0);

  /* ---------------- daemon C: --max-inflight 2 --threads 1 */
  g_port = start_daemon("--max-inflight 2 --threads 1");
  REQUIRE(g_port > 0);
  {
    fd = connect_to(g_port);
    REQUIRE(fd >= 0);
    sm_proto_hello_resp hr;
    CHECK(hello_tok(fd, NULL, &hr) == 0);
    CHECK(hr.max_inflight == 2);
    /* 6 PREPAREs of new variants (slow: bases to compute) and a PING, in one write. */
    enum { NP = 6 };
    req rq[NP + 1];
    uint8_t buf[(NP + 1) * 128];
    size_t len = 0;
    for (int i = 0; i <= NP; i++) {
      req r = {R_PREP, i % 2 ? &g_y : &g_x, NULL, 0, 40 + i};
      if (i == 2) r = (req){R_PING, NULL, NULL, 77, 0};
      rq[i] = r;
      ptrdiff_t n = enc_req(buf + len, sizeof buf - len, (uint32_t)i + 1, &rq[i]);
      REQUIRE(n > 0);
      len += (size_t)n;
    }
    REQUIRE(send_all(fd, buf, len) == 0);
    int seen[NP + 1] = {0}, n_ok = 0, n_lim = 0, bad = 0;
    for (int k = 0; k <= NP; k++) {
      frame f;
      REQUIRE(recv_frame(fd, &f) == 0);
      uint32_t i = f.h.request_id - 1;
      REQUIRE(i <= NP);
      seen[i]++;
      if (f.h.status == SM_ST_LIMIT_EXCEEDED) {
        sm_proto_error e;
        CHECK(sm_proto_dec_error(f.body, f.body_len, &e) == 0 && e.detail == 2);
        CHECK(rq[i].kind == R_PREP);
        n_lim++;
      } else if (verify_ok(&rq[i], &f, f.h.request_id) == 0) {
        n_ok++;
      } else {
        print_error(kind_name(rq[i].kind), &f);
        bad++;
      }
      frame_free(&f);
    }
    for (int i = 0; i <= NP; i++) CHECK(seen[i] == 1);
    fprintf(stderr, "max-inflight 2: %d OK (incl. PING), %d LIMIT_EXCEEDED\n", n_ok, n_lim);
    CHECK(bad == 0);
    CHECK(n_lim >= 1);
    CHECK(n_ok >= 3); /* the PING and at least the first two PREPAREs */
    CHECK(n_ok + n_lim == NP + 1);
    /* Once they are answered, the connection accepts requests again. */
    req d = {R_DIST, &g_x, &g_y, 0, 0};
    CHECK(call(fd, 20, &d, 1) == 0);
    close(fd);
  }
  CHECK(stop_daemon() == 0);

  /* ---------------- daemon D: --max-conns 2 */
  g_port = start_daemon("--max-conns 2 --threads 1");
  REQUIRE(g_port > 0);
  {
    int c1 = open_client(), c2 = open_client();
    REQUIRE(c1 >= 0 && c2 >= 0);
    int c3 = connect_to(g_port);
    REQUIRE(c3 >= 0);
    frame f; /* the daemon answers at accept, before any HELLO */
    REQUIRE(recv_frame(c3, &f) == 0);
    CHECK(f.h.opcode == SM_OP_GOAWAY && f.h.status == SM_ST_TOO_MANY_CONNECTIONS);
    sm_proto_error e;
    CHECK(sm_proto_dec_error(f.body, f.body_len, &e) == 0 && e.retry_after_ms > 0 && e.detail == 2);
    frame_free(&f);
    CHECK(peer_closed(c3));
    close(c3);
    req p = {R_PING, NULL, NULL, 1, 0};
    CHECK(call(c1, 1, &p, 1) == 0);
    req d = {R_DIST, &g_x, &g_y, 0, 0};
    CHECK(call(c2, 1, &d, 1) == 0);
    /* After one closes, a new connection is accepted (once the daemon has seen the EOF:
     * retried after the retry_after_ms the GOAWAY suggested, bounded). */
    close(c2);
    int st = -1;
    for (int tries = 0; tries < 100 && st != 0; tries++) {
      int c = connect_to(g_port);
      REQUIRE(c >= 0);
      st = hello_tok(c, NULL, NULL);
      if (st == 0) CHECK(call(c, 2, &p, 1) == 0);
      close(c);
      if (st != 0) sleep_us(50000);
    }
    CHECK(st == 0);
    CHECK(call(c1, 3, &p, 1) == 0);
    close(c1);
  }
  CHECK(stop_daemon() == 0);

  /* ---------------- daemon E: --token */
  g_port = start_daemon("--token s3cret --threads 1");
  REQUIRE(g_port > 0);
  {
    const char *toks[2] = {NULL, "wrong"};
    for (int i = 0; i < 2; i++) {
      int c = connect_to(g_port);
      REQUIRE(c >= 0);
      CHECK(hello_tok(c, toks[i], NULL) == SM_ST_UNAUTHORIZED);
      CHECK(peer_closed(c));
      close(c);
    }
    int c = connect_to(g_port);
    REQUIRE(c >= 0);
    sm_proto_hello_resp hr;
    CHECK(hello_tok(c, "s3cret", &hr) == 0);
    CHECK(hr.features & SM_HELLO_F_AUTH_REQUIRED);
    req d = {R_DIST, &g_x, &g_y, 0, 0};
    CHECK(call(c, 1, &d, 1) == 0);
    close(c);
  }
  CHECK(stop_daemon() == 0);

  /* ---------------- daemon F: --cache-mb 1: evictions, reloads from disk, right answers */
  g_port = start_daemon("--cache-mb 1 --threads 2");
  REQUIRE(g_port > 0);
  {
    fd = open_client();
    REQUIRE(fd >= 0);
    uint32_t rid = 1;
    for (int round = 0; round < 2; round++) {
      req pz = {R_PREP, &g_z, NULL, 0, 0};
      CHECK(call(fd, rid++, &pz, 1) == 0);
      req m = {R_MATCH, &g_x, &g_y, 0, 0};
      CHECK(call(fd, rid++, &m, 1) == 0);
      req d = {R_DIST, &g_x, &g_y, 0, 0};
      CHECK(call(fd, rid++, &d, 1) == 0);
    }
    uint64_t ev = stat_of(fd, "cache_evictions"), loaded = stat_of(fd, "bases_loaded");
    uint64_t cb = stat_of(fd, "cache_bytes");
    fprintf(stderr, "cache 1 MB: evictions %llu, bases_loaded %llu, cache_bytes %llu\n",
            (unsigned long long)ev, (unsigned long long)loaded, (unsigned long long)cb);
    CHECK(ev != UINT64_MAX && ev > 0);
    CHECK(loaded != UINT64_MAX && loaded > 6); /* z, x, y once each = 6; more = reloads */
    CHECK(stat_of(fd, "bases_computed") == 0);  /* everything came from disk */
    close(fd);
  }
  CHECK(stop_daemon() == 0);

  /* ---------------- daemon G: --threads 2: BATCH items and QUERY candidates on the pool */
  g_port = start_daemon("--threads 2");
  REQUIRE(g_port > 0);
  {
    fd = open_client();
    REQUIRE(fd >= 0);
    shape extra[3];
    double stx[3][3] = {{1.1, 1, 0.9}, {0.9, 1.1, 1.2}, {1.2, 1.2, 0.8}};
    for (int i = 0; i < 3; i++) {
      make_blob(&extra[i], 3, 20u + (unsigned)i, stx[i]);
      CHECK(put(fd, &extra[i]) == SM_ST_OK);
    }
    const shape *pool[6] = {&g_x, &g_y, &g_z, &extra[0], &extra[1], &extra[2]};
    enum { NB = 12 };
    const shape *pairs[NB][2];
    for (int i = 0; i < NB; i++) {
      pairs[i][0] = pool[i % 6];
      pairs[i][1] = pool[(i + 1 + i / 6) % 6];
    }
    /* references: the same pairs as single requests */
    double ref[NB];
    for (int i = 0; i < NB; i++) ref[i] = dist_single(fd, 10 + (uint32_t)i, pairs[i][0], pairs[i][1], 1);
    for (int i = 0; i < NB; i++) CHECK(ref[i] >= 0);
    CHECK(fabs(ref[0] - g_ref_dist.total) <= 1e-12); /* x -> y */
    uint64_t u0 = stat_of(fd, "fanout_units");
    /* 1. every item answered exactly once, as the single requests */
    send_dist_batch(fd, 100, pairs, NB);
    int seen[NB] = {0}, st[NB];
    double got[NB];
    sm_proto_batch_done done = {0, 0};
    CHECK(read_batch(fd, 100, NB, seen, got, st, &done, NULL) == 0);
    for (int i = 0; i < NB; i++) {
      CHECK_MSG(seen[i] == 1, "item %d answered %d times", i, seen[i]);
      CHECK_MSG(seen[i] == 1 && st[i] == 0 && got[i] == ref[i], "item %d: status %d, %.17g vs %.17g",
                i, st[i], got[i], ref[i]);
    }
    CHECK(done.n_items == NB && done.n_ok == NB);
    uint64_t u1 = stat_of(fd, "fanout_units"), wmax = stat_of(fd, "fanout_workers_max");
    fprintf(stderr, "batch of %d: fanout_units +%llu, fanout_workers_max %llu\n", NB,
            (unsigned long long)(u1 - u0), (unsigned long long)wmax);
    CHECK(u1 - u0 == NB);
    CHECK(wmax == 2); /* both workers ran items of the one batch */
    CHECK(stat_of(fd, "inflight") == 0);

    /* 2. CANCEL of a running batch: every item still answered exactly once (OK or
     * CANCELLED), then the final frame. */
    enum { NC = 48 };
    const shape *cp[NC][2];
    for (int i = 0; i < NC; i++) {
      cp[i][0] = pool[(i + 2) % 6];
      cp[i][1] = pool[(i + 3 + i / 6) % 6];
    }
    send_dist_batch(fd, 200, cp, NC);
    sm_proto_cancel_req cq = {200};
    sm_proto_header ch = req_hdr(201);
    uint8_t cbuf[64];
    ptrdiff_t cn = sm_proto_enc_cancel_req(cbuf, sizeof cbuf, &ch, &cq);
    REQUIRE(cn > 0 && send_all(fd, cbuf, (size_t)cn) == 0);
    int cseen[NC] = {0}, cst[NC], other = 0, n_cancelled = 0, n_ok = 0, bad = 0;
    double cd[NC];
    CHECK(read_batch(fd, 200, NC, cseen, cd, cst, &done, &other) == 0);
    for (int i = 0; i < NC; i++) {
      CHECK_MSG(cseen[i] == 1, "cancelled batch: item %d answered %d times", i, cseen[i]);
      if (cst[i] == SM_ST_CANCELLED) n_cancelled++;
      else if (cst[i] == 0) n_ok++;
      else bad++;
    }
    fprintf(stderr, "cancelled batch of %d: %d OK, %d CANCELLED\n", NC, n_ok, n_cancelled);
    CHECK(bad == 0);
    CHECK(n_cancelled >= 1);
    CHECK(done.n_items == NC && done.n_ok == (uint32_t)n_ok);
    if (other == 0) { /* the CANCEL answer came after the final frame */
      frame f;
      REQUIRE(recv_frame(fd, &f) == 0);
      CHECK(f.h.request_id == 201 && f.h.opcode == SM_OP_CANCEL && f.h.status == 0);
      frame_free(&f);
    }
    CHECK(stat_of(fd, "inflight") == 0);
    req p = {R_PING, NULL, NULL, 9, 0};
    CHECK(call(fd, 300, &p, 1) == 0);

    /* 3. QUERY: FULL = a DISTANCE against every other stored shape (server defaults);
     * DEFAULT with 5 candidates (< the shortlist of 16) = the same ranking; SPECTRAL
     * considers the same 5. Units = candidates per phase. */
    const shape *others[5] = {&g_y, &g_z, &extra[0], &extra[1], &extra[2]};
    double full_ref[5];
    for (int i = 0; i < 5; i++) full_ref[i] = dist_single(fd, 400 + (uint32_t)i, &g_x, others[i], 0);
    uint8_t ids[16][32];
    double hd[16];
    uint32_t nh = 0, nc = 0;
    uint64_t q0 = stat_of(fd, "fanout_units");
    CHECK(query(fd, 500, &g_x, 5, SM_QUERY_FULL, ids, hd, &nh, &nc) == 0);
    uint64_t q1 = stat_of(fd, "fanout_units");
    CHECK(nh == 5 && nc == 5);
    CHECK(q1 - q0 == 5);
    for (uint32_t h = 0; h < nh; h++) {
      int found = 0;
      for (int i = 0; i < 5; i++)
        if (!memcmp(ids[h], others[i]->id, 32)) {
          found = 1;
          CHECK_MSG(hd[h] == full_ref[i], "QUERY FULL hit %u: %.17g vs DISTANCE %.17g", h, hd[h], full_ref[i]);
        }
      CHECK(found);
      if (h) CHECK(hd[h - 1] <= hd[h]);
    }
    uint8_t ids2[16][32];
    double hd2[16];
    uint32_t nh2 = 0, nc2 = 0;
    CHECK(query(fd, 501, &g_x, 3, SM_QUERY_DEFAULT, ids2, hd2, &nh2, &nc2) == 0);
    CHECK(nh2 == 3 && nc2 == 5);
    /* 5 spectral, + 5 full matches only when the shipped distance uses maps (otherwise the
     * spectral ranking is already the full one and DEFAULT stops there) */
    CHECK(stat_of(fd, "fanout_units") - q1 == (sm_distance_uses_maps() ? 10u : 5u));
    for (uint32_t h = 0; h < nh2 && h < nh; h++)
      CHECK(!memcmp(ids2[h], ids[h], 32) && hd2[h] == hd[h]);
    CHECK(query(fd, 502, &g_x, 16, SM_QUERY_SPECTRAL, ids2, hd2, &nh2, &nc2) == 0);
    CHECK(nh2 == 5 && nc2 == 5);
    for (uint32_t h = 1; h < nh2; h++) CHECK(hd2[h - 1] <= hd2[h]);
    close(fd);
    for (int i = 0; i < 3; i++) {
      free(extra[i].drc);
      sm_mesh_destroy(extra[i].mesh);
    }
  }
  CHECK(stop_daemon() == 0);

  /* ---------------- daemon H: --config FILE (command-line flags override it) */
  {
    char conf[700];
    write_conf("good.conf",
               "# shapematchd test configuration\n"
               "threads = 1\n"
               "\n"
               "max-inflight = 3   # per connection\n"
               "max-batch-items=5\n"
               "token = c0nf#ig\n",
               conf, sizeof conf);
    char extra[800];
    snprintf(extra, sizeof extra, "--config %s --max-batch-items 9", conf);
    g_port = start_daemon(extra);
    REQUIRE(g_port > 0);
    int c = connect_to(g_port);
    REQUIRE(c >= 0);
    CHECK(hello_tok(c, "wrong", NULL) == SM_ST_UNAUTHORIZED);
    close(c);
    c = connect_to(g_port);
    REQUIRE(c >= 0);
    sm_proto_hello_resp hr;
    CHECK(hello_tok(c, "c0nf#ig", &hr) == 0); /* '#' inside a value is not a comment */
    CHECK(hr.max_inflight == 3);
    CHECK(hr.max_batch_items == 9); /* the flag wins over the file's 5 */
    req d = {R_DIST, &g_x, &g_y, 0, 0};
    CHECK(call(c, 1, &d, 1) == 0);
    close(c);
    CHECK(stop_daemon() == 0);
    CHECK(log_has("threads=1"));

    /* errors name the file and line; the daemon exits (status 2) without listening */
    write_conf("bad_key.conf", "threads = 1\n# fine\nthreadz = 2\n", conf, sizeof conf);
    snprintf(extra, sizeof extra, "--config %s", conf);
    CHECK(start_daemon(extra) == -1);
    char want[800];
    snprintf(want, sizeof want, "%s:3: unknown key 'threadz'", conf);
    CHECK_MSG(log_has(want), "log lacks: %s", want);
    write_conf("bad_val.conf", "max-inflight = lots\n", conf, sizeof conf);
    snprintf(extra, sizeof extra, "--config %s", conf);
    CHECK(start_daemon(extra) == -1);
    snprintf(want, sizeof want, "%s:1: max-inflight: bad value 'lots'", conf);
    CHECK_MSG(log_has(want), "log lacks: %s", want);
    write_conf("bad_line.conf", "port 7878\n", conf, sizeof conf);
    snprintf(extra, sizeof extra, "--config %s", conf);
    CHECK(start_daemon(extra) == -1);
    snprintf(want, sizeof want, "%s:1: expected 'key = value'", conf);
    CHECK_MSG(log_has(want), "log lacks: %s", want);
  }

  /* ---------------- daemon I: the buffer budget, hostile peers, a flood */
  g_port = start_daemon("--buffer-budget-mb 16 --max-conns 40 --threads 1");
  REQUIRE(g_port > 0);
  {
    int good = open_client();
    REQUIRE(good >= 0);
    CHECK(stat_of(good, "buffer_budget") == (uint64_t)BUDGET_MB << 20);
    test_pipeliners(good);
    test_partial_uploads(good);
    test_flood(good, 40);
    close(good);
  }
  CHECK(stop_daemon() == 0);

  kill_daemon();
  if (!sm_test_failures) rm_rf(g_dir);
  else fprintf(stderr, "kept %s for inspection\n", g_dir);
  free(g_ref_map);
  shape *all[3] = {&g_x, &g_y, &g_z};
  for (int i = 0; i < 3; i++) {
    free(all[i]->drc);
    sm_mesh_destroy(all[i]->mesh);
  }
  return sm_test_finish();
}
