/* sm_sha256: SHA-256 (FIPS 180-4), used for shape ids (the digest of a shape's Draco bytes).
 *
 * Contract
 *   Pure computation: no allocation, no I/O, no global state. A context is owned by the
 *   caller (stack is fine); one context must not be used by two threads at once, distinct
 *   contexts are independent. Input buffers are borrowed for the duration of the call.
 *   No error cases: the functions cannot fail (a NULL pointer with length 0 is accepted).
 *   Written here rather than linking OpenSSL so that protocol/ has no dependency at all.
 */
#ifndef SM_SHA256_H
#define SM_SHA256_H

#include <stddef.h>
#include <stdint.h>

#define SM_SHA256_LEN 32

typedef struct sm_sha256_ctx {
  uint32_t h[8];
  uint64_t nbytes;     /* total message bytes so far */
  uint8_t buf[64];     /* pending partial block */
  size_t nbuf;
} sm_sha256_ctx;

void sm_sha256_init(sm_sha256_ctx *c);
void sm_sha256_update(sm_sha256_ctx *c, const void *data, size_t len);
/* Writes the 32-byte digest; the context must be re-initialized before reuse. */
void sm_sha256_final(sm_sha256_ctx *c, uint8_t out[SM_SHA256_LEN]);
/* One-shot convenience. */
void sm_sha256(const void *data, size_t len, uint8_t out[SM_SHA256_LEN]);

#endif
