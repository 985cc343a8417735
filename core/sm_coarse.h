/* sm_coarse: the axiomatic coarse functional map from descriptors (algorithm.md §5) and the
 * orientation test of a point map.
 *
 * With C (k0 x k0) carrying LB coefficients of functions on Y to their pull-back on X
 * (C a_Y ~ a_X), minimize
 *   w_desc ||C A_Y - A_X||^2 + w_lap sum_ij C_ij^2 (lambda^Y_j - lambda^X_i)^2 / |.|
 *   + w_comm sum_f ||C O^Y_f - O^X_f C||^2 + w_orient sum_f ||C R^Y_f - s R^X_f C||^2
 * A = Phi^T M D (descriptor coefficients), O_f = Phi^T M diag(f) Phi (multiplication by
 * descriptor f, Nogneng-Ovsjanikov 2017), R_f = Phi^T M (g -> <n, grad f x grad g>) Phi
 * (orientation operator, Ren et al. 2018). s = +1 asks for an orientation-preserving map,
 * s = -1 for an orientation-reversing one (a mirror, e.g. a shape's intrinsic symmetry).
 * The energy is quadratic in C: it is minimized by conjugate gradients on its normal
 * equations, matrix-free.
 *
 * Contract: meshes (cleaned, normalized) and LB bases (gram_L == NULL) are borrowed, read
 * only; descriptor arrays are n x nd column-major (sm_desc). C is caller-provided, k0 x k0
 * column-major. Thread-safe (no shared state). Errors: SM_EINVAL, SM_ENOMEM.
 */
#ifndef SM_COARSE_H
#define SM_COARSE_H

#include <stdint.h>

#include "sm_basis.h"
#include "sm_error.h"
#include "sm_mesh.h"

typedef struct sm_coarse_opts {
  int k0;           /* LB functions used */
  int op_stride;    /* operators are built for every op_stride-th descriptor */
  double w_desc, w_lap, w_comm, w_orient;
  int orient_sign;  /* +1 preserving, -1 reversing */
  int cg_iters;     /* conjugate-gradient iterations cap */
} sm_coarse_opts;

void sm_coarse_opts_default(sm_coarse_opts *o);

typedef struct sm_coarse_side {
  const sm_mesh *mesh;
  const sm_basis *lb;
  const double *desc; /* n x nd column-major */
} sm_coarse_side;

int sm_coarse_fmap(const sm_coarse_side *x, const sm_coarse_side *y, int nd,
                   const sm_coarse_opts *o, double *C, sm_error *err);

/* The same in two steps, for callers that keep a shape's part: the operators of one side
 * depend only on that side, nd, o->k0 and o->op_stride (built in O(n k0^2 nd / stride),
 * most of a coarse map's cost), and sm_coarse_fmap_prepared solves with two of them. A
 * prepared side borrows s->lb (its eigenvalues) for its whole life and is read only once
 * built (shareable between threads). sm_coarse_fmap_prepared checks that both sides were
 * built with the k0, nd and op_stride of o (SM_EINVAL otherwise). */
typedef struct sm_coarse_prep sm_coarse_prep;
int sm_coarse_prepare(const sm_coarse_side *s, int nd, const sm_coarse_opts *o,
                      sm_coarse_prep **out, sm_error *err);
/* 1 if p was built for these options and nd, else 0. */
int sm_coarse_prep_fits(const sm_coarse_prep *p, int nd, const sm_coarse_opts *o);
void sm_coarse_prep_destroy(sm_coarse_prep *p);
int sm_coarse_fmap_prepared(const sm_coarse_prep *x, const sm_coarse_prep *y,
                            const sm_coarse_opts *o, double *C, sm_error *err);

/* Area-weighted mean, over X's faces, of the sign agreement between the image triangle
 * (T[a], T[b], T[c]) taken in Y and Y's vertex normals there: +1 = every face keeps its
 * orientation, -1 = a mirror. Faces whose image is degenerate count 0. */
double sm_map_orientation_score(const sm_mesh *X, const sm_mesh *Y, const int32_t *T);

/* Orientation features of nu scalar functions U (n x nu, column-major; e.g. the distances
 * from nu landmarks): for each pair a < b, in the order (0,1), (0,2), ..., (1,2), ..., the
 * area-weighted vertex average of the per-face <n, g_a x g_b> with g = grad u / |grad u|:
 * the sine of the angle between the two gradients, signed by the outward normal, in
 * [-1, 1]. A map that keeps the u's and the orientation keeps every feature; a mirror
 * negates them. On a human's torso with u = the distances from the head and from a hand,
 * the front reads one sign and the back the other: what tells them apart once the tips
 * are matched, which the distances alone cannot (they are symmetric front to back).
 * Faces where a gradient is zero or not finite (unreachable vertices) contribute 0.
 * out: n x nu (nu - 1) / 2, row-major (the layout of ZoomOut's fixed features), times
 * scale. Errors: SM_EINVAL (nu < 0), SM_ENOMEM. */
int sm_orientation_features(const sm_mesh *m, const double *U, int nu, double scale,
                            double *out, sm_error *err);

#endif
