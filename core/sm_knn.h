/* sm_knn: exact K-nearest-neighbour search between point sets in R^d (d = 1 .. a few
 * hundred), Euclidean distance. The hot loop of the matcher (algorithm.md §5-6).
 *
 * Two strategies, chosen by dimension and overridable:
 *   - kd-tree: FLANN's single exact kd-tree (FLANN_INDEX_KDTREE_SINGLE, eps = 0, so its
 *     branch-and-bound prunes only subtrees that cannot hold a closer point: exact).
 *     Wins at low d, and for much longer than on random data when the points lie near a
 *     low-dimensional set (spectral embeddings of a surface).
 *   - brute force: blocks of ||x||^2 + ||y||^2 - 2 x.y with BLAS dgemm, a (K+1)-best list
 *     per query row. The expansion loses digits when x ~ y; whenever the gap between the
 *     K-th and (K+1)-th candidate is below a rounding bound, the row is redone with direct
 *     differences, so the selected set is the exact one.
 *
 * Contract
 *   sm_knn_build copies Y (row-major ny x d) at once: the caller may free it after the call.
 *   The index is owned by the caller (sm_knn_destroy) and read only after build.
 *   sm_knn_query writes, for each of the nx query rows of X (row-major nx x d, borrowed),
 *   the K nearest points of Y in idx[i*K + r] and their squared distances in dist2[i*K + r],
 *   ascending; ties are ordered by index. dist2 is always computed as sum_t (x_t - y_t)^2
 *   in index order over t, whatever the strategy, so both strategies return bit-identical
 *   distances. Which one of several points at exactly the same distance is returned at the
 *   K-th place: the lowest index for brute force, unspecified for the kd-tree.
 *   K must satisfy 1 <= K <= ny. dist2 may be NULL.
 *   Threads: distinct indexes are independent; one index may be queried from several
 *   threads at once. FLANN's C API writes process-wide state on every call (logger level,
 *   random seed), so FLANN calls are serialized by a mutex inside this module; brute force
 *   runs concurrently (BLAS threading is the caller's business). The kd-tree search itself
 *   uses opts.threads OpenMP threads inside FLANN.
 *   Errors: SM_EINVAL (sizes, K, strategy), SM_ENONFINITE (NaN/Inf coordinate in Y or X),
 *   SM_ENOMEM, SM_ENUMERIC (FLANN failure).
 */
#ifndef SM_KNN_H
#define SM_KNN_H

#include <stdint.h>

#include "sm_error.h"

enum sm_knn_strategy { SM_KNN_AUTO = 0, SM_KNN_KDTREE = 1, SM_KNN_BRUTE = 2 };

/* Default dimension from which AUTO uses brute force (see the measurement in sm_knn.c). */
#define SM_KNN_CROSSOVER_D 16

typedef struct sm_knn_opts {
  int strategy;     /* SM_KNN_AUTO (default), SM_KNN_KDTREE or SM_KNN_BRUTE */
  int crossover_d;  /* AUTO: kd-tree for d < crossover_d; 0 = SM_KNN_CROSSOVER_D */
  int threads;      /* kd-tree search threads (OpenMP inside FLANN); 0 = 1: FLANN's
                     * OpenMP workers spin after each search and starved the next BLAS
                     * calls (ZoomOut's fit GEMMs ran 5x slower with 2) */
  int leaf_size;    /* kd-tree leaf size; 0 = 10 */
  int query_threads; /* brute force: each query's rows are split over this many threads
                      * (whole blocks, only for >= 2^20 row x point pairs; at most 8); 0 =
                      * 1. The answers do not depend on it. */
} sm_knn_opts;

typedef struct sm_knn sm_knn;

void sm_knn_opts_default(sm_knn_opts *o);

/* o may be NULL (defaults). */
int sm_knn_build(const double *Y, int32_t ny, int d, const sm_knn_opts *o, sm_knn **out,
                 sm_error *err);
/* A brute-force index of points known as a linear image of fewer coordinates: y_j = L u_j,
 * U row-major ny x dr, L row-major d x dr (both copied). Queries take full d-dimensional
 * rows and answer exactly what sm_knn_build(Y) with the brute-force strategy would (same
 * indices, same distances, bit for bit): only the float screening product runs in dr
 * dimensions (x -> L^T x), the certification and the distances stay in d. Pays when dr is
 * well below d: ZoomOut's bijective embeddings are [C u, u]-shaped, twice the dimensions
 * of their coordinates.
 * Y: NULL (Y = U L^T is formed here by dgemm), or the caller's U L^T (ny x d, row-major),
 * borrowed: it must stay unchanged until sm_knn_destroy. The answers are then exact for
 * that Y; it may differ from U L^T by the rounding of any summation order (the screening
 * bound has room for 1e-8 relative and more), not by more. ZoomOut forms its [C u, u]
 * rows with a quarter of the generic product's flops: homer's final pass on two threads,
 * index builds 0.10 -> 0.03 s, its embeddings 0.05 -> 0.09 s.
 * Errors as sm_knn_build. */
int sm_knn_build_factored(const double *U, int32_t ny, int dr, const double *L, int d,
                          const double *Y, const sm_knn_opts *o, sm_knn **out, sm_error *err);
int sm_knn_query(const sm_knn *ix, const double *X, int32_t nx, int K, int32_t *idx,
                 double *dist2, sm_error *err);
/* Both directions at once: idx / dist2 (nx x K) as sm_knn_query(ix, X, ...), and idx_yx /
 * dist_yx (ny x K: the K nearest query rows of every point of the index) as a query of
 * the index's points against an index of X with the same strategy would give. With a
 * brute-force index the two come from one pass over the distance matrix (one GEMM
 * instead of two) and both follow the brute-force rule (lowest index among ties);
 * otherwise, or when a query row is too far out to screen in float, two queries.
 * K <= min(nx, ny); dist2 and dist_yx may be NULL. */
int sm_knn_query_both(const sm_knn *ix, const double *X, int32_t nx, int K, int32_t *idx,
                      double *dist2, int32_t *idx_yx, double *dist_yx, sm_error *err);
void sm_knn_destroy(sm_knn *ix);

/* The strategy the index uses (SM_KNN_KDTREE or SM_KNN_BRUTE). */
int sm_knn_strategy_of(const sm_knn *ix);

/* Squared distance sum_t (x_t - y_t)^2 in index order: the reference all results use. */
double sm_knn_dist2(const double *x, const double *y, int d);

#endif
