/* sm_fuzz_mesh: the path every decoded or parsed mesh takes in the daemon after its
 * reader (validation, cleaning, normalization), with the properties sm_mesh.h promises,
 * for the mesh harnesses (fuzz_draco_mesh, fuzz_meshio).
 *
 * Limits are small (FUZZ_MAX_VERTICES/FACES) so that a header claiming millions of
 * vertices is refused before allocation (the property under test) rather than costing a
 * fuzzer iteration hundreds of megabytes.
 */
#ifndef SM_FUZZ_MESH_H
#define SM_FUZZ_MESH_H

#include <math.h>

#include "sm_fuzz.h"
#include "sm_mesh.h"

#define FUZZ_MAX_VERTICES 100000
#define FUZZ_MAX_FACES 200000

static inline sm_limits sm_fuzz_limits(void) {
  sm_limits lim = {FUZZ_MAX_VERTICES, FUZZ_MAX_FACES};
  return lim;
}

/* A reader's result: code and message agree; a mesh only on success, within the limits. */
static inline void sm_fuzz_check_read(int rc, const sm_mesh *m, const sm_error *err) {
  SM_FUZZ_CHECK(rc <= 0);
  if (rc) {
    SM_FUZZ_CHECK(m == NULL && err->code == rc && err->msg[0] != 0);
    return;
  }
  SM_FUZZ_CHECK(m != NULL && m->nv >= 0 && m->nf >= 0);
  SM_FUZZ_CHECK(m->nv <= FUZZ_MAX_VERTICES && m->nf <= FUZZ_MAX_FACES);
  SM_FUZZ_CHECK(m->to_input == NULL && m->n_input == m->nv);
}

/* Validation, then cleaning, then normalization, checking what each promises. */
static inline void sm_fuzz_prepare_mesh(const sm_mesh *m) {
  sm_error err;
  sm_limits lim = sm_fuzz_limits();
  int rc = sm_mesh_validate(m, &err);
  if (rc) return;
  sm_mesh *c = NULL;
  sm_clean_report rep;
  rc = sm_mesh_clean(m, &lim, &c, &rep, &err);
  SM_FUZZ_CHECK(rc <= 0 && (rc == 0) == (c != NULL));
  if (rc) return;
  SM_FUZZ_CHECK(sm_mesh_validate(c, &err) == 0); /* what cleaning returns is valid */
  SM_FUZZ_CHECK(c->nv > 0 && c->nf > 0 && c->nv <= m->nv && c->nf <= m->nf);
  SM_FUZZ_CHECK(c->n_input == m->nv);
  for (int32_t v = 0; v < c->nv; v++) {
    int32_t i = c->to_input ? c->to_input[v] : v;
    SM_FUZZ_CHECK(i >= 0 && i < m->nv);
    for (int d = 0; d < 3; d++) SM_FUZZ_CHECK(c->V[3 * v + d] == m->V[3 * i + d]);
  }
  for (int64_t f = 0; f < c->nf; f++) { /* no repeated-index face survives */
    const int32_t *t = c->F + 3 * f;
    SM_FUZZ_CHECK(t[0] != t[1] && t[1] != t[2] && t[0] != t[2]);
  }
  int32_t *inv = sm_mesh_input_to_clean(c);
  SM_FUZZ_CHECK(inv != NULL);
  for (int32_t v = 0; v < c->nv; v++) SM_FUZZ_CHECK(inv[c->to_input ? c->to_input[v] : v] == v);
  free(inv);
  if (sm_mesh_normalize(c, &err) == 0) {
    SM_FUZZ_CHECK(isfinite(c->scale) && c->scale > 0);
    for (int64_t i = 0; i < 3 * (int64_t)c->nv; i++) SM_FUZZ_CHECK(isfinite(c->V[i]));
  }
  sm_mesh_destroy(c);
}

#endif
