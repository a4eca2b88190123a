import functools
import sys
import time
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from numpy.testing import assert_allclose
from sklearn.exceptions import ConvergenceWarning
from sklearn.metrics import auc as trapezoid_auc

from skoccmap import OccupancyGrid
from skoccmap.baselines import OccupancyGridMap
from skoccmap.datasets import make_paper_scans
from skoccmap.experiment import (
    METHODS,
    cluster_counts,
    format_tables,
    make_models,
    plot_clusters,
    plot_maps,
    plot_roc,
    points_along_beams,
    run_paper_experiment,
    save_figures,
    save_maps,
)
from skoccmap.metrics import ground_truth_auc
from skoccmap.observations import HIT, NO_RETURN, RETURN
from skoccmap.uncertainty import probability_std


def _distance_to_observations(grid, X):
    """Distance from each cell centre of a 2-D grid to the nearest segment row of ``X``."""
    ny, nx = grid.shape
    xs = grid.origin[0] + (np.arange(nx) + 0.5) * grid.resolution
    ys = grid.origin[1] + (np.arange(ny) + 0.5) * grid.resolution
    cells = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 1, 2)
    a, d = X[:, :2], X[:, 2:] - X[:, :2]
    dd = np.einsum("ij,ij->i", d, d)
    t = np.einsum("cij,ij->ci", cells - a, d) / np.where(dd > 0, dd, 1.0)
    nearest = a + np.clip(t, 0.0, 1.0)[..., None] * d
    return np.linalg.norm(cells - nearest, axis=-1).min(axis=1).reshape(grid.shape)


@pytest.fixture(scope="module")
def result():
    # A coarse grid and the single GP on the mixture's kernel keep this to a few seconds.
    # The single GP is listed first: the mixture must still be fitted first to hand it its
    # kernel, and the result keeps the order asked for.
    return run_paper_experiment(
        ["single", "moe"], resolution=0.5, single_hyperparameters="from_mixture"
    )


class _SlowGridMap(OccupancyGridMap):
    """A counting grid that takes at least 50 ms to fit and 20 ms to predict."""

    def fit(self, X, y):
        time.sleep(0.05)
        return super().fit(X, y)

    def predict_proba(self, X):
        time.sleep(0.02)
        return super().predict_proba(X)


@pytest.fixture
def fast_models(monkeypatch):
    """Cheap stand-ins for the paper's models (a counting grid), and the calls building them."""
    calls = []

    def make_fast_models(methods, **kwargs):
        calls.append((list(methods), kwargs))
        return {m: _SlowGridMap(resolution=0.5) for m in methods}

    monkeypatch.setattr("skoccmap.experiment.make_models", make_fast_models)
    return calls


# ---------------------------------------------------------------------------------------
# points_along_beams
# ---------------------------------------------------------------------------------------


def test_points_along_beams_against_a_loop():
    rng = np.random.default_rng(0)
    starts = rng.uniform(-5, 5, size=(30, 2))
    ends = starts + rng.uniform(-3, 3, size=(30, 2))
    hits = rng.uniform(-5, 5, size=(7, 2))
    X = np.vstack([np.hstack([starts, ends]), np.hstack([hits, hits])])
    y = np.r_[np.zeros(30, int), np.ones(7, int)]
    spacing = 0.3
    points, labels = points_along_beams(X, y, spacing)

    expected = [hits]
    for a, b in zip(starts, ends, strict=True):
        length = np.hypot(*(b - a))
        t = 0.0
        while t <= length + 1e-9:
            expected.append((a + t * (b - a) / length)[None])
            t += spacing
    expected = np.vstack(expected)
    assert_allclose(points, expected, atol=1e-9)
    assert labels.tolist() == [1] * 7 + [0] * (len(expected) - 7)


def test_points_along_beams_keeps_the_start_of_occupied_rows():
    # As documented: an occupied row's start point is kept (a hit row is [hit, hit]).
    points, labels = points_along_beams([[1.0, 2.0, 3.0, 4.0], [0, 0, 0.3, 0.4]], [1, 0], 0.25)
    assert_allclose(points, [[1, 2], [0, 0], [0.15, 0.2], [0.3, 0.4]])
    assert labels.tolist() == [1, 0, 0, 0]


def test_points_along_beams_zero_length_free_row_and_3d():
    X = [[1.0, 2.0, 3.0, 1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]]
    points, labels = points_along_beams(X, [0, 0], spacing=0.5)
    assert_allclose(points, [[1, 2, 3], [0, 0, 0], [0, 0, 0.5], [0, 0, 1.0]])
    assert labels.tolist() == [0, 0, 0, 0]


@pytest.mark.parametrize(
    "X, y, spacing, match",
    [
        ([[0.0, 0.0, np.nan, 1.0]], [0], 0.2, "NaN"),
        ([[0.0, 0.0, 1.0]], [0], 0.2, "even number of columns"),
        ([[0.0, 0.0, 1.0, 1.0]], [0, 1], 0.2, "y must have shape"),
        ([[0.0, 0.0, 1.0, 1.0]], [2], 0.2, "0 \\(free\\) and 1"),
        ([[0.0, 0.0, 1.0, 1.0]], [0], 0.0, "spacing"),
        ([[0.0, 0.0, 1.0, 1.0]], [0], np.nan, "spacing"),
        ([[0.0, 0.0, 1.0, 1.0]], [0], np.inf, "spacing"),
        (np.empty((0, 4)), [], 0.2, "no rows"),
        # More points than an array holds ("negative dimensions are not allowed" before).
        ([[0.0, 0.0, 1.0, 1.0]], [0], 1e-300, "more than an array can hold"),
        ([[0.0, 0.0, 1e20, 0.0], [0.0, 0.0, 1e20, 0.0]], [0, 0], 1e1, "larger spacing"),
    ],
)
def test_points_along_beams_bad_input(X, y, spacing, match):
    with pytest.raises(ValueError, match=match):
        points_along_beams(X, y, spacing)


# ---------------------------------------------------------------------------------------
# run_paper_experiment
# ---------------------------------------------------------------------------------------


def test_result_layout_and_scores(result):
    assert list(result.methods) == ["single", "moe"]
    truth = result.truth
    data = make_paper_scans(random_state=0)
    assert_allclose(result.data.X, data.X)
    for name, res in result.methods.items():
        assert res.label == METHODS[name]
        assert res.grid.shape == truth.shape
        assert res.grid.variance is not None and res.fit_s > 0 and res.predict_s > 0
        # The stored AUC equals an independent evaluation: the fitted model predicted at the
        # observed cells of the true map by skoccmap.metrics.
        expected = ground_truth_auc(res.model, data.environment, 0.5, scans=data.scans)
        assert res.auc == pytest.approx(expected, abs=1e-9)
        assert res.auc > 0.9
        # The ROC curve runs from (0, 0) to (1, 1), monotone, with the AUC as its area.
        assert (res.fpr[0], res.tpr[0], res.fpr[-1], res.tpr[-1]) == (0, 0, 1, 1)
        assert np.all(np.diff(res.fpr) >= 0) and np.all(np.diff(res.tpr) >= 0)
        assert trapezoid_auc(res.fpr, res.tpr) == pytest.approx(res.auc, abs=1e-9)
        # Unknown cells are those far from all data, by geometry: the distance from each cell
        # centre to the nearest beam or hit is computed here, apart from any variance.
        unknown = res.grid.unknown
        assert unknown.any() and not unknown.all()
        distance = _distance_to_observations(res.grid, data.X)
        # Measured with the learned l = 1.63 m: unknown cells are at least 0.74 l from all
        # data, known cells at most 1.68 l; the bounds leave a margin on both sides.
        length_scale = result.mixture.shared_kernel_.k2.length_scale
        assert not unknown[distance < 0.6 * length_scale].any()
        assert unknown[distance > 2.0 * length_scale].all()
        assert (distance > 2.0 * length_scale).any()
    assert result.mixture is result.methods["moe"].model


def test_single_gp_reuses_the_mixture_kernel(result):
    single = result.methods["single"].model
    assert single.optimizer is None
    assert single.kernel_.get_params() == result.mixture.shared_kernel_.get_params()
    # The kernel of the mixture in the result (fitted before the single GP though listed
    # after it), not of another mixture fitted for the purpose.
    assert single.kernel is result.mixture.shared_kernel_


def test_single_gp_alone_takes_the_kernel_a_mixture_learns(monkeypatch):
    # Without a mixture among the methods one is fitted for its kernel (on a small world
    # here), and the result still has none.
    small = functools.partial(make_paper_scans, n_beams=5, n_poses_per_piece=2)
    monkeypatch.setattr("skoccmap.datasets.make_paper_scans", small)
    result = run_paper_experiment(
        ["single"], resolution=1.0, single_hyperparameters="from_mixture"
    )
    assert result.mixture is None and list(result.methods) == ["single"]
    single = result.methods["single"].model
    initial = make_models(["single"])["single"].kernel
    assert single.optimizer is None
    assert single.kernel.k2.length_scale != initial.k2.length_scale  # learned
    assert result.methods["single"].auc > 0.8


def test_run_paper_experiment_passes_its_options_on(fast_models, capsys):
    # The paper's models replaced by a counting grid: what run_paper_experiment does around
    # them, fast.
    result = run_paper_experiment(
        ["single", "moe", "bcm"], resolution=0.5, noise_std=0.05, random_state=4, n_jobs=2,
        verbose=1,
    )  # fmt: skip
    data = make_paper_scans(noise_std=0.05, random_state=4)
    assert_allclose(result.data.X, data.X)
    assert not np.allclose(result.data.X, make_paper_scans(random_state=4).X)
    # Mixtures first, each model built with the experiment's seed and jobs.
    assert [(m, kw["random_state"], kw["n_jobs"]) for m, kw in fast_models] == [
        (["moe"], 4, 2),
        (["bcm"], 4, 2),
        (["single"], 4, 2),
    ]
    # The result keeps the order asked for; its mixture is the first fitted.
    assert list(result.methods) == ["single", "moe", "bcm"]
    assert result.mixture is result.methods["moe"].model
    # The times measured take in the work.
    for res in result.methods.values():
        assert res.fit_s >= 0.05 and res.predict_s >= 0.02
    # One progress line per step on stdout, numbered from 1, with the AUC found.
    out = capsys.readouterr().out.splitlines()
    ny, nx = result.truth.shape
    assert f"{len(data.X)} observations; map grid {nx} x {ny} cells at 0.5 m" in out[0]
    for step, method in enumerate(["moe", "bcm", "single"], start=1):
        assert out[2 * step - 1] == f"[{step}/3] {METHODS[method]}: fitting ..."
        assert out[2 * step].startswith(f"[{step}/3] {METHODS[method]}: fit ")
        assert out[2 * step].endswith(f"AUC {result.methods[method].auc:.4f}")
    assert len(out) == 7
    run_paper_experiment(["moe"], resolution=0.5)
    assert capsys.readouterr().out == ""


def test_one_class_truth_is_refused_before_any_fit(fast_models):
    # At 5 m every observed cell touches a wall.
    with pytest.raises(ValueError, match="the AUC is undefined"):
        run_paper_experiment(["moe"], resolution=5.0)
    assert fast_models == []


def test_moe_and_bcm_share_clusters_and_differ_in_merging():
    models = make_models(["moe", "bcm", "single"], random_state=3)
    assert models["moe"].combiner == "moe" and models["bcm"].combiner == "bcm"
    assert [m.random_state for m in models.values()] == [3, 3, 3]
    # Same parameters but how they merge (the committee machine multiplies every expert
    # within reach: see test_committee_machine_has_no_seam), so the same clusters and
    # experts; estimators compared by their own parameters.
    merging = ("combiner", "gating_threshold")
    params = [
        {k: repr(v) for k, v in m.get_params().items() if k not in merging}
        for m in (models["moe"], models["bcm"])
    ]
    assert params[0] == params[1]
    # The paper's model: whole beams, hyperparameters learned on them too, experts gated by
    # the clusters of hits; the mixture weighs only the experts its gate keeps.
    moe = models["moe"]
    assert moe.max_beam_length is None and moe.beam_end_length is None
    assert moe.hyperparameter_beam_length is None
    assert moe.gating == "clusterer" and moe.gating_threshold != 0


def test_experts_are_fitted_on_their_clusters_whole_observations(result):
    # The paper's model: each expert learns exactly the observations of its cluster (those
    # cluster_counts tabulates), whole beams and every hit, none cut, thinned or moved.
    model, data = result.mixture, result.data
    assert not model.transient_hits_.any()
    for k, expert in enumerate(model.experts_):
        rows = model.cluster_labels_ == k
        expected = np.column_stack([data.X[rows], data.y[rows]])
        fitted = np.column_stack([expert.X_train_, expert.y_train_ > 0])
        assert_allclose(np.unique(fitted, axis=0), np.unique(expected, axis=0))
        assert len(fitted) == rows.sum()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"methods": ["moe", "gp"]}, "methods"),
        ({"methods": []}, "methods"),
        ({"methods": ["moe", "moe"]}, "methods"),
        ({"resolution": 0.0}, "resolution"),
        ({"resolution": np.inf}, "resolution"),
        ({"resolution": "0.5"}, "resolution"),
        ({"single_hyperparameters": "fixed"}, "single_hyperparameters"),
        ({"random_state": None}, "random_state"),
        # No hit left by the noise: said in the experiment's terms, not the mixture's y.
        ({"methods": ["moe"], "noise_std": 1e3}, r"noise_std=1000 m hold 0 hit"),
        ({"methods": ["single"], "noise_std": 1e3}, r"Use a smaller noise_std"),
    ],
)
def test_run_paper_experiment_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        run_paper_experiment(**kwargs)


# ---------------------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------------------


def test_cluster_counts_cover_every_observation(result):
    model, data = result.mixture, result.data
    counts = cluster_counts(model)
    assert counts.shape == (model.n_experts_, 3)
    expected = [np.sum(data.kind == k) for k in (HIT, RETURN, NO_RETURN)]
    assert counts.sum(axis=0).tolist() == expected
    assert counts.sum(axis=1).tolist() == np.bincount(model.cluster_labels_).tolist()
    with pytest.raises(ValueError, match="fitted MixtureGPOccupancyMap"):
        cluster_counts(result.methods["single"].model)


def test_paper_model_keeps_repeated_beams_and_a_rare_hit():
    # A wall at x = 2 seen from x = 0 by 5 beams, the middle beam's path 7 more times and,
    # once, a passer-by at x = 1 on it. The paper's model keeps every observation: repeated
    # beams are not thinned, the rare hit is not left out as transient.
    rows, labels = [], []
    for y in (-1.0, -0.5, 0.0, 0.5, 1.0, *[0.0] * 7):
        rows += [[0.0, y, 1.95, y], [2.0, y, 2.0, y]]
        labels += [0, 1]
    rows += [[0.0, 0.0, 0.95, 0.0], [1.0, 0.0, 1.0, 0.0]]
    labels += [0, 1]
    X, y = np.array(rows), np.array(labels)
    model = make_models(["moe"], random_state=0)["moe"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model.fit(X, y)
    assert not model.transient_hits_.any()
    fitted = np.vstack([np.column_stack([e.X_train_, e.y_train_ > 0]) for e in model.experts_])
    assert_allclose(np.unique(fitted, axis=0), np.unique(np.column_stack([X, y]), axis=0))
    assert len(fitted) == len(X)


def test_cluster_counts_of_a_hand_built_mixture():
    # Three experts; the last fitted on one hit only (no beam of either kind).
    model = SimpleNamespace(
        n_experts_=3,
        cluster_labels_=np.array([0, 0, 1, 0, 1, 1, 2]),
        observation_kind_=np.array([HIT, RETURN, NO_RETURN, NO_RETURN, HIT, RETURN, HIT]),
    )
    assert cluster_counts(model).tolist() == [[1, 1, 1], [1, 1, 1], [1, 0, 0]]
    model.observation_kind_ = np.array([HIT, RETURN, RETURN, NO_RETURN, RETURN, HIT, HIT])
    assert cluster_counts(model).tolist() == [[1, 1, 1], [1, 2, 0], [1, 0, 0]]


def test_format_tables(result):
    text = format_tables(result)
    data = result.data
    h, r, n = (int(np.sum(data.kind == k)) for k in (HIT, RETURN, NO_RETURN))
    assert f"| all | {h} | {r} | {n} | {h + r + n} |" in text
    for k, row in enumerate(cluster_counts(result.mixture)):
        assert f"| {k + 1} | {row[0]} | {row[1]} | {row[2]} | {row.sum()} |" in text
    for res in result.methods.values():
        assert f"| {res.label} | {res.fit_s:.2f} | {res.predict_s:.2f} | {res.auc:.4f} |" in text
    assert f"{int(result.truth.observed.sum())} observed cells at 0.5 m" in text


def test_format_tables_without_mixture(result):
    only_single = type(result)(**{**result, "mixture": None})
    only_single.methods = {"single": result.methods["single"]}
    text = format_tables(only_single)
    assert "Table 1" not in text and "| single GP |" in text


# ---------------------------------------------------------------------------------------
# Files and figures
# ---------------------------------------------------------------------------------------


def test_save_maps_round_trip(result, tmp_path):
    paths = save_maps(result, tmp_path / "maps")
    assert [p.name for p in paths] == ["map_single.yaml", "map_moe.yaml"]
    for path, res in zip(paths, result.methods.values(), strict=True):
        assert path.with_suffix(".pgm").is_file()
        back = OccupancyGrid.load_map_server(path)
        assert back.shape == res.grid.shape
        assert_allclose(back.origin, res.grid.origin)
        np.testing.assert_array_equal(back.trinary(), res.grid.trinary())


def test_figures(result, tmp_path):
    pytest.importorskip("matplotlib")
    ax = plot_roc(result)
    # One curve per method plus the chance diagonal.
    assert len(ax.get_lines()) == len(result.methods) + 1
    fig = plot_maps(result)
    images = [im for a in fig.axes for im in a.get_images()]
    assert len(images) == 2 * len(result.methods)
    ax = plot_clusters(result)
    # One marker line per expert plus the poses.
    assert len(ax.get_lines()) == result.mixture.n_experts_ + 1
    paths = save_figures(result, tmp_path, dpi=20)
    assert [p.name for p in paths] == [
        "figure2_clusters.png",
        "figure4_maps.png",
        "figure5_roc.png",
    ]
    for path in paths:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # At the dpi asked for: width and height in the PNG header are inches times dpi.
    header = (tmp_path / "figure5_roc.png").read_bytes()
    size = [int.from_bytes(header[16:20], "big"), int.from_bytes(header[20:24], "big")]
    assert size == (plot_roc(result).figure.get_size_inches() * 20).round().tolist()


def test_figures_show_the_result(result):
    pytest.importorskip("matplotlib")
    from matplotlib.colors import to_rgba

    data, model = result.data, result.mixture
    # Figure 2: each cluster's hits, in its own colour, numbered as in Table 1; the poses.
    ax = plot_clusters(result)
    lines = ax.get_lines()
    n = model.n_experts_
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert texts == [f"cluster {k + 1}" for k in range(n)] + ["poses"]
    for k, line in enumerate(lines[:n]):
        hits = data.X[(model.cluster_labels_ == k) & (data.y == 1), :2]
        assert_allclose(line.get_xydata(), hits)
    assert len({to_rgba(line.get_color()) for line in lines[:n]}) == n
    assert_allclose(lines[n].get_xydata(), data.scans.poses[:, :2])
    xmin, xmax, ymin, ymax = data.environment.extent
    assert ax.get_xlim()[0] < xmin and ax.get_xlim()[1] > xmax
    assert ax.get_ylim()[0] < ymin and ax.get_ylim()[1] > ymax
    # Figure 4: a row per method, its probability then its std.
    fig = plot_maps(result)
    panels = [a for a in fig.axes if a.get_images()]
    assert len(panels) == 2 * len(result.methods)
    for row, res in enumerate(result.methods.values()):
        prob_ax, std_ax = panels[2 * row], panels[2 * row + 1]
        assert prob_ax.get_title() == f"{res.label}: P(occupied)"
        assert std_ax.get_title() == f"{res.label}: std of P(occupied)"
        grid = res.grid
        assert_allclose(prob_ax.get_images()[0].get_array().data, grid.probability)
        std = probability_std(grid.probability, grid.variance)
        assert_allclose(std_ax.get_images()[0].get_array().data, std)
    # Figure 5: false positive rate across, true positive rate up, the AUC in the legend.
    ax = plot_roc(result)
    for line, res in zip(ax.get_lines(), result.methods.values(), strict=False):
        assert_allclose(line.get_xdata(), res.fpr)
        assert_allclose(line.get_ydata(), res.tpr)
        assert line.get_label() == f"{res.label} (AUC {res.auc:.3f})"


def test_plot_clusters_needs_a_mixture(result, tmp_path):
    pytest.importorskip("matplotlib")
    no_mixture = type(result)(**{**result, "mixture": None})
    with pytest.raises(ValueError, match="mixture"):
        plot_clusters(no_mixture)
    # save_figures then leaves Figure 2 out.
    paths = save_figures(no_mixture, tmp_path, dpi=10)
    assert [p.name for p in paths] == ["figure4_maps.png", "figure5_roc.png"]


def test_figure_functions_refuse_what_is_no_axes_figure_or_dpi(result, tmp_path):
    pytest.importorskip("matplotlib")
    # Before: AttributeErrors from inside the drawing ('str' object has no attribute ...).
    for plot in (plot_clusters, plot_roc):
        with pytest.raises(TypeError, match="ax must be a matplotlib Axes or None, got 'x'"):
            plot(result, ax="x")
    with pytest.raises(TypeError, match="fig must be a matplotlib Figure or None, got 'x'"):
        plot_maps(result, fig="x")
    # Before: matplotlib's TypeError ("x") and a C++ bad_alloc (1e6), after the folder was made.
    out = tmp_path / "figures"
    for dpi in ("x", True, None):
        with pytest.raises(TypeError, match="dpi must be a number"):
            save_figures(result, out, dpi=dpi)
    for dpi in (0, -5, 1201, 1e6, float("nan")):
        with pytest.raises(ValueError, match=r"dpi must be in \(0, 1200\]"):
            save_figures(result, out, dpi=dpi)
    assert not out.exists()


def test_save_figures_without_matplotlib(result, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(ImportError, match=r"skoccmap\[plot\]"):
        save_figures(result, tmp_path)
    assert not list(tmp_path.iterdir())


def _largest_lone_step(p, axis):
    """Largest step between neighbouring cells minus the larger of the steps either side
    of it: a wall is a ramp of several steps, a seam one step alone."""
    steps = np.moveaxis(np.abs(np.diff(p, axis=axis)), axis, 0)
    return float((steps[1:-1] - np.maximum(steps[:-2], steps[2:])).max())


def test_committee_machine_has_no_seam():
    # It used to skip the experts that the clusters' gate weighs below 1e-3, and its
    # product jumped where they dropped out: one step of 0.24 among steps below 0.01
    # (the demo's Figure 4). Every expert within reach now takes part.
    data = make_paper_scans(random_state=0)
    model = make_models(["bcm"], random_state=0)["bcm"]
    assert model.gating_threshold == 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model.fit(data.X, data.y)
    x, y = np.meshgrid(np.arange(0.0, 22.0, 0.05), np.arange(0.0, 18.0, 0.05))
    points = np.column_stack([x.ravel(), y.ravel()])
    p = model.predict_proba(np.hstack([points, points]))[:, 1].reshape(x.shape)
    # Measured 0.016 across y and 0.078 across x; 0.24 and 0.25 with the gate's cut.
    assert max(_largest_lone_step(p, 0), _largest_lone_step(p, 1)) < 0.12
