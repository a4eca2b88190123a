"""Tuning: MixtureGPOccupancyMap's parameters swept one at a time around the defaults.

Run standalone::

    python benchmarks/bench_tuning.py --n-jobs 2                  # full run (see README)
    python benchmarks/bench_tuning.py --quick --n-jobs 2          # fewer configurations
    python benchmarks/bench_tuning.py --only combiner gating_threshold --n-jobs 2
    python benchmarks/bench_tuning.py --datasets office paper     # without ACES

Prints one markdown table per parameter and writes ``benchmarks/results/bench_tuning.json``
(``results/quick/`` with ``--quick``; ``bench_tuning_<sweeps>.json`` with ``--only`` or
``--datasets``). The numbers quoted "on the tuning data" in the parameter docstrings of
:class:`skoccmap.MixtureGPOccupancyMap` come from this script; those of the baselines
(:class:`skoccmap.baselines.HilbertMap`, :class:`skoccmap.baselines.OccupancyGridMap`) from
``bench_tuning_baselines.py``, on the same data (its ``grid`` group adds Intel rows,
labelled as report-log measurements).

**Tuning data only.** Nothing here touches the report data (the Intel log, seeds 0-2):

- ``aces``: the ACES log (``../shared/data/aces-corrected.log.gz``; skipped when absent) on
  the Hilbert-maps protocol (``skoccmap.metrics.blocks_protocol``) with seed 100, trained on
  every 10th remaining scan; held-out ROC AUC, predict us/point on the test points, experts
  consulted per test point (the last two also on the simulated worlds' observed cells).
  The data are built as ``bench_quality.run_logs`` builds them.
- ``office`` and ``paper``: the office floor (30 poses x 45 beams) and the paper's world
  (17 beams x 26 poses), the sparse settings of ``bench_quality.SIM_SETTINGS``, with range
  noise ``bench_quality.NOISE_STD`` of seed 100, scored as ``bench_quality.run_sim`` scores
  them (``skoccmap.metrics.map_quality`` on the observed 0.1 m cells): walls found, phantom
  rate, free found, ECE, wall thickness, AUC.

The estimators' ``random_state`` is the data seed (100), as in ``bench_quality``;
``--random-state N`` refits the same data with another one, to see how far a difference
between two values is the draw of one fit (clustering sample, thinning, learning groups).

**Sweeps** (one parameter at a time, all others at their defaults): ``combiner``,
``gating`` (with the threshold that suits each gate), ``gating_threshold`` and
``reach_tolerance`` (experts consulted per query), ``max_expert_size``,
``max_beam_length`` (with ``beam_end_length`` 0.35, and the whole-beam model with both
``None``), ``beam_end_length``, ``max_pieces_per_cell``, ``piece_cell_size``,
``min_hit_frequency`` (with the
share of hits left out as transient), ``piece_assignment``, ``nearest_hit_radius``,
``share_hyperparameters``, ``hyperparameter_window`` (with
the learned length scale; ``--datasets aces_all`` adds ACES trained on every scan, for the
length scale's stability against the density of the scans), and the default expert's signal
variance (``ConstantKernel`` fixed at 1e2 / 1e3 / 1e4, or learned), and the default
expert's kernel with one length scale or two (``kernel``: a second integral kernel with its
own learned signal variance; ``--datasets paper_dense`` adds the paper's world at B4's dense
setting, where the phantoms are; ``office_dense`` the office at B4's dense setting).
``combiner``, ``gating`` and ``gating_threshold`` are read at predict time: one fit per
dataset serves all their values (``set_params`` on the fitted map). Every other value is a
fit of its own; a fit shared by several sweeps (the defaults) is done once.

Fit and predict times are informative only: the machine the numbers were taken on is shared,
and its seconds drift by tens of percent between runs. A configuration that fails is
reported with its error; the run goes on.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _tables import print_table  # noqa: E402
from bench_quality import (  # noqa: E402
    LOGS,
    NOISE_STD,
    RESOLUTION,
    SIM_SETTINGS,
    TUNING_SEEDS,
    WORLD_TITLES,
    Method,
    fit_model,
    fmt,
    guarded,
    model_facts,
    run_record,
)
from sklearn.gaussian_process.kernels import ConstantKernel  # noqa: E402
from sklearn.metrics import roc_auc_score  # noqa: E402

from skoccmap._experts import _default_expert  # noqa: E402
from skoccmap.datasets import load_carmen  # noqa: E402
from skoccmap.kernels import IntegralKernel  # noqa: E402
from skoccmap.metrics import blocks_protocol, map_quality  # noqa: E402
from skoccmap.mixture import MixtureGPOccupancyMap  # noqa: E402
from skoccmap.observations import as_segments  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"

SEED = TUNING_SEEDS[0]  # 100: the data seed and the estimators' random_state
ACES_EVERY = 10  # ACES trained on every 10th remaining scan
PREDICT_REPEATS = 2  # predict time: the best of this many runs
DATASETS = ("aces", "office", "paper")
# ACES trained on every remaining scan: the learned length scale's stability against the
# density of the scans (with --datasets; not in the default run, its fits are ten times
# larger).
EXTRA_DATASETS_ALL = ("aces_all",)
# The 3-D room at both sparsities of B4 (with --datasets; not in the default run).
EXTRA_DATASETS_ROOM = ("room3d", "room3d_dense")
# The paper's world at B4's dense setting (45 beams x 52 poses), where the phantoms are.
EXTRA_DATASETS_DENSE = ("paper_dense", "office_dense")
DATASET_TITLES = {
    "aces": f"ACES, blocks protocol, every {ACES_EVERY}th scan",
    "aces_all": "ACES, blocks protocol, every scan",
    "office": WORLD_TITLES["office"],
    "paper": WORLD_TITLES["paper"],
    "room3d": WORLD_TITLES["room3d"] + ", sparse",
    "room3d_dense": WORLD_TITLES["room3d"] + ", dense",
    "paper_dense": WORLD_TITLES["paper"] + ", dense",
    "office_dense": WORLD_TITLES["office"] + ", dense",
}


# ---------------------------------------------------------------------------------------
# Configurations
# ---------------------------------------------------------------------------------------


def _expert(constant):
    """The default expert with another signal variance (fixed value, or learned bounds)."""
    if isinstance(constant, tuple):
        kernel = ConstantKernel(1e3, constant) * IntegralKernel()
    else:
        kernel = ConstantKernel(constant, "fixed") * IntegralKernel()
    return _default_expert(kernel)


LEARNED_SIGNAL_BOUNDS = (1e-2, 1e5)


def _two_scale_expert():
    """The default kernel plus a second integral kernel with its own (learned) signal
    variance and length scale, started long: a detail and a trend scale."""
    kernel = ConstantKernel(1e3, "fixed") * IntegralKernel(0.5) + ConstantKernel(
        1e2, (1.0, 1e5)
    ) * IntegralKernel(2.0)
    return _default_expert(kernel)


# Fits: key -> (constructor parameters, description). "default" is the estimator's defaults.
FITS = {
    "default": ({}, "defaults"),
    "reach_1e-1": ({"reach_tolerance": 1e-1}, "reach_tolerance=1e-1"),
    "reach_1e-3": ({"reach_tolerance": 1e-3}, "reach_tolerance=1e-3"),
    "size_200": ({"max_expert_size": 200}, "max_expert_size=200"),
    "size_800": ({"max_expert_size": 800}, "max_expert_size=800"),
    "beam_none": ({"max_beam_length": None}, "max_beam_length=None"),
    "beam_2": ({"max_beam_length": 2.0}, "max_beam_length=2"),
    "beam_0.5": ({"max_beam_length": 0.5}, "max_beam_length=0.5"),
    "whole_beams": (
        {"max_beam_length": None, "beam_end_length": None},
        "max_beam_length=None, beam_end_length=None",
    ),
    "end_none": ({"beam_end_length": None}, "beam_end_length=None"),
    "end_0.5": ({"beam_end_length": 0.5}, "beam_end_length=0.5"),
    "end_0.25": ({"beam_end_length": 0.25}, "beam_end_length=0.25"),
    "cap_none": ({"max_pieces_per_cell": None}, "max_pieces_per_cell=None"),
    "cap_16": ({"max_pieces_per_cell": 16}, "max_pieces_per_cell=16"),
    "cap_8": ({"max_pieces_per_cell": 8}, "max_pieces_per_cell=8"),
    "cap_4": ({"max_pieces_per_cell": 4}, "max_pieces_per_cell=4"),
    "cap_2": ({"max_pieces_per_cell": 2}, "max_pieces_per_cell=2"),
    "piece_cell_0.3": ({"piece_cell_size": 0.3}, "piece_cell_size=0.3"),
    "piece_cell_0.4": ({"piece_cell_size": 0.4}, "piece_cell_size=0.4"),
    "piece_cell_0.6": ({"piece_cell_size": 0.6}, "piece_cell_size=0.6"),
    "hits_none": ({"min_hit_frequency": None}, "min_hit_frequency=None"),
    "hits_0.1": ({"min_hit_frequency": 0.1}, "min_hit_frequency=0.1"),
    "hits_0.3": ({"min_hit_frequency": 0.3}, "min_hit_frequency=0.3"),
    "hits_0.4": ({"min_hit_frequency": 0.4}, "min_hit_frequency=0.4"),
    "hits_0.5": ({"min_hit_frequency": 0.5}, "min_hit_frequency=0.5"),
    "pieces_beam": ({"piece_assignment": "beam"}, 'piece_assignment="beam"'),
    "radius_1": ({"nearest_hit_radius": 1.0}, "nearest_hit_radius=1"),
    "radius_4": ({"nearest_hit_radius": 4.0}, "nearest_hit_radius=4"),
    "no_share": ({"share_hyperparameters": False}, "share_hyperparameters=False"),
    "window_1.5": ({"hyperparameter_window": 1.5}, "hyperparameter_window=1.5"),
    "window_3": ({"hyperparameter_window": 3.0}, "hyperparameter_window=3"),
    "window_6": ({"hyperparameter_window": 6.0}, "hyperparameter_window=6"),
    "signal_1e2": ({"expert": _expert(1e2)}, "ConstantKernel(1e2, fixed) * IntegralKernel()"),
    "signal_1e4": ({"expert": _expert(1e4)}, "ConstantKernel(1e4, fixed) * IntegralKernel()"),
    "signal_learned": (
        {"expert": _expert(LEARNED_SIGNAL_BOUNDS)},
        f"ConstantKernel(1e3, {LEARNED_SIGNAL_BOUNDS}) * IntegralKernel()",
    ),
    "two_scales": (
        {"expert": _two_scale_expert()},
        "ConstantKernel(1e3, fixed) * IntegralKernel(0.5) + ConstantKernel(1e2, (1, 1e5)) "
        "* IntegralKernel(2.0)",
    ),
}


@dataclass
class Entry:
    """One row of a sweep: a fit, and the parameters set on it before predicting."""

    label: str
    fit: str
    predict: dict = field(default_factory=dict)
    default: bool = False


@dataclass
class Sweep:
    name: str
    title: str
    entries: list
    quick: tuple = ()  # labels kept by --quick; empty: the sweep is skipped by --quick
    extra: tuple = ()  # extra columns (see EXTRA_COLUMNS)


def _predict_entries(parameter, values, default):
    # The default value is the fit as it stands: its row is shared with the other sweeps.
    return [
        Entry(label, "default", {} if value == default else {parameter: value}, value == default)
        for label, value in values
    ]


SWEEPS = [
    Sweep(
        "combiner",
        "`combiner` (predict time, one fit)",
        _predict_entries(
            "combiner", [(c, c) for c in ("moe", "poe", "gpoe", "bcm", "rbcm")], "rbcm"
        ),
        quick=("moe", "poe", "gpoe", "bcm", "rbcm"),
    ),
    Sweep(
        "gating",
        "`gating` with its `gating_threshold` (predict time, one fit)",
        [
            Entry("coverage, auto (0.35)", "default", default=True),
            Entry("clusterer, 1e-3", "default", {"gating": "clusterer", "gating_threshold": 1e-3}),
            Entry("clusterer, 0", "default", {"gating": "clusterer", "gating_threshold": 0.0}),
        ],
        quick=("coverage, auto (0.35)", "clusterer, 1e-3"),
        extra=("predict", "consulted"),
    ),
    Sweep(
        "gating_threshold",
        "`gating_threshold` (predict time, one fit)",
        _predict_entries(
            "gating_threshold",
            [
                ("0.8", 0.8),
                ("0.7", 0.7),
                ("0.6", 0.6),
                ("0.5", 0.5),
                ("auto (0.35)", "auto"),
                ("0.2", 0.2),
                ("0.1", 0.1),
                ("0.05", 0.05),
                ("0.02", 0.02),
                ("0", 0.0),
            ],
            "auto",
        ),
        quick=("0.7", "auto (0.35)", "0.1"),
        extra=("predict", "consulted"),
    ),
    Sweep(
        "reach_tolerance",
        "`reach_tolerance` (a fit each: `reach_` is set by fit)",
        [
            Entry("1e-1", "reach_1e-1"),
            Entry("1e-2", "default", default=True),
            Entry("1e-3", "reach_1e-3"),
        ],
        quick=("1e-1", "1e-2"),
        extra=("reach", "predict", "consulted"),
    ),
    Sweep(
        "max_expert_size",
        "`max_expert_size`",
        [
            Entry("200", "size_200"),
            Entry("400", "default", default=True),
            Entry("800", "size_800"),
        ],
    ),
    Sweep(
        "max_beam_length",
        "`max_beam_length` (`beam_end_length` 0.35; first row: whole beams, both None)",
        [
            Entry("None, beam_end_length None (whole beams)", "whole_beams"),
            Entry("None", "beam_none"),
            Entry("2", "beam_2"),
            Entry("1", "default", default=True),
            Entry("0.5", "beam_0.5"),
        ],
        quick=("None, beam_end_length None (whole beams)", "1"),
        extra=("length_scale", "thickness"),
    ),
    Sweep(
        "beam_end_length",
        "`beam_end_length` (`max_beam_length` 1)",
        [
            Entry("None", "end_none"),
            Entry("0.5", "end_0.5"),
            Entry("0.35", "default", default=True),
            Entry("0.25", "end_0.25"),
        ],
        extra=("thickness",),
    ),
    Sweep(
        "max_pieces_per_cell",
        "`max_pieces_per_cell` (free pieces kept per 0.2 m cell, direction and length)",
        [
            Entry("None", "cap_none"),
            Entry("16", "cap_16"),
            Entry("8", "cap_8"),
            Entry("4", "cap_4"),
            Entry("2", "cap_2"),
        ],
        quick=("None", "4"),
        extra=("length_scale", "predict", "consulted", "fit"),
    ),
    Sweep(
        "piece_cell_size",
        "`piece_cell_size` (side of the cells `max_pieces_per_cell` counts pieces in)",
        [
            Entry("0.2", "default", default=True),
            Entry("0.3", "piece_cell_0.3"),
            Entry("0.4", "piece_cell_0.4"),
            Entry("0.6", "piece_cell_0.6"),
        ],
        quick=("0.2", "0.4"),
        extra=("length_scale", "predict", "consulted", "fit"),
    ),
    Sweep(
        "min_hit_frequency",
        "`min_hit_frequency` (hits left out where 0.1 m cells count hits / (hits + passes) "
        "below it)",
        [
            Entry("None", "hits_none"),
            Entry("0.1", "hits_0.1"),
            Entry("0.2", "default", default=True),
            Entry("0.3", "hits_0.3"),
            Entry("0.4", "hits_0.4"),
            Entry("0.5", "hits_0.5"),
        ],
        quick=("None", "0.2"),
        extra=("transient", "thickness"),
    ),
    Sweep(
        "piece_assignment",
        "`piece_assignment` (which expert a beam piece joins)",
        [
            Entry("nearest_hit", "default", default=True),
            Entry("beam", "pieces_beam"),
        ],
        quick=("nearest_hit", "beam"),
        extra=("length_scale", "predict", "consulted", "thickness"),
    ),
    Sweep(
        "nearest_hit_radius",
        '`nearest_hit_radius` (`piece_assignment="nearest_hit"`)',
        [
            Entry("1", "radius_1"),
            Entry("2", "default", default=True),
            Entry("4", "radius_4"),
        ],
        extra=("length_scale", "consulted"),
    ),
    Sweep(
        "share_hyperparameters",
        "`share_hyperparameters`",
        [Entry("True", "default", default=True), Entry("False", "no_share")],
        extra=("length_scale",),
    ),
    Sweep(
        "hyperparameter_window",
        "`hyperparameter_window` (radius of the windows that learn the shared kernel)",
        [
            Entry("None (experts' own data)", "default", default=True),
            Entry("1.5", "window_1.5"),
            Entry("3", "window_3"),
            Entry("6", "window_6"),
        ],
        extra=("length_scale",),
    ),
    Sweep(
        "signal_variance",
        "the default expert's signal variance (`ConstantKernel` of `expert=None`)",
        [
            Entry("1e2, fixed", "signal_1e2"),
            Entry("1e3, fixed", "default", default=True),
            Entry("1e4, fixed", "signal_1e4"),
            Entry(
                f"learned in [{LEARNED_SIGNAL_BOUNDS[0]:g}, {LEARNED_SIGNAL_BOUNDS[1]:g}]",
                "signal_learned",
            ),
        ],
        extra=("signal", "thickness"),
    ),
    Sweep(
        "kernel",
        "the default expert's kernel: one length scale, or two (summed integral kernels)",
        [
            Entry("one length scale", "default", default=True),
            Entry("two length scales", "two_scales"),
        ],
        extra=("kernel", "reach", "predict", "consulted", "thickness"),
    ),
]
SWEEP_NAMES = tuple(s.name for s in SWEEPS)


# ---------------------------------------------------------------------------------------
# Data and scoring (as bench_quality builds and scores them)
# ---------------------------------------------------------------------------------------


@dataclass
class Dataset:
    name: str
    X: np.ndarray
    y: np.ndarray
    scan_index: np.ndarray
    queries: np.ndarray  # segments whose prediction is timed and whose experts are counted
    info: dict
    labels: np.ndarray = None  # ACES: held-out labels of ``queries``
    sim: object = None  # simulated worlds: the generator's bunch


def load_aces(seed, every=ACES_EVERY, name="aces"):
    path = LOGS["aces"][0]
    if not path.is_file():
        return None
    scans = load_carmen(path)
    bunch = blocks_protocol(scans, train_every=every, random_state=seed)
    X, y, _, scan_index = bunch.train.to_observations(return_scan_index=True)
    info = dict(
        log=str(path),
        n_scans=len(scans),
        train_every=every,
        n_train_scans=len(bunch.train),
        n_train=int(len(X)),
        n_test=int(len(bunch.points)),
    )
    return Dataset(name, X, y, scan_index, as_segments(bunch.points), info, labels=bunch.labels)


def load_sim(world, seed, sparsity="sparse"):
    world_, sparsity, generator, kwargs, description = next(
        s for s in SIM_SETTINGS if s[0] == world and s[1] == sparsity
    )
    data = generator(noise_std=NOISE_STD, random_state=seed, **kwargs)
    grid = data.environment.ground_truth_grid(RESOLUTION, scans=data.scans)
    cells = np.asarray(grid.points)[np.asarray(grid.observed)]
    info = dict(
        world=world_,
        sparsity=sparsity,
        description=description,
        kwargs=kwargs,
        noise_std=NOISE_STD,
        n_train=int(data.X.shape[0]),
        n_cells=int(len(grid.points)),
        n_observed_cells=int(len(cells)),
    )
    return Dataset(world, data.X, data.y, data.scan_index, as_segments(cells), info, sim=data)


def consulted_per_query(model, Q):
    """Mean number of experts a query consults (None if the model cannot say)."""
    consulted = getattr(model, "_consulted", None)
    if consulted is None:
        return None
    return float(consulted(Q)[0].size / len(Q))


def timed_predict(model, Q, repeats):
    best, proba = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        proba = model.predict_proba(Q)[:, 1]
        best = min(best, time.perf_counter() - start)
    return proba, best


def score(model, data, row):
    """Scores of a fitted model on its dataset, into ``row``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if data.name.startswith("aces"):
            proba, predict_s = timed_predict(model, data.queries, PREDICT_REPEATS)
            row["auc"] = float(roc_auc_score(data.labels, proba))
        else:
            _, predict_s = timed_predict(model, data.queries, PREDICT_REPEATS)
            start = time.perf_counter()
            row.update(
                map_quality(
                    model, data.sim.environment, resolution=RESOLUTION, scans=data.sim.scans
                )
            )
            row["score_s"] = time.perf_counter() - start
        row["predict_us_per_point"] = 1e6 * predict_s / len(data.queries)
        row["consulted_per_query"] = consulted_per_query(model, data.queries)


def learned_signal_variance(model):
    kernel = getattr(model, "shared_kernel_", None)
    if kernel is None:
        return None
    values = [v for k, v in kernel.get_params().items() if k.endswith("constant_value")]
    return float(values[0]) if values else None


# ---------------------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------------------


def selected_sweeps(args):
    sweeps = []
    for sweep in SWEEPS:
        if args.only and sweep.name not in args.only:
            continue
        entries = sweep.entries
        if args.quick:
            if not sweep.quick:
                continue
            entries = [e for e in entries if e.label in sweep.quick]
        sweeps.append(Sweep(sweep.name, sweep.title, entries, sweep.quick, sweep.extra))
    return sweeps


def plan(sweeps):
    """Fit key -> list of predict-time parameter sets, in the order the fits run."""
    fits = {}
    for sweep in sweeps:
        for entry in sweep.entries:
            variants = fits.setdefault(entry.fit, [])
            if entry.predict not in variants:
                variants.append(entry.predict)
    order = list(FITS)
    return dict(sorted(fits.items(), key=lambda item: order.index(item[0])))


def run(args, result, save):
    sweeps = selected_sweeps(args)
    fits = plan(sweeps)
    result["fits"] = {key: FITS[key][1] for key in fits}
    rows = result.setdefault("rows", [])
    for name in args.datasets:
        print(f"\nTuning: loading {name} (seed {SEED}) ...", flush=True)
        if name == "aces_all":
            data = load_aces(SEED, every=1, name=name)
        elif name == "aces":
            data = load_aces(SEED)
        elif name in ("paper_dense", "office_dense"):
            data = load_sim(name.split("_")[0], SEED, "dense")
        elif name.startswith("room3d"):
            data = load_sim("room3d", SEED, "dense" if name.endswith("dense") else "sparse")
        else:
            data = load_sim(name, SEED)
        if data is None:
            path = LOGS["aces"][0]
            print(f"Tuning: {path} not found, ACES skipped", flush=True)
            result["datasets"][name] = {"skipped": f"{path} not found"}
            save()
            continue
        result["datasets"][name] = data.info
        print(
            f"Tuning: {name}: {data.info['n_train']} observations, "
            f"{len(data.queries)} query points",
            flush=True,
        )
        for key, variants in fits.items():
            params, description = FITS[key]
            method = Method(
                key,
                "mixture",
                description,
                lambda s, j, params=params: MixtureGPOccupancyMap(
                    random_state=s, n_jobs=j, **params
                ),
            )
            print(f"Tuning: {name}, fit {description} ...", flush=True)
            fitted = {}

            def fit(row, method=method, data=data, fitted=fitted):
                model, fit_s, caught = fit_model(
                    method, args.random_state, args.n_jobs, data.X, data.y, data.scan_index
                )
                row.update(fit_s=fit_s, **model_facts(model))
                row["reach"] = float(getattr(model, "reach_", np.nan))
                row["signal_variance"] = learned_signal_variance(model)
                row["kernel"] = repr(getattr(model, "shared_kernel_", None))
                if caught:
                    row["warnings"] = caught
                fitted["model"] = model
                print(
                    f"    fit {fit_s:.1f} s, {row.get('n_experts')} experts, length scale "
                    f"{fmt(row.get('length_scale'), '.3f')} m",
                    flush=True,
                )

            fit_row = guarded(dict(dataset=name, fit=key), fit)
            model = fitted.get("model")
            for predict in variants:
                row = dict(fit_row, predict=predict)
                if model is None:
                    rows.append(row)
                    continue
                defaults = {k: model.get_params()[k] for k in predict}

                def work(row, model=model, predict=predict, data=data):
                    model.set_params(**predict)
                    score(model, data, row)

                guarded(row, work)
                model.set_params(**defaults)
                print("    " + summary_line(predict, row), flush=True)
                rows.append(row)
                save()
    result["tables"] = tables(sweeps, rows, args)


def summary_line(predict, row):
    what = ", ".join(f"{k}={v}" for k, v in predict.items()) or "as fitted"
    if "error" in row:
        return f"{what}: FAILED"
    text = f"{what}: AUC {fmt(row.get('auc'), '.4f')}"
    if "walls_found" in row:
        text += (
            f", walls {100 * row['walls_found']:.1f} %, phantom "
            f"{100 * row['phantom_rate']:.2f} %, free {100 * row['free_found']:.1f} %, "
            f"ECE {row['ece']:.3f}"
        )
    text += (
        f", {row['predict_us_per_point']:.1f} us/point, "
        f"{fmt(row.get('consulted_per_query'), '.2f')} experts/query"
    )
    return text


# ---------------------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------------------


def _pct(key, spec):
    return lambda r: fmt(None if r.get(key) is None else 100 * r[key], spec)


def _value(key, spec):
    return lambda r: fmt(r.get(key), spec)


# Columns per dataset: (header, cell). ACES has no true map, the simulated worlds no
# held-out points.
DATASET_COLUMNS = {
    "aces": [("AUC", _value("auc", ".4f")), ("experts", _value("n_experts", "d"))],
    "sim": [
        ("walls %", _pct("walls_found", ".1f")),
        ("phantom %", _pct("phantom_rate", ".2f")),
        ("free %", _pct("free_found", ".1f")),
        ("ECE", _value("ece", ".3f")),
    ],
}
EXTRA_COLUMNS = {
    "predict": ("predict us/point", _value("predict_us_per_point", ".0f")),
    "consulted": ("experts/query", _value("consulted_per_query", ".2f")),
    "reach": ("reach m", _value("reach", ".2f")),
    "length_scale": ("length scale m", _value("length_scale", ".3f")),
    "thickness": ("thickness m", _value("wall_thickness", ".2f")),
    "fit": ("fit s", _value("fit_s", ".0f")),
    "transient": (
        "transient hits %",
        lambda row: fmt(100 * row["transient_hits"], ".2f") if "transient_hits" in row else "",
    ),
    "signal": ("signal variance", _value("signal_variance", ".3g")),
    "kernel": ("learned kernel", lambda row: str(row.get("kernel", ""))),
}
# Extras that only make sense where they are measured.
EXTRA_DATASETS = {
    "thickness": ("office", "paper", *EXTRA_DATASETS_ROOM, *EXTRA_DATASETS_DENSE),
    "kernel": (*DATASETS, *EXTRA_DATASETS_ALL, *EXTRA_DATASETS_ROOM, *EXTRA_DATASETS_DENSE),
}


def tables(sweeps, rows, args):
    names = [n for n in args.datasets if any(r["dataset"] == n and "error" not in r for r in rows)]
    out = {}
    for sweep in sweeps:
        header = [sweep.name]
        for name in names:
            short = {
                "aces": "ACES",
                "aces_all": "ACES all",
                "office": "office",
                "paper": "paper",
                "room3d": "room",
                "room3d_dense": "dense room",
                "paper_dense": "dense paper",
                "office_dense": "dense office",
            }[name]
            columns = DATASET_COLUMNS["aces" if name.startswith("aces") else "sim"]
            header += [f"{short} {title}" for title, _ in columns]
            for extra in sweep.extra:
                if name in EXTRA_DATASETS.get(extra, (*DATASETS, *EXTRA_DATASETS_ALL)):
                    header.append(f"{short} {EXTRA_COLUMNS[extra][0]}")
        header.append("fit s (" + " / ".join(names) + ")")
        table, json_rows = [], []
        for entry in sweep.entries:
            label = entry.label + (" (default)" if entry.default else "")
            cells, fit_s, record = [label], [], dict(value=entry.label, default=entry.default)
            for name in names:
                row = next(
                    (
                        r
                        for r in rows
                        if r["dataset"] == name
                        and r["fit"] == entry.fit
                        and r["predict"] == entry.predict
                    ),
                    {},
                )
                record[name] = {k: v for k, v in row.items() if k not in ("dataset", "warnings")}
                columns = DATASET_COLUMNS["aces" if name.startswith("aces") else "sim"]
                if "error" in row:
                    cells += ["error: " + row["error"][:60].replace("|", "/")]
                    cells += [""] * (len(columns) - 1)
                else:
                    cells += [cell(row) for _, cell in columns]
                for extra in sweep.extra:
                    if name in EXTRA_DATASETS.get(extra, (*DATASETS, *EXTRA_DATASETS_ALL)):
                        cells.append("" if "error" in row else EXTRA_COLUMNS[extra][1](row))
                fit_s.append(fmt(row.get("fit_s"), ".0f") or "-")
            cells.append(" / ".join(fit_s))
            table.append(cells)
            json_rows.append(record)
        out[sweep.name] = json_rows
        print_table(
            f"Tuning: {sweep.title}; tuning data, seed {SEED}"
            + ("" if args.random_state == SEED else f", random_state {args.random_state}"),
            header,
            table,
        )
    print(
        "\nFit and predict times are informative only: measured on a shared machine "
        f"({os.cpu_count()} cores, n_jobs={args.n_jobs}, one BLAS thread), they drift by "
        "tens of percent between runs.",
        flush=True,
    )
    return out


# ---------------------------------------------------------------------------------------


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="fewer configurations: combiner, gating (coverage / clusterer), "
        "gating_threshold 0.7/auto/0.1, reach_tolerance "
        "1e-1/1e-2, whole beams against the defaults",
    )
    parser.add_argument(
        "--only", nargs="+", choices=SWEEP_NAMES, default=None, help="sweeps to run"
    )
    parser.add_argument(
        "--datasets",
        nargs="+",
        choices=DATASETS + EXTRA_DATASETS_ALL + EXTRA_DATASETS_ROOM + EXTRA_DATASETS_DENSE,
        default=list(DATASETS),
        help="tuning datasets (default: " + " ".join(DATASETS) + "; aces_all trains on every "
        "ACES scan; room3d and room3d_dense are the 3-D room of B4; paper_dense and "
        "office_dense are the paper's world and the office at B4's dense setting)",
    )
    parser.add_argument("--n-jobs", type=int, default=1, help="parallel expert fits")
    parser.add_argument(
        "--random-state",
        type=int,
        default=SEED,
        help=f"the estimators' random_state (default {SEED}, the data seed); the data stay "
        f"those of seed {SEED}",
    )
    parser.add_argument(
        "--out", default=None, help="folder of the JSON (default benchmarks/results[/quick])"
    )
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = RESULTS / "quick" if args.quick else RESULTS
    args.out = Path(args.out)
    return args


def main(argv=None):
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    name = "bench_tuning"
    if args.only:
        name += "_" + "_".join(args.only)
    if list(args.datasets) != list(DATASETS):
        name += "_" + "_".join(args.datasets)
    if args.random_state != SEED:
        name += f"_rs{args.random_state}"
    path = args.out / f"{name}.json"
    result, save = run_record(
        "tuning sweeps of MixtureGPOccupancyMap",
        args,
        path,
        seed=SEED,
        random_state=args.random_state,
        note="fit and predict times are informative only (shared machine)",
        datasets={},
    )
    run(args, result, save)
    save()
    print(f"\nTuning done in {result['total_s']:.0f} s; JSON in {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
