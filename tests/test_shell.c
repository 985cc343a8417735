/* test_shell: the thin-shell energy (rest value, rigid invariance, zero gradient at rest)
 * and its closed-form rest Hessian (against second differences of the nonlinear energy,
 * symmetric PSD, kernel = rigid motions per component), plus an assembly timing. */
#include <lapacke.h>
#include <string.h>
#include <time.h>

#include "sm_shell.h"
#include "sm_test.h"
#include "sm_testmesh.h"

typedef struct shell_case {
  sm_mesh *m;
  sm_edges *topo;
} shell_case;

static shell_case make_case(sm_mesh *m) {
  shell_case c = {m, NULL};
  REQUIRE(m);
  REQUIRE(sm_edges_build(m, &c.topo, NULL) == SM_OK);
  return c;
}

static void free_case(shell_case *c) {
  sm_edges_destroy(c->topo);
  sm_mesh_destroy(c->m);
}

static sm_shell_params params(double mu, double lambda, double eta) {
  sm_shell_params p = {mu, lambda, eta};
  return p;
}

static double energy(const shell_case *c, const sm_shell_params *p, const double *x) {
  double E;
  sm_error err;
  int rc = sm_shell_energy(c->m, c->topo, p, x, &E, NULL, NULL, &err);
  if (rc) fprintf(stderr, "energy: %s\n", err.msg);
  REQUIRE(rc == SM_OK);
  return E;
}

/* Dense (column-major, full) 3nv x 3nv Hessian from the lower-triangle triplets. */
static double *dense_hessian(const shell_case *c, const sm_shell_params *p) {
  int n = 3 * c->m->nv;
  sm_triplets t;
  sm_error err;
  REQUIRE(sm_triplets_init(&t, n, 0) == SM_OK);
  int rc = sm_shell_hessian(c->m, c->topo, p, &t, &err);
  if (rc) fprintf(stderr, "hessian: %s\n", err.msg);
  REQUIRE(rc == SM_OK);
  double *H = calloc((size_t)n * n, sizeof *H);
  REQUIRE(H);
  for (int64_t e = 0; e < t.len; e++) {
    int r = t.row[e], q = t.col[e];
    CHECK(r >= q);
    H[(size_t)q * n + r] += t.val[e];
    if (r != q) H[(size_t)r * n + q] += t.val[e];
  }
  sm_triplets_free(&t);
  return H;
}

/* H_ij ~ (E(+h,+h) - E(+h,-h) - E(-h,+h) + E(-h,-h)) / 4h^2 at the rest state. */
static double *fd_hessian(const shell_case *c, const sm_shell_params *p, double h) {
  int n = 3 * c->m->nv;
  double *x = malloc((size_t)n * sizeof *x), *H = malloc((size_t)n * n * sizeof *H);
  REQUIRE(x && H);
  memcpy(x, c->m->V, (size_t)n * sizeof *x);
  const double *x0 = c->m->V;
  for (int i = 0; i < n; i++)
    for (int j = 0; j <= i; j++) {
      double s[4], si[4] = {1, 1, -1, -1}, sj[4] = {1, -1, 1, -1};
      for (int q = 0; q < 4; q++) {
        x[i] = x0[i] + si[q] * h;
        x[j] = (i == j ? x[i] : x0[j]) + sj[q] * h;
        s[q] = energy(c, p, x);
        x[i] = x0[i];
        x[j] = x0[j];
      }
      H[(size_t)j * n + i] = H[(size_t)i * n + j] = (s[0] - s[1] - s[2] + s[3]) / (4 * h * h);
    }
  free(x);
  return H;
}

static double frob_diff(const double *A, const double *B, size_t len, double *normB) {
  double d = 0, b = 0;
  for (size_t i = 0; i < len; i++) {
    d += (A[i] - B[i]) * (A[i] - B[i]);
    b += B[i] * B[i];
  }
  *normB = sqrt(b);
  return sqrt(d);
}

/* Relative Frobenius error of the FD Hessian at h (and Richardson from h, 2h). */
static void check_fd(const char *name, const shell_case *c, sm_shell_params p) {
  int n = 3 * c->m->nv;
  size_t len = (size_t)n * n;
  double *H = dense_hessian(c, &p), *F1 = fd_hessian(c, &p, 1e-4),
         *F2 = fd_hessian(c, &p, 2e-4), nH;
  double e1 = frob_diff(F1, H, len, &nH) / nH;
  for (size_t i = 0; i < len; i++) F2[i] = (4 * F1[i] - F2[i]) / 3;
  double er = frob_diff(F2, H, len, &nH) / nH;
  fprintf(stderr, "FD %-34s mu=%g lambda=%g eta=%g  |H|=%.3g  rel err h=1e-4: %.2e  "
          "Richardson: %.2e\n", name, p.mu, p.lambda, p.eta, nH, e1, er);
  CHECK_MSG(e1 < 1e-6, "%s: FD relative error %.3e", name, e1);
  CHECK_MSG(er < 1e-7, "%s: Richardson FD relative error %.3e", name, er);
  free(H);
  free(F1);
  free(F2);
}

/* Eigenvalues (ascending) of a dense symmetric matrix (copied). */
static double *eigenvalues(const double *H, int n) {
  double *A = malloc((size_t)n * n * sizeof *A), *w = malloc((size_t)n * sizeof *w);
  REQUIRE(A && w);
  memcpy(A, H, (size_t)n * n * sizeof *A);
  REQUIRE(LAPACKE_dsyev(LAPACK_COL_MAJOR, 'N', 'L', n, A, n, w) == 0);
  free(A);
  return w;
}

static int kernel_dim(const char *name, const shell_case *c, sm_shell_params p) {
  int n = 3 * c->m->nv;
  double *H = dense_hessian(c, &p), *w = eigenvalues(H, n);
  double lmax = w[n - 1];
  int k = 0;
  for (int i = 0; i < n; i++) k += fabs(w[i]) < 1e-8 * lmax;
  fprintf(stderr, "eig %-30s eta=%g: n=%d kernel=%d  min=%.2e  first nonzero=%.2e  max=%.3g\n",
          name, p.eta, n, k, w[0], k < n ? w[k] : 0.0, lmax);
  CHECK_MSG(w[0] >= -1e-10 * lmax, "%s: min eigenvalue %.3e (max %.3e)", name, w[0], lmax);
  free(H);
  free(w);
  return k;
}

static sm_mesh *jittered(sm_mesh *m, double amp, uint64_t seed) {
  REQUIRE(m);
  tm_jitter(m, amp, seed);
  return m;
}

/* Grid on [0,1]^2 with z-jitter (not flat) plus a little in-plane jitter. */
static sm_mesh *bumpy_grid(int nx, int ny, uint64_t seed) {
  sm_mesh *m = tm_grid(nx, ny);
  REQUIRE(m);
  uint64_t s = seed;
  for (int32_t v = 0; v < m->nv; v++) {
    m->V[3 * v] += 0.03 * (2 * tm_rand(&s) - 1);
    m->V[3 * v + 1] += 0.03 * (2 * tm_rand(&s) - 1);
    m->V[3 * v + 2] += 0.1 * (2 * tm_rand(&s) - 1);
  }
  return m;
}

static void test_energy(const char *name, shell_case *c) {
  sm_shell_params p = params(1, 3, 0.5);
  int n = 3 * c->m->nv;
  double E, Em, Eb;
  REQUIRE(sm_shell_energy(c->m, c->topo, &p, c->m->V, &E, &Em, &Eb, NULL) == SM_OK);
  CHECK_MSG(fabs(E) < 1e-12 && fabs(Em) < 1e-12 && fabs(Eb) < 1e-12, "%s: rest E=%g", name, E);
  /* rigid motion of the rest positions */
  sm_mesh *r;
  REQUIRE(sm_mesh_copy(c->m, &r, NULL) == SM_OK);
  const double t[3] = {0.3, -1.2, 2.5};
  tm_rigid(r, 0.7, -1.1, 2.3, 1.0, t);
  REQUIRE(sm_shell_energy(c->m, c->topo, &p, r->V, &E, &Em, &Eb, NULL) == SM_OK);
  CHECK_MSG(fabs(E) < 1e-12, "%s: rigidly moved E=%g", name, E);
  /* random perturbation: both parts strictly positive */
  memcpy(r->V, c->m->V, (size_t)n * sizeof(double));
  tm_jitter(r, 0.01, 99);
  REQUIRE(sm_shell_energy(c->m, c->topo, &p, r->V, &E, &Em, &Eb, NULL) == SM_OK);
  CHECK_MSG(Em > 0 && Eb > 0 && E > 0, "%s: perturbed Em=%g Eb=%g", name, Em, Eb);
  /* zero gradient at rest: central differences at h and 2h, Richardson-extrapolated so
   * the h^2 E''' term cancels (E''' is ~1e3 on these meshes); rounding is ~eps. */
  double gmax = 0, h = 1e-4;
  memcpy(r->V, c->m->V, (size_t)n * sizeof(double));
  for (int i = 0; i < n; i++) {
    double d[2];
    for (int q = 0; q < 2; q++) {
      r->V[i] = c->m->V[i] + (q + 1) * h;
      double ep = energy(c, &p, r->V);
      r->V[i] = c->m->V[i] - (q + 1) * h;
      double em = energy(c, &p, r->V);
      r->V[i] = c->m->V[i];
      d[q] = (ep - em) / (2 * (q + 1) * h);
    }
    gmax = fmax(gmax, fabs(4 * d[0] - d[1]) / 3);
  }
  fprintf(stderr, "energy %-20s rest gradient (FD) max %.2e\n", name, gmax);
  CHECK_MSG(gmax < 1e-9, "%s: gradient at rest %.3e", name, gmax);
  sm_mesh_destroy(r);
}

static void test_errors(void) {
  shell_case c = make_case(tm_icosphere(0));
  sm_shell_params p;
  sm_shell_params_default(&p);
  CHECK(p.mu == 1 && p.lambda == 1 && p.eta == SM_SHELL_DEFAULT_ETA);
  sm_error err;
  double E;
  /* a deformed face collapsed to a point: log det G undefined */
  double *x = malloc((size_t)c.m->nv * 3 * sizeof *x);
  REQUIRE(x);
  memcpy(x, c.m->V, (size_t)c.m->nv * 3 * sizeof *x);
  const int32_t *F = c.m->F;
  memcpy(x + 3 * F[1], x + 3 * F[0], 3 * sizeof *x);
  memcpy(x + 3 * F[2], x + 3 * F[0], 3 * sizeof *x);
  CHECK(sm_shell_energy(c.m, c.topo, &p, x, &E, NULL, NULL, &err) == SM_ENONFINITE);
  x[0] = NAN;
  CHECK(sm_shell_energy(c.m, c.topo, &p, x, &E, NULL, NULL, &err) == SM_ENONFINITE);
  free(x);
  /* wrong triplet size, bad parameters */
  sm_triplets t;
  REQUIRE(sm_triplets_init(&t, 3 * c.m->nv + 1, 0) == SM_OK);
  CHECK(sm_shell_hessian(c.m, c.topo, &p, &t, &err) == SM_EINVAL);
  sm_triplets_free(&t);
  REQUIRE(sm_triplets_init(&t, 3 * c.m->nv, 0) == SM_OK);
  p.mu = -1;
  CHECK(sm_shell_hessian(c.m, c.topo, &p, &t, &err) == SM_EINVAL);
  sm_shell_params_default(&p);
  /* a rest face of zero area */
  memcpy(c.m->V + 3 * F[1], c.m->V + 3 * F[0], 3 * sizeof(double));
  CHECK(sm_shell_hessian(c.m, c.topo, &p, &t, &err) == SM_EINVAL);
  CHECK(strstr(err.msg, "zero area") != NULL);
  CHECK(sm_shell_energy(c.m, c.topo, &p, c.m->V, &E, NULL, NULL, &err) == SM_EINVAL);
  sm_triplets_free(&t);
  free_case(&c);
}

static void test_fd(void) {
  shell_case ico = make_case(jittered(tm_icosphere(1), 0.05, 7));
  shell_case grid = make_case(bumpy_grid(4, 4, 11));
  const sm_shell_params ps[] = {params(1, 1, 0), params(1, 3, 0), params(0, 0, 1),
                                params(1, 1, 1), params(1, 3, 1), params(2, 0.5, 1e-4)};
  for (size_t k = 0; k < sizeof ps / sizeof *ps; k++) {
    check_fd("icosphere(1) jittered (closed)", &ico, ps[k]);
    check_fd("grid(4,4) bumpy (boundary)", &grid, ps[k]);
  }
  free_case(&ico);
  free_case(&grid);
}

/* Bumpy grid(3,3) plus a fin: one more face on an interior edge, which makes that edge
 * non-manifold (no hinge) while the others keep theirs. */
static sm_mesh *grid_with_fin(void) {
  sm_mesh *g = bumpy_grid(3, 3, 17), *m;
  REQUIRE(sm_mesh_alloc(g->nv + 1, g->nf + 1, NULL, &m, NULL) == SM_OK);
  memcpy(m->V, g->V, (size_t)g->nv * 3 * sizeof(double));
  memcpy(m->F, g->F, (size_t)g->nf * 3 * sizeof(int32_t));
  int32_t a = 5, b = 6; /* interior vertices of the 4x4-vertex grid, joined by an edge */
  double *x = m->V + 3 * g->nv;
  for (int d = 0; d < 3; d++) x[d] = 0.5 * (g->V[3 * a + d] + g->V[3 * b + d]);
  x[1] += 0.05;
  x[2] += 0.3;
  m->F[3 * g->nf] = a;
  m->F[3 * g->nf + 1] = b;
  m->F[3 * g->nf + 2] = g->nv;
  sm_mesh_destroy(g);
  return m;
}

static void test_nonmanifold_and_mismatch(void) {
  shell_case c = make_case(grid_with_fin());
  CHECK(c.topo->n_nonmanifold == 1);
  check_fd("grid(3,3) + fin (non-manifold edge)", &c, params(1, 3, 1));
  /* the triplets hold exactly one block per edge, vertex and hinge diamond */
  sm_shell_params p = params(1, 1, 1);
  sm_triplets t;
  REQUIRE(sm_triplets_init(&t, 3 * c.m->nv, 0) == SM_OK);
  REQUIRE(sm_shell_hessian(c.m, c.topo, &p, &t, NULL) == SM_OK);
  CHECK(t.len == 9LL * c.topo->ne + 6LL * c.m->nv + 9LL * c.topo->nhinge);
  sm_triplets_free(&t);
  /* a topology built from another mesh with the same vertex count is rejected */
  shell_case o = make_case(bumpy_grid(3, 3, 17));
  int32_t perm[16];
  tm_permutation(perm, o.m->nv, 5);
  sm_mesh *pm = tm_permuted(o.m, perm);
  REQUIRE(pm);
  sm_error err;
  REQUIRE(sm_triplets_init(&t, 3 * pm->nv, 0) == SM_OK);
  CHECK(sm_shell_hessian(pm, o.topo, &p, &t, &err) == SM_EINVAL);
  CHECK(strstr(err.msg, "topology") != NULL);
  sm_triplets_free(&t);
  sm_mesh_destroy(pm);
  free_case(&o);
  free_case(&c);
}

static void test_kernel(void) {
  sm_shell_params p;
  sm_shell_params_default(&p);
  shell_case s = make_case(tm_icosphere(2));
  CHECK(kernel_dim("icosphere(2)", &s, p) == 6);
  free_case(&s);
  shell_case sj = make_case(jittered(tm_icosphere(2), 0.02, 3));
  CHECK(kernel_dim("icosphere(2) jittered", &sj, p) == 6);
  free_case(&sj);
  sm_mesh *a = tm_icosphere(1), *b = tm_icosphere(2);
  shell_case u = make_case(tm_union(a, b, 3.0));
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
  CHECK(kernel_dim("union of two spheres", &u, p) == 12);
  free_case(&u);
  shell_case tor = make_case(tm_torus(16, 8, 1.0, 0.4));
  CHECK(kernel_dim("torus(16,8)", &tor, p) == 6);
  free_case(&tor);
  /* flat grid: membrane alone has no out-of-plane stiffness (nv z-modes + 3 in-plane rigid
   * motions); bending must pin them down to the 6 rigid motions. */
  shell_case flat = make_case(tm_grid(5, 5));
  CHECK(kernel_dim("flat grid(5,5)", &flat, params(1, 1, 0)) == flat.m->nv + 3);
  CHECK(kernel_dim("flat grid(5,5)", &flat, p) == 6);
  free_case(&flat);
  shell_case bg = make_case(bumpy_grid(5, 5, 5));
  CHECK(kernel_dim("bumpy grid(5,5)", &bg, p) == 6);
  kernel_dim("bumpy grid(5,5), membrane only", &bg, params(1, 1, 0)); /* reported only */
  free_case(&bg);
}

static double now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

static void test_timing(void) {
  shell_case c = make_case(tm_icosphere(5));
  sm_shell_params p;
  sm_shell_params_default(&p);
  double best = 1e30;
  int64_t len = 0;
  for (int rep = 0; rep < 5; rep++) {
    sm_triplets t;
    REQUIRE(sm_triplets_init(&t, 3 * c.m->nv, 0) == SM_OK);
    double t0 = now_ms();
    REQUIRE(sm_shell_hessian(c.m, c.topo, &p, &t, NULL) == SM_OK);
    best = fmin(best, now_ms() - t0);
    len = t.len;
    sm_triplets_free(&t);
  }
  fprintf(stderr, "timing: icosphere(5) nv=%d nf=%d hinges=%d: %lld triplets, assembly %.1f ms\n",
          c.m->nv, c.m->nf, c.topo->nhinge, (long long)len, best);
  CHECK(best < 1000); /* generous: also holds under sanitizers; the report has the number */
  free_case(&c);
}

int main(void) {
  test_errors();
  shell_case ico = make_case(jittered(tm_icosphere(2), 0.02, 5));
  shell_case grid = make_case(bumpy_grid(4, 4, 13));
  test_energy("icosphere(2) jittered", &ico);
  test_energy("grid(4,4) bumpy", &grid);
  free_case(&ico);
  free_case(&grid);
  test_fd();
  test_nonmanifold_and_mismatch();
  test_kernel();
  test_timing();
  return sm_test_finish();
}
