"""Beams of a scan as training rows: which rows are hits, return and no-return beams, the
return beam a no-return beam is most like (the paper's assignment rule), and the pieces
beams are cut into.
"""

import numpy as np
from scipy.spatial import cKDTree
from sklearn.utils import check_random_state, gen_batches
from sklearn.utils.parallel import Parallel, delayed

from .observations import HIT, NO_RETURN, RETURN, split_segments

# No-return beams are compared with at most this many return beams, drawn uniformly per
# block: the exact argmax over all of them costs about 6% of all (no-return, return)
# pairs in quadrature (on dense simulated scans), quadratic in the number of observations.
_NO_RETURN_REFERENCES = 1000


# (no-return, return) pairs bounded at once, and pairs per no-return beam integrated
# first (the rest in rounds of doubling size).
_NO_RETURN_PAIRS = 1 << 18


_NO_RETURN_FIRST = 4


# ... and the pairs with the largest loose bound whose exact bound is computed first.
_NO_RETURN_SCREEN = 16


def _midpoints(X):
    """:func:`~skoccmap.observations.segment_midpoints` of rows already validated, without
    its input checks (called per prediction chunk and per update)."""
    d = X.shape[1] // 2
    return 0.5 * (X[:, :d] + X[:, d:])


def _hit_tree(points):
    """k-d tree over hit points, for nearest-hit queries.

    Without compact nodes: on hits that share a coordinate exactly (the walls of a
    simulated world along the axes) compact nodes made nearest-hit queries within 2 m
    about 4x slower (545 against 126 us per query on B2's 3M observations, timed ad hoc),
    while on the Intel log both take 2-3 us.
    """
    return cKDTree(points, compact_nodes=False)


def _observation_kinds(X, occupied, return_radius, workers=1):
    """HIT / RETURN / NO_RETURN code per row and the hit nearest to every return beam's end.

    A beam is a return beam when a hit lies closer than ``return_radius`` to its end (the
    observation model stops return beams a small margin short of their hit). A hit's
    nearest hit is itself; a no-return beam's is -1.
    """
    d = X.shape[1] // 2
    kinds = np.full(X.shape[0], NO_RETURN, dtype=np.intp)
    kinds[occupied] = HIT
    nearest_hit = np.full(X.shape[0], -1, dtype=np.intp)
    beams = np.flatnonzero(~occupied)
    hit_rows = np.flatnonzero(occupied)
    nearest_hit[hit_rows] = hit_rows
    if beams.size and hit_rows.size:
        # Bounded: the nearest hit to the end of a no-return beam can lie far off, and
        # looking for it dominated fits of millions of rows.
        dist, idx = _hit_tree(X[hit_rows, :d]).query(
            X[beams, d:], distance_upper_bound=return_radius, workers=workers
        )
        ret = dist <= return_radius
        kinds[beams[ret]] = RETURN
        nearest_hit[beams[ret]] = hit_rows[idx[ret]]
    return kinds, nearest_hit


def _similarity_length_scale(kernel, dim):
    """Length scale(s) of the first ``length_scale`` parameter of a kernel.

    One value or one per coordinate (``dim``); one per segment column (``2 * dim``, e.g.
    an RBF over segment rows) gives the larger of the start and end values. 1.0 when the
    kernel has no such parameter.
    """
    for key, value in kernel.get_params(deep=True).items():
        if not key.endswith("length_scale"):
            continue
        value = np.asarray(value, dtype=float)
        if value.size in (1, dim):
            return value
        if value.size == 2 * dim:
            return np.maximum(value[:dim], value[dim:])
    return np.asarray(1.0)


def _assign_no_return(
    X_nr, X_ret, ret_labels, length_scale, max_references=None, random_state=None, n_jobs=None
):
    """Label of the most similar return beam under the integral kernel, per no-return beam.

    The paper's rule, exact over the return beams compared with (up to near-ties within the
    quadrature's error, about 1e-8). The argmax is found by bounds: per no-return beam the
    few return beams with the largest upper bound
    (:func:`~skoccmap._integrals.pair_upper_bound`) are evaluated first, then, largest
    bound first, only those whose bound beats the best value so far. A beam beyond the
    kernel's reach of every return beam takes the label of the nearest one.

    With more than ``max_references`` return beams, each block of no-return beams is
    compared with its own uniform sample of (at most) that many: the cost stays linear in
    the number of no-return beams, and they spread over all return beams instead of
    piling onto the few of one sample. The samples are drawn up front and the blocks run
    in ``n_jobs`` threads, so the labels do not depend on ``n_jobs``.
    """
    rng = check_random_state(random_state)
    dim = X_nr.shape[1] // 2
    scale = np.tile(np.broadcast_to(length_scale, (dim,)), 2)
    A, B_all = X_nr / scale, X_ret / scale
    n_ret = B_all.shape[0]
    n_ref = n_ret if max_references is None else min(n_ret, max_references)
    blocks = list(gen_batches(A.shape[0], max(1, _NO_RETURN_PAIRS // n_ref)))
    if n_ref == n_ret:
        samples = [np.arange(n_ret)] * len(blocks)
    else:
        # Drawn with replacement (duplicates dropped): without, every block would
        # permute all return beams, a cost quadratic in the data overall.
        samples = [np.unique(rng.randint(n_ret, size=n_ref)) for _ in blocks]
    labels = np.empty(A.shape[0], dtype=np.intp)

    def assign(block, refs):
        labels[block] = ret_labels[refs[_most_similar(A[block], B_all[refs])]]

    # Threads: the work is in numpy calls over a block's pairs, which release the GIL.
    Parallel(n_jobs=n_jobs, require="sharedmem")(
        delayed(assign)(block, refs) for block, refs in zip(blocks, samples, strict=True)
    )
    return labels


def _most_similar(A, B):
    """Index into ``B`` of the most similar segment to each row of ``A``.

    Rows in scaled coordinates; found by bounds (see :func:`_assign_no_return`); the
    nearest segment where none is within the kernel's reach. The exact bounds
    (:func:`~skoccmap._integrals.pair_upper_bound`, which need the segments' distance) are
    computed only for the pairs a looser, cheaper bound cannot rule out
    (:func:`~skoccmap._integrals.loose_upper_bound`): the ``_NO_RETURN_SCREEN`` with the
    largest loose bound, whose ``_NO_RETURN_FIRST`` largest exact bounds are integrated
    first, then every pair whose loose bound beats the best similarity found. The pairs
    whose exact bound beats it are then integrated in rounds, largest bound first, each
    round raising the best and ruling out more of the rest.
    """
    from ._integrals import (
        _CUTOFF,
        crossing_upper_bound,
        loose_upper_bound,
        pair_integrals,
        pair_upper_bound,
    )

    n_a, n_b = A.shape[0], B.shape[0]
    rows = np.arange(n_a)
    # Slack for the rounding of the bounds and the quadrature's error against them: the
    # quadrature of long segments crossing at small angles comes out a few 1e-9 above the
    # integral, where the crossing bound is tight.
    slack = 1.0 + 1e-7
    loose = loose_upper_bound(A, B) * slack
    bound = np.full((n_a, n_b), -1.0)  # -1: not computed (bounds are >= 0)
    dist2 = np.full((n_a, n_b), np.inf)
    sim = np.full((n_a, n_b), -np.inf)

    def exact(ii, jj):
        bound[ii, jj], dist2[ii, jj] = pair_upper_bound(A[ii], B[jj])

    def integrate(ii, jj):
        sim[ii, jj] = pair_integrals(A[ii], B[jj])[0]

    n_screen, n_first = min(_NO_RETURN_SCREEN, n_b), min(_NO_RETURN_FIRST, n_b)
    top = np.argpartition(-loose, n_screen - 1, axis=1)[:, :n_screen]
    exact(np.repeat(rows, n_screen), top.ravel())
    first = np.argpartition(-bound, n_first - 1, axis=1)[:, :n_first]
    integrate(np.repeat(rows, n_first), first.ravel())
    best = sim.max(axis=1)
    # The crossing bound, which needs no distances, rules out most crossing beams.
    ii, jj = np.nonzero((loose > best[:, None]) & (bound < 0.0))
    crossing = crossing_upper_bound(A[ii], B[jj]) * slack > best[ii]
    exact(ii[crossing], jj[crossing])
    # The rest of the candidates, each row's in decreasing order of their bounds.
    ii, jj = np.nonzero((bound * slack > best[:, None]) & (dist2 < _CUTOFF**2) & np.isneginf(sim))
    order = np.lexsort((-bound[ii, jj], ii))
    ii, jj = ii[order], jj[order]
    rank = np.arange(ii.size) - np.searchsorted(ii, ii)
    done, step = 0, n_first
    while True:
        # A row is finished at its first candidate that the best rules out.
        open_ = (rank >= done) & (bound[ii, jj] * slack > best[ii])
        if not np.any(open_):
            break
        now = open_ & (rank < done + step)
        integrate(ii[now], jj[now])
        np.maximum.at(best, ii[now], sim[ii[now], jj[now]])
        done, step = done + step, 2 * step
    choice = np.argmax(sim, axis=1)
    out_of_reach = np.flatnonzero(sim[rows, choice] <= 0.0)
    if out_of_reach.size:
        far_rows = A[out_of_reach]
        _, far = pair_upper_bound(
            np.repeat(far_rows, n_b, axis=0), np.tile(B, (far_rows.shape[0], 1))
        )
        choice[out_of_reach] = np.argmin(far.reshape(far_rows.shape[0], n_b), axis=1)
    return choice


def _beam_pieces(X, kinds, max_length, end_length):
    """Training rows cut into pieces, and the row each piece comes from.

    Return beams: pieces no longer than ``max_length``, halving in length towards their
    hit down to ``end_length``. No-return beams: pieces doubling in length away from the
    sensor, the first ``max_length`` long -- their evidence stays local near the robot,
    while a beam that leaves the map for the sensor's maximum range (82 m on the Intel log)
    costs a few rows rather than one per metre. ``max_length=None`` keeps no-return beams
    whole. Hits and free points stay as they are.
    """
    d = X.shape[1] // 2
    no_return = np.flatnonzero(kinds == NO_RETURN)
    rest = np.flatnonzero(kinds != NO_RETURN)
    near, near_source = split_segments(
        X[rest], max_length, end_length=end_length, graded=kinds[rest] == RETURN
    )
    near_source = rest[near_source]
    if no_return.size == 0:
        return near, near_source
    # From the far end, pieces double towards the sensor: split the reversed segments.
    far, far_source = split_segments(
        np.hstack([X[no_return, d:], X[no_return, :d]]), None, end_length=max_length
    )
    far_source = no_return[far_source]
    # Both parts are in row order and no row is in both: merge them by row, in place.
    at_near = np.arange(near_source.size) + np.searchsorted(far_source, near_source)
    at_far = np.arange(far_source.size) + np.searchsorted(near_source, far_source)
    pieces = np.empty((at_near.size + at_far.size, 2 * d))
    source = np.empty(pieces.shape[0], dtype=near_source.dtype)
    pieces[at_near], source[at_near] = near, near_source
    pieces[at_far, :d], pieces[at_far, d:], source[at_far] = far[:, d:], far[:, :d], far_source
    return pieces, source
