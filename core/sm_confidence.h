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
 * Geodesic distortion (sm_map_turns): how far T is from an isometry, measured on
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

/* Geodesic directions at sample vertices. At sample c, the direction toward sample a is
 * minus the gradient of the edge-path distance from a, fitted by least squares over the
 * vertices within SM_DIR_RADIUS (Euclidean, unit area) whose normal is within 60 degrees
 * of c's, in c's tangent plane: two coordinates in a frame fixed by c's outward normal.
 * sm_dir_probe_create keeps the neighbourhoods and frames of the samples `at` (the mesh
 * is borrowed for the probe's life); sm_dir_probe_eval writes dir[2 c] for every sample c
 * from one distance field. A probe is read only after creation (shareable). */
#define SM_DIR_RADIUS 0.1
typedef struct sm_dir_probe sm_dir_probe;
int sm_dir_probe_create(const sm_mesh *m, const int32_t *at, int na, sm_dir_probe **out,
                        sm_error *err);
void sm_dir_probe_eval(const sm_dir_probe *p, const double *field, double *dir);
void sm_dir_probe_destroy(sm_dir_probe *p);

/* Orientation of T seen at the scale of body parts: for each sample c and pairs of other
 * samples a, b within half of the largest sample distance, the turn from the direction
 * toward a to the direction toward b (sign of their 2D cross product, outward normal up) on
 * X, and at T(c) toward T(a), T(b) on Y. A mirror reverses every turn, a map that is right
 * at large scale keeps most of them even when it is noisy from triangle to triangle (where
 * sm_map_orientation_score reads about 0 between species). Turns of nearly collinear
 * directions (|sin| < 0.3) are skipped. Result: the mean agreement, in [-1, 1] (0 when no
 * turn qualifies). T has n_X entries; src are ns samples of X with pairwise distances
 * src_dist (row-major, leading dimension ld >= ns) and directions dir_x[2 (c ns + a)]
 * (sm_dir_probe_eval per source field); the Y side is measured here with one path search
 * (paths_y, on Y) per sample, which also gives the geodesic distortion (*distortion). */
int sm_map_turns(sm_edge_paths *paths_y, const sm_mesh *Y, const int32_t *T,
                 const int32_t *src, const double *src_dist, const double *dir_x, int ns,
                 int ld, double *distortion, double *turns, sm_error *err);

/* How well T carries a scalar field: the correlation, weighted by X's vertex masses, of
 * f_x(i) and f_y(T(i)) over X's vertices, in [-1, 1] (0 when either side is constant).
 * With f = the smoothed mean curvature (sm_mean_curvature), a half turn about a body's
 * axis (front onto back, left onto right: orientation kept, so the turns cannot see it)
 * reads lower than the right map: it puts a chest, a face or toes where the other shape
 * is flat or hollow. */
double sm_map_field_agreement(const double *fx, const double *fy, const double *mass_x,
                              int32_t nx, const int32_t *T);

#endif
