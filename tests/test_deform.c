/* test_deform: the evaluation suite's deformations (sm_deform.h) against what they must
 * do analytically: stretch scales exactly one direction, a region deformation stays
 * inside its radius and is the identity at factor 1, noise is reproducible and moves
 * vertices only along normals, decimation keeps a closed manifold close to the input. */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

#include "sm_deform.h"
#include "sm_metrics.h"
#include "sm_test.h"
#include "sm_testmesh.h"

static void extent(const sm_mesh *m, double lo[3], double hi[3]) {
  for (int d = 0; d < 3; d++) lo[d] = INFINITY, hi[d] = -INFINITY;
  for (int32_t v = 0; v < m->nv; v++)
    for (int d = 0; d < 3; d++) {
      double x = m->V[3 * (size_t)v + d];
      if (x < lo[d]) lo[d] = x;
      if (x > hi[d]) hi[d] = x;
    }
}


static void test_stretch(void) {
  sm_mesh *s = tm_icosphere(3), *t = NULL;
  double lo0[3], hi0[3], lo[3], hi[3];
  extent(s, lo0, hi0);
  REQUIRE(sm_deform_stretch(s, 1, 1.4, &t, NULL) == SM_OK);
  extent(t, lo, hi);
  CHECK_NEAR(hi[1] - lo[1], 1.4 * (hi0[1] - lo0[1]), 1e-12);
  CHECK_NEAR(hi[0] - lo[0], hi0[0] - lo0[0], 1e-12);
  CHECK_NEAR(hi[2] - lo[2], hi0[2] - lo0[2], 1e-12);
  CHECK(t->nf == s->nf && memcmp(t->F, s->F, 3 * (size_t)s->nf * sizeof *s->F) == 0);
  sm_mesh_destroy(t);

  /* An ellipsoid elongated along (1,1,0)/sqrt2: the principal axis is that direction, and
   * stretching along it by f multiplies the extent along it by f. */
  sm_mesh *e = NULL;
  REQUIRE(sm_deform_stretch(s, 0, 2.0, &e, NULL) == SM_OK);
  const double zero[3] = {0, 0, 0};
  tm_rigid(e, 0, 0, M_PI / 4, 1.0, zero);
  double ax[3];
  REQUIRE(sm_principal_axis(e, ax, NULL) == SM_OK);
  CHECK_NEAR(fabs(ax[0]), sqrt(0.5), 1e-9);
  CHECK_NEAR(fabs(ax[1]), sqrt(0.5), 1e-9);
  CHECK_NEAR(ax[2], 0, 1e-9);
  REQUIRE(sm_deform_stretch(e, SM_AXIS_PRINCIPAL, 1.5, &t, NULL) == SM_OK);
  double m0 = 0, m1 = 0;
  for (int32_t v = 0; v < e->nv; v++) {
    double p0 = e->V[3 * v] * ax[0] + e->V[3 * v + 1] * ax[1] + e->V[3 * v + 2] * ax[2];
    double p1 = t->V[3 * v] * ax[0] + t->V[3 * v + 1] * ax[1] + t->V[3 * v + 2] * ax[2];
    if (fabs(p0) > m0) m0 = fabs(p0);
    if (fabs(p1) > m1) m1 = fabs(p1);
  }
  CHECK_NEAR(m1 / m0, 1.5, 1e-9);
  CHECK(sm_deform_stretch(s, 3, 1.2, &t, NULL) == SM_EINVAL);
  CHECK(sm_deform_stretch(s, 0, -1, &t, NULL) == SM_EINVAL);
  CHECK(sm_deform_stretch(s, 0, NAN, &t, NULL) == SM_EINVAL);
  sm_mesh_destroy(t);
  sm_mesh_destroy(e);
  sm_mesh_destroy(s);
}

static void test_region(void) {
  sm_mesh *s = tm_icosphere(4), *t = NULL;
  REQUIRE(sm_deform_region(s, 0, 0.2, 0.0, &t, NULL) == SM_OK);
  CHECK(memcmp(t->V, s->V, 3 * (size_t)s->nv * sizeof *s->V) == 0);
  sm_mesh_destroy(t);

  REQUIRE(sm_deform_region(s, 0, 0.2, 0.3, &t, NULL) == SM_OK);
  double *dist = malloc((size_t)s->nv * sizeof *dist);
  REQUIRE(dist && sm_mesh_edge_dijkstra(s, 0, dist, NULL) == SM_OK);
  double r = 0.2 * sqrt(sm_mesh_face_areas(s, NULL));
  int moved_outside = 0, moved_inside = 0;
  for (int32_t v = 0; v < s->nv; v++) {
    double dx = 0;
    for (int d = 0; d < 3; d++) dx += fabs(t->V[3 * v + d] - s->V[3 * v + d]);
    if (dist[v] >= r && dx != 0) moved_outside++;
    if (dist[v] < 0.5 * r && dist[v] > 0 && dx > 0) moved_inside++;
  }
  CHECK(moved_outside == 0);
  CHECK(moved_inside > 0);
  /* Inflation adds volume, shrinking removes it. */
  double v0 = tm_signed_volume(s), v1 = tm_signed_volume(t);
  CHECK_MSG(v1 > v0 * 1.01, "volume %g -> %g", v0, v1);
  sm_mesh_destroy(t);
  REQUIRE(sm_deform_region(s, 0, 0.2, -0.3, &t, NULL) == SM_OK);
  CHECK_MSG(tm_signed_volume(t) < v0 * 0.99, "volume %g -> %g", v0, tm_signed_volume(t));
  CHECK(sm_deform_region(s, s->nv, 0.2, 0.2, &t, NULL) == SM_ERANGE);
  sm_mesh_destroy(t);
  free(dist);
  sm_mesh_destroy(s);
}

static void test_noise(void) {
  sm_mesh *s = tm_icosphere(3), *a = NULL, *b = NULL, *z = NULL;
  REQUIRE(sm_deform_noise(s, 0.1, 42, &a, NULL) == SM_OK);
  REQUIRE(sm_deform_noise(s, 0.1, 42, &b, NULL) == SM_OK);
  REQUIRE(sm_deform_noise(s, 0.0, 42, &z, NULL) == SM_OK);
  CHECK(memcmp(a->V, b->V, 3 * (size_t)s->nv * sizeof *s->V) == 0);
  CHECK(memcmp(z->V, s->V, 3 * (size_t)s->nv * sizeof *s->V) == 0);
  /* On the unit sphere the normal is radial: each vertex stays on its ray, and the radial
   * offsets have about the requested spread (0.1 mean edge lengths). */
  double sum2 = 0, tangential = 0, edge = 0;
  for (int32_t f = 0; f < s->nf; f++) {
    const double *p = s->V + 3 * s->F[3 * f], *q = s->V + 3 * s->F[3 * f + 1];
    edge += sqrt((p[0] - q[0]) * (p[0] - q[0]) + (p[1] - q[1]) * (p[1] - q[1]) +
                 (p[2] - q[2]) * (p[2] - q[2]));
  }
  edge /= s->nf;
  for (int32_t v = 0; v < s->nv; v++) {
    const double *p = s->V + 3 * v, *q = a->V + 3 * v;
    double r = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]) - 1;
    double c[3] = {p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]};
    tangential += sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
    sum2 += r * r;
  }
  CHECK(tangential / s->nv < 1e-3 * edge);
  double sd = sqrt(sum2 / s->nv) / edge;
  CHECK_MSG(sd > 0.08 && sd < 0.12, "noise spread %g edge lengths", sd);
  sm_mesh_destroy(a), sm_mesh_destroy(b), sm_mesh_destroy(z), sm_mesh_destroy(s);
}

static void test_decimate(void) {
  sm_mesh *s = tm_icosphere(4), *d = NULL; /* 2562 vertices */
  REQUIRE(sm_mesh_decimate(s, 1000, &d, NULL) == SM_OK);
  CHECK(d->nv <= 1000 && d->nv >= 900);
  CHECK(d->nv - (3 * d->nf / 2) + d->nf == 2); /* closed genus 0: V - E + F = 2 */
  REQUIRE(sm_mesh_validate(d, NULL) == SM_OK);
  double maxdev = 0;
  for (int32_t v = 0; v < d->nv; v++) {
    const double *p = d->V + 3 * v;
    double r = fabs(sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) - 1);
    if (r > maxdev) maxdev = r;
  }
  CHECK_MSG(maxdev < 0.01, "decimated vertices %g off the sphere", maxdev);
  /* Each face keeps the outward orientation. */
  int inward = 0;
  for (int32_t f = 0; f < d->nf; f++) {
    const double *a = d->V + 3 * d->F[3 * f], *b = d->V + 3 * d->F[3 * f + 1],
                 *c = d->V + 3 * d->F[3 * f + 2];
    double u[3], w[3];
    for (int k = 0; k < 3; k++) u[k] = b[k] - a[k], w[k] = c[k] - a[k];
    double n[3] = {u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]};
    if (n[0] * a[0] + n[1] * a[1] + n[2] * a[2] <= 0) inward++;
  }
  CHECK(inward == 0);
  sm_mesh_destroy(d);
  REQUIRE(sm_mesh_decimate(s, 5000, &d, NULL) == SM_OK);
  CHECK(d->nv == s->nv);
  sm_mesh_destroy(d);
  CHECK(sm_mesh_decimate(s, 3, &d, NULL) == SM_EINVAL);
  sm_mesh_destroy(s);
}

int main(void) {
  test_stretch();
  test_region();
  test_noise();
  test_decimate();
  return sm_test_finish();
}
