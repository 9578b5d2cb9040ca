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


def _row(**kw):
    """A compare row (JSON keys) with distinctive figures."""
    row = dict(
        strategy="qiu", tau=4.0, triangles=4036, max_screen_error_px=3.25,
        p99_screen_error_px=1.5, mean_screen_error_px=0.25, crack_pixels=0,
        crack_pixels_above=0, open_edges=0, gap_edges=0, max_gap_m=0.0, terrain_covered=1.0,
        nodata_covered=0.0, uncovered_px=0.0, near_clipped_samples=0, fly_triangles=3648.0,
        fly_cpu_ms=1.25, fly_gpu_ms=7.5, popping_path_px=0.5, popping_path_lod_frames=2,
        popping_path_frames=3, popping_dolly_px=0.75, popping_dolly_lod_frames=4,
        popping_dolly_frames=8, used_bytes=2**20, own_gpu_bytes=0,
    )  # fmt: skip
    row.update(kw)
    return row


def test_table_shows_the_middle_views_triangles_beside_its_errors():
    """The table's triangles beside the middle camera's errors were the fly-through mean
    (3,648) where the JSON row and the plot have the middle camera's (4,036)."""
    line = compare.format_row(_row()).split()
    i = line.index("4,036")  # the JSON's `triangles`, as the plot draws them
    assert line[i + 1 : i + 4] == ["3.25", "1.50", "0.250"]  # its max / p99 / mean px
    assert "3,648" in line[i + 4 :]  # the flight's mean in a column of its own
    assert "mid tris" in compare.HEADER and "fly tris" in compare.HEADER
    assert len(compare.format_row(_row())) == len(compare.HEADER)  # columns line up


def test_a_motion_with_no_frame_pairs_shows_no_popping_figure():
    """A one-camera path compares no frames: its popping read 0.00 (0/0), as if measured."""
    row = _row(popping_path_px=None, popping_path_lod_frames=0, popping_path_frames=0)
    line = compare.format_row(row)
    assert "n/a (0/0)" in line and "0.00 (0/0)" not in line
    assert "0.75 (4/8)" in line  # the dolly, measured, is shown
