/* eval_pairs: experiments 1, 2 and 4 of the evaluation suite on one real pair with ground
 * truth (bench_util.h: homer, head, lion -> cat, man -> permuted woman).
 *
 *   1. ablation and basis-size sweep: the five configurations nn/sinkhorn x lb/elastic and
 *      sinkhorn+hybrid for every refinement size k of --ks: mean geodesic error, accuracy
 *      curve and its area, bijectivity error (mean geodesic distance on X from i to
 *      T_yx(T_xy(i)), / sqrt(area); also the fraction of i with an inexact cycle and the
 *      distinct targets hit),
 *      coverage, Chamfer distance, Dirichlet energy, run time (init / refine / total).
 *   2. accuracy curves: the same records carry the 41-point curve (thresholds 0..0.1).
 *   4. visual check (--visual DIR): the default configuration at --visual-k; a smooth colour
 *      field on the source (its coordinates in the principal frame, mapped to RGB) and the
 *      target coloured through the map Y -> X, written as two PLY files with vertex colours.
 *
 * Bases are computed once per shape with k = max(--ks, 100) functions and cached in
 * --cache DIR (sm_basis_save files tied to the cleaned mesh by its hash), so a rerun costs
 * only the matching. The WKS descriptors (coarse map) always come from the first 100 LB
 * functions, as the product computes them at its default k_lb = 100: only the refinement
 * size varies along the sweep. Maps are scored on the raw meshes with sm_metrics (the
 * definitions of shared/tools/eval_map.py). nn rows run without the Sinkhorn refinement
 * steps (nothing transport-based anywhere), as in bench_match.
 *
 * Usage: eval_pairs --pair NAME --json OUT [--ks 30,50,...] [--configs a,b] [--cache DIR]
 *                   [--visual DIR] [--visual-k K] [--k-basis K] [--blas-threads N]
 * --k-basis raises the basis size (default max(--ks, 100)).
 * Exit: 0, 1 on a failure, 77 when the pair's files are absent (no ../shared/data).
 */
#define _POSIX_C_SOURCE 200809L
#include <cblas.h>
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "bench_util.h"
#include "sm_deform.h"
#include "sm_desc.h"
#include "sm_eigs.h"
#include "sm_match.h"
#include "sm_meshio.h"
#include "sm_metrics.h"

#define MAX_KS 16
#define DESC_K 100

#include "eval_configs.h"

typedef struct pair_data {
  const pair_spec *spec;
  sm_mesh *rawx, *rawy;
  sm_gt *gt;
  sm_shape *sx, *sy;
  int32_t *perm, *inv;
  double t_prep[2];
  int cached[2];
} pair_data;

/* ---- shapes with cached bases -------------------------------------------------------- */

/* Like sm_shape_prepare (clean, unit area, both bases), with the bases cached and the
 * descriptors taken from the first DESC_K LB functions. */
static int prepare_shape(const sm_mesh *raw, int k, const char *cache, const char *stem,
                         sm_shape **out, int *all_cached, sm_error *err) {
  char lbp[4096], elp[4096];
  snprintf(lbp, sizeof lbp, "%s/%s.lb.k%d.smb", cache, stem, k);
  snprintf(elp, sizeof elp, "%s/%s.el.k%d.smb", cache, stem, k);
  int rc = bench_cached_shape(raw, k, lbp, elp, out, all_cached, err);
  const sm_basis *lb = rc ? NULL : (*out)->lb;
  if (rc || lb->k <= DESC_K) return rc;
  sm_basis head = *lb; /* a view of the first DESC_K columns (LB: M-orthonormal) */
  head.k = DESC_K;
  return sm_desc_wks(&head, DESC_K, (*out)->n_desc, 0, (*out)->desc, err);
}

static int load_pair(const pair_spec *ps, int kbasis, const char *cache, pair_data *pd,
                     sm_error *err) {
  bench_raw_pair raw;
  int rc = bench_load_raw_pair(ps, &raw, err);
  if (rc) return rc;
  pd->rawx = raw.rawx;
  pd->rawy = raw.rawy;
  pd->gt = raw.gt;
  pd->perm = raw.perm;
  pd->inv = raw.inv;
  const sm_mesh *raws[2] = {pd->rawx, pd->rawy};
  sm_shape **shapes[2] = {&pd->sx, &pd->sy};
  for (int s = 0; s < 2 && !rc; s++) {
    char stem[256];
    snprintf(stem, sizeof stem, "%s_%s", ps->name, s ? "target" : "source");
    double t0 = sm_now();
    rc = prepare_shape(raws[s], kbasis, cache, stem, shapes[s], &pd->cached[s], err);
    pd->t_prep[s] = sm_now() - t0;
  }
  return rc;
}

static void free_pair(pair_data *pd) {
  sm_shape_destroy(pd->sx);
  sm_shape_destroy(pd->sy);
  sm_gt_destroy(pd->gt);
  sm_mesh_destroy(pd->rawx);
  sm_mesh_destroy(pd->rawy);
  free(pd->perm);
  free(pd->inv);
}

/* ---- one configuration at one k ------------------------------------------------------ */

typedef struct run_result {
  int ok;
  char error[256];
  double t_init, t_refine, t_total, cycle, cycle_geo, orientation;
  int flipped;
  sm_metrics m;
} run_result;

static void match_opts(const eval_config *c, int k, sm_match_opts *o) {
  sm_match_opts_default(o);
  o->init = c->init;
  o->basis = c->basis;
  o->k1 = k;
  if (o->k0 > k) o->k0 = k;
  o->want_yx = 1;
  if (c->init == SM_INIT_NN) o->sinkhorn_levels = 0;
  /* The ablation compares bases: the final pass's LB functions (bench_hard measures
   * them) would mix LB into the elastic configurations. */
  o->final_hybrid = 0;
}

/* The map in the raw numbering; vertices cleaning dropped (none on these meshes) -> 0. */
static int32_t *input_map(const sm_shape *x, const sm_shape *y, const int32_t *T,
                          int32_t n_input) {
  int32_t *map = malloc((size_t)n_input * sizeof *map);
  if (!map) return NULL;
  sm_match_to_input(x, y, T, map);
  for (int32_t i = 0; i < n_input; i++)
    if (map[i] < 0) map[i] = 0;
  return map;
}

/* Mean geodesic distance on X (raw, / sqrt(area)) between i and T_yx(T_xy(i)): the
 * bijectivity error that stays meaningful when the two meshes have different vertex
 * counts (an exact cycle is then rare even for a perfect map). */
static int cycle_geodesic(const pair_data *pd, const sm_match_result *res, double *out,
                          sm_error *err) {
  int32_t nx = pd->sx->mesh->nv, n = pd->rawx->nv;
  int32_t *comp = malloc((size_t)nx * sizeof *comp);
  double *e = malloc((size_t)n * sizeof *e);
  sm_gt *id = NULL;
  int rc = (!comp || !e) ? sm_error_set(err, SM_ENOMEM, "cycle") : 0;
  for (int32_t i = 0; !rc && i < nx; i++) comp[i] = res->T_yx[res->T[i]];
  int32_t *map = rc ? NULL : input_map(pd->sx, pd->sx, comp, n);
  if (!rc && !map) rc = sm_error_set(err, SM_ENOMEM, "cycle");
  if (!rc) rc = sm_gt_identity(n, &id, err);
  if (!rc) rc = sm_geodesic_errors(pd->rawx, map, n, id, 2, e, err);
  sm_geo_stats st;
  if (!rc) rc = sm_geo_summarize(e, n, &st, err);
  if (!rc) *out = st.mean;
  sm_gt_destroy(id);
  free(map), free(comp), free(e);
  return rc;
}

static int run_one(const pair_data *pd, const eval_config *c, int k, run_result *rr,
                   sm_match_result *keep) {
  sm_error err = {0};
  sm_match_opts o;
  match_opts(c, k, &o);
  sm_match_result res = {0};
  double t0 = sm_now();
  int rc = sm_match(pd->sx, pd->sy, &o, &res, &err);
  rr->t_total = sm_now() - t0;
  int32_t *map = NULL;
  if (!rc) {
    rr->t_init = res.t_init;
    rr->t_refine = res.t_refine;
    rr->orientation = res.orientation;
    rr->flipped = res.flipped;
    rc = sm_map_cycle_error(res.T, res.nx, res.T_yx, res.ny, &rr->cycle, &err);
  }
  if (!rc) rc = cycle_geodesic(pd, &res, &rr->cycle_geo, &err);
  if (!rc && !(map = input_map(pd->sx, pd->sy, res.T, pd->rawx->nv)))
    rc = sm_error_set(&err, SM_ENOMEM, "map");
  if (!rc) rc = sm_metrics_compute(pd->rawx, pd->rawy, map, pd->gt, 2, &rr->m, &err);
  free(map);
  if (!rc && keep) {
    *keep = res;
  } else {
    sm_match_result_free(&res);
  }
  rr->ok = !rc;
  if (rc) snprintf(rr->error, sizeof rr->error, "%s", err.msg);
  return rc;
}

/* ---- visual check --------------------------------------------------------------------- */

/* Colour of each source vertex: its coordinates in the principal frame, each scaled to
 * [0.1, 0.9] over the shape, as RGB: smooth, and different on every part. */
static int color_field(const sm_mesh *m, float *rgb) {
  double c[3] = {0, 0, 0}, ax[3];
  sm_error err;
  if (sm_principal_axis(m, ax, &err)) return -1;
  for (int32_t v = 0; v < m->nv; v++)
    for (int d = 0; d < 3; d++) c[d] += m->V[3 * v + d] / m->nv;
  /* A frame: the principal axis, then any two orthonormal directions completing it. */
  double e0[3] = {ax[0], ax[1], ax[2]}, t[3] = {1, 0, 0}, e1[3], e2[3];
  if (fabs(e0[0]) > 0.9) t[0] = 0, t[1] = 1;
  e1[0] = e0[1] * t[2] - e0[2] * t[1], e1[1] = e0[2] * t[0] - e0[0] * t[2];
  e1[2] = e0[0] * t[1] - e0[1] * t[0];
  double n1 = sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]);
  for (int d = 0; d < 3; d++) e1[d] /= n1;
  e2[0] = e0[1] * e1[2] - e0[2] * e1[1], e2[1] = e0[2] * e1[0] - e0[0] * e1[2];
  e2[2] = e0[0] * e1[1] - e0[1] * e1[0];
  const double *E[3] = {e0, e1, e2};
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (int pass = 0; pass < 2; pass++)
    for (int32_t v = 0; v < m->nv; v++)
      for (int a = 0; a < 3; a++) {
        const double *p = m->V + 3 * (size_t)v;
        double q = (p[0] - c[0]) * E[a][0] + (p[1] - c[1]) * E[a][1] + (p[2] - c[2]) * E[a][2];
        if (!pass) {
          lo[a] = q < lo[a] ? q : lo[a];
          hi[a] = q > hi[a] ? q : hi[a];
        } else {
          rgb[3 * (size_t)v + a] = (float)(0.1 + 0.8 * (q - lo[a]) / (hi[a] - lo[a] + 1e-300));
        }
      }
  return 0;
}

static int write_ply(const char *path, const sm_mesh *m, const float *rgb) {
  FILE *f = fopen(path, "w");
  if (!f) return -1;
  fprintf(f, "ply\nformat ascii 1.0\ncomment shapematch eval_pairs colour transfer\n"
             "element vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
             "property uchar red\nproperty uchar green\nproperty uchar blue\n"
             "element face %d\nproperty list uchar int vertex_indices\nend_header\n",
          m->nv, m->nf);
  for (int32_t v = 0; v < m->nv; v++)
    fprintf(f, "%.7g %.7g %.7g %d %d %d\n", m->V[3 * v], m->V[3 * v + 1], m->V[3 * v + 2],
            (int)lrintf(255 * rgb[3 * v]), (int)lrintf(255 * rgb[3 * v + 1]),
            (int)lrintf(255 * rgb[3 * v + 2]));
  for (int32_t t = 0; t < m->nf; t++)
    fprintf(f, "3 %d %d %d\n", m->F[3 * t], m->F[3 * t + 1], m->F[3 * t + 2]);
  return fclose(f);
}

/* Source coloured by the field, target coloured through T_yx (target vertex j takes the
 * colour of the source vertex it maps to): where the map is right, the pictures agree. */
static int write_visual(const pair_data *pd, const sm_match_result *res, const char *dir) {
  const sm_mesh *x = pd->sx->mesh, *y = pd->sy->mesh;
  float *cx = malloc(3 * (size_t)x->nv * sizeof *cx), *cy = malloc(3 * (size_t)y->nv * sizeof *cy);
  int rc = (!cx || !cy) ? -1 : color_field(x, cx);
  for (int32_t j = 0; !rc && j < y->nv; j++)
    memcpy(cy + 3 * (size_t)j, cx + 3 * (size_t)res->T_yx[j], 3 * sizeof *cy);
  char path[4096];
  snprintf(path, sizeof path, "%s/%s_source.ply", dir, pd->spec->name);
  if (!rc) rc = write_ply(path, x, cx);
  snprintf(path, sizeof path, "%s/%s_target.ply", dir, pd->spec->name);
  if (!rc) rc = write_ply(path, y, cy);
  /* The map itself, in the PLY files' numbering: the renderer aligns the target to the
   * source through it so both are seen from the same side. */
  snprintf(path, sizeof path, "%s/%s_target_to_source.txt", dir, pd->spec->name);
  sm_error err;
  if (!rc) rc = sm_map_save(path, res->T_yx, y->nv, &err);
  free(cx);
  free(cy);
  return rc;
}

/* ---- output --------------------------------------------------------------------------- */

static void json_run(FILE *f, const eval_config *c, int k, const run_result *rr, int first) {
  fprintf(f, "%s\n  {\"config\": \"%s\", \"k\": %d, \"ok\": %s", first ? "" : ",", c->name, k,
          rr->ok ? "true" : "false");
  if (!rr->ok) {
    fprintf(f, ", \"error\": ");
    jstr(f, rr->error);
    fprintf(f, "}");
    return;
  }
  const sm_metrics *m = &rr->m;
  fprintf(f, ", ");
  jnum(f, "geo_mean", m->geo.mean, 1);
  jnum(f, "geo_median", m->geo.median, 1);
  jnum(f, "frac_le_005", m->geo.frac_le_005, 1);
  jnum(f, "auc", m->geo.auc, 1);
  jnum(f, "bijectivity_error", rr->cycle_geo, 1);
  jnum(f, "cycle_fraction", rr->cycle, 1);
  jnum(f, "distinct_targets", m->bijectivity, 1);
  jnum(f, "coverage", m->coverage, 1);
  jnum(f, "chamfer", m->chamfer, 1);
  jnum(f, "dirichlet", m->dirichlet, 1);
  jnum(f, "dirichlet_gt", m->dirichlet_gt, 1);
  jnum(f, "orientation", rr->orientation, 1);
  fprintf(f, "\"flipped\": %s, ", rr->flipped ? "true" : "false");
  jnum(f, "t_init", rr->t_init, 1);
  jnum(f, "t_refine", rr->t_refine, 1);
  jnum(f, "t_total", rr->t_total, 1);
  fprintf(f, "\"curve\": [");
  for (int i = 0; i < SM_METRICS_CURVE_N; i++)
    fprintf(f, "%s%.6g", i ? ", " : "", m->geo.curve[i]);
  fprintf(f, "]}");
}

static int parse_ks(const char *s, int *ks) {
  int n = 0;
  char buf[256];
  snprintf(buf, sizeof buf, "%s", s);
  for (char *t = strtok(buf, ","); t && n < MAX_KS; t = strtok(NULL, ",")) {
    ks[n] = atoi(t);
    if (ks[n] < 2 || ks[n] > 500) return -1;
    n++;
  }
  return n;
}

static const pair_spec *find_pair(const char *name) {
  for (int p = 0; p < N_PAIRS; p++)
    if (!strcmp(name, PAIRS[p].name)) return &PAIRS[p];
  return NULL;
}

static int config_selected(const char *list, const char *name) {
  if (!list) return 1;
  char buf[512];
  snprintf(buf, sizeof buf, "%s", list);
  for (char *t = strtok(buf, ","); t; t = strtok(NULL, ","))
    if (!strcmp(t, name)) return 1;
  return 0;
}

static void usage(void) {
  fprintf(stderr, "usage: eval_pairs --pair homer|head|lion|man --json OUT [--ks 30,50,...] "
                  "[--configs nn+lb,...] [--cache DIR] [--visual DIR] [--visual-k K] "
                  "[--k-basis K] [--blas-threads N]\n");
}

int main(int argc, char **argv) {
  const char *pair = NULL, *json = NULL, *cache = "eval-cache", *visual = NULL, *cfgs = NULL;
  int ks[MAX_KS] = {30, 50, 70, 90, 110, 130, 150}, nk = 7, visual_k = 100, blas = 1;
  int kbasis_arg = 0;
  for (int i = 1; i < argc; i++) {
    int more = i + 1 < argc;
    if (!strcmp(argv[i], "--pair") && more) pair = argv[++i];
    else if (!strcmp(argv[i], "--json") && more) json = argv[++i];
    else if (!strcmp(argv[i], "--cache") && more) cache = argv[++i];
    else if (!strcmp(argv[i], "--visual") && more) visual = argv[++i];
    else if (!strcmp(argv[i], "--visual-k") && more) visual_k = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--configs") && more) cfgs = argv[++i];
    else if (!strcmp(argv[i], "--blas-threads") && more) blas = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--k-basis") && more) kbasis_arg = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--ks") && more) {
      if ((nk = parse_ks(argv[++i], ks)) < 1) return usage(), 2;
    } else {
      return usage(), 2;
    }
  }
  const pair_spec *ps = pair ? find_pair(pair) : NULL;
  if (!ps || !json || blas < 1) return usage(), 2;
  if (mkdir(cache, 0777) && errno != EEXIST) return perror(cache), 1;
  openblas_set_num_threads(blas);
  int kbasis = DESC_K;
  for (int i = 0; i < nk; i++) kbasis = ks[i] > kbasis ? ks[i] : kbasis;
  if (visual_k > kbasis) kbasis = visual_k;
  /* A larger basis than needed: the eigenvectors of repeated or close eigenvalues depend on
   * how many were computed, so a run that must reproduce another uses its basis size. */
  if (kbasis_arg > kbasis) kbasis = kbasis_arg;

  pair_data pd = {.spec = ps};
  sm_error err = {0};
  int rc = load_pair(ps, kbasis, cache, &pd, &err);
  if (rc == 77) {
    printf("eval_pairs %s: skipped (../shared/data absent)\n", ps->name);
    free_pair(&pd);
    return 77;
  }
  if (rc) {
    fprintf(stderr, "eval_pairs %s: %s\n", ps->name, err.msg);
    free_pair(&pd);
    return 1;
  }
  printf("eval_pairs %s: %d -> %d vertices, bases k=%d %s (%.1f + %.1f s)\n", ps->name,
         pd.rawx->nv, pd.rawy->nv, kbasis, pd.cached[0] && pd.cached[1] ? "cached" : "computed",
         pd.t_prep[0], pd.t_prep[1]);
  FILE *f = fopen(json, "w");
  if (!f) return perror(json), 1;
  fprintf(f, "{\"pair\": \"%s\", \"source\": \"%s\", \"target\": \"%s\", \"n_source\": %d, "
             "\"n_target\": %d, \"k_basis\": %d, \"prepare_s\": [%.4f, %.4f], "
             "\"bases_cached\": %s, \"thresholds_max\": %g, \"runs\": [",
          ps->name, ps->src, ps->tgt, pd.rawx->nv, pd.rawy->nv, kbasis, pd.t_prep[0],
          pd.t_prep[1], pd.cached[0] && pd.cached[1] ? "true" : "false", SM_METRICS_CURVE_MAX);
  int failed = 0, first = 1;
  for (int c = 0; c < N_CONFIGS; c++) {
    if (!config_selected(cfgs, CONFIGS[c].name)) continue;
    for (int i = 0; i < nk; i++) {
      run_result rr = {0};
      failed |= run_one(&pd, &CONFIGS[c], ks[i], &rr, NULL) != 0;
      json_run(f, &CONFIGS[c], ks[i], &rr, first);
      first = 0;
      printf("  %-17s k=%3d  %s geo %.4f auc %.3f bij %.4f cov %.3f dir %.2f  %.2f s\n",
             CONFIGS[c].name, ks[i], rr.ok ? "ok" : rr.error, rr.m.geo.mean, rr.m.geo.auc,
             rr.cycle_geo, rr.m.coverage, rr.m.dirichlet, rr.t_total);
      fflush(stdout);
    }
  }
  fprintf(f, "]");
  if (visual) {
    sm_match_result res = {0};
    run_result rr = {0};
    int vrc = run_one(&pd, &CONFIGS[3], visual_k, &rr, &res);
    if (!vrc) vrc = write_visual(&pd, &res, visual);
    sm_match_result_free(&res);
    fprintf(f, ", \"visual\": {\"config\": \"%s\", \"k\": %d, \"ok\": %s, ", CONFIGS[3].name,
            visual_k, vrc ? "false" : "true");
    jnum(f, "geo_mean", rr.m.geo.mean, 0);
    fprintf(f, "}");
    failed |= vrc != 0;
  }
  fprintf(f, "}\n");
  if (fclose(f)) failed = 1;
  free_pair(&pd);
  return failed;
}
