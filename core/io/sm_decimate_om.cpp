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
 *   triangles, which the coarse bases of sm_multires.h are computed on. The proxy runs
 *   the same greedy order with fewer legality tests (LazyDecimater::greedy_decimate):
 *   OpenMesh's DecimaterT tests every outgoing halfedge of every neighbour of each collapse
 *   (topology and the veto modules, 60-70% of its time), the lazy order only the
 *   collapses that reach the top of the heap. Measured (bench_large --decimate, CPU):
 *   dragon 100k -> 5k 5.6-6.0 s -> 1.6 s, the proxy's distance to the surface unchanged.
 *   sm_mesh_decimate and _lenient keep DecimaterT (their outputs are test and benchmark
 *   inputs elsewhere).
 *   After garbage collection the vertices are renumbered 0..n-1 in OpenMesh's order.
 */
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <exception>
#include <mutex>
#include <new>
#include <queue>
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

/* DecimaterT with greedy_decimate, a faster run of its own greedy order (below). */
class LazyDecimater : public OpenMesh::Decimater::DecimaterT<OmTri> {
 public:
  /* BaseDecimaterT is a virtual base of DecimaterT: the most derived class constructs it. */
  explicit LazyDecimater(OmTri &m)
      : OpenMesh::Decimater::BaseDecimaterT<OmTri>(m), OpenMesh::Decimater::DecimaterT<OmTri>(m),
        om_(m) {}

  /* The greedy order of DecimaterT (each vertex keyed by its best legal collapse, the
   * lowest quadric error first, the neighbours of a collapse keyed again) with fewer tests.
   * A vertex is first keyed by its lowest quadric error over all its outgoing halfedges,
   * legal or not: a lower bound of its best legal one. When such a key reaches the top
   * and its halfedge passes the topology test and the veto modules, it is the best legal
   * collapse of all (every other key is at most as low as its vertex's best legal
   * collapse); when it fails, the vertex is keyed again by its best legal halfedge,
   * found by testing its halfedges in quadric order until one passes. The tests, which
   * cost most (OpenMesh's is_collapse_ok and the modules), then run for the keys that
   * reach the top, not for every halfedge around every neighbour of every collapse. The
   * heap is lazy (a vertex keyed again gets a new stamp, older entries are skipped) and
   * ties go to the lower vertex index. */
  size_t greedy_decimate(OpenMesh::Decimater::ModQuadricT<OmTri> &quadric, size_t alive,
                         size_t target) {
    struct entry {
      float prio;
      int v, h;
      unsigned stamp;
      bool verified;
      bool operator<(const entry &o) const {  /* priority_queue pops the largest */
        return prio != o.prio ? prio > o.prio : v > o.v;
      }
    };
    std::vector<unsigned> stamp(om_.n_vertices(), 0);
    std::priority_queue<entry> heap;
    std::vector<std::pair<float, int>> out;
    auto key = [&](OmTri::VertexHandle v, bool verify) {
      unsigned st = ++stamp[(size_t)v.idx()];
      out.clear();
      for (auto h : om_.voh_range(v)) {
        float p = quadric.collapse_priority(CollapseInfo(om_, h));
        if (p >= 0.0f) out.push_back({p, h.idx()});
      }
      std::stable_sort(out.begin(), out.end(), [](const std::pair<float, int> &a,
                                                  const std::pair<float, int> &b) {
        return a.first < b.first;
      });
      for (const auto &c : out) {
        if (!verify) {
          heap.push({c.first, v.idx(), c.second, st, false});
          return;
        }
        CollapseInfo ci(om_, OmTri::HalfedgeHandle(c.second));
        if (this->is_collapse_legal(ci) && this->collapse_priority(ci) >= 0.0f) {
          heap.push({c.first, v.idx(), c.second, st, true});
          return;
        }
      }
    };
    for (auto v : om_.vertices())
      if (!om_.status(v).deleted()) key(v, false);
    std::vector<OmTri::VertexHandle> support;
    size_t n = 0;
    while (alive > target && !heap.empty()) {
      entry e = heap.top();
      heap.pop();
      if (e.stamp != stamp[(size_t)e.v] || om_.status(OmTri::VertexHandle(e.v)).deleted()) continue;
      CollapseInfo ci(om_, OmTri::HalfedgeHandle(e.h));
      if (!this->is_collapse_legal(ci) || (!e.verified && this->collapse_priority(ci) < 0.0f)) {
        if (!e.verified) key(ci.v0, true);
        continue;
      }
      support.clear();
      for (auto w : om_.vv_range(ci.v0)) support.push_back(w);
      this->preprocess_collapse(ci);
      om_.collapse(ci.v0v1);
      for (auto f : om_.vf_range(ci.v1))
        if (!om_.status(f).deleted()) om_.set_normal(f, om_.calc_face_normal(f));
      this->postprocess_collapse(ci);
      stamp[(size_t)ci.v0.idx()]++;
      for (auto w : support) key(w, false);
      alive--;
      n++;
    }
    return n;
  }

 private:
  OmTri &om_;
};

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
  LazyDecimater dec(om);
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
  if (max_aspect > 0) {
    /* As decimate_to: the result has target_nv vertices counting those without a face (left
     * by refused faces), which cannot be collapsed. */
    size_t alive = 0;
    for (auto v : om.vertices()) alive += !om.is_isolated(v);
    size_t isolated = om.n_vertices() - alive, target = (size_t)target_nv;
    target = target > isolated ? target - isolated : 0;
    if (alive > target) dec.greedy_decimate(dec.module(quadric), alive, target);
  } else {
    dec.decimate_to((size_t)target_nv);
  }
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
