/* dist_dump: the raw material for studying shape distances offline (issue 11).
 *
 * Computing the maps is the expensive part of a distance (0.3-1 s a pair); every
 * definition of the distance itself is a cheap function of the two shapes and their maps.
 * This tool computes the maps of a list of pairs once, as the daemon's DISTANCE does
 * (sm_distance_match_opts, bases k = 100, refinement up to -k), and writes them with the
 * per-shape quantities a distance may use, so that bench/eval/dist_study.py can score
 * many definitions without matching again.
 *
 *   dist_dump --list SHAPES --out DIR [--pairs PAIRS] [--configs nn+lb,...] [-k K]
 *             [--cache DIR] [--part P/N] [--shapes-only] [--k0 K0] [--step S]
 *             [--samples N] [--init-samples] [--tag T]
 *
 * SHAPES: lines "name path". PAIRS: lines "i j" (0-based rows of SHAPES). Writes
 *   DIR/shape_NAME.bin   int32 n, nf, k_lb, k_el; double V[3n], int32 F[3nf],
 *                        double mass[n], lb evals[k_lb], float lb phi[n k_lb] (column-
 *                        major), el evals[k_el], float el phi[n k_el]   (written once)
 *   DIR/CONFIG.partP.bin records: int32 i, j, nx, ny, kC; int32 T_xy[nx], T_yx[ny];
 *                        double C[kC kC], dirichlet, orientation, confidence
 * --part P/N keeps the pairs whose row index is P mod N, so N processes share a list.
 * --k0, --step, --samples change the refinement schedule from the preset's, --init-samples
 * sets sm_match_opts.init_samples (cheaper maps for a study); --tag T names the records
 * CONFIG.T.partP.bin. Prints the medians of the pairs' start, refinement and match times.
 */
#define _POSIX_C_SOURCE 200809L
#include <cblas.h>
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "bench_util.h"
#include "sm_distance.h"
#include "sm_eigs.h"
#include "sm_match.h"
#include "sm_meshio.h"

#include "eval_configs.h"

#define K_BASIS 100
#define MAX_SHAPES 4096

static int prepare(const char *path, const char *cache, const char *name, sm_shape **out,
                   sm_error *err) {
  sm_mesh *raw = NULL;
  char lb[4096], el[4096];
  snprintf(lb, sizeof lb, "%s/%s.lb.smb", cache, name);
  snprintf(el, sizeof el, "%s/%s.el.smb", cache, name);
  int rc = sm_mesh_read_file(path, NULL, &raw, err);
  if (!rc) rc = bench_cached_shape(raw, K_BASIS, lb, el, out, NULL, err);
  sm_mesh_destroy(raw);
  return rc;
}

static void put_basis(FILE *f, const sm_basis *b) {
  fwrite(b->evals, sizeof(double), (size_t)b->k, f);
  size_t n = (size_t)b->n * b->k;
  float *tmp = malloc(n * sizeof *tmp);
  for (size_t i = 0; i < n; i++) tmp[i] = (float)b->phi[i];
  fwrite(tmp, sizeof *tmp, n, f);
  free(tmp);
}

static int write_shape(const char *dir, const char *name, const sm_shape *s) {
  char p[4096];
  snprintf(p, sizeof p, "%s/shape_%s.bin", dir, name);
  FILE *f = fopen(p, "wb");
  if (!f) return -1;
  const sm_mesh *m = s->mesh;
  int32_t hdr[4] = {m->nv, m->nf, s->lb->k, s->elastic ? s->elastic->k : 0};
  fwrite(hdr, sizeof hdr[0], 4, f);
  fwrite(m->V, sizeof(double), 3 * (size_t)m->nv, f);
  fwrite(m->F, sizeof(int32_t), 3 * (size_t)m->nf, f);
  fwrite(s->lb->mass, sizeof(double), (size_t)m->nv, f);
  put_basis(f, s->lb);
  if (s->elastic) put_basis(f, s->elastic);
  return fclose(f);
}

int main(int argc, char **argv) {
  const char *list = NULL, *pairs = NULL, *out = NULL, *cache = "dist-cache", *cfgs = "nn+lb";
  const char *tag = NULL;
  int k = 50, part = 0, nparts = 1, shapes_only = 0, k0 = 0, step = 0, samples = 0;
  int init_samples = 0;
  for (int i = 1; i < argc; i++) {
    int more = i + 1 < argc;
    if (!strcmp(argv[i], "--list") && more) list = argv[++i];
    else if (!strcmp(argv[i], "--pairs") && more) pairs = argv[++i];
    else if (!strcmp(argv[i], "--out") && more) out = argv[++i];
    else if (!strcmp(argv[i], "--cache") && more) cache = argv[++i];
    else if (!strcmp(argv[i], "--configs") && more) cfgs = argv[++i];
    else if (!strcmp(argv[i], "-k") && more) k = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--part") && more) {
      if (sscanf(argv[++i], "%d/%d", &part, &nparts) != 2 || nparts < 1) return 2;
    } else if (!strcmp(argv[i], "--shapes-only")) shapes_only = 1;
    else if (!strcmp(argv[i], "--k0") && more) k0 = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--step") && more) step = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--samples") && more) samples = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--init-samples")) init_samples = 1;
    else if (!strcmp(argv[i], "--tag") && more) tag = argv[++i];
    else return fprintf(stderr, "dist_dump: unexpected '%s'\n", argv[i]), 2;
  }
  if (!list || !out) return fprintf(stderr, "dist_dump --list SHAPES --out DIR ...\n"), 2;
  openblas_set_num_threads(1);
  mkdir(out, 0777);
  mkdir(cache, 0777);
  static char names[MAX_SHAPES][128], paths[MAX_SHAPES][1024];
  static sm_shape *shapes[MAX_SHAPES];
  int ns = 0;
  FILE *f = fopen(list, "r");
  if (!f) return perror(list), 1;
  while (ns < MAX_SHAPES && fscanf(f, "%127s %1023s", names[ns], paths[ns]) == 2) ns++;
  fclose(f);
  /* Shapes are prepared lazily: a part only loads the shapes its pairs use. */
  int npairs = 0, cap = 0, (*pl)[2] = NULL;
  if (pairs) {
    f = fopen(pairs, "r");
    if (!f) return perror(pairs), 1;
    int a, b;
    while (fscanf(f, "%d %d", &a, &b) == 2) {
      if (a < 0 || b < 0 || a >= ns || b >= ns) return fprintf(stderr, "bad pair %d %d\n", a, b), 2;
      if (npairs == cap) pl = realloc(pl, (size_t)(cap = cap ? 2 * cap : 1024) * sizeof *pl);
      pl[npairs][0] = a, pl[npairs][1] = b, npairs++;
    }
    fclose(f);
  }
  sm_error err = {0};
  for (int s = 0; s < ns; s++) {
    int used = shapes_only;
    for (int p = 0; p < npairs && !used; p++)
      used = p % nparts == part && (pl[p][0] == s || pl[p][1] == s);
    if (!used) continue;
    if (prepare(paths[s], cache, names[s], &shapes[s], &err))
      return fprintf(stderr, "dist_dump: %s: %s\n", paths[s], err.msg), 1;
    char p[4096];
    struct stat st;
    snprintf(p, sizeof p, "%s/shape_%s.bin", out, names[s]);
    if (part == 0 && stat(p, &st) != 0 && write_shape(out, names[s], shapes[s]))
      return fprintf(stderr, "dist_dump: cannot write %s\n", p), 1;
  }
  if (shapes_only) return 0;
  for (int c = 0; c < N_CONFIGS; c++) {
    char buf[512];
    snprintf(buf, sizeof buf, ",%s,", cfgs);
    char key[64];
    snprintf(key, sizeof key, ",%s,", CONFIGS[c].name);
    if (!strstr(buf, key)) continue;
    char p[4096];
    if (tag) snprintf(p, sizeof p, "%s/%s.%s.part%d.bin", out, CONFIGS[c].name, tag, part);
    else snprintf(p, sizeof p, "%s/%s.part%d.bin", out, CONFIGS[c].name, part);
    FILE *o = fopen(p, "wb");
    if (!o) return perror(p), 1;
    double t0 = sm_now();
    int nt = 0;
    double *tt = malloc(3 * (size_t)(npairs ? npairs : 1) * sizeof *tt);
    if (!tt) return fprintf(stderr, "dist_dump: out of memory\n"), 1;
    for (int q = 0; q < npairs; q++) {
      if (q % nparts != part) continue;
      const sm_shape *x = shapes[pl[q][0]], *y = shapes[pl[q][1]];
      sm_match_opts mo;
      sm_match_opts_default(&mo);
      sm_distance_match_opts(&mo);
      mo.init = CONFIGS[c].init;
      mo.basis = CONFIGS[c].basis; /* each configuration's own basis */
      mo.k1 = k;
      if (mo.k0 > k) mo.k0 = k;
      mo.sinkhorn_levels = 0; /* as the suite's distance preset */
      if (k0 > 0) mo.k0 = k0 < k ? k0 : k;
      if (step > 0) mo.step = step;
      if (samples > 0) mo.samples = samples;
      if (init_samples) mo.init_samples = 1;
      sm_match_result r = {0};
      double tq = sm_now();
      if (sm_match(x, y, &mo, &r, &err))
        return fprintf(stderr, "dist_dump: %s %s-%s: %s\n", CONFIGS[c].name, names[pl[q][0]],
                       names[pl[q][1]], err.msg), 1;
      int32_t hdr[5] = {pl[q][0], pl[q][1], r.nx, r.ny, r.kC};
      fwrite(hdr, sizeof hdr[0], 5, o);
      fwrite(r.T, sizeof(int32_t), (size_t)r.nx, o);
      fwrite(r.T_yx, sizeof(int32_t), (size_t)r.ny, o);
      fwrite(r.C, sizeof(double), (size_t)r.kC * r.kC, o);
      double tail[3] = {r.dirichlet, r.orientation, r.confidence};
      fwrite(tail, sizeof(double), 3, o);
      tt[nt] = r.t_init, tt[npairs + nt] = r.t_refine, tt[2 * npairs + nt] = sm_now() - tq;
      nt++;
      sm_match_result_free(&r);
    }
    if (fclose(o)) return perror(p), 1;
    fprintf(stderr, "dist_dump: %s part %d/%d: %.0f s; median per pair: init %.3f s, "
            "refinement %.3f s, match %.3f s\n", CONFIGS[c].name, part, nparts, sm_now() - t0,
            median(tt, nt), median(tt + npairs, nt), median(tt + 2 * npairs, nt));
    free(tt);
  }
  for (int s = 0; s < ns; s++) sm_shape_destroy(shapes[s]);
  free(pl);
  return 0;
}
