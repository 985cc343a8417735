/* sm_eigs: the smallest eigenpairs of a sparse symmetric generalized problem
 *     A x = lambda D x,   A symmetric PSD (lower triangle in an sm_csc), D diagonal > 0,
 * by shift-invert Lanczos (ARPACK dsaupd) over a sparse Cholesky factor (CHOLMOD) of
 * K = A - sigma D, with sigma < 0 so that K is SPD even when A is singular.
 *
 * Why this formulation: with s = sqrt(D), the operator s K^-1 s is symmetric in the plain
 * inner product and has eigenvalues 1/(lambda - sigma), so ARPACK runs in its standard
 * mode on it ('LA' = largest algebraic = smallest lambda) and the eigenvectors come back
 * D-orthonormal after scaling by 1/s. No B-inner products, no explicit inverse.
 *
 * Contract
 *   A and D are borrowed, read only. evals (nev) and evecs (n*nev, column-major) are
 *   caller-provided outputs; eigenvalues ascending, eigenvectors D-orthonormal.
 *   ARPACK keeps state in Fortran SAVE variables and is not re-entrant: calls are
 *   serialized by a process-wide mutex inside this module (CHOLMOD factorization runs
 *   outside it). The cancel callback (may be NULL) is polled every iteration.
 *   Errors: SM_EINVAL (sizes), SM_ENOMEM, SM_ENUMERIC (K not positive definite, ARPACK
 *   failure or no convergence within maxiter restarts / maxsolves operator applications;
 *   the message says which), SM_ECANCELED.
 */
#ifndef SM_EIGS_H
#define SM_EIGS_H

#include "sm_error.h"
#include "sm_sparse.h"

enum { SM_ORDER_DEFAULT = 0, SM_ORDER_AMD = 1, SM_ORDER_METIS = 2, SM_ORDER_NESDIS = 3 };

typedef struct sm_eigs_opts {
  int nev;          /* eigenpairs wanted */
  double sigma;     /* shift, < smallest eigenvalue */
  double tol;       /* ARPACK relative tolerance (0 = 1e-9) */
  int ncv;          /* Lanczos vectors (0 = automatic) */
  int maxiter;      /* restarts (0 = automatic: 100) */
  int maxsolves;    /* operator applications (0 = automatic: 10 ncv + 100); with maxiter
                     * it bounds the time a failing run takes (normal runs need 1-2 ncv) */
  int ordering;     /* fill-reducing ordering: SM_ORDER_* (0 = CHOLMOD's default choice) */
  int (*cancel)(void *ud);
  void *cancel_ud;
} sm_eigs_opts;

typedef struct sm_eigs_stats {
  double t_analyze, t_factor, t_solve; /* seconds: ordering, numeric factor, Lanczos */
  double t_op;      /* part of t_solve spent applying the operator (triangular solves) */
  int nsolves;      /* operator applications */
  int restarts;
  double factor_nnz;
} sm_eigs_stats;

int sm_eigs_smallest(const sm_csc *A, const double *D, const sm_eigs_opts *o, double *evals,
                     double *evecs, sm_eigs_stats *st, sm_error *err);

/* Monotonic clock in seconds (used by timing splits across core/). */
double sm_now(void);

#endif
