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
#include "sm_topology.h"

/* Mesh from literal arrays. */
static sm_mesh *make_mesh(int32_t nv, const double *V, int32_t nf, const int32_t *F) {
  sm_mesh *m;
  REQUIRE(sm_mesh_alloc(nv, nf, NULL, &m, NULL) == SM_OK);
  memcpy(m->V, V, (size_t)nv * 3 * sizeof *V);
  memcpy(m->F, F, (size_t)nf * 3 * sizeof *F);
  return m;
}

static double total_area(const sm_mesh *m) { return sm_mesh_face_areas(m, NULL); }


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
  CHECK(tm_signed_volume(m) > 4); /* the test mesh is outward (4/3 pi r^3 minus facets) */
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

  /* center/scale reproduce V from the input over successive calls, starting from an
   * earlier recorded transform (center c0, scale s0) so that composition matters */
  m = orig;
  const double c0[3] = {1, -2, 3}, s0 = 0.37;
  for (int32_t v = 0; v < m->nv; v++)
    for (int d = 0; d < 3; d++) m->V[3 * v + d] = (m->V[3 * v + d] - c0[d]) * s0;
  memcpy(m->center, c0, sizeof c0);
  m->scale = s0;
  REQUIRE(sm_mesh_normalize(m, &err) == SM_OK);
  REQUIRE(sm_mesh_normalize(m, &err) == SM_OK);
  check_normalized(m);
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

/* ---- orientation helpers ---- */

/* Every hinge's second face traverses the shared edge opposite to the first. */
static int all_consistent(const sm_mesh *m) {
  sm_edges *e;
  REQUIRE(sm_edges_build(m, &e, NULL) == SM_OK);
  int ok = 1;
  for (int32_t h = 0; h < e->nhinge; h++) {
    int32_t i = e->hinge[4 * h], j = e->hinge[4 * h + 1], g = e->hinge_face[2 * h + 1];
    int found = 0;
    for (int c = 0; c < 3; c++)
      found |= m->F[3 * g + c] == j && m->F[3 * g + (c + 1) % 3] == i;
    ok &= found;
  }
  sm_edges_destroy(e);
  return ok;
}

static void flip_face(sm_mesh *m, int32_t f) {
  int32_t t = m->F[3 * f + 1];
  m->F[3 * f + 1] = m->F[3 * f + 2];
  m->F[3 * f + 2] = t;
}

/* Flips each face with probability p; returns how many. */
static int32_t flip_random(sm_mesh *m, double p, uint64_t seed) {
  int32_t k = 0;
  for (int32_t f = 0; f < m->nf; f++)
    if (tm_rand(&seed) < p) flip_face(m, f), k++;
  return k;
}

static int same_faces(const sm_mesh *a, const sm_mesh *b) {
  return a->nf == b->nf && memcmp(a->F, b->F, (size_t)a->nf * 3 * sizeof *a->F) == 0;
}

/* ---- clean ---- */

static void test_clean_drops(void) {
  /* Input: vertex 0 unused, 1..42 the icosphere, 43 the midpoint of ico vertices 0 and 1
   * (only in a zero-area face), 44 unused. Faces: a reversed copy of ico face 10 first
   * (kept, since it comes first, then flipped back), the icosphere, then junk. */
  sm_mesh *ico = tm_icosphere(1);
  int32_t nv = ico->nv + 3, nf = ico->nf + 6;
  sm_mesh *in;
  REQUIRE(sm_mesh_alloc(nv, nf, NULL, &in, NULL) == SM_OK);
  in->V[0] = 100, in->V[1] = 100, in->V[2] = 100;
  memcpy(in->V + 3, ico->V, (size_t)ico->nv * 3 * sizeof(double));
  for (int d = 0; d < 3; d++) {
    in->V[3 * 43 + d] = 0.5 * (ico->V[d] + ico->V[3 + d]);
    in->V[3 * 44 + d] = -7;
  }
  int32_t *F = in->F;
  F[0] = ico->F[30] + 1, F[1] = ico->F[32] + 1, F[2] = ico->F[31] + 1; /* reversed face 10 */
  for (int32_t i = 0; i < 3 * ico->nf; i++) F[3 + i] = ico->F[i] + 1;
  int32_t *x = F + 3 + 3 * ico->nf;
  const int32_t junk[15] = {
      1, 1, 2,                                           /* repeated index */
      1, 43, 2,                                          /* zero area (collinear) */
      ico->F[21] + 1, ico->F[22] + 1, ico->F[23] + 1,    /* duplicate of face 7 */
      ico->F[22] + 1, ico->F[21] + 1, ico->F[23] + 1,    /* reversed duplicate of face 7 */
      5, 5, 5};                                          /* repeated index */
  memcpy(x, junk, sizeof junk);
  sm_mesh *before;
  REQUIRE(sm_mesh_copy(in, &before, NULL) == SM_OK);

  sm_mesh *out;
  sm_clean_report r;
  sm_error err;
  REQUIRE(sm_mesh_clean(in, NULL, &out, &r, &err) == SM_OK);
  CHECK(r.input_vertices == nv && r.input_faces == nf);
  CHECK(r.dropped_repeated_index == 2);
  CHECK(r.dropped_zero_area == 1);
  CHECK(r.dropped_duplicate == 3); /* face 7 twice, and ico face 10 (after its reversed copy) */
  CHECK(r.dropped_unreferenced == 3);
  CHECK(r.flipped_faces == 1);
  CHECK(r.boundary_edges == 0 && r.nonmanifold_edges == 0);
  CHECK(r.components == 1 && r.nonorientable_components == 0);
  CHECK(out->nv == ico->nv && out->nf == ico->nf);
  CHECK(out->n_input == nv);
  REQUIRE(out->to_input != NULL);
  int ok = 1;
  for (int32_t v = 0; v < out->nv; v++) {
    ok &= out->to_input[v] == v + 1; /* vertex 0 dropped, order kept */
    ok &= memcmp(out->V + 3 * v, in->V + 3 * out->to_input[v], 3 * sizeof(double)) == 0;
  }
  CHECK(ok);
  CHECK(all_consistent(out));
  CHECK(tm_signed_volume(ico) > 3);
  CHECK_NEAR(tm_signed_volume(out), tm_signed_volume(ico), 1e-12);
  CHECK_NEAR(total_area(out), total_area(ico), 1e-12);
  /* `in` untouched */
  CHECK(memcmp(in->V, before->V, (size_t)nv * 3 * sizeof(double)) == 0 && same_faces(in, before));
  sm_mesh_destroy(before);
  sm_mesh_destroy(out);
  sm_mesh_destroy(in);
  sm_mesh_destroy(ico);
}

static void test_clean_all_degenerate(void) {
  /* 12 faces, each with a repeated index or collinear corners */
  const double V[] = {0, 0, 0, 1, 0, 0, 2, 0, 0, 3, 0, 0, 0, 0, 0};
  const int32_t F[] = {0, 1, 2, 1, 2, 3, 0, 2, 3, 0, 1, 3, 0, 0, 1, 1, 2, 2,
                       3, 3, 3, 0, 4, 1, 4, 0, 4, 2, 3, 1, 3, 2, 0, 1, 0, 4};
  sm_mesh *m = make_mesh(5, V, 12, F), *out = (sm_mesh *)1;
  sm_error err;
  sm_clean_report r;
  CHECK(sm_mesh_clean(m, NULL, &out, &r, &err) == SM_EEMPTY);
  CHECK(out == NULL);
  CHECK_MSG(strstr(err.msg, "12 faces"), "%s", err.msg);
  sm_mesh_destroy(m);

  /* scale invariance: a tiny but proper triangle survives, a 1e-14-high sliver does not */
  const double Vs[] = {0, 0, 0, 1e-6, 0, 0, 0, 1e-6, 0, 1e-6, 1e-6, 1e-20};
  const int32_t Fs[] = {0, 1, 2, 1, 3, 2};
  m = make_mesh(4, Vs, 2, Fs);
  REQUIRE(sm_mesh_clean(m, NULL, &out, &r, &err) == SM_OK);
  CHECK(out->nf == 2 && r.dropped_zero_area == 0);
  sm_mesh_destroy(out);
  m->V[9] = 0.5e-6, m->V[10] = 0.5e-6 + 1e-20; /* vertex 3 onto the hypotenuse */
  REQUIRE(sm_mesh_clean(m, NULL, &out, &r, &err) == SM_OK);
  CHECK(out->nf == 1 && r.dropped_zero_area == 1 && r.dropped_unreferenced == 1);
  sm_mesh_destroy(out);
  sm_mesh_destroy(m);
}

static void test_clean_twice(void) {
  /* A: vertex 0 unused, 1..3 a lone triangle, 4.. the icosphere */
  sm_mesh *ico = tm_icosphere(1), *a;
  REQUIRE(sm_mesh_alloc(ico->nv + 4, ico->nf + 1, NULL, &a, NULL) == SM_OK);
  const double tri[12] = {9, 9, 9, 5, 0, 0, 6, 0, 0, 5, 1, 0};
  memcpy(a->V, tri, sizeof tri);
  memcpy(a->V + 12, ico->V, (size_t)ico->nv * 3 * sizeof(double));
  a->F[0] = 1, a->F[1] = 2, a->F[2] = 3;
  for (int32_t i = 0; i < 3 * ico->nf; i++) a->F[3 + i] = ico->F[i] + 4;
  sm_mesh *m1, *m2;
  sm_clean_report r;
  sm_error err;
  REQUIRE(sm_mesh_clean(a, NULL, &m1, &r, &err) == SM_OK);
  CHECK(m1->nv == ico->nv + 3 && m1->to_input[0] == 1 && m1->to_input[3] == 4);
  CHECK(r.components == 2);
  /* collapse the triangle (now vertices 0..2 of m1) so the second cleaning drops it */
  memcpy(m1->V + 6, m1->V, 3 * sizeof(double));
  REQUIRE(sm_mesh_clean(m1, NULL, &m2, &r, &err) == SM_OK);
  CHECK(r.dropped_zero_area == 1 && r.dropped_unreferenced == 3 && r.components == 1);
  CHECK(m2->nv == ico->nv && m2->n_input == a->nv);
  int ok = 1;
  for (int32_t v = 0; v < m2->nv; v++) {
    ok &= m2->to_input[v] == v + 4;
    ok &= memcmp(m2->V + 3 * v, a->V + 3 * m2->to_input[v], 3 * sizeof(double)) == 0;
  }
  CHECK(ok);
  sm_mesh_destroy(m1);
  sm_mesh_destroy(m2);
  sm_mesh_destroy(a);
  sm_mesh_destroy(ico);
}

static void test_clean_nonmanifold_and_components(void) {
  /* three faces on edge (0, 1) */
  const double V[] = {0, 0, 0, 1, 0, 0, 0.5, 1, 0, 0.5, -1, 0, 0.5, 0, 1};
  const int32_t F[] = {0, 1, 2, 1, 0, 3, 0, 1, 4};
  sm_mesh *m = make_mesh(5, V, 3, F), *out;
  sm_clean_report r;
  sm_error err;
  REQUIRE(sm_mesh_clean(m, NULL, &out, &r, &err) == SM_OK);
  CHECK(out->nf == 3 && r.nonmanifold_edges == 1 && r.boundary_edges == 6);
  CHECK(r.components == 1 && r.flipped_faces == 0);
  sm_mesh_destroy(out);
  sm_mesh_destroy(m);

  sm_mesh *s = tm_icosphere(2), *t = tm_torus(16, 8, 2, 0.5);
  sm_mesh *u = tm_union(s, t, 5);
  REQUIRE(sm_mesh_clean(u, NULL, &out, &r, &err) == SM_OK);
  CHECK(r.components == 2 && r.flipped_faces == 0 && r.boundary_edges == 0);
  CHECK(out->nv == u->nv && out->nf == u->nf);
  sm_mesh_destroy(out);
  sm_mesh_destroy(u);
  sm_mesh_destroy(s);
  sm_mesh_destroy(t);
}

/* ---- orientation ---- */

static void test_orient_sphere(void) {
  sm_mesh *ref = tm_icosphere(3), *m, *out;
  sm_clean_report r;
  sm_error err;
  REQUIRE(sm_mesh_copy(ref, &m, NULL) == SM_OK);
  int32_t k = flip_random(m, 0.3, 11);
  CHECK(k > 0);
  CHECK(!all_consistent(m));
  REQUIRE(sm_mesh_clean(m, NULL, &out, &r, &err) == SM_OK);
  CHECK_MSG(r.flipped_faces == k, "flipped %d, expected %d", r.flipped_faces, k);
  CHECK(all_consistent(out) && tm_signed_volume(out) > 4);
  CHECK(same_faces(out, ref)); /* exactly the original winding back */
  sm_mesh_destroy(out);
  sm_mesh_destroy(m);

  /* more than half flipped: the cheap orientation is inward, the volume test wins */
  REQUIRE(sm_mesh_copy(ref, &m, NULL) == SM_OK);
  k = flip_random(m, 0.7, 12);
  REQUIRE(sm_mesh_clean(m, NULL, &out, &r, &err) == SM_OK);
  CHECK_MSG(r.flipped_faces == k, "flipped %d, expected %d", r.flipped_faces, k);
  CHECK(same_faces(out, ref));
  sm_mesh_destroy(out);
  sm_mesh_destroy(m);

  /* inside-out: every face flipped */
  REQUIRE(sm_mesh_copy(ref, &m, NULL) == SM_OK);
  for (int32_t f = 0; f < m->nf; f++) flip_face(m, f);
  CHECK(tm_signed_volume(m) < 0);
  REQUIRE(sm_mesh_clean(m, NULL, &out, &r, &err) == SM_OK);
  CHECK(r.flipped_faces == m->nf && tm_signed_volume(out) > 4);
  sm_mesh_destroy(out);
  sm_mesh_destroy(m);
  sm_mesh_destroy(ref);
}

static void test_orient_torus_and_union(void) {
  /* inside-out torus (non-convex, genus 1), oriented in place */
  sm_mesh *t = tm_torus(24, 12, 2, 0.7);
  double v0 = tm_signed_volume(t);
  CHECK(v0 > 0);
  for (int32_t f = 0; f < t->nf; f++) flip_face(t, f);
  flip_random(t, 0.2, 5);
  int32_t flipped = -1, bad = -1;
  sm_error err;
  REQUIRE(sm_mesh_orient(t, &flipped, &bad, &err) == SM_OK);
  CHECK(bad == 0 && flipped > t->nf / 2);
  CHECK(all_consistent(t));
  CHECK_NEAR(tm_signed_volume(t), v0, 1e-9 * v0);

  /* two spheres, one inside-out: each closed component is turned outward on its own */
  sm_mesh *a = tm_icosphere(2), *b = tm_icosphere(2);
  for (int32_t f = 0; f < b->nf; f++) flip_face(b, f);
  sm_mesh *u = tm_union(a, b, 3), *out;
  sm_clean_report r;
  REQUIRE(sm_mesh_clean(u, NULL, &out, &r, &err) == SM_OK);
  CHECK(r.components == 2 && r.flipped_faces == b->nf);
  CHECK(all_consistent(out));
  CHECK(tm_signed_volume(out) > 2 * 4);
  sm_mesh_destroy(out);
  sm_mesh_destroy(u);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
  sm_mesh_destroy(t);
}

static void test_orient_grid(void) {
  sm_mesh *ref = tm_grid(12, 9), *m, *out;
  REQUIRE(sm_mesh_copy(ref, &m, NULL) == SM_OK);
  int32_t k = flip_random(m, 0.35, 3);
  if (m->F[1] == ref->F[1]) flip_face(m, 0), k++; /* the BFS seed must be a wrong one */
  sm_clean_report r;
  sm_error err;
  REQUIRE(sm_mesh_clean(m, NULL, &out, &r, &err) == SM_OK);
  CHECK(r.flipped_faces == k && r.boundary_edges == 2 * (12 + 9) && r.components == 1);
  CHECK(all_consistent(out));
  CHECK(same_faces(out, ref)); /* majority (+z) orientation kept */
  sm_mesh_destroy(out);
  sm_mesh_destroy(m);
  sm_mesh_destroy(ref);
}

/* Moebius strip: no orientation is consistent. */
static void test_orient_moebius(void) {
  const int n = 20;
  sm_mesh *m;
  REQUIRE(sm_mesh_alloc(2 * n, 2 * n, NULL, &m, NULL) == SM_OK);
  for (int i = 0; i < n; i++)
    for (int s = 0; s < 2; s++) {
      double u = 2 * M_PI * i / n, w = s ? 0.3 : -0.3, *p = m->V + 3 * (2 * i + s);
      p[0] = (1 + w * cos(u / 2)) * cos(u), p[1] = (1 + w * cos(u / 2)) * sin(u);
      p[2] = w * sin(u / 2);
    }
  for (int i = 0; i < n; i++) {
    int32_t a = 2 * i, b = 2 * i + 1, c = 2 * (i + 1), d = c + 1;
    if (i == n - 1) c = 1, d = 0; /* the half twist: w -> -w after one turn */
    int32_t q[6] = {a, c, d, a, d, b};
    memcpy(m->F + 6 * i, q, sizeof q);
  }
  sm_mesh *out;
  sm_clean_report r;
  sm_error err;
  REQUIRE(sm_mesh_clean(m, NULL, &out, &r, &err) == SM_OK);
  CHECK(r.nonorientable_components == 1 && r.components == 1);
  CHECK(r.boundary_edges == 2 * n);
  CHECK(r.flipped_faces <= n); /* never more than half */
  sm_mesh_destroy(out);
  /* a sphere is orientable */
  sm_mesh *s = tm_icosphere(1);
  int32_t bad = -1;
  REQUIRE(sm_mesh_orient(s, NULL, &bad, &err) == SM_OK);
  CHECK(bad == 0);
  sm_mesh_destroy(s);
  sm_mesh_destroy(m);
}

/* ---- limits ---- */

static void test_limits(void) {
  sm_limits lim = {10, 20};
  sm_error err;
  CHECK(sm_limits_check(&lim, 10, 20, &err) == SM_OK);
  CHECK(sm_limits_check(&lim, 11, 20, &err) == SM_ELIMIT);
  CHECK(sm_limits_check(&lim, 10, 21, &err) == SM_ELIMIT);
  CHECK(sm_limits_check(&lim, -1, 0, &err) == SM_ELIMIT);
  sm_mesh *m = tm_icosphere(1), *out = (sm_mesh *)1; /* 42 vertices, 80 faces */
  sm_limits lf = {1000, 79}, lv = {41, 1000}, ok = {42, 80};
  CHECK(sm_mesh_clean(m, &lf, &out, NULL, &err) == SM_ELIMIT && out == NULL);
  CHECK_MSG(strstr(err.msg, "80"), "%s", err.msg);
  CHECK(sm_mesh_clean(m, &lv, &out, NULL, &err) == SM_ELIMIT && out == NULL);
  REQUIRE(sm_mesh_clean(m, &ok, &out, NULL, &err) == SM_OK);
  sm_mesh_destroy(out);
  sm_mesh_destroy(m);
}

int main(void) {
  test_validate();
  test_areas_and_mass();
  test_normals();
  test_normalize();
  test_components();
  test_clean_drops();
  test_clean_all_degenerate();
  test_clean_twice();
  test_clean_nonmanifold_and_components();
  test_orient_sphere();
  test_orient_torus_and_union();
  test_orient_grid();
  test_orient_moebius();
  test_limits();
  return sm_test_finish();
}
