import warnings

import numpy as np
import pytest
from scipy.spatial.distance import cdist
from sklearn.base import clone
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process.kernels import RBF
from sklearn.gaussian_process.kernels import ConstantKernel as C

from skoccmap import EPGaussianProcessClassifier
from skoccmap._shared_kernel import (
    _negative_sum,
    learn_shared_kernel,
    warn_at_bounds,
    warn_beyond_extent,
    window_pieces,
)


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


def test_learned_kernel_does_not_depend_on_n_jobs():
    # The evidence terms are computed in worker processes and summed in the pieces' order.
    expert = EPGaussianProcessClassifier(C(1.0, (1e-2, 1e2)) * RBF(1.0, (1e-2, 1e2)))
    pieces = [_piece(seed) for seed in range(5)]
    one = learn_shared_kernel(expert, pieces, n_jobs=1)
    two = learn_shared_kernel(expert, pieces, n_jobs=2)
    np.testing.assert_array_equal(one.theta, two.theta)
    assert not np.allclose(one.theta, expert.kernel.theta)


def test_fixed_optimizer_keeps_the_kernel():
    kernel = C(2.0) * RBF(0.7)
    expert = EPGaussianProcessClassifier(kernel, optimizer=None)
    shared = learn_shared_kernel(expert, [_piece(0)])
    np.testing.assert_allclose(shared.theta, kernel.theta)


def test_reversed_bounds_are_named_before_any_fit():
    expert = EPGaussianProcessClassifier(C(1.0, (1e-2, 1e2)) * RBF(1.0, (5.0, 1.0)))
    with pytest.raises(ValueError, match=r"kernel's k2__length_scale .* got \[5.0, 1.0\]"):
        learn_shared_kernel(expert, [_piece(0)])


def test_callable_optimizer_gets_the_summed_evidence_of_fixed_fits():
    # The objective is minus the sum of the pieces' log evidences, each piece fitted with the
    # given kernel; the optimiser starts from that kernel and its result is returned.
    kernel = C(2.0, (1e-2, 1e2)) * RBF(0.7, (1e-2, 1e2))
    pieces = [_piece(seed) for seed in range(2)]
    target = np.log([2.0, 0.5])
    seen = {}

    def optimizer(obj_func, initial_theta, bounds):
        seen["initial_theta"], seen["bounds"] = initial_theta, bounds
        seen["value"] = obj_func(target, eval_gradient=False)
        seen["value_and_grad"] = obj_func(target)
        return target, seen["value"]

    shared = learn_shared_kernel(EPGaussianProcessClassifier(kernel, optimizer=optimizer), pieces)
    np.testing.assert_array_equal(seen["initial_theta"], kernel.theta)
    np.testing.assert_array_equal(seen["bounds"], kernel.bounds)
    np.testing.assert_allclose(shared.theta, target, rtol=1e-12)
    terms = [
        EPGaussianProcessClassifier(kernel, optimizer=None)
        .fit(X, y)
        .log_marginal_likelihood(target, eval_gradient=True)
        for X, y in pieces
    ]
    assert np.ndim(seen["value"]) == 0
    assert seen["value"] == pytest.approx(-sum(t[0] for t in terms), rel=1e-10)
    value, grad = seen["value_and_grad"]
    assert value == pytest.approx(seen["value"], rel=1e-12)
    np.testing.assert_allclose(grad, -np.sum([t[1] for t in terms], axis=0), rtol=1e-8)


def test_kernel_with_nothing_to_learn_is_not_optimised():
    def optimizer(obj_func, initial_theta, bounds):
        raise AssertionError("the optimiser was called with no hyperparameter to learn")

    kernel = C(2.0, "fixed") * RBF(0.7, "fixed")
    shared = learn_shared_kernel(
        EPGaussianProcessClassifier(kernel, optimizer=optimizer), [_piece(0)]
    )
    assert shared == kernel


def test_bounds_are_not_checked_when_nothing_is_learned():
    # optimizer=None keeps the kernel as given: its bounds are never used.
    kernel = C(1.0) * RBF(1.0, (5.0, 1.0))
    shared = learn_shared_kernel(EPGaussianProcessClassifier(kernel, optimizer=None), [_piece(0)])
    assert shared == kernel


@pytest.mark.parametrize("optimizer", [None, "fmin_l_bfgs_b"])
def test_expert_without_a_kernel_learns_from_its_default(optimizer):
    X, y = _piece(0)
    expert = EPGaussianProcessClassifier(optimizer=optimizer)
    shared = learn_shared_kernel(expert, [(X, y)])
    own = clone(expert).fit(X, y).kernel_
    assert shared.get_params().keys() == own.get_params().keys()
    np.testing.assert_allclose(shared.theta, own.theta, atol=1e-3)


class _Evidence:
    """A fitted expert's stand-in: its log evidence and gradient at theta from ``f``."""

    def __init__(self, f):
        self.f = f

    def log_marginal_likelihood(self, theta, eval_gradient=False):
        return self.f(theta)


def _singular(theta):
    raise np.linalg.LinAlgError("not positive definite")


@pytest.mark.parametrize(
    "failing",
    [
        _singular,
        lambda theta: (np.nan, np.zeros_like(theta)),
        lambda theta: (-np.inf, np.zeros_like(theta)),
        lambda theta: (-1.0, np.array([np.nan, 0.0])),
        lambda theta: (-1.0, np.array([0.0, np.inf])),
    ],
    ids=["singular", "nan value", "-inf value", "nan gradient", "inf gradient"],
)
def test_failed_evidence_term_makes_the_objective_infinite(failing):
    # The optimiser is to step back from such theta: +inf, never -inf or NaN.
    good = _Evidence(lambda theta: (-2.0, np.array([0.5, -1.0])))
    theta = np.zeros(2)
    value, grad = _negative_sum(theta, [good, _Evidence(failing), good], None)
    assert value == np.inf
    np.testing.assert_array_equal(grad, [0.0, 0.0])
    value, grad = _negative_sum(theta, [good, good, good], None)
    assert value == 6.0
    np.testing.assert_array_equal(grad, [-1.5, 3.0])


def test_warns_at_bounds_only():
    kernel = C(1e3, (1e-3, 1e3)) * RBF(0.5, (1e-2, 1e2))
    with pytest.warns(ConvergenceWarning, match=r"k1__constant_value ended at its upper"):
        warn_at_bounds(kernel, "shared kernel")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_at_bounds(C(10.0, (1e-3, 1e3)) * RBF(0.5, (1e-2, 1e2)), "shared kernel")
        warn_at_bounds(C(1e3, "fixed") * RBF(0.5, (1e-2, 1e2)), "shared kernel")
    with pytest.warns(ConvergenceWarning, match=r"k2__length_scale ended at its lower"):
        warn_at_bounds(C(10.0, (1e-3, 1e3)) * RBF(1e-2, (1e-2, 1e2)), "shared kernel")


@pytest.mark.parametrize(
    "log_offset, side",
    [(5e-4, "lower"), (2e-3, None), (-5e-4, "upper"), (-2e-3, None)],
)
def test_at_bound_means_within_a_thousandth_in_log(log_offset, side):
    low, high = 1e-2, 1e2
    value = (low if log_offset > 0 else high) * np.exp(log_offset)
    kernel = C(10.0, (1e-3, 1e3)) * RBF(value, (low, high))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_at_bounds(kernel, "shared kernel")
    messages = [str(w.message) for w in caught if w.category is ConvergenceWarning]
    if side is None:
        assert messages == []
    else:
        shown = f"{value:.3g}"
        assert messages == [
            f"The shared kernel hyperparameter k2__length_scale ended at its {side} bound "
            f"({shown}). Widen its bounds in the kernel if the map needs it, or fix it "
            "(bounds='fixed')."
        ]


def test_warns_at_bounds_for_each_anisotropic_length_scale():
    kernel = C(1.0, "fixed") * RBF([1e-2, 0.5, 1e2], (1e-2, 1e2))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_at_bounds(kernel, "shared kernel")
    sides = [str(w.message).split("ended at its ")[1][:5] for w in caught]
    assert sides == ["lower", "upper"]


def test_warns_when_any_length_scale_is_beyond_the_extent():
    # The longest of the per-axis length scales counts: one axis beyond the extent makes the
    # map nearly constant along it.
    with pytest.warns(ConvergenceWarning, match="beyond the extent"):
        warn_beyond_extent(RBF([0.5, 50.0]), 10.0, "shared kernel")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_beyond_extent(RBF([0.5, 5.0]), 10.0, "shared kernel")


def _beyond_extent_warnings(kernel, extent):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_beyond_extent(kernel, extent, "shared kernel")
    return [str(w.message) for w in caught if w.category is ConvergenceWarning]


@pytest.mark.parametrize(
    "kernel, names",
    [
        (C(1.0) * RBF(50.0), ["k2__length_scale"]),
        (RBF(50.0, "fixed") + RBF(0.5), []),
        (RBF(50.0, "fixed") + C(2.0) * RBF(50.0), ["k2__k2__length_scale"]),
        (RBF(10.0), []),
        (RBF(10.5), ["length_scale"]),
    ],
    ids=["composed", "fixed", "fixed then learned", "at the extent", "just beyond"],
)
def test_beyond_extent_names_each_learned_length_scale(kernel, names):
    messages = _beyond_extent_warnings(kernel, 10.0)
    assert [m.split(" hyperparameter ")[1].split(" ")[0] for m in messages] == names
    for message in messages:
        assert "was learned at" in message and "(10)" in message
    if names == ["k2__length_scale"]:
        assert "learned at 50, beyond the extent of the training data (10)" in messages[0]


def _scatter(n=600, seed=0):
    rng = np.random.RandomState(seed)
    points = rng.uniform(0, 20, size=(n, 2))
    y = (rng.uniform(size=n) < 0.3).astype(int)
    return points, y


def test_windows_are_balls_around_occupied_points():
    points, y = _scatter()
    radius = 2.0
    pieces = window_pieces(
        points,
        y,
        radius=radius,
        max_rows=10_000,
        n_pieces=5,
        random_state=np.random.RandomState(1),
    )
    assert len(pieces) == 5
    occupied = points[y == 1]
    for rows in pieces:
        assert np.all(np.diff(rows) > 0)
        assert 0 < y[rows].sum() < rows.size
        # Not capped: the window is exactly the ball around one occupied point.
        inside = cdist(occupied, points) <= radius
        assert any(np.array_equal(np.flatnonzero(ball), rows) for ball in inside)


def test_windows_are_capped_and_reproducible():
    points, y = _scatter()
    kwargs = dict(radius=5.0, max_rows=30, n_pieces=8)
    first = window_pieces(points, y, random_state=np.random.RandomState(3), **kwargs)
    again = window_pieces(points, y, random_state=np.random.RandomState(3), **kwargs)
    assert len(first) == 8
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)
        assert a.size == 30
        assert np.all(np.diff(a) > 0)  # sorted, and no row drawn twice
        assert cdist(points[a], points[a]).max() <= 2 * 5.0


def test_capped_windows_still_hold_both_classes():
    # A few rows drawn from a window of mostly free rows may hold no occupied one: such a
    # draw is not a window.
    points, y = _scatter(seed=2)
    y = (np.random.RandomState(4).uniform(size=len(y)) < 0.1).astype(int)
    for seed in range(20):
        rng = np.random.RandomState(seed)
        pieces = window_pieces(points, y, radius=20.0, max_rows=3, n_pieces=6, random_state=rng)
        assert pieces
        assert all(0 < y[rows].sum() < rows.size for rows in pieces)


def test_windows_need_both_classes():
    points, _ = _scatter()
    for y in (np.zeros(len(points), int), np.ones(len(points), int)):
        assert (
            window_pieces(
                points,
                y,
                radius=3.0,
                max_rows=50,
                n_pieces=4,
                random_state=np.random.RandomState(0),
            )
            == []
        )
    # Occupied rows far from every free row: no window holds both classes.
    y = np.r_[np.ones(10, int), np.zeros(10, int)]
    points = np.r_[np.zeros((10, 2)), np.full((10, 2), 100.0)]
    assert (
        window_pieces(
            points, y, radius=3.0, max_rows=50, n_pieces=4, random_state=np.random.RandomState(0)
        )
        == []
    )


def test_windows_holding_the_same_rows_count_once():
    # A radius larger than the data: every centre draws the same window, whose evidence
    # would count 8 times (and cost 8 learnings).
    rng = np.random.default_rng(0)
    points = rng.uniform(0.0, 5.0, size=(40, 2))
    y = (np.arange(40) % 2).astype(np.int64)
    pieces = window_pieces(
        points, y, radius=100.0, max_rows=50, n_pieces=8, random_state=np.random.RandomState(0)
    )
    assert len(pieces) == 1
    np.testing.assert_array_equal(pieces[0], np.arange(40))
    # Subsampled windows differ: all 8 are kept.
    pieces = window_pieces(
        points, y, radius=100.0, max_rows=10, n_pieces=8, random_state=np.random.RandomState(0)
    )
    assert len(pieces) == 8
