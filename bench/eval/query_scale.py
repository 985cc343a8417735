#!/usr/bin/python3
"""query_scale: QUERY against a stored gallery of 520 shapes through the real daemon
(issue 11).

    bench/eval/query_scale.py [--build DIR] [--work DIR] [--threads 2] [--queries N]
                              [--full N] [--json OUT]

Gallery: the 40 shapes of tosca_classification_5k and 12 deformed copies of each, made by
the suite's deformation tool (eval_tool deform: principal-axis stretch 1.1-1.4, bulges,
a dent, decimation to 50% and 40%, normal noise), all stored and prepared in one daemon
(--threads workers, default 2; the store under --work persists, so a rerun costs only the
queries). Queries: stored shapes (a fixed-seed random sample of the gallery), each excluded from
its own candidates, top-10.

Prints, per mode: latency p50 / p90 / max over the queries (wall time of `shapematch
query`, client included), and the top-1 agreement of DEFAULT with the exhaustive answer.
Exhaustive: FULL mode (a match and the shipped distance against every stored shape) for
the first --full queries (each costs ~520 matches: 70 s with the distance preset of 2026-12-02); the
DEFAULT answer of every query is also compared with SPECTRAL mode's. The FULL queries
ask for every candidate, SPECTRAL too, so the script also scores shortlists of other
sizes m offline: top-1 = exhaustive and the exhaustive top-10's recall when the spectral
term's first m are ranked by the full distance. Exit 1 when a command fails.
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import smdaemon  # noqa: E402  (bench/smdaemon.py)

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
TOSCA = os.path.abspath(os.path.join(ROOT, "..", "shared", "data", "tosca_classification_5k"))
# (flag, amount, seed offset): 12 copies per shape; the seed picks the bulge / dent centre
# and the noise.
VARIANTS = [("stretch", 1.1, 0), ("stretch", 1.2, 0), ("stretch", 1.3, 0), ("stretch", 1.4, 0),
            ("bulge", 0.2, 0), ("bulge", 0.3, 0), ("bulge", 0.3, 1000), ("dent", 0.2, 0),
            ("decimate", 0.5, 0), ("decimate", 0.4, 0), ("noise", 0.1, 0), ("noise", 0.2, 0)]


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def run_parallel(cmds, jobs, env):
    procs, pending, bad = [], list(cmds), 0
    while pending or procs:
        while pending and len(procs) < jobs:
            procs.append(subprocess.Popen(pending.pop(0), env=env))
        for p in list(procs):
            if p.poll() is not None:
                bad += p.returncode != 0
                procs.remove(p)
        time.sleep(0.05)
    return bad


class Daemon:
    def __init__(self, build, work, threads, env):
        self.cli = os.path.join(build, "clients", "shapematch")
        self.proc, port = smdaemon.start(
            os.path.join(build, "server", "shapematchd"), os.path.join(work, "store"),
            ["--cache-mb", "8192", "--threads", str(threads)],
            os.path.join(work, "shapematchd.log"), env=env)
        env["SHAPEMATCH_SERVER"] = f"127.0.0.1:{port}"
        self.env = env

    def cli_run(self, args):
        r = subprocess.run([self.cli] + args, env=self.env, capture_output=True, text=True)
        if r.returncode:
            raise RuntimeError(f"shapematch {' '.join(args[:3])}: {r.stderr.strip()[:300]}")
        return r.stdout

    def stop(self):
        smdaemon.stop(self.proc)


def make_gallery(build, work, env):
    """The gallery's files, originals first in each group of 13."""
    tool = os.path.join(build, "bench", "eval", "eval_tool")
    ddir = os.path.join(work, "deformed")
    os.makedirs(ddir, exist_ok=True)
    files, labels, cmds = [], [], []
    with open(os.path.join(TOSCA, "labels.csv")) as f:
        rows = [line.strip().split(",") for line in f][1:]
    for q, (path, cls, _) in enumerate(rows):
        name = os.path.basename(path).split(".")[0]
        src = os.path.join(TOSCA, "drc", name + ".drc")
        files.append(src)
        labels.append(cls)
        for kind, amount, seed_off in VARIANTS:
            out = os.path.join(ddir, f"{name}_{kind}_{amount}_{seed_off}.drc")
            files.append(out)
            labels.append(cls)
            if not os.path.exists(out):
                cmds.append([tool, "deform", src, "-o", out, f"--{kind}", str(amount),
                             "--seed", str(q + 1 + seed_off)])
    if run_parallel(cmds, 2, env):
        raise RuntimeError("eval_tool deform failed")
    return files, labels


def query(d, sid, mode, k=10):
    t0 = time.time()
    out = d.cli_run(["query", sid, "-k", str(k), "--mode", mode, "--json"])
    return time.time() - t0, [(h["id"], h["distance"]) for h in json.loads(out)]


def shortlist_scores(ranked):
    """For shortlist sizes m: how often the best of the spectral term's first m by the full
    distance is the exhaustive top-1, and the exhaustive top-10's share in the top-10 of
    that shortlist. ranked: (ids by the spectral term, FULL hits (id, distance) ranked)."""
    out = {}
    for m in (10, 12, 14, 16, 20, 30):
        top1 = rec = 0
        for spec, hits in ranked:
            full = dict(hits)
            short = sorted(spec[:m], key=lambda h: (full.get(h, np.inf), h))
            top1 += bool(hits) and short[0] == hits[0][0]
            rec += len(set(short[:10]) & {h for h, _ in hits[:10]}) / 10
        out[m] = {"top1": [top1, len(ranked)], "top10_recall": rec / max(len(ranked), 1)}
    return out


def pct(v, p):
    return float(np.percentile(v, p)) if v else float("nan")


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--build", default=os.path.join(ROOT, "build"))
    ap.add_argument("--work", default=os.path.join(ROOT, "out", "query-scale"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--queries", type=int, default=60)
    ap.add_argument("--full", type=int, default=1)
    ap.add_argument("--json")
    a = ap.parse_args()
    if not os.path.isdir(TOSCA):
        print("query_scale: skipped (no ../shared/data)")
        return 0
    work = os.path.abspath(a.work)
    os.makedirs(work, exist_ok=True)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    t0 = time.time()
    files, labels = make_gallery(os.path.abspath(a.build), work, env)
    log(f"gallery: {len(files)} files ({time.time() - t0:.0f} s)")
    d = Daemon(os.path.abspath(a.build), work, a.threads, env)
    res = {"gallery": len(files), "threads": a.threads, "modes": {}}
    try:
        t1 = time.time()
        ids = {}
        for i in range(0, len(files), 40):  # a few requests, each preparing its shapes
            for line in d.cli_run(["put", "--prepare"] + files[i:i + 40]).splitlines():
                sid, path = line.split(None, 1)
                ids[path] = sid
        sids = [ids[f] for f in files]
        res["put_prepare_s"] = time.time() - t1
        log(f"stored and prepared in {res['put_prepare_s']:.0f} s")
        # warm-up: loads every stored shape into the daemon's cache once
        query(d, sids[0], "spectral")
        qs = [int(i) for i in np.random.default_rng(0).permutation(len(files))[:a.queries]]
        answers = {}
        for mode in ("default", "spectral"):
            lat, top1 = [], []
            for q in qs:
                t, hits = query(d, sids[q], mode)
                lat.append(t)
                top1.append(hits[0][0] if hits else None)
            answers[mode] = top1
            res["modes"][mode] = {"queries": len(qs), "p50_s": pct(lat, 50),
                                  "p90_s": pct(lat, 90), "max_s": max(lat)}
            log(f"{mode}: p50 {pct(lat, 50):.3f} s over {len(qs)} queries")
        full_lat, agree_full, ranked = [], 0, []
        for q, want in zip(qs[:a.full], answers["default"]):
            t, hits = query(d, sids[q], "full", len(files))
            full_lat.append(t)
            agree_full += bool(hits) and hits[0][0] == want
            spec = [h for h, _ in query(d, sids[q], "spectral", len(files))[1]]
            ranked.append((spec, hits))
            log(f"full query {len(full_lat)}/{a.full}: {t:.0f} s")
        if ranked:
            res["shortlists"] = shortlist_scores(ranked)
        if full_lat:
            res["modes"]["full"] = {"queries": len(full_lat), "p50_s": pct(full_lat, 50),
                                    "p90_s": pct(full_lat, 90), "max_s": max(full_lat)}
        res["top1_default_eq_full"] = [agree_full, len(full_lat)]
        same = sum(x == y for x, y in zip(answers["default"], answers["spectral"]))
        res["top1_default_eq_spectral"] = [same, len(qs)]
        by_id = {s: labels[i] for i, s in enumerate(sids)}
        right = sum(by_id.get(h) == labels[q] for q, h in zip(qs, answers["default"]))
        res["top1_same_class"] = [right, len(qs)]
    finally:
        d.stop()
    print(f"\nQUERY, top-10, gallery {res['gallery']} stored shapes, {a.threads} workers "
          f"(prepared in {res['put_prepare_s']:.0f} s)")
    print("| mode | queries | p50 (s) | p90 (s) | max (s) |\n|---|---|---|---|---|")
    for mode, r in res["modes"].items():
        print(f"| {mode} | {r['queries']} | {r['p50_s']:.3f} | {r['p90_s']:.3f} | "
              f"{r['max_s']:.3f} |")
    if res.get("shortlists"):
        print("\nShortlist m (the spectral term's first m, ranked by the full distance) "
              "against the exhaustive ranking, over the FULL queries:")
        print("| m | top-1 = exhaustive | top-10 recall |\n|---|---|---|")
        for m, r in res["shortlists"].items():
            print(f"| {m} | {r['top1'][0]}/{r['top1'][1]} | {r['top10_recall']:.3f} |")
    for key, text in (("top1_default_eq_full", "DEFAULT top-1 = exhaustive (FULL) top-1"),
                      ("top1_default_eq_spectral", "DEFAULT top-1 = SPECTRAL top-1"),
                      ("top1_same_class", "DEFAULT top-1 of the query's class")):
        k, n = res[key]
        print(f"{text}: {k}/{n}" + (f" ({k / n:.3f})" if n else ""))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
