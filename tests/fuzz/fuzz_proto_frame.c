/* fuzz_proto_frame: the frame parser (sm_proto_parse_frame / _parse_header) fed one byte
 * stream in chunks whose sizes come from the input itself.
 *
 * Input: byte 0 = mode, byte 1 = k, then the stream, then k chunk-size bytes at the end.
 *   mode bit 0: repair each frame's header CRC (and payload CRC trailer) before parsing,
 *               so mutations get past the CRC to the later header and payload rules;
 *   mode bit 1: also write the magic of each frame;
 *   mode bits 2-3: the receiver's max_payload (HELLO limit, 64, 1 MiB, UINT32_MAX).
 *   k = byte 1 % 33 chunk sizes, each 1 + byte (1..256), used cyclically; k = 0 feeds
 *   the stream 7 bytes at a time.
 * Properties (sm_proto.h: the parser is stateless, "any split of the stream gives the same
 * frames"): a receiver that appends each chunk and parses until PARTIAL sees exactly the
 * frames, and the same final error or leftover, as one pass over the whole stream; every
 * frame is 24 + payload_len bytes with its body inside it; parse_header agrees with
 * parse_frame; write_header reproduces the header bytes of a parsed frame.
 */
#include "sm_fuzz.h"
#include "sm_proto.h"

#define MAX_STREAM (16u << 10) /* the chunked pass re-parses its buffer: keep it quadratic-safe */
#define MAX_FRAMES 4096

typedef struct outcome {
  uint32_t n_frames;
  uint32_t sizes[MAX_FRAMES]; /* frame sizes, in order */
  uint32_t crcs[MAX_FRAMES];  /* CRC32C of each frame's body: same bytes, not just length */
  int final;                  /* error code, or SM_PROTO_PARTIAL */
  size_t leftover;            /* bytes not consumed when the stream ended */
} outcome;

static uint32_t ld32(const uint8_t *p) {
  return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

static void st32(uint8_t *p, uint32_t v) {
  for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}

/* Makes each frame's magic / CRCs right, walking the stream as a receiver would. */
static void repair(uint8_t *s, size_t len, int magic) {
  size_t off = 0;
  while (len - off >= SM_PROTO_HEADER_LEN) {
    uint8_t *h = s + off;
    if (magic) memcpy(h, "\x89SMP", 4);
    st32(h + 20, sm_proto_crc32c(0, h, 20));
    uint32_t pl = ld32(h + 16);
    if ((size_t)pl > len - off - SM_PROTO_HEADER_LEN) return;
    if ((h[6] & SM_PROTO_F_PAYLOAD_CRC) && pl >= 4)
      st32(h + SM_PROTO_HEADER_LEN + pl - 4, sm_proto_crc32c(0, h + SM_PROTO_HEADER_LEN, pl - 4));
    off += SM_PROTO_HEADER_LEN + (size_t)pl;
  }
}

/* One parse of buf[0..len) in an exact-size copy; checks the per-frame properties. */
static ptrdiff_t parse_one(const uint8_t *buf, size_t len, uint32_t maxp, uint32_t *crc) {
  uint8_t *c = sm_fuzz_dup(buf, len);
  sm_proto_frame f;
  sm_proto_header h;
  ptrdiff_t r = sm_proto_parse_frame(c, len, maxp, &f);
  int rh = sm_proto_parse_header(c, len, maxp, &h);
  if (r > 0) {
    SM_FUZZ_CHECK(rh == SM_PROTO_HEADER_LEN);
    SM_FUZZ_CHECK((size_t)r <= len && r == SM_PROTO_HEADER_LEN + (ptrdiff_t)f.h.payload_len);
    SM_FUZZ_CHECK(f.body == c + SM_PROTO_HEADER_LEN && f.body_len <= f.h.payload_len);
    SM_FUZZ_CHECK(h.version == f.h.version && h.opcode == f.h.opcode && h.flags == f.h.flags &&
                  h.request_id == f.h.request_id && h.status == f.h.status &&
                  h.payload_len == f.h.payload_len);
    uint8_t w[SM_PROTO_HEADER_LEN];
    SM_FUZZ_CHECK(sm_proto_write_header(w, &f.h) == SM_PROTO_HEADER_LEN);
    SM_FUZZ_CHECK(memcmp(w, c, SM_PROTO_HEADER_LEN) == 0);
    *crc = sm_proto_crc32c(0, f.body, f.body_len);
  } else {
    /* a header error is the frame's error; PARTIAL may be the payload's turn */
    SM_FUZZ_CHECK(rh == r || (rh == SM_PROTO_HEADER_LEN && r == SM_PROTO_PARTIAL) ||
                  (rh == SM_PROTO_HEADER_LEN && r == SM_PROTO_EPAYLOADCRC));
    (void)sm_proto_strerror((int)r);
    (void)sm_proto_status_for_error((int)r);
  }
  free(c);
  return r;
}

/* Parses what buf holds; returns bytes consumed; sets *stop on an error. */
static size_t drain(const uint8_t *buf, size_t len, uint32_t maxp, outcome *o, int *stop) {
  size_t off = 0;
  for (;;) {
    uint32_t crc = 0;
    ptrdiff_t r = parse_one(buf + off, len - off, maxp, &crc);
    if (r == SM_PROTO_PARTIAL) return off;
    if (r < 0) {
      o->final = (int)r;
      *stop = 1;
      return off;
    }
    if (o->n_frames < MAX_FRAMES) {
      o->sizes[o->n_frames] = (uint32_t)r;
      o->crcs[o->n_frames] = crc;
    }
    o->n_frames++;
    off += (size_t)r;
  }
}

static void whole(const uint8_t *s, size_t len, uint32_t maxp, outcome *o) {
  int stop = 0;
  o->final = SM_PROTO_PARTIAL;
  size_t used = drain(s, len, maxp, o, &stop);
  o->leftover = len - used;
}

static void chunked(const uint8_t *s, size_t len, const uint8_t *ks, size_t k, uint32_t maxp,
                    outcome *o) {
  uint8_t *rb = malloc(len ? len : 1); /* a receiver buffer: never holds more than the stream */
  SM_FUZZ_CHECK(rb != NULL);
  size_t rlen = 0, fed = 0, ki = 0;
  int stop = 0;
  o->final = SM_PROTO_PARTIAL;
  while (fed < len && !stop) {
    size_t n = k ? 1 + (size_t)ks[ki++ % k] : 7;
    if (n > len - fed) n = len - fed;
    memcpy(rb + rlen, s + fed, n);
    rlen += n;
    fed += n;
    size_t used = drain(rb, rlen, maxp, o, &stop);
    memmove(rb, rb + used, rlen - used);
    rlen -= used;
  }
  o->leftover = rlen + (len - fed);
  free(rb);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  static const uint32_t maxps[4] = {SM_PROTO_HELLO_MAX_PAYLOAD, 64, 1u << 20, UINT32_MAX};
  uint8_t mode = sm_fuzz_take(&data, &size);
  size_t k = sm_fuzz_take(&data, &size) % 33;
  if (k > size) k = size;
  const uint8_t *ks = data + size - k;
  size_t len = size - k;
  if (len > MAX_STREAM) len = MAX_STREAM;
  uint8_t *s = sm_fuzz_dup(data, len);
  if (mode & 1) repair(s, len, mode & 2);
  uint32_t maxp = maxps[(mode >> 2) & 3];

  static outcome a, b; /* big: not on the stack */
  memset(&a, 0, sizeof a);
  memset(&b, 0, sizeof b);
  whole(s, len, maxp, &a);
  chunked(s, len, ks, k, maxp, &b);
  SM_FUZZ_CHECK(a.n_frames == b.n_frames);
  uint32_t n = a.n_frames < MAX_FRAMES ? a.n_frames : MAX_FRAMES;
  SM_FUZZ_CHECK(memcmp(a.sizes, b.sizes, n * sizeof a.sizes[0]) == 0);
  SM_FUZZ_CHECK(memcmp(a.crcs, b.crcs, n * sizeof a.crcs[0]) == 0);
  SM_FUZZ_CHECK(a.final == b.final);
  SM_FUZZ_CHECK(a.final != SM_PROTO_PARTIAL || a.leftover == b.leftover);
  free(s);
  return 0;
}
