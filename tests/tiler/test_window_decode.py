"""The windowed decode (``read_block(..., extent=)``): an edge block's samples inside the DEM,
decoded without its padding, bit for bit the whole grid's top-left part, on both backends."""

from __future__ import annotations

import numpy as np
import pytest
from demtools import fractal, write_dem

from tiler import codecs, encoding, kernels
from tiler.layout import grid_side
from tiler.store import TerrainStore, open_store
from tiler.tile import TileOptions, tile

DTYPES = ["uint8", "int16", "int32", "float32", "float64"]


def _grid(k: int, dtype: str, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    side = grid_side(k)
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return (rng.standard_normal((side, side)).cumsum(0) * 100).astype(dt)
    info = np.iinfo(dt)
    return rng.integers(info.min, info.max, (side, side), endpoint=True).astype(dt)


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint8)


@pytest.mark.parametrize("dtype", DTYPES)
def test_numpy_window_is_the_grid_s_top_left_for_every_extent(dtype):
    k = 4
    stored = encoding.encode_levels_numpy(_grid(k, dtype, 1), k)
    for level in range(k + 1):
        full = encoding.decode_grid_numpy(stored, dtype, level)
        side = grid_side(level)
        for rows in range(1, side + 1):
            for cols in range(1, side + 1):
                got = encoding.decode_grid_numpy(stored, dtype, level, (rows, cols))
                assert got.shape == (rows, cols) and got.flags.c_contiguous
                assert np.array_equal(_bits(got), _bits(full[:rows, :cols])), (level, rows, cols)


@pytest.mark.parametrize("dtype", DTYPES)
def test_compiled_window_equals_the_numpy_window(dtype, numba_backend):
    k = 6
    stored = encoding.encode_levels_numpy(_grid(k, dtype, 2), k)
    side = grid_side(k)
    work = np.full((side, side), 77, dtype=dtype)  # stale scratch must not leak into the window
    rng = np.random.default_rng(3)
    extents = [(1, 1), (side, 1), (1, side), (side, side), (2, 3), (side - 1, side - 1)]
    extents += [tuple(int(v) for v in rng.integers(1, side + 1, 2)) for _ in range(40)]
    for rows, cols in extents:
        want = encoding.decode_grid_numpy(stored, dtype, k, (rows, cols))
        for w in (None, work):
            got = encoding.decode_grid(stored, dtype, k, (rows, cols), w)
            assert got.shape == (rows, cols) and got.base is None  # a new array, not the scratch
            assert np.array_equal(_bits(got), _bits(want)), (rows, cols)
    coarse = encoding.decode_grid(stored, dtype, 3, (5, 2))  # a coarser level's window
    want = encoding.decode_grid_numpy(stored, dtype, 3)[:5, :2]
    assert np.array_equal(_bits(coarse), _bits(want))


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_window_reads_no_stored_value_past_it(backend, monkeypatch):
    """Control both ways: damaging a finest-level value outside the window leaves the window
    alone (it is not decoded: the point of the window), one inside changes it."""
    if backend == "numba":
        pytest.importorskip("numba")
    monkeypatch.setenv(kernels.ENV, backend)
    k, dtype = 5, "int16"
    stored = encoding.encode_levels_numpy(_grid(k, dtype, 4), k)
    rows, cols = 9, 12
    want = encoding.decode_grid(stored, dtype, k, (rows, cols))
    side, m = grid_side(k), grid_side(k - 1)
    # the finest level's values in sequence order: even rows' odd columns, then odd rows
    pos = np.zeros((side, side), dtype=np.int64) - 1
    order = [(y, x) for y in range(side) for x in range(side) if (y % 2 or x % 2)]
    for i, (y, x) in enumerate(order):
        pos[y, x] = i
    assert len(order) == stored[k].size == (m - 1) * (3 * m - 2) + (m - 1)
    for (y, x), inside in (((side - 1, side - 2), False), ((rows + 4, 3), False), ((3, 5), True)):
        bad = [s.copy() for s in stored]
        bad[k][pos[y, x]] ^= 0x55
        got = encoding.decode_grid(bad, dtype, k, (rows, cols))
        full = encoding.decode_grid(bad, dtype, k)
        assert not np.array_equal(full, encoding.decode_grid(stored, dtype, k))  # damage shows
        assert np.array_equal(got, want) is not inside, ((y, x), inside)


def test_bad_extent_names_the_value():
    stored = encoding.encode_levels_numpy(_grid(3, "int16", 5), 3)
    for bad in [(0, 3), (3, 10), (10, 1)]:
        with pytest.raises(ValueError, match=r"extent .* is outside the 9x9 grid"):
            encoding.decode_grid(stored, "int16", 3, bad)


def test_a_codec_without_decode_window_is_cropped():
    base = codecs.get(encoding.INT_RESIDUAL)
    plain = codecs.LevelCodec("plain", base.encode, base.decode, base.decode_next, base.decode_grid)
    stored = encoding.encode_levels_numpy(_grid(3, "int16", 6), 3)
    bound = codecs.BoundCodec(plain, np.dtype("int16"), np.dtype("int16"), None)
    got = bound.decode_grid(stored, 3, (4, 7))
    assert got.shape == (4, 7) and got.base is None
    np.testing.assert_array_equal(got, encoding.decode_grid_numpy(stored, "int16", 3)[:4, :7])


@pytest.fixture(scope="module")
def edge_stores(tmp_path_factory):
    """150x100 DEMs in 65-sample blocks: 3x2 blocks, the last row and column mostly padding."""
    d = tmp_path_factory.mktemp("window")
    ints = fractal((150, 100), 41)
    ints[140:, 90:] = -9999
    write_dem(d / "i.tif", ints, nodata=-9999)
    write_dem(d / "f.tif", fractal((150, 100), 42, "float32"))
    for name in ("i", "f"):
        tile(d / f"{name}.tif", d / f"{name}.zarr", TileOptions(block_size=65))
    return d


@pytest.mark.parametrize("name", ["i", "f"])
@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_store_extent_reads_equal_the_grid_s_samples_inside_the_dem(
    edge_stores, name, backend, monkeypatch
):
    if backend == "numba":
        pytest.importorskip("numba")
    monkeypatch.setenv(kernels.ENV, backend)
    direct = open_store(edge_stores / f"{name}.zarr")
    via_zarr = TerrainStore(edge_stores / f"{name}.zarr", direct_reads=False)
    assert direct.block_extent((2, 1)) == (150 - 128, 100 - 64)  # the DEM's last samples
    assert direct.block_extent((0, 0)) == (65, 65)
    assert direct.block_extent((2, 1), 3) == ((150 - 128 - 1) // 8 + 1, (100 - 64 - 1) // 8 + 1)
    for b in direct.grid.blocks():
        for level in range(direct.k + 1):
            ext = direct.block_extent(b, level)
            full = direct.read_block(b, level)
            for s in (direct, via_zarr):
                got = s.read_block(b, level, extent=ext)
                assert got.shape == ext and got.dtype == full.dtype
                assert np.array_equal(_bits(got), _bits(full[: ext[0], : ext[1]])), (b, level)
    edge = direct.read_block((2, 1), extent=direct.block_extent((2, 1)))
    r0, c0, h, w = direct.grid.block_window(2, 1)
    import rasterio

    with rasterio.open(edge_stores / f"{name}.tif") as ds:
        src = ds.read(1)[r0 : r0 + h, c0 : c0 + w]
    valid = direct.read_mask((2, 1))[:h, :w]
    np.testing.assert_array_equal(edge[valid], src[valid])  # lossless where there is terrain
