/* sm_proto: codec for PROTOCOL.md. Layout offsets in this file are those of the spec's
 * tables; change both together.
 *
 * DESIGN
 *   Decoders check the fixed part's length (ETRUNC), then compute the exact payload length
 *   its counts imply in 64-bit arithmetic (no overflow for any u32 count) and require
 *   equality (ELENGTH): a count can never make a reader step past the body. Encoders
 *   write sequentially through a cursor that stores only what fits in cap but always
 *   advances, so one pass yields both the bytes and the needed size (snprintf style).
 *   Integers and doubles go through byte-wise load/store helpers: no struct casts, no
 *   alignment or host byte order assumptions.
 */
#include "sm_proto.h"

#include <float.h>
#include <math.h>
#include <string.h>

/* ---- CRC32C ----
 * Castagnoli polynomial, reflected (0x82F63B78), init and final xor 0xFFFFFFFF, as in
 * RFC 3720 (iSCSI) §B.4. Written here because Debian 12 ships no small C library that
 * provides CRC32C (zlib's crc32 is the IEEE polynomial). Byte-wise table; the table was
 * generated with the loop `c = c & 1 ? (c >> 1) ^ 0x82F63B78 : c >> 1` (8 times per byte),
 * a const array so that the module has no initialization and no mutable state. */
static const uint32_t crc32c_tab[256] = {
    0x00000000u, 0xf26b8303u, 0xe13b70f7u, 0x1350f3f4u, 0xc79a971fu, 0x35f1141cu,
    0x26a1e7e8u, 0xd4ca64ebu, 0x8ad958cfu, 0x78b2dbccu, 0x6be22838u, 0x9989ab3bu,
    0x4d43cfd0u, 0xbf284cd3u, 0xac78bf27u, 0x5e133c24u, 0x105ec76fu, 0xe235446cu,
    0xf165b798u, 0x030e349bu, 0xd7c45070u, 0x25afd373u, 0x36ff2087u, 0xc494a384u,
    0x9a879fa0u, 0x68ec1ca3u, 0x7bbcef57u, 0x89d76c54u, 0x5d1d08bfu, 0xaf768bbcu,
    0xbc267848u, 0x4e4dfb4bu, 0x20bd8edeu, 0xd2d60dddu, 0xc186fe29u, 0x33ed7d2au,
    0xe72719c1u, 0x154c9ac2u, 0x061c6936u, 0xf477ea35u, 0xaa64d611u, 0x580f5512u,
    0x4b5fa6e6u, 0xb93425e5u, 0x6dfe410eu, 0x9f95c20du, 0x8cc531f9u, 0x7eaeb2fau,
    0x30e349b1u, 0xc288cab2u, 0xd1d83946u, 0x23b3ba45u, 0xf779deaeu, 0x05125dadu,
    0x1642ae59u, 0xe4292d5au, 0xba3a117eu, 0x4851927du, 0x5b016189u, 0xa96ae28au,
    0x7da08661u, 0x8fcb0562u, 0x9c9bf696u, 0x6ef07595u, 0x417b1dbcu, 0xb3109ebfu,
    0xa0406d4bu, 0x522bee48u, 0x86e18aa3u, 0x748a09a0u, 0x67dafa54u, 0x95b17957u,
    0xcba24573u, 0x39c9c670u, 0x2a993584u, 0xd8f2b687u, 0x0c38d26cu, 0xfe53516fu,
    0xed03a29bu, 0x1f682198u, 0x5125dad3u, 0xa34e59d0u, 0xb01eaa24u, 0x42752927u,
    0x96bf4dccu, 0x64d4cecfu, 0x77843d3bu, 0x85efbe38u, 0xdbfc821cu, 0x2997011fu,
    0x3ac7f2ebu, 0xc8ac71e8u, 0x1c661503u, 0xee0d9600u, 0xfd5d65f4u, 0x0f36e6f7u,
    0x61c69362u, 0x93ad1061u, 0x80fde395u, 0x72966096u, 0xa65c047du, 0x5437877eu,
    0x4767748au, 0xb50cf789u, 0xeb1fcbadu, 0x197448aeu, 0x0a24bb5au, 0xf84f3859u,
    0x2c855cb2u, 0xdeeedfb1u, 0xcdbe2c45u, 0x3fd5af46u, 0x7198540du, 0x83f3d70eu,
    0x90a324fau, 0x62c8a7f9u, 0xb602c312u, 0x44694011u, 0x5739b3e5u, 0xa55230e6u,
    0xfb410cc2u, 0x092a8fc1u, 0x1a7a7c35u, 0xe811ff36u, 0x3cdb9bddu, 0xceb018deu,
    0xdde0eb2au, 0x2f8b6829u, 0x82f63b78u, 0x709db87bu, 0x63cd4b8fu, 0x91a6c88cu,
    0x456cac67u, 0xb7072f64u, 0xa457dc90u, 0x563c5f93u, 0x082f63b7u, 0xfa44e0b4u,
    0xe9141340u, 0x1b7f9043u, 0xcfb5f4a8u, 0x3dde77abu, 0x2e8e845fu, 0xdce5075cu,
    0x92a8fc17u, 0x60c37f14u, 0x73938ce0u, 0x81f80fe3u, 0x55326b08u, 0xa759e80bu,
    0xb4091bffu, 0x466298fcu, 0x1871a4d8u, 0xea1a27dbu, 0xf94ad42fu, 0x0b21572cu,
    0xdfeb33c7u, 0x2d80b0c4u, 0x3ed04330u, 0xccbbc033u, 0xa24bb5a6u, 0x502036a5u,
    0x4370c551u, 0xb11b4652u, 0x65d122b9u, 0x97baa1bau, 0x84ea524eu, 0x7681d14du,
    0x2892ed69u, 0xdaf96e6au, 0xc9a99d9eu, 0x3bc21e9du, 0xef087a76u, 0x1d63f975u,
    0x0e330a81u, 0xfc588982u, 0xb21572c9u, 0x407ef1cau, 0x532e023eu, 0xa145813du,
    0x758fe5d6u, 0x87e466d5u, 0x94b49521u, 0x66df1622u, 0x38cc2a06u, 0xcaa7a905u,
    0xd9f75af1u, 0x2b9cd9f2u, 0xff56bd19u, 0x0d3d3e1au, 0x1e6dcdeeu, 0xec064eedu,
    0xc38d26c4u, 0x31e6a5c7u, 0x22b65633u, 0xd0ddd530u, 0x0417b1dbu, 0xf67c32d8u,
    0xe52cc12cu, 0x1747422fu, 0x49547e0bu, 0xbb3ffd08u, 0xa86f0efcu, 0x5a048dffu,
    0x8ecee914u, 0x7ca56a17u, 0x6ff599e3u, 0x9d9e1ae0u, 0xd3d3e1abu, 0x21b862a8u,
    0x32e8915cu, 0xc083125fu, 0x144976b4u, 0xe622f5b7u, 0xf5720643u, 0x07198540u,
    0x590ab964u, 0xab613a67u, 0xb831c993u, 0x4a5a4a90u, 0x9e902e7bu, 0x6cfbad78u,
    0x7fab5e8cu, 0x8dc0dd8fu, 0xe330a81au, 0x115b2b19u, 0x020bd8edu, 0xf0605beeu,
    0x24aa3f05u, 0xd6c1bc06u, 0xc5914ff2u, 0x37faccf1u, 0x69e9f0d5u, 0x9b8273d6u,
    0x88d28022u, 0x7ab90321u, 0xae7367cau, 0x5c18e4c9u, 0x4f48173du, 0xbd23943eu,
    0xf36e6f75u, 0x0105ec76u, 0x12551f82u, 0xe03e9c81u, 0x34f4f86au, 0xc69f7b69u,
    0xd5cf889du, 0x27a40b9eu, 0x79b737bau, 0x8bdcb4b9u, 0x988c474du, 0x6ae7c44eu,
    0xbe2da0a5u, 0x4c4623a6u, 0x5f16d052u, 0xad7d5351u
};

uint32_t sm_proto_crc32c(uint32_t crc, const void *data, size_t len) {
  const uint8_t *p = data;
  crc = ~crc;
  while (len--) crc = crc32c_tab[(crc ^ *p++) & 0xFF] ^ (crc >> 8);
  return ~crc;
}

/* ---- little-endian load/store ---- */
static inline uint16_t ld16(const uint8_t *p) { return (uint16_t)(p[0] | p[1] << 8); }
static inline uint32_t ld32(const uint8_t *p) {
  return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}
static inline uint64_t ld64(const uint8_t *p) { return ld32(p) | (uint64_t)ld32(p + 4) << 32; }
static inline double ldf64(const uint8_t *p) {
  uint64_t u = ld64(p);
  double d;
  memcpy(&d, &u, 8);
  return d;
}
static inline void st16(uint8_t *p, uint16_t v) {
  p[0] = (uint8_t)v;
  p[1] = (uint8_t)(v >> 8);
}
static inline void st32(uint8_t *p, uint32_t v) {
  for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}
static inline void st64(uint8_t *p, uint64_t v) {
  for (int i = 0; i < 8; i++) p[i] = (uint8_t)(v >> (8 * i));
}

int32_t sm_proto_i32_at(const sm_proto_i32s *a, uint32_t i) {
  return a->v ? a->v[i] : (int32_t)ld32(a->le + 4 * (size_t)i);
}
double sm_proto_f64_at(const sm_proto_f64s *a, uint32_t i) {
  return a->v ? a->v[i] : ldf64(a->le + 8 * (size_t)i);
}

/* ---- header ---- */
int sm_proto_write_header(uint8_t out[SM_PROTO_HEADER_LEN], const sm_proto_header *h) {
  out[0] = SM_PROTO_MAGIC0;
  out[1] = SM_PROTO_MAGIC1;
  out[2] = SM_PROTO_MAGIC2;
  out[3] = SM_PROTO_MAGIC3;
  out[4] = h->version;
  out[5] = h->opcode;
  st16(out + 6, h->flags);
  st32(out + 8, h->request_id);
  st16(out + 12, h->status);
  st16(out + 14, 0);
  st32(out + 16, h->payload_len);
  st32(out + 20, sm_proto_crc32c(0, out, 20));
  return SM_PROTO_HEADER_LEN;
}

int sm_proto_parse_header(const uint8_t *buf, size_t len, uint32_t max_payload,
                          sm_proto_header *out) {
  static const uint8_t magic[4] = {SM_PROTO_MAGIC0, SM_PROTO_MAGIC1, SM_PROTO_MAGIC2,
                                   SM_PROTO_MAGIC3};
  /* the magic is judged on whatever prefix is present: a text client fails at byte 0 */
  for (size_t i = 0; i < 4 && i < len; i++)
    if (buf[i] != magic[i]) return SM_PROTO_EMAGIC;
  if (len < SM_PROTO_HEADER_LEN) return SM_PROTO_PARTIAL;
  /* CRC before the fields it covers: a corrupted byte is reported as corruption */
  if (ld32(buf + 20) != sm_proto_crc32c(0, buf, 20)) return SM_PROTO_EHDRCRC;
  sm_proto_header h;
  h.version = buf[4];
  h.opcode = buf[5];
  h.flags = ld16(buf + 6);
  h.request_id = ld32(buf + 8);
  h.status = ld16(buf + 12);
  h.payload_len = ld32(buf + 16);
  if (h.version < SM_PROTO_VERSION_MIN || h.version > SM_PROTO_VERSION_MAX)
    return SM_PROTO_EVERSION;
  if (h.flags & ~(uint16_t)SM_PROTO_F_KNOWN_) return SM_PROTO_EFLAGS;
  if (ld16(buf + 14) != 0) return SM_PROTO_ERESERVED;
  if (h.opcode == 0) return SM_PROTO_EHEADER;
  if (!(h.flags & SM_PROTO_F_RESPONSE) &&
      (h.status != 0 || (h.flags & SM_PROTO_F_MORE) || h.request_id == 0))
    return SM_PROTO_EHEADER;
  if ((h.flags & SM_PROTO_F_PAYLOAD_CRC) && h.payload_len < 4) return SM_PROTO_EHEADER;
  if (h.payload_len > max_payload) return SM_PROTO_ETOOBIG;
  if (out) *out = h;
  return SM_PROTO_HEADER_LEN;
}

int sm_proto_check_payload(const sm_proto_header *h, const uint8_t *payload,
                           uint32_t *body_len) {
  uint32_t n = h->payload_len;
  if (h->flags & SM_PROTO_F_PAYLOAD_CRC) {
    if (n < 4) return SM_PROTO_EHEADER;
    n -= 4;
    if (ld32(payload + n) != sm_proto_crc32c(0, payload, n)) return SM_PROTO_EPAYLOADCRC;
  }
  *body_len = n;
  return SM_PROTO_OK;
}

ptrdiff_t sm_proto_parse_frame(const uint8_t *buf, size_t len, uint32_t max_payload,
                               sm_proto_frame *out) {
  sm_proto_header h;
  int r = sm_proto_parse_header(buf, len, max_payload, &h);
  if (r < 0) return r;
  if (len - SM_PROTO_HEADER_LEN < h.payload_len) return SM_PROTO_PARTIAL;
  uint32_t body = 0;
  r = sm_proto_check_payload(&h, buf + SM_PROTO_HEADER_LEN, &body);
  if (r < 0) return r;
  if (out) {
    out->h = h;
    out->body = buf + SM_PROTO_HEADER_LEN;
    out->body_len = body;
  }
  return (ptrdiff_t)SM_PROTO_HEADER_LEN + (ptrdiff_t)h.payload_len;
}

/* ---- encoder cursor ---- */
typedef struct wr {
  uint8_t *b;
  size_t cap, pos;
} wr;

static void w_bytes(wr *w, const void *src, size_t k) {
  if (k && w->b && w->pos <= w->cap && k <= w->cap - w->pos) {
    if (src)
      memcpy(w->b + w->pos, src, k);
    else
      memset(w->b + w->pos, 0, k);
  }
  w->pos += k;
}
static void w_u8(wr *w, uint8_t v) { w_bytes(w, &v, 1); }
static void w_u16(wr *w, uint16_t v) {
  uint8_t t[2];
  st16(t, v);
  w_bytes(w, t, 2);
}
static void w_u32(wr *w, uint32_t v) {
  uint8_t t[4];
  st32(t, v);
  w_bytes(w, t, 4);
}
static void w_u64(wr *w, uint64_t v) {
  uint8_t t[8];
  st64(t, v);
  w_bytes(w, t, 8);
}
static void w_f64(wr *w, double d) {
  uint64_t u;
  memcpy(&u, &d, 8);
  w_u64(w, u);
}
static void w_i32s(wr *w, const sm_proto_i32s *a) {
  if (a->v)
    for (uint32_t i = 0; i < a->count; i++) w_u32(w, (uint32_t)a->v[i]);
  else
    w_bytes(w, a->le, 4 * (size_t)a->count);
}
static void w_f64s(wr *w, const sm_proto_f64s *a) {
  if (a->v)
    for (uint32_t i = 0; i < a->count; i++) w_f64(w, a->v[i]);
  else
    w_bytes(w, a->le, 8 * (size_t)a->count);
}

/* Starts a frame: reserves the header when hdr is given. Returns 0 or EINVAL. */
static int begin(wr *w, uint8_t *buf, size_t cap, const sm_proto_header *hdr, int response) {
  w->b = buf;
  w->cap = cap;
  w->pos = 0;
  if (!hdr) return 0;
  if (hdr->flags & ~(uint16_t)SM_PROTO_F_KNOWN_) return SM_PROTO_EINVAL;
  if (hdr->version && (hdr->version < SM_PROTO_VERSION_MIN || hdr->version > SM_PROTO_VERSION_MAX))
    return SM_PROTO_EINVAL;
  if (!response && (hdr->status || (hdr->flags & SM_PROTO_F_MORE) || hdr->request_id == 0))
    return SM_PROTO_EINVAL;
  w->pos = SM_PROTO_HEADER_LEN;
  return 0;
}

/* Completes the frame begun by begin(): header, trailer, size. */
static ptrdiff_t finish(wr *w, const sm_proto_header *hdr, uint8_t opcode, int response,
                        uint16_t add_flags) {
  if (!hdr) return w->pos > (size_t)PTRDIFF_MAX ? SM_PROTO_EINVAL : (ptrdiff_t)w->pos;
  sm_proto_header h = *hdr;
  if (h.version == 0) h.version = SM_PROTO_VERSION_HELLO;
  h.opcode = opcode;
  h.flags = (uint16_t)((h.flags | add_flags) & ~SM_PROTO_F_RESPONSE);
  if (response) h.flags |= SM_PROTO_F_RESPONSE;
  size_t body = w->pos - SM_PROTO_HEADER_LEN;
  int crc = (h.flags & SM_PROTO_F_PAYLOAD_CRC) != 0;
  if (body > (size_t)UINT32_MAX - 4) return SM_PROTO_EINVAL;
  h.payload_len = (uint32_t)(body + (crc ? 4 : 0));
  size_t total = SM_PROTO_HEADER_LEN + (size_t)h.payload_len;
  if (total > (size_t)PTRDIFF_MAX) return SM_PROTO_EINVAL;
  if (w->b && total <= w->cap) {
    if (crc)
      st32(w->b + SM_PROTO_HEADER_LEN + body,
           sm_proto_crc32c(0, w->b + SM_PROTO_HEADER_LEN, body));
    sm_proto_write_header(w->b, &h);
  }
  return (ptrdiff_t)total;
}

/* ---- validation shared by encoders and decoders ---- */
static int eta_ok(double eta) { return eta == 0 || (eta > 0 && eta <= DBL_MAX); }

static int stat_name_ok(const char *name, size_t cap) {
  size_t n = 0;
  while (n < cap && name[n]) n++;
  if (n == 0) return 0;
  for (size_t i = 0; i < n; i++) {
    char c = name[i];
    if (!((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_' || c == '.')) return 0;
  }
  for (size_t i = n; i < cap; i++)
    if (name[i]) return 0;
  return 1;
}

/* The opcode table (sm_proto.h). */
typedef struct op_info {
  const char *name;
  unsigned flags;
} op_info;
enum { REQ = SM_OPF_REQUEST, Q = SM_OPF_QUEUED, B = SM_OPF_BATCHABLE, I = SM_OPF_IDEMPOTENT };
/* Not idempotent: HELLO (sets up the connection it is sent on), DROP_SHAPE (a resend after
 * a lost answer reports NOT_FOUND for a drop that happened, and would remove a copy another
 * client PUT in between), CANCEL (names a request of its own connection). */
static const op_info op_table[SM_OP_MAX_ + 1] = {
  [0] = {"INVALID", 0},
  [SM_OP_HELLO] = {"HELLO", REQ},
  [SM_OP_PING] = {"PING", REQ | B | I},
  [SM_OP_STATS] = {"STATS", REQ | I},
  [SM_OP_PUT_SHAPE] = {"PUT_SHAPE", REQ | Q | I},
  [SM_OP_HAS_SHAPE] = {"HAS_SHAPE", REQ | B | I},
  [SM_OP_DROP_SHAPE] = {"DROP_SHAPE", REQ},
  [SM_OP_PREPARE] = {"PREPARE", REQ | Q | B | I},
  [SM_OP_MATCH] = {"MATCH", REQ | Q | B | I},
  [SM_OP_DISTANCE] = {"DISTANCE", REQ | Q | B | I},
  [SM_OP_QUERY] = {"QUERY", REQ | Q | B | I},
  [SM_OP_BATCH] = {"BATCH", REQ | Q | I},
  [SM_OP_CANCEL] = {"CANCEL", REQ},
  [SM_OP_GOAWAY] = {"GOAWAY", SM_OPF_SERVER},
};

unsigned sm_proto_op_flags(uint8_t op) { return op <= SM_OP_MAX_ ? op_table[op].flags : 0; }

const char *sm_proto_op_name(uint8_t op) { return op <= SM_OP_MAX_ ? op_table[op].name : "UNKNOWN"; }

static int batch_op_allowed(uint8_t op) { return (sm_proto_op_flags(op) & SM_OPF_BATCHABLE) != 0; }

static int i32s_min_ok(const sm_proto_i32s *a, int32_t lo) {
  for (uint32_t i = 0; i < a->count; i++)
    if (sm_proto_i32_at(a, i) < lo) return 0;
  return 1;
}

/* ---- HELLO ---- */
static int hello_req_ok(const sm_proto_hello_req *m) {
  return m->min_version >= 1 && m->min_version <= m->max_version &&
         m->token_len <= SM_PROTO_MAX_TOKEN && (m->token || m->token_len == 0);
}
ptrdiff_t sm_proto_enc_hello_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                 const sm_proto_hello_req *m) {
  wr w;
  if (!hello_req_ok(m) || (hdr && hdr->version > SM_PROTO_VERSION_HELLO) ||
      begin(&w, buf, cap, hdr, 0))
    return SM_PROTO_EINVAL;
  w_u16(&w, m->min_version);
  w_u16(&w, m->max_version);
  w_u32(&w, m->max_response);
  w_bytes(&w, m->affinity, SM_PROTO_ID_LEN);
  w_u16(&w, m->token_len);
  w_u16(&w, 0);
  w_bytes(&w, m->token, m->token_len);
  return finish(&w, hdr, SM_OP_HELLO, 0, 0);
}
int sm_proto_dec_hello_req(const uint8_t *p, size_t n, sm_proto_hello_req *m) {
  if (n < 44) return SM_PROTO_ETRUNC;
  m->min_version = ld16(p);
  m->max_version = ld16(p + 2);
  m->max_response = ld32(p + 4);
  memcpy(m->affinity, p + 8, SM_PROTO_ID_LEN);
  m->token_len = ld16(p + 40);
  m->token = p + 44;
  if (ld16(p + 42) != 0) return SM_PROTO_EFIELD;
  if (n != 44 + (size_t)m->token_len) return SM_PROTO_ELENGTH;
  if (!hello_req_ok(m)) return SM_PROTO_EFIELD;
  return 0;
}

ptrdiff_t sm_proto_enc_hello_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_hello_resp *m) {
  wr w;
  if (m->version < 1 || (m->features & ~(uint32_t)SM_HELLO_F_KNOWN_) ||
      (hdr && hdr->version > SM_PROTO_VERSION_HELLO) || begin(&w, buf, cap, hdr, 1))
    return SM_PROTO_EINVAL;
  w_u16(&w, m->version);
  w_u16(&w, 0);
  w_u32(&w, m->max_payload);
  w_u32(&w, m->max_vertices);
  w_u32(&w, m->max_faces);
  w_u32(&w, m->max_inflight);
  w_u32(&w, m->max_batch_items);
  w_u32(&w, m->max_query_k);
  w_u32(&w, m->max_k);
  w_u32(&w, m->idle_timeout_ms);
  w_u32(&w, m->features);
  return finish(&w, hdr, SM_OP_HELLO, 1, 0);
}
int sm_proto_dec_hello_resp(const uint8_t *p, size_t n, sm_proto_hello_resp *m) {
  if (n < 40) return SM_PROTO_ETRUNC;
  if (n != 40) return SM_PROTO_ELENGTH;
  m->version = ld16(p);
  m->max_payload = ld32(p + 4);
  m->max_vertices = ld32(p + 8);
  m->max_faces = ld32(p + 12);
  m->max_inflight = ld32(p + 16);
  m->max_batch_items = ld32(p + 20);
  m->max_query_k = ld32(p + 24);
  m->max_k = ld32(p + 28);
  m->idle_timeout_ms = ld32(p + 32);
  m->features = ld32(p + 36);
  if (ld16(p + 2) != 0 || m->version < 1 || (m->features & ~(uint32_t)SM_HELLO_F_KNOWN_))
    return SM_PROTO_EFIELD;
  return 0;
}

/* ---- PING, empty ---- */
ptrdiff_t sm_proto_enc_ping(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                            int response, const sm_proto_ping *m) {
  wr w;
  if (begin(&w, buf, cap, hdr, response)) return SM_PROTO_EINVAL;
  w_u64(&w, m->opaque);
  return finish(&w, hdr, SM_OP_PING, response, 0);
}
int sm_proto_dec_ping(const uint8_t *p, size_t n, sm_proto_ping *m) {
  if (n < 8) return SM_PROTO_ETRUNC;
  if (n != 8) return SM_PROTO_ELENGTH;
  m->opaque = ld64(p);
  return 0;
}
ptrdiff_t sm_proto_enc_empty(uint8_t *buf, size_t cap, const sm_proto_header *hdr) {
  wr w;
  if (!hdr || hdr->opcode == 0 || hdr->opcode > SM_OP_MAX_) return SM_PROTO_EINVAL;
  int response = (hdr->flags & SM_PROTO_F_RESPONSE) != 0;
  if (begin(&w, buf, cap, hdr, response)) return SM_PROTO_EINVAL;
  return finish(&w, hdr, hdr->opcode, response, 0);
}
int sm_proto_dec_empty(const uint8_t *p, size_t n) {
  (void)p;
  return n == 0 ? 0 : SM_PROTO_ELENGTH;
}

/* ---- STATS ---- */
ptrdiff_t sm_proto_enc_stats_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_stats_resp *m) {
  wr w;
  if (begin(&w, buf, cap, hdr, 1)) return SM_PROTO_EINVAL;
  for (uint32_t i = 0; i < m->count; i++) {
    sm_proto_stat s;
    if (sm_proto_stat_at(m, i, &s)) return SM_PROTO_EINVAL;
  }
  w_u32(&w, m->count);
  w_u32(&w, 0);
  for (uint32_t i = 0; i < m->count; i++) {
    sm_proto_stat s;
    sm_proto_stat_at(m, i, &s);
    w_bytes(&w, s.name, SM_PROTO_STAT_NAME_LEN); /* NUL padded by stat_at */
    w_u64(&w, s.value);
  }
  return finish(&w, hdr, SM_OP_STATS, 1, 0);
}
/* Copies entry i into *out (NUL padded); EFIELD for a bad name. */
int sm_proto_stat_at(const sm_proto_stats_resp *s, uint32_t i, sm_proto_stat *out) {
  memset(out->name, 0, sizeof out->name);
  if (s->v) {
    size_t n = strnlen(s->v[i].name, sizeof s->v[i].name);
    if (n > SM_PROTO_STAT_NAME_LEN) return SM_PROTO_EFIELD;
    memcpy(out->name, s->v[i].name, n);
    out->value = s->v[i].value;
  } else {
    memcpy(out->name, s->le + 32 * (size_t)i, SM_PROTO_STAT_NAME_LEN);
    out->value = ld64(s->le + 32 * (size_t)i + SM_PROTO_STAT_NAME_LEN);
    if (!stat_name_ok((const char *)s->le + 32 * (size_t)i, SM_PROTO_STAT_NAME_LEN))
      return SM_PROTO_EFIELD;
  }
  return stat_name_ok(out->name, SM_PROTO_STAT_NAME_LEN) ? 0 : SM_PROTO_EFIELD;
}
int sm_proto_dec_stats_resp(const uint8_t *p, size_t n, sm_proto_stats_resp *m) {
  if (n < 8) return SM_PROTO_ETRUNC;
  m->v = NULL;
  m->count = ld32(p);
  m->le = p + 8;
  if (ld32(p + 4) != 0) return SM_PROTO_EFIELD;
  if ((uint64_t)n != 8 + 32 * (uint64_t)m->count) return SM_PROTO_ELENGTH;
  for (uint32_t i = 0; i < m->count; i++)
    if (!stat_name_ok((const char *)m->le + 32 * (size_t)i, SM_PROTO_STAT_NAME_LEN))
      return SM_PROTO_EFIELD;
  return 0;
}

/* ---- PUT_SHAPE ---- */
ptrdiff_t sm_proto_enc_put_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                               const sm_proto_put_req *m) {
  wr w;
  if (m->draco_len == 0 || !m->draco || (m->flags & ~(uint32_t)SM_PUT_F_KNOWN_) ||
      begin(&w, buf, cap, hdr, 0))
    return SM_PROTO_EINVAL;
  w_bytes(&w, m->id, SM_PROTO_ID_LEN);
  w_u32(&w, m->flags);
  w_u32(&w, 0);
  w_bytes(&w, m->draco, m->draco_len);
  return finish(&w, hdr, SM_OP_PUT_SHAPE, 0, 0);
}
int sm_proto_dec_put_req(const uint8_t *p, size_t n, sm_proto_put_req *m) {
  if (n < 41) return SM_PROTO_ETRUNC;
  if (n - 40 > UINT32_MAX) return SM_PROTO_ELENGTH;
  memcpy(m->id, p, SM_PROTO_ID_LEN);
  m->flags = ld32(p + 32);
  m->draco = p + 40;
  m->draco_len = (uint32_t)(n - 40);
  if ((m->flags & ~(uint32_t)SM_PUT_F_KNOWN_) || ld32(p + 36) != 0) return SM_PROTO_EFIELD;
  return 0;
}
ptrdiff_t sm_proto_enc_put_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                const sm_proto_put_resp *m) {
  wr w;
  if ((m->flags & ~(uint32_t)SM_PUT_R_KNOWN_) || begin(&w, buf, cap, hdr, 1))
    return SM_PROTO_EINVAL;
  w_bytes(&w, m->id, SM_PROTO_ID_LEN);
  w_u32(&w, m->n_vertices);
  w_u32(&w, m->n_faces);
  w_u32(&w, m->flags);
  return finish(&w, hdr, SM_OP_PUT_SHAPE, 1, 0);
}
int sm_proto_dec_put_resp(const uint8_t *p, size_t n, sm_proto_put_resp *m) {
  if (n < 44) return SM_PROTO_ETRUNC;
  if (n != 44) return SM_PROTO_ELENGTH;
  memcpy(m->id, p, SM_PROTO_ID_LEN);
  m->n_vertices = ld32(p + 32);
  m->n_faces = ld32(p + 36);
  m->flags = ld32(p + 40);
  return (m->flags & ~(uint32_t)SM_PUT_R_KNOWN_) ? SM_PROTO_EFIELD : 0;
}

/* ---- HAS_SHAPE / DROP_SHAPE ---- */
ptrdiff_t sm_proto_enc_id_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                              uint8_t opcode, const sm_proto_id_req *m) {
  wr w;
  if ((opcode != SM_OP_HAS_SHAPE && opcode != SM_OP_DROP_SHAPE) || begin(&w, buf, cap, hdr, 0))
    return SM_PROTO_EINVAL;
  w_bytes(&w, m->id, SM_PROTO_ID_LEN);
  return finish(&w, hdr, opcode, 0, 0);
}
int sm_proto_dec_id_req(const uint8_t *p, size_t n, sm_proto_id_req *m) {
  if (n < 32) return SM_PROTO_ETRUNC;
  if (n != 32) return SM_PROTO_ELENGTH;
  memcpy(m->id, p, SM_PROTO_ID_LEN);
  return 0;
}
static int has_ok(const sm_proto_has_resp *m) {
  if (m->flags & ~(uint32_t)SM_HAS_KNOWN_) return 0;
  if ((m->flags & SM_HAS_PREPARED) && !(m->flags & SM_HAS_STORED)) return 0;
  return 1;
}
ptrdiff_t sm_proto_enc_has_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                const sm_proto_has_resp *m) {
  wr w;
  if (!has_ok(m) || begin(&w, buf, cap, hdr, 1)) return SM_PROTO_EINVAL;
  w_u32(&w, m->flags);
  w_u32(&w, m->n_vertices);
  w_u32(&w, m->n_faces);
  return finish(&w, hdr, SM_OP_HAS_SHAPE, 1, 0);
}
int sm_proto_dec_has_resp(const uint8_t *p, size_t n, sm_proto_has_resp *m) {
  if (n < 12) return SM_PROTO_ETRUNC;
  if (n != 12) return SM_PROTO_ELENGTH;
  m->flags = ld32(p);
  m->n_vertices = ld32(p + 4);
  m->n_faces = ld32(p + 8);
  return has_ok(m) ? 0 : SM_PROTO_EFIELD;
}

/* ---- PREPARE ---- */
ptrdiff_t sm_proto_enc_prepare_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                   const sm_proto_prepare_req *m) {
  wr w;
  if (!eta_ok(m->eta) || begin(&w, buf, cap, hdr, 0)) return SM_PROTO_EINVAL;
  w_bytes(&w, m->id, SM_PROTO_ID_LEN);
  w_u16(&w, m->k_lb);
  w_u16(&w, m->k_elastic);
  w_u32(&w, 0);
  w_f64(&w, m->eta);
  return finish(&w, hdr, SM_OP_PREPARE, 0, 0);
}
int sm_proto_dec_prepare_req(const uint8_t *p, size_t n, sm_proto_prepare_req *m) {
  if (n < 48) return SM_PROTO_ETRUNC;
  if (n != 48) return SM_PROTO_ELENGTH;
  memcpy(m->id, p, SM_PROTO_ID_LEN);
  m->k_lb = ld16(p + 32);
  m->k_elastic = ld16(p + 34);
  m->eta = ldf64(p + 40);
  if (ld32(p + 36) != 0 || !eta_ok(m->eta)) return SM_PROTO_EFIELD;
  return 0;
}
ptrdiff_t sm_proto_enc_prepare_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                    const sm_proto_prepare_resp *m) {
  wr w;
  if ((m->flags & ~(uint32_t)SM_PREP_R_KNOWN_) || begin(&w, buf, cap, hdr, 1))
    return SM_PROTO_EINVAL;
  w_u32(&w, m->n_vertices);
  w_u32(&w, m->n_faces);
  w_u16(&w, m->k_lb);
  w_u16(&w, m->k_elastic);
  w_u32(&w, m->flags);
  w_u64(&w, m->t_clean_us);
  w_u64(&w, m->t_lb_us);
  w_u64(&w, m->t_elastic_us);
  w_u64(&w, m->t_desc_us);
  return finish(&w, hdr, SM_OP_PREPARE, 1, 0);
}
int sm_proto_dec_prepare_resp(const uint8_t *p, size_t n, sm_proto_prepare_resp *m) {
  if (n < 48) return SM_PROTO_ETRUNC;
  if (n != 48) return SM_PROTO_ELENGTH;
  m->n_vertices = ld32(p);
  m->n_faces = ld32(p + 4);
  m->k_lb = ld16(p + 8);
  m->k_elastic = ld16(p + 10);
  m->flags = ld32(p + 12);
  m->t_clean_us = ld64(p + 16);
  m->t_lb_us = ld64(p + 24);
  m->t_elastic_us = ld64(p + 32);
  m->t_desc_us = ld64(p + 40);
  return (m->flags & ~(uint32_t)SM_PREP_R_KNOWN_) ? SM_PROTO_EFIELD : 0;
}

/* ---- MATCH / DISTANCE ---- */
static int match_req_ok(uint8_t opcode, const sm_proto_match_req *m) {
  uint16_t known = opcode == SM_OP_MATCH ? SM_MATCH_F_KNOWN_ : SM_DISTANCE_F_KNOWN_;
  if (opcode != SM_OP_MATCH && opcode != SM_OP_DISTANCE) return 0;
  if (m->basis > 3 || m->init > 2 || (m->flags & ~known) || !eta_ok(m->eta)) return 0;
  if (m->k0 && m->k1 && m->k0 > m->k1) return 0;
  if ((m->flags & SM_MATCH_F_SINGLE_START) && (m->flags & SM_MATCH_F_MULTI_START)) return 0;
  if ((m->flags & SM_MATCH_F_MULTIRES) && (m->flags & SM_MATCH_F_DIRECT)) return 0;
  if (!(m->flags & SM_MATCH_F_SINKHORN_LEVELS) && m->sinkhorn_levels) return 0;
  if (m->landmarks.count % 2) return 0;
  if ((m->landmarks.count && !m->landmarks.v && !m->landmarks.le) ||
      (m->init_map.count && !m->init_map.v && !m->init_map.le))
    return 0;
  return i32s_min_ok(&m->landmarks, 0) && i32s_min_ok(&m->init_map, -1);
}
ptrdiff_t sm_proto_enc_match_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                 uint8_t opcode, const sm_proto_match_req *m) {
  wr w;
  if (!match_req_ok(opcode, m) || begin(&w, buf, cap, hdr, 0)) return SM_PROTO_EINVAL;
  w_bytes(&w, m->x, SM_PROTO_ID_LEN);
  w_bytes(&w, m->y, SM_PROTO_ID_LEN);
  w_u8(&w, m->basis);
  w_u8(&w, m->init);
  w_u16(&w, m->flags);
  w_u16(&w, m->k0);
  w_u16(&w, m->k1);
  w_u16(&w, m->step);
  w_u16(&w, m->sinkhorn_levels);
  w_u32(&w, m->landmarks.count / 2);
  w_f64(&w, m->eta);
  w_u32(&w, m->deadline_ms);
  w_u32(&w, m->init_map.count);
  w_i32s(&w, &m->landmarks);
  w_i32s(&w, &m->init_map);
  return finish(&w, hdr, opcode, 0, 0);
}
int sm_proto_dec_match_req(uint8_t opcode, const uint8_t *p, size_t n, sm_proto_match_req *m) {
  if (opcode != SM_OP_MATCH && opcode != SM_OP_DISTANCE) return SM_PROTO_EOPCODE;
  if (n < 96) return SM_PROTO_ETRUNC;
  memcpy(m->x, p, SM_PROTO_ID_LEN);
  memcpy(m->y, p + 32, SM_PROTO_ID_LEN);
  m->basis = p[64];
  m->init = p[65];
  m->flags = ld16(p + 66);
  m->k0 = ld16(p + 68);
  m->k1 = ld16(p + 70);
  m->step = ld16(p + 72);
  m->sinkhorn_levels = ld16(p + 74);
  uint32_t nl = ld32(p + 76);
  m->eta = ldf64(p + 80);
  m->deadline_ms = ld32(p + 88);
  uint32_t ni = ld32(p + 92);
  if ((uint64_t)n != 96 + 8 * (uint64_t)nl + 4 * (uint64_t)ni) return SM_PROTO_ELENGTH;
  m->landmarks = (sm_proto_i32s){NULL, p + 96, 2 * nl}; /* 2*nl*4 <= n: no overflow */
  m->init_map = (sm_proto_i32s){NULL, p + 96 + 8 * (size_t)nl, ni};
  if (!match_req_ok(opcode, m)) return SM_PROTO_EFIELD;
  return 0;
}

static void w_dist(wr *w, const sm_proto_dist *d) {
  w_f64(w, d->total);
  w_f64(w, d->point_xy);
  w_f64(w, d->point_yx);
  w_f64(w, d->spectrum_lb);
  w_f64(w, d->spectrum_elastic);
}
static void ld_dist(const uint8_t *p, sm_proto_dist *d) {
  d->total = ldf64(p);
  d->point_xy = ldf64(p + 8);
  d->point_yx = ldf64(p + 16);
  d->spectrum_lb = ldf64(p + 24);
  d->spectrum_elastic = ldf64(p + 32);
}

/* [0, 1]; NaN fails both comparisons */
static int confidence_ok(double c) { return c >= 0 && c <= 1; }

static int match_resp_ok(const sm_proto_match_resp *m) {
  if (m->init_used < 1 || m->init_used > 2 || (m->flags & ~(unsigned)SM_MATCH_R_KNOWN_))
    return 0;
  if ((uint32_t)m->kC * m->kC != m->fmap.count) return 0;
  if ((m->map_xy.count && !m->map_xy.v && !m->map_xy.le) ||
      (m->map_yx.count && !m->map_yx.v && !m->map_yx.le) ||
      (m->fmap.count && !m->fmap.v && !m->fmap.le))
    return 0;
  return i32s_min_ok(&m->map_xy, -1) && i32s_min_ok(&m->map_yx, -1);
}
ptrdiff_t sm_proto_enc_match_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  uint8_t version, const sm_proto_match_resp *m) {
  wr w;
  sm_proto_header hv;
  if (version < SM_PROTO_VERSION_MIN || version > SM_PROTO_VERSION_MAX) return SM_PROTO_EINVAL;
  int has_conf = version >= SM_PROTO_VERSION_CONFIDENCE;
  if (hdr) { /* the frame carries the version whose layout it holds */
    if (hdr->version && hdr->version != version) return SM_PROTO_EINVAL;
    hv = *hdr;
    hv.version = version;
    hdr = &hv;
  }
  if (!match_resp_ok(m) || (has_conf && !confidence_ok(m->confidence)) ||
      begin(&w, buf, cap, hdr, 1))
    return SM_PROTO_EINVAL;
  w_u32(&w, m->map_xy.count);
  w_u32(&w, m->map_yx.count);
  w_u16(&w, m->kC);
  w_u8(&w, m->init_used);
  w_u8(&w, m->flags);
  w_u32(&w, 0);
  w_f64(&w, m->orientation);
  w_f64(&w, m->dirichlet);
  w_dist(&w, &m->dist);
  w_u64(&w, m->t_prepare_us);
  w_u64(&w, m->t_init_us);
  w_u64(&w, m->t_refine_us);
  w_u64(&w, m->t_distance_us);
  w_u64(&w, m->t_total_us);
  w_i32s(&w, &m->map_xy);
  w_i32s(&w, &m->map_yx);
  w_f64s(&w, &m->fmap);
  if (has_conf) w_f64(&w, m->confidence); /* §7: new fields go after everything else */
  return finish(&w, hdr, SM_OP_MATCH, 1, 0);
}
int sm_proto_dec_match_resp(uint8_t version, const uint8_t *p, size_t n,
                            sm_proto_match_resp *m) {
  if (version < SM_PROTO_VERSION_MIN || version > SM_PROTO_VERSION_MAX) return SM_PROTO_EVERSION;
  uint64_t tail = version >= SM_PROTO_VERSION_CONFIDENCE ? 8 : 0;
  if (n < 112 + tail) return SM_PROTO_ETRUNC;
  uint32_t nx = ld32(p), ny = ld32(p + 4);
  m->kC = ld16(p + 8);
  m->init_used = p[10];
  m->flags = p[11];
  m->orientation = ldf64(p + 16);
  m->dirichlet = ldf64(p + 24);
  ld_dist(p + 32, &m->dist);
  m->t_prepare_us = ld64(p + 72);
  m->t_init_us = ld64(p + 80);
  m->t_refine_us = ld64(p + 88);
  m->t_distance_us = ld64(p + 96);
  m->t_total_us = ld64(p + 104);
  uint64_t nf = (uint64_t)m->kC * m->kC;
  if ((uint64_t)n != 112 + 4 * ((uint64_t)nx + ny) + 8 * nf + tail) return SM_PROTO_ELENGTH;
  m->map_xy = (sm_proto_i32s){NULL, p + 112, nx};
  m->map_yx = (sm_proto_i32s){NULL, p + 112 + 4 * (size_t)nx, ny};
  m->fmap = (sm_proto_f64s){NULL, p + 112 + 4 * ((size_t)nx + ny), (uint32_t)nf};
  m->confidence = tail ? ldf64(p + n - 8) : NAN; /* NaN: absent before version 2 */
  if (ld32(p + 12) != 0 || !match_resp_ok(m)) return SM_PROTO_EFIELD;
  if (tail && !confidence_ok(m->confidence)) return SM_PROTO_ECONFIDENCE;
  return 0;
}

ptrdiff_t sm_proto_enc_distance_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                     const sm_proto_distance_resp *m) {
  wr w;
  if (begin(&w, buf, cap, hdr, 1)) return SM_PROTO_EINVAL;
  w_dist(&w, &m->dist);
  w_u64(&w, m->t_total_us);
  return finish(&w, hdr, SM_OP_DISTANCE, 1, 0);
}
int sm_proto_dec_distance_resp(const uint8_t *p, size_t n, sm_proto_distance_resp *m) {
  if (n < 48) return SM_PROTO_ETRUNC;
  if (n != 48) return SM_PROTO_ELENGTH;
  ld_dist(p, &m->dist);
  m->t_total_us = ld64(p + 40);
  return 0;
}

/* ---- QUERY ---- */
static int query_req_ok(const sm_proto_query_req *m) {
  return m->k >= 1 && m->mode <= SM_QUERY_FULL && (m->candidates || m->n_candidates == 0);
}
ptrdiff_t sm_proto_enc_query_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                 const sm_proto_query_req *m) {
  wr w;
  if (!query_req_ok(m) || begin(&w, buf, cap, hdr, 0)) return SM_PROTO_EINVAL;
  w_bytes(&w, m->id, SM_PROTO_ID_LEN);
  w_u16(&w, m->k);
  w_u8(&w, m->mode);
  w_u8(&w, 0);
  w_u32(&w, m->deadline_ms);
  w_u32(&w, m->n_candidates);
  w_u32(&w, 0);
  w_bytes(&w, m->candidates, SM_PROTO_ID_LEN * (size_t)m->n_candidates);
  return finish(&w, hdr, SM_OP_QUERY, 0, 0);
}
int sm_proto_dec_query_req(const uint8_t *p, size_t n, sm_proto_query_req *m) {
  if (n < 48) return SM_PROTO_ETRUNC;
  memcpy(m->id, p, SM_PROTO_ID_LEN);
  m->k = ld16(p + 32);
  m->mode = p[34];
  m->deadline_ms = ld32(p + 36);
  m->n_candidates = ld32(p + 40);
  m->candidates = p + 48;
  if ((uint64_t)n != 48 + 32 * (uint64_t)m->n_candidates) return SM_PROTO_ELENGTH;
  if (p[35] != 0 || ld32(p + 44) != 0 || !query_req_ok(m)) return SM_PROTO_EFIELD;
  return 0;
}
void sm_proto_hit_at(const sm_proto_query_resp *q, uint32_t i, sm_proto_hit *out) {
  if (q->v) {
    *out = q->v[i];
  } else {
    memcpy(out->id, q->le + 40 * (size_t)i, SM_PROTO_ID_LEN);
    out->distance = ldf64(q->le + 40 * (size_t)i + 32);
  }
}
ptrdiff_t sm_proto_enc_query_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_query_resp *m) {
  wr w;
  if ((m->count && !m->v && !m->le) || begin(&w, buf, cap, hdr, 1)) return SM_PROTO_EINVAL;
  w_u32(&w, m->count);
  w_u32(&w, m->n_considered);
  w_u64(&w, m->t_total_us);
  for (uint32_t i = 0; i < m->count; i++) {
    sm_proto_hit h;
    sm_proto_hit_at(m, i, &h);
    w_bytes(&w, h.id, SM_PROTO_ID_LEN);
    w_f64(&w, h.distance);
  }
  return finish(&w, hdr, SM_OP_QUERY, 1, 0);
}
int sm_proto_dec_query_resp(const uint8_t *p, size_t n, sm_proto_query_resp *m) {
  if (n < 16) return SM_PROTO_ETRUNC;
  m->v = NULL;
  m->count = ld32(p);
  m->n_considered = ld32(p + 4);
  m->t_total_us = ld64(p + 8);
  m->le = p + 16;
  if ((uint64_t)n != 16 + 40 * (uint64_t)m->count) return SM_PROTO_ELENGTH;
  return 0;
}

/* ---- BATCH ---- */
int sm_proto_batch_next(const sm_proto_batch_req *b, size_t *pos, sm_proto_batch_item *it) {
  if (b->v) {
    if (*pos >= b->count) return 0;
    *it = b->v[(*pos)++];
    return 1;
  }
  /* le region was validated by the decoder (or comes from a trusted encoder caller) */
  if (*pos + 8 > b->le_len) return 0;
  const uint8_t *q = b->le + *pos;
  it->opcode = q[0];
  it->len = ld32(q + 4);
  it->payload = q + 8;
  *pos += 8 + (size_t)it->len;
  return 1;
}
ptrdiff_t sm_proto_enc_batch_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                 const sm_proto_batch_req *m) {
  wr w;
  if (m->count == 0 || begin(&w, buf, cap, hdr, 0)) return SM_PROTO_EINVAL;
  size_t pos = 0;
  sm_proto_batch_item it;
  uint32_t k = 0;
  while (sm_proto_batch_next(m, &pos, &it)) {
    if (!batch_op_allowed(it.opcode) || (it.len && !it.payload)) return SM_PROTO_EINVAL;
    k++;
  }
  if (k != m->count) return SM_PROTO_EINVAL;
  w_u32(&w, m->count);
  w_u32(&w, 0);
  pos = 0;
  while (sm_proto_batch_next(m, &pos, &it)) {
    w_u8(&w, it.opcode);
    w_u8(&w, 0);
    w_u16(&w, 0);
    w_u32(&w, it.len);
    w_bytes(&w, it.payload, it.len);
  }
  return finish(&w, hdr, SM_OP_BATCH, 0, 0);
}
int sm_proto_dec_batch_req(const uint8_t *p, size_t n, sm_proto_batch_req *m) {
  if (n < 8) return SM_PROTO_ETRUNC;
  m->v = NULL;
  m->count = ld32(p);
  m->le = p + 8;
  if (n - 8 > UINT32_MAX) return SM_PROTO_ELENGTH;
  m->le_len = (uint32_t)(n - 8);
  if (ld32(p + 4) != 0 || m->count == 0) return SM_PROTO_EFIELD;
  size_t pos = 8;
  for (uint32_t i = 0; i < m->count; i++) {
    if (n - pos < 8) return SM_PROTO_ELENGTH;
    const uint8_t *q = p + pos;
    uint32_t len = ld32(q + 4);
    if (!batch_op_allowed(q[0])) return SM_PROTO_EOPCODE;
    if (q[1] != 0 || ld16(q + 2) != 0) return SM_PROTO_EFIELD;
    if (n - pos - 8 < len) return SM_PROTO_ELENGTH;
    pos += 8 + (size_t)len;
  }
  return pos == n ? 0 : SM_PROTO_ELENGTH;
}
ptrdiff_t sm_proto_enc_batch_item_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                       const sm_proto_batch_item_resp *m) {
  wr w;
  if (!batch_op_allowed(m->opcode) || (m->len && !m->payload) ||
      begin(&w, buf, cap, hdr, 1))
    return SM_PROTO_EINVAL;
  w_u32(&w, m->index);
  w_u8(&w, m->opcode);
  w_u8(&w, 0);
  w_u16(&w, 0);
  w_bytes(&w, m->payload, m->len);
  return finish(&w, hdr, SM_OP_BATCH, 1, SM_PROTO_F_MORE);
}
int sm_proto_dec_batch_item_resp(const uint8_t *p, size_t n, sm_proto_batch_item_resp *m) {
  if (n < 8) return SM_PROTO_ETRUNC;
  if (n - 8 > UINT32_MAX) return SM_PROTO_ELENGTH;
  m->index = ld32(p);
  m->opcode = p[4];
  m->payload = p + 8;
  m->len = (uint32_t)(n - 8);
  if (!batch_op_allowed(m->opcode)) return SM_PROTO_EOPCODE;
  if (p[5] != 0 || ld16(p + 6) != 0) return SM_PROTO_EFIELD;
  return 0;
}
ptrdiff_t sm_proto_enc_batch_done(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_batch_done *m) {
  wr w;
  if (m->n_ok > m->n_items || (hdr && (hdr->flags & SM_PROTO_F_MORE)) ||
      begin(&w, buf, cap, hdr, 1))
    return SM_PROTO_EINVAL;
  w_u32(&w, m->n_items);
  w_u32(&w, m->n_ok);
  return finish(&w, hdr, SM_OP_BATCH, 1, 0);
}
int sm_proto_dec_batch_done(const uint8_t *p, size_t n, sm_proto_batch_done *m) {
  if (n < 8) return SM_PROTO_ETRUNC;
  if (n != 8) return SM_PROTO_ELENGTH;
  m->n_items = ld32(p);
  m->n_ok = ld32(p + 4);
  return m->n_ok > m->n_items ? SM_PROTO_EFIELD : 0;
}

/* ---- CANCEL ---- */
ptrdiff_t sm_proto_enc_cancel_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_cancel_req *m) {
  wr w;
  if (m->target == 0 || begin(&w, buf, cap, hdr, 0)) return SM_PROTO_EINVAL;
  w_u32(&w, m->target);
  return finish(&w, hdr, SM_OP_CANCEL, 0, 0);
}
int sm_proto_dec_cancel_req(const uint8_t *p, size_t n, sm_proto_cancel_req *m) {
  if (n < 4) return SM_PROTO_ETRUNC;
  if (n != 4) return SM_PROTO_ELENGTH;
  m->target = ld32(p);
  return m->target == 0 ? SM_PROTO_EFIELD : 0;
}

/* ---- error / GOAWAY ---- */
ptrdiff_t sm_proto_enc_error(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                             const sm_proto_error *m) {
  wr w;
  if (m->msg_len > SM_PROTO_MAX_MSG || (m->msg_len && !m->msg)) return SM_PROTO_EINVAL;
  if (hdr) {
    if (hdr->opcode == 0 || hdr->opcode > SM_OP_MAX_) return SM_PROTO_EINVAL;
    if (hdr->opcode != SM_OP_GOAWAY && hdr->status == SM_ST_OK) return SM_PROTO_EINVAL;
  }
  if (begin(&w, buf, cap, hdr, 1)) return SM_PROTO_EINVAL;
  w_u32(&w, m->retry_after_ms);
  w_u32(&w, m->detail);
  w_u32(&w, m->msg_len);
  w_bytes(&w, m->msg, m->msg_len);
  return finish(&w, hdr, hdr ? hdr->opcode : 0, 1, 0);
}
int sm_proto_dec_error(const uint8_t *p, size_t n, sm_proto_error *m) {
  if (n < 12) return SM_PROTO_ETRUNC;
  m->retry_after_ms = ld32(p);
  m->detail = ld32(p + 4);
  m->msg_len = ld32(p + 8);
  m->msg = (const char *)p + 12;
  if ((uint64_t)n != 12 + (uint64_t)m->msg_len) return SM_PROTO_ELENGTH;
  if (m->msg_len > SM_PROTO_MAX_MSG) return SM_PROTO_EFIELD;
  return 0;
}

/* ---- names ---- */
const char *sm_proto_strerror(int err) {
  switch (err) {
  case SM_PROTO_OK: return "ok";
  case SM_PROTO_PARTIAL: return "incomplete frame (need more bytes)";
  case SM_PROTO_EMAGIC: return "bad magic";
  case SM_PROTO_EHDRCRC: return "header CRC32C mismatch";
  case SM_PROTO_EVERSION: return "unsupported protocol version";
  case SM_PROTO_EFLAGS: return "unknown header flag";
  case SM_PROTO_ERESERVED: return "reserved header field not zero";
  case SM_PROTO_EHEADER: return "invalid header";
  case SM_PROTO_ETOOBIG: return "payload length above the limit";
  case SM_PROTO_EPAYLOADCRC: return "payload CRC32C mismatch";
  case SM_PROTO_ETRUNC: return "payload shorter than its fixed part";
  case SM_PROTO_ELENGTH: return "payload length disagrees with its counts";
  case SM_PROTO_EFIELD: return "invalid payload field";
  case SM_PROTO_EOPCODE: return "opcode not valid here";
  case SM_PROTO_EINVAL: return "message cannot be encoded";
  case SM_PROTO_ECONFIDENCE: return "confidence is NaN or outside [0, 1]";
  default: return "unknown error";
  }
}

const char *sm_proto_status_name(uint16_t st) {
  switch (st) {
  case SM_ST_OK: return "OK";
  case SM_ST_BAD_REQUEST: return "BAD_REQUEST";
  case SM_ST_UNKNOWN_OPCODE: return "UNKNOWN_OPCODE";
  case SM_ST_NOT_FOUND: return "NOT_FOUND";
  case SM_ST_DECODE_FAILED: return "DECODE_FAILED";
  case SM_ST_MESH_REJECTED: return "MESH_REJECTED";
  case SM_ST_LIMIT_EXCEEDED: return "LIMIT_EXCEEDED";
  case SM_ST_ID_MISMATCH: return "ID_MISMATCH";
  case SM_ST_BUSY: return "BUSY";
  case SM_ST_DEADLINE: return "DEADLINE";
  case SM_ST_CANCELLED: return "CANCELLED";
  case SM_ST_INTERNAL: return "INTERNAL";
  case SM_ST_SHUTTING_DOWN: return "SHUTTING_DOWN";
  case SM_ST_RESPONSE_TOO_LARGE: return "RESPONSE_TOO_LARGE";
  case SM_ST_BAD_MAGIC: return "BAD_MAGIC";
  case SM_ST_UNSUPPORTED_VERSION: return "UNSUPPORTED_VERSION";
  case SM_ST_BAD_HEADER_CRC: return "BAD_HEADER_CRC";
  case SM_ST_BAD_HEADER: return "BAD_HEADER";
  case SM_ST_FRAME_TOO_LARGE: return "FRAME_TOO_LARGE";
  case SM_ST_BAD_PAYLOAD_CRC: return "BAD_PAYLOAD_CRC";
  case SM_ST_PROTOCOL_ERROR: return "PROTOCOL_ERROR";
  case SM_ST_UNAUTHORIZED: return "UNAUTHORIZED";
  case SM_ST_TIMEOUT: return "TIMEOUT";
  case SM_ST_TOO_MANY_CONNECTIONS: return "TOO_MANY_CONNECTIONS";
  case SM_ST_OVERLOADED: return "OVERLOADED";
  default: return sm_proto_status_is_fatal(st) ? "UNKNOWN_FATAL" : "UNKNOWN";
  }
}

uint16_t sm_proto_status_for_error(int err) {
  switch (err) {
  case SM_PROTO_OK:
  case SM_PROTO_PARTIAL: return SM_ST_OK;
  case SM_PROTO_EMAGIC: return SM_ST_BAD_MAGIC;
  case SM_PROTO_EHDRCRC: return SM_ST_BAD_HEADER_CRC;
  case SM_PROTO_EVERSION: return SM_ST_UNSUPPORTED_VERSION;
  case SM_PROTO_EFLAGS:
  case SM_PROTO_ERESERVED:
  case SM_PROTO_EHEADER: return SM_ST_BAD_HEADER;
  case SM_PROTO_ETOOBIG: return SM_ST_FRAME_TOO_LARGE;
  case SM_PROTO_EPAYLOADCRC: return SM_ST_BAD_PAYLOAD_CRC;
  case SM_PROTO_EOPCODE: return SM_ST_UNKNOWN_OPCODE;
  default: return SM_ST_BAD_REQUEST;
  }
}
