"""
====================================
The integral kernel over laser beams
====================================

A laser beam says that the whole segment from the sensor to the hit is free.
:class:`~skoccmap.IntegralKernel` keeps the beam whole: the covariance between a beam and
any other segment or point is the squared-exponential kernel **averaged along** the beam,

.. math::

    k(s, x) = \\frac{1}{L} \\int_0^L \\exp\\left(-\\frac{\\lVert s(t) - x \\rVert^2}
    {2 \\ell^2}\\right) dt,

computed in closed form (with ``erf``) for a point and by adaptive quadrature of a closed
form for two beams. One beam is then one training row of a GP classifier, where the
point-based way cuts it into points every few centimetres.
"""

# %%
# The covariance of one beam with the plane
# -----------------------------------------
# A 4 m beam from the origin and query points on a grid (points are zero-length segments).
import matplotlib.pyplot as plt
import numpy as np
from scipy.integrate import quad
from sklearn.gaussian_process.kernels import RBF

from skoccmap import IntegralKernel
from skoccmap.observations import as_segments

length_scale = 0.5
kernel = IntegralKernel(length_scale=length_scale)
beam = np.array([[0.0, 0.0, 4.0, 0.0]])

xs, ys = np.linspace(-1.5, 5.5, 141), np.linspace(-2.0, 2.0, 81)
grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
k_beam = kernel(as_segments(grid), beam).reshape(len(ys), len(xs))

fig, ax = plt.subplots(figsize=(8, 4), layout="constrained")
image = ax.imshow(k_beam, origin="lower", extent=(xs[0], xs[-1], ys[0], ys[-1]))
ax.plot([0, 4], [0, 0], "w-", lw=2, label="beam")
ax.set_title(f"k(beam, point), length scale {length_scale} m")
ax.set_xlabel("x [m]")
ax.set_ylabel("y [m]")
ax.legend(loc="upper right")
fig.colorbar(image, ax=ax, shrink=0.8)

# %%
# The same numbers by numerical quadrature
# ----------------------------------------
# An independent check with :func:`scipy.integrate.quad` of the point kernel along the beam.
rbf = RBF(length_scale)
L = 4.0


def averaged_rbf(point):
    def integrand(t):
        return rbf(np.array([[t, 0.0]]), point[None])[0, 0]

    return quad(integrand, 0.0, L, points=[np.clip(point[0], 0, L)], epsabs=1e-13)[0] / L


rng = np.random.default_rng(0)
checks = rng.uniform([-1.0, -1.0], [5.0, 1.0], size=(8, 2))
closed_form = kernel(as_segments(checks), beam)[:, 0]
numeric = np.array([averaged_rbf(p) for p in checks])
print(f"largest difference from quadrature: {np.max(np.abs(closed_form - numeric)):.1e}")

# %%
# Beams cut into points
# ---------------------
# Before the integral kernel a beam became free points every ``spacing`` metres; the mean of
# the point kernel over them approximates the average above. The approximation error is
# largest next to the beam, where the integrand is peaked, and it costs ``L / spacing``
# training rows per beam instead of one.
near = as_segments(np.array([[2.0, 0.1], [4.2, 0.0], [1.0, 0.6]]))
exact = kernel(near, beam)[:, 0]
spacings = np.array([1.0, 0.5, 0.4, 0.2, 0.1, 0.05, 0.02])
errors = []
for spacing in spacings:
    t = np.arange(0.0, L + 1e-9, spacing)
    cut = np.column_stack([t, np.zeros_like(t)])
    errors.append(np.abs(rbf(near[:, :2], cut).mean(axis=1) - exact).max())

fig, ax = plt.subplots(figsize=(5.5, 4), layout="constrained")
ax.loglog(spacings, errors, "o-")
ax.set_xlabel("spacing of the points along the beam [m]")
ax.set_ylabel("largest kernel error")
ax.set_title("Cutting a 4 m beam into points")
for spacing, error in zip(spacings, errors, strict=True):
    print(f"spacing {spacing:5.2f} m: {int(L / spacing) + 1:3d} rows, error {error:.1e}")
