import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from skoccmap.datasets import Environment2D, make_office_environment, make_office_scans
from skoccmap.datasets._office import _office_path, _office_poses, _room_of
from skoccmap.observations import HIT, NO_RETURN, segment_endpoints

# Least distance between the sensor and any wall surface: 0.4 m, at the jambs of the 0.9 m
# door (half its width less half the wall thickness), less rounding.
CLEARANCE = 0.45 - 0.05 - 1e-9


def _clearance(env, points):
    return env.distance(points) - env.wall_thickness / 2


def test_office_environment_extent_and_doors():
    env = make_office_environment()
    assert_allclose(env.extent, [-0.05, 20.05, -0.05, 15.05])
    assert env.wall_thickness == 0.1
    # Door openings: the free runs along the two corridor walls, surface to surface.
    x = np.arange(0.0, 20.0, 0.001)
    widths = []
    for y in (6.5, 8.5):
        free = env.occupancy(np.column_stack([x, np.full_like(x, y)])) == 0
        edges = np.flatnonzero(np.diff(free.astype(int)))
        assert len(edges) % 2 == 0
        widths += ((edges[1::2] - edges[0::2]) * 0.001 + env.wall_thickness).tolist()
    assert len(widths) == 7
    assert all(0.9 - 2e-3 <= w <= 1.2 + 2e-3 for w in widths)
    # The corridor runs from end to end; the table and the pillar stand in their rooms.
    assert np.isinf(env.cast([[0.2, 7.5]], [[1.0, 0.0]], max_range=19.5))[0]
    assert_array_equal(env.occupancy([[12.3, 11.35], [15.8, 3.5], [10.0, 7.5]]), [1, 1, 0])


def test_office_furniture():
    env = make_office_environment()
    rooms = make_office_scans(2, 2).rooms
    path = _office_path()
    labels = _room_of(path)
    north = np.flatnonzero(rooms[:, 2] == 8.5)
    south = np.flatnonzero(rooms[:, 3] == 6.5)
    meeting = north[np.argsort(rooms[north, 0])[2]]  # the third north room
    hall = south[np.argmax(rooms[south, 0])]  # the south-east hall
    # Blocks are outlined by walls, closed all round: measured from a point inside, the
    # table is 1.6 m x 0.8 m and the pillar 0.5 m x 0.5 m (each centred in its room's loop),
    # and the shelf against the west wall of the south-west room is 2 m long.
    axes = [[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]
    angle = np.linspace(0.0, 2 * np.pi, 360, endpoint=False)
    around = np.column_stack([np.cos(angle), np.sin(angle)])
    blocks = [
        (path[labels == meeting].mean(axis=0), 1.6, 0.8),
        (path[labels == hall].mean(axis=0), 0.5, 0.5),
        (np.array([0.2, 2.5]), None, 2.0),  # midway along the shelf, 0.2 m off the wall
    ]
    for inside, width, depth in blocks:
        east, west, north_, south_ = env.cast([inside] * 4, axes)
        if width is not None:
            assert abs(east + west + env.wall_thickness - width) < 1e-9
        assert abs(north_ + south_ + env.wall_thickness - depth) < 1e-9
        assert np.all(env.cast(np.repeat([inside], 360, axis=0), around) < 1.0)
    # The partition (x = 12) stands free in the middle south room, 2.5 m long: one run of
    # occupied points along it, 2.5 m plus its round caps, clear of the room's walls.
    y = np.arange(0.1, 6.4, 0.001)
    occupied = env.occupancy(np.column_stack([np.full_like(y, 12.0), y]))
    edges = np.flatnonzero(np.diff(occupied))
    assert len(edges) == 2
    assert abs((edges[1] - edges[0]) * 0.001 - (2.5 + env.wall_thickness)) < 2e-3


def test_office_poses_run_from_end_to_end_of_the_path():
    # The first pose is the path's start at the corridor's west end, the last its end at
    # the east end, both heading east along the corridor.
    path = _office_path()
    for n_poses in (2, 7, 30):
        poses = _office_poses(n_poses)
        assert_allclose(poses[[0, -1], :2], path[[0, -1]], atol=1e-9)
        assert poses[0, 0] < 1.0 and poses[-1, 0] > 19.0
        assert np.all((poses[[0, -1], 1] > 6.5) & (poses[[0, -1], 1] < 8.5))
        assert_allclose(poses[[0, -1], 2], 0.0, atol=1e-9)


@pytest.mark.parametrize("n_poses", [2, 7, 30, 120])
def test_office_poses_in_free_space(n_poses):
    data = make_office_scans(n_poses, 3)
    env, poses = data.environment, data.scans.poses
    assert poses.shape == (n_poses, 3)
    assert np.all(env.occupancy(poses[:, :2]) == 0)
    assert _clearance(env, poses[:, :2]).min() >= CLEARANCE
    assert np.all((poses[:, 0] > 0) & (poses[:, 0] < 20) & (poses[:, 1] > 0) & (poses[:, 1] < 15))
    # The poses lie on the path, and the room labels match the room rectangles.
    path = _office_path()
    on_path = Environment2D(np.hstack([path[:-1], path[1:]]), wall_thickness=0.0)
    assert on_path.distance(poses[:, :2]).max() < 1e-9
    rooms = data.rooms
    for pose, room in zip(poses, data.room, strict=True):
        inside = [x0 < pose[0] < x1 and y0 < pose[1] < y1 for x0, x1, y0, y1 in rooms]
        assert inside.count(True) == (room >= 0)
        if room >= 0:
            assert inside[room]
        else:
            assert 6.5 < pose[1] < 8.5  # the corridor


def test_office_path_stays_clear_and_connected():
    env = make_office_environment()
    path = _office_path()
    # Every 6 mm along the path, not only at its vertices (the straight legs have none).
    assert _clearance(env, _office_poses(20_000)[:, :2]).min() >= CLEARANCE
    # No wall between consecutive path points: every pose is reachable from the corridor.
    step = np.diff(path, axis=0)
    length = np.linalg.norm(step, axis=1)
    moving = length > 0
    ranges = env.cast(path[:-1][moving], step[moving], max_range=np.inf)
    assert np.all(ranges > length[moving])
    # The path enters each of the seven rooms once, in order, and turns all the way round in
    # each: its headings there leave no gap of more than a degree.
    labels = _room_of(path)
    runs = labels[np.r_[0, np.flatnonzero(np.diff(labels)) + 1]]
    assert_array_equal(runs, [-1, 0, -1, 1, -1, 2, -1, 3, -1, 4, -1, 5, -1, 6, -1])
    heading = np.arctan2(step[:, 1], step[:, 0])
    for room in range(7):
        h = np.sort(heading[moving & (labels[:-1] == room)])
        gaps = np.diff(np.r_[h, h[0] + 2 * np.pi])
        assert gaps.max() < np.deg2rad(1.0)


def test_office_scans_observe_every_room():
    data = make_office_scans(random_state=0)
    env, rooms = data.environment, data.rooms
    assert_array_equal(np.unique(data.room), np.arange(-1, 7))  # a pose in every room
    # Every wall of every room is hit.
    hits = data.X[data.kind == HIT, :2]
    assert np.all(env.occupancy(hits) == 1)
    near = env.wall_thickness / 2 + 1e-6
    for x0, x1, y0, y1 in rooms:
        in_x = (hits[:, 0] > x0 - near) & (hits[:, 0] < x1 + near)
        in_y = (hits[:, 1] > y0 - near) & (hits[:, 1] < y1 + near)
        for side, coord, span in ((x0, 0, in_y), (x1, 0, in_y), (y0, 1, in_x), (y1, 1, in_x)):
            assert np.any(span & (np.abs(hits[:, coord] - side) <= near))
    # Observed cells cover the floor's free area: 85.3 % overall, 73.9 % in the least covered
    # room (the meeting room, whose table hides the far side of the room), at 0.1 m cells.
    grid = env.ground_truth_grid(0.1, scans=data.scans)
    x, y = grid.points.T
    free = (x > 0) & (x < 20) & (y > 0) & (y < 15) & (grid.occupied == 0)
    assert grid.observed[free].mean() >= 0.83
    labels = _room_of(grid.points)
    for room in range(len(rooms)):
        assert grid.observed[free & (labels == room)].mean() >= 0.70


def test_office_dense_variant():
    data = make_office_scans(n_poses=120, n_beams=180)
    scans = data.scans
    assert (len(scans), scans.n_beams) == (120, 180)
    counts = np.bincount(data.kind, minlength=3)
    assert counts[HIT] + counts[NO_RETURN] == 120 * 180
    assert np.all(np.bincount(data.room + 1)[1:] >= 10)
    # 99.1 % of the free floor observed.
    grid = data.environment.ground_truth_grid(0.1, scans=scans)
    x, y = grid.points.T
    free = (x > 0) & (x < 20) & (y > 0) & (y < 15) & (grid.occupied == 0)
    assert grid.observed[free].mean() >= 0.98


@pytest.mark.parametrize("n_poses, n_beams", [(30, 45), (12, 5), (2, 2)])
def test_office_scans_shapes(n_poses, n_beams):
    data = make_office_scans(n_poses, n_beams)
    scans = data.scans
    assert (len(scans), scans.n_beams, scans.max_range) == (n_poses, n_beams, 10.0)
    assert_allclose(scans.angles, np.linspace(-np.pi / 2, np.pi / 2, n_beams))
    counts = np.bincount(data.kind, minlength=3)
    assert counts[HIT] + counts[NO_RETURN] == n_poses * n_beams
    assert data.X.shape == (len(data.y), 4) and len(data.kind) == len(data.y)
    assert_array_equal(data.y, data.kind == HIT)
    assert data.scan_index.min() >= 0 and data.scan_index.max() < n_poses
    assert data.room.shape == (n_poses,) and data.rooms.shape == (7, 4)
    start, end = segment_endpoints(data.X)
    assert_allclose(np.linalg.norm(end - start, axis=1)[data.kind == NO_RETURN], 10.0)


def test_office_scans_deterministic():
    a = make_office_scans(noise_std=0.05, random_state=3)
    b = make_office_scans(noise_std=0.05, random_state=3)
    c = make_office_scans(noise_std=0.05, random_state=4)
    exact = make_office_scans()
    assert_array_equal(a.X, b.X)
    assert not np.array_equal(a.X, c.X)
    # The poses never depend on the seed; only the ranges do.
    assert_array_equal(a.scans.poses, c.scans.poses)
    assert_array_equal(a.scans.poses, exact.scans.poses)
    assert_array_equal(exact.X, make_office_scans(random_state=7).X)
    both = np.isfinite(exact.scans.ranges) & np.isfinite(a.scans.ranges)
    assert 0 < np.abs(a.scans.ranges[both] - exact.scans.ranges[both]).max() < 0.5
    # A shorter range and a wider free margin are passed on.
    short = make_office_scans(max_range=3.0, free_margin=0.2)
    assert short.scans.max_range == 3.0
    assert np.bincount(short.kind, minlength=3)[NO_RETURN] > np.bincount(exact.kind)[NO_RETURN]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_poses": 1}, "n_poses"),
        ({"n_poses": 2.5}, "n_poses"),
        ({"n_poses": True}, "n_poses"),
        ({"n_poses": "30"}, "n_poses"),
        ({"n_beams": 1}, "n_beams"),
        ({"n_beams": None}, "n_beams"),
        ({"max_range": 0.0}, "max_range"),
        ({"noise_std": -0.1}, "noise_std"),
        ({"free_margin": -0.1}, "free_margin"),
        ({"free_margin": np.nan}, "free_margin"),
    ],
)
def test_office_scans_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_office_scans(**kwargs)
