/* sm_sinkhorn: entropy-regularized optimal transport between two point sets over a sparse
 * kernel, solved on the dual potentials (log-domain stable) with eps annealing. Spec:
 * ../shared/design/algorithm.md §5 ("Sinkhorn init").
 *
 * Problem. Points F (nx x d) and G (ny x d), row-major; cost C_ij = |f_i - g_j|^2; masses
 * a (nx) and b (ny). On a support S (below) find the plan P >= 0 minimizing
 *     <C, P> + eps sum_ij P_ij (log P_ij - 1)
 * subject to P 1 = a, P^T 1 = b (balanced, rho = 0), or with the two constraints replaced
 * by rho KL(P 1 | a) + rho KL(P^T 1 | b) (unbalanced, rho > 0; always feasible). The
 * solution is P_ij = exp((f_i + g_j - C_ij) / eps) on S for dual potentials f, g.
 *
 * Support. S = {(i, j): g_j is one of the K nearest g's of f_i} union {f_i is one of the K
 * nearest f's of g_j} union a feasibility backbone: the north-west-corner plan of the 1-D
 * transport between a and b along the principal axis of the union of the two point sets
 * (at most nx + ny - 1 entries). That plan is itself feasible, so the balanced problem on S
 * always has a solution, whatever the geometry (a K-NN support alone may have none: e.g. X
 * clustered, Y spread, every f_i has the same few nearest g's). Backbone entries far from
 * the K-NN ones are costly and end up with negligible mass unless feasibility needs them.
 * Convergence (measured): the backbone makes the balanced problem feasible, but a K-NN
 * support usually holds entries that no feasible plan can use; their duals must diverge,
 * and Sinkhorn then converges sublinearly. On spectral-like embeddings (5k points, d=20,
 * K=16) the L1 row error is ~2e-2 after 330 iterations and ~2e-3 after 3000, while the
 * row-argmax map is already stable (distinct targets 0.96, 0.99 with the bijective
 * extraction). Hence the short default schedule: the map, not the marginals, is the goal.
 * The typical input is already aligned (embeddings through a functional map), so the
 * schedule starts at 0.3 c0, not c0, with 20 iterations per level (80 on the last):
 * 180 iterations in all. On bench_sinkhorn's torus data (5k points, d = 20 and 60) it
 * ends at L1 row error 4e-2 (1e-2 after the former 1 c0 / 50 iterations, 550 in all), with
 * a mean map error 15% lower (0.085 vs 0.100: the argmax of a less converged plan sits
 * nearer the neighbours) and distinct targets 0.95 (vs 0.96).
 * The cure for exact marginals is re-truncation (theta > 0), which replaces the K-NN
 * support by the entries the duals ask for, repeated until it no longer grows; it then
 * matches the dense solution, at the price of an all-pairs scan per round. The unbalanced
 * mode (rho > 0) converges linearly (rate rho/(rho+eps)) on any support, but it destroys
 * mass where the support is thin (rho = 1: 19% L1 row error, lower bijectivity).
 * Nearest neighbours: sm_knn (exact; kd-tree at small d, blocked dgemm brute force
 * otherwise), one index per direction.
 *
 * Iteration. Sinkhorn in scaling form on a stabilized kernel K_ij = exp((f_i + g_j -
 * C_ij)/eps) stored once per support entry, u = a / (K v), v = b / (K^T u) in a single
 * sweep, with log u, log v absorbed into f, g when they leave [e^-50, e^50] and at each
 * eps change (Schmitzer 2019). It computes the log-domain iterates (same duals, same
 * residual) at a fraction of the cost, and falls back to a log-domain step where a
 * kernel sum underflows, so any eps > 0 works. opts.log_domain selects the plain
 * log-domain iteration (reference). Details: the DESIGN comment in sm_sinkhorn.c.
 *
 * Scale. eps, rho and the re-truncation threshold are given relative to
 *     c0 = mean of C_ij over the K-NN entries of S,
 * so they do not depend on the units or the spread of the embeddings (scaling both point
 * sets by s multiplies C, c0 and the absolute eps by s^2 and leaves P unchanged).
 *
 * Contract
 *   F, G, a, b are borrowed, read only, during the call; a and b may be NULL (uniform);
 *   otherwise they must be finite, > 0 and sum to 1 within 1e-6 (they are rescaled to sum
 *   to exactly 1). *plan is allocated here and owned by the caller (sm_plan_destroy); on
 *   error *plan is NULL. No global state: calls on distinct outputs may run concurrently
 *   (sm_knn serializes its FLANN calls; BLAS threading is the caller's business). The cancel callback, if set, is polled once per iteration.
 *   Errors: SM_EINVAL (sizes, options, masses; the message says which), SM_ENONFINITE
 *   (NaN/Inf coordinate), SM_ENOMEM, SM_ELIMIT (re-truncation keeps too many entries),
 *   SM_ENUMERIC (nearest-neighbour library failure or non-finite duals), SM_ECANCELED.
 *   Not reaching the tolerance is not an error: see stats.converged and the errors.
 */
#ifndef SM_SINKHORN_H
#define SM_SINKHORN_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_knn.h"


/* Every field's 0 means "default", so `sm_sinkhorn_opts o = {0};` is a valid start. */
typedef struct sm_sinkhorn_opts {
  int k;            /* neighbours per point and direction (default 16); >= ny/nx = dense */
  double eps_start; /* first eps, relative to c0 (default 0.3) */
  double eps_end;   /* last eps, relative to c0 (default 0.01) */
  double decay;     /* eps_{l+1} = max(eps_end, decay * eps_l), in (0, 1) (default 0.5) */
  int max_iter;     /* iterations per eps level (default 20; the last level gets 4x) */
  double tol;       /* L1 marginal residual ending the last level (default 1e-6);
                       intermediate levels stop at max(tol, 1e-3) */
  double rho;       /* > 0: unbalanced with marginal penalty rho * c0; 0: balanced */
  int no_backbone;  /* 1: do not add the feasibility backbone (balanced may then fail
                       to converge; for measurements) */
  double theta;     /* > 0: after the last level, re-truncate the support from the duals
                       (keep (i, j) with P_ij >= exp(-theta) * min(a_i, b_j), searched
                       over all pairs) and iterate again; 0: off */
  int knn;          /* enum sm_knn_strategy (default AUTO: sm_knn's rule, kd-tree for
                       d < SM_KNN_CROSSOVER_D) */
  int threads;      /* neighbour search threads (default 2): the kd-tree search's, or
                       the two brute-force directions run concurrently when their K
                       differ (with one K, brute force does both in one pass, its query
                       rows split over the threads: sm_knn_query_both). sm_match passes
                       its own (1 in the daemon) */
  int log_domain;   /* 1: plain log-domain iterations, no kernel scaling (the slow
                       reference path; for tests and measurements) */
  int (*cancel)(void *ud); /* nonzero = stop (SM_ECANCELED); may be NULL */
  void *cancel_ud;
} sm_sinkhorn_opts;

typedef struct sm_sinkhorn_stats {
  int iterations;      /* all levels together (one iteration = row + column update) */
  int levels;          /* eps levels run */
  int converged;       /* 1 if the last level reached tol */
  int absorptions;     /* kernel recomputations inside levels (scalings out of bounds,
                          or log-domain fallback steps) */
  double c0;           /* cost scale (absolute) */
  double eps;          /* final eps (absolute) */
  double residual;     /* last L1 residual of the row optimality condition */
  double err_a, err_b; /* L1 marginal errors |P 1 - a|_1, |P^T 1 - b|_1 of the plan */
  int64_t nnz;         /* support size */
  int64_t nnz_knn;     /* of which K-NN entries (before the backbone) */
  double t_knn, t_setup, t_iter, t_total; /* seconds: neighbour search, support and cost
                                             assembly, iterations (+ re-truncation), all */
} sm_sinkhorn_stats;

/* A sparse plan in CSR form; columns sorted within each row. */
typedef struct sm_plan {
  int32_t nx, ny;
  int64_t nnz;
  int64_t *rowptr; /* nx + 1 */
  int32_t *col;    /* nnz */
  double *val;     /* nnz, P_ij */
  double *f, *g;   /* nx, ny: dual potentials (cost units), P_ij = exp((f+g-C)/eps) */
  double eps;      /* absolute eps of the duals */
} sm_plan;

void sm_sinkhorn_opts_default(sm_sinkhorn_opts *o);

/* Solves the problem above. st may be NULL. */
int sm_sinkhorn(const double *F, int32_t nx, const double *G, int32_t ny, int32_t d,
                const double *a, const double *b, const sm_sinkhorn_opts *opts,
                sm_plan **plan, sm_sinkhorn_stats *st, sm_error *err);

void sm_plan_destroy(sm_plan *p);

/* T[i] = argmax_j P_ij (nx entries; -1 for an empty row). */
void sm_plan_row_argmax(const sm_plan *p, int32_t *T);
/* T_yx[j] = argmax_i P_ij (ny entries; -1 for an empty column). SM_ENOMEM only. */
int sm_plan_col_argmax(const sm_plan *p, int32_t *T_yx);

/* A point map X -> Y that uses each target at most once where it can: entries are taken
 * greedily by decreasing P_ij / (row mass of i) (the conditional probability of j given
 * i, so that small-area vertices are not outranked by large ones), assigning i -> j when
 * both are still free; rows left over (there are nx - ny of them at least when nx > ny,
 * or rows whose support is all taken) get their row argmax. T has nx entries.
 * SM_ENOMEM only. */
int sm_plan_extract_bijective(const sm_plan *p, int32_t *T, sm_error *err);

/* Number of distinct targets hit by T (nx entries, values in [0, ny) or -1), divided by
 * min(nx, ny): 1 for a bijection. NaN if nx or ny < 1 or out of memory. */
double sm_plan_map_distinct(const int32_t *T, int32_t nx, int32_t ny);

/* L1 marginal errors |P 1 - a|_1 and |P^T 1 - b|_1 (a, b NULL = uniform). SM_ENOMEM only. */
int sm_plan_marginal_error(const sm_plan *p, const double *a, const double *b,
                           double *err_a, double *err_b);

#endif
