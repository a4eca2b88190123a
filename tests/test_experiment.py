import sys
import warnings

import numpy as np
import pytest
from numpy.testing import assert_allclose
from sklearn.exceptions import ConvergenceWarning
from sklearn.metrics import auc as trapezoid_auc

from skoccmap import OccupancyGrid
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
    return run_paper_experiment(
        ["moe", "single"], resolution=0.5, single_hyperparameters="from_mixture"
    )


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
        (np.empty((0, 4)), [], 0.2, "no rows"),
    ],
)
def test_points_along_beams_bad_input(X, y, spacing, match):
    with pytest.raises(ValueError, match=match):
        points_along_beams(X, y, spacing)


# ---------------------------------------------------------------------------------------
# run_paper_experiment
# ---------------------------------------------------------------------------------------


def test_result_layout_and_scores(result):
    assert list(result.methods) == ["moe", "single"]
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


def test_moe_and_bcm_share_clusters_and_differ_in_merging():
    models = make_models(["moe", "bcm"], random_state=3)
    assert models["moe"].combiner == "moe" and models["bcm"].combiner == "bcm"
    # Same parameters but how they merge (the committee machine multiplies every expert
    # within reach: see test_committee_machine_has_no_seam), so the same clusters and
    # experts; estimators compared by their own parameters.
    merging = ("combiner", "gating_threshold")
    params = [
        {k: repr(v) for k, v in m.get_params().items() if k not in merging}
        for m in (models["moe"], models["bcm"])
    ]
    assert params[0] == params[1]
    # The paper's model: whole beams.
    assert models["moe"].max_beam_length is None and models["moe"].beam_end_length is None


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"methods": ["moe", "gp"]}, "methods"),
        ({"methods": []}, "methods"),
        ({"methods": ["moe", "moe"]}, "methods"),
        ({"resolution": 0.0}, "resolution"),
        ({"resolution": np.inf}, "resolution"),
        ({"single_hyperparameters": "fixed"}, "single_hyperparameters"),
        ({"random_state": None}, "random_state"),
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
    assert [p.name for p in paths] == ["map_moe.yaml", "map_single.yaml"]
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
    paths = save_figures(result, tmp_path)
    assert [p.name for p in paths] == [
        "figure2_clusters.png",
        "figure4_maps.png",
        "figure5_roc.png",
    ]
    for path in paths:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plot_clusters_needs_a_mixture(result):
    pytest.importorskip("matplotlib")
    no_mixture = type(result)(**{**result, "mixture": None})
    with pytest.raises(ValueError, match="mixture"):
        plot_clusters(no_mixture)


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
