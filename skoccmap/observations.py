"""Laser scans to observations: segment rows ``[start, end]`` with occupancy labels.

Every estimator in skoccmap sees one representation: a float array of rows
``[start_1..start_D, end_1..end_D]`` (D = 2 or 3). A hit point is a zero-length segment
(``start == end``, label 1 = occupied); a laser beam is the segment from the sensor towards what
it saw (label 0 = free). Each row also carries a *kind* code:

- :data:`HIT` (0): the end point of a beam with a return -- a zero-length segment, ``y = 1``;
- :data:`RETURN` (1): the free part of a beam with a return -- from the sensor to ``free_margin``
  short of the hit, ``y = 0``;
- :data:`NO_RETURN` (2): a beam without a return (range at or beyond ``max_range``, ``inf`` or
  ``NaN``) -- from the sensor to ``max_range`` along the beam, ``y = 0``.

Pose conventions
----------------
2-D poses are ``[x, y, theta]`` (metres, radians); beam angles are radians counter-clockwise from
the heading ``theta``. 3-D poses are ``[x, y, z, qw, qx, qy, qz]``: the sensor position and a unit
quaternion (scalar first) rotating sensor-frame vectors into the world frame; beams are unit
direction vectors in the sensor frame.
"""

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from ._validation import check_segments, segment_dim, warn

__all__ = [
    "HIT",
    "RETURN",
    "NO_RETURN",
    "ObservationKind",
    "Scans",
    "scans_to_observations",
    "beam_directions",
    "as_segments",
    "split_segments",
    "segment_endpoints",
    "segment_midpoints",
    "segment_lengths",
]


class ObservationKind(IntEnum):
    """Kind code of an observation row; the members compare equal to the plain ints."""

    HIT = 0
    RETURN = 1
    NO_RETURN = 2


HIT = int(ObservationKind.HIT)
RETURN = int(ObservationKind.RETURN)
NO_RETURN = int(ObservationKind.NO_RETURN)

# A unit quaternion or beam direction read from a log may carry float32 rounding;
# anything further from unit length than this is a caller's mistake, not rounding.
_UNIT_TOL = 1e-3

# Pieces computed at once by split_segments (a few tens of MB of temporaries).
_PIECE_BLOCK = 1 << 18
# Relative rounding of a segment's length that split_segments ignores: a segment as long
# as k pieces, or as a graded boundary, up to rounding, takes no sliver of a last piece.
_LENGTH_ROUNDING = 1e-9

_POSE_COLUMNS = {3: 2, 7: 3}


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def _number(value):
    """``float(value)``, with TypeError for a bool (which would read as a length of 0 or 1)
    and for text ("8" is no length, though ``float`` reads it)."""
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise TypeError(value)
    return float(value)


def _check_max_range(max_range):
    try:
        value = _number(max_range)
    except (TypeError, ValueError):
        raise ValueError(f"max_range must be a positive number, got {max_range!r}.") from None
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"max_range must be a positive finite number, got {max_range!r}.")
    return value


def _check_free_margin(free_margin):
    try:
        value = _number(free_margin)
    except (TypeError, ValueError):
        raise ValueError(
            f"free_margin must be a non-negative number, got {free_margin!r}."
        ) from None
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"free_margin must be a non-negative finite number, got {free_margin!r}.")
    return value


# |qw| at most this at every pose: a rotation of more than 174 degrees, the sensor upside
# down; a level robot's quaternions given [qx, qy, qz, qw] read so (their qx is 0).
_UPSIDE_DOWN_QW = 0.05


def _check_poses(poses):
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] not in _POSE_COLUMNS:
        raise ValueError(
            "poses must have shape (n_scans, 3) for 2-D [x, y, theta] or (n_scans, 7) for 3-D "
            f"[x, y, z, qw, qx, qy, qz], got shape {poses.shape}."
        )
    if poses.shape[0] == 0:
        raise ValueError("poses is empty: at least one scan is needed.")
    if not np.all(np.isfinite(poses)):
        raise ValueError("poses contains NaN or infinite values.")
    if poses.shape[1] == 7:
        norms = np.linalg.norm(poses[:, 3:], axis=1)
        if np.any(np.abs(norms - 1.0) > _UNIT_TOL):
            worst = int(np.argmax(np.abs(norms - 1.0)))
            raise ValueError(
                "poses[:, 3:7] must be unit quaternions [qw, qx, qy, qz]; "
                f"row {worst} has norm {norms[worst]:.6g}."
            )
        poses = poses.copy()
        poses[:, 3:] /= norms[:, None]
        if poses.shape[0] > 1 and np.all(np.abs(poses[:, 3]) <= _UPSIDE_DOWN_QW):
            warn(
                "Every pose turns the sensor upside down (qw = poses[:, 3] near 0). "
                "skoccmap reads quaternions scalar first, [qw, qx, qy, qz]; ROS messages "
                "and scipy's Rotation.as_quat() give [qx, qy, qz, qw]: reorder them with "
                "np.roll(q, 1, axis=1). A sensor mounted upside down gives these poses too.",
                UserWarning,
            )
    return poses


def _check_ranges(ranges, n_scans):
    ranges = np.asarray(ranges, dtype=np.float64)
    if ranges.ndim != 2:
        raise ValueError(
            f"ranges must have shape (n_scans, n_beams), got {ranges.ndim} dimension(s) "
            f"(shape {ranges.shape})."
        )
    if ranges.shape[0] != n_scans:
        raise ValueError(
            f"ranges has {ranges.shape[0]} row(s) but poses has {n_scans} scan(s); "
            "they must match."
        )
    if ranges.shape[1] == 0:
        raise ValueError("ranges has no beams (n_beams = 0).")
    # NaN and +inf mean "no return"; only -inf and negative values are invalid.
    with np.errstate(invalid="ignore"):
        if np.any(ranges < 0):
            raise ValueError("ranges must be non-negative (NaN or inf mean no return).")
    return ranges


def _returned(ranges, max_range):
    """Readings with a return: in (0, max_range); False for 0 (no reading), NaN and inf."""
    with np.errstate(invalid="ignore"):
        return (ranges > 0.0) & (ranges < max_range)


def _unread(ranges):
    """Readings of 0: many drivers' code for "no measurement"."""
    return ranges == 0.0


def _shape_hint(beam_axis, n_beams):
    """The end of a wrong-angles message: which array holds how many beams, when they differ."""
    if beam_axis and beam_axis[0] != n_beams:
        return (
            f"; ranges has {n_beams} beam(s) (columns) per scan and angles "
            f"{beam_axis[0]}, one per beam."
        )
    return "."


def _check_angles(angles, n_scans, n_beams, n_dims):
    angles = np.asarray(angles, dtype=np.float64)
    if n_dims == 2:
        valid = ((n_beams,), (n_scans, n_beams))
        if angles.shape not in valid and angles.shape[-2:] == (n_beams, 3) and angles.ndim < 4:
            raise ValueError(
                f"angles holds 3-D beam directions of shape {angles.shape}, but the poses are "
                "2-D [x, y, theta]: 3-D beams need 3-D poses of shape (n_scans, 7), "
                "[x, y, z, qw, qx, qy, qz]; 2-D poses take one angle per beam."
            )
        if angles.shape not in valid:
            raise ValueError(
                f"angles must have shape ({n_beams},) shared by all scans or ({n_scans}, "
                f"{n_beams}) per scan for 2-D poses, got shape {angles.shape}"
                + _shape_hint(angles.shape[-1:] if angles.ndim <= 2 else (), n_beams)
            )
    else:
        if angles.shape not in ((n_beams, 3), (n_scans, n_beams, 3)):
            raise ValueError(
                f"angles must hold unit beam directions of shape ({n_beams}, 3) or ({n_scans}, "
                f"{n_beams}, 3) for 3-D poses, got shape {angles.shape}"
                + _shape_hint(angles.shape[-2:-1] if angles.ndim in (2, 3) else (), n_beams)
            )
    if not np.all(np.isfinite(angles)):
        raise ValueError("angles contains NaN or infinite values.")
    span = np.ptp(angles, axis=-1).max() if n_dims == 2 and angles.size else 0.0
    if span > 2 * np.pi + 1e-9:
        # A scan's beams span at most one turn: more is degrees read as radians, which
        # would fan the beams around the sensor several times.
        warn(
            f"The beam angles of a scan span {span:.4g} radians, more "
            "than a full turn: if they are in degrees, pass np.radians(angles).",
            UserWarning,
        )
    if n_dims == 3:
        norms = np.linalg.norm(angles, axis=-1)
        if np.any(np.abs(norms - 1.0) > _UNIT_TOL):
            raise ValueError(
                "angles must be unit direction vectors for 3-D scans; norms range over "
                f"[{norms.min():.6g}, {norms.max():.6g}]."
            )
        angles = angles / norms[..., None]
    return angles


def _check_scan_arrays(poses, ranges, angles, max_range):
    poses = _check_poses(poses)
    ranges = _check_ranges(ranges, poses.shape[0])
    n_dims = _POSE_COLUMNS[poses.shape[1]]
    angles = _check_angles(angles, *ranges.shape, n_dims)
    return poses, ranges, angles, _check_max_range(max_range)


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def _quaternion_to_matrix(q):
    """Rotation matrices (n, 3, 3) of unit quaternions ``[qw, qx, qy, qz]`` (n, 4)."""
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def _directions(poses, angles, n_beams):
    """World-frame unit beam directions (n_scans, n_beams, D) of validated arrays."""
    n_scans = poses.shape[0]
    if poses.shape[1] == 3:
        heading = poses[:, 2:3] + np.broadcast_to(angles, (n_scans, n_beams))
        return np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    sensor = np.broadcast_to(angles, (n_scans, n_beams, 3))
    return np.einsum("sij,sbj->sbi", _quaternion_to_matrix(poses[:, 3:]), sensor)


def beam_directions(poses, angles):
    """World-frame unit direction of every beam.

    Parameters
    ----------
    poses : array-like of shape (n_scans, 3) or (n_scans, 7)
        2-D poses ``[x, y, theta]`` or 3-D poses ``[x, y, z, qw, qx, qy, qz]``.
    angles : array-like
        2-D: beam angles (radians, counter-clockwise from the heading) of shape (n_beams,) or
        (n_scans, n_beams). 3-D: unit sensor-frame directions of shape (n_beams, 3) or
        (n_scans, n_beams, 3).

    Returns
    -------
    directions : ndarray of shape (n_scans, n_beams, D)
        Unit vectors in the world frame.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.observations import beam_directions
    >>> beam_directions([[0.0, 0.0, np.pi / 2]], [0.0]).round(6)
    array([[[0., 1.]]])
    """
    poses = _check_poses(poses)
    n_dims = _POSE_COLUMNS[poses.shape[1]]
    angles_arr = np.asarray(angles, dtype=np.float64)
    if angles_arr.ndim < (1 if n_dims == 2 else 2):
        shapes = "(n_beams,) or (n_scans, n_beams)" if n_dims == 2 else "(n_beams, 3) or more"
        raise ValueError(
            f"angles must have shape {shapes} for {n_dims}-D poses, got shape "
            f"{angles_arr.shape}; one beam is an array of one."
        )
    n_beams = angles_arr.shape[-1] if n_dims == 2 else angles_arr.shape[-2]
    angles = _check_angles(angles_arr, poses.shape[0], n_beams, n_dims)
    return _directions(poses, angles, n_beams)


# --------------------------------------------------------------------------------------------
# Scans -> observations
# --------------------------------------------------------------------------------------------


def scans_to_observations(
    poses, ranges, angles, max_range, *, free_margin=0.05, return_scan_index=False
):
    """Turn laser scans into labelled segment rows.

    A beam with range ``r < max_range`` gives a :data:`HIT` (a zero-length segment at the hit
    point, ``y = 1``) and, when ``r > free_margin``, a :data:`RETURN` beam from the sensor to
    ``free_margin`` short of the hit (``y = 0``); a hit within ``free_margin`` of the sensor has
    no free part. A beam with ``r >= max_range``, ``inf`` or ``NaN`` gives a :data:`NO_RETURN`
    beam from the sensor to ``max_range`` (``y = 0``). A reading of 0 gives no row: many
    drivers write 0 for "no measurement", and neither a hit at the sensor nor free space up
    to ``max_range`` is what the sensor saw (set readings below a sensor's minimum range
    to 0 to drop them too).

    Rows are grouped by scan, in scan order; within a scan come its hits, then its return beams,
    then its no-return beams, each in beam order.

    Parameters
    ----------
    poses : array-like of shape (n_scans, 3) or (n_scans, 7)
        Sensor poses: 2-D ``[x, y, theta]`` or 3-D ``[x, y, z, qw, qx, qy, qz]`` with a unit
        quaternion (scalar first) rotating the sensor frame into the world frame.
    ranges : array-like of shape (n_scans, n_beams)
        Measured ranges in metres; ``inf``, ``NaN`` or values ``>= max_range`` mean no return,
        0 no reading.
    angles : array-like
        2-D: beam angles in radians counter-clockwise from the heading, shape (n_beams,) shared
        by all scans or (n_scans, n_beams). 3-D: unit beam directions in the sensor frame, shape
        (n_beams, 3) or (n_scans, n_beams, 3).
    max_range : float
        Sensor range in metres; the length of no-return beams.
    free_margin : float, default=0.05
        Gap in metres between the end of a return beam and its hit, so that free and occupied
        observations never coincide.
    return_scan_index : bool, default=False
        Whether to return the scan index of every row.

    Returns
    -------
    X : ndarray of shape (n_observations, 2 * D)
        Segment rows ``[start, end]``.
    y : ndarray of shape (n_observations,), dtype int64
        1 for hits (occupied), 0 for beams (free).
    kind : ndarray of shape (n_observations,), dtype int64
        :data:`HIT`, :data:`RETURN` or :data:`NO_RETURN`.
    scan_index : ndarray of shape (n_observations,), dtype int64
        Index of the scan each row comes from; only if ``return_scan_index``.

    Raises
    ------
    ValueError
        For non-finite poses, negative ranges, mismatched shapes, no scans or beams,
        ``max_range <= 0`` or ``free_margin < 0``.

    Warns
    -----
    UserWarning
        When ``free_margin`` leaves more than half of the returned beams without a free row.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.observations import scans_to_observations
    >>> X, y, kind = scans_to_observations(
    ...     poses=[[0.0, 0.0, 0.0]], ranges=[[2.0, np.inf]], angles=[0.0, np.pi / 2],
    ...     max_range=4.0, free_margin=0.5)
    >>> X.round(6)
    array([[2. , 0. , 2. , 0. ],
           [0. , 0. , 1.5, 0. ],
           [0. , 0. , 0. , 4. ]])
    >>> y, kind
    (array([1, 0, 0]), array([0, 1, 2]))
    """
    poses, ranges, angles, max_range = _check_scan_arrays(poses, ranges, angles, max_range)
    free_margin = _check_free_margin(free_margin)
    n_scans, n_beams = ranges.shape
    n_dims = _POSE_COLUMNS[poses.shape[1]]

    origins = poses[:, None, :n_dims]
    directions = _directions(poses, angles, n_beams)
    unread, returned = _unread(ranges), _returned(ranges, max_range)
    r = np.where(returned, ranges, 0.0)[..., None]

    hit_points = origins + r * directions
    starts = np.broadcast_to(origins, directions.shape)
    ends = np.stack(
        [hit_points, origins + (r - free_margin) * directions, origins + max_range * directions],
        axis=1,
    )  # (n_scans, kind, n_beams, D)
    starts = np.stack([hit_points, starts, starts], axis=1)
    valid = np.stack(
        [returned, returned & (r[..., 0] > free_margin), ~(returned | unread)], axis=1
    )
    n_returned, n_free = int(returned.sum()), int(valid[:, 1].sum())
    if n_free < n_returned / 2:
        warn(
            f"free_margin={free_margin:g} m is at least as long as {n_returned - n_free} of "
            f"the {n_returned} returned ranges: their beams give no free row, only a hit. "
            "free_margin is the gap between a beam's free part and its hit (a few cm).",
            UserWarning,
        )

    # Boolean indexing walks (scan, kind, beam) in C order: the documented row order.
    X = np.concatenate([starts[valid], ends[valid]], axis=1)
    kind_grid = np.broadcast_to(np.arange(3)[None, :, None], valid.shape)
    kind = kind_grid[valid].astype(np.int64)
    y = (kind == HIT).astype(np.int64)
    if not return_scan_index:
        return X, y, kind
    scan_grid = np.broadcast_to(np.arange(n_scans)[:, None, None], valid.shape)
    return X, y, kind, scan_grid[valid].astype(np.int64)


@dataclass(eq=False)
class Scans:
    """A sequence of laser scans taken from known poses.

    Parameters
    ----------
    poses : array-like of shape (n_scans, 3) or (n_scans, 7)
        2-D ``[x, y, theta]`` or 3-D ``[x, y, z, qw, qx, qy, qz]`` (unit quaternion, scalar
        first, rotating the sensor frame into the world frame; normalised on construction).
    ranges : array-like of shape (n_scans, n_beams)
        Ranges in metres; ``inf``/``NaN`` or ``>= max_range`` mean no return, 0 no reading.
    angles : array-like
        2-D: beam angles in radians counter-clockwise from the heading, (n_beams,) shared or
        (n_scans, n_beams) per scan. 3-D: unit beam directions in the sensor frame, (n_beams, 3)
        or (n_scans, n_beams, 3).
    max_range : float
        Sensor range in metres.
    timestamps : array-like of shape (n_scans,), default=None
        Acquisition times in seconds, if known.

    Attributes
    ----------
    n_dims : int
        Spatial dimension D (2 or 3).
    n_scans, n_beams : int
        Number of scans and of beams per scan.

    Notes
    -----
    Indexing with an int, a slice, an integer array or a boolean mask over scans returns a new
    :class:`Scans` (an int keeps a single scan, not a bare array). ``len(scans)`` is the number
    of scans.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.observations import Scans
    >>> scans = Scans(poses=np.zeros((4, 3)), ranges=np.full((4, 2), 1.0),
    ...               angles=[0.0, np.pi / 2], max_range=5.0)
    >>> len(scans), scans.n_dims, len(scans[::2]), len(scans[np.array([True, False, True, True])])
    (4, 2, 2, 3)
    >>> X, y, kind = scans.to_observations(free_margin=0.1)
    >>> X.shape, int(y.sum())
    ((16, 4), 8)
    """

    poses: np.ndarray
    ranges: np.ndarray
    angles: np.ndarray
    max_range: float
    timestamps: np.ndarray | None = None

    def __post_init__(self):
        self.poses, self.ranges, self.angles, self.max_range = _check_scan_arrays(
            self.poses, self.ranges, self.angles, self.max_range
        )
        if self.timestamps is not None:
            timestamps = np.asarray(self.timestamps, dtype=np.float64)
            if timestamps.shape != (self.n_scans,):
                raise ValueError(
                    f"timestamps must have shape ({self.n_scans},), got {timestamps.shape}."
                )
            if not np.all(np.isfinite(timestamps)):
                raise ValueError("timestamps contains NaN or infinite values.")
            self.timestamps = timestamps

    @property
    def n_dims(self):
        return _POSE_COLUMNS[self.poses.shape[1]]

    @property
    def n_scans(self):
        return self.ranges.shape[0]

    @property
    def n_beams(self):
        return self.ranges.shape[1]

    def __len__(self):
        return self.n_scans

    def __repr__(self):
        stamps = "" if self.timestamps is None else ", with timestamps"
        return (
            f"Scans({self.n_scans} scan{'s' * (self.n_scans != 1)} x {self.n_beams} "
            f"beam{'s' * (self.n_beams != 1)}, {self.n_dims}-D, "
            f"max_range={self.max_range:g}{stamps})"
        )

    def __getitem__(self, index):
        if isinstance(index, (int, np.integer)):
            if not -self.n_scans <= index < self.n_scans:
                raise IndexError(f"scan index {index} out of range for {self.n_scans} scans.")
            index = [index]
        elif isinstance(index, tuple):
            # numpy would read scans[0, 1] as scan 0, beam 1; a Scans holds whole scans.
            raise IndexError(
                "Scans are indexed by scan only (an int, a slice, a 1-D integer array or a "
                f"boolean mask), got the tuple {index!r}; read beams from .ranges."
            )
        elif not isinstance(index, slice):
            index = np.asarray(index)
            if index.dtype == bool:
                if index.shape != (self.n_scans,):
                    raise IndexError(
                        f"boolean mask must have shape ({self.n_scans},), got {index.shape}."
                    )
            elif not np.issubdtype(index.dtype, np.integer) or index.ndim != 1:
                raise IndexError(
                    "Scans can be indexed by an int, a slice, a 1-D integer array or a boolean "
                    f"mask, got an array of dtype {index.dtype} and shape {index.shape}."
                )
        if np.arange(self.n_scans)[index].size == 0:
            raise IndexError(
                f"the selection holds none of the {self.n_scans} scans; a Scans holds at least "
                "one."
            )
        per_scan = self.angles.ndim == (2 if self.n_dims == 2 else 3)
        return Scans(
            poses=self.poses[index],
            ranges=self.ranges[index],
            angles=self.angles[index] if per_scan else self.angles,
            max_range=self.max_range,
            timestamps=None if self.timestamps is None else self.timestamps[index],
        )

    def directions(self):
        """World-frame unit beam directions, shape (n_scans, n_beams, n_dims)."""
        return _directions(self.poses, self.angles, self.n_beams)

    def origins(self):
        """Sensor positions, shape (n_scans, n_dims)."""
        return self.poses[:, : self.n_dims].copy()

    def returned(self):
        """Boolean mask (n_scans, n_beams) of beams with a return (range in (0, max_range))."""
        return _returned(self.ranges, self.max_range)

    def unread(self):
        """Boolean mask (n_scans, n_beams) of readings of 0: no measurement, no return or
        free space (:func:`scans_to_observations` gives them no row).

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap.observations import Scans
        >>> scans = Scans([[0.0, 0.0, 0.0]], [[0.0, 2.0, np.inf]], [-1.0, 0.0, 1.0], 5.0)
        >>> scans.unread(), scans.returned()
        (array([[ True, False, False]]), array([[False,  True, False]]))
        """
        return _unread(self.ranges)

    def hit_points(self):
        """Hit points of all beams with a return, shape (n_hits, n_dims), in scan/beam order."""
        returned = self.returned()
        points = self.poses[:, None, : self.n_dims] + (
            np.where(returned, self.ranges, 0.0)[..., None] * self.directions()
        )
        return points[returned]

    def to_observations(self, free_margin=0.05, *, return_scan_index=False):
        """Labelled segment rows of these scans (:func:`skoccmap.scans_to_observations`
        with their poses, ranges, beam angles and maximum range).

        Parameters
        ----------
        free_margin : float, default=0.05
            Gap in metres between the end of a return beam and its hit.
        return_scan_index : bool, default=False
            Whether to return the scan index of every row.

        Returns
        -------
        X : ndarray of shape (n_observations, 2 * D)
            Segment rows ``[start, end]``.
        y : ndarray of shape (n_observations,)
            1 for hits (occupied), 0 for beams (free).
        kind : ndarray of shape (n_observations,)
            :data:`HIT`, :data:`RETURN` or :data:`NO_RETURN` per row.
        scan_index : ndarray of shape (n_observations,)
            Index of the scan each row comes from; only if ``return_scan_index``.

        Examples
        --------
        >>> from skoccmap.datasets import make_paper_scans
        >>> scans = make_paper_scans(random_state=0).scans
        >>> X, y, kind = scans[:2].to_observations()
        >>> X.shape[1], sorted(set(y.tolist()))
        (4, [0, 1])
        """
        return scans_to_observations(
            self.poses,
            self.ranges,
            self.angles,
            self.max_range,
            free_margin=free_margin,
            return_scan_index=return_scan_index,
        )


# --------------------------------------------------------------------------------------------
# Segment helpers
# --------------------------------------------------------------------------------------------


def as_segments(points):
    """Turn points into zero-length segment rows ``[p, p]``.

    Parameters
    ----------
    points : array-like of shape (n_points, D)
        Query points or hit points.

    Returns
    -------
    X : ndarray of shape (n_points, 2 * D)

    Examples
    --------
    >>> from skoccmap.observations import as_segments
    >>> as_segments([[1.0, 2.0]])
    array([[1., 2., 1., 2.]])
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] == 0:
        raise ValueError(
            f"points must be a 2-D array of shape (n_points, D), got shape {points.shape}."
        )
    if not np.all(np.isfinite(points)):
        raise ValueError("points contains NaN or infinite values.")
    return np.concatenate([points, points], axis=1)


def segment_endpoints(X):
    """Split segment rows into start and end points.

    Parameters
    ----------
    X : array-like of shape (n_segments, 2 * D)

    Returns
    -------
    start, end : ndarray of shape (n_segments, D)

    Examples
    --------
    >>> from skoccmap.observations import segment_endpoints
    >>> segment_endpoints([[0.0, 0.0, 3.0, 4.0]])
    (array([[0., 0.]]), array([[3., 4.]]))
    """
    X = check_segments(X, allow_empty=True)
    d = segment_dim(X)
    return X[:, :d], X[:, d:]


def segment_midpoints(X):
    """Midpoint of every segment row.

    Parameters
    ----------
    X : array-like of shape (n_segments, 2 * D)

    Returns
    -------
    midpoints : ndarray of shape (n_segments, D)

    Examples
    --------
    >>> from skoccmap.observations import segment_midpoints
    >>> segment_midpoints([[0.0, 0.0, 3.0, 4.0]])
    array([[1.5, 2. ]])
    """
    start, end = segment_endpoints(X)
    return 0.5 * (start + end)


def segment_lengths(X):
    """Euclidean length of every segment row (0 for points).

    Parameters
    ----------
    X : array-like of shape (n_segments, 2 * D)

    Returns
    -------
    lengths : ndarray of shape (n_segments,)

    Examples
    --------
    >>> from skoccmap.observations import segment_lengths
    >>> segment_lengths([[0.0, 0.0, 3.0, 4.0], [1.0, 1.0, 1.0, 1.0]])
    array([5., 0.])
    """
    start, end = segment_endpoints(X)
    return np.linalg.norm(end - start, axis=1)


def split_segments(X, max_length, *, end_length=None, graded=None):
    """Cut segments into pieces no longer than ``max_length``, shorter towards their end.

    A whole beam is one observation of the *average* of the latent function along it
    under :class:`~skoccmap.IntegralKernel`, which barely constrains the function near the
    beam's end, next to the wall it hit. Bounded pieces keep that free-space evidence local;
    pieces that halve in length towards the end (down to ``end_length``) make it finest
    where it matters, next to the wall, for a number of pieces that grows with the
    logarithm of the beam's length there.

    Parameters
    ----------
    X : array-like of shape (n_segments, 2 * D)
        Segment rows ``[start, end]``; points (zero-length rows) are kept as they are.
    max_length : float or None
        Longest piece in metres, > 0; ``None`` or ``inf`` sets no bound.
    end_length : float or None, default=None
        Length of the last piece of a graded segment; the pieces before it are twice as
        long each, up to ``max_length``, and the rest is cut into equal pieces no longer
        than ``max_length``. ``None`` cuts every segment into equal pieces.
    graded : array-like of bool of shape (n_segments,), default=None
        Segments cut with pieces shrinking towards their end (e.g. beams with a return);
        ``None`` means all of them, when ``end_length`` is given.

    Returns
    -------
    pieces : ndarray of shape (n_pieces, 2 * D)
        The pieces, in the order of their segments and from start to end along each.
    source : ndarray of shape (n_pieces,), dtype intp
        Row of ``X`` each piece comes from (``X[source]`` repeats labels, scans, ...).

    Examples
    --------
    >>> from skoccmap.observations import split_segments
    >>> pieces, source = split_segments([[0.0, 0.0, 5.0, 0.0], [1.0, 1.0, 1.0, 1.0]], 2.0)
    >>> pieces
    array([[0.        , 0.        , 1.66666667, 0.        ],
           [1.66666667, 0.        , 3.33333333, 0.        ],
           [3.33333333, 0.        , 5.        , 0.        ],
           [1.        , 1.        , 1.        , 1.        ]])
    >>> source
    array([0, 0, 0, 1])
    >>> pieces, _ = split_segments([[0.0, 0.0, 5.0, 0.0]], 2.0, end_length=0.5)
    >>> pieces[:, [0, 2]]  # pieces of 0.5 and 1 m at the end, 3.5 m cut in two before
    array([[0.  , 1.75],
           [1.75, 3.5 ],
           [3.5 , 4.5 ],
           [4.5 , 5.  ]])
    """
    X = check_segments(X, allow_empty=True)
    max_length = _check_piece_length(max_length, "max_length", allow_none=True)
    if end_length is not None:
        end_length = _check_piece_length(end_length, "end_length")
    lengths = segment_lengths(X)
    # Boundaries of the graded pieces, as distances from the end: 0, e, 3e, 7e, ...
    ends = np.zeros(1)
    if end_length is not None and X.shape[0]:
        n_graded = int(np.ceil(np.log2(max(lengths.max(), end_length) / end_length))) + 1
        piece = end_length * 2.0 ** np.arange(n_graded)
        ends = np.r_[0.0, np.cumsum(piece[piece < max_length])]
    is_graded = np.ones(X.shape[0], bool) if graded is None else np.asarray(graded, bool)
    if is_graded.shape != (X.shape[0],):
        raise ValueError(f"graded must have shape ({X.shape[0]},), got {is_graded.shape}.")
    # Graded pieces that fit strictly inside each segment (up to rounding: a 15 m beam has
    # boundaries 1, 3, 7, 15), then equal pieces for the rest.
    inside = ends[None, 1:] < lengths[:, None] * (1.0 - _LENGTH_ROUNDING)
    n_end = np.where(is_graded, np.sum(inside, axis=1), 0)
    rest = lengths - ends[n_end]
    n_rest = np.ones(X.shape[0], dtype=np.intp)
    if np.isfinite(max_length):
        n_float = np.maximum(np.ceil(rest / max_length - _LENGTH_ROUNDING), 1)
        # Past the largest array index the count wrapped to a negative number, and numpy
        # stopped on "negative dimensions are not allowed".
        if n_float.sum() > np.iinfo(np.intp).max:
            raise ValueError(
                f"Cutting X into pieces of at most max_length={max_length:g} m gives "
                f"{n_float.sum():.3g} pieces, more than an array can hold (the longest "
                f"segment is {lengths.max():.3g} m long): pass a larger max_length, or drop "
                "segments far longer than the rest."
            )
        n_rest = n_float.astype(np.intp)
    n_pieces = n_end + n_rest
    source = np.repeat(np.arange(X.shape[0]), n_pieces)
    d = X.shape[1] // 2
    pieces = np.empty((source.size, 2 * d))
    # Pieces a block of segments at a time: a dozen temporaries per piece would otherwise
    # cost gigabytes on logs of millions of beams.
    first = np.cumsum(n_pieces) - n_pieces
    for block in _row_blocks(source.size, _PIECE_BLOCK):
        seg = source[block]
        # Index of each piece counted from its segment's end: 0 .. n_pieces - 1.
        p = n_pieces[seg] - 1 - (np.arange(block.start, block.stop) - first[seg])
        in_end = p < n_end[seg]
        u = np.where(in_end, 0, p - n_end[seg])
        base, step = ends[n_end[seg]], rest[seg] / n_rest[seg]
        near = np.where(in_end, ends[np.minimum(p, ends.size - 1)], base + u * step)
        far = np.where(in_end, ends[np.minimum(p + 1, ends.size - 1)], base + (u + 1) * step)
        with np.errstate(invalid="ignore", divide="ignore"):
            t0 = np.nan_to_num(1.0 - far / lengths[seg])[:, None]
            t1 = np.nan_to_num(1.0 - near / lengths[seg], nan=1.0)[:, None]
        start, end = X[seg, :d], X[seg, d:]
        pieces[block, :d] = start + t0 * (end - start)
        pieces[block, d:] = start + t1 * (end - start)
    return pieces, source


def _check_piece_length(value, name, allow_none=False):
    if value is None and allow_none:
        return np.inf
    try:
        value = _number(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number > 0, got {value!r}.") from None
    if not value > 0:
        raise ValueError(f"{name} must be > 0, got {value!r}.")
    if np.isinf(value) and not allow_none:
        raise ValueError(f"{name} must be finite, got {value!r}.")
    return value


def _row_blocks(n, size):
    """Slices of at most ``size`` of ``n`` rows (none when ``n`` is 0, which
    :func:`sklearn.utils.gen_batches` rejects)."""
    return (slice(lo, min(lo + size, n)) for lo in range(0, n, size))
