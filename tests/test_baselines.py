import itertools
import warnings

import numpy as np
import pytest
import sklearn
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import expit
from sklearn.base import clone
from sklearn.exceptions import NotFittedError
from sklearn.metrics import roc_auc_score
from sklearn.utils.estimator_checks import check_param_validation, parametrize_with_checks

from skoccmap.baselines import FrequencyGridMap, HilbertMap, OccupancyGridMap, traverse_cells
from skoccmap.datasets import make_office_scans


def _cells_by_slabs(start, end, origin, res, shape):
    """Reference: every cell whose box the segment overlaps over a positive length.

    Liang-Barsky clipping of the segment against each candidate box, one box at a time.
    """
    direction = end - start
    length = np.linalg.norm(direction)
    lo_cell = np.floor((np.minimum(start, end) - origin) / res).astype(int)
    hi_cell = np.floor((np.maximum(start, end) - origin) / res).astype(int)
    cells = set()
    ranges = [
        range(max(lo, 0), min(hi, n - 1) + 1)
        for lo, hi, n in zip(lo_cell, hi_cell, shape, strict=True)
    ]
    for cell in itertools.product(*ranges):
        box_lo = origin + res * np.array(cell)
        box_hi = box_lo + res
        t0, t1 = 0.0, 1.0
        for d in range(len(start)):
            if direction[d] == 0:
                if not box_lo[d] <= start[d] < box_hi[d]:
                    t0, t1 = 1.0, 0.0
                continue
            a = (box_lo[d] - start[d]) / direction[d]
            b = (box_hi[d] - start[d]) / direction[d]
            t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
        if length == 0:
            inside = np.all((box_lo <= start) & (start < box_hi))
            if inside:
                cells.add(cell)
        elif (t1 - t0) * length > 1e-9:
            cells.add(cell)
    return cells


@pytest.mark.parametrize("n_dims", [2, 3])
def test_traverse_cells_matches_box_clipping(n_dims):
    rng = np.random.default_rng(n_dims)
    origin, res = np.full(n_dims, -2.0), 0.3
    shape = (14,) * n_dims
    starts = rng.uniform(-2.0, 2.2, (40, n_dims))
    ends = rng.uniform(-2.0, 2.2, (40, n_dims))
    seg, cells = traverse_cells(starts, ends, origin, res, shape)
    for i in range(len(starts)):
        got = [tuple(c) for c in cells[seg == i].tolist()]
        assert len(got) == len(set(got)), "a cell visited twice"
        assert set(got) == _cells_by_slabs(starts[i], ends[i], origin, res, shape)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=4, max_size=4),
    st.floats(0.05, 1.0),
)
def test_traverse_cells_property(coords, res):
    start, end = np.array(coords[:2]), np.array(coords[2:])
    origin = np.floor(np.minimum(start, end) / res) * res
    origin = np.where(origin > np.minimum(start, end), origin - res, origin)  # rounding
    shape = tuple(np.floor((np.maximum(start, end) - origin) / res).astype(int) + 1)
    seg, cells = traverse_cells(start[None], end[None], origin, res, shape)
    visited = [tuple(c) for c in cells.tolist()]
    # First and last visits are the start and end cells; consecutive cells along a crossing
    # sequence form a connected path, so the count is 1 + the number of boundary crossings.
    i0 = tuple(np.clip(np.floor((start - origin) / res).astype(int), 0, np.array(shape) - 1))
    i1 = tuple(np.clip(np.floor((end - origin) / res).astype(int), 0, np.array(shape) - 1))
    assert visited[0] == i0 and i1 in visited
    assert len(visited) == 1 + sum(abs(a - b) for a, b in zip(i0, i1, strict=True))
    assert len(set(visited)) == len(visited)


@pytest.mark.parametrize("res", [0.0546875, 0.1, 0.3, 1 / 3])
def test_traverse_diagonal_through_corners_visits_each_cell_once(res):
    # The diagonal meets every corner; the two axes' crossings are computed separately and
    # round differently, which once entered cells twice.
    start, end = np.zeros(2), np.array([3.0, 3.0])
    shape = tuple(np.floor(end / res).astype(int) + 1)
    _, cells = traverse_cells(start[None], end[None], np.zeros(2), res, shape)
    visited = [tuple(c) for c in cells.tolist()]
    last = tuple(np.minimum(np.floor(end / res).astype(int), np.array(shape) - 1))
    assert len(set(visited)) == len(visited) == 1 + sum(last)
    # A face-connected staircase: every step raises i + j by one.
    np.testing.assert_array_equal(np.sort(cells.sum(axis=1)), np.arange(len(visited)))


def _assert_staircase(cells, first, last):
    """Visits form a monotone face-connected path from ``first`` to ``last``, each once."""
    visited = [tuple(c) for c in cells.tolist()]
    assert len(set(visited)) == len(visited)
    assert first in visited and last in visited
    assert len(visited) == 1 + int(np.abs(np.subtract(last, first)).sum())
    order = cells[np.argsort(np.abs(cells - np.asarray(first)).sum(axis=1), kind="stable")]
    assert np.all(np.abs(np.diff(order, axis=0)).sum(axis=1) == 1)


@pytest.mark.parametrize("dy", [0.0, 1e-12, 1e-9, -1e-9, 1e-7, -1e-7, 1e-5])
def test_traverse_lines_passing_near_a_corner(dy):
    # Near the corner (1, 1) each axis's crossing point rounds on its own; the order of the
    # crossings must still be one order, or cells are entered twice or skipped.
    start, end = np.array([0.5, 0.95]), np.array([1.5, 1.05 + dy])
    _, cells = traverse_cells(start[None], end[None], np.zeros(2), 1.0, (3, 3))
    _assert_staircase(cells, (0, 0), (1, 1))


def test_traverse_near_corners_in_3d():
    rng = np.random.default_rng(0)
    corner = rng.integers(2, 8, size=(500, 3)).astype(float)
    direction = rng.normal(size=(500, 3))
    offset = rng.choice([0.0, 1e-12, 1e-9, 1e-7], size=(500, 1)) * rng.normal(size=(500, 3))
    starts = corner + offset - 1.5 * direction / np.abs(direction).max(axis=1, keepdims=True)
    ends = corner + offset + 1.5 * direction / np.abs(direction).max(axis=1, keepdims=True)
    seg, cells = traverse_cells(starts, ends, np.zeros(3), 1.0, (12, 12, 12))
    for i in range(500):
        first = tuple(np.floor(starts[i]).astype(int))
        last = tuple(np.floor(ends[i]).astype(int))
        _assert_staircase(cells[seg == i], first, last)


@pytest.mark.parametrize(
    ("res", "start", "end"),
    [
        (0.05, [0.5, 0.1 + 0.2], [0.1 + 0.2, 0.0]),
        (0.1, [1.0, 0.2 + 0.4], [0.2 + 0.4, 0.0]),
        (0.05, [0.35, 0.1 + 0.2], [0.55, 0.0]),
        (0.1, [0.5, 0.2 + 0.4], [0.1 + 0.2, 0.0]),
        (0.05, [0.25, 3 * 0.05, 0.1 + 0.2], [0.05000000000000002, 0.35, 0.0]),
    ],
)
def test_traverse_lines_through_corners_a_rounding_below_the_face(res, start, end):
    # Lines of slope 3/2 through grid corners, with corner coordinates that round a little
    # above the corner (0.1 + 0.2 = 0.30000000000000004): at some corners the crossing point
    # of one axis lands just below the other axis's face. Each cell must still be entered
    # once, along a face-connected staircase.
    start, end = np.array(start), np.array(end)
    shape = (12,) * start.size
    seg, cells = traverse_cells(start[None], end[None], np.zeros(start.size), res, shape)
    first = tuple(np.floor(start / res).astype(int))
    last = tuple(np.floor(end / res).astype(int))
    _assert_staircase(cells, first, last)


def test_traverse_segments_between_grid_corners_stay_in_their_cell_range():
    # Start and end on grid corners, every direction: the crossing points land on faces of
    # the other axes, and a visit must not leave the box of cells between the two end cells.
    rng = np.random.default_rng(14)
    for res in (1.0, 0.7, 0.1):
        corners = rng.integers(0, 12, (200, 2, 2)) * res
        starts, ends = corners[:, 0], corners[:, 1]
        seg, cells = traverse_cells(starts, ends, np.zeros(2), res, (12, 12))
        for i in range(200):
            i0 = np.minimum(np.floor(starts[i] / res).astype(int), 11)
            i1 = np.minimum(np.floor(ends[i] / res).astype(int), 11)
            mine = cells[seg == i]
            assert np.all(mine >= np.minimum(i0, i1)) and np.all(mine <= np.maximum(i0, i1))
            _assert_staircase(mine, tuple(i0), tuple(i1))


def test_traverse_refuses_a_segment_over_the_cell_limit(monkeypatch):
    import skoccmap.baselines as baselines

    monkeypatch.setattr(baselines, "_MAX_SEGMENT_CELLS", 10)
    # 9 crossings (10 cells, 4 + 5 along the axes) pass; 10 crossings are refused.
    seg, cells = traverse_cells(np.zeros((1, 2)), [[4.5, 5.5]], np.zeros(2), 1.0, (12, 12))
    assert len(cells) == 10
    with pytest.raises(ValueError, match="crosses 11 grid cells, more than 10"):
        traverse_cells(np.zeros((1, 2)), [[5.5, 5.5]], np.zeros(2), 1.0, (12, 12))


def test_chunks_by_crossings_cover_the_rows_within_the_budget(monkeypatch):
    import skoccmap.baselines as baselines

    monkeypatch.setattr(baselines, "_CROSSINGS_PER_CHUNK", 50)
    rng = np.random.default_rng(5)
    first = rng.integers(0, 100, (200, 2))
    last = first + rng.integers(-30, 30, (200, 2))
    last[17] = first[17] + [80, 0]  # crosses 80 cells alone: a chunk of its own
    crossings = np.abs(last - first).sum(axis=1) + 1
    chunks = list(baselines._chunks_by_crossings(first, last, max_rows=7))
    assert chunks[0][0] == 0 and chunks[-1][1] == 200
    assert all(a[1] == b[0] for a, b in zip(chunks, chunks[1:], strict=False))
    assert (17, 18) in chunks
    for lo, hi in chunks:
        assert 1 <= hi - lo <= 7
        assert hi - lo == 1 or crossings[lo:hi].sum() <= 50
        # As many rows as fit: one more would pass the budget or the row count.
        if hi < 200 and hi - lo < 7:
            assert crossings[lo : hi + 1].sum() > 50


@pytest.mark.parametrize(
    "estimator, per_scan",
    [(OccupancyGridMap, False), (OccupancyGridMap, True), (FrequencyGridMap, False)],
)
def test_grids_do_not_depend_on_how_the_beams_are_chunked(monkeypatch, estimator, per_scan):
    import skoccmap.baselines as baselines

    scans = make_office_scans(n_poses=4, n_beams=30, random_state=0)
    kwargs = {"scan_index": scans.scan_index} if per_scan else {}
    whole = estimator().fit(scans.X, scans.y, **kwargs)
    monkeypatch.setattr(baselines, "_CROSSINGS_PER_CHUNK", 64)
    chunked = estimator().fit(scans.X, scans.y, **kwargs)
    np.testing.assert_array_equal(chunked.cell_index_, whole.cell_index_)
    np.testing.assert_array_equal(chunked.predict_proba(scans.X), whole.predict_proba(scans.X))


def _loop_reference(X, y, res, l_occ, l_free, l_min, l_max):
    """Per-row log-odds sums with the box-clipping cells, excluding each beam's end cell."""
    n_dims = X.shape[1] // 2
    low = np.floor(np.minimum(X[:, :n_dims], X[:, n_dims:]).min(axis=0) / res) * res
    high = np.maximum(X[:, :n_dims], X[:, n_dims:]).max(axis=0)
    shape = tuple(np.floor((high - low) / res).astype(int) + 1)
    total = {}
    for row, label in zip(X, y, strict=True):
        start, end = row[:n_dims], row[n_dims:]
        end_cell = tuple(np.floor((end - low) / res).astype(int))
        if label == 1:
            total[end_cell] = total.get(end_cell, 0.0) + l_occ
            continue
        cells = _cells_by_slabs(start, end, low, res, shape)
        if len(cells) > 1:
            cells.discard(end_cell)
        for cell in cells:
            total[cell] = total.get(cell, 0.0) + l_free
    return low, {cell: np.clip(v, l_min, l_max) for cell, v in total.items()}


def test_log_odds_match_loop_reference():
    rng = np.random.default_rng(0)
    sensor = rng.uniform(-1, 1, (30, 2))
    hit = sensor + rng.uniform(-3, 3, (30, 2))
    beam_end = hit - 0.05 * (hit - sensor) / np.linalg.norm(hit - sensor, axis=1, keepdims=True)
    X = np.vstack([np.hstack([sensor, beam_end]), np.hstack([hit, hit])])
    y = np.r_[np.zeros(30), np.ones(30)]
    params = dict(l_occ=0.9, l_free=-0.3, l_min=-1.0, l_max=2.0)
    est = OccupancyGridMap(resolution=0.25, **params).fit(X, y)
    origin, ref = _loop_reference(X, y, 0.25, **params)
    np.testing.assert_allclose(est.origin_, origin)
    assert len(ref) == est.cell_index_.size
    cells = np.array(list(ref))
    centers = origin + 0.25 * (cells + 0.5)
    queries = np.hstack([centers, centers])
    np.testing.assert_allclose(est.log_odds(queries), list(ref.values()), atol=1e-12)
    np.testing.assert_allclose(est.predict_proba(queries)[:, 1], expit(list(ref.values())))


def test_unknown_and_outside_are_half():
    X = np.array([[0.0, 0.0, 2.0, 0.0], [2.02, 0.0, 2.02, 0.0], [0.0, 3.0, 0.0, 3.0]])
    est = OccupancyGridMap(resolution=0.1).fit(X, [0, 1, 1])
    queries = np.array([[1.0, 2.0], [50.0, 50.0], [-50.0, 0.0], [1.05, 0.05], [2.05, 0.05]])
    proba = est.predict_proba(np.hstack([queries, queries]))
    np.testing.assert_allclose(proba[:3], 0.5)  # never observed / outside the grid
    assert proba[3, 1] < 0.5 < proba[4, 1]
    np.testing.assert_allclose(proba.sum(axis=1), 1.0)
    np.testing.assert_array_equal(est.predict(np.hstack([queries, queries])), [0, 0, 0, 0, 1])


def test_hit_cell_survives_its_own_beam():
    # A beam stopping 5 cm short of its hit ends in the hit's cell: it must not lower it.
    X = np.array([[0.0, 0.0, 0.98, 0.0], [1.03, 0.0, 1.03, 0.0]] * 3)
    est = OccupancyGridMap(resolution=0.1).fit(X, [0, 1] * 3)
    hit = np.array([[1.03, 0.0, 1.03, 0.0]])
    assert est.log_odds(hit)[0] == pytest.approx(min(3 * 0.85, 3.5))


def test_points_layout_equals_zero_length_segments():
    rng = np.random.default_rng(1)
    points = rng.uniform(-2, 2, (200, 3))
    y = (points[:, 0] > 0).astype(int)
    as_points = OccupancyGridMap(resolution=0.5, layout="points").fit(points, y)
    as_segments = OccupancyGridMap(resolution=0.5).fit(np.hstack([points, points]), y)
    queries = rng.uniform(-2.5, 2.5, (100, 3))
    np.testing.assert_allclose(
        as_points.predict_proba(queries),
        as_segments.predict_proba(np.hstack([queries, queries])),
    )
    # "auto" reads 3 columns as points
    auto = OccupancyGridMap(resolution=0.5).fit(points, y)
    np.testing.assert_allclose(auto.predict_proba(queries), as_points.predict_proba(queries))


def test_3d_room_is_mapped():
    # A sensor at the centre of a 4 m cube room, beams to the walls.
    rng = np.random.default_rng(2)
    directions = rng.normal(size=(2000, 3))
    directions /= np.abs(directions).max(axis=1, keepdims=True)  # hit the cube faces
    hits = 1.95 * directions
    beam_ends = hits * (1 - 0.05 / np.linalg.norm(hits, axis=1, keepdims=True))
    X = np.vstack([np.hstack([np.zeros_like(hits), beam_ends]), np.hstack([hits, hits])])
    y = np.r_[np.zeros(len(hits)), np.ones(len(hits))]
    est = OccupancyGridMap(resolution=0.2).fit(X, y)
    inside = rng.uniform(-1.5, 1.5, (500, 3))
    wall = 1.95 * directions[:500]
    p_in = est.predict_proba(np.hstack([inside, inside]))[:, 1]
    p_wall = est.predict_proba(np.hstack([wall, wall]))[:, 1]
    assert np.mean(p_in < 0.5) > 0.95
    assert np.mean(p_wall > 0.5) > 0.8


def test_bad_input():
    X = np.zeros((4, 4))
    with pytest.raises(ValueError, match="2 classes"):
        OccupancyGridMap().fit(X, [1, 1, 1, 1])
    with pytest.raises(ValueError, match="Only binary"):
        OccupancyGridMap().fit(X, [0, 1, 2, 1])
    with pytest.raises(ValueError, match="NaN"):
        OccupancyGridMap().fit(np.full((4, 4), np.nan), [0, 1, 0, 1])
    with pytest.raises(ValueError, match="layout='segments'"):
        OccupancyGridMap(layout="segments").fit(np.zeros((4, 3)), [0, 1, 0, 1])
    with pytest.raises(ValueError, match="l_min"):
        OccupancyGridMap(l_min=0.0, l_max=0.0).fit(X, [0, 1, 0, 1])
    with pytest.raises(ValueError, match="resolution"):
        OccupancyGridMap(resolution=0).fit(X, [0, 1, 0, 1])
    # One reading far off the map: too many cells to index.
    far = np.array([[0.0, 0.0, 1.0, 0.0], [3e9, 3e9, 3e9, 3e9]])
    for grid in (OccupancyGridMap, FrequencyGridMap):
        with pytest.raises(ValueError, match="far off the map"):
            grid().fit(far, [0, 1])
    # A beam that fits the index but crosses a billion cells: refused before traversal.
    failed_range = np.array([[0.0, 0.0, 1e8, 0.0], [0.0, 0.0, 0.0, 1.0]])
    for fit in (
        OccupancyGridMap().fit,
        FrequencyGridMap().fit,
        lambda X, y: OccupancyGridMap().fit(X, y, scan_index=[0, 1]),
    ):
        with pytest.raises(ValueError, match="crosses 1,000,000,001 grid cells"):
            fit(failed_range, [0, 1])
    with pytest.raises(NotFittedError):
        OccupancyGridMap().predict_proba(X)
    est = OccupancyGridMap().fit(X, [0, 1, 0, 1])
    with pytest.raises(ValueError, match="features"):
        est.predict_proba(np.zeros((2, 6)))


def test_string_labels_larger_is_occupied():
    X = np.array([[0.0, 0.0, 0.48, 0.0], [0.53, 0.0, 0.53, 0.0]])
    est = OccupancyGridMap(resolution=0.1).fit(X, ["free", "wall"])
    np.testing.assert_array_equal(est.classes_, ["free", "wall"])
    queries = np.array([[0.53, 0.0, 0.53, 0.0], [0.2, 0.0, 0.2, 0.0]])
    np.testing.assert_array_equal(est.predict(queries), ["wall", "free"])


@pytest.mark.parametrize("estimator", [OccupancyGridMap, FrequencyGridMap])
def test_origin_rounding_above_the_data(estimator):
    # floor(0.85 / 0.05) * 0.05 rounds above 0.85: the grid must still hold the point.
    X = np.array([[0.85, 0.85, 0.85, 0.85], [1.0, 1.0, 1.0, 1.0]])
    est = estimator(resolution=0.05).fit(X, [1, 0])
    assert np.all(est.origin_ <= 0.85) and min(est.shape_) >= 1
    assert est.cell_index_.size == 2
    assert est.predict_proba(X)[0, 1] > 0.5 > est.predict_proba(X)[1, 1]


def test_chunking_does_not_change_result():
    rng = np.random.default_rng(3)
    X = rng.uniform(-3, 3, (500, 4))
    y = rng.integers(0, 2, 500)
    a = OccupancyGridMap(resolution=0.2, chunk_size=7).fit(X, y)
    b = OccupancyGridMap(resolution=0.2).fit(X, y)
    np.testing.assert_array_equal(a.cell_index_, b.cell_index_)
    np.testing.assert_allclose(a.log_odds_, b.log_odds_)


def test_sparse_accumulation_equals_dense(monkeypatch):
    import skoccmap.baselines as baselines

    rng = np.random.default_rng(4)
    X = rng.uniform(-3, 3, (300, 4))
    y = rng.integers(0, 2, 300)
    dense = OccupancyGridMap(resolution=0.2).fit(X, y)
    monkeypatch.setattr(baselines, "_DENSE_CELL_LIMIT", 10)
    sparse = OccupancyGridMap(resolution=0.2).fit(X, y)
    np.testing.assert_array_equal(sparse.cell_index_, dense.cell_index_)
    np.testing.assert_allclose(sparse.log_odds_, dense.log_odds_)


@pytest.mark.parametrize("grid", [FrequencyGridMap(0.1), OccupancyGridMap(0.1)])
def test_grid_reaches_free_rows_ending_below_every_start(grid):
    # A beam without a return, drawn from x = 1 back to x = -1, beyond every row's start:
    # the grid must hold its end, and it passes the cells up to its end cell.
    X = np.array([[1.05, 0.05, 1.05, 0.05], [1.0, 0.05, -1.0, 0.05]])
    est = clone(grid).fit(X, [1, 0])
    assert np.all(est.origin_ <= [-1.0, 0.05])
    queries = np.array([[x, 0.05] * 2 for x in (-0.85, -0.55, 0.55, 0.95)])
    np.testing.assert_array_less(est.predict_proba(queries)[:, 1], 0.5)
    # The end cell is not passed; beyond it is outside the grid.
    beyond = np.array([[-0.95, 0.05] * 2, [-1.5, 0.05] * 2])
    np.testing.assert_allclose(est.predict_proba(beyond)[:, 1], 0.5)


@pytest.mark.parametrize("grid", [FrequencyGridMap(0.25), OccupancyGridMap(0.25)])
def test_grid_extent_is_the_grid_of_cells_and_covers_the_data(grid):
    rng = np.random.default_rng(15)
    X = rng.uniform(-3, 2, (60, 4))
    est = clone(grid).fit(X, rng.integers(0, 2, 60))
    lower, upper = est.extent_[0::2], est.extent_[1::2]
    np.testing.assert_allclose(lower, est.origin_)
    np.testing.assert_allclose((upper - lower) / 0.25, est.shape_)
    points = np.vstack([X[:, :2], X[:, 2:]])
    assert np.all(points >= lower) and np.all(points < upper)


@pytest.mark.parametrize("grid", [FrequencyGridMap(0.1), OccupancyGridMap(0.1)])
def test_max_free_length_is_the_euclidean_length(grid):
    # A beam 3 m along x and 4 m along y is 5 m long: a bound of 4.5 m drops it (its longest
    # coordinate difference, 4 m, would keep it), a bound of 5 m keeps it.
    hit, beam = [3.05, 4.05] * 2, [0.05, 0.05, 3.05, 4.05]
    X, y = np.array([hit, beam]), [1, 0]
    query = np.array([[1.55, 2.05] * 2])  # on the beam, halfway
    assert clone(grid).set_params(max_free_length=4.5).fit(X, y).predict_proba(query)[0, 1] == 0.5
    assert clone(grid).set_params(max_free_length=5.0).fit(X, y).predict_proba(query)[0, 1] < 0.5


@pytest.mark.parametrize("grid", [FrequencyGridMap(0.1), OccupancyGridMap(0.1)])
def test_grid_looks_segment_queries_up_at_their_midpoint(grid):
    # A beam along y = 0.05 to a hit at x = 1.05: a query segment from the free cell at
    # x = 0.55 to x = 1.55 has its midpoint in the hit's cell; reversed, the same.
    X = np.array([[0.0, 0.05, 1.0, 0.05], [1.05, 0.05, 1.05, 0.05]])
    est = clone(grid).fit(X, [0, 1])
    at_hit = est.predict_proba(np.array([[1.05, 0.05] * 2]))
    for query in ([0.55, 0.05, 1.55, 0.05], [1.55, 0.05, 0.55, 0.05]):
        np.testing.assert_allclose(est.predict_proba(np.array([query])), at_hit)
    assert at_hit[0, 1] > 0.5


def test_counting_grid_on_intel(shared_data):
    from skoccmap.datasets._carmen import load_carmen

    # The first 300 scans (a third of the log) keep the test fast.
    scans = load_carmen(shared_data / "intel.gfs.log")[:300]
    train, test = scans[np.arange(len(scans)) % 10 != 0], scans[::10]
    X, y, _ = train.to_observations()
    est = OccupancyGridMap(resolution=0.1).fit(X, y)
    # Held-out hits should mostly land in occupied cells and mid-beam points in free ones.
    hits = test.hit_points()
    directions = test.directions()[test.returned()]
    origins = np.broadcast_to(test.origins()[:, None], test.directions().shape)[test.returned()]
    ranges = test.ranges[test.returned()]
    middle = origins + 0.5 * ranges[:, None] * directions
    p_hit = est.predict_proba(np.hstack([hits, hits]))[:, 1]
    p_mid = est.predict_proba(np.hstack([middle, middle]))[:, 1]
    assert np.mean(p_hit > 0.5) > 0.6
    assert np.mean(p_mid < 0.5) > 0.9


def test_baselines_heldout_auc_on_intel(shared_data):
    from skoccmap.datasets import load_carmen
    from skoccmap.metrics import heldout_auc, split_scans

    # The first 300 scans, every 10th held out. Clamping once saturates the cells the robot
    # sees again and again; clamping per scan and the unclamped frequencies do not (AUC 0.907,
    # 0.946, 0.972 when written).
    train, test = split_scans(load_carmen(shared_data / "intel.gfs.log")[:300], 10)
    X, y, _, scan = train.to_observations(return_scan_index=True)
    auc = {
        "summed": OccupancyGridMap().fit(X, y),
        "per scan": OccupancyGridMap().fit(X, y, scan_index=scan),
        "frequency": FrequencyGridMap().fit(X, y),
        "hilbert": HilbertMap(n_components=300, max_samples=10_000, random_state=0).fit(X, y),
    }
    auc = {name: heldout_auc(est, test, random_state=0) for name, est in auc.items()}
    assert auc["per scan"] > auc["summed"] + 0.02
    assert auc["frequency"] > 0.95
    assert auc["hilbert"] > 0.85


# --------------------------------------------------------------------------------------------
# OccupancyGridMap: OctoMap's per-scan update
# --------------------------------------------------------------------------------------------

_HIT = [1.05, 0.05, 1.05, 0.05]  # in cell (10, 0) of a 0.1 m grid
_BEAM = [0.0, 0.05, 2.0, 0.05]  # passes cells (0..19, 0), cell (10, 0) among them


def _log_odds_at_hit(X, y, **fit_params):
    est = OccupancyGridMap(resolution=0.1).fit(np.array(X), y, **fit_params)
    return est.log_odds(np.array([_HIT]))[0]


def test_per_scan_hit_wins_over_passes_in_the_same_scan():
    # Scan 0: two hits in the cell and two beams through it -> one hit update, nothing else.
    X, y = [_HIT, _BEAM, _HIT, _BEAM], [1, 0, 1, 0]
    assert _log_odds_at_hit(X, y, scan_index=[0, 0, 0, 0]) == pytest.approx(0.85)
    assert _log_odds_at_hit(X, y) == pytest.approx(2 * 0.85 - 2 * 0.4)
    # A cell both beams pass, no hit: one free update in the scan.
    est = OccupancyGridMap(resolution=0.1).fit(np.array(X), y, scan_index=[0, 0, 0, 0])
    assert est.log_odds(np.array([[0.55, 0.05, 0.55, 0.05]]))[0] == pytest.approx(-0.4)
    # In separate scans every row is one update again.
    assert _log_odds_at_hit(X, y, scan_index=[0, 1, 2, 3]) == pytest.approx(2 * 0.85 - 2 * 0.4)


def test_per_scan_clamps_after_every_scan():
    # Five scans hit the cell (0.85 each: 3.4 after four, clamped to 3.5 after the fifth); a
    # sixth passes it: 3.5 - 0.4. Summed, 4.25 - 0.4 = 3.85 is clamped to 3.5.
    X, y = [_HIT] * 5 + [_BEAM], [1] * 5 + [0]
    assert _log_odds_at_hit(X, y, scan_index=np.arange(6)) == pytest.approx(3.1)
    assert _log_odds_at_hit(X, y) == pytest.approx(3.5)
    # The pass first: -0.4, then 3.0, then 3.5 (clamped from 3.85) after four hits more.
    assert _log_odds_at_hit(X, y, scan_index=[1, 2, 3, 4, 5, 0]) == pytest.approx(3.5)
    # The lower bound: six passes reach -2.4, clamped to -2.0 after the sixth; a hit adds 0.85.
    X, y = [_BEAM] * 6 + [_HIT], [0] * 6 + [1]
    assert _log_odds_at_hit(X, y, scan_index=np.arange(7)) == pytest.approx(-1.15)
    assert _log_odds_at_hit(X, y) == pytest.approx(-2.4 + 0.85)


def test_per_scan_order_is_the_scan_index_not_the_row_order():
    X = np.array([_HIT] * 5 + [_BEAM])
    y = np.array([1] * 5 + [0])
    scan = np.array([30, 10, 20, 40, 50, 60])  # any integers; the pass comes last
    rng = np.random.default_rng(0)
    for _ in range(3):
        perm = rng.permutation(6)
        assert _log_odds_at_hit(X[perm], y[perm], scan_index=scan[perm]) == pytest.approx(3.1)
    # Integer-valued floats are scan indices too.
    assert _log_odds_at_hit(X, y, scan_index=scan.astype(float)) == pytest.approx(3.1)


def test_per_scan_equals_sum_without_clamping():
    # One row per scan and bounds never reached: the same updates, summed.
    rng = np.random.default_rng(5)
    X = rng.uniform(-3, 3, (400, 4))
    X[::3, 2:] = X[::3, :2]  # some hits and free points
    y = rng.integers(0, 2, 400)
    params = dict(resolution=0.2, l_min=-1e6, l_max=1e6)
    summed = OccupancyGridMap(**params).fit(X, y)
    per_scan = OccupancyGridMap(**params).fit(X, y, scan_index=rng.permutation(400))
    np.testing.assert_array_equal(per_scan.cell_index_, summed.cell_index_)
    np.testing.assert_allclose(per_scan.log_odds_, summed.log_odds_, atol=1e-9)


def _per_scan_reference(X, y, scan, res, l_occ, l_free, l_min, l_max):
    """OctoMap's update, one scan and one cell at a time (box-clipping cells)."""
    n_dims = X.shape[1] // 2
    low = np.floor(np.minimum(X[:, :n_dims], X[:, n_dims:]).min(axis=0) / res) * res
    high = np.maximum(X[:, :n_dims], X[:, n_dims:]).max(axis=0)
    shape = tuple(np.floor((high - low) / res).astype(int) + 1)
    value = {}
    for s in np.unique(scan):
        occupied, free = set(), set()
        for row, label in zip(X[scan == s], y[scan == s], strict=True):
            start, end = row[:n_dims], row[n_dims:]
            end_cell = tuple(np.floor((end - low) / res).astype(int))
            if label == 1:
                occupied.add(end_cell)
                continue
            cells = _cells_by_slabs(start, end, low, res, shape)
            if len(cells) > 1:
                cells.discard(end_cell)
            free |= cells
        for cell in free - occupied:
            value[cell] = np.clip(value.get(cell, 0.0) + l_free, l_min, l_max)
        for cell in occupied:
            value[cell] = np.clip(value.get(cell, 0.0) + l_occ, l_min, l_max)
    return low, value


@pytest.mark.parametrize("chunk_size", [5, 100_000])
def test_per_scan_matches_reference(chunk_size):
    # A few sensors sweeping beams over a box room, 12 scans, many repeated cells.
    rng = np.random.default_rng(6)
    rows, labels, scans = [], [], []
    for s in range(12):
        sensor = rng.uniform(-0.5, 0.5, 2)
        angle = rng.uniform(0, 2 * np.pi, 15)
        direction = np.column_stack([np.cos(angle), np.sin(angle)])
        reach = 1.5 / np.abs(direction).max(axis=1)
        hit = sensor + reach[:, None] * direction
        beam_end = hit - 0.03 * direction
        rows += [np.hstack([np.tile(sensor, (15, 1)), beam_end]), np.hstack([hit, hit])]
        labels += [np.zeros(15), np.ones(15)]
        scans += [np.full(30, s)]
    X, y, scan = np.vstack(rows), np.concatenate(labels), np.concatenate(scans)
    params = dict(l_occ=0.9, l_free=-0.7, l_min=-1.5, l_max=2.0)
    est = OccupancyGridMap(resolution=0.25, chunk_size=chunk_size, **params)
    est.fit(X, y, scan_index=scan)
    origin, ref = _per_scan_reference(X, y, scan, 0.25, **params)
    assert len(ref) == est.cell_index_.size
    cells = np.array(list(ref))
    centers = origin + 0.25 * (cells + 0.5)
    np.testing.assert_allclose(
        est.log_odds(np.hstack([centers, centers])), list(ref.values()), atol=1e-12
    )
    # Evidence lost at the bounds: the per-scan map differs from the summed one here.
    summed = OccupancyGridMap(resolution=0.25, **params).fit(X, y)
    assert not np.allclose(summed.log_odds_, est.log_odds_)


@pytest.mark.parametrize(
    ("scan_index", "match"),
    [
        (np.arange(3), "one scan index per row"),
        (np.arange(8).reshape(4, 2), "one scan index per row"),
        ([0.0, 1.0, np.nan, 2.0], "NaN"),
        ([0.0, 1.0, np.inf, 2.0], "NaN or infinite"),
        ([0.0, 0.5, 1.0, 2.0], "integers"),
        (["a", "b", "c", "d"], "integers"),
    ],
)
def test_scan_index_errors(scan_index, match):
    with pytest.raises(ValueError, match=match):
        OccupancyGridMap().fit(np.zeros((4, 4)), [0, 1, 0, 1], scan_index=scan_index)


# --------------------------------------------------------------------------------------------
# FrequencyGridMap
# --------------------------------------------------------------------------------------------


def test_frequency_hand_built_rays():
    # Three beams pass cell (5, 0) and one hit falls in it: 1 / (1 + 3). Cell (2, 0) is only
    # passed, cell (12, 10) only hit, cell (10, 20) never observed.
    X = np.array([_BEAM] * 3 + [[0.55, 0.05] * 2, [1.25, 1.05] * 2, [0.0, 3.05] * 2])
    y = [0, 0, 0, 1, 1, 1]
    est = FrequencyGridMap(resolution=0.1).fit(X, y)
    queries = np.array([[0.55, 0.05], [0.25, 0.05], [1.25, 1.05], [1.05, 2.05], [9.0, 9.0]])
    proba = est.predict_proba(np.hstack([queries, queries]))
    np.testing.assert_allclose(proba[:, 1], [0.25, 0.0, 1.0, 0.5, 0.5])
    np.testing.assert_allclose(proba.sum(axis=1), 1.0)
    np.testing.assert_array_equal(est.predict(np.hstack([queries, queries])), [0, 0, 1, 0, 0])
    # The beams' end cell (20, 0) is not passed: they end there. A free point passes its cell.
    end = np.array([[2.0, 0.05, 2.0, 0.05]])
    assert est.predict_proba(end)[0, 1] == 0.5
    point = FrequencyGridMap(resolution=0.1).fit(np.vstack([end, end, [_HIT]]), [0, 0, 1])
    assert point.predict_proba(end)[0, 1] == 0.0
    assert point.hits_.tolist() == [1, 0] and point.passes_.tolist() == [0, 2]  # x: 1.05, 2.0


@pytest.mark.parametrize("grid", [FrequencyGridMap(0.1), OccupancyGridMap(0.1)])
def test_free_rows_beyond_max_free_length_pass_no_cell(grid):
    # A 3 m beam through the hit's cell and a 1 m beam: with a 2 m bound only the short one
    # counts, as if the long one were not there.
    hit, short, long = [0.55, 0.05] * 2, [0.0, 0.05, 1.0, 0.05], [0.0, 0.05, 3.0, 0.05]
    X, y = np.array([hit, short, long]), [1, 0, 0]
    queries = np.array([hit, [0.25, 0.05] * 2, [2.05, 0.05] * 2])
    bounded = clone(grid).set_params(max_free_length=2.0).fit(X, y)
    without = clone(grid).fit(X[:2], y[:2])
    everything = clone(grid).fit(X, y)
    np.testing.assert_allclose(bounded.predict_proba(queries), without.predict_proba(queries))
    assert bounded.predict_proba(queries)[2, 1] == 0.5  # only the long beam passed it
    assert everything.predict_proba(queries)[0, 1] < bounded.predict_proba(queries)[0, 1]
    # A row exactly as long as the bound counts.
    at_bound = clone(grid).set_params(max_free_length=3.0).fit(X, y)
    np.testing.assert_allclose(at_bound.predict_proba(queries), everything.predict_proba(queries))


def test_frequency_grid_predicts_occupied_only_above_one_half():
    # One hit and one pass in a cell: p = 1/2, which predict reads as free.
    est = FrequencyGridMap(resolution=0.1).fit(np.array([_BEAM, _HIT]), [0, 1])
    assert est.predict_proba(np.array([_HIT]))[0, 1] == 0.5
    assert est.predict(np.array([_HIT]))[0] == 0


def test_frequency_counts_match_loop_reference():
    rng = np.random.default_rng(7)
    sensor = rng.uniform(-1, 1, (40, 2))
    hit = sensor + rng.uniform(-3, 3, (40, 2))
    beam_end = hit - 0.05 * (hit - sensor) / np.linalg.norm(hit - sensor, axis=1, keepdims=True)
    X = np.vstack([np.hstack([sensor, beam_end]), np.hstack([hit, hit])])
    y = np.r_[np.zeros(40), np.ones(40)]
    est = FrequencyGridMap(resolution=0.25, chunk_size=9).fit(X, y)
    inf = dict(l_min=-np.inf, l_max=np.inf)
    origin, hits = _loop_reference(X, y, 0.25, l_occ=1.0, l_free=0.0, **inf)
    _, passes = _loop_reference(X, y, 0.25, l_occ=0.0, l_free=1.0, **inf)
    cells = np.array(list(hits))
    centers = np.hstack([origin + 0.25 * (cells + 0.5)] * 2)
    pos = est._cell_position(centers)
    np.testing.assert_array_equal(est.hits_[pos], list(hits.values()))
    np.testing.assert_array_equal(est.passes_[pos], [passes[c] for c in hits])
    h, p = np.array(list(hits.values())), np.array([passes[c] for c in hits])
    np.testing.assert_allclose(est.predict_proba(centers)[:, 1], h / (h + p))
    # The same cells as the log-odds grid: sharing one traversal.
    grid = OccupancyGridMap(resolution=0.25).fit(X, y)
    np.testing.assert_array_equal(est.cell_index_, grid.cell_index_)


def test_frequency_does_not_saturate():
    # 50 hits and 10 passes: 50/60, where a clamped log-odds grid sits at its bound.
    X = np.array([_HIT] * 50 + [_BEAM] * 10)
    y = [1] * 50 + [0] * 10
    est = FrequencyGridMap().fit(X, y)
    assert est.predict_proba(np.array([_HIT]))[0, 1] == pytest.approx(50 / 60)


def test_frequency_3d_and_points_layout():
    rng = np.random.default_rng(8)
    points = rng.uniform(-2, 2, (300, 3))
    y = (points[:, 2] > 1).astype(int)
    as_points = FrequencyGridMap(resolution=0.5).fit(points, y)  # "auto": 3 columns
    as_segments = FrequencyGridMap(resolution=0.5).fit(np.hstack([points, points]), y)
    queries = rng.uniform(-2, 2, (50, 3))
    np.testing.assert_allclose(
        as_points.predict_proba(queries), as_segments.predict_proba(np.hstack([queries] * 2))
    )
    assert as_points.predict_proba(np.array([[0.0, 0.0, 1.5]]))[0, 1] > 0.5


def test_frequency_bad_input():
    with pytest.raises(ValueError, match="2 classes"):
        FrequencyGridMap().fit(np.zeros((4, 4)), [1, 1, 1, 1])
    with pytest.raises(ValueError, match="NaN"):
        FrequencyGridMap().fit(np.full((4, 4), np.nan), [0, 1, 0, 1])
    with pytest.raises(ValueError, match="layout='segments'"):
        FrequencyGridMap(layout="segments").fit(np.zeros((4, 3)), [0, 1, 0, 1])
    with pytest.raises(NotFittedError):
        FrequencyGridMap().predict_proba(np.zeros((4, 4)))


# --------------------------------------------------------------------------------------------
# HilbertMap
# --------------------------------------------------------------------------------------------


def _room_scans(n_poses, n_beams, rng, n_dims=2, half=2.0):
    """Beams from random poses inside a box room to its walls: rows, labels, the hits."""
    sensors = rng.uniform(-0.6 * half, 0.6 * half, (n_poses, n_dims))
    direction = rng.normal(size=(n_poses, n_beams, n_dims))
    direction /= np.linalg.norm(direction, axis=2, keepdims=True)
    # Distance to the first wall along each beam.
    with np.errstate(divide="ignore"):
        reach = np.min((half - np.sign(direction) * sensors[:, None]) / np.abs(direction), axis=2)
    hits = (sensors[:, None] + reach[..., None] * direction).reshape(-1, n_dims)
    direction = direction.reshape(-1, n_dims)
    starts = np.repeat(sensors, n_beams, axis=0)
    beam_ends = hits - 0.05 * direction
    X = np.vstack([np.hstack([starts, beam_ends]), np.hstack([hits, hits])])
    y = np.r_[np.zeros(len(hits)), np.ones(len(hits))]
    return X, y, hits


def _wall_and_free_auc(est, rng, n_dims=2, half=2.0):
    """AUC on fresh hits on the walls against fresh points inside the room."""
    _, _, wall = _room_scans(10, 30, rng, n_dims, half)
    inside = rng.uniform(-0.8 * half, 0.8 * half, (len(wall), n_dims))
    points = np.vstack([wall, inside])
    labels = np.r_[np.ones(len(wall)), np.zeros(len(inside))]
    return roc_auc_score(labels, est.predict_proba(np.hstack([points, points]))[:, 1])


def test_hilbert_map_separates_walls_from_free_space():
    rng = np.random.default_rng(10)
    X, y, _ = _room_scans(20, 40, rng)
    est = HilbertMap(n_components=300, random_state=0).fit(X, y)
    assert _wall_and_free_auc(est, rng) > 0.9
    proba = est.predict_proba(X)
    np.testing.assert_allclose(proba.sum(axis=1), 1.0)
    np.testing.assert_allclose(proba[:, 1], expit(est.decision_function(X)), atol=1e-6)
    assert est.n_iter_ >= 1 and est.n_training_points_ <= 50_000


def test_hilbert_map_is_deterministic_with_random_state():
    rng = np.random.default_rng(11)
    X, y, _ = _room_scans(10, 30, rng)
    queries = rng.uniform(-2, 2, (200, 2))
    queries = np.hstack([queries, queries])
    params = dict(n_components=100, max_samples=500)
    a = HilbertMap(random_state=3, **params).fit(X, y).predict_proba(queries)
    b = HilbertMap(random_state=3, **params).fit(X, y).predict_proba(queries)
    c = HilbertMap(random_state=4, **params).fit(X, y).predict_proba(queries)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_hilbert_map_3d():
    rng = np.random.default_rng(12)
    X, y, _ = _room_scans(10, 200, rng, n_dims=3)
    est = HilbertMap(n_components=300, random_state=0).fit(X, y)
    assert est.nystroem_.components_.shape == (300, 3)
    assert _wall_and_free_auc(est, rng, n_dims=3) > 0.85


def test_hilbert_map_training_points():
    # A hit, a 2 m free beam (4 points, one every 0.5 m: the centres of 4 equal pieces) and a
    # zero-length free row (1 point). With as many landmarks, the landmarks are all of them.
    X = np.array([[2.1, 0.0, 2.1, 0.0], [0.0, 0.0, 2.0, 0.0], [0.0, 1.0, 0.0, 1.0]])
    est = HilbertMap(n_components=10, free_spacing=0.5, random_state=0).fit(X, [1, 0, 0])
    assert est.n_training_points_ == 6
    landmarks = (est.nystroem_.components_ + est.center_).round(9).tolist()
    landmarks = sorted(map(tuple, landmarks))
    expected = [(0.0, 1.0), (0.25, 0.0), (0.75, 0.0), (1.25, 0.0), (1.75, 0.0), (2.1, 0.0)]
    assert landmarks == expected
    # A spacing that does not divide the length: ceil(2 / 0.8) = 3 points.
    est = HilbertMap(n_components=10, free_spacing=0.8, random_state=0).fit(X, [1, 0, 0])
    assert est.n_training_points_ == 5


def test_hilbert_map_does_not_depend_on_where_the_map_lies():
    # The same scan at the origin and at UTM-sized coordinates: the same features (the
    # kernel they approximate between query points). Uncentred, scikit-learn's RBF lost the
    # distances between nearby points there: errors of 0.28 at 1e5 m, 1.6 at 1e7 m.
    angles = np.linspace(-0.6, 0.6, 40)
    ends = np.c_[5 * np.ones(40), 5 * np.tan(angles)]
    X = np.r_[np.c_[np.zeros((40, 2)), ends], np.c_[ends, ends]]
    y = np.r_[np.zeros(40), np.ones(40)]
    queries = np.random.default_rng(0).uniform(0, 6, (200, 2))

    def feature_kernel(offset):
        est = HilbertMap(random_state=0, n_components=80).fit(X + offset, y)
        features = np.vstack(list(est._batches(np.c_[queries, queries] + offset)))
        return features @ features.T

    here = feature_kernel(0.0)
    # At 1e7 m a coordinate is rounded to about 1e-9 m, and the landmarks' inverse square
    # root amplifies that to about 2e-6 of the kernel.
    for offset in (1e5, 1e7):
        np.testing.assert_allclose(feature_kernel(offset), here, atol=1e-4)


def test_hilbert_map_max_samples_keeps_both_classes():
    # One hit among 4000 free points: a draw of 20 still holds the hit.
    X = np.array([[9.0, 0.0, 9.0, 0.0]] + [[0.0, 0.0, 0.0, 50.0]] * 40)
    y = [1] + [0] * 40
    params = dict(n_components=20, max_free_length=None, random_state=0)
    est = HilbertMap(free_spacing=0.5, max_samples=20, **params).fit(X, y)
    assert est.n_training_points_ == 20
    assert [9.0, 0.0] in (est.nystroem_.components_ + est.center_).tolist()
    every = HilbertMap(max_samples=None, **params).fit(X, y)
    assert every.n_training_points_ == 1 + 40 * 100


@pytest.mark.parametrize("kept, hits_kept", [(20, 2), (29, 3)])
def test_hilbert_map_max_samples_keeps_the_classes_in_proportion(kept, hits_kept):
    # 10 hits and 90 free points (zero-length free rows): 20 kept are 2 hits and 18 free;
    # 29 kept are 2.9 hits in proportion, rounded (not floored) to 3 hits and 26 free.
    rng = np.random.default_rng(3)
    points = rng.uniform(0, 5, size=(100, 2))
    hit = np.arange(100) < 10
    est = HilbertMap(max_samples=kept, max_free_length=None)
    _, labels = est._training_points(points, points, hit, np.random.RandomState(0))
    assert labels.size == kept and labels.sum() == hits_kept


def test_hilbert_map_skips_free_rows_beyond_max_free_length():
    # A 50 m beam (no return) and a 2 m one: by default only the short one gives points.
    X = np.array([[2.1, 0.0, 2.1, 0.0], [0.0, 0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 50.0]])
    est = HilbertMap(n_components=10, random_state=0).fit(X, [1, 0, 0])
    assert est.n_training_points_ == 1 + 4
    est = HilbertMap(n_components=10, max_free_length=None, random_state=0).fit(X, [1, 0, 0])
    assert est.n_training_points_ == 1 + 4 + 100
    with pytest.raises(ValueError, match="every free row is longer than max_free_length=1"):
        HilbertMap(max_free_length=1.0).fit(X, [1, 0, 0])


def test_hilbert_map_labels_and_class_weight():
    rng = np.random.default_rng(13)
    X, y, _ = _room_scans(5, 20, rng)
    labels = np.where(y == 1, "wall", "free")
    weights = {"free": 1.0, "wall": 5.0}
    params = dict(n_components=50, alpha=1e-3, random_state=0)
    est = HilbertMap(class_weight=weights, **params).fit(X, labels)
    np.testing.assert_array_equal(est.classes_, ["free", "wall"])
    assert est.classifier_.class_weight == {0: 1.0, 1: 5.0}
    assert set(est.predict(X)) <= {"free", "wall"}
    # More weight on the walls raises the probabilities over the room.
    plain = HilbertMap(**params).fit(X, labels)
    queries = rng.uniform(-2, 2, (500, 2))
    queries = np.hstack([queries, queries])
    assert (
        est.predict_proba(queries)[:, 1].mean() > plain.predict_proba(queries)[:, 1].mean() + 0.05
    )
    with pytest.raises(ValueError, match="class_weight has a weight for class 'door'"):
        HilbertMap(class_weight={"door": 2.0}).fit(X, labels)


def test_hilbert_map_bad_input():
    X = np.zeros((4, 4))
    with pytest.raises(ValueError, match="2 classes"):
        HilbertMap().fit(X, [1, 1, 1, 1])
    with pytest.raises(ValueError, match="Only binary"):
        HilbertMap().fit(X, [0, 1, 2, 1])
    with pytest.raises(ValueError, match="NaN"):
        HilbertMap().fit(np.full((4, 4), np.nan), [0, 1, 0, 1])
    with pytest.raises(ValueError, match="free_spacing"):
        HilbertMap(free_spacing=0.0).fit(X, [0, 1, 0, 1])
    with pytest.raises(ValueError, match="max_samples"):
        HilbertMap(max_samples=1).fit(X, [0, 1, 0, 1])
    # numpy's "SVD did not converge" from the landmarks' kernel.
    beams = X + np.arange(4)[:, None] + np.array([[0.0, 0.0, 1.0, 0.0]])
    far = np.r_[beams, [[1e200, 0.0, 1e200, 0.0]]]
    with pytest.raises(ValueError, match=r"up to 1e\+200.*Rescale or shift"):
        HilbertMap(random_state=0).fit(far, [0, 1, 0, 1, 1])
    with pytest.raises(NotFittedError):
        HilbertMap().predict(X)
    est = HilbertMap(n_components=4, random_state=0).fit(X + np.arange(4)[:, None], [0, 1, 0, 1])
    with pytest.raises(ValueError, match="features"):
        est.predict_proba(np.zeros((2, 6)))


def test_hilbert_map_queries_are_looked_up_at_their_midpoint():
    rng = np.random.default_rng(16)
    X, y, _ = _room_scans(5, 20, rng)
    est = HilbertMap(n_components=50, random_state=0).fit(X, y)
    starts, ends = rng.uniform(-2, 2, (2, 30, 2))
    mid = 0.5 * (starts + ends)
    np.testing.assert_allclose(
        est.decision_function(np.hstack([starts, ends])),
        est.decision_function(np.hstack([mid, mid])),
        atol=1e-6,
    )


def test_hilbert_map_default_kernel_is_exp_of_minus_squared_distance():
    # gamma defaults to 1 / m^2: with every training point a landmark, the features' inner
    # products between training points are exp(-|x - x'|^2) (Nystroem is exact there).
    X = np.array([[0.0, 0.0, 1.5, 0.0], [1.6, 0.0, 1.6, 0.0], [0.0, 0.0, 0.0, 1.0]])
    est = HilbertMap(n_components=10, random_state=0).fit(X, [0, 1, 0])
    points = est.nystroem_.components_ + est.center_
    features = np.vstack(list(est._batches(np.hstack([points, points]))))
    distance2 = ((points[:, None] - points[None]) ** 2).sum(axis=2)
    np.testing.assert_allclose(features @ features.T, np.exp(-distance2), atol=1e-8)


def test_hilbert_map_random_state_seeds_the_sgd_passes():
    # Every training point kept and every one a landmark: only the order of the SGD passes
    # (and of the landmarks, which does not change the fitted function) depends on the seed.
    rng = np.random.default_rng(17)
    X, y, _ = _room_scans(3, 10, rng)
    queries = rng.uniform(-2, 2, (100, 2))
    queries = np.hstack([queries, queries])
    fits = [
        HilbertMap(n_components=500, max_samples=None, alpha=1e-3, random_state=seed).fit(X, y)
        for seed in (0, 1)
    ]
    assert fits[0].n_training_points_ <= 500
    a, b = (est.decision_function(queries) for est in fits)
    assert np.abs(a - b).max() > 1e-3


def test_hilbert_map_class_weight_zero_is_allowed():
    # A weight of 0 drops a class from the loss; the check asks for >= 0.
    X = np.array([[0.0, 0.0, 0.9, 0.0], [1.0, 0.0, 1.0, 0.0]])
    est = HilbertMap(n_components=4, class_weight={0: 1.0, 1: 0.0}, random_state=0).fit(X, [0, 1])
    assert est.classifier_.class_weight == {0: 1.0, 1: 0.0}


def test_hilbert_map_free_points_follow_the_euclidean_length():
    # A 3-4-5 beam: 5 m long, so ceil(5 / 0.5) = 10 points; with max_free_length exactly 5
    # it still counts (a bound of 4.9 drops it: no free row left).
    X = np.array([[3.0, 4.0, 3.0, 4.0], [0.0, 0.0, 3.0, 4.0], [0.0, 1.0, 0.0, 1.0]])
    est = HilbertMap(n_components=20, random_state=0).fit(X, [1, 0, 0])
    assert est.n_training_points_ == 1 + 10 + 1
    est = HilbertMap(n_components=20, max_free_length=5.0, random_state=0).fit(X, [1, 0, 0])
    assert est.n_training_points_ == 1 + 10 + 1
    est = HilbertMap(n_components=20, max_free_length=4.9, random_state=0).fit(X, [1, 0, 0])
    assert est.n_training_points_ == 1 + 1


def test_hilbert_map_max_samples_keeps_a_free_point_among_many_hits():
    # 100 hits and one free point, 20 kept: 19.8 hits in proportion, but one free point
    # stays, so both classes are there to fit.
    rng = np.random.default_rng(19)
    points = rng.uniform(0, 5, size=(101, 2))
    X, y = np.hstack([points, points]), np.r_[np.ones(100), 0]
    est = HilbertMap(n_components=10, max_samples=20, random_state=0).fit(X, y)
    assert est.n_training_points_ == 20
    _, labels = est._training_points(points, points, y == 1, np.random.RandomState(0))
    assert labels.sum() == 19


# --------------------------------------------------------------------------------------------
# scikit-learn's estimator checks for the estimators not in tests/test_common.py
# --------------------------------------------------------------------------------------------

# Small: the checks' data sets have tens of rows.
CHECKED = [FrequencyGridMap(), HilbertMap(n_components=50)]


# check_class_weight_classifiers weights one class 10^7 times the other; SGD then need not
# settle within max_iter.
@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
@parametrize_with_checks(CHECKED)
def test_estimator_checks(estimator, check):
    check(estimator)


@pytest.mark.parametrize(
    "estimator", [*CHECKED, OccupancyGridMap()], ids=lambda est: type(est).__name__
)
def test_param_validation(estimator):
    check_param_validation(type(estimator).__name__, estimator)


def test_scan_index_is_an_optional_fit_parameter():
    # scan_index is an optional fit parameter: every row its own scan, in row order, with
    # bounds never reached, is the summed fit; metadata routing can request it.
    rng = np.random.default_rng(9)
    X, y = rng.uniform(-1, 1, (50, 4)), rng.integers(0, 2, 50)
    est = OccupancyGridMap(l_min=-100.0, l_max=100.0)
    np.testing.assert_allclose(
        est.fit(X, y, scan_index=np.arange(50)).log_odds_, clone(est).fit(X, y).log_odds_
    )
    with sklearn.config_context(enable_metadata_routing=True):
        assert est.set_fit_request(scan_index=True) is est


@pytest.mark.parametrize(
    ("starts", "ends", "resolution", "shape", "match"),
    [
        ([[np.nan, 0.05]], [[0.25, 0.15]], 0.1, (3, 2), "segment 0 .* is not finite and inside"),
        ([[0.05, 0.05]], [[0.45, 0.15]], 0.1, (3, 2), "segment 0 .* is not finite and inside"),
        ([[0.05, 0.05]], [[0.25, 0.15]], 0.0, (3, 2), "resolution must be a positive"),
        ([[0.05, 0.05]], [[0.25, 0.15]], -0.1, (3, 2), "resolution must be a positive"),
        ([[0.05, 0.05]], [[0.25, 0.15]], 0.1, (0, 2), "shape must be positive integers"),
        ([0.05, 0.05], [0.25, 0.15], 0.1, (3, 2), "shape .n_segments, n_dims."),
        ([[0.05, 0.05]], [[0.25, 0.15]], 0.1, (3, 2, 2), "one value per dimension"),
    ],
)
def test_traverse_cells_rejects_bad_input(starts, ends, resolution, shape, match):
    with pytest.raises(ValueError, match=match):
        traverse_cells(starts, ends, np.zeros(2), resolution, shape)


# Two beams along the axes, each with its hit.
_TWO_BEAMS = np.array([[0.0, 0.0, 0.9, 0.0], [1.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.9],
                       [0.0, 1.0, 0.0, 1.0]])  # fmt: skip


@pytest.mark.parametrize(
    "estimator", [OccupancyGridMap(resolution=0.5), FrequencyGridMap(resolution=0.5), HilbertMap()]
)
def test_points_as_queries_get_a_hint(estimator):
    estimator.fit(_TWO_BEAMS, [0, 1, 0, 1])
    with pytest.raises(ValueError, match=r"pass skoccmap.as_segments\(points\)"):
        estimator.predict_proba([[0.5, 0.5]])


@pytest.mark.parametrize(
    "estimator", [OccupancyGridMap(resolution=0.5), FrequencyGridMap(resolution=0.5), HilbertMap()]
)
def test_rows_of_different_lengths_are_one_clear_error(estimator):
    # Rows of 2-D and 3-D segments: the hint for points read their shape again, and numpy's
    # error came out of the error handler, chained under "During handling of the above
    # exception, another exception occurred".
    estimator.fit(_TWO_BEAMS, [0, 1, 0, 1])
    ragged = [[0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]]
    calls = [lambda: estimator.predict_proba(ragged)]
    if hasattr(estimator, "partial_fit"):  # a later batch
        calls.append(lambda: estimator.partial_fit(ragged, [0, 1]))
    for call in calls:
        with pytest.raises(ValueError, match="inhomogeneous shape") as info:
            call()
        assert info.value.__context__ is None or info.value.__suppress_context__


@pytest.mark.parametrize(
    "estimator", [OccupancyGridMap(resolution=0.5), FrequencyGridMap(resolution=0.5), HilbertMap()]
)
def test_no_queries_give_empty_predictions(estimator):
    estimator.fit(_TWO_BEAMS, [0, 1, 0, 1])
    assert estimator.predict_proba(np.empty((0, 4))).shape == (0, 2)
    assert estimator.predict(np.empty((0, 4))).shape == (0,)


def test_hilbert_map_refuses_features_beyond_memory():
    # 0.9 m beams sampled every nanometre, unbounded: 1.8e9 points, refused before any
    # is drawn (numpy was asked for tens of GiB); with the default bound they are sampled.
    with pytest.raises(ValueError, match="set max_samples"):
        HilbertMap(free_spacing=1e-9, max_samples=None).fit(_TWO_BEAMS, [0, 1, 0, 1])
    # With one feature per point the points themselves outweigh the features.
    with pytest.raises(ValueError, match="set max_samples"):
        HilbertMap(free_spacing=1e-9, max_samples=None, n_components=1).fit(
            _TWO_BEAMS, [0, 1, 0, 1]
        )
    est = HilbertMap(free_spacing=1e-9, n_components=20).fit(_TWO_BEAMS, [0, 1, 0, 1])
    assert est.n_training_points_ == 50_000


@pytest.mark.parametrize("weight", [np.nan, -1.0, np.inf])
def test_hilbert_map_class_weight_must_be_finite_and_not_negative(weight):
    X = np.array([[0.0, 0.0, 0.9, 0.0], [1.0, 0.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="a finite weight >= 0"):
        HilbertMap(class_weight={1: weight}).fit(X, [0, 1])


def test_traverse_cells_takes_ends_on_the_far_face_far_from_the_origin():
    # A UTM-like origin: ends computed as origin + shape * resolution round to 1e-8 cells
    # outside the grid, which a tolerance of 1e-9 cells refused.
    rng = np.random.default_rng(0)
    for _ in range(50):
        origin = rng.uniform(4e5, 6e5, size=2)
        shape, res = (7, 5), 0.1
        ends = origin + np.array(shape) * res
        seg, cells = traverse_cells(origin[None], ends[None], origin, np.array(res), shape)
        assert cells.min() >= 0 and np.all(cells < shape)


def _scattered_batches(n_rows=20):
    """Four batches of beams and their hits around centres metres apart, so that the grid
    grows below and above its first extent, the last where the first lies; each row's scan
    is its batch's 2 i or 2 i + 1."""
    rng = np.random.default_rng(3)
    batches = []
    for i, centre in enumerate(([0.0, 0.0], [-6.0, 2.0], [5.0, -4.0], [0.5, 0.5])):
        sensor = centre + rng.uniform(-1, 1, (n_rows, 2))
        hit = sensor + rng.uniform(-3, 3, (n_rows, 2))
        end = hit - 0.05 * (hit - sensor) / np.linalg.norm(hit - sensor, axis=1, keepdims=True)
        X = np.vstack([np.hstack([sensor, end]), np.hstack([hit, hit])])
        scan = 2 * i + np.arange(2 * n_rows) % 2
        batches.append((X, np.r_[np.zeros(n_rows), np.ones(n_rows)], scan))
    return batches


def test_frequency_partial_fit_in_batches_is_one_fit_on_all_rows():
    batches = _scattered_batches()
    grid = FrequencyGridMap(resolution=0.25)
    for X, y, _ in batches:
        grid.partial_fit(X, y)
    full = FrequencyGridMap(resolution=0.25).fit(
        np.vstack([b[0] for b in batches]), np.concatenate([b[1] for b in batches])
    )
    assert grid.shape_ == full.shape_
    np.testing.assert_allclose(grid.origin_, full.origin_, atol=1e-12)
    np.testing.assert_allclose(grid.extent_, full.extent_, atol=1e-12)
    np.testing.assert_array_equal(grid.cell_index_, full.cell_index_)
    np.testing.assert_array_equal(grid.hits_, full.hits_)
    np.testing.assert_array_equal(grid.passes_, full.passes_)


def test_log_odds_partial_fit_of_whole_scans_is_one_fit_with_their_scan_index():
    batches = _scattered_batches()
    grid = OccupancyGridMap(resolution=0.25, l_max=1.0)  # a low bound: clamping matters
    for X, y, scan in batches:
        grid.partial_fit(X, y, scan_index=scan)
    full = OccupancyGridMap(resolution=0.25, l_max=1.0).fit(
        np.vstack([b[0] for b in batches]),
        np.concatenate([b[1] for b in batches]),
        scan_index=np.concatenate([b[2] for b in batches]),
    )
    assert grid.shape_ == full.shape_
    np.testing.assert_array_equal(grid.cell_index_, full.cell_index_)
    np.testing.assert_allclose(grid.log_odds_, full.log_odds_, atol=1e-12)


def test_log_odds_partial_fit_sums_each_call_and_clamps_after_it():
    params = dict(l_occ=0.9, l_free=-0.3, l_min=-1.0, l_max=2.0)
    grid, expected = OccupancyGridMap(resolution=0.25, **params), {}
    for X, y, _ in _scattered_batches():
        grid.partial_fit(X, y)
        # The call's evidence summed per cell by the loop reference, keyed by cell centre.
        origin, evidence = _loop_reference(X, y, 0.25, 0.9, -0.3, -np.inf, np.inf)
        for cell, value in evidence.items():
            key = tuple(np.rint((origin + 0.25 * (np.array(cell) + 0.5)) / 0.125).astype(int))
            expected[key] = np.clip(expected.get(key, 0.0) + value, -1.0, 2.0)
    centres = 0.125 * np.array(list(expected))
    assert grid.cell_index_.size == len(expected)
    queries = np.hstack([centres, centres])
    np.testing.assert_allclose(grid.log_odds(queries), list(expected.values()), atol=1e-12)


@pytest.mark.parametrize("grid", [FrequencyGridMap(0.25), OccupancyGridMap(0.25)])
def test_a_refused_partial_fit_leaves_the_grid_as_it_was(grid):
    import pickle

    (X, y, _), (X2, y2, _), *_ = _scattered_batches()
    grid.partial_fit(X, y)
    before = pickle.dumps(grid)
    nan = X2.copy()
    nan[0, 0] = np.nan
    far = X2.copy()
    far[0, 2:] = 1e8  # a beam of 1e8 m: refused after the grid was grown for it
    bad = [
        ((nan, y2), {}, "NaN"),
        ((X2[:, :3], y2), {}, "features"),
        ((X2, np.where(y2 == 1, 7, 0)), {}, r"label\(s\) \[7\]"),
        ((X2, y2), {"classes": [0, 2]}, "differ from classes_"),
        ((far, y2), {}, "cells"),
    ]
    for args, kwargs, match in bad:
        with pytest.raises(ValueError, match=match), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the far beam's "millimetres?" warning
            grid.partial_fit(*args, **kwargs)
        assert pickle.dumps(grid) == before


@pytest.mark.parametrize("estimator", [FrequencyGridMap, OccupancyGridMap])
def test_first_partial_fit_takes_its_classes_from_classes_or_y(estimator):
    beams = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="exactly 2 classes"):
        estimator().partial_fit(beams, [0, 0])
    grid = estimator().partial_fit(beams, ["free", "free"], classes=["wall", "free"])
    assert grid.classes_.tolist() == ["free", "wall"]
    grid.partial_fit([[1.05, 0.0, 1.05, 0.0]], ["wall"])
    assert grid.predict([[1.05, 0.0, 1.05, 0.0]]).tolist() == ["wall"]
    assert grid.predict_proba([[0.55, 0.0, 0.55, 0.0]])[0, 1] < 0.5


@pytest.mark.parametrize("estimator", [FrequencyGridMap, OccupancyGridMap])
def test_partial_fit_checks_parameters_set_between_calls(estimator):
    import pickle

    (X, y, _), (X2, y2, _), *_ = _scattered_batches()
    grid = estimator(resolution=0.25).partial_fit(X, y)
    before = pickle.dumps(grid)
    changes = [({"resolution": -1.0}, "resolution"), ({"resolution": 0.5}, "resolution=0.5")]
    if estimator is OccupancyGridMap:
        changes.append(({"l_min": 3.0, "l_max": 1.0}, "l_min"))
    for params, match in changes:
        # Cells of 0.25 m read as 0.5 m ones would move every observed cell.
        with pytest.raises(ValueError, match=match):
            clone_of = pickle.loads(before)
            clone_of.set_params(**params).partial_fit(X2, y2)
        assert pickle.dumps(clone_of.set_params(**grid.get_params())) == before
    # Parameters that apply to later rows only are taken up.
    grid.set_params(max_free_length=1.0).partial_fit(X2, y2)


def test_partial_fit_origin_does_not_drift_over_many_growths():
    # A robot driving away from the map's origin grows it at every call: the grid's origin
    # stays the multiple of the resolution that fit on all rows takes, not a sum of shifts.
    rng = np.random.default_rng(1)
    grid, rows = FrequencyGridMap(resolution=0.1), []
    for i in range(300):
        sensor = 5e5 - np.array([0.37, 0.23]) * i + rng.uniform(-0.5, 0.5, 2)
        hit = sensor + rng.normal(0, 0.5, 2)
        X = np.array([np.r_[sensor, hit], np.r_[hit, hit]])
        grid.partial_fit(X, [0, 1])
        rows.append(X)
    X = np.vstack(rows)
    low = X.reshape(-1, 2, 2).min(axis=(0, 1))
    expected = np.floor(low / 0.1) * 0.1
    expected = np.where(expected > low, expected - 0.1, expected)
    np.testing.assert_array_equal(grid.origin_, expected)
    full = FrequencyGridMap(resolution=0.1).fit(X, np.tile([0, 1], len(rows)))
    np.testing.assert_array_equal(grid.origin_, full.origin_)
    np.testing.assert_array_equal(grid.hits_, full.hits_)


@pytest.mark.parametrize("estimator", [FrequencyGridMap, OccupancyGridMap])
def test_a_later_empty_partial_fit_adds_nothing(estimator):
    # A scan whose readings all failed gives no rows: the robot's loop goes on, as with
    # MixtureGPOccupancyMap.partial_fit.
    import pickle

    (X, y, _), *_ = _scattered_batches()
    grid = estimator(resolution=0.25).partial_fit(X, y)
    before = pickle.dumps(grid)
    assert grid.partial_fit(np.zeros((0, 4)), np.zeros(0)) is grid
    assert pickle.dumps(grid) == before
    with pytest.raises(ValueError, match="0 sample"):
        estimator().partial_fit(np.zeros((0, 4)), np.zeros(0), classes=[0, 1])


@pytest.mark.parametrize("classes", [[1, 1], [0, 1, 2], ["free"]])
def test_first_partial_fit_refuses_classes_other_than_two_labels(classes):
    beams = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="classes must name the 2 labels"):
        FrequencyGridMap().partial_fit(beams, [1, 1], classes=classes)


@pytest.mark.parametrize("estimator", [FrequencyGridMap, OccupancyGridMap, HilbertMap])
def test_float32_coordinates_coarser_than_a_centimetre_warn(estimator):
    # UTM-like offsets in float32 round the rows to 0.25-0.5 m before any cast: the grids'
    # 0.1 m cells then read a map with gaps and stripes (up to 1.0 off the float64 one),
    # as the mixture warns.
    data = make_office_scans(n_poses=4, n_beams=9)
    X, y = data.X, data.y
    utm = (X + [5e5, 4e6, 5e5, 4e6]).astype(np.float32)
    match = "float32 steps are 0.25 m: the map cannot be finer"
    with pytest.warns(UserWarning, match=match):
        model = estimator(random_state=0) if estimator is HilbertMap else estimator()
        model.fit(utm, y)
    if estimator is not HilbertMap:
        model = estimator()
        for rows in (slice(0, 40), slice(40, None)):  # the first call and a later one
            with pytest.warns(UserWarning, match=match):
                model.partial_fit(utm[rows], y[rows], classes=[0, 1])
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        estimator().fit(X.astype(np.float32), y)
