#include "sm_distance.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define SM_DIST_TIMES 8
/* The shipped map term compares the first SM_DIST_MAP_TIMES times (10^-3 .. 7.2 10^-3 at
 * unit area): the local scale. The larger times mix in how each body part sits in the
 * whole, which a stretch or another person's proportions move as much as a class change
 * (docs/RESULTS.md section 3, map term study). */
#define SM_DIST_MAP_TIMES 4
#define SM_DIST_SPECTRUM 70 /* shipped K */
#define SM_DIST_PAPER_SPECTRUM 50

void sm_distance_opts_default(sm_distance_opts *o) {
  o->def = SM_DIST_SHIPPED;
  o->map_weight = SM_DIST_MAP_WEIGHT;
  o->spectrum_k = SM_DIST_SPECTRUM;
  o->level_weight = SM_DIST_LEVEL_WEIGHT;
}

/* F (n x SM_DIST_TIMES, column-major): log HKS at the fixed times, each column minus its
 * area-weighted mean. */
static void features(const sm_shape *s, double *F) {
  const sm_basis *b = s->lb;
  int32_t n = b->n;
  memset(F, 0, (size_t)n * SM_DIST_TIMES * sizeof *F);
  for (int q = 0; q < SM_DIST_TIMES; q++) {
    double t = pow(10.0, -3.0 + 2.0 * q / (SM_DIST_TIMES - 1)), *f = F + (size_t)q * n;
    for (int i = 0; i < b->k; i++) {
      double w = exp(-t * fmax(b->evals[i], 0.0));
      const double *phi = b->phi + (size_t)i * n;
      for (int32_t v = 0; v < n; v++) f[v] += w * phi[v] * phi[v];
    }
    double mean = 0, area = 0;
    for (int32_t v = 0; v < n; v++) {
      f[v] = log(fmax(f[v], 1e-300));
      mean += b->mass[v] * f[v];
      area += b->mass[v];
    }
    mean /= area;
    for (int32_t v = 0; v < n; v++) f[v] -= mean;
  }
}

static double cos_dist(double ab, double aa, double bb) {
  if (!(aa > 0) || !(bb > 0)) return aa == bb ? 0.0 : 1.0;
  double c = ab / sqrt(aa * bb);
  return 1.0 - (c > 1 ? 1 : c < -1 ? -1 : c);
}

/* 1 - cos between X's features and Y's features pulled back through T. */
static double point_term(const sm_shape *x, const double *Fx, const sm_shape *y,
                         const double *Fy, const int32_t *T) {
  int32_t nx = x->mesh->nv, ny = y->mesh->nv;
  double ab = 0, aa = 0, bb = 0;
  for (int q = 0; q < SM_DIST_TIMES; q++)
    for (int32_t v = 0; v < nx; v++) {
      double m = x->lb->mass[v], a = Fx[(size_t)q * nx + v], b = Fy[(size_t)q * ny + T[v]];
      ab += m * a * b;
      aa += m * a * a;
      bb += m * b * b;
    }
  return cos_dist(ab, aa, bb);
}

typedef struct wval {
  double r, m;
} wval;

static int cmp_wval(const void *a, const void *b) {
  double x = ((const wval *)a)->r, y = ((const wval *)b)->r;
  return (x > y) - (x < y);
}

/* Shipped map term X -> Y: per vertex v of X, the RMS over the first SM_DIST_MAP_TIMES
 * times of the centered log h_X(v, t) - log h_Y(T(v), t); the area-weighted median of it
 * over X. W: nx slots. */
static double median_term(const sm_shape *x, const double *Fx, const sm_shape *y,
                          const double *Fy, const int32_t *T, wval *W) {
  int32_t nx = x->mesh->nv, ny = y->mesh->nv;
  double area = 0;
  for (int32_t v = 0; v < nx; v++) {
    double ss = 0;
    for (int q = 0; q < SM_DIST_MAP_TIMES; q++) {
      double d = Fx[(size_t)q * nx + v] - Fy[(size_t)q * ny + T[v]];
      ss += d * d;
    }
    W[v].r = sqrt(ss / SM_DIST_MAP_TIMES);
    W[v].m = x->lb->mass[v];
    area += W[v].m;
  }
  qsort(W, (size_t)nx, sizeof *W, cmp_wval);
  double acc = 0;
  for (int32_t v = 0; v < nx; v++) {
    acc += W[v].m;
    if (acc >= 0.5 * area) return W[v].r;
  }
  return nx ? W[nx - 1].r : 0.0;
}

/* First non-zero eigenvalue of a basis (the zero ones: one per connected component). */
static int first_positive(const sm_basis *b) {
  int i = 0;
  double top = fabs(b->evals[b->k - 1]);
  while (i < b->k && b->evals[i] <= 1e-9 * top) i++;
  return i;
}

double sm_spectrum_ratio_distance(const sm_basis *a, const sm_basis *b, int K, double level) {
  int ia = first_positive(a), ib = first_positive(b);
  int n = a->k - ia < b->k - ib ? a->k - ia : b->k - ib;
  if (K <= 0 || K > n) K = n;
  if (K < 1) return 0.0;
  double mean = 0, ss = 0;
  for (int i = 0; i < K; i++) mean += log(a->evals[ia + i] / b->evals[ib + i]) / K;
  /* two passes: the spread around the mean, then the level's share */
  for (int i = 0; i < K; i++) {
    double d = log(a->evals[ia + i] / b->evals[ib + i]) - mean;
    ss += d * d;
  }
  return sqrt(ss / K + level * mean * mean);
}

double sm_spectrum_distance(const sm_basis *a, const sm_basis *b) {
  int ia = 0, ib = 0;
  double top_a = fabs(a->evals[a->k - 1]), top_b = fabs(b->evals[b->k - 1]);
  while (ia < a->k && a->evals[ia] <= 1e-9 * top_a) ia++;
  while (ib < b->k && b->evals[ib] <= 1e-9 * top_b) ib++;
  int K = a->k - ia < b->k - ib ? a->k - ia : b->k - ib;
  if (K > SM_DIST_PAPER_SPECTRUM) K = SM_DIST_PAPER_SPECTRUM;
  if (K < 2) return 0.0;
  double ma = 0, mb = 0, ab = 0, aa = 0, bb = 0;
  for (int i = 0; i < K; i++) {
    ma += log(a->evals[ia + i]) / K;
    mb += log(b->evals[ib + i]) / K;
  }
  for (int i = 0; i < K; i++) {
    double u = log(a->evals[ia + i]) - ma, v = log(b->evals[ib + i]) - mb;
    ab += u * v;
    aa += u * u;
    bb += v * v;
  }
  return cos_dist(ab, aa, bb);
}

/* 1 - exp(-s): the shipped terms are >= 0 and unbounded; this keeps each in [0, 1), equal
 * to s to first order, so the shipped total stays in the documented [0, 1). */
static double squash(double s) { return 1.0 - exp(-s); }

double sm_shape_spectral_term(const sm_shape *x, const sm_shape *y) {
  return squash(
      sm_spectrum_ratio_distance(x->lb, y->lb, SM_DIST_SPECTRUM, SM_DIST_LEVEL_WEIGHT));
}

int sm_distance_uses_maps(void) { return SM_DIST_MAP_WEIGHT > 0; }

int sm_shape_distance_ex(const sm_shape *x, const sm_shape *y, const int32_t *T_xy,
                         const int32_t *T_yx, const sm_distance_opts *o,
                         sm_distance_parts *out, sm_error *err) {
  sm_distance_opts def;
  if (!o) {
    sm_distance_opts_default(&def);
    o = &def;
  }
  if (o->def != SM_DIST_SHIPPED && o->def != SM_DIST_PAPER)
    return sm_error_set(err, SM_EINVAL, "unknown distance definition %d", o->def);
  if (!(o->map_weight >= 0) || !isfinite(o->map_weight))
    return sm_error_set(err, SM_EINVAL, "map_weight must be >= 0");
  if (!(o->level_weight >= 0) || !isfinite(o->level_weight))
    return sm_error_set(err, SM_EINVAL, "level_weight must be >= 0");
  if (!T_xy || !T_yx) return sm_error_set(err, SM_EINVAL, "distance needs maps both ways");
  int32_t nx = x->mesh->nv, ny = y->mesh->nv;
  for (int32_t v = 0; v < nx; v++)
    if (T_xy[v] < 0 || T_xy[v] >= ny)
      return sm_error_set(err, SM_ERANGE, "T_xy[%d] = %d", v, T_xy[v]);
  for (int32_t v = 0; v < ny; v++)
    if (T_yx[v] < 0 || T_yx[v] >= nx)
      return sm_error_set(err, SM_ERANGE, "T_yx[%d] = %d", v, T_yx[v]);
  int shipped = o->def == SM_DIST_SHIPPED;
  int32_t nmax = nx > ny ? nx : ny;
  double *Fx = malloc((size_t)nx * SM_DIST_TIMES * sizeof *Fx);
  double *Fy = malloc((size_t)ny * SM_DIST_TIMES * sizeof *Fy);
  wval *W = shipped ? malloc((size_t)nmax * sizeof *W) : NULL;
  if (!Fx || !Fy || (shipped && !W)) {
    free(Fx);
    free(Fy);
    free(W);
    return sm_error_set(err, SM_ENOMEM, "distance: out of memory");
  }
  /* both definitions center: the shipped one so that, like S, it ignores the mesh's area
   * (normal noise inflates it and lifts every log h by about the same amount) */
  features(x, Fx);
  features(y, Fy);
  if (shipped) {
    out->point_xy = squash(median_term(x, Fx, y, Fy, T_xy, W));
    out->point_yx = squash(median_term(y, Fy, x, Fx, T_yx, W));
    out->spectrum_lb =
        squash(sm_spectrum_ratio_distance(x->lb, y->lb, o->spectrum_k, o->level_weight));
    out->spectrum_elastic = -1;
    double w = o->map_weight;
    out->total = (out->spectrum_lb + w * 0.5 * (out->point_xy + out->point_yx)) / (1 + w);
  } else {
    out->point_xy = point_term(x, Fx, y, Fy, T_xy);
    out->point_yx = point_term(y, Fy, x, Fx, T_yx);
    out->spectrum_lb = sm_spectrum_distance(x->lb, y->lb);
    out->spectrum_elastic =
        x->elastic && y->elastic ? sm_spectrum_distance(x->elastic, y->elastic) : -1;
    double sum = out->point_xy + out->point_yx + out->spectrum_lb;
    int terms = 3;
    if (out->spectrum_elastic >= 0) {
      sum += out->spectrum_elastic;
      terms++;
    }
    out->total = sum / terms;
  }
  free(Fx);
  free(Fy);
  free(W);
  return SM_OK;
}

int sm_shape_distance(const sm_shape *x, const sm_shape *y, const int32_t *T_xy,
                      const int32_t *T_yx, sm_distance_parts *out, sm_error *err) {
  return sm_shape_distance_ex(x, y, T_xy, T_yx, NULL, out, err);
}

void sm_distance_match_opts(sm_match_opts *o) {
  o->basis = SM_MATCH_LB;
  if (o->k1 > SM_DIST_MATCH_K) o->k1 = SM_DIST_MATCH_K;
  if (o->k0 > o->k1) o->k0 = o->k1;
  o->sinkhorn_levels = 0;
  o->init_samples = 1;
  o->want_yx = 1;
  o->orientation_fix = 0;
  o->extremities = SM_EXT_OFF;
  o->bijective = 0;
}
