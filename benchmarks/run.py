"""The benchmark suite in one command: workloads B1-B4 with the baselines, same run.

Run::

    python benchmarks/run.py              # full: B1, B2 (1k..3M), B3 (all, 10th, 40th scan), B4
    python benchmarks/run.py --quick      # smoke run, a few minutes per workload
    python benchmarks/run.py --only B3 --skip-full-log   # B3 on every 10th and 40th only
    python benchmarks/run.py --only B4 --n-jobs 2        # map quality only (the longest)

Every process runs one BLAS thread (set below, before numpy is imported). Prints one
markdown table per workload and writes JSON to ``benchmarks/results/``: ``b1_paper.json``,
``bench_mixture.json`` (B2, written by ``bench_mixture.py``), ``b3_intel.json``,
``bench_quality.json`` (B4, written by ``bench_quality.py``) and a summary ``run.json``
(``run_B1_B3.json`` and so on for a partial run); ``--quick`` writes them to
``benchmarks/results/quick/``.

- **B1**, the paper's simulation (``skoccmap.experiment.run_paper_experiment``): mixture of
  GP experts, BCM and our single ``EPGaussianProcessClassifier`` with ``IntegralKernel``,
  against scikit-learn's ``GaussianProcessClassifier`` (Laplace, RBF) on the beams cut into
  points every 0.2 m (all hits and a random subset of the free points, ``--gpc-points`` in
  all: it is cubic in them) and the counting grid ``OccupancyGridMap`` at 0.2 m. Fit s
  includes hyperparameter learning; predict s is the 0.2 m map (all cells); AUC is against
  the true map on the observed cells.
- **B2**, the mixture's fit and predict time from 1k to 64k, 300k and 3M observations and the
  log-log slopes of fit time: ``benchmarks/bench_mixture.py`` run as a subprocess.
- **B3**, the Intel Research Lab log (``../shared/data/intel.gfs.log``): every 10th scan held
  out (offset 5); the mixture and two counting grids at 0.1 m (the frequency grid, and the
  log-odds grid updated scan by scan as OctoMap does) trained on every 1st (unless
  ``--skip-full-log``), 10th and 40th remaining scan; AUC on held-out hits against points drawn
  along the held-out beams (as ``skoccmap.metrics.heldout_auc``); fit s, predict us/point
  on the test points, the time of the whole 0.1 m map over the training hits
  (``OccupancyGrid.from_estimator``, probability and variance), and the median time of
  ``predict_proba`` on 1 and on 100 test points drawn at random (a robot asking about a
  few places; five draws each).
  The single GP and scikit-learn's GPC are not run on B3: they are cubic in n, and every
  40th scan already gives ~7k observations (~30k points for the GPC).
- **B4**, map quality: ``benchmarks/bench_quality.py`` run as a subprocess (simulated worlds
  scored against their true maps at the ROS thresholds; Intel and ACES on the Hilbert-maps
  protocol; against the frequency grid, the per-scan log-odds grid and the Hilbert map).
  ``--skip-full-log`` passes ``--logs-every 10 40`` (no training on all scans).
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _tables import print_table  # noqa: E402
from sklearn.gaussian_process import GaussianProcessClassifier  # noqa: E402
from sklearn.gaussian_process.kernels import RBF  # noqa: E402
from sklearn.gaussian_process.kernels import ConstantKernel as C  # noqa: E402
from sklearn.metrics import roc_auc_score  # noqa: E402

from skoccmap import OccupancyGrid  # noqa: E402
from skoccmap.baselines import FrequencyGridMap, OccupancyGridMap  # noqa: E402
from skoccmap.experiment import points_along_beams, run_paper_experiment  # noqa: E402
from skoccmap.metrics import heldout_points, split_scans  # noqa: E402
from skoccmap.mixture import MixtureGPOccupancyMap  # noqa: E402
from skoccmap.observations import as_segments  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
INTEL = HERE.parents[1] / "shared" / "data" / "intel.gfs.log"
WORKLOADS = ("B1", "B2", "B3", "B4")


def timed(func, *args, **kwargs):
    start = time.perf_counter()
    with warnings.catch_warnings():
        # Convergence chatter of the optimisers would bury the tables; results are reported.
        warnings.simplefilter("ignore")
        out = func(*args, **kwargs)
    return out, time.perf_counter() - start


def fmt(value, spec):
    return "" if value is None else format(value, spec)


# ---------------------------------------------------------------------------------------
# B1: the paper's simulation
# ---------------------------------------------------------------------------------------


def gpc_on_points(data, truth_points, n_points, seed):
    """scikit-learn's Laplace GPC on beams cut into points every 0.2 m.

    All hits are kept and the free points are subsampled uniformly to ``n_points`` in all: a
    uniform subsample of all points keeps so few hits (2 %) that the GPC learns a flat map.
    """
    points, labels = points_along_beams(data.X, data.y, spacing=0.2)
    rng = np.random.default_rng(seed)
    hits, free = np.flatnonzero(labels == 1), np.flatnonzero(labels == 0)
    n_free = min(max(n_points - hits.size, 1), free.size)
    idx = np.r_[hits, rng.choice(free, n_free, replace=False)]
    gpc = GaussianProcessClassifier(C(1.0) * RBF(1.0), random_state=seed)
    _, fit_s = timed(gpc.fit, points[idx], labels[idx])
    proba, predict_s = timed(gpc.predict_proba, truth_points)
    return gpc, proba[:, 1], fit_s, predict_s, idx.size, points.shape[0]


def run_b1(args):
    quick = args.quick
    print("B1: the paper's simulation ...", flush=True)
    # Warm-up on a coarse grid: first-call imports are not part of the timings.
    run_paper_experiment(["moe"], resolution=1.0, single_hyperparameters="from_mixture")
    result = run_paper_experiment(
        ["moe", "bcm", "single"], random_state=0, n_jobs=args.n_jobs, verbose=1
    )
    truth = result.truth
    data = result.data
    cells = truth.points  # every cell of the 0.2 m map
    observed = truth.observed
    labels = truth.occupied[observed]
    rows = []
    for name, res in result.methods.items():
        rows.append(
            dict(
                method=res.label,
                n_train=int(data.X.shape[0]),
                fit_s=res.fit_s,
                predict_s=res.predict_s,
                auc=res.auc,
            )
        )
        if name != "single":
            rows[-1]["n_experts"] = int(res.model.n_experts_)

    grid = OccupancyGridMap(resolution=0.2)
    _, fit_s = timed(grid.fit, data.X, data.y)
    proba, predict_s = timed(grid.predict_proba, as_segments(cells))
    rows.append(
        dict(
            method="counting grid (0.2 m)",
            n_train=int(data.X.shape[0]),
            fit_s=fit_s,
            predict_s=predict_s,
            auc=float(roc_auc_score(labels, proba[observed, 1])),
        )
    )

    n_points = args.gpc_points or (500 if quick else 1000)
    print(f"B1: scikit-learn GPC (Laplace, RBF) on {n_points} points ...", flush=True)
    _, proba, fit_s, predict_s, n_used, n_all = gpc_on_points(data, cells, n_points, seed=0)
    rows.append(
        dict(
            method=f"sklearn GPC, points every 0.2 m ({n_used} of {n_all})",
            n_train=n_used,
            fit_s=fit_s,
            predict_s=predict_s,
            auc=float(roc_auc_score(labels, proba[observed])),
        )
    )
    moe = rows[0]
    total = moe["fit_s"] + moe["predict_s"]
    for row in rows:
        row["time_vs_mixture"] = (row["fit_s"] + row["predict_s"]) / total
        row["auc_minus_mixture"] = row["auc"] - moe["auc"]
    print_table(
        f"B1: paper simulation ({data.X.shape[0]} observations, 0.2 m map of "
        f"{cells.shape[0]} cells, AUC on {int(observed.sum())} observed cells)",
        ["method", "train rows", "fit s", "predict s", "AUC", "time / mixture", "AUC - mixture"],
        [
            (
                r["method"],
                r["n_train"],
                f"{r['fit_s']:.2f}",
                f"{r['predict_s']:.2f}",
                f"{r['auc']:.4f}",
                f"{r['time_vs_mixture']:.1f}",
                f"{r['auc_minus_mixture']:+.4f}",
            )
            for r in rows
        ],
    )
    return {"benchmark": "B1 paper simulation", "grid_resolution": 0.2, "rows": rows}


# ---------------------------------------------------------------------------------------
# B2: scaling of the mixture (bench_mixture.py)
# ---------------------------------------------------------------------------------------


def run_b2(args):
    print("\nB2: mixture scaling (benchmarks/bench_mixture.py) ...", flush=True)
    command = [
        sys.executable,
        str(HERE / "bench_mixture.py"),
        "--n-jobs",
        str(args.n_jobs),
        "--out",
        str(args.results),
    ]
    if args.quick:
        # The single-GP reference at 2k alone takes minutes: only at 1k in a smoke run.
        command += ["--quick", "--single-max", "1100"]
    elif args.b2_sizes:
        command += ["--sizes", *(str(n) for n in args.b2_sizes)]
    completed = subprocess.run(command, env=os.environ.copy(), check=False)
    path = args.results / "bench_mixture.json"
    if completed.returncode != 0 or not path.is_file():
        print(f"B2 failed (exit status {completed.returncode})", flush=True)
        return {"benchmark": "B2 mixture scaling", "error": completed.returncode}
    result = json.loads(path.read_text())
    print(
        f"\nB2: log-log slope of fit time from 2k observations: "
        f"{fmt(result.get('fit_slope'), '.2f')} (target <= 1.2)"
    )
    return result


# ---------------------------------------------------------------------------------------
# B3: Intel Research Lab
# ---------------------------------------------------------------------------------------


def score_heldout(model, points, labels):
    proba, predict_s = timed(model.predict_proba, as_segments(points))
    return float(roc_auc_score(labels, proba[:, 1])), predict_s


def query_cost(model, points):
    """Experts consulted per query, and one expert's cost per point, on the test points.

    One expert is the largest (most training rows) predicting every test point; the
    mixture's cost per query is then compared with it in the same run (issue 13's
    measure). Most test points lie beyond that expert's kernel cut-off, where its
    cross-covariances cost next to nothing, so its cost is also timed on the test points
    that consult it, the points a mixture asks it about (repeated to a batch of at least
    2048). Each time is the fewest seconds of three calls, as the mixture's own (a single
    call on this shared machine moved the ratio by a tenth).
    """
    Q = as_segments(points)
    query, expert, _ = model._consulted(Q)
    sizes = [e.X_train_.shape[0] if hasattr(e, "X_train_") else -1 for e in model.experts_]
    k = int(np.argmax(sizes))
    largest = model.experts_[k]
    expert_s = min(timed(largest.latent_mean_and_variance, Q)[1] for _ in range(3))
    near = Q[query[expert == k]]
    # Repeated to at least 2048 rows, so that a call's fixed costs do not count per point
    # (a hundred points may consult the expert); the fewest seconds of three calls.
    batch = near[np.arange(max(len(near), 2048)) % len(near)] if len(near) else near
    near_s = min(timed(largest.latent_mean_and_variance, batch)[1] for _ in range(3))
    return {
        "n_experts": int(model.n_experts_),
        "consulted_per_query": query.size / len(Q),
        "largest_expert_rows": int(sizes[k]),
        "expert_us_per_point": 1e6 * expert_s / len(Q),
        "expert_near_points": int(len(near)),
        "expert_near_us_per_point": 1e6 * near_s / max(len(batch), 1),
    }


def few_queries_ms(model, points, n, repeats=5, seed=0):
    """Median milliseconds of ``predict_proba`` on ``n`` held-out points drawn at random
    (a robot asking about a few places), over ``repeats`` draws."""
    rng = np.random.default_rng(seed)
    draws = [rng.choice(len(points), n, replace=False) for _ in range(repeats)]
    seconds = [timed(model.predict_proba, as_segments(points[d]))[1] for d in draws]
    return 1e3 * float(np.median(seconds))


def run_b3(args):
    from skoccmap.datasets import load_carmen

    log = Path(args.intel)
    if not log.is_file():
        print(f"\nB3 skipped: {log} not found", flush=True)
        return {"benchmark": "B3 Intel", "skipped": f"{log} not found"}
    print(f"\nB3: {log.name} ...", flush=True)
    scans = load_carmen(log)
    train_all, test = split_scans(scans, 10, offset=5)
    points, labels = heldout_points(test, random_state=0)
    sparsities = [40] if args.quick else [10, 40]
    if not (args.quick or args.skip_full_log):
        sparsities.insert(0, 1)
    rows = []
    for every in sparsities:
        train = train_all[::every]
        X, y, _, scan_index = train.to_observations(return_scan_index=True)
        models = {
            "mixture of GP experts": MixtureGPOccupancyMap(n_jobs=args.n_jobs, random_state=0),
            "frequency grid (0.1 m)": FrequencyGridMap(resolution=0.1),
            "log-odds grid per scan (0.1 m)": OccupancyGridMap(resolution=0.1),
        }
        for name, model in models.items():
            print(f"B3: every {every} scan(s), {len(X)} observations: {name} ...", flush=True)
            per_scan = {"scan_index": scan_index} if isinstance(model, OccupancyGridMap) else {}
            _, fit_s = timed(partial(model.fit, **per_scan), X, y)
            auc, predict_s = score_heldout(model, points, labels)
            # The fewest seconds of three calls, as the expert's in query_cost.
            queries = as_segments(points)
            predict_s = min(predict_s, *(timed(model.predict_proba, queries)[1] for _ in range(2)))
            # The whole map: every 0.1 m cell of the training hits' bounding box.
            grid, map_s = timed(
                OccupancyGrid.from_estimator, model, extent=X[y == 1, :2], resolution=0.1
            )
            row = dict(
                every_nth=every,
                n_scans=len(train),
                n_train=int(len(X)),
                method=name,
                fit_s=fit_s,
                predict_us_per_point=1e6 * predict_s / len(points),
                map_cells=int(grid.probability.size),
                map_s=map_s,
                auc=auc,
                one_point_ms=few_queries_ms(model, points, 1),
                hundred_points_ms=few_queries_ms(model, points, 100),
            )
            if hasattr(model, "n_experts_"):
                row.update(query_cost(model, points))
            rows.append(row)
            print(f"    fit {fit_s:.1f} s, map {map_s:.1f} s, AUC {auc:.4f}", flush=True)
    print_table(
        f"B3: Intel Research Lab, {len(test)} held-out scans ({len(points)} test points)",
        [
            "training scans",
            "observations",
            "method",
            "fit s",
            "0.1 m map s",
            "fit + map s",
            "predict us/point",
            "experts / query",
            "query / one expert",
            "query / one expert near its data",
            "1 / 100 points ms",
            "AUC",
        ],
        [
            (
                f"every {r['every_nth']} ({r['n_scans']})",
                r["n_train"],
                r["method"],
                f"{r['fit_s']:.1f}",
                f"{r['map_s']:.1f}",
                f"{r['fit_s'] + r['map_s']:.1f}",
                f"{r['predict_us_per_point']:.1f}",
                fmt(r.get("consulted_per_query"), ".1f"),
                fmt(
                    r["predict_us_per_point"] / r["expert_us_per_point"]
                    if "expert_us_per_point" in r
                    else None,
                    ".1f",
                ),
                fmt(
                    r["predict_us_per_point"] / r["expert_near_us_per_point"]
                    if r.get("expert_near_points")
                    else None,
                    ".1f",
                ),
                f"{r['one_point_ms']:.1f} / {r['hundred_points_ms']:.1f}",
                f"{r['auc']:.4f}",
            )
            for r in rows
        ],
    )
    return {
        "benchmark": "B3 Intel",
        "log": str(log),
        "heldout": "every 10th scan, offset 5",
        "n_test_points": int(len(points)),
        "rows": rows,
    }


# ---------------------------------------------------------------------------------------
# B4: map quality (bench_quality.py)
# ---------------------------------------------------------------------------------------


def run_b4(args):
    print("\nB4: map quality (benchmarks/bench_quality.py) ...", flush=True)
    command = [
        sys.executable,
        str(HERE / "bench_quality.py"),
        "--n-jobs",
        str(args.n_jobs),
        "--out",
        str(args.results),
    ]
    if args.quick:
        command.append("--quick")
    elif args.skip_full_log:
        command += ["--logs-every", "10", "40"]
    completed = subprocess.run(command, env=os.environ.copy(), check=False)
    path = args.results / "bench_quality.json"
    if completed.returncode != 0 or not path.is_file():
        print(f"B4 failed (exit status {completed.returncode})", flush=True)
        return {"benchmark": "B4 map quality", "error": completed.returncode}
    return json.loads(path.read_text())


# ---------------------------------------------------------------------------------------


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run (a few minutes)")
    parser.add_argument(
        "--only", default=",".join(WORKLOADS), help="comma-separated workloads (default all)"
    )
    parser.add_argument(
        "--skip-full-log",
        action="store_true",
        help="B3 and B4 without training on all training scans (saves ~3 min in B3)",
    )
    parser.add_argument("--n-jobs", type=int, default=1, help="parallel expert fits")
    parser.add_argument(
        "--gpc-points",
        type=int,
        default=None,
        help="training points of scikit-learn's GPC in B1 (default 1000; 500 with --quick)",
    )
    parser.add_argument(
        "--b2-sizes",
        type=int,
        nargs="+",
        default=None,
        help="B2 observation counts (default: bench_mixture.py's, 1000 to 64000, 300000 and "
        "3000000)",
    )
    parser.add_argument("--intel", default=str(INTEL), help="path of intel.gfs.log")
    args = parser.parse_args(argv)
    args.only = [w.strip().upper() for w in args.only.split(",") if w.strip()]
    unknown = sorted(set(args.only) - set(WORKLOADS))
    if unknown or not args.only:
        parser.error(f"--only takes workloads among {', '.join(WORKLOADS)}, got {args.only}")
    return args


def main(argv=None):
    args = parse_args(argv)
    # A smoke run keeps its JSON apart from the full run's.
    args.results = RESULTS / "quick" if args.quick else RESULTS
    args.results.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    summary = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": platform.platform(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "quick": args.quick,
        "blas_threads": 1,
        "workloads": {},
    }
    runners = {"B1": run_b1, "B2": run_b2, "B3": run_b3, "B4": run_b4}
    files = {"B1": "b1_paper.json", "B3": "b3_intel.json"}
    for workload in WORKLOADS:
        if workload not in args.only:
            continue
        result = runners[workload](args)
        summary["workloads"][workload] = result
        if workload in files:
            (args.results / files[workload]).write_text(json.dumps(result, indent=2))
    summary["total_s"] = time.perf_counter() - started
    # A partial run (--only) keeps the summary of the others.
    name = "run.json" if len(args.only) == len(WORKLOADS) else f"run_{'_'.join(args.only)}.json"
    (args.results / name).write_text(json.dumps(summary, indent=2))
    print(f"\nDone in {summary['total_s']:.0f} s; JSON in {args.results}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
