/* The matching pipeline end to end: self-match against a moved, rescaled, renumbered copy
 * (every basis and init), the mirror test, shape distance properties, and regression bounds
 * on the real pairs of ../shared/data (skipped when absent). */
#include <pthread.h>
#include <string.h>

#include "sm_coarse.h"
#include "sm_confidence.h"
#include "sm_distance.h"
#include "sm_match.h"
#include "sm_meshio.h"
#include "sm_metrics.h"
#include "sm_test.h"
#include "sm_testmesh.h"

static sm_shape *prepare(const sm_mesh *m, int k) {
  sm_shape_opts so;
  sm_shape *s = NULL;
  sm_error err;
  sm_shape_opts_default(&so);
  so.k_lb = so.k_elastic = k;
  int rc = sm_shape_prepare(m, &so, &s, &err);
  if (rc) fprintf(stderr, "prepare: %s\n", err.msg);
  REQUIRE(rc == 0);
  return s;
}

static void match(const sm_shape *x, const sm_shape *y, int basis, int init, int k,
                  sm_match_result *r) {
  sm_match_opts o;
  sm_error err;
  sm_match_opts_default(&o);
  o.basis = basis;
  o.init = init;
  o.k1 = k;
  o.want_yx = 1;
  int rc = sm_match(x, y, &o, r, &err);
  if (rc) fprintf(stderr, "match: %s\n", err.msg);
  REQUIRE(rc == 0);
}

/* An asymmetric blob (bumps at random directions, anisotropic stretch). */
static sm_mesh *blob(int subdiv) {
  sm_mesh *m = NULL;
  const double st[3] = {1.0, 1.35, 0.8};
  REQUIRE(sm_synth_blob(subdiv, 0.35, 4, st, &m, NULL) == 0);
  return m;
}

/* The 642-vertex blob and a copy p with its vertices renumbered: vertex j of p is vertex
 * perm[j] of the blob (perm allocated here, freed by the caller). */
static sm_mesh *blob_and_permuted(uint64_t seed, int32_t **perm, sm_mesh **p) {
  sm_mesh *m = blob(3);
  *perm = malloc((size_t)m->nv * sizeof **perm);
  REQUIRE(*perm != NULL);
  tm_permutation(*perm, m->nv, seed);
  *p = tm_permuted(m, *perm);
  return m;
}

/* Copy p of m: vertex j of p is vertex perm[j] of m, moved by a rotation, translation and a
 * scale of 3.7 (so sm_mesh_normalize has something to undo). */
static void self_match_case(int basis, int init) {
  int32_t *perm;
  sm_mesh *p, *m = blob_and_permuted(99, &perm, &p);
  const double t[3] = {1.5, -2.0, 0.3};
  tm_rigid(p, 0.7, 2.1, -0.4, 3.7, t);
  sm_shape *x = prepare(m, 40), *y = prepare(p, 40);
  sm_match_result r;
  match(x, y, basis, init, 40, &r);
  int exact = 0;
  for (int32_t i = 0; i < m->nv; i++) exact += perm[r.T[i]] == i;
  double frac = (double)exact / m->nv;
  CHECK_MSG(frac >= 0.98, "basis %d init %d: %.4f of vertices mapped exactly", basis, init, frac);
  CHECK_MSG(r.orientation > 0.95, "basis %d init %d: orientation %.3f", basis, init, r.orientation);
  CHECK_MSG(r.confidence > 0.9 && r.confidence <= 1.0, "basis %d init %d: confidence %.3f of a "
            "correct self-match", basis, init, r.confidence);
  sm_distance_parts d;
  sm_error err;
  REQUIRE(sm_shape_distance(x, y, r.T, r.T_yx, &d, &err) == 0);
  CHECK_MSG(d.total < 1e-3, "basis %d init %d: self distance %.3g", basis, init, d.total);
  sm_match_result_free(&r);
  sm_shape_destroy(x);
  sm_shape_destroy(y);
  sm_mesh_destroy(m);
  sm_mesh_destroy(p);
  free(perm);
}

/* The distance preset's Sinkhorn start on the farthest-point samples (init_samples): the
 * blob against its moved, renumbered copy with 300 of its 642 vertices as samples (the
 * path is taken only with fewer samples than vertices) is matched about as exactly as
 * with the plan on every vertex (the preset has no bijective pass: 95-98% of the vertices
 * exactly either way), and its distance is ~0. */
static void preset_self_match(const sm_shape *x, const sm_shape *y, const int32_t *perm,
                              int init_samples, int *exact, double *dist) {
  sm_match_opts o;
  sm_match_opts_default(&o);
  sm_distance_match_opts(&o);
  o.samples = 300;
  o.init_samples = init_samples;
  sm_match_result r;
  sm_error err;
  REQUIRE(sm_match(x, y, &o, &r, &err) == 0);
  *exact = 0;
  for (int32_t i = 0; i < x->mesh->nv; i++) *exact += perm[r.T[i]] == i;
  for (int32_t j = 0; j < y->mesh->nv; j++) *exact += r.T_yx[j] == perm[j];
  sm_distance_parts d;
  REQUIRE(sm_shape_distance(x, y, r.T, r.T_yx, &d, &err) == 0);
  *dist = d.total;
  sm_match_result_free(&r);
}

static void test_sampled_start(void) {
  int32_t *perm;
  sm_mesh *p, *m = blob_and_permuted(7, &perm, &p);
  const double t[3] = {-0.4, 1.0, 2.0};
  tm_rigid(p, -0.3, 1.2, 0.8, 0.6, t);
  sm_shape *x = prepare(m, 60), *y = prepare(p, 60);
  sm_match_opts o;
  sm_match_opts_default(&o);
  sm_distance_match_opts(&o);
  CHECK(o.init_samples == 1 && o.init == SM_INIT_SINKHORN);
  int ex_s, ex_a;
  double d_s, d_a;
  preset_self_match(x, y, perm, 1, &ex_s, &d_s);
  preset_self_match(x, y, perm, 0, &ex_a, &d_a);
  int n = m->nv + p->nv;
  CHECK_MSG(ex_s >= 0.95 * n && ex_s >= ex_a - 0.02 * n,
            "sampled start: %d of %d vertices (both maps) exact, %d with the plan on every "
            "vertex", ex_s, n, ex_a);
  CHECK_MSG(d_s < 1e-3, "sampled start: self distance %.3g (every vertex: %.3g)", d_s, d_a);
  sm_shape_destroy(x);
  sm_shape_destroy(y);
  sm_mesh_destroy(m);
  sm_mesh_destroy(p);
  free(perm);
}

/* final_choice: a doubtful map (here every map: the tip search always runs) gets the final
 * pass at two LB weights and the more confident result: the one pass's result exactly, or
 * the weight-1 pass's with a strictly higher confidence; the map stays right either way.
 * A map the search did not run for gets one pass. Under the sanitizers too (copy, swap,
 * free). */
static void test_final_choice(void) {
  int32_t *perm;
  sm_mesh *p, *m = blob_and_permuted(5, &perm, &p);
  sm_shape *x = prepare(m, 40), *y = prepare(p, 40);
  sm_match_result r[2];
  for (int c = 0; c < 2; c++) {
    sm_match_opts o;
    sm_error err;
    sm_match_opts_default(&o);
    o.k1 = 40;
    o.extremities = SM_EXT_ALWAYS;
    o.final_choice = c;
    int rc = sm_match(x, y, &o, &r[c], &err);
    if (rc) fprintf(stderr, "match: %s\n", err.msg);
    REQUIRE(rc == 0);
    REQUIRE(r[c].T_yx == NULL);
    int exact = 0;
    for (int32_t i = 0; i < m->nv; i++) exact += perm[r[c].T[i]] == i;
    CHECK_MSG(exact >= 0.98 * m->nv, "final_choice %d: %d of %d vertices exact", c, exact,
              (int)m->nv);
  }
  CHECK(r[0].final_lb_weight == SM_MATCH_FINAL_LB_WEIGHT);
  CHECK_MSG(r[1].final_lb_weight == SM_MATCH_FINAL_LB_WEIGHT || r[1].final_lb_weight == 1.0,
            "final_choice: kept pass's LB weight %g", r[1].final_lb_weight);
  fprintf(stderr, "final_choice: kept LB weight %g, confidence %.4f (one pass %.4f)\n",
          r[1].final_lb_weight, r[1].confidence, r[0].confidence);
  if (r[1].final_lb_weight == 1.0) /* the other pass won: strictly more confident */
    CHECK_MSG(r[1].confidence > r[0].confidence, "final_choice: weight 1 kept at confidence "
              "%.4f, one pass %.4f", r[1].confidence, r[0].confidence);
  else /* the same pass from the same map: the same result */
    CHECK(r[1].confidence == r[0].confidence &&
          !memcmp(r[1].T, r[0].T, (size_t)r[0].nx * sizeof *r[0].T));
  for (int c = 0; c < 2; c++) sm_match_result_free(&r[c]);
  /* A map the tip search did not run for keeps the one pass. */
  sm_match_opts o;
  sm_error err;
  sm_match_opts_default(&o);
  o.k1 = 40;
  o.extremities = SM_EXT_OFF;
  REQUIRE(sm_match(x, y, &o, &r[0], &err) == 0);
  CHECK(r[0].final_lb_weight == SM_MATCH_FINAL_LB_WEIGHT);
  sm_match_result_free(&r[0]);
  sm_shape_destroy(x);
  sm_shape_destroy(y);
  sm_mesh_destroy(m);
  sm_mesh_destroy(p);
  free(perm);
}

/* A shape with a left/right mirror symmetry (x -> -x) and its mirror image, in the same
 * vertex order: the identity is the mirror (orientation-reversing); the orientation-
 * preserving map sends each vertex to its symmetric partner. */
static sm_mesh *symmetric_shape(void) {
  sm_mesh *m = tm_icosphere(3);
  double d[3][3] = {{0.6, 0.5, 0.62}, {-0.6, 0.5, 0.62}, {0.0, -0.7, 0.3}};
  double amp[3] = {0.45, 0.45, -0.3};
  for (int b = 0; b < 3; b++) {
    double n = sqrt(d[b][0] * d[b][0] + d[b][1] * d[b][1] + d[b][2] * d[b][2]);
    for (int c = 0; c < 3; c++) d[b][c] /= n;
  }
  for (int32_t v = 0; v < m->nv; v++) {
    double *q = m->V + 3 * v, r = 1;
    for (int b = 0; b < 3; b++)
      r += amp[b] * exp(-5 * (1 - (q[0] * d[b][0] + q[1] * d[b][1] + q[2] * d[b][2])));
    q[0] *= r;
    q[1] *= 1.3 * r;
    q[2] *= 0.8 * r;
  }
  return m;
}

static void test_mirror(void) {
  sm_mesh *m = symmetric_shape();
  sm_mesh *w;
  REQUIRE(sm_mesh_copy(m, &w, NULL) == 0);
  for (int32_t v = 0; v < w->nv; v++) w->V[3 * v] = -w->V[3 * v];
  for (int32_t f = 0; f < w->nf; f++) { /* keep the mirror image outward */
    int32_t s = w->F[3 * f + 1];
    w->F[3 * f + 1] = w->F[3 * f + 2];
    w->F[3 * f + 2] = s;
  }
  /* partner[i]: the vertex of m at (-x, y, z) of vertex i (exists: the icosphere's vertex
   * set and the bump field are symmetric). */
  int32_t *partner = malloc((size_t)m->nv * sizeof *partner);
  for (int32_t i = 0; i < m->nv; i++) {
    double best = INFINITY;
    for (int32_t j = 0; j < m->nv; j++) {
      double dx = m->V[3 * j] + m->V[3 * i], dy = m->V[3 * j + 1] - m->V[3 * i + 1],
             dz = m->V[3 * j + 2] - m->V[3 * i + 2], dd = dx * dx + dy * dy + dz * dz;
      if (dd < best) {
        best = dd;
        partner[i] = j;
      }
    }
  }
  sm_shape *x = prepare(m, 40), *y = prepare(w, 40);
  sm_match_result r;
  match(x, y, SM_MATCH_ELASTIC, SM_INIT_SINKHORN, 40, &r);
  int pres = 0, mirror = 0;
  double dist = 0;
  for (int32_t i = 0; i < m->nv; i++) {
    pres += r.T[i] == partner[i];
    mirror += r.T[i] == i && partner[i] != i;
    const double *u = y->mesh->V + 3 * r.T[i], *v = y->mesh->V + 3 * partner[i];
    dist += sqrt((u[0] - v[0]) * (u[0] - v[0]) + (u[1] - v[1]) * (u[1] - v[1]) + (u[2] - v[2]) * (u[2] - v[2]));
  }
  fprintf(stderr, "mirror: flipped %d, orientation %.3f, %d on partner, %d on mirror, mean "
          "distance to partner %.4f (unit area)\n", r.flipped, r.orientation, pres, mirror, dist / m->nv);
  /* The mirror itself would score -1 and put every vertex on the mirror. Measured with the
   * default pipeline: orientation 0.80, 549 of 642 exactly on the partner, 20 on the mirror,
   * mean distance to the partner 0.037 (edges are ~0.05 long at unit area). */
  CHECK_MSG(r.orientation > 0.6, "mirror: orientation %.3f", r.orientation);
  CHECK_MSG(pres >= 0.8 * m->nv, "mirror: %d of %d vertices on their partner", pres, m->nv);
  CHECK_MSG(mirror < 0.05 * m->nv, "mirror: %d of %d vertices on the mirror", mirror, m->nv);
  CHECK_MSG(dist / m->nv < 0.05, "mirror: mean distance to partner %.4f", dist / m->nv);
  /* Again, with y's self-symmetry now cached: the same result. */
  sm_match_result r2;
  match(x, y, SM_MATCH_ELASTIC, SM_INIT_SINKHORN, 40, &r2);
  CHECK(r2.flipped == r.flipped && !memcmp(r.T, r2.T, (size_t)m->nv * sizeof *r.T));
  sm_match_result_free(&r2);
  sm_match_result_free(&r);
  sm_shape_destroy(x);
  sm_shape_destroy(y);
  sm_mesh_destroy(m);
  sm_mesh_destroy(w);
  free(partner);
}

/* Distance: symmetric, in [0, 2], larger across different shapes than across a re-posed
 * copy. */
static void test_distance_properties(void) {
  sm_mesh *a = blob(3), *b = tm_torus(32, 16, 1.0, 0.35);
  sm_shape *x = prepare(a, 30), *y = prepare(b, 30);
  sm_match_result r1, r2;
  match(x, y, SM_MATCH_ELASTIC, SM_INIT_NN, 30, &r1);
  match(y, x, SM_MATCH_ELASTIC, SM_INIT_NN, 30, &r2);
  sm_distance_parts d1, d2;
  sm_error err;
  REQUIRE(sm_shape_distance(x, y, r1.T, r1.T_yx, &d1, &err) == 0);
  REQUIRE(sm_shape_distance(y, x, r1.T_yx, r1.T, &d2, &err) == 0);
  CHECK_NEAR(d1.total, d2.total, 1e-12); /* same maps swapped: exactly symmetric */
  CHECK(d1.total > 0.05 && d1.total <= 2.0);
  sm_match_result_free(&r1);
  sm_match_result_free(&r2);
  sm_shape_destroy(x);
  sm_shape_destroy(y);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
}

/* The shipped map term is an area-weighted median: on a re-posed, permuted and scaled copy
 * with the exact maps it is ~0; with 30% of each map's vertices sent to random vertices it
 * stays near 0 (the median ignores them), with 70% it is large; the spectral term never
 * looks at the maps. */
static void test_map_term_median(void) {
  int32_t *perm;
  sm_mesh *p, *m = blob_and_permuted(17, &perm, &p);
  const double t[3] = {0.2, 0.1, -0.3};
  tm_rigid(p, 0.3, -1.2, 0.8, 2.5, t);
  sm_shape *x = prepare(m, 30), *y = prepare(p, 30);
  int32_t n = m->nv, *Txy = malloc((size_t)n * sizeof *Txy), *Tyx = malloc((size_t)n * sizeof *Tyx);
  REQUIRE(Txy && Tyx);
  double got[3];
  const double wrong[3] = {0.0, 0.3, 0.7};
  sm_distance_parts d[3];
  for (int c = 0; c < 3; c++) {
    uint64_t rng = 12345;
    for (int32_t j = 0; j < n; j++) Txy[perm[j]] = j, Tyx[j] = perm[j];
    for (int32_t i = 0; i < n; i++) {
      rng = rng * 6364136223846793005ull + 1442695040888963407ull;
      if ((double)(rng >> 11) / 9007199254740992.0 < wrong[c]) {
        Txy[i] = (int32_t)((rng >> 20) % (uint64_t)n);
        Tyx[i] = (int32_t)((rng >> 40) % (uint64_t)n);
      }
    }
    sm_error err;
    REQUIRE(sm_shape_distance(x, y, Txy, Tyx, &d[c], &err) == 0);
    got[c] = 0.5 * (d[c].point_xy + d[c].point_yx);
  }
  CHECK_MSG(got[0] < 1e-3, "exact maps: map term %.3g", got[0]);
  CHECK_MSG(got[1] < 0.25 * got[2], "30%% wrong %.3g, 70%% wrong %.3g", got[1], got[2]);
  CHECK_MSG(got[2] > 0.01, "70%% wrong: map term %.3g", got[2]);
  CHECK_NEAR(d[0].spectrum_lb, d[2].spectrum_lb, 1e-15);
  CHECK(d[2].total > d[0].total);
  free(Txy);
  free(Tyx);
  sm_shape_destroy(x);
  sm_shape_destroy(y);
  sm_mesh_destroy(m);
  sm_mesh_destroy(p);
  free(perm);
}

/* The shipped spectral term on hand-made spectra: a uniform scale of every eigenvalue
 * (what a wrong area normalization does) costs nothing with level 0 and exactly
 * sqrt(level) |log c| otherwise; the zero eigenvalue is skipped; K limits the count. */
static void test_spectral_level(void) {
  double ea[6] = {0, 1, 2, 3, 5, 8}, eb[6], ec[6] = {0, 1, 3, 3, 4, 9};
  const double c = 1.07;
  for (int i = 0; i < 6; i++) eb[i] = c * ea[i];
  sm_basis a = {.k = 6, .evals = ea}, b = {.k = 6, .evals = eb}, d = {.k = 6, .evals = ec};
  CHECK_NEAR(sm_spectrum_ratio_distance(&a, &b, 0, 0.0), 0.0, 1e-12);
  CHECK_NEAR(sm_spectrum_ratio_distance(&a, &b, 0, 1.0), log(c), 1e-12);
  CHECK_NEAR(sm_spectrum_ratio_distance(&a, &b, 3, 0.25), 0.5 * log(c), 1e-12);
  double ad = sm_spectrum_ratio_distance(&a, &d, 0, 0.0);
  CHECK(ad > 0.05);
  CHECK_NEAR(ad, sm_spectrum_ratio_distance(&d, &a, 0, 0.0), 1e-15);
  /* only the first two non-zero eigenvalues (1, 2 vs 1, 3): log ratios 0 and log(2/3) */
  double r = log(2.0 / 3.0);
  CHECK_NEAR(sm_spectrum_ratio_distance(&a, &d, 2, 0.0), fabs(r) / 2, 1e-12);
}

/* The per-shape cache (farthest-point samples, coarse operators): a match that fills it
 * (two threads at once), one that reads it and one without it give the same maps. */
typedef struct cache_job {
  const sm_shape *x, *y;
  sm_match_result r;
  int rc;
} cache_job;

static void cache_match(const sm_shape *x, const sm_shape *y, sm_match_result *r, int *rc) {
  sm_match_opts o;
  sm_error err;
  sm_match_opts_default(&o);
  o.k1 = 30;
  o.samples = 300; /* below the 642 vertices: ZoomOut samples, so the samples are cached */
  o.want_yx = 1;
  *rc = sm_match(x, y, &o, r, &err);
}

static void *cache_thread(void *arg) {
  cache_job *j = arg;
  cache_match(j->x, j->y, &j->r, &j->rc);
  return NULL;
}

static int same_maps(const sm_match_result *a, const sm_match_result *b) {
  return a->nx == b->nx && a->ny == b->ny &&
         !memcmp(a->T, b->T, (size_t)a->nx * sizeof *a->T) &&
         !memcmp(a->T_yx, b->T_yx, (size_t)a->ny * sizeof *a->T_yx);
}

static void test_shape_cache(void) {
  int32_t *perm;
  sm_mesh *p, *m = blob_and_permuted(7, &perm, &p);
  sm_shape *x = prepare(m, 30), *y = prepare(p, 30);
  cache_job j[2] = {{x, y, {0}, -1}, {x, y, {0}, -1}};
  pthread_t th;
  int threaded = pthread_create(&th, NULL, cache_thread, &j[1]) == 0;
  cache_thread(&j[0]);
  if (threaded) pthread_join(th, NULL);
  else cache_thread(&j[1]);
  REQUIRE(j[0].rc == 0 && j[1].rc == 0);
  CHECK(same_maps(&j[0].r, &j[1].r));
  sm_match_result warm, cold;
  int rc_w, rc_c;
  cache_match(x, y, &warm, &rc_w);
  struct sm_shape_cache *cx = x->cache, *cy = y->cache;
  x->cache = y->cache = NULL; /* nothing cached: everything computed in the call */
  cache_match(x, y, &cold, &rc_c);
  x->cache = cx;
  y->cache = cy;
  REQUIRE(rc_w == 0 && rc_c == 0);
  CHECK(same_maps(&j[0].r, &warm));
  CHECK(same_maps(&warm, &cold));
  sm_match_result_free(&j[0].r);
  sm_match_result_free(&j[1].r);
  sm_match_result_free(&warm);
  sm_match_result_free(&cold);
  sm_shape_destroy(x);
  sm_shape_destroy(y);
  sm_mesh_destroy(m);
  sm_mesh_destroy(p);
  free(perm);
}

/* A correct map scores near 1, the same map scrambled (random targets, both directions)
 * near 0, and a mirror (orientation reversed) exactly 0. */
static void test_confidence(void) {
  sm_mesh *m = blob(3);
  sm_shape *x = prepare(m, 40);
  int32_t n = m->nv, *id = malloc((size_t)n * sizeof *id), *sc = malloc((size_t)n * sizeof *sc);
  for (int32_t i = 0; i < n; i++) id[i] = i;
  tm_permutation(sc, n, 7);
  sm_confidence c;
  sm_error err;
  REQUIRE(sm_map_confidence(x->mesh, x->mesh, x->lb->mass, id, id, &c, &err) == 0);
  CHECK_MSG(c.confidence > 0.999, "identity: confidence %.4f", c.confidence);
  REQUIRE(sm_map_confidence(x->mesh, x->mesh, x->lb->mass, sc, sc, &c, &err) == 0);
  CHECK_MSG(c.confidence < 0.05, "scrambled: confidence %.4f (orientation %.3f, continuity "
            "%.3f, cycle %.3f)", c.confidence, c.orientation, c.continuity, c.cycle);
  CHECK(c.continuity < 0.05);
  /* The mirror: x -> -x of the same mesh, with faces flipped to stay outward; the identity
   * between the two reverses orientation. */
  sm_mesh *mm = tm_permuted(m, id);
  for (int32_t v = 0; v < n; v++) mm->V[3 * (size_t)v] = -mm->V[3 * (size_t)v];
  for (int32_t f = 0; f < mm->nf; f++) {
    int32_t t = mm->F[3 * (size_t)f + 1];
    mm->F[3 * (size_t)f + 1] = mm->F[3 * (size_t)f + 2];
    mm->F[3 * (size_t)f + 2] = t;
  }
  sm_shape *y = prepare(mm, 40);
  REQUIRE(y->mesh->nv == n);
  REQUIRE(sm_map_confidence(x->mesh, y->mesh, x->lb->mass, id, id, &c, &err) == 0);
  CHECK_MSG(c.orientation < -0.95 && c.confidence == 0.0, "mirror: orientation %.3f, "
            "confidence %.3f", c.orientation, c.confidence);
  id[0] = n; /* out of range */
  CHECK(sm_map_confidence(x->mesh, x->mesh, x->lb->mass, id, sc, &c, &err) == SM_ERANGE);
  sm_shape_destroy(x);
  sm_shape_destroy(y);
  sm_mesh_destroy(m);
  sm_mesh_destroy(mm);
  free(id);
  free(sc);
}

#define TND "tosca_nonisometric_dev/"

typedef struct real_pair {
  const char *name, *src, *tgt, *gt; /* gt NULL = identity through a permutation of tgt */
  double bound;                       /* mean geodesic error bound (from bench_match) */
  const char *gt_tgt;                 /* set: gt and gt_tgt are 1-based .vts files */
} real_pair;

static void real_pair_case(const real_pair *p) {
  char b1[512], b2[512], b3[512];
  const char *src = sm_test_data(p->src, b1, sizeof b1), *tgt = sm_test_data(p->tgt, b2, sizeof b2);
  char b4[512];
  const char *gtp = p->gt ? sm_test_data(p->gt, b3, sizeof b3) : NULL;
  const char *gtt = p->gt_tgt ? sm_test_data(p->gt_tgt, b4, sizeof b4) : NULL;
  if (!src || !tgt || (p->gt && !gtp) || (p->gt_tgt && !gtt)) {
    fprintf(stderr, "%s: data absent, skipped\n", p->name);
    return;
  }
  sm_error err;
  sm_mesh *a, *b;
  REQUIRE(sm_mesh_read_file(src, NULL, &a, &err) == 0);
  REQUIRE(sm_mesh_read_file(tgt, NULL, &b, &err) == 0);
  sm_gt *gt = NULL;
  if (p->gt_tgt) {
    REQUIRE(sm_gt_load_vts(gtp, gtt, 1, a->nv, b->nv, &gt, &err) == 0);
  } else if (p->gt) {
    REQUIRE(sm_gt_load_dense(gtp, 0, a->nv, b->nv, &gt, &err) == 0);
  } else { /* permute the target so that index matching cannot solve it */
    int32_t *perm = malloc((size_t)b->nv * sizeof *perm), *inv = malloc((size_t)b->nv * sizeof *inv);
    tm_permutation(perm, b->nv, 2024);
    sm_mesh *pb = tm_permuted(b, perm);
    for (int32_t j = 0; j < b->nv; j++) inv[perm[j]] = j;
    REQUIRE(sm_gt_identity(a->nv, &gt, &err) == 0);
    REQUIRE(sm_gt_remap_target(gt, inv, b->nv, &err) == 0);
    sm_mesh_destroy(b);
    b = pb;
    free(perm);
    free(inv);
  }
  sm_shape *x = prepare(a, 100), *y = prepare(b, 100);
  sm_match_opts o;
  sm_match_result r;
  sm_match_opts_default(&o);
  REQUIRE(sm_match(x, y, &o, &r, &err) == 0);
  int32_t *map = malloc((size_t)a->nv * sizeof *map);
  sm_match_to_input(x, y, r.T, map);
  sm_metrics mt;
  REQUIRE(sm_metrics_compute(a, b, map, gt, 2, &mt, &err) == 0);
  fprintf(stderr, "%s: mean geodesic error %.4f (bound %.3f), orientation %.3f, confidence "
          "%.3f, final pass's LB weight %g\n", p->name, mt.geo.mean, p->bound, r.orientation,
          r.confidence, r.final_lb_weight);
  CHECK_MSG(mt.geo.mean <= p->bound, "%s: %.4f > %.3f", p->name, mt.geo.mean, p->bound);
  /* A map that failed (error above 0.25, a wrong basin) must say so. */
  CHECK_MSG(!(mt.geo.mean > 0.25) || r.confidence < 0.2, "%s: failed map (error %.3f) with "
            "confidence %.3f", p->name, mt.geo.mean, r.confidence);
  free(map);
  sm_match_result_free(&r);
  sm_shape_destroy(x);
  sm_shape_destroy(y);
  sm_gt_destroy(gt);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
}

/* sm_orientation_features: exact on linear functions of a flat patch (the sine between two
 * constant gradients, signed by the normal), negated by a mirror, unchanged by a rigid
 * motion with scaling, 0 where a function is constant or unreachable. */
static void test_orientation_features(void) {
  sm_mesh *g = tm_grid(12, 9);
  REQUIRE(g);
  int32_t n = g->nv;
  double *U = malloc((size_t)n * 4 * sizeof *U), *O = malloc((size_t)n * 6 * sizeof *O);
  REQUIRE(U && O);
  for (int32_t v = 0; v < n; v++) {
    const double *p = g->V + 3 * (size_t)v;
    U[v] = p[0];                  /* gradient +x */
    U[n + v] = 2 * p[1];          /* +y */
    U[2 * n + v] = p[0] + p[1];   /* (+x + y) / sqrt 2 */
    U[3 * n + v] = 5;             /* constant: no gradient */
  }
  sm_error err;
  REQUIRE(sm_orientation_features(g, U, 4, 1.0, O, &err) == 0);
  const double want[6] = {1, sqrt(0.5), 0, -sqrt(0.5), 0, 0}; /* (0,1) (0,2) (0,3) (1,2) ... */
  for (int32_t v = 0; v < n; v++)
    for (int q = 0; q < 6; q++) CHECK_NEAR(O[(size_t)v * 6 + q], want[q], 1e-12);
  sm_mesh_destroy(g);
  free(U);
  free(O);

  /* A closed bumpy shape, the distances from three of its vertices. */
  sm_mesh *m = tm_icosphere(3), *mir = NULL;
  REQUIRE(m);
  tm_jitter(m, 0.03, 7);
  n = m->nv;
  U = malloc((size_t)n * 3 * sizeof *U);
  O = malloc((size_t)n * 3 * sizeof *O);
  REQUIRE(U && O);
  sm_edge_paths *ep = NULL;
  REQUIRE(sm_edge_paths_create(m, &ep, &err) == 0);
  const int32_t src[3] = {0, n / 3, 2 * n / 3};
  for (int l = 0; l < 3; l++) REQUIRE(sm_edge_paths_run(ep, src[l], U + (size_t)l * n, &err) == 0);
  sm_edge_paths_destroy(ep);
  REQUIRE(sm_orientation_features(m, U, 3, 2.0, O, &err) == 0);
  double *O2 = malloc((size_t)n * 3 * sizeof *O2), amax = 0;
  REQUIRE(O2);
  for (int32_t i = 0; i < 3 * n; i++) amax = fmax(amax, fabs(O[i]));
  CHECK_MSG(amax > 1.0 && amax <= 2.0 + 1e-12, "scale 2: largest feature %.4f", amax);

  /* Mirror x -> -x, faces reversed so that the normals stay outward: same distances. */
  REQUIRE(sm_mesh_alloc(n, m->nf, NULL, &mir, NULL) == 0);
  for (int32_t v = 0; v < n; v++) {
    mir->V[3 * v] = -m->V[3 * v];
    mir->V[3 * v + 1] = m->V[3 * v + 1];
    mir->V[3 * v + 2] = m->V[3 * v + 2];
  }
  for (int32_t t = 0; t < m->nf; t++) {
    mir->F[3 * t] = m->F[3 * t];
    mir->F[3 * t + 1] = m->F[3 * t + 2];
    mir->F[3 * t + 2] = m->F[3 * t + 1];
  }
  REQUIRE(sm_orientation_features(mir, U, 3, 2.0, O2, &err) == 0);
  double worst = 0;
  for (int32_t i = 0; i < 3 * n; i++) worst = fmax(worst, fabs(O2[i] + O[i]));
  CHECK_MSG(worst < 1e-9, "mirror: features not negated (worst %.3g)", worst);

  /* Rotated, scaled 3x and moved, the distances scaled with it: unchanged. */
  const double t3[3] = {1, -2, 0.5};
  tm_rigid(m, 0.3, -1.1, 2.0, 3.0, t3);
  for (int32_t i = 0; i < 3 * n; i++) U[i] *= 3;
  REQUIRE(sm_orientation_features(m, U, 3, 2.0, O2, &err) == 0);
  worst = 0;
  for (int32_t i = 0; i < 3 * n; i++) worst = fmax(worst, fabs(O2[i] - O[i]));
  CHECK_MSG(worst < 1e-9, "rigid motion: features changed (worst %.3g)", worst);

  /* An unreachable source (+inf distances) contributes nothing. */
  for (int32_t v = 0; v < n; v++) U[2 * (size_t)n + v] = INFINITY;
  REQUIRE(sm_orientation_features(m, U, 3, 2.0, O2, &err) == 0);
  for (int32_t v = 0; v < n; v++) {
    CHECK(O2[(size_t)v * 3 + 1] == 0 && O2[(size_t)v * 3 + 2] == 0);
    CHECK_NEAR(O2[(size_t)v * 3], O[(size_t)v * 3], 1e-9);
  }
  CHECK(sm_orientation_features(m, U, -1, 1.0, O2, &err) == SM_EINVAL);
  free(U);
  free(O);
  free(O2);
  sm_mesh_destroy(m);
  sm_mesh_destroy(mir);
}

/* sm_map_field_agreement: 1 for a field carried by the identity, -1 against its negation,
 * 0 against a constant, and a permuted copy through its permutation reads 1 again. */
static void test_field_agreement(void) {
  enum { N = 50 };
  double fx[N], fy[N], neg[N], cst[N], mass[N];
  int32_t id[N], perm[N], inv[N];
  for (int i = 0; i < N; i++) {
    fx[i] = sin(0.3 * i) + 0.01 * i;
    neg[i] = -2 * fx[i] + 5;
    cst[i] = 1.5;
    mass[i] = 1 + (i % 3);
    id[i] = i;
  }
  tm_permutation(perm, N, 3);
  for (int i = 0; i < N; i++) {
    fy[i] = fx[perm[i]]; /* fy = fx renumbered: vertex i of Y is vertex perm[i] of X */
    inv[perm[i]] = i;
  }
  CHECK_NEAR(sm_map_field_agreement(fx, fx, mass, N, id), 1.0, 1e-12);
  CHECK_NEAR(sm_map_field_agreement(fx, neg, mass, N, id), -1.0, 1e-12);
  CHECK(sm_map_field_agreement(fx, cst, mass, N, id) == 0.0);
  CHECK_NEAR(sm_map_field_agreement(fx, fy, mass, N, inv), 1.0, 1e-12);
  CHECK(sm_map_field_agreement(fx, fy, mass, N, id) < 0.5);
}

int main(int argc, char **argv) {
  const int bases[3] = {SM_MATCH_LB, SM_MATCH_ELASTIC, SM_MATCH_HYBRID};
  const int inits[2] = {SM_INIT_NN, SM_INIT_SINKHORN};
  for (int b = 0; b < 3; b++)
    for (int i = 0; i < 2; i++) self_match_case(bases[b], inits[i]);
  test_mirror();
  test_sampled_start();
  test_distance_properties();
  test_map_term_median();
  test_spectral_level();
  test_shape_cache();
  test_confidence();
  test_final_choice();
  test_orientation_features();
  test_field_agreement();
  /* Bounds: the mean geodesic errors bench_match measured with the default pipeline
   * (homer 0.0238, head 0.0107, lion -> cat 0.0360, man -> woman 0.0022) plus ~20%.
   * Since the hybrid bijective pass (issue 9): homer 0.0233, head 0.0127 (bound now the
   * issue's 0.015), lion -> cat 0.0326, man -> woman 0.0029, man03 0.0387, man07 0.0349,
   * gorilla03 -> man03 0.122 (bound 0.15, was 0.23). With the kept tip map refined again
   * anchored by its confirmed tips: man03 0.0397, man07 0.0349, gorilla03 -> man03
   * 0.0929, the others unchanged. With final_choice (2026-11-28): man03 0.0348, man07
   * 0.0333, gorilla04 -> woman07 0.1041, the others unchanged (not doubtful, or same map). */
  const real_pair pairs[] = {
      {"homer", "elasticbasis_cartoon_pairs/homerA.obj", "elasticbasis_cartoon_pairs/homerB.obj",
       "elasticbasis_cartoon_pairs/gt_homerA_homerB.txt", 0.029, NULL},
      {"head", "elasticbasis_cartoon_pairs/headA.obj", "elasticbasis_cartoon_pairs/headB.obj",
       "elasticbasis_cartoon_pairs/gt_headA_headB.txt", 0.015, NULL},
      {"lion-cat", "pyfm_cat_lion/lion-00.off", "pyfm_cat_lion/cat-00.off", "pyfm_cat_lion/lion2cat",
       0.044, NULL},
      /* man -> woman: 0.0022 with ARPACK's eigenvectors, 0.0063 (confidence 0.88) since
       * the block eigensolver and the intrinsic sign rule of sm_basis.c (issue 13): same
       * eigenvalues to 1e-13 and functions up to sign, so the pipeline depends on the
       * bases' signs on this pair; the other pairs stay in their bounds (homer 0.0238,
       * head 0.0107, lion -> cat 0.0358, man03 0.0430, man07 0.0368, gorilla 0.210). */
      {"man-woman", "smpl_man_woman_odedstein/human_man.obj",
       "smpl_man_woman_odedstein/human_woman.obj", NULL, 0.0076, NULL},
      /* Dev pairs of tosca_nonisometric_dev (bench_hard, default pipeline, +20%): two man ->
       * woman pairs the descriptor start gets right (0.0428 -> 0.0379 after the tip search,
       * 0.0336 without it), and a gorilla -> human pair the descriptor start gets wrong
       * (0.634) that the tip search brings to 0.190 (the field's failure line is 0.1). Not
       * here: a pair whose outcome flips between 0.04 and 0.17 with the hypothesis the
       * search keeps (man 04 -> woman 03). */
      {"man03-woman03", TND "meshes/8_man_03.off.gz", TND "meshes/8_woman_03.off.gz",
       TND "corres/8_man_03.vts", 0.046, TND "corres/8_woman_03.vts"},
      {"man07-woman12", TND "meshes/8_man_07.off.gz", TND "meshes/8_woman_12.off.gz",
       TND "corres/8_man_07.vts", 0.041, TND "corres/8_woman_12.vts"},
      {"gorilla03-man03", TND "meshes/8_gorilla_03.off.gz", TND "meshes/8_man_03.off.gz",
       TND "corres/8_gorilla_03.vts", 0.15, TND "corres/8_man_03.vts"},
      /* Every tip assignment was wrong on this pair before tips needed an AGD above 0.95
       * of the mean (sm_extremity.h): 0.7376; with it and the anchoring 0.1097. */
      {"gorilla04-woman07", TND "meshes/8_gorilla_04.off.gz", TND "meshes/8_woman_07.off.gz",
       TND "corres/8_gorilla_04.vts", 0.15, TND "corres/8_woman_07.vts"},
  };
  /* The sanitizer pass sets SM_TEST_SYNTHETIC_ONLY: the real pairs are numerics already
   * covered by the optimized pass, and ten times slower under ASan. */
  int real = (argc < 2 || strcmp(argv[1], "--synthetic-only")) && !getenv("SM_TEST_SYNTHETIC_ONLY");
  if (real && !sm_test_data_present()) fprintf(stderr, "../shared/data absent: real pairs skipped\n");
  for (size_t i = 0; real && sm_test_data_present() && i < sizeof pairs / sizeof *pairs; i++)
    real_pair_case(&pairs[i]);
  return sm_test_finish();
}
