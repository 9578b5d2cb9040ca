"""Block/level layout: known answers from Qiu et al. and exact round trips."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tiler.errors import LayoutError
from tiler.layout import (
    decompose,
    grid_side,
    level_end,
    level_index,
    level_size,
    level_start,
    order_index,
    parse_block_size,
    reconstruct,
    sequence_index,
    subgrid,
    vertex_offset,
)


def test_qiu_figure_4_vertex_3_3():
    assert vertex_offset(2, 3, 3) == (2, 12, 21)


@pytest.mark.parametrize(
    ("level", "start", "end", "size"),
    [
        (0, 0, 3, 4),
        (1, 4, 8, 5),
        (2, 9, 24, 16),
        (3, 25, 80, 56),
        (10, 513**2, 1025**2 - 1, 787456),
    ],
    ids=["L0", "L1", "L2", "L3", "L10"],
)
def test_offsets_equations_1_and_2(level, start, end, size):
    assert (level_start(level), level_end(level), level_size(level)) == (start, end, size)


def test_qiu_5x5_tables():
    expected_levels = np.array(
        [[0, 2, 1, 2, 0], [2, 2, 2, 2, 2], [1, 2, 1, 2, 1], [2, 2, 2, 2, 2], [0, 2, 1, 2, 0]]
    )
    np.testing.assert_array_equal(level_index(2), expected_levels)
    # order is the row-major rank among each level's new vertices
    assert order_index(2)[0, 0] == 0 and order_index(2)[4, 4] == 3
    assert order_index(2)[2, 2] == 2  # level 1: (0,2),(2,0),(2,2),(2,4),(4,2)


def _reference_tables(k: int) -> tuple[np.ndarray, np.ndarray]:
    """The tables by their definitions: the first level whose grid holds a vertex (trailing
    zeros in int64), and the row-major rank among each level's vertices (a mask per level)."""
    side = grid_side(k)
    tz = np.array([k if v == 0 else (v & -v).bit_length() - 1 for v in range(side)])
    lev = k - np.minimum(np.minimum(tz[:, None], tz[None, :]), k)
    order = np.zeros((side, side), dtype=np.int64)
    for i in range(k + 1):
        m = lev == i
        order[m] = np.arange(int(m.sum()))
    return lev, order


@pytest.mark.parametrize("k", [*range(1, 12), 13])
def test_tables_equal_their_definitions(k):
    """The uint8 level table and the strided order table equal the definitions, dtypes too;
    a moved vertex in either reference is told apart (the comparison can fail)."""
    lev, order = _reference_tables(k)
    assert level_index(k).dtype == np.uint8 and order_index(k).dtype == np.int32
    np.testing.assert_array_equal(level_index(k), lev)
    np.testing.assert_array_equal(order_index(k), order)
    order[1, 0], order[0, 1] = order[0, 1], order[1, 0]  # two level-k vertices swapped
    assert not np.array_equal(order_index(k), order)
    lev[0, 1] -= 1
    assert not np.array_equal(level_index(k), lev)
    assert not level_index(k).flags.writeable and not order_index(k).flags.writeable


@pytest.mark.parametrize("k", range(1, 11))
def test_sequence_index_is_a_permutation(k):
    seq = sequence_index(k).ravel()
    np.testing.assert_array_equal(np.sort(seq), np.arange(grid_side(k) ** 2))
    for i in range(k + 1):
        assert (level_index(k) == i).sum() == level_size(i)


@pytest.mark.parametrize(("size", "k"), [(3, 1), (5, 2), (65, 6), (1025, 10), (32769, 15)], ids=str)
def test_parse_block_size_accepts(size, k):
    assert parse_block_size(size) == k


@pytest.mark.parametrize("size", [0, 1, 2, 4, 64, 1024, 1026, 65537 + 1, -5, 2.5, "65", True])
def test_parse_block_size_rejects_with_value(size):
    with pytest.raises(LayoutError, match="2\\^k\\+1"):
        parse_block_size(size)


@settings(max_examples=40, deadline=None)
@given(
    k=st.integers(1, 7),
    seed=st.integers(0, 2**32 - 1),
    dtype=st.sampled_from(["i2", "f4", "f8", "u2"]),
)
def test_decompose_reconstruct_every_level(k, seed, dtype):
    rng = np.random.default_rng(seed)
    side = grid_side(k)
    grid = (rng.standard_normal((side, side)) * 1000).astype(dtype)
    levels = decompose(grid, k)
    assert [len(v) for v in levels] == [level_size(i) for i in range(k + 1)]
    for level in range(k + 1):
        np.testing.assert_array_equal(reconstruct(levels, level), subgrid(grid, k, level))


def test_reconstruct_rejects_missing_levels():
    levels = decompose(np.zeros((5, 5)), 2)
    with pytest.raises(LayoutError, match="needs levels 0..2"):
        reconstruct(levels[:2], 2)
    with pytest.raises(LayoutError, match="must hold 5 values"):
        reconstruct([levels[0], levels[1][:3]], 1)


def test_decompose_rejects_wrong_shape():
    with pytest.raises(LayoutError, match="Expected a 5x5 block"):
        decompose(np.zeros((4, 5)), 2)
