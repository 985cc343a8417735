/* sm_fmap: functional maps in (non-)orthogonal bases and ZoomOut. See sm_fmap.h.
 *
 * DESIGN
 *   Whitening. With u_i = L^-1 Phi[i,:]^T (a triangular solve per shape), the basis becomes
 *   L2-orthonormal: U M U^T = L^-1 A L^-T = I. Because L is lower triangular, the first k
 *   entries of u_i equal L_k^-1 Phi[i,:k]^T, so the coordinates are computed once at the
 *   largest k and truncated for every smaller k. In them
 *     C = A^-1 Phi^T M Psi[T]  <=>  Cw = L_A^T C L_B^-T = U_X M U_Y[T]^T,
 *     b_j = L_A^T C B^-1 Psi_j = L_A^T C L_B^-T L_B^-1 Psi_j = Cw u^Y_j,
 *   so each ZoomOut iteration is two GEMMs (fit, embedding) and a kNN query, whatever the
 *   basis. The public one-shot P -> C follows the spec literally (Cholesky solve with the
 *   leading block of gram_L); the tests check both forms agree.
 *   Sampled fit. On a farthest-point sample S with cell masses w_s, the least squares
 *   min sum_s w_s |Phi_s C - Psi_T(s)|^2 becomes Cw = G_s^-1 U_S^T W U_Y[T_S]^T with
 *   G_s = U_S^T W U_S, factored once at the largest k (leading blocks again).
 */
#include "sm_fmap.h"

#include <cblas.h>
#include <lapacke.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "sm_eigs.h" /* sm_now */
#include "sm_par.h"

/* ---- checks ------------------------------------------------------------------------- */

static int check_pair(const sm_basis *x, const sm_basis *y, int k, sm_error *err) {
  if (!x || !y || !x->phi || !y->phi || !x->mass)
    return sm_error_set(err, SM_EINVAL, "fmap: missing basis");
  if (k < 1 || k > x->k || k > y->k)
    return sm_error_set(err, SM_EINVAL, "fmap: k=%d outside [1, min(%d, %d)]", k, x->k, y->k);
  return 0;
}

static int check_map(const int32_t *T, int32_t n, int32_t ny, sm_error *err) {
  if (!T) return sm_error_set(err, SM_EINVAL, "fmap: missing point map");
  for (int32_t i = 0; i < n; i++)
    if (T[i] < 0 || T[i] >= ny)
      return sm_error_set(err, SM_ERANGE, "fmap: T[%d]=%d outside the %d target vertices", i,
                          T[i], ny);
  return 0;
}

/* All pairs must describe the same X and the same Y. */
static int check_pairs(const sm_fmap_pair *pairs, int np, sm_error *err) {
  if (!pairs || np < 1 || np > SM_FMAP_MAX_PAIRS)
    return sm_error_set(err, SM_EINVAL, "fmap: %d basis pairs (1 to %d)", np, SM_FMAP_MAX_PAIRS);
  for (int p = 0; p < np; p++) {
    int rc = check_pair(pairs[p].x, pairs[p].y, pairs[p].k, err);
    if (rc) return rc;
    if (pairs[p].weight < 0 || !isfinite(pairs[p].weight))
      return sm_error_set(err, SM_EINVAL, "fmap: pair %d weight %g", p, pairs[p].weight);
    const sm_basis *x0 = pairs[0].x, *y0 = pairs[0].y, *x = pairs[p].x, *y = pairs[p].y;
    if (x->n != x0->n || x->mesh_hash != x0->mesh_hash || y->n != y0->n ||
        y->mesh_hash != y0->mesh_hash)
      return sm_error_set(err, SM_EINVAL, "fmap: pair %d is not on the meshes of pair 0", p);
  }
  return 0;
}

static double pair_weight(const sm_fmap_pair *p) { return p->weight > 0 ? p->weight : 1.0; }

/* ---- whitened coordinates and map conversions --------------------------------------- */

/* Rows r < nr of U (row-major, stride ld >= k): u = L_k^-1 Phi[v,:k]^T for v = rows[r]
 * (rows NULL: v = r), scaled by s. */
static void whiten(const sm_basis *b, int k, const int32_t *rows, int32_t nr, double s,
                   double *U, int ld) {
  for (int32_t r = 0; r < nr; r++) {
    int32_t v = rows ? rows[r] : r;
    for (int c = 0; c < k; c++) U[(size_t)r * ld + c] = s * b->phi[(size_t)c * b->n + v];
  }
  /* Row-major nr x ld is column-major ld x nr: the k leading entries of each column. */
  if (b->gram_L)
    cblas_dtrsm(CblasColMajor, CblasLeft, CblasLower, CblasNoTrans, CblasNonUnit, k, nr, 1.0,
                b->gram_L, b->k, U, ld);
}

/* Cw = L_A^T C L_B^-T (k x k column-major). */
static void to_white(const sm_basis *x, const sm_basis *y, int k, const double *C, double *Cw) {
  memcpy(Cw, C, (size_t)k * k * sizeof(double));
  if (y->gram_L)
    cblas_dtrsm(CblasColMajor, CblasRight, CblasLower, CblasTrans, CblasNonUnit, k, k, 1.0,
                y->gram_L, y->k, Cw, k);
  if (x->gram_L)
    cblas_dtrmm(CblasColMajor, CblasLeft, CblasLower, CblasTrans, CblasNonUnit, k, k, 1.0,
                x->gram_L, x->k, Cw, k);
}

/* C = L_A^-T Cw L_B^T. */
static void from_white(const sm_basis *x, const sm_basis *y, int k, const double *Cw, double *C) {
  memcpy(C, Cw, (size_t)k * k * sizeof(double));
  if (x->gram_L)
    cblas_dtrsm(CblasColMajor, CblasLeft, CblasLower, CblasTrans, CblasNonUnit, k, k, 1.0,
                x->gram_L, x->k, C, k);
  if (y->gram_L)
    cblas_dtrmm(CblasColMajor, CblasRight, CblasLower, CblasTrans, CblasNonUnit, k, k, 1.0,
                y->gram_L, y->k, C, k);
}

/* E[r, :k] = s * Cw U[r, :k] for nr rows (row-major; Cw column-major read as Cw^T). */
static void apply_map(const double *U, int ldu, int32_t nr, int k, const double *Cw, double s,
                      double *E, int lde) {
  cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, nr, k, k, s, U, ldu, Cw, k, 0.0, E,
              lde);
}

/* T[i] = cand[nearest row of EY to row i of EX] (cand NULL: identity). */
static int assign(const double *EY, int32_t ny, const double *EX, int32_t nx, int D,
                  const int32_t *cand, const sm_knn_opts *ko, int32_t *T, sm_error *err) {
  sm_knn *ix = NULL;
  int rc = sm_knn_build(EY, ny, D, ko, &ix, err);
  if (rc) return rc;
  rc = sm_knn_query(ix, EX, nx, 1, T, NULL, err);
  sm_knn_destroy(ix);
  if (rc || !cand) return rc;
  for (int32_t i = 0; i < nx; i++) T[i] = cand[T[i]];
  return 0;
}

/* T[i] = nearest row of EY to row i of EX and T_yx[j] = nearest row of EX to row j of EY:
 * what two assign calls give, from one pass (sm_knn_query_both). */
static int assign_both(const double *EY, int32_t ny, const double *EX, int32_t nx, int D,
                       const sm_knn_opts *ko, int32_t *T, int32_t *T_yx, sm_error *err) {
  sm_knn *ix = NULL;
  int rc = sm_knn_build(EY, ny, D, ko, &ix, err);
  if (!rc) rc = sm_knn_query_both(ix, EX, nx, 1, T, NULL, T_yx, NULL, err);
  sm_knn_destroy(ix);
  return rc;
}

/* The same for candidates given as y_j = L u_j (sm_knn_build_factored), with their rows
 * EY = U L^T: the bijective embeddings, whose GEMM then runs on half the dimensions. */
static int assign_both_factored(const double *U, int32_t ny, int dr, const double *L,
                                const double *EY, int D, const double *EX, int32_t nx,
                                const sm_knn_opts *ko, int32_t *T, int32_t *T_yx,
                                sm_error *err) {
  sm_knn *ix = NULL;
  int rc = sm_knn_build_factored(U, ny, dr, L, D, EY, ko, &ix, err);
  if (!rc) rc = sm_knn_query_both(ix, EX, nx, 1, T, NULL, T_yx, NULL, err);
  sm_knn_destroy(ix);
  return rc;
}

/* ---- one-shot P -> C, C -> P, embeddings --------------------------------------------- */

int sm_fmap_from_p2p(const sm_basis *x, const sm_basis *y, int k, const int32_t *T, double *C,
                     sm_error *err) {
  int rc = check_pair(x, y, k, err);
  if (!rc) rc = check_map(T, x->n, y->n, err);
  if (rc) return rc;
  if (!C) return sm_error_set(err, SM_EINVAL, "fmap: missing output C");
  int32_t n = x->n;
  double *Z = malloc((size_t)n * k * sizeof(double));
  if (!Z) return sm_error_set(err, SM_ENOMEM, "fmap: %d x %d pulled-back functions", n, k);
  for (int c = 0; c < k; c++)
    for (int32_t i = 0; i < n; i++)
      Z[(size_t)c * n + i] = x->mass[i] * y->phi[(size_t)c * y->n + T[i]];
  cblas_dgemm(CblasColMajor, CblasTrans, CblasNoTrans, k, k, n, 1.0, x->phi, n, Z, n, 0.0, C, k);
  free(Z);
  if (x->gram_L) {
    /* A_k = L_k L_k^T: the leading block of the stored factor, never an inverse. */
    int info = LAPACKE_dpotrs(LAPACK_COL_MAJOR, 'L', k, k, x->gram_L, x->k, C, k);
    if (info) return sm_error_set(err, SM_ENUMERIC, "fmap: dpotrs failed (info %d)", info);
  }
  return 0;
}

int sm_fmap_embed_x(const sm_basis *x, int k, double *E_x, int ld, sm_error *err) {
  if (!x || !x->phi || k < 1 || k > x->k || !E_x || ld < k)
    return sm_error_set(err, SM_EINVAL, "fmap: bad X embedding arguments (k=%d, ld=%d)", k, ld);
  whiten(x, k, NULL, x->n, 1.0, E_x, ld);
  return 0;
}

/* E_y rows = s * Cw u^Y_j: the Y half of the embedding of one pair. */
static int embed_y_scaled(const sm_basis *x, const sm_basis *y, int k, const double *C,
                          double s, double *E_y, int ld, sm_error *err) {
  double *U = malloc((size_t)y->n * k * sizeof(double));
  double *Cw = malloc((size_t)k * k * sizeof(double));
  if (!U || !Cw) {
    free(U);
    free(Cw);
    return sm_error_set(err, SM_ENOMEM, "fmap: Y embedding (%d x %d)", y->n, k);
  }
  whiten(y, k, NULL, y->n, 1.0, U, k);
  to_white(x, y, k, C, Cw);
  apply_map(U, k, y->n, k, Cw, s, E_y, ld);
  free(U);
  free(Cw);
  return 0;
}

int sm_fmap_embed_y(const sm_basis *x, const sm_basis *y, int k, const double *C, double *E_y,
                    int ld, sm_error *err) {
  int rc = check_pair(x, y, k, err);
  if (rc) return rc;
  if (!C || !E_y || ld < k)
    return sm_error_set(err, SM_EINVAL, "fmap: bad Y embedding arguments (ld=%d)", ld);
  return embed_y_scaled(x, y, k, C, 1.0, E_y, ld, err);
}

/* C -> P on the X rows `rows` (NULL: all nq = n_X of them, T[i]; otherwise T[rows[r]]),
 * T_yx (only with every row) from the same pass. */
static int to_p2p(const sm_fmap_pair *pairs, int npairs, const double *const *C,
                  const int32_t *rows, int32_t nq, int32_t *T, int32_t *T_yx,
                  const sm_knn_opts *ko, sm_error *err) {
  if (!C || !T) return sm_error_set(err, SM_EINVAL, "fmap: missing C or T");
  int D = 0, rc = 0;
  for (int p = 0; p < npairs; p++) {
    if (!C[p]) return sm_error_set(err, SM_EINVAL, "fmap: missing C for pair %d", p);
    D += pairs[p].k;
  }
  int32_t ny = pairs[0].y->n;
  double *EX = malloc((size_t)nq * D * sizeof(double));
  double *EY = malloc((size_t)ny * D * sizeof(double));
  int32_t *Tq = rows ? malloc((size_t)nq * sizeof(int32_t)) : T;
  if (!EX || !EY || !Tq) {
    rc = sm_error_set(err, SM_ENOMEM, "fmap: embeddings of dimension %d", D);
    goto done;
  }
  for (int p = 0, off = 0; p < npairs && !rc; off += pairs[p].k, p++) {
    double s = pair_weight(&pairs[p]);
    whiten(pairs[p].x, pairs[p].k, rows, nq, s, EX + off, D);
    rc = embed_y_scaled(pairs[p].x, pairs[p].y, pairs[p].k, C[p], s, EY + off, D, err);
  }
  if (!rc && T_yx) rc = assign_both(EY, ny, EX, nq, D, ko, Tq, T_yx, err);
  else if (!rc) rc = assign(EY, ny, EX, nq, D, NULL, ko, Tq, err);
  for (int32_t r = 0; !rc && rows && r < nq; r++) T[rows[r]] = Tq[r];
done:
  if (rows) free(Tq);
  free(EX);
  free(EY);
  return rc;
}

int sm_fmap_to_p2p(const sm_fmap_pair *pairs, int npairs, const double *const *C, int32_t *T,
                   int32_t *T_yx, const sm_knn_opts *ko, sm_error *err) {
  int rc = check_pairs(pairs, npairs, err);
  if (rc) return rc;
  return to_p2p(pairs, npairs, C, NULL, pairs[0].x->n, T, T_yx, ko, err);
}

int sm_fmap_to_p2p_rows(const sm_fmap_pair *pairs, int npairs, const double *const *C,
                        const int32_t *rows, int32_t nrows, int32_t *T, const sm_knn_opts *ko,
                        sm_error *err) {
  int rc = check_pairs(pairs, npairs, err);
  if (rc) return rc;
  if (!rows || nrows < 1) return sm_error_set(err, SM_EINVAL, "fmap: no query rows");
  rc = check_map(rows, nrows, pairs[0].x->n, err);
  if (rc) return rc;
  return to_p2p(pairs, npairs, C, rows, nrows, T, NULL, ko, err);
}

/* ---- farthest-point sampling -------------------------------------------------------- */

static double sqdist(const double *a, const double *b, int dim) {
  double s = 0;
  for (int t = 0; t < dim; t++) s += (a[t] - b[t]) * (a[t] - b[t]);
  return s;
}

static int32_t argmax(const double *a, int32_t n) {
  int32_t best = 0;
  for (int32_t i = 1; i < n; i++)
    if (a[i] > a[best]) best = i;
  return best;
}

/* The argmax of the distance to the samples so far is tracked in the update pass (first
 * index among equals, like a separate scan): one pass over the points per sample. */
static int fps(const double *P, int32_t n, int dim, int ldp, const double *mass, int32_t ns,
               int32_t *S, double *cellw, sm_error *err) {
  double *md = malloc((size_t)n * sizeof(double));
  int32_t *owner = malloc((size_t)n * sizeof(int32_t));
  if (!md || !owner) {
    free(md);
    free(owner);
    return sm_error_set(err, SM_ENOMEM, "fmap: farthest-point sampling of %d points", n);
  }
  for (int32_t i = 0; i < n; i++) md[i] = sqdist(P + (size_t)i * ldp, P, dim);
  S[0] = argmax(md, n);
  for (int32_t s = 0; s < ns; s++) {
    const double *c = P + (size_t)S[s] * ldp;
    double best = -1;
    int32_t bi = 0;
    for (int32_t i = 0; i < n; i++) {
      double d = sqdist(P + (size_t)i * ldp, c, dim);
      if (s == 0 || d < md[i]) {
        md[i] = d;
        owner[i] = s;
      }
      if (md[i] > best) {
        best = md[i];
        bi = i;
      }
    }
    if (s + 1 < ns) S[s + 1] = bi;
  }
  for (int32_t s = 0; s < ns; s++) cellw[s] = 0;
  for (int32_t i = 0; i < n; i++) cellw[owner[i]] += mass[i];
  free(md);
  free(owner);
  return 0;
}

int sm_fmap_fps(const double *P, int32_t n, int dim, int ldp, const double *mass, int32_t ns,
                int32_t *S, double *cellw, sm_error *err) {
  if (!P || !mass || !S || !cellw || n < 1 || dim < 1 || ldp < dim || ns < 1 || ns > n)
    return sm_error_set(err, SM_EINVAL, "fmap: bad sampling arguments (n=%d, ns=%d)", n, ns);
  return fps(P, n, dim, ldp, mass, ns, S, cellw, err);
}

/* ---- ZoomOut -------------------------------------------------------------------------- */

void sm_zoomout_opts_default(sm_zoomout_opts *o) {
  memset(o, 0, sizeof *o);
  o->step = 1;
  o->nsample_x = 2000;
  o->nsample_y = 0;
  sm_knn_opts_default(&o->knn);
}

typedef struct zpair {
  const sm_basis *x, *y;
  int K, k0, k;  /* final, first and current k */
  double w;
  double *UX;    /* n_X x K whitened X coordinates */
  double *UY;    /* n_Y x K whitened Y coordinates */
  double *UYc;   /* candidate rows of UY (the Y samples), or NULL = UY */
  double *UF;    /* fit rows x K: sqrt(cell mass) u^X */
  double *GF;    /* K x K Cholesky factor of UF^T UF, NULL when the fit set is all of X */
  double *Cw;    /* K x K current whitened map */
  /* Bijective only: the same for the Y -> X map (fit rows on Y, Dw: X -> Y coefficients). */
  double *UFy, *GFy, *Dw;
} zpair;

typedef struct zctx {
  const sm_zoomout_opts *o;
  int np, Dmax, niter;
  int full_y_last;     /* final iterations with every Y vertex as candidate */
  zpair p[SM_FMAP_MAX_PAIRS];
  int32_t nx, ny;
  int32_t nfit, ncand; /* fit set (X samples or all X); Y candidates of intermediate steps */
  int32_t *fit;        /* X samples, or NULL = all */
  int32_t *cand;       /* Y samples, or NULL = all */
  double *sqw;         /* nfit: sqrt of the fit weights */
  int32_t *Tfit;       /* current map on the fit set, global Y indices */
  int32_t *T_yx;       /* wanted Y -> X map (filled with the last iteration), or NULL */
  /* Bijective only: the Y fit set (the Y samples, or all of Y) and the Y -> X map on it. */
  int32_t nfit_y;
  double *sqw_y;
  int32_t *Sfit;       /* global X indices; valid once have_s */
  int32_t *Sq;         /* Y -> query-row map of the last assignment (ncand or n_Y) */
  int have_s;
  double *EX, *EY;
  double *Z[2 * SM_FMAP_MAX_PAIRS]; /* fit scratch per fit job (one when on one thread) */
  int nz, threads;
  double *LY;          /* bijective: D x D/2 map of the factored candidates (EY then holds
                        * their D/2 coordinates: y = LY u, see zembed) */
  double *EYf;         /* bijective: the candidates' full D-wide rows LY u (zfactor) */
  sm_zoomout_stats st;
} zctx;

static void zctx_free(zctx *z) {
  for (int p = 0; p < z->np; p++) {
    zpair *q = &z->p[p];
    free(q->UX);
    free(q->UY);
    free(q->UYc);
    free(q->UF);
    free(q->GF);
    free(q->Cw);
    free(q->UFy);
    free(q->GFy);
    free(q->Dw);
  }
  free(z->sqw_y);
  free(z->Sfit);
  free(z->Sq);
  free(z->fit);
  free(z->cand);
  free(z->sqw);
  free(z->Tfit);
  free(z->EX);
  free(z->EY);
  free(z->LY);
  free(z->EYf);
  for (int i = 0; i < z->nz; i++) free(z->Z[i]);
}

static int check_zoomout(const sm_fmap_pair *pairs, int np, const sm_zoomout_opts *o,
                         const int32_t *T0, int32_t *T, sm_error *err) {
  int rc = check_pairs(pairs, np, err);
  if (rc) return rc;
  if (!o || o->step < 1 || o->nsample_x < 0 || o->nsample_y < 0 || o->full_y_last < 0 || !T)
    return sm_error_set(err, SM_EINVAL, "zoomout: bad options (step %d, samples %d/%d)",
                        o ? o->step : 0, o ? o->nsample_x : 0, o ? o->nsample_y : 0);
  for (int p = 0; p < np; p++)
    if (pairs[p].k0 < 1 || pairs[p].k0 > pairs[p].k)
      return sm_error_set(err, SM_EINVAL, "zoomout: pair %d k0=%d outside [1, k=%d]", p,
                          pairs[p].k0, pairs[p].k);
  int32_t nx = pairs[0].x->n, ny = pairs[0].y->n;
  if (o->samples_x && o->nsample_x < nx && (!o->cellw_x || check_map(o->samples_x, o->nsample_x, nx, err)))
    return sm_error_set(err, SM_EINVAL, "zoomout: bad X samples");
  if (o->samples_y && o->nsample_y < ny &&
      (check_map(o->samples_y, o->nsample_y, ny, err) || (o->bijective > 0 && !o->cellw_y)))
    return sm_error_set(err, SM_EINVAL, "zoomout: bad Y samples");
  if (!(o->bijective >= 0) || !isfinite(o->bijective))
    return sm_error_set(err, SM_EINVAL, "zoomout: bijective weight %g", o->bijective);
  if (o->nfeat < 0 || (o->nfeat > 0 && (!o->feat_x || !o->feat_y || o->bijective > 0)))
    return sm_error_set(err, SM_EINVAL, "zoomout: %d fixed features (need both sides, and "
                        "not with the bijective variant)", o->nfeat);
  return check_map(T0, pairs[0].x->n, pairs[0].y->n, err);
}

/* k of pair p at iteration t. */
static int k_at(const zctx *z, int p, int t) {
  const zpair *q = &z->p[p];
  if (p == 0) {
    long k = q->k0 + (long)t * z->o->step;
    return k < q->K ? (int)k : q->K;
  }
  if (z->niter == 1) return q->K;
  return q->k0 + (int)lround((double)(q->K - q->k0) * t / (z->niter - 1));
}

static int zalloc_pair(zctx *z, zpair *q, const sm_fmap_pair *in, sm_error *err) {
  q->x = in->x;
  q->y = in->y;
  q->K = in->k;
  q->k0 = in->k0;
  q->w = pair_weight(in);
  q->UX = malloc((size_t)z->nx * q->K * sizeof(double));
  q->UY = malloc((size_t)z->ny * q->K * sizeof(double));
  q->Cw = malloc((size_t)q->K * q->K * sizeof(double));
  if (!q->UX || !q->UY || !q->Cw)
    return sm_error_set(err, SM_ENOMEM, "zoomout: whitened coordinates (k=%d)", q->K);
  return 0;
}

/* Whitening job i (sm_par_for): pair i / 2's X (i even) or Y (i odd) coordinates. */
static void zwhiten_job(void *ctx, int i) {
  zctx *z = ctx;
  zpair *q = &z->p[i / 2];
  if (i % 2 == 0) whiten(q->x, q->K, NULL, z->nx, 1.0, q->UX, q->K);
  else whiten(q->y, q->K, NULL, z->ny, 1.0, q->UY, q->K);
}

/* Chooses the X fit set and the Y candidates (farthest-point samples or everything). */
static int zsample(zctx *z, sm_error *err) {
  const sm_zoomout_opts *o = z->o;
  const zpair *q = &z->p[0];
  int32_t nsx = o->nsample_x > 0 && o->nsample_x < z->nx ? o->nsample_x : z->nx;
  int32_t nsy = o->nsample_y > 0 && o->nsample_y < z->ny ? o->nsample_y : z->ny;
  z->nfit = nsx;
  z->ncand = nsy;
  z->sqw = malloc((size_t)nsx * sizeof(double));
  if (!z->sqw) return sm_error_set(err, SM_ENOMEM, "zoomout: %d weights", nsx);
  int rc = 0;
  if (nsx < z->nx) {
    z->fit = malloc((size_t)nsx * sizeof(int32_t));
    if (!z->fit) return sm_error_set(err, SM_ENOMEM, "zoomout: %d samples", nsx);
    if (o->samples_x && o->cellw_x) {
      memcpy(z->fit, o->samples_x, (size_t)nsx * sizeof(int32_t));
      memcpy(z->sqw, o->cellw_x, (size_t)nsx * sizeof(double));
    } else {
      rc = o->pos_x ? fps(o->pos_x, z->nx, 3, 3, q->x->mass, nsx, z->fit, z->sqw, err)
                    : fps(q->UX, z->nx, q->k0, q->K, q->x->mass, nsx, z->fit, z->sqw, err);
    }
  } else {
    memcpy(z->sqw, q->x->mass, (size_t)nsx * sizeof(double));
  }
  for (int32_t s = 0; s < nsx; s++) z->sqw[s] = sqrt(z->sqw[s]);
  if (rc) return rc;
  double *cw = malloc((size_t)nsy * sizeof(double));
  if (!cw) return sm_error_set(err, SM_ENOMEM, "zoomout: %d Y samples", nsy);
  if (nsy == z->ny) {
    memcpy(cw, q->y->mass, (size_t)nsy * sizeof(double));
  } else if (!(z->cand = malloc((size_t)nsy * sizeof(int32_t)))) {
    rc = sm_error_set(err, SM_ENOMEM, "zoomout: %d Y samples", nsy);
  } else if (o->samples_y) {
    memcpy(z->cand, o->samples_y, (size_t)nsy * sizeof(int32_t));
    if (o->cellw_y) memcpy(cw, o->cellw_y, (size_t)nsy * sizeof(double));
  } else {
    rc = o->pos_y ? fps(o->pos_y, z->ny, 3, 3, q->y->mass, nsy, z->cand, cw, err)
                  : fps(q->UY, z->ny, q->k0, q->K, q->y->mass, nsy, z->cand, cw, err);
  }
  if (rc || o->bijective <= 0) {
    free(cw);
    return rc;
  }
  /* The Y -> X fit of the bijective variant runs on the Y samples, weighted like X's. */
  for (int32_t s = 0; s < nsy; s++) cw[s] = sqrt(cw[s]);
  z->sqw_y = cw;
  z->nfit_y = nsy;
  return 0;
}

/* The weighted fit rows UF[s] = sqw[s] U[rows[s]] (rows NULL: s) of one side and, when
 * the fit set is a sample (rows != NULL), the Cholesky factor *GF of their Gram. */
static int zfit_rows(const double *U, int K, const int32_t *rows, int32_t nfit,
                     const double *sqw, double **UF, double **GF, sm_error *err) {
  *UF = malloc((size_t)nfit * K * sizeof(double));
  if (!*UF) return sm_error_set(err, SM_ENOMEM, "zoomout: fit rows");
  for (int32_t s = 0; s < nfit; s++) {
    int32_t v = rows ? rows[s] : s;
    for (int c = 0; c < K; c++) (*UF)[(size_t)s * K + c] = sqw[s] * U[(size_t)v * K + c];
  }
  if (!rows) return 0; /* U M U^T = I on the whole shape */
  *GF = malloc((size_t)K * K * sizeof(double));
  if (!*GF) return sm_error_set(err, SM_ENOMEM, "zoomout: sample Gram");
  /* UF row-major nfit x K is column-major K x nfit: G = UF_col UF_col^T. */
  cblas_dsyrk(CblasColMajor, CblasLower, CblasNoTrans, K, nfit, 1.0, *UF, K, 0.0, *GF, K);
  int info = LAPACKE_dpotrf(LAPACK_COL_MAJOR, 'L', K, *GF, K);
  if (info)
    return sm_error_set(err, SM_ENUMERIC,
                        "zoomout: Gram of %d samples not positive definite at k=%d (column %d); "
                        "use more samples",
                        nfit, K, info);
  return 0;
}

/* Per pair: the weighted fit rows and their Gram factor of X (side 0), and of Y when
 * bijective with the candidate rows of Y (side 1). */
static int zfit_setup(zctx *z, zpair *q, int side, sm_error *err) {
  int K = q->K, rc = 0;
  if (side == 0) return zfit_rows(q->UX, K, z->fit, z->nfit, z->sqw, &q->UF, &q->GF, err);
  if (z->sqw_y) rc = zfit_rows(q->UY, K, z->cand, z->nfit_y, z->sqw_y, &q->UFy, &q->GFy, err);
  if (!rc && z->sqw_y && !(q->Dw = malloc((size_t)K * K * sizeof(double))))
    rc = sm_error_set(err, SM_ENOMEM, "zoomout: Y -> X map");
  if (rc || !z->cand) return rc;
  q->UYc = malloc((size_t)z->ncand * K * sizeof(double));
  if (!q->UYc) return sm_error_set(err, SM_ENOMEM, "zoomout: candidate rows");
  for (int32_t s = 0; s < z->ncand; s++)
    memcpy(q->UYc + (size_t)s * K, q->UY + (size_t)z->cand[s] * K, K * sizeof(double));
  return 0;
}

/* Setup job i (sm_par_for): pair i / 2, side i % 2 (zfit_setup); each its own error. */
typedef struct zsetup_jobs {
  zctx *z;
  int rc[2 * SM_FMAP_MAX_PAIRS];
  sm_error err[2 * SM_FMAP_MAX_PAIRS];
} zsetup_jobs;

static void zfit_setup_job(void *ctx, int i) {
  zsetup_jobs *j = ctx;
  j->rc[i] = zfit_setup(j->z, &j->z->p[i / 2], i % 2, &j->err[i]);
}

static int zsetup(zctx *z, const sm_fmap_pair *pairs, const int32_t *T0, sm_error *err) {
  double t0 = sm_now();
  int rc = 0;
  z->threads = z->o->threads > 1 ? z->o->threads : 1;
  for (int p = 0; p < z->np && !rc; p++) rc = zalloc_pair(z, &z->p[p], &pairs[p], err);
  if (!rc) sm_par_for(2 * z->np, z->threads, zwhiten_job, z);
  if (!rc) rc = zsample(z, err);
  if (rc) return rc;
  zsetup_jobs sj = {.z = z};
  sm_par_for(2 * z->np, z->threads, zfit_setup_job, &sj);
  for (int i = 0; i < 2 * z->np; i++)
    if (sj.rc[i]) {
      if (err) *err = sj.err[i];
      return sj.rc[i];
    }
  int Kmax = 0;
  z->Dmax = 0;
  for (int p = 0; p < z->np; p++) {
    z->Dmax += z->sqw_y ? 2 * z->p[p].K : z->p[p].K;
    if (z->p[p].K > Kmax) Kmax = z->p[p].K;
  }
  z->Dmax += z->o->nfeat;
  int32_t zrows = z->nfit > z->nfit_y ? z->nfit : z->nfit_y;
  z->Tfit = malloc((size_t)z->nfit * sizeof(int32_t));
  z->EX = malloc((size_t)z->nx * z->Dmax * sizeof(double));
  z->EY = malloc((size_t)z->ny * z->Dmax * sizeof(double));
  z->nz = z->threads > 1 ? (z->sqw_y ? 2 : 1) * z->np : 1;
  int zok = 1;
  for (int i = 0; i < z->nz; i++) zok &= (z->Z[i] = malloc((size_t)zrows * Kmax * sizeof(double))) != NULL;
  if (z->sqw_y) {
    z->Sfit = malloc((size_t)z->nfit_y * sizeof(int32_t));
    z->Sq = malloc((size_t)z->ny * sizeof(int32_t));
    z->LY = malloc((size_t)z->Dmax * (z->Dmax / 2) * sizeof(double));
    z->EYf = malloc((size_t)z->ny * z->Dmax * sizeof(double));
  }
  if (!z->Tfit || !z->EX || !z->EY || !zok ||
      (z->sqw_y && (!z->Sfit || !z->Sq || !z->LY || !z->EYf)))
    return sm_error_set(err, SM_ENOMEM, "zoomout: embeddings (%d + %d rows x %d)", z->nx, z->ny,
                        z->Dmax);
  for (int32_t s = 0; s < z->nfit; s++) z->Tfit[s] = T0[z->fit ? z->fit[s] : s];
  z->st.t_setup = sm_now() - t0;
  return 0;
}

/* P -> C in whitened coordinates on a fit set: W = G^-1 UF^T (sqrt(w) U_to[map]), k x k
 * column-major, carrying coefficients of the map's target side to the fit side's. */
/* Z: nfit x k scratch. Returns 0 or the failing dpotrs' info. */
static int zlsq(double *Z, int k, int K, int32_t nfit, const double *UF, const double *GF,
                const double *sqw, const double *U_to, const int32_t *map, double *W) {
  for (int32_t s = 0; s < nfit; s++) {
    const double *u = U_to + (size_t)map[s] * K;
    for (int c = 0; c < k; c++) Z[(size_t)s * k + c] = sqw[s] * u[c];
  }
  cblas_dgemm(CblasColMajor, CblasNoTrans, CblasTrans, k, k, nfit, 1.0, UF, K, Z, k, 0.0, W, k);
  return GF ? LAPACKE_dpotrs(LAPACK_COL_MAJOR, 'L', k, k, GF, K, W, k) : 0;
}

/* Fit job i of an iteration (sm_par_for). Bijective: pair i / 2, Cw from the X -> Y map on
 * the X fit set (i even) or Dw from the Y -> X map on the Y fit set (i odd); otherwise Cw
 * of pair i. */
typedef struct zfit_jobs {
  zctx *z;
  int info[2 * SM_FMAP_MAX_PAIRS];
} zfit_jobs;

static void zfit_job(void *ctx, int i) {
  zfit_jobs *j = ctx;
  zctx *z = j->z;
  zpair *q = &z->p[z->have_s ? i / 2 : i];
  double *Z = z->Z[z->nz > 1 ? i : 0];
  j->info[i] = !z->have_s || i % 2 == 0
                   ? zlsq(Z, q->k, q->K, z->nfit, q->UF, q->GF, z->sqw, q->UY, z->Tfit, q->Cw)
                   : zlsq(Z, q->k, q->K, z->nfit_y, q->UFy, q->GFy, z->sqw_y, q->UX, z->Sfit,
                          q->Dw);
}

/* Every pair's fit(s) at its current k, on z->threads threads: the pairs' two directions
 * and the pairs themselves are independent least-squares problems. */
static int zfmap_all(zctx *z, sm_error *err) {
  zfit_jobs j = {.z = z};
  int n = z->have_s ? 2 * z->np : z->np;
  sm_par_for(n, z->threads, zfit_job, &j);
  for (int i = 0; i < n; i++)
    if (j.info[i])
      return sm_error_set(err, SM_ENUMERIC, "zoomout: dpotrs failed (info %d)", j.info[i]);
  return 0;
}

/* The bijective candidates [w Cw u, w wb u] per pair as y = LY u (LY: D x D/2, row-major,
 * block p at rows off.., columns roff..; u: the pairs' coordinates side by side in EY,
 * D/2 wide), so that the assignment's GEMM runs on D/2 dimensions; and the rows y
 * themselves in EYf (for the exact distances), formed block by block: the generic U LY^T
 * would multiply every u by the zeros of LY as well. */
static void zfactor(const zctx *z, const zpair *q, const double *UY, int32_t nc, int D, int off,
                    int roff) {
  int dr = D / 2, k = q->k;
  double wb = z->o->bijective;
  for (int32_t r = 0; r < nc; r++)
    memcpy(z->EY + (size_t)r * dr + roff, UY + (size_t)r * q->K, (size_t)k * sizeof(double));
  apply_map(UY, q->K, nc, k, q->Cw, q->w, z->EYf + off, D);
  for (int32_t r = 0; r < nc; r++)
    for (int c = 0; c < k; c++)
      z->EYf[(size_t)r * D + off + k + c] = q->w * wb * UY[(size_t)r * q->K + c];
  for (int c = 0; c < k; c++) {
    double *row = z->LY + (size_t)(off + c) * dr + roff; /* (w Cw)(c, :) */
    for (int i = 0; i < k; i++) row[i] = q->w * q->Cw[(size_t)i * k + c];
    z->LY[(size_t)(off + k + c) * dr + roff + c] = q->w * wb;
  }
}

/* The fixed features in the last nfeat columns of both embeddings (never factored: they
 * exclude the bijective variant). */
static void zembed_features(zctx *z, int32_t nq, int full_q, int32_t nc, int full_c, int D) {
  int nf = z->o->nfeat, off = D - nf;
  double w = z->o->feat_w;
  for (int32_t r = 0; r < nq; r++) {
    const double *f = z->o->feat_x + (size_t)(full_q || !z->fit ? r : z->fit[r]) * nf;
    for (int c = 0; c < nf; c++) z->EX[(size_t)r * D + off + c] = w * f[c];
  }
  for (int32_t r = 0; r < nc; r++) {
    const double *f = z->o->feat_y + (size_t)(full_c || !z->cand ? r : z->cand[r]) * nf;
    for (int c = 0; c < nf; c++) z->EY[(size_t)r * D + off + c] = w * f[c];
  }
}

/* Embeds the queries (X samples, or all X when full_q) and the candidates (Y samples, or
 * all Y when full_c): a_i = u^X_i against b_j = Cw u^Y_j; once a Y -> X map exists
 * (bijective), [a_i, wb Dw a_i] against [b_j, wb u^Y_j], the candidates factored
 * (zfactor). */
typedef struct zembed_jobs {
  zctx *z;
  int full_q, full_c, D;
  int yparts; /* jobs per pair on the candidates' side */
  int off[SM_FMAP_MAX_PAIRS], roff[SM_FMAP_MAX_PAIRS]; /* pair p's columns in EX/EY, LY */
} zembed_jobs;

/* Plain candidates (b_j = Cw u_j) are one GEMM, most of an embedding's work, and a single
 * pair has no other to run beside it: their rows are cut in this many parts. */
#define ZEMBED_YPARTS 2

/* Embedding job i (sm_par_for): pair p = i / (1 + yparts)'s columns of the queries (first
 * job of the pair) or of the candidates (the others: part r of their rows); the pairs, the
 * sides and the parts write disjoint entries. */
static void zembed_job(void *ctx, int i) {
  const zembed_jobs *j = ctx;
  zctx *z = j->z;
  int pi = i / (1 + j->yparts), r = i % (1 + j->yparts) - 1;
  const zpair *q = &z->p[pi];
  int D = j->D, off = j->off[pi];
  if (r < 0) {
    int32_t nq = j->full_q || !z->fit ? z->nx : z->nfit;
    for (int32_t r = 0; r < nq; r++) {
      int32_t v = j->full_q || !z->fit ? r : z->fit[r];
      const double *u = q->UX + (size_t)v * q->K;
      double *e = z->EX + (size_t)r * D + off;
      for (int c = 0; c < q->k; c++) e[c] = q->w * u[c];
    }
    if (z->have_s)
      apply_map(z->EX + off, D, nq, q->k, q->Dw, z->o->bijective, z->EX + off + q->k, D);
    return;
  }
  int32_t nc = j->full_c || !z->cand ? z->ny : z->ncand;
  const double *UY = j->full_c || !z->cand ? q->UY : q->UYc;
  if (z->have_s) {
    zfactor(z, q, UY, nc, D, off, j->roff[pi]);
    return;
  }
  int32_t r0, r1;
  sm_par_part(nc, r, j->yparts, &r0, &r1);
  apply_map(UY + (size_t)r0 * q->K, q->K, r1 - r0, q->k, q->Cw, q->w,
            z->EY + (size_t)r0 * D + off, D);
}

static void zembed(zctx *z, int full_q, int full_c, int D) {
  zembed_jobs j = {.z = z, .full_q = full_q, .full_c = full_c, .D = D};
  for (int p = 0, off = 0, roff = 0; p < z->np; p++) {
    j.off[p] = off;
    j.roff[p] = roff;
    off += z->have_s ? 2 * z->p[p].k : z->p[p].k;
    roff += z->p[p].k;
  }
  if (z->have_s) memset(z->LY, 0, (size_t)D * (D / 2) * sizeof(double));
  j.yparts = z->have_s ? 1 : ZEMBED_YPARTS;
  sm_par_for((1 + j.yparts) * z->np, z->threads, zembed_job, &j);
  int32_t nq = full_q || !z->fit ? z->nx : z->nfit;
  int32_t nc = full_c || !z->cand ? z->ny : z->ncand;
  zembed_features(z, nq, full_q, nc, full_c, D);
}

/* Bijective: the Y -> X map on the Y fit set from the last assignment's Y -> query-row
 * map (Sq over the candidates: the Y samples, or all of Y). */
static void zkeep_yx(zctx *z, int full_q, int full_c) {
  for (int32_t s = 0; s < z->nfit_y; s++) {
    int32_t r = z->Sq[z->cand && full_c ? z->cand[s] : s];
    z->Sfit[s] = full_q || !z->fit ? r : z->fit[r];
  }
  z->have_s = 1;
}

/* One iteration: fit every pair at its k, embed, assign. The last one maps all of X to all
 * of Y; the full_y_last - 1 before it already take all of Y as candidates, so that the last
 * fit does not inherit the resolution of the Y sample. */
static int ziterate(zctx *z, int t, int32_t *T, sm_error *err) {
  int last = t == z->niter - 1, full_c = t >= z->niter - z->full_y_last, D = 0, rc = 0;
  double t0 = sm_now();
  for (int p = 0; p < z->np; p++) {
    z->p[p].k = k_at(z, p, t);
    D += z->have_s ? 2 * z->p[p].k : z->p[p].k;
  }
  rc = zfmap_all(z, err);
  D += z->o->nfeat;
  if (rc) return rc;
  double t1 = sm_now();
  zembed(z, last, full_c, D);
  double t2 = sm_now();
  int32_t nq = last || !z->fit ? z->nx : z->nfit;
  int32_t nc = full_c || !z->cand ? z->ny : z->ncand;
  int32_t *out = last ? T : z->Tfit;
  if (z->Sq) { /* bijective: both ways every time, the Y -> X map feeds the next fit */
    rc = z->have_s ? assign_both_factored(z->EY, nc, D / 2, z->LY, z->EYf, D, z->EX, nq,
                                          &z->o->knn, out, z->Sq, err)
                   : assign_both(z->EY, nc, z->EX, nq, D, &z->o->knn, out, z->Sq, err);
    if (!rc && !full_c && z->cand)
      for (int32_t i = 0; i < nq; i++) out[i] = z->cand[out[i]];
    if (!rc && last && z->T_yx) memcpy(z->T_yx, z->Sq, (size_t)z->ny * sizeof(int32_t));
    if (!rc) zkeep_yx(z, last, full_c);
  } else if (last && z->T_yx) { /* the last iteration maps all of X to all of Y: both ways */
    rc = assign_both(z->EY, nc, z->EX, nq, D, &z->o->knn, out, z->T_yx, err);
  } else {
    rc = assign(z->EY, nc, z->EX, nq, D, full_c ? NULL : z->cand, &z->o->knn, out, err);
  }
  z->st.t_fmap += t1 - t0;
  z->st.t_embed += t2 - t1;
  z->st.t_knn += sm_now() - t2;
  return rc;
}

/* Optional output after the last iteration: C per pair (T_yx came with the last
 * iteration's assignment). */
static void zfinish(zctx *z, double *const *C_out) {
  for (int p = 0; p < z->np; p++)
    if (C_out && C_out[p]) from_white(z->p[p].x, z->p[p].y, z->p[p].k, z->p[p].Cw, C_out[p]);
}

int sm_zoomout(const sm_fmap_pair *pairs, int npairs, const sm_zoomout_opts *o,
               const int32_t *T0, int32_t *T, double *const *C_out, int32_t *T_yx,
               sm_zoomout_stats *st, sm_error *err) {
  int rc = check_zoomout(pairs, npairs, o, T0, T, err);
  if (rc) return rc;
  double t_start = sm_now();
  zctx z;
  memset(&z, 0, sizeof z);
  z.o = o;
  z.np = npairs;
  z.nx = pairs[0].x->n;
  z.ny = pairs[0].y->n;
  z.niter = (pairs[0].k - pairs[0].k0 + o->step - 1) / o->step + 1;
  z.full_y_last = o->full_y_last > 0 ? o->full_y_last : 3;
  z.T_yx = T_yx;
  rc = zsetup(&z, pairs, T0, err);
  for (int t = 0; t < z.niter && !rc; t++) {
    if (o->cancel && o->cancel(o->cancel_ud)) {
      rc = sm_error_set(err, SM_ECANCELED, "zoomout: canceled before iteration %d of %d", t,
                        z.niter);
      break;
    }
    rc = ziterate(&z, t, T, err);
    z.st.iterations = t + 1;
  }
  if (!rc) zfinish(&z, C_out);
  z.st.t_total = sm_now() - t_start;
  if (st) *st = z.st;
  zctx_free(&z);
  return rc;
}
