"""A small 3-D world -- a box-shaped room with box obstacles -- and a 3-D laser scanner."""

import numpy as np
from sklearn.utils import Bunch

from ..observations import _check_max_range
from ._simulator import (
    _GRID_DOC,
    _SURFACE_TOL,
    _check_points,
    _check_rays,
    _chunks,
    _ground_truth_grid,
    _spread,
    simulate_scans,
)

__all__ = ["Room3D", "make_room3d_scans", "scanner_directions"]


def _slab(o, d, lo, hi):
    """Entry and exit parameters (k, m) of rays ``o + t d`` (k, 3) through boxes (m, 3)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo[None] - o[:, None]) / d[:, None]
        t1 = (hi[None] - o[:, None]) / d[:, None]
    parallel = d[:, None] == 0
    inside = (o[:, None] >= lo[None]) & (o[:, None] <= hi[None])
    near = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
    far = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
    return near.max(axis=-1), far.min(axis=-1)


class Room3D:
    """A closed box-shaped room with solid box obstacles, with exact ray casting.

    Free space is the open interior of the room, ``0 < x < size[0]`` (likewise y, z), minus the
    obstacles; everything else (the walls, floor, ceiling and beyond) is occupied.

    Parameters
    ----------
    size : array-like of shape (3,), default=(6.0, 5.0, 3.0)
        Room dimensions in metres; the room spans ``[0, size]`` on each axis.
    obstacles : array-like of shape (n_obstacles, 6), default=None
        Boxes ``[x_min, y_min, z_min, x_max, y_max, z_max]``.
    wall_thickness : float, default=0.2
        How far beyond the room :attr:`extent` reaches, so that a grid over it holds the walls.

    Attributes
    ----------
    n_dims : int
        Always 3.
    extent : ndarray of shape (6,)
        ``(x_min, x_max, y_min, y_max, z_min, z_max)`` of the room and its walls.

    Examples
    --------
    >>> from skoccmap.datasets import Room3D
    >>> room = Room3D(size=(4, 4, 2), obstacles=[[2, 2, 0, 3, 3, 1]])
    >>> room.cast([[1.0, 2.5, 0.5], [1.0, 2.5, 0.5]], [[1, 0, 0], [0, 0, 1]])
    array([1. , 1.5])
    >>> room.occupancy([[2.5, 2.5, 0.5], [1.0, 1.0, 1.0], [5.0, 1.0, 1.0]])
    array([1, 0, 1])
    """

    n_dims = 3

    def __init__(self, size=(6.0, 5.0, 3.0), obstacles=None, wall_thickness=0.2):
        size = np.asarray(size, dtype=np.float64)
        if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
            raise ValueError(f"size must be 3 positive finite numbers, got {size}.")
        obstacles = np.zeros((0, 6)) if obstacles is None else np.asarray(obstacles, float)
        if obstacles.ndim != 2 or obstacles.shape[1] != 6:
            raise ValueError(
                "obstacles must have shape (n_obstacles, 6) rows "
                f"[x_min, y_min, z_min, x_max, y_max, z_max], got {obstacles.shape}."
            )
        if not np.all(np.isfinite(obstacles)) or np.any(obstacles[:, 3:] < obstacles[:, :3]):
            raise ValueError("obstacles must be finite boxes with max >= min on every axis.")
        thickness = float(wall_thickness)
        if not np.isfinite(thickness) or thickness <= 0:
            raise ValueError(f"wall_thickness must be positive, got {wall_thickness!r}.")
        self.size = size
        self.obstacles = obstacles
        self.wall_thickness = thickness

    def __repr__(self):
        return f"Room3D(size={self.size.tolist()}, n_obstacles={len(self.obstacles)})"

    @property
    def extent(self):
        t = self.wall_thickness
        return np.ravel(np.column_stack([np.full(3, -t), self.size + t]))

    def cast(self, origins, directions, max_range=np.inf):
        """Distance along each ray to the first surface (room boundary or obstacle).

        Parameters
        ----------
        origins : array-like of shape (n_rays, 3)
        directions : array-like of shape (n_rays, 3)
            Normalised here; zero vectors are rejected.
        max_range : float, default=inf
            Larger distances are reported as ``inf``.

        Returns
        -------
        ranges : ndarray of shape (n_rays,)
            0 for an origin in occupied space.

        Examples
        --------
        >>> from skoccmap.datasets import Room3D
        >>> Room3D(size=(2, 2, 2)).cast([[1, 1, 1]], [[1, 1, 0]]).round(6)
        array([1.414214])
        """
        origins, directions = _check_rays(origins, directions, 3)
        # As Environment2D.cast: the default (inf) stays, anything else must be a range.
        max_range = np.inf if max_range == np.inf else _check_max_range(max_range)
        zero = np.zeros(3)
        _, ranges = _slab(origins, directions, zero[None], self.size[None])
        ranges = ranges[:, 0]
        if len(self.obstacles):
            lo, hi = self.obstacles[:, :3], self.obstacles[:, 3:]
            for chunk in _chunks(len(origins), len(lo)):
                near, far = _slab(origins[chunk], directions[chunk], lo, hi)
                t = np.where((near <= far) & (far >= 0), np.maximum(near, 0.0), np.inf)
                ranges[chunk] = np.minimum(ranges[chunk], t.min(axis=1))
        ranges[self.occupancy(origins).astype(bool)] = 0.0
        ranges[ranges >= max_range] = np.inf
        return ranges

    def occupancy(self, points):
        """True occupancy: 1 outside the open room interior or in an obstacle (surfaces count).

        Parameters
        ----------
        points : array-like of shape (n_points, 3)

        Returns
        -------
        occupied : ndarray of shape (n_points,), dtype int64

        Examples
        --------
        >>> from skoccmap.datasets import Room3D
        >>> Room3D(size=(2, 2, 2)).occupancy([[1, 1, 1], [1, 1, 2]])
        array([0, 1])
        """
        points = _check_points(points, 3)
        tol = _SURFACE_TOL
        occupied = ~np.all((points > tol) & (points < self.size - tol), axis=1)
        for lo, hi in zip(self.obstacles[:, :3], self.obstacles[:, 3:], strict=True):
            occupied |= np.all((points >= lo - tol) & (points <= hi + tol), axis=1)
        return occupied.astype(np.int64)

    def distance(self, points):
        """Distance from each point to occupied space: the room's boundary or an obstacle.

        Parameters
        ----------
        points : array-like of shape (n_points, 3)

        Returns
        -------
        distance : ndarray of shape (n_points,)
            Euclidean distance to the nearest occupied point; 0 in occupied space.

        Examples
        --------
        >>> from skoccmap.datasets import Room3D
        >>> room = Room3D(size=(4, 4, 2), obstacles=[[2, 2, 0, 3, 3, 1]])
        >>> room.distance([[0.5, 1.0, 1.0], [2.5, 2.5, 1.2], [2.5, 2.5, 0.5], [5.0, 1.0, 1.0]])
        array([0.5, 0.2, 0. , 0. ])
        """
        points = _check_points(points, 3)
        # Everything outside the open room is occupied: inside it, the nearest occupied point
        # lies straight across the nearest face.
        out = np.maximum(np.minimum(points, self.size - points).min(axis=1), 0.0)
        for lo, hi in zip(self.obstacles[:, :3], self.obstacles[:, 3:], strict=True):
            gap = np.maximum(np.maximum(lo - points, points - hi), 0.0)
            out = np.minimum(out, np.linalg.norm(gap, axis=1))
        return out

    def _cells_occupied(self, centres, resolution):
        # A voxel is occupied when its closed cube meets occupied space (closed sets, as the
        # cells of Environment2D): a voxel touching a face counts. On a grid aligned with the
        # room the faces lie on voxel boundaries, and a hit on a face with range noise falls
        # into the voxel in front of it half the time; that voxel is a wall's, not free space.
        half, tol = resolution / 2, _SURFACE_TOL
        lo, hi = centres - half, centres + half
        occupied = np.any((lo <= tol) | (hi >= self.size - tol), axis=1)
        for o_lo, o_hi in zip(self.obstacles[:, :3], self.obstacles[:, 3:], strict=True):
            occupied |= np.all(np.minimum(hi, o_hi) - np.maximum(lo, o_lo) >= -tol, axis=1)
        return occupied

    def ground_truth_grid(self, resolution, extent=None, *, scans=None):
        return _ground_truth_grid(self, resolution, extent, scans)

    ground_truth_grid.__doc__ = (
        "True occupancy of a regular grid of cubic voxels.\n"
        + _GRID_DOC.format(n2=6, zext=", z_min, z_max", d=3, idx="[z, y, x]")
        + """
        Examples
        --------
        >>> from skoccmap.datasets import Room3D
        >>> grid = Room3D(size=(3, 3, 3), wall_thickness=1.0).ground_truth_grid(1.0)
        >>> grid.shape, int(grid.occupied.sum())
        ((5, 5, 5), 124)

        Voxels touching a wall count as occupied: only the centre one is free.

        >>> grid.points[grid.occupied == 0]
        array([[1.5, 1.5, 1.5]])
        """
    )


def scanner_directions(azimuths, elevations):
    """Unit beam directions of a scanner sweeping a grid of azimuth x elevation angles.

    Parameters
    ----------
    azimuths : array-like of shape (n_azimuths,)
        Radians counter-clockwise about the sensor's z axis from its x axis.
    elevations : array-like of shape (n_elevations,)
        Radians above the sensor's x-y plane.

    Returns
    -------
    directions : ndarray of shape (n_elevations * n_azimuths, 3)
        Sensor-frame unit vectors, azimuth varying fastest.

    Examples
    --------
    >>> from skoccmap.datasets import scanner_directions
    >>> scanner_directions([0.0], [0.0])
    array([[1., 0., 0.]])
    """
    azimuths, elevations = np.asarray(azimuths, float), np.asarray(elevations, float)
    for name, angles in (("azimuths", azimuths), ("elevations", elevations)):
        if angles.ndim != 1 or angles.size == 0 or not np.all(np.isfinite(angles)):
            raise ValueError(
                f"{name} must be a non-empty 1-D array of finite angles, got {angles!r}."
            )
    az, el = np.meshgrid(azimuths, elevations)
    az, el = az.ravel(), el.ravel()
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def make_room3d_environment():
    """The default :class:`Room3D`: a 6 m x 5 m x 3 m room with a table, a cabinet, a pillar.

    Returns
    -------
    room : Room3D

    Examples
    --------
    >>> from skoccmap.datasets import make_room3d_environment
    >>> make_room3d_environment()
    Room3D(size=[6.0, 5.0, 3.0], n_obstacles=3)
    """
    obstacles = [
        [1.0, 3.2, 0.0, 2.6, 4.2, 0.8],  # table
        [4.6, 0.0, 0.0, 6.0, 0.7, 2.0],  # cabinet against a wall
        [3.4, 2.2, 0.0, 3.8, 2.6, 3.0],  # pillar, floor to ceiling
    ]
    return Room3D(size=(6.0, 5.0, 3.0), obstacles=obstacles)


def make_room3d_scans(
    *,
    n_azimuths=12,
    n_elevations=4,
    max_range=4.0,
    noise_std=0.0,
    random_state=None,
    free_margin=0.05,
):
    """Simulated 3-D laser scans in a small furnished room; a few hundred observations.

    Four sensor poses at 1.2 m height, each turned to a different heading, sweep
    ``n_azimuths`` azimuths over 360 degrees times ``n_elevations`` elevations in
    [-30, 30] degrees. With the defaults, noise-free: 192 beams, 366 observations (174
    hits, 174 return beams, 18 no-return beams).

    Parameters
    ----------
    n_azimuths, n_elevations : int, default=12, 4
        Size of the scanner's angular grid. A single elevation is horizontal.
    max_range : float, default=4.0
        Sensor range in metres (long diagonals of the room give no-return beams).
    noise_std : float, default=0.0
        Gaussian range noise in metres.
    random_state : int, RandomState instance or None, default=None
        Seed of the range noise.
    free_margin : float, default=0.05
        Gap between return beams and their hits, see
        :func:`~skoccmap.observations.scans_to_observations`.

    Returns
    -------
    data : sklearn.utils.Bunch
        ``X`` (n, 6) segment rows, ``y``, ``kind``, ``scan_index``, ``scans``
        (:class:`~skoccmap.observations.Scans`), ``environment`` (:class:`Room3D`).

    Examples
    --------
    >>> from skoccmap.datasets import make_room3d_scans
    >>> import numpy as np
    >>> data = make_room3d_scans(random_state=0)
    >>> data.X.shape[1], len(data.scans), data.scans.n_beams
    (6, 4, 48)
    >>> len(data.X), np.bincount(data.kind).tolist()
    (366, [174, 174, 18])
    """
    for name, value in (("n_azimuths", n_azimuths), ("n_elevations", n_elevations)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    room = make_room3d_environment()
    positions = np.array([[1.2, 1.2, 1.2], [4.5, 1.8, 1.2], [4.8, 4.0, 1.2], [2.0, 2.4, 1.2]])
    yaws = np.array([0.3, 1.9, 3.5, 5.1])
    quats = np.column_stack(
        [np.cos(yaws / 2), np.zeros_like(yaws), np.zeros_like(yaws), np.sin(yaws / 2)]
    )
    poses = np.column_stack([positions, quats])
    azimuths = np.linspace(0.0, 2 * np.pi, n_azimuths, endpoint=False)
    elevations = np.deg2rad(_spread(-30.0, 30.0, n_elevations))
    directions = scanner_directions(azimuths, elevations)
    scans = simulate_scans(
        room, poses, directions, max_range, noise_std=noise_std, random_state=random_state
    )
    X, y, kind, scan_index = scans.to_observations(free_margin, return_scan_index=True)
    return Bunch(X=X, y=y, kind=kind, scan_index=scan_index, scans=scans, environment=room)
