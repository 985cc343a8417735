"""The evaluation suite's regression check for CI (`bench/eval/run.sh ci`).

A reduced run: one pair (CI_PAIR) at two k values with every configuration, and the
distance matrix of a 2-class subset (CI_CLASSES) through the daemon. Its numbers are
checked against bench/eval/ci_bounds.json, which `bench/eval/run.sh bounds` derives from
the full run's JSON (docs/eval/): each mean geodesic error may exceed the full run's by
GEO_REL + GEO_ABS, each subset distance may differ from the full run's by DIST_ABS (the
pipeline is deterministic; the slack covers BLAS builds that round differently), and the
leave-one-out accuracy on the subset may not fall below the full run's. Exit 0 when all
hold, 1 otherwise (each violation printed), 77 without ../shared/data.
"""
import json
import os

import numpy as np

CI_PAIR = "lion"
CI_KS = [30, 50]
CI_CLASSES = ["cat", "dog"]
CI_CONFIGS = ["sinkhorn+lb", "sinkhorn+elastic"]  # the distance's default maps, the match's
GEO_REL, GEO_ABS = 0.10, 0.002
DIST_ABS = 0.01
HERE = os.path.dirname(os.path.abspath(__file__))
BOUNDS = os.path.join(HERE, "ci_bounds.json")


def derive_bounds(full_out):
    """ci_bounds.json from the full run's ablation.json and classify.json."""
    with open(os.path.join(full_out, "ablation.json")) as f:
        ab = json.load(f)
    with open(os.path.join(full_out, "classify.json")) as f:
        cl = json.load(f)
    geo = {f"{r['config']} k={r['k']}": r["geo_mean"]
           for r in ab["pairs"][CI_PAIR]["runs"] if r["k"] in CI_KS and r["ok"]}
    keep = [i for i, l in enumerate(cl["labels"]) if l in CI_CLASSES]
    sub = {"shapes": [cl["shapes"][i] for i in keep], "labels": [cl["labels"][i] for i in keep]}
    for cfg in CI_CONFIGS:
        D = np.array(cl["configs"][cfg]["D"])[np.ix_(keep, keep)]
        sub[cfg] = {"D": D.tolist(), "loo": loo(D, sub["labels"])}
    bounds = {"pair": CI_PAIR, "ks": CI_KS, "geo_mean_full": geo, "classes": CI_CLASSES,
              "k_basis": ab["pairs"][CI_PAIR]["k_basis"],
              "subset": sub, "classify_k": cl["k"], "sinkhorn_steps": cl["sinkhorn_steps"]}
    with open(BOUNDS, "w") as f:
        json.dump(bounds, f, indent=1)
    return bounds


def loo(D, labels):
    n = len(labels)
    ok = 0
    for i in range(n):
        j = min((j for j in range(n) if j != i), key=lambda j: (D[i][j], j))
        ok += labels[j] == labels[i]
    return ok / n


def run(suite, args):
    if not os.path.isdir(os.path.join(HERE, "..", "..", "..", "shared", "data")):
        print("eval ci: skipped (no ../shared/data)")
        return 77
    with open(BOUNDS) as f:
        bounds = json.load(f)
    bad = []
    # The full run's basis size: eigenvectors of close eigenvalues depend on it.
    res, _ = suite.run_pairs("ci", CI_KS, [CI_PAIR], k_basis=bounds["k_basis"])
    for r in res[CI_PAIR]["runs"]:
        key = f"{r['config']} k={r['k']}"
        ref = bounds["geo_mean_full"].get(key)
        if not r["ok"]:
            bad.append(f"{key}: failed: {r.get('error')}")
        elif ref is not None and r["geo_mean"] > ref * (1 + GEO_REL) + GEO_ABS:
            bad.append(f"{key}: mean geodesic error {r['geo_mean']:.4f} > bound "
                       f"{ref * (1 + GEO_REL) + GEO_ABS:.4f} (full run {ref:.4f})")
        else:
            print(f"eval ci: {CI_PAIR} {key}: {r['geo_mean']:.4f} (full run {ref})")
    cl = suite.classify(classes=set(CI_CLASSES), configs=CI_CONFIGS, name="ci_classify")
    sub = bounds["subset"]
    if cl["shapes"] != sub["shapes"]:
        bad.append("classification subset differs from the bounds' shapes")
    else:
        for cfg in CI_CONFIGS:
            D, R = np.array(cl["configs"][cfg]["D"]), np.array(sub[cfg]["D"])
            worst = float(np.nanmax(np.abs(D - R))) if not np.isnan(D).any() else float("inf")
            acc = cl["configs"][cfg]["classes_8"]["loo"]["accuracy"]
            print(f"eval ci: {cfg}: LOO accuracy {acc:.3f} (full run {sub[cfg]['loo']:.3f}), "
                  f"largest distance change {worst:.2e}")
            if worst > DIST_ABS:
                bad.append(f"{cfg}: a subset distance moved by {worst:.3g} (> {DIST_ABS})")
            if acc < sub[cfg]["loo"]:
                bad.append(f"{cfg}: LOO accuracy {acc:.3f} < full run's {sub[cfg]['loo']:.3f}")
    for b in bad:
        print("eval ci: OUT OF BOUNDS: " + b)
    print(f"eval ci: {'FAILED' if bad else 'all numbers within the bounds of the full run'}")
    return 1 if bad else 0
