#include "sm_mesh.h"

#include <stdlib.h>
#include <string.h>

void sm_limits_default(sm_limits *lim) {
  lim->max_vertices = SM_DEFAULT_MAX_VERTICES;
  lim->max_faces = SM_DEFAULT_MAX_FACES;
}

int sm_limits_check(const sm_limits *lim, int64_t nv, int64_t nf, sm_error *err) {
  sm_limits def;
  if (!lim) {
    sm_limits_default(&def);
    lim = &def;
  }
  if (nv < 0 || nf < 0)
    return sm_error_set(err, SM_ELIMIT, "negative count (%lld vertices, %lld faces)",
                        (long long)nv, (long long)nf);
  if (nv > lim->max_vertices || nv > INT32_MAX)
    return sm_error_set(err, SM_ELIMIT, "%lld vertices exceeds the limit of %lld",
                        (long long)nv, (long long)lim->max_vertices);
  if (nf > lim->max_faces || nf > INT32_MAX / 3)
    return sm_error_set(err, SM_ELIMIT, "%lld faces exceeds the limit of %lld",
                        (long long)nf, (long long)lim->max_faces);
  return SM_OK;
}

int sm_mesh_alloc(int64_t nv, int64_t nf, const sm_limits *lim, sm_mesh **out, sm_error *err) {
  int rc = sm_limits_check(lim, nv, nf, err);
  *out = NULL;
  if (rc) return rc;
  sm_mesh *m = calloc(1, sizeof *m);
  if (!m) return sm_error_set(err, SM_ENOMEM, "mesh: out of memory");
  m->nv = (int32_t)nv;
  m->nf = (int32_t)nf;
  m->n_input = (int32_t)nv;
  m->scale = 1.0;
  m->V = malloc((size_t)(nv ? nv : 1) * 3 * sizeof *m->V);
  m->F = malloc((size_t)(nf ? nf : 1) * 3 * sizeof *m->F);
  if (!m->V || !m->F) {
    sm_mesh_destroy(m);
    return sm_error_set(err, SM_ENOMEM, "mesh: out of memory for %lld vertices, %lld faces",
                        (long long)nv, (long long)nf);
  }
  *out = m;
  return SM_OK;
}

int sm_mesh_copy(const sm_mesh *m, sm_mesh **out, sm_error *err) {
  int rc = sm_mesh_alloc(m->nv, m->nf, NULL, out, err);
  if (rc) return rc;
  sm_mesh *c = *out;
  memcpy(c->V, m->V, (size_t)m->nv * 3 * sizeof *m->V);
  memcpy(c->F, m->F, (size_t)m->nf * 3 * sizeof *m->F);
  c->n_input = m->n_input;
  memcpy(c->center, m->center, sizeof c->center);
  c->scale = m->scale;
  if (m->to_input) {
    c->to_input = malloc((size_t)(m->nv ? m->nv : 1) * sizeof *c->to_input);
    if (!c->to_input) {
      sm_mesh_destroy(c);
      *out = NULL;
      return sm_error_set(err, SM_ENOMEM, "mesh copy: out of memory");
    }
    memcpy(c->to_input, m->to_input, (size_t)m->nv * sizeof *c->to_input);
  }
  return SM_OK;
}

int32_t *sm_mesh_input_to_clean(const sm_mesh *m) {
  int32_t *inv = malloc((size_t)(m->n_input > 0 ? m->n_input : 1) * sizeof *inv);
  if (!inv) return NULL;
  for (int32_t i = 0; i < m->n_input; i++) inv[i] = -1;
  for (int32_t v = 0; v < m->nv; v++) inv[m->to_input ? m->to_input[v] : v] = v;
  return inv;
}

void sm_mesh_destroy(sm_mesh *m) {
  if (!m) return;
  free(m->V);
  free(m->F);
  free(m->to_input);
  free(m);
}

/* ---- the rest of the preparation (validate, clean, normalize, mass, normals, orient,
 *      components) follows below ---- */

/* DESIGN (preparation, algorithm.md §1)
 *   validate  O(n) scan; the first offence is reported.
 *   geometry  areas, mixed-Voronoi mass and normals are single passes over the faces.
 *   clean     drops faces in the order repeated index -> zero area -> duplicate, so each
 *             dropped face is counted once, under the first reason that applies. Duplicates
 *             are found by sorting sorted index triples (O(nf log nf)), not by hashing.
 *   orient    BFS over hinges (edges with exactly two faces) groups faces into "patches";
 *             each patch gets the cheaper of its two consistent orientations, and a patch
 *             with no boundary edge is then turned outward by its signed volume. Working per
 *             patch rather than per vertex component keeps e.g. two spheres touching at a
 *             vertex both outward; a closed component consists of closed patches only, so
 *             it always ends up outward as the contract asks. */
#include <math.h>

#include "sm_topology.h"

static const char *const axis_name[3] = {"x", "y", "z"};

int sm_mesh_validate(const sm_mesh *m, sm_error *err) {
  if (m->nv <= 0 || m->nf <= 0)
    return sm_error_set(err, SM_EEMPTY, "mesh is empty (%d vertices, %d faces)", m->nv, m->nf);
  for (int64_t v = 0; v < m->nv; v++)
    for (int d = 0; d < 3; d++)
      if (!isfinite(m->V[3 * v + d]))
        return sm_error_set(err, SM_ENONFINITE, "vertex %lld has %s = %g", (long long)v,
                            axis_name[d], m->V[3 * v + d]);
  for (int64_t f = 0; f < m->nf; f++)
    for (int c = 0; c < 3; c++) {
      int32_t i = m->F[3 * f + c];
      if (i < 0 || i >= m->nv)
        return sm_error_set(err, SM_ERANGE,
                            "face %lld corner %d references vertex %d, mesh has %d vertices",
                            (long long)f, c, i, m->nv);
    }
  return SM_OK;
}

/* ---- per-face geometry ---- */

static void sub3(const double *a, const double *b, double *out) {
  out[0] = a[0] - b[0];
  out[1] = a[1] - b[1];
  out[2] = a[2] - b[2];
}

static double dot3(const double *a, const double *b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static void cross3(const double *a, const double *b, double *out) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

/* Unnormalized normal (x1 - x0) x (x2 - x0) = 2 A n of face f. */
static void face_cross(const sm_mesh *m, int64_t f, double *n) {
  const int32_t *t = m->F + 3 * f;
  double u[3], w[3];
  sub3(m->V + 3 * (int64_t)t[1], m->V + 3 * (int64_t)t[0], u);
  sub3(m->V + 3 * (int64_t)t[2], m->V + 3 * (int64_t)t[0], w);
  cross3(u, w, n);
}

static double norm3(const double *a) { return sqrt(dot3(a, a)); }

static double face_area(const sm_mesh *m, int64_t f) {
  double n[3];
  face_cross(m, f, n);
  return 0.5 * norm3(n);
}

double sm_mesh_face_areas(const sm_mesh *m, double *area) {
  double total = 0;
  for (int64_t f = 0; f < m->nf; f++) {
    double a = face_area(m, f);
    if (area) area[f] = a;
    total += a;
  }
  return total;
}

/* Mixed Voronoi area of Meyer, Desbrun, Schroeder, Barr (2003), fig. 4: in a non-obtuse
 * triangle the Voronoi cell of corner i is (|e_ij|^2 cot k + |e_ik|^2 cot j) / 8, and the
 * three cells tile the triangle; in an obtuse one the Voronoi cells would leave the
 * triangle, so the area is split A/2 to the obtuse corner and A/4 to the others. cot of the
 * angle at a corner is (dot of its two edge vectors) / (2A). */
static void face_mass(const sm_mesh *m, int64_t f, double *mass) {
  const int32_t *t = m->F + 3 * f;
  const double *x[3] = {m->V + 3 * (int64_t)t[0], m->V + 3 * (int64_t)t[1],
                        m->V + 3 * (int64_t)t[2]};
  double e[3][3], len2[3], dots[3], n[3];
  for (int c = 0; c < 3; c++) { /* e[c]: edge opposite corner c */
    sub3(x[(c + 2) % 3], x[(c + 1) % 3], e[c]);
    len2[c] = dot3(e[c], e[c]);
  }
  cross3(e[2], e[1], n); /* (x1 - x0) x (x0 - x2) = -(2A n): only its length matters */
  double area = 0.5 * norm3(n);
  if (!(area > 0)) return;
  for (int c = 0; c < 3; c++) /* dot of the two edges leaving corner c */
    dots[c] = -dot3(e[(c + 1) % 3], e[(c + 2) % 3]);
  for (int c = 0; c < 3; c++)
    if (dots[c] < 0) {
      for (int k = 0; k < 3; k++) mass[t[k]] += (k == c ? 0.5 : 0.25) * area;
      return;
    }
  for (int c = 0; c < 3; c++) {
    int j = (c + 1) % 3, k = (c + 2) % 3;
    /* |e_ij|^2 is the edge opposite k, |e_ik|^2 the edge opposite j */
    mass[t[c]] += (len2[k] * dots[k] + len2[j] * dots[j]) / (2 * area) / 8;
  }
}

int sm_mesh_lumped_mass(const sm_mesh *m, double *mass) {
  for (int64_t v = 0; v < m->nv; v++) mass[v] = 0;
  for (int64_t f = 0; f < m->nf; f++) face_mass(m, f, mass);
  return SM_OK;
}

/* Sum of unnormalized face normals (|cross| = 2A, so this is the area weighting). When the
 * sum cancels (|sum| <= 1e-12 of the summed magnitudes, e.g. at a fold where two sheets
 * meet back to back) the direction is noise, so the vertex takes the unit normal of its
 * largest incident face instead. A vertex with no incident face of nonzero area (possible
 * only before sm_mesh_clean) gets (0, 0, 0): there is no direction to report. */
int sm_mesh_vertex_normals(const sm_mesh *m, double *N) {
  double *wsum = calloc((size_t)(m->nv ? m->nv : 1), sizeof *wsum);
  if (!wsum) return SM_ENOMEM;
  memset(N, 0, (size_t)m->nv * 3 * sizeof *N);
  for (int64_t f = 0; f < m->nf; f++) {
    double n[3];
    face_cross(m, f, n);
    double w = norm3(n);
    for (int c = 0; c < 3; c++) {
      int64_t v = m->F[3 * f + c];
      for (int d = 0; d < 3; d++) N[3 * v + d] += n[d];
      wsum[v] += w;
    }
  }
  int64_t nfallback = 0;
  for (int64_t v = 0; v < m->nv; v++) {
    double len = norm3(N + 3 * v);
    if (wsum[v] > 0 && len > 1e-12 * wsum[v]) {
      for (int d = 0; d < 3; d++) N[3 * v + d] /= len;
      wsum[v] = -1; /* done */
    } else {
      memset(N + 3 * v, 0, 3 * sizeof *N);
      wsum[v] = 0; /* now: magnitude of the largest incident face seen so far */
      nfallback++;
    }
  }
  for (int64_t f = 0; f < m->nf && nfallback; f++) {
    double n[3];
    face_cross(m, f, n);
    double w = norm3(n);
    for (int c = 0; c < 3; c++) {
      int64_t v = m->F[3 * f + c];
      if (wsum[v] < 0 || !(w > wsum[v])) continue;
      wsum[v] = w;
      for (int d = 0; d < 3; d++) N[3 * v + d] = n[d] / w;
    }
  }
  free(wsum);
  return SM_OK;
}

/* ---- normalization ---- */

int sm_mesh_normalize(sm_mesh *m, sm_error *err) {
  double total = 0, c[3] = {0, 0, 0};
  for (int64_t f = 0; f < m->nf; f++) {
    const int32_t *t = m->F + 3 * f;
    double a = face_area(m, f);
    total += a;
    for (int d = 0; d < 3; d++)
      c[d] += a * (m->V[3 * (int64_t)t[0] + d] + m->V[3 * (int64_t)t[1] + d] +
                   m->V[3 * (int64_t)t[2] + d]) / 3;
  }
  if (!(total > 0) || !isfinite(total))
    return sm_error_set(err, SM_EEMPTY, "cannot normalize: total area is %g (%d faces)", total,
                        m->nf);
  for (int d = 0; d < 3; d++) c[d] /= total;
  double s = 1 / sqrt(total);
  for (int64_t v = 0; v < m->nv; v++)
    for (int d = 0; d < 3; d++) m->V[3 * v + d] = (m->V[3 * v + d] - c[d]) * s;
  /* V_now = (V_in - center) * scale and V_new = (V_now - c) * s give
   * V_new = (V_in - (center + c / scale)) * (scale * s). */
  for (int d = 0; d < 3; d++) m->center[d] += c[d] / m->scale;
  m->scale *= s;
  return SM_OK;
}

/* ---- connected components ---- */

/* Union-find stored in comp[] itself. Roots are always linked to the smaller root and path
 * halving only moves a parent further toward the root, so parent[v] <= v holds throughout;
 * that lets one ascending pass turn parents into labels numbered by first vertex. */
static int32_t uf_find(int32_t *p, int32_t v) {
  while (p[v] != v) {
    p[v] = p[p[v]];
    v = p[v];
  }
  return v;
}

int sm_mesh_components(const sm_mesh *m, int32_t *comp, int32_t *ncomp) {
  for (int32_t v = 0; v < m->nv; v++) comp[v] = v;
  for (int64_t f = 0; f < m->nf; f++)
    for (int c = 1; c < 3; c++) {
      int32_t a = uf_find(comp, m->F[3 * f]), b = uf_find(comp, m->F[3 * f + c]);
      if (a < b) comp[b] = a;
      else if (b < a) comp[a] = b;
    }
  int32_t n = 0;
  for (int32_t v = 0; v < m->nv; v++)
    comp[v] = comp[v] == v ? n++ : comp[comp[v]]; /* comp[p] for p < v is already a label */
  *ncomp = n;
  return SM_OK;
}

/* ---- orientation ---- */

/* Nonzero when face g traverses the edge of face f at corner c in the same direction as f,
 * i.e. when g has to be flipped relative to f for the two to agree. */
static int same_direction(const sm_mesh *m, const sm_edges *e, int64_t f, int c, int64_t g) {
  int32_t edge = e->face_edge[3 * f + c];
  for (int d = 0; d < 3; d++)
    if (e->face_edge[3 * g + d] == edge) return m->F[3 * g + d] == m->F[3 * f + c];
  return 0;
}

/* Signed volume of the cone from the patch's area centroid over the patch's faces, each
 * taken flipped when flip[f]. For a closed patch the origin does not matter; taking the
 * centroid keeps it meaningful for patches closed only up to non-manifold edges (e.g. a
 * hemisphere cut off by an internal membrane) and reduces cancellation far from 0. */
static double patch_volume(const sm_mesh *m, const int32_t *faces, int64_t n,
                           const int8_t *flip) {
  double o[3] = {0, 0, 0}, wsum = 0, vol = 0;
  for (int64_t i = 0; i < n; i++) {
    const int32_t *t = m->F + 3 * (int64_t)faces[i];
    double a = face_area(m, faces[i]);
    wsum += a;
    for (int d = 0; d < 3; d++)
      o[d] += a * (m->V[3 * (int64_t)t[0] + d] + m->V[3 * (int64_t)t[1] + d] +
                   m->V[3 * (int64_t)t[2] + d]) / 3;
  }
  if (!(wsum > 0)) return 0;
  for (int d = 0; d < 3; d++) o[d] /= wsum;
  for (int64_t i = 0; i < n; i++) {
    const int32_t *t = m->F + 3 * (int64_t)faces[i];
    double a[3], b[3], c[3], bc[3];
    sub3(m->V + 3 * (int64_t)t[0], o, a);
    sub3(m->V + 3 * (int64_t)t[1], o, b);
    sub3(m->V + 3 * (int64_t)t[2], o, c);
    cross3(b, c, bc);
    vol += flip[faces[i]] ? -dot3(a, bc) : dot3(a, bc);
  }
  return vol / 6;
}

typedef struct {
  int64_t n;    /* faces in the patch */
  int conflict; /* some hinge could not be made consistent: non-orientable */
  int open;     /* the patch has a boundary edge */
} patch_info;

/* BFS from `seed` through hinges, assigning flip[] relative to the seed (0) and appending
 * the patch's faces to queue[]. A hinge whose two faces traverse the edge the same way
 * needs exactly one of them flipped. */
static patch_info patch_bfs(const sm_mesh *m, const sm_edges *e, int32_t seed, int8_t *flip,
                            int32_t *queue) {
  patch_info p = {0, 0, 0};
  int64_t tail = 0;
  queue[tail++] = seed;
  flip[seed] = 0;
  for (int64_t head = 0; head < tail; head++) {
    int32_t f = queue[head];
    for (int c = 0; c < 3; c++) {
      int32_t g = e->face_adj[3 * (int64_t)f + c];
      if (e->nfaces[e->face_edge[3 * (int64_t)f + c]] == 1) p.open = 1;
      if (g < 0 || g == f) continue;
      int8_t want = (int8_t)(flip[f] ^ same_direction(m, e, f, c, g));
      if (flip[g] < 0) {
        flip[g] = want;
        queue[tail++] = g;
      } else if (flip[g] != want) {
        p.conflict = 1;
      }
    }
  }
  p.n = tail;
  return p;
}

/* Chooses the patch's final orientation: the one flipping fewer faces, except that a patch
 * without boundary (and orientable, so that "outside" means something) points outward. */
static void patch_settle(const sm_mesh *m, const int32_t *faces, patch_info p, int8_t *flip) {
  int64_t ones = 0;
  for (int64_t i = 0; i < p.n; i++) ones += flip[faces[i]];
  int invert = 2 * ones > p.n;
  if (!p.open && !p.conflict) {
    double vol = patch_volume(m, faces, p.n, flip);
    invert = vol < 0;
  }
  if (invert)
    for (int64_t i = 0; i < p.n; i++) flip[faces[i]] ^= 1;
}

/* Orientation given m's edges and vertex components (both of the current F). */
static int orient_with(sm_mesh *m, const sm_edges *e, const int32_t *comp, int32_t ncomp,
                       int32_t *flipped, int32_t *nonorientable) {
  int8_t *flip = malloc((size_t)(m->nf ? m->nf : 1) * sizeof *flip);
  int32_t *queue = malloc((size_t)(m->nf ? m->nf : 1) * sizeof *queue);
  uint8_t *bad = calloc((size_t)(ncomp ? ncomp : 1), 1);
  if (!flip || !queue || !bad) {
    free(flip);
    free(queue);
    free(bad);
    return SM_ENOMEM;
  }
  memset(flip, -1, (size_t)m->nf * sizeof *flip);
  int64_t done = 0; /* faces already placed in queue[0..done) by earlier patches */
  for (int32_t f = 0; f < m->nf; f++) {
    if (flip[f] >= 0) continue;
    patch_info p = patch_bfs(m, e, f, flip, queue + done);
    patch_settle(m, queue + done, p, flip);
    if (p.conflict) bad[comp[m->F[3 * (int64_t)f]]] = 1;
    done += p.n;
  }
  int32_t nflip = 0, nbad = 0;
  for (int64_t f = 0; f < m->nf; f++)
    if (flip[f]) { /* swapping two corners reverses the winding */
      int32_t t = m->F[3 * f + 1];
      m->F[3 * f + 1] = m->F[3 * f + 2];
      m->F[3 * f + 2] = t;
      nflip++;
    }
  for (int32_t c = 0; c < ncomp; c++) nbad += bad[c];
  if (flipped) *flipped = nflip;
  if (nonorientable) *nonorientable = nbad;
  free(flip);
  free(queue);
  free(bad);
  return SM_OK;
}

int sm_mesh_orient(sm_mesh *m, int32_t *flipped, int32_t *nonorientable, sm_error *err) {
  int rc = sm_mesh_validate(m, err);
  if (rc) return rc;
  sm_edges *e = NULL;
  int32_t *comp = malloc((size_t)m->nv * sizeof *comp), ncomp = 0;
  if (!comp) return sm_error_set(err, SM_ENOMEM, "orient: out of memory");
  rc = sm_edges_build(m, &e, err);
  if (!rc) rc = sm_mesh_components(m, comp, &ncomp);
  if (!rc) rc = orient_with(m, e, comp, ncomp, flipped, nonorientable);
  if (rc == SM_ENOMEM)
    sm_error_set(err, rc, "orient: out of memory for %d faces", m->nf);
  sm_edges_destroy(e);
  free(comp);
  return rc;
}

/* ---- cleaning ---- */

/* Squared diagonal of the bounding box of the vertices used by faces still kept. */
static double kept_bbox_diag2(const sm_mesh *m, const uint8_t *keep) {
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  int any = 0;
  for (int64_t f = 0; f < m->nf; f++) {
    if (!keep[f]) continue;
    any = 1;
    for (int c = 0; c < 3; c++)
      for (int d = 0; d < 3; d++) {
        double x = m->V[3 * (int64_t)m->F[3 * f + c] + d];
        lo[d] = x < lo[d] ? x : lo[d];
        hi[d] = x > hi[d] ? x : hi[d];
      }
  }
  if (!any) return 0;
  return (hi[0] - lo[0]) * (hi[0] - lo[0]) + (hi[1] - lo[1]) * (hi[1] - lo[1]) +
         (hi[2] - lo[2]) * (hi[2] - lo[2]);
}

/* Zero area is judged relative to the mesh's size, so that cleaning commutes with scaling:
 * a face is dropped when area <= 1e-12 * diag^2 (diag = bounding-box diagonal of the
 * vertices in use). Rounding leaves collinear or coincident corners with an area of about
 * 1e-16 diag^2, while a real triangle of a 4M-face mesh is around 1e-7 diag^2; the ones in
 * between are slivers whose cotangents would blow up the Laplacian and shell Hessian. */
#define SM_ZERO_AREA_REL 1e-12

static void drop_degenerate(const sm_mesh *m, uint8_t *keep, sm_clean_report *r) {
  for (int64_t f = 0; f < m->nf; f++) {
    const int32_t *t = m->F + 3 * f;
    keep[f] = !(t[0] == t[1] || t[1] == t[2] || t[0] == t[2]);
    r->dropped_repeated_index += !keep[f];
  }
  double tol = SM_ZERO_AREA_REL * kept_bbox_diag2(m, keep);
  for (int64_t f = 0; f < m->nf; f++)
    if (keep[f] && face_area(m, f) <= tol) {
      keep[f] = 0;
      r->dropped_zero_area++;
    }
}

typedef struct {
  int32_t v[3]; /* sorted vertex indices */
  int32_t f;
} face_key;

static int face_key_cmp(const void *pa, const void *pb) {
  const face_key *a = pa, *b = pb;
  for (int i = 0; i < 3; i++)
    if (a->v[i] != b->v[i]) return a->v[i] < b->v[i] ? -1 : 1;
  return (a->f > b->f) - (a->f < b->f);
}

/* Faces with the same vertex set as an earlier kept face (any order, either orientation)
 * are dropped: sorting the sorted triples puts each set's faces together, earliest first. */
static int drop_duplicates(const sm_mesh *m, uint8_t *keep, sm_clean_report *r) {
  int64_t n = 0;
  face_key *k = malloc((size_t)(m->nf > 0 ? m->nf : 1) * sizeof *k);
  if (!k) return SM_ENOMEM;
  for (int64_t f = 0; f < m->nf; f++) {
    if (!keep[f]) continue;
    int32_t a = m->F[3 * f], b = m->F[3 * f + 1], c = m->F[3 * f + 2], t;
    if (a > b) t = a, a = b, b = t;
    if (b > c) t = b, b = c, c = t;
    if (a > b) t = a, a = b, b = t;
    k[n] = (face_key){{a, b, c}, (int32_t)f};
    n++;
  }
  qsort(k, (size_t)n, sizeof *k, face_key_cmp);
  for (int64_t i = 1; i < n; i++)
    if (memcmp(k[i].v, k[i - 1].v, sizeof k[i].v) == 0) {
      keep[k[i].f] = 0;
      r->dropped_duplicate++;
    }
  free(k);
  return SM_OK;
}

/* Builds the output from the kept faces: used vertices renumbered in increasing input
 * order, to_input composed with in's, normalization transform carried over. */
static int compact(const sm_mesh *in, const uint8_t *keep, int64_t nf, const sm_limits *lim,
                   sm_mesh **out, sm_clean_report *r, sm_error *err) {
  int32_t *newidx = malloc((size_t)in->nv * sizeof *newidx);
  if (!newidx) return sm_error_set(err, SM_ENOMEM, "clean: out of memory");
  for (int64_t v = 0; v < in->nv; v++) newidx[v] = -1;
  for (int64_t f = 0; f < in->nf; f++)
    if (keep[f])
      for (int c = 0; c < 3; c++) newidx[in->F[3 * f + c]] = 0;
  int32_t nv = 0;
  for (int64_t v = 0; v < in->nv; v++)
    if (newidx[v] == 0) newidx[v] = nv++;
  r->dropped_unreferenced = in->nv - nv;
  int rc = sm_mesh_alloc(nv, nf, lim, out, err);
  sm_mesh *m = *out;
  if (!rc && !(m->to_input = malloc((size_t)nv * sizeof *m->to_input))) {
    sm_mesh_destroy(m);
    *out = NULL;
    rc = sm_error_set(err, SM_ENOMEM, "clean: out of memory for %d vertices", nv);
  }
  if (rc) {
    free(newidx);
    return rc;
  }
  for (int64_t v = 0; v < in->nv; v++) {
    int32_t w = newidx[v];
    if (w < 0) continue;
    memcpy(m->V + 3 * (int64_t)w, in->V + 3 * v, 3 * sizeof *m->V);
    m->to_input[w] = in->to_input ? in->to_input[v] : (int32_t)v;
  }
  int64_t g = 0;
  for (int64_t f = 0; f < in->nf; f++) {
    if (!keep[f]) continue;
    for (int c = 0; c < 3; c++) m->F[3 * g + c] = newidx[in->F[3 * f + c]];
    g++;
  }
  m->n_input = in->n_input;
  memcpy(m->center, in->center, sizeof m->center);
  m->scale = in->scale;
  free(newidx);
  return SM_OK;
}

/* Topology counts and orientation of the cleaned mesh. */
static int finish_topology(sm_mesh *m, sm_clean_report *r, sm_error *err) {
  sm_edges *e = NULL;
  int32_t *comp = malloc((size_t)m->nv * sizeof *comp), ncomp = 0;
  if (!comp) return sm_error_set(err, SM_ENOMEM, "clean: out of memory");
  int rc = sm_edges_build(m, &e, err);
  if (!rc) {
    r->boundary_edges = e->n_boundary;
    r->nonmanifold_edges = e->n_nonmanifold;
    rc = sm_mesh_components(m, comp, &ncomp);
    r->components = ncomp;
  }
  if (!rc) rc = orient_with(m, e, comp, ncomp, &r->flipped_faces, &r->nonorientable_components);
  if (rc == SM_ENOMEM) sm_error_set(err, rc, "clean: out of memory orienting %d faces", m->nf);
  sm_edges_destroy(e);
  free(comp);
  return rc;
}

int sm_mesh_clean(const sm_mesh *in, const sm_limits *lim, sm_mesh **out,
                  sm_clean_report *rep, sm_error *err) {
  sm_clean_report r;
  memset(&r, 0, sizeof r);
  *out = NULL;
  int rc = sm_mesh_validate(in, err);
  if (!rc) rc = sm_limits_check(lim, in->nv, in->nf, err);
  if (rc) return rc;
  r.input_vertices = in->nv;
  r.input_faces = in->nf;
  uint8_t *keep = malloc((size_t)in->nf);
  if (!keep) return sm_error_set(err, SM_ENOMEM, "clean: out of memory for %d faces", in->nf);
  drop_degenerate(in, keep, &r);
  if (drop_duplicates(in, keep, &r)) {
    free(keep);
    return sm_error_set(err, SM_ENOMEM, "clean: out of memory for %d faces", in->nf);
  }
  int64_t nf = (int64_t)in->nf - r.dropped_repeated_index - r.dropped_zero_area -
               r.dropped_duplicate;
  if (nf == 0) {
    free(keep);
    return sm_error_set(err, SM_EEMPTY,
                        "all %d faces are degenerate (%d with a repeated index, %d with zero "
                        "area)", in->nf, r.dropped_repeated_index, r.dropped_zero_area);
  }
  rc = compact(in, keep, nf, lim, out, &r, err);
  free(keep);
  if (!rc) rc = finish_topology(*out, &r, err);
  if (rc) {
    sm_mesh_destroy(*out);
    *out = NULL;
    return rc;
  }
  if (rep) *rep = r;
  return SM_OK;
}
