/* sm_prepare: the one preparation of a shape, for every caller (sm_shape_prepare, the CLI,
 * the benchmarks, the daemon's store).
 *
 *   input mesh -> sm_mesh_clean (within o->lim) -> sm_mesh_normalize (unit area) -> one
 *   basis per spec in o->spec (each one loaded through the caller's hooks when it has it,
 *   else computed and handed to them to keep) -> WKS descriptors from the LB basis
 *   (sm_shape_assemble).
 *   sm_prepare_multires: the coarse level of sm_multires.h (clean, decimate, prepare the
 *   coarse mesh as above with the same specs and hooks, locate the fine vertices).
 *
 * Why hooks: the daemon's store keeps bases on disk and shares them between daemons; the
 * mathematics and its order stay here, the store only says where a piece comes from and
 * where it goes (sm_srv_store.c). Pieces are whole bases, keyed by their spec and checked
 * against the mesh they were computed on (sm_basis_fits), so a stale or foreign file is
 * never used.
 *
 * Contract
 *   Hooks (all optional; ud passed back):
 *     load(ud, spec, m, &b): 1 and *b (the caller's basis, now owned by the shape) when it
 *       has the basis of spec on m (cleaned, normalized; the hook checks it with
 *       sm_basis_fits), 0 when it has not, or a negative SM_E* code with a message in err
 *       (the preparation fails with it, e.g. SM_ECANCELED while waiting for another
 *       process). After a 0, save is called exactly once for that spec: with the computed
 *       basis (borrowed; the hook copies or serializes it), or with NULL when the
 *       computation failed, was cancelled or never ran. So load may reserve something (e.g.
 *       a lock that makes other processes wait for this computation) that save releases.
 *       Hooks are called from the calling thread, in spec order.
 *   Threads: o->threads bounds the bases computed at once (1 = one after another, in the
 *     calling thread; more = one thread each, up to that many), and the threads of that
 *     budget no basis runs on (fewer bases than threads, or a basis already done) are lent
 *     to the eigensolvers still running, for their Krylov basis products
 *     (sm_eigs_opts.spare_threads; the bases are the same bit for bit whatever they get).
 *     BLAS threading is the caller's business. No global state; re-entrant.
 *   Errors: 0 or a negative SM_E* code with a message: SM_EINVAL (a bad spec or a k the
 *     mesh cannot carry, naming it), SM_ECANCELED (o->cancel), SM_ENOMEM, and those of the
 *     mesh cleaning and sm_basis_compute. *out is NULL on failure.
 */
#ifndef SM_PREPARE_H
#define SM_PREPARE_H

#include "sm_basis.h"
#include "sm_error.h"
#include "sm_match.h"
#include "sm_mesh.h"
#include "sm_multires.h"

#define SM_PREP_MAX_BASES 4 /* specs per preparation: one per kind today, room for more */

typedef struct sm_prep_hooks {
  int (*load)(void *ud, const sm_basis_spec *spec, const sm_mesh *m, sm_basis **out,
              sm_error *err);
  void (*save)(void *ud, const sm_basis_spec *spec, const sm_basis *b);
  void *ud;
} sm_prep_hooks;

typedef struct sm_prep_opts {
  sm_basis_spec spec[SM_PREP_MAX_BASES]; /* at most one per kind; an LB spec is required
                                            (descriptors, coarse map) */
  int nspec;
  int n_desc;                 /* WKS energies */
  int threads;                /* bases computed at once, >= 1 */
  const sm_limits *lim;       /* cleaning limits; NULL = none */
  const sm_prep_hooks *hooks; /* NULL = compute everything, keep nothing */
  int (*cancel)(void *ud);    /* polled by the eigensolvers; may be NULL */
  void *cancel_ud;
} sm_prep_opts;

/* Per call; times in seconds, per spec in o->spec order. */
typedef struct sm_prep_info {
  double t_clean, t_desc;
  double t_basis[SM_PREP_MAX_BASES]; /* loading or computing it */
  int loaded, computed;              /* bases by origin */
} sm_prep_info;

/* Specs of the shipped preparation: LB k_lb, and elastic k_el with bending weight eta
 * when k_el > 0. Returns the count (1 or 2). */
int sm_prep_default_specs(sm_basis_spec *spec, int k_lb, int k_el, double eta);
/* o = the shipped preparation: LB and elastic k = 100, default eta, 100 WKS energies,
 * one thread, no limits, no hooks. */
void sm_prep_opts_default(sm_prep_opts *o);
/* o from the legacy sm_shape_opts (k_lb, k_elastic, eta, n_desc, cancel). */
void sm_prep_opts_from_shape(sm_prep_opts *o, const sm_shape_opts *so);

/* Approximate bytes held by a prepared shape (mesh, bases, descriptors): cache budgets. */
size_t sm_shape_bytes(const sm_shape *s);
/* Bases a prepared shape holds. */
int sm_shape_nbases(const sm_shape *s);

/* The spec of kind in o, or NULL. */
const sm_basis_spec *sm_prep_spec_of(const sm_prep_opts *o, int kind);

int sm_prepare(const sm_mesh *input, const sm_prep_opts *o, sm_shape **out,
               sm_prep_info *info, sm_error *err);

/* The multi-resolution shape (sm_multires.h) whose coarse level is prepared by sm_prepare
 * with o (so its bases go through o->hooks: a caller that caches them names them apart from
 * the full-resolution ones, e.g. by the coarse target size). info covers the coarse level's
 * bases; the clean / decimate / locate times are in the shape. */
int sm_prepare_multires(const sm_mesh *input, const sm_prep_opts *o,
                        const sm_multires_opts *mo, sm_multires_shape **out,
                        sm_prep_info *info, sm_error *err);

#endif
