/* bench_hard: the default matching pipeline (no landmarks) on the hard benchmark pairs of
 * ../shared/data, with ground truth, and how well the map's confidence tells failures.
 *
 * Sets (--sets, comma-separated; default all):
 *   gorilla   tosca_nonisometric_dev/pairs_gorilla_human.txt  (45 pairs, 900-point GT)
 *   manwoman  tosca_nonisometric_dev/pairs_man_woman.txt      (20 pairs, 900-point GT)
 *   within    tosca_classification_5k/pairs_within_class_from_test_pairs.txt (63 pairs)
 *   classic   the four tuned pairs of bench_util.h (homer, head, lion -> cat, man ->
 *             permuted woman; dense GT)
 * Per pair: mean geodesic error (sm_metrics, the definitions of shared/tools/eval_map.py),
 * the confidence the match reports, the time split; per set: mean, median, max, pairs
 * above 0.06 / 0.1 / 0.25, and how many of those above 0.25 lie within half their error
 * of the target's mirrored GT (`swapped`: left and right exchanged, by a mirror or by a
 * half turn that also exchanges front and back; tosca_nonisometric_dev ships X.sym.vts;
 * per pair `mirr`, NAN without one); over all pairs: the AUROC of the confidence for separating
 * failed maps (error > 0.1) from good ones (error < 0.05), i.e. the probability that a
 * random good map gets a higher confidence than a random failed one (ties count half).
 *
 * Bases are computed once per shape (k = 100, the product's default) and cached in --cache
 * DIR. Pairs run on --threads worker threads (one pair per thread, one BLAS thread each).
 * Options of the match (default: the product's defaults): --multi-start, --global 1 (the
 * opt-in global search of sm_global.h; 2 adds orderings), --k1 K, --extremities 0|1|2 (the
 * tip search: off, when doubtful, always; "tips h/n" = winning hypothesis / refined); --analyze prints every start of the global search
 * with its true error instead of matching; --trace-tips prints every map the tip search
 * judges, its score and its true error (both design data, never used by the product).
 *
 * Usage: bench_hard [--sets a,b] [--cache DIR] [--threads N] [--json OUT] [--limit N]
 *                   [--global 0|1|2] [--multi-start] [--k1 K] [--analyze] [--trace-tips]
 *                   [--extremities 0|1|2] [--ext-below C] [--ext-hypotheses H]
 *                   [--bijective W] (the last stage's bijective ZoomOut weight, 0 = off)
 *                   [--anchor W] (landmark anchoring of the kept tip map; 0 = off)
 *                   [--anchor-orient W] (weight of the tips' orientation features in
 *                   that anchoring, sm_match_opts.anchor_orient; 0 = off)
 *                   [--match-threads N] (threads of each match, sm_match_opts.threads;
 *                   with --threads 1, the time of one match using N cores)
 *                   [--only A-B,C-D] (only these pairs of the lists, by name)
 *                   [--final-choice 0|1] (sm_match_opts.final_choice; default: the product's)
 *                   [--save-maps DIR] (each pair's map as DIR/NAME.map, the format of
 *                   shared/tools/eval_map.py: one 0-based target vertex per source vertex)
 * Exit: 0, 1 on a failure, 77 when ../shared/data is absent.
 */
#define _POSIX_C_SOURCE 200809L
#include <cblas.h>
#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "bench_util.h"
#include "sm_coarse.h"
#include "sm_alloc.h"
#include "sm_confidence.h"
#include "sm_eigs.h"
#include "sm_global.h"
#include "sm_knn.h"
#include "sm_match.h"
#include "sm_meshio.h"
#include "sm_metrics.h"

void openblas_set_num_threads(int);

#define K_BASIS 100
#define MAX_PAIRS 256
#define FAIL_ERR 0.1
#define GOOD_ERR 0.05

typedef struct hard_pair {
  char set[16], name[300];
  char src[1024], tgt[1024], gt_src[1024], gt_tgt[1024]; /* gt_*: vts files or "" */
  char gt_mirror[1024]; /* the target's left/right-mirrored GT (X.sym.vts), or "" */
  int classic;  /* index into PAIRS, or -1 */
  /* results */
  int ok;
  char error[1200];
  double err_mean, err_max, confidence, orientation, continuity, cycle, distortion, turns, curvature, t_init,
      t_refine, t_total;
  int flipped, hypothesis, ext_tried, ext_hypothesis;
  double final_lb_weight; /* sm_match_result.final_lb_weight */
  double err_mirror;      /* mean error against gt_mirror; NAN without one */
} hard_pair;

typedef struct bench_cfg {
  const char *cache;
  int global, multi_start, k1, analyze, trace_tips, extremities, ext_h;
  double ext_below, bijective; /* bijective < 0: the product's default */
  double anchor;                /* < 0: the product's default */
  double anchor_orient;         /* < 0: the product's default */
  int match_threads;            /* sm_match_opts.threads of each match; 0: the default */
  const char *save_maps;        /* directory for each pair's map (input vertices), or NULL */
  int final_choice;             /* < 0: the product's default */
} bench_cfg;

/* ---- shapes, with their bases cached on disk ----------------------------------------- */

/* The stem names the cache files: the mesh file's name plus a tag (permuted copies). */
static int prepare(const sm_mesh *raw, const char *cache, const char *stem, sm_shape **out,
                   sm_error *err) {
  char lb[4096], el[4096];
  snprintf(lb, sizeof lb, "%s/%s.lb.k%d.smb", cache, stem, K_BASIS);
  snprintf(el, sizeof el, "%s/%s.el.k%d.smb", cache, stem, K_BASIS);
  return bench_cached_shape(raw, K_BASIS, lb, el, out, NULL, err);
}

static const char *base_name(const char *path) {
  const char *s = strrchr(path, '/');
  return s ? s + 1 : path;
}

/* ---- the pair lists --------------------------------------------------------------- */

/* --only: a comma-separated list of pair names "src-tgt" (NULL: every pair). */
static const char *only_pairs;

static int wanted(const char *a, const char *b) {
  if (!only_pairs) return 1;
  char name[260];
  snprintf(name, sizeof name, "%s-%s", a, b);
  size_t len = strlen(name);
  for (const char *s = only_pairs; *s;) {
    const char *e = strchr(s, ',');
    size_t l = e ? (size_t)(e - s) : strlen(s);
    if (l == len && !strncmp(s, name, l)) return 1;
    s += l + (e ? 1 : 0);
  }
  return 0;
}

static int add_list(hard_pair *P, int n, const char *set, const char *dir, const char *list,
                    const char *mesh_fmt, int limit) {
  char path[2048];
  snprintf(path, sizeof path, "%s/%s/%s", SM_DATA_DIR, dir, list);
  FILE *f = fopen(path, "r");
  if (!f) return n;
  char a[128], b[128];
  int added = 0;
  while (n < MAX_PAIRS && fscanf(f, "%127s %127s", a, b) == 2 && (!limit || added < limit)) {
    if (!wanted(a, b)) continue;
    hard_pair *p = &P[n++];
    memset(p, 0, sizeof *p);
    snprintf(p->set, sizeof p->set, "%s", set);
    snprintf(p->name, sizeof p->name, "%s-%s", a, b);
    snprintf(p->src, sizeof p->src, "%s/%s/", SM_DATA_DIR, dir);
    snprintf(p->src + strlen(p->src), sizeof p->src - strlen(p->src), mesh_fmt, a);
    snprintf(p->tgt, sizeof p->tgt, "%s/%s/", SM_DATA_DIR, dir);
    snprintf(p->tgt + strlen(p->tgt), sizeof p->tgt - strlen(p->tgt), mesh_fmt, b);
    snprintf(p->gt_src, sizeof p->gt_src, "%s/%s/corres/%s.vts", SM_DATA_DIR, dir, a);
    snprintf(p->gt_tgt, sizeof p->gt_tgt, "%s/%s/corres/%s.vts", SM_DATA_DIR, dir, b);
    snprintf(p->gt_mirror, sizeof p->gt_mirror, "%s/%s/corres/%s.sym.vts", SM_DATA_DIR, dir, b);
    if (access(p->gt_mirror, R_OK)) p->gt_mirror[0] = 0;
    p->classic = -1;
    p->err_mirror = NAN;
    added++;
  }
  fclose(f);
  return n;
}

static int add_classic(hard_pair *P, int n, int limit) {
  for (int i = 0; i < N_PAIRS && n < MAX_PAIRS && (!limit || i < limit); i++) {
    hard_pair *p = &P[n++];
    memset(p, 0, sizeof *p);
    snprintf(p->set, sizeof p->set, "classic");
    snprintf(p->name, sizeof p->name, "%s", PAIRS[i].name);
    p->classic = i;
    p->err_mirror = NAN;
  }
  return n;
}

static int has_set(const char *sets, const char *name) {
  if (!sets) return 1;
  const char *s = strstr(sets, name);
  size_t l = strlen(name);
  return s && (s == sets || s[-1] == ',') && (s[l] == 0 || s[l] == ',');
}

/* ---- one pair ----------------------------------------------------------------------- */

static int load_listed(const hard_pair *p, bench_raw_pair *L, sm_error *err) {
  int rc = sm_mesh_read_file(p->src, NULL, &L->rawx, err);
  if (!rc) rc = sm_mesh_read_file(p->tgt, NULL, &L->rawy, err);
  if (!rc)
    rc = sm_gt_load_vts(p->gt_src, p->gt_tgt, 1, L->rawx->nv, L->rawy->nv, &L->gt, err);
  return rc;
}

static void stems(const hard_pair *p, char *sx, char *sy, size_t n) {
  if (p->classic >= 0) {
    snprintf(sx, n, "%s_source", PAIRS[p->classic].name);
    snprintf(sy, n, "%s_target", PAIRS[p->classic].name);
  } else {
    snprintf(sx, n, "%s", base_name(p->src));
    snprintf(sy, n, "%s", base_name(p->tgt));
  }
}

static void match_options(const bench_cfg *c, sm_match_opts *o) {
  sm_match_opts_default(o);
  if (c->global >= 0) o->global = c->global;
  if (c->extremities >= 0) o->extremities = c->extremities;
  if (c->ext_below >= 0) o->ext_below = c->ext_below;
  if (c->ext_h > 0) o->ext_hypotheses = c->ext_h;
  o->multi_start = c->multi_start;
  if (c->k1 > 0) o->k1 = c->k1;
  if (c->bijective >= 0) o->bijective = c->bijective;
  if (c->anchor >= 0) o->anchor = c->anchor;
  if (c->anchor_orient >= 0) o->anchor_orient = c->anchor_orient;
  if (c->final_choice >= 0) o->final_choice = c->final_choice;
  if (c->match_threads > 0) o->threads = c->match_threads;
  o->want_yx = 1;
}

/* Mean geodesic error of map (input vertices of X -> of Y) against gt; NAN on failure. */
static double mean_error(const bench_raw_pair *L, const int32_t *map, const sm_gt *gt,
                         sm_error *err) {
  double *e = malloc((size_t)gt->n * sizeof *e), mean = NAN;
  sm_geo_stats gs;
  if (e && !sm_geodesic_errors(L->rawy, map, L->rawx->nv, gt, 1, e, err) &&
      !sm_geo_summarize(e, gt->n, &gs, err))
    mean = gs.mean;
  free(e);
  return mean;
}

/* --analyze: every start of the global search, its intrinsic scores and its true error
 * (the data the search's energy is designed from; never used by the product). */
static double map_error(const bench_raw_pair *L, const sm_shape *sx, const sm_shape *sy,
                        const int32_t *T, sm_error *err) {
  int32_t *map = malloc((size_t)L->rawx->nv * sizeof *map);
  double mean = NAN;
  if (map) {
    sm_match_to_input(sx, sy, T, map);
    for (int32_t i = 0; i < L->rawx->nv; i++)
      if (map[i] < 0) map[i] = 0;
    mean = mean_error(L, map, L->gt, err);
  }
  free(map);
  return mean;
}

static void analyze(const hard_pair *p, const bench_raw_pair *L, const sm_shape *sx,
                    const sm_shape *sy) {
  sm_error err = {0};
  sm_coarse_opts co;
  sm_coarse_opts_default(&co);
  co.k0 = 20;
  double C[400];
  sm_coarse_side cx = {sx->mesh, sx->lb, sx->desc}, cy = {sy->mesh, sy->lb, sy->desc};
  if (sm_coarse_fmap(&cx, &cy, sx->n_desc, &co, C, &err)) return;
  const double *ex[1] = {C};
  sm_global_opts go;
  sm_global_opts_default(&go);
  go.extra = ex;
  go.n_extra = 1;
  go.k_extra = 20;
  if (getenv("ANA_M")) go.k_signs = atoi(getenv("ANA_M"));
  if (getenv("ANA_PERM")) go.permute = atoi(getenv("ANA_PERM"));
  sm_global_side gx = {sx->mesh, sx->lb, sx->desc, sx->n_desc},
                 gy = {sy->mesh, sy->lb, sy->desc, sy->n_desc};
  sm_global_hyp *h = NULL;
  int nh = 0;
  double t0 = sm_now();
  if (sm_global_search(&gx, &gy, &go, &h, &nh, &err)) {
    printf("analyze %s: %s\n", p->name, err.msg);
    return;
  }
  double t = sm_now() - t0;
  for (int i = 0; i < nh; i++)
    if (h[i].T) printf("HYP %s %s %2d err %.4f resid %.4f cycle %.4f cover %.3f orient %+.3f desc %.4f E %.4f\n", p->set,
           p->name, i, map_error(L, sx, sy, h[i].T, &err), h[i].residual, h[i].cycle,
           h[i].coverage, h[i].orientation, h[i].desc, h[i].energy);
  printf("HYPTIME %s %.3f\n", p->name, t);
  sm_global_free(h, nh);
}

/* --trace-tips: every map the tip search judges (h = 0: the descriptor start's; h = -1:
 * the kept one refined anchored, with how far it moved from the kept map), its score and
 * true error (design data for the search; never used by the product). */
typedef struct tip_trace {
  const hard_pair *p;
  const bench_raw_pair *L;
  const sm_shape *sx, *sy;
  int32_t *best;     /* the best-scored hypothesis map so far (what the search keeps) */
  double best_score;
} tip_trace;

/* How far the anchored map moved from the kept one (target positions, unit area): mean
 * displacement and the share of vertices moved by more than SM_CONFIDENCE_TAU. */
static void trace_moved(const tip_trace *t, const int32_t *T, double *mean, double *far) {
  const sm_mesh *my = t->sy->mesh;
  int32_t n = t->sx->mesh->nv, nfar = 0;
  double sum = 0;
  for (int32_t i = 0; i < n; i++) {
    double d = sqrt(sm_knn_dist2(my->V + 3 * (size_t)T[i], my->V + 3 * (size_t)t->best[i], 3));
    sum += d;
    nfar += d > SM_CONFIDENCE_TAU;
  }
  *mean = sum / n;
  *far = (double)nfar / n;
}

static void trace_tip(void *ud, int h, const sm_match_result *r, double score) {
  tip_trace *t = ud;
  sm_error err = {0};
  double e = map_error(t->L, t->sx, t->sy, r->T, &err), mean = 0, far = 0;
  if (h < 0) trace_moved(t, r->T, &mean, &far);
  else if (h == 0 || score > t->best_score) {
    memcpy(t->best, r->T, (size_t)t->sx->mesh->nv * sizeof *t->best);
    t->best_score = score;
  }
  printf("TIP %s %s %d err %.4f score %.4f cont %.4f orient %+.4f turns %.4f distort %.4f "
         "curv %.4f cycle %.4f conf %.4f moved %.4f far %.4f\n", t->p->set, t->p->name, h, e,
         score, r->continuity, r->orientation, r->turns, r->distortion, r->curvature, r->cycle,
         r->confidence, mean, far);
  fflush(stdout);
}

/* The map as eval_map.py reads it: one 0-based target vertex per source vertex. */
static void save_map(const char *dir, const hard_pair *p, const int32_t *map, int32_t n) {
  char path[1500];
  snprintf(path, sizeof path, "%s/%s.map", dir, p->name);
  FILE *f = fopen(path, "w");
  if (!f) {
    fprintf(stderr, "bench_hard: cannot write %s\n", path);
    return;
  }
  for (int32_t i = 0; i < n; i++) fprintf(f, "%d\n", (int)map[i]);
  fclose(f);
}

/* Mean error of map (input vertices) against the target's mirrored GT: a failed map that
 * is near it swapped left and right, alone (a mirror) or with front and back (a half
 * turn about the body's axis; orientation-preserving). NAN without a mirrored GT. */
static double mirror_error(const hard_pair *p, const bench_raw_pair *L, const int32_t *map,
                           sm_error *err) {
  sm_gt *gt = NULL;
  if (!p->gt_mirror[0] ||
      sm_gt_load_vts(p->gt_src, p->gt_mirror, 1, L->rawx->nv, L->rawy->nv, &gt, err))
    return NAN;
  double mean = mean_error(L, map, gt, err);
  sm_gt_destroy(gt);
  return mean;
}

static int run_pair(const bench_cfg *c, hard_pair *p, sm_error *err) {
  bench_raw_pair L = {0};
  sm_shape *sx = NULL, *sy = NULL;
  sm_match_result r = {0};
  char stx[1100], sty[1100];
  stems(p, stx, sty, sizeof stx);
  int rc = p->classic >= 0 ? bench_load_raw_pair(&PAIRS[p->classic], &L, err) : load_listed(p, &L, err);
  if (!rc) rc = prepare(L.rawx, c->cache, stx, &sx, err);
  if (!rc) rc = prepare(L.rawy, c->cache, sty, &sy, err);
  if (!rc && c->analyze) {
    analyze(p, &L, sx, sy);
    sm_shape_destroy(sx);
    sm_shape_destroy(sy);
    bench_raw_pair_free(&L);
    return SM_OK;
  }
  sm_match_opts o;
  match_options(c, &o);
  tip_trace tt = {p, &L, sx, sy, malloc((size_t)sx->mesh->nv * sizeof(int32_t)), 0};
  if (!tt.best) rc = SM_ENOMEM;
  if (c->trace_tips) {
    o.on_tip_map = trace_tip;
    o.on_tip_map_ud = &tt;
  }
  double t0 = sm_now();
  if (!rc) rc = sm_match(sx, sy, &o, &r, err);
  p->t_total = sm_now() - t0;
  free(tt.best);
  int32_t *map = rc ? NULL : malloc((size_t)L.rawx->nv * sizeof *map);
  double *e = rc ? NULL : malloc((size_t)L.gt->n * sizeof *e);
  if (!rc && (!map || !e)) rc = sm_error_set(err, SM_ENOMEM, "out of memory");
  if (!rc) {
    sm_match_to_input(sx, sy, r.T, map);
    for (int32_t i = 0; i < L.rawx->nv; i++)
      if (map[i] < 0) map[i] = 0;
    rc = sm_geodesic_errors(L.rawy, map, L.rawx->nv, L.gt, 1, e, err);
  }
  if (!rc && c->save_maps) save_map(c->save_maps, p, map, L.rawx->nv);
  if (!rc) {
    sm_geo_stats gs;
    rc = sm_geo_summarize(e, L.gt->n, &gs, err);
    p->err_mean = gs.mean;
    p->err_max = gs.max;
    p->confidence = r.confidence;
    p->orientation = r.orientation;
    p->continuity = r.continuity;
    p->cycle = r.cycle;
    p->distortion = r.distortion;
    p->turns = r.turns;
    p->curvature = r.curvature;
    p->t_init = r.t_init;
    p->t_refine = r.t_refine;
    p->flipped = r.flipped;
    p->hypothesis = r.hypothesis;
    p->ext_tried = r.ext_tried;
    p->ext_hypothesis = r.ext_hypothesis;
    p->final_lb_weight = r.final_lb_weight;
    p->err_mirror = mirror_error(p, &L, map, err);
  }
  free(map);
  free(e);
  sm_match_result_free(&r);
  sm_shape_destroy(sx);
  sm_shape_destroy(sy);
  bench_raw_pair_free(&L);
  return rc;
}

/* ---- workers ------------------------------------------------------------------------ */

typedef struct work {
  const bench_cfg *cfg;
  hard_pair *P;
  int n, next;
  pthread_mutex_t lock;
} work;

static void *worker(void *arg) {
  work *w = arg;
  openblas_set_num_threads(1);
  for (;;) {
    pthread_mutex_lock(&w->lock);
    int i = w->next++;
    pthread_mutex_unlock(&w->lock);
    if (i >= w->n) return NULL;
    hard_pair *p = &w->P[i];
    sm_error err = {0};
    int rc = run_pair(w->cfg, p, &err);
    p->ok = rc == SM_OK;
    if (!p->ok) snprintf(p->error, sizeof p->error, "%s", err.msg);
    pthread_mutex_lock(&w->lock);
    if (p->ok)
      printf("%-9s %-28s err %.4f  max %.3f  conf %.3f  orient %+.2f cont %.3f cyc %.3f  hyp %2d%s  "
             "tips %d/%d  lbw %.1f  init %.2f s  refine %.2f s  total %.2f s  mirr %.4f\n",
             p->set, p->name, p->err_mean, p->err_max, p->confidence, p->orientation,
             p->continuity, p->cycle, p->hypothesis, p->flipped ? " flip" : "",
             p->ext_hypothesis, p->ext_tried, p->final_lb_weight, p->t_init, p->t_refine,
             p->t_total, p->err_mirror);
    else
      printf("%-9s %-28s FAILED: %s\n", p->set, p->name, p->error);
    fflush(stdout);
    pthread_mutex_unlock(&w->lock);
  }
}

/* ---- summaries ---------------------------------------------------------------------- */

/* P(conf of a good map > conf of a failed map), ties half; NaN without both kinds. */
static double auroc(const hard_pair *P, int n, int *ngood, int *nbad) {
  double s = 0;
  *ngood = *nbad = 0;
  for (int i = 0; i < n; i++) {
    if (!P[i].ok) continue;
    if (P[i].err_mean < GOOD_ERR) ++*ngood;
    if (P[i].err_mean > FAIL_ERR) ++*nbad;
  }
  if (!*ngood || !*nbad) return NAN;
  for (int i = 0; i < n; i++) {
    if (!P[i].ok || !(P[i].err_mean < GOOD_ERR)) continue;
    for (int j = 0; j < n; j++) {
      if (!P[j].ok || !(P[j].err_mean > FAIL_ERR)) continue;
      s += P[i].confidence > P[j].confidence ? 1.0
           : P[i].confidence == P[j].confidence ? 0.5 : 0.0;
    }
  }
  return s / ((double)*ngood * *nbad);
}

typedef struct set_stats {
  int n, failed, above006, above01, above025;
  int swapped; /* of the maps above 0.25: those within half their error of the mirrored GT */
  double mean, median, max, conf_mean, t_median;
} set_stats;

static set_stats summarize(const hard_pair *P, int n, const char *set) {
  set_stats s = {0};
  double *v = malloc((size_t)(n + 1) * sizeof *v), *t = malloc((size_t)(n + 1) * sizeof *t);
  for (int i = 0; i < n; i++) {
    if (set && strcmp(P[i].set, set)) continue;
    if (!P[i].ok) {
      s.failed++;
      continue;
    }
    double e = P[i].err_mean;
    v[s.n] = e;
    t[s.n] = P[i].t_total;
    s.n++;
    s.mean += e;
    s.conf_mean += P[i].confidence;
    if (e > s.max) s.max = e;
    s.above006 += e > 0.06;
    s.above01 += e > 0.1;
    s.above025 += e > 0.25;
    s.swapped += e > 0.25 && P[i].err_mirror < e / 2; /* false when NAN */
  }
  if (s.n) {
    s.mean /= s.n;
    s.conf_mean /= s.n;
    s.median = median(v, s.n);
    s.t_median = median(t, s.n);
  }
  free(v);
  free(t);
  return s;
}

static void write_json(const char *path, const bench_cfg *c, const hard_pair *P, int n,
                       const char **sets, int nsets, double au, int ng, int nb) {
  FILE *f = fopen(path, "w");
  if (!f) {
    fprintf(stderr, "bench_hard: cannot write %s: %s\n", path, strerror(errno));
    return;
  }
  char load[128];
  load_string(load, sizeof load);
  fprintf(f, "{\"bench\": \"bench_hard\", \"global\": %d, \"multi_start\": %d, \"k1\": %d, "
          "\"extremities\": %d, \"loadavg\": ", c->global, c->multi_start, c->k1, c->extremities);
  jstr(f, load);
  fprintf(f, ",\n \"pairs\": [\n");
  for (int i = 0; i < n; i++) {
    const hard_pair *p = &P[i];
    fprintf(f, "  {\"set\": \"%s\", \"pair\": \"%s\", \"ok\": %d, ", p->set, p->name, p->ok);
    if (p->ok) {
      jnum(f, "err_mean", p->err_mean, 1);
      jnum(f, "err_max", p->err_max, 1);
      jnum(f, "confidence", p->confidence, 1);
      jnum(f, "orientation", p->orientation, 1);
      jnum(f, "continuity", p->continuity, 1);
      jnum(f, "cycle", p->cycle, 1);
      jnum(f, "distortion", p->distortion, 1);
      jnum(f, "turns", p->turns, 1);
      jnum(f, "curvature", p->curvature, 1);
      fprintf(f, "\"hypothesis\": %d, \"flipped\": %d, ", p->hypothesis, p->flipped);
      fprintf(f, "\"ext_tried\": %d, \"ext_hypothesis\": %d, ", p->ext_tried, p->ext_hypothesis);
      fprintf(f, "\"final_lb_weight\": %g, ", p->final_lb_weight);
      jnum(f, "t_init", p->t_init, 1);
      jnum(f, "t_refine", p->t_refine, 1);
      if (!isnan(p->err_mirror)) jnum(f, "err_mirror", p->err_mirror, 1);
      jnum(f, "t_total", p->t_total, 0);
    } else {
      fprintf(f, "\"error\": ");
      jstr(f, p->error);
    }
    fprintf(f, "}%s\n", i + 1 < n ? "," : "");
  }
  fprintf(f, " ],\n \"sets\": {");
  for (int s = 0; s < nsets; s++) {
    set_stats st = summarize(P, n, sets[s]);
    fprintf(f, "%s\"%s\": {\"n\": %d, \"failed\": %d, ", s ? ", " : "", sets[s], st.n,
            st.failed);
    jnum(f, "mean", st.mean, 1);
    jnum(f, "median", st.median, 1);
    jnum(f, "max", st.max, 1);
    fprintf(f, "\"above_0.06\": %d, \"above_0.1\": %d, \"above_0.25\": %d, ", st.above006,
            st.above01, st.above025);
    fprintf(f, "\"above_0.25_swapped\": %d, ", st.swapped);
    jnum(f, "confidence_mean", st.conf_mean, 1);
    jnum(f, "t_median", st.t_median, 0);
    fprintf(f, "}");
  }
  fprintf(f, "},\n \"auroc\": {");
  jnum(f, "value", au, 1);
  fprintf(f, "\"good\": %d, \"failed\": %d, \"good_below\": %g, \"failed_above\": %g}}\n", ng,
          nb, GOOD_ERR, FAIL_ERR);
  fclose(f);
}

static void usage(void) {
  fprintf(stderr, "usage: bench_hard [--sets gorilla,manwoman,within,classic] [--cache DIR] "
                  "[--threads N] [--json OUT] [--limit N] [--global 0|1] [--multi-start] "
                  "[--k1 K] [--analyze] [--trace-tips] [--extremities 0|1|2] [--ext-below C] "
                  "[--ext-hypotheses H] [--bijective W] [--anchor W] [--anchor-orient W] [--match-threads N] "
                  "[--only PAIR,PAIR] [--save-maps DIR] [--final-choice 0|1]\n");
}

int main(int argc, char **argv) {
  sm_alloc_keep_large(); /* as the daemon and the CLI run (sm_alloc.h) */
  bench_cfg cfg = {.cache = "bench-cache", .global = -1, .extremities = -1,
                   .ext_below = -1, .bijective = -1,
                   .anchor = -1, .anchor_orient = -1, .final_choice = -1};
  const char *sets_arg = NULL, *json = NULL;
  int threads = 2, limit = 0;
  for (int i = 1; i < argc; i++) {
    const char *a = argv[i];
    const char *v = i + 1 < argc ? argv[i + 1] : NULL;
    if (!strcmp(a, "--sets") && v) sets_arg = argv[++i];
    else if (!strcmp(a, "--cache") && v) cfg.cache = argv[++i];
    else if (!strcmp(a, "--threads") && v) threads = atoi(argv[++i]);
    else if (!strcmp(a, "--json") && v) json = argv[++i];
    else if (!strcmp(a, "--limit") && v) limit = atoi(argv[++i]);
    else if (!strcmp(a, "--global") && v) cfg.global = atoi(argv[++i]);
    else if (!strcmp(a, "--k1") && v) cfg.k1 = atoi(argv[++i]);
    else if (!strcmp(a, "--extremities") && v) cfg.extremities = atoi(argv[++i]);
    else if (!strcmp(a, "--ext-below") && v) cfg.ext_below = atof(argv[++i]);
    else if (!strcmp(a, "--ext-hypotheses") && v) cfg.ext_h = atoi(argv[++i]);
    else if (!strcmp(a, "--bijective") && v) cfg.bijective = atof(argv[++i]);
    else if (!strcmp(a, "--anchor") && v) cfg.anchor = atof(argv[++i]);
    else if (!strcmp(a, "--anchor-orient") && v) cfg.anchor_orient = atof(argv[++i]);
    else if (!strcmp(a, "--match-threads") && v) cfg.match_threads = atoi(argv[++i]);
    else if (!strcmp(a, "--only") && v) only_pairs = argv[++i];
    else if (!strcmp(a, "--save-maps") && v) cfg.save_maps = argv[++i];
    else if (!strcmp(a, "--final-choice") && v) cfg.final_choice = atoi(argv[++i]);
    else if (!strcmp(a, "--multi-start")) cfg.multi_start = 1;
    else if (!strcmp(a, "--analyze")) cfg.analyze = 1;
    else if (!strcmp(a, "--trace-tips")) cfg.trace_tips = 1;
    else {
      usage();
      return 2;
    }
  }
  char probe[2048];
  data_path(probe, sizeof probe, "tosca_nonisometric_dev/pairs_gorilla_human.txt");
  if (!file_exists(probe)) {
    fprintf(stderr, "bench_hard: %s absent: skipped\n", SM_DATA_DIR);
    return 77;
  }
  mkdir(cfg.cache, 0755);
  static hard_pair P[MAX_PAIRS];
  int n = 0;
  const char *all[4] = {"gorilla", "manwoman", "within", "classic"}, *sets[4];
  int nsets = 0;
  for (int s = 0; s < 4; s++)
    if (has_set(sets_arg, all[s])) sets[nsets++] = all[s];
  if (has_set(sets_arg, "gorilla"))
    n = add_list(P, n, "gorilla", "tosca_nonisometric_dev", "pairs_gorilla_human.txt",
                 "meshes/%s.off.gz", limit);
  if (has_set(sets_arg, "manwoman"))
    n = add_list(P, n, "manwoman", "tosca_nonisometric_dev", "pairs_man_woman.txt",
                 "meshes/%s.off.gz", limit);
  if (has_set(sets_arg, "within"))
    n = add_list(P, n, "within", "tosca_classification_5k",
                 "pairs_within_class_from_test_pairs.txt", "meshes/%s.off.gz", limit);
  if (has_set(sets_arg, "classic")) n = add_classic(P, n, limit);
  if (!n) {
    usage();
    return 2;
  }
  if (threads < 1) threads = 1;
  work w = {.cfg = &cfg, .P = P, .n = n};
  pthread_mutex_init(&w.lock, NULL);
  pthread_t th[16];
  int nt = threads > 16 ? 16 : threads;
  for (int t = 0; t < nt; t++) pthread_create(&th[t], NULL, worker, &w);
  for (int t = 0; t < nt; t++) pthread_join(th[t], NULL);
  int any_failed = 0;
  printf("\n%-9s %4s %7s %7s %7s %6s %6s %6s %7s %7s %8s\n", "set", "n", "mean", "median",
         "max", ">0.06", ">0.1", ">0.25", "swapped", "conf", "t_med");
  for (int s = 0; s < nsets; s++) {
    set_stats st = summarize(P, n, sets[s]);
    any_failed |= st.failed > 0;
    printf("%-9s %4d %7.4f %7.4f %7.4f %6d %6d %6d %7d %7.3f %7.2fs%s\n", sets[s], st.n,
           st.mean, st.median, st.max, st.above006, st.above01, st.above025, st.swapped,
           st.conf_mean, st.t_median, st.failed ? "  (some FAILED)" : "");
  }
  int ng, nb;
  double au = auroc(P, n, &ng, &nb);
  printf("AUROC of the confidence (good < %.2f: %d maps, failed > %.2f: %d maps): %.3f\n",
         GOOD_ERR, ng, FAIL_ERR, nb, au);
  if (json) write_json(json, &cfg, P, n, sets, nsets, au, ng, nb);
  return any_failed ? 1 : 0;
}
