/* sm_srv_pool: a fixed pool of worker threads, a bounded job queue, and a completion list
 * handed back to the event loop through an eventfd.
 *
 * Contract
 *   - Jobs are caller-defined structs embedding sm_pool_job (first member); the pool only
 *     links them and calls job->run(job) on a worker. sm_pool_submit never blocks: it
 *     returns SM_POOL_EFULL when queue_cap jobs are already waiting (the caller answers
 *     BUSY). Ownership of a submitted job passes to run(); run() hands its results back
 *     with sm_pool_post.
 *   - sm_pool_post(msg) may be called from any thread; it appends msg to the done list and
 *     makes the eventfd (sm_pool_fd) readable. The loop thread calls sm_pool_take to get
 *     the whole list in posting order (FIFO), after reading the eventfd.
 *   - Each worker calls openblas_set_num_threads(1) once at start, and sm_pool_create turns
 *     OpenMP parallel regions off for the process (sm_eigs_openmp_off: CHOLMOD's
 *     factorization would open teams of 4 threads per worker): the pool is the only
 *     parallelism, so neither may oversubscribe the cores.
 *   - Background jobs (sm_pool_submit_bg) wait in a second queue of at most bg_cap jobs. A
 *     worker takes one only when no request job waits and fewer than bg_max workers run
 *     background jobs: with bg_max = threads - 1 one worker is always left for requests,
 *     and a request never waits behind a background job in the queue. bg_max = 0 (the
 *     default, and what sm_pool_set_background makes of one thread) turns them off.
 *   - sm_pool_destroy stops the workers after both queues are empty (queued jobs still
 *     run, background ones too, whatever bg_max: the caller cancels them first if it wants
 *     them short) and joins them.
 *   Locks: mu (queue) and done_mu (completion list); never nested.
 */
#ifndef SM_SRV_POOL_H
#define SM_SRV_POOL_H

#include <stddef.h>

enum { SM_POOL_EFULL = -1, SM_POOL_ESTOPPED = -2 };

typedef struct sm_pool_job {
  void (*run)(struct sm_pool_job *j);
  struct sm_pool_job *qnext;
} sm_pool_job;

typedef struct sm_pool_msg {
  struct sm_pool_msg *next;
} sm_pool_msg;

typedef struct sm_pool sm_pool;

int sm_pool_create(int nthreads, int queue_cap, sm_pool **out);
void sm_pool_destroy(sm_pool *p);
int sm_pool_submit(sm_pool *p, sm_pool_job *j);
/* Same, ignoring queue_cap (only SM_POOL_ESTOPPED): for the runner jobs of a request that
 * was already admitted through sm_pool_submit and re-enters the queue a bounded number of
 * times at once (sm_srv_exec's fan-out), so admission control stays with the request. */
int sm_pool_submit_force(sm_pool *p, sm_pool_job *j);
/* Background jobs (see the contract): SM_POOL_EFULL when bg_cap wait already, or when
 * they are off. */
int sm_pool_submit_bg(sm_pool *p, sm_pool_job *j);
/* Call before the first sm_pool_submit_bg: at most bg_max workers at once on background
 * jobs (clamped to threads - 1), at most bg_cap waiting. */
void sm_pool_set_background(sm_pool *p, int bg_max, int bg_cap);
int sm_pool_threads(const sm_pool *p);
/* Lending idle cores to a running job (the pool's threads are the daemon's CPU budget): at
 * most want of the workers that neither run a job nor have a queued one to take (a
 * request, or a background job within bg_max), less those lent already; returns how many
 * (0 when the pool is busy). The job runs that many threads of its own beside its worker and hands them back
 * with sm_pool_return. Workers never wait for lent cores: a job submitted meanwhile
 * starts at once, so the cores are oversubscribed by at most the lent count until the
 * borrower returns them. */
int sm_pool_borrow(sm_pool *p, int want);
void sm_pool_return(sm_pool *p, int n);
/* On a worker thread: its index 0..threads-1; elsewhere -1. */
int sm_pool_worker_index(void);
int sm_pool_fd(const sm_pool *p);
void sm_pool_post(sm_pool *p, sm_pool_msg *m);
/* Reads the eventfd counter and returns the done list (FIFO), or NULL. */
sm_pool_msg *sm_pool_take(sm_pool *p);
int sm_pool_queue_depth(sm_pool *p);

#endif
