/* bench_basis: wall-time split and peak memory of the LB and elastic bases.
 *
 * For each mesh and basis kind, runs the whole pipeline (read, clean, normalize, basis)
 * `reps` times, each in a forked child so that its peak resident memory (ru_maxrss of that
 * child alone) is measured, and prints the median of every timing column. `cpu` is the
 * child's user + system time (getrusage via wait4): on a shared machine it moves less
 * with the load than the wall times do; the load average is printed before and after.
 * Usage: bench_basis [-r reps] [-k k] [--eta e] [mesh ...]   (default: homerA, headA, koala)
 */
#define _DEFAULT_SOURCE /* wait4: per-child peak memory */
#include <cblas.h> /* OpenBLAS: openblas_set_num_threads */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include "sm_basis.h"
#include "sm_eigs.h"
#include "sm_meshio.h"

typedef struct sample {
  double load, clean, assembly, factor, eigs, project, total;
  int solves, n, k, n_kernel;
  double cpu; /* child's user + system seconds, whole run */
  long maxrss_kb;
  int ok;
} sample;

static int run_once(const char *path, int kind, int k, double eta, sample *s) {
  sm_error err;
  sm_mesh *raw = NULL, *m = NULL;
  sm_basis *b = NULL;
  sm_basis_opts o;
  double t0 = sm_now();
  if (sm_mesh_read_file(path, NULL, &raw, &err)) goto fail;
  double t1 = sm_now();
  if (sm_mesh_clean(raw, NULL, &m, NULL, &err) || sm_mesh_normalize(m, &err)) goto fail;
  double t2 = sm_now();
  sm_basis_opts_default(&o, kind, k);
  if (eta > 0 && kind == SM_BASIS_ELASTIC) o.eta = eta;
  if (sm_basis_compute(m, &o, &b, &err)) goto fail;
  double t3 = sm_now();
  *s = (sample){.load = t1 - t0, .clean = t2 - t1, .assembly = b->timing.assembly,
                .factor = b->timing.factorization, .eigs = b->timing.eigensolve,
                .project = b->timing.projection, .total = t3 - t0, .solves = b->timing.solves,
                .n = b->n, .k = b->k, .n_kernel = b->n_kernel, .ok = 1};
  sm_basis_destroy(b);
  sm_mesh_destroy(m);
  sm_mesh_destroy(raw);
  return 0;
fail:
  fprintf(stderr, "%s: %s\n", path, err.msg);
  sm_mesh_destroy(m);
  sm_mesh_destroy(raw);
  return 1;
}

/* Child computes, writes its sample through a pipe; parent adds the child's peak RSS. */
static int run_forked(const char *path, int kind, int k, double eta, sample *s) {
  int fd[2];
  if (pipe(fd)) return 1;
  pid_t pid = fork();
  if (pid == 0) {
    close(fd[0]);
    sample c = {0};
    run_once(path, kind, k, eta, &c);
    ssize_t w = write(fd[1], &c, sizeof c);
    _exit(w == (ssize_t)sizeof c ? 0 : 1);
  }
  close(fd[1]);
  ssize_t r = read(fd[0], s, sizeof *s);
  close(fd[0]);
  int status;
  struct rusage ru;
  if (wait4(pid, &status, 0, &ru) < 0 || r != (ssize_t)sizeof *s) return 1;
  s->maxrss_kb = ru.ru_maxrss;
  s->cpu = (double)ru.ru_utime.tv_sec + 1e-6 * (double)ru.ru_utime.tv_usec +
           (double)ru.ru_stime.tv_sec + 1e-6 * (double)ru.ru_stime.tv_usec;
  return !s->ok;
}

static int cmp_double(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

static double median_of(const sample *s, int n, size_t off) {
  double v[64];
  for (int i = 0; i < n; i++) v[i] = *(const double *)((const char *)&s[i] + off);
  qsort(v, (size_t)n, sizeof *v, cmp_double);
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

static void bench(const char *path, int kind, int k, double eta, int reps) {
  sample s[64];
  int n = 0;
  for (int r = 0; r < reps && r < 64; r++)
    if (run_forked(path, kind, k, eta, &s[n]) == 0) n++;
  const char *name = strrchr(path, '/') ? strrchr(path, '/') + 1 : path;
  if (!n) {
    printf("%-26s %-7s failed\n", name, kind == SM_BASIS_LB ? "lb" : "elastic");
    return;
  }
  long rss = 0;
  for (int i = 0; i < n; i++) rss = s[i].maxrss_kb > rss ? s[i].maxrss_kb : rss;
  printf("%-26s %-7s %7d %4d %3d %3d  %6.3f %6.3f %6.3f %6.3f %7.3f %6.3f  %7.3f %7.3f %6d %8.1f\n",
         name, kind == SM_BASIS_LB ? "lb" : "elastic", s[0].n, s[0].k, s[0].n_kernel, n,
         median_of(s, n, offsetof(sample, load)), median_of(s, n, offsetof(sample, clean)),
         median_of(s, n, offsetof(sample, assembly)), median_of(s, n, offsetof(sample, factor)),
         median_of(s, n, offsetof(sample, eigs)), median_of(s, n, offsetof(sample, project)),
         median_of(s, n, offsetof(sample, total)), median_of(s, n, offsetof(sample, cpu)),
         s[0].solves, rss / 1024.0);
  fflush(stdout);
}

/* The machine may be shared: the load average says how much the wall times are inflated. */
static void print_load(const char *when) {
  double la[3];
  if (getloadavg(la, 3) == 3)
    printf("load average %s: %.2f %.2f %.2f\n", when, la[0], la[1], la[2]);
}

int main(int argc, char **argv) {
  /* One BLAS thread, as in the shapematch CLI (see its main for the measurements), unless
   * OPENBLAS_NUM_THREADS is set: the children inherit the setting. */
  if (!getenv("OPENBLAS_NUM_THREADS")) openblas_set_num_threads(1);
  int reps = 5, k = 100;
  double eta = 0;
  const char *meshes[32];
  int nm = 0;
  for (int i = 1; i < argc; i++) {
    if (!strcmp(argv[i], "-r") && i + 1 < argc) reps = atoi(argv[++i]);
    else if (!strcmp(argv[i], "-k") && i + 1 < argc) k = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--eta") && i + 1 < argc) eta = atof(argv[++i]);
    else if (nm < 32) meshes[nm++] = argv[i];
  }
  if (!nm) {
    meshes[nm++] = SM_DATA_DIR "/elasticbasis_cartoon_pairs/homerA.obj";
    meshes[nm++] = SM_DATA_DIR "/elasticbasis_cartoon_pairs/headA.obj";
    meshes[nm++] = SM_DATA_DIR "/koala_50k_odedstein/koala.obj.gz";
  }
  printf("median of %d runs, seconds; peak RSS = max over runs of the child's ru_maxrss\n", reps);
  print_load("before");
  printf("%-26s %-7s %7s %4s %3s %3s  %6s %6s %6s %6s %7s %6s  %7s %7s %6s %8s\n", "mesh",
         "basis", "verts", "k", "ker", "ok", "load", "clean", "assem", "factor", "eigs", "proj",
         "total", "cpu", "solves", "peakMB");
  for (int i = 0; i < nm; i++) {
    bench(meshes[i], SM_BASIS_LB, k, eta, reps);
    bench(meshes[i], SM_BASIS_ELASTIC, k, eta, reps);
  }
  print_load("after");
  return 0;
}
