/* sm_fuzz: what every harness in tests/fuzz shares.
 *
 * Contract
 *   A harness is one C file defining LLVMFuzzerTestOneInput(data, size), the libFuzzer entry
 *   point. The same file builds three ways (tests/fuzz/CMakeLists.txt): with libFuzzer
 *   (SM_FUZZ_ENGINE=libfuzzer, clang), with AFL++ (SM_FUZZ_ENGINE=afl, afl-clang-fast, main
 *   from sm_fuzz_main.c in persistent mode) and, in the normal build, as a replay ctest over
 *   tests/fuzz/regress/<harness>/ and the generated seeds (sm_fuzz_main.c again).
 *   A harness must return 0 for every input the code under test rejects cleanly; it aborts
 *   (SM_FUZZ_CHECK) only when a property the module's contract promises is broken, so a
 *   crash is always a bug, never a "bad input". It frees everything it allocated (leak
 *   checks are on) and keeps no state between inputs.
 *   The code under test gets its input in an exact-size heap copy (sm_fuzz_dup), so ASan
 *   sees any read one byte past the end.
 */
#ifndef SM_FUZZ_H
#define SM_FUZZ_H

#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

/* A broken invariant: say which, then abort so every engine records the input. */
#define SM_FUZZ_CHECK(cond)                                                        \
  do {                                                                             \
    if (!(cond)) {                                                                 \
      fprintf(stderr, "%s:%d: fuzz invariant failed: %s\n", __FILE__, __LINE__, #cond); \
      abort();                                                                     \
    }                                                                              \
  } while (0)

/* Exact-size heap copy (n may be 0); aborts on ENOMEM, which a harness cannot recover. */
static inline uint8_t *sm_fuzz_dup(const uint8_t *p, size_t n) {
  uint8_t *q = malloc(n ? n : 1);
  SM_FUZZ_CHECK(q != NULL);
  if (n) memcpy(q, p, n);
  return q;
}

/* Takes the first input byte as a harness parameter (0 once the input is empty). */
static inline uint8_t sm_fuzz_take(const uint8_t **data, size_t *size) {
  if (*size == 0) return 0;
  uint8_t b = **data;
  (*data)++;
  (*size)--;
  return b;
}

#endif
