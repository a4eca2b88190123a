"""MixtureGPOccupancyMap: assignment rules, experts, gating, merging, sklearn integration.

Structural tests use fast stand-ins passed explicitly (sklearn's KMeans / GaussianMixture as
clusterer, sklearn's GaussianProcessClassifier with fixed hyperparameters as expert): the
mixture must work with any clusterer with fit/predict and any expert with
``latent_mean_and_variance``. The paper-level claims use the package's defaults.
"""

import pickle
import warnings

import numpy as np
import pytest
from scipy.special import ndtr, ndtri
from sklearn.base import BaseEstimator, ClassifierMixin, clone
from sklearn.cluster import KMeans
from sklearn.gaussian_process import GaussianProcessClassifier
from sklearn.gaussian_process.kernels import RBF
from sklearn.gaussian_process.kernels import ConstantKernel as C
from sklearn.metrics import roc_auc_score
from sklearn.mixture import GaussianMixture
from sklearn.model_selection import GridSearchCV
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import FunctionTransformer

from skoccmap._beams import _assign_no_return, _beam_pieces, _similarity_length_scale
from skoccmap._experts import _ConstantExpert, _default_kernel, _fit_expert, _warn_once_each
from skoccmap._partition import (
    _bisect,
    _merge_small,
    _nearest_with_room,
    _piece_gates,
    _PieceGate,
    _split_hits,
)
from skoccmap.combine import COMBINERS, combine
from skoccmap.datasets import make_paper_scans
from skoccmap.kernels import IntegralKernel
from skoccmap.mixture import MixtureGPOccupancyMap
from skoccmap.observations import HIT, NO_RETURN, RETURN, as_segments


def _fast_expert(length_scale=1.5):
    return GaussianProcessClassifier(C(2.0) * RBF(length_scale), optimizer=None)


def _mixture(**params):
    params.setdefault("clusterer", GaussianMixture(5, random_state=0))
    params.setdefault("expert", _fast_expert())
    params.setdefault("random_state", 0)
    # Every piece kept, so that the tests below can rebuild an expert's rows from the beams
    # (thinning has its own tests, in test_thinning.py).
    params.setdefault("max_pieces_per_cell", None)
    return MixtureGPOccupancyMap(**params)


@pytest.fixture(scope="module")
def paper():
    return make_paper_scans(random_state=0)


@pytest.fixture(scope="module")
def grid(paper):
    # The cells a map can know about, at 0.2 m: coarser cells that touch a wall count as
    # occupied although most of them is free, which rewards thick walls.
    g = paper.environment.ground_truth_grid(0.2, scans=paper.scans)
    return g.occupied[g.observed], as_segments(g.points[g.observed])


# --- assignment ------------------------------------------------------------------------


def _consulted_weights(model, Q):
    """Dense (queries, experts) gate weights of the experts each query consults."""
    query, expert, weights = model._consulted(Q)
    dense = np.zeros((Q.shape[0], model.n_experts_))
    dense[query, expert] = weights
    return dense


def _combined_by_hand(model, Q, combiners):
    """Each combiner's :func:`combine` of every expert's own mean, variance and prior at
    ``Q``, weighted by the gate of the experts each query consults."""
    weights = _consulted_weights(model, Q)
    means, variances = zip(*(e.latent_mean_and_variance(Q) for e in model.experts_), strict=True)
    priors = np.column_stack([e.kernel_.diag(Q) for e in model.experts_])
    return {
        combiner: combine(
            np.column_stack(means),
            np.column_stack(variances),
            weights,
            method=combiner,
            prior_variance=priors,
        )
        for combiner in combiners
    }


def test_observation_kinds_recovered_from_geometry(paper):
    model = _mixture().fit(paper.X, paper.y)
    np.testing.assert_array_equal(model.observation_kind_, paper.kind)


def test_hits_and_return_beams_follow_their_hit(paper):
    model = _mixture().fit(paper.X, paper.y)
    X, labels = paper.X, model.cluster_labels_
    hits = np.flatnonzero(paper.kind == HIT)
    # Hits carry the clusterer's labels.
    raw = model.clusterer_.predict(X[hits, :2])
    _, expected = np.unique(raw, return_inverse=True)
    np.testing.assert_array_equal(
        model.expert_cluster_[labels[hits]], model.cluster_merge_[expected]
    )
    # A return beam stops free_margin short of its hit: brute-force nearest hit to its end.
    for row in np.flatnonzero(paper.kind == RETURN):
        nearest = hits[np.argmin(np.linalg.norm(X[hits, :2] - X[row, 2:], axis=1))]
        assert labels[row] == labels[nearest]


def test_free_points_follow_their_nearest_hit_however_far():
    # layout="points": free points are return beams of no length, whatever the distance to
    # the nearest hit (return_radius bounds beams only), and follow that hit.
    X, y = _wall_and_post()
    model = MixtureGPOccupancyMap(layout="points", random_state=0).fit(X, y)
    assert np.all(model.observation_kind_[y == 0] == RETURN)
    hits = X[y == 1]
    dist = np.linalg.norm(X[y == 0][:, None] - hits[None], axis=-1)
    assert dist.min(axis=1).max() > 10 * model.return_radius
    chosen = dist[np.arange(dist.shape[0]), model._row_hit[y == 0]]
    np.testing.assert_allclose(chosen, dist.min(axis=1), rtol=1e-12)


def test_without_return_beams_a_beam_follows_the_hit_nearest_to_its_midpoint():
    # Beams that stop 2 m short of a wall (no hit near their end) listed before the hits:
    # each follows the hit nearest to its midpoint.
    rng = np.random.default_rng(0)
    wall = np.column_stack([np.full(30, 5.0), np.linspace(-3, 3, 30)])
    y_beam = rng.uniform(-3, 3, 40)
    beams = np.column_stack([np.zeros(40), y_beam, np.full(40, 3.0), rng.uniform(-3, 3, 40)])
    X = np.vstack([beams, as_segments(wall)])
    y = np.r_[np.zeros(40, int), np.ones(30, int)]
    model = _mixture(min_hit_frequency=None).fit(X, y)
    assert np.all(model.observation_kind_[:40] == NO_RETURN)
    mids = 0.5 * (beams[:, :2] + beams[:, 2:])
    dist = np.linalg.norm(mids[:, None] - wall[None], axis=-1)
    chosen = dist[np.arange(40), model._row_hit[:40]]
    np.testing.assert_allclose(chosen, dist.min(axis=1), rtol=1e-12)


@pytest.mark.parametrize("length_scale", [0.3, 1.0, [0.5, 2.0]])
def test_no_return_rule_matches_brute_force(paper, length_scale):
    # Pruning by upper bounds must not change the argmax of the integral kernel.
    X, kind = paper.X, paper.kind
    ret = np.flatnonzero(kind == RETURN)
    ret_labels = np.arange(ret.size)
    nr = X[kind == NO_RETURN]
    got = _assign_no_return(nr, X[ret], ret_labels, np.asarray(length_scale))
    expected = np.argmax(IntegralKernel(length_scale)(nr, X[ret]), axis=1)
    np.testing.assert_array_equal(got, expected)


def test_no_return_rule_on_samples_of_return_beams(paper, monkeypatch):
    import skoccmap._beams as beams

    monkeypatch.setattr(beams, "_NO_RETURN_PAIRS", 40 * 30)  # blocks of 40 beams
    X, kind = paper.X, paper.kind
    ret, nr = X[kind == RETURN], X[kind == NO_RETURN]
    labels = np.arange(len(ret))
    got = _assign_no_return(nr, ret, labels, 1.0, max_references=30, random_state=0)
    again = _assign_no_return(nr, ret, labels, 1.0, max_references=30, random_state=0)
    np.testing.assert_array_equal(got, again)
    # Each choice is the best of a uniform sample of 30: better than almost all return
    # beams (the median rank of the best of 30 is about 2% from the top).
    K = IntegralKernel(1.0)(nr, ret)
    better = (K > K[np.arange(len(nr)), got][:, None]).mean(axis=1)
    assert np.median(better) < 0.1
    # Every block draws its own sample, so the choices spread beyond one sample.
    assert np.unique(got).size > 30


def test_no_return_beams_of_a_block_choose_among_its_sample(paper, monkeypatch):
    import skoccmap._beams as beams

    # Blocks of 40 no-return beams, each compared with a sample of at most 3 return beams.
    monkeypatch.setattr(beams, "_NO_RETURN_PAIRS", 40 * 3)
    X, kind = paper.X, paper.kind
    ret, nr = X[kind == RETURN], X[kind == NO_RETURN]
    assert ret.shape[0] > 3 and nr.shape[0] > 80
    got = _assign_no_return(nr, ret, np.arange(len(ret)), 1.0, max_references=3, random_state=0)
    K = IntegralKernel(1.0)(nr, ret)
    for start in range(0, len(nr), 40):
        block = np.arange(start, min(start + 40, len(nr)))
        sample = np.unique(got[block])
        # At most the sample's return beams are chosen, and each beam takes the most
        # similar of those (all of them are in its block's sample).
        assert sample.size <= 3
        np.testing.assert_array_equal(
            got[block], sample[np.argmax(K[np.ix_(block, sample)], axis=1)]
        )


def test_no_return_beam_out_of_reach_joins_the_nearest_return_beam():
    ret = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 5.0, 1.0, 5.0]])
    far = np.array([[30.0, 4.0, 40.0, 4.0]])
    assert _assign_no_return(far, ret, np.array([7, 9]), np.asarray(0.1))[0] == 9


def test_clusterer_fitted_on_a_subsample_labels_every_hit(paper):
    X, y = paper.X, paper.y
    model = _mixture(
        clusterer=KMeans(4, n_init=2, random_state=0),
        max_cluster_samples=60,
        min_expert_size=1,
        max_expert_size=None,
    ).fit(X, y)
    assert model.clusterer_.labels_.size == 60 < np.sum(y == 1)
    # Every hit, sampled or not, joins the cluster the fitted clusterer predicts for it.
    hits = X[y == 1, :2]
    np.testing.assert_array_equal(
        model.cluster_ids_[model.cluster_labels_[y == 1]], model.clusterer_.predict(hits)
    )
    # Fewer hits than the cap: the clusterer sees them all.
    full = _mixture(clusterer=KMeans(4, n_init=2, random_state=0)).fit(X, y)
    assert full.clusterer_.labels_.size == np.sum(y == 1)


def _wall_and_far_hits():
    """Left: a wall at x=0 seen by 30 beams from x=3; right: 12 hits at x=20 that no beam
    reaches (a one-class cluster)."""
    rng = np.random.default_rng(1)
    wall = np.column_stack([np.zeros(30), np.linspace(-2, 2, 30)])
    beams = np.column_stack([np.full(30, 3.0), wall[:, 1], wall + [0.05, 0.0]])
    far = rng.normal([20.0, 0.0], 0.3, size=(12, 2))
    X = np.vstack([as_segments(wall), beams, as_segments(far)])
    return X, np.r_[np.ones(30), np.zeros(30), np.ones(12)].astype(int)


def test_one_class_cluster_gets_constant_expert():
    X, y = _wall_and_far_hits()
    model = MixtureGPOccupancyMap(
        KMeans(2, n_init=3, random_state=0),
        _fast_expert(),
        combiner="moe",
        min_expert_size=1,
        random_state=0,
    ).fit(X, y)
    constant = [e for e in model.experts_ if isinstance(e, _ConstantExpert)]
    assert len(constant) == 1
    q = as_segments([[20.0, 0.0], [25.0, 3.0]])
    mean, var = constant[0].latent_mean_and_variance(q)
    # Prior variance of the expert's kernel, and smoothed frequency (12 + 1) / (12 + 2).
    np.testing.assert_allclose(var, _fast_expert().kernel.diag(q))
    np.testing.assert_allclose(ndtr(mean / np.sqrt(1 + var)), 13 / 14)
    # Among its hits the mixture is that expert; beyond the reach of all data, the prior.
    assert 3.0 < model.reach_ < np.hypot(5.0, 3.0) - 1.0
    np.testing.assert_allclose(model.predict_proba(q)[:, 1], [13 / 14, 0.5])
    # The robust BCM weighs experts by their information gain over the prior, which is
    # zero for a constant expert: where it is the only expert, the merge is the prior.
    model.set_params(combiner="rbcm")
    np.testing.assert_allclose(model.predict_proba(q)[:, 1], 0.5)


def _wall_and_post():
    """A wall with the free space in front of it, and a post of 25 hits far from any free
    point: the post's expert sees one class."""
    rng = np.random.default_rng(0)
    wall = np.c_[np.full(60, 5.0), np.linspace(-3, 3, 60)]
    free = np.c_[rng.uniform(0, 4.7, 400), rng.uniform(-3, 3, 400)]
    post = np.array([10.0, 10.0]) + rng.normal(0, 0.2, (25, 2))
    X = np.r_[wall, free, post]
    return X, np.r_[np.ones(60), np.zeros(400), np.ones(25)].astype(int)


def test_a_one_class_ep_expert_is_the_gp_posterior_and_counts_under_the_robust_bcm():
    from skoccmap.ep import ep_latent_predictive, expectation_propagation

    # Run as a constant at the prior variance, the post's expert had no weight under the
    # robust BCM, which drew the post at p = 0.5.
    X, y = _wall_and_post()
    model = MixtureGPOccupancyMap(layout="points", random_state=0).fit(X, y)
    one_class = [e for e in model.experts_ if np.all(getattr(e, "y_train_", [0]) == 1)]
    assert len(one_class) == 1 and one_class[0].classes_.tolist() == [0, 1]
    expert = one_class[0]
    # EP on the expert's rows alone, computed here, with the expert's (shared) kernel and
    # its stopping tolerance.
    K = expert.kernel_(expert.X_train_)
    res = expectation_propagation(K, np.ones(len(K)), tol=expert.tol)
    Q = as_segments([[10.0, 10.0], [10.5, 9.5]])
    mean, var = ep_latent_predictive(
        expert.kernel_(Q, expert.X_train_), expert.kernel_.diag(Q), res.posterior
    )
    got_mean, got_var = expert.latent_mean_and_variance(Q)
    np.testing.assert_allclose(got_mean, mean, rtol=1e-5)
    np.testing.assert_allclose(got_var, var, rtol=1e-5)
    assert np.all(var < 0.5 * expert.kernel_.diag(Q))  # it learned something there
    for combiner in ("rbcm", "bcm", "poe", "moe"):
        model.set_params(combiner=combiner)
        assert model.predict_proba([[10.0, 10.0]])[0, 1] > 0.9, combiner
        # ... and beyond the reach of all data, the prior.
        np.testing.assert_allclose(model.predict_proba([[40.0, 40.0]])[:, 1], 0.5)


def test_free_rows_added_to_a_one_class_ep_expert_refit_it_at_once():
    # Its sites, fitted on one class, are saturated: held while EP ran on two new free
    # points beside the post, they let the post fall to p = 0.32. Refitted, it stays.
    X, y = _wall_and_post()
    model = MixtureGPOccupancyMap(layout="points", random_state=0).partial_fit(X, y, [0, 1])
    assert model.predict_proba([[10.0, 10.0]])[0, 1] > 0.9
    near = np.array([[8.5, 10.0], [11.5, 10.0]])
    model.partial_fit(near, [0, 0])
    expert = model.experts_[model.touched_experts_[0]]
    assert model.touched_experts_.size == 1 and np.ptp(expert.y_train_) > 0
    whole = MixtureGPOccupancyMap(layout="points", random_state=0).fit(
        np.r_[X, near], np.r_[y, 0, 0]
    )
    assert model.predict_proba([[10.0, 10.0]])[0, 1] > 0.9
    np.testing.assert_allclose(
        model.predict_proba([[10.0, 10.0]]), whole.predict_proba([[10.0, 10.0]]), atol=1e-3
    )


# --- experts, merging and splitting ------------------------------------------------------


def test_small_clusters_are_merged_and_their_gates_summed(paper, grid):
    _, Q = grid
    model = _mixture(clusterer=GaussianMixture(12, random_state=0), min_expert_size=60)
    model.fit(paper.X, paper.y)
    # Sizes of the merged clusters (before big ones are split into experts).
    sizes = np.bincount(model.expert_cluster_[model.cluster_labels_])
    assert model.cluster_ids_.size > model.n_clusters_ > 1
    assert sizes.min() >= 60
    # Every clusterer cluster maps to one merged cluster whose gate is the sum.
    raw = model.clusterer_.predict_proba(Q[:, :2])[:, model.cluster_ids_]
    merged = model._cluster_weights(Q[:, :2])
    for c in range(model.n_clusters_):
        np.testing.assert_allclose(merged[:, c], raw[:, model.cluster_merge_ == c].sum(axis=1))
    # Hits keep their clusterer cluster, up to the merge.
    hits = paper.y == 1
    raw_hit = np.searchsorted(model.cluster_ids_, model.clusterer_.predict(paper.X[hits, :2]))
    np.testing.assert_array_equal(
        model.expert_cluster_[model.cluster_labels_[hits]], model.cluster_merge_[raw_hit]
    )


@pytest.mark.parametrize("max_beam_length, end_length", [(None, None), (1.0, None), (1.0, 0.25)])
def test_single_cluster_mixture_equals_its_expert(paper, grid, max_beam_length, end_length):
    _, Q = grid
    # Every other pose: the pieces of all of them make the two O(n^3) fits the slowest test.
    half = paper.scan_index % 2 == 0
    X, y, kind = paper.X[half], paper.y[half], paper.kind[half]
    model = _mixture(
        clusterer=KMeans(1, n_init=1),
        max_expert_size=None,
        max_beam_length=max_beam_length,
        beam_end_length=end_length,
    ).fit(X, y)
    # The expert sees the beams cut into pieces (see the test of _beam_pieces).
    pieces, source = _beam_pieces(X, kind, max_beam_length, end_length)
    single = _fast_expert().fit(pieces, y[source])
    mean, var = single.latent_mean_and_variance(Q)
    for combiner in ["moe", "poe", "gpoe", "bcm"]:
        model.set_params(combiner=combiner)
        got_mean, got_var = model.latent_mean_and_variance(Q)
        np.testing.assert_allclose(got_mean, mean, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(got_var, var, rtol=1e-10)


def test_big_clusters_are_split_and_gated(paper, grid):
    _, Q = grid
    model = _mixture(clusterer=KMeans(2, n_init=3, random_state=0), max_expert_size=100)
    model.fit(paper.X, paper.y)
    sizes = np.bincount(model.cluster_labels_, minlength=model.n_experts_)
    assert sizes.max() <= 100
    assert model.n_experts_ >= int(np.ceil(paper.X.shape[0] / 100))
    n, k = Q.shape[0], model.n_experts_
    every = (np.repeat(np.arange(n), k), np.tile(np.arange(k), n))
    w = model._pair_gates(Q[:, :2], *every).reshape(n, k)
    # Pieces share their cluster's weight: the split gate is a partition of unity.
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-12)


def test_piece_gates_favour_each_hits_own_piece(paper):
    # Within a split cluster the Gaussian piece gates share the cluster's weight out by
    # location: at a hit of piece k, piece k gets the largest share (a gate that ignored the
    # location, e.g. uniform shares, would pick its first piece: about 1 / pieces).
    model = _mixture(clusterer=KMeans(2, n_init=3, random_state=0), max_expert_size=100)
    model.fit(paper.X, paper.y)
    hits = np.flatnonzero(paper.y == 1)
    own = model.cluster_labels_[hits]
    k = model.n_experts_
    q = np.repeat(np.arange(hits.size), k)
    weights = model._pair_gates(paper.X[hits, :2], q, np.tile(np.arange(k), hits.size))
    weights = weights.reshape(hits.size, k)
    # Among the pieces of the hit's own cluster (the cluster gate weighs clusters).
    cluster = model.expert_cluster_
    weights = np.where(cluster[None, :] == cluster[own][:, None], weights, -1.0)
    split = np.bincount(cluster)[cluster[own]] > 1
    assert split.sum() > 100
    agreement = np.mean(np.argmax(weights[split], axis=1) == own[split])
    chance = np.mean(1.0 / np.bincount(cluster)[cluster[own[split]]])
    # Measured 0.72 against a chance of 0.05; uniform shares give 0.05.
    assert agreement > 0.5 > 5 * chance, (agreement, chance)


def test_piece_gate_of_an_expert_without_pieces_weighs_nothing():
    # An online update can leave an expert of a split cluster without pieces (its hits all
    # transient): its share is 0, not NaN, and the others still sum to one.
    rng = np.random.default_rng(0)
    groups = [rng.normal(size=(20, 2)), np.empty((0, 2)), rng.normal(3.0, size=(5, 2))]
    points = rng.normal(1.0, 2.0, size=(50, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        share = _PieceGate(groups).predict_proba(points)
        alone = _PieceGate([groups[0], groups[2]]).predict_proba(points)
        none = _PieceGate([np.empty((0, 2))] * 2).predict_proba(points)
    np.testing.assert_array_equal(share[:, 1], 0.0)
    np.testing.assert_allclose(share[:, [0, 2]], alone, rtol=1e-12)
    np.testing.assert_allclose(none, 0.5)


def test_piece_gate_is_the_posterior_of_a_gaussian_per_expert_weighted_by_its_pieces():
    # Each expert's Gaussian: mean and covariance of its pieces' midpoints (a single piece:
    # unit covariance), plus a ridge of 1e-3 of its mean variance; its prior weight: its
    # share of the pieces.
    from scipy.stats import multivariate_normal

    rng = np.random.default_rng(0)
    groups = [
        rng.normal([0.0, 0.0], [2.0, 0.8], size=(30, 2)),
        rng.normal([1.0, 1.0], [0.5, 0.5], size=(8, 2)),
        np.array([[2.0, -1.0]]),
    ]
    points = rng.uniform(-2.0, 2.0, size=(50, 2))
    density = np.empty((50, 3))
    n_pieces = sum(len(g) for g in groups)
    for k, g in enumerate(groups):
        cov = np.cov(g, rowvar=False) if len(g) > 1 else np.eye(2)
        cov = cov + 1e-3 * np.trace(cov) / 2 * np.eye(2)
        weight = len(g) / n_pieces
        density[:, k] = weight * multivariate_normal(g.mean(axis=0), cov).pdf(points)
    expected = density / density.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(_PieceGate(groups).predict_proba(points), expected, rtol=1e-9)


def test_piece_gates_remake_only_the_clusters_asked_for():
    # Clusters 0 and 1 of two experts each, cluster 2 of one; then cluster 1 gains a piece
    # and a cluster 3 of two experts is added: only clusters 1 and 3 get new gates.
    rng = np.random.default_rng(0)
    expert_cluster = np.array([0, 0, 1, 1, 2])
    piece_expert = np.repeat(np.arange(5), 4)
    pieces = rng.normal(size=(20, 4))
    old = _piece_gates(expert_cluster, 3, pieces, piece_expert)
    assert isinstance(old[0], _PieceGate) and isinstance(old[1], _PieceGate) and old[2] is None
    expert_cluster = np.r_[expert_cluster, 3, 3]
    piece_expert = np.r_[piece_expert, 2, 5, 5, 6, 6]
    pieces = np.vstack([pieces, rng.normal(size=(5, 4))])
    new = _piece_gates(expert_cluster, 4, pieces, piece_expert, clusters=[1, 3], gates=old)
    assert len(new) == 4 and new[0] is old[0] and new[2] is None
    assert new[1] is not old[1] and isinstance(new[3], _PieceGate)
    # The new gates are those of the experts' pieces now: each Gaussian at its midpoints.
    mids = 0.5 * (pieces[:, :2] + pieces[:, 2:])
    for c, experts in ((1, [2, 3]), (3, [5, 6])):
        for mean, k in zip(new[c].means_, experts, strict=True):
            np.testing.assert_allclose(mean, mids[piece_expert == k].mean(axis=0), rtol=1e-12)


def test_split_pieces_keep_each_hit_with_its_beams(paper):
    # Pieces are cut through the hits; beams follow their hit, so no piece is left with
    # one class (a wall without the beams that saw it, or free space without its wall).
    X, kind = paper.X, paper.kind
    model = _mixture(
        clusterer=KMeans(2, n_init=3, random_state=0), max_expert_size=60, piece_assignment="beam"
    )
    model.fit(X, paper.y)
    labels = model.cluster_labels_
    assert model.n_experts_ >= int(np.ceil(X.shape[0] / 60))
    hits = np.flatnonzero(kind == HIT)
    for row in np.flatnonzero(kind == RETURN):
        # Several scans can hit the very same point: any of the nearest hits will do.
        dist = np.linalg.norm(X[hits, :2] - X[row, 2:], axis=1)
        nearest = hits[dist <= dist.min() + 1e-12]
        assert labels[row] in labels[nearest]
    for k in range(model.n_experts_):
        assert 0 < paper.y[labels == k].mean() < 1, k
    assert not any(isinstance(e, _ConstantExpert) for e in model.experts_)
    # Nearest-hit pieces split alike: every expert still holds both classes.
    nearest = _mixture(clusterer=KMeans(2, n_init=3, random_state=0), max_expert_size=60)
    nearest.fit(X, paper.y)
    assert not any(isinstance(e, _ConstantExpert) for e in nearest.experts_)


def test_weighted_bisection_bounds_piece_weight():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 10, size=(300, 2))
    weights = rng.integers(1, 6, size=300)
    pieces = _bisect(points, 50, weights)
    np.testing.assert_array_equal(np.sort(np.concatenate(pieces)), np.arange(300))
    assert max(weights[p].sum() for p in pieces) <= 50
    # Balanced: no more pieces than twice the minimum needed.
    assert len(pieces) <= 2 * int(np.ceil(weights.sum() / 50))
    # A point heavier than the cap stays a piece of its own.
    heavy = _bisect(points[:3], 5, np.array([9, 1, 1]))
    assert [0] in [p.tolist() for p in heavy]
    assert sorted(np.concatenate(heavy).tolist()) == [0, 1, 2]


def test_bisection_splits_at_the_median():
    # Eight collinear points of unit weight and room for four: two halves of four.
    points = np.column_stack([np.arange(8.0), np.zeros(8)])
    pieces = _bisect(points, 4)
    assert sorted(sorted(p.tolist()) for p in pieces) == [[0, 1, 2, 3], [4, 5, 6, 7]]


def test_bisection_cuts_across_the_principal_axis_wherever_the_points_lie():
    # A cloud 10 m long (along x) and 1 m wide: the first cut is across its length at the
    # median, however far from the origin the cloud lies.
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-5, 5, 64), rng.uniform(-0.5, 0.5, 64)])
    median = np.median(points[:, 0])
    for offset in ([0.0, 0.0], [0.0, 100.0], [-300.0, 40.0]):
        pieces = _bisect(points + offset, 32)
        assert len(pieces) == 2
        left, right = sorted(pieces, key=lambda p: points[p, 0].mean())
        assert points[left, 0].max() < median < points[right, 0].min()


def test_clusters_of_min_size_are_kept_and_smaller_ones_merged_into_the_nearest():
    # Observations of clusters 0 (20), 1 (50) and 2 (5); hits at x = 0, 10 and 2.
    labels = np.repeat([0, 1, 2], [20, 50, 5])
    hit_points = np.array([[0.0, 0.0], [10.0, 0.0], [2.0, 0.0]])
    hit_labels = np.array([0, 1, 2])
    assert _merge_small(labels, hit_points, hit_labels, 5).tolist() == [0, 1, 2]
    # Cluster 2 joins cluster 0, its nearest by hit centroid; cluster 0 of exactly 20 stays.
    assert _merge_small(labels, hit_points, hit_labels, 20).tolist() == [0, 1, 0]
    # With room for 26 the merged cluster of 25 joins cluster 1 as well.
    assert _merge_small(labels, hit_points, hit_labels, 26).tolist() == [0, 0, 0]


def _merge_small_by_hand(labels, hit_points, hit_labels, min_size):
    """The documented rule, a cluster (a set of hits) at a time: the smallest cluster under
    min_size joins the one whose hits' centroid is nearest to its own (ties: lowest index)."""
    n = hit_labels.max() + 1
    members = {c: [c] for c in range(n)}
    size = {c: int(np.sum(labels == c)) for c in range(n)}
    while len(members) > 1:
        small = min(members, key=lambda c: (size[c], c))
        if size[small] >= min_size:
            break

        def centroid(c):
            return hit_points[np.isin(hit_labels, members[c])].mean(axis=0)

        others = [c for c in members if c != small]
        target = min(others, key=lambda c: (np.linalg.norm(centroid(c) - centroid(small)), c))
        members[target] += members.pop(small)
        size[target] += size.pop(small)
    merged = np.empty(n, dtype=int)
    for rank, c in enumerate(sorted(members)):
        merged[members[c]] = rank
    return merged


def test_merge_small_matches_the_rule_worked_by_hand():
    # Random clusters of a few hits each, merged in chains (a merged cluster's centroid is
    # that of all its hits, and it may be merged again), down to one cluster when
    # min_size exceeds all observations.
    rng = np.random.default_rng(0)
    for _ in range(200):
        n = rng.integers(2, 9)
        n_hits = rng.integers(1, 6, size=n)
        hit_labels = np.repeat(np.arange(n), n_hits)
        hit_points = rng.uniform(0, 10, size=(hit_labels.size, 2))
        labels = np.repeat(np.arange(n), n_hits + rng.integers(0, 30, size=n))
        min_size = int(rng.integers(1, labels.size + 10))
        np.testing.assert_array_equal(
            _merge_small(labels, hit_points, hit_labels, min_size),
            _merge_small_by_hand(labels, hit_points, hit_labels, min_size),
        )


def test_coverage_gate_is_each_experts_share_of_the_data_near_the_query(paper, grid):
    _, Q = grid
    model = _mixture(gating="coverage", max_expert_size=100).fit(paper.X, paper.y)
    assert model._gating_threshold() == 0.35
    # The width is where the kernel falls to exp(-1/8) of its peak (half a length scale
    # for the squared exponential between points; this RBF over segment rows sees a point
    # at distance r at sqrt(2) r).
    kernel = model.experts_[0].kernel_
    at = as_segments([[0.0, 0.0], [model.coverage_width_, 0.0]])
    ratio = kernel(at[:1], at[1:])[0, 0] / kernel(at[:1])[0, 0]
    assert ratio == pytest.approx(np.exp(-1 / 8), abs=0.01)
    # The observed cells and a ring of points beyond them, some of them further than the
    # coverage counts (three widths) from all data.
    lo, hi = Q[:, :2].min(axis=0) - 2.5, Q[:, :2].max(axis=0) + 2.5
    ring = np.vstack([[[x, lo[1]], [x, hi[1]]] for x in np.linspace(lo[0], hi[0], 40)])
    Q = np.vstack([Q[::10], as_segments(ring)])
    index = model._reach_index
    query, expert = index.candidates(Q)
    cover = index.coverage(Q, query, expert, model.coverage_width_)
    total = np.bincount(query, weights=cover, minlength=len(Q))
    weights = model._coverage_gates(Q, query, expert)
    covered = total[query] > 0
    assert covered.mean() > 0.9 and not covered.all()
    np.testing.assert_allclose(weights[covered], cover[covered] / total[query][covered])
    np.testing.assert_array_equal(weights[~covered], 1.0)
    # Consulted: the shares of at least the threshold times the largest (which is kept),
    # among those within reach.
    q, e, w = model._consulted(Q)
    pairs = set(zip(q.tolist(), e.tolist(), strict=True))
    best = np.zeros(len(Q))
    np.maximum.at(best, query, weights)
    kept = weights >= model._gating_threshold() * best[query]
    # Relative, not absolute: experts under the threshold's share but near the best's are
    # kept (where several overlap, each share is small).
    assert np.any(kept & (weights < model._gating_threshold()) & (weights < best[query]))
    near = index.within_reach(Q, query, expert)
    expected = set(zip(query[kept & near].tolist(), expert[kept & near].tolist(), strict=True))
    assert pairs == expected


@pytest.mark.parametrize("threshold", ["auto", 0.8, 0.99])
def test_coverage_gate_from_the_covering_pairs_equals_it_from_the_candidates(
    paper, grid, threshold, monkeypatch
):
    # Many queries choose their experts from the pairs of positive coverage alone; the
    # same pairs, weights and map as from every candidate's coverage. The ring lies
    # beyond the coverage's cut: its queries consult every candidate within reach.
    _, Q = grid
    model = _mixture(max_expert_size=100, gating_threshold=threshold).fit(paper.X, paper.y)
    lo, hi = Q[:, :2].min(axis=0) - 2.5, Q[:, :2].max(axis=0) + 2.5
    ring = np.vstack([[[x, lo[1]], [x, hi[1]]] for x in np.linspace(lo[0], hi[0], 40)])
    Q = np.vstack([Q, as_segments(ring)])
    assert model._reach_index.prefers_covering(len(Q))
    fast = model._consulted(Q)
    proba = model.predict_proba(Q)
    monkeypatch.setattr(type(model._reach_index), "prefers_covering", lambda self, n: False)
    slow = model._consulted(Q)
    for got, expected in zip(fast, slow, strict=True):
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(model.predict_proba(Q), proba)
    # Uncovered queries within reach consult experts, with equal weights.
    cover = model._reach_index.covering(Q, model.coverage_width_)[0]
    bare = ~np.isin(fast[0], cover)
    assert np.any(bare) and np.all(fast[2][bare] == 1.0)


def test_few_queries_choose_their_experts_from_the_candidates_until_the_tree_is_built(
    paper,
):
    model = _mixture(max_expert_size=100).fit(paper.X, paper.y)
    Q = as_segments(paper.X[paper.y == 1, :2][:5])
    assert not model._reach_index.prefers_covering(len(Q))
    model.predict_proba(np.repeat(Q, 1000, axis=0))
    index = model._reach_index
    assert index._centre_tree is not None and index.prefers_covering(len(Q))


def test_coverage_gate_consults_the_experts_whose_data_are_at_the_query(paper):
    # At the midpoints of training beams (pieces follow their nearest hit), the consulted
    # experts include the one with the most data near the query, and hold at least 30 %
    # of that data, at every query (measured); the clusterer's gate, whose densities
    # describe the hits only, at 84 %.
    model = _mixture(gating="coverage", max_expert_size=100).fit(paper.X, paper.y)
    free = paper.y == 0
    Q = as_segments(0.5 * (paper.X[free, :2] + paper.X[free, 2:])[::7])
    query, expert = model._reach_index.candidates(Q)
    cover = model._reach_index.coverage(Q, query, expert, model.coverage_width_)
    total = np.bincount(query, weights=cover, minlength=len(Q))
    q, e, _ = model._consulted(Q)
    held = np.isin(query * model.n_experts_ + expert, q * model.n_experts_ + e)
    share = np.bincount(query[held], weights=cover[held], minlength=len(Q))
    best = np.zeros(len(Q))
    np.maximum.at(best, query, cover)
    holds_best = np.bincount(query[held & (cover == best[query])], minlength=len(Q)) > 0
    assert np.all(total > 0)
    assert holds_best.all()
    assert np.mean(share >= 0.3 * total) >= 0.95


def test_gating_threshold_skips_experts(paper, grid):
    _, Q = grid
    model = _mixture(combiner="moe", gating_threshold=0.05).fit(paper.X, paper.y)
    calls = []
    for k, expert in enumerate(model.experts_):
        original = expert.latent_mean_and_variance

        def spy(X, k=k, original=original):
            calls.append((k, X.shape[0]))
            return original(X)

        expert.latent_mean_and_variance = spy
    weights = _consulted_weights(model, Q)
    proba = model.predict_proba(Q)[:, 1]
    assert sum(n for _, n in calls) == int(np.count_nonzero(weights))
    assert sum(n for _, n in calls) < Q.shape[0] * model.n_experts_
    # The skipped weights are small, so MoE barely moves against using every expert.
    full = clone(model).set_params(gating_threshold=0.0).fit(paper.X, paper.y)
    assert np.max(np.abs(full.predict_proba(Q)[:, 1] - proba)) < 0.05 * model.n_experts_


def test_merge_matches_combine_on_expert_outputs(paper, grid):
    _, Q = grid
    model = _mixture(combiner="bcm", gating_threshold=0.0).fit(paper.X, paper.y)
    # Queries beyond the reach of every expert get the prior.
    far = as_segments([[1e3, 1e3], [-50.0, 0.0]])
    np.testing.assert_allclose(model.predict_proba(far)[:, 1], 0.5)
    np.testing.assert_allclose(model.predict_var(far), model.shared_kernel_.diag(far))
    assert np.all(_consulted_weights(model, Q).sum(axis=1) > 0)
    for combiner, expected in _combined_by_hand(model, Q, COMBINERS).items():
        model.set_params(combiner=combiner)
        np.testing.assert_allclose(model.predict_proba(Q)[:, 1], expected.proba, rtol=1e-12)
        np.testing.assert_allclose(model.predict_var(Q), expected.variance, rtol=1e-12)


def test_share_hyperparameters_learns_once():
    data = make_paper_scans(random_state=0)
    # The signal variance fixed: on separable data the evidence keeps growing with it.
    expert = GaussianProcessClassifier(C(4.0, "fixed") * RBF(1.0))
    # The experts of the paper's rule, on which the kernel is learned (with nearest-hit
    # pieces too: test_nearest_hit_experts_learn_their_kernel_on_whole_beams).
    model = _mixture(expert=expert, share_hyperparameters=True, piece_assignment="beam")
    model.fit(data.X, data.y)
    learned = model.shared_kernel_
    assert learned != expert.kernel  # it did learn
    fitted = [e for e in model.experts_ if not isinstance(e, _ConstantExpert)]
    assert fitted
    for e in fitted:
        assert e.kernel_ == learned
        assert e.optimizer is None
    # The paper's data give fewer two-class experts than the pieces the sum may use, so
    # the learned kernel is a stationary point of the summed evidence of all of them.
    total = np.zeros_like(learned.theta)
    for e in fitted:
        total += e.log_marginal_likelihood(learned.theta, eval_gradient=True)[1]
    bounds = learned.bounds
    interior = (learned.theta > bounds[:, 0] + 1e-3) & (learned.theta < bounds[:, 1] - 1e-3)
    assert interior.any()
    scale = sum(abs(e.log_marginal_likelihood_value_) for e in fitted)
    assert np.all(np.abs(total[interior]) < 1e-3 * scale)
    # ... and not the optimum of one expert alone.
    pieces, source = _beam_pieces(data.X, data.kind, model.max_beam_length, model.beam_end_length)
    rows = model.cluster_labels_[source] == np.argmax(np.bincount(model.cluster_labels_))
    own = clone(expert).fit(pieces[rows], data.y[source][rows]).kernel_
    assert not np.allclose(own.theta, learned.theta, atol=1e-2)


def test_hyperparameter_window_learns_on_windows(paper, monkeypatch):
    import skoccmap.mixture as mixture_module
    from skoccmap._shared_kernel import learn_shared_kernel, window_pieces

    seen = {}

    def recording(points, y, **kwargs):
        seen["pieces"] = window_pieces(points, y, **kwargs)
        seen["radius"] = kwargs["radius"]
        seen["max_rows"] = kwargs["max_rows"]
        return seen["pieces"]

    monkeypatch.setattr(mixture_module, "window_pieces", recording)
    expert = GaussianProcessClassifier(C(4.0, "fixed") * RBF(1.0))
    model = _mixture(
        expert=expert, hyperparameter_window=2.5, max_expert_size=150, share_hyperparameters=True
    ).fit(paper.X, paper.y)
    assert seen["radius"] == 2.5 and seen["max_rows"] == 150
    assert seen["pieces"] and all(p.size <= 150 for p in seen["pieces"])
    # The learned kernel is the summed-evidence optimum of exactly those windows.
    pieces, source = _beam_pieces(
        paper.X, paper.kind, model.max_beam_length, model.beam_end_length
    )
    y = paper.y[source]
    expected = learn_shared_kernel(expert, [(pieces[p], y[p]) for p in seen["pieces"]])
    np.testing.assert_allclose(model.shared_kernel_.theta, expected.theta, atol=1e-4)
    default = _mixture(expert=expert, share_hyperparameters=True).fit(paper.X, paper.y)
    assert not np.allclose(default.shared_kernel_.theta, model.shared_kernel_.theta, atol=1e-3)


def test_shared_kernel_is_learned_on_its_own_beam_cut(paper):
    # The evidence of cut beams depends on how finely they are cut, so the shared kernel is
    # learned on beams cut at hyperparameter_beam_length whatever the experts' bound: 2 m
    # pieces learn exactly what 1 m pieces learn (the clusters, and so the learning
    # groups, are the same; the paper's data give fewer groups than the learner draws).
    expert = GaussianProcessClassifier(C(4.0, "fixed") * RBF(1.0))
    one = _mixture(expert=expert, share_hyperparameters=True, max_beam_length=1.0)
    one.fit(paper.X, paper.y)
    assert one._learning is None  # the experts' own pieces
    two = _mixture(expert=expert, share_hyperparameters=True, max_beam_length=2.0)
    two.fit(paper.X, paper.y)
    pieces, y, _ = two._learning
    assert pieces.shape[0] == one._pieces.shape[0] > two._pieces.shape[0]
    np.testing.assert_array_equal(pieces, one._pieces)
    np.testing.assert_array_equal(y, one._piece_y)
    np.testing.assert_allclose(two.shared_kernel_.theta, one.shared_kernel_.theta, rtol=1e-10)
    own = _mixture(
        expert=expert,
        share_hyperparameters=True,
        max_beam_length=2.0,
        hyperparameter_beam_length=None,
    ).fit(paper.X, paper.y)
    assert own._learning is None
    assert not np.allclose(own.shared_kernel_.theta, one.shared_kernel_.theta, atol=1e-3)
    # partial_fit keeps the learning cut up to date: a re-learn on all rows learns what
    # the 1 m pieces of the same batches learn.
    half = paper.X.shape[0] // 2
    for model in (one, two):
        model.fit(paper.X[:half], paper.y[:half])
        model.partial_fit(paper.X[half:], paper.y[half:])
        model.refit_hyperparameters()
    np.testing.assert_array_equal(two._learning[0], one._pieces)
    np.testing.assert_allclose(two.shared_kernel_.theta, one.shared_kernel_.theta, rtol=1e-10)


def test_share_hyperparameters_needs_kernel_param(paper):
    model = _mixture(expert=_NoKernelExpert(), share_hyperparameters=True)
    with pytest.raises(ValueError, match="share_hyperparameters"):
        model.fit(paper.X, paper.y)


class _NoKernelExpert(GaussianProcessClassifier):
    def get_params(self, deep=True):
        return {}


# --- prediction -------------------------------------------------------------------------


def test_chunked_prediction_equals_one_chunk(paper, grid):
    from sklearn import config_context

    _, Q = grid
    model = _mixture().fit(paper.X, paper.y)
    whole = model.predict_proba(Q)
    with config_context(working_memory=0.05):  # a few hundred rows per chunk
        chunked = model.predict_proba(Q)
    # Equal up to the summation order of BLAS blocks.
    np.testing.assert_allclose(whole, chunked, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("gating", ["coverage", "clusterer", "gpc"])
def test_every_combiner_gives_a_valid_map(paper, grid, gating):
    occupied, Q = grid
    model = _mixture(gating=gating).fit(paper.X, paper.y)
    for combiner in COMBINERS:
        model.set_params(combiner=combiner)  # used at prediction only
        proba = model.predict_proba(Q)
        mean, var = model.latent_mean_and_variance(Q)
        assert np.all(np.isfinite(proba)) and np.all((proba >= 0) & (proba <= 1))
        np.testing.assert_allclose(proba.sum(axis=1), 1.0)
        assert np.all(np.isfinite(mean)) and np.all(var > 0)
        np.testing.assert_array_equal(model.predict_var(Q), var)
        auc = roc_auc_score(occupied, proba[:, 1])
        assert auc > 0.8, (combiner, auc)


def test_labels_are_any_two_classes(paper, grid):
    _, Q = grid
    label_names = np.array(["free", "occupied"])
    model = _mixture().fit(paper.X, label_names[paper.y])
    ref = _mixture().fit(paper.X, paper.y)
    np.testing.assert_array_equal(model.classes_, label_names)
    np.testing.assert_array_equal(model.predict(Q), label_names[ref.predict(Q)])
    # The larger label is the occupied one, as documented: labels that give it to the
    # beams and the smaller one to the hits would draw an inverted map.
    for reversed_labels, occupied in (
        (5 - 4 * paper.y, "5"),
        (np.array(["hit", "miss"])[1 - paper.y], "'miss'"),
    ):
        # The labels as written, not numpy's reprs (np.int64(5), np.str_('miss')).
        with pytest.raises(ValueError, match=rf"labelled occupied \(y == {occupied}, the"):
            _mixture().fit(paper.X, reversed_labels)
        with pytest.raises(ValueError, match="labels look reversed"):
            _mixture().partial_fit(paper.X, reversed_labels)


def test_occupied_rows_with_a_length_warn(paper):
    # 2-D points read as 1-D segments: the hits' two coordinates differ.
    hits = paper.X[paper.y == 1, :2]
    free = 0.5 * (paper.X[paper.y == 0, :2] + paper.X[paper.y == 0, 2:])
    P, yp = np.vstack([hits, free]), np.r_[np.ones(len(hits)), np.zeros(len(free))]
    with pytest.warns(UserWarning, match="layout='points'"):
        _mixture().fit(P, yp)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        _mixture(layout="points").fit(P, yp)
    # In 2-D: occupied surface segments (a hit joined to the next), free rows beams.
    X = paper.X.copy()
    X[paper.y == 1, 2:] = np.roll(X[paper.y == 1, :2], 1, axis=0)
    with pytest.warns(UserWarning, match="Most rows labelled occupied") as record:
        _mixture().fit(X, paper.y)
    assert not any("layout='points'" in str(w.message) for w in record)


def test_columns_scaled_each_on_its_own_are_named_in_the_warning(paper):
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    # A scaler in a pipeline scales the start and end columns apart: hits stop being points.
    pipeline = make_pipeline(StandardScaler(), _mixture())
    with pytest.warns(UserWarning, match="Most rows.*StandardScaler in a pipeline") as record:
        pipeline.fit(paper.X, paper.y)
    assert not any("layout='points'" in str(w.message) for w in record)


def test_float32_coordinates_coarser_than_a_centimetre_warn(paper):
    from skoccmap._validation import warn_if_coarse_float32

    # float32 steps by 2**-7 m below 131 072 m and by 2**-6 m from there on.
    for largest, warns in [(131071.0, False), (131072.0, True)]:
        X = np.array([[0.0, 0.0, largest, 0.0]], dtype=np.float32)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            warn_if_coarse_float32(X, X.astype(np.float64))
            warn_if_coarse_float32(X.astype(np.float64), X.astype(np.float64))
        assert len(caught) == warns
    # UTM-like offsets in float32: the rows are rounded to 0.25 m before any cast.
    utm = (paper.X + [5e5, 4e6, 5e5, 4e6]).astype(np.float32)
    match = "float32 steps are 0.25 m: the map cannot be finer"
    with pytest.warns(UserWarning, match=match):
        _mixture().fit(utm, paper.y)
    model = MixtureGPOccupancyMap(random_state=0)
    for rows in (slice(0, 400), slice(400, None)):  # the first call and a later one
        with pytest.warns(UserWarning, match=match):
            model.partial_fit(utm[rows], paper.y[rows], classes=[0, 1])
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        _mixture().fit(paper.X.astype(np.float32), paper.y)


def test_hits_warn_only_when_most_of_them_have_a_length():
    from skoccmap.mixture import _check_hits_are_points

    # Four occupied rows beside two beams: "most" is more than half of the occupied rows.
    beams = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    occupied = np.r_[False, False, True, True, True, True]
    for n_long, warns in [(2, False), (3, True)]:
        hits = np.tile([2.0, 2.0, 2.0, 2.0], (4, 1))
        hits[:n_long, 2] += 0.5
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _check_hits_are_points(np.vstack([beams, hits]), occupied, np.array([0, 1]))
        assert any("Most rows labelled occupied" in str(w.message) for w in caught) == warns


def test_verbose_reports_progress(paper, capsys):
    _mixture(verbose=2, max_expert_size=100).fit(paper.X, paper.y)
    out = capsys.readouterr().out
    assert "clustering" in out and "expert(s) fitted" in out and "split" in out
    assert "hits left out as transient" in out


# --- bad input ------------------------------------------------------------------------


def test_bad_input_raises_clear_errors(paper):
    model = _mixture()
    with pytest.raises(ValueError, match="3 feature"):
        model.fit(np.zeros((10, 3)), np.r_[np.zeros(5), np.ones(5)])
    # One class is no multi-class problem: the message starts with what is missing.
    with pytest.raises(ValueError, match=r"^MixtureGPOccupancyMap needs y with exactly 2 class"):
        model.fit(paper.X, np.ones(paper.X.shape[0]))
    with pytest.raises(ValueError, match="^Only binary classification.*got 3 class"):
        model.fit(paper.X, np.arange(paper.X.shape[0]) % 3)
    X = paper.X.copy()
    X[0, 0] = np.nan
    # Not scikit-learn's advice to impute or to use HistGradientBoosting.
    occupancy_words = "Observations must be finite: drop those rows.*scans_to_observations"
    for fit in (model.fit, MixtureGPOccupancyMap().partial_fit):
        with pytest.raises(ValueError, match=f"contains NaN. {occupancy_words}") as info:
            fit(X, paper.y)
        assert "impute" not in str(info.value)
    X[0, 0] = np.inf
    with pytest.raises(ValueError, match=f"contains infinity. {occupancy_words}"):
        model.fit(X, paper.y)
    one_hit = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.9, 0.0], [0.0, 0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="at least 2 of them, got 1"):
        MixtureGPOccupancyMap(random_state=0).fit(one_hit, [1, 0, 0])
    with pytest.raises(ValueError, match="'n_jobs' parameter"):
        MixtureGPOccupancyMap(n_jobs=0).fit(paper.X, paper.y)
    # A beam reaching 1e160: overflow warnings from the no-return assignment, then an
    # OverflowError from cutting it into pieces; on the next batch, the same.
    far_beam = np.r_[paper.X, [[0.0, 0.0, 1e160, 0.0]]]
    far_y = np.r_[paper.y, 0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=r"up to 1e\+160.*Rescale or shift"):
            _mixture().fit(far_beam, far_y)
    model.fit(paper.X, paper.y)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=r"up to 1e\+160.*Rescale or shift"):
            model.partial_fit(far_beam[-5:], far_y[-5:])
    # A failed range read as 1e8 m: a billion cells for the transient hits' counts.
    failed_range = np.r_[paper.X, [[0.0, 0.0, 1e8, 0.0]]]
    with pytest.raises(ValueError, match="crosses 1,000,000,001 grid cells.*Drop such rows"):
        _mixture().fit(failed_range, far_y)
    with pytest.raises(ValueError, match="crosses 1,000,000,001 grid cells"):
        model.partial_fit(failed_range[-5:], far_y[-5:])
    with pytest.raises(ValueError, match="contains NaN. Observations must be finite"):
        model.partial_fit(X[:5] * np.nan, paper.y[:5])
    with pytest.raises(ValueError, match="contains infinity. Query points must be finite"):
        model.predict_proba(np.full((1, 4), np.inf))
    # SciPy's "floating point overflow" from the spatial index (with the default expert,
    # for a point that far as well), or the combiner's "prior_variance must be positive".
    for far in ([[0.0, 0.0, 1e160, 0.0]], [[1e160, 0.0, 1e160, 0.0]]):
        for predict in (model.predict_proba, model.predict_var):
            with pytest.raises(ValueError, match=r"up to 1e\+160.*Rescale or shift"):
                predict(np.array(far))
    with pytest.raises(ValueError, match="features"):
        model.predict(np.zeros((3, 6)))
    with pytest.raises(ValueError, match="combiner"):
        _mixture(combiner="mean").fit(paper.X, paper.y)


def test_two_hits_are_enough_to_map():
    # The fewest hits the default clusterer takes: two hits and the beams to them.
    X = np.array(
        [
            [1.0, 0.0, 1.0, 0.0],
            [0.0, 1.0, 0.0, 1.0],
            [0.0, 0.0, 0.95, 0.0],
            [0.0, 0.0, 0.0, 0.95],
        ]
    )
    model = MixtureGPOccupancyMap(random_state=0).fit(X, [1, 1, 0, 0])
    p = model.predict_proba(np.array([[1.0, 0.0, 1.0, 0.0], [0.3, 0.0, 0.3, 0.0]]))[:, 1]
    assert p[0] > 0.5 > p[1]


# --- reproducibility and sklearn integration ----------------------------------------------


def test_same_result_for_n_jobs_and_after_pickle(paper, grid):
    _, Q = grid
    one = _mixture(n_jobs=1).fit(paper.X, paper.y)
    two = _mixture(n_jobs=2).fit(paper.X, paper.y)
    p1 = one.predict_proba(Q)
    np.testing.assert_array_equal(p1, two.predict_proba(Q))
    np.testing.assert_array_equal(one.cluster_labels_, two.cluster_labels_)
    again = pickle.loads(pickle.dumps(one))
    np.testing.assert_array_equal(p1, again.predict_proba(Q))
    np.testing.assert_array_equal(one.predict_var(Q), again.predict_var(Q))


def test_joint_proba_and_var_equal_the_separate_calls(paper, grid):
    _, Q = grid
    model = _mixture(combiner="rbcm").fit(paper.X, paper.y)
    proba, var = model._predict_proba_and_var(Q)
    np.testing.assert_array_equal(proba, model.predict_proba(Q)[:, 1])
    np.testing.assert_array_equal(var, model.predict_var(Q))


def test_pipeline_and_grid_search(paper):
    pipe = make_pipeline(FunctionTransformer(), _mixture(max_expert_size=150))
    search = GridSearchCV(
        pipe,
        {
            "mixturegpoccupancymap__combiner": ["moe", "rbcm"],
            "mixturegpoccupancymap__expert__kernel__k2__length_scale": [0.5, 2.0],
        },
        cv=3,
        scoring="roc_auc",
    )
    search.fit(paper.X, paper.y)
    assert len(search.cv_results_["params"]) == 4
    assert np.all(np.isfinite(search.cv_results_["mean_test_score"]))
    best = search.best_estimator_[-1]
    assert (
        best.expert.kernel.k2.length_scale
        == search.best_params_["mixturegpoccupancymap__expert__kernel__k2__length_scale"]
    )


@pytest.mark.slow  # starting a LocalCluster of 2 processes takes ~15 s here
def test_dask_backend_matches_local(paper, grid):
    distributed = pytest.importorskip("distributed")
    from joblib import parallel_config

    _, Q = grid
    local = _mixture(n_jobs=1).fit(paper.X, paper.y).predict_proba(Q)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        with distributed.get_task_stream(client) as stream, parallel_config(backend="dask"):
            model = _mixture(n_jobs=2).fit(paper.X, paper.y)
        # The experts ran as tasks on the workers.
        assert len(stream.data) > 0
    np.testing.assert_array_equal(model.predict_proba(Q), local)


# --- the package's defaults on simulated scans ----------------------------------------------


@pytest.fixture(scope="module")
def default_model(paper):
    return MixtureGPOccupancyMap(random_state=0).fit(paper.X, paper.y)


def test_default_expert_ep_tolerance_moves_the_map_by_under_1e_3(default_model, paper, grid):
    # The default experts stop EP at 1e-4 of a site's marginal: against experts run to
    # 1e-9, with fewer sweeps, and the map within 1e-3 (EP at 1e-2 moves it by ~1e-2).
    from skoccmap import EPGaussianProcessClassifier

    _, Q = grid
    experts = [e for e in default_model.experts_ if hasattr(e, "n_iter_")]
    assert experts and all(e.tol == 1e-4 for e in experts)
    tight_expert = EPGaussianProcessClassifier(kernel=_default_kernel(), tol=1e-9)
    tight = MixtureGPOccupancyMap(expert=tight_expert, random_state=0).fit(paper.X, paper.y)
    assert tight.n_experts_ == default_model.n_experts_
    sweeps = [np.sum([e.n_iter_ for e in m.experts_ if hasattr(e, "n_iter_")])
              for m in (default_model, tight)]  # fmt: skip
    assert sweeps[0] < sweeps[1]
    np.testing.assert_allclose(
        default_model.predict_proba(Q), tight.predict_proba(Q), rtol=0, atol=1e-3
    )


def test_an_expert_without_a_kernel_keeps_the_integral_kernel(default_model, paper, grid):
    # EP given for its settings alone fitted an RBF over [start, end] as one 4-D point.
    from skoccmap import EPGaussianProcessClassifier

    _, Q = grid
    expert = EPGaussianProcessClassifier(tol=1e-4)  # the default expert's tolerance
    model = MixtureGPOccupancyMap(expert=expert, random_state=0).fit(paper.X, paper.y)
    assert model.expert is expert and expert.kernel is None
    assert model.shared_kernel_ == default_model.shared_kernel_
    np.testing.assert_array_equal(model.predict_proba(Q), default_model.predict_proba(Q))


@pytest.mark.parametrize("combiner", sorted(COMBINERS))
def test_defaults_map_the_paper_scans(default_model, grid, combiner):
    occupied, Q = grid
    # The combiner acts at prediction only: switching it on the fitted model is enough.
    model = default_model.set_params(combiner=combiner)
    proba = model.predict_proba(Q)[:, 1]
    var = model.predict_var(Q)
    assert np.all((proba >= 0) & (proba <= 1)) and not np.any(np.isnan(proba))
    assert np.all(var > 0) and np.all(np.isfinite(var))
    assert roc_auc_score(occupied, proba) > 0.95


@pytest.mark.slow  # the single EP GP on all ~700 observations takes minutes here
@pytest.mark.parametrize("share", [False, True])
def test_mixture_auc_within_001_of_single_gp(paper, share):
    from skoccmap import EPGaussianProcessClassifier

    g = paper.environment.ground_truth_grid(0.2, scans=paper.scans)
    Q = as_segments(g.points[g.observed])
    truth = g.occupied[g.observed]
    single = EPGaussianProcessClassifier(kernel=_default_kernel()).fit(paper.X, paper.y)
    mixture = MixtureGPOccupancyMap(share_hyperparameters=share, random_state=0)
    mixture.fit(paper.X, paper.y)
    auc_single = roc_auc_score(truth, single.predict_proba(Q)[:, 1])
    auc_mixture = roc_auc_score(truth, mixture.predict_proba(Q)[:, 1])
    assert auc_mixture >= auc_single - 0.01, (auc_mixture, auc_single)


def test_maps_a_3d_scan():
    from skoccmap.datasets import make_room3d_scans

    data = make_room3d_scans(random_state=0)
    g = data.environment.ground_truth_grid(0.5, scans=data.scans)
    Q = as_segments(g.points[g.observed])
    model = MixtureGPOccupancyMap(random_state=0).fit(data.X, data.y)
    np.testing.assert_array_equal(model.observation_kind_, data.kind)
    proba = model.predict_proba(Q)[:, 1]
    assert np.all(model.predict_var(Q) > 0)
    assert roc_auc_score(g.occupied[g.observed], proba) > 0.85


@pytest.mark.slow  # runs all of check_estimator once more (~1-3 min)
def test_segments_layout_fails_exactly_the_documented_checks():
    # tests/test_common.py runs the checks on layout="points", where every column count is
    # valid. The default layout reads rows as segments: the checks it fails are the public
    # table of skoccmap.estimator_checks: the documented odd-column ValueError, and the
    # training score of blobs read as segments with nearest-hit pieces.
    from sklearn.utils.estimator_checks import check_estimator

    from skoccmap.estimator_checks import NEAREST_HIT_FAILURES, expected_failed_checks

    table = expected_failed_checks(MixtureGPOccupancyMap())
    results = check_estimator(MixtureGPOccupancyMap(), on_fail=None)
    failed = [r for r in results if r["status"] == "failed"]
    assert {r["check_name"] for r in failed} == set(table)
    for r in failed:
        if r["check_name"] in NEAREST_HIT_FAILURES:
            assert isinstance(r["exception"], AssertionError), r["check_name"]
            continue
        assert isinstance(r["exception"], ValueError), r["check_name"]
        assert "even number of columns" in str(r["exception"]), r["check_name"]
    # With the table, check_estimator passes (expected failures are xfailed, not raised).
    check_estimator(MixtureGPOccupancyMap(), expected_failed_checks=table)


@pytest.mark.parametrize("n_jobs", [1, 2])
def test_expert_warnings_reach_the_caller(paper, n_jobs):
    # Warnings raised in joblib worker processes are lost unless passed back.
    from sklearn.exceptions import ConvergenceWarning

    from skoccmap import EPGaussianProcessClassifier

    expert = EPGaussianProcessClassifier(C(4.0) * RBF(1.0), optimizer=None, max_iter=1)
    model = _mixture(expert=expert, share_hyperparameters=False, n_jobs=n_jobs)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(paper.X, paper.y)
    messages = [str(w.message) for w in caught if w.category is ConvergenceWarning]
    # Every EP expert stops at max_iter=1; their messages differ only in the residual, so
    # the caller sees one warning that counts them.
    n_ep = sum(not isinstance(e, _ConstantExpert) for e in model.experts_)
    assert n_ep >= 2
    assert len(messages) == 1
    assert messages[0].startswith(f"{n_ep} of {model.n_experts_} expert(s): ")
    assert "max_iter" in messages[0]


def test_expert_warnings_in_threads_are_not_recorded(paper):
    # catch_warnings is process-wide: in a thread the expert warns as usual instead of
    # recording (and racing with other threads on the warning filters).
    import threading

    from sklearn.exceptions import ConvergenceWarning

    from skoccmap import EPGaussianProcessClassifier

    expert = EPGaussianProcessClassifier(C(4.0) * RBF(1.0), optimizer=None, max_iter=1)
    out = []
    worker = threading.Thread(
        target=lambda: out.append(_fit_expert(expert, paper.X[:200], paper.y[:200]))
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        worker.start()
        worker.join()
    assert out and out[0][1] == []
    assert any(w.category is ConvergenceWarning for w in caught)


def test_expert_warnings_are_counted_once_per_expert_and_kind():
    from sklearn.exceptions import ConvergenceWarning

    caught = [
        # One expert warning twice of one kind (numbers of any width) counts once.
        [
            (ConvergenceWarning, "EP stopped after 7 sweeps (residual 0.0012)"),
            (ConvergenceWarning, "EP stopped after 120 sweeps (residual 3.5e-05)"),
        ],
        [(ConvergenceWarning, "EP stopped after 15 sweeps (residual -2e+3)")],
        [],
        # Another category is another kind.
        [(UserWarning, "EP stopped after 7 sweeps (residual 0.0012)")],
    ]
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        _warn_once_each(caught, 5)
    assert [(w.category, str(w.message)) for w in got] == [
        (ConvergenceWarning, "2 of 5 expert(s): EP stopped after 7 sweeps (residual 0.0012)"),
        (UserWarning, "1 of 5 expert(s): EP stopped after 7 sweeps (residual 0.0012)"),
    ]


def test_warnings_of_fit_and_partial_fit_name_the_callers_line(paper):
    # The experts' warnings, passed back and counted, and the shared kernel's: each names
    # the line that called fit or partial_fit (as the package's other warnings do), not a
    # line of the mixture's own code.
    from sklearn.exceptions import ConvergenceWarning

    from skoccmap import EPGaussianProcessClassifier

    expert = EPGaussianProcessClassifier(C(4.0) * RBF(1.0), optimizer=None, max_iter=1)
    model = _mixture(expert=expert, share_hyperparameters=False)
    for fit in (model.fit, model.partial_fit):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fit(paper.X, paper.y)
        counted = [w for w in caught if "expert(s): " in str(w.message)]
        assert counted and {w.filename for w in counted} == {__file__}
    at_bound = GaussianProcessClassifier(C(1.0, (1e-2, 2.0)) * RBF(1.0, (1e-2, 1e2)))
    with pytest.warns(ConvergenceWarning, match="shared kernel hyperparameter") as caught:
        _mixture(expert=at_bound).fit(paper.X, paper.y)
    shared = [w for w in caught if "shared kernel" in str(w.message)]
    assert {w.filename for w in shared} == {__file__}


@pytest.mark.parametrize(
    "kernel, expected",
    [
        (IntegralKernel(0.5), [0.5]),
        (C(2.0) * IntegralKernel([0.3, 0.7]), [0.3, 0.7]),
        (RBF([1.0, 2.0, 3.0, 0.5]), [3.0, 2.0]),  # per segment column: max of start, end
        (C(1.0), [1.0]),
    ],
)
def test_similarity_length_scale(kernel, expected):
    np.testing.assert_allclose(np.atleast_1d(_similarity_length_scale(kernel, 2)), expected)


def _expert_pieces(model, pieces):
    """Expert of every piece, read from the experts' own training rows."""
    labels = np.full(pieces.shape[0], -1)
    index = {}
    for i, row in enumerate(pieces):
        index.setdefault(row.tobytes(), []).append(i)
    for k, expert in enumerate(model.experts_):
        if isinstance(expert, _ConstantExpert):
            continue
        # Equal pieces (repeated hits) are told apart by order only.
        labels[[index[row.tobytes()].pop() for row in expert.base_estimator_.X_train_]] = k
    return labels


def test_beams_are_cut_into_pieces_that_stay_with_their_beam(paper):
    model = _mixture(max_beam_length=1.0, beam_end_length=0.25, piece_assignment="beam")
    model.fit(paper.X, paper.y)
    pieces, source = _beam_pieces(paper.X, paper.kind, 1.0, 0.25)
    labels = model.cluster_labels_[source]
    assert pieces.shape[0] > paper.X.shape[0]
    for k, expert in enumerate(model.experts_):
        if isinstance(expert, _ConstantExpert):
            continue
        X_train = expert.base_estimator_.X_train_
        # The expert holds exactly the pieces of its rows.
        np.testing.assert_array_equal(X_train, pieces[labels == k])


def test_pieces_join_the_expert_of_the_hit_nearest_to_them(paper):
    model = _mixture(max_beam_length=1.0, beam_end_length=0.25).fit(paper.X, paper.y)
    assert model.piece_assignment == "nearest_hit"
    pieces, source = _beam_pieces(paper.X, paper.kind, 1.0, 0.25)
    labels = _expert_pieces(model, pieces)
    assert np.all(labels >= 0)
    hits = paper.X[paper.y == 1, :2]
    hit_labels = model.cluster_labels_[paper.y == 1]
    # Each free piece's nearest hit, by brute force, within 2 m (nearest_hit_radius); a
    # piece further out stays with its row's anchor, and hits keep their own expert.
    mids = 0.5 * (pieces[:, :2] + pieces[:, 2:])
    dist2 = ((mids[:, None, :] - hits[None]) ** 2).sum(axis=-1)
    nearest, near = np.argmin(dist2, axis=1), dist2.min(axis=1) <= 2.0**2
    is_hit = paper.y[source] == 1
    assert np.any(~near) and np.mean(near[~is_hit]) > 0.5
    expected = np.where(near, hit_labels[nearest], model.cluster_labels_[source])
    np.testing.assert_array_equal(labels[~is_hit], expected[~is_hit])
    np.testing.assert_array_equal(labels[is_hit], model.cluster_labels_[source[is_hit]])
    # The beams' pieces spread over several experts, and each expert's pieces lie closer
    # together than under the beam rule.
    assert np.any([np.unique(labels[source == r]).size > 1 for r in np.unique(source)])
    beam = _mixture(max_beam_length=1.0, beam_end_length=0.25, piece_assignment="beam")
    beam_labels = beam.fit(paper.X, paper.y).cluster_labels_[source]

    def spread(lab):
        return np.mean([mids[lab == k].std(axis=0).sum() for k in np.unique(lab)])

    assert spread(labels) < spread(beam_labels)


def test_a_hit_takes_at_most_half_an_expert_of_nearest_pieces(paper):
    model = _mixture(max_expert_size=40).fit(paper.X, paper.y)
    pieces, source = _beam_pieces(paper.X, model.observation_kind_, 1.0, 0.35)
    free = paper.y[source] == 0
    hits = paper.X[paper.y == 1, :2]
    mids = 0.5 * (pieces[free, :2] + pieces[free, 2:])
    dist2 = ((mids[:, None, :] - hits[None]) ** 2).sum(axis=-1)
    nearest = np.where(dist2.min(axis=1) <= 4.0, np.argmin(dist2, axis=1), -1)
    # Without the bound some hit would take more than 20 pieces by nearness ...
    assert np.bincount(nearest[nearest >= 0]).max() > 20
    # ... with it, no hit takes more than 20 pieces beyond those of its own beams.
    chosen = model._piece_hit[free]
    moved = chosen != model._piece_beam_hit[free]
    load = np.bincount(chosen[moved], minlength=len(hits))
    assert load.max() <= 20
    # A moved piece went to the nearest hit with room: every nearer hit is full. (Pieces
    # within 2 m of their own beam's hit may hold it by nearness or by their beam: counted.)
    rows = np.flatnonzero(moved)
    held = np.bincount(chosen[dist2[np.arange(chosen.size), chosen] <= 4.0], minlength=len(hits))
    nearer = dist2[rows] < dist2[rows, chosen[moved]][:, None]
    assert np.all(~nearer | (held[None, :] >= 20))
    # Pieces overflow to further hits (not back to their beams) where the nearest is full.
    assert np.any(chosen[moved] != np.argmin(dist2[rows], axis=1))


def _greedy_nearest_with_room(points, hits, radius, cap, rounds):
    """Brute force of the rounds: the j-th choices of the unplaced points, nearest first
    (equally near ones in point order)."""
    dist = np.sqrt(((points[:, None] - hits[None]) ** 2).sum(axis=-1))
    order = np.argsort(dist, axis=1)
    expected, load = np.full(len(points), -1), np.zeros(len(hits), dtype=int)
    for j in range(min(rounds, len(hits))):
        asking = [
            i for i in range(len(points)) if expected[i] < 0 and dist[i, order[i, j]] <= radius
        ]
        for i in sorted(asking, key=lambda i: (order[i, j], dist[i, order[i, j]])):
            if load[order[i, j]] < cap:
                expected[i] = order[i, j]
                load[order[i, j]] += 1
    return expected, order


def test_nearest_with_room_matches_a_greedy_assignment():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    points, hits = rng.random((300, 2)), rng.random((12, 2))
    chosen = _nearest_with_room(cKDTree(hits), points, 0.5, cap=15, rounds=4)
    expected, order = _greedy_nearest_with_room(points, hits, 0.5, 15, 4)
    np.testing.assert_array_equal(chosen, expected)
    assert np.bincount(chosen[chosen >= 0]).max() == 15 and np.any(chosen < 0)
    assert np.any(chosen != order[:, 0])


def test_nearest_with_room_asks_up_to_the_last_hit():
    # As many rounds as hits, each with room for one point: one point is left to take its
    # farthest hit in the last round.
    from scipy.spatial import cKDTree

    points = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0]])
    hits = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    chosen = _nearest_with_room(cKDTree(hits), points, 5.0, cap=1, rounds=3)
    expected, _ = _greedy_nearest_with_room(points, hits, 5.0, 1, 3)
    np.testing.assert_array_equal(chosen, expected)
    assert sorted(chosen.tolist()) == [0, 1, 2]


def test_nearest_with_room_gives_equally_near_askers_room_in_point_order():
    # Hits B, A, C at x = 3, -3, 0, with room for one point each. Points at B and A take
    # them in round 1; p (x = -2, nearest A) and q (x = 2, nearest B) then ask C, 2 m from
    # both, in round 2: the first point in order, p, takes it.
    from scipy.spatial import cKDTree

    hits = np.array([[3.0, 0.0], [-3.0, 0.0], [0.0, 0.0]])
    points = np.array([[3.0, 0.0], [-3.0, 0.0], [-2.0, 0.0], [2.0, 0.0]])
    chosen = _nearest_with_room(cKDTree(hits), points, 10.0, cap=1, rounds=3)
    expected, _ = _greedy_nearest_with_room(points, hits, 10.0, 1, 3)
    np.testing.assert_array_equal(chosen, expected)
    assert chosen.tolist() == [0, 1, 2, -1]


def test_free_pieces_follow_the_nearest_hit_whatever_its_index():
    # Hit 0 at the origin and hit 1 at (4, 0); a beam to hit 1 passes 0.4 m from hit 0. Its
    # pieces follow the hit nearest to their midpoint (within nearest_hit_radius=2), hit 0
    # for those at its end of the beam.
    X = np.array(
        [
            [0.0, 0.0, 0.0, 0.0],
            [4.0, 0.0, 4.0, 0.0],
            [-1.0, 0.5, 3.95, 0.0],
            [4.0, -3.0, 4.0, -0.05],
        ]
    )
    y = np.array([1, 1, 0, 0])
    model = MixtureGPOccupancyMap(min_hit_frequency=None, random_state=0).fit(X, y)
    free = model._piece_y == 0
    pieces = model._pieces[free]
    mids = 0.5 * (pieces[:, :2] + pieces[:, 2:])
    dist = np.linalg.norm(mids[:, None] - X[None, :2, :2], axis=-1)
    expected = np.where(dist.min(axis=1) <= 2.0, dist.argmin(axis=1), 1)
    assert np.any(expected == 0) and np.any(expected == 1)
    np.testing.assert_array_equal(model._piece_hit[free], expected)


def test_nearest_hit_experts_learn_their_kernel_on_whole_beams(paper):
    # The shared kernel is learned on the experts the paper's rule would make: every piece of
    # a beam in one group, groups of at most max_expert_size pieces, every piece in one.
    model = MixtureGPOccupancyMap(
        max_expert_size=150, max_pieces_per_cell=None, random_state=0
    ).fit(paper.X, paper.y)
    pieces, source = _beam_pieces(paper.X, model.observation_kind_, 1.0, 0.35)
    groups = model._hyperparameter_groups(None)
    group_of = np.full(pieces.shape[0], -1)
    for g, rows in enumerate(groups):
        assert np.all(group_of[rows] == -1)
        group_of[rows] = g
    assert np.all(group_of >= 0) and max(len(r) for r in groups) <= 150
    assert all(np.unique(group_of[source == r]).size == 1 for r in np.unique(source))
    # ... which the experts are not: their pieces follow the nearest hit.
    experts = _expert_pieces(model, pieces)
    assert any(np.unique(experts[source == r]).size > 1 for r in np.unique(source))


class _SideClusterer(BaseEstimator):
    """Hits left of x = 1 in one cluster, the others in another."""

    def fit(self, X):
        self.labels_ = self.predict(X)
        return self

    def predict(self, X):
        return (np.asarray(X)[:, 0] > 1.0).astype(int)


def test_shared_kernel_is_learned_on_groups_that_hold_both_classes(monkeypatch):
    import skoccmap.mixture as mixture_module

    seen = []
    learn = mixture_module.learn_shared_kernel

    def recording(learner, pieces, **kwargs):
        seen.extend(pieces)
        return learn(learner, pieces, **kwargs)

    monkeypatch.setattr(mixture_module, "learn_shared_kernel", recording)
    # Forty beams cross the cell [0, 0.1)^2 to a wall at x = 2; three hits in that cell
    # (a passer-by, left out as transient) are seen by three beams from below. The paper's
    # rule groups pieces by their beam's hit: the passer-by's cluster keeps its beams'
    # pieces, all free, as a group, which has no evidence to learn from.
    y_beam = np.linspace(0.01, 0.09, 40)
    wall = np.column_stack([np.full(40, 2.0), y_beam, np.full(40, 2.0), y_beam])
    beams = np.column_stack([np.full(40, -2.0), y_beam, np.full(40, 1.95), y_beam])
    passer = np.tile([0.05, 0.05, 0.05, 0.05], (3, 1))
    below = np.tile([0.05, -2.0, 0.05, 0.0], (3, 1))
    X = np.vstack([wall, beams, passer, below])
    y = np.r_[np.ones(40, int), np.zeros(40, int), np.ones(3, int), np.zeros(3, int)]
    model = MixtureGPOccupancyMap(
        _SideClusterer(),
        GaussianProcessClassifier(C(4.0, "fixed") * RBF(1.0)),
        min_expert_size=1,
        max_pieces_per_cell=None,
        random_state=0,
    ).fit(X, y)
    assert model.n_clusters_ == 2 and model.transient_hits_[80:83].all()
    assert seen and all(0 < labels.mean() < 1 for _, labels in seen)


def test_shared_hyperparameter_at_its_bound_warns(paper):
    from sklearn.exceptions import ConvergenceWarning

    # Occupancy data are nearly separable: the evidence keeps growing with the signal
    # variance, which then ends at a tight upper bound.
    expert = GaussianProcessClassifier(C(1.0, (1e-2, 2.0)) * RBF(1.0, (1e-2, 1e2)))
    with pytest.warns(ConvergenceWarning, match="shared kernel hyperparameter k1__constant"):
        model = _mixture(expert=expert).fit(paper.X, paper.y)
    np.testing.assert_allclose(model.shared_kernel_.k1.constant_value, 2.0, rtol=1e-2)


@pytest.mark.parametrize("length_scale, warns", [(1e4, True), (1.0, False)])
def test_shared_length_scale_beyond_the_data_warns(paper, length_scale, warns):
    from sklearn.exceptions import ConvergenceWarning

    # Far within its bounds, a length scale longer than the map makes it nearly constant.
    def optimizer(obj_func, initial_theta, bounds):
        theta = np.log([length_scale])
        return theta, obj_func(theta, eval_gradient=False)

    expert = GaussianProcessClassifier(
        C(1.0, "fixed") * RBF(1.0, (1e-2, 1e5)), optimizer=optimizer
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = _mixture(expert=expert).fit(paper.X, paper.y)
    assert model.shared_kernel_.k2.length_scale == pytest.approx(length_scale)
    beyond = [
        w
        for w in caught
        if w.category is ConvergenceWarning and "beyond the extent" in str(w.message)
    ]
    assert len(beyond) == int(warns)
    assert all(w.filename == __file__ for w in beyond)  # the caller's line


def test_reach_bounds_every_experts_own_kernel(paper):
    from sklearn.exceptions import ConvergenceWarning

    # Experts that learn their own kernels: beyond reach_ every one of them has fallen
    # below reach_tolerance of its peak, the one with the longest length scale included.
    expert = GaussianProcessClassifier(C(2.0, "fixed") * RBF(1.5, (0.05, 20.0)))
    model = _mixture(expert=expert, share_hyperparameters=False, max_expert_size=150)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # a few end at their bound
        model.fit(paper.X, paper.y)
    scales = {e.kernel_.k2.length_scale for e in model.experts_ if hasattr(e, "kernel_")}
    assert len(scales) > 1
    origin = np.zeros((1, 4))
    for e in model.experts_:
        for axis in (0, 1):
            at = np.zeros((1, 4))
            at[0, [axis, axis + 2]] = model.reach_
            ratio = e.kernel_(origin, at)[0, 0] / e.kernel_(origin)[0, 0]
            assert ratio <= model.reach_tolerance * (1 + 1e-6)


def test_beam_pieces_shrink_towards_hits_and_grow_away_from_the_sensor():
    X = np.array(
        [
            [0.0, 0.0, 82.0, 0.0],  # no-return beam to the 82 m maximum range
            [0.0, 0.0, 3.0, 0.0],  # return beam ...
            [3.05, 0.0, 3.05, 0.0],  # ... and its hit
        ]
    )
    kinds = np.array([NO_RETURN, RETURN, HIT])
    pieces, source = _beam_pieces(X, kinds, 1.0, 0.5)
    np.testing.assert_array_equal(source, [0] * 7 + [1] * 4 + [2])
    lengths = np.linalg.norm(pieces[:, 2:] - pieces[:, :2], axis=1)
    # No-return: 1, 2, 4, ... m from the sensor, the rest in one piece (7 rows, not 82).
    starts = pieces[source == 0, 0]
    np.testing.assert_allclose(np.sort(starts), [0, 1, 3, 7, 15, 31, 63])
    np.testing.assert_allclose(np.sort(lengths[source == 0]), [1, 2, 4, 8, 16, 19, 32])
    # Return: 0.5 m at the hit, the other 2.5 m in pieces of at most 1 m.
    np.testing.assert_allclose(np.sort(lengths[source == 1]), [0.5, 2.5 / 3, 2.5 / 3, 2.5 / 3])
    assert pieces[source == 1][:, 2].max() == pytest.approx(3.0)
    np.testing.assert_array_equal(pieces[source == 2], X[2:])
    # Pieces cover every beam exactly.
    for row in (0, 1):
        np.testing.assert_allclose(lengths[source == row].sum(), X[row, 2])
    # No bound: every row whole.
    pieces, source = _beam_pieces(X, kinds, None, None)
    np.testing.assert_array_equal(pieces, X)


def test_beam_pieces_keep_row_order_when_kinds_interleave():
    X = np.array(
        [
            [0.0, 0.0, 2.5, 0.0],
            [0.0, 0.0, 0.0, 9.0],
            [2.55, 0.0, 2.55, 0.0],
            [1.0, 1.0, 7.0, 1.0],
            [0.0, 0.0, -3.0, 0.0],
        ]
    )
    kinds = np.array([RETURN, NO_RETURN, HIT, NO_RETURN, RETURN])
    pieces, source = _beam_pieces(X, kinds, 1.0, 0.5)
    assert np.all(np.diff(source) >= 0)
    for row in range(len(X)):
        alone, _ = _beam_pieces(X[row : row + 1], kinds[row : row + 1], 1.0, 0.5)
        np.testing.assert_array_equal(pieces[source == row], alone)


def test_fixed_shared_kernel_at_a_bound_does_not_warn(paper):
    from sklearn.exceptions import ConvergenceWarning

    # Nothing is learned (optimizer=None): a starting value on a bound is no convergence issue.
    expert = GaussianProcessClassifier(C(2.0, (1e-2, 2.0)) * RBF(1.0), optimizer=None)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        _mixture(expert=expert).fit(paper.X, paper.y)


def test_a_length_scale_far_below_the_beams_fits_in_bounded_memory():
    # A fixed length scale of 0.1 mm on metre-long 3-D beam pieces: a reach of 0.3 mm. The
    # spatial index once sampled the pieces every reach / 8 and listed every cell's
    # stencil at once (tens of GiB); its grid is now bounded by the pieces' length.
    from skoccmap.classifier import EPGaussianProcessClassifier
    from skoccmap.datasets import make_room3d_scans

    data = make_room3d_scans(random_state=0, n_azimuths=12, n_elevations=4)
    kernel = C(1e3, "fixed") * IntegralKernel(1e-4, "fixed")
    model = MixtureGPOccupancyMap(
        expert=EPGaussianProcessClassifier(kernel=kernel), random_state=0
    ).fit(data.X, data.y)
    assert model.reach_ < 1e-3 < model._reach_index.scale
    assert len(model._reach_index.cell_expert) <= 70 * len(model._pieces)
    # At its own hits each expert is sure of them; a metre away only the prior is left.
    hits = data.X[data.y == 1][:20]
    assert np.all(model.predict_proba(hits)[:, 1] > 0.7)
    away = hits.copy()
    away[:, [0, 3]] += 1.0
    np.testing.assert_allclose(model.predict_proba(away)[:, 1], 0.5)


def _consulted_bounds(model, Q):
    query, expert, _ = model._consulted(Q)
    return query, np.searchsorted(expert, np.arange(model.n_experts_ + 1))


def test_few_queries_take_the_experts_cross_covariances_at_once(default_model, grid):
    # Few point queries: the experts' cross-covariances are evaluated together, each equal
    # to the expert's own kernel call to the bit, every consulted expert once.
    _, Q = grid
    Xc = Q[::97][:12]
    query, bounds = _consulted_bounds(default_model, Xc)
    consulted = np.flatnonzero(np.diff(bounds))
    seen = []
    for k, cross in default_model._cross_covariances(Xc, query, bounds, consulted):
        seen.append(k)
        expert = default_model.experts_[k]
        if not hasattr(expert, "X_train_"):
            assert cross is None
            continue
        rows = Xc[query[bounds[k] : bounds[k + 1]]]
        np.testing.assert_array_equal(cross, expert.kernel_(rows, expert.X_train_))
    assert sorted(seen) == consulted.tolist()
    # Segments (not points) are left to each expert.
    segments = Xc.copy()
    segments[:, 2] += 0.3
    query, bounds = _consulted_bounds(default_model, segments)
    consulted = np.flatnonzero(np.diff(bounds))
    pairs = list(default_model._cross_covariances(segments, query, bounds, consulted))
    assert [k for k, _ in pairs] == consulted.tolist()
    assert all(cross is None for _, cross in pairs)


def test_few_queries_predict_as_a_whole_map_does(default_model, grid):
    # One query at a time (cross-covariances together, packed factors) against the same
    # queries inside the whole map (one kernel call and blocked solve per expert).
    _, Q = grid
    whole = default_model._merged(Q)
    picked = np.arange(0, Q.shape[0], max(Q.shape[0] // 25, 1))
    for i in picked:
        one = default_model._merged(Q[i : i + 1])
        for part, full in zip(one, whole, strict=True):
            np.testing.assert_allclose(part[0], full[i], rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("shrink", [1.0, 0.2])
def test_pairs_the_coverage_gate_weighs_are_within_reach(default_model, grid, shrink):
    # _consulted takes a pair with positive coverage as within reach without searching:
    # the coverage counts cells within its cut, which is at most the reach (also a reach
    # shorter than the coverage's own cut of three widths).
    import copy

    _, Q = grid
    index = copy.copy(default_model._reach_index)
    index.reach = shrink * index.reach
    assert (shrink == 1.0) or index.reach < 3 * default_model.coverage_width_
    query, expert = index.candidates(Q)
    cover = index.coverage(Q, query, expert, default_model.coverage_width_)
    weighed = cover > 0
    assert weighed.sum() > Q.shape[0] and not weighed.all()
    assert index.within_reach(Q, query[weighed], expert[weighed]).all()


def test_a_beam_far_longer_than_the_map_is_a_clear_error(paper):
    # Ranges in millimetres by mistake: a return beam of 100 km cut into 1 m pieces gave
    # its hit's expert 1e5 rows, and a MemoryError asking for 75 GiB.
    X = np.vstack([paper.X, [[0.0, 0.0, 1e5, 0.0], [1e5 + 0.05, 0.0, 1e5 + 0.05, 0.0]]])
    y = np.r_[paper.y, 0, 1]
    with pytest.raises(ValueError, match=r"carries \d+ rows.*check that the ranges are in metres"):
        MixtureGPOccupancyMap(random_state=0).fit(X, y)


def test_split_hits_bounds_at_exactly_the_limits():
    # Two clusters of three hits on a line; piece_hit gives each hit its pieces.
    hits = np.column_stack([np.arange(6.0), np.zeros(6)])
    hit_cluster = np.array([0, 0, 0, 1, 1, 1])
    # Cluster 0 carries exactly max_size = 30 pieces: one expert. Cluster 1 carries 31: split.
    piece_hit = np.repeat(np.arange(6), [10, 10, 10, 10, 10, 11])
    hit_expert, expert_cluster = _split_hits(hits, hit_cluster, 2, piece_hit, 30)
    assert hit_expert[:3].tolist() == [0, 0, 0]
    assert expert_cluster[0] == 0 and np.count_nonzero(expert_cluster == 1) >= 2
    assert np.bincount(hit_expert[piece_hit]).max() <= 30
    # A hit may carry up to the larger of 10 x max_size and 10_000 rows, not one more.
    for max_size in (5, 2000):
        limit = max(10 * max_size, 10_000)
        one = np.zeros(limit, dtype=np.intp)
        _split_hits(hits[:1], np.zeros(1, np.intp), 1, one, max_size)
        with pytest.raises(ValueError, match=f"carries {limit + 1} rows"):
            _split_hits(hits[:1], np.zeros(1, np.intp), 1, np.r_[one, 0], max_size)


def test_points_as_queries_get_a_hint(paper):
    model = MixtureGPOccupancyMap(random_state=0).fit(paper.X, paper.y)
    with pytest.raises(ValueError, match=r"pass skoccmap.as_segments\(points\)"):
        model.predict_proba([[5.0, 5.0]])


def test_no_queries_give_empty_predictions(paper):
    # A robot asking about an empty region: empty answers, as partial_fit takes an empty batch.
    model = MixtureGPOccupancyMap(random_state=0).fit(paper.X, paper.y)
    empty = np.empty((0, 4))
    assert model.predict_proba(empty).shape == (0, 2)
    assert model.predict(empty).shape == (0,)
    assert model.predict_var(empty).shape == (0,)
    assert model.prior_variance(empty).shape == (0,)
    assert [a.shape for a in model.latent_mean_and_variance(empty)] == [(0,), (0,)]


def test_an_expert_without_rows_is_the_prior():
    # A part of a split cluster whose hits are all transient holds no rows; EP on one class
    # had nothing to run on ("Found array with 0 sample(s)").
    from skoccmap import EPGaussianProcessClassifier

    kernel = C(1e3, "fixed") * IntegralKernel(1.0, "fixed")
    expert = EPGaussianProcessClassifier(kernel, optimizer=None)
    fitted, _, _ = _fit_expert(expert, np.empty((0, 4)), np.empty(0, dtype=np.int64))
    assert isinstance(fitted, _ConstantExpert)
    mean, var = fitted.latent_mean_and_variance(np.array([[1.0, 2.0, 1.0, 2.0]]))
    np.testing.assert_allclose(mean, 0.0, atol=1e-12)
    np.testing.assert_allclose(var, 1e3)


def test_a_one_class_expert_of_another_kind_is_the_smoothed_frequency():
    # A non-EP expert on free rows only: Phi(mean / sqrt(1 + var)) = (0 + 1) / (n + 2); on
    # hits only, (n + 1) / (n + 2).
    X = np.tile([0.0, 0.0, 1.0, 0.0], (8, 1))
    Q = np.array([[0.0, 0.0, 1.0, 1.0], [3.0, 3.0, 3.0, 3.0]])
    expert = _fast_expert()
    for label, expected in [(0, 1 / 10), (1, 9 / 10)]:
        est, _, _ = _fit_expert(expert, X, np.full(8, label))
        assert isinstance(est, _ConstantExpert)
        mean, var = est.latent_mean_and_variance(Q)
        np.testing.assert_allclose(var, expert.kernel.diag(Q))
        np.testing.assert_allclose(ndtr(mean / np.sqrt(1 + var)), expected)


class _KernelFreeExpert(ClassifierMixin, BaseEstimator):
    """Stand-in expert that exposes no kernel: the probit of its smoothed hit frequency,
    at latent variance 0.5 everywhere."""

    def fit(self, X, y):
        self.classes_ = np.unique(y)
        self.mean_ = float(ndtri((np.sum(y == 1) + 1) / (y.size + 2)))
        return self

    def latent_mean_and_variance(self, X):
        return np.full(X.shape[0], self.mean_), np.full(X.shape[0], 0.5)


def test_experts_without_a_kernel_have_a_unit_prior():
    # Without a kernel to read it from, an expert's prior latent variance is 1 (the
    # probit's scale), and so is that of a one-class cluster's constant expert of such an
    # expert: it learned nothing, so the robust BCM gives the prior where it alone speaks.
    X, y = _wall_and_far_hits()
    model = MixtureGPOccupancyMap(
        KMeans(2, n_init=3, random_state=0),
        _KernelFreeExpert(),
        share_hyperparameters=False,
        combiner="moe",
        min_expert_size=1,
        random_state=0,
    ).fit(X, y)
    constant = [e for e in model.experts_ if isinstance(e, _ConstantExpert)]
    assert len(constant) == 1 and model.n_experts_ == 2
    q = as_segments([[20.0, 0.0], [1e3, 1e3]])
    np.testing.assert_array_equal(model.prior_variance(q), 1.0)
    mean, var = constant[0].latent_mean_and_variance(q)
    np.testing.assert_array_equal(var, 1.0)
    np.testing.assert_allclose(ndtr(mean / np.sqrt(1 + var)), 13 / 14)
    np.testing.assert_allclose(model.predict_proba(q)[:, 1], 13 / 14)
    model.set_params(combiner="rbcm")
    np.testing.assert_allclose(model.predict_proba(q)[:, 1], 0.5)
    np.testing.assert_allclose(model.predict_var(q), 1.0)


def test_a_one_class_ep_expert_is_the_same_whether_its_kernel_matrix_is_kept():
    # Hits along a wall and no free row, or free rows alone: the GP posterior of one class,
    # whether the kernel matrix is kept for later refits or not.
    from skoccmap import EPGaussianProcessClassifier

    rng = np.random.default_rng(0)
    wall = as_segments(np.column_stack([np.zeros(15), rng.uniform(-2, 2, 15)]))
    Q = wall + [0.3, 0.0, 0.3, 0.0]
    kernel = C(1e2, "fixed") * IntegralKernel(1.0, "fixed")
    for label in (0, 1):
        y = np.full(15, label)
        fitted = [
            _fit_expert(EPGaussianProcessClassifier(kernel, optimizer=None), wall, y, **kw)[0]
            for kw in ({}, {"keep_kernel": True})
        ]
        for est in fitted:
            np.testing.assert_array_equal(est.classes_, [0, 1])
        p = [est.predict_proba(Q)[:, 1] for est in fitted]
        np.testing.assert_allclose(p[1], p[0], rtol=1e-10)
        assert np.all(p[0] > 0.5) if label else np.all(p[0] < 0.5)


def test_a_one_class_ep_expert_keeps_the_kernel_it_was_given():
    # Learning hyperparameters on one class would drive the signal variance to its bound:
    # an expert with an optimiser fits the GP posterior under the kernel it was given.
    from skoccmap import EPGaussianProcessClassifier

    rng = np.random.default_rng(0)
    wall = as_segments(np.column_stack([np.zeros(15), rng.uniform(-2, 2, 15)]))
    kernel = C(10.0, (1e-2, 1e5)) * IntegralKernel(1.0, (0.1, 10.0))
    for label in (0, 1):
        est, _, _ = _fit_expert(EPGaussianProcessClassifier(kernel), wall, np.full(15, label))
        np.testing.assert_array_equal(est.kernel_.theta, kernel.theta)


def test_integral_parts_of_a_product_in_either_order():
    # An integral kernel alone, or times a constant on either side; None for others.
    from skoccmap._experts import _integral_parts

    c, k = C(3.0), IntegralKernel(0.7)
    assert _integral_parts(k) == (None, k)
    for product in (c * k, k * c):
        got = _integral_parts(product)
        assert got[0] is c and got[1] is k
    assert _integral_parts(C(2.0) * RBF(1.0)) is None
    assert _integral_parts(k + c) is None


def test_small_experts_are_no_error(paper):
    # The bound on a hit's rows is absolute as well: a few dozen rows per hit are common.
    model = MixtureGPOccupancyMap(max_expert_size=4, random_state=0).fit(paper.X, paper.y)
    assert model.n_experts_ > 100


# --- prediction where no expert reaches, and of query segments ---------------------------


class _RowCountPriorExpert(ClassifierMixin, BaseEstimator):
    """Stand-in expert whose prior variance is its number of training rows (the experts
    of one mixture then have different priors) and whose posterior is its prior."""

    def __init__(self, length_scale=1.5):
        self.length_scale = length_scale

    def fit(self, X, y):
        self.classes_ = np.unique(y)
        self.kernel_ = C(float(X.shape[0])) * RBF(self.length_scale)
        return self

    def latent_mean_and_variance(self, X):
        return np.zeros(X.shape[0]), self.kernel_.diag(X)


def test_queries_beyond_every_expert_get_the_experts_mean_prior_precision(paper):
    # Without shared hyperparameters the prior where no expert reaches is the experts' mean
    # prior precision (averaged over all of them when there are at most 16).
    model = _mixture(expert=_RowCountPriorExpert(), share_hyperparameters=False)
    model.fit(paper.X, paper.y)
    rows = np.array([e.kernel_.diag(paper.X[:1])[0] for e in model.experts_])
    assert model.shared_kernel_ is None and 1 < model.n_experts_ <= 16
    assert np.unique(rows).size > 1
    far = as_segments([[1e3, 1e3], [-50.0, 0.0], [0.0, 1e4]])
    expected = 1.0 / np.mean(1.0 / rows)
    for combiner in COMBINERS:
        model.set_params(combiner=combiner)
        mean, var = model.latent_mean_and_variance(far)
        np.testing.assert_array_equal(model.predict_proba(far), 0.5)
        np.testing.assert_array_equal(mean, 0.0)
        np.testing.assert_allclose(var, expected, rtol=1e-12)
        np.testing.assert_allclose(model.prior_variance(far), expected, rtol=1e-12)


def test_many_queries_beyond_every_expert_get_the_prior(default_model):
    # More queries than the coverage's search of all cells takes: the coverage gate looks
    # for the covering pairs, and finds none.
    rng = np.random.default_rng(0)
    far = as_segments(rng.uniform(500.0, 600.0, size=(3000, 2)))
    assert default_model._reach_index.prefers_covering(len(far))
    proba, mean, var = default_model._merged(far)
    np.testing.assert_array_equal(proba, 0.5)
    np.testing.assert_array_equal(mean, 0.0)
    np.testing.assert_array_equal(var, default_model.shared_kernel_.diag(far))
    np.testing.assert_array_equal(default_model.prior_variance(far), var)


def test_segments_beyond_every_expert_get_exactly_the_shared_prior(default_model):
    # Where no expert reaches, predict_var is prior_variance bit for bit: the shared
    # kernel's prior at each query, not an average of the experts' priors that rounds.
    # Segments of many lengths give many priors (one falls with its segment's length).
    rng = np.random.default_rng(1)
    far = as_segments(rng.uniform(500.0, 600.0, size=(300, 2)))
    far[:, 2:] += rng.uniform(-2.0, 2.0, size=(300, 2))
    prior = default_model.shared_kernel_.diag(far)
    assert np.unique(prior).size > 200
    np.testing.assert_array_equal(default_model.predict_var(far), prior)
    np.testing.assert_array_equal(default_model.prior_variance(far), prior)


def test_query_segments_merge_the_experts_own_predictions_and_priors(default_model, grid):
    # Under the integral kernel a segment's prior variance falls with its length: the
    # committee machines take each expert's prior at each query segment, as the experts
    # compute it themselves.
    _, Q = grid
    rng = np.random.default_rng(0)
    Q = Q[::20].copy()
    Q[:, 2:] += rng.uniform(-2.0, 2.0, size=(Q.shape[0], 2))
    prior = default_model.shared_kernel_.diag(Q)
    assert np.ptp(prior) > 0.03 * prior.max()
    # rbcm last: the fixture's own combiner.
    for combiner, expected in _combined_by_hand(default_model, Q, ("bcm", "rbcm")).items():
        model = default_model.set_params(combiner=combiner)
        proba, _, var = model._merged(Q)
        np.testing.assert_allclose(proba, expected.proba, rtol=1e-10)
        np.testing.assert_allclose(var, expected.variance, rtol=1e-10)


def test_prior_variance_validates_its_queries_as_predict_does(default_model):
    from sklearn.exceptions import NotFittedError

    with pytest.raises(NotFittedError):
        MixtureGPOccupancyMap().prior_variance([[0.0, 0.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match=r"pass skoccmap.as_segments\(points\)"):
        default_model.prior_variance([[5.0, 5.0]])
    with pytest.raises(ValueError):
        default_model.prior_variance([[np.nan, 0.0, 1.0, 1.0]])


def test_predict_is_the_more_probable_class(default_model, grid):
    _, Q = grid
    proba = default_model.predict_proba(Q)[:, 1]
    assert np.any(proba > 0.5) and np.any(proba < 0.5)
    np.testing.assert_array_equal(
        default_model.predict(Q), default_model.classes_[(proba > 0.5).astype(int)]
    )
