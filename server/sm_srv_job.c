/* sm_srv_job.c: write buffers and error frames (sm_srv_job.h). */
#include "sm_srv_job.h"

#include <stdlib.h>
#include <string.h>

#include "sm_proto.h"

sm_wbuf *sm_wbuf_new(size_t len) {
  sm_wbuf *w = malloc(sizeof *w + len);
  if (!w) return NULL;
  w->next = NULL;
  w->len = len;
  w->off = 0;
  w->cap = len;
  return w;
}

size_t sm_error_payload(uint8_t *out, uint32_t retry, uint32_t detail, const char *msg) {
  size_t ml = msg ? strlen(msg) : 0;
  if (ml > SM_PROTO_MAX_MSG) ml = SM_PROTO_MAX_MSG;
  uint32_t v[3] = {retry, detail, (uint32_t)ml};
  for (int i = 0; i < 3; i++)
    for (int b = 0; b < 4; b++) out[4 * i + b] = (uint8_t)(v[i] >> (8 * b));
  if (ml) memcpy(out + 12, msg, ml);
  return 12 + ml;
}

sm_wbuf *sm_error_frame(uint8_t version, uint8_t opcode, uint32_t rid, uint16_t status,
                        uint32_t retry, uint32_t detail, const char *msg) {
  sm_wbuf *w = sm_wbuf_new(SM_PROTO_HEADER_LEN + 12 + SM_PROTO_MAX_MSG);
  if (!w) return NULL;
  size_t pl = sm_error_payload(w->data + SM_PROTO_HEADER_LEN, retry, detail, msg);
  sm_proto_header h = {version, opcode, SM_PROTO_F_RESPONSE, rid, status, (uint32_t)pl};
  sm_proto_write_header(w->data, &h);
  w->len = SM_PROTO_HEADER_LEN + pl;
  return w;
}
