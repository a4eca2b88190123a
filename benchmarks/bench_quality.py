"""B4: map quality -- simulated worlds against their true maps, real logs on a published protocol.

Run standalone::

    python benchmarks/bench_quality.py --n-jobs 2             # full run (long: see README)
    python benchmarks/bench_quality.py --quick --n-jobs 2     # smoke run, a few minutes
    python benchmarks/bench_quality.py --only logs --logs-every 10 40   # logs without all scans
    python benchmarks/bench_quality.py --tuning               # the tuning seeds (100, 101)

or through ``python benchmarks/run.py --only B4``. Prints markdown tables and writes
``benchmarks/results/bench_quality.json`` (``results/quick/`` with ``--quick``;
``bench_quality_sim.json`` / ``bench_quality_logs.json`` for ``--only``, ``_tuning`` added
with the tuning seeds).

1. **Simulated worlds** with a true map, scored by ``skoccmap.metrics.map_quality`` on the
   0.1 m cells the scans observed: the paper's world (17 beams x 26 poses, and a dense
   45 x 52), the office floor (30 poses x 45 beams, and a dense 120 x 180) and the 3-D room
   (12 x 4 and 72 x 24 beams per pose). Range noise ``NOISE_STD`` seeded by the data seed.
   Methods: the mixture with its defaults; the mixture with every hit kept
   (``min_hit_frequency=None``, all else default); the mixture with whole beams
   as in the paper
   (``max_beam_length=None``, ``beam_end_length=None``, ``hyperparameter_beam_length=None``,
   all else default); the frequency
   grid and the clamped log-odds grid updated per scan (OctoMap), each at 0.1 m and 0.2 m
   (both reported, chosen before any result); the Hilbert map.
2. **Real logs**, Intel (report log) and ACES (tuning log), on the Hilbert-maps protocol
   (``skoccmap.metrics.blocks_protocol``): trained on every 1st / 10th / 40th remaining scan;
   AUC (``sklearn.metrics.roc_auc_score``) on the held-out points, fit s, predict us/point.
   Methods: the mixture with its defaults and with every hit kept, the frequency grid
   (0.1 m) and the per-scan
   log-odds grid (0.1 m), each with every beam and with free beams up to the protocol's
   40 m, the Hilbert map.
3. **Summary**: per log and sparsity, whether the mixture's mean AUC reaches the best
   baseline's; per simulated setting, the targets (``TARGETS``) met or missed.
4. **Length-scale stability**: the mixture's learned length scale on Intel with all vs every
   10th training scan, and with ``max_beam_length`` 1.0 vs 2.0 on every 10th scan (``--quick``:
   10th vs 40th, and the beam bounds on every 40th); the same density comparison with
   ``hyperparameter_window=STABILITY_WINDOW``; the held-out AUC of each fit; target:
   relative change < 30 %, for each report seed (the data seed and the estimator's
   ``random_state``: the draw of pieces the length scale is learned on moves it by tens of
   percent). ``--only stability`` runs this report alone.

Seeds: ``REPORT_SEEDS`` (0, 1, 2) are the numbers to report; ``TUNING_SEEDS`` (100, 101),
with ``--tuning``, are the ones to choose defaults on, so that reported numbers are not
the ones the defaults were picked on. On the logs, ACES is the log to tune on and Intel the
log to report. A seed is the data seed (range noise, held-out blocks and test points) and
the estimators' ``random_state``.

A method that fails is reported with its error (in the table and the JSON); the run goes on.
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
import traceback  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _tables import print_table  # noqa: E402
from sklearn.metrics import roc_auc_score  # noqa: E402

from skoccmap.baselines import FrequencyGridMap, HilbertMap, OccupancyGridMap  # noqa: E402
from skoccmap.datasets import (  # noqa: E402
    load_carmen,
    make_office_scans,
    make_paper_scans,
    make_room3d_scans,
)
from skoccmap.metrics import HILBERT_MAX_BEAM_RANGE, blocks_protocol, map_quality  # noqa: E402
from skoccmap.mixture import MixtureGPOccupancyMap  # noqa: E402
from skoccmap.observations import HIT, as_segments  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
DATA = HERE.parents[1] / "shared" / "data"
LOGS = {
    # name: (file, role, title)
    "intel": (DATA / "intel.gfs.log", "report", "Intel Research Lab"),
    "aces": (DATA / "aces-corrected.log.gz", "tuning", "ACES3, UT Austin"),
}

REPORT_SEEDS = (0, 1, 2)
TUNING_SEEDS = (100, 101)
NOISE_STD = 0.02  # range noise of the simulated scans, metres
RESOLUTION = 0.1  # cells scored in the simulated worlds, metres
GRID_RESOLUTIONS = (0.1, 0.2)  # the grid baselines on simulated worlds, both reported
LOG_GRID_RESOLUTION = 0.1  # the protocol's grid
LOGS_EVERY = (1, 10, 40)
STABILITY_BEAM_LENGTHS = (1.0, 2.0)
# The shared kernel learned on windows of this radius (metres) instead of the experts' own
# data: the stable setting of bench_tuning.py's hyperparameter_window sweep on ACES.
STABILITY_WINDOW = 3.0
STABILITY_TARGET = 0.30

# Targets of a simulated map (the mixture with its defaults); "max" means at most.
TARGETS = {
    "phantom_rate": ("max", 0.01, "phantom <= 1 %"),
    "free_found": ("min", 0.95, "free found >= 95 %"),
    "walls_found": ("min", 0.95, "walls found >= 95 %"),
    "ece": ("max", 0.05, "ECE <= 0.05"),
    "wall_thickness": ("max", 0.3, "thickness <= 0.3 m"),
}
# How the summary prints each target's value: (scale, format).
TARGET_FORMATS = {
    "phantom_rate": (100, ".2f"),
    "free_found": (100, ".1f"),
    "walls_found": (100, ".1f"),
    "ece": (1, ".3f"),
    "wall_thickness": (1, ".2f"),
}

# Simulated settings: (world, sparsity, generator, its keyword arguments, description).
SIM_SETTINGS = [
    ("paper", "sparse", make_paper_scans, {}, "17 beams x 26 poses"),
    (
        "paper",
        "dense",
        make_paper_scans,
        dict(n_beams=45, n_poses_per_piece=26),
        "45 beams x 52 poses",
    ),
    ("office", "sparse", make_office_scans, dict(n_poses=30, n_beams=45), "30 poses x 45 beams"),
    (
        "office",
        "dense",
        make_office_scans,
        dict(n_poses=120, n_beams=180),
        "120 poses x 180 beams",
    ),
    (
        "room3d",
        "sparse",
        make_room3d_scans,
        dict(n_azimuths=12, n_elevations=4),
        "4 poses x 12 x 4 beams",
    ),
    (
        "room3d",
        "dense",
        make_room3d_scans,
        dict(n_azimuths=72, n_elevations=24),
        "4 poses x 72 x 24 beams",
    ),
]
WORLD_TITLES = {"paper": "the paper's world", "office": "office floor", "room3d": "3-D room"}


# ---------------------------------------------------------------------------------------
# Methods
# ---------------------------------------------------------------------------------------


@dataclass
class Method:
    key: str  # unique name in the JSON
    family: str  # what --methods selects
    label: str  # name in the tables
    make: Callable  # (seed, n_jobs) -> unfitted estimator
    per_scan: bool = False  # fit(X, y, scan_index=...)


# The paper's beams: every beam one observation (the shared kernel learned on them too),
# all else default, so that the two mixture rows compare beam pieces against whole beams.
WHOLE_BEAMS = {
    "max_beam_length": None,
    "beam_end_length": None,
    "hyperparameter_beam_length": None,
}


def _hilbert(seed, n_jobs):
    return HilbertMap(random_state=seed)


MIXTURE = Method(
    "mixture",
    "mixture",
    "mixture of GP experts (defaults)",
    lambda s, j: MixtureGPOccupancyMap(random_state=s, n_jobs=j),
)
WHOLE_BEAM_MIXTURE = Method(
    "mixture_whole_beams",
    "whole-beams",
    "mixture, whole beams",
    lambda s, j: MixtureGPOccupancyMap(random_state=s, n_jobs=j, **WHOLE_BEAMS),
)
# Every hit kept, even where the free beams contradict it (min_hit_frequency=None; the
# defaults leave such hits out), all else default.
EVERY_HIT_MIXTURE = Method(
    "mixture_every_hit",
    "every-hit",
    "mixture, every hit kept",
    lambda s, j: MixtureGPOccupancyMap(random_state=s, n_jobs=j, min_hit_frequency=None),
)
HILBERT = Method("hilbert", "hilbert", "Hilbert map", _hilbert)


def _grid_names(r, max_free):
    """Key suffix and table label of a grid of cell ``r`` using free beams up to ``max_free``."""
    if max_free is None:
        return f"{r}", f"{r} m"
    return f"{r}_{max_free:g}m", f"{r} m, beams <= {max_free:g} m"


def _frequency(r, max_free=None):
    key, label = _grid_names(r, max_free)
    return Method(
        f"frequency_{key}",
        "frequency",
        f"frequency grid ({label})",
        lambda s, j: FrequencyGridMap(resolution=r, max_free_length=max_free),
    )


def _octomap(r, max_free=None):
    key, label = _grid_names(r, max_free)
    return Method(
        f"octomap_{key}",
        "octomap",
        f"log-odds grid per scan ({label})",
        lambda s, j: OccupancyGridMap(resolution=r, max_free_length=max_free),
        per_scan=True,
    )


def sim_methods(families):
    methods = [MIXTURE, EVERY_HIT_MIXTURE, WHOLE_BEAM_MIXTURE]
    methods += [_frequency(r) for r in GRID_RESOLUTIONS]
    methods += [_octomap(r) for r in GRID_RESOLUTIONS]
    methods.append(HILBERT)
    return [m for m in methods if m.family in families]


def log_methods(families):
    # The grids with every beam and with the protocol's 40 m bound on free beams (the
    # Hilbert map's default), both fixed before any result.
    r, bound = LOG_GRID_RESOLUTION, HILBERT_MAX_BEAM_RANGE
    methods = [
        MIXTURE,
        EVERY_HIT_MIXTURE,
        _frequency(r),
        _frequency(r, bound),
        _octomap(r),
        _octomap(r, bound),
        HILBERT,
    ]
    return [m for m in methods if m.family in families]


FAMILIES = ("mixture", "every-hit", "whole-beams", "frequency", "octomap", "hilbert")


def learned_length_scale(model):
    """Length scale of the mixture's shared kernel (geometric mean if anisotropic), or None."""
    kernel = getattr(model, "shared_kernel_", None)
    if kernel is None:
        return None
    values = [v for k, v in kernel.get_params().items() if k.endswith("length_scale")]
    if not values:
        return None
    value = np.asarray(values[0], dtype=np.float64)
    return float(np.exp(np.mean(np.log(value))))


def fit_model(method, seed, n_jobs, X, y, scan_index):
    """Fit one method; returns the model, fit seconds and the distinct warnings raised."""
    model = method.make(seed, n_jobs)
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        # Optimiser chatter would bury the tables; the warnings are kept in the JSON.
        warnings.simplefilter("always")
        if method.per_scan:
            model.fit(X, y, scan_index=scan_index)
        else:
            model.fit(X, y)
    fit_s = time.perf_counter() - start
    seen = []
    for w in caught:
        text = f"{w.category.__name__}: {str(w.message)[:160]}"
        if text not in seen:
            seen.append(text)
    return model, fit_s, seen[:5]


def model_facts(model):
    facts = {}
    length_scale = learned_length_scale(model)
    if length_scale is not None:
        facts["length_scale"] = length_scale
    if hasattr(model, "n_experts_"):
        facts["n_experts"] = int(model.n_experts_)
    if hasattr(model, "transient_hits_"):
        kinds = getattr(model, "observation_kind_", None)
        n_hits = int(np.sum(kinds == HIT)) if kinds is not None else 0
        facts["transient_hits"] = float(model.transient_hits_.sum() / max(n_hits, 1))
    return facts


def guarded(row, func):
    """Run ``func(row)``; on failure record the error in ``row`` and go on."""
    try:
        func(row)
    except Exception as exc:  # noqa: BLE001 -- one failing method must not end the run
        row["error"] = f"{type(exc).__name__}: {exc}"
        print(f"    FAILED: {row['error']}", flush=True)
        traceback.print_exc(file=sys.stderr)
        sys.stderr.flush()
    return row


# ---------------------------------------------------------------------------------------
# Formatting
# ---------------------------------------------------------------------------------------


def fmt(value, spec):
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return ""
    return format(value, spec)


def aggregate(rows, keys):
    """Mean and standard deviation over seeds of each key; errors and seed counts."""
    ok = [r for r in rows if "error" not in r]
    out = {"n_seeds": len(rows), "n_ok": len(ok)}
    errors = [r["error"] for r in rows if "error" in r]
    if errors:
        out["errors"] = errors
    for key in keys:
        values = [r[key] for r in ok if r.get(key) is not None]
        values = np.asarray(values, dtype=np.float64)
        if values.size:
            out[key] = float(np.mean(values))
            out[f"{key}_std"] = float(np.std(values)) if values.size > 1 else None
        else:
            out[key] = None
    return out


def mean_sd(agg, key, spec, scale=1.0):
    value = agg.get(key)
    if value is None or not np.isfinite(value):
        return ""
    text = format(value * scale, spec)
    sd = agg.get(f"{key}_std")
    if sd is not None and agg["n_ok"] > 1:
        text += " ± " + format(sd * scale, spec)
    return text


def method_cell(label, agg):
    if agg["n_ok"] < agg["n_seeds"]:
        label += f" ({agg['n_seeds'] - agg['n_ok']} of {agg['n_seeds']} seeds failed)"
    return label


def error_cell(agg, width=90):
    if agg["n_ok"] == 0 and agg.get("errors"):
        return "error: " + agg["errors"][0][:width].replace("|", "/")
    return None


# ---------------------------------------------------------------------------------------
# 1. Simulated worlds
# ---------------------------------------------------------------------------------------

SIM_KEYS = (
    "auc",
    "phantom_rate",
    "free_found",
    "walls_found",
    "ece",
    "brier",
    "wall_thickness",
    "fit_s",
    "score_s",
    "length_scale",
    "n_experts",
)


def run_sim(args, result, save):
    settings = [s for s in SIM_SETTINGS if not args.quick or s[1] == "sparse"]
    methods = sim_methods(args.methods)
    sim = result.setdefault(
        "sim",
        {
            "resolution": RESOLUTION,
            "noise_std": NOISE_STD,
            "settings": [],
            "rows": [],
            "summary": [],
        },
    )
    for world, sparsity, generator, kwargs, description in settings:
        setting_rows = []
        n_obs, n_seen = [], []
        for seed in args.seeds:
            data = generator(noise_std=NOISE_STD, random_state=seed, **kwargs)
            n_obs.append(int(data.X.shape[0]))
            grid = data.environment.ground_truth_grid(RESOLUTION, scans=data.scans)
            n_cells, n_observed = int(len(grid.points)), int(grid.observed.sum())
            n_seen.append(n_observed)
            for method in methods:
                print(
                    f"B4 sim: {world} {sparsity} seed {seed}, {data.X.shape[0]} observations "
                    f"({n_observed} of {n_cells} cells observed): {method.label} ...",
                    flush=True,
                )
                row = dict(
                    world=world,
                    sparsity=sparsity,
                    seed=seed,
                    method=method.key,
                    label=method.label,
                    n_train=int(data.X.shape[0]),
                )

                def work(row, method=method, data=data, seed=seed):
                    model, fit_s, caught = fit_model(
                        method, seed, args.n_jobs, data.X, data.y, data.scan_index
                    )
                    row.update(fit_s=fit_s, **model_facts(model))
                    if caught:
                        row["warnings"] = caught
                    start = time.perf_counter()
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        scores = map_quality(
                            model, data.environment, resolution=RESOLUTION, scans=data.scans
                        )
                    row["score_s"] = time.perf_counter() - start
                    row.update(scores)
                    print(
                        f"    AUC {scores['auc']:.4f}, phantom "
                        f"{100 * scores['phantom_rate']:.2f} %, "
                        f"free {100 * scores['free_found']:.1f} %, walls "
                        f"{100 * scores['walls_found']:.1f} %, ECE {scores['ece']:.3f}, "
                        f"thickness {scores['wall_thickness']:.2f} m, fit {fit_s:.1f} s",
                        flush=True,
                    )

                setting_rows.append(guarded(row, work))
                sim["rows"].append(row)
                save()
        info = dict(
            world=world,
            sparsity=sparsity,
            description=description,
            kwargs=kwargs,
            n_train=n_obs,
            n_cells=n_cells,
            n_observed_cells=n_seen,
        )
        sim["settings"].append(info)
        table = []
        for method in methods:
            rows = [r for r in setting_rows if r["method"] == method.key]
            agg = aggregate(rows, SIM_KEYS)
            agg.update(world=world, sparsity=sparsity, method=method.key, label=method.label)
            sim["summary"].append(agg)
            err = error_cell(agg)
            cells = [method_cell(method.label, agg)]
            if err:
                cells += [err] + [""] * 8
            else:
                cells += [
                    mean_sd(agg, "auc", ".4f"),
                    mean_sd(agg, "phantom_rate", ".2f", 100),
                    mean_sd(agg, "free_found", ".1f", 100),
                    mean_sd(agg, "walls_found", ".1f", 100),
                    mean_sd(agg, "ece", ".3f"),
                    mean_sd(agg, "brier", ".3f"),
                    mean_sd(agg, "wall_thickness", ".2f"),
                    fmt(agg.get("fit_s"), ".2f"),
                    mean_sd(agg, "length_scale", ".2f"),
                ]
            table.append(cells)
        print_table(
            f"B4 sim: {WORLD_TITLES[world]}, {sparsity} ({description}, "
            f"{int(np.mean(n_obs))} observations, "
            f"{int(np.mean(n_seen))} observed {RESOLUTION} m cells), "
            f"{args.seed_role} seeds {', '.join(map(str, args.seeds))}",
            [
                "method",
                "AUC",
                "phantom %",
                "free found %",
                "walls found %",
                "ECE",
                "Brier",
                "thickness m",
                "fit s",
                "length scale m",
            ],
            table,
        )
        save()


# ---------------------------------------------------------------------------------------
# 2. Real logs, Hilbert-maps protocol
# ---------------------------------------------------------------------------------------

LOG_KEYS = ("auc", "fit_s", "predict_us_per_point", "length_scale", "n_experts", "n_train")


def run_logs(args, result, save, cache):
    methods = log_methods(args.methods)
    logs = result.setdefault("logs", {"rows": [], "summary": [], "protocol": {}})
    for name, (path, role, title) in LOGS.items():
        if name not in args.logs:
            continue
        if not path.is_file():
            print(f"\nB4 logs: {path} not found, skipped", flush=True)
            logs["protocol"][name] = {"skipped": f"{path} not found"}
            continue
        scans = load_carmen(path)
        log_rows = []
        n_test = {}
        for seed in args.seeds:
            for every in args.logs_every:
                bunch = blocks_protocol(scans, train_every=every, random_state=seed)
                X, y, _, scan_index = bunch.train.to_observations(return_scan_index=True)
                Q = as_segments(bunch.points)
                n_test[seed] = int(len(bunch.points))
                for method in methods:
                    print(
                        f"B4 logs: {name} seed {seed}, every {every} ({len(bunch.train)} scans, "
                        f"{len(X)} observations, {len(Q)} test points): {method.label} ...",
                        flush=True,
                    )
                    row = dict(
                        log=name,
                        role=role,
                        seed=seed,
                        every=every,
                        method=method.key,
                        label=method.label,
                        n_scans=len(bunch.train),
                        n_train=int(len(X)),
                        n_test=int(len(Q)),
                    )

                    def work(
                        row,
                        method=method,
                        X=X,
                        y=y,
                        scan_index=scan_index,
                        Q=Q,
                        labels=bunch.labels,
                        seed=seed,
                        every=every,
                        name=name,
                    ):
                        model, fit_s, caught = fit_model(
                            method, seed, args.n_jobs, X, y, scan_index
                        )
                        row.update(fit_s=fit_s, **model_facts(model))
                        if caught:
                            row["warnings"] = caught
                        start = time.perf_counter()
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            proba = model.predict_proba(Q)[:, 1]
                        predict_s = time.perf_counter() - start
                        row.update(
                            auc=float(roc_auc_score(labels, proba)),
                            predict_us_per_point=1e6 * predict_s / len(Q),
                        )
                        if method.family == "mixture" and "length_scale" in row:
                            beam = model.get_params().get("max_beam_length")
                            cache[(name, every, seed, beam)] = dict(
                                length_scale=row["length_scale"],
                                fit_s=fit_s,
                                auc=row["auc"],
                                source="logs",
                            )
                        print(
                            f"    AUC {row['auc']:.4f}, fit {fit_s:.1f} s, "
                            f"{row['predict_us_per_point']:.1f} us/point",
                            flush=True,
                        )

                    log_rows.append(guarded(row, work))
                    logs["rows"].append(row)
                    save()
        logs["protocol"][name] = dict(
            log=str(path), role=role, n_scans=len(scans), n_test_points=n_test
        )
        table = []
        for every in args.logs_every:
            for method in methods:
                rows = [r for r in log_rows if r["method"] == method.key and r["every"] == every]
                agg = aggregate(rows, LOG_KEYS)
                agg.update(log=name, role=role, every=every, method=method.key, label=method.label)
                logs["summary"].append(agg)
                err = error_cell(agg)
                n_scans = rows[0]["n_scans"] if rows else ""
                cells = [
                    f"every {every} ({n_scans})",
                    fmt(agg.get("n_train"), ".0f"),
                    method_cell(method.label, agg),
                ]
                if err:
                    cells += [err, "", "", ""]
                else:
                    cells += [
                        mean_sd(agg, "auc", ".4f"),
                        fmt(agg.get("fit_s"), ".2f"),
                        fmt(agg.get("predict_us_per_point"), ".1f"),
                        mean_sd(agg, "length_scale", ".2f"),
                    ]
                table.append(cells)
        tests = sorted(set(n_test.values()))
        print_table(
            f"B4 logs: {title} ({role} log), Hilbert-maps protocol, {args.seed_role} seeds "
            f"{', '.join(map(str, args.seeds))} ({'/'.join(map(str, tests))} test points)",
            [
                "training scans",
                "observations",
                "method",
                "AUC",
                "fit s",
                "predict us/point",
                "length scale m",
            ],
            table,
        )
        save()


# ---------------------------------------------------------------------------------------
# 3. Summary
# ---------------------------------------------------------------------------------------


def _met(kind, value, bound):
    if value is None or not np.isfinite(value):
        return None
    # Thicknesses are sums of grid steps (3 * 0.1 = 0.30000000000000004): compare with a
    # tolerance far below any reported digit.
    tol = 1e-9 * max(1.0, abs(bound))
    return bool(value <= bound + tol) if kind == "max" else bool(value >= bound - tol)


def summarise(args, result):
    summary = result.setdefault("summary", {})
    if "logs" in result:
        rows, table = [], []
        aggs = result["logs"]["summary"]
        for name, (_, role, title) in LOGS.items():
            for every in args.logs_every:
                here = [a for a in aggs if a["log"] == name and a["every"] == every]
                mixture = next((a for a in here if a["method"] == "mixture"), None)
                # Baselines only: the mixture's own variants are not what it must beat.
                others = [
                    a
                    for a in here
                    if not a["method"].startswith("mixture") and a.get("auc") is not None
                ]
                if mixture is None or not here:
                    continue
                best = max(others, key=lambda a: a["auc"], default=None)
                ok = (
                    None
                    if mixture.get("auc") is None or best is None
                    else bool(mixture["auc"] >= best["auc"])
                )
                rows.append(
                    dict(
                        log=name,
                        role=role,
                        every=every,
                        mixture_auc=mixture.get("auc"),
                        best_baseline=best and best["method"],
                        best_baseline_auc=best and best["auc"],
                        mixture_at_least_best=ok,
                    )
                )
                table.append(
                    [
                        f"{title} ({role})",
                        f"every {every}",
                        fmt(mixture.get("auc"), ".4f"),
                        "" if best is None else best["label"],
                        fmt(best and best["auc"], ".4f"),
                        {True: "yes", False: "**no**", None: "n/a"}[ok],
                    ]
                )
        summary["logs"] = rows
        if table:
            print_table(
                "B4 summary: mixture mean AUC against the best baseline's, per log and sparsity",
                [
                    "log",
                    "training scans",
                    "mixture AUC",
                    "best baseline",
                    "its AUC",
                    "mixture >= best",
                ],
                table,
            )
    if "sim" in result:
        rows, table = [], []
        for agg in result["sim"]["summary"]:
            if agg["method"] not in ("mixture", "mixture_every_hit", "mixture_whole_beams"):
                continue
            marks, row = (
                [],
                dict(
                    world=agg["world"], sparsity=agg["sparsity"], method=agg["method"], targets={}
                ),
            )
            for key, (kind, bound, _) in TARGETS.items():
                met = _met(kind, agg.get(key), bound)
                row["targets"][key] = dict(value=agg.get(key), bound=bound, kind=kind, met=met)
                scale, spec = TARGET_FORMATS[key]
                value = fmt(None if agg.get(key) is None else agg[key] * scale, spec)
                verdict = {True: "met", False: "**missed**", None: "n/a"}[met]
                marks.append(f"{value} {verdict}")
            row["all_met"] = all(t["met"] for t in row["targets"].values())
            rows.append(row)
            table.append([WORLD_TITLES[agg["world"]], agg["sparsity"], agg["label"], *marks])
        summary["sim"] = rows
        if table:
            print_table(
                "B4 summary: targets of the simulated maps (means over seeds)",
                ["world", "sparsity", "method", *(t[2] for t in TARGETS.values())],
                table,
            )


# ---------------------------------------------------------------------------------------
# 4. Length-scale stability (Intel)
# ---------------------------------------------------------------------------------------


def relative_change(a, b):
    """|a - b| / min(a, b): symmetric, the larger of the two relative changes."""
    if a is None or b is None or min(a, b) <= 0:
        return None
    return abs(a - b) / min(a, b)


def run_stability(args, result, save, cache):
    path, role, title = LOGS["intel"]
    stability = result.setdefault("stability", {})
    if not path.is_file():
        stability["skipped"] = f"{path} not found"
        print(f"\nB4 stability skipped: {path} not found", flush=True)
        return
    dense, sparse = args.stability_every
    default_beam = MixtureGPOccupancyMap().get_params()["max_beam_length"]
    scans = None

    def length_scale(seed, every, beam, window=None):
        nonlocal scans
        key = ("intel", every, seed, beam) + (() if window is None else (window,))
        if key in cache:
            return cache[key]
        if scans is None:
            scans = load_carmen(path)
        bunch = blocks_protocol(scans, train_every=every, random_state=seed)
        X, y, _ = bunch.train.to_observations()
        print(
            f"B4 stability: Intel every {every} ({len(X)} observations), "
            f"max_beam_length={beam}, hyperparameter_window={window} ...",
            flush=True,
        )
        method = Method(
            "mixture",
            "mixture",
            "mixture",
            lambda s, j: MixtureGPOccupancyMap(
                max_beam_length=beam, hyperparameter_window=window, random_state=s, n_jobs=j
            ),
        )
        entry = {"source": "stability"}

        def work(entry):
            model, fit_s, caught = fit_model(method, seed, args.n_jobs, X, y, None)
            entry.update(length_scale=learned_length_scale(model), fit_s=fit_s)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                proba = model.predict_proba(as_segments(bunch.points))[:, 1]
            entry["auc"] = float(roc_auc_score(bunch.labels, proba))
            if caught:
                entry["warnings"] = caught
            print(
                f"    length scale {fmt(entry['length_scale'], '.3f')} m, fit {fit_s:.1f} s, "
                f"AUC {fmt(entry.get('auc'), '.4f')}",
                flush=True,
            )

        cache[key] = guarded(entry, work)
        return cache[key]

    comparisons = [
        (
            (f"all vs every {sparse}" if dense == 1 else f"every {dense} vs every {sparse}")
            + f", max_beam_length {default_beam} (default)",
            (dense, default_beam),
            (sparse, default_beam),
        ),
    ]
    comparisons += [
        (
            f"max_beam_length {STABILITY_BEAM_LENGTHS[0]} vs {STABILITY_BEAM_LENGTHS[1]}, "
            f"every {sparse}",
            (sparse, STABILITY_BEAM_LENGTHS[0]),
            (sparse, STABILITY_BEAM_LENGTHS[1]),
        ),
    ]
    comparisons += [
        (
            comparisons[0][0].replace(" (default)", "")
            + f", hyperparameter_window {STABILITY_WINDOW}",
            (dense, default_beam, STABILITY_WINDOW),
            (sparse, default_beam, STABILITY_WINDOW),
        ),
    ]
    rows, table = [], []
    runs = [(seed, *comparison) for seed in args.seeds for comparison in comparisons]
    for seed, what, (every_a, beam_a, *window_a), (every_b, beam_b, *window_b) in runs:
        a = length_scale(seed, every_a, beam_a, *window_a)
        b = length_scale(seed, every_b, beam_b, *window_b)
        window = window_a[0] if window_a else None
        change = relative_change(a.get("length_scale"), b.get("length_scale"))
        ok = None if change is None else bool(change < STABILITY_TARGET)
        rows.append(
            dict(
                comparison=what,
                seed=seed,
                hyperparameter_window=window,
                a=dict(every=every_a, max_beam_length=beam_a, **a),
                b=dict(every=every_b, max_beam_length=beam_b, **b),
                relative_change=change,
                met=ok,
            )
        )
        errors = "; ".join(e["error"][:60] for e in (a, b) if "error" in e).replace("|", "/")
        table.append(
            [
                what,
                seed,
                fmt(a.get("length_scale"), ".3f"),
                fmt(b.get("length_scale"), ".3f"),
                fmt(None if change is None else 100 * change, ".1f"),
                fmt(a.get("auc"), ".4f"),
                fmt(b.get("auc"), ".4f"),
                {True: "met", False: "**missed**", None: "n/a"}[ok]
                + (f" ({errors})" if errors else ""),
            ]
        )
    stability.update(
        log=str(path),
        seeds=list(args.seeds),
        default_max_beam_length=default_beam,
        target=STABILITY_TARGET,
        rows=rows,
    )
    print_table(
        f"B4 stability: the mixture's learned length scale on {title} ({role} log), "
        "Hilbert-maps training scans of each report seed (the estimator's random_state "
        "too); relative change |a - b| / min(a, b)",
        [
            "comparison",
            "seed",
            "a: length scale m",
            "b: length scale m",
            "change %",
            "a: AUC",
            "b: AUC",
            f"< {100 * STABILITY_TARGET:.0f} %",
        ],
        table,
    )
    save()


# ---------------------------------------------------------------------------------------


def run_record(benchmark, args, path, **fields):
    """A run's JSON record (machine, commit, ``fields``, arguments) and its ``save()``.

    ``save()`` writes the record to ``path`` with the run's time so far, so that a run cut
    short still leaves what it measured.
    """
    started = time.perf_counter()
    result = {
        "benchmark": benchmark,
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": platform.platform(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "blas_threads": 1,
        "git": git_state(),
        **fields,
        "params": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
    }

    def save():
        result["total_s"] = time.perf_counter() - started
        path.write_text(json.dumps(result, indent=2, default=str))

    return result, save


def git_state():
    """Commit of the code measured, and whether the package had uncommitted changes."""
    root = HERE.parent

    def git(*command):
        done = subprocess.run(
            ["git", *command], cwd=root, capture_output=True, text=True, check=False
        )
        return done.stdout.strip() if done.returncode == 0 else None

    changed = git("status", "--porcelain", "--", "skoccmap")
    return {"commit": git("rev-parse", "HEAD"), "skoccmap_modified": bool(changed)}


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: sparse simulated settings, one seed, logs at every "
        "40th scan (a few minutes)",
    )
    parser.add_argument("--n-jobs", type=int, default=1, help="parallel expert fits")
    parser.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=None,
        help=f"seeds (default: the report seeds {REPORT_SEEDS}; the first with --quick)",
    )
    parser.add_argument(
        "--tuning",
        action="store_true",
        help=f"use the tuning seeds {TUNING_SEEDS} (to choose defaults on)",
    )
    parser.add_argument(
        "--only",
        choices=("sim", "logs", "stability"),
        default=None,
        help="simulated worlds only, real logs (and stability) only, or the stability report "
        "only (its own fits)",
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=FAMILIES,
        default=list(FAMILIES),
        help="methods to run (default all)",
    )
    parser.add_argument(
        "--logs",
        nargs="+",
        choices=tuple(LOGS),
        default=list(LOGS),
        help="real logs to run (default all)",
    )
    parser.add_argument(
        "--logs-every",
        type=int,
        nargs="+",
        default=None,
        help=f"training sparsities on the logs (default {LOGS_EVERY}; "
        "40 with --quick); '10 40' skips the slow all-scans setting",
    )
    parser.add_argument(
        "--stability-every",
        type=int,
        nargs=2,
        default=None,
        metavar=("DENSE", "SPARSE"),
        help="the two sparsities of the stability report (default 1 10 when "
        "the logs run on all scans, else 10 40)",
    )
    parser.add_argument(
        "--no-stability", action="store_true", help="skip the length-scale stability report"
    )
    parser.add_argument(
        "--out", default=None, help="folder of the JSON (default benchmarks/results[/quick])"
    )
    args = parser.parse_args(argv)

    if args.seeds is None:
        args.seeds = list(TUNING_SEEDS if args.tuning else REPORT_SEEDS)
        if args.quick:
            args.seeds = args.seeds[:1]
    elif args.tuning:
        parser.error("give either --tuning or --seeds")
    if set(args.seeds) <= set(REPORT_SEEDS):
        args.seed_role = "report"
    elif set(args.seeds) <= set(TUNING_SEEDS):
        args.seed_role = "tuning"
    else:
        args.seed_role = "custom"
    if args.logs_every is None:
        args.logs_every = [40] if args.quick else list(LOGS_EVERY)
    if any(k < 1 for k in args.logs_every):
        parser.error("--logs-every takes positive integers")
    if args.stability_every is None:
        args.stability_every = [1, 10] if 1 in args.logs_every else [10, 40]
    if args.out is None:
        args.out = RESULTS / "quick" if args.quick else RESULTS
    args.out = Path(args.out)
    return args


def main(argv=None):
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    name = "bench_quality"
    if args.only:
        name += f"_{args.only}"
    if args.seed_role == "tuning":
        name += "_tuning"
    path = args.out / f"{name}.json"
    result, save = run_record(
        "B4 map quality",
        args,
        path,
        quick=args.quick,
        seeds=args.seeds,
        seed_role=args.seed_role,
        report_seeds=list(REPORT_SEEDS),
        tuning_seeds=list(TUNING_SEEDS),
        targets={k: dict(kind=v[0], bound=v[1]) for k, v in TARGETS.items()},
    )

    cache = {}  # (log, every, seed, max_beam_length) -> the mixture's length scale
    if args.only in (None, "sim"):
        run_sim(args, result, save)
    if args.only in (None, "logs"):
        run_logs(args, result, save, cache)
    if args.only in (None, "logs", "stability"):
        if not args.no_stability and "mixture" in args.methods:
            run_stability(args, result, save, cache)
    summarise(args, result)
    save()
    print(f"\nB4 done in {result['total_s']:.0f} s; JSON in {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
