"""Occupancy maps sampled on a regular grid, and their export to ROS.

:class:`OccupancyGrid` evaluates any estimator with ``predict_proba`` (and, when it has one,
``predict_var``) on the cell centres of a grid, in chunks, and writes the result as a ROS
``nav_msgs/OccupancyGrid`` layout, as ``map_server`` PGM + YAML files, or as ``.npz``.

Array layout: ``probability[j, i]`` (2-D) or ``probability[k, j, i]`` (3-D) is the cell whose
lower corner is ``origin + resolution * (i, j[, k])``: C order with x fastest, row 0 at the
origin -- the row-major layout of ROS ``OccupancyGrid.data``.
"""

import json
import re
import sys
import time
import warnings
import zipfile
import zlib
from numbers import Integral
from pathlib import Path

import numpy as np

from ._validation import (
    caller_stacklevel,
    check_magnitude,
    is_number,
    queries_at,
    queries_of_our_own,
)

__all__ = ["OccupancyGrid", "ROS_FREE_THRESH", "ROS_OCCUPIED_THRESH"]

# map_server reads a pixel v as p = (255 - v) / 255 (negate: 0) and calls it occupied above
# occupied_thresh, free below free_thresh, unknown otherwise. The trinary pixels 0 / 254 / 205
# read back as p = 1, 0.004, 0.196; with free_thresh 0.196 (not the customary 0.25) the
# unknown pixel stays unknown.
ROS_FREE_THRESH = 0.196
ROS_OCCUPIED_THRESH = 0.65
_PIXEL_OCCUPIED, _PIXEL_FREE, _PIXEL_UNKNOWN = 0, 254, 205
# unknown_variance="auto": this fraction of the prior variance (see _reference_variance).
_AUTO_UNKNOWN = 0.9
# YAML booleans as yaml-cpp (map_server's YAML reader) spells them, as negate's 0 / 1.
_YAML_BOOLEANS = {
    word: bit
    for words, bit in (("y yes true on", "1"), ("n no false off", "0"))
    for lower in words.split()
    for word in (lower, lower.capitalize(), lower.upper())
}
# Cells of one map at most: a probability and a variance each, 0.8 GB at this bound.
_MAX_CELLS = 50_000_000


def _check_thresholds(free, occupied, names=("free_threshold", "occupied_threshold"), where=""):
    """Refuse thresholds that are no numbers, out of order or outside [0, 1], naming them
    ``names``."""
    for name, value in zip(names, (free, occupied), strict=True):
        if not is_number(value):
            raise TypeError(f"{where}{name} must be a number, got {value!r}.")
    if not 0.0 <= free <= occupied <= 1.0:
        f, o = names
        raise ValueError(f"{where}need 0 <= {f} <= {o} <= 1, got {f}={free}, {o}={occupied}.")


def _grid_from_extent(extent, resolution):
    """Origin and cell counts (in coordinate order) covering ``extent``.

    A flat sequence ``(min_1, max_1, .., min_D, max_D)`` is covered exactly from ``min``;
    a 2-D array of points (m, D) or segment rows (m, 2D) is covered by a grid snapped to
    multiples of ``resolution`` around all its coordinates.
    """
    arr = np.asarray(extent, dtype=np.float64)
    if arr.ndim == 1:
        if arr.size not in (4, 6) or not np.all(np.isfinite(arr)):
            raise ValueError(
                "extent must be (xmin, xmax, ymin, ymax[, zmin, zmax]) or an array of points "
                f"or segment rows, got {extent!r}."
            )
        check_magnitude(arr, "extent")
        low, high = arr[0::2], arr[1::2]
        if np.any(high <= low):
            raise ValueError(f"extent must have max > min on every axis, got {extent!r}.")
        with np.errstate(over="ignore"):  # inf counts are refused below
            counts = np.ceil((high - low) / resolution - 1e-9)
        return low, _checked_counts(np.maximum(counts, 1), resolution)
    if arr.ndim != 2 or arr.shape[0] == 0 or arr.shape[1] not in (2, 3, 4, 6):
        raise ValueError(
            "extent data must be a non-empty array of 2-D/3-D points (m, 2|3) or segment rows "
            f"(m, 4|6), got shape {arr.shape}."
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError("extent data contains NaN or infinite values.")
    check_magnitude(arr, "extent")
    n_dims = arr.shape[1] if arr.shape[1] in (2, 3) else arr.shape[1] // 2
    coords = arr.reshape(-1, n_dims) if arr.shape[1] > n_dims else arr
    low = _snapped_origin(coords.min(axis=0), resolution)
    with np.errstate(over="ignore"):  # inf counts are refused below
        counts = np.floor((coords.max(axis=0) - low) / resolution) + 1
    if arr.shape[0] == 2 and arr.shape[1] == n_dims and np.any(counts == 1):
        warnings.warn(
            f"extent {arr.tolist()} was read as two points, which span a grid one cell wide; "
            "for bounds pass a flat (xmin, xmax, ymin, ymax[, zmin, zmax]).",
            UserWarning,
            stacklevel=caller_stacklevel(),
        )
    return low, _checked_counts(counts, resolution)


def _snapped_origin(low, resolution):
    """A multiple of ``resolution`` at or below ``low`` (per axis): the largest, or one cell
    below it where the quotient rounds down (75.3 / 0.1 is 752.99..., so 75.2 where 75.3
    itself is 753 * 0.1). The grid then holds an empty row or column on its low side;
    it covers the data either way."""
    origin = np.floor(low / resolution) * resolution
    # floor(m / r) * r can round above m (0.85 / 0.05 -> 17 * 0.05 > 0.85): one cell lower.
    return np.where(origin > low, origin - resolution, origin)


def _cells_below(position):
    """``floor(position)``, a position within 1e-9 (relative) of a whole number taken as
    that number: a point on a cell's lower edge is in that cell, whichever way the division
    by the resolution rounded it (1.2 m above -0.2 m is 6.999... cells of 0.2 m).
    Infinite or NaN positions stay as they are."""
    position = np.asarray(position, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        nearest = np.rint(position)
        on_edge = np.abs(position - nearest) <= 1e-9 * np.maximum(1.0, np.abs(nearest))
    return np.floor(np.where(on_edge, nearest, position))


def _checked_counts(counts, resolution):
    """Cell counts as integers; ValueError when the grid would exceed ``_MAX_CELLS``."""
    with np.errstate(over="ignore"):
        too_many = np.prod(counts) > _MAX_CELLS
    if too_many:
        # Counts beyond 1e15 as 1e+200, not as their 201 digits.
        sizes = " x ".join(f"{c:.0f}" if c < 1e15 else f"{c:.3g}" for c in counts)
        raise ValueError(
            f"a grid of {sizes} cells at resolution "
            f"{resolution:g} is too large (at most {_MAX_CELLS:,} cells): use a coarser "
            "resolution or a smaller extent (a reading far off the map can stretch an extent "
            "taken from the data)."
        )
    return counts.astype(np.int64)


def _check_grid_dims(estimator, n_dims):
    """ValueError where the estimator's rows cannot be cells of an ``n_dims``-D grid (points
    of ``n_dims`` columns or zero-length segments of twice as many)."""
    n_features = getattr(estimator, "n_features_in_", None)
    if n_features is None or n_features in (n_dims, 2 * n_dims):
        return
    raise ValueError(
        f"extent gives a {n_dims}-D grid, but {type(estimator).__name__} was fitted on "
        f"{n_features} columns ({n_dims}-D takes {n_dims} or {2 * n_dims}): pass extent as "
        "(xmin, xmax, ymin, ymax) in 2-D or (xmin, xmax, ymin, ymax, zmin, zmax) in 3-D, or "
        "points or segment rows of the estimator's dimension (2-D poses [x, y, theta] are "
        "no points: pass poses[:, :2])."
    )


class OccupancyGrid:
    """Occupancy probabilities (and variances) on a regular 2-D or 3-D grid.

    Parameters
    ----------
    probability : array-like of shape (ny, nx) or (nz, ny, nx)
        P(occupied) per cell, in [0, 1]; row 0 is the row at ``origin`` (see the module notes).
    origin : array-like of shape (n_dims,)
        World coordinates of the lower corner of cell ``(0, .., 0)``.
    resolution : float
        Cell edge length in metres.
    variance : array-like of the shape of ``probability``, default=None
        Predictive (latent) variance per cell, if the estimator provides it.
    unknown : array-like of bool of the shape of ``probability``, default=None
        Cells without enough evidence to call (``-1`` in ROS). ``None``: none.

    Attributes
    ----------
    n_dims : int
        2 or 3.
    shape : tuple of int
        Array shape, ``(ny, nx)`` or ``(nz, ny, nx)``.
    extent : tuple of float
        ``(xmin, xmax, ymin, ymax[, zmin, zmax])``, matplotlib's ``imshow`` extent in 2-D.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap import OccupancyGrid
    >>> grid = OccupancyGrid([[0.1, 0.9], [0.5, 0.0]], origin=(0.0, 0.0), resolution=0.5,
    ...                      unknown=[[False, False], [True, False]])
    >>> grid.extent
    (0.0, 1.0, 0.0, 1.0)
    >>> grid.to_ros_occupancy_grid()["data"]
    array([10, 90, -1,  0], dtype=int8)
    >>> grid.trinary()
    array([[  0, 100],
           [ -1,   0]], dtype=int8)
    """

    def __init__(self, probability, origin, resolution, *, variance=None, unknown=None):
        probability = np.asarray(probability, dtype=np.float64)
        if probability.ndim not in (2, 3) or probability.size == 0:
            raise ValueError(
                "probability must be a non-empty 2-D (ny, nx) or 3-D (nz, ny, nx) array, got "
                f"shape {probability.shape}."
            )
        if not np.all((probability >= 0) & (probability <= 1)):
            raise ValueError("probability must lie in [0, 1] (and hold no NaN).")
        origin = np.asarray(origin, dtype=np.float64)
        if origin.shape != (probability.ndim,) or not np.all(np.isfinite(origin)):
            raise ValueError(
                f"origin must be {probability.ndim} finite coordinates, got {origin.tolist()}."
            )
        if not (is_number(resolution) and np.isfinite(resolution) and resolution > 0):
            raise ValueError(f"resolution must be a positive number, got {resolution!r}.")
        with np.errstate(over="ignore"):
            far_corner = origin + resolution * np.array(probability.shape[::-1])
        if not np.all(np.isfinite(far_corner)):
            raise ValueError(
                f"origin {origin.tolist()} and resolution {resolution!r} put the grid's far "
                "corner beyond the largest float: rescale the coordinates."
            )
        if variance is not None:
            variance = np.asarray(variance, dtype=np.float64)
            if variance.shape != probability.shape:
                raise ValueError(
                    f"variance has shape {variance.shape}, probability {probability.shape}."
                )
            if not np.all(variance >= 0):
                raise ValueError("variance must be non-negative (and hold no NaN).")
        if unknown is not None:
            unknown = np.asarray(unknown)
            if unknown.dtype != bool or unknown.shape != probability.shape:
                raise ValueError(
                    f"unknown must be a boolean array of shape {probability.shape}, got "
                    f"dtype {unknown.dtype} and shape {unknown.shape}."
                )
        self.probability = probability
        self.origin = origin
        self.resolution = float(resolution)
        self.variance = variance
        self.unknown = unknown

    # -- geometry ---------------------------------------------------------------------------

    @property
    def n_dims(self):
        return self.probability.ndim

    @property
    def shape(self):
        return self.probability.shape

    @property
    def extent(self):
        counts = np.array(self.shape[::-1])
        high = self.origin + self.resolution * counts
        return tuple(float(v) for pair in zip(self.origin, high, strict=True) for v in pair)

    def cell_centers(self):
        """Centres of all cells, shape (n_cells, n_dims), in the C order of ``probability``.

        Examples
        --------
        >>> from skoccmap import OccupancyGrid
        >>> grid = OccupancyGrid([[0.1, 0.9], [0.5, 0.8]], origin=(-1.0, 2.0), resolution=0.5)
        >>> grid.cell_centers().tolist()  # x fastest, rows upwards from the origin
        [[-0.75, 2.25], [-0.25, 2.25], [-0.75, 2.75], [-0.25, 2.75]]
        """
        return _cell_centers(self.origin, self.resolution, self.shape[::-1])

    # -- construction -----------------------------------------------------------------------

    @classmethod
    def from_estimator(
        cls,
        estimator,
        extent=None,
        resolution=0.1,
        *,
        unknown_variance="auto",
        observed_by=None,
        chunk_size=65_536,
        verbose=0,
    ):
        """Evaluate a fitted estimator on the cell centres of a grid.

        Parameters
        ----------
        estimator : fitted estimator
            Has ``predict_proba`` on segment rows (column 1 = P(occupied)); ``predict_var`` is
            used when present. The cells are zero-length segments, or points for an
            estimator fitted on as many columns as the grid has dimensions (e.g.
            ``layout="points"``).
        extent : tuple, array-like or None, default=None
            ``(xmin, xmax, ymin, ymax[, zmin, zmax])``; or data -- points (m, 2|3) or segment
            rows (m, 4|6) -- whose bounding box, snapped to multiples of ``resolution``, is
            covered (pass the hit points: no-return beams reach far outside the map); or
            ``None`` for the estimator's own ``extent_`` (as
            :class:`~skoccmap.baselines.OccupancyGridMap` has).
        resolution : float, default=0.1
            Cell edge length in metres.
        unknown_variance : float, "auto" or None, default="auto"
            Cells whose variance exceeds this are unknown. ``"auto"``: 90 % of the prior
            variance (the estimator's ``prior_variance`` where it has one, or the largest
            variance on the grid where that is larger or there is none) -- far from all
            data a GP's variance returns to its prior, the largest value it takes, while
            cells seen by a few beams keep much of it when the signal variance is large
            (on the Intel lab, every 10th scan, half the largest variance hid 43 % of the
            cells the map calls free; 90 % hides none of them and still marks the outside
            of the building unknown). ``None``, or an estimator without ``predict_var``: no
            cell is unknown.
        observed_by : Scans or None, default=None
            The training scans: cells that none of their beams crossed (sensor to hit, or,
            without a return, to the first cell past the sensor's that holds one of their
            hits) and that hold none of their hits are unknown as well. A continuous map
            extrapolates into space no sensor saw -- behind a wall seen from one side it
            stays confidently occupied for about a length scale -- which this draws as
            unknown, as a counting grid would. A beam without a return stops at a wall that
            other beams hit: on the Intel lab such beams cross glass walls to the maximum
            range, and counted whole they drew strokes of occupied cells behind the walls
            (their free pieces that far out are metres long). A beam that grazes a cell
            holding a hit stops there too: the rule errs towards unknown.
        chunk_size : int, default=65536
            At most this many query rows are built and predicted at once.
        verbose : int, default=0
            Print progress (cells done, elapsed time) to stderr when > 0.

        Returns
        -------
        grid : OccupancyGrid

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap import OccupancyGrid
        >>> from skoccmap.baselines import OccupancyGridMap
        >>> X = np.array([[0.0, 0.0, 0.95, 0.0], [1.0, 0.0, 1.0, 0.0]])
        >>> est = OccupancyGridMap(resolution=0.5).fit(X, [0, 1])
        >>> grid = OccupancyGrid.from_estimator(est, extent=(0, 1.5, -0.5, 0.5), resolution=0.5)
        >>> grid.shape, grid.probability.round(2).tolist()
        ((2, 3), [[0.5, 0.5, 0.5], [0.4, 0.5, 0.7]])
        """
        if not (is_number(resolution) and np.isfinite(resolution) and resolution > 0):
            raise ValueError(f"resolution must be a positive number, got {resolution!r}.")
        integral = isinstance(chunk_size, Integral) and not isinstance(chunk_size, bool)
        if not (integral and chunk_size >= 1):
            raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}.")
        if not hasattr(estimator, "predict_proba"):
            raise ValueError(f"estimator {type(estimator).__name__} has no predict_proba.")
        if not (
            unknown_variance is None
            or (isinstance(unknown_variance, str) and unknown_variance == "auto")
            or (is_number(unknown_variance) and unknown_variance > 0)  # False for NaN
        ):
            raise ValueError(
                "unknown_variance must be 'auto', None or a positive number (a variance), "
                f"got {unknown_variance!r}."
            )
        if extent is None:
            extent = getattr(estimator, "extent_", None)
            if extent is None:
                raise ValueError(
                    "extent=None needs an estimator with an extent_ attribute; pass extent as "
                    "(xmin, xmax, ymin, ymax[, zmin, zmax]) or the hit points to cover."
                )
        origin, counts = _grid_from_extent(extent, resolution)
        _check_grid_dims(estimator, origin.size)
        shape = tuple(int(c) for c in counts[::-1])
        proba, var = _predict_on_cells(estimator, origin, resolution, counts, chunk_size, verbose)
        proba = proba.reshape(shape)
        var = None if var is None else var.reshape(shape)
        unknown = None
        if var is not None and unknown_variance is not None:
            auto = isinstance(unknown_variance, str)
            reference = _reference_variance(estimator, var, origin, resolution, counts)
            threshold = _AUTO_UNKNOWN * reference if auto else float(unknown_variance)
            unknown = var > threshold
        if observed_by is not None:
            unseen = ~_observed_by(observed_by, origin, resolution, counts).reshape(shape)
            unknown = unseen if unknown is None else unknown | unseen
        return cls(proba, origin, resolution, variance=var, unknown=unknown)

    # -- export -----------------------------------------------------------------------------

    def _unknown_mask(self):
        return np.zeros(self.shape, dtype=bool) if self.unknown is None else self.unknown

    def trinary(self, free_threshold=ROS_FREE_THRESH, occupied_threshold=ROS_OCCUPIED_THRESH):
        """The map as ``map_server`` would load it: 100 occupied, 0 free, -1 unknown.

        Parameters
        ----------
        free_threshold, occupied_threshold : float, default=0.196, 0.65
            Cells with P(occupied) above ``occupied_threshold`` are occupied, below
            ``free_threshold`` free, in between (or flagged ``unknown``) unknown.

        Returns
        -------
        values : ndarray of int8, shape of ``probability``
        """
        _check_thresholds(free_threshold, occupied_threshold)
        values = np.full(self.shape, -1, dtype=np.int8)
        values[self.probability > occupied_threshold] = 100
        values[self.probability < free_threshold] = 0
        values[self._unknown_mask()] = -1
        return values

    def to_ros_occupancy_grid(
        self,
        *,
        frame_id="map",
        trinary=False,
        free_threshold=ROS_FREE_THRESH,
        occupied_threshold=ROS_OCCUPIED_THRESH,
    ):
        """The fields of a ROS ``nav_msgs/OccupancyGrid`` message, as a dict.

        Parameters
        ----------
        frame_id : str, default="map"
            ``header.frame_id``.
        trinary : bool, default=False
            ``data`` holds 0 / 100 / -1 (see :meth:`trinary`) instead of
            ``round(100 * probability)``.
        free_threshold, occupied_threshold : float, default=0.196, 0.65
            The thresholds of ``trinary=True`` (as :meth:`save_map_server` takes them).

        Returns
        -------
        message : dict
            ``{"header": {"frame_id"}, "info": {"resolution", "width", "height", "origin":
            {"position": {"x", "y", "z"}, "orientation": {"x", "y", "z", "w"}}}, "data"}``;
            ``data`` is int8, row-major starting with the row at the origin, -1 unknown.

        Examples
        --------
        >>> from skoccmap import OccupancyGrid
        >>> grid = OccupancyGrid([[0.1, 0.9], [0.5, 0.0]], origin=(-1.0, 2.0), resolution=0.5)
        >>> msg = grid.to_ros_occupancy_grid()
        >>> msg["info"]["width"], msg["info"]["height"], msg["info"]["origin"]["position"]
        (2, 2, {'x': -1.0, 'y': 2.0, 'z': 0.0})
        >>> msg["data"]  # cell (i, j) is data[i + j * width]
        array([10, 90, 50,  0], dtype=int8)
        """
        if self.n_dims != 2:
            raise ValueError("nav_msgs/OccupancyGrid is 2-D; this grid is 3-D (use to_points).")
        if not isinstance(frame_id, str):
            raise TypeError(f"frame_id must be a string, got {frame_id!r}.")
        # MapMetaData.resolution is a float32: it must not round to 0 or overflow.
        with np.errstate(over="ignore"):
            stored = np.float32(self.resolution)
        if not 0.0 < stored < np.inf:
            raise ValueError(
                f"resolution {self.resolution!r} is not a positive float32, as "
                "nav_msgs/MapMetaData.resolution must be: rescale the coordinates."
            )
        _check_thresholds(free_threshold, occupied_threshold)
        if trinary:
            data = self.trinary(free_threshold, occupied_threshold)
        else:
            data = np.rint(100.0 * self.probability).astype(np.int8)
            data[self._unknown_mask()] = -1
        height, width = self.shape
        return {
            "header": {"frame_id": frame_id},
            "info": {
                "resolution": self.resolution,
                "width": width,
                "height": height,
                "origin": {
                    "position": {"x": float(self.origin[0]), "y": float(self.origin[1]), "z": 0.0},
                    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                },
            },
            "data": data.ravel(),
        }

    def to_ros_message(
        self,
        *,
        frame_id="map",
        trinary=False,
        stamp=None,
        ros_version=2,
        free_threshold=ROS_FREE_THRESH,
        occupied_threshold=ROS_OCCUPIED_THRESH,
    ):
        """The map as a ``nav_msgs/OccupancyGrid`` message of the ``rosbags`` package.

        Needs ``rosbags`` (``pip install "skoccmap[ros]"``); no ROS installation.

        Parameters
        ----------
        frame_id : str, default="map"
            ``header.frame_id``.
        trinary : bool, default=False
            ``data`` holds 0 (free) / 100 (occupied) / -1 (unknown) at the map_server
            thresholds (see :meth:`trinary`) instead of ``round(100 * probability)``, with -1
            for unknown cells either way (see :meth:`to_ros_occupancy_grid`).
        stamp : float or None, default=None
            ``header.stamp`` and ``info.map_load_time`` in seconds; ``None``: now.
        ros_version : {1, 2}, default=2
            Message definitions of ROS 1 (Noetic) or ROS 2 (Humble); serialise the message
            with the matching ``rosbags`` type store.
        free_threshold, occupied_threshold : float, default=0.196, 0.65
            The thresholds of ``trinary=True``.

        Returns
        -------
        message : nav_msgs__msg__OccupancyGrid
            ``info.origin`` is the pose of the lower-left corner of cell ``(0, 0)``; ``data`` is
            row-major from the row at the origin.

        Examples
        --------
        >>> from skoccmap import OccupancyGrid
        >>> grid = OccupancyGrid([[0.1, 0.9], [0.5, 0.0]], origin=(-1.0, 2.0), resolution=0.5)
        >>> msg = grid.to_ros_message(stamp=0.0, trinary=True)
        >>> msg.info.width, msg.info.height, msg.info.origin.position.x, msg.data.tolist()
        (2, 2, -1.0, [0, 100, -1, 0])
        """
        from .datasets._rosbag import occupancy_grid_message

        fields = self.to_ros_occupancy_grid(
            frame_id=frame_id,
            trinary=trinary,
            free_threshold=free_threshold,
            occupied_threshold=occupied_threshold,
        )
        return occupancy_grid_message(fields, stamp=stamp, ros_version=ros_version)

    def write_rosbag(
        self,
        path,
        *,
        topic="/map",
        frame_id="map",
        trinary=False,
        stamp=None,
        ros_version=2,
        storage="sqlite3",
        free_threshold=ROS_FREE_THRESH,
        occupied_threshold=ROS_OCCUPIED_THRESH,
    ):
        """Write the map into a new ROS bag, one ``nav_msgs/OccupancyGrid`` on a latched topic.

        The topic is offered as map_server offers ``/map``: latched in ROS 1 (``latching=1``
        in the connection header), ``transient_local`` durability, reliable, history depth 1
        in ROS 2, so that a node subscribing after ``ros2 bag play`` / ``rosbag play``
        started still receives the map. Needs ``rosbags`` (``pip install "skoccmap[ros]"``).

        Parameters
        ----------
        path : str or path-like
            The new bag: a ``.bag`` file for ROS 1, a directory for ROS 2. It must not exist.
        topic : str, default="/map"
            Topic of the map.
        frame_id, trinary, stamp, ros_version, free_threshold, occupied_threshold
            As in :meth:`to_ros_message`.
        storage : {"sqlite3", "mcap"}, default="sqlite3"
            ROS 2 storage plugin.

        Returns
        -------
        path : pathlib.Path
            The bag written.

        Examples
        --------
        >>> import os, tempfile
        >>> from rosbags.highlevel import AnyReader
        >>> from skoccmap import OccupancyGrid
        >>> grid = OccupancyGrid([[0.1, 0.9], [0.5, 0.0]], origin=(-1.0, 2.0), resolution=0.5)
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     path = grid.write_rosbag(os.path.join(tmp, "map"), stamp=0.0)
        ...     with AnyReader([path]) as reader:
        ...         ((conn, _, raw),) = list(reader.messages())
        ...         msg = reader.deserialize(raw, conn.msgtype)
        >>> conn.topic, msg.info.width, msg.data.tolist()
        ('/map', 2, [10, 90, 50, 0])
        """
        from .datasets._rosbag import write_occupancy_grid

        fields = self.to_ros_occupancy_grid(
            frame_id=frame_id,
            trinary=trinary,
            free_threshold=free_threshold,
            occupied_threshold=occupied_threshold,
        )
        return write_occupancy_grid(
            fields, path, topic=topic, stamp=stamp, ros_version=ros_version, storage=storage
        )

    def to_points(self, occupied_threshold=ROS_OCCUPIED_THRESH):
        """Centres of the occupied cells (known, P(occupied) above the threshold).

        Parameters
        ----------
        occupied_threshold : float, default=0.65

        Returns
        -------
        points : ndarray of shape (n_occupied, n_dims)

        Examples
        --------
        >>> from skoccmap import OccupancyGrid
        >>> grid = OccupancyGrid([[0.1, 0.9], [0.5, 0.8]], origin=(-1.0, 2.0), resolution=0.5)
        >>> grid.to_points().tolist()
        [[-0.25, 2.25], [-0.25, 2.75]]
        """
        _check_thresholds(0.0, occupied_threshold)
        occupied = (self.probability > occupied_threshold) & ~self._unknown_mask()
        return self.cell_centers()[occupied.ravel()]

    def save_map_server(
        self, stem, *, free_threshold=ROS_FREE_THRESH, occupied_threshold=ROS_OCCUPIED_THRESH
    ):
        """Write ``<stem>.pgm`` and ``<stem>.yaml`` for ROS ``map_server`` (trinary mode).

        Pixels are 0 (occupied), 254 (free) and 205 (unknown), rows top (largest y) to bottom;
        the YAML names the image, ``resolution``, ``origin`` (lower-left corner),
        ``negate: 0``, ``occupied_thresh: 0.65``, ``free_thresh: 0.196`` and
        ``mode: trinary``, the thresholds under which map_server reloads these three pixel
        values as exactly :meth:`trinary`.

        Parameters
        ----------
        stem : str or path-like
            Output path without suffix.
        free_threshold, occupied_threshold : float, default=0.196, 0.65
            How probabilities are called free / occupied (see :meth:`trinary`).

        Returns
        -------
        yaml_path, pgm_path : pathlib.Path
        """
        if self.n_dims != 2:
            raise ValueError("map_server maps are 2-D; this grid is 3-D.")
        values = self.trinary(free_threshold, occupied_threshold)
        pixels = np.full(self.shape, _PIXEL_UNKNOWN, dtype=np.uint8)
        pixels[values == 100] = _PIXEL_OCCUPIED
        pixels[values == 0] = _PIXEL_FREE
        stem = Path(stem)
        # Appended, not with_suffix: a stem such as "intel_0.05" keeps its dot.
        pgm_path = stem.with_name(stem.name + ".pgm")
        yaml_path = stem.with_name(stem.name + ".yaml")
        height, width = self.shape
        with open(pgm_path, "wb") as fh:
            fh.write(f"P5\n{width} {height}\n255\n".encode("ascii"))
            fh.write(np.ascontiguousarray(pixels[::-1]).tobytes())
        yaml_path.write_text(
            f"image: {_yaml_string(pgm_path.name)}\n"
            f"resolution: {self.resolution!r}\n"
            f"origin: [{float(self.origin[0])!r}, {float(self.origin[1])!r}, 0.0]\n"
            "negate: 0\n"
            f"occupied_thresh: {ROS_OCCUPIED_THRESH}\n"
            f"free_thresh: {ROS_FREE_THRESH}\n"
            "mode: trinary\n",
            encoding="utf-8",
        )
        return yaml_path, pgm_path

    @classmethod
    def load_map_server(cls, yaml_path):
        """Read a ``map_server`` map (YAML + PGM) the way map_server interprets it.

        Supports the subset this package writes and common hand-made maps: binary ``P5``
        images (8-bit, scaled to 255 as map_server's image reader does), ``negate`` 0 or 1
        (or a YAML boolean, as Nav2 reads it), ``mode`` trinary (default), scale or raw
        (with ``negate: 0``), and an ``origin`` yaw of 0.

        Parameters
        ----------
        yaml_path : str or path-like
            The YAML file, or the stem :meth:`save_map_server` took (``<stem>.yaml`` is
            read when ``yaml_path`` itself is not a file).

        Returns
        -------
        grid : OccupancyGrid
            ``probability`` is the pixel's occupancy ``(255 - v) / 255`` (``v / 255`` when
            negated); ``unknown`` marks pixels map_server would load as -1, so
            :meth:`trinary` reproduces its ``OccupancyGrid.data`` in trinary mode -- with
            the YAML's ``free_thresh`` and ``occupied_thresh`` as its arguments when they
            are not the defaults (0.196 and 0.65). In raw mode a pixel is the occupancy in
            percent, as map_server loads it: ``probability`` is ``v / 100``, and pixels above
            100 are ``unknown`` (their ``probability`` 0.5), so that
            :meth:`to_ros_occupancy_grid` reproduces map_server's ``data``.

        Examples
        --------
        >>> import tempfile, os
        >>> from skoccmap import OccupancyGrid
        >>> grid = OccupancyGrid([[0.05, 0.9], [0.5, 0.1]], origin=(-1.0, 2.0), resolution=0.05)
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     yaml_path, _ = grid.save_map_server(os.path.join(tmp, "map"))
        ...     back = OccupancyGrid.load_map_server(yaml_path)
        >>> (back.trinary() == grid.trinary()).all(), back.origin.tolist(), back.resolution
        (np.True_, [-1.0, 2.0], 0.05)
        """
        yaml_path = Path(yaml_path)
        if not yaml_path.is_file() and yaml_path.name:
            stem_yaml = yaml_path.with_name(yaml_path.name + ".yaml")
            yaml_path = stem_yaml if stem_yaml.is_file() else yaml_path
        meta = _read_simple_yaml(yaml_path)
        for key in ("image", "resolution", "origin"):
            if key not in meta:
                raise ValueError(f"{yaml_path}: missing key {key!r}.")
        mode = meta.get("mode", "trinary")
        if mode not in ("trinary", "scale", "raw"):
            raise ValueError(
                f"{yaml_path}: mode {mode!r} is not supported (trinary, scale or raw)."
            )
        if not isinstance(meta["origin"], list) or len(meta["origin"]) not in (2, 3):
            raise ValueError(
                f"{yaml_path}: origin must be a list [x, y, yaw], got {meta['origin']!r}."
            )
        if len(meta["origin"]) > 2 and float(meta["origin"][2]) != 0.0:
            raise ValueError(
                f"{yaml_path}: the origin's yaw is {meta['origin'][2]}; only axis-aligned "
                "maps (yaw 0) are supported."
            )
        negate = str(meta.get("negate", 0))
        # Nav2's map_server reads a YAML boolean too (yaml-cpp's spellings of one).
        negate = _YAML_BOOLEANS.get(negate, negate)
        if negate not in ("0", "1"):
            raise ValueError(
                f"{yaml_path}: negate must be 0 or 1 (or true or false), got {negate!r}."
            )
        occupied_thresh = _yaml_number(meta, "occupied_thresh", yaml_path, ROS_OCCUPIED_THRESH)
        free_thresh = _yaml_number(meta, "free_thresh", yaml_path, ROS_FREE_THRESH)
        _check_thresholds(
            free_thresh, occupied_thresh, ("free_thresh", "occupied_thresh"), f"{yaml_path}: "
        )
        resolution = _yaml_number(meta, "resolution", yaml_path)
        if mode == "raw" and negate == "1":
            # ROS 1's map_server negates raw pixels, Nav2's does not: the map is ambiguous.
            raise ValueError(
                f"{yaml_path}: mode raw with negate 1 is not supported (ROS 1's map_server "
                "negates raw pixels, Nav2's does not)."
            )
        pixels = _read_pgm(yaml_path.parent / meta["image"])[::-1]
        origin = [float(v) for v in meta["origin"][:2]]
        if mode == "raw":
            # map_server's data is the pixel value itself, -1 outside 0..100.
            percent = np.rint(pixels)
            unknown = percent > 100
            occ = np.where(unknown, 0.5, percent / 100.0)
            return cls(occ, origin, resolution, unknown=unknown)
        occ = pixels / 255.0 if negate == "1" else (255.0 - pixels) / 255.0
        unknown = ~((occ > occupied_thresh) | (occ < free_thresh))
        if mode == "scale":
            unknown = np.zeros_like(unknown)
        return cls(occ, origin, resolution, unknown=unknown)

    def save(self, path):
        """Save to a compressed ``.npz`` file (no pickles); read back with :meth:`load`.

        Parameters
        ----------
        path : str or path-like
            ``.npz`` is appended when the name does not end with it (as numpy does);
            :meth:`load` takes the path either way.

        Examples
        --------
        >>> import tempfile, os
        >>> from skoccmap import OccupancyGrid
        >>> grid = OccupancyGrid([[0.1, 0.9]], origin=(0.0, 0.0), resolution=0.5,
        ...                      variance=[[0.2, 0.3]], unknown=[[False, True]])
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     grid.save(os.path.join(tmp, "office"))  # writes office.npz
        ...     back = OccupancyGrid.load(os.path.join(tmp, "office"))
        >>> back.variance.tolist(), back.unknown.tolist()
        ([[0.2, 0.3]], [[False, True]])
        """
        arrays = {
            "probability": self.probability,
            "origin": self.origin,
            "resolution": np.float64(self.resolution),
        }
        if self.variance is not None:
            arrays["variance"] = self.variance
        if self.unknown is not None:
            arrays["unknown"] = self.unknown
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path):
        """Load a grid written by :meth:`save`.

        Parameters
        ----------
        path : str or path-like
            The path given to :meth:`save`, with or without its ``.npz``.

        Returns
        -------
        grid : OccupancyGrid
            With the variance and unknown mask that were saved, if any.

        Examples
        --------
        See :meth:`save`.
        """
        path = Path(path)
        if not path.is_file() and path.suffix != ".npz":
            # save("maps/office") wrote maps/office.npz, a folder "office" there or not.
            with_npz = path.with_name(path.name + ".npz")
            if with_npz.is_file() or not path.exists():
                path = with_npz
        not_saved = f"{path} is not an OccupancyGrid saved by OccupancyGrid.save (a .npz)"
        # A truncated or damaged archive fails in zipfile or zlib, when opened or read.
        damaged = (EOFError, zipfile.BadZipFile, zlib.error)
        try:
            archive = np.load(path, allow_pickle=False)
        except FileNotFoundError:
            raise
        except (ValueError, OSError, *damaged):
            hint = "; a map_server map is read by OccupancyGrid.load_map_server(yaml_path)"
            raise ValueError(f"{not_saved}{hint}.") from None
        if not hasattr(archive, "files"):  # a single .npy array
            raise ValueError(f"{not_saved}: it holds one array.")
        with archive as data:
            # Names from the archive's list: on numpy < 1.24 ``k in data`` reads the array.
            missing = [k for k in ("probability", "origin", "resolution") if k not in data.files]
            if missing:
                raise ValueError(f"{not_saved}: it holds no {', '.join(missing)}.")
            try:
                names = ("probability", "origin", "resolution", "variance", "unknown")
                arrays = {k: data[k] for k in names if k in data.files}
            except damaged as exc:
                raise ValueError(f"{path} is damaged or truncated ({exc}).") from None
        return cls(
            arrays["probability"],
            arrays["origin"],
            float(arrays["resolution"]),
            variance=arrays.get("variance"),
            unknown=arrays.get("unknown"),
        )

    def __repr__(self):
        return (
            f"OccupancyGrid(shape={self.shape}, resolution={self.resolution}, "
            f"extent={tuple(round(v, 3) for v in self.extent)})"
        )


def _cell_centers(origin, resolution, counts, flat=None):
    """Centres of the cells of flat indices ``flat`` (all cells when None), in C order of an
    array of shape ``counts[::-1]``."""
    if flat is None:
        flat = np.arange(int(np.prod(counts)))
    index = np.unravel_index(flat, tuple(int(c) for c in counts[::-1]))[::-1]
    return origin + resolution * (np.column_stack(index) + 0.5)


def _duration(seconds):
    """``seconds`` rounded for a progress line: "12 s", "3 min", "2 h 5 min"."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    return f"{minutes} min" if minutes < 60 else f"{minutes // 60} h {minutes % 60} min"


def _output_of(estimator, method, queries, shape):
    """``estimator.method(queries)`` as an array, or a ValueError naming the shape expected
    (an estimator of another kind: numpy's IndexError or broadcasting error otherwise)."""
    out = np.asarray(getattr(estimator, method)(queries))
    if out.shape != shape:
        expected = "(n_queries, 2), column 1 P(occupied)" if len(shape) == 2 else "(n_queries,)"
        raise ValueError(
            f"{type(estimator).__name__}.{method} returned an array of shape {out.shape} for "
            f"{queries.shape[0]} queries; OccupancyGrid expects shape {expected}."
        )
    return out


def _predict_on_cells(estimator, origin, resolution, counts, chunk_size, verbose):
    """P(occupied) and (if available) variance on all cell centres, ``chunk_size`` at a time."""
    n_cells = int(np.prod(counts))
    proba = np.empty(n_cells)
    # One pass for both when the estimator offers it (the mixture of experts does): its
    # kernels are the cost, and predict_proba + predict_var would compute them twice.
    joint = getattr(estimator, "_predict_proba_and_var", None)
    has_var = joint is not None or hasattr(estimator, "predict_var")
    var = np.empty(n_cells) if has_var else None
    tic = time.perf_counter()
    next_report = 0.0
    for lo in range(0, n_cells, chunk_size):
        hi = min(lo + chunk_size, n_cells)
        centers = _cell_centers(origin, resolution, counts, np.arange(lo, hi))
        queries = queries_at(estimator, centers)  # zero-length segments, or points
        with queries_of_our_own():
            if joint is not None:
                proba[lo:hi], var[lo:hi] = joint(queries)
            else:
                p = _output_of(estimator, "predict_proba", queries, (hi - lo, 2))
                proba[lo:hi] = p[:, 1]
                if has_var:
                    var[lo:hi] = _output_of(estimator, "predict_var", queries, (hi - lo,))
        if verbose and (hi / n_cells >= next_report or hi == n_cells):
            elapsed = time.perf_counter() - tic
            # From the first chunk on: a grid far larger than meant (an extent set by
            # far-away hits) shows its cost before it is paid.
            left = (
                "" if hi == n_cells else f", about {_duration(elapsed * (n_cells - hi) / hi)} left"
            )
            print(
                f"[OccupancyGrid] {hi}/{n_cells} cells ({100 * hi / n_cells:.0f}%), "
                f"{elapsed:.1f} s{left}",
                file=sys.stderr,
                flush=True,
            )
            next_report = hi / n_cells + 0.1
    if not np.all(np.isfinite(proba)):
        raise ValueError("the estimator predicted NaN or infinite probabilities.")
    return np.clip(proba, 0.0, 1.0), var


def _reference_variance(estimator, var, origin, resolution, counts):
    """The largest variance a cell could have: the estimator's prior variance (sampled at up
    to 1024 cells spread over the grid) when it has ``prior_variance``, and never less than
    the largest on the grid. On a map every cell of which some beam saw, the grid's own
    largest variance is that of a well-observed cell."""
    reference = float(var.max())
    prior_variance = getattr(estimator, "prior_variance", None)
    if prior_variance is None:
        return reference
    n_cells = int(np.prod(counts))
    sample = np.unique(np.linspace(0, n_cells - 1, min(n_cells, 1024)).astype(np.int64))
    centers = _cell_centers(origin, resolution, counts, sample)
    with queries_of_our_own():
        prior = prior_variance(queries_at(estimator, centers))
    return max(reference, float(np.max(prior)))


def _observed_by(scans, origin, resolution, counts):
    """Cells of the grid that a beam of ``scans`` crossed or that hold one of their hits."""
    from .datasets._simulator import _observed_cells
    from .observations import Scans

    if not isinstance(scans, Scans) or scans.n_dims != len(counts):
        raise ValueError(
            f"observed_by must be a {len(counts)}-D skoccmap.observations.Scans, got "
            f"{type(scans).__name__}."
        )
    # A beam without a return that crosses a wall other beams hit saw nothing beyond it
    # (on the Intel lab such beams pass through glass), and the model's free evidence that
    # far along a beam is too coarse to draw: counted whole, they drew strokes of occupied
    # cells behind the walls.
    return _observed_cells(
        scans, np.asarray(origin, float), float(resolution), counts, through_hits=False
    )


def _yaml_string(text):
    """``text`` as a YAML scalar: plain where YAML reads it back unchanged as a string (a
    file name of letters, digits, ``_ . + -`` and inner spaces), single-quoted otherwise --
    a ``#`` after a space would start a comment, ``: `` a mapping, and a leading ``[``,
    ``*``, ``&`` or ``!`` another kind of node."""
    if re.fullmatch(r"[\w.][\w.+\- ]*[\w.+\-]|\w", text):
        return text
    return "'" + text.replace("'", "''") + "'"


def _yaml_value(text, path, key):
    """The value of a ``key: value`` line as YAML reads it: a single-quoted (``''`` a
    quote) or double-quoted string, or a plain scalar up to a comment (a ``#`` at its start,
    after whitespace or right after a flow sequence's ``]``; ``map#2.pgm`` is a name)."""
    if text[:1] == "'":
        match = re.fullmatch(r"'((?:[^']|'')*)'\s*(?:#.*)?", text)
        if match:
            return match.group(1).replace("''", "'")
    elif text[:1] == '"':
        match = re.fullmatch(r'("(?:[^"\\]|\\.)*")\s*(?:#.*)?', text)
        if match:
            try:
                return json.loads(match.group(1))
            except ValueError:
                pass
    else:
        # A flow sequence ends at its "]": a "#" right after it starts a comment.
        flow = re.fullmatch(r"(\[[^\]]*\])\s*#.*", text)
        if flow:
            return flow.group(1)
        return re.split(r"(?:^|\s)#", text, maxsplit=1)[0].strip()
    raise ValueError(f"{path}: cannot read the quoted value of {key!r}: {text!r}.")


def _read_simple_yaml(path):
    """``key: value`` lines of a map_server YAML (flat; lists in brackets)."""
    meta = {}
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise ValueError(
            f"{path} is not a map_server YAML file (it is not text); pass the .yaml file "
            "that names the image."
        ) from None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise ValueError(f"{path}: cannot read line {raw!r}.")
        key, value = key.strip(), value.strip()
        quoted = value[:1] in ("'", '"')
        value = _yaml_value(value, path, key)
        if value.startswith("[") and not quoted:
            try:
                meta[key] = [float(v) for v in value.strip("[]").split(",")]
            except ValueError:
                raise ValueError(
                    f"{path}: cannot read {key!r} as a list of numbers: {value!r}."
                ) from None
        else:
            meta[key] = value
    return meta


def _yaml_number(meta, key, path, default=None):
    """``meta[key]`` (or ``default``) as a float, or a ValueError naming the key and file."""
    value = meta.get(key, default)
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {key} must be a number, got {value!r}.") from None


def _read_pgm(path):
    """Pixels of a binary (P5, maxval <= 255) PGM image, rows top to bottom."""
    data = Path(path).read_bytes()
    unsupported = f"{path}: only binary 8-bit PGM (P5) images are supported"
    if not data.startswith(b"P5"):
        raise ValueError(f"{unsupported}; this file does not start with P5.")
    fields, pos = [], 0
    while len(fields) < 4 and pos < len(data):
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            newline = data.find(b"\n", pos)
            pos = len(data) if newline < 0 else newline + 1
            continue
        end = pos
        while end < len(data) and not data[end : end + 1].isspace():
            end += 1
        fields.append(data[pos:end])
        pos = end
    try:
        width, height, maxval = (int(f) for f in fields[1:4])
    except ValueError:
        width = height = maxval = 0
    if len(fields) < 4 or fields[0] != b"P5" or width <= 0 or height <= 0 or not 0 < maxval <= 255:
        raise ValueError(f"{unsupported}; its header is not one (got {b' '.join(fields)!r}).")
    if len(data) - (pos + 1) < width * height:
        raise ValueError(
            f"{path}: the image is truncated: {width} x {height} pixels need {width * height} "
            f"bytes, it holds {max(len(data) - (pos + 1), 0)}."
        )
    pixels = np.frombuffer(data, dtype=np.uint8, count=width * height, offset=pos + 1)
    # Scaled to 0-255, as image readers deliver a PGM of a smaller maxval.
    return pixels.reshape(height, width).astype(np.float64) * (255.0 / maxval)
