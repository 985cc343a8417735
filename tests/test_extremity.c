/* test_extremity: tips of a shape and the tip hypotheses (sm_extremity), on a "star": a
 * sphere with five spikes of distinct lengths in known directions, so the tips and their
 * correspondence are known exactly. Also the reusable path search (sm_edge_paths) against
 * the one-shot Dijkstra, the tip search inside sm_match on a permuted copy, and the
 * geodesic directions and turns its choice uses (sm_confidence: a sphere's known
 * directions, a copy's and a mirror's turns). With ../shared/data: the tips of two real
 * women (SM_EXT_MIN_AGD keeps trunk bumps out), checked against the ground truth. */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "sm_confidence.h"
#include "sm_extremity.h"
#include "sm_knn.h"
#include "sm_match.h"
#include "sm_meshio.h"
#include "sm_metrics.h"
#include "sm_test.h"
#include "sm_testmesh.h"

#define N_SPIKES 5
static const double SPIKE_DIR[N_SPIKES][3] = {
    {0, 0, 1}, {1, 0, -0.2}, {-1, 0, -0.2}, {0, 1, -0.6}, {0, -1, -0.6}};
static const double SPIKE_LEN[N_SPIKES] = {1.6, 1.3, 1.1, 0.9, 0.75};

static void unit(const double *a, double *u) {
  double n = sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
  for (int d = 0; d < 3; d++) u[d] = a[d] / n;
}

/* Sphere pushed out along each spike direction by a narrow Gaussian of the spike's length,
 * then at unit area (the scale sm_extremity's radius is defined at). */
static sm_mesh *star(void) {
  sm_mesh *m = tm_icosphere(4);
  for (int32_t v = 0; v < m->nv; v++) {
    double *p = m->V + 3 * v, r = 1;
    for (int s = 0; s < N_SPIKES; s++) {
      double u[3];
      unit(SPIKE_DIR[s], u);
      double c = p[0] * u[0] + p[1] * u[1] + p[2] * u[2];
      r += SPIKE_LEN[s] * exp(-25 * (1 - c));
    }
    for (int d = 0; d < 3; d++) p[d] *= r;
  }
  sm_error err = {0};
  REQUIRE(sm_mesh_normalize(m, &err) == 0);
  return m;
}

/* Index of the spike whose direction is closest to vertex v's direction. */
static int spike_of(const sm_mesh *m, int32_t v) {
  const double *p = m->V + 3 * v;
  double u[3], best = -2;
  int bs = -1;
  unit(p, u);
  for (int s = 0; s < N_SPIKES; s++) {
    double d[3];
    unit(SPIKE_DIR[s], d);
    double c = u[0] * d[0] + u[1] * d[1] + u[2] * d[2];
    if (c > best) best = c, bs = s;
  }
  return best > 0.98 ? bs : -1; /* within ~11 degrees of a spike axis */
}

static void test_paths_match_dijkstra(void) {
  sm_mesh *m = star();
  sm_error err = {0};
  sm_edge_paths *p;
  REQUIRE(sm_edge_paths_create(m, &p, &err) == 0);
  double *a = malloc((size_t)m->nv * sizeof *a), *b = malloc((size_t)m->nv * sizeof *b);
  int32_t src[3] = {0, m->nv / 2, m->nv - 1};
  for (int k = 0; k < 3; k++) { /* repeated runs on one handle give the one-shot answer */
    REQUIRE(sm_edge_paths_run(p, src[k], a, &err) == 0);
    REQUIRE(sm_mesh_edge_dijkstra(m, src[k], b, &err) == 0);
    for (int32_t v = 0; v < m->nv; v++) CHECK(a[v] == b[v]);
  }
  CHECK(sm_edge_paths_run(p, m->nv, a, &err) == SM_ERANGE);
  free(a);
  free(b);
  sm_edge_paths_destroy(p);
  sm_mesh_destroy(m);
}

static void test_star_tips(void) {
  sm_mesh *m = star();
  sm_error err = {0};
  sm_ext_set *t;
  REQUIRE(sm_ext_detect(m, &t, &err) == 0);
  CHECK(t->n == N_SPIKES);
  int seen[N_SPIKES] = {0};
  for (int i = 0; i < t->n; i++) {
    int s = spike_of(m, t->v[i]);
    CHECK(s >= 0);
    if (s >= 0) seen[s]++;
    /* by decreasing AGD: the longest spike's tip is the farthest out */
    if (i > 0) CHECK(t->agd[i] <= t->agd[i - 1]);
    CHECK(t->dist[i][i] == 0);
    for (int j = 0; j < t->n; j++) CHECK(fabs(t->dist[i][j] - t->dist[j][i]) < 1e-12);
  }
  for (int s = 0; s < N_SPIKES; s++) CHECK(seen[s] == 1);
  CHECK(t->n > 0 && spike_of(m, t->v[0]) == 0);
  sm_ext_destroy(t);
  sm_mesh_destroy(m);
}

/* ---- real shapes (../shared/data, skipped when absent) ------------------------------ */

#define TND SM_DATA_DIR "/tosca_nonisometric_dev/"
#define TND_ROWS 900

static sm_mesh *read_unit(const char *name, int32_t *vts) {
  char path[1024];
  sm_error err = {0};
  sm_mesh *m = NULL;
  snprintf(path, sizeof path, TND "meshes/%s.off.gz", name);
  REQUIRE(sm_mesh_read_file(path, NULL, &m, &err) == 0);
  REQUIRE(sm_mesh_normalize(m, &err) == 0);
  snprintf(path, sizeof path, TND "corres/%s.vts", name);
  FILE *f = fopen(path, "r");
  REQUIRE(f != NULL);
  for (int r = 0; r < TND_ROWS; r++) {
    REQUIRE(fscanf(f, "%d", &vts[r]) == 1);
    vts[r]--; /* 1-based */
  }
  fclose(f);
  return m;
}

static double dist3(const sm_mesh *m, int32_t a, int32_t b) {
  return sqrt(sm_knn_dist2(m->V + 3 * (size_t)a, m->V + 3 * (size_t)b, 3));
}

/* 8_woman_07 holds her arms low: two local AGD maxima on her trunk (AGD 0.85 of the mean)
 * used to be tips, and took her head's place in every assignment with a gorilla. Her
 * tips are her head, hands and feet: the points the ground truth matches to 8_woman_06's
 * five tips (nearest truth row to each), within 0.1 at unit area. */
static void test_real_tips(void) {
  if (!sm_test_data_present()) {
    fprintf(stderr, "../shared/data absent: real tips skipped\n");
    return;
  }
  static int32_t ga[TND_ROWS], gb[TND_ROWS];
  sm_mesh *a = read_unit("8_woman_06", ga), *b = read_unit("8_woman_07", gb);
  sm_error err = {0};
  sm_ext_set *ta, *tb;
  REQUIRE(sm_ext_detect(a, &ta, &err) == 0);
  REQUIRE(sm_ext_detect(b, &tb, &err) == 0);
  CHECK_MSG(ta->n == 5 && tb->n == 5, "tips: woman_06 %d, woman_07 %d (want 5 each)", ta->n,
            tb->n);
  for (int i = 0; i < ta->n; i++) {
    int row = 0;
    for (int r = 1; r < TND_ROWS; r++)
      if (dist3(a, ga[r], ta->v[i]) < dist3(a, ga[row], ta->v[i])) row = r;
    double best = INFINITY;
    for (int j = 0; j < tb->n; j++) best = fmin(best, dist3(b, gb[row], tb->v[j]));
    CHECK_MSG(best < 0.1, "woman_06 tip %d: no woman_07 tip within 0.1 of its image (%.3f)", i,
              best);
  }
  sm_ext_destroy(ta);
  sm_ext_destroy(tb);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
}

/* A permuted, rotated copy: the cheapest hypothesis pairs every tip with its own image,
 * at a small cost; any other assignment costs clearly more (the spikes differ in length). */
static void test_hypotheses_on_copy(void) {
  sm_mesh *x = star();
  int32_t *perm = malloc((size_t)x->nv * sizeof *perm);
  tm_permutation(perm, x->nv, 7);
  sm_mesh *y = tm_permuted(x, perm);
  const double shift[3] = {0.2, 0.1, -0.3};
  tm_rigid(y, 0.3, -1.1, 0.7, 1.0, shift);
  sm_error err = {0};
  sm_ext_set *tx, *ty;
  REQUIRE(sm_ext_detect(x, &tx, &err) == 0);
  REQUIRE(sm_ext_detect(y, &ty, &err) == 0);
  sm_ext_hypothesis h[4];
  int nh;
  REQUIRE(sm_ext_hypotheses(tx, ty, 4, h, &nh, &err) == 0);
  CHECK(nh == 4);
  CHECK(h[0].m == N_SPIKES);
  for (int a = 0; a < h[0].m; a++) /* y's vertex u is x's vertex perm[u] */
    CHECK(perm[h[0].pairs[2 * a + 1]] == h[0].pairs[2 * a]);
  /* not 0: the AGD is a mean over farthest-point samples that start at vertex 0, which
   * the permutation moves (measured 0.029 for the right assignment, 0.073 next) */
  CHECK_MSG(h[0].cost < 0.05 && h[1].cost > 1.5 * h[0].cost, "costs %g %g", h[0].cost,
            h[1].cost);
  for (int i = 1; i < nh; i++) CHECK(h[i].cost >= h[i - 1].cost);
  /* too few tips to fix a correspondence: no hypothesis */
  sm_ext_set few = *tx;
  few.n = 2;
  REQUIRE(sm_ext_hypotheses(&few, ty, 4, h, &nh, &err) == 0);
  CHECK(nh == 0);
  sm_ext_destroy(tx);
  sm_ext_destroy(ty);
  free(perm);
  sm_mesh_destroy(x);
  sm_mesh_destroy(y);
}

/* The tip search forced on (SM_EXT_ALWAYS) inside sm_match on a permuted copy: it refines
 * every hypothesis and must keep an exact map (the right tip assignment, or the descriptor
 * start, is exact; a wrong one cannot be more confident). */
static void test_match_always(void) {
  sm_mesh *x = star();
  int32_t *perm = malloc((size_t)x->nv * sizeof *perm);
  tm_permutation(perm, x->nv, 11);
  sm_mesh *y = tm_permuted(x, perm);
  sm_shape_opts so;
  sm_shape_opts_default(&so);
  so.k_lb = 40;
  so.k_elastic = 0;
  sm_error err = {0};
  sm_shape *sx, *sy;
  REQUIRE(sm_shape_prepare(x, &so, &sx, &err) == 0);
  REQUIRE(sm_shape_prepare(y, &so, &sy, &err) == 0);
  sm_match_opts o;
  sm_match_opts_default(&o);
  o.basis = SM_MATCH_LB;
  o.k1 = 40;
  o.extremities = SM_EXT_ALWAYS;
  o.ext_hypotheses = 3;
  sm_match_result r;
  REQUIRE(sm_match(sx, sy, &o, &r, &err) == 0);
  CHECK(r.ext_tried == 3);
  int32_t exact = 0, *in = malloc((size_t)x->nv * sizeof *in);
  sm_match_to_input(sx, sy, r.T, in);
  for (int32_t v = 0; v < x->nv; v++) exact += in[v] >= 0 && perm[in[v]] == v;
  free(in);
  CHECK(exact > 0.98 * r.nx);
  CHECK(r.confidence > 0.9);
  CHECK(r.T_yx == NULL); /* not asked for */
  /* The hypotheses on 3 threads: the same maps judged in the same order, so the same
   * result, bit for bit. */
  sm_match_opts o3 = o;
  o3.threads = 3;
  sm_match_result r3;
  REQUIRE(sm_match(sx, sy, &o3, &r3, &err) == 0);
  CHECK(r3.ext_tried == r.ext_tried && r3.ext_hypothesis == r.ext_hypothesis);
  CHECK(memcmp(r3.T, r.T, (size_t)r.nx * sizeof *r.T) == 0);
  CHECK(r3.confidence == r.confidence && r3.turns == r.turns);
  sm_match_result_free(&r3);
  sm_match_result_free(&r);
  o.ext_hypotheses = SM_MATCH_EXT_MAX_H + 1;
  CHECK(sm_match(sx, sy, &o, &r, &err) == SM_EINVAL);
  sm_shape_destroy(sx);
  sm_shape_destroy(sy);
  free(perm);
  sm_mesh_destroy(x);
  sm_mesh_destroy(y);
}

/* Unit-area ellipsoid with three distinct axes: mirror symmetric in x (the icosphere's
 * vertex set is symmetric under each coordinate reflection), with no other symmetry that
 * keeps orientation and the distances in play. */
static sm_mesh *ellipsoid(void) {
  sm_mesh *m = tm_icosphere(4);
  const double axis[3] = {1.0, 1.6, 2.3};
  for (int32_t v = 0; v < m->nv; v++)
    for (int d = 0; d < 3; d++) m->V[3 * v + d] *= axis[d];
  sm_error err = {0};
  REQUIRE(sm_mesh_normalize(m, &err) == 0);
  return m;
}

/* Geodesic directions on a sphere are known: at c toward a, the tangent projection of the
 * chord a - c (a great circle). The probe's fit of the edge-path distance must agree. */
static void test_directions_on_sphere(void) {
  sm_mesh *m = tm_icosphere(4);
  sm_error err = {0};
  REQUIRE(sm_mesh_normalize(m, &err) == 0);
  sm_ext_set *t;
  REQUIRE(sm_ext_detect(m, &t, &err) == 0);
  double worst = 0, mean = 0;
  int n = 0;
  for (int c = 0; c < SM_EXT_SOURCES; c++) {
    const double *pc = m->V + 3 * t->src[c];
    double nrm[3], e1[3], e2[3];
    unit(pc, nrm); /* sphere centred at the origin after normalization */
    for (int a = 0; a < SM_EXT_SOURCES; a++) {
      const double *pa = m->V + 3 * t->src[a];
      double ch[3] = {pa[0] - pc[0], pa[1] - pc[1], pa[2] - pc[2]};
      double dn = ch[0] * nrm[0] + ch[1] * nrm[1] + ch[2] * nrm[2];
      for (int d = 0; d < 3; d++) e1[d] = ch[d] - dn * nrm[d];
      double len = sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]);
      if (a == c || len < 0.05) continue; /* itself, or (nearly) antipodal */
      /* the probe's 2D direction lifted back to 3D through the same tangent frame */
      double u[3] = {1, 0, 0};
      if (fabs(nrm[0]) > 0.8) u[0] = 0, u[1] = 1;
      double un = u[0] * nrm[0] + u[1] * nrm[1] + u[2] * nrm[2];
      for (int d = 0; d < 3; d++) e2[d] = u[d] - un * nrm[d];
      unit(e2, e2);
      double e3[3] = {nrm[1] * e2[2] - nrm[2] * e2[1], nrm[2] * e2[0] - nrm[0] * e2[2],
                      nrm[0] * e2[1] - nrm[1] * e2[0]};
      const double *g = t->src_dir[c][a];
      double lift[3], gl = hypot(g[0], g[1]);
      for (int d = 0; d < 3; d++) lift[d] = (g[0] * e2[d] + g[1] * e3[d]) / gl;
      double cosang = (lift[0] * e1[0] + lift[1] * e1[1] + lift[2] * e1[2]) / len;
      double ang = acos(cosang > 1 ? 1 : cosang) * 180 / M_PI;
      worst = ang > worst ? ang : worst;
      mean += ang, n++;
    }
  }
  mean /= n;
  /* edge paths zigzag along the mesh, so their distance field is not exactly geodesic
   * (measured: mean 5.9, worst 18 degrees); a wrong frame or sign would be off by 90-180 */
  CHECK_MSG(mean < 8 && worst < 25, "direction error mean %.2f, worst %.2f degrees", mean,
            worst);
  sm_ext_destroy(t);
  sm_mesh_destroy(m);
}

/* Turns: a permuted copy keeps every turn (+1, no distortion); the mirror image x -> -x of
 * the ellipsoid, an isometry, reverses every turn (-1) with no distortion either: the one
 * thing the distortion cannot see. */
static void test_turns_copy_and_mirror(void) {
  sm_mesh *x = ellipsoid();
  int32_t *perm = malloc((size_t)x->nv * sizeof *perm), *T = malloc((size_t)x->nv * sizeof *T);
  tm_permutation(perm, x->nv, 5);
  sm_mesh *y = tm_permuted(x, perm);
  sm_error err = {0};
  sm_ext_set *t;
  sm_edge_paths *py, *px;
  REQUIRE(sm_ext_detect(x, &t, &err) == 0);
  REQUIRE(sm_edge_paths_create(y, &py, &err) == 0);
  REQUIRE(sm_edge_paths_create(x, &px, &err) == 0);
  for (int32_t u = 0; u < y->nv; u++) T[perm[u]] = u; /* y's vertex u is x's perm[u] */
  double dist, turns;
  REQUIRE(sm_map_turns(py, y, T, t->src, &t->src_dist[0][0], &t->src_dir[0][0][0],
                       SM_EXT_SOURCES, SM_EXT_SOURCES, &dist, &turns, &err) == 0);
  CHECK_MSG(turns > 0.99 && dist < 1e-12, "copy: turns %g distortion %g", turns, dist);
  int exact = 1;
  for (int32_t v = 0; v < x->nv; v++) {
    const double *p = x->V + 3 * v;
    double best = INFINITY;
    for (int32_t w = 0; w < x->nv; w++) {
      const double *q = x->V + 3 * w;
      double d = fabs(p[0] + q[0]) + fabs(p[1] - q[1]) + fabs(p[2] - q[2]);
      if (d < best) best = d, T[v] = w;
    }
    exact &= best < 1e-9;
  }
  REQUIRE(exact);
  REQUIRE(sm_map_turns(px, x, T, t->src, &t->src_dist[0][0], &t->src_dir[0][0][0],
                       SM_EXT_SOURCES, SM_EXT_SOURCES, &dist, &turns, &err) == 0);
  CHECK_MSG(turns < -0.9 && dist < 0.02, "mirror: turns %g distortion %g", turns, dist);
  CHECK(sm_map_turns(NULL, x, T, t->src, &t->src_dist[0][0], &t->src_dir[0][0][0],
                     SM_EXT_SOURCES, SM_EXT_SOURCES, &dist, &turns, &err) == SM_EINVAL);
  sm_edge_paths_destroy(px);
  sm_edge_paths_destroy(py);
  sm_ext_destroy(t);
  free(perm);
  free(T);
  sm_mesh_destroy(x);
  sm_mesh_destroy(y);
}

int main(void) {
  test_directions_on_sphere();
  test_turns_copy_and_mirror();
  test_paths_match_dijkstra();
  test_star_tips();
  test_real_tips();
  test_hypotheses_on_copy();
  test_match_always();
  return sm_test_finish();
}
