/* test_multires: the multi-resolution path (core/sm_multires.h).
 *   - location and prolongation: on a mesh whose vertices all lie on a coarse mesh (two
 *     midpoint subdivisions of it, not projected), a coarse vertex's copy gets weight 1 on
 *     it, a coarse function is reproduced exactly at the coarse vertices, and a linear
 *     function of the position exactly everywhere;
 *   - the coarse level does not depend on the vertex order (a permuted copy gets the very
 *     same coarse mesh), and a permuted copy forced through the path is matched exactly;
 *   - a non-manifold mesh (a fin on an edge), which sm_mesh_decimate refuses, is prepared;
 *   - the fine snap: an exact map stays, one-edge offsets go back (onto the mesh and onto a
 *     stretched copy of it);
 *   - options: auto threshold, forced modes, invalid values;
 *   - data (skipped without ../shared/data, and under SM_TEST_SYNTHETIC_ONLY as test_match):
 *     homerA against its permuted copy forced through the path, >= 99% exact.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "sm_deform.h"
#include "sm_meshio.h"
#include "sm_multires.h"
#include "sm_synth.h"
#include "sm_test.h"
#include "sm_testmesh.h"

/* One midpoint subdivision (each face into 4, new vertices at edge midpoints, not moved):
 * every new vertex lies on the input surface. */
static sm_mesh *subdivide(const sm_mesh *m) {
  int32_t ne_max = 3 * m->nf;
  int32_t *ea = malloc((size_t)ne_max * sizeof *ea), *eb = malloc((size_t)ne_max * sizeof *eb);
  int32_t ne = 0, *mid = malloc((size_t)3 * m->nf * sizeof *mid);
  for (int32_t f = 0; f < m->nf; f++)
    for (int c = 0; c < 3; c++) {
      int32_t a = m->F[3 * f + c], b = m->F[3 * f + (c + 1) % 3], lo = a < b ? a : b, hi = a ^ b ^ lo;
      int32_t e = 0;
      while (e < ne && !(ea[e] == lo && eb[e] == hi)) e++;
      if (e == ne) ea[ne] = lo, eb[ne++] = hi;
      mid[3 * f + c] = m->nv + e;
    }
  sm_mesh *s;
  REQUIRE(sm_mesh_alloc((int64_t)m->nv + ne, 4LL * m->nf, NULL, &s, NULL) == 0);
  memcpy(s->V, m->V, (size_t)3 * m->nv * sizeof *s->V);
  for (int32_t e = 0; e < ne; e++)
    for (int d = 0; d < 3; d++)
      s->V[3 * (m->nv + e) + d] = 0.5 * (m->V[3 * ea[e] + d] + m->V[3 * eb[e] + d]);
  for (int32_t f = 0; f < m->nf; f++) {
    const int32_t *t = m->F + 3 * f, *u = mid + 3 * f;
    int32_t q[12] = {t[0], u[0], u[2], t[1], u[1], u[0], t[2], u[2], u[1], u[0], u[1], u[2]};
    memcpy(s->F + 12 * f, q, sizeof q);
  }
  free(ea), free(eb), free(mid);
  return s;
}

static void test_prolongation(void) {
  sm_mesh *c = tm_icosphere(2), *s1 = subdivide(c), *f = subdivide(s1);
  sm_error err;
  int32_t n = f->nv, *tri = malloc((size_t)3 * n * sizeof *tri);
  double *bary = malloc((size_t)3 * n * sizeof *bary);
  REQUIRE(sm_multires_locate(f->V, n, c, tri, bary, &err) == 0);
  int bad_w = 0, unit = 0;
  for (int32_t i = 0; i < n; i++) {
    double s = 0;
    for (int t = 0; t < 3; t++) {
      s += bary[3 * i + t];
      bad_w += bary[3 * i + t] < -1e-12 || bary[3 * i + t] > 1 + 1e-12;
    }
    bad_w += fabs(s - 1) > 1e-12;
  }
  CHECK_MSG(bad_w == 0, "%d bad barycentric weights", bad_w);
  /* The subdivision keeps the coarse vertices first: vertex v of f is vertex v of c. */
  for (int32_t v = 0; v < c->nv; v++)
    for (int t = 0; t < 3; t++) unit += tri[3 * v + t] == v && bary[3 * v + t] == 1.0;
  CHECK_MSG(unit == c->nv, "%d of %d coarse vertices located with weight 1 on themselves",
            unit, c->nv);
  /* A coarse function (3 columns: random values, x, and a linear function) prolonged. */
  double *Fc = malloc((size_t)3 * c->nv * sizeof *Fc), *Ff = malloc((size_t)3 * n * sizeof *Ff);
  uint64_t seed = 99;
  const double g[4] = {0.3, -1.7, 2.2, 0.5};
  for (int32_t v = 0; v < c->nv; v++) {
    const double *p = c->V + 3 * v;
    Fc[3 * v] = tm_rand(&seed) * 2 - 1;
    Fc[3 * v + 1] = p[0];
    Fc[3 * v + 2] = g[0] * p[0] + g[1] * p[1] + g[2] * p[2] + g[3];
  }
  sm_multires_prolong(tri, bary, n, Fc, 3, 3, Ff, 3);
  int exact = 0;
  double lin_err = 0;
  for (int32_t v = 0; v < c->nv; v++)
    exact += Ff[3 * v] == Fc[3 * v] && Ff[3 * v + 1] == Fc[3 * v + 1];
  CHECK_MSG(exact == c->nv, "coarse values reproduced at %d of %d coarse vertices", exact, c->nv);
  for (int32_t i = 0; i < n; i++) {
    const double *p = f->V + 3 * i;
    double e1 = fabs(Ff[3 * i + 1] - p[0]);
    double e2 = fabs(Ff[3 * i + 2] - (g[0] * p[0] + g[1] * p[1] + g[2] * p[2] + g[3]));
    lin_err = fmax(lin_err, fmax(e1, e2));
  }
  CHECK_MSG(lin_err < 1e-12, "linear functions off by %g", lin_err);
  /* A point off the surface is located at its closest surface point: a vertex pushed out
   * along the radius lands back on itself. */
  double P[3];
  for (int d = 0; d < 3; d++) P[d] = 1.5 * c->V[3 * 7 + d];
  int32_t t1[3];
  double w1[3];
  REQUIRE(sm_multires_locate(P, 1, c, t1, w1, &err) == 0);
  double wv = 0;
  for (int t = 0; t < 3; t++) wv += t1[t] == 7 ? w1[t] : 0;
  CHECK_NEAR(wv, 1.0, 1e-12);
  free(Fc), free(Ff), free(tri), free(bary);
  sm_mesh_destroy(c), sm_mesh_destroy(s1), sm_mesh_destroy(f);
}

static double map_exact(const int32_t *T, const int32_t *gt, int32_t n) {
  int32_t k = 0;
  for (int32_t i = 0; i < n; i++) k += T[i] == gt[i];
  return (double)k / n;
}

/* has_tips: the shape has tips (limbs, head), so the coarse match's tip search, on by
 * default whatever the coarse map's confidence (SM_MULTIRES_COARSE_TIPS), must have refined
 * hypotheses even for this self-match, and the map must stay exact. */
static void test_permuted(const sm_mesh *m, int32_t coarse_nv, const char *name, int has_tips) {
  sm_error err;
  int32_t *perm = malloc((size_t)m->nv * sizeof *perm), *inv = malloc((size_t)m->nv * sizeof *inv);
  tm_permutation(perm, m->nv, 4242);
  for (int32_t j = 0; j < m->nv; j++) inv[perm[j]] = j;
  sm_mesh *pm = tm_permuted(m, perm);
  sm_shape_opts so;
  sm_match_opts mo;
  sm_multires_opts ro;
  sm_shape_opts_default(&so);
  sm_match_opts_default(&mo);
  sm_multires_opts_default(&ro);
  ro.mode = SM_MULTIRES_ON;
  ro.coarse_nv = coarse_nv;
  sm_multires_shape *x = NULL, *y = NULL;
  REQUIRE(sm_multires_shape_prepare(m, &so, &ro, &x, &err) == 0);
  REQUIRE(sm_multires_shape_prepare(pm, &so, &ro, &y, &err) == 0);
  const sm_mesh *cx = x->coarse->mesh, *cy = y->coarse->mesh;
  CHECK_MSG(cx->nv < m->nv && cx->nv <= coarse_nv + 2, "%s: coarse level of %d vertices", name,
            cx->nv);
  /* The coarse level is a function of the surface, not of the file's vertex order. */
  CHECK_MSG(cx->nv == cy->nv && cx->nf == cy->nf &&
                !memcmp(cx->V, cy->V, (size_t)3 * cx->nv * sizeof *cx->V) &&
                !memcmp(cx->F, cy->F, (size_t)3 * cx->nf * sizeof *cx->F),
            "%s: permuted copy got another coarse mesh", name);
  sm_multires_result r;
  REQUIRE(sm_multires_match(x, y, &mo, &ro, &r, &err) == 0);
  int32_t *map = malloc((size_t)m->nv * sizeof *map), *back = malloc((size_t)m->nv * sizeof *back);
  sm_multires_to_input(x, y, r.T, map);
  sm_multires_to_input(y, x, r.T_yx, back);
  double ex = map_exact(map, inv, m->nv), ey = map_exact(back, perm, m->nv);
  fprintf(stderr, "%s: %d -> %d coarse vertices, exact %.4f (Y->X %.4f), confidence %.3f, "
          "times: match %.2f s, prolongation %.2f s\n", name, m->nv, cx->nv, ex, ey,
          r.confidence, r.t_match, r.t_prolong);
  CHECK_MSG(ex >= 0.99, "%s: only %.4f of the vertices exact", name, ex);
  CHECK_MSG(ey >= 0.99, "%s: only %.4f of the vertices exact (Y -> X)", name, ey);
  CHECK_MSG(r.confidence > 0.9, "%s: confidence %.3f", name, r.confidence);
  if (has_tips)
    CHECK_MSG(r.coarse.ext_tried > 0, "%s: the coarse tip search did not run (confidence %.3f)",
              name, r.coarse.confidence);
  free(map), free(back), free(perm), free(inv);
  sm_multires_result_free(&r);
  sm_multires_shape_destroy(x);
  sm_multires_shape_destroy(y);
  sm_mesh_destroy(pm);
}

/* The fine snap (sm_multires_snap) on a blob and on a copy of it stretched 1.15x along x
 * and shrunk along y (same connectivity, area about kept, not an isometry): the identity
 * is left alone on the blob itself, and an identity map with every fourth vertex moved to
 * a neighbour (about the share the prolonged extraction gets wrong) is put back. */
static void test_snap(void) {
  sm_mesh *a = NULL, *b = NULL;
  const double one[3] = {1, 1, 1};
  sm_error err;
  REQUIRE(sm_synth_blob(4, 0.2, 3, one, &a, &err) == 0);
  REQUIRE(sm_mesh_alloc(a->nv, a->nf, NULL, &b, &err) == 0);
  memcpy(b->F, a->F, (size_t)3 * a->nf * sizeof *a->F);
  for (int32_t v = 0; v < a->nv; v++) {
    b->V[3 * v] = 1.15 * a->V[3 * v];
    b->V[3 * v + 1] = a->V[3 * v + 1] / 1.15;
    b->V[3 * v + 2] = a->V[3 * v + 2];
  }
  int32_t n = a->nv, *T = malloc((size_t)n * sizeof *T), moved = 0;
  for (int32_t v = 0; v < n; v++) T[v] = v;
  REQUIRE(sm_multires_snap(a, a, 10, T, &err) == 0);
  for (int32_t v = 0; v < n; v++) moved += T[v] != v;
  CHECK_MSG(moved == 0, "snap moved %d vertices of an exact self-map", moved);
  const sm_mesh *targets[2] = {a, b};
  for (int t = 0; t < 2; t++) {
    int32_t off = 0, exact = 0;
    for (int32_t v = 0; v < n; v++) T[v] = v;
    for (int32_t f = 0; f < a->nf; f++) { /* every fourth vertex one edge off */
      int32_t v = a->F[3 * f], w = a->F[3 * f + 1];
      if (v % 4 == 0 && T[v] == v) T[v] = w, off++;
    }
    REQUIRE(sm_multires_snap(a, targets[t], 10, T, &err) == 0);
    for (int32_t v = 0; v < n; v++) exact += T[v] == v;
    fprintf(stderr, "snap onto %s: %d of %d vertices one edge off, %d exact after\n",
            t ? "the stretched copy" : "itself", off, n, exact);
    CHECK_MSG(off > n / 10, "only %d vertices moved off", off);
    CHECK_MSG(exact >= 0.99 * n, "snap onto %s: %d of %d exact", t ? "stretched" : "itself",
              exact, n);
  }
  free(T);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
}

/* An icosphere with a fin: a triangle on an existing edge makes it non-manifold. */
static void test_nonmanifold(void) {
  sm_mesh *s = tm_icosphere(4), *m;
  sm_error err;
  REQUIRE(sm_mesh_alloc(s->nv + 1, s->nf + 1, NULL, &m, NULL) == 0);
  memcpy(m->V, s->V, (size_t)3 * s->nv * sizeof *m->V);
  memcpy(m->F, s->F, (size_t)3 * s->nf * sizeof *m->F);
  int32_t a = s->F[0], b = s->F[1];
  for (int d = 0; d < 3; d++) m->V[3 * s->nv + d] = 0.5 * (s->V[3 * a + d] + s->V[3 * b + d]) * 1.3;
  int32_t fin[3] = {a, b, s->nv};
  memcpy(m->F + 3 * s->nf, fin, sizeof fin);
  sm_mesh *d = NULL;
  CHECK(sm_mesh_decimate(m, 500, &d, &err) == SM_EFORMAT);
  sm_mesh_destroy(d);
  int32_t skipped = -1;
  d = NULL;
  CHECK(sm_mesh_decimate_lenient(m, 500, &d, &skipped, &err) == 0);
  CHECK(skipped == 1);
  CHECK(d && d->nv <= 501);
  sm_mesh_destroy(d);
  sm_shape_opts so;
  sm_multires_opts ro;
  sm_shape_opts_default(&so);
  sm_multires_opts_default(&ro);
  ro.coarse_nv = 500;
  sm_multires_shape *x = NULL;
  CHECK(sm_multires_shape_prepare(m, &so, &ro, &x, &err) == 0);
  if (x) {
    CHECK(x->skipped_faces == 1 && x->mesh->nv == m->nv);
    /* The fin's tip is located on the coarse surface too. */
    int32_t tip = x->mesh->nv - 1;
    CHECK(x->owner[tip] >= 0 && x->owner[tip] < x->coarse->mesh->nv);
  }
  sm_multires_shape_destroy(x);
  sm_mesh_destroy(m);
  sm_mesh_destroy(s);
}

static void test_options(void) {
  sm_multires_opts o;
  sm_multires_opts_default(&o);
  CHECK(o.mode == SM_MULTIRES_AUTO && o.threshold == SM_MULTIRES_THRESHOLD);
  CHECK(!sm_multires_wanted(&o, 15000, SM_MULTIRES_THRESHOLD));
  CHECK(sm_multires_wanted(&o, 5000, SM_MULTIRES_THRESHOLD + 1));
  o.mode = SM_MULTIRES_ON;
  CHECK(sm_multires_wanted(&o, 100, 100));
  o.mode = SM_MULTIRES_OFF;
  CHECK(!sm_multires_wanted(&o, 1000000, 1000000));
  sm_mesh *s = tm_icosphere(2);
  sm_shape_opts so;
  sm_shape_opts_default(&so);
  sm_multires_shape *x = NULL;
  sm_error err;
  sm_multires_opts_default(&o);
  o.coarse_nv = 10;
  CHECK(sm_multires_shape_prepare(s, &so, &o, &x, &err) == SM_EINVAL && !x);
  sm_multires_opts_default(&o);
  o.ring = 0;
  CHECK(sm_multires_shape_prepare(s, &so, &o, &x, &err) == SM_EINVAL && !x);
  sm_multires_opts_default(&o);
  o.fine_iters = -1;
  CHECK(sm_multires_shape_prepare(s, &so, &o, &x, &err) == SM_EINVAL && !x);
  sm_multires_opts_default(&o);
  o.snap_iters = -1;
  CHECK(sm_multires_shape_prepare(s, &so, &o, &x, &err) == SM_EINVAL && !x);
  sm_multires_opts_default(&o);
  o.max_aspect = 1.0;
  CHECK(sm_multires_shape_prepare(s, &so, &o, &x, &err) == SM_EINVAL && !x);
  sm_multires_opts_default(&o);
  o.coarse_tips = 2;
  CHECK(sm_multires_shape_prepare(s, &so, &o, &x, &err) == SM_EINVAL && !x);
  sm_mesh *d = NULL;
  CHECK(sm_mesh_decimate_proxy(s, 20, NAN, &d, NULL, &err) == SM_EINVAL && !d);
  sm_mesh_destroy(s);
}

/* Largest face aspect ratio (longest edge over its height). */
static double max_aspect(const sm_mesh *m) {
  double worst = 0;
  for (int32_t f = 0; f < m->nf; f++) {
    const double *p[3];
    for (int c = 0; c < 3; c++) p[c] = m->V + 3 * (size_t)m->F[3 * (size_t)f + c];
    double e[3][3], l2max = 0;
    for (int c = 0; c < 3; c++) {
      double l2 = 0;
      for (int d = 0; d < 3; d++) {
        e[c][d] = p[(c + 1) % 3][d] - p[c][d];
        l2 += e[c][d] * e[c][d];
      }
      if (l2 > l2max) l2max = l2;
    }
    double cx = e[0][1] * e[2][2] - e[0][2] * e[2][1], cy = e[0][2] * e[2][0] - e[0][0] * e[2][2],
           cz = e[0][0] * e[2][1] - e[0][1] * e[2][0];
    double a = sqrt(cx * cx + cy * cy + cz * cz); /* twice the area = longest edge x height */
    double r = a > 0 ? l2max / a : INFINITY;
    if (r > worst) worst = r;
  }
  return worst;
}

/* The proxy decimation's veto: on an anisotropically stretched blob, where the quadric order
 * alone leaves needles, the proxy's worst face stays near the bound. */
static void test_proxy_aspect(void) {
  sm_mesh *blob = NULL, *a = NULL, *b = NULL;
  const double stretch[3] = {4, 1, 0.5};
  sm_error err;
  REQUIRE(sm_synth_blob(5, 0.2, 3, stretch, &blob, &err) == 0);
  CHECK(sm_mesh_decimate_lenient(blob, 1500, &a, NULL, &err) == 0);
  CHECK(sm_mesh_decimate_proxy(blob, 1500, 10.0, &b, NULL, &err) == 0);
  if (a && b) {
    double wa = max_aspect(a), wb = max_aspect(b);
    fprintf(stderr, "proxy aspect: worst face %.1f unconstrained, %.1f with bound 10 (%d / %d vertices)\n",
            wa, wb, a->nv, b->nv);
    CHECK(wb < wa);
    CHECK(wb <= 20.0);
    CHECK(b->nv <= 1.2 * 1500);
  }
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
  sm_mesh_destroy(blob);
}

int main(int argc, char **argv) {
  test_options();
  test_prolongation();
  test_nonmanifold();
  test_proxy_aspect();
  test_snap();
  sm_mesh *blob = NULL;
  const double one[3] = {1, 1, 1};
  sm_error err;
  REQUIRE(sm_synth_blob(5, 0.2, 3, one, &blob, &err) == 0);
  test_permuted(blob, 1000, "blob", 0);
  sm_mesh_destroy(blob);
  int real = (argc < 2 || strcmp(argv[1], "--synthetic-only")) && !getenv("SM_TEST_SYNTHETIC_ONLY");
  char buf[512];
  const char *homer = sm_test_data("elasticbasis_cartoon_pairs/homerA.obj", buf, sizeof buf);
  if (real && homer) {
    sm_mesh *h = NULL;
    REQUIRE(sm_mesh_read_file(homer, NULL, &h, &err) == 0);
    test_permuted(h, 2000, "homerA", 1);
    sm_mesh_destroy(h);
  } else if (real) {
    fprintf(stderr, "../shared/data absent: homerA case skipped\n");
  }
  return sm_test_finish();
}
