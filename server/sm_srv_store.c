#define _GNU_SOURCE /* F_OFD_SETLK */
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
#define LOCK_SPACE ((uint64_t)1 << 40) /* bytes of store.lock that names hash onto */
#define RECHECKS 4 /* a file that keeps changing under a lookup is taken as it is then */

/* FAILED: a background preparation's error, kept for the next acquire of its key. */
enum { V_COMPUTING = 1, V_READY = 2, V_FAILED = 3 };

struct sm_prepared {
  sm_shape *shape;          /* full-resolution key */
  sm_multires_shape *mr;    /* coarse-level key */
  int refs; /* under st->mu */
  size_t bytes;
};

typedef struct entry entry;
typedef struct variant {
  entry *e;
  sm_store_key key;
  int state;
  sm_prepared *p; /* READY: the cache's reference */
  sm_error failure; /* FAILED */
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
  char lockpath[SM_SRV_PATH_MAX + 16]; /* <dir>/store.lock */
  int64_t shapes_mtime_ns; /* shapes/ as of the last sync_dir (0: sync next time) */
  sm_limits lim;
  sm_store_key def;
  uint32_t max_components;
  uint64_t budget;
  uint64_t computing; /* preparations running now (under mu): prepares_concurrent_max */
  entry *buckets[NBUCKETS];
  variant *lru_head, *lru_tail;
  sm_store_stats s; /* counters; shapes/shapes_bytes/bases_cached/cache_bytes kept live */
};

static void forget_locked(sm_store *st, entry *e, int files);

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
  if (a->nspec != b->nspec || a->coarse_nv != b->coarse_nv) return 0;
  if (a->coarse_nv && memcmp(&a->max_aspect, &b->max_aspect, sizeof a->max_aspect)) return 0;
  for (int i = 0; i < a->nspec; i++)
    if (!sm_basis_spec_eq(&a->spec[i], &b->spec[i])) return 0;
  return 1;
}

sm_store_key sm_store_key_make(int k_lb, int k_el, double eta) {
  sm_store_key k;
  memset(&k, 0, sizeof k);
  k.nspec = sm_prep_default_specs(k.spec, k_lb, k_el, eta);
  return k;
}

sm_store_key sm_store_key_multires(const sm_store_key *full, int32_t coarse_nv) {
  sm_store_key k = *full;
  sm_multires_opts mo;
  sm_multires_opts_default(&mo);
  k.coarse_nv = coarse_nv;
  k.max_aspect = mo.max_aspect;
  return k;
}

int sm_store_key_k(const sm_store_key *key, int kind) {
  for (int i = 0; i < key->nspec; i++)
    if (key->spec[i].kind == kind) return key->spec[i].k;
  return 0;
}

uint64_t sm_store_info_basis_us(const sm_store_prep_info *info, const sm_store_key *key,
                                int kind) {
  for (int i = 0; i < key->nspec; i++)
    if (key->spec[i].kind == kind) return info->t_basis_us[i];
  return 0;
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

/* level: "" at full resolution, else "mr<nv>.a<bits>.d<version>." (level_tag) */
static void basis_path(const sm_store *st, const char *hex, const char *level,
                       const sm_basis_spec *spec, char *out, size_t n) {
  char name[128];
  sm_basis_spec_name(spec, name, sizeof name);
  snprintf(out, n, "%s/bases/%s.%s%s.v%u.smb", st->dir, hex, level, name, SM_BASIS_FORMAT_VERSION);
}

static void level_tag(const sm_store_key *key, char *out, size_t n) {
  uint64_t bits;
  memcpy(&bits, &key->max_aspect, sizeof bits);
  /* The decimation's version too: two daemon versions sharing a store would otherwise
   * each take the other's coarse bases for corrupt and delete them. */
  if (key->coarse_nv)
    snprintf(out, n, "mr%d.a%016llx.d%d.", key->coarse_nv, (unsigned long long)bits,
             SM_MULTIRES_DECIMATION);
  else snprintf(out, n, "%s", "");
}

static void meta_path(const sm_store *st, const char *hex, char *out, size_t n) {
  snprintf(out, n, "%s/meta/%s.counts", st->dir, hex);
}

/* The counts of hex's decoded mesh from meta/ (0), or -1 when absent or not readable as
 * written by write_meta (then the caller decodes the shape and writes them). */
static int read_meta(const sm_store *st, const char *hex, uint32_t *nv, uint32_t *nf) {
  char p[PATHBUF], id[65];
  meta_path(st, hex, p, sizeof p);
  FILE *f = fopen(p, "re");
  if (!f) return -1;
  unsigned long a = 0, b = 0;
  int ok = fscanf(f, "%64s %lu %lu", id, &a, &b) == 3 && !strcmp(id, hex) && a > 0 &&
           a <= UINT32_MAX && b > 0 && b <= UINT32_MAX;
  fclose(f);
  if (!ok) return -1;
  *nv = (uint32_t)a;
  *nf = (uint32_t)b;
  return 0;
}

static int lock_name(const sm_store *st, const char *name, int try, int (*cancel)(void *),
                     void *ud);
static void unlock_name(int fd);

/* Under the name's lock, as every write (remove_stale_temp spares a live writer's temp
 * file). A lost counts file only costs a decode at the next start, so failures are logged. */
static void write_meta(const sm_store *st, const char *hex, uint32_t nv, uint32_t nf) {
  char p[PATHBUF], line[128];
  meta_path(st, hex, p, sizeof p);
  int len = snprintf(line, sizeof line, "%s %u %u\n", hex, nv, nf);
  sm_error err;
  int fd = lock_name(st, strrchr(p, '/') + 1, 0, NULL, NULL);
  if (sm_file_write_atomic(p, (const uint8_t *)line, (size_t)len, &err))
    sm_log("warn", "store: cannot write the counts file", " path=%s err=\"%s\"", p, err.msg);
  unlock_name(fd);
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

/* ---------------------------------------------------------------- cross-process locks */

/* Several daemons may share one data directory (docs/DEPLOY.md). Their mutexes say
 * nothing to each other, so the steps where two processes could undo or repeat each
 * other's work hold a lock on one byte of <dir>/store.lock chosen by the name of the file
 * concerned: writing a shape file, deleting one found damaged, computing a basis, and
 * deleting a leftover temp file. Open-file-description locks (F_OFD_SETLK) because they
 * belong to the open file, so two threads of one daemon exclude each other as two
 * daemons do, and the kernel releases them when the holder dies, SIGKILL included (a
 * lock file that outlives a crash would wedge the store). Two names hashing onto one byte
 * only wait for each other. */
static uint64_t name_hash(const char *s) {
  uint64_t h = 1469598103934665603ull; /* FNV-1a */
  for (; *s; s++) h = (h ^ (unsigned char)*s) * 1099511628211ull;
  return h;
}

static void sleep_ms(int ms) {
  struct timespec ts = {ms / 1000, (long)(ms % 1000) * 1000000L};
  while (nanosleep(&ts, &ts) && errno == EINTR) {
  }
}

/* Locks name's byte; returns a descriptor for unlock_name, or -1 with errno. try: never
 * wait (EAGAIN when held). cancel: poll it every 20 ms while another holder has the
 * byte (ECANCELED when it says so); NULL waits in the kernel. */
static int lock_name(const sm_store *st, const char *name, int try, int (*cancel)(void *),
                     void *ud) {
  int fd = open(st->lockpath, O_RDWR | O_CREAT | O_CLOEXEC, 0600);
  if (fd < 0) return -1;
  struct flock fl;
  memset(&fl, 0, sizeof fl);
  fl.l_type = F_WRLCK;
  fl.l_whence = SEEK_SET;
  fl.l_start = (off_t)(name_hash(name) % LOCK_SPACE);
  fl.l_len = 1;
  int block = !try && !cancel;
  for (;;) {
    if (fcntl(fd, block ? F_OFD_SETLKW : F_OFD_SETLK, &fl) == 0) return fd;
    int e = errno;
    if (e != EINTR) {
      if (try || (e != EAGAIN && e != EACCES)) {
        close(fd);
        errno = try && e == EACCES ? EAGAIN : e;
        return -1;
      }
      if (cancel(ud)) {
        close(fd);
        errno = ECANCELED;
        return -1;
      }
      sleep_ms(20);
    }
  }
}

static void unlock_name(int fd) {
  if (fd >= 0) close(fd); /* closing the description releases its lock */
}

/* Deletes a temp file left by an interrupted write in subdir, unless its writer is alive:
 * writers hold the lock of the final name from creating the temp file to the rename. */
static void remove_stale_temp(const sm_store *st, const char *subdir, const char *name) {
  const char *t = strstr(name, ".tmp.");
  char final[300], p[PATHBUF];
  snprintf(final, sizeof final, "%.*s", (int)(t - name), name);
  int fd = lock_name(st, final, 1, NULL, NULL);
  if (fd < 0) return;
  snprintf(p, sizeof p, "%s/%s/%s", st->dir, subdir, name);
  unlink(p);
  unlock_name(fd);
}

static int prepared_nbases(const sm_prepared *p) {
  return sm_shape_nbases(p->shape ? p->shape : p->mr->coarse);
}

/* Approximate bytes of a multi-resolution shape: its coarse shape, and per fine vertex the
 * mesh (3 doubles, index maps), the mass and the location (3 ints, 3 weights, owner). */
static size_t multires_bytes(const sm_multires_shape *mr) {
  size_t per_v = 3 * sizeof(double) + 2 * sizeof(int32_t) + sizeof(double) +
                 3 * sizeof(int32_t) + 3 * sizeof(double) + sizeof(int32_t);
  return sm_shape_bytes(mr->coarse) + (size_t)mr->mesh->nv * per_v +
         (size_t)mr->mesh->nf * 3 * sizeof(int32_t);
}

static void prepared_unref_locked(sm_prepared *p) {
  if (--p->refs == 0) {
    sm_shape_destroy(p->shape);
    sm_multires_shape_destroy(p->mr);
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
  st->s.bases_cached -= (uint64_t)prepared_nbases(v->p);
  prepared_unref_locked(v->p);
  free(v);
}

static void maybe_free_entry(entry *e) {
  if (e->dropped && e->pins == 0 && !e->vars) free(e);
}

/* ---------------------------------------------------------------- verify / index */

enum { VF_OK, VF_GONE, VF_BAD, VF_UNREADABLE };

typedef struct vfile {
  uint32_t nv, nf;
  uint64_t bytes;
  file_sig sig; /* taken before reading: a later change is seen by the next check */
  char why[256];
} vfile;

/* Checks shapes/<hex>.drc: its SHA-256 must be its name and, with decode, it must decode
 * within the limits (counts filled). VF_GONE: no such file. */
static int verify_file(const sm_store *st, const char *hex, int decode, vfile *out) {
  char path[PATHBUF];
  shape_path(st, hex, path, sizeof path);
  memset(out, 0, sizeof *out);
  if (file_sig_of(path, &out->sig)) {
    snprintf(out->why, sizeof out->why, "%s", strerror(errno));
    return errno == ENOENT ? VF_GONE : VF_UNREADABLE;
  }
  uint8_t *buf = NULL;
  size_t len = 0;
  sm_error err;
  if (sm_read_file_bytes(path, (size_t)1 << 34, &buf, &len, &err)) {
    struct stat sb;
    snprintf(out->why, sizeof out->why, "%s", err.msg);
    return stat(path, &sb) && errno == ENOENT ? VF_GONE : VF_UNREADABLE;
  }
  uint8_t id[32];
  char got[65];
  sm_sha256(buf, len, id);
  sm_hex(id, 32, got);
  int r = VF_OK;
  if (memcmp(got, hex, 64)) {
    r = VF_BAD;
    snprintf(out->why, sizeof out->why, "SHA-256 %s does not match the file name", got);
  } else if (decode) {
    sm_mesh *m = NULL;
    if (sm_draco_decode(buf, len, &st->lim, &m, &err)) {
      r = VF_BAD;
      snprintf(out->why, sizeof out->why, "%s", err.msg);
    } else {
      out->nv = (uint32_t)m->nv;
      out->nf = (uint32_t)m->nf;
      sm_mesh_destroy(m);
    }
  }
  out->bytes = len;
  free(buf);
  return r;
}

/* A file that failed verify_file is deleted only if it still fails under its lock:
 * another daemon may have just renamed good bytes over it (a PUT that heals it). Returns
 * the second verdict; VF_UNREADABLE (and the file left alone) when it cannot lock. */
static int delete_if_bad(const sm_store *st, const char *hex, int decode, vfile *vf) {
  char name[80], path[PATHBUF];
  snprintf(name, sizeof name, "%s.drc", hex);
  int fd = lock_name(st, name, 0, NULL, NULL);
  if (fd < 0) {
    snprintf(vf->why, sizeof vf->why, "cannot lock store.lock: %s", strerror(errno));
    return VF_UNREADABLE;
  }
  int r = verify_file(st, hex, decode, vf);
  if (r == VF_BAD) {
    shape_path(st, hex, path, sizeof path);
    unlink(path);
  }
  unlock_name(fd);
  return r;
}

/* Indexes a verified file unless it already is. Under st->mu. */
static entry *index_insert_locked(sm_store *st, const uint8_t id[32], const char *hex,
                                  const vfile *vf) {
  entry *e = find(st, id);
  if (e) return e;
  if (!(e = calloc(1, sizeof *e))) return NULL;
  memcpy(e->id, id, 32);
  memcpy(e->hex, hex, 65);
  e->nv = vf->nv;
  e->nf = vf->nf;
  e->bytes = vf->bytes;
  e->sig = vf->sig;
  unsigned b = bucket_of(id);
  e->hnext = st->buckets[b];
  st->buckets[b] = e;
  st->s.shapes++;
  st->s.shapes_bytes += vf->bytes;
  return e;
}

/* Verifies and indexes shapes/<hex>.drc (startup scan, or a shape that another daemon
 * sharing the data directory stored: this daemon's index only knows what it scanned and
 * what it stored itself). A damaged file is deleted (counted shapes_corrupt). Without
 * st->mu. Returns 1 if the shape is now indexed, 0 if not, -1 out of memory. */
static int adopt(sm_store *st, const uint8_t id[32], const char *hex) {
  vfile vf;
  uint32_t nv, nf;
  int counted = read_meta(st, hex, &nv, &nf) == 0;
  int r = verify_file(st, hex, !counted, &vf);
  if (r == VF_BAD) r = delete_if_bad(st, hex, !counted, &vf);
  if (r == VF_OK && counted) {
    vf.nv = nv;
    vf.nf = nf;
  } else if (r == VF_OK) {
    write_meta(st, hex, vf.nv, vf.nf);
  }
  if (r == VF_BAD) {
    sm_log("warn", "store: corrupt shape file deleted", " id=%s err=\"%s\"", hex, vf.why);
  } else if (r == VF_UNREADABLE) {
    sm_log("warn", "store: unreadable shape file", " id=%s err=\"%s\"", hex, vf.why);
  }
  pthread_mutex_lock(&st->mu);
  int rc = 0;
  if (r == VF_BAD) st->s.shapes_corrupt++;
  if (r == VF_OK) rc = index_insert_locked(st, id, hex, &vf) ? 1 : -1;
  pthread_mutex_unlock(&st->mu);
  return rc;
}

static int id_of_name(const char *name, uint8_t id[32]) {
  if (strlen(name) != 68 || strcmp(name + 64, ".drc")) return -1;
  for (int i = 0; i < 64; i++) {
    char c = name[i];
    int v = c >= '0' && c <= '9' ? c - '0' : c >= 'a' && c <= 'f' ? c - 'a' + 10 : -1;
    if (v < 0) return -1;
    if (i % 2) id[i / 2] |= (uint8_t)v;
    else id[i / 2] = (uint8_t)(v << 4);
  }
  return 0;
}

static int load_shape_file(sm_store *st, const char *name) {
  uint8_t id[32];
  if (strstr(name, ".tmp.")) { /* a crash between create and rename */
    remove_stale_temp(st, "shapes", name);
    return 0;
  }
  if (id_of_name(name, id)) { /* not ours to delete, but never silently ignored */
    char p[PATHBUF];
    snprintf(p, sizeof p, "%s/shapes/%s", st->dir, name);
    sm_log("warn", "store: stray file in shapes/ ignored (not named <sha256>.drc)",
           " path=%s", p);
    return 0;
  }
  char hex[65];
  snprintf(hex, sizeof hex, "%.64s", name);
  return adopt(st, id, hex) < 0 ? -1 : 0;
}

/* ---------------------------------------------------------------- open / scan */

int sm_store_open(const char *dir, uint64_t cache_bytes, const sm_limits *lim,
                  const sm_store_key *default_key, sm_store **out, sm_error *err) {
  *out = NULL;
  sm_store *st = calloc(1, sizeof *st);
  if (!st) return sm_error_set(err, SM_ENOMEM, "store: out of memory");
  snprintf(st->dir, sizeof st->dir, "%s", dir);
  snprintf(st->lockpath, sizeof st->lockpath, "%s/store.lock", dir);
  st->lim = *lim;
  st->def = *default_key;
  st->budget = cache_bytes;
  pthread_mutex_init(&st->mu, NULL);
  pthread_cond_init(&st->cv, NULL);
  char p[SM_SRV_PATH_MAX + 16];
  static const char *const subdirs[] = {"shapes", "bases", "meta"};
  for (int i = 0; i < 3; i++) {
    snprintf(p, sizeof p, "%s/%s", dir, subdirs[i]);
    if (mkdir_p(p)) {
      int e = errno;
      sm_store_close(st);
      return sm_error_set(err, SM_EIO, "%s: %s", p, strerror(e));
    }
  }
  int lfd = open(st->lockpath, O_RDWR | O_CREAT | O_CLOEXEC, 0600);
  if (lfd < 0) {
    int e = errno;
    sm_store_close(st);
    return sm_error_set(err, SM_EIO, "%s: %s", st->lockpath, strerror(e));
  }
  close(lfd);
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
  /* Leftover temp files of interrupted basis and counts writes. */
  for (int i = 1; i < 3; i++) {
    snprintf(p, sizeof p, "%s/%s", dir, subdirs[i]);
    if ((d = opendir(p))) {
      while ((de = readdir(d)))
        if (strstr(de->d_name, ".tmp.")) remove_stale_temp(st, subdirs[i], de->d_name);
      closedir(d);
    }
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
  int k = 0;
  for (int i = 0; i < st->def.nspec; i++) k = st->def.spec[i].k > k ? st->def.spec[i].k : k;
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

/* Stores bytes as shapes/<hex>.drc unless the file already holds them, under the name's
 * lock: two daemons storing one shape write it once, and delete_if_bad never removes
 * bytes renamed in meanwhile. An identical file is left alone, which also keeps the inode
 * that other daemons' indexes remember. *wrote = 1 if written. */
static int write_shape_file(sm_store *st, const char *hex, const uint8_t *draco, size_t len,
                            int *wrote, sm_error *err) {
  char name[80], path[PATHBUF];
  *wrote = 0;
  snprintf(name, sizeof name, "%s.drc", hex);
  shape_path(st, hex, path, sizeof path);
  int fd = lock_name(st, name, 0, NULL, NULL);
  if (fd < 0)
    return sm_error_set(err, SM_EIO, "%s: cannot lock: %s", st->lockpath, strerror(errno));
  int rc = SM_OK;
  if (!stored_file_matches(st, hex, draco, len)) {
    rc = sm_file_write_atomic(path, draco, len, err);
    *wrote = rc == SM_OK;
  }
  unlock_name(fd);
  return rc;
}

/* Re-PUT of a stored id: the bytes are verified, so they can repair a file that was
 * damaged or removed behind the daemon's back. */
static int put_existing(sm_store *st, const uint8_t id[32], const char *hex,
                        const uint8_t *draco, size_t len, int *existed, sm_error *err) {
  int wrote;
  int rc = write_shape_file(st, hex, draco, len, &wrote, err);
  if (rc || !wrote) return rc;
  char path[PATHBUF];
  shape_path(st, hex, path, sizeof path);
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
                 uint32_t *nv, uint32_t *nf, int *existed, sm_mesh **decoded, sm_error *err) {
  *existed = 0;
  if (decoded) *decoded = NULL;
  uint8_t got[32];
  char hex[65];
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
  vfile vf;
  memset(&vf, 0, sizeof vf);
  vf.nv = (uint32_t)m->nv;
  vf.nf = (uint32_t)m->nf;
  vf.bytes = len;
  sm_mesh_destroy(c);
  if (rc || !decoded) sm_mesh_destroy(m);
  if (rc) return rc;

  int wrote;
  char path[PATHBUF];
  rc = write_shape_file(st, hex, draco, len, &wrote, err);
  if (rc) {
    if (decoded) sm_mesh_destroy(m);
    return rc;
  }
  uint32_t mnv, mnf;
  if (wrote || read_meta(st, hex, &mnv, &mnf)) write_meta(st, hex, vf.nv, vf.nf);
  shape_path(st, hex, path, sizeof path);
  if (file_sig_of(path, &vf.sig)) memset(&vf.sig, 0, sizeof vf.sig);

  pthread_mutex_lock(&st->mu);
  /* Not written: another daemon sharing the data directory stored these bytes first. */
  *existed = find(st, id) != NULL || !wrote;
  if (!(e = index_insert_locked(st, id, hex, &vf)))
    rc = sm_error_set(err, SM_ENOMEM, "store: out of memory");
  if (e) {
    *nv = e->nv;
    *nf = e->nf;
  }
  pthread_mutex_unlock(&st->mu);
  if (decoded && !rc) *decoded = m;
  else if (decoded) sm_mesh_destroy(m);
  return rc;
}

/* e's file no longer has the signature it was verified with: another daemon renamed
 * identical bytes over it (content-addressed, so that is harmless), dropped it, or it
 * was damaged. Reads it again and keeps, or forgets, the shape. Without st->mu; returns
 * the verdict (VF_OK: still indexed, with the new signature). */
static int revalidate(sm_store *st, const uint8_t id[32], const char *hex) {
  vfile vf;
  int r = verify_file(st, hex, 0, &vf);
  if (r == VF_BAD) r = delete_if_bad(st, hex, 0, &vf);
  pthread_mutex_lock(&st->mu);
  entry *e = find(st, id);
  if (e && r == VF_OK) {
    e->sig = vf.sig;
  } else if (e && r == VF_GONE) {
    sm_log("info", "store: shape file gone (dropped by a daemon sharing the data directory, "
           "or removed), shape forgotten", " id=%s", hex);
    forget_locked(st, e, 0);
  } else if (e) { /* a damaged file was deleted by delete_if_bad; an unreadable one stays */
    sm_log("warn", "store: shape file changed on disk, shape forgotten", " id=%s err=\"%s\"",
           hex, vf.why);
    if (r == VF_BAD) st->s.shapes_corrupt++;
    forget_locked(st, e, 0);
  }
  pthread_mutex_unlock(&st->mu);
  return r;
}

int sm_store_has(sm_store *st, const uint8_t id[32], uint32_t *nv, uint32_t *nf,
                 int *prepared) {
  *nv = *nf = 0;
  *prepared = 0;
  char hex[65];
  sm_hex(id, 32, hex);
  pthread_mutex_lock(&st->mu);
  entry *e = find(st, id);
  for (int i = 0; i < RECHECKS && e && !entry_file_intact(st, e); i++) {
    pthread_mutex_unlock(&st->mu);
    revalidate(st, id, hex);
    pthread_mutex_lock(&st->mu);
    e = find(st, id);
  }
  if (!e) {
    pthread_mutex_unlock(&st->mu);
    int adopted = adopt(st, id, hex) > 0;
    pthread_mutex_lock(&st->mu);
    e = adopted ? find(st, id) : NULL;
  }
  if (e) {
    *nv = e->nv;
    *nf = e->nf;
    for (variant *v = e->vars; v; v = v->next)
      if (v->state == V_READY && key_eq(&v->key, &st->def)) *prepared = 1;
  }
  pthread_mutex_unlock(&st->mu);
  if (e && !*prepared) { /* bases on disk count as prepared */
    char p[PATHBUF];
    struct stat sb;
    int ok = 1;
    for (int i = 0; ok && i < st->def.nspec; i++) {
      basis_path(st, hex, "", &st->def.spec[i], p, sizeof p);
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

/* Removes e from the index and the cache; with files (DROP), its files too. A shape whose
 * file was found damaged or gone keeps its bases: they are checked against the mesh they
 * belong to when loaded, so they can only serve the same bytes stored again. */
static void forget_locked(sm_store *st, entry *e, int files) {
  unlink_entry(st, e);
  e->dropped = 1;
  st->s.shapes--;
  st->s.shapes_bytes -= e->bytes;
  for (variant *v = e->vars, *n; v; v = n) {
    n = v->next;
    if (v->state == V_READY) var_evict_locked(st, v);
    else if (v->state == V_FAILED) {
      var_unlink(e, v);
      free(v);
    }
  }
  char hex[65], p[PATHBUF];
  memcpy(hex, e->hex, 65);
  maybe_free_entry(e);
  if (!files) return;
  /* Unlinks under the lock so that a PUT of the same id racing with this DROP cannot have
   * its fresh file deleted afterwards. */
  shape_path(st, hex, p, sizeof p);
  unlink(p);
  meta_path(st, hex, p, sizeof p);
  unlink(p);
  unlink_bases(st, hex);
}

int sm_store_drop(sm_store *st, const uint8_t id[32]) {
  char hex[65];
  sm_hex(id, 32, hex);
  pthread_mutex_lock(&st->mu);
  entry *e = find(st, id);
  if (!e) { /* perhaps stored by another daemon sharing the data directory */
    pthread_mutex_unlock(&st->mu);
    if (adopt(st, id, hex) <= 0) return SM_STORE_ENOTFOUND;
    pthread_mutex_lock(&st->mu);
    if (!(e = find(st, id))) {
      pthread_mutex_unlock(&st->mu);
      return SM_STORE_ENOTFOUND;
    }
  }
  forget_locked(st, e, 1);
  pthread_mutex_unlock(&st->mu);
  return SM_OK;
}

/* ---------------------------------------------------------------- prepare */

/* The NOT_FOUND error of acquire for a file revalidate did not keep. */
static int not_stored(sm_error *err, int verdict) {
  if (verdict == VF_GONE)
    return sm_error_set(err, SM_STORE_ENOTFOUND, "shape not stored (its file was dropped)");
  if (verdict == VF_UNREADABLE)
    return sm_error_set(err, SM_STORE_ENOTFOUND,
                        "the stored file cannot be read (see the daemon's log); PUT the shape "
                        "again");
  return sm_error_set(err, SM_STORE_ENOTFOUND,
                      "the stored file was damaged on disk and has been removed; PUT the shape "
                      "again");
}

static uint64_t us_since(uint64_t t0) { return (sm_srv_now_ns() - t0) / 1000; }

/* sm_prepare's hooks (sm_prepare.h): bases come from and go to bases/. A missing basis is
 * computed under its file's lock, taken by load and released by save, so a daemon sharing
 * the data directory that needs the same basis waits and loads the file instead of
 * computing it again (single-flight across daemons, as store->cv is within one). */
typedef struct prep_io {
  sm_store *st;
  const char *hex;
  const char *level; /* level_tag of the key */
  int (*cancel)(void *);
  void *ud;
  sm_basis_spec held[SM_PREP_MAX_BASES]; /* specs whose lock is held ... */
  int fd[SM_PREP_MAX_BASES];             /* ... and its descriptor (-1: none) */
  int nheld;
} prep_io;

static void count(sm_store *st, uint64_t *counter) {
  pthread_mutex_lock(&st->mu);
  (*counter)++;
  pthread_mutex_unlock(&st->mu);
}

/* The verified basis file, or NULL (a file that fails is deleted, counted bases_corrupt). */
static sm_basis *load_file(sm_store *st, const char *path, const sm_basis_spec *spec,
                           const sm_mesh *m) {
  struct stat sb;
  if (stat(path, &sb)) return NULL;
  sm_basis *b = NULL;
  sm_error lerr;
  int rc = sm_basis_load(path, &b, &lerr);
  if (!rc) rc = sm_basis_fits(b, spec, m, &lerr);
  if (!rc) return b;
  sm_basis_destroy(b);
  sm_log("warn", "store: corrupt basis file deleted, recomputing", " path=%s err=\"%s\"", path,
         lerr.msg);
  unlink(path);
  count(st, &st->s.bases_corrupt);
  return NULL;
}

static int io_load(void *ud, const sm_basis_spec *spec, const sm_mesh *m, sm_basis **out,
                   sm_error *err) {
  prep_io *io = ud;
  char path[PATHBUF];
  basis_path(io->st, io->hex, io->level, spec, path, sizeof path);
  int fd = lock_name(io->st, strrchr(path, '/') + 1, 0, io->cancel, io->ud);
  if (fd < 0 && errno == ECANCELED)
    return sm_error_set(err, SM_ECANCELED, "cancelled while another daemon computed the basis");
  if (fd < 0) /* no lock: at worst the basis is computed twice (the rename is atomic) */
    sm_log("warn", "store: cannot lock, computing without", " path=%s err=\"%s\"",
           io->st->lockpath, strerror(errno));
  if ((*out = load_file(io->st, path, spec, m))) {
    unlock_name(fd);
    count(io->st, &io->st->s.bases_loaded);
    return 1;
  }
  io->held[io->nheld] = *spec;
  io->fd[io->nheld++] = fd;
  return 0;
}

static void io_save(void *ud, const sm_basis_spec *spec, const sm_basis *b) {
  prep_io *io = ud;
  char path[PATHBUF];
  basis_path(io->st, io->hex, io->level, spec, path, sizeof path);
  sm_error serr;
  if (b) count(io->st, &io->st->s.bases_computed);
  if (b && sm_basis_save(b, path, &serr))
    sm_log("warn", "store: cannot save basis", " path=%s err=\"%s\"", path, serr.msg);
  for (int i = 0; i < io->nheld; i++)
    if (sm_basis_spec_eq(&io->held[i], spec)) {
      unlock_name(io->fd[i]);
      io->fd[i] = -1;
    }
}

/* The stored bytes of hex, checked against their name (SM_STORE_ECORRUPT otherwise). */
static int read_shape(sm_store *st, const char *hex, uint8_t **buf, size_t *len,
                      sm_error *err) {
  char path[PATHBUF];
  shape_path(st, hex, path, sizeof path);
  if (sm_read_file_bytes(path, (size_t)1 << 34, buf, len, err)) return SM_STORE_ECORRUPT;
  uint8_t id[32];
  char h2[65];
  sm_sha256(*buf, *len, id);
  sm_hex(id, 32, h2);
  if (strcmp(h2, hex)) {
    free(*buf);
    *buf = NULL;
    return sm_error_set(err, SM_STORE_ECORRUPT, "%s: content does not match its id", path);
  }
  return SM_OK;
}

/* raw_in: the shape's decoded bytes when the caller has them (PUT decoded them), else
 * NULL: the file is read and decoded. */
static int compute_variant(sm_store *st, const char *hex, const sm_store_key *key,
                           const sm_mesh *raw_in, int (*cancel)(void *), void *ud,
                           sm_prepared **out, sm_store_prep_info *info, sm_error *err) {
  uint64_t t0 = sm_srv_now_ns();
  sm_mesh *raw = NULL;
  int rc = SM_OK;
  if (!raw_in) {
    uint8_t *buf = NULL;
    size_t len = 0;
    if ((rc = read_shape(st, hex, &buf, &len, err))) return rc;
    rc = sm_draco_decode(buf, len, &st->lim, &raw, err);
    free(buf);
  }
  const sm_mesh *input = raw_in ? raw_in : raw;
  uint64_t t_decode = us_since(t0);
  char level[64];
  level_tag(key, level, sizeof level);
  prep_io io = {.st = st, .hex = hex, .level = level, .cancel = cancel, .ud = ud};
  sm_prep_hooks hooks = {io_load, io_save, &io};
  sm_prep_opts po;
  sm_prep_opts_default(&po);
  memcpy(po.spec, key->spec, sizeof po.spec);
  po.nspec = key->nspec;
  po.lim = &st->lim;
  po.hooks = &hooks;
  po.cancel = cancel;
  po.cancel_ud = ud;
  sm_prep_info pi;
  memset(&pi, 0, sizeof pi);
  sm_shape *s = NULL;
  sm_multires_shape *mr = NULL;
  if (!rc && key->coarse_nv) {
    sm_multires_opts mo;
    sm_multires_opts_default(&mo);
    mo.mode = SM_MULTIRES_ON;
    mo.coarse_nv = key->coarse_nv;
    mo.max_aspect = key->max_aspect;
    rc = sm_prepare_multires(input, &po, &mo, &mr, &pi, err);
    if (!rc) /* the fine level's cleaning, decimation and location count as cleaning */
      pi.t_clean += mr->t_clean + mr->t_decimate + mr->t_locate;
  } else if (!rc) {
    rc = sm_prepare(input, &po, &s, &pi, err);
  }
  sm_mesh_destroy(raw);
  info->t_clean_us = t_decode + (uint64_t)(pi.t_clean * 1e6);
  for (int i = 0; i < key->nspec; i++) info->t_basis_us[i] = (uint64_t)(pi.t_basis[i] * 1e6);
  info->t_desc_us = (uint64_t)(pi.t_desc * 1e6);
  info->bases_loaded = pi.loaded;
  info->bases_computed = pi.computed;
  if (rc) return rc;
  sm_prepared *p = calloc(1, sizeof *p);
  if (!p) {
    sm_shape_destroy(s);
    return sm_error_set(err, SM_ENOMEM, "store: out of memory");
  }
  p->shape = s;
  p->mr = mr;
  p->bytes = s ? sm_shape_bytes(s) : multires_bytes(mr);
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
  return sm_store_acquire_ex(st, id, key, NULL, 0, cancel, ud, out, info, err);
}

int sm_store_acquire_ex(sm_store *st, const uint8_t id[32], const sm_store_key *key,
                        const sm_mesh *raw, int background, int (*cancel)(void *), void *ud,
                        sm_prepared **out, sm_store_prep_info *info, sm_error *err) {
  *out = NULL;
  memset(info, 0, sizeof *info);
  char hex0[65];
  sm_hex(id, 32, hex0);
  int rechecks = 0, adopted = 0;
  pthread_mutex_lock(&st->mu);
  for (;;) {
    entry *e = find(st, id);
    if (e && !e->pins && rechecks < RECHECKS && !entry_file_intact(st, e)) {
      rechecks++;
      pthread_mutex_unlock(&st->mu);
      int r = revalidate(st, id, hex0);
      if (r != VF_OK) return not_stored(err, r);
      pthread_mutex_lock(&st->mu);
      continue;
    }
    if (!e && !adopted) {
      adopted = 1;
      pthread_mutex_unlock(&st->mu);
      adopt(st, id, hex0);
      pthread_mutex_lock(&st->mu);
      continue;
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
    if (v && v->state == V_FAILED) { /* reported once: the next request computes again */
      int code = v->failure.code;
      *err = v->failure;
      size_t l = strlen(err->msg);
      snprintf(err->msg + l, sizeof err->msg - l, " (background preparation after PUT)");
      if (!background) {
        var_unlink(e, v);
        free(v);
      }
      pthread_mutex_unlock(&st->mu);
      return code;
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
    if (++st->computing > st->s.prepares_concurrent_max)
      st->s.prepares_concurrent_max = st->computing;
    char hex[65];
    memcpy(hex, e->hex, 65);
    pthread_mutex_unlock(&st->mu);

    sm_prepared *p = NULL;
    int w = info->waited;
    int rc = compute_variant(st, hex, key, raw, cancel, ud, &p, info, err);
    info->waited = w;

    pthread_mutex_lock(&st->mu);
    st->computing--;
    e->pins--;
    var_unlink(e, v);
    if (rc == SM_STORE_ECORRUPT) {
      free(v);
      pthread_cond_broadcast(&st->cv);
      maybe_free_entry(e);
      pthread_mutex_unlock(&st->mu);
      int r = revalidate(st, id, hex); /* e is not used again: DROP may free it */
      if (r != VF_OK || ++rechecks > RECHECKS) return not_stored(err, r == VF_OK ? VF_BAD : r);
      pthread_mutex_lock(&st->mu); /* replaced by good bytes meanwhile: again */
      continue;
    } else if (rc && background && rc != SM_ECANCELED && !e->dropped) {
      v->state = V_FAILED; /* kept for the request that needs it (sm_srv_store.h) */
      v->failure = *err;
      v->failure.code = rc;
      v->next = e->vars;
      e->vars = v;
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
      st->s.bases_cached += (uint64_t)prepared_nbases(p);
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

/* 1 when the variant (id, key) exists and is in the given state. */
static int variant_in_state(sm_store *st, const uint8_t id[32], const sm_store_key *key,
                            int state) {
  pthread_mutex_lock(&st->mu);
  entry *e = find(st, id);
  variant *v = e ? find_var(e, key) : NULL;
  int in = v && (int)v->state == state;
  pthread_mutex_unlock(&st->mu);
  return in;
}

int sm_store_busy(sm_store *st, const uint8_t id[32], const sm_store_key *key) {
  return variant_in_state(st, id, key, V_COMPUTING);
}

int sm_store_cached(sm_store *st, const uint8_t id[32], const sm_store_key *key) {
  return variant_in_state(st, id, key, V_READY);
}

void sm_store_release(sm_store *st, sm_prepared *p) {
  if (!p) return;
  pthread_mutex_lock(&st->mu);
  prepared_unref_locked(p);
  pthread_mutex_unlock(&st->mu);
}

const sm_shape *sm_prepared_shape(const sm_prepared *p) { return p->shape; }
const sm_multires_shape *sm_prepared_multires(const sm_prepared *p) { return p->mr; }

static int cmp_id(const void *a, const void *b) { return memcmp(a, b, 32); }

/* QUERY ranks every stored shape, including those another daemon sharing the data
 * directory stored or dropped since this one looked: when shapes/ changed (its mtime),
 * its new files are adopted and the entries whose file went away are forgotten. */
static void sync_dir(sm_store *st) {
  char p[PATHBUF];
  struct stat sb;
  snprintf(p, sizeof p, "%s/shapes", st->dir);
  if (stat(p, &sb)) return;
  int64_t mt = (int64_t)sb.st_mtim.tv_sec * 1000000000 + sb.st_mtim.tv_nsec;
  pthread_mutex_lock(&st->mu);
  int same = mt == st->shapes_mtime_ns;
  pthread_mutex_unlock(&st->mu);
  if (same) return;
  DIR *d = opendir(p);
  if (!d) return;
  uint8_t *ids = NULL;
  size_t n = 0, cap = 0;
  struct dirent *de;
  while ((de = readdir(d))) {
    if (n == cap) {
      uint8_t *g = realloc(ids, (cap = cap ? 2 * cap : 256) * 32);
      if (!g) break;
      ids = g;
    }
    if (!id_of_name(de->d_name, ids + 32 * n)) n++;
  }
  closedir(d);
  if (!ids) return;
  qsort(ids, n, 32, cmp_id);
  char hex[65];
  for (size_t i = 0; i < n; i++) {
    pthread_mutex_lock(&st->mu);
    int known = find(st, ids + 32 * i) != NULL;
    pthread_mutex_unlock(&st->mu);
    if (!known) {
      sm_hex(ids + 32 * i, 32, hex);
      adopt(st, ids + 32 * i, hex);
    }
  }
  /* Entries whose file is not listed: revalidate decides (gone, or renamed in since). */
  uint8_t *gone = NULL;
  size_t ng = 0;
  pthread_mutex_lock(&st->mu);
  if (st->s.shapes && (gone = malloc(st->s.shapes * 32)))
    for (unsigned b = 0; b < NBUCKETS; b++)
      for (entry *e = st->buckets[b]; e && ng < st->s.shapes; e = e->hnext)
        if (!bsearch(e->id, ids, n, 32, cmp_id)) memcpy(gone + 32 * ng++, e->id, 32);
  pthread_mutex_unlock(&st->mu);
  for (size_t i = 0; i < ng; i++) {
    sm_hex(gone + 32 * i, 32, hex);
    revalidate(st, gone + 32 * i, hex);
  }
  free(gone);
  free(ids);
  /* Remembered only once it is in the past by more than any file system's timestamp
   * granularity: a change in the same tick as this scan would otherwise go unseen. */
  struct timespec now;
  clock_gettime(CLOCK_REALTIME, &now);
  if ((int64_t)now.tv_sec * 1000000000 + now.tv_nsec - mt > 2000000000) {
    pthread_mutex_lock(&st->mu);
    st->shapes_mtime_ns = mt;
    pthread_mutex_unlock(&st->mu);
  }
}

int sm_store_list(sm_store *st, uint8_t **ids, size_t *n) {
  sync_dir(st);
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
