/* sm_shell: discrete thin-shell energy and its closed-form rest-state Hessian.
 * Spec: ../shared/design/algorithm.md §3.1-3.2.
 *
 * DESIGN
 *   Energy. Near the rest state every term is a small difference of O(1) quantities, so it is
 *   evaluated in "difference form": per face D = g_bar^-1 (g - g_bar) with g - g_bar built
 *   from (u - u_bar) and (u + u_bar), det G - 1 = tr D + det D, and
 *     W = mu/2 (tr D - log1p(delta)) + lambda/4 (delta - log1p(delta)),  delta = det G - 1,
 *   which equals the W of the spec (expand a = 2 + tr D, d = 1 + delta). E then has relative
 *   rounding error ~eps/|x - x_bar| instead of absolute error ~eps, which is what lets a
 *   second-difference test of the Hessian reach ~1e-12 (Richardson, h = 1e-4). Bending uses the signed dihedral
 *   theta = atan2((N1 x N2).e, |e| N1.N2) with unnormalised face normals N (atan2 is
 *   invariant under a common positive scale of its arguments; N1 x N2 is parallel to e).
 *
 *   Membrane Hessian at rest (derivation; the spec's closed form is confirmed by FD in
 *   tests/test_shell.c, also for mu != lambda). With a = tr G, d = det G, at G = I:
 *     W_a = mu/2, W_d = lambda/4 - (mu/2 + lambda/4)/d = -mu/2, W_aa = W_ad = 0,
 *     W_dd = mu/2 + lambda/4, and grad d = grad a (d det = tr dG at I): gradient 0.
 *     hess(A_bar W) = A_bar (mu/2 hess a - mu/2 hess d + (mu/2 + lambda/4) grad d grad d^T).
 *   - A_bar tr(g_bar^-1 g) is the Dirichlet energy of the affine map of the face,
 *     1/2 sum_o cot(theta_o) |x_p - x_q|^2, so the first term is mu times the cotan stencil.
 *   - d = det g / det g_bar = S / S_bar (S = A^2, det g = 4S): A_bar hess d = hess S / A,
 *     giving -(mu / 2A) hess S.
 *   - grad d = grad S / A^2 = 2 grad A / A: A (mu/2 + lambda/4) 4/A^2 = (2 mu + lambda)/A.
 *   Bending: hess 3 (theta - theta_bar)^2 w = 6 w grad theta grad theta^T at rest.
 *
 *   Assembly is one pass over faces and one over hinges with element matrices on the
 *   stack, summed into one scratch block per edge and per vertex, then emitted once each.
 */
#include "sm_shell.h"

#include <float.h>
#include <math.h>
#include <stddef.h>
#include <stdlib.h>

static const double PI = 3.14159265358979323846; /* M_PI is not ISO C */

void sm_shell_params_default(sm_shell_params *p) {
  p->mu = 1.0;
  p->lambda = 1.0;
  p->eta = SM_SHELL_DEFAULT_ETA;
}

/* ---- small vector helpers ---- */

static inline void sub3(const double *a, const double *b, double *r) {
  r[0] = a[0] - b[0];
  r[1] = a[1] - b[1];
  r[2] = a[2] - b[2];
}

static inline void add3(const double *a, const double *b, double *r) {
  r[0] = a[0] + b[0];
  r[1] = a[1] + b[1];
  r[2] = a[2] + b[2];
}

static inline double dot3(const double *a, const double *b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static inline void cross3(const double *a, const double *b, double *r) {
  r[0] = a[1] * b[2] - a[2] * b[1];
  r[1] = a[2] * b[0] - a[0] * b[2];
  r[2] = a[0] * b[1] - a[1] * b[0];
}

/* A face is degenerate when |u x v| (twice its area) is at the rounding level of its edge
 * lengths: its cotangents and 1/A factors would be noise. */
static inline int degenerate(double two_area, double uu, double vv) {
  return !(two_area > DBL_EPSILON * (uu + vv));
}

static int check_args(const sm_mesh *rest, const sm_edges *topo, const sm_shell_params *p,
                      sm_error *err) {
  if (!rest || !topo || !p)
    return sm_error_set(err, SM_EINVAL, "sm_shell: NULL rest mesh, topology or parameters");
  if (!(isfinite(p->mu) && isfinite(p->lambda) && isfinite(p->eta)) || p->mu < 0 ||
      p->lambda < 0 || p->eta < 0)
    return sm_error_set(err, SM_EINVAL, "sm_shell: mu=%g lambda=%g eta=%g must be finite >= 0",
                        p->mu, p->lambda, p->eta);
  return SM_OK;
}

static int bad_face(const sm_mesh *m, int32_t f, sm_error *err) {
  const int32_t *F = m->F + 3 * (int64_t)f;
  for (int c = 0; c < 3; c++)
    if (F[c] < 0 || F[c] >= m->nv)
      return sm_error_set(err, SM_EINVAL, "face %d references vertex %d, mesh has %d", f, F[c],
                          m->nv);
  return SM_OK;
}

static int bad_hinge(const sm_mesh *m, const sm_edges *topo, int32_t h, sm_error *err) {
  const int32_t *q = topo->hinge + 4 * (int64_t)h;
  for (int c = 0; c < 4; c++)
    if (q[c] < 0 || q[c] >= m->nv)
      return sm_error_set(err, SM_EINVAL, "hinge %d references vertex %d, mesh has %d", h, q[c],
                          m->nv);
  return SM_OK;
}

/* ---- energy ---- */

/* W of one face in difference form (see DESIGN). Returns 1 if the deformed face has
 * (numerically) zero area, where log det G is undefined. */
static int face_energy(const double *ra, const double *rb, const double *rc, const double *xa,
                       const double *xb, const double *xc, double mu, double lambda,
                       double *W) {
  double ub[3], vb[3], u[3], v[3], du[3], dv[3], su[3], sv[3];
  sub3(rb, ra, ub);
  sub3(rc, ra, vb);
  sub3(xb, xa, u);
  sub3(xc, xa, v);
  sub3(u, ub, du);
  sub3(v, vb, dv);
  add3(u, ub, su);
  add3(v, vb, sv);
  double g11 = dot3(ub, ub), g12 = dot3(ub, vb), g22 = dot3(vb, vb), n[3];
  cross3(ub, vb, n);
  double detg = dot3(n, n); /* = g11 g22 - g12^2, without the cancellation */
  double d11 = dot3(du, su), d22 = dot3(dv, sv);
  double d12 = 0.5 * (dot3(du, sv) + dot3(su, dv)); /* u.v - ub.vb */
  double trD = (g22 * d11 - 2 * g12 * d12 + g11 * d22) / detg;
  double detD = (d11 * d22 - d12 * d12) / detg;
  double delta = trD + detD;
  if (!(delta > -1.0)) return 1;
  double l1 = log1p(delta);
  *W = 0.5 * mu * (trD - l1) + 0.25 * lambda * (delta - l1);
  return 0;
}

static int membrane_energy(const sm_mesh *rest, const sm_shell_params *p, const double *x,
                           double *E, sm_error *err) {
  double sum = 0;
  for (int32_t f = 0; f < rest->nf; f++) {
    if (bad_face(rest, f, err)) return SM_EINVAL;
    const int32_t *F = rest->F + 3 * (int64_t)f;
    const double *ra = rest->V + 3 * (int64_t)F[0], *rb = rest->V + 3 * (int64_t)F[1],
                 *rc = rest->V + 3 * (int64_t)F[2];
    double ub[3], vb[3], n[3], W;
    sub3(rb, ra, ub);
    sub3(rc, ra, vb);
    cross3(ub, vb, n);
    double two_area = sqrt(dot3(n, n));
    if (degenerate(two_area, dot3(ub, ub), dot3(vb, vb)))
      return sm_error_set(err, SM_EINVAL, "rest face %d has zero area", f);
    if (face_energy(ra, rb, rc, x + 3 * (int64_t)F[0], x + 3 * (int64_t)F[1],
                    x + 3 * (int64_t)F[2], p->mu, p->lambda, &W))
      return sm_error_set(err, SM_ENONFINITE, "face %d is deformed to zero area", f);
    sum += 0.5 * two_area * W;
  }
  *E = sum;
  return SM_OK;
}

/* Signed dihedral angle of hinge (i, j, k, l): 0 when flat, smooth through 0. */
static double dihedral(const double *xi, const double *xj, const double *xk, const double *xl,
                       double *ee, double *two_a1, double *two_a2) {
  double e[3], me[3], ak[3], al[3], n1[3], n2[3], c[3];
  sub3(xj, xi, e);
  sub3(xi, xj, me);
  sub3(xk, xi, ak);
  sub3(xl, xj, al);
  cross3(e, ak, n1);
  cross3(me, al, n2);
  cross3(n1, n2, c);
  *ee = dot3(e, e);
  *two_a1 = sqrt(dot3(n1, n1));
  *two_a2 = sqrt(dot3(n2, n2));
  return atan2(dot3(c, e), sqrt(*ee) * dot3(n1, n2));
}

static int bending_energy(const sm_mesh *rest, const sm_edges *topo, const double *x,
                          double *E, sm_error *err) {
  double sum = 0;
  for (int32_t h = 0; h < topo->nhinge; h++) {
    if (bad_hinge(rest, topo, h, err)) return SM_EINVAL;
    const int32_t *q = topo->hinge + 4 * (int64_t)h;
    const double *V = rest->V;
    double ee, a1, a2, xee, xa1, xa2;
    double tb = dihedral(V + 3 * (int64_t)q[0], V + 3 * (int64_t)q[1], V + 3 * (int64_t)q[2],
                         V + 3 * (int64_t)q[3], &ee, &a1, &a2);
    double t = dihedral(x + 3 * (int64_t)q[0], x + 3 * (int64_t)q[1], x + 3 * (int64_t)q[2],
                        x + 3 * (int64_t)q[3], &xee, &xa1, &xa2);
    if (!(a1 + a2 > 0)) return sm_error_set(err, SM_EINVAL, "hinge %d: zero-area rest faces", h);
    double d = t - tb; /* keep the difference in [-pi, pi] across the atan2 branch cut */
    if (d > PI) d -= 2 * PI;
    if (d < -PI) d += 2 * PI;
    sum += 3 * d * d * ee / (0.5 * (a1 + a2));
  }
  *E = sum;
  return SM_OK;
}

int sm_shell_energy(const sm_mesh *rest, const sm_edges *topo, const sm_shell_params *p,
                    const double *x, double *E, double *E_mem, double *E_bend, sm_error *err) {
  int rc = check_args(rest, topo, p, err);
  if (rc) return rc;
  if (!x) return sm_error_set(err, SM_EINVAL, "sm_shell_energy: NULL positions");
  double em = 0, eb = 0;
  if ((rc = membrane_energy(rest, p, x, &em, err))) return rc;
  if ((p->eta != 0 || E_bend) && (rc = bending_energy(rest, topo, x, &eb, err))) return rc;
  double e = em + p->eta * eb;
  if (!isfinite(e))
    return sm_error_set(err, SM_ENONFINITE, "shell energy is not finite (positions NaN/Inf?)");
  if (E) *E = e;
  if (E_mem) *E_mem = em;
  if (E_bend) *E_bend = eb;
  return SM_OK;
}

/* ---- rest Hessian ----
 * The 3x3 block of a vertex pair gets up to 7 element contributions (2 faces, its own
 * hinge, 4 neighbouring hinges), so blocks are summed in scratch first: one block per edge
 * (oriented ev[2e] -> ev[2e+1]) and per vertex, then emitted once each. Only the (k, l)
 * "diamond" block of a hinge is not an edge; it goes straight to the triplets. This emits
 * ~5x fewer triplets than per-element assembly, which dominated the time (memory traffic)
 * and also made sm_triplets_to_csc slower. */

/* Local pairs of a triangle's corners, r <= s. */
static const int PAIR3[6][2] = {{0, 0}, {1, 1}, {2, 2}, {0, 1}, {0, 2}, {1, 2}};

/* 9x9 membrane element matrix of face (a, b, c) as the six blocks of PAIR3.
 * H = L (x) I3 - mu/(2A) hess S + (2mu+lambda)/A gradA gradA^T (see DESIGN). */
static void membrane_element(const double *xa, const double *xb, const double *xc, double mu,
                             double lambda, double two_area, double K[6][9]) {
  double u[3], v[3];
  sub3(xb, xa, u);
  sub3(xc, xa, v);
  double uu = dot3(u, u), vv = dot3(v, v), uv = dot3(u, v);
  /* cotan stencil: w_o = mu cot(theta_o)/2 on the edge opposite o; cot = dot / (2A) */
  double wa = 0.5 * mu * uv / two_area, wb = 0.5 * mu * (uu - uv) / two_area,
         wc = 0.5 * mu * (vv - uv) / two_area;
  const double L[6] = {wb + wc, wa + wc, wa + wb, -wc, -wb, -wa};
  /* hess S blocks; Suv[i][j] = d2S / du_i dv_j */
  double Suu[9], Svv[9], Suv[9], HS[6][9], gS[3][3];
  for (int i = 0; i < 3; i++)
    for (int j = 0; j < 3; j++) {
      double id = i == j ? 1.0 : 0.0;
      Suu[3 * i + j] = 0.5 * (vv * id - v[i] * v[j]);
      Svv[3 * i + j] = 0.5 * (uu * id - u[i] * u[j]);
      Suv[3 * i + j] = 0.5 * (2 * u[i] * v[j] - v[i] * u[j] - uv * id);
    }
  for (int i = 0; i < 3; i++)
    for (int j = 0; j < 3; j++) {
      int ij = 3 * i + j, ji = 3 * j + i;
      double m1 = Suu[ij] + Suv[ji], m2 = Suv[ij] + Svv[ij]; /* Suu+Svu, Suv+Svv */
      HS[0][ij] = m1 + m2; /* (a,a) = Suu+Suv+Svu+Svv */
      HS[1][ij] = Suu[ij];
      HS[2][ij] = Svv[ij];
      HS[3][ij] = -m1;
      HS[4][ij] = -m2;
      HS[5][ij] = Suv[ij];
    }
  for (int i = 0; i < 3; i++) {
    gS[1][i] = 0.5 * (vv * u[i] - uv * v[i]);
    gS[2][i] = 0.5 * (uu * v[i] - uv * u[i]);
    gS[0][i] = -(gS[1][i] + gS[2][i]);
  }
  /* gradA = gradS / (2A): (2mu+lambda)/A gA gA^T = 2(2mu+lambda)/(2A)^3 gS gS^T */
  double c1 = -mu / two_area, c2 = 2 * (2 * mu + lambda) / (two_area * two_area * two_area);
  for (int k = 0; k < 6; k++) {
    const double *gr = gS[PAIR3[k][0]], *gs = gS[PAIR3[k][1]];
    for (int i = 0; i < 3; i++)
      for (int j = 0; j < 3; j++)
        K[k][3 * i + j] = (i == j ? L[k] : 0.0) + c1 * HS[k][3 * i + j] + c2 * gr[i] * gs[j];
  }
}

/* Gradient g (4 x 3, corners i, j, k, l) of the dihedral angle at the rest state and the
 * weight 6 |e|^2 / (A1 + A2). Returns 1 if a face of the hinge is degenerate. */
static int hinge_gradient(const double *xi, const double *xj, const double *xk, const double *xl,
                          double g[4][3], double *w) {
  double e[3], me[3], ak[3], al[3], n1[3], n2[3], ik[3], il[3];
  sub3(xj, xi, e);
  sub3(xi, xj, me);
  sub3(xk, xi, ak);
  sub3(xl, xj, al);
  cross3(e, ak, n1);
  cross3(me, al, n2);
  double ee = dot3(e, e), q1 = dot3(n1, n1), q2 = dot3(n2, n2), le = sqrt(ee);
  if (!(q1 > 0 && q2 > 0 && ee > 0)) return 1;
  /* g_k = -|e|/(2 A1) N1/|N1| = -|e| N1 / |N1|^2 */
  sub3(xk, xi, ik);
  sub3(xl, xi, il);
  double tk = dot3(ik, e) / ee, tl = dot3(il, e) / ee;
  for (int c = 0; c < 3; c++) {
    g[2][c] = -le * n1[c] / q1;
    g[3][c] = -le * n2[c] / q2;
    g[0][c] = -(1 - tk) * g[2][c] - (1 - tl) * g[3][c];
    g[1][c] = -tk * g[2][c] - tl * g[3][c];
  }
  *w = 6 * ee / (0.5 * (sqrt(q1) + sqrt(q2)));
  return 0;
}
typedef struct block_acc {
  const sm_edges *topo;
  double *eb; /* 9 per edge */
  double *vb; /* 9 per vertex */
} block_acc;

/* Adds B (rows of I, columns of J) to the block of edge e, which must join I and J. */
static inline int acc_edge(block_acc *a, int32_t e, int32_t I, int32_t J, const double B[9]) {
  if (e < 0 || e >= a->topo->ne) return 1;
  const int32_t *ev = a->topo->ev + 2 * (int64_t)e;
  double *D = a->eb + 9 * (int64_t)e;
  if (ev[0] == I && ev[1] == J) {
    for (int q = 0; q < 9; q++) D[q] += B[q];
  } else if (ev[0] == J && ev[1] == I) {
    for (int r = 0; r < 3; r++)
      for (int c = 0; c < 3; c++) D[3 * r + c] += B[3 * c + r];
  } else {
    return 1;
  }
  return 0;
}

static inline void acc_vertex(block_acc *a, int32_t v, const double B[9]) {
  double *D = a->vb + 9 * (int64_t)v;
  for (int q = 0; q < 9; q++) D[q] += B[q];
}

static int topo_mismatch(sm_error *err, const char *what, int32_t id) {
  return sm_error_set(err, SM_EINVAL, "%s %d: topology does not match the rest mesh", what, id);
}

/* Edge of face f between corner pairs PAIR3[3..5] = (0,1), (0,2), (1,2). */
static const int PAIR_SLOT[3] = {0, 2, 1};

static int membrane_hessian(const sm_mesh *rest, const sm_shell_params *p, block_acc *a,
                            sm_error *err) {
  for (int32_t f = 0; f < rest->nf; f++) {
    if (bad_face(rest, f, err)) return SM_EINVAL;
    const int32_t *F = rest->F + 3 * (int64_t)f;
    const double *xa = rest->V + 3 * (int64_t)F[0], *xb = rest->V + 3 * (int64_t)F[1],
                 *xc = rest->V + 3 * (int64_t)F[2];
    double u[3], v[3], n[3], K[6][9];
    sub3(xb, xa, u);
    sub3(xc, xa, v);
    cross3(u, v, n);
    double two_area = sqrt(dot3(n, n));
    if (degenerate(two_area, dot3(u, u), dot3(v, v)))
      return sm_error_set(err, SM_EINVAL, "rest face %d has zero area", f);
    membrane_element(xa, xb, xc, p->mu, p->lambda, two_area, K);
    for (int k = 0; k < 3; k++) acc_vertex(a, F[k], K[k]);
    for (int k = 3; k < 6; k++) {
      int32_t e = a->topo->face_edge[3 * (int64_t)f + PAIR_SLOT[k - 3]];
      if (acc_edge(a, e, F[PAIR3[k][0]], F[PAIR3[k][1]], K[k])) return topo_mismatch(err, "face", f);
    }
  }
  return SM_OK;
}

/* Edges of hinge h for its local pairs (i,j), (i,k), (j,k), (i,l), (j,l), from the
 * face_edge lists of its two faces. Returns 1 if the hinge does not fit its faces. */
static int hinge_edges(const sm_mesh *rest, const sm_edges *topo, int32_t h, int32_t e5[5]) {
  const int32_t *q = topo->hinge + 4 * (int64_t)h, *hf = topo->hinge_face + 2 * (int64_t)h;
  if (hf[0] < 0 || hf[0] >= rest->nf || hf[1] < 0 || hf[1] >= rest->nf) return 1;
  const int32_t *F1 = rest->F + 3 * (int64_t)hf[0], *F2 = rest->F + 3 * (int64_t)hf[1];
  const int32_t *E1 = topo->face_edge + 3 * (int64_t)hf[0],
                *E2 = topo->face_edge + 3 * (int64_t)hf[1];
  int c = 0, d = 0;
  while (c < 3 && F1[c] != q[0]) c++;
  while (d < 3 && F2[d] != q[3]) d++;
  if (c == 3 || d == 3) return 1;
  e5[0] = E1[c];           /* i -> j */
  e5[2] = E1[(c + 1) % 3]; /* j -> k */
  e5[1] = E1[(c + 2) % 3]; /* k -> i */
  /* face 2 runs l -> next and prev -> l; one of next/prev is i, the other j */
  int i_next = F2[(d + 1) % 3] == q[0];
  e5[3] = i_next ? E2[d] : E2[(d + 2) % 3];
  e5[4] = i_next ? E2[(d + 2) % 3] : E2[d];
  return 0; /* acc_edge checks each edge's endpoints */
}

/* Local pairs (r < s) of a hinge (i, j, k, l) that are edges, in hinge_edges order. */
static const int HPAIR[5][2] = {{0, 1}, {0, 2}, {1, 2}, {0, 3}, {1, 3}};

static int bending_hessian(const sm_mesh *rest, const sm_edges *topo, double eta,
                           block_acc *a, sm_triplets *t, sm_error *err) {
  const double *V = rest->V;
  for (int32_t h = 0; h < topo->nhinge; h++) {
    if (bad_hinge(rest, topo, h, err)) return SM_EINVAL;
    const int32_t *q = topo->hinge + 4 * (int64_t)h;
    double g[4][3], w, B[9];
    int32_t e5[5];
    if (hinge_edges(rest, topo, h, e5)) return topo_mismatch(err, "hinge", h);
    if (hinge_gradient(V + 3 * (int64_t)q[0], V + 3 * (int64_t)q[1], V + 3 * (int64_t)q[2],
                       V + 3 * (int64_t)q[3], g, &w))
      return sm_error_set(err, SM_EINVAL, "hinge %d has a zero-area rest face", h);
    w *= eta;
    for (int r = 0; r < 4; r++) {
      for (int x = 0; x < 3; x++)
        for (int y = 0; y < 3; y++) B[3 * x + y] = w * g[r][x] * g[r][y];
      acc_vertex(a, q[r], B);
    }
    for (int k = 0; k < 5; k++) {
      const double *gr = g[HPAIR[k][0]], *gs = g[HPAIR[k][1]];
      for (int x = 0; x < 3; x++)
        for (int y = 0; y < 3; y++) B[3 * x + y] = w * gr[x] * gs[y];
      if (acc_edge(a, e5[k], q[HPAIR[k][0]], q[HPAIR[k][1]], B))
        return topo_mismatch(err, "hinge", h);
    }
    /* (k, l): not an edge. k == l only for a hinge between two copies of one face. */
    for (int x = 0; x < 3; x++)
      for (int y = 0; y < 3; y++) B[3 * x + y] = w * g[2][x] * g[3][y];
    if (q[2] == q[3]) {
      double S[9];
      for (int x = 0; x < 3; x++)
        for (int y = 0; y < 3; y++) S[3 * x + y] = B[3 * x + y] + B[3 * y + x];
      acc_vertex(a, q[2], S);
    } else if (sm_triplets_add_block3(t, q[2], q[3], B)) {
      return sm_error_set(err, SM_ENOMEM, "out of memory assembling the shell Hessian");
    }
  }
  return SM_OK;
}

/* One block per edge and per vertex (diagonal blocks are symmetric; add_block3 keeps
 * their lower triangle). */
static int emit_blocks(const sm_mesh *rest, const block_acc *a, sm_triplets *t) {
  const sm_edges *topo = a->topo;
  for (int32_t e = 0; e < topo->ne; e++)
    if (sm_triplets_add_block3(t, topo->ev[2 * (int64_t)e], topo->ev[2 * (int64_t)e + 1],
                               a->eb + 9 * (int64_t)e))
      return SM_ENOMEM;
  for (int32_t v = 0; v < rest->nv; v++)
    if (sm_triplets_add_block3(t, v, v, a->vb + 9 * (int64_t)v)) return SM_ENOMEM;
  return SM_OK;
}

int sm_shell_hessian(const sm_mesh *rest, const sm_edges *topo, const sm_shell_params *p,
                     sm_triplets *t, sm_error *err) {
  int rc = check_args(rest, topo, p, err);
  if (rc) return rc;
  if (!t || (int64_t)t->n != 3 * (int64_t)rest->nv)
    return sm_error_set(err, SM_EINVAL, "sm_shell_hessian: triplets of size %d, need 3*nv = %lld",
                        t ? t->n : -1, 3 * (long long)rest->nv);
  block_acc a = {topo, NULL, NULL};
  a.eb = calloc(9 * ((size_t)topo->ne + (size_t)rest->nv), sizeof(double));
  if (!a.eb) return sm_error_set(err, SM_ENOMEM, "out of memory for shell Hessian scratch");
  a.vb = a.eb + 9 * (size_t)topo->ne;
  /* On failure the triplets may hold part of the Hessian; the caller discards them. */
  rc = membrane_hessian(rest, p, &a, err);
  if (!rc && p->eta != 0) rc = bending_hessian(rest, topo, p->eta, &a, t, err);
  if (!rc && emit_blocks(rest, &a, t))
    rc = sm_error_set(err, SM_ENOMEM, "out of memory assembling the shell Hessian");
  free(a.eb);
  return rc;
}
