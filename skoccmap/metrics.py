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

from ._validation import queries_at, queries_of_our_own
from .datasets import Environment2D, Room3D
from .grid import ROS_FREE_THRESH, ROS_OCCUPIED_THRESH, _cells_below
from .observations import Scans, _check_free_margin

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
# heldout_points' and heldout_auc's gap between a beam's free test points and its hit.
_FREE_MARGIN = 0.05


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
    if (
        not isinstance(offset, numbers.Integral)
        or isinstance(offset, bool)
        or not 0 <= offset < every_nth
    ):
        raise ValueError(f"offset must be an integer in [0, every_nth), got {offset!r}.")
    # A slice, not np.arange(n) % every_nth: an every_nth beyond int64 overflows numpy.
    held_out = np.zeros(len(scans), dtype=bool)
    held_out[offset::every_nth] = True
    if held_out.all() or not held_out.any():
        raise ValueError(
            f"holding out one scan in {every_nth} from offset {offset} of {len(scans)} scans "
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


# Free test points heldout_points draws at most with "half_range": a billion is 16 GB of
# 2-D points, far beyond a real log's (Intel's held-out scans give about 30 000).
_MAX_FREE_POINTS = 1e9


def _free_points_per_beam(n_free_per_beam, beam_range):
    """Free points to draw on each beam of the given ranges."""
    if isinstance(n_free_per_beam, str):
        if n_free_per_beam != "half_range":
            raise ValueError(
                "n_free_per_beam must be a positive integer or 'half_range', got "
                f"{n_free_per_beam!r}."
            )
        counts = np.maximum(np.floor(beam_range / 2), 1)
        total = counts.sum()
        if total > _MAX_FREE_POINTS:
            raise ValueError(
                f"n_free_per_beam='half_range' would draw {total:.3g} free points (beams up to "
                f"{beam_range.max():.3g} m long); give max_beam_range to leave long beams out, "
                "or an integer n_free_per_beam."
            )
        return counts.astype(np.int64)
    if (
        not isinstance(n_free_per_beam, numbers.Integral)
        or isinstance(n_free_per_beam, bool)
        or n_free_per_beam < 1
    ):
        raise ValueError(
            f"n_free_per_beam must be a positive integer or 'half_range', got {n_free_per_beam!r}."
        )
    total = int(n_free_per_beam) * beam_range.size
    if total > _MAX_FREE_POINTS:
        raise ValueError(
            f"n_free_per_beam={n_free_per_beam} would draw {total:.3g} free points "
            f"({beam_range.size} beams); use a smaller n_free_per_beam."
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
    scans, *, n_free_per_beam=1, free_margin=_FREE_MARGIN, max_beam_range=None, random_state=None
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
    usable = (free_length > 0) & ~scans.unread()
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


def _check_environment(environment):
    if not isinstance(environment, (Environment2D, Room3D)):
        raise ValueError(
            "environment must be a skoccmap.datasets.Environment2D or Room3D, got "
            f"{type(environment).__name__}."
        )


def _positive_proba(estimator, X):
    """P(occupied) from ``predict_proba``: the column of the larger class, as every
    estimator of the package reads its labels (1 of {0, 1}, 2 of {1, 2}); the last column
    without ``classes_``."""
    if not hasattr(estimator, "predict_proba"):
        raise ValueError(
            f"the estimator must be a fitted classifier with predict_proba, got "
            f"{type(estimator).__name__}."
        )
    with queries_of_our_own():
        proba = np.asarray(estimator.predict_proba(X))
    if proba.ndim != 2 or proba.shape[1] != 2:
        raise ValueError(
            "the estimator must predict two classes (free, occupied); predict_proba gave "
            f"shape {proba.shape}."
        )
    classes = getattr(estimator, "classes_", None)
    column = 0 if classes is not None and len(classes) == 2 and classes[0] > classes[1] else 1
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
    estimator,
    scans,
    *,
    n_free_per_beam=1,
    free_margin=_FREE_MARGIN,
    max_beam_range=None,
    random_state=None,
):
    """ROC AUC of a map on held-out scans (hit points vs. free points along their beams).

    Parameters
    ----------
    estimator : fitted classifier
        Its ``predict_proba`` on zero-length segments (on points, for a classifier fitted
        on as many columns as the scans have dimensions, e.g. ``layout="points"``) gives
        P(occupied) in the column of the larger class, ``classes_[1]`` (1 of {0, 1}, 2 of
        {1, 2}, ``"occupied"`` of {``"free"``, ``"occupied"``}), as every estimator of the
        package reads its labels: labels whose occupied one sorts first (e.g. ``"hit"`` and
        ``"miss"``) score the map inverted.
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
    proba = _positive_proba(estimator, queries_at(estimator, points))
    return _auc(labels, proba, "held-out point")


def ground_truth_auc(estimator_or_proba, environment, resolution=0.2, *, extent=None, scans=None):
    """ROC AUC of a map against a simulator's true occupancy grid.

    Parameters
    ----------
    estimator_or_proba : fitted classifier or array-like of shape (n_cells,)
        A classifier whose ``predict_proba`` is evaluated at the cell centres (as zero-length
        segments, or points for a classifier fitted on points), or P(occupied) per cell of
        ``environment.ground_truth_grid(resolution, extent)`` in its order (or, with
        ``scans``, per observed cell only). The centre stands for the whole cell here, so
        that AUCs stay comparable with earlier results;
        :func:`map_quality` reads a classifier's cell by its largest value over the cell.
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
    _check_environment(environment)
    grid = environment.ground_truth_grid(resolution, extent, scans=scans)
    scored = np.ones(len(grid.points), bool) if scans is None else grid.observed
    what = "grid cell" if scans is None else "observed grid cell"
    labels = grid.occupied[scored]
    _check_both_classes(labels, what)
    if hasattr(estimator_or_proba, "predict_proba"):
        queries = queries_at(estimator_or_proba, grid.points[scored])
        proba = _positive_proba(estimator_or_proba, queries)
    else:
        proba = np.asarray(estimator_or_proba, dtype=np.float64)
        if proba.shape == scored.shape:  # one per cell of the grid: keep the scored ones
            proba = proba[scored]
    return _auc(labels, proba, what)


# --------------------------------------------------------------------------------------------
# Map quality against a simulator's true map
# --------------------------------------------------------------------------------------------

# Free cells farther than this (metres) from every surface are where a map has no excuse to
# mark occupied: beyond the blur a 0.1 m grid and a few centimetres of range noise explain.
_PHANTOM_CLEARANCE = 0.35
# Cells within this distance (metres) of a surface count towards walls found: a wall drawn
# one cell off is still found.
_WALL_TOLERANCE = 0.1
# How far (metres) the wall-thickness walk goes from a wall along its normal.
_BAND_REACH = 2.0
_ECE_BINS = 10
# Rounding slack of distances and step positions.
_TOL = 1e-9


def _check_probabilities(proba, name="proba"):
    proba = np.asarray(proba, dtype=np.float64)
    if not np.all(np.isfinite(proba)):
        raise ValueError(
            f"{name}: {np.count_nonzero(~np.isfinite(proba))} NaN or infinite value(s); the "
            "map cannot be scored."
        )
    if proba.size and (proba.min() < 0 or proba.max() > 1):
        raise ValueError(
            f"{name}: probabilities must lie in [0, 1], got values in "
            f"[{proba.min():.6g}, {proba.max():.6g}]."
        )
    return proba


# Beyond this many bins ``p * n_bins`` is no longer exact in float64, so samples would fall
# in bins by rounding.
_MAX_BINS = 2**52


def expected_calibration_error(y_true, proba, n_bins=10):
    """Expected calibration error of binary probabilities, with equal-width bins.

    The probabilities are put in ``n_bins`` bins of equal width on [0, 1] (bin k holds
    ``k / n_bins <= p < (k + 1) / n_bins``; p = 1 falls in the last bin). The error is the mean
    over bins, weighted by their share of the samples, of ``|mean p - frequency of 1|``:
    0 for a perfectly calibrated predictor, at most 1.

    Parameters
    ----------
    y_true : array-like of shape (n_samples,)
        True labels, 0 or 1.
    proba : array-like of shape (n_samples,)
        Predicted probabilities of class 1.
    n_bins : int, default=10
        Number of bins, at most 2**52 (a ValueError beyond).

    Returns
    -------
    ece : float

    See Also
    --------
    sklearn.calibration.calibration_curve : The per-bin means behind this summary.
    sklearn.metrics.brier_score_loss : Mean squared error of the probabilities.

    Examples
    --------
    >>> from skoccmap.metrics import expected_calibration_error
    >>> expected_calibration_error([0, 0, 1, 1], [0.1, 0.3, 0.7, 0.9])
    0.2
    >>> expected_calibration_error([0, 1, 0, 1], [0.5, 0.5, 0.5, 0.5])
    0.0
    """
    y_true = np.asarray(y_true)
    proba = _check_probabilities(proba)
    if y_true.ndim != 1 or proba.shape != y_true.shape:
        raise ValueError(
            "y_true and proba must be 1-D arrays of the same length, got shapes "
            f"{y_true.shape} and {proba.shape}."
        )
    if y_true.size == 0:
        raise ValueError("y_true is empty: there is nothing to score.")
    if not np.all(np.isin(y_true, [0, 1])):
        raise ValueError("y_true must hold only the labels 0 and 1.")
    n_bins = _check_positive_int(n_bins, "n_bins")
    if n_bins > _MAX_BINS:
        raise ValueError(
            f"n_bins={n_bins} is more bins than float64 probabilities can be told apart "
            f"by (at most 2**52); use fewer."
        )
    bins = np.minimum((proba * n_bins).astype(np.int64), n_bins - 1)
    if n_bins > proba.size:
        # More bins than samples: only those holding samples, as empty ones add nothing.
        _, bins = np.unique(bins, return_inverse=True)
    # sum_b (n_b / n) |mean_b(p) - mean_b(y)| = sum_b |sum_b(p) - sum_b(y)| / n
    gap = np.bincount(bins, proba) - np.bincount(bins, y_true.astype(float))
    return float(np.abs(gap).sum() / len(proba))


def _surface_distance(environment, points):
    """Distance from points to the environment's occupied space (0 inside it)."""
    if isinstance(environment, Environment2D):
        # Environment2D.distance is to the walls' centre lines.
        h = environment.wall_thickness / 2
        return np.maximum(environment.distance(points) - h, 0.0)
    return environment.distance(points)


def _cell_index(points, grid):
    """Flat index of the grid cell holding each point; -1 outside the grid.

    A point on a cell edge is in the cell above it (cells are ``[lo, lo + resolution)``),
    whichever way ``(x - lo) / resolution`` rounded (:func:`~skoccmap.grid._cells_below`):
    the band steps of a wall lie on cell edges, and the same map would otherwise measure a
    step thicker or thinner as the wall moved by whole cells.
    """
    lo = grid.extent[0::2]
    counts = np.array(grid.shape[::-1])  # x first, like the cell order of the grid
    cell = _cells_below((points - lo) / grid.resolution).astype(np.int64)
    inside = np.all((cell >= 0) & (cell < counts), axis=-1)
    strides = np.cumprod(np.r_[1, counts[:-1]])
    return np.where(inside, cell @ strides, -1)


def _wall_bands_2d(environment, resolution):
    """Samples every ``resolution`` along the walls' centre lines, walked both ways."""
    a, b = environment.walls[:, :2], environment.walls[:, 2:]
    length = np.linalg.norm(b - a, axis=1)
    origins, normals = [], []
    for start, end, L in zip(a, b, length, strict=True):
        if L == 0:  # no direction, so no normal
            continue
        n = max(1, round(L / resolution))
        u = (end - start) / L
        origins.append(start + ((np.arange(n) + 0.5) * L / n)[:, None] * u)
        normals.append(np.broadcast_to([-u[1], u[0]], (n, 2)))
    k = round(_BAND_REACH / resolution)
    steps = np.arange(-k, k + 1) * resolution
    h = environment.wall_thickness / 2
    return Bunch(
        origins=np.concatenate(origins or [np.zeros((0, 2))]),
        normals=np.concatenate(normals or [np.zeros((0, 2))]),
        steps=steps,
        # A band goes through the wall: it holds a step within half a step of the wall.
        seeds=np.where(np.abs(steps) <= h + resolution / 2 + _TOL, np.abs(steps), np.inf),
        own=np.maximum(np.abs(steps) - h, 0.0),  # distance of each step to this wall
        # The cells just inside and just outside both surfaces.
        surface=np.array([h - resolution / 2, h + resolution / 2, -h + resolution / 2,
                          -h - resolution / 2]),
    )  # fmt: skip


def _face_bands_3d(room, resolution):
    """Samples every ``resolution`` over the faces of the room and its obstacles.

    A face bounds a solid whose inside no scan sees, so the walk starts half a step inside
    the solid and goes out into free space only.
    """
    size = room.size
    # (axis, position, sign of the normal into free space, lower and upper corner of the face)
    faces = []
    for axis in range(3):
        faces += [(axis, 0.0, 1.0, np.zeros(3), size), (axis, size[axis], -1.0, np.zeros(3), size)]
        for lo, hi in zip(room.obstacles[:, :3], room.obstacles[:, 3:], strict=True):
            faces += [(axis, lo[axis], -1.0, lo, hi), (axis, hi[axis], 1.0, lo, hi)]
    origins, normals = [], []
    for axis, position, sign, lo, hi in faces:
        others = [other for other in range(3) if other != axis]
        axes = [[position]]
        for other in others:
            n = max(1, round((hi[other] - lo[other]) / resolution))
            axes.append(lo[other] + (np.arange(n) + 0.5) * (hi[other] - lo[other]) / n)
        points = np.empty((np.prod([len(x) for x in axes]), 3))
        points[:, [axis, *others]] = np.column_stack(
            [m.ravel() for m in np.meshgrid(*axes, indexing="ij")]
        )
        origins.append(points)
        normals.append(np.broadcast_to(sign * np.eye(3)[axis], points.shape))
    k = round(_BAND_REACH / resolution)
    steps = (np.arange(k + 1) - 0.5) * resolution
    return Bunch(
        origins=np.concatenate(origins),
        normals=np.concatenate(normals),
        steps=steps,
        # A band starts at the face: it holds one of the steps half a step either side.
        seeds=np.where(steps < resolution / 2 + _TOL, np.abs(steps), np.inf),
        own=np.maximum(steps, 0.0),
        surface=np.array([-resolution / 2, resolution / 2]),
    )


def _runs(occupied, seeds):
    """First and last step of the run of True through the best seed step, per row.

    ``occupied`` is (n_rows, n_steps); ``seeds`` (n_steps,) ranks the steps a run may go
    through (lower first, ``inf`` for the others). Returns ``start``, ``end`` and ``found``
    (rows holding an occupied seed step; ``start`` and ``end`` are meaningless elsewhere).
    """
    n_rows, n_steps = occupied.shape
    rows, index = np.arange(n_rows), np.arange(n_steps)
    rank = np.where(occupied, seeds[None, :], np.inf)
    seed = np.argmin(rank, axis=1)
    found = np.isfinite(rank[rows, seed])
    last_free = np.maximum.accumulate(np.where(occupied, -1, index), axis=1)
    next_free = np.minimum.accumulate(np.where(occupied, n_steps, index)[:, ::-1], axis=1)
    return last_free[rows, seed] + 1, next_free[:, ::-1][rows, seed] - 1, found


def _cell_maximum(probability_at, grid, scored):
    """A point map's value for each cell: its largest P(occupied) over the closed cell.

    The true grids mark a cell occupied when any of its closed square (cube) touches occupied
    space, so the probability that a cell is occupied is at least that of any of its points.
    Queried at the centre alone, the exact map misses every cell that overlaps a wall by less
    than half a cell. The cell is sampled at its corners, edge (and face) midpoints and centre,
    a lattice of step ``resolution / 2`` shared between neighbouring cells: walls at least a
    cell thick never fall between its points.
    """
    centres, half, lo = grid.points[scored], grid.resolution / 2, grid.extent[0::2]
    n_dims = centres.shape[1]
    offsets = np.stack(np.meshgrid(*[[-1, 0, 1]] * n_dims, indexing="ij"), -1).reshape(-1, n_dims)
    # Integer lattice coordinates in half cells, so that shared points are queried once.
    lattice = np.rint((centres - lo) / half).astype(np.int64)[:, None, :] + offsets[None]
    points, cell_of_point = np.unique(lattice.reshape(-1, n_dims), axis=0, return_inverse=True)
    proba = probability_at(lo + points * half, "grid-cell point")
    return proba[cell_of_point.reshape(len(centres), -1)].max(axis=1)


def _probability_source(estimator_or_proba, grid, scored):
    """P(occupied) of the scored cells and a function giving it at any points."""
    if hasattr(estimator_or_proba, "predict_proba"):
        estimator = estimator_or_proba

        def at(points, what):
            if len(points) == 0:
                return np.zeros(0)
            proba = _positive_proba(estimator, queries_at(estimator, points))
            if proba.shape != (len(points),):
                raise ValueError(
                    f"predict_proba gave {proba.shape[0]} probabilities for {len(points)} {what}s."
                )
            return _check_probabilities(proba, f"predict_proba at the {what}s")

        return _cell_maximum(at, grid, scored), at

    proba = np.asarray(estimator_or_proba, dtype=np.float64)
    n_cells, n_scored = len(grid.points), int(scored.sum())
    if proba.shape == tuple(grid.shape):
        proba = proba.ravel()
    if proba.shape == (n_cells,):
        full = proba
    elif proba.shape == (n_scored,):
        full = np.full(n_cells, np.nan)  # cells not scored: unknown, never in a band
        full[scored] = proba
    else:
        raise ValueError(
            f"probabilities must have shape ({n_cells},) or {tuple(grid.shape)} (one per grid "
            f"cell) or ({n_scored},) (one per scored cell), got {proba.shape}."
        )
    _check_probabilities(proba, "estimator_or_proba")

    def lookup(points, what):
        cell = _cell_index(points, grid)
        return np.where(cell >= 0, full[cell], np.nan)

    return full[scored], lookup


def _wall_thickness(environment, grid, probability_at):
    """Median width of the occupied band across the observed walls, and the sample counts."""
    resolution = grid.resolution
    if isinstance(environment, Environment2D):
        band = _wall_bands_2d(environment, resolution)
    else:
        band = _face_bands_3d(environment, resolution)

    # A sample counts when a cell at its surface lies in the grid (and was observed).
    surface = band.origins[:, None, :] + band.surface[None, :, None] * band.normals[:, None, :]
    cell = _cell_index(surface, grid)
    known = cell >= 0 if grid.observed is None else (cell >= 0) & grid.observed[cell]
    origins, normals = band.origins[known.any(axis=1)], band.normals[known.any(axis=1)]
    if len(origins) == 0:
        raise ValueError(
            "no wall sample lies inside the grid"
            + ("" if grid.observed is None else " where the scans observed it")
            + ": there is no wall whose thickness could be measured."
        )
    walk = origins[:, None, :] + band.steps[None, :, None] * normals[:, None, :]
    shape, flat = walk.shape[:2], walk.reshape(-1, walk.shape[2])
    proba = probability_at(flat, "wall-band point")
    distance = _surface_distance(environment, flat)
    if grid.observed is not None:
        # Space no scan observed is the map's unknown region, not its wall: the band ends
        # there (the wall's own inside is never observed and keeps the map's value).
        cell = _cell_index(flat, grid)
        unobserved = (cell < 0) | ~grid.observed[np.maximum(cell, 0)]
        proba = np.where(unobserved & (distance > 0), 0.0, proba)
    proba = proba.reshape(shape)
    start, end, found = _runs(proba > ROS_OCCUPIED_THRESH, band.seeds)  # NaN: not occupied

    # Where the walk nears another surface (corners, junctions, faces against a solid), or
    # where the map has no value, the band cannot be told from another wall's or does not
    # end where the map says: such samples are skipped. Checked over the band and the wall's
    # own extent, one step beyond each.
    nearer_other = distance.reshape(shape) < band.own - 1e-6
    bad = np.pad(np.cumsum(nearer_other | np.isnan(proba), axis=1), ((0, 0), (1, 0)))
    wall = np.flatnonzero(np.isfinite(band.seeds))
    lo = np.maximum(np.where(found, np.minimum(start, wall[0]), wall[0]) - 1, 0)
    hi = np.minimum(np.where(found, np.maximum(end, wall[-1]), wall[-1]) + 1, shape[1] - 1)
    rows = np.arange(shape[0])
    measured = bad[rows, hi + 1] == bad[rows, lo]
    width = (end - start + 1)[measured & found] * resolution
    thickness = float(np.median(width)) if len(width) else float("nan")
    return thickness, int(measured.sum()), len(width)


def map_quality(estimator_or_proba, environment, *, resolution=0.1, scans=None, extent=None):
    """Thresholded and calibration scores of a map against a simulator's true map.

    An AUC only ranks cells; a navigation stack thresholds them. This scores a map on the
    cells of ``environment.ground_truth_grid(resolution, extent, scans=scans)`` at the ROS
    map_server thresholds (occupied: p > :data:`~skoccmap.grid.ROS_OCCUPIED_THRESH` = 0.65,
    free: p < :data:`~skoccmap.grid.ROS_FREE_THRESH` = 0.196), with the cell's true
    occupancy (``occupied``) as the truth.

    Parameters
    ----------
    estimator_or_proba : fitted classifier or array-like
        A classifier whose ``predict_proba`` (column of the larger class, as in
        :func:`heldout_auc`) is evaluated, as
        zero-length segments (as points, for a classifier fitted on points), over each cell
        and at the wall-band points; or P(occupied) per cell of the grid, of shape
        (n_cells,) in the grid's order or the grid's ``shape`` (an image), or (with
        ``scans``) of shape (n_observed_cells,) for the observed cells only. The wall-band
        points of an array take the value of the cell holding them. A classifier's value for
        a cell is its largest probability over the cell's corners, edge (3-D: and face)
        midpoints and centre: the true grid marks a cell occupied when any of it touches
        occupied space, and a cell is at least as likely occupied as any of its points. The
        exact map queried at the centres alone would miss every cell that overlaps a wall by
        less than half a cell (it finds 26-27 % of the walls of the paper's world and the
        office).
    environment : Environment2D or Room3D
        The simulated world.
    resolution : float, default=0.1
        Cell side in metres, and the step of the wall-band walk.
    scans : Scans, default=None
        If given, only the cells these scans observed are scored, and only the walls they
        observed are measured: a map cannot know the rest.
    extent : array-like, default=None
        Grid extent; defaults to the environment's.

    Returns
    -------
    scores : dict
        - ``"auc"``: ROC AUC of the probabilities of the scored cells against the truth.
        - ``"brier"``: Brier score (mean squared error of the probabilities,
          :func:`sklearn.metrics.brier_score_loss`) over the scored cells.
        - ``"ece"``: :func:`expected_calibration_error` over the scored cells (10 bins).
        - ``"phantom_rate"``: share of the truly free scored cells farther than 0.35 m from
          every surface that the map marks occupied (p > 0.65): phantom obstacles.
        - ``"free_found"``: share of the same cells that the map marks free (p < 0.196); the
          rest of them are unknown to a planner.
        - ``"walls_found"``: share of the truly occupied scored cells whose centre lies
          within 0.1 m of occupied space (inside it included) that the map marks occupied.
          Only truly occupied cells count: the free cells beside a wall belong to the
          phantom side of the ledger, and counting them would reward thick walls (a map as
          thin as the truth would score below 1).
        - ``"wall_thickness"``: median width in metres of the occupied band (p > 0.65)
          across the walls. Walls are sampled every ``resolution`` along their centre lines
          (2-D) or over the faces of the room and its box obstacles (3-D). From each sample
          the walk goes in ``resolution`` steps along the wall's normal: up to 2 m both ways
          in 2-D; in 3-D from half a step inside the solid out into free space, up to 2 m,
          since the inside of a solid is never seen. The band is the run of contiguous
          occupied steps through the wall (2-D: through a step within half a step of the
          wall; 3-D: through one of the two steps half a step either side of the face); its
          width is its number of steps times ``resolution``. An exact map queried as a
          classifier scores the wall's thickness in whole steps (2-D) or one step (3-D); the
          true grid of an Environment2D, whose cells touching a wall are occupied, scores a
          step more on each side.
          With ``scans``, steps outside the walls in cells no scan observed end the band:
          a map's extrapolation into space no sensor saw (behind a wall seen from one side)
          is its unknown region, not its wall.
          A sample counts when a cell at the wall's surface lies in the grid and (with
          ``scans``) was observed, and its band can be measured: samples whose band, or
          the wall itself, comes within a step of space nearer another surface (corners,
          junctions, faces against another solid) or of a point where the map has no value
          (outside the grid or, for arrays per observed cell, an unobserved cell) are
          skipped. The median is over the counted samples with a band (NaN if there are
          none): walls the map misses are what ``walls_found`` measures.
        - ``"n_cells"``, ``"n_far_free_cells"``, ``"n_near_wall_cells"``: cells scored, in
          the phantom / free-found set, and in the walls-found set; ``"n_wall_samples"``
          and ``"n_wall_bands"``: wall samples counted, and those with a band.

    Raises
    ------
    ValueError
        For NaN, infinite or out-of-range probabilities, probabilities of the wrong shape,
        an unsupported environment, scored cells all free or all occupied, or an empty set
        of cells or of wall samples (the message says which). Zero-length walls have no
        normal and give no wall samples.

    See Also
    --------
    ground_truth_auc : The AUC alone.

    Examples
    --------
    The true map itself, as probabilities per cell, on the cells the scans observed:

    >>> from skoccmap.datasets import make_paper_scans
    >>> from skoccmap.metrics import map_quality
    >>> data = make_paper_scans()
    >>> grid = data.environment.ground_truth_grid(0.1, scans=data.scans)
    >>> scores = map_quality(grid.occupied, data.environment, scans=data.scans)
    >>> scores["phantom_rate"], scores["free_found"], scores["walls_found"]
    (0.0, 1.0, 1.0)
    >>> scores["ece"], scores["brier"], round(scores["wall_thickness"], 2)
    (0.0, 0.0, 0.2)

    The true grid marks the cells that touch a 0.1 m wall occupied: a band of three cells,
    of which the scans see the wall and the cell on their side.
    A classifier is queried at the cells and along the bands; a map that is everywhere
    0.5 finds nothing at the thresholds:

    >>> import numpy as np
    >>> class Unsure:
    ...     classes_ = np.array([0, 1])
    ...     def predict_proba(self, X):
    ...         return np.full((len(X), 2), 0.5)
    >>> scores = map_quality(Unsure(), data.environment, scans=data.scans)
    >>> scores["phantom_rate"], scores["free_found"], scores["walls_found"]
    (0.0, 0.0, 0.0)
    >>> scores["wall_thickness"], scores["n_wall_bands"], round(scores["brier"], 2)
    (nan, 0, 0.25)
    """
    _check_environment(environment)
    grid = environment.ground_truth_grid(resolution, extent, scans=scans)
    scored = np.ones(len(grid.points), bool) if scans is None else grid.observed
    what = "grid cell" if scans is None else "observed grid cell"
    truth = grid.occupied[scored]
    _check_both_classes(truth, what)
    proba, probability_at = _probability_source(estimator_or_proba, grid, scored)

    distance = _surface_distance(environment, grid.points[scored])
    far_free = (truth == 0) & (distance > _PHANTOM_CLEARANCE)
    near_wall = (truth == 1) & (distance <= _WALL_TOLERANCE + _TOL)
    for cells, description in (
        (far_free, f"free and farther than {_PHANTOM_CLEARANCE} m from every surface"),
        (near_wall, f"occupied and within {_WALL_TOLERANCE} m of a surface"),
    ):
        if not cells.any():
            raise ValueError(
                f"no {what} is {description}: score a larger region, or observe more of it."
            )
    thickness, n_samples, n_bands = _wall_thickness(environment, grid, probability_at)
    return {
        "auc": _auc(truth, proba, what),
        "brier": float(brier_score_loss(truth, proba, labels=[0, 1])),
        "ece": expected_calibration_error(truth, proba, n_bins=_ECE_BINS),
        "phantom_rate": float(np.mean(proba[far_free] > ROS_OCCUPIED_THRESH)),
        "free_found": float(np.mean(proba[far_free] < ROS_FREE_THRESH)),
        "walls_found": float(np.mean(proba[near_wall] > ROS_OCCUPIED_THRESH)),
        "wall_thickness": thickness,
        "n_cells": int(scored.sum()),
        "n_far_free_cells": int(far_free.sum()),
        "n_near_wall_cells": int(near_wall.sum()),
        "n_wall_samples": n_samples,
        "n_wall_bands": n_bands,
    }
