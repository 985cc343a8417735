/* sm_testmesh: small analytic meshes for tests (icosphere, grid patch, torus) and helpers
 * to perturb, move and permute them. Header-only, test code only. */
#ifndef SM_TESTMESH_H
#define SM_TESTMESH_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "sm_mesh.h"
#include "sm_synth.h"

/* Signed enclosed volume (divergence theorem); positive for a closed outward surface. */
static inline double tm_signed_volume(const sm_mesh *m) {
  double vol = 0;
  for (int32_t f = 0; f < m->nf; f++) {
    const double *a = m->V + 3 * m->F[3 * f], *b = m->V + 3 * m->F[3 * f + 1],
                 *c = m->V + 3 * m->F[3 * f + 2];
    vol += (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) +
            a[2] * (b[0] * c[1] - b[1] * c[0])) / 6;
  }
  return vol;
}

/* Deterministic uniform in [0,1) (xorshift64*), so tests are reproducible. */
static inline double tm_rand(uint64_t *s) {
  *s ^= *s >> 12;
  *s ^= *s << 25;
  *s ^= *s >> 27;
  return (double)((*s * 2685821657736338717ULL) >> 11) / 9007199254740992.0;
}

/* Icosphere of radius 1: 10*4^s + 2 vertices, outward faces. */
static inline sm_mesh *tm_icosphere(int subdiv) {
  sm_mesh *m = NULL;
  sm_synth_icosphere(subdiv, &m, NULL);
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
  sm_mesh *m = NULL;
  sm_synth_torus(nu, nvv, R, r, &m, NULL);
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
