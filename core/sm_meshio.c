/* sm_meshio: file reading, gzip, format dispatch and the plain-C parsers.
 *
 * DESIGN
 *   A file is read whole into memory (gunzipped in memory if it ends in ".gz") with a NUL
 *   after the last byte, so the text parsers can use strtod/strtoll without running off
 *   the end.
 *
 *   OFF, OBJ and ASCII PLY are parsed here, not by OpenMesh: OpenMesh's text parsers round
 *   coordinates to float32 (measured on homerA.obj), and its halfedge mesh refuses
 *   non-manifold faces. Binary PLY with float32 coordinates and STL (float32 by definition)
 *   go to OpenMesh first (io/sm_openmesh_io.cpp); when its vertex or face count differs
 *   from what the file declares, the file is parsed again here.
 *
 *   Each parser runs twice over the buffer: a first pass only counts (and finds syntax
 *   errors), so the counts are checked against the limits before anything is allocated;
 *   the second pass fills the mesh.
 *
 *   Face indices that fit in int32 are returned as the file gives them even when out of
 *   range: sm_mesh_validate reports those, naming the face. Indices that cannot be stored,
 *   polygons with fewer than 3 corners and OBJ index 0 are format errors here.
 */
#include "sm_meshio.h"

#include <ctype.h>
#include <errno.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <zlib.h>

/* Largest file or decompressed content accepted by sm_mesh_read_file. */
#define SM_IO_MAX_BYTES ((size_t)2 << 30)

/* ------------------------------------------------------------------------------------ */
/* Whole-file reading and gzip                                                          */

static int grow(uint8_t **buf, size_t *cap, size_t need, size_t max_bytes, const char *what,
                sm_error *err) {
  if (need <= *cap) return 0;
  size_t ncap = *cap ? *cap : 1 << 16;
  while (ncap < need) ncap = ncap > SIZE_MAX / 2 ? SIZE_MAX : 2 * ncap;
  if (ncap > max_bytes + 1) ncap = max_bytes + 1;
  uint8_t *nb = realloc(*buf, ncap + 1); /* +1: room for the terminating NUL */
  if (!nb) return sm_error_set(err, SM_ENOMEM, "%s: cannot allocate %zu bytes", what, ncap);
  *buf = nb;
  *cap = ncap;
  return 0;
}

int sm_read_file_bytes(const char *path, size_t max_bytes, uint8_t **buf, size_t *len,
                       sm_error *err) {
  if (!path || !buf || !len) return sm_error_set(err, SM_EINVAL, "sm_read_file_bytes: null argument");
  *buf = NULL;
  *len = 0;
  FILE *f = fopen(path, "rb");
  if (!f) {
    char why[128];
    if (strerror_r(errno, why, sizeof why)) snprintf(why, sizeof why, "errno %d", errno);
    return sm_error_set(err, SM_EIO, "cannot open %s: %s", path, why);
  }
  uint8_t *b = NULL;
  size_t cap = 0, n = 0;
  int rc = 0;
  for (;;) {
    if ((rc = grow(&b, &cap, n + 1, max_bytes, path, err))) break;
    size_t got = fread(b + n, 1, cap - n, f);
    n += got;
    if (n > max_bytes) {
      rc = sm_error_set(err, SM_ELIMIT, "%s is larger than the limit of %zu bytes", path, max_bytes);
      break;
    }
    if (got == 0) {
      if (ferror(f)) rc = sm_error_set(err, SM_EIO, "read error in %s", path);
      break;
    }
  }
  fclose(f);
  if (rc) {
    free(b);
    return rc;
  }
  if (!b && (rc = grow(&b, &cap, 1, max_bytes, path, err))) return rc;
  b[n] = 0;
  *buf = b;
  *len = n;
  return 0;
}

/* Inflates gzip data (several concatenated members allowed, as gzip itself does). */
static int gunzip(const char *name, const uint8_t *in, size_t inlen, size_t max_bytes,
                  uint8_t **out, size_t *outlen, sm_error *err) {
  z_stream zs;
  memset(&zs, 0, sizeof zs);
  if (inflateInit2(&zs, 16 + MAX_WBITS) != Z_OK)
    return sm_error_set(err, SM_ENOMEM, "%s: cannot initialise zlib", name);
  uint8_t *b = NULL;
  size_t cap = 0, n = 0, used = 0;
  int rc = 0, zr = Z_OK;
  while (!rc) {
    if ((rc = grow(&b, &cap, n + 1, max_bytes, name, err))) break;
    if (zs.avail_in == 0 && used < inlen) {
      size_t chunk = inlen - used > (1u << 30) ? (1u << 30) : inlen - used;
      zs.next_in = (Bytef *)(uintptr_t)(in + used);
      zs.avail_in = (uInt)chunk;
      used += chunk;
    }
    size_t room = cap - n > (1u << 30) ? (1u << 30) : cap - n;
    zs.next_out = b + n;
    zs.avail_out = (uInt)room;
    zr = inflate(&zs, Z_NO_FLUSH);
    n += room - zs.avail_out;
    if (n > max_bytes) {
      rc = sm_error_set(err, SM_ELIMIT, "%s: decompresses to more than %zu bytes", name, max_bytes);
    } else if (zr == Z_STREAM_END) {
      size_t left = zs.avail_in + (inlen - used);
      const uint8_t *next = zs.next_in;
      if (left < 2 || (zs.avail_in >= 2 && (next[0] != 0x1f || next[1] != 0x8b))) break;
      if (inflateReset(&zs) != Z_OK) rc = sm_error_set(err, SM_EFORMAT, "%s: zlib reset failed", name);
    } else if (zr == Z_BUF_ERROR && zs.avail_in == 0 && used == inlen) {
      rc = sm_error_set(err, SM_EFORMAT, "%s: gzip data is truncated", name);
    } else if (zr != Z_OK && zr != Z_BUF_ERROR) {
      rc = sm_error_set(err, zr == Z_MEM_ERROR ? SM_ENOMEM : SM_EFORMAT, "%s: corrupt gzip data: %s",
                        name, zs.msg ? zs.msg : "unknown zlib error");
    }
  }
  inflateEnd(&zs);
  if (rc) {
    free(b);
    return rc;
  }
  b[n] = 0;
  *out = b;
  *outlen = n;
  return 0;
}

/* ------------------------------------------------------------------------------------ */
/* Text cursor shared by the text parsers                                               */

typedef struct tcur {
  const char *p, *end; /* *end is a NUL */
  const char *name;    /* file name for messages */
  long line;           /* 1-based line of p */
} tcur;

static int is_blank(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f'; }

static void skip_blanks(tcur *c) {
  while (c->p < c->end && is_blank(*c->p)) c->p++;
}

/* True at a line end, the buffer end or a comment. */
static int at_eol(tcur *c) {
  skip_blanks(c);
  return c->p >= c->end || *c->p == '\n' || *c->p == '#';
}

static void next_line(tcur *c) {
  while (c->p < c->end && *c->p != '\n') c->p++;
  if (c->p < c->end) {
    c->p++;
    c->line++;
  }
}

/* Skips blank and comment lines; returns 0 at the end of the buffer. */
static int next_content_line(tcur *c) {
  for (;;) {
    if (c->p >= c->end) return 0;
    if (!at_eol(c)) return 1;
    next_line(c);
  }
}

/* A number must end at a blank, a line end, a comment or (OBJ) a slash. */
static int ends_token(const tcur *c, const char *q) {
  return q >= c->end || is_blank(*q) || *q == '\n' || *q == '#' || *q == '/';
}

static int read_double(tcur *c, double *x) {
  if (at_eol(c)) return -2;
  char *q;
  *x = strtod(c->p, &q);
  if (q == c->p || !ends_token(c, q)) return -1;
  c->p = q;
  return 0;
}

static int read_long(tcur *c, long long *x) {
  if (at_eol(c)) return -2;
  char *q;
  errno = 0;
  *x = strtoll(c->p, &q, 10);
  if (q == c->p || !ends_token(c, q) || errno == ERANGE) return -1;
  c->p = q;
  return 0;
}

static int syntax_error(tcur *c, sm_error *err, const char *what) {
  return sm_error_set(err, SM_EFORMAT, "%s line %ld: %s", c->name, c->line, what);
}

/* Reads x y z; the rest of the line (w, colours, normals) is ignored. */
static int read_xyz(tcur *c, double *xyz, sm_error *err) {
  for (int k = 0; k < 3; k++)
    if (read_double(c, &xyz[k])) return syntax_error(c, err, "expected 3 coordinates");
  return 0;
}

/* Counting pass (m == NULL) or filling pass: emits the fan of one polygon. */
typedef struct fan {
  sm_mesh *m;  /* NULL while counting */
  int64_t ntri; /* triangles emitted so far */
  int32_t first, prev;
  int k; /* corners seen in the current polygon */
} fan;

static void fan_begin(fan *f) { f->k = 0; }

static void fan_add(fan *f, int32_t v) {
  if (f->k == 0) f->first = v;
  else if (f->k >= 2) {
    if (f->m) {
      int32_t *t = f->m->F + 3 * f->ntri;
      t[0] = f->first;
      t[1] = f->prev;
      t[2] = v;
    }
    f->ntri++;
  }
  f->prev = v;
  f->k++;
}

/* Puts the file name in front of a message set by a function that does not know it. */
static int prefix_error(sm_error *err, int rc, const char *name) {
  if (err) {
    char msg[sizeof err->msg];
    snprintf(msg, sizeof msg, "%.200s", err->msg);
    sm_error_set(err, rc, "%s: %s", name, msg);
  }
  return rc;
}

static int alloc_counted(const char *name, int64_t nv, int64_t nt, const sm_limits *lim,
                         sm_mesh **m, sm_error *err) {
  int rc = sm_limits_check(lim, nv, nt, err);
  if (rc) return prefix_error(err, rc, name);
  return sm_mesh_alloc(nv, nt, lim, m, err);
}

/* ------------------------------------------------------------------------------------ */
/* OFF                                                                                  */

/* Accepts [ST][C][N]OFF; the optional parts only add per-vertex data after x y z. */
static int off_keyword(tcur *c) {
  const char *w = c->p;
  while (c->p < c->end && isalpha((unsigned char)*c->p)) c->p++;
  size_t n = (size_t)(c->p - w);
  if (n < 3 || strncmp(c->p - 3, "OFF", 3) != 0) return -1;
  for (const char *q = w; q < c->p - 3; q++)
    if (!strchr("STCN", *q)) return -1;
  return 0;
}

static int off_header(tcur *c, long long *nv, long long *nf, sm_error *err) {
  if (!next_content_line(c) || off_keyword(c))
    return sm_error_set(err, SM_EFORMAT, "%s: not an OFF file (no OFF keyword)", c->name);
  if (at_eol(c)) {
    next_line(c);
    if (!next_content_line(c)) return syntax_error(c, err, "missing vertex and face counts");
  }
  if (read_long(c, nv) || read_long(c, nf) || *nv < 0 || *nf < 0)
    return syntax_error(c, err, "expected vertex and face counts");
  next_line(c);
  return 0;
}

static int off_face(tcur *c, fan *fn, long long nf_seen, sm_error *err) {
  long long n, idx;
  if (read_long(c, &n) || n < 3) {
    char what[96];
    snprintf(what, sizeof what, "face %lld: expected a corner count of at least 3", nf_seen);
    return syntax_error(c, err, what);
  }
  fan_begin(fn);
  for (long long k = 0; k < n; k++) {
    if (read_long(c, &idx)) return syntax_error(c, err, "face has fewer indices than its count");
    if (idx < INT32_MIN || idx > INT32_MAX) return syntax_error(c, err, "face index does not fit 32 bits");
    fan_add(fn, (int32_t)idx);
  }
  return 0;
}

static int off_pass(tcur *c, long long nv, long long nf, fan *fn, sm_error *err) {
  for (long long v = 0; v < nv; v++) {
    double xyz[3];
    if (!next_content_line(c))
      return sm_error_set(err, SM_EFORMAT, "%s: file ends after %lld of %lld vertices", c->name, v, nv);
    int rc = read_xyz(c, xyz, err);
    if (rc) return rc;
    if (fn->m) memcpy(fn->m->V + 3 * v, xyz, sizeof xyz);
    next_line(c);
  }
  for (long long f = 0; f < nf; f++) {
    if (!next_content_line(c))
      return sm_error_set(err, SM_EFORMAT, "%s: file ends after %lld of %lld faces", c->name, f, nf);
    int rc = off_face(c, fn, f, err);
    if (rc) return rc;
    next_line(c);
  }
  return 0;
}

static int read_off(const char *name, const char *buf, size_t len, const sm_limits *lim,
                    sm_mesh **out, sm_error *err) {
  tcur c0 = {buf, buf + len, name, 1}, c;
  long long nv, nf;
  int rc = off_header(&c0, &nv, &nf, err);
  if (rc) return rc;
  if ((rc = sm_limits_check(lim, nv, nf, err))) return rc;
  fan count = {0};
  c = c0;
  if ((rc = off_pass(&c, nv, nf, &count, err))) return rc;
  fan fill = {0};
  if ((rc = alloc_counted(name, nv, count.ntri, lim, &fill.m, err))) return rc;
  c = c0;
  if ((rc = off_pass(&c, nv, nf, &fill, err))) {
    sm_mesh_destroy(fill.m);
    return rc;
  }
  *out = fill.m;
  return 0;
}

/* ------------------------------------------------------------------------------------ */
/* OBJ                                                                                  */

/* One corner "v", "v/vt", "v//vn" or "v/vt/vn"; only v matters. Negative = relative. */
static int obj_corner(tcur *c, long long nv_sofar, int32_t *v, sm_error *err) {
  long long i;
  if (read_long(c, &i)) return syntax_error(c, err, "bad face corner");
  while (c->p < c->end && !is_blank(*c->p) && *c->p != '\n' && *c->p != '#') c->p++;
  if (i == 0) return syntax_error(c, err, "face refers to vertex 0 (OBJ indices start at 1)");
  if (i < 0) {
    i += nv_sofar;
    if (i < 0) return syntax_error(c, err, "relative face index points before the first vertex");
  } else {
    i -= 1;
  }
  if (i > INT32_MAX) return syntax_error(c, err, "face index does not fit 32 bits");
  *v = (int32_t)i;
  return 0;
}

static int obj_face(tcur *c, long long nv_sofar, fan *fn, sm_error *err) {
  fan_begin(fn);
  while (!at_eol(c)) {
    int32_t v = 0;
    int rc = obj_corner(c, nv_sofar, &v, err);
    if (rc) return rc;
    fan_add(fn, v);
  }
  if (fn->k < 3) return syntax_error(c, err, "face has fewer than 3 corners");
  return 0;
}

static int word_is(const tcur *c, const char *w) {
  size_t n = strlen(w);
  return (size_t)(c->end - c->p) >= n && memcmp(c->p, w, n) == 0 &&
         (c->p + n >= c->end || is_blank(c->p[n]) || c->p[n] == '\n');
}

static int obj_pass(tcur *c, long long *nv, fan *fn, sm_error *err) {
  *nv = 0;
  while (next_content_line(c)) {
    int rc = 0;
    if (word_is(c, "v")) {
      double xyz[3];
      c->p += 1;
      if (!(rc = read_xyz(c, xyz, err)) && fn->m) memcpy(fn->m->V + 3 * *nv, xyz, sizeof xyz);
      (*nv)++;
    } else if (word_is(c, "f")) {
      c->p += 1;
      rc = obj_face(c, *nv, fn, err);
    } else if (!isalpha((unsigned char)*c->p)) {
      /* Every OBJ statement starts with a letter; anything else means this is not OBJ. */
      rc = syntax_error(c, err, "not an OBJ statement");
    }
    if (rc) return rc;
    next_line(c);
  }
  return 0;
}

static int read_obj(const char *name, const char *buf, size_t len, const sm_limits *lim,
                    sm_mesh **out, sm_error *err) {
  tcur c = {buf, buf + len, name, 1};
  long long nv;
  fan count = {0};
  int rc = obj_pass(&c, &nv, &count, err);
  if (rc) return rc;
  fan fill = {0};
  if ((rc = alloc_counted(name, nv, count.ntri, lim, &fill.m, err))) return rc;
  c = (tcur){buf, buf + len, name, 1};
  if ((rc = obj_pass(&c, &nv, &fill, err))) {
    sm_mesh_destroy(fill.m);
    return rc;
  }
  *out = fill.m;
  return 0;
}

/* ------------------------------------------------------------------------------------ */
/* PLY (ascii, binary little and big endian)                                            */

enum { PLY_ASCII, PLY_BLE, PLY_BBE };
enum { PT_NONE, PT_I8, PT_U8, PT_I16, PT_U16, PT_I32, PT_U32, PT_F32, PT_F64 };
enum { ROLE_SKIP, ROLE_X, ROLE_Y, ROLE_Z, ROLE_FACE };
#define PLY_MAX_ELEMS 16
#define PLY_MAX_PROPS 64

typedef struct ply_prop {
  int type;      /* value type (item type for a list) */
  int list_type; /* PT_NONE unless a list: the type of its count */
  int role;
} ply_prop;

typedef struct ply_elem {
  int is_vertex, is_face;
  long long count;
  int nprops;
  ply_prop props[PLY_MAX_PROPS];
} ply_elem;

typedef struct ply_header {
  int format;
  int nelems;
  ply_elem elems[PLY_MAX_ELEMS];
  long long nv, nf;
  int seen_vertex;
  int xyz_float32; /* x, y, z all float32: OpenMesh reads them exactly */
  int plain;       /* OpenMesh tokenizes this header as we do (ply_header_is_plain) */
  size_t body;     /* offset of the first byte after end_header */
} ply_header;

static int ply_type(const char *w, size_t n) {
  static const struct { const char *name; int type; } t[] = {
      {"char", PT_I8},    {"int8", PT_I8},     {"uchar", PT_U8},   {"uint8", PT_U8},
      {"short", PT_I16},  {"int16", PT_I16},   {"ushort", PT_U16}, {"uint16", PT_U16},
      {"int", PT_I32},    {"int32", PT_I32},   {"uint", PT_U32},   {"uint32", PT_U32},
      {"float", PT_F32},  {"float32", PT_F32}, {"double", PT_F64}, {"float64", PT_F64}};
  for (size_t i = 0; i < sizeof t / sizeof t[0]; i++)
    if (strlen(t[i].name) == n && memcmp(t[i].name, w, n) == 0) return t[i].type;
  return PT_NONE;
}

static size_t ply_size(int type) {
  static const size_t s[] = {0, 1, 1, 2, 2, 4, 4, 4, 8};
  return s[type];
}

/* Next blank-separated word on the current line (empty at the line end). */
static size_t header_word(tcur *c, const char **w) {
  skip_blanks(c);
  *w = c->p;
  while (c->p < c->end && !is_blank(*c->p) && *c->p != '\n') c->p++;
  return (size_t)(c->p - *w);
}

static int wordeq(const char *w, size_t n, const char *s) { return strlen(s) == n && memcmp(w, s, n) == 0; }

static int ply_property(tcur *c, ply_header *h, sm_error *err) {
  if (h->nelems == 0) return syntax_error(c, err, "property before any element");
  ply_elem *e = &h->elems[h->nelems - 1];
  if (e->nprops == PLY_MAX_PROPS) return syntax_error(c, err, "too many properties");
  ply_prop *p = &e->props[e->nprops++];
  const char *w;
  size_t n = header_word(c, &w);
  p->list_type = PT_NONE;
  if (wordeq(w, n, "list")) {
    n = header_word(c, &w);
    if ((p->list_type = ply_type(w, n)) == PT_NONE || p->list_type >= PT_F32)
      return syntax_error(c, err, "bad list count type");
    n = header_word(c, &w);
  }
  if ((p->type = ply_type(w, n)) == PT_NONE) return syntax_error(c, err, "unknown property type");
  n = header_word(c, &w);
  /* A nameless property would be harmless to us, but OpenMesh's reader, which sees binary
   * files first, loops forever on one (found by tests/fuzz/fuzz_meshio). */
  if (n == 0) return syntax_error(c, err, "property without a name");
  p->role = ROLE_SKIP;
  if (e->is_vertex && p->list_type == PT_NONE) {
    if (wordeq(w, n, "x")) p->role = ROLE_X;
    if (wordeq(w, n, "y")) p->role = ROLE_Y;
    if (wordeq(w, n, "z")) p->role = ROLE_Z;
  }
  if (e->is_face && p->list_type != PT_NONE &&
      (wordeq(w, n, "vertex_indices") || wordeq(w, n, "vertex_index")))
    p->role = ROLE_FACE;
  return 0;
}

static int ply_element(tcur *c, ply_header *h, sm_error *err) {
  if (h->nelems == PLY_MAX_ELEMS) return syntax_error(c, err, "too many elements");
  ply_elem *e = &h->elems[h->nelems++];
  memset(e, 0, sizeof *e);
  const char *w;
  size_t n = header_word(c, &w);
  e->is_vertex = wordeq(w, n, "vertex");
  e->is_face = wordeq(w, n, "face");
  if (read_long(c, &e->count) || e->count < 0) return syntax_error(c, err, "bad element count");
  if (e->is_vertex && h->seen_vertex++) return syntax_error(c, err, "second vertex element");
  if (e->is_vertex) h->nv = e->count;
  if (e->is_face) h->nf = e->count;
  return 0;
}

/* A format, element or property line with words after its last field: we ignore them, but
 * OpenMesh reads the header as one stream of words, so they shift everything it reads after
 * them (and it loops forever when a count then fails to parse; found by fuzz_meshio). */
static void ply_note_trailing_words(tcur *c, ply_header *h) {
  const char *w;
  if (header_word(c, &w) != 0) h->plain = 0;
}

static int ply_header_fields(tcur *c, ply_header *h, int *done, sm_error *err) {
  const char *w;
  size_t n = header_word(c, &w);
  if (wordeq(w, n, "format")) {
    n = header_word(c, &w);
    if (wordeq(w, n, "ascii")) h->format = PLY_ASCII;
    else if (wordeq(w, n, "binary_little_endian")) h->format = PLY_BLE;
    else if (wordeq(w, n, "binary_big_endian")) h->format = PLY_BBE;
    else return syntax_error(c, err, "unknown PLY format");
    /* PLY has only version 1.0. Checked here because OpenMesh's reader, which sees binary
     * files first, loops forever on a version its stream cannot parse as a number. */
    n = header_word(c, &w);
    char *q;
    if (n == 0 || strtod(w, &q) != 1.0 || q != w + n)
      return syntax_error(c, err, "PLY format version is not 1.0");
    return 0;
  }
  if (wordeq(w, n, "element")) return ply_element(c, h, err);
  if (wordeq(w, n, "property")) return ply_property(c, h, err);
  if (wordeq(w, n, "end_header")) *done = 1;
  else if (n && !wordeq(w, n, "comment") && !wordeq(w, n, "obj_info"))
    return syntax_error(c, err, "unknown header keyword");
  return 0;
}

static int ply_header_line(tcur *c, ply_header *h, int *done, sm_error *err) {
  tcur peek = *c;
  const char *w;
  size_t n = header_word(&peek, &w);
  int fielded = wordeq(w, n, "format") || wordeq(w, n, "element") || wordeq(w, n, "property") ||
                wordeq(w, n, "end_header");
  int rc = ply_header_fields(c, h, done, err);
  if (rc == 0 && fielded) ply_note_trailing_words(c, h);
  return rc;
}

/* True when the header's bytes are printable ASCII, spaces, tabs and line ends only, so
 * that OpenMesh's stream tokenizer (which also splits at \v and \f, and reads across
 * lines) sees the words and lines we parsed. Anything else goes to our own reader. */
static int ply_header_bytes_plain(const char *buf, size_t body) {
  for (size_t i = 0; i < body; i++) {
    unsigned char ch = (unsigned char)buf[i];
    if (ch == '\r' && i + 1 < body && buf[i + 1] == '\n') continue;
    if (ch != '\n' && ch != '\t' && (ch < 0x20 || ch > 0x7e)) return 0;
  }
  return 1;
}

static void ply_check_xyz(ply_header *h) {
  h->xyz_float32 = 1;
  for (int i = 0; i < h->nelems; i++)
    for (int k = 0; k < h->elems[i].nprops; k++) {
      const ply_prop *p = &h->elems[i].props[k];
      if (h->elems[i].is_vertex && p->role != ROLE_SKIP && p->type != PT_F32) h->xyz_float32 = 0;
    }
}

static int ply_read_header(const char *name, const char *buf, size_t len, ply_header *h,
                           sm_error *err) {
  memset(h, 0, sizeof *h);
  h->format = -1;
  h->plain = 1;
  tcur c = {buf, buf + len, name, 1};
  const char *w;
  size_t n = header_word(&c, &w);
  if (!wordeq(w, n, "ply")) return sm_error_set(err, SM_EFORMAT, "%s: not a PLY file", name);
  ply_note_trailing_words(&c, h);
  int done = 0, rc;
  while (!done) {
    next_line(&c);
    if (c.p >= c.end) return sm_error_set(err, SM_EFORMAT, "%s: PLY header has no end_header", name);
    if ((rc = ply_header_line(&c, h, &done, err))) return rc;
  }
  if (h->format < 0) return sm_error_set(err, SM_EFORMAT, "%s: PLY header has no format line", name);
  next_line(&c);
  h->body = (size_t)(c.p - buf);
  h->plain = h->plain && ply_header_bytes_plain(buf, h->body);
  ply_check_xyz(h);
  return 0;
}

/* Body reader: one value at a time, in whichever encoding the header named. */
typedef struct ply_rd {
  tcur c; /* ascii: the cursor; binary: c.p and c.end only */
  int format;
} ply_rd;

static int host_is_little(void) {
  const uint16_t one = 1;
  return *(const uint8_t *)&one == 1;
}

static double ply_decode(int type, const uint8_t *b) {
  union { int8_t i8; uint8_t u8; int16_t i16; uint16_t u16; int32_t i32; uint32_t u32;
          float f32; double f64; } u;
  memcpy(&u, b, ply_size(type));
  switch (type) {
    case PT_I8: return u.i8;
    case PT_U8: return u.u8;
    case PT_I16: return u.i16;
    case PT_U16: return u.u16;
    case PT_I32: return u.i32;
    case PT_U32: return u.u32;
    case PT_F32: return u.f32;
    default: return u.f64;
  }
}

/* 0 or -1 (missing or malformed value). */
static int ply_value(ply_rd *r, int type, double *x) {
  if (r->format == PLY_ASCII) {
    while (r->c.p < r->c.end && (is_blank(*r->c.p) || *r->c.p == '\n')) r->c.p++;
    if (r->c.p >= r->c.end) return -1;
    char *q;
    *x = strtod(r->c.p, &q);
    if (q == r->c.p || !(q >= r->c.end || is_blank(*q) || *q == '\n')) return -1;
    r->c.p = q;
    return 0;
  }
  size_t n = ply_size(type);
  if ((size_t)(r->c.end - r->c.p) < n) return -1;
  uint8_t b[8];
  memcpy(b, r->c.p, n);
  if ((r->format == PLY_BLE) != host_is_little())
    for (size_t i = 0; i < n / 2; i++) {
      uint8_t t = b[i];
      b[i] = b[n - 1 - i];
      b[n - 1 - i] = t;
    }
  r->c.p += n;
  *x = ply_decode(type, b);
  return 0;
}

static int ply_item_error(const char *name, const char *what, long long item, sm_error *err) {
  return sm_error_set(err, SM_EFORMAT, "%s: %s %lld: %s", name, "element item", item, what);
}

/* A list count or face index read as a double: 0 when it is a whole number within int32.
 * The range is tested before any conversion: converting inf, NaN or a number beyond the
 * integer type (an ascii "1e30", a binary double) is undefined behaviour in C. */
static int ply_whole_i32(double x, int32_t *out) {
  if (!(x >= INT32_MIN && x <= INT32_MAX)) return -1;
  int32_t i = (int32_t)x;
  if ((double)i != x) return -1;
  *out = i;
  return 0;
}

static int ply_list(ply_rd *r, const ply_prop *p, fan *fn, long long item, sm_error *err) {
  double v, x;
  int32_t cnt, idx;
  const char *name = r->c.name;
  if (ply_value(r, p->list_type, &v)) return ply_item_error(name, "truncated or malformed list count", item, err);
  if (ply_whole_i32(v, &cnt) || cnt < 0)
    return ply_item_error(name, "bad list count (not a whole number in [0, 2^31))", item, err);
  if (p->role == ROLE_FACE) {
    if (cnt < 3) return ply_item_error(name, "face has fewer than 3 corners", item, err);
    fan_begin(fn);
  }
  for (int32_t k = 0; k < cnt; k++) {
    if (ply_value(r, p->type, &x)) return ply_item_error(name, "truncated or malformed list", item, err);
    if (p->role != ROLE_FACE) continue;
    if (ply_whole_i32(x, &idx)) return ply_item_error(name, "face index is not a 32-bit integer", item, err);
    fan_add(fn, idx);
  }
  return 0;
}

static int ply_item(ply_rd *r, const ply_elem *e, long long item, long long *vi, fan *fn,
                    sm_error *err) {
  double xyz[3] = {0, 0, 0}, x;
  for (int k = 0; k < e->nprops; k++) {
    const ply_prop *p = &e->props[k];
    if (p->list_type != PT_NONE) {
      int rc = ply_list(r, p, fn, item, err);
      if (rc) return rc;
      continue;
    }
    if (ply_value(r, p->type, &x))
      return ply_item_error(r->c.name, "truncated or malformed value", item, err);
    if (p->role >= ROLE_X && p->role <= ROLE_Z) xyz[p->role - ROLE_X] = x;
  }
  if (e->is_vertex) {
    if (fn->m) memcpy(fn->m->V + 3 * *vi, xyz, sizeof xyz);
    (*vi)++;
  }
  return 0;
}

static int ply_pass(const char *name, const char *buf, size_t len, const ply_header *h, fan *fn,
                    sm_error *err) {
  ply_rd r = {{buf + h->body, buf + len, name, 0}, h->format};
  long long vi = 0;
  for (int i = 0; i < h->nelems; i++)
    /* An element without properties takes no bytes; a huge count must not spin. */
    for (long long item = 0; h->elems[i].nprops && item < h->elems[i].count; item++) {
      int rc = ply_item(&r, &h->elems[i], item, &vi, fn, err);
      if (rc) return rc;
    }
  return 0;
}

static int ply_check_roles(const char *name, const ply_header *h, sm_error *err) {
  for (int i = 0; i < h->nelems; i++) {
    const ply_elem *e = &h->elems[i];
    int roles = 0;
    for (int k = 0; k < e->nprops; k++) roles |= 1 << e->props[k].role;
    if (e->is_vertex && (roles & 0xE) != 0xE)
      return sm_error_set(err, SM_EFORMAT, "%s: vertex element lacks x, y or z", name);
    if (e->is_face && !(roles & (1 << ROLE_FACE)))
      return sm_error_set(err, SM_EFORMAT, "%s: face element has no vertex_indices list", name);
  }
  return 0;
}

static int read_ply_own(const char *name, const char *buf, size_t len, const ply_header *h,
                        const sm_limits *lim, sm_mesh **out, sm_error *err) {
  int rc = ply_check_roles(name, h, err);
  if (rc) return rc;
  if ((rc = sm_limits_check(lim, h->nv, h->nf, err))) return rc;
  fan count = {0};
  if ((rc = ply_pass(name, buf, len, h, &count, err))) return rc;
  fan fill = {0};
  if ((rc = alloc_counted(name, h->nv, count.ntri, lim, &fill.m, err))) return rc;
  if ((rc = ply_pass(name, buf, len, h, &fill, err))) {
    sm_mesh_destroy(fill.m);
    return rc;
  }
  *out = fill.m;
  return 0;
}

/* True when no element claims more items than the body has bytes, as in every complete
 * binary file whose elements have properties. OpenMesh reads counts into an unsigned int,
 * and a count past 2^32 fails its header stream, which it then reads forever (found by
 * fuzz_meshio: "element f 8888888888888960"); such files go to our own reader. */
static int ply_counts_fit_body(const ply_header *h, size_t len) {
  for (int i = 0; i < h->nelems; i++)
    if ((unsigned long long)h->elems[i].count > len - h->body) return 0;
  return 1;
}

/* OpenMesh first for binary float32 files with a plain header and believable counts; our
 * own parser for the rest and when OpenMesh's counts differ from the header's (or OpenMesh
 * fails). */
static int read_ply(const char *name, const char *buf, size_t len, const sm_limits *lim,
                    sm_mesh **out, sm_error *err) {
  ply_header h;
  int rc = ply_read_header(name, buf, len, &h, err);
  if (rc) return rc;
  if (h.format != PLY_ASCII && h.xyz_float32 && h.plain && h.nv > 0 &&
      ply_counts_fit_body(&h, len)) {
    sm_mesh *m = NULL;
    int64_t npoly = -1;
    if (sm_limits_check(lim, h.nv, h.nf, err) == 0 &&
        sm_openmesh_read((const uint8_t *)buf, len, "ply", 1, lim, &m, &npoly, NULL) == 0) {
      if (m->nv == h.nv && npoly == h.nf) {
        *out = m;
        return 0;
      }
      sm_mesh_destroy(m);
    }
  }
  return read_ply_own(name, buf, len, &h, lim, out, err);
}

/* ------------------------------------------------------------------------------------ */
/* STL                                                                                  */

/* Binary STL: 80-byte header, uint32 count, 50 bytes per triangle. */
static int stl_is_binary(const char *buf, size_t len) {
  if (len < 84) return 0;
  uint32_t n;
  memcpy(&n, buf + 80, 4);
  if (!host_is_little()) n = (n >> 24) | ((n >> 8) & 0xff00) | ((n << 8) & 0xff0000) | (n << 24);
  if (84 + 50 * (uint64_t)n == len) return 1;
  return !(len >= 5 && strncasecmp(buf, "solid", 5) == 0);
}

static int stl_binary_corners(const char *name, const char *buf, size_t len, double **P,
                              int64_t *nt, const sm_limits *lim, sm_error *err) {
  uint8_t cnt[4];
  memcpy(cnt, buf + 80, 4);
  uint64_t n = cnt[0] | (uint64_t)cnt[1] << 8 | (uint64_t)cnt[2] << 16 | (uint64_t)cnt[3] << 24;
  if (84 + 50 * n != len)
    return sm_error_set(err, SM_EFORMAT, "%s: binary STL declares %llu triangles (%llu bytes), file has %zu bytes",
                        name, (unsigned long long)n, (unsigned long long)(84 + 50 * n), len);
  int rc = sm_limits_check(lim, 3 * (int64_t)n, (int64_t)n, err);
  if (rc) return rc;
  *P = malloc((n ? n : 1) * 9 * sizeof(double));
  if (!*P) return sm_error_set(err, SM_ENOMEM, "%s: cannot allocate %llu triangles", name, (unsigned long long)n);
  for (uint64_t t = 0; t < n; t++)
    for (int k = 0; k < 9; k++) {
      uint8_t b[4];
      memcpy(b, buf + 84 + 50 * t + 12 + 4 * k, 4);
      if (!host_is_little()) {
        uint8_t s = b[0]; b[0] = b[3]; b[3] = s;
        s = b[1]; b[1] = b[2]; b[2] = s;
      }
      (*P)[9 * t + k] = ply_decode(PT_F32, b);
    }
  *nt = (int64_t)n;
  return 0;
}

/* ASCII STL: every "vertex x y z" between "facet" and "endfacet"; a facet with more than
 * three vertices (seen in the wild) is fan-triangulated. Counting pass when P == NULL. */
static int stl_ascii_pass(tcur *c, double *P, int64_t *nt, sm_error *err) {
  double first[3] = {0}, prev[3] = {0};
  int k = 0;
  *nt = 0;
  while (next_content_line(c)) {
    if (word_is(c, "vertex")) {
      double xyz[3];
      c->p += 6;
      int rc = read_xyz(c, xyz, err);
      if (rc) return rc;
      if (k == 0) memcpy(first, xyz, sizeof xyz);
      if (k >= 2) {
        if (P) {
          memcpy(P + 9 * *nt, first, sizeof first);
          memcpy(P + 9 * *nt + 3, prev, sizeof prev);
          memcpy(P + 9 * *nt + 6, xyz, sizeof xyz);
        }
        (*nt)++;
      }
      memcpy(prev, xyz, sizeof xyz);
      k++;
    } else if (word_is(c, "endfacet")) {
      if (k < 3) return syntax_error(c, err, "facet has fewer than 3 vertices");
      k = 0;
    } else if (word_is(c, "facet")) {
      k = 0;
    }
    next_line(c);
  }
  if (k) return sm_error_set(err, SM_EFORMAT, "%s: file ends inside a facet", c->name);
  return 0;
}

static int stl_ascii_corners(const char *name, const char *buf, size_t len, double **P,
                             int64_t *nt, const sm_limits *lim, sm_error *err) {
  tcur c = {buf, buf + len, name, 1};
  int rc = stl_ascii_pass(&c, NULL, nt, err);
  if (rc) return rc;
  if ((rc = sm_limits_check(lim, 3 * *nt, *nt, err))) return rc;
  *P = malloc((size_t)(*nt ? *nt : 1) * 9 * sizeof(double));
  if (!*P) return sm_error_set(err, SM_ENOMEM, "%s: cannot allocate %lld triangles", name, (long long)*nt);
  c = (tcur){buf, buf + len, name, 1};
  if ((rc = stl_ascii_pass(&c, *P, nt, err))) {
    free(*P);
    *P = NULL;
  }
  return rc;
}

/* STL repeats each corner's coordinates in every triangle; corners with exactly equal
 * coordinates become one vertex, numbered in order of first appearance. Hash on the bit
 * patterns (with -0.0 folded into 0.0, which compare equal). */
static uint64_t point_hash(const double *p) {
  uint64_t h = 0x9E3779B97F4A7C15ULL;
  for (int k = 0; k < 3; k++) {
    double x = p[k] == 0 ? 0.0 : p[k];
    uint64_t b;
    memcpy(&b, &x, sizeof b);
    h = (h ^ b) * 0xBF58476D1CE4E5B9ULL;
    h ^= h >> 31;
  }
  return h;
}

static int same_point(const double *p, const double *q) {
  return p[0] == q[0] && p[1] == q[1] && p[2] == q[2];
}

/* id[i] = welded vertex of point i; rep[k] = first point of welded vertex k. */
static int weld_points(const double *P, int64_t n, int32_t *id, int64_t *rep, int64_t *nu,
                       sm_error *err) {
  uint64_t cap = 16;
  while (cap < 2 * (uint64_t)n) cap <<= 1;
  int64_t *slot = malloc(cap * sizeof *slot);
  if (!slot) return sm_error_set(err, SM_ENOMEM, "STL weld: cannot allocate %llu slots", (unsigned long long)cap);
  for (uint64_t i = 0; i < cap; i++) slot[i] = -1;
  *nu = 0;
  for (int64_t i = 0; i < n; i++) {
    uint64_t h = point_hash(P + 3 * i) & (cap - 1);
    while (slot[h] >= 0 && !same_point(P + 3 * rep[slot[h]], P + 3 * i)) h = (h + 1) & (cap - 1);
    if (slot[h] < 0) {
      slot[h] = *nu;
      rep[(*nu)++] = i;
    }
    id[i] = (int32_t)slot[h];
  }
  free(slot);
  return 0;
}

/* Faces: F[3t..3t+2] index P when F is given, else corner c of the soup is point c. */
static int build_welded(const char *name, const double *P, int64_t npts, const int32_t *F,
                        int64_t nt, const sm_limits *lim, sm_mesh **out, sm_error *err) {
  int32_t *id = malloc((size_t)(npts ? npts : 1) * sizeof *id);
  int64_t *rep = malloc((size_t)(npts ? npts : 1) * sizeof *rep);
  int64_t nu = 0;
  int rc = (!id || !rep) ? sm_error_set(err, SM_ENOMEM, "%s: cannot allocate weld arrays", name)
                         : weld_points(P, npts, id, rep, &nu, err);
  sm_mesh *m = NULL;
  if (!rc) rc = alloc_counted(name, nu, nt, lim, &m, err);
  if (!rc) {
    for (int64_t k = 0; k < nu; k++) memcpy(m->V + 3 * k, P + 3 * rep[k], 3 * sizeof(double));
    for (int64_t c = 0; c < 3 * nt; c++) m->F[c] = id[F ? F[c] : c];
    *out = m;
  }
  free(id);
  free(rep);
  return rc;
}

static int read_stl_own(const char *name, const char *buf, size_t len, int binary,
                        const sm_limits *lim, sm_mesh **out, sm_error *err) {
  double *P = NULL;
  int64_t nt = 0;
  int rc = binary ? stl_binary_corners(name, buf, len, &P, &nt, lim, err)
                  : stl_ascii_corners(name, buf, len, &P, &nt, lim, err);
  if (!rc) rc = build_welded(name, P, 3 * nt, NULL, nt, lim, out, err);
  free(P);
  return rc;
}

/* Triangles the file declares (binary header) or lists (ascii), -1 if unknown. */
static int64_t stl_declared(const char *name, const char *buf, size_t len, int binary) {
  if (binary) {
    if (len < 84) return -1;
    const uint8_t *b = (const uint8_t *)buf + 80;
    return (int64_t)(b[0] | (uint64_t)b[1] << 8 | (uint64_t)b[2] << 16 | (uint64_t)b[3] << 24);
  }
  tcur c = {buf, buf + len, name, 1};
  int64_t nt;
  return stl_ascii_pass(&c, NULL, &nt, NULL) ? -1 : nt;
}

static int faces_in_range(const sm_mesh *m) {
  for (int64_t i = 0; i < 3 * (int64_t)m->nf; i++)
    if (m->F[i] < 0 || m->F[i] >= m->nv) return 0;
  return 1;
}

static int read_stl(const char *name, const char *buf, size_t len, const sm_limits *lim,
                    sm_mesh **out, sm_error *err) {
  int binary = stl_is_binary(buf, len);
  int64_t declared = stl_declared(name, buf, len, binary);
  sm_mesh *m = NULL;
  int64_t npoly = -1;
  if (declared > 0 && sm_limits_check(lim, 0, declared, NULL) == 0 &&
      sm_openmesh_read((const uint8_t *)buf, len, "stl", binary, lim, &m, &npoly, NULL) == 0) {
    int rc = SM_EFORMAT;
    if (npoly == declared && m->nf == declared && faces_in_range(m))
      rc = build_welded(name, m->V, m->nv, m->F, m->nf, lim, out, err);
    sm_mesh_destroy(m);
    if (rc != SM_EFORMAT) return rc;
  }
  return read_stl_own(name, buf, len, binary, lim, out, err);
}

/* ------------------------------------------------------------------------------------ */
/* Dispatch                                                                             */

enum { FMT_UNKNOWN, FMT_OFF, FMT_OBJ, FMT_PLY, FMT_STL, FMT_DRC };

static int ext_is(const char *e, size_t n, const char *s) {
  return strlen(s) == n && strncasecmp(e, s, n) == 0;
}

/* Format from the last extension, or the one before an extra ".gz". */
static int format_of(const char *base, int *gz) {
  const char *end = base + strlen(base);
  *gz = 0;
  for (int pass = 0; pass < 2; pass++) {
    const char *dot = end;
    while (dot > base && dot[-1] != '.') dot--;
    if (dot == base) return FMT_UNKNOWN;
    size_t n = (size_t)(end - dot);
    if (pass == 0 && ext_is(dot, n, "gz")) {
      *gz = 1;
      end = dot - 1;
      continue;
    }
    if (ext_is(dot, n, "off")) return FMT_OFF;
    if (ext_is(dot, n, "obj")) return FMT_OBJ;
    if (ext_is(dot, n, "ply")) return FMT_PLY;
    if (ext_is(dot, n, "stl")) return FMT_STL;
    if (ext_is(dot, n, "drc")) return FMT_DRC;
    return FMT_UNKNOWN;
  }
  return FMT_UNKNOWN;
}

static int parse_content(int fmt, const char *name, const uint8_t *b, size_t n,
                         const sm_limits *lim, sm_mesh **out, sm_error *err) {
  const char *s = (const char *)b;
  switch (fmt) {
    case FMT_OFF: return read_off(name, s, n, lim, out, err);
    case FMT_OBJ: return read_obj(name, s, n, lim, out, err);
    case FMT_PLY: return read_ply(name, s, n, lim, out, err);
    case FMT_STL: return read_stl(name, s, n, lim, out, err);
    default: break;
  }
  int rc = sm_draco_decode(b, n, lim, out, err);
  return rc ? prefix_error(err, rc, name) : 0;
}

/* Parses buf[len] as a file called base (format fmt, gzip'd if gz). The text parsers stop
 * at a NUL (strtod), so buf[len] must be one: sm_read_file_bytes and gunzip both add it. */
static int read_terminated(const char *base, int fmt, int gz, const uint8_t *buf, size_t len,
                           const sm_limits *lim, sm_mesh **out, sm_error *err) {
  uint8_t *data = NULL;
  if (gz) {
    int rc = gunzip(base, buf, len, SM_IO_MAX_BYTES, &data, &len, err);
    if (rc) return rc;
    buf = data;
  }
  int rc = len == 0 ? sm_error_set(err, SM_EFORMAT, "%s: file is empty", base)
                    : parse_content(fmt, base, buf, len, lim, out, err);
  free(data);
  return rc;
}

static int format_or_error(const char *base, int *gz, sm_error *err) {
  int fmt = format_of(base, gz);
  if (fmt == FMT_UNKNOWN)
    sm_error_set(err, SM_EFORMAT, "%s: unknown mesh file extension (want .off .obj .ply .stl .drc, optionally .gz)", base);
  return fmt;
}

int sm_mesh_read_buffer(const char *name, const uint8_t *buf, size_t len, const sm_limits *lim,
                        sm_mesh **out, sm_error *err) {
  if (!name || (!buf && len) || !out)
    return sm_error_set(err, SM_EINVAL, "sm_mesh_read_buffer: null argument");
  *out = NULL;
  const char *base = strrchr(name, '/') ? strrchr(name, '/') + 1 : name;
  int gz, fmt = format_or_error(base, &gz, err);
  if (fmt == FMT_UNKNOWN) return SM_EFORMAT;
  if (len > SM_IO_MAX_BYTES)
    return sm_error_set(err, SM_ELIMIT, "%s: more than %zu bytes", base, (size_t)SM_IO_MAX_BYTES);
  uint8_t *copy = malloc(len + 1); /* the caller's bytes need not end with a NUL */
  if (!copy) return sm_error_set(err, SM_ENOMEM, "%s: cannot allocate %zu bytes", base, len + 1);
  if (len) memcpy(copy, buf, len);
  copy[len] = 0;
  int rc = read_terminated(base, fmt, gz, copy, len, lim, out, err);
  free(copy);
  return rc;
}

int sm_mesh_read_file(const char *path, const sm_limits *lim, sm_mesh **out, sm_error *err) {
  if (!path || !out) return sm_error_set(err, SM_EINVAL, "sm_mesh_read_file: null argument");
  *out = NULL;
  const char *base = strrchr(path, '/') ? strrchr(path, '/') + 1 : path;
  int gz, fmt = format_or_error(base, &gz, err);
  if (fmt == FMT_UNKNOWN) return SM_EFORMAT;
  uint8_t *raw = NULL;
  size_t rawlen = 0;
  int rc = sm_read_file_bytes(path, SM_IO_MAX_BYTES, &raw, &rawlen, err);
  if (rc) return rc;
  rc = read_terminated(base, fmt, gz, raw, rawlen, lim, out, err);
  free(raw);
  return rc;
}
