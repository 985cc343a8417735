/* sm_knn: exact K nearest neighbours by FLANN kd-tree or blocked dgemm brute force.
 *
 * DESIGN
 *   Brute force: with Y centered on its mean (less cancellation) and scaled by a power of
 *   two s (exact) so that max_j |s (y_j - center)| is in [1/2, 1), one GEMM of a block of
 *   query rows [x_i, 1] by a block of rows [-2 y_j, |y_j|^2] gives v_ij = |y_j|^2 - 2 x_i.y_j,
 *   the squared distance minus the row constant |x_i|^2, so the scan only compares.
 *   Screening in single precision, certification in double. The GEMM runs in float32
 *   (sgemm: twice the flops per cycle of dgemm and half the memory traffic; it was 60% of
 *   a match). Each row keeps its K + SCREEN_EXTRA smallest v. Rounding: |computed - exact|
 *   <= delta_i = 4 (d + 4) u (|x_i|^2 + max_j |y_j|^2) with u = 2^-24 (the gamma_{d+1}
 *   bound of a dot product plus the rounding of the inputs to float, with a factor 2 to
 *   spare; the scaling keeps everything far from float overflow and underflow). If the
 *   K-th and the last kept candidate are more than 2 delta_i apart, every point left out
 *   is strictly farther than the K-th nearest, so the K nearest (and all points tied with
 *   the K-th) are among the kept ones: their distances are recomputed directly in double
 *   and sorted by (distance, index), the same answer as a double-precision scan. Otherwise
 *   (ties, duplicates, near-ties; about 1 row in 300 on ZoomOut and Sinkhorn embeddings)
 *   the row is screened again against all of Y (sgemv) and every point whose value is
 *   within lv_K + 2 delta_i is kept: a superset of the points within the K-th nearest
 *   distance, whose distances are then computed directly. Rows with more than RESCREEN_MAX
 *   such points, or too far from Y to screen in float, get a direct scan of all of Y;
 *   both keep the lowest index among equals.
 *   Two-way query (sm_knn_query_both): each block of the product also feeds one list per
 *   Y point, of full squared distances v_ij + |x_i|^2 (two more roundings, in the bound),
 *   certified and finished the same way against the query rows. Saves the second GEMM
 *   when ZoomOut wants T and T_yx, or Sinkhorn the K nearest in both directions.
 *   Scan order: the scans see Y's points (and, two-way, the query rows) in a fixed
 *   low-discrepancy order (scan_order), not by index: mesh vertices come in spatially
 *   coherent runs, and in index order a list's threshold fell slowly (homer's initial
 *   Sinkhorn kNN: 387 insertions per list of 20). The answers do not depend on the order.
 *   kd-tree: FLANN's exact single tree; distances are recomputed the same direct way so
 *   that both strategies agree bit for bit.
 *
 * Crossover (build + query, K = 1, best of 2 runs, seconds; 2 cores shared with other
 * jobs, load ~5, so absolute figures are ~2x pessimistic; FLANN with 2 threads here):
 *   uniform random in [0,1]^d, 5k x 5k:
 *     d        3      8     12     16     20     32     64    100    200
 *     kd-tree  0.003  0.019  0.089  0.221  0.306  0.383  0.628  0.895  1.423
 *     brute    0.044  0.049  0.050  0.068  0.052  0.058  0.089  0.135  0.196
 *   uniform random, 15k x 15k:
 *     kd-tree  0.022  0.128  0.546  1.305  4.837  6.362  (not run above d = 32)
 *     brute    0.499  0.557  0.431  0.854  0.861  0.810  1.298  1.980  4.410
 *   LB eigenfunction rows of a torus, queries = the same rows +-2.5% (what ZoomOut sees
 *   once converged: points on a 2-manifold, queries close to the data), 5k x 5k:
 *     kd-tree  0.006  0.008  0.008  0.012  0.010  0.014  0.015  0.017  0.042
 *     brute    0.159  0.078  0.076  0.081  0.075  0.114  0.126  0.169  0.302
 *   (15k x 15k: kd-tree 0.03-0.2 s at every d up to 300, brute 1-2.9 s.)
 *   Inside ZoomOut (cat0 -> cat1 of TOSCA, 5k vertices, k = 20..100, 2000 X samples
 *   against all of Y, total kNN seconds): all brute 8.3, crossover 12: 7.5, 24: 12.9
 *   (noisy), 32: 7.7: queries far from the data (a map still being refined) cost the
 *   kd-tree as much as random data. Uniform data put the crossover at d ~ 10-12; manifold
 *   data near convergence favour the kd-tree at every d; ZoomOut is in between and flat
 *   from 12 to 32. Default: 16. (The table's brute figures predate the compare-only scan,
 *   which made brute force ~1.5x faster at low d: the crossover only moves down.)
 */
#include "sm_knn.h"

#include <cblas.h>
#include <flann/flann.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif
#if defined(__x86_64__) && defined(__GNUC__) && !defined(SM_KNN_NO_AVX2)
#include <immintrin.h>
#define SM_KNN_AVX2 1 /* 8-wide scans, chosen at run time (cpu_has_avx2) */
#endif
#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <string.h>

#include "sm_par.h"

/* Query rows x Y rows per GEMM block (G = 1 MiB of floats): the best of 128/256 x
 * 512/1024/2048 on 2000 x 5000 points, d = 20 and 60 (measured with doubles). */
enum { BLK_X = 256, BLK_Y = 1024 };

/* Candidates kept beyond K per row: the margin that certifies the float screening. A row
 * that fails it is rescreened; beyond RESCREEN_MAX candidates it is scanned directly. */
enum { SCREEN_EXTRA = 4, RESCREEN_MAX = 1024 };

struct sm_knn {
  int strategy;
  int32_t ny;
  int d;
  int ds;          /* brute: dimension of the screening product (d, or dr when factored) */
  double *Y;       /* caller's points, copied (exact distances are taken on these) */
  int y_borrowed;  /* factored with the caller's Y: Y is the caller's, not freed here */
  float *Ya;       /* brute: rows [-2 yc_j, |yc_j|^2], yc_j = s (y_j - center), ds + 1 wide;
                    * factored: [-2 s (u_j - ubar), |yc_j|^2] */
  double *L;       /* factored: the d x dr map (row-major), y = L u; NULL otherwise */
  double *center;  /* brute: mean of Y (factored: L ubar) */
  int32_t *ypos;   /* brute: the point at each scan position (scan_order); Ya follows it */
  double scale;    /* brute: s, a power of two */
  double ymax2;    /* brute: max_j |yc_j|^2, in [1/4, 1) (or 0) */
  double sy;       /* brute: the index's part of the rounding bound (see screen_delta) */
  int threads;     /* brute: query rows split over this many threads (opts.query_threads) */
  flann_index_t flann;
  struct FLANNParameters fp;
};

/* FLANN's C API is not re-entrant: every entry point (build, query, free) starts with
 * init_flann_parameters(), which writes the library's process-wide logger level
 * (flann::Logger, a static) and, for random_seed > 0, reseeds the C rand() state. Two
 * threads in it at once race on that static even when they write the same value (a data
 * race for ThreadSanitizer and for the C++ memory model), so the calls stay serialized.
 * Re-checked for issue 13 (flann 1.9.2's src/cpp/flann/flann.cpp); the search itself is
 * const on the index, so only this wrapper forces the lock: kd-tree queries of concurrent
 * matches take turns here (brute-force queries, d >= SM_KNN_CROSSOVER_D, do not). Lifting
 * it needs FLANN's C++ API (flann::Index::knnSearch, no logger write) behind a core/io
 * adapter. */
static pthread_mutex_t flann_lock = PTHREAD_MUTEX_INITIALIZER;

double sm_knn_dist2(const double *x, const double *y, int d) {
  double s = 0;
  for (int t = 0; t < d; t++) {
    double e = x[t] - y[t];
    s += e * e;
  }
  return s;
}

void sm_knn_opts_default(sm_knn_opts *o) {
  memset(o, 0, sizeof *o);
  o->strategy = SM_KNN_AUTO;
}

int sm_knn_strategy_of(const sm_knn *ix) { return ix->strategy; }

static int check_finite(const double *a, int64_t n, const char *what, sm_error *err) {
  for (int64_t i = 0; i < n; i++)
    if (!isfinite(a[i]))
      return sm_error_set(err, SM_ENONFINITE, "knn: %s value %lld is not finite", what,
                          (long long)i);
  return 0;
}

/* The power of two s with s * sqrt(r2) in [1/2, 1) (1 when r2 is 0 or not finite). */
static double unit_scale(double r2) {
  if (!(r2 > 0) || !isfinite(r2)) return 1;
  int e;
  frexp(sqrt(r2), &e);
  return ldexp(1.0, -e);
}

/* Mean of the n rows of A (n x d) into c (zeroed by the caller). */
static void row_mean(const double *A, int32_t n, int d, double *c) {
  for (int32_t j = 0; j < n; j++)
    for (int t = 0; t < d; t++) c[t] += A[(size_t)j * d + t];
  for (int t = 0; t < d; t++) c[t] /= n;
}

/* The order in which the scans see n points (or query rows): position p holds point
 * p a mod n, a the integer nearest to n / golden ratio that is coprime to n, so that
 * consecutive positions lie far apart in index order and every stretch of positions
 * samples the whole index range evenly. Why: mesh vertices are numbered in spatially
 * coherent runs, and so are their embeddings; scanned in index order, a query's list
 * threshold falls slowly as the scan nears the query's own region, and most values on
 * the way get inserted. Homer's initial Sinkhorn kNN (K = 16 both ways, 5,103 x 8,018)
 * made 387 insertions per list in index order. The answers do not depend on the order
 * (the certification is by value; ties are settled by exact distance and index), only
 * the work does. NULL when out of memory. */
static int64_t gcd64(int64_t a, int64_t b) {
  while (b) {
    int64_t t = a % b;
    a = b;
    b = t;
  }
  return a;
}

static int32_t *scan_order(int32_t n) {
  int32_t *pos = malloc((size_t)(n > 0 ? n : 1) * sizeof *pos);
  if (!pos) return NULL;
  int64_t a = llround(n * 0.6180339887498949);
  if (a < 1) a = 1;
  while (n > 1 && gcd64(a, n) != 1) a++;
  for (int64_t p = 0; p < n; p++) pos[p] = (int32_t)(p * a % n);
  return pos;
}

/* ---- brute-force index: passes over Y in row parts (sm_par_for) ------------------------- */

/* Parts of a build pass over Y: one per query thread once Y is large enough to pay for a
 * thread start. Every value is per row, and the parts' maxima combine exactly, so the
 * index does not depend on the thread count. */
enum { BUILD_PAR_MIN = 1 << 18 /* ny x d */ };

typedef struct build_pass {
  sm_knn *ix;
  const double *U, *ubar; /* factored: the coordinates and their mean */
  int np, fill;           /* parts; 0: radius pass, 1: screening rows */
  double ym[SM_PAR_MAX_THREADS], um[SM_PAR_MAX_THREADS]; /* the parts' maxima */
} build_pass;

static int build_parts(const sm_knn *ix) {
  int64_t work = (int64_t)ix->ny * ix->d;
  int t = ix->threads < SM_PAR_MAX_THREADS ? ix->threads : SM_PAR_MAX_THREADS;
  return work < BUILD_PAR_MIN ? 1 : t;
}

/* Largest |y_j - center|^2 over points j0 .. j1 - 1 (NaN if some y_j is not finite). */
static double radius_part(const sm_knn *ix, int32_t j0, int32_t j1) {
  double r2 = 0;
  for (int32_t j = j0; j < j1; j++) {
    double s = 0;
    for (int t = 0; t < ix->d; t++) {
      double c = ix->Y[(size_t)j * ix->d + t] - ix->center[t];
      s += c * c;
    }
    if (!(s <= r2)) r2 = isnan(r2) ? r2 : s; /* keeps the first NaN */
  }
  return r2;
}

/* Screening rows of scan positions p0 .. p1 - 1: Ya[p, :ds] = -2 s (y_j - center) (plain)
 * or -2 s (u_j - ubar) (factored), Ya[p, ds] = |s (y_j - center)|^2. *ym gets the largest
 * of that last column, *um (factored) the largest |s (u_j - ubar)|^2. */
static void rows_part(const sm_knn *ix, const double *U, const double *ubar, int32_t p0,
                      int32_t p1, double *ym, double *um) {
  int d = ix->d, ds = ix->ds;
  *ym = *um = 0;
  for (int32_t p = p0; p < p1; p++) {
    int32_t j = ix->ypos[p];
    double s = 0;
    float *ya = ix->Ya + (size_t)p * (ds + 1);
    for (int t = 0; t < d; t++) {
      double c = ix->scale * (ix->Y[(size_t)j * d + t] - ix->center[t]);
      if (!U) ya[t] = (float)(-2 * c);
      s += c * c;
    }
    ya[ds] = (float)s;
    if (s > *ym) *ym = s;
    if (!U) continue;
    double su = 0;
    for (int t = 0; t < ds; t++) {
      double c = ix->scale * (U[(size_t)j * ds + t] - ubar[t]);
      ya[t] = (float)(-2 * c);
      su += c * c;
    }
    if (su > *um) *um = su;
  }
}

static void build_job(void *ctx, int p) {
  build_pass *b = ctx;
  int32_t j0, j1;
  sm_par_part(b->ix->ny, p, b->np, &j0, &j1);
  if (b->fill) rows_part(b->ix, b->U, b->ubar, j0, j1, &b->ym[p], &b->um[p]);
  else b->ym[p] = radius_part(b->ix, j0, j1);
}

/* The largest of the parts' values (NaN if one is). */
static double parts_max(const double *m, int np) {
  double r = 0;
  for (int p = 0; p < np; p++)
    if (!(m[p] <= r)) r = isnan(r) ? r : m[p];
  return r;
}

/* U != NULL: factored index (Y = U L^T already in ix->Y, L in ix->L, ds = dr columns).
 * The finiteness of Y (plain) or of U and Y (factored) is checked here, by the passes
 * that read them anyway: a full check only names the culprit once one failed. */
static int build_brute(sm_knn *ix, const double *U, sm_error *err) {
  int32_t ny = ix->ny;
  int d = ix->d, ds = ix->ds;
  ix->Ya = malloc((size_t)ny * (ds + 1) * sizeof(float));
  ix->center = calloc((size_t)d, sizeof(double));
  ix->ypos = scan_order(ny);
  double *ubar = U ? calloc((size_t)ds, sizeof(double)) : NULL;
  if (!ix->Ya || !ix->center || !ix->ypos || (U && !ubar)) {
    free(ubar);
    return sm_error_set(err, SM_ENOMEM, "knn: brute-force index of %d x %d", ny, d);
  }
  int rc = 0;
  if (U) { /* center = L ubar, so that y_j - center = L (u_j - ubar) */
    row_mean(U, ny, ds, ubar);
    for (int t = 0; t < ds && !rc; t++)
      if (!isfinite(ubar[t])) rc = check_finite(U, (int64_t)ny * ds, "U", err);
    cblas_dgemv(CblasRowMajor, CblasNoTrans, d, ds, 1.0, ix->L, ds, ubar, 1, 0.0, ix->center, 1);
  } else {
    row_mean(ix->Y, ny, d, ix->center);
  }
  build_pass b = {.ix = ix, .U = U, .ubar = ubar, .np = build_parts(ix)};
  if (!rc) sm_par_for(b.np, b.np, build_job, &b);
  double r2 = parts_max(b.ym, b.np);
  if (!rc && !isfinite(r2)) rc = check_finite(ix->Y, (int64_t)ny * d, U ? "Y = U L^T" : "Y", err);
  if (!rc) {
    ix->scale = unit_scale(r2);
    b.fill = 1;
    sm_par_for(b.np, b.np, build_job, &b);
    ix->ymax2 = parts_max(b.ym, b.np);
    ix->sy = ix->ymax2 + (U ? parts_max(b.um, b.np) : 0);
  }
  free(ubar);
  return rc;
}

static int build_flann(sm_knn *ix, const sm_knn_opts *o, sm_error *err) {
  struct FLANNParameters *p = &ix->fp;
  *p = DEFAULT_FLANN_PARAMETERS;
  p->algorithm = FLANN_INDEX_KDTREE_SINGLE;
  p->checks = FLANN_CHECKS_UNLIMITED;
  p->eps = 0;        /* prune only subtrees that cannot contain a closer point: exact */
  p->sorted = 1;
  p->max_neighbors = -1;
  p->cores = o->threads > 0 ? o->threads : 1;
  p->trees = 1;
  p->leaf_max_size = o->leaf_size > 0 ? o->leaf_size : 10;
  p->log_level = FLANN_LOG_NONE; /* core/ never logs */
  p->random_seed = 0;            /* a single kd-tree is deterministic; do not touch rand() */
  float speedup = 0;
  pthread_mutex_lock(&flann_lock);
  ix->flann = flann_build_index_double(ix->Y, ix->ny, ix->d, &speedup, p);
  pthread_mutex_unlock(&flann_lock);
  if (!ix->flann)
    return sm_error_set(err, SM_ENUMERIC, "knn: FLANN failed to build a kd-tree on %d x %d",
                        ix->ny, ix->d);
  return 0;
}

/* A new index of ny points in d dimensions, screened in ds, with room for the points (Y)
 * but nothing built, or borrowing the caller's Y when given; NULL when out of memory. */
static sm_knn *knn_new(int32_t ny, int d, int ds, const double *Y, const sm_knn_opts *o) {
  sm_knn *ix = calloc(1, sizeof *ix);
  if (!ix) return NULL;
  ix->ny = ny;
  ix->d = d;
  ix->ds = ds;
  ix->threads = o && o->query_threads > 1 ? o->query_threads : 1;
  ix->y_borrowed = Y != NULL;
  ix->Y = Y ? (double *)Y : malloc((size_t)ny * d * sizeof(double));
  if (!ix->Y) {
    free(ix);
    return NULL;
  }
  return ix;
}

int sm_knn_build(const double *Y, int32_t ny, int d, const sm_knn_opts *o, sm_knn **out,
                 sm_error *err) {
  sm_knn_opts def;
  if (!o) {
    sm_knn_opts_default(&def);
    o = &def;
  }
  *out = NULL;
  if (!Y || ny < 1 || d < 1)
    return sm_error_set(err, SM_EINVAL, "knn: bad point set (ny=%d, d=%d)", ny, d);
  if (o->strategy < SM_KNN_AUTO || o->strategy > SM_KNN_BRUTE)
    return sm_error_set(err, SM_EINVAL, "knn: unknown strategy %d", o->strategy);
  sm_knn *ix = knn_new(ny, d, d, NULL, o);
  if (!ix) return sm_error_set(err, SM_ENOMEM, "knn: copy of %d x %d points", ny, d);
  int cross = o->crossover_d > 0 ? o->crossover_d : SM_KNN_CROSSOVER_D;
  ix->strategy = o->strategy != SM_KNN_AUTO ? o->strategy
                 : d < cross                 ? SM_KNN_KDTREE
                                             : SM_KNN_BRUTE;
  memcpy(ix->Y, Y, (size_t)ny * d * sizeof(double));
  int rc = ix->strategy == SM_KNN_BRUTE ? build_brute(ix, NULL, err)
                                         : check_finite(Y, (int64_t)ny * d, "Y", err);
  if (!rc && ix->strategy != SM_KNN_BRUTE) rc = build_flann(ix, o, err);
  if (rc) {
    sm_knn_destroy(ix);
    return rc;
  }
  *out = ix;
  return 0;
}

int sm_knn_build_factored(const double *U, int32_t ny, int dr, const double *L, int d,
                          const double *Y, const sm_knn_opts *o, sm_knn **out, sm_error *err) {
  *out = NULL;
  if (!U || !L || ny < 1 || dr < 1 || d < 1)
    return sm_error_set(err, SM_EINVAL, "knn: bad factored point set (ny=%d, dr=%d, d=%d)", ny,
                        dr, d);
  int rc = check_finite(L, (int64_t)d * dr, "L", err); /* U: in build_brute */
  if (rc) return rc;
  sm_knn *ix = knn_new(ny, d, dr, Y, o);
  if (ix) ix->strategy = SM_KNN_BRUTE;
  if (ix) ix->L = malloc((size_t)d * dr * sizeof(double));
  if (!ix || !ix->L) {
    sm_knn_destroy(ix);
    return sm_error_set(err, SM_ENOMEM, "knn: factored index of %d x %d", ny, d);
  }
  memcpy(ix->L, L, (size_t)d * dr * sizeof(double));
  if (!Y)
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, ny, d, dr, 1.0, U, dr, L, dr, 0.0,
                ix->Y, d);
  rc = build_brute(ix, U, err);
  if (rc) {
    sm_knn_destroy(ix);
    return rc;
  }
  *out = ix;
  return 0;
}

void sm_knn_destroy(sm_knn *ix) {
  if (!ix) return;
  if (ix->flann) {
    pthread_mutex_lock(&flann_lock);
    flann_free_index_double(ix->flann, &ix->fp);
    pthread_mutex_unlock(&flann_lock);
  }
  if (!ix->y_borrowed) free(ix->Y);
  free(ix->Ya);
  free(ix->L);
  free(ix->center);
  free(ix->ypos);
  free(ix);
}

/* ---- sorted candidate lists ------------------------------------------------------- */

/* Inserts (v, j) into the ascending list (lv, li) of length *cnt <= cap. Equal values keep
 * their arrival order, so scanning j upwards keeps the lowest index first. */
static void list_insert(double *lv, int32_t *li, int *cnt, int cap, double v, int32_t j) {
  int p = *cnt < cap ? (*cnt)++ : cap - 1;
  while (p > 0 && lv[p - 1] > v) {
    lv[p] = lv[p - 1];
    li[p] = li[p - 1];
    p--;
  }
  lv[p] = v;
  li[p] = j;
}

/* The same for the float screening lists. */
static void list_insert_f(float *lv, int32_t *li, int *cnt, int cap, float v, int32_t j) {
  int p = *cnt < cap ? (*cnt)++ : cap - 1;
  while (p > 0 && lv[p - 1] > v) {
    lv[p] = lv[p - 1];
    li[p] = li[p - 1];
    p--;
  }
  lv[p] = v;
  li[p] = j;
}

/* Sorts K (dist, idx) pairs by distance then index (K is small: insertion sort). */
static void sort_pairs(double *dv, int32_t *iv, int K) {
  for (int a = 1; a < K; a++) {
    double v = dv[a];
    int32_t j = iv[a];
    int p = a;
    while (p > 0 && (dv[p - 1] > v || (dv[p - 1] == v && iv[p - 1] > j))) {
      dv[p] = dv[p - 1];
      iv[p] = iv[p - 1];
      p--;
    }
    dv[p] = v;
    iv[p] = j;
  }
}

/* Direct scan of the n points P (row-major, d wide) for query q: the exact K nearest,
 * lowest index among ties. */
static void exact_scan(const double *P, int32_t n, int d, const double *q, int K, double *dv,
                       int32_t *iv) {
  int cnt = 0;
  for (int32_t j = 0; j < n; j++) {
    double s = sm_knn_dist2(q, P + (size_t)j * d, d);
    if (cnt < K || s < dv[K - 1]) list_insert(dv, iv, &cnt, K, s, j);
  }
}

/* Exact K nearest among the n candidate points cand (ascending indices into P) of query
 * q, by (distance, index): the answer of exact_scan when cand holds every point within the
 * K-th nearest distance. */
static void exact_among(const double *P, int d, const double *q, const int32_t *cand, int n,
                        int K, double *dv, int32_t *iv) {
  int cnt = 0;
  for (int c = 0; c < n; c++) {
    double s = sm_knn_dist2(q, P + (size_t)cand[c] * d, d);
    if (cnt < K || s < dv[K - 1]) list_insert(dv, iv, &cnt, K, s, cand[c]);
  }
}

/* ---- brute force -------------------------------------------------------------------- */

/* Screening lists of one direction: cap smallest float values per query, ascending. */
typedef struct screen_lists {
  float *lv;   /* n x cap */
  int32_t *li; /* n x cap */
  int *cnt;    /* n */
  float *thr;  /* n: lv[cap - 1] once full, else +inf (columns only: compared 4 at a time) */
} screen_lists;

typedef struct brute_ws {
  float *Xc, *G;
  /* G[0 .. g_zero) is zero between blocks (scan_block clears what a block used), so the
   * next GEMM accumulates (beta = 1); a block reaching beyond it overwrites (beta = 0).
   * Not calloc: calloc hands over untouched pages, which a beta = 1 GEMM's first read maps
   * to the shared zero page; its write then replaces each one, and while other threads
   * of the process run that flushes their TLBs by an interrupt (a third of a two-thread
   * match's samples in the daemon, whose heaps hand out fresh pages; perf: do_wp_page). */
  size_t g_zero;
  double *xn;        /* |s (x - center)|^2 per query row */
  double *sn;        /* the row's part of the rounding bound: xn, or |x''|^2 when factored */
  double *Xd;        /* factored: BLK_X rows of s (x - center), then of x'' = L^T of them */
  screen_lists rows; /* BLK_X query rows */
  screen_lists cols; /* two-way query: one list per Y point; lv == NULL otherwise */
  double *dv;
  int32_t *iv;
  float *vec;        /* max(nx, ny) screening values of one query, for uncertified lists */
} brute_ws;

static void lists_free(screen_lists *l) {
  free(l->lv);
  free(l->li);
  free(l->cnt);
  free(l->thr);
}

static int lists_alloc(screen_lists *l, int32_t n, int cap) {
  l->lv = malloc((size_t)n * cap * sizeof(float));
  l->li = malloc((size_t)n * cap * sizeof(int32_t));
  l->cnt = calloc((size_t)n, sizeof(int));
  l->thr = malloc((size_t)n * sizeof(float));
  if (!l->lv || !l->li || !l->cnt || !l->thr) return -1;
  for (int32_t i = 0; i < n; i++) l->thr[i] = INFINITY;
  return 0;
}

static void brute_ws_free(brute_ws *w) {
  free(w->Xc);
  free(w->G);
  free(w->xn);
  free(w->sn);
  free(w->Xd);
  lists_free(&w->rows);
  lists_free(&w->cols);
  free(w->dv);
  free(w->iv);
  free(w->vec);
}

/* Xc / xn / sn for nr query rows (BLK_X one-way; all nx two-way, where the column rescreen
 * needs every row; 0: a helper thread of a two-way query, which reads the first
 * workspace's), and the column lists when two_way. */
static int brute_ws_alloc(brute_ws *w, const sm_knn *ix, int32_t nx, int32_t nr, int cap,
                          int capc, int two_way) {
  memset(w, 0, sizeof *w);
  int32_t ny = ix->ny, nmax = nx > ny ? nx : ny;
  int nbuf = cap > RESCREEN_MAX ? cap : RESCREEN_MAX;
  if (capc > nbuf) nbuf = capc;
  if (nr > 0) {
    w->Xc = malloc((size_t)nr * (ix->ds + 1) * sizeof(float));
    w->xn = malloc((size_t)nr * sizeof(double));
    w->sn = malloc((size_t)nr * sizeof(double));
    if (!w->Xc || !w->xn || !w->sn) return -1;
  }
  if (ix->L && !(w->Xd = malloc((size_t)BLK_X * (ix->d + ix->ds) * sizeof(double)))) return -1;
  w->G = malloc((size_t)BLK_X * BLK_Y * sizeof(float)); /* see g_zero */
  w->g_zero = 0;
  w->dv = malloc((size_t)(nbuf + cap) * sizeof(double));
  w->iv = malloc((size_t)nbuf * sizeof(int32_t));
  w->vec = malloc((size_t)nmax * sizeof(float));
  if (!w->G || !w->dv || !w->iv || !w->vec) return -1;
  if (lists_alloc(&w->rows, BLK_X, cap)) return -1;
  return two_way ? lists_alloc(&w->cols, ny, capc) : 0;
}

/* Largest |s (x - center)|^2 screened in float: beyond it the row is scanned directly
 * (its float products could overflow, and its delta would fail the test anyway). */
#define SCREEN_MAX_XN 1e24

/* Factored index: n <= BLK_X query rows (row r: X row rows[r], NULL: r) as x'' = L^T s (x
 * - center) in float (stride dr + 1), sn = |x''|^2; rows with xn = INFINITY stay zero. */
static int32_t screen_factored(const sm_knn *ix, const double *X, const int32_t *rows,
                               int32_t n, double *Xd, float *Xc, const double *xn, double *sn) {
  int d = ix->d, dr = ix->ds;
  double *R = Xd + (size_t)BLK_X * d;
  int32_t bad = 0;
  for (int32_t r = 0; r < n; r++) {
    const double *x = X + (size_t)(rows ? rows[r] : r) * d;
    for (int t = 0; t < d; t++)
      Xd[(size_t)r * d + t] = isfinite(xn[r]) ? ix->scale * (x[t] - ix->center[t]) : 0;
  }
  cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, n, dr, d, 1.0, Xd, d, ix->L, dr, 0.0, R,
              dr);
  for (int32_t r = 0; r < n; r++) {
    double s = 0;
    for (int t = 0; t < dr; t++) s += R[(size_t)r * dr + t] * R[(size_t)r * dr + t];
    int ok = isfinite(xn[r]) && s <= SCREEN_MAX_XN;
    float *xc = Xc + (size_t)r * (dr + 1);
    for (int t = 0; t < dr; t++) xc[t] = ok ? (float)R[(size_t)r * dr + t] : 0.0f;
    xc[dr] = 1;
    sn[r] = ok ? s : INFINITY;
    bad += !ok;
  }
  return bad;
}

/* Float rows [s (x_r - center), 1] (stride ds + 1; factored: [x''_r, 1]), xn_r = |s (x_r -
 * center)|^2 and sn_r (see brute_ws), or INFINITY (and a zero row) when the row is not
 * screenable; x_r is row rows[r] of X (rows NULL: r). Xd: the factored workspace. Returns
 * how many rows are not screenable. */
static int32_t screen_rows(const sm_knn *ix, const double *X, const int32_t *rows, int32_t n,
                           float *Xc, double *xn, double *sn, double *Xd) {
  int d = ix->d, ds = ix->ds;
  int32_t bad = 0;
  for (int32_t r = 0; r < n; r++) {
    double s = 0;
    float *xc = Xc + (size_t)r * (ds + 1);
    const double *x = X + (size_t)(rows ? rows[r] : r) * d;
    for (int t = 0; t < d; t++) {
      double c = ix->scale * (x[t] - ix->center[t]);
      s += c * c;
    }
    int ok = s <= SCREEN_MAX_XN;
    for (int t = 0; t < d && !ix->L; t++)
      xc[t] = ok ? (float)(ix->scale * (x[t] - ix->center[t])) : 0.0f;
    xc[ds] = 1; /* picks up |y|^2 from the last column of Ya */
    xn[r] = sn[r] = ok ? s : INFINITY;
    bad += !ok;
  }
  if (!ix->L) return bad;
  bad = 0;
  for (int32_t r0 = 0; r0 < n; r0 += BLK_X) {
    int32_t m = n - r0 < BLK_X ? n - r0 : BLK_X;
    bad += screen_factored(ix, rows ? X : X + (size_t)r0 * d, rows ? rows + r0 : NULL, m, Xd,
                           Xc + (size_t)r0 * (ds + 1), xn + r0, sn + r0);
  }
  return bad;
}

/* Not fminf: its NaN rules cost a call; there are no NaNs here (inputs are checked). */
#define MIN2(a, b) ((a) < (b) ? (a) : (b))

static inline void offer(screen_lists *l, int cap, size_t q, float v, int32_t j) {
  int cnt = l->cnt[q];
  list_insert_f(l->lv + q * cap, l->li + q * cap, &cnt, cap, v, j);
  l->cnt[q] = cnt;
  if (cnt == cap) l->thr[q] = l->lv[q * cap + cap - 1];
}

/* One row of a GEMM block into its own list: most entries are above the row's threshold,
 * so test the minimum of 16 (SSE) or 8 at a time and only walk a group that holds a
 * candidate. Column j0 + t is scan position j0 + t: the point pos[j0 + t]. */
static void scan_row(screen_lists *l, int cap, int r, const float *g, const int32_t *pos,
                     int32_t j0, int by) {
  int j = 0;
  float thr = l->thr[r];
#if defined(__SSE2__)
  __m128 vt = _mm_set1_ps(thr);
  for (; j + 16 <= by; j += 16) {
    __m128 m = _mm_min_ps(_mm_min_ps(_mm_loadu_ps(g + j), _mm_loadu_ps(g + j + 4)),
                          _mm_min_ps(_mm_loadu_ps(g + j + 8), _mm_loadu_ps(g + j + 12)));
    if (!_mm_movemask_ps(_mm_cmplt_ps(m, vt))) continue;
    for (int t = j; t < j + 16; t++)
      if (g[t] < thr) {
        offer(l, cap, r, g[t], pos[j0 + t]);
        thr = l->thr[r];
      }
    vt = _mm_set1_ps(thr);
  }
#endif
  for (; j + 8 <= by; j += 8) {
    float m01 = MIN2(g[j], g[j + 1]), m23 = MIN2(g[j + 2], g[j + 3]);
    float m45 = MIN2(g[j + 4], g[j + 5]), m67 = MIN2(g[j + 6], g[j + 7]);
    if (MIN2(MIN2(m01, m23), MIN2(m45, m67)) >= thr) continue;
    for (int t = j; t < j + 8; t++)
      if (g[t] < thr) {
        offer(l, cap, r, g[t], pos[j0 + t]);
        thr = l->thr[r];
      }
  }
  for (; j < by; j++)
    if (g[j] < thr) {
      offer(l, cap, r, g[j], pos[j0 + j]);
      thr = l->thr[r];
    }
}

/* The same row into the lists of the Y points j0 .. j0 + by - 1 (two-way query), as full
 * squared distances g + xn (the column's own constant differs per row). */
static void scan_cols(screen_lists *l, int cap, int32_t i, float xr, const float *g,
                      int32_t j0, int by) {
  const float *thr = l->thr + j0;
  int j = 0;
#if defined(__SSE2__)
  __m128 vx = _mm_set1_ps(xr);
  for (; j + 4 <= by; j += 4) {
    __m128 v = _mm_add_ps(_mm_loadu_ps(g + j), vx);
    if (!_mm_movemask_ps(_mm_cmplt_ps(v, _mm_loadu_ps(thr + j)))) continue;
    for (int t = j; t < j + 4; t++) {
      float vt = g[t] + xr;
      if (vt < thr[t]) offer(l, cap, (size_t)j0 + t, vt, i);
    }
  }
#endif
  for (; j < by; j++) {
    float vt = g[j] + xr;
    if (vt < thr[j]) offer(l, cap, (size_t)j0 + j, vt, i);
  }
}

#ifdef SM_KNN_AVX2
/* scan_row and scan_cols 8 lanes wide: the same float values compared in the same order,
 * so the same lists. The scans were about a fifth of a match on one thread. */
__attribute__((target("avx2"))) static void scan_row_avx2(screen_lists *l, int cap, int r,
                                                          const float *g, const int32_t *pos,
                                                          int32_t j0, int by) {
  int j = 0;
  float thr = l->thr[r];
  __m256 vt = _mm256_set1_ps(thr);
  for (; j + 32 <= by; j += 32) {
    __m256 m = _mm256_min_ps(_mm256_min_ps(_mm256_loadu_ps(g + j), _mm256_loadu_ps(g + j + 8)),
                             _mm256_min_ps(_mm256_loadu_ps(g + j + 16),
                                           _mm256_loadu_ps(g + j + 24)));
    if (!_mm256_movemask_ps(_mm256_cmp_ps(m, vt, _CMP_LT_OQ))) continue;
    for (int t = j; t < j + 32; t++)
      if (g[t] < thr) {
        offer(l, cap, r, g[t], pos[j0 + t]);
        thr = l->thr[r];
      }
    vt = _mm256_set1_ps(thr);
  }
  for (; j < by; j++)
    if (g[j] < thr) {
      offer(l, cap, r, g[j], pos[j0 + j]);
      thr = l->thr[r];
    }
}

__attribute__((target("avx2"))) static void scan_cols_avx2(screen_lists *l, int cap, int32_t i,
                                                           float xr, const float *g,
                                                           int32_t j0, int by) {
  const float *thr = l->thr + j0;
  int j = 0;
  __m256 vx = _mm256_set1_ps(xr);
  for (; j + 8 <= by; j += 8) {
    __m256 v = _mm256_add_ps(_mm256_loadu_ps(g + j), vx);
    if (!_mm256_movemask_ps(_mm256_cmp_ps(v, _mm256_loadu_ps(thr + j), _CMP_LT_OQ))) continue;
    for (int t = j; t < j + 8; t++) {
      float vt = g[t] + xr;
      if (vt < thr[t]) offer(l, cap, (size_t)j0 + t, vt, i);
    }
  }
  for (; j < by; j++) {
    float vt = g[j] + xr;
    if (vt < thr[j]) offer(l, cap, (size_t)j0 + j, vt, i);
  }
}

/* Atomic: concurrent first calls (two daemon workers) may both compute it; a plain int
 * would be a data race (ThreadSanitizer stopped the daemon on one). */
static int cpu_has_avx2(void) {
  static atomic_int known = -1;
  int k = atomic_load_explicit(&known, memory_order_relaxed);
  if (k < 0) {
    k = __builtin_cpu_supports("avx2") ? 1 : 0;
    atomic_store_explicit(&known, k, memory_order_relaxed);
  }
  return k;
}
#endif

/* Scans one GEMM block (query rows at positions i0 .. i0 + bx - 1, the query row at
 * position i being xrow[i] (NULL: i); Y points at scan positions j0 .. j0 + by - 1) into
 * the rows' lists (cap > 0) and the columns' (w->cols allocated),
 * zeroing each row while it is in cache so that the next GEMM can accumulate (beta = 1):
 * with beta = 0 OpenBLAS clears C in a separate pass, which cost half as much as the GEMM
 * itself at d = 20. */
static void scan_block(brute_ws *w, const sm_knn *ix, const int32_t *xrow, const double *xn,
                       int bx, int32_t i0, int32_t j0, int by, int cap, int capc) {
#ifdef SM_KNN_AVX2
  if (cpu_has_avx2()) {
    for (int r = 0; r < bx; r++) {
      float *g = w->G + (size_t)r * by;
      int32_t i = xrow ? xrow[i0 + r] : i0 + r;
      if (cap) scan_row_avx2(&w->rows, cap, r, g, ix->ypos, j0, by);
      if (w->cols.lv) scan_cols_avx2(&w->cols, capc, i, (float)xn[r], g, j0, by);
      memset(g, 0, (size_t)by * sizeof(float));
    }
    return;
  }
#endif
  for (int r = 0; r < bx; r++) {
    float *g = w->G + (size_t)r * by;
    int32_t i = xrow ? xrow[i0 + r] : i0 + r;
    if (cap) scan_row(&w->rows, cap, r, g, ix->ypos, j0, by);
    if (w->cols.lv) scan_cols(&w->cols, capc, i, (float)xn[r], g, j0, by);
    memset(g, 0, (size_t)by * sizeof(float));
  }
}

/* Exact K nearest of query q among the n points P from its screening list (lv, li: cap
 * smallest screening values; delta: their rounding bound; see DESIGN). Uncertified: the
 * screening values of q against all of P, vec (computed by fill(ctx) on demand), and every
 * point within lv_K + 2 delta of them; a direct scan beyond RESCREEN_MAX of those.
 * Certified: only the list's prefix within lv_K + 2 delta can hold the K nearest or tie
 * with the K-th (a point's distance is within delta of its screening value, and the K-th
 * distance is at most lv_K + delta), so only those distances are computed; and none when
 * dv is NULL (distances not wanted) and the prefix is the one answer (K = 1). ZoomOut's
 * assignments want no distances: homer's match 1.62 -> 1.43 s on one thread, the same
 * maps bit for bit. */
typedef void (*fill_fn)(const void *ctx, float *vec);

static int i32_cmp(const void *a, const void *b) {
  int32_t x = *(const int32_t *)a, y = *(const int32_t *)b;
  return (x > y) - (x < y);
}

/* vec (from fill) is in scan order: entry j is point pos[j] of P (pos NULL: j). */
static void finish_list(brute_ws *w, const double *P, int32_t n, int d, const double *q,
                        const float *lv, const int32_t *li, int K, int cap, double delta,
                        fill_fn fill, const void *ctx, const int32_t *pos, double *dv,
                        int32_t *iv) {
  int want = dv != NULL;
  if (!want) dv = w->dv + cap; /* scratch beside the candidates' (brute_ws_alloc) */
  if (!isfinite(delta)) {
    exact_scan(P, n, d, q, K, dv, iv);
    return;
  }
  if (cap < n && (double)lv[cap - 1] - (double)lv[K - 1] <= 2 * delta) {
    double thr = (double)lv[K - 1] + 2 * delta;
    int m = 0;
    fill(ctx, w->vec);
    for (int32_t j = 0; j < n; j++) {
      if (w->vec[j] > thr) continue;
      if (m == RESCREEN_MAX) {
        exact_scan(P, n, d, q, K, dv, iv);
        return;
      }
      w->iv[m++] = pos ? pos[j] : j;
    }
    if (pos) qsort(w->iv, (size_t)m, sizeof *w->iv, i32_cmp); /* exact_among: ascending */
    exact_among(P, d, q, w->iv, m, K, dv, iv);
    return;
  }
  double lim = (double)lv[K - 1] + 2 * delta;
  int m = K;
  while (m < cap && (double)lv[m] <= lim) m++;
  if (m == 1 && !want) {
    *iv = li[0];
    return;
  }
  for (int r = 0; r < m; r++) {
    w->iv[r] = li[r];
    w->dv[r] = sm_knn_dist2(q, P + (size_t)li[r] * d, d);
  }
  sort_pairs(w->dv, w->iv, m);
  memcpy(dv, w->dv, (size_t)K * sizeof *dv);
  memcpy(iv, w->iv, (size_t)K * sizeof *iv);
}

/* Rounding bound of a screening value (DESIGN): u = 2^-24, ds = the product's length,
 * sn the row's part, sy the index's. Factored (y = L u, x'' = L^T s (x - center)): the
 * value |yc|^2 - 2 x''.u'' has error <= (dr + 4) u (2 |yc|^2 + |x''|^2 + |u''|^2), so sn =
 * |x''|^2 and sy = max |yc|^2 + max |u''|^2 keep the factor 2 to spare of the plain bound,
 * 4 (d + 4) u (|xc|^2 + max |yc|^2). */
static double screen_delta(int ds, double sn, double sy) {
  return 4.0 * (ds + 4) * 5.9604644775390625e-08 * (sn + sy);
}

typedef struct row_fill { const sm_knn *ix; const float *xc; } row_fill;

/* Screening values of one query row against all of Y (sgemv). */
static void fill_row(const void *vctx, float *vec) {
  const row_fill *c = vctx;
  cblas_sgemv(CblasRowMajor, CblasNoTrans, c->ix->ny, c->ix->ds + 1, 1.0f, c->ix->Ya,
              c->ix->ds + 1, c->xc, 1, 0.0f, vec, 1);
}

/* Query rows at positions i0 .. i0 + bx - 1 (row xrow[i], NULL: i; their float rows Xc,
 * constants xn and bound parts sn) against all of Y: GEMM blocks, scans, then the exact K
 * nearest of each row. idx NULL: only the column lists of w are filled. */
static void brute_rows(const sm_knn *ix, brute_ws *w, const float *Xc, const double *xn,
                       const double *sn, const double *X, const int32_t *xrow, int32_t i0,
                       int bx, int K, int cap, int capc, int32_t *idx, double *dist2) {
  int d = ix->d, ds = ix->ds;
  for (int r = 0; r < bx && idx; r++) {
    w->rows.cnt[r] = 0;
    w->rows.thr[r] = INFINITY;
  }
  for (int32_t j0 = 0; j0 < ix->ny; j0 += BLK_Y) {
    int by = ix->ny - j0 < BLK_Y ? ix->ny - j0 : BLK_Y;
    size_t used = (size_t)bx * by;
    cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasTrans, bx, by, ds + 1, 1.0f, Xc, ds + 1,
                ix->Ya + (size_t)j0 * (ds + 1), ds + 1, used <= w->g_zero ? 1.0f : 0.0f,
                w->G, by);
    scan_block(w, ix, xrow, xn, bx, i0, j0, by, idx ? cap : 0, capc);
    if (used > w->g_zero) w->g_zero = used;
  }
  for (int r = 0; r < bx && idx; r++) {
    row_fill c = {ix, Xc + (size_t)r * (ds + 1)};
    size_t i = (size_t)(xrow ? xrow[i0 + r] : i0 + r);
    finish_list(w, ix->Y, ix->ny, d, X + i * d, w->rows.lv + (size_t)r * cap,
                w->rows.li + (size_t)r * cap, K, cap, screen_delta(ds, sn[r], ix->sy),
                fill_row, &c, ix->ypos, dist2 ? dist2 + i * K : NULL, idx + i * K);
  }
}

/* ---- threads ------------------------------------------------------------------------ */

enum { KNN_MAX_THREADS = SM_PAR_MAX_THREADS, PAR_MIN_WORK = 1 << 20 /* query rows x points */ };
/* Two-way queries split over threads only from this many product dimensions per column
 * list entry, or from this many query rows (query_both_brute). */
enum { MIN_DS_PER_LIST = 8, MIN_ROWS_SPLIT = 10000 };

/* Runs fn on jobs[0 .. n-1] (each `size` bytes) on n threads (sm_par_for). */
typedef struct job_array {
  void *(*fn)(void *);
  char *jobs;
  size_t size;
} job_array;

static void job_at(void *ctx, int i) {
  job_array *a = ctx;
  a->fn(a->jobs + (size_t)i * a->size);
}

static void run_jobs(void *(*fn)(void *), void *jobs, size_t size, int n) {
  job_array a = {fn, jobs, size};
  sm_par_for(n, n, job_at, &a);
}

/* Threads for nx query rows against ix: whole BLK_X blocks each, and only when the work
 * pays for them. */
static int query_threads(const sm_knn *ix, int32_t nx) {
  int32_t nb = (nx + BLK_X - 1) / BLK_X;
  int t = ix->threads < KNN_MAX_THREADS ? ix->threads : KNN_MAX_THREADS;
  if ((int64_t)nx * ix->ny < PAR_MIN_WORK) return 1;
  return t < nb ? t : nb;
}

/* Query rows of part t of n: whole blocks, in order. */
static void part_rows(int32_t nx, int t, int n, int32_t *i0, int32_t *i1) {
  int32_t nb = (nx + BLK_X - 1) / BLK_X;
  *i0 = (int32_t)((int64_t)nb * t / n) * BLK_X;
  *i1 = (int32_t)((int64_t)nb * (t + 1) / n) * BLK_X;
  if (*i1 > nx) *i1 = nx;
}

typedef struct row_job {
  const sm_knn *ix;
  const double *X;
  int32_t nx, i0, i1;
  int K, cap;
  int32_t *idx;
  double *dist2;
  int rc;
} row_job;

/* One-way: rows i0 .. i1 - 1, screened block by block in the job's own workspace. */
static void *row_job_run(void *arg) {
  row_job *j = arg;
  const sm_knn *ix = j->ix;
  brute_ws w;
  j->rc = brute_ws_alloc(&w, ix, j->nx, BLK_X, j->cap, 0, 0);
  for (int32_t i0 = j->i0; !j->rc && i0 < j->i1; i0 += BLK_X) {
    int bx = j->i1 - i0 < BLK_X ? j->i1 - i0 : BLK_X;
    screen_rows(ix, j->X + (size_t)i0 * ix->d, NULL, bx, w.Xc, w.xn, w.sn, w.Xd);
    brute_rows(ix, &w, w.Xc, w.xn, w.sn, j->X, NULL, i0, bx, j->K, j->cap, 0, j->idx,
               j->dist2);
  }
  brute_ws_free(&w);
  return NULL;
}

static int query_brute(const sm_knn *ix, const double *X, int32_t nx, int K, int32_t *idx,
                       double *dist2, sm_error *err) {
  /* The (K + SCREEN_EXTRA)-th candidate certifies the K-th. */
  int cap = K + SCREEN_EXTRA < ix->ny ? K + SCREEN_EXTRA : ix->ny;
  int n = query_threads(ix, nx), rc = 0;
  row_job jobs[KNN_MAX_THREADS];
  for (int t = 0; t < n; t++) {
    jobs[t] = (row_job){ix, X, nx, 0, 0, K, cap, idx, dist2, 0};
    part_rows(nx, t, n, &jobs[t].i0, &jobs[t].i1);
  }
  run_jobs(row_job_run, jobs, sizeof *jobs, n);
  for (int t = 0; t < n; t++) rc |= jobs[t].rc;
  if (rc) return sm_error_set(err, SM_ENOMEM, "knn: brute-force workspace (K=%d, d=%d)", K, ix->d);
  return 0;
}

typedef struct col_fill {
  const sm_knn *ix;
  const float *Xc;
  const double *xn;
  int32_t nx, j;
} col_fill;

/* Screening values (full squared distances) of Y point j against every query row. */
static void fill_col(const void *vctx, float *vec) {
  const col_fill *c = vctx;
  int ds = c->ix->ds;
  cblas_sgemv(CblasRowMajor, CblasNoTrans, c->nx, ds + 1, 1.0f, c->Xc, ds + 1,
              c->ix->Ya + (size_t)c->j * (ds + 1), 1, 0.0f, vec, 1);
  for (int32_t i = 0; i < c->nx; i++) vec[i] += (float)c->xn[i];
}

/* a[q] := the cap smallest of a[q] and b[q] for q < n, a's entries first among equals: a
 * holds the earlier query rows, so this is the list one pass over all rows would keep. */
static void merge_lists(screen_lists *a, const screen_lists *b, int32_t n, int cap, float *tv,
                        int32_t *ti) {
  for (int32_t q = 0; q < n; q++) {
    float *la = a->lv + (size_t)q * cap;
    int32_t *ia = a->li + (size_t)q * cap;
    const float *lb = b->lv + (size_t)q * cap;
    const int32_t *ib = b->li + (size_t)q * cap;
    int na = a->cnt[q], nb = b->cnt[q], pa = 0, pb = 0, m = 0;
    while (m < cap && (pa < na || pb < nb)) {
      int take_a = pb == nb || (pa < na && la[pa] <= lb[pb]);
      tv[m] = take_a ? la[pa] : lb[pb];
      ti[m++] = take_a ? ia[pa++] : ib[pb++];
    }
    memcpy(la, tv, (size_t)m * sizeof *tv);
    memcpy(ia, ti, (size_t)m * sizeof *ti);
    a->cnt[q] = m;
  }
}

/* Two-way: rows i0 .. i1 - 1 into the job's row results (idx NULL: none) and its own
 * column lists (if its workspace has them) (phase 0), then (phase 1) the exact nearest
 * query rows of Y points j0 .. j1 - 1 from the merged lists of ws0. */
typedef struct both_job {
  const sm_knn *ix;
  const double *X;
  const int32_t *xrow; /* the query row at each position (scan_order) */
  brute_ws *w, *w0;
  int32_t nx, i0, i1, j0, j1;
  int K, cap, capc, phase;
  double delta;
  int32_t *idx, *idx_yx;
  double *dist2, *dist_yx;
} both_job;

static void *both_job_run(void *arg) {
  both_job *j = arg;
  const sm_knn *ix = j->ix;
  brute_ws *w0 = j->w0;
  int ds = ix->ds, d = ix->d;
  if (j->phase == 0) {
    for (int32_t i0 = j->i0; i0 < j->i1; i0 += BLK_X) {
      int bx = j->i1 - i0 < BLK_X ? j->i1 - i0 : BLK_X;
      brute_rows(ix, j->w, w0->Xc + (size_t)i0 * (ds + 1), w0->xn + i0, w0->sn + i0, j->X,
                 j->xrow, i0, bx, j->K, j->cap, j->capc, j->idx, j->dist2);
    }
    return NULL;
  }
  for (int32_t c = j->j0; c < j->j1; c++) { /* scan position c: point ypos[c] */
    col_fill f = {ix, w0->Xc, w0->xn, j->nx, c};
    size_t y = (size_t)ix->ypos[c];
    finish_list(j->w, j->X, j->nx, d, ix->Y + y * d, w0->cols.lv + (size_t)c * j->capc,
                w0->cols.li + (size_t)c * j->capc, j->K, j->capc, j->delta, fill_col, &f,
                j->xrow, j->dist_yx ? j->dist_yx + y * j->K : NULL, j->idx_yx + y * j->K);
  }
  return NULL;
}

/* Float rows of a two-way query's rows i0 .. i1 - 1 (positions; xrow maps them to X's
 * rows) into ws0, with the job's own factored workspace Xd; run_jobs splits them. */
typedef struct screen_job {
  const sm_knn *ix;
  const double *X;
  const int32_t *xrow;
  brute_ws *w0;
  double *Xd;
  int32_t i0, i1, bad;
} screen_job;

static void *screen_job_run(void *arg) {
  screen_job *j = arg;
  int ds = j->ix->ds;
  j->bad = screen_rows(j->ix, j->X, j->xrow + j->i0, j->i1 - j->i0,
                       j->w0->Xc + (size_t)j->i0 * (ds + 1), j->w0->xn + j->i0,
                       j->w0->sn + j->i0, j->Xd);
  return NULL;
}

/* Every query row's float row, the rows split over the query's threads (each row's values
 * do not depend on the split). Returns how many rows are not screenable. */
static int32_t screen_all(const sm_knn *ix, const double *X, const int32_t *xrow, int32_t nx,
                          brute_ws *ws, int n) {
  screen_job jobs[KNN_MAX_THREADS];
  for (int t = 0; t < n; t++) {
    jobs[t] = (screen_job){ix, X, xrow, &ws[0], ws[t].Xd, 0, 0, 0};
    part_rows(nx, t, n, &jobs[t].i0, &jobs[t].i1);
  }
  run_jobs(screen_job_run, jobs, sizeof *jobs, n);
  int32_t bad = 0;
  for (int t = 0; t < n; t++) bad += jobs[t].bad;
  return bad;
}

/* Workspaces of a two-way query: ws[0] holds every query row's float row and column
 * lists; the others read its float rows and keep their own GEMM block, row lists and
 * (unless the directions are split) column lists. */
static int both_ws_alloc(brute_ws *ws, int n, const sm_knn *ix, int32_t nx, int cap,
                         int capc, int split_dirs) {
  int rc = brute_ws_alloc(&ws[0], ix, nx, nx, cap, capc, 1);
  for (int t = 1; t < n; t++)
    if (brute_ws_alloc(&ws[t], ix, nx, 0, cap, capc, !split_dirs)) rc = -1;
  return rc;
}

/* Both directions from one pass; 1 (nothing written) when some query row cannot be
 * screened in float (the caller then runs two plain queries). */
static int query_both_brute(const sm_knn *ix, const double *X, int32_t nx, int K,
                            int32_t *idx, double *dist2, int32_t *idx_yx, double *dist_yx,
                            sm_error *err) {
  int d = ix->d, ds = ix->ds, n = query_threads(ix, nx);
  int cap = K + SCREEN_EXTRA < ix->ny ? K + SCREEN_EXTRA : ix->ny;
  int capc = K + SCREEN_EXTRA < nx ? K + SCREEN_EXTRA : nx;
  /* Split rows share the GEMM but not the column lists: each thread fills its own list for
   * every Y point, and the lists are merged after. That pays when the product dominates
   * the list work: ZoomOut's (K = 1, d = 100-400) 0.89 -> 0.57 s; or when there are many
   * rows (the lists' fill grows as the log of the rows, the scans linearly): the head
   * pair's (15,000 x 14,118, d = 20) initial map, 0.68 -> 0.46 s. Otherwise (list work
   * dominates) the two directions are split instead: one thread fills the rows' lists,
   * the other the columns', each running the whole (cheap) product, nothing to merge.
   * Homer's Sinkhorn supports (K = 16, d = 20 on 5,103 x 8,018; d = 20 and 60 on 2,000 x
   * 2,000) took 0.09-0.10 / 0.018 / 0.024 s on one thread, 0.11-0.15 / 0.025 / 0.027 s
   * with split rows. The lists are the ones a single pass builds either way. */
  int split_dirs = n >= 2 && ds < MIN_DS_PER_LIST * capc && nx < MIN_ROWS_SPLIT;
  if (split_dirs) n = 2;
  brute_ws ws[KNN_MAX_THREADS];
  int32_t *xrow = scan_order(nx); /* the rows in scan order too, for the columns' lists */
  int rc = both_ws_alloc(ws, n, ix, nx, cap, capc, split_dirs);
  if (!xrow) rc = -1;
  if (!rc && screen_all(ix, X, xrow, nx, ws, n)) rc = 1;
  if (rc) {
    for (int t = 0; t < n; t++) brute_ws_free(&ws[t]);
    free(xrow);
    return rc == 1 ? 1 : sm_error_set(err, SM_ENOMEM, "knn: two-way workspace (K=%d, d=%d)", K, d);
  }
  double xmax2 = 0, smax = 0;
  for (int32_t i = 0; i < nx; i++) {
    xmax2 = ws[0].xn[i] > xmax2 ? ws[0].xn[i] : xmax2;
    smax = ws[0].sn[i] > smax ? ws[0].sn[i] : smax;
  }
  /* A column value also rounds xn to float and adds: two more units in the bound, and
   * (factored) the added xn itself. */
  double delta = screen_delta(ds + 2, smax, ix->sy + (ix->L ? xmax2 : 0));
  both_job jobs[KNN_MAX_THREADS];
  for (int t = 0; t < n; t++) {
    jobs[t] = (both_job){ix, X, xrow, &ws[t], &ws[0], nx, 0, nx, 0, 0, K, cap, capc, 0, delta,
                         idx, idx_yx, dist2, dist_yx};
    if (split_dirs && t == 0) jobs[t].idx = NULL; /* ws[0]: the columns' lists only */
    if (!split_dirs) part_rows(nx, t, n, &jobs[t].i0, &jobs[t].i1);
    sm_par_part(ix->ny, t, n, &jobs[t].j0, &jobs[t].j1);
  }
  run_jobs(both_job_run, jobs, sizeof *jobs, n);
  for (int t = 1; t < n && !split_dirs; t++)
    merge_lists(&ws[0].cols, &ws[t].cols, ix->ny, capc, ws[0].vec, ws[0].iv);
  for (int t = 0; t < n; t++) jobs[t].phase = 1;
  run_jobs(both_job_run, jobs, sizeof *jobs, n);
  for (int t = 0; t < n; t++) brute_ws_free(&ws[t]);
  free(xrow);
  return 0;
}

/* ---- kd-tree ------------------------------------------------------------------------ */

static int query_flann(const sm_knn *ix, const double *X, int32_t nx, int K, int32_t *idx,
                       double *dist2, sm_error *err) {
  struct FLANNParameters p = ix->fp;
  pthread_mutex_lock(&flann_lock);
  /* FLANN takes non-const pointers but does not write the query set. */
  int rc = flann_find_nearest_neighbors_index_double(ix->flann, (double *)X, nx, idx, dist2,
                                                     K, &p);
  pthread_mutex_unlock(&flann_lock);
  if (rc < 0)
    return sm_error_set(err, SM_ENUMERIC, "knn: FLANN search failed (%d queries, K=%d)", nx, K);
  for (int32_t i = 0; i < nx; i++) {
    const double *x = X + (size_t)i * ix->d;
    int32_t *iv = idx + (size_t)i * K;
    double *dv = dist2 + (size_t)i * K;
    for (int r = 0; r < K; r++) {
      if (iv[r] < 0 || iv[r] >= ix->ny)
        return sm_error_set(err, SM_ENUMERIC, "knn: FLANN returned index %d for query %d",
                            iv[r], i);
      dv[r] = sm_knn_dist2(x, ix->Y + (size_t)iv[r] * ix->d, ix->d);
    }
    sort_pairs(dv, iv, K);
  }
  return 0;
}

static int query_any(const sm_knn *ix, const double *X, int32_t nx, int K, int32_t *idx,
                     double *dist2, sm_error *err) {
  return ix->strategy == SM_KNN_BRUTE ? query_brute(ix, X, nx, K, idx, dist2, err)
                                      : query_flann(ix, X, nx, K, idx, dist2, err);
}

int sm_knn_query_both(const sm_knn *ix, const double *X, int32_t nx, int K, int32_t *idx,
                      double *dist2, int32_t *idx_yx, double *dist_yx, sm_error *err) {
  if (!ix || !X || nx < 1 || !idx || !idx_yx)
    return sm_error_set(err, SM_EINVAL, "knn: bad two-way query arguments");
  if (K < 1 || K > ix->ny || K > nx)
    return sm_error_set(err, SM_EINVAL, "knn: K=%d outside [1, min(%d, %d)]", K, nx, ix->ny);
  int rc = check_finite(X, (int64_t)nx * ix->d, "query", err);
  if (rc) return rc;
  rc = ix->strategy == SM_KNN_BRUTE
           ? query_both_brute(ix, X, nx, K, idx, dist2, idx_yx, dist_yx, err)
           : 1;
  if (rc != 1) return rc;
  /* kd-tree, or rows too far to screen: two plain queries (the kd-tree's want distances) */
  double *own = malloc(((size_t)nx + ix->ny) * K * sizeof(double));
  if (!own) return sm_error_set(err, SM_ENOMEM, "knn: %d + %d x %d distances", nx, ix->ny, K);
  if (!dist2) dist2 = own;
  if (!dist_yx) dist_yx = own + (size_t)nx * K;
  sm_knn_opts o;
  sm_knn_opts_default(&o);
  o.strategy = ix->strategy;
  sm_knn *ixx = NULL;
  rc = query_any(ix, X, nx, K, idx, dist2, err);
  if (!rc) rc = sm_knn_build(X, nx, ix->d, &o, &ixx, err);
  if (!rc) rc = query_any(ixx, ix->Y, ix->ny, K, idx_yx, dist_yx, err);
  sm_knn_destroy(ixx);
  free(own);
  return rc;
}

int sm_knn_query(const sm_knn *ix, const double *X, int32_t nx, int K, int32_t *idx,
                 double *dist2, sm_error *err) {
  if (!ix || (!X && nx > 0) || nx < 0 || !idx)
    return sm_error_set(err, SM_EINVAL, "knn: bad query arguments");
  if (K < 1 || K > ix->ny)
    return sm_error_set(err, SM_EINVAL, "knn: K=%d outside [1, %d]", K, ix->ny);
  if (nx == 0) return 0;
  int rc = check_finite(X, (int64_t)nx * ix->d, "query", err);
  if (rc) return rc;
  if (ix->strategy == SM_KNN_BRUTE) return query_brute(ix, X, nx, K, idx, dist2, err);
  double *own = NULL;
  if (!dist2) {
    own = malloc((size_t)nx * K * sizeof(double));
    if (!own) return sm_error_set(err, SM_ENOMEM, "knn: %d x %d distances", nx, K);
    dist2 = own;
  }
  rc = query_any(ix, X, nx, K, idx, dist2, err);
  free(own);
  return rc;
}
