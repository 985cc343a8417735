#include "sm_topology.h"

#include <stdlib.h>

/* One half-edge per face corner, keyed by its unordered endpoint pair. Sorting the keys
 * groups the half-edges of each undirected edge together, which gives edges, adjacency and
 * hinges in one pass without a hash table. */
typedef struct {
  int64_t key;
  int32_t face;
  int32_t corner;
} halfedge;

static int halfedge_cmp(const void *a, const void *b) {
  const halfedge *x = a, *y = b;
  if (x->key != y->key) return x->key < y->key ? -1 : 1;
  return (x->face > y->face) - (x->face < y->face);
}

void sm_edges_destroy(sm_edges *e) {
  if (!e) return;
  free(e->ev);
  free(e->nfaces);
  free(e->face_edge);
  free(e->face_adj);
  free(e->hinge);
  free(e->hinge_face);
  free(e);
}

static void add_hinge(sm_edges *e, const sm_mesh *m, const halfedge *h0, const halfedge *h1) {
  const int32_t *f0 = m->F + 3 * (int64_t)h0->face, *f1 = m->F + 3 * (int64_t)h1->face;
  int32_t *h = e->hinge + 4 * (int64_t)e->nhinge;
  h[0] = f0[h0->corner];
  h[1] = f0[(h0->corner + 1) % 3];
  h[2] = f0[(h0->corner + 2) % 3];
  h[3] = f1[(h1->corner + 2) % 3];
  e->hinge_face[2 * e->nhinge] = h0->face;
  e->hinge_face[2 * e->nhinge + 1] = h1->face;
  e->face_adj[3 * (int64_t)h0->face + h0->corner] = h1->face;
  e->face_adj[3 * (int64_t)h1->face + h1->corner] = h0->face;
  e->nhinge++;
}

int sm_edges_build(const sm_mesh *m, sm_edges **out, sm_error *err) {
  int64_t nh = 3 * (int64_t)m->nf;
  halfedge *he = malloc((size_t)(nh ? nh : 1) * sizeof *he);
  sm_edges *e = calloc(1, sizeof *e);
  *out = NULL;
  if (!he || !e) goto nomem;
  for (int64_t f = 0; f < m->nf; f++)
    for (int c = 0; c < 3; c++) {
      int64_t a = m->F[3 * f + c], b = m->F[3 * f + (c + 1) % 3];
      halfedge *h = &he[3 * f + c];
      h->key = a < b ? a * m->nv + b : b * m->nv + a;
      h->face = (int32_t)f;
      h->corner = c;
    }
  qsort(he, (size_t)nh, sizeof *he, halfedge_cmp);

  /* Upper bounds: at most nh edges, at most nh/2 hinges. */
  e->ev = malloc((size_t)(nh + 1) * 2 * sizeof *e->ev);
  e->nfaces = malloc((size_t)(nh + 1) * sizeof *e->nfaces);
  e->face_edge = malloc((size_t)(nh + 1) * sizeof *e->face_edge);
  e->face_adj = malloc((size_t)(nh + 1) * sizeof *e->face_adj);
  e->hinge = malloc((size_t)(nh / 2 + 1) * 4 * sizeof *e->hinge);
  e->hinge_face = malloc((size_t)(nh / 2 + 1) * 2 * sizeof *e->hinge_face);
  if (!e->ev || !e->nfaces || !e->face_edge || !e->face_adj || !e->hinge || !e->hinge_face)
    goto nomem;
  for (int64_t i = 0; i < nh; i++) e->face_adj[i] = -1;

  for (int64_t s = 0; s < nh;) {
    int64_t t = s + 1;
    while (t < nh && he[t].key == he[s].key) t++;
    int32_t id = e->ne++;
    e->ev[2 * id] = (int32_t)(he[s].key / m->nv);
    e->ev[2 * id + 1] = (int32_t)(he[s].key % m->nv);
    e->nfaces[id] = (int32_t)(t - s);
    for (int64_t i = s; i < t; i++) e->face_edge[3 * (int64_t)he[i].face + he[i].corner] = id;
    if (t - s == 1) e->n_boundary++;
    else if (t - s == 2) add_hinge(e, m, &he[s], &he[s + 1]);
    else e->n_nonmanifold++;
    s = t;
  }
  free(he);
  *out = e;
  return SM_OK;
nomem:
  free(he);
  sm_edges_destroy(e);
  return sm_error_set(err, SM_ENOMEM, "edge topology: out of memory for %d faces", m->nf);
}
