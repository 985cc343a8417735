/* Nearest neighbours (both strategies against a naive search, ties and duplicates
 * included) and functional maps: P -> C -> P consistency in the LB and the elastic basis,
 * the non-orthogonal C -> P against its formula, the LB path against a direct classic
 * ZoomOut, and ZoomOut recovering a vertex permutation (LB, elastic, hybrid). */
#include <string.h>

#include <cblas.h>

#include "sm_basis.h"
#include "sm_fmap.h"
#include "sm_knn.h"
#include "sm_mesh.h"
#include "sm_test.h"
#include "sm_testmesh.h"

/* ---- kNN ---------------------------------------------------------------------------- */

/* Reference: every distance, then K smallest by (distance, index). */
static void naive_knn(const double *Y, int ny, const double *x, int d, int K, int32_t *idx,
                      double *dist) {
  int cnt = 0;
  for (int j = 0; j < ny; j++) {
    double s = sm_knn_dist2(x, Y + (size_t)j * d, d);
    if (cnt == K && s >= dist[K - 1]) continue;
    int p = cnt < K ? cnt++ : K - 1;
    while (p > 0 && dist[p - 1] > s) {
      dist[p] = dist[p - 1];
      idx[p] = idx[p - 1];
      p--;
    }
    dist[p] = s;
    idx[p] = j;
  }
}

/* Checks a kNN answer against the naive one; exact_idx: indices must match too (no ties,
 * or the brute-force rule "lowest index among equals"). Returns rows that differ. */
static int compare_knn(const double *Y, int ny, const double *X, int nx, int d, int K,
                       const int32_t *idx, const double *dist, int exact_idx) {
  int32_t *ri = malloc((size_t)K * sizeof *ri);
  double *rd = malloc((size_t)K * sizeof *rd);
  int bad = 0;
  for (int i = 0; i < nx; i++) {
    const double *x = X + (size_t)i * d;
    naive_knn(Y, ny, x, d, K, ri, rd);
    int ok = 1;
    for (int r = 0; r < K; r++) {
      const int32_t *iv = idx + (size_t)i * K;
      ok &= iv[r] >= 0 && iv[r] < ny;
      ok &= dist[(size_t)i * K + r] == rd[r];
      if (ok) ok &= sm_knn_dist2(x, Y + (size_t)iv[r] * d, d) == dist[(size_t)i * K + r];
      for (int q = 0; q < r; q++) ok &= iv[q] != iv[r];
      if (exact_idx) ok &= iv[r] == ri[r];
    }
    bad += !ok;
  }
  free(ri);
  free(rd);
  return bad;
}

/* The same query without distances (dist NULL: brute force then skips the exact distance
 * of a certified single nearest) must give the indices idx of the checked query. */
static int same_without_dist(const sm_knn *ix, const double *X, int nx, int ny, int K,
                             const int32_t *idx, const int32_t *iyx) {
  int32_t *a = malloc((size_t)nx * K * sizeof *a), *b = malloc((size_t)ny * K * sizeof *b);
  sm_error err;
  int rc = iyx ? sm_knn_query_both(ix, X, nx, K, a, NULL, b, NULL, &err)
               : sm_knn_query(ix, X, nx, K, a, NULL, &err);
  int same = rc == 0 && !memcmp(a, idx, (size_t)nx * K * sizeof *a) &&
             (!iyx || !memcmp(b, iyx, (size_t)ny * K * sizeof *b));
  free(a);
  free(b);
  return same;
}

/* Brute-force query threads of run_knn and run_knn_both (test_knn_threads). */
static int g_query_threads = 1;

static int run_knn(const double *Y, int ny, const double *X, int nx, int d, int K, int strat,
                   int exact_idx) {
  sm_knn_opts o;
  sm_knn_opts_default(&o);
  o.strategy = strat;
  o.query_threads = g_query_threads;
  sm_knn *ix = NULL;
  sm_error err;
  int32_t *idx = malloc((size_t)nx * K * sizeof *idx);
  double *dist = malloc((size_t)nx * K * sizeof *dist);
  int rc = sm_knn_build(Y, ny, d, &o, &ix, &err);
  if (!rc) rc = sm_knn_query(ix, X, nx, K, idx, dist, &err);
  if (rc) fprintf(stderr, "knn: %s\n", err.msg);
  REQUIRE(rc == 0);
  CHECK(sm_knn_strategy_of(ix) == strat);
  int bad = compare_knn(Y, ny, X, nx, d, K, idx, dist, exact_idx);
  CHECK_MSG(bad == 0, "strategy %d d=%d K=%d ny=%d: %d of %d rows differ", strat, d, K, ny, bad,
            nx);
  CHECK_MSG(same_without_dist(ix, X, nx, ny, K, idx, NULL),
            "strategy %d d=%d K=%d: no-distance query differs", strat, d, K);
  sm_knn_destroy(ix);
  free(idx);
  free(dist);
  return bad;
}

/* sm_knn_query_both against the naive search both ways: rows of X among Y, and points of
 * Y among the rows of X. */
static int run_knn_both(const double *Y, int ny, const double *X, int nx, int d, int K,
                        int strat, int exact_idx) {
  sm_knn_opts o;
  sm_knn_opts_default(&o);
  o.strategy = strat;
  o.query_threads = g_query_threads;
  sm_knn *ix = NULL;
  sm_error err;
  int32_t *idx = malloc((size_t)nx * K * sizeof *idx), *iyx = malloc((size_t)ny * K * sizeof *iyx);
  double *dist = malloc((size_t)nx * K * sizeof *dist), *dyx = malloc((size_t)ny * K * sizeof *dyx);
  int rc = sm_knn_build(Y, ny, d, &o, &ix, &err);
  if (!rc) rc = sm_knn_query_both(ix, X, nx, K, idx, dist, iyx, dyx, &err);
  if (rc) fprintf(stderr, "knn both: %s\n", err.msg);
  REQUIRE(rc == 0);
  int bad = compare_knn(Y, ny, X, nx, d, K, idx, dist, exact_idx);
  int bad_yx = compare_knn(X, nx, Y, ny, d, K, iyx, dyx, exact_idx);
  CHECK_MSG(bad == 0 && bad_yx == 0,
            "two-way strategy %d d=%d K=%d nx=%d ny=%d: %d + %d rows differ", strat, d, K, nx,
            ny, bad, bad_yx);
  CHECK_MSG(same_without_dist(ix, X, nx, ny, K, idx, iyx),
            "two-way strategy %d d=%d K=%d: no-distance query differs", strat, d, K);
  sm_knn_destroy(ix);
  free(idx);
  free(iyx);
  free(dist);
  free(dyx);
  return bad + bad_yx;
}

static double *random_points(int n, int d, double lo, double hi, uint64_t *s) {
  double *P = malloc((size_t)n * d * sizeof *P);
  for (int64_t i = 0; i < (int64_t)n * d; i++) P[i] = lo + (hi - lo) * tm_rand(s);
  return P;
}

static void test_knn_random(void) {
  uint64_t s = 20240611;
  const int dims[] = {1, 2, 3, 7, 16, 33, 100, 257};
  const int Ks[] = {1, 4, 17};
  for (size_t a = 0; a < sizeof dims / sizeof *dims; a++)
    for (size_t b = 0; b < sizeof Ks / sizeof *Ks; b++) {
      int d = dims[a], K = Ks[b], ny = d >= 100 ? 2300 : 2500, nx = 301;
      double *Y = random_points(ny, d, -1, 1, &s), *X = random_points(nx, d, -1, 1, &s);
      run_knn(Y, ny, X, nx, d, K, SM_KNN_BRUTE, 1);
      run_knn(Y, ny, X, nx, d, K, SM_KNN_KDTREE, 1);
      if (a % 2 == 0) {
        run_knn_both(Y, ny, X, nx, d, K, SM_KNN_BRUTE, 1);
        run_knn_both(Y, ny, X, nx, d, K, SM_KNN_KDTREE, 1);
      }
      free(Y);
      free(X);
    }
}

/* Integer lattice points with every point repeated: distance ties everywhere. */
static void test_knn_ties(void) {
  uint64_t s = 99;
  const int dims[] = {1, 3, 40};
  for (size_t a = 0; a < sizeof dims / sizeof *dims; a++) {
    int d = dims[a], ny = 2600, nx = 200;
    double *Y = malloc((size_t)ny * d * sizeof *Y), *X = malloc((size_t)nx * d * sizeof *X);
    for (int j = 0; j < ny / 2; j++)
      for (int t = 0; t < d; t++) Y[(size_t)j * d + t] = floor(4 * tm_rand(&s));
    memcpy(Y + (size_t)(ny / 2) * d, Y, (size_t)(ny / 2) * d * sizeof *Y); /* duplicates */
    for (int i = 0; i < nx; i++)
      for (int t = 0; t < d; t++) X[(size_t)i * d + t] = floor(4 * tm_rand(&s)) + (i % 2) * 0.5;
    for (int K = 1; K <= 9; K += 4) {
      run_knn(Y, ny, X, nx, d, K, SM_KNN_BRUTE, 1);   /* lowest index among equals */
      run_knn(Y, ny, X, nx, d, K, SM_KNN_KDTREE, 0);  /* same distances, any tied index */
      run_knn_both(Y, ny, X, nx, d, K, SM_KNN_BRUTE, 1);
    }
    run_knn(Y, 7, X, nx, d, 7, SM_KNN_BRUTE, 1); /* K = ny */
    run_knn(Y, 7, X, nx, d, 7, SM_KNN_KDTREE, 0);
    free(Y);
    free(X);
  }
}

/* Two far clusters with tiny spreads: |x|^2 + |y|^2 - 2 x.y cancels catastrophically, so
 * brute force must fall back to direct differences and still be exact. */
static void test_knn_cancellation(void) {
  uint64_t s = 5;
  int d = 30, ny = 600, nx = 100;
  double *Y = random_points(ny, d, 0, 1e-6, &s), *X = random_points(nx, d, 0, 1e-6, &s);
  for (int j = 0; j < ny; j++) Y[(size_t)j * d] += j % 2 ? 1e6 : -1e6;
  for (int i = 0; i < nx; i++) X[(size_t)i * d] += i % 2 ? 1e6 : -1e6;
  run_knn(Y, ny, X, nx, d, 3, SM_KNN_BRUTE, 1);
  run_knn(Y, ny, X, nx, d, 3, SM_KNN_KDTREE, 1);
  run_knn_both(Y, ny, X, nx, d, 3, SM_KNN_BRUTE, 1);
  free(Y);
  free(X);
}

/* Brute force screens in float32 after scaling Y by a power of two: coordinates near the
 * ends of the double range, and queries far outside Y (not screenable in float), must
 * still give the exact answer. */
static void test_knn_scales(void) {
  uint64_t s = 77;
  int d = 24, ny = 1500, nx = 120;
  const double scales[] = {1e-150, 1e-30, 1e30, 1e150};
  for (size_t a = 0; a < sizeof scales / sizeof *scales; a++) {
    double *Y = random_points(ny, d, -1, 1, &s), *X = random_points(nx, d, -1, 1, &s);
    for (int64_t i = 0; i < (int64_t)ny * d; i++) Y[i] *= scales[a];
    for (int i = 0; i < nx; i++) {
      double far = i % 3 == 0 ? 1e20 : i % 3 == 1 ? 1e3 : 1; /* outside, near, inside */
      for (int t = 0; t < d; t++) X[(size_t)i * d + t] *= far * scales[a];
    }
    for (int K = 1; K <= 17; K += 8) {
      run_knn(Y, ny, X, nx, d, K, SM_KNN_BRUTE, 1);
      run_knn_both(Y, ny, X, nx, d, K, SM_KNN_BRUTE, 1); /* far rows: two queries */
      run_knn_both(Y, ny, X + (size_t)2 * d, 40, d, K, SM_KNN_BRUTE, 1); /* rows 2, 5, ...: inside */
    }
    free(Y);
    free(X);
  }
}

/* A factored index (y = L u) against the naive search on Y = U L^T, one-way and two-way.
 * Dyadic entries (dyadic = 1) make Y exact whatever the summation order, and put many
 * points at equal distances; otherwise Y comes from the same dgemm the index uses, or,
 * with caller_y, from a plain loop in reverse order (rounded differently) that the index
 * borrows: the answers must be exact for that Y. */
static void run_knn_factored_y(int ny, int dr, int d, int nx, int K, int dyadic, double far,
                               int caller_y, uint64_t *s) {
  double *U = random_points(ny, dr, -1, 1, s), *L = random_points(d, dr, -1, 1, s);
  double *X = random_points(nx, d, -1, 1, s), *Y = malloc((size_t)ny * d * sizeof *Y);
  if (dyadic) {
    for (int64_t i = 0; i < (int64_t)ny * dr; i++) U[i] = floor(8 * U[i]) / 8;
    for (int64_t i = 0; i < (int64_t)d * dr; i++) L[i] = floor(4 * L[i]) / 4;
    for (int64_t i = 0; i < (int64_t)nx * d; i++) X[i] = floor(8 * X[i]) / 4;
  }
  for (int i = 0; i < nx; i += 3)
    for (int t = 0; t < d; t++) X[(size_t)i * d + t] *= far; /* every third row far out */
  cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, ny, d, dr, 1.0, U, dr, L, dr, 0.0, Y, d);
  for (int j = 0; caller_y && j < ny; j++)
    for (int t = 0; t < d; t++) {
      double v = 0;
      for (int q = dr - 1; q >= 0; q--) v += L[(size_t)t * dr + q] * U[(size_t)j * dr + q];
      Y[(size_t)j * d + t] = v;
    }
  int32_t *idx = malloc((size_t)nx * K * sizeof *idx), *iyx = malloc((size_t)ny * K * sizeof *iyx);
  double *dist = malloc((size_t)nx * K * sizeof *dist), *dyx = malloc((size_t)ny * K * sizeof *dyx);
  sm_knn *ix = NULL;
  sm_error err;
  sm_knn_opts ko;
  sm_knn_opts_default(&ko);
  ko.query_threads = g_query_threads;
  int rc = sm_knn_build_factored(U, ny, dr, L, d, caller_y ? Y : NULL, &ko, &ix, &err);
  if (!rc) rc = sm_knn_query(ix, X, nx, K, idx, dist, &err);
  if (rc) fprintf(stderr, "knn factored: %s\n", err.msg);
  REQUIRE(rc == 0);
  CHECK(sm_knn_strategy_of(ix) == SM_KNN_BRUTE);
  int bad = compare_knn(Y, ny, X, nx, d, K, idx, dist, 1);
  rc = sm_knn_query_both(ix, X, nx, K, idx, dist, iyx, dyx, &err);
  REQUIRE(rc == 0);
  int bad2 = compare_knn(Y, ny, X, nx, d, K, idx, dist, 1);
  int bad_yx = compare_knn(X, nx, Y, ny, d, K, iyx, dyx, 1);
  CHECK_MSG(bad == 0 && bad2 == 0 && bad_yx == 0,
            "factored dr=%d d=%d K=%d dyadic=%d far=%g caller_y=%d: %d / %d + %d rows differ",
            dr, d, K, dyadic, far, caller_y, bad, bad2, bad_yx);
  CHECK_MSG(same_without_dist(ix, X, nx, ny, K, idx, iyx),
            "factored dr=%d d=%d K=%d dyadic=%d: no-distance query differs", dr, d, K, dyadic);
  sm_knn_destroy(ix);
  free(U), free(L), free(X), free(Y), free(idx), free(iyx), free(dist), free(dyx);
}

static void run_knn_factored(int ny, int dr, int d, int nx, int K, int dyadic, double far,
                             uint64_t *s) {
  run_knn_factored_y(ny, dr, d, nx, K, dyadic, far, 0, s);
}

static void test_knn_factored(void) {
  uint64_t s = 4711;
  run_knn_factored_y(2100, 40, 80, 300, 1, 0, 1, 1, &s);
  run_knn_factored_y(1500, 12, 24, 200, 3, 0, 1e3, 1, &s);
  run_knn_factored(2100, 20, 40, 300, 1, 0, 1, &s);
  run_knn_factored(2100, 50, 100, 301, 3, 0, 1, &s);
  run_knn_factored(1500, 7, 31, 200, 5, 0, 1, &s);
  run_knn_factored(1500, 12, 24, 200, 4, 1, 1, &s);  /* ties */
  run_knn_factored(1300, 16, 32, 150, 1, 1, 1, &s);
  run_knn_factored(1300, 16, 32, 150, 2, 0, 1e20, &s); /* rows too far to screen */
  run_knn_factored(1300, 16, 32, 150, 2, 0, 1e3, &s);
  double U[4] = {0, 1, 2, 3}, L[2] = {1, 0};
  sm_knn *ix = NULL;
  sm_error err;
  CHECK(sm_knn_build_factored(U, 4, 1, L, 0, NULL, NULL, &ix, &err) == SM_EINVAL && !ix);
  U[2] = NAN;
  CHECK(sm_knn_build_factored(U, 4, 1, L, 2, NULL, NULL, &ix, &err) == SM_ENONFINITE && !ix);
  U[2] = INFINITY;
  CHECK(sm_knn_build_factored(U, 4, 1, L, 2, NULL, NULL, &ix, &err) == SM_ENONFINITE && !ix);
  CHECK_MSG(strstr(err.msg, "U value 2"), "factored U: '%s'", err.msg);
  U[2] = 2;
  double Yc[8] = {0, 0, 1, 0, 2, NAN, 3, 0}; /* a caller's rows Y = U L^T, one not finite */
  CHECK(sm_knn_build_factored(U, 4, 1, L, 2, Yc, NULL, &ix, &err) == SM_ENONFINITE && !ix);
  CHECK_MSG(strstr(err.msg, "value 5"), "factored Y: '%s'", err.msg);
}

/* Non-finite points of a brute-force index are refused and named, one thread or several
 * (its passes over Y run in parts from 2^18 values: the check rides on them). */
static void test_knn_nonfinite(void) {
  sm_knn_opts o;
  sm_knn_opts_default(&o);
  o.strategy = SM_KNN_BRUTE;
  const double bad[3] = {NAN, INFINITY, -INFINITY};
  for (int th = 1; th <= 2; th++)
    for (int n = 5; n <= 5000; n += 4995) {
      int d = 100;
      double *Y = calloc((size_t)n * d, sizeof *Y);
      for (int b = 0; b < 3; b++) {
        o.query_threads = th;
        size_t at = (size_t)(n - 1) * d + 7;
        Y[at] = bad[b];
        sm_knn *ix = NULL;
        sm_error err;
        CHECK(sm_knn_build(Y, n, d, &o, &ix, &err) == SM_ENONFINITE && !ix);
        char want[64];
        snprintf(want, sizeof want, "Y value %zu ", at);
        CHECK_MSG(strstr(err.msg, want), "n=%d threads %d: '%s'", n, th, err.msg);
        Y[at] = 1e300; /* finite: its square overflows, which is no error */
        CHECK(sm_knn_build(Y, n, d, &o, &ix, &err) == 0);
        sm_knn_destroy(ix);
        Y[at] = 0;
      }
      free(Y);
    }
}

/* Query rows split over threads (whole blocks of 256 rows; >= 2^20 pairs): the same
 * exact answers, ties included (the merged column lists must keep the lowest row). A
 * two-way query splits its rows only from 8 product dimensions per column-list entry (K +
 * 4): d = 100 and the factored dr = 48 / 64 below take that path; d = 20 splits the two
 * directions instead (one thread the rows' lists, one the columns'). */
static void test_knn_threads(void) {
  uint64_t s = 31337;
  for (int th = 2; th <= 3; th++) {
    g_query_threads = th;
    for (int d = 20; d <= 100; d += 80) {
      int ny = 1900, nx = 1100;
      double *Y = random_points(ny, d, -1, 1, &s), *X = random_points(nx, d, -1, 1, &s);
      run_knn(Y, ny, X, nx, d, 3, SM_KNN_BRUTE, 1);
      run_knn_both(Y, ny, X, nx, d, 1, SM_KNN_BRUTE, 1);
      run_knn_both(Y, ny, X, nx, d, 5, SM_KNN_BRUTE, 1);
      for (int64_t i = 0; i < (int64_t)ny * d; i++) Y[i] = floor(3 * Y[i]); /* ties */
      for (int64_t i = 0; i < (int64_t)nx * d; i++) X[i] = floor(3 * X[i]);
      run_knn(Y, ny, X, nx, d, 4, SM_KNN_BRUTE, 1);
      run_knn_both(Y, ny, X, nx, d, 4, SM_KNN_BRUTE, 1);
      free(Y);
      free(X);
    }
    run_knn_factored(2000, 48, 96, 1300, 1, 0, 1, &s);
    run_knn_factored(2000, 64, 128, 1300, 3, 1, 1, &s);
  }
  g_query_threads = 1;
}

static void test_knn_errors(void) {
  double Y[6] = {0, 1, 2, 3, 4, 5}, X[2] = {0, NAN};
  sm_knn *ix = NULL;
  sm_error err;
  CHECK(sm_knn_build(Y, 0, 2, NULL, &ix, &err) == SM_EINVAL && !ix);
  sm_knn_opts o;
  sm_knn_opts_default(&o);
  o.strategy = 7;
  CHECK(sm_knn_build(Y, 3, 2, &o, &ix, &err) == SM_EINVAL);
  Y[3] = INFINITY;
  CHECK(sm_knn_build(Y, 3, 2, NULL, &ix, &err) == SM_ENONFINITE);
  Y[3] = 3;
  REQUIRE(sm_knn_build(Y, 3, 2, NULL, &ix, &err) == 0);
  CHECK(sm_knn_strategy_of(ix) == SM_KNN_KDTREE); /* low d: AUTO picks the kd-tree */
  int32_t idx[4];
  CHECK(sm_knn_query(ix, X, 1, 4, idx, NULL, &err) == SM_EINVAL);
  CHECK(sm_knn_query(ix, X, 1, 0, idx, NULL, &err) == SM_EINVAL);
  CHECK(sm_knn_query(ix, X, 1, 1, idx, NULL, &err) == SM_ENONFINITE);
  sm_knn_destroy(ix);
  double *Z = calloc(300 * 4, sizeof *Z);
  REQUIRE(sm_knn_build(Z, 4, 300, NULL, &ix, &err) == 0);
  CHECK(sm_knn_strategy_of(ix) == SM_KNN_BRUTE); /* high d: AUTO picks brute force */
  sm_knn_destroy(ix);
  free(Z);
}

/* ---- functional maps ---------------------------------------------------------------- */

static sm_basis *basis_of(const sm_mesh *m, int kind, int k) {
  sm_basis_opts o;
  sm_error err;
  sm_basis *b = NULL;
  sm_basis_opts_default(&o, kind, k);
  int rc = sm_basis_compute(m, &o, &b, &err);
  if (rc) fprintf(stderr, "basis: %s\n", err.msg);
  REQUIRE(rc == 0 && b);
  return b;
}

static sm_mesh *blob(int subdiv, unsigned seed) {
  double stretch[3] = {1.3, 1.0, 0.8};
  sm_mesh *m = NULL;
  sm_error err;
  REQUIRE(sm_synth_blob(subdiv, 0.25, seed, stretch, &m, &err) == 0);
  REQUIRE(sm_mesh_normalize(m, &err) == 0);
  return m;
}

static int count_diff(const int32_t *a, const int32_t *b, int32_t n) {
  int c = 0;
  for (int32_t i = 0; i < n; i++) c += a[i] != b[i];
  return c;
}

/* Identity map -> C = I -> identity map, in one basis. */
static void check_identity(const sm_basis *b, int k) {
  int32_t n = b->n;
  int32_t *T = malloc((size_t)n * sizeof *T), *T2 = malloc((size_t)n * sizeof *T2);
  int32_t *Tyx = malloc((size_t)n * sizeof *Tyx);
  double *C = malloc((size_t)k * k * sizeof *C);
  sm_error err;
  for (int32_t i = 0; i < n; i++) T[i] = i;
  REQUIRE(sm_fmap_from_p2p(b, b, k, T, C, &err) == 0);
  double worst = 0;
  for (int q = 0; q < k; q++)
    for (int p = 0; p < k; p++) worst = fmax(worst, fabs(C[(size_t)q * k + p] - (p == q)));
  CHECK_MSG(worst < 1e-8, "kind %d: |C - I| = %g", b->kind, worst);
  for (int q = 0; q < k; q++)
    for (int p = 0; p < k; p++) C[(size_t)q * k + p] = p == q;
  sm_fmap_pair pr = {b, b, k, k, 1.0};
  const double *Cs[1] = {C};
  REQUIRE(sm_fmap_to_p2p(&pr, 1, Cs, T2, Tyx, NULL, &err) == 0);
  CHECK_MSG(count_diff(T, T2, n) == 0, "kind %d: identity C maps %d vertices elsewhere",
            b->kind, count_diff(T, T2, n));
  CHECK(count_diff(T, Tyx, n) == 0);
  free(T);
  free(T2);
  free(Tyx);
  free(C);
}

static void test_identity(void) {
  sm_mesh *m = blob(3, 11);
  sm_basis *lb = basis_of(m, SM_BASIS_LB, 40), *el = basis_of(m, SM_BASIS_ELASTIC, 40);
  CHECK(lb->gram_L == NULL && el->gram_L != NULL);
  check_identity(lb, 40);
  check_identity(el, 40);
  check_identity(el, 17); /* a leading block of the Gram factor */
  sm_basis_destroy(lb);
  sm_basis_destroy(el);
  sm_mesh_destroy(m);
}

/* Solves L y = x with the leading k block of the k_full-stored lower factor. */
static void lower_solve(const double *L, int ld, int k, double *x) {
  for (int r = 0; r < k; r++) {
    for (int c = 0; c < r; c++) x[r] -= L[(size_t)c * ld + r] * x[c];
    x[r] /= L[(size_t)r * ld + r];
  }
}

static void lower_t_solve(const double *L, int ld, int k, double *x) {
  for (int r = k - 1; r >= 0; r--) {
    for (int c = r + 1; c < k; c++) x[r] -= L[(size_t)r * ld + c] * x[c];
    x[r] /= L[(size_t)r * ld + r];
  }
}

/* C -> P in the elastic basis against the formula of algorithm.md §4, written naively:
 * a_i = L_A^-1 Phi_i, b_j = L_A^T C L_B^-T L_B^-1 Psi_j, nearest b for each a. */
static void test_p2p_formula(void) {
  sm_mesh *mx = blob(3, 21), *my = blob(3, 22);
  int k = 24;
  sm_basis *x = basis_of(mx, SM_BASIS_ELASTIC, 30), *y = basis_of(my, SM_BASIS_ELASTIC, 30);
  int32_t n = x->n, *T = malloc((size_t)n * sizeof *T), *Tref = malloc((size_t)n * sizeof *T);
  double *C = malloc((size_t)k * k * sizeof *C);
  for (int32_t i = 0; i < n; i++) T[i] = i; /* same connectivity: identity is a fair map */
  sm_error err;
  REQUIRE(sm_fmap_from_p2p(x, y, k, T, C, &err) == 0);
  sm_fmap_pair pr = {x, y, k, k, 1.0};
  const double *Cs[1] = {C};
  REQUIRE(sm_fmap_to_p2p(&pr, 1, Cs, T, NULL, NULL, &err) == 0);
  double *A = malloc((size_t)n * k * sizeof *A), *B = malloc((size_t)y->n * k * sizeof *B);
  double v[64], w[64];
  for (int32_t i = 0; i < n; i++) {
    for (int c = 0; c < k; c++) A[(size_t)i * k + c] = x->phi[(size_t)c * n + i];
    lower_solve(x->gram_L, x->k, k, A + (size_t)i * k);
  }
  for (int32_t j = 0; j < y->n; j++) {
    for (int c = 0; c < k; c++) v[c] = y->phi[(size_t)c * y->n + j];
    lower_solve(y->gram_L, y->k, k, v);
    lower_t_solve(y->gram_L, y->k, k, v); /* B^-1 Psi_j */
    for (int r = 0; r < k; r++) {
      w[r] = 0;
      for (int c = 0; c < k; c++) w[r] += C[(size_t)c * k + r] * v[c];
    }
    for (int r = 0; r < k; r++) { /* L_A^T w */
      double s = 0;
      for (int c = r; c < k; c++) s += x->gram_L[(size_t)r * x->k + c] * w[c];
      B[(size_t)j * k + r] = s;
    }
  }
  double dref;
  for (int32_t i = 0; i < n; i++) naive_knn(B, y->n, A + (size_t)i * k, k, 1, Tref + i, &dref);
  CHECK_MSG(count_diff(T, Tref, n) == 0, "%d of %d vertices differ from the formula",
            count_diff(T, Tref, n), n);
  /* On a subset of rows (every third vertex, backwards): those rows as the formula says,
   * the others untouched; a row outside X is refused. */
  int32_t nr = 0, *rows = malloc((size_t)n * sizeof *rows), *Tr = malloc((size_t)n * sizeof *Tr);
  for (int32_t i = n - 1; i >= 0; i -= 3) rows[nr++] = i;
  for (int32_t i = 0; i < n; i++) Tr[i] = -7;
  REQUIRE(sm_fmap_to_p2p_rows(&pr, 1, Cs, rows, nr, Tr, NULL, &err) == 0);
  int bad = 0;
  for (int32_t i = 0; i < n; i++) bad += Tr[i] != ((n - 1 - i) % 3 == 0 ? Tref[i] : -7);
  CHECK_MSG(bad == 0, "%d of %d entries wrong after the %d-row conversion", bad, n, nr);
  rows[nr / 2] = n;
  CHECK(sm_fmap_to_p2p_rows(&pr, 1, Cs, rows, nr, Tr, NULL, &err) == SM_ERANGE);
  free(rows);
  free(Tr);
  /* The embeddings exported for other assignment schemes are the same ones. */
  double *E = malloc((size_t)y->n * k * sizeof *E), worst = 0;
  REQUIRE(sm_fmap_embed_y(x, y, k, C, E, k, &err) == 0);
  for (int64_t t = 0; t < (int64_t)y->n * k; t++) worst = fmax(worst, fabs(E[t] - B[t]));
  REQUIRE(sm_fmap_embed_x(x, k, E, k, &err) == 0);
  for (int64_t t = 0; t < (int64_t)n * k; t++) worst = fmax(worst, fabs(E[t] - A[t]));
  CHECK_MSG(worst < 1e-9, "embedding error %g", worst);
  free(E);
  free(A);
  free(B);
  free(C);
  free(T);
  free(Tref);
  sm_basis_destroy(x);
  sm_basis_destroy(y);
  sm_mesh_destroy(mx);
  sm_mesh_destroy(my);
}

/* Classic ZoomOut written directly: C = Phi^T M Psi[T], T[i] = argmin_j |Phi_i - (Psi C^T)_j|. */
static void classic_zoomout(const sm_basis *x, const sm_basis *y, int k0, int k1, int32_t *T) {
  int32_t nx = x->n, ny = y->n;
  double *C = malloc((size_t)k1 * k1 * sizeof *C), *E = malloc((size_t)ny * k1 * sizeof *E);
  double *a = malloc((size_t)k1 * sizeof *a);
  for (int k = k0; k <= k1; k++) {
    for (int p = 0; p < k; p++)
      for (int q = 0; q < k; q++) {
        double s = 0;
        for (int32_t i = 0; i < nx; i++)
          s += x->phi[(size_t)p * nx + i] * x->mass[i] * y->phi[(size_t)q * ny + T[i]];
        C[(size_t)q * k + p] = s;
      }
    for (int32_t j = 0; j < ny; j++)
      for (int p = 0; p < k; p++) {
        double s = 0;
        for (int q = 0; q < k; q++) s += y->phi[(size_t)q * ny + j] * C[(size_t)q * k + p];
        E[(size_t)j * k + p] = s;
      }
    for (int32_t i = 0; i < nx; i++) {
      double d;
      for (int p = 0; p < k; p++) a[p] = x->phi[(size_t)p * nx + i];
      naive_knn(E, ny, a, k, 1, T + i, &d);
    }
  }
  free(C);
  free(E);
  free(a);
}

typedef struct shape_pair {
  sm_mesh *mx, *my;
  sm_basis *lbx, *lby, *elx, *ely;
  int32_t *truth; /* X vertex i is Y vertex truth[i] */
} shape_pair;

/* X = a blob, Y = the same blob with its vertices shuffled, bases computed on each. */
static shape_pair make_permuted(int subdiv, int k) {
  shape_pair s;
  s.mx = blob(subdiv, 31);
  int32_t n = s.mx->nv, *perm = malloc((size_t)n * sizeof *perm);
  tm_permutation(perm, n, 4242);
  s.my = tm_permuted(s.mx, perm);
  s.truth = malloc((size_t)n * sizeof *s.truth);
  for (int32_t i = 0; i < n; i++) s.truth[perm[i]] = i;
  free(perm);
  s.lbx = basis_of(s.mx, SM_BASIS_LB, k);
  s.lby = basis_of(s.my, SM_BASIS_LB, k);
  s.elx = basis_of(s.mx, SM_BASIS_ELASTIC, k);
  s.ely = basis_of(s.my, SM_BASIS_ELASTIC, k);
  return s;
}

static void free_pair(shape_pair *s) {
  sm_basis_destroy(s->lbx);
  sm_basis_destroy(s->lby);
  sm_basis_destroy(s->elx);
  sm_basis_destroy(s->ely);
  sm_mesh_destroy(s->mx);
  sm_mesh_destroy(s->my);
  free(s->truth);
}

/* The truth with a fraction of the vertices sent to the image of a random vertex two edge
 * steps away (a random walk on the mesh graph): a noisy start. */
static void noisy_start(const sm_mesh *m, const int32_t *truth, double frac, uint64_t seed,
                        int32_t *T) {
  enum { MAXDEG = 12 };
  int32_t n = m->nv, *nb = malloc((size_t)n * MAXDEG * sizeof *nb);
  int *deg = calloc((size_t)n, sizeof *deg);
  for (int64_t f = 0; f < m->nf; f++)
    for (int c = 0; c < 3; c++) {
      int32_t a = m->F[3 * f + c], b = m->F[3 * f + (c + 1) % 3];
      if (deg[a] < MAXDEG) nb[(size_t)a * MAXDEG + deg[a]++] = b; /* each edge twice: fine */
    }
  uint64_t s = seed;
  int moved = 0;
  for (int32_t i = 0; i < n; i++) {
    int32_t v = i;
    if (tm_rand(&s) < frac) {
      for (int step = 0; step < 2; step++) v = nb[(size_t)v * MAXDEG + (int)(tm_rand(&s) * deg[v])];
      moved += v != i;
    }
    T[i] = truth[v];
  }
  REQUIRE(moved > frac * n / 2);
  free(nb);
  free(deg);
}

static void test_classic_equivalence(void) {
  shape_pair s = make_permuted(3, 30);
  int32_t n = s.mx->nv, *T = malloc((size_t)n * sizeof *T), *Tc = malloc((size_t)n * sizeof *T);
  noisy_start(s.mx, s.truth, 0.3, 99, Tc);
  memcpy(T, Tc, (size_t)n * sizeof *T);
  int wrong0 = count_diff(Tc, s.truth, n);
  classic_zoomout(s.lbx, s.lby, 5, 30, Tc);
  sm_zoomout_opts o;
  sm_zoomout_opts_default(&o);
  o.nsample_x = o.nsample_y = 0;
  sm_fmap_pair pr = {s.lbx, s.lby, 30, 5, 1.0};
  sm_error err;
  REQUIRE(sm_zoomout(&pr, 1, &o, T, T, NULL, NULL, NULL, &err) == 0);
  CHECK_MSG(count_diff(T, Tc, n) == 0, "%d of %d vertices differ from classic ZoomOut",
            count_diff(T, Tc, n), n);
  fprintf(stderr, "classic equivalence: start %d wrong, end %d wrong of %d\n", wrong0,
          count_diff(T, s.truth, n), n);
  free(T);
  free(Tc);
  free_pair(&s);
}

static double mean_error(const sm_mesh *my, const int32_t *T, const int32_t *truth, int32_t n) {
  double s = 0;
  for (int32_t i = 0; i < n; i++) s += sqrt(sm_knn_dist2(my->V + 3 * T[i], my->V + 3 * truth[i], 3));
  return s / n;
}

typedef struct zcase {
  const char *name;
  int np;
  sm_fmap_pair pr[2];
} zcase;

/* bij > 0: the bijective variant with that weight. */
static void run_zoomout_case(const shape_pair *s, const zcase *c, int nsample, int nsy,
                             int noisy, double bij) {
  int32_t n = s->mx->nv, *T = malloc((size_t)n * sizeof *T), *Tyx = malloc((size_t)n * sizeof *T);
  if (noisy)
    noisy_start(s->mx, s->truth, 0.3, 777, T);
  else
    memcpy(T, s->truth, (size_t)n * sizeof *T);
  int wrong0 = count_diff(T, s->truth, n);
  sm_zoomout_opts o;
  sm_zoomout_opts_default(&o);
  o.nsample_x = nsample;
  o.nsample_y = nsy;
  o.pos_x = s->mx->V;
  o.pos_y = s->my->V;
  o.bijective = bij;
  double C0[40 * 40], C1[40 * 40];
  double *Cs[2] = {C0, C1};
  sm_zoomout_stats st;
  sm_error err;
  int rc = sm_zoomout(c->pr, c->np, &o, T, T, Cs, Tyx, &st, &err);
  if (rc) fprintf(stderr, "zoomout %s: %s\n", c->name, err.msg);
  REQUIRE(rc == 0);
  int wrong = count_diff(T, s->truth, n), wrong_yx = 0;
  for (int32_t i = 0; i < n; i++) wrong_yx += Tyx[s->truth[i]] != i;
  double me = mean_error(s->my, T, s->truth, n);
  fprintf(stderr, "zoomout %-8s bij %g samples %4d/%4d start %4d wrong -> %d wrong (yx %d), "
          "mean err %.2e, %d it, %.3f s\n", c->name, bij, nsample, nsy, wrong0, wrong, wrong_yx,
          me, st.iterations, st.t_total);
  /* Sampling Y blurs the intermediate maps (sm_fmap.h): a few vertices may stay a ring off. */
  int tol = nsy ? n / 20 : 0;
  CHECK_MSG(wrong <= tol && wrong_yx <= tol, "%s bij %g from %s: %d (%d) of %d vertices wrong",
            c->name, bij, noisy ? "noisy" : "exact", wrong, wrong_yx, n);
  CHECK(me < (nsy ? 2e-3 : 1e-12));
  if (nsy) {
    free(T);
    free(Tyx);
    return;
  }
  /* The returned C is the map of the returned T: P -> C of the truth at the final k. */
  double Ct[40 * 40];
  for (int p = 0; p < c->np; p++) {
    int k = c->pr[p].k;
    REQUIRE(sm_fmap_from_p2p(c->pr[p].x, c->pr[p].y, k, s->truth, Ct, &err) == 0);
    double worst = 0;
    for (int t = 0; t < k * k; t++) worst = fmax(worst, fabs(Ct[t] - Cs[p][t]));
    CHECK_MSG(worst < (nsample ? 1e-6 : 1e-8), "%s pair %d: |C - C_true| = %g", c->name, p,
              worst);
  }
  free(T);
  free(Tyx);
}

static void test_zoomout_permuted(void) {
  shape_pair s = make_permuted(3, 40);
  zcase cases[3] = {
      {"LB", 1, {{s.lbx, s.lby, 40, 6, 1.0}}},
      {"elastic", 1, {{s.elx, s.ely, 40, 6, 1.0}}},
      {"hybrid", 2, {{s.lbx, s.lby, 40, 6, 1.0}, {s.elx, s.ely, 30, 6, 1.0}}},
  };
  for (int c = 0; c < 3; c++) {
    for (int b = 0; b < 2; b++) { /* plain, bijective */
      run_zoomout_case(&s, &cases[c], 0, 0, 0, b);   /* exact start stays exact */
      run_zoomout_case(&s, &cases[c], 300, 0, 0, b); /* also with sampled iterations */
      run_zoomout_case(&s, &cases[c], 0, 0, 1, b);   /* noisy start converges */
      run_zoomout_case(&s, &cases[c], 300, 0, 1, b);
      run_zoomout_case(&s, &cases[c], 300, 300, 0, b); /* Y sampled too */
      run_zoomout_case(&s, &cases[c], 300, 300, 1, b);
    }
  }
  free_pair(&s);
}

/* The fits and embeddings of the pairs on several threads (sm_zoomout_opts.threads, the
 * kNN's query threads too) give the maps and functional maps of one thread, bit for bit:
 * hybrid, plain and bijective, from a noisy start, intermediate iterations on samples. */
static void test_zoomout_threads(void) {
  shape_pair s = make_permuted(3, 40);
  sm_fmap_pair pr[2] = {{s.lbx, s.lby, 40, 6, 1.0}, {s.elx, s.ely, 30, 6, 0.7}};
  int32_t n = s.mx->nv;
  for (int b = 0; b < 2; b++) {
    int32_t *T[3], *Tyx[3];
    double C[3][2][40 * 40];
    memset(C, 0, sizeof C); /* pair 1 fills 30 x 30 of its 40 x 40 */
    for (int th = 1; th <= 3; th++) {
      T[th - 1] = malloc((size_t)n * sizeof(int32_t));
      Tyx[th - 1] = malloc((size_t)n * sizeof(int32_t));
      noisy_start(s.mx, s.truth, 0.3, 99, T[th - 1]);
      sm_zoomout_opts o;
      sm_zoomout_opts_default(&o);
      o.nsample_x = o.nsample_y = 300;
      o.pos_x = s.mx->V;
      o.pos_y = s.my->V;
      o.bijective = b;
      o.threads = th;
      o.knn.query_threads = th;
      double *Cs[2] = {C[th - 1][0], C[th - 1][1]};
      sm_error err;
      REQUIRE(sm_zoomout(pr, 2, &o, T[th - 1], T[th - 1], Cs, Tyx[th - 1], NULL, &err) == 0);
    }
    for (int th = 2; th <= 3; th++) {
      CHECK_MSG(!memcmp(T[0], T[th - 1], (size_t)n * sizeof(int32_t)) &&
                    !memcmp(Tyx[0], Tyx[th - 1], (size_t)n * sizeof(int32_t)) &&
                    !memcmp(C[0], C[th - 1], sizeof C[0]),
                "zoomout bij %d: %d threads differ from one", b, th);
    }
    for (int th = 0; th < 3; th++) {
      free(T[th]);
      free(Tyx[th]);
    }
  }
  free_pair(&s);
}

/* Fixed features (sm_zoomout_opts.feat_*) decide the assignment when their weight
 * dominates: features that name another bijection W of the blob onto its permuted copy
 * (row W[i] of feat_y = row i of feat_x = X's position of i) must make ZoomOut return W
 * exactly, both ways, whether or not its intermediate iterations run on samples (feature
 * rows must follow the sampled rows); without them the same start ends on the geometric
 * truth instead. */
static void test_zoomout_features(void) {
  shape_pair s = make_permuted(3, 30);
  int32_t n = s.mx->nv, *T = malloc((size_t)n * sizeof *T), *Tyx = malloc((size_t)n * sizeof *T);
  int32_t *W = malloc((size_t)n * sizeof *W);
  double *fy = malloc((size_t)n * 3 * sizeof *fy);
  for (int32_t i = 0; i < n; i++) W[i] = s.truth[(i * 7919 + 13) % n];
  for (int32_t i = 0; i < n; i++) memcpy(fy + 3 * (size_t)W[i], s.mx->V + 3 * (size_t)i, 3 * sizeof *fy);
  sm_fmap_pair pr = {s.elx, s.ely, 30, 6, 1.0};
  sm_zoomout_opts o;
  sm_error err;
  for (int sampled = 0; sampled < 2; sampled++) {
    for (int with = 0; with < 2; with++) {
      memcpy(T, s.truth, (size_t)n * sizeof *T);
      sm_zoomout_opts_default(&o);
      o.nsample_x = o.nsample_y = sampled ? 300 : 0;
      o.pos_x = s.mx->V;
      o.pos_y = s.my->V;
      if (with) {
        o.feat_x = s.mx->V;
        o.feat_y = fy;
        o.nfeat = 3;
        o.feat_w = 1e4;
      }
      REQUIRE(sm_zoomout(&pr, 1, &o, T, T, NULL, Tyx, NULL, &err) == 0);
      const int32_t *want = with ? W : s.truth;
      int wrong = count_diff(T, want, n), wrong_yx = 0;
      for (int32_t i = 0; i < n; i++) wrong_yx += Tyx[want[i]] != i;
      fprintf(stderr, "zoomout features %d, samples %d: %d (yx %d) of %d off the %s\n", with,
              o.nsample_x, wrong, wrong_yx, n, with ? "features' map" : "truth");
      CHECK_MSG(wrong == 0 && wrong_yx == 0, "features %d, samples %d: %d (%d) wrong", with,
                o.nsample_x, wrong, wrong_yx);
    }
  }
  o.bijective = 1; /* the factored bijective candidates have no room for them */
  CHECK(sm_zoomout(&pr, 1, &o, T, T, NULL, NULL, NULL, &err) == SM_EINVAL);
  o.bijective = 0;
  o.feat_y = NULL;
  CHECK(sm_zoomout(&pr, 1, &o, T, T, NULL, NULL, NULL, &err) == SM_EINVAL);
  free(T);
  free(Tyx);
  free(W);
  free(fy);
  free_pair(&s);
}

static int cancel_after(void *ud) { return --*(int *)ud < 0; }

static void test_zoomout_errors(void) {
  shape_pair s = make_permuted(2, 12);
  int32_t n = s.mx->nv, *T = malloc((size_t)n * sizeof *T);
  memcpy(T, s.truth, (size_t)n * sizeof *T);
  sm_zoomout_opts o;
  sm_zoomout_opts_default(&o);
  sm_error err;
  sm_fmap_pair bad = {s.lbx, s.lby, 12, 13, 1.0};
  CHECK(sm_zoomout(&bad, 1, &o, T, T, NULL, NULL, NULL, &err) == SM_EINVAL);
  sm_fmap_pair mixed[2] = {{s.lbx, s.lby, 12, 4, 1.0}, {s.elx, s.elx, 12, 4, 1.0}};
  CHECK(sm_zoomout(mixed, 2, &o, T, T, NULL, NULL, NULL, &err) == SM_EINVAL);
  sm_fmap_pair pr = {s.lbx, s.lby, 12, 4, 1.0};
  T[3] = n;
  CHECK(sm_zoomout(&pr, 1, &o, T, T, NULL, NULL, NULL, &err) == SM_ERANGE);
  T[3] = s.truth[3];
  int budget = 2;
  o.cancel = cancel_after;
  o.cancel_ud = &budget;
  sm_zoomout_stats st;
  CHECK(sm_zoomout(&pr, 1, &o, T, T, NULL, NULL, &st, &err) == SM_ECANCELED);
  CHECK(st.iterations == 2);
  o.cancel = NULL;
  o.bijective = NAN;
  CHECK(sm_zoomout(&pr, 1, &o, T, T, NULL, NULL, NULL, &err) == SM_EINVAL);
  o.bijective = 1;
  int32_t *ys = malloc(6 * sizeof *ys);
  for (int i = 0; i < 6; i++) ys[i] = i;
  o.nsample_y = 6;
  o.samples_y = ys; /* without cellw_y: the Y -> X fit has no weights */
  CHECK(sm_zoomout(&pr, 1, &o, T, T, NULL, NULL, NULL, &err) == SM_EINVAL);
  o.nsample_y = 0;
  o.samples_y = NULL;
  o.bijective = 0;
  free(ys);
  o.nsample_x = 5; /* fewer samples than functions: the sampled fit is singular */
  CHECK(sm_zoomout(&pr, 1, &o, T, T, NULL, NULL, NULL, &err) == SM_ENUMERIC);
  free(T);
  free_pair(&s);
}

int main(void) {
  test_knn_random();
  test_knn_ties();
  test_knn_cancellation();
  test_knn_scales();
  test_knn_factored();
  test_knn_threads();
  test_knn_errors();
  test_knn_nonfinite();
  test_identity();
  test_p2p_formula();
  test_classic_equivalence();
  test_zoomout_permuted();
  test_zoomout_threads();
  test_zoomout_features();
  test_zoomout_errors();
  return sm_test_finish();
}
