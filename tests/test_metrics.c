/* test_metrics: Dijkstra, geodesic error statistics, bijectivity, coverage, chamfer,
 * Dirichlet energy, GT and map files; and agreement with the reference evaluator
 * ../shared/tools/eval_map.py on real pairs (skipped when the data, python3 or scipy is
 * missing). */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "sm_meshio.h"
#include "sm_metrics.h"
#include "sm_test.h"
#include "sm_testmesh.h"

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static void write_text(const char *path, const char *text) {
  FILE *f = fopen(path, "w");
  REQUIRE(f);
  fputs(text, f);
  fclose(f);
}

/* ---------------------------------------------------------------- Dijkstra */

/* Brute-force shortest paths (Bellman-Ford over the face edges) to compare against. */
static void bellman_ford(const sm_mesh *m, int32_t src, double *d) {
  for (int32_t v = 0; v < m->nv; v++) d[v] = INFINITY;
  d[src] = 0;
  for (int changed = 1; changed;) {
    changed = 0;
    for (int64_t f = 0; f < m->nf; f++)
      for (int c = 0; c < 3; c++) {
        int32_t a = m->F[3 * f + c], b = m->F[3 * f + (c + 1) % 3];
        const double *pa = m->V + 3 * a, *pb = m->V + 3 * b;
        double w = sqrt((pa[0] - pb[0]) * (pa[0] - pb[0]) + (pa[1] - pb[1]) * (pa[1] - pb[1]) +
                        (pa[2] - pb[2]) * (pa[2] - pb[2]));
        if (d[a] + w < d[b] - 1e-15) d[b] = d[a] + w, changed = 1;
        if (d[b] + w < d[a] - 1e-15) d[a] = d[b] + w, changed = 1;
      }
  }
}

static void test_dijkstra_grid(void) {
  sm_mesh *g = tm_grid(3, 3); /* spacing h = 1/3, vertex (i,j) = 4j + i */
  double d[16], ref[16], h = 1.0 / 3, r2 = sqrt(2.0);
  sm_error err;
  REQUIRE(sm_mesh_edge_dijkstra(g, 0, d, &err) == 0);
  CHECK_NEAR(d[0], 0, 1e-15);
  CHECK_NEAR(d[3], 1, 1e-12);              /* along the bottom edge */
  CHECK_NEAR(d[4 + 1], 2 * h, 1e-12);      /* cell (0,0)'s diagonal does not touch (0,0) */
  CHECK_NEAR(d[4 + 2], h + r2 * h, 1e-12); /* (1,0) then cell (1,0)'s diagonal */
  CHECK_NEAR(d[15], 2 * h + 2 * r2 * h, 1e-12);
  for (int32_t s = 0; s < 16; s += 5) {
    REQUIRE(sm_mesh_edge_dijkstra(g, s, d, &err) == 0);
    bellman_ford(g, s, ref);
    for (int v = 0; v < 16; v++) CHECK_NEAR(d[v], ref[v], 1e-12);
  }
  CHECK(sm_mesh_edge_dijkstra(g, 16, d, &err) == SM_ERANGE);
  /* two components: the other one is unreachable */
  REQUIRE(sm_mesh_edge_dijkstra(g, 0, d, &err) == 0);
  sm_mesh *u = tm_union(g, g, 5.0);
  double du[32];
  REQUIRE(sm_mesh_edge_dijkstra(u, 0, du, &err) == 0);
  CHECK(isinf(du[16]) && isinf(du[31]) && fabs(du[15] - d[15]) < 1e-12);
  sm_mesh_destroy(u);
  sm_mesh_destroy(g);
}

/* ---------------------------------------------------------------- geodesic errors */

static void test_geodesic_identity_and_shift(void) {
  sm_mesh *g = tm_grid(6, 6); /* scaled by 2: area 4, spacing 1/3 */
  for (int64_t i = 0; i < 3 * (int64_t)g->nv; i++) g->V[i] *= 2;
  int32_t n = g->nv, *map = malloc((size_t)n * sizeof *map);
  double *e = malloc((size_t)n * sizeof *e), *e1 = malloc((size_t)n * sizeof *e1);
  sm_gt *gt;
  sm_error err;
  REQUIRE(sm_gt_identity(n, &gt, &err) == 0);
  for (int32_t i = 0; i < n; i++) map[i] = i;
  REQUIRE(sm_geodesic_errors(g, map, n, gt, 2, e, &err) == 0);
  double mx = 0;
  for (int32_t i = 0; i < n; i++) mx = fmax(mx, e[i]);
  CHECK(mx == 0);
  /* shift by one vertex along x: every error is one edge (1/3) over sqrt(area) = 2 */
  for (int32_t i = 0; i < n; i++) map[i] = i % 7 == 6 ? i - 1 : i + 1;
  REQUIRE(sm_geodesic_errors(g, map, n, gt, 2, e, &err) == 0);
  for (int32_t i = 0; i < n; i++) CHECK_NEAR(e[i], 1.0 / 6, 1e-12);
  /* one thread and four threads give the same numbers */
  for (int32_t i = 0; i < n; i++) map[i] = (i * 17 + 5) % n;
  REQUIRE(sm_geodesic_errors(g, map, n, gt, 1, e, &err) == 0);
  REQUIRE(sm_geodesic_errors(g, map, n, gt, 4, e1, &err) == 0);
  CHECK(memcmp(e, e1, (size_t)n * sizeof *e) == 0);
  /* out-of-range map entry */
  map[3] = n;
  CHECK(sm_geodesic_errors(g, map, n, gt, 2, e, &err) == SM_ERANGE);
  sm_gt_destroy(gt);
  free(map);
  free(e);
  free(e1);
  sm_mesh_destroy(g);
}

/* Permuting the target (with our own RNG) and remapping GT and map leaves errors alone. */
static void test_geodesic_target_permutation(void) {
  sm_mesh *s = tm_icosphere(2), *t = tm_icosphere(2);
  int32_t n = t->nv, *perm = malloc((size_t)n * sizeof *perm), *inv = malloc((size_t)n * sizeof *inv);
  int32_t *map = malloc((size_t)n * sizeof *map), *pmap = malloc((size_t)n * sizeof *pmap);
  double *e = malloc((size_t)n * sizeof *e), *pe = malloc((size_t)n * sizeof *pe);
  tm_permutation(perm, n, 7);
  for (int32_t i = 0; i < n; i++) inv[perm[i]] = i;
  sm_mesh *pt = tm_permuted(t, perm);
  uint64_t rs = 99;
  for (int32_t i = 0; i < n; i++) map[i] = tm_rand(&rs) < 0.3 ? (int32_t)(tm_rand(&rs) * n) : i;
  for (int32_t i = 0; i < n; i++) pmap[i] = inv[map[i]];
  sm_gt *gt;
  sm_error err;
  REQUIRE(sm_gt_identity(n, &gt, &err) == 0);
  REQUIRE(sm_geodesic_errors(t, map, n, gt, 2, e, &err) == 0);
  /* this map hits fewer vertices than the GT, so searches start from the mapped side:
   * compare with plain single-source searches from the GT side */
  double *dist = malloc((size_t)n * sizeof *dist), sq = sqrt(sm_mesh_face_areas(t, NULL));
  for (int32_t i = 0; i < n; i += 37) {
    REQUIRE(sm_mesh_edge_dijkstra(t, i, dist, &err) == 0);
    CHECK_NEAR(e[i] * sq, dist[map[i]], 1e-12);
  }
  free(dist);
  int32_t *cmap = malloc((size_t)n * sizeof *cmap);
  double *ce = malloc((size_t)n * sizeof *ce);
  for (int32_t i = 0; i < n; i++) cmap[i] = 11;
  REQUIRE(sm_geodesic_errors(t, cmap, n, gt, 2, ce, &err) == 0);
  double *d11 = malloc((size_t)n * sizeof *d11);
  REQUIRE(sm_mesh_edge_dijkstra(t, 11, d11, &err) == 0);
  for (int32_t i = 0; i < n; i++) CHECK_NEAR(ce[i] * sq, d11[i], 1e-12);
  free(cmap), free(ce), free(d11);
  REQUIRE(sm_gt_remap_target(gt, inv, n, &err) == 0);
  REQUIRE(sm_geodesic_errors(pt, pmap, n, gt, 2, pe, &err) == 0);
  for (int32_t i = 0; i < n; i++) CHECK_NEAR(e[i], pe[i], 1e-12);
  sm_gt_destroy(gt);
  free(perm), free(inv), free(map), free(pmap), free(e), free(pe);
  sm_mesh_destroy(s), sm_mesh_destroy(t), sm_mesh_destroy(pt);
}

static void test_summary(void) {
  /* values kept off the thresholds so the expected curve is unambiguous */
  double e[5] = {0.2, 0.0, INFINITY, 0.029, 0.011};
  sm_geo_stats st;
  sm_error err;
  REQUIRE(sm_geo_summarize(e, 5, &st, &err) == 0);
  CHECK(st.n == 5 && st.n_inf == 1);
  CHECK_NEAR(st.mean, 0.24 / 4, 1e-15); /* finite ones only, as eval_map.py */
  CHECK_NEAR(st.median, 0.029, 1e-15);  /* all of them */
  CHECK_NEAR(st.max, 0.2, 1e-15);
  CHECK_NEAR(st.frac_le_0025, 0.4, 1e-15);
  CHECK_NEAR(st.frac_le_005, 0.6, 1e-15);
  CHECK_NEAR(st.frac_le_01, 0.6, 1e-15);
  CHECK_NEAR(sm_metrics_threshold(40), 0.1, 0);
  /* curve: 0.2 for k = 0..4, 0.4 for k = 5..11, 0.6 for k = 12..40 */
  for (int k = 0; k < SM_METRICS_CURVE_N; k++)
    CHECK_NEAR(st.curve[k], k <= 4 ? 0.2 : k <= 11 ? 0.4 : 0.6, 1e-15);
  /* trapezoids of width 0.0025: 4 x 0.2, 0.3, 6 x 0.4, 0.5, 28 x 0.6 */
  CHECK_NEAR(st.auc, (0.8 + 0.3 + 2.4 + 0.5 + 16.8) * 0.0025 / 0.1, 1e-12);
  double even[4] = {0.4, 0.1, 0.3, 0.2};
  REQUIRE(sm_geo_summarize(even, 4, &st, &err) == 0);
  CHECK_NEAR(st.median, 0.25, 1e-15);
  double bad[2] = {0.1, NAN};
  CHECK(sm_geo_summarize(bad, 2, &st, &err) == SM_EINVAL);
  REQUIRE(sm_geo_summarize(NULL, 0, &st, &err) == 0);
  CHECK(isnan(st.mean) && isnan(st.auc));
}

/* ---------------------------------------------------------------- map statistics */

static void test_bijectivity_coverage(void) {
  sm_mesh *m = tm_icosphere(2);
  REQUIRE(sm_mesh_normalize(m, NULL) == 0);
  int32_t n = m->nv, *map = malloc((size_t)n * sizeof *map);
  double b, bm, cov, cyc;
  sm_error err;
  for (int32_t i = 0; i < n; i++) map[i] = i;
  REQUIRE(sm_map_bijectivity(map, n, n, &b, &bm, &err) == 0);
  REQUIRE(sm_map_coverage(m, map, n, &cov, &err) == 0);
  CHECK(b == 1 && bm == 1);
  CHECK_NEAR(cov, 1, 1e-12);
  REQUIRE(sm_map_cycle_error(map, n, map, n, &cyc, &err) == 0);
  CHECK(cyc == 0);
  for (int32_t i = 0; i < n; i++) map[i] = 5;
  REQUIRE(sm_map_bijectivity(map, n, n, &b, &bm, &err) == 0);
  REQUIRE(sm_map_coverage(m, map, n, &cov, &err) == 0);
  double *mass = malloc((size_t)n * sizeof *mass), tot = 0;
  sm_mesh_lumped_mass(m, mass);
  for (int32_t i = 0; i < n; i++) tot += mass[i];
  CHECK_NEAR(b, 1.0 / n, 1e-15);
  CHECK_NEAR(cov, mass[5] / tot, 1e-15);
  /* fewer source than target vertices: distinct / min(n_source, n_target) */
  int32_t half[3] = {0, 1, 1};
  REQUIRE(sm_map_bijectivity(half, 3, n, &b, &bm, &err) == 0);
  CHECK_NEAR(bm, 2.0 / 3, 1e-15);
  /* cycle: X has 3 vertices, Y 2 */
  int32_t xy[3] = {0, 1, 1}, yx[2] = {0, 2};
  REQUIRE(sm_map_cycle_error(xy, 3, yx, 2, &cyc, &err) == 0);
  CHECK_NEAR(cyc, 1.0 / 3, 1e-15); /* 1 -> 1 -> 2 */
  yx[1] = 3;
  CHECK(sm_map_cycle_error(xy, 3, yx, 2, &cyc, &err) == SM_ERANGE);
  free(mass);
  free(map);
  sm_mesh_destroy(m);
}

static void test_dirichlet(void) {
  sm_mesh *m = tm_icosphere(3), *open = tm_grid(5, 4);
  sm_error err;
  double d;
  /* identity of a closed surface at unit area: 2 (sum over a triangle of cot|e|^2 = 4A,
   * so it is exactly 2 for any mesh, open or closed, and any scale) */
  REQUIRE(sm_map_dirichlet(m, NULL, NULL, &d, &err) == 0);
  CHECK_NEAR(d, 2.0, 1e-10);
  REQUIRE(sm_map_dirichlet(open, NULL, NULL, &d, &err) == 0);
  CHECK_NEAR(d, 2.0, 1e-10);
  int32_t *map = malloc((size_t)m->nv * sizeof *map);
  for (int32_t i = 0; i < m->nv; i++) map[i] = i;
  sm_mesh *big = tm_icosphere(3);
  for (int64_t i = 0; i < 3 * (int64_t)big->nv; i++) big->V[i] *= 3; /* target scale is removed */
  REQUIRE(sm_map_dirichlet(m, big, map, &d, &err) == 0);
  CHECK_NEAR(d, 2.0, 1e-10);
  for (int32_t i = 0; i < m->nv; i++) map[i] = 0; /* constant: zero energy */
  REQUIRE(sm_map_dirichlet(m, big, map, &d, &err) == 0);
  CHECK(d == 0);
  free(map);
  sm_mesh_destroy(m), sm_mesh_destroy(big), sm_mesh_destroy(open);
}

/* ---------------------------------------------------------------- chamfer */

static void test_chamfer(void) {
  double A[6] = {0, 0, 0, 1, 0, 0}, B[3] = {0, 0, 2};
  double ab, ba;
  sm_error err;
  REQUIRE(sm_chamfer(A, 2, B, 1, &ab, &ba, &err) == 0);
  CHECK_NEAR(ab, (2 + sqrt(5.0)) / 2, 1e-15);
  CHECK_NEAR(ba, 2, 1e-15);
  CHECK(sm_chamfer(A, 0, B, 1, &ab, &ba, &err) == SM_EINVAL);
  /* k-d tree against brute force, with duplicates */
  int64_t na = 1500, nb = 1000;
  double *P = malloc((size_t)na * 3 * sizeof *P), *Q = malloc((size_t)nb * 3 * sizeof *Q);
  uint64_t s = 3;
  for (int64_t i = 0; i < 3 * na; i++) P[i] = tm_rand(&s);
  for (int64_t i = 0; i < 3 * nb; i++) Q[i] = i < 300 ? P[i] : tm_rand(&s);
  for (int64_t i = 0; i < 3 * 100; i++) P[3 * 1000 + i] = P[i]; /* repeats */
  double ref_ab = 0, ref_ba = 0;
  for (int pass = 0; pass < 2; pass++) {
    const double *X = pass ? Q : P, *Y = pass ? P : Q;
    int64_t nx = pass ? nb : na, ny = pass ? na : nb;
    double sum = 0;
    for (int64_t i = 0; i < nx; i++) {
      double best = INFINITY;
      for (int64_t j = 0; j < ny; j++) {
        double dx = X[3 * i] - Y[3 * j], dy = X[3 * i + 1] - Y[3 * j + 1], dz = X[3 * i + 2] - Y[3 * j + 2];
        best = fmin(best, dx * dx + dy * dy + dz * dz);
      }
      sum += sqrt(best);
    }
    *(pass ? &ref_ba : &ref_ab) = sum / nx;
  }
  REQUIRE(sm_chamfer(P, na, Q, nb, &ab, &ba, &err) == 0);
  CHECK_NEAR(ab, ref_ab, 1e-12);
  CHECK_NEAR(ba, ref_ba, 1e-12);
  free(P);
  free(Q);
  /* 50k points each way, on a surface */
  sm_mesh *sph = tm_icosphere(6); /* 40962 vertices */
  int64_t n = sph->nv;
  double *R = malloc((size_t)n * 3 * sizeof *R);
  for (int64_t i = 0; i < n; i++)
    for (int d = 0; d < 3; d++) R[3 * i + d] = 1.01 * sph->V[3 * ((i * 7919) % n) + d];
  double t0 = now_s();
  REQUIRE(sm_chamfer(sph->V, n, R, n, &ab, &ba, &err) == 0);
  double dt = now_s() - t0;
  fprintf(stderr, "chamfer %lld x %lld points: %.3f s\n", (long long)n, (long long)n, dt);
  CHECK_NEAR(ab, 0.01, 1e-9);
  CHECK_NEAR(ba, 0.01, 1e-9);
  CHECK(dt < 10); /* < 1 s in an optimized build; generous for the sanitizers */
  free(R);
  sm_mesh_destroy(sph);
}

/* ---------------------------------------------------------------- files */

static void test_gt_files(void) {
  char p1[512], p2[512];
  snprintf(p1, sizeof p1, "%s/metrics_gt1.txt", SM_TEST_TMP);
  snprintf(p2, sizeof p2, "%s/metrics_gt2.txt", SM_TEST_TMP);
  sm_gt *gt;
  sm_error err;
  write_text(p1, "# comment\n2.000000000000000000e+00\n\n  1 \r\n0.0e+00 # zero\n");
  REQUIRE(sm_gt_load_dense(p1, 0, 3, 3, &gt, &err) == 0);
  CHECK(gt->n == 3 && gt->src[2] == 2 && gt->tgt[0] == 2 && gt->tgt[1] == 1 && gt->tgt[2] == 0);
  CHECK(sm_gt_is_dense(gt, 3, NULL) && !sm_gt_is_dense(gt, 4, NULL));
  sm_gt_destroy(gt);
  REQUIRE(sm_gt_load_inverse(p1, 0, 3, 3, &gt, &err) == 0);
  CHECK(gt->n == 3 && gt->tgt[0] == 0 && gt->src[0] == 2);
  sm_gt_destroy(gt);
  /* out of range: target 2 with only 2 target vertices, on file line 2 */
  CHECK(sm_gt_load_dense(p1, 0, 3, 2, &gt, &err) == SM_ERANGE);
  CHECK_MSG(strstr(err.msg, "metrics_gt1.txt:2:") != NULL, "%s", err.msg);
  /* more lines than source vertices: line 5 holds source vertex 2 */
  CHECK(sm_gt_load_dense(p1, 0, 2, 3, &gt, &err) == SM_ERANGE);
  CHECK_MSG(strstr(err.msg, "metrics_gt1.txt:5:") != NULL, "%s", err.msg);
  /* base 1: the 0 becomes -1 */
  CHECK(sm_gt_load_dense(p1, 1, 3, 3, &gt, &err) == SM_ERANGE);
  write_text(p2, "1 3\n2 1\n");
  REQUIRE(sm_gt_load_pairs(p2, 1, 2, 3, &gt, &err) == 0);
  CHECK(gt->n == 2 && gt->src[0] == 0 && gt->tgt[0] == 2 && gt->src[1] == 1 && gt->tgt[1] == 0);
  sm_gt_destroy(gt);
  write_text(p1, "3\n1\n");
  REQUIRE(sm_gt_load_vts(p1, p2, 1, 3, 3, &gt, &err) != 0); /* p2 has 2 columns */
  write_text(p2, "2\n2\n");
  REQUIRE(sm_gt_load_vts(p1, p2, 1, 3, 3, &gt, &err) == 0);
  CHECK(gt->n == 2 && gt->src[0] == 2 && gt->tgt[0] == 1 && gt->src[1] == 0);
  sm_gt_destroy(gt);
  write_text(p2, "2\n");
  CHECK(sm_gt_load_vts(p1, p2, 1, 3, 3, &gt, &err) == SM_EFORMAT);
  write_text(p1, "1\nx\n");
  CHECK(sm_gt_load_dense(p1, 0, 3, 3, &gt, &err) == SM_EFORMAT);
  CHECK_MSG(strstr(err.msg, ":2:") != NULL, "%s", err.msg);
  CHECK(sm_gt_load_dense("/nonexistent/gt.txt", 0, 3, 3, &gt, &err) == SM_EIO);
  /* map files round trip; wrong length and range are refused */
  int32_t map[4] = {3, 0, 2, 2}, *back;
  REQUIRE(sm_map_save(p1, map, 4, &err) == 0);
  REQUIRE(sm_map_load(p1, 4, 4, &back, &err) == 0);
  CHECK(memcmp(map, back, sizeof map) == 0);
  free(back);
  CHECK(sm_map_load(p1, 5, 4, &back, &err) == SM_EFORMAT);
  CHECK(sm_map_load(p1, 4, 3, &back, &err) == SM_ERANGE);
  remove(p1);
  remove(p2);
}

/* Degenerate faces (repeated index, zero area) must not crash or poison the numbers. */
static void test_degenerate_faces(void) {
  sm_mesh *g = tm_grid(4, 4), *d;
  REQUIRE(sm_mesh_alloc(g->nv + 1, g->nf + 2, NULL, &d, NULL) == 0);
  memcpy(d->V, g->V, (size_t)g->nv * 3 * sizeof *d->V);
  d->V[3 * g->nv] = 0.5, d->V[3 * g->nv + 1] = 0, d->V[3 * g->nv + 2] = 0; /* on an edge */
  memcpy(d->F, g->F, (size_t)g->nf * 3 * sizeof *d->F);
  int32_t extra[6] = {0, 0, 6, 0, 4, g->nv}; /* repeated index; collinear (zero area) */
  memcpy(d->F + 3 * g->nf, extra, sizeof extra);
  int32_t *map = malloc((size_t)d->nv * sizeof *map);
  for (int32_t i = 0; i < d->nv; i++) map[i] = d->nv - 1 - i;
  sm_gt *gt;
  sm_metrics mt;
  sm_error err;
  REQUIRE(sm_gt_identity(d->nv, &gt, &err) == 0);
  REQUIRE(sm_metrics_compute(d, d, map, gt, 2, &mt, &err) == 0);
  CHECK(isfinite(mt.geo.mean) && isfinite(mt.coverage) && isfinite(mt.dirichlet) &&
        isfinite(mt.chamfer) && isfinite(mt.dirichlet_gt));
  CHECK_NEAR(mt.dirichlet_source_identity, 2.0, 1e-10);
  CHECK(mt.bijectivity == 1);
  sm_gt_destroy(gt);
  free(map);
  sm_mesh_destroy(g), sm_mesh_destroy(d);
}

/* ---------------------------------------------------------------- eval_map.py agreement */

static const char *find_python(void) {
  static const char *cand[] = {"/usr/bin/python3", "python3"};
  char cmd[256];
  for (size_t i = 0; i < sizeof cand / sizeof *cand; i++) {
    snprintf(cmd, sizeof cmd, "%s -c 'import numpy, scipy.sparse.csgraph' >/dev/null 2>&1", cand[i]);
    if (system(cmd) == 0) return cand[i];
  }
  return NULL;
}

static char *slurp(const char *path) {
  FILE *f = fopen(path, "rb");
  if (!f) return NULL;
  fseek(f, 0, SEEK_END);
  long n = ftell(f);
  fseek(f, 0, SEEK_SET);
  char *s = malloc((size_t)n + 1);
  size_t got = fread(s, 1, (size_t)n, f);
  s[got] = 0;
  fclose(f);
  return s;
}

/* The number after "key": in eval_map.py's JSON (NaN/Infinity included: strtod reads them). */
static int json_num(const char *js, const char *key, double *v) {
  char pat[128];
  snprintf(pat, sizeof pat, "\"%s\":", key);
  const char *p = strstr(js, pat);
  if (!p) return 0;
  *v = strtod(p + strlen(pat), NULL);
  return 1;
}

static int json_curve(const char *js, double *c) {
  const char *p = strstr(js, "\"frac\": [");
  if (!p) return 0;
  p += strlen("\"frac\": [");
  for (int k = 0; k < SM_METRICS_CURVE_N; k++) {
    char *end;
    c[k] = strtod(p, &end);
    if (end == p) return 0;
    p = end;
    while (*p == ',' || *p == ' ' || *p == '\n') p++;
  }
  return 1;
}

static int agree(double ours, double theirs) {
  if (isnan(ours) || isnan(theirs)) return isnan(ours) && isnan(theirs);
  double d = fabs(ours - theirs);
  return d <= 1e-6 || d <= 0.01 * fmax(fabs(ours), fabs(theirs));
}

static void compare_one(const char *label, const char *json_path, const sm_metrics *m) {
  char *js = slurp(json_path);
  CHECK_MSG(js != NULL, "eval_map.py wrote no %s", json_path);
  if (!js) return;
  struct { const char *key; double ours; } row[] = {
      {"n_gt_pairs", (double)m->geo.n}, {"n_inf", (double)m->geo.n_inf},
      {"mean_geo_err", m->geo.mean}, {"median_geo_err", m->geo.median},
      {"max_geo_err", m->geo.max}, {"frac_le_0.025", m->geo.frac_le_0025},
      {"frac_le_0.05", m->geo.frac_le_005}, {"frac_le_0.1", m->geo.frac_le_01},
      {"auc_0_0.1", m->geo.auc}, {"bijectivity", m->bijectivity},
      {"distinct_over_min_n", m->distinct_over_min_n}, {"coverage", m->coverage},
      {"dirichlet", m->dirichlet}, {"dirichlet_source_identity", m->dirichlet_source_identity},
      {"dirichlet_gt", m->dirichlet_gt}};
  for (size_t i = 0; i < sizeof row / sizeof *row; i++) {
    double theirs;
    int found = json_num(js, row[i].key, &theirs);
    CHECK_MSG(found, "%s: %s missing from eval_map.py output", label, row[i].key);
    if (!found) continue;
    fprintf(stderr, "  %-10s %-26s ours %-14.8g eval_map %-14.8g\n", label, row[i].key,
            row[i].ours, theirs);
    CHECK_MSG(agree(row[i].ours, theirs), "%s: %s ours %.10g eval_map %.10g", label,
              row[i].key, row[i].ours, theirs);
  }
  double curve[SM_METRICS_CURVE_N], worst = 0;
  CHECK_MSG(json_curve(js, curve), "%s: accuracy curve missing", label);
  for (int k = 0; k < SM_METRICS_CURVE_N; k++) {
    CHECK_MSG(agree(m->geo.curve[k], curve[k]), "%s: curve[%d] ours %.10g eval_map %.10g",
              label, k, m->geo.curve[k], curve[k]);
    worst = fmax(worst, fabs(m->geo.curve[k] - curve[k]));
  }
  fprintf(stderr, "  %-10s accuracy curve: largest difference %.3g over 41 thresholds\n", label, worst);
  free(js);
}

typedef struct pair_case {
  const char *tag, *src, *tgt, *gt;
} pair_case;

#define NMAPS 3
static const char *map_names[NMAPS] = {"gt", "noisy20", "const"};

/* Map m of the pair: the GT, the GT with 20% of entries replaced by random target
 * vertices (fixed seed), a constant map. */
static void make_map(int m, const sm_gt *gt, int32_t nt, int32_t *map) {
  uint64_t s = 20240611;
  for (int64_t i = 0; i < gt->n; i++) map[gt->src[i]] = gt->tgt[i];
  for (int64_t i = 0; m == 1 && i < gt->n; i++)
    if (tm_rand(&s) < 0.2) map[i] = (int32_t)(tm_rand(&s) * nt);
  for (int64_t i = 0; m == 2 && i < gt->n; i++) map[i] = nt / 3;
}

/* One python process per pair so eval_map.py's in-process Dijkstra cache serves all its
 * maps (the rows depend only on the GT); the pairs run concurrently. */
static void append_eval_cmd(char *cmd, size_t cap, const char *py, const pair_case *pc) {
  char tools[512], part[4096];
  snprintf(tools, sizeof tools, "%s/../tools", SM_DATA_DIR);
  snprintf(part, sizeof part,
           "%s -c 'import sys; sys.path.insert(0, sys.argv[1]); import eval_map as E; "
           "[E.main(a.split(\"|\")) for a in sys.argv[2:]]' '%s'", py, tools);
  strncat(cmd, part, cap - strlen(cmd) - 1);
  for (int m = 0; m < NMAPS; m++) {
    snprintf(part, sizeof part,
             " '%s/%s|%s/%s|%s/metrics_%s_%s.txt|--gt-kind|dense|--gt|%s/%s|--gt-base|0|"
             "--out|%s/metrics_%s_%s.json'",
             SM_DATA_DIR, pc->src, SM_DATA_DIR, pc->tgt, SM_TEST_TMP, pc->tag, map_names[m],
             SM_DATA_DIR, pc->gt, SM_TEST_TMP, pc->tag, map_names[m]);
    strncat(cmd, part, cap - strlen(cmd) - 1);
  }
  strncat(cmd, " >/dev/null &\n", cap - strlen(cmd) - 1);
}

typedef struct pair_data {
  sm_mesh *s, *t;
  sm_gt *gt;
  int32_t *maps[NMAPS];
} pair_data;

static void load_pair(const pair_case *pc, pair_data *d) {
  char ps[512], pt[512], pg[512];
  sm_error err;
  snprintf(ps, sizeof ps, "%s/%s", SM_DATA_DIR, pc->src);
  snprintf(pt, sizeof pt, "%s/%s", SM_DATA_DIR, pc->tgt);
  snprintf(pg, sizeof pg, "%s/%s", SM_DATA_DIR, pc->gt);
  REQUIRE(sm_mesh_read_file(ps, NULL, &d->s, &err) == 0);
  REQUIRE(sm_mesh_read_file(pt, NULL, &d->t, &err) == 0);
  REQUIRE(sm_gt_load_dense(pg, 0, d->s->nv, d->t->nv, &d->gt, &err) == 0);
  REQUIRE(d->gt->n == d->s->nv);
  for (int m = 0; m < NMAPS; m++) {
    char path[512];
    d->maps[m] = malloc((size_t)d->s->nv * sizeof *d->maps[m]);
    make_map(m, d->gt, d->t->nv, d->maps[m]);
    snprintf(path, sizeof path, "%s/metrics_%s_%s.txt", SM_TEST_TMP, pc->tag, map_names[m]);
    REQUIRE(sm_map_save(path, d->maps[m], d->s->nv, &err) == 0);
  }
}

static void test_eval_map_agreement(void) {
  if (!sm_test_data_present()) {
    fprintf(stderr, "eval_map.py agreement: no ../shared/data, skipped\n");
    return;
  }
  const char *py = find_python();
  static const pair_case cases[2] = {
      {"homer", "elasticbasis_cartoon_pairs/homerA.obj", "elasticbasis_cartoon_pairs/homerB.obj",
       "elasticbasis_cartoon_pairs/gt_homerA_homerB.txt"},
      {"lioncat", "pyfm_cat_lion/lion-00.off", "pyfm_cat_lion/cat-00.off", "pyfm_cat_lion/lion2cat"}};
  pair_data d[2];
  static char cmd[32768];
  cmd[0] = 0;
  for (int c = 0; c < 2; c++) {
    load_pair(&cases[c], &d[c]);
    if (py) append_eval_cmd(cmd, sizeof cmd, py, &cases[c]);
  }
  strncat(cmd, "wait\n", sizeof cmd - strlen(cmd) - 1);
  /* eval_map.py runs in the background while we compute ours */
  double t0 = now_s();
  FILE *ev = py ? popen(cmd, "r") : NULL;
  if (!py) fprintf(stderr, "python3 with numpy and scipy not found: eval_map.py comparison skipped\n");
  sm_metrics mt[2][NMAPS];
  for (int c = 0; c < 2; c++)
    for (int m = 0; m < NMAPS; m++) {
      sm_error err;
      REQUIRE(sm_metrics_compute(d[c].s, d[c].t, d[c].maps[m], d[c].gt, 2, &mt[c][m], &err) == 0);
      fprintf(stderr, "%s/%s: geodesic errors in %.3f s (%d -> %d vertices), chamfer %.5g\n",
              cases[c].tag, map_names[m], mt[c][m].geodesic_seconds, mt[c][m].n_source,
              mt[c][m].n_target, mt[c][m].chamfer);
    }
  fprintf(stderr, "ours, all six maps: %.1f s\n", now_s() - t0);
  if (ev) {
    CHECK_MSG(pclose(ev) == 0, "eval_map.py failed: %s", cmd);
    fprintf(stderr, "eval_map.py (both pairs, concurrently): %.1f s\n", now_s() - t0);
  }
  for (int c = 0; c < 2; c++) {
    for (int m = 0; m < NMAPS; m++) {
      char label[64], json[512];
      snprintf(label, sizeof label, "%s/%s", cases[c].tag, map_names[m]);
      snprintf(json, sizeof json, "%s/metrics_%s_%s.json", SM_TEST_TMP, cases[c].tag, map_names[m]);
      if (ev) compare_one(label, json, &mt[c][m]);
      free(d[c].maps[m]);
    }
    sm_gt_destroy(d[c].gt);
    sm_mesh_destroy(d[c].s);
    sm_mesh_destroy(d[c].t);
  }
}

int main(void) {
  test_dijkstra_grid();
  test_geodesic_identity_and_shift();
  test_geodesic_target_permutation();
  test_summary();
  test_bijectivity_coverage();
  test_dirichlet();
  test_chamfer();
  test_gt_files();
  test_degenerate_faces();
  test_eval_map_agreement();
  if (!sm_test_data_present() && sm_test_failures == 0) {
    sm_test_finish();
    SM_SKIP("data-free checks passed; %s absent, eval_map.py agreement not run", SM_DATA_DIR);
  }
  return sm_test_finish();
}
