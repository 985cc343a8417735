/* bench_service: the daemon (shapematchd) measured end to end through the client library,
 * against the same pipeline called in-process.
 *
 * What runs: the real daemon binary (SM_SERVER_BIN, built by CMake before this program),
 * started with --port 0 on a fresh temporary data dir; its log goes to a file in that dir
 * (read to learn the port), so a chatty daemon can never block on a full pipe.
 * Shapes: two 5k-vertex TOSCA meshes (cat0.drc, cat1.drc) uploaded unchanged; if they are
 * absent, two synthetic blobs (sm_synth_blob, subdivision 5, different seeds) encoded as
 * unquantized Draco. The in-process side decodes the very same bytes and prepares them with
 * sm_shape_opts_default, which is what the daemon's store computes for --default-k 100
 * (clean, unit area, LB and elastic bases k = 100, 100 WKS energies).
 *
 * Sections
 *   1. Warm throughput: bases cached (PUT with prepare, then PREPARE, then one warm-up
 *      MATCH), DISTANCE and MATCH with 1, 2 and 8 clients, each client a thread with its own
 *      connection sending a fixed number of requests back to back (one in flight: the
 *      latency of a request is what a caller waits for). req/s = requests done / wall time
 *      from the start barrier to the last answer; p50/p99 from client-side latencies
 *      (nearest rank, so with 20 samples p99 is the maximum). Every phase has a time budget:
 *      clients stop sending when it is spent, and the table says how many were done.
 *   2. Overhead: one client; daemon MATCH and in-process sm_match alternate, so drift in
 *      machine load hits both sides alike. The in-process side runs on the threads a lone
 *      request gets from the daemon (its idle workers, sm_pool_borrow: min(--threads, 4)). Ratio of medians; target <= 1.05. The daemon's
 *      own t_total (request received -> answer encoded) splits the difference into
 *      server-side work (input-numbering translation, encoding) and transport.
 *   3. Cold: a new daemon on a new data dir, PUT both shapes without prepare, then one
 *      MATCH: decoding, cleaning and both bases of both shapes are inside the measured time.
 *      Then warm MATCHes on the same daemon.
 *   4. Pool vs BLAS threads: --threads 2 (each worker BLAS single-threaded, the daemon's
 *      default) vs --threads 1 started with OPENBLAS_NUM_THREADS=2, MATCH with 2 and 8
 *      clients. The daemon calls openblas_set_num_threads(1) in main and in every worker
 *      (server/main.c, server/sm_srv_pool.c), which overrides the environment variable, so
 *      the second daemon really runs one BLAS thread: the row shows that. To still answer
 *      the question, the same trade is measured in-process, where this program controls
 *      BLAS: 2 threads x 1 BLAS thread vs 1 thread x 2 BLAS threads.
 *   5. PREPARE throughput: N distinct shapes (the first N 5k TOSCA meshes by name, else
 *      synthetic blobs) PUT without prepare on a fresh data dir, then prepared cold with
 *      PREPARE by W clients taking shapes from a shared counter, on a daemon with
 *      --threads W, for W = 1 and W = 2 (alternating, on fresh data dirs, --prepare-runs
 *      times). shapes/s = N / wall time; the ratio of the medians (2 workers over 1)
 *      shows whether preparations run in parallel (2 cores: ideal 2, target >= 1.8).
 *
 * --sections picks sections by digit (default 12345; 2 and 4 need 1). --server runs
 * another daemon binary (e.g. an older build, for a before/after in one script).
 *
 * Usage: bench_service [--match N] [--dist N] [--overhead N] [--cold N] [--emul N]
 *                      [--budget S] [--threads N] [--prepare-shapes N] [--prepare-runs N]
 *                      [--sections DIGITS] [--server PATH] [--json FILE] [--keep]
 */
#include <cblas.h> /* OpenBLAS: openblas_set_num_threads, for the in-process side */
#include <dirent.h>
#include <errno.h>
#include <ftw.h>
#include <math.h>
#include <pthread.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "sm_client.h"
#include "sm_eigs.h"
#include "sm_match.h"
#include "sm_meshio.h"
#include "sm_prepare.h"
#include "sm_synth.h"

#define MAX_CLIENTS 8
#define MAX_ROWS 32
#define MAX_PREP_SHAPES 40

static const char *g_server_bin = SM_SERVER_BIN;

/* ------------------------------------------------------------------ small helpers */

static int cmp_double(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

/* Sorts v in place. Nearest-rank percentile: the smallest sample with at least p of the
 * samples at or below it (no interpolation between two requests that both happened). */
static double percentile(double *v, int n, double p) {
  if (n <= 0) return NAN;
  qsort(v, (size_t)n, sizeof *v, cmp_double);
  int i = (int)ceil(p * n) - 1;
  if (i < 0) i = 0;
  if (i >= n) i = n - 1;
  return v[i];
}

static double median(double *v, int n) {
  if (n <= 0) return NAN;
  qsort(v, (size_t)n, sizeof *v, cmp_double);
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

static void sleep_ms(long ms) {
  struct timespec ts = {ms / 1000, (ms % 1000) * 1000000L};
  while (nanosleep(&ts, &ts) && errno == EINTR) {
  }
}

/* `uptime` as the task's record of machine load; /proc/loadavg if it cannot run. */
static void load_string(char *buf, size_t n) {
  buf[0] = 0;
  FILE *p = popen("uptime 2>/dev/null", "r");
  if (p) {
    if (!fgets(buf, (int)n, p)) buf[0] = 0;
    pclose(p);
  }
  if (!buf[0]) {
    FILE *f = fopen("/proc/loadavg", "r");
    if (f) {
      if (!fgets(buf, (int)n, f)) buf[0] = 0;
      fclose(f);
    }
  }
  buf[strcspn(buf, "\n")] = 0;
}

static int rm_entry(const char *path, const struct stat *sb, int flag, struct FTW *ftw) {
  (void)sb, (void)flag, (void)ftw;
  return remove(path);
}

static void rm_tree(const char *dir) { nftw(dir, rm_entry, 16, FTW_DEPTH | FTW_PHYS); }

/* ------------------------------------------------------------------ the daemon */

typedef struct daemon_proc {
  pid_t pid;
  char dir[256];  /* temp dir: data/ and the log live here */
  char addr[64];  /* "127.0.0.1:port" */
} daemon_proc;

/* mkdtemp under $TMPDIR (or /tmp): every daemon gets a directory nothing else touches. */
static int make_tmpdir(char *out, size_t n) {
  const char *t = getenv("TMPDIR");
  snprintf(out, n, "%s/bench_service.XXXXXX", t && *t ? t : "/tmp");
  return mkdtemp(out) ? 0 : -1;
}

/* Starts the daemon on data dir `data` with `threads` workers; blas_env, when non-NULL,
 * is exported as OPENBLAS_NUM_THREADS; prepare_on_put 0 stops PUT from queueing the
 * shape's preparation (section 5 measures PREPARE doing it). Waits (<= 30 s) for
 * `msg=listening port=N`. */
static int daemon_start(daemon_proc *d, const char *tmp, const char *data, int threads,
                        const char *blas_env, int prepare_on_put) {
  memset(d, 0, sizeof *d);
  snprintf(d->dir, sizeof d->dir, "%s", tmp);
  char log[320], th[16];
  snprintf(log, sizeof log, "%s/daemon-%d.log", tmp, threads);
  snprintf(th, sizeof th, "%d", threads);
  unlink(log);
  fflush(stdout);
  fflush(stderr);
  pid_t pid = fork();
  if (pid < 0) return -1;
  if (pid == 0) {
    FILE *f = freopen(log, "w", stderr);
    if (!f) _exit(126);
    dup2(fileno(stderr), 1);
    if (blas_env) setenv("OPENBLAS_NUM_THREADS", blas_env, 1);
    execl(g_server_bin, "shapematchd", "--port", "0", "--data-dir", data, "--threads", th,
          "--prepare-on-put", prepare_on_put ? "1" : "0", (char *)NULL);
    _exit(127);
  }
  d->pid = pid;
  for (int waited = 0; waited < 30000; waited += 20) {
    int st;
    if (waitpid(pid, &st, WNOHANG) == pid) {
      fprintf(stderr, "daemon exited during start-up, see %s\n", log);
      d->pid = 0;
      return -1;
    }
    FILE *f = fopen(log, "r");
    char line[1024];
    while (f && fgets(line, sizeof line, f)) {
      const char *p = strstr(line, "msg=listening");
      p = p ? strstr(p, " port=") : NULL;
      if (p) {
        snprintf(d->addr, sizeof d->addr, "127.0.0.1:%d", atoi(p + 6));
        fclose(f);
        return 0;
      }
    }
    if (f) fclose(f);
    sleep_ms(20);
  }
  fprintf(stderr, "daemon did not report its port within 30 s, see %s\n", log);
  kill(pid, SIGKILL);
  waitpid(pid, NULL, 0);
  d->pid = 0;
  return -1;
}

/* SIGTERM (graceful drain), SIGKILL after 15 s: a benchmark must not hang on shutdown. */
static void daemon_stop(daemon_proc *d) {
  if (d->pid <= 0) return;
  kill(d->pid, SIGTERM);
  for (int waited = 0; waited < 15000; waited += 20) {
    if (waitpid(d->pid, NULL, WNOHANG) == d->pid) {
      d->pid = 0;
      return;
    }
    sleep_ms(20);
  }
  kill(d->pid, SIGKILL);
  waitpid(d->pid, NULL, 0);
  d->pid = 0;
}

static int connect_client(const char *addr, sm_client **c) {
  sm_client_opts o;
  sm_client_opts_default(&o);
  o.compute_timeout_ms = 600000; /* bounded: a wedged daemon ends the run, not hangs it */
  sm_client_error e;
  if (sm_client_connect(addr, &o, c, &e)) {
    fprintf(stderr, "connect %s: %s\n", addr, e.msg);
    return -1;
  }
  return 0;
}

/* ------------------------------------------------------------------ inputs */

typedef struct inputs {
  char name[2][64];
  uint8_t *draco[2];
  size_t len[2];
  uint8_t id[2][SM_PROTO_ID_LEN];
  int nv[2];
} inputs;

static int load_inputs(inputs *in, sm_error *err) {
  const char *names[2] = {"cat0.drc", "cat1.drc"};
  int ok = 1;
  for (int i = 0; i < 2 && ok; i++) {
    char path[512];
    snprintf(path, sizeof path, "%s/tosca_classification_5k/drc/%s", SM_DATA_DIR, names[i]);
    if (access(path, R_OK) || sm_read_file_bytes(path, (size_t)1 << 30, &in->draco[i],
                                                 &in->len[i], err))
      ok = 0;
    else
      snprintf(in->name[i], sizeof in->name[i], "tosca/%s", names[i]);
  }
  if (!ok) {
    /* Fallback: two blobs with the same connectivity and different bumps. */
    for (int i = 0; i < 2; i++) {
      free(in->draco[i]);
      in->draco[i] = NULL;
      const double stretch[3] = {1.0, 0.8 + 0.1 * i, 0.6};
      sm_mesh *m = NULL;
      int rc = sm_synth_blob(5, 0.25, 11u + 7u * (unsigned)i, stretch, &m, err);
      if (!rc) rc = sm_draco_encode(m, 0, &in->draco[i], &in->len[i], err);
      sm_mesh_destroy(m);
      if (rc) return rc;
      snprintf(in->name[i], sizeof in->name[i], "blob(5, seed %u)", 11u + 7u * (unsigned)i);
    }
  }
  for (int i = 0; i < 2; i++) {
    sm_mesh *m = NULL;
    int rc = sm_draco_decode(in->draco[i], in->len[i], NULL, &m, err);
    if (rc) return rc;
    in->nv[i] = m->nv;
    sm_mesh_destroy(m);
    sm_client_shape_id(in->draco[i], in->len[i], in->id[i]);
  }
  return 0;
}

/* Prepared in-process exactly as the daemon's store does for the default key. */
static int prepare_local(const inputs *in, sm_shape *s[2], sm_error *err) {
  for (int i = 0; i < 2; i++) {
    sm_mesh *m = NULL;
    sm_prep_opts po;
    sm_prep_opts_default(&po);
    int rc = sm_draco_decode(in->draco[i], in->len[i], NULL, &m, err);
    if (!rc) rc = sm_prepare(m, &po, &s[i], NULL, err);
    sm_mesh_destroy(m);
    if (rc) return rc;
  }
  return 0;
}

/* The most threads the daemon lends one MATCH (SM_SRV_MATCH_THREADS, sm_srv_exec.c). */
#define DAEMON_MATCH_THREADS 4

/* The daemon's MATCH with default options: sm_match_opts_default, k1 capped by
 * --default-k (100, so unchanged), no Y -> X map, on `threads` threads. */
static void local_match_opts(sm_match_opts *mo, int threads) {
  sm_match_opts_default(mo);
  if (mo->k1 > 100) mo->k1 = 100;
  mo->want_yx = 0;
  mo->threads = threads;
}

/* ------------------------------------------------------------------ client phases */

enum { OP_MATCH = 1, OP_DISTANCE = 2 };

typedef struct worker {
  const char *addr;
  int op, n;
  const uint8_t *x, *y;
  double deadline; /* sm_now() after which no new request is sent */
  pthread_barrier_t *bar;
  sm_client *c;
  double *lat;
  int done, failed, busy;
  double t_start, t_end;
  char err[320];
} worker;

static int one_request(sm_client *c, int op, const uint8_t *x, const uint8_t *y,
                       double *server_s, sm_client_error *e) {
  if (op == OP_DISTANCE) {
    sm_proto_dist d;
    return sm_client_distance(c, x, y, NULL, &d, server_s, e);
  }
  sm_client_match_result r;
  memset(&r, 0, sizeof r);
  int rc = sm_client_match(c, x, y, NULL, &r, e);
  if (!rc && server_s) *server_s = r.t_total;
  sm_client_match_result_free(&r);
  return rc;
}

static void *worker_main(void *arg) {
  worker *w = arg;
  /* Connected before the barrier: connection set-up is not what the phase measures. */
  pthread_barrier_wait(w->bar);
  w->t_start = sm_now();
  for (int i = 0; i < w->n && sm_now() < w->deadline && w->c && sm_client_is_open(w->c);) {
    sm_client_error e;
    double t0 = sm_now();
    int rc = one_request(w->c, w->op, w->x, w->y, NULL, &e);
    double dt = sm_now() - t0;
    if (rc == SM_CLIENT_ESTATUS && e.status == SM_ST_BUSY) {
      /* Queue full: honour the hint and resend; not a completed request. */
      w->busy++;
      sleep_ms(e.retry_after_ms ? e.retry_after_ms : 10);
      continue;
    }
    if (rc) {
      w->failed++;
      snprintf(w->err, sizeof w->err, "%s", e.msg);
    } else {
      w->lat[w->done++] = dt;
    }
    i++;
  }
  w->t_end = sm_now();
  return NULL;
}

typedef struct row {
  char section[24], daemon[40], op[12];
  int clients, requested, done, failed, busy;
  double rps, p50, p99, wall; /* seconds for latencies */
} row;

static row g_rows[MAX_ROWS];
static int g_nrows;

static int run_phase(const char *section, const char *dname, const char *addr, int op,
                     const inputs *in, int clients, int n, double budget_s) {
  worker w[MAX_CLIENTS];
  pthread_t th[MAX_CLIENTS];
  pthread_barrier_t bar;
  memset(w, 0, sizeof w);
  pthread_barrier_init(&bar, NULL, (unsigned)clients);
  int rc = 0;
  for (int i = 0; i < clients && !rc; i++) {
    w[i].lat = calloc((size_t)n, sizeof *w[i].lat);
    if (!w[i].lat || connect_client(addr, &w[i].c)) rc = -1;
  }
  if (rc) {
    /* A phase with fewer clients than asked would measure something else: skip it. */
    for (int i = 0; i < clients; i++) sm_client_close(w[i].c), free(w[i].lat);
    pthread_barrier_destroy(&bar);
    return -1;
  }
  /* The deadline starts counting once everyone is connected. */
  double deadline = sm_now() + budget_s;
  for (int i = 0; i < clients; i++) {
    w[i].addr = addr, w[i].op = op, w[i].n = n, w[i].x = in->id[0], w[i].y = in->id[1];
    w[i].deadline = deadline, w[i].bar = &bar;
    pthread_create(&th[i], NULL, worker_main, &w[i]);
  }
  for (int i = 0; i < clients; i++) pthread_join(th[i], NULL);
  pthread_barrier_destroy(&bar);

  row *r = &g_rows[g_nrows < MAX_ROWS ? g_nrows++ : MAX_ROWS - 1];
  memset(r, 0, sizeof *r);
  snprintf(r->section, sizeof r->section, "%s", section);
  snprintf(r->daemon, sizeof r->daemon, "%s", dname);
  snprintf(r->op, sizeof r->op, "%s", op == OP_MATCH ? "MATCH" : "DISTANCE");
  r->clients = clients, r->requested = clients * n;
  double t0 = INFINITY, t1 = 0, *all = malloc((size_t)(clients * n + 1) * sizeof *all);
  int na = 0;
  for (int i = 0; i < clients; i++) {
    if (w[i].t_start < t0) t0 = w[i].t_start;
    if (w[i].t_end > t1) t1 = w[i].t_end;
    for (int k = 0; k < w[i].done && all; k++) all[na++] = w[i].lat[k];
    r->done += w[i].done, r->failed += w[i].failed, r->busy += w[i].busy;
    if (w[i].failed) fprintf(stderr, "  client %d: %d failed (%s)\n", i, w[i].failed, w[i].err);
    sm_client_close(w[i].c);
    free(w[i].lat);
  }
  r->wall = t1 - t0;
  r->rps = r->wall > 0 ? r->done / r->wall : 0;
  r->p50 = all ? percentile(all, na, 0.50) : NAN;
  r->p99 = all ? percentile(all, na, 0.99) : NAN;
  free(all);
  printf("  %-10s %-26s %-8s clients=%d done=%d/%d failed=%d busy=%d  %.2f req/s  "
         "p50 %.1f ms  p99 %.1f ms  (%.1f s)\n",
         section, dname, r->op, clients, r->done, r->requested, r->failed, r->busy, r->rps,
         1e3 * r->p50, 1e3 * r->p99, r->wall);
  fflush(stdout);
  return r->done == 0 ? -1 : 0;
}

/* PUT both (with prepare) then PREPARE both: after this the bases are in the daemon's
 * cache, whether they were computed now or loaded from the data dir. */
static int warm_up(const char *addr, const inputs *in, int put) {
  sm_client *c = NULL;
  if (connect_client(addr, &c)) return -1;
  sm_client_error e;
  int rc = 0;
  for (int i = 0; i < 2 && !rc; i++) {
    if (put) rc = sm_client_put(c, in->draco[i], in->len[i], 1, NULL, NULL, &e);
    sm_proto_prepare_resp pr;
    if (!rc) rc = sm_client_prepare(c, in->id[i], 0, 0, 0, &pr, &e);
    if (!rc)
      printf("  prepared %s: %u vertices, k_lb %u, k_elastic %u%s\n", in->name[i],
             pr.n_vertices, pr.k_lb, pr.k_elastic,
             pr.flags & SM_PREP_R_CACHED ? " (cached)" : "");
  }
  /* One MATCH so first-touch costs (page faults, lazy allocations) stay out of phases. */
  if (!rc) rc = one_request(c, OP_MATCH, in->id[0], in->id[1], NULL, &e);
  if (rc) fprintf(stderr, "warm-up: %s\n", e.msg);
  sm_client_close(c);
  return rc;
}

/* ------------------------------------------------------------------ in-process threads */

typedef struct local_job {
  const sm_shape *x, *y;
  int n;
  int failed;
} local_job;

static void *local_main(void *arg) {
  local_job *j = arg;
  sm_match_opts mo;
  local_match_opts(&mo, 1); /* one match per thread, as on a busy daemon's workers */
  for (int i = 0; i < j->n; i++) {
    sm_match_result r;
    memset(&r, 0, sizeof r);
    sm_error e;
    if (sm_match(j->x, j->y, &mo, &r, &e)) j->failed++;
    sm_match_result_free(&r);
  }
  return NULL;
}

/* n matches split over `threads` threads with `blas` BLAS threads: matches per second. */
static double local_throughput(const sm_shape *s[2], int threads, int blas, int n) {
  openblas_set_num_threads(blas);
  pthread_t th[MAX_CLIENTS];
  local_job j[MAX_CLIENTS];
  double t0 = sm_now();
  for (int i = 0; i < threads; i++) {
    j[i] = (local_job){s[0], s[1], n / threads + (i < n % threads), 0};
    pthread_create(&th[i], NULL, local_main, &j[i]);
  }
  int failed = 0;
  for (int i = 0; i < threads; i++) pthread_join(th[i], NULL), failed += j[i].failed;
  double dt = sm_now() - t0;
  openblas_set_num_threads(1);
  if (failed) fprintf(stderr, "  in-process: %d matches failed\n", failed);
  return (n - failed) / dt;
}

/* ------------------------------------------------------------------ PREPARE throughput */

typedef struct shape_set {
  int n;
  char name[MAX_PREP_SHAPES][64];
  uint8_t *draco[MAX_PREP_SHAPES];
  size_t len[MAX_PREP_SHAPES];
  uint8_t id[MAX_PREP_SHAPES][SM_PROTO_ID_LEN];
} shape_set;

static int cmp_name(const void *a, const void *b) {
  return strcmp((const char *)a, (const char *)b);
}

/* The first n .drc files of the 5k TOSCA set by name (distinct shapes, 4-5k vertices
 * each), or n synthetic blobs of different seeds when the shared data is absent. */
static int load_shape_set(shape_set *ss, int n, sm_error *err) {
  char dir[512], names[64][64];
  int nn = 0;
  snprintf(dir, sizeof dir, "%s/tosca_classification_5k/drc", SM_DATA_DIR);
  DIR *d = opendir(dir);
  struct dirent *de;
  while (d && (de = readdir(d)) && nn < 64) {
    size_t l = strlen(de->d_name);
    if (l > 4 && l < 64 && !strcmp(de->d_name + l - 4, ".drc")) memcpy(names[nn++], de->d_name, l + 1);
  }
  if (d) closedir(d);
  qsort(names, (size_t)nn, sizeof names[0], cmp_name);
  ss->n = n;
  for (int i = 0; i < n; i++) {
    if (i < nn) {
      char path[600];
      snprintf(path, sizeof path, "%s/%s", dir, names[i]);
      if (sm_read_file_bytes(path, (size_t)1 << 30, &ss->draco[i], &ss->len[i], err)) return -1;
      snprintf(ss->name[i], sizeof ss->name[i], "%s", names[i]);
    } else {
      const double stretch[3] = {1.0, 0.7 + 0.02 * i, 0.6};
      sm_mesh *m = NULL;
      int rc = sm_synth_blob(5, 0.25, 101u + 13u * (unsigned)i, stretch, &m, err);
      if (!rc) rc = sm_draco_encode(m, 0, &ss->draco[i], &ss->len[i], err);
      sm_mesh_destroy(m);
      if (rc) return rc;
      snprintf(ss->name[i], sizeof ss->name[i], "blob(5, seed %u)", 101u + 13u * (unsigned)i);
    }
    sm_client_shape_id(ss->draco[i], ss->len[i], ss->id[i]);
  }
  return 0;
}

typedef struct prep_client {
  const shape_set *ss;
  atomic_int *next;
  pthread_barrier_t *bar;
  sm_client *c;
  int done, failed;
  double t_start, t_end;
  double server_s[MAX_PREP_SHAPES]; /* the daemon's own preparation time per shape done */
  char err[320];
} prep_client;

static void *prep_main(void *arg) {
  prep_client *w = arg;
  pthread_barrier_wait(w->bar);
  w->t_start = sm_now();
  for (int i; (i = atomic_fetch_add(w->next, 1)) < w->ss->n;) {
    sm_client_error e;
    sm_proto_prepare_resp pr;
    int rc;
    while ((rc = sm_client_prepare(w->c, w->ss->id[i], 0, 0, 0, &pr, &e)) ==
               SM_CLIENT_ESTATUS && e.status == SM_ST_BUSY)
      sleep_ms(e.retry_after_ms ? e.retry_after_ms : 10);
    if (rc || (pr.flags & SM_PREP_R_CACHED)) { /* a cached answer did not prepare anything */
      w->failed++;
      snprintf(w->err, sizeof w->err, "%s", rc ? e.msg : "answered from the cache");
      continue;
    }
    w->server_s[w->done++] =
        1e-6 * (double)(pr.t_clean_us + pr.t_lb_us + pr.t_elastic_us + pr.t_desc_us);
  }
  w->t_end = sm_now();
  return NULL;
}

/* Seconds the daemon's threads spent on a CPU and waiting for one (runnable, in a run
 * queue), summed over its threads (/proc/PID/task/TID/schedstat: run ns, wait ns). */
static void daemon_sched(pid_t pid, double *run_s, double *wait_s) {
  char dir[64];
  *run_s = *wait_s = 0;
  snprintf(dir, sizeof dir, "/proc/%d/task", (int)pid);
  DIR *d = opendir(dir);
  struct dirent *de;
  while (d && (de = readdir(d))) {
    if (de->d_name[0] == '.') continue;
    char p[128];
    snprintf(p, sizeof p, "%s/%s/schedstat", dir, de->d_name);
    FILE *f = fopen(p, "r");
    unsigned long long run = 0, wait = 0;
    if (f && fscanf(f, "%llu %llu", &run, &wait) == 2) *run_s += 1e-9 * run, *wait_s += 1e-9 * wait;
    if (f) fclose(f);
  }
  if (d) closedir(d);
}

/* One round: a daemon with `workers` workers on a fresh data dir, every shape PUT without
 * preparation (untimed), then `workers` clients PREPARE them all. Returns shapes/s (NaN on
 * failure); *server_med: median of the daemon's per-shape preparation times. */
static double prepare_round(const shape_set *ss, int workers, double *server_med,
                            double *runnable) {
  char tmp[256], data[300];
  *server_med = *runnable = NAN;
  if (make_tmpdir(tmp, sizeof tmp)) return NAN;
  snprintf(data, sizeof data, "%s/data", tmp);
  daemon_proc dp = {0};
  prep_client w[MAX_CLIENTS];
  pthread_t th[MAX_CLIENTS];
  memset(w, 0, sizeof w);
  double rate = NAN;
  int ok = !daemon_start(&dp, tmp, data, workers, NULL, 0);
  sm_client *c = NULL;
  if (ok) ok = !connect_client(dp.addr, &c);
  for (int i = 0; ok && i < ss->n; i++) {
    sm_client_error e;
    if (sm_client_put(c, ss->draco[i], ss->len[i], 0, NULL, NULL, &e)) {
      fprintf(stderr, "prepare phase: PUT %s: %s\n", ss->name[i], e.msg);
      ok = 0;
    }
  }
  sm_client_close(c);
  for (int i = 0; ok && i < workers; i++) ok = !connect_client(dp.addr, &w[i].c);
  if (ok) {
    atomic_int next;
    atomic_init(&next, 0);
    pthread_barrier_t bar;
    pthread_barrier_init(&bar, NULL, (unsigned)workers);
    double run0, wait0, run1, wait1;
    daemon_sched(dp.pid, &run0, &wait0);
    for (int i = 0; i < workers; i++) {
      w[i].ss = ss, w[i].next = &next, w[i].bar = &bar;
      pthread_create(&th[i], NULL, prep_main, &w[i]);
    }
    double t0 = INFINITY, t1 = 0, all[MAX_PREP_SHAPES];
    int done = 0, failed = 0;
    for (int i = 0; i < workers; i++) {
      pthread_join(th[i], NULL);
      if (w[i].t_start < t0) t0 = w[i].t_start;
      if (w[i].t_end > t1) t1 = w[i].t_end;
      for (int k = 0; k < w[i].done; k++) all[done++] = w[i].server_s[k];
      failed += w[i].failed;
      if (w[i].failed) fprintf(stderr, "  prepare client %d: %d failed (%s)\n", i, w[i].failed, w[i].err);
    }
    pthread_barrier_destroy(&bar);
    daemon_sched(dp.pid, &run1, &wait1);
    if (!failed && done == ss->n && t1 > t0) {
      rate = done / (t1 - t0);
      *server_med = median(all, done);
      /* The workers' time on or waiting for a CPU over workers x wall: near 1 when they
       * were never blocked (no lock serializes them; a ratio under 2 then comes from the
       * cores being taken by others), well under 1 when they waited on each other. */
      *runnable = (run1 - run0 + wait1 - wait0) / (workers * (t1 - t0));
      printf("    %d worker%s: on a CPU %.2f, waiting for one %.2f (share of workers x wall)\n",
             workers, workers > 1 ? "s" : "", (run1 - run0) / (workers * (t1 - t0)),
             (wait1 - wait0) / (workers * (t1 - t0)));
    }
  }
  for (int i = 0; i < workers; i++) sm_client_close(w[i].c);
  daemon_stop(&dp);
  rm_tree(tmp);
  return rate;
}

/* ------------------------------------------------------------------ main */

/* NaN is not JSON: unmeasured values become null. */
static void fjson_num(FILE *f, const char *key, double v) {
  if (isnan(v)) fprintf(f, "  \"%s\": null,\n", key);
  else fprintf(f, "  \"%s\": %.6g,\n", key, v);
}

static const row *find_row(const char *section, const char *op, int clients) {
  for (int i = 0; i < g_nrows; i++)
    if (!strcmp(g_rows[i].section, section) && !strcmp(g_rows[i].op, op) &&
        g_rows[i].clients == clients)
      return &g_rows[i];
  return NULL;
}

int main(int argc, char **argv) {
  int n_match = 20, n_dist = 40, n_over = 15, n_cold = 2, n_emul = 8, threads = 2, keep = 0;
  int n_prep = 4, prep_runs = 3;
  const char *sections = "12345";
  double budget = 120.0;
  const char *json = "bench_service.json";
  for (int i = 1; i < argc; i++) {
    int more = i + 1 < argc;
    if (!strcmp(argv[i], "--match") && more) n_match = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--dist") && more) n_dist = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--overhead") && more) n_over = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--cold") && more) n_cold = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--emul") && more) n_emul = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--budget") && more) budget = atof(argv[++i]);
    else if (!strcmp(argv[i], "--threads") && more) threads = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--prepare-shapes") && more) n_prep = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--prepare-runs") && more) prep_runs = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--sections") && more) sections = argv[++i];
    else if (!strcmp(argv[i], "--server") && more) g_server_bin = argv[++i];
    else if (!strcmp(argv[i], "--json") && more) json = argv[++i];
    else if (!strcmp(argv[i], "--keep")) keep = 1;
    else {
      fprintf(stderr,
              "usage: %s [--match N] [--dist N] [--overhead N] [--cold N] [--emul N] "
              "[--budget S] [--threads N] [--prepare-shapes N] [--prepare-runs N] "
              "[--sections DIGITS] [--server PATH] [--json FILE] [--keep]\n",
              argv[0]);
      return 2;
    }
  }
  if (n_match < 1 || n_dist < 1 || n_over < 1 || n_cold < 0 || n_emul < 2 || threads < 1 ||
      budget <= 0 || n_prep < 2 || n_prep > MAX_PREP_SHAPES || prep_runs < 1) {
    fprintf(stderr, "counts must be >= 1 (--emul >= 2, --prepare-shapes 2..%d), --budget > 0\n",
            MAX_PREP_SHAPES);
    return 2;
  }
  int want[6] = {0};
  for (const char *c = sections; *c; c++)
    if (*c >= '1' && *c <= '5') want[*c - '0'] = 1;
  if (!want[1] && (want[2] || want[4])) {
    printf("note: sections 2 and 4 need section 1; skipped\n");
    want[2] = want[4] = 0;
  }
  signal(SIGPIPE, SIG_IGN);
  /* The in-process side runs like a daemon worker: one BLAS thread, no OpenMP teams. */
  openblas_set_num_threads(1);
  sm_eigs_openmp_off();

  char load0[256], load1[256];
  load_string(load0, sizeof load0);
  printf("bench_service: daemon %s\nload before: %s\n", g_server_bin, load0);

  sm_error err;
  sm_error_clear(&err);
  inputs in;
  memset(&in, 0, sizeof in);
  if (load_inputs(&in, &err)) {
    fprintf(stderr, "inputs: %s\n", err.msg);
    return 1;
  }
  printf("shapes: %s (%d vertices, %zu bytes), %s (%d vertices, %zu bytes)\n", in.name[0],
         in.nv[0], in.len[0], in.name[1], in.nv[1], in.len[1]);

  /* In-process shapes, outside any timing. */
  sm_shape *ls[2] = {NULL, NULL};
  double tp = sm_now();
  if ((want[2] || want[4]) && prepare_local(&in, ls, &err)) {
    fprintf(stderr, "in-process prepare: %s\n", err.msg);
    return 1;
  }
  if (want[2] || want[4])
    printf("in-process prepare of both shapes: %.1f s (1 BLAS thread)\n", sm_now() - tp);

  char tmpA[256], dataA[300], dnameA[40], dnameB[40];
  if (make_tmpdir(tmpA, sizeof tmpA)) {
    perror("mkdtemp");
    return 1;
  }
  snprintf(dataA, sizeof dataA, "%s/data", tmpA);
  snprintf(dnameA, sizeof dnameA, "threads=%d blas=1", threads);
  snprintf(dnameB, sizeof dnameB, "threads=1 OPENBLAS=2");
  int rc = 0;
  daemon_proc dA = {0};

  /* ---- 1. warm throughput ---- */
  if (want[1]) printf("\n[1] warm throughput, daemon --threads %d\n", threads);
  if (want[1] && (daemon_start(&dA, tmpA, dataA, threads, NULL, 1) || warm_up(dA.addr, &in, 1)))
    rc = 1;
  static const int NCL[3] = {1, 2, 8};
  for (int op = OP_DISTANCE; want[1] && !rc && op >= OP_MATCH; op--)
    for (int k = 0; k < 3; k++)
      if (run_phase("warm", dnameA, dA.addr, op, &in, NCL[k],
                    op == OP_MATCH ? n_match : n_dist, budget))
        rc = 1;

  /* ---- 2. overhead, alternating daemon and in-process ---- */
  double *od = calloc((size_t)n_over, sizeof *od), *ol = calloc((size_t)n_over, sizeof *ol),
         *os = calloc((size_t)n_over, sizeof *os);
  double med_d = NAN, med_l = NAN, med_s = NAN, dir_d = NAN, dir_l = NAN;
  if (!rc && want[2]) {
    printf("\n[2] overhead: MATCH through the daemon (1 client) vs sm_match in-process\n");
    sm_client *c = NULL;
    if (!od || !ol || !os || connect_client(dA.addr, &c)) rc = 1;
    sm_match_opts mo; /* a lone request borrows the idle workers (sm_srv_pool.h) */
    local_match_opts(&mo, threads < DAEMON_MATCH_THREADS ? threads : DAEMON_MATCH_THREADS);
    double t_end = sm_now() + budget;
    int n = 0;
    for (; !rc && n < n_over && sm_now() < t_end; n++) {
      sm_client_match_result r;
      memset(&r, 0, sizeof r);
      sm_client_error e;
      double t0 = sm_now();
      int e1 = sm_client_match(c, in.id[0], in.id[1], NULL, &r, &e);
      od[n] = sm_now() - t0;
      os[n] = r.t_total;
      dir_d = r.dirichlet;
      sm_client_match_result_free(&r);
      sm_match_result lr;
      memset(&lr, 0, sizeof lr);
      t0 = sm_now();
      int e2 = sm_match(ls[0], ls[1], &mo, &lr, &err);
      ol[n] = sm_now() - t0;
      dir_l = lr.dirichlet;
      sm_match_result_free(&lr);
      if (e1 || e2) {
        fprintf(stderr, "overhead: %s\n", e1 ? e.msg : err.msg);
        rc = 1;
      }
    }
    sm_client_close(c);
    if (!rc) {
      med_d = median(od, n), med_l = median(ol, n), med_s = median(os, n);
      printf("  %d pairs: daemon median %.1f ms (server-side t_total %.1f ms), in-process "
             "median %.1f ms, ratio %.3f\n",
             n, 1e3 * med_d, 1e3 * med_s, 1e3 * med_l, med_d / med_l);
      /* Same maps on both sides, or the comparison is of different work. */
      printf("  same result check: Dirichlet energy daemon %.6g, in-process %.6g\n", dir_d,
             dir_l);
    }
  }
  free(od), free(ol), free(os);
  daemon_stop(&dA);

  /* ---- 4. pool vs BLAS threads (reuses the data dir: bases load from disk) ---- */
  daemon_proc dB = {0};
  double emul_pool = NAN, emul_blas = NAN;
  if (!rc && want[4]) {
    printf("\n[4] pool vs BLAS threads: daemon --threads 1 with OPENBLAS_NUM_THREADS=2\n");
    if (daemon_start(&dB, tmpA, dataA, 1, "2", 1) || warm_up(dB.addr, &in, 0)) rc = 1;
    for (int k = 1; k < 3 && !rc; k++)
      if (run_phase("blas", dnameB, dB.addr, OP_MATCH, &in, NCL[k], n_match, budget)) rc = 1;
    daemon_stop(&dB);
    if (!rc) {
      printf("  in-process, %d matches each:\n", n_emul);
      emul_pool = local_throughput((const sm_shape **)ls, 2, 1, n_emul);
      printf("    2 threads x 1 BLAS thread : %.2f matches/s\n", emul_pool);
      emul_blas = local_throughput((const sm_shape **)ls, 1, 2, n_emul);
      printf("    1 thread  x 2 BLAS threads: %.2f matches/s\n", emul_blas);
    }
  }

  /* ---- 3. cold PUT + MATCH on fresh data dirs ---- */
  double cold[16], warm[16 * 5], cold_prep[16];
  int nc = 0, nw = 0;
  if (n_cold > 16) n_cold = 16;
  if (!want[3]) n_cold = 0;
  if (!rc && n_cold) printf("\n[3] cold PUT+MATCH (new data dir) vs warm MATCH\n");
  for (int i = 0; !rc && i < n_cold; i++) {
    char tmpC[256], dataC[300];
    daemon_proc dC = {0};
    if (make_tmpdir(tmpC, sizeof tmpC)) {
      rc = 1;
      break;
    }
    snprintf(dataC, sizeof dataC, "%s/data", tmpC);
    sm_client *c = NULL;
    if (daemon_start(&dC, tmpC, dataC, threads, NULL, 1) || connect_client(dC.addr, &c)) rc = 1;
    sm_client_error e;
    sm_client_match_result r;
    memset(&r, 0, sizeof r);
    double t0 = sm_now();
    for (int s = 0; s < 2 && !rc; s++)
      if (sm_client_put(c, in.draco[s], in.len[s], 0, NULL, NULL, &e)) rc = 1;
    if (!rc && sm_client_match(c, in.id[0], in.id[1], NULL, &r, &e)) rc = 1;
    if (!rc) {
      cold[nc] = sm_now() - t0;
      cold_prep[nc++] = r.t_prepare;
    }
    sm_client_match_result_free(&r);
    for (int k = 0; k < 5 && !rc; k++) {
      t0 = sm_now();
      if (one_request(c, OP_MATCH, in.id[0], in.id[1], NULL, &e)) rc = 1;
      else warm[nw++] = sm_now() - t0;
    }
    if (rc) fprintf(stderr, "cold: %s\n", e.msg);
    else
      printf("  run %d: cold PUT+MATCH %.2f s (server prepare %.2f s), warm MATCH after: "
             "%.1f ms (median of 5)\n",
             i + 1, cold[nc - 1], cold_prep[nc - 1], 1e3 * median(warm + nw - 5, 5));
    sm_client_close(c);
    daemon_stop(&dC);
    if (!keep) rm_tree(tmpC);
  }
  if (!keep) rm_tree(tmpA);
  else printf("kept %s\n", tmpA);

  /* ---- 5. PREPARE throughput, 1 vs 2 workers ---- */
  double pr1[16], pr2[16], ps1[16], ps2[16], ru1[16], ru2[16];
  double prep_ratio = NAN, prep_r1 = NAN, prep_r2 = NAN, prep_run2 = NAN;
  int np = 0;
  if (prep_runs > 16) prep_runs = 16;
  shape_set ss;
  memset(&ss, 0, sizeof ss);
  if (!rc && want[5]) {
    if (load_shape_set(&ss, n_prep, &err)) {
      fprintf(stderr, "prepare phase: %s\n", err.msg);
      rc = 1;
    } else {
      printf("\n[5] PREPARE throughput: %d distinct shapes (%s .. %s), cold, daemon with 1 "
             "and 2 workers (as many clients)\n", ss.n, ss.name[0], ss.name[ss.n - 1]);
    }
    for (int i = 0; !rc && i < prep_runs; i++) {
      pr1[np] = prepare_round(&ss, 1, &ps1[np], &ru1[np]);
      pr2[np] = prepare_round(&ss, 2, &ps2[np], &ru2[np]);
      if (isnan(pr1[np]) || isnan(pr2[np])) {
        rc = 1;
        break;
      }
      printf("  run %d: 1 worker %.3f shapes/s (server %.2f s/shape, runnable %.2f), 2 workers "
             "%.3f shapes/s (server %.2f s/shape, runnable %.2f): x%.2f\n",
             i + 1, pr1[np], ps1[np], ru1[np], pr2[np], ps2[np], ru2[np], pr2[np] / pr1[np]);
      fflush(stdout);
      np++;
    }
    if (np) {
      prep_r1 = median(pr1, np), prep_r2 = median(pr2, np), prep_ratio = prep_r2 / prep_r1;
      prep_run2 = median(ru2, np);
    }
  }
  for (int i = 0; i < ss.n; i++) free(ss.draco[i]);

  load_string(load1, sizeof load1);

  /* ---- table ---- */
  printf("\n== bench_service summary (medians; latencies client-side) ==\n");
  printf("%-6s %-22s %-8s %7s %9s %9s %9s %9s\n", "sect", "daemon", "op", "clients", "done",
         "req/s", "p50 ms", "p99 ms");
  for (int i = 0; i < g_nrows; i++) {
    const row *r = &g_rows[i];
    char done[24];
    snprintf(done, sizeof done, "%d/%d", r->done, r->requested);
    printf("%-6s %-22s %-8s %7d %9s %9.2f %9.1f %9.1f\n", r->section, r->daemon, r->op,
           r->clients, done, r->rps, 1e3 * r->p50, 1e3 * r->p99);
  }
  if (!isnan(med_d))
    printf("overhead: daemon MATCH %.1f ms vs in-process sm_match %.1f ms -> ratio %.3f "
           "(%+.1f%%, target <= +5%%)\n",
           1e3 * med_d, 1e3 * med_l, med_d / med_l, 100 * (med_d / med_l - 1));
  if (nc)
    printf("cold PUT+MATCH %.2f s (median of %d) vs warm MATCH %.1f ms (median of %d): "
           "x%.0f\n",
           median(cold, nc), nc, 1e3 * median(warm, nw), nw,
           median(cold, nc) / median(warm, nw));
  if (np)
    printf("PREPARE throughput: 1 worker %.3f shapes/s, 2 workers %.3f shapes/s (medians of "
           "%d) -> x%.2f (target >= 1.8); 2 workers runnable %.2f of the time (1 = never "
           "blocked on each other)\n", prep_r1, prep_r2, np, prep_ratio, prep_run2);
  const char *faster = NULL;
  for (int k = 1; k < 3; k++) {
    const row *a = find_row("warm", "MATCH", NCL[k]), *b = find_row("blas", "MATCH", NCL[k]);
    if (a && b)
      printf("daemon, %d clients: %s %.2f req/s vs %s %.2f req/s -> %s faster (x%.2f)\n",
             NCL[k], dnameA, a->rps, dnameB, b->rps, a->rps >= b->rps ? dnameA : dnameB,
             a->rps >= b->rps ? a->rps / b->rps : b->rps / a->rps);
  }
  if (!isnan(emul_pool)) {
    faster = emul_pool >= emul_blas ? "2 workers x 1 BLAS" : "1 worker x 2 BLAS";
    printf("in-process (BLAS really varied): 2x1 %.2f vs 1x2 %.2f matches/s -> %s faster\n",
           emul_pool, emul_blas, faster);
  }
  printf("note: shapematchd calls openblas_set_num_threads(1) in main and in each worker, so "
         "OPENBLAS_NUM_THREADS does not reach the daemon's BLAS\n");
  printf("load before: %s\nload after:  %s\n", load0, load1);

  if (json) {
    FILE *f = fopen(json, "w");
    if (f) {
      fprintf(f, "{\n  \"shapes\": [\"%s\", \"%s\"],\n  \"vertices\": [%d, %d],\n", in.name[0],
              in.name[1], in.nv[0], in.nv[1]);
      fprintf(f, "  \"load_before\": \"%s\",\n  \"load_after\": \"%s\",\n  \"phases\": [\n",
              load0, load1);
      for (int i = 0; i < g_nrows; i++) {
        const row *r = &g_rows[i];
        fprintf(f,
                "    {\"section\": \"%s\", \"daemon\": \"%s\", \"op\": \"%s\", \"clients\": %d, "
                "\"done\": %d, \"requested\": %d, \"failed\": %d, \"rps\": %.4f, "
                "\"p50_s\": %.6f, \"p99_s\": %.6f}%s\n",
                r->section, r->daemon, r->op, r->clients, r->done, r->requested, r->failed,
                r->rps, r->p50, r->p99, i + 1 < g_nrows ? "," : "");
      }
      fprintf(f, "  ],\n");
      fjson_num(f, "overhead_daemon_s", med_d);
      fjson_num(f, "overhead_inprocess_s", med_l);
      fjson_num(f, "overhead_server_t_total_s", med_s);
      fjson_num(f, "cold_put_match_s", nc ? median(cold, nc) : NAN);
      fjson_num(f, "warm_match_s", nw ? median(warm, nw) : NAN);
      fjson_num(f, "inprocess_2x1blas_per_s", emul_pool);
      fjson_num(f, "inprocess_1x2blas_per_s", emul_blas);
      fjson_num(f, "prepare_1worker_per_s", prep_r1);
      fjson_num(f, "prepare_2workers_per_s", prep_r2);
      fjson_num(f, "prepare_ratio", prep_ratio);
      fjson_num(f, "prepare_2workers_runnable", prep_run2);
      fprintf(f, "  \"end\": null\n}\n");
      fclose(f);
    }
  }
  sm_shape_destroy(ls[0]);
  sm_shape_destroy(ls[1]);
  free(in.draco[0]);
  free(in.draco[1]);
  return rc;
}
