"""Level encodings: exact inversion, nodata filling, quantisation bound."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tiler.encoding import (
    decode_grid,
    decode_levels,
    dequantise,
    encode_levels,
    fill_invalid,
    predict,
    quantise,
    storage_dtype_for,
)
from tiler.layout import decompose, grid_side, subgrid

DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64"]


def _random_grid(rng, side, dtype):
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return (rng.standard_normal((side, side)) * 5000).astype(dt)
    info = np.iinfo(dt)
    return rng.integers(info.min, info.max, (side, side), endpoint=True).astype(dt)


@settings(max_examples=60, deadline=None)
@given(k=st.integers(1, 7), seed=st.integers(0, 2**32 - 1), dtype=st.sampled_from(DTYPES))
def test_residual_round_trip_exact_including_extremes(k, seed, dtype):
    rng = np.random.default_rng(seed)
    grid = _random_grid(rng, grid_side(k), dtype)  # full dtype range: wraps must invert
    stored = encode_levels(grid, k)
    assert all(s.dtype == storage_dtype_for(grid.dtype) for s in stored)
    for level in range(k + 1):
        out = decode_grid(stored, grid.dtype, level)
        np.testing.assert_array_equal(
            out.view(np.uint8), np.ascontiguousarray(subgrid(grid, k, level)).view(np.uint8)
        )
    decoded = decode_levels(stored, grid.dtype)
    for a, b in zip(decoded, decompose(grid, k), strict=True):
        np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))


def test_smooth_surface_has_zero_residuals():
    x = np.arange(17)
    plane = (3 * x[None, :] + 5 * x[:, None]).astype(np.int16)
    stored = encode_levels(plane, 4)
    assert all(not s.any() for s in stored[1:])


def test_predict_integer_floor_and_float_mean():
    g = np.array([[0, 3], [5, 7]], dtype=np.int16)
    p = predict(g)
    assert p[0, 1] == 1 and p[1, 0] == 2 and p[1, 1] == 3  # floors of 1.5, 2.5, 3.75
    pf = predict(g.astype(np.float32))
    assert pf[1, 1] == 3.75


def test_fill_invalid_uses_coarse_prediction_and_keeps_valid():
    rng = np.random.default_rng(1)
    grid = rng.integers(100, 200, (9, 9)).astype(np.int16)
    valid = np.ones((9, 9), bool)
    valid[3:6, 3:6] = False
    grid[~valid] = -32768  # a nodata value that must never show as a spike
    filled = fill_invalid(grid, valid, 3)
    np.testing.assert_array_equal(filled[valid], grid[valid])
    assert filled[~valid].min() >= 100 and filled[~valid].max() <= 200


def test_fill_invalid_all_invalid_block_is_flat_zero():
    grid = np.full((5, 5), np.nan, np.float32)
    filled = fill_invalid(grid, np.zeros((5, 5), bool), 2)
    assert np.all(filled == 0)


@pytest.mark.parametrize("step", [0.01, 0.1, 1.0, 0.25])
def test_quantise_error_at_most_half_step(step):
    rng = np.random.default_rng(2)
    v = (rng.standard_normal(10000) * 3000).astype(np.float64)
    back = dequantise(quantise(v, step), step, np.float64)
    assert np.max(np.abs(back - v)) <= step / 2 * (1 + 1e-9)


def test_quantise_refuses_overflow():
    from tiler.errors import SourceError

    with pytest.raises(SourceError, match="coarser precision"):
        quantise(np.array([1e9]), 0.001)
