"""Reference tests for the EP functions in skoccmap.ep.

References are computed independently: quadrature of the tilted distributions, dense inverses of
small matrices, the defining product form of the EP evidence, the exact probit evidence as a
Gaussian orthant probability, and finite differences.
"""

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import multivariate_normal, norm
from sklearn.gaussian_process.kernels import RBF
from sklearn.gaussian_process.kernels import ConstantKernel as C

import skoccmap.ep as ep_module
from skoccmap.ep import (
    ep_append_sites,
    ep_latent_joint_predictive,
    ep_latent_predictive,
    ep_latent_predictive_packed,
    ep_log_marginal_likelihood,
    ep_log_marginal_likelihood_gradient,
    ep_posterior,
    expectation_propagation,
    probit_site_update,
)


def _problem(n=12, signal=2.0, length_scale=0.7, noise=0.4, seed=0, ard=False):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, size=(n, 2))
    y = np.where(np.sin(2 * X[:, 0]) + X[:, 1] + noise * rng.standard_normal(n) > 0, 1.0, -1.0)
    ls = [length_scale, 1.3 * length_scale] if ard else length_scale
    kernel = C(signal) * RBF(ls)
    return kernel, X, y


def _tilted_moments(y, mu_cav, s2_cav, m=0.0):
    """Moments of Phi(y (g + m)) N(g | mu_cav, s2_cav) by quadrature."""
    sd = np.sqrt(s2_cav)
    lo, hi = mu_cav - 12 * sd, mu_cav + 12 * sd

    def w(g):
        return norm.cdf(y * (g + m)) * norm.pdf(g, mu_cav, sd)

    z0 = quad(w, lo, hi, epsabs=0, epsrel=1e-12, limit=200)[0]
    z1 = quad(lambda g: g * w(g), lo, hi, epsabs=0, epsrel=1e-12, limit=200)[0]
    z2 = quad(lambda g: g * g * w(g), lo, hi, epsabs=0, epsrel=1e-12, limit=200)[0]
    mean = z1 / z0
    return z0, mean, z2 / z0 - mean**2


def _matched_sites(K, y, tau, nu, sites=None):
    """Sites matching the tilted moments of the marginals of the sites ``tau``, ``nu``: the
    posterior densely, the moments of R&W eq. 3.58 in closed form (eq. 3.59)."""
    n = len(y)
    Sigma = np.linalg.solve(np.eye(n) + K * tau, K)
    mu, var = Sigma @ nu, np.diag(Sigma)
    tau_cav, nu_cav = 1 / var - tau, mu / var - nu
    mu_cav, s2_cav = nu_cav / tau_cav, 1 / tau_cav
    z = y * mu_cav / np.sqrt(1 + s2_cav)
    ratio = norm.pdf(z) / norm.cdf(z)
    mean = mu_cav + y * s2_cav * ratio / np.sqrt(1 + s2_cav)
    var_hat = s2_cav - s2_cav**2 * ratio * (z + ratio) / (1 + s2_cav)
    tau_new, nu_new = tau.copy(), nu.copy()
    sites = np.arange(n) if sites is None else sites
    tau_new[sites] = 1 / var_hat[sites] - tau_cav[sites]
    nu_new[sites] = mean[sites] / var_hat[sites] - nu_cav[sites]
    return tau_new, nu_new


@pytest.mark.parametrize("y", [-1.0, 1.0])
@pytest.mark.parametrize("k", [0.3, 4.0])
@pytest.mark.parametrize("m", [-0.8, 0.0, 1.1])
def test_single_observation_is_exact(y, k, m):
    # One site sees the exact likelihood: EP is exact for n = 1 (R&W section 3.6).
    K = np.array([[k]])
    res = expectation_propagation(K, [y], mean=m, tol=1e-13, damping=0.0)
    assert res.converged
    lml = ep_log_marginal_likelihood(K, [y], res.site_precision, res.site_nu, mean=m)
    np.testing.assert_allclose(lml, norm.logcdf(y * m / np.sqrt(1 + k)), rtol=1e-10)
    z0, mean, var = _tilted_moments(y, 0.0, k, m)
    np.testing.assert_allclose(res.posterior.mean[0], mean, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.posterior.var[0], var, rtol=1e-8)


@pytest.mark.parametrize(
    "y, tau_cav, nu_cav, m",
    [(1.0, 1.0, 0.0, 0.0), (-1.0, 0.2, 1.5, 0.3), (1.0, 5.0, -10.0, 0.0), (-1.0, 0.05, 0.4, -2.0)],
)
def test_site_update_matches_tilted_moments(y, tau_cav, nu_cav, m):
    # New site = tilted moments divided by the cavity, in natural parameters (R&W eq. 3.59).
    tau, nu, log_Z = probit_site_update(
        np.array([y]), np.array([tau_cav]), np.array([nu_cav]), np.array([m])
    )
    z0, mean, var = _tilted_moments(y, nu_cav / tau_cav, 1 / tau_cav, m)
    np.testing.assert_allclose(np.exp(log_Z[0]), z0, rtol=1e-9)
    np.testing.assert_allclose(tau[0], 1 / var - tau_cav, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(nu[0], mean / var - nu_cav, rtol=1e-7, atol=1e-12)


def test_site_update_far_tail_is_finite_and_nonnegative():
    # z -> -inf (a confidently wrong cavity) must not overflow; z -> +inf gives a flat site.
    tau, nu, log_Z = probit_site_update(
        np.array([1.0, 1.0, -1.0]), np.array([1.0, 1.0, 1.0]), np.array([-60.0, 60.0, 60.0])
    )
    assert np.all(np.isfinite(tau)) and np.all(np.isfinite(nu)) and np.all(np.isfinite(log_Z))
    assert np.all(tau >= 0)
    assert tau[1] < 1e-100


@pytest.mark.parametrize("nu_cav", [-1e2, -1e3, -1e4, -1e5, -1e8])
def test_site_update_far_into_the_wrong_tail_stays_a_proper_site(nu_cav):
    # z = nu_cav / sqrt(2) for tau_cav = 1: r = lambda (z + lambda) in [0, 1] and
    # tau = r / (2 - r) <= 1. Against the asymptotic series z + lambda = 1/x - 2/x^3 +
    # 10/x^5 - 74/x^7 (x = -z, exact to 1e-12 here) up to |z| ~ 1e3, a cavity a thousand
    # standard deviations on the wrong side; beyond, z + lambda cancels to a relative error
    # of about z^4 eps in 1 - tau, and the bounds hold (unclipped, r came out above 1 and
    # tau negative).
    tau, nu, log_Z = probit_site_update(np.array([1.0]), np.array([1.0]), np.array([nu_cav]))
    assert np.isfinite(tau[0]) and np.isfinite(nu[0]) and np.isfinite(log_Z[0])
    assert 0.0 <= tau[0] <= 1.0
    x = -nu_cav / np.sqrt(2.0)
    if x < 1e3:
        delta = 1 / x - 2 / x**3 + 10 / x**5 - 74 / x**7
        one_minus_r = 1.0 - (x + delta) * delta
        np.testing.assert_allclose(1.0 - tau[0], 2 * one_minus_r / (1 + one_minus_r), rtol=1e-4)


def test_fixed_point_marginals_match_tilted_moments():
    # At an EP fixed point each posterior marginal has the moments of its tilted distribution.
    kernel, X, y = _problem(n=6)
    res = expectation_propagation(kernel(X), y, tol=1e-12)
    assert res.converged
    post = res.posterior
    tau_cav = 1 / post.var - res.site_precision
    mu_cav = (post.mean / post.var - res.site_nu) / tau_cav
    for i in range(len(y)):
        _, mean, var = _tilted_moments(y[i], mu_cav[i], 1 / tau_cav[i])
        np.testing.assert_allclose(post.mean[i], mean, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(post.var[i], var, rtol=1e-7)


def _dense_posterior(K, tau, nu):
    Sigma = np.linalg.inv(np.linalg.inv(K) + np.diag(tau))
    return Sigma @ nu, Sigma


@pytest.mark.parametrize(
    "tau",
    [
        np.array([0.5, 2.0, 0.0, 1e-9, 3.0, 1e-14, 0.7, 10.0]),  # flat and vanishing sites
        np.array([0.5, -0.3, 1.0, 2.0, -0.2, 0.4, 1.5, 0.8]),  # negative precisions (LU path)
        np.zeros(8),  # all sites flat: the prior, with nu still entering the mean
    ],
)
def test_posterior_matches_dense_inverse(tau):
    rng = np.random.default_rng(1)
    A = rng.standard_normal((8, 8))
    K = A @ A.T / 8 + 0.8 * np.eye(8)  # well conditioned, so the dense inverse is a reference
    nu = rng.standard_normal(8)
    post = ep_posterior(K, tau, nu)
    mean, Sigma = _dense_posterior(K, tau, nu)
    assert np.all(np.isfinite(post.var))
    np.testing.assert_allclose(post.var, np.diag(Sigma), rtol=1e-10)
    np.testing.assert_allclose(post.mean, mean, rtol=1e-10, atol=1e-12)
    # det(I + S^1/2 K S^1/2) = det(I + K S) (Sylvester), also for negative precisions.
    sign, log_det = np.linalg.slogdet(np.eye(8) + K * tau)
    assert sign > 0
    np.testing.assert_allclose(post.log_det_B, log_det, rtol=1e-10, atol=1e-12)
    # Predictions at new points from the joint Gaussian of (f, f_*).
    B = rng.standard_normal((3, 8))
    K_star = B @ A.T / 8
    k_ss = np.einsum("ij,ij->i", B, B) / 8 + 0.8
    m_star, v_star = ep_latent_predictive(K_star, k_ss, post)
    K_inv_Ks = np.linalg.solve(K, K_star.T)
    np.testing.assert_allclose(m_star, K_inv_Ks.T @ mean, rtol=1e-9, atol=1e-12)
    v_ref = k_ss - np.einsum("ij,ji->i", K_star, K_inv_Ks)
    v_ref += np.einsum("ji,jk,ki->i", K_inv_Ks, Sigma, K_inv_Ks)
    np.testing.assert_allclose(v_star, v_ref, rtol=1e-9)


def test_variances_of_nearly_flat_sites_are_not_lost_to_cancellation():
    # Sites so weak that 1 - [B^-1]_ii is between 1e-7 and 1e-4: the posterior variance is
    # within a hair of the prior's, and is recomputed rather than taken from the difference.
    rng = np.random.default_rng(1)
    A = rng.standard_normal((8, 8))
    K = A @ A.T / 8 + 0.8 * np.eye(8)
    tau = np.array([2e-7, 1e-6, 3e-6, 1e-5, 3e-5, 2.0, 0.5, 1e-4])
    nu = rng.standard_normal(8)
    _, Sigma = _dense_posterior(K, tau, nu)
    np.testing.assert_allclose(ep_posterior(K, tau, nu).var, np.diag(Sigma), rtol=1e-11)


def test_posterior_of_flat_sites_keeps_the_natural_means_it_was_given():
    # All sites flat: alpha = (I + S K)^-1 nu = nu and the mean is K nu, whatever the
    # caller does with its array of natural means afterwards.
    rng = np.random.default_rng(1)
    A = rng.standard_normal((5, 5))
    K = A @ A.T / 5 + 0.8 * np.eye(5)
    nu = rng.standard_normal(5)
    given = nu.copy()
    post = ep_posterior(K, np.zeros(5), nu)
    nu[:] = 7.0
    np.testing.assert_array_equal(post.alpha, given)
    np.testing.assert_allclose(post.mean, K @ given, rtol=1e-12)


def test_negative_precisions_that_need_row_exchanges_match_dense_inverse():
    # I + K S = [[0, 0.9], [-0.9, 2]]: its LU factorisation exchanges the rows and has a
    # negative pivot, yet K^-1 + S is positive definite and det(I + K S) = 0.81.
    K = np.array([[1.0, 0.9], [0.9, 1.0]])
    tau, nu = np.array([-1.0, 1.0]), np.array([0.3, -0.7])
    assert np.all(np.linalg.eigvalsh(np.linalg.inv(K) + np.diag(tau)) > 0)
    post = ep_posterior(K, tau, nu)
    mean, Sigma = _dense_posterior(K, tau, nu)
    np.testing.assert_allclose(post.var, np.diag(Sigma), rtol=1e-12)
    np.testing.assert_allclose(post.mean, mean, rtol=1e-12)
    np.testing.assert_allclose(post.log_det_B, np.log(0.81), rtol=1e-12)


@pytest.mark.parametrize("n", [1, 64, 65, 130, 301])
def test_lower_inverse_matches_dense_inverse(n):
    # Sizes at, just above and well above the dtrtri base case (halves of odd sizes).
    rng = np.random.default_rng(n)
    L = np.tril(rng.standard_normal((n, n))) / np.sqrt(n)
    L[np.diag_indices(n)] = 1.0 + rng.uniform(size=n)  # like EP's factor: diagonal >= 1
    inverse = ep_module._lower_inverse(L)
    np.testing.assert_allclose(inverse, np.linalg.inv(L), rtol=1e-12, atol=1e-13)
    assert np.all(np.triu(inverse, 1) == 0.0)


def test_lower_inverse_of_a_singular_factor_raises():
    L = np.eye(100)
    L[90, 90] = 0.0
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        ep_module._lower_inverse(L)


def test_posterior_of_many_sites_matches_dense_inverse():
    # Beyond the base case of the factor's inverse, which gives the marginal variances.
    rng = np.random.default_rng(2)
    A = rng.standard_normal((150, 150))
    K = A @ A.T / 150 + 0.8 * np.eye(150)  # well conditioned, so the dense inverse is a reference
    tau = rng.uniform(0.0, 3.0, size=150)
    nu = rng.standard_normal(150)
    post = ep_posterior(K, tau, nu)
    mean, Sigma = _dense_posterior(K, tau, nu)
    np.testing.assert_allclose(post.var, np.diag(Sigma), rtol=1e-8)
    np.testing.assert_allclose(post.mean, mean, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize(
    "tau",
    [
        np.array([0.5, 2.0, 0.0, 1e-9, 3.0, 1e-14, 0.7, 10.0]),
        np.array([0.5, -0.3, 1.0, 2.0, -0.2, 0.4, 1.5, 0.8]),  # negative precisions (LU path)
    ],
)
def test_joint_predictive_matches_dense_computation(tau):
    rng = np.random.default_rng(2)
    A = rng.standard_normal((8, 8))
    K = A @ A.T / 8 + 0.8 * np.eye(8)
    nu = rng.standard_normal(8)
    mean, Sigma = _dense_posterior(K, tau, nu)
    B = rng.standard_normal((3, 8))
    K_star, K_ss = B @ A.T / 8, B @ B.T / 8 + 0.8 * np.eye(3)
    m_star, cov = ep_latent_joint_predictive(K_star, K_ss, ep_posterior(K, tau, nu))
    # Joint Gaussian of (f, f_*): E[f_* | f] = K_* K^-1 f, Cov = K_** - K_* K^-1 K_*^T.
    W = np.linalg.solve(K, K_star.T)
    np.testing.assert_allclose(m_star, W.T @ mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov, K_ss - K_star @ W + W.T @ Sigma @ W, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(cov, cov.T)


def test_packed_predictive_matches_dense_computation():
    # The factor's packed lower triangle, solved a test point at a time, against the
    # marginal of the dense joint predictive (R&W eq. 3.61 from the posterior).
    rng = np.random.default_rng(5)
    A = rng.standard_normal((40, 40))
    K = A @ A.T / 40 + 0.5 * np.eye(40)
    tau, nu = rng.uniform(0.0, 3.0, 40), rng.standard_normal(40)
    tau[:3] = [0.0, 1e-14, 50.0]
    posterior = ep_posterior(K, tau, nu)
    mean, Sigma = _dense_posterior(K, tau, nu)
    B = rng.standard_normal((5, 40))
    K_star, k_diag = B @ A.T / 40, np.einsum("ij,ij->i", B, B) / 40 + 0.5
    lower = posterior.L[np.tri(40, dtype=bool)]
    m_star, var = ep_latent_predictive_packed(K_star, k_diag, posterior._replace(L=None), lower)
    W = np.linalg.solve(K, K_star.T)
    np.testing.assert_allclose(m_star, W.T @ mean, rtol=1e-9, atol=1e-12)
    dense_var = k_diag - np.einsum("ij,ji->i", K_star, W) + np.einsum("ji,jk,ki->i", W, Sigma, W)
    np.testing.assert_allclose(var, dense_var, rtol=1e-9, atol=1e-12)
    # ... and the unpacked path's numbers, to rounding.
    np.testing.assert_allclose(
        np.column_stack([m_star, var]),
        np.column_stack(ep_latent_predictive(K_star, k_diag, posterior)),
        rtol=1e-12,
        atol=1e-14,
    )


def test_appended_sites_reach_the_whole_fixed_point_and_its_posterior():
    # Held at the fixed point of EP on all points, the current sites leave the new points'
    # sites at it too; the assembled factor and alpha must equal those of all sites.
    kernel, X, y = _problem(n=30, seed=3)
    K = kernel(X)
    whole = expectation_propagation(K, y, tol=1e-12)
    tau, nu = whole.site_precision, whole.site_nu
    current = ep_posterior(K[:22, :22], tau[:22], nu[:22])
    result, _ = ep_append_sites(current, K[22:, :22], K[22:, 22:], y[22:], tol=1e-12)
    np.testing.assert_allclose(result.site_precision, tau[22:], atol=1e-9)
    np.testing.assert_allclose(result.site_nu, nu[22:], atol=1e-9)
    full = ep_posterior(K, tau, nu)
    np.testing.assert_allclose(result.posterior.L, full.L, atol=1e-9)
    np.testing.assert_allclose(result.posterior.alpha, full.alpha, atol=1e-9)
    np.testing.assert_allclose(result.posterior.log_det_B, full.log_det_B, rtol=1e-10)
    assert result.posterior.mean is None and result.posterior.var is None


def test_appended_evidence_is_that_of_the_new_points_given_the_current_sites():
    # Z_EP of all sites = Z_EP(current) * integral of the current posterior times the new
    # sites (each site normalised at its own update): checked against the product form.
    kernel, X, y = _problem(n=14, seed=4)
    K = kernel(X)
    part = expectation_propagation(K[:10, :10], y[:10], tol=1e-12)
    result, log_new = ep_append_sites(part.posterior, K[10:, :10], K[10:, 10:], y[10:], tol=1e-12)
    mean, cov = ep_latent_joint_predictive(K[10:, :10], K[10:, 10:], part.posterior)
    direct = ep_log_marginal_likelihood(
        cov, y[10:], result.site_precision, result.site_nu - result.site_precision * mean,
        mean=mean,
    )  # fmt: skip
    np.testing.assert_allclose(log_new, direct)
    assert log_new < 0


def test_appended_sites_that_do_not_converge_give_none():
    kernel, X, y = _problem(n=14, seed=4)
    K = kernel(X)
    part = expectation_propagation(K[:10, :10], y[:10], tol=1e-12)
    # One sweep of EP on the new points' prior does not reach its fixed point.
    mean, cov = ep_latent_joint_predictive(K[10:, :10], K[10:, 10:], part.posterior)
    assert not expectation_propagation(cov, y[10:], mean=mean, max_iter=1).converged
    result = ep_append_sites(part.posterior, K[10:, :10], K[10:, 10:], y[10:], max_iter=1)
    assert result == (None, -np.inf)


def test_append_needs_the_cholesky_form():
    kernel, X, y = _problem(n=10)
    K = kernel(X)
    lu_form = ep_posterior(K[:8, :8], np.r_[-0.01, np.ones(7)], np.zeros(8))
    assert lu_form.L is None
    assert ep_append_sites(lu_form, K[8:, :8], K[8:, 8:], y[8:])[0] is None


@pytest.mark.parametrize("func", [ep_latent_joint_predictive, ep_append_sites])
def test_new_point_covariances_of_the_wrong_shape_are_refused(func):
    kernel, X, y = _problem(n=10)
    K = kernel(X)
    posterior = expectation_propagation(K[:8, :8], y[:8]).posterior
    with_nan = K[8:, :8].copy()
    with_nan[0, 0] = np.nan
    bad = [
        (K[8:, :7], K[8:, 8:], r"K_cross must have shape \(n_new, 8\)"),
        (K[8:, :8], K[7:, 7:], r"K_new must have shape \(2, 2\)"),
        (with_nan, K[8:, 8:], "NaN or infinite"),
    ]
    for K_cross, K_new, message in bad:
        with pytest.raises(ValueError, match=message):
            if func is ep_latent_joint_predictive:
                func(K_cross, K_new, posterior)
            else:
                func(posterior, K_cross, K_new, y[8:])


@pytest.mark.parametrize(
    "tau",
    [
        [1.0, -2.0, 1.0],  # det(I + K S) < 0
        [-2.0, -2.0, 1.0],  # det(I + K S) > 0, two negative directions
    ],
)
def test_improper_sites_raise_linalg_error(tau):
    K = np.eye(3)
    assert np.linalg.eigvalsh(np.linalg.inv(K) + np.diag(tau))[0] < 0
    with pytest.raises(np.linalg.LinAlgError, match="proper Gaussian"):
        ep_posterior(K, np.array(tau), np.zeros(3))


def test_two_negative_directions_with_positive_marginals_are_refused():
    # det(I + K S) > 0 and every marginal of (K^-1 + S)^-1 positive: only the inertia of
    # K^-1 + S tells that this is no Gaussian.
    K = np.array(
        [
            [4.256, -2.41, -0.217, -1.299],
            [-2.41, 4.57, 3.149, 1.993],
            [-0.217, 3.149, 5.037, 0.985],
            [-1.299, 1.993, 0.985, 1.923],
        ]
    )
    tau = np.array([-1.413, -1.141, 2.292, -2.026])
    precision = np.linalg.inv(K) + np.diag(tau)
    assert np.sum(np.linalg.eigvalsh(precision) < 0) == 2
    assert np.all(np.diagonal(np.linalg.inv(precision)) > 0)
    with pytest.raises(np.linalg.LinAlgError, match="proper Gaussian"):
        ep_posterior(K, tau, np.zeros(4))


def test_sites_are_refused_exactly_when_the_precision_is_indefinite():
    rng = np.random.default_rng(5)
    refused = accepted = 0
    for _ in range(300):
        n = int(rng.integers(2, 6))
        G = rng.normal(size=(n, n))
        K = G @ G.T + 0.1 * np.eye(n)
        tau = rng.normal(0.0, 2.0, n)
        smallest = np.linalg.eigvalsh(np.linalg.inv(K) + np.diag(tau))[0]
        if abs(smallest) < 1e-6 or np.all(tau >= 0):
            continue
        if smallest < 0:
            with pytest.raises(np.linalg.LinAlgError, match="proper Gaussian"):
                ep_posterior(K, tau, np.zeros(n))
            refused += 1
        else:
            Sigma = np.linalg.inv(np.linalg.inv(K) + np.diag(tau))
            np.testing.assert_allclose(ep_posterior(K, tau, np.zeros(n)).var, np.diag(Sigma))
            accepted += 1
    assert refused > 20 and accepted > 20


def test_evidence_of_sites_with_an_improper_cavity_is_minus_infinity():
    # A proper posterior, but without the second site K^-1 + diag(-3, 0) is indefinite:
    # the cavity of that site has a negative precision, and these are no EP sites.
    K = np.array([[1.0, 0.9], [0.9, 1.0]])
    tau = np.array([-3.0, 20.0])
    assert np.all(np.linalg.eigvalsh(np.linalg.inv(K) + np.diag(tau)) > 0)
    assert np.linalg.eigvalsh(np.linalg.inv(K) + np.diag([-3.0, 0.0]))[0] < 0
    assert ep_log_marginal_likelihood(K, [1.0, 1.0], tau, [0.5, 1.0]) == -np.inf


def test_negative_initial_sites_reach_the_same_fixed_point():
    kernel, X, y = _problem(n=15, seed=3)
    K = kernel(X)
    ref = expectation_propagation(K, y, tol=1e-12)
    start_tau = np.full(15, 0.3)
    start_tau[[2, 7]] = -0.2
    res = expectation_propagation(
        K, y, site_precision=start_tau, site_nu=np.zeros(15), tol=1e-12, max_iter=500
    )
    assert res.converged and np.all(res.site_precision >= 0)
    np.testing.assert_allclose(res.site_precision, ref.site_precision, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(res.site_nu, ref.site_nu, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("seed", [0, 1])
def test_parallel_steps_never_propose_negative_site_precisions(monkeypatch, seed):
    # Anderson steps that would make a site precision negative fall back to the plain
    # damped step: every posterior on the way has non-negative sites (on these problems
    # the unguarded extrapolation goes below zero).
    kernel, X, y = _problem(n=30, signal=1e3, seed=seed)
    lowest = []
    posterior = ep_module.ep_posterior

    def spy(K, tau, nu):
        lowest.append(np.min(tau))
        return posterior(K, tau, nu)

    monkeypatch.setattr(ep_module, "ep_posterior", spy)
    res = expectation_propagation(kernel(X), y, tol=1e-10)
    assert res.converged and len(lowest) > 5
    assert min(lowest) >= 0.0


def test_large_signal_variance_with_label_noise_stays_finite():
    # Flipped labels inside a strongly varying latent: sites become very precise next to
    # nearly flat ones, the regime where cavity precisions cancel.
    rng = np.random.default_rng(4)
    X = rng.uniform(0, 5, size=(80, 1))
    y = np.where(X[:, 0] > 2.5, 1.0, -1.0)
    flip = rng.choice(80, size=12, replace=False)
    y[flip] *= -1
    K = (C(1e4) * RBF(0.3))(X)
    for update in ("parallel", "sequential"):
        # 1e-8 of the marginals: rounding in the sequential sweeps' rank-one updates leaves
        # a floor near 2e-9 at this signal variance.
        res = expectation_propagation(K, y, update=update, tol=1e-8, max_iter=500)
        assert res.converged
        assert np.all(np.isfinite(res.site_precision)) and np.all(res.site_precision >= 0)
        assert np.all(res.posterior.var > 0)
        lml = ep_log_marginal_likelihood(K, y, res.site_precision, res.site_nu)
        assert np.isfinite(lml)


def test_evidence_matches_product_form():
    # R&W eq. 3.65 before simplification: log N(mu~ | 0, K + S~^-1) + sum log Z~_i, with the
    # site normalisers Z~_i of eq. 3.59.
    kernel, X, y = _problem(n=12, seed=5)
    K = kernel(X)
    res = expectation_propagation(K, y, tol=1e-12)
    tau, nu = res.site_precision, res.site_nu
    post = res.posterior
    tau_cav = 1 / post.var - tau
    mu_cav = (post.mean / post.var - nu) / tau_cav
    s2_cav, s2_site, mu_site = 1 / tau_cav, 1 / tau, nu / tau
    log_Z_hat = norm.logcdf(y * mu_cav / np.sqrt(1 + s2_cav))
    log_Z_site = (
        log_Z_hat
        + 0.5 * np.log(2 * np.pi * (s2_cav + s2_site))
        + (mu_cav - mu_site) ** 2 / (2 * (s2_cav + s2_site))
    )
    direct = multivariate_normal(np.zeros(12), K + np.diag(s2_site)).logpdf(mu_site)
    direct += log_Z_site.sum()
    lml = ep_log_marginal_likelihood(K, y, tau, nu)
    np.testing.assert_allclose(lml, direct, rtol=1e-10)


def _laplace_probit_log_evidence(K, y):
    """Laplace approximation with the probit likelihood (R&W Algorithm 3.1 and eq. 3.32)."""
    n = len(y)
    f = np.zeros(n)
    for _ in range(100):
        z = y * f
        ratio = np.exp(norm.logpdf(z) - norm.logcdf(z))
        grad = y * ratio
        W = ratio**2 + z * ratio
        sW = np.sqrt(W)
        L = np.linalg.cholesky(np.eye(n) + sW[:, None] * K * sW[None, :])
        b = W * f + grad
        a = b - sW * np.linalg.solve(L.T, np.linalg.solve(L, sW * (K @ b)))
        f_new = K @ a
        if np.max(np.abs(f_new - f)) < 1e-12:
            f = f_new
            break
        f = f_new
    return -0.5 * a @ f + norm.logcdf(y * f).sum() - np.log(np.diag(L)).sum()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_evidence_close_to_exact_orthant_probability(seed):
    # For probit, Z = P(y_i (f_i + eps_i) > 0 for all i), a Gaussian orthant probability.
    # EP approximates it closely and better than Laplace.
    kernel, X, y = _problem(n=4, signal=3.0, length_scale=1.0, seed=seed)
    K = kernel(X)
    res = expectation_propagation(K, y, tol=1e-12)
    lml = ep_log_marginal_likelihood(K, y, res.site_precision, res.site_nu)
    # u = Y (f + eps) ~ N(0, Y (K + I) Y); P(u > 0) = P(-u <= 0) = its cdf at 0 by symmetry.
    cov = (K + np.eye(4)) * np.outer(y, y)
    mvn = multivariate_normal(np.zeros(4), cov, abseps=1e-10, releps=1e-10, maxpts=10**6)
    exact = np.log(mvn.cdf(np.zeros(4)))
    laplace = _laplace_probit_log_evidence(K, y)
    assert abs(lml - exact) < abs(laplace - exact)
    assert abs(lml - exact) < 0.02


def test_sequential_and_parallel_reach_the_same_fixed_point():
    kernel, X, y = _problem(n=25, signal=5.0, seed=6)
    K = kernel(X)
    runs = [
        expectation_propagation(K, y, update="sequential", damping=0.0, tol=1e-12),
        expectation_propagation(K, y, update="sequential", damping=0.5, tol=1e-12),
        expectation_propagation(K, y, damping=0.5, acceleration=0, tol=1e-12, max_iter=1000),
        expectation_propagation(K, y, damping=0.5, tol=1e-12),
        expectation_propagation(K, y, damping=0.0, tol=1e-12),
    ]
    ref = runs[0]
    ref_lml = ep_log_marginal_likelihood(K, y, ref.site_precision, ref.site_nu)
    for res in runs:
        assert res.converged
        np.testing.assert_allclose(res.site_precision, ref.site_precision, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(res.site_nu, ref.site_nu, rtol=1e-6, atol=1e-9)
        lml = ep_log_marginal_likelihood(K, y, res.site_precision, res.site_nu)
        np.testing.assert_allclose(lml, ref_lml, rtol=1e-6)


def _wall_hit_again_and_again():
    """39 hits within 3 cm of each other and one free point 6 m away, signal variance 1e3:
    the kernel matrix is numerically singular, and the hits' sites trade precision among
    themselves while their marginals settle."""
    rng = np.random.RandomState(0)
    hits = np.column_stack([21.67 + 0.03 * rng.rand(39), np.full(39, 8.95)])
    X = np.vstack([[16.07, 6.54], hits])
    return (C(1e3) * RBF(1.67))(X), np.r_[-1.0, np.ones(39)]


def test_parallel_ep_on_near_duplicates_reaches_the_sequential_fixed_point(monkeypatch):
    K, y = _wall_hit_again_and_again()
    ref = expectation_propagation(K, y, update="sequential", damping=0.0, tol=1e-10)
    res = expectation_propagation(K, y, tol=1e-10)
    assert res.converged and res.n_iter <= 200
    np.testing.assert_allclose(res.posterior.mean, ref.posterior.mean, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(res.posterior.var, ref.posterior.var, rtol=1e-6, atol=1e-9)
    # Where parallel sweeps stall, harder damping and then sequential sweeps take over, and
    # reach the same fixed point.
    calls = []
    sequential = ep_module._sequential_ep
    with monkeypatch.context() as patch:
        patch.setattr(ep_module, "_STALL_SWEEPS", 2)
        patch.setattr(
            ep_module, "_sequential_ep", lambda *a, **k: calls.append(1) or sequential(*a, **k)
        )
        stalled = expectation_propagation(K, y, tol=1e-10)
    assert calls and stalled.converged
    np.testing.assert_allclose(stalled.posterior.mean, ref.posterior.mean, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(stalled.posterior.var, ref.posterior.var, rtol=1e-6, atol=1e-9)


def _recorded_parallel_sweeps(monkeypatch, K, y, stall_sweeps, **options):
    """EP's result, and each parallel sweep's sites, proposed sites and marginal variances."""
    sweeps = []
    proposed = ep_module._proposed_sites

    def spy(y, mean, tau, nu, posterior):
        tau_new, nu_new = proposed(y, mean, tau, nu, posterior)
        sweeps.append((np.r_[tau, nu], np.r_[tau_new, nu_new], posterior.var.copy()))
        return tau_new, nu_new

    with monkeypatch.context() as patch:
        patch.setattr(ep_module, "_proposed_sites", spy)
        patch.setattr(ep_module, "_STALL_SWEEPS", stall_sweeps)
        res = expectation_propagation(K, y, **options)
    return res, sweeps


def _sweep_residual(x, x_new, var):
    """Largest change of a site in units of its marginal: |d tau| var, |d nu| sqrt(var)."""
    n = len(var)
    change = np.abs(x_new - x)
    return max(np.max(change[:n] * var), np.max(change[n:] * np.sqrt(var)))


def _stalls(sweeps, stall_sweeps):
    """Sweeps at which the largest residual has not reached a new minimum for
    ``stall_sweeps`` sweeps, counted afresh from each stall."""
    stalls, best, best_sweep = [], np.inf, 0
    for k, sweep in enumerate(sweeps, start=1):
        residual = _sweep_residual(*sweep)
        if residual < best:
            best, best_sweep = residual, k
        elif k - best_sweep == stall_sweeps:
            stalls.append(k)
            best, best_sweep = residual, k
    return stalls


def _is_damped_step(x, x_new, x_next, damping):
    return np.allclose(
        x_next - x, (1 - damping) * (x_new - x), rtol=1e-9, atol=1e-12 * np.max(np.abs(x))
    )


def test_stalled_parallel_ep_damps_halfway_to_one_then_sweeps_sequentially(monkeypatch):
    # At damping 0.2 parallel sweeps cycle on the near-duplicate hits: the first stall
    # moves the damping halfway to 1 (0.6), the second hands the sites over to sequential
    # sweeps. Every parallel step is the plain damped one (no acceleration).
    K, y = _wall_hit_again_and_again()
    options = {"damping": 0.2, "acceleration": 0, "tol": 1e-10}
    res, sweeps = _recorded_parallel_sweeps(monkeypatch, K, y, 3, **options)
    stalls = _stalls(sweeps, 3)
    assert len(stalls) >= 2 and len(sweeps) == stalls[1]
    for k in range(1, len(sweeps)):  # the step of sweep k, from sweeps[k - 1] to sweeps[k]
        (x, x_new, _), (x_next, _, _) = sweeps[k - 1], sweeps[k]
        assert _is_damped_step(x, x_new, x_next, 0.2 if k < stalls[0] else 0.6)
    assert res.converged and res.n_iter > stalls[1]


def test_sequential_sweeps_after_a_stall_stay_within_max_iter(monkeypatch):
    # The sequential sweeps after a second stall share the budget of max_iter sweeps.
    K, y = _wall_hit_again_and_again()
    options = {"damping": 0.2, "acceleration": 0, "tol": 1e-10}
    _, sweeps = _recorded_parallel_sweeps(monkeypatch, K, y, 3, **options)
    handover = _stalls(sweeps, 3)[1]
    res, _ = _recorded_parallel_sweeps(monkeypatch, K, y, 3, max_iter=handover + 1, **options)
    assert res.n_iter == handover + 1 and not res.converged


def test_a_jump_of_the_residual_restarts_the_acceleration(monkeypatch):
    # A sweep whose residual is more than ten times the smallest before it drops the
    # Anderson history: it takes the plain damped step (no stall changes the damping here).
    K, y = _wall_hit_again_and_again()
    _, sweeps = _recorded_parallel_sweeps(monkeypatch, K, y, 10**6, tol=1e-10, max_iter=60)
    lowest, jumps = np.inf, 0
    for (x, x_new, var), (x_next, _, _) in zip(sweeps[:-1], sweeps[1:], strict=True):
        residual = _sweep_residual(x, x_new, var)
        if residual > 10 * lowest:
            jumps += 1
            assert _is_damped_step(x, x_new, x_next, 0.5)
        lowest = min(lowest, residual)
    assert jumps > 0


@pytest.mark.parametrize("signal_variance", [1e3, 1e5, 1e13])
def test_first_sweep_from_the_prior_is_not_taken_for_convergence(signal_variance):
    # At a large signal variance the sites are of order 1 / variance: measured against
    # 1 + |site|, a whole first sweep from zero sites fell within tol, and EP returned the
    # prior (p = 0.5 everywhere) after one sweep, without a warning. Measured in units of
    # the marginals it is a change of order one.
    X = np.linspace(0, 5, 40)[:, None]
    y = np.where(X[:, 0] > 2.5, 1.0, -1.0)
    K = (C(signal_variance) * RBF(0.5))(X)
    tol = 1e-2 if signal_variance < 1e13 else 1e-6
    for update in ("parallel", "sequential"):
        res = expectation_propagation(K, y, update=update, tol=tol)
        assert res.converged and res.n_iter > 1
        assert np.all(np.sign(res.posterior.mean) == y)


@pytest.mark.parametrize("damping", [0.0, 0.3])
def test_sequential_sweep_matches_algorithm_3_5_site_by_site(damping):
    # R&W Algorithm 3.5 with the posterior recomputed densely before each site, against the
    # sweep's rank-one updates of Sigma and mu.
    kernel, X, y = _problem(n=12, signal=2.5, seed=3)
    K = kernel(X) + 1e-8 * np.eye(12)
    start = expectation_propagation(K, y, max_iter=2)
    tau, nu = start.site_precision.copy(), start.site_nu.copy()
    mean = np.zeros(12)
    got_tau, got_nu, _, _ = ep_module._sequential_sweep(
        K, y, mean, tau, nu, ep_posterior(K, tau, nu), damping
    )
    for i in range(12):
        # Sigma = K - K S^1/2 B^-1 S^1/2 K with B = I + S^1/2 K S^1/2 (tau may be 0).
        sq = np.sqrt(tau)
        B = np.eye(12) + sq[:, None] * K * sq[None, :]
        Sigma = K - K @ (sq[:, None] * np.linalg.solve(B, sq[:, None] * K))
        mu = Sigma @ nu
        tau_cav = 1.0 / Sigma[i, i] - tau[i]
        nu_cav = mu[i] / Sigma[i, i] - nu[i]
        t, n_, _ = probit_site_update(y[i : i + 1], np.array([tau_cav]), np.array([nu_cav]))
        tau[i] += (1.0 - damping) * (t[0] - tau[i])
        nu[i] += (1.0 - damping) * (n_[0] - nu[i])
    np.testing.assert_allclose(got_tau, tau, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got_nu, nu, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("damping", [0.0, 0.3, 0.8])
def test_parallel_sweeps_keep_the_damping_weight_on_the_current_sites(damping):
    # new = damping * current + (1 - damping) * proposed, all sites at once, for the first
    # two sweeps from the prior's zero sites.
    kernel, X, y = _problem(n=6)
    K = kernel(X)
    tau, nu = np.zeros(6), np.zeros(6)
    for max_iter in (1, 2):
        tau_new, nu_new = _matched_sites(K, y, tau, nu)
        tau = damping * tau + (1 - damping) * tau_new
        nu = damping * nu + (1 - damping) * nu_new
        res = expectation_propagation(K, y, damping=damping, acceleration=0, max_iter=max_iter)
        np.testing.assert_allclose(res.site_precision, tau, rtol=1e-7)
        np.testing.assert_allclose(res.site_nu, nu, rtol=1e-7)


@pytest.mark.parametrize("damping", [0.3, 0.7])
def test_sequential_sweep_from_the_prior_keeps_the_damping_weight_on_each_site(damping):
    # R&W Algorithm 3.5 with damping: site i is updated against the posterior of the
    # sites before it, already damped.
    kernel, X, y = _problem(n=6)
    K = kernel(X)
    res = expectation_propagation(K, y, update="sequential", damping=damping, max_iter=1)
    tau, nu = np.zeros(6), np.zeros(6)
    for i in range(6):
        tau_new, nu_new = _matched_sites(K, y, tau, nu, sites=[i])
        tau[i] = damping * tau[i] + (1 - damping) * tau_new[i]
        nu[i] = damping * nu[i] + (1 - damping) * nu_new[i]
    np.testing.assert_allclose(res.site_precision, tau, rtol=1e-7)
    np.testing.assert_allclose(res.site_nu, nu, rtol=1e-7)


def test_anderson_acceleration_of_one_step_mixes_the_last_two_damped_steps():
    # Anderson mixing (Walker & Ni 2011) of the damped map x -> x + f(x), x = (tau, nu),
    # with one past step (acceleration=1): x3 = x2 + f2 - gamma (dx + df), gamma fitting
    # f2 by df = f2 - f1 in least squares, dx = x2 - x1, from the prior's zero sites x1.
    kernel, X, y = _problem(n=6)
    K = kernel(X)

    def damped_step(x):
        return 0.5 * (np.concatenate(_matched_sites(K, y, x[:6], x[6:])) - x)

    x1 = np.zeros(12)
    f1 = damped_step(x1)
    x2 = x1 + f1
    f2 = damped_step(x2)
    dx, df = x2 - x1, f2 - f1
    gamma = (df @ f2) / (df @ df)
    x3 = x2 + f2 - gamma * (dx + df)
    assert np.all(x3[:6] >= 0) and abs(gamma) > 0.01  # a proper, accelerated step
    res = expectation_propagation(K, y, damping=0.5, acceleration=1, max_iter=2)
    np.testing.assert_allclose(np.r_[res.site_precision, res.site_nu], x3, rtol=1e-7)


@pytest.mark.parametrize("update", ["parallel", "sequential"])
@pytest.mark.parametrize("signal_variance", [1e-4, 1e-2, 0.1])
def test_converged_sites_meet_the_documented_stopping_rule(update, signal_variance):
    # EP stops when no site would move by more than tol in units of its marginal:
    # |d tau| var and |d nu| sqrt(var). Small variances tell these units apart.
    X = np.linspace(0, 5, 30)[:, None]
    y = np.where(X[:, 0] > 2.5, 1.0, -1.0)
    K = (C(signal_variance) * RBF(0.5))(X)
    tol = 1e-4
    res = expectation_propagation(K, y, update=update, acceleration=0, tol=tol)
    assert res.converged
    tau, nu, post = res.site_precision, res.site_nu, res.posterior
    tau_new, nu_new = ep_module._proposed_sites(y, np.zeros(30), tau, nu, post)
    var = post.var
    assert np.max(np.abs(tau_new - tau) * var) <= tol
    assert np.max(np.abs(nu_new - nu) * np.sqrt(var)) <= tol


@pytest.mark.parametrize("ard", [False, True])
def test_gradient_matches_finite_differences(ard):
    kernel, X, y = _problem(n=20, signal=2.5, seed=7, ard=ard)

    def lml(theta):
        K = kernel.clone_with_theta(theta)(X)
        res = expectation_propagation(K, y, tol=1e-13, max_iter=1000)
        assert res.converged
        return ep_log_marginal_likelihood(K, y, res.site_precision, res.site_nu)

    theta = kernel.theta
    K, dK = kernel(X, eval_gradient=True)
    res = expectation_propagation(K, y, tol=1e-13, max_iter=1000)
    grad = ep_log_marginal_likelihood_gradient(dK, res.posterior)
    h = 1e-5
    fd = np.array(
        [(lml(theta + h * e) - lml(theta - h * e)) / (2 * h) for e in np.eye(len(theta))]
    )
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


@pytest.mark.parametrize("negative", [False, True])
def test_gradient_is_that_of_the_site_gaussian_for_given_sites(negative):
    # Sites held fixed, log Z_EP depends on K only through log N(nu/tau | 0, K + S^-1)
    # (R&W eq. 3.65): its derivative, by finite differences of the dense form, is the
    # gradient, also in the general (LU) form for negative precisions.
    kernel, X, _ = _problem(n=8, seed=2)
    rng = np.random.default_rng(3)
    tau, nu = rng.uniform(0.3, 2.0, 8), rng.standard_normal(8)
    if negative:
        tau[[1, 5]] = -0.05
    K, dK = kernel(X, eval_gradient=True)
    posterior = ep_posterior(K, tau, nu)
    assert (posterior.lu is not None) == negative

    def log_gauss(theta):
        A = kernel.clone_with_theta(theta)(X) + np.diag(1 / tau)
        return -0.5 * np.linalg.slogdet(A)[1] - 0.5 * (nu / tau) @ np.linalg.solve(A, nu / tau)

    h = 1e-5
    theta = kernel.theta
    fd = [(log_gauss(theta + h * e) - log_gauss(theta - h * e)) / (2 * h) for e in np.eye(2)]
    grad = ep_log_marginal_likelihood_gradient(dK, posterior)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_not_converged_is_reported():
    kernel, X, y = _problem(n=15)
    K = kernel(X)
    res = expectation_propagation(K, y, max_iter=2)
    assert not res.converged and res.n_iter == 2 and res.residual > 1e-6
    # The residual is that of the last sweep: how far the sites after the first sweep
    # were from their tilted-moment updates, in units of the marginals (dense, quadrature).
    first = expectation_propagation(K, y, max_iter=1)
    tau, nu = first.site_precision, first.site_nu
    Sigma = np.linalg.solve(np.eye(15) + K * tau, K)
    mu, var = Sigma @ nu, np.diag(Sigma)
    tau_cav, nu_cav = 1 / var - tau, mu / var - nu
    change = 0.0
    for i in range(15):
        _, m, v = _tilted_moments(y[i], nu_cav[i] / tau_cav[i], 1 / tau_cav[i])
        d_tau, d_nu = 1 / v - tau_cav[i] - tau[i], m / v - nu_cav[i] - nu[i]
        change = max(change, abs(d_tau) * var[i], abs(d_nu) * np.sqrt(var[i]))
    np.testing.assert_allclose(res.residual, change, rtol=1e-6)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"K": np.ones((2, 3)), "y": [1, 1]}, "K must be a square"),
        ({"K": np.eye(2), "y": [1, 1, 1]}, "y must have shape"),
        ({"K": np.eye(2), "y": [0, 1]}, r"y must hold labels in \{-1, \+1\}"),
        ({"K": np.array([[np.nan, 0], [0, 1]]), "y": [1, -1]}, "K contains NaN"),
        ({"K": np.zeros((0, 0)), "y": []}, "K has no rows"),
        ({"K": np.eye(2), "y": [1, -1], "damping": 1.0}, "damping"),
        ({"K": np.eye(2), "y": [1, -1], "update": "async"}, "update"),
        ({"K": np.eye(2), "y": [1, -1], "site_precision": [1.0]}, "site_precision"),
        ({"K": np.eye(2), "y": [1, -1], "site_nu": [0.0, np.nan]}, "site_nu"),
        ({"K": np.eye(2), "y": [1, -1], "acceleration": -1}, "acceleration"),
        ({"K": np.eye(2), "y": [1, -1], "mean": [0.0, np.inf]}, "mean"),
    ],
)
def test_bad_input_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        expectation_propagation(**kwargs)


def test_gradient_shape_is_checked():
    res = expectation_propagation(np.eye(3), [1, -1, 1])
    with pytest.raises(ValueError, match="K_gradient must have shape"):
        ep_log_marginal_likelihood_gradient(np.zeros((2, 2, 1)), res.posterior)


@pytest.mark.parametrize("n_columns", [7, 200])
@pytest.mark.parametrize("n", [1, 40, 64, 150])
def test_blocked_lower_solve_matches_lapack(n, n_columns):
    from scipy.linalg import solve_triangular

    from skoccmap.ep import _solve_lower

    rng = np.random.default_rng(n)
    # A Cholesky factor of I + A A^T, as EP's B = I + S^1/2 K S^1/2 has.
    A = rng.normal(size=(n, n))
    L = np.linalg.cholesky(np.eye(n) + A @ A.T)
    B = rng.normal(size=(n, n_columns))
    expected = solve_triangular(L, B, lower=True)
    # Only the lower triangle is read, as with solve_triangular.
    L[np.triu_indices(n, 1)] = rng.normal(size=n * (n - 1) // 2)
    np.testing.assert_allclose(_solve_lower(L, B.copy()), expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("tau_cav", [0.0, -1.0, np.nan])
def test_site_update_refuses_a_cavity_without_positive_precision(tau_cav):
    # It returned NaN sites (1 / 0, or the square root of a negative 1 + s2) without a word.
    with pytest.raises(ValueError, match="tau_cav must hold positive cavity precisions"):
        probit_site_update(np.array([1.0, -1.0]), np.array([1.0, tau_cav]), np.zeros(2))
