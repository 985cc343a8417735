/* sm_picture: pictures of a point map A -> B for people who look at a match: vertex-
 * coloured PLY files (open in MeshLab) and a PNG of both meshes side by side, drawn by a
 * small software rasterizer (z-buffer, Lambert shading, PNG through zlib), so it works
 * headless and adds no dependency.
 *
 * Colours. A gets a smooth field: its bounding-box-normalized coordinates as RGB. B is
 *   coloured through the map being shown, not through a map B -> A: a target vertex takes
 *   the mean colour of the source vertices mapped to it. A second, inverse map would
 *   colour every target vertex, but it is another computation (possibly another answer),
 *   and the picture must show the map the user got, folds and gaps included. A target
 *   vertex no source vertex reaches takes the colour of the nearest reached vertex along
 *   B's edges (so a finer target than source is not speckled; a map that misses a whole
 *   region shows it as a flat patch), and one in a component nothing reaches is grey.
 * Meshes are in the maps' numbering, i.e. as read from the files (sm_mesh_read_file),
 *   not cleaned: map entries of -1 (vertices cleaning dropped) are skipped.
 *
 * Contract: no global state, thread-safe. Arrays are borrowed for the call; rgb arrays
 *   are 3 bytes per vertex, caller-allocated. Functions return 0 or a negative SM_E* code
 *   with *err (may be NULL) filled; nothing is printed. Files are written in place (no
 *   temp + rename: a picture is not state anyone reads back).
 */
#ifndef SM_PICTURE_H
#define SM_PICTURE_H

#include <stdint.h>

#include "sm_error.h"
#include "sm_mesh.h"

/* The smooth field on the source: rgb of vertex v from its coordinates in m's bounding
 * box (each channel in [40, 255], so no vertex is black). */
void sm_pic_source_colors(const sm_mesh *m, uint8_t *rgb);

/* Colours of the target b through map (na entries: vertex of b per vertex of the source,
 * -1 = none) from the source colours rgb_a, as the header says. *n_reached (may be NULL)
 * receives the number of target vertices with at least one preimage. SM_ERANGE for a map
 * entry outside b. */
int sm_pic_target_colors(const sm_mesh *b, const int32_t *map, int32_t na,
                         const uint8_t *rgb_a, uint8_t *rgb_b, int32_t *n_reached,
                         sm_error *err);

/* ASCII PLY 1.0: vertices with uchar red, green, blue; triangular faces. */
int sm_pic_write_ply(const char *path, const sm_mesh *m, const uint8_t *rgb, sm_error *err);

typedef struct sm_pic_view {
  int width, height;    /* of the whole picture; each mesh gets one half */
  double azimuth_deg;   /* turn about the vertical (y) axis, then ... */
  double elevation_deg; /* ... tilt towards the viewer about the horizontal axis */
} sm_pic_view;
void sm_pic_view_default(sm_pic_view *v); /* 960 x 480, azimuth 30, elevation 20 */

/* Renders a (left) and b (right), each scaled to fill its half, same orientation, on
 * white, and writes an 8-bit RGB PNG. */
int sm_pic_render_png(const char *path, const sm_mesh *a, const uint8_t *rgb_a,
                      const sm_mesh *b, const uint8_t *rgb_b, const sm_pic_view *view,
                      sm_error *err);

#endif
