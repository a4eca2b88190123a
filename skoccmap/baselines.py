"""Baseline occupancy maps to compare the Gaussian-process maps against.

- :class:`OccupancyGridMap` is the counting occupancy grid of ROS mapping and OctoMap: every
  cell holds a log-odds value, raised by the hits that fall in it and lowered by the beams that
  pass through it (Thrun, Burgard & Fox, *Probabilistic Robotics*, Table 9.1; Hornung et al.,
  *OctoMap*, 2013, eq. 2-3), clamped once over all rows or, given each row's scan, after every
  scan as OctoMap does.
- :class:`FrequencyGridMap` is the counting grid of the Hilbert-map evaluation protocol: the
  fraction ``hits / (hits + passes)`` of each cell, unclamped.
- :class:`HilbertMap` is the Hilbert map of Ramos & Ott (RSS 2015): logistic regression by
  stochastic gradient descent on Nystroem features of an RBF kernel, trained on the hits and on
  points sampled along the free beams.

All three take the segment rows ``[start_1..start_D, end_1..end_D]`` of every skoccmap
estimator (hits are zero-length segments, ``y = 1``; free beams ``y = 0``) in any dimension
``D``, and return P(occupied) in column 1 of ``predict_proba``.
"""

from numbers import Integral, Real

import numpy as np
from scipy.special import expit
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.kernel_approximation import Nystroem
from sklearn.linear_model import SGDClassifier
from sklearn.utils import check_random_state
from sklearn.utils._param_validation import Interval, StrOptions
from sklearn.utils.multiclass import check_classification_targets, type_of_target
from sklearn.utils.random import sample_without_replacement
from sklearn.utils.validation import check_is_fitted, validate_data

from ._validation import (
    check_known_labels,
    check_magnitude,
    fit_or_unfitted,
    non_finite_explained,
    unfitted_on_error,
    validate_queries,
    warn_if_coarse_float32,
    warn_unless_metres,
)
from .grid import _snapped_origin

__all__ = ["FrequencyGridMap", "HilbertMap", "OccupancyGridMap", "traverse_cells"]

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
# Most cells one segment may cross: 1 678 km at 0.1 m. The traversal holds about 100 bytes
# per crossing, so a reading far off the map (a failed range of 1e8 m) would ask for
# gigabytes before anything else could say what is wrong.
_MAX_SEGMENT_CELLS = 1 << 24
# Cell crossings traversed at once (about 100 bytes each while traversing): a chunk of long
# beams, such as ranges given in millimetres, stays within half a gigabyte.
_CROSSINGS_PER_CHUNK = 1 << 22


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

    Raises
    ------
    ValueError
        If a segment is not finite or leaves the grid, or crosses more than 16 777 216
        cells (1 678 km at 0.1 m: a failed range read as a distance), whose visits alone
        would take gigabytes.

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap.baselines import traverse_cells
    >>> seg, cells = traverse_cells(np.array([[0.05, 0.05]]), np.array([[0.25, 0.15]]),
    ...                             origin=np.zeros(2), resolution=0.1, shape=(3, 2))
    >>> sorted(map(tuple, cells.tolist()))
    [(0, 0), (1, 0), (1, 1), (2, 1)]
    """
    starts, ends = np.asarray(starts, dtype=np.float64), np.asarray(ends, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    if starts.ndim != 2 or starts.shape != ends.shape:
        raise ValueError(
            "starts and ends must be arrays of shape (n_segments, n_dims) alike, got "
            f"{starts.shape} and {ends.shape}."
        )
    n_dims = starts.shape[1]
    if origin.shape != (n_dims,) or np.ndim(shape) != 1 or len(shape) != n_dims:
        raise ValueError(
            f"origin and shape must hold one value per dimension ({n_dims}), got origin of "
            f"shape {origin.shape} and shape={shape!r}."
        )
    counts = np.asarray(shape)
    if not (np.issubdtype(counts.dtype, np.integer) and np.all(counts >= 1)):
        raise ValueError(f"shape must be positive integers, got {shape!r}.")
    if not (np.ndim(resolution) == 0 and np.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive finite number, got {resolution!r}.")
    resolution = float(resolution)
    q0, q1 = (starts - origin) / resolution, (ends - origin) / resolution
    # Within rounding of the grid's faces (end points computed from the grid's own corner,
    # far from the origin of the coordinates: UTM-like values round to 1e-8 cells).
    scale = np.max(np.abs(origin), initial=0.0) / resolution + np.max(counts)
    lo, hi = -1e-12 * scale - 1e-9, counts + 1e-12 * scale + 1e-9
    inside = np.all((q0 >= lo) & (q0 <= hi) & (q1 >= lo) & (q1 <= hi), axis=1)
    if not np.all(inside):  # NaN included
        row = int(np.flatnonzero(~inside)[0])
        raise ValueError(
            f"segment {row} ({starts[row].tolist()} -> {ends[row].tolist()}) is not finite "
            "and inside the grid; clip segments to the grid first."
        )
    seg, flat = _traverse_flat(q0, q1, tuple(int(c) for c in counts))
    return seg, np.column_stack(np.unravel_index(flat, tuple(int(c) for c in counts)))


def _traverse_flat(q0, q1, shape):
    """:func:`traverse_cells` in grid units (cell edge 1, origin 0), returning flat indices.

    The one hot loop of the counting grid: per axis, all crossings of all segments at once,
    on 1-D columns only (gathers of whole rows cost more than the arithmetic).
    """
    n, n_dims = q0.shape
    upper = np.asarray(shape) - 1
    i0 = np.clip(np.floor(q0).astype(np.int64), 0, upper)
    i1 = np.clip(np.floor(q1).astype(np.int64), 0, upper)
    _check_crossings(np.abs(i1 - i0).sum(axis=1))
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


def _check_crossings(n_crossings):
    """ValueError when a segment would cross more than ``_MAX_SEGMENT_CELLS`` cells."""
    if n_crossings.size and n_crossings.max() >= _MAX_SEGMENT_CELLS:
        longest = int(n_crossings.max()) + 1
        raise ValueError(
            f"a segment crosses {longest:,} grid cells, more than {_MAX_SEGMENT_CELLS:,}: a "
            "reading far beyond any sensor's range (a failed range read as a distance?). "
            "Drop such rows or clip them to the sensor's maximum range (or, for a grid, use a "
            "coarser resolution)."
        )


def _chunks_by_crossings(first, last, max_rows):
    """Consecutive row ranges ``(lo, hi)`` to traverse at once: at most ``max_rows`` rows
    whose segments, from cell ``first`` to cell ``last`` (cell coordinates, one row per
    segment), cross at most ``_CROSSINGS_PER_CHUNK`` cells, but for a row that alone
    crosses more, which is a range of its own."""
    crossings = np.cumsum(np.abs(last - first).sum(axis=1) + 1)
    lo = 0
    while lo < crossings.size:
        done = crossings[lo - 1] if lo else 0
        hi = int(np.searchsorted(crossings, done + _CROSSINGS_PER_CHUNK, side="right"))
        hi = min(max(hi, lo + 1), lo + max_rows)
        yield lo, hi
        lo = hi


def _bounding_box(starts, ends):
    """Lower and upper corners of the box holding every row's start and end."""
    return (
        np.minimum(starts.min(axis=0), ends.min(axis=0)),
        np.maximum(starts.max(axis=0), ends.max(axis=0)),
    )


def _passed_cells(q0, q1, shape):
    """The cells free segments pass, in grid units: (segment, flat cell) pairs.

    Every cell a segment crosses (:func:`_traverse_flat`) except its end cell, as OctoMap's
    ray update does, so a beam ending a few centimetres short of its hit does not pass the
    hit's cell; a segment inside a single cell passes that cell.
    """
    seg, flat = _traverse_flat(q0, q1, shape)
    top = np.asarray(shape) - 1

    def cell(q):
        return np.ravel_multi_index(tuple(np.clip(np.floor(q), 0, top).astype(np.int64).T), shape)

    first, last = cell(q0)[seg], cell(q1)[seg]
    keep = (flat != last) | (first == last)
    return seg[keep], flat[keep]


# --------------------------------------------------------------------------------------------
# Shared by the estimators
# --------------------------------------------------------------------------------------------


def _binary_classes(y, name):
    """``classes_`` and the 0/1 index of every label; ``classes_[1]`` is the occupied class."""
    check_classification_targets(y)
    y_type = type_of_target(y, input_name="y")
    if y_type != "binary":
        raise ValueError(
            "Only binary classification is supported (free, occupied). The type of the "
            f"target is {y_type}."
        )
    classes, y_idx = np.unique(y, return_inverse=True)
    if classes.size != 2:
        raise ValueError(
            f"{name} needs samples of exactly 2 classes (free, occupied) in y, "
            f"got {classes.size} class(es)."
        )
    return classes, y_idx


def _label_index(y, classes):
    """0/1 index of every label among ``classes``, refusing labels outside them."""
    check_classification_targets(y)
    check_known_labels(y, classes)
    return np.searchsorted(classes, y)


def _check_scan_index(scan_index, n_samples):
    """Rank (0, 1, ... in increasing scan order) of the scan of every row."""
    scan_index = np.asarray(scan_index)
    if scan_index.ndim != 1 or scan_index.shape[0] != n_samples:
        raise ValueError(
            f"scan_index must hold one scan index per row of X ({n_samples}), got an array "
            f"of shape {scan_index.shape}."
        )
    if scan_index.dtype.kind == "f":
        if not np.all(np.isfinite(scan_index)):
            raise ValueError("scan_index contains NaN or infinite values.")
        if np.any(scan_index != np.round(scan_index)):
            raise ValueError("scan_index must hold integers (the scan of every row).")
    elif scan_index.dtype.kind not in "iu":
        raise ValueError(
            f"scan_index must hold integers (the scan of every row), got dtype {scan_index.dtype}."
        )
    return np.unique(scan_index, return_inverse=True)[1].astype(np.int64)


def _first_per_pair(major, minor, priority):
    """Unique ``(major, minor)`` pairs in lexicographic order, keeping the highest priority.

    Returns the pairs' ``major``, ``minor`` and ``priority`` (of the kept entry).
    """
    order = np.lexsort((~priority, minor, major))
    major, minor, priority = major[order], minor[order], priority[order]
    first = np.ones(major.size, dtype=bool)
    first[1:] = (major[1:] != major[:-1]) | (minor[1:] != minor[:-1])
    return major[first], minor[first], priority[first]


def _sum_by_cell(keys, weights, n_cells):
    """Observed cells (sorted flat indices) and the sum of each weight array over each.

    Dense bincounts while the grid has at most ``_DENSE_CELL_LIMIT`` cells, sort + unique
    beyond.
    """
    if n_cells <= _DENSE_CELL_LIMIT:
        index = np.flatnonzero(np.bincount(keys, minlength=n_cells))
        return index, [np.bincount(keys, weights=w, minlength=n_cells)[index] for w in weights]
    index, inverse = np.unique(keys, return_inverse=True)
    return index, [np.bincount(inverse, weights=w, minlength=index.size) for w in weights]


class _CountingGridBase(ClassifierMixin, BaseEstimator):
    """Grid geometry, cell visits of hits and free beams, and cell look-up of queries.

    Subclasses store one value per observed cell (sorted flat indices in ``cell_index_``) and
    turn it into P(occupied) in ``_proba_of_cells``.
    """

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.classifier_tags.multi_class = False
        # Columns are coordinates of segment end points; on generic features (the checks'
        # blobs) a grid over half of the columns cannot reach a good training score.
        tags.classifier_tags.poor_score = True
        return tags

    def _prepare_fit(self, X, y, classes=None):
        """Validate ``X, y``; set ``classes_`` (from ``y``, or ``classes`` where given), an
        empty grid over the data; return starts, ends, hit mask."""
        self._validate_params()
        self._check_params()
        with non_finite_explained("observations"):
            X_in, (X, y) = X, validate_data(self, X, y, dtype=np.float64)
        warn_if_coarse_float32(X_in, X)
        if classes is None:
            self.classes_, y_idx = _binary_classes(y, type(self).__name__)
        else:
            self.classes_ = np.unique(classes)
            if self.classes_.size != 2:
                raise ValueError(
                    "classes must name the 2 labels (free, occupied), got "
                    f"{self.classes_.tolist()!r}."
                )
            y_idx = _label_index(y, self.classes_)
        starts, ends = _split_rows(X, self.layout)
        warn_unless_metres(starts, ends)
        res = float(self.resolution)
        low, high = _bounding_box(starts, ends)
        origin = _snapped_origin(low, res)
        self._set_grid(origin, np.floor((high - origin) / res) + 1)
        self.cell_index_ = np.zeros(0, dtype=np.int64)
        self._start_empty()
        return starts, ends, y_idx == 1

    def _set_grid(self, origin, shape):
        # Cells are stored sparsely, but their flat index must fit an int64.
        if np.prod(shape) >= 2.0**62:
            raise ValueError(
                f"the data span {' x '.join(f'{s:.3g}' for s in shape)} cells at resolution "
                f"{self.resolution:g}, too many to index: use a coarser resolution, or look "
                "for a reading far off the map."
            )
        self.origin_ = origin
        self.shape_ = tuple(int(s) for s in shape)
        self.extent_ = np.column_stack(
            [self.origin_, self.origin_ + float(self.resolution) * np.array(self.shape_)]
        ).ravel()

    def _check_params(self):
        """Checks of parameters beyond their constraints (none here)."""

    def _prepare_batch(self, X, y, classes):
        """Validate a later ``partial_fit`` batch; grow the grid to hold it; return starts,
        ends, hit mask."""
        # Parameters set between calls: checked as the first call checks them.
        self._validate_params()
        self._check_params()
        self._check_resolution()
        X_in, (X, y) = X, validate_queries(self, X, y)  # an empty batch passes
        warn_if_coarse_float32(X_in, X)
        if classes is not None and not np.array_equal(np.unique(classes), self.classes_):
            raise ValueError(
                f"classes={list(classes)!r} differ from classes_ {self.classes_.tolist()!r} "
                "of the earlier calls."
            )
        hit = _label_index(y, self.classes_) == 1
        starts, ends = _split_rows(X, self.layout)
        warn_unless_metres(starts, ends)
        if hit.size:
            self._grow(starts, ends)
        return starts, ends, hit

    def _check_resolution(self):
        """``resolution`` set since the grid was built would read its cells at another
        size: refused, as the cells cannot be resized."""
        edge = (self.extent_[1::2] - self.extent_[::2]) / np.asarray(self.shape_)
        if not np.allclose(edge, self.resolution, rtol=1e-6, atol=0.0):
            raise ValueError(
                f"resolution={self.resolution!r} was set after the grid was built with cells "
                f"of {float(edge[0]):g}; call fit again (partial_fit cannot resize cells)."
            )

    def _grow(self, starts, ends):
        """Widen the grid to hold ``starts`` and ``ends``; the observed cells keep their
        places, their flat indices renumbered (C order is kept: they stay sorted)."""
        res = float(self.resolution)
        low, high = _bounding_box(starts, ends)
        snapped = _snapped_origin(low, res)
        shift = np.maximum(np.rint((self.origin_ - snapped) / res), 0)
        # An axis that grows down takes the snapped origin of its new lowest point, as fit
        # on all rows would: origin_ - shift * res would add its rounding at every growth.
        origin = np.where(shift > 0, snapped, self.origin_)
        shape = np.maximum(np.asarray(self.shape_) + shift, np.floor((high - origin) / res) + 1)
        if np.array_equal(shape, self.shape_):
            return
        cells = np.unravel_index(self.cell_index_, self.shape_)
        self._set_grid(origin, shape)
        moved = tuple(c + int(s) for c, s in zip(cells, shift, strict=True))
        self.cell_index_ = np.ravel_multi_index(moved, self.shape_).astype(np.int64)

    def _with_cells(self, cells, *values):
        """Add the sorted flat indices ``cells`` to ``cell_index_``; return ``values`` (one
        per observed cell) laid out on the new cells, 0 where a cell is new, and the
        positions of ``cells`` among them."""
        if self.cell_index_.size:
            index = np.union1d(self.cell_index_, cells)
        else:
            index = cells
        kept = np.searchsorted(index, self.cell_index_)
        laid = []
        for value in values:
            out = np.zeros(index.size, dtype=value.dtype)
            out[kept] = value
            laid.append(out)
        self.cell_index_ = index
        return laid, np.searchsorted(index, cells)

    def _partial_fit(self, X, y, classes, update):
        """``partial_fit``: the first call fits (with ``classes`` where given); a later one
        grows the grid and ``update(starts, ends, hit)`` adds its rows, an empty one
        none. A refused batch leaves the grid as it was."""
        if not hasattr(self, "cell_index_"):
            with unfitted_on_error(self):
                update(*self._prepare_fit(X, y, classes))
            return self
        before = dict(vars(self))
        try:
            starts, ends, hit = self._prepare_batch(X, y, classes)
            if hit.size:  # an empty batch (every reading of a scan failed) adds nothing
                update(starts, ends, hit)
        except BaseException:
            vars(self).clear()
            vars(self).update(before)
            raise
        return self

    def _n_cells(self):
        return int(np.prod(self.shape_, dtype=np.float64))

    def _cell_of(self, points):
        cells = np.floor((points - self.origin_) / self.resolution).astype(np.int64)
        return np.clip(cells, 0, np.asarray(self.shape_) - 1)

    def _flat(self, cells):
        return np.ravel_multi_index(tuple(cells.T), self.shape_)

    def _hit_cells(self, ends, hit):
        """Rows of the hits and the flat index of the cell holding each one's end point."""
        rows = np.flatnonzero(hit)
        return rows, self._flat(self._cell_of(ends[rows]))

    def _free_cells(self, starts, ends, hit):
        """Chunks of (row, flat cell) pairs: the cells each free row passes
        (:func:`_passed_cells`). Free rows longer than ``max_free_length`` pass nothing.
        At most ``chunk_size`` rows are traversed at once, fewer where they are long.
        """
        free = np.flatnonzero(~hit)
        if self.max_free_length is not None:
            length = np.linalg.norm(ends[free] - starts[free], axis=1)
            free = free[length <= self.max_free_length]
        res = float(self.resolution)
        q0, q1 = (starts[free] - self.origin_) / res, (ends[free] - self.origin_) / res
        for lo, hi in _chunks_by_crossings(np.floor(q0), np.floor(q1), self.chunk_size):
            seg, flat = _passed_cells(q0[lo:hi], q1[lo:hi], self.shape_)
            yield free[lo:hi][seg], flat

    def _cell_position(self, X):
        """Position in ``cell_index_`` of the cell holding each query's midpoint, else -1."""
        check_is_fitted(self)
        X = validate_queries(self, X)
        starts, ends = _split_rows(X, self.layout)
        mid = 0.5 * (starts + ends)
        cells = np.floor((mid - self.origin_) / self.resolution)
        inside = np.all((cells >= 0) & (cells < np.asarray(self.shape_)), axis=1)
        out = np.full(X.shape[0], -1, dtype=np.int64)
        if not inside.any() or self.cell_index_.size == 0:
            return out
        flat = self._flat(cells[inside].astype(np.int64))
        pos = np.minimum(np.searchsorted(self.cell_index_, flat), self.cell_index_.size - 1)
        out[inside] = np.where(self.cell_index_[pos] == flat, pos, -1)
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
        p = self._proba_of_cells(self._cell_position(X))
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
        occupied = self._occupied_of_cells(self._cell_position(X))
        return self.classes_[occupied.astype(int)]


# --------------------------------------------------------------------------------------------
# Counting grids
# --------------------------------------------------------------------------------------------


class OccupancyGridMap(_CountingGridBase):
    """Counting occupancy grid with log-odds updates (the ROS mapping / OctoMap baseline).

    Fitted on segment rows ``[start, end]`` like every skoccmap estimator: rows of the
    occupied class (the larger label, ``classes_[1]``) are hits and add ``l_occ`` to the
    log-odds of the cell holding their end point; rows of the free class are beams that add
    ``l_free`` to every cell they cross (exact traversal, :func:`traverse_cells`) except
    their end cell, as OctoMap's ray update does, so a beam ending a few centimetres short of
    its hit does not erase the hit's cell. A free segment inside a single cell (a free point)
    lowers that cell. Log-odds start at 0 (probability 0.5) and stay within
    ``[l_min, l_max]``, in one of two ways:

    - ``fit(X, y)``: evidence is summed over all rows and clamped once. The result does not
      depend on the order of the rows, which carry no time.
    - ``fit(X, y, scan_index=...)``: OctoMap's update. Scans are applied one after the other
      in increasing ``scan_index``; within a scan every cell is updated at most once -- by
      ``l_occ`` if any hit of the scan falls in it (a hit wins over the scan's free passes),
      else by ``l_free`` if one of its beams passes it -- and the log-odds are clamped after
      every scan. Evidence beyond a bound is then lost, so a cell saturated at ``l_max`` is
      lowered by the next free pass; with the sum, it may take many.

    :meth:`partial_fit` adds rows online, either way, the grid growing to hold them.

    Summed evidence saturates as scans accumulate: many cells tie at the bounds and ranking
    scores (AUC) fall with more data. Clamping after every scan keeps recent evidence in play.
    On the Hilbert-maps protocol at 0.1 m, trained on all remaining scans, the held-out AUC
    was 0.929 per scan against 0.901 summed on ACES (the tuning log, seed 100), and 0.938
    against 0.874 on the Intel lab (the report log, seed 0); trained on every 10th scan, the
    two were within 0.006 (ACES 0.888 against 0.893, Intel 0.941 both). Measured by
    ``python benchmarks/bench_tuning_baselines.py --only grid``.

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
    max_free_length : float or None, default=None
        Free rows longer than this (metres) update no cell, as OctoMap's ``maxrange``
        shortens them; ``None`` uses them all. See :class:`FrequencyGridMap`.
    layout : {"auto", "segments", "points"}, default="auto"
        How rows of ``X`` are read. ``"segments"``: ``[start, end]`` with ``2 * D`` columns;
        ``"points"``: every row is a point of ``D = n_columns`` coordinates (a free point
        lowers its cell); ``"auto"``: segments when the number of columns is even, points
        when it is odd (such a row cannot hold a segment). Use ``"points"`` for 2-column
        points in 2-D, which ``"auto"`` reads as 1-D segments.
    chunk_size : int, default=100_000
        Most beams traversed at once (fewer where they cross many cells); bounds the
        memory of the fit.

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

    See Also
    --------
    FrequencyGridMap : The unclamped hit frequency of every cell.

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

    Five scans see the same wall cell, a sixth passes it. Clamped after every scan, the cell
    sits at ``l_max = 3.5`` after the fifth hit and the pass lowers it to 3.1; summed, the
    excess evidence (5 * 0.85 = 4.25) keeps it at the bound:

    >>> hit, beam = [1.05, 0.0, 1.05, 0.0], [0.0, 0.0, 2.0, 0.0]
    >>> X, y = np.array([hit] * 5 + [beam]), [1] * 5 + [0]
    >>> OccupancyGridMap().fit(X, y, scan_index=[0, 1, 2, 3, 4, 5]).log_odds([hit]).round(2)
    array([3.1])
    >>> OccupancyGridMap().fit(X, y).log_odds([hit]).round(2)
    array([3.5])
    """

    _parameter_constraints: dict = {
        "resolution": [Interval(Real, 0, None, closed="neither")],
        "l_occ": [Interval(Real, 0, None, closed="neither")],
        "l_free": [Interval(Real, None, 0, closed="neither")],
        "l_min": [Interval(Real, None, 0, closed="right")],
        "l_max": [Interval(Real, 0, None, closed="left")],
        "max_free_length": [Interval(Real, 0, None, closed="neither"), None],
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
        max_free_length=None,
        layout="auto",
        chunk_size=100_000,
    ):
        self.resolution = resolution
        self.l_occ = l_occ
        self.l_free = l_free
        self.l_min = l_min
        self.l_max = l_max
        self.max_free_length = max_free_length
        self.layout = layout
        self.chunk_size = chunk_size

    @fit_or_unfitted
    def fit(self, X, y, scan_index=None):
        """Accumulate the log-odds of the cells hit and crossed by the observations.

        Parameters
        ----------
        X : array-like of shape (n_samples, 2 * n_dims)
            Segment rows ``[start, end]``; hits are zero-length segments.
        y : array-like of shape (n_samples,)
            Two classes; the larger label (``classes_[1]``) marks hits.
        scan_index : array-like of int of shape (n_samples,), default=None
            The scan each row comes from, e.g. from
            ``Scans.to_observations(return_scan_index=True)``. Given, scans are applied in
            increasing order, every cell updated at most once per scan and the log-odds
            clamped after every scan (OctoMap); ``None`` sums all evidence and clamps once.

        Returns
        -------
        self : OccupancyGridMap
            The fitted grid.
        """
        self._add(*self._prepare_fit(X, y), scan_index)
        return self

    def partial_fit(self, X, y, classes=None, scan_index=None):
        """Add observations to the grid (online mapping).

        The first call is :meth:`fit` (``classes`` names both labels where its ``y`` holds
        one only). Each later call applies its rows to the log-odds the grid holds, as
        :meth:`fit` applies them to zeros: summed and clamped once per call, or, with
        ``scan_index``, scan by scan, its scans after those of the earlier calls. Calls
        that each hold whole scans, with their ``scan_index``, give the grid of one
        ``fit`` on all the rows with theirs. The grid grows to hold new rows; a refused
        call (NaN, other columns, a label outside ``classes_``, a ``resolution`` set since
        the grid was built) leaves it as it was. Other parameters set between calls apply
        to the later rows.

        Parameters
        ----------
        X : array-like of shape (n_samples, 2 * n_dims)
            Segment rows ``[start, end]``; hits are zero-length segments.
        y : array-like of shape (n_samples,)
            Labels among ``classes_`` (the larger one marks hits). After the first call a
            batch may be empty (nothing is added), as in
            :meth:`skoccmap.MixtureGPOccupancyMap.partial_fit`.
        classes : array-like of shape (2,), default=None
            Both labels; needed on the first call only if its ``y`` holds one.
        scan_index : array-like of int of shape (n_samples,), default=None
            The scan of each row, as in :meth:`fit`.

        Returns
        -------
        self : OccupancyGridMap
            The updated grid.

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap.baselines import OccupancyGridMap
        >>> beam, hit = [0.0, 0.0, 1.0, 0.0], [1.05, 0.0, 1.05, 0.0]
        >>> grid = OccupancyGridMap().partial_fit([beam], [0], classes=[0, 1])
        >>> grid = grid.partial_fit([hit, [3.05, 0.0, 3.05, 0.0]], [1, 1])
        >>> grid.log_odds([hit, [0.55, 0.0, 0.55, 0.0]]).round(2), grid.extent_.round(2)
        (array([ 0.85, -0.4 ]), array([0. , 3.1, 0. , 0.1]))
        """
        return self._partial_fit(X, y, classes, lambda *rows: self._add(*rows, scan_index))

    def _check_params(self):
        if self.l_min >= self.l_max:
            raise ValueError(f"l_min ({self.l_min}) must be below l_max ({self.l_max}).")

    def _start_empty(self):
        self.log_odds_ = np.zeros(0)

    def _add(self, starts, ends, hit, scan_index):
        if scan_index is None:
            self._add_summed(starts, ends, hit)
        else:
            self._add_per_scan(starts, ends, hit, _check_scan_index(scan_index, hit.size))

    def _add_summed(self, starts, ends, hit):
        _, hit_flat = self._hit_cells(ends, hit)
        keys = [hit_flat]
        weights = [np.full(hit_flat.size, float(self.l_occ))]
        for _, flat in self._free_cells(starts, ends, hit):
            keys.append(flat)
            weights.append(np.full(flat.size, float(self.l_free)))
        cells, (evidence,) = _sum_by_cell(
            np.concatenate(keys), [np.concatenate(weights)], self._n_cells()
        )
        (log_odds,), at = self._with_cells(cells, self.log_odds_)
        log_odds[at] = np.clip(log_odds[at] + evidence, self.l_min, self.l_max)
        self.log_odds_ = log_odds

    def _add_per_scan(self, starts, ends, hit, scan):
        # One update per (scan, cell): hits first in each pair, so a hit wins over a pass.
        hit_rows, hit_flat = self._hit_cells(ends, hit)
        scans, cells, is_hit = [scan[hit_rows]], [hit_flat], [np.ones(hit_rows.size, bool)]
        for rows, flat in self._free_cells(starts, ends, hit):
            # Reduce each chunk at once: beams of a scan pass the cells near the sensor many
            # times.
            s, c, h = _first_per_pair(scan[rows], flat, np.zeros(flat.size, bool))
            scans.append(s)
            cells.append(c)
            is_hit.append(h)
        scans, cells, is_hit = _first_per_pair(
            np.concatenate(scans), np.concatenate(cells), np.concatenate(is_hit)
        )
        # The pairs come in scan order; within a scan each cell once.
        (log_odds,), _ = self._with_cells(np.unique(cells), self.log_odds_)
        cell_id = np.searchsorted(self.cell_index_, cells)
        update = np.where(is_hit, float(self.l_occ), float(self.l_free))
        bounds = np.flatnonzero(np.diff(scans)) + 1
        for lo, hi in zip(np.r_[0, bounds], np.r_[bounds, scans.size], strict=True):
            ids = cell_id[lo:hi]
            log_odds[ids] = np.clip(log_odds[ids] + update[lo:hi], self.l_min, self.l_max)
        self.log_odds_ = log_odds

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
        return self._log_odds_of_cells(self._cell_position(X))

    def _log_odds_of_cells(self, pos):
        out = np.zeros(pos.size)
        seen = pos >= 0
        out[seen] = self.log_odds_[pos[seen]]
        return out

    def _proba_of_cells(self, pos):
        return expit(self._log_odds_of_cells(pos))

    def _occupied_of_cells(self, pos):
        return self._log_odds_of_cells(pos) > 0


class FrequencyGridMap(_CountingGridBase):
    """Hit frequency per cell: the counting grid of the Hilbert-map evaluation protocol.

    Every cell counts the hits that fall in it and the free beams that pass it; its occupancy
    probability is ``hits / (hits + passes)``, unclamped, so evidence never saturates and cells
    keep their ranking however many scans are added (Ramos & Ott, RSS 2015, compare Hilbert
    maps against this grid at 0.1 m). A cell never observed -- no hit and no pass -- and a
    query outside the grid predict 0.5.

    Rows are counted as :class:`OccupancyGridMap` updates cells: a hit (a row of the occupied
    class, the larger label ``classes_[1]``) counts in the cell holding its end point; a free
    row passes every cell it crosses (exact traversal, :func:`traverse_cells`) except its end
    cell, and a free row inside a single cell passes that cell. Counts are summed over rows,
    so the fit does not depend on their order, nor on how :meth:`partial_fit` calls split
    them.

    Works in any dimension ``D`` (``2 * D`` columns); cells are stored sparsely.

    Parameters
    ----------
    resolution : float, default=0.1
        Cell edge length in metres (0.1 m: the protocol's grid).
    max_free_length : float or None, default=None
        Free rows longer than this (metres) pass no cell; ``None`` counts them all. The
        Hilbert-maps protocol skips readings beyond 40 m, as :class:`HilbertMap` does by
        default: beams without a return run to the sensor's maximum range through walls
        that glass or a grazing angle hid, and lower those walls' frequency everywhere
        they cross.
    layout : {"auto", "segments", "points"}, default="auto"
        How rows of ``X`` are read; see :class:`OccupancyGridMap`.
    chunk_size : int, default=100_000
        Most beams traversed at once (fewer where they cross many cells); bounds the
        memory of the fit.

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
    hits_ : ndarray of shape (n_observed_cells,), dtype int64
        Hits counted in each of those cells.
    passes_ : ndarray of shape (n_observed_cells,), dtype int64
        Free beams counted passing each of those cells.
    extent_ : ndarray of shape (2 * n_dims,)
        ``[min_1, max_1, ..., min_D, max_D]`` of the grid, for :class:`skoccmap.OccupancyGrid`.
    n_features_in_ : int
        Number of columns seen in fit (``2 * n_dims``).

    See Also
    --------
    OccupancyGridMap : Clamped log-odds updates (ROS mapping, OctoMap).

    Examples
    --------
    Three beams pass the cell at x = 0.5 and one hit falls in it:

    >>> import numpy as np
    >>> from skoccmap.baselines import FrequencyGridMap
    >>> X = np.array([[0.0, 0.0, 1.0, 0.0]] * 3 + [[0.55, 0.0, 0.55, 0.0]])
    >>> grid = FrequencyGridMap(resolution=0.1).fit(X, [0, 0, 0, 1])
    >>> queries = np.array([[0.55, 0.0, 0.55, 0.0], [0.25, 0.0, 0.25, 0.0], [5.0, 5.0, 5.0, 5.0]])
    >>> grid.predict_proba(queries)[:, 1]
    array([0.25, 0.  , 0.5 ])
    """

    _parameter_constraints: dict = {
        "resolution": [Interval(Real, 0, None, closed="neither")],
        "max_free_length": [Interval(Real, 0, None, closed="neither"), None],
        "layout": [StrOptions({"auto", "segments", "points"})],
        "chunk_size": [Interval(Integral, 1, None, closed="left")],
    }

    def __init__(self, resolution=0.1, *, max_free_length=None, layout="auto", chunk_size=100_000):
        self.resolution = resolution
        self.max_free_length = max_free_length
        self.layout = layout
        self.chunk_size = chunk_size

    @fit_or_unfitted
    def fit(self, X, y):
        """Count the hits in and the free beams through every cell.

        Parameters
        ----------
        X : array-like of shape (n_samples, 2 * n_dims)
            Segment rows ``[start, end]``; hits are zero-length segments.
        y : array-like of shape (n_samples,)
            Two classes; the larger label (``classes_[1]``) marks hits.

        Returns
        -------
        self : FrequencyGridMap
            The fitted grid.
        """
        self._add(*self._prepare_fit(X, y))
        return self

    def partial_fit(self, X, y, classes=None):
        """Add observations to the grid (online mapping).

        The first call is :meth:`fit` (``classes`` names both labels where its ``y`` holds
        one only); later calls add their counts, so any split of the rows into calls gives
        the grid of one ``fit`` on all of them (up to the rounding of a point on a cell's
        edge, which the grown grid's origin may place in either cell). The grid grows to
        hold new rows; a refused call (NaN, other columns, a label outside ``classes_``, a
        ``resolution`` set since the grid was built) leaves it as it was. Other parameters
        set between calls apply to the later rows.

        Parameters
        ----------
        X : array-like of shape (n_samples, 2 * n_dims)
            Segment rows ``[start, end]``; hits are zero-length segments.
        y : array-like of shape (n_samples,)
            Labels among ``classes_`` (the larger one marks hits). After the first call a
            batch may be empty (nothing is added), as in
            :meth:`skoccmap.MixtureGPOccupancyMap.partial_fit`.
        classes : array-like of shape (2,), default=None
            Both labels; needed on the first call only if its ``y`` holds one.

        Returns
        -------
        self : FrequencyGridMap
            The updated grid.

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap.baselines import FrequencyGridMap
        >>> beam, hit = [0.0, 0.0, 1.0, 0.0], [0.55, 0.0, 0.55, 0.0]
        >>> grid = FrequencyGridMap().partial_fit([beam, beam], [0, 0], classes=[0, 1])
        >>> grid.partial_fit([beam, hit], [0, 1]).predict_proba([hit])[:, 1]
        array([0.25])
        """
        return self._partial_fit(X, y, classes, self._add)

    def _start_empty(self):
        self.hits_ = np.zeros(0, dtype=np.int64)
        self.passes_ = np.zeros(0, dtype=np.int64)

    def _add(self, starts, ends, hit):
        _, hit_flat = self._hit_cells(ends, hit)
        keys, is_hit = [hit_flat], [np.ones(hit_flat.size)]
        for _, flat in self._free_cells(starts, ends, hit):
            keys.append(flat)
            is_hit.append(np.zeros(flat.size))
        is_hit = np.concatenate(is_hit)
        cells, (hits, passes) = _sum_by_cell(
            np.concatenate(keys), [is_hit, 1.0 - is_hit], self._n_cells()
        )
        (total_hits, total_passes), at = self._with_cells(cells, self.hits_, self.passes_)
        total_hits[at] += np.rint(hits).astype(np.int64)
        total_passes[at] += np.rint(passes).astype(np.int64)
        self.hits_, self.passes_ = total_hits, total_passes

    def _proba_of_cells(self, pos):
        p = np.full(pos.size, 0.5)
        seen = pos >= 0
        hits, passes = self.hits_[pos[seen]], self.passes_[pos[seen]]
        p[seen] = hits / (hits + passes)
        return p

    def _occupied_of_cells(self, pos):
        seen = pos >= 0
        occupied = np.zeros(pos.size, dtype=bool)
        occupied[seen] = self.hits_[pos[seen]] > self.passes_[pos[seen]]
        return occupied


# --------------------------------------------------------------------------------------------
# Hilbert map
# --------------------------------------------------------------------------------------------

# Query rows turned into Nystroem features at once (n_components float64 columns each).
_FEATURE_BATCH = 8192
# Training sets beyond this many bytes (mostly float32 features) are refused before any
# point is drawn.
_MAX_TRAINING_BYTES = 2**34


def _free_points_per_row(length, spacing):
    """Number of points sampled along each free row: one per ``spacing``, at least one."""
    # The cap only keeps absurdly long rows from overflowing the count.
    return np.maximum(1, np.ceil(np.minimum(length / spacing, 1e12))).astype(np.int64)


def _points_along(starts, ends, counts, index):
    """The ``index``-th of all points along the rows, ``counts[i]`` per row in row order.

    Row ``i`` is cut into ``counts[i]`` equal pieces and holds the pieces' centres.
    """
    offsets = np.cumsum(counts)
    row = np.searchsorted(offsets, index, side="right")
    k = index - (offsets[row] - counts[row])
    t = ((k + 0.5) / counts[row])[:, None]
    return starts[row] + t * (ends[row] - starts[row])


class HilbertMap(ClassifierMixin, BaseEstimator):
    """Hilbert map: logistic regression on kernel features (Ramos & Ott, RSS 2015).

    The continuous occupancy map of Ramos & Ott, assembled from scikit-learn parts: the
    training points are mapped to :class:`~sklearn.kernel_approximation.Nystroem` features of
    an RBF kernel ``exp(-gamma * |x - x'|^2)``, and a logistic regression on those features is
    fitted by stochastic gradient descent (:class:`~sklearn.linear_model.SGDClassifier` with
    ``loss="log_loss"``). Occupancy probabilities are the classifier's ``predict_proba``.

    Training points, from segment rows ``[start, end]``:

    - every row of the occupied class (the larger label, ``classes_[1]``) gives its end point
      (hits are zero-length segments);
    - every free row up to ``max_free_length`` long gives ``max(1, ceil(length /
      free_spacing))`` points, the centres of as many equal pieces of the row: one point every
      ``free_spacing`` metres at most, one point for a zero-length free row. Longer free rows
      -- beams without a return, drawn to the sensor's maximum range -- give none, as in the
      paper's code (see ``max_free_length``).

    When there are more than ``max_samples`` such points, ``max_samples`` of them are drawn
    uniformly without replacement, within each class in proportion to its size (at least one
    of each), so that the fit costs the same whatever the size of the log. Nystroem draws its
    ``n_components`` landmarks uniformly from the training points. Queries are segments looked
    up at their midpoints (a point is a zero-length segment).

    Free points outnumber hits (about ten to one on laser logs). By default the classes are
    not reweighted, as in the paper's code: the probabilities then follow the data's class
    frequencies, and far from all data the map returns to the intercept, which leans towards
    free. ``class_weight="balanced"`` weights the two classes equally instead.

    The figures quoted below for the parameters come from
    ``python benchmarks/bench_tuning_baselines.py --only hilbert``, one parameter changed at a
    time from the defaults: held-out AUC on ACES (the Hilbert-maps protocol, seed 100,
    trained on every 10th remaining scan) and map scores on the sparse office floor. Over
    five values of ``random_state`` the defaults gave an AUC of 0.928 to 0.946, so smaller
    differences are not resolved.

    Works in any dimension ``D`` (``2 * D`` columns).

    Parameters
    ----------
    gamma : float, default=1.0
        RBF kernel coefficient, in 1/m^2: ``gamma = 1 / (2 * l^2)`` for a length scale ``l``.
        1.0 (``l`` = 0.71 m) is the default of the reference implementation's CARMEN example.
        The landmarks must reach the whole map, which favours long length scales: the AUC on
        ACES was 0.867, 0.911, 0.937 and 0.951 at ``gamma`` 5, 2, 1 and 0.5, and at 2000
        components 0.919, 0.947 and 0.954 at 2, 1 and 0.5. 0.5 marked 0.40 % of the office's
        far free cells occupied (ECE 0.071), against 0.03-0.17 % (ECE 0.013-0.064) for 1.0
        over five seeds.
    n_components : int, default=1000
        Nystroem landmarks (features), as in the paper; at most the number of training points
        are used. On ACES the AUC was 0.891, 0.937 and 0.947 at 500, 1000 and 2000
        components, for fit times of 2.6, 5.8 and 16.0 s.
    alpha : float, default=1e-6
        Regularisation strength of the SGD classifier. The paper's code uses 1e-4, which
        underfits: on ACES the AUC was 0.907 at 1e-4, 0.926 at 1e-5, 0.937 at 1e-6 and 0.940
        at 1e-7, the last after 88 epochs instead of 35; at 1e-4 the office map found 2 % of
        its walls.
    penalty : {"l2", "l1", "elasticnet"} or None, default="l2"
        Regularisation of the SGD classifier. The paper's code uses ``"elasticnet"``; on ACES it
        gave an AUC of 0.941 against 0.937 for ``"l2"`` (0.938 for ``"l1"``, 0.939 for
        ``None``) at 1.5 times the fit time.
    l1_ratio : float, default=0.15
        Elastic-net mixing (``penalty="elasticnet"`` only); 0.15 as in the paper's code.
    free_spacing : float, default=0.5
        Largest spacing in metres of the points sampled along free rows: under the kernel's
        length scale, so that no stretch of a beam goes unconstrained. The paper's code draws
        one random point per 2 m of beam; at 0.5, 1 and 2 m the AUC on ACES was 0.937, 0.926
        and 0.901, and the office map marked 0.03, 0.30 and 2.82 % of its far free cells
        occupied.
    max_free_length : float or None, default=40.0
        Free rows longer than this (in metres) give no training points; ``None`` uses them
        all. The paper's code and its evaluation protocol skip readings beyond 40 m. Beams
        without a return run to the sensor's maximum range, far outside the mapped area, and
        take a share of the landmarks and of ``max_samples`` there: in ACES' training rows,
        the free rows over 40 m (1.0 % of them, 49 m long on average) would hold 11.4 % of
        the free points. On ACES the AUC was 0.937 at 40 m against 0.919 with every row.
    max_samples : int or None, default=50_000
        Training points kept (hits and free points together); ``None`` keeps all. 50 000
        points at 1000 components store 200 MB of float32 features and fitted in 5.8 s on
        ACES (one BLAS thread). ACES' 10th scans give 62 266 points: keeping them all gave an
        AUC of 0.920 against 0.937 (6.4 s), and 25 000 gave 0.891.
    class_weight : dict, "balanced" or None, default=None
        Passed to the SGD classifier; dictionary keys are class labels of ``y``. ``None``:
        no reweighting, as in the paper's Nystroem code (see above). ``"balanced"`` gave the
        same AUC on ACES (0.938 against 0.937) after 64 epochs instead of 35, and on the
        office found 99.7 % of the walls, drawn 0.3 m thick instead of 0.2 m, with an ECE of
        0.090 against 0.016.
    max_iter : int, default=100
        Passes (epochs) over the training points at most. With the defaults the classifier
        stopped after 28-35 epochs on ACES and 55-63 on the office (five seeds); at
        ``alpha=1e-7`` the office reached 100. Reaching ``max_iter`` raises a
        :class:`~sklearn.exceptions.ConvergenceWarning`.
    tol : float or None, default=1e-3
        Stopping criterion of the SGD classifier (scikit-learn's default).
    layout : {"auto", "segments", "points"}, default="auto"
        How rows of ``X`` are read; see :class:`OccupancyGridMap`.
    random_state : int, RandomState instance or None, default=None
        Seeds the sampling of the training points, the landmarks and the SGD passes.

    Attributes
    ----------
    classes_ : ndarray of shape (2,)
        Class labels; ``classes_[1]`` is the occupied class.
    nystroem_ : sklearn.kernel_approximation.Nystroem
        The fitted feature map, of coordinates relative to ``center_``; its
        ``components_`` are the landmarks.
    center_ : ndarray of shape (n_dims,)
        Centre of ``extent_``, subtracted from every point before the features.
    classifier_ : sklearn.linear_model.SGDClassifier
        The logistic regression on the features, fitted on labels 0 (free) and 1 (occupied).
    n_training_points_ : int
        Training points used (at most ``max_samples``).
    n_iter_ : int
        Epochs the SGD classifier ran.
    extent_ : ndarray of shape (2 * n_dims,)
        ``[min_1, max_1, ..., min_D, max_D]`` of the rows seen in fit, for
        :class:`skoccmap.OccupancyGrid`.
    n_features_in_ : int
        Number of columns seen in fit (``2 * n_dims``).

    See Also
    --------
    FrequencyGridMap : The counting grid the Hilbert-map papers compare against.

    References
    ----------
    F. Ramos and L. Ott, "Hilbert maps: scalable continuous occupancy mapping with stochastic
    gradient descent", Robotics: Science and Systems, 2015.

    Examples
    --------
    Beams from the origin to a wall at x = 2:

    >>> import numpy as np
    >>> from skoccmap.baselines import HilbertMap
    >>> y_wall = np.linspace(-1.0, 1.0, 21)
    >>> hits = np.column_stack([np.full(21, 2.0), y_wall])
    >>> beams = np.hstack([np.zeros((21, 2)), hits - [0.05, 0.0]])
    >>> X = np.vstack([beams, np.hstack([hits, hits])])
    >>> y = np.r_[np.zeros(21), np.ones(21)]
    >>> hm = HilbertMap(n_components=100, random_state=0).fit(X, y)
    >>> queries = np.array([[2.0, 0.0, 2.0, 0.0], [0.8, 0.0, 0.8, 0.0]])
    >>> hm.predict(queries)
    array([1., 0.])
    """

    _parameter_constraints: dict = {
        "gamma": [Interval(Real, 0, None, closed="neither")],
        "n_components": [Interval(Integral, 1, None, closed="left")],
        "alpha": [Interval(Real, 0, None, closed="left")],
        "penalty": [StrOptions({"l2", "l1", "elasticnet"}), None],
        "l1_ratio": [Interval(Real, 0, 1, closed="both")],
        "free_spacing": [Interval(Real, 0, None, closed="neither")],
        "max_free_length": [Interval(Real, 0, None, closed="left"), None],
        "max_samples": [Interval(Integral, 2, None, closed="left"), None],
        "class_weight": [StrOptions({"balanced"}), dict, None],
        "max_iter": [Interval(Integral, 1, None, closed="left")],
        "tol": [Interval(Real, None, None, closed="neither"), None],
        "layout": [StrOptions({"auto", "segments", "points"})],
        "random_state": ["random_state"],
    }

    def __init__(
        self,
        gamma=1.0,
        *,
        n_components=1000,
        alpha=1e-6,
        penalty="l2",
        l1_ratio=0.15,
        free_spacing=0.5,
        max_free_length=40.0,
        max_samples=50_000,
        class_weight=None,
        max_iter=100,
        tol=1e-3,
        layout="auto",
        random_state=None,
    ):
        self.gamma = gamma
        self.n_components = n_components
        self.alpha = alpha
        self.penalty = penalty
        self.l1_ratio = l1_ratio
        self.free_spacing = free_spacing
        self.max_free_length = max_free_length
        self.max_samples = max_samples
        self.class_weight = class_weight
        self.max_iter = max_iter
        self.tol = tol
        self.layout = layout
        self.random_state = random_state

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.classifier_tags.multi_class = False
        # Columns are coordinates of segment end points and the kernel's length scale is in
        # metres; on generic features (the checks' blobs) the score need not be good.
        tags.classifier_tags.poor_score = True
        return tags

    @fit_or_unfitted
    def fit(self, X, y):
        """Sample training points from the rows and fit the features and the classifier.

        Parameters
        ----------
        X : array-like of shape (n_samples, 2 * n_dims)
            Segment rows ``[start, end]``; hits are zero-length segments.
        y : array-like of shape (n_samples,)
            Two classes; the larger label (``classes_[1]``) marks hits.

        Returns
        -------
        self : HilbertMap
            The fitted map.
        """
        self._validate_params()
        with non_finite_explained("observations"):
            X_in, (X, y) = X, validate_data(self, X, y, dtype=np.float64)
        warn_if_coarse_float32(X_in, X)
        self.classes_, y_idx = _binary_classes(y, type(self).__name__)
        class_weight = self._class_weight()
        # Beyond 1e100 the features' squared distances overflow: the landmarks' SVD stopped
        # on "SVD did not converge".
        starts, ends = _split_rows(check_magnitude(X), self.layout)
        warn_unless_metres(starts, ends)
        self.extent_ = np.column_stack(_bounding_box(starts, ends)).ravel()
        # Features are computed relative to the data's centre: scikit-learn's RBF kernel
        # takes |x|^2 + |y|^2 - 2 x.y, which at map coordinates of 1e5-1e7 m (UTM) loses
        # the distances between nearby points.
        self.center_ = 0.5 * (self.extent_[0::2] + self.extent_[1::2])
        rng = check_random_state(self.random_state)
        points, labels = self._training_points(starts, ends, y_idx == 1, rng)
        points -= self.center_
        self.n_training_points_ = labels.size

        self.nystroem_ = Nystroem(
            kernel="rbf",
            gamma=self.gamma,
            n_components=min(self.n_components, labels.size),
            random_state=rng.randint(np.iinfo(np.int32).max),
        ).fit(points)
        # float32 features halve the memory; the classifier fits in float32 (same AUC).
        features = np.empty((labels.size, self.nystroem_.n_components), dtype=np.float32)
        for lo in range(0, labels.size, _FEATURE_BATCH):
            features[lo : lo + _FEATURE_BATCH] = self.nystroem_.transform(
                points[lo : lo + _FEATURE_BATCH]
            )
        self.classifier_ = SGDClassifier(
            loss="log_loss",
            penalty=self.penalty,
            alpha=self.alpha,
            l1_ratio=self.l1_ratio,
            max_iter=self.max_iter,
            tol=self.tol,
            class_weight=class_weight,
            random_state=rng.randint(np.iinfo(np.int32).max),
        ).fit(features, labels)
        self.n_iter_ = int(self.classifier_.n_iter_)
        return self

    def _class_weight(self):
        """``class_weight`` with the labels of ``y`` replaced by 0 (free) and 1 (occupied)."""
        if not isinstance(self.class_weight, dict):
            return self.class_weight
        weights = {}
        for label, weight in self.class_weight.items():
            matches = np.flatnonzero(self.classes_ == label)
            if matches.size == 0:
                raise ValueError(
                    f"class_weight has a weight for class {label!r}, which is not in y "
                    f"(classes {self.classes_.tolist()})."
                )
            if not (isinstance(weight, Real) and np.isfinite(weight) and weight >= 0):
                raise ValueError(
                    f"class_weight must give each class a finite weight >= 0, got "
                    f"{weight!r} for class {label!r}."
                )
            weights[int(matches[0])] = weight
        return weights

    def _training_points(self, starts, ends, hit, rng):
        """Hit end points and points along the free rows, at most ``max_samples`` of them."""
        hits = ends[hit]
        free = ~hit
        length = np.linalg.norm(ends - starts, axis=1)
        if self.max_free_length is not None:
            free &= length <= self.max_free_length
            if not free.any():
                raise ValueError(
                    f"every free row is longer than max_free_length={self.max_free_length}: "
                    "no free training points. Raise max_free_length or pass None."
                )
        free_starts, free_ends = starts[free], ends[free]
        counts = _free_points_per_row(length[free], float(self.free_spacing))
        n_hit, n_free = hits.shape[0], int(counts.sum())
        take_hit, take_free = n_hit, n_free
        if self.max_samples is not None and n_hit + n_free > self.max_samples:
            # Per class in proportion, at least one of each (then take_free <= n_free too).
            take_hit = int(round(self.max_samples * n_hit / (n_hit + n_free)))
            take_hit = min(max(take_hit, 1), n_hit, self.max_samples - 1)
            take_free = self.max_samples - take_hit
        n_points = take_hit + take_free
        # float32 features, and the points (2-D float64), labels and sample index.
        n_bytes = n_points * (4.0 * min(self.n_components, n_points) + 32.0)
        if n_bytes > _MAX_TRAINING_BYTES:
            raise ValueError(
                f"HilbertMap would train on {n_points:.3g} points, whose features take "
                f"{n_bytes / 2**30:.3g} GiB: set max_samples (default 50 000) or a "
                f"larger free_spacing (now {self.free_spacing})."
            )
        if take_hit < n_hit:
            hits = hits[np.sort(sample_without_replacement(n_hit, take_hit, random_state=rng))]
        if take_free < n_free:
            index = np.sort(sample_without_replacement(n_free, take_free, random_state=rng))
        else:
            index = np.arange(n_free)
        free_points = _points_along(free_starts, free_ends, counts, index)
        labels = np.r_[np.ones(len(hits), np.int64), np.zeros(len(free_points), np.int64)]
        return np.vstack([hits, free_points]), labels

    def _batches(self, X):
        """Features of the query rows' midpoints, in batches (validated before the first)."""
        check_is_fitted(self)
        X = validate_queries(self, X)
        starts, ends = _split_rows(X, self.layout)
        mid = 0.5 * (starts + ends) - self.center_
        return (
            self.nystroem_.transform(mid[lo : lo + _FEATURE_BATCH])
            for lo in range(0, mid.shape[0], _FEATURE_BATCH)
        )

    def decision_function(self, X):
        """Log-odds of occupancy at the query segments' midpoints.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * n_dims)
            Query segment rows; points are zero-length segments.

        Returns
        -------
        log_odds : ndarray of shape (n_queries,)
            Positive where ``classes_[1]`` (occupied) is more probable.
        """
        parts = [self.classifier_.decision_function(f) for f in self._batches(X)]
        return np.concatenate(parts).astype(np.float64) if parts else np.zeros(0)

    def predict_proba(self, X):
        """Occupancy probability at the query segments' midpoints.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * n_dims)
            Query segment rows; points are zero-length segments.

        Returns
        -------
        proba : ndarray of shape (n_queries, 2)
            Column 1 is P(occupied), the SGD classifier's ``predict_proba``.
        """
        parts = [self.classifier_.predict_proba(f) for f in self._batches(X)]
        return np.vstack(parts).astype(np.float64) if parts else np.zeros((0, 2))

    def predict(self, X):
        """Most probable class at the query segments' midpoints.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * n_dims)
            Query segment rows.

        Returns
        -------
        y : ndarray of shape (n_queries,)
            ``classes_[1]`` where the log-odds are positive, else ``classes_[0]``.
        """
        occupied = self.decision_function(X) > 0
        return self.classes_[occupied.astype(int)]
