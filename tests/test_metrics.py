import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from scipy import stats
from sklearn.calibration import calibration_curve

from skoccmap.datasets import (
    Environment2D,
    Room3D,
    make_paper_scans,
    make_room3d_scans,
    simulate_scans,
)
from skoccmap.grid import ROS_FREE_THRESH, ROS_OCCUPIED_THRESH
from skoccmap.metrics import (
    HILBERT_BLOCK_SIZE,
    HILBERT_FREE_MARGIN,
    HILBERT_HELDOUT_FRACTION,
    HILBERT_MAX_BEAM_RANGE,
    HILBERT_N_FREE_PER_BEAM,
    _heldout_blocks,
    blocks_protocol,
    expected_calibration_error,
    ground_truth_auc,
    heldout_auc,
    heldout_points,
    map_quality,
    split_scan_blocks,
    split_scans,
)
from skoccmap.observations import Scans, as_segments


class _TruthClassifier:
    """P(occupied) from the simulator's truth at the segment start (points only)."""

    classes_ = np.array([0, 1])

    def __init__(self, environment, flip=False, noise=None, seed=0):
        self.environment, self.flip, self.noise, self.seed = environment, flip, noise, seed

    def predict_proba(self, X):
        d = X.shape[1] // 2
        assert_array_equal(X[:, :d], X[:, d:])  # scored on zero-length segments
        p = self.environment.occupancy(X[:, :d]).astype(float)
        if self.flip:
            p = 1 - p
        if self.noise == "random":
            p = np.random.default_rng(self.seed).uniform(size=len(X))
        return np.column_stack([1 - p, p])


@pytest.fixture(scope="module")
def paper():
    return make_paper_scans()


def test_split_scans(paper):
    train, test = split_scans(paper.scans, every_nth=10)
    assert (len(train), len(test)) == (23, 3)
    assert_array_equal(test.poses, paper.scans.poses[[0, 10, 20]])
    train, test = split_scans(paper.scans, every_nth=4, offset=3)
    assert_array_equal(test.poses, paper.scans.poses[[3, 7, 11, 15, 19, 23]])
    merged = np.concatenate([train.poses, test.poses])
    assert len(np.unique(merged, axis=0)) == len(paper.scans)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"every_nth": 1}, "every_nth must be an integer >= 2"),
        ({"every_nth": 2.5}, "every_nth must be an integer >= 2"),
        ({"every_nth": 3, "offset": 3}, r"offset must be an integer in \[0, every_nth\)"),
        # Read as offset 1.
        ({"every_nth": 3, "offset": True}, r"offset must be an integer .*got True"),
        ({"every_nth": 100, "offset": 50}, "empty"),
    ],
)
def test_split_scans_bad_input(paper, kwargs, match):
    with pytest.raises(ValueError, match=match):
        split_scans(paper.scans, **kwargs)


def test_split_scans_of_one_scan_leaves_nothing_to_train_on(paper):
    # Scan 0 is held out from offset 0: a one-scan log has no training scan left.
    with pytest.raises(ValueError, match="training or the test set empty"):
        split_scans(paper.scans[:1], every_nth=2)
    train, test = split_scans(paper.scans[:2], every_nth=2)
    assert_array_equal(train.poses, paper.scans.poses[[1]])
    assert_array_equal(test.poses, paper.scans.poses[[0]])


def test_split_scans_every_nth_beyond_int64(paper):
    # Only scan 0 is held out; numpy's int64 cannot hold such an every_nth.
    train, test = split_scans(paper.scans, every_nth=10**30)
    assert (len(train), len(test)) == (25, 1)
    assert_array_equal(test.poses, paper.scans.poses[[0]])
    with pytest.raises(ValueError, match="empty"):
        split_scans(paper.scans, every_nth=10**30, offset=10**29)


def test_split_scans_rejects_arrays():
    with pytest.raises(ValueError, match="must be a skoccmap.observations.Scans"):
        split_scans(np.zeros((3, 3)))


def test_heldout_points_geometry(paper):
    scans = paper.scans[5:9]
    points, labels = heldout_points(scans, n_free_per_beam=3, free_margin=0.2, random_state=0)
    hits = scans.hit_points()
    assert_array_equal(labels, np.r_[np.ones(len(hits)), np.zeros(len(points) - len(hits))])
    assert_allclose(points[: len(hits)], hits)
    free = points[len(hits) :]
    returned = scans.returned()
    n_with_free = np.count_nonzero(~returned | (scans.ranges > 0.2))
    assert len(free) == 3 * n_with_free
    # each free point lies on one of its scans' beams, before the hit minus the margin
    origins, dirs = scans.origins(), scans.directions()
    limit = np.where(returned, scans.ranges - 0.2, scans.max_range)
    for p in free:
        rel = p - origins[:, None, :]
        t = np.einsum("sbd,sbd->sb", rel, dirs)
        off = np.linalg.norm(rel - t[..., None] * dirs, axis=-1)
        on_beam = (off < 1e-9) & (t >= 0) & (t <= limit + 1e-9)
        assert on_beam.any()
    assert not np.any(paper.environment.occupancy(free))


def test_heldout_points_uniform_along_beam():
    scans = Scans([[0.0, 0.0, 0.0]], [[5.0]], [0.0], max_range=8.0)
    points, labels = heldout_points(scans, n_free_per_beam=4000, free_margin=1.0, random_state=0)
    x = points[labels == 0, 0]
    assert_allclose(points[labels == 0, 1], 0.0)
    assert stats.kstest(x, stats.uniform(0, 4).cdf).pvalue > 1e-3
    no_return = Scans([[0.0, 0.0, 0.0]], [[np.inf]], [0.0], max_range=8.0)
    points, labels = heldout_points(no_return, n_free_per_beam=4000, random_state=0)
    assert labels.sum() == 0
    assert stats.kstest(points[:, 0], stats.uniform(0, 8).cdf).pvalue > 1e-3


def test_zero_readings_give_no_heldout_point():
    scans = Scans([[0.0, 0.0, 0.0]], [[0.0, 2.0, np.inf]], [0.0, 0.5, 1.0], max_range=8.0)
    points, labels = heldout_points(scans, n_free_per_beam=50, random_state=0)
    assert labels.sum() == 1 and not np.any(np.all(points == 0.0, axis=1))
    # The two beams read: along directions 0.5 and 1.0 only.
    angles = np.arctan2(points[:, 1], points[:, 0])
    assert np.all(np.isclose(angles, 0.5) | np.isclose(angles, 1.0))


def test_a_hit_exactly_at_the_free_margin_gives_no_free_point():
    # The free stretch of a beam ends free_margin short of its hit: a hit at exactly that
    # range leaves a stretch of length zero, and no free point (one would sit on the sensor).
    # 0.25 and 0.5 are exact in binary, so the stretches are exactly 0 and 0.25 m.
    scans = Scans([[1.0, 2.0, 0.0]], [[0.25, 0.5]], [0.0, 0.5 * np.pi], max_range=8.0)
    points, labels = heldout_points(scans, n_free_per_beam=5, free_margin=0.25, random_state=0)
    assert_allclose(points[labels == 1], [[1.25, 2.0], [1.0, 2.5]], atol=1e-15)
    free = points[labels == 0]
    assert len(free) == 5
    assert_allclose(free[:, 0], 1.0, atol=1e-15)  # all on the second beam, northwards
    assert np.all((free[:, 1] >= 2.0) & (free[:, 1] <= 2.25))


def test_heldout_points_draw_major_order():
    # n free points per beam are n rounds over the usable beams (scan and beam order), each
    # at a uniform fraction of its beam's free length: for a given seed, more points per
    # beam extend the set drawn with fewer.
    ranges = [[2.0, 3.0, np.inf], [1.0, 0.02, 4.0]]
    scans = Scans([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5]], ranges, [0.0, 1.0, 2.0], max_range=8.0)
    # (scan, beam) and free length: range - margin, max_range without a return; the 0.02 m
    # beam is within the margin.
    usable = [(0, 0, 1.95), (0, 1, 2.95), (0, 2, 8.0), (1, 0, 0.95), (1, 2, 3.95)]
    u = np.random.RandomState(0).uniform(size=(3, len(usable)))
    origins, directions = scans.origins(), scans.directions()
    expected = [
        origins[s] + u[j, i] * length * directions[s, b]
        for j in range(3)
        for i, (s, b, length) in enumerate(usable)
    ]
    points, labels = heldout_points(scans, n_free_per_beam=3, free_margin=0.05, random_state=0)
    assert_allclose(points[labels == 0], expected, rtol=1e-12)
    fewer, labels1 = heldout_points(scans, n_free_per_beam=1, free_margin=0.05, random_state=0)
    assert_array_equal(fewer[labels1 == 0], points[labels == 0][: len(usable)])


def test_heldout_points_deterministic_and_3d():
    scans = make_room3d_scans().scans
    a = heldout_points(scans, random_state=3)
    b = heldout_points(scans, random_state=3)
    c = heldout_points(scans, random_state=4)
    assert_array_equal(a[0], b[0])
    assert not np.array_equal(a[0], c[0])
    assert a[0].shape[1] == 3


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_free_per_beam": 0}, "n_free_per_beam"),
        ({"free_margin": -1.0}, "free_margin"),
    ],
)
def test_heldout_points_bad_input(paper, kwargs, match):
    with pytest.raises(ValueError, match=match):
        heldout_points(paper.scans, **kwargs)


def test_heldout_points_too_many_free_points(paper):
    # Drawn at once, 10**12 points per beam would be a MemoryError deep in numpy.
    with pytest.raises(ValueError, match="would draw .* free points .*smaller n_free_per_beam"):
        heldout_points(paper.scans, n_free_per_beam=10**12)


def test_heldout_auc_perfect_inverted_random(paper):
    _, test = split_scans(paper.scans, every_nth=3)
    env = paper.environment
    assert heldout_auc(_TruthClassifier(env), test, random_state=0) == 1.0
    assert heldout_auc(_TruthClassifier(env, flip=True), test, random_state=0) == 0.0
    aucs = [
        heldout_auc(_TruthClassifier(env, noise="random", seed=s), test, n_free_per_beam=5)
        for s in range(5)
    ]
    assert abs(np.mean(aucs) - 0.5) < 0.05


def test_heldout_auc_uses_class_one_column(paper):
    class Reordered(_TruthClassifier):
        classes_ = np.array([1, 0])

        def predict_proba(self, X):
            return super().predict_proba(X)[:, ::-1]

    assert heldout_auc(Reordered(paper.environment), paper.scans[:4], random_state=0) == 1.0


def test_the_larger_class_is_occupied(paper):
    # Labels {1, 2}: 2 is occupied, as every estimator of the package reads them.
    class OneTwo(_TruthClassifier):
        classes_ = np.array([1, 2])

    test = paper.scans[:4]
    assert heldout_auc(OneTwo(paper.environment), test, random_state=0) == 1.0
    scores = map_quality(OneTwo(paper.environment), paper.environment, scans=test)
    assert scores["auc"] == 1.0 and scores["walls_found"] == 1.0

    class ThreeColumns(_TruthClassifier):
        def predict_proba(self, X):
            return np.full((len(X), 3), 1 / 3)

    with pytest.raises(ValueError, match="two classes"):
        heldout_auc(ThreeColumns(paper.environment), test, random_state=0)


def test_string_labels_read_the_larger_one_as_occupied(paper):
    # As the docstrings say: "occupied" of {"free", "occupied"} is the occupied column, and
    # "miss" of {"hit", "miss"} too, which scores the truth as the worst map. Each classifier
    # gives the true occupancy as the probability of its occupied label.
    test = paper.scans[:4]
    for classes, occupied, auc in ((["free", "occupied"], 1, 1.0), (["hit", "miss"], 0, 0.0)):

        class Named(_TruthClassifier):
            classes_ = np.array(classes)

            def predict_proba(self, X, occupied=occupied):
                proba = super().predict_proba(X)
                return proba if occupied == 1 else proba[:, ::-1]

        assert heldout_auc(Named(paper.environment), test, random_state=0) == auc


def test_heldout_auc_rejects_nan_and_one_class():
    class NaNClassifier:
        def predict_proba(self, X):
            return np.full((len(X), 2), np.nan)

    class InfClassifier:
        def predict_proba(self, X):
            return np.column_stack([np.zeros(len(X)), np.full(len(X), np.inf)])

    scans = make_paper_scans().scans[:3]
    for estimator in (NaNClassifier(), InfClassifier()):
        with pytest.raises(ValueError, match="NaN or infinite value.*cannot be scored"):
            heldout_auc(estimator, scans)
    only_free = Scans([[0.0, 0.0, 0.0]], [[np.inf, np.inf]], [0.0, 1.0], max_range=8.0)
    with pytest.raises(ValueError, match="AUC is undefined"):
        heldout_auc(_TruthClassifier(None), only_free)


def test_ground_truth_auc(paper):
    env = paper.environment
    grid = env.ground_truth_grid(0.5)
    assert ground_truth_auc(grid.occupied, env, 0.5) == 1.0
    assert ground_truth_auc(1 - grid.occupied, env, 0.5) == 0.0
    rng = np.random.default_rng(0)
    assert abs(ground_truth_auc(rng.uniform(size=grid.occupied.shape), env, 0.5) - 0.5) < 0.05

    # an estimator is queried at the cell centres, as zero-length segments
    class DistanceClassifier:
        def predict_proba(self, X):
            assert_array_equal(X[:, :2], X[:, 2:])
            p = np.exp(-env.distance(X[:, :2]))
            return np.column_stack([1 - p, p])

    auc = ground_truth_auc(DistanceClassifier(), env, 0.5)
    assert auc == ground_truth_auc(np.exp(-env.distance(grid.points)), env, 0.5)
    assert auc > 0.9


def test_ground_truth_auc_observed_cells(paper):
    env = paper.environment
    grid = env.ground_truth_grid(0.5, scans=paper.scans)
    # wrong only on never-observed cells: still perfect on the observed ones
    proba = np.where(grid.observed, grid.occupied, 1 - grid.occupied)
    assert ground_truth_auc(proba, env, 0.5) < 0.9
    assert ground_truth_auc(proba, env, 0.5, scans=paper.scans) == 1.0
    # probabilities for the observed cells only are accepted too
    assert ground_truth_auc(grid.occupied[grid.observed], env, 0.5, scans=paper.scans) == 1.0


def test_ground_truth_auc_errors(paper):
    env = paper.environment
    with pytest.raises(ValueError, match="AUC is undefined"):
        ground_truth_auc(np.zeros(16), env, 0.5, extent=(8, 10, 5, 7))  # open hall only
    n = len(env.ground_truth_grid(0.5).points)
    with pytest.raises(ValueError, match=f"{n} NaN or infinite value.*cannot be scored"):
        ground_truth_auc(np.full(n, np.nan), env, 0.5)
    with pytest.raises(ValueError, match="1 NaN or infinite value.*cannot be scored"):
        ground_truth_auc(np.r_[np.zeros(n - 1), np.inf], env, 0.5)
    with pytest.raises(ValueError, match="must have shape"):
        ground_truth_auc(np.zeros(n + 1), env, 0.5)
    box = Environment2D([[0, 0, 1, 0]])
    with pytest.raises(ValueError, match="resolution"):
        ground_truth_auc(np.zeros(3), box, -1.0)


# --------------------------------------------------------------------------------------------
# The Hilbert-maps protocol: blocks of consecutive scans, floor(r / 2) free points, 40 m
# --------------------------------------------------------------------------------------------


def _indexed_scans(n_scans, n_beams=1):
    """Scans whose pose x is the scan's index, so held-out indices can be read back."""
    poses = np.column_stack([np.arange(n_scans), np.zeros(n_scans), np.zeros(n_scans)])
    angles = np.linspace(-1.0, 1.0, n_beams)
    return Scans(poses, np.full((n_scans, n_beams), 3.0), angles, max_range=10.0)


def _runs(indices):
    """Lengths of the runs of consecutive integers in sorted ``indices``."""
    breaks = np.flatnonzero(np.diff(indices) != 1) + 1
    return np.diff(np.r_[0, breaks, len(indices)])


@pytest.mark.parametrize(
    "n_scans, n_blocks", [(41, 1), (120, 1), (700, 2), (1200, 3), (13631, 34)]
)
def test_split_scan_blocks_contiguous_and_about_ten_percent(n_scans, n_blocks):
    scans = _indexed_scans(n_scans)
    for seed in range(5):
        train, test = split_scan_blocks(scans, random_state=seed)
        held = test.poses[:, 0].astype(int)
        kept = train.poses[:, 0].astype(int)
        # Every scan lands on exactly one side, in time order.
        assert_array_equal(np.sort(np.r_[held, kept]), np.arange(n_scans))
        assert np.all(np.diff(held) > 0) and np.all(np.diff(kept) > 0)
        # Blocks of 40 consecutive scans (touching blocks merge into longer runs).
        assert len(held) == 40 * n_blocks
        assert np.all(_runs(held) % 40 == 0)
    if n_scans > 1000:
        assert abs(len(held) / n_scans - 0.1) < 40 / n_scans


def test_split_scan_blocks_deterministic():
    scans = _indexed_scans(1200)
    a = split_scan_blocks(scans, random_state=7)[1].poses
    b = split_scan_blocks(scans, random_state=7)[1].poses
    c = split_scan_blocks(scans, random_state=8)[1].poses
    assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_heldout_blocks_cover_every_placement():
    # 50 scans, two blocks of 10: C(32, 2) = 496 non-overlapping placements, all reachable,
    # none overlapping, and about equally likely.
    rng = np.random.RandomState(0)
    seen = {}
    for _ in range(20000):
        held = np.flatnonzero(_heldout_blocks(50, 0.4, 10, rng))
        assert len(held) == 20 and np.all(_runs(held) % 10 == 0)
        starts = (held[0], held[10])
        seen[starts] = seen.get(starts, 0) + 1
    assert len(seen) == 496
    assert all(s2 >= s1 + 10 and s2 <= 40 for s1, s2 in seen)
    counts = np.array(list(seen.values()))
    assert stats.chisquare(counts).pvalue > 1e-3


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({}, "too few"),
        ({"block_size": 0}, "block_size"),
        ({"block_size": 2.0}, "block_size"),
        ({"heldout_fraction": 0.0}, "heldout_fraction"),
        ({"heldout_fraction": 1.0}, "heldout_fraction"),
    ],
)
def test_split_scan_blocks_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        split_scan_blocks(_indexed_scans(40), **kwargs)


def _on_some_beam(points, scans, free_margin):
    """Whether every point lies on a beam of ``scans``, within the beam's free part."""
    origins, dirs = scans.origins(), scans.directions()
    limit = np.where(scans.returned(), scans.ranges - free_margin, scans.max_range)
    for p in points:
        rel = p - origins[:, None, :]
        t = np.einsum("sbd,sbd->sb", rel, dirs)
        off = np.linalg.norm(rel - t[..., None] * dirs, axis=-1)
        if not np.any((off < 1e-9) & (t >= 0) & (t <= limit + 1e-9)):
            return False
    return True


def test_heldout_points_half_range_and_max_beam_range():
    # One scan, beams east, north, west, south, north-east, south-west:
    # r = 0.5 (one point), 5 (two), 40 (twenty: at the limit), 45 (beyond it), no return,
    # 0.05 (within the margin: none).
    angles = np.array([0.0, 0.5, 1.0, 1.5, 0.25, 1.25]) * np.pi
    ranges = [[0.5, 5.0, 40.0, 45.0, np.inf, 0.05]]
    scans = Scans([[0.0, 0.0, 0.0]], ranges, angles, max_range=80.0)
    points, labels = heldout_points(
        scans, n_free_per_beam="half_range", free_margin=0.1, max_beam_range=40.0,
        random_state=0,
    )  # fmt: skip
    assert_allclose(points[labels == 1], scans.hit_points())
    assert labels.sum() == 5  # every hit, the 45 m one included
    free = points[labels == 0]
    assert len(free) == 1 + 2 + 20
    bearing = np.round(np.arctan2(free[:, 1], free[:, 0]) / np.pi, 6)
    assert_array_equal(np.unique(bearing, return_counts=True)[1], [1, 2, 20])
    assert_array_equal(np.unique(bearing), [0.0, 0.5, 1.0])
    dist = np.linalg.norm(free, axis=1)
    for angle, r in [(0.0, 0.5), (0.5, 5.0), (1.0, 40.0)]:
        assert np.all(dist[bearing == angle] <= r - 0.1 + 1e-12)
    # Without the limit: 22 points on the 45 m beam, 40 on the no-return one (80 m).
    points, labels = heldout_points(
        scans, n_free_per_beam="half_range", free_margin=0.1, random_state=0
    )
    assert (labels == 0).sum() == 1 + 2 + 20 + 22 + 40


def test_heldout_points_half_range_on_beams_and_uniform():
    scans = make_paper_scans().scans[3:7]
    points, labels = heldout_points(
        scans, n_free_per_beam="half_range", free_margin=0.1, max_beam_range=40.0,
        random_state=0,
    )  # fmt: skip
    free = points[labels == 0]
    returned = scans.returned()
    expected = np.maximum(np.floor(scans.ranges[returned & (scans.ranges > 0.1)] / 2), 1)
    assert len(free) == expected.sum()
    assert _on_some_beam(free, scans, 0.1)
    one_beam = Scans([[0.0, 0.0, 0.0]], [[2000.0]], [0.0], max_range=3000.0)
    points, labels = heldout_points(
        one_beam, n_free_per_beam="half_range", free_margin=0.1, random_state=0
    )
    assert (labels == 0).sum() == 1000
    assert stats.kstest(points[labels == 0, 0], stats.uniform(0, 1999.9).cdf).pvalue > 1e-3
    # A sensor whose no-return beams reach 1e20 m would need 5e19 points: refused, naming
    # the way out, instead of overflowing.
    far = Scans([[0.0, 0.0, 0.0]], [[np.inf, 1.0]], [0.0, 1.0], max_range=1e20)
    with pytest.raises(ValueError, match="max_beam_range"):
        heldout_points(far, n_free_per_beam="half_range")
    points, labels = heldout_points(far, n_free_per_beam="half_range", max_beam_range=40.0)
    assert (labels == 0).sum() == 1


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_free_per_beam": "half"}, "half_range"),
        ({"n_free_per_beam": True}, "n_free_per_beam"),
        ({"max_beam_range": 0.0}, "max_beam_range"),
        ({"max_beam_range": np.inf}, "max_beam_range"),
    ],
)
def test_heldout_points_protocol_bad_input(paper, kwargs, match):
    with pytest.raises(ValueError, match=match):
        heldout_points(paper.scans, **kwargs)


def test_blocks_protocol_constants():
    assert HILBERT_HELDOUT_FRACTION == 0.1
    assert HILBERT_BLOCK_SIZE == 40
    assert HILBERT_N_FREE_PER_BEAM == "half_range"
    assert HILBERT_MAX_BEAM_RANGE == 40.0
    assert HILBERT_FREE_MARGIN == 0.1


def test_blocks_protocol_same_test_set_for_every_sparsity():
    scans = _indexed_scans(900, n_beams=3)
    runs = {k: blocks_protocol(scans, train_every=k, random_state=3) for k in (1, 10, 40)}
    for k, run in runs.items():
        assert_array_equal(run.test_index, runs[1].test_index)
        assert_array_equal(run.points, runs[1].points)
        assert_array_equal(run.train_index, runs[1].train_index[::k])
        assert_array_equal(run.train.poses[:, 0], run.train_index)
        assert_array_equal(run.test.poses[:, 0], run.test_index)
    assert len(runs[1].test_index) == 80  # round(0.1 * 900 / 40) = 2 blocks
    assert len(runs[1].train_index) == 820
    assert np.intersect1d(runs[1].train_index, runs[1].test_index).size == 0
    other = blocks_protocol(scans, random_state=4)
    assert not np.array_equal(other.test_index, runs[1].test_index)


def test_blocks_protocol_points(paper):
    run = blocks_protocol(paper.scans, block_size=6, random_state=0)
    assert len(run.test) == 6 and np.all(_runs(run.test_index) % 6 == 0)
    hits = run.test.hit_points()
    assert_allclose(run.points[: len(hits)], hits)
    assert_array_equal(
        run.labels, np.r_[np.ones(len(hits)), np.zeros(len(run.points) - len(hits))]
    )
    returned = run.test.returned()
    # The paper's 8 m sensor: no beam is over 40 m, beams without a return give nothing.
    expected = np.maximum(np.floor(run.test.ranges[returned & (run.test.ranges > 0.1)] / 2), 1)
    assert len(run.points) - len(hits) == expected.sum()
    assert _on_some_beam(run.points[len(hits) :], run.test, HILBERT_FREE_MARGIN)


@pytest.mark.parametrize(
    "kwargs, match",
    [({"train_every": 0}, "train_every"), ({"block_size": 40}, "too few")],
)
def test_blocks_protocol_bad_input(paper, kwargs, match):
    with pytest.raises(ValueError, match=match):
        blocks_protocol(paper.scans, **kwargs)


# --------------------------------------------------------------------------------------------
# Calibration and map quality against the true map
# --------------------------------------------------------------------------------------------


def test_expected_calibration_error_by_hand():
    y = [0, 0, 1, 1, 1, 0]
    p = [0.05, 0.15, 0.62, 0.68, 0.95, 0.99]
    # bins 0, 1, 6, 6, 9, 9: |0.05 - 0|, |0.15 - 0|, 2 x |0.65 - 1|, 2 x |0.97 - 0.5|
    assert_allclose(expected_calibration_error(y, p), (0.05 + 0.15 + 0.7 + 0.94) / 6)
    # one bin: |mean p - mean y|; p = 1 falls in the last bin
    assert_allclose(expected_calibration_error(y, p, n_bins=1), abs(np.mean(p) - 0.5))
    assert_allclose(expected_calibration_error([1, 0], [1.0, 0.0]), 0.0)
    assert_allclose(expected_calibration_error([0, 0], [1.0, 1.0]), 1.0)


def test_expected_calibration_error_zero_when_calibrated():
    # In every bin the frequency of 1 equals the probability.
    p = np.repeat([0.05, 0.25, 0.55, 0.85], 20)
    y = np.concatenate([np.arange(20) < k for k in (1, 5, 11, 17)]).astype(int)
    assert_allclose(expected_calibration_error(y, p), 0.0, atol=1e-12)
    assert expected_calibration_error(1 - y, p) > 0.3


def test_expected_calibration_error_matches_calibration_curve():
    rng = np.random.default_rng(0)
    p = rng.uniform(size=2000)
    y = (rng.uniform(size=2000) < p**2).astype(int)
    prob_true, prob_pred = calibration_curve(y, p, n_bins=8)
    counts = np.histogram(p, bins=np.linspace(0, 1, 9))[0]
    expected = np.sum(counts[counts > 0] * np.abs(prob_true - prob_pred)) / len(p)
    assert_allclose(expected_calibration_error(y, p, n_bins=8), expected)


def test_expected_calibration_error_against_binning_written_out():
    # Bin k holds k / n <= p < (k + 1) / n, and p = 1 the last bin; the error is the
    # sample-weighted mean over bins of |mean p - frequency of 1|. Labels drawn independently
    # of p, so that bins err in both directions (a map biased one way everywhere scores the
    # same whatever the binning); probabilities on the edges k / 8 (exact in binary), and 1.
    rng = np.random.default_rng(3)
    p = np.r_[rng.uniform(size=300), np.arange(9) / 8, np.ones(5)]
    y = rng.integers(0, 2, size=p.size)
    n_bins = 8
    total = 0.0
    for k in range(n_bins):
        upper = p < (k + 1) / n_bins if k < n_bins - 1 else p <= 1.0
        held = (p >= k / n_bins) & upper
        if held.any():
            total += held.sum() * abs(p[held].mean() - y[held].mean())
    assert_allclose(expected_calibration_error(y, p, n_bins=n_bins), total / p.size)
    # p = 1 shares the last bin: with p = 0.95 of a one it offsets a zero at p = 1.
    assert_allclose(expected_calibration_error([1, 0], [0.95, 1.0]), abs(1.95 / 2 - 0.5))


def test_expected_calibration_error_many_bins():
    # Bins finer than the probabilities' spacing hold one sample each: |p - y| per sample.
    # The bins are counted where samples fall, not allocated (10**12 of them).
    rng = np.random.default_rng(1)
    p = np.linspace(0.0005, 0.9995, 1000)
    y = (rng.uniform(size=1000) < p).astype(int)
    assert_allclose(expected_calibration_error(y, p, n_bins=10**12), np.mean(np.abs(p - y)))
    # More bins (8) than samples (5), each sample alone in its bin (0, 1, 4, 5, 7).
    p5, y5 = [0.05, 0.15, 0.62, 0.68, 0.95], [0, 0, 1, 1, 0]
    assert_allclose(
        expected_calibration_error(y5, p5, n_bins=8), (0.05 + 0.15 + 0.38 + 0.32 + 0.95) / 5
    )
    # The largest number of bins allowed, 2**52: every sample alone again.
    assert_allclose(
        expected_calibration_error(y5, p5, n_bins=2**52), np.mean(np.abs(np.subtract(p5, y5)))
    )


@pytest.mark.parametrize(
    "y, p, kwargs, match",
    [
        ([0, 1], [0.5, np.nan], {}, "NaN"),
        ([0, 1], [0.5, 1.2], {}, r"\[0, 1\]"),
        ([0, 1], [-0.1, 0.5], {}, r"\[0, 1\]"),
        ([0, 1], [0.5], {}, "same length"),
        ([0, 2], [0.5, 0.5], {}, "labels 0 and 1"),
        ([], [], {}, "empty"),
        ([0, 1], [0.5, 0.5], {"n_bins": 0}, "n_bins"),
        ([0, 1], [0.5, 0.5], {"n_bins": 2**53}, "more bins"),
    ],
)
def test_expected_calibration_error_bad_input(y, p, kwargs, match):
    with pytest.raises(ValueError, match=match):
        expected_calibration_error(y, p, **kwargs)


class _ExactMap(_TruthClassifier):
    """The simulator's true occupancy at the query points."""

    def __init__(self, environment):
        super().__init__(environment)
        self.n_queries = 0

    def predict_proba(self, X):
        self.n_queries += len(X)
        return super().predict_proba(X)


class _CellMap:
    """A per-cell map queried as a classifier: the value of the cell holding each point."""

    classes_ = np.array([0, 1])

    def __init__(self, grid, values, outside=0.0):
        self.grid, self.values, self.outside = grid, np.asarray(values, float), outside

    def predict_proba(self, X):
        d = X.shape[1] // 2
        lo = self.grid.extent[0::2]
        counts = np.array(self.grid.shape[::-1])
        cell = np.floor((X[:, :d] - lo) / self.grid.resolution).astype(int)
        inside = np.all((cell >= 0) & (cell < counts), axis=1)
        flat = np.ravel_multi_index(np.clip(cell, 0, counts - 1).T[::-1], self.grid.shape)
        p = np.where(inside, self.values[flat], self.outside)
        return np.column_stack([1 - p, p])


def _thickened(environment, grid, by):
    """A map marking occupied every cell whose centre is within ``by`` of a surface."""
    if isinstance(environment, Environment2D):
        d = environment.distance(grid.points) - environment.wall_thickness / 2
    else:
        d = environment.distance(grid.points)
    return (d <= by + 1e-9).astype(float)


def test_map_quality_true_map_2d(paper):
    env = paper.environment
    grid = env.ground_truth_grid(0.1, scans=paper.scans)
    scores = [map_quality(grid.occupied, env, scans=scans) for scans in (None, paper.scans)]
    for q in scores:
        assert (q["auc"], q["brier"], q["ece"]) == (1.0, 0.0, 0.0)
        assert (q["phantom_rate"], q["free_found"]) == (0.0, 1.0)
        assert q["walls_found"] == 1.0
        assert q["n_wall_bands"] == q["n_wall_samples"] > 100
    full, seen = scores
    # 0.1 m walls plus the cell touching each side, which the true grid marks occupied ...
    assert_allclose(full["wall_thickness"], 0.3)
    # ... of which the scans see one side: the band ends where space was never observed.
    assert_allclose(seen["wall_thickness"], 0.2)
    # The scans observe part of the world only: fewer cells and wall samples.
    assert seen["n_cells"] < full["n_cells"] == len(grid.points)
    assert seen["n_cells"] == np.count_nonzero(grid.observed)
    assert seen["n_wall_samples"] < full["n_wall_samples"]


def test_map_quality_exact_classifier_2d(paper):
    env = paper.environment
    exact = _ExactMap(env)
    q = map_quality(exact, env, scans=paper.scans)
    assert (q["phantom_rate"], q["free_found"]) == (0.0, 1.0)
    # Its cells are as occupied as the true grid's, those overlapping a wall by a sliver too.
    assert (q["auc"], q["walls_found"], q["ece"], q["brier"]) == (1.0, 1.0, 0.0, 0.0)
    assert_allclose(q["wall_thickness"], 0.1)  # the walls' own thickness, in 0.1 m steps
    assert exact.n_queries > q["n_cells"]  # cells, then the band points


def test_map_quality_thick_walls_2d(paper):
    env = paper.environment
    grid = env.ground_truth_grid(0.1)
    thin = map_quality(grid.occupied, env, scans=paper.scans)
    thick = map_quality(_thickened(env, grid, 0.5), env, scans=paper.scans)
    # 0.5 m more on each side of a 0.1 m wall ...
    everywhere = map_quality(_thickened(env, grid, 0.5), env)
    assert_allclose(everywhere["wall_thickness"], 0.1 + 1.0)
    # ... on the observed side only when scored on what the scans saw (the band point at
    # 0.45 m from the wall may fall in a cell centred beyond 0.5 m: 0.5 or 0.6).
    assert 0.5 - 1e-9 <= thick["wall_thickness"] <= 0.6 + 1e-9
    assert thick["walls_found"] == 1.0
    # free cells 0.35 to 0.5 m from a wall are now phantom obstacles
    assert 0.02 < thick["phantom_rate"] < 0.2
    assert_allclose(thick["free_found"], 1 - thick["phantom_rate"])
    assert thick["brier"] > thin["brier"] and thick["ece"] > thin["ece"]
    assert thick["auc"] < 1.0


def test_map_quality_array_shapes_and_classifier_agree(paper):
    env, scans = paper.environment, paper.scans
    grid = env.ground_truth_grid(0.1, scans=scans)
    values = _thickened(env, grid, 0.2)
    by_cell = map_quality(values, env, scans=scans)
    image = map_quality(values.reshape(grid.shape), env, scans=scans)
    observed_only = map_quality(values[grid.observed], env, scans=scans)
    queried = map_quality(_CellMap(grid, values), env, scans=scans)
    assert image == by_cell
    cell_keys = ["auc", "brier", "ece", "phantom_rate", "free_found", "walls_found", "n_cells"]
    assert {k: observed_only[k] for k in cell_keys} == {k: by_cell[k] for k in cell_keys}
    # Queried as a classifier, a cell takes the largest value over its closed square: a
    # point on its edge may lie in the next cell, so walls come out a cell thicker.
    assert queried["walls_found"] == 1.0 and queried["phantom_rate"] >= by_cell["phantom_rate"]
    # 0.2 m more on the observed side of a 0.1 m wall, however the map is given.
    for scores in (by_cell, queried, observed_only):
        assert_allclose(scores["wall_thickness"], 0.1 + 0.2)


class _Ripples:
    """A smooth map, so that the value of a point does not hinge on rounding."""

    classes_ = np.array([0, 1])

    def predict_proba(self, X):
        p = 0.5 + 0.5 * np.sin(3.1 * X[:, 0]) * np.cos(2.3 * X[:, 1])
        return np.column_stack([1 - p, p])


def test_map_quality_classifier_cells_take_their_largest_value(paper):
    env, scans = paper.environment, paper.scans
    grid = env.ground_truth_grid(0.1, scans=scans)
    h = grid.resolution / 2
    square = np.array([[dx, dy] for dx in (-h, 0, h) for dy in (-h, 0, h)])
    largest = [
        _Ripples().predict_proba(as_segments(c + square))[:, 1].max()
        for c in grid.points[grid.observed]
    ]
    by_hand = map_quality(np.array(largest), env, scans=scans)
    queried = map_quality(_Ripples(), env, scans=scans)
    for key in ["auc", "brier", "ece", "phantom_rate", "free_found", "walls_found", "n_cells"]:
        assert_allclose(queried[key], by_hand[key], rtol=1e-12, err_msg=key)


class _HollowWalls:
    """Occupied from 0.07 to 0.25 m off each wall's centre line, free on it: a wall drawn
    a step beside where it is."""

    classes_ = np.array([0, 1])

    def __init__(self, environment):
        self.environment = environment

    def predict_proba(self, X):
        d = self.environment.distance(X[:, :2])
        p = ((d > 0.07) & (d <= 0.25)).astype(float)
        return np.column_stack([1 - p, p])


def test_map_quality_band_may_start_beside_the_centre_line(paper):
    # A band goes through the wall when it holds a step within half a step of the wall's
    # surface, not only the step on its centre line: here the steps 0.1 and 0.2 m off it.
    q = map_quality(_HollowWalls(paper.environment), paper.environment)
    assert q["n_wall_bands"] > 0.9 * q["n_wall_samples"]
    assert_allclose(q["wall_thickness"], 0.2)


def test_map_quality_no_band():
    env = make_paper_scans().environment
    grid = env.ground_truth_grid(0.2)
    q = map_quality(np.full(len(grid.points), 0.1), env, resolution=0.2)
    assert np.isnan(q["wall_thickness"]) and q["n_wall_bands"] == 0 and q["n_wall_samples"] > 0
    assert (q["walls_found"], q["free_found"], q["phantom_rate"]) == (0.0, 1.0, 0.0)


def test_map_quality_thresholds_are_strict(paper):
    # As map_server reads them: occupied when p > 0.65, free when p < 0.196. A map sitting
    # on a threshold marks nothing; a step past it marks every cell.
    env = paper.environment
    n = len(env.ground_truth_grid(0.2).points)
    on, past = ROS_OCCUPIED_THRESH, np.nextafter(ROS_OCCUPIED_THRESH, 1)
    q = map_quality(np.full(n, on), env, resolution=0.2)
    marked = (q["phantom_rate"], q["free_found"], q["walls_found"], q["n_wall_bands"])
    assert marked == (0, 0, 0, 0)
    assert np.isnan(q["wall_thickness"]) and q["n_wall_samples"] > 0
    q = map_quality(np.full(n, past), env, resolution=0.2)
    assert (q["phantom_rate"], q["walls_found"], q["n_wall_bands"]) == (1, 1, q["n_wall_samples"])
    on, past = ROS_FREE_THRESH, np.nextafter(ROS_FREE_THRESH, 0)
    assert map_quality(np.full(n, on), env, resolution=0.2)["free_found"] == 0.0
    assert map_quality(np.full(n, past), env, resolution=0.2)["free_found"] == 1.0


def test_phantoms_count_only_cells_farther_than_the_clearance():
    # A 0.3 m wall along y = 0, longer than the grid: a cell centre's clearance is |y| - 0.15.
    # Rows of cells at y = -1.0, -0.9, ..., 1.0, 20 cells each: the rows at |y| = 0.5 lie
    # exactly 0.35 m from the wall (also in floating point), not farther; the ten rows at
    # |y| >= 0.6 are the phantom set. A map occupied on the rows at 0.35 m has no phantom.
    env = Environment2D([[-10.0, 0.0, 10.0, 0.0]], wall_thickness=0.3)
    extent = (-1, 1, -1.05, 1.05)
    grid = env.ground_truth_grid(0.1, extent)
    assert grid.shape == (21, 20)
    y = grid.points[:, 1]
    on_clearance = np.isclose(np.abs(y), 0.5)
    assert on_clearance.sum() == 40
    proba = np.where(on_clearance | (np.abs(y) < 0.25), 1.0, 0.0)
    q = map_quality(proba, env, extent=extent)
    assert q["n_far_free_cells"] == 10 * 20
    assert (q["phantom_rate"], q["free_found"]) == (0.0, 1.0)


def test_map_quality_thick_wall_seen_from_one_side():
    # A 0.3 m wall along y = 0.05 (surfaces on cell edges), scanned from below only. The true
    # grid marks the wall's three rows of cells and the row touching each surface occupied:
    # 0.5 m. Scored on what the scans saw, the wall's inside (never observed) keeps the map's
    # value and the unobserved row above it ends the band: 0.4 m.
    env = Environment2D([[0.0, 0.05, 4.0, 0.05]], wall_thickness=0.3)
    poses = [[x, -1.5, 0.0] for x in np.linspace(0.5, 3.5, 7)]
    scans = simulate_scans(env, poses, np.linspace(-np.pi, np.pi, 360, endpoint=False), 8.0)
    extent = (-1, 5, -2.5, 2.5)
    truth = env.ground_truth_grid(0.1, extent).occupied
    everywhere = map_quality(truth, env, extent=extent)
    seen = map_quality(truth, env, extent=extent, scans=scans)
    assert_allclose(everywhere["wall_thickness"], 0.5)
    assert_allclose(seen["wall_thickness"], 0.4)
    assert seen["n_wall_bands"] == seen["n_wall_samples"] == 40  # 4 m in 0.1 m steps
    # Given for the observed cells only, the map has no value inside the wall, which every
    # band crosses: each sample is skipped, none measured as if the inside were free.
    observed = env.ground_truth_grid(0.1, extent, scans=scans).observed
    only_seen = map_quality(truth[observed], env, extent=extent, scans=scans)
    assert only_seen["n_wall_samples"] == only_seen["n_wall_bands"] == 0
    assert np.isnan(only_seen["wall_thickness"])
    assert only_seen["walls_found"] == seen["walls_found"] == 1.0


def test_walls_found_counts_cells_touching_a_wall_along_a_side():
    # A 0.2 m wall from (0, 0.1) to (4, 0.1), surfaces at y = 0 and 0.2 on the edges of 0.2 m
    # cells: the row inside the wall (22 cells, x from -0.2 to 4.2 with the round ends) and
    # the 20 cells along each surface, whose centres are 0.1 m from it, are near the wall.
    # The 4 cells touching the round ends at a corner are occupied too, their centres
    # 0.1 * (sqrt(5) - 1) m away.
    env = Environment2D([[0.0, 0.1, 4.0, 0.1]], wall_thickness=0.2)
    extent = (-1, 5, -2, 2.6)
    grid = env.ground_truth_grid(0.2, extent)
    assert grid.occupied.sum() == 22 + 2 * 20 + 4
    inside = (np.abs(grid.points[:, 1] - 0.1) < 0.05).astype(float)
    q = map_quality(inside, env, resolution=0.2, extent=extent)
    assert q["n_near_wall_cells"] == 22 + 2 * 20
    assert_allclose(q["walls_found"], 22 / 62)
    assert map_quality(grid.occupied, env, resolution=0.2, extent=extent)["walls_found"] == 1.0


@pytest.mark.parametrize("reverse", [False, True])
def test_map_quality_skips_bands_next_to_space_nearer_another_wall(reverse):
    # Two 0.1 m walls 0.4 m apart, at y = 0.05 and 0.45 (steps on cell centres). A map
    # occupied from y = 0.25 to 0.45 gives the upper wall a band ending at y = 0.25, where
    # both walls are 0.15 m away; the step beyond it, y = 0.15, is nearer the lower wall: the
    # band cannot be told from that wall's, and the sample is skipped. The lower wall's
    # samples are counted, with no band (the map is free on it). Walls drawn either way walk
    # their normals either way.
    walls = np.array([[0.0, 0.05, 4.0, 0.05], [0.0, 0.45, 4.0, 0.45]])
    if reverse:
        walls = walls[:, [2, 3, 0, 1]]
    env = Environment2D(walls, wall_thickness=0.1)
    extent = (-1, 5, -2.5, 3.0)
    grid = env.ground_truth_grid(0.1, extent)
    x, y = grid.points.T
    band = ((y > 0.2) & (y < 0.5) & (x > 0) & (x < 4)).astype(float)
    q = map_quality(band, env, extent=extent)
    assert (q["n_wall_samples"], q["n_wall_bands"]) == (40, 0)
    assert np.isnan(q["wall_thickness"])
    # The true map: both walls measured, 0.1 m plus the cell touching each side.
    q = map_quality(grid.occupied, env, extent=extent)
    assert q["n_wall_samples"] == q["n_wall_bands"] == 80
    assert_allclose(q["wall_thickness"], 0.3)


@pytest.mark.parametrize("gap, measured", [(0.38, 0), (0.42, 80)])
def test_a_band_step_a_little_nearer_another_wall_is_nearer(gap, measured):
    # Two 0.1 m walls 4 m long, at y = 0.05 and 0.05 + gap, with the true map. Each wall's
    # check runs to the step one beyond its wall (steps of 0.1 m from its centre line): for
    # the lower wall y = 0.25, for the upper one y = gap - 0.15. At either, the own wall's
    # surface is 0.15 m away and the other's gap - 0.25: 2 cm nearer at gap = 0.38, so every
    # sample is skipped; 2 cm farther at gap = 0.42, so all 80 are measured.
    walls = np.array([[0.0, 0.05, 4.0, 0.05], [0.0, 0.05 + gap, 4.0, 0.05 + gap]])
    env = Environment2D(walls, wall_thickness=0.1)
    extent = (-1, 5, -2.5, 3.0)
    q = map_quality(env.ground_truth_grid(0.1, extent).occupied, env, extent=extent)
    assert q["n_wall_samples"] == q["n_wall_bands"] == measured


@pytest.mark.parametrize("x0", [0.0, 0.3, 0.7, 1.0, 2.0, 0.33])
def test_wall_thickness_of_a_band_on_cell_edges_does_not_hang_on_rounding(x0):
    # A 0.1 m wall at x = x0 on the edge between two 0.1 m cells (the grid starts at x0 - 1),
    # so every band step lies on a cell edge. The map is occupied in the four cells from
    # x0 - 0.2 to x0 + 0.2: a band 0.4 m wide, as many steps from the wall's centre line at
    # x0 - 0.2, x0 - 0.1, x0 and x0 + 0.1 (a step on an edge is in the cell above it). The
    # true grid marks the two cells touching the wall: 0.2 m. The step x0 + 0.2 used to read
    # the cell below or above by the rounding of (x - x_min) / 0.1, so the same map measured
    # 0.4 or 0.5 m (the true grid 0.1 or 0.2 m) as the wall moved by whole cells.
    env = Environment2D([[x0, -1.0, x0, 1.0]], wall_thickness=0.1)
    extent = (x0 - 1, x0 + 1, -1, 1)
    grid = env.ground_truth_grid(0.1, extent)
    assert grid.occupied.sum() == 2 * 20
    centre = grid.points[:, 0] - x0
    band = (np.abs(centre) < 0.2).astype(float)
    assert band.sum() == 4 * 20
    q = map_quality(band, env, extent=extent)
    assert q["n_wall_samples"] == q["n_wall_bands"] == 20
    assert_allclose(q["wall_thickness"], 0.4)
    assert_allclose(map_quality(grid.occupied, env, extent=extent)["wall_thickness"], 0.2)


def test_map_quality_samples_a_wall_shorter_than_a_step():
    # Every wall of non-zero length has at least one sample, at its middle: a 0.04 m post
    # beside a 4 m wall adds one to its 40.
    extent = (-1, 5, -2.5, 3.0)
    counts = []
    for walls in ([[0.0, 0.05, 4.0, 0.05]], [[0.0, 0.05, 4.0, 0.05], [2.0, -1.45, 2.04, -1.45]]):
        env = Environment2D(walls, wall_thickness=0.1)
        q = map_quality(env.ground_truth_grid(0.1, extent).occupied, env, extent=extent)
        assert_allclose(q["wall_thickness"], 0.3)
        counts.append((q["n_wall_samples"], q["n_wall_bands"]))
    assert counts == [(40, 40), (41, 41)]


@pytest.fixture(scope="module")
def room():
    return make_room3d_scans()


def test_map_quality_room3d(room):
    env = room.environment
    grid = env.ground_truth_grid(0.1)
    true = map_quality(grid.occupied, env)
    assert (true["auc"], true["ece"], true["phantom_rate"], true["free_found"]) == (1, 0, 0, 1)
    # the cell at each face, half a step inside the solid, and the voxel touching the face
    assert_allclose(true["wall_thickness"], 0.2)
    thick = map_quality(_thickened(env, grid, 0.5), env)
    assert_allclose(thick["wall_thickness"], 0.1 + 0.5)  # on the free side only
    assert thick["phantom_rate"] > 0.1 and thick["walls_found"] == 1.0
    exact = map_quality(_ExactMap(env), env, resolution=0.2, scans=room.scans)
    assert_allclose(exact["wall_thickness"], 0.2)
    assert (exact["phantom_rate"], exact["free_found"]) == (0.0, 1.0)
    assert (exact["auc"], exact["walls_found"], exact["ece"]) == (1.0, 1.0, 0.0)
    assert 0 < exact["n_wall_samples"] < thick["n_wall_samples"]


def test_map_quality_empty_room3d_walks_every_face_into_the_room():
    # A 2 m room without obstacles, 0.1 m steps: 6 faces of 20 x 20 samples. The walk goes
    # from half a step inside the wall into the room; samples in the ring along the room's
    # edges (within a step of the next face) are skipped: 6 x 18 x 18 counted.
    env = Room3D(size=(2, 2, 2), obstacles=np.zeros((0, 6)), wall_thickness=0.2)
    q = map_quality(env.ground_truth_grid(0.1).occupied, env)
    assert q["n_wall_samples"] == q["n_wall_bands"] == 6 * 18 * 18
    assert_allclose(q["wall_thickness"], 0.2)

    class Shell:
        """Occupied up to a step out from the faces, free inside the walls."""

        classes_ = np.array([0, 1])

        def predict_proba(self, X):
            d = env.distance(X[:, :3])
            p = ((d > 0) & (d <= 0.1)).astype(float)
            return np.column_stack([1 - p, p])

    # A band may start on either side of the face: here at the step just outside it.
    q = map_quality(Shell(), env)
    assert q["n_wall_samples"] == q["n_wall_bands"] == 6 * 18 * 18
    assert_allclose(q["wall_thickness"], 0.1)


def test_map_quality_room3d_skips_covered_faces():
    # A 0.5 m cube pushed against the wall x = 0 and the floor: its faces against them and
    # the parts of the wall and floor it covers have no free side to walk into. The same
    # cube floating in the room has all its faces, and the room all of its own.
    def samples(cube):
        env = Room3D(size=(2, 2, 2), obstacles=[cube], wall_thickness=0.2)
        q = map_quality(env.ground_truth_grid(0.1).occupied, env)
        assert_allclose(q["wall_thickness"], 0.2)
        return q["n_wall_samples"]

    floating = samples([0.7, 0.7, 0.7, 1.2, 1.2, 1.2])
    pushed = samples([0.0, 0.7, 0.0, 0.5, 1.2, 0.5])
    # 2 x 25 samples of the cube and 2 x 25 of the room are covered; the rows next to them
    # (about 60 more) walk within a step of the other solid
    assert 100 + 40 <= floating - pushed <= 100 + 80


def test_map_quality_errors(paper):
    env = paper.environment
    n = len(env.ground_truth_grid(0.5).points)
    with pytest.raises(ValueError, match="NaN"):
        map_quality(np.full(n, np.nan), env, resolution=0.5)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        map_quality(np.full(n, 2.0), env, resolution=0.5)
    with pytest.raises(ValueError, match=r"values in \[-0.5, 0\]"):
        map_quality(np.r_[-0.5, np.zeros(n - 1)], env, resolution=0.5)
    with pytest.raises(ValueError, match="must have shape"):
        map_quality(np.zeros(n + 1), env, resolution=0.5)
    with pytest.raises(ValueError, match="Environment2D or Room3D"):
        map_quality(np.zeros(n), object(), resolution=0.5)

    class NaNMap:
        def predict_proba(self, X):
            return np.full((len(X), 2), np.nan)

    with pytest.raises(ValueError, match="predict_proba at the grid-cell points: .* NaN"):
        map_quality(NaNMap(), env, resolution=0.5)
    # only free space: the AUC and the thresholded rates are undefined
    with pytest.raises(ValueError, match="AUC is undefined"):
        map_quality(np.zeros(16), env, resolution=0.5, extent=(8, 10, 5, 7))
    # a strip along a wall: no cell is far from it
    with pytest.raises(ValueError, match="farther than 0.35 m"):
        map_quality(np.zeros(40), env, resolution=0.1, extent=(4.8, 5.2, 5, 6))
    # a round post (a zero-length wall) has no normal: no wall to measure
    post = Environment2D([[5.0, 5.0, 5.0, 5.0]], wall_thickness=0.4)
    with pytest.raises(ValueError, match="no wall"):
        map_quality(np.zeros(400), post, resolution=0.2, extent=(3, 7, 3, 7))


@pytest.mark.parametrize("make", [make_paper_scans, make_room3d_scans])
def test_walls_found_counts_truly_occupied_cells_only(make):
    data = make()
    res = 0.1 if make is make_paper_scans else 0.2
    grid = data.environment.ground_truth_grid(res, scans=data.scans)
    truth = grid.occupied.astype(float)
    # The true map finds every wall, however thin.
    assert (
        map_quality(truth, data.environment, resolution=res, scans=data.scans)["walls_found"]
        == 1.0
    )
    # Marking the free cells beside the walls occupied too finds no more walls ...
    near = data.environment.distance(grid.points) <= 0.1 + 1e-9
    thick = map_quality(
        np.maximum(truth, near), data.environment, resolution=res, scans=data.scans
    )
    assert thick["walls_found"] == 1.0
    # ... and clearing the occupied cells loses them all.
    cleared = map_quality(
        np.where(near, 0.0, truth), data.environment, resolution=res, scans=data.scans
    )
    assert cleared["walls_found"] == 0.0


def test_wrong_objects_are_clear_errors():
    from skoccmap.datasets import make_paper_scans

    data = make_paper_scans()
    with pytest.raises(ValueError, match="environment must be a skoccmap.datasets"):
        ground_truth_auc(np.zeros(3), object())
    with pytest.raises(ValueError, match="fitted classifier with predict_proba, got object"):
        heldout_auc(object(), data.scans)


def test_a_classifier_fitted_on_points_is_scored_at_points(paper):
    # The scores query a classifier fitted on points (layout="points", or any scikit-learn
    # one) at points; zero-length segments were refused as "X has 4 features".
    from sklearn.metrics import roc_auc_score
    from sklearn.neighbors import KNeighborsClassifier

    train, test = split_scans(paper.scans, every_nth=4)
    points, labels = heldout_points(train, n_free_per_beam=3, random_state=0)
    on_points = KNeighborsClassifier(5).fit(points, labels)
    test_points, test_labels = heldout_points(test, random_state=0)
    expected = roc_auc_score(test_labels, on_points.predict_proba(test_points)[:, 1])
    assert heldout_auc(on_points, test, random_state=0) == pytest.approx(expected, abs=1e-15)
    grid = paper.environment.ground_truth_grid(0.4)
    expected = roc_auc_score(grid.occupied, on_points.predict_proba(grid.points)[:, 1])
    auc = ground_truth_auc(on_points, paper.environment, 0.4)
    assert auc == pytest.approx(expected, abs=1e-15)
    # On [p, p] every distance is sqrt(2) times as long: the same neighbours, the same map.
    on_segments = KNeighborsClassifier(5).fit(as_segments(points), labels)
    env, scans = paper.environment, paper.scans
    expected = map_quality(on_segments, env, resolution=0.2, scans=scans)
    assert map_quality(on_points, env, resolution=0.2, scans=scans) == expected
