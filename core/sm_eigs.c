#include "sm_eigs.h"

#include <arpack/arpack.h>
#include <cholmod.h>
#include <math.h>
#include <pthread.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static pthread_mutex_t arpack_lock = PTHREAD_MUTEX_INITIALIZER;

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

/* A deterministic, well-spread start vector: reproducible results run to run. Uniform
 * pseudo-random entries are the standard Lanczos start (no eigenvector is likely to be
 * missing from it); results then depend on the BLAS thread count only through rounding. */
static void start_vector(double *r, int32_t n) {
  uint64_t s = 0x9E3779B97F4A7C15ULL;
  for (int32_t i = 0; i < n; i++) {
    s ^= s >> 12;
    s ^= s << 25;
    s ^= s >> 27;
    r[i] = (double)((s * 2685821657736338717ULL) >> 11) / 9007199254740992.0 - 0.5;
  }
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
  cholmod_dense *X, *Y, *E;
  cholmod_dense B;
  const double *s; /* sqrt(D) */
  double *tmp;
  int32_t n;
} solver;

/* y = s K^-1 s x */
static int apply_op(solver *sv, const double *x, double *y) {
  for (int32_t i = 0; i < sv->n; i++) sv->tmp[i] = sv->s[i] * x[i];
  if (!cholmod_solve2(CHOLMOD_A, sv->L, &sv->B, NULL, &sv->X, NULL, &sv->Y, &sv->E, &sv->c))
    return SM_ENUMERIC;
  const double *z = sv->X->x;
  for (int32_t i = 0; i < sv->n; i++) y[i] = sv->s[i] * z[i];
  return SM_OK;
}

/* Supernodal LL' with CHOLMOD's own ordering choice. Measured on homerA elastic
 * (283 solves, one BLAS thread, load ~4): operator time 1.50-1.63 s supernodal against
 * 1.96-2.19 s for a simplicial LDL' factor and 2.16-2.19 s for the supernodal factor
 * converted to simplicial LL'. Orderings: AMD (the default pick) 2.01M nonzeros, METIS
 * 2.06M, NESDIS 1.98M, operator times within the noise. The solve's permutation of the
 * right-hand side is O(n) against O(nnz(L)) = 2M per solve, so running ARPACK in the
 * permuted space would gain under 1%. */
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

typedef struct lanczos {
  int n, nev, ncv, lworkl;
  int iparam[11], ipntr[14];
  double *resid, *V, *workd, *workl, *Z, *d;
  int *select;
} lanczos;

static void lanczos_free(lanczos *lz) {
  free(lz->resid); free(lz->V); free(lz->workd); free(lz->workl);
  free(lz->Z); free(lz->d); free(lz->select);
}

static int lanczos_alloc(lanczos *lz, int n, int nev, int ncv) {
  memset(lz, 0, sizeof *lz);
  lz->n = n;
  lz->nev = nev;
  lz->ncv = ncv;
  lz->lworkl = ncv * (ncv + 8);
  lz->resid = malloc((size_t)n * sizeof(double));
  lz->V = malloc((size_t)n * ncv * sizeof(double));
  lz->workd = malloc((size_t)3 * n * sizeof(double));
  lz->workl = malloc((size_t)lz->lworkl * sizeof(double));
  lz->Z = malloc((size_t)n * nev * sizeof(double));
  lz->d = malloc((size_t)nev * sizeof(double));
  lz->select = calloc((size_t)ncv, sizeof(int));
  if (!lz->resid || !lz->V || !lz->workd || !lz->workl || !lz->Z || !lz->d || !lz->select)
    return SM_ENOMEM;
  start_vector(lz->resid, n);
  return SM_OK;
}

static int run_lanczos(solver *sv, lanczos *lz, const sm_eigs_opts *o, sm_eigs_stats *st,
                       sm_error *err) {
  /* 1e-9, measured on homerA elastic k = 100: 1e-8 to 1e-11 all stop after the same 283
   * solves (ARPACK overshoots at the restart that converges); 1e-6 saves a restart (226)
   * but leaves residuals of 1e-4 lambda_max; 1e-12 costs the koala 340 solves instead
   * of 281 (+20% CPU). maxiter and maxsolves only bound a failing run: normal runs
   * restart 1-3 times and apply the operator 1-2 ncv times. They used to allow 1000
   * restarts: with a shift far below the wanted eigenvalues (an operator whose spectrum is
   * compressed to relative gaps of 1e-6) that was minutes to hours inside dsaupd, with
   * nothing converging (centaur3 elastic: 21 solves per restart, 0 of 112 converged). */
  double tol = o->tol > 0 ? o->tol : 1e-9;
  int maxsolves = o->maxsolves > 0 ? o->maxsolves : 10 * lz->ncv + 100;
  int ido = 0, info = 1; /* info = 1: use our start vector */
  lz->iparam[0] = 1;     /* exact shifts */
  lz->iparam[2] = o->maxiter > 0 ? o->maxiter : 100;
  lz->iparam[6] = 1;     /* mode 1: standard problem with our operator */
  for (;;) {
    dsaupd_c(&ido, "I", lz->n, "LA", lz->nev, tol, lz->resid, lz->ncv, lz->V, lz->n,
             lz->iparam, lz->ipntr, lz->workd, lz->workl, lz->lworkl, &info);
    if (ido != -1 && ido != 1) break;
    if (o->cancel && o->cancel(o->cancel_ud))
      return sm_error_set(err, SM_ECANCELED, "eigensolver canceled");
    if (st->nsolves >= maxsolves)
      return sm_error_set(err, SM_ENUMERIC, "Lanczos: no convergence after %d operator "
                          "applications (%d eigenpairs, %d Lanczos vectors); the problem is "
                          "ill-conditioned or the shift is far from the wanted eigenvalues",
                          st->nsolves, lz->nev, lz->ncv);
    double t0 = sm_now();
    if (apply_op(sv, lz->workd + lz->ipntr[0] - 1, lz->workd + lz->ipntr[1] - 1))
      return sm_error_set(err, SM_ENUMERIC, "sparse triangular solve failed");
    st->t_op += sm_now() - t0;
    st->nsolves++;
  }
  st->restarts = lz->iparam[2];
  if (info == 1)
    return sm_error_set(err, SM_ENUMERIC, "Lanczos: %d of %d eigenpairs converged in %d restarts",
                        lz->iparam[4], lz->nev, lz->iparam[2]);
  if (info != 0)
    return sm_error_set(err, SM_ENUMERIC, "ARPACK dsaupd failed with info = %d", info);
  dseupd_c(1, "A", lz->select, lz->d, lz->Z, lz->n, 0.0, "I", lz->n, "LA", lz->nev, tol,
           lz->resid, lz->ncv, lz->V, lz->n, lz->iparam, lz->ipntr, lz->workd, lz->workl,
           lz->lworkl, &info);
  if (info != 0)
    return sm_error_set(err, SM_ENUMERIC, "ARPACK dseupd failed with info = %d", info);
  return SM_OK;
}

/* ARPACK returns the operator's eigenvalues nu ascending; lambda = sigma + 1/nu is then
 * descending, so reverse, and undo the symmetric scaling of the eigenvectors. */
static void unpack(const lanczos *lz, const double *s, double sigma, double *evals,
                   double *evecs) {
  for (int j = 0; j < lz->nev; j++) {
    int src = lz->nev - 1 - j;
    evals[j] = sigma + 1.0 / lz->d[src];
    const double *z = lz->Z + (size_t)src * lz->n;
    double *x = evecs + (size_t)j * lz->n;
    for (int i = 0; i < lz->n; i++) x[i] = z[i] / s[i];
  }
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
  /* ncv = 2 nev + 1. A narrower space (1.3 nev) saved 15% of the solves on homerA but
   * missed one copy of an 11-fold eigenvalue of the sphere: single-vector Lanczos finds
   * repeated eigenvalues only through rounding, and needs room to do it.
   * Re-measured (homerA elastic k = 100, nev 112, one BLAS thread, load ~4): ncv/nev =
   * 1.3: 248 solves, 7 restarts; 1.5: 253, 4; 1.75: 239, 2 (1.6 s CPU against 2.3 s);
   * 2.0: 283, 2; 2.5: 281, 1. On the koala 1.75 saved nothing (281 solves either way,
   * 28.7 against 29.6 s CPU). 1.5 nev fails test_repeated_eigenvalues (icosphere k = 50),
   * so the width stays: robustness first. Even 2 nev + 1 loses a copy of an exactly
   * 10-fold eigenvalue (two identical spheres); only a block method or a deflated
   * re-check would make that safe. */
  int ncv = o->ncv > 0 ? o->ncv : 2 * o->nev + 1;
  if (ncv < o->nev + 2) ncv = o->nev + 2;
  if (ncv > n) ncv = n;

  solver sv;
  memset(&sv, 0, sizeof sv);
  sv.n = n;
  cholmod_start(&sv.c);
  sv.c.print = 0;
  sv.c.error_handler = NULL;
  set_ordering(&sv.c, o->ordering);
  double *s = malloc((size_t)n * sizeof *s);
  sv.tmp = malloc((size_t)n * sizeof *sv.tmp);
  lanczos lz;
  int rc = lanczos_alloc(&lz, n, o->nev, ncv);
  if (rc || !s || !sv.tmp) {
    rc = sm_error_set(err, SM_ENOMEM, "eigensolver: out of memory (n = %d, ncv = %d)", n, ncv);
    goto done;
  }
  for (int32_t i = 0; i < n; i++) {
    if (!(D[i] > 0)) {
      rc = sm_error_set(err, SM_ENUMERIC, "eigensolver: mass %d is %g, not positive", i, D[i]);
      goto done;
    }
    s[i] = sqrt(D[i]);
  }
  sv.s = s;
  sv.B = (cholmod_dense){.nrow = (size_t)n, .ncol = 1, .nzmax = (size_t)n, .d = (size_t)n,
                         .x = sv.tmp, .xtype = CHOLMOD_REAL, .dtype = CHOLMOD_DOUBLE};
  if ((rc = factor(&sv, A, D, o->sigma, st, err))) goto done;
  double t0 = sm_now();
  pthread_mutex_lock(&arpack_lock);
  rc = run_lanczos(&sv, &lz, o, st, err);
  pthread_mutex_unlock(&arpack_lock);
  if (!rc) unpack(&lz, s, o->sigma, evals, evecs);
  st->t_solve = sm_now() - t0;
done:
  lanczos_free(&lz);
  free(s);
  free(sv.tmp);
  cholmod_free_dense(&sv.X, &sv.c);
  cholmod_free_dense(&sv.Y, &sv.c);
  cholmod_free_dense(&sv.E, &sv.c);
  cholmod_free_factor(&sv.L, &sv.c);
  cholmod_finish(&sv.c);
  return rc;
}
