/* sm_fuzz_main: main() for a harness that is not linked with libFuzzer.
 *
 *   fuzz_<h> PATH...  replays every file given, and every regular file directly inside a
 *                     directory given (sorted, so runs are repeatable), once each; prints
 *                     how many ran. A missing path is an error (exit 2), so a ctest cannot
 *                     pass by replaying nothing by mistake. A crash aborts as it would
 *                     under a fuzzer, with the file named on stderr first.
 *   fuzz_<h>          reads one input from stdin; built with afl-clang-fast it runs in
 *                     AFL++'s persistent shared-memory mode instead (many inputs per
 *                     process), which is why this is the AFL++ driver too.
 */
#include <dirent.h>
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h> /* read(): AFL++'s test case macros use it */

#include "sm_fuzz.h"

#ifdef __AFL_FUZZ_TESTCASE_LEN
__AFL_FUZZ_INIT(); /* afl-clang-fast: the shared-memory test case buffer */
#endif

static int run_file(const char *path) {
  FILE *f = fopen(path, "rb");
  if (!f) {
    fprintf(stderr, "%s: %s\n", path, strerror(errno));
    return -1;
  }
  size_t cap = 1 << 16, n = 0;
  uint8_t *buf = malloc(cap);
  for (size_t r; buf && (r = fread(buf + n, 1, cap - n, f)) > 0;) {
    n += r;
    if (n == cap) buf = realloc(buf, cap *= 2);
  }
  fclose(f);
  SM_FUZZ_CHECK(buf != NULL);
  fprintf(stderr, "replay %s (%zu bytes)\n", path, n);
  uint8_t *exact = sm_fuzz_dup(buf, n); /* exact size: an over-read is an ASan report */
  free(buf);
  LLVMFuzzerTestOneInput(exact, n);
  free(exact);
  return 0;
}

static int cmp_names(const void *a, const void *b) {
  return strcmp(*(char *const *)a, *(char *const *)b);
}

/* Every regular file directly inside dir, in name order; returns how many, or -1. */
static int run_dir(const char *dir) {
  DIR *d = opendir(dir);
  if (!d) return -1;
  char **names = NULL;
  size_t n = 0;
  for (struct dirent *e; (e = readdir(d));) {
    if (e->d_name[0] == '.') continue; /* ., .. and .gitkeep-style files */
    names = realloc(names, (n + 1) * sizeof *names);
    SM_FUZZ_CHECK(names != NULL);
    names[n++] = strdup(e->d_name);
  }
  closedir(d);
  if (n) qsort(names, n, sizeof *names, cmp_names);
  int ran = 0;
  for (size_t i = 0; i < n; i++) {
    char path[4096];
    struct stat st;
    snprintf(path, sizeof path, "%s/%s", dir, names[i]);
    if (stat(path, &st) == 0 && S_ISREG(st.st_mode) && run_file(path) == 0) ran++;
    free(names[i]);
  }
  free(names);
  return ran;
}

static int run_stdin(void) {
#ifdef __AFL_FUZZ_TESTCASE_LEN
  __AFL_INIT();
  const unsigned char *buf = __AFL_FUZZ_TESTCASE_BUF;
  while (__AFL_LOOP(10000)) {
    size_t n = (size_t)__AFL_FUZZ_TESTCASE_LEN;
    uint8_t *exact = sm_fuzz_dup(buf, n);
    LLVMFuzzerTestOneInput(exact, n);
    free(exact);
  }
  return 0;
#else
  return run_file("/dev/stdin");
#endif
}

int main(int argc, char **argv) {
  if (argc < 2) return run_stdin() ? 2 : 0;
  int total = 0;
  for (int i = 1; i < argc; i++) {
    struct stat st;
    if (stat(argv[i], &st) != 0) {
      fprintf(stderr, "%s: %s\n", argv[i], strerror(errno));
      return 2;
    }
    int ran = S_ISDIR(st.st_mode) ? run_dir(argv[i]) : run_file(argv[i]) == 0;
    if (ran < 0) return 2;
    total += ran;
  }
  printf("%s: %d inputs replayed, no failure\n", argv[0], total);
  return 0;
}
