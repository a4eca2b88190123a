"""DPGMMClusterer against BayesianGaussianMixture on Gaussian blobs, same data, same run.

Run standalone: ``python benchmarks/bench_cluster.py [--sizes 10000 100000] [--quick]``.
Prints a markdown table and writes ``benchmarks/results/bench_cluster.json``.
BayesianGaussianMixture gets the matched prior (alpha = 1, the same NIW hyper-parameters),
``n_components=20`` and ``max_iter=1000``; it is skipped at sizes above ``--bgm-max``.
"""

import argparse
import json
import os
import time
import warnings
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
from sklearn.exceptions import ConvergenceWarning  # noqa: E402
from sklearn.metrics import adjusted_rand_score  # noqa: E402
from sklearn.mixture import BayesianGaussianMixture  # noqa: E402

from skoccmap.cluster import DPGMMClusterer  # noqa: E402


def blobs(n, D, K, seed, separation=7.0):
    """Anisotropic Gaussian blobs with centres at least ``separation`` apart."""
    rng = np.random.default_rng(seed)
    centres = [rng.uniform(-15, 15, D)]
    while len(centres) < K:
        c = rng.uniform(-15, 15, D)
        if min(np.linalg.norm(c - k) for k in centres) > separation:
            centres.append(c)
    centres = np.array(centres)
    y = rng.integers(K, size=n)
    A = rng.normal(size=(K, D, D)) * 0.3 + np.eye(D)
    return centres[y] + np.einsum("nij,nj->ni", A[y], rng.normal(size=(n, D))), y


def run_ours(X, y, **params):
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        model = DPGMMClusterer(random_state=0, **params).fit(X)
    seconds = time.perf_counter() - t0
    return model, {
        "seconds": seconds,
        "n_clusters": int(model.n_clusters_),
        "ari_truth": float(adjusted_rand_score(y, model.labels_)),
        "n_iter": int(model.n_iter_),
        "converged": not any(issubclass(w.category, ConvergenceWarning) for w in caught),
    }


def run_bgm(X, y, ours):
    bgm = BayesianGaussianMixture(
        n_components=20,
        weight_concentration_prior_type="dirichlet_process",
        weight_concentration_prior=1.0,
        mean_prior=ours.mean_prior_,
        mean_precision_prior=ours.mean_precision_prior_,
        covariance_prior=ours.covariance_prior_,
        degrees_of_freedom_prior=ours.degrees_of_freedom_prior_,
        max_iter=1000,
        random_state=0,
    )
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        bgm.fit(X)
    seconds = time.perf_counter() - t0
    labels = bgm.predict(X)
    return {
        "seconds": seconds,
        "n_clusters": int(len(np.unique(labels))),
        "ari_truth": float(adjusted_rand_score(y, labels)),
        "ari_ours": float(adjusted_rand_score(labels, ours.labels_)),
        "n_iter": int(bgm.n_iter_),
        "converged": bool(bgm.converged_),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--dims", type=int, nargs="+", default=[2])
    parser.add_argument("--clusters", type=int, default=6)
    parser.add_argument("--block-size", type=int, default=1024)
    parser.add_argument("--bgm-max", type=int, default=100_000)
    args = parser.parse_args()

    rows = []
    for D in args.dims:
        for n in args.sizes:
            X, y = blobs(n, D, args.clusters, seed=n + D)
            row = {"n": n, "D": D, "K_true": args.clusters}
            ours, row["exact"] = run_ours(X, y)
            _, row["blocked"] = run_ours(X, y, block_size=args.block_size)
            row["bgm"] = run_bgm(X, y, ours) if n <= args.bgm_max else None
            rows.append(row)
            print(json.dumps(row), flush=True)

    print()
    print("| n | D | method | fit s | K | ARI truth | sweeps/iters | converged | time / BGM |")
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        bgm_s = row["bgm"]["seconds"] if row["bgm"] else None
        for name in ("exact", "blocked", "bgm"):
            r = row[name]
            if r is None:
                continue
            ratio = f"{r['seconds'] / bgm_s:.2f}" if bgm_s else "-"
            label = {
                "exact": "DPGMMClusterer (exact)",
                "blocked": f"DPGMMClusterer (block_size={args.block_size})",
                "bgm": "BayesianGaussianMixture",
            }[name]
            print(
                f"| {row['n']} | {row['D']} | {label} | {r['seconds']:.2f} | {r['n_clusters']} "
                f"| {r['ari_truth']:.3f} | {r['n_iter']} | {r['converged']} | {ratio} |"
            )
    out = Path(__file__).resolve().parent / "results" / "bench_cluster.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"block_size": args.block_size, "rows": rows}, indent=2))
    print(f"\nwritten {out}")


if __name__ == "__main__":
    main()
