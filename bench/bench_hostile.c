/* bench_hostile: the real daemon under 1,000 hostile connections while a good client
 * measures its latency (issue 10: the memory budget and hostile clients). Loopback only,
 * bounded in time and in connections.
 *
 * What runs: shapematchd (SM_SERVER_BIN) on --port 0, a fresh temp data dir, --threads 2,
 * --max-conns 1024 and --buffer-budget-mb B (default 256, so that the hostile load really
 * meets the budget). The good client (the C client library, one connection) uploads two
 * blob shapes with prepare, so every DISTANCE below runs on cached bases.
 *   1. Unloaded: the good client alternates PING and DISTANCE for --secs seconds.
 *   2. Loaded: the same, while one driver thread keeps --hostile connections (default
 *      1,000) busy in these kinds, round robin:
 *        idle        HELLO, then nothing;
 *        prehello    connects and never says HELLO;
 *        trickle     HELLO, then a PING frame one byte every 200 ms, forever;
 *        pipeliner   HELLO, 16 KiB receive buffer, sends PING and STATS as fast as the
 *                    daemon takes them and never reads;
 *        claim       HELLO, then a PUT_SHAPE header declaring max_payload bytes, whose
 *                    payload follows 64 KiB per ~200 ms and never ends;
 *        oversize    HELLO, a header above max_payload (FRAME_TOO_LARGE), reconnects;
 *        garbage     random bytes, reads until closed, reconnects;
 *        abrupt      HELLO, half a frame, close with RST (SO_LINGER 0), reconnects;
 *      plus a flood: 300 extra connections that never say HELLO opened on top (past
 *      --max-conns with the rest), and every 250 ms a new good client connects, says
 *      HELLO and PINGs (admitted or not is counted).
 *   Peak RSS: /proc/PID/status VmHWM, reset through /proc/PID/clear_refs ("5") before
 *   each phase, so each phase reports its own peak; also the daemon's STATS
 *   buffered_peak, shed_overloaded, shed_idle, read_pauses, connections_rejected.
 *   Percentiles are nearest rank over the good client's wall-clock latencies.
 *
 * Usage: bench_hostile [--hostile N] [--secs S] [--budget-mb B] [--daemon PATH] [--keep]
 *   --daemon: another shapematchd binary (default: this build's), to compare two builds
 *   under the same load; bench/hostile_runs.sh repeats runs and prints medians.
 */
#define _GNU_SOURCE
#include <arpa/inet.h>
#include <errno.h>
#include <ftw.h>
#include <math.h>
#include <netinet/in.h>
#include <pthread.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "sm_client.h"
#include "sm_meshio.h"
#include "sm_proto.h"
#include "sm_synth.h"

#define MAX_HOSTILE 4000
#define FLOOD 300

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static void sleep_ms(long ms) {
  struct timespec ts = {ms / 1000, (ms % 1000) * 1000000L};
  while (nanosleep(&ts, &ts) && errno == EINTR) {
  }
}

static int cmp_double(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

static double pct(double *v, int n, double p) {
  if (n <= 0) return NAN;
  qsort(v, (size_t)n, sizeof *v, cmp_double);
  int i = (int)ceil(p * n) - 1;
  return v[i < 0 ? 0 : i >= n ? n - 1 : i];
}

static int rm_entry(const char *path, const struct stat *sb, int flag, struct FTW *ftw) {
  (void)sb, (void)flag, (void)ftw;
  return remove(path);
}

/* ------------------------------------------------------------------ the daemon */

static pid_t g_pid;
static int g_port;
static const char *g_daemon_bin = SM_SERVER_BIN;
static char g_dir[256];

static int daemon_start(int budget_mb) {
  const char *t = getenv("TMPDIR");
  snprintf(g_dir, sizeof g_dir, "%s/bench_hostile.XXXXXX", t && *t ? t : "/tmp");
  if (!mkdtemp(g_dir)) return -1;
  char log[320], data[300], bud[16];
  snprintf(log, sizeof log, "%s/daemon.log", g_dir);
  snprintf(data, sizeof data, "%s/data", g_dir);
  snprintf(bud, sizeof bud, "%d", budget_mb);
  pid_t pid = fork();
  if (pid < 0) return -1;
  if (pid == 0) {
    if (!freopen(log, "w", stderr)) _exit(126);
    dup2(fileno(stderr), 1);
    execl(g_daemon_bin, "shapematchd", "--port", "0", "--data-dir", data, "--threads", "2",
          "--max-conns", "1024", "--buffer-budget-mb", bud, "--default-k", "30", (char *)NULL);
    _exit(127);
  }
  g_pid = pid;
  for (int waited = 0; waited < 30000; waited += 20) {
    FILE *f = fopen(log, "r");
    char line[1024];
    while (f && fgets(line, sizeof line, f)) {
      const char *p = strstr(line, "msg=listening port=");
      if (p) g_port = atoi(p + strlen("msg=listening port="));
    }
    if (f) fclose(f);
    if (g_port > 0) return 0;
    if (waitpid(pid, NULL, WNOHANG) == pid) return -1;
    sleep_ms(20);
  }
  return -1;
}

static void daemon_stop(void) {
  if (g_pid <= 0) return;
  kill(g_pid, SIGTERM);
  for (int waited = 0; waited < 15000 && waitpid(g_pid, NULL, WNOHANG) != g_pid; waited += 20)
    sleep_ms(20);
  kill(g_pid, SIGKILL);
  waitpid(g_pid, NULL, 0);
  g_pid = 0;
}

/* VmHWM or VmRSS of the daemon in MiB. */
static double proc_mib(const char *key) {
  char path[64], line[256];
  snprintf(path, sizeof path, "/proc/%d/status", (int)g_pid);
  FILE *f = fopen(path, "r");
  double v = NAN;
  while (f && fgets(line, sizeof line, f))
    if (!strncmp(line, key, strlen(key))) v = atof(line + strlen(key) + 1) / 1024.0;
  if (f) fclose(f);
  return v;
}

/* CPU seconds (user + system) of the daemon's process, or of its loop thread (the main
 * thread: its tid is the pid), from /proc. */
static double cpu_s(int loop_only) {
  char path[96], buf[1024];
  if (loop_only) snprintf(path, sizeof path, "/proc/%d/task/%d/stat", (int)g_pid, (int)g_pid);
  else snprintf(path, sizeof path, "/proc/%d/stat", (int)g_pid);
  FILE *f = fopen(path, "r");
  size_t n = f ? fread(buf, 1, sizeof buf - 1, f) : 0;
  if (f) fclose(f);
  buf[n] = 0;
  const char *p = strrchr(buf, ')'); /* fields after the command name; utime, stime = 14, 15 */
  unsigned long long ut = 0, st = 0;
  if (!p || sscanf(p + 2, "%*c %*d %*d %*d %*d %*d %*u %*u %*u %*u %*u %llu %llu", &ut, &st) != 2)
    return NAN;
  return (double)(ut + st) / (double)sysconf(_SC_CLK_TCK);
}

static void reset_hwm(void) {
  char path[64];
  snprintf(path, sizeof path, "/proc/%d/clear_refs", (int)g_pid);
  FILE *f = fopen(path, "w");
  if (f) {
    fputs("5", f);
    fclose(f);
  }
}

static char g_addr[64];

static int good_connect(sm_client **c) {
  sm_client_opts o;
  sm_client_opts_default(&o);
  o.connect_timeout_ms = 2000;
  o.io_timeout_ms = 10000;
  sm_client_error e;
  return sm_client_connect(g_addr, &o, c, &e);
}

static uint64_t stat_get(sm_client *c, const char *name) {
  sm_proto_stat *st = NULL;
  uint32_t n = 0;
  sm_client_error e;
  uint64_t v = 0;
  if (sm_client_stats(c, &st, &n, &e)) return 0;
  for (uint32_t i = 0; i < n; i++)
    if (!strcmp(st[i].name, name)) v = st[i].value;
  free(st);
  return v;
}

/* ------------------------------------------------------------------ hostile driver */

enum { K_IDLE, K_PREHELLO, K_TRICKLE, K_PIPE, K_CLAIM, K_OVERSIZE, K_GARBAGE, K_ABRUPT, K_N };
static const char *kind_names[K_N] = {"idle",  "prehello", "trickle", "pipeliner",
                                      "claim", "oversize", "garbage", "abrupt"};

typedef struct hconn {
  int fd, kind;
  size_t off;     /* progress in the kind's byte stream */
  unsigned ticks; /* rounds seen: the slow kinds act every 20th (~200 ms) */
} hconn;

static atomic_int g_stop;
static long g_reconnects[K_N], g_connect_fail;

static int raw_connect(int rcvbuf) {
  int fd = socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK, 0);
  if (fd < 0) return -1;
  if (rcvbuf) setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
  struct sockaddr_in a = {.sin_family = AF_INET, .sin_port = htons((uint16_t)g_port)};
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (connect(fd, (struct sockaddr *)&a, sizeof a) && errno != EINPROGRESS) {
    close(fd);
    g_connect_fail++;
    return -1;
  }
  return fd;
}

static size_t hello_frame(uint8_t *out, size_t cap) {
  sm_proto_hello_req q;
  memset(&q, 0, sizeof q);
  q.min_version = q.max_version = 1;
  sm_proto_header h = {0};
  h.request_id = 1;
  ptrdiff_t n = sm_proto_enc_hello_req(out, cap, &h, &q);
  return n > 0 ? (size_t)n : 0;
}

static size_t ping_frame(uint8_t *out, size_t cap, uint32_t rid) {
  sm_proto_header h = {0};
  h.version = 1;
  h.request_id = rid;
  sm_proto_ping q = {rid};
  ptrdiff_t n = sm_proto_enc_ping(out, cap, &h, 0, &q);
  return n > 0 ? (size_t)n : 0;
}

static size_t header_frame(uint8_t *out, uint8_t op, uint32_t len) {
  sm_proto_header h = {0};
  h.version = 1;
  h.opcode = op;
  h.request_id = 7;
  h.payload_len = len;
  sm_proto_write_header(out, &h);
  return SM_PROTO_HEADER_LEN;
}

/* Sends what the socket takes now; -1 if the daemon closed it. */
static int try_send(int fd, const uint8_t *b, size_t n, size_t *sent) {
  *sent = 0;
  while (*sent < n) {
    ssize_t w = send(fd, b + *sent, n - *sent, MSG_NOSIGNAL | MSG_DONTWAIT);
    if (w > 0) {
      *sent += (size_t)w;
      continue;
    }
    if (w < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == ENOTCONN)) return 0;
    if (w < 0 && errno == EINTR) continue;
    return -1;
  }
  return 0;
}

/* Reads and discards; -1 when the daemon closed the connection. */
static int drain(int fd) {
  uint8_t b[4096];
  for (;;) {
    ssize_t r = recv(fd, b, sizeof b, MSG_DONTWAIT);
    if (r > 0) continue;
    if (r == 0) return -1;
    if (errno == EAGAIN || errno == EWOULDBLOCK || errno == ENOTCONN) return 0;
    if (errno == EINTR) continue;
    return -1;
  }
}

static uint8_t g_pipe_buf[64 * 1024], g_zero[64 * 1024];
static size_t g_pipe_len;

static void h_open(hconn *h) {
  h->off = 0;
  h->fd = raw_connect(h->kind == K_PIPE ? 16384 : 0);
  if (h->fd < 0) return;
  uint8_t b[512];
  size_t n = 0, sent;
  if (h->kind != K_PREHELLO && h->kind != K_GARBAGE) n = hello_frame(b, sizeof b);
  if (n) {
    /* a fresh loopback socket takes 80 bytes at once (after the connect completes) */
    for (int i = 0; i < 50 && try_send(h->fd, b, n, &sent) == 0 && sent == 0; i++) sleep_ms(1);
  }
}

static void h_reopen(hconn *h) {
  if (h->fd >= 0) close(h->fd);
  g_reconnects[h->kind]++;
  h_open(h);
}

/* One round of a connection's behaviour. */
static void h_step(hconn *h, unsigned *seed) {
  if (h->fd < 0) {
    h_open(h);
    return;
  }
  size_t sent;
  uint8_t b[256];
  int slow_turn = h->ticks++ % 20 == 0; /* reconnecting kinds: ~5 per second each */
  switch (h->kind) {
  case K_IDLE:
  case K_PREHELLO:
    if (drain(h->fd)) h_reopen(h); /* evicted or timed out: come back */
    return;
  case K_TRICKLE: {
    if (drain(h->fd)) {
      h_reopen(h);
      return;
    }
    size_t n = ping_frame(b, sizeof b, 9);
    if (!slow_turn) return; /* one byte per ~200 ms */
    if (try_send(h->fd, b + h->off % n, 1, &sent)) h_reopen(h);
    else h->off += sent;
    return;
  }
  case K_PIPE:
    if (try_send(h->fd, g_pipe_buf, g_pipe_len, &sent)) h_reopen(h); /* shed: comes back */
    return;
  case K_CLAIM:
    if (h->off == 0) {
      header_frame(b, SM_OP_PUT_SHAPE, 256u << 20);
      if (try_send(h->fd, b, SM_PROTO_HEADER_LEN, &sent) || !sent) return;
      h->off = 1;
    }
    if (slow_turn && (drain(h->fd) || try_send(h->fd, g_zero, sizeof g_zero, &sent)))
      h_reopen(h);
    return;
  case K_OVERSIZE:
    if (!slow_turn) return;
    if (h->off == 0) {
      header_frame(b, SM_OP_PUT_SHAPE, 0xfffffff0u);
      if (try_send(h->fd, b, SM_PROTO_HEADER_LEN, &sent) || !sent) return;
      h->off = 1;
    }
    if (drain(h->fd)) h_reopen(h);
    return;
  case K_GARBAGE:
    if (!slow_turn) return;
    for (size_t i = 0; i < sizeof b; i++) b[i] = (uint8_t)rand_r(seed);
    if (drain(h->fd) || try_send(h->fd, b, sizeof b, &sent)) h_reopen(h);
    return;
  case K_ABRUPT: {
    if (!slow_turn) return;
    size_t n = ping_frame(b, sizeof b, 11);
    if (try_send(h->fd, b, n / 2, &sent) == 0) {
      struct linger l = {1, 0};
      setsockopt(h->fd, SOL_SOCKET, SO_LINGER, &l, sizeof l);
    }
    h_reopen(h);
    return;
  }
  }
}

typedef struct driver {
  hconn *h;
  int n;
  int flood[FLOOD];
} driver;

/* The driver thread: every ~10 ms one round over all hostile connections. */
static void *drive(void *arg) {
  driver *d = arg;
  unsigned seed = 12345;
  /* Nice 19 for this thread only: on a small machine the load generator must not take
   * the daemon's CPU, or the good client measures the generator, not the daemon. */
  setpriority(PRIO_PROCESS, (id_t)syscall(SYS_gettid), 19);
  for (int i = 0; i < d->n && !atomic_load(&g_stop); i++) {
    d->h[i].ticks = (unsigned)i; /* spread the slow kinds' turns */
    h_open(&d->h[i]);
  }
  for (int i = 0; i < FLOOD && !atomic_load(&g_stop); i++) d->flood[i] = raw_connect(0);
  while (!atomic_load(&g_stop)) {
    for (int i = 0; i < d->n; i++) h_step(&d->h[i], &seed);
    for (int i = 0; i < FLOOD; i++) /* the flood: reopen what the daemon closed */
      if (d->flood[i] < 0 || drain(d->flood[i])) {
        if (d->flood[i] >= 0) close(d->flood[i]);
        d->flood[i] = raw_connect(0);
      }
    sleep_ms(10);
  }
  for (int i = 0; i < d->n; i++)
    if (d->h[i].fd >= 0) close(d->h[i].fd);
  for (int i = 0; i < FLOOD; i++)
    if (d->flood[i] >= 0) close(d->flood[i]);
  return NULL;
}

/* The good client's phase: PING and DISTANCE alternately for secs seconds; also, every
 * 250 ms, a new connection that must be admitted (HELLO + PING). */
typedef struct phase {
  double *ping, *dist;
  int n_ping, n_dist, cap, errors, newconn_ok, newconn_fail;
  double hwm_mib, rss_end_mib;
} phase;

static void run_phase(sm_client *c, const uint8_t ids[2][32], double secs, phase *p) {
  memset(p, 0, sizeof *p);
  p->cap = 200000;
  p->ping = malloc(sizeof(double) * (size_t)p->cap);
  p->dist = malloc(sizeof(double) * (size_t)p->cap);
  double t_end = now_s() + secs, t_new = now_s();
  sm_client_error e;
  while (now_s() < t_end && p->n_ping < p->cap && p->n_dist < p->cap) {
    double rtt;
    for (int i = 0; i < 10; i++) {
      double t0 = now_s();
      if (sm_client_ping(c, &rtt, &e)) p->errors++;
      else p->ping[p->n_ping++] = now_s() - t0;
    }
    double t0 = now_s();
    sm_proto_dist d;
    if (sm_client_distance(c, ids[0], ids[1], NULL, &d, NULL, &e)) p->errors++;
    else p->dist[p->n_dist++] = now_s() - t0;
    if (now_s() >= t_new) {
      t_new = now_s() + 0.25;
      sm_client *nc = NULL;
      if (good_connect(&nc) == 0 && sm_client_ping(nc, &rtt, &e) == 0) p->newconn_ok++;
      else p->newconn_fail++;
      sm_client_close(nc);
    }
  }
}

static void report(const char *name, phase *p) {
  int np = p->n_ping, nd = p->n_dist;
  printf("| %s | %d | %.3f | %.3f | %d | %.2f | %.2f | %d | %d/%d | %.0f |\n", name, np,
         1e3 * pct(p->ping, np, 0.5), 1e3 * pct(p->ping, np, 0.99), nd,
         1e3 * pct(p->dist, nd, 0.5), 1e3 * pct(p->dist, nd, 0.99), p->errors, p->newconn_ok,
         p->newconn_ok + p->newconn_fail, p->hwm_mib);
}

int main(int argc, char **argv) {
  int n_hostile = 1000, budget_mb = 256, keep = 0;
  double secs = 20;
  for (int i = 1; i < argc; i++) {
    if (!strcmp(argv[i], "--hostile") && i + 1 < argc) n_hostile = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--secs") && i + 1 < argc) secs = atof(argv[++i]);
    else if (!strcmp(argv[i], "--budget-mb") && i + 1 < argc) budget_mb = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--daemon") && i + 1 < argc) g_daemon_bin = argv[++i];
    else if (!strcmp(argv[i], "--keep")) keep = 1;
    else {
      fprintf(stderr, "usage: bench_hostile [--hostile N] [--secs S] [--budget-mb B] "
                      "[--daemon PATH] [--keep]\n");
      return 2;
    }
  }
  if (n_hostile < 0 || n_hostile > MAX_HOSTILE || secs <= 0 || secs > 600) {
    fprintf(stderr, "bench_hostile: --hostile 0..%d, --secs (0, 600]\n", MAX_HOSTILE);
    return 2;
  }
  signal(SIGPIPE, SIG_IGN);
  if (daemon_start(budget_mb)) {
    fprintf(stderr, "bench_hostile: daemon did not start (see %s)\n", g_dir);
    return 1;
  }
  snprintf(g_addr, sizeof g_addr, "127.0.0.1:%d", g_port);
  sm_client *c = NULL;
  sm_client_error e;
  uint8_t ids[2][32];
  int rc = good_connect(&c);
  for (int i = 0; i < 2 && !rc; i++) { /* two 642-vertex blobs, prepared at PUT */
    sm_error err;
    sm_mesh *m = NULL;
    uint8_t *drc = NULL;
    size_t len = 0;
    const double st[3] = {1.0, 0.8 + 0.2 * i, 0.7};
    rc = sm_synth_blob(3, 0.2, 3u + (unsigned)i, st, &m, &err) ||
         sm_draco_encode(m, 0, &drc, &len, &err) ||
         sm_client_put(c, drc, len, 1, ids[i], NULL, &e);
    sm_mesh_destroy(m);
    free(drc);
  }
  sm_proto_dist d;
  for (int i = 0; i < 3 && !rc; i++) rc = sm_client_distance(c, ids[0], ids[1], NULL, &d, NULL, &e);
  if (rc) {
    fprintf(stderr, "bench_hostile: setup failed: %s\n", e.msg);
    daemon_stop();
    return 1;
  }
  /* The pipeliners' stream: PINGs with a STATS every 16 (STATS answers are ~30x larger). */
  for (uint32_t i = 0; g_pipe_len + 64 < sizeof g_pipe_buf; i++) {
    if (i % 16 == 15) {
      sm_proto_header h = {0};
      h.version = 1;
      h.opcode = SM_OP_STATS;
      h.request_id = i + 1;
      g_pipe_len += (size_t)sm_proto_enc_empty(g_pipe_buf + g_pipe_len, 64, &h);
    } else {
      g_pipe_len += ping_frame(g_pipe_buf + g_pipe_len, 64, i + 1);
    }
  }
  printf("bench_hostile: daemon %s pid %d, --buffer-budget-mb %d, %d hostile connections + %d "
         "flood, %.0f s per phase\n\n", g_daemon_bin, (int)g_pid, budget_mb, n_hostile, FLOOD, secs);
  printf("| phase | PINGs | PING p50 ms | PING p99 ms | DISTANCEs | DIST p50 ms | DIST p99 ms "
         "| errors | new clients admitted | peak RSS MiB (VmHWM) |\n|---|---|---|---|---|---|---|---|---|---|\n");
  double rss0 = proc_mib("VmRSS:");
  phase un, lo;
  reset_hwm();
  double cpu0 = cpu_s(0), loop0 = cpu_s(1);
  run_phase(c, (const uint8_t(*)[32])ids, secs, &un);
  double cpu1 = cpu_s(0), loop1 = cpu_s(1);
  un.hwm_mib = proc_mib("VmHWM:");
  report("unloaded", &un);

  driver dr;
  memset(&dr, 0, sizeof dr);
  dr.n = n_hostile;
  dr.h = calloc((size_t)(n_hostile ? n_hostile : 1), sizeof *dr.h);
  for (int i = 0; i < n_hostile; i++) dr.h[i].kind = i % K_N, dr.h[i].fd = -1;
  reset_hwm();
  pthread_t th;
  pthread_create(&th, NULL, drive, &dr);
  sleep_ms(2000); /* every hostile connection opened and at work */
  double cpu2 = cpu_s(0), loop2 = cpu_s(1);
  run_phase(c, (const uint8_t(*)[32])ids, secs, &lo);
  double cpu3 = cpu_s(0), loop3 = cpu_s(1);
  lo.hwm_mib = proc_mib("VmHWM:");
  double rss_loaded = proc_mib("VmRSS:");
  uint64_t conns = stat_get(c, "connections");
  atomic_store(&g_stop, 1);
  pthread_join(th, NULL);
  report("loaded", &lo);
  sleep_ms(3000); /* the daemon sees the closes; malloc_trim after the burst */
  printf("\nDaemon CPU: unloaded phase %.2f s (loop thread %.2f s), loaded phase %.2f s (loop "
         "thread %.2f s; the 2 s of hostile start-up before it: loop %.2f s)\n",
         cpu1 - cpu0, loop1 - loop0, cpu3 - cpu2, loop3 - loop2, loop2 - loop1);
  printf("Daemon RSS: %.0f MiB before, %.0f MiB at the end of the loaded phase, %.0f MiB 3 s "
         "after the hostile connections closed.\n", rss0, rss_loaded, proc_mib("VmRSS:"));
  printf("STATS: connections during load %llu, buffered_peak %llu bytes (budget %llu), "
         "shed_overloaded %llu, shed_idle %llu, read_pauses %llu, budget_blocks %llu, "
         "connections_rejected %llu, buffered_bytes now %llu\n",
         (unsigned long long)conns, (unsigned long long)stat_get(c, "buffered_peak"),
         (unsigned long long)stat_get(c, "buffer_budget"),
         (unsigned long long)stat_get(c, "shed_overloaded"),
         (unsigned long long)stat_get(c, "shed_idle"),
         (unsigned long long)stat_get(c, "read_pauses"),
         (unsigned long long)stat_get(c, "budget_blocks"),
         (unsigned long long)stat_get(c, "connections_rejected"),
         (unsigned long long)stat_get(c, "buffered_bytes"));
  printf("Hostile reconnects:");
  for (int k = 0; k < K_N; k++) printf(" %s %ld", kind_names[k], g_reconnects[k]);
  printf("; failed connects %ld\n", g_connect_fail);
  double r = pct(lo.dist, lo.n_dist, 0.99) / pct(un.dist, un.n_dist, 0.99);
  printf("Targets: PING p99 loaded %.3f ms (< 5 ms: %s); DISTANCE p99 loaded/unloaded %.2f "
         "(<= 1.5: %s); peak RSS %.0f MiB vs budget %d MiB + unloaded peak %.0f MiB (%s)\n",
         1e3 * pct(lo.ping, lo.n_ping, 0.99), 1e3 * pct(lo.ping, lo.n_ping, 0.99) < 5 ? "met" : "NOT met",
         r, r <= 1.5 ? "met" : "NOT met", lo.hwm_mib, budget_mb, un.hwm_mib,
         lo.hwm_mib <= budget_mb + un.hwm_mib ? "met" : "NOT met");
  sm_client_close(c);
  daemon_stop();
  if (!keep) nftw(g_dir, rm_entry, 16, FTW_DEPTH | FTW_PHYS);
  else printf("kept %s\n", g_dir);
  free(dr.h);
  free(un.ping), free(un.dist), free(lo.ping), free(lo.dist);
  return 0;
}
