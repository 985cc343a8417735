/* sm_srv_job: what travels between the loop thread and a worker: the job carrying one
 * request (sm_job), the encoded frames a worker hands back (sm_srv_out, a chain of
 * sm_wbuf), and the error frame both sides build.
 *
 * Why a header of its own: the connection (sm_srv_conn) creates jobs and receives their
 * frames, the executor (sm_srv_exec) runs them; both need these types, and neither needs
 * the other's header for them (sm_srv_conn includes sm_srv_exec.h for sm_exec_run only),
 * so the server's include graph has no cycle.
 *
 * Contract
 *   - A job is created and freed by the loop thread (sm_srv_conn). Between sm_pool_submit
 *     and its final sm_srv_out a worker owns it: it reads the job's own fields and writes
 *     nothing but deadline_hit (atomic: a MATCH's own core threads set it too); conn is
 *     opaque to it (a loop-thread pointer).
 *   - cancel is the only field both sides touch at once (atomic): 1 = CANCEL or
 *     disconnect, 2 = the drain budget is spent.
 *   - An sm_wbuf is one malloc'd block; sm_wbuf_new returns NULL when out of memory.
 */
#ifndef SM_SRV_JOB_H
#define SM_SRV_JOB_H

#include <stdatomic.h>
#include <stddef.h>
#include <stdint.h>

#include "sm_srv.h"
#include "sm_srv_pool.h"

/* One encoded frame (or a packed run of small ones) waiting to be sent. */
typedef struct sm_wbuf {
  struct sm_wbuf *next;
  size_t len, off;
  size_t cap; /* bytes allocated for data (>= len) */
  uint8_t data[];
} sm_wbuf;

sm_wbuf *sm_wbuf_new(size_t len);

typedef struct sm_job {
  sm_pool_job base; /* first member */
  sm_server *srv;
  struct sm_conn *conn; /* loop thread only */
  uint32_t rid;
  uint8_t opcode;
  uint8_t version;  /* the connection's negotiated version: response layouts and headers */
  uint32_t max_response;
  uint8_t *buf;     /* owned: holds the frame or the body */
  size_t buf_cap;   /* buf's capacity when it is a stolen read buffer (freed as one: mapped
                       pages from 64 KiB, sm_srv_conn.c), 0 when malloc'ed */
  const uint8_t *body;
  uint32_t body_len;
  _Atomic int cancel; /* 1 CANCEL or disconnect, 2 drain budget spent */
  _Atomic int deadline_hit; /* worker side only: its own thread and the core threads a
                               MATCH borrowed (sm_pool_borrow) poll the cancel callback */
  struct sm_job *parent; /* a unit of a fanned-out request (sm_srv_exec): the request whose
                            cancel flag also applies; NULL for a request */
  uint64_t recv_ns, deadline_ns;
  size_t charged;     /* loop thread: bytes of buf charged to the budget */
} sm_job;

/* A worker's result frames for one job; final = the job is done. */
typedef struct sm_srv_out {
  sm_pool_msg base;
  sm_job *job;
  sm_wbuf *frames;
  int final;
} sm_srv_out;

/* Error payload (PROTOCOL.md 4) into out (12 + msg bytes, msg truncated to 1024). */
size_t sm_error_payload(uint8_t *out, uint32_t retry, uint32_t detail, const char *msg);
/* A complete error frame with header version `version` (the connection's); NULL when out
 * of memory. */
sm_wbuf *sm_error_frame(uint8_t version, uint8_t opcode, uint32_t rid, uint16_t status,
                        uint32_t retry, uint32_t detail, const char *msg);

#endif
