/* sm_client: see sm_client.h for the contract.
 *
 * DESIGN
 *   One receive buffer per connection. Frames are parsed in place with sm_proto (the header
 *   is validated from its 24 bytes before the buffer grows for the payload, and the buffer
 *   only grows as bytes arrive, so a lying payload_len costs nothing until the bytes come).
 *   A parsed frame is a view into the buffer that stays valid until the next read on the
 *   connection (c->consume records how much to drop then).
 *   Every wait goes through wait_io(): poll() with the remaining time to an absolute
 *   deadline (monotonic clock), in slices of 100 ms when a stop flag is watched.
 *   Sending also reads: a daemon that stops reading a connection whose answers are not
 *   collected (backpressure) would otherwise deadlock against a client blocked in send.
 *   Lost connections: the places that see a connection die of something a new connection
 *   may not see (EOF, reset, an unanswered probe, a GOAWAY that invites a retry) set
 *   c->lost; a graceful GOAWAY sets c->goaway. may_relink() says whether the caller may
 *   then connect again (relink()) and resend; call() does that for one request, and
 *   sm_client_batch for the items it has not received answers to. The resent request gets
 *   a new id: the old connection's ids mean nothing to the new daemon.
 */
#include "sm_client.h"

#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <math.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <time.h>
#include <unistd.h>

#include "sm_meshio.h"
#include "sm_sha256.h"

struct sm_client {
  int fd;
  int open;   /* 0 once unusable */
  int goaway; /* graceful GOAWAY seen: no new requests */
  sm_client_opts o;
  uint8_t token[SM_PROTO_MAX_TOKEN];
  uint8_t affinity[SM_PROTO_ID_LEN];
  sm_proto_hello_resp hello;
  uint8_t version;
  uint32_t next_id;
  uint8_t *rbuf;
  size_t rlen, rcap, consume;
  uint32_t parse_limit;
  uint32_t *cancels; /* ids of CANCEL requests whose answers are still to be read */
  size_t n_cancels, cap_cancels;
  uint32_t probe_rid; /* liveness PING in flight (0 = none) */
  int64_t last_rx_ms; /* when the last frame arrived (or the last wait began) */
  char *addr;         /* sm_client_connect's address (NULL: made from an fd) */
  int lost;           /* the connection died in a way a new one may not (file comment) */
  uint32_t retry_hint_ms; /* the server's wait hint that came with the loss */
  unsigned reconnects;
  uint32_t rng;       /* backoff jitter */
};

/* ---- errors ---- */
const char *sm_client_strerror(int code) {
  switch (code) {
  case SM_CLIENT_OK: return "ok";
  case SM_CLIENT_EINVAL: return "invalid argument";
  case SM_CLIENT_ENOMEM: return "out of memory";
  case SM_CLIENT_EADDR: return "bad address";
  case SM_CLIENT_ECONNECT: return "cannot connect";
  case SM_CLIENT_EIO: return "I/O error";
  case SM_CLIENT_ETIMEOUT: return "timed out";
  case SM_CLIENT_EPROTO: return "protocol violation by the server";
  case SM_CLIENT_ESTATUS: return "server error";
  case SM_CLIENT_ECLOSED: return "connection closed";
  case SM_CLIENT_ECANCELED: return "cancelled";
  case SM_CLIENT_EMESH: return "mesh error";
  case SM_CLIENT_ELIMIT: return "over the server's limit";
  default: return "unknown error";
  }
}

__attribute__((format(printf, 3, 4))) static int seterr(sm_client_error *err, int code,
                                                        const char *fmt, ...) {
  if (err) {
    memset(err, 0, sizeof *err);
    err->code = code;
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(err->msg, sizeof err->msg, fmt, ap);
    va_end(ap);
  }
  return code;
}

static void clear_err(sm_client_error *err) {
  if (err) memset(err, 0, sizeof *err);
}

/* Marks the connection unusable and returns code (error already set by the caller). */
static int broken(sm_client *c, int code) {
  if (c->open && c->fd >= 0) shutdown(c->fd, SHUT_RDWR);
  c->open = 0;
  return code;
}

/* ---- options, addresses ---- */
void sm_client_opts_default(sm_client_opts *o) {
  memset(o, 0, sizeof *o);
  o->connect_timeout_ms = 10000;
  o->io_timeout_ms = 30000;
  o->reconnect_backoff_ms = 100;
}

int sm_client_parse_addr(const char *addr, char *host, size_t host_cap, uint16_t *port,
                         sm_client_error *err) {
  if (!addr || !host || !host_cap || !port) return seterr(err, SM_CLIENT_EINVAL, "parse_addr: NULL argument");
  const char *h = addr, *p = NULL;
  size_t hl;
  if (!strncmp(addr, "unix:", 5)) {
    const char *path = addr + 5;
    size_t n = strlen(path);
    if (!n || n >= host_cap || n >= sizeof(((struct sockaddr_un *)0)->sun_path))
      return seterr(err, SM_CLIENT_EADDR, "'%s': unix socket path empty or too long", addr);
    memcpy(host, path, n + 1);
    *port = 0;
    return 0;
  }
  if (addr[0] == '[') {
    const char *e = strchr(addr, ']');
    if (!e || e == addr + 1) return seterr(err, SM_CLIENT_EADDR, "'%s': unterminated [ipv6]", addr);
    h = addr + 1;
    hl = (size_t)(e - h);
    if (e[1] == ':') p = e + 2;
    else if (e[1]) return seterr(err, SM_CLIENT_EADDR, "'%s': junk after ]", addr);
  } else {
    const char *colon = strrchr(addr, ':');
    if (colon && strchr(addr, ':') != colon)
      return seterr(err, SM_CLIENT_EADDR, "'%s': an IPv6 address needs brackets: [addr]:port", addr);
    hl = colon ? (size_t)(colon - addr) : strlen(addr);
    if (colon) p = colon + 1;
  }
  if (hl == 0) {
    if (!p) return seterr(err, SM_CLIENT_EADDR, "empty address");
    h = "localhost";
    hl = strlen(h);
  }
  if (hl >= host_cap) return seterr(err, SM_CLIENT_EADDR, "'%s': host name too long", addr);
  long pv = SM_CLIENT_DEFAULT_PORT;
  if (p) {
    char *end;
    errno = 0;
    pv = *p ? strtol(p, &end, 10) : -1;
    if (!*p || *end || errno || pv < 1 || pv > 65535 || p[0] == '+' || p[0] == '-')
      return seterr(err, SM_CLIENT_EADDR, "'%s': port must be 1..65535", addr);
  }
  for (size_t i = 0; i < hl; i++)
    if (h[i] == ' ' || h[i] == '/' || h[i] == '[' || h[i] == ']')
      return seterr(err, SM_CLIENT_EADDR, "'%s': bad character in host", addr);
  memcpy(host, h, hl);
  host[hl] = 0;
  *port = (uint16_t)pv;
  return 0;
}

/* ---- time and waiting ---- */
static int64_t now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (int64_t)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}
static int64_t deadline_in(int ms) { return ms > 0 ? now_ms() + ms : -1; }

/* Waits for events on c->fd. Returns revents (> 0), or ETIMEOUT / ECANCELED / EIO. */
static int wait_io(sm_client *c, short events, int64_t deadline, int watch_stop,
                   sm_client_error *err) {
  for (;;) {
    if (watch_stop && c->o.stop && *c->o.stop)
      return seterr(err, SM_CLIENT_ECANCELED, "stopped by the caller");
    int tmo = -1;
    if (deadline >= 0) {
      int64_t left = deadline - now_ms();
      if (left <= 0) return seterr(err, SM_CLIENT_ETIMEOUT, "no answer from the server in time");
      tmo = left > INT_MAX ? INT_MAX : (int)left;
    }
    if (watch_stop && c->o.stop && (tmo < 0 || tmo > 100)) tmo = 100;
    struct pollfd pf = {c->fd, events, 0};
    int r = poll(&pf, 1, tmo);
    if (r < 0 && errno == EINTR) continue;
    if (r < 0) return seterr(err, SM_CLIENT_EIO, "poll: %s", strerror(errno));
    if (r > 0) return pf.revents;
  }
}

/* Reads what is available (one recv). Returns bytes read (> 0), 0 if it would block, or
 * ECLOSED / EIO. */
static ptrdiff_t read_some(sm_client *c, sm_client_error *err) {
  if (c->consume) {
    memmove(c->rbuf, c->rbuf + c->consume, c->rlen - c->consume);
    c->rlen -= c->consume;
    c->consume = 0;
  }
  if (c->rcap - c->rlen < 4096) {
    size_t ncap = c->rcap < 65536 ? 65536 : c->rcap * 2;
    uint8_t *nb = realloc(c->rbuf, ncap);
    if (!nb) return seterr(err, SM_CLIENT_ENOMEM, "receive buffer of %zu bytes", ncap);
    c->rbuf = nb;
    c->rcap = ncap;
  }
  for (;;) {
    ssize_t r = recv(c->fd, c->rbuf + c->rlen, c->rcap - c->rlen, 0);
    if (r > 0) {
      c->rlen += (size_t)r;
      return r;
    }
    if (r == 0) return seterr(err, SM_CLIENT_ECLOSED, "the server closed the connection");
    if (errno == EINTR) continue;
    if (errno == EAGAIN || errno == EWOULDBLOCK) return 0;
    return seterr(err, SM_CLIENT_EIO, "recv: %s", strerror(errno));
  }
}

static int send_all(sm_client *c, const uint8_t *buf, size_t len, sm_client_error *err) {
  int64_t dl = deadline_in(c->o.io_timeout_ms);
  while (len) {
    int ev = wait_io(c, POLLOUT | POLLIN, dl, 0, err);
    if (ev < 0) return broken(c, ev);
    if (ev & POLLIN) {
      ptrdiff_t r = read_some(c, err);
      if (r < 0 && r != SM_CLIENT_ECLOSED) return broken(c, (int)r);
    }
    if (ev & (POLLOUT | POLLERR | POLLHUP)) {
      ssize_t w = send(c->fd, buf, len, MSG_NOSIGNAL);
      if (w < 0 && (errno == EINTR || errno == EAGAIN || errno == EWOULDBLOCK)) continue;
      if (w < 0) {
        c->lost = 1;
        return broken(c, seterr(err, errno == EPIPE || errno == ECONNRESET ? SM_CLIENT_ECLOSED : SM_CLIENT_EIO,
                                "send: %s", strerror(errno)));
      }
      buf += w;
      len -= (size_t)w;
    }
  }
  return 0;
}

/* Next complete server frame into *f (a view valid until the next read). */
static int next_frame(sm_client *c, int64_t deadline, int watch_stop, sm_proto_frame *f,
                      sm_client_error *err) {
  for (;;) {
    const uint8_t *p = c->rbuf + c->consume;
    size_t avail = c->rlen - c->consume;
    ptrdiff_t r = sm_proto_parse_frame(p, avail, c->parse_limit, f);
    if (r > 0) {
      c->consume += (size_t)r;
      c->last_rx_ms = now_ms();
      if (!(f->h.flags & SM_PROTO_F_RESPONSE) || (c->version && f->h.version != c->version))
        return broken(c, seterr(err, SM_CLIENT_EPROTO, "server frame with %s",
                                (f->h.flags & SM_PROTO_F_RESPONSE) ? "another version" : "no RESPONSE flag"));
      return 0;
    }
    if (r != SM_PROTO_PARTIAL)
      return broken(c, seterr(err, SM_CLIENT_EPROTO, "server stream: %s", sm_proto_strerror((int)r)));
    int ev = wait_io(c, POLLIN, deadline, watch_stop, err);
    if (ev == SM_CLIENT_ETIMEOUT || ev == SM_CLIENT_ECANCELED) return ev; /* caller decides */
    if (ev < 0) return broken(c, ev);
    ptrdiff_t n = read_some(c, err);
    if (n == SM_CLIENT_ECLOSED || n == SM_CLIENT_EIO) c->lost = 1;
    if (n < 0) return broken(c, (int)n);
  }
}

/* Fills err from a non-OK frame's error payload. Fatal statuses close the connection. */
static int status_error(sm_client *c, const sm_proto_frame *f, sm_client_error *err) {
  sm_proto_error e;
  memset(&e, 0, sizeof e);
  int bad = sm_proto_dec_error(f->body, f->body_len, &e);
  seterr(err, SM_CLIENT_ESTATUS, "server: %s%s%.*s", sm_proto_status_name(f->h.status),
         bad || !e.msg_len ? "" : ": ", bad ? 0 : (int)e.msg_len, bad ? "" : e.msg);
  if (err) {
    err->status = f->h.status;
    err->detail = bad ? 0 : e.detail;
    err->retry_after_ms = bad ? 0 : e.retry_after_ms;
  }
  if (sm_proto_status_is_fatal(f->h.status)) {
    /* these close a connection for reasons of the moment (idleness, load), not for what
     * the client sent: a new connection may do better */
    uint16_t st = f->h.status;
    if (st == SM_ST_TIMEOUT || st == SM_ST_TOO_MANY_CONNECTIONS || st == SM_ST_OVERLOADED) {
      c->lost = 1;
      c->retry_hint_ms = bad ? 0 : e.retry_after_ms;
    }
    broken(c, 0);
  }
  return SM_CLIENT_ESTATUS;
}

/* A frame the request loops do not expect for themselves: GOAWAY and CANCEL answers.
 * Returns 1 if handled, 0 if not ours, < 0 on a fatal GOAWAY (err set). */
static int side_frame(sm_client *c, const sm_proto_frame *f, sm_client_error *err) {
  if (f->h.opcode == SM_OP_GOAWAY) {
    if (f->h.status == SM_ST_OK) {
      sm_proto_error e;
      c->goaway = 1;
      c->retry_hint_ms = sm_proto_dec_error(f->body, f->body_len, &e) ? 0 : e.retry_after_ms;
      return 1;
    }
    return status_error(c, f, err);
  }
  if (f->h.opcode == SM_OP_PING && c->probe_rid && f->h.request_id == c->probe_rid) {
    c->probe_rid = 0; /* the server is alive (any status: SHUTTING_DOWN says so too) */
    return 1;
  }
  if (f->h.opcode == SM_OP_CANCEL && !(f->h.flags & SM_PROTO_F_MORE))
    for (size_t i = 0; i < c->n_cancels; i++)
      if (c->cancels[i] == f->h.request_id) {
        c->cancels[i] = c->cancels[--c->n_cancels];
        return 1;
      }
  return 0;
}

/* ---- encoding ---- */
static uint32_t new_id(sm_client *c) {
  if (++c->next_id == 0) c->next_id = 1;
  return c->next_id;
}

static ptrdiff_t enc_req(uint8_t *b, size_t cap, const sm_proto_header *h, uint8_t op,
                         const void *m) {
  switch (op) {
  case SM_OP_HELLO: return sm_proto_enc_hello_req(b, cap, h, m);
  case SM_OP_PING: return sm_proto_enc_ping(b, cap, h, 0, m);
  case SM_OP_STATS: return sm_proto_enc_empty(b, cap, h);
  case SM_OP_PUT_SHAPE: return sm_proto_enc_put_req(b, cap, h, m);
  case SM_OP_HAS_SHAPE:
  case SM_OP_DROP_SHAPE: return sm_proto_enc_id_req(b, cap, h, op, m);
  case SM_OP_PREPARE: return sm_proto_enc_prepare_req(b, cap, h, m);
  case SM_OP_MATCH:
  case SM_OP_DISTANCE: return sm_proto_enc_match_req(b, cap, h, op, m);
  case SM_OP_QUERY: return sm_proto_enc_query_req(b, cap, h, m);
  case SM_OP_CANCEL: return sm_proto_enc_cancel_req(b, cap, h, m);
  default: return SM_PROTO_EINVAL;
  }
}

/* Encodes and sends one request; *rid receives its id. */
static int send_req(sm_client *c, uint8_t op, const void *m, uint32_t *rid,
                    sm_client_error *err) {
  if (!c->open) return seterr(err, SM_CLIENT_ECLOSED, "connection is closed");
  if (c->goaway && op != SM_OP_CANCEL)
    return seterr(err, SM_CLIENT_ECLOSED, "the server is shutting down (GOAWAY)");
  sm_proto_header h = {0};
  h.version = op == SM_OP_HELLO ? SM_PROTO_VERSION_HELLO : c->version;
  h.opcode = op;
  h.request_id = new_id(c);
  h.flags = c->o.payload_crc ? SM_PROTO_F_PAYLOAD_CRC : 0;
  ptrdiff_t n = enc_req(NULL, 0, &h, op, m);
  if (n < 0) return seterr(err, SM_CLIENT_EINVAL, "%s request cannot be encoded (invalid field)", sm_proto_op_name(op));
  if (op != SM_OP_HELLO && c->hello.max_payload &&
      (uint64_t)n - SM_PROTO_HEADER_LEN > c->hello.max_payload)
    return seterr(err, SM_CLIENT_ELIMIT, "%s request of %td bytes, server accepts %u", sm_proto_op_name(op),
                  n - SM_PROTO_HEADER_LEN, c->hello.max_payload);
  if (op == SM_OP_MATCH && c->version < SM_PROTO_VERSION_MULTIRES &&
      (((const sm_proto_match_req *)m)->flags & (SM_MATCH_F_MULTIRES | SM_MATCH_F_DIRECT)))
    return seterr(err, SM_CLIENT_ELIMIT, "the server speaks protocol version %u: choosing the "
                  "multi-resolution or the direct path of MATCH needs version %d",
                  c->version, SM_PROTO_VERSION_MULTIRES);
  uint8_t small[512], *buf = (size_t)n <= sizeof small ? small : malloc((size_t)n);
  if (!buf) return seterr(err, SM_CLIENT_ENOMEM, "request of %td bytes", n);
  enc_req(buf, (size_t)n, &h, op, m);
  int rc = send_all(c, buf, (size_t)n, err);
  if (buf != small) free(buf);
  if (!rc && rid) *rid = h.request_id;
  return rc;
}

/* Requests that go through the server's job queue: their answer may wait behind other
 * clients' computations for any time, so they are not bounded by io_timeout_ms. */
static int is_compute(uint8_t op) { return (sm_proto_op_flags(op) & SM_OPF_QUEUED) != 0; }

/* Waits for the next frame of a queued request. deadline: the caller's limit (-1 none).
 * A queued request is not a dead connection: after io_timeout_ms without any frame the
 * client sends a PING (the server answers it at once, without queuing it); the wait goes
 * on while such probes are answered and fails with ETIMEOUT when one is not answered
 * within io_timeout_ms, or when the deadline passes. Probe answers are consumed by
 * side_frame. Silence counts from c->last_rx_ms: the last frame, or the start of the
 * caller's wait (call, sm_client_batch). */
static int next_frame_live(sm_client *c, int64_t deadline, int watch_stop, sm_proto_frame *f,
                           sm_client_error *err) {
  int io = c->o.io_timeout_ms;
  for (;;) {
    int64_t w = deadline;
    if (io > 0 && (w < 0 || c->last_rx_ms + io < w)) w = c->last_rx_ms + io;
    int rc = next_frame(c, w, watch_stop, f, err);
    if (rc != SM_CLIENT_ETIMEOUT) return rc;
    if (deadline >= 0 && now_ms() >= deadline)
      return seterr(err, SM_CLIENT_ETIMEOUT, "no answer from the server within the time limit "
                    "(%d ms)", c->o.compute_timeout_ms);
    if (c->probe_rid) { /* the connection is dead: nothing will come */
      c->lost = 1;
      return broken(c, seterr(err, SM_CLIENT_ETIMEOUT, "the server stopped answering (no answer "
                              "to a PING within %d ms)", io));
    }
    if (c->goaway) { /* draining: it answers or closes within its drain time */
      c->last_rx_ms = now_ms();
      continue;
    }
    sm_proto_ping m = {0};
    uint32_t rid;
    int src = send_req(c, SM_OP_PING, &m, &rid, err);
    if (src) return src;
    c->probe_rid = rid;
    c->last_rx_ms = now_ms();
  }
}

/* One request, one answer: *f is the OK response body (view valid until the next call). */
static int call_once(sm_client *c, uint8_t op, const void *m, sm_proto_frame *f,
                     sm_client_error *err) {
  uint32_t rid;
  clear_err(err);
  int rc = send_req(c, op, m, &rid, err);
  if (rc) return rc;
  int compute = is_compute(op);
  c->last_rx_ms = now_ms();
  int64_t dl = deadline_in(compute ? c->o.compute_timeout_ms : c->o.io_timeout_ms);
  for (;;) {
    /* a single call that times out or is stopped leaves an answer in flight: closing is
     * the only way to keep the stream in step (and cancels the work server-side) */
    rc = compute ? next_frame_live(c, dl, 1, f, err) : next_frame(c, dl, 1, f, err);
    if (rc) return c->open ? broken(c, rc) : rc;
    int s = side_frame(c, f, err);
    if (s < 0) return s;
    if (s) continue;
    if (f->h.request_id != rid || (f->h.flags & SM_PROTO_F_MORE))
      return broken(c, seterr(err, SM_CLIENT_EPROTO, "answer for request %u while waiting for %u",
                              f->h.request_id, rid));
    if (f->h.status != SM_ST_OK) return status_error(c, f, err);
    if (f->h.opcode != op)
      return broken(c, seterr(err, SM_CLIENT_EPROTO, "%s answer to a %s request",
                              sm_proto_op_name(f->h.opcode), sm_proto_op_name(op)));
    return 0;
  }
}

/* 1 when the connection was lost in a way a new connection may cure, or is open but
 * draining (graceful GOAWAY), and the options allow connecting again. A connection the
 * client closed itself (a compute_timeout_ms, a protocol violation) is neither. */
static int may_relink(const sm_client *c) {
  return c->addr && c->o.reconnect_tries > 0 && (c->lost || (c->goaway && c->open)) &&
         !(c->o.stop && *c->o.stop);
}

/* Sleeps ms milliseconds in slices that watch the stop flag: 0, or ECANCELED. */
static int nap(const sm_client *c, int64_t ms, sm_client_error *err) {
  int64_t end = now_ms() + ms;
  for (int64_t left = ms; left > 0; left = end - now_ms()) {
    if (c->o.stop && *c->o.stop) return seterr(err, SM_CLIENT_ECANCELED, "stopped by the caller");
    int64_t d = left > 100 ? 100 : left;
    struct timespec ts = {(time_t)(d / 1000), (long)(d % 1000) * 1000000L};
    nanosleep(&ts, NULL);
  }
  return 0;
}

/* After a loss (may_relink): up to reconnect_tries connection attempts, the first after the
 * server's hint (if any), then waits doubling from reconnect_backoff_ms, at most 2 s, each
 * drawn in [w/2, w] so that many clients cut at once do not come back at once. err holds
 * the loss on entry; on failure it says both what was lost and why connecting failed. */
static int relink(sm_client *c, sm_client_error *err) {
  char why[sizeof err->msg];
  snprintf(why, sizeof why, "%s", err && err->msg[0] ? err->msg : "connection lost");
  int64_t w = c->o.reconnect_backoff_ms > 0 ? c->o.reconnect_backoff_ms : 100;
  int64_t hint = c->retry_hint_ms;
  sm_client_error e;
  memset(&e, 0, sizeof e);
  for (int t = 0; t < c->o.reconnect_tries; t++) {
    int64_t d = 0;
    if (t > 0) {
      c->rng ^= c->rng << 13, c->rng ^= c->rng >> 17, c->rng ^= c->rng << 5;
      d = w / 2 + (int64_t)(c->rng % (uint32_t)(w / 2 + 1));
      w = w * 2 > 2000 ? 2000 : w * 2;
    }
    if (d < hint) d = hint > 2000 ? 2000 : hint;
    if (nap(c, d, err)) return SM_CLIENT_ECANCELED;
    if (!sm_client_reconnect(c, &e)) return 0;
    hint = e.retry_after_ms; /* TOO_MANY_CONNECTIONS says how long to wait */
  }
  c->lost = 0; /* this loss was handled: a later call fails until the caller reconnects */
  int code = e.code ? e.code : SM_CLIENT_ECONNECT;
  return seterr(err, code, "%.150s; connecting again failed %d times, the last: %.150s", why,
                c->o.reconnect_tries, e.msg);
}

/* call_once, and for an idempotent request whose connection was lost before its answer
 * came (or that was refused as SHUTTING_DOWN by a draining server): connect again and
 * resend, at most SM_CLIENT_MAX_LOSSES sends in all. */
static int call(sm_client *c, uint8_t op, const void *m, sm_proto_frame *f, sm_client_error *err) {
  sm_client_error local;
  if (!err) err = &local;
  int idem = (sm_proto_op_flags(op) & SM_OPF_IDEMPOTENT) != 0;
  if (idem && !c->open && may_relink(c)) { /* lost by an earlier call */
    int rc = relink(c, err);
    if (rc) return rc;
  }
  for (int sends = 1;; sends++) {
    int rc = call_once(c, op, m, f, err);
    if (rc == SM_CLIENT_ESTATUS && err->status == SM_ST_SHUTTING_DOWN) c->goaway = 1;
    int cut = c->lost || rc == SM_CLIENT_ECLOSED /* refused by send_req after GOAWAY */ ||
              (rc == SM_CLIENT_ESTATUS && err->status == SM_ST_SHUTTING_DOWN);
    if (!rc || !idem || !cut || !may_relink(c)) return rc;
    if (sends >= SM_CLIENT_MAX_LOSSES) {
      c->lost = 0;
      char m0[sizeof err->msg];
      snprintf(m0, sizeof m0, "%s", err->msg);
      snprintf(err->msg, sizeof err->msg, "%.200s (sent %d times, the connection was lost each time)",
               m0, sends);
      return rc;
    }
    if ((rc = relink(c, err))) return rc;
  }
}

static int bad_body(sm_client *c, uint8_t op, int prc, sm_client_error *err) {
  return broken(c, seterr(err, SM_CLIENT_EPROTO, "%s answer: %s", sm_proto_op_name(op), sm_proto_strerror(prc)));
}

/* ---- connection ---- */
static int hello(sm_client *c, sm_client_error *err) {
  sm_proto_hello_req m = {0};
  m.min_version = SM_PROTO_VERSION_MIN;
  m.max_version = SM_PROTO_VERSION_MAX;
  m.max_response = c->o.max_response;
  memcpy(m.affinity, c->affinity, SM_PROTO_ID_LEN);
  m.token = c->o.token_len ? c->token : NULL;
  m.token_len = (uint16_t)c->o.token_len;
  sm_proto_frame f;
  int rc = call(c, SM_OP_HELLO, &m, &f, err);
  if (rc) return rc;
  rc = sm_proto_dec_hello_resp(f.body, f.body_len, &c->hello);
  if (rc) return bad_body(c, SM_OP_HELLO, rc, err);
  if (c->hello.version < SM_PROTO_VERSION_MIN || c->hello.version > SM_PROTO_VERSION_MAX)
    return broken(c, seterr(err, SM_CLIENT_EPROTO, "server chose version %u", c->hello.version));
  c->version = (uint8_t)c->hello.version;
  return 0;
}

int sm_client_connect_fd(int fd, const sm_client_opts *opts, sm_client **out,
                         sm_client_error *err) {
  clear_err(err);
  if (out) *out = NULL;
  sm_client_opts def;
  if (!opts) sm_client_opts_default(&def), opts = &def;
  if (fd < 0 || !out || opts->token_len > SM_PROTO_MAX_TOKEN || (opts->token_len && !opts->token)) {
    if (fd >= 0) close(fd);
    return seterr(err, SM_CLIENT_EINVAL, "connect: bad fd, output or token (at most %u bytes)", SM_PROTO_MAX_TOKEN);
  }
  sm_client *c = calloc(1, sizeof *c);
  if (!c) {
    close(fd);
    return seterr(err, SM_CLIENT_ENOMEM, "client");
  }
  c->fd = fd;
  c->open = 1;
  c->o = *opts;
  c->rng = (uint32_t)now_ms() ^ (uint32_t)getpid() ^ 0x9e3779b9u;
  if (!c->rng) c->rng = 1;
  if (opts->token_len) memcpy(c->token, opts->token, opts->token_len);
  c->o.token = NULL;
  if (opts->affinity) memcpy(c->affinity, opts->affinity, SM_PROTO_ID_LEN);
  c->o.affinity = NULL;
  /* The HELLO answer is tiny; afterwards our own max_response (+ a CRC trailer) bounds a
   * frame, else the protocol's 2^32 - 1. */
  c->parse_limit = SM_PROTO_HELLO_MAX_PAYLOAD;
  int fl = fcntl(fd, F_GETFL);
  if (fl < 0 || fcntl(fd, F_SETFL, fl | O_NONBLOCK) < 0) {
    seterr(err, SM_CLIENT_EIO, "fcntl: %s", strerror(errno));
    sm_client_close(c);
    return SM_CLIENT_EIO;
  }
  int rc = hello(c, err);
  if (rc) {
    sm_client_close(c);
    return rc;
  }
  c->parse_limit = opts->max_response && opts->max_response <= UINT32_MAX - 4 ? opts->max_response + 4 : UINT32_MAX;
  *out = c;
  return 0;
}

static int connect_to(const struct sockaddr *sa, socklen_t len, int timeout_ms, int *fd_out,
                      sm_client_error *err) {
  int fd = socket(sa->sa_family, SOCK_STREAM, 0);
  if (fd < 0) return seterr(err, SM_CLIENT_ECONNECT, "socket: %s", strerror(errno));
  int fl = fcntl(fd, F_GETFL);
  fcntl(fd, F_SETFL, fl | O_NONBLOCK);
  int r = connect(fd, sa, len);
  if (r < 0 && errno != EINPROGRESS && errno != EINTR) {
    int e = errno;
    close(fd);
    return seterr(err, SM_CLIENT_ECONNECT, "connect: %s", strerror(e));
  }
  if (r < 0) {
    struct pollfd pf = {fd, POLLOUT, 0};
    int64_t dl = deadline_in(timeout_ms);
    for (;;) {
      int tmo = dl < 0 ? -1 : (int)(dl - now_ms() > 0 ? dl - now_ms() : 0);
      r = poll(&pf, 1, tmo);
      if (r < 0 && errno == EINTR) continue;
      break;
    }
    int so = 0;
    socklen_t sl = sizeof so;
    if (r == 0) so = ETIMEDOUT;
    else if (r < 0) so = errno;
    else if (getsockopt(fd, SOL_SOCKET, SO_ERROR, &so, &sl) < 0) so = errno;
    if (so) {
      close(fd);
      return seterr(err, r == 0 ? SM_CLIENT_ETIMEOUT : SM_CLIENT_ECONNECT, "connect: %s", strerror(so));
    }
  }
  if (sa->sa_family != AF_UNIX) {
    int one = 1;
    setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
  }
  *fd_out = fd;
  return 0;
}

/* A connected socket to addr (not yet HELLO'd): the fd, or a negative SM_CLIENT_E*. */
static int open_socket(const char *addr, int connect_timeout_ms, sm_client_error *err) {
  char host[256];
  uint16_t port;
  int rc = sm_client_parse_addr(addr, host, sizeof host, &port, err);
  if (rc) return rc;
  int fd = -1;
  if (!port) {
    struct sockaddr_un su;
    memset(&su, 0, sizeof su);
    su.sun_family = AF_UNIX;
    memcpy(su.sun_path, host, strlen(host) + 1);
    rc = connect_to((struct sockaddr *)&su, sizeof su, connect_timeout_ms, &fd, err);
  } else {
    struct addrinfo hints, *res = NULL;
    memset(&hints, 0, sizeof hints);
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    char ps[8];
    snprintf(ps, sizeof ps, "%u", port);
    int g = getaddrinfo(host, ps, &hints, &res);
    if (g) return seterr(err, SM_CLIENT_EADDR, "%s: %s", host, gai_strerror(g));
    rc = SM_CLIENT_ECONNECT;
    for (struct addrinfo *ai = res; ai && rc; ai = ai->ai_next)
      rc = connect_to(ai->ai_addr, ai->ai_addrlen, connect_timeout_ms, &fd, err);
    freeaddrinfo(res);
  }
  if (rc) {
    if (err) {
      char m[sizeof err->msg];
      snprintf(m, sizeof m, "%.60s: %.250s", addr, err->msg);
      memcpy(err->msg, m, sizeof m);
    }
    return rc;
  }
  return fd;
}

int sm_client_connect(const char *addr, const sm_client_opts *opts, sm_client **out,
                      sm_client_error *err) {
  clear_err(err);
  if (out) *out = NULL;
  if (!out) return seterr(err, SM_CLIENT_EINVAL, "connect: NULL output");
  sm_client_opts def;
  if (!opts) sm_client_opts_default(&def), opts = &def;
  char *copy = strdup(addr ? addr : "");
  if (!copy) return seterr(err, SM_CLIENT_ENOMEM, "address");
  int fd = open_socket(addr, opts->connect_timeout_ms, err);
  int rc = fd < 0 ? fd : sm_client_connect_fd(fd, opts, out, err);
  if (rc) {
    free(copy);
    return rc;
  }
  (*out)->addr = copy;
  return 0;
}

int sm_client_reconnect(sm_client *c, sm_client_error *err) {
  clear_err(err);
  if (!c) return seterr(err, SM_CLIENT_EINVAL, "reconnect: NULL client");
  if (!c->addr) return seterr(err, SM_CLIENT_EINVAL, "reconnect: the client was made from a socket, it has no address");
  if (c->fd >= 0) close(c->fd);
  c->fd = -1;
  c->open = c->goaway = c->lost = 0;
  c->retry_hint_ms = 0;
  int fd = open_socket(c->addr, c->o.connect_timeout_ms, err);
  if (fd < 0) return fd;
  int fl = fcntl(fd, F_GETFL);
  if (fl < 0 || fcntl(fd, F_SETFL, fl | O_NONBLOCK) < 0) {
    close(fd);
    return seterr(err, SM_CLIENT_EIO, "fcntl: %s", strerror(errno));
  }
  c->fd = fd;
  c->open = 1;
  c->rlen = c->consume = 0;
  c->n_cancels = 0;
  c->probe_rid = 0;
  c->version = 0;
  memset(&c->hello, 0, sizeof c->hello);
  c->parse_limit = SM_PROTO_HELLO_MAX_PAYLOAD;
  int rc = hello(c, err);
  if (rc) {
    broken(c, rc);
    return rc;
  }
  c->parse_limit = c->o.max_response && c->o.max_response <= UINT32_MAX - 4 ? c->o.max_response + 4 : UINT32_MAX;
  c->reconnects++;
  return 0;
}

unsigned sm_client_reconnects(const sm_client *c) { return c ? c->reconnects : 0; }

const sm_proto_hello_resp *sm_client_limits(const sm_client *c) { return &c->hello; }
int sm_client_is_open(const sm_client *c) { return c && c->open; }

void sm_client_close(sm_client *c) {
  if (!c) return;
  if (c->fd >= 0) close(c->fd);
  free(c->rbuf);
  free(c->cancels);
  free(c->addr);
  free(c);
}

/* ---- ids, files ---- */
void sm_client_shape_id(const uint8_t *draco, size_t len, uint8_t id[SM_PROTO_ID_LEN]) {
  sm_sha256(draco, len, id);
}

void sm_client_id_to_hex(const uint8_t id[SM_PROTO_ID_LEN], char hex[SM_CLIENT_ID_HEX_LEN + 1]) {
  static const char d[] = "0123456789abcdef";
  for (int i = 0; i < SM_PROTO_ID_LEN; i++) {
    hex[2 * i] = d[id[i] >> 4];
    hex[2 * i + 1] = d[id[i] & 15];
  }
  hex[SM_CLIENT_ID_HEX_LEN] = 0;
}

static int hexval(char ch) {
  if (ch >= '0' && ch <= '9') return ch - '0';
  if (ch >= 'a' && ch <= 'f') return ch - 'a' + 10;
  if (ch >= 'A' && ch <= 'F') return ch - 'A' + 10;
  return -1;
}

int sm_client_id_from_hex(const char *hex, uint8_t id[SM_PROTO_ID_LEN]) {
  if (!hex || strlen(hex) != SM_CLIENT_ID_HEX_LEN) return SM_CLIENT_EINVAL;
  uint8_t t[SM_PROTO_ID_LEN];
  for (int i = 0; i < SM_PROTO_ID_LEN; i++) {
    int a = hexval(hex[2 * i]), b = hexval(hex[2 * i + 1]);
    if (a < 0 || b < 0) return SM_CLIENT_EINVAL;
    t[i] = (uint8_t)(a << 4 | b);
  }
  memcpy(id, t, sizeof t);
  return 0;
}

static int ends_with_ci(const char *s, const char *suf) {
  size_t n = strlen(s), m = strlen(suf);
  if (n < m) return 0;
  for (size_t i = 0; i < m; i++) {
    char a = s[n - m + i];
    if (a >= 'A' && a <= 'Z') a = (char)(a - 'A' + 'a');
    if (a != suf[i]) return 0;
  }
  return 1;
}

int sm_client_file_draco(const char *path, uint8_t **buf, size_t *len, sm_client_error *err) {
  sm_error e;
  clear_err(err);
  if (!path || !buf || !len) return seterr(err, SM_CLIENT_EINVAL, "file_draco: NULL argument");
  *buf = NULL;
  *len = 0;
  if (ends_with_ci(path, ".drc")) {
    /* As is: the server decodes it as sm_mesh_read_file does locally, same numbering. */
    if (sm_read_file_bytes(path, (size_t)UINT32_MAX - 64, buf, len, &e))
      return seterr(err, SM_CLIENT_EMESH, "%s", e.msg);
    if (!*len) {
      free(*buf);
      *buf = NULL;
      return seterr(err, SM_CLIENT_EMESH, "%s: empty file", path);
    }
    return 0;
  }
  sm_mesh *m = NULL;
  /* The core's messages already say what failed and, for I/O, name the file. */
  if (sm_mesh_read_file(path, NULL, &m, &e)) return seterr(err, SM_CLIENT_EMESH, "%s", e.msg);
  int rc = sm_draco_encode(m, 0, buf, len, &e);
  sm_mesh_destroy(m);
  if (rc) return seterr(err, SM_CLIENT_EMESH, "%s", e.msg);
  return 0;
}

/* ---- simple requests ---- */
int sm_client_ping(sm_client *c, double *rtt_s, sm_client_error *err) {
  if (!c) return seterr(err, SM_CLIENT_EINVAL, "NULL client");
  struct timespec t0, t1;
  clock_gettime(CLOCK_MONOTONIC, &t0);
  sm_proto_ping p = {(uint64_t)t0.tv_sec * 1000000000u + (uint64_t)t0.tv_nsec}, q;
  sm_proto_frame f;
  int rc = call(c, SM_OP_PING, &p, &f, err);
  if (rc) return rc;
  if ((rc = sm_proto_dec_ping(f.body, f.body_len, &q))) return bad_body(c, SM_OP_PING, rc, err);
  if (q.opaque != p.opaque)
    return broken(c, seterr(err, SM_CLIENT_EPROTO, "PING answer does not echo the request"));
  clock_gettime(CLOCK_MONOTONIC, &t1);
  if (rtt_s) *rtt_s = (double)(t1.tv_sec - t0.tv_sec) + 1e-9 * (double)(t1.tv_nsec - t0.tv_nsec);
  return 0;
}

int sm_client_stats(sm_client *c, sm_proto_stat **stats, uint32_t *n, sm_client_error *err) {
  if (!c || !stats || !n) return seterr(err, SM_CLIENT_EINVAL, "stats: NULL argument");
  *stats = NULL;
  *n = 0;
  sm_proto_frame f;
  sm_proto_stats_resp s;
  int rc = call(c, SM_OP_STATS, NULL, &f, err);
  if (rc) return rc;
  if ((rc = sm_proto_dec_stats_resp(f.body, f.body_len, &s))) return bad_body(c, SM_OP_STATS, rc, err);
  sm_proto_stat *v = malloc((s.count ? s.count : 1) * sizeof *v);
  if (!v) return seterr(err, SM_CLIENT_ENOMEM, "%u stats", s.count);
  for (uint32_t i = 0; i < s.count; i++)
    if ((rc = sm_proto_stat_at(&s, i, &v[i]))) {
      free(v);
      return bad_body(c, SM_OP_STATS, rc, err);
    }
  *stats = v;
  *n = s.count;
  return 0;
}

int sm_client_put(sm_client *c, const uint8_t *draco, size_t len, int prepare,
                  uint8_t id_out[SM_PROTO_ID_LEN], sm_proto_put_resp *resp,
                  sm_client_error *err) {
  if (!c || !draco || !len) return seterr(err, SM_CLIENT_EINVAL, "put: no Draco bytes");
  if (len > (size_t)UINT32_MAX - 64) return seterr(err, SM_CLIENT_ELIMIT, "put: %zu bytes do not fit a frame", len);
  sm_proto_put_req m;
  memset(&m, 0, sizeof m);
  sm_client_shape_id(draco, len, m.id);
  m.flags = prepare ? SM_PUT_F_PREPARE : 0;
  m.draco = draco;
  m.draco_len = (uint32_t)len;
  sm_proto_frame f;
  sm_proto_put_resp r;
  int rc = call(c, SM_OP_PUT_SHAPE, &m, &f, err);
  if (rc) return rc;
  if ((rc = sm_proto_dec_put_resp(f.body, f.body_len, &r))) return bad_body(c, SM_OP_PUT_SHAPE, rc, err);
  if (memcmp(r.id, m.id, SM_PROTO_ID_LEN))
    return broken(c, seterr(err, SM_CLIENT_EPROTO, "PUT_SHAPE answer names another id"));
  if (id_out) memcpy(id_out, m.id, SM_PROTO_ID_LEN);
  if (resp) *resp = r;
  return 0;
}

int sm_client_put_file(sm_client *c, const char *path, int prepare,
                       uint8_t id_out[SM_PROTO_ID_LEN], sm_proto_put_resp *resp,
                       sm_client_error *err) {
  uint8_t *buf;
  size_t len;
  if (!c) return seterr(err, SM_CLIENT_EINVAL, "NULL client");
  int rc = sm_client_file_draco(path, &buf, &len, err);
  if (rc) return rc;
  rc = sm_client_put(c, buf, len, prepare, id_out, resp, err);
  free(buf);
  return rc;
}

int sm_client_has(sm_client *c, const uint8_t id[SM_PROTO_ID_LEN], sm_proto_has_resp *resp,
                  sm_client_error *err) {
  if (!c || !id || !resp) return seterr(err, SM_CLIENT_EINVAL, "has: NULL argument");
  sm_proto_id_req m;
  memcpy(m.id, id, SM_PROTO_ID_LEN);
  sm_proto_frame f;
  int rc = call(c, SM_OP_HAS_SHAPE, &m, &f, err);
  if (rc) return rc;
  if ((rc = sm_proto_dec_has_resp(f.body, f.body_len, resp))) return bad_body(c, SM_OP_HAS_SHAPE, rc, err);
  return 0;
}

int sm_client_drop(sm_client *c, const uint8_t id[SM_PROTO_ID_LEN], sm_client_error *err) {
  if (!c || !id) return seterr(err, SM_CLIENT_EINVAL, "drop: NULL argument");
  sm_proto_id_req m;
  memcpy(m.id, id, SM_PROTO_ID_LEN);
  sm_proto_frame f;
  int rc = call(c, SM_OP_DROP_SHAPE, &m, &f, err);
  if (rc) return rc;
  if ((rc = sm_proto_dec_empty(f.body, f.body_len))) return bad_body(c, SM_OP_DROP_SHAPE, rc, err);
  return 0;
}

static int fill_prepare(sm_proto_prepare_req *m, const uint8_t *id, int k_lb, int k_elastic,
                        double eta, sm_client_error *err) {
  if (k_lb < 0 || k_lb > 65535 || k_elastic < 0 || k_elastic > 65535 || !(eta == 0 || (eta > 0 && isfinite(eta))))
    return seterr(err, SM_CLIENT_EINVAL, "prepare: k must be 0..65535, eta 0 or finite > 0");
  memset(m, 0, sizeof *m);
  memcpy(m->id, id, SM_PROTO_ID_LEN);
  m->k_lb = (uint16_t)k_lb;
  m->k_elastic = (uint16_t)k_elastic;
  m->eta = eta;
  return 0;
}

int sm_client_prepare(sm_client *c, const uint8_t id[SM_PROTO_ID_LEN], int k_lb, int k_elastic,
                      double eta, sm_proto_prepare_resp *resp, sm_client_error *err) {
  if (!c || !id) return seterr(err, SM_CLIENT_EINVAL, "prepare: NULL argument");
  sm_proto_prepare_req m;
  sm_proto_prepare_resp r;
  int rc = fill_prepare(&m, id, k_lb, k_elastic, eta, err);
  if (rc) return rc;
  sm_proto_frame f;
  if ((rc = call(c, SM_OP_PREPARE, &m, &f, err))) return rc;
  if ((rc = sm_proto_dec_prepare_resp(f.body, f.body_len, &r))) return bad_body(c, SM_OP_PREPARE, rc, err);
  if (resp) *resp = r;
  return 0;
}

/* ---- MATCH / DISTANCE ---- */
void sm_client_match_opts_default(sm_client_match_opts *o) {
  memset(o, 0, sizeof *o);
  o->sinkhorn_levels = -1;
  o->multi_start = -1;
}

void sm_client_match_result_free(sm_client_match_result *r) {
  if (!r) return;
  free(r->map_xy);
  free(r->map_yx);
  free(r->fmap);
  r->map_xy = r->map_yx = NULL;
  r->fmap = NULL;
}

static int u16ok(int v) { return v >= 0 && v <= 65535; }

static int fill_match(uint8_t op, const uint8_t *x, const uint8_t *y, const sm_client_match_opts *o,
                      sm_proto_match_req *m, sm_client_error *err) {
  sm_client_match_opts def;
  if (!o) sm_client_match_opts_default(&def), o = &def;
  memset(m, 0, sizeof *m);
  memcpy(m->x, x, SM_PROTO_ID_LEN);
  memcpy(m->y, y, SM_PROTO_ID_LEN);
  if (o->basis < 0 || o->basis > 3 || o->init < 0 || o->init > 2)
    return seterr(err, SM_CLIENT_EINVAL, "basis must be 0..3, init 0..2");
  if (!u16ok(o->k0) || !u16ok(o->k1) || !u16ok(o->step) || (o->k0 && o->k1 && o->k0 > o->k1))
    return seterr(err, SM_CLIENT_EINVAL, "k0=%d, k1=%d, step=%d: each 0..65535 and k0 <= k1", o->k0, o->k1, o->step);
  if (o->sinkhorn_levels < -1 || o->sinkhorn_levels > 65535 || o->multi_start < -1 || o->multi_start > 1)
    return seterr(err, SM_CLIENT_EINVAL, "sinkhorn_levels must be -1..65535, multi_start -1, 0 or 1");
  if (!(o->eta == 0 || (o->eta > 0 && isfinite(o->eta))))
    return seterr(err, SM_CLIENT_EINVAL, "eta must be 0 (default) or finite > 0");
  if ((o->n_landmarks && !o->landmarks) || (o->n_init_map && !o->init_map) || o->n_landmarks > UINT32_MAX / 2)
    return seterr(err, SM_CLIENT_EINVAL, "landmarks or init_map missing");
  for (uint32_t i = 0; i < 2 * o->n_landmarks; i++)
    if (o->landmarks[i] < 0) return seterr(err, SM_CLIENT_EINVAL, "landmark %u has a negative vertex", i / 2);
  for (uint32_t i = 0; i < o->n_init_map; i++)
    if (o->init_map[i] < -1) return seterr(err, SM_CLIENT_EINVAL, "init_map[%u] = %d < -1", i, o->init_map[i]);
  /* DISTANCE has MATCH's layout: basis, init and the schedule travel as given; of the
   * flags only the start ones apply (the want_* are MATCH's and are not sent). */
  m->basis = (uint8_t)o->basis;
  m->init = (uint8_t)o->init;
  m->k0 = (uint16_t)o->k0;
  m->k1 = (uint16_t)o->k1;
  m->step = (uint16_t)o->step;
  m->eta = o->eta;
  m->deadline_ms = o->deadline_ms;
  uint16_t fl = 0;
  if (op == SM_OP_MATCH) {
    if (o->want_yx) fl |= SM_MATCH_F_WANT_YX;
    if (o->want_fmap) fl |= SM_MATCH_F_WANT_FMAP;
    if (o->want_distance) fl |= SM_MATCH_F_WANT_DISTANCE;
  }
  if (o->multi_start == 1) fl |= SM_MATCH_F_MULTI_START;
  if (o->multi_start == 0) fl |= SM_MATCH_F_SINGLE_START;
  if (o->multires < 0 || o->multires > 2)
    return seterr(err, SM_CLIENT_EINVAL, "multires must be 0 (server default), 1 (on) or 2 (off)");
  if (op == SM_OP_MATCH && o->multires == 1) fl |= SM_MATCH_F_MULTIRES;
  if (op == SM_OP_MATCH && o->multires == 2) fl |= SM_MATCH_F_DIRECT;
  if (o->sinkhorn_levels >= 0) {
    fl |= SM_MATCH_F_SINKHORN_LEVELS;
    m->sinkhorn_levels = (uint16_t)o->sinkhorn_levels;
  }
  m->flags = fl;
  m->landmarks = (sm_proto_i32s){o->landmarks, NULL, 2 * o->n_landmarks};
  m->init_map = (sm_proto_i32s){o->init_map, NULL, o->n_init_map};
  return 0;
}

static int copy_match(const sm_client *c, const sm_proto_match_resp *p, sm_client_match_result *r,
                      sm_client_error *err) {
  memset(r, 0, sizeof *r);
  r->nx = p->map_xy.count;
  r->ny = p->map_yx.count;
  r->kC = p->kC;
  r->map_xy = malloc((r->nx ? r->nx : 1) * sizeof *r->map_xy);
  r->map_yx = r->ny ? malloc(r->ny * sizeof *r->map_yx) : NULL;
  r->fmap = p->fmap.count ? malloc(p->fmap.count * sizeof *r->fmap) : NULL;
  if (!r->map_xy || (r->ny && !r->map_yx) || (p->fmap.count && !r->fmap)) {
    sm_client_match_result_free(r);
    return seterr(err, SM_CLIENT_ENOMEM, "match result (%u + %u vertices)", r->nx, r->ny);
  }
  for (uint32_t i = 0; i < r->nx; i++) r->map_xy[i] = sm_proto_i32_at(&p->map_xy, i);
  for (uint32_t i = 0; i < r->ny; i++) r->map_yx[i] = sm_proto_i32_at(&p->map_yx, i);
  for (uint32_t i = 0; i < p->fmap.count; i++) r->fmap[i] = sm_proto_f64_at(&p->fmap, i);
  r->init_used = p->init_used;
  r->flipped = (p->flags & SM_MATCH_R_FLIPPED) != 0;
  r->has_distance = (p->flags & SM_MATCH_R_HAS_DISTANCE) != 0;
  r->orientation = p->orientation;
  r->dirichlet = p->dirichlet;
  r->has_confidence = c->version >= SM_PROTO_VERSION_CONFIDENCE;
  r->confidence = p->confidence; /* the decoder checked it, or set NaN for version 1 */
  r->dist = p->dist;
  r->t_prepare = 1e-6 * (double)p->t_prepare_us;
  r->t_init = 1e-6 * (double)p->t_init_us;
  r->t_refine = 1e-6 * (double)p->t_refine_us;
  r->t_distance = 1e-6 * (double)p->t_distance_us;
  r->t_total = 1e-6 * (double)p->t_total_us;
  return 0;
}

int sm_client_match(sm_client *c, const uint8_t x[SM_PROTO_ID_LEN],
                    const uint8_t y[SM_PROTO_ID_LEN], const sm_client_match_opts *o,
                    sm_client_match_result *r, sm_client_error *err) {
  if (r) memset(r, 0, sizeof *r);
  if (!c || !x || !y || !r) return seterr(err, SM_CLIENT_EINVAL, "match: NULL argument");
  sm_proto_match_req m;
  sm_proto_match_resp p;
  sm_proto_frame f;
  int rc = fill_match(SM_OP_MATCH, x, y, o, &m, err);
  if (rc || (rc = call(c, SM_OP_MATCH, &m, &f, err))) return rc;
  if ((rc = sm_proto_dec_match_resp(c->version, f.body, f.body_len, &p)))
    return bad_body(c, SM_OP_MATCH, rc, err);
  if (o && o->n_init_map && p.map_xy.count != o->n_init_map)
    return broken(c, seterr(err, SM_CLIENT_EPROTO, "map of %u entries for an init_map of %u", p.map_xy.count, o->n_init_map));
  return copy_match(c, &p, r, err);
}

int sm_client_distance(sm_client *c, const uint8_t x[SM_PROTO_ID_LEN],
                       const uint8_t y[SM_PROTO_ID_LEN], const sm_client_match_opts *o,
                       sm_proto_dist *d, double *t_total_s, sm_client_error *err) {
  if (!c || !x || !y || !d) return seterr(err, SM_CLIENT_EINVAL, "distance: NULL argument");
  sm_proto_match_req m;
  sm_proto_distance_resp p;
  sm_proto_frame f;
  int rc = fill_match(SM_OP_DISTANCE, x, y, o, &m, err);
  if (rc || (rc = call(c, SM_OP_DISTANCE, &m, &f, err))) return rc;
  if ((rc = sm_proto_dec_distance_resp(f.body, f.body_len, &p))) return bad_body(c, SM_OP_DISTANCE, rc, err);
  *d = p.dist;
  if (t_total_s) *t_total_s = 1e-6 * (double)p.t_total_us;
  return 0;
}

/* ---- QUERY ---- */
static int fill_query(const uint8_t *id, int k, int mode, const uint8_t *cand, uint32_t n_cand,
                      uint32_t deadline_ms, sm_proto_query_req *m, sm_client_error *err) {
  if (k < 1 || k > 65535 || mode < 0 || mode > 2 || (n_cand && !cand))
    return seterr(err, SM_CLIENT_EINVAL, "query: k must be 1..65535, mode 0..2");
  memset(m, 0, sizeof *m);
  memcpy(m->id, id, SM_PROTO_ID_LEN);
  m->k = (uint16_t)k;
  m->mode = (uint8_t)mode;
  m->deadline_ms = deadline_ms;
  m->candidates = cand;
  m->n_candidates = n_cand;
  return 0;
}

static int copy_hits(const sm_proto_query_resp *q, sm_client_hit **hits, uint32_t *n, sm_client_error *err) {
  sm_client_hit *h = malloc((q->count ? q->count : 1) * sizeof *h);
  if (!h) return seterr(err, SM_CLIENT_ENOMEM, "%u hits", q->count);
  for (uint32_t i = 0; i < q->count; i++) {
    sm_proto_hit ph;
    sm_proto_hit_at(q, i, &ph);
    memcpy(h[i].id, ph.id, SM_PROTO_ID_LEN);
    h[i].distance = ph.distance;
  }
  *hits = h;
  *n = q->count;
  return 0;
}

int sm_client_query(sm_client *c, const uint8_t id[SM_PROTO_ID_LEN], int k, int mode,
                    const uint8_t *cand, uint32_t n_cand, uint32_t deadline_ms,
                    sm_client_hit **hits, uint32_t *n_hits, uint32_t *n_considered,
                    sm_client_error *err) {
  if (!c || !id || !hits || !n_hits) return seterr(err, SM_CLIENT_EINVAL, "query: NULL argument");
  *hits = NULL;
  *n_hits = 0;
  sm_proto_query_req m;
  sm_proto_query_resp q;
  sm_proto_frame f;
  int rc = fill_query(id, k, mode, cand, n_cand, deadline_ms, &m, err);
  if (rc || (rc = call(c, SM_OP_QUERY, &m, &f, err))) return rc;
  if ((rc = sm_proto_dec_query_resp(f.body, f.body_len, &q))) return bad_body(c, SM_OP_QUERY, rc, err);
  if (q.count > (uint32_t)k) return broken(c, seterr(err, SM_CLIENT_EPROTO, "QUERY answered %u hits for k = %d", q.count, k));
  if (n_considered) *n_considered = q.n_considered;
  return copy_hits(&q, hits, n_hits, err);
}

/* ---- CANCEL ---- */
int sm_client_cancel(sm_client *c, uint32_t request_id, sm_client_error *err) {
  if (!c || !request_id) return seterr(err, SM_CLIENT_EINVAL, "cancel: request id 0");
  if (c->n_cancels == c->cap_cancels) {
    size_t nc = c->cap_cancels ? 2 * c->cap_cancels : 8;
    uint32_t *v = realloc(c->cancels, nc * sizeof *v);
    if (!v) return seterr(err, SM_CLIENT_ENOMEM, "cancel list");
    c->cancels = v;
    c->cap_cancels = nc;
  }
  sm_proto_cancel_req m = {request_id};
  uint32_t rid;
  int rc = send_req(c, SM_OP_CANCEL, &m, &rid, err);
  if (!rc) c->cancels[c->n_cancels++] = rid;
  return rc;
}

/* ---- batch ---- */
enum { ST_PENDING = 0, ST_FLIGHT, ST_DONE };
typedef struct bitem {
  uint32_t rid;
  int state, attempts;
  int losses; /* connections lost (or drained) while it was in flight */
  int cut;    /* put back by the last loss, not sent again yet */
  int64_t not_before;
} bitem;

static int build_item(const sm_client_req *q, uint8_t *op, void *msg, sm_client_error *err) {
  *op = q->op;
  switch (q->op) {
  case SM_OP_PUT_SHAPE: {
    sm_proto_put_req *m = msg;
    if (!q->draco || !q->draco_len || q->draco_len > (size_t)UINT32_MAX - 64)
      return seterr(err, SM_CLIENT_EINVAL, "batch: PUT_SHAPE without Draco bytes (or too many)");
    memset(m, 0, sizeof *m);
    sm_client_shape_id(q->draco, q->draco_len, m->id);
    m->flags = q->prepare ? SM_PUT_F_PREPARE : 0;
    m->draco = q->draco;
    m->draco_len = (uint32_t)q->draco_len;
    return 0;
  }
  case SM_OP_PING:
    ((sm_proto_ping *)msg)->opaque = 0;
    return 0;
  case SM_OP_HAS_SHAPE: memcpy(((sm_proto_id_req *)msg)->id, q->x, SM_PROTO_ID_LEN); return 0;
  case SM_OP_PREPARE:
    return fill_prepare(msg, q->x, q->k_lb, q->k_elastic, q->match ? q->match->eta : 0, err);
  case SM_OP_MATCH:
  case SM_OP_DISTANCE: return fill_match(q->op, q->x, q->y, q->match, msg, err);
  case SM_OP_QUERY: return fill_query(q->x, q->k, q->mode, NULL, 0, 0, msg, err);
  default: return seterr(err, SM_CLIENT_EINVAL, "batch: opcode %u is not PING, PUT_SHAPE, HAS_SHAPE, PREPARE, MATCH, DISTANCE or QUERY", q->op);
  }
}

/* Decodes an OK answer into *r (arrays owned by r, freed by the caller). */
static int decode_item(sm_client *c, const sm_client_req *q, const sm_proto_frame *f,
                       sm_client_resp *r, sm_client_error *err) {
  int rc = 0;
  switch (q->op) {
  case SM_OP_PING: {
    sm_proto_ping p;
    rc = sm_proto_dec_ping(f->body, f->body_len, &p);
    break;
  }
  case SM_OP_HAS_SHAPE: rc = sm_proto_dec_has_resp(f->body, f->body_len, &r->has); break;
  case SM_OP_PUT_SHAPE: {
    rc = sm_proto_dec_put_resp(f->body, f->body_len, &r->put);
    uint8_t id[SM_PROTO_ID_LEN];
    if (!rc) sm_client_shape_id(q->draco, q->draco_len, id);
    if (!rc && memcmp(id, r->put.id, SM_PROTO_ID_LEN))
      return broken(c, seterr(err, SM_CLIENT_EPROTO, "PUT_SHAPE answer names another id"));
    break;
  }
  case SM_OP_PREPARE: rc = sm_proto_dec_prepare_resp(f->body, f->body_len, &r->prepare); break;
  case SM_OP_MATCH: {
    sm_proto_match_resp p;
    rc = sm_proto_dec_match_resp(c->version, f->body, f->body_len, &p);
    if (!rc) return copy_match(c, &p, &r->match, err);
    break;
  }
  case SM_OP_DISTANCE: {
    sm_proto_distance_resp p;
    rc = sm_proto_dec_distance_resp(f->body, f->body_len, &p);
    if (!rc) {
      r->dist = p.dist;
      r->t_total = 1e-6 * (double)p.t_total_us;
    }
    break;
  }
  case SM_OP_QUERY: {
    sm_proto_query_resp p;
    rc = sm_proto_dec_query_resp(f->body, f->body_len, &p);
    if (!rc) {
      r->n_considered = p.n_considered;
      return copy_hits(&p, &r->hits, &r->n_hits, err);
    }
    break;
  }
  }
  return rc ? bad_body(c, q->op, rc, err) : 0;
}

static int deliver(sm_client_batch_cb cb, void *ud, size_t i, const sm_client_req *q,
                   sm_client_resp *r, size_t *n_failed) {
  if (r->code && n_failed) (*n_failed)++;
  int stop = cb ? cb(ud, i, q, r) : 0;
  sm_client_match_result_free(&r->match);
  free(r->hits);
  r->hits = NULL;
  return stop;
}

/* Items in flight when the connection was lost: each goes back to the queue, or fails with
 * the loss when it was in flight at SM_CLIENT_MAX_LOSSES losses. Returns 1 if a callback
 * asked to stop. */
static int requeue_cut(bitem *it, const sm_client_req *reqs, size_t n, size_t *next,
                       size_t *done, const sm_client_error *loss, sm_client_batch_cb cb,
                       void *ud, size_t *n_failed) {
  int stop = 0;
  for (size_t i = 0; i < n; i++) {
    if (it[i].state != ST_FLIGHT) continue;
    if (++it[i].losses < SM_CLIENT_MAX_LOSSES) {
      it[i].state = ST_PENDING;
      it[i].cut = 1;
      it[i].not_before = 0;
      if (i < *next) *next = i;
      continue;
    }
    sm_client_resp r;
    memset(&r, 0, sizeof r);
    r.request_id = it[i].rid;
    r.attempts = it[i].attempts;
    r.code = loss->code ? loss->code : SM_CLIENT_ECLOSED;
    r.err = *loss;
    r.err.code = r.code;
    snprintf(r.err.msg, sizeof r.err.msg, "%.200s (sent %d times, the connection was lost each time)",
             loss->msg, it[i].attempts);
    it[i].state = ST_DONE;
    (*done)++;
    stop |= deliver(cb, ud, i, &reqs[i], &r, n_failed) != 0;
  }
  return stop;
}

int sm_client_batch(sm_client *c, const sm_client_req *reqs, size_t n, unsigned inflight,
                    int busy_retries, sm_client_batch_cb cb, void *ud, size_t *n_failed,
                    sm_client_error *err) {
  clear_err(err);
  if (n_failed) *n_failed = 0;
  if (!c || (n && !reqs) || inflight < 1) return seterr(err, SM_CLIENT_EINVAL, "batch: bad argument");
  if (!c->open && !may_relink(c)) return seterr(err, SM_CLIENT_ECLOSED, "connection is closed");
  bitem *it = calloc(n ? n : 1, sizeof *it);
  if (!it) return seterr(err, SM_CLIENT_ENOMEM, "batch of %zu", n);
  size_t next = 0, in_flight = 0, done = 0;
  int stopping = 0, rc = 0;
  sm_client_error loss; /* what cut the connection, for the items it cut */
  memset(&loss, 0, sizeof loss);
  snprintf(loss.msg, sizeof loss.msg, "connection lost");
  c->last_rx_ms = now_ms();
  union {
    sm_proto_ping ping;
    sm_proto_put_req put;
    sm_proto_id_req id;
    sm_proto_prepare_req prep;
    sm_proto_match_req match;
    sm_proto_query_req query;
  } msg;
  int64_t dl = -1;
  while (done < n) {
    /* a lost connection (or a drained one with nothing left in flight): connect again and
     * put back what it cut; a failure to connect ends the batch below as a loss does */
    if (!stopping && may_relink(c) && (!c->open || (c->goaway && !in_flight))) {
      if (requeue_cut(it, reqs, n, &next, &done, &loss, cb, ud, n_failed)) stopping = 1;
      in_flight = 0;
      if (done == n || stopping) break; /* nothing left to send: no new connection */
      sm_client_error re = loss;
      if ((rc = relink(c, &re))) {
        seterr(err, rc, "%s", re.msg);
        for (size_t i = 0; i < n; i++) /* the items the loss cut fail with it (below) */
          if (it[i].state == ST_PENDING && it[i].cut) it[i].state = ST_FLIGHT;
        break;
      }
    }
    unsigned window = inflight;
    if (c->hello.max_inflight && window > c->hello.max_inflight) window = c->hello.max_inflight;
    /* fill the window with items whose time has come (BUSY retries wait their hint) */
    int64_t t = now_ms(), wake = -1;
    while (!stopping && in_flight < window && !(c->goaway && may_relink(c))) {
      size_t pick = n;
      for (size_t i = next; i < n; i++) {
        if (it[i].state != ST_PENDING) {
          if (i == next) next++;
          continue;
        }
        if (it[i].not_before <= t) {
          pick = i;
          break;
        }
        if (wake < 0 || it[i].not_before < wake) wake = it[i].not_before;
      }
      if (pick == n) break;
      uint8_t op;
      sm_client_resp r;
      memset(&r, 0, sizeof r);
      int brc = build_item(&reqs[pick], &op, &msg, &r.err);
      if (!brc) brc = send_req(c, op, &msg, &it[pick].rid, &r.err);
      it[pick].attempts++;
      if (brc && may_relink(c)) { /* the connection died under this send: it stays queued */
        loss = r.err;
        break;
      }
      if (brc) {
        it[pick].state = ST_DONE;
        done++;
        r.code = brc;
        r.attempts = it[pick].attempts;
        if (deliver(cb, ud, pick, &reqs[pick], &r, n_failed)) stopping = 1;
        if (!c->open) {
          rc = seterr(err, brc, "%s", r.err.msg);
          break;
        }
        continue;
      }
      it[pick].state = ST_FLIGHT;
      it[pick].cut = 0;
      in_flight++;
      dl = deadline_in(c->o.compute_timeout_ms);
    }
    if (rc || done == n) break;
    if (!stopping && may_relink(c) && (!c->open || (c->goaway && !in_flight))) continue;
    if (stopping && !in_flight) break;
    if (!in_flight) { /* only BUSY items waiting for their hint */
      int64_t d = wake - now_ms();
      if (d > 0) {
        struct timespec ts = {(time_t)(d / 1000), (long)(d % 1000) * 1000000L};
        nanosleep(&ts, NULL);
      }
      continue;
    }
    /* wait for one frame; a pending retry shortens the wait */
    int64_t w = dl;
    if (wake >= 0 && (w < 0 || wake < w) && in_flight < window) w = wake;
    sm_proto_frame f;
    sm_client_error fe;
    int frc = next_frame_live(c, w, !stopping, &f, &fe);
    if (frc == SM_CLIENT_ETIMEOUT && c->open && w == wake && w != dl) continue; /* a retry is due */
    if (frc == SM_CLIENT_ETIMEOUT) broken(c, frc);
    if (frc == SM_CLIENT_ECANCELED) { /* stop requested: cancel what is in flight, drain */
      stopping = 1;
      for (size_t i = 0; i < n; i++)
        if (it[i].state == ST_FLIGHT && sm_client_cancel(c, it[i].rid, &fe)) break;
      if (!c->open) {
        rc = seterr(err, fe.code, "%s", fe.msg);
        break;
      }
      dl = deadline_in(c->o.io_timeout_ms);
      continue;
    }
    if (frc && !stopping && may_relink(c)) {
      loss = fe;
      continue;
    }
    if (frc) {
      rc = seterr(err, frc, "%s", fe.msg);
      break;
    }
    int s = side_frame(c, &f, &fe);
    if (s < 0 && !stopping && may_relink(c)) {
      loss = fe;
      continue;
    }
    if (s < 0) {
      rc = seterr(err, s, "%s", fe.msg);
      if (err) err->status = fe.status;
      break;
    }
    if (s) continue;
    size_t i = 0;
    while (i < n && !(it[i].state == ST_FLIGHT && it[i].rid == f.h.request_id)) i++;
    if (i == n || (f.h.flags & SM_PROTO_F_MORE) || (f.h.status == SM_ST_OK && f.h.opcode != reqs[i].op)) {
      rc = broken(c, seterr(err, SM_CLIENT_EPROTO, "unexpected %s answer for request %u",
                            sm_proto_op_name(f.h.opcode), f.h.request_id));
      break;
    }
    in_flight--;
    if (!stopping) dl = deadline_in(c->o.compute_timeout_ms);
    sm_client_resp r;
    memset(&r, 0, sizeof r);
    r.request_id = f.h.request_id;
    r.attempts = it[i].attempts;
    if (f.h.status == SM_ST_BUSY && !stopping && (busy_retries < 0 || it[i].attempts <= busy_retries)) {
      sm_proto_error e;
      uint32_t hint = sm_proto_dec_error(f.body, f.body_len, &e) ? 0 : e.retry_after_ms;
      it[i].state = ST_PENDING;
      it[i].not_before = now_ms() + (hint ? hint : 50);
      if (i < next) next = i;
      continue;
    }
    if (f.h.status == SM_ST_SHUTTING_DOWN && !stopping) {
      /* not executed: the server is draining (it sent GOAWAY before); the next connection
       * takes the item */
      c->goaway = 1;
      if (may_relink(c) && ++it[i].losses < SM_CLIENT_MAX_LOSSES) {
        it[i].state = ST_PENDING;
        it[i].cut = 1;
        it[i].not_before = 0;
        if (i < next) next = i;
        continue;
      }
    }
    it[i].state = ST_DONE;
    done++;
    if (f.h.status != SM_ST_OK) r.code = status_error(c, &f, &r.err);
    else r.code = decode_item(c, &reqs[i], &f, &r, &r.err);
    if (deliver(cb, ud, i, &reqs[i], &r, n_failed) && !stopping) {
      stopping = 1;
      for (size_t j = 0; j < n; j++)
        if (it[j].state == ST_FLIGHT && sm_client_cancel(c, it[j].rid, &fe)) break;
      dl = deadline_in(c->o.io_timeout_ms);
    }
    if (!c->open && !stopping && may_relink(c)) {
      loss = r.err;
      continue;
    }
    if (!c->open) {
      rc = seterr(err, r.code ? r.code : SM_CLIENT_ECLOSED, "%s", r.code ? r.err.msg : "connection lost");
      break;
    }
  }
  /* the connection is gone: whatever was in flight will not be answered */
  if (rc)
    for (size_t i = 0; i < n; i++)
      if (it[i].state == ST_FLIGHT) {
        sm_client_resp r;
        memset(&r, 0, sizeof r);
        r.request_id = it[i].rid;
        r.attempts = it[i].attempts;
        r.code = rc;
        r.err = err ? *err : (sm_client_error){.code = rc};
        it[i].state = ST_DONE;
        deliver(cb, ud, i, &reqs[i], &r, n_failed);
      }
  free(it);
  if (!rc && stopping) {
    /* answers to our CANCELs may still be on their way; read them so the connection
     * stays in step for the next call */
    int64_t d2 = deadline_in(c->o.io_timeout_ms);
    while (c->n_cancels && c->open) {
      sm_proto_frame f;
      sm_client_error fe;
      if (next_frame(c, d2, 0, &f, &fe) || side_frame(c, &f, &fe) <= 0) break;
    }
    if (done < n) rc = seterr(err, SM_CLIENT_ECANCELED, "batch stopped before all requests were sent");
  }
  return rc;
}
