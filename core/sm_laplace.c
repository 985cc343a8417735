#include "sm_laplace.h"

#include <math.h>
#include <stddef.h>

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
