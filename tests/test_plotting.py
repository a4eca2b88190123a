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
    # matplotlib's "'str' object has no attribute 'imshow'", after a figure was made.
    for stray in ("foo", 3, [None]):
        with pytest.raises(TypeError, match="ax must hold matplotlib Axes, got"):
            disp.plot(ax=stray)
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
    # Heights whose layer number overflows (an OverflowError from int() before).
    for z in (1e308, -1e308, np.float64(1e308)):
        with pytest.raises(ValueError, match="outside"):
            OccupancyMapDisplay.from_grid(grid, z=z)
    # Not a number (numpy's ufunc TypeError, or int() of an array, before).
    for z in ("1.5", np.array([1.5]), True, np.array("1.5")):
        with pytest.raises(TypeError, match="z must be a height"):
            OccupancyMapDisplay.from_grid(grid, z=z)
    # A 0-d array is a number.
    a = OccupancyMapDisplay.from_grid(grid, z=np.array(1.5)).probability
    np.testing.assert_array_equal(a, OccupancyMapDisplay.from_grid(grid, z=1.5).probability)


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


@pytest.mark.parametrize("z, k", [(1.2, 7), (1.4, 8), (-0.2, 0), (1.1999, 6)])
def test_3d_slice_at_a_layers_lower_face_is_that_layer(z, k):
    # Layers of 0.2 m from -0.2 m: 1.2 m is the lower face of layer 7, though
    # (1.2 + 0.2) / 0.2 rounds to 6.999...
    rng = np.random.default_rng(3)
    grid = OccupancyGrid(rng.uniform(size=(10, 2, 3)), (0.0, 0.0, -0.2), 0.2)
    disp = OccupancyMapDisplay.from_grid(grid, z=z)
    np.testing.assert_allclose(disp.im_.get_array(), grid.probability[k])


def test_3d_slice_at_the_grids_lower_face_rounded_below_it_is_the_bottom_layer():
    # 0.1 + 0.2 is 0.30000000000000004: z = 0.3 is the grid's lower face, a rounding below.
    rng = np.random.default_rng(4)
    grid = OccupancyGrid(rng.uniform(size=(3, 2, 2)), (0.0, 0.0, 0.1 + 0.2), 0.1)
    disp = OccupancyMapDisplay.from_grid(grid, z=0.3)
    np.testing.assert_allclose(disp.im_.get_array(), grid.probability[0])
    with pytest.raises(ValueError, match="outside the grid's height range"):
        OccupancyMapDisplay.from_grid(grid, z=0.29)


def test_3d_default_slice_is_the_layer_holding_the_mid_height():
    # An even number of layers: four of 1 m from z = 0. The grid's mid-height, 2 m, is the
    # bottom of layer 2 (layers span [k, k + 1)): the default slice is the layer asking for
    # that height draws, not layer 1 below it.
    rng = np.random.default_rng(4)
    grid = OccupancyGrid(rng.uniform(size=(4, 2, 3)), (0.0, 0.0, 0.0), 1.0)
    zmin, zmax = grid.extent[4:]
    default = OccupancyMapDisplay.from_grid(grid)
    asked = OccupancyMapDisplay.from_grid(grid, z=(zmin + zmax) / 2)
    np.testing.assert_allclose(default.im_.get_array(), asked.im_.get_array())
    np.testing.assert_allclose(default.im_.get_array(), grid.probability[2])
    assert default.ax_.get_title() == asked.ax_.get_title() == "P(occupied), slice at z = 2.50 m"


def test_every_panel_has_square_cells_and_axes_in_metres():
    # A metre is as long along x as along y on every panel, so the walls keep their angles,
    # even under a style whose images fill their axes.
    with matplotlib.rc_context({"image.aspect": "auto"}):
        disp = OccupancyMapDisplay.from_grid(_grid())
    for ax in disp.axes_:
        assert ax.get_aspect() == 1.0
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("x [m]", "y [m]")


def test_poses_overlay_as_their_positions():
    # The robot's path as poses (x, y, heading): the heading column is not drawn.
    grid = _grid()
    poses = np.array([[1.2, -0.8, 0.0], [2.5, 0.1, 1.5], [1.9, -0.3, -3.0]])
    disp = OccupancyMapDisplay.from_grid(grid, kind="probability", points=poses)
    (scatter,) = disp.ax_.collections
    np.testing.assert_allclose(scatter.get_offsets(), poses[:, :2])


def _rendered(fig):
    """The figure rendered: RGB per pixel, row 0 at the top."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3] / 255.0


def _colours_at(rgb, ax, extent, shape, at):
    """Colour of ``rgb`` at fractions ``at = (fx, fy)`` across each cell of a map on ``ax``."""
    xmin, xmax, ymin, ymax = extent
    ny, nx = shape
    dx, dy = (xmax - xmin) / nx, (ymax - ymin) / ny
    out = np.empty((ny, nx, 3))
    for i in range(ny):
        for j in range(nx):
            px, py = ax.transData.transform((xmin + (j + at[0]) * dx, ymin + (i + at[1]) * dy))
            out[i, j] = rgb[int(rgb.shape[0] - py), int(px)]
    return out


def test_rendered_map_occupied_dark_row_0_at_the_bottom_and_unknown_in_its_colour():
    # A map drawn as pixels: each cell one flat colour (no smoothing across cells), its
    # grey level 1 - P(occupied) (occupied black, free white), row 0 at the lowest y, and
    # the unknown cell in the unknown colour on both panels.
    p = np.array([[0.0, 1.0, 0.25], [0.9, 0.0, 0.6]])
    variance = np.array([[0.5, 2.0, 0.1], [1.0, 0.0, 0.5]])
    unknown = np.zeros(p.shape, dtype=bool)
    unknown[0, 0] = True
    extent = (2.0, 5.0, -1.0, 1.0)
    fig, axes = plt.subplots(1, 2, figsize=(8, 3), dpi=40)
    OccupancyMapDisplay(p, extent=extent, variance=variance, unknown=unknown).plot(
        ax=axes, colorbar=False, unknown_color="red"
    )
    rgb = _rendered(fig)
    grey = np.repeat((1.0 - p)[..., None], 3, axis=-1)
    std_rgb = matplotlib.colormaps["viridis"](probability_std(p, variance) / 0.5)[..., :3]
    known = ~unknown
    for at in [(0.5, 0.5), (0.15, 0.5), (0.85, 0.5), (0.5, 0.15)]:
        for ax, expected in zip(axes, [grey, std_rgb], strict=True):
            shown = _colours_at(rgb, ax, extent, p.shape, at)
            np.testing.assert_allclose(shown[known], expected[known], atol=0.02)
            np.testing.assert_allclose(shown[unknown], [[1.0, 0.0, 0.0]], atol=0.02)


def test_legend_shows_the_colour_unknown_cells_are_drawn_in():
    p = np.full((2, 3), 0.5)
    unknown = np.zeros(p.shape, dtype=bool)
    disp = OccupancyMapDisplay(p, extent=(0, 3, 0, 2), unknown=unknown).plot()
    assert disp.ax_.get_legend() is None  # no unknown cell: nothing to name
    unknown[1, 1] = True
    disp = OccupancyMapDisplay(p, extent=(0, 3, 0, 2), unknown=unknown).plot(
        unknown_color="tab:orange"
    )
    (patch,) = disp.ax_.get_legend().get_patches()
    orange = matplotlib.colors.to_rgba("tab:orange")
    np.testing.assert_allclose(patch.get_facecolor(), orange)
    masked = disp.im_.to_rgba(disp.im_.get_array())
    np.testing.assert_allclose(masked[1, 1], orange)


def test_cmap_argument_is_used():
    p = np.array([[0.0, 1.0]])
    disp = OccupancyMapDisplay(p, extent=(0, 2, 0, 1)).plot(cmap="viridis")
    np.testing.assert_allclose(
        disp.im_.to_rgba(p), matplotlib.colormaps["viridis"]([0.0, 1.0])[None]
    )


def test_3d_grid_slices_every_panel_at_the_same_layer():
    # Five layers of 0.5 m from z = 1: the default is the middle one (layer 2, centre 2.25 m);
    # probability, std and unknown cells all come from the layer drawn.
    rng = np.random.default_rng(3)
    shape = (5, 2, 3)
    probability = rng.uniform(0.05, 0.95, size=shape)
    variance = rng.uniform(0.1, 3.0, size=shape)
    unknown = rng.uniform(size=shape) < 0.3
    grid = OccupancyGrid(probability, (0.0, 0.0, 1.0), 0.5, variance=variance, unknown=unknown)
    for z, k in [(None, 2), (1.2, 0), (3.4, 4)]:
        disp = OccupancyMapDisplay.from_grid(grid, z=z)
        std = disp.images_[1].get_array()
        np.testing.assert_allclose(disp.im_.get_array().data, probability[k])
        np.testing.assert_allclose(std.data, probability_std(probability[k], variance[k]))
        for image in disp.images_:
            np.testing.assert_array_equal(np.ma.getmaskarray(image.get_array()), unknown[k])
        height = 1.0 + (k + 0.5) * 0.5
        assert [a.get_title() for a in disp.axes_] == [
            f"P(occupied), slice at z = {height:.2f} m",
            f"std of P(occupied), slice at z = {height:.2f} m",
        ]
    # The grid spans z in [1, 3.5): a height on either side of it has no layer.
    for z in (0.9, 3.5):
        with pytest.raises(ValueError, match="outside"):
            OccupancyMapDisplay.from_grid(grid, z=z)


def test_points_are_overlaid_on_every_panel_with_the_given_style():
    grid = _grid()
    points = np.array([[1.2, -0.8], [2.5, 0.1], [1.9, -0.3]])
    disp = OccupancyMapDisplay.from_grid(grid, points=points, colorbar=False)
    for ax in disp.axes_:
        (scatter,) = ax.collections
        np.testing.assert_allclose(scatter.get_offsets(), points)
    disp = OccupancyMapDisplay.from_grid(
        grid, kind="probability", points=points, point_kwargs={"s": 9, "c": "blue"}
    )
    (scatter,) = disp.ax_.collections
    np.testing.assert_allclose(scatter.get_sizes(), [9])
    np.testing.assert_allclose(scatter.get_facecolors(), [matplotlib.colors.to_rgba("blue")])


def test_colorbar_one_per_panel_labelled_or_none():
    grid = _grid()
    disp = OccupancyMapDisplay.from_grid(grid, colorbar=False)
    assert len(disp.figure_.axes) == 2
    disp = OccupancyMapDisplay.from_grid(grid)
    bars = [a for a in disp.figure_.axes if a not in list(disp.axes_)]
    assert sorted(a.get_ylabel() for a in bars) == ["P(occupied)", "std of P(occupied)"]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(probability=np.full((2, 3), 1.5)), r"values in \[0, 1\]"),
        (dict(probability=np.full((2, 3), -0.1)), r"values in \[0, 1\]"),
        (dict(probability=np.full((2, 3, 3), 0.5)), "2-D"),
        (dict(extent=(3.0, 0.0, 0.0, 2.0)), "extent"),
        (dict(extent=(0.0, 3.0, 2.0, 0.0)), "extent"),
        (dict(extent=(0.0, np.inf, 0.0, 2.0)), "extent"),
        # A map of no width or no height has no cell to draw.
        (dict(extent=(1.0, 1.0, 0.0, 2.0)), "extent"),
        (dict(extent=(0.0, 3.0, 2.0, 2.0)), "extent"),
    ],
)
def test_values_and_extents_a_map_cannot_have(kwargs, match):
    # A probability outside [0, 1] has no colour on the fixed scale; a (ny, nx, 3) array
    # would be drawn as RGB; a reversed extent mirrors the map.
    args = dict(probability=np.full((2, 3), 0.5), extent=(0.0, 3.0, 0.0, 2.0)) | kwargs
    disp = OccupancyMapDisplay(args.pop("probability"), **args)
    with pytest.raises(ValueError, match=match):
        disp.plot(kind="probability")


def test_boundary_values_are_drawn():
    # Certain cells (P = 0 or 1), zero variance, and no variance for unknown cells are valid.
    p = np.array([[0.0, 1.0, 0.5]])
    variance = np.array([[0.0, 0.0, np.nan]])
    unknown = np.array([[False, False, True]])
    disp = OccupancyMapDisplay(p, extent=(0, 3, 0, 1), variance=variance, unknown=unknown)
    disp.plot(kind="variance")
    np.testing.assert_allclose(disp.im_.get_array()[0, :2], [0.0, 0.0])
    assert disp.im_.get_array().mask.tolist() == [[False, False, True]]


def test_std_panel_of_a_map_without_values_in_its_unknown_cells():
    # NaN probability and variance in cells marked unknown are accepted (no value to draw):
    # the std panel used to pass them to probability_std, which refused them.
    p = np.array([[0.2, np.nan, 0.9], [0.5, 0.7, np.nan]])
    variance = np.array([[1.0, np.nan, 0.3], [0.0, 2.0, np.nan]])
    unknown = np.isnan(p)
    disp = OccupancyMapDisplay(p, extent=(0, 3, 0, 2), variance=variance, unknown=unknown)
    disp.plot(kind="both")
    shown = disp.images_[1].get_array()
    np.testing.assert_array_equal(np.ma.getmaskarray(shown), unknown)
    known = ~unknown
    np.testing.assert_allclose(shown[known], probability_std(p[known], variance[known]))
