#include "sm_desc.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* First index with a positive eigenvalue: LB bases start with one zero per component. */
static int first_positive(const sm_basis *b, int k) {
  double top = fabs(b->evals[k - 1]);
  int i = 0;
  while (i < k && b->evals[i] <= 1e-9 * top) i++;
  return i;
}

static int check(const sm_basis *b, int k, int nd, sm_error *err) {
  if (b->gram_L)
    return sm_error_set(err, SM_EINVAL, "descriptors need an orthonormal (LB) basis");
  if (k < 2 || k > b->k || nd < 1)
    return sm_error_set(err, SM_EINVAL, "descriptor sizes k = %d (basis has %d), nd = %d", k,
                        b->k, nd);
  if (first_positive(b, k) >= k - 1)
    return sm_error_set(err, SM_EINVAL, "fewer than two positive eigenvalues in %d", k);
  return SM_OK;
}

/* D[:, j] = sum_i w[j*k + i] phi_i^2, then each column normalized by its mass norm. */
static void weighted_squares(const sm_basis *b, int first, int k, int nd, const double *w,
                             double *D) {
  int32_t n = b->n;
  memset(D, 0, (size_t)n * nd * sizeof *D);
  for (int i = first; i < k; i++) {
    const double *phi = b->phi + (size_t)i * n;
    for (int j = 0; j < nd; j++) {
      double c = w[(size_t)j * k + i];
      if (c < 1e-300) continue;
      double *d = D + (size_t)j * n;
      for (int32_t v = 0; v < n; v++) d[v] += c * phi[v] * phi[v];
    }
  }
  for (int j = 0; j < nd; j++) {
    double *d = D + (size_t)j * n, s = 0;
    for (int32_t v = 0; v < n; v++) s += b->mass[v] * d[v] * d[v];
    s = s > 0 ? 1.0 / sqrt(s) : 0.0;
    for (int32_t v = 0; v < n; v++) d[v] *= s;
  }
}

int sm_desc_wks(const sm_basis *b, int k, int nd, double width, double *D, sm_error *err) {
  int rc = check(b, k, nd, err);
  if (rc) return rc;
  int first = first_positive(b, k);
  double emin = log(b->evals[first]), emax = log(b->evals[k - 1]);
  double sigma = (width > 0 ? width : 7.0) * (emax - emin) / nd;
  /* Keep the energies two widths inside the spectrum so every band is covered. */
  emin += 2 * sigma;
  emax -= 2 * sigma;
  if (emax <= emin) emax = emin = 0.5 * (emin + emax);
  double *w = calloc((size_t)nd * k, sizeof *w);
  if (!w) return sm_error_set(err, SM_ENOMEM, "WKS: out of memory");
  for (int j = 0; j < nd; j++) {
    double e = nd > 1 ? emin + (emax - emin) * j / (nd - 1) : emin, sum = 0;
    for (int i = first; i < k; i++) {
      double z = e - log(b->evals[i]);
      sum += (w[(size_t)j * k + i] = exp(-z * z / (2 * sigma * sigma)));
    }
    for (int i = first; i < k && sum > 0; i++) w[(size_t)j * k + i] /= sum;
  }
  weighted_squares(b, first, k, nd, w, D);
  free(w);
  return SM_OK;
}

int sm_desc_hks(const sm_basis *b, int k, int nd, double *D, sm_error *err) {
  int rc = check(b, k, nd, err);
  if (rc) return rc;
  int first = first_positive(b, k);
  double tmin = 4 * log(10.0) / b->evals[k - 1], tmax = 4 * log(10.0) / b->evals[first];
  double *w = calloc((size_t)nd * k, sizeof *w);
  if (!w) return sm_error_set(err, SM_ENOMEM, "HKS: out of memory");
  for (int j = 0; j < nd; j++) {
    double t = nd > 1 ? tmin * pow(tmax / tmin, (double)j / (nd - 1)) : tmin;
    for (int i = first; i < k; i++) w[(size_t)j * k + i] = exp(-t * b->evals[i]);
  }
  weighted_squares(b, first, k, nd, w, D);
  free(w);
  return SM_OK;
}
