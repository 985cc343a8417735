/* test_sinkhorn: sparse log-domain Sinkhorn against a dense reference, tiny eps, recovery
 * of a permutation, feasibility of a clustered configuration, re-truncation, threaded
 * sweeps, bad arguments, cancellation. */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "sm_sinkhorn.h"
#include "sm_test.h"

/* ---------------------------------------------------------------- helpers */

static uint64_t rng_state = 0x9e3779b97f4a7c15ull;

static double urand(void) { /* xorshift64*, uniform in [0, 1) */
  rng_state ^= rng_state >> 12;
  rng_state ^= rng_state << 25;
  rng_state ^= rng_state >> 27;
  return (double)((rng_state * 0x2545f4914f6cdd1dull) >> 11) * 0x1.0p-53;
}

static double nrand(void) {
  double u = urand(), v = urand();
  return sqrt(-2.0 * log(u + 1e-300)) * cos(2.0 * M_PI * v);
}

static double *points(int n, int d, double lo, double hi) {
  double *X = malloc(sizeof(double) * (size_t)n * d);
  for (int t = 0; t < n * d; t++) X[t] = lo + (hi - lo) * urand();
  return X;
}

static double *masses(int n) {
  double *m = malloc(sizeof(double) * (size_t)n), s = 0;
  for (int i = 0; i < n; i++) s += (m[i] = 0.5 + urand());
  for (int i = 0; i < n; i++) m[i] /= s;
  return m;
}

static double sq(const double *x, const double *y, int d) {
  double s = 0;
  for (int t = 0; t < d; t++) s += (x[t] - y[t]) * (x[t] - y[t]);
  return s;
}

static double lse(const double *v, int n, int stride) {
  double m = -INFINITY, s = 0;
  for (int k = 0; k < n; k++) m = fmax(m, v[k * stride]);
  for (int k = 0; k < n; k++) s += exp(v[k * stride] - m);
  return m + log(s);
}

/* Dense log-domain Sinkhorn written independently of the module: P (nx*ny row-major). */
static void dense_sinkhorn(const double *F, int nx, const double *G, int ny, int d,
                           const double *a, const double *b, double eps, double rho,
                           double *P) {
  double *C = malloc(sizeof(double) * nx * ny), *w = malloc(sizeof(double) * (nx + ny));
  double *f = calloc(nx, sizeof(double)), *g = calloc(ny, sizeof(double));
  double lam = rho > 0 ? rho / (rho + eps) : 1.0;
  for (int i = 0; i < nx; i++)
    for (int j = 0; j < ny; j++) C[i * ny + j] = sq(F + i * d, G + j * d, d);
  for (int it = 0; it < 200000; it++) {
    double change = 0;
    for (int i = 0; i < nx; i++) {
      for (int j = 0; j < ny; j++) w[j] = (g[j] - C[i * ny + j]) / eps;
      double v = lam * eps * (log(a[i]) - lse(w, ny, 1));
      change = fmax(change, fabs(v - f[i]));
      f[i] = v;
    }
    for (int j = 0; j < ny; j++) {
      for (int i = 0; i < nx; i++) w[i] = (f[i] - C[i * ny + j]) / eps;
      double v = lam * eps * (log(b[j]) - lse(w, nx, 1));
      change = fmax(change, fabs(v - g[j]));
      g[j] = v;
    }
    if (change < 1e-15 * eps) break;
  }
  for (int i = 0; i < nx; i++)
    for (int j = 0; j < ny; j++) P[i * ny + j] = exp((f[i] + g[j] - C[i * ny + j]) / eps);
  free(C), free(w), free(f), free(g);
}

/* Largest |P_sparse - P_dense| over all pairs (entries off the support count as 0). */
static double plan_vs_dense(const sm_plan *p, const double *P) {
  double *D = calloc((size_t)p->nx * p->ny, sizeof(double)), m = 0;
  for (int i = 0; i < p->nx; i++)
    for (int64_t q = p->rowptr[i]; q < p->rowptr[i + 1]; q++) D[i * p->ny + p->col[q]] = p->val[q];
  for (int t = 0; t < p->nx * p->ny; t++) m = fmax(m, fabs(D[t] - P[t]));
  free(D);
  return m;
}

static int plan_finite(const sm_plan *p) {
  for (int64_t q = 0; q < p->nnz; q++)
    if (!isfinite(p->val[q]) || p->val[q] < 0) return 0;
  for (int i = 0; i < p->nx; i++)
    if (!isfinite(p->f[i])) return 0;
  for (int j = 0; j < p->ny; j++)
    if (!isfinite(p->g[j])) return 0;
  return 1;
}

/* ---------------------------------------------------------------- tests */

/* (1) K = all: the sparse code must reproduce a dense reference at the same eps. */
static void test_dense_reference(double rho) {
  enum { NX = 60, NY = 50, D = 3 };
  double *F = points(NX, D, -1, 1), *G = points(NY, D, -1, 1);
  double *a = masses(NX), *b = masses(NY), *P = malloc(sizeof(double) * NX * NY);
  sm_sinkhorn_opts o;
  sm_sinkhorn_opts_default(&o);
  o.k = 1000;
  o.eps_start = o.eps_end = 0.1;
  o.tol = 1e-13;
  o.max_iter = 20000;
  o.rho = rho;
  sm_plan *p = NULL;
  sm_sinkhorn_stats st;
  sm_error e;
  REQUIRE(sm_sinkhorn(F, NX, G, NY, D, a, b, &o, &p, &st, &e) == 0);
  CHECK(p->nnz == NX * NY && st.nnz_knn == NX * NY);
  double c0 = 0;
  for (int i = 0; i < NX; i++)
    for (int j = 0; j < NY; j++) c0 += sq(F + i * D, G + j * D, D) / (NX * NY);
  CHECK_NEAR(st.c0, c0, 1e-12 * c0);
  CHECK_NEAR(st.eps, 0.1 * c0, 1e-12 * c0);
  dense_sinkhorn(F, NX, G, NY, D, a, b, st.eps, rho * st.c0, P);
  double diff = plan_vs_dense(p, P);
  CHECK_MSG(diff < 1e-10, "rho=%g: max |P - P_dense| = %g", rho, diff);
  CHECK(st.converged);
  if (rho == 0) {
    CHECK_MSG(st.err_a < 1e-12 && st.err_b < 1e-12, "err_a=%g err_b=%g", st.err_a, st.err_b);
  }
  /* scale invariance: eps is relative to c0 */
  for (int t = 0; t < NX * D; t++) F[t] *= 7.0;
  for (int t = 0; t < NY * D; t++) G[t] *= 7.0;
  sm_plan *p2 = NULL;
  REQUIRE(sm_sinkhorn(F, NX, G, NY, D, a, b, &o, &p2, &st, &e) == 0);
  CHECK_MSG(plan_vs_dense(p2, P) < 1e-10, "scaled: %g", plan_vs_dense(p2, P));
  sm_plan_destroy(p), sm_plan_destroy(p2);
  free(F), free(G), free(a), free(b), free(P);
}

/* (2) eps = 1e-6 c0: exp(-C/eps) would underflow to 0 everywhere; the log domain must not. */
static void test_tiny_eps(void) {
  enum { N = 300, D = 3 };
  double *F = points(N, D, 0, 1), *G = points(N, D, 0, 1);
  sm_sinkhorn_opts o;
  sm_sinkhorn_opts_default(&o);
  o.k = 8;
  o.eps_end = 1e-6;
  o.max_iter = 300;
  sm_plan *p = NULL;
  sm_sinkhorn_stats st;
  sm_error e;
  REQUIRE(sm_sinkhorn(F, N, G, N, D, NULL, NULL, &o, &p, &st, &e) == 0);
  CHECK(plan_finite(p));
  CHECK(exp(-st.c0 / st.eps) == 0.0); /* the naive kernel really underflows here */
  /* f + g - C carries rounding ~1e-16 c0, i.e. ~1e-10 relative in P at eps = 1e-6 c0 */
  CHECK_MSG(st.err_a < 1e-4 && st.err_b < 1e-8, "err_a=%g err_b=%g residual=%g", st.err_a,
            st.err_b, st.residual);
  int32_t *T = malloc(sizeof(int32_t) * N);
  sm_plan_row_argmax(p, T);
  double bij = sm_plan_map_distinct(T, N, N);
  CHECK_MSG(bij > 0.95, "bijectivity at eps 1e-6: %g", bij); /* near a permutation */
  fprintf(stderr, "tiny eps: %d levels, %d iterations, residual %.2e, bij %.3f\n", st.levels,
          st.iterations, st.residual, bij);
  sm_plan_destroy(p);
  free(F), free(G), free(T);
}

/* Y = X[perm] + noise, noise well below the nearest-neighbour spacing. */
static void noisy_copy(int n, int d, double sigma, double **X, double **Y, int32_t **perm) {
  *X = points(n, d, 0, 1);
  *Y = malloc(sizeof(double) * (size_t)n * d);
  *perm = malloc(sizeof(int32_t) * n); /* X point i is Y point perm[i] */
  for (int i = 0; i < n; i++) (*perm)[i] = i;
  for (int i = n - 1; i > 0; i--) {
    int j = (int)(urand() * (i + 1));
    int32_t t = (*perm)[i];
    (*perm)[i] = (*perm)[j], (*perm)[j] = t;
  }
  for (int i = 0; i < n; i++)
    for (int t = 0; t < d; t++) (*Y)[(size_t)(*perm)[i] * d + t] = (*X)[(size_t)i * d + t] + sigma * nrand();
}

/* (3) small K recovers a permutation; the kd-tree and brute force give the same support. */
static void test_permutation(int n, int d, int knn) {
  double *X, *Y;
  int32_t *perm, *T = malloc(sizeof(int32_t) * n), *Tb = malloc(sizeof(int32_t) * n);
  noisy_copy(n, d, 0.01, &X, &Y, &perm);
  sm_sinkhorn_opts o;
  sm_sinkhorn_opts_default(&o);
  o.k = 5;
  o.knn = knn;
  sm_plan *p = NULL;
  sm_sinkhorn_stats st;
  sm_error e;
  REQUIRE(sm_sinkhorn(X, n, Y, n, d, NULL, NULL, &o, &p, &st, &e) == 0);
  sm_plan_row_argmax(p, T);
  REQUIRE(sm_plan_extract_bijective(p, Tb, &e) == 0);
  int hit = 0, hitb = 0;
  for (int i = 0; i < n; i++) hit += T[i] == perm[i], hitb += Tb[i] == perm[i];
  double bij = sm_plan_map_distinct(T, n, n), bijb = sm_plan_map_distinct(Tb, n, n);
  CHECK_MSG(hit >= 0.99 * n, "argmax recovers %d / %d", hit, n);
  CHECK_MSG(bij >= 0.99, "bijectivity %g", bij);
  CHECK_MSG(hitb >= hit && bijb >= bij, "bijective extraction: %d hits, %g", hitb, bijb);
  CHECK(st.converged && st.err_a < 1e-5 && st.err_b < 1e-12);
  int32_t *Tyx = malloc(sizeof(int32_t) * n);
  REQUIRE(sm_plan_col_argmax(p, Tyx) == 0);
  int back = 0;
  for (int i = 0; i < n; i++) back += Tyx[perm[i]] == i;
  CHECK_MSG(back >= 0.99 * n, "column argmax recovers %d / %d", back, n);
  fprintf(stderr, "perm n=%d d=%d knn=%d: hits %d/%d (bijective %d), bij %.4f, nnz %lld, "
          "%d it, knn %.3fs iter %.3fs\n", n, d, knn, hit, n, hitb, bij, (long long)st.nnz,
          st.iterations, st.t_knn, st.t_iter);
  if (knn == SM_KNN_KDTREE) { /* both neighbour searches are exact: same support */
    sm_plan *q = NULL;
    o.knn = SM_KNN_BRUTE;
    REQUIRE(sm_sinkhorn(X, n, Y, n, d, NULL, NULL, &o, &q, &st, &e) == 0);
    CHECK(q->nnz == p->nnz && memcmp(q->col, p->col, sizeof(int32_t) * p->nnz) == 0);
    sm_plan_destroy(q);
  }
  sm_plan_destroy(p);
  free(X), free(Y), free(perm), free(T), free(Tb), free(Tyx);
}

/* (4) X clustered, Y spread: every f_i has the same few nearest g's, so the K-NN support
 * alone admits no plan with uniform marginals. */
static void test_feasibility(void) {
  enum { NX = 400, NY = 300, D = 3 };
  double *F = malloc(sizeof(double) * NX * D), *G = points(NY, D, -1, 1);
  for (int t = 0; t < NX * D; t++) F[t] = 1e-3 * nrand();
  sm_sinkhorn_opts o;
  sm_sinkhorn_opts_default(&o);
  o.k = 5;
  o.max_iter = 300;
  sm_plan *p = NULL;
  sm_sinkhorn_stats st;
  sm_error e;
  /* without the backbone the balanced iteration cannot meet the marginals */
  o.no_backbone = 1;
  REQUIRE(sm_sinkhorn(F, NX, G, NY, D, NULL, NULL, &o, &p, &st, &e) == 0);
  CHECK(plan_finite(p));
  CHECK_MSG(!st.converged && st.err_a > 0.1, "K-NN only: err_a=%g", st.err_a);
  fprintf(stderr, "feasibility, K-NN only: err_a %.3g err_b %.3g\n", st.err_a, st.err_b);
  sm_plan_destroy(p);
  /* default (balanced + backbone): marginals met */
  o.no_backbone = 0;
  REQUIRE(sm_sinkhorn(F, NX, G, NY, D, NULL, NULL, &o, &p, &st, &e) == 0);
  CHECK(plan_finite(p));
  /* Feasible, but the K-NN entries that no feasible plan can use must decay to 0 with
   * diverging duals: convergence is sublinear (documented), far better than without */
  CHECK_MSG(st.err_a < 1e-2 && st.err_b < 1e-12, "backbone: err_a=%g err_b=%g", st.err_a,
            st.err_b);
  fprintf(stderr, "feasibility, backbone: err_a %.3g err_b %.3g, %d it, nnz %lld (K-NN %lld)\n",
          st.err_a, st.err_b, st.iterations, (long long)st.nnz, (long long)st.nnz_knn);
  sm_plan_destroy(p);
  /* unbalanced without the backbone: always feasible; marginals are relaxed, not met */
  o.no_backbone = 1;
  o.rho = 1.0;
  REQUIRE(sm_sinkhorn(F, NX, G, NY, D, NULL, NULL, &o, &p, &st, &e) == 0);
  CHECK(plan_finite(p) && st.converged);
  double mass = 0;
  for (int64_t q = 0; q < p->nnz; q++) mass += p->val[q];
  CHECK_MSG(mass > 0 && mass <= 1.0 + 1e-9, "unbalanced mass %g", mass);
  fprintf(stderr, "feasibility, unbalanced rho=1: mass %.3f err_a %.3g err_b %.3g\n", mass,
          st.err_a, st.err_b);
  sm_plan_destroy(p);
  free(F), free(G);
}

/* Re-truncation from the duals turns a too-small K-NN support into the support of the
 * dense solution: the result matches a dense solve at the same eps. */
static void test_retruncation(void) {
  enum { NX = 150, NY = 120, D = 3 };
  double *F = points(NX, D, -1, 1), *G = points(NY, D, -1, 1), *a = masses(NX), *b = masses(NY);
  double *P = malloc(sizeof(double) * NX * NY);
  sm_sinkhorn_opts o;
  sm_sinkhorn_opts_default(&o);
  o.k = 5;
  o.eps_end = 0.05;
  o.tol = 1e-13;
  o.max_iter = 3000;
  o.theta = 30;
  sm_plan *p = NULL;
  sm_sinkhorn_stats st;
  sm_error e;
  REQUIRE(sm_sinkhorn(F, NX, G, NY, D, a, b, &o, &p, &st, &e) == 0);
  dense_sinkhorn(F, NX, G, NY, D, a, b, st.eps, 0, P);
  double diff = plan_vs_dense(p, P);
  CHECK_MSG(diff < 1e-10, "re-truncated vs dense: %g (nnz %lld)", diff, (long long)st.nnz);
  CHECK(st.converged);
  fprintf(stderr, "re-truncation: nnz %lld of %d, |P - P_dense| %.2g\n", (long long)st.nnz,
          NX * NY, diff);
  sm_plan_destroy(p);
  o.theta = 1e6; /* keeps everything (150 x 120 is below the support limit) */
  REQUIRE(sm_sinkhorn(F, NX, G, NY, D, a, b, &o, &p, &st, &e) == 0);
  CHECK(p->nnz == NX * NY);
  sm_plan_destroy(p);
  free(F), free(G), free(a), free(b), free(P);
}

/* Kernel scaling with absorption against the plain log-domain iteration on the same
 * problem: the same iterates in exact arithmetic, so the plans agree to rounding, down to
 * eps where the kernel exp(-C/eps) underflows. Cold starts at a tiny eps (f = g = 0, the
 * kernel sums vanish) and large eps steps force the fallback and the absorptions. */
static void test_absorption_vs_log_domain(void) {
  enum { NX = 80, NY = 70, D = 3, NC = 6 };
  double *F = points(NX, D, -1, 1), *G = points(NY, D, -1, 1), *a = masses(NX), *b = masses(NY);
  struct { int k; double rho, eps_start, eps_end, decay; int absorbs; } cs[NC] = {
      {1000, 0, 1, 1e-4, 0.5, 0},     {5, 0, 1, 1e-3, 0.5, 0},
      {5, 0.5, 1, 1e-3, 0.5, 0},      {1000, 0.2, 1, 1e-5, 0.5, 0},
      {1000, 0, 1e-4, 1e-4, 0.5, 1},  {5, 0, 1, 1e-5, 0.01, 1}};
  for (int c = 0; c < NC; c++) {
    sm_sinkhorn_opts o;
    sm_sinkhorn_opts_default(&o);
    o.k = cs[c].k, o.rho = cs[c].rho, o.eps_start = cs[c].eps_start;
    o.eps_end = cs[c].eps_end, o.decay = cs[c].decay;
    o.max_iter = 100, o.tol = 1e-15;
    sm_plan *p = NULL, *q = NULL;
    sm_sinkhorn_stats st, sq_;
    sm_error e;
    REQUIRE(sm_sinkhorn(F, NX, G, NY, D, a, b, &o, &p, &st, &e) == 0);
    o.log_domain = 1;
    REQUIRE(sm_sinkhorn(F, NX, G, NY, D, a, b, &o, &q, &sq_, &e) == 0);
    REQUIRE(p->nnz == q->nnz);
    double m = 0;
    for (int64_t t = 0; t < p->nnz; t++) m = fmax(m, fabs(p->val[t] - q->val[t]));
    CHECK_MSG(m < 1e-9, "case %d: max |P_scaling - P_log| = %g", c, m);
    CHECK(memcmp(p->col, q->col, sizeof(int32_t) * (size_t)p->nnz) == 0);
    CHECK(plan_finite(p) && sq_.absorptions == 0);
    CHECK_MSG(st.iterations == sq_.iterations || (st.converged && sq_.converged),
              "case %d: %d vs %d iterations", c, st.iterations, sq_.iterations);
    if (cs[c].absorbs) {
      CHECK(exp(-st.c0 / st.eps) == 0.0); /* exp(-C/eps) underflows */
      CHECK_MSG(st.absorptions > 0, "case %d: no absorption", c);
    }
    fprintf(stderr, "absorption vs log domain, case %d: |dP| %.2g, %d it, %d absorptions\n", c,
            m, st.iterations, st.absorptions);
    sm_plan_destroy(p), sm_plan_destroy(q);
  }
  free(F), free(G), free(a), free(b);
}

/* Threaded sweeps (from 32,768 support entries: (nx + ny) k) compute every value as one
 * thread does: the same plan, duals and iteration counts bit for bit, whatever the
 * thread count; balanced and unbalanced, with absorptions and a re-truncation. */
static void test_threads_same_plan(void) {
  enum { NX = 3000, NY = 2600, D = 4, NC = 3 };
  double *F = points(NX, D, -1, 1), *G = points(NY, D, -1, 1), *a = masses(NX), *b = masses(NY);
  struct { double rho, eps_end, decay, theta; } cs[NC] = {
      {0, 1e-3, 0.5, 0}, {0.3, 1e-3, 0.5, 0}, {0, 1e-5, 0.05, 20}};
  for (int c = 0; c < NC; c++) {
    sm_plan *p[3] = {NULL, NULL, NULL};
    sm_sinkhorn_stats st[3];
    for (int t = 0; t < 3; t++) {
      sm_sinkhorn_opts o;
      sm_sinkhorn_opts_default(&o);
      o.k = 8, o.rho = cs[c].rho, o.eps_end = cs[c].eps_end, o.decay = cs[c].decay;
      o.theta = cs[c].theta, o.max_iter = 60, o.tol = 1e-12, o.threads = t + 1;
      sm_error e;
      REQUIRE(sm_sinkhorn(F, NX, G, NY, D, a, b, &o, &p[t], &st[t], &e) == 0);
    }
    for (int t = 1; t < 3; t++) {
      int same = p[t]->nnz == p[0]->nnz && st[t].iterations == st[0].iterations &&
                 st[t].absorptions == st[0].absorptions &&
                 !memcmp(p[t]->val, p[0]->val, sizeof(double) * (size_t)p[0]->nnz) &&
                 !memcmp(p[t]->f, p[0]->f, sizeof(double) * NX) &&
                 !memcmp(p[t]->g, p[0]->g, sizeof(double) * NY);
      CHECK_MSG(same, "case %d, %d threads: plan differs from one thread's", c, t + 1);
    }
    CHECK_MSG(cs[c].decay > 0.1 || st[0].absorptions > 0, "case %d: no absorption", c);
    fprintf(stderr, "threads, case %d: nnz %lld, %d iterations, %d absorptions\n", c,
            (long long)st[0].nnz, st[0].iterations, st[0].absorptions);
    for (int t = 0; t < 3; t++) sm_plan_destroy(p[t]);
  }
  free(F), free(G), free(a), free(b);
}

static int expect_einval(const char *what, int rc, const sm_error *e, const sm_plan *p) {
  CHECK_MSG(rc == SM_EINVAL && e->code == SM_EINVAL && e->msg[0] && !p, "%s: rc=%d msg='%s'",
            what, rc, e->msg);
  return 0;
}

/* (5) bad arguments. */
static void test_bad_args(void) {
  double F[6] = {0, 0, 1, 1, 2, 2}, G[6] = {0, 1, 1, 0, 2, 1}, a[3] = {0.5, 0.5, 0.5};
  sm_sinkhorn_opts o;
  sm_plan *p = NULL;
  sm_error e;
  sm_sinkhorn_opts_default(&o);
  expect_einval("F NULL", sm_sinkhorn(NULL, 3, G, 3, 2, NULL, NULL, &o, &p, NULL, &e), &e, p);
  expect_einval("nx 0", sm_sinkhorn(F, 0, G, 3, 2, NULL, NULL, &o, &p, NULL, &e), &e, p);
  expect_einval("d 0", sm_sinkhorn(F, 3, G, 3, 0, NULL, NULL, &o, &p, NULL, &e), &e, p);
  CHECK(sm_sinkhorn(F, 3, G, 3, 2, NULL, NULL, &o, NULL, NULL, &e) == SM_EINVAL);
  expect_einval("mass sum", sm_sinkhorn(F, 3, G, 3, 2, a, NULL, &o, &p, NULL, &e), &e, p);
  a[0] = -0.5;
  expect_einval("mass < 0", sm_sinkhorn(F, 3, G, 3, 2, NULL, a, &o, &p, NULL, &e), &e, p);
  struct { const char *what; sm_sinkhorn_opts o; } bad[8];
  for (int t = 0; t < 8; t++) sm_sinkhorn_opts_default(&bad[t].o);
  bad[0].what = "k < 0", bad[0].o.k = -1;
  bad[1].what = "eps_end > eps_start", bad[1].o.eps_end = 2;
  bad[2].what = "decay > 1", bad[2].o.decay = 1.5;
  bad[3].what = "rho < 0", bad[3].o.rho = -1;
  bad[4].what = "tol < 0", bad[4].o.tol = -1e-3;
  bad[5].what = "theta NaN", bad[5].o.theta = NAN;
  bad[6].what = "knn", bad[6].o.knn = 7;
  bad[7].what = "eps_start inf", bad[7].o.eps_start = INFINITY;
  for (int t = 0; t < 8; t++)
    expect_einval(bad[t].what, sm_sinkhorn(F, 3, G, 3, 2, NULL, NULL, &bad[t].o, &p, NULL, &e), &e, p);
  G[3] = NAN;
  CHECK(sm_sinkhorn(F, 3, G, 3, 2, NULL, NULL, &o, &p, NULL, &e) == SM_ENONFINITE && !p);
  CHECK(strstr(e.msg, "G[1][1]") != NULL);
  /* NULL options = defaults */
  G[3] = 0;
  CHECK(sm_sinkhorn(F, 3, G, 3, 2, NULL, NULL, NULL, &p, NULL, &e) == 0 && p);
  sm_plan_destroy(p);
}

static int cancel_after(void *ud) { return --*(int *)ud < 0; }

static void test_cancel(void) {
  double *F = points(100, 3, 0, 1), *G = points(100, 3, 0, 1);
  int budget = 5;
  sm_sinkhorn_opts o;
  sm_sinkhorn_opts_default(&o);
  o.cancel = cancel_after;
  o.cancel_ud = &budget;
  sm_plan *p = NULL;
  sm_sinkhorn_stats st;
  sm_error e;
  CHECK(sm_sinkhorn(F, 100, G, 100, 3, NULL, NULL, &o, &p, &st, &e) == SM_ECANCELED);
  CHECK(!p && st.iterations == 5 && e.code == SM_ECANCELED);
  free(F), free(G);
}

int main(void) {
  test_dense_reference(0.0);
  test_dense_reference(0.5);
  test_tiny_eps();
  test_permutation(3000, 8, SM_KNN_KDTREE);
  test_permutation(2000, 30, SM_KNN_AUTO);
  test_feasibility();
  test_retruncation();
  test_absorption_vs_log_domain();
  test_threads_same_plan();
  test_bad_args();
  test_cancel();
  return sm_test_finish();
}
