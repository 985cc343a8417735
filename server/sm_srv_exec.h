/* sm_srv_exec: executes a queued request on a worker thread (PUT_SHAPE, PREPARE, MATCH,
 * DISTANCE, QUERY, BATCH) and posts its response frame(s) to the loop.
 *
 * Contract: sm_exec_run is the pool's run function for an sm_job. It reads only the job,
 * the configuration and the store; the job's cancel flag and deadline are polled by the
 * core through the cancel callback (SM_ECANCELED -> CANCELLED or DEADLINE). Each request
 * gets exactly one final sm_srv_out; BATCH posts one per item first (flag MORE).
 * BATCH items and QUERY candidates are fanned out: they run as units of runner jobs on
 * the whole pool (DESIGN in sm_srv_exec.c), the last unit to finish posts the final
 * sm_srv_out, and sm_exec_run returns as soon as the fan is started. */
#ifndef SM_SRV_EXEC_H
#define SM_SRV_EXEC_H

#include "sm_srv_pool.h" /* sm_pool_job; the job itself is sm_srv_job.h's */

void sm_exec_run(sm_pool_job *j);

#endif
