#!/usr/bin/python3
"""The evaluation suite: the paper's experiments on ../shared/data, one command each.

    bench/eval/run.sh EXPERIMENT      (builds, then runs this script)

    ablation  basis-size sweep x configurations on the four pairs with ground truth
    curves    accuracy curves (fraction under a geodesic-error threshold) at k = 100
    classify  distance matrices of tosca_classification_5k through the daemon (shapematch
              batch), k-NN classification (leave-one-out, 80/20, 70/30), ShapeDNA baseline
    visual    colour transfer through a map, PLY files + a PNG rendering
    robust    classification of deformed queries against the undeformed gallery
    report    docs/RESULTS.md from the JSON files
    all       everything above, then the report
    ci        a reduced run (one pair, two k, a 2-class subset) checked against bounds
              taken from the full run (bench/eval/ci_bounds.json); exit 1 outside them
    bounds    bench/eval/ci_bounds.json from the full run's JSON

Results: docs/eval/*.json and *.png, docs/RESULTS.md. Matching runs in C (eval_pairs,
the daemon); this script only drives the programs, computes the classification scores
from the distances, and plots with matplotlib. Bases are cached (eval_pairs' cache, the
daemon's on-disk store under out/eval/), so a rerun costs only the matching.
"""
import argparse
import json
import math
import os
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import smdaemon  # noqa: E402  (bench/smdaemon.py)

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
DATA = os.path.abspath(os.path.join(ROOT, "..", "shared", "data"))
TOSCA = os.path.join(DATA, "tosca_classification_5k")
PAIRS = ["homer", "head", "lion", "man"]
PAIR_TITLES = {"homer": "homer A -> B", "head": "head A -> B", "lion": "lion -> cat",
               "man": "SMPL man -> permuted woman"}
SWEEP_KS = [30, 50, 70, 90, 110, 130, 150]
CONFIGS = ["nn+lb", "nn+elastic", "sinkhorn+lb", "sinkhorn+elastic", "sinkhorn+hybrid"]
DEFAULT_CONFIG = "sinkhorn+elastic"
# The distance's default (core/sm_distance.h, sm_distance_match_opts): Sinkhorn init, maps
# refined in the LB basis, whose heat signatures the map term compares.
DISTANCE_CONFIG = "sinkhorn+lb"
HUMANS = {"david", "michael", "victoria"}
# The terms of the distance (core/sm_distance.h), kept per pair for analysis.
PARTS = ["point_xy", "point_yx", "spectrum_lb", "spectrum_elastic"]
# The spectral term alone (map weight 0: the definition shipped before the map term study).
SPECTRAL_ROW = "spectral term only (w=0)"

# The shape distance used for retrieval and classification: the product's distance
# (core/sm_distance.h) after a lighter refinement than a full match (k up to CLASSIFY_K,
# no soft Sinkhorn steps): 780 pairs x 5 configurations must fit the suite's time budget
# (0.34 s per distance instead of 1.0-1.3 s with the match defaults, measured warm).
CLASSIFY_K = 50
SINKHORN_STEPS = 0
# Robustness: 8 deformed queries x 39 gallery shapes per deformation, classified with the
# distance's default configuration (--configs runs others), its spectral term alone and
# ShapeDNA; every pair through DISTANCE (BATCH). --deformations runs any other set (e.g.
# stretch:1.1,...,stretch:1.5).
DEFORMATIONS = [("stretch", 1.2), ("stretch", 1.4), ("bulge", 0.3), ("decimate", 0.4),
                ("noise", 0.2)]


def config_args(cfg, k=CLASSIFY_K):
    init, basis = cfg.split("+")
    args = ["--init", init, "--basis", basis, "-k", str(k)]
    args += ["--refine-sinkhorn", str(SINKHORN_STEPS if init == "sinkhorn" else 0)]
    return args


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


class Suite:
    def __init__(self, args):
        self.build = os.path.abspath(args.build)
        self.out = os.path.abspath(args.out)
        self.work = os.path.abspath(args.work)
        self.quick = args.quick
        self.classes = set(args.classes.split(",")) if args.classes else None
        self.deform_arg = args.deformations
        self.configs = args.configs.split(",") if args.configs else CONFIGS
        os.makedirs(self.out, exist_ok=True)
        os.makedirs(self.work, exist_ok=True)
        self.cli = os.path.join(self.build, "clients", "shapematch")
        self.daemon_bin = os.path.join(self.build, "server", "shapematchd")
        self.eval_pairs = os.path.join(self.build, "bench", "eval", "eval_pairs")
        self.eval_tool = os.path.join(self.build, "bench", "eval", "eval_tool")
        self.daemon = None
        self.env = dict(os.environ, OPENBLAS_NUM_THREADS="1")

    # ---- helpers ------------------------------------------------------------------------
    def save(self, name, obj):
        path = os.path.join(self.out, name)
        with open(path + ".tmp", "w") as f:
            json.dump(obj, f, indent=1)
        os.replace(path + ".tmp", path)
        return path

    def load(self, name):
        path = os.path.join(self.out, name)
        if not os.path.exists(path):
            return None
        with open(path) as f:
            return json.load(f)

    def run_parallel(self, cmds, jobs=2):
        """Runs commands, `jobs` at a time; returns their exit codes in order."""
        procs, codes, pending = {}, [None] * len(cmds), list(enumerate(cmds))
        while pending or procs:
            while pending and len(procs) < jobs:
                i, c = pending.pop(0)
                procs[i] = subprocess.Popen(c, env=self.env)
            for i, p in list(procs.items()):
                if p.poll() is not None:
                    codes[i] = p.returncode
                    del procs[i]
            time.sleep(0.05)
        return codes

    # ---- daemon -------------------------------------------------------------------------
    def start_daemon(self):
        store = os.path.join(self.work, "store")
        self.daemon, port = smdaemon.start(self.daemon_bin, store, ["--cache-mb", "4096"],
                                           os.path.join(self.work, "shapematchd.log"),
                                           env=self.env)
        self.env["SHAPEMATCH_SERVER"] = f"127.0.0.1:{port}"
        log(f"shapematchd on {self.env['SHAPEMATCH_SERVER']}, store {store}")

    def stop_daemon(self):
        if self.daemon:
            rc = smdaemon.stop(self.daemon)
            self.daemon = None
            if rc != 0:
                raise RuntimeError(f"shapematchd exited {rc} after SIGTERM")

    def cli_run(self, args):
        r = subprocess.run([self.cli] + args, env=self.env, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"shapematch {' '.join(args[:3])}...: {r.stderr.strip()}")
        return r.stdout

    def put(self, files):
        """Uploads and prepares (bases computed once, then served from the store)."""
        ids = {}
        for line in self.cli_run(["put", "--prepare"] + files).splitlines():
            sid, path = line.split(None, 1)
            ids[path] = sid
        return [ids[f] for f in files]

    def batch(self, pairs, cfg, tag):
        """Distances of (id_a, id_b) pairs through `shapematch batch`; returns the list of
        distances (None for a failed item) and the wall time."""
        listf = os.path.join(self.work, f"batch_{tag}.txt")
        with open(listf, "w") as f:
            for a, b in pairs:
                f.write(f"{a} {b}\n")
        t0 = time.time()
        r = subprocess.run([self.cli, "batch", listf, "--inflight", "4"] + config_args(cfg),
                           env=self.env, capture_output=True, text=True)
        wall = time.time() - t0
        dist = [None] * len(pairs)
        self.last_parts = [None] * len(pairs)
        for line in r.stdout.splitlines():
            rec = json.loads(line)
            if rec.get("ok"):
                dist[rec["index"]] = rec["distance"]
                self.last_parts[rec["index"]] = [rec[k] for k in PARTS]
        failed = sum(d is None for d in dist)
        if failed:
            log(f"  {tag}: {failed} of {len(pairs)} items failed: {r.stderr.strip()[:500]}")
        return dist, wall

    # ---- 1 + 2 + 4: pairs ---------------------------------------------------------------
    def eval_pairs_cmd(self, pair, ks, out, configs=None, visual=None, k_basis=None):
        cmd = [self.eval_pairs, "--pair", pair, "--ks", ",".join(map(str, ks)),
               "--cache", os.path.join(self.work, "basis-cache"), "--json", out]
        if configs:
            cmd += ["--configs", ",".join(configs)]
        if visual:
            cmd += ["--visual", visual]
        if k_basis:
            cmd += ["--k-basis", str(k_basis)]
        return cmd

    def run_pairs(self, name, ks, pairs, configs=None, k_basis=None):
        t0 = time.time()
        outs = {p: os.path.join(self.out, f"{name}_{p}.json") for p in pairs}
        # head (15k vertices) is the longest: start it first so the two slots stay busy.
        order = sorted(pairs, key=lambda p: p != "head")
        codes = self.run_parallel([self.eval_pairs_cmd(p, ks, outs[p], configs, k_basis=k_basis)
                                   for p in order])
        res = {}
        for p, c in zip(order, codes):
            if c == 77:
                log(f"  {p}: skipped (no data)")
            elif c != 0:
                raise RuntimeError(f"eval_pairs {p} failed ({c})")
            else:
                with open(outs[p]) as f:
                    res[p] = json.load(f)
        return res, time.time() - t0

    def ablation(self):
        ks = [30, 50] if self.quick else SWEEP_KS
        res, wall = self.run_pairs("ablation", ks, PAIRS)
        self.save("ablation.json", {"ks": ks, "configs": CONFIGS, "pairs": res,
                                    "wall_s": wall})
        plot_ablation(self.out, res, ks)
        log(f"ablation: {wall:.0f} s")

    def curves(self):
        res, wall = self.run_pairs("curves", [100], PAIRS)
        self.save("curves.json", {"k": 100, "pairs": res, "wall_s": wall})
        plot_curves(self.out, res)
        log(f"curves: {wall:.0f} s")

    def visual(self):
        t0 = time.time()
        vis = os.path.join(self.out, "visual")
        os.makedirs(vis, exist_ok=True)
        done = []
        for p in ["lion", "homer"]:
            out = os.path.join(self.work, f"visual_{p}.json")
            c = subprocess.run(self.eval_pairs_cmd(p, [100], out, ["none"], vis),
                               env=self.env).returncode
            if c == 77:
                continue
            if c != 0:
                raise RuntimeError(f"eval_pairs --visual {p} failed")
            with open(out) as f:
                info = json.load(f)["visual"]
            png = os.path.join(self.out, f"visual_{p}.png")
            render_pair(os.path.join(vis, f"{p}_source.ply"), os.path.join(vis, f"{p}_target.ply"),
                        os.path.join(vis, f"{p}_target_to_source.txt"), png, f"{PAIR_TITLES[p]}: colour transfer ({info['config']}, k={info['k']}, "
                        f"mean geodesic error {info['geo_mean']:.4f})")
            done.append({"pair": p, "png": os.path.basename(png), **info})
        self.save("visual.json", {"pairs": done, "wall_s": time.time() - t0})
        log(f"visual: {time.time() - t0:.0f} s")

    # ---- 3: classification --------------------------------------------------------------
    def tosca_labels(self, classes=None):
        rows = []
        with open(os.path.join(TOSCA, "labels.csv")) as f:
            next(f)
            for line in f:
                file, cls, _ = line.strip().split(",")
                name = os.path.basename(file).split(".")[0]
                if classes is None or cls in classes:
                    rows.append((name, cls, os.path.join(TOSCA, "drc", name + ".drc")))
        return rows

    def shapedna(self, files):
        """ShapeDNA signatures of files, in order."""
        recs = shapedna_records(self.eval_tool, [], files, self.env)
        return [np.array(recs[f]["eig"]) for f in files]

    def classify(self, classes=None, configs=None, name="classify"):
        classes = classes or self.classes
        configs = configs or self.configs
        if not os.path.isdir(TOSCA):
            log("classify: skipped (no ../shared/data)")
            return None
        rows = self.tosca_labels(classes)
        names, labels, files = zip(*rows)
        n = len(rows)
        result = {"shapes": list(names), "labels": list(labels), "k": CLASSIFY_K,
                  "sinkhorn_steps": SINKHORN_STEPS, "configs": {}, "timing": {}}
        t0 = time.time()
        self.start_daemon()
        try:
            ids = self.put(list(files))
            result["timing"]["put_prepare_s"] = time.time() - t0
            log(f"  {n} shapes stored and prepared in {time.time() - t0:.0f} s")
            pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
            for cfg in configs:
                dist, wall = self.batch([(ids[i], ids[j]) for i, j in pairs], cfg, f"{name}_{cfg}")
                D = np.zeros((n, n))
                P = np.zeros((len(PARTS), n, n))
                for (i, j), d, parts in zip(pairs, dist, self.last_parts):
                    D[i, j] = D[j, i] = np.nan if d is None else d
                    P[:, i, j] = P[:, j, i] = np.nan if parts is None else parts
                result["configs"][cfg] = {"D": D.tolist(), "wall_s": wall,
                                          "per_distance_s": wall / len(pairs),
                                          "parts": {k: P[m].tolist() for m, k in enumerate(PARTS)}}
                log(f"  {cfg}: {len(pairs)} distances in {wall:.0f} s")
            # The spectral term alone (the same for every configuration: no map in it).
            ref = DISTANCE_CONFIG if DISTANCE_CONFIG in configs else configs[0]
            result["configs"][SPECTRAL_ROW] = {
                "D": result["configs"][ref]["parts"]["spectrum_lb"]}
        finally:
            self.stop_daemon()
        t1 = time.time()
        sig = self.shapedna(list(files))
        D = np.array([[cosine_distance(a, b) for b in sig] for a in sig])
        result["configs"]["shapedna"] = {"D": D.tolist(), "wall_s": time.time() - t1}
        result["timing"]["total_s"] = time.time() - t0
        score_classification(result)
        self.save(f"{name}.json", result)
        plot_classification(self.out, result, name)
        log(f"{name}: {result['timing']['total_s']:.0f} s")
        return result

    # ---- 5: robustness ------------------------------------------------------------------
    def deformations(self):
        if self.deform_arg:
            return [(k, float(v)) for k, v in (d.split(":") for d in self.deform_arg.split(","))]
        return [("stretch", 1.4)] if self.quick else DEFORMATIONS

    def robust(self, configs=None):
        configs = configs or (self.configs if self.configs != CONFIGS else [DISTANCE_CONFIG])
        if not os.path.isdir(TOSCA):
            log("robust: skipped (no ../shared/data)")
            return None
        rows = self.tosca_labels(self.classes)
        names, labels, files = zip(*rows)
        queries = []
        for cls in dict.fromkeys(labels):  # first shape of each class, in file order
            queries.append(labels.index(cls))
        t0 = time.time()
        ddir = os.path.join(self.work, "deformed")
        os.makedirs(ddir, exist_ok=True)
        variants = []  # (kind, strength, query index, file)
        cmds = []
        for kind, s in self.deformations():
            for q in queries:
                out = os.path.join(ddir, f"{names[q]}_{kind}_{s}.drc")
                variants.append((kind, s, q, out))
                if not os.path.exists(out):
                    cmds.append([self.eval_tool, "deform", files[q], "-o", out, f"--{kind}",
                                 str(s), "--seed", str(q + 1)])
        if any(c != 0 for c in self.run_parallel(cmds)):
            raise RuntimeError("deformation failed")
        result = {"queries": [names[q] for q in queries], "deformations": self.deformations(),
                  "k": CLASSIFY_K, "configs": {}, "timing": {"deform_s": time.time() - t0}}
        self.start_daemon()
        try:
            t1 = time.time()
            gid = self.put(list(files))
            vid = self.put([v[3] for v in variants])
            result["timing"]["put_prepare_s"] = time.time() - t1
            pairs, owners = [], []
            for vi, (kind, s, q, _) in enumerate(variants):
                for g in range(len(files)):
                    if g != q:  # the query's own undeformed original is not in its gallery
                        pairs.append((vid[vi], gid[g]))
                        owners.append((vi, g))
            for cfg in configs:
                dist, wall = self.batch(pairs, cfg, f"robust_{cfg}")
                result["configs"][cfg] = robust_scores(variants, owners, dist, labels, wall)
                log(f"  {cfg}: {len(pairs)} distances in {wall:.0f} s")
                if cfg == configs[0]:
                    spec = [None if p is None else p[PARTS.index("spectrum_lb")]
                            for p in self.last_parts]
                    result["configs"][SPECTRAL_ROW] = robust_scores(variants, owners, spec,
                                                                    labels, 0)
        finally:
            self.stop_daemon()
        sig_g = self.shapedna(list(files))
        sig_v = self.shapedna([v[3] for v in variants])
        dist = [cosine_distance(sig_v[vi], sig_g[g]) for vi, g in owners]
        result["configs"]["shapedna"] = robust_scores(variants, owners, dist, labels, 0)
        result["timing"]["total_s"] = time.time() - t0
        self.save("robust.json", result)
        plot_robust(self.out, result)
        log(f"robust: {result['timing']['total_s']:.0f} s")
        return result


# ---- scores ---------------------------------------------------------------------------------
def shapedna_records(tool, args, files, env):
    """`eval_tool shapedna ARGS FILE...` with the list split over two processes (one per
    core): its JSON record per file, keyed by file."""
    half = (len(files) + 1) // 2
    procs = [subprocess.Popen([tool, "shapedna"] + args + part, env=env,
                              stdout=subprocess.PIPE, text=True)
             for part in (files[:half], files[half:]) if part]
    recs = {}
    for p in procs:
        out, _ = p.communicate()
        if p.returncode:
            raise RuntimeError("eval_tool shapedna failed")
        for line in out.splitlines():
            rec = json.loads(line)
            recs[rec["file"]] = rec
    return recs


def cosine_distance(a, b):
    return float(1 - a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def class_metrics(true, pred, classes):
    """Accuracy and macro precision / recall / F1 / specificity, confusion matrix."""
    idx = {c: i for i, c in enumerate(classes)}
    C = np.zeros((len(classes), len(classes)), dtype=int)
    for t, p in zip(true, pred):
        C[idx[t], idx[p]] += 1
    tp = np.diag(C).astype(float)
    fp = C.sum(0) - tp
    fn = C.sum(1) - tp
    tn = C.sum() - tp - fp - fn
    with np.errstate(invalid="ignore", divide="ignore"):
        prec = np.where(tp + fp > 0, tp / (tp + fp), 0.0)
        rec = np.where(tp + fn > 0, tp / (tp + fn), 0.0)
        f1 = np.where(prec + rec > 0, 2 * prec * rec / (prec + rec), 0.0)
        spec = np.where(tn + fp > 0, tn / (tn + fp), 0.0)
    return {"accuracy": float(tp.sum() / C.sum()), "precision": float(prec.mean()),
            "recall": float(rec.mean()), "f1": float(f1.mean()),
            "specificity": float(spec.mean()), "confusion": C.tolist(), "classes": classes}


def nn_predict(D, labels, queries, gallery):
    pred = []
    for q in queries:
        g = min(gallery, key=lambda j: (D[q][j], j) if j != q else (math.inf, j))
        pred.append(labels[g])
    return pred


def stratified_split(labels, test_frac, seed):
    rng = np.random.default_rng(seed)
    train, test = [], []
    for c in dict.fromkeys(labels):
        members = [i for i, l in enumerate(labels) if l == c]
        rng.shuffle(members)
        nt = max(1, int(round(test_frac * len(members))))
        test += members[:nt]
        train += members[nt:]
    return sorted(train), sorted(test)


SPLIT_SEEDS = list(range(20))


def knn_scores(D, labels):
    classes = sorted(set(labels))
    n = len(labels)
    out = {"loo": class_metrics(labels, nn_predict(D, labels, range(n), range(n)), classes)}
    for frac, key in ((0.2, "split_80_20"), (0.3, "split_70_30")):
        runs = []
        for seed in SPLIT_SEEDS:
            train, test = stratified_split(labels, frac, seed)
            runs.append(class_metrics([labels[i] for i in test],
                                      nn_predict(D, labels, test, train), classes))
        agg = {m: float(np.mean([r[m] for r in runs])) for m in
               ("accuracy", "precision", "recall", "f1", "specificity")}
        agg["accuracy_std"] = float(np.std([r["accuracy"] for r in runs]))
        agg["confusion"] = np.sum([r["confusion"] for r in runs], axis=0).tolist()
        agg["classes"] = classes
        agg["seeds"] = SPLIT_SEEDS
        out[key] = agg
    return out


def retrieval_scores(D, labels):
    """Retrieval figures with the conventions of the SHREC tracks and the Princeton Shape
    Benchmark (Shilane et al. 2004): every shape queries the others (itself excluded),
    ranked by distance (ties by index, as nn_predict); with C the query's class size,
    nearest neighbour = share of queries whose first answer is of their class, first tier =
    recall in the first C - 1 answers, second tier = recall in the first 2 (C - 1), DCG =
    sum of G_i / log2(i) (G_1 undivided; G_i = 1 for a relevant answer) over the ideal
    DCG, mAP = mean over queries of the precision at each relevant answer's rank, averaged.
    Means over all queries; classes of one shape (nothing to retrieve) are left out."""
    D = np.asarray(D, dtype=float)
    n = len(labels)
    nn = ft = st = dcg = ap = 0.0
    nq = 0
    for q in range(n):
        order = sorted((j for j in range(n) if j != q), key=lambda j: (D[q][j], j))
        rel = np.array([labels[j] == labels[q] for j in order], dtype=float)
        R = int(rel.sum())
        if R == 0:
            continue
        nq += 1
        nn += rel[0]
        ft += rel[:R].sum() / R
        st += rel[:2 * R].sum() / R
        disc = np.ones(len(rel))
        disc[1:] = 1 / np.log2(np.arange(2, len(rel) + 1))
        dcg += (rel * disc).sum() / disc[:R].sum()
        hits = np.flatnonzero(rel)
        ap += np.mean((np.arange(len(hits)) + 1) / (hits + 1))
    return {"nn": nn / nq, "ft": ft / nq, "st": st / nq, "dcg": dcg / nq, "map": ap / nq,
            "queries": nq}


def intra_inter(D, labels):
    n = len(labels)
    intra = [D[i][j] for i in range(n) for j in range(i + 1, n) if labels[i] == labels[j]]
    inter = [D[i][j] for i in range(n) for j in range(i + 1, n) if labels[i] != labels[j]]
    return {"intra_mean": float(np.mean(intra)), "intra_max": float(np.max(intra)),
            "inter_mean": float(np.mean(inter)), "inter_min": float(np.min(inter)),
            "ratio_inter_over_intra": float(np.mean(inter) / np.mean(intra))}


def score_classification(result):
    labels = result["labels"]
    merged = ["human" if l in HUMANS else l for l in labels]
    for cfg, r in result["configs"].items():
        D = np.array(r["D"])
        if np.isnan(D).any():
            r["error"] = f"{int(np.isnan(D).sum() // 2)} distances failed"
            D = np.nan_to_num(D, nan=2.0)
        r["classes_8"] = knn_scores(D, labels)
        r["classes_6"] = knn_scores(D, merged)
        r["retrieval_8"] = retrieval_scores(D, labels)
        r["retrieval_6"] = retrieval_scores(D, merged)
        r["distances_8"] = intra_inter(D, labels)


def robust_scores(variants, owners, dist, labels, wall):
    best = {}
    for (vi, g), d in zip(owners, dist):
        d = 2.0 if d is None else d
        if vi not in best or d < best[vi][0]:
            best[vi] = (d, g)
    acc = {}
    for vi, (kind, s, q, _) in enumerate(variants):
        key = f"{kind} {s}"
        ok = labels[best[vi][1]] == labels[q]
        acc.setdefault(key, []).append(ok)
    return {"accuracy": {k: float(np.mean(v)) for k, v in acc.items()},
            "correct": {k: int(np.sum(v)) for k, v in acc.items()},
            "n_queries": {k: len(v) for k, v in acc.items()},
            "failed_items": int(sum(d is None for d in dist)), "wall_s": wall}


# ---- plots ----------------------------------------------------------------------------------
def plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as p
    return p


METRICS = [("geo_mean", "mean geodesic error"), ("bijectivity_error", "bijectivity error"),
           ("coverage", "coverage"), ("chamfer", "Chamfer distance"),
           ("dirichlet", "Dirichlet energy"), ("t_total", "runtime (s)"), ("auc", "AUC")]


def plot_ablation(out, res, ks):
    p = plt()
    for key, title in METRICS:
        pairs = [q for q in PAIRS if q in res]
        fig, axes = p.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 3.6), squeeze=False)
        for ax, pair in zip(axes[0], pairs):
            for cfg in CONFIGS:
                pts = [(r["k"], r.get(key)) for r in res[pair]["runs"]
                       if r["config"] == cfg and r["ok"] and r.get(key) is not None]
                if pts:
                    ax.plot(*zip(*pts), marker="o", ms=3, label=cfg,
                            lw=2.2 if cfg == DEFAULT_CONFIG else 1.2)
            ax.set_title(PAIR_TITLES[pair], fontsize=10)
            ax.set_xlabel("k")
            if key == "dirichlet":
                ax.set_yscale("log")
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel(title)
        axes[0][-1].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(os.path.join(out, f"ablation_{key}.png"), dpi=90)
        p.close(fig)


def plot_curves(out, res):
    p = plt()
    pairs = [q for q in PAIRS if q in res]
    fig, axes = p.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 3.6), squeeze=False)
    t = np.linspace(0, 0.1, 41)
    for ax, pair in zip(axes[0], pairs):
        for r in res[pair]["runs"]:
            if r["ok"]:
                ax.plot(t, r["curve"], label=f"{r['config']} (AUC {r['auc']:.3f})",
                        lw=2.2 if r["config"] == DEFAULT_CONFIG else 1.2)
        ax.set_title(PAIR_TITLES[pair], fontsize=10)
        ax.set_xlabel("geodesic error / sqrt(area)")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    axes[0][0].set_ylabel("fraction of correspondences")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "curves.png"), dpi=90)
    p.close(fig)


def plot_classification(out, result, name):
    p = plt()
    cfgs = list(result["configs"])
    labels = result["labels"]
    fig, axes = p.subplots(2, (len(cfgs) + 1) // 2, figsize=(4.3 * ((len(cfgs) + 1) // 2), 8.4),
                           squeeze=False)
    ticks = [i for i in range(len(labels)) if i == 0 or labels[i] != labels[i - 1]]
    for ax, cfg in zip(axes.flat, cfgs):
        D = np.array(result["configs"][cfg]["D"])
        im = ax.imshow(D, cmap="viridis")
        loo = result["configs"][cfg]["classes_8"]["loo"]["accuracy"]
        ax.set_title(f"{cfg}\nLOO 1-NN accuracy {loo:.3f}", fontsize=9)
        ax.set_xticks(ticks)
        ax.set_xticklabels([labels[i] for i in ticks], rotation=90, fontsize=7)
        ax.set_yticks(ticks)
        ax.set_yticklabels([labels[i] for i in ticks], fontsize=7)
        fig.colorbar(im, ax=ax, fraction=0.046)
    for ax in list(axes.flat)[len(cfgs):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(os.path.join(out, f"{name}_heatmaps.png"), dpi=90)
    p.close(fig)


def plot_robust(out, result):
    p = plt()
    kinds = list(dict.fromkeys(k for k, _ in result["deformations"]))
    fig, axes = p.subplots(1, len(kinds), figsize=(3.8 * len(kinds), 3.6), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        xs = [s for k, s in result["deformations"] if k == kind]
        for cfg, r in result["configs"].items():
            ys = [r["accuracy"][f"{kind} {s}"] for s in xs]
            style = dict(marker="o", ms=4, lw=2.2 if cfg == DISTANCE_CONFIG else 1.2)
            if cfg == "shapedna":
                style.update(color="black", ls="--")
            if len(xs) > 1:
                ax.plot(xs, ys, label=cfg, **style)
            else:
                ax.bar(cfg, ys[0], color="black" if cfg == "shapedna" else None)
                ax.tick_params(axis="x", rotation=90, labelsize=7)
        ax.set_title(f"{kind}", fontsize=10)
        ax.set_ylim(0, 1.05)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("1-NN accuracy of deformed queries")
    handles, names = axes[0][0].get_legend_handles_labels()
    if handles:
        axes[0][0].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "robust.png"), dpi=90)
    p.close(fig)


def read_ply(path):
    with open(path) as f:
        nv = nf = 0
        while True:
            line = f.readline().split()
            if line[:2] == ["element", "vertex"]:
                nv = int(line[2])
            elif line[:2] == ["element", "face"]:
                nf = int(line[2])
            elif line == ["end_header"]:
                break
        V = np.loadtxt(f, max_rows=nv)
        F = np.loadtxt(f, max_rows=nf, dtype=int)[:, 1:4]
    return V[:, :3], V[:, 3:6] / 255.0, F


def kabsch(P, Q):
    """Similarity transform (s, R, t) minimizing |s R P + t - Q|."""
    mp, mq = P.mean(0), Q.mean(0)
    U, S, Wt = np.linalg.svd((Q - mq).T @ (P - mp))
    d = np.sign(np.linalg.det(U @ Wt))
    R = U @ np.diag([1, 1, d]) @ Wt
    s = (S * [1, 1, d]).sum() / ((P - mp) ** 2).sum()
    return s, R, mq - s * R @ mp


def render_pair(src, tgt, t2s, png, title):
    """Headless rendering with matplotlib's 3D polygons: the source in its principal frame,
    seen along its smallest extent; the target aligned to the source through the map
    (similarity fit of each target vertex to its image) so both show the same side."""
    p = plt()
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    Vs, Cs, Fs = read_ply(src)
    Vt, Ct, Ft = read_ply(tgt)
    m = np.loadtxt(t2s, dtype=int)
    s, R, t = kabsch(Vt, Vs[m])
    Vt = (s * (R @ Vt.T)).T + t
    c = Vs.mean(0)
    _, _, W = np.linalg.svd(Vs - c, full_matrices=False)
    fig = p.figure(figsize=(11, 5.2))
    for i, (V, C, F) in enumerate(((Vs, Cs, Fs), (Vt, Ct, Ft))):
        V = (V - c) @ W.T  # x largest extent, z smallest: look along z
        tri = V[F]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-30
        shade = 0.35 + 0.65 * np.abs(n @ np.array([0.3, 0.4, 0.866]))
        col = np.clip(C[F].mean(1) * shade[:, None], 0, 1)
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(tri, facecolors=col, edgecolors="none"))
        lo, hi = V.min(0), V.max(0)
        ax.set_xlim(lo[0], hi[0]), ax.set_ylim(lo[1], hi[1]), ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(hi - lo, zoom=1.0)
        ax.view_init(elev=90, azim=-90)
        ax.set_axis_off()
        ax.set_title("source" if i == 0 else "target (colours pulled through the map)",
                     fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.9, wspace=0)
    fig.savefig(png, dpi=90)
    p.close(fig)


# ---- main -----------------------------------------------------------------------------------
def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiment", choices=["ablation", "curves", "classify", "visual", "robust",
                                           "report", "all", "ci", "bounds"])
    ap.add_argument("--build", default=os.path.join(ROOT, "build"))
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "eval"))
    ap.add_argument("--work", default=os.path.join(ROOT, "out", "eval"))
    ap.add_argument("--quick", action="store_true", help="fewer k values and deformations")
    ap.add_argument("--classes", help="classify/robust: only these classes (comma list)")
    ap.add_argument("--configs", help="only these configurations (comma list)")
    ap.add_argument("--deformations", help="robust: KIND:STRENGTH list (stretch, bulge, dent, "
                    "decimate, noise), e.g. stretch:1.2,noise:0.1")
    args = ap.parse_args()
    if args.experiment in ("ci", "bounds"):
        import ci_check
        if args.experiment == "bounds":
            ci_check.derive_bounds(os.path.abspath(args.out))
            sys.exit(0)
        sys.exit(ci_check.run(Suite(args), args))
    s = Suite(args)
    import report
    t0 = time.time()
    steps = {"ablation": s.ablation, "curves": s.curves, "classify": s.classify,
             "visual": s.visual, "robust": s.robust, "report": lambda: None}
    todo = list(steps) if args.experiment == "all" else [args.experiment]
    timing = s.load("timing.json") or {}
    for step in todo:
        log(f"== {step}")
        t1 = time.time()
        steps[step]()
        if step != "report":
            timing[step] = {"wall_s": round(time.time() - t1, 1), "quick": s.quick,
                            "finished": time.strftime("%Y-%m-%d %H:%M:%S")}
            s.save("timing.json", timing)
    report.write(s.out, os.path.join(os.path.dirname(s.out), "RESULTS.md"))
    log(f"done in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
