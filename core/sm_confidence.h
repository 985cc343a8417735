/* sm_confidence: how far a point map can be trusted, from the two shapes and the maps alone
 * (no ground truth). A correct map between two surfaces is, at the scale of the field's
 * failure threshold, (a) orientation preserving, (b) continuous: neighbouring vertices land
 * near each other, and (c) invertible: the adjoint map Y -> X brings every vertex back near
 * where it started. A map that landed in a wrong basin breaks at least one of them: a mirror
 * reverses orientation, a swapped limb leaves a seam where the map jumps, a collapsed or
 * scrambled map is neither continuous nor invertible.
 *
 *   orientation  sm_map_orientation_score(X, Y, T), in [-1, 1]
 *   continuity   1 - the mass fraction of X's vertices with an incident edge whose image is
 *                longer than tau (jumps across the target)
 *   cycle        the mass fraction of X's vertices i with |x_i - x_{T_yx(T(i))}| <= tau
 *   confidence   max(0, orientation) * continuity * cycle, in [0, 1]
 * with tau = SM_CONFIDENCE_TAU in units of sqrt(area) (both meshes at unit area: the
 * field's threshold for a failed correspondence, 0.1). A correct self-map scores 1 on each
 * factor; a scrambled map scores near 0 on each.
 *
 * Geodesic distortion (sm_map_distortion): how far T is from an isometry, measured on
 * samples s_a of X with edge-path distances d (unit area):
 *   sum_{a != b} |d_X(s_a, s_b) - d_Y(T s_a, T s_b)| / sum_{a != b} d_X(s_a, s_b)
 * 0 for an isometry, about 0.08-0.12 for right maps between two people, 0.2-0.5 when a
 * limb or the whole body landed in a wrong basin (a swapped leg stretches every distance
 * from it). A mirror is an isometry of a symmetric shape: the distortion cannot see it,
 * the orientation can. Pairs of samples in different components of either shape are
 * left out. Not part of the confidence (it costs a path search per sample); sm_match's
 * tip search uses it to choose among its maps.
 *
 * Contract: meshes (cleaned, normalized to unit area) and maps are borrowed, read only;
 * mass is X's lumped vertex mass (n_X). No global state, thread-safe, except that a
 * sm_edge_paths handle serves one thread at a time.
 * Errors: SM_EINVAL (missing argument), SM_ERANGE (a map entry out of range), SM_ENOMEM.
 */
#ifndef SM_CONFIDENCE_H
#define SM_CONFIDENCE_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_mesh.h"
#include "sm_metrics.h"

#define SM_CONFIDENCE_TAU 0.1

typedef struct sm_confidence {
  double orientation, continuity, cycle, confidence;
} sm_confidence;

int sm_map_confidence(const sm_mesh *X, const sm_mesh *Y, const double *mass_x,
                      const int32_t *T, const int32_t *T_yx, sm_confidence *out,
                      sm_error *err);

/* Distortion of T (n_X entries) over the ns samples src of X whose pairwise distances are
 * src_dist (row-major, leading dimension ld >= ns); paths_y searches Y (sm_metrics.h). */
int sm_map_distortion(sm_edge_paths *paths_y, const int32_t *T, const int32_t *src,
                      const double *src_dist, int ns, int ld, double *out, sm_error *err);

#endif
