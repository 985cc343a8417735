/* sm_metrics: scoring a vertex-to-vertex map against ground truth, shared by the benchmarks
 * and the command-line tool. Spec: ../shared/design/algorithm.md §8. The reference is the
 * project's evaluator ../shared/tools/eval_map.py: every metric it reports is defined here
 * the same way (same formula, same edge cases) so the two agree to rounding.
 *
 * Contract
 *   - A map is `int32_t map[n_source]`: map[i] = target vertex (0-based) of source vertex i.
 *     Meshes are taken as READ (sm_mesh_read_file, not cleaned): the numbering the map and
 *     the GT speak of. Faces of zero area (including repeated-index faces) contribute nothing
 *     anywhere (eval_map.py would produce NaN for them); they never crash anything.
 *   - sm_gt is owned by the caller once returned; sm_gt_destroy frees it. Every other
 *     function only reads its inputs (borrowed for the call) and writes caller-allocated
 *     outputs whose size is stated. Nothing is kept after a call returns.
 *   - Threads: no global state; every function is reentrant. sm_geodesic_errors and
 *     sm_metrics_compute use up to `nthreads` threads internally (calling thread included,
 *     0 = default 2) and join them before returning.
 *   - Errors: 0 or a negative SM_E* code with a message in *err. Index files: SM_EIO,
 *     SM_EFORMAT (file:line for an unparsable line), SM_ERANGE (file:line, the index and the
 *     vertex count). Maps and GT passed to the computing functions are range-checked first
 *     (SM_ERANGE). SM_ENOMEM. No logging.
 *
 * Definitions (as eval_map.py; Y = target coordinates / sqrt(area(T)))
 *   geodesic error  e_k = d_T(map(s_k), t_k) / sqrt(area(T)) for each GT pair (s_k, t_k);
 *                   d_T = exact Dijkstra on the target's undirected edge graph (edges of the
 *                   faces, Euclidean lengths). Unreachable pairs (other component) are +inf:
 *                   mean and max are over the finite e only, the median and the fractions
 *                   count every pair (an inf is above every threshold). With no finite e,
 *                   mean and max are NaN.
 *   accuracy curve  frac(e <= t) for t = linspace(0, 0.1, 41); auc = trapezoid / 0.1.
 *   bijectivity     #distinct target vertices hit / n_target (and / min(n_source, n_target)).
 *   coverage        sum of the mixed-Voronoi (Meyer) masses of hit target vertices / sum of
 *                   all masses: sm_mesh_lumped_mass, the same rule as eval_map.py's
 *                   voronoi_mass (obtuse: A/2 and A/4; else cotangent cells).
 *   dirichlet       sum over source edges (i,j) of w_ij |Y[map i] - Y[map j]|^2 with
 *                   w_ij = (cot a + cot b)/2 of the source (one cot/2 on a boundary). Not
 *                   centred (irrelevant: only differences enter). The identity map of a
 *                   closed surface scaled to unit area gives 2 (dirichlet_source_identity).
 *   chamfer         (not in eval_map.py) for point sets A and B: mean over a in A of
 *                   min_b |a - b|, plus mean over b in B of min_a |a - b| (Euclidean, not
 *                   squared). For a map: A = {Y[map i]} (n_source points, repeats kept),
 *                   B = Y. A's points are target vertices, so the first term is 0 for a
 *                   vertex map and the value measures how far the target lies from what
 *                   the map hits, in units of sqrt(area(T)).
 *   cycle error     for T_XY and T_YX: fraction of source i with T_YX[T_XY[i]] != i.
 */
#ifndef SM_METRICS_H
#define SM_METRICS_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_mesh.h"

#define SM_METRICS_CURVE_N 41  /* thresholds 0, 0.0025, ..., 0.1 */
#define SM_METRICS_CURVE_MAX 0.1

/* Ground truth: n pairs (src[k], tgt[k]), 0-based. */
typedef struct sm_gt {
  int64_t n;
  int32_t *src;
  int32_t *tgt;
} sm_gt;

/* Loaders. Index files hold whitespace-separated numbers, '#' starts a comment, blank lines
 * are skipped; numbers may be written as floats ("7.529e+03") and are rounded to the
 * nearest integer (half to even, as numpy.rint), then `base` (0 or 1) is subtracted.
 * n_source / n_target bound the indices (SM_ERANGE naming file and line); a negative bound
 * means "not checked here" (sm_metrics_compute checks again anyway). *out is new. */

/* Line i = target vertex of source vertex i (one number per line). */
int sm_gt_load_dense(const char *path, int base, int32_t n_source, int32_t n_target,
                     sm_gt **out, sm_error *err);
/* Line j = source vertex of target vertex j. */
int sm_gt_load_inverse(const char *path, int base, int32_t n_source, int32_t n_target,
                       sm_gt **out, sm_error *err);
/* Row k of src_path and of tgt_path are the same point (TOSCA .vts, base 1). The row
 * counts must agree (SM_EFORMAT). */
int sm_gt_load_vts(const char *src_path, const char *tgt_path, int base, int32_t n_source,
                   int32_t n_target, sm_gt **out, sm_error *err);
/* Two numbers per line: "src tgt". */
int sm_gt_load_pairs(const char *path, int base, int32_t n_source, int32_t n_target,
                     sm_gt **out, sm_error *err);
/* gt(i) = i for i < n (same connectivity). */
int sm_gt_identity(int32_t n, sm_gt **out, sm_error *err);
void sm_gt_destroy(sm_gt *gt);

/* After the target is permuted so that new vertex j = old vertex perm[j], every GT target
 * index t becomes inv_perm[t] (inv_perm[perm[j]] = j, n_target entries). SM_ERANGE if a GT
 * index is outside [0, n_target); gt is unchanged then. */
int sm_gt_remap_target(sm_gt *gt, const int32_t *inv_perm, int32_t n_target, sm_error *err);

/* True (1) if the GT source indices are exactly a permutation of 0..n_source-1 (a GT
 * defined at every source vertex); fills dense[n_source] (dense[s] = t) when dense != NULL. */
int sm_gt_is_dense(const sm_gt *gt, int32_t n_source, int32_t *dense);

/* Map files: one 0-based target index per source vertex (eval_map.py's format; floats
 * accepted). Exactly n_source numbers (SM_EFORMAT otherwise), each in [0, n_target).
 * *map is malloc'd, owned by the caller. sm_map_save writes "%d\n" per entry. */
int sm_map_load(const char *path, int32_t n_source, int32_t n_target, int32_t **map,
                sm_error *err);
int sm_map_save(const char *path, const int32_t *map, int32_t n_source, sm_error *err);

/* Exact single-source shortest paths on m's edge graph (Euclidean edge lengths):
 * dist[m->nv], +inf where unreachable. m must have valid face indices (SM_ERANGE). */
int sm_mesh_edge_dijkstra(const sm_mesh *m, int32_t source, double *dist, sm_error *err);

/* The same searches from many sources on one mesh: the edge graph and the workspace are
 * built once (sm_edge_paths_create copies what it needs; m may go afterwards). A handle
 * is used by one thread at a time. run: dist[nv] from source, +inf where unreachable. */
typedef struct sm_edge_paths sm_edge_paths;
int sm_edge_paths_create(const sm_mesh *m, sm_edge_paths **out, sm_error *err);
int sm_edge_paths_run(sm_edge_paths *p, int32_t source, double *dist, sm_error *err);
int32_t sm_edge_paths_size(const sm_edge_paths *p); /* vertices of the mesh */
void sm_edge_paths_destroy(sm_edge_paths *p);

/* e[gt->n]: the geodesic errors defined above, on `target`, for a map of length n_source.
 * One Dijkstra per distinct GT target vertex (or per distinct mapped vertex when those are
 * fewer: distances are symmetric), stopped as soon as every vertex it must measure is
 * settled; the searches are shared among nthreads threads. Exact, like eval_map.py's.
 * Cost: O(#distinct * E log V) worst case (maps far from the GT), about #distinct * deg
 * for a near-perfect map. homerA -> homerB (8k target vertices), 2 threads: GT map 0.01 s,
 * GT with 20% random entries 0.4 s, constant map 0.005 s (eval_map.py: 11 s each). */
int sm_geodesic_errors(const sm_mesh *target, const int32_t *map, int32_t n_source,
                       const sm_gt *gt, int nthreads, double *e, sm_error *err);

typedef struct sm_geo_stats {
  int64_t n;      /* errors summarized */
  int64_t n_inf;  /* unreachable ones */
  double mean, median, max;               /* NaN when n == 0 (mean, max: no finite e) */
  double frac_le_0025, frac_le_005, frac_le_01;
  double curve[SM_METRICS_CURVE_N];       /* frac(e <= sm_metrics_threshold(k)) */
  double auc;                             /* trapezoid of the curve / 0.1 */
} sm_geo_stats;

/* Threshold k of the accuracy curve: k * 0.1/40 (numpy.linspace's values; the last is 0.1). */
double sm_metrics_threshold(int k);

/* Summarizes e[n] (inf allowed, NaN not: SM_EINVAL). Uses O(n) scratch (SM_ENOMEM). */
int sm_geo_summarize(const double *e, int64_t n, sm_geo_stats *out, sm_error *err);

/* Bijectivity and coverage of map (n_source entries in [0, n_target), range-checked). */
int sm_map_bijectivity(const int32_t *map, int32_t n_source, int32_t n_target,
                       double *bijectivity, double *distinct_over_min_n, sm_error *err);
int sm_map_coverage(const sm_mesh *target, const int32_t *map, int32_t n_source,
                    double *coverage, sm_error *err);

/* Fraction of i in [0, nx) with t_yx[t_xy[i]] != i (t_xy: nx entries in [0, ny); t_yx: ny
 * entries in [0, nx); range-checked). */
int sm_map_cycle_error(const int32_t *t_xy, int32_t nx, const int32_t *t_yx, int32_t ny,
                       double *frac, sm_error *err);

/* Chamfer terms for A[3*na] and B[3*nb] (both non-empty): *a_to_b = mean_a min_b |a-b|,
 * *b_to_a = mean_b min_a |a-b|; the chamfer distance is their sum. Exact nearest
 * neighbours from a k-d tree: O((na + nb) log) for surface samples (50k in ~0.1 s). */
int sm_chamfer(const double *A, int64_t na, const double *B, int64_t nb, double *a_to_b,
               double *b_to_a, sm_error *err);

/* Dirichlet energy of map (source -> target, defined above). target == NULL and map ==
 * NULL give the identity on the source scaled to unit area (dirichlet_source_identity). */
int sm_map_dirichlet(const sm_mesh *source, const sm_mesh *target, const int32_t *map,
                     double *energy, sm_error *err);

typedef struct sm_metrics {
  int32_t n_source, n_target;
  double area_target;
  sm_geo_stats geo;           /* geo.n = 0 and NaN fields when gt == NULL */
  double bijectivity, distinct_over_min_n, coverage;
  double chamfer, chamfer_map_to_target, chamfer_target_to_map;
  double dirichlet, dirichlet_source_identity;
  double dirichlet_gt;        /* the GT map's energy if the GT is dense, else NaN */
  double geodesic_seconds;    /* wall time of the geodesic errors */
} sm_metrics;

/* Everything above for map (source->nv entries) on raw source/target meshes. gt may be
 * NULL (no geodesic metrics). Meshes are validated first (sm_mesh_validate). */
int sm_metrics_compute(const sm_mesh *source, const sm_mesh *target, const int32_t *map,
                       const sm_gt *gt, int nthreads, sm_metrics *out, sm_error *err);

#endif
