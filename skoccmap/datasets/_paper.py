"""The simulated indoor environment and laser scans of Kim & Kim (ICRA 2012).

The paper's layout is not published as coordinates; this one keeps its stated setup -- a
22 m x 18 m indoor environment of rooms and corridors, 26 poses on two trajectory pieces, 17
beams over 180 degrees, 8 m maximum range -- and was laid out so that the observation counts
come close to the paper's (254 hits, 254 return beams, 188 no-return beams).
"""

import numbers

import numpy as np
from sklearn.utils import Bunch

from ._simulator import Environment2D, _spread, simulate_scans

__all__ = ["make_paper_environment", "make_paper_scans"]

PAPER_MAX_RANGE = 8.0
PAPER_N_BEAMS = 17
PAPER_POSES_PER_PIECE = 13


def _polyline(*points):
    return [[*points[i], *points[i + 1]] for i in range(len(points) - 1)]


def make_paper_environment(wall_thickness=0.1):
    """A 22 m x 18 m indoor environment of rooms, corridors and an open hall.

    Three rooms stack along the west side (doors facing east), three rooms line the north
    side, a partly walled corridor runs along the south, a small room juts into the east
    end of the central hall and an L-shaped partition stands in its middle. The map spans
    ``[0, 22] x [0, 18]`` metres (plus half the wall thickness).

    Parameters
    ----------
    wall_thickness : float, default=0.1
        Wall thickness in metres.

    Returns
    -------
    environment : Environment2D

    Examples
    --------
    >>> from skoccmap.datasets import make_paper_environment
    >>> env = make_paper_environment()
    >>> env.extent.round(2)
    array([-0.05, 22.05, -0.05, 18.05])
    """
    walls = _polyline((0, 0), (22, 0), (22, 18), (0, 18), (0, 0))
    walls += [
        # west rooms, x in [0, 5], doors in the wall x = 5
        [0, 6, 5, 6], [0, 12, 5, 12],
        [5, 0, 5, 2], [5, 3.2, 5, 8], [5, 9.2, 5, 14], [5, 15.2, 5, 18],
        # north rooms, y in [14, 18], doors in the wall y = 14
        [5, 14, 7, 14], [8.2, 14, 13, 14], [14.2, 14, 19, 14], [20.2, 14, 22, 14],
        [11, 14, 11, 18], [17, 14, 17, 18],
        # south corridor, y in [0, 3], with a gap in its north wall
        [8, 3, 13, 3], [16, 3, 19, 3],
        # small room in the east end of the hall
        [18, 9, 22, 9], [18, 9, 18, 10.5],
        # an L-shaped partition in the middle of the hall
        [11, 9, 12, 9], [11, 9, 11, 10],
    ]  # fmt: skip
    return Environment2D(walls, wall_thickness=wall_thickness)


def _paper_poses(n_per_piece):
    s = np.linspace(0.0, 1.0, n_per_piece)
    # Piece 1: west to east across the hall.
    piece1 = np.column_stack([6.5 + 12.5 * s, np.full_like(s, 6.0)])
    # Piece 2: out of the south corridor, bending west then back, towards the north rooms.
    piece2 = np.column_stack([14.5 - 2.0 * np.sin(np.pi * s), 1.5 + 10.5 * s])
    poses = []
    for piece in (piece1, piece2):
        # Heading along the path: the sensor looks where the robot drives.
        heading = np.arctan2(np.gradient(piece[:, 1]), np.gradient(piece[:, 0]))
        poses.append(np.column_stack([piece, heading]))
    return np.vstack(poses)


def make_paper_scans(
    *,
    noise_std=0.0,
    random_state=None,
    free_margin=0.05,
    n_beams=PAPER_N_BEAMS,
    n_poses_per_piece=PAPER_POSES_PER_PIECE,
):
    """Simulated laser scans of the paper's experiment: about 700 observations.

    26 poses on two trajectory pieces of 13 poses each in :func:`make_paper_environment`;
    at each pose 17 beams evenly spread over 180 degrees (-90 to +90 from the heading) with an
    8 m maximum range. Noise-free, this gives 259 hits, 259 return beams and 183 no-return
    beams (the paper reports 254, 254 and 188).

    Parameters
    ----------
    noise_std : float, default=0.0
        Standard deviation in metres of Gaussian noise added to returned ranges.
    random_state : int, RandomState instance or None, default=None
        Seed of the range noise.
    free_margin : float, default=0.05
        Gap between return beams and their hits, see
        :func:`~skoccmap.observations.scans_to_observations`.
    n_beams : int, default=17
        Beams per scan over the same 180 degrees; raise it (with ``n_poses_per_piece``) for a
        larger data set of the same world (observations grow with their product). A single
        beam points straight ahead.
    n_poses_per_piece : int, default=13
        Poses along each of the two trajectory pieces.

    Returns
    -------
    data : sklearn.utils.Bunch
        ``X`` (n, 4) segment rows; ``y`` (1 hit, 0 free); ``kind`` (HIT / RETURN / NO_RETURN);
        ``scan_index`` (n,) scan of each row; ``piece`` (n_scans,) trajectory piece (0 or 1) of
        each scan; ``scans`` (:class:`~skoccmap.observations.Scans`); ``environment``
        (:class:`Environment2D`).

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.datasets import make_paper_scans
    >>> data = make_paper_scans(random_state=0)
    >>> data.X.shape, np.bincount(data.kind).tolist()
    ((701, 4), [259, 259, 183])
    """
    for name, value, least in (
        ("n_beams", n_beams, 1),
        ("n_poses_per_piece", n_poses_per_piece, 2),
    ):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}.")
    environment = make_paper_environment()
    angles = _spread(-np.pi / 2, np.pi / 2, n_beams)
    scans = simulate_scans(
        environment,
        _paper_poses(n_poses_per_piece),
        angles,
        PAPER_MAX_RANGE,
        noise_std=noise_std,
        random_state=random_state,
    )
    X, y, kind, scan_index = scans.to_observations(free_margin, return_scan_index=True)
    piece = np.repeat([0, 1], n_poses_per_piece)
    return Bunch(
        X=X,
        y=y,
        kind=kind,
        scan_index=scan_index,
        piece=piece,
        scans=scans,
        environment=environment,
    )
