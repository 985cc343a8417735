/* Connection state machine and frame handling on the loop thread: see sm_srv_conn.h. */
#define _GNU_SOURCE /* mremap: read buffers grow as mapped pages */
#include "sm_srv_conn.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <unistd.h>

#include "sm_srv_exec.h"
#include "sm_srv_log.h"
#include "sm_srv_metrics.h"
#include "sm_srv_store.h"

#define RBUF_MIN 4096u
/* Read buffers from this size on are pages of their own (mmap, grown by mremap) instead of
 * heap chunks: freeing one gives its pages back at once. From the heap, the holes that
 * growing and freed read buffers left stayed resident until malloc_trim: bench_hostile's
 * uploads held the daemon 7-16 MiB above budget + unloaded peak with heap buffers up to
 * the 1 MiB mmap threshold (docs/RELIABILITY.md section 3). */
#ifndef SM_CONN_RBUF_MAP_MIN /* the fuzz harness sets 8 KiB: its inputs take both paths */
#define SM_CONN_RBUF_MAP_MIN (64u << 10)
#endif
#define RBUF_MAP_MIN ((size_t)SM_CONN_RBUF_MAP_MIN)
#define STEAL_MIN (64u << 10)  /* hand a large frame's buffer to its job instead of copying */
#define LINGER_NS 2000000000ull
#define BUSY_RETRY_MS 100u
#define CHUNK 4096u            /* small answers are packed into chunks of this size */
#define SMALL_FRAME 512u
#define MALLOC_OVERHEAD 16u    /* charged per allocation: what malloc keeps beside it */
#define SHED_RETRY_MS 1000u
#define READ_SLICE (64u << 10) /* bytes read from one connection per event: fairness */

/* ------------------------------------------------------------------ budget */

static void charge(sm_server *s, size_t *acct, size_t n) {
  *acct += n;
  s->buf_used += n;
  if (s->buf_used > s->buf_trim_mark) s->buf_trim_mark = s->buf_used;
  sm_met_add(&sm_met.buffered, n);
  sm_met_max(&sm_met.buffered_peak, s->buf_used);
}

static void release(sm_server *s, size_t *acct, size_t n) {
  *acct -= n;
  s->buf_used -= n;
  sm_met_sub(&sm_met.buffered, n);
}

static size_t wbuf_cost(const sm_wbuf *w) { return sizeof *w + w->cap + MALLOC_OVERHEAD; }

/* Rule 1's threshold: lower once half the budget is in use. */
static size_t wq_cap(const sm_server *s) {
  return s->buf_used > s->cfg.buffer_budget / 2 ? SM_CONN_WQ_TIGHT : SM_CONN_WQ_HIGH;
}

/* ---- read buffer memory: heap below RBUF_MAP_MIN, mapped pages from it (a capacity
 * tells which) */

static size_t rmem_cap(size_t want) {
  if (want < RBUF_MAP_MIN) return want;
  size_t pg = (size_t)sysconf(_SC_PAGESIZE);
  return (want + pg - 1) / pg * pg;
}

/* What a buffer of capacity cap costs the budget: its pages, or the chunk and malloc's
 * bookkeeping beside it. */
static size_t rmem_cost(size_t cap) {
  return cap == 0 ? 0 : cap >= RBUF_MAP_MIN ? cap : cap + MALLOC_OVERHEAD;
}

static void rmem_free(uint8_t *p, size_t cap) {
  if (cap >= RBUF_MAP_MIN) munmap(p, cap);
  else free(p);
}

/* p (capacity cap, keep bytes used; NULL when cap is 0) moved to capacity ncap (from
 * rmem_cap); NULL when out of memory, p untouched then. */
static uint8_t *rmem_resize(uint8_t *p, size_t cap, size_t ncap, size_t keep) {
  void *q;
  if (cap >= RBUF_MAP_MIN && ncap >= RBUF_MAP_MIN) {
    q = mremap(p, cap, ncap, MREMAP_MAYMOVE);
    return q == MAP_FAILED ? NULL : q;
  }
  if (cap < RBUF_MAP_MIN && ncap < RBUF_MAP_MIN) return realloc(p, ncap);
  if (ncap >= RBUF_MAP_MIN) {
    q = mmap(NULL, ncap, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (q == MAP_FAILED) return NULL;
  } else if (!(q = malloc(ncap))) {
    return NULL;
  }
  if (keep) memcpy(q, p, keep);
  rmem_free(p, cap);
  return q;
}

static void rbuf_free(sm_server *s, sm_conn *c) {
  if (c->rcap) release(s, &c->held, rmem_cost(c->rcap));
  if (c->rbuf) rmem_free(c->rbuf, c->rcap);
  c->rbuf = NULL;
  c->rcap = 0;
  c->rlen = 0;
  c->rneed = 0;
}

/* Resizes the read buffer to ncap (>= rlen), within the budget when it grows. Returns 0,
 * or -1: no room (rule 2: the caller stops reading) or out of memory (errno ENOMEM). */
static int rbuf_resize(sm_server *s, sm_conn *c, size_t ncap) {
  size_t old = rmem_cost(c->rcap);
  ncap = rmem_cap(ncap);
  if (ncap > c->rcap && s->buf_used - old + rmem_cost(ncap) > s->cfg.buffer_budget) {
    errno = 0;
    return -1;
  }
  uint8_t *nb = rmem_resize(c->rbuf, c->rcap, ncap, c->rlen);
  if (!nb) {
    errno = ENOMEM;
    return -1;
  }
  if (old) release(s, &c->held, old);
  charge(s, &c->held, rmem_cost(ncap));
  c->rbuf = nb;
  c->rcap = ncap;
  return 0;
}

/* Appends w to the queue; an answer of at most SMALL_FRAME bytes is copied into the tail
 * chunk instead (a pipelined PING costs its 32 bytes, not a malloc of its own). */
static void wq_push(sm_server *s, sm_conn *c, sm_wbuf *w) {
  w->next = NULL;
  if (w->len <= SMALL_FRAME) {
    sm_wbuf *t = c->wq_tail;
    if (!t || t->cap - t->len < w->len) {
      t = sm_wbuf_new(CHUNK);
      if (t) {
        t->len = 0;
        if (c->wq_tail) c->wq_tail->next = t;
        else c->wq_head = t;
        c->wq_tail = t;
        charge(s, &c->held, wbuf_cost(t));
      }
    }
    if (t && t->cap - t->len >= w->len) {
      memcpy(t->data + t->len, w->data, w->len);
      t->len += w->len;
      c->wq_bytes += w->len;
      free(w);
      return;
    }
  }
  if (c->wq_tail) c->wq_tail->next = w;
  else c->wq_head = w;
  c->wq_tail = w;
  c->wq_bytes += w->len;
  charge(s, &c->held, wbuf_cost(w));
}

static void wq_pop(sm_server *s, sm_conn *c) {
  sm_wbuf *w = c->wq_head;
  c->wq_head = w->next;
  if (!c->wq_head) c->wq_tail = NULL;
  c->wq_bytes -= w->len - w->off;
  release(s, &c->held, wbuf_cost(w));
  free(w);
}

static void wq_free(sm_server *s, sm_conn *c) {
  while (c->wq_head) wq_pop(s, c);
}

/* Drops the answers not yet started; a partly sent one stays (the peer must be able to
 * parse the stream up to the GOAWAY that follows). */
static void wq_drop_unsent(sm_server *s, sm_conn *c) {
  sm_wbuf *h = c->wq_head;
  if (h && h->off == 0) {
    wq_free(s, c);
    return;
  }
  if (!h) return;
  while (h->next) {
    sm_wbuf *n = h->next;
    h->next = n->next;
    c->wq_bytes -= n->len;
    release(s, &c->held, wbuf_cost(n));
    free(n);
  }
  c->wq_tail = h;
}

/* ------------------------------------------------------------------ lifecycle */

sm_conn *sm_conn_new(sm_server *s, int fd, int kind, const char *peer) {
  sm_conn *c = calloc(1, sizeof *c);
  if (!c) return NULL;
  c->inflight = calloc(s->cfg.max_inflight ? s->cfg.max_inflight : 1, sizeof *c->inflight);
  if (!c->inflight) {
    free(c);
    return NULL;
  }
  charge(s, &c->own, sizeof *c + MALLOC_OVERHEAD +
                        (s->cfg.max_inflight ? s->cfg.max_inflight : 1) * sizeof *c->inflight +
                        MALLOC_OVERHEAD);
  c->kind = kind;
  c->fd = fd;
  c->id = ++s->next_conn_id;
  snprintf(c->peer, sizeof c->peer, "%s", peer);
  c->limit = SM_PROTO_HELLO_MAX_PAYLOAD;
  c->version = SM_PROTO_VERSION_HELLO;
  c->born_ns = c->last_active_ns = sm_srv_now_ns();
  c->next = s->conns;
  if (s->conns) s->conns->prev = c;
  s->conns = c;
  if (kind == SM_H_CONN) {
    s->n_active++;
    sm_met_add(&sm_met.connections, 1);
    sm_met_add(&sm_met.connections_total, 1);
  }
  struct epoll_event ev = {.events = EPOLLIN, .data.ptr = c};
  c->ev_mask = EPOLLIN;
  epoll_ctl(s->epfd, EPOLL_CTL_ADD, fd, &ev);
  return c;
}

static void conn_free(sm_server *s, sm_conn *c) {
  if (c->prev) c->prev->next = c->next;
  else s->conns = c->next;
  if (c->next) c->next->prev = c->prev;
  wq_free(s, c);
  rbuf_free(s, c);
  if (c->budget_blocked) s->n_budget_blocked--;
  if (c->backlogged) s->n_backlogged--;
  release(s, &c->own, c->own);
  free(c->inflight);
  free(c);
}

static void set_backlogged(sm_server *s, sm_conn *c, int v) {
  if (c->backlogged == v) return;
  c->backlogged = v;
  s->n_backlogged += v ? 1 : -1;
}

static void leave_active(sm_server *s, sm_conn *c) {
  if (c->kind == SM_H_CONN && c->state == SM_CONN_OPEN) {
    s->n_active--;
    sm_met_sub(&sm_met.connections, 1);
  }
}

void sm_conn_cancel_all(sm_conn *c, int v) {
  for (uint32_t i = 0; i < c->n_inflight; i++) {
    int zero = 0;
    atomic_compare_exchange_strong(&c->inflight[i]->cancel, &zero, v);
  }
}

void sm_conn_close(sm_server *s, sm_conn *c) {
  if (c->state == SM_CONN_DEAD) return;
  leave_active(s, c);
  if (c->fd >= 0) {
    epoll_ctl(s->epfd, EPOLL_CTL_DEL, c->fd, NULL);
    close(c->fd);
    c->fd = -1;
  }
  c->state = SM_CONN_DEAD;
  set_backlogged(s, c, 0);
  wq_free(s, c);
  rbuf_free(s, c);
  sm_conn_cancel_all(c, 1); /* closing a connection cancels its requests */
  if (c->kind == SM_H_CONN)
    sm_log("info", "connection closed", " conn=%llu peer=%s inflight=%u",
           (unsigned long long)c->id, c->peer, c->n_inflight);
}

void sm_conn_sweep(sm_server *s) {
  for (sm_conn *c = s->conns, *n; c; c = n) {
    n = c->next;
    if (c->state == SM_CONN_DEAD && c->n_inflight == 0) conn_free(s, c);
  }
}

void sm_conn_update_events(sm_server *s, sm_conn *c) {
  if (c->fd < 0) return;
  uint32_t m = 0;
  int paused = c->state == SM_CONN_OPEN && c->wq_bytes >= wq_cap(s);
  if (paused && !c->read_paused) sm_met_add(&sm_met.read_pauses, 1);
  c->read_paused = paused;
  if (c->state == SM_CONN_OPEN && !paused && !c->budget_blocked && !c->backlogged) m |= EPOLLIN;
  if (c->state == SM_CONN_LINGER) m |= EPOLLIN;
  if (c->wq_head) m |= EPOLLOUT;
  if (m != c->ev_mask) {
    struct epoll_event ev = {.events = m, .data.ptr = c};
    epoll_ctl(s->epfd, EPOLL_CTL_MOD, c->fd, &ev);
    c->ev_mask = m;
  }
}

static void queue_frame(sm_server *s, sm_conn *c, sm_wbuf *w) {
  if (!w || c->fd < 0 || c->state == SM_CONN_DEAD) {
    free(w);
    return;
  }
  wq_push(s, c, w);
  sm_conn_update_events(s, c);
}

void sm_conn_queue(sm_server *s, sm_conn *c, sm_wbuf *w) { queue_frame(s, c, w); }

void sm_conn_send_error(sm_server *s, sm_conn *c, uint8_t opcode, uint32_t rid,
                        uint16_t status, uint32_t retry, uint32_t detail, const char *msg) {
  sm_met_add(&sm_met.errors, 1);
  queue_frame(s, c, sm_error_frame(c->version, opcode, rid, status, retry, detail, msg));
}

void sm_conn_fatal(sm_server *s, sm_conn *c, uint16_t status, uint32_t rid, uint32_t retry,
                   uint32_t detail, const char *msg) {
  if (c->state != SM_CONN_OPEN) return;
  sm_met_add(&sm_met.fatal_errors, 1);
  sm_log("warn", "connection-fatal error", " conn=%llu peer=%s status=%s rid=%u detail=%u",
         (unsigned long long)c->id, c->peer, sm_proto_status_name(status), rid, detail);
  queue_frame(s, c, sm_error_frame(c->version, SM_OP_GOAWAY, rid, status, retry, detail, msg));
  leave_active(s, c);
  c->state = SM_CONN_FLUSH_CLOSE;
  sm_conn_cancel_all(c, 1);
  rbuf_free(s, c); /* nothing more is read but the lingering discard */
  if (c->budget_blocked) {
    c->budget_blocked = 0;
    s->n_budget_blocked--;
  }
  sm_conn_update_events(s, c);
  if (!c->wq_head) sm_conn_on_writable(s, c);
}

void sm_conn_goaway(sm_server *s, sm_conn *c) {
  if (c->state != SM_CONN_OPEN || c->goaway_sent || c->kind != SM_H_CONN) return;
  c->goaway_sent = 1;
  queue_frame(s, c, sm_error_frame(c->version, SM_OP_GOAWAY, 0, SM_ST_OK, 1000, s->cfg.drain_ms,
                                   "server shutting down"));
}

static void process(sm_server *s, sm_conn *c);

/* ------------------------------------------------------------------ write side */

/* Sends queued frames until the socket is full; -1 when the peer is gone. */
static int send_queued(sm_server *s, sm_conn *c) {
  while (c->wq_head) {
    sm_wbuf *w = c->wq_head;
    ssize_t n = send(c->fd, w->data + w->off, w->len - w->off, MSG_NOSIGNAL);
    if (n < 0) {
      if (errno == EINTR) continue;
      if (errno == EAGAIN || errno == EWOULDBLOCK) break;
      return -1;
    }
    sm_met_add(&sm_met.bytes_out, (uint64_t)n);
    w->off += (size_t)n;
    c->wq_bytes -= (size_t)n;
    if (w->off == w->len) wq_pop(s, c);
  }
  return 0;
}

/* Answers leave in the turn that made them rather than at the next writable event, one
 * loop iteration later (which, under load, is when a PING or a finished DISTANCE waited).
 * Called where closing the connection is not safe: a failure is left to that event. */
static void flush_now(sm_server *s, sm_conn *c) {
  if (c->fd >= 0 && c->state == SM_CONN_OPEN && c->wq_head) (void)send_queued(s, c);
}

void sm_conn_on_writable(sm_server *s, sm_conn *c) {
  if (c->fd < 0) return;
  if (send_queued(s, c)) {
    sm_conn_close(s, c); /* peer gone */
    return;
  }
  if (c->kind == SM_H_CONN && c->state == SM_CONN_OPEN && c->rlen && c->wq_bytes < wq_cap(s)) {
    process(s, c); /* frames held back by rule 1 */
    if (c->state != SM_CONN_OPEN || c->fd < 0) return;
  }
  if (!c->wq_head && c->state == SM_CONN_FLUSH_CLOSE) {
    /* Half-close, then read and discard for a moment: closing with unread input would
     * make the kernel send RST, which can destroy the GOAWAY frame before it is read. */
    shutdown(c->fd, SHUT_WR);
    c->state = SM_CONN_LINGER;
    c->linger_deadline_ns = sm_srv_now_ns() + LINGER_NS;
  }
  if (c->kind == SM_H_CONN && c->state == SM_CONN_OPEN && s->draining && !c->wq_head &&
      c->n_inflight == 0) {
    leave_active(s, c); /* drained: graceful close */
    c->state = SM_CONN_FLUSH_CLOSE;
    sm_conn_on_writable(s, c);
    return;
  }
  sm_conn_update_events(s, c);
}

/* ------------------------------------------------------------------ read side */

static int inflight_find(const sm_conn *c, uint32_t rid) {
  for (uint32_t i = 0; i < c->n_inflight; i++)
    if (c->inflight[i]->rid == rid) return (int)i;
  return -1;
}

static void send_ok(sm_server *s, sm_conn *c, sm_wbuf *w, ptrdiff_t len) {
  if (len <= 0 || !w || (size_t)len > w->len) {
    free(w);
    return;
  }
  w->len = (size_t)len;
  if (c->max_response && w->len - SM_PROTO_HEADER_LEN > c->max_response) {
    uint8_t op = w->data[5];
    uint32_t rid = (uint32_t)w->data[8] | (uint32_t)w->data[9] << 8 |
                   (uint32_t)w->data[10] << 16 | (uint32_t)w->data[11] << 24;
    uint32_t need = (uint32_t)(w->len - SM_PROTO_HEADER_LEN);
    free(w);
    sm_conn_send_error(s, c, op, rid, SM_ST_RESPONSE_TOO_LARGE, 0, need,
                       "response exceeds max_response");
    return;
  }
  queue_frame(s, c, w);
}

static int ct_equal(const uint8_t *a, size_t na, const uint8_t *b, size_t nb) {
  unsigned d = na != nb;
  size_t n = na > nb ? na : nb;
  for (size_t i = 0; i < n; i++) d |= (unsigned)((i < na ? a[i] : 0) ^ (i < nb ? b[i] : 0));
  return d == 0;
}

static void on_hello(sm_server *s, sm_conn *c, const sm_proto_frame *f) {
  const sm_srv_config *cfg = &s->cfg;
  sm_proto_hello_req q;
  int rc = sm_proto_dec_hello_req(f->body, f->body_len, &q);
  if (rc) {
    sm_conn_send_error(s, c, SM_OP_HELLO, f->h.request_id, SM_ST_BAD_REQUEST, 0, 0,
                       sm_proto_strerror(rc));
    return;
  }
  if (q.max_version < SM_PROTO_VERSION_MIN || q.min_version > SM_PROTO_VERSION_MAX) {
    sm_conn_fatal(s, c, SM_ST_UNSUPPORTED_VERSION, f->h.request_id, 0,
                  SM_PROTO_VERSION_MIN | (uint32_t)SM_PROTO_VERSION_MAX << 16,
                  "no common protocol version");
    return;
  }
  if (cfg->has_token && !ct_equal(q.token, q.token_len, cfg->token, cfg->token_len)) {
    sm_conn_fatal(s, c, SM_ST_UNAUTHORIZED, f->h.request_id, 0, 0, "token missing or wrong");
    return;
  }
  uint16_t v = q.max_version < SM_PROTO_VERSION_MAX ? q.max_version : SM_PROTO_VERSION_MAX;
  sm_proto_hello_resp o = {v, cfg->max_payload, cfg->max_vertices, cfg->max_faces,
                           cfg->max_inflight, cfg->max_batch_items, cfg->max_query_k,
                           cfg->max_k, cfg->idle_timeout_ms,
                           cfg->has_token ? SM_HELLO_F_AUTH_REQUIRED : 0};
  sm_proto_header h = {SM_PROTO_VERSION_HELLO, SM_OP_HELLO, SM_PROTO_F_RESPONSE, f->h.request_id,
                       0, 0};
  sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + 40 + 4);
  if (w) send_ok(s, c, w, sm_proto_enc_hello_resp(w->data, w->len, &h, &o));
  c->hello_done = 1;
  c->version = (uint8_t)v;
  c->limit = cfg->max_payload;
  c->max_response = q.max_response;
}

static void on_stats(sm_server *s, sm_conn *c, const sm_proto_frame *f) {
  sm_proto_stat st[64];
  sm_proto_stats_resp o = {st, NULL, sm_met_stats(s->store, st, 64)};
  sm_proto_header h = {c->version, SM_OP_STATS, SM_PROTO_F_RESPONSE, f->h.request_id, 0, 0};
  sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + 8 + 32 * 64 + 4);
  if (w) send_ok(s, c, w, sm_proto_enc_stats_resp(w->data, w->len, &h, &o));
}

/* Queues a compute request; takes the frame bytes from rbuf (copied or stolen). */
static void submit_job(sm_server *s, sm_conn *c, const sm_proto_frame *f, size_t frame_len,
                       int steal) {
  uint32_t rid = f->h.request_id;
  if (c->n_inflight >= s->cfg.max_inflight) {
    sm_conn_send_error(s, c, f->h.opcode, rid, SM_ST_LIMIT_EXCEEDED, 0, s->cfg.max_inflight,
                       "too many requests in flight on this connection");
    return;
  }
  sm_job *j = calloc(1, sizeof *j);
  if (!j) {
    sm_conn_send_error(s, c, f->h.opcode, rid, SM_ST_INTERNAL, 0, 0, "out of memory");
    return;
  }
  if (steal) { /* the frame is the whole buffer: hand it over, with its charge */
    j->buf = c->rbuf;
    j->buf_cap = c->rcap;
    j->body = f->body;
    j->charged = rmem_cost(c->rcap);
    release(s, &c->held, j->charged);
    c->rbuf = NULL;
    c->rcap = 0;
  } else {
    j->buf = malloc(f->body_len ? f->body_len : 1);
    if (!j->buf) {
      free(j);
      sm_conn_send_error(s, c, f->h.opcode, rid, SM_ST_INTERNAL, 0, 0, "out of memory");
      return;
    }
    memcpy(j->buf, f->body, f->body_len);
    j->body = j->buf;
    j->charged = (size_t)f->body_len + MALLOC_OVERHEAD;
  }
  charge(s, &c->job_bytes, j->charged + sizeof *j);
  (void)frame_len;
  j->body_len = f->body_len;
  j->base.run = sm_exec_run;
  j->srv = s;
  j->conn = c;
  j->rid = rid;
  j->opcode = f->h.opcode;
  j->version = c->version;
  j->max_response = c->max_response;
  j->recv_ns = sm_srv_now_ns();
  int rc = sm_pool_submit(s->pool, &j->base);
  if (rc) {
    release(s, &c->job_bytes, j->charged + sizeof *j);
    rmem_free(j->buf, j->buf_cap);
    free(j);
    if (rc == SM_POOL_EFULL) {
      sm_met_add(&sm_met.busy, 1);
      sm_conn_send_error(s, c, f->h.opcode, rid, SM_ST_BUSY, BUSY_RETRY_MS, 0, "job queue full");
    } else {
      sm_conn_send_error(s, c, f->h.opcode, rid, SM_ST_SHUTTING_DOWN, 0, 0, "shutting down");
    }
    return;
  }
  c->inflight[c->n_inflight++] = j;
  sm_met_add(&sm_met.inflight, 1);
}

/* One complete, header-valid frame. Returns 1 if the frame's buffer was stolen. */
static int on_frame(sm_server *s, sm_conn *c, const sm_proto_frame *f, size_t frame_len,
                    int can_steal) {
  uint32_t rid = f->h.request_id;
  uint8_t op = f->h.opcode;
  if (f->h.flags & SM_PROTO_F_RESPONSE) {
    sm_conn_fatal(s, c, SM_ST_PROTOCOL_ERROR, rid, 0, 0, "RESPONSE flag on a client frame");
    return 0;
  }
  if (!c->hello_done) {
    if (op != SM_OP_HELLO) {
      sm_conn_fatal(s, c, SM_ST_PROTOCOL_ERROR, rid, 0, 0, "HELLO must be the first frame");
      return 0;
    }
    if (f->h.version != SM_PROTO_VERSION_HELLO) { /* PROTOCOL.md 5.1: parseable by every server */
      sm_conn_fatal(s, c, SM_ST_UNSUPPORTED_VERSION, rid, 0,
                    SM_PROTO_VERSION_MIN | (uint32_t)SM_PROTO_VERSION_MAX << 16,
                    "HELLO must carry header version 1");
      return 0;
    }
    sm_met_add(&sm_met.requests, 1);
    on_hello(s, c, f);
    return 0;
  }
  if (f->h.version != c->version) {
    sm_conn_fatal(s, c, SM_ST_UNSUPPORTED_VERSION, rid, 0,
                  SM_PROTO_VERSION_MIN | (uint32_t)SM_PROTO_VERSION_MAX << 16,
                  "frame version differs from the negotiated one");
    return 0;
  }
  if (op == SM_OP_HELLO) {
    sm_conn_fatal(s, c, SM_ST_PROTOCOL_ERROR, rid, 0, 0, "second HELLO");
    return 0;
  }
  if (inflight_find(c, rid) >= 0) {
    sm_conn_fatal(s, c, SM_ST_PROTOCOL_ERROR, rid, 0, 0, "request_id reused while in flight");
    return 0;
  }
  sm_met_add(&sm_met.requests, 1);
  if (s->draining) {
    sm_conn_send_error(s, c, op, rid, SM_ST_SHUTTING_DOWN, 1000, 0, "server is shutting down");
    return 0;
  }
  unsigned kind = sm_proto_op_flags(op); /* the opcode table: queued or answered here */
  if (kind & SM_OPF_QUEUED) {
    int steal = can_steal && frame_len >= STEAL_MIN && c->n_inflight < s->cfg.max_inflight;
    submit_job(s, c, f, frame_len, steal);
    return steal && c->rbuf == NULL;
  }
  if (kind & SM_OPF_SERVER) { /* a GOAWAY answer would read as "closing" while the connection lived on */
    sm_conn_fatal(s, c, SM_ST_PROTOCOL_ERROR, rid, 0, 0, "GOAWAY is server to client only");
    return 0;
  }
  sm_proto_header h = {c->version, op, SM_PROTO_F_RESPONSE, rid, 0, 0};
  int rc;
  switch (op) {
  case SM_OP_PING: {
    sm_proto_ping q;
    if ((rc = sm_proto_dec_ping(f->body, f->body_len, &q))) break;
    sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + 8 + 4);
    if (w) send_ok(s, c, w, sm_proto_enc_ping(w->data, w->len, &h, 1, &q));
    return 0;
  }
  case SM_OP_STATS:
    if ((rc = sm_proto_dec_empty(f->body, f->body_len))) break;
    on_stats(s, c, f);
    return 0;
  case SM_OP_HAS_SHAPE: {
    sm_proto_id_req q;
    if ((rc = sm_proto_dec_id_req(f->body, f->body_len, &q))) break;
    sm_proto_has_resp o = {0, 0, 0};
    int prepared = 0;
    if (sm_store_has(s->store, q.id, &o.n_vertices, &o.n_faces, &prepared))
      o.flags = SM_HAS_STORED | (prepared ? SM_HAS_PREPARED : 0);
    sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + 12 + 4);
    if (w) send_ok(s, c, w, sm_proto_enc_has_resp(w->data, w->len, &h, &o));
    return 0;
  }
  case SM_OP_DROP_SHAPE: {
    sm_proto_id_req q;
    if ((rc = sm_proto_dec_id_req(f->body, f->body_len, &q))) break;
    if (sm_store_drop(s->store, q.id)) {
      sm_conn_send_error(s, c, op, rid, SM_ST_NOT_FOUND, 0, 0, "shape not stored");
    } else {
      char hex[65];
      sm_hex(q.id, 32, hex);
      sm_log("info", "shape dropped", " id=%s conn=%llu", hex, (unsigned long long)c->id);
      sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + 4);
      if (w) send_ok(s, c, w, sm_proto_enc_empty(w->data, w->len, &h));
    }
    return 0;
  }
  case SM_OP_CANCEL: {
    sm_proto_cancel_req q;
    if ((rc = sm_proto_dec_cancel_req(f->body, f->body_len, &q))) break;
    int i = inflight_find(c, q.target);
    if (i < 0) {
      sm_conn_send_error(s, c, op, rid, SM_ST_NOT_FOUND, 0, 0, "no such request in flight");
    } else {
      int zero = 0;
      atomic_compare_exchange_strong(&c->inflight[i]->cancel, &zero, 1);
      sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + 4);
      if (w) send_ok(s, c, w, sm_proto_enc_empty(w->data, w->len, &h));
    }
    return 0;
  }
  default: /* every immediate request of the opcode table has its case above */
    sm_conn_send_error(s, c, op, rid, SM_ST_UNKNOWN_OPCODE, 0, 0, "unknown opcode");
    return 0;
  }
  sm_conn_send_error(s, c, op, rid, sm_proto_status_for_error(rc), 0, 0, sm_proto_strerror(rc));
  return 0;
}

static uint32_t le32(const uint8_t *p) {
  return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

/* Handles the complete frames at the start of rbuf, until rule 1 pauses the connection or
 * its turn's slice is used (it is then backlogged: sm_conn_run_backlog continues). */
static void process(sm_server *s, sm_conn *c) {
  size_t off = 0;
  int frames = 0;
  set_backlogged(s, c, 0);
  while (c->state == SM_CONN_OPEN && c->rbuf && off < c->rlen) {
    if (c->wq_bytes >= wq_cap(s)) break; /* rule 1: resumed by sm_conn_on_writable */
    if (frames == SM_CONN_FRAME_SLICE) {
      set_backlogged(s, c, 1); /* possibly only a partial frame left: the next turn sees */
      break;
    }
    const uint8_t *p = c->rbuf + off;
    size_t avail = c->rlen - off;
    sm_proto_header h;
    int rc = sm_proto_parse_header(p, avail, c->limit, &h);
    if (rc == SM_PROTO_PARTIAL) break;
    if (rc < 0) {
      uint16_t st = sm_proto_status_for_error(rc);
      uint32_t rid = 0, detail = 0;
      if (rc == SM_PROTO_ETOOBIG) { /* header intact, only too large */
        rid = le32(p + 8);
        detail = c->limit;
      }
      if (rc == SM_PROTO_EVERSION) detail = SM_PROTO_VERSION_MIN | (uint32_t)SM_PROTO_VERSION_MAX << 16;
      char msg[128];
      snprintf(msg, sizeof msg, "%s", sm_proto_strerror(rc));
      sm_conn_fatal(s, c, st, rid, 0, detail, msg);
      return;
    }
    size_t total = SM_PROTO_HEADER_LEN + (size_t)h.payload_len;
    if (avail < total) {
      c->rneed = total; /* rule 2: the buffer grows as the payload arrives */
      break;
    }
    c->rneed = 0;
    sm_proto_frame f;
    ptrdiff_t fr = sm_proto_parse_frame(p, avail, c->limit, &f);
    if (fr < 0) {
      sm_conn_fatal(s, c, sm_proto_status_for_error((int)fr), h.request_id, 0, 0,
                    sm_proto_strerror((int)fr));
      return;
    }
    c->frame_start_ns = sm_srv_now_ns();
    int can_steal = off == 0 && total == c->rlen;
    int stolen = on_frame(s, c, &f, total, can_steal);
    if (stolen || c->state != SM_CONN_OPEN) { /* fatal already discarded the input */
      c->rlen = 0;
      return;
    }
    off += total;
    frames++;
  }
  if (off && c->rbuf) {
    memmove(c->rbuf, c->rbuf + off, c->rlen - off);
    c->rlen -= off;
    c->frame_start_ns = sm_srv_now_ns(); /* a partial frame's clock starts now */
  }
  flush_now(s, c);
  /* Give memory back as soon as a large buffer is no longer needed. */
  if (c->rlen == 0 && c->rcap > RBUF_MIN) rbuf_free(s, c);
  else if (c->rcap > 4 * RBUF_MIN && c->rlen < c->rcap / 4 && c->rneed < c->rcap / 4)
    (void)rbuf_resize(s, c, c->rlen > RBUF_MIN ? c->rlen : RBUF_MIN);
}

/* The next read buffer size: the first RBUF_MIN, then growing, but never beyond the frame
 * being received (its header is valid: rneed) nor the connection's payload limit. */
static size_t rbuf_next_cap(const sm_conn *c) {
  if (!c->rbuf) return RBUF_MIN;
  /* 1.5x: the charge stays close to the bytes that arrived; realloc of a large
   * (mmapped) buffer moves pages, not bytes. */
  size_t ncap = c->rcap + c->rcap / 2;
  if (c->rneed > c->rcap && ncap > c->rneed) ncap = c->rneed;
  size_t maxcap = (size_t)SM_PROTO_HEADER_LEN + c->limit;
  if (ncap > maxcap) ncap = maxcap > c->rcap ? maxcap : c->rcap + RBUF_MIN;
  return ncap;
}

/* Rule 2: the budget has no room for this buffer to grow: stop reading it until
 * sm_conn_budget makes room. */
static void budget_block(sm_server *s, sm_conn *c) {
  if (!c->budget_blocked) {
    c->budget_blocked = 1;
    s->n_budget_blocked++;
    sm_met_add(&sm_met.budget_blocks, 1);
  }
}

void sm_conn_on_readable(sm_server *s, sm_conn *c) {
  if (c->state == SM_CONN_LINGER) {
    uint8_t tmp[16384];
    for (;;) {
      ssize_t n = recv(c->fd, tmp, sizeof tmp, 0);
      if (n > 0) continue;
      if (n < 0 && errno == EINTR) continue;
      if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) return;
      sm_conn_close(s, c); /* EOF or error: the peer has seen everything */
      return;
    }
  }
  if (c->state != SM_CONN_OPEN) return;
  /* At most READ_SLICE bytes per event (level-triggered: the rest wakes us again), so a
   * peer that uploads at loopback speed cannot hold the loop while others wait. */
  size_t got = 0;
  for (int rounds = 0; rounds < 16 && got < READ_SLICE && c->state == SM_CONN_OPEN; rounds++) {
    if (c->budget_blocked || c->backlogged || (c->kind == SM_H_CONN && c->wq_bytes >= wq_cap(s)))
      break;
    if (!c->rbuf || c->rlen == c->rcap) {
      if (rbuf_resize(s, c, rbuf_next_cap(c))) {
        if (errno == ENOMEM) {
          sm_conn_fatal(s, c, SM_ST_OVERLOADED, 0, SHED_RETRY_MS, (uint32_t)(c->held >> 10),
                        "out of memory for the read buffer");
          return;
        }
        budget_block(s, c);
        break;
      }
    }
    size_t room = c->rcap - c->rlen;
    ssize_t n = recv(c->fd, c->rbuf + c->rlen, room < READ_SLICE ? room : READ_SLICE, 0);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) break;
    if (n <= 0) {
      sm_conn_close(s, c); /* EOF or reset: cancels the connection's jobs */
      return;
    }
    sm_met_add(&sm_met.bytes_in, (uint64_t)n);
    got += (size_t)n;
    uint64_t now = sm_srv_now_ns();
    if (c->rlen == 0) c->frame_start_ns = now;
    c->last_active_ns = now;
    c->rlen += (size_t)n;
    if (c->kind == SM_H_HTTP) return; /* handled by the loop */
    process(s, c);
  }
  if (c->fd >= 0) sm_conn_update_events(s, c);
}

void sm_conn_run_backlog(sm_server *s) {
  if (!s->n_backlogged) return;
  for (sm_conn *c = s->conns; c; c = c->next) {
    if (!c->backlogged) continue;
    if (c->state != SM_CONN_OPEN || c->fd < 0) {
      set_backlogged(s, c, 0);
      continue;
    }
    process(s, c); /* rule 1 may hold it instead: sm_conn_on_writable resumes it then */
    if (c->fd >= 0) sm_conn_update_events(s, c);
  }
}

void sm_conn_on_done(sm_server *s, sm_srv_out *o) {
  sm_job *j = o->job;
  sm_conn *c = j->conn;
  sm_wbuf *w = o->frames;
  if (c->state == SM_CONN_OPEN) {
    c->last_active_ns = sm_srv_now_ns();
    queue_frame(s, c, w);
    flush_now(s, c);
    sm_conn_update_events(s, c);
  } else {
    free(w);
  }
  if (o->final) {
    int i = inflight_find(c, j->rid);
    if (i >= 0) c->inflight[i] = c->inflight[--c->n_inflight];
    sm_met_sub(&sm_met.inflight, 1);
    release(s, &c->job_bytes, j->charged + sizeof *j);
    rmem_free(j->buf, j->buf_cap);
    free(j);
    if (c->state == SM_CONN_OPEN && s->draining) sm_conn_on_writable(s, c);
  }
  free(o);
}

void sm_conn_tick(sm_server *s, uint64_t now) {
  uint64_t idle = (uint64_t)s->cfg.idle_timeout_ms * 1000000ull;
  for (sm_conn *c = s->conns, *n; c; c = n) {
    n = c->next;
    if (c->state == SM_CONN_LINGER && now > c->linger_deadline_ns) {
      sm_conn_close(s, c);
      continue;
    }
    if (c->state == SM_CONN_FLUSH_CLOSE && now > c->last_active_ns + 30000000000ull) {
      sm_conn_close(s, c); /* the peer does not read its GOAWAY */
      continue;
    }
    if (c->state != SM_CONN_OPEN) continue;
    if (c->kind == SM_H_CONN && !c->hello_done &&
        now > c->born_ns + (uint64_t)SM_CONN_HELLO_TIMEOUT_MS * 1000000ull) {
      sm_conn_fatal(s, c, SM_ST_TIMEOUT, 0, 0, SM_CONN_HELLO_TIMEOUT_MS,
                    "HELLO not completed in time");
      continue;
    }
    if (!idle) continue;
    if (c->rlen > 0 && now > c->frame_start_ns + idle) {
      sm_conn_fatal(s, c, SM_ST_TIMEOUT, 0, 0, s->cfg.idle_timeout_ms,
                    "frame not completed within the idle timeout");
    } else if (c->rlen == 0 && c->n_inflight == 0 && !c->wq_head &&
               now > c->last_active_ns + idle) {
      sm_conn_fatal(s, c, SM_ST_TIMEOUT, 0, 0, s->cfg.idle_timeout_ms, "idle timeout");
    }
  }
}

/* ------------------------------------------------------------------ budget and limits */

/* The connection whose closing gives back the most: its buffers and its jobs' bodies
 * (freed when the cancelled jobs stop). NULL if none holds anything. */
static sm_conn *greediest(sm_server *s) {
  sm_conn *g = NULL;
  size_t most = 0;
  for (sm_conn *c = s->conns; c; c = c->next) {
    if (c->state == SM_CONN_DEAD || c->held + c->job_bytes <= most) continue;
    if (c->state != SM_CONN_OPEN && c->held == 0) continue; /* its jobs are cancelled */
    g = c;
    most = c->held + c->job_bytes;
  }
  return g;
}

static void shed(sm_server *s, sm_conn *c) {
  sm_met_add(&sm_met.shed_budget, 1);
  if (c->state != SM_CONN_OPEN) { /* already closing (its GOAWAY is not read): now */
    sm_conn_close(s, c);
    return;
  }
  uint32_t kib = (uint32_t)((c->held + c->job_bytes) >> 10);
  wq_drop_unsent(s, c);
  rbuf_free(s, c);
  sm_conn_fatal(s, c, SM_ST_OVERLOADED, 0, SHED_RETRY_MS, kib,
                "server buffer budget exhausted; this connection held the most");
}

/* Room for c's read buffer to grow as it wants. */
static int room_for(const sm_server *s, const sm_conn *c) {
  size_t want = rmem_cost(rmem_cap(rbuf_next_cap(c))) - rmem_cost(c->rcap);
  return s->buf_used + want <= s->cfg.buffer_budget;
}

void sm_conn_budget(sm_server *s) {
  for (int guard = 0; guard < 1024; guard++) {
    int starved = 0;
    if (s->n_budget_blocked)
      for (sm_conn *c = s->conns; c && !starved; c = c->next)
        starved = c->budget_blocked && !room_for(s, c);
    if (s->buf_used <= s->cfg.buffer_budget && !starved) break;
    sm_conn *g = greediest(s);
    if (!g) break; /* what is left is held by cancelled jobs: they free it soon */
    shed(s, g);
  }
  if (!s->n_budget_blocked) return;
  for (sm_conn *c = s->conns; c; c = c->next)
    if (c->budget_blocked && room_for(s, c)) {
      c->budget_blocked = 0;
      s->n_budget_blocked--;
      sm_conn_update_events(s, c); /* level-triggered: its pending bytes wake it */
    }
}

int sm_conn_evict_idle(sm_server *s, uint64_t now) {
  /* First a connection that never said HELLO (a good client says it at once), then one
   * idle after HELLO; the oldest of its kind. */
  sm_conn *best = NULL;
  int best_rank = 0;
  uint64_t best_t = 0;
  for (sm_conn *c = s->conns; c; c = c->next) {
    if (c->kind != SM_H_CONN || c->state != SM_CONN_OPEN) continue;
    int rank = 0;
    uint64_t t = 0;
    if (!c->hello_done && now >= c->born_ns + SM_CONN_HELLO_GRACE_MS * 1000000ull) {
      rank = 2;
      t = c->born_ns;
    } else if (c->hello_done && !c->n_inflight && !c->wq_head && !c->rlen &&
               now >= c->last_active_ns + SM_CONN_IDLE_EVICT_MS * 1000000ull) {
      rank = 1;
      t = c->last_active_ns;
    }
    if (rank > best_rank || (rank && rank == best_rank && t < best_t)) {
      best = c;
      best_rank = rank;
      best_t = t;
    }
  }
  if (!best) return 0;
  sm_met_add(&sm_met.shed_idle, 1);
  sm_conn_fatal(s, best, SM_ST_TOO_MANY_CONNECTIONS, 0, SHED_RETRY_MS,
                (uint32_t)s->cfg.max_conns,
                best_rank == 2 ? "connection limit reached: closed for a newer one (no HELLO)"
                               : "connection limit reached: closed for a newer one (idle)");
  return 1;
}
