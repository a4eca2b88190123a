"""Integrals of the squared-exponential kernel along segments.

All functions work in *scaled* coordinates: every coordinate divided by its length scale, so that
the point kernel is ``exp(-|p - q|**2 / 2)``. A segment is ``a + u * d`` with ``u`` in ``[0, 1]``
and the integral kernel is the average of the point kernel over both segments::

    k(s1, s2) = int_0^1 int_0^1 exp(-|a1 + u d1 - a2 - v d2|**2 / 2) du dv

so a point against itself gives 1 and a zero-length segment reduces to the point kernel.

Evaluation (see :func:`pair_integrals` and the driver :func:`integral_kernel`):

- point-point: the closed form.
- segment-point and the inner integral of segment-segment: ``|w - v d|**2`` is a quadratic in
  ``v``, so the integral is a Gaussian factor times a difference of normal CDFs. It is written with
  ``erfc`` of non-negative arguments only, so that neither tail of the CDF cancels.
- in a kernel matrix, every pair with a point row or column (query cells, hits) takes these
  closed forms, vectorised over chunks of candidate pairs that a tiling of the points finds
  within the cut-off; only segment-segment pairs go through the quadrature below.
- segment-segment: the inner integral (over the longer segment) is analytic, the outer one (over
  the shorter segment) is Gauss-Legendre on the window where the integrand is not negligible, with
  a node count that grows with the window length (:data:`_GL_MAX_WINDOW`). Viewed along the outer
  segment, the integrand is a mixture of unit-width Gaussians, so the rule that integrates every
  unit Gaussian to 1e-12 (relative to its mass) integrates the mixture as well.
- two segments both shorter than :data:`_SHORT`: a fixed tensor Gauss-Legendre rule (the analytic
  inner form divides by the length and would lose digits there).

Gradients are with respect to the log length scale of each dimension. Differentiating the
integrand, ``d/d log l_k exp(-sum_j (dx_j / l_j)**2 / 2) = (dx_k / l_k)**2 * exp(...)``, so the
gradient is the integral of the squared scaled difference in dimension ``k`` times the point
kernel; the inner integral of that is analytic too (first and second moments of a truncated
Gaussian).
"""

import numpy as np
from scipy.special import erfc, erfcx, ndtr

_SQRT_2PI = np.sqrt(2.0 * np.pi)
_SQRT_HALF = np.sqrt(0.5)

# Pairs of segments further apart than this (scaled) are set to zero: exp(-8**2 / 2) < 1.3e-14.
_CUTOFF = 8.0
# The outer window is where the integrand is within exp(-6**2 / 2) < 2e-8 of its largest value
# (see _outer_windows).
_WINDOW_MARGIN = 6.0
# Below this scaled length the analytic inner integral loses more than ~1/_SHORT of its digits.
_SHORT = 0.05
# Gauss-Legendre order for pairs of short segments (error < 1e-12 for lengths below _SHORT).
_SHORT_ORDER = 5

# _GL_MAX_WINDOW[n - 1]: the longest interval (scaled units) on which n-point Gauss-Legendre
# integrates a unit Gaussian, centred anywhere, with an error below 5e-13 of its mass
# (found by bisection; tests/test_integrals.py checks it). Longer windows are split into panels.
# fmt: off
_GL_MAX_WINDOW = np.array([
    0.000311, 0.01784, 0.1077, 0.3027, 0.597, 0.9704, 1.403, 1.877, 2.383, 2.909, 3.451, 4.004,
    4.564, 5.13, 5.699, 6.27, 6.842, 7.416, 7.988, 8.562, 9.131, 9.702, 10.27, 10.84, 11.41,
    11.98, 12.55, 13.11, 13.67, 14.23, 14.8, 15.35,
])
# fmt: on
_GL_MAX_ORDER = len(_GL_MAX_WINDOW)


def _gauss_legendre_table(max_order):
    """Nodes and weights on [0, 1] for orders 1..max_order, padded rows of a 2-D table."""
    nodes = np.zeros((max_order + 1, max_order))
    weights = np.zeros((max_order + 1, max_order))
    for n in range(1, max_order + 1):
        x, w = np.polynomial.legendre.leggauss(n)
        nodes[n, :n] = 0.5 * (x + 1.0)
        weights[n, :n] = 0.5 * w
    return nodes, weights


_GL_NODES, _GL_WEIGHTS = _gauss_legendre_table(_GL_MAX_ORDER)


def gauss_legendre_order(window):
    """Number of Gauss-Legendre nodes for an outer window of the given scaled length.

    Parameters
    ----------
    window : ndarray
        Window lengths in scaled units, at most ``_GL_MAX_WINDOW[-1]``.

    Returns
    -------
    order : ndarray of int
        The smallest order whose error on any unit Gaussian is below 5e-13 of its mass.
    """
    return np.searchsorted(_GL_MAX_WINDOW, window) + 1


def point_point(p, q):
    """Squared-exponential kernel between points in scaled coordinates.

    Parameters
    ----------
    p, q : ndarray of shape (..., n_dims)

    Returns
    -------
    k : ndarray of shape (...)
        ``exp(-|p - q|**2 / 2)``.
    """
    diff = np.asarray(p, dtype=float) - np.asarray(q, dtype=float)
    return np.exp(-0.5 * np.einsum("...i,...i->...", diff, diff))


def _inner_scalars(f0, dw, length, ends=True):
    """Line-point integral from the scalars of ``f(v) = |w - v d|**2``.

    ``f0 = |w|**2``, ``dw = w . d``, ``length = |d|`` (>= _SHORT). Returns
    ``M0 = int_0^1 exp(-f(v)/2) dv``, the pieces the moments need and ``min f`` (the squared
    distance between the point and the segment).

    With ``v0 = dw / length**2`` the closest point, ``h**2 = f0 - dw**2 / length**2`` and
    ``x1 = -length * v0``, ``x2 = x1 + length``::

        M0 = sqrt(2 pi) / length * exp(-h**2 / 2) * (Phi(x2) - Phi(x1))

    The difference of CDFs is that of upper tails, ``Q(x1) - Q(x2)`` with
    ``Q(x) = erfc(x / sqrt 2) / 2``, or ``Q(-x2) - Q(-x1)`` by symmetry: whichever puts the
    segment's middle at or beyond the closest point, so that its lower end ``lo`` is at
    least ``-length / 2`` and neither tail cancels (the upper end ``lo + length`` is
    positive). ``erfc`` is accurate relative to its value far into the tail (it underflows
    only where ``exp(-x**2 / 2)`` does), so the Gaussian factor ``exp(-h**2 / 2)`` can stay
    outside: half the cost of the equivalent ``erfcx(z) exp(-f / 2)`` form. The closest
    point of the segment is ``max(lo, 0)`` along it from the foot of the perpendicular.

    ``e0 = exp(-f0 / 2)`` and ``e1 = exp(-f(1) / 2)``, which only the gradients need, are
    None unless ``ends``.
    """
    inv_len = 1.0 / length
    x1 = -dw * inv_len
    x2 = x1 + length
    h2 = np.maximum(f0 - x1 * x1, 0.0)
    lo = np.where(x1 + x2 >= 0.0, x1, -x2)
    diff = erfc(lo * _SQRT_HALF) - erfc((lo + length) * _SQRT_HALF)
    m0 = (0.5 * _SQRT_2PI) * inv_len * np.exp(-0.5 * h2) * diff
    beyond = np.maximum(lo, 0.0)
    fmin = h2 + beyond * beyond
    if not ends:
        return m0, x1, x2, None, None, h2, inv_len, fmin
    f1 = f0 - 2.0 * dw + length * length
    return m0, x1, x2, np.exp(-0.5 * f0), np.exp(-0.5 * f1), h2, inv_len, fmin


def _inner_gradient_iso(m0, x1, x2, e0, e1, h2, inv_len):
    """``int_0^1 |w - v d|**2 exp(-f(v)/2) dv`` (the isotropic gradient integrand).

    With ``t = v - v0`` and ``w - v d = w_perp - t d`` (``w_perp . d = 0``) this is
    ``h**2 M0 + |d|**2 M2``, and integrating by parts
    ``|d|**2 M2 = M0 - [t exp(-f/2)]_{t=-v0}^{1-v0} = M0 - (x2 e1 - x1 e0) / |d|``.
    """
    return (1.0 + h2) * m0 - (x2 * e1 - x1 * e0) * inv_len


def _inner_gradient_aniso(m0, x1, x2, e0, e1, inv_len, w, d):
    """Per-dimension ``int_0^1 (w_k - v d_k)**2 exp(-f(v)/2) dv``, shape (..., n_dims).

    ``(w_k - v d_k)**2 = wp_k**2 - 2 wp_k d_k t + d_k**2 t**2`` with ``wp = w - v0 d``,
    ``M1 = (e0 - e1) / |d|**2`` and ``M2`` as in :func:`_inner_gradient_iso`.
    """
    inv_len2 = inv_len * inv_len
    v0 = -x1 * inv_len
    m1 = (e0 - e1) * inv_len2
    m2 = (m0 - (x2 * e1 - x1 * e0) * inv_len) * inv_len2
    wp = w - v0[..., None] * d
    return (wp * wp) * m0[..., None] - 2.0 * (wp * d) * m1[..., None] + (d * d) * m2[..., None]


def segment_point(a, d, p, *, eval_gradient=False):
    """Average of the point kernel along a segment, against a point (scaled coordinates).

    ``int_0^1 exp(-|a + v d - p|**2 / 2) dv`` in closed form (:func:`_inner_scalars`, erfc
    of non-negative arguments); segments shorter than the cancellation threshold ``_SHORT`` use
    Gauss-Legendre on the (then nearly flat) integrand. No cut-off is applied.

    Parameters
    ----------
    a, d : ndarray of shape (..., n_dims)
        Segment start and direction (end minus start).
    p : ndarray of shape (..., n_dims)
        Point.
    eval_gradient : bool, default=False
        Also return, per dimension k, ``int (a_k + v d_k - p_k)**2 exp(...) dv``.

    Returns
    -------
    k : ndarray of shape (...)
    grad : ndarray of shape (..., n_dims), only when ``eval_gradient``

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap._integrals import segment_point
    >>> round(float(segment_point(np.zeros(2), np.array([1e-9, 0.0]), np.zeros(2))), 12)
    1.0
    """
    a, d, p = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (a, d, p)))
    dim = a.shape[-1]
    w = (p - a).reshape(-1, dim)
    k, grad, _ = _point_segment(w, d.reshape(-1, dim), "aniso" if eval_gradient else None)
    k = k.reshape(a.shape[:-1])
    if eval_gradient:
        return k, grad.reshape(a.shape)
    return k


def segment_self(length, *, eval_gradient=False):
    """Integral kernel of a segment with itself, closed form.

    ``int_0^1 int_0^1 exp(-(u - v)**2 L**2 / 2) du dv = 2 int_0^1 (1 - t) exp(-L**2 t**2 / 2) dt``.

    Parameters
    ----------
    length : ndarray
        Scaled segment lengths ``L``.
    eval_gradient : bool, default=False
        Also return ``H(L) = 2 int_0^1 (1 - t) t**2 exp(-L**2 t**2 / 2) dt``; the gradient with
        respect to log l_k is ``(d_k / l_k)**2 * H``.

    Returns
    -------
    k : ndarray
    H : ndarray, only when ``eval_gradient``

    Examples
    --------
    >>> from skoccmap._integrals import segment_self
    >>> float(segment_self(0.0))
    1.0
    """
    length = np.asarray(length, dtype=float)
    # Points (the query cells) are 1 and H = 2 / 12; the series and the closed form are
    # evaluated only where they are needed.
    k = np.ones_like(length)
    h = np.full_like(length, 2.0 / 12.0)
    small = (length > 0.0) & (length < 1.0)
    if np.any(small):
        # Series for short segments: exp(-a2 t^2/2) = sum (-a2/2)^j t^(2j) / j!, and
        # 2 int_0^1 (1-t) t^m dt = 2 / ((m+1)(m+2)).
        a2s = length[small] ** 2
        k_series = np.zeros_like(a2s)
        h_series = np.zeros_like(a2s)
        term = np.ones_like(a2s)
        for j in range(25):
            k_series += term * 2.0 / ((2 * j + 1) * (2 * j + 2))
            h_series += term * 2.0 / ((2 * j + 3) * (2 * j + 4))
            term = term * (-0.5 * a2s) / (j + 1)
        k[small], h[small] = k_series, h_series
    long = length >= 1.0
    if np.any(long):
        # Closed form for longer ones: I0 = int_0^1 exp(-a2 t^2/2) dt, I1 = int t exp(.), etc.
        big = length[long]
        ebig = np.exp(-0.5 * big * big)
        i0 = _SQRT_2PI / big * (0.5 - 0.5 * erfcx(big * _SQRT_HALF) * ebig)
        i1 = -np.expm1(-0.5 * big * big) / (big * big)
        k[long] = 2.0 * (i0 - i1)
        if eval_gradient:
            i2 = (i0 - ebig) / (big * big)
            i3 = (2.0 / big**4) * (1.0 - ebig * (1.0 + 0.5 * big * big))
            h[long] = 2.0 * (i2 - i3)
    if not eval_gradient:
        return k
    return k, h


def _point_pairs(s1, s2, dim, gradient):
    diff2 = (s1[:, :dim] - s2[:, :dim]) ** 2
    k = np.exp(-0.5 * diff2.sum(axis=1))
    return k, diff2 * k[:, None]


def _short_pairs(s1, s2, dim, gradient):
    """Tensor Gauss-Legendre on the point kernel for pairs of short segments, 0 beyond
    ``_CUTOFF`` as every other kind of pair."""
    x, w = _GL_NODES[_SHORT_ORDER, :_SHORT_ORDER], _GL_WEIGHTS[_SHORT_ORDER, :_SHORT_ORDER]
    a1, d1 = s1[:, :dim], s1[:, dim:] - s1[:, :dim]
    a2, d2 = s2[:, :dim], s2[:, dim:] - s2[:, :dim]
    # diff[p, i, j, k] = a1 + x_i d1 - a2 - x_j d2
    diff = (
        (a1 - a2)[:, None, None, :]
        + x[None, :, None, None] * d1[:, None, None, :]
        - x[None, None, :, None] * d2[:, None, None, :]
    )
    diff2 = diff * diff
    kern = np.exp(-0.5 * diff2.sum(axis=-1)) * (w[:, None] * w[None, :])
    k = kern.sum(axis=(1, 2))
    far = _segment_dist2(a1, d1, a2, d2) > _CUTOFF**2
    k[far] = 0.0
    if gradient is None:
        return k, None
    grad = np.einsum("pij,pijk->pk", kern, diff2)
    grad[far] = 0.0
    return k, grad


def _point_point_values(w, gradient):
    """Point kernel from differences ``w`` (n, n_dims): (k, grad, dist2)."""
    if gradient is None:
        # The same sums as ``(w * w).sum(axis=1)``, in the same order, in half the time:
        # numpy's reduction over a row of two or three is slow.
        dist2 = _dot(w, w)
        return np.exp(-0.5 * dist2), None, dist2
    ww = w * w
    dist2 = ww.sum(axis=1)
    k = np.exp(-0.5 * dist2)
    if gradient == "aniso":
        return k, ww * k[:, None], dist2
    return k, (dist2 * k)[:, None], dist2


def _point_short_values(w, d, gradient):
    """Point against segments shorter than ``_SHORT``: Gauss-Legendre, (k, grad, dist2).

    The ``_SHORT_ORDER``-point rule is the tensor rule of :func:`_short_pairs` with one factor
    collapsed on the point.
    """
    x = _GL_NODES[_SHORT_ORDER, :_SHORT_ORDER]
    wt = _GL_WEIGHTS[_SHORT_ORDER, :_SHORT_ORDER]
    diff = w[:, None, :] - x[None, :, None] * d[:, None, :]
    diff2 = diff * diff
    kern = np.exp(-0.5 * diff2.sum(axis=-1)) * wt
    dist2 = _point_segment_dist2(w, np.zeros_like(w), d, _dot(d, d))
    if gradient is None:
        return kern.sum(axis=1), None, dist2
    grad = np.einsum("pn,pnk->pk", kern, diff2)
    if gradient == "iso":
        grad = grad.sum(axis=1, keepdims=True)
    return kern.sum(axis=1), grad, dist2


def _point_long_values(w, d, gradient, length=None):
    """Point against segments of length ``_SHORT`` or more: closed form, (k, grad, dist2)."""
    if length is None:
        length = np.sqrt(_dot(d, d))
    f0, dw = _dot(w, w), _dot(w, d)
    m0, x1, x2, e0, e1, h2, inv_len, dist2 = _inner_scalars(f0, dw, length, gradient is not None)
    if gradient == "aniso":
        return m0, _inner_gradient_aniso(m0, x1, x2, e0, e1, inv_len, w, d), dist2
    if gradient == "iso":
        return m0, _inner_gradient_iso(m0, x1, x2, e0, e1, h2, inv_len)[:, None], dist2
    return m0, None, dist2


def _length_kinds(length):
    """Masks of the rows that are points, short segments (below ``_SHORT``, Gauss-Legendre)
    and long ones (the closed form), from the rows' scaled lengths."""
    return length == 0.0, (length > 0.0) & (length < _SHORT), length >= _SHORT


def _point_segment(w, d, gradient):
    """Integral kernel of points ``p`` against segments ``a + v d``, from ``w = p - a`` and ``d``.

    Vectorised over rows (n, n_dims): zero-length segments by the point kernel, short ones
    (below ``_SHORT``) by Gauss-Legendre, the rest by the closed form of :func:`_inner_scalars`.

    Returns (k, grad, dist2): grad is None, (n, 1) for "iso" or (n, n_dims) for "aniso";
    ``dist2`` is the squared distance from the point to the segment, for the cut-off.
    """
    n, dim = w.shape
    k = np.empty(n)
    grad = None if gradient is None else np.empty((n, dim if gradient == "aniso" else 1))
    dist2 = np.empty(n)
    length = np.sqrt(_dot(d, d))
    values_of = (
        lambda i: _point_point_values(w[i], gradient),
        lambda i: _point_short_values(w[i], d[i], gradient),
        lambda i: _point_long_values(w[i], d[i], gradient, length[i]),
    )
    for mask, values in zip(_length_kinds(length), values_of, strict=True):
        if not np.any(mask):
            continue
        i = slice(None) if np.all(mask) else np.flatnonzero(mask)
        k[i], g, dist2[i] = values(i)
        if grad is not None:
            grad[i] = g
    return k, grad, dist2


def _point_segment_pairs(s1, s2, dim, gradient):
    """Pairs in which exactly one row is a point: the closed form, zero beyond ``_CUTOFF``."""
    len1 = _dot(s1[:, dim:] - s1[:, :dim], s1[:, dim:] - s1[:, :dim])
    first_is_point = (len1 == 0.0)[:, None]
    p = np.where(first_is_point, s1[:, :dim], s2[:, :dim])
    seg = np.where(first_is_point, s2, s1)
    k, grad, dist2 = _point_segment(p - seg[:, :dim], seg[:, dim:] - seg[:, :dim], gradient)
    far = dist2 > _CUTOFF**2
    k[far] = 0.0
    if grad is not None:
        grad[far] = 0.0
    return k, grad


def _dot(x, y):
    """Dot product over the last axis, e.g. row-wise for (n, D) arrays (column loop: D is 2
    or 3, faster than einsum). The operands broadcast; the order of the operations is that
    of the row-wise case, so a broadcast (n1, n2) product equals it to the bit."""
    out = x[..., 0] * y[..., 0]
    for k in range(1, x.shape[-1]):
        out += x[..., k] * y[..., k]
    return out


def _point_segment_dist2(p, a, d, dd):
    """Squared distance from points ``p`` to segments ``a + v d`` (``dd = |d|**2``)."""
    w = p - a
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.clip(np.where(dd > 0.0, _dot(w, d) / dd, 0.0), 0.0, 1.0)
    r = w - v[:, None] * d
    return _dot(r, r)


def _segment_dist2(a1, d1, a2, d2):
    """Squared distance between segments ``a1 + u d1`` and ``a2 + v d2``, u, v in [0, 1].

    The squared distance is a convex quadratic on the unit square: its minimum is at the lines'
    closest approach when that lies inside, else on an edge (an endpoint against a segment).
    The closest approach is solved with the part of ``d2`` orthogonal to ``d1``: the textbook
    determinant ``|d1|^2 |d2|^2 - (d1.d2)^2`` cancels for nearly parallel segments.
    """
    dd1, dd2 = _dot(d1, d1), _dot(d2, d2)
    best = np.minimum.reduce(
        [
            _point_segment_dist2(a1, a2, d2, dd2),
            _point_segment_dist2(a1 + d1, a2, d2, dd2),
            _point_segment_dist2(a2, a1, d1, dd1),
            _point_segment_dist2(a2 + d2, a1, d1, dd1),
        ]
    )
    w = a2 - a1
    with np.errstate(divide="ignore", invalid="ignore"):
        d2_perp = d2 - (_dot(d2, d1) / dd1)[:, None] * d1
        w_perp = w - (_dot(w, d1) / dd1)[:, None] * d1
        den = _dot(d2_perp, d2_perp)
        v = -_dot(w_perp, d2_perp) / den
        u = _dot(w + v[:, None] * d2, d1) / dd1
    # NaN (a zero-length segment) fails every comparison.
    inside = (den > 0.0) & (u > 0.0) & (u < 1.0) & (v > 0.0) & (v < 1.0)
    if np.any(inside):
        i = np.flatnonzero(inside)
        diff = w[i] + v[i, None] * d2[i] - u[i, None] * d1[i]
        best[i] = np.minimum(best[i], _dot(diff, diff))
    return best


def pair_upper_bound(s1, s2):
    """Upper bound of :func:`pair_integrals` for paired segment rows, in scaled coordinates.

    Cheap (no quadrature), for pruning a search for the most similar segment. With ``r`` the
    distance between the segments, lengths ``L1``, ``L2`` and angle ``t`` between them::

        k <= exp(-r**2 / 2) * min(1, sqrt(2 pi) / max(L1, L2))
        k <= 2 pi / (L1 L2 |sin t|) * min(P1, P2)

    The first holds because along a segment of length ``L`` at distance at least ``r``
    from a point, the point kernel integrates to at most ``sqrt(2 pi) exp(-r**2 / 2)``.
    For the second, the integrand over the two lines' arc lengths is ``exp(-d**2 / 2)``
    (``d`` the lines' distance) times a bivariate normal density of total mass ``2 pi /
    |sin t|``, centred on the lines' closest approach, at arc lengths ``(s0, u0)`` along
    the two segments; the segments take the mass of a rectangle, at most that of either
    strip: ``P1 = Phi((L1 - s0) |sin t|) - Phi(-s0 |sin t|)`` (the marginal of the first
    arc length has standard deviation ``1 / |sin t|``), and ``P2`` alike. Beams that cross
    near their ends (beams of one scan, fanning out from the sensor) score a fraction of the
    whole lines' integral.

    Parameters
    ----------
    s1, s2 : ndarray of shape (n_pairs, 2 * n_dims)
        Segment rows ``[start, end]``, already divided by the length scales.

    Returns
    -------
    bound : ndarray of shape (n_pairs,)
    dist2 : ndarray of shape (n_pairs,)
        Squared (scaled) distance between the segments.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap._integrals import pair_integrals, pair_upper_bound
    >>> s1, s2 = np.array([[0.0, 0.0, 4.0, 0.0]]), np.array([[1.0, 0.5, 3.0, 0.5]])
    >>> bound, _ = pair_upper_bound(s1, s2)
    >>> bool(pair_integrals(s1, s2)[0][0] <= bound[0])
    True
    """
    dim = s1.shape[1] // 2
    d1 = s1[:, dim:] - s1[:, :dim]
    d2 = s2[:, dim:] - s2[:, :dim]
    dist2 = _segment_dist2(s1[:, :dim], d1, s2[:, :dim], d2)
    len1_2, len2_2 = _dot(d1, d1), _dot(d2, d2)
    with np.errstate(divide="ignore"):  # two points: no length, no bound from it
        bound = np.exp(-0.5 * dist2) * np.minimum(
            1.0, _SQRT_2PI / np.sqrt(np.maximum(len1_2, len2_2))
        )
    crossing = _crossing_bound(s1[:, :dim] - s2[:, :dim], d1, d2, len1_2, len2_2)
    return np.minimum(bound, crossing), dist2


def crossing_upper_bound(s1, s2):
    """The second bound of :func:`pair_upper_bound`, ``2 pi / (L1 L2 |sin t|) * min(P1,
    P2)`` (``inf`` for parallel segments): no distances, about a third of its cost.

    Parameters
    ----------
    s1, s2 : ndarray of shape (n_pairs, 2 * n_dims)
        Segment rows ``[start, end]``, already divided by the length scales.

    Returns
    -------
    bound : ndarray of shape (n_pairs,)

    Examples
    --------
    Two beams from one sensor at right angles: about half the two whole lines' ``2 pi / (L1
    L2)`` (each strip holds ``Phi(L) - Phi(0)`` of the mass).

    >>> import numpy as np
    >>> from skoccmap._integrals import crossing_upper_bound, pair_integrals
    >>> s1, s2 = np.array([[0.0, 0.0, 4.0, 0.0]]), np.array([[0.0, 0.0, 0.0, 5.0]])
    >>> bound = crossing_upper_bound(s1, s2)
    >>> round(float(bound[0] / (2 * np.pi / 20)), 3)
    0.5
    >>> bool(pair_integrals(s1, s2)[0][0] <= bound[0])
    True
    """
    dim = s1.shape[1] // 2
    d1 = s1[:, dim:] - s1[:, :dim]
    d2 = s2[:, dim:] - s2[:, :dim]
    return _crossing_bound(s1[:, :dim] - s2[:, :dim], d1, d2, _dot(d1, d1), _dot(d2, d2))


def _crossing_bound(w, d1, d2, len1_2, len2_2):
    """:func:`crossing_upper_bound` of segments ``a + t d`` (``w = a1 - a2``, squared
    lengths ``len1_2``, ``len2_2``), shared with :func:`pair_upper_bound`."""
    cross = _dot(d1, d2)
    area = np.sqrt(np.maximum(len1_2 * len2_2 - cross * cross, 0.0))
    mass = _strip_mass(w, d1, d2, len1_2, len2_2, cross, area)
    with np.errstate(divide="ignore"):
        return 2.0 * np.pi / area * mass


def _strip_mass(w, d1, d2, len1_2, len2_2, cross, area):
    """Upper bound of the normal mass of the rectangle of two segments' arc lengths (see
    :func:`pair_upper_bound`): the smaller of the masses of its two strips, 1 where the
    lines are nearly parallel. ``w`` is the start of the first segment less that of the
    second; ``area`` is ``L1 L2 |sin t|``."""
    len1, len2 = np.sqrt(len1_2), np.sqrt(len2_2)
    with np.errstate(divide="ignore", invalid="ignore"):
        sin_t = area / (len1 * len2)
        # Closest approach of the lines a1 + t1 d1, a2 + t2 d2, in units of the segments.
        wd1, wd2 = _dot(w, d1), _dot(w, d2)
        area2 = area * area
        t1 = (cross * wd2 - len2_2 * wd1) / area2
        t2 = (len1_2 * wd2 - cross * wd1) / area2
        # The strips widened by the rounding of their ends (cancellation in t1, t2 and
        # area grows as 1 / sin t), in standard units: L1 |sin t| = area / L2.
        slack = 16.0 * np.finfo(float).eps * (np.sqrt(_dot(w, w)) + len1 + len2) / sin_t
        s1, s2 = area / len2, area / len1
        mass1 = _normal_interval(-t1 * s1 - slack, (1.0 - t1) * s1 + slack)
        mass2 = _normal_interval(-t2 * s2 - slack, (1.0 - t2) * s2 + slack)
        mass = np.minimum(mass1, mass2)
    # Nearly parallel lines cross far away, where rounding rules: no bound from the strips.
    return np.where((sin_t > 1e-3) & np.isfinite(mass), np.minimum(mass, 1.0), 1.0)


def _normal_interval(lo, hi):
    """``Phi(hi) - Phi(lo)`` for ``lo <= hi``, rounded up: from the tail nearer the
    interval, with the rounding of the two terms added, so that it never falls below the
    exact mass."""
    left = hi <= 0.0
    a = ndtr(np.where(left, lo, -hi))
    b = ndtr(np.where(left, hi, -lo))
    return (b - a) + 4.0 * np.finfo(float).eps * b


def loose_upper_bound(s1, s2):
    """An upper bound of :func:`pair_upper_bound` for every pair of rows of ``s1`` and ``s2``.

    The same two bounds, the second without its strip mass (``min(P1, P2) <= 1``), with
    the segments' distance replaced by a lower bound of it: the gap between their bounding
    circles (the distance of the midpoints less both half lengths) and, in 2-D, the
    distance from each segment to the other's line. A dense (n1, n2) matrix at a fraction
    of the cost of the exact distances, for screening which pairs need them.

    Parameters
    ----------
    s1 : ndarray of shape (n1, 2 * n_dims)
    s2 : ndarray of shape (n2, 2 * n_dims)
        Segment rows ``[start, end]``, already divided by the length scales.

    Returns
    -------
    bound : ndarray of shape (n1, n2)

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap._integrals import loose_upper_bound, pair_upper_bound
    >>> s1, s2 = np.array([[0.0, 0.0, 4.0, 0.0]]), np.array([[1.0, 3.0, 3.0, 3.5]])
    >>> bool(loose_upper_bound(s1, s2)[0, 0] >= pair_upper_bound(s1, s2)[0][0])
    True
    """
    dim = s1.shape[1] // 2
    d1 = s1[:, dim:] - s1[:, :dim]
    d2 = s2[:, dim:] - s2[:, :dim]
    m1 = s1[:, :dim] + 0.5 * d1
    m2 = s2[:, :dim] + 0.5 * d2
    len1_2, len2_2 = _dot(d1, d1), _dot(d2, d2)
    gap2 = np.maximum(_dot(m1, m1)[:, None] - 2.0 * (m1 @ m2.T) + _dot(m2, m2)[None, :], 0.0)
    gap = np.sqrt(gap2) - 0.5 * (np.sqrt(len1_2)[:, None] + np.sqrt(len2_2)[None, :])
    if dim == 2:
        # In the plane, also the distance from each segment to the other's line.
        gap = np.maximum(gap, _line_gap(s1[:, :2], d1, s2))
        gap = np.maximum(gap, _line_gap(s2[:, :2], d2, s1).T)
    # Shrunk by more than the rounding of either distance (the products above round to
    # about 1e-16 of the squared coordinates), so that it stays below the distance
    # pair_upper_bound computes for segments that touch.
    scale = 1.0 + np.sqrt(np.maximum(_dot(m1, m1)[:, None], _dot(m2, m2)[None, :]))
    gap = np.maximum(gap - 1e-7 * scale, 0.0)
    # Formed by _dot as in pair_upper_bound, so that the area term is the same to the bit
    # (a matrix product rounds differently, and nearly parallel long segments cancel).
    cross = _dot(d1[:, None, :], d2[None, :, :])
    with np.errstate(divide="ignore"):
        bound = np.exp(-0.5 * gap * gap) * np.minimum(
            1.0, _SQRT_2PI / np.sqrt(np.maximum(len1_2[:, None], len2_2[None, :]))
        )
        area = np.sqrt(np.maximum(len1_2[:, None] * len2_2[None, :] - cross * cross, 0.0))
        return np.minimum(bound, 2.0 * np.pi / area)


def _line_gap(a, d, s2):
    """Distance from each 2-D segment row of ``s2`` to the line ``a + t d`` of each row
    of ``a``, ``d`` (0 where the segment crosses the line or ``d`` is zero): (n1, n2)."""
    length = np.sqrt(_dot(d, d))
    with np.errstate(divide="ignore", invalid="ignore"):
        normal = np.where((length > 0.0)[:, None], d[:, ::-1] * [-1.0, 1.0] / length[:, None], 0.0)
    offset = _dot(normal, a)[:, None]
    start = normal @ s2[:, :2].T - offset
    end = normal @ s2[:, 2:].T - offset
    far = start * end > 0.0
    np.abs(start, out=start)
    np.abs(end, out=end)
    return np.where(far, np.minimum(start, end), 0.0)


def _sublevel(qa, qb, qc):
    """Interval ``{s : qa s**2 + qb s + qc <= 0}`` for ``qa >= 0`` (empty when lo > hi)."""
    disc = qb * qb - 4.0 * qa * qc
    sq = np.sqrt(np.maximum(disc, 0.0))
    # Stable roots: q / qa and qc / q, with no cancellation in q; qa -> 0 sends one root to inf.
    q = -0.5 * (qb + np.copysign(sq, qb))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(qa > 0.0, q / qa, np.copysign(np.inf, q))
        r2 = np.where(q != 0.0, qc / q, -np.copysign(np.inf, qb))
    lo, hi = np.minimum(r1, r2), np.maximum(r1, r2)
    constant = (qa == 0.0) & (qb == 0.0)
    lo = np.where(constant, np.where(qc <= 0.0, -np.inf, np.inf), np.where(disc >= 0, lo, np.inf))
    hi = np.where(constant, np.where(qc <= 0.0, np.inf, -np.inf), np.where(disc >= 0, hi, -np.inf))
    return lo, hi


def _outer_windows(a1, d1, len1, a2, d2):
    """Window ``[lo, hi]`` (in u) on the outer segment where the integrand matters.

    Along the outer segment (arc length s), the integrand is at most ``exp(-dist(s)**2 / 2)``
    with ``dist(s)`` the distance from ``a1 + s e1`` to the inner segment, a convex function.
    The window is where ``dist(s)**2 <= dmin**2 + _WINDOW_MARGIN**2`` (``dmin`` the segments'
    distance): outside it the integrand is below ``exp(-_WINDOW_MARGIN**2 / 2)`` times its peak
    and decays at least exponentially, so the neglected part is about that fraction of the value.
    ``dist(s)**2`` is the distance to an end of the inner segment or to its line (where the
    closest point is inside), so the window is the hull of three quadratic sublevel sets.

    Returns (lo, hi, keep) with ``keep`` False for pairs further apart than ``_CUTOFF``.
    """
    dmin2 = _segment_dist2(a1, d1, a2, d2)
    keep = dmin2 <= _CUTOFF**2
    thresh = dmin2 + _WINDOW_MARGIN**2
    with np.errstate(divide="ignore", invalid="ignore"):
        inv1 = np.where(len1 > 0.0, 1.0 / len1, 0.0)
        e1 = d1 * inv1[:, None]
        dd2 = _dot(d2, d2)
        w0 = a1 - a2
        lo = np.full(len1.shape, np.inf)
        hi = np.full(len1.shape, -np.inf)
        for end in (w0, w0 - d2):  # |a1 + s e1 - q|^2 for the inner segment's ends q
            b = _dot(end, e1)
            l_, h_ = _sublevel(np.ones_like(b), 2.0 * b, _dot(end, end) - thresh)
            lo, hi = np.minimum(lo, l_), np.maximum(hi, h_)
        # Distance to the inner line, where the closest point v0(s) lies in [0, 1].
        ed, wd = _dot(e1, d2), _dot(w0, d2)
        l_, h_ = _sublevel(
            np.maximum(1.0 - ed * ed / dd2, 0.0),
            2.0 * (_dot(w0, e1) - wd * ed / dd2),
            _dot(w0, w0) - wd * wd / dd2 - thresh,
        )
        # v0(s) = (wd + s ed) / dd2 in [0, 1]
        j1 = np.where(ed != 0.0, -wd / ed, np.where(wd >= 0.0, -np.inf, np.inf))
        j2 = np.where(ed != 0.0, (dd2 - wd) / ed, np.where(wd <= dd2, np.inf, -np.inf))
        l_ = np.maximum(l_, np.minimum(j1, j2))
        h_ = np.minimum(h_, np.maximum(j1, j2))
        valid = l_ <= h_
        lo = np.where(valid, np.minimum(lo, l_), lo)
        hi = np.where(valid, np.maximum(hi, h_), hi)
        lo = np.clip(lo, 0.0, len1) * inv1
        hi = np.clip(hi, 0.0, len1) * inv1
    # Points (len1 == 0) need a single node anywhere.
    hi = np.where(len1 > 0.0, np.maximum(hi, lo), 1.0)
    lo = np.where(len1 > 0.0, lo, 0.0)
    return lo, hi, keep


def _segment_pairs(s1, s2, dim, gradient, max_nodes):
    """Analytic inner integral over the longer segment, Gauss-Legendre over the shorter one."""
    a1, d1 = s1[:, :dim], s1[:, dim:] - s1[:, :dim]
    a2, d2 = s2[:, :dim], s2[:, dim:] - s2[:, :dim]
    len1 = np.sqrt(_dot(d1, d1))
    len2 = np.sqrt(_dot(d2, d2))
    # The kernel is symmetric in its arguments: integrate the shorter segment numerically.
    swap = len1 > len2
    if np.any(swap):
        a1, a2 = np.where(swap[:, None], a2, a1), np.where(swap[:, None], a1, a2)
        d1, d2 = np.where(swap[:, None], d2, d1), np.where(swap[:, None], d1, d2)
        len1, len2 = np.where(swap, len2, len1), np.where(swap, len1, len2)
    n_pairs = len(len1)
    k = np.zeros(n_pairs)
    n_grad = dim if gradient == "aniso" else 1
    grad = np.zeros((n_pairs, n_grad)) if gradient else None

    lo, hi, keep = _outer_windows(a1, d1, len1, a2, d2)
    pidx = np.flatnonzero(keep)
    if pidx.size == 0:
        return k, grad
    # Split long windows into equal panels short enough for the largest tabulated rule.
    span = (hi - lo)[pidx]
    window = span * len1[pidx]
    n_panels = np.maximum(np.ceil(window / _GL_MAX_WINDOW[-1]).astype(np.intp), 1)
    panel_pair = np.repeat(pidx, n_panels)
    first = np.cumsum(n_panels) - n_panels
    panel_rank = np.arange(panel_pair.size) - np.repeat(first, n_panels)
    panel_span = np.repeat(span / n_panels, n_panels)
    panel_lo = lo[panel_pair] + panel_rank * panel_span
    order = gauss_legendre_order(np.repeat(window / n_panels, n_panels))

    # Panels grouped by order, so that nodes form (panels, order) arrays that broadcast the
    # per-pair coefficients; at most max_nodes nodes at once bound the temporaries.
    by_order = np.argsort(order, kind="stable")
    orders, counts = np.unique(order[by_order], return_counts=True)
    start = 0
    for n_nodes, count in zip(orders, counts, strict=True):
        group = by_order[start : start + count]
        start += count
        step = max(1, max_nodes // int(n_nodes))
        for first in range(0, count, step):
            sel = group[first : first + step]
            _accumulate_panels(
                k,
                grad,
                panel_pair[sel],
                panel_lo[sel],
                panel_span[sel],
                int(n_nodes),
                a1,
                d1,
                a2,
                d2,
                len2,
                gradient,
            )
    return k, grad


def _accumulate_panels(k, grad, pair, lo, span, n_nodes, a1, d1, a2, d2, len2, gradient):
    """Add the n_nodes-point Gauss-Legendre sums of the given panels into k and grad."""
    x, w = _GL_NODES[n_nodes, :n_nodes], _GL_WEIGHTS[n_nodes, :n_nodes]
    u = lo[:, None] + span[:, None] * x  # (panels, nodes)
    # f0(u) = |w0 + u d1|^2 and dw(u) = d2 . (w0 + u d1) with w0 = a1 - a2: polynomials in u.
    w0, dd1, dd2 = a1[pair] - a2[pair], d1[pair], d2[pair]
    coef_b = 2.0 * _dot(w0, dd1)
    coef_c = _dot(dd1, dd1)
    f0 = _dot(w0, w0)[:, None] + u * (coef_b[:, None] + u * coef_c[:, None])
    dw = _dot(dd2, w0)[:, None] + u * _dot(dd2, dd1)[:, None]
    m0, x1, x2, e0, e1, h2, inv_len, _ = _inner_scalars(
        f0, dw, len2[pair][:, None], gradient is not None
    )
    np.add.at(k, pair, (m0 @ w) * span)
    if gradient is None:
        return
    if gradient == "iso":
        g = _inner_gradient_iso(m0, x1, x2, e0, e1, h2, inv_len)
        np.add.at(grad[:, 0], pair, (g @ w) * span)
        return
    wvec = w0[:, None, :] + u[:, :, None] * dd1[:, None, :]
    g = _inner_gradient_aniso(m0, x1, x2, e0, e1, inv_len, wvec, dd2[:, None, :])
    np.add.at(grad, pair, np.einsum("pnk,n->pk", g, w) * span[:, None])


def pair_integrals(s1, s2, gradient=None, max_nodes=1 << 16, *, _closed_form_points=True):
    """Integral kernel of paired segment rows, in scaled coordinates.

    This is the one hot loop: it sorts the pairs into point-point, point-segment, short
    segment and general segment pairs and evaluates each group vectorised.

    Parameters
    ----------
    s1, s2 : ndarray of shape (n_pairs, 2 * n_dims)
        Segment rows ``[start, end]``, already divided by the length scales.
    gradient : {None, "iso", "aniso"}, default=None
        None: values only. "iso": also the sum over dimensions of the log-length-scale gradient,
        shape (n_pairs, 1). "aniso": the gradient per dimension, shape (n_pairs, n_dims).
    max_nodes : int, default=65536
        Quadrature nodes evaluated at once (bounds the temporary memory).
    _closed_form_points : bool, default=True
        Private. False sends point-segment pairs through the general segment-segment
        quadrature (the reference for tests and benchmarks).

    Returns
    -------
    k : ndarray of shape (n_pairs,)
    grad : ndarray of shape (n_pairs, n_grad) or None

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap._integrals import pair_integrals
    >>> k, _ = pair_integrals(np.array([[0.0, 0.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 1.0, 0.0]]))
    >>> bool(np.isclose(k[0], np.exp(-0.5)))
    True
    """
    dim = s1.shape[1] // 2
    n_pairs = s1.shape[0]
    n_grad = dim if gradient == "aniso" else 1
    k = np.zeros(n_pairs)
    grad = np.zeros((n_pairs, n_grad)) if gradient else None
    d1 = s1[:, dim:] - s1[:, :dim]
    d2 = s2[:, dim:] - s2[:, :dim]
    len1 = np.sqrt(_dot(d1, d1))
    len2 = np.sqrt(_dot(d2, d2))
    longest = np.maximum(len1, len2)
    one_point = (np.minimum(len1, len2) == 0.0) & (longest > 0.0)
    if not _closed_form_points:
        one_point[:] = False
    groups = (
        (longest == 0.0, _point_pairs, {}),
        (one_point, _point_segment_pairs, {}),
        ((longest > 0.0) & (longest < _SHORT) & ~one_point, _short_pairs, {}),
        ((longest >= _SHORT) & ~one_point, _segment_pairs, {"max_nodes": max_nodes}),
    )
    for mask, func, kwargs in groups:
        idx = np.flatnonzero(mask)
        if idx.size == 0:
            continue
        k_g, grad_g = func(s1[idx], s2[idx], dim, gradient, **kwargs)
        k[idx] = k_g
        if gradient == "iso":
            grad[idx] = grad_g.sum(axis=1, keepdims=True) if grad_g.shape[1] > 1 else grad_g
        elif gradient == "aniso":
            grad[idx] = grad_g
    return k, grad


def _bounding_circles(Xs, dim):
    """Midpoints and half-lengths of segment rows."""
    mid = 0.5 * (Xs[:, :dim] + Xs[:, dim:])
    half = Xs[:, dim:] - mid
    return mid, np.sqrt(_dot(half, half))


def _circle_pairs(mid_x, rad_x, mid_y, rad_y, rows, cols, symmetric, block_size):
    """Pairs (rows[i], cols[j]) whose bounding circles are within ``_CUTOFF``, in blocks.

    Dense test of every pair, by blocks of rows of about ``block_size`` pairs. ``symmetric``
    (rows is cols, ascending): only pairs with the column after the row.
    """
    n, m = len(rows), len(cols)
    start = 0
    while start < n:
        first_col = start + 1 if symmetric else 0
        stop = min(n, start + max(1, block_size // max(m - first_col, 1)))
        r, c = rows[start:stop], cols[first_col:]
        gap2 = np.zeros((len(r), len(c)))
        for k in range(mid_x.shape[1]):
            gap2 += (mid_x[r, k, None] - mid_y[None, c, k]) ** 2
        reach = rad_x[r, None] + rad_y[None, c] + _CUTOFF
        near = gap2 <= reach * reach
        if symmetric:
            near &= np.arange(first_col, m)[None, :] > np.arange(start, stop)[:, None]
        rr, cc = np.nonzero(near)
        if rr.size:
            yield r[rr], c[cc]
        start = stop


def _point_tiles(P, size):
    """Points sorted into cubic cells of side ``size``: order, starts, counts, centres, radii.

    The centre and radius are those of each cell's bounding box of its points.
    """
    key = np.floor((P - P.min(axis=0)) / size)
    order = np.lexsort(key.T[::-1])
    key = key[order]
    new = np.any(key[1:] != key[:-1], axis=1)
    starts = np.flatnonzero(np.r_[True, new])
    counts = np.diff(np.r_[starts, len(P)])
    Ps = P[order]
    lo = np.minimum.reduceat(Ps, starts, axis=0)
    hi = np.maximum.reduceat(Ps, starts, axis=0)
    half = 0.5 * (hi - lo)
    return order, starts, counts, lo + half, np.sqrt(_dot(half, half))


def _tile_pairs(tiles, A, D, chunk):
    """Candidate pairs of tiled points and segments ``a + v d`` for the cut-off, in chunks.

    A (tile, segment) pair is kept when the distance from the tile's centre to the segment is
    within ``_CUTOFF`` plus the tile's radius, so every pair of a point and a segment within
    ``_CUTOFF`` is a candidate (with a few beyond it). Yields (point index, segment index)
    arrays of about ``chunk`` pairs (more only where one tile holds more points).
    """
    order, starts, counts, centre, radius = tiles
    n_tiles, m = len(starts), len(A)
    dd = _dot(D, D)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_dd = np.where(dd > 0.0, 1.0 / dd, 0.0)
    step = max(1, chunk // max(m, 1))
    tt, cc = [], []
    for t0 in range(0, n_tiles, step):
        c = centre[t0 : t0 + step]
        w = [c[:, k, None] - A[None, :, k] for k in range(A.shape[1])]
        v = w[0] * D[None, :, 0]
        for k in range(1, A.shape[1]):
            v += w[k] * D[None, :, k]
        np.clip(v * inv_dd, 0.0, 1.0, out=v)
        dist2 = (w[0] - v * D[None, :, 0]) ** 2
        for k in range(1, A.shape[1]):
            dist2 += (w[k] - v * D[None, :, k]) ** 2
        reach = radius[t0 : t0 + step, None] + _CUTOFF
        t, j = np.nonzero(dist2 <= reach * reach)
        tt.append(t + t0)
        cc.append(j)
    tt, cc = np.concatenate(tt), np.concatenate(cc)
    n_pairs = counts[tt]
    ends = np.cumsum(n_pairs)
    # Cut the candidate list where the running pair count crosses multiples of chunk.
    total = ends[-1] if ends.size else 0
    cuts = np.searchsorted(ends, np.arange(chunk, total, chunk), side="right")
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, len(tt)], strict=True):
        if hi <= lo:
            continue
        cnt = n_pairs[lo:hi]
        first = ends[lo:hi] - cnt - (ends[lo - 1] if lo else 0)
        pos = np.repeat(starts[tt[lo:hi]] - first, cnt) + np.arange(cnt.sum())
        yield order[pos], np.repeat(cc[lo:hi], cnt)


# Side (scaled units) of the cells that group points for the cut-off test, and the pairs
# evaluated at once on the point paths. A chunk is a few dozen arrays of this many
# elements: large enough that numpy's per-call overhead, which holds the GIL, stays small
# next to the loops, which release it (a mixture's experts predict in threads), and small
# enough that the temporaries stay a few MB.
_TILE = 2.0
_POINT_CHUNK = 1 << 16


def _points_against(P, Ys, cols, gradient, chunk):
    """Kernel values of points ``P`` against segment rows ``Ys[cols]`` within the cut-off.

    The columns are split into points, short and long segments, each with its closed form.
    Yields (point index, index into cols, k, grad) chunks of about ``chunk`` pairs; pairs
    beyond ``_CUTOFF`` are left out (their kernel value is exactly 0). When all the pairs
    fit in one chunk (a few queries against an expert) they are evaluated without tiling
    the points, whose cut-off test then costs more than it saves.
    """
    dim = P.shape[1]
    A = Ys[cols, :dim]
    D = Ys[cols, dim:] - A
    length = np.sqrt(_dot(D, D))
    tiles = None if len(P) * len(cols) <= chunk else _point_tiles(P, _TILE)
    values_of = (
        lambda w, j: _point_point_values(w, gradient),
        lambda w, j: _point_short_values(w, D[j], gradient),
        lambda w, j: _point_long_values(w, D[j], gradient, length[j]),
    )
    for mask, values in zip(_length_kinds(length), values_of, strict=True):
        sub = np.flatnonzero(mask)
        if sub.size == 0:
            continue
        if tiles is None:
            pairs = [(np.repeat(np.arange(len(P)), sub.size), np.tile(sub, len(P)))]
        else:
            pairs = ((pi, sub[cj]) for pi, cj in _tile_pairs(tiles, A[sub], D[sub], chunk))
        for pi, cj in pairs:
            k, grad, dist2 = values(P.take(pi, axis=0) - A.take(cj, axis=0), cj)
            keep = dist2 <= _CUTOFF**2
            if not np.all(keep):
                pi, cj, k = pi[keep], cj[keep], k[keep]
                grad = None if grad is None else grad[keep]
            yield pi, cj, k, grad


def _point_block(P, Ys):
    """Kernel values of points ``P`` against every segment row of ``Ys``, as a dense block.

    For a few queries against an expert's rows, where every pair is evaluated anyway: the
    differences are broadcast per coordinate (an (n_points, n_rows) array each) instead of
    gathered pair by pair, and the block is written whole. Each pair goes through the
    operations of :func:`_points_against` in the same order, so the values are the same to
    the bit; pairs beyond ``_CUTOFF`` are exactly 0.
    """
    dim = P.shape[1]
    A = Ys[:, :dim]
    D = Ys[:, dim:] - A
    length = np.sqrt(_dot(D, D))
    K = np.empty((len(P), len(Ys)))
    for mask, kind in zip(_length_kinds(length), ("point", "short", "long"), strict=True):
        sub = slice(None) if np.all(mask) else np.flatnonzero(mask)
        if not isinstance(sub, slice) and sub.size == 0:
            continue
        # w[j] = P[:, j] - A[sub, j]: as _dot sums over a pair's coordinates, in order.
        w = [P[:, j, None] - A[None, sub, j] for j in range(dim)]
        if kind == "short":  # Gauss-Legendre takes rows of pairs
            shape = w[0].shape
            d = np.broadcast_to(D[None, sub], (*shape, dim)).reshape(-1, dim)
            k, _, dist2 = _point_short_values(np.stack(w, axis=-1).reshape(-1, dim), d, None)
            k, dist2 = k.reshape(shape), dist2.reshape(shape)
        else:
            f0 = _coordinate_dot(w, w)
            if kind == "point":
                k, dist2 = np.exp(-0.5 * f0), f0
            else:
                dw = _coordinate_dot(w, [D[None, sub, j] for j in range(dim)])
                k, *_, dist2 = _inner_scalars(f0, dw, length[None, sub], ends=False)
        k[dist2 > _CUTOFF**2] = 0.0
        K[:, sub] = k
    return K


def _coordinate_dot(x, y):
    """``sum_j x[j] * y[j]`` over lists of per-coordinate arrays, in the order of :func:`_dot`."""
    out = x[0] * y[0]
    for xj, yj in zip(x[1:], y[1:], strict=True):
        out += xj * yj
    return out


def point_row_pairs(points, rows, point_index, row_index, *, length_scale=1.0):
    """Integral kernel of points against segment rows, for a list of (point, row) pairs.

    Each value is the one :func:`integral_kernel` gives the pair (a zero-length row of X
    against a row of Y), to the bit: the same scaling, closed forms and cut-off, applied
    to the listed pairs only. Several experts' cross-covariances at a few queries are then
    one vectorised evaluation instead of one kernel call each, whose fixed costs dominate
    at that size.

    Parameters
    ----------
    points : ndarray of shape (n_points, n_dims)
        Points in the original units.
    rows : ndarray of shape (n_rows, 2 * n_dims)
        Segment rows in the original units.
    point_index, row_index : ndarray of int of shape (n_pairs,)
        The pairs.
    length_scale : float or ndarray of shape (n_dims,)

    Returns
    -------
    k : ndarray of shape (n_pairs,)

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap._integrals import integral_kernel, point_row_pairs
    >>> rows = np.array([[0.0, 0.0, 2.0, 0.0], [1.0, 1.0, 1.0, 1.0]])
    >>> points = np.array([[0.5, 0.2]])
    >>> k = point_row_pairs(points, rows, np.array([0, 0]), np.array([0, 1]))
    >>> bool(np.array_equal(k, integral_kernel(np.hstack([points, points]), rows)[0]))
    True
    """
    dim = points.shape[1]
    scale = np.broadcast_to(np.asarray(length_scale, dtype=float), (dim,))
    # As integral_kernel scales its rows (each coordinate divided by its length scale),
    # then takes starts and directions: the same operations on the same numbers.
    scaled_rows = rows / np.concatenate([scale, scale])
    starts = scaled_rows[:, :dim]
    directions = scaled_rows[:, dim:] - starts
    w = (points / scale).take(point_index, axis=0) - starts.take(row_index, axis=0)
    k, _, dist2 = _point_segment(w, directions.take(row_index, axis=0), None)
    k[dist2 > _CUTOFF**2] = 0.0
    return k


def integral_kernel(
    X,
    Y=None,
    *,
    length_scale=1.0,
    eval_gradient=False,
    anisotropic=False,
    block_size=None,
    _fast=True,
):
    """Integral kernel matrix between segment rows, in blocks.

    Pairs with a point (a zero-length row) take the closed forms of :func:`_point_segment`,
    with candidate pairs found by tiling the points; segment-segment pairs are pre-cut by
    bounding circles and evaluated by :func:`pair_integrals`. Pairs further apart than
    ``_CUTOFF`` scaled units are exactly 0.

    Parameters
    ----------
    X : ndarray of shape (n_X, 2 * n_dims)
        Segment rows in the original units (already validated).
    Y : ndarray of shape (n_Y, 2 * n_dims) or None
        None means ``Y = X``: only the upper triangle is computed, the diagonal by the closed form
        of :func:`segment_self`, and K is exactly symmetric.
    length_scale : float or ndarray of shape (n_dims,)
    eval_gradient : bool, default=False
        Also return the gradient with respect to log length scale(s) (needs ``Y is None``).
    anisotropic : bool, default=False
        Gradient per dimension (shape (n, n, n_dims)) instead of one column.
    block_size : int, optional
        Pairs per block. By default, on the segment-segment path a sixteenth of the output
        size (at least 4096, at most 262144), so that temporaries stay within about the
        output's size, and ``_POINT_CHUNK`` on the paths with a point.
    _fast : bool, default=True
        Private. False evaluates every pair through the general path (dense bounding-circle
        pre-cut, segment-segment quadrature for point-segment pairs): the reference for tests
        and benchmarks.

    Returns
    -------
    K : ndarray of shape (n_X, n_Y)
    K_gradient : ndarray of shape (n_X, n_X, n_grad), only when ``eval_gradient``

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap._integrals import integral_kernel
    >>> X = np.array([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 2.0, 0.0]])
    >>> K = integral_kernel(X, length_scale=1.0)
    >>> bool(np.allclose(K, K.T)) and float(K[0, 0])
    1.0
    """
    dim = X.shape[1] // 2
    scale = np.broadcast_to(np.asarray(length_scale, dtype=float), (dim,))
    scale2 = np.concatenate([scale, scale])
    point_chunk = _POINT_CHUNK if block_size is None else min(block_size, _POINT_CHUNK)
    few = Y is not None and X.shape[0] * Y.shape[0] <= point_chunk
    if few and not eval_gradient and _fast and np.array_equal(X[:, :dim], X[:, dim:]):
        # A few points against all of Y (an expert's cross-covariances at a chunk of
        # queries): one dense block, without the bookkeeping of the general case.
        return _point_block(X[:, :dim] / scale, Y / scale2)
    Xs = X / scale2
    symmetric = Y is None
    Ys = Xs if symmetric else Y / scale2
    n, m = Xs.shape[0], Ys.shape[0]
    gradient = ("aniso" if anisotropic else "iso") if eval_gradient else None
    n_grad = dim if anisotropic else 1
    K = np.zeros((n, m))
    G = np.zeros((n, m, n_grad)) if eval_gradient else None
    if block_size is None:
        block_size = int(np.clip(n * m // 16, 4096, 1 << 18))

    def put(rr, cc, k, g):
        np.put(K, rr * m + cc, k)
        if symmetric:
            np.put(K, cc * m + rr, k)
        if eval_gradient:
            G[rr, cc] = g
            if symmetric:
                G[cc, rr] = g

    x_point = np.all(Xs[:, :dim] == Xs[:, dim:], axis=1) if _fast else np.zeros(n, bool)
    y_point = (
        x_point
        if symmetric
        else (np.all(Ys[:, :dim] == Ys[:, dim:], axis=1) if _fast else np.zeros(m, bool))
    )
    x_pts, x_segs = np.flatnonzero(x_point), np.flatnonzero(~x_point)
    y_pts, y_segs = np.flatnonzero(y_point), np.flatnonzero(~y_point)

    # Point rows of X against every column (symmetric: the other points after them and all
    # segments), then segment rows of X against the point columns of Y. A few points against
    # all of Y are one dense block.
    if x_pts.size and not symmetric and not eval_gradient and x_pts.size * m <= point_chunk:
        K[x_pts] = _point_block(Xs[x_pts, :dim], Ys)
    elif x_pts.size:
        cols = np.arange(m) if not symmetric else np.r_[x_pts, x_segs]
        for pi, cj, k, g in _points_against(Xs[x_pts, :dim], Ys, cols, gradient, point_chunk):
            rr, cc = x_pts[pi], cols[cj]
            if symmetric:
                upper = (cc > rr) | ~x_point[cc]
                rr, cc, k = rr[upper], cc[upper], k[upper]
                g = None if g is None else g[upper]
            put(rr, cc, k, g)
    if not symmetric and y_pts.size and x_segs.size:
        for pj, ci, k, g in _points_against(Ys[y_pts, :dim], Xs, x_segs, gradient, point_chunk):
            put(x_segs[ci], y_pts[pj], k, g)

    # Segment-segment pairs: bounding circles, then the general quadrature.
    if x_segs.size and y_segs.size:
        mid_x, rad_x = _bounding_circles(Xs, dim)
        mid_y, rad_y = (mid_x, rad_x) if symmetric else _bounding_circles(Ys, dim)
        for rr, cc in _circle_pairs(
            mid_x, rad_x, mid_y, rad_y, x_segs, y_segs, symmetric, block_size
        ):
            k, g = pair_integrals(
                Xs[rr], Ys[cc], gradient=gradient, max_nodes=block_size, _closed_form_points=_fast
            )
            put(rr, cc, k, g)

    if symmetric:
        d = Xs[:, dim:] - Xs[:, :dim]
        diag = np.arange(n)
        if eval_gradient:
            kd, h = segment_self(np.sqrt(_dot(d, d)), eval_gradient=True)
            gd = (d * d) * h[:, None]
            G[diag, diag] = gd if anisotropic else gd.sum(axis=1, keepdims=True)
        else:
            kd = segment_self(np.sqrt(_dot(d, d)))
        K[diag, diag] = kd
    if eval_gradient:
        return K, G
    return K
