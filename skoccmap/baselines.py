"""Baseline occupancy maps to compare the Gaussian-process maps against.

:class:`OccupancyGridMap` is the counting occupancy grid of ROS mapping and OctoMap: every
cell holds a log-odds value, raised by the hits that fall in it and lowered by the beams that
pass through it (Thrun, Burgard & Fox, *Probabilistic Robotics*, Table 9.1; Hornung et al.,
*OctoMap*, 2013, eq. 2-3).
"""

from numbers import Integral, Real

import numpy as np
from scipy.special import expit
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.utils._param_validation import Interval, StrOptions
from sklearn.utils.multiclass import check_classification_targets, type_of_target
from sklearn.utils.validation import check_is_fitted, validate_data

__all__ = ["OccupancyGridMap", "traverse_cells"]

# Above this many cells in the bounding box the counts are accumulated sparsely (sort + unique)
# instead of in a dense array.
_DENSE_CELL_LIMIT = 1 << 25


def _split_rows(X, layout):
    """Start and end coordinates of the rows of ``X`` under ``layout``."""
    n_columns = X.shape[1]
    if layout == "points" or (layout == "auto" and n_columns % 2):
        return X, X
    if n_columns % 2:
        raise ValueError(
            f"X has {n_columns} feature(s); with layout='segments' rows [start_1..start_D, "
            "end_1..end_D] need an even number of columns (2*D). Pass layout='points' for "
            "rows that are points."
        )
    n_dims = n_columns // 2
    return X[:, :n_dims], X[:, n_dims:]


# Within this distance (in cells) of a face, the order of two axes' crossings is decided
# from their crossing parameters rather than from the rounded crossing point.
_NEAR_FACE = 1e-6


def traverse_cells(starts, ends, origin, resolution, shape):
    """Cells crossed by line segments on a regular grid, by exact boundary crossings.

    The grid traversal of Amanatides & Woo (1987), vectorised over all segments at once: a
    segment leaves its current cell exactly where it crosses a cell boundary, so along axis
    ``d`` it crosses ``|i_end[d] - i_start[d]|`` boundaries at parameters ``t`` found in closed
    form; the cell entered at each crossing is the next index on axis ``d`` and the cell of
    the crossing point on the other axes. No per-cell loop and no sampling, so no cell is
    missed, whatever the segment length. (Passing exactly through a cell corner, a set of
    measure zero, visits the cell on one side of the corner.)

    Parameters
    ----------
    starts, ends : ndarray of shape (n_segments, n_dims)
        Segment end points; both must lie inside the grid.
    origin : ndarray of shape (n_dims,)
        Lower corner of cell ``(0, ..., 0)``.
    resolution : float
        Cell edge length.
    shape : tuple of int
        Number of cells along each axis (axis order as the coordinates).

    Returns
    -------
    segment : ndarray of shape (n_visits,)
        Index of the segment of each visit.
    cells : ndarray of shape (n_visits, n_dims)
        Integer cell index of each visit. Each segment visits its start cell and every cell
        it passes through exactly once. Visits are not in path order: first every
        segment's start cell, then the cells entered through faces of each axis in turn.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.baselines import traverse_cells
    >>> seg, cells = traverse_cells(np.array([[0.05, 0.05]]), np.array([[0.25, 0.15]]),
    ...                             origin=np.zeros(2), resolution=0.1, shape=(3, 2))
    >>> sorted(map(tuple, cells.tolist()))
    [(0, 0), (1, 0), (1, 1), (2, 1)]
    """
    origin = np.asarray(origin, dtype=np.float64)
    q0 = (np.asarray(starts, dtype=np.float64) - origin) / resolution
    q1 = (np.asarray(ends, dtype=np.float64) - origin) / resolution
    seg, flat = _traverse_flat(q0, q1, tuple(int(s) for s in shape))
    return seg, np.column_stack(np.unravel_index(flat, shape))


def _traverse_flat(q0, q1, shape):
    """:func:`traverse_cells` in grid units (cell edge 1, origin 0), returning flat indices.

    The one hot loop of the counting grid: per axis, all crossings of all segments at once,
    on 1-D columns only (gathers of whole rows cost more than the arithmetic).
    """
    n, n_dims = q0.shape
    upper = np.asarray(shape) - 1
    i0 = np.clip(np.floor(q0).astype(np.int64), 0, upper)
    i1 = np.clip(np.floor(q1).astype(np.int64), 0, upper)
    dq = q1 - q0
    strides = np.cumprod((1,) + shape[:0:-1])[::-1]
    seg_parts = [np.arange(n)]
    flat_parts = [i0 @ strides]
    for d in range(n_dims):
        n_cross = np.abs(i1[:, d] - i0[:, d])
        total = int(n_cross.sum())
        if total == 0:
            continue
        seg = np.repeat(np.arange(n), n_cross)
        step = np.sign(i1[:, d] - i0[:, d])
        # k = 1..n_cross within each segment; the cell entered at crossing k is i0 + step * k.
        k = np.arange(1, total + 1) - np.repeat(np.cumsum(n_cross) - n_cross, n_cross)
        entered = i0[seg, d] + step[seg] * k
        # The face crossed is the entered cell's lower face moving up, its upper face moving
        # down.
        t = (entered + (step[seg] < 0) - q0[seg, d]) / dq[seg, d]
        flat = entered * strides[d]
        for e in range(n_dims):
            if e == d:
                continue
            dqe = dq[seg, e]
            q = q0[seg, e] + t * dqe
            # Near a face of axis e, which axis crossed first is decided by comparing the
            # crossing parameters, computed exactly as axis e's own loop computes its t, so
            # the two loops agree bit for bit: no cell is entered twice or skipped. At an
            # exact corner the axes are crossed in index order (e before d).
            face = np.round(q)
            near = (np.abs(q - face) <= _NEAR_FACE) & (dqe != 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                t_e = (face.astype(np.int64) - q0[seg, e]) / dqe
            e_first = (t_e < t) | ((t_e == t) & (e < d))
            idx = np.where(
                near, np.where(dqe > 0, face - 1 + e_first, face - e_first), np.floor(q)
            )
            low = np.minimum(i0[:, e], i1[:, e])[seg]
            high = np.maximum(i0[:, e], i1[:, e])[seg]
            # Rounding at a face must not push an axis outside the segment's cell range.
            flat += np.clip(idx.astype(np.int64), low, high) * strides[e]
        seg_parts.append(seg)
        flat_parts.append(flat)
    return np.concatenate(seg_parts), np.concatenate(flat_parts)


class OccupancyGridMap(ClassifierMixin, BaseEstimator):
    """Counting occupancy grid with log-odds updates (the ROS mapping / OctoMap baseline).

    Fitted on segment rows ``[start, end]`` like every skoccmap estimator: rows of the
    occupied class (the larger label, ``classes_[1]``) are hits and add ``l_occ`` to the
    log-odds of the cell holding their end point; rows of the free class are beams that add
    ``l_free`` to every cell they cross (exact traversal, :func:`traverse_cells`) except
    their end cell, as OctoMap's ray update does, so a beam ending a few centimetres short of
    its hit does not erase the hit's cell. A free segment inside a single cell (a free point)
    lowers that cell. The summed log-odds are clamped to ``[l_min, l_max]``.

    The fit is order-free: evidence is summed over all rows and clamped once. OctoMap clamps
    after every update, which makes old evidence fade; that depends on the time order of the
    scans, which rows of ``X`` do not carry.

    Works in any dimension ``D`` (``2 * D`` columns); cells are stored sparsely, so memory
    grows with the number of observed cells, not with the bounding box.

    Parameters
    ----------
    resolution : float, default=0.1
        Cell edge length in metres.
    l_occ : float, default=0.85
        Log-odds added per hit (0.85 = log(0.7/0.3), OctoMap's hit probability 0.7).
    l_free : float, default=-0.4
        Log-odds added per beam passing a cell (-0.4 = log(0.4/0.6), miss probability 0.4).
    l_min, l_max : float, default=-2.0, 3.5
        Clamping bounds of the log-odds (OctoMap's 0.12 and 0.97).
    layout : {"auto", "segments", "points"}, default="auto"
        How rows of ``X`` are read. ``"segments"``: ``[start, end]`` with ``2 * D`` columns;
        ``"points"``: every row is a point of ``D = n_columns`` coordinates (a free point
        lowers its cell); ``"auto"``: segments when the number of columns is even, points
        when it is odd (such a row cannot hold a segment). Use ``"points"`` for 2-column
        points in 2-D, which ``"auto"`` reads as 1-D segments.
    chunk_size : int, default=100_000
        Beams traversed at once; bounds the memory of the fit.

    Attributes
    ----------
    classes_ : ndarray of shape (2,)
        Class labels; ``classes_[1]`` is the occupied class.
    origin_ : ndarray of shape (n_dims,)
        Lower corner of cell ``(0, .., 0)``, a multiple of ``resolution``.
    shape_ : tuple of int
        Cells along each axis of the bounding box of the data.
    cell_index_ : ndarray of shape (n_observed_cells,)
        Sorted flat (C-order) indices of the cells observed at least once.
    log_odds_ : ndarray of shape (n_observed_cells,)
        Clamped log-odds of those cells; all other cells hold 0 (probability 0.5).
    extent_ : ndarray of shape (2 * n_dims,)
        ``[min_1, max_1, ..., min_D, max_D]`` of the grid, for :class:`skoccmap.OccupancyGrid`.
    n_features_in_ : int
        Number of columns seen in fit (``2 * n_dims``).

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.baselines import OccupancyGridMap
    >>> X = np.array([[0.0, 0.0, 1.0, 0.0],     # a beam from (0, 0) to (1, 0)
    ...               [1.05, 0.0, 1.05, 0.0]])  # its hit at (1.05, 0)
    >>> grid = OccupancyGridMap(resolution=0.1).fit(X, [0, 1])
    >>> queries = np.array([[0.5, 0.0, 0.5, 0.0], [1.05, 0.0, 1.05, 0.0], [5.0, 5.0, 5.0, 5.0]])
    >>> grid.predict_proba(queries)[:, 1].round(3)
    array([0.401, 0.701, 0.5  ])
    """

    _parameter_constraints: dict = {
        "resolution": [Interval(Real, 0, None, closed="neither")],
        "l_occ": [Interval(Real, 0, None, closed="neither")],
        "l_free": [Interval(Real, None, 0, closed="neither")],
        "l_min": [Interval(Real, None, 0, closed="right")],
        "l_max": [Interval(Real, 0, None, closed="left")],
        "layout": [StrOptions({"auto", "segments", "points"})],
        "chunk_size": [Interval(Integral, 1, None, closed="left")],
    }

    def __init__(
        self,
        resolution=0.1,
        *,
        l_occ=0.85,
        l_free=-0.4,
        l_min=-2.0,
        l_max=3.5,
        layout="auto",
        chunk_size=100_000,
    ):
        self.resolution = resolution
        self.l_occ = l_occ
        self.l_free = l_free
        self.l_min = l_min
        self.l_max = l_max
        self.layout = layout
        self.chunk_size = chunk_size

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.classifier_tags.multi_class = False
        # Columns are coordinates of segment end points; on generic features (the checks'
        # blobs) a grid over half of the columns cannot reach a good training score.
        tags.classifier_tags.poor_score = True
        return tags

    def fit(self, X, y):
        """Accumulate the log-odds of the cells hit and crossed by the observations.

        Parameters
        ----------
        X : array-like of shape (n_samples, 2 * n_dims)
            Segment rows ``[start, end]``; hits are zero-length segments.
        y : array-like of shape (n_samples,)
            Two classes; the larger label (``classes_[1]``) marks hits.

        Returns
        -------
        self : OccupancyGridMap
            The fitted grid.
        """
        self._validate_params()
        X, y = validate_data(self, X, y, dtype=np.float64)
        check_classification_targets(y)
        y_type = type_of_target(y, input_name="y")
        if y_type != "binary":
            raise ValueError(
                "Only binary classification is supported (free, occupied). The type of the "
                f"target is {y_type}."
            )
        self.classes_, y_idx = np.unique(y, return_inverse=True)
        if self.classes_.size != 2:
            raise ValueError(
                f"OccupancyGridMap needs samples of exactly 2 classes (free, occupied) in y, "
                f"got {self.classes_.size} class(es)."
            )
        if self.l_min >= self.l_max:
            raise ValueError(f"l_min ({self.l_min}) must be below l_max ({self.l_max}).")
        starts, ends = _split_rows(X, self.layout)
        res = float(self.resolution)
        low = np.minimum(starts.min(axis=0), ends.min(axis=0))
        high = np.maximum(starts.max(axis=0), ends.max(axis=0))
        self.origin_ = np.floor(low / res) * res
        self.shape_ = tuple(int(s) for s in np.floor((high - self.origin_) / res) + 1)
        self.extent_ = np.column_stack(
            [self.origin_, self.origin_ + res * np.array(self.shape_)]
        ).ravel()

        hit = y_idx == 1
        keys = [self._flat(self._cell_of(ends[hit]))]
        weights = [np.full(hit.sum(), float(self.l_occ))]
        free = np.flatnonzero(~hit)
        for lo in range(0, free.size, self.chunk_size):
            rows = free[lo : lo + self.chunk_size]
            seg, flat = _traverse_flat(
                (starts[rows] - self.origin_) / res, (ends[rows] - self.origin_) / res, self.shape_
            )
            end_flat = self._flat(self._cell_of(ends[rows]))[seg]
            start_flat = self._flat(self._cell_of(starts[rows]))[seg]
            keep = (flat != end_flat) | (start_flat == end_flat)
            keys.append(flat[keep])
            weights.append(np.full(int(keep.sum()), float(self.l_free)))
        self.cell_index_, log_odds = self._accumulate(
            np.concatenate(keys), np.concatenate(weights)
        )
        self.log_odds_ = np.clip(log_odds, self.l_min, self.l_max)
        return self

    def _cell_of(self, points):
        cells = np.floor((points - self.origin_) / self.resolution).astype(np.int64)
        return np.clip(cells, 0, np.asarray(self.shape_) - 1)

    def _flat(self, cells):
        return np.ravel_multi_index(tuple(cells.T), self.shape_)

    def _accumulate(self, keys, weights):
        n_cells = int(np.prod(self.shape_, dtype=np.float64))
        if n_cells <= _DENSE_CELL_LIMIT:
            total = np.bincount(keys, weights=weights, minlength=n_cells)
            seen = np.bincount(keys, minlength=n_cells) > 0
            index = np.flatnonzero(seen)
            return index, total[index]
        index, inverse = np.unique(keys, return_inverse=True)
        return index, np.bincount(inverse, weights=weights, minlength=index.size)

    def log_odds(self, X):
        """Log-odds of the cells holding the query segments' midpoints.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * n_dims)
            Query segment rows; points are zero-length segments. A segment is looked up at its
            midpoint.

        Returns
        -------
        log_odds : ndarray of shape (n_queries,)
            0 for cells never observed and for queries outside the grid.
        """
        check_is_fitted(self)
        X = validate_data(self, X, reset=False, dtype=np.float64)
        starts, ends = _split_rows(X, self.layout)
        mid = 0.5 * (starts + ends)
        cells = np.floor((mid - self.origin_) / self.resolution)
        inside = np.all((cells >= 0) & (cells < np.asarray(self.shape_)), axis=1)
        out = np.zeros(X.shape[0])
        if not inside.any() or self.cell_index_.size == 0:
            return out
        flat = self._flat(cells[inside].astype(np.int64))
        pos = np.minimum(np.searchsorted(self.cell_index_, flat), self.cell_index_.size - 1)
        found = self.cell_index_[pos] == flat
        values = np.where(found, self.log_odds_[pos], 0.0)
        out[inside] = values
        return out

    def predict_proba(self, X):
        """Occupancy probability of the cells holding the query segments' midpoints.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * n_dims)
            Query segment rows; points are zero-length segments.

        Returns
        -------
        proba : ndarray of shape (n_queries, 2)
            Column 1 is P(occupied); cells never observed and queries outside the grid get 0.5.
        """
        p = expit(self.log_odds(X))
        return np.column_stack([1.0 - p, p])

    def predict(self, X):
        """Most probable class; unknown cells (probability 0.5) are labelled free.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * n_dims)
            Query segment rows.

        Returns
        -------
        y : ndarray of shape (n_queries,)
            ``classes_[1]`` where P(occupied) > 0.5, else ``classes_[0]``.
        """
        occupied = self.log_odds(X) > 0
        return self.classes_[occupied.astype(int)]
