"""The comparison's pure parts: matching two drawn surfaces sample by sample (no GL)."""

from __future__ import annotations

import numpy as np
import pytest

from render.strategies import compare


def _surface(rows, cols, h):
    return np.array(rows), np.array(cols), np.array(h, dtype=np.float64)


@pytest.mark.parametrize("limit", [compare.DENSE_LIMIT, 0])  # dense map, then sorting
def test_common_samples_pairs_heights_of_samples_drawn_in_both(monkeypatch, limit):
    monkeypatch.setattr(compare, "DENSE_LIMIT", limit)
    a = _surface([0, 0, 5, 9, 3], [0, 1, 7, 9, 3], [1.0, 2.0, 3.0, 4.0, np.nan])
    b = _surface([5, 0, 9, 3, 100], [7, 1, 8, 3, 100], [30.0, 20.0, 5.0, 6.0, 7.0])
    rows, cols, ha, hb = compare.common_samples(a, b)
    got = sorted(zip(rows.tolist(), cols.tolist(), ha.tolist(), hb.tolist(), strict=True))
    # (3, 3) is NaN (hidden) in a; (9, 9) and (9, 8) differ; (100, 100) only in b
    assert got == [(0, 1, 2.0, 20.0), (5, 7, 3.0, 30.0)]


def test_common_samples_of_disjoint_or_empty_surfaces():
    a = _surface([0], [0], [1.0])
    empty = _surface([], [], [])
    assert all(v.size == 0 for v in compare.common_samples(a, empty))
    assert all(v.size == 0 for v in compare.common_samples(a, _surface([1], [1], [1.0])))


def test_same_surface_detects_any_change():
    a = _surface([0, 1], [2, 3], [1.0, np.nan])
    assert compare._same(a, _surface([0, 1], [2, 3], [1.0, np.nan]))
    assert not compare._same(a, _surface([0, 1], [2, 3], [1.5, np.nan]))
    assert not compare._same(a, _surface([0, 1], [2, 4], [1.0, np.nan]))
    assert not compare._same(a, _surface([0], [2], [1.0]))


def test_block_levels_of_triangles():
    from render.strategies.base import block_levels
    from tiler.grid import BlockGrid

    g = BlockGrid(height=65, width=65, k=5, x0=0.0, y0=0.0, dx=1.0, dy=1.0)  # 2 x 2 blocks
    tri = np.array(
        [
            [[0, 0], [32, 0], [0, 32]],  # block (0, 0), corners of level 0
            [[0, 0], [16, 0], [0, 16]],  # block (0, 0), level 1
            [[32, 0], [64, 0], [32, 32]],  # block (0, 1), level 0 (its corners)
            [[33, 33], [34, 33], [33, 34]],  # block (1, 1), full resolution
        ]
    )
    assert block_levels(g, tri) == {(0, 0): 1, (0, 1): 0, (1, 1): 5}
    assert block_levels(g, np.zeros((0, 3, 2), np.int64)) == {}


def test_pareto_front_keeps_the_non_dominated_points():
    pts = [(1.0, 100), (0.5, 300), (2.0, 50), (1.5, 120), (0.5, 400), (3.0, 50)]
    assert compare.pareto_front(pts) == [(0.5, 300), (1.0, 100), (2.0, 50)]
    assert compare.pareto_front([]) == []


def test_strategies_with_their_own_error_stream_with_the_conservative_metric():
    from render.strategies import strategy_class, strategy_names, stream_metric

    assert stream_metric("qiu", "qiu") == "qiu"
    assert stream_metric("qiu", "conservative") == "conservative"
    for name in strategy_names():
        want = "qiu" if strategy_class(name).uses_metric else "conservative"
        assert stream_metric(name, "qiu") == want
    assert stream_metric("jung-han", "qiu") == "conservative"
