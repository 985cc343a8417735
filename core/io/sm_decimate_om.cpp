/* sm_decimate_om: sm_mesh_decimate (sm_deform.h) on OpenMesh's incremental decimater.
 *
 * DESIGN
 *   The mesh is copied into an OpenMesh TriMesh with double coordinates; a face OpenMesh
 *   refuses (a complex edge or vertex) makes the whole call fail with SM_EFORMAT rather
 *   than decimate a silently different surface (sm_mesh_decimate_lenient leaves such faces
 *   out instead and counts them: for a coarse proxy of a non-manifold scan). Collapses are ordered by the quadric error
 *   (ModQuadric, no error bound) and vetoed when they flip a face normal by more than
 *   60 degrees (ModNormalFlipping), which keeps the decimated surface free of fold-overs.
 *   sm_mesh_decimate_proxy also vetoes collapses that would leave a face with an aspect
 *   ratio above a bound (ModAspectRatio, binary): the quadric order alone leaves needle
 *   triangles, which the coarse bases of sm_multires.h are computed on.
 *   After garbage collection the vertices are renumbered 0..n-1 in OpenMesh's order.
 */
#include <cmath>
#include <cstdint>
#include <exception>
#include <mutex>
#include <new>
#include <vector>

#include <OpenMesh/Core/Mesh/TriMesh_ArrayKernelT.hh>
#include <OpenMesh/Tools/Decimater/DecimaterT.hh>
#include <OpenMesh/Tools/Decimater/ModAspectRatioT.hh>
#include <OpenMesh/Tools/Decimater/ModNormalFlippingT.hh>
#include <OpenMesh/Tools/Decimater/ModQuadricT.hh>

extern "C" {
#include "sm_deform.h"
}

namespace {

struct DoubleTraits : OpenMesh::DefaultTraits {
  typedef OpenMesh::Vec3d Point;
  typedef OpenMesh::Vec3d Normal;
  VertexAttributes(OpenMesh::Attributes::Status);
  EdgeAttributes(OpenMesh::Attributes::Status);
  FaceAttributes(OpenMesh::Attributes::Status | OpenMesh::Attributes::Normal);
};
typedef OpenMesh::TriMesh_ArrayKernelT<DoubleTraits> OmTri;

/* skipped == NULL: a refused face fails the call; otherwise it is left out and counted. */
int build(const sm_mesh *in, OmTri &om, int32_t *skipped, sm_error *err) {
  std::vector<OmTri::VertexHandle> vh((size_t)in->nv);
  for (int32_t v = 0; v < in->nv; v++) {
    const double *p = in->V + 3 * (size_t)v;
    vh[(size_t)v] = om.add_vertex(OmTri::Point(p[0], p[1], p[2]));
  }
  for (int32_t f = 0; f < in->nf; f++) {
    const int32_t *t = in->F + 3 * (size_t)f;
    for (int c = 0; c < 3; c++)
      if (t[c] < 0 || t[c] >= in->nv)
        return sm_error_set(err, SM_ERANGE, "decimate: face %d references vertex %d of %d", f,
                            t[c], in->nv);
    if (om.add_face(vh[(size_t)t[0]], vh[(size_t)t[1]], vh[(size_t)t[2]]).is_valid()) continue;
    if (skipped) {
      (*skipped)++;
      continue;
    }
    return sm_error_set(err, SM_EFORMAT,
                          "decimate: face %d is non-manifold here; clean the mesh first", f);
  }
  return SM_OK;
}

int extract(OmTri &om, sm_mesh **out, sm_error *err) {
  om.garbage_collection();
  int rc = sm_mesh_alloc((int64_t)om.n_vertices(), (int64_t)om.n_faces(), NULL, out, err);
  if (rc) return rc;
  for (auto v : om.vertices()) {
    const OmTri::Point &p = om.point(v);
    for (int d = 0; d < 3; d++) (*out)->V[3 * (size_t)v.idx() + d] = p[d];
  }
  size_t k = 0;
  for (auto f : om.faces())
    for (auto v : om.fv_range(f)) (*out)->F[k++] = (int32_t)v.idx();
  return SM_OK;
}

/* OpenMesh reports every refused face on its global error stream; the lenient build
 * expects thousands of them (the dragon: 1,900) and core does not log, so the stream is
 * muted while it runs. The stream is process-wide: the mutex keeps concurrent lenient
 * builds from re-enabling it under each other. */
std::mutex g_omerr_lock;

int decimate_impl(const sm_mesh *in, int32_t target_nv, double max_aspect, int32_t *skipped,
                  sm_mesh **out, sm_error *err) {
  OmTri om;
  int rc;
  if (skipped) {
    std::lock_guard<std::mutex> guard(g_omerr_lock);
    bool was = omerr().is_enabled();
    omerr().disable();
    rc = build(in, om, skipped, err);
    if (was) omerr().enable();
  } else {
    rc = build(in, om, skipped, err);
  }
  if (rc) return rc;
  om.update_face_normals();
  OpenMesh::Decimater::DecimaterT<OmTri> dec(om);
  OpenMesh::Decimater::ModQuadricT<OmTri>::Handle quadric;
  OpenMesh::Decimater::ModNormalFlippingT<OmTri>::Handle flipping;
  dec.add(quadric);
  dec.add(flipping);
  dec.module(flipping).set_max_normal_deviation(60.0);
  OpenMesh::Decimater::ModAspectRatioT<OmTri>::Handle aspect;
  if (max_aspect > 0) {
    dec.add(aspect);
    dec.module(aspect).set_aspect_ratio((float)max_aspect);
    dec.module(aspect).set_binary(true);
  }
  if (!dec.initialize())
    return sm_error_set(err, SM_EINVAL, "decimate: OpenMesh decimater failed to initialize");
  dec.decimate_to((size_t)target_nv);
  return extract(om, out, err);
}

}  // namespace

static int decimate_entry(const sm_mesh *in, int32_t target_nv, double max_aspect,
                          int32_t *skipped, sm_mesh **out, sm_error *err) {
  if (!in || !out || target_nv < 4)
    return sm_error_set(err, SM_EINVAL, "decimate: target of %d vertices (need >= 4)", target_nv);
  *out = NULL;
  if (in->nv <= target_nv) return sm_mesh_copy(in, out, err);
  try {
    int rc = decimate_impl(in, target_nv, max_aspect, skipped, out, err);
    if (rc && *out) {
      sm_mesh_destroy(*out);
      *out = NULL;
    }
    return rc;
  } catch (const std::bad_alloc &) {
    return sm_error_set(err, SM_ENOMEM, "decimate: out of memory (%d vertices)", in->nv);
  } catch (const std::exception &e) {
    return sm_error_set(err, SM_EFORMAT, "decimate: %s", e.what());
  }
}

extern "C" int sm_mesh_decimate(const sm_mesh *in, int32_t target_nv, sm_mesh **out,
                                sm_error *err) {
  return decimate_entry(in, target_nv, 0, NULL, out, err);
}

extern "C" int sm_mesh_decimate_lenient(const sm_mesh *in, int32_t target_nv, sm_mesh **out,
                                        int32_t *skipped, sm_error *err) {
  int32_t n = 0;
  int rc = decimate_entry(in, target_nv, 0, &n, out, err);
  if (skipped) *skipped = n;
  return rc;
}

extern "C" int sm_mesh_decimate_proxy(const sm_mesh *in, int32_t target_nv, double max_aspect,
                                      sm_mesh **out, int32_t *skipped, sm_error *err) {
  if (!(max_aspect >= 1.5) || !std::isfinite(max_aspect))
    return sm_error_set(err, SM_EINVAL, "decimate: aspect ratio bound %g (need >= 1.5)",
                        max_aspect);
  int32_t n = 0;
  int rc = decimate_entry(in, target_nv, max_aspect, &n, out, err);
  if (skipped) *skipped = n;
  return rc;
}
