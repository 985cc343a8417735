#include "sm_srv_metrics.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "sm_srv.h"
#include "sm_srv_store.h"

sm_metrics sm_met;

static const uint64_t lat_edges_us[7] = {1000, 10000, 100000, 1000000, 10000000, 100000000,
                                         UINT64_MAX};

void sm_met_latency(uint64_t us) {
  sm_met_add(&sm_met.req_us_sum, us);
  sm_met_add(&sm_met.req_count, 1);
  for (int i = 0; i < 7; i++)
    if (us <= lat_edges_us[i]) {
      sm_met_add(&sm_met.lat_bucket[i], 1);
      break;
    }
}

static void put(sm_proto_stat *out, uint32_t cap, uint32_t *n, const char *name, uint64_t v) {
  if (*n >= cap) return;
  snprintf(out[*n].name, sizeof out[*n].name, "%s", name);
  out[*n].value = v;
  (*n)++;
}

uint32_t sm_met_stats(struct sm_store *st, sm_proto_stat *out, uint32_t cap) {
  sm_store_stats ss;
  sm_store_get_stats(st, &ss);
  uint32_t n = 0;
  put(out, cap, &n, "shapes", ss.shapes);
  put(out, cap, &n, "shapes_bytes", ss.shapes_bytes);
  put(out, cap, &n, "bases_cached", ss.bases_cached);
  put(out, cap, &n, "connections", sm_met_get(&sm_met.connections));
  put(out, cap, &n, "inflight", sm_met_get(&sm_met.inflight));
  put(out, cap, &n, "queue_depth", sm_met_get(&sm_met.queue_depth));
  put(out, cap, &n, "requests", sm_met_get(&sm_met.requests));
  put(out, cap, &n, "errors", sm_met_get(&sm_met.errors));
  put(out, cap, &n, "uptime_s", (sm_srv_now_ns() - sm_met.start_ns) / 1000000000ull);
  put(out, cap, &n, "busy", sm_met_get(&sm_met.busy));
  put(out, cap, &n, "cancelled", sm_met_get(&sm_met.cancelled));
  put(out, cap, &n, "fanout_units", sm_met_get(&sm_met.fanout_units));
  put(out, cap, &n, "fanout_workers_max", sm_met_get(&sm_met.fanout_workers_max));
  put(out, cap, &n, "cache_bytes", ss.cache_bytes);
  put(out, cap, &n, "cache_hits", ss.cache_hits);
  put(out, cap, &n, "cache_misses", ss.cache_misses);
  put(out, cap, &n, "cache_evictions", ss.evictions);
  put(out, cap, &n, "singleflight_waits", ss.singleflight_waits);
  put(out, cap, &n, "prepares", ss.prepares);
  put(out, cap, &n, "prepares_concurrent_max", ss.prepares_concurrent_max);
  put(out, cap, &n, "bases_computed", ss.bases_computed);
  put(out, cap, &n, "bases_loaded", ss.bases_loaded);
  put(out, cap, &n, "bases_corrupt", ss.bases_corrupt);
  put(out, cap, &n, "shapes_corrupt", ss.shapes_corrupt);
  put(out, cap, &n, "connections_rejected", sm_met_get(&sm_met.connections_rejected));
  put(out, cap, &n, "buffered_bytes", sm_met_get(&sm_met.buffered));
  put(out, cap, &n, "buffered_peak", sm_met_get(&sm_met.buffered_peak));
  put(out, cap, &n, "buffer_budget", sm_met_get(&sm_met.buffer_budget));
  put(out, cap, &n, "read_pauses", sm_met_get(&sm_met.read_pauses));
  put(out, cap, &n, "budget_blocks", sm_met_get(&sm_met.budget_blocks));
  put(out, cap, &n, "shed_overloaded", sm_met_get(&sm_met.shed_budget));
  put(out, cap, &n, "shed_idle", sm_met_get(&sm_met.shed_idle));
  put(out, cap, &n, "put_prepares_queued", sm_met_get(&sm_met.bg_queued));
  put(out, cap, &n, "put_prepares_skipped", sm_met_get(&sm_met.bg_skipped));
  put(out, cap, &n, "put_prepares_done", sm_met_get(&sm_met.bg_prepared));
  put(out, cap, &n, "put_prepares_failed", sm_met_get(&sm_met.bg_failed));
  put(out, cap, &n, "put_prepares_cancelled", sm_met_get(&sm_met.bg_cancelled));
  return n;
}

char *sm_met_prometheus(struct sm_store *st, size_t *len) {
  sm_proto_stat s[64];
  uint32_t n = sm_met_stats(st, s, 64);
  size_t cap = 8192;
  char *b = malloc(cap);
  if (!b) return NULL;
  size_t o = 0;
  for (uint32_t i = 0; i < n && o < cap; i++)
    o += (size_t)snprintf(b + o, cap - o, "# TYPE shapematch_%s gauge\nshapematch_%s %llu\n",
                          s[i].name, s[i].name, (unsigned long long)s[i].value);
  static const char *le[7] = {"0.001", "0.01", "0.1", "1", "10", "100", "+Inf"};
  if (o < cap)
    o += (size_t)snprintf(b + o, cap - o, "# TYPE shapematch_request_seconds histogram\n");
  uint64_t acc = 0;
  for (int i = 0; i < 7 && o < cap; i++) {
    acc += sm_met_get(&sm_met.lat_bucket[i]);
    o += (size_t)snprintf(b + o, cap - o, "shapematch_request_seconds_bucket{le=\"%s\"} %llu\n",
                          le[i], (unsigned long long)acc);
  }
  if (o < cap)
    o += (size_t)snprintf(b + o, cap - o,
                          "shapematch_request_seconds_sum %.6f\nshapematch_request_seconds_count %llu\n",
                          (double)sm_met_get(&sm_met.req_us_sum) / 1e6,
                          (unsigned long long)sm_met_get(&sm_met.req_count));
  if (o >= cap) o = cap - 1;
  b[o] = 0;
  *len = o;
  return b;
}

char *sm_met_http(struct sm_store *st, const char *req, size_t req_len, int ready,
                  size_t *len) {
  const char *status = "404 Not Found", *ctype = "text/plain";
  char *body = NULL;
  size_t blen = 0;
  int is_get = req_len >= 4 && !memcmp(req, "GET ", 4);
  const char *path = is_get ? req + 4 : "";
  size_t plen = 0;
  while (is_get && 4 + plen < req_len && path[plen] != ' ' && path[plen] != '\r') plen++;
  if (!is_get) {
    status = "405 Method Not Allowed";
  } else if (plen == 8 && !memcmp(path, "/metrics", 8)) {
    status = "200 OK";
    ctype = "text/plain; version=0.0.4";
    body = sm_met_prometheus(st, &blen);
  } else if (plen == 8 && !memcmp(path, "/healthz", 8)) {
    status = "200 OK";
  } else if (plen == 7 && !memcmp(path, "/readyz", 7)) {
    status = ready ? "200 OK" : "503 Service Unavailable";
  }
  const char *txt = body ? body : !strncmp(status, "200", 3) ? "ok\n"
                                  : !strncmp(status, "503", 3) ? "draining\n" : "not found\n";
  if (!body) blen = strlen(txt);
  size_t cap = blen + 256;
  char *out = malloc(cap);
  if (out) {
    int h = snprintf(out, cap, "HTTP/1.0 %s\r\nContent-Type: %s\r\nContent-Length: %zu\r\n"
                     "Connection: close\r\n\r\n", status, ctype, blen);
    memcpy(out + h, txt, blen);
    *len = (size_t)h + blen;
  }
  free(body);
  return out;
}
