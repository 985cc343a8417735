/* sm_desc: intrinsic point descriptors from a Laplace-Beltrami basis — the Wave Kernel
 * Signature (Aubry, Schlickewei, Cremers 2011) and the Heat Kernel Signature (Sun,
 * Ovsjanikov, Guibas 2009). Both are functions of the spectrum and the squared
 * eigenfunctions only, hence invariant to isometries, vertex order, sign flips of the
 * eigenfunctions and, at unit area, to scale; and blind to left/right symmetry.
 *
 * Contract
 *   The basis is borrowed (an M-orthonormal LB basis: gram_L == NULL). Output D is a
 *   caller-provided n x nd column-major array: D[v + n*j] = descriptor j at vertex v.
 *   Each descriptor column is scaled to unit mass-weighted L2 norm (sqrt(sum m_v D^2) = 1)
 *   so that no energy band dominates a least-squares fit. Eigenvalues <= 0 (the constant
 *   functions) are skipped. Pure functions, thread-safe.
 */
#ifndef SM_DESC_H
#define SM_DESC_H

#include "sm_basis.h"
#include "sm_error.h"

/* WKS at nd log-spaced energies over the first k eigenpairs (k <= b->k). The Gaussian width
 * is `width` times the energy step (7 is the customary value; 0 = 7). */
int sm_desc_wks(const sm_basis *b, int k, int nd, double width, double *D, sm_error *err);

/* HKS at nd log-spaced times between 4 ln10 / lambda_max and 4 ln10 / lambda_1. */
int sm_desc_hks(const sm_basis *b, int k, int nd, double *D, sm_error *err);

#endif
