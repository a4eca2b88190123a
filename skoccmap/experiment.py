"""The simulation experiment of Kim & Kim (ICRA 2012), as functions returning its results.

:func:`run_paper_experiment` simulates the paper's laser scans, fits the three maps it
compares -- a mixture of GP experts (``"moe"``), a Bayesian committee machine over the same
experts (``"bcm"``) and a single GP on all observations (``"single"``) -- evaluates each on
a grid, and scores it against the simulator's true map. The helpers below turn the result
into the paper's tables (:func:`format_tables`), figures (:func:`plot_clusters`,
:func:`plot_maps`, :func:`plot_roc`) and ROS map files (:func:`save_maps`).

``skoccmap demo``, ``examples/plot_paper_experiment.py`` and benchmark B1 all call
:func:`run_paper_experiment`.
"""

import sys
import time
import warnings
from numbers import Integral, Real
from pathlib import Path

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.metrics import roc_auc_score, roc_curve
from sklearn.utils import Bunch

from ._validation import is_number
from .metrics import _check_both_classes
from .observations import HIT, NO_RETURN, RETURN

__all__ = [
    "METHODS",
    "cluster_counts",
    "format_tables",
    "make_models",
    "plot_clusters",
    "plot_maps",
    "plot_roc",
    "points_along_beams",
    "run_paper_experiment",
    "save_figures",
    "save_maps",
]

#: The three maps of the paper, in its order, with the names its tables use.
METHODS = {
    "moe": "mixture of GP experts",
    "bcm": "Bayesian committee machine",
    "single": "single GP",
}
_SINGLE_HYPERPARAMETERS = ("learn", "from_mixture")
# save_figures: the 1200 dpi some journals ask of line art makes figures of up to 15,000
# pixels a side (about 0.8 GB of pixels for Figure 4 of three maps).
_MAX_DPI = 1200


def _signal_and_integral_kernel():
    from sklearn.gaussian_process.kernels import ConstantKernel

    from .kernels import IntegralKernel

    # The paper's kernel, signal variance and length scale learned, for the single GP and the
    # experts alike: they differ only in the data they see.
    return ConstantKernel(1.0, (1e-3, 1e3)) * IntegralKernel()


def _check_methods(methods):
    methods = tuple(methods)
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown or len(set(methods)) != len(methods):
        raise ValueError(
            f"methods must be distinct names among {list(METHODS)}, got {list(methods)}."
        )
    return methods


def _check_positive(name, value):
    if not isinstance(value, Real) or not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number, got {value!r}.")
    return float(value)


def _progress(verbose, message):
    if verbose:
        print(message, file=sys.stdout, flush=True)


def _timed(func, *args):
    start = time.perf_counter()
    out = func(*args)
    return out, time.perf_counter() - start


def make_models(methods=tuple(METHODS), *, random_state=0, n_jobs=None, single_kernel=None):
    """Unfitted estimators of the paper's maps.

    Parameters
    ----------
    methods : sequence of {"moe", "bcm", "single"}, default=("moe", "bcm", "single")
        Maps to build.
    random_state : int, default=0
        Seed shared by all estimators; ``"moe"`` and ``"bcm"`` then cluster and fit their
        experts identically and differ only in how they merge them: the mixture weighs the
        experts its clusters' gate keeps, the committee machine multiplies every expert
        with data within reach (``gating_threshold=0``).
    n_jobs : int or None, default=None
        Parallel expert fits of the mixtures.
    single_kernel : kernel or None, default=None
        Fixed kernel of the single GP (no hyperparameter learning); ``None`` learns
        ``ConstantKernel * IntegralKernel`` from the data.

    Returns
    -------
    models : dict
        Method name -> estimator, in the order of ``methods``.

    Examples
    --------
    >>> from skoccmap.experiment import make_models
    >>> sorted(make_models())
    ['bcm', 'moe', 'single']
    """
    from .classifier import EPGaussianProcessClassifier
    from .mixture import MixtureGPOccupancyMap

    models = {}
    for method in _check_methods(methods):
        if method == "single":
            if single_kernel is None:
                models[method] = EPGaussianProcessClassifier(
                    kernel=_signal_and_integral_kernel(), random_state=random_state
                )
            else:
                models[method] = EPGaussianProcessClassifier(
                    kernel=single_kernel, optimizer=None, random_state=random_state
                )
        else:
            # The paper's model: every whole beam with its hit, every hit, both
            # hyperparameters learned, gated by the clusters of hits. The committee
            # machine multiplies every expert within reach, as Tresp's BCM does: a gate
            # cutting experts out of a product leaves a seam where it cuts.
            models[method] = MixtureGPOccupancyMap(
                expert=EPGaussianProcessClassifier(kernel=_signal_and_integral_kernel()),
                gating="clusterer",
                gating_threshold=0.0 if method == "bcm" else "auto",
                combiner=method,
                max_beam_length=None,
                beam_end_length=None,
                hyperparameter_beam_length=None,
                piece_assignment="beam",
                max_pieces_per_cell=None,
                min_hit_frequency=None,
                n_jobs=n_jobs,
                random_state=random_state,
            )
    return models


def _score(grid, truth):
    """AUC and ROC curve of a map on the cells the scans observed."""
    proba = grid.probability.ravel()
    if proba.shape != truth.occupied.shape:
        raise ValueError(
            f"map grid {grid.shape} and true grid {truth.shape} differ; use the same extent "
            "and resolution."
        )
    labels = truth.occupied[truth.observed]
    scores = proba[truth.observed]
    fpr, tpr, _ = roc_curve(labels, scores)
    return float(roc_auc_score(labels, scores)), fpr, tpr


def run_paper_experiment(
    methods=tuple(METHODS),
    *,
    resolution=0.2,
    noise_std=0.0,
    single_hyperparameters="learn",
    random_state=0,
    n_jobs=None,
    verbose=0,
):
    """Fit and score the maps of the paper's simulation experiment.

    Simulates :func:`~skoccmap.datasets.make_paper_scans` (26 poses, 17 beams, about 700
    observations), fits each map (timed: clustering and hyperparameter learning included),
    evaluates it on the grid of cell centres at ``resolution`` over the environment (timed:
    probability and variance of every cell) and scores it by the ROC AUC against the true
    occupancy of the cells the scans observed.

    Parameters
    ----------
    methods : sequence of {"moe", "bcm", "single"}, default=("moe", "bcm", "single")
        Maps to fit, see :data:`METHODS`. ``"moe"`` and ``"bcm"`` are
        :class:`~skoccmap.MixtureGPOccupancyMap` with that combiner (same seed, so the same
        clusters and experts); ``"single"`` is one
        :class:`~skoccmap.EPGaussianProcessClassifier` with the experts' kernel.
    resolution : float, default=0.2
        Cell size of the map grid and of the true map, in metres.
    noise_std : float, default=0.0
        Range noise of the simulated scans, in metres.
    single_hyperparameters : {"learn", "from_mixture"}, default="learn"
        ``"learn"``: the single GP learns its hyperparameters, as in the paper.
        ``"from_mixture"``: it reuses the kernel learned by the first mixture fitted
        (fast; for smoke runs -- its fit time then excludes learning).
    random_state : int, default=0
        Seed of the range noise and of every estimator.
    n_jobs : int or None, default=None
        Parallel expert fits of the mixtures.
    verbose : int, default=0
        Print one progress line per step when > 0.

    Returns
    -------
    result : sklearn.utils.Bunch
        ``data`` (the simulated scans, see ``make_paper_scans``); ``truth`` (the true grid,
        ``Environment2D.ground_truth_grid`` with ``observed``); ``resolution``;
        ``methods``: dict name -> Bunch with ``name``, ``label``, ``model`` (fitted),
        ``grid`` (:class:`~skoccmap.OccupancyGrid` with variance), ``fit_s``, ``predict_s``,
        ``auc``, ``fpr``, ``tpr``; ``mixture``: the first fitted mixture (or None), whose
        clusters :func:`cluster_counts` tabulates.

    Examples
    --------
    >>> from skoccmap.experiment import run_paper_experiment
    >>> result = run_paper_experiment(["moe"], resolution=0.5)
    >>> bool(result.methods["moe"].auc > 0.9)
    True
    """
    from .datasets import make_paper_scans
    from .grid import OccupancyGrid

    methods = _check_methods(methods)
    resolution = _check_positive("resolution", resolution)
    if single_hyperparameters not in _SINGLE_HYPERPARAMETERS:
        raise ValueError(
            f"single_hyperparameters must be one of {_SINGLE_HYPERPARAMETERS}, got "
            f"{single_hyperparameters!r}."
        )
    if not isinstance(random_state, Integral):
        raise ValueError(f"random_state must be an int, got {random_state!r}.")
    data = make_paper_scans(noise_std=noise_std, random_state=random_state)
    n_hits = int(np.count_nonzero(data.y == 1))
    if n_hits < 2:
        # Before the fits, whose own refusal names an estimator's y the caller never saw.
        raise ValueError(
            f"the scans simulated with noise_std={noise_std:g} m hold {n_hits} hit(s): the "
            f"noise pushes the readings past the {data.scans.max_range:g} m range or to 0 "
            "(no measurement), and the maps need at least 2 hits. Use a smaller noise_std."
        )
    environment = data.environment
    truth = environment.ground_truth_grid(resolution, scans=data.scans)
    # Before any fit: a grid whose observed cells are all occupied (or all free) has no AUC.
    _check_both_classes(
        truth.occupied[truth.observed], f"observed cell of the true map at {resolution:g} m"
    )
    _progress(
        verbose,
        f"Simulated {len(data.scans)} scans x {data.scans.n_beams} beams: {len(data.X)} "
        f"observations; map grid {truth.shape[1]} x {truth.shape[0]} cells at {resolution:g} m.",
    )
    # The mixtures go first so that "from_mixture" can hand their kernel to the single GP.
    order = sorted(methods, key=lambda m: m == "single")
    results, mixture = {}, None
    for step, method in enumerate(order, start=1):
        single_kernel = None
        if method == "single" and single_hyperparameters == "from_mixture":
            single_kernel = _learned_kernel(mixture, data, random_state, n_jobs)
        model = make_models(
            [method], random_state=random_state, n_jobs=n_jobs, single_kernel=single_kernel
        )[method]
        _progress(verbose, f"[{step}/{len(order)}] {METHODS[method]}: fitting ...")
        with warnings.catch_warnings():
            # EP at the bounds of the signal variance may stop at max_iter; the map is
            # still scored, and the demo's output should stay a table.
            warnings.simplefilter("ignore", ConvergenceWarning)
            _, fit_s = _timed(model.fit, data.X, data.y)
            grid, predict_s = _timed(
                lambda m=model: OccupancyGrid.from_estimator(
                    m, extent=environment.extent, resolution=resolution
                )
            )
        auc, fpr, tpr = _score(grid, truth)
        _progress(
            verbose,
            f"[{step}/{len(order)}] {METHODS[method]}: fit {fit_s:.2f} s, map {predict_s:.2f} s,"
            f" AUC {auc:.4f}",
        )
        if mixture is None and method != "single":
            mixture = model
        results[method] = Bunch(
            name=method,
            label=METHODS[method],
            model=model,
            grid=grid,
            fit_s=fit_s,
            predict_s=predict_s,
            auc=auc,
            fpr=fpr,
            tpr=tpr,
        )
    return Bunch(
        data=data,
        truth=truth,
        resolution=resolution,
        methods={m: results[m] for m in methods},
        mixture=mixture,
    )


def _learned_kernel(mixture, data, random_state, n_jobs):
    """Kernel the single GP reuses under ``single_hyperparameters="from_mixture"``."""
    if mixture is None:
        # No mixture in this run: fit one for its kernel (not timed with the single GP).
        mixture = make_models(["moe"], random_state=random_state, n_jobs=n_jobs)["moe"]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            mixture.fit(data.X, data.y)
    kernel = getattr(mixture, "shared_kernel_", None)
    if kernel is None:
        kernel = next(e.kernel_ for e in mixture.experts_ if hasattr(e, "kernel_"))
    return kernel


def cluster_counts(model):
    """Observations of each kind per expert of a fitted mixture: the paper's Table 1.

    Parameters
    ----------
    model : fitted MixtureGPOccupancyMap

    Returns
    -------
    counts : ndarray of shape (n_experts, 3)
        Hits (H), return beams (R) and no-return beams (N) that each expert was fitted on.

    Examples
    --------
    >>> from skoccmap import MixtureGPOccupancyMap
    >>> from skoccmap.datasets import make_paper_scans
    >>> from skoccmap.experiment import cluster_counts
    >>> data = make_paper_scans()
    >>> model = MixtureGPOccupancyMap(random_state=0).fit(data.X, data.y)
    >>> counts = cluster_counts(model)
    >>> counts.sum(axis=0).tolist() == [int((data.kind == k).sum()) for k in range(3)]
    True
    """
    labels = getattr(model, "cluster_labels_", None)
    kinds = getattr(model, "observation_kind_", None)
    if labels is None or kinds is None:
        raise ValueError(
            "model must be a fitted MixtureGPOccupancyMap (with cluster_labels_ and "
            f"observation_kind_), got {type(model).__name__}."
        )
    counts = np.zeros((model.n_experts_, 3), dtype=np.int64)
    for column, kind in enumerate((HIT, RETURN, NO_RETURN)):
        counts[:, column] = np.bincount(labels[kinds == kind], minlength=model.n_experts_)
    return counts


def format_tables(result):
    """The paper's Table 1 (data per cluster), Table 2 (times) and the AUCs, as markdown.

    Parameters
    ----------
    result : Bunch
        Output of :func:`run_paper_experiment`.

    Returns
    -------
    text : str

    Examples
    --------
    >>> from skoccmap.experiment import format_tables, run_paper_experiment
    >>> text = format_tables(run_paper_experiment(["moe"], resolution=0.5))
    >>> "Table 1" in text and "Table 2" in text
    True
    """
    lines = []
    if result.mixture is not None:
        counts = cluster_counts(result.mixture)
        lines += [
            "Table 1: observations per cluster (H hits, R return beams, N no-return beams)",
            "",
            "| cluster | H | R | N | total |",
            "|---|---|---|---|---|",
        ]
        for k, (h, r, n) in enumerate(counts):
            lines.append(f"| {k + 1} | {h} | {r} | {n} | {h + r + n} |")
        h, r, n = counts.sum(axis=0)
        lines += [f"| all | {h} | {r} | {n} | {h + r + n} |", ""]
    lines += [
        "Table 2: learning and inference time, and AUC against the true map "
        f"({int(result.truth.observed.sum())} observed cells at {result.resolution:g} m)",
        "",
        "| method | learning s | inference s | AUC |",
        "|---|---|---|---|",
    ]
    for res in result.methods.values():
        lines.append(f"| {res.label} | {res.fit_s:.2f} | {res.predict_s:.2f} | {res.auc:.4f} |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------
# Figures (matplotlib imported lazily) and map files
# ---------------------------------------------------------------------------------------


def _new_figure(figsize):
    from matplotlib.figure import Figure

    # A bare Figure: no pyplot state, no GUI backend, nothing left open after saving.
    return Figure(figsize=figsize, layout="constrained")


def _axes_or_new(ax, figsize):
    """``ax`` if it is a matplotlib Axes, a new figure's when None; else a TypeError."""
    from matplotlib.axes import Axes

    if ax is None:
        return _new_figure(figsize).add_subplot()
    if not isinstance(ax, Axes):
        raise TypeError(f"ax must be a matplotlib Axes or None, got {ax!r}.")
    return ax


def _environment_axes(ax, environment):
    from matplotlib.collections import LineCollection

    ax.add_collection(
        LineCollection(environment.walls.reshape(-1, 2, 2), colors="k", linewidths=1.5)
    )
    xmin, xmax, ymin, ymax = environment.extent
    ax.set_xlim(xmin - 0.5, xmax + 0.5)
    ax.set_ylim(ymin - 0.5, ymax + 0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def plot_clusters(result, ax=None):
    """Figure 2 of the paper: the observations coloured by the expert that learns them.

    Parameters
    ----------
    result : Bunch
        Output of :func:`run_paper_experiment` with a mixture among its methods.
    ax : matplotlib Axes, default=None
        Where to draw; ``None`` makes a new figure.

    Returns
    -------
    ax : matplotlib Axes

    Examples
    --------
    >>> from skoccmap.experiment import plot_clusters, run_paper_experiment
    >>> ax = plot_clusters(run_paper_experiment(["moe"], resolution=0.5))
    >>> ax.get_title()
    'Observations by cluster'
    """
    from matplotlib import colormaps
    from matplotlib.collections import LineCollection

    model = result.mixture
    if model is None:
        raise ValueError("plot_clusters needs a result with a mixture ('moe' or 'bcm').")
    ax = _axes_or_new(ax, (8, 6.8))
    data = result.data
    _environment_axes(ax, data.environment)
    colors = colormaps["tab10" if model.n_experts_ <= 10 else "tab20"]
    labels = model.cluster_labels_
    beams = data.X.reshape(-1, 2, 2)
    is_hit = data.y == 1
    for k in range(model.n_experts_):
        color = colors(k % colors.N)
        rows = labels == k
        ax.add_collection(
            LineCollection(beams[rows & ~is_hit], colors=[color], linewidths=0.5, alpha=0.6)
        )
        hits = data.X[rows & is_hit]
        ax.plot(hits[:, 0], hits[:, 1], "o", color=color, ms=3, label=f"cluster {k + 1}")
    poses = data.scans.poses
    ax.plot(poses[:, 0], poses[:, 1], "k^", ms=4, label="poses")
    ax.legend(loc="upper left", fontsize="small", ncols=2)
    ax.set_title("Observations by cluster")
    return ax


def plot_maps(result, fig=None):
    """Figure 4 of the paper: each map's occupancy probability and uncertainty side by side.

    Parameters
    ----------
    result : Bunch
        Output of :func:`run_paper_experiment`.
    fig : matplotlib Figure, default=None
        Where to draw (one row of two panels per method); ``None`` makes a new figure.

    Returns
    -------
    fig : matplotlib Figure

    Examples
    --------
    >>> from skoccmap.experiment import plot_maps, run_paper_experiment
    >>> fig = plot_maps(run_paper_experiment(["moe"], resolution=0.5))
    >>> len(fig.axes) >= 2
    True
    """
    from matplotlib.figure import FigureBase

    from .plotting import OccupancyMapDisplay

    n_rows = len(result.methods)
    if fig is None:
        fig = _new_figure((11, 4.2 * n_rows))
    elif not isinstance(fig, FigureBase):
        raise TypeError(f"fig must be a matplotlib Figure or None, got {fig!r}.")
    axes = fig.subplots(n_rows, 2, squeeze=False)
    for row, res in zip(axes, result.methods.values(), strict=True):
        OccupancyMapDisplay.from_grid(res.grid, kind="both", ax=row)
        row[0].set_title(f"{res.label}: P(occupied)")
        row[1].set_title(f"{res.label}: std of P(occupied)")
    return fig


def plot_roc(result, ax=None):
    """Figure 5 of the paper: ROC curves of the maps against the true map.

    Parameters
    ----------
    result : Bunch
        Output of :func:`run_paper_experiment`.
    ax : matplotlib Axes, default=None
        Where to draw; ``None`` makes a new figure.

    Returns
    -------
    ax : matplotlib Axes

    Examples
    --------
    >>> from skoccmap.experiment import plot_roc, run_paper_experiment
    >>> ax = plot_roc(run_paper_experiment(["moe"], resolution=0.5))
    >>> len(ax.get_lines())
    2
    """
    ax = _axes_or_new(ax, (5.5, 5))
    for res in result.methods.values():
        ax.plot(res.fpr, res.tpr, label=f"{res.label} (AUC {res.auc:.3f})")
    ax.plot([0, 1], [0, 1], ":", color="gray")
    ax.set_xlabel("false positive rate")
    ax.set_ylabel("true positive rate")
    ax.set_title("ROC against the true map")
    ax.legend(loc="lower right")
    ax.set_aspect("equal")
    return ax


def save_figures(result, out, *, dpi=110):
    """Write Figures 2, 4 and 5 as PNG files into ``out``.

    Parameters
    ----------
    result : Bunch
        Output of :func:`run_paper_experiment`.
    out : str or path-like
        Folder, created if missing.
    dpi : float, default=110
        Resolution of the images, in (0, 1200].

    Returns
    -------
    paths : list of pathlib.Path

    Raises
    ------
    ImportError
        When matplotlib is not installed (``pip install "skoccmap[plot]"``).
    TypeError, ValueError
        For a ``dpi`` that is no number, or not in (0, 1200], before ``out`` is made.

    Examples
    --------
    >>> import tempfile
    >>> from skoccmap.experiment import run_paper_experiment, save_figures
    >>> result = run_paper_experiment(["moe"], resolution=0.5)
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     [p.name for p in save_figures(result, tmp)]
    ['figure2_clusters.png', 'figure4_maps.png', 'figure5_roc.png']
    """
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        raise ImportError(
            'Figures need matplotlib: pip install "skoccmap[plot]" (or pip install matplotlib).'
        ) from exc
    # Checked before the folder is made: matplotlib's own refusal comes after it, and a
    # dpi of 1e6 is a C++ bad_alloc.
    if not is_number(dpi):
        raise TypeError(f"dpi must be a number, got {dpi!r}.")
    if not 0 < dpi <= _MAX_DPI:
        raise ValueError(f"dpi must be in (0, {_MAX_DPI}], got {dpi!r}.")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figures = []
    if result.mixture is not None:
        figures.append(("figure2_clusters.png", plot_clusters(result).figure))
    figures += [
        ("figure4_maps.png", plot_maps(result)),
        ("figure5_roc.png", plot_roc(result).figure),
    ]
    paths = []
    for name, fig in figures:
        fig.savefig(out / name, dpi=dpi)
        paths.append(out / name)
    return paths


def save_maps(result, out):
    """Write each map as a ROS ``map_server`` PGM + YAML pair, ``map_<method>.{pgm,yaml}``.

    Parameters
    ----------
    result : Bunch
        Output of :func:`run_paper_experiment`.
    out : str or path-like
        Folder, created if missing.

    Returns
    -------
    paths : list of pathlib.Path
        The YAML files, one per method (each names its PGM image).

    Examples
    --------
    >>> import tempfile
    >>> from skoccmap.experiment import run_paper_experiment, save_maps
    >>> result = run_paper_experiment(["moe"], resolution=0.5)
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     [p.name for p in save_maps(result, tmp)]
    ['map_moe.yaml']
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return [
        res.grid.save_map_server(out / f"map_{name}")[0] for name, res in result.methods.items()
    ]


# ---------------------------------------------------------------------------------------
# Beams as points: the input of point-based baselines
# ---------------------------------------------------------------------------------------


def points_along_beams(X, y, spacing=0.2):
    """Cut free segments into points every ``spacing`` metres; keep occupied rows as points.

    The way GP occupancy maps were fitted before the integral kernel: a beam becomes free
    points at ``0, spacing, 2 * spacing, ...`` metres from its start, up to its end.

    Parameters
    ----------
    X : array-like of shape (n_samples, 2 * D)
        Segment rows ``[start, end]``.
    y : array-like of shape (n_samples,)
        1 (occupied: the row's start point is kept) or 0 (free: the segment is cut).
    spacing : float, default=0.2
        Distance between consecutive points along a beam, in metres.

    Returns
    -------
    points : ndarray of shape (n_points, D)
        Occupied points first, then the free points beam by beam.
    labels : ndarray of shape (n_points,)
        1 for occupied, 0 for free points.

    Examples
    --------
    >>> from skoccmap.experiment import points_along_beams
    >>> points, labels = points_along_beams([[0, 0, 0.5, 0], [0.6, 0, 0.6, 0]], [0, 1])
    >>> points.tolist(), labels.tolist()
    ([[0.6, 0.0], [0.0, 0.0], [0.2, 0.0], [0.4, 0.0]], [1, 0, 0, 0])
    """
    from ._validation import check_segments, segment_dim

    X = check_segments(X, name="X")
    y = np.asarray(y)
    if y.shape != (X.shape[0],):
        raise ValueError(f"y must have shape ({X.shape[0]},), got {y.shape}.")
    if not np.all(np.isin(y, (0, 1))):
        raise ValueError("y must hold 0 (free) and 1 (occupied) only.")
    spacing = _check_positive("spacing", spacing)
    d = segment_dim(X)
    start, end = X[y == 0, :d], X[y == 0, d:]
    length = np.linalg.norm(end - start, axis=1)
    n_float = np.floor(length / spacing + 1e-9) + 1
    # Past the largest array index the count wrapped to a negative number, and numpy
    # stopped on "negative dimensions are not allowed" (as split_segments refuses).
    if n_float.sum() > np.iinfo(np.intp).max:
        raise ValueError(
            f"Points every spacing={spacing:g} m along the beams are {n_float.sum():.3g} "
            f"points, more than an array can hold (the longest beam is {length.max():.3g} m "
            "long): pass a larger spacing."
        )
    n_per_beam = n_float.astype(np.int64)
    beam = np.repeat(np.arange(start.shape[0]), n_per_beam)
    # Position of each point within its beam: 0, 1, 2, ... restarted at every beam.
    step = np.arange(beam.size) - np.repeat(np.cumsum(n_per_beam) - n_per_beam, n_per_beam)
    safe = np.where(length > 0, length, 1.0)[:, None]
    unit = (end - start) / safe
    free = start[beam] + (step * spacing)[:, None] * unit[beam]
    occupied = X[y == 1, :d]
    points = np.concatenate([occupied, free])
    labels = np.r_[np.ones(len(occupied), np.int64), np.zeros(len(free), np.int64)]
    return points, labels
