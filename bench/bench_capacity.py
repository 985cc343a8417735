#!/usr/bin/python3
"""bench_capacity: the capacity figures of docs/DEPLOY.md section 4, measured with the real
daemon, CLI and Debian's haproxy on loopback (issue 14).

    bench/bench_capacity.py [--build DIR] [--work DIR] [--pairs P] [--reps R] [--json OUT]

Shapes: the 40 Draco files of ../shared/data/tosca_classification_5k (5,000 vertices each,
Google's encoder), the daemons at their defaults (k = 100) but --threads 1, so every
figure is per core. Prints:
  1. disk per shape (Draco file + its two basis files, `du` of the store) and cache per
     prepared shape (STATS cache_bytes / shapes), as shapes per GB;
  2. preparation: the 40 shapes prepared by one worker, shapes/s;
  3. one daemon, one worker: distances/s (a batch of P mixed pairs, every shape cached) and
     matches/s (one `match --server` per class, shapes 0 -> 1 of the class, sequential);
  4. 1, 2 and 3 daemons on one shared data directory behind haproxy, configured as the
     shipped deploy/cluster/haproxy.cfg with only the first N server lines: 6 clients
     send a sixth of the P pairs each through the front at once (batches of mixed pairs go
     to the least loaded daemon); distances/s and the ratio to one daemon, with how many
     requests each daemon served (STATS `requests`: HELLO, PING and STATS included).
Times are medians of R runs. The machine's core count bounds what 3 daemons can add
(nproc is printed). Exit 77 without ../shared/data or haproxy, 1 on a failed command.
"""
import argparse
import json
import os
import re
import shutil
import socket
import statistics
import subprocess
import sys
import time

import smdaemon

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
TOSCA = os.path.abspath(os.path.join(ROOT, "..", "shared", "data", "tosca_classification_5k"))
HAPROXY_CFG = os.path.join(ROOT, "deploy", "cluster", "haproxy.cfg")
CLIENTS = 6  # concurrent batch clients through the front: 2 per daemon at 3 daemons


def die(msg):
    print("bench_capacity: " + msg, file=sys.stderr)
    sys.exit(1)


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class Daemon:
    def __init__(self, build, data, log):
        try:
            self.proc, self.port = smdaemon.start(
                os.path.join(build, "server", "shapematchd"), data,
                ["--threads", "1", "--prepare-on-put", "0", "--cache-mb", "4096"], log)
        except RuntimeError as e:
            die(str(e))
        self.addr = "127.0.0.1:%d" % self.port

    def stop(self):
        smdaemon.stop(self.proc, 30)


class Cli:
    def __init__(self, build):
        self.exe = os.path.join(build, "clients", "shapematch")

    def run(self, args, server):
        r = subprocess.run([self.exe] + args + ["--server", server, "--timeout", "600"],
                           capture_output=True, text=True)
        if r.returncode != 0:
            die("shapematch %s: %s" % (" ".join(args[:2]), r.stderr.strip()[-400:]))
        return r.stdout

    def stats(self, server):
        out = {}
        for line in self.run(["stats"], server).splitlines():
            k, _, v = line.partition(" ")
            out[k] = float(v) if v.replace(".", "", 1).isdigit() else v
        return out


def timed(fn):
    t0 = time.monotonic()
    fn()
    return time.monotonic() - t0


def shapes_by_class():
    """[(stem, class)] in labels.csv order."""
    out = []
    with open(os.path.join(TOSCA, "labels.csv")) as f:
        next(f)
        for line in f:
            path, cls = line.strip().split(",")[:2]
            out.append((os.path.basename(path).split(".")[0], cls))
    return out


def du(path):
    return sum(os.path.getsize(os.path.join(path, n)) for n in os.listdir(path))


def write_batch(path, pairs):
    with open(path, "w") as f:
        for a, b in pairs:
            f.write("%s %s\n" % (a, b))


def front_config(n, out):
    """The shipped haproxy.cfg with only the first n daemons' server lines."""
    keep = []
    with open(HAPROXY_CFG) as f:
        for line in f:
            m = re.match(r"\s*server d(\d+) ", line)
            if m and int(m.group(1)) > n:
                continue
            keep.append(line)
    with open(out, "w") as f:
        f.write("".join(keep))


def start_front(cfg, daemons, log):
    env = dict(os.environ)
    env["SM_FRONT_BIND"] = "127.0.0.1:%d" % free_port()
    for i in range(3):
        env["SM_DAEMON%d" % (i + 1)] = daemons[min(i, len(daemons) - 1)].addr
    proc = subprocess.Popen(["haproxy", "-db", "-f", cfg], env=env, stdout=log, stderr=log)
    return proc, env["SM_FRONT_BIND"]


def front_run(cli, front, batches):
    """The batches (files) sent at once by one client each; wall seconds."""
    t0 = time.monotonic()
    procs = [subprocess.Popen([cli.exe, "batch", b, "--server", front, "--timeout", "600",
                               "--inflight", "2"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True) for b in batches]
    for p in procs:
        _, err = p.communicate()
        if p.returncode != 0:
            die("batch through the front: " + err.strip()[-400:])
    return time.monotonic() - t0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--build", default=os.path.join(ROOT, "build"))
    ap.add_argument("--work", default="/tmp/sm-capacity")
    ap.add_argument("--pairs", type=int, default=36)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--json")
    a = ap.parse_args()
    if not os.path.isdir(TOSCA):
        print("bench_capacity: ../shared/data absent, skipped")
        return 77
    if not shutil.which("haproxy"):
        print("bench_capacity: haproxy not installed, skipped")
        return 77
    shutil.rmtree(a.work, ignore_errors=True)
    os.makedirs(a.work)
    data = os.path.join(a.work, "data")
    cli = Cli(a.build)
    res = {"nproc": os.cpu_count(), "pairs": a.pairs, "reps": a.reps}
    print("bench_capacity: %d cores, %d pairs per run, medians of %d runs"
          % (os.cpu_count(), a.pairs, a.reps))

    shapes = shapes_by_class()
    files = [os.path.join(TOSCA, "drc", s + ".drc") for s, _ in shapes]
    d = [Daemon(a.build, data, os.path.join(a.work, "d1.log"))]
    t_put = timed(lambda: cli.run(["put"] + files, d[0].addr))
    ids = [line.split()[0] for line in cli.run(["put"] + files, d[0].addr).splitlines()]
    t_prep = timed(lambda: cli.run(["put", "--prepare", "--inflight", "1"] + files, d[0].addr))
    st = cli.stats(d[0].addr)
    n = len(ids)
    disk = (du(os.path.join(data, "shapes")) + du(os.path.join(data, "bases"))) / n
    cache = st["cache_bytes"] / st["shapes"]
    res["disk_bytes_per_shape"] = disk
    res["cache_bytes_per_shape"] = cache
    res["prepare_shapes_per_s"] = n / t_prep
    print("1. per shape (5,000 vertices, k = 100): disk %.2f MB -> %.0f shapes per GB; cache "
          "%.2f MB -> %.0f shapes per GB of --cache-mb" % (disk / 1e6, 1e9 / disk, cache / 1e6,
                                                           1e9 / cache))
    print("2. %d shapes PUT in %.2f s; prepared by one worker in %.1f s: %.2f shapes/s"
          % (n, t_put, t_prep, n / t_prep))

    pairs = [(ids[i % n], ids[(i * 7 + 3) % n]) for i in range(a.pairs)]
    pairs = [(x, y) for x, y in pairs if x != y]
    write_batch(os.path.join(a.work, "all.txt"), pairs)
    t_dist = statistics.median(
        timed(lambda: cli.run(["batch", os.path.join(a.work, "all.txt"), "--inflight", "2"],
                              d[0].addr)) for _ in range(a.reps))
    first = {}
    for i, (_, cls) in enumerate(shapes):
        first.setdefault(cls, []).append(ids[i])
    mpairs = [v[:2] for v in first.values() if len(v) >= 2]
    t_match = statistics.median(
        timed(lambda: [cli.run(["match", x, y, "-o", os.devnull], d[0].addr) for x, y in mpairs])
        for _ in range(a.reps))
    res["distances_per_s_core"] = len(pairs) / t_dist
    res["matches_per_s_core"] = len(mpairs) / t_match
    print("3. one daemon, one worker: %d distances in %.1f s: %.3f distances/s; %d matches "
          "(within class) in %.1f s: %.3f matches/s"
          % (len(pairs), t_dist, len(pairs) / t_dist, len(mpairs), t_match,
             len(mpairs) / t_match))

    for i in (2, 3):
        d.append(Daemon(a.build, data, os.path.join(a.work, "d%d.log" % i)))
        cli.run(["put", "--prepare", "--inflight", "1"] + files, d[-1].addr)
    batches = []
    for c in range(CLIENTS):
        path = os.path.join(a.work, "client%d.txt" % c)
        write_batch(path, pairs[c::CLIENTS])
        batches.append(path)
    res["front"] = []
    base = None
    with open(os.path.join(a.work, "haproxy.log"), "w") as hlog:
        for nd in (1, 2, 3):
            cfg = os.path.join(a.work, "haproxy%d.cfg" % nd)
            front_config(nd, cfg)
            proc, front = start_front(cfg, d[:nd], hlog)
            for _ in range(100):
                if subprocess.run([cli.exe, "ping", "--server", front, "--timeout", "2"],
                                  capture_output=True).returncode == 0:
                    break
                time.sleep(0.1)
            r0 = [cli.stats(x.addr)["requests"] for x in d[:nd]]
            t = statistics.median(front_run(cli, front, batches) for _ in range(a.reps))
            served = [cli.stats(x.addr)["requests"] - r for x, r in zip(d[:nd], r0)]
            proc.terminate()
            proc.wait()
            rate = len(pairs) / t
            base = base or rate
            res["front"].append({"daemons": nd, "seconds": t, "distances_per_s": rate,
                                 "ratio": rate / base, "requests_served": served})
            print("4. %d daemon(s) behind haproxy, %d clients: %d distances in %.1f s: %.3f/s, "
                  "x%.2f of one daemon; requests served per daemon %s"
                  % (nd, CLIENTS, len(pairs), t, rate, rate / base, [int(s) for s in served]))
    for x in d:
        x.stop()
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
