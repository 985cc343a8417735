/* sm_srv_metrics: process-wide counters and gauges, rendered as STATS records (wire) and
 * as Prometheus text (/metrics on the loopback --metrics-port; /healthz answers "ok").
 *
 * Contract: one global sm_metrics (sm_met); every field is an atomic updated with
 * relaxed ordering from any thread (values are statistics, never used for control).
 * Rendering allocates the returned buffer (caller frees); it reads the store's own
 * counters through sm_store_stats (store lock taken briefly). */
#ifndef SM_SRV_METRICS_H
#define SM_SRV_METRICS_H

#include <stdatomic.h>
#include <stddef.h>
#include <stdint.h>

#include "sm_proto.h"

typedef struct sm_metrics {
  _Atomic uint64_t connections, connections_total, connections_rejected;
  _Atomic uint64_t requests, errors, fatal_errors, busy;
  _Atomic uint64_t inflight, queue_depth;
  _Atomic uint64_t bytes_in, bytes_out;
  _Atomic uint64_t cancelled, deadlines;
  _Atomic uint64_t req_us_sum, req_count; /* compute request latency (worker jobs) */
  _Atomic uint64_t fanout_units;          /* BATCH items and QUERY candidates run as units */
  _Atomic uint64_t fanout_workers_max;    /* most distinct workers one request's units ran on */
  _Atomic uint64_t lat_bucket[8];         /* <= 1ms,10ms,100ms,1s,10s,100s,+Inf (7 used) */
  /* The buffer budget (sm_srv_conn.h, "Memory"); written by the loop thread only. */
  _Atomic uint64_t buffered, buffered_peak, buffer_budget;
  _Atomic uint64_t read_pauses;           /* a connection's reading paused (answers unread) */
  _Atomic uint64_t budget_blocks;         /* a read buffer could not grow: budget exhausted */
  _Atomic uint64_t shed_budget;           /* connections closed with OVERLOADED */
  _Atomic uint64_t shed_idle;             /* idle connections closed to admit a new one */
  /* PUT_SHAPE's background preparations (sm_srv_exec.c): queued; not queued (queue full
   * or off); that computed or loaded something; that failed (kept for the next request);
   * cancelled (shutdown, --prepare-timeout-ms) */
  _Atomic uint64_t bg_queued, bg_skipped, bg_prepared, bg_failed, bg_cancelled;
  uint64_t start_ns;
} sm_metrics;

extern sm_metrics sm_met;

static inline void sm_met_add(_Atomic uint64_t *c, uint64_t v) {
  atomic_fetch_add_explicit(c, v, memory_order_relaxed);
}
static inline void sm_met_sub(_Atomic uint64_t *c, uint64_t v) {
  atomic_fetch_sub_explicit(c, v, memory_order_relaxed);
}
static inline uint64_t sm_met_get(_Atomic uint64_t *c) {
  return atomic_load_explicit(c, memory_order_relaxed);
}
void sm_met_latency(uint64_t us);
static inline void sm_met_max(_Atomic uint64_t *c, uint64_t v) {
  uint64_t o = atomic_load_explicit(c, memory_order_relaxed);
  while (o < v && !atomic_compare_exchange_weak_explicit(c, &o, v, memory_order_relaxed,
                                                          memory_order_relaxed)) {
  }
}

struct sm_store;
/* Fills up to cap records (names per PROTOCOL.md 5.3 plus store counters); returns count. */
uint32_t sm_met_stats(struct sm_store *st, sm_proto_stat *out, uint32_t cap);
/* Prometheus text exposition of the same values. malloc'd, NUL-terminated. */
char *sm_met_prometheus(struct sm_store *st, size_t *len);
/* Builds a complete HTTP/1.0 response for a request head (method + path parsed);
 * malloc'd. ready: 0 while draining (healthz says so). */
char *sm_met_http(struct sm_store *st, const char *req, size_t req_len, int ready,
                  size_t *len);

#endif
