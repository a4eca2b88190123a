import warnings

import numpy as np
import pytest
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process.kernels import RBF
from sklearn.gaussian_process.kernels import ConstantKernel as C

from skoccmap import EPGaussianProcessClassifier
from skoccmap._shared_kernel import learn_shared_kernel, warn_at_bounds


def _piece(seed, n=40):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-3, 3, size=(n, 1))
    y = (np.sin(2 * X[:, 0]) + 0.3 * rng.normal(size=n) > 0).astype(int)
    return X, y


def test_one_piece_is_the_experts_own_optimum():
    expert = EPGaussianProcessClassifier(C(1.0, (1e-2, 1e2)) * RBF(1.0, (1e-2, 1e2)))
    X, y = _piece(0)
    own = expert.fit(X, y).kernel_
    shared = learn_shared_kernel(expert, [(X, y)])
    np.testing.assert_allclose(shared.theta, own.theta, atol=1e-3)


def test_sum_of_pieces_is_a_stationary_point_of_the_summed_evidence():
    expert = EPGaussianProcessClassifier(C(1.0, (1e-2, 1e2)) * RBF(1.0, (1e-2, 1e2)))
    pieces = [_piece(seed) for seed in range(3)]
    shared = learn_shared_kernel(expert, pieces, n_jobs=2)
    grad = np.zeros_like(shared.theta)
    for X, y in pieces:
        fitted = EPGaussianProcessClassifier(shared, optimizer=None).fit(X, y)
        grad += fitted.log_marginal_likelihood(shared.theta, eval_gradient=True)[1]
    np.testing.assert_allclose(grad, 0.0, atol=1e-3)
    # Different from every piece's own optimum.
    for X, y in pieces:
        assert not np.allclose(expert.fit(X, y).kernel_.theta, shared.theta, atol=1e-2)


def test_fixed_optimizer_keeps_the_kernel():
    kernel = C(2.0) * RBF(0.7)
    expert = EPGaussianProcessClassifier(kernel, optimizer=None)
    shared = learn_shared_kernel(expert, [_piece(0)])
    np.testing.assert_allclose(shared.theta, kernel.theta)


def test_warns_at_bounds_only():
    kernel = C(1e3, (1e-3, 1e3)) * RBF(0.5, (1e-2, 1e2))
    with pytest.warns(ConvergenceWarning, match=r"k1__constant_value ended at its upper"):
        warn_at_bounds(kernel, "shared kernel")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_at_bounds(C(10.0, (1e-3, 1e3)) * RBF(0.5, (1e-2, 1e2)), "shared kernel")
        warn_at_bounds(C(1e3, "fixed") * RBF(0.5, (1e-2, 1e2)), "shared kernel")
