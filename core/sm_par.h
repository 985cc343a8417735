/* sm_par: parallel loops over independent jobs.
 *
 * sm_par_for runs fn(ctx, i) once for every i in 0 .. n-1, on up to `threads` threads: the
 * caller's and threads - 1 new ones, each taking the next index until none is left. It
 * returns when every job has run. A thread that cannot be started leaves its share to
 * the others (never an error). Jobs must not depend on each other's order or thread; the
 * results then do not depend on the thread count.
 * Threads: the new threads exist only during the call. fn's writes are visible to the
 * caller on return (pthread_join). Meant for jobs of a millisecond or more: starting a
 * thread costs tens of microseconds.
 *
 * A team (sm_team) keeps threads - 1 helper threads for many short loops in a row (an
 * iterative solver's sweeps): sm_team_for has sm_par_for's contract, and costs a wake-up
 * instead of a thread start. Between loops the helpers spin briefly, then sleep.
 * sm_team_new returns NULL when threads <= 1 or no helper could start; sm_team_for(NULL,
 * ...) then runs the jobs on the caller, in order. One caller thread per team: sm_team_for
 * is not reentrant. sm_team_free(NULL) is a no-op.
 */
#ifndef SM_PAR_H
#define SM_PAR_H

#include <stdint.h>

#define SM_PAR_MAX_THREADS 8

void sm_par_for(int n, int threads, void (*fn)(void *ctx, int i), void *ctx);

/* Part p of `parts` near-equal consecutive parts of 0 .. n - 1: [*a, *b). The parts
 * depend on n and parts only, never on which thread runs them. */
static inline void sm_par_part(int32_t n, int p, int parts, int32_t *a, int32_t *b) {
  *a = (int32_t)((int64_t)n * p / parts);
  *b = (int32_t)((int64_t)n * (p + 1) / parts);
}

typedef struct sm_team sm_team;

sm_team *sm_team_new(int threads);
int sm_team_threads(const sm_team *t); /* helpers + the caller; 1 for NULL */
void sm_team_for(sm_team *t, int n, void (*fn)(void *ctx, int i), void *ctx);
void sm_team_free(sm_team *t);

#endif
