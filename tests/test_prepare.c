/* The one preparation API (core/sm_prepare.h): the hooks' contract (what is loaded is
 * used, what is missing is computed and saved once, a load failure releases what earlier
 * misses reserved, a foreign basis is refused), the thread budget (same bases on 1 and 2
 * threads), the spec checks, and the multi-resolution coarse level through the same hooks. */
#include <math.h>
#include <string.h>

#include "sm_prepare.h"
#include "sm_synth.h"
#include "sm_test.h"
#include "sm_testmesh.h"

/* A cache of at most 4 bases, with call counters. */
typedef struct cache {
  sm_basis_spec spec[8];
  uint8_t *buf[8];
  size_t len[8];
  int n;
  int loads, hits, saves, saves_null, fail_kind; /* fail_kind: load of it errs */
} cache;

static int c_load(void *ud, const sm_basis_spec *spec, const sm_mesh *m, sm_basis **out,
                  sm_error *err) {
  cache *c = ud;
  c->loads++;
  if (spec->kind == c->fail_kind) return sm_error_set(err, SM_ECANCELED, "test: load fails");
  for (int i = 0; i < c->n; i++)
    if (sm_basis_spec_eq(&c->spec[i], spec)) {
      if (sm_basis_deserialize(c->buf[i], c->len[i], out, NULL)) return 0;
      if (sm_basis_fits(*out, spec, m, NULL) == SM_OK) {
        c->hits++;
        return 1;
      }
      sm_basis_destroy(*out);
      *out = NULL;
      return 0;
    }
  return 0;
}

static void c_save(void *ud, const sm_basis_spec *spec, const sm_basis *b) {
  cache *c = ud;
  if (!b) {
    c->saves_null++;
    return;
  }
  c->saves++;
  REQUIRE(c->n < 8);
  c->spec[c->n] = *spec;
  REQUIRE(sm_basis_serialize(b, &c->buf[c->n], &c->len[c->n], NULL) == 0);
  c->n++;
}

static void cache_free(cache *c) {
  for (int i = 0; i < c->n; i++) free(c->buf[i]);
}

static int same_basis(const sm_basis *a, const sm_basis *b) {
  return a && b && a->k == b->k && a->n == b->n &&
         !memcmp(a->evals, b->evals, (size_t)a->k * sizeof *a->evals) &&
         !memcmp(a->phi, b->phi, (size_t)a->n * a->k * sizeof *a->phi);
}

static void opts(sm_prep_opts *po, int k, const sm_prep_hooks *h) {
  sm_prep_opts_default(po);
  po->nspec = sm_prep_default_specs(po->spec, k, k, 1e-4);
  po->hooks = h;
}

static void test_hooks_and_threads(void) {
  sm_mesh *m = NULL;
  const double st[3] = {1.0, 0.8, 0.6};
  sm_error err;
  REQUIRE(sm_synth_blob(3, 0.2, 7, st, &m, &err) == 0); /* 642 vertices */
  cache c;
  memset(&c, 0, sizeof c);
  sm_prep_hooks h = {c_load, c_save, &c};
  sm_prep_opts po;
  opts(&po, 30, &h);
  sm_prep_info info;

  /* Cold: both computed (on two threads), both saved. */
  po.threads = 2;
  sm_shape *a = NULL;
  REQUIRE(sm_prepare(m, &po, &a, &info, &err) == 0);
  CHECK(info.computed == 2 && info.loaded == 0);
  CHECK(c.loads == 2 && c.saves == 2 && c.saves_null == 0);
  CHECK(a->lb && a->elastic && a->lb->k == 30 && a->elastic->k == 30);

  /* One thread, no hooks: the same bases bit for bit. */
  sm_prep_opts plain;
  opts(&plain, 30, NULL);
  sm_shape *b = NULL;
  REQUIRE(sm_prepare(m, &plain, &b, NULL, &err) == 0);
  CHECK(same_basis(a->lb, b->lb));
  CHECK(same_basis(a->elastic, b->elastic));

  /* Warm: both loaded, nothing saved, same descriptors. */
  sm_shape *w = NULL;
  REQUIRE(sm_prepare(m, &po, &w, &info, &err) == 0);
  CHECK(info.loaded == 2 && info.computed == 0 && c.hits == 2 && c.saves == 2);
  CHECK(!memcmp(w->desc, a->desc, (size_t)a->mesh->nv * a->n_desc * sizeof *a->desc));

  /* Another mesh asks for the same specs: the cached bases do not fit, so they are
   * computed again (and saved). */
  sm_mesh *m2 = NULL;
  REQUIRE(sm_synth_blob(3, 0.2, 8, st, &m2, &err) == 0);
  sm_shape *o = NULL;
  int hits = c.hits;
  REQUIRE(sm_prepare(m2, &po, &o, &info, &err) == 0);
  CHECK(c.hits == hits && info.computed == 2);

  /* A load that fails after an earlier miss: the miss is released (save NULL), the
   * preparation fails with the hook's code and message. */
  cache d;
  memset(&d, 0, sizeof d);
  d.fail_kind = SM_BASIS_ELASTIC;
  sm_prep_hooks hd = {c_load, c_save, &d};
  opts(&po, 30, &hd);
  sm_shape *f = NULL;
  CHECK(sm_prepare(m, &po, &f, &info, &err) == SM_ECANCELED && !f);
  CHECK(d.saves_null == 1 && d.saves == 0);
  CHECK(strstr(err.msg, "test: load fails") != NULL);

  sm_shape_destroy(a);
  sm_shape_destroy(b);
  sm_shape_destroy(w);
  sm_shape_destroy(o);
  cache_free(&c);
  cache_free(&d);
  sm_mesh_destroy(m);
  sm_mesh_destroy(m2);
}

static void test_spec_checks(void) {
  sm_mesh *m = tm_icosphere(2); /* 162 vertices */
  sm_prep_opts po;
  sm_shape *s = NULL;
  sm_error err;
  opts(&po, 20, NULL);
  po.spec[1].eta = NAN;
  CHECK(sm_prepare(m, &po, &s, NULL, &err) == SM_EINVAL && !s && strstr(err.msg, "eta"));
  opts(&po, 20, NULL);
  po.spec[1].kind = SM_BASIS_LB;
  po.spec[1].eta = 0;
  CHECK(sm_prepare(m, &po, &s, NULL, &err) == SM_EINVAL && strstr(err.msg, "two specs"));
  opts(&po, 20, NULL);
  po.spec[0] = po.spec[1];
  po.nspec = 1;
  CHECK(sm_prepare(m, &po, &s, NULL, &err) == SM_EINVAL && strstr(err.msg, "LB basis spec"));
  opts(&po, 200, NULL);
  CHECK(sm_prepare(m, &po, &s, NULL, &err) == SM_EINVAL && strstr(err.msg, "k_lb = 200"));
  opts(&po, 20, NULL);
  po.spec[0].kind = 9;
  CHECK(sm_prepare(m, &po, &s, NULL, &err) == SM_EINVAL && strstr(err.msg, "kind 9"));
  /* Names are stable: the daemon's cache files are named by them. */
  char name[128];
  sm_basis_spec lb = {SM_BASIS_LB, 100, 0.0}, el = {SM_BASIS_ELASTIC, 100, 1e-4};
  sm_basis_spec_name(&lb, name, sizeof name);
  CHECK(!strcmp(name, "lb.k100.eta0000000000000000"));
  sm_basis_spec_name(&el, name, sizeof name);
  CHECK(!strcmp(name, "el.k100.eta3f1a36e2eb1c432d"));
  sm_mesh_destroy(m);
}

/* The coarse level's bases go through the same hooks: a second preparation loads them. */
static void test_multires_hooks(void) {
  sm_mesh *m = NULL;
  const double st[3] = {1.0, 0.7, 0.5};
  sm_error err;
  REQUIRE(sm_synth_blob(4, 0.2, 3, st, &m, &err) == 0); /* 2562 vertices */
  cache c;
  memset(&c, 0, sizeof c);
  sm_prep_hooks h = {c_load, c_save, &c};
  sm_prep_opts po;
  opts(&po, 30, &h);
  sm_multires_opts mo;
  sm_multires_opts_default(&mo);
  mo.mode = SM_MULTIRES_ON;
  mo.coarse_nv = 800;
  sm_multires_shape *x = NULL, *y = NULL;
  sm_prep_info info;
  REQUIRE(sm_prepare_multires(m, &po, &mo, &x, &info, &err) == 0);
  CHECK(info.computed == 2 && c.saves == 2);
  CHECK(x->coarse->mesh->nv < m->nv && x->coarse->elastic->k == 30);
  REQUIRE(sm_prepare_multires(m, &po, &mo, &y, &info, &err) == 0);
  CHECK(info.loaded == 2 && info.computed == 0 && c.saves == 2);
  CHECK(same_basis(x->coarse->elastic, y->coarse->elastic));
  sm_multires_shape_destroy(x);
  sm_multires_shape_destroy(y);
  cache_free(&c);
  sm_mesh_destroy(m);
}

int main(void) {
  test_hooks_and_threads();
  test_spec_checks();
  test_multires_hooks();
  return sm_test_finish();
}
