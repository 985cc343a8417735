/* test_crash: crash consistency of the daemon's store (issue 10), with the real daemon.
 *
 * Each cycle: the daemon starts on the same data directory and every shape whose PUT was
 * acknowledged before any earlier SIGKILL must be STORED and preparable, with no torn
 * file found (shapes_corrupt and bases_corrupt stay 0 unless this test damaged a file
 * itself); then a client thread PUTs fresh shapes as fast as the daemon takes them, every
 * other one with the PREPARE flag (basis files being written), and the daemon is
 * SIGKILLed after a random 30-400 ms, in the middle of whatever it was doing. Every fourth
 * cycle, while the daemon is down, the test also damages one stored shape file and one
 * basis file at rest: the shape must then be reported not stored (never served) and
 * accepted again by a PUT of its bytes, and the basis recomputed.
 *
 * Cycles: SM_CRASH_CYCLES (default 12, so that CI stays short; docs/RELIABILITY.md reports
 * a 100-cycle run). Shapes: jittered icospheres of 162 vertices (k = 20), each unique.
 */
#include <dirent.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "sm_client.h"
#include "sm_meshio.h"
#include "sm_test.h"
#include "sm_test_daemon.h"
#include "sm_test_wire.h"
#include "sm_testmesh.h"

#define MAX_SHAPES 4096

typedef struct acked {
  uint8_t id[32];
  uint8_t *drc;
  size_t len;
  int damaged; /* this test damaged its file at rest */
} acked;

static acked g_acked[MAX_SHAPES];
static int g_nacked;
static pthread_mutex_t g_mu = PTHREAD_MUTEX_INITIALIZER;
static atomic_int g_seed = 1;

typedef struct putter {
  int port;
  int sent;
} putter;

/* PUTs fresh shapes until the connection dies (the SIGKILL); records the acknowledged. */
static void *put_loop(void *arg) {
  putter *p = arg;
  char addr[64];
  snprintf(addr, sizeof addr, "127.0.0.1:%d", p->port);
  sm_client *c = NULL;
  sm_client_error e;
  if (sm_client_connect(addr, NULL, &c, &e)) return NULL;
  for (;;) {
    int seed = atomic_fetch_add(&g_seed, 1);
    sm_mesh *m = tm_icosphere(2);
    tm_jitter(m, 0.01, (uint64_t)seed);
    uint8_t *drc = NULL;
    size_t len = 0;
    int rc = sm_draco_encode(m, 0, &drc, &len, NULL);
    sm_mesh_destroy(m);
    if (rc) break;
    uint8_t id[32];
    p->sent++;
    if (sm_client_put(c, drc, len, seed % 2, id, NULL, &e)) {
      free(drc);
      break;
    }
    pthread_mutex_lock(&g_mu);
    if (g_nacked < MAX_SHAPES) {
      acked *a = &g_acked[g_nacked++];
      memcpy(a->id, id, 32);
      a->drc = drc;
      a->len = len;
      drc = NULL;
    }
    pthread_mutex_unlock(&g_mu);
    free(drc);
  }
  sm_client_close(c);
  return NULL;
}

static uint64_t stat_value(sm_client *c, const char *name) {
  sm_proto_stat *st = NULL;
  uint32_t n = 0;
  sm_client_error e;
  uint64_t v = UINT64_MAX;
  if (sm_client_stats(c, &st, &n, &e)) return v;
  for (uint32_t i = 0; i < n; i++)
    if (!strcmp(st[i].name, name)) v = st[i].value;
  free(st);
  return v;
}

static void hex_of(const uint8_t id[32], char hex[65]) { sm_client_id_to_hex(id, hex); }

/* 1 if the basis file `name` (named after its shape's id) belongs to an acknowledged shape
 * whose own file is intact: verify prepares exactly those, so such a damaged basis must be
 * read, and counted, there. (A basis of a shape PUT but killed before its acknowledgement
 * may be on disk too, and nothing prepares it after the restart.) */
static int basis_of_intact_acked(const char *name) {
  char hex[65];
  for (int i = 0; i < g_nacked; i++) {
    hex_of(g_acked[i].id, hex);
    if (g_acked[i].damaged != 1 && !strncmp(name, hex, 64)) return 1;
  }
  return 0;
}

/* Damages, at rest, the stored file of the last undamaged acknowledged shape and the first
 * basis file of another acknowledged shape; returns how many basis files it damaged. */
static int damage_at_rest(void) {
  char path[1400], hex[65];
  for (int i = g_nacked - 1; i >= 0; i--) {
    if (g_acked[i].damaged) continue;
    hex_of(g_acked[i].id, hex);
    snprintf(path, sizeof path, "%s/data/shapes/%s.drc", g_dir, hex);
    damage_file(path);
    g_acked[i].damaged = 1;
    break;
  }
  snprintf(path, sizeof path, "%s/data/bases", g_dir);
  DIR *d = opendir(path);
  struct dirent *de;
  int n = 0;
  while (d && !n && (de = readdir(d)))
    if (strstr(de->d_name, ".smb") && !strstr(de->d_name, ".tmp.") &&
        basis_of_intact_acked(de->d_name)) {
      char f[1700];
      snprintf(f, sizeof f, "%s/%s", path, de->d_name);
      damage_file(f);
      n = 1;
    }
  if (d) closedir(d);
  return n;
}

/* After a restart: every acknowledged shape is stored (or, if damaged here, refused and
 * then accepted again), a few are prepared, and no torn file was found. */
static void verify(int port, int damaged_shapes, int damaged_bases, int cycle) {
  char addr[64];
  snprintf(addr, sizeof addr, "127.0.0.1:%d", port);
  sm_client *c = NULL;
  sm_client_error e;
  REQUIRE(sm_client_connect(addr, NULL, &c, &e) == 0);
  CHECK_MSG(stat_value(c, "shapes_corrupt") == (uint64_t)damaged_shapes,
            "cycle %d: shapes_corrupt %llu, expected %d", cycle,
            (unsigned long long)stat_value(c, "shapes_corrupt"), damaged_shapes);
  int lost = 0;
  for (int i = 0; i < g_nacked; i++) {
    sm_proto_has_resp h;
    REQUIRE(sm_client_has(c, g_acked[i].id, &h, &e) == 0);
    int stored = (h.flags & SM_HAS_STORED) != 0;
    if (g_acked[i].damaged == 1) {
      CHECK_MSG(!stored, "cycle %d: a shape damaged at rest is still served", cycle);
      CHECK(sm_client_put(c, g_acked[i].drc, g_acked[i].len, 0, NULL, NULL, &e) == 0);
      g_acked[i].damaged = 2; /* stored again */
    } else if (!stored) {
      lost++;
    }
  }
  CHECK_MSG(lost == 0, "cycle %d: %d acknowledged shapes lost", cycle, lost);
  /* Prepare the newest acknowledged shapes: their bases were being written at the kill. */
  for (int i = g_nacked - 1; i >= 0 && i >= g_nacked - 3; i--) {
    int rc = sm_client_prepare(c, g_acked[i].id, 0, 0, 0, NULL, &e);
    CHECK_MSG(rc == 0, "cycle %d: PREPARE after the kill: %s", cycle, e.msg);
  }
  if (damaged_bases)
    for (int i = 0; i < g_nacked; i++) sm_client_prepare(c, g_acked[i].id, 0, 0, 0, NULL, &e);
  CHECK_MSG(stat_value(c, "bases_corrupt") == (uint64_t)damaged_bases,
            "cycle %d: bases_corrupt %llu, expected %d", cycle,
            (unsigned long long)stat_value(c, "bases_corrupt"), damaged_bases);
  sm_client_close(c);
}

int main(void) {
  signal(SIGPIPE, SIG_IGN);
  atexit(kill_daemon);
  int cycles = getenv("SM_CRASH_CYCLES") ? atoi(getenv("SM_CRASH_CYCLES")) : 12;
  snprintf(g_dir, sizeof g_dir, "%s/test_crash.XXXXXX", SM_TEST_TMP);
  REQUIRE(mkdtemp(g_dir) != NULL);
  uint64_t rng = 0x5eed;
  int damaged_shapes = 0, damaged_bases = 0, sent = 0;
  for (int cycle = 0; cycle < cycles; cycle++) {
    int port = start_daemon_with("--threads 2 --default-k 20", NULL);
    REQUIRE(port > 0);
    verify(port, damaged_shapes, damaged_bases, cycle);
    putter p = {port, 0};
    pthread_t th;
    REQUIRE(pthread_create(&th, NULL, put_loop, &p) == 0);
    sleep_us(30000 + (long)(tm_rand(&rng) * 370000));
    kill_daemon(); /* SIGKILL + wait */
    pthread_join(th, NULL);
    sent += p.sent;
    damaged_shapes = damaged_bases = 0;
    if (cycle % 4 == 3) {
      damaged_bases = damage_at_rest();
      damaged_shapes = 1;
    }
  }
  int port = start_daemon_with("--threads 2 --default-k 20", NULL);
  REQUIRE(port > 0);
  verify(port, damaged_shapes, damaged_bases, cycles);
  kill_daemon();
  fprintf(stderr, "%d SIGKILL cycles, %d PUTs sent, %d acknowledged, none lost\n", cycles, sent,
          g_nacked);
  if (!sm_test_failures) rm_rf(g_dir);
  for (int i = 0; i < g_nacked; i++) free(g_acked[i].drc);
  return sm_test_finish();
}
