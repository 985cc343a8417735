/* DESIGN
 *   Block Krylov-Schur (thick-restart block Lanczos) on the operator T = S K^-1 S, with
 *   S = diag(sqrt(D)) and K = A - sigma D factored once by CHOLMOD. T is symmetric in the
 *   plain inner product and T z = theta z <=> A x = lambda D x with x = S^-1 z and
 *   lambda = sigma + 1 / theta, so the nev largest theta are the nev smallest lambda.
 *
 *   Invariant. V = [V_1 .. V_k] (n x k, orthonormal) and the pending block P (n x b,
 *   orthonormal, P ⊥ V) satisfy  T V = V H + P C,  H = V^T T V (k x k, symmetric) and
 *   C = P^T T V (b x k). One step appends P to V, computes T P with one CHOLMOD solve of
 *   b right-hand sides, fills the new columns of H by V^T T P (two passes of classical
 *   Gram-Schmidt as BLAS 3), and QR-factors the remainder (I - V V^T) T P = P' R into the
 *   next pending block: then C = [0 .. 0 R]. A Ritz pair (theta, V y) of H has the
 *   residual T V y - theta V y = P C y, so its norm ||R y_last|| (y_last: y's last b
 *   entries) costs nothing of size n. Restart (k + b over the basis size): keep the top
 *   `keep` Ritz vectors, V <- V Y_keep, H <- diag(theta), C <- C Y_keep; the pending block
 *   stays, and the relation holds without any new solve (Stewart's Krylov-Schur, in block
 *   form). Convergence: ||r_i|| <= tol theta_i for the nev largest, as ARPACK's test.
 *   Locking: at a restart the converged leading Ritz vectors are frozen at the front of V
 *   (their coupling to the rest is their residual, below tol); Gram-Schmidt still keeps
 *   new blocks orthogonal to them, but the Rayleigh-Ritz eigenproblem and the restart's
 *   rotation only cover the active columns after them. Block QR is Cholesky QR twice
 *   (level-3), with Householder QR as the fallback for ill-conditioned blocks.
 *   Measured with them and the convergence-test schedule (next_gap) against without
 *   (homerA, one BLAS thread, CPU seconds of the basis, load ~11, alternating runs):
 *   elastic k = 100 1.115 -> 0.989 (420 -> 408 solves), LB k = 100 0.279 -> 0.243.
 *
 *   Why a block method rather than ARPACK (measured, homerA elastic k = 100, one BLAS
 *   thread): single-vector Lanczos spent half of its 2.3 s in one-vector triangular solves
 *   (reading the 2M-entry factor once per vector: memory bound) and half in level-2
 *   reorthogonalization; a block of b vectors reads the factor once per b and turns both
 *   into level-3 BLAS. A block of b also captures eigenvalues of multiplicity up to b
 *   directly, where single-vector Lanczos needs rounding to find the second copy (ARPACK
 *   lost one copy of an exactly 10-fold eigenvalue). And ARPACK keeps Fortran SAVE state:
 *   it forced a process-wide lock; this module has no global state.
 *
 *   Problems too small for the Krylov space (n < basis + 2 b) are solved densely (LAPACK
 *   dsyevr on S^-1 A S^-1).
 *
 *   Threads (sm_eigs_opts.spare_threads): the products with the basis (Gram-Schmidt, the
 *   restarts' rotations) run by row parts fixed by n, on the calling thread and the ones
 *   it may borrow; a large problem's basis is first touched on a borrowed thread during
 *   the factorization. The solves stay on the calling thread (CHOLMOD's supernodal solve
 *   of the whole block). bench_basis, koala elastic k = 100 (150k rows, 8 parts), medians
 *   of 3 alternating runs on the 2-core VM: total 12.57 s (eigensolve 10.48) with no
 *   spare thread, 10.13 s (8.07) with one; 13.12 s before the change, so the parts cost
 *   nothing on one thread.
 */
#define _DEFAULT_SOURCE /* madvise, MADV_HUGEPAGE */
#include "sm_eigs.h"

#include <cblas.h>
#include <cholmod.h>
#include <lapacke.h>
#include <math.h>
#include <pthread.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <time.h>

#include "sm_par.h"

/* OpenMP's switch, reached through CHOLMOD: libcholmod links libgomp when it was built
 * with OpenMP, and a weak reference finds it there without making OpenMP a build
 * dependency of ours (NULL when CHOLMOD has no OpenMP: nothing to turn off). */
extern void omp_set_max_active_levels(int) __attribute__((weak));

void sm_eigs_openmp_off(void) {
  if (omp_set_max_active_levels) omp_set_max_active_levels(0);
}

double sm_now(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* K = A - sigma D as a CHOLMOD lower-triangular matrix. A's columns hold sorted rows, so
 * the diagonal, when present, is the first entry of its column; a missing diagonal is
 * inserted so that the shift always lands. */
static cholmod_sparse *shifted_matrix(const sm_csc *A, const double *D, double sigma,
                                      cholmod_common *c) {
  int32_t n = A->n;
  int64_t missing = 0;
  for (int32_t j = 0; j < n; j++) {
    int32_t p = A->colptr[j];
    if (p == A->colptr[j + 1] || A->rowind[p] != j) missing++;
  }
  cholmod_sparse *K = cholmod_allocate_sparse((size_t)n, (size_t)n, (size_t)(A->nnz + missing),
                                              1, 1, -1, CHOLMOD_REAL, c);
  if (!K) return NULL;
  int *Kp = K->p, *Ki = K->i;
  double *Kx = K->x;
  int64_t q = 0;
  for (int32_t j = 0; j < n; j++) {
    int32_t p = A->colptr[j], end = A->colptr[j + 1];
    Kp[j] = (int)q;
    if (p == end || A->rowind[p] != j) {
      Ki[q] = j;
      Kx[q++] = -sigma * D[j];
    } else {
      Ki[q] = j;
      Kx[q++] = A->val[p++] - sigma * D[j];
    }
    for (; p < end; p++) {
      Ki[q] = A->rowind[p];
      Kx[q++] = A->val[p];
    }
  }
  Kp[n] = (int)q;
  return K;
}

/* Deterministic, well-spread start vectors (xorshift64*, uniform in [-1/2, 1/2)): results
 * are reproducible run to run; no eigenvector is likely to be missing from them. */
static void random_fill(double *r, size_t len, uint64_t *state) {
  uint64_t s = *state;
  for (size_t i = 0; i < len; i++) {
    s ^= s >> 12;
    s ^= s << 25;
    s ^= s >> 27;
    r[i] = (double)((s * 2685821657736338717ULL) >> 11) / 9007199254740992.0 - 0.5;
  }
  *state = s;
}

static void set_ordering(cholmod_common *c, int ordering) {
  static const int method[] = {0, CHOLMOD_AMD, CHOLMOD_METIS, CHOLMOD_NESDIS};
  if (ordering <= 0 || ordering > 3) return;
  c->nmethods = 1;
  c->method[0].ordering = method[ordering];
  c->postorder = 1;
}

typedef struct solver {
  cholmod_common c;
  cholmod_factor *L;
  cholmod_dense *X, *Y, *E; /* cholmod_solve2's workspace, kept across calls */
  const double *s;          /* sqrt(D) */
  double *tmp;              /* n x b */
  int32_t n;
} solver;

/* Y = S K^-1 S X for the b columns of X (n x b, column-major); one multi-right-hand-side
 * solve: the supernodal factor is read once for all b columns (dtrsm/dgemm per supernode). */
static int apply_block(solver *sv, const double *X, int b, double *Y) {
  size_t n = (size_t)sv->n;
  for (int j = 0; j < b; j++)
    for (size_t i = 0; i < n; i++) sv->tmp[j * n + i] = sv->s[i] * X[j * n + i];
  cholmod_dense B = {.nrow = n, .ncol = (size_t)b, .nzmax = n * (size_t)b, .d = n,
                     .x = sv->tmp, .xtype = CHOLMOD_REAL, .dtype = CHOLMOD_DOUBLE};
  if (!cholmod_solve2(CHOLMOD_A, sv->L, &B, NULL, &sv->X, NULL, &sv->Y, &sv->E, &sv->c))
    return SM_ENUMERIC;
  const double *z = sv->X->x;
  size_t ld = sv->X->d;
  for (int j = 0; j < b; j++)
    for (size_t i = 0; i < n; i++) Y[j * n + i] = sv->s[i] * z[j * ld + i];
  return SM_OK;
}

/* Supernodal LL' with CHOLMOD's own ordering choice. Measured on homerA elastic
 * (one-vector solves, one BLAS thread, load ~4): operator time 1.50-1.63 s supernodal
 * against 1.96-2.19 s for a simplicial LDL' factor and 2.16-2.19 s for the supernodal
 * factor converted to simplicial LL'; with blocks of right-hand sides the supernodal
 * factor's advantage only grows (level-3 BLAS per supernode). Orderings: AMD (the default
 * pick) 2.01M nonzeros, METIS 2.06M, NESDIS 1.98M, operator times within the noise. */
static int factor(solver *sv, const sm_csc *A, const double *D, double sigma,
                  sm_eigs_stats *st, sm_error *err) {
  double t0 = sm_now();
  cholmod_sparse *K = shifted_matrix(A, D, sigma, &sv->c);
  if (!K) return sm_error_set(err, SM_ENOMEM, "eigensolver: out of memory for K");
  sv->L = cholmod_analyze(K, &sv->c);
  double t1 = sm_now();
  if (sv->L) cholmod_factorize(K, sv->L, &sv->c);
  cholmod_free_sparse(&K, &sv->c);
  st->t_analyze = t1 - t0;
  st->t_factor = sm_now() - t1;
  if (!sv->L) return sm_error_set(err, SM_ENOMEM, "eigensolver: ordering failed (status %d)",
                                  sv->c.status);
  if (sv->c.status == CHOLMOD_NOT_POSDEF)
    return sm_error_set(err, SM_ENUMERIC,
                        "shifted matrix is not positive definite at column %d (sigma = %g)",
                        (int)sv->L->minor, sigma);
  if (sv->c.status < CHOLMOD_OK)
    return sm_error_set(err, SM_ENUMERIC, "sparse Cholesky failed (status %d)", sv->c.status);
  st->factor_nnz = sv->c.lnz;
  return SM_OK;
}

/* ---- block Krylov-Schur ------------------------------------------------------------- */

typedef struct bks {
  int n, nev, b, mmax, keep; /* mmax: basis columns before a restart (pending block extra) */
  double *V;   /* n x (mmax + b): basis, then the pending block */
  double *W;   /* n x b: T P */
  double *H;   /* mmax x mmax, leading dimension mmax */
  double *R;   /* b x b: C's last block (upper triangular) */
  double *T;   /* mmax x mmax: copy of H for LAPACK */
  double *Z;   /* mmax x keep: Ritz vectors of H (descending theta) */
  double *th;  /* keep: Ritz values, descending */
  double *res; /* keep: residual norms */
  double *G;   /* (mmax + b) x b: projections */
  double *tau; /* b */
  double *rows;/* row chunk for the in-place restart: RCHUNK x keep */
  int *isuppz; /* 2 mmax */
  double *lth; /* nev: Ritz values of the locked columns */
  int nlock;   /* leading columns of V locked (converged at a restart, then frozen) */
  uint64_t seed;
  int parts;   /* row parts of the basis products (for_parts) */
  _Atomic int *spare; /* threads to borrow for them, or NULL */
  double *gpart; /* parts x (mmax + b) x b: partial projections, one per part */
} bks;

enum { RCHUNK = 256 };

static void bks_free(bks *w) {
  free(w->V); free(w->W); free(w->H); free(w->R); free(w->T); free(w->Z); free(w->th);
  free(w->res); free(w->G); free(w->tau); free(w->rows); free(w->isuppz); free(w->lth);
  free(w->gpart);
}

/* The Krylov basis: 0.5 GB for the koala's elastic problem (150k unknowns x 416 vectors).
 * Aligned to 2 MiB and marked for transparent huge pages (the kernel's "madvise" mode, as
 * on Debian): first touches then fault 2 MiB at a time and the GEMMs over it miss the TLB
 * less. perf on this VM: 10% of the koala's eigensolve was the kernel zeroing fresh 4 KiB
 * pages as the basis grew; measured, eigensolve 11.49 -> 11.0 s (two runs each). */
static void *big_alloc(size_t bytes) {
  enum { PAGE_2M = 2u << 20 };
  void *p = NULL;
  if (bytes < 4 * (size_t)PAGE_2M) return malloc(bytes);
  size_t len = (bytes + PAGE_2M - 1) / PAGE_2M * PAGE_2M;
  if (posix_memalign(&p, PAGE_2M, len)) return NULL;
  madvise(p, len, MADV_HUGEPAGE); /* advice only: its failure changes nothing */
  return p;
}

static int bks_alloc(bks *w, int n, int nev, int b, int mmax, int keep, int parts) {
  memset(w, 0, sizeof *w);
  w->n = n; w->nev = nev; w->b = b; w->mmax = mmax; w->keep = keep; w->parts = parts;
  size_t m = (size_t)mmax;
  w->V = big_alloc((size_t)n * (m + (size_t)b) * sizeof(double));
  w->W = malloc((size_t)n * b * sizeof(double));
  w->H = calloc(m * m, sizeof(double));
  w->R = calloc((size_t)b * b, sizeof(double));
  w->T = malloc(m * m * sizeof(double));
  w->Z = malloc(m * (size_t)keep * sizeof(double));
  w->th = malloc((size_t)keep * sizeof(double));
  w->res = malloc((size_t)keep * sizeof(double));
  w->G = malloc((m + (size_t)b) * b * sizeof(double));
  w->tau = malloc((size_t)b * sizeof(double));
  w->rows = malloc((size_t)parts * RCHUNK * keep * sizeof(double));
  w->gpart = malloc((size_t)parts * (m + (size_t)b) * b * sizeof(double));
  w->isuppz = malloc(2 * m * sizeof(int));
  w->lth = malloc((size_t)nev * sizeof(double));
  w->seed = 0x9E3779B97F4A7C15ULL;
  if (!w->V || !w->W || !w->H || !w->R || !w->T || !w->Z || !w->th || !w->res || !w->G ||
      !w->tau || !w->rows || !w->isuppz || !w->lth || !w->gpart)
    return SM_ENOMEM;
  return SM_OK;
}

/* ---- the basis products, by row parts ----------------------------------------------
 * The n rows are split into w->parts parts fixed by n alone (sizes()), and each product
 * runs part by part, its partial results summed in part order: so the result is the same
 * bit for bit whatever the number of threads that runs the parts. The calling thread takes
 * parts too; the threads it borrows from w->spare are returned when the product ends. */

typedef void (*part_fn)(bks *w, void *ctx, int p, int r0, int rn);

static void part_range(const bks *w, int p, int *r0, int *rn) {
  int64_t a = (int64_t)w->n * p / w->parts, e = (int64_t)w->n * (p + 1) / w->parts;
  *r0 = (int)a;
  *rn = (int)(e - a);
}

/* Part p of a for_parts loop (sm_par_for job). */
typedef struct part_call {
  bks *w;
  part_fn fn;
  void *ctx;
} part_call;

static void part_job(void *vc, int p) {
  part_call *c = vc;
  int r0, rn;
  part_range(c->w, p, &r0, &rn);
  c->fn(c->w, c->ctx, p, r0, rn);
}

/* Up to want threads from *spare (NULL: none). */
static int borrow_threads(_Atomic int *spare, int want) {
  if (!spare || want <= 0) return 0;
  int have = atomic_load(spare);
  while (have > 0) {
    int take = have < want ? have : want;
    if (atomic_compare_exchange_weak(spare, &have, have - take)) return take;
  }
  return 0;
}

static void for_parts(bks *w, part_fn fn, void *ctx) {
  part_call c = {w, fn, ctx};
  int extra = borrow_threads(w->spare, w->parts - 1);
  sm_par_for(w->parts, 1 + extra, part_job, &c);
  if (extra) atomic_fetch_add(w->spare, extra);
}

typedef struct proj_ctx {
  const double *Q;
  int k;
  double *X, *g;
} proj_ctx;

/* gpart[p] = Q[rows of p]^T X[rows of p] (k x b); with one part, straight into g. */
static void proj_dots(bks *w, void *ctx, int p, int r0, int rn) {
  proj_ctx *c = ctx;
  double *out = w->parts == 1 ? c->g : w->gpart + (size_t)p * c->k * w->b;
  cblas_dgemm(CblasColMajor, CblasTrans, CblasNoTrans, c->k, w->b, rn, 1.0, c->Q + r0, w->n,
              c->X + r0, w->n, 0.0, out, c->k);
}

/* X[rows of p] -= Q[rows of p] g. */
static void proj_update(bks *w, void *ctx, int p, int r0, int rn) {
  proj_ctx *c = ctx;
  (void)p;
  cblas_dgemm(CblasColMajor, CblasNoTrans, CblasNoTrans, rn, w->b, c->k, -1.0, c->Q + r0, w->n,
              c->g, c->k, 1.0, c->X + r0, w->n);
}

/* X (n x b) -= Q (n x k) Q^T X, accumulating Q^T X into G (k x b, ld k) when acc. */
static void project_out(bks *w, const double *Q, int k, double *X, double *G, int acc,
                        double *Gtmp) {
  if (k == 0) return;
  int b = w->b;
  proj_ctx c = {.Q = Q, .k = k, .X = X, .g = acc ? Gtmp : G};
  for_parts(w, proj_dots, &c);
  size_t kb = (size_t)k * b;
  if (w->parts > 1) {
    memcpy(c.g, w->gpart, kb * sizeof(double));
    for (int p = 1; p < w->parts; p++)
      for (size_t i = 0; i < kb; i++) c.g[i] += w->gpart[p * kb + i];
  }
  for_parts(w, proj_update, &c);
  if (acc)
    for (size_t i = 0; i < kb; i++) G[i] += c.g[i];
}

/* Householder QR of X (n x b) in place: X <- Q, Rout (b x b, upper) <- R. */
static int qr_inplace(double *X, int n, int b, double *tau, double *Rout) {
  if (LAPACKE_dgeqrf(LAPACK_COL_MAJOR, n, b, X, n, tau)) return SM_ENUMERIC;
  for (int j = 0; j < b; j++)
    for (int i = 0; i < b; i++) Rout[(size_t)j * b + i] = i <= j ? X[(size_t)j * n + i] : 0.0;
  if (LAPACKE_dorgqr(LAPACK_COL_MAJOR, n, b, b, X, n, tau)) return SM_ENUMERIC;
  return SM_OK;
}

/* One Cholesky QR pass: G = X^T X = R^T R, X <- X R^-1. Nonzero when X is numerically
 * rank deficient (G not positive definite). */
static int cholqr_pass(double *X, int n, int b, double *R) {
  cblas_dsyrk(CblasColMajor, CblasUpper, CblasTrans, b, n, 1.0, X, n, 0.0, R, b);
  if (LAPACKE_dpotrf(LAPACK_COL_MAJOR, 'U', b, R, b)) return SM_ENUMERIC;
  for (int j = 0; j < b; j++)
    for (int i = j + 1; i < b; i++) R[(size_t)j * b + i] = 0.0;
  cblas_dtrsm(CblasColMajor, CblasRight, CblasUpper, CblasNoTrans, CblasNonUnit, n, b, 1.0, R,
              b, X, n);
  return SM_OK;
}

/* C = A B for upper triangular b x b A, B (C may not alias them). */
static void triu_product(const double *A, const double *B, int b, double *C) {
  for (int j = 0; j < b; j++)
    for (int i = 0; i < b; i++) {
      double s = 0;
      for (int l = i; l <= j; l++) s += A[(size_t)l * b + i] * B[(size_t)j * b + l];
      C[(size_t)j * b + i] = s;
    }
}

/* Cholesky QR twice (X <- Q, Rout <- R): two level-3 passes instead of Householder's
 * panel factorization and its explicit Q; the second pass restores orthogonality to
 * rounding as long as the first left it within a fraction of 1, i.e. cond(X) below about
 * 1e7. Returns nonzero, with X destroyed, when that cannot be trusted: the caller then
 * starts again from a copy with the Householder path. */
static int cholqr2(double *X, int n, int b, double *Rout) {
  double R1[64 * 64], R2[64 * 64];
  if (cholqr_pass(X, n, b, R1)) return SM_ENUMERIC;
  double dmax = 0, dmin = INFINITY;
  for (int i = 0; i < b; i++) {
    dmax = fmax(dmax, R1[(size_t)i * b + i]);
    dmin = fmin(dmin, R1[(size_t)i * b + i]);
  }
  if (!(dmin > 1e-6 * dmax)) return SM_ENUMERIC;
  if (cholqr_pass(X, n, b, R2)) return SM_ENUMERIC;
  for (int j = 0; j < b; j++) /* R2 = I up to the first pass's loss of orthogonality */
    for (int i = 0; i <= j; i++)
      if (!(fabs(R2[(size_t)j * b + i] - (i == j)) < 1e-2)) return SM_ENUMERIC;
  triu_product(R2, R1, b, Rout);
  return SM_OK;
}

/* Orthonormalizes X (n x b) against Q (n x k) and within itself: X_in = Q G + X_out R
 * (up to rounding); G (k x b) is not returned (callers that need it project first).
 * Well-conditioned blocks (the usual case) go through Cholesky QR; `copy` (n x b) holds
 * X_in for the fallback, which handles the rest: columns of X_in that are (numerically)
 * in span(Q) come out as other unit vectors ⊥ Q: after the first Householder QR such a
 * column is a rounding-noise direction, which one more projection and QR turn into a
 * valid one, with R's tiny entries still describing X_in. */
static int orthonormalize(bks *w, const double *Q, int k, double *X, const double *copy,
                          double *Rout, double *Gtmp) {
  int n = w->n, b = w->b;
  double R1[64 * 64], R2[64 * 64];
  if (!cholqr2(X, n, b, Rout)) return SM_OK;
  memcpy(X, copy, (size_t)n * b * sizeof(double));
  if (qr_inplace(X, n, b, w->tau, R1)) return SM_ENUMERIC;
  double dmax = 0, dmin = INFINITY;
  for (int i = 0; i < b; i++) {
    double d = fabs(R1[(size_t)i * b + i]);
    dmax = fmax(dmax, d);
    dmin = fmin(dmin, d);
  }
  if (!(dmin > 1e-8 * dmax)) {
    project_out(w, Q, k, X, Gtmp, 0, NULL);
    project_out(w, Q, k, X, Gtmp, 0, NULL);
    if (qr_inplace(X, n, b, w->tau, R2)) return SM_ENUMERIC;
    triu_product(R2, R1, b, Rout);
  } else {
    memcpy(Rout, R1, (size_t)b * b * sizeof(double));
  }
  return SM_OK;
}

/* Top m Ritz pairs of the active part of H, rows and columns nlock..k-1: th descending,
 * Z columns (ld k - nlock) in the same order, and their residual norms ||R y_last||. The
 * locked columns are converged Ritz vectors whose coupling to the rest is below the
 * tolerance (the residual of their pair): leaving it out is the deflation of Krylov-Schur
 * locking, a perturbation of T of that size, and the eigenproblem shrinks by them. */
static int ritz(bks *w, int k, int m) {
  int b = w->b, a0 = w->nlock, ka = k - a0;
  double *ev = malloc((size_t)ka * sizeof *ev), *Y = w->T;
  if (!ev) return SM_ENOMEM;
  /* All pairs by divide and conquer: at k <= a few hundred it is faster than bisection
   * and inverse iteration for the top m (dsyevr's path for a partial range). Its secular
   * equation solver can fail to converge on clusters of (numerically) equal eigenvalues
   * (seen: two identical icospheres, 10-fold eigenvalues, block 8: info > 0); the
   * implicit QL/QR algorithm of dsyev then takes the same matrix again. */
  int info = 1;
  for (int pass = 0; info && pass < 2; pass++) {
    for (int j = 0; j < ka; j++)
      memcpy(w->T + (size_t)j * ka, w->H + (size_t)(a0 + j) * w->mmax + a0,
             (size_t)ka * sizeof(double));
    info = pass ? LAPACKE_dsyev(LAPACK_COL_MAJOR, 'V', 'L', ka, w->T, ka, ev)
                : LAPACKE_dsyevd(LAPACK_COL_MAJOR, 'V', 'L', ka, w->T, ka, ev);
  }
  if (info) {
    free(ev);
    return SM_ENUMERIC;
  }
  Y += (size_t)(ka - m) * ka;
  for (int j = 0; j < m; j++) { /* ascending -> descending */
    w->th[j] = ev[ka - 1 - j];
    memcpy(w->Z + (size_t)j * ka, Y + (size_t)(m - 1 - j) * ka, (size_t)ka * sizeof(double));
  }
  free(ev);
  for (int j = 0; j < m; j++) {
    const double *y = w->Z + (size_t)j * ka + (ka - b);
    double s2 = 0;
    for (int i = 0; i < b; i++) {
      double r = 0;
      for (int l = i; l < b; l++) r += w->R[(size_t)l * b + i] * y[l];
      s2 += r * r;
    }
    w->res[j] = sqrt(s2);
  }
  return SM_OK;
}

typedef struct rotate_ctx {
  int k, m;
} rotate_ctx;

/* The rows of part p, by chunks of RCHUNK (the part's own chunk buffer). */
static void rotate_rows(bks *w, void *ctx, int p, int r0, int rn) {
  rotate_ctx *c = ctx;
  int n = w->n, ka = c->k - w->nlock, m = c->m;
  double *Va = w->V + (size_t)w->nlock * n, *buf = w->rows + (size_t)p * RCHUNK * w->keep;
  for (int a = r0; a < r0 + rn; a += RCHUNK) {
    int cn = r0 + rn - a < RCHUNK ? r0 + rn - a : RCHUNK;
    cblas_dgemm(CblasColMajor, CblasNoTrans, CblasNoTrans, cn, m, ka, 1.0, Va + a, n, w->Z, ka,
                0.0, buf, cn);
    for (int j = 0; j < m; j++)
      memcpy(Va + (size_t)j * n + a, buf + (size_t)j * cn, (size_t)cn * sizeof(double));
  }
}

/* V[:, nlock:nlock+m] <- V[:, nlock:k] Z[:, 0:m] in place, by chunks of rows. */
static void rotate_basis(bks *w, int k, int m) {
  rotate_ctx c = {.k = k, .m = m};
  for_parts(w, rotate_rows, &c);
}

/* Expansion steps until the next convergence test. A test (a dense eigensolve of the
 * active part, O(k^3)) costs about as much as a step on the smaller problems, and the
 * residuals fall geometrically once they start to: from the decay of the worst wanted
 * residual since the previous test, predict the steps to convergence; far from it (the
 * decay then still speeds up, so the prediction is long) wait half of them, 2 to 8
 * steps; close to it (under 4 steps), about them, rounded down: a test there is cheap
 * (the active part is small after the locking) and one step too many is not. */
static int next_gap(double q, double qprev, int steps) {
  if (!(qprev > q) || steps <= 0 || !(q > 1)) return 2;
  double rate = log(qprev / q) / steps, est = log(q) / rate;
  if (est < 4) return est < 2 ? 1 : (int)est;
  int gap = (int)(0.5 * est);
  return gap < 2 ? 2 : gap > 8 ? 8 : gap;
}

static int run_bks(solver *sv, bks *w, const sm_eigs_opts *o, sm_eigs_stats *st,
                   sm_error *err) {
  /* tol 1e-9 relative to theta, as the ARPACK runs before it (see sm_basis.c). */
  double tol = o->tol > 0 ? o->tol : 1e-9;
  int n = w->n, b = w->b, nev = w->nev, mmax = w->mmax;
  int maxsolves = o->maxsolves > 0 ? o->maxsolves : 10 * mmax + 100;
  int maxrestarts = o->maxiter > 0 ? o->maxiter : 100;
  double *Gtmp = malloc(((size_t)mmax + b) * b * sizeof *Gtmp);
  if (!Gtmp) return sm_error_set(err, SM_ENOMEM, "eigensolver: out of memory");
  double R0[64 * 64];
  random_fill(w->V, (size_t)n * b, &w->seed);
  memcpy(w->W, w->V, (size_t)n * b * sizeof(double));
  int rc = orthonormalize(w, NULL, 0, w->V, w->W, R0, Gtmp);
  int k = 0, conv = 0, krestart = 0, since = 0, gap = 2;
  double qprev = 0;
  w->nlock = 0;
  /* Convergence is tested only once the space is well past nev: a Ritz value found early
   * can look converged while an eigenvalue above it is not in the space yet. */
  int kcheck = nev + 2 * b < mmax ? nev + 2 * b : mmax;
  while (!rc) {
    if (o->cancel && o->cancel(o->cancel_ud)) {
      rc = sm_error_set(err, SM_ECANCELED, "eigensolver canceled");
      break;
    }
    if (st->nsolves + b > maxsolves) {
      rc = sm_error_set(err, SM_ENUMERIC, "block Lanczos: no convergence after %d operator "
                        "applications (%d eigenpairs, %d of them converged; basis %d, block "
                        "%d); the problem is ill-conditioned or the shift is far from the "
                        "wanted eigenvalues", st->nsolves, nev, conv, mmax, b);
      break;
    }
    /* Expand: P = V[:, k:k+b] joins the basis. */
    double *P = w->V + (size_t)k * n;
    double t0 = sm_now();
    if (apply_block(sv, P, b, w->W)) {
      rc = sm_error_set(err, SM_ENUMERIC, "sparse triangular solve failed");
      break;
    }
    st->t_op += sm_now() - t0;
    st->nsolves += b;
    int k1 = k + b;
    /* New columns of H: V^T T P, by two passes of block Gram-Schmidt on W = T P. */
    /* Local pass: in exact arithmetic T P couples only to P and the block before it (or,
     * right after a restart, to every kept Ritz vector; to the locked ones only below the
     * tolerance), so removing those first leaves small components along the rest of V;
     * one full pass removes them, and a second runs only when that pass still cancelled
     * most of a column (the test of Daniel, Gragg, Kaufman and Stewart, as ARPACK's
     * dsaitr does for one vector). */
    int lo = k == krestart ? w->nlock : k - b;
    project_out(w, w->V + (size_t)lo * n, k1 - lo, w->W, Gtmp, 0, NULL);
    double nb[64], ratio = INFINITY;
    for (int j = 0; j < b; j++) nb[j] = cblas_dnrm2(n, w->W + (size_t)j * n, 1);
    project_out(w, w->V, k1, w->W, w->G, 0, NULL);
    for (int j = 0; j < b; j++)
      for (int i = lo; i < k1; i++) w->G[(size_t)j * k1 + i] += Gtmp[(size_t)j * (k1 - lo) + i - lo];
    for (int j = 0; j < b; j++)
      ratio = fmin(ratio, cblas_dnrm2(n, w->W + (size_t)j * n, 1) / nb[j]);
    if (!(ratio > 0.717)) project_out(w, w->V, k1, w->W, w->G, 1, Gtmp);
    for (int j = 0; j < b; j++)
      for (int i = 0; i < k1; i++) w->H[(size_t)(k + j) * mmax + i] = w->G[(size_t)j * k1 + i];
    for (int j = 0; j < b; j++) /* symmetric: mirror the new block row */
      for (int i = 0; i < k1; i++) {
        double *hij = &w->H[(size_t)(k + j) * mmax + i], *hji = &w->H[(size_t)i * mmax + k + j];
        if (i >= k && i > k + j) continue;
        double v = i >= k ? 0.5 * (*hij + *hji) : *hij;
        *hij = *hji = v;
      }
    k = k1;
    since++;
    /* Next pending block: the part of T P outside the basis (W keeps a copy). */
    memcpy(w->V + (size_t)k * n, w->W, (size_t)n * b * sizeof(double));
    if ((rc = orthonormalize(w, w->V, k, w->V + (size_t)k * n, w->W, w->R, Gtmp))) {
      rc = sm_error_set(err, SM_ENUMERIC, "eigensolver: QR of a block failed");
      break;
    }
    int full = k + b > mmax;
    if (k < kcheck && !full) continue;
    if (!full && since < gap) continue;
    int a0 = w->nlock, need = nev - a0;
    int m = w->keep - a0 < k - a0 ? w->keep - a0 : k - a0;
    if (ritz(w, k, m)) {
      rc = sm_error_set(err, SM_ENUMERIC, "eigensolver: Rayleigh-Ritz failed (k = %d)", k);
      break;
    }
    int ca = 0;
    while (ca < need && ca < m && w->res[ca] <= tol * fabs(w->th[ca])) ca++;
    conv = a0 + ca;
    if (ca >= need) {
      rotate_basis(w, k, need);
      break;
    }
    double q = 0;
    for (int j = ca; j < need && j < m; j++) q = fmax(q, w->res[j] / (tol * fabs(w->th[j])));
    gap = next_gap(q, qprev, since);
    qprev = q;
    since = 0;
    if (!full) continue;
    if (st->restarts >= maxrestarts) {
      rc = sm_error_set(err, SM_ENUMERIC, "block Lanczos: %d of %d eigenpairs converged in %d "
                        "restarts", conv, nev, st->restarts);
      break;
    }
    /* Thick restart: keep the top m active Ritz vectors, lock the converged ones among
     * them, move the pending block after them. */
    st->restarts++;
    rotate_basis(w, k, m);
    memmove(w->V + (size_t)(a0 + m) * n, w->V + (size_t)k * n, (size_t)n * b * sizeof(double));
    /* C <- C Z: its last block R times Z's last b rows; stored as the b x m coupling in
     * H's rows after the next expansion, which recomputes them from V^T T P. */
    memset(w->H, 0, (size_t)mmax * mmax * sizeof(double));
    for (int j = 0; j < ca; j++) w->lth[a0 + j] = w->th[j];
    for (int j = 0; j < a0 + ca; j++) w->H[(size_t)j * mmax + j] = w->lth[j];
    for (int j = ca; j < m; j++) w->H[(size_t)(a0 + j) * mmax + a0 + j] = w->th[j];
    w->nlock = a0 + ca;
    k = krestart = a0 + m;
  }
  if (!rc) { /* th[0:nev] <- the locked values, then the active ones */
    int a0 = w->nlock;
    memmove(w->th + a0, w->th, (size_t)(nev - a0) * sizeof(double));
    memcpy(w->th, w->lth, (size_t)a0 * sizeof(double));
  }
  free(Gtmp);
  return rc;
}

/* Small problems: dense eigenvalues of S^-1 A S^-1. */
static int dense_smallest(const sm_csc *A, const double *s, int nev, double *evals,
                          double *evecs, sm_error *err) {
  int n = A->n;
  double *C = calloc((size_t)n * n, sizeof *C), *ev = malloc((size_t)n * sizeof *ev);
  int *isuppz = malloc((size_t)2 * n * sizeof *isuppz);
  if (!C || !ev || !isuppz) {
    free(C); free(ev); free(isuppz);
    return sm_error_set(err, SM_ENOMEM, "eigensolver: out of memory (dense %d x %d)", n, n);
  }
  for (int j = 0; j < n; j++)
    for (int32_t p = A->colptr[j]; p < A->colptr[j + 1]; p++) {
      int i = A->rowind[p];
      if (i >= j) C[(size_t)j * n + i] += A->val[p] / (s[i] * s[j]);
    }
  int found = 0;
  int info = LAPACKE_dsyevr(LAPACK_COL_MAJOR, 'V', 'I', 'L', n, C, n, 0.0, 0.0, 1, nev, 0.0,
                            &found, ev, evecs, n, isuppz);
  int rc = SM_OK;
  if (info || found != nev)
    rc = sm_error_set(err, SM_ENUMERIC, "dense eigensolver failed (info = %d)", info);
  for (int j = 0; !rc && j < nev; j++) {
    evals[j] = ev[j];
    for (int i = 0; i < n; i++) evecs[(size_t)j * n + i] /= s[i];
  }
  free(C); free(ev); free(isuppz);
  return rc;
}

/* Block size and basis size. Measured (elastic k = 100, nev = 112, one BLAS thread, CPU
 * seconds of the iteration on a loaded 2-core machine; "ncv" = basis before a restart):
 *   homerA (15k unknowns)   b = 8, ncv 2 nev: 392 solves, 1.04 s;  b = 8, 3 nev: 344, 0.91;
 *                           b = 16, 2 nev: 528, 1.08;  b = 16, 3 nev: 496, 1.06
 *   headA (45k unknowns)    b = 8, 3 nev: 344, 3.01;  b = 12: 396, 3.14;  b = 16: 480, 3.27;
 *                           b = 8, 2.5 nev: 384, 3.15
 * (ARPACK, one vector at a time, ncv = 2 nev + 1: 283 solves, 2.3 s wall unloaded on
 * homerA.) Wider blocks need more vectors (a block Krylov space of dimension m has degree
 * m / b) but each costs less (the factor is read once per block); the totals are flat
 * from 8 to 16. Robustness decides: b = 4 loses copies of the exactly 10-fold eigenvalues
 * of two identical spheres (test_basis), b = 8 finds them only through rounding, b = 12
 * captures them by construction. A basis of 3 nev saves a restart over 2 nev; its memory,
 * 8 n (3 nev + b) bytes, is 0.4 GB on a 47k-vertex elastic problem.
 * Large problems (n >= SM_EIGS_LARGE_N) take b = 16 and 4 nev: there the factor and the
 * basis are far larger than the caches and a step is bound by reading them, so fewer,
 * wider steps win. Measured with locking (CPU seconds of the basis, alternating runs,
 * load ~8-9): koala (150k unknowns) b = 12, 3 nev: 540 solves, 15.6 s; b = 16, 4 nev:
 * 544 solves in 34 steps, 14.2 s (b = 12, 4 nev: 468 solves, 14.7 s; b = 24, 4 nev: 720,
 * 16.5 s); headA (45k) 3.75 s either way; homerA (15k) 0.99 s against 1.05 s. Memory at
 * 150k unknowns: 0.56 GB of basis instead of 0.42 GB.
 * Very sparse factors (under SM_EIGS_CHEAP_FILL nonzeros per row: LB on small meshes)
 * take a basis of 2 nev: a solve then costs less than a Gram-Schmidt step over a long
 * basis (4 fill against 4 k flops per vector), so more solves and restarts on a shorter
 * basis win. Measured (LB k = 100, CPU of the basis, alternating runs, load ~7-8): homerA
 * (5k vertices, fill 19) 0.236 -> 0.208 s, lion (fill 16) 0.247 -> 0.224 s; headA (fill
 * 42) 0.863 against 0.849 s; the elastic problems (fill 130 and more) lose with 2 nev:
 * homerA 0.93 against 1.06 s, lion 0.92 against 0.94 s. They also take blocks of 8:
 * Gram-Schmidt is then most of a step (homerA: 45% of the iteration, the solves 25%), and
 * a narrower block needs fewer vectors (400 solves against 492) while 8 columns still fit
 * OpenBLAS's dgemm kernel without a remainder pass. Measured (homerA LB k = 100, basis 2
 * nev, CPU of the iteration, medians of 5, load ~5): b = 6 0.19-0.20 s, 8 0.15-0.16, 10
 * 0.20-0.22, 12 0.18-0.22, 16 0.22 s; alternating whole runs 0.219 -> 0.167 s; the
 * 10-fold eigenvalues of two identical icospheres still come out (test_basis). */
enum { SM_EIGS_LARGE_N = 100000, SM_EIGS_CHEAP_FILL = 30 };

/* fill: the factor's nonzeros per row, 0 before it is known. */
/* The Krylov basis's first touch, on a thread borrowed for the factorization's duration.
 * The kernel zeroes a fresh page at its first write, and on this VM that was 7% of the
 * koala's eigensolve (perf: clear_page_erms under the memcpy that appends each block to
 * V), in the calling thread; the factorization (1.6 s there, one thread) hides it. */
typedef struct prefault {
  char *p;
  size_t len;
  _Atomic int *spare;
  pthread_t th;
  int running;
} prefault;

static void *prefault_run(void *arg) {
  prefault *f = arg;
  for (size_t off = 0; off < f->len; off += 4096) ((volatile char *)f->p)[off] = 0;
  return NULL;
}

static void prefault_start(prefault *f, const bks *w, _Atomic int *spare) {
  f->p = (char *)w->V;
  f->len = (size_t)w->n * ((size_t)w->mmax + w->b) * sizeof(double);
  f->spare = spare;
  if (!borrow_threads(spare, 1)) return;
  f->running = !pthread_create(&f->th, NULL, prefault_run, f);
  if (!f->running) atomic_fetch_add(spare, 1);
}

static void prefault_join(prefault *f) {
  if (!f->running) return;
  pthread_join(f->th, NULL);
  atomic_fetch_add(f->spare, 1);
  f->running = 0;
}

/* Row parts of the basis products (for_parts): one per part_rows rows, 1 to
 * SM_EIGS_MAX_PARTS. A function of n alone, so that the result does not depend on the
 * threads. Below 2 part_rows (homerA's elastic problem, 15k rows) one part: the products
 * are short there and the solves dominate. */
static int row_parts(const sm_eigs_opts *o, int n) {
  int pr = o->part_rows > 0 ? o->part_rows : SM_EIGS_PART_ROWS;
  int p = n / pr;
  return p < 1 ? 1 : p > SM_EIGS_MAX_PARTS ? SM_EIGS_MAX_PARTS : p;
}

static void sizes(const sm_eigs_opts *o, int n, double fill, int *b, int *mmax, int *keep) {
  int large = n >= SM_EIGS_LARGE_N, cheap = fill > 0 && fill < SM_EIGS_CHEAP_FILL;
  int bb = o->block > 0 ? o->block : large ? 16 : cheap ? 8 : 12;
  if (bb > 64) bb = 64; /* the b x b workspaces live on the stack */
  if (bb > o->nev) bb = o->nev < 4 ? 4 : o->nev;
  int m = o->ncv > 0 ? o->ncv : (large ? 4 : cheap ? 2 : 3) * o->nev;
  int kp = o->nev + bb;
  if (m < kp + 2 * bb) m = kp + 2 * bb;
  m = (m + bb - 1) / bb * bb;
  *b = bb;
  *mmax = m;
  *keep = kp;
}

int sm_eigs_smallest(const sm_csc *A, const double *D, const sm_eigs_opts *o, double *evals,
                     double *evecs, sm_eigs_stats *st, sm_error *err) {
  sm_eigs_stats local;
  int32_t n = A->n;
  if (!st) st = &local;
  memset(st, 0, sizeof *st);
  if (o->nev <= 0 || o->nev >= n)
    return sm_error_set(err, SM_EINVAL, "eigensolver: %d eigenpairs requested of a %d x %d "
                        "problem", o->nev, n, n);
  if (!(o->sigma < 0))
    return sm_error_set(err, SM_EINVAL, "eigensolver: shift %g must be negative", o->sigma);
  int b, mmax, keep; /* the largest basis first: it decides whether n is too small */
  sizes(o, n, 0, &b, &mmax, &keep);

  double *s = malloc((size_t)n * sizeof *s);
  if (!s) return sm_error_set(err, SM_ENOMEM, "eigensolver: out of memory (n = %d)", n);
  for (int32_t i = 0; i < n; i++) {
    if (!(D[i] > 0)) {
      free(s);
      return sm_error_set(err, SM_ENUMERIC, "eigensolver: mass %d is %g, not positive", i, D[i]);
    }
    s[i] = sqrt(D[i]);
  }
  if (n < mmax + 2 * b) {
    double t0 = sm_now();
    int rc = dense_smallest(A, s, o->nev, evals, evecs, err);
    st->t_solve = sm_now() - t0;
    free(s);
    return rc;
  }

  solver sv;
  memset(&sv, 0, sizeof sv);
  sv.n = n;
  sv.s = s;
  cholmod_start(&sv.c);
  sv.c.print = 0;
  sv.c.error_handler = NULL;
  set_ordering(&sv.c, o->ordering);
  sv.tmp = malloc((size_t)n * b * sizeof *sv.tmp);
  bks w;
  memset(&w, 0, sizeof w);
  int rc = sv.tmp ? SM_OK : SM_ENOMEM;
  if (rc) {
    rc = sm_error_set(err, SM_ENOMEM, "eigensolver: out of memory (n = %d)", n);
    goto done;
  }
  /* Large problems' sizes do not depend on the fill: their basis is allocated before the
   * factorization, and first touched meanwhile on a borrowed thread (prefault). */
  int early = n >= SM_EIGS_LARGE_N;
  prefault pf = {0};
  if (early && (rc = bks_alloc(&w, n, o->nev, b, mmax, keep, row_parts(o, n)))) goto nomem;
  if (early) prefault_start(&pf, &w, o->spare_threads);
  rc = factor(&sv, A, D, o->sigma, st, err);
  prefault_join(&pf);
  if (rc) goto done;
  if (!early) {
    sizes(o, n, st->factor_nnz / n, &b, &mmax, &keep);
    if ((rc = bks_alloc(&w, n, o->nev, b, mmax, keep, row_parts(o, n)))) goto nomem;
  }
  w.spare = o->spare_threads;
  double t0 = sm_now();
  rc = run_bks(&sv, &w, o, st, err);
  int *order = rc ? NULL : malloc((size_t)o->nev * sizeof *order);
  if (!rc && !order) rc = sm_error_set(err, SM_ENOMEM, "eigensolver: out of memory");
  if (!rc) { /* columns by theta descending (a pair found after the locking of smaller
              * ones comes after them in V) -> lambda ascending; x = S^-1 z */
    for (int j = 0; j < o->nev; j++) {
      int i = j;
      for (; i > 0 && w.th[order[i - 1]] < w.th[j]; i--) order[i] = order[i - 1];
      order[i] = j;
    }
    for (int j = 0; j < o->nev; j++) {
      evals[j] = o->sigma + 1.0 / w.th[order[j]];
      const double *z = w.V + (size_t)order[j] * n;
      double *x = evecs + (size_t)j * n;
      for (int32_t i = 0; i < n; i++) x[i] = z[i] / s[i];
    }
  }
  free(order);
  st->t_solve = sm_now() - t0;
  goto done;
nomem:
  rc = sm_error_set(err, SM_ENOMEM, "eigensolver: out of memory (n = %d, basis %d)", n, mmax);
done:
  bks_free(&w);
  free(s);
  free(sv.tmp);
  cholmod_free_dense(&sv.X, &sv.c);
  cholmod_free_dense(&sv.Y, &sv.c);
  cholmod_free_dense(&sv.E, &sv.c);
  cholmod_free_factor(&sv.L, &sv.c);
  cholmod_finish(&sv.c);
  return rc;
}
