#include "sm_laplace.h"

#include <math.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>

static double cot_at(const double *o, const double *p, const double *q) {
  double u[3] = {p[0] - o[0], p[1] - o[1], p[2] - o[2]};
  double v[3] = {q[0] - o[0], q[1] - o[1], q[2] - o[2]};
  double cx = u[1] * v[2] - u[2] * v[1], cy = u[2] * v[0] - u[0] * v[2],
         cz = u[0] * v[1] - u[1] * v[0];
  double s = sqrt(cx * cx + cy * cy + cz * cz);
  return s > 0 ? (u[0] * v[0] + u[1] * v[1] + u[2] * v[2]) / s : 0.0;
}

void sm_face_cotan_weights(const double *a, const double *b, const double *c, double w[3]) {
  w[0] = 0.5 * cot_at(a, b, c);
  w[1] = 0.5 * cot_at(b, c, a);
  w[2] = 0.5 * cot_at(c, a, b);
}

int sm_cotan_stiffness(const sm_mesh *m, sm_csc **W, sm_error *err) {
  sm_triplets t;
  *W = NULL;
  if (sm_triplets_init(&t, m->nv, 6 * (int64_t)m->nf + m->nv))
    return sm_error_set(err, SM_ENOMEM, "cotan Laplacian: out of memory");
  int rc = SM_OK;
  for (int32_t f = 0; f < m->nf && !rc; f++) {
    const int32_t *F = m->F + 3 * (int64_t)f;
    double w[3];
    sm_face_cotan_weights(m->V + 3 * (int64_t)F[0], m->V + 3 * (int64_t)F[1],
                          m->V + 3 * (int64_t)F[2], w);
    for (int c = 0; c < 3 && !rc; c++) {
      int32_t p = F[(c + 1) % 3], q = F[(c + 2) % 3];
      rc = sm_triplets_add(&t, p, q, -w[c]);
      if (!rc) rc = sm_triplets_add(&t, p, p, w[c]);
      if (!rc) rc = sm_triplets_add(&t, q, q, w[c]);
    }
  }
  if (rc) rc = sm_error_set(err, SM_ENOMEM, "cotan Laplacian: out of memory");
  else rc = sm_triplets_to_csc(&t, W, err);
  sm_triplets_free(&t);
  return rc;
}

static double dist2(const double *a, const double *b) {
  double d[3] = {a[0] - b[0], a[1] - b[1], a[2] - b[2]};
  return d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
}

/* The mixed Voronoi area of Meyer et al. 2003 that face (p0, p1, p2), of area `area` and
 * cotan weights w (sm_face_cotan_weights), gives each corner: the Voronoi region's part in
 * a non-obtuse face, else half the face to the obtuse corner and a quarter to the others.
 * With it, the cotan mean curvature is exact to O(h^2) at vertices of any valence. */
static void mixed_area(const double *const p[3], const double w[3], double area, double out[3]) {
  int obtuse = -1;
  for (int c = 0; c < 3; c++)
    if (w[c] < 0) obtuse = c;
  for (int c = 0; c < 3; c++) {
    int a = (c + 1) % 3, b = (c + 2) % 3;
    if (obtuse < 0) out[c] = (w[a] * dist2(p[c], p[b]) + w[b] * dist2(p[c], p[a])) / 4;
    else out[c] = obtuse == c ? area / 2 : area / 4;
  }
}

/* Unsmoothed: (sum_j w_ij (x_i - x_j)) . n_i / (2 A_i), A_i the mixed area, n_i the
 * area-weighted normal. */
static void curvature_raw(const sm_mesh *m, double *L, double *A, double *N, double *H) {
  for (int32_t f = 0; f < m->nf; f++) {
    const int32_t *F = m->F + 3 * (int64_t)f;
    const double *p[3] = {m->V + 3 * (int64_t)F[0], m->V + 3 * (int64_t)F[1],
                          m->V + 3 * (int64_t)F[2]};
    double w[3], u[3], v[3], ma[3];
    sm_face_cotan_weights(p[0], p[1], p[2], w);
    for (int d = 0; d < 3; d++) {
      u[d] = p[1][d] - p[0][d];
      v[d] = p[2][d] - p[0][d];
    }
    double n[3] = {u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]};
    mixed_area(p, w, sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) / 2, ma);
    for (int c = 0; c < 3; c++) {
      int32_t a = F[(c + 1) % 3], b = F[(c + 2) % 3];
      for (int d = 0; d < 3; d++) {
        double e = w[c] * (m->V[3 * (int64_t)a + d] - m->V[3 * (int64_t)b + d]);
        L[3 * (int64_t)a + d] += e;
        L[3 * (int64_t)b + d] -= e;
        N[3 * (int64_t)F[c] + d] += n[d];
      }
      A[F[c]] += ma[c];
    }
  }
  for (int32_t i = 0; i < m->nv; i++) {
    const double *l = L + 3 * (int64_t)i, *n = N + 3 * (int64_t)i;
    double len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    H[i] = len > 0 && A[i] > 0 ? (l[0] * n[0] + l[1] * n[1] + l[2] * n[2]) / (len * 2 * A[i]) : 0;
  }
}

/* One pass: each vertex takes the mean of its faces' mean values (isolated ones keep). */
static void smooth_pass(const sm_mesh *m, double *H, double *sum, double *cnt) {
  memset(sum, 0, (size_t)m->nv * sizeof *sum);
  memset(cnt, 0, (size_t)m->nv * sizeof *cnt);
  for (int32_t f = 0; f < m->nf; f++) {
    const int32_t *F = m->F + 3 * (int64_t)f;
    double mean = (H[F[0]] + H[F[1]] + H[F[2]]) / 3;
    for (int c = 0; c < 3; c++) {
      sum[F[c]] += mean;
      cnt[F[c]] += 1;
    }
  }
  for (int32_t i = 0; i < m->nv; i++)
    if (cnt[i] > 0) H[i] = sum[i] / cnt[i];
}

int sm_mean_curvature(const sm_mesh *m, int smooth, double *H, sm_error *err) {
  size_t n = (size_t)m->nv;
  double *L = calloc(3 * n, sizeof *L), *N = calloc(3 * n, sizeof *N), *A = calloc(n, sizeof *A);
  int rc = (!L || !N || !A) ? sm_error_set(err, SM_ENOMEM, "mean curvature: out of memory") : SM_OK;
  if (!rc) curvature_raw(m, L, A, N, H);
  for (int it = 0; !rc && it < smooth; it++) smooth_pass(m, H, L, A); /* L, A reused */
  free(L);
  free(N);
  free(A);
  return rc;
}
