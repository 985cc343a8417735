/* sm_fmap: functional maps between two shapes in possibly non-orthogonal bases, the
 * point map they induce, and ZoomOut refinement. Spec: ../shared/design/algorithm.md §4, §6.
 *
 * Conventions. X is the source, Y the target; a point map T: X -> Y is T[i] = vertex of Y
 * for vertex i of X, indices into the meshes the bases were computed on. A functional map
 * C (k x k, column-major) carries coefficients of a function on Y to the coefficients of its
 * pull-back on X. Phi (X) has Gram A = Phi^T M_X Phi = L_A L_A^T, Psi (Y) has B = L_B L_B^T
 * (gram_L == NULL means the identity); the leading k x k block of L factors the leading
 * block of the Gram, so one factor serves every k.
 *   P -> C:  C = A^-1 Phi_k^T M_X Psi_k[T, :]       (M_X-weighted least squares)
 *   C -> P:  T[i] = argmin_j |a_i - b_j|,  a_i = L_A^-1 Phi_k[i,:]^T,
 *            b_j = L_A^T C B^-1 Psi_k[j,:]^T
 * In the whitened coordinates u = L^-1 Phi^T (orthonormal in L2) the map is
 * Cw = L_A^T C L_B^-T and a_i = u^X_i, b_j = Cw u^Y_j: ordinary ZoomOut. The code works
 * in those coordinates (a triangular solve per shape, then only GEMMs).
 * Hybrid (Bastian et al. 2024): up to SM_FMAP_MAX_PAIRS basis pairs (e.g. LB and elastic),
 * one C per pair, each with its own k; the nearest-neighbour search runs on the
 * concatenation [w_1 a^(1), w_2 a^(2)] against [w_1 b^(1), w_2 b^(2)].
 *
 * ZoomOut (sm_zoomout): for t = 0 .. niter-1: C_p = fmap(T, k_p(t)); T = p2p(C, k(t)).
 *   Schedule: pair 0 runs k = k0, k0 + step, ..., and always ends at k (its last step may be
 *   shorter); that fixes niter. Every other pair goes from its k0 to its k in the same niter
 *   iterations, rounded linearly.
 *   Sampling: when nsample_x (nsample_y) is below the vertex count, the iterations run on
 *   a farthest-point sample of X (Y): queries are the X samples, candidates the Y samples;
 *   the last full_y_last iterations take all of Y as candidates, and the very last maps
 *   every X vertex to any Y vertex. P -> C on a sample is the least squares restricted to the
 *   samples, each weighted by the mass of its farthest-point (Voronoi) cell:
 *   Cw = G_s^-1 U_s^T W Psi_w[T_s], G_s = U_s^T W U_s, an approximation of the full
 *   M_X-weighted fit (G_s ~ I, not exactly I): a quadrature of the L2 inner product.
 *   Sampling X keeps an exact map exact (the restricted least squares is consistent).
 *   Sampling Y blurs the intermediate maps (an X sample can only reach a Y sample); the
 *   all-Y final iterations remove most of it, not always all: on a permuted 642-vertex
 *   blob, 300/300 samples, full_y_last 1/2/3 left 106/49/17 vertices one ring off with
 *   the LB basis, 0 with the elastic and hybrid ones.
 *   nsample_y trades that for speed: the kNN work is proportional to nsample_x * nsample_y.
 *   Farthest-point sampling measures Euclidean distance on opts.pos_x / pos_y (vertex
 *   positions, row-major n x 3) when given, otherwise on the whitened spectral embedding of
 *   pair 0 truncated to its k0 columns. It starts from the vertex farthest from vertex 0;
 *   deterministic.
 *   Y -> X map (optional T_yx): the nearest X vertex of each Y vertex in the same final
 *   embedding space (same C): T_yx[j] = argmin_i |a_i - b_j|. Not a second ZoomOut: the
 *   adjoint assignment of the same functional map, found in the same pass over the
 *   distances as the last iteration's assignment (sm_knn_query_both).
 *   C_out (optional) is the C whose point map is the returned T (the final iteration's).
 *   Bijective variant (opts.bijective = w > 0; Ren et al. 2021, "Discrete optimization for
 *   shape matching"): a second map D (X coefficients to Y coefficients) is fitted from a
 *   Y -> X point map S on the Y fit set (the Y samples, weighted by their cells like X's),
 *   and both point maps come from one nearest-neighbour problem between
 *     a_i = [u^X_i, w D u^X_i]   and   b_j = [C u^Y_j, w u^Y_j]:
 *   T[i] = argmin_j |a_i - b_j| (C's properness plus D's), S[j] = argmin_i |a_i - b_j|, so
 *   the two maps are pulled toward each other's inverse. The first iteration has no S yet
 *   and runs as plain ZoomOut, whose adjoint assignment starts S (a Y -> X map handed in
 *   was tried: no better on the gorilla pairs, and a noisy one spoiled an exact T on a
 *   test blob). About twice the kNN
 *   work per iteration. With samples_y given, cellw_y must be too.
 *
 * Contract
 *   Bases are borrowed, read only; all pairs must share the X mesh (same n and mesh_hash)
 *   and the Y mesh. Outputs are caller-allocated: C (k x k), T (n_X), T_yx (n_Y).
 *   No global state: calls are thread-safe on distinct outputs (BLAS threading and the
 *   kNN's internal FLANN mutex aside, see sm_knn.h). The cancel callback (may be NULL) is
 *   polled before each ZoomOut iteration (SM_ECANCELED).
 *   Errors: SM_EINVAL (sizes, k, schedule, mismatched bases), SM_ERANGE (T entry outside Y),
 *   SM_ENOMEM, SM_ENUMERIC (sample Gram not positive definite: too few samples for k),
 *   SM_ECANCELED; kNN errors pass through.
 */
#ifndef SM_FMAP_H
#define SM_FMAP_H

#include <stdint.h>

#include "sm_basis.h"
#include "sm_error.h"
#include "sm_knn.h"

#define SM_FMAP_MAX_PAIRS 2

typedef struct sm_fmap_pair {
  const sm_basis *x; /* basis on X (borrowed) */
  const sm_basis *y; /* basis on Y (borrowed) */
  int k;             /* functions used: by the one-shot calls, and ZoomOut's final k */
  int k0;            /* ZoomOut's first k (ignored by the one-shot calls) */
  double weight;     /* scale of this pair's embedding in the joint search; 0 means 1 */
} sm_fmap_pair;

/* P -> C: C (k x k, column-major) from T (n_X entries in [0, n_Y)). */
int sm_fmap_from_p2p(const sm_basis *x, const sm_basis *y, int k, const int32_t *T, double *C,
                     sm_error *err);

/* C -> P: T (n_X) from one C per pair (C[p] is pairs[p].k square, column-major). T_yx (n_Y)
 * may be NULL; ko may be NULL (kNN defaults). */
int sm_fmap_to_p2p(const sm_fmap_pair *pairs, int npairs, const double *const *C, int32_t *T,
                   int32_t *T_yx, const sm_knn_opts *ko, sm_error *err);

/* The same for the X vertices rows[0 .. nrows) only: T[rows[r]] is written, every other
 * entry of T (n_X) is left as it was. For a caller that needs the map on a sample (the
 * start of a ZoomOut on that sample). Errors also SM_ERANGE (a row outside X). */
int sm_fmap_to_p2p_rows(const sm_fmap_pair *pairs, int npairs, const double *const *C,
                        const int32_t *rows, int32_t nrows, int32_t *T, const sm_knn_opts *ko,
                        sm_error *err);

/* The embeddings themselves (for other assignment schemes, e.g. Sinkhorn): row-major, row
 * stride ld >= k, only columns [0, k) written. E_x: n_X rows a_i; E_y: n_Y rows b_j. */
int sm_fmap_embed_x(const sm_basis *x, int k, double *E_x, int ld, sm_error *err);
int sm_fmap_embed_y(const sm_basis *x, const sm_basis *y, int k, const double *C, double *E_y,
                    int ld, sm_error *err);

typedef struct sm_zoomout_opts {
  int step;              /* k increment of pair 0 per iteration; >= 1 */
  int nsample_x;         /* intermediate iterations on this many X samples; 0 = all */
  int nsample_y;         /* same for the Y candidates; 0 = all (see below) */
  int full_y_last;       /* with nsample_y: final iterations on all Y candidates; 0 = 3 */
  const double *pos_x;   /* n_X x 3 positions for farthest-point sampling, or NULL */
  const double *pos_y;   /* n_Y x 3, or NULL */
  /* Optional precomputed samples (e.g. cached per shape): when set, used instead of
   * sampling. samples_x / cellw_x: nsample_x vertices of X and the masses of their cells,
   * as sm_fmap_fps returns them; samples_y: nsample_y vertices of Y. */
  const int32_t *samples_x;
  const double *cellw_x;
  const int32_t *samples_y;
  const double *cellw_y; /* the masses of samples_y's cells (needed when bijective) */
  /* Bijective variant: the weight of the bijectivity term (0 = off; see above). */
  double bijective;
  /* Fixed features (optional, not with the bijective variant): nfeat columns appended to
   * both embeddings, row i of feat_x (n_X x nfeat, row-major) against row j of feat_y
   * (n_Y x nfeat), scaled by feat_w. They are not carried by C: functions known to
   * correspond (landmark heat kernels) that keep every assignment near the landmarks. */
  const double *feat_x, *feat_y;
  int nfeat;
  double feat_w;
  sm_knn_opts knn;       /* nearest-neighbour strategy */
  int threads;           /* the pairs' fits and embeddings of an iteration run on this many
                          * threads (0 = 1; the kNN's own: knn.query_threads). The maps do
                          * not depend on it. */
  int (*cancel)(void *ud);
  void *cancel_ud;
} sm_zoomout_opts;

typedef struct sm_zoomout_stats {
  int iterations;
  double t_setup;  /* whitening, sampling, sample Gram (s) */
  double t_fmap;   /* P -> C solves, all iterations */
  double t_embed;  /* building the embeddings */
  double t_knn;    /* kNN build + query */
  double t_total;
} sm_zoomout_stats;

/* Farthest-point sampling as ZoomOut does it: ns vertices S of the n points P (row stride
 * ldp, first dim coordinates), greedy farthest-first from the point farthest from point 0;
 * cellw[s] = mass of the points whose nearest sample is S[s]. Deterministic. O(n ns dim).
 * Errors: SM_EINVAL, SM_ENOMEM. */
int sm_fmap_fps(const double *P, int32_t n, int dim, int ldp, const double *mass, int32_t ns,
                int32_t *S, double *cellw, sm_error *err);

/* step 1, nsample_x = 2000, nsample_y = 0 (all), no positions, default kNN. */
void sm_zoomout_opts_default(sm_zoomout_opts *o);

/* Refines T0 (n_X entries, any map X -> Y) into T (n_X; may alias T0). C_out (npairs
 * pointers to k x k, or NULL; entries may be NULL), T_yx (n_Y or NULL) and st (or NULL)
 * are optional outputs. */
int sm_zoomout(const sm_fmap_pair *pairs, int npairs, const sm_zoomout_opts *o,
               const int32_t *T0, int32_t *T, double *const *C_out, int32_t *T_yx,
               sm_zoomout_stats *st, sm_error *err);

#endif
