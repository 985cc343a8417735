"""Requests and their results: one class per operation, each knowing its opcode, how to
encode its payload and how to decode the answer (PROTOCOL.md section 5).

Client's single calls (client.match(...)) and its pipelined batch (client.batch([...])) go
through the same objects, so a request means the same thing both ways. The numbers in the
results are the wire's own: maps are the server's int32 entries, distances and times its
f64 / microsecond fields (times given here in seconds).
"""
import array
import binascii
import hashlib
import os
import struct
import sys
import time
from dataclasses import dataclass, field
from typing import Any, List, Optional

from . import wire
from .errors import MeshError, OverLimit, ProtocolViolation
from .meshes import encode_arrays, encode_file


def shape_id(ref):
    """The 32-byte id of a shape named by a 64-hex string, 32 raw bytes, or a PutResult."""
    if isinstance(ref, PutResult):
        ref = ref.id
    if isinstance(ref, (bytes, bytearray)) and len(ref) == wire.ID_LEN:
        return bytes(ref)
    if isinstance(ref, str) and len(ref) == 2 * wire.ID_LEN:
        try:
            return binascii.unhexlify(ref)
        except binascii.Error:
            pass
    raise ValueError("a shape is named by its 64-hex id, 32 id bytes or a PutResult, not %r"
                     % (ref if not isinstance(ref, (bytes, bytearray)) or len(ref) < 40
                        else "%d bytes" % len(ref),))


def _hex(raw):
    return binascii.hexlify(raw).decode("ascii")


def _int32_array(body, offset, count, np):
    """count little-endian int32 from body[offset:], as a numpy int32 array or a list."""
    if np is not None:
        return np.frombuffer(body, dtype="<i4", count=count, offset=offset).astype(np.int32)
    a = array.array("i")
    if a.itemsize != 4:
        return list(struct.unpack_from("<%di" % count, body, offset))
    a.frombytes(bytes(body[offset:offset + 4 * count]))
    if sys.byteorder != "little":
        a.byteswap()
    return a.tolist()


def _int_list(name, values, lo):
    """values (list, tuple, numpy array, nested pairs flattened) as Python ints >= lo."""
    flat = values.ravel().tolist() if hasattr(values, "ravel") else values
    out = []
    for v in flat:
        if isinstance(v, (list, tuple)):
            out.extend(v)
        else:
            out.append(v)
    for i, v in enumerate(out):
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= 0x7FFFFFFF:
            raise ValueError("%s entry %d is %r; expected an integer in %d..2^31-1"
                             % (name, i, v, lo))
    return out


# ---- results ----
@dataclass
class PutResult:
    id: str            # 64 hex: SHA-256 of the uploaded Draco bytes
    n_vertices: int    # as decoded, before the server's cleaning
    n_faces: int
    existed: bool      # the shape was already stored


@dataclass
class HasResult:
    stored: bool
    prepared: bool     # the default bases are cached
    n_vertices: int
    n_faces: int


@dataclass
class PrepareResult:
    n_vertices: int    # after cleaning
    n_faces: int
    k_lb: int
    k_elastic: int
    cached: bool       # nothing was computed
    t_clean: float
    t_lb: float
    t_elastic: float
    t_desc: float


@dataclass
class DistanceResult:
    total: float            # in [0, 1)
    point_xy: float
    point_yx: float
    spectrum_lb: float
    spectrum_elastic: float  # -1 when a shape has no elastic spectrum
    t_total: float = 0.0     # server side, seconds (0 inside a MATCH answer)

    def __float__(self):
        return self.total


@dataclass
class MatchResult:
    map: Any                  # vertex of Y per input vertex of X (-1: none); numpy or list
    map_yx: Any               # vertex of X per vertex of Y when want_yx, else None
    fmap: Any                 # kC x kC functional map when want_fmap, else None
    init_used: str            # "nn" or "sinkhorn": the start that won
    flipped: bool             # the orientation fix was applied
    orientation: float        # in [-1, 1]
    dirichlet: float          # Dirichlet energy of the map
    confidence: Optional[float]       # in [0, 1]; None from a protocol version 1 server
    distance: Optional[DistanceResult]  # when want_distance
    t_prepare: float          # server-side time split, seconds
    t_init: float
    t_refine: float
    t_distance: float
    t_total: float


@dataclass
class Hit:
    id: str
    distance: float


@dataclass
class QueryResult:
    hits: List[Hit] = field(default_factory=list)  # ascending distance
    n_considered: int = 0
    t_total: float = 0.0


# ---- requests ----
class Request:
    """One operation. op: its opcode; compute: it goes through the server's job queue (its
    answer may wait behind other work, section 3)."""
    op = 0
    compute = False

    def payload(self, ctx):
        raise NotImplementedError

    def decode(self, ctx, body):
        raise NotImplementedError

    def name(self):
        return wire.OP_NAMES[self.op]


class HelloRequest(Request):
    """The first exchange of a connection (section 5.1); Client sends it itself."""
    op = wire.HELLO

    def __init__(self, max_response, affinity, token):
        self.body = wire.enc_hello(max_response, affinity, token)

    def payload(self, ctx):
        return self.body

    def decode(self, ctx, body):
        return wire.dec_hello(body)


class PingRequest(Request):
    op = wire.PING

    def __init__(self):
        self.opaque = time.monotonic_ns() & 0xFFFFFFFFFFFFFFFF
        self.sent = None

    def payload(self, ctx):
        self.sent = time.monotonic()
        return struct.pack("<Q", self.opaque)

    def decode(self, ctx, body):
        if wire.dec_ping(body) != self.opaque:
            raise ProtocolViolation("PING answer does not echo the request")
        return time.monotonic() - self.sent  # round trip, seconds


class StatsRequest(Request):
    op = wire.STATS

    def payload(self, ctx):
        return b""

    def decode(self, ctx, body):
        return wire.dec_stats(body)


class PutRequest(Request):
    """shape: Draco bytes (uploaded as is), a mesh file path (a .drc file as is, any other
    format encoded by the shapematch CLI: meshes.py), or (vertices, faces) arrays."""
    op = wire.PUT_SHAPE
    compute = True

    def __init__(self, shape, prepare=False, cli=None):
        if isinstance(shape, (bytes, bytearray, memoryview)):
            self.draco = bytes(shape)
        elif isinstance(shape, (str, os.PathLike)):
            self.draco = encode_file(shape, cli)
        elif isinstance(shape, tuple) and len(shape) == 2:
            self.draco = encode_arrays(shape[0], shape[1], cli)
        else:
            raise TypeError("put takes Draco bytes, a mesh file path or (vertices, faces), "
                            "not %s" % type(shape).__name__)
        if not self.draco:
            raise MeshError("empty Draco bytes")
        self.prepare = bool(prepare)
        self.id = hashlib.sha256(self.draco).digest()  # the shape id (section 1)

    def payload(self, ctx):
        return wire.enc_put(self.id, self.draco, self.prepare)

    def decode(self, ctx, body):
        sid, nv, nf, existed = wire.dec_put(body)
        if sid != self.id:
            raise ProtocolViolation("PUT_SHAPE answer names another shape")
        return PutResult(_hex(sid), nv, nf, existed)


class HasRequest(Request):
    op = wire.HAS_SHAPE

    def __init__(self, shape):
        self.id = shape_id(shape)

    def payload(self, ctx):
        return self.id

    def decode(self, ctx, body):
        return HasResult(*wire.dec_has(body))


class DropRequest(HasRequest):
    op = wire.DROP_SHAPE

    def decode(self, ctx, body):
        wire.dec_empty(body, "DROP_SHAPE")


class PrepareRequest(Request):
    op = wire.PREPARE
    compute = True

    def __init__(self, shape, k_lb=0, k_elastic=0, eta=0.0):
        self.id = shape_id(shape)
        self.body = wire.enc_prepare(self.id, k_lb, k_elastic, eta)  # checks the ranges now

    def payload(self, ctx):
        return self.body

    def decode(self, ctx, body):
        nv, nf, klb, kel, flags, tc, tl, te, td = wire.dec_prepare(body)
        return PrepareResult(nv, nf, klb, kel, bool(flags & 1), tc * 1e-6, tl * 1e-6,
                             te * 1e-6, td * 1e-6)


BASES = {"default": 0, "lb": 1, "elastic": 2, "hybrid": 3}
INITS = {"default": 0, "nn": 1, "sinkhorn": 2}
MULTIRES = {"auto": 0, "on": wire.M_MULTIRES, "off": wire.M_DIRECT}


def _choice(name, value, table):
    if value in table:
        return table[value]
    raise ValueError("%s must be one of %s, not %r" % (name, ", ".join(table), value))


class MatchRequest(Request):
    """MATCH x -> y with the options of `shapematch match` (0 / None = server default):
    basis ("default", "lb", "elastic", "hybrid"), init ("default", "nn", "sinkhorn"), k0,
    k1, step, eta, sinkhorn_levels (None = default; 0 turns the Sinkhorn refinement off),
    multi_start (None, True, False), landmarks (pairs (vx, vy) of input vertices),
    init_map (a vertex of y per input vertex of x, -1 allowed), want_yx, want_fmap,
    want_distance, deadline_ms, multires ("auto": the server's choice by vertex count, "on":
    through the coarse level, "off": the direct path; "on" and "off" need a protocol version
    3 server, else OverLimit and nothing is sent)."""
    op = wire.MATCH
    compute = True
    _wants = True

    def __init__(self, x, y, basis="default", init="default", k0=0, k1=0, step=0, eta=0.0,
                 sinkhorn_levels=None, multi_start=None, landmarks=None, init_map=None,
                 want_yx=False, want_fmap=False, want_distance=False, deadline_ms=0,
                 multires="auto"):
        self.x, self.y = shape_id(x), shape_id(y)
        flags = 0
        if self._wants:
            flags |= (wire.M_WANT_YX if want_yx else 0) | (wire.M_WANT_FMAP if want_fmap else 0)
            flags |= wire.M_WANT_DISTANCE if want_distance else 0
            flags |= _choice("multires", multires, MULTIRES)
        elif want_yx or want_fmap or want_distance or multires != "auto":
            raise ValueError("want_yx, want_fmap, want_distance and multires are MATCH options")
        if multi_start is not None:
            flags |= wire.M_MULTI_START if multi_start else wire.M_SINGLE_START
        levels = 0
        if sinkhorn_levels is not None:
            flags |= wire.M_SINKHORN_LEVELS
            levels = sinkhorn_levels
        lm = _int_list("landmarks", landmarks, 0) if landmarks is not None else []
        if len(lm) % 2:
            raise ValueError("landmarks must be pairs (vx, vy); got %d numbers" % len(lm))
        self.init_map = _int_list("init_map", init_map, -1) if init_map is not None else []
        # encoded now, so a bad option raises here and not in the middle of a batch
        self.body = wire.enc_match(self.x, self.y, _choice("basis", basis, BASES),
                                   _choice("init", init, INITS), flags, k0, k1, step, levels,
                                   eta, deadline_ms, lm, self.init_map)

    def payload(self, ctx):
        flags = struct.unpack_from("<H", self.body, 2 * wire.ID_LEN + 2)[0]
        if flags & (wire.M_MULTIRES | wire.M_DIRECT) and ctx.version < wire.VERSION_MULTIRES:
            raise OverLimit("the server speaks protocol version %d: choosing the path "
                            "(multires on/off) needs version %d"
                            % (ctx.version, wire.VERSION_MULTIRES))
        return self.body

    def decode(self, ctx, body):
        head, off_xy, off_yx, off_fmap, conf = wire.dec_match(ctx.version, body)
        nx, ny, kc, init_used, flags = head[:5]
        if self.init_map and nx != len(self.init_map):
            raise ProtocolViolation("map of %d entries for an init_map of %d"
                                    % (nx, len(self.init_map)))
        np = ctx.numpy
        fmap = None
        if kc:
            vals = struct.unpack_from("<%dd" % (kc * kc), body, off_fmap)
            if np is not None:
                fmap = np.array(vals, dtype=np.float64).reshape((kc, kc), order="F")
            else:  # rows of the column-major matrix
                fmap = [[vals[j * kc + i] for j in range(kc)] for i in range(kc)]
        dist = DistanceResult(*head[8:13]) if flags & 2 else None
        t = [v * 1e-6 for v in head[13:18]]
        return MatchResult(
            map=_int32_array(body, off_xy, nx, np),
            map_yx=_int32_array(body, off_yx, ny, np) if ny else None,
            fmap=fmap, init_used="nn" if init_used == 1 else "sinkhorn",
            flipped=bool(flags & 1), orientation=head[6], dirichlet=head[7],
            confidence=conf, distance=dist, t_prepare=t[0], t_init=t[1], t_refine=t[2],
            t_distance=t[3], t_total=t[4])


class DistanceRequest(MatchRequest):
    """DISTANCE x, y: MATCH's options without the want_* ones (section 5.8)."""
    op = wire.DISTANCE
    _wants = False

    def decode(self, ctx, body):
        dist, t_us = wire.dec_distance(body)
        return DistanceResult(*dist, t_total=t_us * 1e-6)


class QueryRequest(Request):
    """The k stored shapes nearest to shape; mode "default", "spectral" or "full";
    candidates: shapes to rank (None = every stored shape)."""
    op = wire.QUERY
    compute = True

    def __init__(self, shape, k=10, mode="default", candidates=None, deadline_ms=0):
        self.id = shape_id(shape)
        self.k = k
        cand = [shape_id(c) for c in candidates] if candidates else []
        self.body = wire.enc_query(self.id, k, _choice("mode", mode, wire.QUERY_MODES),
                                   deadline_ms, cand)

    def payload(self, ctx):
        return self.body

    def decode(self, ctx, body):
        hits, considered, t_us = wire.dec_query(body)
        if len(hits) > self.k:
            raise ProtocolViolation("QUERY answered %d hits for k = %d" % (len(hits), self.k))
        return QueryResult([Hit(_hex(i), d) for i, d in hits], considered, t_us * 1e-6)


class BatchRequest(Request):
    """The protocol's BATCH (section 5.10) of item requests; Client.server_batch sends it
    and reads its item frames. The item payloads are taken once, here."""
    op = wire.BATCH
    compute = True

    def __init__(self, items, ctx):
        if not items:
            raise ValueError("a BATCH needs at least one item")
        for i, r in enumerate(items):
            if r.op not in wire.BATCH_ITEM_OPS:
                raise ValueError("BATCH item %d is a %s request; items are PING, HAS_SHAPE, "
                                 "PREPARE, MATCH, DISTANCE or QUERY" % (i, r.name()))
        limit = ctx.limits.max_batch_items
        if limit and len(items) > limit:
            raise OverLimit("BATCH of %d items; the server takes at most %d" % (len(items), limit))
        self.items = items
        self.body = wire.enc_batch([(r.op, r.payload(ctx)) for r in items])

    def payload(self, ctx):
        return self.body
