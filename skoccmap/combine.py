"""Rules that merge the predictions of several GP experts into one.

Every combiner is a pure function on arrays of shape ``(n_queries, n_experts)``:
the experts' latent means ``mu_k`` and latent variances ``s_k^2`` at each query, and the
non-negative gating weights ``w_k`` (``p(expert k | x)``). A zero weight means "expert
skipped at this query": its mean and variance there are never read, so they may hold NaN.
:func:`combine_pairs` takes the same rules on (query, expert) pairs, for maps in which each
query consults a few of many experts (the mixture's prediction): nothing of size
``(n_queries, n_experts)`` is formed.

The rules: the mixture of experts of the paper ([KK2012]_), the product of experts and
its generalised form ([CF2014]_), the Bayesian committee machine ([Tresp2000]_) and its
robust form ([DN2015]_).

Each combiner returns a :class:`MergedPrediction` ``(proba, mean, variance)``: the
probability of the positive class and the merged latent Gaussian. For the product rules
(PoE, gPoE, BCM, rBCM) the probability is the probit link of the merged Gaussian,
``Phi(mu / sqrt(1 + s^2))`` (R&W eq. 3.82); for the mixture of experts it is the mixture of
the experts' probabilities.

References
----------
.. [KK2012] S. Kim and J. Kim, "Building occupancy maps with a mixture of
   Gaussian processes", ICRA 2012.
.. [Tresp2000] V. Tresp, "A Bayesian committee machine", Neural Computation 12, 2000.
.. [CF2014] Y. Cao and D. J. Fleet, "Generalized product of experts for automatic and
   principled fusion of Gaussian process predictions", arXiv:1410.7827, 2014.
.. [DN2015] M. P. Deisenroth and J. W. Ng, "Distributed Gaussian processes", ICML 2015.
"""

from numbers import Integral
from typing import NamedTuple

import numpy as np
from scipy.special import ndtr

__all__ = [
    "COMBINERS",
    "MergedPrediction",
    "bayesian_committee_machine",
    "combine",
    "combine_pairs",
    "generalized_product_of_experts",
    "mixture_of_experts",
    "product_of_experts",
    "robust_bayesian_committee_machine",
]

# Floor for merged latent variances: a mixture of identical experts with tiny variances
# could otherwise round to zero or below.
_VARIANCE_FLOOR = 1e-12
# Smallest merged precision: the smallest normal float, whose reciprocal is finite (that of
# 1 / finfo.max, a subnormal, is infinite: variances at the largest float gave NaN maps).
_PRECISION_FLOOR = np.finfo(np.float64).tiny
# A query's latent means beyond this are scaled down, exactly, by a power of two before their
# weighted sums: near the float maximum those overflowed to inf (NaN with both signs).
_LARGE_MEAN = 2.0**500
_FLOAT_MAX = np.finfo(np.float64).max


class MergedPrediction(NamedTuple):
    """Merged prediction at each query.

    Attributes
    ----------
    proba : ndarray of shape (n_queries,)
        Probability of the positive class.
    mean : ndarray of shape (n_queries,)
        Merged latent mean.
    variance : ndarray of shape (n_queries,)
        Merged latent variance (strictly positive).
    """

    proba: np.ndarray
    mean: np.ndarray
    variance: np.ndarray


def _check_inputs(means, variances, weights, prior_variance=None):
    """Validate shapes and return float arrays plus the boolean mask of used experts."""
    means = np.asarray(means, dtype=np.float64)
    variances = np.asarray(variances, dtype=np.float64)
    if means.ndim != 2:
        raise ValueError(
            f"means must be a 2-D array of shape (n_queries, n_experts), got {means.ndim} "
            "dimension(s)."
        )
    if variances.shape != means.shape:
        raise ValueError(
            f"variances has shape {variances.shape}, expected the shape of means {means.shape}."
        )
    if means.shape[1] == 0:
        raise ValueError("means has no expert columns; at least one expert is needed.")
    if weights is None:
        weights = np.ones_like(means)
    else:
        weights = np.asarray(weights, dtype=np.float64)
        if weights.shape != means.shape:
            raise ValueError(
                f"weights has shape {weights.shape}, expected the shape of means {means.shape}."
            )
        if not np.all(np.isfinite(weights)) or np.any(weights < 0):
            raise ValueError("weights must be finite and non-negative.")
    used = weights > 0
    if not np.all(used.any(axis=1)):
        raise ValueError(
            "weights has a row of zeros: every query needs at least one expert with positive "
            "weight."
        )
    if not np.all(np.isfinite(means[used])):
        raise ValueError("means contains NaN or infinite values where the weight is positive.")
    if not np.all(np.isfinite(variances[used])) or np.any(variances[used] <= 0):
        raise ValueError("variances must be finite and positive where the weight is positive.")
    if prior_variance is not None:
        prior_variance = np.asarray(prior_variance, dtype=np.float64)
        if prior_variance.shape == means.shape[:1]:
            prior_variance = np.broadcast_to(prior_variance[:, None], means.shape)
        elif prior_variance.shape != means.shape:
            raise ValueError(
                f"prior_variance has shape {prior_variance.shape}; expected (n_queries,) or "
                f"the shape of means {means.shape}."
            )
        if not np.all(np.isfinite(prior_variance[used])) or np.any(prior_variance[used] <= 0):
            raise ValueError(
                "prior_variance must be finite and positive where the weight is positive."
            )
    return means, variances, weights, used, prior_variance


def _probit(mean, variance):
    # Probit likelihood integrated against the latent Gaussian, R&W eq. 3.82.
    return ndtr(mean / np.sqrt(1.0 + variance))


class _Pairs(NamedTuple):
    """The (query, expert) pairs that enter the merge, one entry per pair."""

    query: np.ndarray
    n_queries: int
    means: np.ndarray
    variances: np.ndarray
    weights: np.ndarray
    prior_variance: np.ndarray | None


def _dense_pairs(means, variances, weights, prior_variance=None):
    """Validated dense inputs as the pairs of experts with positive weight."""
    means, variances, weights, used, prior_variance = _check_inputs(
        means, variances, weights, prior_variance
    )
    query, expert = np.nonzero(used)
    prior = None if prior_variance is None else prior_variance[query, expert]
    return _Pairs(
        query,
        means.shape[0],
        means[query, expert],
        variances[query, expert],
        weights[query, expert],
        prior,
    )


def _sum(pairs, values):
    """Per-query sums of a value per pair."""
    # float64 also for no pairs (bincount then gives integers)
    return np.bincount(pairs.query, weights=values, minlength=pairs.n_queries).astype(
        np.float64, copy=False
    )


def _normalized(pairs):
    # Scaled by each query's largest weight first: weights near the float maximum would
    # sum to infinity.
    largest = np.zeros(pairs.n_queries)
    np.maximum.at(largest, pairs.query, pairs.weights)
    scaled = pairs.weights / largest[pairs.query]
    return scaled / _sum(pairs, scaled)[pairs.query]


def _scaled_means(pairs):
    """The pairs' means scaled down by a power of two per query before their sums, and
    that power (its exponent) per query: the one of the largest ``|mu_k|`` where it exceeds
    ``_LARGE_MEAN``, else 0 (no scaling)."""
    mu = pairs.means
    if not mu.size or max(np.max(mu), -np.min(mu)) <= _LARGE_MEAN:  # as a rule: one pass
        exponent = np.zeros(pairs.n_queries, dtype=np.intc)
    else:
        largest = np.zeros(pairs.n_queries)
        np.maximum.at(largest, pairs.query, np.abs(mu))
        exponent = np.where(largest > _LARGE_MEAN, np.frexp(largest)[1], 0)
    return np.ldexp(mu, -exponent[pairs.query]), exponent


def _unscaled(values, exponent):
    """``values * 2**exponent``, saturated at the largest float where the product (a merged
    mean or variance beyond the float range) overflows."""
    with np.errstate(over="ignore"):
        return np.clip(np.ldexp(values, exponent), -_FLOAT_MAX, _FLOAT_MAX)


def _moe(pairs):
    w = _normalized(pairs)
    mu, var = pairs.means, pairs.variances
    proba = _sum(pairs, w * _probit(mu, var))
    scaled, exponent = _scaled_means(pairs)
    mean_scaled = _sum(pairs, w * scaled)
    mean = _unscaled(mean_scaled, exponent)
    # Law of total variance: E[var] + Var[mean]; each term saturates at the largest float.
    spread = _unscaled((scaled - mean_scaled[pairs.query]) ** 2, 2 * exponent[pairs.query])
    with np.errstate(over="ignore"):
        variance = np.minimum(_sum(pairs, w * np.minimum(var + spread, _FLOAT_MAX)), _FLOAT_MAX)
    return MergedPrediction(np.clip(proba, 0.0, 1.0), mean, np.maximum(variance, _VARIANCE_FLOOR))


def _merged_mean(pairs, variance, coef):
    """``variance * sum_k coef_k mu_k`` per query (``coef_k = beta_k / s_k^2``), the means
    scaled as :func:`_scaled_means` says."""
    scaled, exponent = _scaled_means(pairs)
    return _unscaled(variance * _sum(pairs, coef * scaled), exponent)


def _gaussian_product(pairs, betas):
    """Merge Gaussians by adding weighted natural parameters.

    ``1/s^2 = sum_k beta_k / s_k^2`` and ``mu = s^2 sum_k beta_k mu_k / s_k^2``.
    """
    # Floored as the experts' own variances are: 1 / a subnormal is infinite.
    inv_var = 1.0 / np.maximum(pairs.variances, _VARIANCE_FLOOR)
    precision = np.maximum(_sum(pairs, betas * inv_var), _PRECISION_FLOOR)
    variance = 1.0 / precision
    mean = _merged_mean(pairs, variance, betas * inv_var)
    variance = np.maximum(variance, _VARIANCE_FLOOR)
    return MergedPrediction(_probit(mean, variance), mean, variance)


def _bcm(pairs, betas):
    """``1/s^2 = 1/s_**^2 + sum_k beta_k (1/s_k^2 - 1/s_**^2)``, ``mu = s^2 sum beta mu/s_k^2``.

    The common prior precision ``1/s_**^2`` is the mean prior precision of the experts
    used (with one shared prior, that prior); each expert's information gain is over its
    own prior.
    """
    inv_var = 1.0 / np.maximum(pairs.variances, _VARIANCE_FLOOR)
    inv_prior = 1.0 / np.maximum(pairs.prior_variance, _VARIANCE_FLOOR)
    # Roundoff can put a posterior variance a hair above the prior; clip so that no expert
    # removes information.
    gain = np.maximum(inv_var - inv_prior, 0.0)
    used = np.bincount(pairs.query, minlength=pairs.n_queries)
    precision = np.maximum(
        _sum(pairs, inv_prior) / used + _sum(pairs, betas * gain), _PRECISION_FLOOR
    )
    variance = 1.0 / precision
    # Zero prior mean: only the experts' linear natural parameters enter the mean.
    mean = _merged_mean(pairs, variance, betas * inv_var)
    variance = np.maximum(variance, _VARIANCE_FLOOR)
    return MergedPrediction(_probit(mean, variance), mean, variance)


def _rbcm_betas(pairs):
    # Differential-entropy drop from prior to posterior; roundoff can make s_k^2 exceed
    # s_**^2 by a hair, and an expert never gets negative weight.
    return np.maximum(0.5 * (np.log(pairs.prior_variance) - np.log(pairs.variances)), 0.0)


_RULES = {
    "moe": _moe,
    "poe": lambda pairs: _gaussian_product(pairs, np.ones_like(pairs.means)),
    "gpoe": lambda pairs: _gaussian_product(pairs, _normalized(pairs)),
    "bcm": lambda pairs: _bcm(pairs, np.ones_like(pairs.means)),
    "rbcm": lambda pairs: _bcm(pairs, _rbcm_betas(pairs)),
}


def _require_prior(prior_variance, name):
    if prior_variance is None:
        raise ValueError(f"prior_variance is required by the {name}.")


def mixture_of_experts(means, variances, weights=None):
    """Mixture of experts: average the experts' probabilities with the gating weights.

    ``p = sum_k w_k Phi(mu_k / sqrt(1 + s_k^2))`` with the weights normalised to sum to one at
    each query (Kim and Kim 2012). The latent summary is the mixture's mean and variance,
    ``mu = sum_k w_k mu_k`` and ``s^2 = sum_k w_k (s_k^2 + mu_k^2) - mu^2``.

    Parameters
    ----------
    means : array-like of shape (n_queries, n_experts)
        Latent means of the experts.
    variances : array-like of shape (n_queries, n_experts)
        Latent variances of the experts.
    weights : array-like of shape (n_queries, n_experts), default=None
        Non-negative gating weights; zero skips the expert. ``None`` weights all equally.

    Returns
    -------
    MergedPrediction
        ``(proba, mean, variance)``, each of shape (n_queries,).

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.combine import mixture_of_experts
    >>> merged = mixture_of_experts([[2.0, -2.0]], [[1.0, 1.0]], [[0.5, 0.5]])
    >>> float(merged.proba[0]), float(merged.mean[0]), float(merged.variance[0])
    (0.5, 0.0, 5.0)
    """
    return _moe(_dense_pairs(means, variances, weights))


def product_of_experts(means, variances, weights=None):
    """Product of experts: multiply the experts' Gaussian predictions.

    ``1/s^2 = sum_k 1/s_k^2``, ``mu = s^2 sum_k mu_k / s_k^2`` over the experts with positive
    weight (Deisenroth and Ng 2015, eq. 10). The weights only select experts; the product is
    overconfident when experts share data, and far from all data its variance shrinks with
    their number.

    Parameters
    ----------
    means : array-like of shape (n_queries, n_experts)
        Latent means of the experts.
    variances : array-like of shape (n_queries, n_experts)
        Latent variances of the experts.
    weights : array-like of shape (n_queries, n_experts), default=None
        Non-negative weights; zero skips the expert, other values are ignored.

    Returns
    -------
    MergedPrediction
        ``(proba, mean, variance)``, each of shape (n_queries,).

    Examples
    --------
    >>> from skoccmap.combine import product_of_experts
    >>> merged = product_of_experts([[1.0, 3.0]], [[1.0, 1.0]])
    >>> float(merged.mean[0]), float(merged.variance[0])
    (2.0, 0.5)
    """
    return _RULES["poe"](_dense_pairs(means, variances, weights))


def generalized_product_of_experts(means, variances, weights=None):
    """Generalised product of experts with the gating weights as exponents.

    ``1/s^2 = sum_k beta_k / s_k^2``, ``mu = s^2 sum_k beta_k mu_k / s_k^2`` (Cao and Fleet
    2014; Deisenroth and Ng 2015, eq. 13) with ``beta_k = w_k / sum_j w_j``. Because the
    betas sum to one, far from all data the merged prediction falls back to the prior rather
    than shrinking, as Deisenroth and Ng recommend; with equal weights ``beta_k = 1/M``.

    Parameters
    ----------
    means : array-like of shape (n_queries, n_experts)
        Latent means of the experts.
    variances : array-like of shape (n_queries, n_experts)
        Latent variances of the experts.
    weights : array-like of shape (n_queries, n_experts), default=None
        Non-negative gating weights; zero skips the expert. ``None`` weights all equally.

    Returns
    -------
    MergedPrediction
        ``(proba, mean, variance)``, each of shape (n_queries,).

    Examples
    --------
    >>> from skoccmap.combine import generalized_product_of_experts
    >>> merged = generalized_product_of_experts([[1.0, 3.0]], [[1.0, 1.0]])
    >>> float(merged.mean[0]), float(merged.variance[0])
    (2.0, 1.0)
    """
    return _RULES["gpoe"](_dense_pairs(means, variances, weights))


def bayesian_committee_machine(means, variances, prior_variance, weights=None):
    """Bayesian committee machine: product of experts with the prior counted once.

    ``1/s^2 = sum_k 1/s_k^2 + (1 - M) / s_**^2``, ``mu = s^2 sum_k mu_k / s_k^2`` over the
    ``M`` experts with positive weight (Tresp 2000; Deisenroth and Ng 2015, eq. 15), where
    ``s_**^2`` is the prior variance at the query. Written as
    ``1/s_**^2 + sum_k (1/s_k^2 - 1/s_**^2)``, which also covers experts with their own prior
    variances (their information gains over their own priors are added to the mean prior
    precision).

    Parameters
    ----------
    means : array-like of shape (n_queries, n_experts)
        Latent means of the experts.
    variances : array-like of shape (n_queries, n_experts)
        Latent variances of the experts.
    prior_variance : array-like of shape (n_queries,) or (n_queries, n_experts)
        Prior latent variance at each query (per expert if the experts' priors differ).
    weights : array-like of shape (n_queries, n_experts), default=None
        Non-negative weights; zero skips the expert, other values are ignored.

    Returns
    -------
    MergedPrediction
        ``(proba, mean, variance)``, each of shape (n_queries,).

    Examples
    --------
    >>> from skoccmap.combine import bayesian_committee_machine
    >>> merged = bayesian_committee_machine([[1.0, 3.0]], [[1.0, 1.0]], [2.0])
    >>> float(merged.mean[0]), float(merged.variance[0])
    (2.6666666666666665, 0.6666666666666666)
    """
    _require_prior(prior_variance, "Bayesian committee machine")
    return _RULES["bcm"](_dense_pairs(means, variances, weights, prior_variance))


def robust_bayesian_committee_machine(means, variances, prior_variance, weights=None):
    """Robust Bayesian committee machine of Deisenroth & Ng (2015).

    ``1/s^2 = sum_k beta_k / s_k^2 + (1 - sum_k beta_k) / s_**^2`` and
    ``mu = s^2 sum_k beta_k mu_k / s_k^2`` with ``beta_k = (log s_**^2 - log s_k^2) / 2``,
    the differential-entropy drop from prior to posterior (Deisenroth and Ng 2015, eq.
    19-20). Experts that learned nothing at a query (``s_k = s_**``) get ``beta_k = 0``, so
    far from all data the merged prediction is the prior.

    Parameters
    ----------
    means : array-like of shape (n_queries, n_experts)
        Latent means of the experts.
    variances : array-like of shape (n_queries, n_experts)
        Latent variances of the experts.
    prior_variance : array-like of shape (n_queries,) or (n_queries, n_experts)
        Prior latent variance at each query (per expert if the experts' priors differ).
    weights : array-like of shape (n_queries, n_experts), default=None
        Non-negative weights; zero skips the expert, other values are ignored.

    Returns
    -------
    MergedPrediction
        ``(proba, mean, variance)``, each of shape (n_queries,).

    Examples
    --------
    Experts that learned nothing at a query leave the prior untouched:

    >>> from skoccmap.combine import robust_bayesian_committee_machine
    >>> merged = robust_bayesian_committee_machine([[0.3, -0.2]], [[1.0, 1.0]], [1.0])
    >>> float(merged.mean[0]), float(merged.variance[0])
    (0.0, 1.0)
    """
    _require_prior(prior_variance, "robust Bayesian committee machine")
    return _RULES["rbcm"](_dense_pairs(means, variances, weights, prior_variance))


COMBINERS = {
    "moe": mixture_of_experts,
    "poe": product_of_experts,
    "gpoe": generalized_product_of_experts,
    "bcm": bayesian_committee_machine,
    "rbcm": robust_bayesian_committee_machine,
}
"""Combiner name -> function; ``"bcm"`` and ``"rbcm"`` need the prior variance."""

_NEEDS_PRIOR = frozenset({"bcm", "rbcm"})


def combine(means, variances, weights=None, *, method="moe", prior_variance=None):
    """Merge expert predictions with the rule named by ``method``.

    Parameters
    ----------
    means : array-like of shape (n_queries, n_experts)
        Latent means of the experts.
    variances : array-like of shape (n_queries, n_experts)
        Latent variances of the experts.
    weights : array-like of shape (n_queries, n_experts), default=None
        Non-negative gating weights; zero skips the expert at that query.
    method : {"moe", "poe", "gpoe", "bcm", "rbcm"}, default="moe"
        Mixture of experts, product of experts, generalised product of experts, Bayesian
        committee machine, robust Bayesian committee machine.
    prior_variance : array-like of shape (n_queries,) or (n_queries, n_experts), default=None
        Prior latent variance at each query; required by ``"bcm"`` and ``"rbcm"``.

    Returns
    -------
    MergedPrediction
        ``(proba, mean, variance)``, each of shape (n_queries,).

    Examples
    --------
    >>> from skoccmap.combine import combine
    >>> merged = combine([[1.0, 3.0]], [[1.0, 1.0]], method="poe")
    >>> float(merged.mean[0])
    2.0
    """
    if method not in COMBINERS:
        raise ValueError(f"method must be one of {sorted(COMBINERS)}, got {method!r}.")
    if method in _NEEDS_PRIOR:
        return COMBINERS[method](means, variances, prior_variance, weights)
    return COMBINERS[method](means, variances, weights)


def combine_pairs(
    query_index, means, variances, weights=None, *, n_queries, method="moe", prior_variance=None
):
    """Merge expert predictions given as (query, expert) pairs.

    The rules of :func:`combine` for maps in which each query consults a few of many
    experts: entry ``i`` of every array is the prediction of one expert at query
    ``query_index[i]``. The result is that of :func:`combine` on the dense arrays with
    these entries and zero weight elsewhere; nothing of size ``(n_queries, n_experts)``
    is formed. The per-query sums run over the pairs in the order given.

    Parameters
    ----------
    query_index : array-like of int of shape (n_pairs,)
        Query of each pair, in ``[0, n_queries)``.
    means : array-like of shape (n_pairs,)
        Latent mean of the pair's expert at its query.
    variances : array-like of shape (n_pairs,)
        Latent variance of the pair's expert at its query.
    weights : array-like of shape (n_pairs,), default=None
        Non-negative gating weights; a zero weight drops the pair. ``None`` weights all
        pairs equally.
    n_queries : int
        Number of queries; each needs at least one pair with positive weight.
    method : {"moe", "poe", "gpoe", "bcm", "rbcm"}, default="moe"
        Merging rule, as in :func:`combine`.
    prior_variance : array-like of shape (n_pairs,), default=None
        Prior latent variance of the pair's expert at its query; required by ``"bcm"``
        and ``"rbcm"``.

    Returns
    -------
    MergedPrediction
        ``(proba, mean, variance)``, each of shape (n_queries,).

    Examples
    --------
    Query 0 is seen by two experts, query 1 by one:

    >>> from skoccmap.combine import combine_pairs
    >>> merged = combine_pairs([0, 0, 1], [1.0, 3.0, -1.0], [1.0, 1.0, 2.0],
    ...                        n_queries=2, method="poe")
    >>> merged.mean.tolist(), merged.variance.tolist()
    ([2.0, -1.0], [0.5, 2.0])
    """
    if method not in _RULES:
        raise ValueError(f"method must be one of {sorted(_RULES)}, got {method!r}.")
    if method in _NEEDS_PRIOR and prior_variance is None:
        raise ValueError(f"prior_variance is required by method={method!r}.")
    if not (isinstance(n_queries, Integral) and n_queries >= 0):
        raise ValueError(f"n_queries must be an integer >= 0, got {n_queries!r}.")
    n_queries = int(n_queries)
    query = np.asarray(query_index)
    if query.size == 0:
        query = query.astype(np.intp)  # [] is a float array
    arrays = {"means": means, "variances": variances}
    if weights is not None:
        arrays["weights"] = weights
    if prior_variance is not None:
        arrays["prior_variance"] = prior_variance
    arrays = {name: np.asarray(a, dtype=np.float64) for name, a in arrays.items()}
    if query.ndim != 1 or not np.issubdtype(query.dtype, np.integer):
        raise ValueError("query_index must be a 1-D array of integers.")
    for name, a in arrays.items():
        if a.shape != query.shape:
            raise ValueError(
                f"{name} has shape {a.shape}, expected the shape of query_index {query.shape}."
            )
    if query.size and (query.min() < 0 or query.max() >= n_queries):
        raise ValueError(f"query_index must lie in [0, n_queries={n_queries}).")
    w = arrays.get("weights", np.ones(query.shape))
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights must be finite and non-negative.")
    used = w > 0
    if np.bincount(query[used], minlength=n_queries).min(initial=1) == 0:
        raise ValueError(
            "a query has no pair with positive weight: every query needs at least one expert."
        )
    for name in ("means", "variances", "prior_variance"):
        if name in arrays and not np.all(np.isfinite(arrays[name][used])):
            raise ValueError(
                f"{name} contains NaN or infinite values where the weight is positive."
            )
    for name in ("variances", "prior_variance"):
        if name in arrays and np.any(arrays[name][used] <= 0):
            raise ValueError(f"{name} must be positive where the weight is positive.")
    prior = arrays.get("prior_variance")
    pairs = _Pairs(
        query[used].astype(np.intp),
        n_queries,
        arrays["means"][used],
        arrays["variances"][used],
        w[used],
        None if prior is None else prior[used],
    )
    return _RULES[method](pairs)
