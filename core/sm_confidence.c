/* sm_confidence: orientation, continuity and invertibility of a map. See sm_confidence.h. */
#include "sm_confidence.h"

#include <math.h>
#include <stdlib.h>

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

int sm_map_distortion(sm_edge_paths *paths_y, const int32_t *T, const int32_t *src,
                      const double *src_dist, int ns, int ld, double *out, sm_error *err) {
  if (!paths_y || !T || !src || !src_dist || !out || ns < 2 || ld < ns)
    return sm_error_set(err, SM_EINVAL, "distortion: missing argument");
  int32_t ny = sm_edge_paths_size(paths_y);
  double *dy = malloc((size_t)ny * sizeof *dy);
  if (!dy) return sm_error_set(err, SM_ENOMEM, "distortion: out of memory");
  double num = 0, den = 0;
  int rc = SM_OK;
  for (int a = 0; !rc && a < ns; a++) {
    if ((rc = sm_edge_paths_run(paths_y, T[src[a]], dy, err))) break;
    for (int b = 0; b < ns; b++) {
      double dx = src_dist[(size_t)a * ld + b], d = dy[T[src[b]]];
      if (b == a || !isfinite(dx) || !isfinite(d)) continue;
      num += fabs(dx - d);
      den += dx;
    }
  }
  free(dy);
  if (!rc) *out = den > 0 ? num / den : 0;
  return rc;
}
