/* bench_util: what the benchmarks and the evaluation suite share: the four real pairs
 * with ground truth, the fixed-seed permutation of the SMPL woman, medians, JSON output.
 * Header-only (static functions); no global state. Needs SM_DATA_DIR defined.
 */
#ifndef SM_BENCH_UTIL_H
#define SM_BENCH_UTIL_H

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "sm_basis.h"
#include "sm_match.h"
#include "sm_mesh.h"
#include "sm_meshio.h"
#include "sm_metrics.h"
#include "sm_prepare.h"
#include "sm_shell.h"

#define PERM_SEED 0x5eed2024u

typedef struct pair_spec {
  const char *name;
  const char *src, *tgt; /* relative to SM_DATA_DIR */
  const char *gt;        /* dense base-0 file, or NULL = identity */
  int permute_target;
} pair_spec;

static const pair_spec PAIRS[] __attribute__((unused)) = {
    {"homer", "elasticbasis_cartoon_pairs/homerA.obj", "elasticbasis_cartoon_pairs/homerB.obj",
     "elasticbasis_cartoon_pairs/gt_homerA_homerB.txt", 0},
    {"head", "elasticbasis_cartoon_pairs/headA.obj", "elasticbasis_cartoon_pairs/headB.obj",
     "elasticbasis_cartoon_pairs/gt_headA_headB.txt", 0},
    {"lion", "pyfm_cat_lion/lion-00.off", "pyfm_cat_lion/cat-00.off", "pyfm_cat_lion/lion2cat",
     0},
    {"man", "smpl_man_woman_odedstein/human_man.obj",
     "smpl_man_woman_odedstein/human_woman.obj", NULL, 1},
};
#define N_PAIRS ((int)(sizeof PAIRS / sizeof PAIRS[0]))

static inline int cmp_double(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

static inline double median(double *v, int n) {
  qsort(v, (size_t)n, sizeof *v, cmp_double);
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/* splitmix64: a fixed, platform-independent sequence, so the permuted woman is the same
 * on every machine and every run (rand() is not specified across libcs). */
static inline uint64_t splitmix64(uint64_t *s) {
  uint64_t z = (*s += 0x9e3779b97f4a7c15ull);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

/* perm[j] = old vertex placed at new position j (Fisher-Yates), inv[perm[j]] = j. */
static inline void make_permutation(int32_t n, uint64_t seed, int32_t *perm, int32_t *inv) {
  for (int32_t i = 0; i < n; i++) perm[i] = i;
  for (int32_t i = n - 1; i > 0; i--) {
    int32_t j = (int32_t)(splitmix64(&seed) % (uint64_t)(i + 1));
    int32_t t = perm[i];
    perm[i] = perm[j];
    perm[j] = t;
  }
  for (int32_t j = 0; j < n; j++) inv[perm[j]] = j;
}

/* New mesh whose vertex j is m's vertex perm[j]; faces renamed through inv so the surface
 * is unchanged. */
static inline int permute_mesh(const sm_mesh *m, const int32_t *perm, const int32_t *inv,
                        sm_mesh **out, sm_error *err) {
  int rc = sm_mesh_alloc(m->nv, m->nf, NULL, out, err);
  if (rc) return rc;
  sm_mesh *p = *out;
  for (int32_t j = 0; j < m->nv; j++) memcpy(p->V + 3 * (size_t)j, m->V + 3 * (size_t)perm[j],
                                             3 * sizeof *p->V);
  for (int64_t f = 0; f < 3 * (int64_t)m->nf; f++) {
    int32_t v = m->F[f];
    /* A raw mesh is not validated yet: keep an out-of-range index as it is, so cleaning
     * reports it instead of this loop reading outside inv. */
    p->F[f] = (v >= 0 && v < m->nv) ? inv[v] : v;
  }
  return SM_OK;
}

static inline int file_exists(const char *path) { return access(path, R_OK) == 0; }

static inline void data_path(char *buf, size_t n, const char *rel) {
  snprintf(buf, n, "%s/%s", SM_DATA_DIR, rel);
}

static inline void load_string(char *buf, size_t n) {
  FILE *f = fopen("/proc/loadavg", "r");
  buf[0] = 0;
  if (!f) return;
  if (fgets(buf, (int)n, f)) buf[strcspn(buf, "\n")] = 0;
  fclose(f);
}

/* JSON numbers cannot be NaN or inf: those become null. */
static inline void jnum(FILE *f, const char *key, double v, int comma) {
  if (isfinite(v)) fprintf(f, "\"%s\": %.9g%s", key, v, comma ? ", " : "");
  else fprintf(f, "\"%s\": null%s", key, comma ? ", " : "");
}

/* Escapes what may appear in an error message. */
static inline void jstr(FILE *f, const char *s) {
  fputc('"', f);
  for (; *s; s++) {
    if (*s == '"' || *s == '\\') fprintf(f, "\\%c", *s);
    else if ((unsigned char)*s < 0x20) fprintf(f, "\\u%04x", (unsigned char)*s);
    else fputc(*s, f);
  }
  fputc('"', f);
}


/* The meshes of a pair_spec as read (the target permuted when the spec asks) and its GT in
 * that numbering. Returns 77 when a file is absent (no ../shared/data). */
typedef struct bench_raw_pair {
  sm_mesh *rawx, *rawy;
  sm_gt *gt;
  int32_t *perm, *inv; /* the target's permutation, or NULL */
} bench_raw_pair;

static inline void bench_raw_pair_free(bench_raw_pair *p) {
  sm_mesh_destroy(p->rawx);
  sm_mesh_destroy(p->rawy);
  sm_gt_destroy(p->gt);
  free(p->perm);
  free(p->inv);
  memset(p, 0, sizeof *p);
}

static inline int bench_load_raw_pair(const pair_spec *ps, bench_raw_pair *p, sm_error *err) {
  char src[4096], tgt[4096], gtp[4096];
  memset(p, 0, sizeof *p);
  data_path(src, sizeof src, ps->src);
  data_path(tgt, sizeof tgt, ps->tgt);
  if (ps->gt) data_path(gtp, sizeof gtp, ps->gt);
  if (!file_exists(src) || !file_exists(tgt) || (ps->gt && !file_exists(gtp))) return 77;
  sm_mesh *y = NULL;
  int rc = sm_mesh_read_file(src, NULL, &p->rawx, err);
  if (!rc) rc = sm_mesh_read_file(tgt, NULL, &y, err);
  if (!rc && ps->permute_target) {
    p->perm = malloc((size_t)y->nv * sizeof *p->perm);
    p->inv = malloc((size_t)y->nv * sizeof *p->inv);
    if (!p->perm || !p->inv) rc = sm_error_set(err, SM_ENOMEM, "permutation");
    if (!rc) make_permutation(y->nv, PERM_SEED, p->perm, p->inv);
    if (!rc) rc = permute_mesh(y, p->perm, p->inv, &p->rawy, err);
    sm_mesh_destroy(y);
  } else if (!rc) {
    p->rawy = y;
  }
  if (!rc && ps->gt) rc = sm_gt_load_dense(gtp, 0, p->rawx->nv, p->rawy->nv, &p->gt, err);
  if (!rc && !ps->gt) {
    rc = sm_gt_identity(p->rawx->nv, &p->gt, err);
    if (!rc && p->perm) rc = sm_gt_remap_target(p->gt, p->inv, p->rawy->nv, err);
  }
  if (rc) bench_raw_pair_free(p);
  return rc;
}

/* sm_prepare's hooks over two cache files (one per kind): a file is used when it holds
 * the basis asked for, computed on this mesh (sm_basis_fits); what is computed is saved. */
typedef struct bench_basis_files {
  const char *path[SM_BASIS_NKINDS + 1]; /* by kind */
} bench_basis_files;

static inline int bench_files_load(void *ud, const sm_basis_spec *spec, const sm_mesh *m,
                                   sm_basis **out, sm_error *err) {
  (void)err;
  const bench_basis_files *f = ud;
  if (sm_basis_load(f->path[spec->kind], out, NULL)) return 0;
  if (sm_basis_fits(*out, spec, m, NULL) == SM_OK) return 1;
  sm_basis_destroy(*out);
  *out = NULL;
  return 0;
}

static inline void bench_files_save(void *ud, const sm_basis_spec *spec, const sm_basis *b) {
  const bench_basis_files *f = ud;
  sm_error err;
  if (b && sm_basis_save(b, f->path[spec->kind], &err))
    fprintf(stderr, "warning: cannot cache a basis: %s\n", err.msg);
}

/* raw prepared (sm_prepare) with LB and elastic bases of K functions each, taken from the
 * cache files lb_path and el_path (computed and saved there when missing or stale);
 * *all_cached (may be NULL) says whether both came from the cache. */
static inline int bench_cached_shape(const sm_mesh *raw, int K, const char *lb_path,
                                     const char *el_path, sm_shape **out, int *all_cached,
                                     sm_error *err) {
  bench_basis_files files = {{NULL, lb_path, el_path}};
  sm_prep_hooks hooks = {bench_files_load, bench_files_save, &files};
  sm_prep_opts po;
  sm_prep_opts_default(&po);
  po.nspec = sm_prep_default_specs(po.spec, K, K, SM_SHELL_DEFAULT_ETA);
  po.hooks = &hooks;
  sm_prep_info info;
  int rc = sm_prepare(raw, &po, out, &info, err);
  if (all_cached) *all_cached = !rc && info.loaded == po.nspec;
  return rc;
}

#endif
