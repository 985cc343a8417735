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
