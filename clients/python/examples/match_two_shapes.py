#!/usr/bin/env python3
"""Matches two shapes through shapematchd and writes the match as two coloured PLY files.

    match_two_shapes.py [A.off B.off] [-o PREFIX] [--server HOST:PORT] [--cli PATH]

Without shapes it makes the demo's pair (deploy/demo.sh) with `shapematch synth`: a bumpy
blob and the same blob with higher bumps, stretched 1.2x along y (same vertex order, so the
true map is the identity). Without --server (or $SHAPEMATCH_SERVER) it starts a shapematchd
of its own on a free loopback port with a temporary store, and stops it at the end.

Output: PREFIX_source.ply, the source with a smooth colour field made from its coordinates,
and PREFIX_target.ply, the target coloured through the map: each target vertex takes the
mean colour of the source vertices mapped onto it, and target vertices no source vertex
reaches take their neighbours' colours. Open both in MeshLab: a good map shows the same
colours on corresponding parts. Shapes must be OFF files (the PLY needs their vertices).
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import shapematch  # noqa: E402
from shapematch.meshes import find_cli, read_off, write_ply_colored  # noqa: E402


def coordinate_colors(vertices):
    """RGB per vertex from its position in the bounding box: smooth, and different on
    different parts of the shape, so a map's errors show as colour jumps."""
    lo = [min(v[a] for v in vertices) for a in range(3)]
    hi = [max(v[a] for v in vertices) for a in range(3)]
    span = [h - l if h > l else 1.0 for l, h in zip(lo, hi)]
    return [tuple(int(round(255 * (0.1 + 0.9 * (v[a] - lo[a]) / span[a]))) for a in range(3))
            for v in vertices]


def pull_colors(source_colors, point_map, n_target, target_faces):
    """Target colours through a map source -> target (point_map[i] = target vertex of
    source vertex i, -1 = none)."""
    sums = [[0, 0, 0, 0] for _ in range(n_target)]
    for i, j in enumerate(point_map):
        if j >= 0:
            s = sums[j]
            for a in range(3):
                s[a] += source_colors[i][a]
            s[3] += 1
    colors = [tuple(s[a] // s[3] for a in range(3)) if s[3] else None for s in sums]
    neighbours = [set() for _ in range(n_target)]
    for f in target_faces:
        for a in f:
            neighbours[a].update(f)
    # fill the vertices no source vertex reached, one ring of neighbours at a time
    while any(c is None for c in colors):
        filled = list(colors)
        for v, c in enumerate(colors):
            if c is None:
                known = [colors[u] for u in neighbours[v] if colors[u] is not None]
                if known:
                    filled[v] = tuple(sum(k[a] for k in known) // len(known) for a in range(3))
        if filled == colors:  # a component with no image at all
            filled = [c if c is not None else (128, 128, 128) for c in colors]
        colors = filled
    return colors


def find_daemon(cli):
    """shapematchd next to the CLI (an install), in the build tree beside it, or on PATH."""
    here = os.path.dirname(os.path.abspath(cli))
    for cand in (os.path.join(here, "shapematchd"),
                 os.path.join(here, "..", "server", "shapematchd")):
        if os.access(cand, os.X_OK):
            return cand
    found = shutil.which("shapematchd")
    if not found:
        sys.exit("match_two_shapes: no --server given and no shapematchd found to start")
    return found


def start_daemon(binary, workdir):
    """Starts shapematchd on a free loopback port; returns (process, 'host:port')."""
    log_path = os.path.join(workdir, "shapematchd.log")
    log = open(log_path, "w")
    proc = subprocess.Popen([binary, "--bind", "127.0.0.1", "--port", "0", "--data-dir",
                             os.path.join(workdir, "store")], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=log)
    log.close()
    for _ in range(200):
        with open(log_path) as f:
            for line in f:
                if "msg=listening port=" in line:
                    port = line.split("msg=listening port=")[1].split()[0]
                    return proc, "127.0.0.1:" + port
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.kill()
    sys.exit("match_two_shapes: shapematchd did not start; its log is %s" % log_path)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("shapes", nargs="*", metavar="SHAPE.off")
    ap.add_argument("-o", "--prefix", default="match", help="output prefix (default: match)")
    ap.add_argument("--server", default=os.environ.get("SHAPEMATCH_SERVER"))
    ap.add_argument("--cli", help="the shapematch CLI (default: $SHAPEMATCH_CLI or PATH)")
    args = ap.parse_args()
    if len(args.shapes) not in (0, 2):
        ap.error("give two OFF shapes, or none for the demo's pair")
    cli = find_cli(args.cli)
    work = tempfile.mkdtemp(prefix="shapematch-example-")
    daemon = None
    try:
        shapes = args.shapes
        if not shapes:
            shapes = [os.path.join(work, "blob1.off"), os.path.join(work, "blob2.off")]
            for path, extra in ((shapes[0], ["--amp", "0.8"]),
                                (shapes[1], ["--amp", "0.95", "--stretch", "1,1.2,1"])):
                subprocess.run([cli, "synth", "blob", "--subdiv", "4", "--seed", "1", *extra,
                                "-o", path], check=True, stderr=subprocess.DEVNULL)
        server = args.server
        if not server:
            daemon, server = start_daemon(find_daemon(cli), work)

        # the five lines of the README
        with shapematch.Client(server, cli=cli) as c:
            a, b = c.put(shapes[0]), c.put(shapes[1])
            r = c.match(a, b, want_distance=True)

        (va, fa), (vb, fb) = read_off(shapes[0]), read_off(shapes[1])
        colors = coordinate_colors(va)
        point_map = r.map.tolist() if hasattr(r.map, "tolist") else r.map
        write_ply_colored(args.prefix + "_source.ply", va, fa, colors)
        write_ply_colored(args.prefix + "_target.ply", vb, fb,
                          pull_colors(colors, point_map, len(vb), fb))
        print("matched %d -> %d vertices: confidence %.3f, orientation %.3f, distance %.6f; "
              "server time %.2f s (bases %.2f, init %.2f, refine %.2f)"
              % (len(point_map), len(vb), r.confidence if r.confidence is not None else -1,
                 r.orientation, r.distance.total, r.t_total, r.t_prepare, r.t_init,
                 r.t_refine))
        print("wrote %s_source.ply and %s_target.ply" % (args.prefix, args.prefix))
    finally:
        if daemon is not None:
            daemon.terminate()
            daemon.wait(60)
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
