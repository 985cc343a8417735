/* shapematch: the command-line front end.
 *
 * Subcommands (this file dispatches; each lives in a function below):
 *   basis  MESH --kind lb|elastic -k K [--eta E] -o OUT.smb   compute and save a basis
 *   info   MESH | BASIS.smb                                  describe a mesh or basis file
 *   encode MESH -o OUT.drc [--qbits Q]                        Draco-encode (order-preserving)
 *   synth  sphere|torus|blob [...] -o OUT.off                 write a mesh of our own
 *   match  A B [options] [-o MAP.txt] [--json]                point map A -> B (local)
 *   distance A B [options] [--json]                           shape distance (local)
 *   eval   A B --map MAP.txt [--gt GT --gt-kind K ...]        metrics of a point map
 * With a daemon (--server HOST:PORT or $SHAPEMATCH_SERVER; sm_client.h):
 *   put FILE... | match A B | distance A B | query A | batch ... | stats | ping
 *   match and distance run on the server when one is named, locally otherwise or with
 *   --local. A and B are mesh files (Draco-encoded on the fly, order kept, so maps speak
 *   of the file's own vertex numbering) or the 64-hex ids of stored shapes.
 * Exit status: 0 success, 1 failure (message on stderr), 2 usage error.
 */
#include <cblas.h> /* OpenBLAS: openblas_set_num_threads */
#include <dirent.h>
#include <errno.h>
#include <pthread.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "sm_basis.h"
#include "sm_alloc.h"
#include "sm_eigs.h"
#include "sm_meshio.h"
#include "sm_shell.h"
#include "sm_synth.h"
#include "sm_match.h"
#include "sm_multires.h"
#include "sm_prepare.h"
#include "sm_distance.h"
#include "sm_metrics.h"
#include "sm_client.h"
#include "sm_version.h"
#include "shapematch_picture.h"

static int usage(FILE *f) {
  fprintf(f,
          "usage: shapematch <command> [options]\n"
          "\n"
          "commands:\n"
          "  basis MESH [--kind lb|elastic] [-k K] [--eta E] [--no-normalize] -o OUT.smb\n"
          "        compute a spectral basis (default: elastic, k = 100, eta = %g) and save it\n"
          "  info FILE\n"
          "        describe a mesh (OFF, OBJ, PLY, STL, DRC, optionally .gz) or a .smb basis\n"
          "  encode MESH -o OUT.drc [--qbits Q]\n"
          "        Draco-encode a mesh, sequential (vertex order kept), lossless unless Q > 0\n"
          "  synth sphere|torus|blob [--subdiv S] [--seed N] [--amp A] [--stretch X,Y,Z] -o OUT.off\n"
          "        write an analytic mesh (blobs of one subdiv share connectivity and vertex\n"
          "        order, so any two correspond by identity)\n"
          "  match A B [--basis elastic|lb|hybrid] [--init sinkhorn|nn] [-k K1] [--k0 K0]\n"
          "        [--step S] [--eta E] [--landmarks FILE] [--init-map FILE] [-o MAP.txt]\n"
          "        [--refine-sinkhorn LEVELS] [--yx MAP_BA.txt] [--fmap C.txt] [--multi-start]\n"
          "        [--tips off|doubtful|always] [--multires auto|on|off] [--coarse-nv N]\n"
          "        [--json] [--ply-out PREFIX] [--png-out FILE.png] [--view AZ,EL] [--size W,H]\n"
          "        dense point map from A to B: line i of MAP.txt = vertex of B (0-based, B's\n"
          "        numbering) matched to vertex i of A; -1 for vertices cleaning dropped.\n"
          "        Landmarks: lines 'a b' of 0-based vertex pairs; they start the map and\n"
          "        anchor its refinement (their heat kernels, and the orientation features\n"
          "        of each landmark pair, are compared at every point assignment). --ply-out\n"
          "        writes\n"
          "        PREFIX_src.ply (A coloured by position) and PREFIX_tgt.ply (B coloured\n"
          "        through the map) with vertex colours; --png-out draws both side by side\n"
          "        (turned by AZ degrees about the vertical, EL towards the viewer; default\n"
          "        30,20; 960,480 pixels). --tips (local matching; the daemon uses\n"
          "        doubtful): the tip search, a landmark-free global start from the shapes'\n"
          "        tips (head, hands, feet), run when the map's confidence is doubtful\n"
          "        (below 0.6, the default), always (slower), or off. --multires: match\n"
          "        through coarse levels of about N vertices (--coarse-nv, default 5,000;\n"
          "        local only: the daemon sets its own, see shapematchd(8)) and carry the\n"
          "        map back to every vertex: auto (default) when a mesh has more than\n"
          "        20,000 vertices, on, or off (the full-resolution path); with a server,\n"
          "        on and off need protocol version 3\n"
          "  render A B --map MAP.txt [-o OUT.png] [--ply-out PREFIX] [--view AZ,EL]\n"
          "        [--size W,H]\n"
          "        the same pictures of a map file that match wrote\n"
          "  distance A B [match options] [--json]\n"
          "        shape distance in [0, 1) after matching both ways; prints the number\n"
          "  eval A B --map MAP.txt [--gt FILE] [--gt-kind dense|inverse|vts|pairs|identity]\n"
          "        [--gt-tgt FILE] [--gt-base 0|1] [--json]\n"
          "        geodesic error (Dijkstra on B's edges / sqrt(area B)), accuracy curve,\n"
          "        bijectivity, coverage, Chamfer and Dirichlet energy of a map A -> B\n"
          "  version | --version\n"
          "        print the version (and the git commit of the build)\n"
          "\n"
          "server commands (--server HOST:PORT, or $SHAPEMATCH_SERVER; $SHAPEMATCH_TOKEN is\n"
          "sent as the HELLO token). A and B are mesh files, uploaded as needed (any\n"
          "readable format; Draco-encoded unquantized (float32), vertex order kept, so maps use the\n"
          "file's numbering), or the 64-hex ids of shapes already stored:\n"
          "  put FILE... [--prepare] [--inflight N]\n"
          "        upload shapes (N requests in flight, default 4); prints 'ID FILE' per\n"
          "        shape in argument order (ID = SHA-256 of the Draco bytes); --prepare also\n"
          "        computes their bases on the server\n"
          "  match A B [match options] --server ...    as above, computed by the daemon;\n"
          "  distance A B [options] --server ...       --local forces the local computation\n"
          "  query A [-k N] [--mode default|spectral|full] [--json]\n"
          "        the N stored shapes most similar to A: lines 'DISTANCE ID'\n"
          "  batch FILE | batch --query A --gallery DIR|LIST  [--inflight N] [--maps DIR]\n"
          "        [match options]\n"
          "        distances of the pairs 'A B' (one per line of FILE), or of A against every\n"
          "        mesh of a directory or list file; N requests in flight (default 4); one\n"
          "        JSON line per result on stdout as it arrives; --maps DIR also writes each\n"
          "        map to DIR/INDEX.txt (the line then has its orientation and confidence);\n"
          "        exit status 1 when an item failed (listed on stderr)\n"
          "  stats | ping\n"
          "        the daemon's counters | round-trip time\n"
          "  every server command takes --timeout S: the longest wait for one answer (batch:\n"
          "  between two answers; default: none). A request queued behind other work on the\n"
          "  server is waited for as long as the server answers a PING sent after\n"
          "  --io-timeout S (default 30) of silence; BUSY answers are retried after the\n"
          "  server's hint. When the connection is lost (the daemon died, a front cut it,\n"
          "  the daemon shut down), the command connects again (--reconnect N attempts,\n"
          "  default 5, waits from 0.1 s doubling; 0: never) and sends again the requests\n"
          "  whose answers had not come; a request cut 3 times fails\n",
          SM_SHELL_DEFAULT_ETA);
  return 2;
}

static int fail(const char *what, const sm_error *err) {
  fprintf(stderr, "shapematch: %s: %s (%s)\n", what, err->msg, sm_strerror(err->code));
  return 1;
}

/* Reads, cleans and (optionally) normalizes a mesh; prints what cleaning changed. */
static int load_mesh(const char *path, int normalize, int verbose, sm_mesh **out) {
  sm_error err;
  sm_mesh *raw = NULL;
  sm_clean_report rep;
  *out = NULL;
  if (sm_mesh_read_file(path, NULL, &raw, &err)) return fail(path, &err);
  int rc = sm_mesh_clean(raw, NULL, out, &rep, &err);
  sm_mesh_destroy(raw);
  if (rc) return fail(path, &err);
  if (normalize && sm_mesh_normalize(*out, &err)) {
    sm_mesh_destroy(*out);
    *out = NULL;
    return fail(path, &err);
  }
  if (verbose)
    fprintf(stderr,
            "%s: %d vertices, %d faces read; kept %d vertices, %d faces; dropped %d "
            "repeated-index, %d zero-area, %d duplicate faces, %d unreferenced vertices; "
            "%d faces flipped; %d components, %d boundary and %d non-manifold edges\n",
            path, rep.input_vertices, rep.input_faces, (*out)->nv, (*out)->nf,
            rep.dropped_repeated_index, rep.dropped_zero_area, rep.dropped_duplicate,
            rep.dropped_unreferenced, rep.flipped_faces, rep.components, rep.boundary_edges,
            rep.nonmanifold_edges);
  return 0;
}

static int parse_kind(const char *s) {
  if (!strcmp(s, "lb")) return SM_BASIS_LB;
  if (!strcmp(s, "elastic")) return SM_BASIS_ELASTIC;
  return 0;
}

static int cmd_basis(int argc, char **argv) {
  const char *in = NULL, *out = NULL;
  int kind = SM_BASIS_ELASTIC, k = 100, normalize = 1, quiet = 0;
  double eta = 0;
  for (int i = 0; i < argc; i++) {
    if (!strcmp(argv[i], "--kind") && i + 1 < argc) {
      if (!(kind = parse_kind(argv[++i]))) {
        fprintf(stderr, "shapematch basis: --kind must be lb or elastic, not '%s'\n", argv[i]);
        return 2;
      }
    } else if (!strcmp(argv[i], "-k") && i + 1 < argc) k = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--eta") && i + 1 < argc) eta = atof(argv[++i]);
    else if (!strcmp(argv[i], "-o") && i + 1 < argc) out = argv[++i];
    else if (!strcmp(argv[i], "--no-normalize")) normalize = 0;
    else if (!strcmp(argv[i], "-q")) quiet = 1;
    else if (argv[i][0] == '-' || in) return usage(stderr);
    else in = argv[i];
  }
  if (!in || !out) return usage(stderr);
  sm_mesh *m;
  if (load_mesh(in, normalize, !quiet, &m)) return 1;
  sm_basis_opts o;
  sm_basis_opts_default(&o, kind, k);
  if (eta > 0) o.eta = eta;
  /* One basis on the machine: the second core takes half of the eigensolver's basis
   * products (the koala's elastic basis: 12.7 -> 10.4 s, docs/PERFORMANCE.md). */
  _Atomic int spare = 1;
  o.spare_threads = &spare;
  sm_basis *b = NULL;
  sm_error err;
  double t0 = sm_now();
  int rc = sm_basis_compute(m, &o, &b, &err);
  double dt = sm_now() - t0;
  sm_mesh_destroy(m);
  if (rc) return fail("basis", &err);
  if (!quiet)
    fprintf(stderr,
            "%s basis: n = %d, k = %d, kernel dropped = %d, lambda in [%.6g, %.6g]; "
            "%.3f s (assembly %.3f, factorization %.3f, eigensolve %.3f, projection %.3f)\n",
            kind == SM_BASIS_LB ? "LB" : "elastic", b->n, b->k, b->n_kernel, b->evals[0],
            b->evals[b->k - 1], dt, b->timing.assembly, b->timing.factorization,
            b->timing.eigensolve, b->timing.projection);
  rc = sm_basis_save(b, out, &err);
  sm_basis_destroy(b);
  if (rc) return fail(out, &err);
  if (!quiet) fprintf(stderr, "wrote %s\n", out);
  return 0;
}

static int has_suffix(const char *s, const char *suf) {
  size_t n = strlen(s), m = strlen(suf);
  return n >= m && !strcmp(s + n - m, suf);
}

static int info_basis(const char *path) {
  sm_basis *b;
  sm_error err;
  if (sm_basis_load(path, &b, &err)) return fail(path, &err);
  printf("kind=%s n=%d k=%d kernel_dropped=%d components=%d eta=%g mu=%g lambda=%g "
         "mesh_hash=%016llx lambda_min=%.9g lambda_max=%.9g gram=%s\n",
         b->kind == SM_BASIS_LB ? "lb" : "elastic", b->n, b->k, b->n_kernel, b->n_components,
         b->eta, b->mu, b->lambda, (unsigned long long)b->mesh_hash, b->evals[0],
         b->evals[b->k - 1], b->gram_L ? "cholesky" : "identity");
  sm_basis_destroy(b);
  return 0;
}

static int cmd_info(int argc, char **argv) {
  if (argc != 1) return usage(stderr);
  if (has_suffix(argv[0], ".smb")) return info_basis(argv[0]);
  sm_mesh *m;
  if (load_mesh(argv[0], 0, 1, &m)) return 1;
  printf("vertices=%d faces=%d input_vertices=%d area=%.9g mesh_hash=%016llx\n", m->nv, m->nf,
         m->n_input, sm_mesh_face_areas(m, NULL), (unsigned long long)sm_mesh_hash(m));
  sm_mesh_destroy(m);
  return 0;
}

static int cmd_encode(int argc, char **argv) {
  const char *in = NULL, *out = NULL;
  int qbits = 0;
  for (int i = 0; i < argc; i++) {
    if (!strcmp(argv[i], "-o") && i + 1 < argc) out = argv[++i];
    else if (!strcmp(argv[i], "--qbits") && i + 1 < argc) qbits = atoi(argv[++i]);
    else if (argv[i][0] == '-' || in) return usage(stderr);
    else in = argv[i];
  }
  if (!in || !out) return usage(stderr);
  sm_error err;
  sm_mesh *m;
  uint8_t *buf;
  size_t len;
  /* Encode the file as read, not cleaned: the .drc must keep the user's numbering. */
  if (sm_mesh_read_file(in, NULL, &m, &err)) return fail(in, &err);
  int rc = sm_draco_encode(m, qbits, &buf, &len, &err);
  sm_mesh_destroy(m);
  if (rc) return fail("encode", &err);
  FILE *f = fopen(out, "wb");
  int ok = f && fwrite(buf, 1, len, f) == len;
  ok = f && !fclose(f) && ok;
  free(buf);
  if (!ok) {
    perror(out);
    return 1;
  }
  fprintf(stderr, "wrote %s (%zu bytes)\n", out, len);
  return 0;
}

/* Reads lines of `ncol` integers; returns the count of rows, -1 on error (message printed). */
int read_index_rows(const char *path, int ncol, int32_t **out) {
  FILE *f = fopen(path, "r");
  if (!f) {
    perror(path);
    return -1;
  }
  int cap = 64, n = 0;
  int32_t *v = malloc((size_t)cap * ncol * sizeof *v);
  double x[2];
  for (;;) {
    int got = ncol == 2 ? fscanf(f, "%lf %lf", &x[0], &x[1]) : fscanf(f, "%lf", &x[0]);
    if (got != ncol) break;
    if (n == cap) {
      int32_t *w = realloc(v, (size_t)(cap *= 2) * ncol * sizeof *v);
      if (!w) break;
      v = w;
    }
    for (int c = 0; c < ncol; c++) v[(size_t)n * ncol + c] = (int32_t)x[c];
    n++;
  }
  int bad = !feof(f);
  fclose(f);
  if (bad) {
    fprintf(stderr, "shapematch: %s: line %d is not %d integer(s)\n", path, n + 1, ncol);
    free(v);
    return -1;
  }
  *out = v;
  return n;
}

static int write_map(const char *path, const int32_t *T, int32_t n) {
  FILE *f = strcmp(path, "-") ? fopen(path, "w") : stdout;
  if (!f) {
    perror(path);
    return 1;
  }
  for (int32_t i = 0; i < n; i++) fprintf(f, "%d\n", T[i]);
  if (f != stdout && fclose(f)) {
    perror(path);
    return 1;
  }
  return 0;
}

typedef struct match_args {
  const char *a, *b, *out, *out_yx, *out_fmap, *landmarks, *init_map;
  int json;
  const smcli_pic *pic; /* match only: pictures of the map */
  sm_shape_opts so;
  sm_match_opts mo;
  sm_client_match_opts co; /* the same options for the daemon: only what the user set */
  sm_multires_opts ro;     /* --multires (local match only; distance uses the direct path) */
  char multires_json[256]; /* the multi-resolution part of match --json, "null" if unused */
} match_args;

static void match_args_init(match_args *m) {
  memset(m, 0, sizeof *m);
  sm_shape_opts_default(&m->so);
  sm_match_opts_default(&m->mo);
  m->mo.threads = 2; /* a local match has the machine to itself: tip hypotheses in pairs,
                        * the refinement's neighbour queries on two threads */
  sm_client_match_opts_default(&m->co);
  sm_multires_opts_default(&m->ro);
  snprintf(m->multires_json, sizeof m->multires_json, "null");
}

/* One option of match/distance/batch at argv[*i]: 1 consumed (and *i advanced past its
 * value), 0 not a match option, -1 bad value or missing value. */
static int parse_match_opt(int argc, char **argv, int *i, match_args *m) {
  const char *a = argv[*i], *v = *i + 1 < argc ? argv[*i + 1] : NULL;
  if (!strcmp(a, "--json")) { m->json = 1; return 1; }
  if (!strcmp(a, "--multi-start")) { m->mo.multi_start = m->co.multi_start = 1; return 1; }
  static const char *const valued[] = {"--basis", "--init", "-k", "--k0", "--step",
                                       "--refine-sinkhorn", "--eta", "--landmarks",
                                       "--init-map", "-o", "--yx", "--fmap", "--tips", "--multires",
                                       "--coarse-nv", NULL};
  int known = 0;
  for (int j = 0; valued[j]; j++) known |= !strcmp(a, valued[j]);
  if (!known) return 0;
  if (!v) return -1;
  (*i)++;
  if (!strcmp(a, "--basis")) {
    m->mo.basis = !strcmp(v, "lb") ? SM_MATCH_LB : !strcmp(v, "elastic") ? SM_MATCH_ELASTIC
                : !strcmp(v, "hybrid") ? SM_MATCH_HYBRID : 0;
    if (!m->mo.basis) return -1;
    m->co.basis = m->mo.basis;
  } else if (!strcmp(a, "--init")) {
    m->mo.init = !strcmp(v, "nn") ? SM_INIT_NN : !strcmp(v, "sinkhorn") ? SM_INIT_SINKHORN : 0;
    if (!m->mo.init) return -1;
    m->co.init = m->mo.init;
  } else if (!strcmp(a, "-k")) m->mo.k1 = m->co.k1 = atoi(v);
  else if (!strcmp(a, "--k0")) m->mo.k0 = m->co.k0 = atoi(v);
  else if (!strcmp(a, "--step")) m->mo.step = m->co.step = atoi(v);
  else if (!strcmp(a, "--refine-sinkhorn")) m->mo.sinkhorn_levels = m->co.sinkhorn_levels = atoi(v);
  else if (!strcmp(a, "--eta")) m->so.eta = m->co.eta = atof(v);
  else if (!strcmp(a, "--landmarks")) m->landmarks = v;
  else if (!strcmp(a, "--init-map")) m->init_map = v;
  else if (!strcmp(a, "-o")) m->out = v;
  else if (!strcmp(a, "--yx")) m->out_yx = v;
  else if (!strcmp(a, "--fmap")) m->out_fmap = v;
  else if (!strcmp(a, "--tips")) {
    m->mo.extremities = !strcmp(v, "off") ? SM_EXT_OFF : !strcmp(v, "doubtful")
                        ? SM_EXT_WHEN_DOUBTFUL : !strcmp(v, "always") ? SM_EXT_ALWAYS : -1;
    if (m->mo.extremities < 0) return -1;
  } else if (!strcmp(a, "--multires")) {
    m->ro.mode = !strcmp(v, "auto") ? SM_MULTIRES_AUTO : !strcmp(v, "on") ? SM_MULTIRES_ON
                 : !strcmp(v, "off") ? SM_MULTIRES_OFF : -1;
    if (m->ro.mode < 0) return -1;
    m->co.multires = m->ro.mode; /* the same enum on the wire (sm_client_match_opts) */
  } else if (!strcmp(a, "--coarse-nv")) {
    char *end;
    long nv = strtol(v, &end, 10);
    if (*end || nv < 200 || nv > 10000000) return -1;
    m->ro.coarse_nv = (int32_t)nv;
  }
  return 1;
}

static void match_args_finish(match_args *m) {
  if (m->mo.basis == SM_MATCH_LB) m->so.k_elastic = 0;
  if (m->mo.k1 > m->so.k_lb) m->so.k_lb = m->mo.k1;
  if (m->so.k_elastic && m->mo.k1 > m->so.k_elastic) m->so.k_elastic = m->mo.k1;
}

static int parse_match_args(int argc, char **argv, match_args *m) {
  match_args_init(m);
  for (int i = 0; i < argc; i++) {
    int r = parse_match_opt(argc, argv, &i, m);
    if (r < 0) return -1;
    if (r) continue;
    const char *a = argv[i];
    if (a[0] != '-') {
      if (!m->a) m->a = a;
      else if (!m->b) m->b = a;
      else return -1;
      continue;
    }
    return -1;
  }
  if (!m->a || !m->b) return -1;
  match_args_finish(m);
  return 0;
}

/* A progress line for the long steps, only when a person is watching. */
static void progress(const char *fmt, const char *arg) {
  if (!isatty(STDERR_FILENO)) return;
  fprintf(stderr, "\r\033[K");
  fprintf(stderr, fmt, arg);
  fflush(stderr);
}

/* The preparation options of the local commands: so's bases, computed two at a time (the
 * LB basis beside the elastic one; OpenBLAS itself runs on one thread, see main). */
static void local_prep_opts(const sm_shape_opts *so, sm_prep_opts *po) {
  sm_prep_opts_from_shape(po, so);
  po->threads = 2;
}

static int prepare_shape(const char *path, const sm_shape_opts *so, sm_shape **out) {
  sm_error err;
  sm_mesh *raw;
  if (sm_mesh_read_file(path, NULL, &raw, &err)) return fail(path, &err);
  progress("computing the bases of %s ...", path);
  sm_prep_opts po;
  local_prep_opts(so, &po);
  int rc = sm_prepare(raw, &po, out, NULL, &err);
  progress("%s", "");
  sm_mesh_destroy(raw);
  return rc ? fail(path, &err) : 0;
}

/* Landmarks and initial maps come in the caller's numbering: translate to cleaned indices. */
static int translate_inputs(const match_args *m, const sm_shape *x, const sm_shape *y,
                            int32_t **lm, int32_t **init) {
  int32_t *ix = sm_mesh_input_to_clean(x->mesh), *iy = sm_mesh_input_to_clean(y->mesh);
  int32_t *rows = NULL;
  int rc = 0;
  if (m->landmarks) {
    int n = read_index_rows(m->landmarks, 2, &rows);
    rc = n < 0;
    for (int i = 0; !rc && i < n; i++) {
      int32_t a = rows[2 * i], b = rows[2 * i + 1];
      if (a < 0 || a >= x->mesh->n_input || b < 0 || b >= y->mesh->n_input || ix[a] < 0 || iy[b] < 0) {
        fprintf(stderr, "shapematch: landmark %d (%d, %d) is not a vertex of both meshes\n", i + 1, a, b);
        rc = 1;
      } else {
        rows[2 * i] = ix[a];
        rows[2 * i + 1] = iy[b];
      }
    }
    *lm = rows;
    ((match_args *)m)->mo.landmarks = rows;
    ((match_args *)m)->mo.nlandmarks = rc ? 0 : n;
  }
  if (!rc && m->init_map) {
    int32_t *t = NULL;
    int n = read_index_rows(m->init_map, 1, &t);
    rc = n != x->mesh->n_input;
    if (rc && n >= 0) fprintf(stderr, "shapematch: %s has %d lines, A has %d vertices\n", m->init_map, n, x->mesh->n_input);
    *init = malloc((size_t)x->mesh->nv * sizeof **init);
    for (int32_t v = 0; !rc && v < x->mesh->nv; v++) {
      int32_t b = t[x->mesh->to_input ? x->mesh->to_input[v] : v];
      if (b < 0 || b >= y->mesh->n_input || iy[b] < 0) {
        fprintf(stderr, "shapematch: %s: entry %d is not a vertex of B\n", m->init_map, v);
        rc = 1;
      } else {
        (*init)[v] = iy[b];
      }
    }
    free(t);
    ((match_args *)m)->mo.init_map = *init;
  }
  free(ix);
  free(iy);
  return rc;
}

/* A map's confidence as a JSON value: null when it is unknown (a protocol version 1
 * server has no such field, PROTOCOL.md 7.1) or not in [0, 1] (printf's "nan" is not
 * JSON), so a script can tell "unknown" from a value. */
static void confidence_json(int has, double v, char *out, size_t cap) {
  if (has && v >= 0 && v <= 1) snprintf(out, cap, "%.6f", v);
  else snprintf(out, cap, "null");
}

static void print_match_json(const match_args *m, const sm_shape *x, const sm_shape *y,
                             const sm_match_result *r, double t_total) {
  char conf[32];
  confidence_json(1, r->confidence, conf, sizeof conf);
  printf("{\"source\":\"%s\",\"target\":\"%s\",\"n_source\":%d,\"n_target\":%d,"
         "\"basis\":\"%s\",\"init\":\"%s\",\"k0\":%d,\"k1\":%d,\"step\":%d,"
         "\"orientation\":%.6f,\"confidence\":%s,\"flipped\":%d,\"init_distinct\":%.6f,"
         "\"start_used\":\"%s\",\"dirichlet\":%.6f,\"tips\":{\"tried\":%d,\"kept\":%d},"
         "\"time\":{\"basis\":%.4f,\"init\":%.4f,\"refine\":%.4f,\"total\":%.4f},"
         "\"multires\":%s,\"map\":\"%s\"}\n",
         m->a, m->b, x->mesh->n_input, y->mesh->n_input,
         m->mo.basis == SM_MATCH_LB ? "lb" : m->mo.basis == SM_MATCH_ELASTIC ? "elastic" : "hybrid",
         m->mo.init == SM_INIT_NN ? "nn" : "sinkhorn", m->mo.k0, m->mo.k1, m->mo.step,
         r->orientation, conf, r->flipped, r->init_distinct,
         r->init_used == SM_INIT_NN ? "nn" : "sinkhorn", r->dirichlet, r->ext_tried,
         r->ext_hypothesis,
         x->t_clean + x->t_lb + x->t_elastic + x->t_desc + y->t_clean + y->t_lb + y->t_elastic + y->t_desc,
         r->t_init, r->t_refine, t_total, m->multires_json, m->out ? m->out : "");
}

/* The functional map as text: k rows of k numbers, row i = coefficient i on A. */
static int write_fmap(const char *path, const double *C, int k) {
  FILE *f = fopen(path, "w");
  if (!f) {
    perror(path);
    return 1;
  }
  for (int i = 0; i < k; i++)
    for (int j = 0; j < k; j++) fprintf(f, "%.17g%c", C[(size_t)j * k + i], j + 1 < k ? ' ' : '\n');
  if (fclose(f)) {
    perror(path);
    return 1;
  }
  return 0;
}

typedef struct match_run {
  sm_shape *x, *y;
  /* The multi-resolution path: its shapes, and views of their full-resolution meshes
   * (mesh and preparation times only) for what follows the match. */
  sm_multires_shape *mx, *my;
  sm_shape vx, vy;
  int32_t *lm, *init;
  sm_match_result r;
  double t_total;
} match_run;

static void match_run_free(match_run *mr) {
  free(mr->lm);
  free(mr->init);
  sm_match_result_free(&mr->r);
  sm_shape_destroy(mr->x);
  sm_shape_destroy(mr->y);
  sm_multires_shape_destroy(mr->mx);
  sm_multires_shape_destroy(mr->my);
}

/* One shape's coarse level, for prepare_multires_pair. */
typedef struct multires_prep {
  const sm_mesh *raw;
  const sm_prep_opts *po;
  const sm_multires_opts *ro;
  sm_multires_shape *out;
  sm_error err;
  int rc;
} multires_prep;

static void *prepare_multires_one(void *arg) {
  multires_prep *j = arg;
  j->rc = sm_prepare_multires(j->raw, j->po, j->ro, &j->out, NULL, &j->err);
  return NULL;
}

/* Both shapes' coarse levels at once, one thread each with one basis at a time (the CLI's
 * two threads): clean, decimation and location are sequential per shape, so two shapes
 * side by side take about half the wall time of one after the other (koala, 50k
 * vertices: docs/RESULTS.md section 7). Without a second thread, one after the other. */
static int prepare_multires_pair(const match_args *m, const sm_mesh *ra, const sm_mesh *rb,
                                 match_run *mr) {
  sm_prep_opts po;
  local_prep_opts(&m->so, &po);
  po.threads = 1;
  multires_prep j[2] = {{.raw = ra, .po = &po, .ro = &m->ro}, {.raw = rb, .po = &po, .ro = &m->ro}};
  pthread_t th;
  int threaded = !pthread_create(&th, NULL, prepare_multires_one, &j[1]);
  prepare_multires_one(&j[0]);
  if (threaded) pthread_join(th, NULL);
  else prepare_multires_one(&j[1]);
  mr->mx = j[0].out;
  mr->my = j[1].out;
  if (j[0].rc) return fail(m->a, &j[0].err);
  if (j[1].rc) return fail(m->b, &j[1].err);
  return 0;
}

/* The multi-resolution path (sm_multires.h) when --multires and the sizes ask for it:
 * returns 1 when it ran (its status in *rc), 0 for the direct path. The result is moved
 * into mr->r as sm_match would give it: the fine maps and their orientation, confidence
 * and Dirichlet energy, the coarse level's C, start and tip-search fields. */
static int run_multires(match_args *m, match_run *mr, int *rc) {
  sm_error err;
  sm_mesh *ra = NULL, *rb = NULL;
  if (m->ro.mode == SM_MULTIRES_OFF) return 0;
  if (sm_mesh_read_file(m->a, NULL, &ra, &err)) return *rc = fail(m->a, &err), 1;
  if (sm_mesh_read_file(m->b, NULL, &rb, &err)) {
    sm_mesh_destroy(ra);
    return *rc = fail(m->b, &err), 1;
  }
  int want = sm_multires_wanted(&m->ro, ra->nv, rb->nv);
  if (want) {
    progress("%s", "building the coarse levels of both shapes ...");
    *rc = prepare_multires_pair(m, ra, rb, mr);
    progress("%s", "");
  }
  sm_mesh_destroy(ra);
  sm_mesh_destroy(rb);
  if (!want || *rc) return want;
  sm_multires_shape *s[2] = {mr->mx, mr->my};
  sm_shape *v[2] = {&mr->vx, &mr->vy};
  for (int i = 0; i < 2; i++) {
    v[i]->mesh = s[i]->mesh;
    v[i]->t_clean = s[i]->t_clean + s[i]->t_decimate + s[i]->t_locate;
    v[i]->t_lb = s[i]->coarse->t_clean + s[i]->coarse->t_lb;
    v[i]->t_elastic = s[i]->coarse->t_elastic;
    v[i]->t_desc = s[i]->coarse->t_desc;
  }
  *rc = translate_inputs(m, &mr->vx, &mr->vy, &mr->lm, &mr->init);
  sm_multires_result res;
  progress("%s", "matching ...");
  if (!*rc && sm_multires_match(mr->mx, mr->my, &m->mo, &m->ro, &res, &err)) *rc = fail("match", &err);
  progress("%s", "");
  if (*rc) return 1;
  mr->r = res.coarse;
  free(mr->r.T);
  free(mr->r.T_yx);
  mr->r.T = res.T;
  mr->r.T_yx = res.T_yx;
  mr->r.nx = res.nx;
  mr->r.ny = res.ny;
  mr->r.orientation = res.orientation;
  mr->r.confidence = res.confidence;
  mr->r.continuity = res.continuity;
  mr->r.cycle = res.cycle;
  mr->r.dirichlet = res.dirichlet;
  snprintf(m->multires_json, sizeof m->multires_json,
           "{\"coarse_source\":%d,\"coarse_target\":%d,\"time\":{\"prepare\":%.4f,"
           "\"coarse_bases\":%.4f,\"coarse_match\":%.4f,\"prolong\":%.4f}}",
           mr->mx->coarse->mesh->nv, mr->my->coarse->mesh->nv,
           mr->mx->t_clean + mr->mx->t_decimate + mr->mx->t_locate + mr->my->t_clean +
               mr->my->t_decimate + mr->my->t_locate,
           mr->mx->t_coarse + mr->my->t_coarse, res.t_match, res.t_prolong);
  return 1;
}

static int run_match(match_args *m, match_run *mr) {
  memset(mr, 0, sizeof *mr);
  double t0 = sm_now();
  int rc = 0;
  if (run_multires(m, mr, &rc)) {
    mr->t_total = sm_now() - t0;
    return rc;
  }
  rc = prepare_shape(m->a, &m->so, &mr->x) || prepare_shape(m->b, &m->so, &mr->y);
  if (!rc) rc = translate_inputs(m, mr->x, mr->y, &mr->lm, &mr->init);
  if (!rc) {
    sm_error err;
    progress("%s", "matching ...");
    int mrc = sm_match(mr->x, mr->y, &m->mo, &mr->r, &err);
    progress("%s", "");
    if (mrc) rc = fail("match", &err);
  }
  mr->t_total = sm_now() - t0;
  return rc;
}

/* ---- the daemon (sm_client) ---- */

static volatile sig_atomic_t g_stop = 0;
static void on_sigint(int sig) {
  (void)sig;
  g_stop = 1;
}

/* Client time limits from --timeout / --io-timeout (seconds; 0 = the library default). */
static int g_timeout_ms = 0, g_io_timeout_ms = 0;
static int g_reconnect = 5; /* --reconnect: connection attempts after a lost connection */

static int parse_secs(const char *v, int *ms) {
  char *e;
  double d = v ? strtod(v, &e) : -1;
  if (!v || *e || !(d >= 0) || d > 2e6) return -1;
  *ms = (int)(d * 1000 + 0.5);
  if (d > 0 && *ms == 0) *ms = 1;
  return 0;
}

/* Removes "--server ADDR", "--local", "--timeout S", "--io-timeout S" and "--reconnect N" from argv
 * (compacting it); falls back to $SHAPEMATCH_SERVER. *addr is NULL when no server is
 * named or --local was given. Returns -1 when a flag lacks its value. */
static int take_server(int *argc, char **argv, const char **addr) {
  int n = 0, local = 0;
  const char *a = NULL;
  for (int i = 0; i < *argc; i++) {
    if (!strcmp(argv[i], "--server")) {
      if (i + 1 >= *argc) return -1;
      a = argv[++i];
    } else if (!strcmp(argv[i], "--timeout")) {
      if (i + 1 >= *argc || parse_secs(argv[++i], &g_timeout_ms)) return -1;
    } else if (!strcmp(argv[i], "--io-timeout")) {
      if (i + 1 >= *argc || parse_secs(argv[++i], &g_io_timeout_ms) || !g_io_timeout_ms) return -1;
    } else if (!strcmp(argv[i], "--reconnect")) {
      char *end;
      long v = i + 1 < *argc ? strtol(argv[++i], &end, 10) : -1;
      if (v < 0 || v > 100 || *end) return -1;
      g_reconnect = (int)v;
    } else if (!strcmp(argv[i], "--local")) local = 1;
    else argv[n++] = argv[i];
  }
  *argc = n;
  if (!a) a = getenv("SHAPEMATCH_SERVER");
  if (a && !*a) a = NULL;
  *addr = local ? NULL : a;
  return 0;
}

/* "shapematch: WHAT: MESSAGE", WHAT left out when the message already names it (the
 * core's file errors do), so that nothing is said twice. */
static int client_fail(const char *what, const sm_client_error *e) {
  const char *msg = e->msg[0] ? e->msg : sm_client_strerror(e->code);
  if (strstr(msg, what)) fprintf(stderr, "shapematch: %s\n", msg);
  else fprintf(stderr, "shapematch: %s: %s\n", what, msg);
  return 1;
}

/* Connects with the options every command shares; affinity: a shape id or NULL. */
static int open_client(const char *addr, const uint8_t *affinity, sm_client **c) {
  sm_client_opts o;
  sm_client_error e;
  sm_client_opts_default(&o);
  const char *tok = getenv("SHAPEMATCH_TOKEN");
  if (tok && *tok) {
    o.token = (const uint8_t *)tok;
    o.token_len = strlen(tok);
  }
  o.affinity = affinity;
  o.compute_timeout_ms = g_timeout_ms;
  if (g_io_timeout_ms) o.io_timeout_ms = g_io_timeout_ms;
  o.reconnect_tries = g_reconnect;
  o.stop = &g_stop;
  signal(SIGINT, on_sigint);
  if (sm_client_connect(addr, &o, c, &e)) return client_fail("connect", &e);
  return 0;
}

/* Closes; says on stderr when requests went over more than one connection, so that a
 * user (or a test) can tell a batch that survived a lost daemon. */
static void close_client(sm_client *c) {
  unsigned n = sm_client_reconnects(c);
  if (n) fprintf(stderr, "shapematch: the connection was lost and made again %u time%s; the requests it "
                         "cut were sent again\n", n, n == 1 ? "" : "s");
  sm_client_close(c);
}

/* A shape named on the command line: a mesh file, or the hex id of a stored shape. */
typedef struct shape_ref {
  const char *arg;
  uint8_t id[SM_PROTO_ID_LEN];
  uint8_t *draco; /* NULL for an id */
  size_t len;
  uint32_t nv;    /* input vertices, once known */
  int state;      /* 0 not resolved, 1 ready, -1 failed */
  sm_client_error err;
} shape_ref;

static int is_file(const char *p) {
  struct stat st;
  return stat(p, &st) == 0;
}

/* Computes the id (encoding the file when needed). Returns 0 or 1 (message in r->err). */
static int ref_load(shape_ref *r, const char *arg) {
  memset(r, 0, sizeof *r);
  r->arg = arg;
  if (!is_file(arg) && !sm_client_id_from_hex(arg, r->id)) return 0;
  if (sm_client_file_draco(arg, &r->draco, &r->len, &r->err)) {
    r->state = -1;
    return 1;
  }
  sm_client_shape_id(r->draco, r->len, r->id);
  return 0;
}

/* Makes sure the server has the shape (uploads it unless stored). 0 or 1. */
static int ref_upload(sm_client *c, shape_ref *r, int prepare) {
  if (r->state) return r->state < 0;
  sm_proto_has_resp h;
  sm_proto_put_resp p;
  if (sm_client_has(c, r->id, &h, &r->err)) goto bad;
  if (h.flags & SM_HAS_STORED) {
    r->nv = h.n_vertices;
    if (!prepare || (h.flags & SM_HAS_PREPARED)) {
      r->state = 1;
      return 0;
    }
  } else if (!r->draco) {
    char hex[SM_CLIENT_ID_HEX_LEN + 1];
    sm_client_id_to_hex(r->id, hex);
    snprintf(r->err.msg, sizeof r->err.msg, "shape %s is not stored on the server", hex);
    r->err.code = SM_CLIENT_ESTATUS;
    r->err.status = SM_ST_NOT_FOUND;
    goto bad;
  }
  if (r->draco) {
    if (sm_client_put(c, r->draco, r->len, prepare, NULL, &p, &r->err)) goto bad;
    r->nv = p.n_vertices;
  } else if (sm_client_prepare(c, r->id, 0, 0, 0, NULL, &r->err)) goto bad;
  r->state = 1;
  return 0;
bad:
  r->state = -1;
  return 1;
}

static void ref_free(shape_ref *r) {
  free(r->draco);
  r->draco = NULL;
}

typedef struct strv {
  char **v;
  size_t n, cap;
} strv;

static int strv_push(strv *s, const char *str) {
  if (s->n == s->cap) {
    size_t nc = s->cap ? 2 * s->cap : 16;
    char **v = realloc(s->v, nc * sizeof *v);
    if (!v) return 1;
    s->v = v;
    s->cap = nc;
  }
  return !(s->v[s->n++] = strdup(str));
}

static void strv_free(strv *s) {
  for (size_t i = 0; i < s->n; i++) free(s->v[i]);
  free(s->v);
}

/* ---- pipelined uploads ---- */

typedef struct upload_ctx {
  shape_ref **refs;  /* refs[k] of the current batch */
  size_t *which;     /* request -> index into refs */
  int prepare;
  void (*settled)(void *ud, shape_ref *r);
  void *ud;
} upload_ctx;

static int upload_has_cb(void *ud, size_t i, const sm_client_req *req, const sm_client_resp *r) {
  (void)req;
  upload_ctx *u = ud;
  shape_ref *s = u->refs[u->which[i]];
  if (r->code) {
    s->err = r->err;
    s->state = -1;
  } else if (r->has.flags & SM_HAS_STORED) {
    s->nv = r->has.n_vertices;
    if (!u->prepare || (r->has.flags & SM_HAS_PREPARED)) s->state = 1;
  } else if (!s->draco) {
    char hex[SM_CLIENT_ID_HEX_LEN + 1];
    sm_client_id_to_hex(s->id, hex);
    memset(&s->err, 0, sizeof s->err);
    snprintf(s->err.msg, sizeof s->err.msg, "shape %s is not stored on the server", hex);
    s->err.code = SM_CLIENT_ESTATUS;
    s->err.status = SM_ST_NOT_FOUND;
    s->state = -1;
  }
  if (s->state && u->settled) u->settled(u->ud, s);
  return 0;
}

static int upload_put_cb(void *ud, size_t i, const sm_client_req *req, const sm_client_resp *r) {
  upload_ctx *u = ud;
  shape_ref *s = u->refs[u->which[i]];
  if (r->code) {
    s->err = r->err;
    s->state = -1;
  } else {
    if (req->op == SM_OP_PUT_SHAPE) s->nv = r->put.n_vertices;
    s->state = 1;
  }
  if (u->settled) u->settled(u->ud, s);
  return 0;
}

/* Makes sure the server stores refs[0..n) (and, with prepare, has their default bases),
 * pipelining up to `inflight` requests: HAS for each unresolved ref, then PUT_SHAPE (or
 * PREPARE for a stored id) for those that need it. A request waiting in the server's queue
 * is waited for as long as the server answers (sm_client.h); BUSY answers are retried.
 * settled(ud, ref) runs as each ref gets its state (1 ready, -1 failed, message in
 * ref->err). Returns 0, or 1 when the connection was lost or the user stopped it
 * (unsettled refs then fail). */
static int upload_refs(sm_client *c, shape_ref **refs, size_t n, int prepare, unsigned inflight,
                       void (*settled)(void *, shape_ref *), void *ud) {
  sm_client_req *reqs = calloc(n ? n : 1, sizeof *reqs);
  size_t *which = calloc(n ? n : 1, sizeof *which);
  upload_ctx u = {refs, which, prepare, settled, ud};
  sm_client_error e;
  memset(&e, 0, sizeof e);
  int rc = !reqs || !which;
  if (rc) snprintf(e.msg, sizeof e.msg, "out of memory");
  for (int phase = 0; !rc && phase < 2; phase++) {
    size_t nr = 0;
    for (size_t k = 0; k < n; k++) {
      shape_ref *s = refs[k];
      if (s->state) continue;
      sm_client_req *q = &reqs[nr];
      memset(q, 0, sizeof *q);
      memcpy(q->x, s->id, SM_PROTO_ID_LEN);
      if (phase == 0) q->op = SM_OP_HAS_SHAPE;
      else if (s->draco) {
        q->op = SM_OP_PUT_SHAPE;
        q->draco = s->draco;
        q->draco_len = s->len;
        q->prepare = prepare;
      } else q->op = SM_OP_PREPARE;
      which[nr++] = k;
    }
    if (!nr) break;
    if (sm_client_batch(c, reqs, nr, inflight, -1, phase ? upload_put_cb : upload_has_cb, &u,
                        NULL, &e))
      rc = 1; /* connection lost or stopped (Ctrl-C): unsent refs fail below */
  }
  for (size_t k = 0; k < n; k++) /* not sent: the connection was lost or out of memory */
    if (!refs[k]->state) {
      refs[k]->err = e;
      if (!refs[k]->err.msg[0]) snprintf(refs[k]->err.msg, sizeof refs[k]->err.msg, "not uploaded");
      refs[k]->state = -1;
      if (settled) settled(ud, refs[k]);
    }
  free(reqs);
  free(which);
  return rc;
}

typedef struct put_ctx {
  shape_ref *refs;
  size_t n, printed;
  int rc;
} put_ctx;

/* Prints the settled prefix, in argument order. */
static void put_settled(void *ud, shape_ref *r) {
  (void)r;
  put_ctx *p = ud;
  while (p->printed < p->n && p->refs[p->printed].state) {
    shape_ref *s = &p->refs[p->printed++];
    if (s->state < 0) {
      p->rc = client_fail(s->arg, &s->err);
    } else {
      char hex[SM_CLIENT_ID_HEX_LEN + 1];
      sm_client_id_to_hex(s->id, hex);
      printf("%s  %s\n", hex, s->arg);
      fflush(stdout);
    }
    ref_free(s);
  }
}

#define PUT_CHUNK 32 /* files encoded and held in memory at once */

static int cmd_put(int argc, char **argv, const char *addr) {
  int prepare = 0, inflight = 4;
  strv files = {0};
  for (int i = 0; i < argc; i++) {
    if (!strcmp(argv[i], "--prepare")) prepare = 1;
    else if (!strcmp(argv[i], "--inflight") && i + 1 < argc) inflight = atoi(argv[++i]);
    else if (argv[i][0] == '-') return usage(stderr);
    else if (strv_push(&files, argv[i])) return 1;
  }
  if (!files.n || inflight < 1) {
    strv_free(&files);
    return usage(stderr);
  }
  sm_client *c;
  if (open_client(addr, NULL, &c)) {
    strv_free(&files);
    return 1;
  }
  int rc = 0;
  for (size_t at = 0; at < files.n; at += PUT_CHUNK) {
    size_t n = files.n - at < PUT_CHUNK ? files.n - at : PUT_CHUNK;
    shape_ref refs[PUT_CHUNK], *rp[PUT_CHUNK];
    put_ctx p = {refs, n, 0, 0};
    for (size_t k = 0; k < n; k++) {
      progress("encoding %s ...", files.v[at + k]);
      ref_load(&refs[k], files.v[at + k]);
      rp[k] = &refs[k];
    }
    progress("%s", "");
    put_settled(&p, NULL); /* files that failed to load, if they come first */
    int lost = upload_refs(c, rp, n, prepare, (unsigned)inflight, put_settled, &p);
    put_settled(&p, NULL);
    if (p.rc) rc = 1;
    for (size_t k = 0; k < n; k++) ref_free(&refs[k]);
    if (lost) {
      for (size_t k = at + n; k < files.n; k++)
        fprintf(stderr, "shapematch: %s: not uploaded\n", files.v[k]);
      rc = 1;
      break;
    }
  }
  close_client(c);
  strv_free(&files);
  return rc;
}

/* Landmarks and the initial map travel in the files' own numbering: read them as they are. */
static int remote_inputs(const match_args *m, sm_client_match_opts *co, int32_t **lm, int32_t **init) {
  *lm = *init = NULL;
  if (m->landmarks) {
    int n = read_index_rows(m->landmarks, 2, lm);
    if (n < 0) return 1;
    co->landmarks = *lm;
    co->n_landmarks = (uint32_t)n;
  }
  if (m->init_map) {
    int n = read_index_rows(m->init_map, 1, init);
    if (n < 0) return 1;
    co->init_map = *init;
    co->n_init_map = (uint32_t)n;
  }
  return 0;
}

/* Connects with A's id as the affinity key and makes sure both shapes are stored. */
static int remote_pair(const char *addr, const match_args *m, shape_ref *x, shape_ref *y, sm_client **c) {
  *c = NULL;
  if (ref_load(x, m->a)) return client_fail(m->a, &x->err);
  if (ref_load(y, m->b)) {
    ref_free(x);
    return client_fail(m->b, &y->err);
  }
  int rc = open_client(addr, x->id, c);
  if (!rc && ref_upload(*c, x, 0)) rc = client_fail(m->a, &x->err);
  if (!rc && ref_upload(*c, y, 0)) rc = client_fail(m->b, &y->err);
  ref_free(x);
  ref_free(y);
  return rc;
}

static const char *basis_name(int b) {
  return b == SM_MATCH_LB ? "lb" : b == SM_MATCH_ELASTIC ? "elastic" : "hybrid";
}

static int remote_match(const char *addr, match_args *m) {
  shape_ref x, y;
  sm_client *c = NULL;
  double t0 = sm_now();
  int32_t *lm = NULL, *init = NULL;
  int rc = remote_inputs(m, &m->co, &lm, &init);
  if (!rc) rc = remote_pair(addr, m, &x, &y, &c);
  sm_client_match_result r;
  memset(&r, 0, sizeof r);
  if (!rc) {
    sm_client_error e;
    m->co.want_yx = m->out_yx != NULL;
    m->co.want_fmap = m->out_fmap != NULL;
    progress("%s", "matching on the server ...");
    if (sm_client_match(c, x.id, y.id, &m->co, &r, &e)) rc = client_fail("match", &e);
    progress("%s", "");
  }
  double t_total = sm_now() - t0;
  if (!rc && m->out) rc = write_map(m->out, r.map_xy, (int32_t)r.nx);
  if (!rc && m->out_yx) rc = write_map(m->out_yx, r.map_yx, (int32_t)r.ny);
  if (!rc && m->out_fmap) rc = write_fmap(m->out_fmap, r.fmap, r.kC);
  if (!rc) rc = smcli_pic_write(m->pic, m->a, m->b, r.map_xy, (int32_t)r.nx);
  if (!rc && m->json) {
    char hx[SM_CLIENT_ID_HEX_LEN + 1], hy[SM_CLIENT_ID_HEX_LEN + 1];
    sm_client_id_to_hex(x.id, hx);
    sm_client_id_to_hex(y.id, hy);
    /* the local keys; init_distinct is not on the wire (null), nor is confidence from a
     * version 1 server (null); the ids are extra */
    char conf[32];
    confidence_json(r.has_confidence, r.confidence, conf, sizeof conf);
    printf("{\"source\":\"%s\",\"target\":\"%s\",\"n_source\":%u,\"n_target\":%u,"
           "\"basis\":\"%s\",\"init\":\"%s\",\"k0\":%d,\"k1\":%d,\"step\":%d,"
           "\"orientation\":%.6f,\"confidence\":%s,\"flipped\":%d,\"init_distinct\":null,"
           "\"start_used\":\"%s\",\"dirichlet\":%.6f,\"tips\":null,"
           "\"time\":{\"basis\":%.4f,\"init\":%.4f,\"refine\":%.4f,\"total\":%.4f},"
           "\"map\":\"%s\",\"server\":true,\"source_id\":\"%s\",\"target_id\":\"%s\"}\n",
           m->a, m->b, r.nx, y.nv, basis_name(m->mo.basis),
           m->mo.init == SM_INIT_NN ? "nn" : "sinkhorn", m->mo.k0, m->mo.k1, m->mo.step,
           r.orientation, conf, r.flipped, r.init_used == SM_INIT_NN ? "nn" : "sinkhorn", r.dirichlet,
           r.t_prepare, r.t_init, r.t_refine, t_total, m->out ? m->out : "", hx, hy);
  } else if (!rc) {
    char conf[32];
    if (r.has_confidence) snprintf(conf, sizeof conf, "%.3f", r.confidence);
    else snprintf(conf, sizeof conf, "n/a (protocol version 1 server)");
    fprintf(stderr, "matched %u -> %u vertices in %.2f s on the server (bases %.2f, init %.2f, "
            "refine %.2f); orientation %.3f%s, confidence %s%s%s\n", r.nx, y.nv, t_total,
            r.t_prepare, r.t_init, r.t_refine, r.orientation, r.flipped ? " (mirror fixed)" : "",
            conf, m->out ? "; map in " : "", m->out ? m->out : "");
  }
  sm_client_match_result_free(&r);
  free(lm);
  free(init);
  close_client(c);
  return rc ? 1 : 0;
}

static int remote_distance(const char *addr, match_args *m) {
  shape_ref x, y;
  sm_client *c = NULL;
  double t0 = sm_now();
  int32_t *lm = NULL, *init = NULL;
  int rc = remote_inputs(m, &m->co, &lm, &init);
  if (!rc) rc = remote_pair(addr, m, &x, &y, &c);
  sm_proto_dist d;
  if (!rc) {
    sm_client_error e;
    progress("%s", "distance on the server ...");
    if (sm_client_distance(c, x.id, y.id, &m->co, &d, NULL, &e)) rc = client_fail("distance", &e);
    progress("%s", "");
  }
  double t = sm_now() - t0;
  if (!rc) {
    printf("%.6f\n", d.total);
    if (m->json)
      fprintf(stderr, "{\"distance\":%.9f,\"point_xy\":%.9f,\"point_yx\":%.9f,"
              "\"spectrum_lb\":%.9f,\"spectrum_elastic\":%.9f,\"orientation\":null,"
              "\"confidence\":null,\"time\":%.4f}\n", d.total, d.point_xy, d.point_yx,
              d.spectrum_lb, d.spectrum_elastic, t);
    else
      fprintf(stderr, "distance %.6f (point %.6f / %.6f, LB spectrum %.6f, elastic spectrum "
              "%.6f) in %.2f s on the server\n", d.total, d.point_xy, d.point_yx, d.spectrum_lb,
              d.spectrum_elastic, t);
  }
  free(lm);
  free(init);
  close_client(c);
  return rc ? 1 : 0;
}

static int cmd_query(int argc, char **argv, const char *addr) {
  const char *a = NULL;
  int k = 10, mode = SM_QUERY_DEFAULT, json = 0;
  for (int i = 0; i < argc; i++) {
    if (!strcmp(argv[i], "-k") && i + 1 < argc) k = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--json")) json = 1;
    else if (!strcmp(argv[i], "--mode") && i + 1 < argc) {
      const char *v = argv[++i];
      mode = !strcmp(v, "spectral") ? SM_QUERY_SPECTRAL : !strcmp(v, "full") ? SM_QUERY_FULL
           : !strcmp(v, "default") ? SM_QUERY_DEFAULT : -1;
      if (mode < 0) return usage(stderr);
    } else if (argv[i][0] == '-' || a) return usage(stderr);
    else a = argv[i];
  }
  if (!a || k < 1) return usage(stderr);
  shape_ref r;
  sm_client *c;
  if (ref_load(&r, a)) return client_fail(a, &r.err);
  int rc = open_client(addr, r.id, &c);
  if (!rc && ref_upload(c, &r, 0)) rc = client_fail(a, &r.err);
  ref_free(&r);
  sm_client_hit *h = NULL;
  uint32_t n = 0, considered = 0;
  sm_client_error e;
  if (!rc && sm_client_query(c, r.id, k, mode, NULL, 0, 0, &h, &n, &considered, &e))
    rc = client_fail("query", &e);
  for (uint32_t i = 0; !rc && i < n; i++) {
    char hex[SM_CLIENT_ID_HEX_LEN + 1];
    sm_client_id_to_hex(h[i].id, hex);
    if (json) printf("%s{\"id\":\"%s\",\"distance\":%.9f}", i ? "," : "[", hex, h[i].distance);
    else printf("%.6f %s\n", h[i].distance, hex);
  }
  if (!rc && json) printf("%s]\n", n ? "" : "[");
  if (!rc) fprintf(stderr, "%u hits; %u stored shapes considered\n", n, considered);
  free(h);
  close_client(c);
  return rc;
}

static int cmd_stats(int argc, char **argv, const char *addr, int ping) {
  int json = 0;
  for (int i = 0; i < argc; i++) {
    if (!strcmp(argv[i], "--json")) json = 1;
    else return usage(stderr);
  }
  sm_client *c;
  sm_client_error e;
  if (open_client(addr, NULL, &c)) return 1;
  int rc = 0;
  if (ping) {
    double rtt;
    if (sm_client_ping(c, &rtt, &e)) rc = client_fail("ping", &e);
    else printf("ok %.3f ms (protocol v%u)\n", 1e3 * rtt, sm_client_limits(c)->version);
  } else {
    sm_proto_stat *st;
    uint32_t n;
    if (sm_client_stats(c, &st, &n, &e)) rc = client_fail("stats", &e);
    else {
      for (uint32_t i = 0; i < n; i++) {
        if (json) printf("%s\"%s\":%llu", i ? "," : "{", st[i].name, (unsigned long long)st[i].value);
        else printf("%s %llu\n", st[i].name, (unsigned long long)st[i].value);
      }
      if (json) printf("%s}\n", n ? "" : "{");
      free(st);
    }
  }
  close_client(c);
  return rc;
}

/* ---- batch ---- */

static void json_str(FILE *f, const char *s) {
  fputc('"', f);
  for (; *s; s++) {
    unsigned char ch = (unsigned char)*s;
    if (ch == '"' || ch == '\\') fprintf(f, "\\%c", ch);
    else if (ch < 0x20) fprintf(f, "\\u%04x", ch);
    else fputc(ch, f);
  }
  fputc('"', f);
}

static int is_mesh_name(const char *s) {
  static const char *const ext[] = {".off", ".obj", ".ply", ".stl", ".drc", NULL};
  char low[512];
  size_t n = strlen(s);
  if (n >= sizeof low) return 0;
  for (size_t i = 0; i <= n; i++) low[i] = (char)(s[i] >= 'A' && s[i] <= 'Z' ? s[i] - 'A' + 'a' : s[i]);
  if (n > 3 && !strcmp(low + n - 3, ".gz")) low[n - 3] = 0;
  for (int i = 0; ext[i]; i++)
    if (has_suffix(low, ext[i])) return 1;
  return 0;
}

static int cmp_str(const void *a, const void *b) {
  return strcmp(*(char *const *)a, *(char *const *)b);
}

/* Words of a text file, whitespace-separated, '#' to the end of a line is a comment. */
static int read_words(const char *path, strv *out) {
  FILE *f = fopen(path, "r");
  if (!f) {
    perror(path);
    return 1;
  }
  char line[8192];
  int rc = 0;
  while (!rc && fgets(line, sizeof line, f)) {
    char *hash = strchr(line, '#');
    if (hash) *hash = 0;
    for (char *tok = strtok(line, " \t\r\n"); tok && !rc; tok = strtok(NULL, " \t\r\n"))
      rc = strv_push(out, tok);
  }
  fclose(f);
  return rc;
}

/* A gallery: every mesh file of a directory (sorted by name), or the paths a list file names. */
static int gallery_paths(const char *g, strv *out) {
  struct stat st;
  if (stat(g, &st)) {
    perror(g);
    return 1;
  }
  if (!S_ISDIR(st.st_mode)) return read_words(g, out);
  DIR *d = opendir(g);
  if (!d) {
    perror(g);
    return 1;
  }
  struct dirent *e;
  int rc = 0;
  size_t first = out->n;
  while (!rc && (e = readdir(d))) {
    if (!is_mesh_name(e->d_name)) continue;
    char p[4096];
    snprintf(p, sizeof p, "%s/%s", g, e->d_name);
    rc = strv_push(out, p);
  }
  closedir(d);
  qsort(out->v + first, out->n - first, sizeof *out->v, cmp_str);
  return rc;
}

typedef struct batch_ctx {
  const char **pa, **pb; /* per item: the names as given */
  size_t n, n_done, n_failed;
  const char *maps_dir;
  int tty;
  strv failed;          /* messages of failed items, printed at the end */
} batch_ctx;

static void batch_progress(const batch_ctx *b) {
  if (!b->tty) return;
  int w = 30, full = b->n ? (int)((double)w * (double)b->n_done / (double)b->n) : w;
  char bar[64];
  for (int i = 0; i < w; i++) bar[i] = i < full ? '#' : '.';
  bar[w] = 0;
  fprintf(stderr, "\r\033[K[%s] %zu/%zu%s", bar, b->n_done, b->n, b->n_failed ? " " : "");
  if (b->n_failed) fprintf(stderr, "(%zu failed)", b->n_failed);
  fflush(stderr);
}

static void batch_fail(batch_ctx *b, size_t i, const char *status, const char *msg) {
  printf("{\"index\":%zu,\"a\":", i);
  json_str(stdout, b->pa[i]);
  printf(",\"b\":");
  json_str(stdout, b->pb[i]);
  printf(",\"ok\":false,\"status\":\"%s\",\"error\":", status);
  json_str(stdout, msg);
  printf("}\n");
  fflush(stdout);
  char line[1024];
  snprintf(line, sizeof line, "item %zu (%s %s): %s", i, b->pa[i], b->pb[i], msg);
  strv_push(&b->failed, line);
  b->n_failed++;
  b->n_done++;
  batch_progress(b);
}

static int batch_cb(void *ud, size_t i, const sm_client_req *req, const sm_client_resp *r) {
  batch_ctx *b = ud;
  if (r->code) {
    batch_fail(b, i, r->code == SM_CLIENT_ESTATUS ? sm_proto_status_name(r->err.status) : sm_client_strerror(r->code),
               r->err.msg);
    return 0;
  }
  const sm_proto_dist *d = req->op == SM_OP_MATCH ? &r->match.dist : &r->dist;
  char map[4200] = "";
  if (req->op == SM_OP_MATCH && b->maps_dir) {
    snprintf(map, sizeof map, "%s/%zu.txt", b->maps_dir, i);
    if (write_map(map, r->match.map_xy, (int32_t)r->match.nx)) {
      batch_fail(b, i, "WRITE_FAILED", map);
      return 0;
    }
  }
  printf("{\"index\":%zu,\"a\":", i);
  json_str(stdout, b->pa[i]);
  printf(",\"b\":");
  json_str(stdout, b->pb[i]);
  printf(",\"ok\":true,\"distance\":%.9f,\"point_xy\":%.9f,\"point_yx\":%.9f,"
         "\"spectrum_lb\":%.9f,\"spectrum_elastic\":%.9f,\"time\":%.4f",
         d->total, d->point_xy, d->point_yx, d->spectrum_lb, d->spectrum_elastic,
         req->op == SM_OP_MATCH ? r->match.t_total : r->t_total);
  if (req->op == SM_OP_MATCH) {
    char conf[32];
    confidence_json(r->match.has_confidence, r->match.confidence, conf, sizeof conf);
    printf(",\"orientation\":%.6f,\"confidence\":%s", r->match.orientation, conf);
  }
  if (map[0]) {
    printf(",\"map\":");
    json_str(stdout, map);
  }
  printf("}\n");
  fflush(stdout);
  b->n_done++;
  batch_progress(b);
  return 0;
}

static int cmd_batch(int argc, char **argv, const char *addr) {
  match_args m;
  const char *file = NULL, *query = NULL, *gallery = NULL, *maps = NULL;
  int inflight = 4;
  match_args_init(&m);
  for (int i = 0; i < argc; i++) {
    int r = parse_match_opt(argc, argv, &i, &m);
    if (r < 0) return usage(stderr);
    if (r) continue;
    const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
    if (!strcmp(a, "--query") && v) query = argv[++i];
    else if (!strcmp(a, "--gallery") && v) gallery = argv[++i];
    else if (!strcmp(a, "--inflight") && v) inflight = atoi(argv[++i]);
    else if (!strcmp(a, "--maps") && v) maps = argv[++i];
    else if (a[0] == '-' || file) return usage(stderr);
    else file = a;
  }
  if (m.landmarks || m.init_map || m.out || m.out_yx || m.out_fmap || inflight < 1 ||
      (!file == !query) || (!query != !gallery)) {
    fprintf(stderr, "shapematch batch: give FILE, or --query A with --gallery DIR|LIST; "
                    "per-pair options (-o, --yx, --fmap, --landmarks, --init-map) do not apply\n");
    return 2;
  }
  match_args_finish(&m);
  strv words = {0};
  if (file) {
    if (read_words(file, &words)) return 1;
    if (words.n % 2) {
      fprintf(stderr, "shapematch batch: %s: %zu names, not pairs 'A B'\n", file, words.n);
      strv_free(&words);
      return 1;
    }
  } else {
    strv g = {0};
    if (gallery_paths(gallery, &g)) {
      strv_free(&g);
      return 1;
    }
    for (size_t i = 0; i < g.n; i++)
      if (strcmp(g.v[i], query) && (strv_push(&words, query) || strv_push(&words, g.v[i]))) break;
    strv_free(&g);
  }
  size_t n = words.n / 2;
  if (!n) {
    fprintf(stderr, "shapematch batch: nothing to do\n");
    strv_free(&words);
    return 1;
  }
  /* distinct shapes: encode each once */
  strv names = {0};
  for (size_t i = 0; i < words.n; i++) {
    int seen = 0;
    for (size_t j = 0; j < names.n && !seen; j++) seen = !strcmp(names.v[j], words.v[i]);
    if (!seen) strv_push(&names, words.v[i]);
  }
  shape_ref *refs = calloc(names.n, sizeof *refs);
  sm_client_req *reqs = calloc(n, sizeof *reqs);
  size_t *item_of = calloc(n, sizeof *item_of);
  batch_ctx b = {0};
  b.pa = calloc(n, sizeof *b.pa);
  b.pb = calloc(n, sizeof *b.pb);
  b.n = n;
  b.maps_dir = maps;
  b.tty = isatty(STDERR_FILENO);
  sm_client *c = NULL;
  int rc = !refs || !reqs || !item_of || !b.pa || !b.pb;
  for (size_t j = 0; !rc && j < names.n; j++) {
    progress("encoding %s ...", names.v[j]);
    ref_load(&refs[j], names.v[j]);
  }
  progress("%s", "");
  if (!rc) rc = open_client(addr, query ? refs[0].id : NULL, &c);
  if (!rc) {
    shape_ref **rp = calloc(names.n, sizeof *rp);
    for (size_t j = 0; rp && j < names.n; j++) rp[j] = &refs[j];
    progress("%s", "uploading ...");
    if (!rp) {
      rc = 1;
      fprintf(stderr, "shapematch batch: out of memory\n");
    } else if (upload_refs(c, rp, names.n, 0, (unsigned)inflight, NULL, NULL)) {
      progress("%s", ""); /* the connection is gone: say why once */
      rc = 1;
      for (size_t j = 0; j < names.n; j++)
        if (refs[j].state < 0 && refs[j].draco) {
          client_fail(names.v[j], &refs[j].err);
          break;
        }
    }
    for (size_t j = 0; j < names.n; j++) ref_free(&refs[j]);
    free(rp);
  }
  progress("%s", "");
  size_t nreq = 0;
  m.co.want_distance = maps != NULL;
  for (size_t i = 0; !rc && i < n; i++) {
    const shape_ref *ra = NULL, *rb = NULL;
    for (size_t j = 0; j < names.n; j++) {
      if (!strcmp(names.v[j], words.v[2 * i])) ra = &refs[j];
      if (!strcmp(names.v[j], words.v[2 * i + 1])) rb = &refs[j];
    }
    b.pa[i] = words.v[2 * i];
    b.pb[i] = words.v[2 * i + 1];
    if (ra->state < 0 || rb->state < 0) {
      const shape_ref *bad = ra->state < 0 ? ra : rb;
      batch_fail(&b, i, "UPLOAD_FAILED", bad->err.msg);
      continue;
    }
    sm_client_req *q = &reqs[nreq];
    q->op = maps ? SM_OP_MATCH : SM_OP_DISTANCE;
    memcpy(q->x, ra->id, SM_PROTO_ID_LEN);
    memcpy(q->y, rb->id, SM_PROTO_ID_LEN);
    q->match = &m.co;
    item_of[nreq++] = i;
  }
  if (!rc && nreq) {
    /* the callback speaks of items: remap request positions to item numbers */
    const char **pa = calloc(nreq, sizeof *pa), **pb = calloc(nreq, sizeof *pb);
    batch_ctx bb = b;
    bb.pa = pa;
    bb.pb = pb;
    for (size_t k = 0; pa && pb && k < nreq; k++) {
      pa[k] = b.pa[item_of[k]];
      pb[k] = b.pb[item_of[k]];
    }
    sm_client_error e;
    int brc = !pa || !pb ? SM_CLIENT_ENOMEM
                         : sm_client_batch(c, reqs, nreq, (unsigned)inflight, -1, batch_cb, &bb, NULL, &e);
    b.n_done = bb.n_done;
    b.n_failed = bb.n_failed;
    b.failed = bb.failed;
    free(pa);
    free(pb);
    if (b.tty) fprintf(stderr, "\n");
    if (brc) rc = client_fail("batch", &e);
  }
  if (b.n_failed) {
    fprintf(stderr, "shapematch batch: %zu of %zu items failed:\n", b.n_failed, n);
    for (size_t k = 0; k < b.failed.n; k++) fprintf(stderr, "  %s\n", b.failed.v[k]);
  }
  if (!rc && b.n_done < n) fprintf(stderr, "shapematch batch: %zu of %zu items not done\n", n - b.n_done, n);
  int fail = rc || b.n_failed || b.n_done < n;
  close_client(c);
  strv_free(&b.failed);
  for (size_t j = 0; refs && j < names.n; j++) ref_free(&refs[j]);
  free(refs);
  free(reqs);
  free(item_of);
  free(b.pa);
  free(b.pb);
  strv_free(&names);
  strv_free(&words);
  return fail ? 1 : 0;
}

static int cmd_match(int argc, char **argv) {
  match_args m;
  match_run mr;
  const char *addr;
  smcli_pic pic;
  if (take_server(&argc, argv, &addr) || smcli_pic_take_opts(&argc, argv, &pic) ||
      parse_match_args(argc, argv, &m))
    return usage(stderr);
  m.pic = &pic;
  if (addr) return remote_match(addr, &m);
  m.mo.want_yx = m.out_yx != NULL;
  int rc = run_match(&m, &mr);
  const sm_shape *x = mr.mx ? &mr.vx : mr.x, *y = mr.my ? &mr.vy : mr.y;
  if (!rc) {
    int32_t *map = malloc((size_t)x->mesh->n_input * sizeof *map);
    sm_match_to_input(x, y, mr.r.T, map);
    if (m.out) rc = write_map(m.out, map, x->mesh->n_input);
    if (!rc) rc = smcli_pic_write(&pic, m.a, m.b, map, x->mesh->n_input);
    free(map);
    if (!rc && m.out_yx) {
      int32_t *back = malloc((size_t)y->mesh->n_input * sizeof *back);
      sm_match_to_input(y, x, mr.r.T_yx, back);
      rc = write_map(m.out_yx, back, y->mesh->n_input);
      free(back);
    }
    if (!rc && m.out_fmap) rc = write_fmap(m.out_fmap, mr.r.C, mr.r.kC);
    if (!rc && m.json) print_match_json(&m, x, y, &mr.r, mr.t_total);
    else if (!rc)
      fprintf(stderr, "matched %d -> %d vertices in %.2f s (bases %.2f, init %.2f, refine %.2f); "
              "orientation %.3f%s, confidence %.3f%s%s\n", x->mesh->n_input, y->mesh->n_input,
              mr.t_total, x->t_lb + x->t_elastic + y->t_lb + y->t_elastic, mr.r.t_init,
              mr.r.t_refine, mr.r.orientation, mr.r.flipped ? " (mirror fixed)" : "",
              mr.r.confidence, m.out ? "; map in " : "", m.out ? m.out : "");
    if (!rc && !m.json && mr.mx)
      fprintf(stderr, "multi-resolution: coarse levels of %d and %d vertices (bases = "
              "decimation, location and coarse bases)\n", mr.mx->coarse->mesh->nv,
              mr.my->coarse->mesh->nv);
  }
  match_run_free(&mr);
  return rc ? 1 : 0;
}

static int cmd_distance(int argc, char **argv) {
  match_args m;
  match_run mr;
  const char *addr;
  if (take_server(&argc, argv, &addr) || parse_match_args(argc, argv, &m)) return usage(stderr);
  if (addr) return remote_distance(addr, &m);
  sm_distance_match_opts(&m.mo);
  /* what the user asked for wins over the distance's preset */
  if (m.co.basis) m.mo.basis = m.co.basis;
  if (m.co.k1) m.mo.k1 = m.co.k1;
  if (m.co.k0) m.mo.k0 = m.co.k0;
  if (m.co.sinkhorn_levels >= 0) m.mo.sinkhorn_levels = m.co.sinkhorn_levels;
  m.ro.mode = SM_MULTIRES_OFF; /* the distance needs the full-resolution bases */
  int rc = run_match(&m, &mr);
  sm_distance_parts d;
  sm_error err;
  if (!rc && sm_shape_distance(mr.x, mr.y, mr.r.T, mr.r.T_yx, &d, &err)) rc = fail("distance", &err);
  if (!rc) {
    char conf[32];
    confidence_json(1, mr.r.confidence, conf, sizeof conf);
    printf("%.6f\n", d.total);
    if (m.json)
      fprintf(stderr, "{\"distance\":%.9f,\"point_xy\":%.9f,\"point_yx\":%.9f,"
              "\"spectrum_lb\":%.9f,\"spectrum_elastic\":%.9f,\"orientation\":%.6f,"
              "\"confidence\":%s,\"time\":%.4f}\n", d.total, d.point_xy, d.point_yx,
              d.spectrum_lb, d.spectrum_elastic, mr.r.orientation, conf, mr.t_total);
    else
      fprintf(stderr, "distance %.6f (point %.6f / %.6f, LB spectrum %.6f, elastic spectrum "
              "%.6f) in %.2f s\n", d.total, d.point_xy, d.point_yx, d.spectrum_lb,
              d.spectrum_elastic, mr.t_total);
  }
  match_run_free(&mr);
  return rc ? 1 : 0;
}

typedef struct eval_args {
  const char *a, *b, *map, *gt, *gt_tgt, *kind;
  int base, json;
} eval_args;

static int load_gt(const eval_args *e, const sm_mesh *a, const sm_mesh *b, sm_gt **gt,
                   sm_error *err) {
  const char *k = e->kind ? e->kind : "dense";
  if (!strcmp(k, "identity")) return sm_gt_identity(a->nv, gt, err);
  if (!e->gt) return sm_error_set(err, SM_EINVAL, "--gt FILE is required for --gt-kind %s", k);
  if (!strcmp(k, "dense")) return sm_gt_load_dense(e->gt, e->base, a->nv, b->nv, gt, err);
  if (!strcmp(k, "inverse")) return sm_gt_load_inverse(e->gt, e->base, a->nv, b->nv, gt, err);
  if (!strcmp(k, "pairs")) return sm_gt_load_pairs(e->gt, e->base, a->nv, b->nv, gt, err);
  if (!strcmp(k, "vts")) {
    if (!e->gt_tgt) return sm_error_set(err, SM_EINVAL, "--gt-kind vts needs --gt-tgt");
    return sm_gt_load_vts(e->gt, e->gt_tgt, e->base, a->nv, b->nv, gt, err);
  }
  return sm_error_set(err, SM_EINVAL, "unknown --gt-kind %s", k);
}

static void print_metrics(const sm_metrics *mt, int json) {
  if (json) {
    printf("{\"mean_geo_err\":%.9g,\"median_geo_err\":%.9g,\"max_geo_err\":%.9g,"
           "\"frac_le_0.025\":%.9g,\"frac_le_0.05\":%.9g,\"frac_le_0.1\":%.9g,"
           "\"auc_0_0.1\":%.9g,\"bijectivity\":%.9g,\"coverage\":%.9g,\"chamfer\":%.9g,"
           "\"dirichlet\":%.9g}\n", mt->geo.mean, mt->geo.median, mt->geo.max,
           mt->geo.frac_le_0025, mt->geo.frac_le_005, mt->geo.frac_le_01, mt->geo.auc,
           mt->bijectivity, mt->coverage, mt->chamfer, mt->dirichlet);
    return;
  }
  printf("mean geodesic error  %.6f (median %.6f, max %.6f; Dijkstra on the target's edges, "
         "/ sqrt(target area))\n", mt->geo.mean, mt->geo.median, mt->geo.max);
  printf("fraction <= 0.025 / 0.05 / 0.1   %.4f / %.4f / %.4f   (AUC over [0, 0.1]: %.4f)\n",
         mt->geo.frac_le_0025, mt->geo.frac_le_005, mt->geo.frac_le_01, mt->geo.auc);
  printf("bijectivity %.4f  coverage %.4f  chamfer %.6f  dirichlet %.4f\n", mt->bijectivity,
         mt->coverage, mt->chamfer, mt->dirichlet);
}

static int cmd_eval(int argc, char **argv) {
  eval_args e = {0};
  for (int i = 0; i < argc; i++) {
    const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
    if (!strcmp(a, "--json")) e.json = 1;
    else if (a[0] != '-') {
      if (!e.a) e.a = a;
      else if (!e.b) e.b = a;
      else return usage(stderr);
    } else if (!v) return usage(stderr);
    else if (!strcmp(a, "--map")) e.map = argv[++i];
    else if (!strcmp(a, "--gt")) e.gt = argv[++i];
    else if (!strcmp(a, "--gt-tgt")) e.gt_tgt = argv[++i];
    else if (!strcmp(a, "--gt-kind")) e.kind = argv[++i];
    else if (!strcmp(a, "--gt-base")) e.base = atoi(argv[++i]);
    else return usage(stderr);
  }
  if (!e.a || !e.b || !e.map) return usage(stderr);
  sm_error err;
  sm_mesh *a = NULL, *b = NULL;
  sm_gt *gt = NULL;
  int32_t *map = NULL;
  sm_metrics mt;
  int rc = sm_mesh_read_file(e.a, NULL, &a, &err) || sm_mesh_read_file(e.b, NULL, &b, &err) ||
           sm_map_load(e.map, a->nv, b->nv, &map, &err) || load_gt(&e, a, b, &gt, &err) ||
           sm_metrics_compute(a, b, map, gt, 2, &mt, &err);
  if (rc) fail("eval", &err);
  else print_metrics(&mt, e.json);
  free(map);
  sm_gt_destroy(gt);
  sm_mesh_destroy(a);
  sm_mesh_destroy(b);
  return rc ? 1 : 0;
}

static int write_off(const sm_mesh *m, const char *path) {
  FILE *f = fopen(path, "w");
  if (!f) {
    perror(path);
    return 1;
  }
  fprintf(f, "OFF\n%d %d 0\n", m->nv, m->nf);
  for (int32_t v = 0; v < m->nv; v++)
    fprintf(f, "%.17g %.17g %.17g\n", m->V[3 * v], m->V[3 * v + 1], m->V[3 * v + 2]);
  for (int32_t t = 0; t < m->nf; t++)
    fprintf(f, "3 %d %d %d\n", m->F[3 * t], m->F[3 * t + 1], m->F[3 * t + 2]);
  if (fclose(f)) {
    perror(path);
    return 1;
  }
  return 0;
}

static int cmd_synth(int argc, char **argv) {
  const char *shape = NULL, *out = NULL;
  int subdiv = 4;
  unsigned seed = 1;
  double amp = 0.35, st[3] = {1, 1, 1};
  for (int i = 0; i < argc; i++) {
    if (!strcmp(argv[i], "-o") && i + 1 < argc) out = argv[++i];
    else if (!strcmp(argv[i], "--subdiv") && i + 1 < argc) subdiv = atoi(argv[++i]);
    else if (!strcmp(argv[i], "--seed") && i + 1 < argc) seed = (unsigned)atoi(argv[++i]);
    else if (!strcmp(argv[i], "--amp") && i + 1 < argc) amp = atof(argv[++i]);
    else if (!strcmp(argv[i], "--stretch") && i + 1 < argc) {
      if (sscanf(argv[++i], "%lf,%lf,%lf", &st[0], &st[1], &st[2]) != 3) return usage(stderr);
    } else if (argv[i][0] == '-' || shape) return usage(stderr);
    else shape = argv[i];
  }
  if (!shape || !out) return usage(stderr);
  sm_mesh *m = NULL;
  sm_error err;
  int rc;
  if (!strcmp(shape, "sphere")) rc = sm_synth_icosphere(subdiv, &m, &err);
  else if (!strcmp(shape, "torus"))
    rc = sm_synth_torus(8 << (subdiv / 2), 4 << (subdiv / 2), 1.0, 0.35, &m, &err);
  else if (!strcmp(shape, "blob")) rc = sm_synth_blob(subdiv, amp, seed, st, &m, &err);
  else return usage(stderr);
  if (rc) return fail(shape, &err);
  rc = write_off(m, out);
  if (!rc) fprintf(stderr, "wrote %s (%d vertices, %d faces)\n", out, m->nv, m->nf);
  sm_mesh_destroy(m);
  return rc;
}

int main(int argc, char **argv) {
  sm_alloc_keep_large(); /* before any thread; why: sm_alloc.h */
  /* One BLAS thread unless OPENBLAS_NUM_THREADS says otherwise: our BLAS calls are small
   * (ARPACK's dgemv over n x ncv, per-supernode solves) and OpenBLAS threading costs more
   * than it gains on them. Measured on homerA k=100, 2 cores, load ~4: elastic eigensolve
   * 3.3-4.8 s CPU (5.0-7.0 s wall) with the default threads vs 2.05-2.15 s CPU (3.1-3.5 s
   * wall) with one; LB 0.34 s CPU / 0.72 s wall (median) vs 0.25 s / 0.48 s. On an idle
   * machine (load < 0.5) two threads win instead: elastic 1.76 s wall / 3.4 s CPU vs
   * 2.44 s / 2.44 s; at load ~1 it is a draw. Shared machines are the common case here;
   * OPENBLAS_NUM_THREADS=2 opts back in. Set here, not in core/: process-wide state. */
  if (!getenv("OPENBLAS_NUM_THREADS")) openblas_set_num_threads(1);
  /* CHOLMOD's factorizations would open OpenMP teams of 4 threads each whatever the
   * above says; a local match prepares its two shapes on two threads at once, which then
   * put 8 threads on the cores (sm_eigs.h). */
  sm_eigs_openmp_off();
  if (argc < 2) return usage(stderr);
  const char *cmd = argv[1];
  if (!strcmp(cmd, "basis")) return cmd_basis(argc - 2, argv + 2);
  if (!strcmp(cmd, "info")) return cmd_info(argc - 2, argv + 2);
  if (!strcmp(cmd, "encode")) return cmd_encode(argc - 2, argv + 2);
  if (!strcmp(cmd, "synth")) return cmd_synth(argc - 2, argv + 2);
  if (!strcmp(cmd, "match")) return cmd_match(argc - 2, argv + 2);
  if (!strcmp(cmd, "distance")) return cmd_distance(argc - 2, argv + 2);
  if (!strcmp(cmd, "eval")) return cmd_eval(argc - 2, argv + 2);
  if (!strcmp(cmd, "render")) {
    int rc = smcli_cmd_render(argc - 2, argv + 2);
    return rc == 2 ? usage(stderr) : rc;
  }
  if (!strcmp(cmd, "put") || !strcmp(cmd, "query") || !strcmp(cmd, "batch") ||
      !strcmp(cmd, "stats") || !strcmp(cmd, "ping")) {
    int n = argc - 2;
    const char *addr;
    if (take_server(&n, argv + 2, &addr)) return usage(stderr);
    if (!addr) {
      fprintf(stderr, "shapematch %s: name the daemon with --server HOST:PORT or "
                      "SHAPEMATCH_SERVER\n", cmd);
      return 2;
    }
    if (!strcmp(cmd, "put")) return cmd_put(n, argv + 2, addr);
    if (!strcmp(cmd, "query")) return cmd_query(n, argv + 2, addr);
    if (!strcmp(cmd, "batch")) return cmd_batch(n, argv + 2, addr);
    return cmd_stats(n, argv + 2, addr, !strcmp(cmd, "ping"));
  }
  if (!strcmp(cmd, "version") || !strcmp(cmd, "--version")) {
    SM_VERSION_PRINT(stdout, "shapematch");
    return 0;
  }
  if (!strcmp(cmd, "help") || !strcmp(cmd, "--help") || !strcmp(cmd, "-h")) {
    usage(stdout);
    return 0;
  }
  fprintf(stderr, "shapematch: unknown command '%s'\n", cmd);
  return usage(stderr);
}
