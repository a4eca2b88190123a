"""Thinning of near-duplicate free pieces (``max_pieces_per_cell``)."""

import numpy as np
import pytest

from skoccmap import MixtureGPOccupancyMap
from skoccmap._thinning import piece_keys, thin_free_pieces
from skoccmap.datasets import make_office_scans


def test_keys_ignore_direction_sign_and_separate_cells_directions_lengths():
    base = np.array([[0.0, 0.0, 0.5, 0.0]])
    reversed_ = np.array([[0.5, 0.0, 0.0, 0.0]])
    other_cell = base + [1.0, 0.0, 1.0, 0.0]
    turned = np.array([[0.25, -0.25, 0.25, 0.25]])  # same midpoint, 90 degrees
    longer = np.array([[-0.25, 0.0, 0.75, 0.0]])  # same midpoint, twice the length
    keys = piece_keys(np.vstack([base, reversed_, other_cell, turned, longer]), 0.2)
    assert np.array_equal(keys[0], keys[1])
    for k in (2, 3, 4):
        assert not np.array_equal(keys[0], keys[k])


def test_at_most_cap_free_pieces_per_key_and_every_hit_kept():
    rng = np.random.RandomState(0)
    free_rows = np.tile([[0.02, 0.02, 0.72, 0.02]], (10, 1)) + rng.uniform(0, 0.01, (10, 4))
    hits = np.tile([[1.0, 1.0, 1.0, 1.0]], (5, 1))
    pieces = np.vstack([free_rows, hits])
    free = np.r_[np.ones(10, bool), np.zeros(5, bool)]
    keep = thin_free_pieces(pieces, free, cell_size=0.2, max_per_cell=3, random_state=rng)
    assert keep[10:].all()
    assert keep[:10].sum() == 3


def test_pieces_kept_earlier_fill_their_key_first():
    rng = np.random.RandomState(0)
    row = np.array([[0.0, 0.0, 0.5, 0.0]])
    pieces = np.repeat(row, 4, axis=0)
    keep = thin_free_pieces(
        pieces,
        np.ones(4, bool),
        cell_size=0.2,
        max_per_cell=3,
        random_state=rng,
        kept=np.repeat(row, 2, axis=0),
    )
    assert keep.sum() == 1


@pytest.fixture(scope="module")
def office():
    return make_office_scans(random_state=0)


def test_map_keeps_fewer_pieces_and_online_keeps_as_many_as_fit(office):
    X, y = office.X, office.y
    plain = MixtureGPOccupancyMap(max_pieces_per_cell=None, random_state=0).fit(X, y)
    thin = MixtureGPOccupancyMap(max_pieces_per_cell=2, random_state=0).fit(X, y)
    assert thin._pieces.shape[0] < plain._pieces.shape[0]
    # Hits are never dropped.
    assert (thin._piece_y == 1).sum() == (plain._piece_y == 1).sum()
    half = X.shape[0] // 2
    online = MixtureGPOccupancyMap(max_pieces_per_cell=2, random_state=0)
    online.partial_fit(X[:half], y[:half]).partial_fit(X[half:], y[half:])
    # The cap counts what earlier updates kept: one batch or two keep as many pieces.
    assert online._pieces.shape[0] == thin._pieces.shape[0]
    proba = thin.predict_proba(X[y == 1][:50])[:, 1]
    assert np.all(np.isfinite(proba)) and proba.mean() > 0.65


def test_bad_cap_is_rejected(office):
    with pytest.raises(ValueError, match="max_pieces_per_cell"):
        MixtureGPOccupancyMap(max_pieces_per_cell=0).fit(office.X, office.y)


@pytest.mark.parametrize("spread", [3, 2**40])
def test_flat_keys_equal_exactly_where_rows_are(spread):
    from skoccmap._thinning import _flat_keys

    rng = np.random.default_rng(0)
    keys = rng.integers(-spread, spread, size=(2000, 5))
    keys[1000:] = keys[rng.integers(0, 1000, size=1000)]  # duplicated rows
    flat = _flat_keys(keys)
    same_row = (keys[:, None] == keys[None]).all(axis=-1)
    np.testing.assert_array_equal(flat[:, None] == flat[None], same_row)


def test_flat_keys_do_not_wrap_when_spans_overflow():
    from skoccmap._thinning import _flat_keys

    # Spans 2 x (2**16)**4 = 2**65: with wrapped int64 arithmetic the first two rows
    # would both flatten to 0.
    top = 2**16 - 1
    keys = np.array([[0, 0, 0, 0, 0], [1, 0, 0, 0, 0], [0, top, top, top, top]])
    assert np.unique(_flat_keys(keys)).size == 3


def test_keys_taken_in_blocks_equal_the_keys_taken_at_once(monkeypatch):
    import skoccmap._thinning as thinning

    rng = np.random.default_rng(1)
    pieces = rng.uniform(-5.0, 5.0, size=(200, 4))
    pieces[::7, 2:] = pieces[::7, :2]  # free points: zero length
    kept = rng.uniform(-5.0, 5.0, size=(30, 4))
    rows = rng.permutation(200)[:150]
    at_once = thinning._flat_keys(piece_keys(np.vstack([kept, pieces[rows]]), 0.2))
    monkeypatch.setattr(thinning, "_KEY_BLOCK", 16)
    in_blocks = thinning._flat_piece_keys(pieces, rows, 0.2, kept)
    np.testing.assert_array_equal(in_blocks, at_once)
    assert thinning._flat_piece_keys(pieces, rows[:0], 0.2).shape == (0,)


def test_keys_taken_in_blocks_fall_back_when_spans_overflow(monkeypatch):
    import skoccmap._thinning as thinning

    # Cells of 1e-14 m over a kilometre: the spans' product exceeds 63 bits.
    pieces = np.array(
        [
            [0.0, 0.0, 0.5, 0.0],
            [1e3, 1e3, 1e3, 1e3 + 0.5],
            [0.0, 0.0, 0.5, 0.0],
            [5.0, 5.0, 5.0, 5.5],
        ]
    )
    rows = np.arange(4)
    at_once = thinning._flat_keys(piece_keys(pieces, 1e-14))
    monkeypatch.setattr(thinning, "_KEY_BLOCK", 3)
    in_blocks = thinning._flat_piece_keys(pieces, rows, 1e-14)
    np.testing.assert_array_equal(in_blocks, at_once)
    assert in_blocks[0] == in_blocks[2] and np.unique(in_blocks).size == 3
