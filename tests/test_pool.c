/* test_pool: the daemon's worker pool (server/sm_srv_pool.h), lending its idle cores.
 *   - a lone job on a pool of 1, 2 and 4 workers may borrow every other worker, no more;
 *   - a job that waits in the queue, or another running job, takes its core out of what
 *     can be lent; a background job waiting beyond bg_max does not (no worker may take it);
 *   - cores already lent are not lent twice, and sm_pool_return gives them back;
 *   - borrowing never blocks or stops a submitted job from running (a job submitted while
 *     the cores are lent still runs at once: oversubscription, not waiting).
 * Jobs block on a gate the test opens, so every count is taken at a known state. */
#include <pthread.h>
#include <stdatomic.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

#include "sm_srv_pool.h"
#include "sm_srv_metrics.h"
#include "sm_test.h"

sm_metrics sm_met; /* the pool counts its queue in the daemon's metrics */

typedef struct gate {
  pthread_mutex_t mu;
  pthread_cond_t cv;
  int open;
  atomic_int started, done;
} gate;

typedef struct gated_job {
  sm_pool_job base;
  gate *g;
  sm_pool *p;
  int want, got; /* got: what the job could borrow once running (-1: did not ask) */
} gated_job;

static void gated_run(sm_pool_job *pj) {
  gated_job *j = (gated_job *)pj;
  if (j->want > 0) j->got = sm_pool_borrow(j->p, j->want);
  atomic_fetch_add(&j->g->started, 1);
  pthread_mutex_lock(&j->g->mu);
  while (!j->g->open) pthread_cond_wait(&j->g->cv, &j->g->mu);
  pthread_mutex_unlock(&j->g->mu);
  if (j->got > 0) sm_pool_return(j->p, j->got);
  atomic_fetch_add(&j->g->done, 1);
}

static void gate_init(gate *g) {
  memset(g, 0, sizeof *g);
  pthread_mutex_init(&g->mu, NULL);
  pthread_cond_init(&g->cv, NULL);
}

static void gate_open(gate *g) {
  pthread_mutex_lock(&g->mu);
  g->open = 1;
  pthread_cond_broadcast(&g->cv);
  pthread_mutex_unlock(&g->mu);
}

static void sleep_ms(int ms) {
  struct timespec ts = {0, ms * 1000000L};
  nanosleep(&ts, NULL);
}

/* Waits until n jobs of g have started (a job on a worker), at most ~5 s. */
static int wait_started(gate *g, int n) {
  for (int i = 0; i < 5000 && atomic_load(&g->started) < n; i++) sleep_ms(1);
  return atomic_load(&g->started) >= n;
}

static int wait_done(gate *g, int n) {
  for (int i = 0; i < 5000 && atomic_load(&g->done) < n; i++) sleep_ms(1);
  return atomic_load(&g->done) >= n;
}

/* A lone running job on a pool of nth workers borrows nth - 1 (asking for more). */
static void test_lone_job(int nth) {
  sm_pool *p;
  REQUIRE(sm_pool_create(nth, 8, &p) == 0);
  gate g;
  gate_init(&g);
  gated_job j = {{gated_run, NULL}, &g, p, 8, -1};
  REQUIRE(sm_pool_submit(p, &j.base) == 0);
  REQUIRE(wait_started(&g, 1));
  CHECK_MSG(j.got == nth - 1, "nth=%d got=%d", nth, j.got);
  CHECK(sm_pool_borrow(p, 8) == 0); /* all lent already */
  gate_open(&g);
  REQUIRE(wait_done(&g, 1));
  /* returned: an idle pool lends every worker to a caller outside it */
  int all = sm_pool_borrow(p, 64);
  CHECK_MSG(all == nth, "nth=%d all=%d", nth, all);
  sm_pool_return(p, all);
  sm_pool_destroy(p);
}

/* Running and queued jobs each take a core out of what can be lent. */
static void test_busy_pool(void) {
  sm_pool *p;
  REQUIRE(sm_pool_create(4, 8, &p) == 0);
  gate g;
  gate_init(&g);
  gated_job a = {{gated_run, NULL}, &g, p, 0, -1}, b = a;
  REQUIRE(sm_pool_submit(p, &a.base) == 0);
  REQUIRE(sm_pool_submit(p, &b.base) == 0);
  REQUIRE(wait_started(&g, 2));
  CHECK(sm_pool_borrow(p, 1) == 1); /* 4 workers, 2 running: 2 spare */
  CHECK(sm_pool_borrow(p, 5) == 1); /* the other one; none left */
  CHECK(sm_pool_borrow(p, 5) == 0);
  sm_pool_return(p, 2);
  /* 2 running, 2 idle; two more jobs start, a fifth waits in the queue */
  gated_job c = a, d = a, e = a;
  REQUIRE(sm_pool_submit(p, &c.base) == 0);
  REQUIRE(sm_pool_submit(p, &d.base) == 0);
  REQUIRE(wait_started(&g, 4));
  REQUIRE(sm_pool_submit(p, &e.base) == 0);
  CHECK(sm_pool_borrow(p, 4) == 0);
  gate_open(&g);
  REQUIRE(wait_done(&g, 5));
  sm_pool_destroy(p);
}

/* Background jobs: running ones take their core; one that waits because bg_max are
 * running leaves the idle worker lendable. */
static void test_background(void) {
  sm_pool *p;
  REQUIRE(sm_pool_create(3, 8, &p) == 0);
  sm_pool_set_background(p, 1, 4);
  gate g;
  gate_init(&g);
  gated_job a = {{gated_run, NULL}, &g, p, 0, -1}, b = a, c = a;
  REQUIRE(sm_pool_submit(p, &a.base) == 0);
  REQUIRE(sm_pool_submit_bg(p, &b.base) == 0);
  REQUIRE(wait_started(&g, 2));
  REQUIRE(sm_pool_submit_bg(p, &c.base) == 0); /* waits: bg_max = 1 runs */
  sleep_ms(20);
  CHECK(atomic_load(&g.started) == 2);
  CHECK(sm_pool_borrow(p, 4) == 1);
  sm_pool_return(p, 1);
  gate_open(&g);
  REQUIRE(wait_done(&g, 3));
  sm_pool_destroy(p);
}

/* Lent cores do not hold back a job: one submitted while both spare workers are lent runs
 * at once beside the borrower. */
static void test_lending_never_blocks(void) {
  sm_pool *p;
  REQUIRE(sm_pool_create(2, 8, &p) == 0);
  gate g;
  gate_init(&g);
  gated_job a = {{gated_run, NULL}, &g, p, 1, -1};
  REQUIRE(sm_pool_submit(p, &a.base) == 0);
  REQUIRE(wait_started(&g, 1));
  CHECK(a.got == 1);
  gated_job b = {{gated_run, NULL}, &g, p, 1, -1};
  REQUIRE(sm_pool_submit(p, &b.base) == 0);
  CHECK(wait_started(&g, 2)); /* runs on the second worker although its core is lent */
  CHECK(b.got == 0);          /* and finds nothing left to borrow */
  gate_open(&g);
  REQUIRE(wait_done(&g, 2));
  sm_pool_destroy(p);
}

int main(void) {
  test_lone_job(1);
  test_lone_job(2);
  test_lone_job(4);
  test_busy_pool();
  test_background();
  test_lending_never_blocks();
  return sm_test_finish();
}
