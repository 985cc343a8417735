/* sm_srv_store: the shape store (content-addressed Draco files) and the cache of prepared
 * shapes (cleaned mesh + bases + descriptors), with single-flight preparation. The
 * preparation itself is core's (sm_prepare.h): the store supplies the bases it has on disk
 * and keeps the new ones through sm_prepare's hooks, and knows nothing of the steps.
 *
 * DESIGN
 *   Disk (the data directory; everything survives a restart):
 *     shapes/<id-hex>.drc                          the Draco bytes as uploaded
 *     meta/<id-hex>.counts                         "<id-hex> <vertices> <faces>\n" of the
 *                                                  decoded mesh, written at PUT
 *     bases/<id-hex>.<spec>.v<format>.smb          one computed basis (sm_basis_save:
 *                                                  versioned, XXH3-checksummed); <spec> is
 *                                                  sm_basis_spec_name, e.g. el.k100.eta<bits>
 *     bases/<id-hex>.mr<nv>.a<bits>.d<dec>.<spec>.v<format>.smb  a basis of the shape's
 *                                                  coarse level (multi-resolution MATCH):
 *                                                  decimated to <nv> vertices with aspect
 *                                                  bound <bits> (the f64's bits in hex) by
 *                                                  decimation version <dec>
 *                                                  (SM_MULTIRES_DECIMATION)
 *     Every file is written by sm_file_write_atomic (core/sm_basis_io.c: a unique temp
 *     name in the same directory, fsynced, renamed over its final name, the directory
 *     fsynced), so a crash leaves either the old state or the complete new file. At
 *     startup shapes/ is scanned: each file's SHA-256 must equal its name, else it is
 *     deleted (counted shapes_corrupt). The counts come from meta/ (a shape's bytes
 *     decoded at PUT, and the SHA-256 says they are the same bytes), so startup decodes
 *     only shapes without a readable counts file (stored by an older daemon), and writes
 *     theirs.
 *     A basis file is verified when loaded (magic, version, checksum, sizes, kind, k, eta
 *     and the XXH3 hash of the cleaned mesh it belongs to); a file that fails is deleted,
 *     recomputed and rewritten (counted bases_corrupt), never served.
 *   Memory: an index of every stored shape (id, counts, size) and an LRU cache of
 *     prepared shapes keyed by (id, k_lb, k_elastic, eta, coarse level), bounded by cache_bytes
 *     (approximate bytes of the arrays). Evicting only drops the cache's reference: a
 *     worker holding a prepared shape (sm_store_acquire) keeps it until sm_store_release.
 *   Single-flight: a missing variant is inserted in state COMPUTING by the first worker,
 *     which computes it without the lock; later requesters wait on store->cv (timed waits
 *     so that their own cancel flag is honoured) and are counted in singleflight_waits.
 *     If the computation fails or is cancelled the variant is removed and one waiter
 *     retries; a background preparation's failure stays instead, for the next request
 *     (sm_store_acquire_ex), and DROP removes it.
 *
 *   Several daemons may share one data directory (docs/DEPLOY.md): every file is written
 *     whole and renamed in, and a shape's file name is the SHA-256 of its bytes, so two
 *     writers of one name write the same bytes. What remains is kept safe by
 *     open-file-description locks on bytes of <dir>/store.lock, one per file name
 *     (released by the kernel when a daemon dies): a shape file is written only if it
 *     does not already hold the bytes (an identical file keeps its inode), a file is
 *     deleted as damaged only if it still fails its check under its lock (another
 *     daemon may just have healed it), a basis is computed under its lock (the others
 *     wait and load the file: bases are computed once for all the daemons), and a
 *     leftover temp file is deleted only if no live writer holds its lock.
 *     Each daemon's index learns about the others' work from the disk: a missing id is
 *     looked up in shapes/ (HAS, PREPARE, MATCH, DROP...), a changed signature is
 *     re-verified (identical bytes renamed over it are kept; a file gone was dropped),
 *     and QUERY re-reads shapes/ when its mtime changed. The cache stays per daemon.
 *
 * Contract: every function is thread-safe (one mutex, never held during computation or
 *   file I/O except the unlinks of DROP). Ids are 32 raw bytes. Returns 0 or a negative
 *   SM_E* code (sm_error.h) or SM_STORE_ENOTFOUND / SM_STORE_EIDMISMATCH, with a message.
 */
#ifndef SM_SRV_STORE_H
#define SM_SRV_STORE_H

#include <stddef.h>
#include <stdint.h>

#include "sm_error.h"
#include "sm_match.h"
#include "sm_mesh.h"
#include "sm_prepare.h"

enum {
  SM_STORE_ENOTFOUND = -100,
  SM_STORE_EIDMISMATCH = -101,
  SM_STORE_ECORRUPT = -102,    /* internal: a stored file failed its check (never returned) */
  SM_STORE_ECOMPONENTS = -103  /* PUT: more connected components than max_components */
};

typedef struct sm_store sm_store;
typedef struct sm_prepared sm_prepared;

/* A prepared variant of a shape: the bases sm_prepare computes (sm_prepare.h), at full
 * resolution (coarse_nv = 0) or on the coarse level of sm_prepare_multires, decimated to
 * coarse_nv vertices with aspect-ratio bound max_aspect (sm_multires_opts): the decimation
 * parameters are part of the key, so levels made with other parameters never mix. */
typedef struct sm_store_key {
  sm_basis_spec spec[SM_PREP_MAX_BASES];
  int nspec;
  int32_t coarse_nv;  /* 0: full resolution */
  double max_aspect;  /* with coarse_nv */
} sm_store_key;

typedef struct sm_store_prep_info {
  int cached;                 /* 1: nothing was computed or loaded by this call */
  int waited;                 /* 1: waited for another worker's computation */
  uint64_t t_clean_us, t_desc_us; /* spent by this call */
  uint64_t t_basis_us[SM_PREP_MAX_BASES]; /* per key spec, loading or computing */
  int bases_loaded, bases_computed;
} sm_store_prep_info;

/* The key of the shipped preparation (sm_prep_default_specs: LB k_lb, elastic k_el with
 * eta when k_el > 0). */
sm_store_key sm_store_key_make(int k_lb, int k_el, double eta);
/* The same key on the coarse level of sm_multires (coarse_nv vertices, mo's other
 * decimation parameters). */
sm_store_key sm_store_key_multires(const sm_store_key *full, int32_t coarse_nv);
/* k of the key's basis of kind, 0 if it has none. */
int sm_store_key_k(const sm_store_key *key, int kind);
/* Microseconds this call spent on the key's basis of kind (0 if none). */
uint64_t sm_store_info_basis_us(const sm_store_prep_info *info, const sm_store_key *key,
                                int kind);

typedef struct sm_store_stats {
  uint64_t shapes, shapes_bytes, bases_cached, cache_bytes;
  uint64_t cache_hits, cache_misses, evictions, singleflight_waits, prepares;
  uint64_t bases_computed, bases_loaded, bases_corrupt, shapes_corrupt;
  uint64_t shapes_healed; /* damaged files rewritten by a PUT of their bytes */
  uint64_t prepares_concurrent_max; /* the most preparations running at once (a cold
                                       MATCH prepares its two shapes together) */
} sm_store_stats;

/* Opens (creating) dir, scans shapes/. lim bounds decoding. default_key: what
 * HAS_SHAPE reports as PREPARED. */
int sm_store_open(const char *dir, uint64_t cache_bytes, const sm_limits *lim,
                  const sm_store_key *default_key, sm_store **out, sm_error *err);
void sm_store_close(sm_store *st);

/* What PUT accepts beyond the decoding limits (0 = no component bound). Call before use. */
void sm_store_set_max_components(sm_store *st, uint32_t max_components);

/* Verifies SHA-256(draco) == id, decodes (limits before allocation), checks that the
 * cleaned mesh can be prepared (components <= max_components: SM_STORE_ECOMPONENTS; more
 * than twice as many vertices as basis functions: SM_EUNSUPPORTED), writes the file.
 * *existed = 1 if it was already stored with these bytes; a stored file that no longer
 * holds them (damaged or removed behind the daemon's back) is rewritten (*existed = 0).
 * *existed = 1 also when another daemon sharing the directory stored it. A file found
 * changed on disk (size, mtime or inode differ from when it was verified; checked by HAS
 * and acquire) is read again: the same bytes are kept; content that fails its SHA-256 is
 * deleted and the shape forgotten (counted shapes_corrupt), a file gone is forgotten
 * quietly; either way it is reported as not stored until PUT again. */
int sm_store_put(sm_store *st, const uint8_t id[32], const uint8_t *draco, size_t len,
                 uint32_t *nv, uint32_t *nf, int *existed, sm_mesh **decoded, sm_error *err);
/* decoded (may be NULL): when the call decoded the bytes (a new shape) and succeeded, the
 * decoded mesh (caller's, sm_mesh_destroy), for a preparation that need not decode them
 * again (sm_store_acquire_ex); else NULL. */
/* 1 stored, 0 not. *prepared: default variant cached in memory or on disk. */
int sm_store_has(sm_store *st, const uint8_t id[32], uint32_t *nv, uint32_t *nf,
                 int *prepared);
/* 0 or SM_STORE_ENOTFOUND. Removes files and cached variants. */
int sm_store_drop(sm_store *st, const uint8_t id[32]);

/* The prepared shape for (id, key), computing it (single-flight) when missing. cancel(ud)
 * is polled while waiting and passed to the core while computing. */
int sm_store_acquire(sm_store *st, const uint8_t id[32], const sm_store_key *key,
                     int (*cancel)(void *), void *ud, sm_prepared **out,
                     sm_store_prep_info *info, sm_error *err);
/* Same, with two additions. raw (may be NULL): the shape's decoded bytes, used instead
 * of reading and decoding the file if this call computes the variant. background: the
 * caller is a background preparation (PUT's, sm_srv_exec.c) that nobody waits for; its
 * failure, unless cancelled, is kept in place of the variant and returned once, with
 * " (background preparation after PUT)" appended to the message, by the next acquire of
 * the key (which computes nothing; the one after it computes again); a background acquire
 * that finds such a failure returns it and leaves it. */
int sm_store_acquire_ex(sm_store *st, const uint8_t id[32], const sm_store_key *key,
                        const sm_mesh *raw, int background, int (*cancel)(void *), void *ud,
                        sm_prepared **out, sm_store_prep_info *info, sm_error *err);
/* 1 when (id, key) is being computed now (an acquire would wait for it), else 0. A hint. */
int sm_store_busy(sm_store *st, const uint8_t id[32], const sm_store_key *key);
/* 1 when (id, key) is prepared in the memory cache now (an acquire would not compute or
 * load anything), else 0. A hint: the answer may change right after. */
int sm_store_cached(sm_store *st, const uint8_t id[32], const sm_store_key *key);
void sm_store_release(sm_store *st, sm_prepared *p);
/* The prepared shape of a full-resolution key (NULL for a coarse-level key) ... */
const sm_shape *sm_prepared_shape(const sm_prepared *p);
/* ... and the multi-resolution shape of a coarse-level key (NULL otherwise). */
const sm_multires_shape *sm_prepared_multires(const sm_prepared *p);

/* Snapshot of every stored id (malloc'd, 32 bytes each), after looking for shapes other
 * daemons stored or dropped in the shared directory (when shapes/ changed). */
int sm_store_list(sm_store *st, uint8_t **ids, size_t *n);
void sm_store_get_stats(sm_store *st, sm_store_stats *out);

#endif
