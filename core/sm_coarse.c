#include "sm_coarse.h"

#include <cblas.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

void sm_coarse_opts_default(sm_coarse_opts *o) {
  o->k0 = 30;
  o->op_stride = 5;
  o->w_desc = 1e-1;
  o->w_lap = 1e-1;
  o->w_comm = 1.0;
  o->w_orient = 1.0;
  o->orient_sign = 1;
  o->cg_iters = 500;
}

/* Per-side data: descriptor coefficients and the operators, all k0-sized. */
typedef struct side_ops {
  int k0, nops;
  double *A;     /* k0 x nd */
  double *O;     /* nops blocks of k0 x k0 */
  double *R;     /* nops blocks of k0 x k0 */
  const double *evals;
  double phi0_sign; /* sign of the first (constant) eigenfunction */
} side_ops;

static void side_free(side_ops *s) {
  free(s->A);
  free(s->O);
  free(s->R);
}

/* out (k0 x cols) = Phi^T M F for F (n x cols). */
static void project(const sm_basis *b, int k0, const double *F, int cols, double *out,
                    double *work) {
  int32_t n = b->n;
  for (int c = 0; c < cols; c++)
    for (int32_t v = 0; v < n; v++) work[(size_t)c * n + v] = b->mass[v] * F[(size_t)c * n + v];
  cblas_dgemm(CblasColMajor, CblasTrans, CblasNoTrans, k0, cols, n, 1.0, b->phi, n, work, n,
              0.0, out, k0);
}

/* Per-face unit normal, area and the three gradient vectors of the hat functions:
 * grad f on face t = sum_c f[F[c]] * H[9t + 3c ..]. */
static void face_geometry(const sm_mesh *m, double *N, double *area, double *H) {
  for (int32_t t = 0; t < m->nf; t++) {
    const int32_t *F = m->F + 3 * (int64_t)t;
    const double *p[3] = {m->V + 3 * (int64_t)F[0], m->V + 3 * (int64_t)F[1],
                          m->V + 3 * (int64_t)F[2]};
    double u[3], v[3], n[3];
    for (int d = 0; d < 3; d++) {
      u[d] = p[1][d] - p[0][d];
      v[d] = p[2][d] - p[0][d];
    }
    n[0] = u[1] * v[2] - u[2] * v[1];
    n[1] = u[2] * v[0] - u[0] * v[2];
    n[2] = u[0] * v[1] - u[1] * v[0];
    double len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    area[t] = 0.5 * len;
    for (int d = 0; d < 3; d++) N[3 * t + d] = len > 0 ? n[d] / len : 0;
    /* grad of hat c = n x e_c / (2A), e_c the edge opposite c, counter-clockwise. */
    for (int c = 0; c < 3; c++) {
      const double *a = p[(c + 1) % 3], *b = p[(c + 2) % 3];
      double e[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]}, *h = H + 9 * (int64_t)t + 3 * c;
      double s = len > 0 ? 1.0 / len : 0; /* 1/(2A) */
      h[0] = s * (N[3 * t + 1] * e[2] - N[3 * t + 2] * e[1]);
      h[1] = s * (N[3 * t + 2] * e[0] - N[3 * t] * e[2]);
      h[2] = s * (N[3 * t] * e[1] - N[3 * t + 1] * e[0]);
    }
  }
}

static void face_grad(const sm_mesh *m, const double *H, int32_t t, const double *f,
                      double g[3]) {
  const int32_t *F = m->F + 3 * (int64_t)t;
  const double *h = H + 9 * (int64_t)t;
  for (int d = 0; d < 3; d++) g[d] = f[F[0]] * h[d] + f[F[1]] * h[3 + d] + f[F[2]] * h[6 + d];
}

/* Unit gradients of the nu functions on face t (zero where undefined). */
static void unit_grads(const sm_mesh *m, const double *H, int32_t t, const double *U, int nu,
                       double *g) {
  for (int a = 0; a < nu; a++) {
    double *ga = g + 3 * a;
    face_grad(m, H, t, U + (size_t)a * m->nv, ga);
    double len = sqrt(ga[0] * ga[0] + ga[1] * ga[1] + ga[2] * ga[2]);
    double s = len > 0 && isfinite(len) ? 1 / len : 0;
    for (int d = 0; d < 3; d++) ga[d] = s ? ga[d] * s : 0;
  }
}

int sm_orientation_features(const sm_mesh *m, const double *U, int nu, double scale,
                            double *out, sm_error *err) {
  if (nu < 0) return sm_error_set(err, SM_EINVAL, "orientation features: nu = %d", nu);
  int np = nu * (nu - 1) / 2;
  int32_t n = m->nv;
  double *N = malloc((size_t)m->nf * 3 * sizeof *N), *area = malloc((size_t)m->nf * sizeof *area);
  double *H = malloc((size_t)m->nf * 9 * sizeof *H), *va = calloc((size_t)n, sizeof *va);
  double *g = malloc((size_t)(nu > 0 ? nu : 1) * 3 * sizeof *g);
  int rc = (!N || !area || !H || !va || !g)
               ? sm_error_set(err, SM_ENOMEM, "orientation features: out of memory")
               : SM_OK;
  if (!rc) {
    face_geometry(m, N, area, H);
    memset(out, 0, (size_t)n * np * sizeof *out);
  }
  for (int32_t t = 0; !rc && t < m->nf; t++) {
    const double *nt = N + 3 * (int64_t)t;
    const int32_t *F = m->F + 3 * (int64_t)t;
    unit_grads(m, H, t, U, nu, g);
    for (int a = 0, q = 0; a < nu; a++)
      for (int b = a + 1; b < nu; b++, q++) {
        const double *ga = g + 3 * a, *gb = g + 3 * b;
        double s = nt[0] * (ga[1] * gb[2] - ga[2] * gb[1]) +
                   nt[1] * (ga[2] * gb[0] - ga[0] * gb[2]) +
                   nt[2] * (ga[0] * gb[1] - ga[1] * gb[0]);
        for (int c = 0; c < 3; c++) out[(size_t)F[c] * np + q] += area[t] * s;
      }
    for (int c = 0; c < 3; c++) va[F[c]] += area[t];
  }
  for (int32_t v = 0; !rc && v < n; v++)
    for (int q = 0; q < np; q++) out[(size_t)v * np + q] *= va[v] > 0 ? scale / va[v] : 0;
  free(N);
  free(area);
  free(H);
  free(va);
  free(g);
  return rc;
}

typedef struct geom {
  double *N, *area, *H, *vert_area;
  double *gradphi; /* nf x 3 x k0: gradient of each basis function per face */
} geom;

static void geom_free(geom *g) {
  free(g->N); free(g->area); free(g->H); free(g->vert_area); free(g->gradphi);
}

static int geom_init(geom *g, const sm_mesh *m, const sm_basis *b, int k0) {
  memset(g, 0, sizeof *g);
  g->N = malloc((size_t)m->nf * 3 * sizeof(double));
  g->area = malloc((size_t)m->nf * sizeof(double));
  g->H = malloc((size_t)m->nf * 9 * sizeof(double));
  g->vert_area = calloc((size_t)m->nv, sizeof(double));
  g->gradphi = malloc((size_t)m->nf * 3 * k0 * sizeof(double));
  if (!g->N || !g->area || !g->H || !g->vert_area || !g->gradphi) return SM_ENOMEM;
  face_geometry(m, g->N, g->area, g->H);
  for (int32_t t = 0; t < m->nf; t++)
    for (int c = 0; c < 3; c++) g->vert_area[m->F[3 * (int64_t)t + c]] += g->area[t];
  for (int j = 0; j < k0; j++)
    for (int32_t t = 0; t < m->nf; t++)
      face_grad(m, g->H, t, b->phi + (size_t)j * b->n, g->gradphi + ((size_t)t * k0 + j) * 3);
  return SM_OK;
}

/* field (n x k0): vertex average (area-weighted) of <n, grad f x grad phi_j> per face,
 * using <n, a x b> = b . (n x a). */
static void orientation_field(const sm_mesh *m, const geom *g, int k0, const double *f,
                              double *field) {
  memset(field, 0, (size_t)m->nv * k0 * sizeof *field);
  for (int32_t t = 0; t < m->nf; t++) {
    double gf[3], w[3];
    const double *n = g->N + 3 * (int64_t)t;
    face_grad(m, g->H, t, f, gf);
    w[0] = n[1] * gf[2] - n[2] * gf[1];
    w[1] = n[2] * gf[0] - n[0] * gf[2];
    w[2] = n[0] * gf[1] - n[1] * gf[0];
    for (int j = 0; j < k0; j++) {
      const double *gp = g->gradphi + ((size_t)t * k0 + j) * 3;
      double val = g->area[t] * (gp[0] * w[0] + gp[1] * w[1] + gp[2] * w[2]);
      for (int c = 0; c < 3; c++) field[(size_t)j * m->nv + m->F[3 * (int64_t)t + c]] += val;
    }
  }
  for (int j = 0; j < k0; j++)
    for (int32_t v = 0; v < m->nv; v++)
      if (g->vert_area[v] > 0) field[(size_t)j * m->nv + v] /= g->vert_area[v];
}

static int side_build(side_ops *s, const sm_coarse_side *x, int nd, const sm_coarse_opts *o) {
  const sm_basis *b = x->lb;
  int k0 = o->k0;
  int32_t n = b->n;
  memset(s, 0, sizeof *s);
  s->k0 = k0;
  s->evals = b->evals;
  s->phi0_sign = b->phi[0] < 0 ? -1.0 : 1.0;
  s->nops = (nd + o->op_stride - 1) / o->op_stride;
  s->A = malloc((size_t)k0 * nd * sizeof *s->A);
  s->O = malloc((size_t)s->nops * k0 * k0 * sizeof *s->O);
  s->R = malloc((size_t)s->nops * k0 * k0 * sizeof *s->R);
  double *work = malloc((size_t)n * (nd > k0 ? nd : k0) * sizeof *work);
  double *field = malloc((size_t)n * k0 * sizeof *field);
  geom g;
  int rc = geom_init(&g, x->mesh, b, k0);
  if (rc || !s->A || !s->O || !s->R || !work || !field) rc = SM_ENOMEM;
  if (!rc) {
    project(b, k0, x->desc, nd, s->A, work);
    for (int q = 0; q < s->nops; q++) {
      const double *f = x->desc + (size_t)q * o->op_stride * n;
      for (int j = 0; j < k0; j++)
        for (int32_t v = 0; v < n; v++) field[(size_t)j * n + v] = f[v] * b->phi[(size_t)j * n + v];
      project(b, k0, field, k0, s->O + (size_t)q * k0 * k0, work);
      orientation_field(x->mesh, &g, k0, f, field);
      project(b, k0, field, k0, s->R + (size_t)q * k0 * k0, work);
    }
  }
  geom_free(&g);
  free(work);
  free(field);
  return rc;
}

/* The quadratic energy's Hessian applied to C (up to the factor 2 shared with the
 * right-hand side): HC = w_d C A_Y A_Y^T + w_l D o C + sum w (E P^T - Q^T E), E = C P - Q C. */
typedef struct problem {
  const side_ops *x, *y;
  const sm_coarse_opts *o;
  int k0, nd;
  double *AyAyT, *lapw, *E, *T1;
  double s_comm, s_orient; /* per-term normalization, see term_scales */
  int fix_first;           /* column 0 (the constant function) is held fixed */
} problem;

static void add_comm(const problem *p, const double *Py, const double *Qx, double s, double w,
                     const double *C, double *out) {
  int k = p->k0;
  /* E = C Py - s Qx C */
  cblas_dgemm(CblasColMajor, CblasNoTrans, CblasNoTrans, k, k, k, 1.0, C, k, Py, k, 0.0, p->E, k);
  cblas_dgemm(CblasColMajor, CblasNoTrans, CblasNoTrans, k, k, k, -s, Qx, k, C, k, 1.0, p->E, k);
  /* out += w (E Py^T - s Qx^T E) */
  cblas_dgemm(CblasColMajor, CblasNoTrans, CblasTrans, k, k, k, w, p->E, k, Py, k, 1.0, out, k);
  cblas_dgemm(CblasColMajor, CblasTrans, CblasNoTrans, k, k, k, -s * w, Qx, k, p->E, k, 1.0, out, k);
}

static void apply_hessian(const problem *p, const double *C, double *out) {
  int k = p->k0;
  const sm_coarse_opts *o = p->o;
  cblas_dgemm(CblasColMajor, CblasNoTrans, CblasNoTrans, k, k, k, o->w_desc, C, k, p->AyAyT, k,
              0.0, out, k);
  for (int i = 0; i < k * k; i++) out[i] += o->w_lap * p->lapw[i] * C[i];
  for (int q = 0; q < p->x->nops; q++) {
    size_t off = (size_t)q * k * k;
    if (o->w_comm > 0)
      add_comm(p, p->y->O + off, p->x->O + off, 1.0, o->w_comm * p->s_comm, C, out);
    if (o->w_orient > 0)
      add_comm(p, p->y->R + off, p->x->R + off, (double)o->orient_sign,
               o->w_orient * p->s_orient, C, out);
  }
}

static double sq_diff(const double *a, const double *b, double s, int n) {
  double e = 0;
  for (int i = 0; i < n; i++) e += (a[i] - s * b[i]) * (a[i] - s * b[i]);
  return e;
}

/* The operator terms have very different magnitudes (orientation operators carry two
 * gradients). As in Ren et al. 2018, each is divided by its value at C = I, so the weights
 * compare like with like: at the identity both terms equal their weight. */
static void term_scales(problem *p) {
  int k = p->k0;
  double ec = 0, eo = 0;
  for (int q = 0; q < p->x->nops; q++) {
    size_t off = (size_t)q * k * k;
    ec += sq_diff(p->y->O + off, p->x->O + off, 1.0, k * k);
    eo += sq_diff(p->y->R + off, p->x->R + off, (double)p->o->orient_sign, k * k);
  }
  p->s_comm = ec > 0 ? 1.0 / ec : 1.0;
  p->s_orient = eo > 0 ? 1.0 / eo : 1.0;
}

static double dot(const double *a, const double *b, int n) {
  double s = 0;
  for (int i = 0; i < n; i++) s += a[i] * b[i];
  return s;
}

/* Conjugate gradients on H C = w_d A_X A_Y^T over the free entries of C. Column 0 is held
 * at (s, 0, ..., 0): the constant function of Y pulls back to the constant of X (both
 * shapes have unit area; s absorbs the arbitrary signs of the two eigenvectors). */
static void solve_cg(const problem *p, double *C, double *r, double *d, double *Hd) {
  int k = p->k0, m = k * k;
  memset(C, 0, (size_t)m * sizeof *C);
  cblas_dgemm(CblasColMajor, CblasNoTrans, CblasTrans, k, k, p->nd, p->o->w_desc, p->x->A, k,
              p->y->A, k, 0.0, r, k);
  if (p->fix_first) {
    C[0] = p->x->phi0_sign * p->y->phi0_sign;
    apply_hessian(p, C, Hd);
    for (int i = 0; i < m; i++) r[i] -= Hd[i];
    for (int i = 0; i < k; i++) r[i] = 0;
  }
  memcpy(d, r, (size_t)m * sizeof *d);
  double rr = dot(r, r, m), rr0 = rr;
  for (int it = 0; it < p->o->cg_iters && rr > 1e-24 * rr0; it++) {
    apply_hessian(p, d, Hd);
    if (p->fix_first)
      for (int i = 0; i < k; i++) Hd[i] = 0;
    double alpha = rr / dot(d, Hd, m);
    for (int i = 0; i < m; i++) {
      C[i] += alpha * d[i];
      r[i] -= alpha * Hd[i];
    }
    double rr_new = dot(r, r, m);
    for (int i = 0; i < m; i++) d[i] = r[i] + (rr_new / rr) * d[i];
    rr = rr_new;
  }
}

/* Laplacian commutativity weights (lambda^Y_j - lambda^X_i)^2 divided by their squared
 * Frobenius norm, so that w_lap does not depend on the spectrum's magnitude. */
static void lap_weights(const side_ops *x, const side_ops *y, double *w) {
  int k = x->k0;
  double s = 0;
  for (int j = 0; j < k; j++)
    for (int i = 0; i < k; i++) {
      double d = y->evals[j] - x->evals[i];
      w[(size_t)j * k + i] = d * d;
      s += d * d * d * d;
    }
  s = s > 0 ? 1.0 / s : 0;
  for (int i = 0; i < k * k; i++) w[i] *= s;
}

struct sm_coarse_prep {
  side_ops ops;
  int nd, op_stride;
};

static int check_side(const sm_coarse_side *s, int nd, const sm_coarse_opts *o,
                      sm_error *err) {
  int k = o->k0;
  if (!s || !s->lb || !s->mesh || !s->desc || k < 2 || k > s->lb->k || nd < 1 ||
      o->op_stride < 1)
    return sm_error_set(err, SM_EINVAL, "coarse map: k0 = %d, nd = %d, stride = %d invalid", k,
                        nd, o->op_stride);
  if (s->lb->gram_L)
    return sm_error_set(err, SM_EINVAL, "coarse map: needs orthonormal LB bases");
  return 0;
}

int sm_coarse_prepare(const sm_coarse_side *s, int nd, const sm_coarse_opts *o,
                      sm_coarse_prep **out, sm_error *err) {
  *out = NULL;
  int rc = check_side(s, nd, o, err);
  if (rc) return rc;
  sm_coarse_prep *p = calloc(1, sizeof *p);
  if (!p || side_build(&p->ops, s, nd, o)) {
    if (p) side_free(&p->ops);
    free(p);
    return sm_error_set(err, SM_ENOMEM, "coarse map: out of memory");
  }
  p->nd = nd;
  p->op_stride = o->op_stride;
  *out = p;
  return 0;
}

int sm_coarse_prep_fits(const sm_coarse_prep *p, int nd, const sm_coarse_opts *o) {
  return p && p->nd == nd && p->op_stride == o->op_stride && p->ops.k0 == o->k0;
}

void sm_coarse_prep_destroy(sm_coarse_prep *p) {
  if (!p) return;
  side_free(&p->ops);
  free(p);
}

int sm_coarse_fmap_prepared(const sm_coarse_prep *x, const sm_coarse_prep *y,
                            const sm_coarse_opts *o, double *C, sm_error *err) {
  if (!x || !y || !C || x->nd != y->nd || !sm_coarse_prep_fits(x, x->nd, o) ||
      !sm_coarse_prep_fits(y, y->nd, o))
    return sm_error_set(err, SM_EINVAL, "coarse map: prepared sides do not fit the options");
  int k = o->k0, nd = x->nd;
  problem p = {.x = &x->ops, .y = &y->ops, .o = o, .k0 = k, .nd = nd};
  double *buf = malloc((size_t)k * k * 7 * sizeof *buf);
  if (!buf) return sm_error_set(err, SM_ENOMEM, "coarse map: out of memory");
  p.AyAyT = buf;
  p.lapw = buf + k * k;
  p.E = buf + 2 * k * k;
  p.T1 = buf + 3 * k * k;
  cblas_dgemm(CblasColMajor, CblasNoTrans, CblasTrans, k, k, nd, 1.0, y->ops.A, k, y->ops.A, k,
              0.0, p.AyAyT, k);
  lap_weights(&x->ops, &y->ops, p.lapw);
  term_scales(&p);
  p.fix_first = 1;
  solve_cg(&p, C, buf + 4 * k * k, buf + 5 * k * k, buf + 6 * k * k);
  free(buf);
  return 0;
}

int sm_coarse_fmap(const sm_coarse_side *x, const sm_coarse_side *y, int nd,
                   const sm_coarse_opts *o, double *C, sm_error *err) {
  sm_coarse_prep *px = NULL, *py = NULL;
  int rc = sm_coarse_prepare(x, nd, o, &px, err);
  if (!rc) rc = sm_coarse_prepare(y, nd, o, &py, err);
  if (!rc) rc = sm_coarse_fmap_prepared(px, py, o, C, err);
  sm_coarse_prep_destroy(px);
  sm_coarse_prep_destroy(py);
  return rc;
}

double sm_map_orientation_score(const sm_mesh *X, const sm_mesh *Y, const int32_t *T) {
  double *NY = malloc((size_t)Y->nv * 3 * sizeof *NY);
  if (!NY || sm_mesh_vertex_normals(Y, NY)) {
    free(NY);
    return 0;
  }
  double score = 0, total = 0;
  for (int32_t t = 0; t < X->nf; t++) {
    const int32_t *F = X->F + 3 * (int64_t)t;
    const double *a = X->V + 3 * (int64_t)F[0], *b = X->V + 3 * (int64_t)F[1],
                 *c = X->V + 3 * (int64_t)F[2];
    double u[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]}, v[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
    double area = 0.5 * sqrt(pow(u[1] * v[2] - u[2] * v[1], 2) + pow(u[2] * v[0] - u[0] * v[2], 2) +
                             pow(u[0] * v[1] - u[1] * v[0], 2));
    total += area;
    int32_t i = T[F[0]], j = T[F[1]], k = T[F[2]];
    if (i == j || j == k || i == k) continue;
    const double *p = Y->V + 3 * (int64_t)i, *q = Y->V + 3 * (int64_t)j, *r = Y->V + 3 * (int64_t)k;
    double e1[3] = {q[0] - p[0], q[1] - p[1], q[2] - p[2]}, e2[3] = {r[0] - p[0], r[1] - p[1], r[2] - p[2]};
    double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                   e1[0] * e2[1] - e1[1] * e2[0]};
    double s = 0;
    for (int d = 0; d < 3; d++) s += n[d] * (NY[3 * i + d] + NY[3 * j + d] + NY[3 * k + d]);
    score += s > 0 ? area : s < 0 ? -area : 0;
  }
  free(NY);
  return total > 0 ? score / total : 0;
}
