"""Scoring occupancy maps: held-out scans of a log, or the simulator's true map.

Real logs have no true map, so the Hilbert-map literature scores a map on held-out scans:
their hit points are the positives, points drawn uniformly along their beams (short of the
hit) the negatives, and the score is the ROC AUC of the predicted occupancy probabilities.
:func:`blocks_protocol` is that protocol as published (Ramos & Ott, RSS 2015), with the
``HILBERT_*`` constants below; :func:`split_scans` and :func:`heldout_points` allow variants.

Simulated data are also scored against the true map on a grid: :func:`ground_truth_auc`, and
:func:`map_quality` for what an AUC hides -- phantom obstacles and free space found at the
thresholds a navigation stack uses, walls found, calibration and wall thickness.
"""

import numbers

import numpy as np
from sklearn.metrics import brier_score_loss, roc_auc_score
from sklearn.utils import Bunch, check_random_state

from .datasets import Environment2D, Room3D
from .grid import ROS_FREE_THRESH, ROS_OCCUPIED_THRESH
from .observations import Scans, _check_free_margin, as_segments

__all__ = [
    "HILBERT_BLOCK_SIZE",
    "HILBERT_FREE_MARGIN",
    "HILBERT_HELDOUT_FRACTION",
    "HILBERT_MAX_BEAM_RANGE",
    "HILBERT_N_FREE_PER_BEAM",
    "blocks_protocol",
    "expected_calibration_error",
    "ground_truth_auc",
    "heldout_auc",
    "heldout_points",
    "map_quality",
    "split_scan_blocks",
    "split_scans",
]

# The Hilbert-maps protocol (Ramos & Ott, RSS 2015), used by :func:`blocks_protocol`.

#: Share of a log's scans held out for testing.
HILBERT_HELDOUT_FRACTION = 0.1
#: Consecutive scans per held-out block: neighbouring scans see the same walls, so scattered
#: single test scans would be nearly copies of training scans.
HILBERT_BLOCK_SIZE = 40
#: Free test points per held-out beam: ``"half_range"`` is floor(r / 2), at least one, for a
#: beam of range r metres, so that long beams weigh more, as the free space they cross does.
HILBERT_N_FREE_PER_BEAM = "half_range"
#: Longest beam in metres whose free space is trusted; longer readings give no free test
#: points (their hits still count as occupied).
HILBERT_MAX_BEAM_RANGE = 40.0
#: Gap in metres between a beam's free test points and its hit.
HILBERT_FREE_MARGIN = 0.1


def _check_scans(scans, name="scans"):
    if not isinstance(scans, Scans):
        raise ValueError(
            f"{name} must be a skoccmap.observations.Scans, got {type(scans).__name__}."
        )
    return scans


def split_scans(scans, every_nth=10, *, offset=0):
    """Hold out every ``every_nth`` scan.

    Parameters
    ----------
    scans : Scans
    every_nth : int, default=10
        Scans ``offset, offset + every_nth, offset + 2 * every_nth, ...`` are held out.
    offset : int, default=0
        Index of the first held-out scan, ``0 <= offset < every_nth``.

    Returns
    -------
    train_scans, test_scans : Scans

    Examples
    --------
    >>> from skoccmap.datasets import make_paper_scans
    >>> from skoccmap.metrics import split_scans
    >>> train, test = split_scans(make_paper_scans().scans, every_nth=5)
    >>> len(train), len(test)
    (20, 6)
    """
    scans = _check_scans(scans)
    if not isinstance(every_nth, numbers.Integral) or every_nth < 2:
        raise ValueError(f"every_nth must be an integer >= 2, got {every_nth!r}.")
    if not isinstance(offset, numbers.Integral) or not 0 <= offset < every_nth:
        raise ValueError(f"offset must be an integer in [0, every_nth), got {offset!r}.")
    held_out = np.arange(len(scans)) % every_nth == offset
    if held_out.all() or not held_out.any():
        raise ValueError(
            f"holding out every {every_nth}th scan from offset {offset} of {len(scans)} scans "
            "leaves the training or the test set empty; use more scans or a smaller every_nth."
        )
    return scans[~held_out], scans[held_out]


def _check_fraction(heldout_fraction):
    if (
        not isinstance(heldout_fraction, numbers.Real)
        or isinstance(heldout_fraction, bool)
        or not 0 < heldout_fraction < 1
    ):
        raise ValueError(f"heldout_fraction must be a number in (0, 1), got {heldout_fraction!r}.")
    return float(heldout_fraction)


def _check_positive_int(value, name):
    if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    return int(value)


def _heldout_blocks(n_scans, heldout_fraction, block_size, rng):
    """Boolean mask of the scans held out as non-overlapping blocks at random starts."""
    n_blocks = max(1, round(heldout_fraction * n_scans / block_size))
    n_rest = n_scans - n_blocks * block_size
    if n_rest < 1:
        raise ValueError(
            f"{n_scans} scans are too few to hold out {n_blocks} block(s) of {block_size} "
            "consecutive scans and keep scans for training; use a smaller block_size."
        )
    # Uniform over all non-overlapping placements: the blocks and the remaining scans form a
    # sequence of n_rest + n_blocks items, and the blocks take n_blocks of its places at random.
    places = np.sort(rng.choice(n_rest + n_blocks, size=n_blocks, replace=False))
    starts = places + np.arange(n_blocks) * (block_size - 1)
    held_out = np.zeros(n_scans, dtype=bool)
    held_out[(starts[:, None] + np.arange(block_size)).ravel()] = True
    return held_out


def split_scan_blocks(scans, *, heldout_fraction=0.1, block_size=40, random_state=None):
    """Hold out blocks of consecutive scans at random starts (the Hilbert-maps split).

    Scans taken a moment apart see the same walls from nearly the same place, so a scan held
    out between two training scans is almost a copy of them. Whole blocks of consecutive scans
    held out leave the map to predict stretches of the log it has not seen.

    Parameters
    ----------
    scans : Scans
        The whole log, in time order.
    heldout_fraction : float, default=0.1
        Share of the scans to hold out, in (0, 1). The number of blocks is
        ``round(heldout_fraction * n_scans / block_size)``, at least one.
    block_size : int, default=40
        Consecutive scans per block.
    random_state : int, RandomState instance or None, default=None
        Seed of the block starts. The blocks never overlap (they may touch); every
        non-overlapping placement is equally likely.

    Returns
    -------
    train_scans, test_scans : Scans
        The remaining scans and the held-out ones, each in time order.

    Raises
    ------
    ValueError
        When the blocks would take every scan (a log shorter than the blocks plus one scan).

    See Also
    --------
    blocks_protocol : This split with the protocol's test points.
    split_scans : Every n-th scan held out.

    Examples
    --------
    >>> from skoccmap.datasets import make_paper_scans
    >>> from skoccmap.metrics import split_scan_blocks
    >>> scans = make_paper_scans().scans
    >>> train, test = split_scan_blocks(scans, block_size=5, random_state=0)
    >>> len(train), len(test)
    (21, 5)
    """
    scans = _check_scans(scans)
    heldout_fraction = _check_fraction(heldout_fraction)
    block_size = _check_positive_int(block_size, "block_size")
    rng = check_random_state(random_state)
    held_out = _heldout_blocks(len(scans), heldout_fraction, block_size, rng)
    return scans[~held_out], scans[held_out]


def _free_points_per_beam(n_free_per_beam, beam_range):
    """Free points to draw on each beam of the given ranges."""
    if isinstance(n_free_per_beam, str):
        if n_free_per_beam != "half_range":
            raise ValueError(
                "n_free_per_beam must be a positive integer or 'half_range', got "
                f"{n_free_per_beam!r}."
            )
        return np.maximum(np.floor(beam_range / 2), 1).astype(np.int64)
    if (
        not isinstance(n_free_per_beam, numbers.Integral)
        or isinstance(n_free_per_beam, bool)
        or n_free_per_beam < 1
    ):
        raise ValueError(
            "n_free_per_beam must be a positive integer or 'half_range', got "
            f"{n_free_per_beam!r}."
        )
    return int(n_free_per_beam)


def _check_max_beam_range(max_beam_range):
    if max_beam_range is None:
        return np.inf
    if (
        not isinstance(max_beam_range, numbers.Real)
        or isinstance(max_beam_range, bool)
        or not 0 < max_beam_range < np.inf
    ):
        raise ValueError(
            f"max_beam_range must be None or a positive number, got {max_beam_range!r}."
        )
    return float(max_beam_range)


def heldout_points(
    scans, *, n_free_per_beam=1, free_margin=0.05, max_beam_range=None, random_state=None
):
    """Labelled test points from held-out scans: hits occupied, points along beams free.

    Parameters
    ----------
    scans : Scans
        Held-out scans.
    n_free_per_beam : int or "half_range", default=1
        Free points drawn per beam: that many on every beam, or with ``"half_range"``
        floor(r / 2) (at least one) on a beam of range r metres -- the measured range of a beam
        with a return, ``max_range`` for one without.
    free_margin : float, default=0.05
        Free points of a beam with a return are drawn uniformly from the sensor to
        ``free_margin`` short of the hit (none when the hit is within ``free_margin``); those
        of a beam without a return, uniformly from the sensor to ``max_range``.
    max_beam_range : float, default=None
        If given, only beams with a return at range ``<= max_beam_range`` give free points:
        long readings are the least reliable, and a beam without a return has no known range.
        Every hit stays a positive, however far.
    random_state : int, RandomState instance or None, default=None
        Seed of the positions along the beams.

    Returns
    -------
    points : ndarray of shape (n_points, D)
        The hit points first (scan and beam order), then the free points.
    labels : ndarray of shape (n_points,), dtype int64
        1 for hit points, 0 for free points.

    Examples
    --------
    >>> from skoccmap.datasets import make_paper_scans
    >>> from skoccmap.metrics import heldout_points
    >>> points, labels = heldout_points(make_paper_scans().scans[:2], random_state=0)
    >>> points.shape, int(labels.sum())
    ((50, 2), 16)

    The Hilbert-maps protocol's negatives: floor(r / 2) points per beam of up to 40 m.

    >>> points, labels = heldout_points(
    ...     make_paper_scans().scans[:2], n_free_per_beam="half_range", free_margin=0.1,
    ...     max_beam_range=40.0, random_state=0)
    >>> points.shape, int(labels.sum())
    ((47, 2), 16)
    """
    scans = _check_scans(scans)
    free_margin = _check_free_margin(free_margin)
    max_beam_range = _check_max_beam_range(max_beam_range)
    rng = check_random_state(random_state)

    returned = scans.returned()
    beam_range = np.where(returned, scans.ranges, scans.max_range)
    free_length = np.where(returned, scans.ranges - free_margin, scans.max_range)
    usable = free_length > 0
    if np.isfinite(max_beam_range):
        usable &= returned & (beam_range <= max_beam_range)
    counts = _free_points_per_beam(n_free_per_beam, beam_range[usable])
    origins = np.broadcast_to(scans.origins()[:, None, :], scans.directions().shape)[usable]
    directions, free_length = scans.directions()[usable], free_length[usable]
    if isinstance(counts, int):
        # Draw-major order: the same points for a given seed as drawing (counts, n_beams) at once.
        beam = np.tile(np.arange(len(directions)), counts)
    else:
        beam = np.repeat(np.arange(len(directions)), counts)
    t = rng.uniform(size=len(beam)) * free_length[beam]
    free = origins[beam] + t[:, None] * directions[beam]

    hits = scans.hit_points()
    points = np.concatenate([hits, free])
    labels = np.r_[np.ones(len(hits), np.int64), np.zeros(len(free), np.int64)]
    return points, labels


def blocks_protocol(scans, *, train_every=1, block_size=HILBERT_BLOCK_SIZE, random_state=None):
    """Training scans and labelled test points of the Hilbert-maps protocol.

    The protocol of Ramos & Ott (RSS 2015) for logs without a true map: hold out
    :data:`HILBERT_HELDOUT_FRACTION` of the scans as blocks of :data:`HILBERT_BLOCK_SIZE`
    consecutive scans at random starts (:func:`split_scan_blocks`); the positives are the
    held-out hits, the negatives floor(r / 2) (at least one) points drawn uniformly along each
    held-out beam of range r <= :data:`HILBERT_MAX_BEAM_RANGE` metres, stopping
    :data:`HILBERT_FREE_MARGIN` short of the hit (:func:`heldout_points`). The map trains on
    every ``train_every``-th remaining scan; the score is the ROC AUC of the predicted
    probabilities at the test points, over several seeds.

    Parameters
    ----------
    scans : Scans
        The whole log, in time order.
    train_every : int, default=1
        Train on every ``train_every``-th of the remaining scans (the protocol reports 1, 10
        and 40).
    block_size : int, default=HILBERT_BLOCK_SIZE
        Consecutive scans per held-out block; lower it only for logs too short for the
        protocol's blocks.
    random_state : int, RandomState instance or None, default=None
        Seed of the blocks and of the free points. An int gives the same test set whatever
        ``train_every``, so that sparser training sets are scored on the same points.

    Returns
    -------
    protocol : sklearn.utils.Bunch
        ``train`` (Scans) the training scans; ``test`` (Scans) the held-out scans;
        ``points`` (n_points, D) and ``labels`` (n_points,) the test points, hits (1) first,
        then free points (0); ``train_index`` and ``test_index`` the indices in ``scans`` of
        the training and the held-out scans.

    See Also
    --------
    split_scan_blocks, heldout_points

    Examples
    --------
    >>> from sklearn.metrics import roc_auc_score
    >>> from sklearn.neighbors import KNeighborsClassifier
    >>> from skoccmap.datasets import make_paper_scans
    >>> from skoccmap.metrics import blocks_protocol, heldout_points
    >>> from skoccmap.observations import as_segments
    >>> protocol = blocks_protocol(make_paper_scans().scans, train_every=2, block_size=5,
    ...                            random_state=0)
    >>> len(protocol.train), len(protocol.test), protocol.test_index.tolist()
    (11, 5, [20, 21, 22, 23, 24])
    >>> points, labels = heldout_points(protocol.train, n_free_per_beam=3, random_state=0)
    >>> knn = KNeighborsClassifier(5).fit(as_segments(points), labels)
    >>> proba = knn.predict_proba(as_segments(protocol.points))[:, 1]
    >>> round(roc_auc_score(protocol.labels, proba), 2)
    0.93
    """
    scans = _check_scans(scans)
    train_every = _check_positive_int(train_every, "train_every")
    block_size = _check_positive_int(block_size, "block_size")
    # One generator for blocks then points, consumed alike whatever train_every.
    rng = check_random_state(random_state)
    held_out = _heldout_blocks(len(scans), HILBERT_HELDOUT_FRACTION, block_size, rng)
    test = scans[held_out]
    points, labels = heldout_points(
        test,
        n_free_per_beam=HILBERT_N_FREE_PER_BEAM,
        free_margin=HILBERT_FREE_MARGIN,
        max_beam_range=HILBERT_MAX_BEAM_RANGE,
        random_state=rng,
    )
    train_index = np.flatnonzero(~held_out)[::train_every]
    return Bunch(
        train=scans[train_index],
        test=test,
        points=points,
        labels=labels,
        train_index=train_index,
        test_index=np.flatnonzero(held_out),
    )


def _positive_proba(estimator, X):
    """P(occupied) from ``predict_proba``, column of class 1 (the last one otherwise)."""
    proba = np.asarray(estimator.predict_proba(X))
    classes = list(getattr(estimator, "classes_", []))
    column = classes.index(1) if 1 in classes else proba.shape[1] - 1
    return proba[:, column]


def _check_both_classes(labels, what):
    # Before any prediction: a one-class truth makes the AUC undefined whatever the map says.
    if labels.size == 0:
        raise ValueError(f"there is no {what} to score.")
    if labels.min() == labels.max():
        raise ValueError(
            f"every {what} is {'occupied' if labels[0] else 'free'}: the AUC is undefined. "
            "Score a region holding both free and occupied space."
        )


def _auc(labels, proba, what):
    proba = np.asarray(proba, dtype=np.float64)
    if proba.shape != labels.shape:
        raise ValueError(
            f"probabilities must have shape {labels.shape} (one per {what}), got {proba.shape}."
        )
    if not np.all(np.isfinite(proba)):
        raise ValueError(
            f"the predicted probabilities contain {np.count_nonzero(~np.isfinite(proba))} NaN "
            "or infinite value(s); the map cannot be scored."
        )
    return float(roc_auc_score(labels, proba))


def heldout_auc(
    estimator, scans, *, n_free_per_beam=1, free_margin=0.05, max_beam_range=None,
    random_state=None,
):
    """ROC AUC of a map on held-out scans (hit points vs. free points along their beams).

    Parameters
    ----------
    estimator : fitted classifier
        Its ``predict_proba`` on zero-length segments gives P(occupied) in the column of
        class 1.
    scans : Scans
        Held-out scans; see :func:`split_scans`.
    n_free_per_beam, free_margin, max_beam_range, random_state
        See :func:`heldout_points`.

    Returns
    -------
    auc : float

    Examples
    --------
    A nearest-neighbour baseline trained on points sampled from the training scans:

    >>> from sklearn.neighbors import KNeighborsClassifier
    >>> from skoccmap.datasets import make_paper_scans
    >>> from skoccmap.metrics import heldout_auc, heldout_points, split_scans
    >>> from skoccmap.observations import as_segments
    >>> train, test = split_scans(make_paper_scans().scans, every_nth=4)
    >>> points, labels = heldout_points(train, n_free_per_beam=3, random_state=0)
    >>> knn = KNeighborsClassifier(5).fit(as_segments(points), labels)
    >>> round(heldout_auc(knn, test, random_state=0), 2)
    0.96
    """
    points, labels = heldout_points(
        scans,
        n_free_per_beam=n_free_per_beam,
        free_margin=free_margin,
        max_beam_range=max_beam_range,
        random_state=random_state,
    )
    _check_both_classes(labels, "held-out point")
    return _auc(labels, _positive_proba(estimator, as_segments(points)), "held-out point")


def ground_truth_auc(estimator_or_proba, environment, resolution=0.2, *, extent=None, scans=None):
    """ROC AUC of a map against a simulator's true occupancy grid.

    Parameters
    ----------
    estimator_or_proba : fitted classifier or array-like of shape (n_cells,)
        A classifier whose ``predict_proba`` is evaluated at the cell centres (as zero-length
        segments), or P(occupied) per cell of ``environment.ground_truth_grid(resolution,
        extent)`` in its order (or, with ``scans``, per observed cell only).
    environment : Environment2D or Room3D
        The simulated world.
    resolution : float, default=0.2
        Cell side in metres.
    extent : array-like, default=None
        Grid extent; defaults to the environment's.
    scans : Scans, default=None
        If given, only the cells these scans observed are scored (see
        ``Environment2D.ground_truth_grid``), so that space no sensor saw does not dominate.

    Returns
    -------
    auc : float

    Raises
    ------
    ValueError
        When the scored cells are all free or all occupied, or probabilities are NaN.

    Examples
    --------
    >>> from skoccmap.datasets import make_paper_scans
    >>> from skoccmap.metrics import ground_truth_auc
    >>> data = make_paper_scans()
    >>> grid = data.environment.ground_truth_grid(0.5)
    >>> ground_truth_auc(grid.occupied * 0.9, data.environment, 0.5)
    1.0
    """
    grid = environment.ground_truth_grid(resolution, extent, scans=scans)
    scored = np.ones(len(grid.points), bool) if scans is None else grid.observed
    what = "grid cell" if scans is None else "observed grid cell"
    labels = grid.occupied[scored]
    _check_both_classes(labels, what)
    if hasattr(estimator_or_proba, "predict_proba"):
        proba = _positive_proba(estimator_or_proba, as_segments(grid.points[scored]))
    else:
        proba = np.asarray(estimator_or_proba, dtype=np.float64)
        if proba.shape == scored.shape:  # one per cell of the grid: keep the scored ones
            proba = proba[scored]
    return _auc(labels, proba, what)
