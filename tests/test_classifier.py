"""Tests for EPGaussianProcessClassifier against independent dense computations.

Multi-class models are checked against binary problems fitted by hand.
"""

import pickle
import warnings

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import norm
from sklearn.base import clone
from sklearn.exceptions import ConvergenceWarning, NotFittedError
from sklearn.gaussian_process.kernels import RBF, CompoundKernel, DotProduct, WhiteKernel
from sklearn.gaussian_process.kernels import ConstantKernel as C
from sklearn.multiclass import OneVsOneClassifier, OneVsRestClassifier

from skoccmap.classifier import (
    _THETA_RESOLUTION,
    EPGaussianProcessClassifier,
    _evaluated_once,
    _is_stationary,
    _minimize_in_bounds,
)


def _data(n=40, seed=0, noise=0.3, dim=2):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, size=(n, dim))
    y = (np.sin(2 * X[:, 0]) + X[:, -1] + noise * rng.standard_normal(n) > 0).astype(int)
    return X, y


def _laplace_probit(K, y):
    """Laplace approximation with a probit likelihood (R&W Algorithms 3.1, 3.2, eq. 3.32).

    Returns the mode-based quantities needed for predictions and the approximate evidence.
    """
    n = len(y)
    f = np.zeros(n)
    for _ in range(200):
        z = y * f
        ratio = np.exp(norm.logpdf(z) - norm.logcdf(z))
        grad = y * ratio
        W = ratio**2 + z * ratio
        sW = np.sqrt(W)
        L = np.linalg.cholesky(np.eye(n) + sW[:, None] * K * sW[None, :])
        b = W * f + grad
        a = b - sW * np.linalg.solve(L.T, np.linalg.solve(L, sW * (K @ b)))
        f_new = K @ a
        done = np.max(np.abs(f_new - f)) < 1e-12
        f = f_new
        if done:
            break
    z = y * f
    ratio = np.exp(norm.logpdf(z) - norm.logcdf(z))
    W = ratio**2 + z * ratio
    log_Z = -0.5 * a @ f + norm.logcdf(z).sum() - np.log(np.diag(L)).sum()
    return f, y * ratio, W, log_Z


def _laplace_predict(K, K_star, k_ss, f, grad, W):
    mean = K_star @ grad
    Sigma_inv = np.linalg.inv(K + np.diag(1 / W))
    var = k_ss - np.einsum("ij,jk,ik->i", K_star, Sigma_inv, K_star)
    return mean, var


def test_predictive_moments_match_dense_computation():
    X, y = _data(n=25, seed=1)
    kernel = C(2.0) * RBF(0.8) + WhiteKernel(0.05)
    clf = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-12).fit(X, y)
    K = kernel(X)
    tau, nu = clf.site_precision_, clf.site_nu_
    # q(f) = N(Sigma nu, Sigma), Sigma = (K^-1 + S~)^-1 (R&W eq. 3.53); f_* | f by conditioning.
    Sigma = np.linalg.inv(np.linalg.inv(K) + np.diag(tau))
    mu = Sigma @ nu
    X_test = np.random.default_rng(2).uniform(-3, 3, size=(7, 2))
    K_star = kernel(X_test, X)
    A = np.linalg.solve(K, K_star.T)
    mean_ref = A.T @ mu
    var_ref = kernel.diag(X_test) - np.einsum("ji,ji->i", K_star.T, A)
    var_ref += np.einsum("ji,jk,ki->i", A, Sigma, A)
    mean, var = clf.latent_mean_and_variance(X_test)
    np.testing.assert_allclose(mean, mean_ref, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(var, var_ref, rtol=1e-8)
    np.testing.assert_allclose(clf.predict_var(X_test), var_ref, rtol=1e-8)
    # P(y_* = 1) = integral of Phi(f) N(f | mean, var) (R&W eq. 3.25), by quadrature.
    p_ref = [
        quad(lambda f, m=m, s=s: norm.cdf(f) * norm.pdf(f, m, s), m - 12 * s, m + 12 * s)[0]
        for m, s in zip(mean_ref, np.sqrt(var_ref), strict=True)
    ]
    proba = clf.predict_proba(X_test)
    np.testing.assert_allclose(proba[:, 1], p_ref, rtol=1e-7)
    np.testing.assert_allclose(proba.sum(axis=1), 1.0)
    np.testing.assert_array_equal(clf.predict(X_test), (np.asarray(p_ref) > 0.5).astype(int))


def test_weak_signal_agrees_with_laplace():
    # With a small signal variance the posterior is nearly Gaussian: EP and Laplace (same
    # probit likelihood) must give nearly the same latent predictions.
    X, y = _data(n=40, seed=3)
    kernel = C(0.05) * RBF(1.0)
    clf = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10).fit(X, y)
    K = kernel(X)
    yy = np.where(y == 1, 1.0, -1.0)
    f, grad, W, _ = _laplace_probit(K, yy)
    X_test = np.random.default_rng(4).uniform(-2, 2, size=(10, 2))
    mean_l, var_l = _laplace_predict(K, kernel(X_test, X), kernel.diag(X_test), f, grad, W)
    mean, var = clf.latent_mean_and_variance(X_test)
    np.testing.assert_allclose(mean, mean_l, rtol=0.02, atol=1e-3)
    np.testing.assert_allclose(var, var_l, rtol=0.005)


@pytest.mark.parametrize("signal, seed", [(0.5, 0), (3.0, 1), (20.0, 2), (100.0, 3)])
def test_ep_evidence_not_below_laplace(signal, seed):
    # Laplace underestimates the probit marginal likelihood (Kuss & Rasmussen, JMLR 2005).
    X, y = _data(n=40, seed=seed)
    kernel = C(signal) * RBF(0.7)
    clf = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10).fit(X, y)
    _, _, _, laplace = _laplace_probit(kernel(X), np.where(y == 1, 1.0, -1.0))
    assert clf.log_marginal_likelihood_value_ >= laplace - 1e-6 * abs(laplace)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_restarts_never_worse_than_single_start(seed):
    X, y = _data(n=30, seed=seed, noise=0.8)
    kernel = C(1.0, (1e-2, 1e2)) * RBF(1.0, (1e-2, 1e2))
    single = EPGaussianProcessClassifier(kernel).fit(X, y)
    multi = EPGaussianProcessClassifier(kernel, n_restarts_optimizer=3, random_state=seed)
    multi.fit(X, y)
    lml_single = single.log_marginal_likelihood_value_
    assert multi.log_marginal_likelihood_value_ >= lml_single - 1e-8 * abs(lml_single)


def _recording_optimizer(starts):
    """An optimiser that stays at its starting point and appends each start to ``starts``."""

    def optimizer(obj_func, initial_theta, bounds):
        starts.append(np.array(initial_theta))
        return initial_theta, obj_func(initial_theta, eval_gradient=False)

    return optimizer


def test_restart_starts_are_drawn_in_log_space_within_bounds():
    X, y = _data(n=20)
    starts = []
    optimizer = _recording_optimizer(starts)
    kernel = C(1.0, (1e-3, 1e3)) * RBF(1.0, (1e-3, 1e3))
    clf = EPGaussianProcessClassifier(
        kernel, optimizer=optimizer, n_restarts_optimizer=40, random_state=0
    ).fit(X, y)
    starts = np.array(starts)
    np.testing.assert_array_equal(starts[0], kernel.theta)
    bounds = clf.kernel_.bounds
    assert np.all(starts >= bounds[:, 0]) and np.all(starts <= bounds[:, 1])
    # Uniform in log space over [-6.9, 6.9]: both halves are visited.
    assert np.all((starts[1:] < 0).sum(axis=0) >= 5)
    assert np.all((starts[1:] > 0).sum(axis=0) >= 5)
    # The kept hyperparameters are the best of the runs.
    values = [clf.log_marginal_likelihood(theta) for theta in starts]
    np.testing.assert_allclose(clf.log_marginal_likelihood_value_, max(values), rtol=1e-6)


def test_optimizer_none_keeps_hyperparameters():
    X, y = _data(n=20)
    kernel = C(3.0) * RBF(0.5)
    clf = EPGaussianProcessClassifier(kernel, optimizer=None).fit(X, y)
    np.testing.assert_array_equal(clf.kernel_.theta, kernel.theta)
    lml = clf.log_marginal_likelihood(kernel.theta)
    np.testing.assert_allclose(lml, clf.log_marginal_likelihood_value_, rtol=1e-8)


def test_learning_raises_the_evidence_and_gradient_vanishes():
    X, y = _data(n=40, seed=5)
    clf = EPGaussianProcessClassifier().fit(X, y)
    start = clf.log_marginal_likelihood(np.zeros(2))  # the default kernel's initial theta
    assert clf.log_marginal_likelihood_value_ > start
    lml, grad = clf.log_marginal_likelihood(clf.kernel_.theta, eval_gradient=True)
    bounds = clf.kernel_.bounds
    theta = clf.kernel_.theta
    interior = (theta > bounds[:, 0] + 1e-3) & (theta < bounds[:, 1] - 1e-3)
    assert np.all(np.abs(grad[interior]) < 1e-3 * max(1.0, abs(lml)))


def test_log_marginal_likelihood_gradient_matches_finite_differences():
    X, y = _data(n=25, seed=6)
    clf = EPGaussianProcessClassifier(C(2.0) * RBF([0.7, 1.2]), optimizer=None, tol=1e-12)
    clf.fit(X, y)
    theta = clf.kernel_.theta + 0.1
    _, grad = clf.log_marginal_likelihood(theta, eval_gradient=True)
    h = 1e-5
    fd = [
        (clf.log_marginal_likelihood(theta + h * e) - clf.log_marginal_likelihood(theta - h * e))
        / (2 * h)
        for e in np.eye(len(theta))
    ]
    np.testing.assert_allclose(grad, fd, rtol=1e-5)
    # clone_kernel=False sets kernel_.theta in place.
    clf.log_marginal_likelihood(theta, clone_kernel=False)
    np.testing.assert_allclose(clf.kernel_.theta, theta, rtol=1e-14)


def test_log_marginal_likelihood_gradient_needs_theta():
    X, y = _data(n=10)
    clf = EPGaussianProcessClassifier(optimizer=None).fit(X, y)
    with pytest.raises(ValueError, match="theta"):
        clf.log_marginal_likelihood(eval_gradient=True)


def test_sequential_and_parallel_estimators_agree():
    X, y = _data(n=30, seed=7)
    kernel = C(4.0) * RBF(0.6)
    par = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10).fit(X, y)
    seq = EPGaussianProcessClassifier(
        kernel, optimizer=None, ep_update="sequential", damping=0.0, tol=1e-10
    ).fit(X, y)
    np.testing.assert_allclose(par.site_precision_, seq.site_precision_, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(par.site_nu_, seq.site_nu_, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(
        par.log_marginal_likelihood_value_, seq.log_marginal_likelihood_value_, rtol=1e-8
    )


def test_convergence_warning_at_max_iter():
    X, y = _data(n=30)
    clf = EPGaussianProcessClassifier(optimizer=None, max_iter=2)
    with pytest.warns(ConvergenceWarning, match="max_iter=2.*Increase max_iter"):
        clf.fit(X, y)
    assert clf.n_iter_ == 2


def test_no_warning_when_converged():
    X, y = _data(n=30)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        clf = EPGaussianProcessClassifier().fit(X, y)
    assert 1 <= clf.n_iter_ < clf.max_iter


@pytest.mark.parametrize("labels", [(0, 1), (-1, 1), (3, 7), ("free", "occupied"), (False, True)])
def test_any_two_labels(labels):
    X, y = _data(n=30)
    ref = EPGaussianProcessClassifier(optimizer=None).fit(X, y)
    y_lab = np.asarray(labels, dtype=object if isinstance(labels[0], str) else None)[y]
    clf = EPGaussianProcessClassifier(optimizer=None).fit(X, y_lab)
    assert list(clf.classes_) == sorted(labels)
    np.testing.assert_allclose(clf.predict_proba(X), ref.predict_proba(X))
    np.testing.assert_array_equal(clf.predict(X), np.asarray(labels)[ref.predict(X)])


def test_one_class_raises():
    X, _ = _data(n=10)
    with pytest.raises(ValueError, match="one class"):
        EPGaussianProcessClassifier().fit(X, np.ones(10))


def _data3(n=45, seed=0, n_classes=3):
    """Classes by bands of a smooth function, with some label noise."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, size=(n, 2))
    f = np.sin(1.5 * X[:, 0]) + 0.5 * X[:, 1] + 0.2 * rng.standard_normal(n)
    edges = np.quantile(f, np.linspace(0, 1, n_classes + 1)[1:-1])
    return X, np.digitize(f, edges)


def test_one_vs_rest_matches_binary_problems_fitted_by_hand():
    X, y = _data3()
    labels = np.array(["a", "b", "c"])[y]
    Q = np.random.default_rng(1).uniform(-2.5, 2.5, size=(20, 2))
    clf = EPGaussianProcessClassifier(random_state=0).fit(X, labels)
    assert clf.n_classes_ == 3 and list(clf.classes_) == ["a", "b", "c"]
    assert isinstance(clf.base_estimator_, OneVsRestClassifier)
    by_hand = [EPGaussianProcessClassifier(random_state=0).fit(X, y == k) for k in range(3)]
    positive = np.column_stack([b.predict_proba(Q)[:, 1] for b in by_hand])
    proba = clf.predict_proba(Q)
    np.testing.assert_allclose(proba, positive / positive.sum(axis=1, keepdims=True))
    np.testing.assert_allclose(proba.sum(axis=1), 1.0)
    np.testing.assert_array_equal(clf.predict(Q), clf.classes_[np.argmax(positive, axis=1)])
    # kernel_ and the evidence are those of the binary classifiers, as in scikit-learn.
    assert isinstance(clf.kernel_, CompoundKernel)
    np.testing.assert_allclose(
        clf.kernel_.theta, np.concatenate([b.kernel_.theta for b in by_hand])
    )
    lml = np.mean([b.log_marginal_likelihood_value_ for b in by_hand])
    assert clf.log_marginal_likelihood_value_ == pytest.approx(lml)
    np.testing.assert_array_equal(clf.n_iter_, [b.n_iter_ for b in by_hand])
    for estimator in clf.base_estimator_.estimators_:
        assert isinstance(estimator, EPGaussianProcessClassifier)
        assert estimator.n_classes_ == 2


def test_one_vs_one_votes_of_pairwise_problems_fitted_by_hand():
    X, y = _data3(n=60, n_classes=4)
    kernel = C(4.0) * RBF(0.8)
    clf = EPGaussianProcessClassifier(kernel, optimizer=None, multi_class="one_vs_one")
    clf.fit(X, y)
    assert isinstance(clf.base_estimator_, OneVsOneClassifier)
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    assert len(clf.base_estimator_.estimators_) == len(pairs) == 6
    Q = np.random.default_rng(2).uniform(-2, 2, size=(30, 2))
    votes = np.zeros((Q.shape[0], 4))
    for i, j in pairs:
        rows = (y == i) | (y == j)
        binary = EPGaussianProcessClassifier(kernel, optimizer=None).fit(X[rows], y[rows])
        p_j = binary.predict_proba(Q)[:, 1]
        votes[np.arange(Q.shape[0]), np.where(p_j > 0.5, j, i)] += 1
    # Without a tie the class with most votes wins.
    top = np.sort(votes, axis=1)
    clear = top[:, -1] > top[:, -2]
    assert clear.sum() >= 20
    np.testing.assert_array_equal(clf.predict(Q)[clear], np.argmax(votes[clear], axis=1))
    with pytest.raises(ValueError, match="one_vs_one multi-class mode does not support"):
        clf.predict_proba(Q)
    # The compound kernel has one part per pair (not per class): each gets its own.
    n_dims = clf.base_estimator_.estimators_[0].kernel_.n_dims
    assert clf.kernel_.theta.shape == (6 * n_dims,)
    assert clf.log_marginal_likelihood(clf.kernel_.theta) == pytest.approx(
        clf.log_marginal_likelihood_value_
    )


def test_multi_class_log_marginal_likelihood():
    X, y = _data3()
    kernel = C(2.0) * RBF(0.7)
    clf = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10).fit(X, y)
    estimators = clf.base_estimator_.estimators_
    # One kernel's theta goes to every binary classifier; the compound theta is split.
    theta = kernel.theta + 0.3
    expected = np.mean([e.log_marginal_likelihood(theta) for e in estimators])
    assert clf.log_marginal_likelihood(theta) == pytest.approx(expected, rel=1e-10)
    thetas = [kernel.theta + d for d in (0.1, -0.2, 0.4)]
    expected = np.mean(
        [e.log_marginal_likelihood(t) for e, t in zip(estimators, thetas, strict=True)]
    )
    value = clf.log_marginal_likelihood(np.concatenate(thetas))
    assert value == pytest.approx(expected, rel=1e-10)
    assert clf.log_marginal_likelihood(clf.kernel_.theta) == pytest.approx(
        clf.log_marginal_likelihood_value_, rel=1e-8
    )
    with pytest.raises(NotImplementedError, match="multi-class"):
        clf.log_marginal_likelihood(theta, eval_gradient=True)
    with pytest.raises(ValueError, match="Shape of theta must be either 2 or 6"):
        clf.log_marginal_likelihood(np.zeros(3))
    # clone_kernel=False sets the binary kernels, and kernel_ with them, in place.
    clf.log_marginal_likelihood(np.concatenate(thetas), clone_kernel=False)
    np.testing.assert_allclose(clf.kernel_.theta, np.concatenate(thetas))
    np.testing.assert_allclose(estimators[2].kernel_.theta, thetas[2])


def test_multi_class_latent_queries_raise():
    X, y = _data3()
    clf = EPGaussianProcessClassifier(optimizer=None).fit(X, y)
    match = "only supported for binary classification, received 3 classes"
    with pytest.raises(ValueError, match=match):
        clf.latent_mean_and_variance(X)
    with pytest.raises(ValueError, match=match):
        clf.predict_var(X)


def test_compound_kernel_raises():
    X, y = _data(n=10)
    with pytest.raises(ValueError, match="kernel cannot be a CompoundKernel"):
        EPGaussianProcessClassifier(CompoundKernel([RBF(), RBF()])).fit(X, y)


def test_binary_base_estimator_is_the_classifier_and_refits_switch_kinds():
    X, y = _data3(n=30)
    clf = EPGaussianProcessClassifier(optimizer=None)
    with pytest.raises(NotFittedError):
        getattr(clf, "base_estimator_")  # noqa: B009
    clf.fit(X, y == 0)
    assert clf.base_estimator_ is clf and clf.n_classes_ == 2
    clf.fit(X, y)
    assert isinstance(clf.base_estimator_, OneVsRestClassifier)
    # No stale binary state on a multi-class model, nor the reverse.
    assert not hasattr(clf, "X_train_") and not hasattr(clf, "site_nu_")
    clf.fit(X, y == 0)
    assert clf.base_estimator_ is clf and not hasattr(clf, "_multi_class_estimator")
    assert clf.predict_proba(X).shape == (30, 2)


def test_multi_class_tags():
    tags = EPGaussianProcessClassifier().__sklearn_tags__()
    assert tags.classifier_tags.multi_class
    assert not tags.classifier_tags.multi_label


def test_hyperparameter_at_its_bound_warns_as_scikit_learn():
    X, y = _data(n=30)
    # A tight upper bound on the length scale: the evidence wants more.
    kernel = C(1.0, "fixed") * RBF(1e-3, (1e-5, 1e-3))
    message = (
        "The optimal value found for dimension 0 of parameter k2__length_scale is close "
        "to the specified upper bound 0.001. Increasing the bound and calling fit again "
        "may find a better value."
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        EPGaussianProcessClassifier(kernel).fit(X, y)
    assert [str(w.message) for w in caught if w.category is ConvergenceWarning] == [message]
    # Nothing learnt, nothing to warn about.
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        EPGaussianProcessClassifier(kernel, optimizer=None).fit(X, y)


def test_bound_warning_tolerance():
    from skoccmap.classifier import _warn_at_bounds

    kernel = C(1.0, (1e-2, 1e2)) * RBF([1.0, 1.0], (1e-2, 1e2))
    # Within 1e-3 of a bound in log space (L-BFGS-B stops about there on flat evidence).
    kernel.theta = np.log([1e2, 1.0, 1e-2]) + [-5e-4, 0.0, 5e-4]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _warn_at_bounds(kernel)
    messages = [str(w.message) for w in caught]
    assert len(messages) == 2
    assert "k1__constant_value is close to the specified upper bound 100.0" in messages[0]
    assert (
        "dimension 1 of parameter k2__length_scale is close to the specified lower"
        in (messages[1])
    )
    kernel.theta = np.log([1e2, 1.0, 1e-2]) + [-1e-2, 0.0, 1e-2]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _warn_at_bounds(kernel)


def test_log_marginal_likelihood_is_numpy_float64():
    # As in scikit-learn: arithmetic with float32 scalars then stays in float64.
    X, y = _data(n=20)
    clf = EPGaussianProcessClassifier(optimizer=None).fit(X, y)
    for value in (clf.log_marginal_likelihood_value_, clf.log_marginal_likelihood([0.0, 0.0])):
        assert isinstance(value, np.float64)
        assert (value - np.finfo(np.float32).eps).dtype == np.float64


@pytest.mark.parametrize(
    "X, y, match",
    [
        (np.array([[0.0, np.nan], [1.0, 1.0]]), [0, 1], "NaN"),
        (np.zeros((0, 2)), [], "0 sample"),
        (np.zeros((3, 2)), [0, 1], "inconsistent numbers of samples"),
        (np.zeros(4), [0, 1, 0, 1], "2D array"),
    ],
)
def test_bad_training_input(X, y, match):
    with pytest.raises(ValueError, match=match):
        EPGaussianProcessClassifier().fit(X, y)


@pytest.mark.parametrize(
    "kernel, match",
    [
        (RBF(-1.0), "kernel's length_scale must be positive and finite to be learned, got -1.0"),
        (C(1.0) * RBF([1.0, np.nan]), r"k2__length_scale must be positive.*\[1.0, nan\]"),
        (C(-2.0) * RBF(1.0), "k1__constant_value must be positive and finite"),
        (C(0.0) * RBF(1.0), "k1__constant_value must be positive and finite.*got 0.0"),
        (RBF(1.0, (5.0, 1.0)), r"bounds of the kernel's length_scale .* got \[5.0, 1.0\]"),
        (RBF(1.0, (0.0, 1.0)), r"0 < low < high \(high may be inf\), got \[0.0, 1.0\]"),
        (RBF(1.0, (1.0, 1.0)), r"0 < low < high \(high may be inf\), got \[1.0, 1.0\]"),
        (RBF(1.0, (np.nan, 2.0)), r"0 < low < high \(high may be inf\), got \[nan, 2.0\]"),
    ],
)
def test_hyperparameters_that_cannot_be_learned_are_named(kernel, match):
    X, y = _data(n=20)
    with warnings.catch_warnings():
        # Nothing is computed from them first: not even their logarithms.
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(ValueError, match=match):
            EPGaussianProcessClassifier(kernel).fit(X, y)
    if "bounds" in match or "low" in match:
        # Bounds matter only to the optimiser: kept fixed, the kernel is used as it is.
        EPGaussianProcessClassifier(kernel, optimizer=None).fit(X, y)


def test_n_jobs_zero_is_refused_before_any_work():
    X, y = _data(n=20)
    with pytest.raises(ValueError, match="'n_jobs' parameter"):
        EPGaussianProcessClassifier(n_jobs=0).fit(X, y)
    EPGaussianProcessClassifier(n_jobs=-1, optimizer=None).fit(X, y)


def test_bad_query_input():
    X, y = _data(n=20)
    clf = EPGaussianProcessClassifier(optimizer=None).fit(X, y)
    with pytest.raises(ValueError, match="features"):
        clf.latent_mean_and_variance(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="NaN"):
        clf.predict_proba([[0.0, np.nan]])


def test_variance_positive_and_bounded_by_prior():
    X, y = _data(n=30)
    clf = EPGaussianProcessClassifier(C(50.0) * RBF(0.3), optimizer=None).fit(X, y)
    Q = np.vstack([X, np.random.default_rng(0).uniform(-6, 6, size=(200, 2))])
    mean, var = clf.latent_mean_and_variance(Q)
    prior = clf.kernel_.diag(Q)
    assert np.all(var > 0) and np.all(var <= prior * (1 + 1e-12))
    far = np.array([[100.0, 100.0]])
    np.testing.assert_allclose(clf.predict_var(far), clf.kernel_.diag(far))
    np.testing.assert_allclose(clf.predict_proba(far), [[0.5, 0.5]], atol=1e-12)


def test_large_signal_variance_with_label_noise():
    rng = np.random.default_rng(8)
    X = rng.uniform(0, 5, size=(100, 1))
    y = (X[:, 0] > 2.5).astype(int)
    y[rng.choice(100, size=15, replace=False)] ^= 1
    clf = EPGaussianProcessClassifier(C(1e3) * RBF(0.2), optimizer=None).fit(X, y)
    assert np.all(clf.site_precision_ >= 0) and np.isfinite(clf.log_marginal_likelihood_value_)
    mean, var = clf.latent_mean_and_variance(np.linspace(-1, 6, 50)[:, None])
    assert np.all(np.isfinite(mean)) and np.all(var > 0)
    learned = EPGaussianProcessClassifier(n_restarts_optimizer=2, random_state=0).fit(X, y)
    assert np.isfinite(learned.log_marginal_likelihood_value_)


def test_shared_hyperparameters_clone():
    # The mixture of experts clones a fitted expert with its kernel_ and optimizer=None.
    X, y = _data(n=30)
    first = EPGaussianProcessClassifier().fit(X, y)
    expert = clone(first).set_params(kernel=first.kernel_, optimizer=None).fit(X, y)
    np.testing.assert_array_equal(expert.kernel_.theta, first.kernel_.theta)
    np.testing.assert_allclose(expert.predict_proba(X), first.predict_proba(X), rtol=1e-5)


def test_predictions_in_blocks_equal_one_block(monkeypatch):
    import skoccmap.classifier as module

    X, y = _data(n=30)
    clf = EPGaussianProcessClassifier(optimizer=None).fit(X, y)
    Q = np.random.default_rng(1).uniform(-2, 2, size=(50, 2))
    mean, var = clf.latent_mean_and_variance(Q)
    monkeypatch.setattr(module, "_PREDICT_BLOCK_ELEMENTS", 30 * 7)
    mean_b, var_b = clf.latent_mean_and_variance(Q)
    np.testing.assert_allclose(mean_b, mean, rtol=1e-12)
    np.testing.assert_allclose(var_b, var, rtol=1e-12)


def test_no_decision_function():
    assert not hasattr(EPGaussianProcessClassifier(), "decision_function")


def test_integral_kernel_works_unchanged():
    kernels = pytest.importorskip("skoccmap.kernels")
    rng = np.random.default_rng(9)
    starts = rng.uniform(0, 4, size=(30, 2))
    ends = starts + rng.uniform(-0.5, 0.5, size=(30, 2))
    X = np.hstack([starts, ends])
    y = (X[:, 0] + X[:, 2] > 4).astype(int)
    kernel = C(1.0) * kernels.IntegralKernel(1.0)
    clf = EPGaussianProcessClassifier(kernel, tol=1e-12).fit(X, y)
    mean, var = clf.latent_mean_and_variance(X)
    assert np.all(var > 0) and np.all(np.isfinite(mean))
    assert clf.score(X, y) > 0.8
    _, grad = clf.log_marginal_likelihood(clf.kernel_.theta + 0.2, eval_gradient=True)
    h = 1e-5
    theta = clf.kernel_.theta + 0.2
    fd = [
        (clf.log_marginal_likelihood(theta + h * e) - clf.log_marginal_likelihood(theta - h * e))
        / (2 * h)
        for e in np.eye(len(theta))
    ]
    np.testing.assert_allclose(grad, fd, rtol=1e-4)


def test_separable_data_learns_without_a_spurious_warning():
    # Setosa against the rest is separable: the evidence keeps rising with the signal
    # variance, the optimum lies at its bound, and there L-BFGS-B's line search stopped
    # "abnormally" (scikit-learn's check_positive_only_tag_during_fit saw the warning).
    # The one warning due is that the signal variance ended at its bound.
    from sklearn.datasets import load_iris

    X, y = load_iris(return_X_y=True)
    X, y = X - X.mean(), (y > 0).astype(int)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = EPGaussianProcessClassifier().fit(X, y)
    at_bound = [w for w in caught if w.category is ConvergenceWarning]
    assert len(at_bound) == 1
    assert str(at_bound[0].message).startswith(
        "The optimal value found for dimension 0 of parameter k1__constant_value is close "
        "to the specified upper bound 1000.0."
    )
    # The warning names the line that called fit, not a line inside a decorator.
    assert at_bound[0].filename == __file__
    assert model.kernel_.k1.constant_value == pytest.approx(1e3)
    # So do the binary problems' warnings of a multi-class fit, inside scikit-learn's
    # one-vs-rest meta-estimator.
    X, y = load_iris(return_X_y=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        EPGaussianProcessClassifier().fit(X - X.mean(), y)
    at_bound = [w for w in caught if w.category is ConvergenceWarning]
    assert at_bound and {w.filename for w in at_bound} == {__file__}


def test_an_infinite_upper_bound_can_be_learned_within():
    X, y = _data(n=30)
    clf = EPGaussianProcessClassifier(C(1.0, (1e-2, np.inf)) * RBF(1.0, (1e-2, 1e2))).fit(X, y)
    assert np.all(np.isfinite(clf.kernel_.theta))


def test_stationarity_ignores_gradients_pressing_on_bounds():
    from scipy.optimize import OptimizeResult

    bounds = np.array([[-7.0, 7.0], [-7.0, 7.0]])

    def result(x, jac):
        return OptimizeResult(x=np.array(x), jac=np.array(jac), fun=4.5, success=False)

    assert _is_stationary(result([7.0, 1.0], [-0.03, 1e-5]), bounds)
    assert _is_stationary(result([-7.0, 1.0], [0.03, 1e-5]), bounds)
    # Pointing into the box at the bound, or a free gradient: not stationary.
    assert not _is_stationary(result([7.0, 1.0], [0.03, 1e-5]), bounds)
    assert not _is_stationary(result([1.0, 1.0], [0.0, 0.01]), bounds)


def test_evaluated_once_answers_nearby_points_from_the_first_evaluation():
    calls = []

    def obj(theta, eval_gradient=True):
        calls.append(theta.copy())
        return float(len(calls)), np.full_like(theta, float(len(calls)))

    once = _evaluated_once(obj)
    first = once(np.array([0.5, -1.0]))
    # Within the resolution (max norm): the first evaluation, not a new one.
    again = once(np.array([0.5 + 0.9 * _THETA_RESOLUTION, -1.0 - 0.9 * _THETA_RESOLUTION]))
    assert len(calls) == 1 and again[0] == first[0] == 1.0
    assert once(np.array([0.5, -1.0]), eval_gradient=False) == 1.0
    # Beyond it in one coordinate: evaluated.
    farther = once(np.array([0.5, -1.0 + 2.0 * _THETA_RESOLUTION]))
    assert len(calls) == 2 and farther[0] == 2.0


def _floored_objective(calls):
    """A smooth minimum whose value is known only to 1e-7 (values rounded, with a jitter
    below that), and whose gradient is off by 3e-4: EP's summed evidence near its optimum."""

    def obj(theta, eval_gradient=True):
        calls.append(np.array(theta, copy=True))
        x = theta[0] - 0.5
        f = 1000.0 + 300.0 * x * x + 200.0 * x**4 + np.exp(x)
        f = np.round(f / 1e-7) * 1e-7 + 1e-7 * np.sin(1e9 * theta[0])
        return f, np.array([600.0 * x + 800.0 * x**3 + np.exp(x) + 3e-4])

    return obj


def test_lbfgs_does_not_re_evaluate_a_point_below_the_evidence_noise():
    """On such an objective plain L-BFGS-B spends most of its evaluations within 1e-6 of
    the optimum (41 instead of 8 with scipy 1.17); each costs an EP run per expert."""
    bounds = np.array([[-11.5, 11.5]])
    calls = []
    objective = _floored_objective(calls)
    theta, value = _minimize_in_bounds("fmin_l_bfgs_b", objective, np.zeros(1), bounds)
    points = np.array(calls)
    gaps = np.abs(points[:, None, 0] - points[None, :, 0]) + np.eye(len(points))
    assert gaps.min() > _THETA_RESOLUTION
    assert len(calls) <= 12
    # The minimiser of the smooth part, where its gradient (with the offset) vanishes.
    from scipy.optimize import brentq

    x_star = brentq(lambda x: 600.0 * x + 800.0 * x**3 + np.exp(x) + 3e-4, -0.1, 0.1)
    assert theta[0] == pytest.approx(0.5 + x_star, abs=1e-5)
    assert np.isfinite(value)


def test_lbfgs_first_step_moves_at_most_one_log_unit():
    """Summed EP evidences have gradients in the hundreds: unscaled, L-BFGS-B's first step
    (the negative gradient) lands on a bound of the length scale."""
    calls = []

    def obj(theta, eval_gradient=True):
        calls.append(np.array(theta, copy=True))
        x = theta - np.array([0.5, -0.3])
        return 400.0 * np.sum(x**2) + 30.0 * np.sum(x**4), 800.0 * x + 120.0 * x**3

    bounds = np.array([[-11.5, 11.5], [-11.5, 11.5]])
    theta, value = _minimize_in_bounds("fmin_l_bfgs_b", obj, np.zeros(2), bounds)
    first_move = calls[1] - calls[0]
    assert np.array_equal(calls[0], np.zeros(2))
    assert np.max(np.abs(first_move)) <= 1.0 + 1e-12
    # The minimiser and the value are those of the unscaled objective.
    np.testing.assert_allclose(theta, [0.5, -0.3], atol=1e-5)
    assert value == pytest.approx(0.0, abs=1e-6)


def _site_log_normalisers(K, y, tau, nu):
    """log Z~_i of EP's probit sites given their cavities in the posterior of ``K`` and all
    sites (R&W eqs. 3.56, 3.58): dense, every site with tau > 0."""
    Sigma = np.linalg.inv(np.linalg.inv(K) + np.diag(tau))
    mu, s2 = Sigma @ nu, np.diag(Sigma)
    cavity_var = 1.0 / (1.0 / s2 - tau)
    cavity_mean = cavity_var * (mu / s2 - nu)
    v = cavity_var + 1.0 / tau
    log_Z_hat = norm.logcdf(y * cavity_mean / np.sqrt(1.0 + cavity_var))
    return log_Z_hat + 0.5 * np.log(2 * np.pi * v) + (cavity_mean - nu / tau) ** 2 / (2 * v)


def _dense_ep_evidence(K, tau, nu, log_Z):
    """log of int N(f | 0, K) prod_i Z~_i N(f_i | nu_i / tau_i, 1 / tau_i) df."""
    S = K + np.diag(1.0 / tau)
    r = nu / tau
    _, logdet = np.linalg.slogdet(2 * np.pi * S)
    return log_Z.sum() - 0.5 * logdet - 0.5 * r @ np.linalg.solve(S, r)


def _holding(clf, X, y, tau, nu, n_held):
    """``clf`` fitted on ``X`` with the first ``n_held`` rows' sites held at ``tau``, ``nu``."""
    tau = np.r_[tau[:n_held], np.zeros(len(X) - n_held)]
    nu = np.r_[nu[:n_held], np.zeros(len(X) - n_held)]
    return clf._fit_warm_start(X, y, tau, nu, hold=np.arange(len(X)) < n_held)


def _first_rows_held(X, y, kernel, whole, n):
    """The first ``n`` rows fitted with every site held at the whole fit's fixed point."""
    clf = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10)
    return _holding(clf, X[:n], y[:n], whole.site_precision_, whole.site_nu_, n)


def _whole_fit():
    """Data, kernel and the fit of EP on all of them to a tight fixed point."""
    X, y = _data(n=60, seed=3)
    kernel = C(3.0) * RBF(0.8)
    return X, y, kernel, EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10).fit(X, y)


def test_held_sites_at_the_fixed_point_leave_the_others_there():
    # With the held rows' sites at the fixed point of EP on all rows, EP on the other
    # rows' sites alone must land on that fixed point's sites for them: the same posterior.
    X, y, kernel, whole = _whole_fit()
    held = _holding(
        EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10),
        X, y, whole.site_precision_, whole.site_nu_, 45,
    )  # fmt: skip
    np.testing.assert_array_equal(held.site_precision_[:45], whole.site_precision_[:45])
    np.testing.assert_allclose(held.site_precision_, whole.site_precision_, atol=1e-8)
    np.testing.assert_allclose(held.site_nu_, whole.site_nu_, atol=1e-8)
    queries = _data(n=30, seed=4)[0]
    np.testing.assert_allclose(held.predict_proba(queries), whole.predict_proba(queries))
    np.testing.assert_allclose(
        held.log_marginal_likelihood_value_, whole.log_marginal_likelihood_value_
    )


def test_held_sites_of_a_smaller_fit_move_the_map_towards_a_refit():
    X, y = _data(n=80, seed=5)
    kernel = C(3.0) * RBF(0.8)
    old = EPGaussianProcessClassifier(kernel, optimizer=None).fit(X[:60], y[:60])
    whole = EPGaussianProcessClassifier(kernel, optimizer=None).fit(X, y)
    held = _holding(
        EPGaussianProcessClassifier(kernel, optimizer=None),
        X, y, old.site_precision_, old.site_nu_, 60,
    )  # fmt: skip
    assert 0 < held.n_iter_ < whole.n_iter_
    queries = _data(n=50, seed=6)[0]
    gap_old = np.abs(old.predict_proba(queries) - whole.predict_proba(queries)).max()
    gap = np.abs(held.predict_proba(queries) - whole.predict_proba(queries)).max()
    # Held fixed, the old sites leave a gap to the refit, but a small one.
    assert gap < 0.25 * gap_old


def test_hold_is_ignored_where_the_kernel_is_learned():
    X, y = _data(n=40)
    clf = EPGaussianProcessClassifier(C(1.0) * RBF(1.0), random_state=0)
    held = clone(clf)._fit_warm_start(
        X, y, np.ones(40), np.zeros(40), hold=np.ones(40, dtype=bool)
    )
    plain = clone(clf).fit(X, y)
    np.testing.assert_allclose(held.site_precision_, plain.site_precision_, rtol=1e-4)


def test_absorbed_rows_land_on_the_fixed_point_of_the_whole_fit():
    X, y, kernel, whole = _whole_fit()
    # The first 45 rows' fit, its sites moved to the whole fit's fixed point.
    old = _first_rows_held(X, y, kernel, whole, 45)
    absorbed = old._absorbed(X[45:], y[45:])
    np.testing.assert_allclose(absorbed.site_precision_, whole.site_precision_, atol=1e-8)
    np.testing.assert_allclose(absorbed.site_nu_, whole.site_nu_, atol=1e-8)
    queries = _data(n=30, seed=4)[0]
    np.testing.assert_allclose(absorbed.predict_proba(queries), whole.predict_proba(queries))
    np.testing.assert_allclose(absorbed.predict_var(queries), whole.predict_var(queries))
    # The evidence is that of the held sites (their normalisers from the 45 rows' cavities)
    # times that of the new sites given them (their cavities in the posterior of all rows).
    K, yy = kernel(X), np.where(y == 1, 1.0, -1.0)
    log_Z = _site_log_normalisers(K, yy, whole.site_precision_, whole.site_nu_)
    np.testing.assert_allclose(  # the reference itself, on the whole fit
        whole.log_marginal_likelihood_value_,
        _dense_ep_evidence(K, whole.site_precision_, whole.site_nu_, log_Z),
        rtol=1e-9,
    )
    tau, nu = absorbed.site_precision_, absorbed.site_nu_
    log_Z = np.r_[
        _site_log_normalisers(K[:45, :45], yy[:45], tau[:45], nu[:45]),
        _site_log_normalisers(K, yy, tau, nu)[45:],
    ]
    np.testing.assert_allclose(
        absorbed.log_marginal_likelihood_value_, _dense_ep_evidence(K, tau, nu, log_Z), rtol=1e-9
    )
    np.testing.assert_array_equal(absorbed.X_train_, X)
    assert old.X_train_.shape[0] == 45  # the original is unchanged


def test_absorbed_refuses_unknown_labels_and_multi_class():
    X, y = _data(n=30)
    clf = EPGaussianProcessClassifier(C(1.0) * RBF(1.0), optimizer=None).fit(X, y)
    with pytest.raises(ValueError, match="not in classes_"):
        clf._absorbed(X[:2], [2, 2])
    multi = EPGaussianProcessClassifier(C(1.0) * RBF(1.0), optimizer=None)
    multi.fit(X, np.arange(30) % 3)
    with pytest.raises(ValueError, match="binary"):
        multi._absorbed(X[:2], [0, 0])


@pytest.mark.parametrize("n", [0, 1, 2, 7, 130])
def test_packed_factor_unpacks_to_its_lower_triangle_with_zeros_above(n):
    # The factor an expert keeps is packed (half the memory) and unpacked at every
    # prediction; the upper triangle must be exact zeros, not left-over memory.
    from skoccmap.classifier import _from_lower_triangle, _lower_triangle

    rng = np.random.default_rng(n)
    lower = np.tril(rng.normal(size=(n, n)))
    full = lower + np.triu(rng.normal(size=(n, n)), 1)  # garbage above, not packed
    for _ in range(3):  # fresh arrays each time: no memory reused by chance
        unpacked = _from_lower_triangle(_lower_triangle(full))
        assert unpacked.flags.c_contiguous
        np.testing.assert_array_equal(unpacked, lower)
        symmetric = _from_lower_triangle(_lower_triangle(full), symmetric=True)
        np.testing.assert_array_equal(symmetric, lower + np.tril(lower, -1).T)


def test_a_fitted_classifier_pickles_to_less_than_one_square_factor():
    # Predictions need the n x n lower Cholesky factor of B; kept as its lower triangle
    # (with the n-vectors of the fit), the whole classifier is smaller than the square.
    X, y = _data(n=150)
    clf = EPGaussianProcessClassifier(C(1.0) * RBF(1.0), optimizer=None).fit(X, y)
    assert len(pickle.dumps(clf)) < 8 * 150 * 150
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(clf)).predict(X), clf.predict(X))


def test_a_refused_one_class_fit_leaves_no_classes_behind():
    X = np.linspace(0, 1, 6)[:, None]
    clf = EPGaussianProcessClassifier(optimizer=None)
    with pytest.raises(ValueError, match="two distinct labels"):
        clf._fit_one_class(X, np.ones(6), classes=[1])
    clf.fit(X, [0, 0, 0, 1, 1, 1])
    assert clf.classes_.tolist() == [0, 1]
    one = EPGaussianProcessClassifier(optimizer=None)._fit_one_class(X, np.ones(6), [0, 1])
    assert one.classes_.tolist() == [0, 1] and np.all(one.predict(X) == 1)


@pytest.mark.parametrize(
    "value, side, verb",
    [(1e-1, "lower bound 0.1", "Decreasing"), (1e1, "upper bound 10.0", "Increasing")],
)
def test_bound_warning_names_each_dimensions_own_bound(value, side, verb):
    from skoccmap.classifier import _warn_at_bounds

    kernel = RBF([1.0, 1.0], length_scale_bounds=[[1e-2, 1e2], [1e-1, 1e1]])
    kernel.theta = np.log([1.0, value])  # dimension 1 at one of its own bounds
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _warn_at_bounds(kernel)
    assert [str(w.message) for w in caught] == [
        "The optimal value found for dimension 1 of parameter length_scale is close to the "
        f"specified {side}. {verb} the bound and calling fit again may find a better value."
    ]


def test_lbfgs_returns_the_unscaled_minimum_value():
    # The objective is divided by its largest initial gradient component while minimising;
    # the value handed back (which restarts compare) must be the objective's own.
    def obj(theta, eval_gradient=True):
        x = theta - 0.5
        return 7.0 + 400.0 * np.sum(x**2), 800.0 * x

    bounds = np.array([[-11.5, 11.5]])
    theta, value = _minimize_in_bounds("fmin_l_bfgs_b", obj, np.zeros(1), bounds)
    np.testing.assert_allclose(theta, [0.5], atol=1e-5)
    assert value == pytest.approx(obj(theta)[0], rel=1e-12)
    assert value == pytest.approx(7.0, rel=1e-8)


def test_kernel_matrix_of_a_warm_start_is_ignored_when_hyperparameters_are_learned():
    # The matrix handed in is K(X, X) of the initial kernel: stale once the kernel is learnt.
    X, y = _data(n=30, seed=2, noise=0.8)
    kernel = C(1.0, (1e-2, 1e2)) * RBF(1.0, (1e-2, 1e2))
    plain = EPGaussianProcessClassifier(kernel, random_state=0).fit(X, y)
    warm = EPGaussianProcessClassifier(kernel, random_state=0)._fit_warm_start(
        X, y, kernel_matrix=kernel(X)
    )
    assert not np.allclose(warm.kernel_.theta, kernel.theta, atol=1e-2)
    np.testing.assert_allclose(warm.kernel_.theta, plain.kernel_.theta, rtol=1e-6, atol=1e-6)
    # The evidence stored is that of the learnt kernel, evaluated afresh.
    lml = warm.log_marginal_likelihood(warm.kernel_.theta)
    np.testing.assert_allclose(warm.log_marginal_likelihood_value_, lml, rtol=1e-6)
    np.testing.assert_allclose(warm.predict_proba(X), plain.predict_proba(X), atol=1e-6)


def test_held_and_free_sites_at_the_fixed_point_need_one_sweep():
    # Every row's sites at EP's fixed point on all rows, the first 45 held: the free rows'
    # starting sites (given in the latent) are their fixed point in the centred latent too,
    # so one sweep confirms them.
    X, y, kernel, whole = _whole_fit()
    held = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10)._fit_warm_start(
        X, y, whole.site_precision_, whole.site_nu_, hold=np.arange(len(X)) < 45
    )
    assert held.n_iter_ == 1
    np.testing.assert_allclose(held.site_nu_, whole.site_nu_, atol=1e-8)


def test_a_warm_start_that_does_not_converge_restarts_from_zero_sites():
    X, y = _data(n=40, seed=5)
    kernel = C(3.0) * RBF(0.8)
    cold = EPGaussianProcessClassifier(kernel, optimizer=None).fit(X, y)
    signs = np.where(y == 1, 1.0, -1.0)
    bad = (np.full(40, 1e3), -3e3 * signs)  # confident sites on the wrong side
    slow = EPGaussianProcessClassifier(kernel, optimizer=None, max_iter=1000)
    assert slow._fit_warm_start(X, y, *bad).n_iter_ > cold.n_iter_
    # With max_iter the sweeps of a cold start, the warm start fails and EP starts over.
    clf = EPGaussianProcessClassifier(kernel, optimizer=None, max_iter=cold.n_iter_)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        clf._fit_warm_start(X, y, *bad)
    assert clf.n_iter_ == cold.n_iter_
    np.testing.assert_allclose(clf.site_precision_, cold.site_precision_, rtol=1e-12)
    np.testing.assert_allclose(clf.site_nu_, cold.site_nu_, rtol=1e-12)


def test_final_ep_run_after_learning_starts_from_the_optimisers_sites():
    X, y = _data(n=40, seed=5)
    learned = EPGaussianProcessClassifier().fit(X, y)
    cold = EPGaussianProcessClassifier(learned.kernel_, optimizer=None).fit(X, y)
    # Warm from the sites of the optimiser's last evaluations: far fewer sweeps.
    assert 2 * learned.n_iter_ < cold.n_iter_
    np.testing.assert_allclose(learned.site_precision_, cold.site_precision_, atol=1e-4)
    np.testing.assert_allclose(learned.site_nu_, cold.site_nu_, atol=1e-4)


def test_restarts_need_finite_bounds():
    X, y = _data(n=20)
    kernel = C(1.0, (1e-2, np.inf)) * RBF(1.0, (1e-2, 1e2))
    with pytest.raises(ValueError, match="needs finite bounds"):
        EPGaussianProcessClassifier(kernel, n_restarts_optimizer=1, random_state=0).fit(X, y)


@pytest.mark.parametrize("n_restarts", [1, 2])
def test_each_restart_is_one_more_optimiser_run(n_restarts):
    X, y = _data(n=20)
    starts = []
    optimizer = _recording_optimizer(starts)
    EPGaussianProcessClassifier(
        optimizer=optimizer, n_restarts_optimizer=n_restarts, random_state=0
    ).fit(X, y)
    assert len(starts) == 1 + n_restarts


def test_restart_starts_cover_asymmetric_log_bounds():
    X, y = _data(n=20)
    starts = []
    optimizer = _recording_optimizer(starts)
    kernel = C(1.0, (1e-1, 1e3)) * RBF(1.0, (1e-3, 1e1))
    EPGaussianProcessClassifier(
        kernel, optimizer=optimizer, n_restarts_optimizer=40, random_state=0
    ).fit(X, y)
    low, high = kernel.bounds.T
    drawn = np.array(starts[1:])
    assert np.all(drawn >= low) and np.all(drawn <= high)
    # Uniform over each log range: 40 draws reach its outer sixths (miss: 0.83**40 < 1e-3).
    width = high - low
    assert np.all(drawn.min(axis=0) < low + width / 6)
    assert np.all(drawn.max(axis=0) > high - width / 6)


@pytest.mark.parametrize(
    "y, classes", [([0, 0, 0, 2, 2, 2], [0, 1]), ([1] * 6, [1, 1]), ([1] * 6, [1, 0])]
)
def test_one_class_fit_refuses_labels_outside_two_sorted_classes(y, classes):
    # Repeated or reversed classes would make the positive class (classes_[1]) wrong.
    X = np.linspace(0, 1, 6)[:, None]
    clf = EPGaussianProcessClassifier(optimizer=None)
    with pytest.raises(ValueError, match="two distinct labels in increasing order"):
        clf._fit_one_class(X, y, classes=classes)
    assert not hasattr(clf, "classes_")


@pytest.mark.parametrize(
    "params, name",
    [({"damping": 1.0}, "damping"), ({"tol": 0.0}, "tol"), ({"max_iter": 0}, "max_iter")],
)
def test_out_of_range_ep_parameters_are_refused(params, name):
    # damping 1 would never move a site, tol 0 never stop short of max_iter.
    X, y = _data(n=10)
    with pytest.raises(ValueError, match=f"'{name}' parameter"):
        EPGaussianProcessClassifier(optimizer=None, **params).fit(X, y)


def test_a_kernel_matrix_given_to_a_multi_class_fit_is_ignored_and_not_kept():
    # Only a binary fit takes the matrix; a multi-class fit ignores it, and the next fit of
    # the same estimator must not find it.
    X, y3 = _data3(n=30)
    kernel = C(1.0) * RBF(1.0)
    clf = EPGaussianProcessClassifier(kernel, optimizer=None)
    clf._fit_warm_start(X, y3, kernel_matrix=np.eye(30))
    plain = EPGaussianProcessClassifier(kernel, optimizer=None).fit(X, y3)
    np.testing.assert_array_equal(clf.predict_proba(X), plain.predict_proba(X))
    y = (y3 == 0).astype(int)
    clf.fit(X, y)
    fresh = EPGaussianProcessClassifier(kernel, optimizer=None).fit(X, y)
    np.testing.assert_array_equal(clf.site_precision_, fresh.site_precision_)
    assert clf.log_marginal_likelihood_value_ == fresh.log_marginal_likelihood_value_


def test_a_kernel_matrix_given_to_a_binary_fit_replaces_the_kernels_evaluation():
    # The caller's K(X, X) is the matrix EP runs on: twice the kernel's matrix gives the
    # sites and evidence of the kernel with twice the signal variance.
    X, y = _data(n=30)
    kernel = C(1.0) * RBF(0.8)
    given = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10)._fit_warm_start(
        X, y, kernel_matrix=2.0 * kernel(X)
    )
    doubled = EPGaussianProcessClassifier(C(2.0) * RBF(0.8), optimizer=None, tol=1e-10)
    doubled.fit(X, y)
    np.testing.assert_allclose(given.site_precision_, doubled.site_precision_, rtol=1e-10)
    np.testing.assert_allclose(given.site_nu_, doubled.site_nu_, rtol=1e-10)
    np.testing.assert_allclose(
        given.log_marginal_likelihood_value_, doubled.log_marginal_likelihood_value_, rtol=1e-10
    )


def test_stationarity_tolerance_is_absolute_below_a_unit_value():
    from scipy.optimize import OptimizeResult

    bounds = np.array([[-7.0, 7.0]])

    def result(jac, fun):
        return OptimizeResult(x=np.array([1.0]), jac=np.array([jac]), fun=fun, success=False)

    # Relative to max(1, |value|): 1e-4 at a value of 0.01, 1e-2 at a value of 100.
    assert _is_stationary(result(5e-5, 0.01), bounds)
    assert not _is_stationary(result(2e-4, 0.01), bounds)
    assert _is_stationary(result(5e-3, -100.0), bounds)
    assert not _is_stationary(result(2e-2, -100.0), bounds)


@pytest.mark.parametrize("copy_X_train", [True, False])
def test_copy_x_train(copy_X_train):
    X, y = _data(n=20)
    clf = EPGaussianProcessClassifier(optimizer=None, copy_X_train=copy_X_train).fit(X, y)
    assert (clf.X_train_ is X) is not copy_X_train
    np.testing.assert_array_equal(clf.X_train_, X)
    before = clf.predict_proba(X[:3].copy())
    X += 1.0  # the caller changes its array after fit
    after = clf.predict_proba(X[:3] - 1.0)
    if copy_X_train:
        np.testing.assert_array_equal(after, before)
    else:
        assert not np.allclose(after, before)


def test_multi_class_queries_are_validated_as_in_fit():
    pd = pytest.importorskip("pandas")
    X, y = _data3(n=30)
    frame = pd.DataFrame(X, columns=["x", "y"])
    clf = EPGaussianProcessClassifier(optimizer=None).fit(frame, y)
    renamed = pd.DataFrame(X[:4], columns=["a", "b"])
    for method in (clf.predict_proba, clf.predict):
        with pytest.raises(ValueError, match="feature names should match"):
            method(renamed)
        with pytest.raises(ValueError, match="NaN"):
            method(pd.DataFrame([[0.0, np.nan]], columns=["x", "y"]))


def test_random_state_draws_the_restart_starts():
    X, y = _data(n=20)

    def starts(random_state):
        drawn = []
        optimizer = _recording_optimizer(drawn)
        EPGaussianProcessClassifier(
            optimizer=optimizer, n_restarts_optimizer=3, random_state=random_state
        ).fit(X, y)
        return np.array(drawn[1:])

    np.testing.assert_array_equal(starts(0), starts(0))
    np.testing.assert_array_equal(starts(np.random.RandomState(0)), starts(0))
    assert not np.any(np.isclose(starts(0), starts(1)))


def test_default_kernel_is_the_documented_one():
    # ConstantKernel(1.0, (1e-3, 1e3)) * RBF(1.0, (1e-3, 1e3)): its start and its bounds.
    X, y = _data(n=20)
    clf = EPGaussianProcessClassifier(optimizer=None).fit(X, y)
    assert clf.kernel_ == C(1.0, (1e-3, 1e3)) * RBF(1.0, (1e-3, 1e3))
    learned = EPGaussianProcessClassifier().fit(X, y)
    np.testing.assert_allclose(learned.kernel_.bounds, np.log([[1e-3, 1e3], [1e-3, 1e3]]))


def test_an_infinite_hyperparameter_cannot_be_learned():
    X, y = _data(n=20)
    with pytest.raises(ValueError, match="constant_value must be positive and finite.*got inf"):
        EPGaussianProcessClassifier(C(np.inf) * RBF(1.0)).fit(X, y)


def test_an_infinite_objective_is_not_a_stationary_point():
    # Every evaluation failed (EP's LinAlgError gives +inf with a zero gradient).
    from scipy.optimize import OptimizeResult

    bounds = np.array([[-7.0, 7.0]])
    res = OptimizeResult(x=np.array([1.0]), jac=np.zeros(1), fun=np.inf, success=False)
    assert not _is_stationary(res, bounds)


def test_lbfgs_stopping_short_of_a_stationary_point_warns():
    # Past theta = 1 the value is flat but the gradient says it still falls: the line
    # search fails where the (unscaled) gradient, 0.5, is far from zero.
    def obj(theta, eval_gradient=True):
        if theta[0] < 1.0:
            return 1e4 * (1.0 - theta[0]), np.array([-1e4])
        return 0.0, np.array([-0.5])

    bounds = np.array([[-10.0, 10.0]])
    with pytest.warns(ConvergenceWarning, match="lbfgs failed to converge"):
        theta, value = _minimize_in_bounds("fmin_l_bfgs_b", obj, np.zeros(1), bounds)
    np.testing.assert_allclose(theta, [1.0], atol=1e-4)
    assert value == 0.0


def test_evaluated_once_keeps_its_own_copy_of_each_point():
    calls = []

    def obj(theta, eval_gradient=True):
        calls.append(theta.copy())
        return float(len(calls)), np.zeros_like(theta)

    once = _evaluated_once(obj)
    theta = np.array([0.5, -1.0])
    once(theta)
    theta += 1.0  # a caller that reuses its array for the next point
    assert once(theta)[0] == 2.0 and len(calls) == 2
    assert once(np.array([0.5, -1.0]))[0] == 1.0 and len(calls) == 2


def test_the_objective_is_infinite_where_ep_fails():
    # A fixed negative constant: the kernel matrix is indefinite at a small signal variance.
    X, y = _data(n=20)
    kernel = C(-0.5, "fixed") + C(10.0, (1e-5, 1e5)) * RBF(1.0, (1e-2, 1e2))
    kernel += WhiteKernel(1.0, "fixed")
    bad = np.log([1e-5, 1.0])
    assert np.linalg.eigvalsh(kernel.clone_with_theta(bad)(X)).min() < 0
    seen = []

    def optimizer(obj_func, initial_theta, bounds):
        seen.extend([obj_func(bad), obj_func(bad, eval_gradient=False)])
        return initial_theta, obj_func(initial_theta, eval_gradient=False)

    clf = EPGaussianProcessClassifier(kernel, optimizer=optimizer).fit(X, y)
    (value, grad), value_only = seen
    assert value == np.inf and value_only == np.inf
    np.testing.assert_array_equal(grad, [0.0, 0.0])
    np.testing.assert_array_equal(clf.kernel_.theta, kernel.theta)


def test_sites_with_a_negative_precision_predict_as_the_dense_posterior():
    # Held sites may have a negative precision (a proper posterior all the same): the
    # posterior is then in LU form, without a Cholesky factor to pack.
    X, y, kernel, whole = _whole_fit()
    tau, nu = whole.site_precision_.copy(), whole.site_nu_.copy()
    tau[0] = -0.05
    held = EPGaussianProcessClassifier(kernel, optimizer=None)._fit_warm_start(
        X, y, tau, nu, hold=np.ones(len(X), dtype=bool)
    )
    np.testing.assert_array_equal(held.site_precision_, tau)
    K = kernel(X)
    Sigma = np.linalg.inv(np.linalg.inv(K) + np.diag(tau))
    Q = np.random.default_rng(2).uniform(-3, 3, size=(20, 2))
    K_star = kernel(Q, X)
    A = np.linalg.solve(K, K_star.T)
    mean_ref = A.T @ Sigma @ nu
    var_ref = kernel.diag(Q) - np.einsum("ji,ji->i", K_star.T, A)
    var_ref += np.einsum("ji,jk,ki->i", A, Sigma, A)
    for rows in (slice(0, 3), slice(None)):  # a few queries, and more
        mean, var = held.latent_mean_and_variance(Q[rows])
        np.testing.assert_allclose(mean, mean_ref[rows], rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(var, var_ref[rows], rtol=1e-8)
    # Rows are absorbed only into a posterior in Cholesky form.
    assert held._absorbed(X[:2], y[:2]) is None


def test_a_held_fit_whose_ep_does_not_converge_warns():
    X, y = _data(n=80, seed=5)
    kernel = C(3.0) * RBF(0.8)
    old = EPGaussianProcessClassifier(kernel, optimizer=None).fit(X[:60], y[:60])
    clf = EPGaussianProcessClassifier(kernel, optimizer=None, max_iter=1)
    with pytest.warns(ConvergenceWarning, match="max_iter=1"):
        _holding(clf, X, y, old.site_precision_, old.site_nu_, 60)


def test_absorbed_refuses_a_mix_of_known_and_unknown_labels():
    X, y = _data(n=30)
    clf = EPGaussianProcessClassifier(C(1.0) * RBF(1.0), optimizer=None).fit(X, y)
    with pytest.raises(ValueError, match="not in classes_"):
        clf._absorbed(X[:2], [1, 2])


def test_absorbed_counts_the_sweeps_of_ep_on_the_new_rows():
    X, y, kernel, whole = _whole_fit()
    # Every row held: no EP sweep in the fit of the first 45 rows.
    old = _first_rows_held(X, y, kernel, whole, 45)
    assert old.n_iter_ == 0
    # The new rows' sites start from zero: EP sweeps over them.
    assert old._absorbed(X[45:], y[45:]).n_iter_ >= 1


def test_latent_of_given_cross_covariances_in_blocks(monkeypatch):
    # A mixture hands in k(x, x) and k(X, X_train_) for all queries; each block takes its rows.
    import skoccmap.classifier as module

    X, y = _data(n=30)
    kernel = C(2.0) * RBF(0.8)
    clf = EPGaussianProcessClassifier(kernel, optimizer=None).fit(X, y)
    Q = np.random.default_rng(1).uniform(-2, 2, size=(50, 2))
    mean, var = clf.latent_mean_and_variance(Q)
    monkeypatch.setattr(module, "_PREDICT_BLOCK_ELEMENTS", 30 * 7)
    mean_b, var_b = clf._latent(Q, kernel.diag(Q), kernel(Q, X))
    np.testing.assert_allclose(mean_b, mean, rtol=1e-12)
    np.testing.assert_allclose(var_b, var, rtol=1e-12)


def test_variance_is_positive_where_the_prior_variance_is_zero():
    # A dot-product kernel without offset has k(0, 0) = 0 and k(0, x) = 0.
    X, y = _data(n=20)
    clf = EPGaussianProcessClassifier(DotProduct(0.0, "fixed"), optimizer=None).fit(X, y)
    origin = np.zeros((1, 2))
    assert clf.prior_variance(origin)[0] == 0.0
    var = clf.predict_var(origin)
    assert var[0] > 0 and var[0] <= 1e-10
    np.testing.assert_allclose(clf.predict_proba(origin), [[0.5, 0.5]])


def test_held_rows_are_released_when_the_kernel_is_learned_by_a_callable():
    # The optimiser's last evaluation need not be at the theta it returns: its EP sites
    # then belong to another kernel and must not be held in the final fit.
    X, y = _data(n=40)
    kernel = C(1.0) * RBF(1.0)
    far = np.log([50.0, 0.2])

    def optimizer(obj_func, initial_theta, bounds):
        value = obj_func(initial_theta, eval_gradient=False)
        obj_func(far)  # the last evaluation, away from the optimum returned
        return initial_theta, value

    clf = EPGaussianProcessClassifier(kernel, optimizer=optimizer, tol=1e-10)
    held = clone(clf)._fit_warm_start(X, y, np.ones(40), np.zeros(40), hold=np.arange(40) < 30)
    plain = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10).fit(X, y)
    np.testing.assert_allclose(held.site_precision_, plain.site_precision_, rtol=1e-6)
    np.testing.assert_allclose(held.site_nu_, plain.site_nu_, rtol=1e-6, atol=1e-9)


def test_held_rows_given_to_a_multi_class_fit_are_not_kept():
    # A multi-class fit ignores hold; a later warm start without one must not find it.
    X, y3 = _data3(n=30)
    kernel = C(1.0) * RBF(1.0)
    clf = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10)
    clf._fit_warm_start(X, y3, hold=np.ones(30, dtype=bool))
    y = (y3 == 0).astype(int)
    clf._fit_warm_start(X, y, np.ones(30), np.zeros(30))
    cold = EPGaussianProcessClassifier(kernel, optimizer=None, tol=1e-10).fit(X, y)
    np.testing.assert_allclose(clf.site_precision_, cold.site_precision_, rtol=1e-6)
    np.testing.assert_allclose(clf.site_nu_, cold.site_nu_, rtol=1e-6, atol=1e-9)


def test_multi_class_theta_of_another_length_is_refused():
    X, y = _data3(n=30)
    clf = EPGaussianProcessClassifier(C(1.0) * RBF(1.0), optimizer=None).fit(X, y)
    for length in (1, 3, 5, 7):
        with pytest.raises(ValueError, match="Shape of theta must be either 2 or 6"):
            clf.log_marginal_likelihood(np.zeros(length))


@pytest.mark.parametrize("n_classes", [2, 3])
def test_theta_that_is_not_1d_is_refused(n_classes):
    # A scalar stopped in scikit-learn's kernels on "too many indices for array".
    X, y = _data3(n=30)
    clf = EPGaussianProcessClassifier(C(1.0) * RBF(1.0), optimizer=None).fit(X, y % n_classes)
    for theta in (0.0, np.zeros((1, 2))):
        with pytest.raises(ValueError, match=r"theta must be a 1-D array.*got shape \("):
            clf.log_marginal_likelihood(theta)
