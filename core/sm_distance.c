#include "sm_distance.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define SM_DIST_TIMES 8
#define SM_DIST_SPECTRUM 50

/* F (n x SM_DIST_TIMES, column-major): centered log HKS at the fixed times. */
static int features(const sm_shape *s, double *F) {
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
  return SM_OK;
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

double sm_spectrum_distance(const sm_basis *a, const sm_basis *b) {
  int ia = 0, ib = 0;
  double top_a = fabs(a->evals[a->k - 1]), top_b = fabs(b->evals[b->k - 1]);
  while (ia < a->k && a->evals[ia] <= 1e-9 * top_a) ia++;
  while (ib < b->k && b->evals[ib] <= 1e-9 * top_b) ib++;
  int K = a->k - ia < b->k - ib ? a->k - ia : b->k - ib;
  if (K > SM_DIST_SPECTRUM) K = SM_DIST_SPECTRUM;
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

int sm_shape_distance(const sm_shape *x, const sm_shape *y, const int32_t *T_xy,
                      const int32_t *T_yx, sm_distance_parts *out, sm_error *err) {
  if (!T_xy || !T_yx) return sm_error_set(err, SM_EINVAL, "distance needs maps both ways");
  int32_t nx = x->mesh->nv, ny = y->mesh->nv;
  for (int32_t v = 0; v < nx; v++)
    if (T_xy[v] < 0 || T_xy[v] >= ny) return sm_error_set(err, SM_ERANGE, "T_xy[%d] = %d", v, T_xy[v]);
  for (int32_t v = 0; v < ny; v++)
    if (T_yx[v] < 0 || T_yx[v] >= nx) return sm_error_set(err, SM_ERANGE, "T_yx[%d] = %d", v, T_yx[v]);
  double *Fx = malloc((size_t)nx * SM_DIST_TIMES * sizeof *Fx);
  double *Fy = malloc((size_t)ny * SM_DIST_TIMES * sizeof *Fy);
  if (!Fx || !Fy) {
    free(Fx);
    free(Fy);
    return sm_error_set(err, SM_ENOMEM, "distance: out of memory");
  }
  features(x, Fx);
  features(y, Fy);
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
  free(Fx);
  free(Fy);
  return SM_OK;
}

void sm_distance_match_opts(sm_match_opts *o) {
  o->want_yx = 1;
  o->orientation_fix = 0;
  o->extremities = SM_EXT_OFF;
}
