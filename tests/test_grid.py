import re
import warnings

import numpy as np
import pytest

from skoccmap import MixtureGPOccupancyMap, OccupancyGrid
from skoccmap.baselines import OccupancyGridMap


class _ProbaOnly:
    """An estimator without predict_var."""

    def predict_proba(self, X):
        return _FieldEstimator().predict_proba(X)


class _FieldEstimator:
    """P(occupied) and variance as known functions of the query point; records batch sizes."""

    def __init__(self):
        self.batches = []

    @staticmethod
    def proba_at(points):
        return 1.0 / (1.0 + np.exp(-(points[:, 0] - 2.0 * points[:, 1])))

    @staticmethod
    def var_at(points):
        return np.hypot(points[:, 0], points[:, 1])

    def predict_proba(self, X):
        X = np.asarray(X)
        self.batches.append(len(X))
        n_dims = X.shape[1] // 2
        assert np.array_equal(X[:, :n_dims], X[:, n_dims:]), "queries must be points"
        p = self.proba_at(X[:, :n_dims])
        return np.column_stack([1 - p, p])

    def predict_var(self, X):
        X = np.asarray(X)
        return self.var_at(X[:, : X.shape[1] // 2])


def test_from_estimator_matches_direct_evaluation():
    est = _FieldEstimator()
    grid = OccupancyGrid.from_estimator(
        est, extent=(-1.0, 2.0, 0.5, 1.5), resolution=0.25, chunk_size=5, unknown_variance=None
    )
    assert grid.shape == (4, 12)
    xs = -1.0 + 0.25 * (np.arange(12) + 0.5)
    ys = 0.5 + 0.25 * (np.arange(4) + 0.5)
    gx, gy = np.meshgrid(xs, ys)  # row j <-> y_j, column i <-> x_i
    points = np.column_stack([gx.ravel(), gy.ravel()])
    np.testing.assert_allclose(grid.probability, est.proba_at(points).reshape(4, 12))
    np.testing.assert_allclose(grid.variance, est.var_at(points).reshape(4, 12))
    assert max(est.batches) <= 5 and sum(est.batches) == 48
    assert grid.unknown is None
    assert grid.extent == (-1.0, 2.0, 0.5, 1.5)
    np.testing.assert_allclose(grid.cell_centers(), points)


class _JointEstimator(_FieldEstimator):
    """Offers probability and variance in one call; the separate methods must not be used."""

    def predict_proba(self, X):
        raise AssertionError("the grid called predict_proba despite _predict_proba_and_var")

    def predict_var(self, X):
        raise AssertionError("the grid called predict_var despite _predict_proba_and_var")

    def _predict_proba_and_var(self, X):
        X = np.asarray(X)
        self.batches.append(len(X))
        points = X[:, : X.shape[1] // 2]
        return self.proba_at(points), self.var_at(points)


def test_from_estimator_uses_joint_prediction_once_per_chunk():
    field, joint = _FieldEstimator(), _JointEstimator()
    kwargs = dict(extent=(-1.0, 2.0, 0.5, 1.5), resolution=0.25, chunk_size=7)
    expected = OccupancyGrid.from_estimator(field, **kwargs)
    grid = OccupancyGrid.from_estimator(joint, **kwargs)
    assert joint.batches == field.batches  # one call per chunk, no second pass
    np.testing.assert_array_equal(grid.probability, expected.probability)
    np.testing.assert_array_equal(grid.variance, expected.variance)
    np.testing.assert_array_equal(grid.unknown, expected.unknown)


def test_extent_from_data_is_snapped_and_covers_it():
    points = np.array([[0.23, -0.61], [1.07, 0.44]])
    grid = OccupancyGrid.from_estimator(_FieldEstimator(), points, resolution=0.2)
    np.testing.assert_allclose(grid.origin, [0.2, -0.8])
    xmin, xmax, ymin, ymax = grid.extent
    assert xmin <= 0.23 and xmax > 1.07 and ymin <= -0.61 and ymax > 0.44
    assert grid.shape == (7, 5)
    # segment rows: both end points are covered
    segments = np.array([[0.0, 0.0, 1.0, 1.0]])
    grid = OccupancyGrid.from_estimator(_FieldEstimator(), segments, resolution=0.5)
    assert grid.shape == (3, 3)


def test_extent_from_estimator_attribute():
    X = np.array([[0.0, 0.0, 0.95, 0.0], [1.0, 0.0, 1.0, 0.0]])
    est = OccupancyGridMap(resolution=0.5).fit(X, [0, 1])
    grid = OccupancyGrid.from_estimator(est, resolution=0.5)
    assert grid.extent == tuple(est.extent_)
    np.testing.assert_allclose(grid.probability, [[0.4013, 0.5, 0.7006]], atol=1e-4)
    with pytest.raises(ValueError, match="extent_"):
        OccupancyGrid.from_estimator(_FieldEstimator(), resolution=0.5)


def test_unknown_variance_rules():
    est = _FieldEstimator()
    extent = (0.0, 4.0, 0.0, 4.0)
    auto = OccupancyGrid.from_estimator(est, extent, 1.0)
    np.testing.assert_array_equal(auto.unknown, auto.variance > 0.9 * auto.variance.max())
    assert 0 < auto.unknown.sum() < auto.unknown.size
    fixed = OccupancyGrid.from_estimator(est, extent, 1.0, unknown_variance=2.0)
    np.testing.assert_array_equal(fixed.unknown, fixed.variance > 2.0)
    assert 0 < fixed.unknown.sum() < fixed.unknown.size
    no_var = OccupancyGrid.from_estimator(_ProbaOnly(), extent, 1.0)
    assert no_var.variance is None and no_var.unknown is None


def test_auto_unknown_is_relative_to_the_prior_variance():
    # On a map whose every cell some beam saw, no cell comes near the prior variance: the
    # grid's own largest variance (a well-observed cell's) must not set the threshold.
    class WithPrior(_FieldEstimator):
        def __init__(self, prior):
            super().__init__()
            self.prior = prior

        def prior_variance(self, X):
            return np.full(len(X), self.prior)

    extent = (0.0, 4.0, 0.0, 4.0)  # variances up to hypot(3.5, 3.5) = 4.95
    seen = OccupancyGrid.from_estimator(WithPrior(100.0), extent, 1.0)
    assert not seen.unknown.any()
    near = OccupancyGrid.from_estimator(WithPrior(5.0), extent, 1.0)
    np.testing.assert_array_equal(near.unknown, near.variance > 4.5)
    assert 0 < near.unknown.sum()
    # A prior below the grid's largest variance never lowers the threshold.
    low = OccupancyGrid.from_estimator(WithPrior(1.0), extent, 1.0)
    np.testing.assert_array_equal(low.unknown, low.variance > 0.9 * low.variance.max())


def test_cells_no_beam_observed_are_unknown():
    from skoccmap.observations import Scans

    # One scan from (0.5, 0.5) looking along +x: a beam hitting at x = 2.5 and a no-return
    # beam along +y up to 2 m.
    scans = Scans([[0.5, 0.5, 0.0]], [[2.0, np.inf]], [0.0, np.pi / 2], max_range=2.0)
    extent = (0.0, 4.0, 0.0, 4.0)
    grid = OccupancyGrid.from_estimator(
        _ProbaOnly(), extent, 1.0, unknown_variance=None, observed_by=scans
    )
    # Cells [y, x]: the beam's row y = 0 up to the hit cell x = 2, the column x = 0 up to
    # y = 2; everything else (behind the hit, away from the beams) is unknown.
    observed = np.zeros((4, 4), bool)
    observed[0, :3] = True
    observed[:3, 0] = True
    np.testing.assert_array_equal(grid.unknown, ~observed)
    # Combined with the variance rule.
    both = OccupancyGrid.from_estimator(_FieldEstimator(), extent, 1.0, observed_by=scans)
    var_only = OccupancyGrid.from_estimator(_FieldEstimator(), extent, 1.0)
    np.testing.assert_array_equal(both.unknown, var_only.unknown | ~observed)
    with pytest.raises(ValueError, match="observed_by"):
        OccupancyGrid.from_estimator(_ProbaOnly(), extent, 1.0, observed_by=np.zeros((2, 4)))
    # A third beam, along the diagonal, reads 0 (no measurement): it observes nothing.
    with_zero = Scans([[0.5, 0.5, 0.0]], [[2.0, np.inf, 0.0]], [0.0, np.pi / 2, np.pi / 4],
                      max_range=2.0)  # fmt: skip
    grid = OccupancyGrid.from_estimator(
        _ProbaOnly(), extent, 1.0, unknown_variance=None, observed_by=with_zero
    )
    np.testing.assert_array_equal(grid.unknown, ~observed)


def test_no_return_beams_count_up_to_the_first_cell_holding_a_hit():
    from skoccmap.datasets._simulator import _observed_cells
    from skoccmap.observations import Scans

    # A return beam hits at x = 2.5; a no-return beam beside it runs on through the hit's
    # cell to the maximum range (x = 4.0): it saw nothing beyond that cell.
    scans = Scans([[0.5, 0.5, 0.0]], [[2.0, np.inf]], [0.0, 0.01], max_range=3.5)
    grid = OccupancyGrid.from_estimator(
        _ProbaOnly(), (0.0, 5.0, 0.0, 1.0), 1.0, unknown_variance=None, observed_by=scans
    )
    np.testing.assert_array_equal(grid.unknown[0], [False, False, False, True, True])
    # A hit in the sensor's own cell (a wall beside the robot, on a coarse grid) does not
    # stop the beams leaving that cell.
    beside = Scans([[0.5, 0.5, 0.0]], [[0.3, np.inf]], [0.0, np.pi / 2], max_range=3.0)
    grid = OccupancyGrid.from_estimator(
        _ProbaOnly(), (0.0, 1.0, 0.0, 4.0), 1.0, unknown_variance=None, observed_by=beside
    )
    np.testing.assert_array_equal(grid.unknown[:, 0], [False, False, False, False])
    # The simulated worlds' scoring counts whole beams (they cannot cross a wall there).
    whole = _observed_cells(scans, np.zeros(2), 1.0, np.array([5, 1]))
    np.testing.assert_array_equal(whole, [True, True, True, True, False])


def test_verbose_reports_progress(capsys):
    OccupancyGrid.from_estimator(_FieldEstimator(), (0, 1, 0, 1), 0.1, chunk_size=10, verbose=1)
    err = capsys.readouterr().err
    assert "100/100 cells (100%)" in err and err.count("[OccupancyGrid]") >= 5
    # Every line but the last says how long the rest will take.
    lines = err.strip().splitlines()
    assert all(re.search(r" s, about \d+ s left$", line) for line in lines[:-1])
    assert "left" not in lines[-1]


def test_durations_read_as_a_person_would():
    from skoccmap.grid import _duration

    assert [_duration(s) for s in (0.4, 89, 90, 3569, 3600, 7500)] == [
        "0 s",
        "89 s",
        "2 min",
        "59 min",
        "1 h 0 min",
        "2 h 5 min",
    ]


def test_ros_layout_starts_at_origin_row():
    probability = np.array([[0.0, 0.1, 0.2], [0.9, 0.95, 1.0]])  # row 0 = lowest y
    unknown = np.array([[False, False, True], [False, False, False]])
    grid = OccupancyGrid(probability, origin=(1.0, -2.0), resolution=0.5, unknown=unknown)
    msg = grid.to_ros_occupancy_grid()
    assert msg["info"]["width"] == 3 and msg["info"]["height"] == 2
    assert msg["info"]["origin"]["position"] == {"x": 1.0, "y": -2.0, "z": 0.0}
    assert msg["data"].dtype == np.int8
    np.testing.assert_array_equal(msg["data"], [0, 10, -1, 90, 95, 100])
    tri = grid.to_ros_occupancy_grid(trinary=True)["data"]
    np.testing.assert_array_equal(tri, [0, 0, -1, 100, 100, 100])


def _read_pgm_independently(path):
    """Minimal reader for the header this package writes: 'P5\\nW H\\n255\\n' + bytes."""
    raw = path.read_bytes()
    magic, size, maxval, rest = raw.split(b"\n", 3)
    width, height = map(int, size.split())
    assert magic == b"P5" and maxval == b"255"
    return np.frombuffer(rest, dtype=np.uint8).reshape(height, width)


def test_map_server_round_trip_reproduces_trinary_map(tmp_path):
    rng = np.random.default_rng(0)
    probability = rng.uniform(size=(37, 53))
    unknown = rng.uniform(size=(37, 53)) < 0.1
    grid = OccupancyGrid(probability, origin=(-3.2, 7.5), resolution=0.05, unknown=unknown)
    yaml_path, pgm_path = grid.save_map_server(tmp_path / "map")
    text = yaml_path.read_text()
    for line in (
        "image: map.pgm",
        "negate: 0",
        "free_thresh: 0.196",
        "occupied_thresh: 0.65",
        "mode: trinary",
        "origin: [-3.2, 7.5, 0.0]",
        "resolution: 0.05",
    ):
        assert line in text.splitlines()
    pixels = _read_pgm_independently(pgm_path)
    assert pixels.shape == (37, 53)
    assert set(np.unique(pixels)) <= {0, 205, 254}
    # Image rows run top (largest y) to bottom: the last image row is grid row 0.
    expected = np.where(probability > 0.65, 0, np.where(probability < 0.196, 254, 205))
    expected[unknown] = 205
    np.testing.assert_array_equal(pixels[::-1], expected)
    # map_server's reading of trinary pixels with the YAML thresholds
    occ = (255.0 - pixels[::-1]) / 255.0
    as_ros = np.where(occ > 0.65, 100, np.where(occ < 0.196, 0, -1))
    np.testing.assert_array_equal(as_ros, grid.trinary())
    back = OccupancyGrid.load_map_server(yaml_path)
    np.testing.assert_array_equal(back.trinary(), grid.trinary())
    np.testing.assert_allclose(back.origin, grid.origin)
    assert back.resolution == grid.resolution
    # The stem that saved it loads it too.
    by_stem = OccupancyGrid.load_map_server(yaml_path.with_suffix(""))
    np.testing.assert_array_equal(by_stem.trinary(), grid.trinary())


def test_trinary_thresholds_are_strict_as_map_servers():
    # map_server marks a cell occupied above occupied_thresh and free below free_thresh.
    grid = OccupancyGrid(np.array([[0.196, 0.65, 0.1959, 0.6501]]), np.zeros(2), 0.1)
    np.testing.assert_array_equal(grid.trinary(), [[-1, -1, 0, 100]])


def test_hand_made_map_server_files(tmp_path):
    # Pixels [0, 100, 128, 200, 230, 255] under thresholds 0.5 / 0.25, as map_server reads
    # them: occupancy (255 - v) / 255 = 1, 0.61, 0.50, 0.22, 0.10, 0.
    (tmp_path / "sub").mkdir()
    pixels = bytes([0, 100, 128, 200, 230, 255])
    (tmp_path / "sub" / "img.pgm").write_bytes(b"P5\n6 1\n255\n" + pixels)
    meta = "image: sub/img.pgm\nresolution: 0.05\norigin: [-10, -5, 0]\nnegate: 0\n"
    (tmp_path / "m.yaml").write_text(meta + "occupied_thresh: 0.5\nfree_thresh: 0.25\n")
    grid = OccupancyGrid.load_map_server(tmp_path / "m.yaml")
    np.testing.assert_array_equal(grid.trinary(0.25, 0.5), [[100, 100, -1, 0, 0, 0]])
    # An image of maxval 1 is scaled as image readers do: pixel 1 is white, free.
    (tmp_path / "bits.pgm").write_bytes(b"P5\n2 1\n1\n" + bytes([0, 1]))
    (tmp_path / "bits.yaml").write_text("image: bits.pgm\nresolution: 1\norigin: [0, 0, 0]\n")
    np.testing.assert_array_equal(
        OccupancyGrid.load_map_server(tmp_path / "bits.yaml").trinary(), [[100, 0]]
    )
    for line, message in (("mode: fancy", "mode 'fancy'"), ("origin: [0, 0, 1.57]", "yaw")):
        bad = tmp_path / "bad.yaml"
        bad.write_text("image: bits.pgm\nresolution: 1\norigin: [0, 0, 0]\n" + line + "\n")
        if line.startswith("origin"):
            bad.write_text("image: bits.pgm\nresolution: 1\n" + line + "\n")
        with pytest.raises(ValueError, match=message):
            OccupancyGrid.load_map_server(bad)


@pytest.mark.parametrize(
    "line, message",
    [
        # float() of a list: "float() argument must be ... not 'list'"
        ("resolution: [1, 2]", r"resolution must be a number, got \[1.0, 2.0\]"),
        ("resolution: fine", "resolution must be a number, got 'fine'"),
        # int("1.0") failed unnamed; 2 was read as negated
        ("negate: 1.0", r"negate must be 0 or 1 \(or true or false\), got '1.0'"),
        ("negate: 2", r"negate must be 0 or 1 \(or true or false\), got '2'"),
        # read, with free cells above the occupied threshold
        ("occupied_thresh: 0.1", "need 0 <= free_thresh <= occupied_thresh <= 1"),
        ("free_thresh: high", "free_thresh must be a number"),
        # "could not convert string to float: 'c'", and ": ''"
        ("origin: abc", "origin must be a list"),
        ("origin: [a, b]", "cannot read 'origin' as a list of numbers"),
    ],
)
def test_malformed_map_server_yaml_names_the_key(tmp_path, line, message):
    (tmp_path / "bits.pgm").write_bytes(b"P5\n2 1\n1\n" + bytes([0, 1]))
    good = {"image": "bits.pgm", "resolution": "1", "origin": "[0, 0, 0]"}
    key = line.split(":")[0]
    text = "".join(f"{k}: {v}\n" for k, v in good.items() if k != key) + line + "\n"
    (tmp_path / "m.yaml").write_text(text)
    with pytest.raises(ValueError, match=rf"m\.yaml: {message}"):
        OccupancyGrid.load_map_server(tmp_path / "m.yaml")


def test_free_thresh_025_would_lose_unknown_cells():
    # Why the YAML says 0.196: the unknown pixel 205 reads as p = 0.196 < 0.25 -> free.
    assert (255 - 205) / 255 < 0.25
    assert not (255 - 205) / 255 < 0.196


def test_npz_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    grid = OccupancyGrid(
        rng.uniform(size=(4, 5)),
        (0.5, -0.5),
        0.2,
        variance=rng.uniform(size=(4, 5)),
        unknown=rng.uniform(size=(4, 5)) < 0.5,
    )
    grid.save(tmp_path / "grid.npz")
    back = OccupancyGrid.load(tmp_path / "grid.npz")
    for name in ("probability", "variance", "unknown", "origin"):
        np.testing.assert_array_equal(getattr(back, name), getattr(grid, name))
    assert back.resolution == grid.resolution
    bare = OccupancyGrid(grid.probability, grid.origin, grid.resolution)
    bare.save(tmp_path / "bare.npz")
    back = OccupancyGrid.load(tmp_path / "bare.npz")
    assert back.variance is None and back.unknown is None
    # Without the suffix: numpy appends it on saving, and load takes the same path.
    grid.save(tmp_path / "nosuffix")
    assert (tmp_path / "nosuffix.npz").is_file()
    np.testing.assert_array_equal(OccupancyGrid.load(tmp_path / "nosuffix").unknown, grid.unknown)


def test_load_takes_the_path_save_took_beside_a_folder_of_that_name(tmp_path):
    # save("out/map") writes out/map.npz; a folder out/map must not hide it from load.
    grid = OccupancyGrid([[0.9, 0.1]], origin=(0.0, 0.0), resolution=0.5)
    (tmp_path / "map").mkdir()
    grid.save(tmp_path / "map")
    np.testing.assert_array_equal(OccupancyGrid.load(tmp_path / "map").probability, [[0.9, 0.1]])
    (tmp_path / "other").mkdir()
    with pytest.raises(ValueError, match="not an OccupancyGrid saved by OccupancyGrid.save"):
        OccupancyGrid.load(tmp_path / "other")


def test_map_server_stem_keeps_its_dots(tmp_path):
    grid = OccupancyGrid([[0.9, 0.1]], origin=(0.0, 0.0), resolution=0.05)
    yaml_path, pgm_path = grid.save_map_server(tmp_path / "intel_0.05")
    assert (yaml_path.name, pgm_path.name) == ("intel_0.05.yaml", "intel_0.05.pgm")
    assert "image: intel_0.05.pgm" in yaml_path.read_text()


def test_load_map_server_from_a_stem_with_dots(tmp_path):
    # The stem "intel_0.05" names intel_0.05.yaml, not intel_0.yaml.
    grid = OccupancyGrid([[0.9, 0.1]], origin=(1.0, -2.0), resolution=0.05)
    grid.save_map_server(tmp_path / "intel_0.05")
    back = OccupancyGrid.load_map_server(tmp_path / "intel_0.05")
    np.testing.assert_array_equal(back.trinary(), [[100, 0]])
    assert back.origin.tolist() == [1.0, -2.0] and back.resolution == 0.05


def test_save_writes_a_compressed_npz(tmp_path):
    import zipfile

    grid = OccupancyGrid(np.full((50, 40), 0.5), (0.0, 0.0), 0.1, variance=np.ones((50, 40)))
    grid.save(tmp_path / "grid.npz")
    with zipfile.ZipFile(tmp_path / "grid.npz") as archive:
        members = archive.infolist()
    assert {m.filename for m in members} == {
        "probability.npy",
        "origin.npy",
        "resolution.npy",
        "variance.npy",
    }
    assert all(m.compress_type == zipfile.ZIP_DEFLATED for m in members)
    # 2000 equal doubles deflate to far less than their 16 kB.
    assert (tmp_path / "grid.npz").stat().st_size < 4000


def test_a_grid_of_exactly_the_largest_size_is_allowed():
    from skoccmap.grid import _grid_from_extent

    # 10000 x 5000 cells: 50,000,000, the most a map may have; one row more is refused.
    origin, counts = _grid_from_extent((0.0, 10000.0, 0.0, 5000.0), 1.0)
    assert origin.tolist() == [0.0, 0.0] and counts.tolist() == [10000, 5000]
    with pytest.raises(ValueError, match="too large .at most 50,000,000 cells"):
        _grid_from_extent((0.0, 10000.0, 0.0, 5001.0), 1.0)


def test_grids_far_too_large_or_far_off_are_refused_in_a_few_words():
    from skoccmap.grid import _grid_from_extent

    # Counts of 1e300 were printed with their 301 digits, after overflow warnings.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for extent, resolution, sizes in [
            ((0.0, 1.0, 0.0, 1.0), 1e-300, "1e+300 x 1e+300"),
            ((0.0, 1.0, 0.0, 1.0), 5e-324, "inf x inf"),
            (np.array([[0.0, 0.0, 1.0, 1.0]]), 1e-200, "1e+200 x 1e+200"),
        ]:
            with pytest.raises(ValueError, match=re.escape(f"a grid of {sizes} cells")):
                _grid_from_extent(extent, resolution)
        # Coordinates beyond 1e100 gave a grid of "-inf x -inf" cells, or one of no width.
        for extent in ((0.0, 1e101, 0.0, 1.0), np.array([[1e308, 1e308, 1e308, 1e308]])):
            for resolution in (1e-5, 1.0):
                with pytest.raises(ValueError, match="extent holds coordinates up to"):
                    _grid_from_extent(extent, resolution)


@pytest.mark.parametrize("coordinate", [0.85, 1.7, 1.95, 0.0, -0.85])
def test_one_point_extent_covers_the_point(coordinate):
    # floor(0.85 / 0.05) * 0.05 rounds above 0.85: the grid must still hold the point.
    grid = OccupancyGrid.from_estimator(
        _FieldEstimator(), [[coordinate, 0.0]], 0.05, unknown_variance=None
    )
    assert grid.shape == (1, 1)
    xmin, xmax, ymin, ymax = grid.extent
    assert xmin <= coordinate <= xmax and ymin <= 0.0 <= ymax


def test_3d_grid_points_and_voxels():
    est = _FieldEstimator()
    grid = OccupancyGrid.from_estimator(est, (0, 1, 0, 2, -1, 1), 0.5, unknown_variance=None)
    assert grid.shape == (4, 4, 2) and grid.n_dims == 3
    centers = grid.cell_centers()
    np.testing.assert_allclose(grid.probability.ravel(), est.proba_at(centers))
    points = grid.to_points(occupied_threshold=0.3)
    np.testing.assert_allclose(points, centers[est.proba_at(centers) > 0.3])
    voxels = grid.trinary()
    assert voxels.shape == grid.shape
    with pytest.raises(ValueError, match="2-D"):
        grid.to_ros_occupancy_grid()
    with pytest.raises(ValueError, match="2-D"):
        grid.save_map_server("unused")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(probability=[[0.5, 1.5]]), "probability must lie in"),
        (dict(probability=[[0.5, np.nan]]), "probability must lie in"),
        (dict(probability=[0.5, 0.5]), "probability must be a non-empty 2-D"),
        (dict(origin=(0.0,)), "origin"),
        (dict(resolution=0.0), "resolution"),
        # The extent was inf, with only numpy's overflow warning.
        (dict(resolution=1e308), "far corner beyond the largest float"),
        (dict(origin=(1.7e308, 0.0), resolution=1e307), "far corner beyond the largest float"),
        (dict(variance=[[1.0]]), "variance has shape"),
        (dict(variance=[[1.0, -1.0]]), "non-negative"),
        (dict(unknown=[[0, 1]]), "unknown must be a boolean"),
    ],
)
def test_bad_grid_arguments(kwargs, match):
    args = dict(probability=[[0.5, 0.5]], origin=(0.0, 0.0), resolution=0.1) | kwargs
    with pytest.raises(ValueError, match=match):
        OccupancyGrid(**args)


@pytest.mark.parametrize("n_features, n_dims", [(4, 3), (6, 2), (3, 2), (2, 3)])
def test_an_extent_of_another_dimension_than_the_estimator_is_named(n_features, n_dims):
    from sklearn.dummy import DummyClassifier

    est = DummyClassifier().fit(np.zeros((2, n_features)), [0, 1])
    extent = (0, 1) * n_dims
    with pytest.raises(ValueError, match=f"extent gives a {n_dims}-D grid, but Dummy.*on "):
        OccupancyGrid.from_estimator(est, extent, 0.5)
    # An extent of its own dimension (2 or 3 columns of points, 4 or 6 of segments).
    own = n_features if n_features in (2, 3) else n_features // 2
    assert OccupancyGrid.from_estimator(est, (0, 1) * own, 0.5).probability.ndim == own


def test_bad_from_estimator_arguments():
    est = _FieldEstimator()
    with pytest.raises(ValueError, match="extent must be"):
        OccupancyGrid.from_estimator(est, (0, 1, 2), 0.1)
    with pytest.raises(ValueError, match="max > min"):
        OccupancyGrid.from_estimator(est, (1, 0, 0, 1), 0.1)
    with pytest.raises(ValueError, match="NaN"):
        OccupancyGrid.from_estimator(est, np.array([[np.nan, 0.0]]), 0.1)
    with pytest.raises(ValueError, match="resolution"):
        OccupancyGrid.from_estimator(est, (0, 1, 0, 1), -0.1)
    for resolution in (None, "0.1", True, np.inf):
        with pytest.raises(ValueError, match="resolution must be a positive number"):
            OccupancyGrid.from_estimator(est, (0, 1, 0, 1), resolution)
        # The constructor too (it read True as 1 m).
        with pytest.raises(ValueError, match="resolution must be a positive number"):
            OccupancyGrid(np.full((2, 2), 0.5), (0.0, 0.0), resolution)
    with pytest.raises(ValueError, match="too large"):
        OccupancyGrid.from_estimator(est, (0, 10, 0, 10), 1e-6)
    with pytest.raises(ValueError, match="too large"):
        OccupancyGrid.from_estimator(est, np.array([[0.0, 0.0], [3e9, 3e9]]), 0.1)
    with pytest.raises(ValueError, match="chunk_size"):
        OccupancyGrid.from_estimator(est, (0, 1, 0, 1), 0.1, chunk_size=0)
    grid = OccupancyGrid.from_estimator(est, (0, 1, 0, 1), 0.5, chunk_size=np.int64(2))
    assert grid.shape == (2, 2)
    with pytest.raises(ValueError, match="predict_proba"):
        OccupancyGrid.from_estimator(object(), (0, 1, 0, 1), 0.1)
    for threshold in ("foo", "AUTO", -1.0, 0.0, np.nan, True):
        with pytest.raises(ValueError, match="unknown_variance must be 'auto', None or a"):
            OccupancyGrid.from_estimator(est, (0, 1, 0, 1), 0.5, unknown_variance=threshold)
    for threshold in ("auto", None, 0.5, np.float32(2.0), 3):
        OccupancyGrid.from_estimator(est, (0, 1, 0, 1), 0.5, unknown_variance=threshold)
    grid = OccupancyGrid([[0.5]], (0, 0), 1.0)
    with pytest.raises(ValueError, match="free_threshold"):
        grid.trinary(free_threshold=0.8, occupied_threshold=0.6)


def _room3d_pipeline(estimator, resolution=0.5):
    """Simulated 3-D scans -> estimator -> 3-D grid -> points and voxels; AUC on seen cells."""
    from sklearn.metrics import roc_auc_score

    from skoccmap.datasets import make_room3d_scans

    data = make_room3d_scans(random_state=0)
    estimator.fit(data.X, data.y)
    extent = data.environment.extent
    grid = OccupancyGrid.from_estimator(estimator, extent, resolution, unknown_variance=None)
    truth = data.environment.ground_truth_grid(resolution, extent=extent, scans=data.scans)
    assert tuple(truth.shape) == grid.shape
    np.testing.assert_allclose(truth.points, grid.cell_centers())
    seen = truth.observed
    auc = roc_auc_score(truth.occupied[seen], grid.probability.ravel()[seen])
    points = grid.to_points()
    voxels = grid.trinary()
    assert points.shape[1] == 3 and len(points) == (voxels == 100).sum() > 0
    # exported occupied voxels mostly overlap true obstacles
    assert truth.occupied[voxels.ravel() == 100].mean() > 0.7
    return auc


def test_3d_scans_mapped_end_to_end_with_counting_grid():
    assert _room3d_pipeline(OccupancyGridMap(resolution=0.5)) > 0.75


@pytest.mark.slow
def test_3d_scans_mapped_end_to_end_with_mixture():
    from skoccmap import MixtureGPOccupancyMap

    model = MixtureGPOccupancyMap(share_hyperparameters=True, random_state=0)
    assert _room3d_pipeline(model) > 0.75


def test_helpers_pass_their_own_queries_without_feature_name_warnings():
    # Fitted on a DataFrame, the estimator warns of arrays without feature names; the
    # package's own cell centres and test points are built in its column order.
    pd = pytest.importorskip("pandas")
    from skoccmap.datasets import make_paper_scans
    from skoccmap.metrics import ground_truth_auc

    data = make_paper_scans(random_state=0)
    frame = pd.DataFrame(data.X, columns=["x0", "y0", "x1", "y1"])
    model = MixtureGPOccupancyMap(random_state=0).fit(frame, data.y)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        grid = OccupancyGrid.from_estimator(model, data.X[data.y == 1, :2], 0.5)
        auc = ground_truth_auc(model, data.environment, 0.5)
    # ... and the same map as a fit on the array.
    plain = MixtureGPOccupancyMap(random_state=0).fit(data.X, data.y)
    same = OccupancyGrid.from_estimator(plain, data.X[data.y == 1, :2], 0.5)
    np.testing.assert_array_equal(grid.probability, same.probability)
    assert auc == ground_truth_auc(plain, data.environment, 0.5)
    with pytest.warns(UserWarning, match="valid feature names"):
        model.predict_proba(data.X[:3])  # the user's own arrays still warn


def test_load_of_an_npz_that_is_no_grid(tmp_path):
    np.savez(tmp_path / "a.npz", a=np.zeros(2))
    with pytest.raises(ValueError, match="not an OccupancyGrid saved by OccupancyGrid.save"):
        OccupancyGrid.load(tmp_path / "a.npz")


def test_loading_the_wrong_file_says_which_reader_to_use(tmp_path):
    grid = OccupancyGrid(np.full((3, 4), 0.5), origin=(0.0, 0.0), resolution=0.5)
    yaml_path, image_path = grid.save_map_server(tmp_path / "map")
    with pytest.raises(ValueError, match="not an OccupancyGrid.*load_map_server"):
        OccupancyGrid.load(yaml_path)
    with pytest.raises(ValueError, match="not an OccupancyGrid.*load_map_server"):
        OccupancyGrid.load(image_path)
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(ValueError, match="holds one array"):
        OccupancyGrid.load(tmp_path / "one.npy")
    with pytest.raises(FileNotFoundError):
        OccupancyGrid.load(tmp_path / "absent")
    with pytest.raises(ValueError, match="not a map_server YAML file.*pass the .yaml"):
        OccupancyGrid.load_map_server(image_path)


def test_load_of_a_truncated_or_damaged_npz(tmp_path):
    # They were zipfile's BadZipFile ("Bad CRC-32", "File is not a zip file") and EOFError.
    rng = np.random.default_rng(0)
    OccupancyGrid(rng.uniform(size=(20, 20)), origin=(0.0, 0.0), resolution=0.5).save(
        tmp_path / "map.npz"
    )
    data = (tmp_path / "map.npz").read_bytes()
    flipped = bytearray(data)
    flipped[100] ^= 0xFF  # inside the compressed probabilities
    for name, content in [
        ("truncated", data[: len(data) // 2]),
        ("empty", b""),
        ("flipped", bytes(flipped)),
    ]:
        (tmp_path / f"{name}.npz").write_bytes(content)
        with pytest.raises(ValueError, match=rf"{name}\.npz (is not an OccupancyGrid|is damaged)"):
            OccupancyGrid.load(tmp_path / f"{name}.npz")


def test_an_extent_of_two_points_one_cell_wide_warns():
    # ((xmin, xmax), (ymin, ymax)) is two points, (0, 22) and (0, 18): a strip one cell wide.
    model = OccupancyGridMap(resolution=0.5).fit(
        np.array([[0.0, 0.0, 0.9, 0.0], [1.0, 0.0, 1.0, 0.0]]), [0, 1]
    )
    with pytest.warns(UserWarning, match="read as two points, which span a grid one cell wide"):
        grid = OccupancyGrid.from_estimator(model, extent=((0, 22), (0, 18)), resolution=0.2)
    assert 1 in grid.shape
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        OccupancyGrid.from_estimator(model, extent=((0, 0), (22, 18)), resolution=0.2)


@pytest.mark.parametrize(
    ("image", "message"),
    [
        (b"\x89PNG\r\n\x1a\n", "does not start with P5"),
        (b"P5\n-2 2\n255\n\x00\x00\x00\x00", "its header is not one"),
        (b"P5\n2 2\n255\n\x00\x00", "truncated: 2 x 2 pixels need 4 bytes, it holds 2"),
        (b"", "does not start with P5"),
        (b"P5\n# a comment without its newline", "its header is not one"),
    ],
)
def test_malformed_map_server_images(tmp_path, image, message):
    (tmp_path / "m.pgm").write_bytes(image)
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(ValueError, match=message):
        OccupancyGrid.load_map_server(tmp_path / "m.yaml")


@pytest.mark.parametrize("threshold", [np.nan, 2.0, -0.1])
def test_to_points_checks_its_threshold(threshold):
    grid = OccupancyGrid([[0.1, 0.9]], origin=(0.0, 0.0), resolution=1.0)
    with pytest.raises(ValueError, match="occupied_threshold"):
        grid.to_points(threshold)


def test_extent_equal_bounds_are_refused():
    # max > min on every axis: a zero-width extent covers nothing.
    with pytest.raises(ValueError, match="max > min"):
        OccupancyGrid.from_estimator(_FieldEstimator(), (0.0, 1.0, 0.5, 0.5), 0.1)


def test_extent_narrower_than_a_cell_gets_one_cell():
    # (xmin, xmax) = (0, 1e-12): covered from xmin by one cell of width 1.
    grid = OccupancyGrid.from_estimator(
        _FieldEstimator(), (0.0, 1e-12, 0.0, 2.0), 1.0, unknown_variance=None
    )
    assert grid.shape == (2, 1)
    assert grid.extent == (0.0, 1.0, 0.0, 2.0)


class _ConstantEstimator:
    """The same probability and variance at every query."""

    def __init__(self, proba, var=1.0):
        self.proba, self.var = proba, var

    def predict_proba(self, X):
        p = np.full(len(X), self.proba)
        return np.column_stack([1 - p, p])

    def predict_var(self, X):
        return np.full(len(X), self.var)


def test_probabilities_a_rounding_error_outside_0_1_are_clipped():
    for proba, expected in ((1.0 + 1e-15, 1.0), (-1e-17, 0.0)):
        grid = OccupancyGrid.from_estimator(_ConstantEstimator(proba), (0, 1, 0, 1), 0.5)
        np.testing.assert_array_equal(grid.probability, np.full((2, 2), expected))


@pytest.mark.parametrize("proba", [np.nan, np.inf, -np.inf])
def test_non_finite_predictions_are_refused(proba):
    with pytest.raises(ValueError, match="NaN or infinite probabilities"):
        OccupancyGrid.from_estimator(_ConstantEstimator(proba), (0, 1, 0, 1), 0.5)


class _MisshapenEstimator(_ConstantEstimator):
    def __init__(self, proba_shape, var_shape):
        super().__init__(0.5, 1.0)
        self.shapes = {"predict_proba": proba_shape, "predict_var": var_shape}

    def predict_proba(self, X):
        return np.full(self.shapes["predict_proba"](len(X)), 0.5)

    def predict_var(self, X):
        return np.full(self.shapes["predict_var"](len(X)), 1.0)


@pytest.mark.parametrize(
    "proba_shape, var_shape, match",
    [
        # numpy's "too many indices for array"
        (lambda n: (n,), lambda n: (n,), r"predict_proba returned .* shape \(4,\) for 4 queries"),
        # a broadcasting error
        (lambda n: (n + 1, 2), lambda n: (n,), r"predict_proba returned .* shape \(5, 2\)"),
        (lambda n: (n, 2), lambda n: (n, 1), r"predict_var returned .* shape \(4, 1\).*\(n_q"),
    ],
)
def test_predictions_of_the_wrong_shape_are_refused(proba_shape, var_shape, match):
    estimator = _MisshapenEstimator(proba_shape, var_shape)
    with pytest.raises(ValueError, match=match):
        OccupancyGrid.from_estimator(estimator, (0, 1, 0, 1), 0.5)


def test_auto_unknown_uses_the_largest_prior_variance_over_the_grid():
    # A prior variance that grows with x: the threshold is 90 % of its largest value on
    # the grid's cell centres, the cell of largest x -- not the value at the first cell.
    class RisingPrior(_ConstantEstimator):
        def prior_variance(self, X):
            return 1.0 + X[:, 0]

    extent = (0.0, 4.0, 0.0, 2.0)  # centres x = 0.5 .. 3.5: prior 1.5 .. 4.5
    # 0.9 * 4.5 = 4.05 (0.9 * 1.5 = 1.35 would be the first cell's alone).
    for var, unknown in ((4.1, True), (4.0, False), (1.4, False)):
        grid = OccupancyGrid.from_estimator(RisingPrior(0.5, var), extent, 1.0)
        np.testing.assert_array_equal(grid.unknown, np.full((2, 4), unknown))


def test_a_variance_equal_to_the_threshold_is_not_unknown():
    # "Cells whose variance exceeds this are unknown": equal is not above.
    grid = OccupancyGrid.from_estimator(
        _ConstantEstimator(0.5, var=2.0), (0, 1, 0, 1), 0.5, unknown_variance=2.0
    )
    assert not grid.unknown.any()


def test_ros_fields_refuse_what_a_message_cannot_hold():
    # A frame_id that is no string stopped in rosbags ("'int' object has no attribute
    # 'encode'"); a resolution beyond float32 stopped in struct.pack, one below it was
    # written as 0.
    grid = OccupancyGrid([[0.5, 0.5]], origin=(0.0, 0.0), resolution=0.1)
    with pytest.raises(TypeError, match="frame_id must be a string, got 3"):
        grid.to_ros_occupancy_grid(frame_id=3)
    for resolution in (1e300, 1e-300):
        far = OccupancyGrid([[0.5, 0.5]], origin=(0.0, 0.0), resolution=resolution)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(ValueError, match="is not a positive float32"):
                far.to_ros_occupancy_grid()


def test_ros_data_rounds_to_the_nearest_percent():
    grid = OccupancyGrid([[0.456, 0.994, 0.005, 0.129]], origin=(0.0, 0.0), resolution=1.0)
    np.testing.assert_array_equal(grid.to_ros_occupancy_grid()["data"], [46, 99, 0, 13])


def _write_map(tmp_path, pixels, yaml_lines):
    pixels = np.asarray(pixels, dtype=np.uint8)
    height, width = pixels.shape
    header = f"P5\n{width} {height}\n255\n".encode()
    (tmp_path / "m.pgm").write_bytes(header + pixels.tobytes())
    (tmp_path / "m.yaml").write_text(
        "image: m.pgm\nresolution: 0.5\norigin: [0, 0, 0]\n"
        + "".join(f"{s}\n" for s in yaml_lines)
    )
    return OccupancyGrid.load_map_server(tmp_path / "m.yaml")


def test_negated_map_server_image(tmp_path):
    # negate: 1 -> occupancy v / 255: white (255) is occupied, black (0) free.
    yaml_lines = ["negate: 1", "occupied_thresh: 0.65", "free_thresh: 0.196"]
    grid = _write_map(tmp_path, [[0, 255, 128]], yaml_lines)
    np.testing.assert_allclose(grid.probability, [[0.0, 1.0, 128 / 255]])
    np.testing.assert_array_equal(grid.trinary(), [[0, 100, -1]])


def test_map_server_thresholds_are_strict_when_loading(tmp_path):
    # (255 - 204) / 255 = 0.2 = free_thresh and (255 - 102) / 255 = 0.6 = occupied_thresh:
    # neither below free_thresh nor above occupied_thresh, map_server loads both as -1;
    # 205 (p = 0.196) is free, 101 (p = 0.604) occupied.
    yaml_lines = ["occupied_thresh: 0.6", "free_thresh: 0.2"]
    grid = _write_map(tmp_path, [[204, 102, 205, 101]], yaml_lines)
    np.testing.assert_array_equal(grid.unknown, [[True, True, False, False]])
    np.testing.assert_array_equal(grid.trinary(0.2, 0.6), [[-1, -1, 0, 100]])


def test_map_server_yaml_without_thresholds_uses_the_defaults(tmp_path):
    # Defaults 0.196 / 0.65: the unknown pixel 205 (p = 0.196078) stays unknown, 255 is
    # free, 0 occupied, 90 (p = 0.647) unknown, 88 (p = 0.655) occupied.
    grid = _write_map(tmp_path, [[205, 255, 0, 90, 88]], [])
    np.testing.assert_array_equal(grid.unknown, [[True, False, False, True, False]])
    np.testing.assert_array_equal(grid.trinary(), [[-1, 0, 100, -1, 100]])


def test_scale_mode_marks_no_pixel_unknown(tmp_path):
    # In scale mode map_server scales pixels between the thresholds, none is -1.
    grid = _write_map(tmp_path, [[0, 128, 205, 255]], ["mode: scale"])
    assert not grid.unknown.any()
    np.testing.assert_allclose(grid.probability, [[1.0, 127 / 255, 50 / 255, 0.0]])


@pytest.mark.parametrize(
    "negate, occupied",
    [("true", 255), ("False", 0), ("yes", 255), ("OFF", 0), ("y", 255), ("N", 0)],
)
def test_negate_may_be_a_yaml_boolean(tmp_path, negate, occupied):
    # Nav2's map_server reads negate as an int or else a boolean, as yaml-cpp spells one:
    # y, yes, true, on and n, no, false, off, lower case, capitalised or upper case.
    grid = _write_map(tmp_path, [[occupied, 255 - occupied]], [f"negate: {negate}"])
    np.testing.assert_array_equal(grid.trinary(), [[100, 0]])


def test_raw_map_server_image_is_percent_occupancy(tmp_path):
    # Raw mode: map_server's data is the pixel itself, -1 for pixels above 100 (Nav2's
    # map_saver writes unknown cells as 255 in raw mode).
    grid = _write_map(tmp_path, [[0, 37, 100, 101, 255]], ["mode: raw", "negate: 0"])
    np.testing.assert_array_equal(grid.unknown, [[False, False, False, True, True]])
    np.testing.assert_allclose(grid.probability, [[0.0, 0.37, 1.0, 0.5, 0.5]])
    data = grid.to_ros_occupancy_grid()["data"]
    np.testing.assert_array_equal(data, [0, 37, 100, -1, -1])
    np.testing.assert_array_equal(grid.trinary(), [[0, -1, 100, -1, -1]])
    with pytest.raises(ValueError, match="mode raw with negate 1 is not supported"):
        _write_map(tmp_path, [[0, 255]], ["mode: raw", "negate: 1"])


def test_map_server_yaml_with_comments_and_quotes(tmp_path):
    _write_map(tmp_path, [[0, 255]], [])  # m.pgm
    (tmp_path / "c.yaml").write_text(
        "# written by hand\n"
        'image: "m.pgm"  # the image\n'
        "resolution: 0.25\n"
        "origin: [1.5, -2.0, 0.0]  # lower-left corner\n"
        "mode: 'trinary'\n"
    )
    grid = OccupancyGrid.load_map_server(tmp_path / "c.yaml")
    assert grid.resolution == 0.25
    np.testing.assert_array_equal(grid.origin, [1.5, -2.0])
    np.testing.assert_array_equal(grid.trinary(), [[100, 0]])


@pytest.mark.parametrize(
    "stem", ["map#2", "map #2", "map: v2", "[floor 1]", "*m", "it's", "-m", "étage", "m a p"]
)
def test_map_server_yaml_names_any_image_as_yaml_reads_it(tmp_path, stem):
    # Unquoted, "map #2.pgm" read as "map" (a comment), "map: v2.pgm" as a nested mapping,
    # "[floor 1].pgm" as a list and "*m.pgm" as an alias, in map_server's YAML reader.
    grid = OccupancyGrid([[0.9, 0.1]], origin=(0.0, 0.0), resolution=0.5)
    yaml_path, pgm_path = grid.save_map_server(tmp_path / stem)
    line = yaml_path.read_text(encoding="utf-8").splitlines()[0]
    image = line.removeprefix("image: ")
    if image.startswith("'"):
        assert image == "'" + pgm_path.name.replace("'", "''") + "'"
    else:
        assert image == pgm_path.name and re.fullmatch(r"[\w.][\w.+\- ]*", image)
    back = OccupancyGrid.load_map_server(yaml_path)
    np.testing.assert_array_equal(back.trinary(), [[100, 0]])


@pytest.mark.parametrize(
    "image, name",
    [
        ("map#2.pgm", "map#2.pgm"),  # a '#' after no space starts no comment
        ("map#2.pgm  # the image", "map#2.pgm"),
        ("'it''s #2.pgm'  # quoted", "it's #2.pgm"),
        ('"a \\"b\\".pgm"', 'a "b".pgm'),
        ("'[m].pgm'", "[m].pgm"),
    ],
)
def test_map_server_yaml_reads_hash_and_quotes_as_yaml_does(tmp_path, image, name):
    (tmp_path / name).write_bytes(b"P5\n2 1\n255\n" + bytes([0, 255]))
    (tmp_path / "m.yaml").write_text(
        f"image: {image}\nresolution: 0.5\norigin: [0, 0, 0]\n", encoding="utf-8"
    )
    grid = OccupancyGrid.load_map_server(tmp_path / "m.yaml")
    np.testing.assert_array_equal(grid.trinary(), [[100, 0]])


def test_map_server_yaml_comment_right_after_a_list(tmp_path):
    # YAML (yaml-cpp, PyYAML) ends a flow sequence at its "]": the "#" after it starts a
    # comment, which the list's numbers took in.
    _write_map(tmp_path, [[0, 255]], [])
    (tmp_path / "c.yaml").write_text(
        "image: m.pgm\nresolution: 0.5\norigin: [-1.0, 2.0, 0.0]# lower-left\n"
    )
    grid = OccupancyGrid.load_map_server(tmp_path / "c.yaml")
    np.testing.assert_array_equal(grid.origin, [-1.0, 2.0])


def test_map_server_yaml_with_a_byte_order_mark(tmp_path):
    _write_map(tmp_path, [[0, 255]], [])
    text = (tmp_path / "m.yaml").read_text()
    (tmp_path / "m.yaml").write_text(text, encoding="utf-8-sig")
    grid = OccupancyGrid.load_map_server(tmp_path / "m.yaml")
    np.testing.assert_array_equal(grid.trinary(), [[100, 0]])


def test_map_server_yaml_unclosed_quote_is_a_clear_error(tmp_path):
    _write_map(tmp_path, [[0, 255]], [])
    (tmp_path / "m.yaml").write_text("image: 'm.pgm\nresolution: 0.5\norigin: [0, 0, 0]\n")
    with pytest.raises(ValueError, match="cannot read the quoted value of 'image'"):
        OccupancyGrid.load_map_server(tmp_path / "m.yaml")


def test_zero_variance_is_a_valid_variance():
    grid = OccupancyGrid([[0.5, 0.9]], (0.0, 0.0), 1.0, variance=[[0.0, 1.0]])
    np.testing.assert_array_equal(grid.variance, [[0.0, 1.0]])


def test_to_points_leaves_out_unknown_and_threshold_cells():
    # Cell (j, i) has its centre at origin + 0.5 * (i + 0.5, j + 0.5).
    probability = [[0.9, 0.65, 0.2], [0.99, 0.7, 0.66]]
    unknown = [[False, False, False], [True, False, False]]
    grid = OccupancyGrid(probability, (1.0, -1.0), 0.5, unknown=np.array(unknown))
    np.testing.assert_allclose(grid.to_points(), [[1.25, -0.75], [1.75, -0.25], [2.25, -0.25]])


def test_trinary_with_equal_thresholds():
    # free_threshold == occupied_threshold is allowed: only that exact value is unknown.
    grid = OccupancyGrid([[0.4, 0.5, 0.6]], (0.0, 0.0), 1.0)
    np.testing.assert_array_equal(grid.trinary(0.5, 0.5), [[0, -1, 100]])


def test_ros_occupancy_grid_takes_the_trinary_thresholds_of_save_map_server(tmp_path):
    # A map saved for map_server with its own thresholds and sent as a message agree.
    grid = OccupancyGrid([[0.1, 0.3, 0.5, 0.8]], (0.0, 0.0), 1.0)
    thresholds = {"free_threshold": 0.25, "occupied_threshold": 0.45}
    message = grid.to_ros_occupancy_grid(trinary=True, **thresholds)
    np.testing.assert_array_equal(message["data"], [0, -1, 100, 100])
    yaml_path, _ = grid.save_map_server(tmp_path / "m", **thresholds)
    np.testing.assert_array_equal(
        OccupancyGrid.load_map_server(yaml_path).trinary(**thresholds).ravel(), message["data"]
    )
    np.testing.assert_array_equal(
        grid.to_ros_occupancy_grid(trinary=True)["data"], [0, -1, -1, 100]
    )
    # Used with trinary=True only, but checked either way.
    with pytest.raises(ValueError, match="free_threshold"):
        grid.to_ros_occupancy_grid(free_threshold=0.7)


def test_trinary_thresholds_that_are_no_numbers_are_named():
    # Before: numpy's comparison TypeError for a string, and True read as 1.
    grid = OccupancyGrid([[0.4, 0.5, 0.6]], (0.0, 0.0), 1.0)
    with pytest.raises(TypeError, match="free_threshold must be a number, got '0.1'"):
        grid.trinary("0.1", 0.65)
    with pytest.raises(TypeError, match="occupied_threshold must be a number, got True"):
        grid.trinary(0.1, True)
    np.testing.assert_array_equal(grid.trinary(np.float32(0.45), 0.55), [[0, -1, 100]])


def test_auto_unknown_samples_the_prior_over_the_whole_grid():
    # 64 x 32 = 2048 cells, more than the sample: the prior 1 + y peaks in the top row
    # (y = 31.5, 0.9 * 32.5 = 29.25), which the first 1024 cells (y < 16) do not reach.
    class PriorRisingInY(_ConstantEstimator):
        def prior_variance(self, X):
            return 1.0 + X[:, 1]

    grid = OccupancyGrid.from_estimator(PriorRisingInY(0.5, var=20.0), (0, 64, 0, 32), 1.0)
    assert grid.shape == (32, 64) and not grid.unknown.any()
    grid = OccupancyGrid.from_estimator(PriorRisingInY(0.5, var=29.5), (0, 64, 0, 32), 1.0)
    assert grid.unknown.all()


def test_pgm_header_comments_are_skipped(tmp_path):
    # Image editors (GIMP) write a comment line into the header; the PGM format allows it.
    header = b"P5\n# CREATOR: GIMP PNM Filter Version 1.1\n3 1\n# max\n255\n"
    (tmp_path / "g.pgm").write_bytes(header + bytes([0, 205, 254]))
    (tmp_path / "g.yaml").write_text("image: g.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n")
    grid = OccupancyGrid.load_map_server(tmp_path / "g.yaml")
    np.testing.assert_array_equal(grid.trinary(), [[100, -1, 0]])


def _field_points(n=60, seed=0):
    """Points of the field of _FieldEstimator over [-1, 2] x [0.5, 1.5], labelled by it."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([-1.0, 0.5], [2.0, 1.5], size=(n, 2))
    return points, (_FieldEstimator.proba_at(points) > 0.5).astype(int)


def test_an_estimator_fitted_on_points_is_queried_at_points():
    # Cells of a classifier fitted on points (of layout="points", or any scikit-learn one)
    # are its points: zero-length segments were refused as "X has 4 features".
    from sklearn.neighbors import KNeighborsClassifier

    points, y = _field_points()
    knn = KNeighborsClassifier(3).fit(points, y)
    grid = OccupancyGrid.from_estimator(knn, extent=(-1.0, 2.0, 0.5, 1.5), resolution=0.25)
    xs = -1.0 + 0.25 * (np.arange(12) + 0.5)
    ys = 0.5 + 0.25 * (np.arange(4) + 0.5)
    gx, gy = np.meshgrid(xs, ys)
    centres = np.column_stack([gx.ravel(), gy.ravel()])
    expected = knn.predict_proba(centres)[:, 1].reshape(4, 12)
    np.testing.assert_array_equal(grid.probability, expected)
    # The package's own: the joint prediction, the variance and the prior variance's "auto".
    grid_map = OccupancyGridMap(resolution=0.25, layout="points").fit(points, y)
    counted = OccupancyGrid.from_estimator(grid_map, resolution=0.25)
    assert counted.probability.shape == grid_map.shape_[::-1]
    model = MixtureGPOccupancyMap(layout="points", random_state=0).fit(points, y)
    grid = OccupancyGrid.from_estimator(model, extent=(-1.0, 2.0, 0.5, 1.5), resolution=0.25)
    segments = np.hstack([centres, centres])
    np.testing.assert_allclose(grid.probability.ravel(), model.predict_proba(centres)[:, 1])
    np.testing.assert_allclose(grid.variance.ravel(), model.predict_var(centres))
    reference = max(float(model.shared_kernel_.diag(segments).max()), grid.variance.max())
    np.testing.assert_array_equal(grid.unknown, grid.variance > 0.9 * reference)
