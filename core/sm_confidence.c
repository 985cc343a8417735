/* sm_confidence: orientation, continuity and invertibility of a map. See sm_confidence.h. */
#include "sm_confidence.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "sm_coarse.h"

static double dist3(const double *a, const double *b) {
  double dx = a[0] - b[0], dy = a[1] - b[1], dz = a[2] - b[2];
  return sqrt(dx * dx + dy * dy + dz * dz);
}

/* Mass fraction of X's vertices none of whose face edges maps to a segment longer than
 * tau on Y. */
static int continuity(const sm_mesh *X, const sm_mesh *Y, const double *mass,
                      const int32_t *T, double *out) {
  char *jump = calloc((size_t)X->nv, 1);
  if (!jump) return SM_ENOMEM;
  for (int32_t f = 0; f < X->nf; f++) {
    const int32_t *F = X->F + 3 * (int64_t)f;
    for (int c = 0; c < 3; c++) {
      int32_t a = F[c], b = F[(c + 1) % 3];
      if (dist3(Y->V + 3 * (int64_t)T[a], Y->V + 3 * (int64_t)T[b]) > SM_CONFIDENCE_TAU)
        jump[a] = jump[b] = 1;
    }
  }
  double ok = 0, tot = 0;
  for (int32_t v = 0; v < X->nv; v++) {
    tot += mass[v];
    if (!jump[v]) ok += mass[v];
  }
  free(jump);
  *out = tot > 0 ? ok / tot : 0;
  return SM_OK;
}

static double cycle(const sm_mesh *X, const double *mass, const int32_t *T,
                    const int32_t *T_yx) {
  double ok = 0, tot = 0;
  for (int32_t v = 0; v < X->nv; v++) {
    tot += mass[v];
    if (dist3(X->V + 3 * (int64_t)v, X->V + 3 * (int64_t)T_yx[T[v]]) <= SM_CONFIDENCE_TAU)
      ok += mass[v];
  }
  return tot > 0 ? ok / tot : 0;
}

int sm_map_confidence(const sm_mesh *X, const sm_mesh *Y, const double *mass_x,
                      const int32_t *T, const int32_t *T_yx, sm_confidence *out,
                      sm_error *err) {
  if (!X || !Y || !mass_x || !T || !T_yx || !out)
    return sm_error_set(err, SM_EINVAL, "confidence: missing argument");
  for (int32_t v = 0; v < X->nv; v++)
    if (T[v] < 0 || T[v] >= Y->nv)
      return sm_error_set(err, SM_ERANGE, "confidence: T[%d] = %d outside Y", v, T[v]);
  for (int32_t v = 0; v < Y->nv; v++)
    if (T_yx[v] < 0 || T_yx[v] >= X->nv)
      return sm_error_set(err, SM_ERANGE, "confidence: T_yx[%d] = %d outside X", v, T_yx[v]);
  out->orientation = sm_map_orientation_score(X, Y, T);
  if (continuity(X, Y, mass_x, T, &out->continuity))
    return sm_error_set(err, SM_ENOMEM, "confidence: out of memory");
  out->cycle = cycle(X, mass_x, T, T_yx);
  double o = out->orientation > 0 ? out->orientation : 0;
  out->confidence = o * out->continuity * out->cycle;
  return SM_OK;
}

/* ---- geodesic directions and turns ---------------------------------------------------- */

struct sm_dir_probe {
  const sm_mesh *m;
  int na;
  int32_t *at;
  int64_t *off;  /* neighbourhood of sample c: nb[off[c] .. off[c + 1]) */
  int32_t *nb;
  double *uv;    /* tangent coordinates of each neighbour, 2 per entry */
  double *inv;   /* per sample: inverse of the 2 x 2 normal matrix (4), 0 when singular */
};

/* e1, e2: an orthonormal frame of the plane normal to n, with e1 x e2 = n. */
static void tangent_frame(const double *n, double *e1, double *e2) {
  double a[3] = {1, 0, 0};
  if (fabs(n[0]) > 0.8) a[0] = 0, a[1] = 1;
  double d = a[0] * n[0] + a[1] * n[1] + a[2] * n[2], l = 0;
  for (int k = 0; k < 3; k++) e1[k] = a[k] - d * n[k], l += e1[k] * e1[k];
  l = sqrt(l);
  for (int k = 0; k < 3; k++) e1[k] /= l;
  e2[0] = n[1] * e1[2] - n[2] * e1[1];
  e2[1] = n[2] * e1[0] - n[0] * e1[2];
  e2[2] = n[0] * e1[1] - n[1] * e1[0];
}

static int probe_count(const sm_mesh *m, const double *N, int32_t c, int32_t v) {
  const double *p = m->V + 3 * (int64_t)c, *q = m->V + 3 * (int64_t)v;
  const double *nc = N + 3 * (int64_t)c, *nv = N + 3 * (int64_t)v;
  return v != c && dist3(p, q) <= SM_DIR_RADIUS &&
         nc[0] * nv[0] + nc[1] * nv[1] + nc[2] * nv[2] >= 0.5;
}

static void probe_fill(sm_dir_probe *p, const double *N) {
  const sm_mesh *m = p->m;
  int64_t k = 0;
  for (int c = 0; c < p->na; c++) {
    double e1[3], e2[3], a11 = 0, a12 = 0, a22 = 0;
    const double *o = m->V + 3 * (int64_t)p->at[c];
    tangent_frame(N + 3 * (int64_t)p->at[c], e1, e2);
    p->off[c] = k;
    for (int32_t v = 0; v < m->nv; v++) {
      if (!probe_count(m, N, p->at[c], v)) continue;
      const double *q = m->V + 3 * (int64_t)v;
      double d[3] = {q[0] - o[0], q[1] - o[1], q[2] - o[2]};
      double u = d[0] * e1[0] + d[1] * e1[1] + d[2] * e1[2];
      double w = d[0] * e2[0] + d[1] * e2[1] + d[2] * e2[2];
      p->nb[k] = v, p->uv[2 * k] = u, p->uv[2 * k + 1] = w, k++;
      a11 += u * u, a12 += u * w, a22 += w * w;
    }
    double det = a11 * a22 - a12 * a12, *inv = p->inv + 4 * c;
    if (det > 1e-18) inv[0] = a22 / det, inv[1] = inv[2] = -a12 / det, inv[3] = a11 / det;
    else memset(inv, 0, 4 * sizeof *inv);
  }
  p->off[p->na] = k;
}

int sm_dir_probe_create(const sm_mesh *m, const int32_t *at, int na, sm_dir_probe **out,
                        sm_error *err) {
  *out = NULL;
  if (!m || !at || na < 1) return sm_error_set(err, SM_EINVAL, "directions: missing argument");
  double *N = malloc((size_t)m->nv * 3 * sizeof *N);
  sm_dir_probe *p = calloc(1, sizeof *p);
  int64_t total = 0;
  int rc = (!N || !p || sm_mesh_vertex_normals(m, N)) ? SM_ENOMEM : SM_OK;
  for (int c = 0; !rc && c < na; c++)
    for (int32_t v = 0; v < m->nv; v++) total += probe_count(m, N, at[c], v);
  if (!rc) {
    p->m = m, p->na = na;
    p->at = malloc((size_t)na * sizeof *p->at);
    p->off = malloc(((size_t)na + 1) * sizeof *p->off);
    p->nb = malloc((size_t)(total + 1) * sizeof *p->nb);
    p->uv = malloc((size_t)(total + 1) * 2 * sizeof *p->uv);
    p->inv = malloc((size_t)na * 4 * sizeof *p->inv);
    if (!p->at || !p->off || !p->nb || !p->uv || !p->inv) rc = SM_ENOMEM;
  }
  if (!rc) {
    memcpy(p->at, at, (size_t)na * sizeof *at);
    probe_fill(p, N);
  }
  free(N);
  if (rc) {
    sm_dir_probe_destroy(p);
    return sm_error_set(err, SM_ENOMEM, "directions: out of memory");
  }
  *out = p;
  return SM_OK;
}

void sm_dir_probe_eval(const sm_dir_probe *p, const double *field, double *dir) {
  for (int c = 0; c < p->na; c++) {
    double b1 = 0, b2 = 0, f0 = field[p->at[c]];
    for (int64_t k = p->off[c]; k < p->off[c + 1]; k++) {
      double f = field[p->nb[k]] - f0;
      if (!isfinite(f)) continue;
      b1 += p->uv[2 * k] * f, b2 += p->uv[2 * k + 1] * f;
    }
    const double *inv = p->inv + 4 * c;
    dir[2 * c] = -(inv[0] * b1 + inv[1] * b2);
    dir[2 * c + 1] = -(inv[2] * b1 + inv[3] * b2);
  }
}

void sm_dir_probe_destroy(sm_dir_probe *p) {
  if (!p) return;
  free(p->at), free(p->off), free(p->nb), free(p->uv), free(p->inv);
  free(p);
}

/* sin of the turn from u to v, 0 for a null vector. */
static double turn(const double *u, const double *v) {
  double n = hypot(u[0], u[1]) * hypot(v[0], v[1]);
  return n > 0 ? (u[0] * v[1] - u[1] * v[0]) / n : 0;
}

static double turn_agreement(const double *dx, const double *dy, const double *src_dist,
                             const int32_t *img, int ns, int ld) {
  double dmax = 0, agree = 0;
  long cnt = 0;
  for (int i = 0; i < ns * ns; i++)
    if (isfinite(src_dist[(i / ns) * ld + i % ns]) && src_dist[(i / ns) * ld + i % ns] > dmax)
      dmax = src_dist[(i / ns) * ld + i % ns];
  for (int c = 0; c < ns; c++)
    for (int a = 0; a < ns; a++) {
      if (a == c || img[a] == img[c] || !(src_dist[c * ld + a] <= 0.5 * dmax)) continue;
      for (int b = a + 1; b < ns; b++) {
        if (b == c || img[b] == img[c] || img[b] == img[a] || !(src_dist[c * ld + b] <= 0.5 * dmax))
          continue;
        double sx = turn(dx + 2 * ((size_t)c * ns + a), dx + 2 * ((size_t)c * ns + b));
        double sy = turn(dy + 2 * ((size_t)c * ns + a), dy + 2 * ((size_t)c * ns + b));
        if (fabs(sx) < 0.3 || fabs(sy) < 0.3) continue;
        agree += (sx > 0) == (sy > 0) ? 1 : -1;
        cnt++;
      }
    }
  return cnt ? agree / (double)cnt : 0;
}

int sm_map_turns(sm_edge_paths *paths_y, const sm_mesh *Y, const int32_t *T,
                 const int32_t *src, const double *src_dist, const double *dir_x, int ns,
                 int ld, double *distortion, double *turns, sm_error *err) {
  if (!paths_y || !Y || !T || !src || !src_dist || !dir_x || !distortion || !turns || ns < 2 ||
      ld < ns)
    return sm_error_set(err, SM_EINVAL, "turns: missing argument");
  int32_t *img = malloc((size_t)ns * sizeof *img);
  double *dy = malloc((size_t)Y->nv * sizeof *dy);
  double *dir_y = malloc((size_t)ns * ns * 2 * sizeof *dir_y), *col = malloc((size_t)ns * 2 * sizeof *col);
  sm_dir_probe *probe = NULL;
  int rc = (!img || !dy || !dir_y || !col) ? sm_error_set(err, SM_ENOMEM, "turns: out of memory") : SM_OK;
  for (int a = 0; !rc && a < ns; a++) img[a] = T[src[a]];
  if (!rc) rc = sm_dir_probe_create(Y, img, ns, &probe, err);
  double num = 0, den = 0;
  for (int a = 0; !rc && a < ns; a++) {
    if ((rc = sm_edge_paths_run(paths_y, img[a], dy, err))) break;
    for (int b = 0; b < ns; b++) {
      double dx = src_dist[(size_t)a * ld + b], d = dy[img[b]];
      if (b == a || !isfinite(dx) || !isfinite(d)) continue;
      num += fabs(dx - d), den += dx;
    }
    sm_dir_probe_eval(probe, dy, col); /* at every image c, toward image a */
    for (int c = 0; c < ns; c++) memcpy(dir_y + 2 * ((size_t)c * ns + a), col + 2 * c, 2 * sizeof *col);
  }
  if (!rc) {
    *distortion = den > 0 ? num / den : 0;
    *turns = turn_agreement(dir_x, dir_y, src_dist, img, ns, ld);
  }
  sm_dir_probe_destroy(probe);
  free(img), free(dy), free(dir_y), free(col);
  return rc;
}

double sm_map_field_agreement(const double *fx, const double *fy, const double *mass_x,
                              int32_t nx, const int32_t *T) {
  double sw = 0, mx = 0, my = 0;
  for (int32_t i = 0; i < nx; i++) {
    sw += mass_x[i];
    mx += mass_x[i] * fx[i];
    my += mass_x[i] * fy[T[i]];
  }
  if (!(sw > 0)) return 0;
  mx /= sw;
  my /= sw;
  double sxy = 0, sxx = 0, syy = 0;
  for (int32_t i = 0; i < nx; i++) {
    double a = fx[i] - mx, b = fy[T[i]] - my;
    sxy += mass_x[i] * a * b;
    sxx += mass_x[i] * a * a;
    syy += mass_x[i] * b * b;
  }
  return sxx > 0 && syy > 0 ? sxy / sqrt(sxx * syy) : 0;
}
