/* sm_srv_log: one logfmt line per event on stderr ("ts=... level=info msg=... k=v ...").
 * Contract: thread-safe (one fprintf per line under the stdio lock); values with spaces,
 * quotes or '=' are quoted by sm_log_q. Only the server logs: core/ and protocol/ never do. */
#ifndef SM_SRV_LOG_H
#define SM_SRV_LOG_H

/* level: "debug", "info", "warn", "error"; fmt continues the line with " k=v" pairs. */
void sm_log(const char *level, const char *msg, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));
/* Copies s into buf as a logfmt value (quoted and escaped when needed). Returns buf. */
const char *sm_log_q(const char *s, char *buf, unsigned n);
/* Tells the service manager a state change ("READY=1", "STOPPING=1"): sd_notify(3) when
 * built with libsystemd (SM_HAVE_SYSTEMD), else nothing. Without $NOTIFY_SOCKET (not run
 * by systemd with Type=notify) it does nothing either. */
void sm_srv_notify(const char *state);
/* Lowercase hex of n bytes into out (2n+1 chars). */
void sm_hex(const unsigned char *p, unsigned n, char *out);

#endif
