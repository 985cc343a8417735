/* shapematch_picture: `match ... --ply-out/--png-out` and `render` (see the header). */
#include "shapematch_picture.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "sm_meshio.h"

int smcli_pic_take_opts(int *argc, char **argv, smcli_pic *p) {
  memset(p, 0, sizeof *p);
  sm_pic_view_default(&p->view);
  int n = 0;
  for (int i = 0; i < *argc; i++) {
    const char *a = argv[i], *v = i + 1 < *argc ? argv[i + 1] : NULL;
    int valued = !strcmp(a, "--ply-out") || !strcmp(a, "--png-out") || !strcmp(a, "--view") ||
                 !strcmp(a, "--size");
    if (!valued) {
      argv[n++] = argv[i];
      continue;
    }
    if (!v) return -1;
    i++;
    if (!strcmp(a, "--ply-out")) p->ply_prefix = v;
    else if (!strcmp(a, "--png-out")) p->png = v;
    else if (!strcmp(a, "--view")) {
      if (sscanf(v, "%lf,%lf", &p->view.azimuth_deg, &p->view.elevation_deg) != 2) return -1;
    } else if (sscanf(v, "%d,%d", &p->view.width, &p->view.height) != 2) return -1;
  }
  *argc = n;
  return 0;
}

static int pic_fail(const char *what, const sm_error *err) {
  fprintf(stderr, "shapematch: %s: %s (%s)\n", what, err->msg, sm_strerror(err->code));
  return 1;
}

/* Both colourings and the outputs asked for; the meshes are as read, in the map's
 * numbering. */
static int write_outputs(const smcli_pic *p, const sm_mesh *ma, const sm_mesh *mb,
                         const int32_t *map) {
  uint8_t *ca = malloc((size_t)ma->nv * 3 + 1), *cb = malloc((size_t)mb->nv * 3 + 1);
  sm_error err;
  int32_t reached = 0;
  int rc = ca && cb ? 0 : 1;
  if (rc) fprintf(stderr, "shapematch: picture: out of memory\n");
  if (!rc) {
    sm_pic_source_colors(ma, ca);
    if (sm_pic_target_colors(mb, map, ma->nv, ca, cb, &reached, &err)) rc = pic_fail("picture", &err);
  }
  if (!rc && p->ply_prefix) {
    size_t len = strlen(p->ply_prefix) + 16;
    char *src = malloc(len), *tgt = malloc(len);
    snprintf(src, len, "%s_src.ply", p->ply_prefix);
    snprintf(tgt, len, "%s_tgt.ply", p->ply_prefix);
    if (sm_pic_write_ply(src, ma, ca, &err) || sm_pic_write_ply(tgt, mb, cb, &err))
      rc = pic_fail("picture", &err);
    else
      fprintf(stderr, "wrote %s and %s (%d of %d target vertices reached by the map%s)\n",
              src, tgt, reached, mb->nv, reached < mb->nv ? "; the others take their "
              "nearest reached neighbour's colour" : "");
    free(src);
    free(tgt);
  }
  if (!rc && p->png) {
    if (sm_pic_render_png(p->png, ma, ca, mb, cb, &p->view, &err)) rc = pic_fail("picture", &err);
    else fprintf(stderr, "wrote %s\n", p->png);
  }
  free(ca);
  free(cb);
  return rc;
}

int smcli_pic_write(const smcli_pic *p, const char *a, const char *b, const int32_t *map,
                    int32_t n) {
  if (!p || (!p->ply_prefix && !p->png)) return 0;
  sm_mesh *ma = NULL, *mb = NULL;
  sm_error err;
  int rc = 0;
  /* the files as read: the map's numbering is theirs (a stored id has no file here) */
  if (sm_mesh_read_file(a, NULL, &ma, &err)) rc = pic_fail(a, &err);
  else if (sm_mesh_read_file(b, NULL, &mb, &err)) rc = pic_fail(b, &err);
  else if (n != ma->nv) {
    fprintf(stderr, "shapematch: picture: the map has %d entries, %s has %d vertices\n", n, a,
            ma->nv);
    rc = 1;
  } else rc = write_outputs(p, ma, mb, map);
  sm_mesh_destroy(ma);
  sm_mesh_destroy(mb);
  return rc;
}

int smcli_cmd_render(int argc, char **argv) {
  smcli_pic p;
  const char *a = NULL, *b = NULL, *map_path = NULL;
  if (smcli_pic_take_opts(&argc, argv, &p)) return 2;
  for (int i = 0; i < argc; i++) {
    if (!strcmp(argv[i], "--map") && i + 1 < argc) map_path = argv[++i];
    else if (!strcmp(argv[i], "-o") && i + 1 < argc) p.png = argv[++i];
    else if (argv[i][0] == '-' || (a && b)) return 2;
    else if (!a) a = argv[i];
    else b = argv[i];
  }
  if (!a || !b || !map_path || (!p.png && !p.ply_prefix)) return 2;
  int32_t *map = NULL;
  int n = read_index_rows(map_path, 1, &map);
  if (n < 0) return 1;
  int rc = smcli_pic_write(&p, a, b, map, n);
  free(map);
  return rc;
}
