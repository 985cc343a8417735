/* fuzz_seeds_draco: Draco encodings the product never writes, for fuzz_draco_mesh's seeds.
 *
 * The daemon decodes whatever a client's encoder produced, but sm_draco_encode writes only
 * the sequential coder. These seeds reach the other decoders (edgebreaker standard and
 * valence connectivity, parallelogram and multi-parallelogram position prediction, extra
 * attributes with their own predictors, a point cloud that must be refused) with small
 * meshes, so that a fuzzer iteration costs microseconds rather than the milliseconds of the
 * 5,000-vertex files of ../shared/data, which cover the same decoders.
 * C ABI for fuzz_seeds.c; every exception is caught (a seed that cannot be made is an error
 * of the generator, reported as -1).
 */
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>

#include <draco/compression/encode.h>
#include <draco/mesh/mesh.h>
#include <draco/point_cloud/point_cloud.h>

extern "C" {
#include "sm_mesh.h"
int sm_fuzz_draco_variant(const sm_mesh *m, int variant, uint8_t **buf, size_t *len);
}

namespace {

/* Adds a per-point attribute of `nc` float components: `f(v, c)` gives vertex v's value. */
template <class F>
void add_attr(draco::PointCloud *pc, draco::GeometryAttribute::Type type, int nc, int32_t nv,
              F f) {
  draco::GeometryAttribute ga;
  ga.Init(type, nullptr, (int8_t)nc, draco::DT_FLOAT32, false, nc * sizeof(float), 0);
  draco::PointAttribute *pa = pc->attribute(pc->AddAttribute(ga, true, (uint32_t)nv));
  for (int32_t v = 0; v < nv; v++) {
    float x[4];
    for (int c = 0; c < nc; c++) x[c] = (float)f(v, c);
    pa->SetAttributeValue(draco::AttributeValueIndex((uint32_t)v), x);
  }
}

void fill(draco::PointCloud *pc, const sm_mesh *m, bool extras) {
  pc->set_num_points((uint32_t)m->nv);
  add_attr(pc, draco::GeometryAttribute::POSITION, 3, m->nv,
           [m](int32_t v, int c) { return m->V[3 * v + c]; });
  if (!extras) return;
  /* Unit vectors (the octahedral normal coder) and 2D coordinates (the texture predictor). */
  add_attr(pc, draco::GeometryAttribute::NORMAL, 3, m->nv, [m](int32_t v, int c) {
    const double *p = m->V + 3 * v;
    double r = std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    return r > 0 ? p[c] / r : (c == 2 ? 1.0 : 0.0);
  });
  add_attr(pc, draco::GeometryAttribute::TEX_COORD, 2, m->nv,
           [m](int32_t v, int c) { return 0.5 + 0.5 * m->V[3 * v + c]; });
}

int encode(const sm_mesh *m, int variant, draco::EncoderBuffer *eb) {
  draco::Encoder enc;
  /* variant: connectivity coder, speed (picks the edgebreaker flavour and predictors),
   * position quantization, extra attributes */
  static const struct {
    int method, speed, qbits;
    bool extras, cloud;
  } v[] = {
      {draco::MESH_EDGEBREAKER_ENCODING, 5, 11, false, false}, /* standard, parallelogram */
      {draco::MESH_EDGEBREAKER_ENCODING, 0, 14, false, false}, /* valence, multi-parallelogram */
      {draco::MESH_EDGEBREAKER_ENCODING, 7, 10, true, false},
      {draco::MESH_SEQUENTIAL_ENCODING, 10, 12, true, false},
      {draco::MESH_SEQUENTIAL_ENCODING, 6, 11, false, true}, /* kd-tree point cloud */
  };
  if (variant < 0 || variant >= (int)(sizeof v / sizeof v[0])) return 1;
  enc.SetSpeedOptions(v[variant].speed, v[variant].speed);
  enc.SetAttributeQuantization(draco::GeometryAttribute::POSITION, v[variant].qbits);
  enc.SetAttributeQuantization(draco::GeometryAttribute::NORMAL, 8);
  enc.SetAttributeQuantization(draco::GeometryAttribute::TEX_COORD, 10);
  if (v[variant].cloud) {
    draco::PointCloud pc;
    fill(&pc, m, false);
    return enc.EncodePointCloudToBuffer(pc, eb).ok() ? 0 : -1;
  }
  enc.SetEncodingMethod(v[variant].method);
  draco::Mesh dm;
  fill(&dm, m, v[variant].extras);
  dm.SetNumFaces((size_t)m->nf);
  for (int32_t f = 0; f < m->nf; f++) {
    draco::Mesh::Face face;
    for (int c = 0; c < 3; c++) face[c] = draco::PointIndex((uint32_t)m->F[3 * f + c]);
    dm.SetFace(draco::FaceIndex((uint32_t)f), face);
  }
  return enc.EncodeMeshToBuffer(dm, eb).ok() ? 0 : -1;
}

}  // namespace

/* Encodes m as variant `variant` (0, 1, ...) into a malloc'd buffer. 0 = done, 1 = no such
 * variant (the caller's loop ends), -1 = the encoder failed. */
extern "C" int sm_fuzz_draco_variant(const sm_mesh *m, int variant, uint8_t **buf, size_t *len) {
  try {
    draco::EncoderBuffer eb;
    int rc = encode(m, variant, &eb);
    if (rc) return rc;
    *buf = static_cast<uint8_t *>(std::malloc(eb.size()));
    if (!*buf) return -1;
    std::memcpy(*buf, eb.data(), eb.size());
    *len = eb.size();
    return 0;
  } catch (...) {
    return -1;
  }
}
