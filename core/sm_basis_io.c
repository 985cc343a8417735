/* sm_basis_io: the binary form of an sm_basis, its file I/O, and sm_mesh_hash.
 *
 * FILE FORMAT, version 1
 *   All integers little-endian, two's complement for signed ones. A "f64" is the 8-byte
 *   IEEE-754 binary64 bit pattern of the value, stored as a little-endian u64, so a reader
 *   reinterprets the u64 as a double (no text, no rounding: load is bit-exact).
 *   No padding anywhere; offsets are in bytes.
 *
 *   Header (32 bytes):
 *     0   8  magic           "SMBASIS\0" (53 4D 42 41 53 49 53 00)
 *     8   4  u32 version     1
 *     12  4  u32 header_size 32 (offset of the payload)
 *     16  8  u64 payload_len bytes after the header; must equal file size - 32 exactly
 *     24  8  u64 checksum    XXH3-64 (XXH3_64bits, seed 0, no secret) of the payload bytes
 *
 *   Payload (offsets from its start, i.e. file offset - 32):
 *     0   4  i32 kind          1 = Laplace-Beltrami, 2 = elastic
 *     4   4  i32 n             vertices, > 0
 *     8   4  i32 k             functions, 0 < k <= n
 *     12  4  i32 n_kernel      >= 0, <= 3n
 *     16  4  i32 n_components  >= 0, <= n
 *     20  8  f64 eta           finite
 *     28  8  f64 mu            finite
 *     36  8  f64 lambda        finite
 *     44  8  u64 mesh_hash     sm_mesh_hash of the mesh (see below)
 *     52  4  u32 flags         bit 0: gram_L present; every other bit must be 0
 *     56     f64 evals[k]
 *            f64 phi[n*k]      column-major: phi[v + n*i] is function i at vertex v
 *            f64 mass[n]
 *            f64 gram_L[k*k]   column-major, only if flags bit 0
 *   payload_len = 56 + 8*(k + n*k + n + (flags & 1 ? k*k : 0)); every array value finite.
 *   Timing (sm_basis.timing) is not stored; it loads as zeros.
 *
 *   Readers check, in this order and before allocating anything from a stored count:
 *   magic (SM_EFORMAT), version (SM_EVERSION), header_size, payload_len against the bytes
 *   actually present (SM_EFORMAT for truncation or trailing bytes), checksum (SM_ECHECKSUM),
 *   then each field above (SM_EFORMAT naming the field), and payload_len against n, k and
 *   flags. Writers apply the same field rules (SM_EINVAL), so whatever saves also loads.
 *
 * MESH HASH
 *   sm_mesh_hash = XXH3_64bits (seed 0) of the byte string
 *   le32(nv) le32(nf) f64(V[0]) .. f64(V[3nv-1]) le32(F[0]) .. le32(F[3nf-1])
 *   with f64 as above: coordinates are hashed as bit patterns, so -0.0 != 0.0.
 *
 * SAVE
 *   Writes path.tmp.<pid>.<counter> in the same directory (O_EXCL), fsyncs it, renames it
 *   over path and fsyncs the directory, so readers see either the old file or the whole new
 *   one, also after a crash. The temp file is removed on any failure.
 */
#include "sm_basis.h"

#include <errno.h>
#include <fcntl.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#define XXH_STATIC_LINKING_ONLY /* XXH3_state_t on the stack: sm_mesh_hash cannot fail */
#include <xxhash.h>

_Static_assert(sizeof(double) == 8, "f64 encoding needs a 64-bit double");

#define BIO_VERSION SM_BASIS_FORMAT_VERSION
#define BIO_HEADER_SIZE 32u
#define BIO_FIXED_SIZE 56u /* payload bytes before the arrays */
#define BIO_FLAG_GRAM 1u
#define BIO_MAX_FILE (16ull << 30) /* load refuses larger files (SM_ELIMIT) */

static const uint8_t bio_magic[8] = {'S', 'M', 'B', 'A', 'S', 'I', 'S', 0};

/* ---- little-endian load/store: byte by byte, so host endianness never matters ---- */

static void st_u32(uint8_t *p, uint32_t v) {
  for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static void st_u64(uint8_t *p, uint64_t v) {
  for (int i = 0; i < 8; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static uint64_t f64_bits(double d) {
  uint64_t u;
  memcpy(&u, &d, 8);
  return u;
}

static void st_f64(uint8_t *p, double d) { st_u64(p, f64_bits(d)); }

static uint32_t ld_u32(const uint8_t *p) {
  uint32_t v = 0;
  for (int i = 0; i < 4; i++) v |= (uint32_t)p[i] << (8 * i);
  return v;
}

/* Two's complement decode without relying on implementation-defined conversions. */
static int32_t ld_i32(const uint8_t *p) {
  uint32_t v = ld_u32(p);
  return v <= INT32_MAX ? (int32_t)v : -(int32_t)(~v) - 1;
}

static uint64_t ld_u64(const uint8_t *p) {
  uint64_t v = 0;
  for (int i = 0; i < 8; i++) v |= (uint64_t)p[i] << (8 * i);
  return v;
}

static double ld_f64(const uint8_t *p) {
  uint64_t u = ld_u64(p);
  double d;
  memcpy(&d, &u, 8);
  return d;
}

/* On the bit pattern, so it holds even under -ffast-math. */
static int bits_finite(uint64_t u) {
  return (u & 0x7ff0000000000000ull) != 0x7ff0000000000000ull;
}

/* ---- mesh hash ---- */

uint64_t sm_mesh_hash(const sm_mesh *m) {
  XXH3_state_t st;
  uint8_t chunk[4096];
  if (!m) return 0;
  XXH3_64bits_reset(&st);
  st_u32(chunk, (uint32_t)m->nv);
  st_u32(chunk + 4, (uint32_t)m->nf);
  XXH3_64bits_update(&st, chunk, 8);
  /* Streaming in fixed chunks hashes the same bytes as one concatenated buffer. */
  size_t nV = m->nv > 0 ? 3 * (size_t)m->nv : 0, nF = m->nf > 0 ? 3 * (size_t)m->nf : 0;
  for (size_t i = 0; i < nV;) {
    size_t c = 0;
    for (; c < sizeof chunk / 8 && i < nV; c++, i++) st_f64(chunk + 8 * c, m->V[i]);
    XXH3_64bits_update(&st, chunk, 8 * c);
  }
  for (size_t i = 0; i < nF;) {
    size_t c = 0;
    for (; c < sizeof chunk / 4 && i < nF; c++, i++) st_u32(chunk + 4 * c, (uint32_t)m->F[i]);
    XXH3_64bits_update(&st, chunk, 4 * c);
  }
  return XXH3_64bits_digest(&st);
}

/* ---- field rules shared by writer (code SM_EINVAL) and reader (SM_EFORMAT) ---- */

static int bio_check_fields(const sm_basis *b, int code, sm_error *err) {
  if (b->kind != SM_BASIS_LB && b->kind != SM_BASIS_ELASTIC)
    return sm_error_set(err, code, "basis field kind=%d, expected 1 or 2", (int)b->kind);
  if (b->n <= 0) return sm_error_set(err, code, "basis field n=%d, must be > 0", (int)b->n);
  if (b->k <= 0 || b->k > b->n)
    return sm_error_set(err, code, "basis field k=%d, must be in [1, n=%d]", (int)b->k,
                        (int)b->n);
  if (b->n_kernel < 0 || (int64_t)b->n_kernel > 3 * (int64_t)b->n)
    return sm_error_set(err, code, "basis field n_kernel=%d, must be in [0, 3n]",
                        (int)b->n_kernel);
  if (b->n_components < 0 || b->n_components > b->n)
    return sm_error_set(err, code, "basis field n_components=%d, must be in [0, n]",
                        (int)b->n_components);
  const double par[3] = {b->eta, b->mu, b->lambda};
  const char *name[3] = {"eta", "mu", "lambda"};
  for (int i = 0; i < 3; i++)
    if (!bits_finite(f64_bits(par[i])))
      return sm_error_set(err, code, "basis field %s is not finite", name[i]);
  return SM_OK;
}

/* Payload bytes for valid n, k; 0 when they do not fit in size_t. The double count is
 * below 2^64 because n, k < 2^31; only the byte count can overflow. */
static size_t bio_payload_size(int32_t n, int32_t k, int has_gram) {
  uint64_t nn = (uint64_t)n, kk = (uint64_t)k;
  uint64_t count = kk + nn * kk + nn + (has_gram ? kk * kk : 0);
  if (count > (SIZE_MAX - BIO_FIXED_SIZE) / 8) return 0;
  return BIO_FIXED_SIZE + 8 * (size_t)count;
}

/* ---- arrays ---- */

static int bio_put_array(uint8_t **p, const double *a, size_t count, const char *name,
                         sm_error *err) {
  uint8_t *q = *p;
  for (size_t i = 0; i < count; i++, q += 8) {
    uint64_t u = f64_bits(a[i]);
    if (!bits_finite(u))
      return sm_error_set(err, SM_EINVAL, "basis %s[%zu] is not finite", name, i);
    st_u64(q, u);
  }
  *p = q;
  return SM_OK;
}

static int bio_get_array(const uint8_t **p, double *a, size_t count, const char *name,
                         sm_error *err) {
  const uint8_t *q = *p;
  for (size_t i = 0; i < count; i++, q += 8) {
    uint64_t u = ld_u64(q);
    if (!bits_finite(u))
      return sm_error_set(err, SM_EFORMAT, "stored basis %s[%zu] is not finite", name, i);
    memcpy(&a[i], &u, 8);
  }
  *p = q;
  return SM_OK;
}

/* ---- serialize ---- */

static void bio_put_fields(uint8_t *p, const sm_basis *b) {
  st_u32(p + 0, (uint32_t)b->kind);
  st_u32(p + 4, (uint32_t)b->n);
  st_u32(p + 8, (uint32_t)b->k);
  st_u32(p + 12, (uint32_t)b->n_kernel);
  st_u32(p + 16, (uint32_t)b->n_components);
  st_f64(p + 20, b->eta);
  st_f64(p + 28, b->mu);
  st_f64(p + 36, b->lambda);
  st_u64(p + 44, b->mesh_hash);
  st_u32(p + 52, b->gram_L ? BIO_FLAG_GRAM : 0);
}

static void bio_put_header(uint8_t *h, size_t payload_len) {
  memcpy(h, bio_magic, 8);
  st_u32(h + 8, BIO_VERSION);
  st_u32(h + 12, BIO_HEADER_SIZE);
  st_u64(h + 16, (uint64_t)payload_len);
  st_u64(h + 24, XXH3_64bits(h + BIO_HEADER_SIZE, payload_len));
}

int sm_basis_serialize(const sm_basis *b, uint8_t **buf, size_t *len, sm_error *err) {
  if (!b || !buf || !len) return sm_error_set(err, SM_EINVAL, "basis_serialize: NULL argument");
  if (!b->evals || !b->phi || !b->mass)
    return sm_error_set(err, SM_EINVAL, "basis_serialize: evals, phi or mass is NULL");
  int rc = bio_check_fields(b, SM_EINVAL, err);
  if (rc) return rc;
  size_t n = (size_t)b->n, k = (size_t)b->k;
  size_t plen = bio_payload_size(b->n, b->k, b->gram_L != NULL);
  if (!plen || plen > SIZE_MAX - BIO_HEADER_SIZE)
    return sm_error_set(err, SM_ELIMIT, "basis n=%zu k=%zu too large to serialize", n, k);
  uint8_t *out = malloc(BIO_HEADER_SIZE + plen);
  if (!out) return sm_error_set(err, SM_ENOMEM, "basis_serialize: %zu bytes", plen);
  uint8_t *p = out + BIO_HEADER_SIZE;
  bio_put_fields(p, b);
  p += BIO_FIXED_SIZE;
  if ((rc = bio_put_array(&p, b->evals, k, "evals", err)) ||
      (rc = bio_put_array(&p, b->phi, n * k, "phi", err)) ||
      (rc = bio_put_array(&p, b->mass, n, "mass", err)) ||
      (b->gram_L && (rc = bio_put_array(&p, b->gram_L, k * k, "gram_L", err)))) {
    free(out);
    return rc;
  }
  bio_put_header(out, plen);
  *buf = out;
  *len = BIO_HEADER_SIZE + plen;
  return SM_OK;
}

/* ---- deserialize ---- */

static int bio_check_header(const uint8_t *buf, size_t len, sm_error *err) {
  if (len < 8 || memcmp(buf, bio_magic, 8) != 0)
    return sm_error_set(err, SM_EFORMAT, "not a basis file (bad magic)");
  if (len < BIO_HEADER_SIZE)
    return sm_error_set(err, SM_EFORMAT, "basis header truncated (%zu bytes)", len);
  uint32_t version = ld_u32(buf + 8), hsize = ld_u32(buf + 12);
  if (version != BIO_VERSION)
    return sm_error_set(err, SM_EVERSION, "basis format version %u, this build reads %u",
                        (unsigned)version, BIO_VERSION);
  if (hsize != BIO_HEADER_SIZE)
    return sm_error_set(err, SM_EFORMAT, "basis header_size %u, expected %u", (unsigned)hsize,
                        BIO_HEADER_SIZE);
  uint64_t plen = ld_u64(buf + 16);
  if (plen != (uint64_t)(len - BIO_HEADER_SIZE))
    return sm_error_set(err, SM_EFORMAT,
                        "basis payload_len %llu but %zu bytes follow the header (%s)",
                        (unsigned long long)plen, len - BIO_HEADER_SIZE,
                        plen > len - BIO_HEADER_SIZE ? "truncated" : "trailing bytes");
  if (ld_u64(buf + 24) != XXH3_64bits(buf + BIO_HEADER_SIZE, (size_t)plen))
    return sm_error_set(err, SM_ECHECKSUM, "basis payload checksum mismatch");
  return SM_OK;
}

/* Reads and validates the fixed payload fields into *b (arrays left NULL). */
static int bio_get_fields(const uint8_t *p, size_t plen, sm_basis *b, int *has_gram,
                          sm_error *err) {
  if (plen < BIO_FIXED_SIZE)
    return sm_error_set(err, SM_EFORMAT, "basis payload %zu bytes, fixed fields need %u", plen,
                        BIO_FIXED_SIZE);
  memset(b, 0, sizeof *b);
  b->kind = ld_i32(p + 0);
  b->n = ld_i32(p + 4);
  b->k = ld_i32(p + 8);
  b->n_kernel = ld_i32(p + 12);
  b->n_components = ld_i32(p + 16);
  b->eta = ld_f64(p + 20);
  b->mu = ld_f64(p + 28);
  b->lambda = ld_f64(p + 36);
  b->mesh_hash = ld_u64(p + 44);
  uint32_t flags = ld_u32(p + 52);
  if (flags & ~BIO_FLAG_GRAM)
    return sm_error_set(err, SM_EFORMAT, "basis field flags=0x%x has unknown bits",
                        (unsigned)flags);
  *has_gram = (flags & BIO_FLAG_GRAM) != 0;
  int rc = bio_check_fields(b, SM_EFORMAT, err);
  if (rc) return rc;
  if (bio_payload_size(b->n, b->k, *has_gram) != plen)
    return sm_error_set(err, SM_EFORMAT,
                        "basis payload_len %zu does not match n=%d k=%d gram_L=%d", plen,
                        (int)b->n, (int)b->k, *has_gram);
  return SM_OK;
}

int sm_basis_deserialize(const uint8_t *buf, size_t len, sm_basis **out, sm_error *err) {
  if (!out || (!buf && len)) return sm_error_set(err, SM_EINVAL, "basis_deserialize: NULL argument");
  *out = NULL;
  int rc = bio_check_header(buf, len, err), has_gram = 0;
  if (rc) return rc;
  sm_basis hdr;
  const uint8_t *p = buf + BIO_HEADER_SIZE;
  if ((rc = bio_get_fields(p, len - BIO_HEADER_SIZE, &hdr, &has_gram, err))) return rc;
  /* Sizes now match bytes actually present, so these allocations are bounded by len. */
  size_t n = (size_t)hdr.n, k = (size_t)hdr.k;
  sm_basis *b = malloc(sizeof *b);
  if (!b) return sm_error_set(err, SM_ENOMEM, "basis_deserialize: basis struct");
  *b = hdr;
  b->evals = malloc(k * 8);
  b->phi = malloc(n * k * 8);
  b->mass = malloc(n * 8);
  b->gram_L = has_gram ? malloc(k * k * 8) : NULL;
  if (!b->evals || !b->phi || !b->mass || (has_gram && !b->gram_L)) {
    sm_basis_destroy(b);
    return sm_error_set(err, SM_ENOMEM, "basis_deserialize: arrays for n=%zu k=%zu", n, k);
  }
  p += BIO_FIXED_SIZE;
  if ((rc = bio_get_array(&p, b->evals, k, "evals", err)) ||
      (rc = bio_get_array(&p, b->phi, n * k, "phi", err)) ||
      (rc = bio_get_array(&p, b->mass, n, "mass", err)) ||
      (has_gram && (rc = bio_get_array(&p, b->gram_L, k * k, "gram_L", err)))) {
    sm_basis_destroy(b);
    return rc;
  }
  *out = b;
  return SM_OK;
}

void sm_basis_destroy(sm_basis *b) {
  if (!b) return;
  free(b->evals);
  free(b->phi);
  free(b->mass);
  free(b->gram_L);
  free(b);
}

/* ---- files ---- */

/* Thread-safe strerror (the XSI strerror_r, as _POSIX_C_SOURCE selects). */
static int bio_io_error(sm_error *err, int errnum, const char *what, const char *path) {
  char msg[128];
  if (strerror_r(errnum, msg, sizeof msg) != 0) snprintf(msg, sizeof msg, "errno %d", errnum);
  return sm_error_set(err, SM_EIO, "%s '%s': %s", what, path, msg);
}

static int bio_write_all(int fd, const uint8_t *buf, size_t len) {
  while (len > 0) {
    ssize_t w = write(fd, buf, len > (1u << 30) ? (1u << 30) : len);
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) {
      if (w == 0) errno = EIO;
      return -1;
    }
    buf += w;
    len -= (size_t)w;
  }
  return 0;
}

/* The rename is only durable once the directory entry is on disk. */
static int bio_fsync_dir(const char *path) {
  size_t cut = 0;
  const char *slash = strrchr(path, '/');
  char *dir;
  if (slash) cut = slash == path ? 1 : (size_t)(slash - path);
  dir = malloc(cut + 2);
  if (!dir) {
    errno = ENOMEM;
    return -1;
  }
  if (slash) {
    memcpy(dir, path, cut);
    dir[cut] = 0;
  } else {
    strcpy(dir, ".");
  }
  int fd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC), rc = -1;
  free(dir);
  if (fd < 0) return -1;
  /* Some file systems cannot fsync a directory (EINVAL); nothing more can be done there. */
  rc = (fsync(fd) == 0 || errno == EINVAL) ? 0 : -1;
  int saved = errno;
  close(fd);
  errno = saved;
  return rc;
}

/* Creates a fresh temp file next to path; O_EXCL so two writers never share one. */
static int bio_open_temp(const char *path, char *tmp, size_t cap) {
  static atomic_ulong counter;
  for (int tries = 0; tries < 100; tries++) {
    snprintf(tmp, cap, "%s.tmp.%ld.%lu", path, (long)getpid(),
             (unsigned long)atomic_fetch_add(&counter, 1));
    int fd = open(tmp, O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
    if (fd >= 0 || errno != EEXIST) return fd;
  }
  return -1;
}

int sm_file_write_atomic(const char *path, const uint8_t *buf, size_t len, sm_error *err) {
  if (!path) return sm_error_set(err, SM_EINVAL, "write: NULL path");
  size_t cap = strlen(path) + 64;
  char *tmp = malloc(cap);
  if (!tmp) return sm_error_set(err, SM_ENOMEM, "write: temp path");
  int rc = SM_OK, fd = bio_open_temp(path, tmp, cap);
  if (fd < 0) {
    rc = bio_io_error(err, errno, "cannot create temp file for", path);
  } else if (bio_write_all(fd, buf, len) || fsync(fd)) {
    rc = bio_io_error(err, errno, "cannot write", tmp);
    close(fd);
    unlink(tmp);
  } else if (close(fd)) {
    rc = bio_io_error(err, errno, "cannot close", tmp);
    unlink(tmp);
  } else if (rename(tmp, path)) {
    rc = bio_io_error(err, errno, "cannot rename temp file to", path);
    unlink(tmp);
  } else if (bio_fsync_dir(path)) {
    rc = bio_io_error(err, errno, "cannot sync directory of", path);
  }
  free(tmp);
  return rc;
}

int sm_basis_save(const sm_basis *b, const char *path, sm_error *err) {
  uint8_t *buf = NULL;
  size_t len = 0;
  if (!path) return sm_error_set(err, SM_EINVAL, "basis_save: NULL path");
  int rc = sm_basis_serialize(b, &buf, &len, err);
  if (rc) return rc;
  rc = sm_file_write_atomic(path, buf, len, err);
  free(buf);
  return rc;
}

/* Reads a whole regular file of at most BIO_MAX_FILE bytes into a malloc'd buffer. */
static int bio_read_file(const char *path, uint8_t **buf, size_t *len, sm_error *err) {
  struct stat st;
  int fd = open(path, O_RDONLY | O_CLOEXEC);
  if (fd < 0) return bio_io_error(err, errno, "cannot open", path);
  int rc = SM_OK;
  uint8_t *data = NULL;
  size_t got = 0;
  if (fstat(fd, &st)) {
    rc = bio_io_error(err, errno, "cannot stat", path);
  } else if (!S_ISREG(st.st_mode)) {
    rc = sm_error_set(err, SM_EIO, "'%s' is not a regular file", path);
  } else if ((uint64_t)st.st_size > BIO_MAX_FILE || (uint64_t)st.st_size > SIZE_MAX) {
    rc = sm_error_set(err, SM_ELIMIT, "'%s' is %lld bytes, limit %llu", path,
                      (long long)st.st_size, (unsigned long long)BIO_MAX_FILE);
  } else if (!(data = malloc(st.st_size ? (size_t)st.st_size : 1))) {
    rc = sm_error_set(err, SM_ENOMEM, "cannot buffer '%s' (%lld bytes)", path,
                      (long long)st.st_size);
  }
  /* A file shorter than fstat said is left to the deserializer (reported as truncated). */
  while (!rc && got < (size_t)st.st_size) {
    ssize_t r = read(fd, data + got, (size_t)st.st_size - got);
    if (r < 0 && errno == EINTR) continue;
    if (r < 0) rc = bio_io_error(err, errno, "cannot read", path);
    if (r <= 0) break;
    got += (size_t)r;
  }
  close(fd);
  if (rc) {
    free(data);
    return rc;
  }
  *buf = data;
  *len = got;
  return SM_OK;
}

int sm_basis_load(const char *path, sm_basis **out, sm_error *err) {
  uint8_t *buf = NULL;
  size_t len = 0;
  if (!path || !out) return sm_error_set(err, SM_EINVAL, "basis_load: NULL argument");
  *out = NULL;
  int rc = bio_read_file(path, &buf, &len, err);
  if (rc) return rc;
  rc = sm_basis_deserialize(buf, len, out, err);
  free(buf);
  if (rc && err) {
    char why[sizeof err->msg];
    memcpy(why, err->msg, sizeof why);
    sm_error_set(err, rc, "'%s': %s", path, why);
  }
  return rc;
}
