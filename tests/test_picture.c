/* test_picture: pictures of a match (clients/sm_picture.h and the CLI's --ply-out,
 * --png-out and render).
 *   1. Colours through a map: a permuted copy gets exactly the source colours at the
 *      permuted places; a map that reaches one vertex colours every connected vertex
 *      with that colour; a map entry outside the target is refused.
 *   2. The CLI on a blob and a permuted copy of it (local match): both PLY files parse
 *      back (counts, colours), every target vertex with one preimage has its preimage's
 *      colour; the PNG decodes (signature, IHDR, every chunk's CRC, zlib stream, row
 *      filters) and both halves show a mesh in many colours; `render` of the written map
 *      gives the same PNG bytes.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <zlib.h>

#include "sm_picture.h"
#include "sm_synth.h"
#include "sm_test.h"

static int32_t *permutation(int32_t n) { /* v -> (v * 7919 + 13) mod n, a bijection for n prime to 7919 */
  int32_t *p = malloc((size_t)n * sizeof *p);
  for (int32_t v = 0; v < n; v++) p[v] = (int32_t)(((int64_t)v * 7919 + 13) % n);
  return p;
}

static sm_mesh *permuted_copy(const sm_mesh *m, const int32_t *perm) {
  sm_mesh *c = NULL;
  REQUIRE(sm_mesh_alloc(m->nv, m->nf, NULL, &c, NULL) == 0);
  for (int32_t v = 0; v < m->nv; v++) memcpy(c->V + 3 * perm[v], m->V + 3 * v, 3 * sizeof(double));
  for (int32_t i = 0; i < 3 * m->nf; i++) c->F[i] = perm[m->F[i]];
  return c;
}

static void test_colors(void) {
  const double st[3] = {1, 1, 1};
  sm_mesh *a = NULL;
  REQUIRE(sm_synth_blob(2, 0.3, 3, st, &a, NULL) == 0);
  int32_t *perm = permutation(a->nv);
  sm_mesh *b = permuted_copy(a, perm);
  uint8_t *ca = malloc(3 * (size_t)a->nv), *cb = malloc(3 * (size_t)b->nv);
  sm_pic_source_colors(a, ca);
  int32_t reached = -1, same = 0, distinct = 0;
  REQUIRE(sm_pic_target_colors(b, perm, a->nv, ca, cb, &reached, NULL) == 0);
  CHECK(reached == b->nv);
  for (int32_t v = 0; v < a->nv; v++) same += !memcmp(ca + 3 * v, cb + 3 * perm[v], 3);
  CHECK_MSG(same == a->nv, "%d of %d", same, a->nv);
  for (int32_t v = 1; v < a->nv; v++) distinct += memcmp(ca + 3 * v, ca, 3) != 0;
  CHECK(distinct > a->nv / 2); /* a field, not one colour */

  /* everything to target vertex 5: it takes the mean colour, its neighbours take it too */
  int32_t *collapse = malloc((size_t)a->nv * sizeof *collapse);
  unsigned sum[3] = {0, 0, 0};
  for (int32_t v = 0; v < a->nv; v++) {
    collapse[v] = v == 0 ? -1 : 5; /* -1: a vertex cleaning dropped, skipped */
    for (int k = 0; k < 3 && v; k++) sum[k] += ca[3 * v + k];
  }
  REQUIRE(sm_pic_target_colors(b, collapse, a->nv, ca, cb, &reached, NULL) == 0);
  CHECK(reached == 1);
  for (int k = 0; k < 3; k++)
    CHECK_MSG(cb[3 * 5 + k] == (sum[k] + (a->nv - 1) / 2) / (a->nv - 1), "channel %d", k);
  int32_t flat = 0;
  for (int32_t v = 0; v < b->nv; v++) flat += !memcmp(cb + 3 * v, cb + 3 * 5, 3);
  CHECK(flat == b->nv);

  collapse[3] = b->nv; /* outside the target */
  sm_error err;
  CHECK(sm_pic_target_colors(b, collapse, a->nv, ca, cb, NULL, &err) == SM_ERANGE);
  free(collapse);
  free(ca);
  free(cb);
  free(perm);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
}

#ifdef SM_CLI_BIN
static void write_off(const char *path, const sm_mesh *m) {
  FILE *f = fopen(path, "w");
  REQUIRE(f);
  fprintf(f, "OFF\n%d %d 0\n", m->nv, m->nf);
  for (int32_t v = 0; v < m->nv; v++)
    fprintf(f, "%.17g %.17g %.17g\n", m->V[3 * v], m->V[3 * v + 1], m->V[3 * v + 2]);
  for (int32_t t = 0; t < m->nf; t++)
    fprintf(f, "3 %d %d %d\n", m->F[3 * t], m->F[3 * t + 1], m->F[3 * t + 2]);
  REQUIRE(fclose(f) == 0);
}

/* Reads the ASCII PLY the CLI writes: the vertex count, x y z r g b per vertex (rgb out),
 * the face count. Returns the vertex count, -1 when the file does not parse. */
static int32_t read_ply(const char *path, uint8_t **rgb, int32_t *nf) {
  FILE *f = fopen(path, "r");
  if (!f) return -1;
  char line[256];
  int32_t nv = -1, props = 0, colors = 0;
  *nf = -1;
  while (fgets(line, sizeof line, f) && strcmp(line, "end_header\n")) {
    if (sscanf(line, "element vertex %d", &nv) == 1) continue;
    if (sscanf(line, "element face %d", nf) == 1) continue;
    if (!strncmp(line, "property ", 9) && *nf < 0) props++;
    if (!strcmp(line, "property uchar red\n") || !strcmp(line, "property uchar green\n") ||
        !strcmp(line, "property uchar blue\n"))
      colors++;
  }
  if (nv < 0 || props != 6 || colors != 3) {
    fclose(f);
    return -1;
  }
  *rgb = malloc(3 * (size_t)nv + 1);
  for (int32_t v = 0; v < nv; v++) {
    double x[3];
    unsigned c[3];
    if (fscanf(f, "%lf %lf %lf %u %u %u", &x[0], &x[1], &x[2], &c[0], &c[1], &c[2]) != 6 ||
        c[0] > 255 || c[1] > 255 || c[2] > 255) {
      fclose(f);
      return -1;
    }
    for (int k = 0; k < 3; k++) (*rgb)[3 * v + k] = (uint8_t)c[k];
  }
  int32_t faces = 0, k, i0, i1, i2;
  while (fscanf(f, "%d %d %d %d", &k, &i0, &i1, &i2) == 4 && k == 3 && i0 >= 0 && i0 < nv &&
         i1 >= 0 && i1 < nv && i2 >= 0 && i2 < nv)
    faces++;
  int ok = feof(f) && faces == *nf;
  fclose(f);
  return ok ? nv : -1;
}

static uint8_t *read_all(const char *path, size_t *len) {
  FILE *f = fopen(path, "rb");
  if (!f) return NULL;
  fseek(f, 0, SEEK_END);
  *len = (size_t)ftell(f);
  rewind(f);
  uint8_t *b = malloc(*len + 1);
  if (fread(b, 1, *len, f) != *len) {
    free(b);
    b = NULL;
  }
  fclose(f);
  return b;
}

static uint32_t rd32(const uint8_t *p) {
  return (uint32_t)p[0] << 24 | (uint32_t)p[1] << 16 | (uint32_t)p[2] << 8 | p[3];
}

static int paeth(int a, int b, int c) {
  int p = a + b - c, pa = abs(p - a), pb = abs(p - b), pc = abs(p - c);
  return pa <= pb && pa <= pc ? a : pb <= pc ? b : c;
}

/* Decodes an 8-bit RGB, non-interlaced PNG (all five row filters), checking the chunk
 * CRCs. Returns the pixels (w * h * 3) or NULL. */
static uint8_t *decode_png(const uint8_t *buf, size_t len, uint32_t *w, uint32_t *h) {
  static const uint8_t sig[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  if (len < 8 || memcmp(buf, sig, 8)) return NULL;
  uint8_t *z = NULL;
  size_t zlen = 0, at = 8;
  int ihdr = 0, iend = 0;
  while (at + 12 <= len && !iend) {
    uint32_t n = rd32(buf + at);
    if (n > len - at - 12) break;
    const uint8_t *type = buf + at + 4, *data = buf + at + 8;
    uLong crc = crc32(crc32(0L, Z_NULL, 0), type, 4 + n);
    CHECK_MSG(crc == rd32(data + n), "CRC of chunk %.4s", (const char *)type);
    if (!memcmp(type, "IHDR", 4) && n == 13) {
      *w = rd32(data), *h = rd32(data + 4);
      ihdr = data[8] == 8 && data[9] == 2 && !data[10] && !data[11] && !data[12];
    } else if (!memcmp(type, "IDAT", 4)) {
      z = realloc(z, zlen + n + 1);
      memcpy(z + zlen, data, n);
      zlen += n;
    } else if (!memcmp(type, "IEND", 4)) iend = 1;
    at += 12 + n;
  }
  if (!ihdr || !iend || !z || *w == 0 || *h == 0 || *w > 8192 || *h > 8192) {
    free(z);
    return NULL;
  }
  size_t stride = (size_t)*w * 3;
  uLongf rawlen = (uLongf)(*h * (stride + 1));
  uint8_t *raw = malloc(rawlen), *px = malloc(*h * stride);
  int ok = uncompress(raw, &rawlen, z, zlen) == Z_OK && rawlen == *h * (stride + 1);
  for (uint32_t y = 0; ok && y < *h; y++) {
    uint8_t ft = raw[y * (stride + 1)], *src = raw + y * (stride + 1) + 1, *row = px + y * stride;
    const uint8_t *up = y ? row - stride : NULL;
    for (size_t i = 0; i < stride; i++) {
      int a = i >= 3 ? row[i - 3] : 0, b = up ? up[i] : 0, c = up && i >= 3 ? up[i - 3] : 0;
      int pred = ft == 0 ? 0 : ft == 1 ? a : ft == 2 ? b : ft == 3 ? (a + b) / 2 : paeth(a, b, c);
      row[i] = (uint8_t)(src[i] + pred);
    }
    ok = ft <= 4;
  }
  free(raw);
  free(z);
  if (!ok) {
    free(px);
    return NULL;
  }
  return px;
}

/* Pixels that are not the white background in columns [x0, x1), and how many distinct
 * colours (quantized to 5 bits a channel) they have. */
static void panel_stats(const uint8_t *px, uint32_t w, uint32_t h, uint32_t x0, uint32_t x1,
                        long *inked, int *colors) {
  static uint8_t seen[1 << 15];
  memset(seen, 0, sizeof seen);
  *inked = 0;
  *colors = 0;
  for (uint32_t y = 0; y < h; y++)
    for (uint32_t x = x0; x < x1; x++) {
      const uint8_t *p = px + 3 * ((size_t)y * w + x);
      if (p[0] == 255 && p[1] == 255 && p[2] == 255) continue;
      (*inked)++;
      int q = (p[0] >> 3) << 10 | (p[1] >> 3) << 5 | p[2] >> 3;
      *colors += !seen[q];
      seen[q] = 1;
    }
}

static void check_png(const char *path) {
  size_t len = 0;
  uint8_t *buf = read_all(path, &len);
  REQUIRE(buf);
  uint32_t w = 0, h = 0;
  uint8_t *px = decode_png(buf, len, &w, &h);
  CHECK_MSG(px != NULL, "%s does not decode", path);
  CHECK(w == 400 && h == 200); /* --size 400,200 */
  for (int half = 0; px && half < 2; half++) {
    long inked;
    int colors;
    panel_stats(px, w, h, half * w / 2, (half + 1) * w / 2, &inked, &colors);
    CHECK_MSG(inked > (long)w * h / 20, "half %d: %ld pixels drawn", half, inked);
    CHECK_MSG(colors > 100, "half %d: %d colours", half, colors);
  }
  free(px);
  free(buf);
}

static int run(const char *cmd) {
  fprintf(stderr, "+ %s\n", cmd);
  return system(cmd);
}

static void test_cli(void) {
  const double st[3] = {1, 1.2, 0.9};
  sm_mesh *a = NULL;
  REQUIRE(sm_synth_blob(3, 0.4, 5, st, &a, NULL) == 0);
  int32_t *perm = permutation(a->nv);
  sm_mesh *b = permuted_copy(a, perm);
  const char *d = SM_TEST_TMP;
  char pa[512], pb[512], cmd[4096], path[600];
  snprintf(pa, sizeof pa, "%s/picture_a.off", d);
  snprintf(pb, sizeof pb, "%s/picture_b.off", d);
  write_off(pa, a);
  write_off(pb, b);
  snprintf(cmd, sizeof cmd, "%s match %s %s --local -o %s/picture_map.txt --ply-out "
           "%s/picture --png-out %s/picture.png --size 400,200", SM_CLI_BIN, pa, pb, d, d, d);
  REQUIRE(run(cmd) == 0);

  /* the map the CLI wrote, and each target vertex's preimages */
  int32_t *map = malloc((size_t)a->nv * sizeof *map), *count = calloc((size_t)b->nv, sizeof *count);
  int32_t *pre = malloc((size_t)b->nv * sizeof *pre);
  snprintf(path, sizeof path, "%s/picture_map.txt", d);
  FILE *f = fopen(path, "r");
  REQUIRE(f);
  int32_t exact = 0;
  for (int32_t v = 0; v < a->nv; v++) {
    REQUIRE(fscanf(f, "%d", &map[v]) == 1 && map[v] >= 0 && map[v] < b->nv);
    count[map[v]]++;
    pre[map[v]] = v;
    exact += map[v] == perm[v];
  }
  fclose(f);
  CHECK_MSG(exact >= a->nv * 95 / 100, "%d of %d matched to their copy", exact, a->nv);

  uint8_t *cs = NULL, *ct = NULL;
  int32_t fs, ft;
  snprintf(path, sizeof path, "%s/picture_src.ply", d);
  CHECK(read_ply(path, &cs, &fs) == a->nv && fs == a->nf);
  snprintf(path, sizeof path, "%s/picture_tgt.ply", d);
  CHECK(read_ply(path, &ct, &ft) == b->nv && ft == b->nf);
  int32_t single = 0, agree = 0;
  for (int32_t j = 0; cs && ct && j < b->nv; j++)
    if (count[j] == 1) {
      single++;
      agree += !memcmp(ct + 3 * j, cs + 3 * pre[j], 3);
    }
  CHECK_MSG(single >= b->nv * 95 / 100, "%d of %d target vertices with one preimage", single, b->nv);
  CHECK_MSG(agree == single, "%d of %d have their preimage's colour", agree, single);

  snprintf(path, sizeof path, "%s/picture.png", d);
  check_png(path);
  /* render: the same picture from the map file */
  snprintf(cmd, sizeof cmd, "%s render %s %s --map %s/picture_map.txt -o %s/picture_r.png "
           "--size 400,200", SM_CLI_BIN, pa, pb, d, d);
  CHECK(run(cmd) == 0);
  size_t l1 = 0, l2 = 0;
  uint8_t *p1 = read_all(path, &l1);
  snprintf(path, sizeof path, "%s/picture_r.png", d);
  uint8_t *p2 = read_all(path, &l2);
  CHECK(p1 && p2 && l1 == l2 && !memcmp(p1, p2, l1));
  snprintf(cmd, sizeof cmd, "%s render %s %s --map %s/picture_map.txt 2>/dev/null", SM_CLI_BIN,
           pa, pb, d);
  CHECK(WEXITSTATUS(run(cmd)) == 2); /* no output named: usage */
  free(p1);
  free(p2);
  free(cs);
  free(ct);
  free(map);
  free(count);
  free(pre);
  free(perm);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
}
#endif

int main(void) {
  test_colors();
#ifdef SM_CLI_BIN
  test_cli();
#endif
  return sm_test_finish();
}
