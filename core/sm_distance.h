/* sm_distance: a distance between two shapes, computed after matching them
 * ("correspondence stability", algorithm.md §7). In [0, 2) (the shipped definition: [0, 1));
 * 0 for a shape against itself in any vertex order, scale or rigid pose (shapes are at unit
 * area); symmetric.
 *
 * Shipped definition (issue 11; docs/RESULTS.md section 3 has the measurements):
 *   total = (S + w (M_xy + M_yx) / 2) / (1 + w), w = map_weight = SM_DIST_MAP_WEIGHT = 1,
 *   each term reported as 1 - exp(-term) (same order, equal to first order, < 1).
 *   Spectral term S. With r_i = log(lambda_i(X) / lambda_i(Y)) over i = 1..K (K = 70, or
 *   fewer if a basis is smaller), the non-zero LB eigenvalues in order, and m their mean:
 *   S = sqrt(mean_i (r_i - m)^2 + beta m^2), beta = level_weight = SM_DIST_LEVEL_WEIGHT = 0
 *   (sm_spectrum_ratio_distance). Isometry-invariant, so blind to pose; with beta = 0 also
 *   scale-invariant: the shapes' relative size comes from the spectrum itself, not from
 *   the mesh area. Why: the level m measures the spectrum against the area the mesh
 *   reports, and surface perturbations that leave the shape alone move it (normal noise of
 *   0.2 edge lengths inflates the area and lifts every log eigenvalue by ~0.03, the
 *   quadric decimation to 40% lifts the high ones by FEM error), by as much as the level
 *   separating tosca's three human classes (0.015-0.025). K and beta were chosen by a
 *   held-out check (bench/eval/spectral_study.py); K = 60..80 is a plateau.
 *   Map terms M_xy, M_yx. Per vertex v of X, the RMS over the 4 smallest of 8 times
 *   t_s = 10^(-3 + 2s/7) (10^-3 .. 7.2 10^-3) of c_X(v, t) - c_Y(T_xy(v), t), c = log h
 *   minus its area-weighted mean over the shape, h the heat kernel signature in the LB basis
 *   (h(v, t) = sum_i exp(-t lambda_i) phi_i(v)^2); M_xy = its area-weighted MEDIAN over X,
 *   so the vertices a map gets wrong (up to half the area) cannot move it. M_yx likewise
 *   through T_yx. Centered like S is scale-blind (noise lifts every log h alike); small
 *   times only: they measure each part's local shape, which a stretch or a change of pose
 *   keeps better than the larger times, which see how the parts sit in the whole.
 *   Chosen by a held-out check (bench/eval/map_term_study.py, maps of this distance
 *   preset, then with the Sinkhorn start on every vertex): picked on the 40 classified
 *   shapes and the suite's 40 deformed queries, it keeps S's leave-one-out (0.975) and
 *   80/20 and lifts 70/30 (0.969 -> 0.975), mAP (0.939 -> 0.968) and the 1.2x stretched
 *   queries (6 -> 7 of 8); on 160 held-out deformed queries it is right for 152 (S alone
 *   143, ShapeDNA 133), never fewer than S for a deformation. With the preset's maps now
 *   (the start on samples, below): 70/30 0.972, mAP 0.969, the 1.4x stretched queries
 *   6 -> 7 of 8, the held-out 152. The raw (not centered), all-times, larger-times, mean
 *   and quartile variants and w = 0.5, 2 were measured too (the table in RESULTS.md).
 *   spectrum_elastic = -1 (the elastic spectrum separated the classes worse: 0.75 LOO).
 *   The maps are the LB basis' (sm_distance_match_opts): the term compares LB heat
 *   signatures, which a map refined in that basis aligns; the elastic basis' maps weighted
 *   in lowered the leave-one-out accuracy to 0.95 (RESULTS.md section 3).
 *
 * Paper-style definition (SM_DIST_PAPER; the shipped one before issue 11): features = the
 * log HKS above, each column centered by its area-weighted mean; point term X -> Y =
 * 1 - cos of X's features and Y's features pulled back through T_xy, weighted by the
 * area of X's vertices; spectral terms = 1 - cos of the centered log eigenvalues (first 50
 * non-zero) of the LB basis and of the elastic basis when both shapes have one; total =
 * mean of d_xy, d_yx and the spectral terms present.
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

enum sm_distance_def {
  SM_DIST_SHIPPED = 0, /* the definition above */
  SM_DIST_PAPER = 1    /* the paper-style definition shipped before issue 11 (below) */
};
#define SM_DIST_MAP_WEIGHT 1.0
#define SM_DIST_MATCH_K 50
#define SM_DIST_LEVEL_WEIGHT 0.0

typedef struct sm_distance_opts {
  int def;           /* enum sm_distance_def */
  double map_weight;   /* shipped: w, the map term's weight (>= 0; 0 = spectrum only) */
  int spectrum_k;      /* shipped: K, eigenvalues compared (<= 0: all both shapes have) */
  double level_weight; /* shipped: beta, the weight of the mean log ratio (>= 0) */
} sm_distance_opts;

void sm_distance_opts_default(sm_distance_opts *o);

/* The shipped definition (sm_distance_opts_default). */
int sm_shape_distance(const sm_shape *x, const sm_shape *y, const int32_t *T_xy,
                      const int32_t *T_yx, sm_distance_parts *out, sm_error *err);
/* Either definition; o NULL = defaults. */
int sm_shape_distance_ex(const sm_shape *x, const sm_shape *y, const int32_t *T_xy,
                         const int32_t *T_yx, const sm_distance_opts *o,
                         sm_distance_parts *out, sm_error *err);

/* Adjusts matching options for a distance: the LB basis (above), the refinement up to
 * k1 = SM_DIST_MATCH_K = 50 without soft Sinkhorn steps (sinkhorn_levels = 0), and the
 * Sinkhorn start's transport on the refinement's 2,000 farthest-point samples
 * (init_samples = 1; its map still on every vertex). The samples halve the start (median
 * over 28 tosca 5k pairs, one thread: 0.164 -> 0.077 s; the whole match 0.253 -> 0.168
 * s) and the distance stays as good: map_term_study on those maps, the same definition:
 * LOO 0.975, 80/20 0.975 / 0.967, mAP 0.968 -> 0.969, the suite's deformed queries
 * 7 6 7 7 6 -> 7 7 7 7 6 (stretch 1.4 gains one), the 160 held-out ones 152 -> 152,
 * 70/30 0.975 / 0.973 -> 0.972 / 0.970 (one human query in a few of the random splits);
 * the nearest-neighbour start measured the same (0.972 on 70/30, 152) at 0.123 s. A
 * caller who asked for other values (basis, init, k, Sinkhorn steps) applies them
 * afterwards. Also both maps (want_yx), no tip search (it fires
 * on the low-confidence maps of pairs of different classes, at one match per hypothesis),
 * no bijective pass (about 40% more CPU per pair; the map term was chosen on maps made
 * without it, and its median ignores the vertices it would fix), and no mirror check
 * (orientation_fix = 0). The check reruns the refinement from the map composed with the
 * target's self-symmetry when the map looks mirrored: up to a second match, and it fires
 * mostly on pairs of different classes, whose maps are poor either way. Measured on
 * tosca pairs (k = 50): within-class distances unchanged; cross-class ones moved by -13%
 * to +25%, all staying far above the within-class ones; 30-60% less time on those pairs.
 * The daemon's DISTANCE and QUERY and the CLI's distance all use it, so they agree; a
 * MATCH with WANT_DISTANCE keeps the check and reports the distance of the map it returns. */
void sm_distance_match_opts(sm_match_opts *o);

/* The shipped spectral term (spectrum_lb of sm_shape_distance with default options), from
 * the LB bases alone, no map needed: QUERY's prefilter. */
double sm_shape_spectral_term(const sm_shape *x, const sm_shape *y);

/* 1 when the shipped total depends on the maps (default map weight > 0); 0 when it is
 * the spectral term alone, so a ranking by sm_shape_spectral_term is already exact. */
int sm_distance_uses_maps(void);

/* The paper-style spectral term: 1 - cos of the centered log positive eigenvalues of a and
 * b, the first min(50, ...) of them. */
double sm_spectrum_distance(const sm_basis *a, const sm_basis *b);

/* The shipped spectral term before squashing: with r_i = log(lambda_i(a) / lambda_i(b))
 * over i = 1..K, non-zero eigenvalues in order (K <= 0 or above what both have: all of
 * them), and m their mean: sqrt(mean (r_i - m)^2 + level m^2). level = 1: the RMS of r_i
 * (the definition shipped before the robustness study), 0: scale-invariant. Bases of
 * shapes at unit area (sm_mesh_normalize) when level > 0; >= 0. */
double sm_spectrum_ratio_distance(const sm_basis *a, const sm_basis *b, int K, double level);

#endif
