"""Clusters made into experts of bounded size: small clusters merged into their nearest,
big ones bisected, free pieces sent to a hit with room, and the Gaussian gates of a split
cluster's pieces.
"""

import numpy as np
from joblib import effective_n_jobs

from ._beams import _midpoints

# A hit carrying more rows (its beams' pieces) than this many times max_expert_size, and
# than _MAX_HIT_ROWS (a kernel matrix of 0.8 GB), is an error: its expert, which holds at
# least that hit, could not be split to size (a return beam of 100 km cut into 1 m pieces
# asked for 75 GiB). A hit of the Intel log carries up to about 400 rows.
_HIT_ROWS_FACTOR = 10
_MAX_HIT_ROWS = 10_000

# Covariance ridge of the Gaussians that gate the pieces of a split cluster, relative to
# the mean variance of the piece: keeps pieces along a wall (rank-deficient) invertible.
_GATING_RIDGE = 1e-3


def _merge_small(labels, hit_points, hit_labels, min_size):
    """Merge clusters with fewer than ``min_size`` observations into their nearest one.

    Returns the merged index of every cluster. A cluster of a few hits can learn nothing,
    and the broad predictive density of a near-empty DP cluster would win the gate far
    from all hits; nearest is by hit centroid, smallest first.
    """
    n_clusters = hit_labels.max() + 1
    counts = np.bincount(labels, minlength=n_clusters).astype(float)
    hit_counts = np.bincount(hit_labels, minlength=n_clusters).astype(float)
    centroids = np.zeros((n_clusters, hit_points.shape[1]))
    np.add.at(centroids, hit_labels, hit_points)
    centroids /= hit_counts[:, None]
    merged = np.arange(n_clusters)
    alive = np.ones(n_clusters, dtype=bool)
    while alive.sum() > 1:
        live = np.flatnonzero(alive)
        small = live[np.argmin(counts[live])]
        if counts[small] >= min_size:
            break
        others = live[live != small]
        target = others[np.argmin(np.linalg.norm(centroids[others] - centroids[small], axis=1))]
        total = hit_counts[target] + hit_counts[small]
        centroids[target] = (
            hit_counts[target] * centroids[target] + hit_counts[small] * centroids[small]
        ) / total
        hit_counts[target] = total
        counts[target] += counts[small]
        alive[small] = False
        merged[merged == small] = target
    # Renumber the surviving clusters 0..K-1 in order.
    return np.unique(merged, return_inverse=True)[1]


def _groups(labels, n_groups):
    """Row indices of each label 0 .. n_groups - 1, in order (one sort, not one pass each)."""
    order = np.argsort(labels, kind="stable")
    return np.split(order, np.searchsorted(labels[order], np.arange(1, n_groups)))


def _query_max(query, weights):
    """Each pair's largest weight among its query's pairs (pairs sorted by query)."""
    if query.size == 0:
        return np.zeros(0)
    starts = np.flatnonzero(np.r_[True, query[1:] != query[:-1]])
    largest = np.maximum.reduceat(weights, starts)
    return np.repeat(largest, np.diff(np.r_[starts, query.size]))


def _best(query, weights):
    """Pairs holding their query's largest weight (pairs sorted by query)."""
    return weights == _query_max(query, weights)


def _bisect(points, max_size, weights=None):
    """Split point indices recursively at the (weighted) median along the principal axis.

    Returns a list of index arrays, each of total weight at most ``max_size`` (or a single
    point heavier than that). Deterministic and balanced, so expert sizes stay bounded
    however large the map grows.
    """
    weights = np.ones(points.shape[0]) if weights is None else np.asarray(weights, float)
    pieces, stack = [], [np.arange(points.shape[0])]
    while stack:
        idx = stack.pop()
        if idx.size == 1 or weights[idx].sum() <= max_size:
            pieces.append(idx)
            continue
        p = points[idx]
        centred = p - p.mean(axis=0)
        # Principal axis = top right-singular vector of the centred points.
        axis = np.linalg.svd(centred, full_matrices=False)[2][0]
        order = np.argsort(centred @ axis, kind="stable")
        cum = np.cumsum(weights[idx[order]])
        half = int(np.clip(np.searchsorted(cum, 0.5 * cum[-1]) + 1, 1, idx.size - 1))
        stack.append(idx[order[half:]])
        stack.append(idx[order[:half]])
    return pieces


def _nearest_with_room(tree, points, radius, cap, rounds, workers=1):
    """Index of each point's nearest hit (of ``tree``) that still has room, or -1.

    In round j every point still without a hit asks its j-th nearest hit within
    ``radius``, and a hit takes the nearest of its askers up to ``cap`` points in all; a
    point whose ``rounds`` nearest hits within the radius are all full gets -1.

    The neighbours are looked up for blocks of rounds that double in length (1, 2-3,
    4-7, ...; at most 8 rounds at a time) and only for the points still asking: a point
    that asks in every round costs about two queries of ``rounds`` neighbours, not one
    per round, and memory stays linear in the points. ``workers`` is passed to
    :meth:`scipy.spatial.cKDTree.query`; the result does not depend on it.
    """
    n_hits = tree.n
    rounds = min(rounds, n_hits)
    chosen = np.full(len(points), -1, dtype=np.intp)
    load = np.zeros(n_hits, dtype=np.float64)
    asking = np.arange(len(points))
    first = 1
    while first <= rounds and asking.size:
        last = min(2 * first - 1, first + 7, rounds)
        dist, hit = tree.query(
            points[asking],
            k=list(range(first, last + 1)),
            distance_upper_bound=radius,
            workers=workers,
        )
        for col in range(last - first + 1):
            # A point with no j-th hit within the radius has none further either.
            inside = np.isfinite(dist[:, col])
            asking, dist, hit = asking[inside], dist[inside], hit[inside]
            if asking.size == 0:
                break
            order = np.lexsort((dist[:, col], hit[:, col]))
            target = hit[order, col]
            rank = np.arange(target.size) - np.searchsorted(target, target, side="left")
            take = rank < cap - load[target]
            chosen[asking[order[take]]] = target[take]
            load += np.bincount(target[take], minlength=n_hits)
            # Still asking, in point order (as the next round's lookups are).
            left = np.sort(order[~take])
            asking, dist, hit = asking[left], dist[left], hit[left]
        first = last + 1
    return chosen


def _query_workers(n_jobs):
    """Threads for a k-d tree query under ``n_jobs`` (joblib's meaning, None = 1)."""
    return max(int(effective_n_jobs(n_jobs)), 1)


def _split_hits(hits, hit_cluster, n_clusters, piece_hit, max_size):
    """Expert of each hit, and cluster of each expert: clusters split to ``max_size``.

    A cluster whose hits carry more than ``max_size`` pieces (``piece_hit``: the hit each
    piece follows) is bisected (:func:`_bisect`), each hit weighted by its pieces, and
    every piece then joins the expert of its hit: cutting the pieces themselves would part
    walls from the free space in front of them and leave one-class experts.
    """
    pieces_per_hit = np.bincount(piece_hit, minlength=hits.shape[0])
    if max_size is not None and pieces_per_hit.size:
        worst = int(np.argmax(pieces_per_hit))
        limit = max(_HIT_ROWS_FACTOR * max_size, _MAX_HIT_ROWS)
        if pieces_per_hit[worst] > limit:
            raise ValueError(
                f"the hit at {np.round(hits[worst], 3).tolist()} carries "
                f"{pieces_per_hit[worst]} rows (its beams' pieces), and an expert holds at "
                f"least one hit with its rows: more than {limit} (the larger of "
                f"{_HIT_ROWS_FACTOR} x max_expert_size={max_size} and {_MAX_HIT_ROWS}). Its "
                "beams are far longer than the map around them: check that the ranges are in "
                "metres, or cut beams into longer pieces (max_beam_length)."
            )
    hit_expert = np.empty(hits.shape[0], dtype=np.intp)
    expert_cluster = []
    for c, mine in enumerate(_groups(hit_cluster, n_clusters)):
        first = len(expert_cluster)
        if max_size is None or pieces_per_hit[mine].sum() <= max_size:
            parts = [np.arange(mine.size)]
        else:
            parts = _bisect(hits[mine], max_size, pieces_per_hit[mine])
        for j, part in enumerate(parts):
            hit_expert[mine[part]] = first + j
            expert_cluster.append(c)
    return hit_expert, np.asarray(expert_cluster, dtype=np.intp)


def _piece_gates(expert_cluster, n_clusters, pieces, piece_expert, clusters=None, gates=None):
    """Gate of the experts of each cluster (None for a cluster of one expert).

    Each gate is fitted to the midpoints of its experts' ``pieces``. Only ``clusters`` (all
    by default) are (re)made; the others keep their entry of ``gates``.
    """
    gates = (
        [None] * n_clusters if gates is None else list(gates) + [None] * (n_clusters - len(gates))
    )
    groups = None
    for c in range(n_clusters) if clusters is None else clusters:
        ks = np.flatnonzero(expert_cluster == c)
        if ks.size < 2:
            gates[c] = None
            continue
        if groups is None:
            groups = _groups(piece_expert, expert_cluster.size)
        gates[c] = _PieceGate([_midpoints(pieces[groups[k]]) for k in ks])
    return gates


class _PieceGate:
    """Gaussian responsibilities of the pieces of one split cluster (a fixed GMM).

    An expert without pieces (its hits all left out as transient) weighs nothing; if no
    expert of the cluster has pieces, they share it equally.
    """

    def __init__(self, pieces_points):
        self.means_, self.chols_, self.log_weights_ = [], [], []
        n_total = sum(len(p) for p in pieces_points)
        for pts in pieces_points:
            dim = pts.shape[1]
            if len(pts) == 0:
                self.means_.append(np.zeros(dim))
                self.chols_.append(np.eye(dim))
                self.log_weights_.append(-np.inf if n_total else 0.0)
                continue
            mean = pts.mean(axis=0)
            cov = np.atleast_2d(np.cov(pts, rowvar=False)) if len(pts) > 1 else np.eye(dim)
            ridge = _GATING_RIDGE * max(np.trace(cov) / dim, 1e-12) + 1e-12
            chol = np.linalg.cholesky(cov + ridge * np.eye(dim))
            self.means_.append(mean)
            self.chols_.append(chol)
            self.log_weights_.append(np.log(len(pts) / n_total))

    def predict_proba(self, points):
        log_p = np.empty((points.shape[0], len(self.means_)))
        for j, (mean, chol, logw) in enumerate(
            zip(self.means_, self.chols_, self.log_weights_, strict=True)
        ):
            z = np.linalg.solve(chol, (points - mean).T)
            log_p[:, j] = logw - 0.5 * np.sum(z * z, axis=0) - np.sum(np.log(np.diag(chol)))
        log_p -= log_p.max(axis=1, keepdims=True)
        p = np.exp(log_p)
        return p / p.sum(axis=1, keepdims=True)
