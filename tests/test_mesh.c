/* test_mesh: validation, cleaning, normalization, mass, normals, components and orientation
 * of sm_mesh (algorithm.md §1). */
#include <math.h>
#include <stdio.h>
#include <string.h>

/* strict C11 + POSIX does not define M_PI (an XSI extension); sm_testmesh.h needs it */
#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

#include "sm_mesh.h"
#include "sm_test.h"
#include "sm_testmesh.h"

/* Mesh from literal arrays. */
static sm_mesh *make_mesh(int32_t nv, const double *V, int32_t nf, const int32_t *F) {
  sm_mesh *m;
  REQUIRE(sm_mesh_alloc(nv, nf, NULL, &m, NULL) == SM_OK);
  memcpy(m->V, V, (size_t)nv * 3 * sizeof *V);
  memcpy(m->F, F, (size_t)nf * 3 * sizeof *F);
  return m;
}

static double total_area(const sm_mesh *m) { return sm_mesh_face_areas(m, NULL); }

/* Signed volume (divergence theorem); positive for a closed outward surface. */
static double signed_volume(const sm_mesh *m) {
  double vol = 0;
  for (int32_t f = 0; f < m->nf; f++) {
    const double *a = m->V + 3 * m->F[3 * f], *b = m->V + 3 * m->F[3 * f + 1],
                 *c = m->V + 3 * m->F[3 * f + 2];
    vol += (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) +
            a[2] * (b[0] * c[1] - b[1] * c[0])) / 6;
  }
  return vol;
}

/* ---- validate ---- */

static void test_validate(void) {
  sm_mesh *m = tm_icosphere(1);
  sm_error err;
  CHECK(sm_mesh_validate(m, &err) == SM_OK);

  double keep = m->V[3 * 17 + 1];
  m->V[3 * 17 + 1] = NAN;
  CHECK(sm_mesh_validate(m, &err) == SM_ENONFINITE);
  CHECK_MSG(strstr(err.msg, "vertex 17") && strstr(err.msg, "y") && strstr(err.msg, "nan"),
            "%s", err.msg);
  m->V[3 * 17 + 1] = keep;

  m->V[3 * 5 + 2] = -INFINITY;
  CHECK(sm_mesh_validate(m, &err) == SM_ENONFINITE);
  CHECK_MSG(strstr(err.msg, "vertex 5") && strstr(err.msg, "z") && strstr(err.msg, "inf"),
            "%s", err.msg);
  m->V[3 * 5 + 2] = 0.5;
  CHECK(sm_mesh_validate(m, &err) == SM_OK);

  int32_t kf = m->F[3 * 12 + 2];
  m->F[3 * 12 + 2] = m->nv;
  CHECK(sm_mesh_validate(m, &err) == SM_ERANGE);
  CHECK_MSG(strstr(err.msg, "face 12") && strstr(err.msg, "42"), "%s", err.msg);
  m->F[3 * 12 + 2] = -3;
  CHECK(sm_mesh_validate(m, &err) == SM_ERANGE);
  CHECK_MSG(strstr(err.msg, "face 12") && strstr(err.msg, "-3"), "%s", err.msg);
  m->F[3 * 12 + 2] = kf;
  CHECK(sm_mesh_validate(m, &err) == SM_OK);

  int32_t nf = m->nf;
  m->nf = 0;
  CHECK(sm_mesh_validate(m, &err) == SM_EEMPTY);
  m->nf = nf;
  m->nv = 0;
  CHECK(sm_mesh_validate(m, &err) == SM_EEMPTY);
  m->nv = 42;
  sm_mesh_destroy(m);
}

/* ---- areas, mass, normals ---- */

static void test_areas_and_mass(void) {
  /* Right triangle with legs 3, 4: area 6. */
  const double V[] = {0, 0, 0, 3, 0, 0, 0, 4, 0};
  const int32_t F[] = {0, 1, 2};
  sm_mesh *m = make_mesh(3, V, 1, F);
  double area[1], mass[3];
  CHECK_NEAR(sm_mesh_face_areas(m, area), 6, 1e-14);
  CHECK_NEAR(area[0], 6, 1e-14);
  /* Right angle: non-obtuse; circumcenter at the hypotenuse midpoint (1.5, 2). Corner 1
   * gets the quadrilateral (3,0)-(1.5,0)-(1.5,2)-(3/2... computed by the formula by hand:
   * vertex 1: (|e_10|^2 cot(angle at 2) + |e_12|^2 cot(angle at 0)) / 8 = (9 * 4/3 + 0)/8. */
  REQUIRE(sm_mesh_lumped_mass(m, mass) == SM_OK);
  CHECK_NEAR(mass[1], 9.0 * (4.0 / 3.0) / 8, 1e-14);
  CHECK_NEAR(mass[2], 16.0 * (3.0 / 4.0) / 8, 1e-14);
  CHECK_NEAR(mass[0], 6 - 1.5 - 1.5, 1e-14);
  sm_mesh_destroy(m);

  /* Obtuse at corner 2: (0,0), (4,0), (2,0.5): area 1, corner 2 gets 1/2, others 1/4. */
  const double Vo[] = {0, 0, 0, 4, 0, 0, 2, 0.5, 0};
  m = make_mesh(3, Vo, 1, F);
  REQUIRE(sm_mesh_lumped_mass(m, mass) == SM_OK);
  CHECK_NEAR(mass[0], 0.25, 1e-14);
  CHECK_NEAR(mass[1], 0.25, 1e-14);
  CHECK_NEAR(mass[2], 0.5, 1e-14);
  sm_mesh_destroy(m);

  /* Regular hexagon fan of equilateral triangles: each triangle gives A/3 to each corner,
   * so the center gets 6 A/3 and each rim vertex (two triangles) 2 A/3. */
  double Vh[21] = {0, 0, 0};
  int32_t Fh[18];
  for (int i = 0; i < 6; i++) {
    Vh[3 * (i + 1)] = cos(M_PI / 3 * i);
    Vh[3 * (i + 1) + 1] = sin(M_PI / 3 * i);
    Vh[3 * (i + 1) + 2] = 0;
    Fh[3 * i] = 0, Fh[3 * i + 1] = i + 1, Fh[3 * i + 2] = (i + 1) % 6 + 1;
  }
  m = make_mesh(7, Vh, 6, Fh);
  double A = sqrt(3.0) / 4, mh[7];
  CHECK_NEAR(total_area(m), 6 * A, 1e-14);
  REQUIRE(sm_mesh_lumped_mass(m, mh) == SM_OK);
  CHECK_NEAR(mh[0], 6 * A / 3, 1e-14);
  for (int v = 1; v < 7; v++) CHECK_NEAR(mh[v], 2 * A / 3, 1e-14);
  sm_mesh_destroy(m);

  /* Masses sum to the total area on a jittered sphere (mixed obtuse / acute triangles). */
  m = tm_icosphere(3);
  tm_jitter(m, 0.02, 7);
  double *ms = malloc((size_t)m->nv * sizeof *ms), sum = 0;
  REQUIRE(sm_mesh_lumped_mass(m, ms) == SM_OK);
  int positive = 1;
  for (int32_t v = 0; v < m->nv; v++) sum += ms[v], positive &= ms[v] > 0;
  CHECK_NEAR(sum, total_area(m), 1e-12 * total_area(m));
  CHECK(positive);
  /* close to the sphere's area 4 pi */
  CHECK(fabs(total_area(m) - 4 * M_PI) < 0.05 * 4 * M_PI);
  free(ms);
  sm_mesh_destroy(m);
}

static void test_normals(void) {
  sm_mesh *m = tm_icosphere(3);
  CHECK(signed_volume(m) > 4); /* the test mesh is outward (4/3 pi r^3 minus facets) */
  double *N = malloc((size_t)m->nv * 3 * sizeof *N);
  REQUIRE(sm_mesh_vertex_normals(m, N) == SM_OK);
  double worst = 1, worst_len = 0;
  for (int32_t v = 0; v < m->nv; v++) {
    const double *n = N + 3 * v, *p = m->V + 3 * v;
    double len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    double d = (n[0] * p[0] + n[1] * p[1] + n[2] * p[2]) / sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    if (fabs(len - 1) > worst_len) worst_len = fabs(len - 1);
    if (d < worst) worst = d;
  }
  CHECK_NEAR(worst_len, 0, 1e-12);
  CHECK_MSG(worst > 0.99, "worst dot %g", worst);
  free(N);
  sm_mesh_destroy(m);

  /* Fold: two triangles back to back on the same three points plus one more face: the
   * shared vertices' sums cancel, so they fall back to the largest incident face. */
  const double V[] = {0, 0, 0, 1, 0, 0, 0, 1, 0, 5, 5, 0};
  const int32_t F[] = {0, 1, 2, 0, 2, 1};
  m = make_mesh(4, V, 2, F);
  double Nf[12];
  REQUIRE(sm_mesh_vertex_normals(m, Nf) == SM_OK);
  for (int v = 0; v < 3; v++)
    CHECK_NEAR(fabs(Nf[3 * v + 2]), 1, 1e-15);
  /* vertex 3 is unreferenced: no direction */
  CHECK(Nf[9] == 0 && Nf[10] == 0 && Nf[11] == 0);
  sm_mesh_destroy(m);
}

/* ---- normalize ---- */

static void check_normalized(const sm_mesh *m) {
  double c[3] = {0, 0, 0}, A = 0;
  for (int32_t f = 0; f < m->nf; f++) {
    double a = 0;
    const int32_t *t = m->F + 3 * f;
    double u[3], w[3];
    for (int d = 0; d < 3; d++) {
      u[d] = m->V[3 * t[1] + d] - m->V[3 * t[0] + d];
      w[d] = m->V[3 * t[2] + d] - m->V[3 * t[0] + d];
    }
    a = 0.5 * sqrt(pow(u[1] * w[2] - u[2] * w[1], 2) + pow(u[2] * w[0] - u[0] * w[2], 2) +
                   pow(u[0] * w[1] - u[1] * w[0], 2));
    A += a;
    for (int d = 0; d < 3; d++)
      c[d] += a * (m->V[3 * t[0] + d] + m->V[3 * t[1] + d] + m->V[3 * t[2] + d]) / 3;
  }
  CHECK_NEAR(A, 1, 1e-12);
  for (int d = 0; d < 3; d++) CHECK_NEAR(c[d], 0, 1e-12);
}

static void test_normalize(void) {
  sm_mesh *m = tm_torus(24, 12, 3, 1);
  const double t[3] = {10, -4, 7};
  tm_rigid(m, 0.3, 0.2, -1.1, 5.0, t);
  sm_mesh *orig;
  sm_error err;
  REQUIRE(sm_mesh_copy(m, &orig, &err) == SM_OK);
  REQUIRE(sm_mesh_normalize(m, &err) == SM_OK);
  check_normalized(m);
  CHECK(m->scale < 1); /* area was 5^2 * 4 pi^2 R r >> 1 */
  /* a second call is (numerically) the identity and still composes */
  tm_rigid(m, 0, 0, 0, 3.0, t); /* (changes V without recording: simulate a caller edit) */
  REQUIRE(sm_mesh_normalize(m, &err) == SM_OK);
  check_normalized(m);
  sm_mesh_destroy(m);

  /* center/scale reproduce V from the input over two successive calls */
  m = orig;
  REQUIRE(sm_mesh_normalize(m, &err) == SM_OK);
  for (int64_t i = 0; i < 3 * (int64_t)m->nv; i++) m->V[i] *= 1; /* no-op */
  REQUIRE(sm_mesh_normalize(m, &err) == SM_OK);
  sm_mesh *in = tm_torus(24, 12, 3, 1);
  tm_rigid(in, 0.3, 0.2, -1.1, 5.0, t);
  double worst = 0;
  for (int32_t v = 0; v < m->nv; v++)
    for (int d = 0; d < 3; d++) {
      double want = (in->V[3 * v + d] - m->center[d]) * m->scale;
      if (fabs(want - m->V[3 * v + d]) > worst) worst = fabs(want - m->V[3 * v + d]);
    }
  CHECK_NEAR(worst, 0, 1e-12);
  sm_mesh_destroy(in);

  /* zero area */
  const double V[] = {0, 0, 0, 1, 0, 0, 2, 0, 0};
  const int32_t F[] = {0, 1, 2};
  sm_mesh *z = make_mesh(3, V, 1, F);
  CHECK(sm_mesh_normalize(z, &err) == SM_EEMPTY);
  sm_mesh_destroy(z);
  sm_mesh_destroy(m);
}

/* ---- components ---- */

static void test_components(void) {
  sm_mesh *a = tm_icosphere(1), *b = tm_torus(8, 6, 2, 0.5);
  sm_mesh *u = tm_union(b, a, 10);
  int32_t *comp = malloc((size_t)u->nv * sizeof *comp), nc = -1;
  REQUIRE(sm_mesh_components(u, comp, &nc) == SM_OK);
  CHECK(nc == 2);
  int ok = 1;
  for (int32_t v = 0; v < u->nv; v++) ok &= comp[v] == (v < b->nv ? 0 : 1);
  CHECK(ok);
  /* faces listed second-component-first still number components by first vertex */
  sm_mesh *w = tm_union(a, b, 10);
  for (int32_t f = 0; f < w->nf / 2; f++) /* reverse face order */
    for (int c = 0; c < 3; c++) {
      int32_t t = w->F[3 * f + c];
      w->F[3 * f + c] = w->F[3 * (w->nf - 1 - f) + c];
      w->F[3 * (w->nf - 1 - f) + c] = t;
    }
  int32_t *cw = malloc((size_t)w->nv * sizeof *cw);
  REQUIRE(sm_mesh_components(w, cw, &nc) == SM_OK);
  CHECK(nc == 2 && cw[0] == 0 && cw[w->nv - 1] == 1);
  free(comp);
  free(cw);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
  sm_mesh_destroy(u);
  sm_mesh_destroy(w);
}

int main(void) {
  test_validate();
  test_areas_and_mass();
  test_normals();
  test_normalize();
  test_components();
  return sm_test_finish();
}
