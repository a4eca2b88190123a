"""The reach of a kernel and the spatial index of the experts (skoccmap._reach)."""

import warnings

import numpy as np
import pytest
from sklearn.gaussian_process.kernels import RBF, DotProduct
from sklearn.gaussian_process.kernels import ConstantKernel as C

from skoccmap import _reach
from skoccmap._reach import ExpertReach, _segment_samples, _unique_rows, kernel_reach
from skoccmap.kernels import IntegralKernel


def _segment_distance(points, segments):
    """Exact distance from each point to each segment, (n_points, n_segments)."""
    dim = points.shape[1]
    a, d = segments[:, :dim], segments[:, dim:] - segments[:, :dim]
    w = points[:, None, :] - a[None]
    dd = np.einsum("ij,ij->i", d, d)
    t = np.where(dd > 0, np.einsum("pij,ij->pi", w, d) / np.where(dd > 0, dd, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(w - t[..., None] * d[None], axis=-1)


@pytest.mark.parametrize("tolerance", [1e-1, 1e-2, 1e-6])
@pytest.mark.parametrize(
    "kernel, factor",
    [
        (IntegralKernel(0.7), 1.0),
        (C(5.0) * IntegralKernel(0.7), 1.0),
        # An RBF over segment rows [start, end] sees a point at distance r at sqrt(2) r.
        (RBF(0.7), np.sqrt(0.5)),
    ],
)
def test_reach_of_a_squared_exponential(kernel, factor, tolerance):
    # exp(-r^2 / (2 l^2)) = tolerance at r = l sqrt(2 ln(1 / tolerance)); the probe grid
    # steps by 2.7 %, and the reach is the first probe beyond.
    exact = factor * 0.7 * np.sqrt(2 * np.log(1 / tolerance))
    reach = kernel_reach(kernel, 2, tolerance, extent=20.0)
    assert exact <= reach <= 1.03 * exact


def test_reach_of_an_anisotropic_kernel_is_its_longest():
    reach = kernel_reach(IntegralKernel([0.5, 2.0, 1.0]), 3, 1e-2, extent=30.0)
    exact = 2.0 * np.sqrt(2 * np.log(100))
    assert exact <= reach <= 1.03 * exact


def test_a_kernel_that_does_not_decay_reaches_everywhere():
    assert kernel_reach(DotProduct(1.0), 2, 1e-2, extent=10.0) == np.inf
    # Wider than ten times the data: no locality to use either.
    assert kernel_reach(RBF(1e3), 2, 1e-2, extent=10.0) == np.inf


def _random_experts(dim, seed, n_rows=400, n_experts=25):
    rng = np.random.default_rng(seed)
    start = rng.uniform(0, 20, size=(n_rows, dim))
    # Points, short pieces and long beams.
    length = rng.choice([0.0, 0.3, 1.0, 6.0], size=n_rows)
    direction = rng.normal(size=(n_rows, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    segments = np.hstack([start, start + length[:, None] * direction])
    return segments, rng.integers(0, n_experts, size=n_rows), n_experts


def _point_and_segment_queries(rng, n, n_segments, dim):
    """Starts and ends of ``n`` queries over the experts' area: points, the last
    ``n_segments`` of them segments."""
    points = rng.uniform(-2, 22, size=(n, dim))
    step = np.where(np.arange(n)[:, None] < n - n_segments, 0.0, rng.normal(size=(n, dim)))
    return points, points + step


@pytest.mark.parametrize("dim", [2, 3])
def test_candidates_hold_every_expert_within_reach_and_none_beyond_the_slack(dim):
    segments, expert, n_experts = _random_experts(dim, seed=dim)
    index = ExpertReach(segments, expert, n_experts, reach=2.0)
    points, ends = _point_and_segment_queries(np.random.default_rng(10 + dim), 300, 50, dim)
    queries = np.hstack([points, ends])
    query, cand = index.candidates(queries)
    got = np.zeros((300, n_experts), dtype=bool)
    got[query, cand] = True
    assert np.all(np.diff(query) >= 0)
    # Exact distance from each query (sampled finely along query segments) to each expert.
    t = np.linspace(0, 1, 201)
    dist = np.full((300, n_experts), np.inf)
    for i in range(300):
        along = points[i] + t[:, None] * (ends[i] - points[i])
        d = _segment_distance(along, segments).min(axis=0)
        np.minimum.at(dist[i], expert, d)
    assert np.all(got[dist <= 2.0])
    # Candidates lie within the reach plus the slack (and the query segment's length).
    length = np.linalg.norm(ends - points, axis=1)[:, None].repeat(n_experts, axis=1)
    assert np.all(dist[got] <= 2.0 + index.slack + length[got])
    # Not everything: the index does prune.
    assert got.mean() < 0.8


def test_candidates_of_a_query_do_not_depend_on_the_others():
    segments, expert, n_experts = _random_experts(2, seed=5)
    index = ExpertReach(segments, expert, n_experts, reach=1.5)
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 20, size=(200, 2))
    queries = np.hstack([points, points])
    query, cand = index.candidates(queries)
    sub = np.arange(0, 200, 7)
    q2, c2 = index.candidates(queries[sub])
    for j, i in enumerate(sub):
        np.testing.assert_array_equal(np.sort(c2[q2 == j]), np.sort(cand[query == i]))


@pytest.mark.parametrize("dim", [2, 3])
def test_a_query_segment_whose_middle_lies_beyond_every_block(dim):
    # A long beam from inside the map: its midpoint's block code sorts past the last one
    # in the table, which the lookup used to read past (IndexError).
    segments, expert, n_experts = _random_experts(dim, seed=7)
    index = ExpertReach(segments, expert, n_experts, reach=1.5)
    start = np.full(dim, 10.0)
    beams = [np.r_[start, start + np.eye(dim)[0] * length] for length in (50.0, 500.0)]
    queries = np.vstack([np.r_[start, start]] + beams)
    query, cand = index.candidates(queries)
    along = start + np.linspace(0, 1, 2001)[:, None] * (np.eye(dim)[0] * 50.0)
    near = np.unique(expert[_segment_distance(along, segments).min(axis=0) <= 1.5])
    assert set(near) <= set(cand[query == 1])
    assert set(cand[query == 1]) <= set(cand[query == 2])
    alone, alone_cand = index.candidates(queries[:1])
    np.testing.assert_array_equal(cand[query == 0], alone_cand)


def test_queries_absurdly_far_away_have_no_candidate_and_no_cast_warning():
    segments, expert, n_experts = _random_experts(2, seed=6)
    index = ExpertReach(segments, expert, n_experts, reach=1.5)
    far = np.array([[1e19, 1e19], [-1e300, 3.0], [5.0, 1e50]])
    queries = np.vstack([np.hstack([far, far]), [[5.0, 5.0, 5.0, 5.0]]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the int64 cast used to warn (and wrap around)
        query, cand = index.candidates(queries)
        order = index.spatial_order(queries)
    assert set(query.tolist()) <= {3}
    np.testing.assert_array_equal(np.sort(order), np.arange(4))


def test_infinite_reach_makes_every_expert_a_candidate():
    segments, expert, n_experts = _random_experts(2, seed=1)
    index = ExpertReach(segments, expert, n_experts, reach=np.inf)
    query, cand = index.candidates(np.zeros((3, 4)))
    assert query.tolist() == np.repeat([0, 1, 2], n_experts).tolist()
    assert cand.tolist() == list(range(n_experts)) * 3
    np.testing.assert_array_equal(index.spatial_order(np.zeros((3, 4))), [0, 1, 2])


def test_spatial_order_is_a_permutation_grouping_blocks():
    segments, expert, n_experts = _random_experts(2, seed=2)
    index = ExpertReach(segments, expert, n_experts, reach=1.0)
    rng = np.random.default_rng(3)
    points = rng.uniform(0, 20, size=(500, 2))
    order = index.spatial_order(np.hstack([points, points]))
    np.testing.assert_array_equal(np.sort(order), np.arange(500))
    # Consecutive queries are near: far closer than in the given (random) order.
    step = np.linalg.norm(np.diff(points[order], axis=0), axis=1)
    assert np.median(step) < 0.25 * np.median(np.linalg.norm(np.diff(points, axis=0), axis=1))


def test_chunks_of_consecutive_queries_are_compact_regions():
    # The map is predicted chunk by chunk in this order: a chunk of a few hundred queries
    # (of 20000 over a map 20 reaches wide) is a patch a few reaches across, not a strip
    # across the map.
    segments, expert, n_experts = _random_experts(2, seed=2)
    index = ExpertReach(segments, expert, n_experts, reach=1.0)
    points = np.random.default_rng(4).uniform(0, 20, size=(20000, 2))
    order = index.spatial_order(np.hstack([points, points]))
    chunks = points[order].reshape(-1, 250, 2)
    across = np.ptp(chunks, axis=1).max(axis=1)
    assert np.median(across) < 5.0


def test_default_origin_is_the_smallest_coordinate_of_either_end():
    segments, expert, n_experts = _random_experts(3, seed=3)
    segments[:, 3:] -= 1.0  # ends below the starts on every axis
    index = ExpertReach(segments, expert, n_experts, reach=1.5)
    np.testing.assert_array_equal(
        index.origin, np.minimum(segments[:, :3], segments[:, 3:]).min(axis=0)
    )
    assert all(cells.min() >= 0 for cells in index._cells + index._centres if len(cells))


@pytest.mark.parametrize("dim", [2, 3])
def test_building_the_index_in_batches_changes_nothing(dim, monkeypatch):
    import skoccmap._reach as reach_module

    segments, expert, n_experts = _random_experts(dim, seed=4)
    whole = ExpertReach(segments, expert, n_experts, reach=1.5)
    monkeypatch.setattr(reach_module, "_BATCH", 64)
    batched = ExpertReach(segments, expert, n_experts, reach=1.5)
    np.testing.assert_array_equal(batched.cell_expert, whole.cell_expert)
    np.testing.assert_array_equal(batched.tree.data, whole.tree.data)
    np.testing.assert_array_equal(batched.centre_expert, whole.centre_expert)
    np.testing.assert_array_equal(batched.centre_tree.data, whole.centre_tree.data)
    np.testing.assert_array_equal(batched._table_codes, whole._table_codes)
    np.testing.assert_array_equal(batched._table_experts, whole._table_experts)
    queries = np.hstack([segments[:, :dim], segments[:, :dim]]) + 0.3
    for got, want in zip(batched.candidates(queries), whole.candidates(queries), strict=True):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("dim", [2, 3])
def test_updated_index_equals_a_rebuilt_one(dim):
    segments, expert, n_experts = _random_experts(dim, seed=4)
    index = ExpertReach(segments, expert, n_experts, reach=1.5)
    # Rows added to experts 3 and 7 and to a new expert, partly below the grid's origin;
    # experts renumbered (reversed).
    rng = np.random.default_rng(0)
    extra = segments[:50] + rng.normal(0, 3, size=(50, 2 * dim)) - 2.0
    number = np.r_[np.arange(n_experts)[::-1], n_experts]
    all_segments = np.vstack([segments, extra])
    all_expert = number[np.r_[expert, np.full(25, 3), np.full(25, n_experts)]]
    previous = np.full(n_experts + 1, -1)
    previous[number[:n_experts]] = np.arange(n_experts)
    touched = [number[3], number[7], n_experts]
    updated = index.updated(all_segments, all_expert, n_experts + 1, touched, previous)
    rebuilt = ExpertReach(all_segments, all_expert, n_experts + 1, 1.5, origin=index.origin)
    names = ("cell_expert", "centre_expert", "_table_codes", "_table_experts", "_table_start")
    for name in names:
        np.testing.assert_array_equal(getattr(updated, name), getattr(rebuilt, name))
    np.testing.assert_array_equal(updated.tree.data, rebuilt.tree.data)
    np.testing.assert_array_equal(updated.centre_tree.data, rebuilt.centre_tree.data)
    assert updated.max_candidates == rebuilt.max_candidates
    queries = np.hstack([all_segments[:, :dim], all_segments[:, :dim]]) + 0.3
    queries[::5, dim:] += 0.5  # some query segments
    for got, want in zip(updated.candidates(queries), rebuilt.candidates(queries), strict=True):
        np.testing.assert_array_equal(got, want)
    pairs = updated.candidates(queries)
    np.testing.assert_array_equal(
        updated.within_reach(queries, *pairs), rebuilt.within_reach(queries, *pairs)
    )
    np.testing.assert_array_equal(
        updated.coverage(queries, *pairs, 0.4), rebuilt.coverage(queries, *pairs, 0.4)
    )
    # The old index is unchanged.
    assert index.n_experts == n_experts and index.cell_expert.max() == n_experts - 1


@pytest.mark.parametrize("dim", [2, 3])
def test_block_table_is_the_stencils_around_every_cell(dim):
    from skoccmap._reach import _codes

    segments, expert, n_experts = _random_experts(dim, seed=6)
    index = ExpertReach(segments, expert, n_experts, reach=1.5)
    for k in range(n_experts):
        # Every cell's block plus every offset of the stencil of its position in it.
        block, sub = np.divmod(index._cells[k], 2)
        code = sub @ (1 << np.arange(dim)[::-1])
        blocks = np.concatenate(
            [(block[code == c, None, :] + s[None]).reshape(-1, dim) for c, s in
             enumerate(index._stencils)]
        )  # fmt: skip
        np.testing.assert_array_equal(index._blocks[k], np.unique(_codes(blocks)))


@pytest.mark.parametrize("span", [5, 2**40])
def test_unique_rows_matches_numpy(span):
    # Coded by one integer per row, or numpy's row-wise unique where codes would overflow.
    rng = np.random.RandomState(0)
    keys = rng.randint(-3, 4, size=(500, 3)).astype(np.int64)
    keys[:, 1] *= span
    np.testing.assert_array_equal(_unique_rows(keys), np.unique(keys, axis=0))
    assert _unique_rows(keys[:0]).shape == (0, 3)


@pytest.mark.parametrize("dim", [2, 3])
def test_a_reach_far_below_the_segments_keeps_the_index_small_and_exact(dim):
    # A kernel of micrometre length scale on metre-long segments: a grid of reach / 8 would
    # sample millions of points per segment (tens of GiB in 3-D). The grid is coarser
    # instead, and still holds every expert within reach.
    segments, expert, n_experts = _random_experts(dim, seed=7)
    reach = 1e-5
    index = ExpertReach(segments, expert, n_experts, reach=reach)
    assert index.reach == reach and index.scale > 1e3 * reach
    assert len(index.cell_expert) <= 70 * len(segments)
    rng = np.random.default_rng(1)
    # Queries on the segments (within reach of their expert) and off them.
    row = rng.integers(0, len(segments), size=100)
    t = rng.uniform(size=(100, 1))
    on = segments[row, :dim] + t * (segments[row, dim:] - segments[row, :dim])
    points = np.vstack([on, rng.uniform(0, 20, size=(100, dim))])
    queries = np.hstack([points, points])
    query, cand = index.candidates(queries)
    dist = np.full((200, n_experts), np.inf)
    np.minimum.at(dist.T, expert, _segment_distance(points, segments).T)
    got = np.zeros((200, n_experts), dtype=bool)
    got[query, cand] = True
    assert np.all(got[dist <= reach])
    keep = index.within_reach(queries, query, cand)
    assert np.all(keep[dist[query, cand] <= reach])
    # Exact up to the cells' size: a kept cell centre within reach + grown of the query,
    # its data within grown of the centre.
    assert np.all(dist[query[keep], cand[keep]] <= reach + 2 * index._grown)


def test_the_grid_follows_the_reach_where_the_reach_is_long_enough():
    segments, expert, n_experts = _random_experts(2, seed=8)
    index = ExpertReach(segments, expert, n_experts, reach=1.5)
    assert index.scale == 1.5 and index.cell == pytest.approx(1.5 / 8)


@pytest.mark.parametrize("width", [0.4, 1.0])
@pytest.mark.parametrize("all_cells", [True, False], ids=["all-cells", "per-expert"])
@pytest.mark.parametrize("dim", [2, 3])
def test_coverage_is_the_gaussian_weighted_count_of_the_midpoint_cells(
    dim, all_cells, width, monkeypatch
):
    # Few queries search all cells at once, many each expert's cells: the same coverage.
    monkeypatch.setattr(_reach, "_COVERAGE_ALL_CELLS", 10**9 if all_cells else 0)
    monkeypatch.setattr(_reach, "_CELLS_PER_EXPERT_SEARCH", 10**9)
    segments, expert, n_experts = _random_experts(dim, seed=20 + dim)
    index = ExpertReach(segments, expert, n_experts, reach=2.0)
    rng = np.random.default_rng(30 + dim)
    points, ends = _point_and_segment_queries(rng, 200, 30, dim)
    queries = np.hstack([points, ends])
    query, cand = index.candidates(queries)
    shuffle = rng.permutation(query.size)
    got = np.empty(query.size)
    got[shuffle] = index.coverage(queries, query[shuffle], cand[shuffle], width)
    # Centres of the cells holding the midpoints of each expert's segments, their
    # distance to the query's midpoint less half its length, weighted up to three widths
    # (1.2 at width 0.4) or, where that is farther (3 at width 1.0), up to the reach (2)
    # less half a cell's diagonal.
    cut = min(3 * width, 2.0 - 0.5 * index.cell * np.sqrt(dim))
    mids, half = 0.5 * (points + ends), 0.5 * np.linalg.norm(ends - points, axis=1)
    segment_mids = 0.5 * (segments[:, :dim] + segments[:, dim:])
    expected, terms = np.empty(query.size), np.empty(query.size)
    for j, (i, k) in enumerate(zip(query, cand, strict=True)):
        cells = np.unique(
            np.floor((segment_mids[expert == k] - index.origin) / index.cell), axis=0
        )
        centres = index.origin + (cells + 0.5) * index.cell
        d = np.linalg.norm(centres - mids[i], axis=1)
        d = np.maximum(d[d <= cut + half[i]] - half[i], 0.0)
        expected[j] = np.sum(np.exp(-0.5 * (d / width) ** 2))
        terms[j] = d.size
    # Each weight is rounded to a whole _COVER_UNIT (so that sums are exact): within half
    # a unit per cell summed.
    error = np.abs(got - expected)
    assert np.all(error <= 0.5 * _reach._COVER_UNIT * terms + 1e-12 * expected)
    assert np.any(got > 0) and np.any(got == 0)
    # Experts taken in threads write their own pairs: the same coverage, bit for bit.
    # (One search of all cells takes no threads.)
    threaded = np.empty(query.size)
    threaded[shuffle] = index.coverage(queries, query[shuffle], cand[shuffle], width, n_jobs=2)
    np.testing.assert_array_equal(threaded, got)


@pytest.mark.parametrize("dim", [2, 3])
def test_covering_lists_exactly_the_candidates_of_positive_coverage(dim, monkeypatch):
    # The pairs of positive coverage found from the cells alone, searched in batches sized
    # to find about 2000 cells (the first of 16 queries): those of the coverage over every
    # candidate, with its values to the bit.
    monkeypatch.setattr(_reach, "_COVERING_PAIRS", 2000)
    monkeypatch.setattr(_reach, "_COVERING_FIRST", 16)
    segments, expert, n_experts = _random_experts(dim, seed=50 + dim)
    index = ExpertReach(segments, expert, n_experts, reach=2.0)
    rng = np.random.default_rng(60 + dim)
    points, ends = _point_and_segment_queries(rng, 200, 30, dim)
    queries = np.hstack([np.vstack([points, points + 100.0]), np.vstack([ends, ends + 100.0])])
    query, cand = index.candidates(queries)
    cover = index.coverage(queries, query, cand, 0.4)
    positive = cover > 0
    got = index.covering(queries, 0.4)
    expected = (query[positive], cand[positive], cover[positive])
    for array, want in zip(got, expected, strict=True):
        np.testing.assert_array_equal(array, want)
    # Queries near the data are covered, and those 100 m away not.
    assert np.unique(got[0]).size > 20 and got[0].max() < 200


def test_covering_is_empty_without_cells_or_queries():
    segments = np.array([[-5.0, 0.0, 5.0, 0.0]])
    queries = np.zeros((2, 4))
    for index, q in [
        (ExpertReach(segments, np.array([0]), 1, reach=np.inf), queries),
        (ExpertReach(segments, np.array([0]), 1, reach=2.0), queries[:0]),
    ]:
        query, cand, cover = index.covering(q, 0.4)
        assert query.size == cand.size == cover.size == 0
        assert query.dtype == cand.dtype == np.intp


def test_tree_of_all_midpoint_cells_is_built_once_searches_apart_cost_as_much(monkeypatch):
    # Ski rental: a few queries search each expert's cells apart until that has cost as
    # much as building the tree of all cells, then the tree; the coverage is the same.
    segments, expert, n_experts = _random_experts(2, seed=40)
    index = ExpertReach(segments, expert, n_experts, reach=2.0)
    n_cells = index.centre_expert.size
    rng = np.random.default_rng(41)
    points = rng.uniform(0, 10, (30, 2))
    queries = np.hstack([points, points])
    query, cand = index.candidates(queries)
    per_call = np.unique(cand).size
    # Three calls' searches apart pay for the tree.
    monkeypatch.setattr(_reach, "_CELLS_PER_EXPERT_SEARCH", int(np.ceil(n_cells / (3 * per_call))))
    covers, built = [], []
    for _ in range(4):
        covers.append(index.coverage(queries, query, cand, 0.4))
        built.append(index._centre_tree is not None)
    assert built == [False, False, True, True]
    for cover in covers[1:]:
        np.testing.assert_array_equal(cover, covers[0])
    assert np.any(covers[0] > 0)


def test_coverage_grows_with_the_data_near_the_query():
    # Two experts: one segment through the query, one segment two widths away.
    segments = np.array([[-5.0, 0.0, 5.0, 0.0], [-5.0, 0.8, 5.0, 0.8]])
    index = ExpertReach(segments, np.array([0, 1]), 2, reach=2.0)
    cover = index.coverage(np.zeros((2, 4)), np.array([0, 0]), np.array([0, 1]), 0.4)
    assert cover[0] > 3 * cover[1] > 0
    # An infinite reach indexes no cells: no coverage.
    index = ExpertReach(segments, np.array([0, 1]), 2, reach=np.inf)
    cover = index.coverage(np.zeros((1, 4)), np.array([0]), np.array([1]), 0.4)
    np.testing.assert_array_equal(cover, [0.0])


def test_segment_samples_reach_both_ends_and_cover_the_segment():
    segments = np.array([[0.0, 0.0, 1.05, 0.0], [2.0, 1.0, 2.0, 1.0], [0.0, 0.0, 0.3, 0.4]])
    samples, row = _segment_samples(segments, 0.2)
    for k, (start, end) in enumerate(zip(segments[:, :2], segments[:, 2:], strict=True)):
        mine = samples[row == k]
        np.testing.assert_array_equal(mine[0], start)
        np.testing.assert_allclose(mine[-1], end, atol=1e-15)
        along = start + np.linspace(0, 1, 1001)[:, None] * (end - start)
        gaps = np.linalg.norm(along[:, None, :] - mine[None, :, :], axis=2).min(axis=1)
        assert gaps.max() <= 0.1 + 1e-12


def _on_segments(segments, expert, n_t):
    """Points at ``n_t`` even steps along every segment, with their segment's expert."""
    dim = segments.shape[1] // 2
    t = np.linspace(0.0, 1.0, n_t)[None, :, None]
    a, b = segments[:, None, :dim], segments[:, None, dim:]
    return (a + t * (b - a)).reshape(-1, dim), np.repeat(expert, n_t)


def _holds(query, cand, n_queries, n_experts):
    got = np.zeros((n_queries, n_experts), dtype=bool)
    got[query, cand] = True
    return got


def test_threads_pay_from_enough_pairs_in_all_and_per_expert():
    # At least _THREADED_PAIRS pairs, and at least _THREADED_PAIRS_PER_EXPERT per expert.
    pairs, per_expert = _reach._THREADED_PAIRS, _reach._THREADED_PAIRS_PER_EXPERT
    assert not _reach.threads_pay(pairs - 1, 1)
    assert _reach.threads_pay(pairs, 1)
    many = 4 * pairs // per_expert  # experts enough that the per-expert count decides
    assert not _reach.threads_pay(per_expert * many - 1, many)
    assert _reach.threads_pay(per_expert * many, many)


class _MexicanHat:
    """(1 - r^2) exp(-r^2 / 2) of the distance r (in length scales) between the rows'
    starts: a kernel with a negative lobe, whose magnitude reaches 2 exp(-3/2) at r^2 = 3."""

    def __init__(self, length_scale):
        self.length_scale = length_scale

    def __call__(self, X, Y=None):
        Y = X if Y is None else Y
        dim = X.shape[1] // 2
        r2 = np.sum((X[:, None, :dim] - Y[None, :, :dim]) ** 2, axis=-1) / self.length_scale**2
        return (1.0 - r2) * np.exp(-0.5 * r2)


def test_reach_of_a_kernel_with_a_negative_lobe_is_past_the_lobe():
    from scipy.optimize import brentq

    # |k| falls below 0.1 k(0) for good on the negative lobe, beyond its minimum at sqrt(3).
    tolerance, length_scale = 0.1, 0.7
    exact = length_scale * brentq(
        lambda r: (r**2 - 1.0) * np.exp(-0.5 * r**2) - tolerance, np.sqrt(3.0), 10.0
    )
    reach = kernel_reach(_MexicanHat(length_scale), 2, tolerance, extent=20.0)
    assert exact <= reach <= 1.03 * exact


@pytest.mark.parametrize("dim", [2, 3])
def test_block_codes_are_ordered_distinct_and_minus_one_out_of_range(dim):
    from skoccmap._reach import _codes

    # Coordinates in [-2**20, 2**20) are coded (non-negative, ordered like the blocks
    # lexicographically), all others are -1.
    half = 2 ** (_reach._CODE_BITS - 1)
    edges = np.array([-(2**40), -half - 1, -half, -half + 1, -1, 0, 1, half - 1, half, 2**40])
    blocks = np.stack(np.meshgrid(*[edges] * dim, indexing="ij"), axis=-1).reshape(-1, dim)
    code = _codes(blocks)
    inside = np.all((blocks >= -half) & (blocks < half), axis=1)
    np.testing.assert_array_equal(code[~inside], -1)
    # The meshgrid lists the blocks in lexicographic order: their codes strictly increase.
    assert code[inside][0] >= 0 and np.all(np.diff(code[inside]) > 0)


@pytest.mark.parametrize("dim", [2, 3])
def test_query_segments_crossing_data_on_a_grid_coarser_than_the_reach(dim):
    # Data segments 30 m long set a grid of cells far coarser than a reach of 1 mm (the
    # samples along a segment lie a cell apart). A query segment 2 mm long crossing a data
    # segment anywhere along it has that segment's data within reach (distance 0), so its
    # expert is a candidate and within reach, between samples too.
    rng = np.random.default_rng(dim)
    n = 10
    start = rng.uniform(0, 20, size=(n, dim))
    direction = rng.normal(size=(n, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    segments = np.hstack([start, start + 30.0 * direction])
    index = ExpertReach(segments, np.arange(n), n, reach=1e-3)
    assert index.cell > 100 * index.reach
    row = np.repeat(np.arange(n), 1001)
    t = np.tile(np.linspace(0.0, 1.0, 1001), n)[:, None]
    on = start[row] + 30.0 * t * direction[row]
    # Across the data segment: a random direction less its component along the segment.
    across = rng.normal(size=(len(row), dim))
    across -= np.einsum("ij,ij->i", across, direction[row])[:, None] * direction[row]
    across *= 1e-3 / np.linalg.norm(across, axis=1, keepdims=True)
    queries = np.hstack([on - across, on + across])
    query, cand = index.candidates(queries)
    assert np.all(_holds(query, cand, len(queries), n)[np.arange(len(queries)), row])
    assert np.all(index.within_reach(queries, np.arange(len(queries)), row))


def test_unique_rows_whose_codes_would_overflow_int64():
    # Three columns of spans near 2**28 (84 bits together): numpy's row-wise unique.
    rng = np.random.RandomState(1)
    keys = rng.randint(-3, 4, size=(500, 3)).astype(np.int64) * 2**26
    np.testing.assert_array_equal(_unique_rows(keys), np.unique(keys, axis=0))


@pytest.mark.parametrize("dim", [2, 3])
def test_points_far_apart_for_a_tiny_reach_are_indexed_and_pruned(dim):
    # Point data (no segment length to set the grid) 20 m across and a reach of 1e-7 m:
    # a grid of reach / 8 would put most points beyond the blocks a code can hold. Each
    # point is within reach of itself, and its candidates within reach + slack.
    rng = np.random.default_rng(50 + dim)
    points = rng.uniform(0, 20, size=(200, dim))
    expert = rng.integers(0, 10, size=200)
    index = ExpertReach(np.hstack([points, points]), expert, 10, reach=1e-7)
    queries = np.hstack([points, points])
    query, cand = index.candidates(queries)
    got = _holds(query, cand, 200, 10)
    assert np.all(got[np.arange(200), expert])
    dist = np.full((200, 10), np.inf)
    np.minimum.at(dist.T, expert, np.linalg.norm(points[:, None] - points[None], axis=-1))
    assert np.all(dist[got] <= index.reach + index.slack)
    np.testing.assert_array_equal(
        index.within_reach(queries, np.arange(200), expert), np.ones(200, dtype=bool)
    )


def test_all_data_at_one_point_with_a_zero_reach():
    segments = np.tile([1.0, 2.0, 1.0, 2.0], (6, 1))
    expert = np.array([0, 0, 2, 2, 2, 0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        index = ExpertReach(segments, expert, 3, reach=0.0)
        query, cand = index.candidates(np.array([[1.0, 2.0, 1.0, 2.0], [9.0, 9.0, 9.0, 9.0]]))
    # The point's experts (1 has no data), nothing far away.
    np.testing.assert_array_equal(query, [0, 0])
    np.testing.assert_array_equal(cand, [0, 2])


def test_candidates_stay_within_the_reach_plus_the_slack_on_a_dense_grid():
    # Short segments, one expert each, and point queries every sixteenth of a reach: a
    # candidate's data lie within reach + slack (the block's diagonal, and a cell's
    # half-diagonal and half sample spacing on either side), which the grid comes near.
    rng = np.random.default_rng(60)
    n, reach = 200, 1.0
    start = rng.uniform(0, 10, (n, 2))
    direction = rng.normal(size=(n, 2))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    segments = np.hstack([start, start + rng.uniform(0, 0.3, (n, 1)) * direction])
    index = ExpertReach(segments, np.arange(n), n, reach, origin=np.zeros(2))
    g = np.arange(-1.0, 11.0, reach / 16) + 1e-9
    points = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    query, cand = index.candidates(np.hstack([points, points]))
    a, d = segments[cand, :2], segments[cand, 2:] - segments[cand, :2]
    w = points[query] - a
    t = np.clip(np.einsum("ij,ij->i", w, d) / np.einsum("ij,ij->i", d, d).clip(1e-300), 0, 1)
    dist = np.linalg.norm(w - t[:, None] * d, axis=1)
    assert np.all(dist <= reach + index.slack)
    assert dist.max() > reach + 0.75 * index.slack


@pytest.mark.parametrize("dim", [2, 3])
def test_data_and_queries_below_the_origin_are_indexed_exactly(dim):
    # The grid's origin in the middle of the data (as after updates with data below it),
    # and a reach short against the cells, so that a cell off by one loses data in reach:
    # every point of every segment is within reach of its expert.
    segments, expert, n_experts = _random_experts(dim, seed=70 + dim, n_rows=200)
    index = ExpertReach(segments, expert, n_experts, reach=1e-5, origin=np.full(dim, 10.0))
    assert index.cell > 1e3 * index.reach
    points, own = _on_segments(segments, expert, 41)
    queries = np.hstack([points, points])
    query, cand = index.candidates(queries)
    got = _holds(query, cand, len(points), n_experts)
    assert np.all(got[np.arange(len(points)), own])
    keep = index.within_reach(queries, np.arange(len(points)), own)
    np.testing.assert_array_equal(keep, np.ones(len(points), dtype=bool))


def test_updated_index_keeps_the_grid_of_a_reach_too_short_to_set_it():
    # The grid is set by the segments' mean length (the reach is far shorter); an update
    # adds an expert of long beams, which would set a coarser grid: the update keeps the
    # old one, on which the unchanged experts' cells lie, and loses no data in reach.
    dim = 2
    segments, expert, n_experts = _random_experts(dim, seed=80, n_rows=200)
    index = ExpertReach(segments, expert, n_experts, reach=1e-5)
    rng = np.random.default_rng(81)
    start = rng.uniform(0, 20, (20, dim))
    beams = np.hstack([start, start + [60.0, 0.0]])
    all_segments = np.vstack([segments, beams])
    all_expert = np.r_[expert, np.full(20, n_experts)]
    updated = index.updated(
        all_segments, all_expert, n_experts + 1, [n_experts], np.r_[np.arange(n_experts), -1]
    )
    assert updated.scale == index.scale
    points, own = _on_segments(all_segments, all_expert, 21)
    queries = np.hstack([points, points])
    query, cand = updated.candidates(queries)
    got = _holds(query, cand, len(points), n_experts + 1)
    assert np.all(got[np.arange(len(points)), own])
    assert np.all(updated.within_reach(queries, np.arange(len(points)), own))


def test_an_expert_without_data_is_never_within_reach():
    segments, expert, _ = _random_experts(2, seed=90, n_experts=4)
    index = ExpertReach(segments, expert, 5, reach=1.5)  # expert 4 has no rows
    on = np.hstack([segments[:3, :2], segments[:3, :2]])
    keep = index.within_reach(on, np.array([0, 1, 2, 0]), np.r_[expert[:3], 4])
    np.testing.assert_array_equal(keep, [True, True, True, False])
    query, cand = index.candidates(on)
    assert 4 not in cand


def test_within_reach_of_query_segments_matches_exact_distances():
    # Points and segments up to 8 reaches long, each against every expert, with experts
    # searched for queries of different lengths at once: kept where the exact distance is
    # within the reach, dropped beyond reach + 2 * grown (+ the half-length, measured from
    # the query's midpoint).
    segments, expert, n_experts = _random_experts(2, seed=100)
    reach = 1.0
    index = ExpertReach(segments, expert, n_experts, reach=reach)
    rng = np.random.default_rng(101)
    n = 60
    start = rng.uniform(-2, 22, size=(n, 2))
    length = np.where(np.arange(n) % 3 == 0, 0.0, rng.uniform(0, 8, n))
    angle = rng.uniform(0, 2 * np.pi, n)
    end = start + length[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    queries = np.hstack([start, end])
    query, cand = np.repeat(np.arange(n), n_experts), np.tile(np.arange(n_experts), n)
    keep = index.within_reach(queries, query, cand)
    # Distance from query segments, sampled every reach / 100 (no shorter than the exact).
    dist = np.full((n, n_experts), np.inf)
    for i in range(n):
        along = start[i] + np.linspace(0, 1, 801)[:, None] * (end[i] - start[i])
        np.minimum.at(dist[i], expert, _segment_distance(along, segments).min(axis=0))
    mid = np.full((n, n_experts), np.inf)
    np.minimum.at(mid.T, expert, _segment_distance(0.5 * (start + end), segments).T)
    assert np.any(~keep) and np.any(keep & (length[query] > 0))
    assert np.all(keep[dist[query, cand] <= reach])
    assert np.all(
        mid[query[keep], cand[keep]] <= reach + 2 * index._grown + length[query[keep]] / 2
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_candidates_are_sorted_by_query_then_expert(dim):
    segments, expert, n_experts = _random_experts(dim, seed=110 + dim, n_experts=60)
    index = ExpertReach(segments, expert, n_experts, reach=3.0)
    points, ends = _point_and_segment_queries(np.random.default_rng(111), 200, 20, dim)
    query, cand = index.candidates(np.hstack([points, ends]))
    assert np.all((np.diff(query) > 0) | ((np.diff(query) == 0) & (np.diff(cand) > 0)))
    assert np.bincount(query).max() > 16  # lists longer than a sort's insertion runs


def test_max_candidates_bounds_the_candidates_of_every_point_query():
    # Chunks of queries are sized by it: no point query has more candidates.
    segments, expert, n_experts = _random_experts(2, seed=120)
    index = ExpertReach(segments, expert, n_experts, reach=1.5)
    g = np.arange(-2.0, 22.0, index.block / 2)
    points = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    query, _ = index.candidates(np.hstack([points, points]))
    counts = np.bincount(query, minlength=len(points))
    assert counts.max() <= index.max_candidates
    assert counts.min() < counts.max()


def test_tree_of_all_midpoint_cells_is_built_once_searches_cost_exactly_as_much(monkeypatch):
    # Searches apart that have cost exactly as much as the tree (one expert searched,
    # costed at all the cells) pay for it at once.
    segments, expert, n_experts = _random_experts(2, seed=130)
    index = ExpertReach(segments, expert, n_experts, reach=2.0)
    monkeypatch.setattr(_reach, "_CELLS_PER_EXPERT_SEARCH", index.centre_expert.size)
    queries = np.hstack([segments[:5, :2], segments[:5, :2]])
    index.coverage(queries, np.arange(5), np.full(5, expert[0]), 0.4)
    assert index._centre_tree is not None


def test_a_pair_with_coverage_is_within_reach():
    # The mixture takes a pair with positive coverage as within reach without searching.
    # A segment shorter than a cell, from cell (0, 1) to cell (1, 0): its ends are its only
    # samples, its midpoint lies in cell (0, 0). Queries on the diagonal below cell (0, 0),
    # up to a cell beyond reach + grown from its centre, with a width whose three widths
    # exceed the reach: wherever covered, within reach.
    reach = 2.0
    cell = reach * _reach._CELL
    segments = np.array([[0.4, 1.05, 1.05, 0.4], [120.0, 120.0, 120.0, 120.0]]) * cell
    index = ExpertReach(segments, np.array([0, 1]), 2, reach, origin=np.zeros(2))
    assert index.cell == cell
    distance = np.linspace(reach - cell, reach + index._grown + cell, 101)
    points = 0.5 * cell - distance[:, None] / np.sqrt(2) * np.ones(2)
    queries = np.hstack([points, points])
    pairs = np.arange(101), np.zeros(101, dtype=int)
    cover = index.coverage(queries, *pairs, width=reach)
    near = index.within_reach(queries, *pairs)
    assert cover[0] > 0 and near[0]
    np.testing.assert_array_equal(near[cover > 0], True)
