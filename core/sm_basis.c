/* Computation of the LB and elastic bases (algorithm.md §2-3). Serialization lives in
 * sm_basis_io.c. */
#include "sm_basis.h"

#include <cblas.h>
#include <lapacke.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "sm_eigs.h"
#include "sm_laplace.h"
#include "sm_shell.h"
#include "sm_topology.h"

/* A relative shift: small against the spectrum (which scales like tr(A)/tr(D)) so that the
 * wanted eigenvalues converge fast, large enough to keep K = A - sigma D well conditioned
 * despite A's kernel. */
/* Measured on homerA elastic k = 100: 1e-6, 1e-5 and 1e-4 all take 283 solves; 1e-3
 * takes 340 and 1e-2 775 (the shift moves close to the wanted eigenvalues and compresses
 * the operator's spectrum). */
#define SM_SHIFT_REL 1e-6
/* Extra eigenpairs computed beyond k + the expected kernel, so that the kernel gap can be
 * seen and a few unexpected zero modes do not eat into k. */
#define SM_KERNEL_MARGIN 6

void sm_basis_opts_default(sm_basis_opts *o, int kind, int k) {
  memset(o, 0, sizeof *o);
  o->kind = kind;
  o->k = k;
  o->eta = kind == SM_BASIS_ELASTIC ? SM_SHELL_DEFAULT_ETA : 0.0;
  o->mu = 1.0;
  o->lambda = 1.0;
}

static double trace_ratio(const sm_csc *A, const double *D) {
  double ta = 0, td = 0;
  for (int32_t j = 0; j < A->n; j++) {
    td += D[j];
    for (int32_t p = A->colptr[j]; p < A->colptr[j + 1]; p++)
      if (A->rowind[p] == j) ta += A->val[p];
  }
  return ta / td;
}

/* Number of kernel modes at the front of the ascending spectrum ev[0..nev): the position of
 * the largest jump (in ratio) between consecutive |eigenvalues| among the leading ones that
 * are negligible against the top of the computed spectrum. 0 when there is no clear gap. */
int sm_basis_kernel_size(const double *ev, int nev, int expected) {
  double top = fabs(ev[nev - 1]), floor_ = 1e-300 + 1e-30 * top;
  int limit = 2 * expected + SM_KERNEL_MARGIN, best = 0;
  double best_ratio = 1e4; /* a kernel must be separated by at least four decades */
  if (limit > nev - 1) limit = nev - 1;
  for (int i = 1; i <= limit; i++) {
    double lo = fmax(fabs(ev[i - 1]), floor_), hi = fmax(fabs(ev[i]), floor_);
    if (lo > 1e-6 * top) break;
    if (hi / lo > best_ratio) {
      best_ratio = hi / lo;
      best = i;
    }
  }
  return best;
}

static sm_basis *basis_new(const sm_mesh *m, const sm_basis_opts *o) {
  sm_basis *b = calloc(1, sizeof *b);
  if (!b) return NULL;
  b->kind = o->kind;
  b->n = m->nv;
  b->k = o->k;
  b->eta = o->kind == SM_BASIS_ELASTIC ? o->eta : 0.0;
  b->mu = o->mu;
  b->lambda = o->lambda;
  b->evals = malloc((size_t)o->k * sizeof *b->evals);
  b->phi = malloc((size_t)m->nv * o->k * sizeof *b->phi);
  b->mass = malloc((size_t)m->nv * sizeof *b->mass);
  if (!b->evals || !b->phi || !b->mass) {
    sm_basis_destroy(b);
    return NULL;
  }
  return b;
}

static int eigs(const sm_csc *A, const double *D, int nev, const sm_basis_opts *o,
                double *evals, double *evecs, sm_basis_timing *tm, sm_error *err) {
  sm_eigs_opts eo = {.nev = nev, .sigma = -SM_SHIFT_REL * trace_ratio(A, D), .tol = 1e-9,
                     .cancel = o->cancel, .cancel_ud = o->cancel_ud};
  sm_eigs_stats st;
  int rc = sm_eigs_smallest(A, D, &eo, evals, evecs, &st, err);
  tm->factorization += st.t_analyze + st.t_factor;
  tm->eigensolve += st.t_solve;
  tm->solves += st.nsolves;
  return rc;
}

static int compute_lb(const sm_mesh *m, const sm_basis_opts *o, sm_basis *b, sm_error *err) {
  double t0 = sm_now();
  sm_csc *W;
  int rc = sm_cotan_stiffness(m, &W, err);
  b->timing.assembly += sm_now() - t0;
  if (rc) return rc;
  rc = eigs(W, b->mass, o->k, o, b->evals, b->phi, &b->timing, err);
  sm_csc_destroy(W);
  return rc;
}

static int assemble_hessian(const sm_mesh *m, const sm_basis_opts *o, sm_csc **H,
                            sm_error *err) {
  sm_edges *e;
  int rc = sm_edges_build(m, &e, err);
  if (rc) return rc;
  sm_shell_params sp = {.mu = o->mu, .lambda = o->lambda, .eta = o->eta};
  sm_triplets t;
  if (sm_triplets_init(&t, 3 * m->nv, 45 * (int64_t)m->nf + 78 * (int64_t)e->nhinge)) {
    sm_edges_destroy(e);
    return sm_error_set(err, SM_ENOMEM, "elastic Hessian: out of memory");
  }
  rc = sm_shell_hessian(m, e, &sp, &t, err);
  if (!rc) rc = sm_triplets_to_csc(&t, H, err);
  sm_triplets_free(&t);
  sm_edges_destroy(e);
  return rc;
}

/* phi_i(v) = n_v . u_i(v), for the k modes after the kernel. */
static void project_on_normals(const double *U, int32_t n, int first, int k, const double *N,
                               double *phi) {
  for (int i = 0; i < k; i++) {
    const double *u = U + (size_t)(first + i) * 3 * n;
    double *p = phi + (size_t)i * n;
    for (int32_t v = 0; v < n; v++)
      p[v] = N[3 * v] * u[3 * v] + N[3 * v + 1] * u[3 * v + 1] + N[3 * v + 2] * u[3 * v + 2];
  }
}

/* gram_L = chol(Phi^T M Phi), lower. */
static int gram_factor(sm_basis *b, sm_error *err) {
  int32_t n = b->n, k = b->k;
  double *S = malloc((size_t)n * k * sizeof *S);
  b->gram_L = calloc((size_t)k * k, sizeof *b->gram_L);
  if (!S || !b->gram_L) {
    free(S);
    return sm_error_set(err, SM_ENOMEM, "Gram matrix: out of memory");
  }
  for (int i = 0; i < k; i++)
    for (int32_t v = 0; v < n; v++) S[(size_t)i * n + v] = sqrt(b->mass[v]) * b->phi[(size_t)i * n + v];
  cblas_dsyrk(CblasColMajor, CblasLower, CblasTrans, k, n, 1.0, S, n, 0.0, b->gram_L, k);
  free(S);
  int info = LAPACKE_dpotrf(LAPACK_COL_MAJOR, 'L', k, b->gram_L, k);
  if (info != 0)
    return sm_error_set(err, SM_ENUMERIC, "Gram matrix of the elastic basis is singular "
                        "(normal components of modes 1..%d are linearly dependent)", info);
  for (int j = 0; j < k; j++) /* clear the strict upper triangle dpotrf left as input */
    for (int i = 0; i < j; i++) b->gram_L[(size_t)j * k + i] = 0.0;
  return SM_OK;
}

static int compute_elastic(const sm_mesh *m, const sm_basis_opts *o, sm_basis *b,
                           sm_error *err) {
  int32_t n = m->nv;
  double t0 = sm_now();
  sm_csc *H = NULL;
  double *M3 = malloc((size_t)3 * n * sizeof *M3), *N = malloc((size_t)3 * n * sizeof *N);
  double *U = NULL, *ev = NULL;
  int rc = (!M3 || !N) ? sm_error_set(err, SM_ENOMEM, "elastic basis: out of memory") : SM_OK;
  if (!rc) rc = sm_mesh_vertex_normals(m, N);
  if (!rc) rc = assemble_hessian(m, o, &H, err);
  for (int32_t v = 0; !rc && v < n; v++) M3[3 * v] = M3[3 * v + 1] = M3[3 * v + 2] = b->mass[v];
  b->timing.assembly += sm_now() - t0;
  int expected = 6 * b->n_components, nev = o->k + expected + SM_KERNEL_MARGIN;
  if (!rc && nev >= 3 * n)
    rc = sm_error_set(err, SM_EINVAL, "k = %d is too large for a mesh of %d vertices", o->k, n);
  for (int attempt = 0; !rc && attempt < 2; attempt++) {
    free(U);
    free(ev);
    U = malloc((size_t)3 * n * nev * sizeof *U);
    ev = malloc((size_t)nev * sizeof *ev);
    if (!U || !ev) {
      rc = sm_error_set(err, SM_ENOMEM, "elastic basis: out of memory for %d modes", nev);
      break;
    }
    rc = eigs(H, M3, nev, o, ev, U, &b->timing, err);
    if (rc) break;
    b->n_kernel = sm_basis_kernel_size(ev, nev, expected);
    if (b->n_kernel + o->k <= nev) break;
    /* More zero modes than expected (e.g. an unbent flat patch): solve again, wider. */
    nev = b->n_kernel + o->k + SM_KERNEL_MARGIN;
    if (nev >= 3 * n)
      rc = sm_error_set(err, SM_ENUMERIC, "%d zero modes leave fewer than k = %d modes",
                        b->n_kernel, o->k);
  }
  if (!rc) {
    double t1 = sm_now();
    memcpy(b->evals, ev + b->n_kernel, (size_t)o->k * sizeof *ev);
    project_on_normals(U, n, b->n_kernel, o->k, N, b->phi);
    rc = gram_factor(b, err);
    b->timing.projection = sm_now() - t1;
  }
  free(U); free(ev); free(M3); free(N);
  sm_csc_destroy(H);
  return rc;
}

static int check_opts(const sm_mesh *m, const sm_basis_opts *o, sm_error *err) {
  if (o->kind != SM_BASIS_LB && o->kind != SM_BASIS_ELASTIC)
    return sm_error_set(err, SM_EINVAL, "unknown basis kind %d", o->kind);
  if (o->k <= 0 || o->k >= m->nv)
    return sm_error_set(err, SM_EINVAL, "k = %d must be in [1, %d) for this mesh", o->k, m->nv);
  if (o->kind == SM_BASIS_ELASTIC && !(o->eta > 0 && isfinite(o->eta)))
    return sm_error_set(err, SM_EINVAL, "eta = %g must be positive and finite", o->eta);
  if (!(o->mu > 0) || !(o->lambda >= 0) || !isfinite(o->mu) || !isfinite(o->lambda))
    return sm_error_set(err, SM_EINVAL, "mu = %g, lambda = %g out of range", o->mu, o->lambda);
  return SM_OK;
}

int sm_basis_compute(const sm_mesh *m, const sm_basis_opts *o, sm_basis **out, sm_error *err) {
  *out = NULL;
  int rc = check_opts(m, o, err);
  if (rc) return rc;
  sm_basis *b = basis_new(m, o);
  int32_t *comp = malloc((size_t)m->nv * sizeof *comp);
  if (!b || !comp) {
    free(comp);
    sm_basis_destroy(b);
    return sm_error_set(err, SM_ENOMEM, "basis: out of memory for %d x %d", m->nv, o->k);
  }
  double t0 = sm_now();
  rc = sm_mesh_lumped_mass(m, b->mass);
  if (!rc) rc = sm_mesh_components(m, comp, &b->n_components);
  free(comp);
  b->mesh_hash = sm_mesh_hash(m);
  b->timing.assembly = sm_now() - t0;
  if (rc) sm_error_set(err, rc, "basis: mass or components failed");
  else if (o->kind == SM_BASIS_LB) rc = compute_lb(m, o, b, err);
  else rc = compute_elastic(m, o, b, err);
  if (rc) {
    sm_basis_destroy(b);
    return rc;
  }
  *out = b;
  return SM_OK;
}
