"""Kernel hyperparameters shared by all experts, learned from the experts' own data.

Product-of-experts training of distributed GPs (Deisenroth & Ng, ICML 2015, eq. 8): the
experts are independent given the hyperparameters, so the log evidence of the whole map is
approximated by the sum of the experts' log evidences, and its gradient by the sum of their
gradients. Each term is computed on one spatially compact piece of the map, the kind of
data the kernel will be used on; a sparse sample spread over the whole map is not, and was
seen to learn a 70 m length scale on the Intel log. The pieces are the experts' own data, or
windows of a fixed radius holding at most an expert's number of rows (:func:`window_pieces`):
the same area and the same number of observations however dense the scans, so that the
learned length scale does not follow the density of the scans.
"""

import numpy as np
from joblib import effective_n_jobs
from scipy.spatial import cKDTree
from sklearn.base import clone
from sklearn.exceptions import ConvergenceWarning
from sklearn.utils.parallel import Parallel, delayed

from ._validation import warn
from .classifier import _check_learnable, _minimize_in_bounds

__all__ = ["learn_shared_kernel", "warn_at_bounds", "warn_beyond_extent", "window_pieces"]

# A learned log-hyperparameter within this distance of a bound counts as at the bound.
_AT_BOUND_ATOL = 1e-3


def _fit_fixed(expert, X, y):
    """The expert fitted with its kernel fixed: the state its evidence is evaluated from."""
    return clone(expert).set_params(optimizer=None).fit(X, y)


def _evidence_terms(fitted, theta):
    """Log evidence and its gradient of each fitted expert at ``theta``."""
    return [est.log_marginal_likelihood(theta, eval_gradient=True) for est in fitted]


def _negative_sum(theta, fitted, n_jobs):
    """Minus the summed log evidence of the fitted experts at ``theta``, and its gradient.

    The experts are split into one group per worker process. Threads ran no faster than
    one: EP's site updates are many small numpy and BLAS calls that hold the GIL. The
    terms are summed in the experts' order, so the result does not depend on ``n_jobs``.
    """
    groups = np.array_split(np.arange(len(fitted)), min(effective_n_jobs(n_jobs), len(fitted)))
    try:
        parts = Parallel(n_jobs=n_jobs)(
            delayed(_evidence_terms)([fitted[k] for k in group], theta) for group in groups
        )
    except np.linalg.LinAlgError:
        return np.inf, np.zeros_like(theta)
    terms = [term for part in parts for term in part]
    value = sum(t[0] for t in terms)
    grad = np.sum([t[1] for t in terms], axis=0)
    if not (np.isfinite(value) and np.all(np.isfinite(grad))):
        return np.inf, np.zeros_like(theta)
    return -value, -grad


def window_pieces(points, y, *, radius, max_rows, n_pieces, random_state):
    """Row indices of up to ``n_pieces`` spatial windows, each holding both classes.

    A window is centred on an occupied row drawn at random and holds the rows whose
    ``points`` lie within ``radius`` of the centre, a random ``max_rows`` of them when there
    are more. Centres are drawn until ``n_pieces`` windows hold both classes, or
    ``10 * n_pieces`` centres were tried. A window holding the same rows as one drawn
    before is skipped: its evidence would only count twice (a radius larger than the map
    gave 128 copies of one window, and 128 times the learning's cost).

    Parameters
    ----------
    points : ndarray of shape (n_rows, n_dims)
        A location per row (a segment's midpoint).
    y : ndarray of shape (n_rows,)
        Labels, 1 for occupied.
    radius : float
        Radius of a window, in the units of ``points``.
    max_rows : int
        Rows kept per window.
    n_pieces : int
        Windows wanted.
    random_state : RandomState
        Draws the centres and the rows kept.

    Returns
    -------
    pieces : list of ndarray of int
        Sorted row indices of each window.
    """
    occupied = np.flatnonzero(y == 1)
    if occupied.size == 0 or occupied.size == y.size:
        return []
    tree = cKDTree(points)
    pieces, seen = [], set()
    for _ in range(10 * n_pieces):
        centre = points[occupied[random_state.randint(occupied.size)]]
        rows = np.asarray(tree.query_ball_point(centre, radius), dtype=np.intp)
        if rows.size > max_rows:
            rows = random_state.choice(rows, max_rows, replace=False)
        rows = np.sort(rows)
        labels = y[rows]
        if 0 < labels.sum() < rows.size and rows.tobytes() not in seen:
            seen.add(rows.tobytes())
            pieces.append(rows)
            if len(pieces) == n_pieces:
                break
    return pieces


def learn_shared_kernel(expert, pieces, *, n_jobs=None):
    """Hyperparameters maximising the summed log evidence of the experts of ``pieces``.

    Parameters
    ----------
    expert : estimator
        GP classifier with ``kernel`` and ``optimizer`` parameters and a
        ``log_marginal_likelihood(theta, eval_gradient=True)`` method once fitted (as
        :class:`~skoccmap.EPGaussianProcessClassifier` or scikit-learn's
        ``GaussianProcessClassifier``). Its ``optimizer`` maximises the sum (L-BFGS-B for
        ``"fmin_l_bfgs_b"``, or a callable as in scikit-learn's GPs); ``None`` keeps the
        kernel as given. Restarts are not drawn.
    pieces : list of (X, y)
        Training data of the experts, each with both classes.
    n_jobs : int, default=None
        The experts are fitted, and the evidence terms of each optimiser step computed, in
        as many processes.

    Returns
    -------
    kernel : kernel instance
        The expert's kernel with the learned hyperparameters.
    """
    optimizer = expert.get_params()["optimizer"]
    if optimizer is not None and getattr(expert, "kernel", None) is not None:
        _check_learnable(expert.kernel)
    fitted = Parallel(n_jobs=n_jobs)(delayed(_fit_fixed)(expert, X, y) for X, y in pieces)
    kernel = fitted[0].kernel_
    if optimizer is None or kernel.n_dims == 0:
        return kernel

    def obj_func(theta, eval_gradient=True):
        value, grad = _negative_sum(theta, fitted, n_jobs)
        return (value, grad) if eval_gradient else value

    theta = _minimize_in_bounds(optimizer, obj_func, kernel.theta, kernel.bounds)[0]
    return kernel.clone_with_theta(theta)


def warn_at_bounds(kernel, where):
    """ConvergenceWarning for every hyperparameter of ``kernel`` learned at a bound."""
    theta, bounds = kernel.theta, kernel.bounds
    names = [h.name for h in kernel.hyperparameters if not h.fixed for _ in range(h.n_elements)]
    for name, value, (lo, hi) in zip(names, theta, bounds, strict=True):
        if lo + _AT_BOUND_ATOL < value < hi - _AT_BOUND_ATOL:
            continue
        side = "lower" if value <= lo + _AT_BOUND_ATOL else "upper"
        warn(
            f"The {where} hyperparameter {name} ended at its {side} bound "
            f"({np.exp(value):.3g}). Widen its bounds in the kernel if the map needs it, "
            "or fix it (bounds='fixed').",
            ConvergenceWarning,
        )


def warn_beyond_extent(kernel, extent, where):
    """ConvergenceWarning for every learned length scale of ``kernel`` beyond ``extent``.

    A length scale longer than the data's extent makes every location look alike: the map
    is nearly one value everywhere, and every expert reaches every query. Within its
    bounds (scikit-learn's default upper bound is 1e5) such a value raises no bound
    warning; it is the failure of learning on pieces too sparse for the map's structure,
    such as wide ``hyperparameter_window`` windows on a sparse log.
    """
    params = kernel.get_params()
    for name, value in params.items():
        if not name.endswith("length_scale"):
            continue
        if isinstance(params.get(name + "_bounds"), str):  # "fixed": not learned
            continue
        longest = float(np.max(value))
        if longest > extent:
            warn(
                f"The {where} hyperparameter {name} was learned at {longest:.3g}, beyond "
                f"the extent of the training data ({extent:.3g}): the map is nearly "
                "constant. Learn it on smaller pieces (hyperparameter_window=None or a "
                "smaller window), narrow its bounds in the kernel, or fix it.",
                ConvergenceWarning,
            )
