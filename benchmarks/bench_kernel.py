"""Speed of IntegralKernel (K and its gradient) against double Simpson quadrature.

Workload: n random laser-beam segments in a 22 m x 18 m area, random directions, lengths uniform
in [0, 8] m, length scale l = 0.5 m (the paper's setting). Reference: the paper's method, the
point kernel integrated by composite Simpson on N nodes per segment, written here with a BLAS
distance matrix between all quadrature nodes; N is the smallest that reaches the same accuracy
(relative error <= 1e-6, or absolute <= 1e-12 where the value is tiny) on a sample of pairs. The
reference cost is exactly proportional to the number of rows, so it is timed on a block of rows
and scaled to n (reported as such). Peak extra memory of ours is measured with tracemalloc.

Run: ``python benchmarks/bench_kernel.py [--sizes 700 2000] [--repeat 3]``
Writes ``benchmarks/results/bench_kernel.json`` and prints a markdown table.
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

LENGTH_SCALE = 0.5
RTOL, ATOL = 1e-6, 1e-12


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


def run(sizes, repeat, ref_rows, seed):
    kernel = IntegralKernel(LENGTH_SCALE)
    results = []
    for n in sizes:
        rng = np.random.default_rng(seed)
        X = random_beams(n, rng)
        t_k = best_time(lambda X=X: kernel(X), repeat)
        t_kg = best_time(lambda X=X: kernel(X, eval_gradient=True), repeat)
        K, G = kernel(X, eval_gradient=True)
        extra, out_bytes = peak_memory(lambda X=X: kernel(X, eval_gradient=True))

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


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[700, 2000])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--ref-rows", type=int, default=8, help="rows timed for the reference")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    results = run(args.sizes, args.repeat, args.ref_rows, args.seed)

    print("| n | ours K (s) | ours K+grad (s) | Simpson N | Simpson K+grad (s, scaled) "
          "| speed-up | peak extra / output |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['n']} | {r['ours_K_s']:.3f} | {r['ours_K_grad_s']:.3f} "
              f"| {r['simpson_nodes_per_segment']} | {r['simpson_K_grad_s']:.1f} "
              f"| {r['speedup_K_grad']:.0f}x | {r['peak_extra_over_output']:.2f} |")
    out = Path(__file__).resolve().parent / "results" / "bench_kernel.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "workload": "random beams in 22 m x 18 m, lengths U(0, 8) m, l = 0.5 m, K + gradient",
        "reference": "double composite Simpson of the point kernel, N nodes per segment, "
                     "timed on a row block and scaled by rows",
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "results": results,
    }
    out.write_text(json.dumps(meta, indent=2))
    print(f"\nwritten {out}")


if __name__ == "__main__":
    main()
