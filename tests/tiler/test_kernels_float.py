"""The compiled float-xor encode/decode (``tiler._codec_nb``) against the numpy reference, bit
for bit, on grids whose float rounding depends on the order of the prediction's operations."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tiler import encoding, kernels
from tiler.layout import grid_side

pytest.importorskip("numba")

from test_kernels import _same_bits  # noqa: E402

FLOATS = ["float32", "float64"]


def _extreme_grid(k: int, dtype: str, seed: int) -> np.ndarray:
    """Finite values mixing magnitudes: ±1e30, subnormals, ±0.0, -11000..9000 m heights with
    fraction bits, so that float64 sums of four of them round (order matters)."""
    dt = np.dtype(dtype)
    info = np.finfo(dt)
    rng = np.random.default_rng(seed)
    side = grid_side(k)
    special = np.array(
        [-0.0, 1e30, -1e30, info.smallest_subnormal, 0.0, -info.smallest_subnormal, 3e29,
         info.smallest_normal * 0.75, -info.smallest_normal, -11000.0, 9000.0],
        dtype=dt,
    )  # fmt: skip
    grid = rng.uniform(-11000.0, 9000.0, side * side).astype(dt)
    at = rng.permutation(side * side)
    n = min(side * side, special.size)
    grid[at[:n]] = special[:n]  # each special value once (the first ones on small grids) ...
    more = at[n:][rng.random(side * side - n) < 0.25]
    grid[more] = special[rng.integers(0, special.size, more.size)]  # ... then a quarter more
    return grid.reshape(side, side)


def _low_bit_noise(stored: list[np.ndarray], dtype: np.dtype, seed: int) -> list[np.ndarray]:
    """Stored levels no encoder wrote: the finest level's low mantissa bits flipped at random.
    Its decoded values are the encoded ones with those bits flipped, so finite (noise on a
    coarser level could move a prediction across an exponent and XOR it to inf or NaN)."""
    rng = np.random.default_rng(seed)
    mant = 16 if dtype.itemsize == 4 else 40
    out = [s.copy() for s in stored]
    noise = rng.integers(0, 1 << mant, size=out[-1].size, dtype=np.uint64)
    out[-1] ^= noise.astype(out[-1].dtype)
    return out


def _check_decodes(stored: list[np.ndarray], dtype: str, k: int) -> np.ndarray:
    """Every decode entry point (whole grids at each level, levels one at a time from a start
    level ``first > 0``) equals the numpy reference; returns the full grid."""
    for level in range(k + 1):
        want = encoding.decode_grid_numpy(stored, dtype, level)
        assert _same_bits(encoding.decode_grid(stored, dtype, level), want), level
    levels = encoding.decode_levels_numpy(stored, dtype)
    assert all(map(_same_bits, encoding.decode_levels(stored, dtype), levels))
    for n in range(k + 1):  # n > 0: the kernel's partial decode (first = n)
        got = encoding.decode_next_level(levels[:n], stored[n], dtype)
        assert _same_bits(got, levels[n]), n
    return want


@pytest.mark.parametrize("dtype", FLOATS)
@pytest.mark.parametrize("k", [1, 2, 3, 6, 10])
def test_float_codec_on_extreme_values_equals_numpy(numba_backend, k, dtype):
    grid = _extreme_grid(k, dtype, seed=k)
    assert np.isfinite(grid).all() and np.signbit(grid[grid == 0]).any()  # -0.0 is there
    stored = encoding.encode_levels(grid, k)
    ref = encoding.encode_levels_numpy(grid, k)
    assert len(stored) == k + 1 and all(map(_same_bits, stored, ref))
    assert _same_bits(_check_decodes(ref, dtype, k), grid)
    _check_decodes(_low_bit_noise(ref, np.dtype(dtype), seed=k), dtype, k)


@settings(max_examples=60, deadline=None)
@given(
    k=st.integers(1, 4),
    dtype=st.sampled_from(FLOATS),
    data=st.data(),
)
def test_float_codec_on_any_finite_values_equals_numpy(k, dtype, data):
    """Hypothesis: any finite values (subnormals, ±0.0, up to ±1e30), any block size to 17²."""
    side = grid_side(k)
    width = 32 if dtype == "float32" else 64
    top = float(np.float32(1e30)) if width == 32 else 1e30
    values = st.floats(-top, top, allow_nan=False, allow_infinity=False, width=width)
    flat = data.draw(st.lists(values, min_size=side * side, max_size=side * side))
    grid = np.array(flat, dtype=dtype).reshape(side, side)
    old = os.environ.get(kernels.ENV)
    os.environ[kernels.ENV] = "numba"  # (no function-scoped fixture under @given)
    try:
        stored = encoding.encode_levels(grid, k)
        assert all(map(_same_bits, stored, encoding.encode_levels_numpy(grid, k)))
        assert _same_bits(_check_decodes(stored, dtype, k), grid)
    finally:
        if old is None:
            os.environ.pop(kernels.ENV, None)
        else:
            os.environ[kernels.ENV] = old


def _reassociated_parts(g: np.ndarray):
    """``_predict_parts`` with the centre summed as (tl + bl) + (tr + br): a plausible wrong
    "optimisation" (column sums shared between neighbours) that rounds differently."""
    w = g.astype(np.float64)
    h = (w[:, :-1] + w[:, 1:]) * 0.5
    v = (w[:-1, :] + w[1:, :]) * 0.5
    col = w[:-1, :] + w[1:, :]
    return h, v, (col[:, :-1] + col[:, 1:]) * 0.25


@pytest.mark.parametrize("dtype", FLOATS)
def test_float_comparison_sees_a_wrong_decoder(numba_backend, dtype, monkeypatch):
    """Positive controls: the comparison above fails for a decoder that reassociates the centre
    sum, and for the compiled decoder given one flipped stored bit."""
    k = 6
    grid = _extreme_grid(k, dtype, seed=k)
    ref = encoding.encode_levels_numpy(grid, k)
    want = encoding.decode_grid_numpy(ref, dtype)
    with monkeypatch.context() as m, np.errstate(all="ignore"):  # wrong values may overflow
        m.setattr(encoding, "_predict_parts", _reassociated_parts)
        wrong = encoding.decode_grid_numpy(ref, dtype)
    assert not _same_bits(wrong, want)
    for level, pos in ((1, 0), (k, 0), (k, ref[k].size // 2), (k, ref[k].size - 1)):
        flipped = [s.copy() for s in ref]
        flipped[level][pos] ^= 1
        assert not _same_bits(encoding.decode_grid(flipped, dtype), want), (level, pos)
