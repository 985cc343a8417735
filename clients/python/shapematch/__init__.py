"""shapematch: a Python client for shapematchd, the dense shape correspondence daemon.

Pure Python (standard library; numpy used when present), speaking protocol/PROTOCOL.md:

    import shapematch
    with shapematch.Client("127.0.0.1:7878") as c:
        a, b = c.put("cat.off"), c.put("lion.drc")
        r = c.match(a, b)            # r.map[i] = vertex of lion for vertex i of cat
        print(r.confidence, c.distance(a, b).total)

Non-Draco mesh files and vertex/face arrays are Draco-encoded by the shapematch CLI (see
shapematch.meshes). Errors raise shapematch.StatusError (status code and name) and the
other classes of shapematch.errors.
"""
from .client import NUMPY, Client, parse_address
from .errors import (ConnectFailed, ConnectionClosed, MeshError, OverLimit, ProtocolViolation,
                     ShapematchError, StatusError, Timeout)
from .requests import (BatchRequest, DistanceRequest, DistanceResult, DropRequest,
                       HasRequest, HasResult, Hit, MatchRequest, MatchResult, PingRequest,
                       PrepareRequest, PrepareResult, PutRequest, PutResult, QueryRequest,
                       QueryResult, StatsRequest)

__version__ = "0.1.0"
