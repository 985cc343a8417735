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
