"""Client: one connection to shapematchd (PROTOCOL.md), blocking calls and pipelined batches.

DESIGN
  The socket is non-blocking and every wait is a selector wait bounded by a deadline, as in
  the C client (clients/sm_client.h), whose behaviour this follows:
  - connect_timeout bounds connecting; io_timeout bounds sending (a stall, not the whole
    upload) and the answer to requests the server answers at once (HELLO, PING, STATS,
    HAS, DROP).
  - Requests that go through the server's job queue (PUT, PREPARE, MATCH, DISTANCE, QUERY)
    may wait there behind other clients' work for any time. After io_timeout of silence the
    client sends a PING, which the server answers at once, and goes on waiting while such
    probes are answered; an unanswered probe is a Timeout. compute_timeout (None = none)
    bounds that wait (batch: the time between two answers).
  - While sending, the client keeps reading, so a batch whose answers pile up cannot
    deadlock against a server that stops reading a connection with unread answers.
  - A request-level status raises StatusError and the connection lives on. Anything that
    leaves the byte stream out of step (fatal status, malformed server bytes, a timeout or
    an interrupt with an answer owed, a lost connection) closes the client first; later
    calls raise ConnectionClosed.
  A Client is not thread-safe: use one per thread.
"""
import os
import selectors
import socket
import time

from . import wire
from .errors import (ConnectFailed, ConnectionClosed, OverLimit, ProtocolViolation,
                     StatusError, Timeout)
from .requests import (BatchRequest, DistanceRequest, DropRequest, HasRequest, HelloRequest,
                       MatchRequest, PingRequest, PrepareRequest, PutRequest, QueryRequest,
                       StatsRequest, shape_id)

DEFAULT_PORT = 7878


def _load_numpy():
    """numpy when importable, unless $SHAPEMATCH_NO_NUMPY is set (not empty, not "0"): the
    switch lets a program, or the tests, get plain lists even where numpy is installed."""
    if os.environ.get("SHAPEMATCH_NO_NUMPY", "") not in ("", "0"):
        return None
    try:
        import numpy
    except ImportError:
        return None
    return numpy


NUMPY = _load_numpy()


def parse_address(addr):
    """"host:port", "host" (port 7878), "[v6addr]:port", ":port" (localhost) or
    "unix:/path". Returns (family, target) for socket.connect."""
    if addr.startswith("unix:"):
        if not addr[5:]:
            raise ConnectFailed("%r: empty unix socket path" % addr)
        return socket.AF_UNIX, addr[5:]
    host, port = addr, None
    if addr.startswith("["):
        end = addr.find("]")
        if end < 2:
            raise ConnectFailed("%r: unterminated [ipv6]" % addr)
        host, rest = addr[1:end], addr[end + 1:]
        if rest and not rest.startswith(":"):
            raise ConnectFailed("%r: junk after ]" % addr)
        port = rest[1:] if rest else None
    elif ":" in addr:
        if addr.count(":") > 1:
            raise ConnectFailed("%r: an IPv6 address needs brackets: [addr]:port" % addr)
        host, port = addr.split(":")
    if port is not None and not (port.isdigit() and 1 <= int(port) <= 65535):
        raise ConnectFailed("%r: port must be 1..65535" % addr)
    return socket.AF_INET, (host or "localhost", int(port) if port else DEFAULT_PORT)


class Client:
    """A connection to shapematchd, HELLO done.

    address: as parse_address, default $SHAPEMATCH_SERVER or localhost:7878.
    token: str or bytes, default $SHAPEMATCH_TOKEN (the daemon's shared secret).
    affinity: a shape (id) this connection is mostly about, the routing key a TCP balancer
      hashes (PROTOCOL.md section 8).
    max_response: largest answer accepted (bytes, 0 = no limit); the server answers
      RESPONSE_TOO_LARGE instead of a bigger one.
    use_numpy: None = numpy when available (see NUMPY), False = lists, True = numpy
      required. cli: the shapematch CLI used to encode non-Draco meshes (meshes.py).
    Timeouts are in seconds. Use as a context manager, or call close().
    """

    def __init__(self, address=None, token=None, *, connect_timeout=10.0, io_timeout=30.0,
                 compute_timeout=None, max_response=0, affinity=None, payload_crc=False,
                 use_numpy=None, cli=None):
        address = address or os.environ.get("SHAPEMATCH_SERVER") or "localhost:%d" % DEFAULT_PORT
        if token is None:
            token = os.environ.get("SHAPEMATCH_TOKEN", "")
        self.token = token.encode("utf-8") if isinstance(token, str) else bytes(token)
        if len(self.token) > wire.MAX_TOKEN:
            raise ValueError("token of %d bytes; at most %d" % (len(self.token), wire.MAX_TOKEN))
        if use_numpy and NUMPY is None:
            raise ImportError("use_numpy=True but numpy cannot be imported (or "
                              "$SHAPEMATCH_NO_NUMPY is set)")
        self.numpy = NUMPY if use_numpy is None else (NUMPY if use_numpy else None)
        self.io_timeout = float(io_timeout)
        self.compute_timeout = compute_timeout
        self.payload_crc = payload_crc
        self.cli = cli
        self.address = address
        self._affinity = shape_id(affinity) if affinity is not None else bytes(wire.ID_LEN)
        self._max_response = max_response
        self._sock = None
        self._rbuf = bytearray()
        self._eof = False
        self._next_rid = 0
        self._goaway = False
        self._probe = 0          # request id of a liveness PING in flight
        self._last_rx = time.monotonic()
        self.version = wire.VERSION_HELLO   # the negotiated version once HELLO is done
        self._limit = wire.HELLO_MAX_PAYLOAD
        self.limits = None                  # the HELLO answer (wire.Hello)
        self._connect(address, connect_timeout)
        try:
            self._hello()
        except BaseException:
            self.close()
            raise

    # ---- connection ----
    def _connect(self, address, timeout):
        family, target = parse_address(address)
        try:
            if family == socket.AF_UNIX:
                s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                s.settimeout(timeout)
                try:
                    s.connect(target)
                except BaseException:
                    s.close()
                    raise
            else:
                s = socket.create_connection(target, timeout=timeout)
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except socket.timeout:
            raise ConnectFailed("%s: connect timed out after %g s" % (address, timeout)) from None
        except OSError as e:
            raise ConnectFailed("%s: %s" % (address, e.strerror or e)) from None
        s.setblocking(False)
        self._sock = s
        self._sel = selectors.DefaultSelector()
        self._sel.register(s, selectors.EVENT_READ)

    def _hello(self):
        h = self._call(HelloRequest(self._max_response, self._affinity, self.token))
        if not wire.VERSION_MIN <= h.version <= wire.VERSION_MAX:
            self._fail(ProtocolViolation("the server chose protocol version %d" % h.version))
        self.limits = h
        self.version = h.version
        m = self._max_response
        self._limit = m + 4 if m and m <= 0xFFFFFFFF - 4 else 0xFFFFFFFF

    @property
    def is_open(self):
        return self._sock is not None

    def close(self):
        """Closes the connection (the server cancels whatever it still had in flight)."""
        if self._sock is not None:
            self._sel.close()
            self._sock.close()
            self._sock = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _fail(self, exc):
        self.close()
        raise exc

    # ---- bytes ----
    def _wait(self, events, deadline):
        """Selector mask once ready, 0 when the deadline (monotonic, None = none) passed."""
        timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
        self._sel.modify(self._sock, events)
        ready = self._sel.select(timeout)
        return ready[0][1] if ready else 0

    def _read_some(self):
        try:
            data = self._sock.recv(1 << 18)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._fail(ConnectionClosed("recv: %s" % (e.strerror or e)))
        if not data:
            self._eof = True
        self._rbuf += data

    def _send(self, data):
        view = memoryview(data)
        stall_deadline = time.monotonic() + self.io_timeout
        while view:
            events = selectors.EVENT_WRITE | (0 if self._eof else selectors.EVENT_READ)
            mask = self._wait(events, stall_deadline)
            if not mask:
                self._fail(Timeout("sending: the server took no bytes for %g s" % self.io_timeout))
            if mask & selectors.EVENT_READ:
                self._read_some()
            if mask & selectors.EVENT_WRITE:
                try:
                    n = self._sock.send(view)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError as e:
                    self._closed_while_sending(e)
                view = view[n:]
                stall_deadline = time.monotonic() + self.io_timeout

    def _closed_while_sending(self, e):
        """The server closed on us: a GOAWAY it sent first says why, else the socket error."""
        while True:
            f = self._parse()
            if f is None:
                break
            if f[0].opcode == wire.GOAWAY and f[0].status:
                self._fail(self._status_error(f[0], f[1], "GOAWAY"))
        self._fail(ConnectionClosed("send: %s" % (e.strerror or e)))

    def _parse(self):
        """The next complete server frame in the buffer as (Header, body), or None."""
        buf = self._rbuf
        if len(buf) < wire.HEADER_LEN:
            if buf and not wire.MAGIC.startswith(bytes(buf[:4])):
                self._fail(ProtocolViolation("server stream: bad magic"))
            return None
        try:
            h = wire.parse_header(buf, self._limit)
        except ProtocolViolation as e:
            self._fail(e)
        if self.limits is not None and h.version != self.version:
            self._fail(ProtocolViolation("server frame of version %d on a version %d connection"
                                         % (h.version, self.version)))
        end = wire.HEADER_LEN + h.payload_len
        if len(buf) < end:
            return None
        payload = bytes(buf[wire.HEADER_LEN:end])
        del buf[:end]
        try:
            return h, wire.frame_body(h, payload)
        except ProtocolViolation as e:
            self._fail(e)

    def _recv_frame(self, deadline):
        """The next server frame, or None when the deadline passes first."""
        while True:
            f = self._parse()
            if f is not None:
                self._last_rx = time.monotonic()
                return f
            if self._eof:
                self._fail(ConnectionClosed("the server closed the connection"))
            if not self._wait(selectors.EVENT_READ, deadline):
                return None
            self._read_some()

    def _recv_live(self, deadline, wake=None):
        """The next frame for a queued request (see DESIGN): liveness PINGs after
        io_timeout of silence; Timeout past the deadline; None when `wake` comes first."""
        while True:
            points = [p for p in (deadline, wake, self._last_rx + self.io_timeout) if p is not None]
            f = self._recv_frame(min(points))
            if f is not None:
                return f
            now = time.monotonic()
            if wake is not None and now >= wake:
                return None
            if deadline is not None and now >= deadline:
                self._fail(Timeout("no answer from the server within the time limit (%g s)"
                                   % self.compute_timeout))
            if now < self._last_rx + self.io_timeout:
                continue
            if self._probe:
                self._fail(Timeout("the server stopped answering (no answer to a PING within "
                                   "%g s)" % self.io_timeout))
            self._last_rx = now
            if not self._goaway:  # draining: it answers or closes within its drain time
                self._probe = self._send_request(PingRequest())

    # ---- frames ----
    def _status_error(self, h, body, what):
        e = wire.dec_error(body)
        err = StatusError(h.status, wire.status_name(h.status), e.detail, e.retry_after_ms,
                          e.message, what)
        if err.fatal:
            self.close()
        return err

    def _side_frame(self, h, body):
        """True for frames no request waits for: a graceful GOAWAY, a probe's answer.
        A fatal GOAWAY raises its status."""
        if h.opcode == wire.GOAWAY:
            if h.status == wire.OK:
                self._goaway = True
                return True
            raise self._status_error(h, body, "GOAWAY")
        if h.opcode == wire.PING and self._probe and h.request_id == self._probe:
            self._probe = 0
            return True
        return False

    def _send_request(self, req):
        if self._sock is None:
            raise ConnectionClosed("the connection is closed")
        if self._goaway:
            raise ConnectionClosed("the server is shutting down (GOAWAY)")
        payload = req.payload(self)
        if self.limits is not None and len(payload) > self.limits.max_payload:
            raise OverLimit("%s request of %d bytes; the server accepts %d"
                            % (req.name(), len(payload), self.limits.max_payload))
        self._next_rid = self._next_rid % 0xFFFFFFFF + 1
        version = wire.VERSION_HELLO if req.op == wire.HELLO else self.version
        self._send(wire.encode_frame(version, req.op, self._next_rid, payload, self.payload_crc))
        return self._next_rid

    def _answer(self, req, h, body):
        """The result of an answer frame for req; a non-OK status raises StatusError."""
        if h.flags & wire.F_MORE or (h.status == wire.OK and h.opcode != req.op):
            self._fail(ProtocolViolation("%s answer (request %d) to a %s request"
                                         % (wire.OP_NAMES.get(h.opcode, h.opcode),
                                            h.request_id, req.name())))
        if h.status != wire.OK:
            raise self._status_error(h, body, req.name())
        try:
            return req.decode(self, body)
        except ProtocolViolation as e:
            self._fail(e)

    def _next_for(self, req, rid):
        """The next frame answering request rid (side frames consumed); the wait is bounded
        as the DESIGN says, from now (a BATCH: between two of its frames)."""
        self._last_rx = time.monotonic()
        limit = self.compute_timeout if req.compute else self.io_timeout
        deadline = None if limit is None else time.monotonic() + limit
        while True:
            if req.compute:
                h, body = self._recv_live(deadline)
            else:
                f = self._recv_frame(deadline)
                if f is None:
                    self._fail(Timeout("no %s answer within %g s" % (req.name(), limit)))
                h, body = f
            if self._side_frame(h, body):
                continue
            if h.request_id != rid:
                self._fail(ProtocolViolation("answer for request %d while waiting for %d"
                                             % (h.request_id, rid)))
            return h, body

    def _guarded(self, fn):
        """Runs fn(); whatever leaves an answer owed (a timeout, an interrupt, a fatal
        status) closes the connection, which also cancels the work server-side. A
        request-level StatusError leaves it open."""
        try:
            return fn()
        except StatusError as e:
            if e.fatal:
                self.close()
            raise
        except BaseException:
            self.close()
            raise

    def _call(self, req):
        """Sends req and returns its decoded answer."""
        def run():
            rid = self._send_request(req)
            h, body = self._next_for(req, rid)
            return self._answer(req, h, body)
        return self._guarded(run)

    # ---- operations ----
    def ping(self):
        """Round-trip time in seconds."""
        return self._call(PingRequest())

    def stats(self):
        """The daemon's counters as {name: value}."""
        return self._call(StatsRequest())

    def put(self, shape, prepare=False):
        """Stores a shape: Draco bytes, or a mesh file path (.drc as is, other formats
        encoded by the shapematch CLI, see meshes.py). prepare: also compute its default
        bases. Returns a PutResult (its .id names the shape in later calls)."""
        return self._call(PutRequest(shape, prepare, self.cli))

    def put_mesh(self, vertices, faces, prepare=False):
        """Stores a triangle mesh given as arrays (n x 3 floats, m x 3 indices); maps then
        index the rows of `vertices`."""
        return self._call(PutRequest((vertices, faces), prepare, self.cli))

    def has(self, shape):
        return self._call(HasRequest(shape))

    def drop(self, shape):
        """Removes a stored shape and its cached bases (NOT_FOUND when not stored)."""
        self._call(DropRequest(shape))

    def prepare(self, shape, k_lb=0, k_elastic=0, eta=0.0):
        return self._call(PrepareRequest(shape, k_lb, k_elastic, eta))

    def match(self, x, y, **options):
        """Dense point map x -> y (MatchRequest lists the options); a MatchResult."""
        return self._call(MatchRequest(x, y, **options))

    def distance(self, x, y, **options):
        """Shape distance in [0, 1) with its terms; a DistanceResult."""
        return self._call(DistanceRequest(x, y, **options))

    def query(self, shape, k=10, mode="default", candidates=None, deadline_ms=0):
        """The k stored shapes nearest to shape; a QueryResult."""
        return self._call(QueryRequest(shape, k, mode, candidates, deadline_ms))

    def server_batch(self, requests, callback=None):
        """One BATCH request (PROTOCOL.md 5.10): the server runs the items (PingRequest,
        HasRequest, PrepareRequest, MatchRequest, DistanceRequest, QueryRequest) in parallel
        on its worker pool and answers each as it completes; one request against
        max_inflight and the job queue. Returns the results in request order, a failed item
        holding its StatusError; callback(index, result) runs per item as it arrives. A
        rejection of the whole batch (BUSY, LIMIT_EXCEEDED, ...) raises StatusError."""
        batch = BatchRequest(list(requests), self)
        results = [None] * len(batch.items)

        def run():
            rid = self._send_request(batch)
            while True:
                h, body = self._next_for(batch, rid)
                if h.opcode != wire.BATCH:
                    self._fail(ProtocolViolation("%s answer to a BATCH request"
                                                 % wire.OP_NAMES.get(h.opcode, h.opcode)))
                if not h.flags & wire.F_MORE:
                    if h.status != wire.OK:
                        raise self._status_error(h, body, "BATCH")
                    n_items, n_ok = wire.dec_batch_end(body)
                    missing = [i for i, r in enumerate(results) if r is None]
                    if n_items != len(results) or missing:
                        self._fail(ProtocolViolation("BATCH ended after %d of %d items"
                                                     % (len(results) - len(missing),
                                                        len(results))))
                    return results
                index, op, rest = wire.dec_batch_item(body)
                if index >= len(results) or results[index] is not None or \
                        op != batch.items[index].op:
                    self._fail(ProtocolViolation("BATCH item answer %d (%s) does not match "
                                                 "the request"
                                                 % (index, wire.OP_NAMES.get(op, op))))
                item = batch.items[index]
                if h.status == wire.OK:
                    try:
                        results[index] = item.decode(self, rest)
                    except ProtocolViolation as e:
                        self._fail(e)
                else:
                    results[index] = self._status_error(h, rest, "BATCH item %d (%s)"
                                                        % (index, item.name()))
                    if results[index].fatal:
                        raise results[index]
                if callback is not None:
                    callback(index, results[index])
        return self._guarded(run)

    def batch(self, requests, inflight=4, busy_retries=-1, callback=None):
        """Runs many requests (PingRequest, PutRequest, HasRequest, PrepareRequest,
        MatchRequest, DistanceRequest, QueryRequest, ...) pipelined on this connection, up
        to `inflight` in flight (capped by the server's max_inflight), answers taken in
        completion order. A BUSY answer is re-sent after the server's hint, at most
        busy_retries times (< 0: no limit). Returns the results in request order; an item
        that failed holds its StatusError (or OverLimit) instead of raising. callback(index,
        result) runs as each completes. A lost connection raises (the batch is over)."""
        reqs = list(requests)
        n = len(reqs)
        if inflight < 1:
            raise ValueError("inflight must be >= 1")
        if self.limits.max_inflight:
            inflight = min(inflight, self.limits.max_inflight)
        results = [None] * n
        waiting = list(range(n))       # not sent yet (or BUSY, to be re-sent)
        not_before = [0.0] * n
        attempts = [0] * n
        flight = {}                    # request id -> index
        done = 0

        def finish(i, result):
            nonlocal done
            results[i] = result
            done += 1
            if callback is not None:
                callback(i, result)

        try:
            self._last_rx = time.monotonic()
            deadline = None
            while done < n:
                now = time.monotonic()
                while len(flight) < inflight:
                    ready = [i for i in waiting if not_before[i] <= now]
                    if not ready:
                        break
                    i = ready[0]
                    waiting.remove(i)
                    attempts[i] += 1
                    try:
                        flight[self._send_request(reqs[i])] = i
                    except OverLimit as e:
                        finish(i, e)
                        continue
                    if self.compute_timeout is not None:
                        deadline = time.monotonic() + self.compute_timeout
                if done == n:
                    break
                wake = min((not_before[i] for i in waiting), default=None)
                if not flight:  # only BUSY items waiting for their hint
                    time.sleep(max(0.0, wake - time.monotonic()))
                    continue
                f = self._recv_live(deadline, wake if len(flight) < inflight else None)
                if f is None:
                    continue
                h, body = f
                if self._side_frame(h, body):
                    continue
                if h.request_id not in flight:
                    self._fail(ProtocolViolation("answer for request %d, which is not in flight"
                                                 % h.request_id))
                i = flight.pop(h.request_id)
                if self.compute_timeout is not None:
                    deadline = time.monotonic() + self.compute_timeout
                if h.status == wire.BUSY and (busy_retries < 0 or attempts[i] <= busy_retries):
                    hint = wire.dec_error(body).retry_after_ms or 50
                    not_before[i] = time.monotonic() + hint / 1000.0
                    waiting.append(i)
                    waiting.sort()
                    continue
                try:
                    result = self._answer(reqs[i], h, body)
                except StatusError as e:
                    if e.fatal:
                        raise
                    result = e
                finish(i, result)
        except StatusError:
            self.close()  # only fatal ones get here
            raise
        except BaseException:
            self.close()
            raise
        return results
