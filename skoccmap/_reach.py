"""Which experts can inform a query: the reach of a kernel and a spatial index of experts.

An expert whose training segments all lie far from a query predicts its prior there: under
the product rules (PoE, BCM, rBCM) it adds nothing, and under the mixture of experts only
dilutes its neighbours with p = 1/2. :class:`ExpertReach` indexes the training segments of
every expert so that a query is sent to the experts with data within a *reach* of it, and
:func:`kernel_reach` derives that reach from the kernel and a tolerance.
"""

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["ExpertReach", "kernel_reach"]

# Distances (in units of the data's extent) at which the kernel is probed for its reach.
_PROBE = np.geomspace(1e-6, 10.0, 600)
# Index cells and query blocks, as fractions of the reach: the finer they are, the closer
# the consulted set comes to "data within reach" (see ExpertReach.slack) and the more
# entries the index holds.
_CELL = 1.0 / 8.0
_BLOCK = 1.0 / 4.0
# The block table's stencils grow as 5**D: beyond 3-D (not a map) every expert is a
# candidate everywhere.
_MAX_DIM = 3
# Sample points, or (cell, block) pairs, handled at once while the index is built.
_BATCH = 1 << 21


def kernel_reach(kernel, dim, tolerance, extent):
    """Distance beyond which the kernel between two points stays below ``tolerance`` of k(0).

    The kernel is evaluated between a point at the origin and points at growing distances
    along each axis (zero-length segment rows, as the mixture's kernels take them). For the
    integral kernel and the other averages of a decaying point kernel, the value between a
    query and a segment is at most the point kernel at their distance, so every entry of a
    kernel row against data further than the reach is below ``tolerance * k(x, x)``.

    Parameters
    ----------
    kernel : Kernel
        Fitted kernel over segment rows of dimension ``dim``.
    dim : int
        Spatial dimension D (rows have 2 D columns).
    tolerance : float
        Relative kernel value, in (0, 1).
    extent : float
        Size of the data (e.g. the diagonal of its bounding box); the kernel is probed up
        to ten times it.

    Returns
    -------
    reach : float
        The distance, or ``inf`` when the kernel does not fall below the tolerance within
        ten times the extent (a kernel that does not decay, such as a dot product).
    """
    r = max(float(extent), 1e-12) * _PROBE
    origin = np.zeros((1, 2 * dim))
    k0 = float(np.ravel(kernel(origin))[0])
    if not np.isfinite(k0) or k0 <= 0.0:
        return np.inf
    reach = 0.0
    for axis in range(dim):
        rows = np.zeros((r.size, 2 * dim))
        rows[:, axis] = rows[:, dim + axis] = r
        k = np.ravel(kernel(origin, rows))
        above = np.flatnonzero(np.abs(k) >= tolerance * k0)
        if above.size and above[-1] == r.size - 1:
            return np.inf
        # The first probe beyond the last one above the tolerance.
        reach = max(reach, r[above[-1] + 1] if above.size else r[0])
    return float(reach)


def _segment_samples(segments, spacing):
    """Points along each segment no further than ``spacing / 2`` from any of its points."""
    dim = segments.shape[1] // 2
    start, delta = segments[:, :dim], segments[:, dim:] - segments[:, :dim]
    length = np.sqrt(np.einsum("ij,ij->i", delta, delta))
    count = np.ceil(length / spacing).astype(np.intp) + 1
    row = np.repeat(np.arange(len(segments)), count)
    first = np.cumsum(count) - count
    t = (np.arange(row.size) - first[row]) / np.maximum(count[row] - 1, 1)
    return start[row] + t[:, None] * delta[row], row


class ExpertReach:
    """Spatial index of the experts' training segments.

    Points are sampled along every training segment and reduced to one entry per
    (expert, cell) of a grid of side ``reach / 8``. From these cells ``fit`` tabulates,
    for every block (a cell of side ``reach / 4``) near the data, the experts with a
    cell within ``reach`` of the block (by the distance between the cell, grown by its
    half-diagonal and half the sample spacing, and the block's box), so that the
    candidates of a point query are a table look-up. Every expert with data within
    ``reach`` of a query is a candidate for it; experts up to ``reach + slack`` away may
    be too (``slack``, the block's diagonal plus the cell's diagonal and sample spacing, is
    about half the reach in 2-D). Candidates depend only on the query and the index, not on
    which other queries are asked with it. Query segments of non-zero length are answered
    by a KD-tree over the cells, within their half-length more.

    Parameters
    ----------
    segments : ndarray of shape (n_rows, 2 * D)
        The training segment rows of all experts.
    expert : ndarray of shape (n_rows,)
        Expert index of each row.
    n_experts : int
        Number of experts.
    reach : float
        Distance beyond which an expert cannot inform a query (``inf``: every expert is a
        candidate everywhere, as for data of more than 3 dimensions).
    """

    def __init__(self, segments, expert, n_experts, reach):
        self.dim = dim = segments.shape[1] // 2
        self.n_experts = int(n_experts)
        self.reach = float(reach)
        self.max_candidates = self.n_experts
        if not np.isfinite(self.reach) or len(segments) == 0 or dim > _MAX_DIM:
            self.reach = np.inf
            return
        self.cell = _CELL * self.reach
        self.block = _BLOCK * self.reach
        grown = 0.5 * self.cell * (np.sqrt(dim) + 1.0)
        self.slack = self.block * np.sqrt(dim) + 2.0 * grown
        self.origin = np.minimum(segments[:, :dim].min(axis=0), segments[:, dim:].min(axis=0))
        self.cell_expert, cells = self._cells(segments, np.asarray(expert))
        centres = self.origin + (cells + 0.5) * self.cell
        self.tree = cKDTree(centres)
        self._grown = grown
        # Keys are sorted by expert: each expert's cells are a contiguous run.
        bounds = np.searchsorted(self.cell_expert, np.arange(self.n_experts + 1))
        self._expert_trees = [
            cKDTree(centres[lo:hi]) if hi > lo else None
            for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)
        ]
        self._tabulate(centres, self.reach + grown)

    def _cells(self, segments, expert):
        """Unique (expert, cell) of the points sampled along the segments, by expert.

        Experts are taken in batches of about ``_BATCH`` sample points, so that the samples
        of millions of segments never exist at once.
        """
        order = np.argsort(expert, kind="stable")
        bounds = np.searchsorted(expert[order], np.arange(self.n_experts + 1))
        dim = self.dim
        delta = segments[:, dim:] - segments[:, :dim]
        count = np.ceil(np.sqrt(np.einsum("ij,ij->i", delta, delta)) / self.cell) + 1
        per_expert = np.cumsum(np.bincount(expert, weights=count, minlength=self.n_experts))
        ends = np.searchsorted(per_expert, np.arange(_BATCH, per_expert[-1], _BATCH)) + 1
        ends = np.unique(np.r_[np.minimum(ends, self.n_experts), self.n_experts])
        experts_out, cells_out = [], []
        for first, last in zip(np.r_[0, ends[:-1]], ends, strict=True):
            rows = order[bounds[first] : bounds[last]]
            if rows.size == 0:
                continue
            points, row = _segment_samples(segments[rows], self.cell)
            cells = np.floor((points - self.origin) / self.cell).astype(np.int64)
            keys = np.unique(np.column_stack([expert[rows][row], cells]), axis=0)
            experts_out.append(keys[:, 0])
            cells_out.append(keys[:, 1:])
        # Batches hold disjoint experts in increasing order: the result is sorted by expert.
        return np.concatenate(experts_out).astype(np.intp), np.concatenate(cells_out)

    def _tabulate(self, centres, radius):
        """CSR table block code -> candidate experts, from the cells grown by ``radius``."""
        dim, block = self.dim, self.block
        lo = np.floor((centres.min(axis=0) - radius - self.origin) / block).astype(np.int64)
        hi = np.floor((centres.max(axis=0) + radius - self.origin) / block).astype(np.int64)
        self._block_lo, self._block_shape = lo, hi - lo + 1
        self._block_stride = np.r_[np.cumprod(self._block_shape[::-1])[::-1][1:], 1]
        # Blocks whose box lies within radius of a cell centre: offsets from the cell's
        # block, by the cell's position inside it (two per axis: cells are half blocks).
        span = int(np.ceil(radius / block)) + 1
        grid = np.stack(
            np.meshgrid(*[np.arange(-span, span + 1)] * dim, indexing="ij"), axis=-1
        ).reshape(-1, dim)
        # np.ndindex runs through the positions in the order of sub_code below.
        stencils = []
        for sub in np.ndindex(*(2,) * dim):
            centre = (np.asarray(sub) + 0.5) * 0.5  # in block units, within its block
            gap = np.maximum(np.maximum(grid - centre, centre - grid - 1.0), 0.0)
            stencils.append(grid[np.einsum("ij,ij->i", gap, gap) <= (radius / block) ** 2])
        rel = (centres - self.origin) / block
        cell_block = np.floor(rel).astype(np.int64)
        sub = np.minimum((2.0 * (rel - cell_block)).astype(np.int64), 1)
        sub_code = sub @ (1 << np.arange(dim)[::-1])
        # Cells are sorted by expert; batches of whole experts give disjoint pair sets, each
        # made unique within its batch, so that no more than a batch of pairs is ever held.
        bounds = np.searchsorted(self.cell_expert, np.arange(self.n_experts + 1))
        step = max(1, _BATCH // max(len(s) for s in stencils))
        cut = np.searchsorted(bounds, np.arange(step, len(centres), step))
        pairs = []
        for first, last in zip(np.r_[0, cut], np.r_[cut, self.n_experts], strict=True):
            part = np.arange(bounds[first], bounds[last])
            if part.size == 0:
                continue
            found = []
            for code, stencil in enumerate(stencils):
                mine = part[sub_code[part] == code]
                blocks = cell_block[mine, None, :] + stencil[None]
                found.append(
                    ((blocks - lo) @ self._block_stride) * self.n_experts
                    + self.cell_expert[mine, None]
                )
            pairs.append(np.unique(np.concatenate([f.ravel() for f in found])))
        # Unique (block, expert) pairs, sorted by block then expert.
        pair = np.sort(np.concatenate(pairs))
        block_code, self._table_experts = np.divmod(pair, self.n_experts)
        self._table_codes, first = np.unique(block_code, return_index=True)
        self._table_start = np.r_[first, pair.size]
        counts = np.diff(self._table_start)
        self.max_candidates = int(counts.max()) if counts.size else 1

    def within_reach(self, queries, query_index, expert_index):
        """Whether each (query, expert) pair has data of the expert within reach.

        Exact up to the cells' size: a pair is kept when a cell of the expert lies within
        ``reach`` plus the cell's half-diagonal and half the sample spacing of the query
        (plus half the query segment's length, measured from its midpoint).
        """
        keep = np.ones(query_index.size, dtype=bool)
        if not np.isfinite(self.reach) or query_index.size == 0:
            return keep
        dim = self.dim
        mids = 0.5 * (queries[:, :dim] + queries[:, dim:])
        delta = queries[:, dim:] - queries[:, :dim]
        radius = self.reach + self._grown + 0.5 * np.sqrt(np.einsum("ij,ij->i", delta, delta))
        order = np.argsort(expert_index, kind="stable")
        bounds = np.searchsorted(expert_index[order], np.arange(self.n_experts + 1))
        for k in np.flatnonzero(np.diff(bounds)):
            pairs = order[bounds[k] : bounds[k + 1]]
            tree = self._expert_trees[k]
            if tree is None:
                keep[pairs] = False
                continue
            q = query_index[pairs]
            dist = tree.query(mids[q], distance_upper_bound=radius[q].max())[0]
            keep[pairs] = dist <= radius[q]
        return keep

    def _block_codes(self, mids):
        """Table code of the block of each point, -1 outside the table."""
        blocks = np.floor((mids - self.origin) / self.block).astype(np.int64) - self._block_lo
        inside = np.all((blocks >= 0) & (blocks < self._block_shape), axis=1)
        return np.where(inside, blocks @ self._block_stride, -1)

    def spatial_order(self, queries):
        """Order of the queries block by block, so that consecutive queries are near."""
        if not np.isfinite(self.reach):
            return np.arange(len(queries))
        dim = self.dim
        mids = 0.5 * (queries[:, :dim] + queries[:, dim:])
        blocks = np.floor((mids - self.origin) / self.block).astype(np.int64)
        # Rows of blocks a few reaches tall, then blocks along each row: chunks of
        # consecutive queries stay compact.
        band = blocks[:, 1:] // 8
        keys = [blocks[:, 0]] + [band[:, j] for j in range(band.shape[1])][::-1]
        return np.lexsort(keys)

    def candidates(self, queries):
        """Candidate experts of each query, as pairs sorted by query then expert.

        Parameters
        ----------
        queries : ndarray of shape (n_queries, 2 * D)
            Query segment rows (a point is a zero-length segment).

        Returns
        -------
        query_index, expert_index : ndarray of shape (n_pairs,)
            One pair per (query, candidate expert).
        """
        n = len(queries)
        if not np.isfinite(self.reach):
            return (np.repeat(np.arange(n), self.n_experts), np.tile(np.arange(self.n_experts), n))
        dim = self.dim
        mids = 0.5 * (queries[:, :dim] + queries[:, dim:])
        delta = queries[:, dim:] - queries[:, :dim]
        half_length = 0.5 * np.sqrt(np.einsum("ij,ij->i", delta, delta))
        lists = [np.empty(0, np.intp)] * n
        code = self._block_codes(mids)
        pos = np.searchsorted(self._table_codes, code).clip(0, len(self._table_codes) - 1)
        found = (self._table_codes[pos] == code) & (half_length == 0.0)
        start = self._table_start[pos]
        count = np.where(found, self._table_start[pos + 1] - start, 0)
        segment_rows = np.flatnonzero(half_length > 0.0)
        if segment_rows.size:
            # Query segments: the cells within reach of the segment, around its midpoint.
            radius = self.reach + 0.5 * self.cell * (np.sqrt(dim) + 1.0) + half_length
            hits = self.tree.query_ball_point(mids[segment_rows], radius[segment_rows])
            for i, h in zip(segment_rows, hits, strict=True):
                lists[i] = np.unique(self.cell_expert[h]) if len(h) else lists[i]
            count[segment_rows] = [lists[i].size for i in segment_rows]
        query_index = np.repeat(np.arange(n), count)
        first = np.cumsum(count) - count
        offset = np.arange(query_index.size) - np.repeat(first, count)
        expert_index = self._table_experts[np.repeat(start, count) + offset]
        for i in segment_rows:
            expert_index[first[i] : first[i] + count[i]] = lists[i]
        return query_index, expert_index
