/* sm_basis: the per-shape spectral bases (Laplace-Beltrami and elastic thin-shell) and
 * their versioned, checksummed binary form. Spec: ../shared/design/algorithm.md §2-3.
 *
 * Contract
 *   sm_basis_compute takes a cleaned, normalized mesh (sm_mesh_clean + sm_mesh_normalize;
 *   borrowed, read only) and returns a new basis owned by the caller (sm_basis_destroy).
 *   LB: W phi = lambda M phi, k smallest pairs, Phi^T M Phi = I (gram_L = NULL); the
 *   constant functions (eigenvalue 0, one per component) are part of the basis.
 *   Elastic: H u = lambda M3 u (H the rest thin-shell Hessian, M3 = blockdiag(M, M, M)); the
 *   rigid kernel (found by the eigenvalue gap, 6 per component) is removed, each remaining
 *   mode is projected on the vertex normals, phi_i(v) = n_v . u_i(v); gram_L is the lower
 *   Cholesky factor of Phi^T M Phi; its leading j x j block factors the leading block.
 *   H is assembled after flipping away sliver caps (faces with nearly collinear corners,
 *   lmax^2 / area > 1e4; same vertices, same surface), whose stiffness would otherwise
 *   swamp the spectrum; fewer zero modes than 6 per component is SM_ENUMERIC.
 *   Dense storage is column-major: phi[v + n*i] is function i at vertex v.
 *   Thread-safe on distinct outputs (BLAS threading is the caller's business); the cancel
 *   callback, if set, is polled between eigensolver iterations (SM_ECANCELED).
 *   Serialization: a little-endian file "SMBASIS" + format version + XXH3-64 checksum of
 *   everything after the header; load rejects bad magic, unknown versions, truncation,
 *   trailing bytes, inconsistent sizes and checksum mismatches; what loads is bit-identical
 *   to what was saved. sm_basis_save writes a temp file, fsyncs it and renames it over path.
 */
#ifndef SM_BASIS_H
#define SM_BASIS_H

#include <stdatomic.h>
#include <stddef.h>
#include <stdint.h>

#include "sm_error.h"
#include "sm_mesh.h"

enum sm_basis_kind { SM_BASIS_LB = 1, SM_BASIS_ELASTIC = 2 };
#define SM_BASIS_NKINDS 2          /* kinds are 1..SM_BASIS_NKINDS */
#define SM_BASIS_FORMAT_VERSION 1u /* of the binary form below (sm_basis_io.c) */

/* What a basis is computed from besides its mesh: the unit of preparation (sm_prepare.h),
 * of the daemon's cache and of its file names. eta is the elastic bending weight; it does
 * not apply to LB and is 0 there (sm_basis_spec_check). */
typedef struct sm_basis_spec {
  int kind; /* enum sm_basis_kind */
  int k;    /* functions kept (kernel excluded for elastic) */
  double eta;
} sm_basis_spec;

typedef struct sm_basis_opts {
  int kind;    /* SM_BASIS_LB or SM_BASIS_ELASTIC */
  int k;       /* number of basis functions (kernel excluded for elastic) */
  double eta;  /* bending weight (elastic) */
  double mu, lambda;
  int (*cancel)(void *ud); /* nonzero = stop; may be NULL */
  void *cancel_ud;
  _Atomic int *spare_threads; /* threads the eigensolver may borrow (sm_eigs_opts); NULL */
} sm_basis_opts;

typedef struct sm_basis_timing {
  double assembly, factorization, eigensolve, projection; /* seconds */
  int32_t solves;      /* linear solves done by the eigensolver */
} sm_basis_timing;

typedef struct sm_basis {
  int32_t kind;
  int32_t n;          /* vertices of the (cleaned) mesh */
  int32_t k;          /* functions kept */
  int32_t n_kernel;   /* kernel modes detected and dropped (elastic), 0 for LB */
  int32_t n_components;
  double eta, mu, lambda; /* parameters it was computed with (eta = 0 for LB) */
  uint64_t mesh_hash; /* sm_mesh_hash of the mesh it was computed on */
  double *evals;      /* k, ascending */
  double *phi;        /* n*k, column-major */
  double *mass;       /* n, lumped mass used */
  double *gram_L;     /* k*k column-major lower factor of Phi^T M Phi; NULL if identity */
  sm_basis_timing timing; /* not serialized */
} sm_basis;

void sm_basis_opts_default(sm_basis_opts *o, int kind, int k);
/* The options that compute spec (defaults for what a spec does not name). */
void sm_basis_opts_of_spec(sm_basis_opts *o, const sm_basis_spec *spec);

/* SM_EINVAL naming the field unless spec is computable: a known kind, k >= 1, and eta
 * finite and > 0 for elastic, exactly 0 for LB. */
int sm_basis_spec_check(const sm_basis_spec *spec, sm_error *err);
/* 1 if two specs name the same basis (eta compared bit for bit). */
int sm_basis_spec_eq(const sm_basis_spec *a, const sm_basis_spec *b);
/* A file-name-safe name of spec, e.g. "el.k100.eta3f1a36e2eb1c432d" (eta's bit pattern in
 * hex): stable across versions, so caches named by it stay valid. Returns snprintf's. */
int sm_basis_spec_name(const sm_basis_spec *spec, char *buf, size_t n);
/* SM_OK if b is the basis spec describes, computed on m (kind, k, eta, vertex count and
 * sm_mesh_hash); else SM_EFORMAT naming the first difference. For bases from a cache. */
int sm_basis_fits(const sm_basis *b, const sm_basis_spec *spec, const sm_mesh *m,
                  sm_error *err);

int sm_basis_compute(const sm_mesh *m, const sm_basis_opts *o, sm_basis **out, sm_error *err);
void sm_basis_destroy(sm_basis *b);

/* Kernel size of an ascending spectrum ev[0..nev): the index of the largest ratio jump
 * (at least 1e4) among leading eigenvalues negligible against |ev[nev-1]|; `expected` (6
 * per component for the elastic basis) bounds the search window. 0 if no clear gap. */
int sm_basis_kernel_size(const double *ev, int nev, int expected);

/* XXH3-64 of nv, nf, V and F (bit patterns): ties a stored basis to its mesh. */
uint64_t sm_mesh_hash(const sm_mesh *m);

/* Serialization (sm_basis_io.c). *buf is malloc'd, caller frees; buf in deserialize is
 * borrowed and may be freed right after. */
int sm_basis_serialize(const sm_basis *b, uint8_t **buf, size_t *len, sm_error *err);
int sm_basis_deserialize(const uint8_t *buf, size_t len, sm_basis **out, sm_error *err);
int sm_basis_save(const sm_basis *b, const char *path, sm_error *err);
int sm_basis_load(const char *path, sm_basis **out, sm_error *err);

/* Writes len bytes to path atomically, as sm_basis_save does (unique temp file
 * path.tmp.<pid>.<n> in the same directory, fsync, rename, directory fsync): readers see
 * the old file or the whole new one, also after a crash. SM_EIO naming the step. */
int sm_file_write_atomic(const char *path, const uint8_t *buf, size_t len, sm_error *err);

#endif
