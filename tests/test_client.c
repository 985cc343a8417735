/* test_client: the client library without a daemon, then (when the build has one) the CLI
 * against the real daemon.
 *
 * Part 1, no server: argument validation, address parsing, ids.
 * Part 2, scripted peer: each case forks; the child plays the server over a socketpair with
 *   sm_proto (decodes what the client sent, checks every field, answers), the parent runs
 *   the client. The child's failed checks come back as its exit status. The peer chooses
 *   protocol version 1 (no MATCH confidence) except in the "version 2" case, which also
 *   sends a confidence outside [0, 1] that the client must refuse.
 * Part 3, only with SM_SERVER_BIN and SM_CLI_BIN (tests/CMakeLists.txt defines them when
 *   the shapematchd target exists): starts the daemon on --port 0 with a temporary data
 *   directory and runs the real CLI (put, match, distance, batch, stats) against it,
 *   comparing with --local; match --json and batch --maps carry a confidence in [0, 1].
 *   Skipped, with a message, when the daemon does not come up.
 */
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "sm_client.h"
#include "sm_meshio.h"
#include "sm_proto.h"
#include "sm_sha256.h"
#include "sm_synth.h"
#include "sm_test.h"

/* ------------------------------------------------------------------ part 1 */

static void test_addr(void) {
  char h[256];
  uint16_t port = 1;
  sm_client_error e;
  CHECK(sm_client_parse_addr("example.org:7000", h, sizeof h, &port, &e) == 0 && !strcmp(h, "example.org") && port == 7000);
  CHECK(sm_client_parse_addr("127.0.0.1", h, sizeof h, &port, &e) == 0 && !strcmp(h, "127.0.0.1") && port == SM_CLIENT_DEFAULT_PORT);
  CHECK(sm_client_parse_addr("[::1]:9", h, sizeof h, &port, &e) == 0 && !strcmp(h, "::1") && port == 9);
  CHECK(sm_client_parse_addr("[fe80::2]", h, sizeof h, &port, &e) == 0 && !strcmp(h, "fe80::2") && port == SM_CLIENT_DEFAULT_PORT);
  CHECK(sm_client_parse_addr(":8080", h, sizeof h, &port, &e) == 0 && !strcmp(h, "localhost") && port == 8080);
  CHECK(sm_client_parse_addr("unix:/tmp/s.sock", h, sizeof h, &port, &e) == 0 && !strcmp(h, "/tmp/s.sock") && port == 0);
  const char *bad[] = {"", "host:", "host:0", "host:65536", "host:12x", "host:-1", "host:+5",
                       "::1", "[::1", "[::1]x", "[]:80", "unix:", "a b:1", ":", NULL};
  for (int i = 0; bad[i]; i++) {
    int rc = sm_client_parse_addr(bad[i], h, sizeof h, &port, &e);
    CHECK_MSG(rc == SM_CLIENT_EADDR && e.code == rc && e.msg[0], "'%s' -> %d", bad[i], rc);
  }
  char small[4];
  CHECK(sm_client_parse_addr("longhost:1", small, sizeof small, &port, &e) == SM_CLIENT_EADDR);
  CHECK(sm_client_parse_addr(NULL, h, sizeof h, &port, &e) == SM_CLIENT_EINVAL);
}

static void test_ids(void) {
  uint8_t id[32], back[32];
  char hex[65];
  sm_client_shape_id((const uint8_t *)"abc", 3, id);
  sm_client_id_to_hex(id, hex);
  CHECK(!strcmp(hex, "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"));
  CHECK(sm_client_id_from_hex(hex, back) == 0 && !memcmp(id, back, 32));
  CHECK(sm_client_id_from_hex("BA7816BF8F01CFEA414140DE5DAE2223B00361A396177A9CB410FF61F20015AD", back) == 0 &&
        !memcmp(id, back, 32));
  CHECK(sm_client_id_from_hex("ba7816bf", back) == SM_CLIENT_EINVAL);
  CHECK(sm_client_id_from_hex("ga7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad", back) == SM_CLIENT_EINVAL);
  CHECK(sm_client_id_from_hex(NULL, back) == SM_CLIENT_EINVAL);
}

static void test_args(void) {
  sm_client_error e;
  sm_client *c = (sm_client *)1;
  CHECK(sm_client_connect("127.0.0.1:1", NULL, NULL, &e) == SM_CLIENT_EINVAL);
  CHECK(sm_client_connect("bad:port", NULL, &c, &e) == SM_CLIENT_EADDR && c == NULL);
  sm_client_opts o;
  sm_client_opts_default(&o);
  o.token_len = SM_PROTO_MAX_TOKEN + 1;
  o.token = (const uint8_t *)"x";
  int sv[2];
  REQUIRE(socketpair(AF_UNIX, SOCK_STREAM, 0, sv) == 0);
  CHECK(sm_client_connect_fd(sv[0], &o, &c, &e) == SM_CLIENT_EINVAL); /* closes sv[0] */
  close(sv[1]);
  CHECK(sm_client_connect_fd(-1, NULL, &c, &e) == SM_CLIENT_EINVAL);
  uint8_t id[32] = {0};
  CHECK(sm_client_ping(NULL, NULL, &e) == SM_CLIENT_EINVAL);
  CHECK(sm_client_put(NULL, id, 1, 0, NULL, NULL, &e) == SM_CLIENT_EINVAL);
  CHECK(sm_client_match(NULL, id, id, NULL, NULL, &e) == SM_CLIENT_EINVAL);
  uint8_t *buf;
  size_t len;
  CHECK(sm_client_file_draco("/nonexistent/x.off", &buf, &len, &e) == SM_CLIENT_EMESH && e.msg[0]);
  CHECK(strcmp(sm_client_strerror(SM_CLIENT_ETIMEOUT), "unknown error") != 0);
  sm_client_close(NULL);
}

/* ------------------------------------------------------------------ part 2: peer */

typedef struct peer {
  int fd;
  uint8_t *buf;
  size_t len, cap, used;
} peer;

/* Next client frame: 0, 1 on timeout, 2 on EOF, < 0 parse error. */
static int peer_frame(peer *p, sm_proto_frame *f, int timeout_ms) {
  if (p->used) {
    memmove(p->buf, p->buf + p->used, p->len - p->used);
    p->len -= p->used;
    p->used = 0;
  }
  for (;;) {
    ptrdiff_t r = sm_proto_parse_frame(p->buf, p->len, UINT32_MAX, f);
    if (r > 0) {
      p->used = (size_t)r;
      return 0;
    }
    if (r != SM_PROTO_PARTIAL) return (int)r;
    struct pollfd pf = {p->fd, POLLIN, 0};
    if (poll(&pf, 1, timeout_ms) == 0) return 1;
    if (p->cap - p->len < 65536) {
      p->cap = p->cap ? 2 * p->cap : 1 << 17;
      p->buf = realloc(p->buf, p->cap);
      REQUIRE(p->buf);
    }
    ssize_t n = read(p->fd, p->buf + p->len, p->cap - p->len);
    if (n <= 0) return 2;
    p->len += (size_t)n;
  }
}

static void peer_send(peer *p, const uint8_t *b, ptrdiff_t n) {
  REQUIRE(n > 0);
  while (n > 0) {
    ssize_t w = write(p->fd, b, (size_t)n);
    if (w < 0 && errno == EINTR) continue;
    REQUIRE(w > 0);
    b += w;
    n -= w;
  }
}

static uint8_t g_out[1 << 20];
#define SEND(p, call)                                                                \
  do {                                                                               \
    ptrdiff_t n_ = (call);                                                           \
    REQUIRE(n_ > 0 && (size_t)n_ <= sizeof g_out);                                   \
    peer_send(p, g_out, n_);                                                         \
  } while (0)

static sm_proto_header resp_hdr(uint32_t rid) {
  sm_proto_header h = {0};
  h.request_id = rid;
  return h;
}

static void send_error(peer *p, uint8_t op, uint32_t rid, uint16_t status, uint32_t detail,
                       uint32_t retry, const char *msg) {
  sm_proto_header h = resp_hdr(rid);
  h.opcode = op;
  h.status = status;
  sm_proto_error e = {retry, detail, msg, (uint32_t)strlen(msg)};
  SEND(p, sm_proto_enc_error(g_out, sizeof g_out, &h, &e));
}

/* Expects a request with opcode op; returns it in *f. */
static int expect(peer *p, uint8_t op, sm_proto_frame *f) {
  int r = peer_frame(p, f, 5000);
  CHECK_MSG(r == 0, "peer_frame: %d", r);
  if (r) return 0;
  CHECK_MSG(f->h.opcode == op, "got %s, want %s", sm_proto_op_name(f->h.opcode), sm_proto_op_name(op));
  CHECK(!(f->h.flags & SM_PROTO_F_RESPONSE) && f->h.request_id != 0);
  return f->h.opcode == op;
}

static const uint8_t k_token[] = "s3cret";
static uint8_t k_affinity[32];

/* Answers the client's HELLO (which offers every version it speaks) choosing `version`. */
static void srv_hello_v(peer *p, uint32_t max_inflight, uint16_t version) {
  sm_proto_frame f;
  sm_proto_hello_req m;
  if (!expect(p, SM_OP_HELLO, &f)) exit(1);
  CHECK(f.h.version == 1);
  REQUIRE(sm_proto_dec_hello_req(f.body, f.body_len, &m) == 0);
  CHECK(m.min_version == 1 && m.max_version == SM_PROTO_VERSION_MAX);
  sm_proto_hello_resp r = {version, 1 << 28, 1000000, 2000000, max_inflight, 64, 100, 300, 0, 0};
  sm_proto_header h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_hello_resp(g_out, sizeof g_out, &h, &r));
}
/* A server of protocol version 1 only, as before version 2 existed. */
static void srv_hello(peer *p, uint32_t max_inflight) { srv_hello_v(p, max_inflight, 1); }

typedef void (*srv_fn)(peer *p, void *ud);
typedef void (*cli_fn)(int fd, void *ud);

/* Forks: the child runs srv on one end of a socketpair, the parent cli on the other. */
static void run_pair(const char *name, srv_fn srv, cli_fn cli, void *ud) {
  int sv[2];
  REQUIRE(socketpair(AF_UNIX, SOCK_STREAM, 0, sv) == 0);
  fflush(NULL);
  pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    sm_test_failures = 0; /* the parent's count is not the child's */
    close(sv[0]);
    peer p = {sv[1], NULL, 0, 0, 0};
    srv(&p, ud);
    free(p.buf);
    _exit(sm_test_failures ? 1 : 0);
  }
  close(sv[1]);
  cli(sv[0], ud);
  int st = 0;
  REQUIRE(waitpid(pid, &st, 0) == pid);
  CHECK_MSG(WIFEXITED(st) && WEXITSTATUS(st) == 0, "%s: the scripted server saw failures (status %d)", name, st);
}

static sm_client *connect_fd(int fd, int io_timeout_ms) {
  sm_client_opts o;
  sm_client_error e;
  sm_client *c = NULL;
  sm_client_opts_default(&o);
  o.token = k_token;
  o.token_len = sizeof k_token - 1;
  o.affinity = k_affinity;
  o.max_response = 1u << 26;
  if (io_timeout_ms) o.io_timeout_ms = io_timeout_ms;
  int rc = sm_client_connect_fd(fd, &o, &c, &e);
  CHECK_MSG(rc == 0, "connect_fd: %d %s", rc, e.msg);
  return c;
}

/* ---- case: HELLO fields, PING, STATS, PUT (id + Draco round trip), HAS, DROP ---- */
static sm_mesh *g_mesh;
static char g_off[512];

static void srv_basic(peer *p, void *ud) {
  (void)ud;
  sm_proto_frame f;
  sm_proto_hello_req hr;
  REQUIRE(expect(p, SM_OP_HELLO, &f));
  REQUIRE(sm_proto_dec_hello_req(f.body, f.body_len, &hr) == 0);
  CHECK(hr.min_version == 1 && hr.max_version == SM_PROTO_VERSION_MAX && hr.max_response == 1u << 26);
  CHECK(hr.token_len == 6 && !memcmp(hr.token, "s3cret", 6));
  CHECK(!memcmp(hr.affinity, k_affinity, 32));
  sm_proto_hello_resp r = {1, 1 << 28, 1000000, 2000000, 8, 64, 100, 300, 60000, 0};
  sm_proto_header h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_hello_resp(g_out, sizeof g_out, &h, &r));

  sm_proto_ping ping;
  REQUIRE(expect(p, SM_OP_PING, &f));
  REQUIRE(sm_proto_dec_ping(f.body, f.body_len, &ping) == 0);
  h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_ping(g_out, sizeof g_out, &h, 1, &ping));

  REQUIRE(expect(p, SM_OP_STATS, &f));
  CHECK(sm_proto_dec_empty(f.body, f.body_len) == 0);
  sm_proto_stat st[2] = {{"shapes", 3}, {"uptime_s", 42}};
  sm_proto_stats_resp sr = {st, NULL, 2};
  h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_stats_resp(g_out, sizeof g_out, &h, &sr));

  /* PUT: the id is the SHA-256 of the Draco bytes, which decode to the file's mesh in the
   * file's order */
  sm_proto_put_req pr;
  REQUIRE(expect(p, SM_OP_PUT_SHAPE, &f));
  CHECK(f.h.flags & SM_PROTO_F_PAYLOAD_CRC); /* the client asked for payload CRCs */
  REQUIRE(sm_proto_dec_put_req(f.body, f.body_len, &pr) == 0);
  uint8_t id[32];
  sm_sha256(pr.draco, pr.draco_len, id);
  CHECK(!memcmp(id, pr.id, 32));
  CHECK(pr.flags == SM_PUT_F_PREPARE);
  sm_mesh *d = NULL;
  sm_error err;
  CHECK(sm_draco_decode(pr.draco, pr.draco_len, NULL, &d, &err) == 0);
  if (d) {
    CHECK(d->nv == g_mesh->nv && d->nf == g_mesh->nf);
    if (d->nv == g_mesh->nv && d->nf == g_mesh->nf) {
      int bad = 0;
      for (int64_t i = 0; i < 3 * (int64_t)d->nv; i++) bad += (double)(float)g_mesh->V[i] != d->V[i];
      CHECK_MSG(bad == 0, "%d coordinates differ from the file's (as float32)", bad);
      CHECK(!memcmp(d->F, g_mesh->F, (size_t)d->nf * 3 * sizeof(int32_t)));
    }
    sm_mesh_destroy(d);
  }
  sm_proto_put_resp pu;
  memcpy(pu.id, pr.id, 32);
  pu.n_vertices = (uint32_t)g_mesh->nv;
  pu.n_faces = (uint32_t)g_mesh->nf;
  pu.flags = 0;
  h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_put_resp(g_out, sizeof g_out, &h, &pu));

  /* a second PUT answered with another id: the client must refuse it */
  REQUIRE(expect(p, SM_OP_PUT_SHAPE, &f));
  REQUIRE(sm_proto_dec_put_req(f.body, f.body_len, &pr) == 0);
  CHECK(pr.draco_len == 3 && !memcmp(pr.draco, "abc", 3) && pr.flags == 0);
  memset(pu.id, 0x55, 32);
  h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_put_resp(g_out, sizeof g_out, &h, &pu));
  CHECK(peer_frame(p, &f, 5000) == 2); /* the client hangs up */
}

static void cli_basic(int fd, void *ud) {
  (void)ud;
  sm_client_opts o;
  sm_client_error e;
  sm_client *c = NULL;
  sm_client_opts_default(&o);
  o.token = k_token;
  o.token_len = 6;
  o.affinity = k_affinity;
  o.max_response = 1u << 26;
  o.payload_crc = 1;
  int rc = sm_client_connect_fd(fd, &o, &c, &e);
  REQUIRE(rc == 0);
  const sm_proto_hello_resp *lim = sm_client_limits(c);
  CHECK(lim->version == 1 && lim->max_inflight == 8 && lim->max_k == 300 && lim->idle_timeout_ms == 60000);
  double rtt = -1;
  CHECK(sm_client_ping(c, &rtt, &e) == 0 && rtt >= 0);
  sm_proto_stat *st = NULL;
  uint32_t n = 0;
  CHECK(sm_client_stats(c, &st, &n, &e) == 0 && n == 2 && !strcmp(st[0].name, "shapes") &&
        st[0].value == 3 && st[1].value == 42);
  free(st);
  uint8_t id[32];
  sm_proto_put_resp pr;
  rc = sm_client_put_file(c, g_off, 1, id, &pr, &e);
  CHECK_MSG(rc == 0, "put_file: %s", e.msg);
  uint8_t *buf;
  size_t len;
  uint8_t want[32];
  REQUIRE(sm_client_file_draco(g_off, &buf, &len, &e) == 0);
  sm_sha256(buf, len, want);
  free(buf);
  CHECK(!memcmp(id, want, 32) && pr.n_vertices == (uint32_t)g_mesh->nv);
  rc = sm_client_put(c, (const uint8_t *)"abc", 3, 0, id, NULL, &e);
  CHECK(rc == SM_CLIENT_EPROTO && !sm_client_is_open(c));
  CHECK(sm_client_ping(c, NULL, &e) == SM_CLIENT_ECLOSED);
  sm_client_close(c);
}

/* ---- case: MATCH fields both ways, option validation, a request-level error ---- */
static const int32_t k_lm[4] = {0, 5, 7, 2};

static void srv_match(peer *p, void *ud) {
  (void)ud;
  sm_proto_frame f;
  sm_proto_match_req m;
  srv_hello(p, 4);
  REQUIRE(expect(p, SM_OP_MATCH, &f));
  REQUIRE(sm_proto_dec_match_req(SM_OP_MATCH, f.body, f.body_len, &m) == 0);
  CHECK(m.x[0] == 1 && m.y[0] == 2 && m.basis == 1 && m.init == 1 && m.k0 == 10 && m.k1 == 30 &&
        m.step == 4 && m.eta == 2e-4 && m.deadline_ms == 5000);
  CHECK(m.flags == (SM_MATCH_F_WANT_YX | SM_MATCH_F_WANT_FMAP | SM_MATCH_F_MULTI_START |
                    SM_MATCH_F_SINKHORN_LEVELS | SM_MATCH_F_WANT_DISTANCE));
  CHECK(m.sinkhorn_levels == 0);
  CHECK(m.landmarks.count == 4 && m.init_map.count == 0);
  for (uint32_t i = 0; i < 4 && m.landmarks.count == 4; i++) CHECK(sm_proto_i32_at(&m.landmarks, i) == k_lm[i]);
  int32_t xy[5] = {4, 3, -1, 1, 0}, yx[3] = {0, 1, 2};
  double C[4] = {1, 0, 0, -1};
  sm_proto_match_resp r;
  memset(&r, 0, sizeof r);
  r.init_used = 1;
  r.flags = SM_MATCH_R_FLIPPED | SM_MATCH_R_HAS_DISTANCE;
  r.orientation = 0.5;
  r.dirichlet = 7.25;
  r.dist = (sm_proto_dist){0.25, 0.1, 0.2, 0.3, -1};
  r.t_init_us = 1500000;
  r.t_total_us = 2000000;
  r.map_xy = (sm_proto_i32s){xy, NULL, 5};
  r.map_yx = (sm_proto_i32s){yx, NULL, 3};
  r.kC = 2;
  r.fmap = (sm_proto_f64s){C, NULL, 4};
  sm_proto_header h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_match_resp(g_out, sizeof g_out, &h, 1, &r));

  /* defaults: everything 0, no flags; answered NOT_FOUND (request-level) */
  REQUIRE(expect(p, SM_OP_DISTANCE, &f));
  REQUIRE(sm_proto_dec_match_req(SM_OP_DISTANCE, f.body, f.body_len, &m) == 0);
  CHECK(m.basis == 0 && m.init == 0 && m.flags == 0 && m.k0 == 0 && m.k1 == 0 && m.eta == 0 &&
        m.landmarks.count == 0 && m.init_map.count == 3);
  send_error(p, SM_OP_DISTANCE, f.h.request_id, SM_ST_NOT_FOUND, 1, 0, "y is not stored");

  /* the connection lives on */
  REQUIRE(expect(p, SM_OP_DISTANCE, &f));
  REQUIRE(sm_proto_dec_match_req(SM_OP_DISTANCE, f.body, f.body_len, &m) == 0);
  CHECK(m.flags == SM_MATCH_F_SINGLE_START);
  sm_proto_distance_resp dr = {{0.5, 0.4, 0.6, 0.1, 0.2}, 1000};
  h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_distance_resp(g_out, sizeof g_out, &h, &dr));

  sm_proto_query_req q;
  REQUIRE(expect(p, SM_OP_QUERY, &f));
  REQUIRE(sm_proto_dec_query_req(f.body, f.body_len, &q) == 0);
  CHECK(q.k == 2 && q.mode == SM_QUERY_SPECTRAL && q.n_candidates == 0 && q.id[0] == 1);
  sm_proto_hit hits[2] = {{{3}, 0.1}, {{4}, 0.2}};
  sm_proto_query_resp qr = {7, 99, hits, NULL, 2};
  h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_query_resp(g_out, sizeof g_out, &h, &qr));

  /* HAS, PREPARE, DROP */
  sm_proto_id_req ir;
  REQUIRE(expect(p, SM_OP_HAS_SHAPE, &f));
  REQUIRE(sm_proto_dec_id_req(f.body, f.body_len, &ir) == 0 && ir.id[0] == 2);
  sm_proto_has_resp hr = {SM_HAS_STORED | SM_HAS_PREPARED, 10, 16};
  h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_has_resp(g_out, sizeof g_out, &h, &hr));
  sm_proto_prepare_req pq;
  REQUIRE(expect(p, SM_OP_PREPARE, &f));
  REQUIRE(sm_proto_dec_prepare_req(f.body, f.body_len, &pq) == 0);
  CHECK(pq.k_lb == 50 && pq.k_elastic == 60 && pq.eta == 1e-3);
  sm_proto_prepare_resp pp = {10, 16, 50, 60, SM_PREP_R_CACHED, 0, 0, 0, 0};
  h = resp_hdr(f.h.request_id);
  SEND(p, sm_proto_enc_prepare_resp(g_out, sizeof g_out, &h, &pp));
  REQUIRE(expect(p, SM_OP_DROP_SHAPE, &f));
  h = resp_hdr(f.h.request_id);
  h.opcode = SM_OP_DROP_SHAPE;
  h.flags = SM_PROTO_F_RESPONSE;
  SEND(p, sm_proto_enc_empty(g_out, sizeof g_out, &h));

  /* a fatal GOAWAY in answer to PING */
  REQUIRE(expect(p, SM_OP_PING, &f));
  send_error(p, SM_OP_GOAWAY, f.h.request_id, SM_ST_PROTOCOL_ERROR, 0, 0, "go away");
  CHECK(peer_frame(p, &f, 5000) == 2);
}

static void cli_match(int fd, void *ud) {
  (void)ud;
  sm_client *c = connect_fd(fd, 0);
  REQUIRE(c);
  sm_client_error e;
  uint8_t x[32] = {1}, y[32] = {2};
  sm_client_match_opts o;
  sm_client_match_result r;
  sm_client_match_opts_default(&o);
  /* refused locally, nothing sent */
  o.basis = 4;
  CHECK(sm_client_match(c, x, y, &o, &r, &e) == SM_CLIENT_EINVAL && e.msg[0]);
  o.basis = 0;
  o.k0 = 40;
  o.k1 = 30;
  CHECK(sm_client_match(c, x, y, &o, &r, &e) == SM_CLIENT_EINVAL);
  o.k0 = 0;
  o.eta = -1;
  CHECK(sm_client_match(c, x, y, &o, &r, &e) == SM_CLIENT_EINVAL);
  o.eta = 0;
  int32_t neg[2] = {-1, 0};
  o.landmarks = neg;
  o.n_landmarks = 1;
  CHECK(sm_client_match(c, x, y, &o, &r, &e) == SM_CLIENT_EINVAL);
  o.multi_start = 2;
  o.n_landmarks = 0;
  CHECK(sm_client_match(c, x, y, &o, &r, &e) == SM_CLIENT_EINVAL);
  CHECK(sm_client_is_open(c));

  sm_client_match_opts_default(&o);
  o.basis = 1;
  o.init = 1;
  o.k0 = 10;
  o.k1 = 30;
  o.step = 4;
  o.eta = 2e-4;
  o.sinkhorn_levels = 0;
  o.multi_start = 1;
  o.landmarks = k_lm;
  o.n_landmarks = 2;
  o.want_yx = o.want_fmap = o.want_distance = 1;
  o.deadline_ms = 5000;
  int rc = sm_client_match(c, x, y, &o, &r, &e);
  CHECK_MSG(rc == 0, "match: %s", e.msg);
  if (!rc) {
    CHECK(r.nx == 5 && r.ny == 3 && r.kC == 2 && r.init_used == 1 && r.flipped && r.has_distance);
    CHECK(r.map_xy[0] == 4 && r.map_xy[2] == -1 && r.map_yx[2] == 2 && r.fmap[3] == -1);
    CHECK(r.orientation == 0.5 && r.dirichlet == 7.25 && r.dist.total == 0.25 && r.dist.spectrum_elastic == -1);
    CHECK(!r.has_confidence && isnan(r.confidence)); /* a version 1 server has none */
    CHECK_NEAR(r.t_init, 1.5, 1e-12);
    CHECK_NEAR(r.t_total, 2.0, 1e-12);
  }
  sm_client_match_result_free(&r);
  sm_client_match_result_free(&r); /* idempotent */

  sm_client_match_opts_default(&o);
  int32_t init[3] = {0, -1, 2};
  o.init_map = init;
  o.n_init_map = 3;
  o.want_yx = 1; /* not a DISTANCE flag: not sent */
  sm_proto_dist d;
  rc = sm_client_distance(c, x, y, &o, &d, NULL, &e);
  CHECK(rc == SM_CLIENT_ESTATUS && e.status == SM_ST_NOT_FOUND && e.detail == 1 && strstr(e.msg, "y is not stored"));
  CHECK(sm_client_is_open(c));
  sm_client_match_opts_default(&o);
  o.multi_start = 0;
  double t = 0;
  CHECK(sm_client_distance(c, x, y, &o, &d, &t, &e) == 0 && d.total == 0.5 && d.spectrum_elastic == 0.2 && t == 1e-3);

  sm_client_hit *h = NULL;
  uint32_t nh = 0, nc = 0;
  CHECK(sm_client_query(c, x, 0, 0, NULL, 0, 0, &h, &nh, &nc, &e) == SM_CLIENT_EINVAL);
  rc = sm_client_query(c, x, 2, SM_QUERY_SPECTRAL, NULL, 0, 0, &h, &nh, &nc, &e);
  CHECK(rc == 0 && nh == 2 && nc == 7 && h[0].id[0] == 3 && h[1].distance == 0.2);
  free(h);

  sm_proto_has_resp hr;
  CHECK(sm_client_has(c, y, &hr, &e) == 0 && hr.flags == 3 && hr.n_vertices == 10);
  sm_proto_prepare_resp pp;
  CHECK(sm_client_prepare(c, y, 50, 60, 1e-3, &pp, &e) == 0 && (pp.flags & SM_PREP_R_CACHED) && pp.k_elastic == 60);
  CHECK(sm_client_drop(c, y, &e) == 0);

  rc = sm_client_ping(c, NULL, &e);
  CHECK(rc == SM_CLIENT_ESTATUS && e.status == SM_ST_PROTOCOL_ERROR && !sm_client_is_open(c));
  CHECK(sm_client_ping(c, NULL, &e) == SM_CLIENT_ECLOSED);
  sm_client_close(c);
}

/* ---- case: batch window, out-of-order answers, BUSY retry, item failure ---- */
typedef struct bseen {
  size_t order[8], n;
  int code[8], attempts[8];
  double total[8];
} bseen;

static int batch_cb(void *ud, size_t i, const sm_client_req *req, const sm_client_resp *r) {
  bseen *s = ud;
  (void)req;
  s->order[s->n++] = i;
  s->code[i] = r->code;
  s->attempts[i] = r->attempts;
  s->total[i] = r->code ? -1 : r->dist.total;
  return 0;
}

static void srv_batch(peer *p, void *ud) {
  (void)ud;
  sm_proto_frame f[8];
  uint32_t rid[8];
  srv_hello(p, 3); /* the server's max_inflight caps the client's window of 5 */
  for (int i = 0; i < 3; i++) {
    REQUIRE(expect(p, SM_OP_DISTANCE, &f[i]));
    CHECK(f[i].body[0] == i); /* x[0] = item index: sent in order */
    rid[i] = f[i].h.request_id;
    CHECK(i == 0 || rid[i] != rid[i - 1]);
  }
  sm_proto_frame extra;
  CHECK(peer_frame(p, &extra, 200) == 1); /* window full: nothing more */
  /* answer the third first */
  sm_proto_distance_resp dr = {{0.2, 0, 0, 0, 0}, 0};
  sm_proto_header h = resp_hdr(rid[2]);
  SEND(p, sm_proto_enc_distance_resp(g_out, sizeof g_out, &h, &dr));
  REQUIRE(expect(p, SM_OP_DISTANCE, &f[3]));
  CHECK(f[3].body[0] == 3);
  uint32_t r3 = f[3].h.request_id;
  send_error(p, SM_OP_DISTANCE, rid[0], SM_ST_BUSY, 0, 30, "queue full"); /* item 0 retried */
  REQUIRE(expect(p, SM_OP_DISTANCE, &f[4]));
  CHECK(f[4].body[0] == 4); /* the slot goes to item 4; item 0 waits its 30 ms */
  uint32_t r4 = f[4].h.request_id;
  CHECK(peer_frame(p, &extra, 200) == 1);
  h = resp_hdr(rid[1]);
  dr.dist.total = 0.1;
  SEND(p, sm_proto_enc_distance_resp(g_out, sizeof g_out, &h, &dr));
  REQUIRE(expect(p, SM_OP_DISTANCE, &f[5]));
  CHECK(f[5].body[0] == 0 && f[5].h.request_id != rid[0]); /* the retry, a new id */
  uint32_t r0b = f[5].h.request_id;
  send_error(p, SM_OP_DISTANCE, r3, SM_ST_INTERNAL, 0, 0, "eigensolver failed");
  dr.dist.total = 0.4;
  h = resp_hdr(r4);
  SEND(p, sm_proto_enc_distance_resp(g_out, sizeof g_out, &h, &dr));
  dr.dist.total = 0.0;
  h = resp_hdr(r0b);
  SEND(p, sm_proto_enc_distance_resp(g_out, sizeof g_out, &h, &dr));

  /* second batch: the callback stops after the first answer; the other is cancelled.
   * (A frame's view lives until the next peer_frame: keep what is needed at once.) */
  REQUIRE(expect(p, SM_OP_DISTANCE, &f[0]));
  CHECK(f[0].body[0] == 0);
  uint32_t a = f[0].h.request_id;
  REQUIRE(expect(p, SM_OP_DISTANCE, &f[1]));
  CHECK(f[1].body[0] == 1);
  uint32_t b = f[1].h.request_id;
  dr.dist.total = 0.0;
  h = resp_hdr(a);
  SEND(p, sm_proto_enc_distance_resp(g_out, sizeof g_out, &h, &dr));
  sm_proto_cancel_req cq;
  REQUIRE(expect(p, SM_OP_CANCEL, &f[2]));
  REQUIRE(sm_proto_dec_cancel_req(f[2].body, f[2].body_len, &cq) == 0);
  CHECK(cq.target == b);
  h = resp_hdr(f[2].h.request_id);
  h.opcode = SM_OP_CANCEL;
  h.flags = SM_PROTO_F_RESPONSE;
  SEND(p, sm_proto_enc_empty(g_out, sizeof g_out, &h));
  send_error(p, SM_OP_DISTANCE, b, SM_ST_CANCELLED, 0, 0, "cancelled");
  /* item 2 is never sent; the next request is a PING */
  sm_proto_ping ping;
  REQUIRE(expect(p, SM_OP_PING, &f[3]));
  REQUIRE(sm_proto_dec_ping(f[3].body, f[3].body_len, &ping) == 0);
  h = resp_hdr(f[3].h.request_id);
  SEND(p, sm_proto_enc_ping(g_out, sizeof g_out, &h, 1, &ping));
  CHECK(peer_frame(p, &f[4], 5000) == 2);
}

static int stop_cb(void *ud, size_t i, const sm_client_req *req, const sm_client_resp *r) {
  batch_cb(ud, i, req, r);
  return 1;
}

static void cli_batch(int fd, void *ud) {
  (void)ud;
  sm_client *c = connect_fd(fd, 0);
  REQUIRE(c);
  sm_client_req q[5];
  memset(q, 0, sizeof q);
  for (int i = 0; i < 5; i++) {
    q[i].op = SM_OP_DISTANCE;
    q[i].x[0] = (uint8_t)i;
    q[i].y[0] = 9;
  }
  bseen s;
  memset(&s, 0, sizeof s);
  size_t nf = 0;
  sm_client_error e;
  int rc = sm_client_batch(c, q, 5, 5, 3, batch_cb, &s, &nf, &e);
  CHECK_MSG(rc == 0, "batch: %d %s", rc, e.msg);
  CHECK(s.n == 5 && nf == 1);
  size_t want[5] = {2, 1, 3, 4, 0};
  for (int i = 0; i < 5; i++) CHECK_MSG(s.order[i] == want[i], "completion %d: item %zu", i, s.order[i]);
  CHECK(s.code[3] == SM_CLIENT_ESTATUS && s.code[0] == 0 && s.attempts[0] == 2 && s.attempts[1] == 1);
  CHECK(s.total[2] == 0.2 && s.total[4] == 0.4);

  memset(&s, 0, sizeof s);
  rc = sm_client_batch(c, q, 3, 2, 0, stop_cb, &s, &nf, &e);
  CHECK(rc == SM_CLIENT_ECANCELED);
  CHECK(s.n == 2 && s.order[0] == 0 && s.order[1] == 1 && s.code[1] == SM_CLIENT_ESTATUS && nf == 1);
  CHECK(sm_client_ping(c, NULL, &e) == 0); /* still in step */
  sm_client_close(c);
}

/* ---- case: version 2: MATCH's confidence, single and batched; one outside [0, 1] is a
 * malformed answer that closes the connection ---- */
static void srv_match_resp_v2(peer *p, const sm_proto_frame *f, double confidence) {
  sm_proto_match_req m;
  REQUIRE(sm_proto_dec_match_req(SM_OP_MATCH, f->body, f->body_len, &m) == 0);
  int32_t xy[2] = {1, 0};
  sm_proto_match_resp r;
  memset(&r, 0, sizeof r);
  r.init_used = 2;
  r.orientation = 0.75;
  r.confidence = confidence;
  r.map_xy = (sm_proto_i32s){xy, NULL, 2};
  sm_proto_header h = resp_hdr(f->h.request_id);
  h.version = 2;
  SEND(p, sm_proto_enc_match_resp(g_out, sizeof g_out, &h, 2, &r));
}

static void srv_v2(peer *p, void *ud) {
  (void)ud;
  sm_proto_frame f;
  srv_hello_v(p, 4, 2);
  REQUIRE(expect(p, SM_OP_MATCH, &f));
  CHECK(f.h.version == 2); /* every frame after HELLO carries the negotiated version */
  srv_match_resp_v2(p, &f, 0.8125);
  REQUIRE(expect(p, SM_OP_MATCH, &f)); /* the batch of one */
  CHECK(f.h.version == 2);
  srv_match_resp_v2(p, &f, 1.0);
  /* a confidence of 1.5: written over a valid answer, since the encoder refuses it */
  REQUIRE(expect(p, SM_OP_MATCH, &f));
  int32_t xy[2] = {1, 0};
  sm_proto_match_resp r;
  memset(&r, 0, sizeof r);
  r.init_used = 2;
  r.confidence = 0.5;
  r.map_xy = (sm_proto_i32s){xy, NULL, 2};
  sm_proto_header h = resp_hdr(f.h.request_id);
  h.version = 2;
  ptrdiff_t n = sm_proto_enc_match_resp(g_out, sizeof g_out, &h, 2, &r);
  REQUIRE(n == 24 + 112 + 8 + 8);
  double bad = 1.5;
  uint64_t u;
  memcpy(&u, &bad, 8);
  for (int i = 0; i < 8; i++) g_out[n - 8 + i] = (uint8_t)(u >> (8 * i));
  peer_send(p, g_out, n);
  CHECK(peer_frame(p, &f, 5000) == 2); /* the client hangs up */
}

static int v2_cb(void *ud, size_t i, const sm_client_req *req, const sm_client_resp *r) {
  (void)i;
  (void)req;
  double *got = ud;
  *got = !r->code && r->match.has_confidence ? r->match.confidence : -1;
  return 0;
}

static void cli_v2(int fd, void *ud) {
  (void)ud;
  sm_client *c = connect_fd(fd, 0);
  REQUIRE(c);
  CHECK(sm_client_limits(c)->version == 2);
  sm_client_error e;
  uint8_t x[32] = {1}, y[32] = {2};
  sm_client_match_result r;
  int rc = sm_client_match(c, x, y, NULL, &r, &e);
  CHECK_MSG(rc == 0, "match: %s", e.msg);
  if (!rc) CHECK(r.has_confidence && r.confidence == 0.8125 && r.orientation == 0.75 && r.nx == 2);
  sm_client_match_result_free(&r);
  sm_client_req q;
  memset(&q, 0, sizeof q);
  q.op = SM_OP_MATCH;
  q.x[0] = 1;
  q.y[0] = 2;
  double got = -2;
  size_t nf = 9;
  rc = sm_client_batch(c, &q, 1, 1, 0, v2_cb, &got, &nf, &e);
  CHECK_MSG(rc == 0 && nf == 0 && got == 1.0, "batch: %d %s, confidence %g", rc, e.msg, got);
  rc = sm_client_match(c, x, y, NULL, &r, &e);
  CHECK_MSG(rc == SM_CLIENT_EPROTO && strstr(e.msg, "confidence"), "bad confidence: %d %s", rc, e.msg);
  CHECK(!sm_client_is_open(c));
  sm_client_close(c);
}

/* ---- case: a server that sends garbage, one that does not answer ---- */
static void srv_garbage(peer *p, void *ud) {
  sm_proto_frame f;
  srv_hello(p, 4);
  REQUIRE(expect(p, SM_OP_PING, &f));
  if (*(int *)ud == 0) peer_send(p, (const uint8_t *)"HTTP/1.1 400 Bad\r\n\r\n", 20);
  CHECK(peer_frame(p, &f, 5000) == 2);
}

static void cli_garbage(int fd, void *ud) {
  sm_client *c = connect_fd(fd, *(int *)ud ? 300 : 0);
  REQUIRE(c);
  sm_client_error e;
  int rc = sm_client_ping(c, NULL, &e);
  CHECK_MSG(rc == (*(int *)ud ? SM_CLIENT_ETIMEOUT : SM_CLIENT_EPROTO), "rc=%d %s", rc, e.msg);
  CHECK(!sm_client_is_open(c));
  sm_client_close(c);
}

/* ---- case: queued requests are not dead connections (io_timeout 300 ms): the client
 * probes with PING after 300 ms of silence and keeps waiting while probes are answered
 * (a PUT answered after two probes, a pipelined PUT batch with a BUSY retry); an
 * unanswered probe ends the wait with ETIMEOUT and closes the connection ---- */
static void put_ok(peer *p, const sm_proto_frame *f) {
  sm_proto_put_req q;
  REQUIRE(sm_proto_dec_put_req(f->body, f->body_len, &q) == 0);
  sm_proto_put_resp r = {{0}, 3, 1, 0};
  memcpy(r.id, q.id, 32);
  sm_proto_header h = resp_hdr(f->h.request_id);
  SEND(p, sm_proto_enc_put_resp(g_out, sizeof g_out, &h, &r));
}

static void answer_ping(peer *p, const sm_proto_frame *f) {
  sm_proto_ping q;
  REQUIRE(sm_proto_dec_ping(f->body, f->body_len, &q) == 0);
  sm_proto_header h = resp_hdr(f->h.request_id);
  SEND(p, sm_proto_enc_ping(g_out, sizeof g_out, &h, 1, &q));
}

static void srv_queued(peer *p, void *ud) {
  (void)ud;
  sm_proto_frame f, put1, put2;
  srv_hello(p, 4);
  /* 1. a single PUT, answered after two liveness probes */
  REQUIRE(expect(p, SM_OP_PUT_SHAPE, &f));
  uint8_t *save = malloc(f.body_len + SM_PROTO_HEADER_LEN);
  REQUIRE(save);
  sm_proto_frame keep = f;
  memcpy(save, f.body, f.body_len);
  keep.body = save;
  for (int i = 0; i < 2; i++) {
    REQUIRE(expect(p, SM_OP_PING, &f));
    answer_ping(p, &f);
  }
  put_ok(p, &keep);
  free(save);
  /* 2. a batch of two PUTs: a probe, BUSY for the first, then both answered */
  REQUIRE(expect(p, SM_OP_PUT_SHAPE, &put1));
  uint8_t *b1 = malloc(put1.body_len);
  REQUIRE(b1);
  memcpy(b1, put1.body, put1.body_len);
  put1.body = b1;
  REQUIRE(expect(p, SM_OP_PUT_SHAPE, &put2));
  uint8_t *b2 = malloc(put2.body_len);
  REQUIRE(b2);
  memcpy(b2, put2.body, put2.body_len);
  put2.body = b2;
  REQUIRE(expect(p, SM_OP_PING, &f));
  answer_ping(p, &f);
  send_error(p, SM_OP_PUT_SHAPE, put1.h.request_id, SM_ST_BUSY, 0, 10, "queue full");
  REQUIRE(expect(p, SM_OP_PUT_SHAPE, &f)); /* the retry */
  put_ok(p, &f);
  put_ok(p, &put2);
  free(b1);
  free(b2);
  /* 3. a PREPARE whose probe is never answered */
  REQUIRE(expect(p, SM_OP_PREPARE, &f));
  REQUIRE(expect(p, SM_OP_PING, &f));
  CHECK(peer_frame(p, &f, 5000) == 2); /* the client gives up and closes */
}

static int queued_cb(void *ud, size_t i, const sm_client_req *req, const sm_client_resp *r) {
  (void)req;
  int *res = ud;
  res[i] = r->code ? -1 : r->attempts;
  return 0;
}

static void cli_queued(int fd, void *ud) {
  (void)ud;
  sm_client *c = connect_fd(fd, 300);
  REQUIRE(c);
  sm_client_error e;
  static const uint8_t d1[] = "draco-one", d2[] = "draco-two";
  uint8_t id[32], want[32];
  sm_client_shape_id(d1, sizeof d1, want);
  int rc = sm_client_put(c, d1, sizeof d1, 1, id, NULL, &e);
  CHECK_MSG(rc == 0, "queued put: %d %s", rc, e.msg);
  CHECK(!memcmp(id, want, 32));
  sm_client_req q[2];
  memset(q, 0, sizeof q);
  q[0].op = q[1].op = SM_OP_PUT_SHAPE;
  q[0].draco = d1;
  q[0].draco_len = sizeof d1;
  q[1].draco = d2;
  q[1].draco_len = sizeof d2;
  q[1].prepare = 1;
  int res[2] = {0, 0};
  size_t nf = 9;
  rc = sm_client_batch(c, q, 2, 2, -1, queued_cb, res, &nf, &e);
  CHECK_MSG(rc == 0 && nf == 0, "queued batch: %d %s", rc, e.msg);
  CHECK_MSG(res[0] == 2 && res[1] == 1, "attempts %d %d", res[0], res[1]);
  uint8_t x[32] = {1};
  rc = sm_client_prepare(c, x, 0, 0, 0, NULL, &e);
  CHECK_MSG(rc == SM_CLIENT_ETIMEOUT && strstr(e.msg, "PING"), "dead server: %d %s", rc, e.msg);
  CHECK(!sm_client_is_open(c));
  sm_client_close(c);
}

/* ---- case: lost connections (sm_client.h, "Lost connections"). The peer listens on a Unix
 * socket, so the client can connect again: a batch whose connection dies keeps every answer
 * it got and resends only what was cut; a graceful GOAWAY moves the rest to a new
 * connection; a single call is resent; an item that brings every connection down fails
 * after SM_CLIENT_MAX_LOSSES; a later call connects again by itself. ---- */
static int accept_peer(int lfd, peer *p) {
  struct pollfd pf = {lfd, POLLIN, 0};
  if (poll(&pf, 1, 5000) != 1) {
    CHECK_MSG(0, "%s", "the client did not connect again");
    return 0;
  }
  p->fd = accept(lfd, NULL, NULL);
  p->len = p->used = 0;
  REQUIRE(p->fd >= 0);
  srv_hello(p, 8);
  return 1;
}

static void answer_dist(peer *p, uint32_t rid, double total) {
  sm_proto_distance_resp dr = {{total, 0, 0, 0, 0}, 0};
  sm_proto_header h = resp_hdr(rid);
  SEND(p, sm_proto_enc_distance_resp(g_out, sizeof g_out, &h, &dr));
}

/* Expects DISTANCE requests for items want[0..n) in that order (item = x[0]); rid[item]. */
static void expect_items(peer *p, const int *want, int n, uint32_t *rid) {
  for (int k = 0; k < n; k++) {
    sm_proto_frame f;
    if (!expect(p, SM_OP_DISTANCE, &f)) exit(1);
    CHECK_MSG(f.body[0] == want[k], "request %d: item %d, expected %d", k, f.body[0], want[k]);
    rid[f.body[0]] = f.h.request_id;
  }
}

static void srv_reconnect(int lfd) {
  peer p = {-1, NULL, 0, 0, 0};
  uint32_t rid[16];
  sm_proto_frame f;
  /* connection 1: items 0..3 fill the window; 1 and 3 are answered, 4 and 5 take their
   * places; then the daemon dies with 0, 2, 4, 5 in flight */
  if (!accept_peer(lfd, &p)) exit(1);
  expect_items(&p, (int[]){0, 1, 2, 3}, 4, rid);
  answer_dist(&p, rid[1], 0.1);
  answer_dist(&p, rid[3], 0.3);
  expect_items(&p, (int[]){4, 5}, 2, rid);
  close(p.fd);
  /* connection 2: the cut items, nothing else; then a graceful GOAWAY: 0 and 2 answered,
   * 4 refused SHUTTING_DOWN (not run), 5 answered; no new request on this connection */
  if (!accept_peer(lfd, &p)) exit(1);
  expect_items(&p, (int[]){0, 2, 4, 5}, 4, rid);
  send_error(&p, SM_OP_GOAWAY, 0, SM_ST_OK, 5000, 20, "draining");
  answer_dist(&p, rid[0], 0.0);
  answer_dist(&p, rid[2], 0.2);
  send_error(&p, SM_OP_DISTANCE, rid[4], SM_ST_SHUTTING_DOWN, 0, 0, "shutting down");
  answer_dist(&p, rid[5], 0.5);
  CHECK(peer_frame(&p, &f, 5000) == 2); /* the client leaves the drained connection */
  close(p.fd);
  /* connection 3: 4 again, and 6, 7 */
  if (!accept_peer(lfd, &p)) exit(1);
  expect_items(&p, (int[]){4, 6, 7}, 3, rid);
  answer_dist(&p, rid[4], 0.4);
  answer_dist(&p, rid[7], 0.7);
  answer_dist(&p, rid[6], 0.6);
  /* a single DISTANCE, cut once */
  expect_items(&p, (int[]){9}, 1, rid);
  close(p.fd);
  if (!accept_peer(lfd, &p)) exit(1);
  expect_items(&p, (int[]){9}, 1, rid);
  answer_dist(&p, rid[9], 0.9);
  /* a batch of one item that every connection dies of: sent on 3 connections, then it
   * fails and no fourth connection is made for it */
  for (int t = 0; t < SM_CLIENT_MAX_LOSSES; t++) {
    if (t && !accept_peer(lfd, &p)) exit(1);
    expect_items(&p, (int[]){10}, 1, rid);
    close(p.fd);
  }
  /* the next call connects again by itself */
  if (!accept_peer(lfd, &p)) exit(1);
  sm_proto_ping ping;
  REQUIRE(expect(&p, SM_OP_PING, &f));
  REQUIRE(sm_proto_dec_ping(f.body, f.body_len, &ping) == 0);
  sm_proto_header h = resp_hdr(f.h.request_id);
  SEND(&p, sm_proto_enc_ping(g_out, sizeof g_out, &h, 1, &ping));
  CHECK(peer_frame(&p, &f, 5000) == 2);
  close(p.fd);
  struct pollfd pf = {lfd, POLLIN, 0};
  CHECK_MSG(poll(&pf, 1, 100) == 0, "%s", "a connection nobody needed");
  free(p.buf);
}

static void cli_reconnect(const char *addr) {
  sm_client_opts o;
  sm_client_error e;
  sm_client *c = NULL;
  sm_client_opts_default(&o);
  o.io_timeout_ms = 5000;
  o.reconnect_tries = 3;
  o.reconnect_backoff_ms = 10;
  int rc = sm_client_connect(addr, &o, &c, &e);
  REQUIRE(rc == 0);
  sm_client_req q[8];
  memset(q, 0, sizeof q);
  for (int i = 0; i < 8; i++) {
    q[i].op = SM_OP_DISTANCE;
    q[i].x[0] = (uint8_t)i;
  }
  bseen s;
  memset(&s, 0, sizeof s);
  for (int i = 0; i < 8; i++) s.total[i] = -2;
  size_t nf = 9;
  rc = sm_client_batch(c, q, 8, 4, 0, batch_cb, &s, &nf, &e);
  CHECK_MSG(rc == 0 && nf == 0 && s.n == 8, "batch over lost connections: %d %s, %zu failed, %zu answers",
            rc, e.msg, nf, s.n);
  int seen[8] = {0};
  for (size_t k = 0; k < s.n && k < 8; k++) seen[s.order[k]]++;
  for (int i = 0; i < 8; i++) {
    CHECK_MSG(seen[i] == 1 && s.code[i] == 0 && s.total[i] == i / 10.0, "item %d: %d answers, code %d, %g",
              i, seen[i], s.code[i], s.total[i]);
  }
  CHECK_MSG(s.attempts[1] == 1 && s.attempts[3] == 1 && s.attempts[0] == 2 && s.attempts[5] == 2 &&
            s.attempts[4] == 3 && s.attempts[6] == 1, "attempts %d %d %d %d %d %d", s.attempts[0],
            s.attempts[1], s.attempts[3], s.attempts[4], s.attempts[5], s.attempts[6]);
  CHECK(sm_client_reconnects(c) == 2);
  uint8_t x[32] = {9}, y[32] = {0};
  sm_proto_dist d;
  rc = sm_client_distance(c, x, y, NULL, &d, NULL, &e);
  CHECK_MSG(rc == 0 && d.total == 0.9 && sm_client_reconnects(c) == 3, "single call: %d %s", rc, e.msg);
  memset(&s, 0, sizeof s);
  q[0].x[0] = 10;
  rc = sm_client_batch(c, q, 1, 1, 0, batch_cb, &s, &nf, &e);
  CHECK_MSG(rc == 0 && nf == 1 && s.n == 1 && s.code[0] == SM_CLIENT_ECLOSED && s.attempts[0] == SM_CLIENT_MAX_LOSSES,
            "an item every connection dies of: %d, %zu failed, code %d, %d sends", rc, nf, s.code[0], s.attempts[0]);
  CHECK(sm_client_reconnects(c) == 5 && !sm_client_is_open(c));
  CHECK(sm_client_ping(c, NULL, &e) == 0 && sm_client_reconnects(c) == 6);
  sm_client_close(c);
  /* without an address there is nothing to connect to */
  int sv[2];
  REQUIRE(socketpair(AF_UNIX, SOCK_STREAM, 0, sv) == 0);
  close(sv[1]);
  CHECK(sm_client_connect_fd(sv[0], &o, &c, &e) != 0);
}

static void test_reconnect(void) {
  char path[108];
  snprintf(path, sizeof path, "%s/recon_%ld.sock", SM_TEST_TMP, (long)getpid());
  if (strlen(path) >= sizeof(((struct sockaddr_un *)0)->sun_path))
    snprintf(path, sizeof path, "/tmp/sm_recon_%ld.sock", (long)getpid());
  unlink(path);
  int lfd = socket(AF_UNIX, SOCK_STREAM, 0);
  struct sockaddr_un su;
  memset(&su, 0, sizeof su);
  su.sun_family = AF_UNIX;
  memcpy(su.sun_path, path, strlen(path) + 1);
  REQUIRE(lfd >= 0 && bind(lfd, (struct sockaddr *)&su, sizeof su) == 0 && listen(lfd, 8) == 0);
  fflush(NULL);
  pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    sm_test_failures = 0;
    srv_reconnect(lfd);
    _exit(sm_test_failures ? 1 : 0);
  }
  close(lfd);
  char addr[128];
  snprintf(addr, sizeof addr, "unix:%s", path);
  cli_reconnect(addr);
  int st = 0;
  REQUIRE(waitpid(pid, &st, 0) == pid);
  CHECK_MSG(WIFEXITED(st) && WEXITSTATUS(st) == 0, "reconnect: the scripted server saw failures (status %d)", st);
  unlink(path);
}

/* ------------------------------------------------------------------ part 3: daemon */
#if defined(SM_SERVER_BIN) && defined(SM_CLI_BIN)

static int run(const char *cmd) {
  fflush(NULL);
  int st = system(cmd);
  return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

static char *slurp(const char *path, size_t *n) {
  uint8_t *b = NULL;
  size_t len = 0;
  if (sm_read_file_bytes(path, 1 << 28, &b, &len, NULL)) return NULL;
  char *s = realloc(b, len + 1);
  if (!s) {
    free(b);
    return NULL;
  }
  s[len] = 0;
  if (n) *n = len;
  return s;
}

/* The number after "confidence": in a JSON text: 1 and *v, or 0 (absent, null, not a number). */
static int json_confidence(const char *s, double *v) {
  const char *k = s ? strstr(s, "\"confidence\":") : NULL;
  if (!k) return 0;
  k += strlen("\"confidence\":");
  char *end;
  *v = strtod(k, &end);
  return end != k;
}

/* The daemon's counter `name` (shapematch stats), or -1. */
static long long daemon_stat(const char *dir, const char *cli, const char *srv, const char *name) {
  char cmd[2048], path[700];
  snprintf(cmd, sizeof cmd, "%s stats --server %s > %s/stat_now.txt 2>/dev/null", cli, srv, dir);
  if (run(cmd)) return -1;
  snprintf(path, sizeof path, "%s/stat_now.txt", dir);
  char *s = slurp(path, NULL);
  long long v = -1;
  for (char *l = s; l && *l; l = strchr(l, '\n') ? strchr(l, '\n') + 1 : NULL) {
    char k[64];
    long long x;
    if (sscanf(l, "%63s %lld", k, &x) == 2 && !strcmp(k, name)) v = x;
  }
  free(s);
  return v;
}

/* MATCH through the multi-resolution path on the daemon (started with a coarse level of
 * 600 vertices): twice, the second served from the cached coarse levels (STATS: nothing
 * computed or loaded, two cache hits), both maps equal to the local multi-resolution map
 * with the same coarse size; the coarse bases are on disk under names carrying the
 * decimation parameters. 2,562-vertex blobs, so that 600 is a real decimation. */
static void test_daemon_multires(const char *dir, const char *cli, const char *srv) {
  char cmd[4096];
  snprintf(cmd, sizeof cmd,
           "cd %s && %s synth blob --subdiv 4 --seed 5 -o ma.off 2>/dev/null && "
           "%s synth blob --subdiv 4 --seed 6 --stretch 1.2,1,0.9 -o mb.off 2>/dev/null && "
           "%s encode ma.off -o ma.drc 2>/dev/null && %s encode mb.off -o mb.drc 2>/dev/null",
           dir, cli, cli, cli, cli);
  REQUIRE(run(cmd) == 0);
  long long c0 = daemon_stat(dir, cli, srv, "bases_computed");
  long long h[3], m[3], b[3];
  for (int k = 0; k < 2; k++) {
    h[k] = daemon_stat(dir, cli, srv, "cache_hits");
    m[k] = daemon_stat(dir, cli, srv, "cache_misses");
    b[k] = daemon_stat(dir, cli, srv, "bases_computed") + daemon_stat(dir, cli, srv, "bases_loaded");
    snprintf(cmd, sizeof cmd, "cd %s && %s match ma.drc mb.drc --server %s --multires on -o mr_remote%d.txt "
             "2> mr_remote%d.err", dir, cli, srv, k, k);
    int rc = run(cmd);
    CHECK_MSG(rc == 0, "multires match %d on the daemon: exit %d", k, rc);
  }
  h[2] = daemon_stat(dir, cli, srv, "cache_hits");
  m[2] = daemon_stat(dir, cli, srv, "cache_misses");
  b[2] = daemon_stat(dir, cli, srv, "bases_computed") + daemon_stat(dir, cli, srv, "bases_loaded");
  CHECK_MSG(m[1] - m[0] == 2 && b[1] - b[0] == 4, "first multires MATCH: %lld misses, %lld bases "
            "computed or loaded (want 2 and 4)", m[1] - m[0], b[1] - b[0]);
  CHECK_MSG(h[2] - h[1] == 2 && m[2] == m[1] && b[2] == b[1], "second multires MATCH: %lld hits, "
            "%lld misses, %lld bases (want 2, 0, 0)", h[2] - h[1], m[2] - m[1], b[2] - b[1]);
  CHECK_MSG(daemon_stat(dir, cli, srv, "bases_computed") - c0 == 4, "%s", "coarse bases computed once");
  snprintf(cmd, sizeof cmd, "cd %s && %s match ma.drc mb.drc --local --multires on --coarse-nv 600 "
           "-o mr_local.txt 2> mr_local.err", dir, cli);
  CHECK(run(cmd) == 0);
  char p[3][700];
  char *t[3];
  for (int k = 0; k < 3; k++) {
    snprintf(p[k], sizeof p[k], k < 2 ? "%s/mr_remote%d.txt" : "%s/mr_local.txt", dir, k);
    t[k] = slurp(p[k], NULL);
  }
  CHECK(t[0] && t[1] && t[2]);
  if (t[0] && t[1] && t[2]) {
    size_t lines = 0;
    for (const char *c = t[2]; *c; c++) lines += *c == '\n';
    CHECK_MSG(lines == 2562, "local multires map: %zu lines", lines);
    CHECK_MSG(!strcmp(t[0], t[2]), "%s", "the daemon's multires map differs from the local one");
    CHECK_MSG(!strcmp(t[1], t[2]), "%s", "the cached multires map differs from the local one");
  }
  for (int k = 0; k < 3; k++) free(t[k]);
  snprintf(cmd, sizeof cmd, "test $(ls %s/data/bases | grep -c '\\.mr600\\.a[0-9a-f]*\\.') = 4", dir);
  CHECK_MSG(run(cmd) == 0, "%s", "the 4 coarse bases on disk, named by their decimation parameters");
  fprintf(stderr, "daemon multires MATCH: computed once (4 coarse bases), then 2 cache hits; map = local --multires on\n");
}

static void test_daemon(void) {
  char dir[512], cmd[4096], log[600];
  snprintf(dir, sizeof dir, "%s/client_it_XXXXXX", SM_TEST_TMP);
  if (!mkdtemp(dir)) {
    fprintf(stderr, "SKIP daemon section: mkdtemp failed\n");
    return;
  }
  snprintf(log, sizeof log, "%s/daemon.log", dir);
  char data[600];
  snprintf(data, sizeof data, "%s/data", dir);
  mkdir(data, 0700);
  fflush(NULL);
  pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    int fd = open(log, O_WRONLY | O_CREAT | O_TRUNC, 0600);
    if (fd >= 0) dup2(fd, 2);
    /* PUT's background preparation off: the multires checks count every basis */
    execl(SM_SERVER_BIN, SM_SERVER_BIN, "--port", "0", "--data-dir", data, "--multires-coarse-nv",
          "600", "--prepare-on-put", "0", (char *)NULL);
    _exit(127);
  }
  int port = 0, exited = 0;
  for (int t = 0; t < 300 && !port && !exited; t++) { /* 30 s */
    struct timespec ts = {0, 100000000L};
    nanosleep(&ts, NULL);
    char *s = slurp(log, NULL);
    const char *l = s ? strstr(s, "msg=listening") : NULL;
    const char *pp = l ? strstr(l, "port=") : NULL;
    if (pp) port = atoi(pp + 5);
    free(s);
    int st;
    if (waitpid(pid, &st, WNOHANG) == pid) exited = 1;
  }
  if (!port) {
    fprintf(stderr, "SKIP daemon section: %s did not report 'msg=listening port=N' (%s)\n",
            SM_SERVER_BIN, exited ? "it exited" : "timeout");
    if (!exited) {
      kill(pid, SIGKILL);
      waitpid(pid, NULL, 0);
    }
    return;
  }
  fprintf(stderr, "daemon on port %d\n", port);
  char srv[64];
  snprintf(srv, sizeof srv, "127.0.0.1:%d", port);
  const char *cli = SM_CLI_BIN;
  /* two shapes of our own; the .drc copies make the local run read exactly the floats the
   * server decodes */
  snprintf(cmd, sizeof cmd,
           "cd %s && %s synth blob --subdiv 3 --seed 3 -o a.off 2>/dev/null && "
           "%s synth blob --subdiv 3 --seed 4 --stretch 1.3,1,0.8 -o b.off 2>/dev/null && "
           "%s encode a.off -o a.drc 2>/dev/null && %s encode b.off -o b.drc 2>/dev/null",
           dir, cli, cli, cli, cli);
  REQUIRE(run(cmd) == 0);

  snprintf(cmd, sizeof cmd, "cd %s && %s put a.drc b.off --server %s > put.txt 2>put.err", dir, cli, srv);
  int rc = run(cmd);
  CHECK_MSG(rc == 0, "put exit %d", rc);
  char path[700];
  snprintf(path, sizeof path, "%s/put.txt", dir);
  char *put = slurp(path, NULL);
  snprintf(path, sizeof path, "%s/a.drc", dir);
  size_t alen;
  char *abytes = slurp(path, &alen);
  if (put && abytes) {
    uint8_t id[32];
    char hex[65];
    sm_sha256(abytes, alen, id);
    sm_client_id_to_hex(id, hex);
    CHECK_MSG(!strncmp(put, hex, 64) && strstr(put, "  a.drc\n") && strstr(put, "  b.off\n"), "put printed: %s", put);
  }
  free(put);
  free(abytes);

  /* A file the CLI cannot encode (NaN coordinate): one clear line, nothing said twice. */
  snprintf(cmd, sizeof cmd,
           "cd %s && printf 'OFF\\n3 1 0\\n0 0 0\\n1 0 nan\\n0 1 0\\n3 0 1 2\\n' > nan.off && "
           "%s put nan.off --server %s 2> nan.err", dir, cli, srv);
  CHECK(run(cmd) != 0);
  {
    snprintf(path, sizeof path, "%s/nan.err", dir);
    char *ne = slurp(path, NULL), *first;
    CHECK_MSG(ne && (first = strstr(ne, "nan.off")) && !strstr(first + 7, "nan.off") &&
                  (first = strstr(ne, "draco encode")) && !strstr(first + 12, "draco encode") &&
                  strstr(ne, "not a finite float"),
              "put nan.off stderr: %s", ne ? ne : "");
    free(ne);
  }

  /* match: the same map as the local computation on the same floats. The CLI uploads a.off
   * Draco-encoded (float32 coordinates, same bytes as `encode a.off -o a.drc`), so the
   * server's map of the OFF pair must equal the local map of the .drc pair; the local map
   * of the OFF pair (double coordinates) may differ where the match is ill-conditioned. */
  const char *pairs[2][2] = {{"a.drc", "b.drc"}, {"a.off", "b.off"}};
  for (int k = 0; k < 2; k++) {
    snprintf(cmd, sizeof cmd, "cd %s && %s match %s %s --server %s -o remote%d.txt --json > remote%d.json 2>match.err",
             dir, cli, pairs[k][0], pairs[k][1], srv, k, k);
    rc = run(cmd);
    CHECK_MSG(rc == 0, "remote match %s %s: exit %d", pairs[k][0], pairs[k][1], rc);
    snprintf(cmd, sizeof cmd, "cd %s && %s match %s %s --local -o local%d.txt --json > local%d.json 2>/dev/null",
             dir, cli, pairs[k][0], pairs[k][1], k, k);
    CHECK(run(cmd) == 0);
  }
  /* --json has the map's confidence in [0, 1], from the server (protocol version 2) and
   * locally; the same floats give the same number */
  {
    char pj[700];
    double conf[2] = {-1, -1};
    for (int w = 0; w < 2; w++) {
      snprintf(pj, sizeof pj, "%s/%s0.json", dir, w ? "local" : "remote");
      char *js = slurp(pj, NULL);
      CHECK_MSG(json_confidence(js, &conf[w]) && conf[w] >= 0 && conf[w] <= 1,
                "%s match --json: no confidence in [0, 1]: %s", w ? "local" : "server", js ? js : "");
      free(js);
    }
    CHECK_MSG(fabs(conf[0] - conf[1]) <= 1e-6, "confidence server %g, local %g", conf[0], conf[1]);
    /* the human-readable line has it too */
    snprintf(cmd, sizeof cmd, "cd %s && %s match a.drc b.drc --server %s -o human.txt 2> human.err",
             dir, cli, srv);
    CHECK(run(cmd) == 0);
    snprintf(pj, sizeof pj, "%s/human.err", dir);
    char *he = slurp(pj, NULL);
    CHECK_MSG(he && (strstr(he, ", confidence 0.") || strstr(he, ", confidence 1.000")),
              "match stderr: %s", he ? he : "");
    free(he);
  }
  for (int k = 0; k < 3; k++) {
    char p1[700], p2[700];
    snprintf(p1, sizeof p1, "%s/remote%d.txt", dir, k == 0 ? 0 : 1);
    snprintf(p2, sizeof p2, "%s/local%d.txt", dir, k == 2 ? 1 : 0);
    char *r = slurp(p1, NULL), *l = slurp(p2, NULL);
    CHECK(r && l);
    if (r && l) {
      size_t lines = 0, same = 0;
      const char *x = r, *y = l;
      while (*x && *y) {
        lines++;
        same += atoi(x) == atoi(y);
        x = strchr(x, '\n');
        y = strchr(y, '\n');
        if (!x || !y) break;
        x++;
        y++;
      }
      static const char *const what[3] = {"server a.drc->b.drc vs local a.drc->b.drc",
                                          "server a.off->b.off vs local a.drc->b.drc",
                                          "server a.off->b.off vs local a.off->b.off (doubles)"};
      fprintf(stderr, "%s: %zu of %zu vertices agree\n", what[k], same, lines);
      CHECK(lines == 642);
      if (k < 2) CHECK_MSG(!strcmp(r, l), "%s: maps differ", what[k]);
    }
    free(r);
    free(l);
  }

  /* distance: the same number */
  snprintf(cmd, sizeof cmd, "cd %s && %s distance a.drc b.drc --server %s > dr.txt 2>/dev/null && "
           "%s distance a.drc b.drc --local > dl.txt 2>/dev/null", dir, cli, srv, cli);
  CHECK(run(cmd) == 0);
  char p1[700], p2[700];
  snprintf(p1, sizeof p1, "%s/dr.txt", dir);
  snprintf(p2, sizeof p2, "%s/dl.txt", dir);
  char *dr = slurp(p1, NULL), *dl = slurp(p2, NULL);
  CHECK_MSG(dr && dl && fabs(atof(dr) - atof(dl)) <= 2e-6, "distance remote %s local %s", dr ? dr : "?", dl ? dl : "?");
  free(dr);
  free(dl);

  /* batch: pairs file, JSON lines; a missing file fails alone */
  snprintf(cmd, sizeof cmd, "cd %s && printf 'a.drc b.drc\\nb.off a.off\\na.drc missing.off\\n' > pairs.txt && "
           "%s batch pairs.txt --server %s --inflight 2 > batch.json 2> batch.err", dir, cli, srv);
  rc = run(cmd);
  CHECK_MSG(rc == 1, "batch with a failing item: exit %d", rc);
  snprintf(p1, sizeof p1, "%s/batch.json", dir);
  char *bj = slurp(p1, NULL);
  int ok = 0, bad = 0;
  for (const char *s = bj; s && (s = strstr(s, "\"ok\":")); s += 5) *(s[5] == 't' ? &ok : &bad) += 1;
  CHECK_MSG(ok == 2 && bad == 1, "batch: %d ok, %d failed: %s", ok, bad, bj ? bj : "");
  free(bj);
  /* batch --maps runs MATCH: its lines carry the confidence */
  snprintf(cmd, sizeof cmd, "cd %s && mkdir -p maps && printf 'a.drc b.drc\\n' > pairs3.txt && "
           "%s batch pairs3.txt --server %s --maps maps > batch3.json 2> batch3.err", dir, cli, srv);
  CHECK(run(cmd) == 0);
  snprintf(p1, sizeof p1, "%s/batch3.json", dir);
  bj = slurp(p1, NULL);
  double bconf = -1;
  CHECK_MSG(bj && strstr(bj, "\"ok\":true") && json_confidence(bj, &bconf) && bconf >= 0 && bconf <= 1,
            "batch --maps: %s", bj ? bj : "");
  free(bj);

  /* a busy server: a batch of 42 distances (8 in flight) and a `put --prepare` of 6 new
   * shapes at the same time, both with --io-timeout 0.2: their requests wait in the
   * daemon's queue far longer than 0.2 s, which must not be taken for a dead connection
   * (the client probes with PING and goes on waiting). Every item succeeds; put prints
   * its lines in argument order. */
  snprintf(cmd, sizeof cmd, "cd %s && for i in 0 1 2 3 4 5; do %s synth blob --subdiv 3 --seed $((20 + i)) "
           "--stretch 1.$i,1,0.9 -o c$i.off 2>/dev/null || exit 1; done && : > pairs2.txt && "
           "for i in 0 1 2 3 4 5; do for j in 0 1 2 3 4 5 a b; do [ $i = $j ] || echo \"c$i.off $j\" >> pairs2.txt; done; done && "
           "sed -i 's/ a$/ a.drc/; s/ b$/ b.off/; s/ \\([0-5]\\)$/ c\\1.off/' pairs2.txt", dir, cli);
  REQUIRE(run(cmd) == 0);
  snprintf(cmd, sizeof cmd, "cd %s && (%s batch pairs2.txt --server %s --inflight 8 --io-timeout 0.2 > busy.json 2> busy.err; "
           "echo $? > busy.rc) & (cd %s && %s put c0.off c1.off c2.off c3.off c4.off c5.off --prepare --inflight 4 "
           "--server %s --io-timeout 0.2 > put2.txt 2> put2.err; echo $? > put2.rc) & wait",
           dir, cli, srv, dir, cli, srv);
  run(cmd);
  {
    char pr[700];
    snprintf(pr, sizeof pr, "%s/busy.rc", dir);
    char *brc = slurp(pr, NULL);
    snprintf(pr, sizeof pr, "%s/put2.rc", dir);
    char *prc = slurp(pr, NULL);
    CHECK_MSG(brc && atoi(brc) == 0, "busy batch exit %s (see %s/busy.err)", brc ? brc : "?", dir);
    CHECK_MSG(prc && atoi(prc) == 0, "busy put exit %s (see %s/put2.err)", prc ? prc : "?", dir);
    free(brc);
    free(prc);
    snprintf(pr, sizeof pr, "%s/busy.json", dir);
    char *bj2 = slurp(pr, NULL);
    int ok2 = 0, bad2 = 0;
    for (const char *q = bj2; q && (q = strstr(q, "\"ok\":")); q += 5) *(q[5] == 't' ? &ok2 : &bad2) += 1;
    CHECK_MSG(ok2 == 42 && bad2 == 0, "busy batch: %d ok, %d failed", ok2, bad2);
    free(bj2);
    snprintf(pr, sizeof pr, "%s/put2.txt", dir);
    char *pt = slurp(pr, NULL);
    const char *at = pt;
    for (int i = 0; i < 6 && at; i++) {
      char name[16];
      snprintf(name, sizeof name, "  c%d.off\n", i);
      at = strstr(at, name);
      CHECK_MSG(at != NULL, "put2: c%d.off missing or out of order: %s", i, pt ? pt : "");
      if (at) at += strlen(name);
    }
    free(pt);
  }

  test_daemon_multires(dir, cli, srv);

  snprintf(cmd, sizeof cmd, "%s stats --server %s > %s/stats.txt 2>&1", cli, srv, dir);
  CHECK(run(cmd) == 0);
  snprintf(cmd, sizeof cmd, "%s query %s/a.drc -k 3 --server %s > %s/query.txt 2>&1", cli, dir, srv, dir);
  rc = run(cmd);
  if (rc) fprintf(stderr, "note: query exit %d (see %s/query.txt)\n", rc, dir);

  kill(pid, SIGTERM);
  int st = 0;
  for (int t = 0; t < 100; t++) {
    if (waitpid(pid, &st, WNOHANG) == pid) break;
    struct timespec ts = {0, 100000000L};
    nanosleep(&ts, NULL);
    if (t == 99) {
      kill(pid, SIGKILL);
      waitpid(pid, &st, 0);
    }
  }
  if (!sm_test_failures) {
    snprintf(cmd, sizeof cmd, "rm -rf %s", dir);
    run(cmd);
  } else {
    fprintf(stderr, "daemon section files kept in %s\n", dir);
  }
}
#endif

int main(void) {
  signal(SIGPIPE, SIG_IGN);
  test_addr();
  test_ids();
  test_args();

  double st[3] = {1, 1.2, 0.9};
  sm_error err;
  REQUIRE(sm_synth_blob(2, 0.3, 7, st, &g_mesh, &err) == 0);
  snprintf(g_off, sizeof g_off, "%s/client_blob_%ld.off", SM_TEST_TMP, (long)getpid());
  FILE *f = fopen(g_off, "w");
  REQUIRE(f);
  fprintf(f, "OFF\n%d %d 0\n", g_mesh->nv, g_mesh->nf);
  for (int32_t v = 0; v < g_mesh->nv; v++)
    fprintf(f, "%.17g %.17g %.17g\n", g_mesh->V[3 * v], g_mesh->V[3 * v + 1], g_mesh->V[3 * v + 2]);
  for (int32_t t = 0; t < g_mesh->nf; t++)
    fprintf(f, "3 %d %d %d\n", g_mesh->F[3 * t], g_mesh->F[3 * t + 1], g_mesh->F[3 * t + 2]);
  REQUIRE(fclose(f) == 0);
  for (int i = 0; i < 32; i++) k_affinity[i] = (uint8_t)(i * 7 + 1);

  run_pair("basic", srv_basic, cli_basic, NULL);
  run_pair("match", srv_match, cli_match, NULL);
  run_pair("batch", srv_batch, cli_batch, NULL);
  run_pair("version 2", srv_v2, cli_v2, NULL);
  int garbage = 0, silent = 1;
  run_pair("garbage", srv_garbage, cli_garbage, &garbage);
  run_pair("silent", srv_garbage, cli_garbage, &silent);
  run_pair("queued", srv_queued, cli_queued, NULL);
  test_reconnect();
  unlink(g_off);
  sm_mesh_destroy(g_mesh);

#if defined(SM_SERVER_BIN) && defined(SM_CLI_BIN)
  test_daemon();
#else
  fprintf(stderr, "note: daemon section not built (no shapematchd target)\n");
#endif
  return sm_test_finish();
}
