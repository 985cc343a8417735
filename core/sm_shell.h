/* sm_shell: the discrete thin-shell energy and its closed-form Hessian at the rest state.
 * Spec: ../shared/design/algorithm.md §3.1-3.2.
 *
 *   E[x] = E_mem[x] + eta * E_bend[x]
 *   E_mem  = sum_f A_bar_f W(tr G, det G),  G = g_bar^-1 g (first fundamental forms),
 *            W(a, d) = mu/2 a + lambda/4 d - (mu/2 + lambda/4) log d - mu - lambda/4
 *   E_bend = sum_hinges 3 (theta - theta_bar)^2 |e_bar|^2 / (A_bar_1 + A_bar_2)
 *
 * Contract
 *   `rest` is the undeformed mesh (usually cleaned and normalized), `topo` its sm_edges
 *   (hinges = edges with exactly two faces; boundary and non-manifold edges get no bending
 *   term). Both are borrowed, read only. Positions x are 3*nv doubles laid out like rest->V.
 *   Pure functions, no global state: thread-safe. Errors: SM_ENOMEM, SM_EINVAL (a rest
 *   face of zero area), SM_ENONFINITE (energy undefined: a face of x inverted to zero area).
 */
#ifndef SM_SHELL_H
#define SM_SHELL_H

#include "sm_error.h"
#include "sm_mesh.h"
#include "sm_sparse.h"
#include "sm_topology.h"

typedef struct sm_shell_params {
  double mu, lambda; /* membrane Lame parameters; 1, 1 by default */
  double eta;        /* bending weight */
} sm_shell_params;

/* mu = lambda = 1, eta = SM_SHELL_DEFAULT_ETA. */
void sm_shell_params_default(sm_shell_params *p);
#define SM_SHELL_DEFAULT_ETA 1e-4

/* Nonlinear energy of deformed positions x; *E = E_mem + eta E_bend, and the two parts
 * separately in *E_mem, *E_bend (either may be NULL). E[rest->V] = 0. */
int sm_shell_energy(const sm_mesh *rest, const sm_edges *topo, const sm_shell_params *p,
                    const double *x, double *E, double *E_mem, double *E_bend, sm_error *err);

/* Appends the 3nv x 3nv rest-state Hessian (membrane + eta * bending) to t, which must have
 * been initialised with n = 3*nv. Dof of vertex v coordinate c is 3v + c. */
int sm_shell_hessian(const sm_mesh *rest, const sm_edges *topo, const sm_shell_params *p,
                     sm_triplets *t, sm_error *err);

#endif
