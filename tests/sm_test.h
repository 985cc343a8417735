/* sm_test: a minimal test harness. One test program per file, run by ctest in its own
 * process. CHECK records a failure and goes on; REQUIRE stops the test program.
 * SM_SKIP(reason) exits 77, which ctest reports as skipped. */
#ifndef SM_TEST_H
#define SM_TEST_H

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/stat.h>

static int sm_test_failures = 0;
static int sm_test_checks = 0;

#define CHECK(cond)                                                                  \
  do {                                                                               \
    sm_test_checks++;                                                                \
    if (!(cond)) {                                                                   \
      sm_test_failures++;                                                            \
      fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond);       \
    }                                                                                \
  } while (0)

#define CHECK_MSG(cond, ...)                                                         \
  do {                                                                               \
    sm_test_checks++;                                                                \
    if (!(cond)) {                                                                   \
      sm_test_failures++;                                                            \
      fprintf(stderr, "%s:%d: CHECK failed: %s: ", __FILE__, __LINE__, #cond);       \
      fprintf(stderr, __VA_ARGS__);                                                  \
      fputc('\n', stderr);                                                           \
    }                                                                                \
  } while (0)

#define REQUIRE(cond)                                                                \
  do {                                                                               \
    sm_test_checks++;                                                                \
    if (!(cond)) {                                                                   \
      fprintf(stderr, "%s:%d: REQUIRE failed: %s\n", __FILE__, __LINE__, #cond);     \
      exit(1);                                                                       \
    }                                                                                \
  } while (0)

#define CHECK_NEAR(a, b, tol)                                                        \
  CHECK_MSG(fabs((double)(a) - (double)(b)) <= (tol), "%s=%.17g %s=%.17g tol=%g", #a, \
            (double)(a), #b, (double)(b), (double)(tol))

#define SM_SKIP(...)                                                                 \
  do {                                                                               \
    fprintf(stderr, "SKIP: " __VA_ARGS__);                                           \
    fputc('\n', stderr);                                                             \
    exit(77);                                                                        \
  } while (0)

/* Path of a file under ../shared/data, or NULL (after printing why) when absent. */
static inline const char *sm_test_data(const char *rel, char *buf, size_t n) {
  struct stat st;
  snprintf(buf, n, "%s/%s", SM_DATA_DIR, rel);
  return stat(buf, &st) == 0 ? buf : NULL;
}

static inline int sm_test_data_present(void) {
  struct stat st;
  return stat(SM_DATA_DIR, &st) == 0 && S_ISDIR(st.st_mode);
}

static inline int sm_test_finish(void) {
  fprintf(stderr, "%d checks, %d failed\n", sm_test_checks, sm_test_failures);
  return sm_test_failures ? 1 : 0;
}

#endif
