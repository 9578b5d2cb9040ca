"""Planned levels that stitching can join (streamer.restriction): no block more than
``patch_log2`` levels below an edge neighbour, so the renderer can split every patch a finer
neighbour needs split (render.select.stitch)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_levels import CAMERAS
from test_planner import GRID, planner

from streamer.camera import Camera
from streamer.frames import SessionConfig
from streamer.restriction import restrict_levels
from tiler.quadtree import block_zranges


def violations(ids: np.ndarray, lv: np.ndarray, p: int) -> int:
    """Edge-adjacent pairs whose levels differ by more than ``p`` (brute force)."""
    where = {tuple(b): i for i, b in enumerate(np.asarray(ids).tolist())}
    n = 0
    for (r, c), i in where.items():
        for j in (where.get((r + 1, c)), where.get((r, c + 1))):
            n += j is not None and abs(int(lv[i]) - int(lv[j])) > p
    return n


def brute_force(ids: np.ndarray, lv: np.ndarray, p: int) -> np.ndarray:
    """The least raise to a fixpoint, one pair at a time."""
    where = {tuple(b): i for i, b in enumerate(np.asarray(ids).tolist())}
    out = [int(v) for v in lv]
    changed = True
    while changed:
        changed = False
        for (r, c), i in where.items():
            for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                j = where.get((r + dr, c + dc))
                if j is not None and out[i] < out[j] - p:
                    out[i], changed = out[j] - p, True
    return np.array(out)


def test_a_fine_block_raises_a_chain_of_coarse_ones():
    ids = np.array([[0, 0], [0, 1], [0, 2], [0, 3], [1, 1]])
    assert restrict_levels(ids, [8, 0, 0, 0, 0], 1).tolist() == [8, 7, 6, 5, 6]
    assert restrict_levels(ids, [8, 0, 0, 0, 0], 2).tolist() == [8, 6, 4, 2, 4]
    assert restrict_levels(ids, [8, 0, 0, 0, 0], 8).tolist() == [8, 0, 0, 0, 0]


def test_diagonal_and_absent_blocks_raise_nothing():
    diagonal = np.array([[0, 0], [1, 1]])
    assert restrict_levels(diagonal, [9, 0], 1).tolist() == [9, 0]
    gap = np.array([[0, 0], [0, 2]])  # (0, 1) is not planned: no shared border
    assert restrict_levels(gap, [9, 0], 1).tolist() == [9, 0]
    assert restrict_levels(np.array([[3, 4]]), [2], 1).tolist() == [2]


@settings(max_examples=60, deadline=None)
@given(
    cells=st.lists(st.tuples(st.integers(0, 5), st.integers(0, 5)), min_size=1, unique=True),
    seed=st.integers(0, 2**32 - 1),
    p=st.integers(1, 4),
)
def test_restricted_levels_are_the_least_joinable_raise(cells, seed, p):
    ids = np.array(cells, dtype=np.int64)
    lv = np.random.default_rng(seed).integers(0, 11, len(ids))
    out = restrict_levels(ids, lv, p)
    assert (out >= lv).all() and out.max() <= lv.max()
    assert violations(ids, out, p) == 0
    np.testing.assert_array_equal(out, brute_force(ids, lv, p))


def test_the_planner_plans_joinable_levels():
    """Positive control first: at 2¹-cell patches some camera's raw levels (the error table's,
    block by block) leave a neighbour too coarse; the planner's are those levels raised."""
    pl, table = planner(SessionConfig(patch_log2=1, tau=1.0))
    raw_violations = 0
    wide = [  # low and wide: blocks at the side of the view need far less than those ahead
        Camera((700.0, 300.0, 160.0), yaw=30, pitch=-20, far=5000, fov_y=170),
        Camera((200.0, 800.0, 155.0), yaw=45, pitch=-10, far=5000, fov_y=150),
    ]
    for cam in [*CAMERAS, *wide]:
        needed = pl.needed(cam)
        blocks = sorted(needed)
        if len(blocks) < 2:
            continue
        ids = np.array(blocks)
        zr = block_zranges(pl.zr[..., 0], pl.zr[..., 1], ids)
        raw, _ = table.needed_levels(GRID, blocks, cam, 1.0, "qiu", zr)
        raw_violations += violations(ids, raw, 1)
        got = np.array([needed[b] for b in blocks])
        assert violations(ids, got, 1) == 0
        np.testing.assert_array_equal(got, restrict_levels(ids, raw, 1))
        wants = pl.prefetch(cam, None, needed).wants  # the prefetch plan is joinable too
        w_ids = np.array(sorted(wants))
        assert violations(w_ids, np.array([wants[tuple(b)][0] for b in w_ids.tolist()]), 1) == 0
    assert raw_violations > 0, "no camera needed the restriction: the test shows nothing"


def _compiled():
    """The compiled planning kernels (skips without numba, as the other kernel tests do)."""
    pytest.importorskip("numba")
    from streamer.levels import _load_numba

    return _load_numba()


@settings(max_examples=60, deadline=None)
@given(
    cells=st.lists(st.tuples(st.integers(-3, 9), st.integers(0, 12)), min_size=1, unique=True),
    seed=st.integers(0, 2**32 - 1),
    p=st.integers(1, 4),
)
def test_compiled_restriction_equals_the_numpy_reference(cells, seed, p):
    nb = _compiled()
    ids = np.array(cells, dtype=np.int64)
    lv = np.random.default_rng(seed).integers(0, 11, len(ids))
    np.testing.assert_array_equal(restrict_levels(ids, lv, p, nb), restrict_levels(ids, lv, p))


def test_compiled_restriction_positive_control():
    """The comparison above can fail: the kernel run one level looser differs on a chain."""
    nb = _compiled()
    ids = np.array([[0, 0], [0, 1], [0, 2]])
    assert restrict_levels(ids, [9, 0, 0], 2, nb).tolist() == [9, 7, 5]
    assert (
        restrict_levels(ids, [9, 0, 0], 3, nb).tolist()
        != restrict_levels(ids, [9, 0, 0], 2).tolist()
    )
