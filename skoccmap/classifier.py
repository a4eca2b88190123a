"""Gaussian-process classification by Expectation Propagation.

Binary problems are solved by EP; more classes by one-vs-rest or one-vs-one binary
problems, as in scikit-learn's ``GaussianProcessClassifier``.
"""

import copy
import warnings
from numbers import Integral, Real

import numpy as np
import scipy.optimize
from scipy.linalg.lapack import dtpttr
from scipy.special import ndtr
from sklearn.base import BaseEstimator, ClassifierMixin, _fit_context, clone
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process.kernels import RBF, CompoundKernel, Kernel
from sklearn.gaussian_process.kernels import ConstantKernel as C
from sklearn.multiclass import OneVsOneClassifier, OneVsRestClassifier
from sklearn.utils import check_random_state
from sklearn.utils._param_validation import Interval, StrOptions
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.optimize import _check_optimize_result
from sklearn.utils.validation import check_is_fitted, validate_data

from ._validation import caller_stacklevel, fit_or_unfitted
from .ep import (
    EPResult,
    ep_append_sites,
    ep_latent_joint_predictive,
    ep_latent_predictive,
    ep_latent_predictive_packed,
    ep_log_marginal_likelihood,
    ep_log_marginal_likelihood_gradient,
    ep_posterior,
    expectation_propagation,
)
from .observations import _row_blocks

# Test points per block in predictions: bounds the (block, n_train) cross-covariance to ~32 MB.
_PREDICT_BLOCK_ELEMENTS = 2**22
# Up to this many queries an expert solves on its packed factor, a query at a time
# (ep_latent_predictive_packed): about 6 us each for 280 training rows, against about
# 35 us to unpack the factor and 30 us for one triangular solve of a few columns.
_PACKED_SOLVE_QUERIES = 8
# Floor of the latent variance; predictions promise a strictly positive variance.
_VAR_FLOOR = 1e-12

# Fitted attributes of a binary fit, and of a multi-class fit (beyond classes_ and the
# like): a refit of the other kind removes them.
_BINARY_ATTRIBUTES = (
    "X_train_",
    "y_train_",
    "site_precision_",
    "site_nu_",
    "_posterior",
    "_posterior_lower",
    "_rng",
)
_MULTI_CLASS_ATTRIBUTES = ("_multi_class_estimator",)


def _lower_triangle(M):
    """The lower triangle of a square matrix, row by row: half of its memory."""
    return M[np.tri(M.shape[0], dtype=bool)]


def _from_lower_triangle(lower, *, symmetric=False):
    """The square matrix of a :func:`_lower_triangle`: zeros above it, or its mirror."""
    n = int(round((np.sqrt(8 * lower.size + 1) - 1) / 2))
    if not symmetric:
        # The rows of a lower triangle are the columns of its transpose's upper one, which
        # LAPACK's column-packed format holds: one pass, where a boolean mask takes four
        # times as long (every few-query prediction of an expert unpacks its factor).
        upper, info = dtpttr(n, lower, uplo="U")
        if info == 0:
            return upper.T
    mask = np.tri(n, dtype=bool)
    M = np.zeros((n, n))
    M[mask] = lower
    if symmetric:
        M.T[mask] = lower
    return M


def _packed(posterior):
    """The posterior without its Cholesky factor, and the factor's lower triangle.

    A fitted classifier keeps the factor for its predictions; its upper triangle is zeros,
    and a map of many experts held twice the memory it needs (the factors are most of a
    mixture's memory).
    """
    if posterior.L is None:
        return posterior, None
    return posterior._replace(L=None), _lower_triangle(posterior.L)


def _unpacked(posterior, lower):
    """The posterior with its Cholesky factor rebuilt from :func:`_packed`'s triangle."""
    if lower is None:
        return posterior
    return posterior._replace(L=_from_lower_triangle(lower))


# Projected gradient (of -log evidence) below this, relative to max(1, |value|), counts as
# a stationary point.
_STATIONARY_RTOL = 1e-4


def _is_stationary(opt_res, bounds):
    """Whether an L-BFGS-B result is a (bound-constrained) stationary point."""
    if opt_res.success:
        return True
    x, grad = opt_res.x, np.asarray(opt_res.jac, dtype=float)
    if not (np.all(np.isfinite(grad)) and np.isfinite(opt_res.fun)):
        return False
    # Components pressing against their bound do not count.
    pressing = ((x <= bounds[:, 0]) & (grad > 0)) | ((x >= bounds[:, 1]) & (grad < 0))
    free = np.where(pressing, 0.0, grad)
    return bool(np.max(np.abs(free), initial=0.0) <= _STATIONARY_RTOL * max(1.0, abs(opt_res.fun)))


# A learnt log-hyperparameter this close to a bound counts as at the bound: scikit-learn's
# np.isclose tolerance (rtol 1e-5), widened to 1e-3 in log space (0.1 % of the value),
# because L-BFGS-B stops on EP's flat evidence near a bound a step of ~1e-4 away from it.
_AT_BOUND_RTOL = 1e-5
_AT_BOUND_ATOL = 1e-3


def _warn_at_bounds(kernel):
    """scikit-learn's ConvergenceWarning for each learnt hyperparameter at its bound."""
    close = np.isclose(
        kernel.bounds, kernel.theta[:, None], rtol=_AT_BOUND_RTOL, atol=_AT_BOUND_ATOL
    )
    idx = 0
    for hyp in kernel.hyperparameters:
        if hyp.fixed:
            continue
        bounds = np.atleast_2d(hyp.bounds)
        for dim in range(hyp.n_elements):
            at_lower, at_upper = close[idx]
            idx += 1
            if at_lower:
                side, bound, verb = "lower", bounds[dim][0], "Decreasing"
            elif at_upper:
                side, bound, verb = "upper", bounds[dim][1], "Increasing"
            else:
                continue
            warnings.warn(
                f"The optimal value found for dimension {dim} of parameter {hyp.name} is "
                f"close to the specified {side} bound {bound}. {verb} the bound and calling "
                "fit again may find a better value.",
                ConvergenceWarning,
                stacklevel=caller_stacklevel(),
            )


# Log-hyperparameters closer than this (max norm) are one point to the optimiser. EP's
# evidence is exact only to EP's tolerance, so near the optimum a line search cannot resolve
# the decrease over smaller steps and L-BFGS-B re-evaluates the same point again and again:
# on the summed evidence of 52 experts (B2's world, 4k rows) 25 of 33 evaluations lay within
# 1e-6 of the optimum, each re-running EP on every expert.
_THETA_RESOLUTION = 1e-6


def _evaluated_once(obj_func, resolution=_THETA_RESOLUTION):
    """``obj_func`` (value and gradient) that answers a point within ``resolution`` of one
    already evaluated with that evaluation, instead of evaluating it again.

    A line search that cannot find a decrease then sees none and ends at once; the point
    returned lies within ``resolution`` of the one the exact evidence would give.
    """
    evaluated = []

    def once(theta, eval_gradient=True):
        theta = np.asarray(theta, dtype=float)
        near = (r for p, r in evaluated if np.max(np.abs(p - theta), initial=0.0) <= resolution)
        result = next(near, None)
        if result is None:
            result = obj_func(theta, eval_gradient=True)
            evaluated.append((theta.copy(), result))
        return result if eval_gradient else result[0]

    return once


def _first_step_scale(obj_func, initial_theta):
    """Largest gradient component at ``initial_theta`` (at least 1): dividing the objective
    by it makes L-BFGS-B's first step, the negative gradient (its Hessian estimate starts as
    the identity), move no log-hyperparameter by more than one unit. Unscaled, EP's summed
    evidence has gradients in the hundreds and the first step went to a bound of the
    length scale (1e5 or 1e-5 m), an evaluation wasted at a meaningless kernel."""
    _, grad = obj_func(np.asarray(initial_theta, dtype=float))
    grad = np.asarray(grad, dtype=float)
    if grad.size == 0 or not np.all(np.isfinite(grad)):
        return 1.0
    return max(1.0, float(np.max(np.abs(grad))))


def _check_learnable(kernel):
    """Raise a ValueError naming the first hyperparameter to be learned whose value or
    bounds are not positive and finite, or whose bounds are reversed: the optimiser works
    on their logarithms, within the bounds."""
    params = kernel.get_params()
    for hyp in kernel.hyperparameters:
        if hyp.fixed:
            continue
        value = np.atleast_1d(np.asarray(params[hyp.name], dtype=float))
        low, high = np.atleast_2d(np.asarray(hyp.bounds, dtype=float)).T
        shown = value.tolist() if value.size > 1 else float(value[0])
        bounds = hyp.bounds.tolist() if low.size > 1 else [float(low[0]), float(high[0])]
        if not np.all((low > 0) & (low < high) & np.isfinite(low)):  # False for NaN
            raise ValueError(
                f"The bounds of the kernel's {hyp.name} must be pairs (low, high) with "
                f"0 < low < high (high may be inf), got {bounds}; correct "
                f"{hyp.name}_bounds, or make them 'fixed' to keep the value as it is."
            )
        if not np.all(np.isfinite(value) & (value > 0)):
            raise ValueError(
                f"The kernel's {hyp.name} must be positive and finite to be learned, got {shown}."
            )


def _minimize_in_bounds(optimizer, obj_func, initial_theta, bounds):
    """Minimise ``obj_func`` over log-hyperparameters within ``bounds``; ``(theta, value)``.

    ``optimizer`` is ``"fmin_l_bfgs_b"`` (L-BFGS-B with the analytic gradient, each point
    evaluated once to :data:`_THETA_RESOLUTION`, the objective scaled by
    :func:`_first_step_scale`) or a callable ``optimizer(obj_func, initial_theta,
    bounds=bounds)``, as in scikit-learn's GPs.
    """
    if optimizer == "fmin_l_bfgs_b":
        once = _evaluated_once(obj_func)
        scale = _first_step_scale(once, initial_theta)

        def scaled(theta):
            value, grad = once(theta)
            return value / scale, np.asarray(grad, dtype=float) / scale

        opt_res = scipy.optimize.minimize(
            scaled, initial_theta, method="L-BFGS-B", jac=True, bounds=bounds
        )
        opt_res.fun, opt_res.jac = opt_res.fun * scale, opt_res.jac * scale
        # EP's evidence is exact only to EP's tolerance, so near a flat optimum (often at a
        # bound, on separable data) the line search can fail although the projected
        # gradient vanishes: that is convergence, not a warning.
        if not _is_stationary(opt_res, bounds):
            _check_optimize_result("lbfgs", opt_res)
        return opt_res.x, opt_res.fun
    return optimizer(obj_func, initial_theta, bounds=bounds)


class EPGaussianProcessClassifier(ClassifierMixin, BaseEstimator):
    """GP classifier with a probit likelihood, fitted by Expectation Propagation.

    The posterior over the latent function is approximated by EP (Rasmussen & Williams 2006,
    Algorithm 3.5) in the numerically stable ``B = I + S^1/2 K S^1/2`` form; predictions follow
    Algorithm 3.6 and the kernel hyperparameters maximise the EP approximation of the log
    marginal likelihood (eq. 3.65) with its analytic gradient (eq. 5.27). The EP math lives in
    :mod:`skoccmap.ep`.

    With more than two classes, one binary classifier of this kind is fitted per class
    against the rest or per pair of classes (``multi_class``), each with its own
    hyperparameters, as scikit-learn's ``GaussianProcessClassifier`` does: this is not a
    true multi-class EP approximation.

    Parameters
    ----------
    kernel : kernel instance, default=None
        Covariance of the latent GP. None means ``ConstantKernel(1.0, (1e-3, 1e3)) *
        RBF(1.0, (1e-3, 1e3))``, whose hyperparameters are learnt. The kernel decides what the
        columns of ``X`` mean (e.g. :class:`skoccmap.IntegralKernel` reads segment rows).
    optimizer : "fmin_l_bfgs_b", callable or None, default="fmin_l_bfgs_b"
        Maximiser of the log marginal likelihood over the kernel's log-hyperparameters. A
        callable is called as ``optimizer(obj_func, initial_theta, bounds=bounds)`` and returns
        ``(theta_opt, func_min)``, as in scikit-learn's GP estimators; ``obj_func(theta,
        eval_gradient=True)`` returns the negative log marginal likelihood and its gradient.
        None keeps the hyperparameters fixed.
    n_restarts_optimizer : int, default=0
        Further optimiser runs, started from log-hyperparameters drawn uniformly within the
        (log-space) bounds of the kernel. The best run is kept.
    ep_update : {"parallel", "sequential"}, default="parallel"
        ``"parallel"`` updates all sites from the current marginals and refactorises once per
        sweep; ``"sequential"`` updates one site at a time with rank-one updates. Both reach
        the same fixed point. Parallel EP that stalls in a cycle damps harder and then
        finishes with sequential sweeps (see :func:`skoccmap.ep.expectation_propagation`).
    damping : float in [0, 1), default=0.5
        Weight kept on the current site parameters in each update: ``new = damping * current
        + (1 - damping) * proposed``. 0 is undamped EP. Raise it if parallel EP oscillates
        (large signal variances).
    max_iter : int, default=200
        Maximum number of EP sweeps per EP run.
    tol : float, default=1e-6
        EP stops when no site would change by more than ``tol`` in units of its
        marginal (see :func:`skoccmap.ep.expectation_propagation`).
    copy_X_train : bool, default=True
        Whether ``X_train_`` is a copy of the training data or a reference to it.
    random_state : int, RandomState instance or None, default=None
        Draws the starting points of the optimiser restarts. Every binary problem of a
        multi-class fit gets the same ``random_state``.
    multi_class : {"one_vs_rest", "one_vs_one"}, default="one_vs_rest"
        How more than two classes are handled: ``"one_vs_rest"`` fits one binary classifier
        per class against all others (probabilities are their normalised positive-class
        probabilities); ``"one_vs_one"`` fits one per pair of classes and predicts by their
        votes, without probability estimates. Ignored for two classes.
    n_jobs : int, default=None
        Number of jobs fitting and predicting the binary problems of a multi-class fit in
        parallel. None means 1 unless in a :obj:`joblib.parallel_config` context; -1 means
        all processors. Ignored for two classes.

    Attributes
    ----------
    base_estimator_ : estimator
        The fitted binary problem(s). For two classes the classifier itself, which holds the
        binary attributes below; for more, a
        :class:`~sklearn.multiclass.OneVsRestClassifier` or
        :class:`~sklearn.multiclass.OneVsOneClassifier` whose ``estimators_`` are fitted
        binary ``EPGaussianProcessClassifier`` instances.
    kernel_ : kernel instance
        The kernel with the learnt (or fixed) hyperparameters. For more than two classes a
        :class:`~sklearn.gaussian_process.kernels.CompoundKernel` of the binary
        classifiers' kernels, in the order of ``base_estimator_.estimators_``.
    classes_ : ndarray of shape (n_classes,)
        The class labels, sorted. With two, ``classes_[1]`` is the positive class (latent
        ``f > 0``).
    n_classes_ : int
        Number of classes.
    X_train_ : ndarray of shape (n_samples, n_features)
        Training inputs, needed for predictions. Two classes only, as ``y_train_``,
        ``site_precision_`` and ``site_nu_``; with more, the binary classifiers in
        ``base_estimator_.estimators_`` hold theirs.
    y_train_ : ndarray of shape (n_samples,)
        Training labels as -1 / +1 (+1 for ``classes_[1]``).
    site_precision_ : ndarray of shape (n_samples,)
        EP site precisions tau (R&W's tau-tilde), all ``>= 0``.
    site_nu_ : ndarray of shape (n_samples,)
        EP site natural means nu = tau * site mean (R&W's nu-tilde).
    n_iter_ : int or ndarray of shape (n_estimators,)
        Number of EP sweeps of the final EP run, at ``kernel_``'s hyperparameters; for more
        than two classes, one per binary classifier of ``base_estimator_.estimators_``.
        After hyperparameter learning that run starts from the optimiser's last sites and
        often takes a single sweep; refit with ``optimizer=None`` and ``kernel=kernel_``
        to count the sweeps EP needs from zero sites.
    log_marginal_likelihood_value_ : float
        EP log marginal likelihood at ``kernel_.theta``; for more than two classes the mean
        over the binary classifiers.
    n_features_in_ : int
        Number of columns seen in fit.

    See Also
    --------
    sklearn.gaussian_process.GaussianProcessClassifier : Laplace approximation, logistic link.

    Notes
    -----
    scikit-learn's ``warm_start`` and ``max_iter_predict`` have no counterpart here: EP
    starts each optimiser step from the last one's sites by itself, ``max_iter`` and
    ``tol`` bound its sweeps, and prediction runs no iteration (the posterior is kept from
    the fit). The default kernel learns the signal variance and the length scale, where
    scikit-learn's default, ``1.0 * RBF(1.0)``, keeps both fixed.

    No ``decision_function`` is provided: the latent mean ranks test points differently from
    ``predict_proba``, which also accounts for the latent variance. One-vs-one predictions
    therefore weigh the votes by the binary classifiers' probabilities.

    A ``ConvergenceWarning`` with scikit-learn's message is raised when a learnt
    hyperparameter ends at one of its bounds: within scikit-learn's ``numpy.isclose``
    tolerance of it, or within 1e-3 in log space (L-BFGS-B stops on the flat evidence near
    a bound a little inside it).

    References
    ----------
    C. E. Rasmussen and C. K. I. Williams, "Gaussian Processes for Machine Learning",
    MIT Press, 2006, chapters 3.6 and 5.5.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap import EPGaussianProcessClassifier
    >>> rng = np.random.default_rng(0)
    >>> X = rng.uniform(-3, 3, size=(60, 1))
    >>> noisy_sine = np.sin(X[:, 0]) + 0.3 * rng.normal(size=60)
    >>> y = (noisy_sine > 0).astype(int)
    >>> clf = EPGaussianProcessClassifier(random_state=0).fit(X, y)
    >>> clf.predict([[-1.5], [1.5]])
    array([0, 1])
    >>> mean, var = clf.latent_mean_and_variance([[1.5]])
    >>> bool(mean[0] > 0 and var[0] > 0)
    True

    Three classes, one binary classifier per class against the rest:

    >>> y3 = np.digitize(np.sin(X[:, 0]) + 0.3 * rng.normal(size=60), [-0.35, 0.35])
    >>> clf3 = EPGaussianProcessClassifier(random_state=0).fit(X, y3)
    >>> clf3.classes_, clf3.n_classes_, len(clf3.base_estimator_.estimators_)
    (array([0, 1, 2]), 3, 3)
    >>> clf3.predict([[-1.5], [0.0], [1.5]])
    array([0, 1, 2])
    >>> clf3.predict_proba([[0.0]]).sum(axis=1)
    array([1.])
    """

    _parameter_constraints: dict = {
        "kernel": [Kernel, None],
        "optimizer": [StrOptions({"fmin_l_bfgs_b"}), callable, None],
        "n_restarts_optimizer": [Interval(Integral, 0, None, closed="left")],
        "ep_update": [StrOptions({"parallel", "sequential"})],
        "damping": [Interval(Real, 0, 1, closed="left")],
        "max_iter": [Interval(Integral, 1, None, closed="left")],
        "tol": [Interval(Real, 0, None, closed="neither")],
        "copy_X_train": ["boolean"],
        "random_state": ["random_state"],
        "multi_class": [StrOptions({"one_vs_rest", "one_vs_one"})],
        "n_jobs": [
            Interval(Integral, None, -1, closed="right"),
            Interval(Integral, 1, None, closed="left"),
            None,
        ],
    }

    def __init__(
        self,
        kernel=None,
        *,
        optimizer="fmin_l_bfgs_b",
        n_restarts_optimizer=0,
        ep_update="parallel",
        damping=0.5,
        max_iter=200,
        tol=1e-6,
        copy_X_train=True,
        random_state=None,
        multi_class="one_vs_rest",
        n_jobs=None,
    ):
        self.kernel = kernel
        self.optimizer = optimizer
        self.n_restarts_optimizer = n_restarts_optimizer
        self.ep_update = ep_update
        self.damping = damping
        self.max_iter = max_iter
        self.tol = tol
        self.copy_X_train = copy_X_train
        self.random_state = random_state
        self.multi_class = multi_class
        self.n_jobs = n_jobs

    @fit_or_unfitted
    @_fit_context(prefer_skip_nested_validation=True)
    def fit(self, X, y):
        """Fit the EP approximation and, unless ``optimizer=None``, the hyperparameters.

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)
            Training inputs.
        y : array-like of shape (n_samples,)
            Labels of two or more classes.

        Returns
        -------
        self : object
            The fitted classifier.
        """
        if isinstance(self.kernel, CompoundKernel):
            raise ValueError("kernel cannot be a CompoundKernel")
        if self.kernel is None or self.kernel.requires_vector_input:
            X, y = validate_data(self, X, y, ensure_2d=True, dtype="numeric")
        else:
            X, y = validate_data(self, X, y, ensure_2d=False, dtype=None)
        check_classification_targets(y)
        classes = self.__dict__.get("_given_classes")
        classes = np.unique(y) if classes is None else classes
        if classes.size < 2:
            raise ValueError(
                f"y holds one class ({classes.tolist()}); {type(self).__name__} needs "
                "samples of two or more classes."
            )
        self.classes_ = classes
        self.n_classes_ = classes.size
        if self.n_classes_ > 2:
            for name in _BINARY_ATTRIBUTES:
                self.__dict__.pop(name, None)
            self._fit_multi_class(X, y)
        else:
            for name in _MULTI_CLASS_ATTRIBUTES:
                self.__dict__.pop(name, None)
            self._fit_binary(X, y)
        return self

    def _fit_multi_class(self, X, y):
        """One binary classifier per class (against the rest) or per pair of classes."""
        binary = clone(self).set_params(n_jobs=None)
        if self.multi_class == "one_vs_rest":
            ensemble = OneVsRestClassifier(binary, n_jobs=self.n_jobs)
        else:
            ensemble = OneVsOneClassifier(binary, n_jobs=self.n_jobs)
        self._multi_class_estimator = ensemble.fit(X, y)
        estimators = ensemble.estimators_
        # References to the binary kernels: log_marginal_likelihood(clone_kernel=False)
        # changes them in place, and kernel_ with them.
        self.kernel_ = CompoundKernel([estimator.kernel_ for estimator in estimators])
        self.log_marginal_likelihood_value_ = np.mean(
            [estimator.log_marginal_likelihood_value_ for estimator in estimators]
        )
        self.n_iter_ = np.array([estimator.n_iter_ for estimator in estimators])

    def _fit_binary(self, X, y):
        if self.kernel is None:
            self.kernel_ = C(1.0, constant_value_bounds=(1e-3, 1e3)) * RBF(
                1.0, length_scale_bounds=(1e-3, 1e3)
            )
        else:
            self.kernel_ = clone(self.kernel)
        self.X_train_ = np.copy(X) if self.copy_X_train else X
        self.y_train_ = np.where(y == self.classes_[1], 1.0, -1.0)
        self._rng = check_random_state(self.random_state)

        # Sites of the last EP run: each optimiser step starts from them (a warm start).
        # _fit_warm_start sets the first start.
        warm = [self.__dict__.pop("_initial_sites", None)]
        # A kernel matrix handed in by _fit_warm_start is K(X, X) of ``kernel``: valid only
        # while kernel_ is that kernel, i.e. unless hyperparameters are learned here.
        K = self.__dict__.pop("_initial_kernel", None)
        hold = self.__dict__.pop("_hold", None)
        if self.optimizer is not None:
            _check_learnable(self.kernel_)
        if self.optimizer is not None and self.kernel_.n_dims > 0:
            self._optimize_hyperparameters(warm)
            _warn_at_bounds(self.kernel_)
            K, hold = None, None

        if K is None:
            K = self.kernel_(self.X_train_)
        result = None
        if hold is not None and warm[0] is not None and np.any(hold):
            result = self._ep_holding(K, *warm[0], hold)
        if result is None:
            result = self._run_ep(K, warm)
        if not result.converged:
            warnings.warn(
                f"EP did not converge in max_iter={self.max_iter} sweeps (largest site "
                f"residual {result.residual:.2e} > tol={self.tol:g}). Increase max_iter, or "
                "increase damping (parallel updates oscillate at large signal variances), or "
                "use ep_update='sequential'.",
                ConvergenceWarning,
                stacklevel=caller_stacklevel(),
            )
        self.site_precision_ = result.site_precision
        self.site_nu_ = result.site_nu
        self.n_iter_ = result.n_iter
        self._posterior, self._posterior_lower = _packed(result.posterior)
        # np.float64 as in scikit-learn: arithmetic with float32 stays in float64.
        self.log_marginal_likelihood_value_ = np.float64(
            ep_log_marginal_likelihood(
                K, self.y_train_, result.site_precision, result.site_nu, posterior=result.posterior
            )
        )

    def _fit_warm_start(
        self, X, y, site_precision=None, site_nu=None, kernel_matrix=None, hold=None
    ):
        """``fit``, with the first EP run started from the given sites (a warm start).

        EP iterates to the same fixed point (within ``tol``) from any start; sites from an
        earlier fit on most of the same rows (zeros for new rows) need fewer sweeps. If EP
        does not converge from them it restarts from zero sites, as every warm start here.
        ``kernel_matrix``, ``kernel(X, X)`` computed by the caller (e.g. mostly from an
        earlier fit's matrix), replaces that evaluation in a binary fit whose kernel is not
        learned; it is ignored otherwise.

        ``hold``, a boolean mask of rows, holds those rows' sites at the given values in
        a binary fit whose kernel is not learned: EP runs on the other rows' sites alone
        (:meth:`_ep_holding`), and the fit is not EP's fixed point on all rows.
        """
        if site_precision is not None:
            self._initial_sites = (
                np.asarray(site_precision, dtype=np.float64),
                np.asarray(site_nu, dtype=np.float64),
            )
        if kernel_matrix is not None:
            self._initial_kernel = np.asarray(kernel_matrix, dtype=np.float64)
        if hold is not None:
            self._hold = np.asarray(hold, dtype=bool)
        try:
            return self.fit(X, y)
        finally:
            for name in ("_initial_sites", "_initial_kernel", "_hold"):
                self.__dict__.pop(name, None)

    def _fit_one_class(self, X, y, classes):
        """``fit`` on labels of one of the two ``classes``: the GP posterior of data that
        show one class only (a wall seen without the free space in front of it).

        EP needs no second class: each site pulls the latent to its own label's side.
        ``fit`` asks for two, as scikit-learn's classifiers do. Learning hyperparameters
        on one class would drive the signal variance to its bound: set ``optimizer=None``.
        """
        given = np.asarray(classes)
        # Sorted, as np.unique gives them to fit: classes_[1] is the positive class.
        if given.size != 2 or not given[0] < given[1] or not np.all(np.isin(y, given)):
            raise ValueError(
                f"classes must be two distinct labels in increasing order holding y's, "
                f"got {classes!r}."
            )
        self._given_classes = given
        try:
            return self.fit(X, y)
        finally:
            self.__dict__.pop("_given_classes", None)

    def _absorbed(self, X, y, K_cross=None, K_new=None):
        """A copy with the rows ``X`` appended to the fit, EP run on their sites alone.

        The other sites are held, and the posterior of all is assembled from this one's
        Cholesky factor (:func:`~skoccmap.ep.ep_append_sites`): ``O(n^2 n_new)``, about
        a prediction of the new rows, with no kernel at the rows already fitted.
        ``K_cross`` (``kernel_(X, X_train_)``) and ``K_new`` (``kernel_(X)``) are computed
        here if None. The log evidence becomes that of the held sites plus that of the
        new ones given them. Only for a binary fit; ``kernel_`` is kept. Returns None
        where the posterior is not in Cholesky form or EP on the new sites fails or does
        not converge (then fit on all rows instead).
        """
        check_is_fitted(self)
        if self.n_classes_ != 2:
            raise ValueError("Only a binary fit can take rows without a refit.")
        y = np.asarray(y)
        if not np.all(np.isin(y, self.classes_)):
            raise ValueError(
                f"y holds labels not in classes_ {self.classes_.tolist()}: refit instead."
            )
        K_cross = self.kernel_(X, self.X_train_) if K_cross is None else K_cross
        K_new = self.kernel_(X) if K_new is None else K_new
        y_new = np.where(y == self.classes_[1], 1.0, -1.0)
        posterior = _unpacked(self._posterior, self._posterior_lower)
        result, log_evidence = ep_append_sites(
            posterior,
            K_cross,
            K_new,
            y_new,
            update=self.ep_update,
            damping=self.damping,
            max_iter=self.max_iter,
            tol=self.tol,
        )
        if result is None:
            return None
        absorbed = copy.copy(self)
        absorbed.X_train_ = np.concatenate([self.X_train_, X])
        absorbed.y_train_ = np.concatenate([self.y_train_, y_new])
        absorbed.site_precision_ = np.concatenate([self.site_precision_, result.site_precision])
        absorbed.site_nu_ = np.concatenate([self.site_nu_, result.site_nu])
        absorbed.n_iter_ = result.n_iter
        absorbed._posterior, absorbed._posterior_lower = _packed(result.posterior)
        absorbed.log_marginal_likelihood_value_ = np.float64(
            self.log_marginal_likelihood_value_ + log_evidence
        )
        return absorbed

    def _ep_holding(self, K, tau, nu, hold):
        """EP on the sites of the rows not in ``hold``, the others held at ``tau``, ``nu``.

        The free rows' prior is then the held sites' posterior predictive there, jointly
        (:func:`~skoccmap.ep.ep_latent_joint_predictive`), and EP costs ``n_free^3`` per
        sweep instead of ``n^3``; the posterior of all sites is computed once at the end.
        With the held sites at EP's fixed point on all rows, the free sites land on it too.
        Returns an :class:`~skoccmap.ep.EPResult`, or None where EP on the free sites
        fails or does not converge.
        """
        held, free = np.flatnonzero(hold), np.flatnonzero(~hold)
        try:
            posterior = ep_posterior(K[np.ix_(held, held)], tau[held], nu[held])
            mean, cov = ep_latent_joint_predictive(
                K[np.ix_(free, held)], K[np.ix_(free, free)], posterior
            )
            tau, nu = tau.copy(), nu.copy()
            n_iter, residual = 0, 0.0
            if free.size:
                # EP's sites on the free rows are in the latent centred on ``mean``; in the
                # latent itself their nu is larger by tau * mean.
                result = expectation_propagation(
                    cov,
                    self.y_train_[free],
                    mean=mean,
                    site_precision=tau[free],
                    site_nu=nu[free] - tau[free] * mean,
                    update=self.ep_update,
                    damping=self.damping,
                    max_iter=self.max_iter,
                    tol=self.tol,
                )
                if not result.converged:
                    return None
                tau[free] = result.site_precision
                nu[free] = result.site_nu + result.site_precision * mean
                n_iter, residual = result.n_iter, result.residual
            return EPResult(tau, nu, ep_posterior(K, tau, nu), n_iter, True, residual)
        except np.linalg.LinAlgError:
            return None

    def _run_ep(self, K, warm):
        """EP started from the sites in ``warm[0]`` (zeros if None); from zero sites if that
        fails. Stores the new sites in ``warm[0]``."""
        start = warm[0] if warm[0] is not None else (None, None)
        try:
            result = expectation_propagation(
                K,
                self.y_train_,
                site_precision=start[0],
                site_nu=start[1],
                update=self.ep_update,
                damping=self.damping,
                max_iter=self.max_iter,
                tol=self.tol,
            )
        except np.linalg.LinAlgError:
            result = None
        if (result is None or not result.converged) and warm[0] is not None:
            warm[0] = None
            return self._run_ep(K, warm)
        if result is None:
            raise np.linalg.LinAlgError(
                "EP failed: the kernel matrix is not positive definite at these "
                "hyperparameters. Add a WhiteKernel or check the kernel."
            )
        warm[0] = (result.site_precision, result.site_nu)
        return result

    def _optimize_hyperparameters(self, warm):
        def obj_func(theta, eval_gradient=True):
            kernel = self.kernel_.clone_with_theta(theta)
            try:
                out = self._lml(kernel, warm, eval_gradient)
            except np.linalg.LinAlgError:
                return (np.inf, np.zeros_like(theta)) if eval_gradient else np.inf
            return (-out[0], -out[1]) if eval_gradient else -out

        bounds = self.kernel_.bounds
        optima = [self._constrained_optimization(obj_func, self.kernel_.theta, bounds)]
        if self.n_restarts_optimizer > 0:
            if not np.isfinite(bounds).all():
                raise ValueError(
                    "n_restarts_optimizer > 0 needs finite bounds on every kernel hyperparameter."
                )
            for _ in range(self.n_restarts_optimizer):
                # kernel.bounds are already log-transformed: draw uniformly in log space.
                theta_initial = self._rng.uniform(bounds[:, 0], bounds[:, 1])
                optima.append(self._constrained_optimization(obj_func, theta_initial, bounds))
        best = int(np.argmin([func_min for _, func_min in optima]))
        self.kernel_.theta = optima[best][0]

    def _lml(self, kernel, warm, eval_gradient):
        """EP log marginal likelihood (and gradient) of the training data under ``kernel``."""
        if eval_gradient:
            K, K_gradient = kernel(self.X_train_, eval_gradient=True)
        else:
            K = kernel(self.X_train_)
        result = self._run_ep(K, warm)
        lml = np.float64(
            ep_log_marginal_likelihood(
                K, self.y_train_, result.site_precision, result.site_nu, posterior=result.posterior
            )
        )
        if not eval_gradient:
            return lml
        return lml, ep_log_marginal_likelihood_gradient(K_gradient, result.posterior)

    def _constrained_optimization(self, obj_func, initial_theta, bounds):
        return _minimize_in_bounds(self.optimizer, obj_func, initial_theta, bounds)

    @property
    def base_estimator_(self):
        """The fitted binary problem(s): the classifier itself for two classes, else a
        ``OneVsRestClassifier`` or ``OneVsOneClassifier`` of binary classifiers."""
        check_is_fitted(self)
        if self.n_classes_ == 2:
            return self
        return self._multi_class_estimator

    def _validate_queries(self, X):
        """``X`` validated for prediction, as in fit."""
        if self.kernel is None or self.kernel.requires_vector_input:
            return validate_data(self, X, ensure_2d=True, dtype="numeric", reset=False)
        return validate_data(self, X, ensure_2d=False, dtype=None, reset=False)

    def log_marginal_likelihood(self, theta=None, eval_gradient=False, clone_kernel=True):
        """EP log marginal likelihood of the training data (R&W eq. 3.65).

        For more than two classes, the mean over the binary classifiers (as scikit-learn's
        ``GaussianProcessClassifier``), without gradient.

        Parameters
        ----------
        theta : array-like of shape (n_kernel_params,), default=None
            Log-hyperparameters at which to evaluate; None returns the value at ``kernel_``
            computed in fit. For more than two classes, either the hyperparameters of one
            binary kernel (given to every binary classifier) or those of ``kernel_``, the
            compound kernel (each binary classifier gets its own part).
        eval_gradient : bool, default=False
            Whether to return the gradient with respect to ``theta`` too (R&W eq. 5.27).
            Two classes only: more raise NotImplementedError.
        clone_kernel : bool, default=True
            If False, ``kernel_``'s hyperparameters are set to ``theta`` in place.

        Returns
        -------
        log_likelihood : float
        log_likelihood_gradient : ndarray of shape (n_kernel_params,)
            Only when ``eval_gradient`` is True.

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap import EPGaussianProcessClassifier
        >>> X = np.linspace(0, 1, 12)[:, None]
        >>> clf = EPGaussianProcessClassifier().fit(X, [0, 0, 0, 1, 0, 0, 1, 0, 1, 1, 1, 1])
        >>> lml, grad = clf.log_marginal_likelihood(clf.kernel_.theta, eval_gradient=True)
        >>> bool(np.isclose(lml, clf.log_marginal_likelihood_value_)), grad.shape
        (True, (2,))
        """
        check_is_fitted(self)
        if theta is None:
            if eval_gradient:
                raise ValueError("Gradient can only be evaluated for theta!=None")
            return self.log_marginal_likelihood_value_
        theta = np.asarray(theta, dtype=np.float64)
        if theta.ndim != 1:
            # A scalar stopped in scikit-learn's kernels: "too many indices for array".
            raise ValueError(
                "theta must be a 1-D array of log-hyperparameters, as kernel_.theta is "
                f"(shape {self.kernel_.theta.shape}), got shape {theta.shape}."
            )
        if self.n_classes_ > 2:
            return self._multi_class_log_marginal_likelihood(theta, eval_gradient, clone_kernel)
        if clone_kernel:
            kernel = self.kernel_.clone_with_theta(theta)
        else:
            kernel = self.kernel_
            kernel.theta = theta
        return self._lml(kernel, [(self.site_precision_, self.site_nu_)], eval_gradient)

    def _multi_class_log_marginal_likelihood(self, theta, eval_gradient, clone_kernel):
        if eval_gradient:
            raise NotImplementedError(
                "Gradient of log-marginal-likelihood not implemented for multi-class GPC."
            )
        estimators = self._multi_class_estimator.estimators_
        n_dims = estimators[0].kernel_.n_dims
        if theta.shape[0] == n_dims:  # the same theta for every binary kernel
            thetas = [theta] * len(estimators)
        elif theta.shape[0] == n_dims * len(estimators):  # theta of the compound kernel
            thetas = np.split(theta, len(estimators))
        else:
            raise ValueError(
                f"Shape of theta must be either {n_dims} or {n_dims * len(estimators)}. "
                f"Obtained theta with shape {theta.shape[0]}."
            )
        return np.mean(
            [
                estimator.log_marginal_likelihood(part, clone_kernel=clone_kernel)
                for estimator, part in zip(estimators, thetas, strict=True)
            ]
        )

    def latent_mean_and_variance(self, X):
        """Mean and variance of the latent function at ``X`` under the EP posterior.

        Parameters
        ----------
        X : array-like of shape (n_queries, n_features)
            Query points.

        Returns
        -------
        mean : ndarray of shape (n_queries,)
            Latent mean (positive favours ``classes_[1]``).
        var : ndarray of shape (n_queries,)
            Latent variance, strictly positive (rounding below zero is clipped).

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap import EPGaussianProcessClassifier
        >>> X = np.linspace(0, 1, 8)[:, None]
        >>> clf = EPGaussianProcessClassifier(optimizer=None).fit(X, X[:, 0] > 0.5)
        >>> mean, var = clf.latent_mean_and_variance([[0.0], [1.0]])
        >>> bool(mean[0] < 0 < mean[1]), bool(np.all(var < clf.kernel_.diag(X[:2])))
        (True, True)
        """
        return self._latent(self._binary_queries(X, "the mean and variance"))

    def _binary_queries(self, X, what):
        """Validated queries of a fitted binary model; ``what`` of the latent function is
        named in the error for more than two classes."""
        check_is_fitted(self)
        if self.n_classes_ > 2:
            raise ValueError(
                f"Returning {what} of the latent function f is only supported for binary "
                f"classification, received {self.n_classes_} classes."
            )
        if self.kernel_.requires_vector_input:
            return validate_data(self, X, ensure_2d=True, dtype="numeric", reset=False)
        return validate_data(self, X, ensure_2d=False, dtype=None, reset=False)

    def _latent(self, X, prior_variance=None, cross=None):
        """:meth:`latent_mean_and_variance` of validated queries of a fitted binary model,
        given their prior variance ``k(x, x)`` and their cross-covariances
        ``k(X, X_train_)`` when the caller has them (a mixture whose experts share one
        kernel computes them for all of them at once)."""
        n_train = self.X_train_.shape[0]
        mean = np.empty(X.shape[0])
        var = np.empty(X.shape[0])
        block = max(1, _PREDICT_BLOCK_ELEMENTS // max(n_train, 1))
        lower = self._posterior_lower
        # A few queries are solved on the packed factor, which is then not unpacked.
        packed = lower is not None and X.shape[0] <= _PACKED_SOLVE_QUERIES
        posterior = self._posterior if packed else _unpacked(self._posterior, lower)
        # Not gen_batches: its parameter validation cost a mixture's expert 0.1 ms a call.
        for rows in _row_blocks(X.shape[0], block):
            K_star = self.kernel_(X[rows], self.X_train_) if cross is None else cross[rows]
            k_diag = self.kernel_.diag(X[rows]) if prior_variance is None else prior_variance[rows]
            if packed:
                mean[rows], var[rows] = ep_latent_predictive_packed(
                    K_star, k_diag, posterior, lower
                )
            else:
                mean[rows], var[rows] = ep_latent_predictive(K_star, k_diag, posterior)
        return mean, np.maximum(var, _VAR_FLOOR)

    def prior_variance(self, X):
        """Prior latent variance at ``X`` (the kernel's diagonal): what :meth:`predict_var`
        returns far from the training data.

        Parameters
        ----------
        X : array-like of shape (n_queries, n_features)
            Query points.

        Returns
        -------
        var : ndarray of shape (n_queries,)

        Examples
        --------
        >>> import numpy as np
        >>> from sklearn.gaussian_process.kernels import RBF, ConstantKernel
        >>> from skoccmap import EPGaussianProcessClassifier
        >>> X = np.linspace(0, 1, 8)[:, None]
        >>> clf = EPGaussianProcessClassifier(ConstantKernel(4.0) * RBF(0.3), optimizer=None)
        >>> clf = clf.fit(X, X[:, 0] > 0.5)
        >>> clf.prior_variance([[100.0]]), bool(np.isclose(clf.predict_var([[100.0]])[0], 4.0))
        (array([4.]), True)
        """
        X = self._binary_queries(X, "the prior variance")
        return np.asarray(self.kernel_.diag(X), dtype=np.float64)

    def predict_var(self, X):
        """Latent variance at ``X``.

        Parameters
        ----------
        X : array-like of shape (n_queries, n_features)
            Query points.

        Returns
        -------
        var : ndarray of shape (n_queries,)
            Latent variance, strictly positive.

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap import EPGaussianProcessClassifier
        >>> X = np.linspace(0, 1, 8)[:, None]
        >>> clf = EPGaussianProcessClassifier(optimizer=None).fit(X, X[:, 0] > 0.5)
        >>> bool(clf.predict_var([[0.5]])[0] < clf.predict_var([[5.0]])[0])
        True
        """
        return self.latent_mean_and_variance(X)[1]

    def predict_proba(self, X):
        """Class probabilities, ``P(classes_[1]) = Phi(mean / sqrt(1 + var))`` (R&W eq. 3.80).

        For more than two classes (``multi_class="one_vs_rest"``), the binary classifiers'
        probabilities of their class, normalised to sum to one. ``"one_vs_one"`` gives no
        probabilities: a ValueError is raised.

        Parameters
        ----------
        X : array-like of shape (n_queries, n_features)
            Query points.

        Returns
        -------
        proba : ndarray of shape (n_queries, n_classes)
            Columns in the order of ``classes_``.

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap import EPGaussianProcessClassifier
        >>> X = np.linspace(0, 1, 8)[:, None]
        >>> clf = EPGaussianProcessClassifier(optimizer=None).fit(X, X[:, 0] > 0.5)
        >>> clf.predict_proba([[1.0]]).sum(axis=1)
        array([1.])
        """
        check_is_fitted(self)
        if self.n_classes_ > 2:
            if isinstance(self._multi_class_estimator, OneVsOneClassifier):
                raise ValueError(
                    "one_vs_one multi-class mode does not support predicting probability "
                    "estimates. Use one_vs_rest mode instead."
                )
            return self._multi_class_estimator.predict_proba(self._validate_queries(X))
        mean, var = self.latent_mean_and_variance(X)
        z = mean / np.sqrt(1.0 + var)
        return np.column_stack([ndtr(-z), ndtr(z)])

    def predict(self, X):
        """Most probable class at ``X``; for ``multi_class="one_vs_one"`` the class with
        the most votes of the binary classifiers.

        Parameters
        ----------
        X : array-like of shape (n_queries, n_features)
            Query points.

        Returns
        -------
        y_pred : ndarray of shape (n_queries,)

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap import EPGaussianProcessClassifier
        >>> X = np.linspace(0, 1, 8)[:, None]
        >>> y = np.where(X[:, 0] > 0.5, "b", "a")
        >>> clf = EPGaussianProcessClassifier(optimizer=None).fit(X, y)
        >>> clf.predict([[0.0], [1.0]]).tolist()
        ['a', 'b']
        """
        check_is_fitted(self)
        if self.n_classes_ > 2:
            return self._multi_class_estimator.predict(self._validate_queries(X))
        proba = self.predict_proba(X)
        return self.classes_[np.argmax(proba, axis=1)]
