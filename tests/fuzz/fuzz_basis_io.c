/* fuzz_basis_io: the basis file loader (sm_basis_deserialize, core/sm_basis_io.c), which
 * reads files of the daemon's data directory that a disk fault or another process may
 * have damaged.
 * Input: byte 0 = mode, the rest is the file.
 *   mode bit 0: write the right XXH3 checksum into the header first, and bit 1 also the
 *               right payload_len, so mutations reach the field checks behind them.
 * Properties: a rejected file gives a code and a message; an accepted one has the sizes
 * its header claims, finite arrays as the format requires, and serializes back to exactly
 * the input bytes (sm_basis.h: "what loads is bit-identical to what was saved").
 */
#include <math.h>
#include <xxhash.h>

#include "sm_basis.h"
#include "sm_fuzz.h"

static void repair(uint8_t *p, size_t n, int len_too) {
  if (n < 32) return;
  uint64_t pl = n - 32, h = XXH3_64bits(p + 32, n - 32);
  for (int i = 0; i < 8; i++) {
    if (len_too) p[16 + i] = (uint8_t)(pl >> (8 * i));
    p[24 + i] = (uint8_t)(h >> (8 * i));
  }
}

static void check_loaded(const sm_basis *b, const uint8_t *p, size_t n) {
  SM_FUZZ_CHECK(b->kind == SM_BASIS_LB || b->kind == SM_BASIS_ELASTIC);
  SM_FUZZ_CHECK(b->n > 0 && b->k > 0 && b->k <= b->n);
  size_t nk = (size_t)b->n * (size_t)b->k;
  for (size_t i = 0; i < (size_t)b->k; i++) SM_FUZZ_CHECK(isfinite(b->evals[i]));
  for (size_t i = 0; i < nk; i++) SM_FUZZ_CHECK(isfinite(b->phi[i]));
  for (size_t i = 0; i < (size_t)b->n; i++) SM_FUZZ_CHECK(isfinite(b->mass[i]));
  uint8_t *out = NULL;
  size_t len = 0;
  sm_error err;
  SM_FUZZ_CHECK(sm_basis_serialize(b, &out, &len, &err) == 0);
  SM_FUZZ_CHECK(len == n && memcmp(out, p, n) == 0);
  free(out);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  uint8_t mode = sm_fuzz_take(&data, &size);
  uint8_t *p = sm_fuzz_dup(data, size);
  if (mode & 1) repair(p, size, mode & 2);
  sm_basis *b = NULL;
  sm_error err;
  sm_error_clear(&err);
  int rc = sm_basis_deserialize(p, size, &b, &err);
  SM_FUZZ_CHECK(rc <= 0 && (rc == 0) == (b != NULL));
  if (rc) {
    SM_FUZZ_CHECK(err.code == rc && err.msg[0] != 0);
  } else {
    check_loaded(b, p, size);
    sm_basis_destroy(b);
  }
  free(p);
  return 0;
}
