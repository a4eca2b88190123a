"""Tuning: the baselines' parameters (HilbertMap, OccupancyGridMap) behind their docstrings.

Run standalone::

    python benchmarks/bench_tuning_baselines.py                  # both groups (see README)
    python benchmarks/bench_tuning_baselines.py --only hilbert   # HilbertMap sweeps only
    python benchmarks/bench_tuning_baselines.py --only grid      # OccupancyGridMap only

Prints one markdown table per sweep and writes ``benchmarks/results/bench_tuning_baselines.json``
(``bench_tuning_baselines_<groups>[_<sweeps>].json`` with ``--only`` / ``--sweeps``). The
numbers quoted in the docstrings of :class:`skoccmap.baselines.HilbertMap` and
:class:`skoccmap.baselines.OccupancyGridMap` come from this script. The data are those of
``bench_tuning.py`` (its ``load_aces`` and ``load_sim``), scored by its ``score``.

Groups:

- ``hilbert``: :class:`~skoccmap.baselines.HilbertMap`'s parameters swept one at a time
  around its defaults (plus ``gamma`` at 2000 components, and the defaults at five
  estimator seeds: the spread that a difference between two rows must exceed), on the
  **tuning data**: ACES on the Hilbert-maps protocol (seed 100, trained on every 10th
  remaining scan; held-out ROC AUC) and the sparse office floor (30 poses x 45 beams, range
  noise of seed 100; walls found, phantom rate, free found, ECE and wall thickness of
  ``map_quality``). Every row
  gives the fit seconds, the SGD epochs (``n_iter_``) and the training points. A first table
  gives facts of the ACES training rows: the share of free rows longer than the default
  ``max_free_length`` and the share of the free points they would hold.
- ``grid``: :class:`~skoccmap.baselines.OccupancyGridMap` at 0.1 m, updated per scan
  (``fit(X, y, scan_index=...)``) against evidence summed over all rows (``fit(X, y)``), on
  the Hilbert-maps protocol trained on every 1st and every 10th remaining scan: held-out AUC
  and the share of observed cells whose log-odds sit at a clamping bound. On ACES (tuning
  log, seed 100) and on Intel (**report log**, report seed 0): the Intel rows are a
  measurement to report, not data to choose anything on; the grid's parameters are
  OctoMap's and none was chosen here.

The estimators' ``random_state`` is the data seed, as in ``bench_quality``. Fit times are
informative only: the machine is shared and its seconds drift by tens of percent.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import warnings  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _tables import print_table  # noqa: E402
from bench_quality import (  # noqa: E402
    LOG_GRID_RESOLUTION,
    LOGS,
    REPORT_SEEDS,
    Method,
    fit_model,
    fmt,
    guarded,
    run_record,
)
from bench_tuning import ACES_EVERY, SEED, load_aces, load_sim, score  # noqa: E402
from sklearn.metrics import roc_auc_score  # noqa: E402

from skoccmap.baselines import HilbertMap, OccupancyGridMap, _free_points_per_row  # noqa: E402
from skoccmap.datasets import load_carmen  # noqa: E402
from skoccmap.metrics import blocks_protocol  # noqa: E402
from skoccmap.observations import as_segments  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
GROUPS = ("hilbert", "grid")

# ---------------------------------------------------------------------------------------
# HilbertMap
# ---------------------------------------------------------------------------------------

HILBERT_DATASETS = ("aces", "office")


@dataclass
class Sweep:
    name: str
    title: str
    entries: list  # (label, constructor parameters, is the default)


def _sweep(parameter, values, default, title=None, **fixed):
    entries = [
        (label, dict(fixed, **({} if value == default else {parameter: value})), value == default)
        for label, value in values
    ]
    return Sweep(parameter, title or f"`{parameter}`", entries)


HILBERT_SWEEPS = [
    _sweep("gamma", [("5", 5.0), ("2", 2.0), ("1", 1.0), ("0.5", 0.5)], 1.0),
    _sweep("n_components", [("500", 500), ("1000", 1000), ("2000", 2000)], 1000),
    Sweep(
        "gamma_2000",
        "`gamma` at `n_components=2000`",
        [
            ("2", {"gamma": 2.0, "n_components": 2000}, False),
            ("1", {"n_components": 2000}, False),
            ("0.5", {"gamma": 0.5, "n_components": 2000}, False),
        ],
    ),
    _sweep("alpha", [("1e-4", 1e-4), ("1e-5", 1e-5), ("1e-6", 1e-6), ("1e-7", 1e-7)], 1e-6),
    _sweep(
        "penalty",
        [("l2", "l2"), ("l1", "l1"), ("elasticnet", "elasticnet"), ("None", None)],
        "l2",
    ),
    _sweep("free_spacing", [("0.5", 0.5), ("1", 1.0), ("2", 2.0)], 0.5),
    _sweep("max_free_length", [("40", 40.0), ("None", None)], 40.0),
    _sweep(
        "max_samples",
        [("25 000", 25_000), ("50 000", 50_000), ("100 000", 100_000), ("None", None)],
        50_000,
    ),
    _sweep("class_weight", [("None", None), ("balanced", "balanced")], None),
    # The spread of one configuration over the estimator's seeds (the data stay at SEED):
    # differences between rows of the sweeps above that are smaller are not resolved.
    Sweep(
        "random_state",
        f"`random_state` (the estimator's seed; data seed {SEED})",
        [
            (str(s), {} if s == SEED else {"random_state": s}, s == SEED)
            for s in range(SEED, SEED + 5)
        ],
    ),
]


def _key(params):
    return json.dumps(params, sort_keys=True)


def long_free_rows(X, y, max_free_length, spacing):
    """Share of free rows longer than ``max_free_length`` and of the free points they hold."""
    hit = y == np.max(y)
    d = X.shape[1] // 2
    length = np.linalg.norm(X[~hit, d:] - X[~hit, :d], axis=1)
    counts = _free_points_per_row(length, spacing)
    long = length > max_free_length
    return dict(
        n_free_rows=int(length.size),
        long_row_share=float(long.mean()),
        long_row_mean_length=float(length[long].mean()) if long.any() else None,
        long_point_share=float(counts[long].sum() / counts.sum()),
        n_free_points_all=int(counts.sum()),
        n_free_points_kept=int(counts[~long].sum()),
        n_hits=int(hit.sum()),
    )


def run_hilbert(args, result, save):
    out = result.setdefault("hilbert", {"datasets": {}, "rows": []})
    datasets = {}
    for name in HILBERT_DATASETS:
        data = load_aces(SEED) if name == "aces" else load_sim(name, SEED)
        if data is None:
            print(f"Hilbert: {LOGS['aces'][0]} not found, ACES skipped", flush=True)
            out["datasets"][name] = {"skipped": "not found"}
            continue
        datasets[name] = data
        out["datasets"][name] = data.info
    defaults = HilbertMap().get_params()
    if "aces" in datasets:
        data = datasets["aces"]
        facts = long_free_rows(
            data.X, data.y, defaults["max_free_length"], defaults["free_spacing"]
        )
        out["aces_free_rows"] = facts
        print_table(
            f"Hilbert: ACES training rows (every {ACES_EVERY}th scan, seed {SEED})",
            [
                "hits",
                "free rows",
                f"free rows > {defaults['max_free_length']:g} m",
                "their mean length m",
                f"free points at {defaults['free_spacing']:g} m",
                "share held by the long rows",
            ],
            [
                [
                    facts["n_hits"],
                    facts["n_free_rows"],
                    f"{100 * facts['long_row_share']:.1f} %",
                    fmt(facts["long_row_mean_length"], ".1f"),
                    facts["n_free_points_all"],
                    f"{100 * facts['long_point_share']:.1f} %",
                ]
            ],
        )
    fits = {}
    for sweep in HILBERT_SWEEPS:
        if args.sweeps and sweep.name not in args.sweeps:
            continue
        for _, params, _ in sweep.entries:
            fits.setdefault(_key(params), params)
    rows = out["rows"]
    for key, params in fits.items():
        for name, data in datasets.items():
            what = ", ".join(f"{k}={v}" for k, v in params.items()) or "defaults"
            print(f"Hilbert: {name}, {what} ...", flush=True)
            method = Method(
                "hilbert",
                "hilbert",
                what,
                lambda s, j, params=params: HilbertMap(**{"random_state": s, **params}),
            )

            def work(row, method=method, data=data):
                model, fit_s, caught = fit_model(method, SEED, 1, data.X, data.y, None)
                row.update(
                    fit_s=fit_s,
                    n_iter=int(model.n_iter_),
                    n_training_points=int(model.n_training_points_),
                    n_components=int(model.nystroem_.n_components),
                )
                if caught:
                    row["warnings"] = caught
                score(model, data, row)
                text = f"    fit {fit_s:.1f} s, {row['n_iter']} epochs"
                if "auc" in row and "walls_found" not in row:
                    text += f", AUC {row['auc']:.4f}"
                else:
                    text += (
                        f", walls {100 * row['walls_found']:.1f} %, phantom "
                        f"{100 * row['phantom_rate']:.2f} %, ECE {row['ece']:.3f}, "
                        f"thickness {fmt(row.get('wall_thickness'), '.2f')} m"
                    )
                print(text, flush=True)

            row = guarded(dict(dataset=name, key=key, params=params), work)
            rows.append(row)
            save()
    out["tables"] = hilbert_tables(args, rows, list(datasets))


def hilbert_tables(args, rows, names):
    columns = {
        "aces": [
            ("ACES AUC", "auc", ".4f", 1),
            ("ACES epochs", "n_iter", "d", 1),
            ("ACES points", "n_training_points", "d", 1),
        ],
        "office": [
            ("office walls %", "walls_found", ".1f", 100),
            ("office phantom %", "phantom_rate", ".2f", 100),
            ("office free %", "free_found", ".1f", 100),
            ("office ECE", "ece", ".3f", 1),
            ("office thickness m", "wall_thickness", ".2f", 1),
            ("office epochs", "n_iter", "d", 1),
        ],
    }
    out = {}
    for sweep in HILBERT_SWEEPS:
        if args.sweeps and sweep.name not in args.sweeps:
            continue
        header = [sweep.name]
        for name in names:
            header += [c[0] for c in columns[name]]
        header.append("fit s (" + " / ".join(names) + ")")
        table, records = [], []
        for label, params, default in sweep.entries:
            cells = [label + (" (default)" if default else "")]
            fit_s = []
            record = dict(value=label, default=default, params=params)
            for name in names:
                row = next(
                    (r for r in rows if r["dataset"] == name and r["key"] == _key(params)), {}
                )
                record[name] = {k: v for k, v in row.items() if k not in ("dataset", "key")}
                if "error" in row:
                    cells += ["error: " + row["error"][:60].replace("|", "/")]
                    cells += [""] * (len(columns[name]) - 1)
                else:
                    for _, field, spec, scale in columns[name]:
                        value = row.get(field)
                        cells.append(fmt(None if value is None else scale * value, spec))
                fit_s.append(fmt(row.get("fit_s"), ".1f") or "-")
            cells.append(" / ".join(fit_s))
            table.append(cells)
            records.append(record)
        out[sweep.name] = records
        print_table(
            f"Hilbert: {sweep.title}; tuning data, seed {SEED}, all else default",
            header,
            table,
        )
    return out


# ---------------------------------------------------------------------------------------
# OccupancyGridMap
# ---------------------------------------------------------------------------------------

# log -> (seed, role): ACES is the tuning log, Intel the report log (report seed 0).
GRID_LOGS = {"aces": (SEED, "tuning"), "intel": (REPORT_SEEDS[0], "report")}
GRID_EVERY = (1, 10)
GRID_UPDATES = ("per scan", "summed")


def at_bounds(model):
    """Share of the observed cells whose log-odds sit at ``l_min`` or ``l_max``."""
    lo = model.log_odds_
    return float(np.mean((lo <= model.l_min) | (lo >= model.l_max)))


def run_grid(args, result, save):
    out = result.setdefault("grid", {"protocol": {}, "rows": []})
    rows = out["rows"]
    r = LOG_GRID_RESOLUTION
    methods = {
        "per scan": Method(
            "per_scan", "octomap", "per scan", lambda s, j: OccupancyGridMap(r), per_scan=True
        ),
        "summed": Method("summed", "octomap", "summed", lambda s, j: OccupancyGridMap(r)),
    }
    for name in args.grid_logs:
        seed, role = GRID_LOGS[name]
        path = LOGS[name][0]
        if not path.is_file():
            print(f"Grid: {path} not found, {name} skipped", flush=True)
            out["protocol"][name] = {"skipped": f"{path} not found"}
            continue
        scans = load_carmen(path)
        out["protocol"][name] = dict(log=str(path), role=role, seed=seed, n_scans=len(scans))
        for every in GRID_EVERY:
            bunch = blocks_protocol(scans, train_every=every, random_state=seed)
            X, y, _, scan_index = bunch.train.to_observations(return_scan_index=True)
            Q = as_segments(bunch.points)
            for update, method in methods.items():
                print(
                    f"Grid: {name} ({role} log, seed {seed}), every {every} "
                    f"({len(bunch.train)} scans, {len(X)} observations, {len(Q)} test "
                    f"points), {update} ...",
                    flush=True,
                )
                row = dict(
                    log=name,
                    role=role,
                    seed=seed,
                    every=every,
                    update=update,
                    n_scans=len(bunch.train),
                    n_train=int(len(X)),
                    n_test=int(len(Q)),
                )

                def work(row, method=method, X=X, y=y, si=scan_index, Q=Q, bunch=bunch, s=seed):
                    model, fit_s, caught = fit_model(method, s, 1, X, y, si)
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        proba = model.predict_proba(Q)[:, 1]
                    row.update(
                        fit_s=fit_s,
                        auc=float(roc_auc_score(bunch.labels, proba)),
                        at_bounds=at_bounds(model),
                        n_cells=int(model.log_odds_.size),
                    )
                    if caught:
                        row["warnings"] = caught
                    print(
                        f"    AUC {row['auc']:.4f}, {100 * row['at_bounds']:.1f} % of "
                        f"{row['n_cells']} cells at a bound, fit {fit_s:.1f} s",
                        flush=True,
                    )

                rows.append(guarded(row, work))
                save()
        table = []
        for every in GRID_EVERY:
            for update in GRID_UPDATES:
                row = next(
                    (
                        x
                        for x in rows
                        if x["log"] == name and x["every"] == every and x["update"] == update
                    ),
                    {},
                )
                table.append(
                    [
                        f"every {every} ({row.get('n_scans', '')})",
                        update,
                        row.get("error", "")[:60] or fmt(row.get("auc"), ".4f"),
                        fmt(None if "at_bounds" not in row else 100 * row["at_bounds"], ".1f"),
                        fmt(row.get("n_cells"), "d"),
                        fmt(row.get("fit_s"), ".2f"),
                    ]
                )
        print_table(
            f"Grid: `OccupancyGridMap` ({r} m), per-scan vs summed; {LOGS[name][2]} "
            f"({role} log), Hilbert-maps protocol, seed {seed}",
            ["training scans", "update", "AUC", "cells at a bound %", "observed cells", "fit s"],
            table,
        )


# ---------------------------------------------------------------------------------------


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", choices=GROUPS, default=None, help="groups to run")
    parser.add_argument(
        "--sweeps",
        nargs="+",
        choices=[s.name for s in HILBERT_SWEEPS],
        default=None,
        help="HilbertMap sweeps to run (default all)",
    )
    parser.add_argument(
        "--grid-logs",
        nargs="+",
        choices=tuple(GRID_LOGS),
        default=list(GRID_LOGS),
        help="logs of the grid group (default ACES and Intel)",
    )
    parser.add_argument("--out", default=None, help="folder of the JSON (default results)")
    args = parser.parse_args(argv)
    args.out = Path(args.out) if args.out else RESULTS
    return args


def main(argv=None):
    args = parse_args(argv)
    groups = args.only or list(GROUPS)
    args.out.mkdir(parents=True, exist_ok=True)
    name = "bench_tuning_baselines"
    if args.only:
        name += "_" + "_".join(args.only)
    if args.sweeps:
        name += "_" + "_".join(args.sweeps)
    path = args.out / f"{name}.json"
    result, save = run_record(
        "tuning sweeps of the baselines (HilbertMap, OccupancyGridMap)",
        args,
        path,
        seed=SEED,
        note="fit times are informative only (shared machine)",
    )

    if "hilbert" in groups:
        run_hilbert(args, result, save)
    if "grid" in groups:
        run_grid(args, result, save)
    save()
    print(
        f"\nBaseline tuning done in {result['total_s']:.0f} s ({os.cpu_count()} cores, one "
        f"BLAS thread; fit times informative only); JSON in {path}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
