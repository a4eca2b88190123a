import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from skoccmap.datasets import (
    Environment2D,
    Room3D,
    make_paper_environment,
    make_paper_scans,
    make_room3d_environment,
    make_room3d_scans,
    scanner_directions,
    simulate_scans,
)
from skoccmap.datasets._simulator import _cells_crossed, _grid
from skoccmap.observations import HIT, NO_RETURN, RETURN, Scans, segment_endpoints


def _first_entry_by_marching(occupancy, origin, direction, max_t, step=1e-3):
    """Reference: march along the ray and bisect the first occupied sample (independent)."""
    t = np.arange(0.0, max_t + step, step)
    occ = occupancy(origin + t[:, None] * direction)
    if not occ.any():
        return np.inf
    i = int(np.argmax(occ))
    if i == 0:
        return 0.0
    lo, hi = t[i - 1], t[i]
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if occupancy((origin + mid * direction)[None])[0]:
            hi = mid
        else:
            lo = mid
    return hi


def _counts_by_marching(occupancy, origins, directions, max_range, free_margin=0.05):
    """(hits, return beams, no-return beams) of noise-free beams, by marching along each.

    Independent of the simulator's ray casting: each beam is sampled every 2.5 cm (a quarter
    of the 0.1 m wall thickness) up to past ``max_range``, and the first entry is bisected
    between its first occupied sample and the one before (as :func:`_first_entry_by_marching`
    does, for all beams at once). A beam returns when that entry lies short of ``max_range``;
    a return longer than ``free_margin`` also gives a return beam (``scans_to_observations``'s
    rule). A wall corner clipped by less than a step would be missed, and show as a mismatch.
    """
    step = 0.025
    t = np.arange(0.0, max_range + 4 * step, step)
    dim = origins.shape[1]
    first = np.empty(len(origins), dtype=np.intp)
    for i in range(0, len(origins), 64):
        o, d = origins[i : i + 64, None, :], directions[i : i + 64, None, :]
        occ = occupancy((o + t[None, :, None] * d).reshape(-1, dim)).reshape(-1, t.size)
        first[i : i + 64] = np.where(occ.any(axis=1), np.argmax(occ, axis=1), -1)
    ranges = np.full(len(origins), np.inf)
    hit = first > 0  # (no beam starts inside an obstacle: checked below)
    assert not np.any(first == 0)
    lo, hi = t[first[hit] - 1], t[first[hit]]
    o, d = origins[hit], directions[hit]
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        inside = occupancy(o + mid[:, None] * d).astype(bool)
        lo, hi = np.where(inside, lo, mid), np.where(inside, mid, hi)
    ranges[hit] = hi
    # Every entry is resolved far finer than its distance to the thresholds (some are within
    # 2 mm of the maximum range), so the classification is that of the exact ranges.
    assert np.all(np.abs(ranges - max_range) > 1e-6)
    assert np.all(np.abs(ranges - free_margin) > 1e-6)
    returned = ranges < max_range
    return (
        int(returned.sum()),
        int((returned & (ranges > free_margin)).sum()),
        int((~returned).sum()),
    )


def _paper_beams(scans):
    """World origins and unit directions of every beam of 2-D scans (pose x, y, heading)."""
    theta = (scans.poses[:, 2:3] + scans.angles[None, :]).ravel()
    origins = np.repeat(scans.poses[:, :2], scans.n_beams, axis=0)
    return origins, np.column_stack([np.cos(theta), np.sin(theta)])


# --------------------------------------------------------------------------------------------
# Environment2D
# --------------------------------------------------------------------------------------------


def test_cast_hand_computed():
    env = Environment2D([[2.0, -1.0, 2.0, 1.0], [3.0, 0.0, 5.0, 0.0]], wall_thickness=0.2)
    origins = [[0, 0], [0, 0], [0, 0.5], [2.5, 0.0], [0, 0], [2.0, 0.05], [0, 0], [0, 0]]
    dirs = [[1, 0], [-1, 0], [1, 0], [1, 0], [0, 1], [1, 0], [1, 0.25], [1, 1]]
    ranges = env.cast(origins, dirs, max_range=10.0)
    expected = [
        1.9,  # thick wall face
        np.inf,  # nothing behind
        1.9,  # face, off-centre
        0.4,  # round cap of the second wall at x = 3 - 0.1
        np.inf,  # parallel to both
        0.0,  # origin inside a wall
        1.9 * np.hypot(1, 0.25),  # oblique onto the face x = 1.9
        np.inf,  # passes above the end cap at (2, 1): distance sqrt(1/2) > 0.1
    ]
    assert_allclose(ranges, expected, atol=1e-12)
    # beyond max_range -> inf
    assert_array_equal(env.cast([[0, 0]], [[1, 0]], max_range=1.5), [np.inf])
    # direction need not be normalised
    assert_allclose(env.cast([[0, 0]], [[5, 0]]), [1.9])


def test_cast_cap_tangent_and_offset_ray():
    env = Environment2D([[0.0, 0.0, 0.0, 0.0]], wall_thickness=2.0)  # a disc of radius 1
    ranges = env.cast([[-3.0, 0.0], [-3.0, 0.5], [-3.0, 1.5]], [[1, 0]] * 3)
    assert_allclose(ranges, [2.0, 3.0 - np.sqrt(1 - 0.25), np.inf])


def test_cast_closed_surfaces_and_max_range():
    # The occupied set is closed: a ray tangent to a round cap meets it at the point of
    # contact, and an origin on the surface is inside (range 0) whichever way it looks.
    disc = Environment2D([[0.0, 0.0, 0.0, 0.0]], wall_thickness=2.0)  # a disc of radius 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a wall of zero length has no direction: no 0 / 0
        ranges = disc.cast([[-3.0, 1.0], [-1.0, 0.0], [0.0, 1.0]], [[1, 0], [-1, 0], [0, 1]])
    assert_array_equal(ranges, [3.0, 0.0, 0.0])
    assert_array_equal(disc.occupancy([[-1.0, 0.0], [0.0, 1.0]]), [1, 1])
    # A wall exactly at max_range gives no return: nothing meets the ray closer than it.
    wall = Environment2D([[3.0, -1.0, 3.0, 1.0]], wall_thickness=0.0)
    assert_array_equal(wall.cast([[0, 0]], [[1, 0]], max_range=3.0), [np.inf])
    assert_array_equal(wall.cast([[0, 0]], [[1, 0]], max_range=3.5), [3.0])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), thickness=st.sampled_from([0.0, 0.1, 0.6]))
def test_cast_matches_marching(seed, thickness):
    rng = np.random.default_rng(seed)
    walls = rng.uniform(-4, 4, (5, 4))
    env = Environment2D(walls, wall_thickness=thickness)
    origins = rng.uniform(-4, 4, (8, 2))
    angle = rng.uniform(-np.pi, np.pi, 8)
    dirs = np.column_stack([np.cos(angle), np.sin(angle)])
    ranges = env.cast(origins, dirs, max_range=6.0)
    for o, d, r in zip(origins, dirs, ranges, strict=True):
        if thickness == 0.0:
            # zero-thickness walls are measure-zero: check the hit point lies on a wall and
            # the ray crosses no wall before it (distance along the segment changes sign)
            if np.isfinite(r):
                assert env.distance((o + r * d)[None])[0] < 1e-9
            continue
        ref = _first_entry_by_marching(env.occupancy, o, d, 6.0)
        if np.isinf(r):
            assert np.isinf(ref) or ref >= 6.0 - 1e-6  # marching may run a step past 6 m
        elif np.isinf(ref):
            # marching stepped over a sliver only a near-tangent ray can cut
            t = np.linspace(r, r + 2e-3, 50)
            assert env.distance(o + t[:, None] * d).min() > thickness / 2 - 1e-5
        else:
            assert abs(r - ref) < 2e-6


def test_occupancy_and_distance():
    env = Environment2D([[0.0, 0.0, 2.0, 0.0]], wall_thickness=0.4)
    pts = [[1.0, 0.2], [1.0, 0.2001], [2.15, 0.0], [2.3, 0.0], [-0.1, -0.1]]
    assert_array_equal(env.occupancy(pts), [1, 0, 1, 0, 1])
    assert_allclose(env.distance(pts), [0.2, 0.2001, 0.15, 0.3, np.sqrt(0.02)])


def test_extent():
    env = Environment2D([[0, 0, 4, 0], [1, -2, 1, 3]], wall_thickness=0.2)
    assert_allclose(env.extent, [-0.1, 4.1, -2.1, 3.1])
    # Zero-thickness walls in a line: the default grid holds one row of cells across them.
    flat = Environment2D([[0, 0, 1, 0]], wall_thickness=0.0).ground_truth_grid(0.1)
    assert flat.shape == (1, 10)
    assert_allclose(flat.extent, [0, 1, -0.05, 0.05])
    assert_array_equal(flat.occupied, 1)


def test_ground_truth_grid_matches_supersampling():
    rng = np.random.default_rng(0)
    env = Environment2D(rng.uniform(0, 3, (4, 4)), wall_thickness=0.1)
    res = 0.25
    grid = env.ground_truth_grid(res, extent=(0, 3, 0, 3))
    assert grid.shape == (12, 12)
    assert len(grid.points) == 144
    assert_allclose(grid.points[:2], [[0.125, 0.125], [0.375, 0.125]])  # x fastest
    # supersample each cell: the minimum distance to a wall over the cell
    offsets = (np.arange(41) / 40 - 0.5) * res
    sub = np.stack(np.meshgrid(offsets, offsets), -1).reshape(-1, 2)
    min_dist = np.array([env.distance(c + sub).min() for c in grid.points])
    h, slack = 0.05, res / 40
    sure_in, sure_out = min_dist <= h, min_dist > h + slack
    assert np.all(grid.occupied[sure_in] == 1)
    assert np.all(grid.occupied[sure_out] == 0)
    assert sure_in.sum() > 10


def test_grid_cell_counts_and_touching_cells():
    # A width of a whole number of cells gets that many cells, also where the division
    # rounds up (2.1 / 0.3 = 7.000000000000001): the last cell overhangs only when it must.
    env = Environment2D([[0.0, 0.0, 1.0, 0.0]], wall_thickness=0.1)
    grid = env.ground_truth_grid(0.3, extent=(0.0, 2.1, 0.0, 2.7))
    assert grid.shape == (9, 7)
    assert_allclose(grid.extent, [0.0, 2.1, 0.0, 2.7])
    assert env.ground_truth_grid(0.3, extent=(0.0, 2.2, 0.0, 2.7)).shape == (9, 8)
    # Closed sets: the column of cells whose left side lies on the wall's surface (x = 0.1)
    # overlaps the wall; the columns beyond it do not.
    wall = Environment2D([[0.0, 0.0, 0.0, 1.0]], wall_thickness=0.2)
    grid = wall.ground_truth_grid(0.1, extent=(0.1, 0.5, 0.0, 1.0))
    occupied = grid.occupied.reshape(grid.shape)
    assert grid.shape == (10, 4)
    assert_array_equal(occupied[:, 0], 1)
    assert_array_equal(occupied[:, 1:], 0)


def test_cells_crossed_counts_a_start_on_a_cell_boundary():
    # A point on a cell boundary belongs to the cell above it (floor), a start point as an
    # end point: on a 0.5 m grid the segment between x = 1.0 and x = 0.2 sees cells 0 to 2,
    # whichever way it runs.
    lo, counts, _ = _grid((0, 4, 0, 1), 0.5, 2)
    a, b = np.array([[1.0, 0.25]]), np.array([[0.2, 0.25]])
    assert_array_equal(np.flatnonzero(_cells_crossed(a, b, lo, 0.5, counts)), [0, 1, 2])
    assert_array_equal(np.flatnonzero(_cells_crossed(b, a, lo, 0.5, counts)), [0, 1, 2])


def test_cells_crossed_matches_box_test():
    rng = np.random.default_rng(1)
    lo, counts, centres = _grid((0, 4, 0, 3), 0.5, 2)
    starts, ends = rng.uniform(-1, 5, (6, 2)), rng.uniform(-1, 5, (6, 2))
    starts[0] = ends[0] = [1.3, 1.7]  # a point
    seen = _cells_crossed(starts, ends, lo, 0.5, counts)
    # reference: dense sampling along each segment (random segments never touch a corner)
    t = np.linspace(0, 1, 20001)
    pts = (starts[:, None] + t[None, :, None] * (ends - starts)[:, None]).reshape(-1, 2)
    idx = np.floor((pts - lo) / 0.5).astype(int)
    ok = np.all((idx >= 0) & (idx < counts), axis=1)
    ref = np.zeros(len(centres), bool)
    ref[idx[ok, 0] + counts[0] * idx[ok, 1]] = True
    assert_array_equal(seen, ref)


def test_cells_crossed_stops_at_the_first_flagged_cell():
    rng = np.random.default_rng(2)
    lo, counts, centres = _grid((0, 4, 0, 3), 0.5, 2)
    starts, ends = rng.uniform(0, 4, (40, 2)), rng.uniform(-1, 5, (40, 2))
    stop = rng.random(len(centres)) < 0.15
    stops = rng.random(40) < 0.5
    seen = _cells_crossed(starts, ends, lo, 0.5, counts, stop=stop, stops=stops)
    # reference: dense samples along each segment, a stopping one cut after its first
    # flagged cell past its start cell (random segments never touch a corner)
    t = np.linspace(0, 1, 20001)
    ref = np.zeros(len(centres), bool)
    for a, b, stopping in zip(starts, ends, stops, strict=True):
        idx = np.floor((a + t[:, None] * (b - a) - lo) / 0.5).astype(int)
        ok = np.all((idx >= 0) & (idx < counts), axis=1)
        flat = idx[ok, 0] + counts[0] * idx[ok, 1]
        later = stop[flat] & (flat != flat[0]) if flat.size and ok[0] else stop[flat]
        if stopping and later.any():
            flat = flat[: np.argmax(later) + 1]
        ref[flat] = True
    assert_array_equal(seen, ref)
    # The stopping segments alone see fewer cells than they cross.
    a, b, every = starts[stops], ends[stops], np.ones(stops.sum(), bool)
    cut = _cells_crossed(a, b, lo, 0.5, counts, stop=stop, stops=every)
    assert cut.sum() < _cells_crossed(a, b, lo, 0.5, counts).sum()


def test_ground_truth_grid_observed_mask():
    env = Environment2D([[3.0, -1.0, 3.0, 1.0]], wall_thickness=0.0)
    scans = simulate_scans(env, [[0.5, 0.25, 0.0]], [0.0], max_range=8.0)
    grid = env.ground_truth_grid(0.5, extent=(0, 4, 0, 1), scans=scans)
    observed = grid.observed.reshape(grid.shape)
    # the beam runs along y = 0.25 from x = 0.5 to the wall at x = 3
    expected = np.zeros((2, 8), bool)
    expected[0, 1:7] = True
    assert_array_equal(observed, expected)


def test_ground_truth_grid_observed_mask_no_return_and_unread():
    # A beam without a return observes the cells up to max_range (here it leaves the grid
    # westwards); a reading of 0, no measurement, observes nothing (the beam north).
    env = Environment2D([[3.0, -1.0, 3.0, 1.0]], wall_thickness=0.0)
    scans = Scans([[0.5, 0.25, 0.0]], [[np.inf, 0.0]], [np.pi, np.pi / 2], max_range=2.0)
    grid = env.ground_truth_grid(0.5, extent=(0, 4, 0, 1), scans=scans)
    expected = np.zeros((2, 8), bool)
    expected[0, :2] = True
    assert_array_equal(grid.observed.reshape(grid.shape), expected)


# --------------------------------------------------------------------------------------------
# simulate_scans
# --------------------------------------------------------------------------------------------


def _free_along(env, X, kind, n=50):
    start, end = segment_endpoints(X[kind != HIT])
    t = np.linspace(0, 1, n)
    pts = (start[:, None] + t[None, :, None] * (end - start)[:, None]).reshape(-1, X.shape[1] // 2)
    return env.occupancy(pts)


def test_simulated_observations_agree_with_truth():
    data = make_paper_scans()
    env, X, kind = data.environment, data.X, data.kind
    hits = X[kind == HIT, :2]
    assert np.all(env.occupancy(hits) == 1)
    assert_allclose(env.distance(hits), env.wall_thickness / 2, atol=1e-9)
    assert not np.any(_free_along(env, X, kind))


def test_simulate_scans_determinism_and_noise():
    env = make_paper_environment()
    poses = [[10.0, 6.0, 0.3], [14.0, 8.0, 2.0]]
    angles = np.linspace(-np.pi / 2, np.pi / 2, 9)
    exact = simulate_scans(env, poses, angles, 8.0)
    a = simulate_scans(env, poses, angles, 8.0, noise_std=0.05, random_state=3)
    b = simulate_scans(env, poses, angles, 8.0, noise_std=0.05, random_state=3)
    c = simulate_scans(env, poses, angles, 8.0, noise_std=0.05, random_state=4)
    assert_array_equal(a.ranges, b.ranges)
    assert not np.array_equal(a.ranges, c.ranges)
    both = np.isfinite(exact.ranges) & np.isfinite(a.ranges)
    diff = a.ranges[both] - exact.ranges[both]
    assert 0 < np.abs(diff).max() < 0.5
    assert isinstance(exact, Scans) and exact.max_range == 8.0
    assert np.all(np.isinf(exact.ranges) | (exact.ranges < 8.0))


def test_simulate_scans_noise_statistics():
    env = Environment2D([[5.0, -50.0, 5.0, 50.0]], wall_thickness=0.0)
    scans = simulate_scans(
        env, np.zeros((1, 3)), np.zeros(4000), 8.0, noise_std=0.1, random_state=0
    )
    r = scans.ranges.ravel()
    assert abs(r.mean() - 5.0) < 0.01
    assert abs(r.std() - 0.1) < 0.01


def test_simulate_scans_noise_is_clipped_at_zero_and_at_max_range():
    # Noise that takes a reading below 0 is clipped to 0; noise that takes it to max_range
    # or beyond makes it a no-return (inf). For walls 0.05 m from the sensor, and 0.05 m
    # short of max_range, each happens with probability P(N(0, 0.1) > 0.05), about 31 %.
    tail = 0.5 * math.erfc(0.5 / math.sqrt(2.0))
    near = Environment2D([[0.05, -50.0, 0.05, 50.0]], wall_thickness=0.0)
    r = simulate_scans(near, np.zeros((1, 3)), np.zeros(4000), 8.0, noise_std=0.1, random_state=0)
    r = r.ranges.ravel()
    assert np.all(np.isfinite(r)) and r.min() == 0.0
    assert abs(np.mean(r == 0.0) - tail) < 0.03
    far = Environment2D([[7.95, -50.0, 7.95, 50.0]], wall_thickness=0.0)
    r = simulate_scans(far, np.zeros((1, 3)), np.zeros(4000), 8.0, noise_std=0.1, random_state=1)
    r = r.ranges.ravel()
    assert np.all(np.isinf(r) | (r < 8.0))
    assert abs(np.mean(np.isinf(r)) - tail) < 0.03


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"noise_std": -1.0}, "noise_std"),
        ({"noise_std": np.nan}, "noise_std"),
        ({"max_range": 0.0}, "max_range"),
        ({"poses": [[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]], "angles": [[1.0, 0.0, 0.0]]}, "3-D"),
        ({"poses": [[np.nan, 0.0, 0.0]]}, "poses"),
    ],
)
def test_simulate_scans_bad_input(kwargs, match):
    args = {"poses": [[1.0, 1.0, 0.0]], "angles": [0.0], "max_range": 5.0}
    args.update(kwargs)
    env = make_paper_environment()
    with pytest.raises(ValueError, match=match):
        simulate_scans(env, args.pop("poses"), args.pop("angles"), args.pop("max_range"), **args)


def test_simulate_scans_refuses_what_is_no_environment():
    # It was "'NoneType' object has no attribute 'n_dims'".
    for environment in (None, np.zeros((3, 4))):
        with pytest.raises(TypeError, match="environment must be an Environment2D, a Room3D"):
            simulate_scans(environment, [[1.0, 1.0, 0.0]], [0.0], 5.0)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: Environment2D([[0, 0, 1]]), "walls must have shape"),
        (lambda: Environment2D(np.zeros((0, 4))), "walls must have shape"),
        (lambda: Environment2D([[0, 0, np.nan, 1]]), "walls contains NaN"),
        (lambda: Environment2D([[0, 0, 1, 1]], wall_thickness=-0.1), "wall_thickness"),
        (lambda: Environment2D([[0, 0, 1, 1]], wall_thickness=np.inf), "wall_thickness"),
        (lambda: make_paper_environment().cast([[0, 0]], [[0, 0]]), "zero vectors"),
        (
            lambda: make_paper_environment().cast([[1, 1], [2, 2]], [[1, 0]]),
            "directions must have the shape of origins",
        ),
        (lambda: make_paper_environment().cast([[1, 1]], [[1, 0]], max_range=0.0), "max_range"),
        (lambda: make_paper_environment().cast([[1, 1]], [[1, 0]], max_range=-1), "max_range"),
        (lambda: make_paper_environment().cast([[0, 0, 0]], [[1, 0, 0]]), "origins must"),
        (lambda: make_paper_environment().occupancy([[0, np.nan]]), "points contains NaN"),
        (lambda: make_paper_environment().ground_truth_grid(0.0), "resolution must be a positive"),
        (
            lambda: make_paper_environment().ground_truth_grid(np.inf),
            "resolution must be a positive",
        ),
        (
            lambda: make_paper_environment().ground_truth_grid(0.2, (0, np.inf, 0, 1)),
            "extent must be 4 finite numbers",
        ),
        (lambda: make_paper_environment().ground_truth_grid(0.2, (0, 1, 2, 2)), "max > min"),
        (lambda: make_paper_environment().ground_truth_grid(0.2, (0, 1, 2)), "extent"),
        (lambda: make_paper_environment().ground_truth_grid(0.2, (1, 0, 0, 1)), "max > min"),
        (lambda: make_paper_environment().ground_truth_grid(1e-5), "too large"),
        (
            lambda: make_paper_environment().ground_truth_grid(
                1.0, scans=make_room3d_scans().scans
            ),
            "2-D",
        ),
        (lambda: Room3D(size=(1, 1)), "size"),
        (lambda: Room3D(size=(1, 0, 1)), "size"),
        (lambda: Room3D(size=(1, np.inf, 1)), "size"),
        (lambda: Room3D(obstacles=[[0, 0, 0, 1, 1]]), "obstacles must have shape"),
        (lambda: Room3D(obstacles=[[1, 1, 1, 0, 0, 0]]), "max >= min"),
        (lambda: Room3D(obstacles=[[1, 1, 1, 2, np.nan, 2]]), "finite boxes"),
        (lambda: Room3D(wall_thickness=0.0), "wall_thickness"),
        (lambda: make_room3d_scans(n_azimuths=0), "n_azimuths"),
        (lambda: make_room3d_scans(n_elevations=2.5), "n_elevations"),
        (lambda: make_room3d_scans(n_azimuths=True), "n_azimuths"),
        (lambda: make_room3d_scans(n_elevations=True), "n_elevations"),
        (lambda: make_paper_scans(n_beams=True), "n_beams"),
        (lambda: make_paper_scans(n_poses_per_piece=1), "n_poses_per_piece"),
    ],
)
def test_environment_bad_input(make, match):
    with pytest.raises(ValueError, match=match):
        make()


# --------------------------------------------------------------------------------------------
# The paper's data set
# --------------------------------------------------------------------------------------------


def test_paper_scans_setup_and_counts():
    data = make_paper_scans(random_state=0)
    scans = data.scans
    assert (len(scans), scans.n_beams, scans.max_range) == (26, 17, 8.0)
    assert_allclose(np.diff(scans.angles), np.pi / 16)
    assert_allclose(scans.angles[[0, -1]], [-np.pi / 2, np.pi / 2])
    counts = np.bincount(data.kind, minlength=3)
    assert counts.sum() == len(data.X) == len(data.y)
    expected = _counts_by_marching(data.environment.occupancy, *_paper_beams(scans), 8.0)
    assert tuple(counts[[HIT, RETURN, NO_RETURN]]) == expected
    # The layout was drawn to come close to the paper's counts (254, 254, 188); it is within 5
    # of each (259, 259, 183), a property of the layout rather than of the simulator.
    for got, paper in zip(counts[[HIT, RETURN, NO_RETURN]], (254, 254, 188), strict=True):
        assert abs(int(got) - paper) <= 5
    assert counts[HIT] + counts[NO_RETURN] == 26 * 17
    assert_array_equal(data.y, data.kind == HIT)
    assert_array_equal(np.bincount(data.piece), [13, 13])
    ext = data.environment.extent
    assert_allclose([ext[1] - ext[0], ext[3] - ext[2]], [22.1, 18.1])
    assert np.all(data.environment.occupancy(scans.origins()) == 0)


def test_paper_scans_noise_is_seeded():
    a = make_paper_scans(noise_std=0.03, random_state=1)
    b = make_paper_scans(noise_std=0.03, random_state=1)
    c = make_paper_scans(noise_std=0.03, random_state=2)
    assert_array_equal(a.X, b.X)
    assert not np.array_equal(a.X, c.X)


def test_paper_pieces_and_west_rooms():
    data = make_paper_scans()
    poses, piece = data.scans.poses, data.piece
    # Each piece is a run of consecutive scans along one smooth path: its poses lie about
    # 1 m apart, each heading towards the next (the sensor looks where the robot drives).
    assert np.all(np.diff(piece) >= 0)
    for k in (0, 1):
        run = poses[piece == k]
        step = np.diff(run[:, :2], axis=0)
        assert np.linalg.norm(step, axis=1).max() < 1.5
        turn = np.arctan2(step[:, 1], step[:, 0]) - run[:-1, 2]
        assert np.abs(np.angle(np.exp(1j * turn))).max() < 0.2
    # The three west rooms (x in [0, 5], 6 m each) are walled off from one another across
    # their full width: their doors face east.
    x = np.linspace(0.0, 5.0, 5001)
    for y in (6.0, 12.0):
        assert np.all(data.environment.occupancy(np.column_stack([x, np.full_like(x, y)])))
    # Two beams point to the two edges of the 180 degrees.
    assert_allclose(make_paper_scans(n_beams=2).scans.angles, [-np.pi / 2, np.pi / 2])


def _returns_stop_short_of_a_hit(data, free_margin):
    """Largest gap between a return beam's end moved on by ``free_margin`` and a hit."""
    start, end = segment_endpoints(data.X)
    ret = data.kind == RETURN
    d = (end[ret] - start[ret]) / np.linalg.norm(end[ret] - start[ret], axis=1, keepdims=True)
    target = end[ret] + free_margin * d
    hits = start[data.kind == HIT]
    return np.linalg.norm(target[:, None] - hits[None], axis=-1).min(axis=1).max()


def test_paper_free_margin_passed_on():
    data = make_paper_scans(free_margin=0.3)
    ret = data.kind == RETURN
    start, end = segment_endpoints(data.X)
    # each return beam is followed by... not by order: compare with the hit of the same beam
    hits = start[data.kind == HIT]
    d = (end[ret] - start[ret]) / np.linalg.norm(end[ret] - start[ret], axis=1, keepdims=True)
    target = end[ret] + 0.3 * d
    dist = np.linalg.norm(target[:, None] - hits[None], axis=-1).min(axis=1)
    assert dist.max() < 1e-9


# --------------------------------------------------------------------------------------------
# 3-D room
# --------------------------------------------------------------------------------------------


def test_room_cast_hand_computed():
    room = Room3D(size=(4, 4, 2), obstacles=[[2, 2, 0, 3, 3, 1]])
    origins = [[1, 2.5, 0.5], [1, 2.5, 0.5], [1, 2.5, 1.5], [2.5, 2.5, 0.5], [1, 1, 1]]
    dirs = [[1, 0, 0], [-1, 0, 0], [1, 0, 0], [0, 0, 1], [1, 1, 0]]
    assert_allclose(room.cast(origins, dirs), [1.0, 1.0, 3.0, 0.0, np.sqrt(2) * 1.0])
    assert_array_equal(room.cast([[1, 2.5, 0.5]], [[1, 0, 0]], max_range=0.5), [np.inf])
    for bad in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="max_range must be a positive finite number"):
            room.cast([[1, 2.5, 0.5]], [[1, 0, 0]], max_range=bad)


def test_room_cast_grazing_rays_and_max_range():
    # Obstacles are closed boxes: a ray in the plane of a face (y = 2) meets the face's
    # edge at x = 2, and a ray through a vertical edge only (x = 2, y = 3) meets it there.
    room = Room3D(size=(4, 4, 2), obstacles=[[2, 2, 0, 3, 3, 1]])
    origins = [[1, 2, 0.5], [1, 3, 0.5], [1, 2.5, 1.0], [1, 2, 0.5]]
    dirs = [[1, 0, 0], [1, 0, 0], [1, 0, 0], [1, 1, 0]]
    assert_allclose(room.cast(origins, dirs), [1.0, 1.0, 1.0, np.sqrt(2)])
    assert_array_equal(room.occupancy([[2, 2, 0.5], [2, 3, 0.5]]), [1, 1])
    # An obstacle exactly at max_range gives no return.
    assert_array_equal(room.cast([[1, 2.5, 0.5]], [[1, 0, 0]], max_range=1.0), [np.inf])
    assert_array_equal(room.cast([[1, 2.5, 0.5]], [[1, 0, 0]], max_range=1.5), [1.0])
    # A flat box (max = min on an axis: a plate) is a valid obstacle.
    plate = Room3D(size=(4, 4, 2), obstacles=[[2, 1, 0, 2, 3, 2]])
    assert_array_equal(plate.cast([[1, 2, 1]], [[1, 0, 0]]), [1.0])


def test_room_cast_matches_marching():
    room = make_room3d_environment()
    rng = np.random.default_rng(2)
    origins = np.column_stack([rng.uniform(0.2, 5.8, 30), rng.uniform(0.2, 4.8, 30),
                               rng.uniform(0.2, 2.8, 30)])  # fmt: skip
    dirs = rng.normal(size=(30, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ranges = room.cast(origins, dirs)
    for o, d, r in zip(origins, dirs, ranges, strict=True):
        ref = _first_entry_by_marching(room.occupancy, o, d, 9.0)
        assert abs(r - ref) < 2e-6


def test_room_cast_from_outside_the_open_room_is_zero():
    # The walls, floor and ceiling (surfaces included) are occupied: a ray starting there,
    # even one pointing into the room, reads 0.
    room = Room3D(size=(4, 4, 2))
    origins = [[-0.1, 1.0, 1.0], [1.0, 1.0, 2.0], [4.0, 2.0, 1.0]]
    dirs = [[1, 0, 0], [0, 0, -1], [-1, 0, 0]]
    assert_array_equal(room.cast(origins, dirs), [0.0, 0.0, 0.0])


def test_room_extent_holds_the_walls_on_both_sides():
    room = Room3D(size=(4, 3, 2), wall_thickness=0.5)
    assert_allclose(room.extent, [-0.5, 4.5, -0.5, 3.5, -0.5, 2.5])


def test_room_grid_voxels_touching_a_face_are_occupied():
    # A grid aligned with the room: of the 3 x 3 x 3 voxels inside a 3 m room, only the
    # centre one touches none of the six faces; the voxels outside are occupied too.
    room = Room3D(size=(3, 3, 3), wall_thickness=1.0)
    grid = room.ground_truth_grid(1.0, extent=(-1, 4, -1, 4, -1, 4))
    assert grid.shape == (5, 5, 5)
    assert_array_equal(grid.points[grid.occupied == 0], [[1.5, 1.5, 1.5]])


def test_room_distance_hand_computed():
    # Distance to the nearest occupied point: across the nearest room face, or to the
    # obstacle box [2, 3] x [2, 3] x [0, 1] (its face, edge or corner); 0 inside it.
    room = Room3D(size=(4, 4, 2), obstacles=[[2, 2, 0, 3, 3, 1]])
    points = [
        [0.5, 1.0, 1.0],  # room face x = 0
        [1.7, 2.5, 0.5],  # obstacle face x = 2, 0.3 away (the floor is 0.5 away)
        [3.3, 3.4, 0.6],  # obstacle edge x = 3, y = 3: hypot(0.3, 0.4)
        [3.2, 1.8, 1.1],  # obstacle corner (3, 2, 1)
        [2.5, 2.5, 0.5],  # inside the obstacle
    ]
    expected = [0.5, 0.3, 0.5, np.sqrt(0.04 + 0.04 + 0.01), 0.0]
    assert_allclose(room.distance(points), expected, atol=1e-12)


def test_room_grid_matches_supersampling():
    room = make_room3d_environment()
    grid = room.ground_truth_grid(0.5)
    assert grid.shape == (7, 11, 13)  # z, y, x over [-0.2, 3.2] x [-0.2, 5.2] x [-0.2, 6.2]
    offsets = np.linspace(-0.5, 0.5, 11) * 0.5  # closed voxels: faces touching count
    sub = np.stack(np.meshgrid(offsets, offsets, offsets), -1).reshape(-1, 3)
    ref = np.array([room.occupancy(c + sub).any() for c in grid.points])
    assert_array_equal(grid.occupied, ref)


def test_room3d_scans():
    data = make_room3d_scans(random_state=0)
    room, X, kind = data.environment, data.X, data.kind
    assert data.scans.n_dims == 3 and X.shape[1] == 6
    counts = np.bincount(kind, minlength=3)
    assert counts.min() > 0
    # Beams in the world frame: the scanner directions turned by each pose's yaw (the poses'
    # quaternions rotate about z only).
    poses, sensor = data.scans.poses, data.scans.angles
    assert_allclose(poses[:, 4:6], 0.0)
    yaw = 2.0 * np.arctan2(poses[:, 6], poses[:, 3])
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    world = np.stack(
        [c * sensor[:, 0] - s * sensor[:, 1], s * sensor[:, 0] + c * sensor[:, 1],
         np.broadcast_to(sensor[:, 2], c.shape[:1] + sensor[:, 2].shape)], axis=-1
    ).reshape(-1, 3)  # fmt: skip
    origins = np.repeat(poses[:, :3], data.scans.n_beams, axis=0)
    expected = _counts_by_marching(room.occupancy, origins, world, data.scans.max_range)
    assert tuple(counts[[HIT, RETURN, NO_RETURN]]) == expected
    assert len(X) == counts.sum()
    assert np.all(room.occupancy(X[kind == HIT, :3]) == 1)
    assert not np.any(_free_along(room, X, kind))
    lengths = np.linalg.norm(X[:, 3:] - X[:, :3], axis=1)
    assert_allclose(lengths[kind == NO_RETURN], 4.0)
    assert_array_equal(lengths[kind == HIT], 0.0)
    noisy_a = make_room3d_scans(noise_std=0.02, random_state=5)
    noisy_b = make_room3d_scans(noise_std=0.02, random_state=5)
    assert_array_equal(noisy_a.X, noisy_b.X)
    assert not np.array_equal(noisy_a.X[noisy_a.kind == HIT], X[kind == HIT])


def test_room3d_scans_setup():
    # Four poses at 1.2 m height, each turned to a different heading; the elevations span
    # [-30, 30] degrees; max_range and free_margin are passed on.
    data = make_room3d_scans(n_elevations=2, max_range=2.5, free_margin=0.3)
    poses = data.scans.poses
    assert_allclose(poses[:, 2], 1.2)
    yaw = np.mod(2.0 * np.arctan2(poses[:, 6], poses[:, 3]), 2 * np.pi)
    assert len(np.unique(yaw.round(6))) == 4
    elevation = np.rad2deg(np.arcsin(data.scans.angles[:, 2]))
    assert_allclose(np.unique(elevation.round(9)), [-30.0, 30.0])
    assert data.scans.max_range == 2.5
    start, end = segment_endpoints(data.X)
    assert_allclose(np.linalg.norm(end - start, axis=1)[data.kind == NO_RETURN], 2.5)
    assert _returns_stop_short_of_a_hit(data, 0.3) < 1e-9


def test_scanner_directions():
    d = scanner_directions([0.0, np.pi / 2], [0.0, np.pi / 6])
    assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    assert_allclose(d[1], [0, 1, 0], atol=1e-12)
    assert_allclose(d[2], [np.cos(np.pi / 6), 0, 0.5], atol=1e-12)


def test_a_single_beam_points_straight_ahead():
    # A one-beam scanner looks along its heading (2-D) or horizontally (3-D), not to the
    # edge of its field of view.
    assert_array_equal(make_paper_scans(n_beams=1).scans.angles, [0.0])
    room = make_room3d_scans(n_azimuths=3, n_elevations=1).scans
    assert_allclose(room.angles[:, 2], 0.0, atol=1e-12)
    level = scanner_directions([0, 2 * np.pi / 3, 4 * np.pi / 3], [0.0])
    assert_allclose(room.angles, level, atol=1e-12)


def test_paper_scans_scale_up():
    data = make_paper_scans(n_beams=34, n_poses_per_piece=26)
    assert (len(data.scans), data.scans.n_beams) == (52, 34)
    assert_allclose(data.scans.angles[[0, -1]], [-np.pi / 2, np.pi / 2])
    assert_allclose(np.diff(data.scans.angles), np.pi / 33)
    counts = np.bincount(data.kind, minlength=3)
    expected = _counts_by_marching(data.environment.occupancy, *_paper_beams(data.scans), 8.0)
    assert tuple(counts[[HIT, RETURN, NO_RETURN]]) == expected
    assert counts[HIT] + counts[NO_RETURN] == 52 * 34
    with pytest.raises(ValueError, match="n_beams"):
        make_paper_scans(n_beams=0)
    with pytest.raises(ValueError, match="n_poses_per_piece"):
        make_paper_scans(n_poses_per_piece=1.5)


@pytest.mark.parametrize(
    ("azimuths", "elevations"), [([np.nan], [0.0]), ([], [0.0]), (0.0, [0.0])]
)
def test_scanner_directions_checks_its_angles(azimuths, elevations):
    with pytest.raises(ValueError, match="non-empty 1-D array of finite angles"):
        scanner_directions(azimuths, elevations)
