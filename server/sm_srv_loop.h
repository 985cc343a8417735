/* sm_srv_loop: the epoll event loop (Redis ae.c style, level-triggered): the listening
 * socket, the metrics HTTP listener, the pool's eventfd and every connection; a periodic
 * tick (100 ms) for timeouts and the shutdown sequence. After every batch of events it
 * enforces the buffer budget (sm_conn_budget, sm_srv_conn.h "Memory"), and after a burst
 * of buffered bytes it hands the freed memory back to the kernel (malloc_trim).
 *
 * Accepting: at max_conns a new connection first evicts the oldest idle one
 * (sm_conn_evict_idle), else it is answered GOAWAY TOO_MANY_CONNECTIONS. When the process
 * runs out of descriptors, a spare one is given up to accept and close the newcomer, so a
 * pending connection cannot keep the listening socket readable forever (a busy loop).
 *
 * Contract: sm_srv_listen binds and listens (non-blocking, SO_REUSEADDR), returning the
 * bound port (the caller logs it). sm_srv_run runs until a SIGTERM/SIGINT (the handler
 * only sets sm_srv_signal_flag) has been followed by the drain: stop accepting, GOAWAY
 * (status 0, detail = drain budget) to every connection, answer what was received,
 * cancel what is still running when the budget is spent, close. Returns 0 on a clean
 * shutdown, -1 if jobs did not finish even after cancellation (the caller then exits
 * without joining the workers). */
#ifndef SM_SRV_LOOP_H
#define SM_SRV_LOOP_H

#include "sm_srv.h"

/* Returns the bound port, or -1 (errno set, message in err). */
int sm_srv_listen(const char *bind_addr, int port, char *err, size_t errlen, int *fd_out);
int sm_srv_run(sm_server *s, int lfd, int mfd);

#endif
