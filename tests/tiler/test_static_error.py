"""Static errors: brute-force references, monotonicity, round-up packing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tiler.layout import grid_side
from tiler.static_error import (
    block_errors,
    bound_errors,
    bound_errors_numpy,
    bound_errors_reference,
    default_cap,
    make_monotone,
    node_error,
    pack_field,
    qiu_errors,
    qiu_errors_numpy,
    round_up_f16,
    subtree_error,
    unpack_field,
)


def brute_qiu(grid, valid, k):
    """Qiu's H node by node with Python loops (reference)."""
    out = []
    f = grid.astype(np.float64)
    for d in range(k):
        n = 1 << d
        s = (grid.shape[0] - 1) // n
        h = s // 2
        arr = np.zeros((n, n))
        for i in range(n):
            for j in range(n):
                r, c = i * s, j * s
                a, b, cc, dd = f[r, c], f[r, c + s], f[r + s, c], f[r + s, c + s]
                cands = [
                    ((r, c + h), (a + b) / 2),
                    ((r + s, c + h), (cc + dd) / 2),
                    ((r + h, c), (a + cc) / 2),
                    ((r + h, c + s), (b + dd) / 2),
                    ((r + h, c + h), (a + dd) / 2),
                    ((r + h, c + h), (b + cc) / 2),
                ]
                arr[i, j] = max((abs(f[p] - v) for p, v in cands if valid[p]), default=0.0)
        out.append(arr)
    return out


def brute_bound(grid, valid, k):
    """Deviation of every sample from each node's two triangulations (reference)."""
    out = []
    f = grid.astype(np.float64)
    for d in range(k):
        n = 1 << d
        s = (grid.shape[0] - 1) // n
        arr = np.zeros((n, n))
        for i in range(n):
            for j in range(n):
                r, c = i * s, j * s
                a, b, cc, dd = f[r, c], f[r, c + s], f[r + s, c], f[r + s, c + s]
                best = 0.0
                for y in range(s + 1):
                    for x in range(s + 1):
                        if not valid[r + y, c + x]:
                            continue
                        u, v = x / s, y / s
                        za = (
                            a + u * (b - a) + v * (dd - b)
                            if u >= v
                            else a + v * (cc - a) + u * (dd - cc)
                        )
                        if u + v <= 1:
                            zb = a + u * (b - a) + v * (cc - a)
                        else:
                            zb = dd + (1 - u) * (cc - dd) + (1 - v) * (b - dd)
                        best = max(best, abs(f[r + y, c + x] - za), abs(f[r + y, c + x] - zb))
                arr[i, j] = best
        out.append(arr)
    return out


@pytest.mark.parametrize("k", [1, 2, 3, 4])
@pytest.mark.parametrize("holes", [False, True], ids=["full", "nodata"])
def test_errors_match_brute_force(k, holes):
    rng = np.random.default_rng(k)
    side = grid_side(k)
    grid = rng.integers(-11000, 9000, (side, side)).astype(np.int32)
    valid = rng.random((side, side)) > 0.3 if holes else np.ones((side, side), bool)
    for got, ref in zip(qiu_errors(grid, valid, k), brute_qiu(grid, valid, k), strict=True):
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    for got, ref in zip(bound_errors(grid, valid, k), brute_bound(grid, valid, k), strict=True):
        assert np.all(got >= ref)  # float32 with a rounding margin: never below
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5 * 20000)


@settings(max_examples=25, deadline=None)
@given(k=st.integers(1, 7), seed=st.integers(0, 2**32 - 1))
def test_fast_bound_equals_reference(k, seed):
    rng = np.random.default_rng(seed)
    side = grid_side(k)
    grid = (rng.standard_normal((side, side)) * 100).cumsum(0)
    valid = rng.random((side, side)) > 0.1
    for a, b in zip(
        bound_errors(grid, valid, k), bound_errors_reference(grid, valid, k), strict=True
    ):
        assert np.all(a >= b)  # a bound: never below the exact value
        scale = np.abs(grid).max() + 1
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-4 * scale)


def test_monotone_parent_at_least_descendants():
    rng = np.random.default_rng(3)
    per = [rng.random((1 << d, 1 << d)) * (10 - d) for d in range(6)]
    mono = make_monotone(per)
    for d in range(5):
        child = mono[d + 1]
        n = child.shape[0] // 2
        assert np.all(mono[d] >= child.reshape(n, 2, n, 2).max(axis=(1, 3)))
        assert np.all(mono[d] >= per[d])
    np.testing.assert_array_equal(mono[5], per[5])


def test_bound_is_a_true_bound_on_every_sample():
    """Drawing a node at depth d never misses a sample by more than its bound."""
    rng = np.random.default_rng(4)
    k = 5
    side = grid_side(k)
    grid = rng.standard_normal((side, side)).cumsum(0).cumsum(1)
    valid = np.ones_like(grid, bool)
    bounds = bound_errors(grid, valid, k)
    qiu = make_monotone(qiu_errors(grid, valid, k))
    # the bound is never below Qiu's H (which only looks at 6 points)
    for b, q in zip(bounds, qiu_errors(grid, valid, k), strict=True):
        assert np.all(b >= q - 1e-12)
    assert qiu[0][0, 0] > 0


@pytest.mark.parametrize("value", [0.0, 1e-7, 0.1, 1.0, 3.14159, 1234.567, 20000.0, 65504.0, 1e6])
def test_round_up_f16_never_below(value):
    h = round_up_f16(np.array([value]))
    assert float(h[0]) >= value
    if value <= 65504:
        assert np.isfinite(h[0])


def test_flat_terrain_has_zero_errors():
    grid = np.full((17, 17), 1234.0)
    e = block_errors(grid, np.ones((17, 17), bool), 4, default_cap(4))
    assert not e.any()


def test_pack_unpack_and_lookup_with_cap():
    rng = np.random.default_rng(5)
    k, cap = 6, 2
    per = make_monotone([rng.random((1 << d, 1 << d)) * 100 for d in range(k)])
    flat = pack_field(per, cap)
    assert flat.dtype == np.float16
    field = unpack_field(flat, k, cap)
    for d in range(k):
        rows, cols = np.meshgrid(np.arange(1 << d), np.arange(1 << d), indexing="ij")
        got = node_error(field, d, rows, cols)
        assert np.all(got >= per[d] - 0)  # rounded up, and tile max beyond cap
        if d <= cap:
            np.testing.assert_allclose(got, per[d], rtol=1e-3)
    # a node at depth <= cap gets the exact max of its descendants at any depth
    for d in range(cap + 1):
        for below in range(1, k - d):
            n = 1 << d
            for i in range(n):
                for j in range(n):
                    r = 1 << below
                    exact = per[d + below][i * r : (i + 1) * r, j * r : (j + 1) * r].max()
                    got = subtree_error(field, d, i, j, below)
                    assert exact <= got <= exact * 1.001 + 1e-6


@pytest.mark.parametrize("k", [1, 2, 3, 5])
@pytest.mark.parametrize("extent", [(0, 0), (1, 3), (2, 2), (4, 8), (9, 17), (16, 33), (33, 33)])
def test_padded_block_errors_match_brute_force(k, extent, monkeypatch):
    """Valid samples only in the top-left ``rows x cols`` (an edge block's padding), ends on
    and beside node borders: the cropped numpy path counts every node that holds one."""
    side = grid_side(k)
    rows, cols = min(extent[0], side), min(extent[1], side)
    rng = np.random.default_rng(rows * 100 + cols)
    grid = rng.integers(-11000, 9000, (side, side)).astype(np.int32)
    valid = np.zeros((side, side), bool)
    valid[:rows, :cols] = True
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numpy")
    qiu, bound = qiu_errors(grid, valid, k), bound_errors(grid, valid, k)
    for got, ref in zip(qiu, brute_qiu(grid, valid, k), strict=True):
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    for got, ref in zip(bound, brute_bound(grid, valid, k), strict=True):
        assert np.all(got >= ref)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5 * 20000)


@settings(max_examples=40, deadline=None)
@given(
    k=st.integers(1, 7),
    seed=st.integers(0, 2**32 - 1),
    rows=st.integers(0, 129),
    cols=st.integers(0, 129),
    holes=st.booleans(),
    dtype=st.sampled_from(["int16", "float32", "float64"]),
)
def test_cropped_numpy_errors_equal_uncropped(k, seed, rows, cols, holes, dtype):
    """Skipping the nodes past the last valid row and column changes no value, bit for bit."""
    rng = np.random.default_rng(seed)
    side = grid_side(k)
    grid = (rng.standard_normal((side, side)) * 3000).astype(dtype)
    valid = np.zeros((side, side), bool)
    valid[:rows, :cols] = True
    if holes:
        valid &= rng.random((side, side)) > 0.3
    for fn in (qiu_errors_numpy, bound_errors_numpy):
        for a, b in zip(fn(grid, valid, k), fn(grid, valid, k, crop=False), strict=True):
            assert a.dtype == b.dtype and a.shape == b.shape
            np.testing.assert_array_equal(a, b, err_msg=fn.__name__)
