/* Shape store and prepared-shape cache: see sm_srv_store.h for the DESIGN. */
#include "sm_srv_store.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "sm_basis.h"
#include "sm_meshio.h"
#include "sm_sha256.h"
#include "sm_srv.h"
#include "sm_srv_log.h"

#define NBUCKETS 16384u
#define PATHBUF (SM_SRV_PATH_MAX + 512) /* dir + subdir + file name */
#define BASIS_FORMAT 1 /* sm_basis_io's format version, part of the cache file name */
#define N_DESC 100     /* WKS energies (sm_shape_opts_default) */

enum { V_COMPUTING = 1, V_READY = 2 };

struct sm_prepared {
  sm_shape *shape;
  int refs; /* under st->mu */
  size_t bytes;
};

typedef struct entry entry;
typedef struct variant {
  entry *e;
  sm_store_key key;
  int state;
  sm_prepared *p; /* READY: the cache's reference */
  struct variant *next;               /* in e->vars */
  struct variant *lru_prev, *lru_next; /* READY only; head = most recent */
} variant;

/* What stat(2) said about a shape file when its content was last verified: any write to
 * the file changes its size, mtime or (rename over it) inode. */
typedef struct file_sig {
  uint64_t size, ino;
  int64_t mtime_ns;
} file_sig;

struct entry {
  uint8_t id[32];
  char hex[65];
  uint32_t nv, nf;
  uint64_t bytes;
  file_sig sig;
  int dropped;
  int pins; /* computations in progress for this entry */
  variant *vars;
  entry *hnext;
};

struct sm_store {
  pthread_mutex_t mu;
  pthread_cond_t cv;
  char dir[SM_SRV_PATH_MAX];
  sm_limits lim;
  sm_store_key def;
  uint32_t max_components;
  uint64_t budget;
  entry *buckets[NBUCKETS];
  variant *lru_head, *lru_tail;
  sm_store_stats s; /* counters; shapes/shapes_bytes/bases_cached/cache_bytes kept live */
};

static atomic_uint tmp_seq;

static void forget_corrupt_locked(sm_store *st, entry *e, const char *why);

/* ---------------------------------------------------------------- helpers */

static unsigned bucket_of(const uint8_t id[32]) {
  return ((unsigned)id[0] | (unsigned)id[1] << 8 | (unsigned)id[2] << 16) % NBUCKETS;
}

static entry *find(sm_store *st, const uint8_t id[32]) {
  for (entry *e = st->buckets[bucket_of(id)]; e; e = e->hnext)
    if (!memcmp(e->id, id, 32)) return e;
  return NULL;
}

static void unlink_entry(sm_store *st, entry *e) {
  entry **pp = &st->buckets[bucket_of(e->id)];
  while (*pp && *pp != e) pp = &(*pp)->hnext;
  if (*pp) *pp = e->hnext;
}

static int key_eq(const sm_store_key *a, const sm_store_key *b) {
  return a->k_lb == b->k_lb && a->k_el == b->k_el && !memcmp(&a->eta, &b->eta, sizeof a->eta);
}

static uint64_t dbits(double d) {
  uint64_t u;
  memcpy(&u, &d, sizeof u);
  return u;
}

static void shape_path(const sm_store *st, const char *hex, char *out, size_t n) {
  snprintf(out, n, "%s/shapes/%s.drc", st->dir, hex);
}

static int file_sig_of(const char *path, file_sig *g) {
  struct stat sb;
  if (stat(path, &sb)) return -1;
  g->size = (uint64_t)sb.st_size;
  g->ino = (uint64_t)sb.st_ino;
  g->mtime_ns = (int64_t)sb.st_mtim.tv_sec * 1000000000 + sb.st_mtim.tv_nsec;
  return 0;
}

/* 1 if e's file is still the one verified (cheap: one stat; the content itself is checked
 * by SHA-256 whenever it is read). */
static int entry_file_intact(const sm_store *st, const entry *e) {
  char p[PATHBUF];
  file_sig g;
  shape_path(st, e->hex, p, sizeof p);
  return file_sig_of(p, &g) == 0 && !memcmp(&g, &e->sig, sizeof g);
}

static void basis_path(const sm_store *st, const char *hex, int kind, int k, double eta,
                       char *out, size_t n) {
  snprintf(out, n, "%s/bases/%s.%s.k%d.eta%016llx.v%d.smb", st->dir, hex,
           kind == SM_BASIS_LB ? "lb" : "el", k, (unsigned long long)dbits(eta), BASIS_FORMAT);
}

static int mkdir_p(const char *path) {
  char buf[PATHBUF];
  snprintf(buf, sizeof buf, "%s", path);
  for (char *p = buf + 1; *p; p++)
    if (*p == '/') {
      *p = 0;
      if (mkdir(buf, 0700) && errno != EEXIST) return -1;
      *p = '/';
    }
  if (mkdir(buf, 0700) && errno != EEXIST) return -1;
  return 0;
}

static void fsync_dir_of(const char *path) {
  char d[PATHBUF];
  snprintf(d, sizeof d, "%s", path);
  char *slash = strrchr(d, '/');
  if (!slash) return;
  *slash = 0;
  int fd = open(d, O_RDONLY | O_DIRECTORY);
  if (fd >= 0) {
    fsync(fd);
    close(fd);
  }
}

/* temp + fsync + rename + directory fsync. */
static int write_atomic(const char *path, const uint8_t *buf, size_t len, sm_error *err) {
  char tmp[PATHBUF + 64];
  snprintf(tmp, sizeof tmp, "%s.tmp.%ld.%u", path, (long)getpid(),
           atomic_fetch_add(&tmp_seq, 1u));
  int fd = open(tmp, O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0600);
  if (fd < 0) return sm_error_set(err, SM_EIO, "%s: %s", tmp, strerror(errno));
  size_t off = 0;
  while (off < len) {
    ssize_t w = write(fd, buf + off, len - off);
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) {
      int e = errno;
      close(fd);
      unlink(tmp);
      return sm_error_set(err, SM_EIO, "%s: %s", tmp, strerror(e));
    }
    off += (size_t)w;
  }
  if (fsync(fd) || close(fd)) {
    int e = errno;
    unlink(tmp);
    return sm_error_set(err, SM_EIO, "%s: fsync: %s", tmp, strerror(e));
  }
  if (rename(tmp, path)) {
    int e = errno;
    unlink(tmp);
    return sm_error_set(err, SM_EIO, "%s: rename: %s", path, strerror(e));
  }
  fsync_dir_of(path);
  return SM_OK;
}

static size_t basis_bytes(const sm_basis *b) {
  if (!b) return 0;
  size_t n = (size_t)b->n, k = (size_t)b->k;
  return sizeof *b + 8 * (k + n * k + n + (b->gram_L ? k * k : 0));
}

static size_t shape_bytes(const sm_shape *s) {
  size_t nv = (size_t)s->mesh->nv, nf = (size_t)s->mesh->nf;
  return sizeof *s + nv * 24 + nf * 12 + nv * 4 + basis_bytes(s->lb) + basis_bytes(s->elastic) +
         nv * (size_t)s->n_desc * 8;
}

static void prepared_unref_locked(sm_prepared *p) {
  if (--p->refs == 0) {
    sm_shape_destroy(p->shape);
    free(p);
  }
}

static void lru_unlink(sm_store *st, variant *v) {
  if (v->lru_prev) v->lru_prev->lru_next = v->lru_next;
  else if (st->lru_head == v) st->lru_head = v->lru_next;
  if (v->lru_next) v->lru_next->lru_prev = v->lru_prev;
  else if (st->lru_tail == v) st->lru_tail = v->lru_prev;
  v->lru_prev = v->lru_next = NULL;
}

static void lru_push(sm_store *st, variant *v) {
  v->lru_prev = NULL;
  v->lru_next = st->lru_head;
  if (st->lru_head) st->lru_head->lru_prev = v;
  st->lru_head = v;
  if (!st->lru_tail) st->lru_tail = v;
}

static void var_unlink(entry *e, variant *v) {
  variant **pp = &e->vars;
  while (*pp && *pp != v) pp = &(*pp)->next;
  if (*pp) *pp = v->next;
}

/* Removes a READY variant from the cache (the prepared shape lives on while referenced). */
static void var_evict_locked(sm_store *st, variant *v) {
  lru_unlink(st, v);
  var_unlink(v->e, v);
  st->s.cache_bytes -= v->p->bytes;
  st->s.bases_cached -= (uint64_t)((v->p->shape->lb ? 1 : 0) + (v->p->shape->elastic ? 1 : 0));
  prepared_unref_locked(v->p);
  free(v);
}

static void maybe_free_entry(entry *e) {
  if (e->dropped && e->pins == 0 && !e->vars) free(e);
}

/* ---------------------------------------------------------------- open / scan */

static int load_shape_file(sm_store *st, const char *name) {
  size_t nl = strlen(name);
  if (nl != 68 || strcmp(name + 64, ".drc")) {
    char p[PATHBUF];
    snprintf(p, sizeof p, "%s/shapes/%s", st->dir, name);
    if (strstr(name, ".tmp.")) /* a crash between create and rename */
      unlink(p);
    else /* not ours to delete, but never silently ignored */
      sm_log("warn", "store: stray file in shapes/ ignored (not named <sha256>.drc)",
             " path=%s", p);
    return 0;
  }
  char path[PATHBUF];
  snprintf(path, sizeof path, "%s/shapes/%s", st->dir, name);
  uint8_t *buf = NULL;
  size_t len = 0;
  sm_error err;
  int rc = sm_read_file_bytes(path, (size_t)1 << 34, &buf, &len, &err);
  if (rc) {
    sm_log("warn", "store: unreadable shape file", " path=%s err=\"%s\"", path, err.msg);
    return 0;
  }
  uint8_t id[32];
  char hex[65];
  sm_sha256(buf, len, id);
  sm_hex(id, 32, hex);
  sm_mesh *m = NULL;
  if (memcmp(hex, name, 64)) {
    rc = SM_ECHECKSUM;
    snprintf(err.msg, sizeof err.msg, "SHA-256 %s does not match the file name", hex);
  } else {
    rc = sm_draco_decode(buf, len, &st->lim, &m, &err);
  }
  free(buf);
  if (rc) {
    sm_log("warn", "store: corrupt shape file deleted", " path=%s err=\"%s\"", path, err.msg);
    unlink(path);
    st->s.shapes_corrupt++;
    return 0;
  }
  entry *e = calloc(1, sizeof *e);
  if (!e) {
    sm_mesh_destroy(m);
    return -1;
  }
  memcpy(e->id, id, 32);
  memcpy(e->hex, hex, 65);
  e->nv = (uint32_t)m->nv;
  e->nf = (uint32_t)m->nf;
  e->bytes = len;
  sm_mesh_destroy(m);
  if (file_sig_of(path, &e->sig)) memset(&e->sig, 0, sizeof e->sig);
  unsigned b = bucket_of(id);
  e->hnext = st->buckets[b];
  st->buckets[b] = e;
  st->s.shapes++;
  st->s.shapes_bytes += len;
  return 0;
}

int sm_store_open(const char *dir, uint64_t cache_bytes, const sm_limits *lim,
                  const sm_store_key *default_key, sm_store **out, sm_error *err) {
  *out = NULL;
  sm_store *st = calloc(1, sizeof *st);
  if (!st) return sm_error_set(err, SM_ENOMEM, "store: out of memory");
  snprintf(st->dir, sizeof st->dir, "%s", dir);
  st->lim = *lim;
  st->def = *default_key;
  st->budget = cache_bytes;
  pthread_mutex_init(&st->mu, NULL);
  pthread_cond_init(&st->cv, NULL);
  char p[SM_SRV_PATH_MAX + 16];
  for (int i = 0; i < 2; i++) {
    snprintf(p, sizeof p, "%s/%s", dir, i ? "bases" : "shapes");
    if (mkdir_p(p)) {
      int e = errno;
      sm_store_close(st);
      return sm_error_set(err, SM_EIO, "%s: %s", p, strerror(e));
    }
  }
  snprintf(p, sizeof p, "%s/shapes", dir);
  DIR *d = opendir(p);
  if (!d) {
    int e = errno;
    sm_store_close(st);
    return sm_error_set(err, SM_EIO, "%s: %s", p, strerror(e));
  }
  struct dirent *de;
  while ((de = readdir(d)))
    if (de->d_name[0] != '.' && load_shape_file(st, de->d_name)) {
      closedir(d);
      sm_store_close(st);
      return sm_error_set(err, SM_ENOMEM, "store: out of memory while scanning");
    }
  closedir(d);
  /* Leftover temp files of interrupted basis writes. */
  snprintf(p, sizeof p, "%s/bases", dir);
  if ((d = opendir(p))) {
    while ((de = readdir(d)))
      if (strstr(de->d_name, ".tmp.")) {
        char f[PATHBUF];
        snprintf(f, sizeof f, "%s/%s", p, de->d_name);
        unlink(f);
      }
    closedir(d);
  }
  *out = st;
  return SM_OK;
}

void sm_store_close(sm_store *st) {
  if (!st) return;
  while (st->lru_head) var_evict_locked(st, st->lru_head);
  for (unsigned b = 0; b < NBUCKETS; b++)
    for (entry *e = st->buckets[b], *n; e; e = n) {
      n = e->hnext;
      for (variant *v = e->vars, *vn; v; v = vn) { /* COMPUTING leftovers: none after join */
        vn = v->next;
        free(v);
      }
      free(e);
    }
  pthread_mutex_destroy(&st->mu);
  pthread_cond_destroy(&st->cv);
  free(st);
}

/* ---------------------------------------------------------------- put / has / drop */

/* 1 if the stored file of hex holds exactly these bytes. */
static int stored_file_matches(const sm_store *st, const char *hex, const uint8_t *draco,
                               size_t len) {
  char path[PATHBUF];
  shape_path(st, hex, path, sizeof path);
  uint8_t *buf = NULL;
  size_t n = 0;
  sm_error e;
  if (sm_read_file_bytes(path, len + 1, &buf, &n, &e)) return 0;
  int ok = n == len && !memcmp(buf, draco, len);
  free(buf);
  return ok;
}

/* What the daemon can prepare, decided at PUT so that no stored shape fails later for
 * a reason its bytes already showed: every component carries its own rigid modes in the
 * elastic basis (hundreds of components made a preparation run for ten minutes), and
 * the eigensolvers need clearly more vertices than basis functions. */
static int check_preparable(const sm_store *st, const sm_mesh *c, const sm_clean_report *rep,
                            sm_error *err) {
  int k = st->def.k_lb > st->def.k_el ? st->def.k_lb : st->def.k_el;
  if (st->max_components && (uint32_t)rep->components > st->max_components)
    return sm_error_set(err, SM_STORE_ECOMPONENTS,
                        "the mesh has %d connected components after cleaning; this daemon "
                        "prepares shapes with at most %u (--max-components)",
                        rep->components, st->max_components);
  if (c->nv < 2 * k + 1)
    return sm_error_set(err, SM_EUNSUPPORTED,
                        "the mesh has %d vertices after cleaning; at least %d are needed for "
                        "the daemon's %d basis functions",
                        c->nv, 2 * k + 1, k);
  return SM_OK;
}

/* Re-PUT of a stored id: the bytes are verified, so they can repair a file that was
 * damaged or removed behind the daemon's back. */
static int put_existing(sm_store *st, const uint8_t id[32], const char *hex,
                        const uint8_t *draco, size_t len, int *existed, sm_error *err) {
  if (stored_file_matches(st, hex, draco, len)) return SM_OK;
  char path[PATHBUF];
  shape_path(st, hex, path, sizeof path);
  int rc = write_atomic(path, draco, len, err);
  if (rc) return rc;
  pthread_mutex_lock(&st->mu);
  entry *e = find(st, id);
  if (e && file_sig_of(path, &e->sig)) memset(&e->sig, 0, sizeof e->sig);
  st->s.shapes_healed++;
  pthread_mutex_unlock(&st->mu);
  sm_log("warn", "store: damaged shape file rewritten from a PUT", " id=%s", hex);
  *existed = 0; /* the bytes were written */
  return SM_OK;
}

int sm_store_put(sm_store *st, const uint8_t id[32], const uint8_t *draco, size_t len,
                 uint32_t *nv, uint32_t *nf, int *existed, sm_error *err) {
  *existed = 0;
  uint8_t got[32];
  char hex[65], path[PATHBUF];
  sm_sha256(draco, len, got);
  sm_hex(id, 32, hex);
  if (memcmp(got, id, 32)) {
    char b[65];
    sm_hex(got, 32, b);
    return sm_error_set(err, SM_STORE_EIDMISMATCH, "id %.16s... but SHA-256 of the bytes is %.16s...",
                        hex, b);
  }
  pthread_mutex_lock(&st->mu);
  entry *e = find(st, id);
  if (e) {
    *nv = e->nv;
    *nf = e->nf;
    *existed = 1;
  }
  pthread_mutex_unlock(&st->mu);
  if (*existed) return put_existing(st, id, hex, draco, len, existed, err);

  sm_mesh *m = NULL, *c = NULL;
  sm_clean_report rep;
  int rc = sm_draco_decode(draco, len, &st->lim, &m, err);
  if (rc) return rc;
  rc = sm_mesh_clean(m, &st->lim, &c, &rep, err);
  if (!rc) rc = check_preparable(st, c, &rep, err);
  uint32_t v = (uint32_t)m->nv, f = (uint32_t)m->nf;
  sm_mesh_destroy(m);
  sm_mesh_destroy(c);
  if (rc) return rc;

  shape_path(st, hex, path, sizeof path);
  rc = write_atomic(path, draco, len, err);
  if (rc) return rc;

  pthread_mutex_lock(&st->mu);
  e = find(st, id);
  if (e) {
    *existed = 1;
  } else if ((e = calloc(1, sizeof *e))) {
    memcpy(e->id, id, 32);
    memcpy(e->hex, hex, 65);
    e->nv = v;
    e->nf = f;
    e->bytes = len;
    if (file_sig_of(path, &e->sig)) memset(&e->sig, 0, sizeof e->sig);
    unsigned b = bucket_of(id);
    e->hnext = st->buckets[b];
    st->buckets[b] = e;
    st->s.shapes++;
    st->s.shapes_bytes += len;
  } else {
    rc = sm_error_set(err, SM_ENOMEM, "store: out of memory");
  }
  if (e) {
    *nv = e->nv;
    *nf = e->nf;
  }
  pthread_mutex_unlock(&st->mu);
  return rc;
}

int sm_store_has(sm_store *st, const uint8_t id[32], uint32_t *nv, uint32_t *nf,
                 int *prepared) {
  *nv = *nf = 0;
  *prepared = 0;
  char hex[65];
  pthread_mutex_lock(&st->mu);
  entry *e = find(st, id);
  if (e && !entry_file_intact(st, e)) {
    forget_corrupt_locked(st, e, "HAS");
    e = NULL;
  }
  if (e) {
    *nv = e->nv;
    *nf = e->nf;
    memcpy(hex, e->hex, 65);
    for (variant *v = e->vars; v; v = v->next)
      if (v->state == V_READY && key_eq(&v->key, &st->def)) *prepared = 1;
  }
  pthread_mutex_unlock(&st->mu);
  if (e && !*prepared) { /* bases on disk count as prepared */
    char p[PATHBUF];
    struct stat sb;
    basis_path(st, hex, SM_BASIS_LB, st->def.k_lb, 0.0, p, sizeof p);
    int ok = stat(p, &sb) == 0;
    if (ok && st->def.k_el > 0) {
      basis_path(st, hex, SM_BASIS_ELASTIC, st->def.k_el, st->def.eta, p, sizeof p);
      ok = stat(p, &sb) == 0;
    }
    *prepared = ok;
  }
  return e != NULL;
}

static void unlink_bases(const sm_store *st, const char *hex) {
  char d[SM_SRV_PATH_MAX + 16];
  snprintf(d, sizeof d, "%s/bases", st->dir);
  DIR *dd = opendir(d);
  if (!dd) return;
  struct dirent *de;
  while ((de = readdir(dd)))
    if (!strncmp(de->d_name, hex, 64) && de->d_name[64] == '.') {
      char f[PATHBUF];
      snprintf(f, sizeof f, "%s/%s", d, de->d_name);
      unlink(f);
    }
  closedir(dd);
}

/* Removes e from the index, the cache and the disk (DROP, or a file found corrupt). */
static void forget_locked(sm_store *st, entry *e) {
  unlink_entry(st, e);
  e->dropped = 1;
  st->s.shapes--;
  st->s.shapes_bytes -= e->bytes;
  for (variant *v = e->vars, *n; v; v = n) {
    n = v->next;
    if (v->state == V_READY) var_evict_locked(st, v);
  }
  char hex[65], p[PATHBUF];
  memcpy(hex, e->hex, 65);
  maybe_free_entry(e);
  /* Unlinks under the lock so that a PUT of the same id racing with this DROP cannot have
   * its fresh file deleted afterwards. */
  shape_path(st, hex, p, sizeof p);
  unlink(p);
  unlink_bases(st, hex);
}

int sm_store_drop(sm_store *st, const uint8_t id[32]) {
  pthread_mutex_lock(&st->mu);
  entry *e = find(st, id);
  if (!e) {
    pthread_mutex_unlock(&st->mu);
    return SM_STORE_ENOTFOUND;
  }
  forget_locked(st, e);
  pthread_mutex_unlock(&st->mu);
  return SM_OK;
}

/* A stored file that changed or vanished behind the daemon's back: it can no longer be
 * trusted, so the shape is forgotten (HAS says not stored, QUERY skips it) until a PUT of
 * the right bytes stores it again. */
static void forget_corrupt_locked(sm_store *st, entry *e, const char *why) {
  sm_log("warn", "store: shape file changed on disk, shape forgotten", " id=%s why=%s",
         e->hex, why);
  st->s.shapes_corrupt++;
  forget_locked(st, e);
}

/* ---------------------------------------------------------------- prepare */

static uint64_t us_since(uint64_t t0) { return (sm_srv_now_ns() - t0) / 1000; }

/* Loads a verified basis from disk or computes and saves it. */
static int get_basis(sm_store *st, const char *hex, const sm_mesh *m, int kind, int k,
                     double eta, int (*cancel)(void *), void *ud, sm_basis **out,
                     sm_store_prep_info *info, uint64_t *t_us, sm_error *err) {
  char path[PATHBUF];
  basis_path(st, hex, kind, k, kind == SM_BASIS_LB ? 0.0 : eta, path, sizeof path);
  uint64_t t0 = sm_srv_now_ns();
  struct stat sb;
  if (stat(path, &sb) == 0) {
    sm_basis *b = NULL;
    sm_error lerr;
    int rc = sm_basis_load(path, &b, &lerr);
    if (!rc && (b->kind != kind || b->k != k || b->n != m->nv ||
                b->mesh_hash != sm_mesh_hash(m) || (kind == SM_BASIS_ELASTIC && b->eta != eta))) {
      rc = sm_error_set(&lerr, SM_EFORMAT, "basis does not belong to this shape/key");
      sm_basis_destroy(b);
      b = NULL;
    }
    if (!rc) {
      *out = b;
      info->bases_loaded++;
      *t_us = us_since(t0);
      pthread_mutex_lock(&st->mu);
      st->s.bases_loaded++;
      pthread_mutex_unlock(&st->mu);
      return SM_OK;
    }
    sm_log("warn", "store: corrupt basis file deleted, recomputing", " path=%s err=\"%s\"",
           path, lerr.msg);
    unlink(path);
    pthread_mutex_lock(&st->mu);
    st->s.bases_corrupt++;
    pthread_mutex_unlock(&st->mu);
  }
  sm_basis_opts bo;
  sm_basis_opts_default(&bo, kind, k);
  if (kind == SM_BASIS_ELASTIC) bo.eta = eta;
  bo.cancel = cancel;
  bo.cancel_ud = ud;
  int rc = sm_basis_compute(m, &bo, out, err);
  *t_us = us_since(t0);
  if (rc) return rc;
  info->bases_computed++;
  pthread_mutex_lock(&st->mu);
  st->s.bases_computed++;
  pthread_mutex_unlock(&st->mu);
  sm_error serr;
  if (sm_basis_save(*out, path, &serr))
    sm_log("warn", "store: cannot save basis", " path=%s err=\"%s\"", path, serr.msg);
  return SM_OK;
}

static int compute_variant(sm_store *st, const char *hex, const sm_store_key *key,
                           int (*cancel)(void *), void *ud, sm_prepared **out,
                           sm_store_prep_info *info, sm_error *err) {
  char path[PATHBUF];
  shape_path(st, hex, path, sizeof path);
  uint8_t *buf = NULL;
  size_t len = 0;
  uint64_t t0 = sm_srv_now_ns();
  int rc = sm_read_file_bytes(path, (size_t)1 << 34, &buf, &len, err);
  if (rc) return SM_STORE_ECORRUPT;
  uint8_t id[32];
  char h2[65];
  sm_sha256(buf, len, id);
  sm_hex(id, 32, h2);
  if (strcmp(h2, hex)) {
    free(buf);
    return sm_error_set(err, SM_STORE_ECORRUPT, "%s: content does not match its id", path);
  }
  sm_mesh *raw = NULL, *m = NULL;
  rc = sm_draco_decode(buf, len, &st->lim, &raw, err);
  free(buf);
  if (!rc) rc = sm_mesh_clean(raw, &st->lim, &m, NULL, err);
  sm_mesh_destroy(raw);
  if (!rc) rc = sm_mesh_normalize(m, err);
  info->t_clean_us = us_since(t0);
  if (!rc && (key->k_lb < 2 || key->k_lb >= m->nv))
    rc = sm_error_set(err, SM_EINVAL, "k_lb = %d must be in [2, %d) for this mesh", key->k_lb,
                      m->nv);
  sm_basis *lb = NULL, *el = NULL;
  if (!rc)
    rc = get_basis(st, hex, m, SM_BASIS_LB, key->k_lb, 0.0, cancel, ud, &lb, info,
                   &info->t_lb_us, err);
  if (!rc && key->k_el > 0)
    rc = get_basis(st, hex, m, SM_BASIS_ELASTIC, key->k_el, key->eta, cancel, ud, &el, info,
                   &info->t_elastic_us, err);
  if (rc) {
    sm_mesh_destroy(m);
    sm_basis_destroy(lb);
    sm_basis_destroy(el);
    return rc;
  }
  sm_shape *s = NULL;
  uint64_t t1 = sm_srv_now_ns();
  rc = sm_shape_assemble(m, lb, el, N_DESC, &s, err); /* takes m, lb, el */
  info->t_desc_us = us_since(t1);
  if (rc) return rc;
  sm_prepared *p = calloc(1, sizeof *p);
  if (!p) {
    sm_shape_destroy(s);
    return sm_error_set(err, SM_ENOMEM, "store: out of memory");
  }
  p->shape = s;
  p->bytes = shape_bytes(s);
  *out = p;
  return SM_OK;
}

static variant *find_var(entry *e, const sm_store_key *key) {
  for (variant *v = e->vars; v; v = v->next)
    if (key_eq(&v->key, key)) return v;
  return NULL;
}

static void abstime_in_ms(struct timespec *ts, int ms) {
  clock_gettime(CLOCK_REALTIME, ts);
  ts->tv_nsec += (long)ms * 1000000L;
  ts->tv_sec += ts->tv_nsec / 1000000000L;
  ts->tv_nsec %= 1000000000L;
}

int sm_store_acquire(sm_store *st, const uint8_t id[32], const sm_store_key *key,
                     int (*cancel)(void *), void *ud, sm_prepared **out,
                     sm_store_prep_info *info, sm_error *err) {
  *out = NULL;
  memset(info, 0, sizeof *info);
  pthread_mutex_lock(&st->mu);
  for (;;) {
    entry *e = find(st, id);
    if (e && !e->pins && !entry_file_intact(st, e)) {
      forget_corrupt_locked(st, e, "acquire");
      pthread_mutex_unlock(&st->mu);
      return sm_error_set(err, SM_STORE_ENOTFOUND,
                          "the stored file was damaged on disk and has been removed; PUT the "
                          "shape again");
    }
    if (!e) {
      pthread_mutex_unlock(&st->mu);
      return sm_error_set(err, SM_STORE_ENOTFOUND, "shape not stored");
    }
    variant *v = find_var(e, key);
    if (v && v->state == V_READY) {
      v->p->refs++;
      lru_unlink(st, v);
      lru_push(st, v);
      st->s.cache_hits++;
      *out = v->p;
      info->cached = !info->waited;
      pthread_mutex_unlock(&st->mu);
      return SM_OK;
    }
    if (v) { /* COMPUTING elsewhere: single-flight wait */
      if (!info->waited) st->s.singleflight_waits++;
      info->waited = 1;
      struct timespec ts;
      abstime_in_ms(&ts, 100);
      pthread_cond_timedwait(&st->cv, &st->mu, &ts);
      if (cancel && cancel(ud)) {
        pthread_mutex_unlock(&st->mu);
        return sm_error_set(err, SM_ECANCELED, "cancelled while waiting for a preparation");
      }
      continue;
    }
    v = calloc(1, sizeof *v);
    if (!v) {
      pthread_mutex_unlock(&st->mu);
      return sm_error_set(err, SM_ENOMEM, "store: out of memory");
    }
    v->e = e;
    v->key = *key;
    v->state = V_COMPUTING;
    v->next = e->vars;
    e->vars = v;
    e->pins++;
    st->s.cache_misses++;
    st->s.prepares++;
    char hex[65];
    memcpy(hex, e->hex, 65);
    pthread_mutex_unlock(&st->mu);

    sm_prepared *p = NULL;
    int w = info->waited;
    int rc = compute_variant(st, hex, key, cancel, ud, &p, info, err);
    info->waited = w;

    pthread_mutex_lock(&st->mu);
    e->pins--;
    var_unlink(e, v);
    if (rc == SM_STORE_ECORRUPT) {
      free(v);
      if (!e->dropped) forget_corrupt_locked(st, e, "content");
      sm_error_set(err, SM_STORE_ENOTFOUND,
                   "the stored file was damaged on disk and has been removed; PUT the shape "
                   "again");
      rc = SM_STORE_ENOTFOUND;
    } else if (rc) {
      free(v);
    } else if (e->dropped) {
      free(v);
      p->refs = 1; /* the caller's only */
      *out = p;
      unlink_bases(st, hex); /* what this computation may have written */
    } else {
      v->state = V_READY;
      v->p = p;
      p->refs = 2; /* cache + caller */
      v->next = e->vars;
      e->vars = v;
      lru_push(st, v);
      st->s.cache_bytes += p->bytes;
      st->s.bases_cached += (uint64_t)((p->shape->lb ? 1 : 0) + (p->shape->elastic ? 1 : 0));
      *out = p;
      while (st->s.cache_bytes > st->budget && st->lru_tail && st->lru_tail != v) {
        st->s.evictions++;
        var_evict_locked(st, st->lru_tail);
      }
    }
    pthread_cond_broadcast(&st->cv);
    maybe_free_entry(e);
    pthread_mutex_unlock(&st->mu);
    return rc;
  }
}

void sm_store_release(sm_store *st, sm_prepared *p) {
  if (!p) return;
  pthread_mutex_lock(&st->mu);
  prepared_unref_locked(p);
  pthread_mutex_unlock(&st->mu);
}

const sm_shape *sm_prepared_shape(const sm_prepared *p) { return p->shape; }

int sm_store_list(sm_store *st, uint8_t **ids, size_t *n) {
  pthread_mutex_lock(&st->mu);
  size_t cnt = st->s.shapes, i = 0;
  uint8_t *out = malloc(cnt ? cnt * 32 : 1);
  if (out)
    for (unsigned b = 0; b < NBUCKETS; b++)
      for (entry *e = st->buckets[b]; e && i < cnt; e = e->hnext) memcpy(out + 32 * i++, e->id, 32);
  pthread_mutex_unlock(&st->mu);
  if (!out) return SM_ENOMEM;
  *ids = out;
  *n = i;
  return SM_OK;
}

void sm_store_get_stats(sm_store *st, sm_store_stats *out) {
  pthread_mutex_lock(&st->mu);
  *out = st->s;
  pthread_mutex_unlock(&st->mu);
}

void sm_store_set_max_components(sm_store *st, uint32_t max_components) {
  pthread_mutex_lock(&st->mu);
  st->max_components = max_components;
  pthread_mutex_unlock(&st->mu);
}
