"""B2: MixtureGPOccupancyMap fit and predict time against the number of observations.

Run standalone: ``python benchmarks/bench_mixture.py [--sizes 1000 2000 ...] [--quick]``.
Prints a markdown table and writes ``benchmarks/results/bench_mixture.json``.

The paper's world (``make_paper_scans``) is scanned with more beams and more poses, so the
number of observations grows while the map stays the same; every size is mapped on the same
0.2 m grid of the observed cells. Fit time includes clustering, assignment and learning
the (shared) hyperparameters. The reference, measured in the same run, is one
``EPGaussianProcessClassifier``, the same as the experts (kernel and EP tolerance), on all
observations (at sizes up to ``--single-max``, it is cubic). The log-log slope of fit time
against n is fitted over the sizes from 2000 up (the target is <= 1.2: expert sizes are
capped by ``max_expert_size``), and from 300k to 3M (target <= 1: linear). Each size also
maps the whole world at 0.1 m (``OccupancyGrid.from_estimator``, probability and
variance), and reports the peak resident memory of the process and its workers (sampled
every 0.1 s with psutil, when installed) during fit and map. "largest" is the number of
rows the largest expert is fitted on (beam pieces, after thinning), the size that
``max_expert_size`` bounds.
"""

import argparse
import json
import os
import platform
import threading
import time
import warnings
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
from sklearn.metrics import roc_auc_score  # noqa: E402

from skoccmap import OccupancyGrid  # noqa: E402
from skoccmap._experts import _default_expert  # noqa: E402
from skoccmap.datasets import make_paper_scans  # noqa: E402
from skoccmap.mixture import MixtureGPOccupancyMap  # noqa: E402
from skoccmap.observations import as_segments  # noqa: E402

PAPER_N = 701  # observations of make_paper_scans() with its defaults
PAPER_BEAMS, PAPER_POSES = 17, 13


def scans_of_size(n):
    """The paper's world scanned with about ``n`` observations (beams and poses scaled)."""
    factor = np.sqrt(max(n, 1) / PAPER_N)
    beams = max(int(round(PAPER_BEAMS * factor)), 3)
    poses = max(int(round(PAPER_POSES * factor)), 2)
    return make_paper_scans(random_state=0, n_beams=beams, n_poses_per_piece=poses)


def timed(func):
    t0 = time.perf_counter()
    out = func()
    return out, time.perf_counter() - t0


class PeakMemory:
    """Peak resident memory (GiB) of this process and its children, sampled in a thread."""

    def __init__(self, interval=0.1):
        try:
            import psutil
        except ImportError:  # the measure is optional
            psutil = None
        self._psutil, self._interval, self.peak = psutil, interval, None

    def _rss(self):
        proc = self._psutil.Process()
        total = proc.memory_info().rss
        for child in proc.children(recursive=True):
            try:
                total += child.memory_info().rss
            except self._psutil.Error:
                pass
        return total / 2**30

    def _sample(self):
        while not self._stop.wait(self._interval):
            self.peak = max(self.peak, self._rss())

    def __enter__(self):
        if self._psutil is not None:
            self.peak = self._rss()
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        if self._psutil is not None:
            self._stop.set()
            self._thread.join()
            self.peak = max(self.peak, self._rss())


def run_size(n, args, grid):
    data = scans_of_size(n)
    Q = as_segments(grid.points[grid.observed])
    truth = grid.occupied[grid.observed]
    model = MixtureGPOccupancyMap(
        max_expert_size=args.max_expert_size, n_jobs=args.n_jobs, random_state=0
    )
    world = data.environment.extent if hasattr(data.environment, "extent") else None
    with warnings.catch_warnings(), PeakMemory() as memory:
        warnings.simplefilter("ignore")
        _, fit_s = timed(lambda: model.fit(data.X, data.y))
        proba, pred_s = timed(lambda: model.predict_proba(Q)[:, 1])
        # The whole world on the map grid, as `skoccmap map` draws it.
        extent = world if world is not None else data.X
        full_map, map_s = timed(
            lambda: OccupancyGrid.from_estimator(model, extent=extent, resolution=0.1)
        )
    # Rows each expert is fitted on (beam pieces after thinning), what max_expert_size
    # bounds; the input observations anchored at an expert's hits can be many more.
    sizes = np.array([getattr(e, "X_train_", np.empty((0,))).shape[0] for e in model.experts_])
    row = {
        "n": int(data.X.shape[0]),
        "fit_s": fit_s,
        "predict_s": pred_s,
        "predict_us_per_cell": 1e6 * pred_s / Q.shape[0],
        "map_cells": int(full_map.probability.size),
        "map_s": map_s,
        "peak_gib": memory.peak,
        "n_experts": int(model.n_experts_),
        "largest_expert": int(sizes.max()),
        "auc": float(roc_auc_score(truth, proba)),
    }
    if row["n"] <= args.single_max:
        single = _default_expert()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, single_fit = timed(lambda: single.fit(data.X, data.y))
            p_single, single_pred = timed(lambda: single.predict_proba(Q)[:, 1])
        row.update(
            single_fit_s=single_fit,
            single_predict_s=single_pred,
            single_auc=float(roc_auc_score(truth, p_single)),
            speedup=(single_fit + single_pred) / (fit_s + pred_s),
        )
    return row


def slope(rows, key, n_min=2000, n_max=np.inf):
    pts = [(r["n"], r[key]) for r in rows if n_min * 0.9 <= r["n"] <= n_max * 1.1]
    if len(pts) < 2:
        return None
    n, t = np.log(np.array(pts)).T
    return float(np.polyfit(n, t, 1)[0])


def fmt(value, spec):
    return "" if value is None else format(value, spec)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        default=[1000, 2000, 4000, 8000, 16000, 32000, 64000, 300000, 3000000],
    )
    parser.add_argument("--quick", action="store_true", help="sizes 1000 2000 4000 only")
    parser.add_argument("--single-max", type=int, default=2100)
    parser.add_argument("--max-expert-size", type=int, default=400)
    parser.add_argument("--n-jobs", type=int, default=1)
    parser.add_argument("--resolution", type=float, default=0.2)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    args = parser.parse_args()
    sizes = [1000, 2000, 4000] if args.quick else args.sizes

    env = make_paper_scans(random_state=0)
    grid = env.environment.ground_truth_grid(args.resolution, scans=env.scans)
    rows = []
    for n in sizes:
        row = run_size(n, args, grid)
        rows.append(row)
        print(
            f"n={row['n']}: fit {row['fit_s']:.1f} s, predict {row['predict_s']:.1f} s, "
            f"0.1 m map {row['map_s']:.1f} s, {row['n_experts']} experts, "
            f"peak {fmt(row['peak_gib'], '.2f')} GiB",
            flush=True,
        )

    fit_slope, pred_slope = slope(rows, "fit_s", n_max=64000), slope(rows, "predict_s")
    big_slope = slope(rows, "fit_s", n_min=300000)
    print()
    print(f"B2 mixture scaling (grid {args.resolution} m, {int(grid.observed.sum())} cells)")
    print()
    print(
        "| n | experts | largest | fit s | predict s | us/cell | 0.1 m map s | peak GiB | AUC "
        "| single fit s | single predict s | single AUC | speed-up |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['n']} | {r['n_experts']} | {r['largest_expert']} | {r['fit_s']:.2f} "
            f"| {r['predict_s']:.2f} | {r['predict_us_per_cell']:.0f} | {r['map_s']:.1f} "
            f"| {fmt(r['peak_gib'], '.2f')} | {r['auc']:.4f} "
            f"| {fmt(r.get('single_fit_s'), '.2f')} | {fmt(r.get('single_predict_s'), '.2f')} "
            f"| {fmt(r.get('single_auc'), '.4f')} | {fmt(r.get('speedup'), '.1f')} |"
        )
    print()
    print(f"log-log slope of fit time, 2000 <= n <= 64k: {fmt(fit_slope, '.2f')} (target <= 1.2)")
    print(f"log-log slope of fit time, n >= 300k: {fmt(big_slope, '.2f')} (target <= 1)")
    print(f"log-log slope of predict time, n >= 2000: {fmt(pred_slope, '.2f')}")

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {
        "benchmark": "B2 mixture scaling",
        "machine": platform.platform(),
        "cpu_count": os.cpu_count(),
        "params": vars(args),
        "rows": rows,
        "fit_slope": fit_slope,
        "fit_slope_300k_3m": big_slope,
        "predict_slope": pred_slope,
    }
    (out / "bench_mixture.json").write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
