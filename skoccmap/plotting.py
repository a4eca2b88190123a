"""Pictures of occupancy maps, in scikit-learn's Display style.

matplotlib is imported only when something is drawn; install it with
``pip install "skoccmap[plot]"``.
"""

import numpy as np

from ._validation import is_number
from .grid import OccupancyGrid, _cells_below
from .uncertainty import probability_std

__all__ = ["OccupancyMapDisplay"]

_KINDS = ("probability", "std", "variance", "both")


def _import_pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - exercised with matplotlib hidden
        raise ImportError(
            'Plotting needs matplotlib: pip install "skoccmap[plot]" (or pip install matplotlib).'
        ) from exc
    return plt


def _is_real_scalar(value):
    """A real number (:func:`is_number`) or a 0-d array of one."""
    if is_number(value):
        return True
    return isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "iuf"


class OccupancyMapDisplay:
    """Occupancy probability and uncertainty panels of a 2-D map.

    Build it with :meth:`from_estimator` or :meth:`from_grid` (which also plot), or construct
    it from arrays and call :meth:`plot`.

    Parameters
    ----------
    probability : ndarray of shape (ny, nx)
        P(occupied) per cell; row 0 is the lowest y (the layout of :class:`OccupancyGrid`).
    extent : tuple of 4 floats
        ``(xmin, xmax, ymin, ymax)`` of the map in metres.
    variance : ndarray of shape (ny, nx), default=None
        Predictive variance per cell; needed for the uncertainty panel.
    unknown : ndarray of bool of shape (ny, nx), default=None
        Cells drawn in the ``unknown_color`` of :meth:`plot` on every panel, with a legend
        entry "unknown" on the probability panel.

    Attributes
    ----------
    ax_ : matplotlib Axes
        The probability panel (or the only panel drawn).
    axes_ : ndarray of matplotlib Axes
        All panels drawn, probability first.
    im_ : matplotlib AxesImage
        The image of ``ax_``.
    images_ : list of matplotlib AxesImage
        The images of ``axes_``.
    figure_ : matplotlib Figure
        The figure holding the panels.

    Examples
    --------
    >>> import matplotlib
    >>> matplotlib.use("Agg")
    >>> import numpy as np
    >>> from skoccmap.baselines import OccupancyGridMap
    >>> from skoccmap.plotting import OccupancyMapDisplay
    >>> X = np.array([[0.0, 0.0, 0.95, 0.0], [1.0, 0.0, 1.0, 0.0]])
    >>> est = OccupancyGridMap(resolution=0.25).fit(X, [0, 1])
    >>> disp = OccupancyMapDisplay.from_estimator(est, extent=(0, 1.5, -0.5, 0.5),
    ...                                           resolution=0.25)
    >>> disp.im_.get_array().shape
    (4, 6)
    """

    def __init__(self, probability, *, extent, variance=None, unknown=None):
        self.probability = probability
        self.extent = extent
        self.variance = variance
        self.unknown = unknown

    @classmethod
    def from_grid(cls, grid, *, kind=None, z=None, ax=None, **plot_kwargs):
        """Draw an :class:`~skoccmap.OccupancyGrid`.

        Parameters
        ----------
        grid : OccupancyGrid
            A 2-D grid, or a 3-D grid of which the horizontal slice at height ``z`` is drawn.
        kind : {"probability", "std", "variance", "both"} or None, default=None
            Panels to draw; ``None``: both when the grid has a variance, else probability.
        z : float or None, default=None
            Height of the slice of a 3-D grid: the layer holding it, a layer spanning
            ``[bottom, top)`` (``None``: the layer holding the grid's mid-height).
        ax : matplotlib Axes, sequence of two Axes or None, default=None
            Where to draw; ``None`` makes a new figure.
        **plot_kwargs
            Passed to :meth:`plot`.

        Returns
        -------
        display : OccupancyMapDisplay

        Examples
        --------
        >>> import matplotlib
        >>> matplotlib.use("Agg")
        >>> import numpy as np
        >>> from skoccmap import OccupancyGrid
        >>> from skoccmap.plotting import OccupancyMapDisplay
        >>> grid = OccupancyGrid(np.full((2, 3, 4), 0.2), origin=(0, 0, 0), resolution=0.5,
        ...                      unknown=np.zeros((2, 3, 4), dtype=bool))
        >>> disp = OccupancyMapDisplay.from_grid(grid, z=0.7)  # the layer [0.5, 1.0)
        >>> disp.ax_.get_title()
        'P(occupied), slice at z = 0.75 m'
        """
        if not isinstance(grid, OccupancyGrid):
            raise ValueError(f"grid must be an OccupancyGrid, got {type(grid).__name__}.")
        probability, variance, unknown = grid.probability, grid.variance, grid.unknown
        height = None
        if grid.n_dims == 2 and z is not None:
            raise ValueError(f"z selects a slice of a 3-D grid; this grid is 2-D (z={z!r}).")
        if grid.n_dims == 3:
            zmin = grid.origin[2]
            if z is not None and not _is_real_scalar(z):
                raise TypeError(f"z must be a height in metres (a number), got {z!r}.")
            if z is not None and not np.isfinite(z):
                raise ValueError(f"z must be a finite height, got {z!r}.")
            if z is None:
                k = grid.shape[0] // 2
            else:
                # The layer as a float first: a height far off the grid gives an infinite
                # one, which int() refuses with an OverflowError. A height on a layer's
                # lower face is in that layer, as a cell's lower edge is in the metrics.
                with np.errstate(over="ignore"):
                    k = _cells_below((float(z) - zmin) / grid.resolution)
            if not 0 <= k < grid.shape[0]:
                raise ValueError(f"z={z} is outside the grid's height range {grid.extent[4:]}.")
            k = int(k)
            probability = probability[k]
            variance = None if variance is None else variance[k]
            unknown = None if unknown is None else unknown[k]
            height = zmin + (k + 0.5) * grid.resolution
        display = cls(probability, extent=grid.extent[:4], variance=variance, unknown=unknown)
        display.plot(ax=ax, kind=kind, **plot_kwargs)
        if height is not None:
            for panel_ax in display.axes_:
                panel_ax.set_title(f"{panel_ax.get_title()}, slice at z = {height:.2f} m")
        return display

    @classmethod
    def from_estimator(
        cls,
        estimator,
        extent=None,
        resolution=0.1,
        *,
        kind=None,
        unknown_variance="auto",
        observed_by=None,
        chunk_size=65_536,
        verbose=0,
        ax=None,
        **plot_kwargs,
    ):
        """Evaluate an estimator on a grid (:meth:`OccupancyGrid.from_estimator`) and draw it.

        Parameters
        ----------
        estimator : fitted estimator with ``predict_proba`` (``predict_var`` optional)
        extent, resolution, unknown_variance, observed_by, chunk_size, verbose
            See :meth:`skoccmap.OccupancyGrid.from_estimator` (``observed_by``: the
            training scans, whose unseen cells are drawn unknown).
        kind : {"probability", "std", "variance", "both"} or None, default=None
            Panels; ``None``: both when the estimator has ``predict_var``.
        ax : matplotlib Axes, sequence of two Axes or None, default=None
            Where to draw; ``None`` makes a new figure.
        **plot_kwargs
            ``z`` (the height of a 3-D grid's slice, see :meth:`from_grid`), and the
            arguments of :meth:`plot`.

        Returns
        -------
        display : OccupancyMapDisplay
        """
        grid = OccupancyGrid.from_estimator(
            estimator,
            extent,
            resolution,
            unknown_variance=unknown_variance,
            observed_by=observed_by,
            chunk_size=chunk_size,
            verbose=verbose,
        )
        return cls.from_grid(grid, kind=kind, ax=ax, **plot_kwargs)

    def plot(
        self,
        ax=None,
        *,
        kind=None,
        cmap="gray_r",
        variance_cmap="viridis",
        unknown_color="#9ecae1",
        colorbar=True,
        points=None,
        point_kwargs=None,
    ):
        """Draw the panels.

        Parameters
        ----------
        ax : matplotlib Axes, sequence of two Axes or None, default=None
            A single Axes for one panel, two for ``kind="both"``; ``None`` makes a new figure.
        kind : {"probability", "std", "variance", "both"} or None, default=None
            ``"std"``: the standard deviation of the occupancy probability under the
            latent Gaussian (:func:`skoccmap.uncertainty.probability_std`; approximate
            for a mixture of experts, ``combiner="moe"``), in ``[0, 1/2]`` whatever the
            kernel, so one threshold fits every map;
            ``"variance"``: the latent variance, in the latent's units; ``"both"``:
            probability and std. ``None``: both when a variance is available, else
            probability.
        cmap : str, default="gray_r"
            Colour map of the probability (occupied dark, free light, as printed maps are).
        variance_cmap : str, default="viridis"
            Colour map of the std and the variance.
        unknown_color : color, default="#9ecae1"
            Colour of unknown cells, on every panel: a map's uncertainty in cells it calls
            unknown is not a confidence to read.
        colorbar : bool, default=True
            Add a colour bar to each panel.
        points : array-like of shape (m, 2) or more columns, default=None
            Points to overlay on every panel (e.g. the training hits or the robot's path);
            the first two columns are drawn, so poses ``(x, y, heading)`` may be passed
            as they are.
        point_kwargs : dict, default=None
            Passed to ``Axes.scatter`` for ``points``.

        Returns
        -------
        display : OccupancyMapDisplay
            ``self``, with ``ax_``, ``axes_``, ``im_``, ``images_`` and ``figure_`` set.

        Examples
        --------
        >>> import matplotlib
        >>> matplotlib.use("Agg")
        >>> import numpy as np
        >>> from skoccmap.plotting import OccupancyMapDisplay
        >>> probability = np.array([[0.1, 0.9], [0.5, 0.2]])
        >>> variance = np.array([[0.2, 0.3], [1.0, 0.1]])
        >>> disp = OccupancyMapDisplay(probability, extent=(0.0, 2.0, 0.0, 2.0),
        ...                            variance=variance, unknown=probability == 0.5)
        >>> disp = disp.plot(points=[[0.5, 0.5, 0.0], [1.5, 1.5, 1.0]])  # e.g. robot poses
        >>> [ax.get_title() for ax in disp.axes_]
        ['P(occupied)', 'std of P(occupied)']
        """
        plt = _import_pyplot()
        if points is not None:
            points = np.asarray(points, dtype=np.float64)
            if points.ndim != 2 or points.shape[1] < 2:
                raise ValueError(
                    f"points must have shape (m, 2) or more columns, got {points.shape}."
                )
        probability = np.asarray(self.probability, dtype=np.float64)
        if probability.ndim != 2:
            raise ValueError(f"probability must be 2-D (ny, nx), got shape {probability.shape}.")
        self._check_arrays(probability)
        if kind is None:
            kind = "both" if self.variance is not None else "probability"
        if kind not in _KINDS:
            raise ValueError(f"kind must be one of {_KINDS} or None, got {kind!r}.")
        if kind != "probability" and self.variance is None:
            raise ValueError(
                f"kind={kind!r} needs a variance; the estimator or grid has none (no "
                "predict_var). Use kind='probability'."
            )
        panels = ["probability", "std"] if kind == "both" else [kind]
        axes = self._axes(plt, ax, len(panels))
        images = []
        for panel, panel_ax in zip(panels, axes, strict=True):
            if panel == "probability":
                image = self._draw_probability(plt, panel_ax, probability, cmap, unknown_color)
                label = "P(occupied)"
            else:
                variance = np.asarray(self.variance, dtype=np.float64)
                if panel == "std":
                    # Unknown cells are masked, never drawn, and may hold no value (NaN,
                    # see _check_arrays): those stand in as P = 1/2 and variance 0.
                    hole = self._unknown_mask(probability.shape) & ~(
                        (probability >= 0.0) & (probability <= 1.0) & (variance >= 0.0)
                    )
                    values = probability_std(
                        np.where(hole, 0.5, probability), np.where(hole, 0.0, variance)
                    )
                    limits = (0.0, 0.5)
                    label = "std of P(occupied)"
                else:
                    values, limits = variance, (None, None)
                    label = "predictive variance"
                image = panel_ax.imshow(
                    self._masked(values),
                    origin="lower",
                    extent=self.extent,
                    cmap=plt.get_cmap(variance_cmap).with_extremes(bad=unknown_color),
                    vmin=limits[0],
                    vmax=limits[1],
                    interpolation="nearest",
                )
            panel_ax.set_title(label)
            panel_ax.set_xlabel("x [m]")
            panel_ax.set_ylabel("y [m]")
            panel_ax.set_aspect("equal")
            if colorbar:
                panel_ax.figure.colorbar(image, ax=panel_ax, shrink=0.8, label=label)
            if points is not None:
                style = {"s": 1, "c": "tab:red", "linewidths": 0} | (point_kwargs or {})
                panel_ax.scatter(points[:, 0], points[:, 1], **style)
            images.append(image)
        self.axes_ = np.array(axes, dtype=object)
        self.ax_ = axes[0]
        self.images_ = images
        self.im_ = images[0]
        self.figure_ = axes[0].figure
        return self

    def _check_arrays(self, probability):
        """ValueError for panels that do not match the probability, or values a map cannot
        hold (a NaN would be drawn in the colour of unknown cells)."""
        for name in ("variance", "unknown"):
            value = getattr(self, name)
            if value is not None and np.shape(value) != probability.shape:
                raise ValueError(
                    f"{name} must have the probability's shape {probability.shape}, got "
                    f"{np.shape(value)}."
                )
        known = ~self._unknown_mask(probability.shape)
        if not np.all(((probability >= 0.0) & (probability <= 1.0)) | ~known):
            raise ValueError(
                "probability must hold values in [0, 1] (no NaN) in the known cells; mark "
                "cells without a value with unknown=."
            )
        if self.variance is not None:
            variance = np.asarray(self.variance, dtype=np.float64)
            if not np.all((variance >= 0.0) | ~known):
                raise ValueError("variance must hold values >= 0 (no NaN) in the known cells.")
        extent = np.asarray(self.extent, dtype=np.float64)
        if not (
            extent.shape == (4,)
            and np.all(np.isfinite(extent))
            and extent[1] > extent[0]
            and extent[3] > extent[2]
        ):
            raise ValueError(
                f"extent must be (x_min, x_max, y_min, y_max) with max > min, got {self.extent!r}."
            )

    def _unknown_mask(self, shape):
        if self.unknown is None:
            return np.zeros(shape, dtype=bool)
        return np.asarray(self.unknown, dtype=bool)

    @staticmethod
    def _axes(plt, ax, n_panels):
        if ax is None:
            fig, axes = plt.subplots(1, n_panels, figsize=(6 * n_panels, 5), squeeze=False)
            return list(axes[0])
        axes = list(np.ravel(np.asarray(ax, dtype=object)))
        if len(axes) != n_panels:
            raise ValueError(f"ax must hold {n_panels} Axes for this kind, got {len(axes)}.")
        from matplotlib.axes import Axes

        strays = [a for a in axes if not isinstance(a, Axes)]
        if strays:
            raise TypeError(f"ax must hold matplotlib Axes, got {strays[0]!r}.")
        return axes

    def _masked(self, values):
        if self.unknown is None:
            return values
        return np.ma.masked_array(values, mask=np.asarray(self.unknown, dtype=bool))

    def _draw_probability(self, plt, ax, probability, cmap, unknown_color):
        colormap = plt.get_cmap(cmap).with_extremes(bad=unknown_color)
        if self.unknown is not None and np.any(self.unknown):
            from matplotlib.patches import Patch

            ax.legend(
                handles=[Patch(facecolor=unknown_color, edgecolor="0.5", label="unknown")],
                loc="upper right",
                fontsize="small",
            )
        return ax.imshow(
            self._masked(probability),
            origin="lower",
            extent=self.extent,
            cmap=colormap,
            vmin=0.0,
            vmax=1.0,
            interpolation="nearest",
        )
