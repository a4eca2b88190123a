"""Which experts can inform a query: the reach of a kernel and a spatial index of experts.

An expert whose training segments all lie far from a query predicts its prior there: under
the product rules (PoE, BCM, rBCM) it adds nothing, and under the mixture of experts only
dilutes its neighbours with p = 1/2. :class:`ExpertReach` indexes the training segments of
every expert so that a query is sent to the experts with data within a *reach* of it, and
:func:`kernel_reach` derives that reach from the kernel and a tolerance.
"""

import numpy as np
from scipy.ndimage import binary_dilation
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree
from sklearn.utils.parallel import Parallel, delayed

__all__ = ["ExpertReach", "kernel_reach", "threads_pay"]

# Distances (in units of the data's extent) at which the kernel is probed for its reach.
_PROBE = np.geomspace(1e-6, 10.0, 600)
# Index cells and query blocks, as fractions of the reach: the finer they are, the closer
# the consulted set comes to "data within reach" (see ExpertReach.slack) and the more
# entries the index holds. Cells are half blocks: ExpertReach finds a cell's block and its
# position in it in integers.
_CELL = 1.0 / 8.0
_BLOCK = 1.0 / 4.0
# The block table's stencils grow as 5**D: beyond 3-D (not a map) every expert is a
# candidate everywhere.
_MAX_DIM = 3
# ExpertReach.coverage ignores cells further than this many widths (weight < exp(-4.5)).
_COVERAGE_CUT = 3.0
# ExpertReach.coverage searches all cells at once for up to this many queries, and each
# candidate expert's cells apart for more (see there).
_COVERAGE_ALL_CELLS = 2048
# ExpertReach.covering searches the cells near a batch of queries at once, sized so that
# about this many (query, cell) pairs are found (a hundred per point query on the Intel
# log, thousands where hundreds of experts overlap): tens of MB of temporaries. The first
# batch, of _COVERING_FIRST queries, measures the pairs per query.
_COVERING_PAIRS = 1 << 20
_COVERING_FIRST = 256
# Building the tree of all cells costs about as much as searching the cells of one
# expert apart per this many cells (ad hoc, Intel log with every scan: 0.09 s for 682k
# cells, against 25 us per expert searched apart for a single query).
_CELLS_PER_EXPERT_SEARCH = 200
# Coverage weights are summed in whole units of this: sums of integers are exact in
# float64 (up to 2**21 cells per pair), so a coverage does not depend on the order in
# which its cells are found, and both searches (and every n_jobs) give the same bits.
_COVER_UNIT = 2.0**-32
# Work on (query, expert) pairs goes to threads only from this many pairs, and this many
# per expert on average (see threads_pay).
_THREADED_PAIRS = 2048
_THREADED_PAIRS_PER_EXPERT = 32
# Sample points, or (cell, block) pairs, handled at once while the index is built.
_BATCH = 1 << 21
# The grid of cells is never finer than this many samples per segment on average, nor than
# this fraction of the data's extent: a reach far below the segments' length (a kernel with
# a length scale of micrometres, say) would otherwise sample millions of points per segment
# and list millions of blocks per cell. A coarser grid only adds candidates (within_reach
# still measures the reach), so the index stays exact up to its cells' size.
_MAX_SAMPLES_PER_SEGMENT = 64
_MIN_SCALE_FRACTION = 2.0**-16
# Bits per axis of a block code (3 axes in a non-negative int64): blocks within 2**20
# blocks of the origin (about 2.6e5 reaches) are indexed.
_CODE_BITS = 21
_CODE_OFFSET = 1 << (_CODE_BITS - 1)


def _cell_weights(d, width):
    """Gaussian weights of cells at distances ``d``, in whole units of ``_COVER_UNIT``."""
    return np.rint(np.exp(-0.5 * (np.maximum(d, 0.0) / width) ** 2) / _COVER_UNIT)


def _cells_within(mids, half, cells, cut):
    """``(query, cell, d)`` for every cell of the tree ``cells`` within ``cut`` of a query,
    ``d`` the distance from the query's midpoint ``mids`` less half its length ``half``.

    The queries' tree is used once: sliding-midpoint splits and no shrunk node boxes build
    in half the time of the default's median splits (which dominated the coverage gate),
    for the same pairs.
    """
    tree = cKDTree(mids, balanced_tree=False, compact_nodes=False)
    near = tree.sparse_distance_matrix(cells, cut + half.max(), output_type="ndarray")
    d = near["v"] - half[near["i"]]
    inside = d <= cut
    return near["i"][inside], near["j"][inside], d[inside]


def threads_pay(n_pairs, n_experts):
    """Whether work on ``n_pairs`` (query, expert) pairs of ``n_experts`` experts, one task
    per expert, should run in threads: starting them costs milliseconds, and a task on a
    few queries is mostly numpy's per-call overhead, which holds the GIL (scattered
    queries ran slower in two threads than in one)."""
    return n_pairs >= max(_THREADED_PAIRS, _THREADED_PAIRS_PER_EXPERT * n_experts)


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


def _block_coordinates(points, origin, side):
    """Integer coordinates of the blocks of side ``side`` holding ``points``.

    Clipped before the cast, which would wrap around for points absurdly far from the
    origin (a query at 1e19 m); clipped coordinates lie far outside every code's range.
    """
    blocks = np.floor((points - origin) / side)
    return np.clip(blocks, -(2**62), 2**62).astype(np.int64)


def _codes(blocks):
    """Code of each block (integer coordinates relative to the origin), -1 out of range.

    ``_CODE_BITS`` bits per axis, coordinates offset to be non-negative: codes are
    absolute, so that an expert's blocks keep their codes whatever the other experts'
    extent, and ordered like the blocks' coordinates lexicographically.
    """
    shifted = blocks + _CODE_OFFSET
    inside = np.all((shifted >= 0) & (shifted < 2 * _CODE_OFFSET), axis=1)
    code = np.zeros(len(blocks), dtype=np.int64)
    for d in range(blocks.shape[1]):
        code = (code << _CODE_BITS) | np.where(inside, shifted[:, d], 0)
    return np.where(inside, code, -1)


def _unique_rows(keys):
    """``np.unique(keys, axis=0)`` for integer rows, by one integer code per row (the
    row-wise unique sorts structured records, several times slower)."""
    if len(keys) == 0:
        return keys
    lo = keys.min(axis=0)
    span = keys.max(axis=0) - lo + 1
    if np.sum(np.log2(span.astype(np.float64))) >= 62:
        return np.unique(keys, axis=0)
    code = np.zeros(len(keys), dtype=np.int64)
    for j in range(keys.shape[1]):
        code = code * span[j] + (keys[:, j] - lo[j])
    code = np.unique(code)
    out = np.empty((code.size, keys.shape[1]), dtype=keys.dtype)
    for j in range(keys.shape[1] - 1, -1, -1):
        code, out[:, j] = np.divmod(code, span[j])
        out[:, j] += lo[j]
    return out


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


def _midpoint_rows(segments):
    """Zero-length segment rows at the segments' midpoints."""
    dim = segments.shape[1] // 2
    mids = 0.5 * (segments[:, :dim] + segments[:, dim:])
    return np.hstack([mids, mids])


def _extent(segments):
    """Diagonal of the bounding box of the segment rows' ends."""
    d = segments.shape[1] // 2
    return float(np.linalg.norm(np.ptp(np.vstack([segments[:, :d], segments[:, d:]]), axis=0)))


def _grid_scale(segments, reach):
    """Reach that sizes the index's grid: ``reach``, or a longer one where ``reach`` would
    sample more than ``_MAX_SAMPLES_PER_SEGMENT`` points per segment on average, or cut the
    extent of the data into more than ``1 / _MIN_SCALE_FRACTION`` reaches."""
    dim = segments.shape[1] // 2
    delta = segments[:, dim:] - segments[:, :dim]
    mean_length = float(np.mean(np.sqrt(np.einsum("ij,ij->i", delta, delta))))
    by_samples = mean_length / (_CELL * _MAX_SAMPLES_PER_SEGMENT)
    scale = max(reach, by_samples, _MIN_SCALE_FRACTION * _extent(segments))
    # All data at one point, with a zero reach: any grid will do.
    return scale if scale > 0.0 else 1.0


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
    about half the reach in 2-D). Cells and blocks are proportional to ``scale``, the
    reach unless that would sample more than 64 points per segment on average or cut the
    data's extent into more than 2**16 reaches; then the coarser grid makes ``slack``
    larger than the reach, never misses an expert within it, and keeps the index's size
    bounded. Candidates depend only on the query and the index, not on
    which other queries are asked with it. Query segments of non-zero length are answered
    by a KD-tree over the cells, within their half-length more. The cells of the
    segments' midpoints are kept apart, for :meth:`coverage`.

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
    origin : array-like of shape (D,), default=None
        Corner of the grid of cells; None means the smallest coordinates of the segments.
        :meth:`updated` keeps it, so that the cells of unchanged experts stay valid.
    """

    def __init__(self, segments, expert, n_experts, reach, origin=None):
        self.dim = dim = segments.shape[1] // 2
        self.n_experts = int(n_experts)
        self.reach = float(reach)
        self.max_candidates = self.n_experts
        if not np.isfinite(self.reach) or len(segments) == 0 or dim > _MAX_DIM:
            self.reach = np.inf
            return
        if origin is None:
            origin = np.minimum(segments[:, :dim].min(axis=0), segments[:, dim:].min(axis=0))
        self.origin = np.asarray(origin, dtype=np.float64)
        self.scale = _grid_scale(segments, self.reach)
        self._set_geometry()
        everyone = np.arange(self.n_experts)
        self._cells = self._cells_of(segments, np.asarray(expert), everyone)
        self._centres = self._cells_of(_midpoint_rows(segments), np.asarray(expert), everyone)
        self._blocks = self._blocks_of(self._cells)
        self._expert_trees = [self._tree_of(cells) for cells in self._cells]
        self._centre_trees = [self._tree_of(cells) for cells in self._centres]
        self._assemble()

    def __setstate__(self, state):
        # An index pickled before the midpoint cells existed covers by its cells, as then.
        self.__dict__.update(state)
        if "_centres" not in state and "_cells" in state:
            self._centres, self._centre_trees = self._cells, self._expert_trees
            self.centre_expert, self._centre_tree = self.cell_expert, state.get("_tree")

    def _set_geometry(self):
        """Cell and block sizes, slack and block stencils, all proportional to ``scale``."""
        dim = self.dim
        self.cell = _CELL * self.scale
        self.block = _BLOCK * self.scale
        self._grown = 0.5 * self.cell * (np.sqrt(dim) + 1.0)
        self.slack = self.block * np.sqrt(dim) + 2.0 * self._grown
        # Blocks whose box lies within reach (of a cell grown by its half-diagonal and half
        # the sample spacing) of a cell centre: offsets from the cell's block, by the
        # cell's position inside it (two per axis: cells are half blocks).
        radius = (self.reach + self._grown) / self.block
        span = int(np.ceil(radius)) + 1
        grid = np.stack(
            np.meshgrid(*[np.arange(-span, span + 1)] * dim, indexing="ij"), axis=-1
        ).reshape(-1, dim)
        # np.ndindex runs through the positions in the order of their codes in _blocks_of.
        self._stencils = []
        for sub in np.ndindex(*(2,) * dim):
            centre = (np.asarray(sub) + 0.5) * 0.5  # in block units, within its block
            gap = np.maximum(np.maximum(grid - centre, centre - grid - 1.0), 0.0)
            self._stencils.append(grid[np.einsum("ij,ij->i", gap, gap) <= radius**2])
        # The same offsets as boolean footprints centred on the cell's block.
        self._span = span
        self._footprints = []
        for stencil in self._stencils:
            footprint = np.zeros((2 * span + 1,) * dim, dtype=bool)
            footprint[tuple((stencil + span).T)] = True
            self._footprints.append(footprint)

    def _cells_of(self, segments, expert, which):
        """Unique cells (sorted) of the points sampled along each expert's segments.

        One array of cell coordinates (relative to ``origin``) per expert of ``which``.
        Experts are taken in batches of about ``_BATCH`` sample points, so that the samples
        of millions of segments never exist at once.
        """
        dim = self.dim
        order = np.argsort(expert, kind="stable")
        bounds = np.searchsorted(expert[order], np.arange(self.n_experts + 1))
        delta = segments[:, dim:] - segments[:, :dim]
        count = np.ceil(np.sqrt(np.einsum("ij,ij->i", delta, delta)) / self.cell) + 1
        per_expert = np.bincount(expert, weights=count, minlength=self.n_experts)[which]
        total = np.cumsum(per_expert)
        ends = np.searchsorted(total, np.arange(_BATCH, total[-1] if total.size else 0, _BATCH))
        ends = np.unique(np.r_[np.minimum(ends + 1, which.size), which.size])
        out = []
        for first, last in zip(np.r_[0, ends[:-1]], ends, strict=True):
            batch = which[first:last]
            rows = np.concatenate([order[bounds[k] : bounds[k + 1]] for k in batch] + [[]])
            rows = rows.astype(np.intp)
            local = np.repeat(np.arange(batch.size), bounds[batch + 1] - bounds[batch])
            empty = np.empty((0, dim), dtype=np.int64)
            if rows.size == 0:
                out.extend([empty] * batch.size)
                continue
            points, row = _segment_samples(segments[rows], self.cell)
            cells = np.floor((points - self.origin) / self.cell).astype(np.int64)
            keys = _unique_rows(np.column_stack([local[row], cells]))
            split = np.searchsorted(keys[:, 0], np.arange(batch.size + 1))
            out.extend(keys[lo:hi, 1:] for lo, hi in zip(split[:-1], split[1:], strict=True))
        return out

    def _blocks_of(self, cells_list):
        """Sorted unique codes of the blocks within reach of each expert's cells.

        Per compact expert, a raster of blocks over its cells' bounding box (grown by the
        stencils' span) is dilated by the stencil of each position of a cell in its
        block: the cost is that of the expert's area, not of cells times stencil. An
        expert whose box holds more blocks than its cells' stencils have entries lists
        those entries instead.
        """
        span = self._span
        entries = max(len(s) for s in self._stencils)
        out = []
        for cells in cells_list:
            if len(cells) == 0:
                out.append(np.empty(0, dtype=np.int64))
                continue
            # A cell is half a block: its block and its position in it are exact in
            # integers.
            cell_block, sub = np.divmod(cells, 2)
            sub_code = sub @ (1 << np.arange(self.dim)[::-1])
            lo = cell_block.min(axis=0) - span
            shape = tuple(cell_block.max(axis=0) - lo + span + 1)
            if np.prod(shape, dtype=np.float64) > len(cells) * entries:
                out.append(self._listed_blocks(cell_block, sub_code))
                continue
            covered = np.zeros(shape, dtype=bool)
            for code, footprint in enumerate(self._footprints):
                mine = cell_block[sub_code == code] - lo
                if len(mine) == 0:
                    continue
                seed = np.zeros(shape, dtype=bool)
                seed[tuple(mine.T)] = True
                covered |= binary_dilation(seed, structure=footprint)
            # np.argwhere runs in C order, the order of the codes.
            out.append(_codes(np.argwhere(covered) + lo))
        return out

    def _listed_blocks(self, cell_block, sub_code):
        """Sorted unique codes of every cell's block plus its stencil, about ``_BATCH``
        (cell, block) pairs at a time."""
        codes = []
        for code, stencil in enumerate(self._stencils):
            mine = cell_block[sub_code == code]
            step = max(_BATCH // len(stencil), 1)
            for first in range(0, len(mine), step):
                part = (mine[first : first + step, None, :] + stencil[None]).reshape(-1, self.dim)
                codes.append(np.unique(_codes(part)))
        return np.unique(np.concatenate(codes)) if codes else np.empty(0, dtype=np.int64)

    def _tree_of(self, cells):
        return cKDTree(self.origin + (cells + 0.5) * self.cell) if len(cells) else None

    def _all_cells_tree(self, cells):
        cells = np.concatenate(cells + [np.empty((0, self.dim), dtype=np.int64)])
        return cKDTree(
            self.origin + (cells + 0.5) * self.cell, balanced_tree=False, compact_nodes=False
        )

    @property
    def tree(self):
        """KD-tree over all cells (for query segments), built at its first use: an update
        of a few experts (:meth:`updated`) should not cost a tree over the whole map."""
        if getattr(self, "_tree", None) is None:
            self._tree = self._all_cells_tree(self._cells)
        return self._tree

    @property
    def centre_tree(self):
        """KD-tree over all midpoint cells (for :meth:`coverage`), built at its first use."""
        if getattr(self, "_centre_tree", None) is None:
            self._centre_tree = self._all_cells_tree(self._centres)
        return self._centre_tree

    def _search_all_cells(self, expert_index):
        """Whether :meth:`coverage` should search the tree of all cells for a few queries.

        Once built, that tree is the faster; building it costs as much as searching
        about ``n_cells / _CELLS_PER_EXPERT_SEARCH`` experts' cells apart, which a map
        that changes with every update may never repay. So it is built once the searches
        made apart since the index was made have cost as much: at most twice the time of
        the better choice made in hindsight.
        """
        if getattr(self, "_centre_tree", None) is not None:
            return True
        self._searched = getattr(self, "_searched", 0) + np.unique(expert_index).size
        return self._searched * _CELLS_PER_EXPERT_SEARCH >= self.centre_expert.size

    def _assemble(self):
        """The expert of each cell and the CSR table block code -> candidate experts."""
        self._tree, self._centre_tree, self._searched = None, None, 0
        everyone = np.arange(self.n_experts)
        self.cell_expert = np.repeat(everyone, [len(c) for c in self._cells])
        self.centre_expert = np.repeat(everyone, [len(c) for c in self._centres])
        codes = np.concatenate(self._blocks + [np.empty(0, dtype=np.int64)])
        owners = np.repeat(np.arange(self.n_experts), [len(b) for b in self._blocks])
        # Sorted by block, then expert (the stable sort keeps the experts' order).
        order = np.argsort(codes, kind="stable")
        self._table_experts = owners[order]
        self._table_codes, first = np.unique(codes[order], return_index=True)
        self._table_start = np.r_[first, codes.size]
        counts = np.diff(self._table_start)
        self.max_candidates = int(counts.max()) if counts.size else 1

    def updated(self, segments, expert, n_experts, touched, previous):
        """The index after some experts changed, recomputing only theirs.

        Equal to ``ExpertReach(segments, expert, n_experts, reach, origin=self.origin)``:
        cells are on the grid of this index's origin, and the block table is keyed by
        absolute block coordinates, so an expert's entries do not depend on the others.
        The grid keeps this index's ``scale`` (a rebuild would differ only where the
        reach is too short to set the grid, see the class docstring).

        Parameters
        ----------
        segments, expert, n_experts
            All training segments, their experts and the number of experts, as for the
            constructor.
        touched : array-like of int
            Experts whose segments changed (or that are new).
        previous : ndarray of shape (n_experts,)
            For every other expert, its index in this index.

        Returns
        -------
        index : ExpertReach
            A new index; this one is left as it was.
        """
        if not np.isfinite(self.reach):
            return ExpertReach(segments, expert, n_experts, self.reach)
        new = object.__new__(ExpertReach)
        new.dim, new.reach, new.origin, new.scale = self.dim, self.reach, self.origin, self.scale
        new.n_experts = int(n_experts)
        new._set_geometry()
        touched = np.unique(np.asarray(touched, dtype=np.intp))
        cells = new._cells_of(segments, np.asarray(expert), touched)
        centres = new._cells_of(_midpoint_rows(segments), np.asarray(expert), touched)
        for name in ("_cells", "_centres", "_blocks", "_expert_trees", "_centre_trees"):
            old = getattr(self, name)
            setattr(new, name, [old[j] if j >= 0 else None for j in previous[: new.n_experts]])
        blocks = new._blocks_of(cells)
        for k, c, m, b in zip(touched, cells, centres, blocks, strict=True):
            new._cells[k], new._blocks[k], new._expert_trees[k] = c, b, new._tree_of(c)
            new._centres[k], new._centre_trees[k] = m, new._tree_of(m)
        new._assemble()
        return new

    def within_reach(self, queries, query_index, expert_index):
        """Whether each (query, expert) pair has data of the expert within reach.

        Exact up to the cells' size: a pair is kept when a cell of the expert lies within
        ``reach`` plus the cell's half-diagonal and half the sample spacing of the query
        (plus half the query segment's length, measured from its midpoint).
        """
        keep = np.ones(query_index.size, dtype=bool)
        if not np.isfinite(self.reach) or query_index.size == 0:
            return keep
        mids, half = self._mids_and_half_lengths(queries)
        radius = self.reach + self._grown + half
        for k, pairs in self._pairs_by_expert(expert_index):
            tree = self._expert_trees[k]
            if tree is None:
                keep[pairs] = False
                continue
            q = query_index[pairs]
            dist = tree.query(mids[q], distance_upper_bound=radius[q].max())[0]
            keep[pairs] = dist <= radius[q]
        return keep

    def _mids_and_half_lengths(self, queries):
        dim = self.dim
        delta = queries[:, dim:] - queries[:, :dim]
        mids = 0.5 * (queries[:, :dim] + queries[:, dim:])
        return mids, 0.5 * np.sqrt(np.einsum("ij,ij->i", delta, delta))

    def _pairs_by_expert(self, expert_index):
        """``(expert, pair indices)`` for every expert that has pairs, in expert order."""
        order = np.argsort(expert_index, kind="stable")
        bounds = np.searchsorted(expert_index[order], np.arange(self.n_experts + 1))
        for k in np.flatnonzero(np.diff(bounds)):
            yield k, order[bounds[k] : bounds[k + 1]]

    def coverage(self, queries, query_index, expert_index, width, n_jobs=None):
        """How much of the space near each pair's query the pair's expert has data in.

        The cells (of side ``cell``) of the expert's segments' midpoints near the query,
        each weighted by ``exp(-d**2 / (2 width**2))`` of its centre's distance ``d`` to the
        query (less half the query segment's length, measured from its midpoint), up to
        three widths or the reach less half a cell's diagonal: a kernel density of where the
        expert's training segments lie, smooth in the query. A midpoint's cell need not be a
        cell of its segment's samples (it lies up to a cell's diagonal and half the sample
        spacing from one); at that cut a pair with positive coverage is always within reach
        by :meth:`within_reach`, which prediction relies on. It counts where the data are,
        not how many rows lie there: repeated beams through a cell add nothing, as they add
        little to a GP's posterior. A segment counts at its midpoint, not along its length:
        on a dense log the free pieces (a metre long) of a dozen experts pass through every
        corridor point, and counted along their length each of those experts covered the
        point about as well as the experts whose data lie around it, so the gate kept them
        all. Zero for every pair when the reach is infinite (no cells are indexed).

        Up to ``_COVERAGE_ALL_CELLS`` queries are searched against the tree of all cells
        at once: a query has a hundred or more candidate experts on a dense log, and a
        search per expert cost a single query about 20 ms (the tree is built once the
        searches apart have cost as much, see :meth:`_search_all_cells`). More queries
        are searched against each candidate expert's own cells (a tree of its queries per
        expert, faster per pair for large batches), the experts in ``n_jobs`` threads (the
        k-d tree searches release the GIL). Both find the same cells, and the weights are
        summed exactly (in whole units of ``_COVER_UNIT``, 2**-32), so the coverage is the
        same to the bit whichever search ran, in whatever order, and for any ``n_jobs``.
        """
        cover = np.zeros(query_index.size)
        if not np.isfinite(self.reach) or query_index.size == 0:
            return cover
        mids, half = self._mids_and_half_lengths(queries)
        cut = self._coverage_cut(width)
        if cut < 0.0:
            return cover
        if len(queries) <= _COVERAGE_ALL_CELLS and self._search_all_cells(expert_index):
            return self._coverage_all_cells(mids, half, query_index, expert_index, cut, width)

        def cover_of(k, pairs):
            tree = self._centre_trees[k]
            if tree is None:
                return
            q = query_index[pairs]
            i, _, d = _cells_within(mids[q], half[q], tree, cut)
            cover[pairs] = np.bincount(i, weights=_cell_weights(d, width), minlength=q.size)

        by_expert = list(self._pairs_by_expert(expert_index))
        if threads_pay(query_index.size, len(by_expert)):
            Parallel(n_jobs=n_jobs, require="sharedmem")(
                delayed(cover_of)(k, pairs) for k, pairs in by_expert
            )
        else:
            # Without joblib, whose bookkeeping per task cost more than a small search.
            for k, pairs in by_expert:
                cover_of(k, pairs)
        return cover * _COVER_UNIT

    def prefers_covering(self, n_queries):
        """Whether :meth:`covering` should find the covered pairs of ``n_queries``
        queries rather than :meth:`coverage` over their candidates: for more queries than
        the coverage's search of all cells is made for, or once the tree of all cells is
        built (see :meth:`_search_all_cells`)."""
        return n_queries > _COVERAGE_ALL_CELLS or getattr(self, "_centre_tree", None) is not None

    def _coverage_cut(self, width):
        """Distance beyond which :meth:`coverage` ignores a cell; negative for a grid
        coarser than about 11 reaches (very long segments, see _grid_scale), where no
        cell's data are surely within reach and every candidate weighs the same."""
        return min(self.reach - 0.5 * self.cell * np.sqrt(self.dim), _COVERAGE_CUT * width)

    def covering(self, queries, width):
        """Every (query, expert) pair of positive :meth:`coverage`, and that coverage.

        The pairs :meth:`coverage` gives a positive value among a query's candidates
        (every expert with a cell within its cut is one), found without listing the
        candidates: one search of the tree of all midpoint cells per batch of queries
        (sized to find about ``_COVERING_PAIRS`` cells), the cells summed per pair. A
        query on a dense log has a hundred or more candidates and a score of them cover
        it, so this costs a fraction of :meth:`coverage` over the candidates. The values
        equal :meth:`coverage`'s to the bit (whole units of ``_COVER_UNIT``).

        Parameters
        ----------
        queries : ndarray of shape (n_queries, 2 * D)
            Query segment rows (a point is a zero-length segment).
        width : float
            The coverage's width, as for :meth:`coverage`.

        Returns
        -------
        query_index, expert_index : ndarray of shape (n_pairs,)
            The pairs, sorted by query, then expert.
        cover : ndarray of shape (n_pairs,)
            Their coverage, positive.
        """
        found = [(np.empty(0, np.intp), np.empty(0, np.intp), np.empty(0))]
        if not np.isfinite(self.reach) or len(queries) == 0:
            return found[0]
        cut = self._coverage_cut(width)
        if cut < 0.0:
            return found[0]
        mids, half = self._mids_and_half_lengths(queries)
        start, batch = 0, _COVERING_FIRST
        while start < len(queries):
            rows = slice(start, min(start + batch, len(queries)))
            n_rows = rows.stop - rows.start
            i, cell, d = _cells_within(mids[rows], half[rows], self.centre_tree, cut)
            # Summed per pair as the sparse matrix is built: whole units, exactly in any order.
            pairs = coo_matrix(
                (_cell_weights(d, width), (i, self.centre_expert[cell])),
                shape=(n_rows, self.n_experts),
            ).tocsr()
            pairs.sort_indices()
            query = start + np.repeat(np.arange(n_rows), np.diff(pairs.indptr))
            found.append((query, pairs.indices.astype(np.intp), pairs.data * _COVER_UNIT))
            start = rows.stop
            batch = int(np.clip(_COVERING_PAIRS * n_rows / max(i.size, 1), 1, 1 << 16))
        return tuple(np.concatenate(part) for part in zip(*found, strict=True))

    def _coverage_all_cells(self, mids, half, query_index, expert_index, cut, width):
        """:meth:`coverage` from one search of all cells."""
        asked = np.unique(query_index)
        i, cell, d = _cells_within(mids[asked], half[asked], self.centre_tree, cut)
        query = asked[i]
        # The pair of each (query, expert) found: cells within the cut of a query belong
        # to its candidates, but a pair not asked for is dropped all the same.
        pair_key = query_index.astype(np.int64) * self.n_experts + expert_index
        order = np.argsort(pair_key, kind="stable")
        sorted_key = pair_key[order]
        key = query.astype(np.int64) * self.n_experts + self.centre_expert[cell]
        pos = np.searchsorted(sorted_key, key).clip(max=order.size - 1)
        found = sorted_key[pos] == key
        weight = _cell_weights(d[found], width)
        cover = np.bincount(order[pos[found]], weights=weight, minlength=query_index.size)
        return cover * _COVER_UNIT

    def _block_codes(self, mids):
        """Table code of the block of each point (-1 too far from the origin to code)."""
        return _codes(_block_coordinates(mids, self.origin, self.block))

    def spatial_order(self, queries):
        """Order of the queries block by block, so that consecutive queries are near."""
        if not np.isfinite(self.reach):
            return np.arange(len(queries))
        mids, _ = self._mids_and_half_lengths(queries)
        blocks = _block_coordinates(mids, self.origin, self.block)
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
        mids, half_length = self._mids_and_half_lengths(queries)
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
        # Segment rows take their experts from their own lists below, not from the table
        # (their midpoint's table entry may be past its end).
        start[segment_rows] = 0
        expert_index = self._table_experts[np.repeat(start, count) + offset]
        for i in segment_rows:
            expert_index[first[i] : first[i] + count[i]] = lists[i]
        return query_index, expert_index
