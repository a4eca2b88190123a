"""Speed of IntegralKernel: K(X) and its gradient against double Simpson, and cross-kernels.

Self workload: n random laser-beam segments in a 22 m x 18 m area, random directions, lengths
uniform in [0, 8] m, l = 0.5 m (the paper's setting). Reference: the paper's method, the
point kernel integrated by composite Simpson on N nodes per segment, written here with a BLAS
distance matrix between all quadrature nodes; N is the smallest that reaches the same accuracy
(relative error <= 1e-6, or absolute <= 1e-12 where the value is tiny) on a sample of pairs. The
reference cost is exactly proportional to the number of rows, so it is timed on a block of rows
and scaled to n (reported as such). Peak extra memory of ours is measured with tracemalloc.

Cross workloads (prediction: query points against training beams and hits), timed with the
point fast path (closed forms, tiled cut-off pre-cut) against the general path (dense
bounding-circle pre-cut, every pair with a segment through the segment-segment quadrature),
both in this run, l = 0.5 m:

- ``paper``: ``make_paper_scans(random_state=0)`` (701 beams and hits) against 10 000 query
  points on a 100 x 100 grid over its 22 m x 18 m world;
- ``intel``: 139 320 query points on a 0.1 m grid over the Intel Research Lab's hits against
  one expert-sized set of 400 observations (the beams and hits whose midpoints are nearest the
  map's centre); skipped when ``../shared/data/intel.gfs.log`` is absent.

Run: ``python benchmarks/bench_kernel.py [--sizes 700 2000] [--repeat 3] [--skip-simpson]
[--workloads self cross]``. Writes ``benchmarks/results/bench_kernel.json`` (self) and
``benchmarks/results/bench_kernel_cross.json`` (cross) and prints markdown tables.
"""

import argparse
import json
import os
import platform
import time
import tracemalloc
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from skoccmap import IntegralKernel  # noqa: E402
from skoccmap._integrals import integral_kernel  # noqa: E402
from skoccmap.datasets import load_carmen, make_paper_scans  # noqa: E402
from skoccmap.observations import as_segments  # noqa: E402

LENGTH_SCALE = 0.5
RTOL, ATOL = 1e-6, 1e-12
INTEL_LOG = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "intel.gfs.log"


def random_beams(n, rng):
    start = rng.uniform([0.0, 0.0], [22.0, 18.0], (n, 2))
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    length = rng.uniform(0.0, 8.0, n)
    end = start + length[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    return np.hstack([start, end])


def simpson_nodes(X, n_nodes):
    """Simpson nodes (n, N, D) along each segment and the weights (N,) on [0, 1]."""
    dim = X.shape[1] // 2
    t = np.linspace(0.0, 1.0, n_nodes)
    w = np.ones(n_nodes)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    w /= 3.0 * (n_nodes - 1)
    pts = X[:, None, :dim] + t[None, :, None] * (X[:, None, dim:] - X[:, None, :dim])
    return pts, w


def simpson_kernel(X, rows, n_nodes, length_scale=LENGTH_SCALE, eval_gradient=True, block=100):
    """Reference K[rows] (and its log-length-scale gradient) by double Simpson quadrature."""
    pts, w = simpson_nodes(X / length_scale, n_nodes)
    n, dim = X.shape[0], X.shape[1] // 2
    K = np.empty((len(rows), n))
    G = np.empty((len(rows), n)) if eval_gradient else None
    for c0 in range(0, n, block):
        Q = pts[c0:c0 + block].reshape(-1, dim)
        q2 = np.einsum("ij,ij->i", Q, Q)
        for r, i in enumerate(rows):
            P = pts[i]
            d2 = np.einsum("ij,ij->i", P, P)[:, None] + q2[None, :] - 2.0 * P @ Q.T
            np.maximum(d2, 0.0, out=d2)
            k = np.exp(-0.5 * d2)
            K[r, c0:c0 + block] = (w @ k).reshape(-1, n_nodes) @ w
            if eval_gradient:
                G[r, c0:c0 + block] = (w @ (d2 * k)).reshape(-1, n_nodes) @ w
    return K, G


def ok(actual, expected):
    err = np.abs(actual - expected)
    return (err <= RTOL * np.abs(expected)) | (err <= ATOL)


def simpson_order_for_accuracy(X, K, rows):
    """Smallest odd N (to within 2 %) with which double Simpson matches K[rows] to the target."""

    def good(n_nodes):
        K_ref, _ = simpson_kernel(X, rows, n_nodes, eval_gradient=False)
        return bool(np.all(ok(K_ref, K[rows])))

    lo, hi = 1, 21
    while not good(hi):
        lo, hi = hi, 2 * hi - 1
        if hi > 5000:
            raise RuntimeError("Simpson did not converge")
    while hi - lo > max(2, hi // 50):
        mid = (lo + hi) // 2 | 1
        lo, hi = (lo, mid) if good(mid) else (mid, hi)
    return hi


def best_time(func, repeat):
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return min(times)


def peak_memory(func):
    tracemalloc.start()
    tracemalloc.reset_peak()
    out = func()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    out_bytes = sum(a.nbytes for a in (out if isinstance(out, tuple) else (out,)))
    return peak - out_bytes, out_bytes


def run(sizes, repeat, ref_rows, seed, simpson=True):
    kernel = IntegralKernel(LENGTH_SCALE)
    results = []
    for n in sizes:
        rng = np.random.default_rng(seed)
        X = random_beams(n, rng)
        t_k = best_time(lambda X=X: kernel(X), repeat)
        t_kg = best_time(lambda X=X: kernel(X, eval_gradient=True), repeat)
        K, G = kernel(X, eval_gradient=True)
        extra, out_bytes = peak_memory(lambda X=X: kernel(X, eval_gradient=True))
        if not simpson:
            results.append({
                "n": n, "ours_K_s": t_k, "ours_K_grad_s": t_kg,
                "ours_peak_extra_MB": extra / 2**20, "output_MB": out_bytes / 2**20,
                "peak_extra_over_output": extra / out_bytes,
            })
            continue

        rows = rng.choice(n, size=min(ref_rows, n), replace=False)
        n_nodes = simpson_order_for_accuracy(X, K, rows[: max(2, len(rows) // 4)])
        t_ref_block = best_time(lambda X=X, r=rows, m=n_nodes: simpson_kernel(X, r, m), 1)
        t_ref = t_ref_block * n / len(rows)
        K_ref, G_ref = simpson_kernel(X, rows, n_nodes)
        grad_err = np.max(np.abs(G_ref - G[rows, :, 0]) / np.maximum(np.abs(G[rows, :, 0]), 1e-6))
        results.append({
            "n": n,
            "ours_K_s": t_k,
            "ours_K_grad_s": t_kg,
            "simpson_nodes_per_segment": n_nodes,
            "simpson_K_grad_s": t_ref,
            "simpson_rows_timed": len(rows),
            "speedup_K_grad": t_ref / t_kg,
            "ours_peak_extra_MB": extra / 2**20,
            "output_MB": out_bytes / 2**20,
            "peak_extra_over_output": extra / out_bytes,
            "simpson_matches_ours_K": bool(np.all(ok(K_ref, K[rows]))),
            "simpson_vs_ours_grad_max_rel": float(grad_err),
        })
    return results


def paper_cross():
    X = make_paper_scans(random_state=0).X
    gx, gy = np.meshgrid(np.linspace(0.0, 22.0, 100), np.linspace(0.0, 18.0, 100))
    return as_segments(np.column_stack([gx.ravel(), gy.ravel()])), X


def intel_cross(n_train=400):
    X, y, _ = load_carmen(INTEL_LOG).to_observations()
    hits = X[y == 1, :2]
    lo, hi = hits.min(axis=0), hits.max(axis=0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], 0.1), np.arange(lo[1], hi[1], 0.1))
    mid = 0.5 * (X[:, :2] + X[:, 2:])
    nearest = np.argsort(np.linalg.norm(mid - 0.5 * (lo + hi), axis=1))[:n_train]
    return as_segments(np.column_stack([gx.ravel(), gy.ravel()])), X[nearest]


def run_cross(repeat, workloads=("paper", "intel")):
    results = []
    for name in workloads:
        if name == "intel" and not INTEL_LOG.exists():
            print(f"skipping intel: {INTEL_LOG} not found")
            continue
        Q, X = paper_cross() if name == "paper" else intel_cross()
        is_point = np.all(X[:, :2] == X[:, 2:], axis=1)
        K_fast = integral_kernel(Q, X, length_scale=LENGTH_SCALE)
        K_general = integral_kernel(Q, X, length_scale=LENGTH_SCALE, _fast=False)
        t_fast = best_time(lambda Q=Q, X=X: integral_kernel(Q, X, length_scale=LENGTH_SCALE),
                           repeat)
        t_kernel = best_time(lambda Q=Q, X=X: IntegralKernel(LENGTH_SCALE)(Q, X), repeat)
        t_general = best_time(
            lambda Q=Q, X=X: integral_kernel(Q, X, length_scale=LENGTH_SCALE, _fast=False),
            max(1, min(repeat, 2)),
        )
        results.append({
            "workload": name,
            "n_queries": len(Q),
            "n_train": len(X),
            "n_train_points": int(is_point.sum()),
            "nonzero_fraction": float(np.count_nonzero(K_fast) / K_fast.size),
            "general_s": t_general,
            "fast_s": t_fast,
            "IntegralKernel_call_s": t_kernel,
            "speedup": t_general / t_fast,
            "max_abs_diff": float(np.abs(K_fast - K_general).max()),
        })
    return results


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[700, 2000])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--ref-rows", type=int, default=8, help="rows timed for the reference")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-simpson", action="store_true",
                        help="time K(X) without the (slow) double Simpson reference")
    parser.add_argument("--workloads", nargs="+", choices=["self", "cross"],
                        default=["self", "cross"])
    args = parser.parse_args()
    results_dir = Path(__file__).resolve().parent / "results"
    results_dir.mkdir(parents=True, exist_ok=True)
    meta = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
    }

    if "self" in args.workloads:
        simpson = not args.skip_simpson
        results = run(args.sizes, args.repeat, args.ref_rows, args.seed, simpson=simpson)
        if simpson:
            print("| n | ours K (s) | ours K+grad (s) | Simpson N | Simpson K+grad (s, scaled) "
                  "| speed-up | peak extra / output |")
            print("|---|---|---|---|---|---|---|")
            for r in results:
                print(f"| {r['n']} | {r['ours_K_s']:.3f} | {r['ours_K_grad_s']:.3f} "
                      f"| {r['simpson_nodes_per_segment']} | {r['simpson_K_grad_s']:.1f} "
                      f"| {r['speedup_K_grad']:.0f}x | {r['peak_extra_over_output']:.2f} |")
        else:
            print("| n | ours K (s) | ours K+grad (s) | peak extra / output |")
            print("|---|---|---|---|")
            for r in results:
                print(f"| {r['n']} | {r['ours_K_s']:.3f} | {r['ours_K_grad_s']:.3f} "
                      f"| {r['peak_extra_over_output']:.2f} |")
        out = results_dir / ("bench_kernel.json" if simpson else "bench_kernel_self.json")
        out.write_text(json.dumps({
            "workload": "random beams in 22 m x 18 m, lengths U(0, 8) m, l = 0.5 m, "
                        "K + gradient",
            "reference": "double composite Simpson of the point kernel, N nodes per segment, "
                         "timed on a row block and scaled by rows" if simpson else "none",
            **meta,
            "results": results,
        }, indent=2))
        print(f"\nwritten {out}\n")

    if "cross" in args.workloads:
        results = run_cross(args.repeat)
        print("| workload | queries x train (points) | nonzero | general path (s) "
              "| fast path (s) | IntegralKernel call (s) | speed-up | max abs diff |")
        print("|---|---|---|---|---|---|---|---|")
        for r in results:
            print(f"| {r['workload']} | {r['n_queries']} x {r['n_train']} "
                  f"({r['n_train_points']}) | {r['nonzero_fraction']:.1%} "
                  f"| {r['general_s']:.3f} | {r['fast_s']:.3f} "
                  f"| {r['IntegralKernel_call_s']:.3f} | {r['speedup']:.1f}x "
                  f"| {r['max_abs_diff']:.1e} |")
        out = results_dir / "bench_kernel_cross.json"
        out.write_text(json.dumps({
            "workload": "K(query points, training beams and hits), l = 0.5 m",
            "reference": "general path of the same code (integral_kernel(..., _fast=False)), "
                         "same run",
            **meta,
            "results": results,
        }, indent=2))
        print(f"\nwritten {out}")


if __name__ == "__main__":
    main()
