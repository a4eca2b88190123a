"""Online mapping: ``MixtureGPOccupancyMap.partial_fit`` and ``DPGMMClusterer.partial_fit``.

Small simulated data and fixed expert hyperparameters keep every fit to about a second.
"""

import pickle
import re
import warnings

import numpy as np
import pytest
from sklearn.base import BaseEstimator, clone
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process.kernels import ConstantKernel
from sklearn.metrics import roc_auc_score

from skoccmap import (
    DPGMMClusterer,
    EPGaussianProcessClassifier,
    IntegralKernel,
    MixtureGPOccupancyMap,
)
from skoccmap.datasets import make_office_scans, make_paper_scans
from skoccmap.observations import NO_RETURN, RETURN, as_segments


def _model(**params):
    expert = EPGaussianProcessClassifier(
        ConstantKernel(100.0, "fixed") * IntegralKernel(1.0, "fixed"), optimizer=None
    )
    params.setdefault("max_expert_size", 150)
    # Every piece kept, so that the tests can rebuild an expert's rows from the beams.
    params.setdefault("max_pieces_per_cell", None)
    return MixtureGPOccupancyMap(expert=expert, random_state=0, **params)


@pytest.fixture(scope="module")
def office():
    data = make_office_scans(random_state=0)
    lo, hi = data.X[:, :2].min(axis=0), data.X[:, :2].max(axis=0)
    queries = as_segments(np.random.default_rng(0).uniform(lo, hi, size=(400, 2)))
    return data, queries


def _batch(data, first, last):
    sel = (data.scan_index >= first) & (data.scan_index < last)
    return data.X[sel], data.y[sel]


@pytest.fixture(scope="module")
def online(office):
    """Office scans 0-9 then 10-14: a model after one update, and one before it."""
    data, _ = office
    model = _model().partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    before = {"n_experts": model.n_experts_, "n_rows": model.cluster_labels_.size}
    snapshot = list(model.experts_)
    model.partial_fit(*_batch(data, 10, 15))
    return before, snapshot, model


def test_first_partial_fit_equals_fit(office):
    data, queries = office
    X, y = _batch(data, 0, 10)
    fitted = _model().fit(X, y)
    online = _model().partial_fit(X, y, classes=[0, 1])
    np.testing.assert_array_equal(online.predict_proba(queries), fitted.predict_proba(queries))
    assert online.n_experts_ == fitted.n_experts_
    # No classes needed when y holds both.
    again = _model().partial_fit(X, y)
    np.testing.assert_array_equal(again.predict_proba(queries), fitted.predict_proba(queries))


def test_update_refits_only_touched_experts(office, online):
    data, _ = office
    before, snapshot, after = online
    touched = set(after.touched_experts_.tolist())
    assert 0 < len(touched) < after.n_experts_
    kept = [e for k, e in enumerate(after.experts_) if k not in touched]
    # Untouched experts are the very objects of the model before the update ...
    assert len(kept) > 0
    assert all(any(e is old for old in snapshot) for e in kept)
    # ... and refitted ones are new objects.
    for k in touched:
        assert all(after.experts_[k] is not old for old in snapshot)
    assert after.n_experts_ >= before["n_experts"]
    assert after.cluster_labels_.size == before["n_rows"] + _batch(data, 10, 15)[0].shape[0]


def test_new_pieces_join_the_expert_of_the_hit_nearest_to_them(office, online):
    from skoccmap._beams import _beam_pieces

    data, _ = office
    _, _, after = online
    X, y = _batch(data, 10, 15)
    kinds = after.observation_kind_[-X.shape[0] :]
    pieces, source = _beam_pieces(X, kinds, after.max_beam_length, after.beam_end_length)
    free = y[source] == 0
    # Among the hits of both batches, by brute force; the hit's expert after the update.
    X_all, y_all = _batch(data, 0, 15)
    hits = X_all[y_all == 1, :2]
    mids = 0.5 * (pieces[free, :2] + pieces[free, 2:])
    dist2 = ((mids[:, None, :] - hits[None]) ** 2).sum(axis=-1)
    # Within nearest_hit_radius (2 m) of a hit: that hit's; else the row's anchor's.
    near = dist2.min(axis=1) <= 2.0**2
    assert np.mean(near) > 0.8
    row_expert = after.cluster_labels_[-X.shape[0] :][source[free]]
    expected = np.where(
        near, after.cluster_labels_[y_all == 1][np.argmin(dist2, axis=1)], row_expert
    )
    # Each expert holds its new free pieces.
    rows_of = [
        {row.tobytes() for row in getattr(expert, "X_train_", np.empty((0, 4)))}
        for expert in after.experts_
    ]
    assert all(row.tobytes() in rows_of[k] for row, k in zip(pieces[free], expected, strict=True))
    # Each new free piece remembers its own beam's hit (by which the paper's rule groups
    # the pieces that learn the shared kernel), wherever it went.
    kept = np.flatnonzero(after._piece_y == 0)[-np.count_nonzero(free) :]
    np.testing.assert_array_equal(after._pieces[kept], pieces[free])
    beam_hit = after._row_hit[-X.shape[0] :][source[free]]
    np.testing.assert_array_equal(after._piece_beam_hit[kept], beam_hit)
    assert np.any(after._piece_hit[kept] != beam_hit)


def test_experts_stay_bounded_and_rows_follow_experts(online):
    _, _, after = online
    sizes = np.array([e.X_train_.shape[0] for e in after.experts_ if hasattr(e, "X_train_")])
    assert sizes.max() <= 150
    # Each expert's cluster is its gate's: experts of a cluster are contiguous.
    assert np.all(np.diff(after.expert_cluster_) >= 0)


def test_experts_grown_past_max_expert_size_are_cut_to_it_in_rows(office):
    # max_expert_size counts the rows (beam pieces) an expert is fitted on, not its hits:
    # after every update each expert holds at most that many, or a single hit that alone
    # carries more.
    data, _ = office
    model = _model(max_expert_size=60)
    for first in range(0, 20, 5):
        model.partial_fit(*_batch(data, first, first + 5), classes=[0, 1])
        rows = np.bincount(model._piece_expert, minlength=model.n_experts_)
        hits = np.bincount(model._hit_expert, minlength=model.n_experts_)
        assert np.all((rows <= 60) | (hits == 1))


def test_online_map_close_to_batch_fit(office):
    data, queries = office
    model = _model()
    for first in range(0, 30, 6):
        model.partial_fit(*_batch(data, first, first + 6), classes=[0, 1])
    fitted = _model().fit(data.X, data.y)
    p_online = model.predict_proba(queries)[:, 1]
    p_fit = fitted.predict_proba(queries)[:, 1]
    # Same decisions on nearly all cells; the two maps differ in their cuts only.
    assert np.mean((p_online > 0.5) == (p_fit > 0.5)) > 0.95
    assert np.mean(np.abs(p_online - p_fit)) < 0.08


def test_far_batch_opens_a_new_cluster_and_expert():
    data = make_paper_scans(random_state=0)
    model = _model().fit(data.X, data.y)
    n_clusters, n_experts = model.n_clusters_, model.n_experts_
    n_dp = model.clusterer_.n_clusters_
    far = data.X + np.tile([500.0, 500.0], 2)
    model.partial_fit(far, data.y)
    assert model.clusterer_.n_clusters_ > n_dp
    assert model.n_clusters_ > n_clusters
    assert model.n_experts_ > n_experts
    # The new experts hold the far data only, and the far map is a map.
    new = model.touched_experts_
    for k in new:
        expert = model.experts_[k]
        if hasattr(expert, "X_train_"):
            assert expert.X_train_[:, 0].min() > 400.0
    # It separates the far hits from the far beams' midpoints as well as the untouched near
    # map separates the same data where they were (a hit beside dense free space may sit
    # under 1/2 in either).
    free = data.X[data.y == 0]
    points = np.vstack([data.X[data.y == 1, 2:], (free[:, :2] + free[:, 2:]) / 2])
    labels = np.r_[np.ones(np.count_nonzero(data.y == 1)), np.zeros(len(free))]
    near = roc_auc_score(labels, model.predict_proba(as_segments(points))[:, 1])
    far_auc = roc_auc_score(labels, model.predict_proba(as_segments(points + 500.0))[:, 1])
    assert far_auc > 0.99 and far_auc >= near - 0.005


class _StripClusterer(BaseEstimator):
    """Clusters by strips of x 50 m wide (no partial_fit: later hits are predicted)."""

    def fit(self, X):
        self.labels_ = self.predict(X)
        return self

    def predict(self, X):
        return np.floor(np.asarray(X)[:, 0] / 50.0).astype(int)


def _wall(x, n_hits, n_beams):
    """Hits along x = const and return beams from 3 m before it, stopping 0.05 m short."""
    y = np.linspace(-2.0, 2.0, n_hits)
    hits = np.column_stack([np.full(n_hits, x), y, np.full(n_hits, x), y])
    beams = np.column_stack(
        [np.full(n_beams, x - 3.0), y[:n_beams], np.full(n_beams, x - 0.05), y[:n_beams]]
    )
    return np.vstack([hits, beams]), np.r_[np.ones(n_hits, int), np.zeros(n_beams, int)]


def test_a_new_clusterer_cluster_gets_an_expert_from_min_expert_size_rows():
    for n_beams, opens in [(10, True), (9, False)]:
        model = _model(clusterer=_StripClusterer(), min_expert_size=20, max_expert_size=None)
        model.fit(*_wall(0.0, 30, 30))
        assert model.n_clusters_ == 1
        n_experts = model.n_experts_
        # A wall 200 m off, in a strip no hit was in: 10 hits and n_beams return beams.
        X, y = _wall(200.0, 10, n_beams)
        model.partial_fit(X, y)
        new = model.cluster_labels_[-len(y) :]
        if opens:
            # Its 20 rows reach min_expert_size: a cluster and an expert of their own.
            assert model.n_clusters_ == 2 and model.n_experts_ == n_experts + 1
            assert np.all(new == n_experts) and model.expert_cluster_[n_experts] == 1
        else:
            # 19 rows: they join the nearest cluster, the only one.
            assert model.n_clusters_ == 1 and model.n_experts_ == n_experts
            assert np.all(model.expert_cluster_[new] == 0)


def test_two_new_clusterer_clusters_in_one_batch_are_two_clusters():
    model = _model(clusterer=_StripClusterer(), min_expert_size=20).fit(*_wall(0.0, 30, 30))
    (Xa, ya), (Xb, yb) = _wall(200.0, 10, 10), _wall(300.0, 10, 10)
    model.partial_fit(np.vstack([Xa, Xb]), np.r_[ya, yb])
    assert model.n_clusters_ == 3
    clusters = model.expert_cluster_[model.cluster_labels_]
    a, b = clusters[-40:-20], clusters[-20:]
    assert np.unique(a).size == 1 and np.unique(b).size == 1
    assert {a[0], b[0]} == {1, 2}
    # Each cluster's experts are numbered together, from its first expert on.
    np.testing.assert_array_equal(
        model._first_expert, np.searchsorted(model.expert_cluster_, np.arange(3))
    )


class _StaleLabelsStripClusterer(_StripClusterer):
    """A ``partial_fit`` that learns nothing and leaves ``labels_`` those of the fit."""

    def partial_fit(self, X):
        return self


def test_labels_left_from_the_fit_by_a_clusterers_partial_fit_are_not_read():
    # labels_ of another length than the batch's hits are not the batch's labels: the
    # hits are predicted, and each joins the cluster of its strip.
    model = _model(clusterer=_StaleLabelsStripClusterer(), min_expert_size=20)
    (Xa, ya), (Xb, yb) = _wall(10.0, 30, 30), _wall(110.0, 30, 30)
    model.fit(np.vstack([Xa, Xb]), np.r_[ya, yb])
    at = [model.expert_cluster_[model._hit_expert[i]] for i in (0, -1)]
    assert at[0] != at[1]
    X, y = _wall(112.0, 10, 10)
    model.partial_fit(X, y)
    assert model.n_clusters_ == 2
    np.testing.assert_array_equal(model.expert_cluster_[model._hit_expert[-10:]], at[1])


def test_a_label_first_seen_below_the_known_ones_keeps_its_cluster():
    # Strip 0 (x in [0, 50)) first appears after strips 2 and 4: its cluster is new, and a
    # later batch in strip 0 joins that cluster (a label the clusterer gave before keeps
    # its cluster), as it does the expert of its hits.
    model = _model(clusterer=_StripClusterer(), min_expert_size=20, max_expert_size=None)
    (Xa, ya), (Xb, yb) = _wall(100.0, 30, 30), _wall(200.0, 30, 30)
    model.fit(np.vstack([Xa, Xb]), np.r_[ya, yb])
    assert model.n_clusters_ == 2
    model.partial_fit(*_wall(10.0, 10, 10))
    assert model.n_clusters_ == 3
    expert = model.cluster_labels_[-1]
    X, y = _wall(10.0, 10, 10)
    model.partial_fit(X + [0.0, 0.1, 0.0, 0.1], y)
    assert model.n_clusters_ == 3 and model.n_experts_ == 3
    np.testing.assert_array_equal(model.cluster_labels_[-20:], expert)


def test_a_small_new_cluster_joins_the_cluster_of_the_nearest_hit_centroid():
    # Walls of 30 hits each at x = 0 (strip 0) and x = 100 (strip 2); 5 hits at x = 60
    # (strip 1, fewer than min_expert_size rows) join the cluster whose hits' mean is
    # nearer: the wall at 100 m, 40 m off against 60 m.
    model = _model(clusterer=_StripClusterer(), min_expert_size=20, max_expert_size=None)
    (Xa, ya), (Xb, yb) = _wall(0.0, 30, 30), _wall(100.0, 30, 30)
    model.fit(np.vstack([Xa, Xb]), np.r_[ya, yb])
    assert model.n_clusters_ == 2
    at_100 = model.expert_cluster_[model._hit_expert[-1]]
    model.partial_fit(*_wall(60.0, 5, 5))
    assert model.n_clusters_ == 2
    np.testing.assert_array_equal(model.expert_cluster_[model._hit_expert[-5:]], at_100)


def test_a_later_beam_ending_short_of_an_old_hit_is_its_return_beam(office):
    # One beam a batch, stopping 0.05 m short of an old hit (return_radius is 0.1 m), from
    # each of the four directions: the hit may lie on either side of the beam's end.
    data, _ = office
    model = _model().partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    hit = model._hits[np.argmax(model._hits[:, 0])]
    for direction in np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]):
        end = hit + 0.05 * direction
        beam = np.r_[end + 2.0 * direction, end][None, :]
        dist = np.linalg.norm(model._hits - end, axis=1).min()
        model.partial_fit(beam, [0])
        assert model.observation_kind_[-1] == RETURN
        # Its hit is the one nearest to its end (by brute force), within the radius.
        assert np.linalg.norm(model._hits[model._row_hit[-1]] - end) == pytest.approx(dist)
        assert dist <= 0.05 + 1e-12


def test_a_later_batch_without_return_beams_follows_the_hit_nearest_to_each_midpoint(office):
    data, _ = office
    model = _model().partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    hits = model._hits
    # Beams from the map's centre, 6 m long, that end far (> 0.1 m) from every hit.
    centre = 0.5 * (hits.min(axis=0) + hits.max(axis=0))
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    ends = centre + 6.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    far = np.linalg.norm(ends[:, None] - hits[None], axis=-1).min(axis=1) > 0.1
    X = np.hstack([np.tile(centre, (far.sum(), 1)), ends[far]])
    n = X.shape[0]
    assert n > 5
    model.partial_fit(X, np.zeros(n, dtype=int))
    assert np.all(model.observation_kind_[-n:] == NO_RETURN)
    mids = 0.5 * (X[:, :2] + X[:, 2:])
    dist = np.linalg.norm(mids[:, None] - hits[None], axis=-1)
    chosen = dist[np.arange(n), model._row_hit[-n:]]
    np.testing.assert_allclose(chosen, dist.min(axis=1), rtol=1e-12)


def test_one_class_batch(office):
    data, queries = office
    model = _model().partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    X, y = _batch(data, 10, 13)
    free = y == 0
    before = model.predict_proba(queries)
    model.partial_fit(X[free], y[free])
    assert model.touched_experts_.size > 0
    after = model.predict_proba(queries)
    assert np.all(np.isfinite(after))
    # Free space lowers the probability of occupancy, on the whole, where it changes it.
    changed = np.abs(after - before)[:, 1] > 1e-6
    assert changed.any()
    assert np.mean(after[changed, 1] - before[changed, 1]) < 0.0


def test_an_empty_batch_changes_nothing(office):
    # A batch of scans whose readings all failed (0, no measurement) has no rows.
    data, queries = office
    model = _model().partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    before = model.predict_proba(queries)
    n_rows, n_experts = model.cluster_labels_.size, model.n_experts_
    model.partial_fit(np.empty((0, 4)), np.empty(0))
    assert model.touched_experts_.size == 0
    assert model.cluster_labels_.size == n_rows and model.n_experts_ == n_experts
    np.testing.assert_array_equal(model.predict_proba(queries), before)
    with pytest.raises(ValueError, match="features"):
        model.partial_fit(np.empty((0, 3)), np.empty(0))  # the columns are still checked
    with pytest.raises(ValueError, match="0 sample"):
        _model().partial_fit(np.empty((0, 4)), np.empty(0), classes=[0, 1])  # a first call


@pytest.mark.parametrize(
    "make_bad",
    [
        lambda X, y: (np.where(np.arange(X.size).reshape(X.shape) == 5, np.nan, X), y),
        lambda X, y: (X[:, :3], y),
        lambda X, y: (X, np.where(y == 1, 7, y)),
        lambda X, y: (X, np.where(np.arange(y.size) % 3 == 0, 2, y)),
        # A failed range read as 1e8 m, refused by the transient hits' cell counts.
        lambda X, y: (np.r_[X, [[0.0, 0.0, 1e8, 0.0]]], np.r_[y, 0]),
    ],
    ids=["nan", "columns", "unknown-label", "three-classes", "failed-range"],
)
def test_bad_batch_is_refused_without_change(office, make_bad):
    data, queries = office
    model = _model().partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    before = model.predict_proba(queries)
    state = pickle.dumps(model)
    n_rows, n_experts = model.cluster_labels_.size, model.n_experts_
    X, y = make_bad(*_batch(data, 10, 12))
    with pytest.raises(ValueError):
        model.partial_fit(X, y)
    assert model.cluster_labels_.size == n_rows and model.n_experts_ == n_experts
    np.testing.assert_array_equal(model.predict_proba(queries), before)
    # Nothing else moved either: the clusterer, the random state, the cell counts.
    assert pickle.dumps(model) == state
    # Still usable: a good batch goes in.
    model.partial_fit(*_batch(data, 10, 12))
    assert model.cluster_labels_.size > n_rows


def test_a_later_batch_is_checked_as_the_first(office):
    # Reversed labels (beams as hits, hits as free points) and millimetres: fit refuses the
    # one and warns of the other, and so must every later batch.
    data, queries = office
    model = _model().partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    before = model.predict_proba(queries)
    n_rows = model.cluster_labels_.size
    X, y = _batch(data, 10, 12)
    with pytest.raises(ValueError, match="labels look reversed"):
        model.partial_fit(X, 1 - y)
    with warnings.catch_warnings():
        # As an error, the warning stops the update before it is made.
        warnings.simplefilter("error", UserWarning)
        with pytest.raises(UserWarning, match="millimetres"):
            model.partial_fit(1000.0 * X, y)
    assert model.cluster_labels_.size == n_rows
    np.testing.assert_array_equal(model.predict_proba(queries), before)


def test_n_jobs_gives_the_same_map(office):
    data, queries = office
    maps = []
    for n_jobs in (1, 2):
        model = _model(n_jobs=n_jobs)
        for first in range(0, 15, 5):
            model.partial_fit(*_batch(data, first, first + 5), classes=[0, 1])
        maps.append(model.predict_proba(queries))
    np.testing.assert_array_equal(maps[0], maps[1])


def test_classes_rules(office):
    data, _ = office
    X, y = _batch(data, 0, 5)
    # One class in the first batch: the same advice with or without classes.
    for classes in (None, [0, 1]):
        with pytest.raises(ValueError, match=r"needs both classes in y.*holds \[0\] only"):
            _model().partial_fit(X[y == 0], y[y == 0], classes=classes)
    with pytest.raises(ValueError, match="2 classes"):
        _model().partial_fit(X, y, classes=[0, 1, 2])
    with pytest.raises(ValueError, match="not in classes"):
        _model().partial_fit(X, y, classes=[0, 5])
    model = _model().partial_fit(X, y, classes=[0, 1])
    # A later batch of points where the model takes segment rows: the as_segments hint.
    with pytest.raises(ValueError, match="as_segments"):
        model.partial_fit(X[:, :2], y)
    with pytest.raises(ValueError, match="differs"):
        model.partial_fit(*_batch(data, 5, 7), classes=[0, 2])
    model.partial_fit(*_batch(data, 5, 7), classes=[1, 0])
    np.testing.assert_array_equal(model.classes_, [0, 1])
    assert model.n_features_in_ == 4


def test_refit_hyperparameters():
    data = make_paper_scans(random_state=0)
    model = MixtureGPOccupancyMap(max_expert_size=300, random_state=0).fit(data.X, data.y)
    kernel = model.shared_kernel_
    model.partial_fit(data.X[::2] + 0.01, data.y[::2])
    assert model.shared_kernel_ is kernel
    reach = model.reach_
    model.refit_hyperparameters()
    assert model.touched_experts_.size == model.n_experts_
    assert model.shared_kernel_ is not kernel
    # The reach is found again, for the new kernel.
    assert model.reach_ != reach
    assert model.reach_ == model._reach(model._pieces, model._kernels())
    with pytest.raises(ValueError, match="share_hyperparameters"):
        _model(share_hyperparameters=False).fit(data.X, data.y).refit_hyperparameters()


def test_training_kernel_from_a_previous_matrix():
    from skoccmap._experts import _training_kernel
    from skoccmap.classifier import _from_lower_triangle, _lower_triangle

    data = make_office_scans(random_state=0)
    kernel = ConstantKernel(100.0) * IntegralKernel(0.8)
    rows = data.X[np.random.default_rng(0).permutation(data.X.shape[0])[:120]]
    full = kernel(rows)
    np.testing.assert_array_equal(
        _from_lower_triangle(_lower_triangle(full), symmetric=True), full
    )
    # An earlier fit on 80 of the rows, in another order, and 10 rows it had that are gone.
    rng = np.random.default_rng(1)
    earlier = rng.permutation(np.r_[np.arange(80), np.arange(120, 130)])
    other = np.vstack([rows, data.X[-10:]])
    lower = _lower_triangle(kernel(other[earlier]))
    inverse = np.full(130, -1)
    inverse[earlier] = np.arange(earlier.size)
    K = _training_kernel(kernel, rows, (lower, inverse[:120]))
    np.testing.assert_array_equal(K, K.T)
    np.testing.assert_allclose(K, full, rtol=1e-10, atol=1e-10 * full.max())
    np.testing.assert_array_equal(_training_kernel(kernel, rows), full)


def test_kernel_cache_gives_the_same_map(office):
    data, queries = office
    maps, models = [], []
    for cache in (256, 0):
        model = _model(kernel_cache_size=cache)
        for first in range(0, 30, 5):
            model.partial_fit(*_batch(data, first, first + 5), classes=[0, 1])
        maps.append(model.latent_mean_and_variance(queries))
        models.append(model)
    cached, fresh = models
    # Every fitted GP expert's matrix is kept (the budget holds them all), none without.
    n_gp = sum(hasattr(est, "site_nu_") for est in cached.experts_)
    assert len(cached._kernel_cache) == n_gp > 0
    assert set(map(id, cached._kernel_cache)) <= set(map(id, cached.experts_))
    assert not fresh._kernel_cache
    for a, b in zip(maps[0], maps[1], strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-8)
    for a, b in zip(cached.experts_, fresh.experts_, strict=True):
        if hasattr(a, "site_nu_"):
            np.testing.assert_allclose(a.site_nu_, b.site_nu_, rtol=1e-6, atol=1e-8)


def test_kernel_cache_budget_and_pickle(office):
    import pickle

    data, _ = office
    # About two 150-row experts' triangles.
    model = _model(kernel_cache_size=0.2)
    for first in range(0, 20, 5):
        model.partial_fit(*_batch(data, first, first + 5), classes=[0, 1])
    cache = model._kernel_cache
    assert 0 < len(cache) < model.n_experts_
    assert sum(lower.nbytes for lower in cache.values()) <= 0.2 * 2**20
    # The most recently refitted experts are the ones kept.
    touched = {id(model.experts_[k]) for k in model.touched_experts_}
    assert set(map(id, cache)) <= touched
    copy = pickle.loads(pickle.dumps(model))
    assert not hasattr(copy, "_kernel_cache")
    copy.partial_fit(*_batch(data, 20, 25))
    model.partial_fit(*_batch(data, 20, 25))
    assert copy.n_experts_ == model.n_experts_


def test_refit_hyperparameters_empties_the_kernel_cache():
    data = make_paper_scans(random_state=0)
    model = MixtureGPOccupancyMap(max_expert_size=300, random_state=0).fit(data.X, data.y)
    before = dict(model._kernel_cache)
    assert before
    model.refit_hyperparameters()
    assert not set(map(id, model._kernel_cache)) & set(map(id, before))


def test_a_relearn_on_no_two_class_group_leaves_no_shared_kernel(office):
    # Nothing to learn from: each expert keeps its own kernel, and the previous shared
    # kernel must not stay behind as every expert's prior.
    data, _ = office
    model = _model(piece_assignment="beam").partial_fit(*_batch(data, 0, 5), classes=[0, 1])
    assert model.shared_kernel_ is not None
    expert = model._make_expert()
    assert model._learn_shared([], expert, model._rng) is expert
    assert model.shared_kernel_ is None


@pytest.mark.parametrize("growth, relearns", [(2.0, True), (2.5, False), (None, False)])
def test_hyperparameters_relearned_when_the_rows_grow(growth, relearns):
    data = make_paper_scans(random_state=0)
    # Every piece kept: the cap would drop most of the shifted copy below.
    model = MixtureGPOccupancyMap(
        max_expert_size=300,
        hyperparameter_growth=growth,
        max_pieces_per_cell=None,
        random_state=0,
    ).fit(data.X, data.y)
    kernel, n_rows = model.shared_kernel_, model._pieces.shape[0]
    # The same scans again, shifted: about twice the rows (a few beams end near a hit of
    # the other copy and are cut as return beams).
    model.partial_fit(data.X + 0.01, data.y)
    assert 2 * n_rows <= model._pieces.shape[0] < 2.5 * n_rows
    assert (model.shared_kernel_ is not kernel) == relearns
    assert model._learned_rows == (model._pieces.shape[0] if relearns else n_rows)
    if relearns:
        # Every expert has the new kernel, and the cache none of the old matrices.
        assert {repr(e.kernel_) for e in model.experts_ if hasattr(e, "site_nu_")} == {
            repr(model.shared_kernel_)
        }
        assert set(map(id, model._kernel_cache)) <= set(map(id, model.experts_))


@pytest.mark.parametrize("optimizer", [None, "fmin_l_bfgs_b"])
def test_fixed_kernel_is_not_relearned(office, optimizer):
    # A kernel whose hyperparameters are all fixed learns nothing, with an optimiser or not.
    data, _ = office
    model = _model()
    model.expert.set_params(optimizer=optimizer)
    model.partial_fit(*_batch(data, 0, 5), classes=[0, 1])
    n_rows, kernel = model._pieces.shape[0], model.shared_kernel_
    model.partial_fit(*_batch(data, 5, 15))
    assert model._pieces.shape[0] >= 2 * n_rows
    assert model._learned_rows == n_rows and model.shared_kernel_ is kernel


def test_a_kernel_with_free_hyperparameters_and_no_optimiser_is_not_relearned(office):
    # Without an optimiser nothing is learned, however many hyperparameters are free: the
    # growth of the rows re-learns nothing and refits only the touched experts.
    data, _ = office
    expert = EPGaussianProcessClassifier(
        ConstantKernel(100.0) * IntegralKernel(1.0), optimizer=None
    )
    model = MixtureGPOccupancyMap(
        expert=expert, max_expert_size=150, max_pieces_per_cell=None, random_state=0
    )
    model.partial_fit(*_batch(data, 0, 5), classes=[0, 1])
    n_rows, kernel = model._pieces.shape[0], model.shared_kernel_
    model.partial_fit(*_batch(data, 5, 15))
    assert model._pieces.shape[0] >= 2 * n_rows
    assert model._learned_rows == n_rows and model.shared_kernel_ is kernel
    assert model.touched_experts_.size < model.n_experts_


@pytest.mark.parametrize("growth", [2.0, 1.5])
def test_hyperparameters_are_relearned_once_the_rows_grow_by_exactly_the_factor(growth):
    model = MixtureGPOccupancyMap(hyperparameter_growth=growth)
    model._learned_rows = 100
    assert model._relearns_at(int(growth * 100))
    assert not model._relearns_at(int(growth * 100) - 1)
    model.set_params(share_hyperparameters=False)
    assert not model._relearns_at(int(growth * 100))


def _settled_and_absorbed(model):
    """Per expert, rows settled by a fit on all its rows and rows added since; every
    expert's training data must be all of its pieces."""
    counts = []
    for k, est in enumerate(model.experts_):
        mine = model._piece_expert == k
        if hasattr(est, "X_train_"):
            np.testing.assert_array_equal(est.X_train_, model._pieces[mine])
        settled = int(np.count_nonzero(mine & model._piece_settled))
        counts.append((settled, int(mine.sum()) - settled))
    return np.array(counts)


@pytest.mark.parametrize("fraction", [0.0, 0.3])
def test_refit_fraction_refits_after_a_share_of_added_rows(office, fraction):
    data, _ = office
    model = _model(refit_fraction=fraction)
    absorbed_seen = 0
    for first in range(0, 30, 3):
        before = list(model.experts_) if first else []
        model.partial_fit(*_batch(data, first, first + 3), classes=[0, 1])
        counts = _settled_and_absorbed(model)
        added = counts[:, 1] > 0
        # An expert whose added rows are not settled keeps them under refit_fraction of
        # its settled rows; every touched expert is a new fit.
        assert np.all(counts[added, 1] < fraction * counts[added, 0])
        assert not any(model.experts_[k] is old for k in model.touched_experts_ for old in before)
        absorbed_seen += added.sum()
    assert (absorbed_seen > 0) == (fraction > 0)
    model.refit_hyperparameters()
    assert not _settled_and_absorbed(model)[:, 1].any()


def test_experts_due_for_a_refit_run_ep_on_all_their_sites(office):
    # With refit_fraction=0 every touched expert is refitted: EP on all its sites, from the
    # sites it had, reaches the fixed point a fit from scratch on the same rows reaches.
    data, queries = office
    model = _model(refit_fraction=0.0)
    model.partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    model.partial_fit(*_batch(data, 10, 12))
    checked = 0
    for k in model.touched_experts_:
        est = model.experts_[k]
        if not hasattr(est, "site_nu_") or np.ptp(est.y_train_) == 0:
            continue
        fresh = clone(est).fit(est.X_train_, est.y_train_)
        for got, want in zip(
            est.latent_mean_and_variance(queries),
            fresh.latent_mean_and_variance(queries),
            strict=True,
        ):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
        checked += 1
    assert checked > 0


def test_an_expert_a_split_leaves_unchanged_is_not_touched(office):
    # Small experts, five scans a batch: some updates split an expert so that all its new
    # rows go to the part split off. The expert keeps exactly its old rows and fit, and
    # touched_experts_ ("fitted, refitted or given new rows") must not name it.
    data, _ = office
    model = _model(refit_fraction=0.3, max_expert_size=60)
    for first in range(0, 30, 5):
        before = {id(e) for e in model.experts_} if first else set()
        model.partial_fit(*_batch(data, first, first + 5), classes=[0, 1])
        touched = set(model.touched_experts_.tolist())
        assert not any(id(model.experts_[k]) in before for k in touched)
        # ... and every expert not named is the one it was.
        if first:
            others = set(range(model.n_experts_)) - touched
            assert all(id(model.experts_[k]) in before for k in others)


def test_experts_below_refit_fraction_hold_the_sites_of_the_expert_they_come_from(office):
    # An expert whose rows came from one old two-class EP expert (the same expert with rows
    # appended, or a part split off it) and whose rows not settled stay below
    # refit_fraction of those settled is not refitted: the sites of its old rows are the
    # old expert's, bit for bit. Small experts make splits common.
    data, _ = office
    fraction = 0.3
    model = _model(refit_fraction=fraction, max_expert_size=60)
    model.partial_fit(*_batch(data, 0, 5), classes=[0, 1])
    split_off_held = 0
    for first in range(5, 25, 5):
        old_experts, old_expert = list(model.experts_), model._piece_expert.copy()
        old_settled, n_old = model._piece_settled.copy(), model._pieces.shape[0]
        model.partial_fit(*_batch(data, first, first + 5))
        for k in model.touched_experts_:
            rows = np.flatnonzero(model._piece_expert == k)
            old = rows[rows < n_old]
            sources = np.unique(old_expert[old])
            if sources.size != 1:
                continue
            j = sources[0]
            source = old_experts[j]
            if not hasattr(source, "site_nu_") or np.ptp(source.y_train_) == 0:
                continue
            n_settled = np.count_nonzero(old_settled[old])
            if rows.size - n_settled >= fraction * max(n_settled, 1):
                continue
            est = model.experts_[k]
            at = np.searchsorted(rows, old)
            was = np.searchsorted(np.flatnonzero(old_expert == j), old)
            np.testing.assert_array_equal(est.site_precision_[at], source.site_precision_[was])
            np.testing.assert_array_equal(est.site_nu_[at], source.site_nu_[was])
            split_off_held += old.size < np.count_nonzero(old_expert == j)
    assert split_off_held > 0


def test_updates_warn_nothing_but_convergence(office):
    # Rows appended in this process and refits in workers alike: no stray warning
    # (such as joblib's about a delayed call run outside Parallel) reaches the user.
    data, _ = office
    model = _model(n_jobs=2)
    absorbed = 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for first in range(0, 18, 3):
            model.partial_fit(*_batch(data, first, first + 3), classes=[0, 1])
            absorbed += _settled_and_absorbed(model)[:, 1].sum()
    assert absorbed > 0
    assert [str(w.message) for w in caught if w.category is not ConvergenceWarning] == []


@pytest.mark.parametrize("label", [0, 1])
def test_added_rows_change_the_map_at_once(office, label):
    data, _ = office
    model = _model(refit_fraction=10.0)
    model.partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    k = np.bincount(model._hit_expert).argmax()
    hits = model._hits[model._hit_expert == k][:8]
    # A few short rows at its hits: free space where the expert draws a wall (label 0),
    # or more hits there (label 1). Far fewer rows than refit_fraction asks for.
    if label == 0:
        X = np.hstack([hits + [0.02, 0.0], hits + [0.01, 0.0]])
    else:
        X = as_segments(hits + [0.001, 0.0])
    p_before = model.experts_[k].predict_proba(X)[:, 1]
    n_settled = np.count_nonzero(model._piece_settled)
    model.partial_fit(X, np.full(len(X), label))
    assert model.touched_experts_.tolist() == [k]
    # Not refitted: the rows are added with the other sites held fixed, unsettled.
    assert np.count_nonzero(model._piece_settled) == n_settled
    p_after = model.experts_[k].predict_proba(X)[:, 1]
    assert np.all(p_after < p_before) if label == 0 else np.all(p_after > p_before)
    _settled_and_absorbed(model)


def test_one_class_expert_is_recounted_at_once():
    from skoccmap._experts import _ConstantExpert

    # A one-class expert is a count: it is refitted (recounted), never added to.
    model = _model(refit_fraction=10.0)
    count = _ConstantExpert(None, 0, 5)
    due = model._due(
        np.array([0]), [np.arange(6)], [count], [np.arange(5)], np.array([0]), np.ones(6, bool)
    )
    np.testing.assert_array_equal(due, [True])


def test_a_one_class_expert_given_more_of_its_class_is_the_one_class_posterior_of_all():
    from sklearn.cluster import KMeans

    # Left: a wall seen by beams; right: hits that no beam reaches, whose EP expert is the
    # GP posterior of one class. More hits there make it that posterior on all of them, as
    # a fit from scratch gives (its saturated sites are no warm start for a fit).
    rng = np.random.default_rng(1)
    wall = np.column_stack([np.zeros(30), np.linspace(-2, 2, 30)])
    beams = np.column_stack([np.full(30, 3.0), wall[:, 1], wall + [0.05, 0.0]])
    far = rng.normal([20.0, 0.0], 0.3, size=(15, 2))
    X = np.vstack([as_segments(wall), beams, as_segments(far[:12])])
    y = np.r_[np.ones(30), np.zeros(30), np.ones(12)].astype(int)
    model = _model(clusterer=KMeans(2, n_init=3, random_state=0), min_expert_size=1)
    model.partial_fit(X, y, classes=[0, 1])
    model.partial_fit(as_segments(far[12:]), np.ones(3, dtype=int))
    (k,) = model.touched_experts_
    est = model.experts_[k]
    np.testing.assert_array_equal(np.sort(est.X_train_[:, 0]), np.sort(far[:, 0]))
    fresh = clone(model.expert)._fit_one_class(
        est.X_train_, est.y_train_, classes=np.array([0, 1])
    )
    q = as_segments(rng.normal([20.0, 0.0], 1.0, size=(50, 2)))
    np.testing.assert_allclose(est.predict_proba(q), fresh.predict_proba(q), rtol=1e-6)


def test_an_expert_is_refitted_once_its_added_rows_reach_refit_fraction():
    # An expert settled on 10 rows takes 4 more by EP on their sites alone; 5 rows, half of
    # 10, reach refit_fraction=0.5: it is refitted.
    data = make_office_scans(random_state=0)
    rows = np.random.default_rng(0).choice(data.X.shape[0], 10, replace=False)
    old = _model().expert.fit(data.X[rows], data.y[rows])
    assert old.n_classes_ == 2
    model = _model(refit_fraction=0.5)
    for n_new, due in [(4, False), (5, True)]:
        settled = np.r_[np.ones(10, bool), np.zeros(n_new, bool)]
        got = model._due(
            np.array([0]), [np.arange(10 + n_new)], [old], [np.arange(10)], np.array([0]), settled
        )
        np.testing.assert_array_equal(got, [due])


def test_rows_added_by_a_refit_hold_exactly_the_old_sites(monkeypatch):
    # Where EP on the new sites alone fails, the expert is refitted on all rows with the old
    # rows' sites held: they stay as they were, and every new row gets a site of its own.
    from skoccmap._experts import _append_rows

    data = make_office_scans(random_state=0)
    rows = np.random.default_rng(0).choice(data.X.shape[0], 80, replace=False)
    X, y = data.X[rows], data.y[rows]
    assert 0 < y[:60].mean() < 1 and y[60:].any()
    old = _model().expert.fit(X[:60], y[:60])
    zeros = np.zeros(20)
    sites = (np.r_[old.site_precision_, zeros], np.r_[old.site_nu_, zeros])
    monkeypatch.setattr(EPGaussianProcessClassifier, "_absorbed", lambda *args, **kw: None)
    est, _, _ = _append_rows(old, clone(old), X, y, 60, sites)
    np.testing.assert_array_equal(est.X_train_, X)
    np.testing.assert_array_equal(est.site_precision_[:60], old.site_precision_)
    np.testing.assert_array_equal(est.site_nu_[:60], old.site_nu_)
    assert np.all(est.site_precision_[60:] > 0)


def test_updated_index_equals_a_rebuilt_one(office):
    from skoccmap._reach import ExpertReach

    data, queries = office
    model = _model()
    for first in range(0, 20, 5):
        model.partial_fit(*_batch(data, first, first + 5), classes=[0, 1])
        index = model._reach_index
        rebuilt = ExpertReach(
            model._pieces, model._piece_expert, model.n_experts_, model.reach_, index.origin
        )
        for got, want in zip(index.candidates(queries), rebuilt.candidates(queries), strict=True):
            np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(index._table_experts, rebuilt._table_experts)
        np.testing.assert_array_equal(index.centre_expert, rebuilt.centre_expert)


# -- DPGMMClusterer.partial_fit ----------------------------------------------------------


def _rooms(seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal([0, 0], 0.3, (150, 2)), rng.normal([10, 0], 0.3, (80, 2))


def test_clusterer_partial_fit_opens_a_table_for_a_new_room():
    a, b = _rooms()
    model = DPGMMClusterer(random_state=0).partial_fit(a)
    assert model.n_clusters_ == 1
    model.partial_fit(b)
    assert model.n_clusters_ == 2
    np.testing.assert_array_equal(model.labels_, np.ones(len(b), dtype=int))
    np.testing.assert_allclose(model.weights_, [150 / 230, 80 / 230])
    # The posterior mean of the new cluster's mean: its points and the prior's mean.
    kappa = model.mean_precision_prior_
    expected = (b.sum(axis=0) + kappa * model.mean_prior_) / (len(b) + kappa)
    np.testing.assert_allclose(model.means_[1], expected)
    # Points of a known room join its cluster, no new one.
    more = np.random.default_rng(1).normal([0, 0], 0.3, (40, 2))
    model.partial_fit(more)
    assert model.n_clusters_ == 2 and np.all(model.labels_ == 0)


def test_clusterer_partial_fit_is_reproducible():
    a, b = _rooms()
    runs = [DPGMMClusterer(random_state=3).fit(a).partial_fit(b).labels_ for _ in range(2)]
    np.testing.assert_array_equal(*runs)
    with pytest.raises(ValueError):
        DPGMMClusterer(random_state=0).fit(a).partial_fit(b[:, :1])


def test_clusterer_partial_fit_refuses_points_too_far_for_its_statistics():
    # Points 1e8 from the first fit's along the diagonal, whose spread is 0.3: the sums of
    # squares about the first fit's mean lose the precision the prior's scale needs (before:
    # numpy's "Matrix is not positive definite"). Refused, with the clusterer as it was, its
    # generator included.
    a, b = _rooms()
    model = DPGMMClusterer(random_state=3).fit(a)
    twin = pickle.loads(pickle.dumps(model))
    with pytest.raises(ValueError, match=r"points 1e\+08 from the mean .* Fit again"):
        model.partial_fit(b + 1e8 * np.sqrt([0.5, 0.5]))
    assert model.n_clusters_ == twin.n_clusters_
    np.testing.assert_array_equal(model.means_, twin.means_)
    np.testing.assert_array_equal(model.partial_fit(b).labels_, twin.partial_fit(b).labels_)


@pytest.mark.parametrize("distance", [500.0, 5000.0])
def test_clusterer_partial_fit_takes_a_far_batch_of_a_level_laser(distance):
    # 3-D points of a level planar laser share one height, which the statistics hold
    # exactly however far the robot goes: a batch kilometres away along x is a new room,
    # not refused (a precision check on the largest coordinate refused it at 500 m, its
    # prior scale along z being a millionth of the others').
    rng = np.random.default_rng(0)
    a = np.column_stack([rng.uniform(0, 10, (200, 2)), np.full(200, 0.3)])
    model = DPGMMClusterer(random_state=0).fit(a)
    n_clusters = model.n_clusters_
    model.partial_fit(a + [distance, 0.0, 0.0])
    assert model.n_clusters_ > n_clusters
    new = model.means_[n_clusters:]
    np.testing.assert_allclose(new[:, 2], 0.3, rtol=1e-12)
    # Posterior means, shrunk towards the first fit's mean by a point's weight in 200.
    assert np.all(new[:, 0] > 0.9 * distance)


def test_a_batch_too_far_for_the_clusterer_leaves_the_map_as_it_was(office):
    data, queries = office
    model = _model().partial_fit(*_batch(data, 0, 10), classes=[0, 1])
    before = model.predict_proba(queries)
    n_rows, n_clusters = model.cluster_labels_.size, model.clusterer_.n_clusters_
    X, y = _batch(data, 10, 12)
    with pytest.raises(ValueError, match="Fit again on all points"):
        model.partial_fit(X + 1e7, y)
    assert model.cluster_labels_.size == n_rows
    assert model.clusterer_.n_clusters_ == n_clusters
    np.testing.assert_array_equal(model.predict_proba(queries), before)
    # Farther still, beyond the cells that count hits (1.07e8 m): refused before the
    # clusterer sees the batch.
    state = pickle.dumps(model)
    with pytest.raises(ValueError, match="cannot be counted in cells: are they in the coord"):
        model.partial_fit(X + 1e10, y)
    assert pickle.dumps(model) == state


# -- skoccmap map --online -----------------------------------------------------------------


def test_cli_online_replay_writes_snapshots(paper_log, tmp_path, capsys):
    from skoccmap import OccupancyGrid
    from skoccmap.cli import main

    log, data = paper_log
    snaps = tmp_path / "snaps"
    argv = ["map", str(log), "--online", "--batch-scans", "9", "--snapshots", str(snaps),
            "--snapshot-every", "2", "--resolution", "1.0", "--max-expert-size", "150",
            "--n-jobs", "1", "--out", str(tmp_path / "out"), "--quiet"]  # fmt: skip
    assert main(argv) == 0
    stdout = capsys.readouterr().out
    table = [line for line in stdout.splitlines() if re.match(r"\| \d+ \|", line)]
    # 26 scans in batches of 9: three updates, each with its time and experts touched.
    assert len(table) == 3
    seen = [int(line.split("|")[2]) for line in table]
    assert seen == [9, 18, 26]
    assert all(int(line.split("|")[5]) > 0 for line in table)
    assert sorted(p.name for p in snaps.glob("*.npz")) == ["batch_00002.npz", "batch_00003.npz"]
    assert (tmp_path / "out" / "paper.npz").is_file()
    # A snapshot knows only the scans seen so far: the cells the first 18 scans never
    # crossed are unknown in the snapshot after them, whatever later scans saw.
    snapshot = OccupancyGrid.load(snaps / "batch_00002.npz")
    seen_so_far = data.environment.ground_truth_grid(1.0, extent=snapshot.extent,
                                                     scans=data.scans[:18])  # fmt: skip
    assert not seen_so_far.observed.all()
    assert np.all(snapshot.unknown.ravel()[~seen_so_far.observed])
    assert "| online replay |" in stdout


def test_cli_online_waits_for_two_hits(paper_log, tmp_path, capsys):
    from skoccmap.cli import main

    # A first scan with one hit (the others reach the 8 m sentinel): the first update waits
    # for the next scan, as it needs two hits to cluster.
    log, _ = paper_log
    text = log.read_text().splitlines(keepends=True)
    first = text[1].split()
    n = int(first[1])
    first[2 : 2 + n] = ["2.0"] + ["8.000000"] * (n - 1)
    one_hit = tmp_path / "one_hit.log"
    one_hit.write_text(" ".join(first) + "\n" + "".join(text[2:6]))
    argv = ["map", str(one_hit), "--online", "--batch-scans", "1", "--resolution", "1.0",
            "--n-jobs", "1", "--out", str(tmp_path / "out"), "--quiet"]  # fmt: skip
    assert main(argv) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if re.match(r"\| \d+ \|", line)]
    assert [int(line.split("|")[2]) for line in table] == [2, 3, 4, 5]


def test_cli_online_skips_a_scan_of_zero_readings(paper_log, tmp_path, capsys):
    from skoccmap.cli import main

    # Zeros are no reading: a scan of nothing but zeros gives no rows, and the replay
    # moves on to the next batch.
    log, _ = paper_log
    text = log.read_text().splitlines(keepends=True)
    third = text[3].split()
    n = int(third[1])
    third[2 : 2 + n] = ["0.0"] * n
    zeros = tmp_path / "zeros.log"
    zeros.write_text("".join(text[1:3]) + " ".join(third) + "\n" + "".join(text[4:6]))
    argv = ["map", str(zeros), "--online", "--batch-scans", "1", "--resolution", "1.0",
            "--n-jobs", "1", "--out", str(tmp_path / "out"), "--quiet"]  # fmt: skip
    assert main(argv) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if re.match(r"\| \d+ \|", line)]
    assert [int(line.split("|")[1]) for line in table] == [1, 2, 4, 5]


def test_cli_online_bad_batch_size(paper_log, capsys):
    from skoccmap.cli import main

    log, _ = paper_log
    assert main(["map", str(log), "--online", "--batch-scans", "0", "--quiet"]) == 2
    assert "--batch-scans must be >= 1" in capsys.readouterr().err
    assert main(["map", str(log), "--online", "--refit-fraction", "-1", "--quiet"]) == 2
    assert "--refit-fraction must be >= 0" in capsys.readouterr().err


@pytest.mark.parametrize("fraction", [0.0, 0.25])
def test_cli_refit_fraction_reaches_the_online_model(paper_log, tmp_path, fraction):
    from skoccmap import _cmd_map
    from skoccmap.cli import build_parser

    log, _ = paper_log
    argv = ["map", str(log), "--online", "--batch-scans", "13", "--refit-fraction",
            str(fraction), "--max-expert-size", "150", "--n-jobs", "1", "--quiet"]  # fmt: skip
    args = build_parser().parse_args(argv)
    train = _cmd_map.load_scans(args)
    model = _cmd_map._replay(args, train, None)
    assert model.refit_fraction == fraction


def test_experts_with_their_own_hyperparameters_take_rows_with_them(office):
    # Each expert learns its kernel: rows are added under the kernel it learned (the very
    # object), and an expert refitted learns again.
    data, _ = office
    expert = EPGaussianProcessClassifier(
        ConstantKernel(100.0, (1.0, 1e4)) * IntegralKernel(1.0, (0.1, 10.0)), max_iter=400
    )
    model = MixtureGPOccupancyMap(
        expert=expert, share_hyperparameters=False, max_expert_size=150, random_state=0
    )
    # Scan 12 touches 16 experts, 5 of which only take rows (with scan 14 every touched
    # expert is split or new).
    model.partial_fit(*_batch(data, 0, 12), classes=[0, 1])
    old = list(model.experts_)
    kernels = {id(e.kernel_) for e in old if hasattr(e, "site_nu_")}
    model.partial_fit(*_batch(data, 12, 13))
    counts = _settled_and_absorbed(model)
    touched = model.touched_experts_
    kept = [k for k in touched if id(getattr(model.experts_[k], "kernel_", None)) in kernels]
    assert kept and len(kept) < len(touched)
    # Those that kept their kernel took rows without settling them; the others settled all.
    assert all(counts[k, 1] > 0 for k in kept)
    assert all(counts[k, 1] == 0 for k in touched if k not in kept)
    # Only a fixed kernel's matrix is kept for later refits: one of the starting
    # hyperparameters would stand in for the learned kernel when rows are added.
    assert model.kernel_cache_size > 0 and not model._kernel_cache
    # The refits learned other kernels: the reach is that of the kernels the experts have.
    assert {repr(e.kernel_) for e in model.experts_} != {repr(e.kernel_) for e in old}
    assert model.reach_ == model._reach(model._pieces, model._kernels())


def test_clusterer_partial_fit_first_seated_points_follow_the_new_room():
    # Room b is near room a's broad cluster: its first-seated points join a (the new table
    # is not open yet); the sweeps after the seating move them to b's cluster.
    rng = np.random.default_rng(0)
    a = rng.normal([0, 0], 1.0, (200, 2))
    b = rng.normal([4, 0], 0.3, (100, 2))
    model = DPGMMClusterer(random_state=0).fit(a)
    n_old = model.n_clusters_
    model.partial_fit(b)
    assert model.n_clusters_ == n_old + 1
    np.testing.assert_array_equal(model.labels_, n_old)


def test_clusterer_partial_fit_sequence_is_reproducible_on_ambiguous_batches():
    # Overlapping batches: the seating is random, so only the fit's generator going on into
    # partial_fit makes the sequence reproducible.
    rng = np.random.default_rng(1)
    batches = [rng.uniform(0, 10, (60, 2)) for _ in range(3)]
    runs = []
    for _ in range(2):
        model = DPGMMClusterer(alpha=5.0, random_state=0).fit(batches[0])
        runs.append([model.partial_fit(b).labels_.copy() for b in batches[1:]])
    for first, second in zip(*runs, strict=True):
        np.testing.assert_array_equal(first, second)


@pytest.mark.parametrize("burn_in", [0, 3, 7])
def test_clusterer_partial_fit_runs_burn_in_sweeps_over_the_batch_only(monkeypatch, burn_in):
    import skoccmap.cluster as cluster

    a, b = _rooms()
    model = DPGMMClusterer(burn_in=burn_in, max_iter=10, random_state=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model.fit(a)
    swept = []
    sweep = cluster._CollapsedGibbs.gibbs_sweep

    def spy(self, rng):
        swept.append(len(self.X))
        return sweep(self, rng)

    monkeypatch.setattr(cluster._CollapsedGibbs, "gibbs_sweep", spy)
    model.partial_fit(b[:20])
    assert swept == [20] * burn_in


def _shown_in_a_loop(action, update, n_calls):
    """Warnings (category, text) that the warnings module shows while ``update(i)`` runs
    for ``i < n_calls`` under ``simplefilter(action)``, as a robot's log would have them."""
    shown = []
    with warnings.catch_warnings():
        warnings.simplefilter(action)
        warnings.showwarning = lambda message, category, *args, **kwargs: shown.append(
            (category, str(message))
        )
        for i in range(n_calls):
            update(i)
    return shown


def test_a_warning_of_every_update_is_shown_once_under_the_default_filter(office):
    # float32 coordinates at UTM-like offsets warn on every batch, with the same text.
    # Python's "default" action shows a repeated warning once per line (a plain
    # warnings.warn in the same loop: once); the experts' fits used to reset that record,
    # so a robot's log got one warning per update.
    data, _ = office
    offset = np.array([500_000.0, 4_000_000.0] * 2)
    model = _model()

    def update(i):
        X, y = _batch(data, 2 * i, 2 * i + 2)
        model.partial_fit((X + offset).astype(np.float32), y, classes=[0, 1])

    coarse = [text for _, text in _shown_in_a_loop("default", update, 4) if "float32" in text]
    assert len(coarse) == 1
    # Under "always" every update still says so.
    model = _model()
    coarse = [text for _, text in _shown_in_a_loop("always", update, 4) if "float32" in text]
    assert len(coarse) == 4


def test_experts_warnings_differing_only_in_their_numbers_are_one_kind_in_a_loop(office):
    # EP stopped early in some experts of every update: "3 of 9 expert(s): EP did not
    # converge ... residual 1.2e-02", numbers changing from one update to the next.
    data, _ = office
    expert = EPGaussianProcessClassifier(
        ConstantKernel(100.0, "fixed") * IntegralKernel(1.0, "fixed"), optimizer=None, max_iter=1
    )
    model = MixtureGPOccupancyMap(expert=expert, max_expert_size=150, random_state=0)

    def update(i):
        model.partial_fit(*_batch(data, 3 * i, 3 * i + 3), classes=[0, 1])

    shown = _shown_in_a_loop("default", update, 4)
    assert len([text for _, text in shown if "expert(s): EP" in text]) == 1
    model = MixtureGPOccupancyMap(expert=expert, max_expert_size=150, random_state=0)
    texts = [text for _, text in _shown_in_a_loop("always", update, 4) if "expert(s): EP" in text]
    # Each update's own counts, numbers and all.
    assert len(texts) >= 4 and len(set(texts)) > 1
