import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from scipy import stats

from skoccmap.datasets import Environment2D, make_paper_scans, make_room3d_scans
from skoccmap.metrics import ground_truth_auc, heldout_auc, heldout_points, split_scans
from skoccmap.observations import Scans


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
        ({"every_nth": 1}, "every_nth"),
        ({"every_nth": 2.5}, "every_nth"),
        ({"every_nth": 3, "offset": 3}, "offset"),
        ({"every_nth": 100, "offset": 50}, "empty"),
    ],
)
def test_split_scans_bad_input(paper, kwargs, match):
    with pytest.raises(ValueError, match=match):
        split_scans(paper.scans, **kwargs)


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


def test_heldout_auc_rejects_nan_and_one_class():
    class NaNClassifier:
        def predict_proba(self, X):
            return np.full((len(X), 2), np.nan)

    scans = make_paper_scans().scans[:3]
    with pytest.raises(ValueError, match="NaN"):
        heldout_auc(NaNClassifier(), scans)
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
    with pytest.raises(ValueError, match="NaN"):
        ground_truth_auc(np.full(n, np.nan), env, 0.5)
    with pytest.raises(ValueError, match="must have shape"):
        ground_truth_auc(np.zeros(n + 1), env, 0.5)
    box = Environment2D([[0, 0, 1, 0]])
    with pytest.raises(ValueError, match="resolution"):
        ground_truth_auc(np.zeros(3), box, -1.0)
