/* sm_synth: analytic meshes the project makes itself (demo data for the README's main
 * command, benchmarks and tests): icosphere, torus, and smooth "blob" deformations of a
 * sphere that give non-isometric shape pairs with a known correspondence (the identity).
 *
 * Contract: returns a new mesh owned by the caller; no global state; thread-safe.
 */
#ifndef SM_SYNTH_H
#define SM_SYNTH_H

#include "sm_error.h"
#include "sm_mesh.h"

/* Unit icosphere: 10*4^subdiv + 2 vertices, outward faces. subdiv in [0, 8]. */
int sm_synth_icosphere(int subdiv, sm_mesh **out, sm_error *err);

/* Torus with nu x nv vertices, major radius R, minor radius r. */
int sm_synth_torus(int nu, int nv, double R, double r, sm_mesh **out, sm_error *err);

/* Icosphere whose radius is modulated by a smooth field: r(p) = 1 + amp * sum of a few
 * low-frequency bumps chosen by `seed`, then stretched by (sx, sy, sz). Same connectivity
 * and vertex order for every seed, so two blobs correspond by identity. */
int sm_synth_blob(int subdiv, double amp, unsigned seed, const double stretch[3],
                  sm_mesh **out, sm_error *err);

#endif
