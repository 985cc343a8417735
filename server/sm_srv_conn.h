/* sm_srv_conn: one client connection and its frame handling (PROTOCOL.md sections 2-5),
 * on the loop thread. The job it hands to a worker is sm_srv_job.h's.
 *
 * Contract
 *   - Everything here runs on the loop thread (a worker owns a job between sm_pool_submit
 *     and its final sm_srv_out: sm_srv_job.h).
 *   - Read side: c->rbuf holds the bytes of the current (partial) frames. The header is
 *     validated from its 24 bytes (sm_proto_parse_header against c->limit: 4096 before
 *     HELLO, then max_payload) before the buffer grows for the payload, so an oversize
 *     frame costs nothing. A connection-fatal condition queues one GOAWAY frame carrying
 *     the status, stops reading, cancels the connection's jobs, and closes after the
 *     frame is flushed (half-close, then a short lingering read so the peer sees it).
 *   - Write side: a FIFO of encoded frames (sm_wbuf), flushed when the socket is writable;
 *     small frames are packed into shared chunks (a PING answer costs 32 bytes, not a malloc).
 *   - Memory (the buffer budget, cfg.buffer_budget, default 1 GiB on top of the cache).
 *     Every byte buffered for a peer is charged to its connection and to s->buf_used: read
 *     buffer capacity, queued answer chunks, and request bodies held by jobs until the job
 *     ends, and the connection's own struct and in-flight table while it exists. Three
 *     rules keep the total bounded:
 *       1. back-pressure: no frame is read or handled while the connection's unsent answers
 *          exceed SM_CONN_WQ_HIGH (SM_CONN_WQ_TIGHT once half the budget is used); the
 *          buffered frames resume when the peer reads. A peer that pipelines without
 *          reading stops being read: its requests wait in the kernel, not here;
 *       2. a read buffer grows with the bytes that arrive (never to a frame's declared size
 *          at once), and only within the budget; a connection whose buffer cannot grow
 *          stops being read until sm_conn_budget finds room;
 *       3. sm_conn_budget (loop, after each event batch): while the budget is exceeded or
 *          reading is blocked on it, the connection holding the most bytes is closed with
 *          GOAWAY OVERLOADED (detail: the KiB it held), its unsent answers dropped.
 *     Buffers are freed as soon as they drain; the loop calls malloc_trim after a burst.
 *     The kernel's send buffer of a connection is fixed at SM_CONN_SNDBUF (256 KiB as the
 *     kernel counts it) instead of growing to tcp_wmem's 4 MiB: rule 1 sees only what the
 *     kernel did not take, so a peer that never reads otherwise made the loop compute
 *     4 MiB more answers (and the kernel hold them) before its reading paused. 256 KiB
 *     covers a 10 Gb/s LAN's bandwidth-delay product; a far peer's large answers flow
 *     more slowly.
 *   - Fairness between connections: one event handles at most SM_CONN_FRAME_SLICE frames
 *     of a connection. Complete frames left in its buffer make it "backlogged": it is not
 *     read meanwhile, and sm_conn_run_backlog (loop, after each event batch, which then
 *     polls without waiting) gives it its next slice. So a peer pipelining thousands of
 *     requests gets its answers in turns with everyone else instead of holding the loop
 *     for all of them while another client's PING or finished DISTANCE waits.
 *   - Connection limit: at max_conns a new connection evicts the oldest idle one
 *     (sm_conn_evict_idle: no HELLO after SM_CONN_HELLO_GRACE_MS, or nothing pending for
 *     SM_CONN_IDLE_EVICT_MS) before it is refused; a HELLO not completed within
 *     SM_CONN_HELLO_TIMEOUT_MS closes the connection (TIMEOUT).
 *   - In-flight table: request ids of jobs not finished (PROTOCOL.md: a reused id is a
 *     PROTOCOL_ERROR; CANCEL looks targets up here). A closed connection is freed only
 *     when its table is empty.
 */
#ifndef SM_SRV_CONN_H
#define SM_SRV_CONN_H

#include <stddef.h>
#include <stdint.h>

#include "sm_proto.h"
#include "sm_srv.h"
#include "sm_srv_job.h"

#define SM_CONN_WQ_HIGH (256u << 10)  /* unsent answers that pause reading */
#define SM_CONN_WQ_TIGHT (16u << 10)  /* the same once half the budget is used */
#define SM_CONN_FRAME_SLICE 32        /* frames of one connection handled per turn */
#define SM_CONN_SNDBUF (128 << 10)     /* SO_SNDBUF of a connection (the kernel doubles it) */
#define SM_CONN_HELLO_GRACE_MS 1000u
#define SM_CONN_IDLE_EVICT_MS 10000u
#define SM_CONN_HELLO_TIMEOUT_MS 10000u

enum { SM_H_LISTEN = 1, SM_H_METRICS_LISTEN, SM_H_EVENTFD, SM_H_CONN, SM_H_HTTP };
enum { SM_CONN_OPEN = 0, SM_CONN_FLUSH_CLOSE, SM_CONN_LINGER, SM_CONN_DEAD };

typedef struct sm_conn {
  int kind; /* SM_H_CONN or SM_H_HTTP: first member, the epoll data points here */
  int fd;
  uint64_t id;
  char peer[64];
  int state;
  uint32_t ev_mask; /* registered epoll events */
  uint8_t *rbuf;
  size_t rlen, rcap;
  size_t rneed;          /* size of the frame being received, once its header is valid */
  sm_wbuf *wq_head, *wq_tail;
  size_t wq_bytes;       /* unsent bytes */
  size_t held;           /* charged to the budget: rcap + the queue's allocations */
  size_t job_bytes;      /* charged to the budget: bodies held by this connection's jobs */
  size_t own;            /* charged to the budget: this struct and its in-flight table */
  int read_paused;       /* rule 1: answers unread */
  int budget_blocked;    /* rule 2: the read buffer could not grow */
  int backlogged;        /* complete frames wait for the next turn (fairness) */
  int hello_done;
  uint8_t version;       /* of every frame: SM_PROTO_VERSION_HELLO, then the negotiated one */
  uint32_t limit;        /* current max payload */
  uint32_t max_response; /* client's limit, 0 = none */
  int goaway_sent;
  uint64_t born_ns, last_active_ns, frame_start_ns, linger_deadline_ns;
  sm_job **inflight; /* max_inflight slots */
  uint32_t n_inflight;
  struct sm_conn *prev, *next;
} sm_conn;

sm_conn *sm_conn_new(sm_server *s, int fd, int kind, const char *peer);
/* Reads what is available and handles complete frames. */
void sm_conn_on_readable(sm_server *s, sm_conn *c);
/* Flushes the write queue; advances the closing states. */
void sm_conn_on_writable(sm_server *s, sm_conn *c);
/* Queues one frame (or a chain from a worker) for sending; charged to the budget; frees
 * it if the connection is closed. */
void sm_conn_queue(sm_server *s, sm_conn *c, sm_wbuf *w);
/* Rule 3 of "Memory": sheds the greediest connections while over the budget, and resumes
 * reading on connections blocked by it once there is room. Loop thread, between batches. */
void sm_conn_budget(sm_server *s);
/* At max_conns: closes the oldest idle connection (GOAWAY TOO_MANY_CONNECTIONS) so that a
 * new one fits. Returns 1 if one was closed, 0 if none qualifies. */
int sm_conn_evict_idle(sm_server *s, uint64_t now);
/* Hands a worker's frames to their connection (or drops them if it is closed). */
void sm_conn_on_done(sm_server *s, sm_srv_out *o);
/* Periodic: timeouts, lingering closes, drain. */
void sm_conn_tick(sm_server *s, uint64_t now);
/* Connection-fatal: one GOAWAY with status, then close. */
void sm_conn_fatal(sm_server *s, sm_conn *c, uint16_t status, uint32_t rid, uint32_t retry,
                   uint32_t detail, const char *msg);
/* Graceful GOAWAY (status 0) at drain start. */
void sm_conn_goaway(sm_server *s, sm_conn *c);
/* Closes the socket now; the struct lives until its jobs are done and sm_conn_sweep
 * (called by the loop between event batches, so no event of the current batch can
 * point to freed memory) frees it. */
void sm_conn_close(sm_server *s, sm_conn *c);
void sm_conn_sweep(sm_server *s);
/* Fairness: one more slice of frames for every backlogged connection. Loop thread, after
 * each event batch; while s->n_backlogged > 0 the loop polls without waiting. */
void sm_conn_run_backlog(sm_server *s);
void sm_conn_update_events(sm_server *s, sm_conn *c);
/* Sets every in-flight job's cancel flag to v. */
void sm_conn_cancel_all(sm_conn *c, int v);
/* Queues an error frame (request-level status). */
void sm_conn_send_error(sm_server *s, sm_conn *c, uint8_t opcode, uint32_t rid,
                        uint16_t status, uint32_t retry, uint32_t detail, const char *msg);

#endif
