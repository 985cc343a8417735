#include "sm_srv_log.h"

#include <stdarg.h>
#include <stdio.h>
#include <string.h>
#include <time.h>
#ifdef SM_HAVE_SYSTEMD
#include <systemd/sd-daemon.h>
#endif

void sm_log(const char *level, const char *msg, const char *fmt, ...) {
  char line[2048];
  struct timespec ts;
  clock_gettime(CLOCK_REALTIME, &ts);
  struct tm tm;
  gmtime_r(&ts.tv_sec, &tm);
  char mq[512];
  int n = snprintf(line, sizeof line, "ts=%04d-%02d-%02dT%02d:%02d:%02d.%03ldZ level=%s msg=%s",
                   tm.tm_year + 1900, tm.tm_mon + 1, tm.tm_mday, tm.tm_hour, tm.tm_min,
                   tm.tm_sec, ts.tv_nsec / 1000000, level, sm_log_q(msg, mq, sizeof mq));
  if (n < 0 || (size_t)n >= sizeof line) n = (int)sizeof line - 1;
  if (fmt && *fmt) {
    va_list ap;
    va_start(ap, fmt);
    int m = vsnprintf(line + n, sizeof line - (size_t)n, fmt, ap);
    va_end(ap);
    if (m > 0) n += m;
    if ((size_t)n >= sizeof line) n = (int)sizeof line - 1;
  }
  flockfile(stderr);
  fwrite(line, 1, (size_t)n, stderr);
  fputc('\n', stderr);
  fflush(stderr);
  funlockfile(stderr);
}

const char *sm_log_q(const char *s, char *buf, unsigned n) {
  if (!s) s = "";
  int quote = *s == 0 || strpbrk(s, " \"=\t\n\\") != NULL;
  unsigned o = 0;
  if (n < 3) {
    if (n) buf[0] = 0;
    return buf;
  }
  if (quote) buf[o++] = '"';
  for (; *s && o + 3 < n; s++) {
    char c = *s;
    if (c == '"' || c == '\\') buf[o++] = '\\', buf[o++] = c;
    else if (c == '\n' || c == '\t') buf[o++] = '\\', buf[o++] = c == '\n' ? 'n' : 't';
    else buf[o++] = c;
  }
  if (quote) buf[o++] = '"';
  buf[o] = 0;
  return buf;
}

void sm_srv_notify(const char *state) {
#ifdef SM_HAVE_SYSTEMD
  sd_notify(0, state);
#else
  (void)state;
#endif
}

void sm_hex(const unsigned char *p, unsigned n, char *out) {
  static const char hx[] = "0123456789abcdef";
  for (unsigned i = 0; i < n; i++) {
    out[2 * i] = hx[p[i] >> 4];
    out[2 * i + 1] = hx[p[i] & 15];
  }
  out[2 * n] = 0;
}
