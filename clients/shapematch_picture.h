/* shapematch_picture: the CLI's pictures of a match (internal to the shapematch tool):
 * `match A B ... --ply-out PREFIX --png-out FILE.png` and `render A B --map MAP.txt`.
 * sm_picture.h does the colouring and drawing; this part reads the files, parses the
 * options and prints what went wrong. Functions return the CLI's exit codes (0, 1, 2). */
#ifndef SHAPEMATCH_PICTURE_H
#define SHAPEMATCH_PICTURE_H

#include <stdint.h>

#include "sm_picture.h"

typedef struct smcli_pic {
  const char *ply_prefix; /* writes PREFIX_src.ply and PREFIX_tgt.ply; NULL = none */
  const char *png;        /* NULL = none */
  sm_pic_view view;
} smcli_pic;

/* Removes --ply-out, --png-out, --view AZ,EL and --size W,H (with their values) from
 * argv, like the CLI's --server handling, so the other parsers never see them. 0, or -1
 * for a missing or bad value. */
int smcli_pic_take_opts(int *argc, char **argv, smcli_pic *p);

/* Pictures of map (n entries, A's vertices as read -> B's, -1 = none) between the mesh
 * files a and b; nothing when p is NULL or asks for neither output. 0 or 1 (message
 * printed). */
int smcli_pic_write(const smcli_pic *p, const char *a, const char *b, const int32_t *map,
                    int32_t n);

/* shapematch render A B --map MAP.txt [-o OUT.png] [--ply-out PREFIX] [--view] [--size] */
int smcli_cmd_render(int argc, char **argv);

/* The CLI's reader of integer rows (clients/shapematch.c): count of rows, -1 on error. */
int read_index_rows(const char *path, int ncol, int32_t **out);

#endif
