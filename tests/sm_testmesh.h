/* sm_testmesh: small analytic meshes for tests (icosphere, grid patch, torus) and helpers
 * to perturb, move and permute them. Header-only, test code only. */
#ifndef SM_TESTMESH_H
#define SM_TESTMESH_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "sm_mesh.h"

/* Deterministic uniform in [0,1) (xorshift64*), so tests are reproducible. */
static inline double tm_rand(uint64_t *s) {
  *s ^= *s >> 12;
  *s ^= *s << 25;
  *s ^= *s >> 27;
  return (double)((*s * 2685821657736338717ULL) >> 11) / 9007199254740992.0;
}

/* Icosphere of radius 1: 10*4^s + 2 vertices, outward faces. */
static inline sm_mesh *tm_icosphere(int subdiv) {
  int64_t nv = 10 * (1LL << (2 * subdiv)) + 2, nf = 20 * (1LL << (2 * subdiv));
  sm_mesh *m;
  if (sm_mesh_alloc(nv, nf, NULL, &m, NULL)) return NULL;
  const double t = (1.0 + sqrt(5.0)) / 2.0;
  const double v0[12][3] = {{-1, t, 0}, {1, t, 0}, {-1, -t, 0}, {1, -t, 0},
                            {0, -1, t}, {0, 1, t}, {0, -1, -t}, {0, 1, -t},
                            {t, 0, -1}, {t, 0, 1}, {-t, 0, -1}, {-t, 0, 1}};
  const int f0[20][3] = {{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11},
                         {1, 5, 9},  {5, 11, 4}, {11, 10, 2}, {10, 7, 6}, {7, 1, 8},
                         {3, 9, 4},  {3, 4, 2},  {3, 2, 6},   {3, 6, 8},  {3, 8, 9},
                         {4, 9, 5},  {2, 4, 11}, {6, 2, 10},  {8, 6, 7},  {9, 8, 1}};
  int32_t cv = 12, cf = 20;
  memcpy(m->V, v0, sizeof v0);
  for (int f = 0; f < 20; f++)
    for (int c = 0; c < 3; c++) m->F[3 * f + c] = f0[f][c];
  /* Midpoint subdivision with an edge->midpoint lookup by sorting is overkill here: a
   * linear scan over a per-level edge list is fine for test sizes (< 50k vertices). */
  for (int s = 0; s < subdiv; s++) {
    int32_t nfc = cf;
    int64_t ecap = 3 * (int64_t)nfc;
    int64_t *ekey = malloc((size_t)ecap * sizeof *ekey);
    int32_t *emid = malloc((size_t)ecap * sizeof *emid);
    int32_t *newF = malloc((size_t)nfc * 12 * sizeof *newF);
    int64_t ne = 0;
    /* hash table keyed by edge */
    int64_t hcap = 1;
    while (hcap < 4 * ecap) hcap <<= 1;
    int64_t *hk = malloc((size_t)hcap * sizeof *hk);
    int32_t *hv = malloc((size_t)hcap * sizeof *hv);
    for (int64_t i = 0; i < hcap; i++) hk[i] = -1;
    for (int32_t f = 0; f < nfc; f++) {
      int32_t mid[3];
      for (int c = 0; c < 3; c++) {
        int64_t a = m->F[3 * f + c], b = m->F[3 * f + (c + 1) % 3];
        int64_t key = a < b ? a * nv + b : b * nv + a;
        int64_t h = (int64_t)(((uint64_t)key * 0x9E3779B97F4A7C15ULL) >> 20) & (hcap - 1);
        while (hk[h] != -1 && hk[h] != key) h = (h + 1) & (hcap - 1);
        if (hk[h] == -1) {
          hk[h] = key;
          hv[h] = cv;
          for (int d = 0; d < 3; d++) m->V[3 * cv + d] = 0.5 * (m->V[3 * a + d] + m->V[3 * b + d]);
          ekey[ne] = key;
          emid[ne++] = cv++;
        }
        mid[c] = hv[h];
      }
      int32_t a = m->F[3 * f], b = m->F[3 * f + 1], c = m->F[3 * f + 2];
      int32_t q[12] = {a, mid[0], mid[2], b, mid[1], mid[0], c, mid[2], mid[1], mid[0], mid[1], mid[2]};
      memcpy(newF + 12 * f, q, sizeof q);
    }
    memcpy(m->F, newF, (size_t)nfc * 12 * sizeof *newF);
    cf = nfc * 4;
    free(ekey); free(emid); free(newF); free(hk); free(hv);
  }
  for (int32_t v = 0; v < cv; v++) {
    double *p = m->V + 3 * v, r = sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    p[0] /= r; p[1] /= r; p[2] /= r;
  }
  return m;
}

/* (nx+1) x (ny+1) grid on [0,1]^2 in the z = 0 plane (an open patch with boundary),
 * diagonals alternating so the mesh has no preferred direction. */
static inline sm_mesh *tm_grid(int nx, int ny) {
  sm_mesh *m;
  if (sm_mesh_alloc((int64_t)(nx + 1) * (ny + 1), 2LL * nx * ny, NULL, &m, NULL)) return NULL;
  for (int j = 0; j <= ny; j++)
    for (int i = 0; i <= nx; i++) {
      double *p = m->V + 3 * (j * (nx + 1) + i);
      p[0] = (double)i / nx; p[1] = (double)j / ny; p[2] = 0;
    }
  int32_t f = 0;
  for (int j = 0; j < ny; j++)
    for (int i = 0; i < nx; i++) {
      int32_t a = j * (nx + 1) + i, b = a + 1, c = a + nx + 1, d = c + 1;
      int32_t t[6];
      if ((i + j) % 2) { int32_t u[6] = {a, b, d, a, d, c}; memcpy(t, u, sizeof t); }
      else { int32_t u[6] = {a, b, c, b, d, c}; memcpy(t, u, sizeof t); }
      memcpy(m->F + 3 * f, t, sizeof t);
      f += 2;
    }
  return m;
}

/* Torus with major radius R, minor r, nu x nv quads split in two. */
static inline sm_mesh *tm_torus(int nu, int nvv, double R, double r) {
  sm_mesh *m;
  if (sm_mesh_alloc((int64_t)nu * nvv, 2LL * nu * nvv, NULL, &m, NULL)) return NULL;
  for (int i = 0; i < nu; i++)
    for (int j = 0; j < nvv; j++) {
      double u = 2 * M_PI * i / nu, v = 2 * M_PI * j / nvv, *p = m->V + 3 * (i * nvv + j);
      p[0] = (R + r * cos(v)) * cos(u); p[1] = (R + r * cos(v)) * sin(u); p[2] = r * sin(v);
    }
  int32_t f = 0;
  for (int i = 0; i < nu; i++)
    for (int j = 0; j < nvv; j++) {
      int32_t a = i * nvv + j, b = ((i + 1) % nu) * nvv + j, c = i * nvv + (j + 1) % nvv,
              d = ((i + 1) % nu) * nvv + (j + 1) % nvv;
      int32_t t[6] = {a, b, d, a, d, c};
      memcpy(m->F + 3 * f, t, sizeof t);
      f += 2;
    }
  return m;
}

/* Disjoint union of a and b (b's copy shifted by `shift` along x). */
static inline sm_mesh *tm_union(const sm_mesh *a, const sm_mesh *b, double shift) {
  sm_mesh *m;
  if (sm_mesh_alloc((int64_t)a->nv + b->nv, (int64_t)a->nf + b->nf, NULL, &m, NULL)) return NULL;
  memcpy(m->V, a->V, (size_t)a->nv * 3 * sizeof(double));
  memcpy(m->V + 3 * a->nv, b->V, (size_t)b->nv * 3 * sizeof(double));
  for (int32_t v = 0; v < b->nv; v++) m->V[3 * (a->nv + v)] += shift;
  memcpy(m->F, a->F, (size_t)a->nf * 3 * sizeof(int32_t));
  for (int64_t i = 0; i < 3 * (int64_t)b->nf; i++) m->F[3 * a->nf + i] = b->F[i] + a->nv;
  return m;
}

/* Adds uniform noise of amplitude amp to every coordinate. */
static inline void tm_jitter(sm_mesh *m, double amp, uint64_t seed) {
  uint64_t s = seed ? seed : 88172645463325252ULL;
  for (int64_t i = 0; i < 3 * (int64_t)m->nv; i++) m->V[i] += amp * (2 * tm_rand(&s) - 1);
}

/* x <- s * R x + t with R a rotation from three angles. */
static inline void tm_rigid(sm_mesh *m, double ax, double ay, double az, double s,
                            const double t[3]) {
  double cx = cos(ax), sx = sin(ax), cy = cos(ay), sy = sin(ay), cz = cos(az), sz = sin(az);
  double R[9] = {cy * cz, sx * sy * cz - cx * sz, cx * sy * cz + sx * sz,
                 cy * sz, sx * sy * sz + cx * cz, cx * sy * sz - sx * cz,
                 -sy,     sx * cy,                cx * cy};
  for (int32_t v = 0; v < m->nv; v++) {
    double *p = m->V + 3 * v, q[3];
    for (int r = 0; r < 3; r++) q[r] = s * (R[3 * r] * p[0] + R[3 * r + 1] * p[1] + R[3 * r + 2] * p[2]) + t[r];
    memcpy(p, q, sizeof q);
  }
}

/* Random permutation perm[new] = old (Fisher-Yates). */
static inline void tm_permutation(int32_t *perm, int32_t n, uint64_t seed) {
  uint64_t s = seed ? seed : 1;
  for (int32_t i = 0; i < n; i++) perm[i] = i;
  for (int32_t i = n - 1; i > 0; i--) {
    int32_t j = (int32_t)(tm_rand(&s) * (i + 1));
    int32_t t = perm[i]; perm[i] = perm[j]; perm[j] = t;
  }
}

/* Returns a copy of m whose vertex `new` is m's vertex perm[new]; faces renumbered. */
static inline sm_mesh *tm_permuted(const sm_mesh *m, const int32_t *perm) {
  sm_mesh *p;
  if (sm_mesh_alloc(m->nv, m->nf, NULL, &p, NULL)) return NULL;
  int32_t *inv = malloc((size_t)m->nv * sizeof *inv);
  for (int32_t i = 0; i < m->nv; i++) {
    inv[perm[i]] = i;
    memcpy(p->V + 3 * i, m->V + 3 * perm[i], 3 * sizeof(double));
  }
  for (int64_t i = 0; i < 3 * (int64_t)m->nf; i++) p->F[i] = inv[m->F[i]];
  free(inv);
  return p;
}

#endif
