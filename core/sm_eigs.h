/* sm_eigs: the smallest eigenpairs of a sparse symmetric generalized problem
 *     A x = lambda D x,   A symmetric PSD (lower triangle in an sm_csc), D diagonal > 0,
 * by block shift-invert Lanczos with thick restarts and locking (block Krylov-Schur,
 * sm_eigs.c) over a sparse Cholesky factor (CHOLMOD) of K = A - sigma D, with sigma < 0
 * so that K is SPD even when A is singular.
 *
 * Why this formulation: with s = sqrt(D), the operator s K^-1 s is symmetric in the plain
 * inner product and has eigenvalues 1/(lambda - sigma), so the iteration is a standard
 * symmetric one on it (largest = smallest lambda) and the eigenvectors come back
 * D-orthonormal after scaling by 1/s. No B-inner products, no explicit inverse. Each step
 * applies the operator to a block of `block` vectors with one multi-right-hand-side
 * solve, so eigenvalues of multiplicity up to `block` are found directly.
 *
 * Contract
 *   A and D are borrowed, read only. evals (nev) and evecs (n*nev, column-major) are
 *   caller-provided outputs; eigenvalues ascending, eigenvectors D-orthonormal.
 *   Re-entrant: no global or static state (CHOLMOD runs on a cholmod_common of the call,
 *   LAPACK/BLAS on the call's buffers), so any number of calls may run in parallel on
 *   different threads; each uses the BLAS threading the caller configured, plus the
 *   threads it may borrow (spare_threads).
 *   The cancel callback (may be NULL) is polled once per block step.
 *   Problems too small for the Krylov basis (n < ncv + 2 block) are solved densely.
 *   Errors: SM_EINVAL (sizes), SM_ENOMEM, SM_ENUMERIC (K not positive definite, a LAPACK
 *   failure, or no convergence within maxiter restarts / maxsolves operator applications;
 *   the message says which and how many eigenpairs had converged), SM_ECANCELED.
 */
#ifndef SM_EIGS_H
#define SM_EIGS_H

#include <stdatomic.h>

#include "sm_error.h"
#include "sm_sparse.h"

enum { SM_ORDER_DEFAULT = 0, SM_ORDER_AMD = 1, SM_ORDER_METIS = 2, SM_ORDER_NESDIS = 3 };

typedef struct sm_eigs_opts {
  int nev;          /* eigenpairs wanted */
  double sigma;     /* shift, < smallest eigenvalue */
  double tol;       /* relative residual: ||T z - theta z|| <= tol theta (0 = 1e-9) */
  int ncv;          /* Krylov basis size before a restart (0 = automatic: 3 nev, 4 nev
                     * from n = 100,000 on, 2 nev when the factor has under 30 nonzeros
                     * per row; at least nev + 3 block, rounded up to a multiple of
                     * block) */
  int maxiter;      /* restarts (0 = automatic: 100) */
  int maxsolves;    /* operator applications, counted per vector (0 = automatic:
                     * 10 ncv + 100); with maxiter it bounds the time a failing run takes
                     * (normal runs need 1-2 ncv) */
  int ordering;     /* fill-reducing ordering: SM_ORDER_* (0 = CHOLMOD's default choice) */
  int (*cancel)(void *ud);
  void *cancel_ud;
  int block;        /* vectors per block (0 = automatic: 12, 16 from n = 100,000 on;
                     * at most 64) */
  /* Threads this call may borrow for the products with its Krylov basis (the block
   * Gram-Schmidt and the restarts' rotations, half of a large problem's time): each such
   * product takes up to SM_EIGS_MAX_PARTS - 1 from *spare_threads (atomically) for its
   * duration and gives them back, so concurrent calls may share one counter. NULL or 0:
   * the calling thread alone. The rows of those products are split into parts fixed by n
   * alone (part_rows each, at least), summed in part order: the result is the same bit
   * for bit whatever the threads. */
  _Atomic int *spare_threads;
  int part_rows;    /* rows per part at least (0 = SM_EIGS_PART_ROWS) */
} sm_eigs_opts;

#define SM_EIGS_MAX_PARTS 8
#define SM_EIGS_PART_ROWS 16384

typedef struct sm_eigs_stats {
  double t_analyze, t_factor, t_solve; /* seconds: ordering, numeric factor, iteration */
  double t_op;      /* part of t_solve spent applying the operator (triangular solves) */
  int nsolves;      /* operator applications (vectors; a block of b counts b) */
  int restarts;
  double factor_nnz;
} sm_eigs_stats;

int sm_eigs_smallest(const sm_csc *A, const double *D, const sm_eigs_opts *o, double *evals,
                     double *evecs, sm_eigs_stats *st, sm_error *err);

/* Process-wide, for programs that bound their own threads (the daemon's pool, sm_prepare's
 * thread budget, the benchmarks): turns OpenMP parallel regions off, so each runs on the
 * thread that opens it. Why: CHOLMOD's numeric factorization opens regions of
 * CHOLMOD_OMP_NUM_THREADS = 4 threads (fixed when Debian built it) whatever the caller
 * asked, so two factorizations at once put 8 threads on the cores, which then wait on each
 * other at every region's barrier. Measured on homerA elastic (load ~4, 2 cores): factor
 * 0.21-0.26 s with the teams, 0.11-0.18 s without. Call once at start-up, before other
 * threads start; the rest of this module keeps no global state. */
void sm_eigs_openmp_off(void);

/* Monotonic clock in seconds (used by timing splits across core/). */
double sm_now(void);

#endif
