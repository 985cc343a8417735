/* shapematchd: the shapematch daemon (PROTOCOL.md). Flags: shapematchd --help.
 * Logs are logfmt lines on stderr; the bound port is announced as
 * `msg=listening port=N` (useful with --port 0). */
#include <cblas.h> /* OpenBLAS: openblas_set_num_threads */
#include <errno.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/epoll.h>
#include <unistd.h>

#include "sm_shell.h"
#include "sm_alloc.h"
#include "sm_srv.h"
#include "sm_srv_log.h"
#include "sm_srv_loop.h"
#include "sm_srv_metrics.h"
#include "sm_srv_pool.h"
#include "sm_srv_store.h"
#include "sm_version.h"

static void on_signal(int sig) {
  (void)sig;
  sm_srv_signal_flag = 1;
}

static void usage(FILE *f) {
  fprintf(f,
          "usage: shapematchd [--config FILE] [--port N] [--bind ADDR] [--data-dir DIR]\n"
          "                   [--threads N] [--cache-mb MB] [--max-payload-mb MB]\n"
          "                   [--buffer-budget-mb MB]\n"
          "                   [--token TOKEN | --token-file FILE] [--metrics-port N]\n"
          "                   [--max-conns N] [--max-inflight N] [--queue N]\n"
          "                   [--idle-timeout-ms MS] [--drain-ms MS] [--max-vertices N]\n"
          "                   [--max-faces N] [--max-k K] [--default-k K]\n"
          "                   [--max-batch-items N] [--max-query-k N]\n"
          "                   [--prepare-timeout-ms MS] [--max-components N]\n"
          "                   [--multires-coarse-nv N] [--prepare-on-put 0|1]\n"
          "  --config FILE reads 'key = value' lines, the keys being the long flags without\n"
          "    '--' (port = 7878, data-dir = /var/lib/shapematch, ...); '#' starts a comment;\n"
          "    an unknown key or a bad value is an error naming the line; flags given on the\n"
          "    command line override the file;\n"
          "  --port 0 picks a free port (logged as msg=listening port=N);\n"
          "  --data-dir defaults to $XDG_STATE_HOME/shapematch or ~/.local/state/shapematch;\n"
          "  --default-k sets the default basis size and MATCH k1 (default 100, >= 20);\n"
          "  --threads: the worker pool (default = cores), the daemon's CPU budget: a MATCH\n"
          "    or DISTANCE also runs on the workers that are idle when it starts (up to 4\n"
          "    threads; the same map), so a lone request is as fast as a local match;\n"
          "  --buffer-budget-mb bounds the bytes buffered for all connections together (read\n"
          "    buffers, queued answers, request bodies waiting for a worker; default 1024, on\n"
          "    top of --cache-mb): past it the greediest connection is closed (GOAWAY\n"
          "    OVERLOADED);\n"
          "  --prepare-timeout-ms bounds the preparation (cleaning, bases, descriptors) of\n"
          "    one shape (default 300000; 0 = none): past it the request fails with\n"
          "    LIMIT_EXCEEDED naming the shape;\n"
          "  --multires-coarse-nv: vertices of the coarse level of MATCH's multi-resolution\n"
          "    path (default 5000, as the local shapematch match; PROTOCOL.md 5.7);\n"
          "  --prepare-on-put 1 (default): after storing a new shape, PUT_SHAPE queues its\n"
          "    preparation as a background job, run by at most threads - 1 workers and only\n"
          "    when no request waits (none with --threads 1); 0: shapes are prepared by the\n"
          "    first request that needs them;\n"
          "  --max-components: PUT_SHAPE refuses a mesh with more connected components after\n"
          "    cleaning (default 64; each component needs its own rigid modes);\n"
          "  --token may also come from $SHAPEMATCH_TOKEN (keeps it out of ps), or from the\n"
          "    first line of --token-file;\n"
          "  --version prints the version (and the git commit of the build).\n");
}

static int parse_u(const char *s, unsigned long long lo, unsigned long long hi,
                   unsigned long long *out) {
  char *e;
  errno = 0;
  unsigned long long v = strtoull(s, &e, 10);
  if (errno || !*s || *e || v < lo || v > hi || *s == '-') return -1;
  *out = v;
  return 0;
}

/* Where an option came from, for messages: "--threads" or "FILE:LINE: threads". */
typedef struct opt_src {
  const char *file; /* NULL: the command line */
  int line;
} opt_src;

static void opt_error(const opt_src *src, const char *key, const char *fmt, const char *v) {
  if (src->file) fprintf(stderr, "shapematchd: %s:%d: %s: ", src->file, src->line, key);
  else fprintf(stderr, "shapematchd: --%s: ", key);
  fprintf(stderr, fmt, v);
  fputc('\n', stderr);
}

/* Reads a token file's first line (without its line end). */
static int read_token_file(const char *path, char *tok, size_t cap) {
  FILE *f = fopen(path, "r");
  if (!f) return -1;
  if (!fgets(tok, (int)cap, f)) tok[0] = 0;
  fclose(f);
  tok[strcspn(tok, "\r\n")] = 0;
  return 0;
}

/* Applies one option (key = long flag without "--"). tok receives a token (static
 * storage). Returns 0, or -1 after printing a message. */
static int apply_opt(const char *key, const char *v, sm_srv_config *c, const char **tok,
                     const opt_src *src) {
  static char tokbuf[4][SM_PROTO_MAX_TOKEN + 2];
  static int ntok;
  unsigned long long u = 0;
  int bad = 0;
#define NUM(name, lo, hi, dst)                                    \
  else if (!strcmp(key, name)) {                                  \
    bad = parse_u(v, lo, hi, &u);                                 \
    if (!bad) dst = u;                                            \
  }
  if (!strcmp(key, "bind")) {
    if (strlen(v) >= sizeof c->bind || !*v) bad = 1;
    else snprintf(c->bind, sizeof c->bind, "%s", v);
  } else if (!strcmp(key, "data-dir")) {
    if (strlen(v) >= sizeof c->data_dir || !*v) bad = 1;
    else snprintf(c->data_dir, sizeof c->data_dir, "%s", v);
  } else if (!strcmp(key, "token")) {
    *tok = v;
  } else if (!strcmp(key, "token-file")) {
    char *b = tokbuf[ntok++ & 3];
    if (read_token_file(v, b, sizeof tokbuf[0])) {
      opt_error(src, key, "cannot read %s", v);
      return -1;
    }
    *tok = b;
  }
  NUM("port", 0, 65535, c->port)
  NUM("threads", 1, 1024, c->threads)
  NUM("cache-mb", 1, 1ull << 24, c->cache_bytes)
  NUM("max-payload-mb", 1, 4095, c->max_payload)
  NUM("buffer-budget-mb", 16, 1ull << 24, c->buffer_budget)
  NUM("metrics-port", 0, 65535, c->metrics_port)
  NUM("max-conns", 1, 1000000, c->max_conns)
  NUM("max-inflight", 1, 65536, c->max_inflight)
  NUM("queue", 1, 1000000, c->queue_len)
  NUM("idle-timeout-ms", 0, 86400000, c->idle_timeout_ms)
  NUM("drain-ms", 0, 3600000, c->drain_ms)
  NUM("max-vertices", 3, 100000000, c->max_vertices)
  NUM("max-faces", 1, 200000000, c->max_faces)
  NUM("max-k", 20, 65535, c->max_k)
  NUM("default-k", 20, 65535, c->default_k)
  NUM("max-batch-items", 1, 1000000, c->max_batch_items)
  NUM("max-query-k", 1, 65535, c->max_query_k)
  NUM("prepare-timeout-ms", 0, 86400000, c->prepare_timeout_ms)
  NUM("max-components", 1, 1000000, c->max_components)
  NUM("multires-coarse-nv", 200, 10000000, c->multires_coarse_nv)
  NUM("prepare-on-put", 0, 1, c->prepare_on_put)
  else {
    if (src->file) fprintf(stderr, "shapematchd: %s:%d: unknown key '%s'\n", src->file, src->line, key);
    else fprintf(stderr, "shapematchd: unknown flag --%s\n", key);
    return -1;
  }
#undef NUM
  if (bad) {
    opt_error(src, key, "bad value '%s'", v);
    return -1;
  }
  if (!strcmp(key, "cache-mb")) c->cache_bytes = u << 20;
  if (!strcmp(key, "max-payload-mb")) c->max_payload = (uint32_t)(u << 20);
  if (!strcmp(key, "buffer-budget-mb")) c->buffer_budget = u << 20;
  return 0;
}

static char *trim(char *s) {
  while (*s == ' ' || *s == '\t') s++;
  size_t n = strlen(s);
  while (n && (s[n - 1] == ' ' || s[n - 1] == '\t' || s[n - 1] == '\r' || s[n - 1] == '\n'))
    s[--n] = 0;
  return s;
}

/* The config file: 'key = value' lines; '#' at the start of a line or after blank space
 * starts a comment; blank lines are ignored. */
static int load_config(const char *path, sm_srv_config *c, const char **tok) {
  FILE *f = fopen(path, "r");
  if (!f) {
    fprintf(stderr, "shapematchd: --config %s: %s\n", path, strerror(errno));
    return -1;
  }
  static char lines[64][1024]; /* values must outlive parsing (the token) */
  char buf[1024];
  opt_src src = {path, 0};
  int rc = 0;
  while (!rc && fgets(buf, sizeof buf, f)) {
    src.line++;
    if (!strchr(buf, '\n') && !feof(f)) {
      fprintf(stderr, "shapematchd: %s:%d: line too long\n", path, src.line);
      rc = -1;
      break;
    }
    for (char *h = buf; (h = strchr(h, '#')); h++)
      if (h == buf || h[-1] == ' ' || h[-1] == '\t') {
        *h = 0;
        break;
      }
    char *l = trim(buf);
    if (!*l) continue;
    char *eq = strchr(l, '=');
    if (!eq) {
      fprintf(stderr, "shapematchd: %s:%d: expected 'key = value', got '%s'\n", path, src.line, l);
      rc = -1;
      break;
    }
    *eq = 0;
    char *key = trim(l), *val = trim(eq + 1);
    if (!strcmp(key, "config")) {
      fprintf(stderr, "shapematchd: %s:%d: a config file cannot name another\n", path, src.line);
      rc = -1;
      break;
    }
    if (!*key || !*val) {
      fprintf(stderr, "shapematchd: %s:%d: %s\n", path, src.line, *key ? "missing value" : "missing key");
      rc = -1;
      break;
    }
    char *keep = lines[(src.line - 1) & 63];
    snprintf(keep, sizeof lines[0], "%s", val);
    rc = apply_opt(key, keep, c, tok, &src);
  }
  fclose(f);
  return rc;
}

static int parse_args(int argc, char **argv, sm_srv_config *c) {
  const char *tok = getenv("SHAPEMATCH_TOKEN");
  /* first --help and --config: the file's values are overridden by the other flags */
  for (int i = 1; i < argc; i++) {
    if (!strcmp(argv[i], "--help") || !strcmp(argv[i], "-h")) {
      usage(stdout);
      exit(0);
    }
    if (!strcmp(argv[i], "--version")) {
      SM_VERSION_PRINT(stdout, "shapematchd");
      exit(0);
    }
    if (!strcmp(argv[i], "--config")) {
      if (i + 1 >= argc) {
        fprintf(stderr, "shapematchd: --config needs a value\n");
        return -1;
      }
      if (load_config(argv[++i], c, &tok)) return -1;
    }
  }
  opt_src cl = {NULL, 0};
  for (int i = 1; i < argc; i++) {
    const char *a = argv[i];
    if (i + 1 >= argc) {
      fprintf(stderr, "shapematchd: %s needs a value\n", a);
      return -1;
    }
    const char *v = argv[++i];
    if (!strcmp(a, "--config")) continue;
    if (strncmp(a, "--", 2) || !a[2]) {
      fprintf(stderr, "shapematchd: unknown flag %s\n", a);
      return -1;
    }
    if (apply_opt(a + 2, v, c, &tok, &cl)) return -1;
  }
  if (tok) {
    size_t n = strlen(tok);
    if (n > SM_PROTO_MAX_TOKEN) {
      fprintf(stderr, "shapematchd: token longer than %u bytes\n", SM_PROTO_MAX_TOKEN);
      return -1;
    }
    if (n) {
      memcpy(c->token, tok, n);
      c->token_len = n;
      c->has_token = 1;
    }
  }
  if ((uint32_t)c->default_k > c->max_k) c->max_k = (uint32_t)c->default_k;
  return 0;
}

int main(int argc, char **argv) {
  sm_alloc_keep_large(); /* before any thread; why: sm_alloc.h */
  sm_server s;
  memset(&s, 0, sizeof s);
  sm_srv_config_default(&s.cfg);
  if (parse_args(argc, argv, &s.cfg)) {
    fprintf(stderr, "shapematchd: see shapematchd --help\n");
    return 2;
  }
  sm_met.start_ns = sm_srv_now_ns();
  /* Parallelism comes from the worker pool; BLAS threads would oversubscribe. */
  openblas_set_num_threads(1);
  signal(SIGPIPE, SIG_IGN);
  struct sigaction sa;
  memset(&sa, 0, sizeof sa);
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGTERM, &sa, NULL);
  sigaction(SIGINT, &sa, NULL);

  char q[SM_SRV_PATH_MAX + 8];
  sm_limits lim = {s.cfg.max_vertices, s.cfg.max_faces};
  sm_store_key def = sm_store_key_make(s.cfg.default_k, s.cfg.default_k, SM_SHELL_DEFAULT_ETA);
  sm_error err;
  uint64_t t0 = sm_srv_now_ns();
  if (sm_store_open(s.cfg.data_dir, s.cfg.cache_bytes, &lim, &def, &s.store, &err)) {
    sm_log("error", "cannot open the data directory", " dir=%s err=%s",
           sm_log_q(s.cfg.data_dir, q, sizeof q), sm_log_q(err.msg, (char[300]){0}, 300));
    return 1;
  }
  sm_store_set_max_components(s.store, s.cfg.max_components);
  sm_store_stats ss;
  sm_store_get_stats(s.store, &ss);
  sm_log("info", "store opened", " dir=%s shapes=%llu bytes=%llu corrupt_deleted=%llu ms=%llu",
         sm_log_q(s.cfg.data_dir, q, sizeof q), (unsigned long long)ss.shapes,
         (unsigned long long)ss.shapes_bytes, (unsigned long long)ss.shapes_corrupt,
         (unsigned long long)((sm_srv_now_ns() - t0) / 1000000));

  char emsg[256];
  int lfd = -1, mfd = -1;
  int port = sm_srv_listen(s.cfg.bind, s.cfg.port, emsg, sizeof emsg, &lfd);
  if (port < 0) {
    sm_log("error", "cannot listen", " err=%s", sm_log_q(emsg, q, sizeof q));
    sm_store_close(s.store);
    return 1;
  }
  int mport = 0;
  if (s.cfg.metrics_port) {
    mport = sm_srv_listen("127.0.0.1", s.cfg.metrics_port, emsg, sizeof emsg, &mfd);
    if (mport < 0) {
      sm_log("error", "cannot listen for metrics", " err=%s", sm_log_q(emsg, q, sizeof q));
      close(lfd);
      sm_store_close(s.store);
      return 1;
    }
  }
  s.epfd = epoll_create1(EPOLL_CLOEXEC);
  if (s.epfd < 0 || sm_pool_create(s.cfg.threads, s.cfg.queue_len, &s.pool)) {
    sm_log("error", "cannot start the event loop or the worker pool", " err=\"%s\"",
           strerror(errno));
    return 1;
  }
  /* Background preparations (PUT_SHAPE): one worker always left for requests. */
  if (s.cfg.prepare_on_put) sm_pool_set_background(s.pool, s.cfg.threads - 1, s.cfg.queue_len);
  sm_log("info", "listening", " port=%d bind=%s threads=%d cache_mb=%llu max_payload=%u "
         "metrics_port=%d auth=%d default_k=%d buffer_budget_mb=%llu",
         port, s.cfg.bind, s.cfg.threads, (unsigned long long)(s.cfg.cache_bytes >> 20),
         s.cfg.max_payload, mport, s.cfg.has_token, s.cfg.default_k,
         (unsigned long long)(s.cfg.buffer_budget >> 20));
  /* Type=notify: systemd starts dependent units (the HAProxy front) only once the store is
   * open and the port listens. */
  sm_srv_notify("READY=1");

  int rc = sm_srv_run(&s, lfd, mfd);
  if (rc) {
    /* Workers are stuck in uncancellable work: everything on disk is already complete
     * (write-through, atomic renames), so leaving without joining loses nothing. */
    sm_log("warn", "exiting without joining workers", NULL);
    _exit(0);
  }
  atomic_store(&s.bg_stop, 1); /* queued background preparations end at once */
  sm_pool_destroy(s.pool);
  sm_store_get_stats(s.store, &ss);
  sm_store_close(s.store);
  close(s.epfd);
  /* Shapes and bases are written through (temp + fsync + rename) when created, so
   * nothing is pending here. */
  sm_log("info", "shutdown complete", " shapes=%llu requests=%llu",
         (unsigned long long)ss.shapes, (unsigned long long)sm_met_get(&sm_met.requests));
  return 0;
}
