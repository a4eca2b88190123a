import sys

import numpy as np
import pytest

from skoccmap import OccupancyGrid
from skoccmap.baselines import OccupancyGridMap
from skoccmap.plotting import OccupancyMapDisplay
from skoccmap.uncertainty import probability_std

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


class _WithVar:
    def predict_proba(self, X):
        p = 1.0 / (1.0 + np.exp(-X[:, 0]))
        return np.column_stack([1 - p, p])

    def predict_var(self, X):
        return np.abs(X[:, 1])


def _grid():
    rng = np.random.default_rng(0)
    return OccupancyGrid(
        rng.uniform(size=(3, 4)),
        (1.0, -1.0),
        0.5,
        variance=rng.uniform(size=(3, 4)),
        unknown=np.eye(3, 4, dtype=bool),
    )


def test_from_grid_both_panels():
    grid = _grid()
    disp = OccupancyMapDisplay.from_grid(grid)
    assert len(disp.axes_) == 2 and disp.ax_ is disp.axes_[0]
    assert disp.figure_ is disp.ax_.figure
    shown = disp.im_.get_array()
    # row 0 is drawn at the bottom (origin="lower") over the grid's extent
    assert disp.im_.origin == "lower"
    np.testing.assert_allclose(disp.im_.get_extent(), grid.extent)
    np.testing.assert_array_equal(np.ma.getmaskarray(shown), grid.unknown)
    np.testing.assert_allclose(shown.data, grid.probability)
    # The second panel is the std of P(occupied), on a fixed [0, 1/2] scale.
    std = probability_std(grid.probability, grid.variance)
    np.testing.assert_allclose(disp.images_[1].get_array().data, std)
    assert disp.images_[1].get_clim() == (0.0, 0.5)
    assert disp.axes_[1].get_title() == "std of P(occupied)"
    # Unknown cells are unknown on both panels (the std panel drew them as confident), and
    # the probability panel's legend names their colour.
    np.testing.assert_array_equal(np.ma.getmaskarray(disp.images_[1].get_array()), grid.unknown)
    legend = disp.ax_.get_legend()
    assert [t.get_text() for t in legend.get_texts()] == ["unknown"]
    plain = OccupancyMapDisplay(probability=grid.probability, extent=grid.extent).plot()
    assert plain.ax_.get_legend() is None
    # The latent variance stays available.
    disp = OccupancyMapDisplay.from_grid(grid, kind="variance")
    np.testing.assert_allclose(disp.im_.get_array(), grid.variance)
    assert disp.ax_.get_title() == "predictive variance"


def test_from_estimator_and_user_axes():
    fig, (a, b) = plt.subplots(1, 2)
    disp = OccupancyMapDisplay.from_estimator(
        _WithVar(), (-1.0, 1.0, -1.0, 1.0), 0.5, ax=[a, b], colorbar=False, points=[[0, 0]]
    )
    assert disp.ax_ is a and disp.axes_[1] is b and disp.figure_ is fig
    centers_x = -1.0 + 0.5 * (np.arange(4) + 0.5)
    expected = np.tile(1.0 / (1.0 + np.exp(-centers_x)), (4, 1))
    np.testing.assert_allclose(np.ma.getdata(disp.im_.get_array()), expected)
    assert len(a.collections) == 1  # the overlaid points


def test_from_estimator_draws_cells_no_beam_saw_as_unknown():
    from skoccmap.observations import Scans

    # One beam along +x from (-0.75, -0.75): the bottom row of cells, the rest unseen.
    scans = Scans([[-0.75, -0.75, 0.0]], [[np.inf]], [0.0], max_range=1.5)
    disp = OccupancyMapDisplay.from_estimator(
        _WithVar(),
        (-1.0, 1.0, -1.0, 1.0),
        0.5,
        kind="probability",
        unknown_variance=None,
        observed_by=scans,
    )
    expected = np.ones((4, 4), dtype=bool)
    expected[0, :] = False
    np.testing.assert_array_equal(np.ma.getmaskarray(disp.im_.get_array()), expected)


def test_probability_only_for_estimators_without_variance():
    X = np.array([[0.0, 0.0, 0.95, 0.0], [1.0, 0.0, 1.0, 0.0]])
    est = OccupancyGridMap(resolution=0.5).fit(X, [0, 1])
    disp = OccupancyMapDisplay.from_estimator(est)
    assert len(disp.axes_) == 1
    with pytest.raises(ValueError, match="needs a variance"):
        OccupancyMapDisplay.from_estimator(est, kind="variance")


def test_plot_on_constructed_display_and_errors():
    grid = _grid()
    disp = OccupancyMapDisplay(grid.probability, extent=grid.extent)
    _, ax = plt.subplots()
    assert disp.plot(ax=ax).ax_ is ax
    with pytest.raises(ValueError, match="kind"):
        disp.plot(kind="heat")
    with pytest.raises(ValueError, match="2 Axes"):
        OccupancyMapDisplay.from_grid(grid, ax=ax)
    with pytest.raises(ValueError, match="OccupancyGrid"):
        OccupancyMapDisplay.from_grid(grid.probability)
    with pytest.raises(ValueError, match="3-D grid; this grid is 2-D"):
        OccupancyMapDisplay.from_grid(grid, z=5.0)
    with pytest.raises(ValueError, match=r"points must have shape \(m, 2\)"):
        disp.plot(points=[0.0, 3.0])
    # Panels that do not match the probability, and values a map cannot hold.
    p = grid.probability
    bad = [
        (dict(variance=np.ones((2, 2))), "variance must have the probability's shape"),
        (dict(unknown=np.zeros(3, dtype=bool)), "unknown must have the probability's shape"),
        (dict(variance=-np.ones(p.shape)), "variance must hold values >= 0"),
    ]
    for kwargs, match in bad:
        with pytest.raises(ValueError, match=match):
            OccupancyMapDisplay(p, extent=grid.extent, **kwargs).plot(ax=ax, kind="probability")
    with pytest.raises(ValueError, match=r"values in \[0, 1\] \(no NaN\) in the known cells"):
        OccupancyMapDisplay(np.full(p.shape, np.nan), extent=grid.extent).plot(ax=ax)
    with pytest.raises(ValueError, match="extent must be"):
        OccupancyMapDisplay(p, extent=(0, 1, 0)).plot(ax=ax)
    # NaN in cells marked unknown is no value to draw: fine.
    unknown = np.zeros(p.shape, dtype=bool)
    unknown[0, 0] = True
    holed = p.copy()
    holed[0, 0] = np.nan
    OccupancyMapDisplay(holed, extent=grid.extent, unknown=unknown).plot(ax=ax)


def test_3d_grid_draws_a_slice():
    rng = np.random.default_rng(1)
    grid = OccupancyGrid(rng.uniform(size=(3, 2, 4)), (0.0, 0.0, 0.0), 1.0)
    disp = OccupancyMapDisplay.from_grid(grid, z=2.5)
    np.testing.assert_allclose(disp.im_.get_array(), grid.probability[2])
    assert disp.ax_.get_title() == "P(occupied), slice at z = 2.50 m"
    with pytest.raises(ValueError, match="outside"):
        OccupancyMapDisplay.from_grid(grid, z=7.0)
    with pytest.raises(ValueError, match="finite height"):
        OccupancyMapDisplay.from_grid(grid, z=np.nan)


def test_clear_error_without_matplotlib(monkeypatch):
    grid = _grid()
    disp = OccupancyMapDisplay(grid.probability, extent=grid.extent)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    with pytest.raises(ImportError, match=r"skoccmap\[plot\]"):
        disp.plot()


def test_import_does_not_load_matplotlib():
    import subprocess

    code = "import sys, skoccmap.plotting, skoccmap.grid; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_every_panel_is_drawn_the_same_way_up_over_the_same_extent():
    # A map whose top row alone is occupied: on every panel the top of the picture is the
    # largest y, over the grid's extent, and probabilities keep the fixed [0, 1] scale.
    probability = np.array([[0.2, 0.3], [0.4, 0.5], [0.9, 0.95]])
    grid = OccupancyGrid(probability, (1.0, -1.0), 0.5, variance=np.full((3, 2), 0.3))
    disp = OccupancyMapDisplay.from_grid(grid)
    assert disp.ax_.get_ylim()[1] > disp.ax_.get_ylim()[0]
    for image in disp.images_:
        assert image.origin == "lower"
        np.testing.assert_allclose(image.get_extent(), (1.0, 2.0, -1.0, 0.5))
    assert disp.im_.get_clim() == (0.0, 1.0)


@pytest.mark.parametrize("z, k", [(2.0, 2), (2.9, 2), (1.999, 1), (0.0, 0)])
def test_3d_slice_is_the_layer_holding_z(z, k):
    # Layer k spans [k, k + 1) m: z = 2.9 lies in layer 2 (not the nearest centre's 3).
    rng = np.random.default_rng(2)
    grid = OccupancyGrid(rng.uniform(size=(4, 2, 3)), (0.0, 0.0, 0.0), 1.0)
    disp = OccupancyMapDisplay.from_grid(grid, z=z)
    np.testing.assert_allclose(disp.im_.get_array(), grid.probability[k])
    assert disp.ax_.get_title() == f"P(occupied), slice at z = {k + 0.5:.2f} m"
