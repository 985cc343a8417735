/* fuzz_meshio: every mesh file parser of core/sm_meshio.c (OFF, OBJ, PLY ascii/binary,
 * STL ascii/binary, each also gzip'd) through sm_mesh_read_buffer, then validation,
 * cleaning and normalization (sm_fuzz_mesh.h lists the properties checked).
 * Input: byte 0 picks the file name (% 8: .off .obj .ply .stl, then the same with .gz),
 * the rest is the file content.
 */
#include "sm_fuzz_mesh.h"
#include "sm_meshio.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  static const char *const names[8] = {"f.off",    "f.obj",    "f.ply",    "f.stl",
                                       "f.off.gz", "f.obj.gz", "f.ply.gz", "f.stl.gz"};
  const char *name = names[sm_fuzz_take(&data, &size) % 8];
  uint8_t *p = sm_fuzz_dup(data, size);
  sm_limits lim = sm_fuzz_limits();
  sm_mesh *m = NULL;
  sm_error err;
  sm_error_clear(&err);
  int rc = sm_mesh_read_buffer(name, p, size, &lim, &m, &err);
  sm_fuzz_check_read(rc, m, &err);
  if (rc == 0) {
    sm_fuzz_prepare_mesh(m);
    sm_mesh_destroy(m);
  }
  free(p);
  return 0;
}
