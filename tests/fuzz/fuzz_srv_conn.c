/* fuzz_srv_conn: the daemon's connection state machine (server/sm_srv_conn.c) in process,
 * driven by a script of peer and loop events taken from the input.
 *
 * Setup per input: one sm_server with a real epoll set and a real connection over a
 * socketpair; the harness plays both the peer (the other end of the pair) and the event
 * loop (it calls the sm_conn_* entry points as sm_srv_loop.c does). Around the state
 * machine it supplies deterministic stand-ins, so that an input always replays the same:
 *   - the worker pool (sm_pool_submit): a FIFO the script runs on this thread;
 *   - the executor (sm_exec_run): answers a job with one OK frame whose size comes from its
 *     body (up to 256 KiB, so answers can fill the write queue), preceded by a MORE frame
 *     when the body's first byte is odd, or CANCELLED when the job's cancel flag is set;
 *   - the store (HAS_SHAPE / DROP_SHAPE / STATS): ids whose first byte is odd are stored;
 *   - the log: formatted and dropped.
 * Input: byte 0 = configuration (bits 0-1 buffer budget 16 KiB..16 MiB, bits 2-3
 *   max_inflight 1/2/4/64, bits 4-5 queue length 0/1/4/64, bit 6 token required, bit 7
 *   max_payload 4 KiB instead of 1 MiB), then commands: [op][len lo][len hi][len bytes]
 *   (len truncated to what is left). op % 10:
 *     0 the peer sends the bytes raw; 1 the peer sends one frame it builds (header with a
 *     correct CRC around the bytes: opcode = b[0], flags = b[1] & 7, request id = b[2],
 *     version = b[3] & 3; a payload CRC trailer when flags ask for one), cut in two writes
 *     at b[4]; 2 the peer sends a valid HELLO (versions from b[0], token from b[1] bit 0,
 *     max_response = b[2] * 64); 3 the loop runs up to b[0] % 8 + 1 queued jobs and hands
 *     their frames to the connection; 4 the peer reads up to (len + 1) * 512 bytes, then
 *     the connection is writable; 5 the clock advances by b[0] * 100 ms (tick); 6 the drain
 *     starts (GOAWAY to the connection); 7 the budget pass runs; 8 the peer half-closes its
 *     sending side; 9 the connection-limit eviction runs (clock advanced by b[0] * 100 ms).
 *   After each command the loop's readable handler runs when the peer has sent something
 *   (level-triggered epoll would wake it), then sm_conn_budget and sm_conn_sweep.
 * Properties (sm_srv_conn.h): every byte the server sends parses as complete response
 *   frames (RESPONSE flag, valid CRCs) except possibly a tail cut by an abrupt close;
 *   nothing follows a connection-fatal GOAWAY; when the peer goes away and every job has
 *   ended, the connection is freed and the buffer budget's charge returns to exactly 0
 *   (every charged byte released), with no connection counted active or budget-blocked.
 */
#include <errno.h>
#include <stdarg.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <unistd.h>

#include "sm_fuzz.h"
#include "sm_proto.h"
#include "sm_srv.h"
#include "sm_srv_conn.h"
#include "sm_srv_exec.h"
#include "sm_srv_log.h"
#include "sm_srv_metrics.h"
#include "sm_srv_pool.h"
#include "sm_srv_store.h"

#define MAX_SEEN (1u << 20) /* bytes of answers kept for the stream check */

/* ---------------------------------------------------------------- stand-ins */

struct sm_pool {
  sm_pool_job *head, *tail;
  int n, cap;
};

int sm_pool_submit(sm_pool *p, sm_pool_job *j) {
  if (p->n >= p->cap) return SM_POOL_EFULL;
  j->qnext = NULL;
  if (p->tail) p->tail->qnext = j;
  else p->head = j;
  p->tail = j;
  p->n++;
  return 0;
}

int sm_pool_queue_depth(sm_pool *p) { return p->n; }

static sm_srv_out *done_head, *done_tail; /* the completion list (empty between inputs) */

static void post(sm_job *j, sm_wbuf *w, int final) {
  sm_srv_out *o = calloc(1, sizeof *o);
  SM_FUZZ_CHECK(o != NULL);
  o->job = j;
  o->frames = w;
  o->final = final;
  if (done_tail) done_tail->base.next = &o->base;
  else done_head = o;
  done_tail = o;
}

static sm_wbuf *ok_frame(const sm_job *j, uint16_t flags, size_t payload) {
  sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + payload);
  SM_FUZZ_CHECK(w != NULL);
  sm_proto_header h = {j->version, j->opcode, (uint16_t)(SM_PROTO_F_RESPONSE | flags), j->rid,
                       SM_ST_OK, (uint32_t)payload};
  sm_proto_write_header(w->data, &h);
  memset(w->data + SM_PROTO_HEADER_LEN, 0xA5, payload);
  return w;
}

void sm_exec_run(sm_pool_job *pj) {
  sm_job *j = (sm_job *)pj;
  if (atomic_load(&j->cancel)) {
    post(j, sm_error_frame(j->version, j->opcode, j->rid, SM_ST_CANCELLED, 0, 0, "cancelled"), 1);
    return;
  }
  uint8_t b0 = j->body_len ? j->body[0] : 0;
  if (b0 & 1) post(j, ok_frame(j, SM_PROTO_F_MORE, 8), 0);
  size_t n = (size_t)j->body_len * 64;
  post(j, ok_frame(j, 0, n > (256u << 10) ? (256u << 10) : n), 1);
}

int sm_store_has(sm_store *st, const uint8_t id[32], uint32_t *nv, uint32_t *nf, int *prepared) {
  (void)st;
  *nv = 3;
  *nf = 1;
  *prepared = (id[0] & 2) != 0;
  return id[0] & 1;
}

int sm_store_drop(sm_store *st, const uint8_t id[32]) {
  (void)st;
  return (id[0] & 1) ? 0 : SM_STORE_ENOTFOUND;
}

void sm_store_get_stats(sm_store *st, sm_store_stats *out) {
  (void)st;
  memset(out, 0, sizeof *out);
}

void sm_log(const char *level, const char *msg, const char *fmt, ...) {
  char line[2048];
  (void)level;
  (void)msg;
  if (!fmt) return;
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(line, sizeof line, fmt, ap); /* the arguments are still checked (UBSan, ASan) */
  va_end(ap);
}

void sm_hex(const unsigned char *p, unsigned n, char *out) {
  static const char d[] = "0123456789abcdef";
  for (unsigned i = 0; i < n; i++) {
    out[2 * i] = d[p[i] >> 4];
    out[2 * i + 1] = d[p[i] & 15];
  }
  out[2 * n] = 0;
}

/* ---------------------------------------------------------------- the peer */

typedef struct peer {
  int fd;
  uint8_t *seen;   /* answers read so far (the first MAX_SEEN bytes) */
  size_t n_seen;
  size_t total;    /* all bytes read */
  int sent;        /* something was sent since the last readable call */
  int closed_wr;
} peer;

static void peer_send(peer *p, const uint8_t *b, size_t n) {
  if (p->closed_wr) return;
  while (n) {
    ssize_t k = send(p->fd, b, n, MSG_NOSIGNAL | MSG_DONTWAIT);
    if (k <= 0) break; /* full (the server stopped reading) or gone: the rest is lost */
    b += k;
    n -= (size_t)k;
    p->sent = 1;
  }
}

static void peer_read(peer *p, size_t cap) {
  uint8_t buf[16384];
  while (cap) {
    ssize_t k = recv(p->fd, buf, cap < sizeof buf ? cap : sizeof buf, MSG_DONTWAIT);
    if (k <= 0) break;
    size_t keep = p->n_seen + (size_t)k <= MAX_SEEN ? (size_t)k : MAX_SEEN - p->n_seen;
    memcpy(p->seen + p->n_seen, buf, keep);
    p->n_seen += keep;
    p->total += (size_t)k;
    cap -= (size_t)k;
  }
}

static void peer_frame(peer *p, const uint8_t *b, size_t n) {
  if (n < 5) return;
  size_t body = n - 5;
  uint16_t flags = b[1] & 7;
  size_t pl = body + ((flags & SM_PROTO_F_PAYLOAD_CRC) ? 4 : 0);
  uint8_t *f = malloc(SM_PROTO_HEADER_LEN + pl);
  SM_FUZZ_CHECK(f != NULL);
  sm_proto_header h = {(uint8_t)(b[3] & 3), b[0], flags, b[2], 0, (uint32_t)pl};
  sm_proto_write_header(f, &h);
  memcpy(f + SM_PROTO_HEADER_LEN, b + 5, body);
  if (flags & SM_PROTO_F_PAYLOAD_CRC) {
    uint32_t crc = sm_proto_crc32c(0, b + 5, body);
    for (int i = 0; i < 4; i++) f[SM_PROTO_HEADER_LEN + body + i] = (uint8_t)(crc >> (8 * i));
  }
  size_t total = SM_PROTO_HEADER_LEN + pl, cut = b[4] % (total + 1);
  peer_send(p, f, cut);
  peer_send(p, f + cut, total - cut);
  free(f);
}

static void peer_hello(peer *p, const uint8_t *b, size_t n) {
  uint8_t b0 = n > 0 ? b[0] : 0, b1 = n > 1 ? b[1] : 0, b2 = n > 2 ? b[2] : 0;
  sm_proto_hello_req m = {(uint16_t)(1 + (b0 & 1)), (uint16_t)(1 + ((b0 >> 1) & 3)),
                          (uint32_t)b2 * 64, {0}, (const uint8_t *)"fuzz",
                          (uint16_t)((b1 & 1) ? 4 : 0)};
  if (m.min_version > m.max_version) m.max_version = m.min_version;
  uint8_t f[512];
  sm_proto_header h = {SM_PROTO_VERSION_HELLO, SM_OP_HELLO, 0, 1 + (uint32_t)(b1 >> 1), 0, 0};
  ptrdiff_t len = sm_proto_enc_hello_req(f, sizeof f, &h, &m);
  if (len > 0 && (size_t)len <= sizeof f) peer_send(p, f, (size_t)len);
}

/* ---------------------------------------------------------------- the loop */

static void run_jobs(sm_server *s, int max) {
  for (int i = 0; i < max && s->pool->head; i++) {
    sm_pool_job *j = s->pool->head;
    s->pool->head = j->qnext;
    if (!s->pool->head) s->pool->tail = NULL;
    s->pool->n--;
    j->run(j);
  }
  while (done_head) { /* sm_srv_loop.c: the eventfd fired */
    sm_srv_out *o = done_head;
    done_head = (sm_srv_out *)o->base.next;
    if (!done_head) done_tail = NULL;
    sm_conn_on_done(s, o);
  }
}

static void after_event(sm_server *s, sm_conn *c, peer *p) {
  if (c && p->sent && (c->ev_mask & EPOLLIN)) sm_conn_on_readable(s, c);
  p->sent = 0;
  sm_conn_run_backlog(s);
  sm_conn_budget(s);
  sm_conn_sweep(s);
}

/* The answers: complete, valid response frames; nothing after a fatal GOAWAY. */
static void check_stream(const peer *p) {
  size_t off = 0;
  int fatal_seen = 0;
  while (off < p->n_seen) {
    sm_proto_frame f;
    ptrdiff_t k = sm_proto_parse_frame(p->seen + off, p->n_seen - off, UINT32_MAX, &f);
    if (k == SM_PROTO_PARTIAL) break; /* cut by a close, or by MAX_SEEN */
    SM_FUZZ_CHECK(k > 0);
    SM_FUZZ_CHECK(f.h.flags & SM_PROTO_F_RESPONSE);
    SM_FUZZ_CHECK(!fatal_seen);
    if (f.h.opcode == SM_OP_GOAWAY && sm_proto_status_is_fatal(f.h.status)) fatal_seen = 1;
    off += (size_t)k;
  }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  uint8_t cfgb = sm_fuzz_take(&data, &size);
  static const uint64_t budgets[4] = {16u << 10, 256u << 10, 2u << 20, 16u << 20};
  static const uint32_t inflight[4] = {1, 2, 4, 64};
  static const int queues[4] = {0, 1, 4, 64};
  sm_server s;
  memset(&s, 0, sizeof s);
  sm_srv_config_default(&s.cfg);
  s.cfg.buffer_budget = budgets[cfgb & 3];
  s.cfg.max_inflight = inflight[(cfgb >> 2) & 3];
  struct sm_pool pool = {NULL, NULL, 0, queues[(cfgb >> 4) & 3]};
  if (cfgb & 64) {
    memcpy(s.cfg.token, "fuzz", 4);
    s.cfg.token_len = 4;
    s.cfg.has_token = 1;
  }
  s.cfg.max_payload = (cfgb & 128) ? 4096 : (1u << 20);
  s.pool = &pool;
  s.epfd = epoll_create1(EPOLL_CLOEXEC);
  SM_FUZZ_CHECK(s.epfd >= 0);
  int sv[2];
  SM_FUZZ_CHECK(socketpair(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0, sv) == 0);
  /* One buffer for every input: a fresh 1 MiB allocation each time went to ASan's mmap
   * allocator and its page faults were most of an iteration's cost. */
  static uint8_t seen[MAX_SEEN];
  peer p = {sv[1], seen, 0, 0, 0, 0};
  sm_conn *c = sm_conn_new(&s, sv[0], SM_H_CONN, "fuzz");
  SM_FUZZ_CHECK(c != NULL);
  uint64_t clock = 0; /* how far the script moved the clock */

  while (size >= 3 && s.conns) {
    uint8_t op = data[0] % 10;
    size_t len = (size_t)data[1] | (size_t)data[2] << 8;
    data += 3;
    size -= 3;
    if (len > size) len = size;
    uint8_t *b = sm_fuzz_dup(data, len); /* exact size: reads past it are ASan reports */
    uint8_t b0 = len ? b[0] : 0;
    data += len;
    size -= len;
    c = s.conns;
    switch (op) {
    case 0: peer_send(&p, b, len); break;
    case 1: peer_frame(&p, b, len); break;
    case 2: peer_hello(&p, b, len); break;
    case 3: run_jobs(&s, b0 % 8 + 1); break;
    case 4:
      peer_read(&p, (len + 1) * 512);
      sm_conn_on_writable(&s, c);
      break;
    case 5:
      clock += (uint64_t)b0 * 100000000ull;
      sm_conn_tick(&s, sm_srv_now_ns() + clock);
      break;
    case 6:
      if (!s.draining) {
        s.draining = 1;
        sm_conn_goaway(&s, c);
        sm_conn_on_writable(&s, c);
      }
      break;
    case 7: break; /* after_event runs the budget pass */
    case 8:
      if (!p.closed_wr) shutdown(p.fd, SHUT_WR);
      p.closed_wr = 1;
      p.sent = 1; /* EOF makes the socket readable */
      break;
    case 9:
      clock += (uint64_t)b0 * 100000000ull;
      sm_conn_evict_idle(&s, sm_srv_now_ns() + clock);
      break;
    }
    free(b);
    after_event(&s, s.conns, &p);
  }

  /* The end: read what is queued, then the peer goes away; jobs end; everything is freed. */
  for (int round = 0; round < 64 && s.conns; round++) {
    c = s.conns;
    sm_conn_on_writable(&s, c);
    peer_read(&p, SIZE_MAX);
    if (round == 8 && p.fd >= 0) { /* long enough for what was queued: now hang up */
      close(p.fd);
      p.fd = -1;
    }
    run_jobs(&s, 1 << 20);
    if (s.conns && s.conns->fd >= 0) sm_conn_on_readable(&s, s.conns);
    if (round > 8 && s.conns && s.conns->state == SM_CONN_LINGER)
      sm_conn_tick(&s, sm_srv_now_ns() + clock + 3000000000ull); /* linger ends */
    sm_conn_run_backlog(&s);
    sm_conn_budget(&s);
    sm_conn_sweep(&s);
  }
  if (p.fd >= 0) close(p.fd);
  check_stream(&p);
  SM_FUZZ_CHECK(s.conns == NULL);
  SM_FUZZ_CHECK(s.buf_used == 0);
  SM_FUZZ_CHECK(s.n_active == 0);
  SM_FUZZ_CHECK(s.n_budget_blocked == 0);
  SM_FUZZ_CHECK(pool.n == 0 && done_head == NULL);
  close(s.epfd);
  return 0;
}
