"""An occupancy uncertainty in probability units, which a user can threshold.

The GP maps report a latent variance ``var[f]``, in the latent's units: its size depends on
the kernel's signal variance, so no threshold on it carries from one map to another. The
standard deviation of the occupancy probability ``Phi(f)`` itself, under the latent
Gaussian ``f ~ N(mu, var)``, lies in ``[0, 1/2]`` whatever the kernel: 0 where the map is
sure, 1/2 where ``Phi(f)`` is as likely 0 as 1.
"""

import numpy as np
from scipy.special import ndtr, ndtri, owens_t

__all__ = ["probability_std"]


def probability_std(proba, latent_variance):
    """Standard deviation of ``Phi(f)`` for ``f ~ N(mu, var)``, from ``E[Phi(f)]`` and ``var``.

    With ``a = mu / sqrt(1 + var)`` the mean is ``E[Phi(f)] = Phi(a)`` (the probability a map
    reports), and ``E[Phi(f)^2]`` is the bivariate normal probability ``Phi_2(a, a; rho)``
    with ``rho = var / (1 + var)``, which Owen's T function gives in closed form:
    ``Phi_2(a, a; rho) = Phi(a) - 2 T(a, sqrt((1 - rho) / (1 + rho)))`` (Owen 1956, eq. 3.1
    with ``h = k``). ``mu`` is recovered from the probability, so the map's two outputs
    suffice.

    Parameters
    ----------
    proba : array-like
        Occupancy probability ``Phi(mu / sqrt(1 + var))``, in ``[0, 1]``: of a map's
        ``predict_proba(X)``, the occupied column ``[:, 1]``.
    latent_variance : array-like
        Latent variance ``var >= 0``, broadcastable against ``proba``.

    Returns
    -------
    std : ndarray
        Standard deviation of the occupancy probability, in ``[0, 1/2]``.

    Notes
    -----
    Exact for a map whose prediction is one Gaussian latent (a single GP, and
    :class:`~skoccmap.MixtureGPOccupancyMap` with the product and committee combiners:
    ``"poe"``, ``"gpoe"``, ``"bcm"``, ``"rbcm"``). Under ``combiner="moe"`` the map reports
    the gate-weighted mean of its experts' probabilities and the mixture's latent variance
    (law of total variance, which may exceed the prior's); they are not one Gaussian's, and
    the std computed from them is that of the Gaussian with the mixture's variance through
    the map's probability: an approximation.

    References
    ----------
    D. B. Owen, "Tables for computing bivariate normal probabilities", Annals of
    Mathematical Statistics 27 (4), 1956.

    Examples
    --------
    >>> from skoccmap.uncertainty import probability_std
    >>> probability_std([0.5, 0.5, 0.5, 0.99], [0.0, 1.0, 1e6, 1e-2]).round(3)
    array([0.   , 0.289, 0.5  , 0.003])

    With ``mu = 0, var = 1``, ``Phi(f)`` is uniform on ``[0, 1]``: its standard deviation is
    ``1 / sqrt(12) = 0.289``.
    """
    proba = np.asarray(proba, dtype=np.float64)
    var = np.asarray(latent_variance, dtype=np.float64)
    if proba.ndim == 2 and proba.shape[1] == 2 and var.shape == proba.shape[:1]:
        # predict_proba's two columns against predict_var's one value per row: with two
        # rows they broadcast, row against column, to a wrong (2, 2) answer.
        raise ValueError(
            f"proba of shape {proba.shape} with latent_variance of shape {var.shape} looks "
            "like predict_proba(X) with predict_var(X): pass the occupied column, "
            "predict_proba(X)[:, 1]."
        )
    try:
        np.broadcast_shapes(proba.shape, var.shape)
    except ValueError:
        raise ValueError(
            f"proba and latent_variance must broadcast together, got shapes {proba.shape} and "
            f"{var.shape}."
        ) from None
    if np.any(np.isnan(proba)) or np.any((proba < 0) | (proba > 1)):
        raise ValueError("proba must hold probabilities in [0, 1] (no NaN).")
    if np.any(np.isnan(var)) or np.any(var < 0):
        raise ValueError("latent_variance must be >= 0 (no NaN).")
    a = ndtri(proba)
    # sqrt((1 - rho) / (1 + rho)) with rho = var / (1 + var), finite for var = inf too.
    # A variance near the largest float overflows 1 + 2 var to inf, which is its limit.
    with np.errstate(invalid="ignore", over="ignore"):
        second = ndtr(a) - 2.0 * owens_t(a, 1.0 / np.sqrt(1.0 + 2.0 * var))
        second = np.where(np.isinf(a), proba, second)  # p = 0 or 1: Phi(f) is constant
    std = np.sqrt(np.clip(second - proba**2, 0.0, 0.25))
    return std
