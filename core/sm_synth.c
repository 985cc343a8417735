#include "sm_synth.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

static const double ico_v[12][3] = {
    {-1, 1.618033988749895, 0}, {1, 1.618033988749895, 0}, {-1, -1.618033988749895, 0},
    {1, -1.618033988749895, 0}, {0, -1, 1.618033988749895}, {0, 1, 1.618033988749895},
    {0, -1, -1.618033988749895}, {0, 1, -1.618033988749895}, {1.618033988749895, 0, -1},
    {1.618033988749895, 0, 1},  {-1.618033988749895, 0, -1}, {-1.618033988749895, 0, 1}};
static const int ico_f[20][3] = {{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11},
                                 {1, 5, 9},  {5, 11, 4}, {11, 10, 2}, {10, 7, 6}, {7, 1, 8},
                                 {3, 9, 4},  {3, 4, 2},  {3, 2, 6},   {3, 6, 8},  {3, 8, 9},
                                 {4, 9, 5},  {2, 4, 11}, {6, 2, 10},  {8, 6, 7},  {9, 8, 1}};

/* Open-addressing table from an edge key to its midpoint vertex: each subdivision level
 * creates every edge midpoint exactly once. */
typedef struct midtab {
  int64_t *key;
  int32_t *val;
  int64_t mask;
} midtab;

static int32_t midpoint(midtab *t, sm_mesh *m, int32_t *nv, int64_t a, int64_t b, int64_t cap) {
  int64_t key = a < b ? a * cap + b : b * cap + a;
  int64_t h = (int64_t)(((uint64_t)key * 0x9E3779B97F4A7C15ULL) >> 17) & t->mask;
  while (t->key[h] != -1 && t->key[h] != key) h = (h + 1) & t->mask;
  if (t->key[h] == -1) {
    t->key[h] = key;
    t->val[h] = *nv;
    for (int d = 0; d < 3; d++) m->V[3 * *nv + d] = 0.5 * (m->V[3 * a + d] + m->V[3 * b + d]);
    (*nv)++;
  }
  return t->val[h];
}

static int subdivide(sm_mesh *m, int32_t *nv, int32_t *nf, int64_t cap) {
  midtab t;
  t.mask = 1;
  while (t.mask < 6 * (int64_t)*nf) t.mask <<= 1;
  t.key = malloc((size_t)t.mask * sizeof *t.key);
  t.val = malloc((size_t)t.mask * sizeof *t.val);
  int32_t *F = malloc((size_t)*nf * 12 * sizeof *F);
  t.mask--;
  if (!t.key || !t.val || !F) {
    free(t.key); free(t.val); free(F);
    return SM_ENOMEM;
  }
  memset(t.key, 0xff, (size_t)(t.mask + 1) * sizeof *t.key);
  for (int32_t f = 0; f < *nf; f++) {
    int32_t a = m->F[3 * f], b = m->F[3 * f + 1], c = m->F[3 * f + 2];
    int32_t ab = midpoint(&t, m, nv, a, b, cap), bc = midpoint(&t, m, nv, b, c, cap),
            ca = midpoint(&t, m, nv, c, a, cap);
    int32_t q[12] = {a, ab, ca, b, bc, ab, c, ca, bc, ab, bc, ca};
    memcpy(F + 12 * (int64_t)f, q, sizeof q);
  }
  memcpy(m->F, F, (size_t)*nf * 12 * sizeof *F);
  *nf *= 4;
  free(t.key); free(t.val); free(F);
  return SM_OK;
}

int sm_synth_icosphere(int subdiv, sm_mesh **out, sm_error *err) {
  *out = NULL;
  if (subdiv < 0 || subdiv > 8)
    return sm_error_set(err, SM_EINVAL, "icosphere subdivision %d not in [0, 8]", subdiv);
  int64_t nv = 10 * (1LL << (2 * subdiv)) + 2, nf = 20 * (1LL << (2 * subdiv));
  sm_mesh *m;
  int rc = sm_mesh_alloc(nv, nf, NULL, &m, err);
  if (rc) return rc;
  memcpy(m->V, ico_v, sizeof ico_v);
  for (int f = 0; f < 20; f++)
    for (int c = 0; c < 3; c++) m->F[3 * f + c] = ico_f[f][c];
  int32_t cv = 12, cf = 20;
  for (int s = 0; s < subdiv; s++)
    if (subdivide(m, &cv, &cf, nv)) {
      sm_mesh_destroy(m);
      return sm_error_set(err, SM_ENOMEM, "icosphere: out of memory");
    }
  for (int32_t v = 0; v < cv; v++) {
    double *p = m->V + 3 * v, r = sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    p[0] /= r; p[1] /= r; p[2] /= r;
  }
  *out = m;
  return SM_OK;
}

int sm_synth_torus(int nu, int nvv, double R, double r, sm_mesh **out, sm_error *err) {
  *out = NULL;
  if (nu < 3 || nvv < 3 || !(R > r) || !(r > 0))
    return sm_error_set(err, SM_EINVAL, "torus %d x %d, R = %g, r = %g is degenerate", nu, nvv,
                        R, r);
  sm_mesh *m;
  int rc = sm_mesh_alloc((int64_t)nu * nvv, 2LL * nu * nvv, NULL, &m, err);
  if (rc) return rc;
  for (int i = 0; i < nu; i++)
    for (int j = 0; j < nvv; j++) {
      double u = 2 * M_PI * i / nu, v = 2 * M_PI * j / nvv, *p = m->V + 3 * (i * nvv + j);
      p[0] = (R + r * cos(v)) * cos(u);
      p[1] = (R + r * cos(v)) * sin(u);
      p[2] = r * sin(v);
    }
  for (int i = 0, f = 0; i < nu; i++)
    for (int j = 0; j < nvv; j++, f += 2) {
      int32_t a = i * nvv + j, b = ((i + 1) % nu) * nvv + j, c = i * nvv + (j + 1) % nvv,
              d = ((i + 1) % nu) * nvv + (j + 1) % nvv;
      int32_t t[6] = {a, b, d, a, d, c};
      memcpy(m->F + 3 * f, t, sizeof t);
    }
  *out = m;
  return SM_OK;
}

int sm_synth_blob(int subdiv, double amp, unsigned seed, const double stretch[3],
                  sm_mesh **out, sm_error *err) {
  int rc = sm_synth_icosphere(subdiv, out, err);
  if (rc) return rc;
  sm_mesh *m = *out;
  /* A few Gaussian bumps at directions drawn from the seed (a small LCG keeps it
   * reproducible across platforms). */
  double dir[5][3];
  unsigned s = seed * 2654435761u + 1;
  for (int b = 0; b < 5; b++) {
    double n = 0;
    for (int d = 0; d < 3; d++) {
      s = s * 1664525u + 1013904223u;
      dir[b][d] = (double)(s >> 8) / 16777216.0 * 2 - 1;
      n += dir[b][d] * dir[b][d];
    }
    for (int d = 0; d < 3; d++) dir[b][d] /= sqrt(n) + 1e-12;
  }
  /* Bumps of distinct heights, so that no two look alike: intrinsic descriptors can then
   * tell them apart, as they can tell a head from a hand. */
  static const double weight[5] = {1.0, -0.45, 0.75, -0.3, 0.55};
  for (int32_t v = 0; v < m->nv; v++) {
    double *p = m->V + 3 * v, r = 1;
    for (int b = 0; b < 5; b++) {
      double c = p[0] * dir[b][0] + p[1] * dir[b][1] + p[2] * dir[b][2];
      r += amp * weight[b] * exp(-6 * (1 - c));
    }
    for (int d = 0; d < 3; d++) p[d] *= r * (stretch ? stretch[d] : 1.0);
  }
  return SM_OK;
}
