/* The one preparation of a shape: see sm_prepare.h. */
#include "sm_prepare.h"

#include <pthread.h>
#include <stdlib.h>
#include <string.h>

#include "sm_eigs.h"
#include "sm_shell.h"

int sm_prep_default_specs(sm_basis_spec *spec, int k_lb, int k_el, double eta) {
  spec[0] = (sm_basis_spec){SM_BASIS_LB, k_lb, 0.0};
  if (k_el <= 0) return 1;
  spec[1] = (sm_basis_spec){SM_BASIS_ELASTIC, k_el, eta};
  return 2;
}

void sm_prep_opts_default(sm_prep_opts *o) {
  memset(o, 0, sizeof *o);
  o->nspec = sm_prep_default_specs(o->spec, 100, 100, SM_SHELL_DEFAULT_ETA);
  o->n_desc = 100;
  o->threads = 1;
}

void sm_prep_opts_from_shape(sm_prep_opts *o, const sm_shape_opts *so) {
  sm_prep_opts_default(o);
  o->nspec = sm_prep_default_specs(o->spec, so->k_lb, so->k_elastic, so->eta);
  o->n_desc = so->n_desc;
  o->cancel = so->cancel;
  o->cancel_ud = so->cancel_ud;
}

static size_t basis_bytes(const sm_basis *b) {
  if (!b) return 0;
  size_t n = (size_t)b->n, k = (size_t)b->k;
  return sizeof *b + 8 * (k + n * k + n + (b->gram_L ? k * k : 0));
}

size_t sm_shape_bytes(const sm_shape *s) {
  size_t nv = (size_t)s->mesh->nv, nf = (size_t)s->mesh->nf;
  return sizeof *s + nv * 24 + nf * 12 + nv * 4 + basis_bytes(s->lb) + basis_bytes(s->elastic) +
         nv * (size_t)s->n_desc * 8;
}

int sm_shape_nbases(const sm_shape *s) { return (s->lb != NULL) + (s->elastic != NULL); }

const sm_basis_spec *sm_prep_spec_of(const sm_prep_opts *o, int kind) {
  for (int i = 0; i < o->nspec; i++)
    if (o->spec[i].kind == kind) return &o->spec[i];
  return NULL;
}

/* The specs, against the cleaned mesh m: valid, one per kind, an LB one, and k small
 * enough for the eigensolvers (LB: the constant functions plus at least one more). */
static int check_specs(const sm_prep_opts *o, const sm_mesh *m, sm_error *err) {
  if (o->nspec < 1 || o->nspec > SM_PREP_MAX_BASES)
    return sm_error_set(err, SM_EINVAL, "prepare: %d basis specs (1..%d)", o->nspec,
                        SM_PREP_MAX_BASES);
  if (o->threads < 1) return sm_error_set(err, SM_EINVAL, "prepare: threads = %d", o->threads);
  if (o->n_desc < 1) return sm_error_set(err, SM_EINVAL, "prepare: n_desc = %d", o->n_desc);
  for (int i = 0; i < o->nspec; i++) {
    int rc = sm_basis_spec_check(&o->spec[i], err);
    if (rc) return rc;
    for (int j = 0; j < i; j++)
      if (o->spec[j].kind == o->spec[i].kind)
        return sm_error_set(err, SM_EINVAL, "prepare: two specs of basis kind %d",
                            o->spec[i].kind);
  }
  const sm_basis_spec *lb = sm_prep_spec_of(o, SM_BASIS_LB);
  if (!lb) return sm_error_set(err, SM_EINVAL, "prepare: an LB basis spec is required");
  if (lb->k < 2 || lb->k >= m->nv)
    return sm_error_set(err, SM_EINVAL, "k_lb = %d must be in [2, %d) for this mesh", lb->k,
                        m->nv);
  return SM_OK;
}

/* One basis to compute. */
typedef struct prep_job {
  const sm_mesh *m;
  sm_basis_opts bo;
  sm_basis *b;
  int rc;
  sm_error err;
  double t;
} prep_job;

/* A finished job's thread joins the budget's spare threads (bo.spare_threads), which the
 * jobs still running borrow for their eigensolvers' basis products. */
static void *run_job(void *arg) {
  prep_job *j = arg;
  double t0 = sm_now();
  sm_error_clear(&j->err);
  j->rc = sm_basis_compute(j->m, &j->bo, &j->b, &j->err);
  j->t = sm_now() - t0;
  atomic_fetch_add(j->bo.spare_threads, 1);
  return NULL;
}

/* Runs the n jobs, at most `threads` at once (the calling thread takes one of each wave),
 * the threads of the budget no job runs on spare for them (sm_eigs_opts.spare_threads):
 * on the koala, the LB basis ends first and the elastic eigensolve then runs its products
 * on both threads. A thread that cannot be started runs its job in the calling thread
 * instead. */
static void run_jobs(prep_job *jobs, int n, int threads) {
  _Atomic int spare;
  for (int i = 0; i < n; i++) jobs[i].bo.spare_threads = &spare;
  for (int w = 0; w < n; w += threads) {
    int m = n - w < threads ? n - w : threads;
    atomic_store(&spare, threads - m);
    pthread_t tid[SM_PREP_MAX_BASES];
    int started[SM_PREP_MAX_BASES] = {0};
    for (int i = 1; i < m; i++) started[i] = !pthread_create(&tid[i], NULL, run_job, &jobs[w + i]);
    run_job(&jobs[w]);
    for (int i = 1; i < m; i++) {
      if (started[i]) pthread_join(tid[i], NULL);
      else run_job(&jobs[w + i]);
    }
  }
}

/* The bases of o->spec on m into b[] (spec order): loaded through the hooks, else computed
 * (the misses together, up to o->threads at once) and handed to save. */
static int get_bases(const sm_mesh *m, const sm_prep_opts *o, sm_basis **b, sm_prep_info *info,
                     sm_error *err) {
  const sm_prep_hooks *h = o->hooks;
  prep_job jobs[SM_PREP_MAX_BASES];
  int slot[SM_PREP_MAX_BASES], nj = 0, rc = SM_OK;
  for (int i = 0; i < o->nspec; i++) {
    double t0 = sm_now();
    b[i] = NULL;
    int got = h && h->load ? h->load(h->ud, &o->spec[i], m, &b[i], err) : 0;
    if (got < 0) { /* release what the earlier misses reserved */
      for (int j = 0; j < nj && h->save; j++) h->save(h->ud, &o->spec[slot[j]], NULL);
      return got;
    }
    if (got == 1 && b[i]) {
      info->loaded++;
      info->t_basis[i] = sm_now() - t0;
      continue;
    }
    memset(&jobs[nj], 0, sizeof jobs[nj]);
    jobs[nj].m = m;
    sm_basis_opts_of_spec(&jobs[nj].bo, &o->spec[i]);
    jobs[nj].bo.cancel = o->cancel;
    jobs[nj].bo.cancel_ud = o->cancel_ud;
    slot[nj++] = i;
  }
  if (nj) run_jobs(jobs, nj, o->threads);
  for (int j = 0; j < nj; j++) {
    int i = slot[j];
    info->t_basis[i] = jobs[j].t;
    if (jobs[j].rc && !rc) {
      rc = jobs[j].rc;
      if (err) *err = jobs[j].err;
    }
    if (!jobs[j].rc) info->computed++;
    if (h && h->save) h->save(h->ud, &o->spec[i], jobs[j].rc ? NULL : jobs[j].b);
    b[i] = jobs[j].b;
  }
  return rc;
}

int sm_prepare(const sm_mesh *input, const sm_prep_opts *o, sm_shape **out,
               sm_prep_info *info, sm_error *err) {
  *out = NULL;
  sm_prep_info local;
  if (!info) info = &local;
  memset(info, 0, sizeof *info);
  double t0 = sm_now();
  sm_mesh *m = NULL;
  sm_basis *b[SM_PREP_MAX_BASES] = {0};
  int rc = sm_mesh_clean(input, o->lim, &m, NULL, err);
  if (!rc) rc = sm_mesh_normalize(m, err);
  info->t_clean = sm_now() - t0;
  if (!rc) rc = check_specs(o, m, err);
  if (!rc) rc = get_bases(m, o, b, info, err);
  sm_basis *by_kind[SM_BASIS_NKINDS + 1] = {0};
  for (int i = 0; !rc && i < o->nspec; i++) {
    by_kind[o->spec[i].kind] = b[i];
    rc = sm_basis_fits(b[i], &o->spec[i], m, err); /* a hook's mistake, never served */
  }
  if (rc) {
    sm_mesh_destroy(m);
    for (int i = 0; i < o->nspec; i++) sm_basis_destroy(b[i]);
    return rc;
  }
  double t1 = sm_now();
  rc = sm_shape_assemble(m, by_kind[SM_BASIS_LB], by_kind[SM_BASIS_ELASTIC], o->n_desc, out,
                         err); /* takes m and the bases */
  info->t_desc = sm_now() - t1;
  if (rc) return rc;
  (*out)->t_clean = info->t_clean;
  for (int i = 0; i < o->nspec; i++) {
    if (o->spec[i].kind == SM_BASIS_LB) (*out)->t_lb = info->t_basis[i];
    if (o->spec[i].kind == SM_BASIS_ELASTIC) (*out)->t_elastic = info->t_basis[i];
  }
  return SM_OK;
}

int sm_shape_prepare(const sm_mesh *input, const sm_shape_opts *so, sm_shape **out,
                     sm_error *err) {
  if (so->prep) return sm_prepare(input, so->prep, out, so->prep_info, err);
  sm_prep_opts o;
  sm_prep_opts_from_shape(&o, so);
  return sm_prepare(input, &o, out, NULL, err);
}

int sm_prepare_multires(const sm_mesh *input, const sm_prep_opts *o,
                        const sm_multires_opts *mo, sm_multires_shape **out,
                        sm_prep_info *info, sm_error *err) {
  /* sm_multires prepares its coarse level with sm_shape_prepare, which follows so.prep. */
  sm_shape_opts so;
  sm_shape_opts_default(&so);
  so.prep = o;
  so.prep_info = info;
  so.cancel = o->cancel;
  so.cancel_ud = o->cancel_ud;
  return sm_multires_shape_prepare(input, &so, mo, out, err);
}
