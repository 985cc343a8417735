/* Sparse Sinkhorn with eps annealing, stabilized by absorption (algorithm.md §5; Schmitzer,
 * "Stabilized sparse scaling algorithms for entropy regularized transport problems", SISC
 * 2019, Alg. 2).
 *
 * DESIGN
 * Log-domain updates (the reference, and the fallback). With P_ij = exp((f_i + g_j - C_ij)/eps), the row marginal of i is
 *     r_i = exp(f_i/eps) S_i,   S_i = sum_{j in S(i)} exp((g_j - C_ij)/eps).
 * Balanced: r_i = a_i gives f_i = eps (log a_i - log S_i) (and symmetrically for g_j).
 * Unbalanced (penalty rho KL(P1|a)): stationarity of the dual
 *     -rho sum_i a_i (exp(-f_i/rho) - 1) - ... - eps sum_ij P_ij
 * in f_i reads a_i exp(-f_i/rho) = r_i, i.e. f_i = lam eps (log a_i - log S_i),
 * lam = rho/(rho + eps) (lam = 1 is the balanced case). log S_i is a log-sum-exp taken
 * after subtracting the row maximum of (g_j - C_ij), so its largest term is exactly 1:
 * nothing overflows or underflows to an empty sum at any eps. Terms below exp(-SK_CUT)
 * relative to the maximum are below the double rounding of the sum and are skipped, which
 * saves most exp() calls once eps is small.
 * The residual sum_i |r_i - a_i exp(-f_i/rho)| (L1 marginal error when balanced) comes
 * for free from the same sums, before f is overwritten.
 *
 * Kernel scaling with absorption (the default path). The log-domain step costs an exp()
 * per support entry and iteration (~10-20 ns; 1.2-3 s for 550 iterations at 5k points).
 * Write the duals as f_i + eps log u_i, g_j + eps log v_j with f, g fixed ("absorbed")
 * and store the stabilized kernel K_ij = exp((f_i + g_j - C_ij)/eps) once. Then
 *     S_i = exp(-f_i/eps) (K v)_i,
 * and the log-domain update becomes the multiplicative one u_i = a_i / (K v)_i
 * (unbalanced: u_i = (a_i / (K v)_i)^lam exp(-(1 - lam) f_i / eps), per row, not per
 * entry); columns likewise with K^T u. One sweep over the CSR kernel does both halves:
 * row i's sum gives u_i, whose contributions K_ij u_i are scattered into the column sums
 * at once, so an iteration is two multiply-adds per entry (~1-2 ns). In exact arithmetic
 * these are the log-domain iterates; the test compares the two paths to 1e-9.
 * Stability: P_ij = u_i K_ij v_j. Whenever some u_i or v_j leaves [e^-SK_ABSORB,
 * e^SK_ABSORB], and at every eps change, log u and log v are folded into f, g and K is
 * recomputed (the only exp() per entry). With bounded scalings an entry of K that
 * underflows carries a plan entry below 1e-308 e^(2 SK_ABSORB), negligible, and nothing
 * overflows. The one failure left is a row or column whose kernel entries all underflow
 * (or a kernel entry that overflows: a far warm start, a re-truncated support): the sweep
 * then detects a zero or infinite sum, leaves u, v untouched, and the iteration is done
 * once in the log domain, after which every plan entry is <= 1 and K is finite again.
 * So the small-eps robustness of the log domain is kept (eps = 1e-6 c0 in the tests).
 */
#include "sm_sinkhorn.h"

#include <cblas.h>
#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "sm_eigs.h" /* sm_now */
#include "sm_par.h"

#define SK_DEFAULT_K 16
#define SK_DEFAULT_EPS_START 0.3
#define SK_DEFAULT_EPS_END 1e-2
#define SK_DEFAULT_DECAY 0.5
#define SK_DEFAULT_MAX_ITER 20
#define SK_DEFAULT_TOL 1e-6
#define SK_MID_TOL 1e-3      /* intermediate levels only warm-start the next one */
#define SK_LAST_LEVEL_MULT 4 /* the last level gets this many times max_iter */
#define SK_CUT 40.0          /* exp(-40) = 4e-18 < DBL_EPSILON / 50 */
#define SK_ABSORB 50.0       /* absorb once a scaling leaves [e^-50, e^50] */
#define SK_MASS_TOL 1e-6
#define SK_BLOCK_ROWS 128    /* re-truncation distance blocks: 128 x 1024 doubles = 1 MB */
#define SK_BLOCK_COLS 1024
#define SK_AXIS_SAMPLE 2048  /* points per set used to find the backbone axis */
#define SK_AXIS_ITERS 12
#define SK_RETRUNC_MAX_PER_POINT 256
#define SK_RETRUNC_ROUNDS 8
#define SK_BIJ_MIN_SCORE 1e-6
#define SK_TEAM_MIN_ENTRIES 32768

void sm_sinkhorn_opts_default(sm_sinkhorn_opts *o) {
  memset(o, 0, sizeof *o);
  o->k = SK_DEFAULT_K;
  o->eps_start = SK_DEFAULT_EPS_START;
  o->eps_end = SK_DEFAULT_EPS_END;
  o->decay = SK_DEFAULT_DECAY;
  o->max_iter = SK_DEFAULT_MAX_ITER;
  o->tol = SK_DEFAULT_TOL;
  o->knn = SM_KNN_AUTO;
  o->threads = 2; /* the neighbour search is most of the time left (bench_sinkhorn) */
}

/* ---------------------------------------------------------------- pair lists */

/* (i, j) candidates of the support; bit 0 of flag = "K-NN entry" (vs backbone). */
typedef struct sk_pairs {
  int32_t *i, *j;
  uint8_t *flag;
  int64_t len, cap;
} sk_pairs;

static void pairs_free(sk_pairs *p) {
  free(p->i);
  free(p->j);
  free(p->flag);
  memset(p, 0, sizeof *p);
}

static int pairs_reserve(sk_pairs *p, int64_t extra) {
  if (p->len + extra <= p->cap) return 0;
  int64_t cap = p->cap ? p->cap : 1024;
  while (cap < p->len + extra) cap *= 2;
  int32_t *ni = realloc(p->i, (size_t)cap * sizeof *ni);
  if (ni) p->i = ni;
  int32_t *nj = realloc(p->j, (size_t)cap * sizeof *nj);
  if (nj) p->j = nj;
  uint8_t *nf = realloc(p->flag, (size_t)cap);
  if (nf) p->flag = nf;
  if (!ni || !nj || !nf) return SM_ENOMEM;
  p->cap = cap;
  return 0;
}

static inline void pairs_put(sk_pairs *p, int32_t i, int32_t j, uint8_t flag) {
  p->i[p->len] = i;
  p->j[p->len] = j;
  p->flag[p->len] = flag;
  p->len++;
}

/* ---------------------------------------------------------------- nearest neighbours */

/* One direction of the K-NN search, job i of an sm_par_for over the two. */
typedef struct sk_knn_job {
  const sm_knn *ix;
  const double *X;
  int32_t n;
  int k;
  int32_t *idx;
  double *dist;
  sm_error err;
  int rc;
} sk_knn_job;

static void knn_job_run(void *jobs, int i) {
  sk_knn_job *jb = (sk_knn_job *)jobs + i;
  jb->rc = sm_knn_query(jb->ix, jb->X, jb->n, jb->k, jb->idx, jb->dist, &jb->err);
}

/* K nearest g's of every f_i and K nearest f's of every g_j, by sm_knn (exact either
 * way, so the support does not depend on the strategy). Brute force with the same K both
 * ways: one two-way pass (sm_knn_query_both). Otherwise, with threads >= 2 and brute
 * force, the two directions run concurrently (two independent indexes: allowed by
 * sm_knn; the kd-tree search is serialized inside sm_knn and uses the threads itself). */
static int add_knn_pairs(const double *F, int32_t nx, const double *G, int32_t ny, int32_t d,
                         const sm_sinkhorn_opts *o, sk_pairs *pr, sm_error *err) {
  int kx = o->k < ny ? o->k : ny, ky = o->k < nx ? o->k : nx;
  sm_knn_opts ko;
  sm_knn_opts_default(&ko);
  ko.strategy = o->knn;
  ko.threads = o->threads;
  ko.query_threads = o->threads;
  int32_t *ri = malloc(sizeof(int32_t) * (size_t)nx * kx);
  int32_t *ci = malloc(sizeof(int32_t) * (size_t)ny * ky);
  double *rd = malloc(sizeof(double) * (size_t)nx * kx);
  double *cd = malloc(sizeof(double) * (size_t)ny * ky);
  sm_knn *ig = NULL, *jf = NULL;
  int rc = ri && ci && rd && cd ? 0 : SM_ENOMEM;
  if (!rc) rc = sm_knn_build(G, ny, d, &ko, &ig, err);
  /* Brute force: both directions from one pass over the distances (one GEMM, not two;
   * cheaper in CPU than the two directions on two threads, which a busy server cannot
   * spare anyway). */
  int both = !rc && kx == ky && sm_knn_strategy_of(ig) == SM_KNN_BRUTE;
  if (both) rc = sm_knn_query_both(ig, F, nx, kx, ri, rd, ci, cd, err);
  if (!rc && !both) rc = sm_knn_build(F, nx, d, &ko, &jf, err);
  if (!rc && !both) {
    sk_knn_job jobs[2] = {{ig, F, nx, kx, ri, rd, {0}, 0}, {jf, G, ny, ky, ci, cd, {0}, 0}};
    int par = o->threads >= 2 && sm_knn_strategy_of(ig) == SM_KNN_BRUTE;
    sm_par_for(2, par ? 2 : 1, knn_job_run, jobs);
    sk_knn_job *bad = jobs[0].rc ? &jobs[0] : jobs[1].rc ? &jobs[1] : NULL;
    if (bad) {
      rc = bad->rc;
      if (err) *err = bad->err;
    }
  }
  sm_knn_destroy(ig), sm_knn_destroy(jf);
  if (!rc) rc = pairs_reserve(pr, (int64_t)nx * kx + (int64_t)ny * ky);
  if (!rc) {
    for (int32_t i = 0; i < nx; i++)
      for (int t = 0; t < kx; t++) pairs_put(pr, i, ri[(size_t)i * kx + t], 1);
    for (int32_t j = 0; j < ny; j++)
      for (int t = 0; t < ky; t++) pairs_put(pr, ci[(size_t)j * ky + t], j, 1);
  }
  free(ri), free(ci), free(rd), free(cd);
  if (rc == SM_ENOMEM) return sm_error_set(err, rc, "sinkhorn: no memory for the neighbour lists");
  return rc;
}

/* ---------------------------------------------------------------- feasibility backbone */

typedef struct sk_key {
  double v;
  int32_t i;
} sk_key;

static int key_cmp(const void *pa, const void *pb) {
  const sk_key *x = pa, *y = pb;
  if (x->v != y->v) return x->v < y->v ? -1 : 1;
  return (x->i > y->i) - (x->i < y->i);
}

/* Principal axis of the union of (subsamples of) F and G by power iteration: any axis
 * gives a feasible backbone, a long one makes it geometrically sensible. */
static void principal_axis(const double *F, int32_t nx, const double *G, int32_t ny,
                           int32_t d, double *mu, double *v, double *w) {
  const double *set[2] = {F, G};
  int32_t n[2] = {nx, ny}, step[2];
  double cnt = 0;
  memset(mu, 0, sizeof(double) * (size_t)d);
  for (int s = 0; s < 2; s++) {
    step[s] = n[s] > SK_AXIS_SAMPLE ? n[s] / SK_AXIS_SAMPLE : 1;
    for (int32_t p = 0; p < n[s]; p += step[s], cnt++)
      for (int32_t t = 0; t < d; t++) mu[t] += set[s][(size_t)p * d + t];
  }
  for (int32_t t = 0; t < d; t++) mu[t] /= cnt, v[t] = 1.0 + 1e-3 * t; /* generic start */
  for (int it = 0; it < SK_AXIS_ITERS; it++) {
    memset(w, 0, sizeof(double) * (size_t)d);
    for (int s = 0; s < 2; s++)
      for (int32_t p = 0; p < n[s]; p += step[s]) {
        const double *x = set[s] + (size_t)p * d;
        double c = 0;
        for (int32_t t = 0; t < d; t++) c += (x[t] - mu[t]) * v[t];
        for (int32_t t = 0; t < d; t++) w[t] += c * (x[t] - mu[t]);
      }
    double nrm = 0;
    for (int32_t t = 0; t < d; t++) nrm += w[t] * w[t];
    if (!(nrm > 0)) return; /* all sampled points equal: keep v */
    nrm = sqrt(nrm);
    for (int32_t t = 0; t < d; t++) v[t] = w[t] / nrm;
  }
}

static void sort_along(const double *X, int32_t n, int32_t d, const double *mu,
                       const double *v, sk_key *key) {
  for (int32_t p = 0; p < n; p++) {
    double c = 0;
    for (int32_t t = 0; t < d; t++) c += (X[(size_t)p * d + t] - mu[t]) * v[t];
    key[p].v = c;
    key[p].i = p;
  }
  qsort(key, (size_t)n, sizeof *key, key_cmp);
}

/* The two sorts of the backbone, one per job (sm_team_for). */
typedef struct sk_sort_job {
  const double *X[2], *mu, *v;
  int32_t n[2], d;
  sk_key *key[2];
} sk_sort_job;

static void sort_job(void *ctx, int s) {
  sk_sort_job *c = ctx;
  sort_along(c->X[s], c->n[s], c->d, c->mu, c->v, c->key[s]);
}

/* North-west-corner rule on the two sorted lists: the support of a feasible plan for
 * (a, b) with at most nx + ny - 1 entries; every row and column appears. team (or NULL)
 * runs the two sorts. */
static int add_backbone(const double *F, int32_t nx, const double *G, int32_t ny, int32_t d,
                        const double *a, const double *b, sm_team *team, sk_pairs *pr) {
  double *tmp = malloc(sizeof(double) * 3 * (size_t)d);
  sk_key *kx = malloc(sizeof(sk_key) * (size_t)nx), *ky = malloc(sizeof(sk_key) * (size_t)ny);
  int rc = SM_ENOMEM;
  if (tmp && kx && ky && !pairs_reserve(pr, (int64_t)nx + ny)) {
    principal_axis(F, nx, G, ny, d, tmp, tmp + d, tmp + 2 * d);
    sk_sort_job sj = {{F, G}, tmp, tmp + d, {nx, ny}, d, {kx, ky}};
    sm_team_for(team, 2, sort_job, &sj);
    int32_t i = 0, j = 0;
    double ra = a[kx[0].i], rb = b[ky[0].i];
    for (;;) {
      pairs_put(pr, kx[i].i, ky[j].i, 0);
      if (i == nx - 1 && j == ny - 1) break;
      if (j == ny - 1 || (i < nx - 1 && ra < rb)) {
        rb -= ra, ra = a[kx[++i].i];
      } else if (i == nx - 1 || rb < ra) {
        ra -= rb, rb = b[ky[++j].i];
      } else {
        ra = a[kx[++i].i], rb = b[ky[++j].i];
      }
    }
    rc = 0;
  }
  free(tmp), free(kx), free(ky);
  return rc;
}

/* ---------------------------------------------------------------- support (CSR + CSC) */

typedef struct sk_support {
  int32_t nx, ny;
  int64_t nnz, nnz_knn;
  int64_t *rowptr;
  int32_t *col;
  double *cost;    /* C_ij in CSR order */
  int64_t *colptr; /* CSC transpose, rows sorted within a column */
  int32_t *row;
  double *ccost;   /* C_ij in CSC order */
  int64_t *cpos;   /* CSC position of each CSR entry */
  int32_t maxlen;  /* longest row or column */
  double c0;       /* mean cost over the K-NN entries */
} sk_support;

static void support_free(sk_support *s) {
  free(s->rowptr), free(s->col), free(s->cost);
  free(s->colptr), free(s->row), free(s->ccost), free(s->cpos);
  memset(s, 0, sizeof *s);
}

static int i64_cmp(const void *pa, const void *pb) {
  int64_t x = *(const int64_t *)pa, y = *(const int64_t *)pb;
  return (x > y) - (x < y);
}

/* Sorts and deduplicates each row's keys (col << 1 | knn flag); returns the new length. */
static int64_t dedup_row(int64_t *k, int64_t len) {
  if (len <= 1) return len;
  qsort(k, (size_t)len, sizeof *k, i64_cmp);
  int64_t w = 0;
  for (int64_t r = 0; r < len; r++) {
    if (w > 0 && (k[w - 1] >> 1) == (k[r] >> 1))
      k[w - 1] |= k[r] & 1;
    else
      k[w++] = k[r];
  }
  return w;
}

/* Row-sorted, deduplicated keys (col << 1 | knn flag) of the pair list and the CSR row
 * pointers; *keys is allocated here. */
/* Row parts of the support's construction (sm_team_for): row i of part p of np. */
typedef struct sk_rows_job {
  int np;
  const int64_t *end; /* csr_keys: row i's keys end at end[i] (and begin at end[i - 1]) */
  int64_t *key, *len; /* csr_keys: each row deduplicated in place, its length in len[i] */
  sk_support *s;      /* fill_support: columns and exact costs per row */
  const double *F, *G;
  int32_t d;
  int64_t maxlen[SM_PAR_MAX_THREADS];
} sk_rows_job;

static void dedup_job(void *ctx, int p) {
  sk_rows_job *c = ctx;
  int32_t a, b;
  sm_par_part(c->s->nx, p, c->np, &a, &b);
  for (int32_t i = a; i < b; i++) {
    int64_t beg = i ? c->end[i - 1] : 0;
    c->len[i] = dedup_row(c->key + beg, c->end[i] - beg);
  }
}

static int csr_keys(const sk_pairs *pr, sk_support *s, sm_team *team, int64_t **keys) {
  int32_t nx = s->nx;
  int64_t *rowptr = s->rowptr;
  int64_t *end = calloc((size_t)nx + 1, sizeof *end);
  int64_t *key = malloc(sizeof(int64_t) * (size_t)(pr->len ? pr->len : 1));
  if (!end || !key) {
    free(end), free(key);
    return SM_ENOMEM;
  }
  for (int64_t p = 0; p < pr->len; p++) end[pr->i[p] + 1]++;
  for (int32_t i = 0; i < nx; i++) end[i + 1] += end[i];
  for (int64_t p = 0; p < pr->len; p++)
    key[end[pr->i[p]]++] = ((int64_t)pr->j[p] << 1) | pr->flag[p];
  /* end[i] is now the end of row i; deduplicate each row (by parts, lengths in
   * rowptr[i + 1]), then compact in place */
  sk_rows_job c = {.np = sm_team_threads(team), .end = end, .key = key, .len = rowptr + 1, .s = s};
  sm_team_for(team, c.np, dedup_job, &c);
  int64_t w = 0, beg = 0;
  rowptr[0] = 0;
  for (int32_t i = 0; i < nx; i++) {
    int64_t len = rowptr[i + 1];
    memmove(key + w, key + beg, sizeof(int64_t) * (size_t)len);
    beg = end[i];
    w += len;
    rowptr[i + 1] = w;
  }
  free(end);
  *keys = key;
  return 0;
}

static void cost_job(void *ctx, int p) {
  sk_rows_job *c = ctx;
  sk_support *s = c->s;
  int32_t a, b, d = c->d;
  sm_par_part(s->nx, p, c->np, &a, &b);
  c->maxlen[p] = 0;
  for (int32_t i = a; i < b; i++) {
    int64_t len = s->rowptr[i + 1] - s->rowptr[i];
    if (len > c->maxlen[p]) c->maxlen[p] = len;
    for (int64_t q = s->rowptr[i]; q < s->rowptr[i + 1]; q++) {
      int32_t j = (int32_t)(c->key[q] >> 1);
      s->col[q] = j;
      s->cost[q] = sm_knn_dist2(c->F + (size_t)i * d, c->G + (size_t)j * d, d);
    }
  }
}

/* Columns, exact costs (by row parts), c0 (summed in CSR order) and the CSC transpose
 * from the keys. */
static int fill_support(sk_support *s, int64_t *key, const double *F, const double *G,
                        int32_t d, sm_team *team) {
  sk_rows_job c = {.np = sm_team_threads(team), .key = key, .s = s, .F = F, .G = G, .d = d};
  sm_team_for(team, c.np, cost_job, &c);
  for (int p = 0; p < c.np; p++)
    if (c.maxlen[p] > s->maxlen) s->maxlen = (int32_t)c.maxlen[p];
  double sum = 0;
  for (int64_t q = 0; q < s->nnz; q++) {
    if (key[q] & 1) s->nnz_knn++, sum += s->cost[q];
    s->colptr[s->col[q] + 1]++;
  }
  s->c0 = s->nnz_knn ? sum / (double)s->nnz_knn : 0.0;
  for (int32_t j = 0; j < s->ny; j++) {
    if (s->colptr[j + 1] > s->maxlen) s->maxlen = (int32_t)s->colptr[j + 1];
    s->colptr[j + 1] += s->colptr[j];
  }
  int64_t *fill = malloc(sizeof(int64_t) * ((size_t)s->ny + 1));
  if (!fill) return SM_ENOMEM;
  memcpy(fill, s->colptr, sizeof(int64_t) * ((size_t)s->ny + 1));
  for (int32_t i = 0; i < s->nx; i++)
    for (int64_t p = s->rowptr[i]; p < s->rowptr[i + 1]; p++) {
      int64_t q = fill[s->col[p]]++;
      s->cpos[p] = q;
      s->row[q] = i;
      s->ccost[q] = s->cost[p];
    }
  free(fill);
  return 0;
}

/* team (or NULL) runs the per-row work; the support does not depend on it. */
static int build_support(const sk_pairs *pr, const double *F, int32_t nx, const double *G,
                         int32_t ny, int32_t d, sm_team *team, sk_support *s) {
  memset(s, 0, sizeof *s);
  s->nx = nx, s->ny = ny;
  s->rowptr = malloc(sizeof(int64_t) * ((size_t)nx + 1));
  s->colptr = calloc((size_t)ny + 1, sizeof(int64_t));
  int64_t *key = NULL;
  if (!s->rowptr || !s->colptr || csr_keys(pr, s, team, &key)) goto oom;
  s->nnz = s->rowptr[nx];
  size_t nz = (size_t)(s->nnz ? s->nnz : 1);
  s->col = malloc(sizeof(int32_t) * nz), s->cost = malloc(sizeof(double) * nz);
  s->row = malloc(sizeof(int32_t) * nz), s->ccost = malloc(sizeof(double) * nz);
  s->cpos = malloc(sizeof(int64_t) * nz);
  if (!s->col || !s->cost || !s->row || !s->ccost || !s->cpos ||
      fill_support(s, key, F, G, d, team))
    goto oom;
  free(key);
  return 0;
oom:
  free(key);
  support_free(s);
  return SM_ENOMEM;
}

/* ---------------------------------------------------------------- iterations */

/* Log-domain half-step for all rows (or, with the CSC arrays, all columns): own_i becomes
 * lam eps (logm_i - log S_i) with S_i = sum_j exp((other_j - C_ij)/eps). Returns the
 * residual sum_i |r_i - m_i exp(-own_i/rho)| of the duals it was given (inf when a
 * changed support makes r_i overflow: harmless, the duals stay finite). z: scratch of the
 * longest row; *sum accumulates the new duals (a cheap finiteness check). */
static double lse_update(int32_t n, const int64_t *ptr, const int32_t *idx, const double *cost,
                         const double *other, double *own, const double *logm, double eps,
                         double lam, double inv_rho, double *z, double *sum) {
  double inv_eps = 1.0 / eps, res = 0.0;
  for (int32_t i = 0; i < n; i++) {
    int64_t p0 = ptr[i], len = ptr[i + 1] - p0;
    if (len == 0) continue;
    double m = -INFINITY;
    for (int64_t q = 0; q < len; q++) {
      double v = other[idx[p0 + q]] - cost[p0 + q];
      z[q] = v;
      if (v > m) m = v;
    }
    double s = 0.0;
    for (int64_t q = 0; q < len; q++) {
      double t = (z[q] - m) * inv_eps;
      if (t > -SK_CUT) s += exp(t);
    }
    double lse = m * inv_eps + log(s);
    res += fabs(exp(own[i] * inv_eps + lse) - exp(logm[i] - own[i] * inv_rho));
    own[i] = lam * eps * (logm[i] - lse);
    *sum += own[i];
  }
  return res;
}

typedef struct sk_solver {
  sk_support S;
  int32_t nx, ny;
  double *a, *b, *loga, *logb; /* normalized masses */
  double *f, *g, *z;           /* absorbed duals; z: scratch of the longest row/column */
  double *K;                   /* exp((f_i + g_j - C_ij)/eps) in CSR order */
  double *u, *v, *un, *cs;     /* scalings (nx, ny), next u, column sums (ny) */
  /* Threaded sweeps (team != NULL): K in CSC order too, and each row's residual. */
  sm_team *team;
  double *Kc, *rres;
  double keps;                 /* eps of K, u, v; 0: K not computed */
  double c0, rho;              /* absolute */
  const sm_sinkhorn_opts *o;
  sm_sinkhorn_stats *st;
} sk_solver;

static void solver_free(sk_solver *sv) {
  support_free(&sv->S);
  free(sv->a), free(sv->b), free(sv->loga), free(sv->logb);
  free(sv->f), free(sv->g), free(sv->z), free(sv->K);
  free(sv->u), free(sv->v), free(sv->un), free(sv->cs);
  free(sv->Kc), free(sv->rres);
  sm_team_free(sv->team);
}

/* Scaling arrays sized for the current support (again after re-truncation). */
static int solver_alloc(sk_solver *sv) {
  free(sv->z), free(sv->K), free(sv->Kc);
  size_t nz = (size_t)(sv->S.nnz > 0 ? sv->S.nnz : 1);
  sv->z = malloc(sizeof(double) * (size_t)(sv->S.maxlen > 0 ? sv->S.maxlen : 1));
  sv->K = malloc(sizeof(double) * nz);
  sv->Kc = sv->team ? malloc(sizeof(double) * nz) : NULL;
  if (sv->team && !sv->rres) sv->rres = malloc(sizeof(double) * (size_t)sv->nx);
  if (sv->team && (!sv->Kc || !sv->rres)) return SM_ENOMEM;
  if (!sv->u) sv->u = malloc(sizeof(double) * (size_t)sv->nx);
  if (!sv->un) sv->un = malloc(sizeof(double) * (size_t)sv->nx);
  if (!sv->v) sv->v = malloc(sizeof(double) * (size_t)sv->ny);
  if (!sv->cs) sv->cs = malloc(sizeof(double) * (size_t)sv->ny);
  sv->keps = 0;
  return sv->z && sv->K && sv->u && sv->un && sv->v && sv->cs ? 0 : SM_ENOMEM;
}

/* Folds eps log u, eps log v into f, g (u = v = 1 afterwards). Returns 0, or SM_ENUMERIC
 * if a dual is not finite. */
static int fold_scalings(sk_solver *sv) {
  double sum = 0;
  if (sv->keps > 0) {
    for (int32_t i = 0; i < sv->nx; i++) sv->f[i] += sv->keps * log(sv->u[i]);
    for (int32_t j = 0; j < sv->ny; j++) sv->g[j] += sv->keps * log(sv->v[j]);
  }
  for (int32_t i = 0; i < sv->nx; i++) sum += sv->f[i], sv->u[i] = 1.0;
  for (int32_t j = 0; j < sv->ny; j++) sum += sv->g[j], sv->v[j] = 1.0;
  sv->keps = 0;
  return isfinite(sum) ? 0 : SM_ENUMERIC;
}

/* ---- threaded steps: rows (columns) in parts, one part per team thread. Every value is
 * computed as on one thread (per row or column, in the same order), so the iterates do
 * not depend on the thread count. */

typedef struct sk_step {
  sk_solver *sv;
  double lam, inv_eps;
  int np;
  int ok[SM_PAR_MAX_THREADS], out[SM_PAR_MAX_THREADS];
} sk_step;

/* Kernel entries of rows i0 .. i1 - 1 (and their CSC copies when threaded); 1 if finite. */
static int absorb_rows(sk_solver *sv, int32_t i0, int32_t i1, double inv_eps) {
  const sk_support *S = &sv->S;
  int ok = 1;
  for (int32_t i = i0; i < i1; i++) {
    double fi = sv->f[i];
    for (int64_t q = S->rowptr[i]; q < S->rowptr[i + 1]; q++) {
      double k = exp((fi + sv->g[S->col[q]] - S->cost[q]) * inv_eps);
      sv->K[q] = k;
      if (sv->Kc) sv->Kc[S->cpos[q]] = k;
      ok &= k <= DBL_MAX;
    }
  }
  return ok;
}

static void absorb_job(void *ctx, int p) {
  sk_step *c = ctx;
  int32_t i0, i1;
  sm_par_part(c->sv->nx, p, c->np, &i0, &i1);
  c->ok[p] = absorb_rows(c->sv, i0, i1, c->inv_eps);
}

/* Absorption: folds the scalings into the duals and recomputes the kernel at eps (the
 * only exp() per entry). Returns 1 if every K_ij is finite. */
static int absorb(sk_solver *sv, double eps) {
  if (fold_scalings(sv)) return 0;
  sk_step c = {.sv = sv, .inv_eps = 1.0 / eps, .np = sm_team_threads(sv->team)};
  sm_team_for(sv->team, c.np, absorb_job, &c);
  int ok = 1;
  for (int p = 0; p < c.np; p++) ok &= c.ok[p];
  sv->keps = eps;
  return ok;
}

/* New scaling of a row (column) from its kernel sum s = (K v)_i: the log-domain update
 * f_i <- lam eps (log a_i - lse_i), lse_i = log s - f_i/eps, divided by exp(f_i/eps). */
static inline double scale_of(double s, double m, double logm, double fi, double inv_eps,
                              double lam) {
  if (lam == 1.0) return m / s;
  return exp(lam * (logm - log(s)) - (1.0 - lam) * fi * inv_eps);
}

/* New scaling of row i from its kernel sum s = (K v)_i; *r gets the row's residual of the
 * incoming u, v (as the log domain computes it). */
static inline double row_scaling(const sk_solver *sv, int32_t i, double s, double lam,
                                 double inv_eps, double *r) {
  double ri = sv->u[i] * s;
  if (lam == 1.0) {
    *r = fabs(ri - sv->a[i]);
    return sv->a[i] / s;
  }
  const double inv_rho = sv->rho > 0 ? 1.0 / sv->rho : 0.0;
  *r = fabs(ri - sv->a[i] * exp(-(sv->f[i] + sv->keps * log(sv->u[i])) * inv_rho));
  return scale_of(s, sv->a[i], sv->loga[i], sv->f[i], inv_eps, lam);
}

/* Column j's new scaling from its kernel sum cs = (K^T u)_j; flags as in scaling_sweep. */
static inline double col_scaling(const sk_solver *sv, int32_t j, double cs, double lam,
                                 double inv_eps, int *ok, int *o) {
  double vj = scale_of(cs, sv->b[j], sv->logb[j], sv->g[j], inv_eps, lam);
  *ok &= vj > 0 && vj <= DBL_MAX;
  *o |= vj > exp(SK_ABSORB) || vj < exp(-SK_ABSORB);
  return vj;
}

/* Finishes a sweep whose new scalings are in un (rows) and cs (non-empty columns). */
static void take_scalings(sk_solver *sv) {
  const sk_support *S = &sv->S;
  for (int32_t j = 0; j < sv->ny; j++)
    if (S->colptr[j] != S->colptr[j + 1]) sv->v[j] = sv->cs[j];
  double *t = sv->u;
  sv->u = sv->un, sv->un = t;
}

/* One iteration of plain scaling, rows then columns, in a single pass over K: the row
 * sums (K v)_i give u_i, whose contributions K_ij u_i are scattered into the column sums
 * at once. Returns 1 and sets *res (the row residual of the incoming u, v, as the log
 * domain computes it) and *out (1 if some scaling left [e^-SK_ABSORB, e^SK_ABSORB]);
 * returns 0 without touching u, v if a sum vanished or overflowed. */
static int scaling_sweep(sk_solver *sv, double lam, double *res, int *out) {
  const sk_support *S = &sv->S;
  const double *K = sv->K, *v = sv->v;
  const double hi = exp(SK_ABSORB), lo = exp(-SK_ABSORB), inv_eps = 1.0 / sv->keps;
  double *un = sv->un, *cs = sv->cs, r = 0.0;
  int ok = 1, o = 0;
  memset(cs, 0, sizeof(double) * (size_t)sv->ny);
  for (int32_t i = 0; i < sv->nx; i++) {
    int64_t p0 = S->rowptr[i], p1 = S->rowptr[i + 1];
    if (p0 == p1) {
      un[i] = sv->u[i];
      continue;
    }
    double s = 0.0, ri;
    for (int64_t q = p0; q < p1; q++) s += K[q] * v[S->col[q]];
    double ui = row_scaling(sv, i, s, lam, inv_eps, &ri);
    r += ri;
    ok &= ui > 0 && ui <= DBL_MAX;
    o |= ui > hi || ui < lo;
    un[i] = ui;
    for (int64_t q = p0; q < p1; q++) cs[S->col[q]] += K[q] * ui;
  }
  if (!ok) return 0;
  for (int32_t j = 0; j < sv->ny; j++)
    if (S->colptr[j] != S->colptr[j + 1]) cs[j] = col_scaling(sv, j, cs[j], lam, inv_eps, &ok, &o);
  if (!ok) return 0;
  take_scalings(sv);
  *res = r, *out = o;
  return 1;
}

/* The same sweep in two threaded halves: the rows' new scalings (and residuals, summed
 * in row order afterwards), then each column's sum gathered from the CSC copy of K, its
 * rows in ascending order: the products and additions of the scattered sum, in the same
 * order, so the same bits. */
static void sweep_rows_job(void *ctx, int p) {
  sk_step *c = ctx;
  sk_solver *sv = c->sv;
  const sk_support *S = &sv->S;
  const double hi = exp(SK_ABSORB), lo = exp(-SK_ABSORB);
  int32_t i0, i1;
  int ok = 1, o = 0;
  sm_par_part(sv->nx, p, c->np, &i0, &i1);
  for (int32_t i = i0; i < i1; i++) {
    int64_t p0 = S->rowptr[i], p1 = S->rowptr[i + 1];
    sv->rres[i] = 0.0;
    if (p0 == p1) {
      sv->un[i] = sv->u[i];
      continue;
    }
    double s = 0.0;
    for (int64_t q = p0; q < p1; q++) s += sv->K[q] * sv->v[S->col[q]];
    double ui = row_scaling(sv, i, s, c->lam, c->inv_eps, &sv->rres[i]);
    ok &= ui > 0 && ui <= DBL_MAX;
    o |= ui > hi || ui < lo;
    sv->un[i] = ui;
  }
  c->ok[p] = ok, c->out[p] = o;
}

static void sweep_cols_job(void *ctx, int p) {
  sk_step *c = ctx;
  sk_solver *sv = c->sv;
  const sk_support *S = &sv->S;
  int32_t j0, j1;
  int ok = 1, o = 0;
  sm_par_part(sv->ny, p, c->np, &j0, &j1);
  for (int32_t j = j0; j < j1; j++) {
    if (S->colptr[j] == S->colptr[j + 1]) continue;
    double cs = 0.0;
    for (int64_t q = S->colptr[j]; q < S->colptr[j + 1]; q++) cs += sv->Kc[q] * sv->un[S->row[q]];
    sv->cs[j] = col_scaling(sv, j, cs, c->lam, c->inv_eps, &ok, &o);
  }
  c->ok[p] = ok, c->out[p] = o;
}

static int scaling_sweep_team(sk_solver *sv, double lam, double *res, int *out) {
  sk_step c = {.sv = sv, .lam = lam, .inv_eps = 1.0 / sv->keps, .np = sm_team_threads(sv->team)};
  int ok = 1, o = 0;
  sm_team_for(sv->team, c.np, sweep_rows_job, &c);
  for (int p = 0; p < c.np; p++) ok &= c.ok[p], o |= c.out[p];
  if (!ok) return 0;
  sm_team_for(sv->team, c.np, sweep_cols_job, &c);
  for (int p = 0; p < c.np; p++) ok &= c.ok[p], o |= c.out[p];
  if (!ok) return 0;
  double r = 0.0;
  for (int32_t i = 0; i < sv->nx; i++) r += sv->rres[i];
  take_scalings(sv);
  *res = r, *out = o;
  return 1;
}

/* One log-domain iteration on the full duals (the stable fallback, and the reference
 * path). Returns the residual, or NaN if a dual is not
 * finite. */
static double log_iteration(sk_solver *sv, double eps, double lam) {
  const sk_support *S = &sv->S;
  double inv_rho = sv->rho > 0 ? 1.0 / sv->rho : 0.0, sum = 0.0;
  if (fold_scalings(sv)) return NAN;
  double r = lse_update(sv->nx, S->rowptr, S->col, S->cost, sv->g, sv->f, sv->loga, eps, lam,
                        inv_rho, sv->z, &sum);
  lse_update(sv->ny, S->colptr, S->row, S->ccost, sv->f, sv->g, sv->logb, eps, lam, inv_rho,
             sv->z, &sum);
  return isfinite(sum) ? r : NAN;
}

/* Iterates at one eps until the residual is below tol or maxit iterations; on return
 * the scalings are folded into f, g. */
static int run_level(sk_solver *sv, double eps, int maxit, double tol, sm_error *err) {
  double lam = sv->rho > 0 ? sv->rho / (sv->rho + eps) : 1.0;
  int scaling = !sv->o->log_domain;
  sm_sinkhorn_stats *st = sv->st;
  st->levels++;
  st->converged = 0;
  /* warm start: the kernel of the previous level's duals at the new eps */
  int stale = scaling && !absorb(sv, eps);
  int rc = 0;
  for (int it = 0; it < maxit; it++) {
    if (sv->o->cancel && sv->o->cancel(sv->o->cancel_ud)) {
      rc = sm_error_set(err, SM_ECANCELED, "sinkhorn: canceled at eps=%g, iteration %d", eps,
                        st->iterations);
      break;
    }
    double r = NAN;
    int out = 0;
    int swept = scaling && !stale &&
                (sv->team ? scaling_sweep_team(sv, lam, &r, &out)
                          : scaling_sweep(sv, lam, &r, &out));
    if (swept) {
      if (out) { /* bounded scalings keep u K v clear of overflow and underflow */
        stale = !absorb(sv, eps);
        st->absorptions++;
      }
    } else {
      /* a kernel sum vanished or overflowed (a far warm start, a new support): one
       * log-domain step brings every entry of the plan below 1 */
      r = log_iteration(sv, eps, lam);
      if (isnan(r)) {
        rc = sm_error_set(err, SM_ENUMERIC, "sinkhorn: non-finite duals at eps=%g", eps);
        break;
      }
      if (scaling) { /* the plan's entries are now <= 1: the kernel is finite */
        stale = !absorb(sv, eps);
        st->absorptions++;
      }
    }
    st->iterations++;
    st->residual = r;
    if (r < tol) {
      st->converged = 1;
      break;
    }
  }
  if (fold_scalings(sv) && !rc)
    rc = sm_error_set(err, SM_ENUMERIC, "sinkhorn: non-finite duals at eps=%g", eps);
  return rc;
}

/* Geometric eps schedule from eps_start to eps_end, duals carried over (warm start). */
static int anneal(sk_solver *sv, sm_error *err) {
  const sm_sinkhorn_opts *o = sv->o;
  double eps = o->eps_start * sv->c0, eps_end = o->eps_end * sv->c0;
  double mid_tol = o->tol > SK_MID_TOL ? o->tol : SK_MID_TOL;
  for (;;) {
    int last = eps <= eps_end * (1 + 1e-12);
    if (last) eps = eps_end;
    int rc = last ? run_level(sv, eps, o->max_iter * SK_LAST_LEVEL_MULT, o->tol, err)
                  : run_level(sv, eps, o->max_iter, mid_tol, err);
    if (rc) return rc;
    if (last) break;
    eps *= o->decay;
  }
  sv->st->eps = eps_end;
  return 0;
}

/* ---------------------------------------------------------------- re-truncation */

/* All-pairs squared distances block by block: D (ni x nj, leading dim SK_BLOCK_COLS) =
 * |x|^2 + |y|^2 - 2 X Y^T, the product by dgemm. Re-truncation keeps pairs under a
 * per-pair threshold, which no K-NN query answers, hence this scan. The visitor sees
 * approximate values (cancellation): the threshold carries a slack, and the costs of the
 * kept pairs are recomputed exactly. */
typedef void (*sk_block_fn)(void *ctx, int32_t i0, int32_t ni, int32_t j0, int32_t nj,
                            const double *D);

static int scan_blocks(const double *F, int32_t nx, const double *G, int32_t ny, int32_t d,
                       sk_block_fn fn, void *ctx) {
  double *D = malloc(sizeof(double) * SK_BLOCK_ROWS * SK_BLOCK_COLS);
  double *nf = malloc(sizeof(double) * (size_t)nx);
  double *ng = malloc(sizeof(double) * (size_t)ny);
  if (!D || !nf || !ng) {
    free(D), free(nf), free(ng);
    return SM_ENOMEM;
  }
  for (int32_t i = 0; i < nx; i++) nf[i] = cblas_ddot(d, F + (size_t)i * d, 1, F + (size_t)i * d, 1);
  for (int32_t j = 0; j < ny; j++) ng[j] = cblas_ddot(d, G + (size_t)j * d, 1, G + (size_t)j * d, 1);
  for (int32_t i0 = 0; i0 < nx; i0 += SK_BLOCK_ROWS) {
    int32_t ni = nx - i0 < SK_BLOCK_ROWS ? nx - i0 : SK_BLOCK_ROWS;
    for (int32_t j0 = 0; j0 < ny; j0 += SK_BLOCK_COLS) {
      int32_t nj = ny - j0 < SK_BLOCK_COLS ? ny - j0 : SK_BLOCK_COLS;
      cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, ni, nj, d, -2.0,
                  F + (size_t)i0 * d, d, G + (size_t)j0 * d, d, 0.0, D, SK_BLOCK_COLS);
      for (int32_t r = 0; r < ni; r++) {
        double *row = D + (size_t)r * SK_BLOCK_COLS;
        for (int32_t c = 0; c < nj; c++) row[c] += nf[i0 + r] + ng[j0 + c];
      }
      fn(ctx, i0, ni, j0, nj, D);
    }
  }
  free(D), free(nf), free(ng);
  return 0;
}

/* Keeps (i, j) with P_ij >= exp(-theta) min(a_i, b_j), i.e.
 * C_ij <= max(A_i + g_j, f_i + B_j), A_i = f_i + eps (theta - log a_i), B_j likewise. */
typedef struct sk_rt_ctx {
  const double *f, *g, *A, *B;
  double slack;
  sk_pairs *pr;
  int64_t limit;
  int rc;
} sk_rt_ctx;

static void rt_block(void *vctx, int32_t i0, int32_t ni, int32_t j0, int32_t nj,
                     const double *D) {
  sk_rt_ctx *c = vctx;
  for (int32_t r = 0; r < ni && !c->rc; r++) {
    int32_t i = i0 + r;
    const double *row = D + (size_t)r * SK_BLOCK_COLS;
    for (int32_t q = 0; q < nj; q++) {
      int32_t j = j0 + q;
      double u = c->A[i] + c->g[j], v = c->f[i] + c->B[j];
      if (row[q] > (u > v ? u : v) + c->slack) continue;
      if (c->pr->len >= c->limit || pairs_reserve(c->pr, 1)) {
        c->rc = c->pr->len >= c->limit ? SM_ELIMIT : SM_ENOMEM;
        break;
      }
      pairs_put(c->pr, i, j, 1);
    }
  }
}

/* Entries of the new support S that the old support O lacks (both CSR, sorted rows). */
static int64_t count_new(const sk_support *S, const sk_support *O) {
  int64_t n = 0;
  for (int32_t i = 0; i < S->nx; i++) {
    int64_t q = O->rowptr[i];
    for (int64_t p = S->rowptr[i]; p < S->rowptr[i + 1]; p++) {
      while (q < O->rowptr[i + 1] && O->col[q] < S->col[p]) q++;
      n += q == O->rowptr[i + 1] || O->col[q] != S->col[p];
    }
  }
  return n;
}

/* One round: new support from the duals (plus the backbone), iterate on it. *added gets
 * the number of entries the old support lacked. */
static int retruncate(sk_solver *sv, const double *F, const double *G, int32_t d,
                      int64_t *added, sm_error *err) {
  double eps = sv->st->eps, th = sv->o->theta;
  sk_pairs pr = {0};
  sk_rt_ctx c = {sv->f, sv->g, malloc(sizeof(double) * (size_t)sv->nx),
                 malloc(sizeof(double) * (size_t)sv->ny), 1e-9 * sv->c0, &pr,
                 (int64_t)SK_RETRUNC_MAX_PER_POINT * ((int64_t)sv->nx + sv->ny), 0};
  int rc = SM_ENOMEM;
  if (c.A && c.B) {
    for (int32_t i = 0; i < sv->nx; i++) ((double *)c.A)[i] = sv->f[i] + eps * (th - sv->loga[i]);
    for (int32_t j = 0; j < sv->ny; j++) ((double *)c.B)[j] = sv->g[j] + eps * (th - sv->logb[j]);
    rc = scan_blocks(F, sv->nx, G, sv->ny, d, rt_block, &c);
    if (!rc) rc = c.rc;
  }
  if (!rc && !sv->o->no_backbone)
    rc = add_backbone(F, sv->nx, G, sv->ny, d, sv->a, sv->b, sv->team, &pr);
  free((void *)c.A), free((void *)c.B);
  if (!rc) {
    sk_support S;
    rc = build_support(&pr, F, sv->nx, G, sv->ny, d, sv->team, &S);
    if (!rc) {
      *added = count_new(&S, &sv->S);
      support_free(&sv->S);
      sv->S = S;
      rc = solver_alloc(sv);
    }
  }
  pairs_free(&pr);
  if (rc == SM_ELIMIT)
    return sm_error_set(err, rc, "sinkhorn: re-truncation at theta=%g keeps more than %lld "
                        "entries; lower theta", th, (long long)c.limit);
  if (rc) return sm_error_set(err, rc, "sinkhorn: no memory for the re-truncated support");
  return run_level(sv, eps, sv->o->max_iter * SK_LAST_LEVEL_MULT, sv->o->tol, err);
}

/* ---------------------------------------------------------------- arguments */

static int resolve_opts(const sm_sinkhorn_opts *in, sm_sinkhorn_opts *o, sm_error *err) {
  sm_sinkhorn_opts def;
  sm_sinkhorn_opts_default(&def);
  *o = in ? *in : def;
  if (o->k == 0) o->k = def.k;
  if (o->eps_start == 0) o->eps_start = def.eps_start;
  if (o->eps_end == 0) o->eps_end = def.eps_end;
  if (o->decay == 0) o->decay = def.decay;
  if (o->max_iter == 0) o->max_iter = def.max_iter;
  if (o->tol == 0) o->tol = def.tol;
  if (o->threads == 0) o->threads = def.threads;
  if (o->k < 1) return sm_error_set(err, SM_EINVAL, "sinkhorn: k=%d must be >= 1", o->k);
  if (!(o->eps_end > 0) || !(o->eps_start >= o->eps_end) || !isfinite(o->eps_start))
    return sm_error_set(err, SM_EINVAL, "sinkhorn: need 0 < eps_end <= eps_start < inf, got "
                        "eps_start=%g eps_end=%g", o->eps_start, o->eps_end);
  if (!(o->decay > 0 && o->decay < 1))
    return sm_error_set(err, SM_EINVAL, "sinkhorn: decay=%g must be in (0, 1)", o->decay);
  if (o->max_iter < 1 || o->max_iter > 100000000 / SK_LAST_LEVEL_MULT)
    return sm_error_set(err, SM_EINVAL, "sinkhorn: max_iter=%d out of range", o->max_iter);
  if (!(o->tol > 0))
    return sm_error_set(err, SM_EINVAL, "sinkhorn: tol=%g must be > 0", o->tol);
  if (!(o->rho >= 0) || !isfinite(o->rho))
    return sm_error_set(err, SM_EINVAL, "sinkhorn: rho=%g must be finite and >= 0", o->rho);
  if (!(o->theta >= 0) || !isfinite(o->theta))
    return sm_error_set(err, SM_EINVAL, "sinkhorn: theta=%g must be finite and >= 0", o->theta);
  if (o->knn < SM_KNN_AUTO || o->knn > SM_KNN_BRUTE)
    return sm_error_set(err, SM_EINVAL, "sinkhorn: unknown knn method %d", o->knn);
  if (o->threads < 1)
    return sm_error_set(err, SM_EINVAL, "sinkhorn: threads=%d must be >= 1", o->threads);
  return 0;
}

static int check_points(const double *X, int32_t n, int32_t d, const char *name, sm_error *err) {
  for (int64_t t = 0; t < (int64_t)n * d; t++)
    if (!isfinite(X[t]))
      return sm_error_set(err, SM_ENONFINITE, "sinkhorn: %s[%lld][%lld] is not finite", name,
                          (long long)(t / d), (long long)(t % d));
  return 0;
}

/* Normalized copies of the masses and their logs (m NULL = uniform). */
static int make_masses(const double *m, int32_t n, const char *name, double **out,
                       double **logout, sm_error *err) {
  *out = malloc(sizeof(double) * (size_t)n);
  *logout = malloc(sizeof(double) * (size_t)n);
  if (!*out || !*logout) return sm_error_set(err, SM_ENOMEM, "sinkhorn: no memory for masses");
  double sum = 0;
  for (int32_t i = 0; i < n; i++) {
    double v = m ? m[i] : 1.0 / n;
    if (!(v > 0) || !isfinite(v))
      return sm_error_set(err, SM_EINVAL, "sinkhorn: mass %s[%d]=%g must be finite and > 0",
                          name, i, v);
    sum += v;
  }
  if (fabs(sum - 1.0) > SK_MASS_TOL)
    return sm_error_set(err, SM_EINVAL, "sinkhorn: masses %s sum to %.9g, not 1", name, sum);
  for (int32_t i = 0; i < n; i++) {
    (*out)[i] = (m ? m[i] : 1.0 / n) / sum;
    (*logout)[i] = log((*out)[i]);
  }
  return 0;
}

static int check_args(const double *F, int32_t nx, const double *G, int32_t ny, int32_t d,
                      sm_plan **plan, sm_error *err) {
  if (!plan) return sm_error_set(err, SM_EINVAL, "sinkhorn: plan out-parameter is NULL");
  if (!F || !G) return sm_error_set(err, SM_EINVAL, "sinkhorn: point set %s is NULL", F ? "G" : "F");
  if (nx < 1 || ny < 1 || d < 1)
    return sm_error_set(err, SM_EINVAL, "sinkhorn: need nx, ny, d >= 1, got %d, %d, %d", nx, ny, d);
  int rc = check_points(F, nx, d, "F", err);
  return rc ? rc : check_points(G, ny, d, "G", err);
}

/* ---------------------------------------------------------------- driver */

static int build_initial(sk_solver *sv, const double *F, const double *G, int32_t d,
                         sm_error *err) {
  sk_pairs pr = {0};
  double t0 = sm_now();
  int rc = add_knn_pairs(F, sv->nx, G, sv->ny, d, sv->o, &pr, err);
  double t1 = sm_now();
  sv->st->t_knn = t1 - t0;
  if (!rc && !sv->o->no_backbone &&
      add_backbone(F, sv->nx, G, sv->ny, d, sv->a, sv->b, sv->team, &pr))
    rc = sm_error_set(err, SM_ENOMEM, "sinkhorn: no memory for the backbone");
  if (!rc && build_support(&pr, F, sv->nx, G, sv->ny, d, sv->team, &sv->S))
    rc = sm_error_set(err, SM_ENOMEM, "sinkhorn: no memory for a support of %lld pairs",
                      (long long)pr.len);
  pairs_free(&pr);
  if (rc) return rc;
  sv->c0 = sv->S.c0 > 0 ? sv->S.c0 : 1.0; /* all K-NN costs 0: coincident points */
  sv->rho = sv->o->rho * sv->c0;
  sv->f = calloc((size_t)sv->nx, sizeof(double));
  sv->g = calloc((size_t)sv->ny, sizeof(double));
  if (!sv->f || !sv->g || solver_alloc(sv)) return sm_error_set(err, SM_ENOMEM, "sinkhorn: no memory for duals");
  sv->st->t_setup = sm_now() - t1;
  return 0;
}

/* Moves the support and the duals into a new plan and evaluates P on it. */
static int make_plan(sk_solver *sv, sm_plan **out, sm_error *err) {
  sm_plan *p = calloc(1, sizeof *p);
  double *val = malloc(sizeof(double) * (size_t)(sv->S.nnz ? sv->S.nnz : 1));
  if (!p || !val) {
    free(p), free(val);
    return sm_error_set(err, SM_ENOMEM, "sinkhorn: no memory for the plan");
  }
  double eps = sv->st->eps;
  for (int32_t i = 0; i < sv->nx; i++)
    for (int64_t q = sv->S.rowptr[i]; q < sv->S.rowptr[i + 1]; q++)
      val[q] = exp((sv->f[i] + sv->g[sv->S.col[q]] - sv->S.cost[q]) / eps);
  p->nx = sv->nx, p->ny = sv->ny, p->nnz = sv->S.nnz, p->eps = eps;
  p->rowptr = sv->S.rowptr, p->col = sv->S.col, p->val = val, p->f = sv->f, p->g = sv->g;
  sv->S.rowptr = NULL, sv->S.col = NULL, sv->f = NULL, sv->g = NULL;
  *out = p;
  return 0;
}

int sm_sinkhorn(const double *F, int32_t nx, const double *G, int32_t ny, int32_t d,
                const double *a, const double *b, const sm_sinkhorn_opts *opts,
                sm_plan **plan, sm_sinkhorn_stats *st, sm_error *err) {
  double t0 = sm_now();
  sm_sinkhorn_stats stl;
  if (!st) st = &stl;
  memset(st, 0, sizeof *st);
  sm_error_clear(err);
  if (plan) *plan = NULL;
  sm_sinkhorn_opts o;
  int rc = check_args(F, nx, G, ny, d, plan, err);
  if (!rc) rc = resolve_opts(opts, &o, err);
  if (rc) return rc;
  sk_solver sv = {0};
  sv.nx = nx, sv.ny = ny, sv.o = &o, sv.st = st;
  rc = make_masses(a, nx, "a", &sv.a, &sv.loga, err);
  if (!rc) rc = make_masses(b, ny, "b", &sv.b, &sv.logb, err);
  /* Threaded sweeps from SK_TEAM_MIN_ENTRIES support entries (about (nx + ny) k): a sweep
   * then takes a few hundred microseconds, a wake-up of the team a few. */
  if (!rc && o.threads >= 2 && ((int64_t)nx + ny) * o.k >= SK_TEAM_MIN_ENTRIES)
    sv.team = sm_team_new(o.threads);
  if (!rc) rc = build_initial(&sv, F, G, d, err);
  double t1 = sm_now();
  if (!rc) rc = anneal(&sv, err);
  for (int r = 0; !rc && o.theta > 0 && r < SK_RETRUNC_ROUNDS; r++) {
    int64_t added = 0;
    rc = retruncate(&sv, F, G, d, &added, err);
    if (!added) break; /* the support holds every entry its own duals ask for */
  }
  if (!rc) {
    st->t_iter = sm_now() - t1;
    st->c0 = sv.c0;
    st->nnz = sv.S.nnz;
    st->nnz_knn = sv.S.nnz_knn;
    rc = make_plan(&sv, plan, err);
  }
  if (!rc) rc = sm_plan_marginal_error(*plan, sv.a, sv.b, &st->err_a, &st->err_b);
  if (rc == SM_ENOMEM && err && err->code == SM_OK)
    sm_error_set(err, rc, "sinkhorn: no memory for marginals");
  solver_free(&sv);
  if (rc && plan && *plan) sm_plan_destroy(*plan), *plan = NULL;
  st->t_total = sm_now() - t0;
  return rc;
}

/* ---------------------------------------------------------------- plan helpers */

void sm_plan_destroy(sm_plan *p) {
  if (!p) return;
  free(p->rowptr), free(p->col), free(p->val), free(p->f), free(p->g);
  free(p);
}

void sm_plan_row_argmax(const sm_plan *p, int32_t *T) {
  for (int32_t i = 0; i < p->nx; i++) {
    int32_t best = -1;
    double bv = -INFINITY;
    for (int64_t q = p->rowptr[i]; q < p->rowptr[i + 1]; q++)
      if (p->val[q] > bv) bv = p->val[q], best = p->col[q];
    T[i] = best;
  }
}

int sm_plan_col_argmax(const sm_plan *p, int32_t *T_yx) {
  double *bv = malloc(sizeof(double) * (size_t)p->ny);
  if (!bv) return SM_ENOMEM;
  for (int32_t j = 0; j < p->ny; j++) T_yx[j] = -1, bv[j] = -INFINITY;
  for (int32_t i = 0; i < p->nx; i++)
    for (int64_t q = p->rowptr[i]; q < p->rowptr[i + 1]; q++)
      if (p->val[q] > bv[p->col[q]]) bv[p->col[q]] = p->val[q], T_yx[p->col[q]] = i;
  free(bv);
  return 0;
}

typedef struct sk_entry {
  double s;
  int32_t i, j;
} sk_entry;

static int entry_cmp(const void *pa, const void *pb) {
  const sk_entry *x = pa, *y = pb;
  if (x->s != y->s) return x->s > y->s ? -1 : 1;
  if (x->i != y->i) return x->i < y->i ? -1 : 1;
  return (x->j > y->j) - (x->j < y->j);
}

/* Rows still free after the greedy pass: best free column of the row, else the argmax. */
static void finish_rows(const sm_plan *p, int32_t *T, const uint8_t *used) {
  for (int32_t i = 0; i < p->nx; i++) {
    if (T[i] >= 0) continue;
    int32_t bf = -1, ba = -1;
    double vf = -INFINITY, va = -INFINITY;
    for (int64_t q = p->rowptr[i]; q < p->rowptr[i + 1]; q++) {
      if (p->val[q] > va) va = p->val[q], ba = p->col[q];
      if (!used[p->col[q]] && p->val[q] > vf) vf = p->val[q], bf = p->col[q];
    }
    T[i] = bf >= 0 ? bf : ba;
  }
}

int sm_plan_extract_bijective(const sm_plan *p, int32_t *T, sm_error *err) {
  double *rs = malloc(sizeof(double) * (size_t)(p->nx ? p->nx : 1));
  uint8_t *used = calloc((size_t)p->ny, 1);
  sk_entry *e = malloc(sizeof(sk_entry) * (size_t)(p->nnz ? p->nnz : 1));
  if (!rs || !used || !e) {
    free(rs), free(used), free(e);
    return sm_error_set(err, SM_ENOMEM, "plan: no memory to sort %lld entries", (long long)p->nnz);
  }
  int64_t n = 0;
  for (int32_t i = 0; i < p->nx; i++) {
    rs[i] = 0;
    for (int64_t q = p->rowptr[i]; q < p->rowptr[i + 1]; q++) rs[i] += p->val[q];
    for (int64_t q = p->rowptr[i]; q < p->rowptr[i + 1]; q++) {
      double s = rs[i] > 0 ? p->val[q] / rs[i] : 0.0;
      /* entries this unlikely never win a free pair that a later pass would miss */
      if (s >= SK_BIJ_MIN_SCORE) e[n++] = (sk_entry){s, i, p->col[q]};
    }
    T[i] = -1;
  }
  qsort(e, (size_t)n, sizeof *e, entry_cmp);
  for (int64_t t = 0; t < n; t++)
    if (T[e[t].i] < 0 && !used[e[t].j]) T[e[t].i] = e[t].j, used[e[t].j] = 1;
  finish_rows(p, T, used);
  free(rs), free(used), free(e);
  return 0;
}

double sm_plan_map_distinct(const int32_t *T, int32_t nx, int32_t ny) {
  uint8_t *hit = calloc((size_t)(ny > 0 ? ny : 1), 1);
  if (!hit || nx < 1 || ny < 1) {
    free(hit);
    return NAN;
  }
  int32_t distinct = 0;
  for (int32_t i = 0; i < nx; i++)
    if (T[i] >= 0 && T[i] < ny && !hit[T[i]]) hit[T[i]] = 1, distinct++;
  free(hit);
  return (double)distinct / (double)(nx < ny ? nx : ny);
}

int sm_plan_marginal_error(const sm_plan *p, const double *a, const double *b,
                           double *err_a, double *err_b) {
  double *cs = calloc((size_t)p->ny, sizeof(double));
  if (!cs) return SM_ENOMEM;
  double ea = 0, eb = 0;
  for (int32_t i = 0; i < p->nx; i++) {
    double r = 0;
    for (int64_t q = p->rowptr[i]; q < p->rowptr[i + 1]; q++) r += p->val[q], cs[p->col[q]] += p->val[q];
    ea += fabs(r - (a ? a[i] : 1.0 / p->nx));
  }
  for (int32_t j = 0; j < p->ny; j++) eb += fabs(cs[j] - (b ? b[j] : 1.0 / p->ny));
  free(cs);
  if (err_a) *err_a = ea;
  if (err_b) *err_b = eb;
  return 0;
}
