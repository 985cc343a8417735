/* sm_proto: the shapematch wire protocol codec (normative spec: protocol/PROTOCOL.md).
 *
 * Contract
 *   Pure codec: no I/O, no allocation, no logging, no global mutable state (the CRC table
 *   is a const array). Every function is thread-safe; the caller owns every buffer.
 *   Parsing (picohttpparser style):
 *     - sm_proto_parse_header / sm_proto_parse_frame read at most `len` bytes of `buf` and
 *       return the bytes consumed (> 0), SM_PROTO_PARTIAL when more bytes are needed, or a
 *       negative SM_PROTO_E* error. They are stateless: call again with the longer buffer
 *       after more bytes arrive (any split of the stream gives the same frames).
 *     - The header is fully validated (magic, header CRC, version, opcode != 0, flags,
 *       reserved bits, direction rules, payload_len <= the caller's max_payload) from its
 *       24 bytes alone, so the caller can reject a frame before allocating its payload.
 *       A wrong first magic byte is reported as soon as that byte is present.
 *   Decoders (sm_proto_dec_*) take a payload body (trailer already removed) and fill a
 *     message struct whose arrays and strings are views into that body: the body must
 *     outlive the struct. Shape ids (32 bytes) are copied. Decoders check every length and
 *     count against the body length (no overflow), every enum and flag field and that
 *     reserved fields are zero and no bytes trail; they return 0 or a negative error.
 *     Array elements are read with sm_proto_i32_at / sm_proto_f64_at (little-endian, no
 *     alignment requirement).
 *   Encoders (sm_proto_enc_*) write one complete frame (24-byte header, payload, CRC32C
 *     trailer if hdr->flags has SM_PROTO_F_PAYLOAD_CRC) into buf[0..cap) and return the
 *     frame size, like snprintf: if the result exceeds cap nothing usable was written (buf
 *     contents unspecified) and the caller retries with a buffer of the returned size.
 *     With hdr == NULL they write the payload only (BATCH items are built that way).
 *     They take request_id, flags (PAYLOAD_CRC, MORE), status and version from *hdr, set
 *     the opcode, the RESPONSE flag as the message requires and payload_len themselves,
 *     and return SM_PROTO_EINVAL for a message the decoder would reject. Array fields of a
 *     message may be given natively (.v) or as the little-endian view a decoder produced
 *     (.le), so a decoded message can be re-encoded unchanged (proxies, tests).
 *   Versions. The codec speaks versions SM_PROTO_VERSION_MIN..MAX (PROTOCOL.md §7). The
 *     header's version is the caller's: hdr->version, 0 meaning SM_PROTO_VERSION_HELLO
 *     (HELLO frames are always version 1; the encoders of HELLO refuse any other). Only
 *     the MATCH response's layout differs between versions, so only its encoder and
 *     decoder take the negotiated version as an argument; every other layout is the same
 *     in all versions the codec speaks. MATCH's request flags MULTIRES and DIRECT exist
 *     from version 3 on; the codec accepts them whatever the version, and the peer that
 *     knows the connection's version refuses them below 3 (the server: BAD_REQUEST).
 *   Errors: negative SM_PROTO_E* codes, sm_proto_strerror; sm_proto_status_for_error maps
 *   a parse/decode error to the status the peer should receive.
 */
#ifndef SM_PROTO_H
#define SM_PROTO_H

#include <stddef.h>
#include <stdint.h>

#define SM_PROTO_HEADER_LEN 24
#define SM_PROTO_VERSION_MIN 1
#define SM_PROTO_VERSION_MAX 3
#define SM_PROTO_VERSION_HELLO 1 /* the header version of every HELLO frame (both ways) */
#define SM_PROTO_VERSION_CONFIDENCE 2 /* first version whose MATCH response has confidence */
#define SM_PROTO_VERSION_MULTIRES 3   /* first version with MATCH's MULTIRES / DIRECT flags */
#define SM_PROTO_ID_LEN 32     /* shape id = SHA-256 of the Draco bytes */
#define SM_PROTO_MAGIC0 0x89
#define SM_PROTO_MAGIC1 'S'
#define SM_PROTO_MAGIC2 'M'
#define SM_PROTO_MAGIC3 'P'
#define SM_PROTO_HELLO_MAX_PAYLOAD 4096u /* limit on any frame before HELLO completes */
#define SM_PROTO_MAX_TOKEN 256u
#define SM_PROTO_MAX_MSG 1024u           /* error/goaway message bytes */
#define SM_PROTO_STAT_NAME_LEN 24

/* Parse/decode results. */
enum {
  SM_PROTO_OK = 0,
  SM_PROTO_PARTIAL = -1,    /* need more bytes (not an error) */
  SM_PROTO_EMAGIC = -2,     /* first 4 bytes are not 0x89 'S' 'M' 'P' */
  SM_PROTO_EHDRCRC = -3,    /* header CRC32C mismatch */
  SM_PROTO_EVERSION = -4,   /* version byte outside [VERSION_MIN, VERSION_MAX] */
  SM_PROTO_EFLAGS = -5,     /* a flag bit this version does not define */
  SM_PROTO_ERESERVED = -6,  /* reserved header field not zero */
  SM_PROTO_EHEADER = -7,    /* other header rule: opcode 0, status/MORE in a request,
                               request_id 0 in a request, CRC flag with payload_len < 4 */
  SM_PROTO_ETOOBIG = -8,    /* payload_len above the caller's limit */
  SM_PROTO_EPAYLOADCRC = -9,/* payload CRC32C trailer mismatch */
  SM_PROTO_ETRUNC = -10,    /* payload shorter than its fixed part */
  SM_PROTO_ELENGTH = -11,   /* counts disagree with the payload length (short or trailing) */
  SM_PROTO_EFIELD = -12,    /* enum out of range, unknown flag, reserved field not zero,
                               bad name/string */
  SM_PROTO_EOPCODE = -13,   /* opcode unknown, or not allowed here (direction, batch) */
  SM_PROTO_EINVAL = -14,    /* encoder: message cannot be encoded (bad argument) */
  SM_PROTO_ECONFIDENCE = -15 /* MATCH response: confidence NaN or outside [0, 1] */
};

/* Opcodes (header byte 5). 0 is invalid. */
enum sm_proto_op {
  SM_OP_HELLO = 1,
  SM_OP_PING = 2,
  SM_OP_STATS = 3,
  SM_OP_PUT_SHAPE = 4,
  SM_OP_HAS_SHAPE = 5,
  SM_OP_DROP_SHAPE = 6,
  SM_OP_PREPARE = 7,
  SM_OP_MATCH = 8,
  SM_OP_DISTANCE = 9,
  SM_OP_QUERY = 10,
  SM_OP_BATCH = 11,
  SM_OP_CANCEL = 12,
  SM_OP_GOAWAY = 13, /* server -> client only */
  SM_OP_MAX_ = 13
};

/* What each opcode is (PROTOCOL.md 3): one table, read by the codec, the server and the
 * clients, so that an opcode is described in one place.
 *   direction: SM_OPF_REQUEST (a client sends it, the server answers) or SM_OPF_SERVER
 *     (the server sends it unasked: GOAWAY);
 *   SM_OPF_QUEUED: the server runs it on a worker behind the job queue, so its answer may
 *     wait for other clients' computations; without it the loop thread answers at once;
 *   SM_OPF_BATCHABLE: it may be an item of a BATCH;
 *   SM_OPF_IDEMPOTENT: sending it again has the effect of sending it once and gets the same
 *     result (flags that say whether work was done, EXISTED and CACHED, and times may
 *     differ), so a client may resend it on a new connection when the one it was sent on
 *     was lost before the answer came (PROTOCOL.md 3, "Lost connections"). */
enum {
  SM_OPF_REQUEST = 1u << 0,
  SM_OPF_SERVER = 1u << 1,
  SM_OPF_QUEUED = 1u << 2,
  SM_OPF_BATCHABLE = 1u << 3,
  SM_OPF_IDEMPOTENT = 1u << 4
};
/* The flags of opcode; 0 for 0 and unknown opcodes. */
unsigned sm_proto_op_flags(uint8_t opcode);

/* Header flags (bytes 6..7). Every other bit must be 0. */
enum {
  SM_PROTO_F_RESPONSE = 1u << 0,
  SM_PROTO_F_PAYLOAD_CRC = 1u << 1,
  SM_PROTO_F_MORE = 1u << 2, /* responses only: more frames follow for this request */
  SM_PROTO_F_KNOWN_ = 0x7u
};

/* Status codes (header bytes 12..13). Bit 15 set = connection-fatal: the sender writes
 * this one frame (a GOAWAY) and closes. */
enum sm_proto_status {
  SM_ST_OK = 0,
  SM_ST_BAD_REQUEST = 1,
  SM_ST_UNKNOWN_OPCODE = 2,
  SM_ST_NOT_FOUND = 3,
  SM_ST_DECODE_FAILED = 4,
  SM_ST_MESH_REJECTED = 5,
  SM_ST_LIMIT_EXCEEDED = 6,
  SM_ST_ID_MISMATCH = 7,
  SM_ST_BUSY = 8,
  SM_ST_DEADLINE = 9,
  SM_ST_CANCELLED = 10,
  SM_ST_INTERNAL = 11,
  SM_ST_SHUTTING_DOWN = 12,
  SM_ST_RESPONSE_TOO_LARGE = 13,
  SM_ST_FATAL_ = 0x8000,
  SM_ST_BAD_MAGIC = 0x8001,
  SM_ST_UNSUPPORTED_VERSION = 0x8002,
  SM_ST_BAD_HEADER_CRC = 0x8003,
  SM_ST_BAD_HEADER = 0x8004,
  SM_ST_FRAME_TOO_LARGE = 0x8005,
  SM_ST_BAD_PAYLOAD_CRC = 0x8006,
  SM_ST_PROTOCOL_ERROR = 0x8007,
  SM_ST_UNAUTHORIZED = 0x8008,
  SM_ST_TIMEOUT = 0x8009,
  SM_ST_TOO_MANY_CONNECTIONS = 0x800A,
  SM_ST_OVERLOADED = 0x800B
};

static inline int sm_proto_status_is_fatal(uint16_t st) { return (st & SM_ST_FATAL_) != 0; }

typedef struct sm_proto_header {
  uint8_t version;
  uint8_t opcode;
  uint16_t flags;
  uint32_t request_id;
  uint16_t status;
  uint32_t payload_len; /* includes the 4-byte CRC trailer when F_PAYLOAD_CRC */
} sm_proto_header;

typedef struct sm_proto_frame {
  sm_proto_header h;
  const uint8_t *body; /* view into the caller's buffer: payload without CRC trailer */
  uint32_t body_len;
} sm_proto_frame;

/* ---- CRC32C (Castagnoli, reflected, poly 0x82F63B78) ---- */
/* Running form: crc = sm_proto_crc32c(0, a, na); crc = sm_proto_crc32c(crc, b, nb). */
uint32_t sm_proto_crc32c(uint32_t crc, const void *data, size_t len);

/* ---- parsing ---- */
/* Returns SM_PROTO_HEADER_LEN, SM_PROTO_PARTIAL or an error (see the contract). */
int sm_proto_parse_header(const uint8_t *buf, size_t len, uint32_t max_payload,
                          sm_proto_header *out);
/* Header + whole payload; verifies the payload CRC trailer when flagged. Returns the frame
 * size (24 + payload_len), SM_PROTO_PARTIAL or an error. */
ptrdiff_t sm_proto_parse_frame(const uint8_t *buf, size_t len, uint32_t max_payload,
                               sm_proto_frame *out);
/* For a caller that read the payload separately: checks/strips the trailer.
 * payload has h->payload_len bytes; *body_len receives the body length. */
int sm_proto_check_payload(const sm_proto_header *h, const uint8_t *payload,
                           uint32_t *body_len);
/* Writes a header (computes its CRC). Returns SM_PROTO_HEADER_LEN. */
int sm_proto_write_header(uint8_t out[SM_PROTO_HEADER_LEN], const sm_proto_header *h);

/* ---- array views ---- */
typedef struct sm_proto_i32s {
  const int32_t *v;  /* encode: native array (or NULL to use le) */
  const uint8_t *le; /* decode: count little-endian int32 inside the payload */
  uint32_t count;
} sm_proto_i32s;
typedef struct sm_proto_f64s {
  const double *v;   /* encode: native array (or NULL to use le) */
  const uint8_t *le; /* decode: count little-endian IEEE-754 binary64 */
  uint32_t count;
} sm_proto_f64s;
int32_t sm_proto_i32_at(const sm_proto_i32s *a, uint32_t i); /* i < count */
double sm_proto_f64_at(const sm_proto_f64s *a, uint32_t i);

/* ---- messages (field meanings and offsets: PROTOCOL.md) ---- */
typedef struct sm_proto_hello_req {
  uint16_t min_version, max_version;
  uint32_t max_response; /* largest response payload the client accepts; 0 = any */
  uint8_t affinity[SM_PROTO_ID_LEN]; /* routing key (a shape id) or zeros */
  const uint8_t *token;  /* token_len bytes, not NUL-terminated; may be NULL if 0 */
  uint16_t token_len;    /* <= SM_PROTO_MAX_TOKEN */
} sm_proto_hello_req;

enum { SM_HELLO_F_AUTH_REQUIRED = 1u << 0, SM_HELLO_F_KNOWN_ = 0x1u };
typedef struct sm_proto_hello_resp {
  uint16_t version; /* chosen */
  uint32_t max_payload, max_vertices, max_faces, max_inflight, max_batch_items,
      max_query_k, max_k, idle_timeout_ms, features;
} sm_proto_hello_resp;

typedef struct sm_proto_ping { uint64_t opaque; } sm_proto_ping; /* request and response */

typedef struct sm_proto_stat {
  char name[SM_PROTO_STAT_NAME_LEN + 1]; /* NUL-terminated, [a-z0-9_.], 1..24 chars */
  uint64_t value;
} sm_proto_stat;
typedef struct sm_proto_stats_resp {
  const sm_proto_stat *v; /* encode */
  const uint8_t *le;      /* decode: count 32-byte records */
  uint32_t count;
} sm_proto_stats_resp;
int sm_proto_stat_at(const sm_proto_stats_resp *s, uint32_t i, sm_proto_stat *out);

enum { SM_PUT_F_PREPARE = 1u << 0, SM_PUT_F_KNOWN_ = 0x1u };
typedef struct sm_proto_put_req {
  uint8_t id[SM_PROTO_ID_LEN];
  uint32_t flags;
  const uint8_t *draco; /* view / input */
  uint32_t draco_len;   /* >= 1 */
} sm_proto_put_req;
enum { SM_PUT_R_EXISTED = 1u << 0, SM_PUT_R_KNOWN_ = 0x1u };
typedef struct sm_proto_put_resp {
  uint8_t id[SM_PROTO_ID_LEN];
  uint32_t n_vertices, n_faces, flags;
} sm_proto_put_resp;

/* HAS_SHAPE, DROP_SHAPE requests */
typedef struct sm_proto_id_req { uint8_t id[SM_PROTO_ID_LEN]; } sm_proto_id_req;
enum { SM_HAS_STORED = 1u << 0, SM_HAS_PREPARED = 1u << 1, SM_HAS_KNOWN_ = 0x3u };
typedef struct sm_proto_has_resp { uint32_t flags, n_vertices, n_faces; } sm_proto_has_resp;

typedef struct sm_proto_prepare_req {
  uint8_t id[SM_PROTO_ID_LEN];
  uint16_t k_lb, k_elastic; /* 0 = server default */
  double eta;               /* 0 = default, else finite > 0 */
} sm_proto_prepare_req;
enum { SM_PREP_R_CACHED = 1u << 0, SM_PREP_R_KNOWN_ = 0x1u };
typedef struct sm_proto_prepare_resp {
  uint32_t n_vertices, n_faces;
  uint16_t k_lb, k_elastic;
  uint32_t flags;
  uint64_t t_clean_us, t_lb_us, t_elastic_us, t_desc_us;
} sm_proto_prepare_resp;

/* MATCH and DISTANCE requests share one layout. basis/init: 0 = server default, else the
 * values of core/sm_match.h (lb 1, elastic 2, hybrid 3; nn 1, sinkhorn 2). */
/* SINGLE_START / MULTI_START force multi-start off / on (neither: server default; both:
 * invalid). SINKHORN_LEVELS: sinkhorn_levels is given (0 = variant off); without it the
 * field must be 0 and the server default applies. MULTIRES / DIRECT (MATCH only, version
 * >= 3) force the multi-resolution path (core/sm_multires.h) or the direct one (neither:
 * the server default, automatic by size; both: invalid). */
enum {
  SM_MATCH_F_WANT_YX = 1u << 0,
  SM_MATCH_F_WANT_FMAP = 1u << 1,
  SM_MATCH_F_SINGLE_START = 1u << 2,
  SM_MATCH_F_WANT_DISTANCE = 1u << 3,
  SM_MATCH_F_MULTI_START = 1u << 4,
  SM_MATCH_F_SINKHORN_LEVELS = 1u << 5,
  SM_MATCH_F_MULTIRES = 1u << 6,
  SM_MATCH_F_DIRECT = 1u << 7,
  SM_MATCH_F_KNOWN_ = 0xFFu,
  SM_DISTANCE_F_KNOWN_ =
      SM_MATCH_F_SINGLE_START | SM_MATCH_F_MULTI_START | SM_MATCH_F_SINKHORN_LEVELS
};
typedef struct sm_proto_match_req {
  uint8_t x[SM_PROTO_ID_LEN], y[SM_PROTO_ID_LEN];
  uint8_t basis, init;
  uint16_t flags;
  uint16_t k0, k1, step;  /* 0 = default */
  uint16_t sinkhorn_levels; /* Sinkhorn refinement steps (CLI --refine-sinkhorn), see flags */
  double eta;             /* 0 = default, else finite > 0 */
  uint32_t deadline_ms;   /* 0 = none */
  sm_proto_i32s landmarks; /* 2 * n pairs (x, y), input vertex numbering; count even */
  sm_proto_i32s init_map;  /* empty, or one entry per input vertex of X */
} sm_proto_match_req;

typedef struct sm_proto_dist {
  double total, point_xy, point_yx, spectrum_lb, spectrum_elastic; /* elastic -1: absent */
} sm_proto_dist;

enum { SM_MATCH_R_FLIPPED = 1u << 0, SM_MATCH_R_HAS_DISTANCE = 1u << 1, SM_MATCH_R_KNOWN_ = 0x3u };
typedef struct sm_proto_match_resp {
  uint8_t init_used; /* 1 nn, 2 sinkhorn */
  uint8_t flags;
  double orientation, dirichlet;
  /* Version >= SM_PROTO_VERSION_CONFIDENCE: in [0, 1] (the encoder refuses anything else,
   * NaN included). Version 1 has no such field: its encoder ignores this one and its
   * decoder sets NaN. */
  double confidence;
  sm_proto_dist dist; /* zeros unless HAS_DISTANCE */
  uint64_t t_prepare_us, t_init_us, t_refine_us, t_distance_us, t_total_us;
  sm_proto_i32s map_xy; /* X input vertex -> Y input vertex or -1 */
  sm_proto_i32s map_yx; /* empty unless requested */
  uint16_t kC;          /* functional map dimension, 0 unless requested */
  sm_proto_f64s fmap;   /* kC * kC, column-major */
} sm_proto_match_resp;

typedef struct sm_proto_distance_resp {
  sm_proto_dist dist;
  uint64_t t_total_us;
} sm_proto_distance_resp;

enum { SM_QUERY_DEFAULT = 0, SM_QUERY_SPECTRAL = 1, SM_QUERY_FULL = 2 };
typedef struct sm_proto_query_req {
  uint8_t id[SM_PROTO_ID_LEN];
  uint16_t k;     /* >= 1 */
  uint8_t mode;   /* SM_QUERY_* */
  uint32_t deadline_ms;
  const uint8_t *candidates; /* n_candidates * 32 bytes of ids; 0 = every stored shape */
  uint32_t n_candidates;
} sm_proto_query_req;
typedef struct sm_proto_hit {
  uint8_t id[SM_PROTO_ID_LEN];
  double distance;
} sm_proto_hit;
typedef struct sm_proto_query_resp {
  uint32_t n_considered;
  uint64_t t_total_us;
  const sm_proto_hit *v; /* encode */
  const uint8_t *le;     /* decode: count 40-byte records, ascending distance */
  uint32_t count;
} sm_proto_query_resp;
void sm_proto_hit_at(const sm_proto_query_resp *q, uint32_t i, sm_proto_hit *out);

typedef struct sm_proto_batch_item {
  uint8_t opcode; /* PING, HAS_SHAPE, PREPARE, MATCH, DISTANCE, QUERY */
  const uint8_t *payload;
  uint32_t len;
} sm_proto_batch_item;
typedef struct sm_proto_batch_req {
  const sm_proto_batch_item *v; /* encode */
  const uint8_t *le;            /* decode: the item region, validated */
  uint32_t le_len;
  uint32_t count;
} sm_proto_batch_req;
/* Iterates a decoded (or natively given) batch: *pos starts at 0; returns 1 with *it
 * filled, 0 at the end. */
int sm_proto_batch_next(const sm_proto_batch_req *b, size_t *pos, sm_proto_batch_item *it);
/* One frame per item (flags MORE, status = the item's status). */
typedef struct sm_proto_batch_item_resp {
  uint32_t index;
  uint8_t opcode;
  const uint8_t *payload; /* the item's response payload, or an error payload */
  uint32_t len;
} sm_proto_batch_item_resp;
/* The final frame (no MORE, status OK). */
typedef struct sm_proto_batch_done { uint32_t n_items, n_ok; } sm_proto_batch_done;

typedef struct sm_proto_cancel_req { uint32_t target; } sm_proto_cancel_req;

/* Payload of every response whose status is not OK, and of GOAWAY. */
typedef struct sm_proto_error {
  uint32_t retry_after_ms; /* BUSY, GOAWAY: suggested wait; else 0 */
  uint32_t detail;         /* status-specific, PROTOCOL.md */
  const char *msg;         /* UTF-8, not NUL-terminated */
  uint32_t msg_len;        /* <= SM_PROTO_MAX_MSG */
} sm_proto_error;

/* ---- decoders: body/len is a frame body; 0 or SM_PROTO_E* ---- */
int sm_proto_dec_hello_req(const uint8_t *p, size_t n, sm_proto_hello_req *m);
int sm_proto_dec_hello_resp(const uint8_t *p, size_t n, sm_proto_hello_resp *m);
int sm_proto_dec_ping(const uint8_t *p, size_t n, sm_proto_ping *m);
int sm_proto_dec_empty(const uint8_t *p, size_t n); /* STATS req, DROP/CANCEL resp */
int sm_proto_dec_stats_resp(const uint8_t *p, size_t n, sm_proto_stats_resp *m);
int sm_proto_dec_put_req(const uint8_t *p, size_t n, sm_proto_put_req *m);
int sm_proto_dec_put_resp(const uint8_t *p, size_t n, sm_proto_put_resp *m);
int sm_proto_dec_id_req(const uint8_t *p, size_t n, sm_proto_id_req *m);
int sm_proto_dec_has_resp(const uint8_t *p, size_t n, sm_proto_has_resp *m);
int sm_proto_dec_prepare_req(const uint8_t *p, size_t n, sm_proto_prepare_req *m);
int sm_proto_dec_prepare_resp(const uint8_t *p, size_t n, sm_proto_prepare_resp *m);
/* opcode: SM_OP_MATCH or SM_OP_DISTANCE (decides which flags are allowed). */
int sm_proto_dec_match_req(uint8_t opcode, const uint8_t *p, size_t n, sm_proto_match_req *m);
/* version: the connection's negotiated version (the layout differs, PROTOCOL.md §5.7);
 * one the codec does not speak is SM_PROTO_EVERSION. A bad confidence is
 * SM_PROTO_ECONFIDENCE (request-level, like EFIELD). */
int sm_proto_dec_match_resp(uint8_t version, const uint8_t *p, size_t n,
                            sm_proto_match_resp *m);
int sm_proto_dec_distance_resp(const uint8_t *p, size_t n, sm_proto_distance_resp *m);
int sm_proto_dec_query_req(const uint8_t *p, size_t n, sm_proto_query_req *m);
int sm_proto_dec_query_resp(const uint8_t *p, size_t n, sm_proto_query_resp *m);
int sm_proto_dec_batch_req(const uint8_t *p, size_t n, sm_proto_batch_req *m);
int sm_proto_dec_batch_item_resp(const uint8_t *p, size_t n, sm_proto_batch_item_resp *m);
int sm_proto_dec_batch_done(const uint8_t *p, size_t n, sm_proto_batch_done *m);
int sm_proto_dec_cancel_req(const uint8_t *p, size_t n, sm_proto_cancel_req *m);
int sm_proto_dec_error(const uint8_t *p, size_t n, sm_proto_error *m);

/* ---- encoders: see the contract; hdr may be NULL (payload only) ---- */
ptrdiff_t sm_proto_enc_hello_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                 const sm_proto_hello_req *m);
ptrdiff_t sm_proto_enc_hello_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_hello_resp *m);
/* PING request (response = 0) or response (response = 1). */
ptrdiff_t sm_proto_enc_ping(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                            int response, const sm_proto_ping *m);
/* Empty payload: STATS request, DROP_SHAPE / CANCEL responses. opcode and RESPONSE flag
 * are taken from *hdr. */
ptrdiff_t sm_proto_enc_empty(uint8_t *buf, size_t cap, const sm_proto_header *hdr);
ptrdiff_t sm_proto_enc_stats_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_stats_resp *m);
ptrdiff_t sm_proto_enc_put_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                               const sm_proto_put_req *m);
ptrdiff_t sm_proto_enc_put_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                const sm_proto_put_resp *m);
/* HAS_SHAPE or DROP_SHAPE request: opcode is one of them. */
ptrdiff_t sm_proto_enc_id_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                              uint8_t opcode, const sm_proto_id_req *m);
ptrdiff_t sm_proto_enc_has_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                const sm_proto_has_resp *m);
ptrdiff_t sm_proto_enc_prepare_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                   const sm_proto_prepare_req *m);
ptrdiff_t sm_proto_enc_prepare_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                    const sm_proto_prepare_resp *m);
/* opcode: SM_OP_MATCH or SM_OP_DISTANCE. */
ptrdiff_t sm_proto_enc_match_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                 uint8_t opcode, const sm_proto_match_req *m);
/* version: the layout to write; with hdr, also the frame's version (hdr->version must be
 * 0 or equal to it). */
ptrdiff_t sm_proto_enc_match_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  uint8_t version, const sm_proto_match_resp *m);
ptrdiff_t sm_proto_enc_distance_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                     const sm_proto_distance_resp *m);
ptrdiff_t sm_proto_enc_query_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                 const sm_proto_query_req *m);
ptrdiff_t sm_proto_enc_query_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_query_resp *m);
ptrdiff_t sm_proto_enc_batch_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                 const sm_proto_batch_req *m);
/* Sets F_MORE itself. */
ptrdiff_t sm_proto_enc_batch_item_resp(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                       const sm_proto_batch_item_resp *m);
ptrdiff_t sm_proto_enc_batch_done(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_batch_done *m);
ptrdiff_t sm_proto_enc_cancel_req(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                                  const sm_proto_cancel_req *m);
/* Error response to hdr->opcode (hdr->status must be non-zero), or GOAWAY when
 * hdr->opcode is SM_OP_GOAWAY (any status; request_id 0 or the offending request). */
ptrdiff_t sm_proto_enc_error(uint8_t *buf, size_t cap, const sm_proto_header *hdr,
                             const sm_proto_error *m);

const char *sm_proto_strerror(int err);
const char *sm_proto_status_name(uint16_t status);
const char *sm_proto_op_name(uint8_t opcode);
/* The status a receiver sends back for a parse/decode error (fatal for header errors). */
uint16_t sm_proto_status_for_error(int err);

#endif
