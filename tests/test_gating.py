"""The paper's gating network, ``MixtureGPOccupancyMap(gating="gpc")``, on the paper's data.

Only the public face of the fitted mixture is used (``fit``, ``predict_proba``, ``gating_``,
``cluster_labels_``, ``experts_``, ``n_experts_``): the tests hold however the prediction is
organised inside. Each would pass with a gate that ignored its input only by chance: a uniform
gate scores about 1 / ``n_experts_`` on the first and zero on the last two.
"""

import copy
import warnings

import numpy as np
import pytest
from scipy.special import ndtr
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
