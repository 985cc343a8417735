/* Worker-side request execution: see sm_srv_exec.h. */
#include "sm_srv_exec.h"

#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "sm_distance.h"
#include "sm_proto.h"
#include "sm_shell.h"
#include "sm_srv_job.h"
#include "sm_srv_log.h"
#include "sm_srv_metrics.h"
#include "sm_srv_store.h"

/* The outcome of one operation: an OK payload or an error. */
typedef struct result {
  uint16_t status;
  uint8_t *payload; /* OK: malloc'd response payload, with SM_PROTO_HEADER_LEN bytes of
                       room before it (payload = base + 24) */
  uint8_t *base;
  size_t len;
  uint32_t retry, detail;
  char msg[300];
} result;

static int fail(result *r, uint16_t st, uint32_t detail, const char *fmt, ...)
    __attribute__((format(printf, 4, 5)));
static int fail(result *r, uint16_t st, uint32_t detail, const char *fmt, ...) {
  r->status = st;
  r->detail = detail;
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(r->msg, sizeof r->msg, fmt, ap);
  va_end(ap);
  return -1;
}

/* Allocates room for a payload of n bytes (plus header room and a CRC trailer slot). */
static uint8_t *room(result *r, size_t n) {
  r->base = malloc(SM_PROTO_HEADER_LEN + n + 4);
  if (!r->base) return NULL;
  r->payload = r->base + SM_PROTO_HEADER_LEN;
  r->len = n;
  return r->payload;
}

static int cancel_cb(void *ud) {
  sm_job *j = ud;
  for (sm_job *a = j; a; a = a->parent) /* a unit also stops with its request */
    if (atomic_load_explicit(&a->cancel, memory_order_relaxed)) return 1;
  if (j->deadline_ns && sm_srv_now_ns() > j->deadline_ns) {
    atomic_store_explicit(&j->deadline_hit, 1, memory_order_relaxed);
    return 1;
  }
  return 0;
}

/* Maps a core/store error to a status. */
static int fail_core(result *r, sm_job *j, int code, const sm_error *err, const char *what) {
  uint16_t st;
  switch (code) {
  case SM_STORE_ENOTFOUND: st = SM_ST_NOT_FOUND; break;
  case SM_STORE_EIDMISMATCH: st = SM_ST_ID_MISMATCH; break;
  case SM_ELIMIT: st = SM_ST_LIMIT_EXCEEDED; break;
  case SM_EFORMAT: st = SM_ST_DECODE_FAILED; break;
  case SM_EUNSUPPORTED:
  case SM_EEMPTY:
  case SM_ENONFINITE: st = SM_ST_MESH_REJECTED; break;
  case SM_EINVAL:
  case SM_ERANGE: st = SM_ST_BAD_REQUEST; break;
  case SM_ECANCELED: st = j->deadline_hit ? SM_ST_DEADLINE : SM_ST_CANCELLED; break;
  default: st = SM_ST_INTERNAL; break;
  }
  if (st == SM_ST_INTERNAL)
    sm_log("error", "request failed", " rid=%u what=%s code=%d err=\"%s\"", j->rid, what,
           code, err->msg);
  return fail(r, st, 0, "%s: %s", what, err->msg[0] ? err->msg : sm_strerror(code));
}

static uint64_t s_to_us(double s) { return s > 0 ? (uint64_t)(s * 1e6) : 0; }

/* ------------------------------------------------------------------ preparation */

/* The preparation bound (--prepare-timeout-ms) on top of the request's own cancel and
 * deadline: acquiring a shape may compute its bases, or wait for the worker that does,
 * and no single shape may hold a worker past the bound, whatever the client asked. */
typedef struct prep_guard {
  sm_job *j;
  uint64_t until_ns; /* 0 = unbounded */
  int hit;
} prep_guard;

static int prep_cancel_cb(void *ud) {
  prep_guard *g = ud;
  if (cancel_cb(g->j)) return 1;
  if (g->until_ns && sm_srv_now_ns() > g->until_ns) {
    g->hit = 1;
    return 1;
  }
  return 0;
}

/* A failed preparation as a status whose message names the shape: not stored (or found
 * damaged) = NOT_FOUND with detail nf_detail; past the bound = LIMIT_EXCEEDED; a shape the
 * solvers cannot handle = MESH_REJECTED; a k the shape is too small for = BAD_REQUEST. */
static int fail_prepare(result *r, sm_job *j, int rc, const sm_error *err, const char *what,
                        const uint8_t id[32], uint32_t nf_detail, const prep_guard *g) {
  char hex[65];
  sm_hex(id, 32, hex);
  const char *msg = err->msg[0] ? err->msg : sm_strerror(rc);
  uint32_t bound = j->srv->cfg.prepare_timeout_ms;
  if (rc == SM_STORE_ENOTFOUND)
    return fail(r, SM_ST_NOT_FOUND, nf_detail, "%s: shape %s: %s", what, hex, msg);
  if (rc == SM_ECANCELED && g->hit)
    return fail(r, SM_ST_LIMIT_EXCEEDED, bound,
                "%s: shape %s: preparation stopped at the daemon's bound of %u ms "
                "(--prepare-timeout-ms)", what, hex, bound);
  if (rc == SM_ENUMERIC || rc == SM_EUNSUPPORTED || rc == SM_EEMPTY || rc == SM_EFORMAT)
    return fail(r, SM_ST_MESH_REJECTED, 0, "%s: shape %s cannot be prepared: %s", what, hex, msg);
  if (rc == SM_EINVAL || rc == SM_ERANGE)
    return fail(r, SM_ST_BAD_REQUEST, 0, "%s: shape %s: %s", what, hex, msg);
  char full[160];
  snprintf(full, sizeof full, "%s: shape %s", what, hex);
  return fail_core(r, j, rc, err, full);
}

/* sm_store_acquire under the bound; r filled on failure (see fail_prepare). raw: the
 * shape decoded by this request's PUT, or NULL. */
static int acquire_raw(sm_job *j, const uint8_t id[32], const sm_store_key *k,
                       const sm_mesh *raw, const char *what, uint32_t nf_detail,
                       sm_prepared **out, sm_store_prep_info *info, result *r) {
  uint32_t bound = j->srv->cfg.prepare_timeout_ms;
  prep_guard g = {j, bound ? sm_srv_now_ns() + (uint64_t)bound * 1000000ull : 0, 0};
  sm_error err;
  sm_error_clear(&err);
  int rc = sm_store_acquire_ex(j->srv->store, id, k, raw, 0, prep_cancel_cb, &g, out, info,
                               &err);
  return rc ? fail_prepare(r, j, rc, &err, what, id, nf_detail, &g) : 0;
}

static int acquire(sm_job *j, const uint8_t id[32], const sm_store_key *k, const char *what,
                   uint32_t nf_detail, sm_prepared **out, sm_store_prep_info *info,
                   result *r) {
  return acquire_raw(j, id, k, NULL, what, nf_detail, out, info, r);
}

static sm_store_key default_key(const sm_server *s) {
  return sm_store_key_make(s->cfg.default_k, s->cfg.default_k, SM_SHELL_DEFAULT_ETA);
}

/* ------------------------------------------------------------------ PUT_SHAPE */

/* Background preparation after PUT_SHAPE (--prepare-on-put, PROTOCOL.md 5.4): whoever
 * stores a shape will match it, so its preparation starts as soon as it is stored
 * instead of inside the first MATCH. It is a background pool job (sm_srv_pool.h): it runs
 * only when no request waits for a worker and on at most threads - 1 workers, so
 * requests always keep one; a request that needs the shape meanwhile either waits for it
 * (the store's single-flight) or, when the job has not started yet, computes it itself
 * (the job then finds it cached). The queue is bounded (--queue; past it PUT only stores,
 * counted put_prepares_skipped). The job gets the mesh the PUT decoded, so the shape is
 * decoded once (the memory held that way by queued jobs is bounded by BG_MESH_BYTES; past
 * it a job decodes the file again). The key is the one a default MATCH involving the
 * shape will need: the default bases at full resolution, or on the coarse level when the
 * shape alone sends MATCH to the multi-resolution path (sm_multires_wanted). A failure is
 * kept by the store and reported by the next request for that key
 * (sm_store_acquire_ex); the bound --prepare-timeout-ms applies; at shutdown the queued
 * jobs end at once and the running ones are cancelled (sm_server.bg_stop). */
typedef struct bg_prep {
  sm_pool_job base; /* first member */
  sm_server *srv;
  uint8_t id[32];
  sm_store_key key;
  sm_mesh *raw;      /* owned; NULL: read and decoded from the file */
  uint64_t raw_bytes; /* charged to bg_mesh_bytes */
  uint64_t until_ns; /* --prepare-timeout-ms, from the job's start; 0 = none */
} bg_prep;

#define BG_MESH_BYTES (256ull << 20)
/* The most threads one MATCH or DISTANCE runs on when the pool has idle cores to lend: the
 * tip search refines its 4 hypotheses at once (sm_match_opts.ext_hypotheses), beyond that
 * the refinement's neighbour queries gain little. */
#define SM_SRV_MATCH_THREADS 4
static _Atomic uint64_t bg_mesh_bytes;

static int bg_cancel_cb(void *ud) {
  const bg_prep *b = ud;
  return atomic_load_explicit(&b->srv->bg_stop, memory_order_relaxed) ||
         (b->until_ns && sm_srv_now_ns() > b->until_ns);
}

static void bg_run(sm_pool_job *pj) {
  bg_prep *b = (bg_prep *)pj;
  sm_store *st = b->srv->store;
  char hex[65];
  sm_hex(b->id, 32, hex);
  if (atomic_load(&b->srv->bg_stop)) {
    sm_met_add(&sm_met.bg_cancelled, 1);
  } else if (!sm_store_cached(st, b->id, &b->key)) {
    uint32_t bound = b->srv->cfg.prepare_timeout_ms;
    b->until_ns = bound ? sm_srv_now_ns() + (uint64_t)bound * 1000000ull : 0;
    sm_prepared *pr = NULL;
    sm_store_prep_info info;
    sm_error err;
    sm_error_clear(&err);
    int rc = sm_store_acquire_ex(st, b->id, &b->key, b->raw, 1, bg_cancel_cb, b, &pr, &info,
                                 &err);
    if (rc == SM_ECANCELED) {
      sm_met_add(&sm_met.bg_cancelled, 1);
    } else if (rc) {
      sm_met_add(&sm_met.bg_failed, 1);
      sm_log("warn", "background preparation failed", " id=%s code=%d err=\"%s\"", hex, rc,
             err.msg);
    } else if (!info.cached && !info.waited) {
      sm_met_add(&sm_met.bg_prepared, 1);
      sm_log("info", "background preparation done", " id=%s computed=%d loaded=%d", hex,
             info.bases_computed, info.bases_loaded);
    }
    sm_store_release(st, pr);
  }
  atomic_fetch_sub(&bg_mesh_bytes, b->raw_bytes);
  sm_mesh_destroy(b->raw);
  free(b);
}

static uint64_t mesh_bytes(const sm_mesh *m) {
  return (uint64_t)m->nv * 3 * sizeof(double) + (uint64_t)m->nf * 3 * sizeof(int32_t);
}

/* Queues id's background preparation; takes raw (may be NULL). */
static void bg_schedule(sm_job *j, const uint8_t id[32], uint32_t nv, sm_mesh *raw) {
  sm_server *s = j->srv;
  bg_prep *b = s->cfg.prepare_on_put ? calloc(1, sizeof *b) : NULL;
  if (!b) {
    sm_mesh_destroy(raw);
    return;
  }
  b->base.run = bg_run;
  b->srv = s;
  memcpy(b->id, id, 32);
  b->key = default_key(s);
  sm_multires_opts mo;
  sm_multires_opts_default(&mo);
  if (sm_multires_wanted(&mo, (int32_t)nv, 0))
    b->key = sm_store_key_multires(&b->key, s->cfg.multires_coarse_nv);
  if (raw) {
    uint64_t sz = mesh_bytes(raw);
    if (atomic_fetch_add(&bg_mesh_bytes, sz) + sz <= BG_MESH_BYTES) {
      b->raw = raw;
      b->raw_bytes = sz;
    } else {
      atomic_fetch_sub(&bg_mesh_bytes, sz);
      sm_mesh_destroy(raw);
    }
  }
  if (sm_store_cached(s->store, id, &b->key) || sm_pool_submit_bg(s->pool, &b->base)) {
    if (!sm_store_cached(s->store, id, &b->key)) sm_met_add(&sm_met.bg_skipped, 1);
    atomic_fetch_sub(&bg_mesh_bytes, b->raw_bytes);
    sm_mesh_destroy(b->raw);
    free(b);
    return;
  }
  sm_met_add(&sm_met.bg_queued, 1);
}

static int op_put(sm_job *j, const uint8_t *p, size_t n, result *r) {
  sm_proto_put_req q;
  int rc = sm_proto_dec_put_req(p, n, &q);
  if (rc) return fail(r, SM_ST_BAD_REQUEST, 0, "PUT_SHAPE: %s", sm_proto_strerror(rc));
  sm_error err;
  sm_error_clear(&err);
  uint32_t nv = 0, nf = 0;
  int existed = 0;
  sm_mesh *raw = NULL; /* decoded by the store for a new shape: prepared from it */
  rc = sm_store_put(j->srv->store, q.id, q.draco, q.draco_len, &nv, &nf, &existed, &raw, &err);
  if (rc == SM_ELIMIT)
    return fail(r, SM_ST_LIMIT_EXCEEDED, j->srv->cfg.max_vertices, "PUT_SHAPE: %s", err.msg);
  if (rc == SM_STORE_ECOMPONENTS)
    return fail(r, SM_ST_LIMIT_EXCEEDED, j->srv->cfg.max_components, "PUT_SHAPE: %s", err.msg);
  if (rc) return fail_core(r, j, rc, &err, "PUT_SHAPE");
  char hex[65];
  sm_hex(q.id, 32, hex);
  if (!existed) sm_log("info", "shape stored", " id=%s vertices=%u faces=%u bytes=%u", hex, nv, nf, q.draco_len);
  if (q.flags & SM_PUT_F_PREPARE) {
    sm_store_key k = default_key(j->srv);
    sm_prepared *pr = NULL;
    sm_store_prep_info info;
    result pre;
    memset(&pre, 0, sizeof pre);
    if (acquire_raw(j, q.id, &k, raw, "PUT_SHAPE prepare", 0, &pr, &info, &pre))
      sm_log("warn", "prepare after put failed", " id=%s status=%u err=\"%s\"", hex,
             pre.status, pre.msg);
    sm_store_release(j->srv->store, pr);
    sm_mesh_destroy(raw);
  } else {
    uint32_t hv, hf;
    int prepared = 0; /* a stored shape's default bases in memory or on disk */
    if (existed) sm_store_has(j->srv->store, q.id, &hv, &hf, &prepared);
    if (!prepared) bg_schedule(j, q.id, nv, raw);
    else sm_mesh_destroy(raw);
  }
  sm_proto_put_resp o = {.n_vertices = nv, .n_faces = nf, .flags = existed ? SM_PUT_R_EXISTED : 0};
  memcpy(o.id, q.id, 32);
  if (!room(r, 44)) return fail(r, SM_ST_INTERNAL, 0, "out of memory");
  sm_proto_enc_put_resp(r->payload, 44, NULL, &o);
  return 0;
}

/* ------------------------------------------------------------------ PREPARE */

static int op_prepare(sm_job *j, const uint8_t *p, size_t n, result *r) {
  sm_proto_prepare_req q;
  int rc = sm_proto_dec_prepare_req(p, n, &q);
  if (rc) return fail(r, SM_ST_BAD_REQUEST, 0, "PREPARE: %s", sm_proto_strerror(rc));
  const sm_srv_config *cfg = &j->srv->cfg;
  sm_store_key k = sm_store_key_make(q.k_lb ? q.k_lb : cfg->default_k,
                                     q.k_elastic ? q.k_elastic : cfg->default_k,
                                     q.eta != 0 ? q.eta : SM_SHELL_DEFAULT_ETA);
  if ((uint32_t)sm_store_key_k(&k, SM_BASIS_LB) > cfg->max_k ||
      (uint32_t)sm_store_key_k(&k, SM_BASIS_ELASTIC) > cfg->max_k)
    return fail(r, SM_ST_LIMIT_EXCEEDED, cfg->max_k, "PREPARE: k above max_k = %u", cfg->max_k);
  sm_prepared *pr = NULL;
  sm_store_prep_info info;
  if (acquire(j, q.id, &k, "PREPARE", 0, &pr, &info, r)) return -1;
  const sm_shape *s = sm_prepared_shape(pr);
  sm_proto_prepare_resp o = {
      .n_vertices = (uint32_t)s->mesh->nv, .n_faces = (uint32_t)s->mesh->nf,
      .k_lb = (uint16_t)s->lb->k, .k_elastic = (uint16_t)(s->elastic ? s->elastic->k : 0),
      .flags = info.cached ? SM_PREP_R_CACHED : 0, .t_clean_us = info.t_clean_us,
      .t_lb_us = sm_store_info_basis_us(&info, &k, SM_BASIS_LB),
      .t_elastic_us = sm_store_info_basis_us(&info, &k, SM_BASIS_ELASTIC),
      .t_desc_us = info.t_desc_us};
  sm_store_release(j->srv->store, pr);
  if (!room(r, 48)) return fail(r, SM_ST_INTERNAL, 0, "out of memory");
  sm_proto_enc_prepare_resp(r->payload, 48, NULL, &o);
  return 0;
}

/* ------------------------------------------------------------------ MATCH / DISTANCE */

/* Options and bases key from a MATCH/DISTANCE request: the defaults (a DISTANCE's:
 * sm_distance_match_opts), then what the request sets. */
static int match_opts(sm_job *j, uint8_t opcode, const sm_proto_match_req *q,
                      sm_match_opts *mo, sm_store_key *key, result *r) {
  const sm_srv_config *cfg = &j->srv->cfg;
  sm_match_opts_default(mo);
  mo->k1 = cfg->default_k < mo->k1 ? cfg->default_k : mo->k1; /* server default k1 */
  if (opcode == SM_OP_DISTANCE) sm_distance_match_opts(mo); /* MATCH keeps its mirror check */
  if (q->basis) mo->basis = q->basis;
  if (q->init) mo->init = q->init;
  if (q->k0) mo->k0 = q->k0;
  if (q->k1) mo->k1 = q->k1;
  if (q->step) mo->step = q->step;
  if (q->flags & SM_MATCH_F_SINKHORN_LEVELS) mo->sinkhorn_levels = q->sinkhorn_levels;
  if (q->flags & SM_MATCH_F_SINGLE_START) mo->multi_start = 0;
  if (q->flags & SM_MATCH_F_MULTI_START) mo->multi_start = 1;
  if ((uint32_t)mo->k1 > cfg->max_k)
    return fail(r, SM_ST_LIMIT_EXCEEDED, cfg->max_k, "k1 = %d above max_k = %u", mo->k1,
                cfg->max_k);
  if (mo->k0 > mo->k1)
    return fail(r, SM_ST_BAD_REQUEST, 0, "k0 = %d > k1 = %d", mo->k0, mo->k1);
  int kb = mo->k1 > (int)cfg->default_k ? mo->k1 : (int)cfg->default_k;
  *key = sm_store_key_make(kb, kb, q->eta != 0 ? q->eta : SM_SHELL_DEFAULT_ETA);
  mo->cancel = cancel_cb;
  mo->cancel_ud = j;
  return 0;
}

typedef struct pair_ctx {
  sm_prepared *px, *py;
  sm_store_prep_info ix, iy;
  int32_t *lm, *init;
} pair_ctx;

static void pair_free(sm_job *j, pair_ctx *c) {
  sm_store_release(j->srv->store, c->px);
  sm_store_release(j->srv->store, c->py);
  free(c->lm);
  free(c->init);
}

/* The two shapes of a pair are prepared at once when neither is in the memory cache: a
 * cold MATCH of two new shapes would otherwise take the sum of two preparations. y's
 * acquire becomes a job on the pool (side_acq), which an idle worker takes while this one
 * acquires x; whoever comes first claims it, so when no worker has taken it by the time x
 * is ready this worker runs it itself: the pair never waits on a busy pool, and the pool's
 * size still bounds the preparations running at once. Single-flight is the store's, as
 * for any acquire; errors name x before y as when they ran in turn (y's is reported only
 * when x succeeded; when x fails, y is cancelled if it is running, never started if not).
 * The job and the request share the struct (refs); a job that finds it claimed by the
 * request's worker only drops its reference and touches nothing of the request, which
 * may be gone by then. */
typedef struct side_acq {
  sm_pool_job base; /* first member */
  pthread_mutex_t mu;
  pthread_cond_t cv;
  int state; /* SIDE_QUEUED, SIDE_RUNNING, SIDE_DONE */
  int refs;
  sm_job uj; /* the unit's context: own deadline flag, parent = the request */
  const uint8_t *id;
  const sm_store_key *key;
  sm_prepared *p;
  sm_store_prep_info info;
  int rc;
  result r;
} side_acq;

enum { SIDE_QUEUED, SIDE_RUNNING, SIDE_DONE };

static void unit_job(sm_job *uj, sm_job *parent);

static void side_unref(side_acq *a) {
  pthread_mutex_lock(&a->mu);
  int last = --a->refs == 0;
  pthread_mutex_unlock(&a->mu);
  if (!last) return;
  pthread_mutex_destroy(&a->mu);
  pthread_cond_destroy(&a->cv);
  free(a);
}

/* Claims a queued side acquire (1) or not (0: taken by the other side, or skipped). */
static int side_claim(side_acq *a) {
  pthread_mutex_lock(&a->mu);
  int mine = a->state == SIDE_QUEUED;
  if (mine) a->state = SIDE_RUNNING;
  pthread_mutex_unlock(&a->mu);
  return mine;
}

/* Runs a claimed side acquire (or, skip, only marks it done) and wakes the request. */
static void side_run(side_acq *a, int skip) {
  if (!skip) a->rc = acquire(&a->uj, a->id, a->key, "y", 1, &a->p, &a->info, &a->r);
  pthread_mutex_lock(&a->mu);
  a->state = SIDE_DONE;
  pthread_cond_broadcast(&a->cv);
  pthread_mutex_unlock(&a->mu);
}

static void side_job(sm_pool_job *pj) {
  side_acq *a = (side_acq *)pj;
  if (side_claim(a)) side_run(a, 0);
  side_unref(a);
}

/* y's acquire queued on the pool, or NULL (then the caller acquires y itself). */
static side_acq *side_start(sm_job *j, const uint8_t *y, const sm_store_key *key) {
  side_acq *a = calloc(1, sizeof *a);
  if (!a) return NULL;
  if (pthread_mutex_init(&a->mu, NULL)) {
    free(a);
    return NULL;
  }
  if (pthread_cond_init(&a->cv, NULL)) {
    pthread_mutex_destroy(&a->mu);
    free(a);
    return NULL;
  }
  a->base.run = side_job;
  a->state = SIDE_QUEUED;
  a->refs = 2; /* the request and the queued job */
  unit_job(&a->uj, j);
  a->id = y;
  a->key = key;
  /* Forced like a fan-out runner: the request was admitted; this is its bounded part. */
  if (sm_pool_submit_force(j->srv->pool, &a->base)) {
    a->refs = 1;
    side_unref(a);
    return NULL;
  }
  return a;
}

static int acquire_pair(sm_job *j, const uint8_t *x, const uint8_t *y, const sm_store_key *key,
                        pair_ctx *c, result *r) {
  sm_store *st = j->srv->store;
  side_acq *a = NULL;
  if (memcmp(x, y, 32) && sm_pool_threads(j->srv->pool) > 1 && !sm_store_cached(st, x, key) &&
      !sm_store_cached(st, y, key))
    a = side_start(j, y, key);
  /* x computed elsewhere (PUT's background preparation, another request): this worker
   * would only wait for it, so it takes y first; x's error still comes first. */
  if (a && sm_store_busy(st, x, key) && side_claim(a)) side_run(a, 0);
  int fx = acquire(j, x, key, "x", 0, &c->px, &c->ix, r);
  if (!a) return fx ? -1 : acquire(j, y, key, "y", 1, &c->py, &c->iy, r);
  if (fx) atomic_store(&a->uj.cancel, 1); /* the pair has failed: y is not needed */
  if (side_claim(a)) side_run(a, fx);
  pthread_mutex_lock(&a->mu);
  while (a->state != SIDE_DONE) pthread_cond_wait(&a->cv, &a->mu);
  pthread_mutex_unlock(&a->mu);
  c->py = a->p; /* released by pair_free, whatever happened to x */
  c->iy = a->info;
  int fy = !fx && a->rc;
  if (fy) *r = a->r;
  side_unref(a);
  return fx || fy ? -1 : 0;
}

static uint64_t prep_us(const sm_store_prep_info *i) {
  uint64_t t = i->t_clean_us + i->t_desc_us;
  for (int b = 0; b < SM_PREP_MAX_BASES; b++) t += i->t_basis_us[b];
  return t;
}

/* Landmarks and initial map arrive in input numbering: translate to cleaned indices. */
static int translate(const sm_proto_match_req *q, const sm_shape *x, const sm_shape *y,
                     sm_match_opts *mo, pair_ctx *c, result *r) {
  int rc = 0;
  int32_t *ix = sm_mesh_input_to_clean(x->mesh), *iy = sm_mesh_input_to_clean(y->mesh);
  if (!ix || !iy) rc = fail(r, SM_ST_INTERNAL, 0, "out of memory");
  uint32_t nl = q->landmarks.count / 2;
  if (!rc && nl) {
    c->lm = malloc((size_t)nl * 2 * sizeof *c->lm);
    if (!c->lm) rc = fail(r, SM_ST_INTERNAL, 0, "out of memory");
    for (uint32_t i = 0; !rc && i < nl; i++) {
      int32_t a = sm_proto_i32_at(&q->landmarks, 2 * i), b = sm_proto_i32_at(&q->landmarks, 2 * i + 1);
      if (a < 0 || a >= x->mesh->n_input || b < 0 || b >= y->mesh->n_input || ix[a] < 0 || iy[b] < 0)
        rc = fail(r, SM_ST_BAD_REQUEST, 0, "landmark %u (%d, %d) is not a vertex of both shapes", i, a, b);
      else {
        c->lm[2 * i] = ix[a];
        c->lm[2 * i + 1] = iy[b];
      }
    }
    mo->landmarks = c->lm;
    mo->nlandmarks = (int)nl;
  }
  if (!rc && q->init_map.count) {
    if (q->init_map.count != (uint32_t)x->mesh->n_input)
      rc = fail(r, SM_ST_BAD_REQUEST, 0, "init_map has %u entries, x has %d input vertices",
                q->init_map.count, x->mesh->n_input);
    else if (!(c->init = malloc((size_t)x->mesh->nv * sizeof *c->init)))
      rc = fail(r, SM_ST_INTERNAL, 0, "out of memory");
    for (int32_t v = 0; !rc && v < x->mesh->nv; v++) {
      int32_t b = sm_proto_i32_at(&q->init_map, (uint32_t)(x->mesh->to_input ? x->mesh->to_input[v] : v));
      if (b < 0 || b >= y->mesh->n_input || iy[b] < 0)
        rc = fail(r, SM_ST_BAD_REQUEST, 0, "init_map entry %d is not a vertex of y", v);
      else
        c->init[v] = iy[b];
    }
    mo->init_map = c->init;
  }
  free(ix);
  free(iy);
  return rc;
}

/* MATCH's path (PROTOCOL.md 5.7): forced by MULTIRES / DIRECT (version >= 3), else chosen
 * by the stored input vertex counts as the local match chooses (sm_multires_wanted). A
 * shape not stored leaves the direct path, whose acquire reports NOT_FOUND. */
static int multires_choice(sm_job *j, const sm_proto_match_req *q, int *on, result *r) {
  uint16_t f = q->flags & (SM_MATCH_F_MULTIRES | SM_MATCH_F_DIRECT);
  *on = 0;
  if (f && j->version < SM_PROTO_VERSION_MULTIRES)
    return fail(r, SM_ST_BAD_REQUEST, 0, "MATCH flags MULTIRES and DIRECT need protocol "
                "version %d; this connection speaks %u", SM_PROTO_VERSION_MULTIRES, j->version);
  sm_multires_opts o;
  sm_multires_opts_default(&o);
  o.mode = (f & SM_MATCH_F_MULTIRES) ? SM_MULTIRES_ON : f ? SM_MULTIRES_OFF : SM_MULTIRES_AUTO;
  uint32_t nx = 0, ny = 0, nf;
  int prepared;
  if (o.mode == SM_MULTIRES_AUTO && (!sm_store_has(j->srv->store, q->x, &nx, &nf, &prepared) ||
                                     !sm_store_has(j->srv->store, q->y, &ny, &nf, &prepared)))
    return 0;
  *on = sm_multires_wanted(&o, (int32_t)nx, (int32_t)ny);
  return 0;
}

/* sm_multires_match on the two coarse levels, its result put in sm_match's form as the
 * local match does: the fine maps and their scores, the coarse level's C, start and tips.
 * With want_dist, *d is the distance of the coarse level's maps. */
static int match_multires(sm_job *j, const sm_multires_shape *x, const sm_multires_shape *y,
                          const sm_match_opts *mo, int want_dist, sm_match_result *mr,
                          sm_distance_parts *d, uint64_t *t_dist, sm_error *err) {
  sm_multires_opts ro;
  sm_multires_opts_default(&ro);
  ro.mode = SM_MULTIRES_ON;
  ro.coarse_nv = j->srv->cfg.multires_coarse_nv;
  sm_multires_result res;
  int e = sm_multires_match(x, y, mo, &ro, &res, err);
  if (e) return e;
  if (want_dist) {
    uint64_t t0 = sm_srv_now_ns();
    e = sm_shape_distance(x->coarse, y->coarse, res.coarse.T, res.coarse.T_yx, d, err);
    *t_dist = (sm_srv_now_ns() - t0) / 1000;
  }
  *mr = res.coarse;
  free(mr->T);
  free(mr->T_yx);
  mr->T = res.T;
  mr->T_yx = res.T_yx;
  mr->nx = res.nx;
  mr->ny = res.ny;
  mr->orientation = res.orientation;
  mr->confidence = res.confidence;
  mr->continuity = res.continuity;
  mr->cycle = res.cycle;
  mr->dirichlet = res.dirichlet;
  return e;
}

static int op_match(sm_job *j, uint8_t opcode, const uint8_t *p, size_t n, result *r) {
  sm_proto_match_req q;
  const char *name = opcode == SM_OP_MATCH ? "MATCH" : "DISTANCE";
  int rc = sm_proto_dec_match_req(opcode, p, n, &q);
  if (rc) return fail(r, SM_ST_BAD_REQUEST, 0, "%s: %s", name, sm_proto_strerror(rc));
  if (q.deadline_ms) j->deadline_ns = j->recv_ns + (uint64_t)q.deadline_ms * 1000000ull;
  sm_match_opts mo;
  sm_store_key key;
  if (match_opts(j, opcode, &q, &mo, &key, r)) return -1;
  int want_dist = opcode == SM_OP_DISTANCE || (q.flags & SM_MATCH_F_WANT_DISTANCE);
  mo.want_yx = want_dist || (q.flags & SM_MATCH_F_WANT_YX);
  int multires = 0;
  if (opcode == SM_OP_MATCH && multires_choice(j, &q, &multires, r)) return -1;
  if (multires) key = sm_store_key_multires(&key, j->srv->cfg.multires_coarse_nv);
  pair_ctx c;
  memset(&c, 0, sizeof c);
  sm_match_result mr;
  memset(&mr, 0, sizeof mr);
  rc = acquire_pair(j, q.x, q.y, &key, &c, r);
  /* multi-resolution: x and y are views of the fine meshes (numbering, the response) */
  const sm_multires_shape *mx = multires && c.px ? sm_prepared_multires(c.px) : NULL;
  const sm_multires_shape *my = multires && c.py ? sm_prepared_multires(c.py) : NULL;
  sm_shape vx = {.mesh = mx ? mx->mesh : NULL}, vy = {.mesh = my ? my->mesh : NULL};
  const sm_shape *x = multires ? (mx ? &vx : NULL) : c.px ? sm_prepared_shape(c.px) : NULL;
  const sm_shape *y = multires ? (my ? &vy : NULL) : c.py ? sm_prepared_shape(c.py) : NULL;
  if (!rc) rc = translate(&q, x, y, &mo, &c, r);
  sm_error err;
  sm_error_clear(&err);
  sm_distance_parts d = {0, 0, 0, 0, -1};
  uint64_t t_dist = 0;
  if (!rc) {
    /* A lone request takes the idle cores too (sm_pool_borrow); the map does not depend
     * on its threads (sm_match_opts.threads). */
    int lent = sm_pool_borrow(j->srv->pool, SM_SRV_MATCH_THREADS - 1);
    mo.threads = 1 + lent;
    int e = multires ? match_multires(j, mx, my, &mo, want_dist, &mr, &d, &t_dist, &err)
                     : sm_match(x, y, &mo, &mr, &err);
    sm_pool_return(j->srv->pool, lent);
    if (e) rc = fail_core(r, j, e, &err, name);
  }
  if (!rc && want_dist && !multires) {
    uint64_t t0 = sm_srv_now_ns();
    int e = sm_shape_distance(x, y, mr.T, mr.T_yx, &d, &err);
    t_dist = (sm_srv_now_ns() - t0) / 1000;
    if (e) rc = fail_core(r, j, e, &err, "distance");
  }
  if (!rc && cancel_cb(j)) {
    sm_error_set(&err, SM_ECANCELED, "cancelled");
    rc = fail_core(r, j, SM_ECANCELED, &err, name);
  }
  sm_proto_dist pd = {d.total, d.point_xy, d.point_yx, d.spectrum_lb, d.spectrum_elastic};
  uint64_t t_total = (sm_srv_now_ns() - j->recv_ns) / 1000;
  if (!rc && opcode == SM_OP_DISTANCE) {
    sm_proto_distance_resp o = {pd, t_total};
    if (!room(r, 48)) rc = fail(r, SM_ST_INTERNAL, 0, "out of memory");
    else sm_proto_enc_distance_resp(r->payload, 48, NULL, &o);
  } else if (!rc) {
    uint32_t nx = (uint32_t)x->mesh->n_input;
    uint32_t ny = (q.flags & SM_MATCH_F_WANT_YX) ? (uint32_t)y->mesh->n_input : 0;
    uint32_t kC = (q.flags & SM_MATCH_F_WANT_FMAP) ? (uint32_t)mr.kC : 0;
    int has_conf = j->version >= SM_PROTO_VERSION_CONFIDENCE;
    uint64_t need = 112 + 4ull * (nx + ny) + 8ull * kC * kC + (has_conf ? 8 : 0);
    int32_t *mxy = malloc((size_t)nx * 4 + 4), *myx = malloc((size_t)ny * 4 + 4);
    if (j->max_response && need > j->max_response)
      rc = fail(r, SM_ST_RESPONSE_TOO_LARGE, need > UINT32_MAX ? UINT32_MAX : (uint32_t)need,
                "MATCH response needs %llu bytes, max_response is %u",
                (unsigned long long)need, j->max_response);
    else if (need > UINT32_MAX - 64 || !mxy || !myx || !room(r, (size_t)need))
      rc = fail(r, SM_ST_INTERNAL, 0, "out of memory");
    else if (has_conf && !(mr.confidence >= 0 && mr.confidence <= 1)) { /* NaN fails too */
      /* a core bug, not the client's: the wire refuses such a value (PROTOCOL.md 5.7) */
      sm_log("error", "match confidence out of range", " rid=%u confidence=%g", j->rid,
             mr.confidence);
      rc = fail(r, SM_ST_INTERNAL, 0, "MATCH: the map's confidence %g is not in [0, 1]",
                mr.confidence);
    }
    if (!rc) {
      sm_match_to_input(x, y, mr.T, mxy);
      if (ny) sm_match_to_input(y, x, mr.T_yx, myx);
      sm_proto_match_resp o;
      memset(&o, 0, sizeof o);
      o.init_used = (uint8_t)mr.init_used;
      o.flags = (mr.flipped ? SM_MATCH_R_FLIPPED : 0) | (want_dist ? SM_MATCH_R_HAS_DISTANCE : 0);
      o.orientation = mr.orientation;
      o.dirichlet = mr.dirichlet;
      o.confidence = mr.confidence;
      if (want_dist) o.dist = pd;
      o.t_prepare_us = prep_us(&c.ix) + prep_us(&c.iy);
      o.t_init_us = s_to_us(mr.t_init);
      o.t_refine_us = s_to_us(mr.t_refine);
      o.t_distance_us = t_dist;
      o.t_total_us = t_total;
      o.map_xy.v = mxy;
      o.map_xy.count = nx;
      o.map_yx.v = myx;
      o.map_yx.count = ny;
      o.kC = (uint16_t)kC;
      o.fmap.v = mr.C;
      o.fmap.count = kC * kC;
      ptrdiff_t w = sm_proto_enc_match_resp(r->payload, r->len, NULL, j->version, &o);
      if (w != (ptrdiff_t)need) rc = fail(r, SM_ST_INTERNAL, 0, "MATCH: encoder returned %td", w);
    }
    free(mxy);
    free(myx);
  }
  sm_match_result_free(&mr);
  pair_free(j, &c);
  return rc;
}

/* ------------------------------------------------------------------ fan-out
 *
 * DESIGN. A BATCH (its items) and a QUERY (its candidates) are split into units that run
 * on the whole pool. fan_start makes W = min(threads, units) runner jobs; a runner claims
 * the next unit (atomic counter), runs it, and then goes back to the *tail* of the job
 * queue if units remain, instead of looping. So one request never holds a worker for more
 * than one unit at a time and never has more than W runners queued: a request from
 * another client that arrives meanwhile waits for at most W units of each running fan
 * before a worker takes it. Runners enter the queue with sm_pool_submit_force: the
 * request itself was admitted (or answered BUSY) by the loop through the bounded queue,
 * and its W runners are a bounded footprint that must not fail half-way. The runner that
 * completes the last unit calls finish(), which posts the final frame (or starts the next
 * phase, QUERY default mode); after that nothing touches the request's job, which the loop
 * may free. The fan struct lives until its last runner has left (refs).
 * Each unit runs with its own sm_job context (unit_job: own deadline and deadline_hit,
 * parent = the request), so cancelling the request cancels every unit not yet finished. */

typedef void (*fan_unit_fn)(void *ctx, uint32_t i, sm_job *uj);
typedef void (*fan_finish_fn)(void *ctx);

typedef struct fan {
  sm_server *srv;
  sm_job *job;
  uint32_t n;
  _Atomic uint32_t next, done;
  _Atomic int refs;
  _Atomic uint64_t workers; /* bit w: worker w ran a unit (w < 64) */
  fan_unit_fn unit;
  fan_finish_fn finish;
  void *ctx;
} fan;

typedef struct runner {
  sm_pool_job base; /* first member */
  fan *f;
} runner;

static void unit_job(sm_job *uj, sm_job *parent) {
  memset(uj, 0, sizeof *uj);
  atomic_init(&uj->cancel, 0);
  uj->srv = parent->srv;
  uj->rid = parent->rid;
  uj->opcode = parent->opcode;
  uj->version = parent->version;
  uj->max_response = parent->max_response;
  uj->recv_ns = parent->recv_ns;
  uj->deadline_ns = parent->deadline_ns;
  uj->parent = parent;
}

static void fan_unref(fan *f) {
  if (atomic_fetch_sub(&f->refs, 1) == 1) free(f);
}

static void runner_run(sm_pool_job *pj) {
  runner *r = (runner *)pj;
  fan *f = r->f;
  for (;;) {
    uint32_t i = atomic_fetch_add(&f->next, 1);
    if (i >= f->n) break;
    int w = sm_pool_worker_index();
    if (w >= 0 && w < 64) atomic_fetch_or(&f->workers, 1ull << w);
    sm_met_add(&sm_met.fanout_units, 1);
    sm_job uj;
    unit_job(&uj, f->job);
    f->unit(f->ctx, i, &uj);
    if (atomic_fetch_add(&f->done, 1) + 1 == f->n) {
      sm_met_max(&sm_met.fanout_workers_max,
                 (uint64_t)__builtin_popcountll(atomic_load(&f->workers)));
      f->finish(f->ctx); /* the request's job may be gone after this */
    }
    if (atomic_load(&f->next) >= f->n) break;
    if (sm_pool_submit_force(f->srv->pool, &r->base) == 0) return; /* back to the tail */
    /* the pool is stopping: finish the units here */
  }
  free(r);
  fan_unref(f);
}

/* Runs n units of ctx on the pool; finish(ctx) once all are done. Called on a worker; this
 * worker runs the first runner itself. Never fails: without memory or runners the units
 * run here. */
static void fan_start(sm_job *job, uint32_t n, fan_unit_fn unit, fan_finish_fn finish,
                      void *ctx) {
  sm_server *s = job->srv;
  if (n == 0) {
    finish(ctx);
    return;
  }
  uint32_t w = (uint32_t)sm_pool_threads(s->pool);
  if (w > n) w = n;
  if (w < 1) w = 1;
  fan *f = calloc(1, sizeof *f);
  runner *first = f ? calloc(1, sizeof *first) : NULL;
  if (!f || !first) { /* out of memory: run them here, in order */
    free(f);
    for (uint32_t i = 0; i < n; i++) {
      sm_job uj;
      unit_job(&uj, job);
      unit(ctx, i, &uj);
    }
    finish(ctx);
    return;
  }
  f->srv = s;
  f->job = job;
  f->n = n;
  f->unit = unit;
  f->finish = finish;
  f->ctx = ctx;
  atomic_init(&f->next, 0);
  atomic_init(&f->done, 0);
  atomic_init(&f->workers, 0);
  atomic_init(&f->refs, (int)w);
  first->base.run = runner_run;
  first->f = f;
  for (uint32_t k = 1; k < w; k++) {
    runner *r = calloc(1, sizeof *r);
    if (r) {
      r->base.run = runner_run;
      r->f = f;
    }
    if (!r || sm_pool_submit_force(s->pool, &r->base)) {
      free(r);
      fan_unref(f); /* refs > 0: first still holds one */
    }
  }
  runner_run(&first->base);
}

/* ------------------------------------------------------------------ QUERY
 *
 * Modes (PROTOCOL.md 5.9): SPECTRAL ranks every candidate by the spectral distance alone;
 * FULL matches the query against every candidate (sm_match + sm_shape_distance); DEFAULT
 * ranks every candidate spectrally, then computes the full distance for the best
 * QUERY_SHORTLIST(k) of them and returns those ranked by the full distance; when the
 * distance is the spectral term alone (sm_distance_uses_maps() = 0: map weight 0, not the
 * default) the spectral ranking is already the full one and DEFAULT stops there. Each
 * candidate of a phase is one fan-out unit (preparing its bases when they are not cached
 * is part of the unit), so a query uses the whole pool. */

/* max(1.5 k, 16). The exhaustive top-1 was within the spectral term's first 12 on the map
 * term study's 240 queries against tosca's 40 shapes (98.8% within 10), and within its
 * first 10 on every FULL query against the 520-shape gallery (bench/eval/query_scale.py).
 * A longer list mostly adds ranks 2..k of the exhaustive answer: its top-10 share was
 * 0.63 / 0.77 / 0.78 / 0.88 with the first 10 / 16 / 20 / 30 (6 FULL queries), at one
 * match per entry (16 keeps a top-10 QUERY of the gallery under 2 s on two workers). */
#define QUERY_SHORTLIST(k) ((k) * 3u / 2u > 16u ? (k) * 3u / 2u : 16u)

typedef struct query_ctx {
  sm_job *job;
  sm_proto_query_req q;
  uint8_t *ids;   /* nid candidate ids */
  size_t nid;
  uint32_t *cand; /* this phase's units: indices into ids */
  uint32_t ncand;
  double *dist;   /* per id */
  uint8_t *valid; /* per id: dist holds this phase's distance */
  int phase;      /* 0 spectral, 1 full */
  uint32_t considered;
  sm_store_key key;
  sm_match_opts mo; /* template; each unit copies it with its own cancel context */
  sm_prepared *px;
  uint64_t t0;
  _Atomic int failed;
  atomic_uint skipped; /* candidates that could not be compared */
  pthread_mutex_t mu; /* err */
  result err;
} query_ctx;

static void query_free(query_ctx *c) {
  sm_store_release(c->job->srv->store, c->px);
  free(c->ids);
  free(c->cand);
  free(c->dist);
  free(c->valid);
  pthread_mutex_destroy(&c->mu);
  free(c);
}

/* Records the first failure of a unit. */
static void query_fail(query_ctx *c, const result *r) {
  pthread_mutex_lock(&c->mu);
  if (!atomic_load(&c->failed)) {
    c->err = *r;
    atomic_store(&c->failed, 1);
  }
  pthread_mutex_unlock(&c->mu);
}

/* A candidate that cannot be compared (dropped, damaged, too small for the basis, past
 * the preparation bound, a solver failure) is one bad shape among many: it is skipped,
 * counted and logged, never fatal to the query. Only the request's own cancel or
 * deadline ends the query. */
static void query_skip_or_fail(query_ctx *c, sm_job *uj, const result *r) {
  if (r->status == SM_ST_CANCELLED || (r->status == SM_ST_DEADLINE && cancel_cb(uj))) {
    query_fail(c, r);
    return;
  }
  if (atomic_fetch_add(&c->skipped, 1) == 0 && r->status != SM_ST_NOT_FOUND)
    sm_log("warn", "QUERY candidate skipped", " rid=%u status=%u err=\"%s\"", c->job->rid,
           r->status, r->msg);
}

/* Decodes and sets up a query; NULL with r filled on a failure. */
static query_ctx *query_begin(sm_job *j, const uint8_t *p, size_t n, result *r) {
  sm_proto_query_req q;
  int rc = sm_proto_dec_query_req(p, n, &q);
  if (rc) {
    fail(r, SM_ST_BAD_REQUEST, 0, "QUERY: %s", sm_proto_strerror(rc));
    return NULL;
  }
  const sm_srv_config *cfg = &j->srv->cfg;
  if (q.k > cfg->max_query_k) {
    fail(r, SM_ST_LIMIT_EXCEEDED, cfg->max_query_k, "QUERY: k above max_query_k");
    return NULL;
  }
  if (q.deadline_ms) j->deadline_ns = j->recv_ns + (uint64_t)q.deadline_ms * 1000000ull;
  query_ctx *c = calloc(1, sizeof *c);
  if (!c) {
    fail(r, SM_ST_INTERNAL, 0, "out of memory");
    return NULL;
  }
  pthread_mutex_init(&c->mu, NULL);
  atomic_init(&c->failed, 0);
  atomic_init(&c->skipped, 0);
  c->job = j;
  c->q = q;
  c->t0 = sm_srv_now_ns();
  if (q.n_candidates) {
    c->ids = malloc((size_t)q.n_candidates * 32);
    if (c->ids) memcpy(c->ids, q.candidates, (size_t)q.n_candidates * 32);
    c->nid = q.n_candidates;
  } else if (sm_store_list(j->srv->store, &c->ids, &c->nid)) {
    c->ids = NULL;
  }
  size_t m = c->nid ? c->nid : 1;
  c->cand = malloc(m * sizeof *c->cand);
  c->dist = calloc(m, sizeof *c->dist);
  c->valid = calloc(m, 1);
  if (!c->ids || !c->cand || !c->dist || !c->valid) {
    fail(r, SM_ST_INTERNAL, 0, "out of memory");
    query_free(c);
    return NULL;
  }
  c->key = default_key(j->srv);
  sm_match_opts_default(&c->mo);
  int k_lb = sm_store_key_k(&c->key, SM_BASIS_LB);
  c->mo.k1 = k_lb < c->mo.k1 ? k_lb : c->mo.k1;
  sm_distance_match_opts(&c->mo);
  sm_store_prep_info info;
  if (acquire(j, q.id, &c->key, "QUERY", 0, &c->px, &info, r)) {
    query_free(c);
    return NULL;
  }
  /* first phase: every candidate except the query itself */
  for (size_t i = 0; i < c->nid; i++)
    if (memcmp(c->ids + 32 * i, q.id, 32)) c->cand[c->ncand++] = (uint32_t)i;
  c->phase = q.mode == SM_QUERY_FULL ? 1 : 0;
  return c;
}

static void query_unit(void *vc, uint32_t u, sm_job *uj) {
  query_ctx *c = vc;
  uint32_t idx = c->cand[u];
  const uint8_t *cid = c->ids + 32 * (size_t)idx;
  if (atomic_load(&c->failed)) return;
  result r;
  memset(&r, 0, sizeof r);
  sm_error err;
  sm_error_clear(&err);
  int e;
  if (cancel_cb(uj)) {
    sm_error_set(&err, SM_ECANCELED, "cancelled");
    fail_core(&r, uj, SM_ECANCELED, &err, "QUERY");
    query_fail(c, &r);
    return;
  }
  sm_store *st = uj->srv->store;
  sm_prepared *py = NULL;
  sm_store_prep_info iy;
  if (acquire(uj, cid, &c->key, "QUERY candidate", 0, &py, &iy, &r)) {
    query_skip_or_fail(c, uj, &r);
    return;
  }
  const sm_shape *x = sm_prepared_shape(c->px), *y = sm_prepared_shape(py);
  double dist;
  if (c->phase == 0) {
    dist = sm_shape_spectral_term(x, y);
  } else {
    sm_match_opts mo = c->mo;
    mo.cancel = cancel_cb;
    mo.cancel_ud = uj;
    sm_match_result mr;
    memset(&mr, 0, sizeof mr);
    sm_distance_parts d;
    e = sm_match(x, y, &mo, &mr, &err);
    if (!e) e = sm_shape_distance(x, y, mr.T, mr.T_yx, &d, &err);
    sm_match_result_free(&mr);
    if (e) {
      sm_store_release(st, py);
      fail_core(&r, uj, e, &err, "QUERY match");
      query_skip_or_fail(c, uj, &r);
      return;
    }
    dist = d.total;
  }
  sm_store_release(st, py);
  c->dist[idx] = dist; /* each unit owns its idx; finish reads after the fan's barrier */
  c->valid[idx] = 1;
}

typedef struct qsort_ctx_item {
  double d;
  uint32_t idx;
  const uint8_t *id;
} qitem;

static int qitem_cmp(const void *a, const void *b) {
  const qitem *x = a, *y = b;
  if (x->d < y->d) return -1;
  if (x->d > y->d) return 1;
  return memcmp(x->id, y->id, 32);
}

/* The phase's distances, ranked; *n receives the count. NULL without memory. */
static qitem *query_ranked(query_ctx *c, uint32_t *n) {
  qitem *v = malloc((c->ncand ? c->ncand : 1) * sizeof *v);
  *n = 0;
  if (!v) return NULL;
  for (uint32_t u = 0; u < c->ncand; u++) {
    uint32_t idx = c->cand[u];
    if (c->valid[idx]) v[(*n)++] = (qitem){c->dist[idx], idx, c->ids + 32 * (size_t)idx};
  }
  qsort(v, *n, sizeof *v, qitem_cmp);
  return v;
}

/* After a phase: sets up the next one and returns 1, or 0 when the query is complete. */
static int query_next_phase(query_ctx *c) {
  if (atomic_load(&c->failed)) return 0;
  if (c->phase == 0) {
    uint32_t n = 0;
    qitem *v = query_ranked(c, &n);
    if (!v) {
      result r;
      memset(&r, 0, sizeof r);
      fail(&r, SM_ST_INTERNAL, 0, "out of memory");
      query_fail(c, &r);
      return 0;
    }
    c->considered = n;
    if (c->q.mode == SM_QUERY_SPECTRAL || !sm_distance_uses_maps()) {
      free(v);
      return 0;
    }
    uint32_t keep = QUERY_SHORTLIST((uint32_t)c->q.k);
    if (keep > n) keep = n;
    for (uint32_t u = 0; u < c->ncand; u++) c->valid[c->cand[u]] = 0;
    for (uint32_t u = 0; u < keep; u++) c->cand[u] = v[u].idx;
    c->ncand = keep;
    c->phase = 1;
    free(v);
    return keep > 0;
  }
  return 0;
}

/* The response (or the recorded failure); frees c. */
static int query_end(query_ctx *c, result *r) {
  int rc = 0;
  if (atomic_load(&c->failed)) {
    *r = c->err;
    query_free(c);
    return -1;
  }
  uint32_t n = 0;
  qitem *v = query_ranked(c, &n);
  if (c->q.mode == SM_QUERY_FULL) c->considered = n;
  unsigned skipped = atomic_load(&c->skipped);
  if (skipped)
    sm_log("info", "QUERY done with skipped candidates", " rid=%u skipped=%u considered=%u",
           c->job->rid, skipped, c->considered);
  sm_job *j = c->job;
  uint32_t count = n < c->q.k ? n : c->q.k;
  sm_proto_hit *hits = calloc(count ? count : 1, sizeof *hits);
  if (!v || !hits) {
    rc = fail(r, SM_ST_INTERNAL, 0, "out of memory");
  } else {
    for (uint32_t i = 0; i < count; i++) {
      memcpy(hits[i].id, v[i].id, 32);
      hits[i].distance = v[i].d;
    }
    sm_proto_query_resp o = {.n_considered = c->considered,
                             .t_total_us = (sm_srv_now_ns() - j->recv_ns) / 1000,
                             .v = hits, .count = count};
    size_t need = 16 + 40 * (size_t)count;
    if (j->max_response && need > j->max_response)
      rc = fail(r, SM_ST_RESPONSE_TOO_LARGE, (uint32_t)need, "QUERY response too large");
    else if (!room(r, need))
      rc = fail(r, SM_ST_INTERNAL, 0, "out of memory");
    else
      sm_proto_enc_query_resp(r->payload, need, NULL, &o);
  }
  free(v);
  free(hits);
  query_free(c);
  return rc;
}

/* QUERY inside a BATCH item: the units run here, in order (the batch already spreads its
 * items over the pool). */
static int op_query(sm_job *j, const uint8_t *p, size_t n, result *r) {
  query_ctx *c = query_begin(j, p, n, r);
  if (!c) return -1;
  do {
    for (uint32_t u = 0; u < c->ncand; u++) {
      sm_job uj;
      unit_job(&uj, j);
      query_unit(c, u, &uj);
    }
  } while (query_next_phase(c));
  return query_end(c, r);
}

/* ------------------------------------------------------------------ dispatch */

static int op_ping(const uint8_t *p, size_t n, result *r) {
  sm_proto_ping q;
  int rc = sm_proto_dec_ping(p, n, &q);
  if (rc) return fail(r, SM_ST_BAD_REQUEST, 0, "PING: %s", sm_proto_strerror(rc));
  if (!room(r, 8)) return fail(r, SM_ST_INTERNAL, 0, "out of memory");
  sm_proto_enc_ping(r->payload, 8, NULL, 1, &q);
  return 0;
}

static int op_has(sm_job *j, const uint8_t *p, size_t n, result *r) {
  sm_proto_id_req q;
  int rc = sm_proto_dec_id_req(p, n, &q);
  if (rc) return fail(r, SM_ST_BAD_REQUEST, 0, "HAS_SHAPE: %s", sm_proto_strerror(rc));
  sm_proto_has_resp o = {0, 0, 0};
  int prepared = 0;
  if (sm_store_has(j->srv->store, q.id, &o.n_vertices, &o.n_faces, &prepared))
    o.flags = SM_HAS_STORED | (prepared ? SM_HAS_PREPARED : 0);
  if (!room(r, 12)) return fail(r, SM_ST_INTERNAL, 0, "out of memory");
  sm_proto_enc_has_resp(r->payload, 12, NULL, &o);
  return 0;
}

static int cancelled_before(sm_job *j, uint8_t op, result *r) {
  sm_error e;
  sm_error_set(&e, SM_ECANCELED, "cancelled before it started");
  return fail_core(r, j, SM_ECANCELED, &e, sm_proto_op_name(op));
}

static int run_op(sm_job *j, uint8_t op, const uint8_t *p, size_t n, result *r) {
  if (cancel_cb(j)) return cancelled_before(j, op, r);
  switch (op) {
  case SM_OP_PING: return op_ping(p, n, r);
  case SM_OP_HAS_SHAPE: return op_has(j, p, n, r);
  case SM_OP_PUT_SHAPE: return op_put(j, p, n, r);
  case SM_OP_PREPARE: return op_prepare(j, p, n, r);
  case SM_OP_MATCH:
  case SM_OP_DISTANCE: return op_match(j, op, p, n, r);
  case SM_OP_QUERY: return op_query(j, p, n, r);
  default: return fail(r, SM_ST_BAD_REQUEST, 0, "opcode %u not allowed here", op);
  }
}

static void post(sm_job *j, sm_wbuf *frames, int final) {
  sm_srv_out *o = calloc(1, sizeof *o);
  if (!o) abort(); /* the loop must learn that the job ended; nothing sane remains */
  o->job = j;
  o->frames = frames;
  o->final = final;
  sm_pool_post(j->srv->pool, &o->base);
}

/* A top-level response frame from a result. */
static sm_wbuf *result_frame(sm_job *j, uint8_t opcode, result *r) {
  if (r->status) {
    sm_met_add(&sm_met.errors, 1);
    if (r->status == SM_ST_CANCELLED) sm_met_add(&sm_met.cancelled, 1);
    return sm_error_frame(j->version, opcode, j->rid, r->status, r->retry, r->detail, r->msg);
  }
  sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + r->len);
  if (!w) return sm_error_frame(j->version, opcode, j->rid, SM_ST_INTERNAL, 0, 0, "out of memory");
  sm_proto_header h = {j->version, opcode, SM_PROTO_F_RESPONSE, j->rid, 0, (uint32_t)r->len};
  sm_proto_write_header(w->data, &h);
  memcpy(w->data + SM_PROTO_HEADER_LEN, r->payload, r->len);
  return w;
}

/* ---- top-level QUERY: its phases fanned out */

static void query_fan_finish(void *vc) {
  query_ctx *c = vc;
  if (query_next_phase(c)) {
    fan_start(c->job, c->ncand, query_unit, query_fan_finish, c);
    return;
  }
  sm_job *j = c->job;
  uint64_t t0 = c->t0;
  result r;
  memset(&r, 0, sizeof r);
  query_end(c, &r);
  sm_wbuf *w = result_frame(j, SM_OP_QUERY, &r);
  free(r.base);
  sm_met_latency((sm_srv_now_ns() - t0) / 1000);
  post(j, w, 1);
}

static void run_query(sm_job *j) {
  result r;
  memset(&r, 0, sizeof r);
  query_ctx *c = cancel_cb(j) ? (cancelled_before(j, SM_OP_QUERY, &r), NULL)
                              : query_begin(j, j->body, j->body_len, &r);
  if (!c) {
    sm_wbuf *w = result_frame(j, SM_OP_QUERY, &r);
    free(r.base);
    post(j, w, 1);
    return;
  }
  fan_start(j, c->ncand, query_unit, query_fan_finish, c);
}

/* ---- BATCH: one unit per item */

typedef struct batch_ctx {
  sm_job *job;
  uint32_t count;
  sm_proto_batch_item *items;
  _Atomic uint32_t n_ok;
  uint64_t t0;
} batch_ctx;

static void batch_unit(void *vc, uint32_t idx, sm_job *uj) {
  batch_ctx *b = vc;
  const sm_proto_batch_item *it = &b->items[idx];
  result ir;
  memset(&ir, 0, sizeof ir);
  run_op(uj, it->opcode, it->payload, it->len, &ir);
  uint8_t errp[12 + SM_PROTO_MAX_MSG];
  sm_proto_batch_item_resp ip = {idx, it->opcode, NULL, 0};
  if (ir.status) {
    ip.len = (uint32_t)sm_error_payload(errp, ir.retry, ir.detail, ir.msg);
    ip.payload = errp;
  } else {
    ip.payload = ir.payload;
    ip.len = (uint32_t)ir.len;
  }
  if (!ir.status && uj->max_response && 8ull + ip.len > uj->max_response) {
    fail(&ir, SM_ST_RESPONSE_TOO_LARGE, (uint32_t)(8 + ip.len), "item response too large");
    ip.len = (uint32_t)sm_error_payload(errp, 0, ir.detail, ir.msg);
    ip.payload = errp;
  }
  if (!ir.status) atomic_fetch_add(&b->n_ok, 1);
  sm_proto_header h = {uj->version, SM_OP_BATCH, SM_PROTO_F_RESPONSE, uj->rid, ir.status, 0};
  size_t cap = SM_PROTO_HEADER_LEN + 8 + ip.len + 4;
  sm_wbuf *w = sm_wbuf_new(cap);
  if (w) {
    ptrdiff_t got = sm_proto_enc_batch_item_resp(w->data, cap, &h, &ip);
    if (got <= 0 || (size_t)got > cap) {
      free(w);
      w = NULL;
    } else {
      w->len = (size_t)got;
    }
  }
  if (w) post(b->job, w, 0);
  free(ir.base);
}

static void batch_finish(void *vc) {
  batch_ctx *b = vc;
  sm_job *j = b->job;
  sm_proto_batch_done d = {b->count, atomic_load(&b->n_ok)};
  uint64_t t0 = b->t0;
  free(b->items);
  free(b);
  sm_proto_header h = {j->version, SM_OP_BATCH, SM_PROTO_F_RESPONSE, j->rid, 0, 0};
  sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + 8);
  if (w) sm_proto_enc_batch_done(w->data, w->len, &h, &d);
  sm_met_latency((sm_srv_now_ns() - t0) / 1000);
  post(j, w, 1);
}

static void run_batch(sm_job *j) {
  const sm_srv_config *cfg = &j->srv->cfg;
  sm_proto_batch_req b;
  result r;
  memset(&r, 0, sizeof r);
  int rc = sm_proto_dec_batch_req(j->body, j->body_len, &b);
  if (rc) {
    /* A count over the limit is LIMIT_EXCEEDED even when the decoder also dislikes it. */
    fail(&r, SM_ST_BAD_REQUEST, 0, "BATCH: %s", sm_proto_strerror(rc));
  } else if (b.count > cfg->max_batch_items) {
    fail(&r, SM_ST_LIMIT_EXCEEDED, cfg->max_batch_items, "BATCH: %u items, max_batch_items is %u",
         b.count, cfg->max_batch_items);
  }
  batch_ctx *bc = r.status ? NULL : calloc(1, sizeof *bc);
  if (!r.status && bc) bc->items = malloc((size_t)b.count * sizeof *bc->items);
  if (!r.status && (!bc || !bc->items)) fail(&r, SM_ST_INTERNAL, 0, "out of memory");
  if (r.status) {
    if (bc) free(bc->items);
    free(bc);
    post(j, result_frame(j, SM_OP_BATCH, &r), 1);
    return;
  }
  size_t pos = 0;
  uint32_t n = 0;
  while (n < b.count && sm_proto_batch_next(&b, &pos, &bc->items[n])) n++;
  bc->job = j;
  bc->count = n;
  bc->t0 = sm_srv_now_ns();
  atomic_init(&bc->n_ok, 0);
  fan_start(j, n, batch_unit, batch_finish, bc);
}

void sm_exec_run(sm_pool_job *pj) {
  sm_job *j = (sm_job *)pj;
  if (j->opcode == SM_OP_BATCH) {
    run_batch(j); /* answers come from the fan's units; latency at its end */
    return;
  }
  if (j->opcode == SM_OP_QUERY) {
    run_query(j);
    return;
  }
  uint64_t t0 = sm_srv_now_ns();
  result r;
  memset(&r, 0, sizeof r);
  run_op(j, j->opcode, j->body, j->body_len, &r);
  sm_wbuf *w = result_frame(j, j->opcode, &r);
  free(r.base);
  sm_met_latency((sm_srv_now_ns() - t0) / 1000);
  post(j, w, 1);
}
