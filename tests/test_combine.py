"""The merging rules against their defining formulas, computed independently.

References integrate the defining densities numerically (scipy.integrate.quad) rather than
re-using the closed forms: a product of Gaussian densities (PoE), tempered by exponents
(gPoE), divided by the prior M-1 times (BCM), and the mixture of probit likelihoods (MoE).
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import integrate, special, stats

from skoccmap.combine import (
    COMBINERS,
    bayesian_committee_machine,
    combine,
    combine_pairs,
    generalized_product_of_experts,
    mixture_of_experts,
    product_of_experts,
    robust_bayesian_committee_machine,
)


def _moments(log_density, center, scale, density=None):
    """Mean and variance of an unnormalised 1-D density (or its log), by quadrature."""
    lo, hi = center - 12 * scale, center + 12 * scale
    if density is None:
        shift = log_density(center)

        def density(f):
            return np.exp(log_density(f) - shift)

    z = integrate.quad(density, lo, hi, epsabs=0, epsrel=1e-11, limit=200)[0]
    m1 = integrate.quad(lambda f: f * density(f), lo, hi, epsabs=0, epsrel=1e-11, limit=200)[0]
    m2 = integrate.quad(lambda f: f * f * density(f), lo, hi, epsabs=0, epsrel=1e-11, limit=200)[0]
    mean = m1 / z
    return mean, m2 / z - mean**2


@pytest.fixture
def experts():
    rng = np.random.default_rng(0)
    n, k = 5, 3
    prior = rng.uniform(1.0, 3.0, size=n)
    variances = prior[:, None] * rng.uniform(0.1, 0.9, size=(n, k))
    means = rng.normal(0, 1.5, size=(n, k))
    weights = rng.dirichlet(np.ones(k), size=n)
    return means, variances, weights, prior


def _log_gauss(f, mu, var):
    # Written out: scipy.stats' per-call overhead inside quad dominates the test time.
    return -0.5 * np.log(2 * np.pi * var) - 0.5 * (f - mu) ** 2 / var


def test_moe_matches_quadrature_of_mixture(experts):
    means, variances, weights, _ = experts
    merged = mixture_of_experts(means, variances, weights)
    for i in range(means.shape[0]):
        # p(y=1) = int Phi(f) sum_k w_k N(f; mu_k, s_k^2) df  (probit likelihood)
        def mix(f, i=i):
            return np.sum(weights[i] * np.exp(_log_gauss(f, means[i], variances[i])))

        lo, hi = -30, 30
        proba = integrate.quad(lambda f, m=mix: special.ndtr(f) * m(f), lo, hi, limit=200)[0]
        mean, var = _moments(None, 0.0, 3.0, density=mix)
        np.testing.assert_allclose(merged.proba[i], proba, rtol=1e-7)
        np.testing.assert_allclose(merged.mean[i], mean, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(merged.variance[i], var, rtol=1e-7)


def test_moe_normalises_weights(experts):
    means, variances, weights, _ = experts
    a = mixture_of_experts(means, variances, weights)
    b = mixture_of_experts(means, variances, 7.5 * weights)
    np.testing.assert_allclose(a.proba, b.proba, rtol=1e-12)
    np.testing.assert_allclose(a.variance, b.variance, rtol=1e-12)


def test_poe_matches_product_of_densities(experts):
    means, variances, _, _ = experts
    merged = product_of_experts(means, variances)
    for i in range(means.shape[0]):
        mean, var = _moments(
            lambda f, i=i: sum(_log_gauss(f, means[i, k], variances[i, k]) for k in range(3)),
            means[i].mean(),
            1.0,
        )
        np.testing.assert_allclose(merged.mean[i], mean, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(merged.variance[i], var, rtol=1e-7)
        np.testing.assert_allclose(
            merged.proba[i], stats.norm.cdf(mean / np.sqrt(1 + var)), rtol=1e-7
        )


def test_gpoe_matches_tempered_product(experts):
    means, variances, weights, _ = experts
    merged = generalized_product_of_experts(means, variances, weights)
    betas = weights / weights.sum(axis=1, keepdims=True)
    for i in range(means.shape[0]):
        mean, var = _moments(
            lambda f, i=i: sum(
                betas[i, k] * _log_gauss(f, means[i, k], variances[i, k]) for k in range(3)
            ),
            means[i].mean(),
            2.0,
        )
        np.testing.assert_allclose(merged.mean[i], mean, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(merged.variance[i], var, rtol=1e-7)


def test_bcm_matches_product_over_prior_powers(experts):
    means, variances, _, prior = experts
    merged = bayesian_committee_machine(means, variances, prior)
    m = means.shape[1]
    for i in range(means.shape[0]):
        # p(f | D) proportional to prod_k p_k(f | D_k) / p(f)^(M-1)   (Tresp 2000)
        mean, var = _moments(
            lambda f, i=i: (
                sum(_log_gauss(f, means[i, k], variances[i, k]) for k in range(m))
                - (m - 1) * _log_gauss(f, 0.0, prior[i])
            ),
            means[i].mean(),
            1.0,
        )
        np.testing.assert_allclose(merged.mean[i], mean, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(merged.variance[i], var, rtol=1e-7)


def test_rbcm_matches_entropy_weighted_product(experts):
    means, variances, _, prior = experts
    merged = robust_bayesian_committee_machine(means, variances, prior)
    m = means.shape[1]
    for i in range(means.shape[0]):
        # beta_k = H[prior] - H[posterior_k], the differential-entropy drop (Deisenroth & Ng).
        betas = [
            stats.norm(0, np.sqrt(prior[i])).entropy()
            - stats.norm(0, np.sqrt(variances[i, k])).entropy()
            for k in range(m)
        ]
        mean, var = _moments(
            lambda f, i=i, b=betas: (
                sum(b[k] * _log_gauss(f, means[i, k], variances[i, k]) for k in range(m))
                + (1 - sum(b)) * _log_gauss(f, 0.0, prior[i])
            ),
            means[i].mean(),
            1.0,
        )
        np.testing.assert_allclose(merged.mean[i], mean, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(merged.variance[i], var, rtol=1e-7)


def test_bcm_per_expert_priors_reduce_to_shared_prior(experts):
    means, variances, _, prior = experts
    shared = bayesian_committee_machine(means, variances, prior)
    per_expert = bayesian_committee_machine(
        means, variances, np.repeat(prior[:, None], means.shape[1], axis=1)
    )
    np.testing.assert_allclose(shared.mean, per_expert.mean, rtol=1e-12)
    np.testing.assert_allclose(shared.variance, per_expert.variance, rtol=1e-12)


@pytest.mark.parametrize("method", ["bcm", "rbcm"])
def test_committee_machines_with_different_priors_per_expert(method):
    # Two experts with their own priors, written out: the common prior precision is the
    # mean of theirs, and each adds its (rBCM: entropy-weighted) gain over its own prior.
    mu, var, prior = np.array([0.8, -0.3]), np.array([0.5, 1.2]), np.array([1.0, 4.0])
    merged = combine([mu], [var], method=method, prior_variance=[prior])
    if method == "bcm":
        b1 = b2 = 1.0
    else:
        b1, b2 = 0.5 * np.log(1.0 / 0.5), 0.5 * np.log(4.0 / 1.2)
    precision = 0.5 * (1 / 1.0 + 1 / 4.0) + b1 * (1 / 0.5 - 1 / 1.0) + b2 * (1 / 1.2 - 1 / 4.0)
    mean = (b1 * 0.8 / 0.5 + b2 * -0.3 / 1.2) / precision
    np.testing.assert_allclose(merged.variance, [1 / precision], rtol=1e-12)
    np.testing.assert_allclose(merged.mean, [mean], rtol=1e-12)


@pytest.mark.parametrize("method", sorted(COMBINERS))
def test_zero_weight_skips_expert_even_if_nan(experts, method):
    means, variances, weights, prior = experts
    weights = weights.copy()
    weights[:, 1] = 0.0
    means = means.copy()
    variances = variances.copy()
    means[:, 1] = np.nan
    variances[:, 1] = np.nan
    keep = [0, 2]
    full = combine(means, variances, weights, method=method, prior_variance=prior)
    dropped = combine(
        means[:, keep], variances[:, keep], weights[:, keep], method=method, prior_variance=prior
    )
    for a, b in zip(full, dropped, strict=True):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=1e-12)


@pytest.mark.parametrize("method", sorted(COMBINERS))
def test_single_expert_is_returned_unchanged(method):
    means = np.array([[0.7], [-1.2]])
    variances = np.array([[0.4], [0.9]])
    merged = combine(means, variances, method=method, prior_variance=np.array([1.0, 1.5]))
    if method == "rbcm":
        # rBCM mixes the single expert with the prior according to its entropy drop.
        assert np.all(merged.variance > variances[:, 0])
        assert np.all(merged.variance < [1.0, 1.5])
    else:
        np.testing.assert_allclose(merged.mean, means[:, 0], rtol=1e-12)
        np.testing.assert_allclose(merged.variance, variances[:, 0], rtol=1e-12)
    np.testing.assert_allclose(
        merged.proba, stats.norm.cdf(merged.mean / np.sqrt(1 + merged.variance)), rtol=1e-12
    )


@pytest.mark.parametrize("method", ["gpoe", "rbcm"])
def test_uninformed_experts_give_back_the_prior(method):
    # Far from all data each expert returns its prior; gPoE and rBCM then return the prior
    # too, whereas PoE would shrink the variance by the number of experts.
    prior = np.array([1.3, 0.8])
    variances = np.repeat(prior[:, None], 4, axis=1)
    means = np.zeros_like(variances)
    merged = combine(means, variances, method=method, prior_variance=prior)
    np.testing.assert_allclose(merged.variance, prior, rtol=1e-12)
    poe = product_of_experts(means, variances)
    np.testing.assert_allclose(poe.variance, prior / 4, rtol=1e-12)


@pytest.mark.parametrize("method", ["bcm", "rbcm"])
def test_experts_above_their_prior_add_no_information(method):
    # A posterior variance above the prior (rounding, or an expert from elsewhere) removes no
    # information: the merged variance is the prior's, and rBCM gives such experts no weight.
    prior = np.array([1.0, 2.0])
    variances = 1.5 * np.repeat(prior[:, None], 3, axis=1)
    means = np.array([[0.3, -0.2, 0.5], [1.0, 0.4, -0.7]])
    merged = combine(means, variances, method=method, prior_variance=prior)
    np.testing.assert_allclose(merged.variance, prior, rtol=1e-12)
    if method == "rbcm":
        assert np.all(merged.mean == 0.0)


finite = st.floats(-50, 50, allow_nan=False)
positive = st.floats(1e-6, 50, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    means=arrays(np.float64, (4, 3), elements=finite),
    scale=arrays(np.float64, (4, 3), elements=st.floats(1e-6, 1.0)),
    weights=arrays(np.float64, (4, 3), elements=st.floats(0.0, 1.0)),
    prior=arrays(np.float64, (4,), elements=positive),
)
def test_every_combiner_gives_valid_output(means, scale, weights, prior):
    weights[:, 0] += 1e-3  # at least one expert per query
    variances = scale * prior[:, None]
    for method in COMBINERS:
        proba, mean, var = combine(means, variances, weights, method=method, prior_variance=prior)
        assert np.all((proba >= 0) & (proba <= 1)), method
        assert np.all(np.isfinite(mean)), method
        assert np.all(var > 0) and np.all(np.isfinite(var)), method


@pytest.mark.parametrize("method", ["moe", "poe", "gpoe", "bcm", "rbcm"])
def test_extreme_finite_inputs_stay_finite(method):
    # Weights near the float maximum merge as equal weights do; a subnormal variance is
    # floored as the experts' own are (1 / it is infinite).
    means, variances, prior = [[1.0, -0.5]], [[1.0, 2.0]], [[3.0, 3.0]]
    huge = combine(means, variances, [[1e308, 1e308]], method=method, prior_variance=prior)
    equal = combine(means, variances, [[1.0, 1.0]], method=method, prior_variance=prior)
    np.testing.assert_allclose(huge, equal, rtol=1e-12)
    tiny = combine(means, [[1e-320, 1.0]], method=method, prior_variance=prior)
    assert np.all(np.isfinite(tiny.proba)) and np.all(np.isfinite(tiny.mean))
    if method != "moe":  # the product rules follow the sure expert
        np.testing.assert_allclose(tiny.mean, [1.0])


@pytest.mark.parametrize("method", sorted(COMBINERS))
def test_subnormal_variances_give_a_positive_merged_variance(method):
    # Two sure experts that agree, at the smallest subnormal variance: half of it rounds to
    # zero, yet the merged variance is documented strictly positive (its floor, 1e-12, is far
    # below any variance a GP reports).
    tiny = np.nextafter(0.0, 1.0)
    merged = combine([[0.3, 0.3]], [[tiny, tiny]], method=method, prior_variance=[tiny])
    assert np.all(merged.variance > 0) and np.all(np.isfinite(merged.variance))
    assert np.all(np.isfinite(merged.mean)) and np.all(np.isfinite(merged.proba))


def test_bcm_of_one_expert_with_a_subnormal_prior_is_that_expert():
    # With M = 1 the committee divides the prior out M - 1 = 0 times: the expert itself,
    # also when its variance and prior are subnormal (their reciprocals overflow).
    mu = np.array([[1.0], [-0.5]])
    merged = bayesian_committee_machine(mu, [[1e-320], [3e-321]], [1e-320, 4e-321])
    np.testing.assert_allclose(merged.mean, mu[:, 0], rtol=1e-12)
    np.testing.assert_allclose(merged.proba, stats.norm.cdf(mu[:, 0]), rtol=1e-9)


@pytest.mark.parametrize("method", ["moe", "poe", "gpoe", "bcm", "rbcm"])
def test_variances_at_the_largest_float_give_an_uninformed_finite_answer(method):
    # Experts that know nothing (variance and prior at the largest float): probability 1/2,
    # a finite mean and variance, never NaN.
    big = np.finfo(np.float64).max
    out = combine([[1.0, -2.0]], [[big, big]], method=method, prior_variance=[big])
    assert np.all(np.isfinite(out.mean)) and np.all(np.isfinite(out.variance))
    assert np.all(out.variance > 1e300)
    np.testing.assert_allclose(out.proba, [0.5], atol=1e-12)


@pytest.mark.parametrize("method", ["moe", "poe", "gpoe", "bcm", "rbcm"])
def test_means_near_the_largest_float_give_finite_merges(method):
    # Sure experts with latent means near the float maximum: their weighted sums overflowed
    # (poe, gpoe and bcm gave an infinite mean, moe an infinite variance, and rbcm a NaN
    # probability where the means had both signs). The merge saturates at the largest float.
    big = np.finfo(np.float64).max
    means = np.array([[1e308, 1e308], [1e308, -1e308], [big, big], [1e300, -3e300]])
    for variances, prior in (([1.0, 1.0], 4.0), ([1e-12, 1e-12], 1e10)):
        variances = np.broadcast_to(variances, means.shape)
        merged = combine(
            means, variances, method=method, prior_variance=np.full(len(means), prior)
        )
        for part in merged:
            assert np.all(np.isfinite(part)), (method, variances[0, 0], merged)
        # Agreeing experts give a sure answer; the mixture averages two sure ones that differ.
        np.testing.assert_allclose(merged.proba[[0, 2]], 1.0)
        assert merged.proba[3] == (0.5 if method == "moe" else 0.0)
    # The scaling is exact: means a power of two apart merge as their scaled copies do.
    small = combine(means / 2.0**1000, [[1.0, 2.0]] * 4, method=method, prior_variance=[4.0] * 4)
    large = combine(means, [[1.0, 2.0]] * 4, method=method, prior_variance=[4.0] * 4)
    np.testing.assert_array_equal(large.mean[[0, 1, 3]], small.mean[[0, 1, 3]] * 2.0**1000)
    pairs = combine_pairs(
        [0, 0],
        [1e308, -1e308],
        [1e-12, 1e-12],
        n_queries=1,
        method=method,
        prior_variance=[1e10] * 2,
    )
    np.testing.assert_allclose(pairs.proba, [0.5])


def test_bad_inputs_raise_clear_errors():
    m = np.zeros((2, 2))
    v = np.ones((2, 2))
    with pytest.raises(ValueError, match="method"):
        combine(m, v, method="average")
    with pytest.raises(ValueError, match="variances has shape"):
        combine(m, np.ones((2, 3)))
    with pytest.raises(ValueError, match="means must be a 2-D"):
        combine(np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="weights has shape"):
        combine(m, v, np.ones((3, 2)))
    with pytest.raises(ValueError, match="non-negative"):
        combine(m, v, [[1, -1], [1, 1]])
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="weights must be finite"):
            combine(m, v, [[bad, 1], [1, 1]])
    with pytest.raises(ValueError, match="row of zeros"):
        combine(m, v, [[0, 0], [1, 1]])
    with pytest.raises(ValueError, match="means contains NaN"):
        combine([[np.nan, 0], [0, 0]], v)
    with pytest.raises(ValueError, match="variances must be finite and positive"):
        combine(m, [[0, 1], [1, 1]])
    with pytest.raises(ValueError, match="variances must be finite and positive"):
        combine(m, [[np.inf, 1], [1, 1]])
    with pytest.raises(ValueError, match="prior_variance must be finite and positive"):
        combine(m, v, method="bcm", prior_variance=[1.0, 0.0])
    with pytest.raises(ValueError, match="prior_variance is required"):
        combine(m, v, method="bcm")
    with pytest.raises(ValueError, match="prior_variance has shape"):
        combine(m, v, method="rbcm", prior_variance=np.ones(3))
    with pytest.raises(ValueError, match="no expert columns"):
        combine(np.zeros((2, 0)), np.zeros((2, 0)))


# --- pairs ---------------------------------------------------------------------------------


@pytest.mark.parametrize("method", sorted(COMBINERS))
def test_pairs_equal_the_dense_rule_on_a_sparse_mask(method):
    rng = np.random.default_rng(7)
    n, k = 40, 9
    means = rng.normal(size=(n, k))
    variances = rng.uniform(0.1, 2.0, size=(n, k))
    prior = variances + rng.uniform(0.0, 1.0, size=(n, k))
    weights = rng.uniform(size=(n, k)) * (rng.uniform(size=(n, k)) < 0.4)
    weights[np.arange(n), rng.integers(0, k, n)] += 0.1
    # Entries that are not pairs hold NaN in the dense arrays: never read.
    skipped = weights == 0
    means[skipped] = variances[skipped] = prior[skipped] = np.nan
    dense = combine(means, variances, weights, method=method, prior_variance=prior)
    # Pairs in a shuffled order, plus zero-weight pairs that must be dropped unread.
    q, e = np.nonzero(~skipped)
    order = rng.permutation(q.size)
    q, e = q[order], e[order]
    zero_q = rng.integers(0, n, 5)
    merged = combine_pairs(
        np.r_[q, zero_q],
        np.r_[means[q, e], np.full(5, np.nan)],
        np.r_[variances[q, e], np.full(5, np.nan)],
        np.r_[weights[q, e], np.zeros(5)],
        n_queries=n,
        method=method,
        prior_variance=np.r_[prior[q, e], np.full(5, np.nan)],
    )
    for got, want in zip(merged, dense, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


def test_pairs_refuse_bad_input():
    ok = dict(n_queries=2, method="poe")
    with pytest.raises(ValueError, match="at least one expert"):
        combine_pairs([0, 0], [1.0, 2.0], [1.0, 1.0], **ok)
    # A query whose only pair has zero weight has no expert either.
    with pytest.raises(ValueError, match="at least one expert"):
        combine_pairs([0, 1], [1.0, 2.0], [1.0, 1.0], [1.0, 0.0], **ok)
    with pytest.raises(ValueError, match=r"\[0, n_queries=2\)"):
        combine_pairs([0, 2], [1.0, 2.0], [1.0, 1.0], **ok)
    with pytest.raises(ValueError, match=r"\[0, n_queries=2\)"):
        combine_pairs([-1, 1], [1.0, 2.0], [1.0, 1.0], **ok)
    with pytest.raises(ValueError, match="shape"):
        combine_pairs([0, 1], [1.0], [1.0, 1.0], **ok)
    with pytest.raises(ValueError, match="integers"):
        combine_pairs([0.0, 1.0], [1.0, 2.0], [1.0, 1.0], **ok)
    with pytest.raises(ValueError, match="positive"):
        combine_pairs([0, 1], [1.0, 2.0], [1.0, 0.0], **ok)
    with pytest.raises(ValueError, match="NaN"):
        combine_pairs([0, 1], [1.0, np.nan], [1.0, 1.0], **ok)
    with pytest.raises(ValueError, match="prior_variance is required"):
        combine_pairs([0, 1], [1.0, 2.0], [1.0, 1.0], n_queries=2, method="rbcm")
    with pytest.raises(ValueError, match="prior_variance must be positive"):
        combine_pairs(
            [0, 1], [1.0, 2.0], [1.0, 1.0], n_queries=2, method="bcm", prior_variance=[1.0, 0.0]
        )
    with pytest.raises(ValueError, match="method must be one of"):
        combine_pairs([0, 1], [1.0, 2.0], [1.0, 1.0], n_queries=2, method="mean")


def test_combine_pairs_checks_n_queries_and_takes_no_pairs():
    with pytest.raises(ValueError, match="n_queries must be an integer >= 0, got 1.7"):
        combine_pairs([0], [0.0], [1.0], n_queries=1.7)
    merged = combine_pairs([], [], [], n_queries=0)
    assert all(a.shape == (0,) and a.dtype == np.float64 for a in merged)
