/* sm_client: a blocking client for the shapematch daemon (protocol/PROTOCOL.md, versions 1
 * to 3: it offers them all and speaks the one the server chooses).
 *
 * Contract
 *   Versions. The client offers protocol versions 1..3. Against an older server, what a
 *     later version added is absent (a MATCH's confidence before 2) or refused before
 *     sending (MATCH's multires choice before 3: SM_CLIENT_ELIMIT, naming the versions).
 *   Connection. sm_client_connect opens a TCP (or Unix, "unix:/path") connection and does
 *     the HELLO exchange; sm_client_close sends nothing and frees everything. A client is a
 *     single connection with its own buffers: use one per thread (no call may run on the
 *     same client from two threads at once; distinct clients are independent). Nothing is
 *     global; nothing is printed or logged: errors come back in an sm_client_error and the
 *     caller decides what to show.
 *   I/O. Sockets are non-blocking and every wait is a poll() bounded by the timeouts in
 *     sm_client_opts: connect_timeout_ms for connecting, io_timeout_ms for sending and for
 *     the answer to a request the server answers at once (HELLO, PING, STATS, HAS, DROP,
 *     CANCEL). A request that goes through the server's job queue (PUT, PREPARE, MATCH,
 *     DISTANCE, QUERY) may wait there behind other work for any time, which is not a dead
 *     connection: while waiting for such an answer, after io_timeout_ms without any frame
 *     the client sends a PING (answered at once by the server's event loop) and goes on
 *     waiting as long as these probes are answered; an unanswered probe (io_timeout_ms)
 *     is ETIMEOUT. compute_timeout_ms additionally bounds that wait (a single call: its
 *     answer; a batch: the time between two answers); 0 = no bound. While sending, the
 *     client keeps reading what the server sends, so a full pipe in both directions
 *     cannot deadlock a batch.
 *   Request ids are chosen by the client (1, 2, ..., never 0). A single call (ping, put,
 *     match, ...) sends one request and waits for its answer. sm_client_batch keeps up to N
 *     requests in flight (pipelining, PROTOCOL.md §3) and calls back per completion, in
 *     completion order.
 *   Ownership. Every input buffer is borrowed for the duration of the call (the token and
 *     affinity in sm_client_opts are copied by sm_client_connect). Results with arrays
 *     (match maps, query hits, stats) are malloc'd and owned by the caller: free them with
 *     the matching *_free function (or free() where said). In a batch callback the
 *     response and its arrays are borrowed: valid only until the callback returns.
 *   Vertex numbering. Maps, landmarks and initial maps use the input numbering of the
 *     uploaded Draco bytes, i.e. the order in which the Draco decoder returns vertices.
 *     sm_client_put_file uploads .drc files unchanged and encodes any other mesh file with
 *     the sequential (order-keeping) Draco method without quantization, so maps refer to
 *     the vertices of the file as the caller reads it.
 *   Errors. Functions return 0 or a negative SM_CLIENT_E* code and fill *err (may be NULL)
 *     with the code, a one-line message and, for SM_CLIENT_ESTATUS, the server's status,
 *     detail and retry hint. A request-level status (bit 15 clear) leaves the connection
 *     usable. A fatal status, a malformed server stream, a timeout, an I/O error or a
 *     closed connection make the client unusable: every later call returns
 *     SM_CLIENT_ECLOSED (sm_client_is_open tells); reconnect to go on. After a graceful
 *     GOAWAY the answers in flight are still read, new requests fail with ECLOSED.
 *   Lost connections (opts.reconnect_tries > 0, clients made by sm_client_connect only).
 *     When the connection is lost before an answer came (EOF, reset, a PING probe left
 *     unanswered, a GOAWAY: graceful, TIMEOUT, TOO_MANY_CONNECTIONS or OVERLOADED) the
 *     client connects again to the same address (a front such as HAProxy then picks a
 *     live daemon) and sends again the requests whose answers it has not received, when
 *     they are idempotent (sm_proto_op_flags' SM_OPF_IDEMPOTENT: PING, STATS, PUT_SHAPE,
 *     HAS_SHAPE, PREPARE, MATCH, DISTANCE, QUERY; never DROP_SHAPE or CANCEL). Answers
 *     already received are never asked for again. Connecting is tried reconnect_tries
 *     times per loss, the waits between tries growing from reconnect_backoff_ms (doubling,
 *     at most 2 s, jittered; at least a GOAWAY's retry hint). A request that was in flight
 *     at SM_CLIENT_MAX_LOSSES losses fails with the loss's error instead of being sent
 *     again, so a request that brings down every daemon it reaches cannot take a whole
 *     fleet down. Single calls and sm_client_batch both do this; nothing is resent after
 *     the caller's stop flag, an error the server reported, or a compute_timeout_ms.
 *     The new connection may land on another daemon: resending assumes it serves the same
 *     shapes (one shared store, docs/DEPLOY.md).
 */
#ifndef SM_CLIENT_H
#define SM_CLIENT_H

#include <signal.h>
#include <stddef.h>
#include <stdint.h>

#include "sm_proto.h"

#define SM_CLIENT_DEFAULT_PORT 7878
#define SM_CLIENT_ID_HEX_LEN 64

enum {
  SM_CLIENT_OK = 0,
  SM_CLIENT_EINVAL = -101,    /* bad argument, or a request the codec refuses to encode */
  SM_CLIENT_ENOMEM = -102,
  SM_CLIENT_EADDR = -103,     /* address does not parse or does not resolve */
  SM_CLIENT_ECONNECT = -104,  /* cannot connect */
  SM_CLIENT_EIO = -105,       /* socket error while connected */
  SM_CLIENT_ETIMEOUT = -106,  /* a wait exceeded its timeout (connection closed) */
  SM_CLIENT_EPROTO = -107,    /* the server's bytes do not follow the protocol */
  SM_CLIENT_ESTATUS = -108,   /* the server answered a non-OK status: err->status */
  SM_CLIENT_ECLOSED = -109,   /* connection closed (by the server, or unusable) */
  SM_CLIENT_ECANCELED = -110, /* *opts.stop was set */
  SM_CLIENT_EMESH = -111,     /* a mesh file cannot be read or encoded */
  SM_CLIENT_ELIMIT = -112     /* a request exceeds a limit the server announced in HELLO */
};

typedef struct sm_client_error {
  int code;                /* SM_CLIENT_E*, 0 = no error */
  uint16_t status;         /* server status for ESTATUS (sm_proto_status_name), else 0 */
  uint32_t detail;         /* status-specific detail (PROTOCOL.md §4) */
  uint32_t retry_after_ms; /* BUSY / TOO_MANY_CONNECTIONS / GOAWAY hint */
  char msg[320];
} sm_client_error;

const char *sm_client_strerror(int code);

typedef struct sm_client sm_client;

typedef struct sm_client_opts {
  int connect_timeout_ms;  /* default 10000 */
  int io_timeout_ms;       /* default 30000; also the silence before a liveness PING */
  int compute_timeout_ms;  /* default 0 = none (wait while the server answers PINGs) */
  uint32_t max_response;   /* sent in HELLO and enforced when parsing; 0 = no limit */
  const uint8_t *token;    /* HELLO token (copied), token_len <= SM_PROTO_MAX_TOKEN */
  size_t token_len;
  const uint8_t *affinity; /* 32-byte routing key (a shape id), or NULL for zeros */
  int payload_crc;         /* 1: requests carry the CRC32C payload trailer */
  /* When non-NULL and set to non-zero (e.g. by a SIGINT handler), waits stop within
   * ~100 ms: a single call returns ECANCELED and closes the connection (which cancels its
   * work server-side); a batch sends CANCEL for its requests in flight first. */
  const volatile sig_atomic_t *stop;
  int reconnect_tries;      /* connection attempts after a lost connection; default 0 =
                               never reconnect (see "Lost connections" above) */
  int reconnect_backoff_ms; /* first wait between two attempts; default 100 */
} sm_client_opts;

/* Losses of the connection a request may be in flight at before it fails. */
#define SM_CLIENT_MAX_LOSSES 3

void sm_client_opts_default(sm_client_opts *o);

/* "host:port", "host" (default port), "[v6addr]:port", ":port" (localhost) or
 * "unix:/path". host receives the host (or the socket path for unix, *port = 0).
 * Returns 0 or SM_CLIENT_EADDR / EINVAL. */
int sm_client_parse_addr(const char *addr, char *host, size_t host_cap, uint16_t *port,
                         sm_client_error *err);

/* Connects and says HELLO (versions 1..2, opts' token, affinity and max_response).
 * opts may be NULL (defaults). *out is owned by the caller (sm_client_close). */
int sm_client_connect(const char *addr, const sm_client_opts *opts, sm_client **out,
                      sm_client_error *err);
/* Same over a connected stream socket the caller hands over (closed by sm_client_close,
 * also when this call fails). Used by tests over a socketpair. */
int sm_client_connect_fd(int fd, const sm_client_opts *opts, sm_client **out,
                         sm_client_error *err);
/* The server's HELLO answer (negotiated version, limits). Valid while c lives. */
const sm_proto_hello_resp *sm_client_limits(const sm_client *c);
int sm_client_is_open(const sm_client *c);
/* Closes the connection (if open) and opens a new one to the address of sm_client_connect
 * with the same options (one attempt, HELLO again; the negotiated version and limits may
 * change). The client keeps its identity: request ids go on increasing. Returns 0,
 * SM_CLIENT_EINVAL for a client of sm_client_connect_fd (no address), or the error of
 * sm_client_connect (the client is then closed; it may be tried again). */
int sm_client_reconnect(sm_client *c, sm_client_error *err);
/* Times this client connected again after a lost connection (by itself or by
 * sm_client_reconnect). */
unsigned sm_client_reconnects(const sm_client *c);
void sm_client_close(sm_client *c); /* NULL is fine */

/* ---- shape ids ---- */
void sm_client_shape_id(const uint8_t *draco, size_t len, uint8_t id[SM_PROTO_ID_LEN]);
/* Lower-case hex, NUL-terminated (65 bytes). */
void sm_client_id_to_hex(const uint8_t id[SM_PROTO_ID_LEN], char hex[SM_CLIENT_ID_HEX_LEN + 1]);
/* 64 hex digits (either case), nothing else. Returns 0 or SM_CLIENT_EINVAL. */
int sm_client_id_from_hex(const char *hex, uint8_t id[SM_PROTO_ID_LEN]);
/* The bytes sm_client_put_file would upload: a .drc file as is, any other mesh file that
 * sm_mesh_read_file reads, Draco-encoded (sequential, unquantized). *buf is malloc'd. */
int sm_client_file_draco(const char *path, uint8_t **buf, size_t *len, sm_client_error *err);

/* ---- requests ---- */
/* PING: rtt_s (may be NULL) receives the round trip in seconds. */
int sm_client_ping(sm_client *c, double *rtt_s, sm_client_error *err);
/* STATS: *stats is a malloc'd array of *n (free()). */
int sm_client_stats(sm_client *c, sm_proto_stat **stats, uint32_t *n, sm_client_error *err);

/* PUT_SHAPE: computes id = SHA-256(draco) itself. prepare: ask the server to compute the
 * default bases after storing. id_out and resp may be NULL. */
int sm_client_put(sm_client *c, const uint8_t *draco, size_t len, int prepare,
                  uint8_t id_out[SM_PROTO_ID_LEN], sm_proto_put_resp *resp,
                  sm_client_error *err);
/* sm_client_file_draco + sm_client_put. */
int sm_client_put_file(sm_client *c, const char *path, int prepare,
                       uint8_t id_out[SM_PROTO_ID_LEN], sm_proto_put_resp *resp,
                       sm_client_error *err);
int sm_client_has(sm_client *c, const uint8_t id[SM_PROTO_ID_LEN], sm_proto_has_resp *resp,
                  sm_client_error *err);
int sm_client_drop(sm_client *c, const uint8_t id[SM_PROTO_ID_LEN], sm_client_error *err);
/* k_lb, k_elastic, eta: 0 = server defaults. resp may be NULL. */
int sm_client_prepare(sm_client *c, const uint8_t id[SM_PROTO_ID_LEN], int k_lb, int k_elastic,
                      double eta, sm_proto_prepare_resp *resp, sm_client_error *err);

/* MATCH / DISTANCE options; 0 (or -1 where said) = the server default, which PROTOCOL.md
 * defines as core's sm_match_opts_default, i.e. the local `shapematch match` default. */
typedef struct sm_client_match_opts {
  int basis;            /* 0 default, 1 lb, 2 elastic, 3 hybrid (enum sm_match_basis) */
  int init;             /* 0 default, 1 nn, 2 sinkhorn (enum sm_match_init) */
  int k0, k1, step;     /* 0..65535, 0 = default; k0 <= k1 when both are given */
  int sinkhorn_levels;  /* -1 default, else 0..65535 (0 = Sinkhorn refinement off) */
  int multi_start;      /* -1 default, 0 off, 1 on */
  double eta;           /* 0 default, else finite > 0 */
  const int32_t *landmarks; /* n_landmarks pairs (x vertex, y vertex), borrowed */
  uint32_t n_landmarks;
  const int32_t *init_map;  /* n_init_map entries (= input vertices of X), >= -1 */
  uint32_t n_init_map;
  int want_yx, want_fmap, want_distance; /* MATCH only */
  uint32_t deadline_ms; /* 0 = none */
  int multires;         /* MATCH only: 0 the server default (by size, as the local match),
                           1 multi-resolution, 2 direct (enum sm_multires_mode); 1 and 2
                           need a server of protocol version >= 3 */
} sm_client_match_opts;
void sm_client_match_opts_default(sm_client_match_opts *o);

typedef struct sm_client_match_result {
  uint32_t nx, ny;   /* ny = 0 unless want_yx */
  int32_t *map_xy;   /* nx: vertex of Y per vertex of X (input numbering), -1 = none */
  int32_t *map_yx;   /* ny, or NULL */
  int kC;            /* 0 unless want_fmap */
  double *fmap;      /* kC * kC column-major, or NULL */
  int init_used;     /* 1 nn, 2 sinkhorn */
  int flipped, has_distance;
  double orientation, dirichlet;
  sm_proto_dist dist; /* valid when has_distance */
  int has_confidence; /* 0 when the server speaks protocol version 1 (no such field) */
  double confidence;  /* in [0, 1] that the map is correct (core/sm_match.h); NaN when
                         !has_confidence */
  double t_prepare, t_init, t_refine, t_distance, t_total; /* seconds, server side */
} sm_client_match_result;
void sm_client_match_result_free(sm_client_match_result *r); /* frees the arrays only */

/* o may be NULL (defaults). x is the source, y the target. */
int sm_client_match(sm_client *c, const uint8_t x[SM_PROTO_ID_LEN],
                    const uint8_t y[SM_PROTO_ID_LEN], const sm_client_match_opts *o,
                    sm_client_match_result *r, sm_client_error *err);
/* Only basis-independent options apply (multi_start, sinkhorn_levels, deadline, and the
 * schedule/landmark fields, which DISTANCE carries like MATCH). t_total_s may be NULL. */
int sm_client_distance(sm_client *c, const uint8_t x[SM_PROTO_ID_LEN],
                       const uint8_t y[SM_PROTO_ID_LEN], const sm_client_match_opts *o,
                       sm_proto_dist *d, double *t_total_s, sm_client_error *err);

typedef struct sm_client_hit {
  uint8_t id[SM_PROTO_ID_LEN];
  double distance;
} sm_client_hit;
/* QUERY: the k stored shapes nearest to id (mode SM_QUERY_*), among candidates (n_cand
 * ids of 32 bytes back to back) or all stored shapes when n_cand = 0. *hits is malloc'd
 * (free()), ascending distance. n_considered may be NULL. */
int sm_client_query(sm_client *c, const uint8_t id[SM_PROTO_ID_LEN], int k, int mode,
                    const uint8_t *cand, uint32_t n_cand, uint32_t deadline_ms,
                    sm_client_hit **hits, uint32_t *n_hits, uint32_t *n_considered,
                    sm_client_error *err);

/* CANCEL: only meaningful from a batch callback (single calls have nothing in flight once
 * they return): asks the server to stop request `request_id`; the batch consumes the
 * CANCEL's own answer, and the target's answer (CANCELLED, or its result if it finished
 * first) reaches the callback as usual. */
int sm_client_cancel(sm_client *c, uint32_t request_id, sm_client_error *err);

/* ---- batch: many requests pipelined on this connection ---- */
typedef struct sm_client_req {
  uint8_t op; /* SM_OP_PING, PUT_SHAPE, HAS_SHAPE, PREPARE, MATCH, DISTANCE or QUERY */
  uint8_t x[SM_PROTO_ID_LEN]; /* the shape (HAS, PREPARE, QUERY) or source (MATCH, DISTANCE) */
  uint8_t y[SM_PROTO_ID_LEN]; /* target (MATCH, DISTANCE) */
  const sm_client_match_opts *match; /* MATCH, DISTANCE; NULL = defaults */
  int k, mode;                /* QUERY: k >= 1, SM_QUERY_* (all stored shapes) */
  int k_lb, k_elastic;        /* PREPARE (0 = default; eta from match->eta if given) */
  const uint8_t *draco;       /* PUT_SHAPE: the Draco bytes (borrowed; id computed here) */
  size_t draco_len;
  int prepare;                /* PUT_SHAPE: also compute the default bases */
} sm_client_req;

typedef struct sm_client_resp {
  uint32_t request_id;
  int code;            /* 0 or SM_CLIENT_E* (ESTATUS: see err.status) */
  sm_client_error err; /* when code != 0 */
  int attempts;        /* sends (BUSY answers are retried; a request cut by a lost
                          connection is sent again on the next one) */
  /* the result for req->op, when code == 0 */
  sm_client_match_result match;
  sm_proto_dist dist;
  double t_total;
  sm_client_hit *hits;
  uint32_t n_hits, n_considered;
  sm_proto_has_resp has;
  sm_proto_prepare_resp prepare;
  sm_proto_put_resp put;
} sm_client_resp;

/* Called once per request, in completion order; resp is borrowed. Return 0 to go on,
 * non-zero to stop: requests not yet sent are skipped (no callback) and those in flight
 * are cancelled (their callbacks still run). */
typedef int (*sm_client_batch_cb)(void *ud, size_t index, const sm_client_req *req,
                                  const sm_client_resp *resp);

/* Sends reqs[0..n) keeping up to `inflight` (>= 1; capped by the server's max_inflight) in
 * flight. An item answered BUSY is re-sent after the server's retry hint, at most
 * busy_retries times (< 0: without limit; BUSY means the server is alive and working), and
 * so is an item answered SHUTTING_DOWN when the client reconnects. With
 * opts.reconnect_tries, a lost connection is replaced and the items in flight on it are
 * sent again on the new one (contract, "Lost connections"); the batch goes on. Item
 * failures go to the callback and do not stop the batch; the return value is 0, or the
 * error that ended the batch early (connection lost and not replaced: unanswered items
 * in flight get a callback with that code, items not yet sent get none; ECANCELED after a
 * stop). *n_failed (may be NULL) counts callbacks with code != 0. */
int sm_client_batch(sm_client *c, const sm_client_req *reqs, size_t n, unsigned inflight,
                    int busy_retries, sm_client_batch_cb cb, void *ud, size_t *n_failed,
                    sm_client_error *err);

#endif
