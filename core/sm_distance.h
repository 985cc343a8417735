/* sm_distance: a cosine distance between two shapes, computed after matching them
 * ("correspondence stability", algorithm.md §7). In [0, 2]; 0 for a shape against itself
 * in any vertex order, scale or rigid pose (shapes are at unit area); symmetric.
 *
 * Definition (what the product ships):
 *   Features. For each vertex, the log heat kernel signature at S = 8 fixed times
 *   t_s = 10^(-3 + 2 s / (S - 1)) (s = 0..S-1, unit area), computed in the LB basis:
 *   h(v, t) = sum_i exp(-t lambda_i) phi_i(v)^2; each column is centered by its area-
 *   weighted mean, so what is compared is the pattern over the surface, not its level.
 *   Point term (X -> Y). a = the features of X at every vertex, b = the features of Y at
 *   T_xy(v), both weighted by sqrt(m_v) of X; d_xy = 1 - a.b / (|a| |b|). d_yx likewise
 *   with T_yx on Y.
 *   Spectral terms. The centered log eigenvalues log lambda_1..log lambda_K (positive
 *   eigenvalues only, K = 50 or fewer if a basis is smaller) of the LB basis, and of the
 *   elastic basis when both shapes have one: 1 - cos of the two vectors.
 *   Total = mean of d_xy, d_yx and the spectral terms present.
 *
 * Contract: shapes (sm_match.h) and maps (cleaned indices: T_xy has x's nv entries, T_yx
 * y's) are borrowed, read only. Thread-safe. Errors: SM_EINVAL, SM_ENOMEM.
 */
#ifndef SM_DISTANCE_H
#define SM_DISTANCE_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_match.h"

typedef struct sm_distance_parts {
  double point_xy, point_yx;       /* pointwise terms through each map */
  double spectrum_lb;              /* LB spectral term */
  double spectrum_elastic;         /* elastic spectral term, or -1 if not computed */
  double total;
} sm_distance_parts;

int sm_shape_distance(const sm_shape *x, const sm_shape *y, const int32_t *T_xy,
                      const int32_t *T_yx, sm_distance_parts *out, sm_error *err);

/* Adjusts matching options for a distance: both maps (want_yx), no tip search (it fires
 * on the low-confidence maps of pairs of different classes, at one match per hypothesis),
 * and no mirror check (orientation_fix = 0). The check reruns the refinement from the map composed with the
 * target's self-symmetry when the map looks mirrored: up to a second match, and it fires
 * mostly on pairs of different classes, whose maps are poor either way. Measured on
 * tosca pairs (k = 50): within-class distances unchanged; cross-class ones moved by -13%
 * to +25%, all staying far above the within-class ones; 30-60% less time on those pairs.
 * The daemon's DISTANCE and QUERY and the CLI's distance all use it, so they agree; a
 * MATCH with WANT_DISTANCE keeps the check and reports the distance of the map it returns. */
void sm_distance_match_opts(sm_match_opts *o);

/* The spectral term alone (no map needed; a cheap pre-filter for retrieval): 1 - cos of
 * the centered log positive eigenvalues of a and b, the first min(50, ...) of them. */
double sm_spectrum_distance(const sm_basis *a, const sm_basis *b);

#endif
