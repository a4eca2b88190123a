"""Thinning of near-duplicate free pieces on dense logs.

A robot that drives the same corridor again and again sends hundreds of beams through each
cell of it. Cut into pieces, these beams tell a GP expert the same thing many times over:
the latent function is low there. They cost rows (and so experts, fit time and experts per
query) without changing the map, so pieces that share a cell, a direction and a length are
kept up to a number per key and the rest dropped before the experts are formed.
"""

import math

import numpy as np

from .observations import _row_blocks

__all__ = ["piece_keys", "thin_free_pieces"]

# Width of a direction bin on each component of the unit direction: 2 sin(pi / 16), about
# 22.5 degrees between neighbouring bins.
_DIRECTION_BIN = 2.0 * np.sin(np.pi / 16.0)

# Octaves begin this far (in log2 units) below the powers of two: pieces cut to a power-of-two
# length (no-return beams double from max_beam_length, 1 m by default) come out a rounding
# error either side of it, and would otherwise fall in two octaves at random.
_OCTAVE_SLACK = 1e-6

# Pieces keyed at once (tens of MB of temporaries).
_KEY_BLOCK = 1 << 18


def piece_keys(pieces, cell_size):
    """An integer key per piece: its midpoint's cell, its direction and its length octave.

    Parameters
    ----------
    pieces : ndarray of shape (n_pieces, 2 * n_dims)
        Segment rows ``[start, end]``.
    cell_size : float
        Side of the cells the midpoints are binned in.

    Returns
    -------
    keys : ndarray of shape (n_pieces, 2 * n_dims + 1) of int64
        Equal rows for pieces counted as duplicates of each other. Direction is taken up to
        its sign (a beam piece observes the same line either way); zero-length rows (free
        points) share one direction and length. Octave ``k`` holds the lengths from
        ``2**k`` (less a rounding error) to ``2**(k + 1)``.
    """
    d = pieces.shape[1] // 2
    start, end = pieces[:, :d], pieces[:, d:]
    step = end - start
    length = np.linalg.norm(step, axis=1)
    unit = step / np.where(length > 0, length, 1.0)[:, None]
    # Up to sign: the first non-zero component made positive.
    first = unit[np.arange(len(unit)), np.argmax(unit != 0, axis=1)]
    unit *= np.where(first < 0, -1.0, 1.0)[:, None]
    log_length = np.log2(np.where(length > 0, length, 1.0)) + _OCTAVE_SLACK
    octave = np.where(length > 0, np.floor(log_length), -1e3)
    return np.column_stack(
        [
            np.floor(0.5 * (start + end) / cell_size),
            np.floor((unit + 1.0) / _DIRECTION_BIN),
            octave,
        ]
    ).astype(np.int64)


def thin_free_pieces(pieces, free, *, cell_size, max_per_cell, random_state, kept=None):
    """Which pieces to keep: all hits, and at most ``max_per_cell`` free pieces per key.

    Parameters
    ----------
    pieces : ndarray of shape (n_pieces, 2 * n_dims)
        Candidate segment rows.
    free : ndarray of shape (n_pieces,) of bool
        Free pieces (the ones that may be dropped).
    cell_size : float
        See :func:`piece_keys`.
    max_per_cell : int
        Free pieces kept per key, counting those of ``kept``.
    random_state : RandomState
        Chooses which free pieces of a crowded key are kept.
    kept : ndarray of shape (n_kept, 2 * n_dims), default=None
        Free pieces kept earlier (online updates): they fill their keys first.

    Returns
    -------
    keep : ndarray of shape (n_pieces,) of bool
    """
    keep = ~free
    candidates = np.flatnonzero(free)
    if candidates.size == 0:
        return keep
    candidates = candidates[random_state.permutation(candidates.size)]
    n_old = 0 if kept is None else len(kept)
    key = _flat_piece_keys(pieces, candidates, cell_size, kept)
    # Rank of each row within its key, old rows first (a stable sort keeps their order).
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    rank = np.empty(key.size, dtype=np.intp)
    rank[order] = np.arange(key.size) - np.searchsorted(sorted_key, sorted_key, side="left")
    keep[candidates] = rank[n_old:] < max_per_cell
    return keep


def _flat_piece_keys(pieces, rows, cell_size, kept=None):
    """:func:`_flat_keys` of the :func:`piece_keys` of ``kept`` followed by
    ``pieces[rows]``, a block of rows at a time: the keys' temporaries, tens of bytes per
    piece, would otherwise cost gigabytes on logs of millions of beams."""
    kept = np.empty((0, pieces.shape[1])) if kept is None else kept

    def blocks():
        for block in _row_blocks(len(kept), _KEY_BLOCK):
            yield piece_keys(kept[block], cell_size)
        for block in _row_blocks(rows.size, _KEY_BLOCK):
            yield piece_keys(pieces[rows[block]], cell_size)

    return _flattened(blocks, len(kept) + rows.size)


def _flat_keys(keys):
    """One int64 per row of ``keys``, equal exactly where the rows are equal.

    Mixed radix over the columns' ranges: sorting one integer column is many times faster
    than ``np.unique(axis=0)`` on millions of rows. Falls back to the latter when the
    ranges overflow 63 bits.
    """
    return _flattened(lambda: iter([keys]), keys.shape[0])


def _flattened(blocks, n_keys):
    """:func:`_flat_keys` of the ``n_keys`` rows that ``blocks()`` yields block by block,
    in two passes over the blocks: the columns' ranges, then the keys."""
    if n_keys == 0:
        return np.zeros(0, dtype=np.int64)
    ranges = [(keys.min(axis=0), keys.max(axis=0)) for keys in blocks()]
    low = np.min([lo for lo, _ in ranges], axis=0)
    span = np.max([hi for _, hi in ranges], axis=0) - low + 1
    # Python integers: a product of int64 spans would wrap around and hide the overflow.
    if math.prod(int(v) for v in span) >= 2**63:
        keys = np.vstack(list(blocks()))
        return np.unique(keys, axis=0, return_inverse=True)[1].ravel().astype(np.int64)
    flat = np.empty(n_keys, dtype=np.int64)
    at = 0
    for keys in blocks():
        flat[at : at + len(keys)] = _mixed_radix(keys - low, span)
        at += len(keys)
    return flat


def _mixed_radix(offsets, span):
    """One integer per row of non-negative ``offsets``, digit ``j`` in base ``span[j]``."""
    flat = np.zeros(offsets.shape[0], dtype=np.int64)
    for column, size in zip(offsets.T, span, strict=True):
        flat = flat * size + column
    return flat
