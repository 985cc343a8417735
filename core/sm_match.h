/* sm_match: the SRE-FMaps matching pipeline (algorithm.md §4-6) on prepared shapes.
 *
 *   prepare (per shape, cacheable): clean -> normalize to unit area -> LB basis -> elastic
 *     basis -> WKS descriptors.
 *   match (per pair): coarse LB functional map from descriptors with the orientation term
 *     -> initial point map (nearest neighbour, or sparse Sinkhorn, between the aligned
 *     spectral embeddings) -> soft Sinkhorn steps and ZoomOut refinement in the lb,
 *     elastic or hybrid basis (both on farthest-point samples, the last ZoomOut iteration
 *     on every vertex) ->
 *     point map X -> Y (and Y -> X), final functional map, orientation score.
 *   multi-start (option, off by default): the refinement is also run from the other initial map (nn
 *     if sinkhorn, and vice versa; on a second thread) and the map with the lower Dirichlet
 *     energy wins. ZoomOut
 *     converges to a local optimum; a start that lands a limb on its symmetric twin ends
 *     with a seam where the map jumps, which the Dirichlet energy sees (homer A -> B:
 *     6.8 for the right map, 59-77 for maps with a swapped limb; no ground truth used).
 *
 *   global (option, off by default; sm_global.h): before the refinement, the descriptor
 *     coarse map and the sign starts of the low LB functions are each refined on samples
 *     and the winner of an intrinsic energy becomes the initial map. Off because, measured
 *     with bench_hard, it did not beat the single start on average (docs/RESULTS.md 6).
 *   tip search (default: when the map's confidence is below ext_below; sm_extremity.h):
 *     the tips of both shapes (head, hands, feet, tail) are found from the average geodesic
 *     distance; each of the ext_hypotheses cheapest tip assignments becomes the landmarks
 *     of a full match (refined with the tips' orientation features, so that the map does
 *     not twist between them), and of those maps and the first one the most continuous,
 *     least distorted and best turn-keeping (sm_map_turns: mirrors reverse turns) whose
 *     smoothed mean curvatures agree best (a half turn, front onto back, keeps the turns
 *     and loses the curvature) is kept.
 *     The descriptor start is right on near-isometric pairs and wrong, with a low
 *     confidence, between species (gorilla -> human); the tips put such a pair in the
 *     right basin. Costs one match per hypothesis, so only doubtful maps pay for it;
 *     SM_EXT_ALWAYS also searches confident ones (exhaustive mode), SM_EXT_OFF never.
 *   landmark anchoring (landmarks given, or the kept tip hypothesis): the landmarks' heat
 *     kernels are fixed features of every point assignment of the refinement
 *     (sm_zoomout_opts.feat_*, weight opts.anchor), so the map keeps them instead of
 *     drifting once they have started it; beside them, one orientation feature per
 *     landmark pair (sm_orientation_features of their distances, weight
 *     opts.anchor_orient), which tells the front of a torso or limb from its back where
 *     the heat kernels are symmetric. The tip search judges its maps unanchored (an
 *     anchored wrong assignment looks as continuous as a right one) and refines the kept
 *     one again from itself, anchored by the tips that map confirms, keeping the anchored
 *     map when the judge scores it at least as well (sm_match.c: confirmed_tips,
 *     anchored).
 *   bijective pass (default on; opts.bijective = its weight, 0 = off): the kept map is
 *     refined once more, ZoomOut from k0 in its bijective form (sm_fmap.h: the Y -> X map
 *     is fitted too and both point maps come from one nearest-neighbour problem), in the
 *     hybrid basis when the refinement basis is elastic (opts.final_hybrid). Tip
 *     hypotheses are judged before it; only the kept map pays for it. The LB functions
 *     weigh SM_MATCH_FINAL_LB_WEIGHT there: more weight serves human pairs and costs the
 *     cartoon heads, which need the elastic basis. So a doubtful map is refined at both
 *     weights and the more confident result kept (opts.final_choice): the pipeline
 *     chooses by the confidence, not by a per-dataset switch.
 *   confidence (every result; sm_confidence.h): max(0, orientation) x continuity x cycle
 *     consistency of the final maps, in [0, 1], from the shapes and maps alone.
 *
 * Contract
 *   sm_shape_prepare copies what it needs from the input mesh (borrowed) and returns a
 *   shape owned by the caller (sm_shape_destroy). Shapes are read only afterwards (except
 *   their internally locked cache of per-shape values): one shape may be used by several
 *   concurrent sm_match calls. sm_match writes a result the
 *   caller releases with sm_match_result_free. Vertex indices in results are those of the
 *   cleaned meshes (shape->mesh); sm_match_to_input translates a map to the caller's
 *   numbering (mesh->to_input), -1 for input vertices cleaning dropped (unreferenced).
 *   The cancel callback is polled inside every long loop (SM_ECANCELED).
 *   Errors: as the modules used (SM_EINVAL for options, with a message).
 */
#ifndef SM_MATCH_H
#define SM_MATCH_H

#include <stdint.h>

#include "sm_basis.h"
#include "sm_error.h"
#include "sm_mesh.h"

enum sm_match_basis { SM_MATCH_LB = 1, SM_MATCH_ELASTIC = 2, SM_MATCH_HYBRID = 3 };
enum sm_match_init { SM_INIT_NN = 1, SM_INIT_SINKHORN = 2 };
enum sm_match_ext { SM_EXT_OFF = 0, SM_EXT_WHEN_DOUBTFUL = 1, SM_EXT_ALWAYS = 2 };
#define SM_MATCH_EXT_BELOW 0.6 /* see "tip search" above and sm_match.c */
#define SM_MATCH_EXT_MAX_H 12
#define SM_MATCH_FINAL_LB_WEIGHT 0.5 /* the LB functions' weight in the hybrid final pass */
#define SM_MATCH_ANCHOR 3.0       /* see "landmark anchoring" above and sm_match.c */
#define SM_MATCH_ANCHOR_ORIENT 3.0 /* the same, for the landmarks' orientation features */
#define SM_MATCH_HYP_ORIENT 1.0   /* the tip hypotheses' orientation features (sm_match.c) */
#define SM_MATCH_CURV_WEIGHT 8.0  /* the judge's curvature agreement term (sm_match.c) */
#define SM_MATCH_CURV_PASSES 10   /* its smoothing passes per 5,000 vertices */

typedef struct sm_shape_opts {
  int k_lb;        /* LB functions (descriptors, coarse map, lb/hybrid refinement) */
  int k_elastic;   /* elastic functions; 0 = no elastic basis */
  double eta;      /* bending weight */
  int n_desc;      /* WKS energies */
  int (*cancel)(void *ud);
  void *cancel_ud;
  /* When set, sm_shape_prepare is sm_prepare(input, prep, out, prep_info) and the fields
   * above are ignored: how sm_prepare_multires hands its specs and hooks to the coarse
   * level (sm_prepare.h). */
  const struct sm_prep_opts *prep;
  struct sm_prep_info *prep_info;
} sm_shape_opts;

typedef struct sm_shape {
  sm_mesh *mesh;     /* cleaned, unit area */
  sm_basis *lb;
  sm_basis *elastic; /* NULL when k_elastic = 0 */
  double *desc;      /* n x n_desc column-major WKS */
  int n_desc;
  double t_clean, t_lb, t_elastic, t_desc; /* seconds */
  /* Values that depend only on this shape (ZoomOut's farthest-point samples, the coarse
   * map's operators), computed by the first sm_match that needs them and kept until
   * sm_shape_destroy; internally locked, so sharing a shape between threads stays safe.
   * Created by sm_shape_assemble; NULL = nothing is cached. */
  struct sm_shape_cache *cache;
} sm_shape;

void sm_shape_opts_default(sm_shape_opts *o);
/* sm_prepare (sm_prepare.h) with the specs of k_lb, k_elastic and eta, or with *o->prep. */
int sm_shape_prepare(const sm_mesh *input, const sm_shape_opts *o, sm_shape **out,
                     sm_error *err);
/* Adopts already computed parts (e.g. bases loaded from a cache): takes ownership of mesh,
 * lb and elastic (may be NULL), computes the descriptors. */
int sm_shape_assemble(sm_mesh *mesh, sm_basis *lb, sm_basis *elastic, int n_desc,
                      sm_shape **out, sm_error *err);
void sm_shape_destroy(sm_shape *s);

struct sm_match_result;

typedef struct sm_match_opts {
  int basis;        /* enum sm_match_basis (default elastic) */
  int init;         /* enum sm_match_init (default sinkhorn) */
  int k0, k1, step; /* refinement schedule */
  int coarse_k;     /* LB functions of the coarse map */
  int sinkhorn_k;   /* sparse kernel: neighbours per point and direction */
  int sinkhorn_levels; /* refinement variant: this many k-steps carried by the Sinkhorn
                          plan (soft) before the hard ZoomOut; 0 = off (default 2) */
  int samples;      /* farthest-point samples for intermediate refinement iterations */
  int init_samples; /* 1: the Sinkhorn start's transport on those samples (cell masses as
                       marginals; every vertex when a shape has no cached samples or no
                       more vertices than samples), its map still on every vertex; 0
                       (default): on every vertex */
  double bijective; /* the bijective pass's weight (see above); default 1, 0 = off */
  int final_hybrid; /* 1 (default): with the elastic basis, the bijective pass refines in
                       the hybrid basis (LB functions beside the elastic ones) */
  int final_choice; /* 1 (default): a doubtful map (the one the tip search ran for) also
                       gets the hybrid pass with LB weight 1, and the more confident of the
                       two maps is kept (see "bijective pass" above); 0 = one pass */
  int orientation_fix; /* try the other orientation when the result looks mirrored */
  int multi_start;  /* also refine from the other init, keep the smoother map (see below) */
  int global;       /* 1: global hypothesis search (see above); 2: also orderings */
  int extremities;  /* tip search (see above): 0 off, 1 when the map's confidence is below
                       ext_below (default), 2 always */
  double ext_below; /* default SM_MATCH_EXT_BELOW */
  int ext_hypotheses; /* tip assignments refined, at most SM_MATCH_EXT_MAX_H (default 4) */
  double anchor;    /* with landmarks (or the kept tips): weight of their heat kernels as
                       fixed features of the refinement's point assignments (0 = they only
                       start the map; default SM_MATCH_ANCHOR) */
  double anchor_orient; /* with landmarks (or the kept tips): weight of their orientation
                       features (sm_orientation_features of the landmarks' edge-path
                       distances, one per landmark pair) beside the heat kernels; 0 = off;
                       default SM_MATCH_ANCHOR_ORIENT */
  int threads;      /* threads of one match (default 1: a server's workers already
                       fill the cores; the local CLI uses 2): tip hypotheses matched at
                       once, else the refinement's nearest-neighbour queries split over
                       them (sm_knn_opts.query_threads). The map does not depend on it. */
  const int32_t *landmarks; /* nlandmarks pairs (x, y), cleaned indices; may be NULL */
  int nlandmarks;
  const int32_t *init_map;  /* optional initial map X -> Y (cleaned indices): skips init */
  int want_yx;      /* also compute the Y -> X map */
  /* Optional observer of the tip search (design data: bench_hard --trace-tips): called on
   * the calling thread with the descriptor start's map (h = 0), each hypothesis's map
   * (h >= 1) and the kept map refined anchored by its tips (h = -1), with the score the
   * search ranks them by, before the bijective pass. The result is borrowed for the call.
   * NULL = none. */
  void (*on_tip_map)(void *ud, int h, const struct sm_match_result *r, double score);
  void *on_tip_map_ud;
  int (*cancel)(void *ud);
  void *cancel_ud;
} sm_match_opts;

typedef struct sm_match_result {
  int32_t nx, ny;
  int32_t *T;        /* nx: X -> Y */
  int32_t *T_yx;     /* ny: Y -> X, or NULL */
  double *C;         /* k1 x k1 functional map of the refinement basis (the first pair) */
  int kC;
  double orientation;       /* sm_map_orientation_score of T, in [-1, 1] */
  double init_distinct;     /* distinct targets of the initial map / min(nx, ny) */
  int flipped;              /* 1 if the orientation fix replaced the first result */
  int init_used;            /* enum sm_match_init of the start that produced T */
  double dirichlet;         /* Dirichlet energy of T (cotan weights of X, unit area) */
  double confidence;        /* in [0, 1]: how far T can be trusted (sm_confidence.h): */
  double continuity, cycle; /* its factors besides the orientation */
  int hypothesis;           /* index of the global search's winning start (0 = descriptors) */
  int ext_tried;            /* tip hypotheses refined (0: the tip search did not run) */
  int ext_hypothesis;       /* 0: the descriptor start's map was kept; h >= 1: the map
                               started from the h-th cheapest tip assignment won */
  double distortion;        /* geodesic distortion of T and T_yx (mean; sm_confidence.h),
                               measured by the tip search only; 0 when it did not run */
  double turns;             /* turn agreement of T and T_yx (mean of both; sm_map_turns),
                               tip search only */
  double curvature;         /* agreement of the shapes' smoothed mean curvatures through T
                               (sm_map_field_agreement), tip search only */
  double t_init, t_refine;  /* seconds; t_init includes the tip search, t_refine is the
                               winning map's refinement */
  double final_lb_weight;   /* the LB functions' weight in the hybrid final pass that made
                               T (SM_MATCH_FINAL_LB_WEIGHT, or 1 when final_choice kept that
                               pass's map); 0 = no hybrid final pass */
} sm_match_result;

void sm_match_opts_default(sm_match_opts *o);
int sm_match(const sm_shape *x, const sm_shape *y, const sm_match_opts *o,
             sm_match_result *res, sm_error *err);
void sm_match_result_free(sm_match_result *res);

/* out[input vertex of X] = input vertex of Y (or -1), from T on the cleaned meshes.
 * out has x->mesh->n_input entries. */
void sm_match_to_input(const sm_shape *x, const sm_shape *y, const int32_t *T, int32_t *out);

#endif
