/* bench_basis: wall-time split and peak memory of the LB and elastic bases.
 *
 * For each mesh and basis kind, runs the whole pipeline (read, clean, normalize, basis)
 * `reps` times, each in a forked child so that its peak resident memory (ru_maxrss of that
 * child alone) is measured, and prints the median of every timing column. `cpu` is the
 * child's user + system time (getrusage via wait4): on a shared machine it moves less
 * with the load than the wall times do; the load average is printed before and after.
 * Usage: bench_basis [-r reps] [-k k] [--eta e] [--kind lb|elastic] [--holes N [--hole-radius r]]
 *                    [--spare N] [mesh ...]   (default: homerA, headA, koala; both kinds)
 *
 * --spare N: threads the eigensolver may borrow for its basis products besides the one
 * it runs on (sm_eigs_opts.spare_threads; default 0). --spare 1 is one basis on both
 * cores of a 2-core machine, as sm_prepare gives the elastic basis once the LB basis
 * beside it is done. The bases are the same bit for bit either way.
 *
 * --holes N: each mesh is also run with N holes cut, a scan-like open surface (issue 13:
 * large open meshes are what scanners produce): after cleaning and normalizing (area 1),
 * N seeds by farthest-point sampling in edge-path distance, the faces with a corner within
 * r (default 0.04) of a seed removed, cleaned and normalized again ("clean" includes the
 * cut). Its row follows the closed one's, named +Nholes, and a line gives the boundary
 * edges, the components and the ratios of eigensolve time and solves to the closed run.
 *
 * --parallel [--kind lb|elastic] [-t threads] [mesh ...]: throughput of basis computations
 * on several threads (default 2) against the same shapes one after another, in the same
 * process and run (default shapes: homerA, homerB, lion, cat; elastic). The meshes are
 * read, cleaned and normalized once; each repetition times the sequential pass and the
 * parallel pass (in alternating order, so that a drift of the machine's load touches
 * both), and the medians and the median of the per-repetition ratios are printed. With a
 * process-wide lock in the eigensolver (ARPACK, before issue 13) the ratio stays near 1.
 */
#define _DEFAULT_SOURCE /* wait4: per-child peak memory */
#include <cblas.h> /* OpenBLAS: openblas_set_num_threads */
#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include "sm_basis.h"
#include "sm_eigs.h"
#include "sm_meshio.h"
#include "sm_metrics.h"
#include "sm_topology.h"

typedef struct sample {
  double load, clean, assembly, factor, eigs, project, total;
  int solves, n, k, n_kernel;
  int n_boundary, n_components; /* of the mesh the basis was computed on */
  double cpu; /* child's user + system seconds, whole run */
  long maxrss_kb;
  int ok;
} sample;

/* *m (cleaned, normalized) <- the same surface with `holes` holes cut: farthest-point
 * seeds in edge-path distance (the first one farthest from vertex 0), the faces with a
 * corner within r of a seed dropped; cleaned and normalized again. */
static int cut_holes(sm_mesh **m, int holes, double r, sm_error *err) {
  sm_mesh *in = *m, *out = NULL;
  int32_t nv = in->nv;
  double *near = malloc((size_t)nv * sizeof *near), *d = malloc((size_t)nv * sizeof *d);
  sm_edge_paths *ep = NULL;
  int rc = near && d ? SM_OK : sm_error_set(err, SM_ENOMEM, "holes: out of memory");
  if (!rc) rc = sm_edge_paths_create(in, &ep, err);
  if (!rc) rc = sm_edge_paths_run(ep, 0, near, err);
  for (int h = 0; !rc && h < holes; h++) {
    int32_t seed = 0; /* the vertex farthest from vertex 0, then from the seeds so far */
    for (int32_t v = 1; v < nv; v++)
      if (isfinite(near[v]) && (!isfinite(near[seed]) || near[v] > near[seed])) seed = v;
    if (h == 0)
      for (int32_t v = 0; v < nv; v++) near[v] = INFINITY;
    rc = sm_edge_paths_run(ep, seed, d, err);
    for (int32_t v = 0; !rc && v < nv; v++) near[v] = fmin(near[v], d[v]);
  }
  int32_t kept = 0;
  for (int32_t f = 0; !rc && f < in->nf; f++) {
    const int32_t *F = in->F + 3 * (int64_t)f;
    if (near[F[0]] < r || near[F[1]] < r || near[F[2]] < r) continue;
    memmove(in->F + 3 * (int64_t)kept++, F, 3 * sizeof *F);
  }
  if (!rc) {
    in->nf = kept;
    rc = sm_mesh_clean(in, NULL, &out, NULL, err);
  }
  if (!rc) rc = sm_mesh_normalize(out, err);
  sm_edge_paths_destroy(ep);
  free(near);
  free(d);
  if (rc) {
    sm_mesh_destroy(out);
    return rc;
  }
  sm_mesh_destroy(in);
  *m = out;
  return SM_OK;
}

static int spare_opt; /* --spare */

static int run_once(const char *path, int kind, int k, double eta, int holes, double radius,
                    sample *s) {
  _Atomic int spare = spare_opt;
  sm_error err;
  sm_mesh *raw = NULL, *m = NULL;
  sm_basis *b = NULL;
  sm_edges *e = NULL;
  sm_basis_opts o;
  double t0 = sm_now();
  if (sm_mesh_read_file(path, NULL, &raw, &err)) goto fail;
  double t1 = sm_now();
  if (sm_mesh_clean(raw, NULL, &m, NULL, &err) || sm_mesh_normalize(m, &err)) goto fail;
  if (holes > 0 && cut_holes(&m, holes, radius, &err)) goto fail;
  double t2 = sm_now();
  sm_basis_opts_default(&o, kind, k);
  if (eta > 0 && kind == SM_BASIS_ELASTIC) o.eta = eta;
  o.spare_threads = &spare;
  if (sm_basis_compute(m, &o, &b, &err)) goto fail;
  double t3 = sm_now();
  if (sm_edges_build(m, &e, &err)) goto fail;
  *s = (sample){.load = t1 - t0, .clean = t2 - t1, .assembly = b->timing.assembly,
                .factor = b->timing.factorization, .eigs = b->timing.eigensolve,
                .project = b->timing.projection, .total = t3 - t0, .solves = b->timing.solves,
                .n = b->n, .k = b->k, .n_kernel = b->n_kernel, .ok = 1,
                .n_boundary = e->n_boundary, .n_components = b->n_components};
  sm_edges_destroy(e);
  sm_basis_destroy(b);
  sm_mesh_destroy(m);
  sm_mesh_destroy(raw);
  return 0;
fail:
  fprintf(stderr, "%s%s: %s\n", path, holes > 0 ? " (with holes)" : "", err.msg);
  sm_basis_destroy(b);
  sm_mesh_destroy(m);
  sm_mesh_destroy(raw);
  return 1;
}

/* Child computes, writes its sample through a pipe; parent adds the child's peak RSS. */
static int run_forked(const char *path, int kind, int k, double eta, int holes, double radius,
                      sample *s) {
  int fd[2];
  if (pipe(fd)) return 1;
  pid_t pid = fork();
  if (pid == 0) {
    close(fd[0]);
    sample c = {0};
    run_once(path, kind, k, eta, holes, radius, &c);
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

static void print_row(const char *name, const char *suffix, int kind, const sample *s, int n) {
  char label[64];
  snprintf(label, sizeof label, "%s%s", name, suffix);
  if (!n) {
    printf("%-26s %-7s failed\n", label, kind == SM_BASIS_LB ? "lb" : "elastic");
    return;
  }
  long rss = 0;
  for (int i = 0; i < n; i++) rss = s[i].maxrss_kb > rss ? s[i].maxrss_kb : rss;
  printf("%-26s %-7s %7d %4d %3d %3d  %6.3f %6.3f %6.3f %6.3f %7.3f %6.3f  %7.3f %7.3f %6d %8.1f\n",
         label, kind == SM_BASIS_LB ? "lb" : "elastic", s[0].n, s[0].k, s[0].n_kernel, n,
         median_of(s, n, offsetof(sample, load)), median_of(s, n, offsetof(sample, clean)),
         median_of(s, n, offsetof(sample, assembly)), median_of(s, n, offsetof(sample, factor)),
         median_of(s, n, offsetof(sample, eigs)), median_of(s, n, offsetof(sample, project)),
         median_of(s, n, offsetof(sample, total)), median_of(s, n, offsetof(sample, cpu)),
         s[0].solves, rss / 1024.0);
}

/* The closed mesh's runs and, with holes, the holed mesh's alternating with them (a drift
 * of the machine's load touches both). */
static void bench(const char *path, int kind, int k, double eta, int reps, int holes,
                  double radius) {
  sample s[64], h[64];
  int n = 0, nh = 0;
  for (int r = 0; r < reps && r < 64; r++) {
    if (run_forked(path, kind, k, eta, 0, 0, &s[n]) == 0) n++;
    if (holes > 0 && run_forked(path, kind, k, eta, holes, radius, &h[nh]) == 0) nh++;
  }
  const char *name = strrchr(path, '/') ? strrchr(path, '/') + 1 : path;
  print_row(name, "", kind, s, n);
  if (holes > 0) {
    char suffix[32];
    snprintf(suffix, sizeof suffix, "+%dholes", holes);
    print_row(name, suffix, kind, h, nh);
    if (n && nh)
      printf("  %s with %d holes (r = %g): %d boundary edges, %d component(s); eigensolve "
             "%.2fx and solves %.2fx the closed mesh's, cpu %.2fx\n", name, holes, radius,
             h[0].n_boundary, h[0].n_components,
             median_of(h, nh, offsetof(sample, eigs)) / median_of(s, n, offsetof(sample, eigs)),
             (double)h[0].solves / s[0].solves,
             median_of(h, nh, offsetof(sample, cpu)) / median_of(s, n, offsetof(sample, cpu)));
  }
  fflush(stdout);
}

/* The machine may be shared: the load average says how much the wall times are inflated. */
static void print_load(const char *when) {
  double la[3];
  if (getloadavg(la, 3) == 3)
    printf("load average %s: %.2f %.2f %.2f\n", when, la[0], la[1], la[2]);
}

/* ---- --parallel ---------------------------------------------------------------------- */

typedef struct par_job {
  sm_mesh **meshes;
  int nm, kind, k;
  double eta;
  atomic_int next, failed;
} par_job;

static void *par_worker(void *arg) {
  par_job *j = arg;
  for (int i; (i = atomic_fetch_add(&j->next, 1)) < j->nm;) {
    sm_basis_opts o;
    sm_basis *b = NULL;
    sm_error err;
    sm_basis_opts_default(&o, j->kind, j->k);
    if (j->eta > 0 && j->kind == SM_BASIS_ELASTIC) o.eta = j->eta;
    if (sm_basis_compute(j->meshes[i], &o, &b, &err)) {
      fprintf(stderr, "basis of shape %d: %s\n", i, err.msg);
      atomic_store(&j->failed, 1);
    }
    sm_basis_destroy(b);
  }
  return NULL;
}

/* Wall seconds to compute the bases of all meshes on nthreads threads (1: this thread). */
static double par_pass(sm_mesh **meshes, int nm, int kind, int k, double eta, int nthreads,
                       int *failed) {
  par_job j = {.meshes = meshes, .nm = nm, .kind = kind, .k = k, .eta = eta};
  atomic_init(&j.next, 0);
  atomic_init(&j.failed, 0);
  pthread_t th[16];
  int started = 0;
  double t0 = sm_now();
  for (int t = 1; t < nthreads && t < 16; t++)
    if (pthread_create(&th[started], NULL, par_worker, &j) == 0) started++;
  par_worker(&j);
  for (int t = 0; t < started; t++) pthread_join(th[t], NULL);
  double dt = sm_now() - t0;
  if (atomic_load(&j.failed)) *failed = 1;
  return dt;
}

static double median_d(double *v, int n) {
  qsort(v, (size_t)n, sizeof *v, cmp_double);
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

static void print_load(const char *when);

static int bench_parallel(const char **paths, int nm, int kind, int k, double eta, int reps,
                          int nthreads) {
  sm_mesh *meshes[32];
  int32_t total_v = 0;
  for (int i = 0; i < nm; i++) {
    sm_error err;
    sm_mesh *raw = NULL;
    meshes[i] = NULL;
    if (sm_mesh_read_file(paths[i], NULL, &raw, &err) ||
        sm_mesh_clean(raw, NULL, &meshes[i], NULL, &err) || sm_mesh_normalize(meshes[i], &err)) {
      fprintf(stderr, "%s: %s\n", paths[i], err.msg);
      sm_mesh_destroy(raw);
      for (int j = 0; j <= i; j++) sm_mesh_destroy(meshes[j]);
      return 1;
    }
    sm_mesh_destroy(raw);
    total_v += meshes[i]->nv;
  }
  if (reps > 64) reps = 64;
  double seq[64], par[64], ratio[64];
  int failed = 0;
  printf("%s bases, k = %d, %d shapes (%d vertices in all), %d repetitions, 1 vs %d threads "
         "(one BLAS thread each)\n", kind == SM_BASIS_LB ? "LB" : "elastic", k, nm, total_v,
         reps, nthreads);
  print_load("before");
  for (int r = 0; r < reps; r++) {
    if (r % 2 == 0) {
      seq[r] = par_pass(meshes, nm, kind, k, eta, 1, &failed);
      par[r] = par_pass(meshes, nm, kind, k, eta, nthreads, &failed);
    } else {
      par[r] = par_pass(meshes, nm, kind, k, eta, nthreads, &failed);
      seq[r] = par_pass(meshes, nm, kind, k, eta, 1, &failed);
    }
    ratio[r] = seq[r] / par[r];
    printf("  run %d: sequential %.3f s, %d threads %.3f s, ratio %.2f\n", r + 1, seq[r],
           nthreads, par[r], ratio[r]);
    fflush(stdout);
  }
  print_load("after");
  printf("median: sequential %.3f s, %d threads %.3f s, ratio of medians %.2f, median ratio "
         "%.2f%s\n", median_d(seq, reps), nthreads, median_d(par, reps),
         median_d(seq, reps) / median_d(par, reps), median_d(ratio, reps),
         failed ? " (some bases FAILED)" : "");
  for (int i = 0; i < nm; i++) sm_mesh_destroy(meshes[i]);
  return failed;
}

int main(int argc, char **argv) {
  /* One BLAS thread, as in the shapematch CLI (see its main for the measurements), unless
   * OPENBLAS_NUM_THREADS is set: the children inherit the setting. */
  if (!getenv("OPENBLAS_NUM_THREADS")) openblas_set_num_threads(1);
  sm_eigs_openmp_off(); /* as the daemon: one thread per basis, CHOLMOD's included */
  int reps = 5, k = 100, parallel = 0, nthreads = 2, kind = 0, holes = 0;
  double eta = 0, radius = 0.04;
  const char *meshes[32];
  int nm = 0;
  for (int i = 1; i < argc; i++) {
    if (!strcmp(argv[i], "-r") && i + 1 < argc) reps = atoi(argv[++i]);
    else if (!strcmp(argv[i], "-k") && i + 1 < argc) k = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--eta") && i + 1 < argc) eta = atof(argv[++i]);
    else if (!strcmp(argv[i], "--parallel")) parallel = 1;
    else if (!strcmp(argv[i], "-t") && i + 1 < argc) nthreads = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--spare") && i + 1 < argc) spare_opt = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--kind") && i + 1 < argc)
      kind = !strcmp(argv[++i], "lb") ? SM_BASIS_LB : SM_BASIS_ELASTIC;
    else if (!strcmp(argv[i], "--holes") && i + 1 < argc) holes = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--hole-radius") && i + 1 < argc) radius = atof(argv[++i]);
    else if (nm < 32) meshes[nm++] = argv[i];
  }
  if (parallel) {
    if (!nm) {
      meshes[nm++] = SM_DATA_DIR "/elasticbasis_cartoon_pairs/homerA.obj";
      meshes[nm++] = SM_DATA_DIR "/elasticbasis_cartoon_pairs/homerB.obj";
      meshes[nm++] = SM_DATA_DIR "/pyfm_cat_lion/lion-00.off";
      meshes[nm++] = SM_DATA_DIR "/pyfm_cat_lion/cat-00.off";
    }
    if (nthreads < 1 || nthreads > 16) nthreads = 2;
    return bench_parallel(meshes, nm, kind ? kind : SM_BASIS_ELASTIC, k, eta, reps, nthreads);
  }
  if (!nm) {
    meshes[nm++] = SM_DATA_DIR "/elasticbasis_cartoon_pairs/homerA.obj";
    meshes[nm++] = SM_DATA_DIR "/elasticbasis_cartoon_pairs/headA.obj";
    meshes[nm++] = SM_DATA_DIR "/koala_50k_odedstein/koala.obj.gz";
  }
  printf("median of %d runs, seconds; peak RSS = max over runs of the child's ru_maxrss; "
         "eigensolver spare threads %d\n", reps, spare_opt);
  print_load("before");
  printf("%-26s %-7s %7s %4s %3s %3s  %6s %6s %6s %6s %7s %6s  %7s %7s %6s %8s\n", "mesh",
         "basis", "verts", "k", "ker", "ok", "load", "clean", "assem", "factor", "eigs", "proj",
         "total", "cpu", "solves", "peakMB");
  for (int i = 0; i < nm; i++) {
    if (kind != SM_BASIS_ELASTIC) bench(meshes[i], SM_BASIS_LB, k, eta, reps, holes, radius);
    if (kind != SM_BASIS_LB) bench(meshes[i], SM_BASIS_ELASTIC, k, eta, reps, holes, radius);
  }
  print_load("after");
  return 0;
}
