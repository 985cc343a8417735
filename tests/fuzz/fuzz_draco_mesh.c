/* fuzz_draco_mesh: what PUT_SHAPE does with a client's bytes: the Draco decoder
 * (sm_draco_decode, core/io/sm_draco_io.cpp) under the fuzz limits, then validation,
 * cleaning and normalization (sm_fuzz_mesh.h lists the properties checked).
 * Input: the Draco bitstream itself, so files of ../shared/data are seeds as they are.
 */
#include "sm_fuzz_mesh.h"
#include "sm_meshio.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  sm_limits lim = sm_fuzz_limits();
  sm_mesh *m = NULL;
  sm_error err;
  sm_error_clear(&err);
  int rc = sm_draco_decode(data, size, &lim, &m, &err);
  sm_fuzz_check_read(rc, m, &err);
  if (rc == 0) {
    sm_fuzz_prepare_mesh(m);
    sm_mesh_destroy(m);
  }
  return 0;
}
