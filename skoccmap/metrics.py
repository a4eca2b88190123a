"""Scoring occupancy maps: held-out scans of a log, or the simulator's true map.

Real logs have no true map, so the Hilbert-map literature scores a map on held-out scans:
their hit points are the positives, points drawn uniformly along their beams (short of the
hit) the negatives, and the score is the ROC AUC of the predicted occupancy probabilities.
Simulated data are also scored against the true map on a grid.
"""

import numbers

import numpy as np
from sklearn.metrics import roc_auc_score
from sklearn.utils import check_random_state

from .observations import Scans, _check_free_margin, as_segments

__all__ = ["split_scans", "heldout_points", "heldout_auc", "ground_truth_auc"]


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


def heldout_points(scans, *, n_free_per_beam=1, free_margin=0.05, random_state=None):
    """Labelled test points from held-out scans: hits occupied, points along beams free.

    Parameters
    ----------
    scans : Scans
        Held-out scans.
    n_free_per_beam : int, default=1
        Free points drawn per beam.
    free_margin : float, default=0.05
        Free points of a beam with a return are drawn uniformly from the sensor to
        ``free_margin`` short of the hit (none when the hit is within ``free_margin``); those
        of a beam without a return, uniformly from the sensor to ``max_range``.
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
    """
    scans = _check_scans(scans)
    if not isinstance(n_free_per_beam, numbers.Integral) or n_free_per_beam < 1:
        raise ValueError(f"n_free_per_beam must be a positive integer, got {n_free_per_beam!r}.")
    free_margin = _check_free_margin(free_margin)
    rng = check_random_state(random_state)

    returned = scans.returned()
    free_length = np.where(returned, scans.ranges - free_margin, scans.max_range)
    has_free = free_length > 0
    origins = np.broadcast_to(scans.origins()[:, None, :], scans.directions().shape)
    directions, origins = scans.directions()[has_free], origins[has_free]
    t = rng.uniform(size=(n_free_per_beam, len(directions))) * free_length[has_free]
    free = (origins[None] + t[..., None] * directions[None]).reshape(-1, scans.n_dims)

    hits = scans.hit_points()
    points = np.concatenate([hits, free])
    labels = np.r_[np.ones(len(hits), np.int64), np.zeros(len(free), np.int64)]
    return points, labels


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


def heldout_auc(estimator, scans, *, n_free_per_beam=1, free_margin=0.05, random_state=None):
    """ROC AUC of a map on held-out scans (hit points vs. free points along their beams).

    Parameters
    ----------
    estimator : fitted classifier
        Its ``predict_proba`` on zero-length segments gives P(occupied) in the column of
        class 1.
    scans : Scans
        Held-out scans; see :func:`split_scans`.
    n_free_per_beam, free_margin, random_state
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
        scans, n_free_per_beam=n_free_per_beam, free_margin=free_margin, random_state=random_state
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
