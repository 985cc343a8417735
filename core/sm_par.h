/* sm_par: a parallel loop over a few coarse, independent jobs.
 *
 * sm_par_for runs fn(ctx, i) once for every i in 0 .. n-1, on up to `threads` threads: the
 * caller's and threads - 1 new ones, each taking the next index until none is left. It
 * returns when every job has run. A thread that cannot be started leaves its share to
 * the others (never an error). Jobs must not depend on each other's order or thread; the
 * results then do not depend on the thread count.
 *
 * Threads: the new threads exist only during the call. fn's writes are visible to the
 * caller on return (pthread_join). Meant for jobs of a millisecond or more: starting a
 * thread costs tens of microseconds.
 */
#ifndef SM_PAR_H
#define SM_PAR_H

#define SM_PAR_MAX_THREADS 8

void sm_par_for(int n, int threads, void (*fn)(void *ctx, int i), void *ctx);

#endif
