/* sm_error: error codes and error messages for every shapematch module.
 *
 * Contract
 *   Functions return 0 (SM_OK) or a negative SM_E* code. Functions that can fail for a
 *   reason worth explaining also take an `sm_error *err` out-parameter (may be NULL) that
 *   receives the code and a one-line message saying what and where ("face 12 references
 *   vertex 9001, mesh has 5103 vertices"). core/ never logs: the caller decides what to print.
 *   sm_strerror() returns a static string; thread-safe.
 */
#ifndef SM_ERROR_H
#define SM_ERROR_H

#include <stdarg.h>

enum {
  SM_OK = 0,
  SM_ENOMEM = -1,       /* allocation failed */
  SM_EINVAL = -2,       /* bad argument (programming error or bad option) */
  SM_EIO = -3,          /* file system error */
  SM_EFORMAT = -4,      /* malformed or unsupported file / stream content */
  SM_ENONFINITE = -5,   /* NaN or Inf coordinate */
  SM_ERANGE = -6,       /* index out of range */
  SM_ELIMIT = -7,       /* input exceeds a configured size limit */
  SM_EEMPTY = -8,       /* nothing left (no vertices, all faces degenerate) */
  SM_ENUMERIC = -9,     /* factorization or eigensolver failure */
  SM_ECHECKSUM = -10,   /* stored data failed its checksum */
  SM_EVERSION = -11,    /* unknown format version */
  SM_ECANCELED = -12,   /* the caller's cancel callback asked to stop */
  SM_EUNSUPPORTED = -13 /* valid input this build cannot handle (e.g. point cloud) */
};

typedef struct sm_error {
  int code;
  char msg[256];
} sm_error;

const char *sm_strerror(int code);

/* Fills *err (if non-NULL) with code and a printf-style message; returns code so callers
 * can write `return sm_error_set(err, SM_EINVAL, "k=%d must be > 0", k);`. */
int sm_error_set(sm_error *err, int code, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));

/* Clears *err (if non-NULL) to SM_OK and an empty message. */
void sm_error_clear(sm_error *err);

#endif
