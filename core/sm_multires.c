#include "sm_multires.h"

#include <cblas.h>
#include <float.h>
#include <lapacke.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "sm_confidence.h"
#include "sm_deform.h"
#include "sm_eigs.h"
#include "sm_fmap.h"
#include "sm_knn.h"
#include "sm_metrics.h"

void sm_multires_opts_default(sm_multires_opts *o) {
  memset(o, 0, sizeof *o);
  o->mode = SM_MULTIRES_AUTO;
  o->threshold = SM_MULTIRES_THRESHOLD;
  o->coarse_nv = SM_MULTIRES_COARSE_NV;
  o->ring = SM_MULTIRES_RING;
  o->fine_iters = SM_MULTIRES_FINE_ITERS;
  o->max_aspect = SM_MULTIRES_MAX_ASPECT;
  o->coarse_tips = SM_MULTIRES_COARSE_TIPS;
  o->snap_iters = SM_MULTIRES_SNAP_ITERS;
}

int sm_multires_wanted(const sm_multires_opts *o, int32_t nv_x, int32_t nv_y) {
  if (o->mode == SM_MULTIRES_ON) return 1;
  if (o->mode == SM_MULTIRES_OFF) return 0;
  return (nv_x > nv_y ? nv_x : nv_y) > o->threshold;
}

static int check_mopts(const sm_multires_opts *o, sm_error *err) {
  if (o->mode < SM_MULTIRES_AUTO || o->mode > SM_MULTIRES_OFF || o->coarse_nv < 200 ||
      o->ring < 1 || o->threshold < 0 || o->fine_iters < 0 || o->snap_iters < 0 ||
      !(o->max_aspect >= 1.5) || !isfinite(o->max_aspect) ||
      (o->coarse_tips != 0 && o->coarse_tips != 1))
    return sm_error_set(err, SM_EINVAL, "multires: mode %d, coarse_nv %d (>= 200), ring %d "
                        "(>= 1), threshold %d (>= 0), fine_iters %d (>= 0), snap_iters %d "
                        "(>= 0), max_aspect %g (>= 1.5), coarse_tips %d (0 or 1) invalid",
                        o->mode, o->coarse_nv, o->ring, o->threshold, o->fine_iters,
                        o->snap_iters, o->max_aspect, o->coarse_tips);
  return SM_OK;
}

/* ---- canonical order ------------------------------------------------------------------ */

typedef struct vkey { double p[3]; int32_t v; } vkey;
typedef struct fkey { int32_t a, b, c; } fkey;

static int cmp_vkey(const void *pa, const void *pb) {
  const vkey *a = pa, *b = pb;
  for (int d = 0; d < 3; d++)
    if (a->p[d] != b->p[d]) return a->p[d] < b->p[d] ? -1 : 1;
  return (a->v > b->v) - (a->v < b->v);
}

static int cmp_fkey(const void *pa, const void *pb) {
  const fkey *a = pa, *b = pb;
  if (a->a != b->a) return a->a < b->a ? -1 : 1;
  if (a->b != b->b) return a->b < b->b ? -1 : 1;
  return (a->c > b->c) - (a->c < b->c);
}

/* A copy of m with vertices sorted by coordinates and faces by their (rotated, orientation
 * kept) vertex triples: what the decimater sees no longer depends on the file's order
 * (only vertices at identical positions keep their relative input order). */
/* Components with fewer than this share of the vertices (scan debris: the dragon has six of
 * 3-7 vertices beside its 100,179) are left out of the coarse proxy: decimated to a
 * triangle or two they have no spectrum, and their degenerate elastic kernel failed the
 * coarse basis. Their fine vertices are located on the nearest kept surface. */
#define SM_MULTIRES_MIN_COMPONENT 0.01

static int canonical_copy(const sm_mesh *m, sm_mesh **out, int32_t *dropped, sm_error *err) {
  vkey *vk = malloc((size_t)m->nv * sizeof *vk);
  int32_t *rank = malloc((size_t)m->nv * sizeof *rank), ncomp = 0;
  int32_t *comp = malloc((size_t)m->nv * sizeof *comp), *size = NULL;
  fkey *fk = malloc((size_t)m->nf * sizeof *fk);
  int rc = (!vk || !rank || !fk || !comp) ? SM_ENOMEM : sm_mesh_components(m, comp, &ncomp);
  if (!rc && !(size = calloc((size_t)ncomp, sizeof *size))) rc = SM_ENOMEM;
  if (rc) rc = sm_error_set(err, SM_ENOMEM, "multires: out of memory");
  int32_t nv = 0, nf = 0, big = 0;
  if (!rc) {
    for (int32_t v = 0; v < m->nv; v++) size[comp[v]]++;
    for (int32_t c = 0; c < ncomp; c++) big = size[c] > size[big] ? c : big;
    for (int32_t v = 0; v < m->nv; v++) {
      if (comp[v] != big && size[comp[v]] < SM_MULTIRES_MIN_COMPONENT * m->nv) continue;
      memcpy(vk[nv].p, m->V + 3 * (size_t)v, sizeof vk[nv].p);
      vk[nv++].v = v;
    }
    *dropped = m->nv - nv;
    qsort(vk, (size_t)nv, sizeof *vk, cmp_vkey);
    for (int32_t v = 0; v < m->nv; v++) rank[v] = -1;
    for (int32_t r = 0; r < nv; r++) rank[vk[r].v] = r;
    for (int32_t f = 0; f < m->nf; f++) {
      int32_t t[3];
      for (int c = 0; c < 3; c++) t[c] = rank[m->F[3 * (size_t)f + c]];
      if (t[0] < 0) continue; /* a dropped component's face */
      int s = t[0] < t[1] ? (t[0] < t[2] ? 0 : 2) : (t[1] < t[2] ? 1 : 2);
      fk[nf++] = (fkey){t[s], t[(s + 1) % 3], t[(s + 2) % 3]};
    }
    qsort(fk, (size_t)nf, sizeof *fk, cmp_fkey);
    rc = sm_mesh_alloc(nv, nf, NULL, out, err);
  }
  if (!rc) {
    for (int32_t r = 0; r < nv; r++) memcpy((*out)->V + 3 * (size_t)r, vk[r].p, sizeof vk[r].p);
    for (int32_t f = 0; f < nf; f++) {
      (*out)->F[3 * (size_t)f] = fk[f].a;
      (*out)->F[3 * (size_t)f + 1] = fk[f].b;
      (*out)->F[3 * (size_t)f + 2] = fk[f].c;
    }
  }
  free(vk);
  free(rank);
  free(fk);
  free(comp);
  free(size);
  return rc;
}

/* ---- locating fine vertices on the coarse surface -------------------------------------- */

static double dot3(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/* Closest point of triangle abc to p by the Voronoi regions of its vertices, edges and
 * interior (the region tests of Ericson, Real-Time Collision Detection, 5.1.5); w gets its
 * barycentric weights, the squared distance is returned. A p equal to a corner gets that
 * corner's weight exactly 1. */
static double closest_on_triangle(const double *p, const double *a, const double *b,
                                  const double *c, double w[3]) {
  double ab[3], ac[3], ap[3], bp[3], cp[3];
  for (int d = 0; d < 3; d++) {
    ab[d] = b[d] - a[d];
    ac[d] = c[d] - a[d];
    ap[d] = p[d] - a[d];
    bp[d] = p[d] - b[d];
    cp[d] = p[d] - c[d];
  }
  double d1 = dot3(ab, ap), d2 = dot3(ac, ap), d3 = dot3(ab, bp), d4 = dot3(ac, bp);
  double d5 = dot3(ab, cp), d6 = dot3(ac, cp);
  double vc = d1 * d4 - d3 * d2, vb = d5 * d2 - d1 * d6, va = d3 * d6 - d5 * d4;
  if (d1 <= 0 && d2 <= 0) {
    w[0] = 1, w[1] = 0, w[2] = 0;
  } else if (d3 >= 0 && d4 <= d3) {
    w[0] = 0, w[1] = 1, w[2] = 0;
  } else if (d6 >= 0 && d5 <= d6) {
    w[0] = 0, w[1] = 0, w[2] = 1;
  } else if (vc <= 0 && d1 >= 0 && d3 <= 0) {
    double v = d1 / (d1 - d3);
    w[0] = 1 - v, w[1] = v, w[2] = 0;
  } else if (vb <= 0 && d2 >= 0 && d6 <= 0) {
    double v = d2 / (d2 - d6);
    w[0] = 1 - v, w[1] = 0, w[2] = v;
  } else if (va <= 0 && d4 - d3 >= 0 && d5 - d6 >= 0) {
    double v = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    w[0] = 0, w[1] = 1 - v, w[2] = v;
  } else {
    double s = va + vb + vc;
    if (!(s > 0)) { /* degenerate triangle: its nearest corner */
      double da = dot3(ap, ap), db = dot3(bp, bp), dc = dot3(cp, cp);
      w[0] = da <= db && da <= dc, w[1] = !w[0] && db <= dc, w[2] = !w[0] && !w[1];
    } else {
      w[1] = vb / s, w[2] = vc / s, w[0] = 1 - w[1] - w[2];
    }
  }
  double r2 = 0;
  for (int d = 0; d < 3; d++) {
    double q = w[0] * a[d] + w[1] * b[d] + w[2] * c[d] - p[d];
    r2 += q * q;
  }
  return r2;
}

/* CSR of the faces around each vertex. */
static int vertex_faces(const sm_mesh *m, int32_t **ptr, int32_t **idx) {
  *ptr = calloc((size_t)m->nv + 1, sizeof **ptr);
  *idx = malloc((size_t)3 * m->nf * sizeof **idx);
  if (!*ptr || !*idx) return SM_ENOMEM;
  for (int64_t i = 0; i < 3 * (int64_t)m->nf; i++) (*ptr)[m->F[i] + 1]++;
  for (int32_t v = 0; v < m->nv; v++) (*ptr)[v + 1] += (*ptr)[v];
  int32_t *fill = malloc((size_t)m->nv * sizeof *fill);
  if (!fill) return SM_ENOMEM;
  memcpy(fill, *ptr, (size_t)m->nv * sizeof *fill);
  for (int64_t i = 0; i < 3 * (int64_t)m->nf; i++) (*idx)[fill[m->F[i]]++] = (int32_t)(i / 3);
  free(fill);
  return SM_OK;
}

/* The decimated proxy made fit for the elastic basis: a vertex where several fans of faces
 * meet only at that vertex (a hinge: OpenMesh's lenient build leaves them where it refused
 * faces) gets one copy per fan, since a hinge adds rotational zero modes the basis cannot
 * tell from the rigid kernel (the dragon's proxy failed so); then components under
 * SM_MULTIRES_MIN_COMPONENT of the vertices are dropped, as before decimation. Vertex and
 * face order are kept, so the result is as order-independent as its input. */
static int find_root(int32_t *p, int32_t a) {
  while (p[a] != a) a = p[a] = p[p[a]];
  return a;
}

static int proxy_fix(const sm_mesh *m, sm_mesh **out, sm_error *err) {
  int32_t nv = m->nv, nf = m->nf, *vc_ptr = NULL, *vc = NULL;
  int64_t n3 = 3 * (int64_t)nf;
  int32_t *uf = malloc((size_t)n3 * sizeof *uf), *cid = malloc((size_t)n3 * sizeof *cid);
  int32_t *comp = NULL, *size = NULL, *newv = NULL, *keepv = NULL;
  int rc = (!uf || !cid || vertex_faces(m, &vc_ptr, &vc)) ? SM_ENOMEM : SM_OK;
  int32_t nn = 0;
  if (!rc) {
    /* Corners (3f + c) of a vertex are one fan when their faces share an edge at it. */
    for (int64_t i = 0; i < n3; i++) uf[i] = (int32_t)i;
    for (int32_t v = 0; v < nv; v++)
      for (int32_t a = vc_ptr[v]; a < vc_ptr[v + 1]; a++)
        for (int32_t b = a + 1; b < vc_ptr[v + 1]; b++) {
          const int32_t *fa = m->F + 3 * (size_t)vc[a], *fb = m->F + 3 * (size_t)vc[b];
          int shared = 0, ca = 0, cb = 0;
          for (int i = 0; i < 3; i++) {
            if (fa[i] == v) ca = i;
            if (fb[i] == v) cb = i;
            for (int j = 0; j < 3; j++) shared += fa[i] != v && fa[i] == fb[j];
          }
          if (shared) {
            int32_t ra = find_root(uf, 3 * vc[a] + ca), rb = find_root(uf, 3 * vc[b] + cb);
            if (ra != rb) uf[ra > rb ? ra : rb] = ra < rb ? ra : rb;
          }
        }
    /* New vertex per fan root, in vertex order then fan order. */
    for (int64_t i = 0; i < n3; i++) cid[i] = -1;
    for (int32_t v = 0; v < nv; v++)
      for (int32_t a = vc_ptr[v]; a < vc_ptr[v + 1]; a++) {
        const int32_t *fa = m->F + 3 * (size_t)vc[a];
        int c = fa[0] == v ? 0 : fa[1] == v ? 1 : 2;
        int32_t r = find_root(uf, 3 * vc[a] + c);
        if (cid[r] < 0) cid[r] = nn++;
      }
    comp = malloc((size_t)nn * sizeof *comp);
    newv = malloc((size_t)nn * sizeof *newv);
    keepv = malloc((size_t)nn * sizeof *keepv);
    if (!comp || !newv || !keepv) rc = SM_ENOMEM;
  }
  sm_mesh *split = NULL;
  if (!rc) rc = sm_mesh_alloc(nn, nf, NULL, &split, err);
  if (!rc) {
    for (int64_t i = 0; i < n3; i++) {
      int32_t r = cid[find_root(uf, (int32_t)i)];
      split->F[i] = r;
      memcpy(split->V + 3 * (size_t)r, m->V + 3 * (size_t)m->F[i], 3 * sizeof *split->V);
    }
    int32_t ncomp = 0, big = 0;
    rc = sm_mesh_components(split, comp, &ncomp);
    if (!rc && !(size = calloc((size_t)ncomp, sizeof *size))) rc = SM_ENOMEM;
    int32_t kv = 0, kf = 0;
    if (!rc) {
      for (int32_t v = 0; v < nn; v++) size[comp[v]]++;
      for (int32_t c = 0; c < ncomp; c++) big = size[c] > size[big] ? c : big;
      for (int32_t v = 0; v < nn; v++)
        keepv[v] = comp[v] == big || size[comp[v]] >= SM_MULTIRES_MIN_COMPONENT * nn;
      for (int32_t v = 0; v < nn; v++) newv[v] = keepv[v] ? kv++ : -1;
      for (int32_t f = 0; f < nf; f++) kf += keepv[split->F[3 * (size_t)f]];
      rc = sm_mesh_alloc(kv, kf, NULL, out, err);
    }
    if (!rc) {
      for (int32_t v = 0; v < nn; v++)
        if (newv[v] >= 0) memcpy((*out)->V + 3 * (size_t)newv[v], split->V + 3 * (size_t)v, 3 * sizeof *split->V);
      int32_t f2 = 0;
      for (int32_t f = 0; f < nf; f++) {
        const int32_t *t = split->F + 3 * (size_t)f;
        if (!keepv[t[0]]) continue;
        for (int c = 0; c < 3; c++) (*out)->F[3 * (size_t)f2 + c] = newv[t[c]];
        f2++;
      }
    }
  }
  if (rc == SM_ENOMEM) rc = sm_error_set(err, SM_ENOMEM, "multires: out of memory");
  sm_mesh_destroy(split);
  free(uf), free(cid), free(vc_ptr), free(vc), free(comp), free(size), free(newv), free(keepv);
  return rc;
}

#define LOCATE_K 8

int sm_multires_locate(const double *P, int32_t np, const sm_mesh *coarse, int32_t *tri,
                       double *bary, sm_error *err) {
  if (!P || np < 0 || !coarse || coarse->nv < 3 || coarse->nf < 1 || !tri || !bary)
    return sm_error_set(err, SM_EINVAL, "multires locate: bad arguments");
  int K = coarse->nv < LOCATE_K ? coarse->nv : LOCATE_K;
  int32_t *vf_ptr = NULL, *vf = NULL, *nb = malloc((size_t)np * K * sizeof *nb);
  sm_knn *ix = NULL;
  sm_knn_opts ko;
  sm_knn_opts_default(&ko);
  ko.strategy = SM_KNN_KDTREE;
  int rc = (!nb || vertex_faces(coarse, &vf_ptr, &vf))
               ? sm_error_set(err, SM_ENOMEM, "multires locate: out of memory") : SM_OK;
  if (!rc) rc = sm_knn_build(coarse->V, coarse->nv, 3, &ko, &ix, err);
  if (!rc) rc = sm_knn_query(ix, P, np, K, nb, NULL, err);
  for (int32_t i = 0; !rc && i < np; i++) {
    const double *p = P + 3 * (size_t)i;
    double best = INFINITY;
    for (int r = 0; r < K; r++) {
      int32_t v = nb[(size_t)i * K + r];
      for (int32_t q = vf_ptr[v]; q < vf_ptr[v + 1]; q++) {
        const int32_t *t = coarse->F + 3 * (size_t)vf[q];
        double w[3];
        double d2 = closest_on_triangle(p, coarse->V + 3 * (size_t)t[0],
                                        coarse->V + 3 * (size_t)t[1],
                                        coarse->V + 3 * (size_t)t[2], w);
        if (d2 < best) {
          best = d2;
          memcpy(tri + 3 * (size_t)i, t, 3 * sizeof *t);
          memcpy(bary + 3 * (size_t)i, w, sizeof w);
        }
      }
    }
    if (best == INFINITY) { /* nearest vertices without faces: cannot happen on a cleaned mesh */
      int32_t v = nb[(size_t)i * K];
      tri[3 * (size_t)i] = tri[3 * (size_t)i + 1] = tri[3 * (size_t)i + 2] = v;
      bary[3 * (size_t)i] = 1, bary[3 * (size_t)i + 1] = bary[3 * (size_t)i + 2] = 0;
    }
  }
  sm_knn_destroy(ix);
  free(nb);
  free(vf_ptr);
  free(vf);
  return rc;
}

void sm_multires_prolong(const int32_t *tri, const double *bary, int32_t nf, const double *Fc,
                         int ldc, int d, double *Ff, int ldf) {
  for (int32_t i = 0; i < nf; i++) {
    const int32_t *t = tri + 3 * (size_t)i;
    const double *w = bary + 3 * (size_t)i;
    const double *a = Fc + (size_t)t[0] * ldc, *b = Fc + (size_t)t[1] * ldc,
                 *c = Fc + (size_t)t[2] * ldc;
    double *o = Ff + (size_t)i * ldf;
    for (int j = 0; j < d; j++) o[j] = w[0] * a[j] + w[1] * b[j] + w[2] * c[j];
  }
}

/* ---- shapes ----------------------------------------------------------------------------- */

void sm_multires_shape_destroy(sm_multires_shape *s) {
  if (!s) return;
  sm_mesh_destroy(s->mesh);
  free(s->mass);
  sm_shape_destroy(s->coarse);
  free(s->tri);
  free(s->bary);
  free(s->owner);
  free(s);
}

int sm_multires_shape_prepare(const sm_mesh *input, const sm_shape_opts *so,
                              const sm_multires_opts *mo, sm_multires_shape **out,
                              sm_error *err) {
  *out = NULL;
  int rc = check_mopts(mo, err);
  if (rc) return rc;
  sm_multires_shape *s = calloc(1, sizeof *s);
  if (!s) return sm_error_set(err, SM_ENOMEM, "multires: out of memory");
  double t0 = sm_now();
  sm_mesh *canon = NULL, *dec = NULL;
  rc = sm_mesh_clean(input, NULL, &s->mesh, NULL, err);
  s->t_clean = sm_now() - t0;
  /* Decimation and location in the input's own frame: the canonical order is then
   * bit-identical for two files of one surface (normalization sums in file order). */
  if (!rc) rc = canonical_copy(s->mesh, &canon, &s->dropped_vertices, err);
  sm_mesh *raw = NULL;
  if (!rc) rc = sm_mesh_decimate_proxy(canon, mo->coarse_nv, mo->max_aspect, &raw,
                                              &s->skipped_faces, err);
  if (!rc) rc = proxy_fix(raw, &dec, err);
  sm_mesh_destroy(raw);
  sm_mesh_destroy(canon);
  double t1 = sm_now();
  s->t_decimate = t1 - t0 - s->t_clean;
  if (!rc) rc = sm_shape_prepare(dec, so, &s->coarse, err);
  double t2 = sm_now();
  s->t_coarse = t2 - t1;
  int32_t nf = s->mesh ? s->mesh->nv : 0;
  if (!rc) {
    /* The cleaned coarse mesh with dec's (unnormalized) coordinates. */
    const sm_mesh *cm = s->coarse->mesh;
    sm_mesh proxy = *cm;
    proxy.V = malloc((size_t)3 * cm->nv * sizeof *proxy.V);
    s->tri = malloc((size_t)3 * nf * sizeof *s->tri);
    s->bary = malloc((size_t)3 * nf * sizeof *s->bary);
    s->owner = malloc((size_t)nf * sizeof *s->owner);
    s->mass = malloc((size_t)nf * sizeof *s->mass);
    if (!proxy.V || !s->tri || !s->bary || !s->owner || !s->mass) {
      rc = sm_error_set(err, SM_ENOMEM, "multires: out of memory");
    } else {
      for (int32_t v = 0; v < cm->nv; v++)
        memcpy(proxy.V + 3 * (size_t)v, dec->V + 3 * (size_t)(cm->to_input ? cm->to_input[v] : v),
               3 * sizeof *proxy.V);
      rc = sm_multires_locate(s->mesh->V, nf, &proxy, s->tri, s->bary, err);
    }
    free(proxy.V);
  }
  for (int32_t i = 0; !rc && i < nf; i++) {
    const double *w = s->bary + 3 * (size_t)i;
    int t = w[0] >= w[1] ? (w[0] >= w[2] ? 0 : 2) : (w[1] >= w[2] ? 1 : 2);
    s->owner[i] = s->tri[3 * (size_t)i + t];
  }
  if (!rc) rc = sm_mesh_normalize(s->mesh, err);
  if (!rc) rc = sm_mesh_lumped_mass(s->mesh, s->mass);
  s->t_locate = sm_now() - t2;
  sm_mesh_destroy(dec);
  if (rc) {
    sm_multires_shape_destroy(s);
    return rc;
  }
  *out = s;
  return SM_OK;
}

/* ---- the fine extraction ---------------------------------------------------------------- */

/* CSR buckets: the n items with key[i] in [0, nk). */
static int buckets(const int32_t *key, int32_t n, int32_t nk, int32_t **ptr, int32_t **idx) {
  *ptr = calloc((size_t)nk + 1, sizeof **ptr);
  *idx = malloc(((size_t)n + 1) * sizeof **idx);
  int32_t *fill = malloc(((size_t)nk + 1) * sizeof *fill);
  if (!*ptr || !*idx || !fill) {
    free(fill);
    return SM_ENOMEM;
  }
  for (int32_t i = 0; i < n; i++) (*ptr)[key[i] + 1]++;
  for (int32_t k = 0; k < nk; k++) (*ptr)[k + 1] += (*ptr)[k];
  memcpy(fill, *ptr, (size_t)nk * sizeof *fill);
  for (int32_t i = 0; i < n; i++) (*idx)[fill[key[i]]++] = i;
  free(fill);
  return SM_OK;
}

/* Vertex neighbours (through edges) of m, CSR; a neighbour may repeat. */
static int vertex_neighbours(const sm_mesh *m, int32_t **ptr, int32_t **idx) {
  *ptr = calloc((size_t)m->nv + 1, sizeof **ptr);
  *idx = malloc((size_t)6 * m->nf * sizeof **idx);
  int32_t *fill = malloc(((size_t)m->nv + 1) * sizeof *fill);
  if (!*ptr || !*idx || !fill) {
    free(fill);
    return SM_ENOMEM;
  }
  for (int64_t i = 0; i < 3 * (int64_t)m->nf; i++) (*ptr)[m->F[i] + 1] += 2;
  for (int32_t v = 0; v < m->nv; v++) (*ptr)[v + 1] += (*ptr)[v];
  memcpy(fill, *ptr, (size_t)m->nv * sizeof *fill);
  for (int32_t f = 0; f < m->nf; f++)
    for (int c = 0; c < 3; c++) {
      int32_t v = m->F[3 * (size_t)f + c];
      (*idx)[fill[v]++] = m->F[3 * (size_t)f + (c + 1) % 3];
      (*idx)[fill[v]++] = m->F[3 * (size_t)f + (c + 2) % 3];
    }
  free(fill);
  return SM_OK;
}

typedef struct extract_side {
  const double *E;        /* n x k row-major fine embedding */
  int32_t n;              /* fine vertices */
  const int32_t *owner;   /* fine vertex -> coarse vertex */
  const sm_mesh *coarse;  /* the coarse mesh (for rings) */
} extract_side;

/* T[q] = the candidate c minimizing |E_q[q] - E_c[c]| (exact squared distances; ties: the
 * lowest index), candidates = the fine vertices of C whose owner lies within `ring` coarse
 * edges of Tc[owner(q)]. Distances by one GEMM per coarse query vertex, then the few
 * candidates the GEMM's rounding cannot separate from the best are compared exactly. */
static int extract(const extract_side *Q, const extract_side *C, const int32_t *Tc, int k,
                   int ring, int (*cancel)(void *), void *cancel_ud, int32_t *T,
                   sm_error *err) {
  int32_t ncq = Q->coarse->nv, ncc = C->coarse->nv;
  int32_t *qp = NULL, *qi = NULL, *cp = NULL, *ci = NULL, *np_ = NULL, *ni = NULL;
  int32_t *stamp = calloc((size_t)ncc, sizeof *stamp), *level = NULL, *cand = NULL;
  double *G = NULL, *Qb = NULL, *D = NULL, *gn = NULL;
  size_t cap = 0, qcap = 0;
  int rc = SM_OK;
  if (!stamp || buckets(Q->owner, Q->n, ncq, &qp, &qi) || buckets(C->owner, C->n, ncc, &cp, &ci) ||
      vertex_neighbours(C->coarse, &np_, &ni) || !(level = malloc((size_t)ncc * sizeof *level)))
    rc = sm_error_set(err, SM_ENOMEM, "multires extract: out of memory");
  for (int32_t a = 0; !rc && a < ncq; a++) {
    int32_t nq = qp[a + 1] - qp[a];
    if (!nq) continue;
    if ((a & 255) == 0 && cancel && cancel(cancel_ud)) {
      rc = sm_error_set(err, SM_ECANCELED, "multires extract: canceled");
      break;
    }
    /* Coarse vertices within `ring` edges of the image, and further until one of them
     * owns a fine vertex (or the image's component is exhausted). */
    int32_t nl = 0, head = 0, nc = 0;
    level[nl++] = Tc[a];
    stamp[Tc[a]] = a + 1;
    for (int r = 0;; r++) {
      if (r >= ring) {
        for (int32_t l = 0; l < nl; l++) nc += cp[level[l] + 1] - cp[level[l]];
        if (nc) break;
      }
      int32_t end = nl;
      if (head == end) break;
      for (; head < end; head++)
        for (int32_t e = np_[level[head]]; e < np_[level[head] + 1]; e++)
          if (stamp[ni[e]] != a + 1) {
            stamp[ni[e]] = a + 1;
            level[nl++] = ni[e];
          }
    }
    if (!nc) { /* no fine vertex owned in the image's component: every vertex competes */
      nl = 0;
      for (int32_t v = 0; v < ncc; v++) level[nl++] = v;
      nc = C->n;
    }
    if ((size_t)nc > cap || (size_t)nq > qcap) {
      cap = (size_t)nc > cap ? (size_t)nc * 2 : cap;
      qcap = (size_t)nq > qcap ? (size_t)nq * 2 : qcap;
      free(G), free(gn), free(cand), free(D), free(Qb);
      G = malloc(cap * k * sizeof *G);
      gn = malloc(cap * sizeof *gn);
      cand = malloc(cap * sizeof *cand);
      D = malloc(cap * qcap * sizeof *D);
      Qb = malloc(qcap * k * sizeof *Qb);
      if (!G || !gn || !cand || !D || !Qb) {
        rc = sm_error_set(err, SM_ENOMEM, "multires extract: out of memory");
        break;
      }
    }
    int32_t m = 0;
    double gmax = 0;
    for (int32_t l = 0; l < nl; l++)
      for (int32_t p = cp[level[l]]; p < cp[level[l] + 1]; p++) {
        int32_t c = ci[p];
        const double *e = C->E + (size_t)c * k;
        memcpy(G + (size_t)m * k, e, (size_t)k * sizeof *G);
        gn[m] = cblas_ddot(k, e, 1, e, 1);
        if (gn[m] > gmax) gmax = gn[m];
        cand[m++] = c;
      }
    for (int32_t j = 0; j < nq; j++)
      memcpy(Qb + (size_t)j * k, Q->E + (size_t)qi[qp[a] + j] * k, (size_t)k * sizeof *Qb);
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, nq, m, k, 1.0, Qb, k, G, k, 0.0, D, m);
    for (int32_t j = 0; j < nq; j++) {
      const double *q = Qb + (size_t)j * k, *dj = D + (size_t)j * m;
      double qn = cblas_ddot(k, q, 1, q, 1), amin = INFINITY;
      for (int32_t c = 0; c < m; c++) {
        double d = qn + gn[c] - 2 * dj[c];
        if (d < amin) amin = d;
      }
      /* Rounding of |q|^2 + |g|^2 - 2 q.g: a few k ulps of the norms. */
      double tol = 8.0 * k * DBL_EPSILON * (qn + gmax);
      double best = INFINITY;
      int32_t arg = -1;
      for (int32_t c = 0; c < m; c++) {
        if (qn + gn[c] - 2 * dj[c] > amin + 2 * tol) continue;
        double d = sm_knn_dist2(q, G + (size_t)c * k, k);
        if (d < best || (d == best && cand[c] < arg)) {
          best = d;
          arg = cand[c];
        }
      }
      T[qi[qp[a] + j]] = arg;
    }
  }
  free(qp), free(qi), free(cp), free(ci), free(np_), free(ni), free(stamp), free(level);
  free(cand), free(G), free(gn), free(D), free(Qb);
  return rc;
}

/* ---- fine-level refinement --------------------------------------------------------------- */

/* E (n x k row-major, prolonged functions) := E L^-T with L L^T = E^T diag(m) E: the
 * prolonged functions made orthonormal in the fine mass. */
static int fine_whiten(double *E, int32_t n, int k, const double *m, sm_error *err) {
  double *S = malloc((size_t)n * k * sizeof *S), *G = malloc((size_t)k * k * sizeof *G);
  if (!S || !G) {
    free(S);
    free(G);
    return sm_error_set(err, SM_ENOMEM, "multires: out of memory (%d x %d)", n, k);
  }
  for (int32_t i = 0; i < n; i++) {
    double r = sqrt(m[i]);
    for (int j = 0; j < k; j++) S[(size_t)i * k + j] = r * E[(size_t)i * k + j];
  }
  cblas_dsyrk(CblasRowMajor, CblasLower, CblasTrans, k, n, 1.0, S, k, 0.0, G, k);
  free(S);
  int rc = SM_OK;
  if (LAPACKE_dpotrf(LAPACK_ROW_MAJOR, 'L', k, G, k))
    rc = sm_error_set(err, SM_ENUMERIC, "multires: prolonged basis Gram not positive definite");
  else
    cblas_dtrsm(CblasRowMajor, CblasRight, CblasLower, CblasTrans, CblasNonUnit, n, k, 1.0, G,
                k, E, k);
  free(G);
  return rc;
}

/* Ey (ny x k) = Uy Cw^T with Cw = Ux^T diag(m) Uy[T]: the M-weighted least-squares
 * functional map of T in the fine orthonormal coordinates, applied to Y. */
static int fine_refit(const double *Ux, int32_t nx, const double *m, const double *Uy,
                      int32_t ny, int k, const int32_t *T, double *Ey, sm_error *err) {
  double *YT = malloc((size_t)nx * k * sizeof *YT), *Cw = malloc((size_t)k * k * sizeof *Cw);
  if (!YT || !Cw) {
    free(YT);
    free(Cw);
    return sm_error_set(err, SM_ENOMEM, "multires: out of memory (%d x %d)", nx, k);
  }
  for (int32_t i = 0; i < nx; i++)
    for (int j = 0; j < k; j++) YT[(size_t)i * k + j] = m[i] * Uy[(size_t)T[i] * k + j];
  cblas_dgemm(CblasRowMajor, CblasTrans, CblasNoTrans, k, k, nx, 1.0, Ux, k, YT, k, 0.0, Cw, k);
  cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, ny, k, k, 1.0, Uy, k, Cw, k, 0.0, Ey, k);
  free(YT);
  free(Cw);
  return SM_OK;
}

/* The fine refits: Exf := the prolonged X functions, orthonormal in X's fine masses; then
 * fine_iters times Eyf := the C-aligned Y embedding of the least-squares C of T, T := the
 * extraction. Eyf ends as the embedding of the last C (for the adjoint Y -> X). */
static int fine_refine(const sm_multires_shape *x, const sm_multires_shape *y,
                       const sm_basis *bx, const sm_basis *by, int k, const int32_t *Tc,
                       const sm_multires_opts *mo, const sm_match_opts *o, double *Exf,
                       double *Eyf, int32_t *T, sm_error *err) {
  int32_t nx = x->mesh->nv, ny = y->mesh->nv;
  int32_t ncx = x->coarse->mesh->nv, ncy = y->coarse->mesh->nv;
  double *Exc = malloc((size_t)ncx * k * sizeof *Exc), *Uyc = malloc((size_t)ncy * k * sizeof *Uyc);
  double *Uy = malloc((size_t)ny * k * sizeof *Uy);
  int rc = (!Exc || !Uyc || !Uy) ? sm_error_set(err, SM_ENOMEM, "multires: out of memory") : SM_OK;
  if (!rc) rc = sm_fmap_embed_x(bx, k, Exc, k, err);
  if (!rc) rc = sm_fmap_embed_x(by, k, Uyc, k, err);
  if (!rc) {
    sm_multires_prolong(x->tri, x->bary, nx, Exc, k, k, Exf, k);
    sm_multires_prolong(y->tri, y->bary, ny, Uyc, k, k, Uy, k);
    rc = fine_whiten(Exf, nx, k, x->mass, err);
  }
  if (!rc) rc = fine_whiten(Uy, ny, k, y->mass, err);
  free(Exc);
  free(Uyc);
  extract_side sx = {Exf, nx, x->owner, x->coarse->mesh}, sy = {Eyf, ny, y->owner, y->coarse->mesh};
  for (int it = 0; !rc && it < mo->fine_iters; it++) {
    rc = fine_refit(Exf, nx, x->mass, Uy, ny, k, T, Eyf, err);
    if (!rc) rc = extract(&sx, &sy, Tc, k, mo->ring, o->cancel, o->cancel_ud, T, err);
  }
  free(Uy);
  return rc;
}

/* ---- the fine snap ------------------------------------------------------------------------ */

/* sum over the fine neighbours j of i of (|y_c - y_T(j)| - lx_ij)^2, lx = X's edge lengths
 * in the neighbour order of xp/xi: how far putting i's image on c breaks the lengths of
 * i's edges. An exact map of a mesh onto a copy of itself scores 0. */
static double snap_cost(const sm_mesh *my, const int32_t *xp, const int32_t *xi,
                        const double *lx, const int32_t *T, int32_t i, int32_t c) {
  const double *pc = my->V + 3 * (size_t)c;
  double cost = 0;
  for (int32_t e = xp[i]; e < xp[i + 1]; e++) {
    double ly = sqrt(sm_knn_dist2(pc, my->V + 3 * (size_t)T[xi[e]], 3)) - lx[e];
    cost += ly * ly;
  }
  return cost;
}

/* Jacobi sweeps (each reads the previous sweep's map), so the result does not depend on
 * the vertex order; a sweep revisits only the vertices whose own image or a neighbour's
 * moved in the sweep before (the others' costs are unchanged). */
int sm_multires_snap(const sm_mesh *mx, const sm_mesh *my, int iters, int32_t *T,
                     sm_error *err) {
  if (iters <= 0) return SM_OK;
  int32_t *xp = NULL, *xi = NULL, *yp = NULL, *yi = NULL, n = mx->nv;
  int32_t *prev = malloc((size_t)n * sizeof *prev);
  uint8_t *todo = malloc((size_t)n), *moved = calloc((size_t)n, 1);
  double *lx = NULL;
  int rc = SM_OK;
  if (!prev || !todo || !moved || vertex_neighbours(mx, &xp, &xi) ||
      vertex_neighbours(my, &yp, &yi) || !(lx = malloc((size_t)xp[n] * sizeof *lx)))
    rc = sm_error_set(err, SM_ENOMEM, "multires snap: out of memory");
  for (int32_t i = 0; !rc && i < n; i++)
    for (int32_t e = xp[i]; e < xp[i + 1]; e++)
      lx[e] = sqrt(sm_knn_dist2(mx->V + 3 * (size_t)i, mx->V + 3 * (size_t)xi[e], 3));
  if (!rc) memset(todo, 1, (size_t)n);
  int64_t nmoved = 1;
  for (int it = 0; !rc && nmoved && it < iters; it++) {
    memcpy(prev, T, (size_t)n * sizeof *prev);
    nmoved = 0;
    for (int32_t i = 0; i < n; i++) {
      moved[i] = 0;
      if (!todo[i]) continue;
      int32_t t = prev[i];
      double best = snap_cost(my, xp, xi, lx, prev, i, t);
      for (int32_t e = yp[t]; e < yp[t + 1]; e++) {
        double c = snap_cost(my, xp, xi, lx, prev, i, yi[e]);
        if (c < best) best = c, T[i] = yi[e];
      }
      moved[i] = T[i] != t;
      nmoved += moved[i];
    }
    for (int32_t i = 0; i < n; i++) {
      todo[i] = moved[i];
      for (int32_t e = xp[i]; !todo[i] && e < xp[i + 1]; e++) todo[i] = moved[xi[e]];
    }
  }
  free(prev), free(todo), free(moved), free(lx), free(xp), free(xi), free(yp), free(yi);
  return rc;
}

/* ---- matching --------------------------------------------------------------------------- */

void sm_multires_result_free(sm_multires_result *r) {
  free(r->T);
  free(r->T_yx);
  sm_match_result_free(&r->coarse);
  memset(r, 0, sizeof *r);
}

/* For each coarse vertex, the fine vertex located on it with the largest weight (-1 if
 * none): how a fine initial map reaches the coarse level. */
static int32_t *coarse_representatives(const sm_multires_shape *s) {
  int32_t nc = s->coarse->mesh->nv;
  int32_t *rep = malloc((size_t)nc * sizeof *rep);
  double *w = malloc((size_t)nc * sizeof *w);
  if (!rep || !w) {
    free(rep);
    free(w);
    return NULL;
  }
  for (int32_t v = 0; v < nc; v++) rep[v] = -1, w[v] = -1;
  for (int32_t i = 0; i < s->mesh->nv; i++)
    for (int t = 0; t < 3; t++) {
      int32_t v = s->tri[3 * (size_t)i + t];
      if (s->bary[3 * (size_t)i + t] > w[v]) w[v] = s->bary[3 * (size_t)i + t], rep[v] = i;
    }
  free(w);
  return rep;
}

int sm_multires_match(const sm_multires_shape *x, const sm_multires_shape *y,
                      const sm_match_opts *o, const sm_multires_opts *mo,
                      sm_multires_result *res, sm_error *err) {
  memset(res, 0, sizeof *res);
  int rc = check_mopts(mo, err);
  if (rc) return rc;
  int32_t nx = x->mesh->nv, ny = y->mesh->nv;
  sm_match_opts co = *o;
  co.want_yx = 1;
  if (mo->coarse_tips && co.extremities == SM_EXT_WHEN_DOUBTFUL) co.extremities = SM_EXT_ALWAYS;
  int32_t *lm = NULL, *init = NULL, *rep = NULL;
  if (o->nlandmarks > 0) {
    lm = malloc((size_t)2 * o->nlandmarks * sizeof *lm);
    if (!lm) return sm_error_set(err, SM_ENOMEM, "multires: out of memory");
    for (int i = 0; !rc && i < o->nlandmarks; i++) {
      int32_t a = o->landmarks[2 * i], b = o->landmarks[2 * i + 1];
      if (a < 0 || a >= nx || b < 0 || b >= ny)
        rc = sm_error_set(err, SM_ERANGE, "landmark %d (%d, %d) out of range", i, a, b);
      else
        lm[2 * i] = x->owner[a], lm[2 * i + 1] = y->owner[b];
    }
    co.landmarks = lm;
  }
  if (!rc && o->init_map) {
    int32_t ncx = x->coarse->mesh->nv;
    init = malloc((size_t)ncx * sizeof *init);
    rep = coarse_representatives(x);
    if (!init || !rep) rc = sm_error_set(err, SM_ENOMEM, "multires: out of memory");
    for (int32_t v = 0; !rc && v < ncx; v++) {
      int32_t i = rep[v] >= 0 ? rep[v] : 0, t = o->init_map[i];
      if (t < 0 || t >= ny) rc = sm_error_set(err, SM_ERANGE, "init map entry %d out of range", i);
      else init[v] = y->owner[t];
    }
    co.init_map = init;
  }
  double t0 = sm_now();
  if (!rc) rc = sm_match(x->coarse, y->coarse, &co, &res->coarse, err);
  free(lm);
  free(init);
  free(rep);
  double t1 = sm_now();
  res->t_match = t1 - t0;
  if (rc) {
    sm_multires_result_free(res);
    return rc;
  }
  const sm_shape *cx = x->coarse, *cy = y->coarse;
  const sm_basis *bx = o->basis == SM_MATCH_LB ? cx->lb : cx->elastic;
  const sm_basis *by = o->basis == SM_MATCH_LB ? cy->lb : cy->elastic;
  int k = res->coarse.kC;
  int32_t ncx = cx->mesh->nv, ncy = cy->mesh->nv;
  double *Exc = malloc((size_t)ncx * k * sizeof *Exc), *Eyc = malloc((size_t)ncy * k * sizeof *Eyc);
  double *Exf = malloc((size_t)nx * k * sizeof *Exf), *Eyf = malloc((size_t)ny * k * sizeof *Eyf);
  res->nx = nx;
  res->ny = ny;
  res->T = malloc((size_t)nx * sizeof *res->T);
  res->T_yx = malloc((size_t)ny * sizeof *res->T_yx);
  if (!Exc || !Eyc || !Exf || !Eyf || !res->T || !res->T_yx)
    rc = sm_error_set(err, SM_ENOMEM, "multires: out of memory (%d x %d embeddings)", nx + ny, k);
  if (!rc) rc = sm_fmap_embed_x(bx, k, Exc, k, err);
  if (!rc) rc = sm_fmap_embed_y(bx, by, k, res->coarse.C, Eyc, k, err);
  if (!rc) {
    sm_multires_prolong(x->tri, x->bary, nx, Exc, k, k, Exf, k);
    sm_multires_prolong(y->tri, y->bary, ny, Eyc, k, k, Eyf, k);
  }
  free(Exc);
  free(Eyc);
  extract_side sx = {Exf, nx, x->owner, cx->mesh}, sy = {Eyf, ny, y->owner, cy->mesh};
  if (!rc) rc = extract(&sx, &sy, res->coarse.T, k, mo->ring, o->cancel, o->cancel_ud, res->T, err);
  if (!rc && mo->fine_iters > 0)
    rc = fine_refine(x, y, bx, by, k, res->coarse.T, mo, o, Exf, Eyf, res->T, err);
  if (!rc)
    rc = extract(&sy, &sx, res->coarse.T_yx, k, mo->ring, o->cancel, o->cancel_ud, res->T_yx, err);
  if (!rc) rc = sm_multires_snap(x->mesh, y->mesh, mo->snap_iters, res->T, err);
  if (!rc) rc = sm_multires_snap(y->mesh, x->mesh, mo->snap_iters, res->T_yx, err);
  free(Exf);
  free(Eyf);
  sm_confidence c;
  if (!rc) rc = sm_map_confidence(x->mesh, y->mesh, x->mass, res->T, res->T_yx, &c, err);
  if (!rc) {
    res->orientation = c.orientation;
    res->confidence = c.confidence;
    res->continuity = c.continuity;
    res->cycle = c.cycle;
    rc = sm_map_dirichlet(x->mesh, y->mesh, res->T, &res->dirichlet, err);
  }
  res->t_prolong = sm_now() - t1;
  if (rc) sm_multires_result_free(res);
  return rc;
}

void sm_multires_to_input(const sm_multires_shape *x, const sm_multires_shape *y,
                          const int32_t *T, int32_t *out) {
  const sm_mesh *mx = x->mesh, *my = y->mesh;
  for (int32_t i = 0; i < mx->n_input; i++) out[i] = -1;
  for (int32_t v = 0; v < mx->nv; v++) {
    int32_t src = mx->to_input ? mx->to_input[v] : v, dst = T[v];
    out[src] = my->to_input ? my->to_input[dst] : dst;
  }
}
