"""Hits that the free beams contradict: transient obstacles.

A person walking down a corridor is hit by a few beams of a few scans, and the same spot
is crossed by dozens of beams before and after. A GP classifier whose probit is nearly a
step (signal variance 1e3) takes every label as a constraint it must meet, so the few
hits draw a dark blob a length scale wide however many beams crossed the spot, where a
counting grid, which weighs the hits against the passes, draws free space. Counting the
hits in and the free beams through every cell, as the frequency grid does, finds those
hits: a hit whose cell counts ``hits / (hits + passes)`` below a bound is left out of
the experts' training rows (its beam stays free evidence). A passer-by leaves a few hits
in a cell; a wall seen from many poses collects more, however many beams of poses that do
not quite align with it cross its cells, so a cell hit more than a few times keeps its hits.

The counts live on an unbounded grid of absolute cell coordinates, so that the counts of
online updates add up to the counts of all rows seen.
"""

import math

import numpy as np

from .baselines import _bounding_box, _chunks_by_crossings, _passed_cells

__all__ = ["CellCounts"]

# Free rows traversed at once: their passed cells (tens per row) stay within tens of MB; at
# 100 000 rows, counting the 3M rows of B2's largest fit took 0.7 GiB.
_CHUNK = 16_384
# Most cells counted: 0.34 km^2 of 0.1 m cells in 2-D, a few GB while merging. Beams far
# longer than any laser's (ranges in millimetres) would otherwise fill the memory.
_MAX_COUNTED_CELLS = 1 << 25


def _occurrences(flat, shape):
    """The cells (coordinates in ``shape``) among the flat indices ``flat``, and how often
    each occurs: a dense count where the grid is not much larger than the indices."""
    size = math.prod(shape)
    if size <= 4 * flat.size:
        count = np.bincount(flat, minlength=size)
        cells = np.flatnonzero(count)
        count = count[cells]
    else:
        cells, count = np.unique(flat, return_counts=True)
    return np.column_stack(np.unravel_index(cells, shape)), count.astype(np.int64)


def _frequency(hits, passes):
    """``hits / (hits + passes)``, 1 where nothing was counted."""
    seen = hits + passes
    return np.where(seen > 0, hits / np.maximum(seen, 1), 1.0)


def _merged(parts):
    """Sorted unique keys of ``(keys, hits, passes)`` parts, with their counts summed."""
    keys = np.concatenate([p[0] for p in parts])
    merged, inverse = np.unique(keys, return_inverse=True)
    inverse = inverse.ravel()
    sums = []
    for column in (1, 2):
        total = np.zeros(merged.size, dtype=np.int64)
        np.add.at(total, inverse, np.concatenate([p[column] for p in parts]))
        sums.append(total)
    return merged, sums[0], sums[1]


class CellCounts:
    """Hits in and free rows through the cells of side ``cell_size``, summed over updates.

    Cells are counted as :class:`skoccmap.baselines.FrequencyGridMap` counts them: a hit in
    the cell holding it, a free row in every cell it crosses except its end cell (a row
    inside one cell passes that cell).

    Parameters
    ----------
    cell_size : float
        Cell edge (metres).
    n_dims : int
        Spatial dimension D.
    """

    def __init__(self, cell_size, n_dims):
        self.cell_size = float(cell_size)
        self.n_dims = int(n_dims)
        self._bits = 62 // self.n_dims
        # Cell of the first point counted: keys hold coordinates relative to it, so that
        # their bits span the map, wherever it lies (UTM eastings in 3-D included).
        self.origin = None
        self.keys = np.empty(0, dtype=np.int64)
        self.hits = np.empty(0, dtype=np.int64)
        self.passes = np.empty(0, dtype=np.int64)

    def __setstate__(self, state):
        # Counts pickled before the origin cell existed keyed absolute cells.
        state.setdefault("origin", np.zeros(state["n_dims"]) if state["keys"].size else None)
        self.__dict__.update(state)

    def _cells(self, points):
        """Cells holding ``points``, relative to the origin cell."""
        cells = np.floor(points / self.cell_size) - self.origin
        # Checked in floating point: far enough out, the cast to int64 wraps around.
        half = 1 << (self._bits - 1)
        if cells.size and np.abs(cells).max() >= half:
            raise ValueError(
                f"Coordinates more than {half * self.cell_size:g} m from the first data "
                f"counted (near {(self.origin * self.cell_size).tolist()}) cannot be counted "
                "in cells: are they in the coordinate frame of the first data? Keep the data "
                "within that distance, or pass min_hit_frequency=None."
            )
        return cells.astype(np.int64)

    def _keys(self, cells):
        """One int64 per cell: the offset coordinates side by side, ``62 // D`` bits each."""
        keys = np.zeros(cells.shape[0], dtype=np.int64)
        for column in (cells + (1 << (self._bits - 1))).T:
            keys = (keys << self._bits) | column
        return keys

    def add(self, X, occupied):
        """Count the rows of ``X`` (segment rows; ``occupied`` marks the hits); free rows
        pass the cells :func:`skoccmap.baselines._passed_cells` says.

        The free rows are taken ``_CHUNK`` at a time (fewer where they are long), each
        chunk's passes reduced to one count per cell before the next: memory follows the
        map's cells, not the cells all beams cross. The count arrays are replaced, never
        written into: a shallow copy of these counts keeps its own.
        """
        d = self.n_dims
        starts, ends = X[:, :d], X[:, d:]
        if len(X) == 0:
            return self
        if self.origin is None:
            self.origin = np.floor(starts[0] / self.cell_size)
        # The range check first, on the extreme coordinates (cells grow with them), so that
        # a row too far out is refused before anything is counted, without holding the
        # cells of every row.
        self._cells(np.vstack([starts.min(axis=0), starts.max(axis=0), ends.min(axis=0),
                               ends.max(axis=0)]))  # fmt: skip
        keys, hits = np.unique(self._keys(self._cells(ends[occupied])), return_counts=True)
        parts = [(self.keys, self.hits, self.passes), (keys, hits, np.zeros_like(hits))]
        free = np.flatnonzero(~occupied)
        first_cells, last_cells = self._cells(starts[free]), self._cells(ends[free])
        for lo, hi in _chunks_by_crossings(first_cells, last_cells, _CHUNK):
            rows, first, last = free[lo:hi], first_cells[lo:hi], last_cells[lo:hi]
            low, high = _bounding_box(first, last)
            shape = tuple(int(n) for n in high - low + 1)
            # Grid units from the absolute cell coordinates, so that every batch rounds a
            # point to the same cell.
            low_corner = low + self.origin
            _, flat = _passed_cells(
                starts[rows] / self.cell_size - low_corner,
                ends[rows] / self.cell_size - low_corner,
                shape,
            )
            cells, passes = _occurrences(flat, shape)
            parts.append((self._keys(cells + low), np.zeros_like(passes), passes))
            if sum(part[0].size for part in parts) > _MAX_COUNTED_CELLS:
                parts = [_merged(parts)]
                self._check_size(parts[0][0].size)
        self.keys, self.hits, self.passes = _merged(parts)
        return self

    def _check_size(self, n_cells):
        if n_cells > _MAX_COUNTED_CELLS:
            raise ValueError(
                f"The free beams pass more than {_MAX_COUNTED_CELLS:,} cells of "
                f"{self.cell_size:g} m, too many to count hits against passes: are the ranges "
                "in metres? For a map this large, pass min_hit_frequency=None."
            )

    def counted(self, points):
        """Hits in and free rows through the cells holding ``points`` (0 where uncounted)."""
        hits = np.zeros(len(points), dtype=np.int64)
        passes = np.zeros(len(points), dtype=np.int64)
        if self.keys.size == 0:
            return hits, passes
        keys = self._keys(self._cells(points))
        pos = np.searchsorted(self.keys, keys).clip(0, self.keys.size - 1)
        found = self.keys[pos] == keys
        hits[found], passes[found] = self.hits[pos[found]], self.passes[pos[found]]
        return hits, passes

    def frequency(self, points):
        """``hits / (hits + passes)`` of the cells holding ``points`` (1 where uncounted)."""
        return _frequency(*self.counted(points))

    def transient(self, points, bound, max_hits):
        """Whether the cell holding each point counts ``hits / (hits + passes)`` below
        ``bound`` and at most ``max_hits`` hits: few hits, contradicted by many passes."""
        hits, passes = self.counted(points)
        return (_frequency(hits, passes) < bound) & (hits <= max_hits)
