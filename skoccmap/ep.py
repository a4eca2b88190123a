"""Expectation Propagation for binary Gaussian-process classification with a probit likelihood.

Pure functions, following Rasmussen & Williams, *Gaussian Processes for Machine Learning*
(2006), chapter 3.6 ([RW2006]_): site updates (Algorithm 3.5), predictions (Algorithm 3.6),
the EP approximation of the log marginal likelihood (eq. 3.65) and its gradient with respect
to the kernel hyperparameters (eq. 5.27 and the EP analogue of Algorithm 5.2).

Notation. Labels ``y`` are in {-1, +1}; the likelihood is ``p(y_i | f_i) = Phi(y_i f_i)``.
The prior is ``f ~ N(m, K)``. Site ``i`` is the unnormalised Gaussian
``exp(-tau_i f_i^2 / 2 + nu_i f_i)`` in the centred latent ``g = f - m``: ``site_precision``
is ``tau`` (R&W's tau-tilde) and ``site_nu`` is ``nu = tau * mu_site`` (R&W's nu-tilde). With
the default ``mean=0`` the centred and uncentred latents coincide.

References
----------
.. [RW2006] C. E. Rasmussen and C. K. I. Williams, "Gaussian Processes for Machine Learning",
   MIT Press, 2006.
"""

import math
from typing import NamedTuple

import numpy as np
from scipy.linalg import cho_solve, cholesky, lu_factor, lu_solve, solve_triangular
from scipy.linalg.blas import dger, dtpsv, dtrmm
from scipy.linalg.lapack import dpotri, dtrtri
from scipy.special import erfcx, log_ndtr

__all__ = [
    "EPPosterior",
    "EPResult",
    "ep_append_sites",
    "ep_latent_joint_predictive",
    "ep_latent_predictive",
    "ep_log_marginal_likelihood",
    "ep_log_marginal_likelihood_gradient",
    "ep_posterior",
    "expectation_propagation",
    "probit_site_update",
]

_SQRT_2_OVER_PI = np.sqrt(2.0 / np.pi)
_SQRT_HALF = np.sqrt(0.5)

# Below this value of 1 - [B^-1]_ii the cheap marginal-variance formula (1 - [B^-1]_ii) / tau_i
# loses more than ~1e-9 relative accuracy to cancellation; those columns are recomputed exactly.
_CANCELLATION_THRESHOLD = 1e-4

# Parallel EP has stalled when its largest site residual has not reached a new minimum in this
# many sweeps; it then damps harder, and after a second stall goes on with sequential sweeps
# (see expectation_propagation).
_STALL_SWEEPS = 20
# Rows of a triangular factor solved at once by _solve_lower.
_TRIANGULAR_BLOCK = 64
# Triangles of at most this order are inverted by LAPACK's dtrtri, larger ones by halves
# (see _lower_inverse).
_INVERSE_BASE = 64


class EPPosterior(NamedTuple):
    """Gaussian approximation q(g) = N(mean, Sigma), Sigma = (K^-1 + diag(tau))^-1.

    Attributes
    ----------
    mean : ndarray of shape (n,)
        Posterior mean of the centred latent ``g = f - m`` at the training points.
    var : ndarray of shape (n,)
        Posterior marginal variances, the diagonal of Sigma.
    alpha : ndarray of shape (n,)
        ``(I + S K)^-1 nu``, so that ``mean = K @ alpha`` and a test mean is ``k_* @ alpha``.
    log_det_B : float
        ``log det(I + S^1/2 K S^1/2)``.
    sqrt_tau : ndarray of shape (n,) or None
        ``sqrt(tau)`` when every site precision is non-negative (Cholesky form), else None.
    L : ndarray of shape (n, n) or None
        Lower Cholesky factor of ``B = I + S^1/2 K S^1/2`` (Cholesky form), else None.
    lu : tuple or None
        LU factors of ``I + K S`` (general form, some ``tau < 0``), else None.
    tau : ndarray of shape (n,)
        The site precisions this posterior was computed from.
    """

    mean: np.ndarray
    var: np.ndarray
    alpha: np.ndarray
    log_det_B: float
    sqrt_tau: np.ndarray | None
    L: np.ndarray | None
    lu: tuple | None
    tau: np.ndarray


class EPResult(NamedTuple):
    """Outcome of :func:`expectation_propagation`.

    Attributes
    ----------
    site_precision : ndarray of shape (n,)
        Site precisions tau (R&W's tau-tilde).
    site_nu : ndarray of shape (n,)
        Site natural means nu = tau * mu_site (R&W's nu-tilde).
    posterior : EPPosterior
        The Gaussian approximation for these sites.
    n_iter : int
        Number of sweeps run.
    converged : bool
        Whether the largest site residual fell below ``tol`` within ``max_iter`` sweeps.
    residual : float
        Largest site residual of the last sweep, in units of the marginals (see ``tol`` of
        :func:`expectation_propagation`).
    """

    site_precision: np.ndarray
    site_nu: np.ndarray
    posterior: EPPosterior
    n_iter: int
    converged: bool
    residual: float


def probit_site_update(y, tau_cav, nu_cav, mean=0.0):
    """Site parameters that match the moments of the probit tilted distributions.

    The tilted distribution of site ``i`` is ``Phi(y_i (g_i + m_i)) N(g_i | mu_cav, s2_cav)``
    (R&W eq. 3.58). Its normaliser and derivatives give the new site in the stable form used by
    GPML's ``infEP``; for the log-concave probit likelihood the new precision is provably
    non-negative, ``tau = r / (1 + s2_cav (1 - r))`` with ``r = lambda (z + lambda)`` in [0, 1].

    Parameters
    ----------
    y : ndarray of shape (n,)
        Labels in {-1, +1}.
    tau_cav, nu_cav : ndarray of shape (n,)
        Cavity precisions (must be positive) and natural means.
    mean : float or ndarray of shape (n,), default=0.0
        Prior mean ``m`` of the latent at these points.

    Returns
    -------
    tau : ndarray of shape (n,)
        New site precisions, ``>= 0``.
    nu : ndarray of shape (n,)
        New site natural means.
    log_Z : ndarray of shape (n,)
        Log normalisers of the tilted distributions, ``log Phi(z)`` (R&W eq. 3.82).

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.ep import probit_site_update
    >>> tau, nu, log_Z = probit_site_update(np.array([1.0]), np.array([1.0]), np.array([0.0]))
    >>> bool(tau[0] > 0), bool(nu[0] > 0), float(np.exp(log_Z[0]))
    (True, True, 0.5)
    """
    tau_cav = np.asarray(tau_cav, dtype=np.float64)
    if not np.all(tau_cav > 0):  # False for NaN
        raise ValueError(
            "tau_cav must hold positive cavity precisions (no NaN); a cavity of precision "
            "<= 0 has no tilted moments to match (EP leaves such a site as it is)."
        )
    return _probit_site_update(y, tau_cav, nu_cav, mean)


def _probit_site_update(y, tau_cav, nu_cav, mean=0.0):
    """:func:`probit_site_update` without its check, for EP's sweeps (which skip the sites
    whose cavity precision is not positive)."""
    s2 = 1.0 / tau_cav
    mu = nu_cav * s2
    denom = np.sqrt(1.0 + s2)
    z = y * (mu + mean) / denom
    log_Z = log_ndtr(z)
    # Inverse Mills ratio lambda = N(z) / Phi(z) = sqrt(2 / pi) / erfcx(-z / sqrt 2), to
    # machine precision relative to itself for every z: from exp(-z^2 / 2) / Phi(z) in log
    # space its error grew as z^2 eps, which z + lambda below cancelled into r (1 - tau was
    # 1 % off at z = -212 and 0 at z = -707). z + lambda still cancels lambda's rounding:
    # 1 - tau keeps a relative error of about z^4 eps (3e-5 at z = -707).
    lam = _SQRT_2_OVER_PI / erfcx(-z * _SQRT_HALF)
    r = np.clip(lam * (z + lam), 0.0, 1.0)
    dlogZ = y * lam / denom
    scale = 1.0 + s2 * (1.0 - r)
    tau = r / scale
    nu = ((1.0 + s2) * dlogZ + mu * r) / scale
    return tau, nu, log_Z


def ep_posterior(K, tau, nu):
    """Posterior marginals of the EP approximation for given sites.

    Uses the numerically stable ``B = I + S^1/2 K S^1/2`` form of R&W Algorithm 3.5 when every
    site precision is non-negative. Negative precisions (which EP with a probit likelihood never
    proposes, but which warm starts or other likelihoods can bring) make ``S^1/2`` complex; then
    the general form ``Sigma = (I + K S)^-1 K`` is solved by LU, which works whenever the
    approximation is a proper Gaussian.

    Parameters
    ----------
    K : ndarray of shape (n, n)
        Prior covariance at the training points.
    tau, nu : ndarray of shape (n,)
        Site precisions and natural means.

    Returns
    -------
    posterior : EPPosterior

    Raises
    ------
    numpy.linalg.LinAlgError
        If the sites do not define a proper Gaussian (``K^-1 + S`` not positive definite).

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.ep import ep_posterior
    >>> K = np.array([[1.0, 0.5], [0.5, 1.0]])
    >>> post = ep_posterior(K, np.array([1.0, 1.0]), np.array([1.0, -1.0]))
    >>> Sigma = np.linalg.inv(np.linalg.inv(K) + np.eye(2))
    >>> bool(np.allclose(post.var, np.diag(Sigma)))
    True
    """
    tau = np.asarray(tau, dtype=np.float64)
    nu = np.asarray(nu, dtype=np.float64)
    if np.all(tau >= 0.0):
        return _posterior_cholesky(K, tau, nu)
    return _posterior_lu(K, tau, nu)


def _posterior_cholesky(K, tau, nu):
    n = tau.shape[0]
    diag_K = np.diagonal(K).copy()
    sqrt_tau = np.sqrt(tau)
    if not np.any(tau > 0.0):
        # All sites flat: the posterior is the prior (B = I).
        return EPPosterior(K @ nu, diag_K, nu.copy(), 0.0, sqrt_tau, np.eye(n), None, tau)
    L = _cholesky_of_b(K, sqrt_tau)
    # Sigma = S^-1/2 (I - B^-1) S^-1/2 (from K = S^-1/2 (B - I) S^-1/2), so the marginal
    # variances need only diag(B^-1), the column norms of L^-1: n^3/3 flops, not the n^3 of
    # V = L^-1 S^1/2 K (R&W Alg. 3.5 line 8). Columns where 1 - [B^-1]_ii cancels are redone.
    L_inv = _lower_inverse(L)
    one_minus = 1.0 - np.einsum("ij,ij->j", L_inv, L_inv)
    var = np.empty(n)
    good = one_minus > _CANCELLATION_THRESHOLD
    var[good] = one_minus[good] / tau[good]
    bad = np.flatnonzero(~good)
    if bad.size:
        V = L_inv @ (sqrt_tau[:, None] * K[:, bad])
        var[bad] = diag_K[bad] - np.einsum("ij,ij->j", V, V)
    # alpha = nu - S^1/2 B^-1 S^1/2 K nu = (I + S K)^-1 nu  (R&W Alg. 3.6 lines 3-4).
    alpha = nu - sqrt_tau * cho_solve((L, True), sqrt_tau * (K @ nu), check_finite=False)
    mean = K @ alpha
    log_det_B = 2.0 * np.sum(np.log(np.diagonal(L)))
    return EPPosterior(mean, var, alpha, log_det_B, sqrt_tau, L, None, tau)


def _cholesky_of_b(K, sqrt_tau):
    """Lower Cholesky factor of ``B = I + S^1/2 K S^1/2`` (R&W Algorithm 3.5 line 7)."""
    B = np.multiply(K, sqrt_tau[:, None])
    B *= sqrt_tau[None, :]
    B.flat[:: sqrt_tau.size + 1] += 1.0
    return cholesky(B, lower=True, overwrite_a=True, check_finite=False)


def _lower_inverse(L):
    """Inverse of the lower triangle of ``L``, zero above its diagonal.

    By halves, ``[[A, 0], [C, D]]^-1 = [[A^-1, 0], [-D^-1 C A^-1, D^-1]]``: the off-diagonal
    block is two triangular matrix products (BLAS ``dtrmm``), and triangles of at most
    ``_INVERSE_BASE`` rows are inverted by LAPACK's ``dtrtri``. The flops are those of
    ``dtrtri`` on the whole (n^3 / 3), but in level-3 BLAS: about three quarters of its
    time at 200 rows and half at 400 (one thread), the sizes of a mixture's experts.
    Parallel EP inverts one factor per sweep.

    Raises ``numpy.linalg.LinAlgError`` if a diagonal entry is zero.
    """
    n = L.shape[0]
    if n <= _INVERSE_BASE:
        inverse, info = dtrtri(L, lower=1)
        if info != 0:
            raise np.linalg.LinAlgError("Cholesky factor of B is singular.")
        return np.tril(inverse)
    h = n // 2
    inverse = np.zeros((n, n))
    inverse[:h, :h] = _lower_inverse(L[:h, :h])
    inverse[h:, h:] = _lower_inverse(L[h:, h:])
    C_times_A_inv = dtrmm(1.0, inverse[:h, :h], L[h:, :h], side=1, lower=1)
    inverse[h:, :h] = dtrmm(-1.0, inverse[h:, h:], C_times_A_inv, lower=1)
    return inverse


def _posterior_lu(K, tau, nu):
    n = tau.shape[0]
    M = K * tau[None, :]  # I + K S, so that Sigma = (I + K S)^-1 K and (I + S K) = M^T
    M.flat[:: n + 1] += 1.0
    _check_proper(K, tau)
    lu = lu_factor(M, check_finite=False)
    diag_U = np.diagonal(lu[0])
    var = np.diagonal(lu_solve(lu, K, check_finite=False)).copy()
    if not np.all(var > 0.0):
        raise np.linalg.LinAlgError(
            "The EP sites do not define a proper Gaussian: non-positive posterior variance."
        )
    alpha = lu_solve(lu, nu, trans=1, check_finite=False)
    mean = K @ alpha
    log_det_B = float(np.sum(np.log(np.abs(diag_U))))
    return EPPosterior(mean, var, alpha, log_det_B, None, None, lu, tau)


def _check_proper(K, tau):
    """Raise ``LinAlgError`` unless the sites with prior ``K`` define a proper Gaussian.

    A sign of ``det(I + K S)`` misses an even number of negative directions. With the sites
    split as ``S = S+ - S-`` and ``P = (K^-1 + S+)^-1`` (R&W's stable form, proper), the
    precision ``P^-1 - S-`` is positive definite iff ``I - S-^1/2 P S-^1/2`` is (congruence
    by ``P^1/2``): a Cholesky test over the m negative sites, which needs no ``K^-1``.
    """
    negative = np.flatnonzero(tau < 0.0)
    P = K[np.ix_(negative, negative)]
    if np.any(tau > 0.0):
        sqrt_tau = np.sqrt(np.maximum(tau, 0.0))
        L = _cholesky_of_b(K, sqrt_tau)
        V = solve_triangular(L, sqrt_tau[:, None] * K[:, negative], lower=True, check_finite=False)
        P = P - V.T @ V
    scale = np.sqrt(-tau[negative])
    C = np.eye(negative.size) - scale[:, None] * P * scale[None, :]
    try:
        cholesky(C, lower=True, overwrite_a=True, check_finite=False)
    except np.linalg.LinAlgError:
        raise np.linalg.LinAlgError(
            "The EP sites do not define a proper Gaussian: K^-1 + S is not positive definite "
            "(negative site precisions)."
        ) from None


def _cavity(posterior, tau, nu):
    """Cavity natural parameters from the posterior marginals (R&W Alg. 3.5 lines 5-6)."""
    inv_var = 1.0 / posterior.var
    return inv_var - tau, posterior.mean * inv_var - nu


def _r_matrix(posterior):
    """R = (K + S^-1)^-1 = S^1/2 B^-1 S^1/2, dense."""
    if posterior.lu is None:
        B_inv, info = dpotri(posterior.L, lower=1)
        if info != 0:
            raise np.linalg.LinAlgError("Cholesky factor of B is singular.")
        B_inv = np.tril(B_inv) + np.tril(B_inv, -1).T
        s = posterior.sqrt_tau
        return s[:, None] * B_inv * s[None, :]
    return lu_solve(posterior.lu, np.diag(posterior.tau), trans=1, check_finite=False)


def _check_inputs(K, y, tau, nu, mean):
    K = np.asarray(K, dtype=np.float64)
    if K.ndim != 2 or K.shape[0] != K.shape[1]:
        raise ValueError(f"K must be a square 2-D array, got shape {K.shape}.")
    n = K.shape[0]
    if n == 0:
        raise ValueError("K has no rows; EP needs at least one observation.")
    y = np.asarray(y, dtype=np.float64)
    if y.shape != (n,):
        raise ValueError(f"y must have shape ({n},) to match K, got {y.shape}.")
    if not np.all((y == 1.0) | (y == -1.0)):
        raise ValueError("y must hold labels in {-1, +1}.")
    if not np.all(np.isfinite(K)):
        raise ValueError("K contains NaN or infinite values.")
    tau = np.zeros(n) if tau is None else np.array(tau, dtype=np.float64)
    nu = np.zeros(n) if nu is None else np.array(nu, dtype=np.float64)
    for name, value in (("site_precision", tau), ("site_nu", nu)):
        if value.shape != (n,) or not np.all(np.isfinite(value)):
            raise ValueError(f"{name} must be a finite array of shape ({n},).")
    mean = np.broadcast_to(np.asarray(mean, dtype=np.float64), (n,))
    if not np.all(np.isfinite(mean)):
        raise ValueError("mean contains NaN or infinite values.")
    return K, y, tau, nu, mean


def expectation_propagation(
    K,
    y,
    *,
    mean=0.0,
    site_precision=None,
    site_nu=None,
    update="parallel",
    damping=0.5,
    max_iter=200,
    tol=1e-6,
    acceleration=5,
):
    """Run EP for a probit GP classifier to a fixed point (R&W Algorithm 3.5).

    Parameters
    ----------
    K : ndarray of shape (n, n)
        Prior covariance at the training points.
    y : ndarray of shape (n,)
        Labels in {-1, +1}.
    mean : float or ndarray of shape (n,), default=0.0
        Prior mean of the latent at the training points.
    site_precision, site_nu : ndarray of shape (n,), default=None
        Initial sites (a warm start); zeros (the prior) when None.
    update : {"parallel", "sequential"}, default="parallel"
        ``"parallel"`` updates every site from the current marginals, then refactorises
        (O(n^3) per sweep, vectorised). ``"sequential"`` updates one site at a time with rank-one
        updates of Sigma (O(n^2) per site) and refactorises after each sweep, as in R&W.
        Parallel EP is not guaranteed to converge: at large signal variances on nearly
        duplicate rows (a wall hit again and again) it can settle into a cycle at the given
        damping. When its largest residual has not reached a new minimum for 20 sweeps
        (``_STALL_SWEEPS``) the damping moves halfway to 1; when that stalls too, EP goes on
        from the current sites with undamped sequential sweeps (R&W Algorithm 3.5 as
        written) for the rest of ``max_iter``. Both updates have the same fixed point.
    damping : float in [0, 1), default=0.5
        Weight kept on the current sites: ``new = damping * current + (1 - damping) *
        proposed``, in natural parameters. 0 is undamped EP; more damping steadies parallel EP
        at large signal variances. Damping changes the path, not the fixed point.
    max_iter : int, default=200
        Maximum number of sweeps.
    tol : float, default=1e-6
        Stop when no site would change by more than ``tol`` in units of its marginal
        (variance ``var``): its precision relative to the marginal precision (``|d tau|
        var``), and its natural mean against the marginal's standard deviation (``|d nu|
        sqrt(var)``). Unlike a change relative to the site itself, this does not stop a
        first sweep from zero sites at a large signal variance, where sites are tiny.
    acceleration : int, default=5
        Parallel updates only: number of past sweeps that Anderson acceleration combines
        (0 turns it off). Parallel EP is a fixed-point iteration that converges linearly;
        Anderson mixing of the last few (damped) steps needs about half the sweeps. Steps that
        would make a site precision negative or the posterior improper fall back to the plain
        damped step, so the fixed point is that of EP.

    Returns
    -------
    result : EPResult
        Sites, posterior, number of sweeps and whether EP converged. Non-convergence is
        reported in ``result.converged``, not warned about, so that callers decide.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.ep import expectation_propagation
    >>> X = np.linspace(0, 1, 5)[:, None]
    >>> K = np.exp(-0.5 * (X - X.T) ** 2 / 0.3**2)
    >>> res = expectation_propagation(K, np.array([-1, -1, 1, 1, 1.0]))
    >>> res.converged, bool(res.posterior.mean[-1] > 0)
    (True, True)
    """
    K, y, tau, nu, mean = _check_inputs(K, y, site_precision, site_nu, mean)
    if update not in ("parallel", "sequential"):
        raise ValueError(f"update must be 'parallel' or 'sequential', got {update!r}.")
    if not 0.0 <= damping < 1.0:
        raise ValueError(f"damping must be in [0, 1), got {damping}.")
    if acceleration < 0:
        raise ValueError(f"acceleration must be >= 0, got {acceleration}.")
    posterior = ep_posterior(K, tau, nu)
    if update == "sequential":
        return _sequential_ep(K, y, mean, tau, nu, posterior, damping, max_iter, tol)
    result = _parallel_ep(K, y, mean, tau, nu, posterior, damping, max_iter, tol, acceleration)
    if result.converged or result.n_iter == max_iter:
        return result
    # Stalled in a cycle: sequential sweeps from here, within the same budget of sweeps.
    tau, nu, posterior, done = result[:4]
    return _sequential_ep(K, y, mean, tau, nu, posterior, 0.0, max_iter - done, tol, done=done)


def _sequential_ep(K, y, mean, tau, nu, posterior, damping, max_iter, tol, done=0):
    """Sequential sweeps until the residual is within ``tol``; ``done`` sweeps were run
    before (they count in ``n_iter``)."""
    residual = np.inf
    for n_iter in range(1, max_iter + 1):
        tau, nu, posterior, residual = _sequential_sweep(K, y, mean, tau, nu, posterior, damping)
        if residual <= tol:
            return EPResult(tau, nu, posterior, done + n_iter, True, residual)
    return EPResult(tau, nu, posterior, done + max_iter, False, residual)


def _residual(tau, nu, tau_new, nu_new, var):
    """Largest change of a site in units of its marginal (variance ``var``): ``|d tau|
    var``, relative to the marginal precision, and ``|d nu| sqrt(var)``, the natural mean's
    change against the marginal's standard deviation (the mean's change when tau stays).

    Scale-free, unlike a change relative to ``1 + |site|``: at a large signal variance the
    sites are of order ``1 / var``, and a whole first sweep from zero sites (the prior)
    would fall within any tolerance of the sites themselves.
    """
    # A site whose marginal variance rounds to <= 0 is skipped (unchanged): no NaN.
    var = np.maximum(var, 0.0)
    return max(
        np.max(np.abs(tau_new - tau) * var, initial=0.0),
        np.max(np.abs(nu_new - nu) * np.sqrt(var), initial=0.0),
    )


def _proposed_sites(y, mean, tau, nu, posterior):
    """Sites that match the tilted moments, all at once (R&W Alg. 3.5 lines 5-9)."""
    tau_cav, nu_cav = _cavity(posterior, tau, nu)
    # A non-positive cavity precision (rounding when a site dominates its marginal) leaves
    # the tilted distribution undefined: that site stays as it is.
    ok = tau_cav > 0.0
    tau_prop, nu_prop = tau.copy(), nu.copy()
    tau_prop[ok], nu_prop[ok], _ = _probit_site_update(y[ok], tau_cav[ok], nu_cav[ok], mean[ok])
    return tau_prop, nu_prop


def _parallel_ep(K, y, mean, tau, nu, posterior, damping, max_iter, tol, memory):
    """Damped parallel EP, with Anderson acceleration of the damped fixed-point map.

    A first stall (no new smallest residual in ``_STALL_SWEEPS`` sweeps) moves the damping
    halfway to 1; a second stall returns the current sites, unconverged, before ``max_iter``
    sweeps."""
    n = tau.shape[0]
    xs, fs = [], []  # past iterates and their damped steps, for Anderson mixing
    lowest = np.inf
    best, best_iter, stalls = np.inf, 0, 0
    residual = np.inf
    for n_iter in range(1, max_iter + 1):
        tau_prop, nu_prop = _proposed_sites(y, mean, tau, nu, posterior)
        residual = _residual(tau, nu, tau_prop, nu_prop, posterior.var)
        if residual <= tol:
            return EPResult(tau, nu, posterior, n_iter, True, residual)
        if residual > 10.0 * lowest:
            xs, fs = [], []  # acceleration is leading away: restart it from here
        lowest = min(lowest, residual)
        if residual < best:
            best, best_iter = residual, n_iter
        elif n_iter - best_iter >= _STALL_SWEEPS:
            if stalls:
                return EPResult(tau, nu, posterior, n_iter, False, residual)
            # First stall: damp harder (halfway to 1) and restart the acceleration.
            stalls, damping = 1, 0.5 * (1.0 + damping)
            xs, fs = [], []
            best, best_iter = residual, n_iter
        x = np.concatenate([tau, nu])
        step = (1.0 - damping) * np.concatenate([tau_prop - tau, nu_prop - nu])
        x_new = x + step
        if memory:
            xs.append(x)
            fs.append(step)
            del xs[: -memory - 1], fs[: -memory - 1]
            if len(xs) > 1:
                d_x = np.diff(np.asarray(xs), axis=0).T
                d_f = np.diff(np.asarray(fs), axis=0).T
                gamma = np.linalg.lstsq(d_f, step, rcond=None)[0]
                x_new = x_new - (d_x + d_f) @ gamma
        posterior_new = None
        if np.all(x_new[:n] >= 0.0):
            try:
                posterior_new = ep_posterior(K, x_new[:n], x_new[n:])
            except np.linalg.LinAlgError:
                pass
        if posterior_new is None or not np.all(posterior_new.var > 0.0):
            # The accelerated step left the valid region: take the plain damped step.
            xs, fs = [], []
            x_new = x + step
            posterior_new = ep_posterior(K, x_new[:n], x_new[n:])
        tau, nu, posterior = x_new[:n].copy(), x_new[n:].copy(), posterior_new
    return EPResult(tau, nu, posterior, max_iter, False, residual)


def _sequential_sweep(K, y, mean, tau, nu, posterior, damping):
    n = tau.shape[0]
    tau, nu = tau.copy(), nu.copy()
    # Full Sigma, Fortran-ordered so that BLAS dger updates it in place and columns are views.
    Sigma = np.asfortranarray(K - K @ _r_matrix(posterior) @ K)
    mu = posterior.mean.copy()
    residual = 0.0
    for i in range(n):
        s2 = Sigma[i, i]
        tau_cav = 1.0 / s2 - tau[i]
        if not tau_cav > 0.0:
            continue
        nu_cav = mu[i] / s2 - nu[i]
        t_new, n_new, _ = _probit_site_update(y[i : i + 1], tau_cav, nu_cav, mean[i])
        t_new, n_new = t_new[0], n_new[0]
        # _residual for one site, in scalars (numpy's call overhead, per site, would cost
        # a fifth of a sweep).
        residual = max(residual, abs(t_new - tau[i]) * s2, abs(n_new - nu[i]) * math.sqrt(s2))
        d_tau = (1.0 - damping) * (t_new - tau[i])
        d_nu = (1.0 - damping) * (n_new - nu[i])
        tau[i] += d_tau
        nu[i] += d_nu
        # Rank-one update of Sigma and mu (R&W Alg. 3.5 lines 10-11, eq. 3.70).
        s_i = Sigma[:, i].copy()
        denom = 1.0 + d_tau * s2
        mu += s_i * ((d_nu - d_tau * mu[i]) / denom)
        Sigma = dger(-d_tau / denom, s_i, s_i, a=Sigma, overwrite_a=1)
    # Refactorise after the sweep so that rounding in the rank-one updates does not build up.
    return tau, nu, ep_posterior(K, tau, nu), residual


def ep_log_marginal_likelihood(K, y, site_precision, site_nu, *, mean=0.0, posterior=None):
    """EP approximation of the log marginal likelihood, log Z_EP (R&W eq. 3.65, 3.73-3.74).

    Written, as in GPML's ``infEP``, with the cavity parameters of the current sites so that
    each term stays finite for vanishing site precisions.

    Parameters
    ----------
    K : ndarray of shape (n, n)
        Prior covariance at the training points.
    y : ndarray of shape (n,)
        Labels in {-1, +1}.
    site_precision, site_nu : ndarray of shape (n,)
        Sites, normally those of a converged :func:`expectation_propagation` run.
    mean : float or ndarray of shape (n,), default=0.0
        Prior mean of the latent at the training points.
    posterior : EPPosterior, default=None
        The posterior for these sites if already computed.

    Returns
    -------
    log_Z : float
        ``-inf`` if some cavity precision is not positive (the sites are not EP sites).

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.ep import expectation_propagation, ep_log_marginal_likelihood
    >>> K = np.array([[2.0]])
    >>> res = expectation_propagation(K, np.array([1.0]), mean=0.5, tol=1e-12)
    >>> lml = ep_log_marginal_likelihood(K, np.array([1.0]), res.site_precision, res.site_nu,
    ...                                  mean=0.5)
    >>> from scipy.stats import norm
    >>> bool(np.isclose(lml, norm.logcdf(0.5 / np.sqrt(3.0))))
    True
    """
    K, y, tau, nu, mean = _check_inputs(K, y, site_precision, site_nu, mean)
    if posterior is None:
        posterior = ep_posterior(K, tau, nu)
    tau_cav, nu_cav = _cavity(posterior, tau, nu)
    if not np.all(tau_cav > 0.0):
        return -np.inf
    mu_cav = nu_cav / tau_cav
    log_Z = log_ndtr(y * (mu_cav + mean) / np.sqrt(1.0 + 1.0 / tau_cav))
    tau_sum = tau + tau_cav
    return float(
        -0.5 * posterior.log_det_B
        + np.sum(log_Z)
        + 0.5 * nu @ posterior.mean
        + 0.5 * nu_cav @ ((tau / tau_cav * nu_cav - 2.0 * nu) / tau_sum)
        - 0.5 * np.sum(nu * nu / tau_sum)
        + 0.5 * np.sum(np.log1p(tau / tau_cav))
    )


def ep_log_marginal_likelihood_gradient(K_gradient, posterior):
    """Gradient of log Z_EP with respect to the kernel hyperparameters (R&W eq. 5.27).

    At an EP fixed point the derivative of log Z_EP through the sites vanishes, so only the
    explicit dependence on K remains: ``1/2 tr((b b^T - R) dK/dtheta)`` with
    ``b = alpha = (I + S K)^-1 nu`` and ``R = (K + S^-1)^-1 = S^1/2 B^-1 S^1/2``.

    Parameters
    ----------
    K_gradient : ndarray of shape (n, n, n_params)
        Derivatives of K, as returned by a scikit-learn kernel with ``eval_gradient=True``
        (with respect to the log-transformed hyperparameters).
    posterior : EPPosterior
        Posterior at converged sites.

    Returns
    -------
    gradient : ndarray of shape (n_params,)

    Examples
    --------
    >>> import numpy as np
    >>> from sklearn.gaussian_process.kernels import RBF
    >>> from skoccmap.ep import expectation_propagation, ep_log_marginal_likelihood_gradient
    >>> X = np.linspace(0, 1, 6)[:, None]
    >>> K, dK = RBF(0.3)(X, eval_gradient=True)
    >>> res = expectation_propagation(K, np.array([-1, -1, -1, 1, 1, 1.0]))
    >>> ep_log_marginal_likelihood_gradient(dK, res.posterior).shape
    (1,)
    """
    n = posterior.alpha.shape[0]
    K_gradient = np.asarray(K_gradient, dtype=np.float64)
    if K_gradient.ndim != 3 or K_gradient.shape[:2] != (n, n):
        raise ValueError(
            f"K_gradient must have shape ({n}, {n}, n_params), got {K_gradient.shape}."
        )
    M = np.outer(posterior.alpha, posterior.alpha) - _r_matrix(posterior)
    return 0.5 * (M.ravel() @ K_gradient.reshape(n * n, -1))


def _whitened_cross(posterior, K_cross):
    """``V = L^-1 S^1/2 K_cross^T`` (Cholesky form): ``K_cross`` through ``B``'s factor, so
    that the posterior's covariance at new points is ``K_new - V^T V``."""
    return _solve_lower(posterior.L, posterior.sqrt_tau[:, None] * K_cross.T)


def _solve_lower(L, B):
    """``L^-1 B`` for a lower-triangular ``L`` (``B`` may be overwritten), by blocks of rows.

    Forward substitution a block of ``_TRIANGULAR_BLOCK`` rows at a time: the update of a
    block by the rows solved before it is a matrix product, which releases the GIL. SciPy's
    triangular solves and inverses hold it, so a block's own triangle is inverted (a
    ``_TRIANGULAR_BLOCK``-sized ``dtrtri``, whatever the number of columns of ``B``) and
    applied by a matrix product. Experts that predict in threads (a mixture's map) then
    run in parallel for nearly all of the solve. ``B`` with at most ``_TRIANGULAR_BLOCK``
    columns (a few queries) is solved by one ``solve_triangular``: the blocks' calls would
    cost more than they free. Only the lower triangle of ``L`` is read.
    """
    n = L.shape[0]
    if B.shape[1] <= _TRIANGULAR_BLOCK:
        # A few columns: one call, short enough to hold the GIL.
        return solve_triangular(L, B, lower=True, overwrite_b=True, check_finite=False)
    for lo in range(0, n, _TRIANGULAR_BLOCK):
        hi = min(lo + _TRIANGULAR_BLOCK, n)
        if lo:
            B[lo:hi] -= L[lo:hi, :lo] @ B[:lo]
        diagonal = L[lo:hi, lo:hi]
        # The factor of EP's B = I + S^1/2 K S^1/2 has a diagonal of at least 1: its
        # blocks are invertible and no worse conditioned than L.
        inverse, info = dtrtri(np.tril(diagonal), lower=1)
        if info == 0:
            B[lo:hi] = inverse @ B[lo:hi]
        else:
            B[lo:hi] = solve_triangular(diagonal, B[lo:hi], lower=True, check_finite=False)
    return B


def ep_latent_predictive(K_star, k_star_diag, posterior):
    """Latent predictive mean and variance at test points (R&W Algorithm 3.6 lines 4-6).

    Parameters
    ----------
    K_star : ndarray of shape (n_test, n)
        Cross-covariances ``k(x_*, X)``.
    k_star_diag : ndarray of shape (n_test,)
        Prior variances ``k(x_*, x_*)``.
    posterior : EPPosterior
        Posterior at the training points.

    Returns
    -------
    mean : ndarray of shape (n_test,)
        Latent mean of the centred latent (add the prior mean at ``x_*`` if any).
    var : ndarray of shape (n_test,)
        Latent variance, not clipped (rounding can make it slightly negative).

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.ep import expectation_propagation, ep_latent_predictive
    >>> K = np.array([[1.0, 0.5], [0.5, 1.0]])
    >>> res = expectation_propagation(K, np.array([1.0, 1.0]))
    >>> mean, var = ep_latent_predictive(K, np.ones(2), res.posterior)
    >>> bool(np.allclose(mean, res.posterior.mean)), bool(np.allclose(var, res.posterior.var))
    (True, True)
    """
    mean = K_star @ posterior.alpha
    if posterior.lu is None:
        V = _whitened_cross(posterior, K_star)
        var = k_star_diag - np.einsum("ij,ij->j", V, V)
    else:
        RK = lu_solve(posterior.lu, posterior.tau[:, None] * K_star.T, trans=1, check_finite=False)
        var = k_star_diag - np.einsum("ij,ji->i", K_star, RK)
    return mean, var


def ep_latent_predictive_packed(K_star, k_star_diag, posterior, lower):
    """:func:`ep_latent_predictive` with the Cholesky factor in packed form.

    ``lower`` is the factor's lower triangle row by row, which is LAPACK's column-packed
    upper triangle of its transpose: each test point's ``L^-1 S^1/2 k_*`` is one BLAS
    ``dtpsv`` on it. For a few test points this costs a fraction of unpacking the factor
    (an expert of a mixture asked about one or two places); the results agree with
    :func:`ep_latent_predictive` to rounding.

    Parameters
    ----------
    K_star : ndarray of shape (n_test, n)
    k_star_diag : ndarray of shape (n_test,)
    posterior : EPPosterior
        In Cholesky form (``sqrt_tau`` not None), its factor ``L`` may be None.
    lower : ndarray of shape (n * (n + 1) // 2,)
        The factor's lower triangle, row by row.

    Returns
    -------
    mean, var : ndarray of shape (n_test,)

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.ep import (
    ...     expectation_propagation, ep_latent_predictive, ep_latent_predictive_packed)
    >>> K = np.array([[1.0, 0.5], [0.5, 1.0]])
    >>> post = expectation_propagation(K, np.array([1.0, -1.0])).posterior
    >>> lower = post.L[np.tri(2, dtype=bool)]
    >>> packed = ep_latent_predictive_packed(K, np.ones(2), post, lower)
    >>> bool(np.allclose(packed, ep_latent_predictive(K, np.ones(2), post)))
    True
    """
    n = K_star.shape[1]
    mean = K_star @ posterior.alpha
    var = np.array(k_star_diag, dtype=np.float64, copy=True)
    for j, k_star in enumerate(K_star):
        v = dtpsv(n, lower, posterior.sqrt_tau * k_star, lower=0, trans=1)
        var[j] -= v @ v
    return mean, var


def _check_new_points(K_cross, K_new, posterior):
    """Clear errors for cross- and new-point covariances that do not fit ``posterior``."""
    n = posterior.alpha.shape[0]
    K_cross, K_new = np.asarray(K_cross, dtype=np.float64), np.asarray(K_new, dtype=np.float64)
    if K_cross.ndim != 2 or K_cross.shape[1] != n:
        raise ValueError(
            f"K_cross must have shape (n_new, {n}) for a posterior at {n} points, "
            f"got {K_cross.shape}."
        )
    m = K_cross.shape[0]
    if K_new.shape != (m, m):
        raise ValueError(f"K_new must have shape ({m}, {m}) to match K_cross, got {K_new.shape}.")
    if not (np.all(np.isfinite(K_cross)) and np.all(np.isfinite(K_new))):
        raise ValueError("K_cross or K_new contains NaN or infinite values.")
    return K_cross, K_new


def ep_latent_joint_predictive(K_cross, K_new, posterior):
    """Joint latent predictive distribution ``N(mean, cov)`` at new points.

    R&W eqs. 3.60-3.61 with the full covariance instead of its diagonal. With the sites
    of the training points held fixed, this is the prior that new points' sites see: EP
    on ``(cov, y_new, mean=mean)`` fits sites for new rows without revisiting the old ones
    (:meth:`skoccmap.classifier.EPGaussianProcessClassifier._absorbed`). Its sites are in
    the latent centred on ``mean``; add ``tau * mean`` to their ``nu`` to express them in
    the latent itself.

    Parameters
    ----------
    K_cross : ndarray of shape (n_new, n)
        Cross-covariances ``k(X_new, X)``.
    K_new : ndarray of shape (n_new, n_new)
        Prior covariance ``k(X_new, X_new)``.
    posterior : EPPosterior
        Posterior at the training points.

    Returns
    -------
    mean : ndarray of shape (n_new,)
        Latent mean of the centred latent.
    cov : ndarray of shape (n_new, n_new)
        Latent covariance, symmetric.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.ep import (
    ...     expectation_propagation, ep_latent_joint_predictive, ep_latent_predictive)
    >>> K = np.array([[1.0, 0.5, 0.2], [0.5, 1.0, 0.5], [0.2, 0.5, 1.0]])
    >>> res = expectation_propagation(K[:2, :2], np.array([1.0, -1.0]))
    >>> mean, cov = ep_latent_joint_predictive(K[2:, :2], K[2:, 2:], res.posterior)
    >>> m, v = ep_latent_predictive(K[2:, :2], np.ones(1), res.posterior)
    >>> bool(np.allclose(mean, m)), bool(np.allclose(np.diag(cov), v))
    (True, True)
    """
    K_cross, K_new = _check_new_points(K_cross, K_new, posterior)
    mean = K_cross @ posterior.alpha
    if posterior.lu is None:
        V = _whitened_cross(posterior, K_cross)
        cov = K_new - V.T @ V
    else:
        RK = lu_solve(
            posterior.lu, posterior.tau[:, None] * K_cross.T, trans=1, check_finite=False
        )
        cov = K_new - K_cross @ RK
        cov = 0.5 * (cov + cov.T)
    return mean, cov


def ep_append_sites(posterior, K_cross, K_new, y, **options):
    """EP on new points' sites with the current sites held, and the posterior of all.

    The new points' prior is the current posterior's joint predictive ``N(m, C)`` there
    (:func:`ep_latent_joint_predictive`); EP on ``(C, y, mean=m)`` costs ``n_new^3`` per
    sweep. The posterior of all sites is then assembled without ``K`` at the current
    points or a new factorisation of it: ``B = I + S^1/2 K S^1/2`` split into current and
    new points has the Cholesky factor ``[[L, 0], [S_new^1/2 V^T, L_C]]``, where
    ``V = L^-1 S^1/2 K_cross^T`` (from the joint predictive) and ``L_C`` is the factor of
    the new points' problem; ``alpha`` follows from conditioning the current posterior on
    the new sites. In all ``O(n^2 n_new)``, against ``O(n^3)`` per sweep for EP on all
    points. Held fixed, the current sites are not quite EP's fixed point on all points.

    Parameters
    ----------
    posterior : EPPosterior
        Posterior at the current points, in Cholesky form (``L`` not None).
    K_cross : ndarray of shape (n_new, n)
        Cross-covariances ``k(X_new, X)``.
    K_new : ndarray of shape (n_new, n_new)
        Prior covariance at the new points.
    y : ndarray of shape (n_new,)
        Labels of the new points, in {-1, +1}.
    **options
        Passed to :func:`expectation_propagation` (``damping``, ``tol``, ...).

    Returns
    -------
    result : EPResult or None
        The new points' sites (in the latent itself, not the centred one), and the
        posterior at all points, current first. Its training marginals ``mean`` and
        ``var`` are None: they would need ``K`` at the current points. None where the
        posterior is not in Cholesky form, or EP on the new sites fails or does not
        converge.
    log_evidence : float
        ``log Z_EP`` of the new sites given the current ones: added to the current log
        evidence, that of all sites.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.ep import ep_append_sites, ep_latent_predictive, expectation_propagation
    >>> X = np.linspace(0, 3, 7)[:, None]
    >>> K = np.exp(-0.5 * (X - X.T) ** 2)
    >>> y = np.array([-1, -1, -1, 1, 1, 1, 1.0])
    >>> whole = expectation_propagation(K, y, tol=1e-12)
    >>> part = expectation_propagation(K[:5, :5], y[:5], tol=1e-12)
    >>> res, _ = ep_append_sites(part.posterior, K[5:, :5], K[5:, 5:], y[5:], tol=1e-12)
    >>> mean, var = ep_latent_predictive(K[:, :], np.ones(7), res.posterior)
    >>> bool(np.all(np.abs(mean - whole.posterior.mean) < 0.1))
    True
    """
    K_cross, K_new = _check_new_points(K_cross, K_new, posterior)
    if posterior.L is None:
        return None, -np.inf
    n = posterior.alpha.shape[0]
    s = posterior.sqrt_tau
    V = _whitened_cross(posterior, K_cross)
    mean, cov = K_cross @ posterior.alpha, K_new - V.T @ V
    try:
        new = expectation_propagation(cov, y, mean=mean, **options)
    except np.linalg.LinAlgError:
        return None, -np.inf
    if not new.converged or new.posterior.L is None:
        return None, -np.inf
    s_new = new.posterior.sqrt_tau
    m = n + s_new.shape[0]
    L = np.zeros((m, m))
    L[:n, :n] = posterior.L
    L[n:, :n] = s_new[:, None] * V.T
    L[n:, n:] = new.posterior.L
    # mean(x) = mean_current(x) + cov_current(x, X_new) alpha_new, and cov_current(x, X_new)
    # = k(x, X_new) - k(x, X) S^1/2 L^-T V.
    back = solve_triangular(posterior.L, V @ new.posterior.alpha, lower=True, trans=1)
    alpha = np.concatenate([posterior.alpha - s * back, new.posterior.alpha])
    tau = np.concatenate([posterior.tau, new.site_precision])
    site_nu = new.site_nu + new.site_precision * mean
    log_det_B = posterior.log_det_B + new.posterior.log_det_B
    joint = EPPosterior(None, None, alpha, log_det_B, np.sqrt(tau), L, None, tau)
    log_evidence = ep_log_marginal_likelihood(
        cov, y, new.site_precision, new.site_nu, mean=mean, posterior=new.posterior
    )
    result = EPResult(new.site_precision, site_nu, joint, new.n_iter, True, new.residual)
    return result, log_evidence
