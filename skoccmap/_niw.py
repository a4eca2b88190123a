"""Normal-inverse-Wishart posterior math for the Dirichlet-process Gaussian mixture.

Pure functions on per-cluster sufficient statistics ``(n, s, S)`` with ``s = sum x`` and
``S = sum x x^T``. The prior ``NIW(m0, kappa0, nu0, Psi0)`` is the one of Murphy (2007),
"Conjugate Bayesian analysis of the Gaussian distribution", section 9; it equals the
Normal-Wishart prior on the precision used by scikit-learn's ``BayesianGaussianMixture`` with
``mean_prior=m0``, ``mean_precision_prior=kappa0``, ``degrees_of_freedom_prior=nu0`` and
``covariance_prior=Psi0`` (``Psi0`` is the inverse of the Wishart scale matrix).

Every function accepts a leading cluster axis so that all clusters are handled in one call.
"""

from typing import NamedTuple

import numpy as np
from scipy.special import gammaln


class NIWPrior(NamedTuple):
    """Conjugate prior ``mu | Sigma ~ N(mean, Sigma / kappa)``, ``Sigma ~ IW(psi, nu)``."""

    mean: np.ndarray  # (D,)
    kappa: float
    nu: float
    psi: np.ndarray  # (D, D), positive definite


def posterior(n, s, S, prior):
    """Posterior NIW parameters from sufficient statistics (Murphy 2007, eqs. 251-254).

    Parameters
    ----------
    n : ndarray of shape (K,)
        Number of points per cluster.
    s : ndarray of shape (K, D)
        Sum of the points per cluster.
    S : ndarray of shape (K, D, D)
        Sum of the outer products ``x x^T`` per cluster.
    prior : NIWPrior

    Returns
    -------
    kappa, nu : ndarray of shape (K,)
    mean : ndarray of shape (K, D)
    psi : ndarray of shape (K, D, D)
    """
    n = np.asarray(n, dtype=float)
    m0 = prior.mean
    kappa = prior.kappa + n
    nu = prior.nu + n
    mean = (prior.kappa * m0 + s) / kappa[:, None]
    # Psi_n = Psi0 + sum (x - xbar)(x - xbar)^T + kappa0 n / kappa_n (xbar - m0)(xbar - m0)^T,
    # written with raw moments: Psi0 + S + kappa0 m0 m0^T - kappa_n m_n m_n^T.
    psi = (
        prior.psi
        + S
        + prior.kappa * np.outer(m0, m0)
        - kappa[:, None, None] * mean[:, :, None] * mean[:, None, :]
    )
    return kappa, nu, mean, psi


def cholesky(psi):
    """Lower Cholesky factors and log-determinants of a stack of SPD matrices."""
    chol = np.linalg.cholesky(psi)
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
    return chol, logdet


def inverse_cholesky(chol):
    """``L^{-1}`` for a stack of lower-triangular factors (one batched triangular solve)."""
    eye = np.broadcast_to(np.eye(chol.shape[-1]), chol.shape)
    return np.linalg.solve(chol, eye)


def log_marginal_likelihood(n, s, S, prior):
    """Log marginal likelihood ``log p(X_k)`` of each cluster's points (Murphy 2007, eq. 266).

    ``p(X) = pi^{-nD/2} Gamma_D(nu_n/2) / Gamma_D(nu_0/2) |Psi_0|^{nu_0/2} / |Psi_n|^{nu_n/2}
    (kappa_0 / kappa_n)^{D/2}``.
    """
    kappa, nu, _, psi = posterior(n, s, S, prior)
    _, logdet_n = cholesky(psi)
    return _log_marginal_from_posterior(np.asarray(n, float), kappa, nu, logdet_n, prior)


def _log_marginal_from_posterior(n, kappa, nu, logdet_n, prior):
    D = prior.psi.shape[0]
    _, logdet_0 = np.linalg.slogdet(prior.psi)
    return (
        -0.5 * n * D * np.log(np.pi)
        + log_multigamma(0.5 * nu, D)
        - log_multigamma(0.5 * prior.nu, D)
        + 0.5 * prior.nu * logdet_0
        - 0.5 * nu * logdet_n
        + 0.5 * D * (np.log(prior.kappa) - np.log(kappa))
    )


def log_multigamma(a, D):
    """Log multivariate gamma function, vectorised over ``a``.

    ``log Gamma_D(a) = D (D - 1) / 4 log(pi) + sum_{j=1..D} log Gamma(a + (1 - j) / 2)``.
    """
    a = np.asarray(a, dtype=float)
    j = np.arange(1, D + 1)
    return 0.25 * D * (D - 1) * np.log(np.pi) + gammaln(a[..., None] + 0.5 * (1 - j)).sum(-1)


def log_crp(counts, alpha):
    """Log probability of a partition with cluster sizes ``counts`` under CRP(``alpha``)."""
    counts = np.asarray(counts, dtype=float)
    n = counts.sum()
    return (
        len(counts) * np.log(alpha) + gammaln(counts).sum() + gammaln(alpha) - gammaln(alpha + n)
    )


class StudentT(NamedTuple):
    """Per-cluster multivariate Student-t in a form cheap to evaluate for many points.

    ``log t(x) = const - (dof + D) / 2 * log1p(scale * |chol_inv (x - loc)|^2)``, where
    ``chol_inv`` is the inverse Cholesky factor of the posterior ``Psi_n``.
    """

    loc: np.ndarray  # (K, D)
    chol_inv: np.ndarray  # (K, D, D)
    scale: np.ndarray  # (K,)  kappa_n / (kappa_n + 1)
    dof: np.ndarray  # (K,)   nu_n - D + 1
    const: np.ndarray  # (K,)


def predictive(n, s, S, prior):
    """Posterior predictive Student-t of each cluster (Murphy 2007, eq. 258).

    ``p(x | X_k) = t_{nu_n - D + 1}(x | m_n, Psi_n (kappa_n + 1) / (kappa_n (nu_n - D + 1)))``.

    Returns
    -------
    t : StudentT
    logdet : ndarray of shape (K,)
        ``log |Psi_n|``, reused for the marginal likelihood.
    """
    kappa, nu, mean, psi = posterior(n, s, S, prior)
    chol, logdet = cholesky(psi)
    return _student_t(kappa, nu, mean, chol, logdet), logdet


def prior_predictive(prior):
    """The prior's predictive Student-t ``t_0``, that of a cluster of no point: a new
    cluster's in the Chinese restaurant."""
    D = prior.mean.shape[0]
    return predictive(np.zeros(1), np.zeros((1, D)), np.zeros((1, D, D)), prior)[0]


def _student_t(kappa, nu, mean, chol, logdet):
    D = mean.shape[-1]
    dof = nu - D + 1.0
    # log|Sigma| of the t scale matrix Sigma = Psi_n (kappa + 1) / (kappa dof).
    logdet_sigma = logdet + D * np.log((kappa + 1.0) / (kappa * dof))
    const = (
        gammaln(0.5 * (dof + D))
        - gammaln(0.5 * dof)
        - 0.5 * D * np.log(dof * np.pi)
        - 0.5 * logdet_sigma
    )
    return StudentT(mean, inverse_cholesky(chol), kappa / (kappa + 1.0), dof, const)


def mahalanobis_sq(X, t):
    """Squared distances ``|chol_inv_k (x - loc_k)|^2`` of points (N, D) to each cluster: (N, K).

    One matrix product for all clusters: ``chol_inv_k x - chol_inv_k loc_k``.
    """
    K, D = t.loc.shape
    shifted = np.einsum("kij,kj->ki", t.chol_inv, t.loc)
    z = (X @ t.chol_inv.reshape(K * D, D).T).reshape(len(X), K, D) - shifted
    return np.einsum("nki,nki->nk", z, z)


def log_student_t(X, t, r=None):
    """Log predictive densities of points ``X`` (N, D) under each cluster: (N, K).

    ``r`` are the precomputed :func:`mahalanobis_sq` distances, if at hand.
    """
    if r is None:
        r = mahalanobis_sq(X, t)
    return t.const - 0.5 * (t.dof + X.shape[1]) * np.log1p(t.scale * r)


def leave_one_out_log_student_t(r, n, logdet, dof, prior):
    """Log predictive density of a cluster's own point ``x`` with ``x`` left out.

    Removing ``x`` from a cluster with posterior ``(kappa, m, Psi)`` gives
    ``Psi' = Psi - c u u^T`` with ``u = x - m`` and ``c = kappa / (kappa - 1)``, so by the matrix
    determinant lemma and Sherman-Morrison the leave-one-out Student-t needs only
    ``r = u^T Psi^{-1} u``: no refactorisation. Arrays broadcast; ``n >= 2``.

    Parameters
    ----------
    r : ndarray
        ``u^T Psi^{-1} u`` (the :func:`mahalanobis_sq` distance to the cluster with ``x``).
    n : ndarray
        Cluster sizes including ``x``.
    logdet : ndarray
        ``log |Psi|`` of the clusters with ``x``.
    dof : ndarray
        Student-t degrees of freedom ``nu - D + 1`` of the clusters with ``x``.
    prior : NIWPrior
    """
    D = prior.psi.shape[0]
    kappa = prior.kappa + n
    c = kappa / (kappa - 1.0)
    one_minus = np.maximum(1.0 - c * r, 1e-300)
    dof = dof - 1.0
    return (
        gammaln(0.5 * (dof + D))
        - gammaln(0.5 * dof)
        - 0.5 * D * np.log(np.pi * c)
        - 0.5 * logdet
        + 0.5 * (dof + D - 1.0) * np.log(one_minus)
    )
