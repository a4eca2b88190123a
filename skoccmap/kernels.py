"""Gaussian-process kernels over segment rows (laser beams and points)."""

import numpy as np
from sklearn.gaussian_process.kernels import Hyperparameter, Kernel

from ._integrals import integral_kernel, segment_self
from ._validation import check_segments, segment_dim

# Longest segments, in length scales, whose kernel with one another is evaluated. The
# quadrature along the shorter segment of a pair takes a panel per 15 length scales: at 1e7
# a pair costs about a second and is off by 2e-3, at 1e8 fifteen seconds and 13 %; beyond
# about 1e19 the panel count overflows.
_MAX_SCALED_LENGTH = 1e7


def _check_length_scale_shape(length_scale):
    """Refuse a length scale of more than one dimension, a row of shape (1, n) included: it
    would give a 2-D ``theta``, which no optimiser takes."""
    shape = np.shape(length_scale)
    if len(shape) > 1:
        raise ValueError(
            "length_scale must be a scalar or a 1-D array (one per spatial dimension), got "
            f"shape {shape}; pass np.ravel(length_scale) for a row of length scales."
        )


def _scaled_lengths(X, length_scale):
    """Lengths of the segment rows ``X`` in length scales (inf where they overflow)."""
    dim = segment_dim(X)
    with np.errstate(over="ignore"):
        d = (X[:, dim:] - X[:, :dim]) / length_scale
        return np.sqrt(np.einsum("ij,ij->i", d, d))


def _check_pair_lengths(longest, length_scale, subject):
    """Refuse pairs of segments too long for the quadrature: ``longest`` is the length, in
    length scales, of the shorter segment of the longest pair the kernel may evaluate."""
    if longest > _MAX_SCALED_LENGTH:
        raise ValueError(
            f"{subject} at least {longest:.3g} length scales long (length_scale="
            f"{length_scale!r}); the kernel between two segments longer than "
            f"{_MAX_SCALED_LENGTH:g} length scales takes seconds per pair and loses digits. "
            "Raise length_scale (and the lower bound of length_scale_bounds), or cut the "
            "segments into pieces with skoccmap.observations.split_segments."
        )


class IntegralKernel(Kernel):
    """Squared-exponential kernel averaged along segments.

    Each sample is a segment row ``[start_1..start_D, end_1..end_D]`` (a point is a segment of
    zero length). The kernel between two segments is the average of the squared-exponential
    kernel over both of them,

    .. math::
        k(s, t) = \\int_0^1 \\int_0^1
        \\exp\\left(-\\tfrac12 \\sum_d \\frac{(s(u)_d - t(v)_d)^2}{l_d^2}\\right) du\\, dv,

    with :math:`s(u) = a + u (b - a)`. A point against itself gives 1 and two points give the
    ordinary squared-exponential (RBF) kernel. The signal variance comes from composing with
    :class:`~sklearn.gaussian_process.kernels.ConstantKernel`, noise from
    :class:`~sklearn.gaussian_process.kernels.WhiteKernel`.

    Point-point and segment-point values are closed forms; segment-segment values integrate the
    inner integral analytically and the outer one by Gauss-Legendre quadrature with a node count
    that grows with the segment length over the length scale (relative error below 1e-6 for
    segments up to about 1e5 length scales long; beyond, the perpendicular distance, a
    difference of two squares of that size, loses digits: about 2e-4 at 1e6 and 2e-3 at 1e7).
    Two segments both longer than 1e7 length scales are refused with a ValueError: their
    kernel would take seconds and lose percents. A segment of any length against points, and
    :meth:`diag`, are closed forms.
    Pairs further apart than 8 length scales are exactly 0 (the point kernel is below 1.3e-14
    there) and are never evaluated, so k(query points, training rows) costs in proportion to
    the pairs within that reach, not to the size of the matrix.

    Parameters
    ----------
    length_scale : float or ndarray of shape (n_dims,), default=1.0
        Length scale, in the units of the coordinates. An array gives one per spatial dimension
        (``n_dims`` is half the number of columns) and an anisotropic kernel.
    length_scale_bounds : pair of floats >= 0 or "fixed", default=(1e-5, 1e5)
        Bounds on ``length_scale`` for hyperparameter optimisation; "fixed" keeps it fixed.

    See Also
    --------
    sklearn.gaussian_process.kernels.RBF : The point kernel being averaged.

    References
    ----------
    .. [1] S. Kim and J. Kim, "Building occupancy maps with a mixture of Gaussian processes",
       IEEE International Conference on Robotics and Automation (ICRA), 2012: the integral
       kernel over laser beams, in the method this package implements.

    Examples
    --------
    >>> import numpy as np
    >>> from sklearn.gaussian_process.kernels import ConstantKernel
    >>> from skoccmap import IntegralKernel
    >>> X = np.array([[0.0, 0.0, 0.0, 0.0],     # a point at the origin
    ...               [0.0, 0.0, 3.0, 0.0]])    # a 3 m beam starting there
    >>> kernel = ConstantKernel(1.0) * IntegralKernel(length_scale=0.5)
    >>> K = kernel(X)
    >>> K.shape
    (2, 2)
    >>> round(float(K[0, 0]), 6)
    1.0
    """

    def __init__(self, length_scale=1.0, length_scale_bounds=(1e-5, 1e5)):
        self.length_scale = length_scale
        self.length_scale_bounds = length_scale_bounds

    @property
    def anisotropic(self):
        return np.iterable(self.length_scale) and len(self.length_scale) > 1

    @property
    def hyperparameter_length_scale(self):
        _check_length_scale_shape(self.length_scale)
        if self.anisotropic:
            return Hyperparameter(
                "length_scale", "numeric", self.length_scale_bounds, len(self.length_scale)
            )
        return Hyperparameter("length_scale", "numeric", self.length_scale_bounds)

    def _checked_length_scale(self, n_dims):
        _check_length_scale_shape(self.length_scale)
        length_scale = np.squeeze(np.asarray(self.length_scale, dtype=float)).astype(float)
        if length_scale.ndim == 1 and length_scale.shape[0] != n_dims:
            raise ValueError(
                f"Anisotropic length_scale has {length_scale.shape[0]} entries but the segments "
                f"have {n_dims} spatial dimension(s) ({2 * n_dims} columns)."
            )
        if not np.all(np.isfinite(length_scale)) or np.any(length_scale <= 0):
            raise ValueError(f"length_scale must be positive and finite, got {self.length_scale}.")
        return length_scale

    def __call__(self, X, Y=None, eval_gradient=False):
        """Return the kernel k(X, Y) and optionally its gradient.

        Parameters
        ----------
        X : ndarray of shape (n_samples_X, 2 * n_dims)
            Segment rows ``[start, end]``.
        Y : ndarray of shape (n_samples_Y, 2 * n_dims), default=None
            Segment rows; None means k(X, X).
        eval_gradient : bool, default=False
            Whether to return the gradient with respect to the log length scale(s). Only
            supported when Y is None.

        Returns
        -------
        K : ndarray of shape (n_samples_X, n_samples_Y)
        K_gradient : ndarray of shape (n_samples_X, n_samples_X, n_grad), optional
            ``n_grad`` is the number of length scales (0 when they are fixed).
        """
        X = check_segments(X, name="X", allow_empty=True)
        n_dims = segment_dim(X)
        length_scale = self._checked_length_scale(n_dims)
        if Y is not None:
            if eval_gradient:
                raise ValueError("Gradient can only be evaluated when Y is None.")
            Y = check_segments(Y, name="Y", allow_empty=True)
            if Y.shape[1] != X.shape[1]:
                raise ValueError(
                    f"X has {X.shape[1]} columns but Y has {Y.shape[1]}; both must be segment "
                    "rows of the same dimension."
                )
            if X.shape[0] and Y.shape[0]:
                longest = min(
                    _scaled_lengths(X, length_scale).max(), _scaled_lengths(Y, length_scale).max()
                )
                _check_pair_lengths(longest, self.length_scale, "X and Y each hold a segment")
            return integral_kernel(X, Y, length_scale=length_scale)
        if X.shape[0] > 1:
            # A segment with itself is a closed form: the second longest bounds the pairs.
            second = np.partition(_scaled_lengths(X, length_scale), -2)[-2]
            _check_pair_lengths(second, self.length_scale, "X holds two segments")
        want_gradient = eval_gradient and not self.hyperparameter_length_scale.fixed
        out = integral_kernel(
            X,
            length_scale=length_scale,
            eval_gradient=want_gradient,
            anisotropic=bool(self.anisotropic),
        )
        if not eval_gradient:
            return out
        if not want_gradient:
            return out, np.empty((X.shape[0], X.shape[0], 0))
        return out

    def diag(self, X):
        """Return the diagonal k(X, X), each segment with itself, in closed form.

        Parameters
        ----------
        X : ndarray of shape (n_samples_X, 2 * n_dims)
            Segment rows.

        Returns
        -------
        K_diag : ndarray of shape (n_samples_X,)
            1 for points, smaller for longer segments.
        """
        X = check_segments(X, name="X", allow_empty=True)
        n_dims = segment_dim(X)
        scale = self._checked_length_scale(n_dims)
        d = (X[:, n_dims:] - X[:, :n_dims]) / scale
        return segment_self(np.sqrt(np.einsum("ij,ij->i", d, d)))

    def is_stationary(self):
        """Return False: the kernel depends on segment lengths, not only on differences."""
        return False

    def __repr__(self):
        if self.anisotropic:
            return "{}(length_scale=[{}])".format(
                self.__class__.__name__, ", ".join(map("{:.3g}".format, self.length_scale))
            )
        return f"{self.__class__.__name__}(length_scale={np.ravel(self.length_scale)[0]:.3g})"
