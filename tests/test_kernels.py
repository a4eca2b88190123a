"""IntegralKernel as a scikit-learn kernel: algebra, gradients, validation, GP estimators."""

import numpy as np
import pytest
import scipy.sparse
from scipy import integrate
from sklearn.base import clone
from sklearn.gaussian_process import GaussianProcessClassifier, GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, WhiteKernel
from sklearn.gaussian_process.kernels import ConstantKernel as C

from skoccmap import IntegralKernel


def _segments(rng, n, dim=2, box=5.0, max_length=4.0, point_fraction=0.3):
    start = rng.uniform(0, box, (n, dim))
    direction = rng.normal(size=(n, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    length = rng.uniform(0, max_length, n)
    length[rng.random(n) < point_fraction] = 0.0
    return np.hstack([start, start + length[:, None] * direction])


def _fd_gradient(kernel, X, eps=1e-5):
    theta = kernel.theta
    out = []
    for i in range(len(theta)):
        step = np.zeros_like(theta)
        step[i] = eps
        plus = kernel.clone_with_theta(theta + step)(X)
        minus = kernel.clone_with_theta(theta - step)(X)
        out.append((plus - minus) / (2 * eps))
    return np.stack(out, axis=-1)


def test_repr_and_properties():
    assert repr(IntegralKernel(0.5)) == "IntegralKernel(length_scale=0.5)"
    assert repr(IntegralKernel([0.5, 2.0])) == "IntegralKernel(length_scale=[0.5, 2])"
    kernel = IntegralKernel(0.5)
    assert not kernel.is_stationary()
    assert kernel.requires_vector_input
    assert kernel.n_dims == 1
    assert IntegralKernel([1.0, 2.0, 3.0]).n_dims == 3
    assert IntegralKernel(1.0, length_scale_bounds="fixed").n_dims == 0
    assert repr(C(2.0) * kernel + WhiteKernel(0.1)) == (
        "1.41**2 * IntegralKernel(length_scale=0.5) + WhiteKernel(noise_level=0.1)"
    )
    np.testing.assert_allclose(kernel.theta, np.log([0.5]))
    assert clone(kernel).get_params() == kernel.get_params()


def test_value_is_the_average_of_the_rbf_kernel():
    # One 2 m beam against a point, l = 0.5, against the quadrature of the RBF kernel itself.
    beam = np.array([[0.0, 0.0, 2.0, 0.0]])
    point = np.array([[1.3, 0.4, 1.3, 0.4]])
    rbf = RBF(0.5)

    def f(u):
        return rbf(np.array([[2.0 * u, 0.0]]), point[:, :2])[0, 0]

    expected = integrate.quad(f, 0, 1, points=[0.65], epsabs=1e-15, epsrel=1e-12)[0]
    assert IntegralKernel(0.5)(beam, point)[0, 0] == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("length_scale", [0.7, [0.5, 1.3]])
def test_points_reduce_to_rbf(length_scale):
    rng = np.random.default_rng(0)
    P = rng.normal(size=(20, 2))
    X = np.hstack([P, P])
    K, G = IntegralKernel(length_scale)(X, eval_gradient=True)
    K_rbf, G_rbf = RBF(length_scale)(P, eval_gradient=True)
    np.testing.assert_allclose(K, K_rbf, rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(G, G_rbf, rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize(
    "kernel",
    [
        IntegralKernel(0.6),
        IntegralKernel([0.6, 1.1]),
        C(2.0) * IntegralKernel(0.8) + WhiteKernel(0.1),
        IntegralKernel(0.5) * IntegralKernel([1.0, 2.0]) + IntegralKernel(1.5) ** 2,
    ],
    ids=["iso", "aniso", "C*IK+White", "products-and-powers"],
)
def test_gradient_of_composed_kernels(kernel):
    rng = np.random.default_rng(1)
    X = _segments(rng, 20)
    K, G = kernel(X, eval_gradient=True)
    assert G.shape == (20, 20, kernel.n_dims)
    np.testing.assert_allclose(G, _fd_gradient(kernel, X), rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(kernel.diag(X), np.diag(K), rtol=1e-12)


def test_fixed_length_scale_has_empty_gradient():
    X = _segments(np.random.default_rng(2), 5)
    K, G = IntegralKernel(1.0, length_scale_bounds="fixed")(X, eval_gradient=True)
    assert G.shape == (5, 5, 0)
    np.testing.assert_array_equal(K, IntegralKernel(1.0)(X))


def test_cross_kernel_is_transpose_and_diag_is_closed_form():
    rng = np.random.default_rng(3)
    X, Y = _segments(rng, 12, dim=3), _segments(rng, 7, dim=3)
    kernel = IntegralKernel([0.4, 0.9, 1.5])
    np.testing.assert_allclose(kernel(X, Y), kernel(Y, X).T, rtol=1e-12, atol=1e-16)
    np.testing.assert_allclose(kernel.diag(X), np.diag(kernel(X)), rtol=1e-14)
    lengths = np.linalg.norm((X[:, 3:] - X[:, :3]) / [0.4, 0.9, 1.5], axis=1)
    assert np.all(kernel.diag(X)[lengths > 0] < 1.0)
    assert np.all(kernel.diag(X)[lengths == 0] == 1.0)


@pytest.mark.parametrize(
    "X, match",
    [
        (np.zeros((3, 3)), "even number of columns"),
        (np.array([[0.0, np.nan, 1.0, 1.0]]), "NaN"),
        (np.zeros(4), "2-D"),
        (np.zeros((3, 0)), r"0 column\(s\)"),
    ],
    ids=["odd columns", "nan", "1-D", "zero_columns"],
)
def test_bad_input_raises(X, match):
    with pytest.raises(ValueError, match=match):
        IntegralKernel(1.0)(X)
    with pytest.raises(ValueError, match=match):
        IntegralKernel(1.0).diag(X)


def test_sparse_input_is_refused_with_advice():
    # It was numpy's "setting an array element with a sequence".
    X = scipy.sparse.csr_matrix(np.ones((3, 4)))
    for call in (IntegralKernel(1.0), IntegralKernel(1.0).diag):
        with pytest.raises(TypeError, match=r"sparse matrix.*X\.toarray\(\)"):
            call(X)
    with pytest.raises(TypeError, match=r"Y\.toarray\(\)"):
        IntegralKernel(1.0)(np.ones((3, 4)), X)


@pytest.mark.parametrize("length_scale", [1.0, [1.0, 2.0]])
def test_empty_input_gives_empty_arrays(length_scale):
    kernel, empty, X = IntegralKernel(length_scale), np.zeros((0, 4)), np.ones((3, 4))
    assert kernel(empty).shape == (0, 0) and kernel.diag(empty).shape == (0,)
    assert kernel(empty, X).shape == (0, 3) and kernel(X, empty).shape == (3, 0)
    K, G = kernel(empty, eval_gradient=True)
    assert K.shape == (0, 0) and G.shape == (0, 0, np.size(length_scale))


def test_bad_arguments_raise():
    X = np.zeros((2, 4))
    with pytest.raises(ValueError, match="Y is None"):
        IntegralKernel(1.0)(X, X, eval_gradient=True)
    with pytest.raises(ValueError, match="columns"):
        IntegralKernel(1.0)(X, np.zeros((2, 6)))
    with pytest.raises(ValueError, match="3 entries"):
        IntegralKernel([1.0, 1.0, 1.0])(X)
    with pytest.raises(ValueError, match="positive"):
        IntegralKernel(-1.0)(X)


def _occupancy_data(rng, n_beams=40):
    # Beams from the origin to hits on a wall at x = 3; hits are points, free space the beams.
    angles = rng.uniform(-0.8, 0.8, n_beams)
    hits = np.column_stack([np.full(n_beams, 3.0), 3.0 * np.tan(angles)])
    ends = hits * 0.95
    beams = np.hstack([np.zeros((n_beams, 2)), ends])
    points = np.hstack([hits, hits])
    X = np.vstack([beams, points])
    y = np.r_[np.zeros(n_beams), np.ones(n_beams)]
    return X, y


def test_gaussian_process_regressor_fits_and_optimises():
    X, y = _occupancy_data(np.random.default_rng(4))
    kernel = C(1.0) * IntegralKernel(3.0) + WhiteKernel(0.05, noise_level_bounds="fixed")
    gpr = GaussianProcessRegressor(kernel, random_state=0).fit(X, y)
    learned = gpr.kernel_.k1.k2.length_scale
    assert learned != pytest.approx(3.0)
    # The optimum is a stationary point of the log marginal likelihood.
    _, grad = gpr.log_marginal_likelihood(gpr.kernel_.theta, eval_gradient=True)
    bounds = gpr.kernel_.bounds
    theta = gpr.kernel_.theta
    interior = (theta > bounds[:, 0] + 1e-3) & (theta < bounds[:, 1] - 1e-3)
    assert np.all(np.abs(grad[interior]) < 1e-2)
    # Queries on the wall look occupied, queries halfway along the beams look free.
    wall = np.array([[3.0, 0.5, 3.0, 0.5]])
    free = np.array([[1.5, 0.2, 1.5, 0.2]])
    mean, std = gpr.predict(np.vstack([wall, free]), return_std=True)
    assert mean[0] > 0.5 > mean[1]
    assert np.all(std > 0)


def test_log_marginal_likelihood_gradient_matches_finite_differences():
    X, y = _occupancy_data(np.random.default_rng(5), n_beams=15)
    gpr = GaussianProcessRegressor(C(1.0) * IntegralKernel(0.7) + WhiteKernel(0.1), optimizer=None)
    gpr.fit(X, y)
    theta = gpr.kernel_.theta
    _, grad = gpr.log_marginal_likelihood(theta, eval_gradient=True)
    eps = 1e-6
    lml = gpr.log_marginal_likelihood
    fd = [(lml(theta + eps * e) - lml(theta - eps * e)) / (2 * eps) for e in np.eye(len(theta))]
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-7)


def test_gaussian_process_classifier_fits_and_optimises():
    X, y = _occupancy_data(np.random.default_rng(6))
    gpc = GaussianProcessClassifier(C(1.0) * IntegralKernel(3.0), random_state=0).fit(X, y)
    assert gpc.kernel_.k2.length_scale != pytest.approx(3.0)
    queries = np.array([[3.0, 0.5, 3.0, 0.5], [1.5, 0.2, 1.5, 0.2]])
    proba = gpc.predict_proba(queries)
    assert proba[0, 1] > 0.5 > proba[1, 1]
    np.testing.assert_array_equal(gpc.predict(queries), [1.0, 0.0])


def test_one_element_length_scale_is_isotropic():
    # As RBF: a length scale given as a one-element list is one length scale for every
    # dimension, with one gradient column, not an anisotropic kernel.
    X = _segments(np.random.default_rng(7), 12)
    kernel = IntegralKernel([0.7])
    assert not kernel.anisotropic and kernel.n_dims == 1
    K, G = kernel(X, eval_gradient=True)
    assert G.shape == (12, 12, 1)
    np.testing.assert_allclose(K, IntegralKernel(0.7)(X), rtol=1e-14)
    np.testing.assert_allclose(G, _fd_gradient(kernel, X), rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize(
    "length_scale, columns, match",
    [
        (0.0, 4, "positive and finite"),
        ([0.5, 0.0], 4, "positive and finite"),
        (np.inf, 4, "positive and finite"),
        ([1.0, np.nan], 4, "positive and finite"),
        ([[0.5, 1.0], [1.0, 2.0]], 4, "scalar or a 1-D array"),
        (
            [1.0, 2.0],
            6,
            r"has 2 entries but the segments have 3 spatial dimension\(s\) \(6 columns\)",
        ),
    ],
    ids=["zero", "one zero", "inf", "nan", "2-D", "too few entries"],
)
def test_bad_length_scales_raise(length_scale, columns, match):
    X = np.zeros((2, columns))
    with pytest.raises(ValueError, match=match):
        IntegralKernel(length_scale)(X)
    with pytest.raises(ValueError, match=match):
        IntegralKernel(length_scale).diag(X)
    with pytest.raises(ValueError, match=match):
        IntegralKernel(length_scale)(X, X)


def test_anisotropic_cross_kernel_matches_quadrature_and_the_joint_matrix():
    length_scale = [0.5, 1.3]
    kernel = IntegralKernel(length_scale)
    # A 2 m beam along x against a point, by quadrature of the anisotropic RBF kernel.
    beam = np.array([[0.0, 0.0, 2.0, 0.0]])
    point = np.array([[1.3, 0.4, 1.3, 0.4]])
    rbf = RBF(length_scale)

    def f(u):
        return rbf(np.array([[2.0 * u, 0.0]]), point[:, :2])[0, 0]

    expected = integrate.quad(f, 0, 1, points=[0.65], epsabs=1e-15, epsrel=1e-12)[0]
    assert kernel(beam, point)[0, 0] == pytest.approx(expected, rel=1e-10)
    assert kernel(point, beam)[0, 0] == pytest.approx(expected, rel=1e-10)
    # Points against points: the anisotropic RBF kernel.
    rng = np.random.default_rng(8)
    P, Q = rng.normal(size=(6, 2)), rng.normal(size=(5, 2))
    np.testing.assert_allclose(
        kernel(np.hstack([P, P]), np.hstack([Q, Q])), rbf(P, Q), rtol=1e-13, atol=1e-300
    )
    # Segments: the off-diagonal block of the kernel of both sets together.
    X, Y = _segments(rng, 9), _segments(rng, 7)
    joint = kernel(np.vstack([X, Y]))
    np.testing.assert_allclose(kernel(X, Y), joint[:9, 9:], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize(
    "Y, match",
    [
        (np.array([[0.0, np.nan, 1.0, 1.0]]), "NaN"),
        (np.array([[0.0, np.inf, 1.0, 1.0]]), "infinite"),
        (np.zeros(4), "2-D"),
    ],
    ids=["nan", "inf", "1-D"],
)
def test_bad_cross_input_raises(Y, match):
    X = np.zeros((2, 4))
    with pytest.raises(ValueError, match=match):
        IntegralKernel(1.0)(X, Y)


@pytest.mark.parametrize("X_columns, Y_columns", [(4, 6), (6, 4)])
def test_cross_kernel_needs_the_same_dimension_either_way(X_columns, Y_columns):
    X, Y = np.zeros((2, X_columns)), np.zeros((3, Y_columns))
    match = f"X has {X_columns} columns but Y has {Y_columns}"
    with pytest.raises(ValueError, match=match):
        IntegralKernel(1.0)(X, Y)


@pytest.mark.parametrize("length_scale", [0.7, [0.7], [0.5, 1.3], [0.2, 0.4, 0.8]])
@pytest.mark.parametrize("bounds", [(1e-2, 1e2), "fixed"])
def test_hyperparameter_theta_and_bounds_are_those_of_rbf(length_scale, bounds):
    # The optimisers of scikit-learn's GPs and of this package see the kernel through these:
    # one log length scale per spatial dimension when anisotropic, each with the bounds.
    kernel, rbf = IntegralKernel(length_scale, bounds), RBF(length_scale, bounds)
    (hyp,), (expected,) = kernel.hyperparameters, rbf.hyperparameters
    assert (hyp.name, hyp.value_type, hyp.n_elements, hyp.fixed) == (
        expected.name,
        expected.value_type,
        expected.n_elements,
        expected.fixed,
    )
    assert kernel.anisotropic == rbf.anisotropic
    assert kernel.n_dims == rbf.n_dims
    np.testing.assert_array_equal(kernel.theta, rbf.theta)
    np.testing.assert_array_equal(kernel.bounds, rbf.bounds)
    assert kernel.bounds.shape == rbf.bounds.shape


@pytest.mark.parametrize("length_scale", [0.12345, [0.12345], 1234.5, [0.12345, 2.0, 6789.0]])
def test_repr_rounds_as_rbf(length_scale):
    assert repr(IntegralKernel(length_scale)) == repr(RBF(length_scale)).replace(
        "RBF", "IntegralKernel"
    )


@pytest.mark.parametrize("length_scale", [[[0.7]], [[0.5, 1.3]]], ids=["1x1", "1x2"])
def test_row_of_length_scales_is_refused_before_learning(length_scale):
    # A row was taken for one isotropic length scale with a 2-D theta: a GP's fit stopped
    # inside scipy with "'x0' must only have one dimension".
    X, y = _occupancy_data(np.random.default_rng(9), n_beams=5)
    kernel = IntegralKernel(length_scale)
    match = r"scalar or a 1-D array .* got shape \(1, \d\); pass np\.ravel\(length_scale\)"
    with pytest.raises(ValueError, match=match):
        GaussianProcessRegressor(C(1.0) * kernel).fit(X, y)
    with pytest.raises(ValueError, match=match):
        _ = kernel.theta
    with pytest.raises(ValueError, match=match):
        kernel(X)
    with pytest.raises(ValueError, match=match):
        kernel.diag(X)


def test_coordinates_whose_squares_overflow_are_refused():
    # A point at 1e155 against a segment reaching it gave a NaN entry, and a segment of that
    # length a diagonal of 0, without a word.
    point, segment = np.array([[1e155, 0.0, 1e155, 0.0]]), np.array([[0.0, 0.0, 1e155, 0.0]])
    kernel = IntegralKernel(1.0)
    for call in (
        lambda: kernel(point, segment),
        lambda: kernel(segment),
        lambda: kernel.diag(segment),
    ):
        with pytest.raises(ValueError, match=r"coordinates up to 1e\+155.*Rescale or shift"):
            call()
    with pytest.raises(ValueError, match=r"Y holds coordinates up to 1e\+155"):
        kernel(np.zeros((1, 4)), segment)
    assert np.isfinite(kernel(point / 1e56, segment / 1e56)).all()


def test_pairs_of_segments_too_long_for_the_quadrature_are_refused():
    # Two 1 m beams at length_scale 1e-8 (1e8 length scales) took 15 s and were off by 13 %;
    # at 1e-30 the panel count overflowed into an IndexError deep in the quadrature.
    beams = np.array([[0.0, 0.0, 1.0, 0.0], [0.1, 0.2, 0.7, 0.9]])
    point = np.array([[0.5, 0.0, 0.5, 0.0]])
    for length_scale in (1e-8, 1e-30, [1e-8, 1.0]):
        kernel = IntegralKernel(length_scale)
        for args, kwargs in (((beams,), {}), ((beams,), {"eval_gradient": True})):
            with pytest.raises(ValueError, match=r"length scales long.*Raise length_scale"):
                kernel(*args, **kwargs)
        with pytest.raises(ValueError, match=r"X and Y each hold a segment"):
            kernel(beams[:1], beams[1:])
        # Closed forms stay: a segment with itself, and segments against points.
        np.testing.assert_allclose(kernel(beams[:1])[0, 0], kernel.diag(beams[:1])[0])
        np.testing.assert_allclose(kernel(point, beams), kernel(beams, point).T)
    # One long segment among short ones needs quadrature along the short ones only.
    short = np.array([[0.3, -1e-7, 0.3, 1e-7]])
    K = IntegralKernel(1e-8)(np.vstack([beams[:1], short]))
    assert np.isfinite(K).all() and K[0, 1] > 0
    # Up to 1e7 length scales the kernel is still evaluated, within 2e-3.
    kernel = IntegralKernel(1e-7)
    np.testing.assert_allclose(np.diag(kernel(beams, beams)), kernel.diag(beams), rtol=2e-3)
