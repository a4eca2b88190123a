"""B5: online mapping -- replay the Intel log with ``partial_fit`` and compare with one ``fit``.

Run standalone: ``python benchmarks/bench_online.py [--max-scans N] [--n-jobs 2]``.
The training scans of B3's split (``split_scans(scans, 10, offset=5)``), every 2nd, are
replayed in time order in batches of 5 scans; the held-out points of the test scans
(``heldout_points(test, random_state=0)``) score the final online map and one ``fit`` on the
same scans. Prints a markdown table and writes ``benchmarks/results/b5_online.json``
(``b5_online_<N>.json`` with ``--max-scans``).

Targets: final AUC within 0.005 of the fit; the median update time over the last half of the
replay at most 5 % of the fit's time; the log-log slope of update time against scans seen at
most 0.2 (updates after the first, which is a fit, and other than those that re-learn the
shared hyperparameters and refit every expert: their few large times, early in the replay,
would pull the slope down); the same map for ``n_jobs`` 1 and 2
(``--check-n-jobs K`` replays the first K batches with both and compares the predictions).
With ``--n-jobs 1`` all work runs in this process, and the update and fit times are also
measured as its CPU time (``time.process_time``), which other jobs on a shared machine do
not inflate; the same targets are checked on them. ``--hyperparameter-growth`` sets the
online model's parameter (``none`` never re-learns).

``--office-steps`` instead replays the simulated office (``make_office_scans``, 60 poses x 90
beams, range noise 0.02 m, tuning seed 100) in batches of 6 scans with ``refit_fraction=0``
(every touched expert refitted), with the default 0.5 and with 1 and 2 (more rows added to
the experts before a refit), and prints ``skoccmap.metrics.map_quality`` on the cells seen so far
after every update: how far the added rows leave the map from the one that refits every
touched expert.
"""

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
from sklearn.exceptions import ConvergenceWarning  # noqa: E402
from sklearn.metrics import roc_auc_score  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _tables import print_table  # noqa: E402
from bench_quality import run_record  # noqa: E402

from skoccmap import MixtureGPOccupancyMap  # noqa: E402
from skoccmap.metrics import heldout_points, split_scans  # noqa: E402
from skoccmap.observations import as_segments  # noqa: E402

INTEL = HERE.parents[1] / "shared" / "data" / "intel.gfs.log"


def replay(train, batch, n_jobs, n_batches=None, log=True, growth=2.0, refit_fraction=None):
    """partial_fit batch by batch; the model and one record per batch.

    ``refit_fraction=None`` keeps the estimator's default."""
    model = MixtureGPOccupancyMap(n_jobs=n_jobs, random_state=0, hyperparameter_growth=growth)
    if refit_fraction is not None:
        model.set_params(refit_fraction=refit_fraction)
    records = []
    starts = list(range(0, len(train), batch))[:n_batches]
    for b, first in enumerate(starts, 1):
        X, y, _ = train[first : first + batch].to_observations()
        tic = time.perf_counter()
        learned = getattr(model, "_learned_rows", None)
        cpu = time.process_time()
        model.partial_fit(X, y, classes=[0, 1])
        cpu = time.process_time() - cpu
        seconds = time.perf_counter() - tic
        records.append(
            dict(
                batch=b,
                scans_seen=min(first + batch, len(train)),
                n_rows=int(len(X)),
                update_s=seconds,
                update_cpu_s=cpu,
                touched=int(model.touched_experts_.size),
                n_experts=int(model.n_experts_),
                n_clusters=int(model.n_clusters_),
                # hyperparameter_growth re-learned the shared kernel (all experts refitted).
                relearned=bool(b > 1 and model._learned_rows != learned),
            )
        )
        if log:
            r = records[-1]
            print(
                f"batch {b}/{len(starts)}: {r['scans_seen']} scans, {seconds:.2f} s "
                f"({cpu:.2f} s CPU), "
                f"{r['touched']} of {r['n_experts']} experts touched"
                + (", hyperparameters re-learned" if r["relearned"] else ""),
                flush=True,
            )
    return model, records


def slope(records, skip_relearned=False, key="update_s"):
    """Log-log slope of update time against scans seen, updates after the first."""
    later = [r for r in records[1:] if not (skip_relearned and r["relearned"])]
    if len(later) < 2:
        return float("nan")
    x = np.log([r["scans_seen"] for r in later])
    t = np.log([r[key] for r in later])
    return float(np.polyfit(x, t, 1)[0])


OFFICE_VARIANTS = {
    "refit every touched expert": dict(refit_fraction=0.0),
    "refit_fraction 0.5 (default)": {},
    "refit_fraction 1": dict(refit_fraction=1.0),
    "refit_fraction 2": dict(refit_fraction=2.0),
}


def office_steps():
    """map_quality after every update of the office replay, for each of OFFICE_VARIANTS."""
    from skoccmap.datasets import make_office_scans
    from skoccmap.metrics import map_quality

    data = make_office_scans(n_poses=60, n_beams=90, noise_std=0.02, random_state=100)
    rows = []
    for name, params in OFFICE_VARIANTS.items():
        model = MixtureGPOccupancyMap(n_jobs=1, random_state=100, **params)
        for first in range(0, len(data.scans), 6):
            X, y, _ = data.scans[first : first + 6].to_observations()
            model.partial_fit(X, y, classes=[0, 1])
            q = map_quality(model, data.environment, scans=data.scans[: first + 6])
            rows.append(
                (name, first + 6, f"{q['auc']:.4f}", f"{100 * q['phantom_rate']:.2f}",
                 f"{100 * q['free_found']:.1f}", f"{100 * q['walls_found']:.1f}",
                 f"{q['ece']:.3f}")
            )  # fmt: skip
    print_table(
        "Office replay (tuning seed 100), batches of 6: map quality after each update",
        ["variant", "scans", "AUC", "phantom %", "free found %", "walls found %", "ECE"],
        rows,
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--log", "--intel", dest="intel", default=str(INTEL),
        help="CARMEN log to replay (default: the Intel log)",
    )  # fmt: skip
    parser.add_argument("--every", type=int, default=2, help="every N-th training scan (2)")
    parser.add_argument("--batch", type=int, default=5, help="scans per update (5)")
    parser.add_argument("--max-scans", type=int, default=None, help="replay a prefix only")
    parser.add_argument("--n-jobs", type=int, default=2)
    parser.add_argument(
        "--check-n-jobs", type=int, default=0, metavar="K",
        help="replay the first K batches with n_jobs 1 and 2 and compare the maps",
    )  # fmt: skip
    parser.add_argument(
        "--hyperparameter-growth", default="2.0",
        help="the online model's hyperparameter_growth ('none': never re-learn)",
    )  # fmt: skip
    parser.add_argument(
        "--refit-fraction", type=float, default=None,
        help="the online model's refit_fraction (default: the estimator's)",
    )  # fmt: skip
    parser.add_argument("--out", default=None, help="JSON path")
    parser.add_argument(
        "--office-steps", action="store_true",
        help="replay the simulated office instead and score the map after every update",
    )  # fmt: skip
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore", ConvergenceWarning)
    if args.office_steps:
        office_steps()
        return

    from skoccmap.datasets import load_carmen

    scans = load_carmen(args.intel)
    train_all, test = split_scans(scans, 10, offset=5)
    train = train_all[:: args.every]
    if args.max_scans is not None:
        train = train[: args.max_scans]
    points, labels = heldout_points(test, random_state=0)
    queries = as_segments(points)
    print(f"B5: {len(train)} training scans, {len(points)} held-out points", flush=True)

    X, y, _ = train.to_observations()
    fitted = MixtureGPOccupancyMap(n_jobs=args.n_jobs, random_state=0)
    tic, cpu = time.perf_counter(), time.process_time()
    fitted.fit(X, y)
    fit_s, fit_cpu_s = time.perf_counter() - tic, time.process_time() - cpu
    fit_auc = float(roc_auc_score(labels, fitted.predict_proba(queries)[:, 1]))
    print(
        f"fit: {len(X)} observations, {fit_s:.1f} s ({fit_cpu_s:.1f} s CPU), AUC "
        f"{fit_auc:.4f}, {fitted.shared_kernel_}",
        flush=True,
    )

    tic = time.perf_counter()
    growth = args.hyperparameter_growth
    growth = None if growth.lower() == "none" else float(growth)
    model, records = replay(
        train, args.batch, args.n_jobs, growth=growth, refit_fraction=args.refit_fraction
    )
    replay_s = time.perf_counter() - tic
    online_auc = float(roc_auc_score(labels, model.predict_proba(queries)[:, 1]))
    last_half = records[len(records) // 2 :]
    median_s = float(np.median([r["update_s"] for r in last_half]))
    median_cpu = float(np.median([r["update_cpu_s"] for r in last_half]))
    suffix = "" if args.max_scans is None else f"_{args.max_scans}"
    out = Path(args.out) if args.out else HERE / "results" / f"b5_online{suffix}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    result, save = run_record(
        "B5 online",
        args,
        out,
        n_scans=len(train),
        n_observations=int(len(X)),
        n_batches=len(records),
        hyperparameter_growth=growth,
        refit_fraction=model.refit_fraction,
        fit_s=fit_s,
        fit_cpu_s=fit_cpu_s,
        fit_kernel=repr(fitted.shared_kernel_),
        online_kernel=repr(model.shared_kernel_),
        fit_auc=fit_auc,
        fit_experts=int(fitted.n_experts_),
        online_auc=online_auc,
        online_experts=int(model.n_experts_),
        replay_s=replay_s,
        median_update_last_half_s=median_s,
        median_update_share_of_fit=median_s / fit_s,
        median_update_cpu_last_half_s=median_cpu,
        median_update_cpu_share_of_fit=median_cpu / fit_cpu_s,
        median_touched_last_half=float(np.median([r["touched"] for r in last_half])),
        slope=slope(records),
        slope_cpu=slope(records, key="update_cpu_s"),
        slope_cpu_without_relearning=slope(records, True, key="update_cpu_s"),
        slope_without_relearning=slope(records, skip_relearned=True),
        relearned_at_scans=[r["scans_seen"] for r in records if r["relearned"]],
        records=records,
    )
    if args.check_n_jobs:
        maps = []
        for n_jobs in (1, 2):
            m, _ = replay(
                train, args.batch, n_jobs, args.check_n_jobs, False, growth, args.refit_fraction
            )
            maps.append(m.predict_proba(queries))
        result["n_jobs_check_batches"] = args.check_n_jobs
        result["n_jobs_same_map"] = bool(np.array_equal(maps[0], maps[1]))

    print_table(
        f"B5: {Path(args.intel).name}, every {args.every}nd training scan ({len(train)} "
        f"scans) in batches of {args.batch}",
        ["", "AUC", "time s", "experts"],
        [
            ("one fit", f"{fit_auc:.4f}", f"{fit_s:.1f}", result["fit_experts"]),
            (
                f"online, {len(records)} updates",
                f"{online_auc:.4f}",
                f"{replay_s:.1f} in all",
                result["online_experts"],
            ),
        ],
    )
    checks = [
        ("|AUC online - AUC fit| <= 0.005", f"{abs(online_auc - fit_auc):.4f}",
         abs(online_auc - fit_auc) <= 0.005),
        ("median update (last half) <= 5 % of fit", f"{median_s:.2f} s = "
         f"{100 * median_s / fit_s:.1f} %", median_s <= 0.05 * fit_s),
        ("log-log slope of update time <= 0.2 (without re-learning updates)",
         f"{result['slope_without_relearning']:.2f} ({result['slope']:.2f} with the "
         f"{len(result['relearned_at_scans'])} re-learning updates)",
         result["slope_without_relearning"] <= 0.2),
    ]  # fmt: skip
    if args.n_jobs == 1:
        # One process does all the work: its CPU time does not count other jobs' load.
        checks += [
            ("median update CPU (last half) <= 5 % of fit CPU", f"{median_cpu:.2f} s = "
             f"{100 * median_cpu / fit_cpu_s:.1f} %", median_cpu <= 0.05 * fit_cpu_s),
            ("log-log slope of update CPU time <= 0.2 (without re-learning updates)",
             f"{result['slope_cpu_without_relearning']:.2f} ({result['slope_cpu']:.2f} with "
             "them)", result["slope_cpu_without_relearning"] <= 0.2),
        ]  # fmt: skip
    if args.check_n_jobs:
        checks.append(
            (f"same map n_jobs 1 / 2 ({args.check_n_jobs} batches)",
             str(result["n_jobs_same_map"]), result["n_jobs_same_map"])
        )  # fmt: skip
    print_table("B5 targets", ["target", "measured", "met"], checks)
    result["targets"] = {name: bool(ok) for name, _, ok in checks}
    save()
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
