"""Reference tests of the segment integrals against scipy quadrature and finite differences."""

import numpy as np
import pytest
from scipy import integrate
from scipy.special import ndtr

from skoccmap._integrals import (
    _CUTOFF,
    _GL_MAX_WINDOW,
    _GL_NODES,
    _GL_WEIGHTS,
    _SHORT,
    crossing_upper_bound,
    gauss_legendre_order,
    integral_kernel,
    loose_upper_bound,
    pair_integrals,
    pair_upper_bound,
    point_point,
    point_row_pairs,
    segment_point,
    segment_self,
)

RTOL = 1e-6
ATOL = 1e-12


def _closest_params(a1, d1, a2, d2):
    """Parameters on segment 1 where the integrand may peak (reference breakpoints)."""
    pts = []
    dd = d1 @ d1
    if dd > 0:
        for q in (a2, a2 + d2):
            pts.append((q - a1) @ d1 / dd)
        # closest approach of the two lines
        b = d1 @ d2
        c = d2 @ d2
        den = dd * c - b * b
        if den > 1e-12 * dd * c:
            w = a1 - a2
            pts.append((b * (d2 @ w) - c * (d1 @ w)) / den)
    return sorted({float(p) for p in pts if 0.0 < p < 1.0})


def reference_nested_quad(s1, s2, gradient_dim=None, epsabs=1e-15):
    """Double integral by nested adaptive ``scipy.integrate.quad``.

    Breakpoints at the projections of the other segment's ends and at the lines' closest
    approach (outer), and at the closest point (inner), so that narrow peaks of long segments
    are never missed. ``gradient_dim`` integrates ``dx_k**2 * kernel`` instead; ``epsabs=0``
    asks for relative accuracy only (for values far below 1e-15).
    """
    dim = len(s1) // 2
    a1, d1 = s1[:dim], s1[dim:] - s1[:dim]
    a2, d2 = s2[:dim], s2[dim:] - s2[:dim]
    dd2 = d2 @ d2

    def inner(u):
        p = a1 + u * d1

        def f(v):
            diff = p - a2 - v * d2
            val = np.exp(-0.5 * diff @ diff)
            return val if gradient_dim is None else diff[gradient_dim] ** 2 * val

        pts = None
        if dd2 > 0:
            v0 = (p - a2) @ d2 / dd2
            if 0.0 < v0 < 1.0:
                pts = [v0]
        return integrate.quad(f, 0.0, 1.0, points=pts, epsabs=epsabs, epsrel=1e-12, limit=500)[0]

    pts = _closest_params(a1, d1, a2, d2) or None
    return integrate.quad(inner, 0.0, 1.0, points=pts, epsabs=epsabs, epsrel=1e-11, limit=500)[0]


def reference_dblquad(s1, s2):
    """Double integral by ``scipy.integrate.dblquad`` on a grid of unit-length sub-squares."""
    dim = len(s1) // 2
    a1, d1 = s1[:dim], s1[dim:] - s1[:dim]
    a2, d2 = s2[:dim], s2[dim:] - s2[:dim]

    def f(v, u):
        diff = a1 + u * d1 - a2 - v * d2
        return np.exp(-0.5 * diff @ diff)

    n1 = int(np.ceil(np.linalg.norm(d1))) + 1
    n2 = int(np.ceil(np.linalg.norm(d2))) + 1
    total = 0.0
    for i in range(n1):
        for j in range(n2):
            total += integrate.dblquad(
                f, i / n1, (i + 1) / n1, j / n2, (j + 1) / n2, epsabs=1e-16, epsrel=1e-12
            )[0]
    return total


def assert_close(actual, expected, rtol=RTOL, atol=ATOL):
    actual, expected = np.asarray(actual), np.asarray(expected)
    err = np.abs(actual - expected)
    ok = (err <= rtol * np.abs(expected)) | (err <= atol)
    assert np.all(ok), f"actual={actual[~ok]}, expected={expected[~ok]}, err={err[~ok]}"


def _segment_point_by_quad(a, d, p):
    """The point kernel averaged along the segment ``a + v d`` against ``p`` (scaled
    units), by adaptive quadrature to 1e-13 relative."""

    def f(v):
        diff = a + v * d - p
        return np.exp(-0.5 * diff @ diff)

    return integrate.quad(f, 0, 1, epsabs=0.0, epsrel=1e-13, limit=200)[0]


def _seg(start, end):
    return np.concatenate([np.asarray(start, float), np.asarray(end, float)])


# Scaled coordinates (length scale 1). Named geometries that stress the quadrature.
CASES_2D = {
    "long crossing": (_seg([-50, 0.3], [50, 0.3]), _seg([0.1, -50], [0.7, 50])),
    "long shallow crossing": (_seg([0, 0], [100, 0]), _seg([10, -2], [90, 3])),
    "long parallel offset": (_seg([0, 0], [100, 0]), _seg([30, 1.5], [130, 1.5])),
    "long collinear overlap": (_seg([0, 0], [100, 0]), _seg([50, 0], [150, 0])),
    "long collinear touching": (_seg([0, 0], [100, 0]), _seg([100, 0], [200, 0])),
    "long antiparallel identical": (_seg([0, 0], [100, 0]), _seg([100, 0], [0, 0])),
    "shared start (one pose)": (_seg([1, 1], [9, 3]), _seg([1, 1], [3, 8])),
    "touching T": (_seg([0, 0], [6, 0]), _seg([3, 0], [3, 7])),
    # The shorter segment starts 30 behind the longer one and crosses it at a shallow angle,
    # both ends of the longer one more than the window margin off its line: the window is
    # where its closest point lies within the longer segment, up to its far end.
    "shallow crossing from behind": (_seg([-30, -11], [59, 1.5]), _seg([0, 0], [100, 0])),
    # Perpendicular segments (axis-aligned beams): the inner segment's closest point is the
    # same for every point of the outer one.
    "perpendicular from the line": (_seg([0, 0], [14, 0]), _seg([6, 0], [6, -6])),
    "perpendicular off the line": (_seg([0, 0], [14, 0]), _seg([6, 1], [6, 4])),
    "perpendicular crossing": (_seg([0, 0], [14, 0]), _seg([6, -3], [6, 3])),
    "near miss tail": (_seg([0, 0], [5, 0]), _seg([12, 0], [20, 0])),
    "short vs long": (_seg([0.2, 0.1], [0.25, 0.12]), _seg([-40, 0], [40, 0.5])),
    "point vs long": (_seg([7.3, 0.4], [7.3, 0.4]), _seg([-40, 0], [40, 0])),
    "point off end": (_seg([46, 0.0], [46, 0.0]), _seg([-40, 0], [40, 0])),
    "two short": (_seg([0, 0], [0.03, 0.01]), _seg([0.5, 0.2], [0.49, 0.24])),
    "short at threshold": (_seg([0, 0], [_SHORT, 0]), _seg([0.3, 0.2], [0.3, 0.2 + _SHORT])),
}
CASES_3D = {
    "long skew": (_seg([-50, 0, 0], [50, 0, 0]), _seg([0, -50, 1], [3, 50, 1.2])),
    "long skew far": (_seg([-50, 0, 0], [50, 0, 0]), _seg([0, -50, 6], [3, 50, 6.5])),
    "long parallel": (_seg([0, 0, 0], [0, 0, 100]), _seg([1, 0.5, 20], [1, 0.5, 70])),
    "crossing": (_seg([0, 0, 0], [4, 4, 4]), _seg([4, 0, 4], [0, 4, 0])),
    "collinear touching": (_seg([0, 0, 0], [2, 3, 1]), _seg([2, 3, 1], [4, 6, 2])),
}


@pytest.mark.parametrize(
    "s1, s2",
    list(CASES_2D.values()) + list(CASES_3D.values()),
    ids=list(CASES_2D) + list(CASES_3D),
)
def test_pairs_match_nested_quad(s1, s2):
    expected = reference_nested_quad(s1, s2, epsabs=0.0)
    # The outer window leaves out about exp(-_WINDOW_MARGIN**2 / 2) ~ 2e-8 of the value (4e-8
    # on the near miss, whose value is 1e-14): relative to the value, a window or a
    # Gauss-Legendre order too small by a little shows here.
    k, _ = pair_integrals(s1[None], s2[None])
    assert_close(k[0], expected, rtol=1e-7, atol=0.0)
    # The kernel is symmetric in its arguments.
    k_swapped, _ = pair_integrals(s2[None], s1[None])
    assert_close(k_swapped[0], expected, rtol=1e-7, atol=0.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_random_pairs_match_dblquad(dim):
    rng = np.random.default_rng(dim)
    s1, s2 = [], []
    for _ in range(6):
        for out in (s1, s2):
            start = rng.uniform(-2, 2, dim)
            length = rng.choice([0.0, 0.01, 0.3, 1.5, 4.0])
            direction = rng.normal(size=dim)
            out.append(_seg(start, start + length * direction / np.linalg.norm(direction)))
    s1, s2 = np.array(s1), np.array(s2)
    k, _ = pair_integrals(s1, s2)
    expected = [reference_dblquad(a, b) for a, b in zip(s1, s2, strict=True)]
    assert_close(k, expected)


def test_references_agree():
    # The two reference methods are independent ways to integrate; they must agree.
    s1, s2 = _seg([0, 0], [3, 1]), _seg([1, -1], [2, 2.5])
    assert reference_nested_quad(s1, s2) == pytest.approx(reference_dblquad(s1, s2), rel=1e-9)


@pytest.mark.parametrize(
    "length", [0.0, 1e-9, 1e-4, 0.02, _SHORT * 0.999, _SHORT * 1.001, 0.5, 3.0, 100.0]
)
@pytest.mark.parametrize("offset", [[0.0, 0.0], [0.3, 0.4], [-2.0, 1.0], [0.6, 7.5]])
def test_segment_point_matches_quad(length, offset):
    # Short segments are where the erf difference would cancel; far points probe the tails.
    a = np.array([0.2, -0.1])
    d = length * np.array([0.6, 0.8])
    p = a + np.asarray(offset) + 0.5 * d
    pts = None
    if length > 0:
        v0 = (p - a) @ d / (d @ d)
        pts = [v0] if 0 < v0 < 1 else None

    def f(v, k=None):
        diff = a + v * d - p
        val = np.exp(-0.5 * diff @ diff)
        return val if k is None else diff[k] ** 2 * val

    quad = dict(points=pts, epsabs=1e-16, epsrel=1e-12, limit=200)
    expected = integrate.quad(f, 0, 1, **quad)[0]
    expected_grad = [integrate.quad(f, 0, 1, args=(k,), **quad)[0] for k in range(2)]
    k, grad = segment_point(a, d, p, eval_gradient=True)
    assert_close(k, expected)
    assert_close(grad, expected_grad)


@pytest.mark.parametrize("length", [0.03, 0.049, _SHORT * 1.001, 0.25, 0.5, 3.0, 30.0])
@pytest.mark.parametrize("beyond", [-7.9, -5.0, -2.0, 2.0, 5.0, 7.9])
@pytest.mark.parametrize("aside", [0.0, 0.5, 3.0])
def test_segment_point_tails_relative_to_value(length, beyond, aside):
    # Points past either end along the segment's line (and beside it): the value is a
    # difference of two far tails of the normal CDF, which must keep its relative digits
    # up to the cut-off. Below _SHORT (0.03, 0.049) the Gauss-Legendre rule must keep them
    # too, and at 0.25 the closed form, where that rule would not.
    a = np.array([1.5, -0.5])
    u = np.array([0.8, 0.6])
    d = length * u
    along = beyond if beyond < 0 else length + beyond
    p = a + along * u + aside * np.array([-0.6, 0.8])
    expected = _segment_point_by_quad(a, d, p)
    assert segment_point(a, d, p) == pytest.approx(expected, rel=1e-11, abs=0.0)


@pytest.mark.parametrize("length", [0.0, 1e-6, 0.3, 0.999, 1.0, 1.001, 2.5, 40.0])
def test_segment_self_matches_quad(length):
    def f(t, power):
        return 2.0 * (1.0 - t) * t**power * np.exp(-0.5 * (length * t) ** 2)

    quad = dict(epsabs=1e-16, epsrel=1e-13, limit=200)
    k, h = segment_self(np.array(length), eval_gradient=True)
    assert_close(k, integrate.quad(f, 0, 1, args=(0,), **quad)[0], rtol=1e-12)
    assert_close(h, integrate.quad(f, 0, 1, args=(2,), **quad)[0], rtol=1e-10)


@pytest.mark.parametrize("case", ["long crossing", "shared start (one pose)", "two short"])
def test_gradient_matches_nested_quad(case):
    s1, s2 = CASES_2D[case]
    _, grad = pair_integrals(s1[None], s2[None], gradient="aniso")
    expected = [reference_nested_quad(s1, s2, gradient_dim=k) for k in range(2)]
    assert_close(grad[0], expected)


def _random_segments(rng, n, dim, box=4.0, max_length=8.0, point_fraction=0.3):
    start = rng.uniform(0, box, (n, dim))
    direction = rng.normal(size=(n, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    length = rng.uniform(0, max_length, n)
    length[rng.random(n) < point_fraction] = 0.0
    return np.hstack([start, start + length[:, None] * direction])


@pytest.mark.parametrize("dim", [2, 3])
def test_gradient_matches_finite_differences(dim):
    rng = np.random.default_rng(10 + dim)
    X = _random_segments(rng, 25, dim)
    scale = rng.uniform(0.4, 1.2, dim)
    _, grad = integral_kernel(X, length_scale=scale, eval_gradient=True, anisotropic=True)
    _, grad_iso = integral_kernel(X, length_scale=0.7, eval_gradient=True)
    eps = 1e-5
    for k in range(dim + 1):
        if k < dim:
            step = np.zeros(dim)
            step[k] = eps
            plus = integral_kernel(X, length_scale=scale * np.exp(step))
            minus = integral_kernel(X, length_scale=scale * np.exp(-step))
            analytic = grad[..., k]
        else:  # isotropic: one log length scale for all dimensions
            plus = integral_kernel(X, length_scale=0.7 * np.exp(eps))
            minus = integral_kernel(X, length_scale=0.7 * np.exp(-eps))
            analytic = grad_iso[..., 0]
        fd = (plus - minus) / (2 * eps)
        assert_close(analytic, fd, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_kernel_matrix_symmetric_psd(dim):
    rng = np.random.default_rng(20 + dim)
    X = _random_segments(rng, 300, dim, box=6.0)
    K = integral_kernel(X, length_scale=0.5)
    assert np.array_equal(K, K.T)
    assert np.linalg.eigvalsh(K).min() >= -1e-9 * len(X)


def test_blocks_do_not_change_the_result():
    rng = np.random.default_rng(3)
    X = _random_segments(rng, 40, 2)
    Y = _random_segments(rng, 17, 2)
    K, G = integral_kernel(X, length_scale=[0.6, 0.9], eval_gradient=True, anisotropic=True)
    K_small, G_small = integral_kernel(
        X, length_scale=[0.6, 0.9], eval_gradient=True, anisotropic=True, block_size=7
    )
    np.testing.assert_allclose(K_small, K, rtol=1e-14, atol=1e-300)
    np.testing.assert_allclose(G_small, G, rtol=1e-14, atol=1e-300)
    KXY = integral_kernel(X, Y, length_scale=0.8)
    KYX = integral_kernel(Y, X, length_scale=0.8, block_size=5)
    assert_close(KXY, KYX.T, rtol=1e-12, atol=1e-15)
    # Off-diagonal entries of K(X, X) equal K(X, Y) with Y = X (the diagonal is closed form).
    KXX = integral_kernel(X, X.copy(), length_scale=0.8)
    assert_close(KXX, integral_kernel(X, length_scale=0.8), rtol=1e-9, atol=1e-14)


@pytest.mark.parametrize("dim", [2, 3])
def test_few_points_untiled_equal_tiled(dim):
    # A few query points against an expert's rows fit in one chunk and skip the tiling of
    # the points; tiled in chunks of 16 pairs, every value is the same to the bit, the
    # pairs beyond the cut-off (8 length scales, in a box 40 m wide) exactly 0 in both.
    rng = np.random.default_rng(50 + dim)
    Y = _random_segments(rng, 60, dim, box=40.0, max_length=3.0, point_fraction=0.3)
    Y[:5, dim:] = Y[:5, :dim] + 0.01  # short segments: Gauss-Legendre
    near = Y[rng.choice(60, 5, replace=False), :dim] + rng.normal(0.0, 0.3, (5, dim))
    points = np.vstack([near, rng.uniform(0, 40.0, (3, dim))])
    P = np.hstack([points, points])
    whole = integral_kernel(P, Y, length_scale=0.7)
    tiled = integral_kernel(P, Y, length_scale=0.7, block_size=16)
    np.testing.assert_array_equal(whole, tiled)
    assert np.any(whole == 0.0) and np.any(whole > 1e-3)


def test_point_pairs_are_the_rbf_kernel():
    rng = np.random.default_rng(4)
    P = rng.normal(size=(30, 3))
    X = np.hstack([P, P])
    scale = np.array([0.5, 1.0, 2.0])
    diff = (P[:, None, :] - P[None, :, :]) / scale
    expected = np.exp(-0.5 * (diff**2).sum(-1))
    K, G = integral_kernel(X, length_scale=scale, eval_gradient=True, anisotropic=True)
    # Pairs further apart than the cutoff are zero, and only those.
    cut = np.exp(-0.5 * _CUTOFF**2)
    assert np.all((K == 0) == (expected < cut))
    assert_close(K, expected, rtol=1e-14, atol=cut)
    assert_close(G, diff**2 * expected[..., None], rtol=1e-14, atol=cut * _CUTOFF**2)


@pytest.mark.parametrize("order", range(1, len(_GL_MAX_WINDOW) + 1))
def test_gauss_legendre_table(order):
    # The tabulated window for each order integrates a unit Gaussian centred anywhere to
    # 1e-12 of its mass, and the next-lower order would not.
    window = _GL_MAX_WINDOW[order - 1]
    centres = np.linspace(-10, window + 10, 2001)
    exact = np.sqrt(2 * np.pi) * (ndtr(window - centres) - ndtr(-centres))

    def worst_error(n):
        x = window * _GL_NODES[n, :n]
        w = window * _GL_WEIGHTS[n, :n]
        approx = np.exp(-0.5 * (x[None, :] - centres[:, None]) ** 2) @ w
        return np.abs(approx - exact).max() / np.sqrt(2 * np.pi)

    assert gauss_legendre_order(np.array([window]))[0] == order
    assert worst_error(order) <= 1e-12
    if order > 1:
        assert worst_error(order - 1) > 1e-12


def _mixed_segments(rng, n, dim, box, max_length):
    """Points, short segments (below _SHORT) and long segments, shuffled."""
    X = _random_segments(rng, n, dim, box=box, max_length=max_length, point_fraction=0.4)
    short = rng.random(n) < 0.15
    step = rng.normal(size=(short.sum(), dim))
    step *= rng.uniform(1e-4, _SHORT, (short.sum(), 1)) / np.linalg.norm(step, axis=1)[:, None]
    X[short, dim:] = X[short, :dim] + step
    return X


def _scaled_distances(X, Y, scale):
    """Squared distances of pairs with a point, by dense sampling of the segment (NaN else)."""
    dim = X.shape[1] // 2
    t = np.linspace(0.0, 1.0, 20001)[:, None]

    def samples(s):
        return s[None, :dim] if np.all(s[:dim] == s[dim:]) else s[:dim] + t * (s[dim:] - s[:dim])

    out = np.full((len(X), len(Y)), np.nan)
    for i, s in enumerate(X / np.r_[scale, scale]):
        for j, r in enumerate(Y / np.r_[scale, scale]):
            ps, qs = samples(s), samples(r)
            if len(ps) == 1 or len(qs) == 1:
                out[i, j] = ((ps - qs) ** 2).sum(-1).min()
    return out


@pytest.mark.parametrize("dim", [2, 3])
def test_point_fast_path_matches_general_path_cross(dim):
    # Mixed blocks spread over more than the cut-off: point rows against beams, hits and short
    # segments, and segment rows against point columns, all through the closed forms.
    rng = np.random.default_rng(30 + dim)
    box = 25.0 if dim == 2 else 14.0  # about as many near pairs as far ones
    X = _mixed_segments(rng, 120, dim, box=box, max_length=12.0)
    Y = _mixed_segments(rng, 70, dim, box=box, max_length=12.0)
    scale = rng.uniform(0.6, 1.4, dim)
    K = integral_kernel(X, Y, length_scale=scale)
    K_ref = integral_kernel(X, Y, length_scale=scale, _fast=False)
    cut = np.exp(-0.5 * _CUTOFF**2)
    assert_close(K, K_ref, rtol=1e-10, atol=cut)
    assert np.count_nonzero(K) > 0.2 * K.size and np.count_nonzero(K == 0) > 0.2 * K.size
    np.testing.assert_allclose(
        integral_kernel(Y, X, length_scale=scale), K.T, rtol=1e-12, atol=1e-300
    )


@pytest.mark.parametrize("anisotropic", [False, True])
@pytest.mark.parametrize("dim", [2, 3])
def test_point_fast_path_matches_general_path_symmetric(dim, anisotropic):
    rng = np.random.default_rng(40 + dim)
    X = _mixed_segments(rng, 150, dim, box=20.0, max_length=10.0)
    scale = rng.uniform(0.7, 1.3, dim) if anisotropic else 1.1
    K, G = integral_kernel(X, length_scale=scale, eval_gradient=True, anisotropic=anisotropic)
    K_ref, G_ref = integral_kernel(
        X, length_scale=scale, eval_gradient=True, anisotropic=anisotropic, _fast=False
    )
    cut = np.exp(-0.5 * _CUTOFF**2)
    assert np.array_equal(K, K.T)
    assert_close(K, K_ref, rtol=1e-10, atol=cut)
    assert_close(G, G_ref, rtol=1e-10, atol=cut * _CUTOFF**2)
    assert np.count_nonzero(K == 0) > 0.2 * K.size


def test_point_pairs_beyond_cutoff_are_exactly_zero():
    # For every pair with a point, K is exactly 0 beyond _CUTOFF and positive within it
    # (distances from an independent dense sampling of each segment).
    rng = np.random.default_rng(50)
    X = _mixed_segments(rng, 40, 2, box=30.0, max_length=15.0)
    Y = _mixed_segments(rng, 30, 2, box=30.0, max_length=15.0)
    K = integral_kernel(X, Y, length_scale=1.0)
    dist2 = _scaled_distances(X, Y, np.ones(2))
    with_point = ~np.isnan(dist2)
    margin = 0.01  # above the sampling resolution of the reference distance
    far = with_point & (dist2 > (_CUTOFF + margin) ** 2)
    near = with_point & (dist2 < (_CUTOFF - margin) ** 2)
    assert far.sum() > 100 and near.sum() > 100
    assert np.all(K[far] == 0.0)
    assert np.all(K[near] > 0.0)


def test_dense_point_tiles_match_general_path():
    # Query grids much finer than the length scale put thousands of points into one tile,
    # more than a chunk of pairs: the chunks must still cover every pair exactly once.
    g = np.linspace(0.0, 3.0, 60)
    P = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    X = np.hstack([P, P])
    Y = np.array(
        [[0.5, 0.5, 2.5, 2.0], [1.0, 1.0, 1.0, 1.0], [2.0, 0.1, 2.01, 0.1], [-9.0, 1.0, -8.0, 1.0]]
    )
    K = integral_kernel(X, Y, length_scale=0.9, block_size=500)
    K_ref = integral_kernel(X, Y, length_scale=0.9, _fast=False)
    assert_close(K, K_ref, rtol=1e-10, atol=1e-300)


def test_diagonal_of_points_is_exactly_one():
    rng = np.random.default_rng(60)
    X = _mixed_segments(rng, 50, 2, box=5.0, max_length=3.0)
    is_point = np.all(X[:, :2] == X[:, 2:], axis=1)
    K = integral_kernel(X, length_scale=0.4)
    assert np.all(np.diag(K)[is_point] == 1.0)
    assert np.all(np.diag(K)[~is_point] < 1.0)


@pytest.mark.parametrize("dim", [2, 3, 5])
@pytest.mark.parametrize("offset", [0.0, 1e3])
def test_loose_upper_bound_bounds_the_exact_bound(dim, offset):
    # Random segments, points, segments that touch end to end or cross, and coordinates far
    # from the origin: the screening bound may never fall below pair_upper_bound.
    rng = np.random.default_rng(10 * dim)
    s1 = rng.uniform(-4, 4, size=(60, 2 * dim))
    s2 = rng.uniform(-4, 4, size=(80, 2 * dim))
    s2[:10, dim:] = s2[:10, :dim]  # points
    s1[:5, dim:] = s1[:5, :dim]
    s2[10:20, :dim] = s1[10:20, dim:]  # touching at an end
    s2[20:30, :dim] = s1[20:30, dim:]
    s2[20:30, dim:] = s1[20:30, dim:] + 2.0 * (s1[20:30, dim:] - s1[20:30, :dim])  # collinear
    # Long, nearly parallel segments (the area term cancels) and parallel ones side by side
    # (where the distance to the other's line is the whole gap).
    direction = rng.normal(size=dim)
    direction /= np.linalg.norm(direction)
    for i, length in zip(range(30, 40), np.geomspace(20.0, 2e4, 10), strict=True):
        tilt = 1e-6 * rng.normal(size=dim)
        s1[i] = np.r_[s1[i, :dim], s1[i, :dim] + length * direction]
        s2[i] = np.r_[s1[i, :dim] + 0.5, s1[i, :dim] + 0.5 + length * (direction + tilt)]
        s2[i + 10] = np.r_[s1[i, :dim] + 0.3, s1[i, dim:] + 0.3]
    s1, s2 = s1 + offset, s2 + offset
    loose = loose_upper_bound(s1, s2)
    ii, jj = np.meshgrid(np.arange(len(s1)), np.arange(len(s2)), indexing="ij")
    exact, _ = pair_upper_bound(s1[ii.ravel()], s2[jj.ravel()])
    exact = exact.reshape(loose.shape)
    assert np.all(loose >= exact)
    # Not vacuous: a useful screen rules out most far pairs.
    if dim == 2:
        assert np.mean(loose < 2.0 * exact + 1e-3) > 0.5


def _directions_at_angles(rng, n, dim, log10_angles):
    """Random unit directions ``e1``, and ``e2`` at angles log-uniform in ``10 **
    log10_angles`` (low, high) from them."""
    e1 = rng.normal(size=(n, dim))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    f = rng.normal(size=(n, dim))
    f -= np.sum(f * e1, axis=1, keepdims=True) * e1
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    angle = 10.0 ** rng.uniform(*log10_angles, size=(n, 1))
    return e1, np.cos(angle) * e1 + np.sin(angle) * f


@pytest.mark.parametrize("dim", [2, 3, 5])
def test_pair_upper_bound_bounds_the_integral(dim):
    # Any dimension: the estimator checks feed 10-column (5-D segment) rows.
    # Random pairs of segments, points and near-parallel segments: the bound must hold.
    rng = np.random.default_rng(dim)
    n = 3000
    s1 = rng.uniform(-3, 3, size=(n, 2 * dim))
    s2 = rng.uniform(-3, 3, size=(n, 2 * dim))
    s2[:500, dim:] = s2[:500, :dim]  # points
    s2[500:1000] = s1[500:1000] + rng.normal(scale=0.3, size=(500, 2 * dim))
    s1[1000:1200, dim:] = s1[1000:1200, :dim] + 12.0 * rng.normal(size=(200, dim))
    # Long, nearly parallel segments crossing at a random point: the closest-approach
    # determinant cancels here, and a distance that is not zero would cut the bound.
    m = 1000
    length = rng.uniform(1.0, 200.0, size=(m, 2))
    e1, e2 = _directions_at_angles(rng, m, dim, (-9, -1))
    cross = rng.normal(size=(m, dim))
    u, v = rng.uniform(size=(2, m, 1))
    a1, a2 = cross - u * length[:, :1] * e1, cross - v * length[:, 1:] * e2
    s1 = np.vstack([s1, np.hstack([a1, a1 + length[:, :1] * e1])])
    s2 = np.vstack([s2, np.hstack([a2, a2 + length[:, 1:] * e2])])
    k, _ = pair_integrals(s1, s2)
    bound, dist2 = pair_upper_bound(s1, s2)
    assert np.all(k <= bound * (1 + 1e-9) + 1e-15)
    np.testing.assert_allclose(dist2[-m:], 0.0, atol=1e-12)
    # The bound is not vacuous: within 2x of the value for most close pairs.
    close = k > 0.1
    assert np.median(k[close] / bound[close]) > 0.5
    np.testing.assert_allclose(
        np.sqrt(dist2[:500]),
        [
            np.min(
                np.linalg.norm(
                    s1[i, :dim]
                    + np.linspace(0, 1, 20001)[:, None] * (s1[i, dim:] - s1[i, :dim])
                    - s2[i, :dim],
                    axis=1,
                )
            )
            for i in range(500)
        ],
        atol=1e-3,
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_pair_upper_bound_of_crossing_beams_counts_their_strips(dim):
    # Beams of one scan fan out from the sensor: they cross at their ends, where the two
    # whole lines' integral 2 pi / (L1 L2 |sin t|) is about twice the value. Nearly
    # parallel segments end to end, far from the origin, cross far away, where the strips'
    # ends round badly: the bound must hold there too.
    rng = np.random.default_rng(dim)
    m = 2000
    origin = rng.uniform(-1e3, 1e3, size=(m, dim))
    u, v = rng.normal(size=(2, m, dim))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    la, lb = rng.uniform(1.0, 10.0, size=(2, m, 1))
    fan1, fan2 = np.hstack([origin, origin + la * u]), np.hstack([origin, origin + lb * v])
    n = 4000
    e1, e2 = _directions_at_angles(rng, n, dim, (-4, -0.5))
    length = rng.uniform(0.5, 50.0, size=(n, 2))
    a1 = rng.uniform(-1e4, 1e4, size=(n, dim))
    b1 = a1 + length[:, :1] * e1
    a2 = b1 + rng.uniform(0.0, 3.0, size=(n, 1)) * e1 + rng.normal(scale=0.3, size=(n, dim))
    s1 = np.vstack([fan1, np.hstack([a1, b1])])
    s2 = np.vstack([fan2, np.hstack([a2, a2 + length[:, 1:] * e2])])
    k, _ = pair_integrals(s1, s2)
    bound, _ = pair_upper_bound(s1, s2)
    crossing = crossing_upper_bound(s1, s2)
    assert np.all(k <= bound * (1 + 1e-9) + 1e-15)
    assert np.all(k <= crossing * (1 + 1e-9) + 1e-15)
    assert np.all(bound <= crossing)
    # On the fans, half the whole lines' integral: each strip holds half the mass.
    d1, d2 = fan1[:, dim:] - origin, fan2[:, dim:] - origin
    lines = (
        2
        * np.pi
        / np.sqrt(np.sum(d1 * d1, axis=1) * np.sum(d2 * d2, axis=1) - np.sum(d1 * d2, axis=1) ** 2)
    )
    crossed = lines < 0.5  # where the lines' integral bounds the pair, not its length
    np.testing.assert_allclose(np.median(bound[:m][crossed] / lines[crossed]), 0.5, atol=0.01)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("anisotropic", [False, True])
def test_point_row_pairs_equal_the_kernel_matrix(dim, anisotropic):
    # Listed pairs of points and rows (points, short and long segments, some beyond the
    # cut-off) take the values of the whole matrix, to the bit, in any order.
    rng = np.random.default_rng(60 + dim + 2 * anisotropic)
    Y = _random_segments(rng, 50, dim, box=30.0, max_length=3.0, point_fraction=0.3)
    Y[:5, dim:] = Y[:5, :dim] + 0.01
    points = np.vstack(
        [Y[rng.choice(50, 6), :dim] + rng.normal(0, 0.3, (6, dim)), rng.uniform(0, 30.0, (4, dim))]
    )
    scale = rng.uniform(0.4, 1.5, dim) if anisotropic else 0.7
    whole = integral_kernel(np.hstack([points, points]), Y, length_scale=scale)
    p, r = np.nonzero(np.ones_like(whole, dtype=bool))
    order = rng.permutation(p.size)
    values = point_row_pairs(points, Y, p[order], r[order], length_scale=scale)
    np.testing.assert_array_equal(values, whole[p[order], r[order]])
    assert np.any(whole == 0.0) and np.any(whole > 1e-3)


def test_point_point_is_the_rbf_kernel():
    from sklearn.gaussian_process.kernels import RBF

    rng = np.random.default_rng(70)
    P, Q = rng.normal(size=(2, 40, 3))
    expected = RBF(length_scale=1.0)(P, Q)
    np.testing.assert_allclose(point_point(P[:, None, :], Q[None, :, :]), expected, rtol=1e-13)
    # A segment of no length is its start point.
    np.testing.assert_allclose(
        segment_point(P, np.zeros_like(P), Q), np.diag(expected), rtol=1e-13, atol=0.0
    )


@pytest.mark.parametrize("excess", [41.0, 50.0, 79.0])
@pytest.mark.parametrize("side", ["before", "after"])
@pytest.mark.parametrize("aside", [0.0, 1.0])
def test_segment_point_far_end_term(excess, side, aside):
    # A point off one end of the segment, the squared distance to the far end ``excess``
    # above that to the near end: the far end's erfc term is about exp(-excess / 2) of the
    # value, 1e-9 at 41, 1e-18 at 79: kept to 1e-12 of the value, whatever the far end.
    r = 2.0
    length = np.sqrt(r * r + excess) - r
    u = np.array([0.6, 0.8])
    a = np.array([0.4, -0.3])
    d = length * u
    along = -r if side == "before" else length + r
    p = a + along * u + aside * np.array([-0.8, 0.6])
    expected = _segment_point_by_quad(a, d, p)
    assert segment_point(a, d, p) == pytest.approx(expected, rel=1e-12, abs=0.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_point_against_segment_of_length_short(dim):
    # A segment of exactly _SHORT, where Gauss-Legendre hands over to the closed form,
    # against points beside, past and on it: every path with a point gives the integral.
    a = np.zeros(dim)
    a[0] = 0.5
    d = np.zeros(dim)
    d[-1] = _SHORT  # from 0 to _SHORT: the difference of the ends is _SHORT exactly
    row = np.r_[a, a + d][None]
    offsets = np.zeros((4, dim))
    offsets[0, 0], offsets[1, -1], offsets[2, :2], offsets[3, -1] = 0.3, 2.0, [1.0, -0.7], -0.01
    points = a + offsets
    expected = [_segment_point_by_quad(a, d, p) for p in points]
    P = np.hstack([points, points])
    zeros = np.zeros(len(points), dtype=int)
    for k in (
        segment_point(a, d, points),
        integral_kernel(P, row, length_scale=1.0)[:, 0],
        integral_kernel(row, P, length_scale=1.0)[0],
        integral_kernel(np.vstack([P, row]), length_scale=1.0)[:-1, -1],
        point_row_pairs(points, row, np.arange(len(points)), zeros),
    ):
        assert_close(k, expected, rtol=1e-12)


def _pairs_at_the_cutoff(dim, gap):
    """Rows X, Y (scaled units) whose paired rows are ``gap`` apart, one of each kind:
    point-point, point past the far end of a short and of a long segment, point beside a
    long segment, short-short, short-long (end to end) and long-long (side by side)."""
    e0, e1 = np.eye(dim)[0], np.eye(dim)[1]
    c = np.r_[0.25, -0.5, 1.0][:dim]
    short, long = 0.03, 5.0

    def row(start, end):
        return np.r_[c + start, c + end]

    def pt(x):
        return row(x, x)

    pairs = [
        (pt(0 * e0), pt(gap * e1)),
        (pt((short + gap) * e0), row(0 * e0, short * e0)),
        (pt((long + gap) * e0), row(0 * e0, long * e0)),
        (pt(2.5 * e0 + gap * e1), row(0 * e0, long * e0)),
        (row(0 * e0, short * e0), row(gap * e1, short * e0 + gap * e1)),
        (row((long + gap) * e0, (long + gap + short) * e0), row(0 * e0, long * e0)),
        (row(0 * e0, long * e0), row(gap * e1 + e0, (long + 1) * e0 + gap * e1)),
    ]
    return np.array([x for x, _ in pairs]), np.array([y for _, y in pairs])


@pytest.mark.parametrize("dim", [2, 3])
def test_pairs_at_the_cutoff(dim):
    # Every kind of pair 1e-3 inside the cut-off is positive, 1e-3 beyond it exactly 0,
    # gradients included: in K(X, Y), K(Y, X) and K of both, in pair_integrals (pairs
    # with a segment) and in point_row_pairs.
    for gap, inside in ((_CUTOFF - 1e-3, True), (_CUTOFF + 1e-3, False)):
        X, Y = _pairs_at_the_cutoff(dim, gap)
        n = len(X)
        both_K, both_G = integral_kernel(np.vstack([X, Y]), eval_gradient=True, anisotropic=True)
        values = [
            integral_kernel(X, Y).diagonal(),
            integral_kernel(Y, X).diagonal(),
            both_K[np.arange(n), n + np.arange(n)],
        ]
        grads = [both_G[np.arange(n), n + np.arange(n)]]
        k, g = pair_integrals(X[1:], Y[1:], gradient="aniso")
        values.append(k)
        grads.append(g)
        k, g = pair_integrals(Y[1:], X[1:], gradient="iso")
        values.append(k)
        grads.append(g)
        is_point = np.all(X[:, :dim] == X[:, dim:], axis=1)
        values.append(
            point_row_pairs(
                X[is_point, :dim], Y, np.arange(is_point.sum()), np.flatnonzero(is_point)
            )
        )
        for v in values:
            assert np.all(v > 0.0) if inside else np.all(v == 0.0), (gap, v)
        for v in grads:  # (pairs, dims); a dimension along which the pair lies gives 0
            assert np.all(v.sum(axis=1) > 0.0) if inside else np.all(v == 0.0), (gap, v)


@pytest.mark.parametrize("dim", [2, 3])
def test_pairs_exactly_at_the_cutoff_are_kept(dim):
    # Only pairs further apart than _CUTOFF are 0: pairs of each kind exactly _CUTOFF apart
    # (coordinates that are sums of powers of 2, so that every distance is exact) are not,
    # in K(X, Y), K(Y, X) and K of both, in pair_integrals (pairs with a segment) and in
    # point_row_pairs.
    e0, e1 = np.eye(dim)[0], np.eye(dim)[1]
    short = 1.0 / 32.0  # below _SHORT

    def row(start, end):
        return np.r_[start, end]

    def pt(x):
        return row(x, x)

    pairs = [
        (pt(0 * e0), pt(_CUTOFF * e1)),
        (pt((1.0 + _CUTOFF) * e0), row(0 * e0, 1.0 * e0)),
        (pt((short + _CUTOFF) * e0), row(0 * e0, short * e0)),
        (pt(2.0 * e0 + _CUTOFF * e1), row(0 * e0, 4.0 * e0)),
        (row(0 * e0, 1.0 * e0), row((1.0 + _CUTOFF) * e0, (2.0 + _CUTOFF) * e0)),
        (row(0 * e0, 4.0 * e0), row(_CUTOFF * e1, 4.0 * e0 + _CUTOFF * e1)),
        (row(0 * e0, short * e0), row((short + _CUTOFF) * e0, (2 * short + _CUTOFF) * e0)),
    ]
    X, Y = np.array([x for x, _ in pairs]), np.array([y for _, y in pairs])
    n = len(X)
    for k in (
        integral_kernel(X, Y).diagonal(),
        integral_kernel(Y, X).diagonal(),
        integral_kernel(np.vstack([X, Y]))[np.arange(n), n + np.arange(n)],
        pair_integrals(X[1:], Y[1:])[0],
        pair_integrals(Y[1:], X[1:])[0],
        point_row_pairs(X[:4, :dim], Y, np.arange(4), np.arange(4)),
    ):
        assert np.all(k > 0.0), k


@pytest.mark.parametrize("swap", [False, True])
def test_crossing_bound_takes_the_smaller_strip(swap):
    # A T: the second segment starts on the middle of the first, at right angles. The
    # first's strip holds nearly all the normal mass, the second's half of it, as does
    # their rectangle: the bound is the value, not twice it, whichever comes first.
    s1, s2 = np.array([[-20.0, 0.0, 20.0, 0.0]]), np.array([[0.0, 0.0, 0.0, 20.0]])
    if swap:
        s1, s2 = s2, s1
    k, _ = pair_integrals(s1, s2)
    for bound in (crossing_upper_bound(s1, s2), pair_upper_bound(s1, s2)[0]):
        assert k[0] <= bound[0] <= 1.05 * k[0]


def _normal_mass(lo, hi):
    """Standard normal mass of ``[lo, hi]`` by adaptive quadrature, relative to its value."""
    value = integrate.quad(lambda x: np.exp(-0.5 * x * x), lo, hi, epsabs=0.0, epsrel=1e-13)[0]
    return value / np.sqrt(2.0 * np.pi)


@pytest.mark.parametrize("cross_at", [-7.5, -6.9, 7.5, 8.5, 8.9])
def test_crossing_bound_of_perpendicular_segments_keeps_its_digits_in_the_tails(cross_at):
    # A unit segment and one 20 long at right angles, whose lines cross past an end of the
    # first: the integral is 2 pi / (L1 L2) times the normal masses of the two strips, that
    # of the first in a far tail (1e-15 near the cut-off), that of the second all but 1e-23.
    # The bound is that product without the second mass: to its relative digits.
    s1 = np.array([[0.0, 0.0, 1.0, 0.0]])
    s2 = np.array([[cross_at, -10.0, cross_at, 10.0]])
    expected = 2.0 * np.pi / 20.0 * _normal_mass(-cross_at, 1.0 - cross_at)
    k, _ = pair_integrals(s1, s2)
    assert k[0] == pytest.approx(expected, rel=1e-7, abs=0.0)
    for bound in (crossing_upper_bound(s1, s2), pair_upper_bound(s1, s2)[0]):
        assert bound[0] == pytest.approx(expected, rel=1e-9, abs=0.0)


def _pair_by_erf_and_quad(s1, s2):
    """Mean of exp(-|p - q|^2 / 2) over two 2-D segments: the first segment's integral in
    closed form (erf) at each point of the second, that one by adaptive quadrature, all in
    the first segment's frame (no large coordinates cancel)."""
    a1, a2 = s1[:2], s2[:2]
    len1, len2 = np.linalg.norm(s1[2:] - a1), np.linalg.norm(s2[2:] - a2)
    e1, e2 = (s1[2:] - a1) / len1, (s2[2:] - a2) / len2
    n1 = np.array([-e1[1], e1[0]])
    along0, across0 = (a2 - a1) @ e1, (a2 - a1) @ n1
    cos_t, sin_t = e2 @ e1, e2 @ n1

    def f(u):
        along, across = along0 + u * cos_t, across0 + u * sin_t
        return np.exp(-0.5 * across * across) * (ndtr(len1 - along) - ndtr(-along))

    # The integrand lives where the second segment runs beside the first one.
    ends = sorted([-along0 / cos_t, (len1 - along0) / cos_t])
    pts = np.clip(np.linspace(ends[0] - 12.0, ends[1] + 12.0, 61), 0.0, len2)
    edges = np.unique(np.r_[0.0, pts, len2])
    quad = dict(epsabs=1e-15, epsrel=1e-12, limit=200)
    pieces = zip(edges[:-1], edges[1:], strict=True)
    total = sum(integrate.quad(f, lo, hi, **quad)[0] for lo, hi in pieces)
    return np.sqrt(2.0 * np.pi) * total / (len1 * len2)


def test_strip_slack_keeps_the_crossing_bound_above_the_integral():
    # Nearly parallel segments (|sin t| about 1e-3) 1e4 from the origin, a short one beside
    # one 2.4e4 (2.7e4) long: the strips' ends come from t1, t2, which cancel here. Without
    # the slack that widens the strips, the bound of these two pairs falls 6e-10 below the
    # integral (with this platform's rounding); with it, it stays 2e-4 above. The reference
    # agrees with a 40-digit mpmath evaluation to about 1e-12; pair_integrals is 4e-8 above
    # the integral here, which is why comparisons with it cannot see the slack.
    s1 = np.array([
        [10149.006734178163, -4491.561094054192, 10148.569894423707, -4492.290800074641],
        [9353.693050052705, 8413.975777076756, 9354.577624068042, 8415.345068083083],
    ])  # fmt: skip
    s2 = np.array([
        [16112.236230668768, 5499.219880767117, 3713.616327376558, -15271.049267245544],
        [1808.285632456149, -3291.611362861344, 16508.653863301923, 19515.164625278958],
    ])  # fmt: skip
    expected = np.array([_pair_by_erf_and_quad(a, b) for a, b in zip(s1, s2, strict=True)])
    assert np.all(expected > 1e-6)  # the integrals are not negligible
    for bound in (crossing_upper_bound(s1, s2), pair_upper_bound(s1, s2)[0]):
        assert np.all(bound >= expected * (1.0 + 1e-10))


@pytest.mark.parametrize("swap", [False, True])
def test_loose_upper_bound_uses_either_line(swap):
    # A short segment whose line crosses a long one, 10 length scales off the long one's
    # line: only the distance to that line keeps the screen below exp(-10**2 / 2).
    s1, s2 = np.array([[0.0, 10.0, 0.0, 11.0]]), np.array([[-50.0, 0.0, 50.0, 0.0]])
    if swap:
        s1, s2 = s2, s1
    exact, dist2 = pair_upper_bound(s1, s2)
    assert dist2[0] == pytest.approx(100.0)
    # Without that distance the screen is the length term, sqrt(2 pi) / 100.
    assert exact[0] <= loose_upper_bound(s1, s2)[0, 0] <= np.exp(-0.5 * 9.99**2)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("offset", [0.0, 1e3])
def test_loose_upper_bound_of_segments_end_to_end_is_their_gap(dim, offset):
    # Collinear segments 3 and 2 long, 5 apart end to end: the bounding circles' gap is the
    # segments' distance, and neither line separates them (each lies on the other's line).
    rng = np.random.default_rng(90 + dim)
    e = rng.normal(size=dim)
    e /= np.linalg.norm(e)
    a = rng.uniform(-1.0, 1.0, dim) + offset
    s1 = np.r_[a, a + 3.0 * e][None]
    s2 = np.r_[a + 8.0 * e, a + 10.0 * e][None]
    exact, dist2 = pair_upper_bound(s1, s2)
    assert dist2[0] == pytest.approx(25.0)
    loose = loose_upper_bound(s1, s2)[0, 0]
    assert exact[0] <= loose <= np.exp(-0.5 * 4.999**2) * np.sqrt(2.0 * np.pi) / 3.0


@pytest.mark.parametrize("dim", [2, 3])
def test_loose_upper_bound_of_collinear_segments_far_from_the_origin(dim):
    # Segments end to end on one line, 1e6 length scales from the origin: their bounding
    # circles touch, and the dense products that give the circles' gap round to about 1e-4
    # there; the screen must still not fall below the exact bound (whose distance is 0).
    rng = np.random.default_rng(95 + dim)
    n = 50
    e = rng.normal(size=(n, dim))
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    a = 1e6 + rng.uniform(-10.0, 10.0, (n, dim))
    joint = a + rng.uniform(0.5, 5.0, (n, 1)) * e
    s1 = np.hstack([a, joint])
    s2 = np.hstack([joint, joint + rng.uniform(0.5, 5.0, (n, 1)) * e])
    exact, dist2 = pair_upper_bound(s1, s2)
    assert np.all(dist2 == 0.0)
    assert np.all(loose_upper_bound(s1, s2).diagonal() >= exact)


@pytest.mark.parametrize("dim", [2, 3])
def test_tiled_points_hold_every_pair_within_the_cutoff(dim):
    # Points on a grid finer than the tiles, around a point, a short and two long segments,
    # with many pairs just inside and just beyond the cut-off; chunks of 64 pairs tile the
    # points. Every pair takes its value from pair_integrals, 0 beyond the cut-off.
    step = 0.3 if dim == 2 else 0.9
    g = np.arange(-12.0, 12.01, step)
    P = np.stack(np.meshgrid(*[g] * dim), -1).reshape(-1, dim)
    rows = [[0.0, 0.0, 0.0, 0.0], [0.1, 0.2, 0.13, 0.21], [-3.0, -1.0, 4.0, 2.0], [2, 5, 2, -4]]
    Y = np.array(rows, dtype=float)
    if dim == 3:
        Y = np.hstack(
            [Y[:, :2], [[0.0], [0.1], [1.0], [-2.0]], Y[:, 2:], [[0.0], [0.1], [2.0], [3.0]]]
        )
    X = np.hstack([P, P])
    K = integral_kernel(X, Y, length_scale=1.0, block_size=64)
    ii, jj = np.meshgrid(np.arange(len(X)), np.arange(len(Y)), indexing="ij")
    expected = pair_integrals(X[ii.ravel()], Y[jj.ravel()])[0].reshape(K.shape)
    # pair_integrals does not cut pairs of two points.
    expected[np.sum(P * P, axis=1) > _CUTOFF**2, 0] = 0.0
    near = (expected > 0.0) & (expected < np.exp(-0.5 * (_CUTOFF - 0.5) ** 2))
    assert near.sum() > 200
    np.testing.assert_array_equal(K == 0.0, expected == 0.0)
    assert_close(K, expected, rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_diagonal_gradient_matches_quad(dim):
    # K(X, X)'s diagonal gradient: along a segment of direction d (scaled), the integrand's
    # squared difference in dimension k is (u - v)**2 d_k**2, so the gradient is d_k**2 times
    # 2 int_0^1 (1 - t) t**2 exp(-|d|**2 t**2 / 2) dt.
    rng = np.random.default_rng(80 + dim)
    direction = rng.normal(size=(4, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    start = rng.uniform(-1.0, 1.0, (4, dim))
    X = np.hstack([start, start + [[0.0], [0.03], [0.7], [2.4]] * direction])
    for scale, anisotropic in ((rng.uniform(0.5, 1.5, dim), True), (np.full(dim, 0.8), False)):
        _, G = integral_kernel(X, length_scale=scale, eval_gradient=True, anisotropic=anisotropic)
        for i, s in enumerate(X):
            d = (s[dim:] - s[:dim]) / scale
            length = np.linalg.norm(d)

            def f(t, length=length):
                return 2.0 * (1.0 - t) * t**2 * np.exp(-0.5 * (length * t) ** 2)

            expected = d * d * integrate.quad(f, 0, 1, epsabs=0.0, epsrel=1e-13)[0]
            if not anisotropic:
                expected = [expected.sum()]
            assert_close(G[i, i], expected, rtol=1e-11, atol=0.0)
