"""Mesh bytes for PUT_SHAPE, and the small mesh files the examples read and write.

What PUT_SHAPE uploads (PROTOCOL.md 5.4) is Draco bytes, and a shape's id is their SHA-256.
A Draco encoder in pure Python is not reasonable, so:
  - a .drc file, or bytes the caller already holds, is uploaded as is;
  - any other mesh file is encoded by the shapematch CLI (`shapematch encode IN -o OUT.drc`,
    sequential, unquantized: vertex order kept), which writes exactly the bytes
    `shapematch put` uploads for that file, so ids and maps agree with the CLI's;
  - vertex and face arrays are written to a temporary OFF file (coordinates printed exactly,
    as repr() round-trips) and encoded the same way, so maps speak of the array's rows.
The CLI is found by the `cli` argument, else $SHAPEMATCH_CLI, else `shapematch` on PATH.
"""
import os
import shutil
import subprocess
import tempfile

from .errors import MeshError


def find_cli(cli=None):
    """Path of the shapematch CLI used as the Draco encoder; MeshError when there is none."""
    cand = cli or os.environ.get("SHAPEMATCH_CLI") or shutil.which("shapematch")
    if not cand:
        raise MeshError("encoding a non-Draco mesh needs the shapematch CLI: pass cli=PATH, "
                        "set $SHAPEMATCH_CLI, or put shapematch on PATH (or upload .drc bytes)")
    if not (os.path.isfile(cand) and os.access(cand, os.X_OK)):
        raise MeshError("shapematch CLI %r is not an executable file" % cand)
    return cand


def is_draco_name(path):
    return os.fspath(path).lower().endswith(".drc")


def encode_file(path, cli=None):
    """The Draco bytes `shapematch put` uploads for the mesh file at path."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise MeshError("%s: no such file" % path)
    if is_draco_name(path):
        with open(path, "rb") as f:
            data = f.read()
        if not data:
            raise MeshError("%s: empty file" % path)
        return data
    exe = find_cli(cli)
    with tempfile.TemporaryDirectory(prefix="shapematch-") as tmp:
        out = os.path.join(tmp, "mesh.drc")
        run = subprocess.run([exe, "encode", path, "-o", out], stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE)
        if run.returncode != 0:
            why = run.stderr.decode("utf-8", "replace").strip() or "exit %d" % run.returncode
            raise MeshError("%s: cannot be encoded: %s" % (path, why))
        with open(out, "rb") as f:
            return f.read()


def _rows(name, a, width):
    """a as a list of `width`-tuples (numpy arrays and nested sequences alike)."""
    rows = a.tolist() if hasattr(a, "tolist") else [list(r) for r in a]
    for i, r in enumerate(rows):
        if len(r) != width:
            raise MeshError("%s row %d has %d entries, expected %d" % (name, i, len(r), width))
    return rows


def encode_arrays(vertices, faces, cli=None):
    """Draco bytes of a triangle mesh given as vertices (n x 3 floats) and faces (m x 3
    vertex indices, 0-based): the map of a match then indexes these rows."""
    V = _rows("vertices", vertices, 3)
    F = _rows("faces", faces, 3)
    if not V or not F:
        raise MeshError("a mesh needs vertices and faces (got %d and %d)" % (len(V), len(F)))
    for i, f in enumerate(F):
        for v in f:
            if not (isinstance(v, int) and 0 <= v < len(V)):
                raise MeshError("face %d names vertex %r; vertices are 0..%d"
                                % (i, v, len(V) - 1))
    with tempfile.TemporaryDirectory(prefix="shapematch-") as tmp:
        path = os.path.join(tmp, "mesh.off")
        write_off(path, V, F)
        return encode_file(path, cli)


def write_off(path, vertices, faces):
    """An OFF file; repr() of a float round-trips, so the reader gets the same doubles."""
    with open(path, "w") as f:
        f.write("OFF\n%d %d 0\n" % (len(vertices), len(faces)))
        for x, y, z in vertices:
            f.write("%r %r %r\n" % (float(x), float(y), float(z)))
        for a, b, c in faces:
            f.write("3 %d %d %d\n" % (a, b, c))


def read_off(path):
    """(vertices, faces) of an OFF file of triangles, as lists; polygons are fanned."""
    with open(path) as f:
        words = []
        for line in f:
            words.extend(line.split("#", 1)[0].split())
    if not words or not words[0].endswith("OFF"):
        raise MeshError("%s: not an OFF file" % path)
    try:
        nv, nf = int(words[1]), int(words[2])
        at = 4
        V = []
        for _ in range(nv):
            V.append((float(words[at]), float(words[at + 1]), float(words[at + 2])))
            at += 3
        F = []
        for _ in range(nf):
            k = int(words[at])
            poly = [int(w) for w in words[at + 1:at + 1 + k]]
            at += 1 + k
            F.extend((poly[0], poly[j], poly[j + 1]) for j in range(1, k - 1))
    except (IndexError, ValueError):
        raise MeshError("%s: truncated or malformed OFF" % path) from None
    return V, F


def write_ply_colored(path, vertices, faces, colors):
    """An ASCII PLY with per-vertex RGB (0..255), which MeshLab and most viewers show."""
    with open(path, "w") as f:
        f.write("ply\nformat ascii 1.0\ncomment written by the shapematch Python client\n"
                "element vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
                "property uchar red\nproperty uchar green\nproperty uchar blue\n"
                "element face %d\nproperty list uchar int vertex_indices\nend_header\n"
                % (len(vertices), len(faces)))
        for (x, y, z), (r, g, b) in zip(vertices, colors):
            f.write("%.9g %.9g %.9g %d %d %d\n" % (x, y, z, r, g, b))
        for a, b, c in faces:
            f.write("3 %d %d %d\n" % (a, b, c))
