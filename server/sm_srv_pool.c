#include "sm_srv_pool.h"

#include <cblas.h> /* OpenBLAS: openblas_set_num_threads */
#include <errno.h>
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include "sm_eigs.h"
#include "sm_srv_metrics.h"

struct sm_pool {
  pthread_mutex_t mu;
  pthread_cond_t cv;
  sm_pool_job *head, *tail;
  int depth, cap, stop;
  sm_pool_job *bhead, *btail; /* background queue (sm_srv_pool.h) */
  int bdepth, bcap, bmax, brunning;
  int running; /* workers inside a job's run(), request or background */
  int lent;    /* cores lent to running jobs (sm_pool_borrow) */
  pthread_t *th;
  int nth;
  pthread_mutex_t done_mu;
  sm_pool_msg *dhead, *dtail;
  int efd;
};

static _Thread_local int tl_worker = -1;

int sm_pool_worker_index(void) { return tl_worker; }

typedef struct worker_arg {
  sm_pool *p;
  int index;
} worker_arg;

static void *worker(void *arg) {
  worker_arg wa = *(worker_arg *)arg;
  free(arg);
  sm_pool *p = wa.p;
  tl_worker = wa.index;
  openblas_set_num_threads(1);
  for (;;) {
    pthread_mutex_lock(&p->mu);
    int bg = 0;
    for (;;) {
      if (p->head) break;
      bg = p->bhead && (p->brunning < p->bmax || p->stop);
      if (bg || p->stop) break;
      pthread_cond_wait(&p->cv, &p->mu);
    }
    sm_pool_job *j = bg ? p->bhead : p->head;
    if (!j) {
      pthread_mutex_unlock(&p->mu);
      return NULL;
    }
    if (bg) {
      if (!(p->bhead = j->qnext)) p->btail = NULL;
      p->bdepth--;
      p->brunning++;
    } else {
      if (!(p->head = j->qnext)) p->tail = NULL;
      p->depth--;
      sm_met_sub(&sm_met.queue_depth, 1);
    }
    p->running++;
    pthread_mutex_unlock(&p->mu);
    j->qnext = NULL;
    j->run(j);
    pthread_mutex_lock(&p->mu);
    p->running--;
    if (bg) { /* a background slot is free: a waiting background job may start */
      p->brunning--;
      if (p->bhead) pthread_cond_broadcast(&p->cv);
    }
    pthread_mutex_unlock(&p->mu);
  }
}

int sm_pool_create(int nthreads, int queue_cap, sm_pool **out) {
  sm_eigs_openmp_off(); /* process-wide, before any worker exists (sm_srv_pool.h) */
  *out = NULL;
  sm_pool *p = calloc(1, sizeof *p);
  if (!p) return -ENOMEM;
  p->cap = queue_cap;
  p->efd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (p->efd < 0) {
    free(p);
    return -errno;
  }
  pthread_mutex_init(&p->mu, NULL);
  pthread_cond_init(&p->cv, NULL);
  pthread_mutex_init(&p->done_mu, NULL);
  p->th = calloc((size_t)nthreads, sizeof *p->th);
  if (!p->th) {
    sm_pool_destroy(p);
    return -ENOMEM;
  }
  for (int i = 0; i < nthreads; i++) {
    worker_arg *wa = malloc(sizeof *wa);
    if (wa) *wa = (worker_arg){p, i};
    if (!wa || pthread_create(&p->th[i], NULL, worker, wa)) {
      free(wa);
      sm_pool_destroy(p);
      return -EAGAIN;
    }
    p->nth++;
  }
  *out = p;
  return 0;
}

void sm_pool_destroy(sm_pool *p) {
  if (!p) return;
  pthread_mutex_lock(&p->mu);
  p->stop = 1;
  pthread_cond_broadcast(&p->cv);
  pthread_mutex_unlock(&p->mu);
  for (int i = 0; i < p->nth; i++) pthread_join(p->th[i], NULL);
  free(p->th);
  close(p->efd);
  pthread_mutex_destroy(&p->mu);
  pthread_cond_destroy(&p->cv);
  pthread_mutex_destroy(&p->done_mu);
  free(p);
}

static int submit(sm_pool *p, sm_pool_job *j, int force) {
  pthread_mutex_lock(&p->mu);
  if (p->stop) {
    pthread_mutex_unlock(&p->mu);
    return SM_POOL_ESTOPPED;
  }
  if (!force && p->depth >= p->cap) {
    pthread_mutex_unlock(&p->mu);
    return SM_POOL_EFULL;
  }
  j->qnext = NULL;
  if (p->tail) p->tail->qnext = j;
  else p->head = j;
  p->tail = j;
  p->depth++;
  sm_met_add(&sm_met.queue_depth, 1);
  pthread_cond_signal(&p->cv);
  pthread_mutex_unlock(&p->mu);
  return 0;
}

int sm_pool_submit_bg(sm_pool *p, sm_pool_job *j) {
  pthread_mutex_lock(&p->mu);
  int rc = p->stop ? SM_POOL_ESTOPPED : p->bmax < 1 || p->bdepth >= p->bcap ? SM_POOL_EFULL : 0;
  if (!rc) {
    j->qnext = NULL;
    if (p->btail) p->btail->qnext = j;
    else p->bhead = j;
    p->btail = j;
    p->bdepth++;
    if (p->brunning < p->bmax) pthread_cond_signal(&p->cv);
  }
  pthread_mutex_unlock(&p->mu);
  return rc;
}

void sm_pool_set_background(sm_pool *p, int bg_max, int bg_cap) {
  pthread_mutex_lock(&p->mu);
  p->bmax = bg_max < p->nth - 1 ? bg_max : p->nth - 1;
  p->bcap = bg_cap;
  pthread_mutex_unlock(&p->mu);
}

int sm_pool_submit(sm_pool *p, sm_pool_job *j) { return submit(p, j, 0); }
int sm_pool_submit_force(sm_pool *p, sm_pool_job *j) { return submit(p, j, 1); }
int sm_pool_threads(const sm_pool *p) { return p->nth; }

int sm_pool_borrow(sm_pool *p, int want) {
  pthread_mutex_lock(&p->mu);
  int bg_ready = p->bmax - p->brunning; /* waiting background jobs a worker may start */
  if (bg_ready > p->bdepth) bg_ready = p->bdepth;
  if (bg_ready < 0) bg_ready = 0;
  int spare = p->nth - p->running - p->depth - bg_ready - p->lent;
  int n = want < spare ? want : spare;
  if (n < 0) n = 0;
  p->lent += n;
  pthread_mutex_unlock(&p->mu);
  return n;
}

void sm_pool_return(sm_pool *p, int n) {
  pthread_mutex_lock(&p->mu);
  p->lent -= n;
  pthread_mutex_unlock(&p->mu);
}

int sm_pool_fd(const sm_pool *p) { return p->efd; }

void sm_pool_post(sm_pool *p, sm_pool_msg *m) {
  m->next = NULL;
  pthread_mutex_lock(&p->done_mu);
  if (p->dtail) p->dtail->next = m;
  else p->dhead = m;
  p->dtail = m;
  pthread_mutex_unlock(&p->done_mu);
  uint64_t one = 1;
  ssize_t w;
  do w = write(p->efd, &one, sizeof one);
  while (w < 0 && errno == EINTR); /* EAGAIN: counter saturated, already readable */
}

sm_pool_msg *sm_pool_take(sm_pool *p) {
  uint64_t v;
  ssize_t r = read(p->efd, &v, sizeof v);
  (void)r;
  pthread_mutex_lock(&p->done_mu);
  sm_pool_msg *m = p->dhead;
  p->dhead = p->dtail = NULL;
  pthread_mutex_unlock(&p->done_mu);
  return m;
}

int sm_pool_queue_depth(sm_pool *p) {
  pthread_mutex_lock(&p->mu);
  int d = p->depth;
  pthread_mutex_unlock(&p->mu);
  return d;
}
