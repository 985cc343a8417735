/* sm_deform: controlled non-isometric deformations and re-meshing, applied to a copy of a
 * mesh, for the robustness experiments of the evaluation suite (a query shape is deformed
 * and must still be classified with its class) and for tests.
 *
 *   stretch   anisotropic scaling by `factor` along one direction through the centroid:
 *             a coordinate axis, or the principal axis (largest variance of the vertices).
 *   region    local inflation (amount > 0) or shrinking (< 0) of the part of the surface
 *             within geodesic radius r of a vertex: x' = x + amount r w n(x), with n the
 *             vertex normal and w = (1 - (d/r)^2)^2 for d < r (d = Dijkstra distance on
 *             the edge graph from the centre vertex): a smooth bulge or dent, the rest
 *             untouched. Keep |amount| below the local thickness / r (no self-intersection
 *             check).
 *   noise     each vertex moves along its normal by sigma * (mean edge length) * N(0, 1)
 *             (Box-Muller on splitmix64: the same seed gives the same mesh everywhere).
 *   decimate  quadric edge-collapse decimation (OpenMesh's Decimater, with the normal-
 *             flipping guard) down to at most target_nv vertices; a new connectivity.
 *
 * Contract: every function reads `in` (borrowed) and returns a new mesh in *out owned by
 * the caller; the input's vertex order is kept except by decimate. Faces are copied as
 * they are (the caller cleans). No global state; thread-safe. Errors: SM_EINVAL (bad
 * parameter, message says which), SM_ERANGE (centre vertex), SM_ENOMEM, SM_EFORMAT
 * (decimation on a mesh OpenMesh cannot build, e.g. non-manifold).
 */
#ifndef SM_DEFORM_H
#define SM_DEFORM_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_mesh.h"

#define SM_AXIS_PRINCIPAL (-1)

/* axis 0, 1, 2 or SM_AXIS_PRINCIPAL; factor > 0. */
int sm_deform_stretch(const sm_mesh *in, int axis, double factor, sm_mesh **out,
                      sm_error *err);

/* radius_rel: geodesic radius / sqrt(surface area), > 0; amount: peak offset / radius. */
int sm_deform_region(const sm_mesh *in, int32_t center, double radius_rel, double amount,
                     sm_mesh **out, sm_error *err);

/* sigma_rel >= 0 (in mean edge lengths). */
int sm_deform_noise(const sm_mesh *in, double sigma_rel, uint64_t seed, sm_mesh **out,
                    sm_error *err);

/* 4 <= target_nv; a mesh already at or below it is copied. */
int sm_mesh_decimate(const sm_mesh *in, int32_t target_nv, sm_mesh **out, sm_error *err);

/* As sm_mesh_decimate, but faces OpenMesh refuses (they would make an edge or a vertex
 * non-manifold) are left out of the decimated surface instead of failing the call;
 * *skipped (may be NULL) gets their number. For a coarse proxy of a non-manifold scan
 * (sm_multires.h), where a few missing faces only shift the proxy locally. */
int sm_mesh_decimate_lenient(const sm_mesh *in, int32_t target_nv, sm_mesh **out,
                             int32_t *skipped, sm_error *err);

/* As sm_mesh_decimate_lenient, with a veto (OpenMesh's ModAspectRatio, binary) on
 * collapses that leave a face around them with an aspect ratio (longest edge over its
 * height; 1.15 for an equilateral face) above max_aspect, unless they improve the worst
 * face there: the coarse proxy of sm_multires.h, whose bases suffer from the needle
 * triangles of the quadric order alone. max_aspect >= 1.5, else SM_EINVAL. The veto can
 * stop the decimation above target_nv. */
int sm_mesh_decimate_proxy(const sm_mesh *in, int32_t target_nv, double max_aspect,
                           sm_mesh **out, int32_t *skipped, sm_error *err);

/* Principal axis (unit vector, sign fixed so its largest component is positive) of the
 * vertices; used by stretch and exposed for tests. */
int sm_principal_axis(const sm_mesh *m, double axis[3], sm_error *err);

#endif
