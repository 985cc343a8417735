/* sm_picture: vertex colours through a map, PLY and PNG writers, a z-buffer rasterizer.
 * See sm_picture.h for the contract and for why the target is coloured through the map
 * shown rather than through an inverse map. */
#include "sm_picture.h"

#include <errno.h>
#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <zlib.h>

#define PIC_SUPERSAMPLE 2 /* 2 x 2 samples per pixel: edges without stair steps */

static void bbox(const sm_mesh *m, double lo[3], double hi[3]) {
  for (int k = 0; k < 3; k++) lo[k] = DBL_MAX, hi[k] = -DBL_MAX;
  for (int32_t v = 0; v < m->nv; v++)
    for (int k = 0; k < 3; k++) {
      double x = m->V[3 * v + k];
      if (x < lo[k]) lo[k] = x;
      if (x > hi[k]) hi[k] = x;
    }
}

void sm_pic_source_colors(const sm_mesh *m, uint8_t *rgb) {
  double lo[3], hi[3];
  bbox(m, lo, hi);
  for (int32_t v = 0; v < m->nv; v++)
    for (int k = 0; k < 3; k++) {
      double ext = hi[k] - lo[k], t = ext > 0 ? (m->V[3 * v + k] - lo[k]) / ext : 0.5;
      rgb[3 * v + k] = (uint8_t)lrint(40 + 215 * t);
    }
}

/* Vertex adjacency of m's faces as CSR (off: nv + 1 entries, adj: the neighbours). */
static int adjacency(const sm_mesh *m, int32_t **off, int32_t **adj) {
  *off = calloc((size_t)m->nv + 1, sizeof **off);
  *adj = malloc((size_t)m->nf * 6 * sizeof **adj + 1);
  if (!*off || !*adj) return SM_ENOMEM;
  for (int64_t i = 0; i < 3 * (int64_t)m->nf; i++) (*off)[m->F[i] + 1] += 2;
  for (int32_t v = 0; v < m->nv; v++) (*off)[v + 1] += (*off)[v];
  int32_t *fill = malloc((size_t)m->nv * sizeof *fill + 1);
  if (!fill) return SM_ENOMEM;
  memcpy(fill, *off, (size_t)m->nv * sizeof *fill);
  for (int32_t f = 0; f < m->nf; f++)
    for (int c = 0; c < 3; c++) {
      int32_t v = m->F[3 * f + c];
      (*adj)[fill[v]++] = m->F[3 * f + (c + 1) % 3];
      (*adj)[fill[v]++] = m->F[3 * f + (c + 2) % 3];
    }
  free(fill);
  return 0;
}

/* Breadth-first from every reached vertex at once: an unreached vertex takes the colour
 * of the reached vertex it is found from, i.e. of (one of) its nearest in edge hops. */
static int fill_unreached(const sm_mesh *b, uint8_t *rgb, uint8_t *reached) {
  int32_t *off = NULL, *adj = NULL, *queue = malloc((size_t)b->nv * sizeof *queue + 1);
  int rc = queue ? adjacency(b, &off, &adj) : SM_ENOMEM;
  if (!rc) {
    int32_t head = 0, tail = 0;
    for (int32_t v = 0; v < b->nv; v++)
      if (reached[v]) queue[tail++] = v;
    while (head < tail) {
      int32_t v = queue[head++];
      for (int32_t j = off[v]; j < off[v + 1]; j++) {
        int32_t w = adj[j];
        if (reached[w]) continue;
        reached[w] = 1;
        memcpy(rgb + 3 * w, rgb + 3 * v, 3);
        queue[tail++] = w;
      }
    }
  }
  free(queue);
  free(off);
  free(adj);
  return rc;
}

int sm_pic_target_colors(const sm_mesh *b, const int32_t *map, int32_t na,
                         const uint8_t *rgb_a, uint8_t *rgb_b, int32_t *n_reached,
                         sm_error *err) {
  uint32_t *sum = calloc((size_t)b->nv * 4 + 1, sizeof *sum); /* r, g, b, count */
  uint8_t *reached = calloc((size_t)b->nv + 1, 1);
  if (!sum || !reached) {
    free(sum);
    free(reached);
    return sm_error_set(err, SM_ENOMEM, "picture: no memory for %d target vertices", b->nv);
  }
  int rc = 0;
  for (int32_t i = 0; i < na && !rc; i++) {
    int32_t j = map[i];
    if (j < -1 || j >= b->nv)
      rc = sm_error_set(err, SM_ERANGE, "picture: map line %d names vertex %d, the target "
                        "has %d", i + 1, j, b->nv);
    else if (j >= 0) {
      for (int k = 0; k < 3; k++) sum[4 * j + k] += rgb_a[3 * i + k];
      sum[4 * j + 3]++;
    }
  }
  int32_t n = 0;
  for (int32_t j = 0; j < b->nv && !rc; j++) {
    uint32_t c = sum[4 * j + 3];
    reached[j] = c > 0;
    n += reached[j];
    for (int k = 0; k < 3; k++) rgb_b[3 * j + k] = c ? (uint8_t)((sum[4 * j + k] + c / 2) / c) : 128;
  }
  if (!rc && fill_unreached(b, rgb_b, reached))
    rc = sm_error_set(err, SM_ENOMEM, "picture: no memory for the target's edges");
  if (n_reached) *n_reached = n;
  free(sum);
  free(reached);
  return rc;
}

int sm_pic_write_ply(const char *path, const sm_mesh *m, const uint8_t *rgb, sm_error *err) {
  FILE *f = fopen(path, "w");
  if (!f) return sm_error_set(err, SM_EIO, "%s: %s", path, strerror(errno));
  fprintf(f, "ply\nformat ascii 1.0\ncomment shapematch: colours of a point map\n"
             "element vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
             "property uchar red\nproperty uchar green\nproperty uchar blue\n"
             "element face %d\nproperty list uchar int vertex_indices\nend_header\n",
          m->nv, m->nf);
  for (int32_t v = 0; v < m->nv; v++)
    fprintf(f, "%.9g %.9g %.9g %u %u %u\n", m->V[3 * v], m->V[3 * v + 1], m->V[3 * v + 2],
            rgb[3 * v], rgb[3 * v + 1], rgb[3 * v + 2]);
  for (int32_t t = 0; t < m->nf; t++)
    fprintf(f, "3 %d %d %d\n", m->F[3 * t], m->F[3 * t + 1], m->F[3 * t + 2]);
  int bad = ferror(f);
  if (fclose(f) || bad) return sm_error_set(err, SM_EIO, "%s: write failed", path);
  return 0;
}

void sm_pic_view_default(sm_pic_view *v) {
  v->width = 960;
  v->height = 480;
  v->azimuth_deg = 30;
  v->elevation_deg = 20;
}

/* ---- the rasterizer ---- */

typedef struct canvas {
  int w, h;
  uint8_t *rgb;
  float *depth; /* larger = nearer the viewer; -FLT_MAX = empty */
} canvas;

/* Vertex positions in view space: rotated about y by the azimuth, then about x by the
 * elevation; the viewer looks down -z, so z grows towards it. */
static void view_transform(const sm_mesh *m, const sm_pic_view *vw, double *P) {
  double lo[3], hi[3], c[3];
  bbox(m, lo, hi);
  for (int k = 0; k < 3; k++) c[k] = 0.5 * (lo[k] + hi[k]);
  double az = vw->azimuth_deg * M_PI / 180, el = vw->elevation_deg * M_PI / 180;
  double ca = cos(az), sa = sin(az), ce = cos(el), se = sin(el);
  for (int32_t v = 0; v < m->nv; v++) {
    double x = m->V[3 * v] - c[0], y = m->V[3 * v + 1] - c[1], z = m->V[3 * v + 2] - c[2];
    double x1 = ca * x + sa * z, z1 = -sa * x + ca * z;
    P[3 * v] = x1;
    P[3 * v + 1] = ce * y - se * z1;
    P[3 * v + 2] = se * y + ce * z1;
  }
}

/* Lambert with a light from the viewer's upper left; both sides lit alike (|n.l|), so a
 * mesh with inconsistent orientation does not render black. */
static double shade(const double *p0, const double *p1, const double *p2) {
  double e1[3], e2[3], n[3];
  for (int k = 0; k < 3; k++) e1[k] = p1[k] - p0[k], e2[k] = p2[k] - p0[k];
  n[0] = e1[1] * e2[2] - e1[2] * e2[1];
  n[1] = e1[2] * e2[0] - e1[0] * e2[2];
  n[2] = e1[0] * e2[1] - e1[1] * e2[0];
  double len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
  if (!(len > 0)) return 0.3;
  static const double L[3] = {-0.3162, 0.3162, 0.8944}; /* (-1, 1, 2.83) normalized */
  double d = fabs(n[0] * L[0] + n[1] * L[1] + n[2] * L[2]) / len;
  return 0.3 + 0.7 * d;
}

/* One triangle, screen coordinates s (x, y, depth per corner), corner colours col. */
static void raster_triangle(canvas *cv, const double s[3][3], const uint8_t *col[3],
                            double light) {
  double area = (s[1][0] - s[0][0]) * (s[2][1] - s[0][1]) -
                (s[2][0] - s[0][0]) * (s[1][1] - s[0][1]);
  if (fabs(area) < 1e-12) return;
  int x0 = (int)floor(fmin(s[0][0], fmin(s[1][0], s[2][0])));
  int x1 = (int)ceil(fmax(s[0][0], fmax(s[1][0], s[2][0])));
  int y0 = (int)floor(fmin(s[0][1], fmin(s[1][1], s[2][1])));
  int y1 = (int)ceil(fmax(s[0][1], fmax(s[1][1], s[2][1])));
  if (x0 < 0) x0 = 0;
  if (y0 < 0) y0 = 0;
  if (x1 > cv->w - 1) x1 = cv->w - 1;
  if (y1 > cv->h - 1) y1 = cv->h - 1;
  for (int y = y0; y <= y1; y++)
    for (int x = x0; x <= x1; x++) {
      double px = x + 0.5, py = y + 0.5, w[3];
      for (int i = 0; i < 3; i++) {
        const double *a = s[(i + 1) % 3], *b = s[(i + 2) % 3];
        w[i] = ((b[0] - a[0]) * (py - a[1]) - (px - a[0]) * (b[1] - a[1])) / area;
      }
      if (w[0] < 0 || w[1] < 0 || w[2] < 0) continue;
      float z = (float)(w[0] * s[0][2] + w[1] * s[1][2] + w[2] * s[2][2]);
      size_t at = (size_t)y * cv->w + x;
      if (z <= cv->depth[at]) continue;
      cv->depth[at] = z;
      for (int k = 0; k < 3; k++) {
        double c = light * (w[0] * col[0][k] + w[1] * col[1][k] + w[2] * col[2][k]);
        cv->rgb[3 * at + k] = (uint8_t)(c > 255 ? 255 : c + 0.5);
      }
    }
}

/* Draws m into the panel [px, px + pw) x [0, ph) of the canvas, scaled to 90% of it. */
static int draw_mesh(canvas *cv, int px, int pw, int ph, const sm_mesh *m, const uint8_t *rgb,
                     const sm_pic_view *vw) {
  double *P = malloc((size_t)m->nv * 3 * sizeof *P + 1);
  if (!P) return SM_ENOMEM;
  view_transform(m, vw, P);
  double lo[2] = {DBL_MAX, DBL_MAX}, hi[2] = {-DBL_MAX, -DBL_MAX};
  for (int32_t v = 0; v < m->nv; v++)
    for (int k = 0; k < 2; k++) {
      lo[k] = fmin(lo[k], P[3 * v + k]);
      hi[k] = fmax(hi[k], P[3 * v + k]);
    }
  double ex = fmax(hi[0] - lo[0], 1e-300), ey = fmax(hi[1] - lo[1], 1e-300);
  double sc = 0.9 * fmin(pw / ex, ph / ey);
  double cx = px + 0.5 * pw, cy = 0.5 * ph, mx = 0.5 * (lo[0] + hi[0]), my = 0.5 * (lo[1] + hi[1]);
  for (int32_t t = 0; t < m->nf; t++) {
    double s[3][3];
    const uint8_t *col[3];
    const int32_t *f = m->F + 3 * t;
    for (int i = 0; i < 3; i++) {
      const double *p = P + 3 * f[i];
      s[i][0] = cx + sc * (p[0] - mx);
      s[i][1] = cy - sc * (p[1] - my); /* image rows grow downwards */
      s[i][2] = p[2];
      col[i] = rgb + 3 * f[i];
    }
    raster_triangle(cv, s, col, shade(P + 3 * f[0], P + 3 * f[1], P + 3 * f[2]));
  }
  free(P);
  return 0;
}

/* ---- PNG (ISO/IEC 15948): signature, IHDR, one IDAT, IEND ---- */

static void be32(uint8_t *p, uint32_t v) {
  p[0] = (uint8_t)(v >> 24), p[1] = (uint8_t)(v >> 16), p[2] = (uint8_t)(v >> 8), p[3] = (uint8_t)v;
}

static int png_chunk(FILE *f, const char *type, const uint8_t *data, uint32_t len) {
  uint8_t hdr[8], crc[4];
  be32(hdr, len);
  memcpy(hdr + 4, type, 4);
  uLong c = crc32(crc32(0L, Z_NULL, 0), hdr + 4, 4); /* the CRC covers type and data */
  if (len) c = crc32(c, data, len);
  be32(crc, (uint32_t)c);
  return fwrite(hdr, 1, 8, f) != 8 || (len && fwrite(data, 1, len, f) != len) ||
         fwrite(crc, 1, 4, f) != 4;
}

/* Each row gets the filter (none, sub or up) with the smallest sum of |bytes| as signed
 * values, the usual heuristic: smooth shading then compresses to a fraction. */
static void png_filter_rows(const uint8_t *rgb, int w, int h, uint8_t *out) {
  size_t stride = (size_t)w * 3;
  for (int y = 0; y < h; y++) {
    const uint8_t *row = rgb + y * stride, *up = y ? row - stride : NULL;
    uint8_t *dst = out + y * (stride + 1);
    long best = -1;
    for (int ft = 0; ft < 3; ft++) {
      uint8_t tmp[3 * 8192];
      long cost = 0;
      for (size_t i = 0; i < stride; i++) {
        uint8_t pred = ft == 1 ? (i >= 3 ? row[i - 3] : 0) : ft == 2 ? (up ? up[i] : 0) : 0;
        tmp[i] = (uint8_t)(row[i] - pred);
        cost += tmp[i] < 128 ? tmp[i] : 256 - tmp[i];
      }
      if (best < 0 || cost < best) {
        best = cost;
        dst[0] = (uint8_t)ft;
        memcpy(dst + 1, tmp, stride);
      }
    }
  }
}

static int write_png(const char *path, const uint8_t *rgb, int w, int h, sm_error *err) {
  size_t raw_len = (size_t)h * ((size_t)w * 3 + 1);
  uLongf z_len = compressBound(raw_len);
  uint8_t *raw = malloc(raw_len), *z = malloc(z_len);
  if (!raw || !z) {
    free(raw);
    free(z);
    return sm_error_set(err, SM_ENOMEM, "picture: no memory for a %d x %d PNG", w, h);
  }
  png_filter_rows(rgb, w, h, raw);
  int rc = compress2(z, &z_len, raw, raw_len, 9) == Z_OK ? 0 : SM_ENOMEM;
  free(raw);
  if (rc) {
    free(z);
    return sm_error_set(err, rc, "picture: zlib could not compress the PNG");
  }
  static const uint8_t sig[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  uint8_t ihdr[13] = {0};
  be32(ihdr, (uint32_t)w);
  be32(ihdr + 4, (uint32_t)h);
  ihdr[8] = 8; /* bit depth; colour type 2 = RGB; compression, filter, interlace 0 */
  ihdr[9] = 2;
  FILE *f = fopen(path, "wb");
  if (!f) {
    free(z);
    return sm_error_set(err, SM_EIO, "%s: %s", path, strerror(errno));
  }
  int bad = fwrite(sig, 1, 8, f) != 8 || png_chunk(f, "IHDR", ihdr, 13) ||
            png_chunk(f, "IDAT", z, (uint32_t)z_len) || png_chunk(f, "IEND", NULL, 0);
  free(z);
  if (fclose(f) || bad) return sm_error_set(err, SM_EIO, "%s: write failed", path);
  return 0;
}

/* Averages each S x S block of the supersampled canvas into one pixel. */
static void downsample(const canvas *cv, uint8_t *out, int w, int h) {
  const int S = PIC_SUPERSAMPLE;
  for (int y = 0; y < h; y++)
    for (int x = 0; x < w; x++)
      for (int k = 0; k < 3; k++) {
        unsigned acc = 0;
        for (int dy = 0; dy < S; dy++)
          for (int dx = 0; dx < S; dx++)
            acc += cv->rgb[3 * ((size_t)(S * y + dy) * cv->w + (S * x + dx)) + k];
        out[3 * ((size_t)y * w + x) + k] = (uint8_t)((acc + S * S / 2) / (S * S));
      }
}

int sm_pic_render_png(const char *path, const sm_mesh *a, const uint8_t *rgb_a,
                      const sm_mesh *b, const uint8_t *rgb_b, const sm_pic_view *view,
                      sm_error *err) {
  int w = view->width, h = view->height, S = PIC_SUPERSAMPLE;
  if (w < 16 || h < 16 || w > 8192 || h > 8192)
    return sm_error_set(err, SM_EINVAL, "picture: size %d x %d outside 16..8192", w, h);
  canvas cv = {S * w, S * h, NULL, NULL};
  size_t n = (size_t)cv.w * cv.h;
  cv.rgb = malloc(n * 3);
  cv.depth = malloc(n * sizeof *cv.depth);
  uint8_t *img = malloc((size_t)w * h * 3);
  int rc = cv.rgb && cv.depth && img ? 0 : SM_ENOMEM;
  if (!rc) {
    memset(cv.rgb, 255, n * 3);
    for (size_t i = 0; i < n; i++) cv.depth[i] = -FLT_MAX;
    int half = cv.w / 2;
    rc = draw_mesh(&cv, 0, half, cv.h, a, rgb_a, view);
    if (!rc) rc = draw_mesh(&cv, half, cv.w - half, cv.h, b, rgb_b, view);
  }
  if (rc) rc = sm_error_set(err, SM_ENOMEM, "picture: no memory for a %d x %d canvas", w, h);
  else {
    downsample(&cv, img, w, h);
    rc = write_png(path, img, w, h, err);
  }
  free(cv.rgb);
  free(cv.depth);
  free(img);
  return rc;
}
