/* The program tests/install/test_install.sh builds against an installed shapematch, once
 * through find_package(shapematch) and once through pkg-config, to prove the installed
 * headers and static libraries (and their dependencies) are enough to link and run.
 *
 * Usage: sample HOST:PORT  (a running shapematchd)
 * It makes a bumpy blob with the core library, a copy whose vertices are permuted, sends
 * both to the daemon through the client library and checks that the map sends every
 * vertex to its own copy. Exit status 0 when at least 95% do, 1 otherwise. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <shapematch/sm_client.h>
#include <shapematch/sm_meshio.h>
#include <shapematch/sm_synth.h>
#include <shapematch/sm_version.h>

/* Vertex v of m becomes vertex perm[v] of *out; faces follow. */
static int permuted_copy(const sm_mesh *m, const int32_t *perm, sm_mesh **out, sm_error *err) {
  if (sm_mesh_alloc(m->nv, m->nf, NULL, out, err)) return -1;
  for (int32_t v = 0; v < m->nv; v++) memcpy((*out)->V + 3 * perm[v], m->V + 3 * v, 3 * sizeof(double));
  for (int32_t i = 0; i < 3 * m->nf; i++) (*out)->F[i] = perm[m->F[i]];
  return 0;
}

static int put_mesh(sm_client *c, const sm_mesh *m, uint8_t id[SM_PROTO_ID_LEN]) {
  uint8_t *buf = NULL;
  size_t len = 0;
  sm_error err;
  sm_client_error cerr;
  if (sm_draco_encode(m, 0, &buf, &len, &err)) {
    fprintf(stderr, "sample: draco: %s\n", err.msg);
    return -1;
  }
  int rc = sm_client_put(c, buf, len, 0, id, NULL, &cerr);
  free(buf);
  if (rc) fprintf(stderr, "sample: put: %s\n", cerr.msg);
  return rc;
}

int main(int argc, char **argv) {
  if (argc != 2) {
    fprintf(stderr, "usage: sample HOST:PORT\n");
    return 2;
  }
  const double stretch[3] = {1.0, 1.3, 0.8};
  sm_mesh *a = NULL, *b = NULL;
  sm_error err;
  if (sm_synth_blob(3, 0.35, 7, stretch, &a, &err)) {
    fprintf(stderr, "sample: blob: %s\n", err.msg);
    return 1;
  }
  int32_t *perm = malloc((size_t)a->nv * sizeof *perm);
  for (int32_t v = 0; v < a->nv; v++) perm[v] = (int32_t)(((int64_t)v * 7919 + 13) % a->nv);
  if (permuted_copy(a, perm, &b, &err)) {
    fprintf(stderr, "sample: copy: %s\n", err.msg);
    return 1;
  }
  sm_client *c = NULL;
  sm_client_error cerr;
  uint8_t ia[SM_PROTO_ID_LEN], ib[SM_PROTO_ID_LEN];
  sm_client_match_result r;
  memset(&r, 0, sizeof r);
  int rc = sm_client_connect(argv[1], NULL, &c, &cerr);
  if (rc) fprintf(stderr, "sample: connect %s: %s\n", argv[1], cerr.msg);
  if (!rc) rc = put_mesh(c, a, ia) || put_mesh(c, b, ib);
  if (!rc && (rc = sm_client_match(c, ia, ib, NULL, &r, &cerr)))
    fprintf(stderr, "sample: match: %s\n", cerr.msg);
  int32_t hits = 0;
  for (uint32_t v = 0; !rc && v < r.nx; v++) hits += r.map_xy[v] == perm[v];
  if (!rc)
    printf("sample (shapematch %s): %d of %d vertices matched to their permuted copy, "
           "confidence %.3f\n", SM_VERSION, hits, a->nv, r.confidence);
  int ok = !rc && r.nx == (uint32_t)a->nv && hits >= 0.95 * a->nv;
  sm_client_match_result_free(&r);
  sm_client_close(c);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
  free(perm);
  return ok ? 0 : 1;
}
