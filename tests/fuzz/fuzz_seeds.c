/* fuzz_seeds: writes the generated seed inputs of every harness, in each harness's input
 * layout (see the harness headers), into OUTDIR/<harness>/.
 *
 *   fuzz_seeds OUTDIR
 *
 * Seeds are built with the product's own encoders from small synthetic values (the
 * kind test_proto, test_meshio and test_basis_io use as vectors), so they stay valid when
 * a format changes and nothing binary needs committing. tests/fuzz/run.sh adds the small
 * files of ../shared/data; tests/fuzz/regress/ holds the committed crashers.
 */
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <zlib.h>

#include "sm_basis.h"
#include "sm_meshio.h"

int sm_fuzz_draco_variant(const sm_mesh *m, int variant, uint8_t **buf, size_t *len);
#include "sm_proto.h"
#include "sm_synth.h"

static const char *g_out;

static int write_seed(const char *harness, const char *name, const uint8_t *pre, size_t npre,
                      const uint8_t *p, size_t n) {
  char path[4096];
  snprintf(path, sizeof path, "%s/%s", g_out, harness);
  if (mkdir(path, 0777) && errno != EEXIST) return -1;
  snprintf(path, sizeof path, "%s/%s/%s", g_out, harness, name);
  FILE *f = fopen(path, "wb");
  if (!f) return -1;
  /* fwrite's buffer must not be NULL even for 0 bytes (UBSan): empty parts are skipped. */
  int ok = (!npre || fwrite(pre, 1, npre, f) == npre) && (!n || fwrite(p, 1, n, f) == n);
  return fclose(f) == 0 && ok ? 0 : -1;
}

/* ---- protocol: one body per decoder (fuzz_proto_decode), and frame streams ---- */

static uint8_t g_stream[1 << 16];
static size_t g_stream_len;

/* Records a framed message for the stream seeds and its body for the decoder seeds. */
static int proto_seed(const char *name, uint8_t dec_case, uint8_t arg, const uint8_t *frame,
                      ptrdiff_t len) {
  if (len < SM_PROTO_HEADER_LEN || (size_t)len > sizeof g_stream - g_stream_len) return -1;
  memcpy(g_stream + g_stream_len, frame, (size_t)len);
  g_stream_len += (size_t)len;
  uint8_t pre[2] = {dec_case, arg};
  return write_seed("proto_decode", name, pre, 2, frame + SM_PROTO_HEADER_LEN,
                    (size_t)len - SM_PROTO_HEADER_LEN);
}

static int proto_requests(uint8_t *b, size_t cap) {
  sm_proto_header h = {.version = 1, .request_id = 1};
  uint8_t id[SM_PROTO_ID_LEN] = {1, 2, 3};
  int rc = 0;
  sm_proto_hello_req hello = {.min_version = 1, .max_version = 2, .token = (const uint8_t *)"tok",
                              .token_len = 3};
  rc |= proto_seed("hello_req", 0, 0, b, sm_proto_enc_hello_req(b, cap, &h, &hello));
  sm_proto_ping ping = {.opaque = 0x1122334455667788ull};
  h.request_id = 2;
  rc |= proto_seed("ping", 2, 0, b, sm_proto_enc_ping(b, cap, &h, 0, &ping));
  h.opcode = SM_OP_STATS;
  rc |= proto_seed("empty", 3, 0, b, sm_proto_enc_empty(b, cap, &h));
  static const uint8_t drc[] = "DRACO\x02\x02\x01\x01";
  sm_proto_put_req put = {.flags = SM_PUT_F_PREPARE, .draco = drc, .draco_len = sizeof drc - 1};
  memcpy(put.id, id, sizeof id);
  rc |= proto_seed("put_req", 5, 0, b, sm_proto_enc_put_req(b, cap, &h, &put));
  sm_proto_id_req idr;
  memcpy(idr.id, id, sizeof id);
  rc |= proto_seed("id_req", 7, 0, b, sm_proto_enc_id_req(b, cap, &h, SM_OP_HAS_SHAPE, &idr));
  sm_proto_prepare_req prep = {.k_lb = 50, .k_elastic = 40, .eta = 0.5};
  rc |= proto_seed("prepare_req", 9, 0, b, sm_proto_enc_prepare_req(b, cap, &h, &prep));
  static const int32_t lm[4] = {0, 1, 2, 3}, init[3] = {2, -1, 0};
  sm_proto_match_req mr = {.basis = 1, .init = 2, .flags = SM_MATCH_F_WANT_YX | SM_MATCH_F_WANT_FMAP |
                           SM_MATCH_F_SINKHORN_LEVELS, .k0 = 10, .k1 = 50, .step = 5,
                           .sinkhorn_levels = 2, .eta = 1.0, .deadline_ms = 1000,
                           .landmarks = {.v = lm, .count = 4}, .init_map = {.v = init, .count = 3}};
  rc |= proto_seed("match_req", 11, 0, b, sm_proto_enc_match_req(b, cap, &h, SM_OP_MATCH, &mr));
  mr.flags = SM_MATCH_F_MULTI_START;
  mr.sinkhorn_levels = 0;
  mr.landmarks.count = mr.init_map.count = 0;
  rc |= proto_seed("distance_req", 11, 1, b, sm_proto_enc_match_req(b, cap, &h, SM_OP_DISTANCE, &mr));
  uint8_t cand[64] = {9};
  sm_proto_query_req q = {.k = 5, .mode = SM_QUERY_FULL, .candidates = cand, .n_candidates = 2};
  memcpy(q.id, id, sizeof id);
  rc |= proto_seed("query_req", 14, 0, b, sm_proto_enc_query_req(b, cap, &h, &q));
  uint8_t pingbody[8] = {1};
  sm_proto_batch_item items[2] = {{.opcode = SM_OP_PING, .payload = pingbody, .len = 8},
                                  {.opcode = SM_OP_HAS_SHAPE, .payload = id, .len = 32}};
  sm_proto_batch_req batch = {.v = items, .count = 2};
  h.flags = SM_PROTO_F_PAYLOAD_CRC;
  rc |= proto_seed("batch_req", 16, 0x80, b, sm_proto_enc_batch_req(b, cap, &h, &batch));
  sm_proto_cancel_req cancel = {.target = 1};
  rc |= proto_seed("cancel_req", 19, 0, b, sm_proto_enc_cancel_req(b, cap, &h, &cancel));
  return rc;
}

static int proto_responses(uint8_t *b, size_t cap) {
  sm_proto_header h = {.version = 1, .request_id = 1};
  int rc = 0;
  sm_proto_hello_resp hr = {.version = 2, .max_payload = 1 << 20, .max_vertices = 1000,
                            .max_faces = 2000, .max_inflight = 8, .max_batch_items = 16,
                            .max_query_k = 10, .max_k = 200, .idle_timeout_ms = 300000};
  rc |= proto_seed("hello_resp", 1, 0, b, sm_proto_enc_hello_resp(b, cap, &h, &hr));
  sm_proto_stat st[2] = {{"uptime_s", 12}, {"shapes.stored", 3}};
  sm_proto_stats_resp sr = {.v = st, .count = 2};
  rc |= proto_seed("stats_resp", 4, 0, b, sm_proto_enc_stats_resp(b, cap, &h, &sr));
  sm_proto_put_resp pr = {.id = {7}, .n_vertices = 4, .n_faces = 4, .flags = SM_PUT_R_EXISTED};
  rc |= proto_seed("put_resp", 6, 0, b, sm_proto_enc_put_resp(b, cap, &h, &pr));
  sm_proto_has_resp has = {.flags = SM_HAS_STORED | SM_HAS_PREPARED, .n_vertices = 4, .n_faces = 4};
  rc |= proto_seed("has_resp", 8, 0, b, sm_proto_enc_has_resp(b, cap, &h, &has));
  sm_proto_prepare_resp pp = {.n_vertices = 4, .n_faces = 4, .k_lb = 3, .k_elastic = 2,
                              .flags = SM_PREP_R_CACHED, .t_lb_us = 5};
  rc |= proto_seed("prepare_resp", 10, 0, b, sm_proto_enc_prepare_resp(b, cap, &h, &pp));
  static const int32_t map[3] = {1, -1, 0};
  static const double fm[4] = {1, 0, 0, -1};
  sm_proto_match_resp m = {.init_used = 1, .flags = SM_MATCH_R_HAS_DISTANCE, .orientation = 0.9,
                           .dirichlet = 2, .confidence = 0.75, .dist = {1, 2, 3, 4, -1},
                           .map_xy = {.v = map, .count = 3}, .map_yx = {.v = map, .count = 3},
                           .kC = 2, .fmap = {.v = fm, .count = 4}};
  rc |= proto_seed("match_resp_v1", 12, 1, b, sm_proto_enc_match_resp(b, cap, &h, 1, &m));
  h.version = 2;
  rc |= proto_seed("match_resp_v2", 12, 2, b, sm_proto_enc_match_resp(b, cap, &h, 2, &m));
  h.version = 1;
  sm_proto_distance_resp dr = {.dist = {1, 0.5, 0.5, 0.1, 0.2}, .t_total_us = 9};
  rc |= proto_seed("distance_resp", 13, 0, b, sm_proto_enc_distance_resp(b, cap, &h, &dr));
  sm_proto_hit hits[2] = {{.id = {1}, .distance = 0.1}, {.id = {2}, .distance = 0.2}};
  sm_proto_query_resp qr = {.n_considered = 5, .v = hits, .count = 2};
  rc |= proto_seed("query_resp", 15, 0, b, sm_proto_enc_query_resp(b, cap, &h, &qr));
  uint8_t pong[8] = {1};
  sm_proto_batch_item_resp bi = {.index = 0, .opcode = SM_OP_PING, .payload = pong, .len = 8};
  rc |= proto_seed("batch_item_resp", 17, 0, b, sm_proto_enc_batch_item_resp(b, cap, &h, &bi));
  sm_proto_batch_done bd = {.n_items = 1, .n_ok = 1};
  rc |= proto_seed("batch_done", 18, 0, b, sm_proto_enc_batch_done(b, cap, &h, &bd));
  sm_proto_error e = {.retry_after_ms = 100, .detail = 3, .msg = "busy", .msg_len = 4};
  h.opcode = SM_OP_GOAWAY;
  h.request_id = 0;
  rc |= proto_seed("error", 20, 0, b, sm_proto_enc_error(b, cap, &h, &e));
  return rc;
}

/* Frame streams: mode byte, chunk-count byte, stream, chunk sizes (fuzz_proto_frame). */
static int frame_seeds(void) {
  static const uint8_t sizes[5] = {0, 23, 1, 200, 7};
  int rc = 0;
  for (uint8_t mode = 0; mode < 16; mode += 5) {
    uint8_t pre[2] = {mode, 5}, name[32];
    snprintf((char *)name, sizeof name, "stream_mode%u", mode);
    char path[4096];
    snprintf(path, sizeof path, "%s/proto_frame", g_out);
    mkdir(path, 0777);
    snprintf(path, sizeof path, "%s/proto_frame/%s", g_out, (char *)name);
    FILE *f = fopen(path, "wb");
    if (!f) return -1;
    fwrite(pre, 1, 2, f);
    fwrite(g_stream, 1, g_stream_len, f);
    fwrite(sizes, 1, sizeof sizes, f);
    rc |= fclose(f);
  }
  uint8_t one[2] = {0, 0}; /* first frame alone, fed 7 bytes at a time */
  rc |= write_seed("proto_frame", "first_frame", one, 2, g_stream, 24 + 20);
  return rc;
}

/* ---- meshes ---- */

static const char off_txt[] =
    "OFF\n# tetrahedron plus a quad\n5 5 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 1 1\n"
    "3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n4 1 4 3 2\n";
static const char obj_txt[] =
    "# tetrahedron\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nvn 0 0 1\n"
    "f 1/1/1 3/1/1 2/1/1\nf 1//1 2//1 4//1\nf -4 -1 -2\nf 2 3 4\n";
static const char ply_txt[] =
    "ply\nformat ascii 1.0\ncomment tet\nelement vertex 4\nproperty float x\nproperty float y\n"
    "property float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n"
    "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n";
static const char stl_txt[] =
    "solid t\nfacet normal 0 0 -1\nouter loop\nvertex 0 0 0\nvertex 0 1 0\nvertex 1 0 0\n"
    "endloop\nendfacet\nfacet normal 0 -1 0\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n"
    "vertex 0 0 1\nendloop\nendfacet\nendsolid t\n";

static int gzip_bytes(const uint8_t *in, size_t n, uint8_t *out, size_t *outlen) {
  z_stream zs;
  memset(&zs, 0, sizeof zs);
  if (deflateInit2(&zs, 9, Z_DEFLATED, 16 + MAX_WBITS, 8, Z_DEFAULT_STRATEGY) != Z_OK) return -1;
  zs.next_in = (Bytef *)(uintptr_t)in;
  zs.avail_in = (uInt)n;
  zs.next_out = out;
  zs.avail_out = (uInt)*outlen;
  int zr = deflate(&zs, Z_FINISH);
  *outlen = zs.total_out;
  deflateEnd(&zs);
  return zr == Z_STREAM_END ? 0 : -1;
}

/* A mesh file as is (format byte fmt) and gzip'd (fmt + 4). */
static int mesh_seed(uint8_t fmt, const char *name, const void *p, size_t n) {
  uint8_t gz[16384];
  size_t gzlen = sizeof gz;
  char gzname[64];
  uint8_t gzfmt = (uint8_t)(fmt + 4);
  snprintf(gzname, sizeof gzname, "%s.gz", name);
  int rc = write_seed("meshio", name, &fmt, 1, p, n);
  if (gzip_bytes(p, n, gz, &gzlen)) return -1;
  return rc | write_seed("meshio", gzname, &gzfmt, 1, gz, gzlen);
}

static void st_f32(uint8_t *p, float x) { memcpy(p, &x, 4); } /* little-endian hosts only */

/* Binary STL (80-byte header, count, 50 bytes a facet) and binary little-endian PLY of m,
 * named <stem>.stl and <stem>.ply. */
static int binary_mesh_seeds(const char *stem, const sm_mesh *m) {
  char name[48];
  uint8_t buf[8192];
  memset(buf, 0, 84);
  memcpy(buf, "binary stl seed", 15);
  size_t nf = m->nf < 100 ? (size_t)m->nf : 100, off = 84;
  buf[80] = (uint8_t)nf;
  for (size_t f = 0; f < nf; f++, off += 50) {
    memset(buf + off, 0, 50);
    for (int c = 0; c < 3; c++)
      for (int d = 0; d < 3; d++)
        st_f32(buf + off + 12 + 12 * c + 4 * d, (float)m->V[3 * m->F[3 * f + c] + d]);
  }
  snprintf(name, sizeof name, "%s.stl", stem);
  int rc = mesh_seed(3, name, buf, off);
  int len = snprintf((char *)buf, sizeof buf,
                     "ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\n"
                     "property float y\nproperty float z\nelement face %zu\n"
                     "property list uchar int vertex_indices\nend_header\n", m->nv, nf);
  off = (size_t)len;
  for (int32_t v = 0; v < m->nv && off + 12 < sizeof buf; v++, off += 12)
    for (int d = 0; d < 3; d++) st_f32(buf + off + 4 * d, (float)m->V[3 * v + d]);
  for (size_t f = 0; f < nf && off + 13 < sizeof buf; f++, off += 13) {
    buf[off] = 3;
    memcpy(buf + off + 1, m->F + 3 * f, 12);
  }
  snprintf(name, sizeof name, "%s.ply", stem);
  return rc | mesh_seed(2, name, buf, off);
}

/* The other Draco coders (fuzz_seeds_draco.cpp), each variant of `m` one seed. */
static int draco_variant_seeds(const char *stem, const sm_mesh *m) {
  int rc = 0;
  for (int v = 0;; v++) {
    uint8_t *drc = NULL;
    size_t len = 0;
    int e = sm_fuzz_draco_variant(m, v, &drc, &len);
    if (e == 1) break;
    if (e) return -1;
    char name[48];
    snprintf(name, sizeof name, "%s_variant%d.drc", stem, v);
    rc |= write_seed("draco_mesh", name, NULL, 0, drc, len);
    free(drc);
  }
  return rc;
}

/* m and a shifted copy of it: two components, as scans and the dragon file have. */
static sm_mesh *two_components(const sm_mesh *m) {
  sm_mesh *t = NULL;
  if (sm_mesh_alloc(2 * (int64_t)m->nv, 2 * m->nf, NULL, &t, NULL)) return NULL;
  for (int32_t v = 0; v < 2 * m->nv; v++)
    for (int d = 0; d < 3; d++) t->V[3 * v + d] = m->V[3 * (v % m->nv) + d] + (v >= m->nv && d == 0 ? 3 : 0);
  for (int64_t f = 0; f < 2 * m->nf; f++)
    for (int c = 0; c < 3; c++) t->F[3 * f + c] = m->F[3 * (f % m->nf) + c] + (f >= m->nf ? m->nv : 0);
  return t;
}

static int mesh_seeds(void) {
  sm_mesh *m = NULL;
  if (sm_synth_icosphere(1, &m, NULL)) return -1;
  int rc = mesh_seed(0, "tet.off", off_txt, sizeof off_txt - 1);
  rc |= mesh_seed(1, "tet.obj", obj_txt, sizeof obj_txt - 1);
  rc |= mesh_seed(2, "tet.ply", ply_txt, sizeof ply_txt - 1);
  rc |= mesh_seed(3, "tet.stl", stl_txt, sizeof stl_txt - 1);
  rc |= binary_mesh_seeds("binary", m); /* 80 faces: about 4 KB of STL */
  sm_mesh *tet = NULL;               /* the same readers on a few hundred bytes */
  if (sm_mesh_alloc(4, 4, NULL, &tet, NULL) == 0) {
    static const int32_t tet_f[12] = {0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3};
    memset(tet->V, 0, 12 * sizeof *tet->V);
    for (int v = 1; v < 4; v++) tet->V[3 * v + v - 1] = 1;
    memcpy(tet->F, tet_f, sizeof tet_f);
    rc |= binary_mesh_seeds("binary_tet", tet);
    sm_mesh_destroy(tet);
  } else {
    rc = -1;
  }
  for (int q = 0; q <= 11; q += 11) { /* raw float32 and quantized positions */
    uint8_t *drc = NULL;
    size_t len = 0;
    char name[32];
    snprintf(name, sizeof name, "icosphere_q%d.drc", q);
    if (sm_draco_encode(m, q, &drc, &len, NULL)) rc = -1;
    else rc |= write_seed("draco_mesh", name, NULL, 0, drc, len);
    free(drc);
  }
  rc |= draco_variant_seeds("icosphere", m);
  sm_mesh *two = two_components(m);
  if (two) rc |= draco_variant_seeds("two", two);
  else rc = -1;
  sm_mesh_destroy(two);
  sm_mesh_destroy(m);
  return rc;
}

/* ---- a basis file: a small hand-filled basis, with and without gram_L ---- */

static int basis_seeds(void) {
  enum { N = 6, K = 3 };
  double evals[K] = {0, 1.5, 2.5}, phi[N * K], mass[N], gram[K * K] = {1, 0, 0, 0.5, 1, 0, 0, 0, 1};
  for (int i = 0; i < N * K; i++) phi[i] = (i % 7) * 0.25 - 0.5;
  for (int i = 0; i < N; i++) mass[i] = 1.0 / N;
  sm_basis b = {.kind = SM_BASIS_LB, .n = N, .k = K, .n_components = 1, .mesh_hash = 42,
                .evals = evals, .phi = phi, .mass = mass};
  int rc = 0;
  for (int g = 0; g < 2; g++) {
    uint8_t *buf = NULL, mode = 0;
    size_t len = 0;
    if (g) {
      b.kind = SM_BASIS_ELASTIC;
      b.eta = 0.1;
      b.n_kernel = 6;
      b.gram_L = gram;
    }
    if (sm_basis_serialize(&b, &buf, &len, NULL)) return -1;
    rc |= write_seed("basis_io", g ? "elastic_gram.smb" : "lb.smb", &mode, 1, buf, len);
    free(buf);
  }
  return rc;
}

/* ---- the connection state machine (fuzz_srv_conn): scripts of peer and loop events ---- */

static size_t cmd(uint8_t *b, size_t n, uint8_t op, const uint8_t *d, size_t len) {
  b[n] = op;
  b[n + 1] = (uint8_t)len;
  b[n + 2] = (uint8_t)(len >> 8);
  if (len) memcpy(b + n + 3, d, len);
  return n + 3 + len;
}

/* A frame for command 1: opcode, flags, request id, version, cut, then the body. */
static size_t frame_cmd(uint8_t *b, size_t n, uint8_t op, uint8_t flags, uint8_t rid,
                        const uint8_t *body, size_t len) {
  uint8_t f[128] = {op, flags, rid, 2, 7};
  if (len) memcpy(f + 5, body, len);
  return cmd(b, n, 1, f, 5 + len);
}

static int conn_seeds(void) {
  static uint8_t b[1 << 17];
  uint8_t ping[8] = {1, 2, 3, 4, 5, 6, 7, 8}, id[32] = {1}, two = 2, one = 1, z = 0;
  uint8_t cancel[4] = {3, 0, 0, 0}, work[40] = {1, 9, 9};
  size_t n = 0;
  b[n++] = 0x3E; /* 2 MiB budget, 64 in flight, queue 64, no token, 1 MiB payloads */
  n = cmd(b, n, 2, &two, 1); /* HELLO, versions 1..2 */
  n = frame_cmd(b, n, SM_OP_PING, 0, 2, ping, sizeof ping);
  n = frame_cmd(b, n, SM_OP_HAS_SHAPE, SM_PROTO_F_PAYLOAD_CRC, 4, id, sizeof id);
  n = frame_cmd(b, n, SM_OP_STATS, 0, 5, NULL, 0);
  n = frame_cmd(b, n, SM_OP_MATCH, 0, 3, work, sizeof work);
  n = frame_cmd(b, n, SM_OP_CANCEL, 0, 6, cancel, sizeof cancel);
  n = frame_cmd(b, n, SM_OP_QUERY, 0, 7, work, 8);
  n = cmd(b, n, 3, &two, 1); /* run jobs */
  n = cmd(b, n, 4, &one, 1); /* read answers */
  n = cmd(b, n, 5, &one, 1); /* tick */
  n = frame_cmd(b, n, SM_OP_DROP_SHAPE, 0, 8, id, sizeof id);
  n = cmd(b, n, 6, &z, 1);   /* drain */
  n = cmd(b, n, 4, &z, 1);
  int rc = write_seed("srv_conn", "session", NULL, 0, b, n);
  /* Every request the codec seeds hold, as one raw upload, with small buffers. */
  n = 0;
  b[n++] = 0x00; /* 16 KiB budget, 1 in flight, queue 0 */
  size_t m = g_stream_len < 60000 ? g_stream_len : 60000;
  n = cmd(b, n, 0, g_stream, m);
  n = cmd(b, n, 7, NULL, 0);
  n = cmd(b, n, 4, &one, 1);
  rc |= write_seed("srv_conn", "raw_stream", NULL, 0, b, n);
  return rc;
}

int main(int argc, char **argv) {
  if (argc != 2) {
    fprintf(stderr, "usage: %s OUTDIR\n", argv[0]);
    return 2;
  }
  g_out = argv[1];
  if (mkdir(g_out, 0777) && errno != EEXIST) {
    perror(g_out);
    return 1;
  }
  static uint8_t frame[1 << 16];
  int rc = proto_requests(frame, sizeof frame);
  rc |= proto_responses(frame, sizeof frame);
  rc |= frame_seeds();
  rc |= conn_seeds();
  rc |= mesh_seeds();
  rc |= basis_seeds();
  if (rc) fprintf(stderr, "%s: could not write every seed\n", argv[0]);
  return rc ? 1 : 0;
}
