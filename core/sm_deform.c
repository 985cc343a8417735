#include "sm_deform.h"

#include <lapacke.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "sm_metrics.h" /* sm_mesh_edge_dijkstra */

static void centroid(const sm_mesh *m, double c[3]) {
  c[0] = c[1] = c[2] = 0;
  for (int32_t v = 0; v < m->nv; v++)
    for (int d = 0; d < 3; d++) c[d] += m->V[3 * (size_t)v + d];
  for (int d = 0; d < 3; d++) c[d] /= m->nv;
}

int sm_principal_axis(const sm_mesh *m, double axis[3], sm_error *err) {
  if (!m || m->nv < 1 || !axis) return sm_error_set(err, SM_EINVAL, "principal axis: empty mesh");
  double c[3], S[9] = {0}, w[3];
  centroid(m, c);
  for (int32_t v = 0; v < m->nv; v++) {
    const double *p = m->V + 3 * (size_t)v;
    for (int a = 0; a < 3; a++)
      for (int b = 0; b < 3; b++) S[3 * a + b] += (p[a] - c[a]) * (p[b] - c[b]);
  }
  if (LAPACKE_dsyev(LAPACK_COL_MAJOR, 'V', 'U', 3, S, 3, w))
    return sm_error_set(err, SM_ENUMERIC, "principal axis: dsyev failed");
  /* Eigenvalues ascend: the last column is the direction of largest variance. */
  int big = 0;
  for (int d = 0; d < 3; d++) {
    axis[d] = S[6 + d];
    if (fabs(axis[d]) > fabs(axis[big])) big = d;
  }
  if (axis[big] < 0)
    for (int d = 0; d < 3; d++) axis[d] = -axis[d];
  return SM_OK;
}

int sm_deform_stretch(const sm_mesh *in, int axis, double factor, sm_mesh **out,
                      sm_error *err) {
  if (!(factor > 0) || !isfinite(factor) || axis < SM_AXIS_PRINCIPAL || axis > 2)
    return sm_error_set(err, SM_EINVAL, "stretch: factor %g / axis %d invalid", factor, axis);
  double u[3] = {0, 0, 0}, c[3];
  int rc = 0;
  if (axis == SM_AXIS_PRINCIPAL)
    rc = sm_principal_axis(in, u, err);
  else
    u[axis] = 1;
  if (!rc) rc = sm_mesh_copy(in, out, err);
  if (rc) return rc;
  centroid(in, c);
  /* x' = x + (factor - 1) ((x - c) . u) u: only the component along u is scaled. */
  for (int32_t v = 0; v < in->nv; v++) {
    double *p = (*out)->V + 3 * (size_t)v;
    double s = (factor - 1) * ((p[0] - c[0]) * u[0] + (p[1] - c[1]) * u[1] + (p[2] - c[2]) * u[2]);
    for (int d = 0; d < 3; d++) p[d] += s * u[d];
  }
  return SM_OK;
}

int sm_deform_region(const sm_mesh *in, int32_t center, double radius_rel, double amount,
                     sm_mesh **out, sm_error *err) {
  if (!(radius_rel > 0) || !isfinite(amount) || !isfinite(radius_rel))
    return sm_error_set(err, SM_EINVAL, "region: radius %g / amount %g invalid", radius_rel,
                        amount);
  if (center < 0 || center >= in->nv)
    return sm_error_set(err, SM_ERANGE, "region: centre vertex %d of %d", center, in->nv);
  int rc = sm_mesh_validate(in, err);
  if (rc) return rc;
  double *dist = malloc((size_t)in->nv * sizeof *dist);
  double *N = malloc(3 * (size_t)in->nv * sizeof *N);
  if (!dist || !N) {
    free(dist), free(N);
    return sm_error_set(err, SM_ENOMEM, "region: %d distances", in->nv);
  }
  double r = radius_rel * sqrt(sm_mesh_face_areas(in, NULL));
  rc = sm_mesh_edge_dijkstra(in, center, dist, err);
  if (!rc && sm_mesh_vertex_normals(in, N)) rc = sm_error_set(err, SM_ENOMEM, "region: normals");
  if (!rc) rc = sm_mesh_copy(in, out, err);
  /* Along the normals, not a scaling about a point: a smooth scaling with fall-off keeps
   * the tangential area almost unchanged (the stretch and the fall-off cancel). */
  for (int32_t v = 0; !rc && v < in->nv; v++) {
    if (!(dist[v] < r)) continue;
    double q = dist[v] / r, w = (1 - q * q) * (1 - q * q);
    for (int d = 0; d < 3; d++) (*out)->V[3 * (size_t)v + d] += amount * r * w * N[3 * (size_t)v + d];
  }
  free(dist);
  free(N);
  return rc;
}

/* splitmix64 then Box-Muller: fixed across platforms, unlike rand(). */
static uint64_t next_u64(uint64_t *s) {
  uint64_t z = (*s += 0x9e3779b97f4a7c15ull);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

static double gaussian(uint64_t *s) {
  double u1 = ((next_u64(s) >> 11) + 1.0) / 9007199254740993.0; /* (0, 1] */
  double u2 = (next_u64(s) >> 11) / 9007199254740992.0;
  return sqrt(-2 * log(u1)) * cos(2 * M_PI * u2);
}

static double mean_edge_length(const sm_mesh *m) {
  double sum = 0;
  for (int32_t f = 0; f < m->nf; f++)
    for (int e = 0; e < 3; e++) {
      const double *a = m->V + 3 * (size_t)m->F[3 * (size_t)f + e];
      const double *b = m->V + 3 * (size_t)m->F[3 * (size_t)f + (e + 1) % 3];
      sum += sqrt((a[0] - b[0]) * (a[0] - b[0]) + (a[1] - b[1]) * (a[1] - b[1]) +
                  (a[2] - b[2]) * (a[2] - b[2]));
    }
  return m->nf ? sum / (3.0 * m->nf) : 0;
}

int sm_deform_noise(const sm_mesh *in, double sigma_rel, uint64_t seed, sm_mesh **out,
                    sm_error *err) {
  if (!(sigma_rel >= 0) || !isfinite(sigma_rel))
    return sm_error_set(err, SM_EINVAL, "noise: sigma %g invalid", sigma_rel);
  int rc = sm_mesh_validate(in, err);
  if (rc) return rc;
  double *N = malloc(3 * (size_t)in->nv * sizeof *N);
  if (!N) return sm_error_set(err, SM_ENOMEM, "noise: normals of %d vertices", in->nv);
  rc = sm_mesh_vertex_normals(in, N);
  if (rc) sm_error_set(err, rc, "noise: vertex normals failed");
  if (!rc) rc = sm_mesh_copy(in, out, err);
  if (!rc) {
    double sigma = sigma_rel * mean_edge_length(in);
    for (int32_t v = 0; v < in->nv; v++) {
      double s = sigma * gaussian(&seed);
      for (int d = 0; d < 3; d++) (*out)->V[3 * (size_t)v + d] += s * N[3 * (size_t)v + d];
    }
  }
  free(N);
  return rc;
}
