"""The experts of a mixture: fitting one on its rows (or extending it with new ones), the
constant expert of a one-class cluster, and the default expert and kernel.
"""

import threading
import warnings
from functools import partial

import numpy as np
from scipy.special import ndtri
from sklearn.gaussian_process.kernels import ConstantKernel, Product

from ._validation import warn, warning_kind
from .classifier import EPGaussianProcessClassifier, _from_lower_triangle, _lower_triangle
from .kernels import IntegralKernel

# EP's stopping tolerance in the default expert (site changes in units of their marginal;
# EPGaussianProcessClassifier's own default is 1e-6): see the ``expert`` parameter.
_EXPERT_TOL = 1e-4


class _ConstantExpert:
    """Expert of a cluster that saw one class only, when the expert is not an
    :class:`~skoccmap.EPGaussianProcessClassifier` (which is fitted on that class).

    Its latent variance is the prior variance (it learned nothing about the shape of the
    map) and its latent mean is chosen so that ``Phi(mu / sqrt(1 + var))`` equals the
    Laplace-smoothed frequency of the positive class, ``(n_pos + 1) / (n + 2)``.
    """

    def __init__(self, kernel, n_positive, n_samples):
        self.kernel_ = kernel
        self.proba_ = (n_positive + 1.0) / (n_samples + 2.0)

    def prior_variance(self, X):
        if self.kernel_ is None:
            return np.ones(X.shape[0])
        return np.asarray(self.kernel_.diag(X), dtype=np.float64)

    def latent_mean_and_variance(self, X):
        var = self.prior_variance(X)
        return ndtri(self.proba_) * np.sqrt(1.0 + var), var


def _takes_kernel_matrix(expert):
    """Whether ``expert`` can be fitted on a kernel matrix computed outside it.

    Only a classifier whose kernel is fixed (no optimiser) uses ``kernel(X, X)`` as it is,
    and only :class:`~skoccmap.EPGaussianProcessClassifier` takes the matrix.
    """
    if not hasattr(expert, "_fit_warm_start") or not hasattr(expert, "get_params"):
        return False
    params = expert.get_params()
    return params.get("kernel") is not None and params.get("optimizer", 0) is None


def _training_kernel(kernel, X, previous=None):
    """``kernel(X, X)``, reusing the entries of a previous fit's matrix where it can.

    ``previous`` is ``(lower, position)``: the lower triangle of an earlier fit's matrix
    (:func:`~skoccmap.classifier._lower_triangle`) and, per row of ``X``, its row in that
    fit (-1 for a new row). Only the new rows' blocks are evaluated; the integral kernel
    over segments is most of an expert's refit, and an update adds a few rows to an expert
    of hundreds.
    """
    if previous is None:
        return kernel(X)
    lower, position = previous
    old, new = np.flatnonzero(position >= 0), np.flatnonzero(position < 0)
    K = np.empty((X.shape[0], X.shape[0]))
    kept = np.ix_(position[old], position[old])
    K[np.ix_(old, old)] = _from_lower_triangle(lower, symmetric=True)[kept]
    if new.size:
        # The new-new block by the symmetric evaluation, so that K stays exactly symmetric.
        K[np.ix_(new, new)] = kernel(X[new])
        if old.size:
            cross = kernel(X[new], X[old])
            K[np.ix_(new, old)] = cross
            K[np.ix_(old, new)] = cross.T
    return K


def _fit_expert(expert, X, y, sites=None, previous=None, keep_kernel=False, hold=None):
    """Fit one expert. One-class data: an EP expert runs EP on them (the GP posterior of
    one class); another expert becomes a :class:`_ConstantExpert`.

    ``sites``, a pair ``(site_precision, site_nu)`` per row, warm-starts an expert that
    can take them (:class:`~skoccmap.EPGaussianProcessClassifier`); others ignore them.
    ``hold``, a mask of rows, holds their sites fixed: EP runs on the others alone.
    With ``keep_kernel``, an expert with a fixed kernel is fitted on ``kernel(X, X)``
    computed here (from ``previous``, see :func:`_training_kernel`), which is returned,
    packed, for the next refit.

    Returns the expert, the warnings its fit raised, as ``(category, message)`` pairs
    (warnings raised in worker processes would otherwise never reach the caller), and the
    packed kernel matrix or None. Only the main thread of a process records warnings
    (``catch_warnings`` is process-wide state, not safe in threads); expert fits in threads
    warn as usual.
    """
    n_positive = int(np.sum(y == 1))
    fit = expert.fit
    if n_positive in (0, y.size):
        # An expert left without rows (a part of a split cluster whose hits are all
        # transient) is the prior.
        if type(expert) is not EPGaussianProcessClassifier or y.size == 0:
            kernel = expert.get_params().get("kernel") if hasattr(expert, "get_params") else None
            return _ConstantExpert(kernel, n_positive, y.size), [], None
        # EP on one class: the GP posterior of walls seen alone (or free space alone), with
        # the kernel given. A constant at the prior variance would say nothing under the
        # robust BCM, which weighs experts by what they learned.
        expert.set_params(optimizer=None)
        fit = partial(expert._fit_one_class, classes=np.array([0, 1], dtype=y.dtype))
        sites, keep_kernel, hold = None, False, None
    K = None
    if keep_kernel and _takes_kernel_matrix(expert):
        K = _training_kernel(expert.get_params()["kernel"], X, previous)
    if (sites is not None or K is not None) and hasattr(expert, "_fit_warm_start"):
        tau, nu = (None, None) if sites is None else sites

        def fit(X, y):
            return expert._fit_warm_start(X, y, tau, nu, kernel_matrix=K, hold=hold)

    lower = None if K is None else _lower_triangle(K)
    if threading.current_thread() is not threading.main_thread():
        return fit(X, y), [], lower
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        expert = fit(X, y)
    return expert, [(w.category, str(w.message)) for w in caught], lower


def _append_rows(old, expert, X, y, n_old, sites=None, previous=None, keep_kernel=False):
    """``old``, fitted on ``X[:n_old]``, with the rows ``X[n_old:]`` appended.

    EP runs on the new rows' sites alone, the others held, on ``old``'s factor
    (:meth:`~skoccmap.EPGaussianProcessClassifier._absorbed`): about the cost of predicting
    the new rows. Where that fails, ``expert`` is fitted as by :func:`_fit_expert`, holding
    the old rows' ``sites``. Returns what :func:`_fit_expert` does.
    """
    if n_old == X.shape[0]:
        return old, [], None
    lower = None
    if previous is not None:
        # The old matrix is kept: extend it for the expert's next refit.
        K = _training_kernel(old.kernel_, X, previous)
        K_cross, K_new = K[n_old:, :n_old], K[n_old:, n_old:]
        lower = _lower_triangle(K) if keep_kernel else None
    else:
        K_cross, K_new = old.kernel_(X[n_old:], X[:n_old]), old.kernel_(X[n_old:])
    absorbed = old._absorbed(X[n_old:], y[n_old:], K_cross, K_new)
    if absorbed is not None:
        return absorbed, [], lower
    hold = np.arange(X.shape[0]) < n_old
    return _fit_expert(expert, X, y, sites, previous, keep_kernel, hold=hold)


def _appended(k, rows, old_rows, origin):
    """Whether expert ``k``'s rows are its old rows with new ones after them (not split,
    not new)."""
    return origin[k] == k and np.array_equal(rows[k][: old_rows[k].size], old_rows[k])


def _warn_once_each(expert_warnings, n_experts):
    """Re-raise the experts' warnings in the caller: each kind once, with how many experts.

    Messages that differ only in their numbers (a residual, an iteration count) are one
    kind; the first expert's message stands for them.
    """
    kinds = {}
    for caught in expert_warnings:
        seen = set()
        for category, message in caught:
            key = (category, warning_kind(message))
            if key not in seen:
                seen.add(key)
                first, count = kinds.get(key, (message, 0))
                kinds[key] = (first, count + 1)
    for (category, _), (message, count) in kinds.items():
        warn(f"{count} of {n_experts} expert(s): {message}", category)


def _learns_kernel(expert):
    """Whether fitting ``expert`` learns kernel hyperparameters (an optimiser and a kernel
    with free ones)."""
    params = expert.get_params() if hasattr(expert, "get_params") else {}
    kernel = params.get("kernel")
    return params.get("optimizer") is not None and kernel is not None and kernel.n_dims > 0


def _is_binary_ep(expert):
    return type(expert) is EPGaussianProcessClassifier and expert.n_classes_ == 2


def _integral_parts(kernel):
    """``(c, k)`` for a kernel that is an :class:`IntegralKernel` ``k`` (``c`` None) or a
    product of one with a ``ConstantKernel`` ``c``; None for any other kernel."""
    if type(kernel) is IntegralKernel:
        return None, kernel
    if type(kernel) is Product:
        for c, k in ((kernel.k1, kernel.k2), (kernel.k2, kernel.k1)):
            if type(c) is ConstantKernel and type(k) is IntegralKernel:
                return c, k
    return None


def _prior_variance(expert, X):
    if isinstance(expert, _ConstantExpert):
        return expert.prior_variance(X)
    kernel = getattr(expert, "kernel_", None)
    if kernel is None:
        return np.ones(X.shape[0])
    return np.asarray(kernel.diag(X), dtype=np.float64)


def _default_kernel():
    from sklearn.gaussian_process.kernels import ConstantKernel

    from .kernels import IntegralKernel

    # On separable occupancy data the evidence keeps growing with the signal variance (to
    # the bound on the office): fixed at 1e3, which keeps most of the walls and calibration
    # that larger values gain at less cost to ACES' ranking (see the ``expert`` parameter
    # and benchmarks/bench_tuning.py), so that only the length scale is learned.
    return ConstantKernel(1e3, "fixed") * IntegralKernel()


def _default_expert(kernel=None):
    """The expert of ``expert=None``: EP with the default kernel (or ``kernel``), stopped at
    ``_EXPERT_TOL`` (see the ``expert`` parameter)."""
    from .classifier import EPGaussianProcessClassifier

    kernel = _default_kernel() if kernel is None else kernel
    return EPGaussianProcessClassifier(kernel=kernel, tol=_EXPERT_TOL)
