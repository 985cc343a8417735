/* bench_match: the matching pipeline and its ablations on the four real pairs, scored
 * against ground truth with sm_metrics (the same definitions as shared/tools/eval_map.py).
 *
 * Per pair: each mesh is read once and each shape prepared ONCE (LB and elastic bases,
 * k = 100 both, WKS descriptors), because preparation is per shape and cacheable; only
 * sm_match is repeated. Every configuration runs `-r` times and reports the median of its
 * timings; maps are deterministic, so the metrics come from the first run. Maps are
 * translated to the caller's numbering (sm_match_to_input) and scored on the RAW meshes,
 * the numbering the GT files use.
 *
 * Pairs: homer (homerA -> homerB), head (headA -> headB), lion -> cat, and man -> woman
 * with the woman's vertices permuted in memory by a fixed-seed permutation (identity GT
 * is otherwise solved by index matching; data/README.md §4).
 *
 * Configurations: the default (sm_match_opts_default: sinkhorn init + elastic refinement
 * with two Sinkhorn refinement steps, one start), the default with multi-start (the nn start
 * is refined too and the lower Dirichlet energy wins),
 * then the ablation {nn, sinkhorn} x {lb, elastic} and sinkhorn + hybrid, each with ONE
 * start (multi_start = 0): with multi-start on, nn and sinkhorn rows would both report
 * whichever start won and the init column would measure nothing. All share k1 = 100.
 * "nn" rows also turn off the Sinkhorn refinement steps (sinkhorn_levels = 0).
 *
 * Usage: bench_match [-r runs] [--pairs homer,head,lion,man] [--json FILE]
 *                    [--out-maps DIR] [--blas-threads N] [--defaults]
 * "default 2 thr" is the default with sm_match_opts.threads = 2 (the CLI's: the
 * refinement's neighbour queries on two threads), the same map; --defaults runs only the
 * two default rows.
 * BLAS runs single-threaded unless --blas-threads is given: the service calls the pipeline
 * from a pool of workers, each with one BLAS thread, so that is the figure that matters.
 */
#define _POSIX_C_SOURCE 200809L /* mkdir, access */
#include <cblas.h>
#include <errno.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "sm_eigs.h"
#include "sm_alloc.h"
#include "sm_match.h"
#include "sm_meshio.h"
#include "sm_metrics.h"
#include "sm_prepare.h"
#include "bench_util.h"

#define MAX_RUNS 64
#define N_CONFIGS 8

typedef struct config {
  const char *name;
  const char *file; /* map file stem: no characters a shell would trip on */
  int init, basis;
  int multi_start;
  int threads; /* sm_match_opts.threads */
} config;

/* The default first, so the "full pipeline" line can refer to it. */
static const config CONFIGS[N_CONFIGS] = {
    {"default", "default", SM_INIT_SINKHORN, SM_MATCH_ELASTIC, 0, 1},
    {"default 2 thr", "default_2threads", SM_INIT_SINKHORN, SM_MATCH_ELASTIC, 0, 2},
    {"multi-start", "multi_start", SM_INIT_SINKHORN, SM_MATCH_ELASTIC, 1, 1},
    {"nn+lb", "nn_lb", SM_INIT_NN, SM_MATCH_LB, 0, 1},
    {"nn+elastic", "nn_elastic", SM_INIT_NN, SM_MATCH_ELASTIC, 0, 1},
    {"sinkhorn+lb", "sinkhorn_lb", SM_INIT_SINKHORN, SM_MATCH_LB, 0, 1},
    {"sinkhorn+elastic", "sinkhorn_elastic", SM_INIT_SINKHORN, SM_MATCH_ELASTIC, 0, 1},
    {"sinkhorn+hybrid", "sinkhorn_hybrid", SM_INIT_SINKHORN, SM_MATCH_HYBRID, 0, 1},
};

/* --defaults: only the two default rows (the speed figures). */
static int g_defaults_only;

typedef struct config_result {
  int ok;
  char error[256];
  int runs;
  double t_init, t_refine, t_total; /* medians, seconds */
  double orientation, init_distinct;
  int flipped;
  int init_used; /* the start whose map was kept (differs from the config's with multi-start) */
  int32_t unmapped; /* input source vertices cleaning dropped (map = -1, scored as 0) */
  sm_metrics m;
} config_result;

typedef struct pair_result {
  const pair_spec *spec;
  int ok;
  char error[256];
  int32_t nx, ny, nx_clean, ny_clean;
  double t_read;
  double prep_total[2], prep_clean[2], prep_lb[2], prep_el[2], prep_desc[2];
  config_result cfg[N_CONFIGS];
} pair_result;

static int run_config(const pair_spec *ps, const sm_shape *sx, const sm_shape *sy,
                      const sm_mesh *rawx, const sm_mesh *rawy, const sm_gt *gt,
                      const int32_t *perm, const config *c, int runs, const char *maps_dir,
                      config_result *cr) {
  sm_error err = {0};
  sm_match_opts o;
  sm_match_opts_default(&o);
  o.init = c->init;
  o.basis = c->basis;
  o.multi_start = c->multi_start;
  o.threads = c->threads;
  /* "nn" rows are the paper's baseline: no transport anywhere, so no Sinkhorn refinement
   * steps either; "sinkhorn" rows keep the default soft steps. */
  if (c->init == SM_INIT_NN) o.sinkhorn_levels = 0;
  double ti[MAX_RUNS], tr[MAX_RUNS], tt[MAX_RUNS];
  int32_t *map = NULL;
  int rc = 0;
  for (int r = 0; r < runs; r++) {
    sm_match_result res = {0};
    double t0 = sm_now();
    rc = sm_match(sx, sy, &o, &res, &err);
    tt[r] = sm_now() - t0;
    if (rc) break;
    ti[r] = res.t_init;
    tr[r] = res.t_refine;
    if (r == 0) {
      /* Score the first run only: the pipeline is deterministic, and the geodesic errors
       * would otherwise dominate the benchmark's own run time. */
      cr->orientation = res.orientation;
      cr->init_distinct = res.init_distinct;
      cr->flipped = res.flipped;
      cr->init_used = res.init_used;
      map = malloc((size_t)rawx->nv * sizeof *map);
      if (!map) {
        sm_match_result_free(&res);
        rc = sm_error_set(&err, SM_ENOMEM, "map: out of memory");
        break;
      }
      sm_match_to_input(sx, sy, res.T, map);
      /* Vertices cleaning dropped have no image; the metrics need one per source vertex.
       * Count them (0 on these closed meshes) and send them to vertex 0. */
      cr->unmapped = 0;
      for (int32_t i = 0; i < rawx->nv; i++)
        if (map[i] < 0) {
          map[i] = 0;
          cr->unmapped++;
        }
    }
    sm_match_result_free(&res);
  }
  if (!rc) rc = sm_metrics_compute(rawx, rawy, map, gt, 2, &cr->m, &err);
  if (!rc && maps_dir) {
    char path[4096];
    snprintf(path, sizeof path, "%s/%s_%s.txt", maps_dir, ps->name, c->file);
    rc = sm_map_save(path, map, rawx->nv, &err);
    if (!rc && perm) {
      /* The same map in the woman's file numbering: eval_map.py with --gt-kind identity
       * scores it without knowing our permutation (distances do not depend on names). */
      int32_t *orig = malloc((size_t)rawx->nv * sizeof *orig);
      if (!orig) {
        rc = sm_error_set(&err, SM_ENOMEM, "map: out of memory");
      } else {
        for (int32_t i = 0; i < rawx->nv; i++) orig[i] = perm[map[i]];
        snprintf(path, sizeof path, "%s/%s_%s_unpermuted.txt", maps_dir, ps->name, c->file);
        rc = sm_map_save(path, orig, rawx->nv, &err);
        free(orig);
      }
    }
  }
  free(map);
  if (rc) {
    cr->ok = 0;
    snprintf(cr->error, sizeof cr->error, "%s", err.msg);
    return rc;
  }
  cr->ok = 1;
  cr->runs = runs;
  cr->t_init = median(ti, runs);
  cr->t_refine = median(tr, runs);
  cr->t_total = median(tt, runs);
  return 0;
}

static void print_config_row(const config *c, const config_result *cr) {
  if (!cr->ok) {
    printf("  %-16s FAILED: %s\n", c->name, cr->error);
    return;
  }
  const sm_metrics *m = &cr->m;
  printf("  %-16s %-3s %6.3f %6.3f %6.3f  %7.4f %6.3f %6.3f %6.3f %7.4f %8.3f %6.3f %4d%s\n",
         c->name, cr->init_used == SM_INIT_NN ? "nn" : "sk", cr->t_init, cr->t_refine,
         cr->t_total, m->geo.mean, m->geo.frac_le_005, m->bijectivity, m->coverage, m->chamfer,
         m->dirichlet, cr->orientation, cr->flipped, cr->unmapped ? " (unmapped sources)" : "");
}

static void bench_pair(const pair_spec *ps, int runs, const char *maps_dir, pair_result *pr) {
  char src[4096], tgt[4096], gtp[4096];
  sm_error err = {0};
  sm_mesh *rawx = NULL, *rawy_file = NULL, *rawy = NULL;
  sm_shape *sx = NULL, *sy = NULL;
  sm_gt *gt = NULL;
  int32_t *perm = NULL, *inv = NULL;
  int rc = 0;
  pr->spec = ps;
  data_path(src, sizeof src, ps->src);
  data_path(tgt, sizeof tgt, ps->tgt);
  if (ps->gt) data_path(gtp, sizeof gtp, ps->gt);
  if (!file_exists(src) || !file_exists(tgt) || (ps->gt && !file_exists(gtp))) {
    printf("\n== %s: skipped (missing %s)\n", ps->name,
           !file_exists(src) ? src : !file_exists(tgt) ? tgt : gtp);
    snprintf(pr->error, sizeof pr->error, "skipped: files missing");
    return;
  }
  double t0 = sm_now();
  rc = sm_mesh_read_file(src, NULL, &rawx, &err);
  if (!rc) rc = sm_mesh_read_file(tgt, NULL, &rawy_file, &err);
  pr->t_read = sm_now() - t0;
  if (!rc && ps->permute_target) {
    perm = malloc((size_t)rawy_file->nv * sizeof *perm);
    inv = malloc((size_t)rawy_file->nv * sizeof *inv);
    if (!perm || !inv) rc = sm_error_set(&err, SM_ENOMEM, "permutation: out of memory");
    if (!rc) {
      make_permutation(rawy_file->nv, PERM_SEED, perm, inv);
      rc = permute_mesh(rawy_file, perm, inv, &rawy, &err);
    }
  } else if (!rc) {
    rawy = rawy_file;
    rawy_file = NULL;
  }
  if (!rc) {
    if (ps->gt) {
      rc = sm_gt_load_dense(gtp, 0, rawx->nv, rawy->nv, &gt, &err);
    } else {
      rc = sm_gt_identity(rawx->nv, &gt, &err);
      if (!rc && perm) rc = sm_gt_remap_target(gt, inv, rawy->nv, &err);
    }
  }
  if (rc) goto done;
  pr->nx = rawx->nv;
  pr->ny = rawy->nv;

  sm_prep_opts po; /* the shipped preparation: LB and elastic k = 100, one thread */
  sm_prep_opts_default(&po);
  const sm_mesh *raws[2] = {rawx, rawy};
  sm_shape **shapes[2] = {&sx, &sy};
  for (int s = 0; s < 2 && !rc; s++) {
    double ts = sm_now();
    rc = sm_prepare(raws[s], &po, shapes[s], NULL, &err);
    pr->prep_total[s] = sm_now() - ts;
    if (rc) break;
    const sm_shape *sh = *shapes[s];
    pr->prep_clean[s] = sh->t_clean;
    pr->prep_lb[s] = sh->t_lb;
    pr->prep_el[s] = sh->t_elastic;
    pr->prep_desc[s] = sh->t_desc;
  }
  if (rc) goto done;
  pr->nx_clean = sx->mesh->nv;
  pr->ny_clean = sy->mesh->nv;

  printf("\n== %s: %s (%d v) -> %s%s (%d v), GT %s, read %.3f s\n", ps->name, ps->src, pr->nx,
         ps->tgt, perm ? " [permuted]" : "", pr->ny, ps->gt ? ps->gt : "identity", pr->t_read);
  printf("  prepare (s)       total  clean     lb  elastic   desc\n");
  for (int s = 0; s < 2; s++)
    printf("  %-16s %6.3f %6.3f %6.3f %8.3f %6.3f\n", s ? "Y (target)" : "X (source)",
           pr->prep_total[s], pr->prep_clean[s], pr->prep_lb[s], pr->prep_el[s], pr->prep_desc[s]);
  printf("  %-16s %-3s %6s %6s %6s  %7s %6s %6s %6s %7s %8s %6s %4s\n", "config", "won", "init",
         "refine", "match", "geo", "<=.05", "bij", "cover", "chamfer", "dirichl", "orient",
         "flip");
  fflush(stdout);
  for (int c = 0; c < N_CONFIGS; c++) {
    if (g_defaults_only && c > 1) break;
    run_config(ps, sx, sy, rawx, rawy, gt, perm, &CONFIGS[c], runs, maps_dir, &pr->cfg[c]);
    print_config_row(&CONFIGS[c], &pr->cfg[c]);
    fflush(stdout);
  }
  if (pr->cfg[0].ok)
    printf("  full pipeline incl. both bases (default): %.3f s = prepare X %.3f + Y %.3f + "
           "match %.3f\n",
           pr->prep_total[0] + pr->prep_total[1] + pr->cfg[0].t_total, pr->prep_total[0],
           pr->prep_total[1], pr->cfg[0].t_total);
  if (pr->cfg[0].ok)
    printf("  GT map: dirichlet %.3f (identity on source %.3f)\n", pr->cfg[0].m.dirichlet_gt,
           pr->cfg[0].m.dirichlet_source_identity);
  pr->ok = 1;
done:
  if (rc) {
    printf("\n== %s: FAILED: %s\n", ps->name, err.msg);
    snprintf(pr->error, sizeof pr->error, "%s", err.msg);
  }
  fflush(stdout);
  sm_shape_destroy(sx);
  sm_shape_destroy(sy);
  sm_gt_destroy(gt);
  sm_mesh_destroy(rawx);
  sm_mesh_destroy(rawy);
  sm_mesh_destroy(rawy_file);
  free(perm);
  free(inv);
}

static int write_json(const char *path, const pair_result *prs, int npr, int runs,
                      int blas_threads, const char *load0, const char *load1) {
  FILE *f = fopen(path, "w");
  if (!f) return -1;
  fprintf(f, "{\n \"benchmark\": \"bench_match\", \"runs\": %d, \"blas_threads\": %d, "
             "\"k_lb\": 100, \"k_elastic\": 100,\n \"loadavg_start\": ",
          runs, blas_threads);
  jstr(f, load0);
  fprintf(f, ", \"loadavg_end\": ");
  jstr(f, load1);
  fprintf(f, ",\n \"pairs\": [");
  for (int p = 0; p < npr; p++) {
    const pair_result *pr = &prs[p];
    fprintf(f, "%s\n  {\"pair\": ", p ? "," : "");
    jstr(f, pr->spec->name);
    fprintf(f, ", \"source\": ");
    jstr(f, pr->spec->src);
    fprintf(f, ", \"target\": ");
    jstr(f, pr->spec->tgt);
    fprintf(f, ", \"target_permuted\": %s, \"ok\": %s", pr->spec->permute_target ? "true" : "false",
            pr->ok ? "true" : "false");
    if (!pr->ok) {
      fprintf(f, ", \"error\": ");
      jstr(f, pr->error);
      fprintf(f, "}");
      continue;
    }
    fprintf(f, ", \"n_source\": %d, \"n_target\": %d, ", pr->nx, pr->ny);
    jnum(f, "read_s", pr->t_read, 0);
    for (int s = 0; s < 2; s++) {
      fprintf(f, ",\n   \"prepare_%s\": {", s ? "target" : "source");
      jnum(f, "total_s", pr->prep_total[s], 1);
      jnum(f, "clean_s", pr->prep_clean[s], 1);
      jnum(f, "lb_s", pr->prep_lb[s], 1);
      jnum(f, "elastic_s", pr->prep_el[s], 1);
      jnum(f, "desc_s", pr->prep_desc[s], 0);
      fprintf(f, "}");
    }
    if (pr->cfg[0].ok) {
      fprintf(f, ",\n   ");
      jnum(f, "full_pipeline_default_s",
           pr->prep_total[0] + pr->prep_total[1] + pr->cfg[0].t_total, 0);
    }
    fprintf(f, ",\n   \"configs\": [");
    for (int c = 0; c < N_CONFIGS; c++) {
      const config_result *cr = &pr->cfg[c];
      const sm_metrics *m = &cr->m;
      fprintf(f, "%s\n    {\"config\": ", c ? "," : "");
      jstr(f, CONFIGS[c].name);
      fprintf(f, ", \"init\": \"%s\", \"multi_start\": %s, \"basis\": \"%s\", \"ok\": %s",
              CONFIGS[c].init == SM_INIT_NN ? "nn" : "sinkhorn",
              CONFIGS[c].multi_start ? "true" : "false",
              CONFIGS[c].basis == SM_MATCH_LB        ? "lb"
              : CONFIGS[c].basis == SM_MATCH_ELASTIC ? "elastic"
                                                     : "hybrid",
              cr->ok ? "true" : "false");
      if (!cr->ok) {
        fprintf(f, ", \"error\": ");
        jstr(f, cr->error);
        fprintf(f, "}");
        continue;
      }
      fprintf(f, ",\n     ");
      jnum(f, "init_s", cr->t_init, 1);
      jnum(f, "refine_s", cr->t_refine, 1);
      jnum(f, "match_s", cr->t_total, 1);
      jnum(f, "geo_mean", m->geo.mean, 1);
      jnum(f, "geo_median", m->geo.median, 1);
      jnum(f, "geo_max", m->geo.max, 1);
      jnum(f, "frac_le_0025", m->geo.frac_le_0025, 1);
      jnum(f, "frac_le_005", m->geo.frac_le_005, 1);
      jnum(f, "frac_le_01", m->geo.frac_le_01, 1);
      jnum(f, "auc", m->geo.auc, 1);
      fprintf(f, "\n     ");
      jnum(f, "bijectivity", m->bijectivity, 1);
      jnum(f, "distinct_over_min_n", m->distinct_over_min_n, 1);
      jnum(f, "coverage", m->coverage, 1);
      jnum(f, "chamfer", m->chamfer, 1);
      jnum(f, "dirichlet", m->dirichlet, 1);
      jnum(f, "dirichlet_gt", m->dirichlet_gt, 1);
      jnum(f, "dirichlet_source_identity", m->dirichlet_source_identity, 1);
      jnum(f, "orientation", cr->orientation, 1);
      jnum(f, "init_distinct", cr->init_distinct, 1);
      fprintf(f, "\"init_used\": \"%s\", \"flipped\": %s, \"unmapped_sources\": %d}",
              cr->init_used == SM_INIT_NN ? "nn" : "sinkhorn", cr->flipped ? "true" : "false",
              cr->unmapped);
    }
    fprintf(f, "]}");
  }
  fprintf(f, "\n ]\n}\n");
  return fclose(f) ? -1 : 0;
}

static void usage(const char *argv0) {
  fprintf(stderr,
          "usage: %s [-r runs] [--pairs homer,head,lion,man] [--json FILE] [--out-maps DIR] "
          "[--blas-threads N] [--defaults]\n",
          argv0);
}

int main(int argc, char **argv) {
  sm_alloc_keep_large(); /* as the daemon and the CLI run (sm_alloc.h) */
  int runs = 3, blas_threads = 1;
  const char *json = "bench_match.json", *maps_dir = NULL, *pairs_arg = NULL;
  for (int i = 1; i < argc; i++) {
    int more = i + 1 < argc;
    if (!strcmp(argv[i], "-r") && more) runs = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--pairs") && more) pairs_arg = argv[++i];
    else if (!strcmp(argv[i], "--json") && more) json = argv[++i];
    else if (!strcmp(argv[i], "--out-maps") && more) maps_dir = argv[++i];
    else if (!strcmp(argv[i], "--blas-threads") && more) blas_threads = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--defaults")) g_defaults_only = 1;
    else {
      usage(argv[0]);
      return 2;
    }
  }
  if (runs < 1 || runs > MAX_RUNS || blas_threads < 1) {
    fprintf(stderr, "runs must be in [1, %d] and blas threads >= 1\n", MAX_RUNS);
    return 2;
  }
  int selected[N_PAIRS] = {0}, nsel = 0;
  if (!pairs_arg) {
    for (int p = 0; p < N_PAIRS; p++) selected[p] = 1;
  } else {
    /* Accept each pair's name and, for the two cross-named pairs, the other animal. */
    char buf[256];
    snprintf(buf, sizeof buf, "%s", pairs_arg);
    for (char *tok = strtok(buf, ","); tok; tok = strtok(NULL, ",")) {
      int found = 0;
      for (int p = 0; p < N_PAIRS; p++)
        if (!strcmp(tok, PAIRS[p].name) || (p == 2 && !strcmp(tok, "cat")) ||
            (p == 3 && !strcmp(tok, "woman"))) {
          selected[p] = found = 1;
        }
      if (!found) {
        fprintf(stderr, "unknown pair '%s' (homer, head, lion, man)\n", tok);
        return 2;
      }
    }
  }
  if (maps_dir && mkdir(maps_dir, 0777) && errno != EEXIST) {
    fprintf(stderr, "%s: %s\n", maps_dir, strerror(errno));
    return 1;
  }
  openblas_set_num_threads(blas_threads);

  char load0[128], load1[128];
  load_string(load0, sizeof load0);
  printf("bench_match: medians of %d runs (seconds), metrics of the first run, k = 100 "
         "(lb and elastic), BLAS threads %d, loadavg %s\n",
         runs, blas_threads, load0);
  printf("geo = mean geodesic error / sqrt(area); <=.05 = fraction within 0.05; bij = distinct "
         "targets / n_target; match = wall time of sm_match;\ndefault = library defaults "
         "(one start, 2 Sinkhorn refinement steps); multi-start = default + the nn start; nn "
         "rows: no Sinkhorn steps; won = start whose map was kept\n");
  fflush(stdout);

  pair_result prs[N_PAIRS];
  memset(prs, 0, sizeof prs);
  for (int p = 0; p < N_PAIRS; p++) {
    if (!selected[p]) continue;
    bench_pair(&PAIRS[p], runs, maps_dir, &prs[nsel]);
    nsel++;
  }
  load_string(load1, sizeof load1);
  printf("\nloadavg at end: %s\n", load1);
  if (write_json(json, prs, nsel, runs, blas_threads, load0, load1)) {
    fprintf(stderr, "%s: cannot write: %s\n", json, strerror(errno));
    return 1;
  }
  printf("json: %s\n", json);
  int failed = 0;
  for (int p = 0; p < nsel; p++) failed |= !prs[p].ok && strncmp(prs[p].error, "skipped", 7);
  return failed;
}
