/* eval_tool: the evaluation suite's small utilities on mesh files.
 *
 *   eval_tool deform IN -o OUT.drc (--stretch F | --bulge A | --dent A | --decimate FRAC |
 *                                   --noise S) [--seed N]
 *       one deformation of sm_deform.h, written as a lossless sequential Draco file:
 *       stretch by F along the principal axis; bulge / dent of amount A (peak offset over
 *       the radius, radius 0.15 sqrt(area)) around a vertex chosen by the seed; decimation
 *       to FRAC of the vertices; normal noise of S mean edge lengths.
 *   eval_tool shapedna FILE... [-k K]
 *       the ShapeDNA baseline's signature: the first K (default 30) non-zero LB eigenvalues
 *       of the shape cleaned and scaled to unit area; one JSON line per file.
 */
#define _POSIX_C_SOURCE 200809L
#include <cblas.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "bench_util.h"
#include "sm_basis.h"
#include "sm_deform.h"
#include "sm_meshio.h"

#define REGION_RADIUS 0.15

static int fail(const char *what, const sm_error *err) {
  fprintf(stderr, "eval_tool: %s: %s\n", what, err->msg);
  return 1;
}

static int write_drc(const sm_mesh *m, const char *path, sm_error *err) {
  uint8_t *buf = NULL;
  size_t len = 0;
  int rc = sm_draco_encode(m, 0, &buf, &len, err);
  if (rc) return rc;
  FILE *f = fopen(path, "wb");
  if (!f || fwrite(buf, 1, len, f) != len) rc = sm_error_set(err, SM_EIO, "cannot write %s", path);
  if (f && fclose(f)) rc = sm_error_set(err, SM_EIO, "cannot write %s", path);
  free(buf);
  return rc;
}

static int cmd_deform(int argc, char **argv) {
  const char *in = NULL, *out = NULL, *kind = NULL;
  double amount = 0;
  uint64_t seed = 1;
  for (int i = 0; i < argc; i++) {
    int more = i + 1 < argc;
    if (!strcmp(argv[i], "-o") && more) out = argv[++i];
    else if (!strcmp(argv[i], "--seed") && more) seed = strtoull(argv[++i], NULL, 10);
    else if (argv[i][0] == '-' && argv[i][1] == '-' && more) kind = argv[i] + 2, amount = atof(argv[++i]);
    else if (!in) in = argv[i];
    else return fprintf(stderr, "eval_tool deform: unexpected '%s'\n", argv[i]), 2;
  }
  if (!in || !out || !kind) return fprintf(stderr, "eval_tool deform: IN -o OUT --KIND X\n"), 2;
  sm_error err = {0};
  sm_mesh *raw = NULL, *m = NULL, *d = NULL;
  int rc = sm_mesh_read_file(in, NULL, &raw, &err);
  if (!rc) rc = sm_mesh_clean(raw, NULL, &m, NULL, &err);
  if (rc) return sm_mesh_destroy(raw), fail(in, &err);
  uint64_t s = seed;
  int32_t center = (int32_t)(splitmix64(&s) % (uint64_t)m->nv);
  if (!strcmp(kind, "stretch")) rc = sm_deform_stretch(m, SM_AXIS_PRINCIPAL, amount, &d, &err);
  else if (!strcmp(kind, "bulge")) rc = sm_deform_region(m, center, REGION_RADIUS, amount, &d, &err);
  else if (!strcmp(kind, "dent")) rc = sm_deform_region(m, center, REGION_RADIUS, -amount, &d, &err);
  else if (!strcmp(kind, "noise")) rc = sm_deform_noise(m, amount, seed, &d, &err);
  else if (!strcmp(kind, "decimate"))
    rc = sm_mesh_decimate(m, (int32_t)(amount * m->nv + 0.5), &d, &err);
  else rc = sm_error_set(&err, SM_EINVAL, "unknown deformation --%s", kind);
  if (!rc) rc = write_drc(d, out, &err);
  sm_mesh_destroy(raw), sm_mesh_destroy(m), sm_mesh_destroy(d);
  return rc ? fail(in, &err) : 0;
}

static int shapedna_one(const char *path, int k, sm_error *err) {
  sm_mesh *raw = NULL, *m = NULL;
  sm_basis *b = NULL;
  int rc = sm_mesh_read_file(path, NULL, &raw, err);
  if (!rc) rc = sm_mesh_clean(raw, NULL, &m, NULL, err);
  if (!rc) rc = sm_mesh_normalize(m, err); /* unit area */
  sm_basis_opts bo;
  sm_basis_opts_default(&bo, SM_BASIS_LB, k + 1);
  if (!rc) rc = sm_basis_compute(m, &bo, &b, err);
  if (!rc) {
    printf("{\"file\": ");
    jstr(stdout, path);
    printf(", \"eig\": [");
    /* Skip the zero eigenvalue of each component (one here: closed, connected meshes). */
    int skip = b->n_components > 0 ? b->n_components : 1;
    for (int i = skip; i < b->k && i < skip + k; i++)
      printf("%s%.10g", i > skip ? ", " : "", b->evals[i]);
    printf("]}\n");
  }
  sm_basis_destroy(b), sm_mesh_destroy(m), sm_mesh_destroy(raw);
  return rc;
}

static int cmd_shapedna(int argc, char **argv) {
  int k = 30, failed = 0;
  for (int i = 0; i < argc; i++) {
    if (!strcmp(argv[i], "-k") && i + 1 < argc) {
      k = atoi(argv[++i]);
      continue;
    }
    sm_error err = {0};
    if (shapedna_one(argv[i], k, &err)) failed = fail(argv[i], &err);
  }
  return failed;
}

int main(int argc, char **argv) {
  openblas_set_num_threads(1);
  if (argc >= 2 && !strcmp(argv[1], "deform")) return cmd_deform(argc - 2, argv + 2);
  if (argc >= 2 && !strcmp(argv[1], "shapedna")) return cmd_shapedna(argc - 2, argv + 2);
  fprintf(stderr, "usage: eval_tool deform IN -o OUT.drc --stretch|--bulge|--dent|--decimate|"
                  "--noise X [--seed N]\n       eval_tool shapedna FILE... [-k K]\n");
  return 2;
}
