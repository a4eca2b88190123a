"""Thinning of near-duplicate free pieces (``max_pieces_per_cell``)."""

import warnings

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


@pytest.mark.slow  # over 30 s: fits of the office at two settings
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


@pytest.mark.parametrize("spread", [3, 2**40, (1, 2, 30, 3, 500)])
def test_flat_keys_equal_exactly_where_rows_are(spread):
    from skoccmap._thinning import _flat_keys

    rng = np.random.default_rng(0)
    # Columns of one range, or of ranges that differ: each column a digit of its own base.
    keys = rng.integers(-np.asarray(spread), spread, size=(2000, 5))
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


@pytest.mark.parametrize("n_dims", [2, 3])
def test_keys_do_not_depend_on_which_end_a_piece_starts(n_dims):
    rng = np.random.default_rng(n_dims)
    starts = rng.uniform(-2.0, 2.0, size=(300, n_dims))
    steps = rng.normal(size=(300, n_dims))
    steps[:60, 0] = 0.0  # first component zero: the sign is the next one's
    steps[60:120, :-1] = 0.0  # along the last axis, either way
    pieces = np.hstack([starts, starts + steps])
    reversed_ = np.hstack([starts + steps, starts])
    np.testing.assert_array_equal(piece_keys(reversed_, 0.2), piece_keys(pieces, 0.2))


def _same_rows(keys):
    return (keys[:, None] == keys[None]).all(axis=-1)


def test_keys_bin_midpoints_in_cells_of_the_given_size():
    # Pieces of one direction and length, their midpoints well inside cells on either
    # side of zero: equal keys exactly where the midpoints share a cell.
    cell = 0.2
    rng = np.random.default_rng(0)
    index = rng.integers(-4, 4, size=(200, 2))
    mid = (index + 0.5 + rng.uniform(-0.4, 0.4, size=(200, 2))) * cell
    half_step = np.array([0.15, 0.05])
    keys = piece_keys(np.hstack([mid - half_step, mid + half_step]), cell)
    np.testing.assert_array_equal(_same_rows(keys), _same_rows(index))


@pytest.mark.parametrize("direction", [[1.0, 0.0], [0.6, -0.8]])
def test_keys_share_a_length_octave(direction):
    # One midpoint and direction: equal keys exactly where floor(log2(length)) is equal.
    lengths = 2.0 ** np.random.default_rng(0).uniform(-4.0, 3.0, size=200)
    half_step = 0.5 * lengths[:, None] * np.asarray(direction)
    keys = piece_keys(np.hstack([0.05 - half_step, 0.05 + half_step]), 10.0)
    octave = np.floor(np.log2(lengths))[:, None]
    np.testing.assert_array_equal(_same_rows(keys), _same_rows(octave))


@pytest.mark.parametrize("length", [0.5, 1.0, 2.0, 4.0])
def test_pieces_cut_to_a_power_of_two_length_share_its_octave(length):
    # No-return beams are cut into pieces of 1, 2, 4 m (max_beam_length=1.0): from different
    # poses, their lengths come out a rounding error either side of the power of two.
    rng = np.random.default_rng(0)
    starts = rng.uniform(-50.0, 50.0, size=(500, 2))
    unit = rng.normal(size=(500, 2))
    unit /= np.linalg.norm(unit, axis=1)[:, None]
    pieces = np.hstack([starts, starts + length * unit])
    assert (np.linalg.norm(pieces[:, 2:] - pieces[:, :2], axis=1) < length).any()
    keys = piece_keys(pieces, 0.2)
    # One octave, the one of pieces half as long again.
    longer = piece_keys(np.hstack([starts, starts + 1.5 * length * unit]), 0.2)
    assert np.unique(np.r_[keys[:, -1], longer[:, -1]]).size == 1


@pytest.mark.parametrize("n_dims", [2, 3])
def test_keys_separate_directions_45_degrees_apart(n_dims):
    # One midpoint and length. Unit vectors 45 degrees apart differ by 2 sin(22.5 deg) =
    # 0.77, so by 0.44 or more on some axis: more than a bin's 2 sin(pi / 16) = 0.39.
    rng = np.random.default_rng(n_dims)
    unit = rng.normal(size=(300, n_dims))
    unit /= np.linalg.norm(unit, axis=1)[:, None]
    keys = piece_keys(np.hstack([0.05 - 0.35 * unit, 0.05 + 0.35 * unit]), 10.0)
    # Angle between the lines (a piece's direction counts up to its sign).
    cosine = np.abs(unit @ unit.T)
    apart = cosine <= np.cos(np.pi / 4)
    assert apart.sum() > 1000
    assert not _same_rows(keys)[apart].any()
    # ... and parallel pieces share a key.
    twins = piece_keys(np.hstack([0.05 - 0.3 * unit, 0.05 + 0.3 * unit]), 10.0)
    np.testing.assert_array_equal(twins, keys)


def test_free_points_are_keyed_by_their_cell_without_warnings():
    points = np.array([[0.05, 0.05], [0.15, 0.05], [0.25, 0.05], [-0.05, 0.05]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        keys = piece_keys(np.hstack([points, points]), 0.2)
    assert np.array_equal(keys[0], keys[1])
    assert not _same_rows(keys)[[0, 0, 2], [2, 3, 3]].any()


def _crowded_pieces(rng, n):
    """``n`` pieces drawn from a few, on a few neighbouring cells and two directions."""
    mid = np.array([[0.1, 0.1], [0.3, 0.1], [0.5, 0.3], [-0.1, 0.1], [0.1, -0.3]])
    half_step = np.array([[0.3, 0.0], [0.2, 0.2]])
    rows = np.hstack([mid[:, None] - half_step, mid[:, None] + half_step]).reshape(-1, 4)
    return rows[rng.integers(0, len(rows), size=n)]


@pytest.mark.parametrize("max_per_cell", [1, 4, 30])
@pytest.mark.parametrize("n_kept", [0, 150])
def test_thinning_keeps_per_key_the_cap_less_the_pieces_kept_earlier(max_per_cell, n_kept):
    rng = np.random.default_rng(max_per_cell + n_kept)
    pieces = _crowded_pieces(rng, 400)
    free = rng.uniform(size=400) < 0.8
    kept = _crowded_pieces(rng, n_kept) if n_kept else None
    keep = thin_free_pieces(
        pieces,
        free,
        cell_size=0.2,
        max_per_cell=max_per_cell,
        random_state=np.random.RandomState(0),
        kept=kept,
    )
    assert keep[~free].all()
    # Counted row by row: free pieces and earlier ones per key, and the kept ones.
    old, new, chosen = {}, {}, {}
    for row in [] if kept is None else piece_keys(kept, 0.2):
        old[tuple(row)] = old.get(tuple(row), 0) + 1
    for row, is_free, is_kept in zip(piece_keys(pieces, 0.2), free, keep, strict=True):
        if is_free:
            new[tuple(row)] = new.get(tuple(row), 0) + 1
            chosen[tuple(row)] = chosen.get(tuple(row), 0) + int(is_kept)
    assert len(new) > 5 and max(new.values()) > max_per_cell
    for key, n in new.items():
        assert chosen[key] == min(n, max(max_per_cell - old.get(key, 0), 0)), key


def test_a_lone_free_piece_is_kept():
    pieces = np.array([[0.0, 0.0, 0.5, 0.0], [1.0, 1.0, 1.0, 1.0]])
    for free in ([True, False], [True, True]):
        keep = thin_free_pieces(
            pieces,
            np.array(free),
            cell_size=0.2,
            max_per_cell=1,
            random_state=np.random.RandomState(0),
        )
        assert keep.all()


def test_which_pieces_of_a_crowded_key_are_kept_is_random():
    pieces = np.tile([[0.0, 0.0, 0.5, 0.0]], (10, 1))
    times_kept = np.zeros(10, dtype=int)
    for seed in range(20):
        keep = thin_free_pieces(
            pieces,
            np.ones(10, bool),
            cell_size=0.2,
            max_per_cell=3,
            random_state=np.random.RandomState(seed),
        )
        assert keep.sum() == 3
        times_kept += keep
    # Each kept 6 times in 20 on average; never kept, about 1 chance in 1250 for one piece.
    assert times_kept.min() > 0
