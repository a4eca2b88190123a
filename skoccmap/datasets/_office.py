"""A simulated office floor -- a corridor with rooms off it -- and laser scans of it.

A second ground-truth world beside the paper's (:mod:`._paper`), larger in the number of rooms
and doors: a 20 m x 15 m floor, an east-west corridor through its middle and seven rooms off
the corridor, each entered through a door by the sensor path.
"""

import numbers

import numpy as np
from sklearn.utils import Bunch

from ._simulator import Environment2D, simulate_scans

__all__ = ["make_office_environment", "make_office_scans"]

OFFICE_SIZE = (20.0, 15.0)
# The corridor spans the floor's width between these two walls.
_CORRIDOR_Y = (6.5, 8.5)
# Rooms (x_min, x_max, y_min, y_max, door centre x, door width), in the order the path visits
# them: sorted by door position from west to east. North rooms have their door in the wall
# y = 8.5, south rooms in the wall y = 6.5.
_ROOMS = np.array([
    [0.0, 5.0, 8.5, 15.0, 2.8, 1.0],     # north-west office
    [0.0, 6.5, 0.0, 6.5, 4.2, 1.0],      # south-west office (a shelf)
    [5.0, 9.5, 8.5, 15.0, 7.0, 0.9],     # small north office
    [6.5, 13.0, 0.0, 6.5, 9.6, 1.2],     # south office with a partition
    [9.5, 14.5, 8.5, 15.0, 12.3, 1.1],   # meeting room (a table)
    [13.0, 20.0, 0.0, 6.5, 15.8, 1.0],   # south-east hall (a pillar)
    [14.5, 20.0, 8.5, 15.0, 17.0, 1.2],  # north-east office
])  # fmt: skip
# Radius of the loop the path drives in each room, around the room's centre line y.
_LOOP_RADIUS = 1.5
# Where the path walks the corridor, and where it starts and ends.
_PATH_Y = 7.5
_PATH_X = (0.8, 19.2)

OFFICE_MAX_RANGE = 10.0
OFFICE_N_BEAMS = 45
OFFICE_N_POSES = 30


def _box(x0, y0, x1, y1):
    return [[x0, y0, x1, y0], [x1, y0, x1, y1], [x1, y1, x0, y1], [x0, y1, x0, y0]]


def _wall_with_doors(y, x0, x1, doors):
    """Pieces of the wall ``y`` from ``x0`` to ``x1`` around door gaps ``(centre, width)``."""
    walls, start = [], x0
    for centre, width in sorted(doors):
        walls.append([start, y, centre - width / 2, y])
        start = centre + width / 2
    walls.append([start, y, x1, y])
    return walls


def make_office_environment(wall_thickness=0.1):
    """A 20 m x 15 m office floor: a corridor, seven rooms off it, and some furniture.

    An east-west corridor 2 m wide (``6.5 <= y <= 8.5``) runs the full width of the floor.
    Four rooms line its north side (``8.5 <= y <= 15``, 5, 4.5, 5 and 5.5 m wide from west to
    east) and three its south side (``0 <= y <= 6.5``, 6.5, 6.5 and 7 m wide); every room has
    one door opening of 0.9 to 1.2 m into the corridor. Interior obstacles: a 1.6 m x 0.8 m
    table in the middle of the third north room (a meeting room), a 0.5 m x 0.5 m pillar in
    the south-east hall, a 2.5 m partition standing free near the east wall of the middle
    south room and a 2 m shelf along the west wall of the south-west room. Blocks are outlined
    by walls (their inside is free but cannot be observed). The map spans ``[0, 20] x [0, 15]``
    metres (plus half the wall thickness).

    Parameters
    ----------
    wall_thickness : float, default=0.1
        Wall thickness in metres.

    Returns
    -------
    environment : Environment2D

    See Also
    --------
    make_office_scans : Laser scans along a path through every room.
    make_paper_environment : The paper's simulated world.

    Examples
    --------
    >>> from skoccmap.datasets import make_office_environment
    >>> env = make_office_environment()
    >>> env.extent.round(2)
    array([-0.05, 20.05, -0.05, 15.05])
    >>> env.occupancy([[10.0, 7.5], [12.3, 11.35]])  # the corridor is free, the table edge not
    array([0, 1])
    """
    width, height = OFFICE_SIZE
    y_south, y_north = _CORRIDOR_Y
    north = _ROOMS[:, 2] == y_north
    walls = _box(0.0, 0.0, width, height)
    walls += _wall_with_doors(y_north, 0.0, width, _ROOMS[north][:, 4:6].tolist())
    walls += _wall_with_doors(y_south, 0.0, width, _ROOMS[~north][:, 4:6].tolist())
    # Walls between neighbouring rooms (the outer walls close the end rooms).
    for x in np.unique(_ROOMS[north][:, :2]):
        if 0.0 < x < width:
            walls.append([x, y_north, x, height])
    for x in np.unique(_ROOMS[~north][:, :2]):
        if 0.0 < x < width:
            walls.append([x, 0.0, x, y_south])
    walls += _box(11.5, 11.35, 13.1, 12.15)  # meeting table, centred in its room's loop
    walls += _box(15.55, 3.0, 16.05, 3.5)  # pillar, centred in the hall's loop
    walls.append([12.0, 1.0, 12.0, 3.5])  # free-standing partition
    walls += _box(0.0, 1.5, 0.4, 3.5)[:3]  # shelf against the west wall (which closes it)
    return Environment2D(walls, wall_thickness=wall_thickness)


def _office_path(n_points_per_loop=1440):
    """Dense polyline (n, 2) of the sensor path and the room (or -1) of each of its points.

    West to east along the corridor's centre line; at each door the path turns through it,
    drives to a loop of radius ``_LOOP_RADIUS`` about the room's centre line, goes once round
    it anticlockwise, and comes back out the same way.
    """
    t = np.linspace(0.0, 2 * np.pi, n_points_per_loop + 1)
    points = [[_PATH_X[0], _PATH_Y]]
    for _, _, y0, y1, door, _ in _ROOMS:
        centre_y = 0.5 * (y0 + y1)
        # Start the loop at the point nearest the door: its bottom (north rooms) or top.
        side = -1.0 if y0 >= _CORRIDOR_Y[1] else 1.0
        start = np.arctan2(side, 0.0)
        loop = np.column_stack(
            [door + _LOOP_RADIUS * np.cos(start + t), centre_y + _LOOP_RADIUS * np.sin(start + t)]
        )
        points += [[door, _PATH_Y], *loop.tolist(), [door, _PATH_Y]]
    points.append([_PATH_X[1], _PATH_Y])
    return np.asarray(points)


def _office_poses(n_poses):
    """``n_poses`` poses evenly spread by arc length over the path, heading along it."""
    path = _office_path()
    step = np.diff(path, axis=0)
    length = np.hypot(step[:, 0], step[:, 1])
    keep = length > 0
    step, length = step[keep], length[keep]
    starts = np.concatenate([[0.0], np.cumsum(length)])
    s = np.linspace(0.0, starts[-1], n_poses)
    # Segment of each pose; the last pose lies at the end of the last segment.
    seg = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, len(length) - 1)
    frac = (s - starts[seg]) / length[seg]
    xy = path[:-1][keep][seg] + frac[:, None] * step[seg]
    heading = np.arctan2(step[seg, 1], step[seg, 0])
    return np.column_stack([xy, heading])


def _room_of(points):
    """Index into the visiting order of the room holding each point, -1 outside all rooms."""
    points = np.asarray(points, dtype=np.float64)
    x, y = points[:, :1], points[:, 1:2]
    inside = (x > _ROOMS[:, 0]) & (x < _ROOMS[:, 1]) & (y > _ROOMS[:, 2]) & (y < _ROOMS[:, 3])
    return np.where(inside.any(axis=1), inside.argmax(axis=1), -1)


def make_office_scans(
    n_poses=OFFICE_N_POSES,
    n_beams=OFFICE_N_BEAMS,
    *,
    max_range=OFFICE_MAX_RANGE,
    noise_std=0.0,
    free_margin=0.05,
    random_state=None,
):
    """Simulated laser scans along a path through every room of the office floor.

    The sensor path (about 123 m) walks the corridor of :func:`make_office_environment` from
    west to east and turns into each of the seven rooms on its way: through the door, once
    round a 1.5 m-radius loop about the room's middle (round the table and the pillar in the
    rooms that have them), and back out through the door. ``n_poses`` poses are spread evenly
    by arc length over the whole path, from its start at the corridor's west end to its end at
    the east end; the poses depend only on ``n_poses``. At each pose, as in the paper's setup
    (:func:`make_paper_scans`), ``n_beams`` beams are spread evenly over 180 degrees (-90 to
    +90 from the heading), and the sensor heads along the path: ahead in the corridor and
    through the doors, and turning all the way round on each room's loop. The path keeps at
    least 0.4 m between the sensor and every wall surface (the least is at the jambs of the
    narrowest, 0.9 m door).

    With the defaults (30 poses, 45 beams, 10 m range) every room holds three poses and,
    noise-free, the scans give 2679 observations (1329 hits, 1329 return beams, 21 no-return
    beams); their beams cross about 85 % of the floor's free area (0.1 m cells).
    For a dense variant of the same world raise both counts, e.g. ``n_poses=120,
    n_beams=180``; observations grow with their product.

    Parameters
    ----------
    n_poses : int, default=30
        Number of sensor poses along the path, at least 2.
    n_beams : int, default=45
        Beams per scan over 180 degrees, at least 2.
    max_range : float, default=10.0
        Sensor range in metres; longer beams (down the corridor, across the hall) read no
        return.
    noise_std : float, default=0.0
        Standard deviation in metres of Gaussian noise added to returned ranges.
    free_margin : float, default=0.05
        Gap between return beams and their hits, see
        :func:`~skoccmap.observations.scans_to_observations`.
    random_state : int, RandomState instance or None, default=None
        Seed of the range noise (the only random part).

    Returns
    -------
    data : sklearn.utils.Bunch
        ``X`` (n, 4) segment rows; ``y`` (1 hit, 0 free); ``kind`` (HIT / RETURN / NO_RETURN);
        ``scan_index`` (n,) scan of each row; ``room`` (n_scans,) the room each scan was taken
        in, as a row of ``rooms``, or -1 in the corridor; ``rooms`` (7, 4) each room's
        ``(x_min, x_max, y_min, y_max)`` between wall centre lines, in the order the path
        visits them; ``scans`` (:class:`~skoccmap.observations.Scans`); ``environment``
        (:class:`Environment2D`).

    Raises
    ------
    ValueError
        If ``n_poses`` or ``n_beams`` is not an integer >= 2, or ``max_range``,
        ``noise_std`` or ``free_margin`` is out of range.

    See Also
    --------
    make_office_environment : The world these scans are taken in.
    make_paper_scans : The paper's smaller data set.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.datasets import make_office_scans
    >>> data = make_office_scans(random_state=0)
    >>> len(data.scans), data.scans.n_beams, data.scans.max_range
    (30, 45, 10.0)
    >>> np.unique(data.room).tolist()  # every room is visited
    [-1, 0, 1, 2, 3, 4, 5, 6]
    >>> grid = data.environment.ground_truth_grid(0.2, scans=data.scans)
    >>> grid.occupied.shape, grid.observed.dtype
    ((7676,), dtype('bool'))
    """
    for name, value in (("n_poses", n_poses), ("n_beams", n_beams)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 2:
            raise ValueError(f"{name} must be an integer >= 2, got {value!r}.")
    environment = make_office_environment()
    poses = _office_poses(int(n_poses))
    angles = np.linspace(-np.pi / 2, np.pi / 2, int(n_beams))
    scans = simulate_scans(
        environment, poses, angles, max_range, noise_std=noise_std, random_state=random_state
    )
    X, y, kind, scan_index = scans.to_observations(free_margin, return_scan_index=True)
    return Bunch(
        X=X,
        y=y,
        kind=kind,
        scan_index=scan_index,
        room=_room_of(poses),
        rooms=_ROOMS[:, :4].copy(),
        scans=scans,
        environment=environment,
    )
