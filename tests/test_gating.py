"""The paper's gating network, ``MixtureGPOccupancyMap(gating="gpc")``, on the paper's data.

Only the public face of the fitted mixture is used (``fit``, ``predict_proba``, ``gating_``,
``cluster_labels_``, ``experts_``, ``n_experts_``): the tests hold however the prediction is
organised inside. Each would pass with a gate that ignored its input only by chance: a uniform
gate scores about 1 / ``n_experts_`` on the first and zero on the last two. The tests after
them (from "the experts each query consults, by brute force" on) read the mixture's parts.
"""

import copy
import warnings

import numpy as np
import pytest
from scipy.special import ndtr
from sklearn.base import BaseEstimator, clone
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process.kernels import ConstantKernel

from skoccmap import EPGaussianProcessClassifier, IntegralKernel, MixtureGPOccupancyMap
from skoccmap.datasets import make_paper_scans
from skoccmap.observations import HIT, RETURN, as_segments


@pytest.fixture(scope="module")
def fitted():
    data = make_paper_scans(random_state=0)
    # Fixed expert hyperparameters keep the fit to a few seconds; max_expert_size=150 cuts the
    # paper's world into about two dozen experts; beams stay with their hits and every piece
    # is kept, as in the paper.
    expert = EPGaussianProcessClassifier(
        ConstantKernel(100.0, "fixed") * IntegralKernel(1.0, "fixed"), optimizer=None
    )
    model = MixtureGPOccupancyMap(
        expert=expert,
        gating="gpc",
        combiner="moe",
        max_expert_size=150,
        piece_assignment="beam",
        max_pieces_per_cell=None,
        random_state=0,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model.fit(data.X, data.y)
    hits = data.kind == HIT
    ret = data.kind == RETURN
    queries = np.vstack([data.X[hits], as_segments(0.5 * (data.X[ret, :2] + data.X[ret, 2:]))])
    return data, model, queries


def _expert_probabilities(model, queries):
    """Each expert's own P(occupied) at the queries, (n_queries, n_experts): probit link."""
    columns = []
    for expert in model.experts_:
        mean, var = expert.latent_mean_and_variance(queries)
        columns.append(ndtr(mean / np.sqrt(1.0 + var)))
    return np.column_stack(columns)


def _gate(model, queries):
    """``p(expert | x)`` of the fitted gating classifier at the queries' midpoints."""
    weights = np.zeros((len(queries), model.n_experts_))
    mids = 0.5 * (queries[:, :2] + queries[:, 2:])
    weights[:, model.gating_.classes_] = model.gating_.predict_proba(mids)
    return weights


def test_several_experts_and_a_fitted_gate(fitted):
    _, model, _ = fitted
    assert model.n_experts_ >= 10
    assert set(model.gating_.classes_) == set(range(model.n_experts_))


def test_gate_favours_each_hits_own_expert(fitted):
    # At a hit assigned to expert k, the gate's most probable expert is k far more often than
    # chance: measured 0.67-0.70 over random states 0-2 (chance, the largest expert's share
    # of the hits, 0.06).
    data, model, _ = fitted
    hits = data.kind == HIT
    weights = _gate(model, data.X[hits])
    own = model.cluster_labels_[hits]
    agreement = np.mean(np.argmax(weights, axis=1) == own)
    chance = np.bincount(own).max() / own.size
    assert chance < 0.1
    assert agreement > 0.6, agreement


def _segment_distance(points, segments):
    """Distance from each point to the nearest of the segments, by projection."""
    a, d = segments[:, :2], segments[:, 2:] - segments[:, :2]
    w = points[:, None, :] - a[None]
    dd = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.einsum("pij,ij->pi", w, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    return np.linalg.norm(w - t[..., None] * d[None], axis=-1).min(axis=1)


def test_moe_prediction_is_the_gate_weighted_mixture_not_a_uniform_one(fitted):
    _, model, queries = fitted
    proba = model.predict_proba(queries)[:, 1]
    experts = _expert_probabilities(model, queries)
    # A query consults the experts with training data within reach_ of it, and the mixture
    # renormalises the gate over them.
    mids = 0.5 * (queries[:, :2] + queries[:, 2:])
    dist = np.column_stack([_segment_distance(mids, e.X_train_) for e in model.experts_])
    near = dist <= model.reach_
    assert np.all(near.any(axis=1)) and not np.all(near)
    gate = _gate(model, queries) * near
    gated = np.sum(gate * experts, axis=1) / gate.sum(axis=1)
    uniform = np.sum(near * experts, axis=1) / near.sum(axis=1)
    # Measured: mean 0.012, max 0.15 from gated; the slack allows for the index consulting
    # some experts a little beyond the reach (within its cell size) and for weights below
    # gating_threshold being dropped.
    assert np.mean(np.abs(proba - gated)) < 0.03
    # A gate that ignored x (uniform weights) gives a measurably different map, and exactly
    # the uniform mixture for a uniform gate.
    assert np.mean(np.abs(proba - uniform)) > 0.04
    assert np.mean(np.abs(proba - gated)) < 0.5 * np.mean(np.abs(proba - uniform))


def test_a_gate_set_after_fit_either_works_or_asks_for_a_fit(fitted):
    data, model, queries = fitted
    model = copy.deepcopy(model)
    # From the fitted gpc gate to the clusterer's: read at predict time.
    model.set_params(gating="clusterer")
    proba = model.predict_proba(queries)
    assert np.all(np.isfinite(proba))
    model.set_params(gating="gpc")
    # A gpc gate is learned by fit: set afterwards on a model fitted without one, it used
    # to fail with "'NoneType' object has no attribute 'predict_proba'".
    other = MixtureGPOccupancyMap(max_expert_size=150, random_state=0).fit(data.X, data.y)
    other.set_params(gating="gpc")
    with pytest.raises(ValueError, match="gating='gpc' was set after"):
        other.predict_proba(queries)
    other.set_params(gating="coverage", layout="points")
    with pytest.raises(ValueError, match="layout='points' was set after"):
        other.predict_proba(queries)
    # A gpc gate that a partial_fit under another gate did not refit is stale: it used to
    # give 14 of 25 experts no weight without a word.
    model.set_params(gating="coverage")
    model.partial_fit(data.X[:40], data.y[:40])
    model.set_params(gating="gpc")
    with pytest.raises(ValueError, match="gating='gpc' was set after"):
        model.predict_proba(queries)


# --- the experts each query consults, by brute force ----------------------------------------
# Unlike the tests above, these read the mixture's parts (``_reach_index``, ``_consulted``,
# the gates): they re-derive the documented choice of experts query by query from the gate
# weights and the index's reach, and each gate from its definition.


def _split_mixture(clusterer, gating, kernel=None):
    from sklearn.gaussian_process import GaussianProcessClassifier
    from sklearn.gaussian_process.kernels import RBF

    # About 40 experts of at most 100 rows in split clusters, in about a second.
    kernel = ConstantKernel(2.0) * RBF(1.5) if kernel is None else kernel
    expert = GaussianProcessClassifier(kernel, optimizer=None)
    model = MixtureGPOccupancyMap(
        clusterer=clusterer,
        expert=expert,
        gating=gating,
        max_expert_size=100,
        max_pieces_per_cell=None,
        random_state=0,
    )
    return model.fit(*_paper_data())


def _paper_data():
    data = make_paper_scans(random_state=0)
    return data.X, data.y


def _queries(n, seed=0):
    """Points over the paper's world and a margin beyond it (some beyond every expert's
    reach), and short segments among them."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([0.0, -4.0], [27.0, 22.0], size=(n, 2))
    Q = as_segments(points)
    Q[::5, 2:] += rng.uniform(-0.5, 0.5, size=(Q[::5].shape[0], 2))
    return Q


def _expected_consulted(model, Q, weights_of, threshold, relative):
    """Dense (query, expert) weights of the experts the documented rule consults.

    Among a query's candidates (the index's superset of the experts within reach), those
    of weight at least ``threshold`` (times the query's largest weight if ``relative``,
    as with the coverage gate) and those of the largest weight are kept if within reach; a
    query that keeps none takes its best-weighted experts within reach, and none when no
    expert is in reach. Weights that vanish count as the smallest positive float.
    """
    index = model._reach_index
    query, expert = index.candidates(Q)
    weights = weights_of(query, expert)
    near = index.within_reach(Q, query, expert)
    dense = np.zeros((len(Q), model.n_experts_))
    cases = {"beyond reach": 0, "best in reach": 0, "weights vanish": 0}
    starts = np.searchsorted(query, np.arange(len(Q) + 1))  # candidates are sorted by query
    for i in range(len(Q)):
        mine = slice(starts[i], starts[i + 1])
        w, e, n = weights[mine], expert[mine], near[mine]
        if not n.any():
            cases["beyond reach"] += 1
            continue
        bound = threshold * w.max() if relative else threshold
        kept = ((w == w.max()) | (w >= bound)) & n
        if not kept.any():
            cases["best in reach"] += 1
            kept = n & (w == w[n].max())
        cases["weights vanish"] += not np.any(w[kept] > 0)
        dense[i, e[kept]] = np.maximum(w[kept], np.finfo(float).tiny)
    return dense, cases


def _consulted_dense(model, Q):
    query, expert, weights = model._consulted(Q)
    # Sorted by expert, as prediction slices the pairs of each expert.
    assert np.all(np.diff(expert) >= 0)
    dense = np.zeros((len(Q), model.n_experts_))
    dense[query, expert] = weights
    assert np.count_nonzero(dense) == query.size  # each pair once, with positive weight
    return dense


@pytest.fixture(scope="module")
def split_models():
    from sklearn.cluster import KMeans
    from sklearn.gaussian_process.kernels import RBF
    from sklearn.mixture import GaussianMixture

    # A kernel that does not decay reaches everywhere: no cells for the coverage gate.
    flat = ConstantKernel(2.0) * RBF(1.5) + ConstantKernel(0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        infinite = _split_mixture(GaussianMixture(5, random_state=0), "coverage", flat)
        return {
            # A clusterer without predict_proba: the gate is its hard assignment.
            "hard": _split_mixture(KMeans(3, n_init=3, random_state=0), "clusterer"),
            "soft": _split_mixture(GaussianMixture(5, random_state=0), "clusterer"),
            "coverage": _split_mixture(GaussianMixture(5, random_state=0), "coverage"),
            "infinite reach": infinite,
        }


def _gate_weights(model, Q, coverage):
    """The gate's weight of each (query, expert) pair, from its parts: the coverage shares
    of the index's coverage, or the clusterer gate at the query's midpoint."""
    mids = 0.5 * (Q[:, :2] + Q[:, 2:])
    if not coverage:
        return lambda query, expert: model._pair_gates(mids, query, expert)

    def shares(query, expert):
        cover = model._reach_index.coverage(Q, query, expert, model.coverage_width_)
        total = np.bincount(query, weights=cover, minlength=len(Q))[query]
        return np.where(total > 0, cover / np.where(total > 0, total, 1.0), 1.0)

    return shares


@pytest.mark.parametrize(
    "name, threshold, bound, relative",
    [
        # "auto": 1e-3 with the clusterer's gate, 0.35 of the largest with the coverage's.
        ("hard", "auto", 1e-3, False),
        ("hard", 0.5, 0.5, False),
        ("soft", "auto", 1e-3, False),
        ("soft", 0.0, 0.0, False),
        ("soft", 0.5, 0.5, False),
        ("coverage", "auto", 0.35, True),
        ("coverage", 0.0, 0.0, True),
        ("coverage", 0.8, 0.8, True),
        # The coverage gate without cells is the clusterer's, with its threshold.
        ("infinite reach", "auto", 1e-3, False),
    ],
)
def test_consulted_experts_follow_the_documented_rule(
    split_models, name, threshold, bound, relative
):
    model = split_models[name].set_params(gating_threshold=threshold)
    # More queries than the coverage's search of all cells takes: the coverage gate with a
    # positive threshold finds its pairs from the covering ones.
    Q = _queries(2500)
    weights_of = _gate_weights(model, Q, coverage=relative)
    expected, cases = _expected_consulted(model, Q, weights_of, bound, relative)
    np.testing.assert_array_equal(_consulted_dense(model, Q), expected)
    # The rule's cases occur: queries beyond every expert's reach (but with infinite
    # reach), queries whose kept experts are all out of reach (with the clusterer's gate
    # and a threshold), queries whose weights in reach all vanish (the hard assignment)
    # and, with threshold 0, experts of weight 0 consulted (the coverage gate).
    assert (cases["beyond reach"] > 0) == (name != "infinite reach")
    assert (cases["best in reach"] > 0) == (name in ("hard", "soft") and bound > 0.0)
    assert (cases["weights vanish"] > 0) == (name == "hard")
    tiny = np.count_nonzero(expected == np.finfo(float).tiny)
    assert (tiny > 0) == (name == "hard" or (name == "coverage" and bound == 0.0))


class _SharpClusterer(BaseEstimator):
    """k-means centres with soft responsibilities ``softmax(-d**2 / (2 scale**2))``, and
    ``extra`` centres far from every hit: clusters that receive no hit, which take the
    responsibility from the others away from the map (and all of it far enough)."""

    def __init__(self, n_clusters=6, scale=1.0, extra=((13.0, -40.0),), random_state=0):
        self.n_clusters = n_clusters
        self.scale = scale
        self.extra = extra
        self.random_state = random_state

    def fit(self, X, y=None):
        from sklearn.cluster import KMeans

        kmeans = KMeans(self.n_clusters, n_init=3, random_state=self.random_state).fit(X)
        self.centres_ = np.vstack([kmeans.cluster_centers_, self.extra])
        return self

    def predict_proba(self, X):
        d2 = np.sum((X[:, None, :] - self.centres_[None]) ** 2, axis=-1)
        log_p = -0.5 * d2 / self.scale**2
        p = np.exp(log_p - log_p.max(axis=1, keepdims=True))
        return p / p.sum(axis=1, keepdims=True)

    def predict(self, X):
        return np.argmax(self.predict_proba(X), axis=1)


def test_clusterer_gate_renormalises_over_the_clusters_that_received_hits():
    # The clusterer gate is the clusterer's responsibilities of the clusters that received
    # hits, renormalised, summed over each merged cluster; where they all vanish, the
    # clusterer's hard assignment (equal weights for a cluster without hits).
    X, y = _paper_data()
    model = _split_mixture(_SharpClusterer(), "clusterer")
    model.set_params(min_expert_size=80).fit(X, y)
    ids = model.cluster_ids_
    assert ids.tolist() == list(range(6))  # the extra cluster received no hit
    assert model.n_clusters_ < ids.size  # small clusters were merged
    rng = np.random.default_rng(0)
    mids = np.vstack(
        [
            rng.uniform([0.0, 0.0], [27.0, 18.0], size=(500, 2)),
            np.c_[np.full(60, 13.0), np.linspace(0.0, -40.0, 60)],
        ]
    )
    raw = model.clusterer_.predict_proba(mids)[:, ids]
    total = raw.sum(axis=1, keepdims=True)
    vanished = total[:, 0] == 0.0
    expected_raw = np.where(
        vanished[:, None], 1.0 / ids.size, raw / np.where(vanished, 1.0, total[:, 0])[:, None]
    )
    expected = np.column_stack(
        [expected_raw[:, model.cluster_merge_ == c].sum(axis=1) for c in range(model.n_clusters_)]
    )
    # Each case occurs: the extra cluster holds some of the mass, or all of it ...
    share = 1.0 - total[:, 0]
    assert np.any((share > 0.1) & ~vanished) and np.any(vanished)
    # ... and merged clusters' components overlap.
    merged = [c for c in range(model.n_clusters_) if np.sum(model.cluster_merge_ == c) > 1]
    assert any(
        np.sum(np.sort(raw[:, model.cluster_merge_ == c], axis=1)[:, -2] > 0.1) for c in merged
    )
    np.testing.assert_allclose(model._cluster_weights(mids), expected, rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(expected.sum(axis=1), 1.0, rtol=1e-12)


def test_gpc_gate_has_the_documented_kernel_and_training_points(fitted):
    # A signal variance of 4 and the mean spread of each expert's pieces (midpoints) as the
    # length scale, both fixed, on at most 300 points, some of every expert.
    _, model, _ = fitted
    spreads = []
    for expert in model.experts_:
        mids = 0.5 * (expert.X_train_[:, :2] + expert.X_train_[:, 2:])
        spreads.append(np.sqrt(np.mean(np.var(mids, axis=0))))
    kernel = model.gating_.kernel
    assert kernel.k1.constant_value == 4.0 and kernel.k1.constant_value_bounds == "fixed"
    assert kernel.k2.length_scale == pytest.approx(np.mean(spreads), rel=1e-12)
    assert kernel.k2.length_scale_bounds == "fixed"
    n_train = model.gating_.base_estimator_.estimators_[0].X_train_.shape[0]
    assert 300 - model.n_experts_ < n_train <= 300


def test_gpc_gate_consults_by_the_documented_rule(fitted):
    _, model, _ = fitted
    Q = _queries(1000)
    dense_gate = _gate(model, Q)
    expected, cases = _expected_consulted(model, Q, lambda q, e: dense_gate[q, e], 1e-3, False)
    np.testing.assert_array_equal(_consulted_dense(model, Q), expected)
    assert cases["beyond reach"] > 0


def test_gpc_gate_without_some_experts_gives_them_no_weight(fitted):
    # A gate fitted on the pieces of some experts only (as after an update that left an
    # expert without pieces) has fewer columns than experts: each is read by its class.
    _, model, _ = fitted
    model = copy.deepcopy(model)
    mids = np.vstack([0.5 * (e.X_train_[:8, :2] + e.X_train_[:8, 2:]) for e in model.experts_])
    labels = np.repeat(
        np.arange(model.n_experts_), [min(len(e.X_train_), 8) for e in model.experts_]
    )
    left_out = np.isin(labels, [0, 3])
    model.gating_ = clone(model.gating_).fit(mids[~left_out], labels[~left_out])
    assert model.gating_.classes_.size == model.n_experts_ - 2
    Q = _queries(1000)
    dense_gate = _gate(model, Q)
    assert np.all(dense_gate[:, [0, 3]] == 0.0)
    expected, _ = _expected_consulted(model, Q, lambda q, e: dense_gate[q, e], 1e-3, False)
    np.testing.assert_array_equal(_consulted_dense(model, Q), expected)


class _OneBasedClusterer(_SharpClusterer):
    """Labels 1 .. n: they are not the columns of its predict_proba."""

    def predict(self, X):
        return super().predict(X) + 1


def test_clusterer_whose_labels_are_not_its_proba_columns_gates_by_its_labels():
    model = _split_mixture(_OneBasedClusterer(extra=np.empty((0, 2))), "clusterer")
    assert model.cluster_ids_.tolist() == list(range(1, 7))
    mids = np.random.default_rng(0).uniform([0.0, 0.0], [27.0, 18.0], size=(300, 2))
    position = np.searchsorted(model.cluster_ids_, model.clusterer_.predict(mids))
    expected = np.zeros((len(mids), model.n_clusters_))
    expected[np.arange(len(mids)), model.cluster_merge_[position]] = 1.0
    np.testing.assert_array_equal(model._cluster_weights(mids), expected)


def test_piece_gate_is_the_posterior_of_a_gaussian_mixture_of_the_pieces():
    # Each piece a Gaussian of its points' mean and covariance, weighted by its share of
    # the points; the gate is the posterior over pieces, and finite far from them all.
    from scipy.special import logsumexp
    from scipy.stats import multivariate_normal

    from skoccmap._partition import _GATING_RIDGE, _PieceGate

    rng = np.random.default_rng(0)
    groups = [
        rng.normal([0.0, 0.0], [3.0, 0.5], size=(60, 2)),
        rng.normal([2.0, 1.0], [0.4, 0.4], size=(10, 2)),
        rng.normal([-1.0, 2.0], [1.0, 2.0], size=(30, 2)),
        # Along a wall: a singular covariance.
        np.c_[rng.uniform(-3.0, 3.0, size=15), np.full(15, 4.0)],
    ]
    n = np.array([len(g) for g in groups])
    points = rng.uniform([-4.0, -3.0], [4.0, 5.0], size=(200, 2))

    def gaussian(g):
        # With the ridge that keeps pieces along a wall invertible.
        cov = np.cov(g, rowvar=False)
        ridge = _GATING_RIDGE * np.trace(cov) / 2 * np.eye(2)
        return multivariate_normal(g.mean(axis=0), cov + ridge)

    log_joint = np.column_stack(
        [np.log(n[k] / n.sum()) + gaussian(g).logpdf(points) for k, g in enumerate(groups)]
    )
    expected = np.exp(log_joint - logsumexp(log_joint, axis=1, keepdims=True))
    gate = _PieceGate(groups)
    np.testing.assert_allclose(gate.predict_proba(points), expected, rtol=1e-6, atol=1e-12)
    far = gate.predict_proba(np.array([[1e3, 0.0], [0.0, -1e3], [1e4, 1e4]]))
    assert np.all(np.isfinite(far))
    np.testing.assert_allclose(far.sum(axis=1), 1.0)


class _TiedIndex:
    """An index under which one query has two candidate experts, both within reach,
    covering it 2 : 1: the second's share is exactly half the first's."""

    reach = 1.0

    def __init__(self, covering):
        self.covering_path = covering

    def prefers_covering(self, n_queries):
        return self.covering_path

    def candidates(self, queries):
        return np.array([0, 0]), np.array([0, 1])

    def within_reach(self, queries, query_index, expert_index):
        return np.ones(query_index.size, dtype=bool)

    def coverage(self, queries, query_index, expert_index, width, n_jobs=None):
        return np.array([2.0, 1.0])

    def covering(self, queries, width):
        return np.array([0, 0]), np.array([0, 1]), np.array([2.0, 1.0])


@pytest.mark.parametrize("covering", [False, True])
def test_a_share_of_exactly_the_threshold_is_kept(fitted, covering):
    # "Below the threshold" is skipped: a share equal to it is kept, from the candidates'
    # coverage or from the covering pairs alike.
    _, model, _ = fitted
    model = copy.copy(model).set_params(gating="coverage", gating_threshold=0.5)
    model._reach_index = _TiedIndex(covering)
    query, expert, weights = model._consulted(as_segments([[5.0, 5.0]]))
    assert query.tolist() == [0, 0] and expert.tolist() == [0, 1]
    np.testing.assert_array_equal(weights, [2.0 / 3.0, 1.0 / 3.0])
