/* sm_meshio: reading mesh files and Draco bitstreams, writing Draco.
 *
 * Contract
 *   Readers return a raw mesh (not validated, not cleaned: run sm_mesh_clean next) owned
 *   by the caller, with to_input NULL (identity): vertex i is the i-th vertex of the file or
 *   the i-th decoded Draco point. Counts are checked against `lim` (NULL = defaults) before
 *   the mesh is allocated. Non-triangle polygons are fan-triangulated. `.gz` files are
 *   decompressed in memory first. Every C++ exception is caught inside the adapters and
 *   becomes an error code; nothing is logged (OpenMesh's own log output is silenced).
 *   Thread-safe: no shared state between calls.
 *   Errors: SM_EIO (cannot open/read), SM_EFORMAT (malformed, truncated or unknown format),
 *   SM_EUNSUPPORTED (Draco point cloud, mesh without positions), SM_ELIMIT, SM_ENOMEM.
 */
#ifndef SM_MESHIO_H
#define SM_MESHIO_H

#include <stddef.h>
#include <stdint.h>

#include "sm_error.h"
#include "sm_mesh.h"

/* Reads OFF, OBJ, PLY (ascii/binary), STL (ascii/binary) or DRC, chosen by extension
 * (case-insensitive; an extra ".gz" means gzip). */
int sm_mesh_read_file(const char *path, const sm_limits *lim, sm_mesh **out, sm_error *err);

/* The same on a whole file's content already in memory (buf borrowed): the format is
 * chosen by `name`'s extension exactly as above (".gz" included) and name prefixes the
 * messages. The bytes are copied once (the text parsers need a terminating NUL); at most
 * 2 GiB like a file (SM_ELIMIT). For callers that hold the bytes, and the fuzz harnesses. */
int sm_mesh_read_buffer(const char *name, const uint8_t *buf, size_t len, const sm_limits *lim,
                        sm_mesh **out, sm_error *err);
/* Decodes a Draco mesh bitstream (versions 1.x and 2.x, sequential or edgebreaker).
 * buf is borrowed. Edgebreaker reorders (and at non-manifold vertices duplicates) points:
 * the result's vertices are the decoded points in decoded order. */
int sm_draco_decode(const uint8_t *buf, size_t len, const sm_limits *lim, sm_mesh **out,
                    sm_error *err);

/* Encodes m with the sequential connectivity method, so vertex and face order survive a
 * decode. quant_bits = 0 stores positions as raw float32 (lossless up to float rounding);
 * 1..30 quantizes. *buf is malloc'd and owned by the caller (free()). */
int sm_draco_encode(const sm_mesh *m, int quant_bits, uint8_t **buf, size_t *len,
                    sm_error *err);

/* Reads a whole file into a malloc'd buffer (at most max_bytes, else SM_ELIMIT). */
int sm_read_file_bytes(const char *path, size_t max_bytes, uint8_t **buf, size_t *len,
                       sm_error *err);

/* Internal, for sm_meshio.c only (implemented in io/sm_openmesh_io.cpp, C++ behind a C
 * ABI). Parses buf[len], a whole file in the format named by ext ("stl" or "ply"), with
 * OpenMesh. Faces are recorded as the file lists them, before OpenMesh's halfedge structure
 * can reject a non-manifold one, so nothing is lost; polygons are fan-triangulated.
 * *n_polygons receives how many faces OpenMesh reported, so the caller can compare it with
 * what the file declares and fall back to its own reader when they differ. binary: 1 if
 * the content is binary (OpenMesh cannot tell from a stream for STL). */
int sm_openmesh_read(const uint8_t *buf, size_t len, const char *ext, int binary,
                     const sm_limits *lim, sm_mesh **out, int64_t *n_polygons, sm_error *err);

#endif
