/* sm_draco_io: Draco decode/encode behind a C ABI.
 *
 * DESIGN
 *   Decoding: the result's vertex i is Draco point i, reading the position through the
 *   attribute's point-to-value map (edgebreaker files share values between points, and a
 *   point is what the faces index). The counts the bitstream announces are checked
 *   against the limits before Draco decodes anything (peek_counts), and the decoded counts
 *   again before the sm_mesh is allocated.
 *   Encoding: the Draco mesh is built with one point per vertex and an identity
 *   point-to-value map, and is never passed through Draco's deduplication, so the
 *   sequential coder writes points and faces in our order and a decode gives them back in
 *   that order.
 */
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <memory>
#include <new>

#include <draco/compression/config/compression_shared.h>
#include <draco/compression/decode.h>
#include <draco/compression/encode.h>
#include <draco/compression/point_cloud/point_cloud_decoder.h>
#include <draco/core/varint_decoding.h>
#include <draco/mesh/mesh.h>
#include <draco/metadata/geometry_metadata.h>
#include <draco/metadata/metadata_decoder.h>

extern "C" {
#include "sm_meshio.h"
}

namespace {

/* Reads one count of the connectivity header: a varint from bitstream 2.2 on (2.0 for the
 * edgebreaker vertex count), a little-endian uint32 before. */
bool read_count(draco::DecoderBuffer *b, bool varint, uint32_t *out) {
  return varint ? draco::DecodeVarint(out, b) : b->Decode(out);
}

/* The vertex and face counts a mesh bitstream announces, read without decoding it (the
 * layout of Draco's sequential and edgebreaker connectivity headers), so that an
 * over-limit mesh is refused before Draco allocates anything for it. Edgebreaker's count
 * is of encoded vertices, which attribute seams can only increase. false = not readable:
 * the caller refuses the file, since Draco would size its tables from those counts. */
bool peek_counts(const uint8_t *buf, size_t len, int64_t *nv, int64_t *nf) {
  draco::DecoderBuffer b;
  b.Init(reinterpret_cast<const char *>(buf), len);
  draco::DracoHeader h;
  if (!draco::PointCloudDecoder::DecodeHeader(&b, &h).ok()) return false;
  if (h.encoder_type != draco::TRIANGULAR_MESH) return false;
  uint16_t version = DRACO_BITSTREAM_VERSION(h.version_major, h.version_minor);
  b.set_bitstream_version(version);
  /* Draco reads metadata from bitstream 1.3 on only; before, the flag is ignored (found by
   * fuzz_draco_mesh: a 1.1 file with the flag made this peek fail and Draco reserve 5 GB). */
  if (version >= DRACO_BITSTREAM_VERSION(1, 3) && (h.flags & METADATA_FLAG_MASK)) {
    draco::MetadataDecoder md;
    draco::GeometryMetadata gm;
    if (!md.DecodeGeometryMetadata(&b, &gm)) return false;
  }
  uint32_t v = 0, f = 0;
  bool v22 = version >= DRACO_BITSTREAM_VERSION(2, 2);
  if (h.encoder_method == draco::MESH_SEQUENTIAL_ENCODING) {
    if (!read_count(&b, v22, &f) || !read_count(&b, v22, &v)) return false;
  } else if (h.encoder_method == draco::MESH_EDGEBREAKER_ENCODING) {
    bool v20 = version >= DRACO_BITSTREAM_VERSION(2, 0);
    uint8_t traversal;
    uint32_t new_vertices;
    if (!b.Decode(&traversal)) return false;
    if (!v22 && !read_count(&b, v20, &new_vertices)) return false;
    if (!read_count(&b, v20, &v) || !read_count(&b, v20, &f)) return false;
  } else {
    return false;
  }
  *nv = v;
  *nf = f;
  return true;
}

int decode_impl(const uint8_t *buf, size_t len, const sm_limits *lim, sm_mesh **out,
                sm_error *err) {
  draco::DecoderBuffer db;
  db.Init(reinterpret_cast<const char *>(buf), len);
  auto type = draco::Decoder::GetEncodedGeometryType(&db);
  if (!type.ok())
    return sm_error_set(err, SM_EFORMAT, "draco: bad header (%zu bytes): %s", len,
                        type.status().error_msg());
  if (type.value() == draco::POINT_CLOUD)
    return sm_error_set(err, SM_EUNSUPPORTED,
                        "draco: the bitstream is a point cloud, not a mesh (no faces)");
  if (type.value() != draco::TRIANGULAR_MESH)
    return sm_error_set(err, SM_EFORMAT, "draco: unknown geometry type %d", (int)type.value());
  int64_t announced_v, announced_f;
  if (!peek_counts(buf, len, &announced_v, &announced_f))
    return sm_error_set(err, SM_EFORMAT,
                        "draco: cannot read the vertex and face counts from the mesh header "
                        "(%zu bytes)", len);
  int rc = sm_limits_check(lim, announced_v, announced_f, err);
  if (rc) return rc;

  db.Init(reinterpret_cast<const char *>(buf), len);
  draco::Decoder dec;
  auto res = dec.DecodeMeshFromBuffer(&db);
  if (!res.ok())
    return sm_error_set(err, SM_EFORMAT, "draco: decode failed (%zu bytes): %s", len,
                        res.status().error_msg());
  std::unique_ptr<draco::Mesh> dm = std::move(res).value();
  if (!dm) return sm_error_set(err, SM_EFORMAT, "draco: decoder returned no mesh");

  const draco::PointAttribute *pos =
      dm->GetNamedAttribute(draco::GeometryAttribute::POSITION);
  if (!pos)
    return sm_error_set(err, SM_EUNSUPPORTED, "draco: mesh has no POSITION attribute");
  if (pos->num_components() < 2 || pos->num_components() > 4)
    return sm_error_set(err, SM_EUNSUPPORTED, "draco: POSITION has %d components",
                        (int)pos->num_components());
  /* Draco converts a DT_BOOL (or unknown) position by loading raw bytes as bool, which is
   * undefined behaviour (found by tests/fuzz/fuzz_draco_mesh): positions must be numbers. */
  if (pos->data_type() < draco::DT_INT8 || pos->data_type() > draco::DT_FLOAT64)
    return sm_error_set(err, SM_EUNSUPPORTED, "draco: POSITION has non-numeric type %d",
                        (int)pos->data_type());

  int64_t nv = dm->num_points(), nf = dm->num_faces();
  rc = sm_limits_check(lim, nv, nf, err);
  if (rc) return rc;
  sm_mesh *m;
  if ((rc = sm_mesh_alloc(nv, nf, lim, &m, err))) return rc;
  std::unique_ptr<sm_mesh, void (*)(sm_mesh *)> guard(m, sm_mesh_destroy);

  for (int64_t i = 0; i < nv; i++) {
    double p[4] = {0, 0, 0, 0};
    draco::AttributeValueIndex av = pos->mapped_index(draco::PointIndex((uint32_t)i));
    if (av.value() >= pos->size() ||
        !pos->ConvertValue<double>(av, (int8_t)pos->num_components(), p))
      return sm_error_set(err, SM_EFORMAT, "draco: point %lld has no readable position",
                          (long long)i);
    std::memcpy(m->V + 3 * i, p, 3 * sizeof(double));
  }
  for (int64_t f = 0; f < nf; f++) {
    const draco::Mesh::Face &face = dm->face(draco::FaceIndex((uint32_t)f));
    for (int c = 0; c < 3; c++) m->F[3 * f + c] = (int32_t)face[c].value();
  }
  *out = guard.release();
  return 0;
}

/* Draco would encode garbage or crash on these, so they are refused up front. */
int check_encodable(const sm_mesh *m, sm_error *err) {
  if (m->nv <= 0 || m->nf <= 0)
    return sm_error_set(err, SM_EEMPTY, "draco encode: mesh has %d vertices and %d faces",
                        (int)m->nv, (int)m->nf);
  for (int64_t i = 0; i < 3 * (int64_t)m->nv; i++)
    if (!std::isfinite(m->V[i]) || std::fabs(m->V[i]) > 3.4e38)
      return sm_error_set(err, SM_ENONFINITE,
                          "draco encode: vertex %lld coordinate %d is not a finite float",
                          (long long)(i / 3), (int)(i % 3));
  for (int64_t i = 0; i < 3 * (int64_t)m->nf; i++)
    if (m->F[i] < 0 || m->F[i] >= m->nv)
      return sm_error_set(err, SM_ERANGE,
                          "draco encode: face %lld refers to vertex %d, mesh has %d",
                          (long long)(i / 3), (int)m->F[i], (int)m->nv);
  return 0;
}

std::unique_ptr<draco::Mesh> to_draco(const sm_mesh *m) {
  std::unique_ptr<draco::Mesh> dm(new draco::Mesh());
  dm->set_num_points((uint32_t)m->nv);
  draco::GeometryAttribute ga;
  ga.Init(draco::GeometryAttribute::POSITION, nullptr, 3, draco::DT_FLOAT32, false,
          3 * sizeof(float), 0);
  int att = dm->AddAttribute(ga, /*identity_mapping=*/true, (uint32_t)m->nv);
  draco::PointAttribute *pa = dm->attribute(att);
  for (int32_t v = 0; v < m->nv; v++) {
    float p[3] = {(float)m->V[3 * v], (float)m->V[3 * v + 1], (float)m->V[3 * v + 2]};
    pa->SetAttributeValue(draco::AttributeValueIndex((uint32_t)v), p);
  }
  dm->SetNumFaces((size_t)m->nf);
  for (int32_t f = 0; f < m->nf; f++) {
    draco::Mesh::Face face;
    for (int c = 0; c < 3; c++) face[c] = draco::PointIndex((uint32_t)m->F[3 * f + c]);
    dm->SetFace(draco::FaceIndex((uint32_t)f), face);
  }
  return dm;
}

int encode_impl(const sm_mesh *m, int quant_bits, uint8_t **buf, size_t *len, sm_error *err) {
  int rc = check_encodable(m, err);
  if (rc) return rc;
  std::unique_ptr<draco::Mesh> dm = to_draco(m);
  draco::Encoder enc;
  enc.SetEncodingMethod(draco::MESH_SEQUENTIAL_ENCODING);
  if (quant_bits > 0) enc.SetAttributeQuantization(draco::GeometryAttribute::POSITION, quant_bits);
  draco::EncoderBuffer eb;
  draco::Status st = enc.EncodeMeshToBuffer(*dm, &eb);
  if (!st.ok()) return sm_error_set(err, SM_EFORMAT, "draco encode failed: %s", st.error_msg());
  uint8_t *b = static_cast<uint8_t *>(std::malloc(eb.size() ? eb.size() : 1));
  if (!b) return sm_error_set(err, SM_ENOMEM, "draco encode: cannot allocate %zu bytes", eb.size());
  std::memcpy(b, eb.data(), eb.size());
  *buf = b;
  *len = eb.size();
  return 0;
}

}  // namespace

extern "C" int sm_draco_decode(const uint8_t *buf, size_t len, const sm_limits *lim,
                               sm_mesh **out, sm_error *err) {
  if (!out || (!buf && len)) return sm_error_set(err, SM_EINVAL, "sm_draco_decode: null argument");
  *out = NULL;
  if (len == 0) return sm_error_set(err, SM_EFORMAT, "draco: empty buffer");
  try {
    return decode_impl(buf, len, lim, out, err);
  } catch (const std::bad_alloc &) {
    return sm_error_set(err, SM_ENOMEM, "draco: out of memory while decoding %zu bytes", len);
  } catch (const std::exception &e) {
    return sm_error_set(err, SM_EFORMAT, "draco: decode failed: %s", e.what());
  } catch (...) {
    return sm_error_set(err, SM_EFORMAT, "draco: decode failed with an unknown exception");
  }
}

extern "C" int sm_draco_encode(const sm_mesh *m, int quant_bits, uint8_t **buf, size_t *len,
                               sm_error *err) {
  if (!m || !buf || !len) return sm_error_set(err, SM_EINVAL, "sm_draco_encode: null argument");
  *buf = NULL;
  *len = 0;
  if (quant_bits < 0 || quant_bits > 30)
    return sm_error_set(err, SM_EINVAL, "draco encode: quant_bits=%d, must be 0..30", quant_bits);
  try {
    return encode_impl(m, quant_bits, buf, len, err);
  } catch (const std::bad_alloc &) {
    return sm_error_set(err, SM_ENOMEM, "draco encode: out of memory");
  } catch (const std::exception &e) {
    return sm_error_set(err, SM_EFORMAT, "draco encode failed: %s", e.what());
  } catch (...) {
    return sm_error_set(err, SM_EFORMAT, "draco encode failed with an unknown exception");
  }
}
