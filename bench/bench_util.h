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

#include "sm_mesh.h"

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


#endif
