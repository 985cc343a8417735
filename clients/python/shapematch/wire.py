"""The shapematch wire format (protocol/PROTOCOL.md, versions 1 to 3) as pure functions.

No sockets and no state here: frames and payloads go in and out as bytes, so the codec can
be checked on its own and the client (client.py) only moves bytes. Every decoder checks the
exact payload length the layout gives and raises ProtocolViolation otherwise; every encoder
checks field ranges and raises ValueError naming the field.
"""
import struct
from collections import namedtuple

from .errors import ProtocolViolation

MAGIC = b"\x89SMP"
HEADER_LEN = 24
VERSION_MIN, VERSION_MAX = 1, 3
VERSION_HELLO = 1        # the header version of both HELLO frames (section 5.1)
VERSION_CONFIDENCE = 2   # first version whose MATCH response ends with confidence
VERSION_MULTIRES = 3     # first version whose MATCH may choose its path (MULTIRES, DIRECT)
HELLO_MAX_PAYLOAD = 4096
MAX_TOKEN = 256
MAX_MSG = 1024
ID_LEN = 32

# Opcodes (section 5).
HELLO, PING, STATS, PUT_SHAPE, HAS_SHAPE, DROP_SHAPE, PREPARE = 1, 2, 3, 4, 5, 6, 7
MATCH, DISTANCE, QUERY, BATCH, CANCEL, GOAWAY = 8, 9, 10, 11, 12, 13
OP_NAMES = {1: "HELLO", 2: "PING", 3: "STATS", 4: "PUT_SHAPE", 5: "HAS_SHAPE",
            6: "DROP_SHAPE", 7: "PREPARE", 8: "MATCH", 9: "DISTANCE", 10: "QUERY",
            11: "BATCH", 12: "CANCEL", 13: "GOAWAY"}

# Header flags (section 2).
F_RESPONSE, F_PAYLOAD_CRC, F_MORE = 1, 2, 4

# Statuses (section 4); bit 15 marks the connection-fatal ones.
STATUS_NAMES = {
    0: "OK", 1: "BAD_REQUEST", 2: "UNKNOWN_OPCODE", 3: "NOT_FOUND", 4: "DECODE_FAILED",
    5: "MESH_REJECTED", 6: "LIMIT_EXCEEDED", 7: "ID_MISMATCH", 8: "BUSY", 9: "DEADLINE",
    10: "CANCELLED", 11: "INTERNAL", 12: "SHUTTING_DOWN", 13: "RESPONSE_TOO_LARGE",
    0x8001: "BAD_MAGIC", 0x8002: "UNSUPPORTED_VERSION", 0x8003: "BAD_HEADER_CRC",
    0x8004: "BAD_HEADER", 0x8005: "FRAME_TOO_LARGE", 0x8006: "BAD_PAYLOAD_CRC",
    0x8007: "PROTOCOL_ERROR", 0x8008: "UNAUTHORIZED", 0x8009: "TIMEOUT",
    0x800A: "TOO_MANY_CONNECTIONS", 0x800B: "OVERLOADED",
}
OK, BUSY = 0, 8


def status_is_fatal(status):
    return bool(status & 0x8000)


def status_name(status):
    """The protocol's name of a status; an unknown one is named by its bit 15 (section 7)."""
    if status in STATUS_NAMES:
        return STATUS_NAMES[status]
    return "UNKNOWN_FATAL" if status_is_fatal(status) else "UNKNOWN"


# ---- CRC32C (Castagnoli, reflected 0x82F63B78) ----
def _crc32c_table():
    table = []
    for n in range(256):
        c = n
        for _ in range(8):
            c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
        table.append(c)
    return table


_CRC_TABLE = _crc32c_table()


def crc32c(data):
    crc = 0xFFFFFFFF
    table = _CRC_TABLE
    for b in data:
        crc = table[(crc ^ b) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


# ---- frames ----
_HEADER = struct.Struct("<4sBBHIHHI")  # bytes 0..19; the CRC32C of them follows
Header = namedtuple("Header", "version opcode flags request_id status payload_len")


def encode_frame(version, opcode, request_id, payload, payload_crc=False):
    """A request frame (RESPONSE clear, status 0). payload_crc appends the CRC32C trailer."""
    if not 1 <= request_id <= 0xFFFFFFFF:
        raise ValueError("request_id must be 1..2^32-1")
    flags = 0
    if payload_crc:
        payload = bytes(payload) + struct.pack("<I", crc32c(payload))
        flags |= F_PAYLOAD_CRC
    head = _HEADER.pack(MAGIC, version, opcode, flags, request_id, 0, 0, len(payload))
    return head + struct.pack("<I", crc32c(head)) + payload


def parse_header(buf, limit):
    """Validates a server frame's 24 header bytes (section 2.1, plus what a response must
    carry) and returns a Header. limit: the largest payload the client accepts."""
    magic, version, opcode, flags, rid, status, reserved, plen = _HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        raise ProtocolViolation("server stream: bad magic %r" % bytes(magic))
    (crc,) = struct.unpack_from("<I", buf, 20)
    if crc != crc32c(bytes(buf[:20])):
        raise ProtocolViolation("server stream: header CRC mismatch")
    if not VERSION_MIN <= version <= VERSION_MAX:
        raise ProtocolViolation("server frame of protocol version %d" % version)
    if flags & ~(F_RESPONSE | F_PAYLOAD_CRC | F_MORE) or reserved or opcode == 0:
        raise ProtocolViolation("server frame header: unknown flag, reserved field or opcode 0")
    if not flags & F_RESPONSE:
        raise ProtocolViolation("server frame without the RESPONSE flag")
    if flags & F_PAYLOAD_CRC and plen < 4:
        raise ProtocolViolation("server frame: PAYLOAD_CRC with a payload under 4 bytes")
    if plen > limit:
        raise ProtocolViolation("server frame of %d payload bytes, over the limit of %d"
                                % (plen, limit))
    return Header(version, opcode, flags, rid, status, plen)


def frame_body(header, payload):
    """The body of a complete payload: the CRC trailer checked and removed when flagged."""
    if not header.flags & F_PAYLOAD_CRC:
        return payload
    body = payload[:-4]
    (crc,) = struct.unpack_from("<I", payload, len(payload) - 4)
    if crc != crc32c(body):
        raise ProtocolViolation("server frame: payload CRC mismatch")
    return body


# ---- payloads: requests ----
def _u16(name, v):
    if not isinstance(v, int) or not 0 <= v <= 0xFFFF:
        raise ValueError("%s must be an integer in 0..65535, not %r" % (name, v))
    return v


def _u32(name, v):
    if not isinstance(v, int) or not 0 <= v <= 0xFFFFFFFF:
        raise ValueError("%s must be an integer in 0..2^32-1, not %r" % (name, v))
    return v


def _eta(v):
    v = float(v)
    if not (v == 0 or (v > 0 and v != float("inf"))):
        raise ValueError("eta must be 0 (server default) or finite and > 0, not %r" % v)
    return v


def enc_hello(max_response, affinity, token):
    if len(token) > MAX_TOKEN:
        raise ValueError("token of %d bytes; at most %d" % (len(token), MAX_TOKEN))
    return (struct.pack("<HHI", VERSION_MIN, VERSION_MAX, _u32("max_response", max_response))
            + affinity + struct.pack("<HH", len(token), 0) + token)


def enc_put(shape_id, draco, prepare):
    return shape_id + struct.pack("<II", 1 if prepare else 0, 0) + draco


def enc_prepare(shape_id, k_lb, k_elastic, eta):
    return shape_id + struct.pack("<HHId", _u16("k_lb", k_lb), _u16("k_elastic", k_elastic),
                                  0, _eta(eta))


# MATCH request flags (section 5.7).
M_WANT_YX, M_WANT_FMAP, M_SINGLE_START = 1, 2, 4
M_WANT_DISTANCE, M_MULTI_START, M_SINKHORN_LEVELS = 8, 16, 32
M_MULTIRES, M_DIRECT = 64, 128   # version >= 3 only


def enc_match(x, y, basis, init, flags, k0, k1, step, sinkhorn_levels, eta, deadline_ms,
              landmarks, init_map):
    """MATCH and DISTANCE share this layout. landmarks: flat [vx0, vy0, vx1, ...] ints;
    init_map: ints >= -1. Both already validated by the caller (client.MatchOptions)."""
    if k0 and k1 and k0 > k1:
        raise ValueError("k0 (%d) must not exceed k1 (%d)" % (k0, k1))
    head = x + y + struct.pack(
        "<BBHHHHHIdII", basis, init, flags, _u16("k0", k0), _u16("k1", k1), _u16("step", step),
        _u16("sinkhorn_levels", sinkhorn_levels), len(landmarks) // 2, _eta(eta),
        _u32("deadline_ms", deadline_ms), len(init_map))
    return (head + struct.pack("<%di" % len(landmarks), *landmarks)
            + struct.pack("<%di" % len(init_map), *init_map))


QUERY_MODES = {"default": 0, "spectral": 1, "full": 2}


def enc_query(shape_id, k, mode, deadline_ms, candidates):
    if not isinstance(k, int) or not 1 <= k <= 0xFFFF:
        raise ValueError("query k must be an integer in 1..65535, not %r" % (k,))
    return (shape_id + struct.pack("<HBBIII", k, mode, 0, _u32("deadline_ms", deadline_ms),
                                   len(candidates), 0) + b"".join(candidates))


# ---- payloads: responses ----
def _exact(body, n, what):
    if len(body) != n:
        raise ProtocolViolation("%s answer of %d bytes, the layout says %d" % (what, len(body), n))


Hello = namedtuple("Hello", "version max_payload max_vertices max_faces max_inflight "
                            "max_batch_items max_query_k max_k idle_timeout_ms auth_required")


def dec_hello(body):
    _exact(body, 40, "HELLO")
    v, _, mp, mv, mf, mi, mb, mq, mk, idle, feat = struct.unpack("<HHIIIIIIIII", body)
    return Hello(v, mp, mv, mf, mi, mb, mq, mk, idle, bool(feat & 1))


ErrorPayload = namedtuple("ErrorPayload", "retry_after_ms detail message")


def dec_error(body):
    """The error payload of a non-OK frame; a malformed one yields empty fields rather than
    hiding the status it came with."""
    if len(body) < 12:
        return ErrorPayload(0, 0, "")
    retry, detail, n = struct.unpack_from("<III", body, 0)
    if n > MAX_MSG or len(body) != 12 + n:
        return ErrorPayload(retry, detail, "")
    return ErrorPayload(retry, detail, bytes(body[12:]).decode("utf-8", "replace"))


def dec_ping(body):
    _exact(body, 8, "PING")
    return struct.unpack("<Q", body)[0]


def dec_stats(body):
    if len(body) < 8:
        raise ProtocolViolation("STATS answer of %d bytes" % len(body))
    (count,) = struct.unpack_from("<I", body, 0)
    _exact(body, 8 + 32 * count, "STATS")
    out = {}
    for i in range(count):
        raw, value = struct.unpack_from("<24sQ", body, 8 + 32 * i)
        out[raw.split(b"\0", 1)[0].decode("ascii", "replace")] = value
    return out


def dec_put(body):
    _exact(body, 44, "PUT_SHAPE")
    nv, nf, flags = struct.unpack_from("<III", body, 32)
    return bytes(body[:32]), nv, nf, bool(flags & 1)


def dec_has(body):
    _exact(body, 12, "HAS_SHAPE")
    flags, nv, nf = struct.unpack("<III", body)
    return bool(flags & 1), bool(flags & 2), nv, nf


def dec_empty(body, what):
    _exact(body, 0, what)


def dec_prepare(body):
    _exact(body, 48, "PREPARE")
    return struct.unpack("<IIHHIQQQQ", body)


DIST_FIELDS = "total point_xy point_yx spectrum_lb spectrum_elastic"
_DIST = struct.Struct("<5d")


def dec_distance(body):
    _exact(body, 48, "DISTANCE")
    return _DIST.unpack_from(body, 0), struct.unpack_from("<Q", body, 40)[0]


_MATCH_HEAD = struct.Struct("<IIHBBIdd5dQQQQQ")  # 112 bytes, section 5.7


def dec_match(version, body):
    """Returns (fixed fields tuple, map_xy offset, map_yx offset, fmap offset, confidence or
    None): the arrays stay in body so the caller picks list or numpy without a copy here."""
    if len(body) < _MATCH_HEAD.size:
        raise ProtocolViolation("MATCH answer of %d bytes" % len(body))
    head = _MATCH_HEAD.unpack_from(body, 0)
    nx, ny, kc, init_used, flags = head[0], head[1], head[2], head[3], head[4]
    tail = 8 if version >= VERSION_CONFIDENCE else 0
    _exact(body, _MATCH_HEAD.size + 4 * (nx + ny) + 8 * kc * kc + tail, "MATCH")
    if init_used not in (1, 2) or flags & ~3 or head[5]:
        raise ProtocolViolation("MATCH answer: init_used %d, flags %#x" % (init_used, flags))
    off_xy = _MATCH_HEAD.size
    off_yx = off_xy + 4 * nx
    off_fmap = off_yx + 4 * ny
    confidence = None
    if tail:
        (confidence,) = struct.unpack_from("<d", body, len(body) - 8)
        if not 0.0 <= confidence <= 1.0:  # also false for NaN
            raise ProtocolViolation("MATCH answer: confidence %r not in [0, 1]" % confidence)
    return head, off_xy, off_yx, off_fmap, confidence


BATCH_ITEM_OPS = (PING, HAS_SHAPE, PREPARE, MATCH, DISTANCE, QUERY)  # section 5.10


def enc_batch(items):
    """items: (opcode, payload) pairs, each payload its opcode's request layout."""
    return struct.pack("<II", len(items), 0) + b"".join(
        struct.pack("<BBHI", op, 0, 0, len(p)) + p for op, p in items)


def dec_batch_item(body):
    """An item frame of a BATCH answer: (index, opcode, the item's payload)."""
    if len(body) < 8:
        raise ProtocolViolation("BATCH item answer of %d bytes" % len(body))
    index, op, _, _ = struct.unpack_from("<IBBH", body, 0)
    return index, op, body[8:]


def dec_batch_end(body):
    """The final frame of a BATCH answer: (n_items, n_ok)."""
    _exact(body, 8, "BATCH")
    n_items, n_ok = struct.unpack("<II", body)
    if n_ok > n_items:
        raise ProtocolViolation("BATCH end: %d ok of %d items" % (n_ok, n_items))
    return n_items, n_ok


def dec_query(body):
    if len(body) < 16:
        raise ProtocolViolation("QUERY answer of %d bytes" % len(body))
    count, considered, t_us = struct.unpack_from("<IIQ", body, 0)
    _exact(body, 16 + 40 * count, "QUERY")
    hits = []
    for i in range(count):
        off = 16 + 40 * i
        hits.append((bytes(body[off:off + 32]), struct.unpack_from("<d", body, off + 32)[0]))
    return hits, considered, t_us
