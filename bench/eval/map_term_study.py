#!/usr/bin/python3
"""map_term_study: does a term computed through the maps make the shipped distance better
(issue 11)? With a held-out check, as spectral_study.py does for the spectral term.

    bench/eval/map_term_study.py [--build DIR] [--work DIR] [--out docs/eval] [--configs C]

The shipped distance (core/sm_distance.h) is the spectral spread S alone (map weight 0).
This script computes, with bench/eval/dist_dump (the distance's own match preset:
sm_distance_match_opts, refinement up to k = 50, no soft Sinkhorn step), the maps of

  - every pair of tosca_classification_5k's 40 shapes (780 pairs),
  - set A: the suite's robustness queries (first shape of each class, 5 deformations)
    against the 39 other shapes (1560 pairs),
  - set B, held out: the same deformations of the 2nd..5th shape of each class (6240
    pairs),

and scores candidate map terms M, alone and as the product combines them:
(1 - e^-S + w (1 - e^-M)) / (1 + w) (core/sm_distance.c; both terms are of the same size:
their medians over the 40 shapes' pairs are 0.138 and 0.129 for the shipped M). Per vertex v of
X the map term compares the log heat kernel signatures log h_X(v, t) and log h_Y(T(v), t)
(LB basis, k = 100) at 8 times 10^-3..10^-1 ("all"), the first 4 ("small") or the last 4
("large"), raw ("H") or with each time's area-weighted mean removed ("Hc", blind to
scale), as an RMS over the times; M is the area-weighted mean, median (q0.5) or first
quartile (q0.25) of that over X, averaged over both directions.

Choice rule (on the 40 shapes and set A only, as spectral_study's): a row qualifies when it
is at least S on leave-one-out, 80/20 and 70/30 (accuracy and F1) and on every deformation
of A; B then says whether it holds on shapes it never saw (B >= S and >= ShapeDNA on every
deformation). Deformed files and dumps are cached in --work (the deformed meshes are
spectral_study's: run it first, or this script makes them the same way). Writes
OUT/map_term_study.json and prints the table.
"""
import argparse
import json
import os
import subprocess
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import suite  # noqa: E402
import dist_study  # noqa: E402
import spectral_study  # noqa: E402

T8 = 10.0 ** (-3 + 2 * np.arange(8) / 7)
TIMES = {"all": slice(0, 8), "small": slice(0, 4), "large": slice(4, 8)}
STATS = ("mean", "q0.5", "q0.25")
WEIGHTS = (0.5, 1.0, 2.0)
# Map variants (--configs CONFIG.TAG): dist_dump's options beside the distance preset.
VARIANTS = {"samples": ["--init-samples"]}


def load_shape(d, name):
    with open(os.path.join(d, f"shape_{name}.bin"), "rb") as f:
        n, nf, klb, _ = np.fromfile(f, np.int32, 4)
        np.fromfile(f, np.float64, 3 * n)
        np.fromfile(f, np.int32, 3 * nf)
        mass = np.fromfile(f, np.float64, n)
        lev = np.fromfile(f, np.float64, klb)
        lphi = np.fromfile(f, np.float32, n * klb).reshape(klb, n).T.astype(np.float64)
    w = np.exp(-np.outer(np.maximum(lev, 0), T8))
    H = np.log(np.maximum((lphi ** 2) @ w, 1e-300))
    return {"mass": mass, "ev": lev[lev > 1e-9 * abs(lev[-1])], "H": H,
            "Hc": H - (mass @ H) / mass.sum()}


def load_maps(d, cfg):
    """(i, j) -> (T_xy, T_yx), dist_dump's records (dist_study.load_pairs)."""
    return {p: rec[:2] for p, rec in dist_study.load_pairs(d, cfg).items()}


def wquantile(r, m, q):
    o = np.argsort(r)
    c = np.cumsum(m[o])
    return r[o][np.searchsorted(c, q * c[-1])]


def pair_terms(a, b, Txy, Tyx):
    t = {"S": spectral_study.spectral(a["ev"], b["ev"], 70, 0.0),
         "shapedna": spectral_study.shapedna(a["ev"], b["ev"])}
    for key in ("H", "Hc"):
        for tn, sl in TIMES.items():
            rx = np.sqrt(((a[key][:, sl] - b[key][Txy, sl]) ** 2).mean(1))
            ry = np.sqrt(((b[key][:, sl] - a[key][Tyx, sl]) ** 2).mean(1))
            for st in STATS:
                if st == "mean":
                    v = [a["mass"] @ rx / a["mass"].sum(), b["mass"] @ ry / b["mass"].sum()]
                else:
                    q = float(st[1:])
                    v = [wquantile(rx, a["mass"], q), wquantile(ry, b["mass"], q)]
                t[f"{key} {tn} {st}"] = 0.5 * (v[0] + v[1])
    return t


def make_sets(work, build):
    """Shape list (40 + deformed), labels, queries (list index, original, rank, kind)."""
    s = suite.Suite.__new__(suite.Suite)
    s.env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    rows = suite.Suite.tosca_labels(s)
    names, labels = [r[0] for r in rows], [r[1] for r in rows]
    L, lab, qs, cmds = [(n, f) for n, _, f in rows], list(labels), [], []
    tool = os.path.join(build, "bench", "eval", "eval_tool")
    ddir = os.path.join(work, "deformed")
    os.makedirs(ddir, exist_ok=True)
    for cls in dict.fromkeys(labels):
        members = [i for i, l in enumerate(labels) if l == cls]
        for rank in spectral_study.RANKS:
            q = members[rank]
            for kind, st in suite.DEFORMATIONS:
                nm = f"{names[q]}_{kind}_{st}"
                out = os.path.join(ddir, nm + ".drc")
                if not os.path.exists(out):
                    cmds.append([tool, "deform", rows[q][2], "-o", out, f"--{kind}", str(st),
                                 "--seed", str(q + 1)])
                qs.append((len(L), q, rank, f"{kind} {st}"))
                L.append((nm, out))
                lab.append(cls)
    if any(c != 0 for c in suite.Suite.run_parallel(s, cmds)):
        raise RuntimeError("eval_tool deform failed")
    return L, lab, qs


def dump(build, work, L, qs, cfgs):
    dd = os.path.join(work, "dump")
    os.makedirs(dd, exist_ok=True)
    lst, prs = os.path.join(dd, "shapes.txt"), os.path.join(dd, "pairs.txt")
    with open(lst, "w") as f:
        f.writelines(f"{n} {os.path.abspath(p)}\n" for n, p in L)
    pairs = [(i, j) for i in range(40) for j in range(i + 1, 40)]
    pairs += [(i, g) for i, q, _, _ in sorted(qs, key=lambda x: x[2] > 0) for g in range(40)
              if g != q]
    with open(prs, "w") as f:
        f.writelines(f"{i} {j}\n" for i, j in pairs)
    tool = os.path.join(build, "bench", "eval", "dist_dump")
    missing = [c for c in cfgs if len(load_maps(dd, c)) < len(pairs)]
    if missing:
        dump_shapes(tool, dd, work, L, lst)
    for tag in dict.fromkeys(c.partition(".")[2] for c in missing):
        bases = [c.partition(".")[0] for c in missing if c.partition(".")[2] == tag]
        extra = ["--tag", tag] + VARIANTS[tag] if tag else []
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
        base = [tool, "--list", lst, "--out", dd, "--cache", os.path.join(work, "cache")]
        ps = [subprocess.Popen(base + ["--pairs", prs, "--configs", ",".join(bases),
                                       "--part", f"{p}/2"] + extra, env=env) for p in (0, 1)]
        if any(p.wait() for p in ps):
            raise RuntimeError("dist_dump failed")
    return dd


def dump_shapes(tool, dd, work, L, lst):
    """The shapes' records and bases, half the shapes per process."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    halves = [os.path.join(dd, f"half{h}.txt") for h in (0, 1)]
    for h, path in enumerate(halves):
        with open(path, "w") as f:
            f.writelines(f"{n} {os.path.abspath(p)}\n" for n, p in L[h::2])
    ps = [subprocess.Popen([tool, "--list", p, "--out", dd, "--cache",
                            os.path.join(work, "cache"), "--shapes-only"], env=env)
          for p in halves]
    if any(p.wait() for p in ps):
        raise RuntimeError("dist_dump --shapes-only failed")


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--build", default=os.path.join(suite.ROOT, "build"))
    ap.add_argument("--work", default=os.path.join(suite.ROOT, "out", "spectral-study"))
    ap.add_argument("--out", default=os.path.join(suite.ROOT, "docs", "eval"))
    ap.add_argument("--configs", default="sinkhorn+lb",
                    help="comma list of CONFIG or CONFIG.TAG, TAG one of "
                    f"{', '.join(VARIANTS)} (a variant of the preset's maps)")
    a = ap.parse_args()
    if not os.path.isdir(suite.TOSCA):
        print("map_term_study: skipped (no ../shared/data)")
        return 0
    build, work = os.path.abspath(a.build), os.path.abspath(a.work)
    L, labels, qs = make_sets(work, build)
    cfgs = a.configs.split(",")
    dd = dump(build, work, L, qs, cfgs)
    kinds = [f"{k} {st}" for k, st in suite.DEFORMATIONS]
    F = {i: load_shape(dd, L[i][0]) for i in range(len(L))}
    # Rows of other map variants scored before (same script, same sets) are kept.
    path = os.path.join(a.out, "map_term_study.json")
    old = json.load(open(path)) if os.path.exists(path) else {}
    res = {"deformations": kinds, "configs": old.get("configs", {})}
    for cfg in cfgs:
        T = {p: pair_terms(F[p[0]], F[p[1]], *m) for p, m in load_maps(dd, cfg).items()}
        res["configs"][cfg] = score_rows(T, labels, qs, kinds)
    with open(path, "w") as f:
        json.dump(res, f, indent=1)
    for cfg in cfgs:
        rows = res["configs"][cfg]
        print(f"{cfg}: {'':24s} LOO   80/20       70/30       mAP   | A | B")
        for name, r in rows.items():
            print(f"{name:30s} {r['loo']:.3f} {r['split_80_20']:.3f}/{r['f1_80_20']:.3f} "
                  f"{r['split_70_30']:.3f}/{r['f1_70_30']:.3f} {r['map']:.3f} | "
                  f"{' '.join(str(r['A'][k]) for k in kinds)} | "
                  f"{' '.join(str(r['B'][k]) for k in kinds)} ({sum(r['B'].values())})"
                  f"{'  rule' if r['rule'] else ''}{'  B ok' if r['B_ok'] else ''}")
    return 0


def score_rows(T, labels, qs, kinds):
    iu = list(zip(*np.triu_indices(40, 1)))
    sq = lambda s: 1.0 - np.exp(-s)  # noqa: E731  (the product's squash)

    def get(i, j):
        return T.get((i, j)) or T[(j, i)]

    def score(fn):
        D = np.zeros((40, 40))
        for i, j in iu:
            D[i, j] = D[j, i] = fn(get(i, j))
        k8, r = suite.knn_scores(D, labels[:40]), suite.retrieval_scores(D, labels[:40])
        right = {"A": dict.fromkeys(kinds, 0), "B": dict.fromkeys(kinds, 0)}
        for i, q, rank, kind in qs:
            d = [fn(get(i, g)) if g != q else np.inf for g in range(40)]
            right["A" if rank == 0 else "B"][kind] += int(labels[int(np.argmin(d))] ==
                                                         labels[q])
        return {"loo": k8["loo"]["accuracy"], "split_80_20": k8["split_80_20"]["accuracy"],
                "f1_80_20": k8["split_80_20"]["f1"],
                "split_70_30": k8["split_70_30"]["accuracy"],
                "f1_70_30": k8["split_70_30"]["f1"], "map": r["map"], **right}

    rows = {"shapedna": score(lambda t: t["shapedna"])}
    rows["S (shipped)"] = score(lambda t: sq(t["S"]))
    keys = [k for k in next(iter(T.values())) if k not in ("S", "shapedna")]
    for k in keys:
        rows[f"{k} alone"] = score(lambda t: t[k])
        for w in WEIGHTS:
            rows[f"S + {w:g} {k}"] = score(lambda t: (sq(t["S"]) + w * sq(t[k])) / (1 + w))
    ref, dna = rows["S (shipped)"], rows["shapedna"]
    cols = ("loo", "split_80_20", "f1_80_20", "split_70_30", "f1_70_30")
    for name, r in rows.items():
        r["rule"] = name not in ("shapedna", "S (shipped)") and all(
            r[c] >= ref[c] for c in cols) and all(r["A"][k] >= ref["A"][k] for k in kinds)
        r["B_ok"] = all(r["B"][k] >= max(ref["B"][k], dna["B"][k]) for k in kinds)
    return rows


if __name__ == "__main__":
    sys.exit(main())
