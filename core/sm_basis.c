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

void sm_basis_opts_of_spec(sm_basis_opts *o, const sm_basis_spec *spec) {
  sm_basis_opts_default(o, spec->kind, spec->k);
  if (spec->kind == SM_BASIS_ELASTIC) o->eta = spec->eta;
}

static const char *kind_tag(int kind) {
  return kind == SM_BASIS_LB ? "lb" : kind == SM_BASIS_ELASTIC ? "el" : "unknown";
}

int sm_basis_spec_check(const sm_basis_spec *spec, sm_error *err) {
  if (spec->kind < 1 || spec->kind > SM_BASIS_NKINDS)
    return sm_error_set(err, SM_EINVAL, "basis kind %d unknown", spec->kind);
  if (spec->k < 1)
    return sm_error_set(err, SM_EINVAL, "%s basis: k = %d, must be >= 1", kind_tag(spec->kind),
                        spec->k);
  if (spec->kind == SM_BASIS_ELASTIC && !(isfinite(spec->eta) && spec->eta > 0))
    return sm_error_set(err, SM_EINVAL, "elastic basis: eta = %g, must be finite and > 0",
                        spec->eta);
  if (spec->kind == SM_BASIS_LB && spec->eta != 0)
    return sm_error_set(err, SM_EINVAL, "lb basis: eta = %g, must be 0 (no parameter)",
                        spec->eta);
  return SM_OK;
}

static uint64_t eta_bits(double eta) {
  uint64_t u;
  memcpy(&u, &eta, sizeof u);
  return u;
}

int sm_basis_spec_eq(const sm_basis_spec *a, const sm_basis_spec *b) {
  return a->kind == b->kind && a->k == b->k && eta_bits(a->eta) == eta_bits(b->eta);
}

int sm_basis_spec_name(const sm_basis_spec *spec, char *buf, size_t n) {
  return snprintf(buf, n, "%s.k%d.eta%016llx", kind_tag(spec->kind), spec->k,
                  (unsigned long long)eta_bits(spec->eta));
}

int sm_basis_fits(const sm_basis *b, const sm_basis_spec *spec, const sm_mesh *m,
                  sm_error *err) {
  if (b->kind != spec->kind || b->k != spec->k)
    return sm_error_set(err, SM_EFORMAT, "basis is %s k = %d, %s k = %d was asked for",
                        kind_tag(b->kind), b->k, kind_tag(spec->kind), spec->k);
  if (spec->kind == SM_BASIS_ELASTIC && eta_bits(b->eta) != eta_bits(spec->eta))
    return sm_error_set(err, SM_EFORMAT, "basis has eta = %g, %g was asked for", b->eta,
                        spec->eta);
  if (b->n != m->nv || b->mesh_hash != sm_mesh_hash(m))
    return sm_error_set(err, SM_EFORMAT, "basis was computed on another mesh (%d vertices, "
                        "hash %016llx; this one: %d)", b->n,
                        (unsigned long long)b->mesh_hash, m->nv);
  return SM_OK;
}

static int cmp_double(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

/* The scale of the shift: tr(A)/tr(D), but at most SM_SHIFT_SPREAD times the median of
 * A_jj / D_j. The trace is a sum and one pathological element dominates it (a sliver made
 * centaur3's 7e7 times its median, putting the shift 1e7 below the wanted eigenvalues and
 * stalling Lanczos); on the TOSCA 5k shapes without one the ratio is 2-112, so the cap
 * leaves their shift, hence their results, unchanged. SM_ENOMEM falls back to the trace. */
#define SM_SHIFT_SPREAD 1000.0
static double shift_scale(const sm_csc *A, const double *D) {
  double ta = 0, td = 0;
  double *r = malloc((size_t)(A->n > 0 ? A->n : 1) * sizeof *r);
  for (int32_t j = 0; j < A->n; j++) {
    td += D[j];
    double ajj = 0;
    for (int32_t p = A->colptr[j]; p < A->colptr[j + 1]; p++)
      if (A->rowind[p] == j) ajj += A->val[p];
    ta += ajj;
    if (r) r[j] = ajj / D[j];
  }
  double scale = ta / td;
  if (r && A->n > 0) {
    qsort(r, (size_t)A->n, sizeof *r, cmp_double);
    double med = r[A->n / 2];
    if (med > 0 && scale > SM_SHIFT_SPREAD * med) scale = SM_SHIFT_SPREAD * med;
  }
  free(r);
  return scale;
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

/* Residual tolerance 1e-7 relative to theta (1e-9 before, as the ARPACK runs did). The
 * block solver's last steps cut the residuals by orders at a time, so the looser test only
 * ends it a step or two earlier with the same bases: against 1e-9, homerA, headA and the
 * koala, LB and elastic k = 100, eigenvalues equal to 1.5e-14 relative and every function
 * equal up to sign (|cos| in the M inner product 1 to 9 digits; 1 - |cos| <= 1.6e-14 where
 * measured to the last digit, homerA LB), in 12% fewer solves on the koala (elastic
 * 544 -> 480; eigensolve 11.5 -> 10.4 s) and 10-30% less eigensolve time on the others. */
#define SM_BASIS_EIGS_TOL 1e-7

static int eigs(const sm_csc *A, const double *D, int nev, const sm_basis_opts *o,
                double *evals, double *evecs, sm_basis_timing *tm, sm_error *err) {
  sm_eigs_opts eo = {.nev = nev, .sigma = -SM_SHIFT_REL * shift_scale(A, D),
                     .tol = SM_BASIS_EIGS_TOL, .cancel = o->cancel, .cancel_ud = o->cancel_ud,
                     .spare_threads = o->spare_threads};
  sm_eigs_stats st;
  int rc = sm_eigs_smallest(A, D, &eo, evals, evecs, &st, err);
  tm->factorization += st.t_analyze + st.t_factor;
  tm->eigensolve += st.t_solve;
  tm->solves += st.nsolves;
  return rc;
}

/* An eigenvector's sign is arbitrary, and which one a solver returns depends on its start
 * vectors, block size and rounding: fix it from the function itself, so that a basis is
 * the same whatever computed it (the ARPACK and block solvers agree to 1e-13 on the
 * eigenvalues and the functions up to sign). The sign makes the mass-weighted third moment
 * sum_v m_v phi(v)^3 positive (intrinsic: invariant under rigid motion and renumbering);
 * for a function without skew (|moment| at rounding level) the entry of largest magnitude
 * is made positive instead. */
static void fix_signs(double *phi, int32_t n, int k, const double *mass) {
  for (int i = 0; i < k; i++) {
    double *p = phi + (size_t)i * n, m3 = 0, m2 = 0, big = 0;
    for (int32_t v = 0; v < n; v++) {
      double x = p[v];
      m3 += mass[v] * x * x * x;
      m2 += mass[v] * x * x;
      if (fabs(x) > fabs(big)) big = x;
    }
    double s = fabs(m3) > 1e-8 * pow(m2, 1.5) ? m3 : big;
    if (s < 0)
      for (int32_t v = 0; v < n; v++) p[v] = -p[v];
  }
}

static int compute_lb(const sm_mesh *m, const sm_basis_opts *o, sm_basis *b, sm_error *err) {
  double t0 = sm_now();
  sm_csc *W;
  int rc = sm_cotan_stiffness(m, &W, err);
  b->timing.assembly += sm_now() - t0;
  if (rc) return rc;
  rc = eigs(W, b->mass, o->k, o, b->evals, b->phi, &b->timing, err);
  sm_csc_destroy(W);
  if (!rc) fix_signs(b->phi, b->n, o->k, b->mass);
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

/* Sliver caps. A face whose corners are nearly collinear ("cap": one angle close to 180
 * degrees) is a meshing artifact, but the shell treats it as real: its membrane terms
 * scale like |e|^2 / A and its bending terms like |e|^4 / A^3 (the dihedral gradient is
 * |e| / 2A). centaur3 of the TOSCA 5k set has one cap of area 2.7e-10 (mean 1e-4,
 * min angle 4e-5 degrees): its Hessian entries reach 1e17 times the mass where the wanted
 * eigenvalues are O(1), so (a) tr(H)/tr(M), the scale of the shift, grows from ~1e6 to
 * 4e13, putting sigma 1e7 below the wanted eigenvalues, where shift-invert cannot tell
 * them apart (the Lanczos run never converged), and (b) rounding in that one element
 * (eps * 1e17) swamps the rigid kernel (kernel "eigenvalues" of 4e-2 against 0.7 for the
 * first elastic mode: no detectable gap) and the low modes.
 * Remedy, for the Hessian only: flip the cap's longest edge, which splits the neighbouring
 * face at the cap's apex. Same vertices, same surface (the cap has no area), so the basis
 * still lives on the caller's mesh; mass and normals come from the mesh as given. A flip is
 * done only when the edge is a consistently oriented hinge, the new edge does not exist
 * yet, both new faces keep the neighbour's orientation and the worst quality improves.
 * Caps that cannot be flipped are left alone (the shift below no longer depends on them;
 * the kernel check reports what rounding did). Quality = lmax^2 / A: 2.3 equilateral,
 * under 300 on every TOSCA 5k shape but that one (5.8e6); 1e4 = a height 2e-4 of the
 * longest edge, where the element's stiffness is ~1e7 times that of a regular face. */
#define SM_SLIVER_QUALITY 1e4

static double tri_quality(const double *V, int32_t a, int32_t b, int32_t c, double *nrm) {
  const double *p = V + 3 * (int64_t)a, *q = V + 3 * (int64_t)b, *r = V + 3 * (int64_t)c;
  double u[3], v[3], w[3], n[3];
  for (int d = 0; d < 3; d++) {
    u[d] = q[d] - p[d];
    v[d] = r[d] - p[d];
    w[d] = r[d] - q[d];
  }
  n[0] = u[1] * v[2] - u[2] * v[1];
  n[1] = u[2] * v[0] - u[0] * v[2];
  n[2] = u[0] * v[1] - u[1] * v[0];
  if (nrm) memcpy(nrm, n, sizeof n);
  double l2 = fmax(u[0] * u[0] + u[1] * u[1] + u[2] * u[2],
                   fmax(v[0] * v[0] + v[1] * v[1] + v[2] * v[2],
                        w[0] * w[0] + w[1] * w[1] + w[2] * w[2]));
  double area = 0.5 * sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
  return area > 0 ? l2 / area : HUGE_VAL;
}

static int edge_exists(const sm_edges *e, const int32_t *added, int nadded, int32_t a,
                       int32_t b) {
  if (a > b) {
    int32_t t = a;
    a = b;
    b = t;
  }
  for (int i = 0; i < nadded; i++)
    if (added[2 * i] == a && added[2 * i + 1] == b) return 1;
  int32_t lo = 0, hi = e->ne; /* e->ev is sorted by (first, second) */
  while (lo < hi) {
    int32_t mid = lo + (hi - lo) / 2;
    const int32_t *x = e->ev + 2 * (int64_t)mid;
    if (x[0] < a || (x[0] == a && x[1] < b)) lo = mid + 1;
    else hi = mid;
  }
  return lo < e->ne && e->ev[2 * (int64_t)lo] == a && e->ev[2 * (int64_t)lo + 1] == b;
}

/* *out = a copy of m with its sliver caps flipped away, or NULL when there is none. */
static int flip_slivers(const sm_mesh *m, sm_mesh **out, int *nflipped, sm_error *err) {
  *out = NULL;
  *nflipped = 0;
  int32_t nsliver = 0;
  for (int32_t f = 0; f < m->nf; f++)
    if (tri_quality(m->V, m->F[3 * f], m->F[3 * f + 1], m->F[3 * f + 2], NULL) >
        SM_SLIVER_QUALITY)
      nsliver++;
  if (!nsliver) return SM_OK;
  sm_mesh *c = NULL;
  sm_edges *e = NULL;
  uint8_t *touched = calloc((size_t)m->nf, 1);
  int32_t *added = malloc((size_t)2 * nsliver * sizeof *added);
  int rc = (!touched || !added) ? sm_error_set(err, SM_ENOMEM, "sliver repair: out of memory")
                                : SM_OK;
  if (!rc) rc = sm_mesh_copy(m, &c, err);
  if (!rc) rc = sm_edges_build(m, &e, err);
  const double *V = m->V;
  for (int32_t f = 0; !rc && f < m->nf; f++) {
    const int32_t *F = m->F + 3 * (int64_t)f;
    double qf = tri_quality(V, F[0], F[1], F[2], NULL);
    if (!(qf > SM_SLIVER_QUALITY) || touched[f]) continue;
    /* The longest edge (corner ci -> ci+1) and its apex k. */
    int ci = 0;
    double best = -1;
    for (int d = 0; d < 3; d++) {
      const double *p = V + 3 * (int64_t)F[d], *q = V + 3 * (int64_t)F[(d + 1) % 3];
      double l2 = (q[0] - p[0]) * (q[0] - p[0]) + (q[1] - p[1]) * (q[1] - p[1]) +
                  (q[2] - p[2]) * (q[2] - p[2]);
      if (l2 > best) {
        best = l2;
        ci = d;
      }
    }
    int32_t i = F[ci], j = F[(ci + 1) % 3], k = F[(ci + 2) % 3];
    /* A cap: the apex projects inside the long edge (obtuse angle at k). */
    const double *pi = V + 3 * (int64_t)i, *pj = V + 3 * (int64_t)j, *pk = V + 3 * (int64_t)k;
    double dot = (pi[0] - pk[0]) * (pj[0] - pk[0]) + (pi[1] - pk[1]) * (pj[1] - pk[1]) +
                 (pi[2] - pk[2]) * (pj[2] - pk[2]);
    if (!(dot < 0)) continue;
    int32_t g = e->face_adj[3 * (int64_t)f + ci];
    if (g < 0 || touched[g]) continue;
    const int32_t *G = m->F + 3 * (int64_t)g;
    int gd = -1;
    for (int d = 0; d < 3; d++)
      if (G[d] == j && G[(d + 1) % 3] == i) gd = d;
    if (gd < 0) continue; /* the neighbour is not consistently oriented */
    int32_t l = G[(gd + 2) % 3];
    if (l == k || edge_exists(e, added, *nflipped, k, l)) continue;
    /* (i, j, k) + (j, i, l) -> (i, l, k) + (l, j, k): same boundary i->l->j->k->i. */
    double ng[3], n1[3], n2[3];
    double qg = tri_quality(V, G[0], G[1], G[2], ng);
    double q1 = tri_quality(V, i, l, k, n1), q2 = tri_quality(V, l, j, k, n2);
    if (!(fmax(q1, q2) < fmax(qf, qg))) continue;
    if (!(n1[0] * ng[0] + n1[1] * ng[1] + n1[2] * ng[2] > 0) ||
        !(n2[0] * ng[0] + n2[1] * ng[1] + n2[2] * ng[2] > 0))
      continue;
    int32_t *cf = c->F + 3 * (int64_t)f, *cg = c->F + 3 * (int64_t)g;
    cf[0] = i; cf[1] = l; cf[2] = k;
    cg[0] = l; cg[1] = j; cg[2] = k;
    touched[f] = touched[g] = 1;
    added[2 * *nflipped] = k < l ? k : l;
    added[2 * *nflipped + 1] = k < l ? l : k;
    (*nflipped)++;
  }
  free(touched);
  free(added);
  sm_edges_destroy(e);
  if (rc || !*nflipped) {
    sm_mesh_destroy(c);
    return rc;
  }
  *out = c;
  return SM_OK;
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
  sm_mesh *fixed = NULL;
  int nflipped = 0;
  if (!rc) rc = flip_slivers(m, &fixed, &nflipped, err);
  if (!rc) rc = assemble_hessian(fixed ? fixed : m, o, &H, err);
  sm_mesh_destroy(fixed);
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
    /* Rigid motions are always in the kernel: fewer zero modes than that means rounding
     * (an ill-conditioned Hessian) blurred the gap, and the "basis" would start with
     * near-rigid motions. Say so rather than return it. */
    if (b->n_kernel < expected) {
      rc = sm_error_set(err, SM_ENUMERIC, "elastic basis: the rigid kernel is not resolved "
                        "(%d clear zero modes, %d expected; eigenvalues %g .. %g): the "
                        "Hessian is ill-conditioned (degenerate faces?)", b->n_kernel,
                        expected, ev[0], ev[expected]);
      break;
    }
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
    fix_signs(b->phi, n, o->k, b->mass);
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
