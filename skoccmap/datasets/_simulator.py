"""A laser range finder simulated against exact geometry (2-D walls, 3-D boxes).

Ray casting is exact and vectorised: a 2-D wall is the set of points within
``wall_thickness / 2`` of a line segment (a capsule), so a ray meets it either on one of the two
sides parallel to the segment or on one of the two round caps. Work is done in chunks of rays so
memory stays bounded for large scans.
"""

import numpy as np
from sklearn.utils import Bunch, check_random_state

from ..grid import _checked_counts
from ..observations import Scans, _check_max_range, beam_directions

__all__ = ["Environment2D", "simulate_scans"]

# Pairs (ray or point) x (wall or cell) evaluated at once; bounds the temporaries to a few MB.
_CHUNK_PAIRS = 1 << 18
# Hit points lie exactly on an obstacle's surface; rounding must not make them free.
_SURFACE_TOL = 1e-9


def _spread(low, high, n):
    """``n`` values evenly from ``low`` to ``high``; a single one at the middle.

    ``np.linspace`` gives one value at ``low``: a scanner with one beam would point it to the
    edge of its field of view instead of straight ahead.
    """
    return np.linspace(low, high, n) if n > 1 else np.array([0.5 * (low + high)])


def _chunks(n_rows, n_cols):
    step = max(1, _CHUNK_PAIRS // max(n_cols, 1))
    for start in range(0, n_rows, step):
        yield slice(start, min(start + step, n_rows))


def _check_rays(origins, directions, n_dims):
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    if origins.ndim != 2 or origins.shape[1] != n_dims:
        raise ValueError(f"origins must have shape (n_rays, {n_dims}), got {origins.shape}.")
    if directions.shape != origins.shape:
        raise ValueError(
            f"directions must have the shape of origins {origins.shape}, got {directions.shape}."
        )
    if not (np.all(np.isfinite(origins)) and np.all(np.isfinite(directions))):
        raise ValueError("origins and directions must be finite.")
    norms = np.linalg.norm(directions, axis=1, keepdims=True)
    if np.any(norms == 0):
        raise ValueError("directions contains zero vectors.")
    return origins, directions / norms


# --------------------------------------------------------------------------------------------
# Grids and the cells that beams cross
# --------------------------------------------------------------------------------------------


def _grid(extent, resolution, n_dims, own_extent=False):
    """Lower corner, cell counts and cell centres of a regular grid over ``extent``.

    ``own_extent``: the extent is an environment's own, which is flat along an axis where
    every wall is (zero-thickness walls in a line): the grid holds one cell across there.
    """
    try:
        resolution = float(resolution)
    except (TypeError, ValueError):
        raise ValueError(f"resolution must be a positive number, got {resolution!r}.") from None
    if not np.isfinite(resolution) or resolution <= 0:
        raise ValueError(f"resolution must be a positive finite number, got {resolution!r}.")
    extent = np.asarray(extent, dtype=np.float64)
    if extent.shape != (2 * n_dims,) or not np.all(np.isfinite(extent)):
        raise ValueError(
            f"extent must be {2 * n_dims} finite numbers (min, max per axis), got {extent}."
        )
    lo, hi = extent[0::2], extent[1::2]
    if own_extent:
        flat = hi == lo
        lo, hi = np.where(flat, lo - resolution / 2, lo), np.where(flat, hi + resolution / 2, hi)
    if np.any(hi <= lo):
        raise ValueError(f"extent must have max > min on every axis, got {extent.tolist()}.")
    counts = _checked_counts(np.maximum(np.ceil((hi - lo) / resolution - 1e-9), 1), resolution)
    axes = [lo[j] + (np.arange(counts[j]) + 0.5) * resolution for j in range(n_dims)]
    # Reversed axes with 'ij' indexing: reshape(shape) gives images indexed [y, x] ([z, y, x]).
    mesh = np.meshgrid(*axes[::-1], indexing="ij")
    centres = np.column_stack([m.ravel() for m in mesh[::-1]])
    return lo, counts, centres


def _cells_crossed(starts, ends, lo, resolution, counts, stop=None, stops=None):
    """Flat indices of grid cells that segments pass through (exact, any dimension).

    A segment crosses the cell lines at parameters ``t`` where a coordinate reaches a grid line;
    between two consecutive crossings it stays inside one cell, found from the midpoint.
    ``stop`` (one flag per cell) and ``stops`` (one per segment): the flagged segments end in
    the first flagged cell they enter after the cell they start in.
    """
    n_dims = len(counts)
    strides = np.cumprod(np.r_[1, counts[:-1]])  # x fastest, matching _grid's ordering
    seen = np.zeros(int(np.prod(counts)), dtype=bool)
    for chunk in _chunks(len(starts), 64):
        s = (starts[chunk] - lo) / resolution
        e = (ends[chunk] - lo) / resolution
        beam_ids, ts = [np.arange(len(s))] * 2, [np.zeros(len(s)), np.ones(len(s))]
        for j in range(n_dims):
            a, b = np.minimum(s[:, j], e[:, j]), np.maximum(s[:, j], e[:, j])
            k_lo = np.maximum(np.floor(a) + 1, 0)
            k_hi = np.minimum(np.ceil(b) - 1, counts[j])
            n = np.maximum(k_hi - k_lo + 1, 0).astype(int)
            ids = np.repeat(np.arange(len(s)), n)
            k = k_lo[ids] + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
            ts.append((k - s[ids, j]) / (e[ids, j] - s[ids, j]))
            beam_ids.append(ids)
        t, ids = np.concatenate(ts), np.concatenate(beam_ids)
        order = np.lexsort((t, ids))
        t, ids = t[order], ids[order]
        same = ids[1:] == ids[:-1]
        mid, ids = 0.5 * (t[1:] + t[:-1])[same], ids[1:][same]
        cell = np.floor(s[ids] + mid[:, None] * (e[ids] - s[ids])).astype(int)
        # End points on a cell boundary belong to the cell above it (floor), like any point.
        end_cells = np.floor(e).astype(int)
        if stop is not None:
            cell, ids, ended = _up_to_first_stop(cell, ids, stop, stops[chunk], counts, strides)
            end_cells = end_cells[~ended]
        cell = np.concatenate([cell, np.floor(s).astype(int), end_cells])
        inside = np.all((cell >= 0) & (cell < counts), axis=1)
        seen[cell[inside] @ strides] = True
    return seen


def _up_to_first_stop(cell, ids, stop, stops, counts, strides):
    """The crossed cells (sorted by segment, then along it) up to each stopping segment's
    first ``stop`` cell after its start cell, that cell included; and which segments ended
    there."""
    inside = np.all((cell >= 0) & (cell < counts), axis=1)
    flat = np.where(inside, cell @ strides, 0)
    blocked = inside & stop[flat] & stops[ids]
    # The start cell does not stop its segment (a sensor beside a wall, on a coarse grid).
    first = np.r_[0, np.flatnonzero(ids[1:] != ids[:-1]) + 1]
    blocked[first] = False
    # Blocked cells before each crossing, counted within its own segment.
    before = np.cumsum(blocked) - blocked
    start_count = np.repeat(before[first], np.diff(np.r_[first, ids.size]))
    keep = before == start_count
    ended = np.zeros(stops.size, dtype=bool)
    ended[ids[blocked]] = True
    return cell[keep], ids[keep], ended


def _observed_cells(scans, lo, resolution, counts, through_hits=True):
    """Cells crossed by any beam (sensor to hit, or to max_range) or holding a hit.

    ``through_hits=False``: a beam without a return counts only up to the first cell that
    holds a hit after the sensor's own cell, that cell included. A reading of 0 (no
    measurement) observes nothing.
    """
    read = ~scans.unread().ravel()
    origins = np.repeat(scans.origins(), scans.n_beams, axis=0)[read]
    directions = scans.directions().reshape(-1, scans.n_dims)[read]
    returned = scans.returned().ravel()[read]
    ranges = np.where(returned, scans.ranges.ravel()[read], scans.max_range)
    ends = origins + ranges[:, None] * directions
    stop = None
    if not through_hits:
        stop = _cells_crossed(ends[returned], ends[returned], lo, resolution, counts)
    return _cells_crossed(
        origins, ends, lo, resolution, counts, stop=stop, stops=None if stop is None else ~returned
    )


def _ground_truth_grid(environment, resolution, extent, scans):
    n_dims = environment.n_dims
    own_extent = extent is None
    extent = environment.extent if own_extent else extent
    lo, counts, centres = _grid(extent, resolution, n_dims, own_extent)
    resolution = float(resolution)
    occupied = environment._cells_occupied(centres, resolution)
    observed = None
    if scans is not None:
        if not isinstance(scans, Scans) or scans.n_dims != n_dims:
            raise ValueError(f"scans must be a {n_dims}-D skoccmap.observations.Scans.")
        observed = _observed_cells(scans, lo, resolution, counts)
    return Bunch(
        points=centres,
        occupied=occupied.astype(np.int64),
        observed=observed,
        shape=tuple(int(c) for c in counts[::-1]),
        extent=np.ravel(np.column_stack([lo, lo + counts * resolution])),
        resolution=resolution,
    )


_GRID_DOC = """
        Parameters
        ----------
        resolution : float
            Cell side in metres.
        extent : array-like of shape ({n2},), default=None
            ``(x_min, x_max, y_min, y_max{zext})`` of the grid; defaults to :attr:`extent`. The
            grid starts at the minima and covers the maxima (the last cell may overhang).
        scans : Scans, default=None
            If given, ``observed`` marks the cells that any of their beams crossed (sensor to hit,
            or to ``max_range``) or that hold a hit: the cells a map built from these scans can
            know about. Scoring only these cells keeps never-observable space (inside walls,
            behind them) from dominating an AUC.

        Returns
        -------
        grid : sklearn.utils.Bunch
            ``points`` (n_cells, {d}) cell centres; ``occupied`` (n_cells,) 1 where the cell
            overlaps an obstacle (closed sets), else 0; ``observed`` (n_cells,) bool or None;
            ``shape`` such that ``occupied.reshape(shape)`` is an image indexed {idx};
            ``extent`` of the grid actually built; ``resolution``.
"""


# --------------------------------------------------------------------------------------------
# 2-D environment of walls
# --------------------------------------------------------------------------------------------


def _point_segment_distance(points, a, b):
    """Distances (n_points, n_segments) between points and segments ``a -> b`` (2-D or 3-D)."""
    ab = b - a
    ab2 = np.einsum("md,md->m", ab, ab)
    rel = points[:, None, :] - a[None]
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.einsum("nmd,md->nm", rel, ab) / ab2
    s = np.clip(np.nan_to_num(s, nan=0.0), 0.0, 1.0)  # zero-length walls: distance to a
    return np.linalg.norm(rel - s[..., None] * ab[None], axis=-1)


def _segment_hits_box(a, b, lo, hi):
    """Whether segments ``a -> b`` meet closed boxes ``[lo, hi]`` (all (n, m, D)); slab test."""
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - a) / d
        t1 = (hi - a) / d
    parallel = d == 0
    inside_slab = (a >= lo) & (a <= hi)
    t_near = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t0, t1))
    t_far = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t0, t1))
    enter = np.maximum(t_near.max(axis=-1), 0.0)
    leave = np.minimum(t_far.min(axis=-1), 1.0)
    return enter <= leave


class Environment2D:
    """A 2-D world of straight walls of a given thickness, with exact ray casting.

    Parameters
    ----------
    walls : array-like of shape (n_walls, 4)
        Wall centre lines ``[x0, y0, x1, y1]`` in metres.
    wall_thickness : float, default=0.1
        Thickness in metres; the occupied set is every point within ``wall_thickness / 2`` of a
        centre line (a capsule around each wall).

    Attributes
    ----------
    n_dims : int
        Always 2.
    extent : ndarray of shape (4,)
        ``(x_min, x_max, y_min, y_max)`` of the occupied set (matplotlib's ``imshow`` order).

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.datasets import Environment2D
    >>> env = Environment2D([[2.0, -1.0, 2.0, 1.0]], wall_thickness=0.2)
    >>> env.cast([[0.0, 0.0], [0.0, 0.0]], [[1.0, 0.0], [-1.0, 0.0]], max_range=5.0)
    array([1.9, inf])
    >>> env.occupancy([[2.05, 0.0], [1.5, 0.0]])
    array([1, 0])
    """

    n_dims = 2

    def __init__(self, walls, wall_thickness=0.1):
        walls = np.asarray(walls, dtype=np.float64)
        if walls.ndim != 2 or walls.shape[1] != 4 or walls.shape[0] == 0:
            raise ValueError(
                f"walls must have shape (n_walls, 4) rows [x0, y0, x1, y1], got {walls.shape}."
            )
        if not np.all(np.isfinite(walls)):
            raise ValueError("walls contains NaN or infinite values.")
        thickness = float(wall_thickness)
        if not np.isfinite(thickness) or thickness < 0:
            raise ValueError(
                f"wall_thickness must be a non-negative finite number, got {wall_thickness!r}."
            )
        self.walls = walls
        self.wall_thickness = thickness

    def __repr__(self):
        return f"Environment2D(n_walls={len(self.walls)}, wall_thickness={self.wall_thickness})"

    @property
    def extent(self):
        h = self.wall_thickness / 2
        xs, ys = self.walls[:, 0::2], self.walls[:, 1::2]
        return np.array([xs.min() - h, xs.max() + h, ys.min() - h, ys.max() + h])

    def cast(self, origins, directions, max_range=np.inf):
        """Distance along each ray to the first wall surface.

        Parameters
        ----------
        origins : array-like of shape (n_rays, 2)
        directions : array-like of shape (n_rays, 2)
            Ray directions (normalised here; zero vectors are rejected).
        max_range : float, default=inf
            Rays that meet nothing closer than this return ``inf``.

        Returns
        -------
        ranges : ndarray of shape (n_rays,)
            Distance to the first wall surface; 0 for an origin inside a wall; ``inf`` when no
            wall lies within ``max_range``.

        Examples
        --------
        >>> from skoccmap.datasets import Environment2D
        >>> Environment2D([[0.0, 3.0, 4.0, 3.0]], wall_thickness=0.0).cast([[1.0, 0.0]], [[0, 1]])
        array([3.])
        """
        origins, directions = _check_rays(origins, directions, 2)
        max_range = np.inf if max_range == np.inf else _check_max_range(max_range)
        ranges = np.empty(len(origins))
        for chunk in _chunks(len(origins), len(self.walls)):
            ranges[chunk] = self._cast_chunk(origins[chunk], directions[chunk])
        ranges[ranges >= max_range] = np.inf
        return ranges

    def _cast_chunk(self, o, d):
        h = self.wall_thickness / 2
        a, b = self.walls[:, :2], self.walls[:, 2:]
        length = np.linalg.norm(b - a, axis=1)
        u = np.divide(b - a, length[:, None], out=np.zeros_like(a), where=length[:, None] > 0)
        n = np.column_stack([-u[:, 1], u[:, 0]])
        rel = o[:, None, :] - a[None]  # (k, m, 2)
        best = np.full((len(o), len(a)), np.inf)

        # Sides: the lines offset by +-h along the normal, within the segment's span.
        d_n = d @ n.T
        rel_n = np.einsum("kmd,md->km", rel, n)
        for side in (h, -h):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (side - rel_n) / d_n  # rays parallel to the wall: +-inf or NaN, dropped
                along = np.einsum("kmd,md->km", rel, u) + t * (d @ u.T)
            ok = (t >= 0) & (along >= 0) & (along <= length) & (length > 0) & np.isfinite(t)
            best = np.where(ok, np.minimum(best, t), best)

        # Caps: circles of radius h at both ends (smaller root of |o + t d - c|^2 = h^2).
        for c in (a, b):
            rel_c = o[:, None, :] - c[None]
            half_b = np.einsum("kmd,kd->km", rel_c, d)
            cc = np.einsum("kmd,kmd->km", rel_c, rel_c) - h * h
            disc = half_b * half_b - cc
            with np.errstate(invalid="ignore"):
                t = -half_b - np.sqrt(disc)
            ok = (disc >= 0) & (t >= 0)
            best = np.where(ok, np.minimum(best, t), best)

        inside = _point_segment_distance(o, a, b) <= h
        best[inside] = 0.0
        return best.min(axis=1)

    def distance(self, points):
        """Distance from each point to the nearest wall centre line, shape (n_points,)."""
        points = _check_points(points, 2)
        out = np.empty(len(points))
        a, b = self.walls[:, :2], self.walls[:, 2:]
        for chunk in _chunks(len(points), len(self.walls)):
            out[chunk] = _point_segment_distance(points[chunk], a, b).min(axis=1)
        return out

    def occupancy(self, points):
        """True occupancy: 1 within ``wall_thickness / 2`` of a wall (surface included), else 0.

        Parameters
        ----------
        points : array-like of shape (n_points, 2)

        Returns
        -------
        occupied : ndarray of shape (n_points,), dtype int64

        Examples
        --------
        >>> from skoccmap.datasets import Environment2D
        >>> Environment2D([[0, 0, 1, 0]], wall_thickness=0.2).occupancy([[0.5, 0.1], [0.5, 0.2]])
        array([1, 0])
        """
        h = self.wall_thickness / 2
        return (self.distance(points) <= h + _SURFACE_TOL).astype(np.int64)

    def _cells_occupied(self, centres, resolution):
        # A square cell overlaps a capsule iff the segment-square distance is <= h. Disjoint
        # convex sets in 2-D are closest at a vertex of one of them, so that distance is the
        # minimum over segment ends -> square and square corners -> segment.
        h, half = self.wall_thickness / 2, resolution / 2
        a, b = self.walls[:, :2], self.walls[:, 2:]
        corners = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]]) * half
        out = np.empty(len(centres), dtype=bool)
        for chunk in _chunks(len(centres), 8 * len(a)):
            c = centres[chunk]
            crosses = _segment_hits_box(
                np.broadcast_to(a, (len(c), *a.shape)),
                np.broadcast_to(b, (len(c), *b.shape)),
                (c - half)[:, None, :],
                (c + half)[:, None, :],
            )
            dist = np.full(crosses.shape, np.inf)
            for end in (a, b):
                gap = np.maximum(np.abs(end[None] - c[:, None]) - half, 0.0)
                dist = np.minimum(dist, np.linalg.norm(gap, axis=-1))
            for corner in corners:
                dist = np.minimum(dist, _point_segment_distance(c + corner, a, b))
            out[chunk] = np.any(crosses | (dist <= h + _SURFACE_TOL), axis=1)
        return out

    def ground_truth_grid(self, resolution, extent=None, *, scans=None):
        return _ground_truth_grid(self, resolution, extent, scans)

    ground_truth_grid.__doc__ = (
        "True occupancy of a regular grid of square cells.\n"
        + _GRID_DOC.format(n2=4, zext="", d=2, idx="[y, x]")
        + """
        Examples
        --------
        >>> from skoccmap.datasets import Environment2D
        >>> env = Environment2D([[0, 0, 0, 1]], wall_thickness=0.1)
        >>> grid = env.ground_truth_grid(0.5, extent=(-1, 1, 0, 1))
        >>> grid.shape, grid.occupied.reshape(grid.shape).tolist()
        ((2, 4), [[0, 1, 1, 0], [0, 1, 1, 0]])
        """
    )


def _check_points(points, n_dims):
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != n_dims:
        raise ValueError(f"points must have shape (n_points, {n_dims}), got {points.shape}.")
    if not np.all(np.isfinite(points)):
        raise ValueError("points contains NaN or infinite values.")
    return points


# --------------------------------------------------------------------------------------------
# Scanning
# --------------------------------------------------------------------------------------------


def simulate_scans(
    environment, poses, angles, max_range, *, noise_std=0.0, random_state=None, timestamps=None
):
    """Simulate a laser range finder at the given poses.

    Parameters
    ----------
    environment : Environment2D or Room3D
        Anything with ``n_dims`` and ``cast(origins, directions, max_range)``.
    poses : array-like of shape (n_scans, 3) or (n_scans, 7)
        2-D ``[x, y, theta]`` or 3-D ``[x, y, z, qw, qx, qy, qz]`` sensor poses.
    angles : array-like
        Beam angles (2-D, radians from the heading) or unit sensor-frame beam directions (3-D),
        as in :class:`~skoccmap.observations.Scans`.
    max_range : float
        Sensor range in metres; beams meeting nothing closer read ``inf`` (no return).
    noise_std : float, default=0.0
        Standard deviation in metres of Gaussian noise added to returned ranges (clipped at 0;
        a reading pushed to ``max_range`` or beyond becomes ``inf``).
    random_state : int, RandomState instance or None, default=None
        Seed of the range noise.
    timestamps : array-like of shape (n_scans,), default=None
        Passed on to the :class:`~skoccmap.observations.Scans`.

    Returns
    -------
    scans : Scans

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.datasets import Environment2D, simulate_scans
    >>> env = Environment2D([[3.0, -5.0, 3.0, 5.0]], wall_thickness=0.0)
    >>> scans = simulate_scans(env, [[0.0, 0.0, 0.0]], [0.0, np.pi], max_range=8.0)
    >>> scans.ranges
    array([[ 3., inf]])
    """
    try:
        noise_std = float(noise_std)
    except (TypeError, ValueError):
        raise ValueError(f"noise_std must be a non-negative number, got {noise_std!r}.") from None
    if not np.isfinite(noise_std) or noise_std < 0:
        raise ValueError(f"noise_std must be a non-negative finite number, got {noise_std!r}.")
    max_range = _check_max_range(max_range)
    poses = np.asarray(poses, dtype=np.float64)
    directions = beam_directions(poses, angles)  # validates poses and angles
    n_scans, n_beams, n_dims = directions.shape
    if not (hasattr(environment, "n_dims") and callable(getattr(environment, "cast", None))):
        raise TypeError(
            "environment must be an Environment2D, a Room3D or an object with n_dims and "
            f"cast(origins, directions, max_range), got {environment!r}."
        )
    if n_dims != environment.n_dims:
        raise ValueError(f"poses are {n_dims}-D but the environment is {environment.n_dims}-D.")
    origins = np.repeat(poses[:, :n_dims], n_beams, axis=0)
    ranges = environment.cast(origins, directions.reshape(-1, n_dims), max_range)
    ranges = ranges.reshape(n_scans, n_beams)
    if noise_std > 0:
        rng = check_random_state(random_state)
        noise = rng.normal(0.0, noise_std, size=ranges.shape)
        finite = np.isfinite(ranges)
        ranges[finite] = np.maximum(ranges[finite] + noise[finite], 0.0)
        ranges[ranges >= max_range] = np.inf
    return Scans(poses, ranges, angles, max_range, timestamps=timestamps)
