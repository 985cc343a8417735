/* sm_topology: undirected edges, face adjacency and bending hinges of an sm_mesh.
 *
 * Contract
 *   sm_edges_build reads the mesh (not kept) and returns a new sm_edges owned by the
 *   caller (sm_edges_destroy). Pure function of F; thread-safe on distinct outputs.
 *   A hinge is an edge with exactly two incident faces; edges with one face are boundary,
 *   with more than two non-manifold (no hinge, no adjacency: they get no bending term).
 */
#ifndef SM_TOPOLOGY_H
#define SM_TOPOLOGY_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_mesh.h"

typedef struct sm_edges {
  int32_t ne;
  int32_t *ev;        /* 2*ne: endpoints, ev[2e] < ev[2e+1] */
  int32_t *nfaces;    /* ne: number of incident faces */
  int32_t *face_edge; /* 3*nf: edge of face f from corner c to corner (c+1)%3 */
  int32_t *face_adj;  /* 3*nf: the other face across that edge if it is a hinge, else -1 */
  int32_t nhinge;
  /* 4*nhinge: (i, j, k, l). (i, j, k) are the corners of the first face in its stored
   * cyclic order, so (x_j - x_i) x (x_k - x_i) is that face's normal; l is the vertex of
   * the second face opposite the edge. */
  int32_t *hinge;
  int32_t *hinge_face; /* 2*nhinge: first and second face */
  int32_t n_boundary, n_nonmanifold;
} sm_edges;

int sm_edges_build(const sm_mesh *m, sm_edges **out, sm_error *err);
void sm_edges_destroy(sm_edges *e);

#endif
