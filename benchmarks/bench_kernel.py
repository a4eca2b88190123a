"""Speed of IntegralKernel: K(X) and its gradient against double Simpson, and cross-kernels.

Self workload: n random laser-beam segments in a 22 m x 18 m area, random directions, lengths
uniform in [0, 8] m, l = 0.5 m (the paper's setting). Reference: the paper's method, the
point kernel integrated by composite Simpson on N nodes per segment, written here with a BLAS
distance matrix between all quadrature nodes (every pair, no cut-off).

Which N? A reference is only as fast as the accuracy demanded of it, so N is chosen by what a
map can use, measured (``--workloads sensitivity``): on the paper's data
(``make_paper_scans(random_state=0)``, 701 observations, whole beams) an
``EPGaussianProcessClassifier`` with ``ConstantKernel(1e3) * K`` (the mixture's default signal
variance; fixed hyperparameters, l = 0.5 m) is fitted with K from double Simpson at 21, 41, 81,
161 and 321 nodes per beam (a point takes one node), and with our kernel; the report is the
largest change of the predicted P(occupied) over the 0.2 m grid of the world (10 101 cells)
against the 321-node fit and against ours. The reference is timed at the node counts
``--nodes`` (default 21, 41 and 81); the speed-up quoted is at the smallest N whose map is within
1e-3 of the converged one (one grey level of a PGM map is 1/255).

Both sides are timed alike: a warm-up call, then the best of ``--repeat`` calls. The reference
cost is exactly proportional to the number of rows, so it is timed on a block of ``--ref-rows``
rows and scaled to n (reported as such). Its accuracy (largest absolute difference from ours on
those rows) is reported next to it. The node count at which Simpson agrees with ours to a
relative 1e-6 on every entry (the criterion of an earlier version of this script, which set the
reference by it) is still found, as a check of our kernel's accuracy, but not used for timing.
Peak extra memory of ours is measured with tracemalloc.

Cross workloads (prediction: query points against training beams and hits), timed with the
point fast path (closed forms, tiled cut-off pre-cut) against the general path (dense
bounding-circle pre-cut, every pair with a segment through the segment-segment quadrature),
both in this run, l = 0.5 m:

- ``paper``: ``make_paper_scans(random_state=0)`` (701 beams and hits) against 10 000 query
  points on a 100 x 100 grid over its 22 m x 18 m world;
- ``intel``: 139 320 query points on a 0.1 m grid over the Intel Research Lab's hits against
  one expert-sized set of 400 observations (the beams and hits whose midpoints are nearest the
  map's centre); skipped when ``../shared/data/intel.gfs.log`` is absent.

Run: ``python benchmarks/bench_kernel.py [--sizes 700 2000] [--repeat 3] [--nodes 21 41 81]
[--skip-simpson] [--workloads sensitivity self cross]``. Writes
``benchmarks/results/bench_kernel_sensitivity.json``, ``benchmarks/results/bench_kernel.json``
(self) and ``benchmarks/results/bench_kernel_cross.json`` (cross) and prints markdown tables.
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

from skoccmap import EPGaussianProcessClassifier, IntegralKernel  # noqa: E402
from skoccmap._integrals import integral_kernel  # noqa: E402
from skoccmap.datasets import load_carmen, make_paper_scans  # noqa: E402
from skoccmap.observations import as_segments  # noqa: E402

LENGTH_SCALE = 0.5
RTOL, ATOL = 1e-6, 1e-12
SENSITIVITY_NODES = (21, 41, 81, 161, 321)
SIGNAL_VARIANCE = 1e3  # the mixture's default ConstantKernel
MAP_TOLERANCE = 1e-3  # a change of P(occupied) a map can show: under one grey level (1/255)
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
        Q = pts[c0 : c0 + block].reshape(-1, dim)
        q2 = np.einsum("ij,ij->i", Q, Q)
        for r, i in enumerate(rows):
            P = pts[i]
            d2 = np.einsum("ij,ij->i", P, P)[:, None] + q2[None, :] - 2.0 * P @ Q.T
            np.maximum(d2, 0.0, out=d2)
            k = np.exp(-0.5 * d2)
            K[r, c0 : c0 + block] = (w @ k).reshape(-1, n_nodes) @ w
            if eval_gradient:
                G[r, c0 : c0 + block] = (w @ (d2 * k)).reshape(-1, n_nodes) @ w
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


def simpson_cross(A, B, n_nodes, length_scale=LENGTH_SCALE, block=64):
    """K(A, B) by double Simpson on ``n_nodes`` per segment; a point (zero length) takes one.

    The same quadrature as :func:`simpson_kernel` (a zero-length segment's nodes coincide and
    its weights sum to one, so a single node gives the same value at less cost).
    """
    dim = A.shape[1] // 2
    A, B = A / length_scale, B / length_scale
    out = np.empty((len(A), len(B)))

    def parts(X):
        point = np.all(X[:, :dim] == X[:, dim:], axis=1)
        seg = np.flatnonzero(~point)
        nodes, w = simpson_nodes(X[seg], n_nodes)
        return seg, nodes, w, np.flatnonzero(point), X[point, :dim]

    def sq_dist(U, V):
        d2 = np.einsum("ij,ij->i", U, U)[:, None] + np.einsum("ij,ij->i", V, V)[None] - 2 * U @ V.T
        return np.maximum(d2, 0.0, out=d2)

    a_seg, a_nodes, w, a_pt, a_xy = parts(A)
    b_seg, b_nodes, _, b_pt, b_xy = parts(B)
    out[np.ix_(a_pt, b_pt)] = np.exp(-0.5 * sq_dist(a_xy, b_xy))
    for r0 in range(0, len(a_seg), block):
        P = a_nodes[r0 : r0 + block]
        k = np.exp(-0.5 * sq_dist(P.reshape(-1, dim), b_xy)).reshape(len(P), n_nodes, len(b_xy))
        out[np.ix_(a_seg[r0 : r0 + block], b_pt)] = np.einsum("j,ijk->ik", w, k)
    for c0 in range(0, len(b_seg), block):
        P = b_nodes[c0 : c0 + block]
        k = np.exp(-0.5 * sq_dist(a_xy, P.reshape(-1, dim))).reshape(len(a_xy), len(P), n_nodes)
        out[np.ix_(a_pt, b_seg[c0 : c0 + block])] = k @ w
    for c0 in range(0, len(b_seg), block):
        Q = b_nodes[c0 : c0 + block].reshape(-1, dim)
        cols = b_seg[c0 : c0 + block]
        for r, i in enumerate(a_seg):
            out[i, cols] = (w @ np.exp(-0.5 * sq_dist(a_nodes[r], Q))).reshape(-1, n_nodes) @ w
    return out


_SIMPSON_CACHE = {}


class SimpsonIntegralKernel(IntegralKernel):
    """:class:`IntegralKernel` evaluated by double Simpson on ``n_nodes`` (fixed length scale)."""

    def __init__(self, length_scale=1.0, length_scale_bounds="fixed", n_nodes=41):
        super().__init__(length_scale, length_scale_bounds)
        self.n_nodes = n_nodes

    def __call__(self, X, Y=None, eval_gradient=False):
        Y = X if Y is None else Y
        key = (self.n_nodes, float(self.length_scale), X.tobytes(), Y.tobytes())
        if key not in _SIMPSON_CACHE:  # the fit and the check below need the same K
            _SIMPSON_CACHE.clear()
            _SIMPSON_CACHE[key] = simpson_cross(X, Y, self.n_nodes, float(self.length_scale))
        K = _SIMPSON_CACHE[key].copy()
        if eval_gradient:
            return K, np.empty((X.shape[0], X.shape[0], 0))
        return K

    def diag(self, X):
        nodes, w = simpson_nodes(X / float(self.length_scale), self.n_nodes)
        d2 = ((nodes[:, :, None, :] - nodes[:, None, :, :]) ** 2).sum(-1)
        return np.einsum("i,nij,j->n", w, np.exp(-0.5 * d2), w)


def map_sensitivity(node_counts=SENSITIVITY_NODES):
    """Largest change of the fitted GP's P(occupied) on the paper's 0.2 m grid with N."""
    from sklearn.gaussian_process.kernels import ConstantKernel

    data = make_paper_scans(random_state=0)
    X, y = data.X, data.y
    gx, gy = np.meshgrid(np.arange(0.0, 22.0 + 1e-9, 0.2), np.arange(0.0, 18.0 + 1e-9, 0.2))
    Q = as_segments(np.column_stack([gx.ravel(), gy.ravel()]))

    def fit_predict(kernel):
        gp = EPGaussianProcessClassifier(
            ConstantKernel(SIGNAL_VARIANCE, "fixed") * kernel, optimizer=None
        ).fit(X, y)
        return gp.predict_proba(Q)[:, 1], gp.predict_proba(X)[:, 1]

    ours = fit_predict(IntegralKernel(LENGTH_SCALE, "fixed"))
    K_ours = integral_kernel(X, length_scale=LENGTH_SCALE)
    maps, rows = {}, []
    for n_nodes in node_counts:
        start = time.perf_counter()
        kernel = SimpsonIntegralKernel(LENGTH_SCALE, n_nodes=n_nodes)
        maps[n_nodes] = fit_predict(kernel)
        seconds = time.perf_counter() - start
        K_ref = kernel(X)
        rows.append(
            {
                "nodes": n_nodes,
                "fit_predict_s": seconds,
                "K_max_abs_diff_vs_ours": float(np.abs(K_ref - K_ours).max()),
            }
        )
    top = maps[node_counts[-1]]
    for row in rows:
        grid, train = maps[row["nodes"]]
        row["map_max_abs_dp_vs_converged"] = float(np.abs(grid - top[0]).max())
        row["train_max_abs_dp_vs_converged"] = float(np.abs(train - top[1]).max())
        row["map_max_abs_dp_vs_ours"] = float(np.abs(grid - ours[0]).max())
        row["train_max_abs_dp_vs_ours"] = float(np.abs(train - ours[1]).max())
    usable = [r["nodes"] for r in rows[:-1] if r["map_max_abs_dp_vs_converged"] <= MAP_TOLERANCE]
    return {
        "data": "make_paper_scans(random_state=0): 701 observations, whole beams",
        "model": f"EPGaussianProcessClassifier, ConstantKernel({SIGNAL_VARIANCE:g}, fixed) * "
        f"kernel, l = {LENGTH_SCALE} m fixed",
        "query": f"{len(Q)} cells, 0.2 m grid over [0, 22] x [0, 18] m",
        "converged_reference_nodes": node_counts[-1],
        "map_tolerance": MAP_TOLERANCE,
        "smallest_usable_nodes": min(usable) if usable else None,
        "results": rows,
    }


def best_time(func, repeat):
    """Best of ``repeat`` timed calls after one untimed warm-up call."""
    func()
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


def run(sizes, repeat, ref_rows, seed, nodes, simpson=True):
    kernel = IntegralKernel(LENGTH_SCALE)
    results = []
    for n in sizes:
        rng = np.random.default_rng(seed)
        X = random_beams(n, rng)
        t_k = best_time(lambda X=X: kernel(X), repeat)
        t_kg = best_time(lambda X=X: kernel(X, eval_gradient=True), repeat)
        K, G = kernel(X, eval_gradient=True)
        extra, out_bytes = peak_memory(lambda X=X: kernel(X, eval_gradient=True))
        row = {
            "n": n,
            "ours_K_s": t_k,
            "ours_K_grad_s": t_kg,
            "ours_peak_extra_MB": extra / 2**20,
            "output_MB": out_bytes / 2**20,
            "peak_extra_over_output": extra / out_bytes,
        }
        results.append(row)
        if not simpson:
            continue
        rows = rng.choice(n, size=min(ref_rows, n), replace=False)
        row["simpson_rows_timed"] = len(rows)
        row["simpson_repeat"] = repeat
        row["simpson"] = []
        for n_nodes in nodes:
            t_block = best_time(lambda X=X, r=rows, m=n_nodes: simpson_kernel(X, r, m), repeat)
            K_ref, G_ref = simpson_kernel(X, rows, n_nodes)
            row["simpson"].append(
                {
                    "nodes": n_nodes,
                    "K_grad_s": t_block * n / len(rows),
                    "speedup_K_grad": t_block * n / len(rows) / t_kg,
                    "K_max_abs_err": float(np.abs(K_ref - K[rows]).max()),
                    "grad_max_abs_err": float(np.abs(G_ref - G[rows, :, 0]).max()),
                }
            )
        # Check of our accuracy: Simpson converges to ours (relative 1e-6 on every entry).
        check = rows[: max(2, len(rows) // 4)]
        n_strict = simpson_order_for_accuracy(X, K, check)
        K_ref, _ = simpson_kernel(X, check, n_strict, eval_gradient=False)
        row["nodes_for_rel_1e-6"] = n_strict
        row["simpson_matches_ours_rel_1e-6"] = bool(np.all(ok(K_ref, K[check])))
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
        t_fast = best_time(
            lambda Q=Q, X=X: integral_kernel(Q, X, length_scale=LENGTH_SCALE), repeat
        )
        t_kernel = best_time(lambda Q=Q, X=X: IntegralKernel(LENGTH_SCALE)(Q, X), repeat)
        t_general = best_time(
            lambda Q=Q, X=X: integral_kernel(Q, X, length_scale=LENGTH_SCALE, _fast=False),
            max(1, min(repeat, 2)),
        )
        results.append(
            {
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
            }
        )
    return results


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[700, 2000])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--ref-rows", type=int, default=16, help="rows timed for the reference")
    parser.add_argument(
        "--nodes",
        type=int,
        nargs="+",
        default=[21, 41, 81],
        help="Simpson nodes per segment at which the reference is timed",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--skip-simpson",
        action="store_true",
        help="time K(X) without the (slow) double Simpson reference",
    )
    parser.add_argument(
        "--workloads",
        nargs="+",
        choices=["sensitivity", "self", "cross"],
        default=["sensitivity", "self", "cross"],
    )
    args = parser.parse_args()
    results_dir = Path(__file__).resolve().parent / "results"
    results_dir.mkdir(parents=True, exist_ok=True)
    meta = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "processor": platform.processor(),
        "date": time.strftime("%Y-%m-%d"),
    }

    if "sensitivity" in args.workloads:
        sens = map_sensitivity()
        print(
            "| Simpson N | K max abs diff vs ours | map max dP vs N = "
            f"{sens['converged_reference_nodes']} | map max dP vs ours "
            "| training rows max dP vs ours | fit + predict s |"
        )
        print("|---|---|---|---|---|---|")
        for r in sens["results"]:
            print(
                f"| {r['nodes']} | {r['K_max_abs_diff_vs_ours']:.1e} "
                f"| {r['map_max_abs_dp_vs_converged']:.1e} | {r['map_max_abs_dp_vs_ours']:.1e} "
                f"| {r['train_max_abs_dp_vs_ours']:.1e} | {r['fit_predict_s']:.1f} |"
            )
        print(
            f"\nsmallest N within {MAP_TOLERANCE:g} of the converged map: "
            f"{sens['smallest_usable_nodes']}"
        )
        out = results_dir / "bench_kernel_sensitivity.json"
        out.write_text(json.dumps({**sens, **meta}, indent=2))
        print(f"\nwritten {out}\n")

    if "self" in args.workloads:
        simpson = not args.skip_simpson
        results = run(
            args.sizes, args.repeat, args.ref_rows, args.seed, args.nodes, simpson=simpson
        )
        if simpson:
            print(
                "| n | ours K (s) | ours K+grad (s) | Simpson N | Simpson max abs err "
                "| Simpson K+grad (s, scaled) | speed-up | peak extra / output |"
            )
            print("|---|---|---|---|---|---|---|---|")
            for r in results:
                for ref in r["simpson"]:
                    print(
                        f"| {r['n']} | {r['ours_K_s']:.3f} | {r['ours_K_grad_s']:.3f} "
                        f"| {ref['nodes']} | {ref['K_max_abs_err']:.0e} "
                        f"| {ref['K_grad_s']:.2f} | {ref['speedup_K_grad']:.0f}x "
                        f"| {r['peak_extra_over_output']:.2f} |"
                    )
            for r in results:
                print(
                    f"\nn = {r['n']}: Simpson agrees with ours to a relative 1e-6 at "
                    f"N = {r['nodes_for_rel_1e-6']} "
                    f"({'yes' if r['simpson_matches_ours_rel_1e-6'] else 'NO'})"
                )
        else:
            print("| n | ours K (s) | ours K+grad (s) | peak extra / output |")
            print("|---|---|---|---|")
            for r in results:
                print(
                    f"| {r['n']} | {r['ours_K_s']:.3f} | {r['ours_K_grad_s']:.3f} "
                    f"| {r['peak_extra_over_output']:.2f} |"
                )
        out = results_dir / ("bench_kernel.json" if simpson else "bench_kernel_self.json")
        out.write_text(
            json.dumps(
                {
                    "workload": "random beams in 22 m x 18 m, lengths U(0, 8) m, l = 0.5 m, "
                    "K + gradient",
                    "reference": (
                        "double composite Simpson of the point kernel, N nodes per segment, "
                        "best of repeat after a warm-up, timed on a row block and scaled by "
                        "rows"
                        if simpson
                        else "none"
                    ),
                    **meta,
                    "results": results,
                },
                indent=2,
            )
        )
        print(f"\nwritten {out}\n")

    if "cross" in args.workloads:
        results = run_cross(args.repeat)
        print(
            "| workload | queries x train (points) | nonzero | general path (s) "
            "| fast path (s) | IntegralKernel call (s) | speed-up | max abs diff |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for r in results:
            print(
                f"| {r['workload']} | {r['n_queries']} x {r['n_train']} "
                f"({r['n_train_points']}) | {r['nonzero_fraction']:.1%} "
                f"| {r['general_s']:.3f} | {r['fast_s']:.3f} "
                f"| {r['IntegralKernel_call_s']:.3f} | {r['speedup']:.1f}x "
                f"| {r['max_abs_diff']:.1e} |"
            )
        out = results_dir / "bench_kernel_cross.json"
        out.write_text(
            json.dumps(
                {
                    "workload": "K(query points, training beams and hits), l = 0.5 m",
                    "reference": "general path of the same code "
                    "(integral_kernel(..., _fast=False)), same run",
                    **meta,
                    "results": results,
                },
                indent=2,
            )
        )
        print(f"\nwritten {out}")


if __name__ == "__main__":
    main()
