/* sm_openmesh_io: OpenMesh's STL/PLY parsers behind a C ABI.
 *
 * DESIGN
 *   OpenMesh builds a halfedge mesh while it reads. A face that would create a complex
 *   (non-manifold) edge is refused by that structure, and OpenMesh's importer then re-adds
 *   it on fresh copies of its vertices, appended after the file's own vertices. Either way
 *   the result no longer matches the file. So the importer here records every vertex and
 *   every face exactly as the parser hands them over, and only then lets OpenMesh do its
 *   usual bookkeeping (some readers use the returned handles afterwards). The recorded
 *   arrays, not OpenMesh's mesh, become the sm_mesh.
 *
 *   OpenMesh's readers are process-wide singletons that keep per-read state in mutable
 *   members (_PLYReader_::elements_, vertexCount_, ...), so two reads at once would race;
 *   one mutex serialises the OpenMesh parse (the rest of the module stays parallel).
 *
 *   Points are recorded in double. OpenMesh's text parsers round to float32, which is why
 *   sm_meshio.c keeps its own readers for the text formats.
 */
#include <cstdint>
#include <cstring>
#include <exception>
#include <mutex>
#include <new>
#include <sstream>
#include <string>
#include <vector>

/* OpenMesh's property arrays default-construct VectorT (deliberately uninitialized); GCC 12
 * reports that inside OpenMesh's own headers when they are instantiated here. */
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <OpenMesh/Core/IO/MeshIO.hh>
#include <OpenMesh/Core/Mesh/PolyMesh_ArrayKernelT.hh>
#include <OpenMesh/Core/System/omstream.hh>

extern "C" {
#include "sm_meshio.h"
}

namespace {

struct DoubleTraits : OpenMesh::DefaultTraits {
  typedef OpenMesh::Vec3d Point;
};
typedef OpenMesh::PolyMesh_ArrayKernelT<DoubleTraits> OmMesh;
typedef OpenMesh::IO::ImporterT<OmMesh> OmImporter;

/* Vertices are numbered in the order the parser creates them; OpenMesh's own numbering
 * drifts once it starts duplicating vertices for refused faces, hence om_to_file. */
class RecordingImporter : public OmImporter {
 public:
  explicit RecordingImporter(OmMesh &m) : OmImporter(m) {}

  std::vector<double> V;           /* 3 per file vertex */
  std::vector<int64_t> corners;    /* file vertex indices of every polygon, concatenated */
  std::vector<int32_t> poly_size;  /* corners per polygon */

  OpenMesh::VertexHandle add_vertex(const OpenMesh::Vec3f &p) override {
    return remember(OmImporter::add_vertex(p), p[0], p[1], p[2]);
  }
  OpenMesh::VertexHandle add_vertex(const OpenMesh::Vec3d &p) override {
    return remember(OmImporter::add_vertex(p), p[0], p[1], p[2]);
  }
  OpenMesh::VertexHandle add_vertex() override {
    return remember(OmImporter::add_vertex(), 0, 0, 0);
  }
  void set_point(OpenMesh::VertexHandle vh, const OpenMesh::Vec3f &p) override {
    int64_t v = file_index(vh);
    if (v >= 0 && v < (int64_t)(V.size() / 3)) {
      V[3 * v] = p[0];
      V[3 * v + 1] = p[1];
      V[3 * v + 2] = p[2];
    }
    OmImporter::set_point(vh, p);
  }
  OpenMesh::FaceHandle add_face(const VHandles &h) override {
    for (const OpenMesh::VertexHandle &vh : h) corners.push_back(file_index(vh));
    poly_size.push_back((int32_t)h.size());
    return OmImporter::add_face(h);
  }

 private:
  std::vector<int64_t> om_to_file;

  OpenMesh::VertexHandle remember(OpenMesh::VertexHandle vh, double x, double y, double z) {
    if (vh.idx() >= 0) {
      if ((size_t)vh.idx() >= om_to_file.size()) om_to_file.resize((size_t)vh.idx() + 1, -1);
      om_to_file[(size_t)vh.idx()] = (int64_t)(V.size() / 3);
    }
    V.push_back(x);
    V.push_back(y);
    V.push_back(z);
    return vh;
  }
  /* A handle the parser never got from add_vertex keeps its raw number, so an
   * out-of-range face index is reported by validation rather than hidden. */
  int64_t file_index(OpenMesh::VertexHandle vh) const {
    int64_t i = vh.idx();
    if (i >= 0 && (size_t)i < om_to_file.size() && om_to_file[(size_t)i] >= 0)
      return om_to_file[(size_t)i];
    return i;
  }
};

void silence_openmesh() {
  static std::once_flag once;
  std::call_once(once, [] {
    omerr().disable();
    omout().disable();
    omlog().disable();
  });
}

int64_t fan_triangles(const RecordingImporter &rec) {
  int64_t n = 0;
  for (int32_t s : rec.poly_size) n += s >= 3 ? s - 2 : 0;
  return n;
}

int to_sm_mesh(const RecordingImporter &rec, const char *ext, const sm_limits *lim,
               sm_mesh **out, sm_error *err) {
  int64_t nv = (int64_t)(rec.V.size() / 3), nt = fan_triangles(rec);
  int rc = sm_limits_check(lim, nv, nt, err);
  if (rc) return rc;
  for (int64_t c : rec.corners)
    if (c < INT32_MIN || c > INT32_MAX)
      return sm_error_set(err, SM_EFORMAT, "%s: vertex index %lld does not fit 32 bits", ext,
                          (long long)c);
  sm_mesh *m;
  if ((rc = sm_mesh_alloc(nv, nt, lim, &m, err))) return rc;
  if (nv) std::memcpy(m->V, rec.V.data(), (size_t)nv * 3 * sizeof(double));
  size_t at = 0;
  int32_t *f = m->F;
  for (int32_t s : rec.poly_size) {
    for (int32_t k = 1; k + 1 < s; k++) {
      *f++ = (int32_t)rec.corners[at];
      *f++ = (int32_t)rec.corners[at + k];
      *f++ = (int32_t)rec.corners[at + k + 1];
    }
    at += (size_t)s;
  }
  *out = m;
  return 0;
}

int read_impl(const uint8_t *buf, size_t len, const char *ext, int binary, const sm_limits *lim,
              sm_mesh **out, int64_t *n_polygons, sm_error *err) {
  silence_openmesh();
  std::istringstream in(std::string(reinterpret_cast<const char *>(buf), len),
                        std::ios::in | std::ios::binary);
  OmMesh mesh;
  RecordingImporter rec(mesh);
  OpenMesh::IO::Options opt;
  if (binary) opt += OpenMesh::IO::Options::Binary;
  static std::mutex reader_lock;
  bool ok;
  {
    std::lock_guard<std::mutex> hold(reader_lock);
    ok = OpenMesh::IO::IOManager().read(in, std::string(".") + ext, rec, opt);
  }
  if (!ok) return sm_error_set(err, SM_EFORMAT, "%s: OpenMesh could not parse the content", ext);
  for (int32_t s : rec.poly_size)
    if (s < 3) return sm_error_set(err, SM_EFORMAT, "%s: a face has %d corners", ext, (int)s);
  if (n_polygons) *n_polygons = (int64_t)rec.poly_size.size();
  return to_sm_mesh(rec, ext, lim, out, err);
}

}  // namespace

extern "C" int sm_openmesh_read(const uint8_t *buf, size_t len, const char *ext, int binary,
                                const sm_limits *lim, sm_mesh **out, int64_t *n_polygons,
                                sm_error *err) {
  if (!out || !ext || (!buf && len))
    return sm_error_set(err, SM_EINVAL, "sm_openmesh_read: null argument");
  *out = NULL;
  try {
    return read_impl(buf, len, ext, binary, lim, out, n_polygons, err);
  } catch (const std::bad_alloc &) {
    return sm_error_set(err, SM_ENOMEM, "%s: out of memory while parsing with OpenMesh", ext);
  } catch (const std::exception &e) {
    return sm_error_set(err, SM_EFORMAT, "%s: OpenMesh failed: %s", ext, e.what());
  } catch (...) {
    return sm_error_set(err, SM_EFORMAT, "%s: OpenMesh failed with an unknown exception", ext);
  }
}
