#!/usr/bin/python3
"""dist_study: scores candidate shape distances offline from dist_dump's output (issue 11).

    bench/eval/dist_study.py DIR [--labels LABELS] [--configs a,b] [--only NAME,...]

DIR holds shape_*.bin and CONFIG.part*.bin (bench/eval/dist_dump.c); LABELS has lines
"name class" in the order of dist_dump's shape list. For every configuration present and
every candidate definition below, prints the leave-one-out 1-NN accuracy (8 classes and
humans merged), the 80/20 and 70/30 split accuracies and F1, and the retrieval figures
(NN, FT, ST, DCG, mAP) with suite.py's own scoring functions, so the figures here are the
ones the suite would report for the same distance matrix.
"""
import argparse
import glob
import os
import sys

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import suite  # noqa: E402


def load_shape(path):
    with open(path, "rb") as f:
        n, nf, klb, kel = np.fromfile(f, np.int32, 4)
        V = np.fromfile(f, np.float64, 3 * n).reshape(n, 3)
        F = np.fromfile(f, np.int32, 3 * nf).reshape(nf, 3)
        mass = np.fromfile(f, np.float64, n)
        lev = np.fromfile(f, np.float64, klb)
        lphi = np.fromfile(f, np.float32, n * klb).reshape(klb, n).T.astype(np.float64)
        eev = np.fromfile(f, np.float64, kel)
        ephi = np.fromfile(f, np.float32, n * kel).reshape(kel, n).T.astype(np.float64)
    return {"n": n, "V": V, "F": F, "mass": mass, "lev": lev, "lphi": lphi, "eev": eev,
            "ephi": ephi}


def load_pairs(d, cfg):
    recs = {}
    for path in sorted(glob.glob(os.path.join(d, f"{cfg}.part*.bin"))):
        with open(path, "rb") as f:
            while True:
                h = np.fromfile(f, np.int32, 5)
                if len(h) < 5:
                    break
                i, j, nx, ny, kc = (int(v) for v in h)
                Txy = np.fromfile(f, np.int32, nx)
                Tyx = np.fromfile(f, np.int32, ny)
                C = np.fromfile(f, np.float64, kc * kc)
                tail = np.fromfile(f, np.float64, 3)
                if len(tail) < 3:  # a file still being written
                    break
                C = C.reshape(kc, kc)
                recs[(i, j)] = (Txy, Tyx, C, tail)
    return recs


def cotan_stiffness(V, F):
    n = len(V)
    W = sp.csr_matrix((n, n))
    rows, cols, vals = [], [], []
    for a in range(3):
        i, j, k = F[:, a], F[:, (a + 1) % 3], F[:, (a + 2) % 3]
        u, v = V[i] - V[k], V[j] - V[k]
        cot = (u * v).sum(1) / np.maximum(np.linalg.norm(np.cross(u, v), axis=1), 1e-30)
        rows += [i, j]
        cols += [j, i]
        vals += [-0.5 * cot, -0.5 * cot]
    W = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n, n))
    W = W - sp.diags(np.asarray(W.sum(1)).ravel())
    return W


# ---- per-shape features ---------------------------------------------------------------------
def hks(s, times, k=None, basis="l"):
    ev, phi = (s["lev"], s["lphi"]) if basis == "l" else (s["eev"], s["ephi"])
    k = k or len(ev)
    w = np.exp(-np.outer(np.maximum(ev[:k], 0), times))  # k x T
    return (phi[:, :k] ** 2) @ w


def centered_log(F, mass):
    F = np.log(np.maximum(F, 1e-300))
    return F - (mass @ F) / mass.sum()


def cos_dist_w(A, B, m):
    ab = (m[:, None] * A * B).sum()
    aa = (m[:, None] * A * A).sum()
    bb = (m[:, None] * B * B).sum()
    return 1 - ab / np.sqrt(aa * bb)


def spectrum_logcos(ea, eb, K=50):
    def pos(e):
        return e[e > 1e-9 * abs(e[-1])]
    a, b = pos(ea), pos(eb)
    K = min(K, len(a), len(b))
    u, v = np.log(a[:K]), np.log(b[:K])
    u, v = u - u.mean(), v - v.mean()
    return 1 - u @ v / np.sqrt(u @ u * v @ v)


def raw_cos(a, b):
    return 1 - a @ b / np.sqrt(a @ a * b @ b)


# ---- the study ------------------------------------------------------------------------------
HKS_T = 10.0 ** (-3 + 2 * np.arange(8) / 7)


def shape_feats(s):
    f = {}
    f["hks_cur"] = centered_log(hks(s, HKS_T), s["mass"])
    f["hks_log"] = np.log(np.maximum(hks(s, HKS_T), 1e-300))
    f["hks_log50"] = np.log(np.maximum(hks(s, HKS_T, k=50), 1e-300))
    return f


def pulled_C(sx, sy, T, k):
    """C (k x k): Y's first k LB functions pulled back to X through T, in X's LB basis."""
    return sx["lphi"][:, :k].T @ (sx["mass"][:, None] * sy["lphi"][T, :k])


def area_diff(sx, sy, T, k):
    C = pulled_C(sx, sy, T, k)
    return np.linalg.norm(C.T @ C - np.eye(k)) / np.sqrt(k)


def conf_diff(sx, sy, T, k, Wx):
    """Conformal shape difference: Dirichlet energies of the pulled-back functions against
    the target's eigenvalues, relative: |Lambda^-1/2 G Lambda^-1/2 - I| over j >= 1."""
    P = sy["lphi"][T, 1:k]
    G = P.T @ (Wx @ P)
    lam = np.maximum(sy["lev"][1:k], 1e-12)
    R = G / np.sqrt(np.outer(lam, lam))
    return np.linalg.norm(R - np.eye(k - 1)) / np.sqrt(k - 1)


def pair_terms(sx, sy, fx, fy, Txy, Tyx, Wx, Wy):
    t = {}
    t["point_cur"] = 0.5 * (cos_dist_w(fx["hks_cur"], fy["hks_cur"][Txy], sx["mass"]) +
                            cos_dist_w(fy["hks_cur"], fx["hks_cur"][Tyx], sy["mass"]))
    for key in ("hks_log", "hks_log50"):
        a = [np.sqrt(sx["mass"] @ ((fx[key] - fy[key][Txy]) ** 2).mean(1)),
             np.sqrt(sy["mass"] @ ((fy[key] - fx[key][Tyx]) ** 2).mean(1))]
        t[key] = 0.5 * (a[0] + a[1])
        # robust: the area-weighted median of the per-vertex RMS difference
        def wmed(s, r):
            o = np.argsort(r)
            c = np.cumsum(s["mass"][o])
            return r[o][np.searchsorted(c, 0.5 * c[-1])]
        t[key + "_med"] = 0.5 * (wmed(sx, np.sqrt(((fx[key] - fy[key][Txy]) ** 2).mean(1))) +
                                 wmed(sy, np.sqrt(((fy[key] - fx[key][Tyx]) ** 2).mean(1))))
    for K in (20, 50):
        t[f"rms{K}"] = np.sqrt(np.mean(np.log(sx["lev"][1:K + 1] / sy["lev"][1:K + 1]) ** 2))
    t["spec_lb"] = spectrum_logcos(sx["lev"], sy["lev"])
    t["spec_el"] = spectrum_logcos(sx["eev"], sy["eev"])
    for k in (10, 20, 30):
        t[f"area{k}"] = 0.5 * (area_diff(sx, sy, Txy, k) + area_diff(sy, sx, Tyx, k))
    for k in (10, 20, 30):
        t[f"conf{k}"] = 0.5 * (conf_diff(sx, sy, Txy, k, Wx) + conf_diff(sy, sx, Tyx, k, Wy))
    ea, eb = sx["lev"][1:31], sy["lev"][1:31]
    t["shapedna"] = raw_cos(ea, eb)
    return t


def retrieval(D, labels):
    return suite.retrieval_scores(np.asarray(D), labels)


def scores(D, labels):
    merged = ["human" if l in suite.HUMANS else l for l in labels]
    k8, k6 = suite.knn_scores(D, labels), suite.knn_scores(D, merged)
    out = {"loo": k8["loo"]["accuracy"], "loo_merged": k6["loo"]["accuracy"]}
    for key in ("split_80_20", "split_70_30"):
        out[key] = {"accuracy": k8[key]["accuracy"], "f1": k8[key]["f1"]}
    out["retrieval"] = retrieval(D, labels)
    return out


def summarize(name, D, labels):
    merged = ["human" if l in suite.HUMANS else l for l in labels]
    k8 = suite.knn_scores(D, labels)
    k6 = suite.knn_scores(D, merged)
    r = retrieval(D, labels)
    return (f"{name:34s} LOO {k8['loo']['accuracy']:.3f} merged {k6['loo']['accuracy']:.3f} "
            f"80/20 {k8['split_80_20']['accuracy']:.3f}/{k8['split_80_20']['f1']:.3f} "
            f"70/30 {k8['split_70_30']['accuracy']:.3f}/{k8['split_70_30']['f1']:.3f} "
            f"NN {r['nn']:.3f} FT {r['ft']:.3f} ST {r['st']:.3f} DCG {r['dcg']:.3f} "
            f"mAP {r['map']:.3f}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("--labels")
    ap.add_argument("--configs", default="sinkhorn+elastic,nn+lb,sinkhorn+lb,sinkhorn+hybrid,"
                    "nn+elastic")
    ap.add_argument("--save", help="write the term matrices to this .npz")
    ap.add_argument("--json", help="write every row's scores to this JSON file")
    a = ap.parse_args()
    rows = [l.split() for l in open(a.labels or os.path.join(a.dir, "..", "labels.txt"))]
    names, labels = [r[0] for r in rows], [r[1] for r in rows]
    n = len(names)
    shapes = [load_shape(os.path.join(a.dir, f"shape_{nm}.bin")) for nm in names]
    feats = [shape_feats(s) for s in shapes]
    Ws = [cotan_stiffness(s["V"], s["F"]) for s in shapes]
    saved, rows_out = {}, {}
    for cfg in a.configs.split(","):
        recs = load_pairs(a.dir, cfg)
        if len(recs) < n * (n - 1) // 2:
            print(f"{cfg}: {len(recs)} pairs only, skipped")
            continue
        M = {}
        for (i, j), (Txy, Tyx, C, tail) in recs.items():
            t = pair_terms(shapes[i], shapes[j], feats[i], feats[j], Txy, Tyx, Ws[i], Ws[j])
            t["dirichlet"] = tail[0]
            for key, v in t.items():
                M.setdefault(key, np.zeros((n, n)))
                M[key][i, j] = M[key][j, i] = v
        for key, D in M.items():
            saved[f"{cfg}|{key}"] = D
            print(summarize(f"{cfg} {key}", D, labels))
            rows_out[f"{cfg} {key}"] = scores(D, labels)
    if a.json:
        import json
        with open(a.json, "w") as f:
            json.dump(rows_out, f, indent=1)
    if a.save:
        np.savez(a.save, names=names, labels=labels, **saved)


if __name__ == "__main__":
    main()
