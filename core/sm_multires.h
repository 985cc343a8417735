/* sm_multires: matching large meshes through a coarse level (issue 14).
 *
 *   prepare (per shape): clean -> decimate a copy to about coarse_nv vertices (OpenMesh's
 *     quadric decimater; non-manifold faces and components under 1% of the vertices, scan
 *     debris, are left out of this proxy) -> sm_shape_prepare on
 *     the coarse mesh (bases, descriptors) -> locate every full-resolution vertex on the
 *     coarse surface: the closest point of the nearest coarse triangle, as 3 coarse
 *     vertices and barycentric weights (the prolongation P, one row per fine vertex).
 *   match (per pair): sm_match on the two coarse shapes (the whole pipeline: descriptors,
 *     coarse map, Sinkhorn init, ZoomOut, mirror fix, tip search, by default whatever the
 *     coarse map's confidence: SM_MULTIRES_COARSE_TIPS) gives the final
 *     functional map C in the refinement basis; its spectral embeddings (sm_fmap.h: a_i on
 *     X, b_j = C-aligned on Y) are prolonged to all fine vertices by P, and the point map
 *     is extracted there, ScalableZoomOut-style: each fine vertex of X takes the nearest b_j
 *     (Euclidean, in the k-dimensional embedding) among the fine vertices of Y located
 *     within `ring` edges of the coarse image of its own coarse vertex. The coarse map
 *     already fixed the basin; the local candidate set makes the extraction O(n) instead
 *     of the O(nx ny k) of an exhaustive search (50 s on 100k x 100k vertices here).
 *     Then fine_iters refits at full resolution (the last step of a ZoomOut run on the
 *     prolonged basis): the prolonged functions are made orthonormal in the fine masses,
 *     C is refitted to the fine map by M-weighted least squares and the point map
 *     extracted again among the same candidates; this fits C to what the prolonged
 *     functions are on the fine vertices rather than on the coarse ones.
 *     Y -> X: the adjoint assignment of the final C (nearest X vertex of each Y vertex,
 *     candidates from the coarse T_yx). Last, both maps are snapped on the fine meshes
 *     (sm_multires_snap: each image moves within its one-ring to keep the source's edge
 *     lengths). Confidence, orientation and Dirichlet energy are computed on the fine maps.
 *   Decimation quality: the decimater's collapses are vetoed when they leave needle
 *     triangles (aspect ratio above max_aspect). Measured (bench_large --small, lion ->
 *     cat, coarse levels 4,500 / 5,000 / 5,500): without the veto the coarse match lost
 *     the map on some levels (mean error 0.063 against 0.036 direct), with it 0.039.
 *   The coarse level does not depend on the input's vertex numbering: the cleaned mesh is
 *   put in a canonical order (vertices by coordinates, faces by their vertices) before
 *   decimation, so two files of the same surface in different vertex orders get the same
 *   coarse mesh (and the daemon may cache it per shape).
 *
 * Why not the direct path everywhere: eigensolves and ZoomOut grow faster than linearly
 * (koala, 50k vertices: 134 s direct, bases 81 s). SM_MULTIRES_THRESHOLD is where auto
 * switches: the largest pairs the direct path is tuned on have 15k vertices (about 20 s),
 * and the coarse level (5k) must be clearly coarser than the input for the path to pay.
 *
 * Contract
 *   sm_multires_shape_prepare reads `input` (borrowed) and returns a shape owned by the
 *   caller (sm_multires_shape_destroy); afterwards read only, so one shape may serve
 *   several concurrent sm_multires_match calls (its coarse sm_shape has sm_match's
 *   internally locked cache). sm_multires_match writes a result the caller frees with
 *   sm_multires_result_free. Vertex indices: fine maps speak of the cleaned full-resolution
 *   meshes (shape->mesh); sm_multires_to_input translates to the caller's numbering.
 *   Landmarks and init_map in sm_match_opts are given in cleaned fine indices and are
 *   carried to the coarse level by the coarse vertex each fine vertex is located on.
 *   No global state, no logging; threads as sm_match (BLAS threading is the caller's).
 *   Cancellation: the shape's and match's cancel callbacks are polled by the modules
 *   used and between blocks of the fine extraction (SM_ECANCELED).
 *   Errors: 0 or a negative SM_E* code with a message: SM_EINVAL (options), SM_ENOMEM,
 *   SM_EFORMAT (no decimation possible), and those of sm_shape_prepare / sm_match.
 */
#ifndef SM_MULTIRES_H
#define SM_MULTIRES_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_match.h"
#include "sm_mesh.h"

enum sm_multires_mode { SM_MULTIRES_AUTO = 0, SM_MULTIRES_ON = 1, SM_MULTIRES_OFF = 2 };

#define SM_MULTIRES_THRESHOLD 20000 /* auto: multires when either shape has more vertices */
#define SM_MULTIRES_COARSE_NV 5000  /* vertices of the coarse level */
#define SM_MULTIRES_RING 2          /* candidate radius of the fine extraction, coarse edges */
#define SM_MULTIRES_FINE_ITERS 2    /* fine-level refits of the functional map */
#define SM_MULTIRES_SNAP_ITERS 10   /* at most this many sweeps of the fine snap (below) */
#define SM_MULTIRES_MAX_ASPECT 10.0 /* aspect-ratio bound of the decimation (sm_deform.h) */
/* The coarse match's tip search (sm_match.h): 1 = it runs whatever the coarse map's
 * confidence when the match options ask for it "when doubtful" (the default), 0 = as asked.
 * Why: the coarse match is the whole pipeline on a remeshed pair, and there its descriptor
 * start lands a limb in a wrong basin on some decimations while the map's confidence stays
 * above the direct path's search threshold (lion -> cat at 8 coarse levels: 2 of 8 maps at
 * 0.056 against 0.037 direct, confidence 0.55-0.57, where right coarse maps of homer -> B
 * score 0.61), so no threshold on that confidence separates them. The search costs about 4
 * more coarse matches (5-6 s of CPU at 5,000 vertices) and the coarse match runs once per
 * pair whatever the input's size. Figures: docs/RESULTS.md section 7. */
#define SM_MULTIRES_COARSE_TIPS 1
/* Version of the decimation's algorithm: the coarse mesh, so everything computed on it,
 * changes with it. Caches of coarse levels key on it (2: the lazy legality checks of
 * 9dfbfb8). */
#define SM_MULTIRES_DECIMATION 2

typedef struct sm_multires_opts {
  int mode;          /* enum sm_multires_mode (default AUTO) */
  int32_t threshold; /* AUTO: multires when max(nv) > threshold */
  int32_t coarse_nv; /* decimation target (>= 200) */
  int ring;          /* candidate radius (>= 1) */
  int fine_iters;    /* fine-level refits after the first extraction (>= 0) */
  double max_aspect; /* decimation's aspect-ratio bound (>= 1.5) */
  int coarse_tips;   /* SM_MULTIRES_COARSE_TIPS above: 1 = search always, 0 = as asked */
  int snap_iters;    /* sweeps of the fine snap (SM_MULTIRES_SNAP_ITERS above; 0 = off) */
} sm_multires_opts;

typedef struct sm_multires_shape {
  sm_mesh *mesh;     /* full resolution: cleaned, unit area; to_input = caller's vertices */
  double *mass;      /* mesh->nv lumped masses */
  sm_shape *coarse;  /* the prepared coarse level (its mesh: cleaned, unit area) */
  int32_t *tri;      /* 3 per fine vertex: coarse vertices (coarse->mesh indices) ... */
  double *bary;      /* ... and barycentric weights (sum 1) of its closest coarse point */
  int32_t *owner;    /* per fine vertex: its coarse vertex of largest weight */
  int32_t skipped_faces; /* faces the decimater refused (left out of the coarse proxy) */
  int32_t dropped_vertices; /* fine vertices of components under 1% of the vertices, left
                               out of the proxy (located on the nearest kept surface) */
  double t_clean, t_decimate, t_coarse, t_locate; /* seconds: t_coarse = sm_shape_prepare */
} sm_multires_shape;

typedef struct sm_multires_result {
  int32_t nx, ny;       /* fine vertex counts */
  int32_t *T;           /* nx: fine X -> fine Y */
  int32_t *T_yx;        /* ny: fine Y -> fine X */
  sm_match_result coarse; /* the coarse correspondence (its C, kC, flipped, tips ...) */
  double orientation, confidence, continuity, cycle, dirichlet; /* of the fine maps */
  double t_match, t_prolong; /* seconds: coarse sm_match; embedding, prolongation, extraction */
} sm_multires_result;

void sm_multires_opts_default(sm_multires_opts *o);

/* 1 when the options send a pair with nv_x and nv_y input vertices through this path. */
int sm_multires_wanted(const sm_multires_opts *o, int32_t nv_x, int32_t nv_y);

int sm_multires_shape_prepare(const sm_mesh *input, const sm_shape_opts *so,
                              const sm_multires_opts *mo, sm_multires_shape **out,
                              sm_error *err);
void sm_multires_shape_destroy(sm_multires_shape *s);

int sm_multires_match(const sm_multires_shape *x, const sm_multires_shape *y,
                      const sm_match_opts *o, const sm_multires_opts *mo,
                      sm_multires_result *res, sm_error *err);
void sm_multires_result_free(sm_multires_result *r);

/* The fine snap, last step of sm_multires_match (both directions): up to iters sweeps,
 * stopping at the first that moves nothing; in each, every vertex i of X moves its image
 * T[i] to the vertex of {T[i]} + its one-ring in Y that best keeps the lengths of i's
 * edges: the lowest sum over neighbours j of (|y_c - y_T[j]| - |x_i - x_j|)^2 (ties keep
 * T[i]). An exact map between copies of one mesh scores 0, so it is a fixed point.
 * Why: the prolonged functions are linear inside each coarse triangle and cannot tell
 * apart the fine vertices lying in one; the extraction then lands a fine ring off where
 * they differ by less than the embedding's error (man -> woman, one connectivity: 67-78%
 * exact at 5 coarse levels against 74% direct). The fine edge lengths carry exactly the
 * detail the prolonged basis lacks. Measured: docs/RESULTS.md section 7.
 * Contract: mx and my at one scale (sm_multires meshes have unit area), T (mx->nv
 * entries, each in [0, my->nv)) updated in place; 0 or SM_ENOMEM. */
int sm_multires_snap(const sm_mesh *mx, const sm_mesh *my, int iters, int32_t *T,
                     sm_error *err);

/* out[input vertex of X] = input vertex of Y or -1 (x->mesh->n_input entries). */
void sm_multires_to_input(const sm_multires_shape *x, const sm_multires_shape *y,
                          const int32_t *T, int32_t *out);

/* ---- the pieces, exposed for tests ---- */

/* Locates each of the np points P (row-major np x 3) on the surface `coarse` (positions
 * and faces; same frame as P): tri[3i..3i+2] and bary[3i..3i+2] describe the closest
 * point among the faces around the K = 8 nearest coarse vertices (exact when it lies
 * there, which it does unless the coarse surface folds back within that neighbourhood).
 * A point on a coarse vertex gets weight exactly 1 on it. */
int sm_multires_locate(const double *P, int32_t np, const sm_mesh *coarse, int32_t *tri,
                       double *bary, sm_error *err);

/* Fine rows from coarse rows: Ff[i, :] = sum_t bary[3i+t] Fc[tri[3i+t], :] for the nf fine
 * vertices; Fc row-major with leading dimension ldc, Ff with ldf, d columns. */
void sm_multires_prolong(const int32_t *tri, const double *bary, int32_t nf, const double *Fc,
                         int ldc, int d, double *Ff, int ldf);

#endif
