/* bench_sinkhorn: wall time of sm_sinkhorn on synthetic spectral-like embeddings, the
 * old schedule (eps 1 -> 0.01 c0, decay 0.5, 50 iterations per level, 4x on the last,
 * tol 1e-6) against the library's current defaults.
 *
 * Data. X and Y are two independent uniform samplings of the flat torus [0, 2pi)^2,
 * embedded by its first d Laplace-Beltrami eigenfunctions sqrt(2) cos / sin(m u + n v)
 * (ordered by m^2 + n^2): the "aligned embeddings" a functional map gives. Y is sampled
 * on a deformed torus (its point q sits at phi(q) on X, phi a smooth non-isometric
 * warp), and its coordinates carry noise growing with the frequency, as the errors of an
 * estimated functional map do. The map error is the torus distance between p_i and
 * phi(q_{T[i]}), T the row argmax; both schedules should give about the same.
 *
 * Usage: bench_sinkhorn [-r reps] [-t threads] [n ...]   (default n: 5000 15000; d 20, 60;
 * threads: opts.threads of both schedules, default the library's)
 * Prints medians over reps of total, neighbour search, setup and iteration seconds.
 * BLAS threads are the environment's business: run with OPENBLAS_NUM_THREADS=1 so that
 * only opts.threads adds threads.
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "sm_sinkhorn.h"

#define MAX_REPS 32

static uint64_t rng = 0x2545f4914f6cdd1dull;

static double urand(void) {
  rng ^= rng >> 12;
  rng ^= rng << 25;
  rng ^= rng >> 27;
  return (double)((rng * 0x2545f4914f6cdd1dull) >> 11) * 0x1.0p-53;
}

static double nrand(void) {
  double u = urand(), v = urand();
  return sqrt(-2.0 * log(u + 1e-300)) * cos(2.0 * M_PI * v);
}

typedef struct freq {
  int m, n;
} freq;

static int freq_cmp(const void *pa, const void *pb) {
  const freq *x = pa, *y = pb;
  int a = x->m * x->m + x->n * x->n, b = y->m * y->m + y->n * y->n;
  if (a != b) return a - b;
  return x->m != y->m ? x->m - y->m : x->n - y->n;
}

/* Frequencies (m, n) of a half plane (one of +-(m, n)), by eigenvalue; each gives 2 coords. */
static int make_freqs(int need, freq *fr) {
  int cnt = 0;
  for (int m = 0; m <= 12; m++)
    for (int n = -12; n <= 12; n++)
      if (m > 0 || n > 0) fr[cnt++] = (freq){m, n};
  qsort(fr, (size_t)cnt, sizeof *fr, freq_cmp);
  return cnt >= need ? 0 : -1;
}

static void embed(double u, double v, int d, const freq *fr, double *x) {
  for (int t = 0; t < d; t++) {
    double ph = fr[t / 2].m * u + fr[t / 2].n * v;
    x[t] = sqrt(2.0) * (t % 2 ? sin(ph) : cos(ph));
  }
}

static void warp(double u, double v, double *pu, double *pv) {
  *pu = u + 0.15 * sin(v) + 0.05 * sin(2 * u);
  *pv = v + 0.10 * cos(u);
}

static double torus_dist(double u1, double v1, double u2, double v2) {
  double du = fabs(fmod(u1 - u2, 2 * M_PI)), dv = fabs(fmod(v1 - v2, 2 * M_PI));
  du = fmin(du, 2 * M_PI - du), dv = fmin(dv, 2 * M_PI - dv);
  return sqrt(du * du + dv * dv);
}

typedef struct dataset {
  int n, d;
  double *F, *G, *px, *py; /* points; torus parameters of X and warped ones of Y */
} dataset;

static int make_data(int n, int d, dataset *ds) {
  freq fr[400];
  if (make_freqs((d + 1) / 2, fr)) return -1;
  ds->n = n, ds->d = d;
  ds->F = malloc(sizeof(double) * (size_t)n * d);
  ds->G = malloc(sizeof(double) * (size_t)n * d);
  ds->px = malloc(sizeof(double) * 2 * (size_t)n);
  ds->py = malloc(sizeof(double) * 2 * (size_t)n);
  if (!ds->F || !ds->G || !ds->px || !ds->py) return -1;
  for (int i = 0; i < n; i++) {
    double u = 2 * M_PI * urand(), v = 2 * M_PI * urand();
    ds->px[2 * i] = u, ds->px[2 * i + 1] = v;
    embed(u, v, d, fr, ds->F + (size_t)i * d);
  }
  for (int j = 0; j < n; j++) {
    double u = 2 * M_PI * urand(), v = 2 * M_PI * urand(), wu, wv;
    warp(u, v, &wu, &wv);
    ds->py[2 * j] = wu, ds->py[2 * j + 1] = wv;
    double *y = ds->G + (size_t)j * d;
    embed(wu, wv, d, fr, y);
    for (int t = 0; t < d; t++) y[t] += 0.05 * (1.0 + 3.0 * t / d) * nrand();
  }
  return 0;
}

static void free_data(dataset *ds) {
  free(ds->F), free(ds->G), free(ds->px), free(ds->py);
}

typedef struct result {
  double total, knn, setup, iter, err_a, map_err, distinct;
  int iterations, levels;
  int64_t nnz;
} result;

static int run(const dataset *ds, const sm_sinkhorn_opts *o, result *r, int32_t *T) {
  sm_plan *p = NULL;
  sm_sinkhorn_stats st;
  sm_error e;
  if (sm_sinkhorn(ds->F, ds->n, ds->G, ds->n, ds->d, NULL, NULL, o, &p, &st, &e)) {
    fprintf(stderr, "sinkhorn: %s\n", e.msg);
    return -1;
  }
  sm_plan_row_argmax(p, T);
  double me = 0;
  for (int i = 0; i < ds->n; i++)
    me += torus_dist(ds->px[2 * i], ds->px[2 * i + 1], ds->py[2 * T[i]], ds->py[2 * T[i] + 1]);
  *r = (result){st.t_total, st.t_knn, st.t_setup, st.t_iter, st.err_a, me / ds->n,
                sm_plan_map_distinct(T, ds->n, ds->n), st.iterations, st.levels, st.nnz};
  sm_plan_destroy(p);
  return 0;
}

static int dbl_cmp(const void *pa, const void *pb) {
  double x = *(const double *)pa, y = *(const double *)pb;
  return (x > y) - (x < y);
}

static double median(double *v, int n) {
  qsort(v, (size_t)n, sizeof *v, dbl_cmp);
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/* Runs one schedule reps times; prints the medians; returns the median total. */
static double bench(const char *name, const dataset *ds, const sm_sinkhorn_opts *o, int reps,
                    int32_t *T) {
  double tot[MAX_REPS], kn[MAX_REPS], se[MAX_REPS], it[MAX_REPS];
  result r = {0};
  for (int k = 0; k < reps; k++) {
    if (run(ds, o, &r, T)) return NAN;
    tot[k] = r.total, kn[k] = r.knn, se[k] = r.setup, it[k] = r.iter;
  }
  double mt = median(tot, reps);
  printf("  %-8s total %7.4f s (knn %.4f setup %.4f iter %.4f) | %4d it %2d lev nnz %lld "
         "err_a %.1e map err %.4f distinct %.3f\n", name, mt, median(kn, reps),
         median(se, reps), median(it, reps), r.iterations, r.levels, (long long)r.nnz,
         r.err_a, r.map_err, r.distinct);
  fflush(stdout);
  return mt;
}

int main(int argc, char **argv) {
  int reps = 5, threads = 0, ns[8], nn = 0; /* threads 0: the library's default */
  for (int a = 1; a < argc; a++) {
    if (!strcmp(argv[a], "-r") && a + 1 < argc) reps = atoi(argv[++a]);
    else if (!strcmp(argv[a], "-t") && a + 1 < argc) threads = atoi(argv[++a]);
    else if (nn < 8) ns[nn++] = atoi(argv[a]);
  }
  if (reps < 1 || reps > MAX_REPS) reps = 5;
  if (!nn) ns[0] = 5000, ns[1] = 15000, nn = 2;
  const int ds_[2] = {20, 60};
  sm_sinkhorn_opts old, cur;
  sm_sinkhorn_opts_default(&old);
  old.eps_start = 1.0, old.eps_end = 0.01, old.decay = 0.5, old.max_iter = 50, old.tol = 1e-6;
  if (threads > 0) old.threads = threads;
  sm_sinkhorn_opts_default(&cur);
  if (threads > 0) cur.threads = threads;
  printf("bench_sinkhorn: reps %d, threads %d; new default: eps %g -> %g, decay %g, "
         "max_iter %d, tol %g, k %d\n", reps, cur.threads, cur.eps_start, cur.eps_end, cur.decay,
         cur.max_iter, cur.tol, cur.k);
  for (int a = 0; a < nn; a++)
    for (int b = 0; b < 2; b++) {
      dataset ds = {0};
      int32_t *T0 = malloc(sizeof(int32_t) * (size_t)ns[a]);
      int32_t *T1 = malloc(sizeof(int32_t) * (size_t)ns[a]);
      if (!T0 || !T1 || make_data(ns[a], ds_[b], &ds)) {
        fprintf(stderr, "out of memory\n");
        return 1;
      }
      printf("n = %d, d = %d\n", ns[a], ds_[b]);
      double t0 = bench("old", &ds, &old, reps, T0);
      double t1 = bench("default", &ds, &cur, reps, T1);
      int same = 0;
      for (int i = 0; i < ns[a]; i++) same += T0[i] == T1[i];
      printf("  ratio old/default %.1fx, argmax maps agree on %.4f\n", t0 / t1,
             (double)same / ns[a]);
      free(T0), free(T1);
      free_data(&ds);
    }
  return 0;
}
