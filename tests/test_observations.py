import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal
from scipy.spatial.transform import Rotation

from skoccmap.observations import (
    HIT,
    NO_RETURN,
    RETURN,
    ObservationKind,
    Scans,
    as_segments,
    beam_directions,
    scans_to_observations,
    segment_endpoints,
    segment_lengths,
    segment_midpoints,
    split_segments,
)


def _random_scans_2d(rng, n_scans=5, n_beams=7, max_range=4.0):
    headings = rng.uniform(-np.pi, np.pi, n_scans)
    poses = np.column_stack([rng.uniform(-3, 3, (n_scans, 2)), headings])
    ranges = rng.uniform(0.0, 1.3 * max_range, (n_scans, n_beams))
    ranges[rng.random((n_scans, n_beams)) < 0.1] = np.inf
    ranges[rng.random((n_scans, n_beams)) < 0.1] = np.nan
    angles = np.linspace(-np.pi / 2, np.pi / 2, n_beams)
    return poses, ranges, angles, max_range


def _random_scans_3d(rng, n_scans=4, n_beams=9, max_range=4.0):
    quats = Rotation.random(n_scans, random_state=rng).as_quat()  # scipy: [x, y, z, w]
    poses = np.column_stack([rng.uniform(-3, 3, (n_scans, 3)), quats[:, 3], quats[:, :3]])
    ranges = rng.uniform(0.0, 1.3 * max_range, (n_scans, n_beams))
    ranges[rng.random((n_scans, n_beams)) < 0.15] = np.inf
    dirs = rng.normal(size=(n_beams, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return poses, ranges, dirs, max_range


def _reference_rows(poses, ranges, angles, max_range, free_margin):
    """Row-by-row construction with loops and scipy rotations, independent of vectorised code."""
    rows, ys, kinds, scan_ids = [], [], [], []
    n_dims = 2 if poses.shape[1] == 3 else 3
    for s, pose in enumerate(poses):
        origin = pose[:n_dims]
        per_kind = {HIT: [], RETURN: [], NO_RETURN: []}
        for b in range(ranges.shape[1]):
            if n_dims == 2:
                a = angles[b] if angles.ndim == 1 else angles[s, b]
                d = np.array([np.cos(pose[2] + a), np.sin(pose[2] + a)])
            else:
                w, x, y, z = pose[3:]
                d = Rotation.from_quat([x, y, z, w]).apply(angles[b])
            r = ranges[s, b]
            if r == 0.0:
                continue
            if np.isfinite(r) and r < max_range:
                hit = origin + r * d
                per_kind[HIT].append(np.r_[hit, hit])
                if r > free_margin:
                    per_kind[RETURN].append(np.r_[origin, origin + (r - free_margin) * d])
            else:
                per_kind[NO_RETURN].append(np.r_[origin, origin + max_range * d])
        for k in (HIT, RETURN, NO_RETURN):
            rows += per_kind[k]
            ys += [int(k == HIT)] * len(per_kind[k])
            kinds += [k] * len(per_kind[k])
            scan_ids += [s] * len(per_kind[k])
    return np.array(rows), np.array(ys), np.array(kinds), np.array(scan_ids)


def test_kind_codes_are_plain_ints():
    assert (HIT, RETURN, NO_RETURN) == (0, 1, 2)
    assert ObservationKind.RETURN == RETURN
    kind = np.array([HIT, RETURN, NO_RETURN])
    assert kind.dtype.kind == "i"
    assert_array_equal(kind == ObservationKind.NO_RETURN, [False, False, True])


def test_hand_computed_2d():
    X, y, kind, scan = scans_to_observations(
        poses=[[1.0, 1.0, np.pi / 2], [0.0, 0.0, 0.0]],
        ranges=[[2.0, 10.0], [np.nan, 0.03]],
        angles=[0.0, -np.pi / 2],
        max_range=5.0,
        free_margin=0.1,
        return_scan_index=True,
    )
    expected = np.array(
        [
            [1.0, 3.0, 1.0, 3.0],  # scan 0 hit straight ahead (heading +y)
            [1.0, 1.0, 1.0, 2.9],  # its return beam, 0.1 short
            [1.0, 1.0, 6.0, 1.0],  # scan 0 beam to the right (+x): no return
            [0.0, -0.03, 0.0, -0.03],  # scan 1 hit 3 cm to the right: no free part
            [0.0, 0.0, 5.0, 0.0],  # scan 1 NaN -> no return
        ]
    )
    assert_allclose(X, expected, atol=1e-12)
    assert_array_equal(y, [1, 0, 0, 1, 0])
    assert_array_equal(kind, [HIT, RETURN, NO_RETURN, HIT, NO_RETURN])
    assert_array_equal(scan, [0, 0, 0, 1, 1])


@pytest.mark.parametrize("make", [_random_scans_2d, _random_scans_3d])
@pytest.mark.parametrize("free_margin", [0.0, 0.05, 0.7])
def test_matches_loop_reference(make, free_margin):
    poses, ranges, angles, max_range = make(np.random.default_rng(3))
    X, y, kind, scan = scans_to_observations(
        poses, ranges, angles, max_range, free_margin=free_margin, return_scan_index=True
    )
    X_ref, y_ref, kind_ref, scan_ref = _reference_rows(
        poses, ranges, angles, max_range, free_margin
    )
    assert_allclose(X, X_ref, atol=1e-12)
    assert_array_equal(y, y_ref)
    assert_array_equal(kind, kind_ref)
    assert_array_equal(scan, scan_ref)


@pytest.mark.parametrize("make", [_random_scans_2d, _random_scans_3d])
def test_readings_of_zero_give_no_row(make):
    poses, ranges, angles, max_range = make(np.random.default_rng(4))
    ranges[:, ::3] = 0.0
    X, y, kind, scan = scans_to_observations(
        poses, ranges, angles, max_range, return_scan_index=True
    )
    X_ref, y_ref, kind_ref, scan_ref = _reference_rows(poses, ranges, angles, max_range, 0.05)
    assert_allclose(X, X_ref, atol=1e-12)
    assert_array_equal(kind, kind_ref)
    assert_array_equal(scan, scan_ref)
    # Every other reading gives a hit or a no-return beam.
    assert np.sum(kind == HIT) + np.sum(kind == NO_RETURN) == np.sum(ranges != 0.0)


def test_zero_readings_are_no_reading_in_scans_too():
    scans = Scans([[1.0, 2.0, 0.0]], [[0.0, 2.0, np.inf]], [0.0, 0.5, 1.0], 5.0)
    X, y, kind = scans.to_observations()
    assert_array_equal(kind, [HIT, RETURN, NO_RETURN])
    assert not np.any(np.all(X == [1.0, 2.0, 1.0, 2.0], axis=1))
    assert_array_equal(scans.returned(), [[False, True, False]])
    assert_array_equal(scans.unread(), [[True, False, False]])
    assert_allclose(scans.hit_points(), X[kind == HIT, :2])


def test_per_scan_angles_2d():
    poses, ranges, _, max_range = _random_scans_2d(np.random.default_rng(0), n_scans=3, n_beams=4)
    angles = np.random.default_rng(1).uniform(-np.pi, np.pi, (3, 4))
    X, y, kind = scans_to_observations(poses, ranges, angles, max_range)
    X_ref, y_ref, kind_ref, _ = _reference_rows(poses, ranges, angles, max_range, 0.05)
    assert_allclose(X, X_ref, atol=1e-12)
    assert_array_equal(kind, kind_ref)


def test_angles_in_degrees_warn():
    poses, ranges = [[0.0, 0.0, 0.0]], [[2.0, 3.0, 2.5]]
    with pytest.warns(UserWarning, match=r"span 180 radians.*np.radians\(angles\)"):
        scans_to_observations(poses, ranges, [-90.0, 0.0, 90.0], 10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # A full turn of beams, and per-scan angles each within one turn, are radians.
        scans_to_observations(poses, ranges, np.linspace(-np.pi, np.pi, 3), 10.0)
        scans_to_observations(poses * 2, ranges * 2, [[0.0, 1.0, 2.0], [5.0, 6.0, 7.0]], 10.0)


def _check_invariants(X, y, kind, scan, poses, ranges, max_range, free_margin):
    n_dims = X.shape[1] // 2
    start, end = X[:, :n_dims], X[:, n_dims:]
    origins = poses[scan, :n_dims]
    lengths = np.linalg.norm(end - start, axis=1)
    hits = kind == HIT
    assert_array_equal(y, hits.astype(int))
    assert_array_equal(lengths[hits], 0.0)
    assert_allclose(start[~hits], origins[~hits], atol=1e-9)
    assert_allclose(lengths[kind == NO_RETURN], max_range, rtol=1e-9)
    # every return beam points at a hit of its scan, free_margin beyond its end
    hit_pts, hit_scan = start[hits], scan[hits]
    for i in np.flatnonzero(kind == RETURN):
        d = (end[i] - start[i]) / lengths[i]
        target = end[i] + free_margin * d
        same = hit_pts[hit_scan == scan[i]]
        assert np.min(np.linalg.norm(same - target, axis=1)) < 1e-9
    returned = np.isfinite(ranges) & (ranges < max_range)
    assert hits.sum() == returned.sum()
    assert (kind == NO_RETURN).sum() == (~returned).sum()
    assert (kind == RETURN).sum() == (returned & (ranges > free_margin)).sum()


@pytest.mark.filterwarnings("ignore:free_margin=.* is at least as long as")
@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    three_d=st.booleans(),
    free_margin=st.floats(0.0, 1.0),
    max_range=st.floats(0.5, 30.0),
)
def test_invariants_property(seed, three_d, free_margin, max_range):
    rng = np.random.default_rng(seed)
    make = _random_scans_3d if three_d else _random_scans_2d
    poses, ranges, angles, _ = make(rng, max_range=max_range)
    X, y, kind, scan = scans_to_observations(
        poses, ranges, angles, max_range, free_margin=free_margin, return_scan_index=True
    )
    _check_invariants(X, y, kind, scan, poses, ranges, max_range, free_margin)


def test_a_free_margin_longer_than_most_ranges_warns():
    args = ([[0.0, 0.0, 0.0]], [[1.0, 2.0, 3.0]], [0.0, 0.5, 1.0], 5.0)
    with pytest.warns(UserWarning, match="free_margin=2.5 m is at least as long as 2 of the 3"):
        X, y, kind = scans_to_observations(*args, free_margin=2.5)
    with pytest.warns(UserWarning, match="at least as long") as caught:
        Scans(*args).to_observations(free_margin=2.0)
    assert caught[0].filename == __file__
    assert_array_equal(kind, [HIT, HIT, HIT, RETURN])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans_to_observations(*args, free_margin=1.5)  # one of three: a near obstacle


def test_range_at_max_range_is_no_return():
    X, y, kind = scans_to_observations([[0.0, 0.0, 0.0]], [[4.0, 3.999]], [0.0, 0.0], 4.0)
    assert_array_equal(kind, [HIT, RETURN, NO_RETURN])


def test_3d_quaternion_rotation_hand_computed():
    # 90 degrees about z: the sensor's x axis points along world +y.
    q = [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]
    X, y, kind = scans_to_observations(
        [[1.0, 2.0, 3.0, *q]], [[2.0]], [[1.0, 0.0, 0.0]], 5.0, free_margin=0.5
    )
    assert_allclose(X, [[1, 4, 3, 1, 4, 3], [1, 2, 3, 1, 3.5, 3]], atol=1e-12)


def test_beam_directions_unit_and_rotated():
    dirs = beam_directions([[0.0, 0.0, np.pi / 2]], [0.0, np.pi / 2])
    assert_allclose(dirs, [[[0.0, 1.0], [-1.0, 0.0]]], atol=1e-12)
    poses, _, d3, _ = _random_scans_3d(np.random.default_rng(5))
    out = beam_directions(poses, d3)
    assert_allclose(np.linalg.norm(out, axis=-1), 1.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"poses": [[0.0, np.nan, 0.0]]}, "poses contains NaN"),
        ({"poses": [[0.0, 0.0]]}, "poses must have shape"),
        ({"poses": np.zeros((0, 3)), "ranges": np.zeros((0, 2))}, "poses is empty"),
        ({"ranges": [[1.0, -0.5]]}, "ranges must be non-negative"),
        ({"ranges": [[1.0, -np.inf]]}, "ranges must be non-negative"),
        ({"ranges": [1.0, 2.0]}, "ranges must have shape"),
        ({"ranges": [[1.0, 2.0], [1.0, 2.0]]}, "ranges has 2 row"),
        ({"ranges": np.zeros((1, 0)), "angles": []}, "no beams"),
        ({"angles": [0.0, 1.0, 2.0]}, "angles must have shape.*ranges has 2 beam"),
        ({"angles": [0.0, np.nan]}, "angles contains NaN"),
        ({"max_range": 0.0}, "max_range must be a positive"),
        ({"max_range": -1.0}, "max_range must be a positive"),
        ({"max_range": np.inf}, "max_range must be a positive"),
        ({"max_range": "far"}, "max_range must be a positive"),
        ({"free_margin": -0.1}, "free_margin must be a non-negative"),
        ({"free_margin": np.nan}, "free_margin must be a non-negative"),
    ],
)
def test_bad_input_2d(kwargs, match):
    args = {
        "poses": [[0.0, 0.0, 0.0]],
        "ranges": [[1.0, 2.0]],
        "angles": [0.0, 1.0],
        "max_range": 5.0,
        "free_margin": 0.05,
    }
    args.update(kwargs)
    free_margin = args.pop("free_margin")
    with pytest.raises(ValueError, match=match):
        scans_to_observations(**args, free_margin=free_margin)


def test_bad_input_3d():
    pose = [[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]
    with pytest.raises(ValueError, match="unit quaternions"):
        scans_to_observations([[0, 0, 0, 2.0, 0, 0, 0]], [[1.0]], [[1.0, 0, 0]], 5.0)
    with pytest.raises(ValueError, match="unit direction vectors"):
        scans_to_observations(pose, [[1.0]], [[2.0, 0, 0]], 5.0)
    with pytest.raises(ValueError, match="angles must hold unit beam directions"):
        scans_to_observations(pose, [[1.0]], [0.0], 5.0)


def _scans(n_scans=6, per_scan_angles=False, timestamps=True):
    rng = np.random.default_rng(0)
    poses, ranges, angles, max_range = _random_scans_2d(rng, n_scans=n_scans, n_beams=5)
    if per_scan_angles:
        angles = rng.uniform(-1, 1, (n_scans, 5))
    ts = np.arange(n_scans) * 0.1 if timestamps else None
    return Scans(poses, ranges, angles, max_range, timestamps=ts)


@pytest.mark.parametrize("per_scan_angles", [False, True])
@pytest.mark.parametrize(
    "index",
    [slice(None, None, 2), np.array([4, 0, 0]), np.array([True, False, True, False, False, True])],
    ids=["slice", "int-array", "mask"],
)
def test_scans_indexing(per_scan_angles, index):
    scans = _scans(per_scan_angles=per_scan_angles)
    sub = scans[index]
    expected = np.arange(6)[index]
    assert isinstance(sub, Scans)
    assert len(sub) == len(expected)
    assert_array_equal(sub.poses, scans.poses[expected])
    assert_array_equal(sub.ranges, scans.ranges[expected])
    assert_array_equal(sub.timestamps, scans.timestamps[expected])
    if per_scan_angles:
        assert_array_equal(sub.angles, scans.angles[expected])
    else:
        assert_array_equal(sub.angles, scans.angles)
    # observations of a subset equal the rows of the full set from those scans (for unique ids)
    if len(np.unique(expected)) == len(expected) and np.all(np.diff(expected) > 0):
        X, y, kind, scan = scans.to_observations(return_scan_index=True)
        X_sub, _, kind_sub = sub.to_observations()
        keep = np.isin(scan, expected)
        assert_allclose(X_sub, X[keep])
        assert_array_equal(kind_sub, kind[keep])


def test_scans_int_index_keeps_one_scan():
    scans = _scans()
    one = scans[-1]
    assert len(one) == 1
    assert_array_equal(one.poses, scans.poses[-1:])
    with pytest.raises(IndexError):
        scans[6]
    with pytest.raises(IndexError, match="boolean mask"):
        scans[np.array([True, False])]
    with pytest.raises(IndexError):
        scans[np.array([0.5])]
    with pytest.raises(IndexError, match="indexed by scan only"):
        scans[0, 1]
    # An empty selection said "poses is empty", about an argument the user never passed.
    for empty in (slice(5, 3), slice(10, 20), np.zeros(6, dtype=bool), np.array([], int)):
        with pytest.raises(IndexError, match="holds none of the 6 scans"):
            scans[empty]


def test_scans_repr_is_one_line():
    # The dataclass repr printed every pose, range and angle: 199 lines for Intel.
    assert repr(_scans()) == "Scans(6 scans x 5 beams, 2-D, max_range=4, with timestamps)"
    assert repr(_scans(timestamps=False)[:2]) == "Scans(2 scans x 5 beams, 2-D, max_range=4)"


def test_scans_properties_and_helpers():
    scans = _scans(timestamps=False)
    assert (scans.n_dims, scans.n_scans, scans.n_beams, scans.timestamps) == (2, 6, 5, None)
    X, y, kind = scans.to_observations(free_margin=0.05)
    assert_allclose(scans.hit_points(), X[kind == HIT, :2])
    assert scans.returned().sum() == (kind == HIT).sum()
    assert_allclose(scans.origins(), scans.poses[:, :2])
    assert scans.directions().shape == (6, 5, 2)


def test_scans_validation():
    with pytest.raises(ValueError, match="timestamps must have shape"):
        Scans(np.zeros((2, 3)), np.ones((2, 1)), [0.0], 3.0, timestamps=[0.0])
    with pytest.raises(ValueError, match="timestamps contains NaN"):
        Scans(np.zeros((2, 3)), np.ones((2, 1)), [0.0], 3.0, timestamps=[0.0, np.nan])
    with pytest.raises(ValueError, match="ranges must be non-negative"):
        Scans(np.zeros((1, 3)), [[-1.0]], [0.0], 3.0)
    scans3 = Scans(np.array([[0, 0, 0, 1.0, 0, 0, 0]]), [[1.0]], [[0.0, 0.0, 1.0]], 3.0)
    assert scans3.n_dims == 3


def test_segment_helpers():
    pts = np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]])
    X = as_segments(pts)
    assert X.shape == (2, 6)
    assert_array_equal(segment_lengths(X), 0.0)
    assert_array_equal(segment_midpoints(X), pts)
    start, end = segment_endpoints([[0.0, 1.0, 3.0, 5.0]])
    assert_array_equal(start, [[0.0, 1.0]])
    assert_array_equal(end, [[3.0, 5.0]])
    assert_allclose(segment_lengths([[0.0, 1.0, 3.0, 5.0]]), [5.0])
    assert_allclose(segment_midpoints([[0.0, 1.0, 3.0, 5.0]]), [[1.5, 3.0]])
    assert segment_lengths(np.zeros((0, 4))).shape == (0,)
    with pytest.raises(ValueError, match="points must be a 2-D"):
        as_segments([1.0, 2.0])
    with pytest.raises(ValueError, match="points contains NaN"):
        as_segments([[np.nan, 1.0]])
    with pytest.raises(ValueError, match="even number of columns"):
        segment_lengths([[0.0, 1.0, 2.0]])


def test_split_segments_cuts_long_segments_into_equal_pieces():
    X = np.array([[0.0, 0.0, 3.0, 4.0], [1.0, 1.0, 1.0, 1.0], [0.0, 0.0, 0.5, 0.0]])
    pieces, source = split_segments(X, 2.0)
    # 5 m -> 3 pieces of 5/3 m; a point and a short segment stay whole.
    np.testing.assert_array_equal(source, [0, 0, 0, 1, 2])
    np.testing.assert_allclose(segment_lengths(pieces), [5 / 3] * 3 + [0.0, 0.5])
    # Consecutive pieces join, and together they span their segment.
    np.testing.assert_allclose(pieces[:2, 2:], pieces[1:3, :2])
    np.testing.assert_allclose(pieces[0, :2], X[0, :2])
    np.testing.assert_allclose(pieces[2, 2:], X[0, 2:])
    np.testing.assert_array_equal(pieces[3:], X[1:])


@pytest.mark.parametrize("max_length", [None, np.inf])
def test_split_segments_without_bound_keeps_segments(max_length):
    X = np.array([[0.0, 0.0, 0.0, 30.0, 0.0, 0.0]])
    pieces, source = split_segments(X, max_length)
    np.testing.assert_array_equal(pieces, X)
    np.testing.assert_array_equal(source, [0])


@pytest.mark.parametrize("max_length", [0.0, -1.0, np.nan])
def test_split_segments_rejects_bad_bound(max_length):
    with pytest.raises(ValueError, match="max_length"):
        split_segments([[0.0, 0.0, 1.0, 0.0]], max_length)


@pytest.mark.parametrize("length", [0.25, 0.75, 1.75, 2.75, 3.0, 0.1])
def test_graded_pieces_tile_a_segment_ending_on_their_boundaries(length):
    # Graded pieces of 0.25, 0.5 and then 1 m from the end: lengths on their boundaries
    # give no zero-length piece (a spurious free point).
    pieces, _ = split_segments([[0.0, 0.0, length, 0.0]], 1.0, end_length=0.25)
    lengths = pieces[:, 2] - pieces[:, 0]
    assert np.all(lengths > 0) and np.all(lengths <= 1.0 + 1e-12)
    assert pieces[0, 0] == 0.0 and pieces[-1, 2] == length
    assert_array_equal(pieces[1:, 0], pieces[:-1, 2])
    if length == 0.75:
        assert_allclose(pieces, [[0.0, 0.0, 0.5, 0.0], [0.5, 0.0, 0.75, 0.0]])


@pytest.mark.parametrize(
    ("length", "max_length", "end_length", "n_pieces"),
    [(15.0, None, 1.0, 4), (1.05, 1.0, 0.35, 2), (0.35 * 7, None, 0.35, 3)],
)
def test_segments_as_long_as_a_graded_boundary_up_to_rounding_take_no_sliver(
    length, max_length, end_length, n_pieces
):
    # A no-return beam of 15 m is cut at 1, 3 and 7 m from its end: computed from
    # coordinates in any direction its length is a rounding error either side of 15, and
    # the long side must not add a last piece of that rounding error's length.
    rng = np.random.default_rng(5)
    angle = rng.uniform(0.0, 2.0 * np.pi, 500)
    start = rng.uniform(-20.0, 20.0, (500, 2))
    X = np.hstack([start, start + length * np.c_[np.cos(angle), np.sin(angle)]])
    assert np.any(np.linalg.norm(X[:, 2:] - X[:, :2], axis=1) > length)
    pieces, source = split_segments(X, max_length, end_length=end_length)
    assert_array_equal(np.bincount(source, minlength=500), n_pieces)
    assert np.linalg.norm(pieces[:, 2:] - pieces[:, :2], axis=1).min() > 0.3


def test_split_segments_takes_a_whole_number_of_pieces_despite_rounding():
    # 3 * 0.1 / 0.1 is 3.0000000000000004 in floating point: three pieces, not four.
    pieces, _ = split_segments([[0.0, 0.0, 3 * 0.1, 0.0]], 0.1)
    assert len(pieces) == 3


def test_split_segments_in_blocks_equals_at_once(monkeypatch):
    import skoccmap.observations as observations

    rng = np.random.default_rng(0)
    X = rng.uniform(-10.0, 10.0, size=(60, 4))
    X[::9, 2:] = X[::9, :2]  # points stay whole
    graded = rng.random(60) < 0.5
    at_once = split_segments(X, 1.0, end_length=0.25, graded=graded)
    monkeypatch.setattr(observations, "_PIECE_BLOCK", 7)
    in_blocks = split_segments(X, 1.0, end_length=0.25, graded=graded)
    assert at_once[0].shape[0] > 7 * 10
    for a, b in zip(at_once, in_blocks, strict=True):
        np.testing.assert_array_equal(a, b)


def test_split_segments_exact_multiples_and_bad_end_length():
    # 0.3 m is three 0.1 m pieces, although 0.3 / 0.1 rounds above 3.
    pieces, _ = split_segments([[0.0, 0.0, 0.3, 0.0]], 0.1)
    assert len(pieces) == 3
    with pytest.raises(ValueError, match="end_length"):
        split_segments(np.empty((0, 4)), 1.0, end_length=-1.0)


@pytest.mark.parametrize(
    ("poses", "angles"),
    [([[0.0, 0.0, 0.0]], 0.0), ([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]], [1.0, 0.0, 0.0])],
)
def test_beam_directions_without_a_beam_axis_is_a_clear_error(poses, angles):
    with pytest.raises(ValueError, match="one beam is an array of one"):
        beam_directions(poses, angles)


def test_split_segments_refuses_an_infinite_end_length():
    with pytest.raises(ValueError, match="end_length must be finite"):
        split_segments([[0.0, 0.0, 5.0, 0.0]], 1.0, end_length=np.inf)


def test_3d_directions_with_2d_poses_name_the_poses():
    directions = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    for angles in (directions, np.stack([directions] * 3)):
        with pytest.raises(ValueError, match=r"3-D beam directions .* poses are 2-D"):
            scans_to_observations(np.zeros((3, 3)), np.ones((3, 2)), angles, 5.0)
    # Per-scan angles of three scans of three beams are 2-D angles, not directions.
    X, _, _ = scans_to_observations(np.zeros((3, 3)), np.ones((3, 3)), np.zeros((3, 3)), 5.0)
    assert X.shape[1] == 4


def test_quaternions_in_scalar_last_order_warn():
    # A level robot turning: scipy's as_quat() is [qx, qy, qz, qw] = [0, 0, sin, cos].
    yaw = np.array([0.0, 0.7, 1.4, -2.0])
    q_scipy = Rotation.from_euler("z", yaw[:, None]).as_quat()
    poses = np.column_stack([np.zeros((4, 3)), q_scipy])
    directions = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    ranges = np.ones((4, 2))
    with pytest.warns(UserWarning, match=r"upside down.*np.roll\(q, 1, axis=1\)"):
        scans_to_observations(poses, ranges, directions, 5.0)
    # Reordered as the warning says: level poses, no warning.
    poses[:, 3:] = np.roll(q_scipy, 1, axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        X, _, _ = scans_to_observations(poses, ranges, directions, 5.0)
    assert_allclose(X[:, 2], 0.0, atol=1e-12)
    # One pose turned by pi is a robot facing back, not a convention: no warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans_to_observations([[0, 0, 0, 0, 0, 0, 1.0]], [[1.0, 1.0]], directions, 5.0)
        scans_to_observations([[0, 0, 0, 0.06, 0, 0, 0.9982]] * 2, ranges[:2], directions, 5.0)


def test_near_unit_quaternions_and_directions_are_normalised_and_far_ones_refused():
    q = Rotation.random(random_state=0).as_quat()  # scipy: [x, y, z, w]
    pose = np.r_[1.0, 2.0, 3.0, q[3], q[:3]]
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    X, y, kind = scans_to_observations([pose], [[2.0, np.inf]], dirs, 5.0)
    # Off unit length by 5e-4 (rounding, as from float32 logs): the same rows.
    rounded = np.r_[pose[:3], pose[3:] * (1 + 5e-4)]
    X_rounded, _, _ = scans_to_observations([rounded], [[2.0, np.inf]], dirs * (1 - 5e-4), 5.0)
    assert_allclose(X_rounded, X, atol=1e-12)
    # Off by 1 %: a caller's mistake.
    with pytest.raises(ValueError, match="unit quaternions"):
        scans_to_observations([np.r_[pose[:3], pose[3:] * 1.01]], [[2.0, np.inf]], dirs, 5.0)
    with pytest.raises(ValueError, match="unit direction vectors"):
        scans_to_observations([pose], [[2.0, np.inf]], dirs * 1.01, 5.0)


def test_wrong_angles_shape_names_both_beam_counts():
    with pytest.raises(ValueError, match=r"ranges has 2 beam\(s\) \(columns\) .* angles 3,"):
        scans_to_observations([[0.0, 0.0, 0.0]], [[1.0, 2.0]], [[0.0, 1.0, 2.0]], 5.0)
    pose = [[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]
    with pytest.raises(ValueError, match=r"ranges has 3 beam\(s\) \(columns\) .* angles 4,"):
        scans_to_observations(pose, [[1.0, 2.0, 3.0]], np.eye(3)[[0, 1, 2, 0]], 5.0)


@pytest.mark.parametrize(
    "angles",
    [[[0.0, 0.5, 1.0], [-90.0, 0.0, 90.0]], [[-90.0, 0.0, 90.0]] * 2, [-5.0, 0.0, 5.0]],
    ids=["one-scan-of-two", "every-scan", "ten-degree-fan"],
)
def test_angles_in_degrees_warn_from_any_scan_at_the_callers_line(angles):
    poses, ranges = [[0.0, 0.0, 0.0]] * 2, [[2.0, 3.0, 2.5]] * 2
    with pytest.warns(UserWarning, match="more than a full turn") as caught:
        scans_to_observations(poses, ranges, angles, 10.0)
    assert caught[0].filename == __file__


def test_long_3d_directions_are_refused_without_a_degrees_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match="unit direction vectors"):
            scans_to_observations([[0, 0, 0, 1.0, 0, 0, 0]], [[1.0]], [[30.0, 0.0, 0.0]], 5.0)


def test_a_free_margin_warning_needs_more_than_half_of_the_returns_without_a_free_row():
    args = ([[0.0, 0.0, 0.0]], [[1.0, 2.0, 3.0, 4.0]], [0.0, 0.5, 1.0, 1.5], 5.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans_to_observations(*args, free_margin=2.0)  # 1 and 2 m: two of four, half
    with pytest.warns(UserWarning, match="at least as long as 3 of the 4"):
        scans_to_observations(*args, free_margin=3.0)


def test_default_free_margin_is_five_cm_in_function_and_scans():
    args = ([[0.0, 0.0, 0.0]], [[0.03, 0.07, 1.0]], [0.0, 0.5, 1.0], 5.0)
    for X, _, kind in (scans_to_observations(*args), Scans(*args).to_observations()):
        assert_array_equal(kind, [HIT, HIT, HIT, RETURN, RETURN])
        assert_allclose(segment_lengths(X[kind == RETURN]), [0.07 - 0.05, 1.0 - 0.05])


def test_scans_index_by_any_integer_in_range_and_refuse_others():
    scans = _scans()
    assert_array_equal(scans[-6].poses, scans.poses[:1])
    assert_array_equal(scans[np.int64(2)].poses, scans.poses[2:3])
    for out in (6, -7):
        with pytest.raises(IndexError, match="out of range for 6 scans"):
            scans[out]
    with pytest.raises(IndexError, match="1-D integer array"):
        scans[np.array([[0, 1]])]


@pytest.mark.parametrize("per_scan_angles", [False, True])
def test_3d_scans_indexing_keeps_each_scans_directions(per_scan_angles):
    rng = np.random.default_rng(6)
    poses, ranges, dirs, max_range = _random_scans_3d(rng, n_scans=4, n_beams=5)
    if per_scan_angles:
        dirs = Rotation.random(20, random_state=rng).apply([1.0, 0.0, 0.0]).reshape(4, 5, 3)
    scans = Scans(poses, ranges, dirs, max_range)
    X, _, kind, scan = scans.to_observations(return_scan_index=True)
    X_sub, _, kind_sub = scans[1:3].to_observations()
    keep = np.isin(scan, [1, 2])
    assert_allclose(X_sub, X[keep])
    assert_array_equal(kind_sub, kind[keep])


def test_scans_origins_are_a_copy():
    scans = _scans()
    poses = scans.poses.copy()
    scans.origins()[:] = 0.0
    assert_array_equal(scans.poses, poses)


def test_as_segments_refuses_points_without_coordinates():
    with pytest.raises(ValueError, match="points must be a 2-D"):
        as_segments(np.zeros((2, 0)))


def _graded_piece_lengths(length, max_length, end_length):
    """Piece lengths, start to end, by the documented rule: pieces of end_length, 2 end_length,
    ... (each shorter than max_length, ending strictly inside the segment) from the end, then
    the rest in equal pieces no longer than max_length."""
    tail, piece = [], end_length
    while piece < max_length and sum(tail) + piece < length:
        tail.append(piece)
        piece *= 2
    rest = length - sum(tail)
    n = max(int(np.ceil(rest / max_length - 1e-9)), 1) if np.isfinite(max_length) else 1
    return [rest / n] * n + tail[::-1]


@pytest.mark.parametrize(
    ("length", "max_length", "end_length"),
    [(5.0, 2.0, 0.5), (4.0, None, 0.5), (3.9, None, 0.5), (100.0, None, 0.3), (9.0, 4.0, 1.0)],
)
def test_graded_pieces_double_from_the_end_below_max_length(length, max_length, end_length):
    X = [[1.0, -2.0, 1.0 + length, -2.0]]
    pieces, _ = split_segments(X, max_length, end_length=end_length)
    bound = np.inf if max_length is None else max_length
    assert_allclose(segment_lengths(pieces), _graded_piece_lengths(length, bound, end_length))
    assert_allclose(pieces[1:, :2], pieces[:-1, 2:])


def test_split_segments_grades_only_the_graded_segments():
    X = np.array([[0.0, 0.0, 4.0, 0.0], [0.0, 1.0, 4.0, 1.0]])
    pieces, source = split_segments(X, 1.0, end_length=0.25, graded=[True, False])
    lengths = segment_lengths(pieces)
    assert_allclose(lengths[source == 0], _graded_piece_lengths(4.0, 1.0, 0.25))
    assert_allclose(lengths[source == 1], [1.0] * 4)
    with pytest.raises(ValueError, match=r"graded must have shape \(2,\)"):
        split_segments(X, 1.0, end_length=0.25, graded=[True])
    pieces, source = split_segments(np.empty((0, 4)), 1.0, end_length=0.25)
    assert pieces.shape == (0, 4) and source.shape == (0,)


def test_scans_degrees_warning_names_the_callers_line():
    # It named '<string>', the __init__ that dataclasses writes, not this file.
    with pytest.warns(UserWarning, match="more than a full turn") as caught:
        Scans([[0.0, 0.0, 0.0]], [[1.0, 2.0]], [-90.0, 90.0], 5.0)
    assert caught[0].filename == __file__


@pytest.mark.parametrize(
    "call",
    [
        lambda: scans_to_observations([[0.0, 0.0, 0.0]], [[0.5]], [0.0], True),
        lambda: scans_to_observations([[0.0, 0.0, 0.0]], [[0.5]], [0.0], 5.0, free_margin=True),
        lambda: Scans([[0.0, 0.0, 0.0]], [[0.5]], [0.0], True),
        lambda: split_segments([[0.0, 0.0, 3.0, 0.0]], True),
        lambda: split_segments([[0.0, 0.0, 3.0, 0.0]], 1.0, end_length=True),
    ],
    ids=["max_range", "free_margin", "Scans-max_range", "max_length", "end_length"],
)
def test_boolean_lengths_are_refused(call):
    # True was read as 1 m.
    with pytest.raises(ValueError, match="got True"):
        call()


def test_segment_helpers_refuse_coordinates_whose_squares_overflow():
    # segment_lengths gave inf, segment_midpoints inf, and split_segments stopped on
    # "cannot convert float infinity to integer".
    far = np.array([[0.0, 0.0, 1e200, 0.0]])
    for call in (
        lambda: segment_lengths(far),
        lambda: segment_midpoints(far * 1.7e108),
        lambda: split_segments(far, None, end_length=0.1),
    ):
        with pytest.raises(ValueError, match="beyond 1e\\+100 their squares overflow"):
            call()


@pytest.mark.parametrize("length, max_length", [(1e20, 1.0), (1.0, 1e-300)])
def test_split_segments_refuses_more_pieces_than_an_array_holds(length, max_length):
    # The count of pieces wrapped to a negative number: "negative dimensions are not allowed".
    with pytest.raises(ValueError, match=r"more than an array can hold.*larger max_length"):
        split_segments([[0.0, 0.0, length, 0.0], [0.0, 0.0, 1.0, 0.0]], max_length)
