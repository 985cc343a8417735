#define _GNU_SOURCE /* accept4, memmem */
/* epoll loop: see sm_srv_loop.h. */
#include "sm_srv_loop.h"

#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <malloc.h> /* malloc_trim (glibc) */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <unistd.h>

#include "sm_srv_conn.h"
#include "sm_srv_log.h"
#include "sm_srv_metrics.h"
#include "sm_srv_pool.h"

#define TICK_MS 100
#define CANCEL_GRACE_NS 10000000000ull /* after cancelling everything, wait this long */
#define TRIM_MIN_BYTES (32ull << 20) /* buffered bytes freed since the peak that call for a trim */
#define TRIM_EVERY_NS 1000000000ull

static int spare_fd = -1; /* given up on EMFILE: see on_emfile */
static uint64_t emfile_logged_ns;

static int h_listen = SM_H_LISTEN, h_metrics = SM_H_METRICS_LISTEN, h_event = SM_H_EVENTFD;

int sm_srv_listen(const char *bind_addr, int port, char *err, size_t errlen, int *fd_out) {
  struct sockaddr_in a;
  memset(&a, 0, sizeof a);
  a.sin_family = AF_INET;
  a.sin_port = htons((uint16_t)port);
  if (inet_pton(AF_INET, bind_addr, &a.sin_addr) != 1) {
    snprintf(err, errlen, "bad IPv4 bind address %s", bind_addr);
    return -1;
  }
  int fd = socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (fd < 0) {
    snprintf(err, errlen, "socket: %s", strerror(errno));
    return -1;
  }
  int one = 1;
  setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
  if (bind(fd, (struct sockaddr *)&a, sizeof a) || listen(fd, 511)) {
    snprintf(err, errlen, "bind/listen %s:%d: %s", bind_addr, port, strerror(errno));
    close(fd);
    return -1;
  }
  socklen_t sl = sizeof a;
  getsockname(fd, (struct sockaddr *)&a, &sl);
  *fd_out = fd;
  return ntohs(a.sin_port);
}

/* Out of descriptors: accept the newcomer on the spare one and close it at once. */
static void on_emfile(int lfd) {
  uint64_t now = sm_srv_now_ns();
  if (now - emfile_logged_ns > 1000000000ull) {
    emfile_logged_ns = now;
    sm_log("warn", "out of file descriptors, refusing connections", NULL);
  }
  if (spare_fd < 0) return;
  close(spare_fd);
  int fd = accept(lfd, NULL, NULL);
  if (fd >= 0) {
    close(fd);
    sm_met_add(&sm_met.connections_rejected, 1);
  }
  spare_fd = open("/dev/null", O_RDONLY | O_CLOEXEC);
}

static void on_accept(sm_server *s, int lfd, int kind) {
  for (int i = 0; i < 64; i++) {
    struct sockaddr_in a;
    socklen_t sl = sizeof a;
    int fd = accept4(lfd, (struct sockaddr *)&a, &sl, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
      if (errno == EINTR) continue;
      if (errno == EMFILE || errno == ENFILE) on_emfile(lfd);
      else if (errno != EAGAIN && errno != EWOULDBLOCK)
        sm_log("warn", "accept failed", " err=\"%s\"", strerror(errno));
      return;
    }
    char peer[64], ip[INET_ADDRSTRLEN];
    inet_ntop(AF_INET, &a.sin_addr, ip, sizeof ip);
    snprintf(peer, sizeof peer, "%s:%d", ip, ntohs(a.sin_port));
    if (kind == SM_H_CONN) {
      int one = 1, sndbuf = SM_CONN_SNDBUF;
      setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
      setsockopt(fd, SOL_SOCKET, SO_SNDBUF, &sndbuf, sizeof sndbuf); /* sm_srv_conn.h */
    }
    int over = kind == SM_H_CONN && s->n_active >= s->cfg.max_conns &&
               !sm_conn_evict_idle(s, sm_srv_now_ns());
    sm_conn *c = sm_conn_new(s, fd, kind, peer);
    if (!c) {
      close(fd);
      continue;
    }
    if (kind != SM_H_CONN) continue;
    if (over) {
      sm_met_add(&sm_met.connections_rejected, 1);
      sm_conn_fatal(s, c, SM_ST_TOO_MANY_CONNECTIONS, 0, 1000, (uint32_t)s->cfg.max_conns,
                    "connection limit reached");
    } else {
      sm_log("info", "connection accepted", " conn=%llu peer=%s", (unsigned long long)c->id, peer);
    }
  }
}

static void on_http(sm_server *s, sm_conn *c) {
  sm_conn_on_readable(s, c);
  if (c->state != SM_CONN_OPEN || c->fd < 0) return;
  int done = c->rlen >= 4 && memmem(c->rbuf, c->rlen, "\r\n\r\n", 4) != NULL;
  if (!done && c->rlen + 1 < c->rcap) return;
  size_t len = 0;
  char *resp = sm_met_http(s->store, (const char *)c->rbuf, c->rlen, !s->draining, &len);
  sm_wbuf *w = resp ? sm_wbuf_new(len) : NULL;
  if (w) memcpy(w->data, resp, len);
  free(resp);
  c->rlen = 0;
  sm_conn_queue(s, c, w);
  c->state = SM_CONN_FLUSH_CLOSE;
  sm_conn_on_writable(s, c);
}

static void start_drain(sm_server *s, int lfd, int mfd) {
  s->draining = 1;
  s->drain_deadline_ns = sm_srv_now_ns() + (uint64_t)s->cfg.drain_ms * 1000000ull;
  if (lfd >= 0) {
    epoll_ctl(s->epfd, EPOLL_CTL_DEL, lfd, NULL);
    close(lfd);
  }
  (void)mfd; /* /metrics stays up while draining; /readyz says 503 */
  int n = 0;
  for (sm_conn *c = s->conns; c; c = c->next)
    if (c->kind == SM_H_CONN && c->state == SM_CONN_OPEN) {
      sm_conn_goaway(s, c);
      n++;
    }
  sm_log("info", "shutdown requested, draining", " connections=%d drain_ms=%u", n,
         s->cfg.drain_ms);
  sm_srv_notify("STOPPING=1");
  for (sm_conn *c = s->conns, *nx; c; c = nx) {
    nx = c->next;
    if (c->fd >= 0) sm_conn_on_writable(s, c);
  }
}

int sm_srv_run(sm_server *s, int lfd, int mfd) {
  int efd = sm_pool_fd(s->pool);
  struct epoll_event ev = {.events = EPOLLIN};
  ev.data.ptr = &h_listen;
  epoll_ctl(s->epfd, EPOLL_CTL_ADD, lfd, &ev);
  if (mfd >= 0) {
    ev.data.ptr = &h_metrics;
    epoll_ctl(s->epfd, EPOLL_CTL_ADD, mfd, &ev);
  }
  ev.data.ptr = &h_event;
  epoll_ctl(s->epfd, EPOLL_CTL_ADD, efd, &ev);
  uint64_t last_tick = 0, cancel_deadline = 0, last_trim = 0;
  int rc = 0;
  sm_met.buffer_budget = s->cfg.buffer_budget;
  /* Large buffers always from mmap: glibc otherwise raises its threshold after the first
   * large free, and later read buffers come from the heap, where freeing them does not
   * lower the RSS (measured: 150 MiB above the budget's charge under bench_hostile). */
  mallopt(M_MMAP_THRESHOLD, 1 << 20);
  if (spare_fd < 0) spare_fd = open("/dev/null", O_RDONLY | O_CLOEXEC);
  for (;;) {
    struct epoll_event evs[128];
    /* Backlogged connections (fairness, sm_srv_conn.h) have work: poll, do not sleep. */
    int n = epoll_wait(s->epfd, evs, 128, s->n_backlogged ? 0 : TICK_MS);
    if (n < 0 && errno != EINTR) {
      sm_log("error", "epoll_wait failed", " err=\"%s\"", strerror(errno));
      return -1;
    }
    for (int i = 0; i < n; i++) {
      int kind = *(int *)evs[i].data.ptr;
      if (kind == SM_H_LISTEN) {
        if (!s->draining) on_accept(s, lfd, SM_H_CONN);
      } else if (kind == SM_H_METRICS_LISTEN) {
        on_accept(s, mfd, SM_H_HTTP);
      } else if (kind == SM_H_EVENTFD) {
        sm_pool_msg *m = sm_pool_take(s->pool);
        while (m) {
          sm_pool_msg *next = m->next;
          sm_conn_on_done(s, (sm_srv_out *)m);
          m = next;
        }
      } else {
        /* A connection. Closed connections are only freed by sm_conn_sweep after the
         * batch, so c is valid even if an earlier event of this batch closed it. */
        sm_conn *c = evs[i].data.ptr;
        uint32_t e = evs[i].events;
        if (c->kind == SM_H_HTTP) {
          if (e & (EPOLLIN | EPOLLERR | EPOLLHUP)) {
            if (c->state == SM_CONN_OPEN) on_http(s, c);
            else sm_conn_on_readable(s, c);
          } else if (e & EPOLLOUT) {
            sm_conn_on_writable(s, c);
          }
          continue;
        }
        if (e & EPOLLOUT) sm_conn_on_writable(s, c);
        else if (e & (EPOLLIN | EPOLLERR | EPOLLHUP)) sm_conn_on_readable(s, c);
      }
    }
    sm_conn_run_backlog(s);
    sm_conn_budget(s);
    sm_conn_sweep(s);
    uint64_t now = sm_srv_now_ns();
    if (sm_srv_signal_flag && !s->draining) {
      start_drain(s, lfd, mfd);
      lfd = -1;
    }
    if (now - last_tick >= (uint64_t)TICK_MS * 1000000ull) {
      last_tick = now;
      sm_conn_tick(s, now);
      if (s->buf_trim_mark > s->buf_used + TRIM_MIN_BYTES && now - last_trim > TRIM_EVERY_NS) {
        /* After a burst: free()d chunks inside the heap stay resident until trimmed. */
        malloc_trim(0);
        s->buf_trim_mark = s->buf_used;
        last_trim = now;
      }
    }
    if (s->draining) {
      int open_conns = 0, jobs = 0;
      for (sm_conn *c = s->conns; c; c = c->next)
        if (c->kind == SM_H_CONN) {
          open_conns++;
          jobs += (int)c->n_inflight;
        }
      if (!open_conns) break;
      if (!s->cancelled_all && now > s->drain_deadline_ns) {
        s->cancelled_all = 1;
        cancel_deadline = now + CANCEL_GRACE_NS;
        sm_log("warn", "drain budget spent, cancelling", " jobs=%d", jobs);
        for (sm_conn *c = s->conns; c; c = c->next) sm_conn_cancel_all(c, 2);
      }
      if (s->cancelled_all && now > cancel_deadline) {
        sm_log("error", "jobs did not stop after cancellation", " jobs=%d", jobs);
        rc = -1;
        break;
      }
    }
  }
  /* Close what is left (metrics connections, lingering sockets). */
  for (sm_conn *c = s->conns, *nx; c; c = nx) {
    nx = c->next;
    if (c->fd >= 0) sm_conn_close(s, c);
  }
  sm_conn_sweep(s);
  if (mfd >= 0) close(mfd);
  if (spare_fd >= 0) close(spare_fd);
  spare_fd = -1;
  return rc;
}
