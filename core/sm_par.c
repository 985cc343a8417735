#include "sm_par.h"

#include <pthread.h>
#include <stdatomic.h>

typedef struct par_run {
  void (*fn)(void *ctx, int i);
  void *ctx;
  int n;
  atomic_int next;
} par_run;

static void *par_worker(void *arg) {
  par_run *r = arg;
  for (int i; (i = atomic_fetch_add(&r->next, 1)) < r->n;) r->fn(r->ctx, i);
  return NULL;
}

void sm_par_for(int n, int threads, void (*fn)(void *ctx, int i), void *ctx) {
  par_run r = {.fn = fn, .ctx = ctx, .n = n};
  atomic_init(&r.next, 0);
  if (threads > SM_PAR_MAX_THREADS) threads = SM_PAR_MAX_THREADS;
  if (threads > n) threads = n;
  pthread_t th[SM_PAR_MAX_THREADS];
  int started = 0;
  while (started + 1 < threads && !pthread_create(&th[started], NULL, par_worker, &r)) started++;
  par_worker(&r);
  for (int t = 0; t < started; t++) pthread_join(th[t], NULL);
}
