/* sm_srv.c: the daemon-wide pieces every server module may use (sm_srv.h): the
 * configuration defaults, the monotonic clock and the signal flag. They live here, not in
 * main.c, so that a module depends on this small file and never on the program's entry
 * point (and a test or a fuzz harness can link the modules without main). */
#include "sm_srv.h"

#include "sm_multires.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

volatile sig_atomic_t sm_srv_signal_flag = 0;

uint64_t sm_srv_now_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

void sm_srv_config_default(sm_srv_config *c) {
  memset(c, 0, sizeof *c);
  snprintf(c->bind, sizeof c->bind, "127.0.0.1");
  c->port = 7878;
  const char *xdg = getenv("XDG_STATE_HOME"), *home = getenv("HOME");
  if (xdg && *xdg) snprintf(c->data_dir, sizeof c->data_dir, "%s/shapematch", xdg);
  else snprintf(c->data_dir, sizeof c->data_dir, "%s/.local/state/shapematch", home ? home : ".");
  long nc = sysconf(_SC_NPROCESSORS_ONLN);
  c->threads = nc > 0 ? (int)nc : 1;
  c->cache_bytes = 1024ull << 20;
  c->buffer_budget = 1024ull << 20;
  c->max_payload = 256u << 20;
  c->max_vertices = 2000000;
  c->max_faces = 4000000;
  c->max_inflight = 64;
  c->max_batch_items = 1024;
  c->max_query_k = 1000;
  c->max_k = 500;
  c->idle_timeout_ms = 300000;
  c->drain_ms = 10000;
  c->max_conns = 1024;
  c->queue_len = 1024;
  c->metrics_port = 0;
  c->default_k = 100;
  c->prepare_timeout_ms = 300000;
  c->prepare_on_put = 1;
  c->max_components = 64;
  c->multires_coarse_nv = SM_MULTIRES_COARSE_NV; /* as the local match */
}
