"""Per-node height ranges (:func:`tiler.quadtree.node_height_bounds`, :class:`NodeBoxes`):
every full-resolution sample of a node's closed footprint lies in its range, and so does every
vertex its patch can draw; a range built from half the stored bound misses samples (the
positive control). Pure numpy, no store, no GL."""

from __future__ import annotations

import numpy as np
import pytest
from demtools import fractal

from render.node_boxes import NodeBoxes
from tiler.errors import LayoutError
from tiler.quadtree import node_height_bounds
from tiler.static_error import bound_errors

K = 6  # blocks of 65² samples


def dem(seed: int) -> np.ndarray:
    d = fractal((65, 65), seed=seed).astype(np.float64)
    return (d - d.mean()) * 40.0 + 800.0


def escapes(h: np.ndarray, lo: np.ndarray, hi: np.ndarray, depth: int) -> int:
    """Samples of the closed footprints of depth-``depth`` nodes outside their ``[lo, hi]``."""
    n, s = 1 << depth, (h.shape[0] - 1) >> depth
    bad = 0
    for r in range(n):
        for c in range(n):
            w = h[r * s : r * s + s + 1, c * s : c * s + s + 1]
            bad += int(((w < lo[r, c]) | (w > hi[r, c])).sum())
    return bad


def level_grid(h: np.ndarray, level: int) -> np.ndarray:
    step = (h.shape[0] - 1) >> level
    return h[::step, ::step]


@pytest.mark.parametrize("resident", [6, 4, 2])
def test_node_height_bounds_hold_every_sample(resident):
    h = dem(3)
    bound = bound_errors(h, np.ones(h.shape, bool), K)
    los, his = node_height_bounds(level_grid(h, resident), bound)
    for d in range(K):
        assert los[d].shape == (1 << d, 1 << d)
        assert escapes(h, los[d], his[d], d) == 0, d
    if resident >= 3:  # tighter than the block's range below the root (the old spheres')
        assert (his[3] - los[3]).max() < h.max() - h.min()


def test_positive_control_half_the_bound_misses_samples():
    h = dem(4)
    bound = bound_errors(h, np.ones(h.shape, bool), K)
    los, his = node_height_bounds(level_grid(h, K), [0.5 * b for b in bound])
    assert sum(escapes(h, los[d], his[d], d) for d in range(K)) > 0


def test_node_height_bounds_rejects_a_bad_grid():
    with pytest.raises(LayoutError, match="2\\*\\*R\\+1"):
        node_height_bounds(np.zeros((10, 10)), [np.zeros((1, 1))] * K)


@pytest.mark.parametrize("p", [2, 4])
def test_node_boxes_hold_samples_and_patch_vertices(p):
    h = dem(5)
    bound = bound_errors(h, np.ones(h.shape, bool), K)
    zr = (float(h.min()), float(h.max()))
    boxes = NodeBoxes(K, p)
    boxes.update((0, 0), K, h, bound, zr)
    boxes.update((0, 1), K, h + 500.0, bound, (zr[0] + 500.0, zr[1] + 500.0))
    slots = boxes.slots(np.array([[0, 0], [0, 1]]))
    for d in range(K - p):
        n = 1 << d
        rows, cols = (a.ravel() for a in np.mgrid[0:n, 0:n])
        for i, offset in enumerate((0.0, 500.0)):
            sl = (np.full(n * n, slots[0][i]), np.full(n * n, slots[1][i]))
            lo, hi = boxes.zrange(sl, np.zeros((n * n, 2)), d, rows, cols)
            lo, hi = lo.reshape(n, n), hi.reshape(n, n)
            assert escapes(h + offset, lo, hi, d) == 0, (d, offset)
            tol = 1e-4 * (abs(zr[0]) + abs(zr[1]) + offset)  # float32, rounded outwards
            assert (lo >= zr[0] + offset - tol).all() and (hi <= zr[1] + offset + tol).all()
        # the patch's range is mostly tighter than the node's 4 corners ∓ its bound at depth d
        los, his = node_height_bounds(h, bound)
        assert np.median(hi - lo) < np.median(his[d] - los[d]), d
    assert boxes.level((0, 0)) == K
    boxes.remove((0, 0))
    assert (0, 0) not in boxes and (0, 1) in boxes


def test_node_boxes_fall_back_to_the_block_range_where_not_finite():
    h = dem(6)
    bound = bound_errors(h, np.ones(h.shape, bool), K)
    bound[2][1, 1] = np.inf  # a mask boundary: the reader raises it to inf
    boxes = NodeBoxes(K, 2)
    boxes.update((0, 0), K, h, bound, (700.0, 900.0))
    sl = boxes.slots(np.array([[0, 0]]))
    lo, hi = boxes.zrange(sl, np.zeros((1, 2)), 0, np.array([0]), np.array([0]))
    assert (lo[0], hi[0]) == (700.0, 900.0)
