/* sm_mesh: the indexed triangle mesh every other module works on, and its per-shape
 * preparation (validation, cleaning, normalization, mass, normals, orientation).
 * Spec: ../shared/design/algorithm.md §1.
 *
 * Contract
 *   - An sm_mesh owns its arrays (V, F, to_input); sm_mesh_destroy frees them all.
 *     Functions taking `const sm_mesh *` only read it; they never keep a pointer to it.
 *   - Coordinates are double, faces int32 0-based, 3 per face, counter-clockwise = normal.
 *   - Index map: a mesh produced by cleaning keeps `to_input[v]` = the index of vertex v in
 *     the mesh the caller supplied (composed over successive cleanings), and `n_input` = how
 *     many vertices the caller supplied. A freshly read or allocated mesh has to_input NULL
 *     (identity) and n_input = nv. Every answer the product gives speaks of input indices.
 *   - Limits (sm_limits) are checked before anything is allocated from a count.
 *   - No global state, no logging. Different meshes may be used from different threads;
 *     one mesh is not to be modified concurrently.
 *   - Errors: 0 or a negative SM_E* code, with a message in *err saying what and where.
 */
#ifndef SM_MESH_H
#define SM_MESH_H

#include <stdint.h>

#include "sm_error.h"

#define SM_DEFAULT_MAX_VERTICES 4000000
#define SM_DEFAULT_MAX_FACES 8000000

typedef struct sm_limits {
  int64_t max_vertices;
  int64_t max_faces;
} sm_limits;

typedef struct sm_mesh {
  int32_t nv, nf;
  double *V;         /* 3*nv: x, y, z of vertex v at V[3v..3v+2] */
  int32_t *F;        /* 3*nf: vertices of face f at F[3f..3f+2] */
  int32_t n_input;   /* number of vertices in the caller's numbering */
  int32_t *to_input; /* nv entries, caller index of each vertex; NULL = identity */
  double center[3];  /* normalization applied: V = (V_input - center) * scale */
  double scale;      /* 1 and center 0 until sm_mesh_normalize */
} sm_mesh;

typedef struct sm_clean_report {
  int32_t input_vertices, input_faces;
  int32_t dropped_repeated_index; /* faces like (a, a, b) */
  int32_t dropped_zero_area;      /* faces with (numerically) zero area */
  int32_t dropped_duplicate;      /* faces with the same vertex set as an earlier one */
  int32_t dropped_unreferenced;   /* vertices no kept face uses */
  int32_t flipped_faces;          /* faces reversed to make orientation consistent */
  int32_t nonmanifold_edges;      /* edges with more than 2 faces (kept, no bending term) */
  int32_t boundary_edges;         /* edges with 1 face */
  int32_t components;             /* connected components (through shared vertices) */
  int32_t nonorientable_components; /* components no flip can make consistent (Moebius) */
} sm_clean_report;

/* Fills *lim with SM_DEFAULT_MAX_*. */
void sm_limits_default(sm_limits *lim);

/* SM_ELIMIT (with message) if nv or nf exceed lim (NULL = defaults) or are negative. */
int sm_limits_check(const sm_limits *lim, int64_t nv, int64_t nf, sm_error *err);

/* Allocates a mesh with uninitialized V and F of the given sizes (checked against lim,
 * NULL = defaults), to_input NULL, n_input = nv, center 0, scale 1. */
int sm_mesh_alloc(int64_t nv, int64_t nf, const sm_limits *lim, sm_mesh **out, sm_error *err);

/* The inverse of the index map: a malloc'd array of n_input entries giving, for each of
 * the caller's vertices, its index in m or -1 if cleaning dropped it. NULL on ENOMEM. */
int32_t *sm_mesh_input_to_clean(const sm_mesh *m);

/* Deep copy. */
int sm_mesh_copy(const sm_mesh *m, sm_mesh **out, sm_error *err);

void sm_mesh_destroy(sm_mesh *m);

/* Checks without modifying: nv > 0 and nf > 0 (SM_EEMPTY), every coordinate finite
 * (SM_ENONFINITE, naming the vertex and coordinate), every face index in [0, nv)
 * (SM_ERANGE, naming the face and index). */
int sm_mesh_validate(const sm_mesh *m, sm_error *err);

/* Validates `in`, then returns in *out a new mesh without repeated-index, zero-area and
 * duplicate faces and without unreferenced vertices, its faces oriented consistently per
 * connected component (closed components outward), and to_input composed with in's.
 * Non-manifold edges and several components are kept. SM_EEMPTY if no face survives.
 * `rep` (may be NULL) receives the counts. `in` is not modified. */
int sm_mesh_clean(const sm_mesh *in, const sm_limits *lim, sm_mesh **out,
                  sm_clean_report *rep, sm_error *err);

/* Translates the area-weighted centroid to 0 and scales total area to 1; records the
 * transform in center/scale (composed with any earlier one). SM_EEMPTY if area is 0. */
int sm_mesh_normalize(sm_mesh *m, sm_error *err);

/* Per-face areas (area[nf], or NULL for the total only); returns the total. */
double sm_mesh_face_areas(const sm_mesh *m, double *area);

/* Lumped mixed-Voronoi mass (Meyer et al.): m[nv]; sums to the total area. */
int sm_mesh_lumped_mass(const sm_mesh *m, double *mass);

/* Unit vertex normals N[3*nv]: normalized sum of area-weighted face normals. */
int sm_mesh_vertex_normals(const sm_mesh *m, double *N);

/* Connected components through shared vertices: comp[nv] in [0, *ncomp). */
int sm_mesh_components(const sm_mesh *m, int32_t *comp, int32_t *ncomp);

/* Makes face orientation consistent per component (flipping as few faces as possible
 * from a BFS seed) and outward for closed components. *flipped (may be NULL) gets the
 * number of reversed faces, *nonorientable (may be NULL) the number of components that
 * cannot be made consistent. */
int sm_mesh_orient(sm_mesh *m, int32_t *flipped, int32_t *nonorientable, sm_error *err);

#endif
