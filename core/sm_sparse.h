/* sm_sparse: symmetric sparse matrices as assembled by the basis code.
 *
 * Contract
 *   Assembly appends (row, col, value) triplets of the LOWER triangle (row >= col; callers
 *   may append upper entries, they are mirrored to the lower triangle) with duplicates
 *   allowed; sm_triplets_to_csc sums duplicates into a compressed-column matrix holding
 *   the lower triangle, rows sorted within each column. Both objects own their arrays;
 *   destroy with the matching _destroy. No global state; not shared between threads.
 */
#ifndef SM_SPARSE_H
#define SM_SPARSE_H

#include <stdint.h>

#include "sm_error.h"

typedef struct sm_triplets {
  int32_t n;      /* matrix is n x n */
  int64_t len, cap;
  int32_t *row, *col;
  double *val;
} sm_triplets;

typedef struct sm_csc {
  int32_t n;
  int64_t nnz;
  int32_t *colptr; /* n+1 (int32: the CHOLMOD int interface) */
  int32_t *rowind; /* nnz */
  double *val;     /* nnz */
} sm_csc;

int sm_triplets_init(sm_triplets *t, int32_t n, int64_t cap_hint);
void sm_triplets_free(sm_triplets *t);
/* Appends one entry (mirrored to the lower triangle). SM_ENOMEM on growth failure. */
int sm_triplets_add(sm_triplets *t, int32_t i, int32_t j, double v);
/* Adds a 3x3 block B (row-major) at block position (bi, bj) (rows 3bi.., cols 3bj..);
 * entries that fall in the strict upper triangle are skipped when bi == bj, and all of
 * them are mirrored when bi < bj, so callers can add every block of a symmetric element
 * matrix exactly once per unordered pair. */
int sm_triplets_add_block3(sm_triplets *t, int32_t bi, int32_t bj, const double B[9]);

int sm_triplets_to_csc(const sm_triplets *t, sm_csc **out, sm_error *err);
void sm_csc_destroy(sm_csc *a);

/* y = A x for the symmetric matrix whose lower triangle A holds. */
void sm_csc_symv(const sm_csc *a, const double *x, double *y);

#endif
