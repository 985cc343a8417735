"""Exceptions of the shapematch client. All derive from ShapematchError.

StatusError carries what the server said (PROTOCOL.md section 4): the numeric status, its
protocol name, the status-specific detail and the retry hint. A request-level status leaves
the connection usable; a fatal one (bit 15) closes it, as do the other classes except
MeshError and the ValueError/TypeError raised for bad arguments before anything is sent.
"""


class ShapematchError(Exception):
    """Base class of every error the client raises on its own behalf."""


class StatusError(ShapematchError):
    """The server answered a non-OK status.

    status: the protocol's code (e.g. 3); name: its name (e.g. "NOT_FOUND"); detail and
    retry_after_ms: the error payload's fields; message: the server's text (for logs);
    fatal: True when the status closed the connection (bit 15).
    """

    def __init__(self, status, name, detail=0, retry_after_ms=0, message="", request=""):
        self.status = status
        self.name = name
        self.detail = detail
        self.retry_after_ms = retry_after_ms
        self.message = message
        self.fatal = bool(status & 0x8000)
        text = "%s%s (status %d%s)%s" % (
            request + ": " if request else "", name, status,
            ", detail %d" % detail if detail else "", ": " + message if message else "")
        super().__init__(text)


class ProtocolViolation(ShapematchError):
    """The server's bytes do not follow PROTOCOL.md; the connection is closed."""


class ConnectionClosed(ShapematchError):
    """The connection is closed (by the server, by an earlier error, or by close())."""


class Timeout(ShapematchError):
    """A wait exceeded its time limit; the connection is closed (an answer may be owed)."""


class MeshError(ShapematchError):
    """A mesh file or array cannot be read or Draco-encoded (names the file and why)."""


class OverLimit(ShapematchError):
    """A request exceeds a limit the server announced in HELLO; nothing was sent."""


class ConnectFailed(ShapematchError):
    """The address does not parse or resolve, or nothing accepts the connection."""
