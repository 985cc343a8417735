#include "sm_extremity.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "sm_confidence.h"
#include "sm_metrics.h"

/* Tips considered in the assignment search: the SM_EXT_ASSIGN + 1 with the largest AGD
 * (one spare for a shape with an extra tip, e.g. a gorilla's protruding brow), which keeps
 * the search at most 7 * 7! = 35,280 assignments. */
#define EXT_SEARCH (SM_EXT_ASSIGN + 1)
/* Cost of a pair of tips in one component on one shape and in two on the other. */
#define EXT_SPLIT_COST 1.0

typedef struct ext_work {
  const sm_mesh *m;
  sm_edge_paths *paths;
  double *agd, *d;          /* nv each */
  double *rows[SM_EXT_MAX]; /* distances from each accepted tip */
} ext_work;

/* set->src_dir from one more path search per source (the AGD loop cannot keep them: a
 * direction at an early source needs the fields of sources found later). */
static int ext_directions(ext_work *w, sm_ext_set *set, sm_error *err) {
  sm_dir_probe *probe = NULL;
  double col[2 * SM_EXT_SOURCES];
  int rc = sm_dir_probe_create(w->m, set->src, SM_EXT_SOURCES, &probe, err);
  for (int a = 0; !rc && a < SM_EXT_SOURCES; a++) {
    if ((rc = sm_edge_paths_run(w->paths, set->src[a], w->d, err))) break;
    sm_dir_probe_eval(probe, w->d, col);
    for (int c = 0; c < SM_EXT_SOURCES; c++)
      set->src_dir[c][a][0] = col[2 * c], set->src_dir[c][a][1] = col[2 * c + 1];
  }
  sm_dir_probe_destroy(probe);
  return rc;
}

/* AGD over farthest-point sources; a vertex's mean runs over the sources that reach it, so
 * the first source of a new component is where the last search left vertices unreached. */
static int ext_agd(ext_work *w, sm_ext_set *set, sm_error *err) {
  int32_t nv = w->m->nv;
  double *mind = malloc((size_t)nv * sizeof *mind);
  int32_t *cnt = calloc((size_t)nv, sizeof *cnt);
  int rc = (!mind || !cnt) ? sm_error_set(err, SM_ENOMEM, "extremities: out of memory") : SM_OK;
  for (int32_t v = 0; !rc && v < nv; v++) mind[v] = INFINITY, w->agd[v] = 0;
  int32_t src = 0;
  for (int s = 0; !rc && s < SM_EXT_SOURCES; s++) {
    rc = sm_edge_paths_run(w->paths, src, w->d, err);
    set->src[s] = src;
    for (int t = 0; !rc && t <= s; t++)
      set->src_dist[s][t] = set->src_dist[t][s] = w->d[set->src[t]];
    int32_t far = 0;
    for (int32_t v = 0; !rc && v < nv; v++) {
      if (isfinite(w->d[v])) w->agd[v] += w->d[v], cnt[v]++;
      if (w->d[v] < mind[v]) mind[v] = w->d[v];
      if (mind[v] > mind[far]) far = v;
    }
    src = far;
  }
  for (int32_t v = 0; !rc && v < nv; v++) w->agd[v] = cnt[v] ? w->agd[v] / cnt[v] : 0;
  free(mind);
  free(cnt);
  return rc ? rc : ext_directions(w, set, err);
}

typedef struct ext_cand {
  double agd;
  int32_t v;
} ext_cand;

static int cmp_desc_agd(const void *a, const void *b) {
  const ext_cand *x = a, *y = b;
  if (x->agd != y->agd) return (x->agd < y->agd) - (x->agd > y->agd);
  return (x->v > y->v) - (x->v < y->v);
}

/* Vertices with no edge neighbour of larger AGD, by decreasing AGD, into cand; count. */
static int32_t ext_local_maxima(const ext_work *w, ext_cand *cand, char *lower) {
  const sm_mesh *m = w->m;
  memset(lower, 0, (size_t)m->nv);
  for (int32_t f = 0; f < m->nf; f++)
    for (int c = 0; c < 3; c++) {
      int32_t a = m->F[3 * f + c], b = m->F[3 * f + (c + 1) % 3];
      if (w->agd[a] < w->agd[b]) lower[a] = 1;
      else if (w->agd[b] < w->agd[a]) lower[b] = 1;
    }
  int32_t n = 0;
  for (int32_t v = 0; v < m->nv; v++)
    if (!lower[v]) cand[n].agd = w->agd[v], cand[n++].v = v;
  qsort(cand, (size_t)n, sizeof *cand, cmp_desc_agd);
  return n;
}

/* c is a tip when it is farther than the radius from every accepted tip and has the
 * largest AGD within the radius (w->d holds its distances afterwards). */
static int ext_is_tip(ext_work *w, int ntips, int32_t c, int *tip, sm_error *err) {
  *tip = 0;
  for (int t = 0; t < ntips; t++)
    if (w->rows[t][c] < SM_EXT_RADIUS) return SM_OK;
  int rc = sm_edge_paths_run(w->paths, c, w->d, err);
  if (rc) return rc;
  for (int32_t v = 0; v < w->m->nv; v++)
    if (w->d[v] < SM_EXT_RADIUS && w->agd[v] > w->agd[c]) return SM_OK;
  *tip = 1;
  return SM_OK;
}

static int ext_collect(ext_work *w, sm_ext_set *s, sm_error *err) {
  int32_t nv = w->m->nv;
  ext_cand *cand = malloc((size_t)nv * sizeof *cand);
  char *lower = malloc((size_t)nv);
  int rc = (!cand || !lower) ? sm_error_set(err, SM_ENOMEM, "extremities: out of memory") : SM_OK;
  int32_t nc = rc ? 0 : ext_local_maxima(w, cand, lower);
  double mean = 0;
  for (int32_t v = 0; v < nv; v++) mean += w->agd[v];
  mean = mean > 0 ? mean / nv : 1;
  /* Candidates come by decreasing AGD: the first below SM_EXT_MIN_AGD ends the list. */
  for (int32_t i = 0; !rc && i < nc && s->n < SM_EXT_MAX && cand[i].agd >= SM_EXT_MIN_AGD * mean;
       i++) {
    int tip;
    rc = ext_is_tip(w, s->n, cand[i].v, &tip, err);
    if (rc || !tip) continue;
    if (!(w->rows[s->n] = malloc((size_t)nv * sizeof *w->d))) {
      rc = sm_error_set(err, SM_ENOMEM, "extremities: out of memory");
      break;
    }
    memcpy(w->rows[s->n], w->d, (size_t)nv * sizeof *w->d);
    s->v[s->n] = cand[i].v;
    s->agd[s->n] = cand[i].agd / mean;
    s->n++;
  }
  for (int a = 0; !rc && a < s->n; a++)
    for (int b = 0; b < s->n; b++) s->dist[a][b] = w->rows[a][s->v[b]] / mean;
  free(cand);
  free(lower);
  return rc;
}

int sm_ext_detect(const sm_mesh *m, sm_ext_set **out, sm_error *err) {
  *out = NULL;
  if (!m || m->nv < 1) return sm_error_set(err, SM_EINVAL, "extremities: empty mesh");
  ext_work w = {.m = m};
  sm_ext_set *s = calloc(1, sizeof *s);
  w.agd = malloc((size_t)m->nv * sizeof *w.agd);
  w.d = malloc((size_t)m->nv * sizeof *w.d);
  int rc = (!s || !w.agd || !w.d) ? sm_error_set(err, SM_ENOMEM, "extremities: out of memory")
                                  : SM_OK;
  if (!rc) rc = sm_edge_paths_create(m, &w.paths, err);
  if (!rc) rc = ext_agd(&w, s, err);
  if (!rc) rc = ext_collect(&w, s, err);
  sm_edge_paths_destroy(w.paths);
  for (int t = 0; t < SM_EXT_MAX; t++) free(w.rows[t]);
  free(w.agd);
  free(w.d);
  if (rc) {
    free(s);
    return rc;
  }
  *out = s;
  return SM_OK;
}

void sm_ext_destroy(sm_ext_set *s) { free(s); }

/* ---- assignment search ------------------------------------------------------------- */

typedef struct ext_search {
  const sm_ext_set *x, *y;
  int nx, ny, m;               /* tips searched on each side, tips per assignment */
  int px[SM_EXT_ASSIGN], py[SM_EXT_ASSIGN];
  int used[SM_EXT_MAX];
  sm_ext_hypothesis *best;     /* sorted by cost, nbest of max_h filled */
  int nbest, max_h;
} ext_search;

static double pair_cost(double gx, double gy) {
  if (isfinite(gx) && isfinite(gy)) return fabs(gx - gy);
  return isfinite(gx) == isfinite(gy) ? 0 : EXT_SPLIT_COST;
}

/* Gromov product (a|b)_c = (d(c,a) + d(c,b) - d(a,b)) / 2: how far from c the paths to a
 * and to b part. */
static double gromov(const sm_ext_set *s, int c, int a, int b) {
  return (s->dist[c][a] + s->dist[c][b] - s->dist[a][b]) / 2;
}

/* The fraction of comparisons (a|b)_c < (a'|b')_c, over the assigned tips, that the
 * assignment reverses. Where paths part is the shape's skeleton: a human's and a gorilla's
 * arms part near the head and their legs far from it, whatever their lengths, so the
 * order survives the change of proportions that misleads AGD and raw distances (which
 * rank a gorilla's long arms as a human's legs). Rank of the first assignment right by the
 * ground truth (nearest truth point to each tip), without / with this term: 45 gorilla ->
 * human pairs, first in 14 / 21, within the 4 kept 36 / 38; 20 man -> woman pairs, within
 * the first 2 (a left/right twin ties) 12 / 20. */
static double ext_order_cost(const ext_search *q) {
  int n = 0, bad = 0, m = q->m;
  for (int c = 0; c < m; c++)
    for (int p1 = 0; p1 < m * m; p1++) {
      int a = p1 / m, b = p1 % m;
      if (a >= b || a == c || b == c) continue;
      double gx = gromov(q->x, q->px[c], q->px[a], q->px[b]);
      double gy = gromov(q->y, q->py[c], q->py[a], q->py[b]);
      for (int p2 = p1 + 1; p2 < m * m; p2++) {
        int a2 = p2 / m, b2 = p2 % m;
        if (a2 >= b2 || a2 == c || b2 == c) continue;
        double dx = gx - gromov(q->x, q->px[c], q->px[a2], q->px[b2]);
        double dy = gy - gromov(q->y, q->py[c], q->py[a2], q->py[b2]);
        if (!isfinite(dx) || !isfinite(dy)) continue;
        n++;
        bad += (dx > 0) != (dy > 0);
      }
    }
  return n ? (double)bad / n : 0;
}

static double ext_cost(const ext_search *q) {
  double u = 0, g = 0;
  int np = 0;
  for (int a = 0; a < q->m; a++) {
    u += fabs(q->x->agd[q->px[a]] - q->y->agd[q->py[a]]);
    for (int b = a + 1; b < q->m; b++, np++)
      g += pair_cost(q->x->dist[q->px[a]][q->px[b]], q->y->dist[q->py[a]][q->py[b]]);
  }
  return u / q->m + (np ? g / np : 0) + ext_order_cost(q);
}

/* Insert the current assignment into the sorted best list if it is cheap enough. */
static void ext_keep(ext_search *q) {
  double c = ext_cost(q);
  if (q->nbest == q->max_h && c >= q->best[q->nbest - 1].cost) return;
  int i = q->nbest < q->max_h ? q->nbest++ : q->max_h - 1;
  for (; i > 0 && q->best[i - 1].cost > c; i--) q->best[i] = q->best[i - 1];
  sm_ext_hypothesis *h = &q->best[i];
  h->cost = c;
  h->m = q->m;
  for (int a = 0; a < q->m; a++) {
    h->pairs[2 * a] = q->x->v[q->px[a]];
    h->pairs[2 * a + 1] = q->y->v[q->py[a]];
  }
}

/* Tip i of X is skipped or assigned to an unused tip of Y; k tips assigned so far. */
static void ext_enumerate(ext_search *q, int i, int k) {
  if (k == q->m) {
    ext_keep(q);
    return;
  }
  if (q->nx - i < q->m - k) return;
  ext_enumerate(q, i + 1, k);
  for (int j = 0; j < q->ny; j++) {
    if (q->used[j]) continue;
    q->used[j] = 1;
    q->px[k] = i;
    q->py[k] = j;
    ext_enumerate(q, i + 1, k + 1);
    q->used[j] = 0;
  }
}

int sm_ext_hypotheses(const sm_ext_set *x, const sm_ext_set *y, int max_h,
                      sm_ext_hypothesis *out, int *nh, sm_error *err) {
  *nh = 0;
  if (!x || !y || !out || max_h < 1)
    return sm_error_set(err, SM_EINVAL, "extremity hypotheses: bad arguments");
  ext_search q = {.x = x, .y = y, .best = out, .max_h = max_h};
  q.nx = x->n < EXT_SEARCH ? x->n : EXT_SEARCH;
  q.ny = y->n < EXT_SEARCH ? y->n : EXT_SEARCH;
  q.m = q.nx < q.ny ? q.nx : q.ny;
  if (q.m > SM_EXT_ASSIGN) q.m = SM_EXT_ASSIGN;
  if (q.m < 3) return SM_OK;
  ext_enumerate(&q, 0, 0);
  *nh = q.nbest;
  return SM_OK;
}
