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
 *       of the shape cleaned and scaled to unit area; one JSON line per file. With --hks,
 *       each line also has "volume" (enclosed, at unit area) and "hksq": at each of the 13
 *       times t = 10^(-3 + j/4), j = 0..12, the area-weighted quantiles 0.05, 0.10, ..., 0.95
 *       of log h(v, t), h the heat kernel signature sum_i exp(-t lambda_i) phi_i(v)^2 over
 *       the K + 1 basis functions (the per-shape descriptor spectral_study.py compares).
 */
#define _POSIX_C_SOURCE 200809L
#include <cblas.h>
#include <math.h>
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

#define HKS_TIMES 13
#define HKS_QUANTILES 19

typedef struct wv {
  double v, w;
} wv;

static int cmp_wv(const void *a, const void *b) {
  double x = ((const wv *)a)->v, y = ((const wv *)b)->v;
  return (x > y) - (x < y);
}

/* Prints , "volume": V, "hksq": [[...] x HKS_TIMES] for a unit-area mesh and its basis. */
static int print_hks(const sm_mesh *m, const sm_basis *b) {
  double vol = 0;
  for (int32_t f = 0; f < m->nf; f++) {
    const double *p = m->V + 3 * m->F[3 * f], *q = m->V + 3 * m->F[3 * f + 1],
                 *r = m->V + 3 * m->F[3 * f + 2];
    vol += (p[0] * (q[1] * r[2] - q[2] * r[1]) - p[1] * (q[0] * r[2] - q[2] * r[0]) +
            p[2] * (q[0] * r[1] - q[1] * r[0])) / 6;
  }
  wv *h = malloc((size_t)b->n * sizeof *h);
  if (!h) return SM_ENOMEM;
  printf(", \"volume\": %.10g, \"hksq\": [", fabs(vol));
  for (int j = 0; j < HKS_TIMES; j++) {
    double t = pow(10.0, -3.0 + 0.25 * j), area = 0;
    for (int32_t v = 0; v < b->n; v++) h[v].v = 0, h[v].w = b->mass[v], area += b->mass[v];
    for (int i = 0; i < b->k; i++) {
      double e = exp(-t * fmax(b->evals[i], 0.0));
      const double *phi = b->phi + (size_t)i * b->n;
      for (int32_t v = 0; v < b->n; v++) h[v].v += e * phi[v] * phi[v];
    }
    for (int32_t v = 0; v < b->n; v++) h[v].v = log(fmax(h[v].v, 1e-300));
    qsort(h, (size_t)b->n, sizeof *h, cmp_wv);
    printf("%s[", j ? ", " : "");
    double acc = 0;
    int32_t v = 0;
    for (int q = 1; q <= HKS_QUANTILES; q++) { /* lower quantile of the area measure */
      while (v < b->n - 1 && acc + h[v].w < 0.05 * q * area) acc += h[v++].w;
      printf("%s%.8g", q > 1 ? ", " : "", h[v].v);
    }
    printf("]");
  }
  printf("]");
  free(h);
  return SM_OK;
}

static int shapedna_one(const char *path, int k, int hks, sm_error *err) {
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
    printf("]");
    if (hks && print_hks(m, b)) rc = sm_error_set(err, SM_ENOMEM, "out of memory");
    printf("}\n");
  }
  sm_basis_destroy(b), sm_mesh_destroy(m), sm_mesh_destroy(raw);
  return rc;
}

static int cmd_shapedna(int argc, char **argv) {
  int k = 30, failed = 0, hks = 0;
  for (int i = 0; i < argc; i++)
    if (!strcmp(argv[i], "--hks")) hks = 1;
  for (int i = 0; i < argc; i++) {
    if (!strcmp(argv[i], "-k") && i + 1 < argc) {
      k = atoi(argv[++i]);
      continue;
    }
    if (!strcmp(argv[i], "--hks")) continue;
    sm_error err = {0};
    if (shapedna_one(argv[i], k, hks, &err)) failed = fail(argv[i], &err);
  }
  return failed;
}

int main(int argc, char **argv) {
  openblas_set_num_threads(1);
  if (argc >= 2 && !strcmp(argv[1], "deform")) return cmd_deform(argc - 2, argv + 2);
  if (argc >= 2 && !strcmp(argv[1], "shapedna")) return cmd_shapedna(argc - 2, argv + 2);
  fprintf(stderr, "usage: eval_tool deform IN -o OUT.drc --stretch|--bulge|--dent|--decimate|"
                  "--noise X [--seed N]\n       eval_tool shapedna FILE... [-k K] [--hks]\n");
  return 2;
}
