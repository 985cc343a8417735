#include "sm_alloc.h"

#include <stdlib.h> /* defines __GLIBC__ on glibc */

#if defined(__GLIBC__)
#include <malloc.h>
#endif

int sm_alloc_keep_large(void) {
#if defined(__GLIBC__)
  /* Either setting also turns glibc's dynamic threshold off: both are set together. */
  if (mallopt(M_MMAP_THRESHOLD, SM_ALLOC_MMAP_MAX) != 1) return -1;
  return mallopt(M_TRIM_THRESHOLD, SM_ALLOC_TRIM) == 1 ? 0 : -1;
#else
  return -1;
#endif
}
