/* test_proto: the wire codec (protocol/sm_proto.h) and SHA-256 (protocol/sm_sha256.h).
 *   - CRC32C and SHA-256 against published vectors;
 *   - every message type: encode -> parse -> decode -> fields equal, and re-encoding the
 *     decoded views gives the same bytes; encoders report the needed size when short;
 *   - every prefix of a multi-frame stream: complete frames parse, the rest is PARTIAL,
 *     and no byte past the given length is read (inputs end flush against a PROT_NONE
 *     page, so an over-read faults);
 *   - random splits of the stream give the same frames;
 *   - malformed headers rejected from their 24 bytes alone (before the payload exists,
 *     i.e. before a receiver would allocate), with the specific error;
 *   - malformed payloads: every truncation, trailing bytes, counts whose byte size would
 *     overflow 32 bits, out-of-range enums, reserved fields, disallowed opcodes;
 *   - versions: the catalogue's frames after HELLO carry the highest version (SM_PROTO_VERSION_MAX);
 *     the MATCH response in both layouts (version 1 is version 2 without the trailing
 *     confidence), each decoder refusing the other's, and a confidence that is NaN or
 *     outside [0, 1] refused by the encoder and the decoder. */
#define _DEFAULT_SOURCE /* MAP_ANONYMOUS */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

#include "sm_proto.h"
#include "sm_sha256.h"
#include "sm_test.h"

/* ---- guard page placement ---- */
typedef struct guard {
  uint8_t *base;
  size_t maplen;
  const uint8_t *p; /* the copy, ending exactly at the PROT_NONE page */
} guard;

static guard guard_place(const void *src, size_t n) {
  size_t ps = (size_t)sysconf(_SC_PAGESIZE);
  size_t data_pages = (n + ps - 1) / ps;
  if (data_pages == 0) data_pages = 1;
  guard g;
  g.maplen = (data_pages + 1) * ps;
  g.base = mmap(NULL, g.maplen, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
  REQUIRE(g.base != MAP_FAILED);
  REQUIRE(mprotect(g.base + data_pages * ps, ps, PROT_NONE) == 0);
  uint8_t *dst = g.base + data_pages * ps - n;
  if (n) memcpy(dst, src, n);
  g.p = dst;
  return g;
}
static void guard_free(guard *g) { munmap(g->base, g->maplen); }

/* ---- deterministic PRNG (xorshift64*) ---- */
static uint64_t rng_state = 0x9E3779B97F4A7C15ull;
static uint64_t rng(void) {
  rng_state ^= rng_state >> 12;
  rng_state ^= rng_state << 25;
  rng_state ^= rng_state >> 27;
  return rng_state * 0x2545F4914F6CDD1Dull;
}

static void hex(const uint8_t *d, size_t n, char *out) {
  for (size_t i = 0; i < n; i++) sprintf(out + 2 * i, "%02x", d[i]);
}

/* ---- vectors ---- */
static void test_crc32c(void) {
  CHECK_MSG(sm_proto_crc32c(0, "123456789", 9) == 0xE3069283u, "got %08x",
            sm_proto_crc32c(0, "123456789", 9));
  uint8_t z[32], f[32], inc[32], dec[32];
  memset(z, 0, 32);
  memset(f, 0xFF, 32);
  for (int i = 0; i < 32; i++) inc[i] = (uint8_t)i, dec[i] = (uint8_t)(31 - i);
  /* RFC 3720 §B.4 */
  CHECK(sm_proto_crc32c(0, z, 32) == 0x8A9136AAu);
  CHECK(sm_proto_crc32c(0, f, 32) == 0x62A8AB43u);
  CHECK(sm_proto_crc32c(0, inc, 32) == 0x46DD794Eu);
  CHECK(sm_proto_crc32c(0, dec, 32) == 0x113FDB5Cu);
  CHECK(sm_proto_crc32c(0, "", 0) == 0);
  /* running form equals one shot */
  uint32_t c = sm_proto_crc32c(0, "1234", 4);
  CHECK(sm_proto_crc32c(c, "56789", 5) == 0xE3069283u);
}

static void check_sha(const void *msg, size_t n, const char *want) {
  uint8_t d[32];
  char h[65];
  sm_sha256(msg, n, d);
  hex(d, 32, h);
  CHECK_MSG(strcmp(h, want) == 0, "len %zu: %s != %s", n, h, want);
  /* the same through uneven update pieces */
  sm_sha256_ctx c;
  sm_sha256_init(&c);
  size_t off = 0, step = 1;
  while (off < n) {
    size_t k = n - off < step ? n - off : step;
    sm_sha256_update(&c, (const uint8_t *)msg + off, k);
    off += k;
    step = step * 3 + 1;
  }
  sm_sha256_final(&c, d);
  hex(d, 32, h);
  CHECK_MSG(strcmp(h, want) == 0, "pieces, len %zu: %s != %s", n, h, want);
}

static void test_sha256(void) {
  /* FIPS 180-4 examples (NIST CSRC "SHA256.pdf") */
  check_sha("", 0, "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
  check_sha("abc", 3, "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  const char *m448 = "abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq";
  check_sha(m448, strlen(m448),
            "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
  const char *m896 = "abcdefghbcdefghicdefghijdefghijkefghijklfghijklmghijklmnhijklmno"
                     "ijklmnopjklmnopqklmnopqrlmnopqrsmnopqrstnopqrstu";
  check_sha(m896, strlen(m896),
            "cf5b16a778af8380036ce59e7b0492370b249b11e8f07a51afac45037afee9d1");
  char *mil = malloc(1000000);
  REQUIRE(mil);
  memset(mil, 'a', 1000000);
  check_sha(mil, 1000000, "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0");
  free(mil);
  /* padding boundaries: 55, 56, 63, 64 bytes (one vs two final blocks) agree between the
   * one-shot and byte-at-a-time paths (checked inside check_sha via a self reference) */
  uint8_t b[64], d1[32];
  memset(b, 'x', 64);
  size_t lens[] = {55, 56, 63, 64};
  for (int i = 0; i < 4; i++) {
    char h[65];
    sm_sha256(b, lens[i], d1);
    hex(d1, 32, h);
    check_sha(b, lens[i], h);
  }
}

/* ---- the message catalogue ---- */
enum kind {
  K_HELLO_REQ, K_HELLO_RESP, K_PING_REQ, K_PING_RESP, K_STATS_REQ, K_STATS_RESP,
  K_PUT_REQ, K_PUT_RESP, K_HAS_REQ, K_HAS_RESP, K_DROP_REQ, K_DROP_RESP, K_PREP_REQ,
  K_PREP_RESP, K_MATCH_REQ, K_MATCH_RESP, K_DIST_REQ, K_DIST_RESP, K_QUERY_REQ,
  K_QUERY_RESP, K_BATCH_REQ, K_BATCH_ITEM, K_BATCH_DONE, K_CANCEL_REQ, K_CANCEL_RESP,
  K_ERROR, K_GOAWAY, K_COUNT
};
static const char *kind_name[K_COUNT] = {
    "hello_req", "hello_resp", "ping_req", "ping_resp", "stats_req", "stats_resp",
    "put_req", "put_resp", "has_req", "has_resp", "drop_req", "drop_resp", "prep_req",
    "prep_resp", "match_req", "match_resp", "dist_req", "dist_resp", "query_req",
    "query_resp", "batch_req", "batch_item", "batch_done", "cancel_req", "cancel_resp",
    "error", "goaway"};
/* kinds whose last field is an open byte tail (trailing bytes are content, not error) */
static int open_tail(int k) { return k == K_PUT_REQ || k == K_BATCH_ITEM; }

static uint8_t ID_A[32], ID_B[32], ID_C[32];
static const uint8_t DRACO[] = {'D', 'R', 'A', 'C', 'O', 2, 2, 0, 1, 0, 0, 9, 8, 7};
static const int32_t LANDMARKS[] = {0, 5, 17, 3, 9, 9};
static const int32_t INIT_MAP[] = {4, 3, -1, 1, 0};
static const int32_t MAP_XY[] = {2, 0, 1, -1, 3, 4, 4};
static const int32_t MAP_YX[] = {1, 2, 0, 4, 6};
static const double FMAP[] = {1.0, -0.25, 0.5, 1e-300, -0.0, 3.5, 2.0, -7.0, 0.125};
static const char TOKEN[] = "s3cr3t-token";
static const char ERRMSG[] = "mesh has 0 faces";
static const sm_proto_stat STATS[] = {{"shapes", 42}, {"bases_cached", 7},
                                      {"uptime_s", 0xFFFFFFFFFFull}, {"queue.depth", 0}};

static sm_proto_hello_req m_hello_req(void) {
  sm_proto_hello_req m = {1, 1, 1u << 24, {0}, (const uint8_t *)TOKEN,
                          (uint16_t)strlen(TOKEN)};
  memcpy(m.affinity, ID_A, 32);
  return m;
}
static sm_proto_hello_resp m_hello_resp(void) {
  return (sm_proto_hello_resp){1, 64u << 20, 2000000, 4000000, 64, 256, 100, 300, 30000,
                               SM_HELLO_F_AUTH_REQUIRED};
}
static sm_proto_put_req m_put_req(void) {
  sm_proto_put_req m = {{0}, SM_PUT_F_PREPARE, DRACO, sizeof DRACO};
  sm_sha256(DRACO, sizeof DRACO, m.id);
  return m;
}
static sm_proto_put_resp m_put_resp(void) {
  sm_proto_put_resp m = {{0}, 5103, 10202, SM_PUT_R_EXISTED};
  memcpy(m.id, ID_A, 32);
  return m;
}
static sm_proto_prepare_req m_prep_req(void) {
  sm_proto_prepare_req m = {{0}, 100, 80, 1e-4};
  memcpy(m.id, ID_B, 32);
  return m;
}
static sm_proto_prepare_resp m_prep_resp(void) {
  return (sm_proto_prepare_resp){5000, 9996, 100, 100, SM_PREP_R_CACHED, 11, 2222, 333333,
                                 4444444444ull};
}
static sm_proto_match_req m_match_req(int distance) {
  sm_proto_match_req m;
  memset(&m, 0, sizeof m);
  memcpy(m.x, ID_A, 32);
  memcpy(m.y, ID_B, 32);
  m.basis = 3;
  m.init = 1;
  m.flags = distance ? SM_MATCH_F_MULTI_START | SM_MATCH_F_SINKHORN_LEVELS
                     : SM_MATCH_F_WANT_YX | SM_MATCH_F_WANT_FMAP | SM_MATCH_F_WANT_DISTANCE |
                           SM_MATCH_F_SINGLE_START;
  m.sinkhorn_levels = distance ? 3 : 0;
  m.k0 = 20;
  m.k1 = 100;
  m.step = 5;
  m.eta = 2.5e-4;
  m.deadline_ms = 60000;
  m.landmarks = (sm_proto_i32s){LANDMARKS, NULL, 6};
  m.init_map = (sm_proto_i32s){distance ? NULL : INIT_MAP, NULL, distance ? 0 : 5};
  return m;
}
static sm_proto_match_resp m_match_resp(void) {
  sm_proto_match_resp m;
  memset(&m, 0, sizeof m);
  m.init_used = 2;
  m.flags = SM_MATCH_R_FLIPPED | SM_MATCH_R_HAS_DISTANCE;
  m.orientation = 0.93;
  m.dirichlet = 6.8;
  m.confidence = 0.8125;
  m.dist = (sm_proto_dist){0.05, 0.04, 0.06, 0.02, -1.0};
  m.t_prepare_us = 1;
  m.t_init_us = 2;
  m.t_refine_us = 3;
  m.t_distance_us = 4;
  m.t_total_us = 10;
  m.map_xy = (sm_proto_i32s){MAP_XY, NULL, 7};
  m.map_yx = (sm_proto_i32s){MAP_YX, NULL, 5};
  m.kC = 3;
  m.fmap = (sm_proto_f64s){FMAP, NULL, 9};
  return m;
}
static uint8_t CANDS[64];
static sm_proto_query_req m_query_req(void) {
  sm_proto_query_req m = {{0}, 10, SM_QUERY_FULL, 5000, CANDS, 2};
  memcpy(m.id, ID_C, 32);
  return m;
}
static sm_proto_hit HITS[2];
static sm_proto_query_resp m_query_resp(void) {
  return (sm_proto_query_resp){1234, 999, HITS, NULL, 2};
}
static uint8_t ITEM_PING[8], ITEM_HAS[32], ITEM_MATCH[256];
static size_t item_match_len;
static sm_proto_batch_item ITEMS[3];
static sm_proto_batch_req m_batch_req(void) { return (sm_proto_batch_req){ITEMS, NULL, 0, 3}; }

static void build_fixtures(void) {
  sm_sha256("A", 1, ID_A);
  sm_sha256("B", 1, ID_B);
  sm_sha256("C", 1, ID_C);
  memcpy(CANDS, ID_A, 32);
  memcpy(CANDS + 32, ID_B, 32);
  memcpy(HITS[0].id, ID_A, 32);
  HITS[0].distance = 0.0;
  memcpy(HITS[1].id, ID_B, 32);
  HITS[1].distance = 0.75;
  sm_proto_ping pg = {0x0102030405060708ull};
  REQUIRE(sm_proto_enc_ping(ITEM_PING, sizeof ITEM_PING, NULL, 0, &pg) == 8);
  sm_proto_id_req idr;
  memcpy(idr.id, ID_C, 32);
  REQUIRE(sm_proto_enc_id_req(ITEM_HAS, sizeof ITEM_HAS, NULL, SM_OP_HAS_SHAPE, &idr) == 32);
  sm_proto_match_req mr = m_match_req(1);
  ptrdiff_t n = sm_proto_enc_match_req(ITEM_MATCH, sizeof ITEM_MATCH, NULL, SM_OP_DISTANCE, &mr);
  REQUIRE(n > 0 && (size_t)n <= sizeof ITEM_MATCH);
  item_match_len = (size_t)n;
  ITEMS[0] = (sm_proto_batch_item){SM_OP_PING, ITEM_PING, 8};
  ITEMS[1] = (sm_proto_batch_item){SM_OP_HAS_SHAPE, ITEM_HAS, 32};
  ITEMS[2] = (sm_proto_batch_item){SM_OP_DISTANCE, ITEM_MATCH, (uint32_t)item_match_len};
}

/* Encodes message kind k with header hdr (may be NULL: payload only) into buf.
 * `dec` selects the source: 0 = native fixture, otherwise a decoded struct in *src. */
typedef union anymsg {
  sm_proto_hello_req hello_req;
  sm_proto_hello_resp hello_resp;
  sm_proto_ping ping;
  sm_proto_stats_resp stats;
  sm_proto_put_req put_req;
  sm_proto_put_resp put_resp;
  sm_proto_id_req id_req;
  sm_proto_has_resp has_resp;
  sm_proto_prepare_req prep_req;
  sm_proto_prepare_resp prep_resp;
  sm_proto_match_req match_req;
  sm_proto_match_resp match_resp;
  sm_proto_distance_resp dist_resp;
  sm_proto_query_req query_req;
  sm_proto_query_resp query_resp;
  sm_proto_batch_req batch_req;
  sm_proto_batch_item_resp batch_item;
  sm_proto_batch_done batch_done;
  sm_proto_cancel_req cancel_req;
  sm_proto_error error;
} anymsg;

static uint8_t ITEM_RESP[48];
static void fixture(int k, anymsg *m) {
  memset(m, 0, sizeof *m);
  switch (k) {
  case K_HELLO_REQ: m->hello_req = m_hello_req(); break;
  case K_HELLO_RESP: m->hello_resp = m_hello_resp(); break;
  case K_PING_REQ: m->ping.opaque = 0xDEADBEEFCAFEF00Dull; break;
  case K_PING_RESP: m->ping.opaque = 1; break;
  case K_STATS_RESP: m->stats = (sm_proto_stats_resp){STATS, NULL, 4}; break;
  case K_PUT_REQ: m->put_req = m_put_req(); break;
  case K_PUT_RESP: m->put_resp = m_put_resp(); break;
  case K_HAS_REQ: memcpy(m->id_req.id, ID_B, 32); break;
  case K_HAS_RESP: m->has_resp = (sm_proto_has_resp){SM_HAS_STORED | SM_HAS_PREPARED, 7, 10};
    break;
  case K_DROP_REQ: memcpy(m->id_req.id, ID_C, 32); break;
  case K_PREP_REQ: m->prep_req = m_prep_req(); break;
  case K_PREP_RESP: m->prep_resp = m_prep_resp(); break;
  case K_MATCH_REQ: m->match_req = m_match_req(0); break;
  case K_MATCH_RESP: m->match_resp = m_match_resp(); break;
  case K_DIST_REQ: m->match_req = m_match_req(1); break;
  case K_DIST_RESP:
    m->dist_resp = (sm_proto_distance_resp){{0.5, 0.25, 0.125, 1.0 / 3, 0.2}, 77};
    break;
  case K_QUERY_REQ: m->query_req = m_query_req(); break;
  case K_QUERY_RESP: m->query_resp = m_query_resp(); break;
  case K_BATCH_REQ: m->batch_req = m_batch_req(); break;
  case K_BATCH_ITEM: {
    sm_proto_distance_resp d = {{0.1, 0.2, 0.3, 0.4, -1}, 5};
    REQUIRE(sm_proto_enc_distance_resp(ITEM_RESP, sizeof ITEM_RESP, NULL, &d) == 48);
    m->batch_item = (sm_proto_batch_item_resp){2, SM_OP_DISTANCE, ITEM_RESP, 48};
    break;
  }
  case K_BATCH_DONE: m->batch_done = (sm_proto_batch_done){3, 2}; break;
  case K_CANCEL_REQ: m->cancel_req.target = 77; break;
  case K_ERROR:
    m->error = (sm_proto_error){250, 0, ERRMSG, (uint32_t)strlen(ERRMSG)};
    break;
  case K_GOAWAY: m->error = (sm_proto_error){1000, 5000, "draining", 8}; break;
  default: break;
  }
}

/* the header a sender would fill for kind k */
static sm_proto_header hdr_for(int k, uint32_t rid, uint16_t extra_flags) {
  sm_proto_header h = {0};
  h.request_id = rid;
  h.flags = extra_flags;
  /* HELLO frames are version 1 (0 = the codec's default, which is that); every later
   * frame carries the negotiated version: here the newest */
  if (k != K_HELLO_REQ && k != K_HELLO_RESP) h.version = SM_PROTO_VERSION_MAX;
  switch (k) {
  case K_STATS_REQ: h.opcode = SM_OP_STATS; break;
  case K_DROP_RESP: h.opcode = SM_OP_DROP_SHAPE; h.flags |= SM_PROTO_F_RESPONSE; break;
  case K_CANCEL_RESP: h.opcode = SM_OP_CANCEL; h.flags |= SM_PROTO_F_RESPONSE; break;
  case K_ERROR: h.opcode = SM_OP_MATCH; h.status = SM_ST_MESH_REJECTED; break;
  case K_GOAWAY: h.opcode = SM_OP_GOAWAY; h.request_id = 0; break;
  case K_BATCH_ITEM: h.status = SM_ST_OK; break;
  default: break;
  }
  return h;
}

static ptrdiff_t encode(int k, uint8_t *buf, size_t cap, const sm_proto_header *h,
                        const anymsg *m) {
  switch (k) {
  case K_HELLO_REQ: return sm_proto_enc_hello_req(buf, cap, h, &m->hello_req);
  case K_HELLO_RESP: return sm_proto_enc_hello_resp(buf, cap, h, &m->hello_resp);
  case K_PING_REQ: return sm_proto_enc_ping(buf, cap, h, 0, &m->ping);
  case K_PING_RESP: return sm_proto_enc_ping(buf, cap, h, 1, &m->ping);
  case K_STATS_REQ:
  case K_DROP_RESP:
  case K_CANCEL_RESP: return h ? sm_proto_enc_empty(buf, cap, h) : 0;
  case K_STATS_RESP: return sm_proto_enc_stats_resp(buf, cap, h, &m->stats);
  case K_PUT_REQ: return sm_proto_enc_put_req(buf, cap, h, &m->put_req);
  case K_PUT_RESP: return sm_proto_enc_put_resp(buf, cap, h, &m->put_resp);
  case K_HAS_REQ: return sm_proto_enc_id_req(buf, cap, h, SM_OP_HAS_SHAPE, &m->id_req);
  case K_HAS_RESP: return sm_proto_enc_has_resp(buf, cap, h, &m->has_resp);
  case K_DROP_REQ: return sm_proto_enc_id_req(buf, cap, h, SM_OP_DROP_SHAPE, &m->id_req);
  case K_PREP_REQ: return sm_proto_enc_prepare_req(buf, cap, h, &m->prep_req);
  case K_PREP_RESP: return sm_proto_enc_prepare_resp(buf, cap, h, &m->prep_resp);
  case K_MATCH_REQ: return sm_proto_enc_match_req(buf, cap, h, SM_OP_MATCH, &m->match_req);
  case K_MATCH_RESP:
    return sm_proto_enc_match_resp(buf, cap, h, SM_PROTO_VERSION_MAX, &m->match_resp);
  case K_DIST_REQ: return sm_proto_enc_match_req(buf, cap, h, SM_OP_DISTANCE, &m->match_req);
  case K_DIST_RESP: return sm_proto_enc_distance_resp(buf, cap, h, &m->dist_resp);
  case K_QUERY_REQ: return sm_proto_enc_query_req(buf, cap, h, &m->query_req);
  case K_QUERY_RESP: return sm_proto_enc_query_resp(buf, cap, h, &m->query_resp);
  case K_BATCH_REQ: return sm_proto_enc_batch_req(buf, cap, h, &m->batch_req);
  case K_BATCH_ITEM: return sm_proto_enc_batch_item_resp(buf, cap, h, &m->batch_item);
  case K_BATCH_DONE: return sm_proto_enc_batch_done(buf, cap, h, &m->batch_done);
  case K_CANCEL_REQ: return sm_proto_enc_cancel_req(buf, cap, h, &m->cancel_req);
  case K_ERROR:
  case K_GOAWAY: return sm_proto_enc_error(buf, cap, h, &m->error);
  }
  return -999;
}

static int decode(int k, const uint8_t *p, size_t n, anymsg *m) {
  memset(m, 0, sizeof *m);
  switch (k) {
  case K_HELLO_REQ: return sm_proto_dec_hello_req(p, n, &m->hello_req);
  case K_HELLO_RESP: return sm_proto_dec_hello_resp(p, n, &m->hello_resp);
  case K_PING_REQ:
  case K_PING_RESP: return sm_proto_dec_ping(p, n, &m->ping);
  case K_STATS_REQ:
  case K_DROP_RESP:
  case K_CANCEL_RESP: return sm_proto_dec_empty(p, n);
  case K_STATS_RESP: return sm_proto_dec_stats_resp(p, n, &m->stats);
  case K_PUT_REQ: return sm_proto_dec_put_req(p, n, &m->put_req);
  case K_PUT_RESP: return sm_proto_dec_put_resp(p, n, &m->put_resp);
  case K_HAS_REQ:
  case K_DROP_REQ: return sm_proto_dec_id_req(p, n, &m->id_req);
  case K_HAS_RESP: return sm_proto_dec_has_resp(p, n, &m->has_resp);
  case K_PREP_REQ: return sm_proto_dec_prepare_req(p, n, &m->prep_req);
  case K_PREP_RESP: return sm_proto_dec_prepare_resp(p, n, &m->prep_resp);
  case K_MATCH_REQ: return sm_proto_dec_match_req(SM_OP_MATCH, p, n, &m->match_req);
  case K_DIST_REQ: return sm_proto_dec_match_req(SM_OP_DISTANCE, p, n, &m->match_req);
  case K_MATCH_RESP: return sm_proto_dec_match_resp(SM_PROTO_VERSION_MAX, p, n, &m->match_resp);
  case K_DIST_RESP: return sm_proto_dec_distance_resp(p, n, &m->dist_resp);
  case K_QUERY_REQ: return sm_proto_dec_query_req(p, n, &m->query_req);
  case K_QUERY_RESP: return sm_proto_dec_query_resp(p, n, &m->query_resp);
  case K_BATCH_REQ: return sm_proto_dec_batch_req(p, n, &m->batch_req);
  case K_BATCH_ITEM: return sm_proto_dec_batch_item_resp(p, n, &m->batch_item);
  case K_BATCH_DONE: return sm_proto_dec_batch_done(p, n, &m->batch_done);
  case K_CANCEL_REQ: return sm_proto_dec_cancel_req(p, n, &m->cancel_req);
  case K_ERROR:
  case K_GOAWAY: return sm_proto_dec_error(p, n, &m->error);
  }
  return -999;
}

#define EQ(f) CHECK_MSG(a->f == b->f, "%s: field %s differs", kind_name[k], #f)
#define EQMEM(f, len) CHECK_MSG(memcmp(a->f, b->f, len) == 0, "%s: %s differs", kind_name[k], #f)
static void eq_dist(int k, const sm_proto_dist *a, const sm_proto_dist *b) {
  EQ(total); EQ(point_xy); EQ(point_yx); EQ(spectrum_lb); EQ(spectrum_elastic);
}
static void eq_i32s(int k, const char *what, const sm_proto_i32s *a, const sm_proto_i32s *b) {
  CHECK_MSG(a->count == b->count, "%s: %s count %u != %u", kind_name[k], what, a->count,
            b->count);
  for (uint32_t i = 0; i < a->count && i < b->count; i++)
    CHECK_MSG(sm_proto_i32_at(a, i) == sm_proto_i32_at(b, i), "%s: %s[%u]", kind_name[k],
              what, i);
}
static void eq_match_req(int k, const sm_proto_match_req *a, const sm_proto_match_req *b) {
  EQMEM(x, 32); EQMEM(y, 32); EQ(basis); EQ(init); EQ(flags); EQ(k0); EQ(k1); EQ(step);
  EQ(sinkhorn_levels);
  EQ(eta); EQ(deadline_ms);
  eq_i32s(k, "landmarks", &a->landmarks, &b->landmarks);
  eq_i32s(k, "init_map", &a->init_map, &b->init_map);
}

/* fields of the native fixture a against the decoded b */
static void compare(int k, const anymsg *A, const anymsg *B) {
  switch (k) {
  case K_HELLO_REQ: {
    const sm_proto_hello_req *a = &A->hello_req, *b = &B->hello_req;
    EQ(min_version); EQ(max_version); EQ(max_response); EQMEM(affinity, 32); EQ(token_len);
    EQMEM(token, a->token_len);
    break;
  }
  case K_HELLO_RESP: {
    const sm_proto_hello_resp *a = &A->hello_resp, *b = &B->hello_resp;
    EQ(version); EQ(max_payload); EQ(max_vertices); EQ(max_faces); EQ(max_inflight);
    EQ(max_batch_items); EQ(max_query_k); EQ(max_k); EQ(idle_timeout_ms); EQ(features);
    break;
  }
  case K_PING_REQ:
  case K_PING_RESP: {
    const sm_proto_ping *a = &A->ping, *b = &B->ping;
    EQ(opaque);
    break;
  }
  case K_STATS_RESP: {
    CHECK(A->stats.count == B->stats.count);
    for (uint32_t i = 0; i < A->stats.count && i < B->stats.count; i++) {
      sm_proto_stat sa, sb;
      CHECK(sm_proto_stat_at(&A->stats, i, &sa) == 0);
      CHECK(sm_proto_stat_at(&B->stats, i, &sb) == 0);
      CHECK(strcmp(sa.name, sb.name) == 0 && sa.value == sb.value);
      CHECK(strcmp(sb.name, STATS[i].name) == 0);
    }
    break;
  }
  case K_PUT_REQ: {
    const sm_proto_put_req *a = &A->put_req, *b = &B->put_req;
    EQMEM(id, 32); EQ(flags); EQ(draco_len); EQMEM(draco, a->draco_len);
    break;
  }
  case K_PUT_RESP: {
    const sm_proto_put_resp *a = &A->put_resp, *b = &B->put_resp;
    EQMEM(id, 32); EQ(n_vertices); EQ(n_faces); EQ(flags);
    break;
  }
  case K_HAS_REQ:
  case K_DROP_REQ: {
    const sm_proto_id_req *a = &A->id_req, *b = &B->id_req;
    EQMEM(id, 32);
    break;
  }
  case K_HAS_RESP: {
    const sm_proto_has_resp *a = &A->has_resp, *b = &B->has_resp;
    EQ(flags); EQ(n_vertices); EQ(n_faces);
    break;
  }
  case K_PREP_REQ: {
    const sm_proto_prepare_req *a = &A->prep_req, *b = &B->prep_req;
    EQMEM(id, 32); EQ(k_lb); EQ(k_elastic); EQ(eta);
    break;
  }
  case K_PREP_RESP: {
    const sm_proto_prepare_resp *a = &A->prep_resp, *b = &B->prep_resp;
    EQ(n_vertices); EQ(n_faces); EQ(k_lb); EQ(k_elastic); EQ(flags); EQ(t_clean_us);
    EQ(t_lb_us); EQ(t_elastic_us); EQ(t_desc_us);
    break;
  }
  case K_MATCH_REQ:
  case K_DIST_REQ: eq_match_req(k, &A->match_req, &B->match_req); break;
  case K_MATCH_RESP: {
    const sm_proto_match_resp *a = &A->match_resp, *b = &B->match_resp;
    EQ(init_used); EQ(flags); EQ(orientation); EQ(dirichlet); EQ(confidence); EQ(t_prepare_us);
    EQ(t_init_us); EQ(t_refine_us); EQ(t_distance_us); EQ(t_total_us); EQ(kC);
    eq_dist(k, &a->dist, &b->dist);
    eq_i32s(k, "map_xy", &a->map_xy, &b->map_xy);
    eq_i32s(k, "map_yx", &a->map_yx, &b->map_yx);
    CHECK(a->fmap.count == b->fmap.count);
    for (uint32_t i = 0; i < a->fmap.count && i < b->fmap.count; i++) {
      double x = sm_proto_f64_at(&a->fmap, i), y = sm_proto_f64_at(&b->fmap, i);
      CHECK_MSG(memcmp(&x, &y, 8) == 0, "fmap[%u] %g != %g", i, x, y); /* bit-exact, -0 */
    }
    break;
  }
  case K_DIST_RESP: {
    const sm_proto_distance_resp *a = &A->dist_resp, *b = &B->dist_resp;
    eq_dist(k, &a->dist, &b->dist);
    EQ(t_total_us);
    break;
  }
  case K_QUERY_REQ: {
    const sm_proto_query_req *a = &A->query_req, *b = &B->query_req;
    EQMEM(id, 32); EQ(k); EQ(mode); EQ(deadline_ms); EQ(n_candidates);
    EQMEM(candidates, 32 * (size_t)a->n_candidates);
    break;
  }
  case K_QUERY_RESP: {
    const sm_proto_query_resp *a = &A->query_resp, *b = &B->query_resp;
    EQ(count); EQ(n_considered); EQ(t_total_us);
    for (uint32_t i = 0; i < a->count && i < b->count; i++) {
      sm_proto_hit ha, hb;
      sm_proto_hit_at(a, i, &ha);
      sm_proto_hit_at(b, i, &hb);
      CHECK(memcmp(ha.id, hb.id, 32) == 0 && ha.distance == hb.distance);
    }
    break;
  }
  case K_BATCH_REQ: {
    const sm_proto_batch_req *a = &A->batch_req, *b = &B->batch_req;
    EQ(count);
    size_t pa = 0, pb = 0;
    sm_proto_batch_item ia, ib;
    uint32_t n = 0;
    while (sm_proto_batch_next(a, &pa, &ia)) {
      CHECK(sm_proto_batch_next(b, &pb, &ib) == 1);
      CHECK(ia.opcode == ib.opcode && ia.len == ib.len &&
            memcmp(ia.payload, ib.payload, ia.len) == 0);
      n++;
    }
    CHECK(sm_proto_batch_next(b, &pb, &ib) == 0);
    CHECK(n == 3);
    break;
  }
  case K_BATCH_ITEM: {
    const sm_proto_batch_item_resp *a = &A->batch_item, *b = &B->batch_item;
    EQ(index); EQ(opcode); EQ(len); EQMEM(payload, a->len);
    break;
  }
  case K_BATCH_DONE: {
    const sm_proto_batch_done *a = &A->batch_done, *b = &B->batch_done;
    EQ(n_items); EQ(n_ok);
    break;
  }
  case K_CANCEL_REQ: {
    const sm_proto_cancel_req *a = &A->cancel_req, *b = &B->cancel_req;
    EQ(target);
    break;
  }
  case K_ERROR:
  case K_GOAWAY: {
    const sm_proto_error *a = &A->error, *b = &B->error;
    EQ(retry_after_ms); EQ(detail); EQ(msg_len); EQMEM(msg, a->msg_len);
    break;
  }
  default: break;
  }
}

/* ---- round trip; also builds the stream used below ---- */
#define MAX_FRAMES (2 * K_COUNT)
static uint8_t *frames[MAX_FRAMES];
static size_t frame_len[MAX_FRAMES];
static int frame_kind[MAX_FRAMES];
static int nframes;
static const uint32_t LIMIT = 1u << 20;

static void test_roundtrip(void) {
  uint8_t *buf = malloc(1 << 16), *buf2 = malloc(1 << 16);
  REQUIRE(buf && buf2);
  for (int pass = 0; pass < 2; pass++) {
    uint16_t crcflag = pass ? SM_PROTO_F_PAYLOAD_CRC : 0;
    for (int k = 0; k < K_COUNT; k++) {
      anymsg m, d;
      fixture(k, &m);
      sm_proto_header h = hdr_for(k, 1000u * (uint32_t)pass + (uint32_t)k + 1, crcflag);
      ptrdiff_t need = encode(k, NULL, 0, &h, &m);
      CHECK_MSG(need >= SM_PROTO_HEADER_LEN, "%s: size query %td", kind_name[k], need);
      if (need < SM_PROTO_HEADER_LEN) continue;
      /* too small: the needed size comes back, the buffer is not overrun */
      memset(buf, 0xA5, (size_t)need + 16);
      CHECK(encode(k, buf, (size_t)need - 1, &h, &m) == need);
      CHECK(buf[need - 1] == 0xA5 || need - 1 < 24);
      ptrdiff_t got = encode(k, buf, 1 << 16, &h, &m);
      CHECK_MSG(got == need, "%s: %td != %td", kind_name[k], got, need);
      /* parse from a guarded copy */
      guard g = guard_place(buf, (size_t)got);
      sm_proto_frame f;
      ptrdiff_t r = sm_proto_parse_frame(g.p, (size_t)got, LIMIT, &f);
      CHECK_MSG(r == got, "%s: parse %td (%s)", kind_name[k], r,
                sm_proto_strerror((int)(r < 0 ? r : 0)));
      if (r == got) {
        int resp = k != K_HELLO_REQ && k != K_PING_REQ && k != K_STATS_REQ &&
                   k != K_PUT_REQ && k != K_HAS_REQ && k != K_DROP_REQ && k != K_PREP_REQ &&
                   k != K_MATCH_REQ && k != K_DIST_REQ && k != K_QUERY_REQ &&
                   k != K_BATCH_REQ && k != K_CANCEL_REQ;
        CHECK(f.h.version == (k == K_HELLO_REQ || k == K_HELLO_RESP ? SM_PROTO_VERSION_HELLO
                                                                     : SM_PROTO_VERSION_MAX));
        CHECK(f.h.request_id == h.request_id);
        CHECK(f.h.status == h.status);
        CHECK(!!(f.h.flags & SM_PROTO_F_RESPONSE) == resp);
        CHECK(!!(f.h.flags & SM_PROTO_F_PAYLOAD_CRC) == !!crcflag);
        CHECK(!!(f.h.flags & SM_PROTO_F_MORE) == (k == K_BATCH_ITEM));
        CHECK(f.h.payload_len == (uint32_t)got - 24);
        CHECK(f.body_len == f.h.payload_len - (crcflag ? 4 : 0));
        int rc = decode(k, f.body, f.body_len, &d);
        CHECK_MSG(rc == 0, "%s: decode %d (%s)", kind_name[k], rc, sm_proto_strerror(rc));
        if (rc == 0) {
          compare(k, &m, &d);
          /* re-encoding the decoded views reproduces the frame */
          ptrdiff_t again = encode(k, buf2, 1 << 16, &h, &d);
          CHECK_MSG(again == got && memcmp(buf, buf2, (size_t)got) == 0,
                    "%s: re-encode differs", kind_name[k]);
          /* the payload-only form equals the frame's body */
          if (k != K_STATS_REQ && k != K_DROP_RESP && k != K_CANCEL_RESP) {
            ptrdiff_t pl = encode(k, buf2, 1 << 16, NULL, &m);
            CHECK_MSG(pl == (ptrdiff_t)f.body_len && memcmp(buf2, f.body, f.body_len) == 0,
                      "%s: payload-only form differs", kind_name[k]);
          }
        }
      }
      guard_free(&g);
      REQUIRE(nframes < MAX_FRAMES);
      frames[nframes] = malloc((size_t)got);
      REQUIRE(frames[nframes]);
      memcpy(frames[nframes], buf, (size_t)got);
      frame_len[nframes] = (size_t)got;
      frame_kind[nframes] = k;
      nframes++;
    }
  }
  /* the opcode written is the one each message belongs to */
  static const uint8_t op_of[K_COUNT] = {
      SM_OP_HELLO, SM_OP_HELLO, SM_OP_PING, SM_OP_PING, SM_OP_STATS, SM_OP_STATS,
      SM_OP_PUT_SHAPE, SM_OP_PUT_SHAPE, SM_OP_HAS_SHAPE, SM_OP_HAS_SHAPE, SM_OP_DROP_SHAPE,
      SM_OP_DROP_SHAPE, SM_OP_PREPARE, SM_OP_PREPARE, SM_OP_MATCH, SM_OP_MATCH,
      SM_OP_DISTANCE, SM_OP_DISTANCE, SM_OP_QUERY, SM_OP_QUERY, SM_OP_BATCH, SM_OP_BATCH,
      SM_OP_BATCH, SM_OP_CANCEL, SM_OP_CANCEL, SM_OP_MATCH, SM_OP_GOAWAY};
  for (int i = 0; i < nframes; i++)
    CHECK_MSG(frames[i][5] == op_of[frame_kind[i]], "%s: opcode %u", kind_name[frame_kind[i]],
              frames[i][5]);
  free(buf);
  free(buf2);
}

/* The shape id sits at payload offset 0 in every request that names a shape, and the
 * HELLO affinity key at payload offset 8 (stream offset 32): what a balancer hashes. */
static void test_fixed_id_offsets(void) {
  for (int i = 0; i < nframes; i++) {
    int k = frame_kind[i];
    const uint8_t *pl = frames[i] + 24;
    const uint8_t *want = NULL;
    anymsg m;
    fixture(k, &m);
    switch (k) {
    case K_PUT_REQ: want = m.put_req.id; break;
    case K_HAS_REQ:
    case K_DROP_REQ: want = m.id_req.id; break;
    case K_PREP_REQ: want = m.prep_req.id; break;
    case K_MATCH_REQ:
    case K_DIST_REQ: want = m.match_req.x; break;
    case K_QUERY_REQ: want = m.query_req.id; break;
    case K_HELLO_REQ: CHECK(memcmp(frames[i] + 32, ID_A, 32) == 0); break;
    default: break;
    }
    if (want) CHECK_MSG(memcmp(pl, want, 32) == 0, "%s: id not at offset 0", kind_name[k]);
  }
}

/* ---- streams ---- */
static uint8_t *stream;
static size_t stream_len;
static size_t boundaries[MAX_FRAMES + 1];

static void build_stream(void) {
  stream_len = 0;
  for (int i = 0; i < nframes; i++) stream_len += frame_len[i];
  stream = malloc(stream_len);
  REQUIRE(stream);
  size_t off = 0;
  for (int i = 0; i < nframes; i++) {
    boundaries[i] = off;
    memcpy(stream + off, frames[i], frame_len[i]);
    off += frame_len[i];
  }
  boundaries[nframes] = off;
}

static void test_prefixes(void) {
  int bad = 0;
  for (size_t L = 0; L <= stream_len && bad < 5; L++) {
    guard g = guard_place(stream, L);
    size_t off = 0;
    int nf = 0;
    ptrdiff_t r;
    while ((r = sm_proto_parse_frame(g.p + off, L - off, LIMIT, NULL)) > 0) {
      off += (size_t)r;
      nf++;
    }
    /* complete frames: those ending at or before L */
    int want = 0;
    while (want < nframes && boundaries[want + 1] <= L) want++;
    if (r != SM_PROTO_PARTIAL || nf != want || off != boundaries[want]) {
      bad++;
      CHECK_MSG(0, "prefix %zu: r=%td frames %d (want %d)", L, r, nf, want);
    }
    /* the header parser alone: partial below 24 bytes of the pending frame */
    if (L - off < 24) {
      CHECK(sm_proto_parse_header(g.p + off, L - off, LIMIT, NULL) == SM_PROTO_PARTIAL);
    }
    guard_free(&g);
  }
  CHECK(bad == 0);
}

static void test_random_splits(void) {
  uint8_t *acc = malloc(stream_len);
  REQUIRE(acc);
  for (int trial = 0; trial < 300; trial++) {
    size_t have = 0, fed = 0, start = 0;
    int nf = 0, ok = 1;
    size_t maxchunk = 1 + (size_t)(rng() % (trial < 100 ? 8 : 400));
    while (fed < stream_len && ok) {
      size_t chunk = 1 + (size_t)(rng() % maxchunk);
      if (chunk > stream_len - fed) chunk = stream_len - fed;
      memcpy(acc + have, stream + fed, chunk);
      have += chunk;
      fed += chunk;
      /* parse what is buffered, from a guarded copy that ends at what has arrived */
      guard g = guard_place(acc + start, have - start);
      size_t off = 0;
      ptrdiff_t r;
      sm_proto_frame f;
      while ((r = sm_proto_parse_frame(g.p + off, have - start - off, LIMIT, &f)) > 0) {
        if (nf >= nframes || (size_t)r != frame_len[nf] ||
            memcmp(g.p + off, frames[nf], (size_t)r) != 0)
          ok = 0;
        off += (size_t)r;
        nf++;
      }
      if (r != SM_PROTO_PARTIAL) ok = 0;
      guard_free(&g);
      start += off;
    }
    CHECK_MSG(ok && nf == nframes && start == stream_len, "trial %d: %d frames of %d", trial,
              nf, nframes);
  }
  free(acc);
}

/* ---- malformed headers ---- */
static void set_crc(uint8_t *h) {
  uint32_t c = sm_proto_crc32c(0, h, 20);
  for (int i = 0; i < 4; i++) h[20 + i] = (uint8_t)(c >> (8 * i));
}
static int parse_hdr24(const uint8_t *h, uint32_t limit) {
  guard g = guard_place(h, 24); /* the header only: the payload has not arrived */
  sm_proto_header out;
  int r = sm_proto_parse_header(g.p, 24, limit, &out);
  ptrdiff_t rf = sm_proto_parse_frame(g.p, 24, limit, NULL);
  /* the frame parser reports the same error from the header alone */
  if (r < 0) CHECK_MSG(rf == r, "frame parser %td vs header parser %d", rf, r);
  guard_free(&g);
  return r;
}

static void test_bad_headers(void) {
  uint8_t good[64];
  sm_proto_ping pg = {5};
  sm_proto_header h = {0};
  h.request_id = 9;
  REQUIRE(sm_proto_enc_ping(good, sizeof good, &h, 0, &pg) == 32);
  uint8_t x[24];

  CHECK(parse_hdr24(good, LIMIT) == 24);
  /* the golden frame of PROTOCOL.md section 9 */
  static const uint8_t golden[32] = {0x89, 0x53, 0x4d, 0x50, 0x01, 0x02, 0x00, 0x00,
                                     0x09, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
                                     0x08, 0x00, 0x00, 0x00, 0x79, 0x1d, 0xd9, 0xed,
                                     0x05, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00};
  CHECK(memcmp(good, golden, 32) == 0);
  /* bad magic: each byte; the first is rejected from a 1-byte prefix */
  for (int i = 0; i < 4; i++) {
    memcpy(x, good, 24);
    x[i] ^= 0x20;
    set_crc(x);
    CHECK_MSG(parse_hdr24(x, LIMIT) == SM_PROTO_EMAGIC, "magic byte %d", i);
    guard g = guard_place(x, (size_t)i + 1);
    CHECK(sm_proto_parse_header(g.p, (size_t)i + 1, LIMIT, NULL) == SM_PROTO_EMAGIC);
    guard_free(&g);
  }
  const char *http = "GET / HTTP/1.1\r\n";
  {
    guard g = guard_place(http, 1);
    CHECK(sm_proto_parse_header(g.p, 1, LIMIT, NULL) == SM_PROTO_EMAGIC);
    guard_free(&g);
  }
  /* unknown version; every version the codec speaks passes */
  uint8_t versions[] = {0, SM_PROTO_VERSION_MAX + 1, 255};
  for (int i = 0; i < 3; i++) {
    memcpy(x, good, 24);
    x[4] = versions[i];
    set_crc(x);
    CHECK(parse_hdr24(x, LIMIT) == SM_PROTO_EVERSION);
  }
  for (int v = SM_PROTO_VERSION_MIN; v <= SM_PROTO_VERSION_MAX; v++) {
    memcpy(x, good, 24);
    x[4] = (uint8_t)v;
    set_crc(x);
    CHECK_MSG(parse_hdr24(x, LIMIT) == 24, "version %d", v);
  }
  /* header CRC: every single-bit error in bytes 4..23 is caught */
  for (int bit = 32; bit < 24 * 8; bit++) {
    memcpy(x, good, 24);
    x[bit / 8] ^= (uint8_t)(1u << (bit % 8));
    CHECK_MSG(parse_hdr24(x, LIMIT) == SM_PROTO_EHDRCRC, "bit %d", bit);
  }
  /* reserved bytes 14..15 */
  for (int i = 14; i < 16; i++) {
    memcpy(x, good, 24);
    x[i] = 1;
    set_crc(x);
    CHECK(parse_hdr24(x, LIMIT) == SM_PROTO_ERESERVED);
  }
  /* unknown flags: bits 3..15 */
  for (int bit = 3; bit < 16; bit++) {
    memcpy(x, good, 24);
    uint16_t fl = (uint16_t)(x[6] | x[7] << 8 | 1u << bit);
    x[6] = (uint8_t)fl;
    x[7] = (uint8_t)(fl >> 8);
    set_crc(x);
    CHECK_MSG(parse_hdr24(x, LIMIT) == SM_PROTO_EFLAGS, "flag bit %d", bit);
  }
  /* payload_len over the limit: rejected with only the header present */
  uint32_t lens[] = {LIMIT + 1, 0x7FFFFFFFu, 0xFFFFFFFFu};
  for (int i = 0; i < 3; i++) {
    memcpy(x, good, 24);
    for (int b = 0; b < 4; b++) x[16 + b] = (uint8_t)(lens[i] >> (8 * b));
    set_crc(x);
    CHECK(parse_hdr24(x, LIMIT) == SM_PROTO_ETOOBIG);
  }
  memcpy(x, good, 24);
  CHECK(parse_hdr24(x, 7) == SM_PROTO_ETOOBIG); /* 8-byte payload, limit 7 */
  CHECK(parse_hdr24(x, 8) == 24);
  CHECK(parse_hdr24(x, SM_PROTO_HELLO_MAX_PAYLOAD) == 24);
  /* other header rules */
  memcpy(x, good, 24);
  x[5] = 0; /* opcode 0 */
  set_crc(x);
  CHECK(parse_hdr24(x, LIMIT) == SM_PROTO_EHEADER);
  memcpy(x, good, 24);
  x[12] = 1; /* status in a request */
  set_crc(x);
  CHECK(parse_hdr24(x, LIMIT) == SM_PROTO_EHEADER);
  memcpy(x, good, 24);
  x[6] |= SM_PROTO_F_MORE; /* MORE in a request */
  set_crc(x);
  CHECK(parse_hdr24(x, LIMIT) == SM_PROTO_EHEADER);
  memcpy(x, good, 24);
  memset(x + 8, 0, 4); /* request_id 0 in a request */
  set_crc(x);
  CHECK(parse_hdr24(x, LIMIT) == SM_PROTO_EHEADER);
  memcpy(x, good, 24);
  x[6] |= SM_PROTO_F_PAYLOAD_CRC;
  x[16] = 3; /* CRC trailer flagged, payload shorter than the trailer */
  set_crc(x);
  CHECK(parse_hdr24(x, LIMIT) == SM_PROTO_EHEADER);
  /* an unknown non-zero opcode passes the header (the receiver answers UNKNOWN_OPCODE) */
  memcpy(x, good, 24);
  x[5] = 200;
  set_crc(x);
  CHECK(parse_hdr24(x, LIMIT) == 24);
  CHECK(sm_proto_status_for_error(SM_PROTO_EOPCODE) == SM_ST_UNKNOWN_OPCODE);
  /* fatal mapping */
  int fatal[] = {SM_PROTO_EMAGIC, SM_PROTO_EHDRCRC, SM_PROTO_EVERSION, SM_PROTO_EFLAGS,
                 SM_PROTO_ERESERVED, SM_PROTO_EHEADER, SM_PROTO_ETOOBIG, SM_PROTO_EPAYLOADCRC};
  for (int i = 0; i < 8; i++)
    CHECK(sm_proto_status_is_fatal(sm_proto_status_for_error(fatal[i])));
  int reqlvl[] = {SM_PROTO_ETRUNC, SM_PROTO_ELENGTH, SM_PROTO_EFIELD, SM_PROTO_EOPCODE};
  for (int i = 0; i < 4; i++)
    CHECK(!sm_proto_status_is_fatal(sm_proto_status_for_error(reqlvl[i])));

  /* payload CRC trailer: any flipped payload bit is caught, header intact */
  uint8_t fr[64];
  h.flags = SM_PROTO_F_PAYLOAD_CRC;
  ptrdiff_t n = sm_proto_enc_ping(fr, sizeof fr, &h, 0, &pg);
  REQUIRE(n == 36);
  for (int bit = 24 * 8; bit < 36 * 8; bit++) {
    uint8_t y[36];
    memcpy(y, fr, 36);
    y[bit / 8] ^= (uint8_t)(1u << (bit % 8));
    guard g = guard_place(y, 36);
    CHECK(sm_proto_parse_frame(g.p, 36, LIMIT, NULL) == SM_PROTO_EPAYLOADCRC);
    uint32_t bl;
    sm_proto_header hh;
    CHECK(sm_proto_parse_header(g.p, 36, LIMIT, &hh) == 24);
    CHECK(sm_proto_check_payload(&hh, g.p + 24, &bl) == SM_PROTO_EPAYLOADCRC);
    guard_free(&g);
  }
}

/* ---- malformed payloads ---- */
static void test_truncations(void) {
  for (int i = 0; i < nframes; i++) {
    int k = frame_kind[i];
    sm_proto_frame f;
    REQUIRE(sm_proto_parse_frame(frames[i], frame_len[i], LIMIT, &f) > 0);
    anymsg m;
    for (size_t n = 0; n < f.body_len; n++) {
      guard g = guard_place(f.body, n);
      int rc = decode(k, g.p, n, &m);
      /* a shorter open tail is still a valid message if the fixed part is whole */
      int may_pass = open_tail(k) && n >= (k == K_PUT_REQ ? 41u : 8u);
      if (!may_pass)
        CHECK_MSG(rc == SM_PROTO_ETRUNC || rc == SM_PROTO_ELENGTH, "%s: %zu/%u bytes -> %d",
                  kind_name[k], n, f.body_len, rc);
      guard_free(&g);
    }
    if (!open_tail(k)) {
      uint8_t *t = malloc(f.body_len + 1);
      REQUIRE(t);
      memcpy(t, f.body, f.body_len);
      t[f.body_len] = 0;
      guard g = guard_place(t, f.body_len + 1);
      CHECK_MSG(decode(k, g.p, f.body_len + 1, &m) == SM_PROTO_ELENGTH, "%s: trailing byte",
                kind_name[k]);
      guard_free(&g);
      free(t);
    }
  }
}

/* body of the first frame of kind k, copied into out */
static size_t body_of(int k, uint8_t *out, size_t cap) {
  for (int i = 0; i < nframes; i++)
    if (frame_kind[i] == k) {
      sm_proto_frame f;
      REQUIRE(sm_proto_parse_frame(frames[i], frame_len[i], LIMIT, &f) > 0);
      REQUIRE(f.body_len <= cap);
      memcpy(out, f.body, f.body_len);
      return f.body_len;
    }
  REQUIRE(0);
  return 0;
}
static void put32(uint8_t *p, uint32_t v) {
  for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}
static void put16(uint8_t *p, uint16_t v) {
  p[0] = (uint8_t)v;
  p[1] = (uint8_t)(v >> 8);
}
static void put_f64(uint8_t *p, double d) {
  uint64_t u;
  memcpy(&u, &d, 8);
  for (int i = 0; i < 8; i++) p[i] = (uint8_t)(u >> (8 * i));
}
/* sm_proto_dec_match_resp on a guarded copy (an over-read faults) */
static int dec_match_v(uint8_t version, const uint8_t *b, size_t n, sm_proto_match_resp *m) {
  guard g = guard_place(b, n);
  int rc = sm_proto_dec_match_resp(version, g.p, n, m);
  guard_free(&g);
  return rc;
}
static int dec_guarded(int k, const uint8_t *b, size_t n) {
  anymsg m;
  guard g = guard_place(b, n);
  int rc = decode(k, g.p, n, &m);
  guard_free(&g);
  return rc;
}
#define MUT(kind, stmt, want)                                                          \
  do {                                                                                 \
    uint8_t b_[4096];                                                                  \
    size_t n_ = body_of(kind, b_, sizeof b_);                                          \
    uint8_t *b = b_;                                                                   \
    (void)b;                                                                           \
    stmt;                                                                              \
    int rc_ = dec_guarded(kind, b_, n_);                                               \
    CHECK_MSG(rc_ == (want), "%s: %s -> %d (%s), want %d", kind_name[kind], #stmt, rc_, \
              sm_proto_strerror(rc_), want);                                           \
  } while (0)

static void test_bad_payloads(void) {
  double nan = NAN;
  uint64_t nanbits;
  memcpy(&nanbits, &nan, 8);
  /* counts that overflow the payload length (some would wrap in 32-bit arithmetic) */
  MUT(K_MATCH_REQ, put32(b + 76, 0xFFFFFFFFu), SM_PROTO_ELENGTH);
  MUT(K_MATCH_REQ, put32(b + 76, 0x20000000u), SM_PROTO_ELENGTH); /* 8*n wraps to 0 */
  MUT(K_MATCH_REQ, put32(b + 92, 0x40000000u), SM_PROTO_ELENGTH); /* 4*n wraps to 0 */
  MUT(K_MATCH_REQ, put32(b + 76, 4), SM_PROTO_ELENGTH);           /* one pair too many */
  MUT(K_MATCH_RESP, put32(b + 0, 0x40000000u + 7), SM_PROTO_ELENGTH);
  MUT(K_MATCH_RESP, put32(b + 4, 0xFFFFFFFFu), SM_PROTO_ELENGTH);
  MUT(K_MATCH_RESP, put16(b + 8, 0xFFFF), SM_PROTO_ELENGTH);
  MUT(K_STATS_RESP, put32(b + 0, 0x08000000u + 4), SM_PROTO_ELENGTH); /* 32*n wraps */
  MUT(K_QUERY_REQ, put32(b + 40, 0x08000000u + 2), SM_PROTO_ELENGTH);
  MUT(K_QUERY_RESP, put32(b + 0, 0xFFFFFFFFu), SM_PROTO_ELENGTH);
  MUT(K_HELLO_REQ, put16(b + 40, 0xFFFF), SM_PROTO_ELENGTH);
  MUT(K_ERROR, put32(b + 8, 0xFFFFFFF8u), SM_PROTO_ELENGTH); /* 12 + n wraps in 32 bits */
  MUT(K_BATCH_REQ, put32(b + 0, 4), SM_PROTO_ELENGTH);       /* count > items present */
  MUT(K_BATCH_REQ, put32(b + 0, 2), SM_PROTO_ELENGTH);       /* items left over */
  MUT(K_BATCH_REQ, put32(b + 12, 0xFFFFFFFFu), SM_PROTO_ELENGTH); /* item length */
  MUT(K_BATCH_REQ, put32(b + 68, (uint32_t)item_match_len + 1), SM_PROTO_ELENGTH); /* last item */
  MUT(K_BATCH_REQ, put32(b + 12, 9), SM_PROTO_EOPCODE); /* next item header misread */
  /* out-of-range enums, unknown flag bits, reserved fields */
  MUT(K_MATCH_REQ, b[64] = 4, SM_PROTO_EFIELD);  /* basis */
  MUT(K_MATCH_REQ, b[65] = 3, SM_PROTO_EFIELD);  /* init */
  MUT(K_MATCH_REQ, put16(b + 74, 1), SM_PROTO_EFIELD); /* levels without its flag */
  MUT(K_MATCH_REQ, put16(b + 66, SM_MATCH_F_SINGLE_START | SM_MATCH_F_MULTI_START),
      SM_PROTO_EFIELD);
  MUT(K_MATCH_REQ, put16(b + 66, 0x100), SM_PROTO_EFIELD); /* first reserved bit */
  MUT(K_MATCH_REQ, put16(b + 66, SM_MATCH_F_MULTIRES | SM_MATCH_F_DIRECT), SM_PROTO_EFIELD);
  MUT(K_MATCH_REQ, put16(b + 66, SM_MATCH_F_MULTIRES), 0); /* version 3's flags */
  MUT(K_MATCH_REQ, put16(b + 66, SM_MATCH_F_DIRECT), 0);
  MUT(K_DIST_REQ, put16(b + 66, SM_MATCH_F_MULTIRES), SM_PROTO_EFIELD); /* MATCH only */
  MUT(K_DIST_REQ, put16(b + 74, 0), 0); /* levels 0 = variant off: valid */
  MUT(K_MATCH_REQ, (put16(b + 68, 50), put16(b + 70, 20)), SM_PROTO_EFIELD); /* k0 > k1 */
  MUT(K_MATCH_REQ, for (int i = 0; i < 8; i++) b[80 + i] = (uint8_t)(nanbits >> (8 * i)),
      SM_PROTO_EFIELD);
  MUT(K_MATCH_REQ, b[87] = 0xBF, SM_PROTO_EFIELD); /* eta < 0 */
  MUT(K_MATCH_REQ, put32(b + 96, 0xFFFFFFFFu), SM_PROTO_EFIELD); /* landmark -1 */
  MUT(K_MATCH_REQ, put32(b + 96 + 24, 0xFFFFFFFEu), SM_PROTO_EFIELD); /* init_map -2 */
  MUT(K_DIST_REQ, put16(b + 66, SM_MATCH_F_WANT_FMAP), SM_PROTO_EFIELD);
  MUT(K_MATCH_RESP, b[10] = 0, SM_PROTO_EFIELD); /* init_used */
  MUT(K_MATCH_RESP, b[10] = 3, SM_PROTO_EFIELD);
  MUT(K_MATCH_RESP, b[11] = 4, SM_PROTO_EFIELD);
  MUT(K_MATCH_RESP, put32(b + 12, 1), SM_PROTO_EFIELD);
  MUT(K_MATCH_RESP, put32(b + 112, 0xFFFFFFFEu), SM_PROTO_EFIELD); /* map entry -2 */
  /* confidence: the last 8 bytes of a version 2 MATCH response */
  MUT(K_MATCH_RESP, put_f64(b + n_ - 8, NAN), SM_PROTO_ECONFIDENCE);
  MUT(K_MATCH_RESP, put_f64(b + n_ - 8, -0.25), SM_PROTO_ECONFIDENCE);
  MUT(K_MATCH_RESP, put_f64(b + n_ - 8, 1.0000001), SM_PROTO_ECONFIDENCE);
  MUT(K_MATCH_RESP, put_f64(b + n_ - 8, INFINITY), SM_PROTO_ECONFIDENCE);
  MUT(K_MATCH_RESP, put_f64(b + n_ - 8, -INFINITY), SM_PROTO_ECONFIDENCE);
  MUT(K_MATCH_RESP, put_f64(b + n_ - 8, 0.0), 0); /* both ends are valid */
  MUT(K_MATCH_RESP, put_f64(b + n_ - 8, 1.0), 0);
  MUT(K_QUERY_REQ, b[34] = 3, SM_PROTO_EFIELD); /* mode */
  MUT(K_QUERY_REQ, put16(b + 32, 0), SM_PROTO_EFIELD); /* k = 0 */
  MUT(K_QUERY_REQ, b[35] = 1, SM_PROTO_EFIELD);
  MUT(K_QUERY_REQ, put32(b + 44, 1), SM_PROTO_EFIELD);
  MUT(K_HELLO_REQ, put16(b + 0, 3), SM_PROTO_EFIELD); /* min > max */
  MUT(K_HELLO_REQ, put16(b + 0, 0), SM_PROTO_EFIELD); /* version 0 */
  MUT(K_HELLO_REQ, put16(b + 42, 1), SM_PROTO_EFIELD);
  MUT(K_HELLO_RESP, put32(b + 36, 2), SM_PROTO_EFIELD);
  MUT(K_HELLO_RESP, put16(b + 0, 0), SM_PROTO_EFIELD);
  MUT(K_HAS_RESP, put32(b + 0, SM_HAS_PREPARED), SM_PROTO_EFIELD);
  MUT(K_HAS_RESP, put32(b + 0, 4), SM_PROTO_EFIELD);
  MUT(K_PUT_REQ, put32(b + 32, 2), SM_PROTO_EFIELD);
  MUT(K_PUT_REQ, put32(b + 36, 1), SM_PROTO_EFIELD);
  MUT(K_PUT_RESP, put32(b + 40, 2), SM_PROTO_EFIELD);
  MUT(K_PREP_REQ, put32(b + 36, 1), SM_PROTO_EFIELD);
  MUT(K_PREP_REQ, b[47] = 0xFF, SM_PROTO_EFIELD); /* eta NaN */
  MUT(K_PREP_RESP, put32(b + 12, 2), SM_PROTO_EFIELD);
  MUT(K_STATS_RESP, b[8] = 'A', SM_PROTO_EFIELD);  /* uppercase name */
  MUT(K_STATS_RESP, b[8] = 0, SM_PROTO_EFIELD);    /* empty name */
  MUT(K_STATS_RESP, b[8 + 23] = 'x', SM_PROTO_EFIELD); /* text after the NUL padding */
  MUT(K_STATS_RESP, put32(b + 4, 1), SM_PROTO_EFIELD);
  MUT(K_BATCH_REQ, b[8] = SM_OP_PUT_SHAPE, SM_PROTO_EOPCODE);
  MUT(K_BATCH_REQ, b[8] = SM_OP_BATCH, SM_PROTO_EOPCODE);
  MUT(K_BATCH_REQ, b[8] = 0, SM_PROTO_EOPCODE);
  MUT(K_BATCH_REQ, b[9] = 1, SM_PROTO_EFIELD);
  MUT(K_BATCH_REQ, put32(b + 0, 0), SM_PROTO_EFIELD);
  MUT(K_BATCH_ITEM, b[4] = SM_OP_HELLO, SM_PROTO_EOPCODE);
  MUT(K_BATCH_ITEM, b[6] = 1, SM_PROTO_EFIELD);
  MUT(K_BATCH_DONE, put32(b + 4, 4), SM_PROTO_EFIELD); /* n_ok > n_items */
  MUT(K_CANCEL_REQ, put32(b + 0, 0), SM_PROTO_EFIELD);
  MUT(K_ERROR, (put32(b + 8, 1025), n_ = 12 + 1025), SM_PROTO_EFIELD);
  MUT(K_DROP_RESP, n_ = 1, SM_PROTO_ELENGTH);
  {
    anymsg m;
    CHECK(sm_proto_dec_match_req(SM_OP_QUERY, ITEM_MATCH, item_match_len, &m.match_req) ==
          SM_PROTO_EOPCODE);
  }
}

/* ---- MATCH response across versions (PROTOCOL.md 5.7, 7.1) ---- */
static void test_match_resp_versions(void) {
  static uint8_t v1[1024], v2[1024], fr[1024];
  sm_proto_match_resp m = m_match_resp(), d;
  ptrdiff_t n1 = sm_proto_enc_match_resp(v1, sizeof v1, NULL, 1, &m);
  ptrdiff_t n2 = sm_proto_enc_match_resp(v2, sizeof v2, NULL, 2, &m);
  /* version 2 = version 1 + the confidence appended: every version 1 offset holds */
  REQUIRE(n1 == 112 + 4 * (7 + 5) + 8 * 9 && n2 == n1 + 8);
  CHECK(memcmp(v1, v2, (size_t)n1) == 0);
  uint8_t want[8];
  put_f64(want, 0.8125);
  CHECK(memcmp(v2 + n1, want, 8) == 0);
  /* each version's decoder takes its own layout only */
  CHECK(dec_match_v(1, v1, (size_t)n1, &d) == 0 && isnan(d.confidence) && d.orientation == 0.93 &&
        d.map_xy.count == 7 && d.fmap.count == 9);
  CHECK(dec_match_v(2, v2, (size_t)n2, &d) == 0 && d.confidence == 0.8125);
  CHECK(dec_match_v(2, v1, (size_t)n1, &d) == SM_PROTO_ELENGTH);
  CHECK(dec_match_v(1, v2, (size_t)n2, &d) == SM_PROTO_ELENGTH);
  CHECK(dec_match_v(2, v2, 112 + 7, &d) == SM_PROTO_ETRUNC); /* fixed part + confidence */
  CHECK(dec_match_v(0, v2, (size_t)n2, &d) == SM_PROTO_EVERSION);
  CHECK(dec_match_v(SM_PROTO_VERSION_MAX + 1, v2, (size_t)n2, &d) == SM_PROTO_EVERSION);
  /* the frame carries the layout's version */
  sm_proto_header h = {0};
  h.request_id = 4;
  sm_proto_frame f;
  for (uint8_t v = 1; v <= 2; v++) {
    ptrdiff_t n = sm_proto_enc_match_resp(fr, sizeof fr, &h, v, &m);
    CHECK(n == 24 + (v == 1 ? n1 : n2));
    CHECK(sm_proto_parse_frame(fr, (size_t)n, LIMIT, &f) == n && f.h.version == v);
  }
  h.version = 1; /* a header of another version than the layout */
  CHECK(sm_proto_enc_match_resp(fr, sizeof fr, &h, 2, &m) == SM_PROTO_EINVAL);
  h.version = 0;
  CHECK(sm_proto_enc_match_resp(fr, sizeof fr, &h, 0, &m) == SM_PROTO_EINVAL);
  CHECK(sm_proto_enc_match_resp(fr, sizeof fr, &h, SM_PROTO_VERSION_MAX + 1, &m) == SM_PROTO_EINVAL);
  /* the encoder refuses a confidence the decoder would; version 1 has none to refuse */
  const double bad[] = {NAN, -0.25, 1.5, INFINITY};
  for (int i = 0; i < 4; i++) {
    m.confidence = bad[i];
    CHECK_MSG(sm_proto_enc_match_resp(v2, sizeof v2, NULL, 2, &m) == SM_PROTO_EINVAL,
              "confidence %g encoded", bad[i]);
    CHECK(sm_proto_enc_match_resp(v1, sizeof v1, NULL, 1, &m) == n1);
  }
  /* a request-level error whose message names the field */
  CHECK(strstr(sm_proto_strerror(SM_PROTO_ECONFIDENCE), "confidence") != NULL);
  CHECK(!sm_proto_status_is_fatal(sm_proto_status_for_error(SM_PROTO_ECONFIDENCE)));
}

/* ---- encoders refuse what decoders would reject ---- */
static void test_encoder_args(void) {
  uint8_t buf[1024];
  sm_proto_header h = {0};
  h.request_id = 1;
  sm_proto_match_req m = m_match_req(0);
  m.basis = 4;
  CHECK(sm_proto_enc_match_req(buf, sizeof buf, &h, SM_OP_MATCH, &m) == SM_PROTO_EINVAL);
  m = m_match_req(0);
  m.landmarks.count = 5; /* odd */
  CHECK(sm_proto_enc_match_req(buf, sizeof buf, &h, SM_OP_MATCH, &m) == SM_PROTO_EINVAL);
  m = m_match_req(0);
  CHECK(sm_proto_enc_match_req(buf, sizeof buf, &h, SM_OP_DISTANCE, &m) == SM_PROTO_EINVAL);
  CHECK(sm_proto_enc_match_req(buf, sizeof buf, &h, SM_OP_QUERY, &m) == SM_PROTO_EINVAL);
  sm_proto_header bad = h;
  bad.status = 1; /* status in a request */
  m = m_match_req(0);
  CHECK(sm_proto_enc_match_req(buf, sizeof buf, &bad, SM_OP_MATCH, &m) == SM_PROTO_EINVAL);
  bad = h;
  bad.request_id = 0;
  CHECK(sm_proto_enc_match_req(buf, sizeof buf, &bad, SM_OP_MATCH, &m) == SM_PROTO_EINVAL);
  bad = h;
  bad.flags = 0x100;
  CHECK(sm_proto_enc_match_req(buf, sizeof buf, &bad, SM_OP_MATCH, &m) == SM_PROTO_EINVAL);
  sm_proto_error e = {0, 0, "x", 1};
  sm_proto_header eh = {0};
  eh.opcode = SM_OP_MATCH;
  eh.request_id = 3;
  CHECK(sm_proto_enc_error(buf, sizeof buf, &eh, &e) == SM_PROTO_EINVAL); /* status OK */
  sm_proto_hello_req hr = m_hello_req();
  hr.token_len = SM_PROTO_MAX_TOKEN + 1;
  CHECK(sm_proto_enc_hello_req(buf, sizeof buf, &h, &hr) == SM_PROTO_EINVAL);
  /* HELLO frames are version 1 (PROTOCOL.md 5.1); other frames any version spoken */
  hr = m_hello_req();
  sm_proto_header h2 = h;
  h2.version = 2;
  CHECK(sm_proto_enc_hello_req(buf, sizeof buf, &h2, &hr) == SM_PROTO_EINVAL);
  sm_proto_hello_resp hs = m_hello_resp();
  CHECK(sm_proto_enc_hello_resp(buf, sizeof buf, &h2, &hs) == SM_PROTO_EINVAL);
  h2.version = 1;
  CHECK(sm_proto_enc_hello_req(buf, sizeof buf, &h2, &hr) > 0);
  h2.version = SM_PROTO_VERSION_MAX + 1;
  sm_proto_ping pv = {1};
  CHECK(sm_proto_enc_ping(buf, sizeof buf, &h2, 0, &pv) == SM_PROTO_EINVAL);
  sm_proto_stat badname[] = {{"Upper", 1}};
  sm_proto_stats_resp sr = {badname, NULL, 1};
  CHECK(sm_proto_enc_stats_resp(buf, sizeof buf, &h, &sr) == SM_PROTO_EINVAL);
  sm_proto_batch_item items[] = {{SM_OP_PUT_SHAPE, ITEM_PING, 8}};
  sm_proto_batch_req br = {items, NULL, 0, 1};
  CHECK(sm_proto_enc_batch_req(buf, sizeof buf, &h, &br) == SM_PROTO_EINVAL);
  /* the size query works with a NULL buffer */
  sm_proto_ping pg = {1};
  CHECK(sm_proto_enc_ping(NULL, 0, &h, 0, &pg) == 32);
  CHECK(sm_proto_enc_ping(NULL, 0, NULL, 0, &pg) == 8);
  /* names */
  CHECK(strcmp(sm_proto_op_name(SM_OP_MATCH), "MATCH") == 0);
  CHECK(strcmp(sm_proto_status_name(SM_ST_BUSY), "BUSY") == 0);
  CHECK(strcmp(sm_proto_strerror(SM_PROTO_EMAGIC), "bad magic") == 0);
}

int main(void) {
  test_crc32c();
  test_sha256();
  build_fixtures();
  test_roundtrip();
  test_fixed_id_offsets();
  build_stream();
  fprintf(stderr, "%d frames, %zu-byte stream\n", nframes, stream_len);
  test_prefixes();
  test_random_splits();
  test_bad_headers();
  test_truncations();
  test_bad_payloads();
  test_match_resp_versions();
  test_encoder_args();
  for (int i = 0; i < nframes; i++) free(frames[i]);
  free(stream);
  return sm_test_finish();
}
