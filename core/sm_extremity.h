/* sm_extremity: the tips of a shape (head, hands, feet, tail, ears) and the hypotheses of
 * how the tips of two shapes correspond: a landmark-free global start for sm_match on
 * pairs where the descriptors alone lead to a wrong basin (different species, proportions
 * and poses).
 *
 *   Tips: local maxima of the average geodesic distance (AGD, the mean edge-path distance
 *     to SM_EXT_SOURCES farthest-point samples) that are the largest AGD within geodesic
 *     radius SM_EXT_RADIUS of themselves (unit-area shapes) and above SM_EXT_MIN_AGD times
 *     the shape's mean AGD. AGD is a pose-invariant
 *     "how far out" measure; tips are where limbs end.
 *   Hypotheses: injective assignments of min(nx, ny, SM_EXT_ASSIGN) tips, scored by how
 *     well they keep the tips' normalized AGD, their pairwise geodesic distances and the
 *     order of where the paths between them part (Gromov products); the
 *     lowest costs come first. A bilaterally symmetric shape gives several near-equal
 *     costs (left/right swaps): the caller refines each and decides by an energy of the
 *     refined maps (sm_match: the confidence).
 *
 * Contract
 *   sm_ext_detect reads the mesh (borrowed) and returns a malloc'd set the caller frees
 *   with sm_ext_destroy; it keeps no pointer to the mesh. Pure functions otherwise;
 *   thread-safe on distinct outputs. Errors: SM_ENOMEM, SM_EINVAL (null arguments), and
 *   what sm_metrics' path search reports for broken faces.
 */
#ifndef SM_EXTREMITY_H
#define SM_EXTREMITY_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_mesh.h"

#define SM_EXT_MAX 10     /* tips kept per shape, by decreasing AGD */
#define SM_EXT_ASSIGN 6   /* tips assigned per hypothesis, at most */
#define SM_EXT_SOURCES 32 /* farthest-point samples of the AGD */
#define SM_EXT_RADIUS 0.2 /* suppression radius, unit-area geodesic units */
/* A tip's AGD is at least this fraction of the shape's mean AGD: an extremity lies farther
 * out than the average point. Two local AGD maxima at 0.85 on 8_woman_07's trunk otherwise
 * took the places of her head in every assignment with a gorilla (all 3 such pairs wrong,
 * error 0.72-0.74; with the bound a right assignment is among the first 4 on all 45
 * gorilla -> human pairs, 42 before). The lowest real tip on the 41 shapes of
 * ../shared/data's tosca sets is a gorilla's brow at 0.997; heads are at 1.0-1.2, limb
 * ends at 1.2-1.7. */
#define SM_EXT_MIN_AGD 0.95

typedef struct sm_ext_set {
  int n;                          /* tips found, <= SM_EXT_MAX */
  int32_t v[SM_EXT_MAX];          /* their vertices */
  double agd[SM_EXT_MAX];         /* their AGD / the mean AGD of the shape */
  double dist[SM_EXT_MAX][SM_EXT_MAX]; /* pairwise geodesic distances / the mean AGD;
                                          +inf between components */
  /* The AGD's farthest-point sources and their pairwise edge-path distances (unit area,
   * not divided by the mean AGD; +inf between components): samples on which a map's
   * geodesic distortion is measured (sm_map_turns). */
  int32_t src[SM_EXT_SOURCES];
  double src_dist[SM_EXT_SOURCES][SM_EXT_SOURCES];
  /* src_dir[c][a]: the geodesic direction at source c toward source a, in c's tangent
   * frame (sm_dir_probe, sm_confidence.h): what sm_map_turns compares a map's turns with. */
  double src_dir[SM_EXT_SOURCES][SM_EXT_SOURCES][2];
} sm_ext_set;

typedef struct sm_ext_hypothesis {
  double cost; /* mean |AGD difference| + mean |pairwise distance difference| + the
                  fraction of Gromov-product comparisons reversed (sm_extremity.c) */
  int m;       /* tips assigned */
  int32_t pairs[2 * SM_EXT_ASSIGN]; /* (vertex of X, vertex of Y) per tip */
} sm_ext_hypothesis;

int sm_ext_detect(const sm_mesh *m, sm_ext_set **out, sm_error *err);
void sm_ext_destroy(sm_ext_set *s);

/* The max_h cheapest hypotheses, cheapest first, into out[max_h]; *nh = how many (0 when
 * either shape has fewer than 3 tips: too few to fix a correspondence). */
int sm_ext_hypotheses(const sm_ext_set *x, const sm_ext_set *y, int max_h,
                      sm_ext_hypothesis *out, int *nh, sm_error *err);

#endif
