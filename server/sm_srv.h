/* sm_srv: the daemon's shared configuration and top-level state.
 *
 * DESIGN (threads and locks; memcached doc/threads.txt style)
 *   Threads
 *     - the loop thread (main): epoll loop, every socket, every sm_conn, the in-flight
 *       tables, and the requests answered inline (HELLO/PING/STATS/HAS/DROP/CANCEL: the
 *       opcodes without SM_OPF_QUEUED in sm_proto.h's table);
 *     - N worker threads (sm_srv_pool): the queued ones (PUT_SHAPE, PREPARE, MATCH,
 *       DISTANCE, QUERY, BATCH).
 *       A worker never touches an sm_conn: it reads its job (an owned copy of the request)
 *       and posts encoded response frames back through the pool's done list + eventfd.
 *       BATCH items and QUERY candidates run as units on several workers at once
 *       (sm_srv_exec fan-out); they share the request's job read-only, except atomics;
 *     - a MATCH or DISTANCE borrows the pool's idle cores (sm_pool_borrow, at most
 *       SM_SRV_MATCH_THREADS in all): core threads of that match (sm_par, the tip
 *       search), started and joined inside sm_match, touching the match's own data and the
 *       shapes' internally locked caches (sm_match.h);
 *       a lone request on an idle daemon runs as fast as the local CLI's two-thread
 *       match, and a busy daemon lends nothing (one thread per request, as before);
 *     - no other thread. Signal handlers only set sm_srv_signal_flag.
 *   Locks (in the only order they may nest; never hold one while blocking on I/O to a peer)
 *     1. store->mu   (sm_srv_store: index, prepared-shape cache, LRU, single-flight state;
 *                     condition variable store->cv for single-flight waiters)
 *     2. pool->mu    (sm_srv_pool: job queue; cv for idle workers)
 *     3. pool->done_mu (completion list; the loop drains it after the eventfd fires)
 *     In practice none of them nests: each is taken and released within one function.
 *   Inside core/, what workers run in parallel: basis computations (the eigensolver,
 *     sm_eigs.h, has no global state since issue 13: N workers run N eigensolves at once),
 *     descriptors, Sinkhorn, ZoomOut's BLAS. One process-wide lock remains: FLANN's C API
 *     (sm_knn.c, its global logger), held for each kd-tree build/query/free, so the
 *     kd-tree nearest-neighbour queries of concurrent matches take turns.
 *   Atomics: sm_metrics counters (relaxed), job->cancel (set by the loop on CANCEL or
 *   disconnect or drain timeout, read by the core's cancel callback on a worker).
 *   Lifetime: a job holds a plain pointer to its connection, used only by the loop thread
 *   when the job's completion arrives; a closed connection stays allocated (fd closed)
 *   until its last job has completed.
 */
#ifndef SM_SRV_H
#define SM_SRV_H

#include <signal.h>
#include <stdatomic.h>
#include <stddef.h>
#include <stdint.h>

#define SM_SRV_PATH_MAX 4096

typedef struct sm_srv_config {
  char bind[64];            /* --bind, default 127.0.0.1 */
  int port;                 /* --port, 0 = ephemeral */
  char data_dir[SM_SRV_PATH_MAX];
  int threads;              /* --threads, default = cores */
  uint64_t cache_bytes;     /* --cache-mb: in-memory prepared shapes */
  uint64_t buffer_budget;   /* --buffer-budget-mb: every connection's buffered bytes (read
                               buffers, queued answers, request bodies held by jobs) */
  uint32_t max_payload;     /* --max-payload-mb */
  uint32_t max_vertices, max_faces;
  uint32_t max_inflight, max_batch_items, max_query_k, max_k;
  uint32_t idle_timeout_ms; /* 0 = none */
  uint32_t drain_ms;        /* graceful shutdown budget */
  int max_conns;
  int queue_len;            /* bounded job queue; full = BUSY */
  int metrics_port;         /* 0 = off */
  int default_k;            /* server default basis size (PROTOCOL.md: 100) */
  uint32_t prepare_timeout_ms; /* bound on one shape's preparation; 0 = none */
  uint32_t max_components;  /* PUT refuses meshes with more connected components */
  int multires_coarse_nv;   /* MATCH's multi-resolution path: vertices of the coarse level
                               (default SM_MULTIRES_COARSE_NV) */
  int prepare_on_put;       /* --prepare-on-put 0|1 (default 1): PUT_SHAPE queues the shape's
                               preparation as a background job (sm_srv_exec.c) */
  uint8_t token[256];
  size_t token_len;
  int has_token;
} sm_srv_config;

void sm_srv_config_default(sm_srv_config *c);

struct sm_store;
struct sm_pool;
struct sm_conn;

/* Loop-thread state (workers read cfg and use store/pool only). */
typedef struct sm_server {
  sm_srv_config cfg;
  struct sm_store *store;
  struct sm_pool *pool;
  int epfd;
  struct sm_conn *conns;    /* every connection not yet freed (incl. closed ones) */
  int n_active;             /* connections counted against max_conns */
  uint64_t next_conn_id;
  int draining;             /* SIGTERM/SIGINT seen: GOAWAY sent, no accepts */
  uint64_t drain_deadline_ns;
  int cancelled_all;        /* drain budget spent: every job's cancel flag set */
  /* The buffer budget (sm_srv_conn.h, "Memory"): bytes charged now, the most since the
   * last malloc_trim, and connections whose reading waits for the budget. */
  uint64_t buf_used, buf_trim_mark;
  int n_budget_blocked;
  int n_backlogged;         /* connections with frames left for their next turn */
  /* Set once the loop has ended: background preparations still queued return at once and
   * running ones are cancelled (their cancel callback reads it on a worker). */
  _Atomic int bg_stop;
} sm_server;

/* sm_srv.c (not main.c, so no module depends on the program's entry point). */
/* Set by the SIGTERM/SIGINT handler; the loop polls it. */
extern volatile sig_atomic_t sm_srv_signal_flag;

/* Monotonic clock in nanoseconds / microseconds. */
uint64_t sm_srv_now_ns(void);

#endif
