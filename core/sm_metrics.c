/* sm_metrics: map scoring as in ../shared/tools/eval_map.py. See sm_metrics.h.
 *
 * DESIGN (geodesic errors). eval_map.py runs a full Dijkstra from every distinct GT target
 * vertex (scipy, float32 rows). We need only d(t, map(s)) for the pairs (s, t) of each
 * distinct t, so pairs are grouped by t and each search stops once all of its group's
 * map(s) are settled: for a good map that is a few rings around t, for a random map it is
 * close to a full search. Dijkstra is exact, so stopping early changes nothing (results
 * equal eval_map.py's up to its float32 rounding). As the graph is undirected, the
 * searches start from the mapped vertices instead when those are fewer (a map that hits
 * few vertices, e.g. a constant one, is then cheap). Distinct
 * t are handed out in small chunks from an atomic counter to nthreads threads (the caller
 * included), each with its own workspace; they write disjoint entries of e[] and are
 * joined before returning. The edge graph has the unique undirected edges of the faces
 * (self-loops of repeated-index faces dropped: they never shorten a path), as in
 * eval_map.py's edge_graph.
 */
#include "sm_metrics.h"

#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "sm_meshio.h"

#define INDEX_FILE_MAX_BYTES ((size_t)1 << 30)
#define DEFAULT_THREADS 2
#define MAX_THREADS 64

/* ================================================================ index files */

/* Rows of a whitespace-separated numeric file, rounded and rebased, with the file line of
 * each row so range errors can say where. */
typedef struct idx_table {
  int64_t nrows, cap;
  int ncols;
  int64_t *val;  /* nrows * ncols */
  int32_t *line; /* nrows */
} idx_table;

static void table_free(idx_table *t) {
  free(t->val);
  free(t->line);
  memset(t, 0, sizeof *t);
}

static int table_push(idx_table *t, const int64_t *vals, int32_t line) {
  if (t->nrows == t->cap) {
    int64_t cap = t->cap ? 2 * t->cap : 1024;
    int64_t *v = realloc(t->val, (size_t)cap * t->ncols * sizeof *v);
    if (!v) return SM_ENOMEM;
    t->val = v;
    int32_t *l = realloc(t->line, (size_t)cap * sizeof *l);
    if (!l) return SM_ENOMEM;
    t->line = l;
    t->cap = cap;
  }
  memcpy(t->val + t->nrows * t->ncols, vals, (size_t)t->ncols * sizeof *vals);
  t->line[t->nrows++] = line;
  return SM_OK;
}

static int is_space(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f'; }

/* Parses one NUL-terminated line (comment already cut) into up to ncols numbers;
 * returns how many there were, or -1 if a token is not a finite number of int range. */
static int parse_line(char *s, int ncols, int base, int64_t *vals) {
  int n = 0;
  for (;;) {
    while (is_space(*s)) s++;
    if (!*s) return n;
    char *end;
    double x = strtod(s, &end);
    if (end == s || (*end && !is_space(*end))) return -1;
    if (!isfinite(x) || fabs(x) > 2147483647.0) return -1;
    if (n < ncols) vals[n] = (int64_t)nearbyint(x) - base; /* half to even, as numpy.rint */
    n++;
    s = end;
  }
}

static int read_table(const char *path, int ncols, int base, idx_table *t, sm_error *err) {
  memset(t, 0, sizeof *t);
  t->ncols = ncols;
  if (base != 0 && base != 1)
    return sm_error_set(err, SM_EINVAL, "index base must be 0 or 1, got %d", base);
  uint8_t *raw;
  size_t len;
  int rc = sm_read_file_bytes(path, INDEX_FILE_MAX_BYTES, &raw, &len, err);
  if (rc) return rc;
  char *buf = realloc(raw, len + 1); /* room for a terminating NUL */
  if (!buf) {
    free(raw);
    return sm_error_set(err, SM_ENOMEM, "out of memory reading %s", path);
  }
  buf[len] = 0;
  int32_t lineno = 0;
  for (char *s = buf; *s && rc == 0;) {
    lineno++;
    char *nl = strchr(s, '\n'), *next = nl ? nl + 1 : s + strlen(s);
    if (nl) *nl = 0;
    char *hash = strchr(s, '#');
    if (hash) *hash = 0;
    int64_t vals[2];
    int n = parse_line(s, ncols, base, vals);
    if (n < 0 || (n > 0 && n != ncols))
      rc = sm_error_set(err, SM_EFORMAT, "%s:%d: expected %d number%s per line", path,
                        lineno, ncols, ncols > 1 ? "s" : "");
    else if (n > 0 && table_push(t, vals, lineno))
      rc = sm_error_set(err, SM_ENOMEM, "out of memory reading %s", path);
    s = next;
  }
  free(buf);
  if (rc) table_free(t);
  return rc;
}

/* Checks column col of t against [0, bound) (bound < 0: unchecked). */
static int check_col(const idx_table *t, int col, int32_t bound, const char *path,
                     const char *what, sm_error *err) {
  if (bound < 0) return SM_OK;
  for (int64_t r = 0; r < t->nrows; r++) {
    int64_t v = t->val[r * t->ncols + col];
    if (v < 0 || v >= bound)
      return sm_error_set(err, SM_ERANGE, "%s:%d: %s vertex %lld out of range (%s has %d vertices)",
                          path, t->line[r], what, (long long)v, what, bound);
  }
  return SM_OK;
}

/* Checks that row numbers (0-based) of t are valid indices of `what`. */
static int check_rows(const idx_table *t, int32_t bound, const char *path, const char *what,
                      sm_error *err) {
  if (bound < 0 || t->nrows <= bound) return SM_OK;
  return sm_error_set(err, SM_ERANGE, "%s:%d: %s vertex %d out of range (%s has %d vertices)",
                      path, t->line[bound], what, bound, what, bound);
}

static int gt_alloc(int64_t n, sm_gt **out, sm_error *err) {
  sm_gt *g = calloc(1, sizeof *g);
  size_t bytes = (size_t)(n ? n : 1) * sizeof(int32_t);
  if (g) {
    g->src = malloc(bytes);
    g->tgt = malloc(bytes);
  }
  if (!g || !g->src || !g->tgt) {
    sm_gt_destroy(g);
    return sm_error_set(err, SM_ENOMEM, "out of memory for %lld GT pairs", (long long)n);
  }
  g->n = n;
  *out = g;
  return SM_OK;
}

void sm_gt_destroy(sm_gt *gt) {
  if (!gt) return;
  free(gt->src);
  free(gt->tgt);
  free(gt);
}

/* Dense on one side: row r is vertex r of the side `rows_are_source` names. */
static int gt_from_column(const char *path, int base, int32_t n_source, int32_t n_target,
                          int rows_are_source, sm_gt **out, sm_error *err) {
  if (!path || !out) return sm_error_set(err, SM_EINVAL, "sm_gt_load: null argument");
  idx_table t;
  int rc = read_table(path, 1, base, &t, err);
  if (rc) return rc;
  int32_t nrow_bound = rows_are_source ? n_source : n_target;
  int32_t val_bound = rows_are_source ? n_target : n_source;
  const char *row_what = rows_are_source ? "source" : "target";
  const char *val_what = rows_are_source ? "target" : "source";
  if (!(rc = check_rows(&t, nrow_bound, path, row_what, err)) &&
      !(rc = check_col(&t, 0, val_bound, path, val_what, err)) &&
      !(rc = gt_alloc(t.nrows, out, err))) {
    for (int64_t r = 0; r < t.nrows; r++) {
      (rows_are_source ? (*out)->src : (*out)->tgt)[r] = (int32_t)r;
      (rows_are_source ? (*out)->tgt : (*out)->src)[r] = (int32_t)t.val[r];
    }
  }
  table_free(&t);
  return rc;
}

int sm_gt_load_dense(const char *path, int base, int32_t n_source, int32_t n_target,
                     sm_gt **out, sm_error *err) {
  return gt_from_column(path, base, n_source, n_target, 1, out, err);
}

int sm_gt_load_inverse(const char *path, int base, int32_t n_source, int32_t n_target,
                       sm_gt **out, sm_error *err) {
  return gt_from_column(path, base, n_source, n_target, 0, out, err);
}

int sm_gt_load_vts(const char *src_path, const char *tgt_path, int base, int32_t n_source,
                   int32_t n_target, sm_gt **out, sm_error *err) {
  if (!src_path || !tgt_path || !out) return sm_error_set(err, SM_EINVAL, "sm_gt_load_vts: null argument");
  idx_table a, b;
  int rc = read_table(src_path, 1, base, &a, err);
  if (rc) return rc;
  if ((rc = read_table(tgt_path, 1, base, &b, err))) {
    table_free(&a);
    return rc;
  }
  if (a.nrows != b.nrows)
    rc = sm_error_set(err, SM_EFORMAT, "%s has %lld rows but %s has %lld", src_path,
                      (long long)a.nrows, tgt_path, (long long)b.nrows);
  if (!rc && !(rc = check_col(&a, 0, n_source, src_path, "source", err)) &&
      !(rc = check_col(&b, 0, n_target, tgt_path, "target", err)) &&
      !(rc = gt_alloc(a.nrows, out, err))) {
    for (int64_t r = 0; r < a.nrows; r++) {
      (*out)->src[r] = (int32_t)a.val[r];
      (*out)->tgt[r] = (int32_t)b.val[r];
    }
  }
  table_free(&a);
  table_free(&b);
  return rc;
}

int sm_gt_load_pairs(const char *path, int base, int32_t n_source, int32_t n_target,
                     sm_gt **out, sm_error *err) {
  if (!path || !out) return sm_error_set(err, SM_EINVAL, "sm_gt_load_pairs: null argument");
  idx_table t;
  int rc = read_table(path, 2, base, &t, err);
  if (rc) return rc;
  if (!(rc = check_col(&t, 0, n_source, path, "source", err)) &&
      !(rc = check_col(&t, 1, n_target, path, "target", err)) &&
      !(rc = gt_alloc(t.nrows, out, err))) {
    for (int64_t r = 0; r < t.nrows; r++) {
      (*out)->src[r] = (int32_t)t.val[2 * r];
      (*out)->tgt[r] = (int32_t)t.val[2 * r + 1];
    }
  }
  table_free(&t);
  return rc;
}

int sm_gt_identity(int32_t n, sm_gt **out, sm_error *err) {
  if (n < 0 || !out) return sm_error_set(err, SM_EINVAL, "sm_gt_identity: bad argument (n=%d)", n);
  int rc = gt_alloc(n, out, err);
  if (rc) return rc;
  for (int32_t i = 0; i < n; i++) (*out)->src[i] = (*out)->tgt[i] = i;
  return SM_OK;
}

int sm_gt_remap_target(sm_gt *gt, const int32_t *inv_perm, int32_t n_target, sm_error *err) {
  if (!gt || !inv_perm) return sm_error_set(err, SM_EINVAL, "sm_gt_remap_target: null argument");
  for (int64_t k = 0; k < gt->n; k++)
    if (gt->tgt[k] < 0 || gt->tgt[k] >= n_target)
      return sm_error_set(err, SM_ERANGE, "GT pair %lld: target vertex %d out of range (target has %d vertices)",
                          (long long)k, gt->tgt[k], n_target);
  for (int64_t k = 0; k < gt->n; k++) gt->tgt[k] = inv_perm[gt->tgt[k]];
  return SM_OK;
}

int sm_gt_is_dense(const sm_gt *gt, int32_t n_source, int32_t *dense) {
  if (!gt || n_source <= 0 || gt->n != n_source) return 0;
  unsigned char *seen = calloc((size_t)n_source, 1);
  if (!seen) return 0;
  int ok = 1;
  for (int64_t k = 0; k < gt->n && ok; k++) {
    int32_t s = gt->src[k];
    if (s < 0 || s >= n_source || seen[s]) ok = 0;
    else seen[s] = 1;
  }
  free(seen);
  if (ok && dense)
    for (int64_t k = 0; k < gt->n; k++) dense[gt->src[k]] = gt->tgt[k];
  return ok;
}

/* ================================================================ map files */

int sm_map_load(const char *path, int32_t n_source, int32_t n_target, int32_t **map,
                sm_error *err) {
  if (!path || !map) return sm_error_set(err, SM_EINVAL, "sm_map_load: null argument");
  idx_table t;
  int rc = read_table(path, 1, 0, &t, err);
  if (rc) return rc;
  if (t.nrows != n_source)
    rc = sm_error_set(err, SM_EFORMAT, "%s has %lld entries, the source has %d vertices", path,
                      (long long)t.nrows, n_source);
  if (!rc && !(rc = check_col(&t, 0, n_target, path, "target", err))) {
    *map = malloc((size_t)(n_source ? n_source : 1) * sizeof **map);
    if (!*map) rc = sm_error_set(err, SM_ENOMEM, "out of memory reading %s", path);
    for (int32_t i = 0; !rc && i < n_source; i++) (*map)[i] = (int32_t)t.val[i];
  }
  table_free(&t);
  return rc;
}

int sm_map_save(const char *path, const int32_t *map, int32_t n_source, sm_error *err) {
  if (!path || (!map && n_source > 0)) return sm_error_set(err, SM_EINVAL, "sm_map_save: null argument");
  FILE *f = fopen(path, "w");
  if (!f) return sm_error_set(err, SM_EIO, "cannot create %s", path);
  int bad = 0;
  for (int32_t i = 0; i < n_source && !bad; i++) bad = fprintf(f, "%d\n", map[i]) < 0;
  if (fclose(f) || bad) return sm_error_set(err, SM_EIO, "write error on %s", path);
  return SM_OK;
}

/* ================================================================ checks */

static int check_map(const int32_t *map, int32_t n, int32_t n_target, const char *what,
                     sm_error *err) {
  if (!map && n > 0) return sm_error_set(err, SM_EINVAL, "%s is NULL", what);
  for (int32_t i = 0; i < n; i++)
    if (map[i] < 0 || map[i] >= n_target)
      return sm_error_set(err, SM_ERANGE, "%s[%d] = %d out of range (target has %d vertices)",
                          what, i, map[i], n_target);
  return SM_OK;
}

static int check_gt(const sm_gt *gt, int32_t n_source, int32_t n_target, sm_error *err) {
  for (int64_t k = 0; k < gt->n; k++) {
    if (gt->src[k] < 0 || gt->src[k] >= n_source)
      return sm_error_set(err, SM_ERANGE, "GT pair %lld: source vertex %d out of range (source has %d vertices)",
                          (long long)k, gt->src[k], n_source);
    if (gt->tgt[k] < 0 || gt->tgt[k] >= n_target)
      return sm_error_set(err, SM_ERANGE, "GT pair %lld: target vertex %d out of range (target has %d vertices)",
                          (long long)k, gt->tgt[k], n_target);
  }
  return SM_OK;
}

static int check_faces(const sm_mesh *m, const char *what, sm_error *err) {
  if (!m) return sm_error_set(err, SM_EINVAL, "%s mesh is NULL", what);
  for (int64_t i = 0; i < 3 * (int64_t)m->nf; i++)
    if (m->F[i] < 0 || m->F[i] >= m->nv)
      return sm_error_set(err, SM_ERANGE, "%s face %lld references vertex %d, mesh has %d vertices",
                          what, (long long)(i / 3), m->F[i], m->nv);
  return SM_OK;
}

/* ================================================================ edge graph */

typedef struct edge_graph {
  int32_t nv;
  int64_t *off; /* nv + 1 */
  int32_t *adj; /* off[nv] */
  double *w;    /* off[nv], Euclidean lengths */
} edge_graph;

static void graph_free(edge_graph *g) {
  free(g->off);
  free(g->adj);
  free(g->w);
}

static int cmp_u64(const void *a, const void *b) {
  uint64_t x = *(const uint64_t *)a, y = *(const uint64_t *)b;
  return (x > y) - (x < y);
}

/* Unique undirected edges of the faces as sorted (min << 32 | max) keys. */
static int64_t unique_edges(const sm_mesh *m, uint64_t *key) {
  int64_t n = 0;
  for (int64_t f = 0; f < m->nf; f++)
    for (int c = 0; c < 3; c++) {
      uint32_t a = (uint32_t)m->F[3 * f + c], b = (uint32_t)m->F[3 * f + (c + 1) % 3];
      if (a == b) continue;
      key[n++] = a < b ? ((uint64_t)a << 32 | b) : ((uint64_t)b << 32 | a);
    }
  qsort(key, (size_t)n, sizeof *key, cmp_u64);
  int64_t u = 0;
  for (int64_t i = 0; i < n; i++)
    if (u == 0 || key[i] != key[u - 1]) key[u++] = key[i];
  return u;
}

static double dist3(const double *a, const double *b) {
  double dx = a[0] - b[0], dy = a[1] - b[1], dz = a[2] - b[2];
  return sqrt(dx * dx + dy * dy + dz * dz);
}

static int graph_build(const sm_mesh *m, edge_graph *g, sm_error *err) {
  memset(g, 0, sizeof *g);
  g->nv = m->nv;
  uint64_t *key = malloc((size_t)(3 * (int64_t)m->nf + 1) * sizeof *key);
  g->off = calloc((size_t)m->nv + 1, sizeof *g->off);
  if (!key || !g->off) goto oom;
  int64_t ne = unique_edges(m, key);
  g->adj = malloc((size_t)(2 * ne + 1) * sizeof *g->adj);
  g->w = malloc((size_t)(2 * ne + 1) * sizeof *g->w);
  if (!g->adj || !g->w) goto oom;
  for (int64_t e = 0; e < ne; e++) {
    g->off[(key[e] >> 32) + 1]++;
    g->off[(key[e] & 0xffffffffu) + 1]++;
  }
  for (int32_t v = 0; v < m->nv; v++) g->off[v + 1] += g->off[v];
  for (int64_t e = 0; e < ne; e++) { /* off[v] doubles as the fill cursor, restored below */
    int32_t a = (int32_t)(key[e] >> 32), b = (int32_t)(key[e] & 0xffffffffu);
    double len = dist3(m->V + 3 * (int64_t)a, m->V + 3 * (int64_t)b);
    g->adj[g->off[a]] = b, g->w[g->off[a]++] = len;
    g->adj[g->off[b]] = a, g->w[g->off[b]++] = len;
  }
  for (int32_t v = m->nv; v > 0; v--) g->off[v] = g->off[v - 1];
  g->off[0] = 0;
  free(key);
  return SM_OK;
oom:
  free(key);
  graph_free(g);
  return sm_error_set(err, SM_ENOMEM, "out of memory for the edge graph (%d vertices)", m->nv);
}

/* ================================================================ Dijkstra */

/* One thread's workspace. done[v] == stamp: v settled in the current search; need[v] ==
 * stamp: the current search must reach v. Stamps avoid clearing O(nv) arrays per search;
 * dist is reset through the touched list. The heap is lazy (stale entries skipped), so it
 * holds at most 1 + (number of directed edges) entries. */
typedef struct dijk_ws {
  double *dist;
  int32_t *done, *need, *touched;
  int32_t ntouched;
  double *hkey;
  int32_t *hval;
  int64_t hn;
} dijk_ws;

static void ws_free(dijk_ws *w) {
  free(w->dist);
  free(w->done);
  free(w->need);
  free(w->touched);
  free(w->hkey);
  free(w->hval);
}

static int ws_init(dijk_ws *w, const edge_graph *g) {
  memset(w, 0, sizeof *w);
  size_t nv = (size_t)g->nv + 1, nh = (size_t)g->off[g->nv] + 2;
  w->dist = malloc(nv * sizeof *w->dist);
  w->done = calloc(nv, sizeof *w->done);
  w->need = calloc(nv, sizeof *w->need);
  w->touched = malloc(nv * sizeof *w->touched);
  w->hkey = malloc(nh * sizeof *w->hkey);
  w->hval = malloc(nh * sizeof *w->hval);
  if (!w->dist || !w->done || !w->need || !w->touched || !w->hkey || !w->hval) {
    ws_free(w);
    return SM_ENOMEM;
  }
  for (int32_t v = 0; v < g->nv; v++) w->dist[v] = INFINITY;
  return SM_OK;
}

static void heap_push(dijk_ws *w, double k, int32_t v) {
  int64_t i = w->hn++;
  while (i > 0) {
    int64_t p = (i - 1) / 2;
    if (w->hkey[p] <= k) break;
    w->hkey[i] = w->hkey[p], w->hval[i] = w->hval[p];
    i = p;
  }
  w->hkey[i] = k, w->hval[i] = v;
}

static void heap_pop(dijk_ws *w, double *k, int32_t *v) {
  *k = w->hkey[0], *v = w->hval[0];
  double lk = w->hkey[--w->hn];
  int32_t lv = w->hval[w->hn];
  int64_t i = 0;
  for (;;) {
    int64_t c = 2 * i + 1;
    if (c >= w->hn) break;
    if (c + 1 < w->hn && w->hkey[c + 1] < w->hkey[c]) c++;
    if (w->hkey[c] >= lk) break;
    w->hkey[i] = w->hkey[c], w->hval[i] = w->hval[c];
    i = c;
  }
  w->hkey[i] = lk, w->hval[i] = lv;
}

static void relax(dijk_ws *w, int32_t v, double d) {
  if (w->dist[v] == INFINITY) w->touched[w->ntouched++] = v;
  w->dist[v] = d;
  heap_push(w, d, v);
}

/* Search from src until `remaining` needed vertices are settled (or everything reachable
 * is). Leaves dist/done valid for this stamp; ws_reset clears dist afterwards. */
static void dijkstra_run(dijk_ws *w, const edge_graph *g, int32_t src, int32_t stamp,
                         int64_t remaining) {
  w->hn = 0;
  relax(w, src, 0.0);
  while (w->hn > 0) {
    double d;
    int32_t v;
    heap_pop(w, &d, &v);
    if (w->done[v] == stamp) continue; /* stale entry */
    w->done[v] = stamp;
    if (w->need[v] == stamp && --remaining == 0) break;
    for (int64_t e = g->off[v]; e < g->off[v + 1]; e++) {
      int32_t u = g->adj[e];
      double nd = d + g->w[e];
      if (nd < w->dist[u] && w->done[u] != stamp) relax(w, u, nd);
    }
  }
}

static void ws_reset(dijk_ws *w) {
  for (int32_t i = 0; i < w->ntouched; i++) w->dist[w->touched[i]] = INFINITY;
  w->ntouched = 0;
}

struct sm_edge_paths {
  edge_graph g;
  dijk_ws w;
  int32_t stamp;
};

int sm_edge_paths_create(const sm_mesh *m, sm_edge_paths **out, sm_error *err) {
  *out = NULL;
  if (!m) return sm_error_set(err, SM_EINVAL, "sm_edge_paths_create: null mesh");
  int rc = check_faces(m, "mesh", err);
  if (rc) return rc;
  sm_edge_paths *p = calloc(1, sizeof *p);
  if (!p) return sm_error_set(err, SM_ENOMEM, "out of memory for Dijkstra (%d vertices)", m->nv);
  if ((rc = graph_build(m, &p->g, err))) {
    free(p);
    return rc;
  }
  if (ws_init(&p->w, &p->g)) {
    graph_free(&p->g);
    free(p);
    return sm_error_set(err, SM_ENOMEM, "out of memory for Dijkstra (%d vertices)", m->nv);
  }
  *out = p;
  return SM_OK;
}

int sm_edge_paths_run(sm_edge_paths *p, int32_t source, double *dist, sm_error *err) {
  if (source < 0 || source >= p->g.nv)
    return sm_error_set(err, SM_ERANGE, "source vertex %d out of range (mesh has %d vertices)",
                        source, p->g.nv);
  dijkstra_run(&p->w, &p->g, source, ++p->stamp, INT64_MAX);
  memcpy(dist, p->w.dist, (size_t)p->g.nv * sizeof *dist);
  ws_reset(&p->w);
  return SM_OK;
}

int32_t sm_edge_paths_size(const sm_edge_paths *p) { return p->g.nv; }

void sm_edge_paths_destroy(sm_edge_paths *p) {
  if (!p) return;
  ws_free(&p->w);
  graph_free(&p->g);
  free(p);
}

int sm_mesh_edge_dijkstra(const sm_mesh *m, int32_t source, double *dist, sm_error *err) {
  if (!m || !dist) return sm_error_set(err, SM_EINVAL, "sm_mesh_edge_dijkstra: null argument");
  if (source < 0 || source >= m->nv)
    return sm_error_set(err, SM_ERANGE, "source vertex %d out of range (mesh has %d vertices)",
                        source, m->nv);
  sm_edge_paths *p;
  int rc = sm_edge_paths_create(m, &p, err);
  if (!rc) rc = sm_edge_paths_run(p, source, dist, err);
  sm_edge_paths_destroy(p);
  return rc;
}

/* ---- grouped, threaded geodesic errors ---- */

#define GEO_CHUNK 8

typedef struct geo_job {
  const edge_graph *g;
  const int32_t *uniq;    /* distinct search sources */
  int32_t nuniq;
  const int64_t *grp;     /* nuniq + 1: pairs of uniq[u] are order[grp[u] .. grp[u+1]) */
  const int64_t *order;   /* pair indices grouped by GT target */
  const int32_t *need_v;  /* per pair: the vertex whose distance from the group's source is needed */
  double scale;           /* 1 / sqrt(area(T)) */
  double *e;
  atomic_int_fast64_t next;
} geo_job;

static void geo_group(geo_job *j, dijk_ws *w, int32_t u) {
  int32_t stamp = u + 1;
  int64_t remaining = 0;
  for (int64_t q = j->grp[u]; q < j->grp[u + 1]; q++) {
    int32_t v = j->need_v[j->order[q]];
    if (w->need[v] != stamp) w->need[v] = stamp, remaining++;
  }
  dijkstra_run(w, j->g, j->uniq[u], stamp, remaining);
  for (int64_t q = j->grp[u]; q < j->grp[u + 1]; q++) {
    int64_t k = j->order[q];
    int32_t v = j->need_v[k];
    j->e[k] = w->done[v] == stamp ? w->dist[v] * j->scale : INFINITY;
  }
  ws_reset(w);
}

static void geo_drain(geo_job *j, dijk_ws *w) {
  for (;;) {
    int64_t s = atomic_fetch_add(&j->next, GEO_CHUNK);
    if (s >= j->nuniq) return;
    int64_t end = s + GEO_CHUNK < j->nuniq ? s + GEO_CHUNK : j->nuniq;
    for (int64_t u = s; u < end; u++) geo_group(j, w, (int32_t)u);
  }
}

/* A helper thread that cannot get memory just does nothing: the caller drains the rest. */
static void *geo_thread(void *arg) {
  geo_job *j = arg;
  dijk_ws w;
  if (ws_init(&w, j->g) == SM_OK) {
    geo_drain(j, &w);
    ws_free(&w);
  }
  return NULL;
}

static void geo_parallel(geo_job *j, dijk_ws *w, int nthreads) {
  pthread_t tid[MAX_THREADS];
  int started = 0;
  for (int t = 1; t < nthreads; t++) {
    if (pthread_create(&tid[started], NULL, geo_thread, j) != 0) break;
    started++;
  }
  geo_drain(j, w);
  for (int t = 0; t < started; t++) pthread_join(tid[t], NULL);
}

/* Groups the n pairs by their search source key[k] (counting sort). */
static int group_pairs(const int32_t *key, int64_t n, int32_t nt, int32_t **uniq,
                       int32_t *nuniq, int64_t **grp, int64_t **order) {
  int64_t *cnt = calloc((size_t)nt + 1, sizeof *cnt);
  *order = malloc((size_t)(n ? n : 1) * sizeof **order);
  *uniq = malloc(((size_t)nt + 1) * sizeof **uniq);
  *grp = malloc(((size_t)nt + 1) * sizeof **grp);
  if (!cnt || !*order || !*uniq || !*grp) {
    free(cnt);
    return SM_ENOMEM;
  }
  for (int64_t k = 0; k < n; k++) cnt[key[k] + 1]++;
  for (int32_t t = 0; t < nt; t++) cnt[t + 1] += cnt[t];
  int32_t nu = 0;
  for (int32_t t = 0; t < nt; t++)
    if (cnt[t + 1] > cnt[t]) (*grp)[nu] = cnt[t], (*uniq)[nu++] = t;
  (*grp)[nu] = n;
  for (int64_t k = 0; k < n; k++) (*order)[cnt[key[k]]++] = k;
  *nuniq = nu;
  free(cnt);
  return SM_OK;
}

static int64_t count_distinct(const int32_t *v, int64_t n, unsigned char *mark, int32_t nv) {
  memset(mark, 0, (size_t)nv);
  int64_t d = 0;
  for (int64_t k = 0; k < n; k++)
    if (!mark[v[k]]) mark[v[k]] = 1, d++;
  return d;
}

/* Fills e[] from the target's edge graph; only SM_ENOMEM can go wrong here. The graph is
 * undirected, so d(t, map s) = d(map s, t): searches start from whichever side (GT target
 * or mapped vertex) has fewer distinct vertices. A constant map then costs one search. */
static int geo_compute(const edge_graph *g, const int32_t *map, const sm_gt *gt, double scale,
                       int nthreads, double *e) {
  geo_job j;
  memset(&j, 0, sizeof j);
  size_t np = (size_t)(gt->n ? gt->n : 1);
  int32_t *uniq = NULL, *mapped = malloc(np * sizeof *mapped);
  int64_t *grp = NULL, *order = NULL;
  unsigned char *mark = malloc((size_t)g->nv + 1);
  dijk_ws w;
  int rc = SM_ENOMEM, swap = 0;
  if (mapped && mark) {
    for (int64_t k = 0; k < gt->n; k++) mapped[k] = map[gt->src[k]];
    swap = count_distinct(mapped, gt->n, mark, g->nv) < count_distinct(gt->tgt, gt->n, mark, g->nv);
  }
  if (mapped && mark &&
      group_pairs(swap ? mapped : gt->tgt, gt->n, g->nv, &uniq, &j.nuniq, &grp, &order) == SM_OK &&
      ws_init(&w, g) == SM_OK) {
    j.g = g, j.uniq = uniq, j.grp = grp, j.order = order, j.need_v = swap ? gt->tgt : mapped;
    j.scale = scale, j.e = e;
    atomic_init(&j.next, 0);
    geo_parallel(&j, &w, nthreads);
    ws_free(&w);
    rc = SM_OK;
  }
  free(mapped);
  free(mark);
  free(uniq);
  free(grp);
  free(order);
  return rc;
}

int sm_geodesic_errors(const sm_mesh *target, const int32_t *map, int32_t n_source,
                       const sm_gt *gt, int nthreads, double *e, sm_error *err) {
  if (!target || !gt || (!e && gt->n > 0))
    return sm_error_set(err, SM_EINVAL, "sm_geodesic_errors: null argument");
  int rc;
  if ((rc = check_faces(target, "target", err)) ||
      (rc = check_map(map, n_source, target->nv, "map", err)) ||
      (rc = check_gt(gt, n_source, target->nv, err)))
    return rc;
  double area = sm_mesh_face_areas(target, NULL);
  if (!(area > 0)) return sm_error_set(err, SM_EEMPTY, "target has zero area");
  nthreads = nthreads <= 0 ? DEFAULT_THREADS : nthreads > MAX_THREADS ? MAX_THREADS : nthreads;
  edge_graph g;
  if ((rc = graph_build(target, &g, err))) return rc;
  if (geo_compute(&g, map, gt, 1.0 / sqrt(area), nthreads, e))
    rc = sm_error_set(err, SM_ENOMEM, "out of memory for geodesic errors (%lld pairs)",
                      (long long)gt->n);
  graph_free(&g);
  return rc;
}

/* ================================================================ summary */

double sm_metrics_threshold(int k) {
  /* numpy.linspace(0, 0.1, 41): k * step, and the last value set to the stop exactly */
  if (k >= SM_METRICS_CURVE_N - 1) return SM_METRICS_CURVE_MAX;
  return k * (SM_METRICS_CURVE_MAX / (SM_METRICS_CURVE_N - 1));
}

static int cmp_double(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

static double frac_le(const double *sorted, int64_t n, double t) {
  int64_t lo = 0, hi = n; /* first index with value > t */
  while (lo < hi) {
    int64_t mid = lo + (hi - lo) / 2;
    if (sorted[mid] <= t) lo = mid + 1;
    else hi = mid;
  }
  return (double)lo / (double)n;
}

static void summarize_sorted(const double *s, int64_t n, sm_geo_stats *o) {
  double sum = 0;
  int64_t nfin = 0;
  for (int64_t i = 0; i < n; i++)
    if (isfinite(s[i])) sum += s[i], nfin++;
  o->n_inf = n - nfin;
  o->mean = nfin ? sum / (double)nfin : NAN;
  o->max = nfin ? s[nfin - 1] : NAN; /* sorted: the finite ones come first */
  o->median = n % 2 ? s[n / 2] : 0.5 * (s[n / 2 - 1] + s[n / 2]);
  o->frac_le_0025 = frac_le(s, n, 0.025);
  o->frac_le_005 = frac_le(s, n, 0.05);
  o->frac_le_01 = frac_le(s, n, 0.1);
  double auc = 0;
  for (int k = 0; k < SM_METRICS_CURVE_N; k++) {
    o->curve[k] = frac_le(s, n, sm_metrics_threshold(k));
    if (k > 0)
      auc += 0.5 * (o->curve[k] + o->curve[k - 1]) *
             (sm_metrics_threshold(k) - sm_metrics_threshold(k - 1));
  }
  o->auc = auc / SM_METRICS_CURVE_MAX;
}

int sm_geo_summarize(const double *e, int64_t n, sm_geo_stats *out, sm_error *err) {
  if (!out || (!e && n > 0) || n < 0) return sm_error_set(err, SM_EINVAL, "sm_geo_summarize: bad argument");
  memset(out, 0, sizeof *out);
  out->n = n;
  if (n == 0) { /* numpy's mean of nothing: NaN everywhere */
    out->mean = out->median = out->max = out->auc = NAN;
    out->frac_le_0025 = out->frac_le_005 = out->frac_le_01 = NAN;
    for (int k = 0; k < SM_METRICS_CURVE_N; k++) out->curve[k] = NAN;
    return SM_OK;
  }
  double *s = malloc((size_t)n * sizeof *s);
  if (!s) return sm_error_set(err, SM_ENOMEM, "out of memory summarizing %lld errors", (long long)n);
  for (int64_t i = 0; i < n; i++) {
    if (isnan(e[i])) {
      free(s);
      return sm_error_set(err, SM_EINVAL, "geodesic error %lld is NaN", (long long)i);
    }
    s[i] = e[i];
  }
  qsort(s, (size_t)n, sizeof *s, cmp_double);
  summarize_sorted(s, n, out);
  free(s);
  return SM_OK;
}

/* ================================================================ map statistics */

/* hit[n_target] = 1 for every vertex the map reaches; returns how many, or -1 (ENOMEM). */
static int64_t mark_hits(const int32_t *map, int32_t n_source, int32_t n_target,
                         unsigned char **hit) {
  *hit = calloc((size_t)n_target, 1);
  if (!*hit) return -1;
  int64_t nhit = 0;
  for (int32_t i = 0; i < n_source; i++)
    if (!(*hit)[map[i]]) (*hit)[map[i]] = 1, nhit++;
  return nhit;
}

int sm_map_bijectivity(const int32_t *map, int32_t n_source, int32_t n_target,
                       double *bijectivity, double *distinct_over_min_n, sm_error *err) {
  if (n_source <= 0 || n_target <= 0)
    return sm_error_set(err, SM_EINVAL, "bijectivity needs non-empty meshes (%d, %d vertices)",
                        n_source, n_target);
  int rc = check_map(map, n_source, n_target, "map", err);
  if (rc) return rc;
  unsigned char *hit;
  int64_t nhit = mark_hits(map, n_source, n_target, &hit);
  free(hit);
  if (nhit < 0) return sm_error_set(err, SM_ENOMEM, "out of memory (%d target vertices)", n_target);
  if (bijectivity) *bijectivity = (double)nhit / n_target;
  if (distinct_over_min_n)
    *distinct_over_min_n = (double)nhit / (n_source < n_target ? n_source : n_target);
  return SM_OK;
}

int sm_map_coverage(const sm_mesh *target, const int32_t *map, int32_t n_source,
                    double *coverage, sm_error *err) {
  if (!target || !coverage) return sm_error_set(err, SM_EINVAL, "sm_map_coverage: null argument");
  int rc;
  if ((rc = check_faces(target, "target", err)) ||
      (rc = check_map(map, n_source, target->nv, "map", err)))
    return rc;
  double *mass = malloc((size_t)(target->nv ? target->nv : 1) * sizeof *mass);
  unsigned char *hit = NULL;
  if (!mass || mark_hits(map, n_source, target->nv, &hit) < 0) {
    free(mass);
    free(hit);
    return sm_error_set(err, SM_ENOMEM, "out of memory (%d target vertices)", target->nv);
  }
  /* zero-area faces add no mass here; eval_map.py would turn them into NaN */
  sm_mesh_lumped_mass(target, mass);
  double all = 0, got = 0;
  for (int32_t v = 0; v < target->nv; v++) {
    all += mass[v];
    if (hit[v]) got += mass[v];
  }
  free(mass);
  free(hit);
  if (!(all > 0)) return sm_error_set(err, SM_EEMPTY, "target has zero area");
  *coverage = got / all;
  return SM_OK;
}

int sm_map_cycle_error(const int32_t *t_xy, int32_t nx, const int32_t *t_yx, int32_t ny,
                       double *frac, sm_error *err) {
  if (!frac || nx <= 0 || ny <= 0)
    return sm_error_set(err, SM_EINVAL, "sm_map_cycle_error: bad argument (nx=%d, ny=%d)", nx, ny);
  int rc;
  if ((rc = check_map(t_xy, nx, ny, "t_xy", err)) || (rc = check_map(t_yx, ny, nx, "t_yx", err)))
    return rc;
  int64_t bad = 0;
  for (int32_t i = 0; i < nx; i++) bad += t_yx[t_xy[i]] != i;
  *frac = (double)bad / nx;
  return SM_OK;
}

/* ================================================================ chamfer (k-d tree) */

/* Implicit balanced k-d tree: node [lo, hi) splits at mid = lo + (hi - lo) / 2 along
 * dim[mid] at value split[mid]; idx[lo, mid) have coordinate <= split, idx[mid, hi) >= it.
 * The value is stored because building the right child reorders idx[mid, hi). Internal
 * nodes (more than KD_LEAF points) have distinct mids, so no node array is needed. */
#define KD_LEAF 8

typedef struct kdtree {
  const double *P;
  int64_t *idx;
  unsigned char *dim;
  double *split;
} kdtree;

static double coord(const kdtree *t, int64_t i, int d) { return t->P[3 * t->idx[i] + d]; }

/* Hoare quickselect: puts the k-th smallest (along d) of idx[lo, hi] at k. */
static void kd_select(kdtree *t, int d, int64_t lo, int64_t hi, int64_t k) {
  while (hi > lo) {
    double pv = coord(t, lo + (hi - lo) / 2, d);
    int64_t i = lo, j = hi;
    while (i <= j) {
      while (coord(t, i, d) < pv) i++;
      while (coord(t, j, d) > pv) j--;
      if (i <= j) {
        int64_t s = t->idx[i];
        t->idx[i++] = t->idx[j];
        t->idx[j--] = s;
      }
    }
    if (k <= j) hi = j;
    else if (k >= i) lo = i;
    else return;
  }
}

static void kd_build(kdtree *t, int64_t lo, int64_t hi) {
  if (hi - lo <= KD_LEAF) return;
  double mn[3] = {INFINITY, INFINITY, INFINITY}, mx[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (int64_t i = lo; i < hi; i++)
    for (int d = 0; d < 3; d++) {
      double c = coord(t, i, d);
      if (c < mn[d]) mn[d] = c;
      if (c > mx[d]) mx[d] = c;
    }
  int d = 0; /* split the widest extent: keeps cells compact on surface samples */
  for (int k = 1; k < 3; k++)
    if (mx[k] - mn[k] > mx[d] - mn[d]) d = k;
  int64_t mid = lo + (hi - lo) / 2;
  kd_select(t, d, lo, hi - 1, mid);
  t->dim[mid] = (unsigned char)d;
  t->split[mid] = coord(t, mid, d);
  kd_build(t, lo, mid);
  kd_build(t, mid, hi);
}

static void kd_nearest(const kdtree *t, const double *q, int64_t lo, int64_t hi, double *best) {
  if (hi - lo <= KD_LEAF) {
    for (int64_t i = lo; i < hi; i++) {
      const double *p = t->P + 3 * t->idx[i];
      double dx = p[0] - q[0], dy = p[1] - q[1], dz = p[2] - q[2];
      double d2 = dx * dx + dy * dy + dz * dz;
      if (d2 < *best) *best = d2;
    }
    return;
  }
  int64_t mid = lo + (hi - lo) / 2;
  double diff = q[t->dim[mid]] - t->split[mid];
  if (diff < 0) {
    kd_nearest(t, q, lo, mid, best);
    if (diff * diff < *best) kd_nearest(t, q, mid, hi, best);
  } else {
    kd_nearest(t, q, mid, hi, best);
    if (diff * diff < *best) kd_nearest(t, q, lo, mid, best);
  }
}

/* mean over Q of the distance to the nearest point of P; -1 on ENOMEM. */
static double mean_nn(const double *P, int64_t np, const double *Q, int64_t nq) {
  kdtree t = {P, malloc((size_t)np * sizeof(int64_t)), calloc((size_t)np, 1),
              calloc((size_t)np, sizeof(double))};
  double sum = 0;
  if (!t.idx || !t.dim || !t.split) {
    sum = -1;
    goto out;
  }
  for (int64_t i = 0; i < np; i++) t.idx[i] = i;
  kd_build(&t, 0, np);
  for (int64_t i = 0; i < nq; i++) {
    double best = INFINITY;
    kd_nearest(&t, Q + 3 * i, 0, np, &best);
    sum += sqrt(best);
  }
  sum /= (double)nq;
out:
  free(t.idx);
  free(t.dim);
  free(t.split);
  return sum;
}

int sm_chamfer(const double *A, int64_t na, const double *B, int64_t nb, double *a_to_b,
               double *b_to_a, sm_error *err) {
  if (!A || !B || na <= 0 || nb <= 0 || !a_to_b || !b_to_a)
    return sm_error_set(err, SM_EINVAL, "sm_chamfer: empty or null point set (%lld, %lld points)",
                        (long long)na, (long long)nb);
  for (int64_t i = 0; i < 3 * na; i++)
    if (!isfinite(A[i])) return sm_error_set(err, SM_ENONFINITE, "chamfer: point %lld of A is not finite", (long long)(i / 3));
  for (int64_t i = 0; i < 3 * nb; i++)
    if (!isfinite(B[i])) return sm_error_set(err, SM_ENONFINITE, "chamfer: point %lld of B is not finite", (long long)(i / 3));
  *a_to_b = mean_nn(B, nb, A, na);
  *b_to_a = mean_nn(A, na, B, nb);
  if (*a_to_b < 0 || *b_to_a < 0)
    return sm_error_set(err, SM_ENOMEM, "out of memory for chamfer (%lld, %lld points)",
                        (long long)na, (long long)nb);
  return SM_OK;
}

/* ================================================================ Dirichlet energy */

static void sub3(const double *a, const double *b, double *o) {
  o[0] = a[0] - b[0], o[1] = a[1] - b[1], o[2] = a[2] - b[2];
}

static double dot3(const double *a, const double *b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static double cross_norm(const double *a, const double *b) {
  double x = a[1] * b[2] - a[2] * b[1], y = a[2] * b[0] - a[0] * b[2], z = a[0] * b[1] - a[1] * b[0];
  return sqrt(x * x + y * y + z * z);
}

/* Sum over the corners o of face f of cot(o)/2 |Y[map p] - Y[map q]|^2 (p, q: the other
 * two corners). Summing per corner equals summing w_ij per unique edge, as eval_map.py's
 * cot_edge_weights does after merging duplicates. */
static double face_dirichlet(const sm_mesh *S, int64_t f, const double *Y, const int32_t *map) {
  const int32_t *t = S->F + 3 * f;
  double sum = 0;
  for (int c = 0; c < 3; c++) {
    int32_t o = t[c], p = t[(c + 1) % 3], q = t[(c + 2) % 3];
    double a[3], b[3], d[3];
    sub3(S->V + 3 * (int64_t)p, S->V + 3 * (int64_t)o, a);
    sub3(S->V + 3 * (int64_t)q, S->V + 3 * (int64_t)o, b);
    double cn = cross_norm(a, b);
    if (!(cn > 0)) return 0; /* zero-area face: no cotangents (eval_map.py: NaN) */
    int32_t yp = map ? map[p] : p, yq = map ? map[q] : q;
    sub3(Y + 3 * (int64_t)yp, Y + 3 * (int64_t)yq, d);
    sum += 0.5 * dot3(a, b) / cn * dot3(d, d);
  }
  return sum;
}

int sm_map_dirichlet(const sm_mesh *source, const sm_mesh *target, const int32_t *map,
                     double *energy, sm_error *err) {
  if (!source || !energy || (!target) != (!map))
    return sm_error_set(err, SM_EINVAL, "sm_map_dirichlet: bad argument");
  int rc;
  if ((rc = check_faces(source, "source", err))) return rc;
  const sm_mesh *Y = target ? target : source;
  if (target && ((rc = check_faces(target, "target", err)) ||
                 (rc = check_map(map, source->nv, target->nv, "map", err))))
    return rc;
  double area = sm_mesh_face_areas(Y, NULL);
  if (!(area > 0)) return sm_error_set(err, SM_EEMPTY, "%s has zero area", target ? "target" : "source");
  double sum = 0;
  for (int64_t f = 0; f < source->nf; f++) sum += face_dirichlet(source, f, Y->V, map);
  *energy = sum / area; /* Y scaled by 1/sqrt(area): squared differences scale by 1/area */
  return SM_OK;
}

/* ================================================================ all metrics */

static double now_seconds(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static int metrics_geodesic(const sm_mesh *target, const int32_t *map, int32_t ns,
                            const sm_gt *gt, int nthreads, sm_metrics *o, sm_error *err) {
  if (!gt) return sm_geo_summarize(NULL, 0, &o->geo, err);
  double *e = malloc((size_t)(gt->n ? gt->n : 1) * sizeof *e);
  if (!e) return sm_error_set(err, SM_ENOMEM, "out of memory for %lld GT pairs", (long long)gt->n);
  double t0 = now_seconds();
  int rc = sm_geodesic_errors(target, map, ns, gt, nthreads, e, err);
  o->geodesic_seconds = now_seconds() - t0;
  if (!rc) rc = sm_geo_summarize(e, gt->n, &o->geo, err);
  free(e);
  return rc;
}

/* Chamfer between the mapped points and the target, both scaled to unit target area. */
static int metrics_chamfer(const sm_mesh *target, const int32_t *map, int32_t ns,
                           sm_metrics *o, sm_error *err) {
  double s = 1.0 / sqrt(o->area_target);
  double *A = malloc((size_t)ns * 3 * sizeof *A), *B = malloc((size_t)target->nv * 3 * sizeof *B);
  int rc = SM_OK;
  if (!A || !B) rc = sm_error_set(err, SM_ENOMEM, "out of memory for chamfer");
  for (int64_t i = 0; !rc && i < 3 * (int64_t)target->nv; i++) B[i] = s * target->V[i];
  for (int32_t i = 0; !rc && i < ns; i++) memcpy(A + 3 * (int64_t)i, B + 3 * (int64_t)map[i], 3 * sizeof *A);
  if (!rc) rc = sm_chamfer(A, ns, B, target->nv, &o->chamfer_map_to_target, &o->chamfer_target_to_map, err);
  o->chamfer = o->chamfer_map_to_target + o->chamfer_target_to_map;
  free(A);
  free(B);
  return rc;
}

static int metrics_dirichlet(const sm_mesh *source, const sm_mesh *target, const int32_t *map,
                             const sm_gt *gt, sm_metrics *o, sm_error *err) {
  int rc;
  if ((rc = sm_map_dirichlet(source, target, map, &o->dirichlet, err)) ||
      (rc = sm_map_dirichlet(source, NULL, NULL, &o->dirichlet_source_identity, err)))
    return rc;
  o->dirichlet_gt = NAN;
  if (!gt || gt->n != source->nv) return SM_OK;
  int32_t *dense = malloc((size_t)source->nv * sizeof *dense);
  if (!dense) return sm_error_set(err, SM_ENOMEM, "out of memory (%d source vertices)", source->nv);
  if (sm_gt_is_dense(gt, source->nv, dense))
    rc = sm_map_dirichlet(source, target, dense, &o->dirichlet_gt, err);
  free(dense);
  return rc;
}

int sm_metrics_compute(const sm_mesh *source, const sm_mesh *target, const int32_t *map,
                       const sm_gt *gt, int nthreads, sm_metrics *out, sm_error *err) {
  if (!source || !target || !map || !out)
    return sm_error_set(err, SM_EINVAL, "sm_metrics_compute: null argument");
  memset(out, 0, sizeof *out);
  int rc;
  if ((rc = sm_mesh_validate(source, err)) || (rc = sm_mesh_validate(target, err)) ||
      (rc = check_map(map, source->nv, target->nv, "map", err)) ||
      (gt && (rc = check_gt(gt, source->nv, target->nv, err))))
    return rc;
  out->n_source = source->nv;
  out->n_target = target->nv;
  out->area_target = sm_mesh_face_areas(target, NULL);
  if (!(out->area_target > 0)) return sm_error_set(err, SM_EEMPTY, "target has zero area");
  if ((rc = metrics_geodesic(target, map, source->nv, gt, nthreads, out, err)) ||
      (rc = sm_map_bijectivity(map, source->nv, target->nv, &out->bijectivity,
                               &out->distinct_over_min_n, err)) ||
      (rc = sm_map_coverage(target, map, source->nv, &out->coverage, err)) ||
      (rc = metrics_chamfer(target, map, source->nv, out, err)) ||
      (rc = metrics_dirichlet(source, target, map, gt, out, err)))
    return rc;
  return SM_OK;
}
