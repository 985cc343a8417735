/* fuzz_proto_decode: every message decoder of protocol/sm_proto.h.
 *
 * Input: byte 0 picks the decoder (% N_CASES), byte 1 is its argument (the opcode for
 * MATCH/DISTANCE requests and HAS/DROP ids, the negotiated version for MATCH responses,
 * PAYLOAD_CRC for the framed re-encode), the rest is the payload body.
 * Properties, for a body the decoder accepts (sm_proto.h: "a decoded message can be
 * re-encoded unchanged"):
 *   - every element view (i32/f64 arrays, stats, hits, batch items) reads inside the body
 *     (the body is an exact-size copy: ASan sees any over-read), and every BATCH item's
 *     own payload goes through its request decoder;
 *   - the encoder, given the decoded message, writes the same bytes (payload-only form);
 *     given one byte less of room it returns the same size and writes nothing past it;
 *   - the framed form parses back (sm_proto_parse_frame) to a frame whose body is the input.
 * A rejected body only has to give an error code that has a name and a status.
 */
#include "sm_fuzz.h"
#include "sm_proto.h"

/* One decoder + its encoder: decodes p[0..n) and, if that succeeded, encodes the result into
 * buf[0..cap) with header h (NULL = payload only). Returns the encoder's result, or the
 * decoder's error as DEC_FAILED. */
typedef ptrdiff_t (*rt_fn)(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                           uint8_t *buf, size_t cap);
#define DEC_FAILED PTRDIFF_MIN

static void walk_i32(const sm_proto_i32s *a) {
  volatile int32_t sink = 0;
  for (uint32_t i = 0; i < a->count; i++) sink ^= sm_proto_i32_at(a, i);
  (void)sink;
}

static void walk_f64(const sm_proto_f64s *a) {
  volatile double sink = 0;
  for (uint32_t i = 0; i < a->count; i++) sink += sm_proto_f64_at(a, i);
  (void)sink;
}

static ptrdiff_t rt_hello_req(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                              uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_hello_req m;
  if (sm_proto_dec_hello_req(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_hello_req(buf, cap, h, &m);
}
static ptrdiff_t rt_hello_resp(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                               uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_hello_resp m;
  if (sm_proto_dec_hello_resp(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_hello_resp(buf, cap, h, &m);
}
static ptrdiff_t rt_ping(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                         uint8_t *buf, size_t cap) {
  sm_proto_ping m;
  if (sm_proto_dec_ping(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_ping(buf, cap, h, arg & 1, &m);
}
static ptrdiff_t rt_empty(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                          uint8_t *buf, size_t cap) {
  (void)arg;
  if (sm_proto_dec_empty(p, n)) return DEC_FAILED;
  if (!h) return 0; /* the payload-only form of nothing; the encoder needs a header */
  sm_proto_header s = *h; /* it takes opcode and direction from the header */
  s.opcode = SM_OP_STATS;
  return sm_proto_enc_empty(buf, cap, &s);
}
static ptrdiff_t rt_stats_resp(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                               uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_stats_resp m;
  if (sm_proto_dec_stats_resp(p, n, &m)) return DEC_FAILED;
  for (uint32_t i = 0; i < m.count; i++) {
    sm_proto_stat s;
    SM_FUZZ_CHECK(sm_proto_stat_at(&m, i, &s) == 0); /* the decoder checked every name */
    SM_FUZZ_CHECK(strlen(s.name) >= 1 && strlen(s.name) <= SM_PROTO_STAT_NAME_LEN);
  }
  return sm_proto_enc_stats_resp(buf, cap, h, &m);
}
static ptrdiff_t rt_put_req(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                            uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_put_req m;
  if (sm_proto_dec_put_req(p, n, &m)) return DEC_FAILED;
  SM_FUZZ_CHECK(m.draco >= p && m.draco + m.draco_len <= p + n);
  return sm_proto_enc_put_req(buf, cap, h, &m);
}
static ptrdiff_t rt_put_resp(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                             uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_put_resp m;
  if (sm_proto_dec_put_resp(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_put_resp(buf, cap, h, &m);
}
static ptrdiff_t rt_id_req(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                           uint8_t *buf, size_t cap) {
  sm_proto_id_req m;
  if (sm_proto_dec_id_req(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_id_req(buf, cap, h, arg & 1 ? SM_OP_DROP_SHAPE : SM_OP_HAS_SHAPE, &m);
}
static ptrdiff_t rt_has_resp(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                             uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_has_resp m;
  if (sm_proto_dec_has_resp(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_has_resp(buf, cap, h, &m);
}
static ptrdiff_t rt_prepare_req(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                                uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_prepare_req m;
  if (sm_proto_dec_prepare_req(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_prepare_req(buf, cap, h, &m);
}
static ptrdiff_t rt_prepare_resp(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                                 uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_prepare_resp m;
  if (sm_proto_dec_prepare_resp(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_prepare_resp(buf, cap, h, &m);
}
static ptrdiff_t rt_match_req(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                              uint8_t *buf, size_t cap) {
  uint8_t op = arg & 1 ? SM_OP_DISTANCE : SM_OP_MATCH;
  sm_proto_match_req m;
  if (sm_proto_dec_match_req(op, p, n, &m)) return DEC_FAILED;
  walk_i32(&m.landmarks);
  walk_i32(&m.init_map);
  return sm_proto_enc_match_req(buf, cap, h, op, &m);
}
static ptrdiff_t rt_match_resp(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                               uint8_t *buf, size_t cap) {
  uint8_t version = arg & 3; /* 0 and 3 are versions the codec must refuse */
  sm_proto_match_resp m;
  int rc = sm_proto_dec_match_resp(version, p, n, &m);
  if (version < SM_PROTO_VERSION_MIN || version > SM_PROTO_VERSION_MAX)
    SM_FUZZ_CHECK(rc == SM_PROTO_EVERSION);
  if (rc) return DEC_FAILED;
  walk_i32(&m.map_xy);
  walk_i32(&m.map_yx);
  walk_f64(&m.fmap);
  SM_FUZZ_CHECK(m.fmap.count == (uint32_t)m.kC * m.kC);
  sm_proto_header s;
  if (h) {
    s = *h;
    s.version = version;
  }
  return sm_proto_enc_match_resp(buf, cap, h ? &s : NULL, version, &m);
}
static ptrdiff_t rt_distance_resp(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                                  uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_distance_resp m;
  if (sm_proto_dec_distance_resp(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_distance_resp(buf, cap, h, &m);
}
static ptrdiff_t rt_query_req(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                              uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_query_req m;
  if (sm_proto_dec_query_req(p, n, &m)) return DEC_FAILED;
  SM_FUZZ_CHECK(m.n_candidates == 0 ||
                (m.candidates >= p && m.candidates + 32 * (size_t)m.n_candidates <= p + n));
  return sm_proto_enc_query_req(buf, cap, h, &m);
}
static ptrdiff_t rt_query_resp(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                               uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_query_resp m;
  if (sm_proto_dec_query_resp(p, n, &m)) return DEC_FAILED;
  for (uint32_t i = 0; i < m.count; i++) {
    sm_proto_hit hit;
    sm_proto_hit_at(&m, i, &hit);
  }
  return sm_proto_enc_query_resp(buf, cap, h, &m);
}
/* A BATCH item's payload through the decoder of its (allowed) request opcode. */
static void decode_item(const sm_proto_batch_item *it) {
  uint8_t *c = sm_fuzz_dup(it->payload, it->len);
  union {
    sm_proto_ping ping;
    sm_proto_id_req id;
    sm_proto_prepare_req prep;
    sm_proto_match_req match;
    sm_proto_query_req query;
  } u;
  int rc = SM_PROTO_EOPCODE;
  switch (it->opcode) {
    case SM_OP_PING: rc = sm_proto_dec_ping(c, it->len, &u.ping); break;
    case SM_OP_HAS_SHAPE: rc = sm_proto_dec_id_req(c, it->len, &u.id); break;
    case SM_OP_PREPARE: rc = sm_proto_dec_prepare_req(c, it->len, &u.prep); break;
    case SM_OP_MATCH:
    case SM_OP_DISTANCE: rc = sm_proto_dec_match_req(it->opcode, c, it->len, &u.match); break;
    case SM_OP_QUERY: rc = sm_proto_dec_query_req(c, it->len, &u.query); break;
    default: SM_FUZZ_CHECK(!"batch decoder let through an opcode it does not allow");
  }
  if (rc == 0 && (it->opcode == SM_OP_MATCH || it->opcode == SM_OP_DISTANCE)) {
    walk_i32(&u.match.landmarks);
    walk_i32(&u.match.init_map);
  }
  free(c);
}
static ptrdiff_t rt_batch_req(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                              uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_batch_req m;
  if (sm_proto_dec_batch_req(p, n, &m)) return DEC_FAILED;
  size_t pos = 0;
  uint32_t k = 0;
  sm_proto_batch_item it;
  while (sm_proto_batch_next(&m, &pos, &it)) {
    SM_FUZZ_CHECK(sm_proto_op_flags(it.opcode) & SM_OPF_BATCHABLE);
    SM_FUZZ_CHECK(it.payload >= p && it.payload + it.len <= p + n);
    decode_item(&it);
    k++;
  }
  SM_FUZZ_CHECK(k == m.count);
  return sm_proto_enc_batch_req(buf, cap, h, &m);
}
static ptrdiff_t rt_batch_item_resp(const uint8_t *p, size_t n, uint8_t arg,
                                    const sm_proto_header *h, uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_batch_item_resp m;
  if (sm_proto_dec_batch_item_resp(p, n, &m)) return DEC_FAILED;
  SM_FUZZ_CHECK(m.payload >= p && m.payload + m.len <= p + n);
  return sm_proto_enc_batch_item_resp(buf, cap, h, &m);
}
static ptrdiff_t rt_batch_done(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                               uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_batch_done m;
  if (sm_proto_dec_batch_done(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_batch_done(buf, cap, h, &m);
}
static ptrdiff_t rt_cancel_req(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                               uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_cancel_req m;
  if (sm_proto_dec_cancel_req(p, n, &m)) return DEC_FAILED;
  return sm_proto_enc_cancel_req(buf, cap, h, &m);
}
static ptrdiff_t rt_error(const uint8_t *p, size_t n, uint8_t arg, const sm_proto_header *h,
                          uint8_t *buf, size_t cap) {
  (void)arg;
  sm_proto_error m;
  if (sm_proto_dec_error(p, n, &m)) return DEC_FAILED;
  sm_proto_header s; /* framed as a GOAWAY: the one error frame any status may carry */
  if (h) {
    s = *h;
    s.opcode = SM_OP_GOAWAY;
  }
  return sm_proto_enc_error(buf, cap, h ? &s : NULL, &m);
}

static const rt_fn cases[] = {
    rt_hello_req,  rt_hello_resp,   rt_ping,          rt_empty,     rt_stats_resp,
    rt_put_req,    rt_put_resp,     rt_id_req,        rt_has_resp,  rt_prepare_req,
    rt_prepare_resp, rt_match_req,  rt_match_resp,    rt_distance_resp, rt_query_req,
    rt_query_resp, rt_batch_req,    rt_batch_item_resp, rt_batch_done, rt_cancel_req,
    rt_error};
#define N_CASES (sizeof cases / sizeof cases[0])

/* The framed form: header + body (+ CRC trailer) must parse back to this very body. */
static void check_framed(rt_fn fn, const uint8_t *p, size_t n, uint8_t arg) {
  sm_proto_header h = {.version = SM_PROTO_VERSION_HELLO, .request_id = 7,
                       .flags = (arg & 0x80) ? SM_PROTO_F_PAYLOAD_CRC : 0};
  size_t cap = SM_PROTO_HEADER_LEN + n + 4;
  uint8_t *frame = malloc(cap);
  SM_FUZZ_CHECK(frame != NULL);
  ptrdiff_t r = fn(p, n, arg, &h, frame, cap);
  if (r == SM_PROTO_EINVAL) { /* a header this message cannot carry (e.g. HELLO version) */
    free(frame);
    return;
  }
  SM_FUZZ_CHECK(r > 0 && (size_t)r <= cap);
  sm_proto_frame f;
  ptrdiff_t pr = sm_proto_parse_frame(frame, (size_t)r, UINT32_MAX, &f);
  SM_FUZZ_CHECK(pr == r);
  SM_FUZZ_CHECK(f.body_len == n && (n == 0 || memcmp(f.body, p, n) == 0));
  free(frame);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  rt_fn fn = cases[sm_fuzz_take(&data, &size) % N_CASES];
  uint8_t arg = sm_fuzz_take(&data, &size);
  uint8_t *p = sm_fuzz_dup(data, size);
  uint8_t *out = malloc(size ? size : 1);
  SM_FUZZ_CHECK(out != NULL);
  ptrdiff_t r = fn(p, size, arg, NULL, out, size);
  if (r != DEC_FAILED) {
    SM_FUZZ_CHECK(r == (ptrdiff_t)size);              /* re-encodes to the same length */
    SM_FUZZ_CHECK(size == 0 || memcmp(out, p, size) == 0); /* ... and the same bytes */
    if (size > 0) { /* one byte short: the snprintf contract, no write past cap */
      uint8_t *small = malloc(size - 1 ? size - 1 : 1);
      SM_FUZZ_CHECK(small != NULL);
      SM_FUZZ_CHECK(fn(p, size, arg, NULL, small, size - 1) == (ptrdiff_t)size);
      free(small);
    }
    check_framed(fn, p, size, arg);
  }
  free(out);
  free(p);
  return 0;
}
