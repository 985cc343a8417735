#include "sm_error.h"

#include <stdio.h>

const char *sm_strerror(int code) {
  switch (code) {
  case SM_OK: return "ok";
  case SM_ENOMEM: return "out of memory";
  case SM_EINVAL: return "invalid argument";
  case SM_EIO: return "i/o error";
  case SM_EFORMAT: return "malformed or unsupported data";
  case SM_ENONFINITE: return "non-finite coordinate";
  case SM_ERANGE: return "index out of range";
  case SM_ELIMIT: return "size limit exceeded";
  case SM_EEMPTY: return "empty mesh";
  case SM_ENUMERIC: return "numerical failure";
  case SM_ECHECKSUM: return "checksum mismatch";
  case SM_EVERSION: return "unsupported format version";
  case SM_ECANCELED: return "canceled";
  case SM_EUNSUPPORTED: return "unsupported input";
  default: return "unknown error";
  }
}

int sm_error_set(sm_error *err, int code, const char *fmt, ...) {
  if (err) {
    va_list ap;
    err->code = code;
    va_start(ap, fmt);
    vsnprintf(err->msg, sizeof err->msg, fmt, ap);
    va_end(ap);
  }
  return code;
}

void sm_error_clear(sm_error *err) {
  if (err) {
    err->code = SM_OK;
    err->msg[0] = '\0';
  }
}
