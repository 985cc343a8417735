#include "sm_par.h"

#include <pthread.h>
#include <stdatomic.h>
#include <stdlib.h>

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#define CPU_RELAX() _mm_pause()
#else
#define CPU_RELAX() ((void)0)
#endif

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

/* ---- team --------------------------------------------------------------------------- */

/* Spin iterations before sleeping (a few tens of microseconds): an iterative solver's
 * next loop usually comes sooner than that, and a futex wake-up costs about as much. */
#define TEAM_SPIN 2000

struct sm_team {
  pthread_mutex_t mu;
  pthread_cond_t go, done;
  atomic_uint gen;    /* loops started; helpers run the loop whose number they see */
  atomic_int active;  /* helpers not yet finished with the current loop */
  atomic_int stop;
  par_run *run;       /* the current loop (written before gen is advanced) */
  int nhelp;
  pthread_t th[SM_PAR_MAX_THREADS];
};

static void *team_helper(void *arg) {
  sm_team *t = arg;
  unsigned seen = 0;
  for (;;) {
    for (int s = 0; s < TEAM_SPIN && atomic_load(&t->gen) == seen && !atomic_load(&t->stop);
         s++)
      CPU_RELAX();
    pthread_mutex_lock(&t->mu);
    while (atomic_load(&t->gen) == seen && !atomic_load(&t->stop))
      pthread_cond_wait(&t->go, &t->mu);
    par_run *r = t->run;
    pthread_mutex_unlock(&t->mu);
    if (atomic_load(&t->stop)) return NULL;
    seen++;
    par_worker(r);
    if (atomic_fetch_sub(&t->active, 1) == 1) {
      pthread_mutex_lock(&t->mu);
      pthread_cond_signal(&t->done);
      pthread_mutex_unlock(&t->mu);
    }
  }
}

sm_team *sm_team_new(int threads) {
  if (threads > SM_PAR_MAX_THREADS) threads = SM_PAR_MAX_THREADS;
  if (threads <= 1) return NULL;
  sm_team *t = calloc(1, sizeof *t);
  if (!t) return NULL;
  pthread_mutex_init(&t->mu, NULL);
  pthread_cond_init(&t->go, NULL);
  pthread_cond_init(&t->done, NULL);
  atomic_init(&t->gen, 0);
  atomic_init(&t->active, 0);
  atomic_init(&t->stop, 0);
  while (t->nhelp + 1 < threads && !pthread_create(&t->th[t->nhelp], NULL, team_helper, t))
    t->nhelp++;
  if (t->nhelp == 0) {
    sm_team_free(t);
    return NULL;
  }
  return t;
}

int sm_team_threads(const sm_team *t) { return t ? t->nhelp + 1 : 1; }

void sm_team_for(sm_team *t, int n, void (*fn)(void *ctx, int i), void *ctx) {
  par_run r = {.fn = fn, .ctx = ctx, .n = n};
  atomic_init(&r.next, 0);
  if (!t || n <= 1) {
    par_worker(&r);
    return;
  }
  pthread_mutex_lock(&t->mu);
  t->run = &r;
  atomic_store(&t->active, t->nhelp);
  atomic_fetch_add(&t->gen, 1);
  pthread_cond_broadcast(&t->go);
  pthread_mutex_unlock(&t->mu);
  par_worker(&r);
  /* r lives on this stack: wait until every helper is done with it */
  for (int s = 0; s < TEAM_SPIN && atomic_load(&t->active) > 0; s++) CPU_RELAX();
  pthread_mutex_lock(&t->mu);
  while (atomic_load(&t->active) > 0) pthread_cond_wait(&t->done, &t->mu);
  pthread_mutex_unlock(&t->mu);
}

void sm_team_free(sm_team *t) {
  if (!t) return;
  pthread_mutex_lock(&t->mu);
  atomic_store(&t->stop, 1);
  pthread_cond_broadcast(&t->go);
  pthread_mutex_unlock(&t->mu);
  for (int i = 0; i < t->nhelp; i++) pthread_join(t->th[i], NULL);
  pthread_cond_destroy(&t->go);
  pthread_cond_destroy(&t->done);
  pthread_mutex_destroy(&t->mu);
  free(t);
}
