/* test_basis_io: binary form of sm_basis (serialize/deserialize, save/load) and
 * sm_mesh_hash. Bases are synthetic (fixed seed), so sm_basis_compute is not needed. */
#include <dirent.h>
#include <errno.h>
#include <float.h>
#include <stdint.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <xxhash.h>

#include "sm_basis.h"
#include "sm_test.h"

#define HDR 32 /* header size, payload follows */

/* Own generator (xorshift64*) so the test depends on nothing but the module under test. */
static double rnd01(uint64_t *s) {
  *s ^= *s >> 12;
  *s ^= *s << 25;
  *s ^= *s >> 27;
  return (double)((*s * 2685821657736338717ULL) >> 11) / 9007199254740992.0;
}

/* g x g grid of vertices with jittered coordinates, two triangles per cell. */
static sm_mesh *grid_mesh(int g) {
  sm_mesh *m = NULL;
  uint64_t s = 77;
  REQUIRE(sm_mesh_alloc((int64_t)g * g, 2 * (int64_t)(g - 1) * (g - 1), NULL, &m, NULL) == SM_OK);
  for (int v = 0; v < g * g; v++) {
    m->V[3 * v] = v % g + 0.1 * rnd01(&s);
    m->V[3 * v + 1] = v / g + 0.1 * rnd01(&s);
    m->V[3 * v + 2] = rnd01(&s);
  }
  int32_t *f = m->F;
  for (int y = 0; y + 1 < g; y++)
    for (int x = 0; x + 1 < g; x++, f += 6) {
      int a = y * g + x, b = a + 1, c = a + g, d = c + 1;
      const int32_t t[6] = {a, b, d, a, d, c};
      memcpy(f, t, sizeof t);
    }
  return m;
}

/* Doubles that a careless encoder (text, float casts, flush-to-zero) would not preserve. */
static const double special[] = {-0.0, 0.0, 4.9406564584124654e-324, 2.2250738585072009e-308,
                                 DBL_MIN, -DBL_MIN, 1e308, -1e308, DBL_MAX, 0.1, -1.0 / 3.0};
#define N_SPECIAL (sizeof special / sizeof special[0])

static double rnd_value(uint64_t *s, size_t i) {
  if (i % 7 == 3) return special[(i / 7) % N_SPECIAL];
  return (rnd01(s) - 0.5) * 1e3;
}

static double *rnd_array(uint64_t *s, size_t count) {
  double *a = malloc(count * sizeof *a);
  REQUIRE(a);
  for (size_t i = 0; i < count; i++) a[i] = rnd_value(s, i);
  return a;
}

static sm_basis *make_basis(int kind, int n, int k, int with_gram, uint64_t seed) {
  sm_basis *b = calloc(1, sizeof *b);
  REQUIRE(b);
  uint64_t s = seed * 0x9E3779B97F4A7C15ull + 1;
  b->kind = kind;
  b->n = n;
  b->k = k;
  b->n_kernel = kind == SM_BASIS_ELASTIC ? 6 : 0;
  b->n_components = 1;
  b->eta = kind == SM_BASIS_ELASTIC ? 1e-3 : 0.0;
  b->mu = -0.0;
  b->lambda = 4.9406564584124654e-324;
  b->mesh_hash = 0xF00DFACE12345678ull ^ seed;
  b->evals = rnd_array(&s, (size_t)k);
  b->phi = rnd_array(&s, (size_t)n * k);
  b->mass = rnd_array(&s, (size_t)n);
  b->gram_L = with_gram ? rnd_array(&s, (size_t)k * k) : NULL;
  b->timing.solves = 42; /* not serialized */
  return b;
}

static int same_array(const double *a, const double *b, size_t count) {
  if (!a || !b) return a == b;
  return memcmp(a, b, count * sizeof *a) == 0;
}

/* Bit-exact comparison of everything serialized (doubles by bit pattern: -0.0 != 0.0). */
static int same_basis(const sm_basis *a, const sm_basis *b) {
  size_t n = (size_t)a->n, k = (size_t)a->k;
  return a->kind == b->kind && a->n == b->n && a->k == b->k && a->n_kernel == b->n_kernel &&
         a->n_components == b->n_components && memcmp(&a->eta, &b->eta, 8) == 0 &&
         memcmp(&a->mu, &b->mu, 8) == 0 && memcmp(&a->lambda, &b->lambda, 8) == 0 &&
         a->mesh_hash == b->mesh_hash && same_array(a->evals, b->evals, k) &&
         same_array(a->phi, b->phi, n * k) && same_array(a->mass, b->mass, n) &&
         same_array(a->gram_L, b->gram_L, k * k);
}

/* Heap copy of exactly len bytes so ASan catches any read past the end. */
static int deser_copy(const uint8_t *buf, size_t len, sm_basis **out, sm_error *err) {
  uint8_t *c = malloc(len ? len : 1);
  REQUIRE(c);
  if (len) memcpy(c, buf, len);
  int rc = sm_basis_deserialize(c, len, out, err);
  free(c);
  return rc;
}

static void put32(uint8_t *p, uint32_t v) {
  for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}
static void put64(uint8_t *p, uint64_t v) {
  for (int i = 0; i < 8; i++) p[i] = (uint8_t)(v >> (8 * i));
}
static uint64_t get64(const uint8_t *p) {
  uint64_t v = 0;
  for (int i = 0; i < 8; i++) v |= (uint64_t)p[i] << (8 * i);
  return v;
}

/* Rewrites payload_len and checksum so only the field checks can reject the buffer. */
static void reseal(uint8_t *buf, size_t len) {
  put64(buf + 16, len - HDR);
  put64(buf + 24, XXH3_64bits(buf + HDR, len - HDR));
}

static void test_roundtrip(void) {
  const int cfg[][4] = {{SM_BASIS_LB, 1, 1, 0},       {SM_BASIS_LB, 37, 5, 0},
                        {SM_BASIS_LB, 37, 5, 1},       {SM_BASIS_ELASTIC, 50, 12, 1},
                        {SM_BASIS_ELASTIC, 50, 12, 0}, {SM_BASIS_ELASTIC, 300, 300, 1}};
  for (size_t c = 0; c < sizeof cfg / sizeof cfg[0]; c++) {
    sm_basis *b = make_basis(cfg[c][0], cfg[c][1], cfg[c][2], cfg[c][3], c + 1), *r = NULL;
    uint8_t *buf = NULL;
    size_t len = 0;
    sm_error err;
    REQUIRE(sm_basis_serialize(b, &buf, &len, &err) == SM_OK);
    size_t n = (size_t)b->n, k = (size_t)b->k;
    CHECK(len == HDR + 56 + 8 * (k + n * k + n + (b->gram_L ? k * k : 0)));
    int rc = deser_copy(buf, len, &r, &err);
    CHECK_MSG(rc == SM_OK, "config %zu: %s", c, err.msg);
    CHECK_MSG(r && same_basis(b, r), "config %zu not bit-exact", c);
    if (r) CHECK(r->timing.solves == 0 && r->timing.assembly == 0.0);
    /* Serializing what was loaded gives the same bytes. */
    uint8_t *buf2 = NULL;
    size_t len2 = 0;
    if (r) CHECK(sm_basis_serialize(r, &buf2, &len2, NULL) == SM_OK);
    CHECK(buf2 && len2 == len && memcmp(buf, buf2, len) == 0);
    free(buf2);
    free(buf);
    sm_basis_destroy(r);
    sm_basis_destroy(b);
  }
}

/* The documented byte layout, checked byte by byte (also pins little-endian storage). */
static void test_layout(void) {
  sm_basis *b = make_basis(SM_BASIS_ELASTIC, 3, 2, 1, 9);
  b->eta = 1.0;
  b->n_kernel = 6;
  b->evals[0] = -2.0;
  uint8_t *buf;
  size_t len;
  REQUIRE(sm_basis_serialize(b, &buf, &len, NULL) == SM_OK);
  const uint8_t magic[8] = {'S', 'M', 'B', 'A', 'S', 'I', 'S', 0};
  CHECK(memcmp(buf, magic, 8) == 0);
  const uint8_t ver[8] = {1, 0, 0, 0, 32, 0, 0, 0};
  CHECK(memcmp(buf + 8, ver, 8) == 0);
  CHECK(get64(buf + 16) == len - HDR);
  CHECK(get64(buf + 24) == XXH3_64bits(buf + HDR, len - HDR));
  const uint8_t *p = buf + HDR;
  const uint8_t ints[20] = {2, 0, 0, 0, 3, 0, 0, 0, 2, 0, 0, 0, 6, 0, 0, 0, 1, 0, 0, 0};
  CHECK(memcmp(p, ints, 20) == 0);
  const uint8_t one[8] = {0, 0, 0, 0, 0, 0, 0xF0, 0x3F}, minus0[8] = {0, 0, 0, 0, 0, 0, 0, 0x80};
  CHECK(memcmp(p + 20, one, 8) == 0);   /* eta = 1.0 */
  CHECK(memcmp(p + 28, minus0, 8) == 0); /* mu = -0.0 */
  CHECK(get64(p + 36) == 1);             /* lambda = smallest denormal */
  CHECK(get64(p + 44) == b->mesh_hash);
  const uint8_t flags[4] = {1, 0, 0, 0}, m2[8] = {0, 0, 0, 0, 0, 0, 0, 0xC0};
  CHECK(memcmp(p + 52, flags, 4) == 0);
  CHECK(memcmp(p + 56, m2, 8) == 0); /* evals[0] = -2.0 */
  free(buf);
  sm_basis_destroy(b);
}

/* Every proper prefix fails cleanly, and leaves *out NULL. */
static void test_truncation(void) {
  sm_basis *b = make_basis(SM_BASIS_ELASTIC, 6, 3, 1, 3);
  uint8_t *buf;
  size_t len;
  REQUIRE(sm_basis_serialize(b, &buf, &len, NULL) == SM_OK);
  for (size_t t = 0; t < len; t++) {
    sm_basis *r = (sm_basis *)1;
    int rc = deser_copy(buf, t, &r, NULL);
    CHECK_MSG(rc < 0 && r == NULL, "prefix of %zu/%zu bytes: rc=%d", t, len, rc);
    if (rc == SM_OK) sm_basis_destroy(r);
    if (t >= 8) CHECK_MSG(rc == SM_EFORMAT, "prefix %zu: rc=%d", t, rc);
  }
  free(buf);
  sm_basis_destroy(b);
}

static int expected_header_error(size_t off) {
  if (off < 8) return SM_EFORMAT;   /* magic */
  if (off < 12) return SM_EVERSION; /* version */
  if (off < 24) return SM_EFORMAT;  /* header_size, payload_len */
  return SM_ECHECKSUM;              /* checksum */
}

static void test_corruption(void) {
  sm_basis *b = make_basis(SM_BASIS_LB, 5, 2, 1, 4);
  uint8_t *buf;
  size_t len;
  REQUIRE(sm_basis_serialize(b, &buf, &len, NULL) == SM_OK);
  for (size_t i = 0; i < len; i++) {
    for (int bit = 0; bit < 8; bit += 7) { /* a low and a high bit of every byte */
      sm_basis *r = NULL;
      sm_error err = {0, ""};
      buf[i] ^= (uint8_t)(1u << bit);
      int rc = deser_copy(buf, len, &r, &err);
      buf[i] ^= (uint8_t)(1u << bit);
      int want = i < HDR ? expected_header_error(i) : SM_ECHECKSUM;
      CHECK_MSG(rc == want && r == NULL, "byte %zu bit %d: rc=%d want %d", i, bit, rc, want);
      CHECK(err.code == rc && err.msg[0]);
      sm_basis_destroy(r);
    }
  }
  /* Every byte of the payload replaced by its complement. */
  for (size_t i = HDR; i < len; i++) {
    sm_basis *r = NULL;
    buf[i] = (uint8_t)~buf[i];
    CHECK_MSG(deser_copy(buf, len, &r, NULL) == SM_ECHECKSUM, "byte %zu complemented", i);
    buf[i] = (uint8_t)~buf[i];
    sm_basis_destroy(r);
  }
  free(buf);
  sm_basis_destroy(b);
}

static void test_header_errors(void) {
  sm_basis *b = make_basis(SM_BASIS_LB, 4, 2, 0, 5), *r = NULL;
  uint8_t *buf;
  size_t len;
  sm_error err;
  REQUIRE(sm_basis_serialize(b, &buf, &len, NULL) == SM_OK);
  uint8_t *x = malloc(len + 16);
  REQUIRE(x);

  memcpy(x, buf, len);
  memcpy(x, "SMBASIT", 8);
  CHECK(deser_copy(x, len, &r, &err) == SM_EFORMAT);
  memcpy(x, "smbasis", 8);
  CHECK(deser_copy(x, len, &r, &err) == SM_EFORMAT);

  uint32_t versions[] = {0, 2, 0xFFFFFFFFu};
  for (int v = 0; v < 3; v++) {
    memcpy(x, buf, len);
    put32(x + 8, versions[v]);
    CHECK(deser_copy(x, len, &r, &err) == SM_EVERSION);
  }
  memcpy(x, buf, len);
  put32(x + 12, 40);
  CHECK(deser_copy(x, len, &r, &err) == SM_EFORMAT);

  /* Trailing bytes: as is, and with the header updated to cover them. */
  memcpy(x, buf, len);
  memset(x + len, 0xAB, 16);
  CHECK(deser_copy(x, len + 1, &r, &err) == SM_EFORMAT);
  CHECK(deser_copy(x, len + 16, &r, &err) == SM_EFORMAT);
  reseal(x, len + 16);
  CHECK(deser_copy(x, len + 16, &r, &err) == SM_EFORMAT);
  CHECK(strstr(err.msg, "payload_len") != NULL);
  CHECK(r == NULL);

  CHECK(sm_basis_deserialize(NULL, 0, &r, &err) == SM_EFORMAT);
  CHECK(sm_basis_deserialize(buf, len, NULL, &err) == SM_EINVAL);
  free(x);
  free(buf);
  sm_basis_destroy(b);
}

/* Valid header and checksum, bad content: each field rule, named in the message. */
static void test_field_errors(void) {
  sm_basis *b = make_basis(SM_BASIS_ELASTIC, 4, 3, 1, 6);
  uint8_t *buf;
  size_t len;
  REQUIRE(sm_basis_serialize(b, &buf, &len, NULL) == SM_OK);
  uint8_t *x = malloc(len);
  REQUIRE(x);
  const uint64_t nan = 0x7FF8000000000000ull, inf = 0x7FF0000000000000ull;
  const uint64_t ninf = 0xFFF0000000000000ull;
  struct {
    size_t off; /* payload offset */
    int width;  /* 4 or 8 */
    uint64_t value;
    const char *name;
  } cases[] = {
      {0, 4, 0, "kind"},       {0, 4, 3, "kind"},          {4, 4, 0, "n"},
      {4, 4, 0x80000000u, "n"}, {8, 4, 0, "k"},             {8, 4, 5, "k"},
      {8, 4, 0xFFFFFFFFu, "k"}, {12, 4, 0xFFFFFFFFu, "n_kernel"}, {12, 4, 13, "n_kernel"},
      {16, 4, 0xFFFFFFFFu, "n_components"}, {16, 4, 5, "n_components"},
      {20, 8, nan, "eta"},     {28, 8, inf, "mu"},         {36, 8, ninf, "lambda"},
      {52, 4, 2, "flags"},     {52, 4, 0x80000001u, "flags"}, {52, 4, 0, "payload_len"},
      {4, 4, 5, "payload_len"}, {56, 8, nan, "evals[0]"},   {56 + 8 * 2, 8, inf, "evals[2]"},
      {56 + 8 * 3, 8, nan, "phi[0]"}, {56 + 8 * 14, 8, ninf, "phi[11]"},
      {56 + 8 * 15, 8, inf, "mass[0]"}, {56 + 8 * 19, 8, nan, "gram_L[0]"},
      {len - HDR - 8, 8, 0x7FF0000000000001ull, "gram_L[8]"},
  };
  for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
    sm_basis *r = NULL;
    sm_error err = {0, ""};
    memcpy(x, buf, len);
    if (cases[c].width == 4) put32(x + HDR + cases[c].off, (uint32_t)cases[c].value);
    else put64(x + HDR + cases[c].off, cases[c].value);
    reseal(x, len);
    int rc = deser_copy(x, len, &r, &err);
    CHECK_MSG(rc == SM_EFORMAT && r == NULL, "case %zu (%s): rc=%d", c, cases[c].name, rc);
    CHECK_MSG(strstr(err.msg, cases[c].name) != NULL, "case %zu: message '%s' lacks '%s'", c,
              err.msg, cases[c].name);
    sm_basis_destroy(r);
  }
  free(x);
  free(buf);
  sm_basis_destroy(b);
}

/* A tiny, correctly checksummed buffer claiming n = k = 2^31-1 (2^65 bytes of arrays)
 * must be refused by the size check: SM_EFORMAT, not an attempted allocation. */
static uint8_t *huge_claim(int32_t n, int32_t k, size_t *len) {
  sm_basis *b = make_basis(SM_BASIS_LB, 1, 1, 0, 7);
  uint8_t *buf;
  REQUIRE(sm_basis_serialize(b, &buf, len, NULL) == SM_OK);
  put32(buf + HDR + 4, (uint32_t)n);
  put32(buf + HDR + 8, (uint32_t)k);
  reseal(buf, *len);
  sm_basis_destroy(b);
  return buf;
}

static void test_huge_claims(void) {
  const int32_t claims[][2] = {{INT32_MAX, INT32_MAX}, {INT32_MAX, 1}, {100000, 1000}};
  for (int c = 0; c < 3; c++) {
    size_t len;
    uint8_t *buf = huge_claim(claims[c][0], claims[c][1], &len);
    sm_basis *r = NULL;
    sm_error err;
    int rc = deser_copy(buf, len, &r, &err);
    CHECK_MSG(rc == SM_EFORMAT && r == NULL, "claim %d: rc=%d %s", c, rc, err.msg);
    /* The same with payload_len claiming the full size (checksum still over what is there). */
    put64(buf + 16, (uint64_t)claims[c][0] * (uint64_t)claims[c][1] * 8 + 64);
    rc = deser_copy(buf, len, &r, &err);
    CHECK_MSG(rc == SM_EFORMAT && r == NULL, "claim %d, big payload_len: rc=%d", c, rc);
    put64(buf + 16, UINT64_MAX);
    CHECK(deser_copy(buf, len, &r, &err) == SM_EFORMAT);
    free(buf);
  }
#if !defined(__SANITIZE_ADDRESS__)
  /* Under an address-space limit an allocate-first reader would get SM_ENOMEM (or die);
   * only a reader that checks sizes first still answers SM_EFORMAT. */
  pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    long pages = 0;
    FILE *f = fopen("/proc/self/statm", "r");
    if (!f || fscanf(f, "%ld", &pages) != 1) _exit(0);
    fclose(f);
    struct rlimit rl = {(rlim_t)pages * sysconf(_SC_PAGESIZE) + (64 << 20), 0};
    rl.rlim_max = rl.rlim_cur;
    if (setrlimit(RLIMIT_AS, &rl)) _exit(0);
    size_t len;
    uint8_t *buf = huge_claim(200000, 1000, &len); /* 1.6 GB if believed */
    sm_basis *r = NULL;
    _exit(sm_basis_deserialize(buf, len, &r, NULL) == SM_EFORMAT ? 0 : 1);
  }
  int status = 0;
  REQUIRE(waitpid(pid, &status, 0) == pid);
  CHECK_MSG(WIFEXITED(status) && WEXITSTATUS(status) == 0, "rlimit child status %d", status);
#endif
}

static void test_serialize_rejects(void) {
  sm_basis *b = make_basis(SM_BASIS_LB, 4, 2, 1, 8);
  uint8_t *buf = (uint8_t *)1;
  size_t len = 7;
  sm_error err;
  CHECK(sm_basis_serialize(NULL, &buf, &len, &err) == SM_EINVAL);
  b->phi[5] = NAN;
  CHECK(sm_basis_serialize(b, &buf, &len, &err) == SM_EINVAL);
  CHECK(strstr(err.msg, "phi[5]") != NULL);
  b->phi[5] = 0;
  b->gram_L[3] = -INFINITY;
  CHECK(sm_basis_serialize(b, &buf, &len, &err) == SM_EINVAL);
  b->gram_L[3] = 0;
  b->k = 5;
  CHECK(sm_basis_serialize(b, &buf, &len, &err) == SM_EINVAL);
  b->k = 2;
  b->kind = 0;
  CHECK(sm_basis_serialize(b, &buf, &len, &err) == SM_EINVAL);
  b->kind = SM_BASIS_LB;
  b->lambda = NAN;
  CHECK(sm_basis_serialize(b, &buf, &len, &err) == SM_EINVAL);
  CHECK(buf == (uint8_t *)1 && len == 7); /* untouched on failure */
  b->lambda = 1;
  CHECK(sm_basis_save(b, NULL, &err) == SM_EINVAL);
  sm_basis_destroy(b);
  sm_basis_destroy(NULL);
}

/* Names in dir other than "." and ".."; fills first with one of them. */
static int dir_entries(const char *dir, char *first, size_t cap) {
  DIR *d = opendir(dir);
  int count = 0;
  if (!d) return -1;
  for (struct dirent *e; (e = readdir(d));) {
    if (!strcmp(e->d_name, ".") || !strcmp(e->d_name, "..")) continue;
    if (count++ == 0) snprintf(first, cap, "%s", e->d_name);
  }
  closedir(d);
  return count;
}

static void test_files(void) {
  char dir[512], path[600], name[256];
  snprintf(dir, sizeof dir, "%s/basis_io_%ld", SM_TEST_TMP, (long)getpid());
  REQUIRE(mkdir(dir, 0777) == 0 || errno == EEXIST);
  snprintf(path, sizeof path, "%s/shape.smb", dir);
  sm_basis *a = make_basis(SM_BASIS_ELASTIC, 40, 10, 1, 11);
  sm_basis *b = make_basis(SM_BASIS_LB, 25, 7, 0, 12), *r = NULL;
  sm_error err;

  CHECK_MSG(sm_basis_save(a, path, &err) == SM_OK, "%s", err.msg);
  CHECK(sm_basis_load(path, &r, &err) == SM_OK && r && same_basis(a, r));
  sm_basis_destroy(r);
  CHECK(dir_entries(dir, name, sizeof name) == 1 && !strcmp(name, "shape.smb"));

  /* Overwrite: the new content replaces the old one, still no leftovers. */
  CHECK(sm_basis_save(b, path, &err) == SM_OK);
  CHECK(sm_basis_load(path, &r, &err) == SM_OK && r && same_basis(b, r));
  sm_basis_destroy(r);
  CHECK(dir_entries(dir, name, sizeof name) == 1);

  /* A failing save (rename onto a directory) removes its temp file. */
  char sub[600];
  snprintf(sub, sizeof sub, "%s/subdir", dir);
  REQUIRE(mkdir(sub, 0777) == 0);
  CHECK(sm_basis_save(b, sub, &err) == SM_EIO && strstr(err.msg, "subdir"));
  CHECK(dir_entries(dir, name, sizeof name) == 2);
  CHECK(sm_basis_load(sub, &r, &err) == SM_EIO && r == NULL);
  rmdir(sub);

  /* A corrupted file is refused, with the path in the message. */
  FILE *f = fopen(path, "r+b");
  REQUIRE(f);
  REQUIRE(fseek(f, 100, SEEK_SET) == 0);
  int byte = fgetc(f);
  REQUIRE(byte != EOF && fseek(f, 100, SEEK_SET) == 0);
  fputc(byte ^ 0xFF, f);
  REQUIRE(fclose(f) == 0);
  CHECK(sm_basis_load(path, &r, &err) == SM_ECHECKSUM && r == NULL &&
        strstr(err.msg, "shape.smb"));

  /* Relative path (directory of the file is "."). */
  char cwd[1024];
  REQUIRE(getcwd(cwd, sizeof cwd));
  REQUIRE(chdir(dir) == 0);
  CHECK(sm_basis_save(a, "rel.smb", &err) == SM_OK);
  CHECK(sm_basis_load("rel.smb", &r, &err) == SM_OK && r && same_basis(a, r));
  sm_basis_destroy(r);
  unlink("rel.smb");
  REQUIRE(chdir(cwd) == 0);

  /* Missing file, missing directory. */
  snprintf(path, sizeof path, "%s/absent.smb", dir);
  CHECK(sm_basis_load(path, &r, &err) == SM_EIO && r == NULL && strstr(err.msg, "absent"));
  snprintf(path, sizeof path, "%s/no_such_dir/x.smb", dir);
  CHECK(sm_basis_save(a, path, &err) == SM_EIO && err.msg[0]);
  CHECK(sm_basis_load(path, &r, &err) == SM_EIO);

  /* Over the size cap: a sparse file, refused before it is read. */
  snprintf(path, sizeof path, "%s/huge.smb", dir);
  f = fopen(path, "wb");
  REQUIRE(f);
  int sparse_ok = ftruncate(fileno(f), (off_t)17 << 30) == 0;
  fclose(f);
  if (sparse_ok) CHECK(sm_basis_load(path, &r, &err) == SM_ELIMIT && r == NULL);
  unlink(path);

  snprintf(path, sizeof path, "%s/shape.smb", dir);
  unlink(path);
  CHECK(dir_entries(dir, name, sizeof name) == 0);
  CHECK(rmdir(dir) == 0);
  sm_basis_destroy(a);
  sm_basis_destroy(b);
}

/* Reference: the byte string the format comment defines, hashed in one piece. */
static uint64_t ref_mesh_hash(const sm_mesh *m) {
  size_t len = 8 + 24 * (size_t)m->nv + 12 * (size_t)m->nf;
  uint8_t *s = malloc(len), *p = s;
  REQUIRE(s);
  put32(p, (uint32_t)m->nv);
  put32(p + 4, (uint32_t)m->nf);
  p += 8;
  for (int i = 0; i < 3 * m->nv; i++, p += 8) {
    uint64_t u;
    memcpy(&u, &m->V[i], 8);
    put64(p, u);
  }
  for (int i = 0; i < 3 * m->nf; i++, p += 4) put32(p, (uint32_t)m->F[i]);
  uint64_t h = XXH3_64bits(s, len);
  free(s);
  return h;
}

static void test_mesh_hash(void) {
  sm_mesh *m = grid_mesh(30), *c = NULL; /* 900 vertices: several hash chunks */
  REQUIRE(sm_mesh_copy(m, &c, NULL) == SM_OK);
  uint64_t h = sm_mesh_hash(m);
  CHECK(h == sm_mesh_hash(c));
  CHECK(h == ref_mesh_hash(m));

  c->V[1000] = nextafter(c->V[1000], INFINITY);
  CHECK(sm_mesh_hash(c) != h);
  c->V[1000] = m->V[1000];
  CHECK(sm_mesh_hash(c) == h);

  c->V[3 * c->nv - 1] = nextafter(c->V[3 * c->nv - 1], -INFINITY);
  CHECK(sm_mesh_hash(c) != h);
  c->V[3 * c->nv - 1] = m->V[3 * m->nv - 1];

  int32_t f = c->F[5];
  c->F[5] = (f + 1) % c->nv;
  CHECK(sm_mesh_hash(c) != h);
  c->F[5] = f;
  c->F[3 * c->nf - 1] ^= 1;
  CHECK(sm_mesh_hash(c) != h);
  CHECK(sm_mesh_hash(c) == ref_mesh_hash(c));
  c->F[3 * c->nf - 1] ^= 1;

  /* Bit patterns, not values: -0.0 and 0.0 differ. */
  sm_mesh *z = NULL, *zn = NULL;
  REQUIRE(sm_mesh_alloc(1, 1, NULL, &z, NULL) == SM_OK);
  REQUIRE(sm_mesh_alloc(1, 1, NULL, &zn, NULL) == SM_OK);
  for (int i = 0; i < 3; i++) {
    z->V[i] = 0.0;
    zn->V[i] = i == 1 ? -0.0 : 0.0;
    z->F[i] = zn->F[i] = 0;
  }
  CHECK(sm_mesh_hash(z) != sm_mesh_hash(zn));
  CHECK(sm_mesh_hash(zn) == ref_mesh_hash(zn));
  sm_mesh_destroy(z);
  sm_mesh_destroy(zn);
  sm_mesh_destroy(c);
  sm_mesh_destroy(m);
}

int main(void) {
  test_roundtrip();
  test_layout();
  test_truncation();
  test_corruption();
  test_header_errors();
  test_field_errors();
  test_huge_claims();
  test_serialize_rejects();
  test_files();
  test_mesh_hash();
  return sm_test_finish();
}
