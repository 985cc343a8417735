#include "sm_sparse.h"

#include <stdlib.h>
#include <string.h>

int sm_triplets_init(sm_triplets *t, int32_t n, int64_t cap_hint) {
  memset(t, 0, sizeof *t);
  t->n = n;
  t->cap = cap_hint > 16 ? cap_hint : 16;
  t->row = malloc((size_t)t->cap * sizeof *t->row);
  t->col = malloc((size_t)t->cap * sizeof *t->col);
  t->val = malloc((size_t)t->cap * sizeof *t->val);
  if (!t->row || !t->col || !t->val) {
    sm_triplets_free(t);
    return SM_ENOMEM;
  }
  return SM_OK;
}

void sm_triplets_free(sm_triplets *t) {
  free(t->row);
  free(t->col);
  free(t->val);
  memset(t, 0, sizeof *t);
}

static int grow(sm_triplets *t) {
  int64_t cap = t->cap * 2;
  int32_t *r = realloc(t->row, (size_t)cap * sizeof *r);
  if (!r) return SM_ENOMEM;
  t->row = r;
  int32_t *c = realloc(t->col, (size_t)cap * sizeof *c);
  if (!c) return SM_ENOMEM;
  t->col = c;
  double *v = realloc(t->val, (size_t)cap * sizeof *v);
  if (!v) return SM_ENOMEM;
  t->val = v;
  t->cap = cap;
  return SM_OK;
}

int sm_triplets_add(sm_triplets *t, int32_t i, int32_t j, double v) {
  if (t->len == t->cap && grow(t)) return SM_ENOMEM;
  if (i < j) {
    int32_t s = i;
    i = j;
    j = s;
  }
  t->row[t->len] = i;
  t->col[t->len] = j;
  t->val[t->len] = v;
  t->len++;
  return SM_OK;
}

int sm_triplets_add_block3(sm_triplets *t, int32_t bi, int32_t bj, const double B[9]) {
  for (int a = 0; a < 3; a++)
    for (int b = 0; b < 3; b++) {
      int32_t i = 3 * bi + a, j = 3 * bj + b;
      if (bi == bj && j > i) continue;
      if (sm_triplets_add(t, i, j, B[3 * a + b])) return SM_ENOMEM;
    }
  return SM_OK;
}

/* Two counting passes: bucket by column, then by row within each column, so rows come
 * out sorted without a comparison sort; duplicates become adjacent and are summed. */
int sm_triplets_to_csc(const sm_triplets *t, sm_csc **out, sm_error *err) {
  int32_t n = t->n;
  int64_t len = t->len;
  sm_csc *a = calloc(1, sizeof *a);
  int64_t *rowcnt = calloc((size_t)n + 1, sizeof *rowcnt);
  int64_t *colcnt = calloc((size_t)n + 1, sizeof *colcnt);
  int64_t *byrow = malloc((size_t)(len ? len : 1) * sizeof *byrow);
  int64_t *bycol = malloc((size_t)(len ? len : 1) * sizeof *bycol);
  *out = NULL;
  if (!a || !rowcnt || !colcnt || !byrow || !bycol) goto nomem;
  for (int64_t e = 0; e < len; e++) rowcnt[t->row[e] + 1]++;
  for (int32_t i = 0; i < n; i++) rowcnt[i + 1] += rowcnt[i];
  for (int64_t e = 0; e < len; e++) byrow[rowcnt[t->row[e]]++] = e;
  /* byrow is sorted by row; a stable bucket by column keeps rows sorted per column. */
  for (int64_t e = 0; e < len; e++) colcnt[t->col[e] + 1]++;
  for (int32_t j = 0; j < n; j++) colcnt[j + 1] += colcnt[j];
  for (int64_t q = 0; q < len; q++) {
    int64_t e = byrow[q];
    bycol[colcnt[t->col[e]]++] = e;
  }
  /* colcnt[j] now holds the end of column j. */
  a->n = n;
  a->colptr = malloc(((size_t)n + 1) * sizeof *a->colptr);
  a->rowind = malloc((size_t)(len ? len : 1) * sizeof *a->rowind);
  a->val = malloc((size_t)(len ? len : 1) * sizeof *a->val);
  if (!a->colptr || !a->rowind || !a->val) goto nomem;
  int64_t nnz = 0, start = 0;
  for (int32_t j = 0; j < n; j++) {
    a->colptr[j] = (int32_t)nnz;
    int32_t last = -1;
    for (int64_t q = start; q < colcnt[j]; q++) {
      int64_t e = bycol[q];
      if (t->row[e] == last) {
        a->val[nnz - 1] += t->val[e];
      } else {
        a->rowind[nnz] = last = t->row[e];
        a->val[nnz++] = t->val[e];
      }
    }
    start = colcnt[j];
  }
  if (nnz > INT32_MAX) {
    free(rowcnt); free(colcnt); free(byrow); free(bycol);
    sm_csc_destroy(a);
    return sm_error_set(err, SM_ELIMIT, "sparse matrix with %lld nonzeros is too large",
                        (long long)nnz);
  }
  a->colptr[n] = (int32_t)nnz;
  a->nnz = nnz;
  free(rowcnt); free(colcnt); free(byrow); free(bycol);
  *out = a;
  return SM_OK;
nomem:
  free(rowcnt); free(colcnt); free(byrow); free(bycol);
  sm_csc_destroy(a);
  return sm_error_set(err, SM_ENOMEM, "sparse assembly: out of memory (%lld entries)",
                      (long long)len);
}

void sm_csc_destroy(sm_csc *a) {
  if (!a) return;
  free(a->colptr);
  free(a->rowind);
  free(a->val);
  free(a);
}

void sm_csc_symv(const sm_csc *a, const double *x, double *y) {
  memset(y, 0, (size_t)a->n * sizeof *y);
  for (int32_t j = 0; j < a->n; j++)
    for (int32_t p = a->colptr[j]; p < a->colptr[j + 1]; p++) {
      int32_t i = a->rowind[p];
      y[i] += a->val[p] * x[j];
      if (i != j) y[j] += a->val[p] * x[i];
    }
}
