"""The block-arrival arithmetic made cheaper without changing a value: ``max_pool`` (the patch
tables' pooling), :func:`tiler.quadtree.node_height_bounds` without its stack, and the float32
round-up of the node boxes, each against the form it replaced. Pure numpy."""

from __future__ import annotations

import numpy as np
import pytest

from render.node_boxes import _up32
from tiler.quadtree import SMALL_POOL, _per_node, max_pool, node_height_bounds


def _reshape_max(a: np.ndarray, r: int) -> np.ndarray:
    n = a.shape[0] // r
    return a.reshape(n, r, n, r).max(axis=(1, 3))


def _field(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((n, n)).astype(np.float32) * 100
    a[rng.random((n, n)) < 0.01] = np.inf  # the nodata rule's bounds
    a[rng.random((n, n)) < 0.01] = -np.inf
    a[rng.random((n, n)) < 0.01] = 0.0
    return a


# 8² and 64² take the one-reduction path (<= SMALL_POOL values), 256² and 512² the halvings
CASES = [(n, r) for n in (8, 64, 256, 512) for r in (1, 2, 4, 8, 16) if r <= n]


@pytest.mark.parametrize(("n", "r"), CASES)
def test_max_pool_equals_one_reduction(n, r):
    assert (n * n <= SMALL_POOL) == (n <= 128)
    a = _field(n, n + r)
    got = max_pool(a, r)
    assert got.shape == (n // r, n // r) and got.dtype == a.dtype and got.base is None
    np.testing.assert_array_equal(got, _reshape_max(a, r))


def test_max_pool_nan_and_non_power_of_two():
    a = _field(96, 3)
    a[5, 7] = np.nan
    for r in (2, 3, 32):
        np.testing.assert_array_equal(max_pool(a, r), _reshape_max(a, r))
    big = _field(512, 4)
    big[100, 3] = np.nan
    np.testing.assert_array_equal(max_pool(big, 4), _reshape_max(big, 4))


def test_max_pool_control_a_dropped_view_is_caught():
    """The comparison above can fail: pooling that forgets one of the four views differs."""
    a = _field(512, 5)

    def dropped(a, r):
        while r > 1:
            a = np.maximum(np.maximum(a[0::2, 0::2], a[0::2, 1::2]), a[1::2, 0::2])
            r >>= 1
        return a

    assert not np.array_equal(dropped(a, 4), _reshape_max(a, 4))


def _bounds_by_stack(grid, bound):
    k, g = len(bound), np.asarray(grid, dtype=np.float64)
    rr = (g.shape[0] - 1).bit_length() - 1
    los, his = [], []
    for d in range(k):
        a = min(d, rr)
        c = g[:: 1 << (rr - a), :: 1 << (rr - a)]
        quad = np.stack([c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]])
        b = _per_node(bound[a], a)
        lo, hi = quad.min(axis=0) - b, quad.max(axis=0) + b
        rep = 1 << (d - a)
        los.append(np.repeat(np.repeat(lo, rep, 0), rep, 1) if rep > 1 else lo)
        his.append(np.repeat(np.repeat(hi, rep, 0), rep, 1) if rep > 1 else hi)
    return los, his


@pytest.mark.parametrize("level", [6, 4])
def test_node_height_bounds_equal_the_stacked_form(level):
    rng = np.random.default_rng(level)
    k = 6
    grid = rng.standard_normal(((1 << level) + 1,) * 2) * 500 + 8000
    grid[3, 4] = np.nan  # non-finite corners stay non-finite
    grid[0, 0] = -0.0
    bound = [np.abs(rng.standard_normal((1 << min(d, 4),) * 2)) * 3 for d in range(k)]
    bound[2][1, 1] = np.inf
    got, want = node_height_bounds(grid, bound), _bounds_by_stack(grid, bound)
    for g, w in zip(got[0] + got[1], want[0] + want[1], strict=True):
        assert g.shape == w.shape
        np.testing.assert_array_equal(g, w)
        assert np.array_equal(np.signbit(g), np.signbit(w))


def test_up32_rounds_up_as_before_and_never_narrows():
    rng = np.random.default_rng(7)
    x = np.concatenate(
        [rng.standard_normal(10_000) * 1e4, [0.0, -0.0, np.inf, -np.inf, 1e-50, -1e-50, 8848.1]]
    )
    f = x.astype(np.float32)
    before = np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)
    got = _up32(x)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, before)
    assert (got.astype(np.float64) >= x).all()
    assert (got.astype(np.float64) > x).sum() > 1000  # the rounding up did happen (control)


def _mixed_by_reductions(valid, k):
    v = np.asarray(valid, dtype=bool)
    quad = (v[:-1, :-1], v[1:, :-1], v[:-1, 1:], v[1:, 1:])
    anyv = quad[0] | quad[1] | quad[2] | quad[3]
    anym = ~(quad[0] & quad[1] & quad[2] & quad[3])
    out = [anyv & anym]
    for d in range(k - 1, -1, -1):
        n = 1 << d
        anyv = anyv.reshape(n, 2, n, 2).any(axis=(1, 3))
        anym = anym.reshape(n, 2, n, 2).any(axis=(1, 3))
        out.append(anyv & anym)
    return out[::-1]


@pytest.mark.parametrize("k", [1, 4, 8])
def test_mixed_nodes_and_raise_mixed_equal_the_reductions(k):
    from streamer.nodata import mixed_nodes, raise_mixed

    rng = np.random.default_rng(k)
    side = (1 << k) + 1
    valid = rng.random((side, side)) > 0.02
    valid[side // 2 :, : side // 3] = False  # a hole with a long boundary
    got, want = mixed_nodes(valid, k), _mixed_by_reductions(valid, k)
    assert len(got) == k + 1 and any(m.any() for m in got) and not all(m.all() for m in got)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == bool
        np.testing.assert_array_equal(g, w)
    field = [np.full((min(1 << d, 4),) * 2, 2.5, np.float32) for d in range(k)]
    raised = raise_mixed(field, got)
    for d, (r, f) in enumerate(zip(raised, field, strict=True)):
        n, m = f.shape[0], got[d].shape[0]
        tiles = got[d].reshape(n, m // n, n, m // n).any(axis=(1, 3))
        np.testing.assert_array_equal(r, np.where(tiles, np.float32(np.inf), f))
