/* sm_global: landmark-free global search for the basin of a correspondence.
 *
 * Intrinsic descriptors and the low-frequency Laplace-Beltrami functions leave a shape pair
 * with a few discrete ambiguities: the sign of each eigenfunction (one of them is the
 * left/right mirror), and, between shapes of different proportions (a gorilla and a human),
 * which descriptor configuration is trustworthy at all. A single coarse map picks one
 * basin; ZoomOut then refines it whether it is right or not. This module instead starts
 * from several hypotheses and lets an intrinsic energy (no ground truth) choose:
 *
 *   starts   every sign combination of the first k_signs non-constant LB functions
 *            (C0 = diag(s0, s1, ..., s_m), 2^m starts), plus any caller-given coarse maps
 *            (e.g. the descriptor-based one of sm_coarse);
 *   refine   each start by ZoomOut in the LB basis on farthest-point samples of both shapes
 *            (k from k_signs + 1 to k_end): a few hundred points, milliseconds per start;
 *   score    each refined hypothesis by descriptor preservation on the samples; the few
 *            best (and the caller's first start) get their full-resolution map, and the
 *            winner minimizes desc * (2 - orientation): the descriptors cannot tell a
 *            start from its mirror image, the orientation score can (sm_global_hyp).
 *
 * Contract: meshes (cleaned, unit area) and LB bases (orthonormal, gram_L == NULL) are
 * borrowed, read only. sm_global_search allocates the hypothesis array (*out, *n_out),
 * which the caller frees with sm_global_free. No global state (thread-safe on distinct
 * outputs). The cancel callback is polled between starts (SM_ECANCELED).
 * Errors: SM_EINVAL (options, bases), SM_ENOMEM, kNN and fmap errors pass through.
 */
#ifndef SM_GLOBAL_H
#define SM_GLOBAL_H

#include <stdint.h>

#include "sm_basis.h"
#include "sm_error.h"
#include "sm_mesh.h"

typedef struct sm_global_opts {
  int samples;  /* farthest-point samples per shape */
  int k_signs;  /* non-constant LB functions whose signs are enumerated (2^k_signs starts) */
  int permute;  /* also every ordering of those functions (k_signs! 2^k_signs starts) */
  int k_end;    /* LB functions at the end of each start's ZoomOut */
  int step;     /* ZoomOut k increment */
  int finalists; /* starts (lowest descriptor error) whose full map and energy are computed */
  /* Extra starts: n_extra coarse maps (k_extra x k_extra each, column-major, the sm_fmap
   * convention), tried first, in order. */
  const double *const *extra;
  int n_extra, k_extra;
  int (*cancel)(void *ud);
  void *cancel_ud;
} sm_global_opts;

void sm_global_opts_default(sm_global_opts *o);

typedef struct sm_global_side {
  const sm_mesh *mesh; /* cleaned, unit area */
  const sm_basis *lb;  /* orthonormal LB basis with at least k_end functions */
  const double *desc;  /* n x nd column-major descriptors (e.g. WKS), or NULL */
  int nd;
} sm_global_side;

typedef struct sm_global_hyp {
  int32_t *T;          /* n_X: the full point map X -> Y of a finalist, else NULL */
  double residual;     /* mean |a_i - b_T(i)|^2 of the samples in the final embedding,
                          divided by the mean |a_i|^2: how well C aligns the two shapes */
  double cycle;        /* mean distance (unit area) from an X sample to its image's image
                          under the adjoint map Y -> X: bijectivity */
  double coverage;     /* fraction of Y's sample mass hit by the X samples */
  double orientation;  /* sm_map_orientation_score of T (finalists): +1 direct, -1 mirror */
  double desc;         /* over X's samples, mass-weighted mean |d_X(i) - d_Y(T(i))|^2 /
                          mean |d_X|^2 (descriptor preservation) */
  double energy;       /* desc * (2 - orientation) for finalists, +inf otherwise */
} sm_global_hyp;

int sm_global_search(const sm_global_side *x, const sm_global_side *y,
                     const sm_global_opts *o, sm_global_hyp **out, int *n_out,
                     sm_error *err);
void sm_global_free(sm_global_hyp *h, int n);

/* The index of the hypothesis with the lowest energy (-1 when n == 0). */
int sm_global_best(const sm_global_hyp *h, int n);

#endif
