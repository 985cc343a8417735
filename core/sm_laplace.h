/* sm_laplace: the cotangent Laplacian (stiffness) of a triangle mesh.
 *
 * Contract
 *   W_ij = -(cot a_ij + cot b_ij)/2 for each edge, rows summing to 0, symmetric PSD.
 *   (sm_mean_curvature below applies the same weights to the vertex positions.)
 *   Returned as the lower triangle in a new sm_csc owned by the caller. The mesh is
 *   borrowed. Faces of zero area contribute nothing (clean the mesh first).
 */
#ifndef SM_LAPLACE_H
#define SM_LAPLACE_H

#include "sm_error.h"
#include "sm_mesh.h"
#include "sm_sparse.h"

int sm_cotan_stiffness(const sm_mesh *m, sm_csc **W, sm_error *err);

/* Adds the cotan weights cot(angle at corner o)/2 of face (a, b, c) to w[0..2], w[c] being
 * the weight of the edge opposite corner c. Shared with the thin-shell membrane term. */
void sm_face_cotan_weights(const double *a, const double *b, const double *c, double w[3]);

/* Signed mean curvature per vertex (H[nv]): the cotan Laplacian of the positions along the
 * area-weighted vertex normal, over twice the vertex's mixed Voronoi area (1/r on a sphere
 * of radius r with outward normals; 0 on a plane), then smoothed by `smooth` passes that
 * replace each vertex's value by the mean, over its faces, of the face's three values (a
 * pass diffuses about one ring: size the count to the mesh's resolution). Extrinsic: a
 * nose, a heel or a chest read positive and keep their sign under a bend of the joints
 * elsewhere, where the intrinsic descriptors find a front and a back alike.
 * Errors: SM_ENOMEM. */
int sm_mean_curvature(const sm_mesh *m, int smooth, double *H, sm_error *err);

#endif
