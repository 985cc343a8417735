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
 * Contract: meshes (cleaned, normalized to unit area) and maps are borrowed, read only;
 * mass is X's lumped vertex mass (n_X). No global state, thread-safe.
 * Errors: SM_EINVAL (missing argument), SM_ERANGE (a map entry out of range), SM_ENOMEM.
 */
#ifndef SM_CONFIDENCE_H
#define SM_CONFIDENCE_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_mesh.h"

#define SM_CONFIDENCE_TAU 0.1

typedef struct sm_confidence {
  double orientation, continuity, cycle, confidence;
} sm_confidence;

int sm_map_confidence(const sm_mesh *X, const sm_mesh *Y, const double *mass_x,
                      const int32_t *T, const int32_t *T_yx, sm_confidence *out,
                      sm_error *err);

#endif
