import copy
import warnings

import numpy as np
import pytest

from skoccmap import MixtureGPOccupancyMap
from skoccmap._transient import CellCounts
from skoccmap.baselines import FrequencyGridMap
from skoccmap.datasets import make_office_scans


def _random_rows(rng, n_dims, n_beams=300, n_hits=200):
    starts = rng.uniform(-3, 3, size=(n_beams, n_dims))
    ends = starts + rng.normal(scale=1.5, size=(n_beams, n_dims))
    hits = rng.uniform(-3, 3, size=(n_hits, n_dims))
    X = np.vstack([np.hstack([starts, ends]), np.hstack([hits, hits])])
    y = np.r_[np.zeros(n_beams, int), np.ones(n_hits, int)]
    return X, y


@pytest.mark.parametrize("n_dims", [2, 3])
def test_counts_are_the_frequency_grid_counts(n_dims):
    X, y = _random_rows(np.random.default_rng(n_dims), n_dims)
    counts = CellCounts(0.1, n_dims).add(X, y == 1)
    grid = FrequencyGridMap(resolution=0.1).fit(X, y)
    hits = X[y == 1, n_dims:]
    np.testing.assert_array_equal(counts.frequency(hits), grid.predict_proba(X[y == 1])[:, 1])
    # Cells where nothing was counted hold no evidence against a hit.
    assert counts.frequency(np.full((1, n_dims), 100.0))[0] == 1.0


def test_counts_of_batches_add_up_to_the_counts_of_all_rows():
    X, y = _random_rows(np.random.default_rng(0), 2)
    order = np.random.default_rng(1).permutation(len(X))
    X, y = X[order], y[order]
    whole = CellCounts(0.1, 2).add(X, y == 1)
    parts = CellCounts(0.1, 2)
    for rows in np.array_split(np.arange(len(X)), 3):
        parts.add(X[rows], y[rows] == 1)
    np.testing.assert_array_equal(parts.keys, whole.keys)
    np.testing.assert_array_equal(parts.hits, whole.hits)
    np.testing.assert_array_equal(parts.passes, whole.passes)
    # Adding to a shallow copy leaves the original's counts as they were.
    before = copy.copy(parts)
    keys, hits = before.keys.copy(), before.hits.copy()
    copy.copy(before).add(X, y == 1)
    np.testing.assert_array_equal(before.keys, keys)
    np.testing.assert_array_equal(before.hits, hits)


@pytest.mark.parametrize("n_dims", [2, 3])
def test_counts_do_not_depend_on_how_the_rows_are_chunked(monkeypatch, n_dims):
    import skoccmap._transient as transient
    import skoccmap.baselines as baselines

    X, y = _random_rows(np.random.default_rng(10 + n_dims), n_dims)
    whole = CellCounts(0.1, n_dims).add(X, y == 1)
    n_cells = whole.keys.size
    # A few crossings per chunk (beams of 1.5 m cross about 20 cells of 0.1 m: a row or
    # two per chunk), and parts merged on the way once they hold more than the map's cells.
    monkeypatch.setattr(baselines, "_CROSSINGS_PER_CHUNK", 40)
    monkeypatch.setattr(transient, "_MAX_COUNTED_CELLS", n_cells)
    chunked = CellCounts(0.1, n_dims).add(X, y == 1)
    for got, expected in zip(
        (chunked.keys, chunked.hits, chunked.passes),
        (whole.keys, whole.hits, whole.passes),
        strict=True,
    ):
        np.testing.assert_array_equal(got, expected)
    monkeypatch.setattr(transient, "_MAX_COUNTED_CELLS", n_cells - 1)
    with pytest.raises(ValueError, match=f"pass more than {n_cells - 1:,} cells of 0.1 m"):
        CellCounts(0.1, n_dims).add(X, y == 1)


def test_a_map_too_large_to_count_names_min_hit_frequency(monkeypatch):
    import skoccmap._transient as transient

    data = make_office_scans(n_poses=4, n_beams=30, random_state=0)
    # As if the beams passed more cells than the counts take (ranges in millimetres).
    monkeypatch.setattr(transient, "_MAX_COUNTED_CELLS", 100)
    with pytest.raises(ValueError, match="in metres.*pass min_hit_frequency=None"):
        MixtureGPOccupancyMap(random_state=0).fit(data.X, data.y)
    MixtureGPOccupancyMap(min_hit_frequency=None, random_state=0).fit(data.X, data.y)


def test_coordinates_too_far_to_count_are_an_error():
    X = np.array([[0.0, 0.0, 1e12, 0.0]])
    with pytest.raises(ValueError, match="cannot be counted"):
        CellCounts(0.1, 2).add(X, np.array([False]))
    # So far out that the cast to int64 would wrap around and pass a check made after it.
    for far in (1e50, 1e300):
        with pytest.raises(ValueError, match="cannot be counted"):
            CellCounts(0.1, 2).add(np.array([[0.0, 0.0, far, far]]), np.array([False]))
        counts = CellCounts(0.1, 2).add(np.array([[0.0, 0.0, 1.0, 1.0]]), np.array([False]))
        with pytest.raises(ValueError, match="cannot be counted"):
            counts.counted(np.array([[far, 0.0]]))


def test_a_row_too_far_to_count_leaves_the_counts_unchanged():
    counts = CellCounts(0.1, 2).add(np.array([[0.0, 0.0, 1.0, 1.0]]), np.array([False]))
    before = (counts.keys.copy(), counts.hits.copy(), counts.passes.copy())
    # Near rows first, the far one last: nothing is counted before it is found.
    X = np.array([[0.0, 0.0, 2.0, 0.0], [0.0, 0.0, 0.5, 0.5], [0.0, 0.0, 1e12, 0.0]])
    with pytest.raises(ValueError, match="cannot be counted"):
        counts.add(X, np.array([False, True, False]))
    for kept, was in zip((counts.keys, counts.hits, counts.passes), before, strict=True):
        np.testing.assert_array_equal(kept, was)


def test_counts_pickled_before_the_origin_cell_still_count():
    # Old pickles keyed absolute cells and have no origin: they read as an origin at zero.
    X, y = _random_rows(np.random.default_rng(4), 2)
    counts = CellCounts(0.1, 2)
    counts.origin = np.zeros(2)
    counts.add(X[:300], y[:300] == 1)
    state = counts.__dict__.copy()
    del state["origin"]
    old = CellCounts.__new__(CellCounts)
    old.__setstate__(state)
    points = X[:, 2:]
    np.testing.assert_array_equal(old.counted(points), counts.counted(points))
    old.add(X[300:], y[300:] == 1)  # used to raise AttributeError: no 'origin'
    whole = CellCounts(0.1, 2).add(X, y == 1)
    np.testing.assert_array_equal(old.counted(points), whole.counted(points))


@pytest.mark.parametrize("n_dims", [2, 3])
def test_counts_do_not_depend_on_where_the_map_lies(n_dims):
    # UTM-sized coordinates: the keys count cells from the first data's, so a 3-D map
    # 5e6 m from the origin (20 bits an axis would reach 52 km) counts as one at the origin.
    X, y = _random_rows(np.random.default_rng(n_dims), n_dims)
    near = CellCounts(0.1, n_dims).add(X, y == 1)
    shift = np.tile(np.r_[5e5, 5e6, 100.0][:n_dims], 2)
    far = CellCounts(0.1, n_dims).add(X + shift, y == 1)
    points = X[:, n_dims:]
    np.testing.assert_array_equal(far.counted(points + shift[:n_dims]), near.counted(points))
    assert near.counted(points)[0].sum() > 0
    # Nothing counted yet: no origin, and nothing found.
    assert CellCounts(0.1, n_dims).add(X[:0], y[:0] == 1).counted(points)[0].sum() == 0


@pytest.fixture(scope="module")
def office_with_a_passer_by():
    """The office, and someone standing where many beams pass, seen from three poses."""
    office = make_office_scans(random_state=0)
    X, y = office.X, office.y
    grid = FrequencyGridMap(resolution=0.1).fit(X, y)
    cell = np.argsort(-(grid.passes_ * (grid.hits_ == 0)))[8]
    index = np.unravel_index(grid.cell_index_[cell], grid.shape_)
    spot = grid.origin_ + (np.array(index) + 0.5) * 0.1
    assert grid.passes_[cell] >= 20
    poses = office.scans.poses[:, :2]
    rows = []
    for k in np.argsort(np.linalg.norm(poses - spot, axis=1))[1:4]:
        toward = (spot - poses[k]) / np.linalg.norm(spot - poses[k])
        hit = spot + np.random.default_rng(k).normal(scale=0.03, size=2)
        rows += [np.r_[hit, hit], np.r_[poses[k], hit - 0.05 * toward]]
    return np.vstack([X, rows]), np.r_[y, [1, 0] * 3], spot


@pytest.mark.slow  # over 30 s: fits of the office at two settings
def test_hits_the_beams_contradict_are_left_out(office_with_a_passer_by):
    X, y, spot = office_with_a_passer_by
    query = np.r_[spot, spot][None, :]
    model = MixtureGPOccupancyMap(min_hit_frequency=0.2, random_state=0).fit(X, y)
    assert model.transient_hits_.shape == (X.shape[0],)
    assert model.transient_hits_[-6::2].all() and not model.transient_hits_[-5::2].any()
    # A few wall cells that grazing beams cross more often than the wall is hit, no more.
    assert model.transient_hits_.sum() < 0.01 * (y == 1).sum()
    assert model.predict_proba(query)[0, 1] < 0.2
    # No piece follows a transient hit: no expert holds a passer-by's free space alone.
    assert not model.transient_hits_[y == 1][model._piece_hit].any()
    # Kept, the two hits draw an occupied blob among the free beams.
    kept = MixtureGPOccupancyMap(min_hit_frequency=None, random_state=0).fit(X, y)
    assert not kept.transient_hits_.any()
    assert kept.predict_proba(query)[0, 1] > 0.5


def test_online_updates_count_every_row_seen(office_with_a_passer_by):
    X, y, _ = office_with_a_passer_by
    # The passer-by's rows arrive last: the beams of the earlier batches contradict them.
    online = MixtureGPOccupancyMap(min_hit_frequency=0.2, random_state=0)
    half = X.shape[0] // 2
    online.partial_fit(X[:half], y[:half]).partial_fit(X[half:], y[half:])
    assert online.transient_hits_.shape == (X.shape[0],)
    assert online.transient_hits_[-6::2].all()
    assert not online.transient_hits_[y == 1][online._piece_hit].any()
    assert (online._piece_y == 1).sum() == (y == 1).sum() - online.transient_hits_.sum()


def test_bad_min_hit_frequency_is_rejected(office_with_a_passer_by):
    X, y, _ = office_with_a_passer_by
    with pytest.raises(ValueError, match="min_hit_frequency"):
        MixtureGPOccupancyMap(min_hit_frequency=1.5).fit(X, y)


@pytest.mark.parametrize("n_hits, left_out", [(3, True), (4, False)])
def test_a_cell_hit_more_than_a_few_times_keeps_its_hits(n_hits, left_out):
    # Forty beams cross the cell [0, 0.1)^2 and end in hits 2 m beyond it (one cell hit 40
    # times); n_hits more hits, of beams from elsewhere, lie in the crossed cell.
    y_beam = np.linspace(0.01, 0.09, 40)
    beams = np.column_stack([np.full(40, -2.0), y_beam, np.full(40, 2.0), y_beam])
    hits = np.tile([0.05, 0.05, 0.05, 0.05], (n_hits, 1))
    ends = np.column_stack([np.full(40, 2.0), y_beam, np.full(40, 2.0), y_beam])
    X = np.vstack([beams, hits, ends])
    y = np.r_[np.zeros(40, int), np.ones(n_hits + 40, int)]
    model = MixtureGPOccupancyMap(min_hit_frequency=0.2, random_state=0).fit(X, y)
    # n_hits / (n_hits + 40) is below 0.2 either way: the count decides.
    assert model.transient_hits_[40 : 40 + n_hits].all() == left_out
    assert not model.transient_hits_[40 + n_hits :].any()


def test_a_hit_at_exactly_the_bound_is_not_transient():
    # One hit and three beams through its cell: a frequency of exactly 1/4, not below 1/4.
    y_beam = np.array([0.02, 0.05, 0.08])
    beams = np.column_stack([np.full(3, -2.0), y_beam, np.full(3, 2.0), y_beam])
    X = np.vstack([beams, [[0.05, 0.05, 0.05, 0.05]]])
    counts = CellCounts(0.1, 2).add(X, np.array([False, False, False, True]))
    hit = X[3:, :2]
    assert [int(c[0]) for c in counts.counted(hit)] == [1, 3]
    assert not counts.transient(hit, 0.25, 3)[0]
    assert counts.transient(hit, 0.26, 3)[0]


def test_a_hit_with_a_length_is_counted_in_the_cell_of_its_end():
    # Hits that are segments (accepted with a warning) count where they end, as the
    # frequency grid counts them, and are looked up there.
    X = np.array(
        [
            [0.05, 0.05, 0.35, 0.05],
            [0.15, 0.05, 0.33, 0.02],
            [0.25, 0.05, 0.37, 0.08],
            [0.55, 0.05, 0.55, 0.05],
        ]
    )
    counts = CellCounts(0.1, 2).add(X, np.ones(4, dtype=bool))
    end_cells = np.floor(X[:, 2:] / 0.1)
    for points in (X[:, 2:], X[:, :2]):
        cells = np.floor(points / 0.1)
        expected = (cells[:, None] == end_cells[None]).all(axis=-1).sum(axis=1)
        hits, passes = counts.counted(points)
        np.testing.assert_array_equal(hits, expected)
        np.testing.assert_array_equal(passes, 0)
    assert counts.counted(X[:3, 2:])[0].tolist() == [3, 3, 3]


def test_a_map_without_a_lasting_hit_says_so():
    # Three hits in one cell that forty beams cross, and no other hit.
    y_beam = np.linspace(0.01, 0.09, 40)
    beams = np.column_stack([np.full(40, -2.0), y_beam, np.full(40, 2.0), y_beam])
    X = np.vstack([beams, np.tile([0.05, 0.05, 0.05, 0.05], (3, 1))])
    y = np.r_[np.zeros(40, int), np.ones(3, int)]
    with pytest.warns(UserWarning, match="Every hit was left out as transient"):
        MixtureGPOccupancyMap(random_state=0).fit(X, y)
    with pytest.warns(UserWarning, match="Every hit was left out as transient"):
        MixtureGPOccupancyMap(random_state=0).partial_fit(X, y, classes=[0, 1])
    # Kept, the hits make a map with an obstacle and no warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        model = MixtureGPOccupancyMap(min_hit_frequency=None, random_state=0).fit(X, y)
    assert model.predict_proba(X[-1:])[0, 1] > 0.5


def test_a_map_with_some_lasting_hits_does_not_say_every_hit_is_transient():
    # Three hits in a cell that forty beams cross (transient), and the forty hits of those
    # beams 2 m beyond it (lasting).
    y_beam = np.linspace(0.01, 0.09, 40)
    beams = np.column_stack([np.full(40, -2.0), y_beam, np.full(40, 2.0), y_beam])
    ends = np.column_stack([np.full(40, 2.0), y_beam, np.full(40, 2.0), y_beam])
    X = np.vstack([beams, np.tile([0.05, 0.05, 0.05, 0.05], (3, 1)), ends])
    y = np.r_[np.zeros(40, int), np.ones(43, int)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = MixtureGPOccupancyMap(min_hit_frequency=0.2, random_state=0).fit(X, y)
        model.partial_fit(X + 0.01, y)
    assert model.transient_hits_.any() and not model.transient_hits_[np.r_[y, y] == 1].all()
    assert not [w for w in caught if "Every hit was left out" in str(w.message)]


def _wall_and_passer_by(passer_first=False):
    """Forty beams cross the cell [0, 0.1)^2 to a wall of forty hits at x = 2; a passer-by
    of three hits in that cell (transient) is seen by three beams from below."""
    y_beam = np.linspace(0.01, 0.09, 40)
    wall = np.column_stack([np.full(40, 2.0), y_beam, np.full(40, 2.0), y_beam])
    beams = np.column_stack([np.full(40, -2.0), y_beam, np.full(40, 1.95), y_beam])
    passer = np.tile([0.05, 0.05, 0.05, 0.05], (3, 1))
    below = np.tile([0.05, -2.0, 0.05, 0.0], (3, 1))
    parts = [(passer, 1), (below, 0), (wall, 1), (beams, 0)]
    if not passer_first:
        parts = parts[2:] + parts[:2]
    X = np.vstack([rows for rows, _ in parts])
    y = np.concatenate([np.full(len(rows), label) for rows, label in parts])
    return X, y


def test_pieces_of_a_transient_hit_follow_the_lasting_hit_nearest_to_it():
    # The passer-by's hits come first: their index among the hits is not their index among
    # the lasting hits. The pieces of the beams that saw them follow the wall hit nearest.
    X, y = _wall_and_passer_by(passer_first=True)
    model = MixtureGPOccupancyMap(
        piece_assignment="beam", max_pieces_per_cell=None, random_state=0
    ).fit(X, y)
    transient = model.transient_hits_[y == 1]
    assert transient[:3].all() and not transient[3:].any()
    moved = np.flatnonzero(model._piece_beam_hit < 3)
    assert moved.size >= 3
    hits = model._hits
    nearest = np.linalg.norm(hits[3:] - hits[0], axis=1).min()
    np.testing.assert_allclose(
        np.linalg.norm(hits[model._piece_hit[moved]] - hits[0], axis=1), nearest
    )
    assert not transient[model._piece_hit].any()


def test_an_update_that_fails_leaves_the_counts_of_the_rows_seen(monkeypatch):
    # The counts of hits and passes are committed with the rest of an update: a batch whose
    # update fails after it was counted must not count against later hits.
    X, y = _wall_and_passer_by()
    model = MixtureGPOccupancyMap(min_hit_frequency=0.2, random_state=0).fit(X, y)
    cell = np.array([[0.05, 0.05]])
    before = model._cell_counts.counted(cell)
    assert before[0][0] == 3 and before[1][0] >= 40

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(MixtureGPOccupancyMap, "_refit_experts", interrupt)
    with pytest.raises(KeyboardInterrupt):
        model.partial_fit(X, y)
    for got, want in zip(model._cell_counts.counted(cell), before, strict=True):
        np.testing.assert_array_equal(got, want)


def test_a_map_without_a_lasting_hit_says_so_at_the_callers_line():
    # The warning names the line that called fit or partial_fit, not the mixture's own.
    y_beam = np.linspace(0.01, 0.09, 40)
    beams = np.column_stack([np.full(40, -2.0), y_beam, np.full(40, 2.0), y_beam])
    X = np.vstack([beams, np.tile([0.05, 0.05, 0.05, 0.05], (3, 1))])
    y = np.r_[np.zeros(40, int), np.ones(3, int)]
    model = MixtureGPOccupancyMap(random_state=0)
    # The fit, and an update of more beams (its own three hits would make the cell lasting).
    for fit, rows in ((model.fit, slice(None)), (model.partial_fit, slice(40))):
        with pytest.warns(UserWarning, match="Every hit was left out") as caught:
            fit(X[rows], y[rows])
        every = [w for w in caught if "Every hit was left out" in str(w.message)]
        assert every and {w.filename for w in every} == {__file__}


def test_counts_taken_in_chunks_equal_the_counts_taken_at_once(monkeypatch):
    import skoccmap._transient as transient

    X, y = _random_rows(np.random.default_rng(5), 2)
    at_once = CellCounts(0.1, 2).add(X, y == 1)
    monkeypatch.setattr(transient, "_CHUNK", 7)
    in_chunks = CellCounts(0.1, 2).add(X, y == 1)
    for name in ("keys", "hits", "passes"):
        np.testing.assert_array_equal(getattr(in_chunks, name), getattr(at_once, name))


@pytest.mark.parametrize("n_dims", [2, 3])
def test_counts_reach_as_far_as_the_keys_bits_and_no_further(n_dims):
    # Keys hold 62 // D bits an axis: cells up to 2**(62 // D - 1) - 1 either way from the
    # first data's are counted each on its own, never with another cell's hits; a cell one
    # further out is refused.
    reach = 2 ** (62 // n_dims - 1) - 1
    edge = np.vstack([reach * np.eye(n_dims), -reach * np.eye(n_dims)])
    edge = np.vstack([edge, np.full((1, n_dims), reach), np.full((1, n_dims), -reach)])
    inner = edge - np.sign(edge)
    # Cells of 1 m, the origin cell first; one hit in each edge cell, two in each inner one.
    hits = np.vstack([np.zeros((1, n_dims)), edge, inner, inner]) + 0.5
    counts = CellCounts(1.0, n_dims).add(np.hstack([hits, hits]), np.ones(len(hits), bool))
    found, passes = counts.counted(np.vstack([edge, inner]) + 0.5)
    np.testing.assert_array_equal(found, np.repeat([1, 2], len(edge)))
    assert not passes.any()
    for point in edge + np.sign(edge) + 0.5:
        with pytest.raises(ValueError, match="cannot be counted"):
            counts.counted(point[None])
