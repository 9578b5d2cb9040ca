"""The xarray backend: a level as a lazy, georeferenced DataArray equal to read_block + mask."""

from __future__ import annotations

import pickle
import tomllib
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rioxarray  # noqa: F401  (registers .rio)
import xarray as xr
from demtools import fractal, shared_file, write_dem
from rasterio.crs import CRS

import tiler.xarray_backend as xb
from tiler.export import export_geotiff
from tiler.store import TerrainStore
from tiler.tile import TileOptions, tile
from tiler.xarray_backend import TerrastreamBackendEntrypoint, level_dataarray

ENGINE = TerrastreamBackendEntrypoint


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    d = tmp_path_factory.mktemp("xr")
    data = fractal((70, 90), seed=9)
    data[10:14, 20:30] = -9999
    src = write_dem(d / "dem.tif", data, nodata=-9999)
    return tile(src, d / "dem.zarr", TileOptions(block_size=33)), data


def expected_level(s: TerrainStore, level: int) -> np.ndarray:
    """The level assembled from read_block + read_mask (NaN where masked)."""
    h, w, step = xb.level_shape(s, level)
    out = np.full((h, w), np.nan)
    bstep = s.grid.step // step
    for br, bc in s.grid.blocks():
        g = s.read_block((br, bc), level).astype(np.float64)
        g[~s.read_mask((br, bc))[::step, ::step]] = np.nan
        r0, c0 = br * bstep, bc * bstep
        nr, nc = min(bstep + 1, h - r0), min(bstep + 1, w - c0)
        out[r0 : r0 + nr, c0 : c0 + nc] = g[:nr, :nc]
    return out


@pytest.mark.parametrize("level", [0, 2, 4, 5])
def test_level_equals_read_block_and_mask(store, level):
    s, data = store
    ds = xr.open_dataset(s.url, engine=ENGINE, level=level, chunks={})
    h = ds["height"]
    assert h.dims == ("y", "x") and h.attrs["units"] == "m"
    np.testing.assert_array_equal(h.values, expected_level(s, level))
    step = 1 << (s.k - level)
    if level == s.k:
        valid = data != -9999
        np.testing.assert_array_equal(np.isnan(h.values), ~valid)
    # one dask chunk per block
    assert len(h.chunks[0]) == s.grid.rows and len(h.chunks[1]) == s.grid.cols
    # coordinates are the level's sample centres
    x, y = s.grid.sample_xy(np.zeros(h.sizes["x"]), np.arange(h.sizes["x"]) * step)
    np.testing.assert_allclose(h.x.values, x)
    _, y = s.grid.sample_xy(np.arange(h.sizes["y"]) * step, np.zeros(h.sizes["y"]))
    np.testing.assert_allclose(h.y.values, y)
    # CRS through rioxarray, transform equal to the export's at that level
    assert h.rio.crs == CRS.from_wkt(s.meta.crs_wkt)


def test_transform_matches_the_export_and_lazy_reads(store, tmp_path, monkeypatch):
    s, _ = store
    export_geotiff(s, tmp_path / "l3.tif", 3)
    with rasterio.open(tmp_path / "l3.tif") as ex:
        ds = xr.open_dataset(s.url, engine=ENGINE, level=3)
        assert tuple(ds.height.rio.transform())[:6] == pytest.approx(tuple(ex.transform)[:6])
        assert ds.height.rio.crs == ex.crs
    calls = []
    real = xb.read_level_chunk
    monkeypatch.setattr(xb, "read_level_chunk", lambda *a: calls.append(a) or real(*a))
    ds = xr.open_dataset(s.url, engine=ENGINE, level=s.k)
    assert calls == []  # opening reads no block
    v = ds.height[40:45, 5:10].values  # one block touched
    assert len(calls) == 1 and calls[0][2:4] == (1, 0)
    np.testing.assert_array_equal(v, expected_level(s, s.k)[40:45, 5:10])


def test_datatree_of_all_levels(store):
    s, _ = store
    tree = xr.open_datatree(s.url, engine=ENGINE)
    assert sorted(tree.children) == sorted(f"level_{i}" for i in range(s.k + 1))
    top = tree[f"level_{s.k}"].to_dataset()
    np.testing.assert_array_equal(top.height.values, expected_level(s, s.k))
    assert tree["level_0"].height.shape == (3, 3)  # the 4 corners of 2x2 blocks + borders


def test_chunks_pickle_for_dask_workers(store):
    s, _ = store
    arr = level_dataarray(s, 4)
    again = pickle.loads(pickle.dumps(arr.data))
    np.testing.assert_array_equal(again.compute(), expected_level(s, 4))


def test_entry_point_and_guess(store, tmp_path):
    s, _ = store
    py = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    target = py["project"]["entry-points"]["xarray.backends"]["terrastream"]
    assert target == "tiler.xarray_backend:TerrastreamBackendEntrypoint"
    assert ENGINE().guess_can_open(s.url)
    tif = write_dem(tmp_path / "x.tif", fractal((5, 5)))
    assert not ENGINE().guess_can_open(tif)
    if "terrastream" in xr.backends.list_engines():  # installed with the entry point
        ds = xr.open_dataset(s.url, engine="terrastream", level=2)
        np.testing.assert_array_equal(ds.height.values, expected_level(s, 2))


@pytest.mark.shared_data
def test_real_float_dem_with_nodata(tmp_path):
    src = shared_file("xdem_aligned_elev_Longyearbyen.tif")
    s = tile(src, tmp_path / "ly.zarr", TileOptions(block_size=257))
    h = xr.open_dataset(s.url, engine=ENGINE, chunks={}).height
    with rasterio.open(src) as ds:
        ref = ds.read(1, masked=True).filled(np.nan).astype(np.float64)
        assert h.rio.crs == ds.crs
        assert tuple(h.rio.transform())[:6] == pytest.approx(tuple(ds.transform)[:6])
    np.testing.assert_array_equal(h.values.astype(np.float64), ref)


def test_raw_arrays_open_with_plain_xarray(store):
    """Every zarr array names its dimensions, so xarray.open_zarr reads each group."""
    s, _ = store
    root = xr.open_zarr(s.url, consolidated=False)
    assert {"errors", "mask", "level_index", "order_index"} <= set(root.data_vars)
    index = xr.open_zarr(s.url, group="index", consolidated=False)
    assert {"exists", "zmin", "zmax", "window", "digest", "done"} <= set(index.data_vars)
    np.testing.assert_array_equal(index.exists.values, s.index.exists)
    levels = xr.open_zarr(s.url, group="levels", consolidated=False)
    assert levels[str(s.k)].dims == ("block_row", "block_col", f"value_{s.k}")


def test_a_store_rewritten_in_place_opens_anew_and_old_datasets_refuse(tmp_path):
    """``tile --overwrite`` rebuilds a store a notebook has open: a fresh ``open_dataset`` reads
    the new build (it raised 'reopen it' for ever: the backend kept the old store per path),
    while a dataset opened before refuses to read on (never a mix of the two builds)."""
    from tiler.errors import StoreChangedError

    a = write_dem(tmp_path / "a.tif", fractal((70, 60), seed=1))
    b = write_dem(tmp_path / "b.tif", fractal((70, 60), seed=2))
    path = tmp_path / "s.zarr"
    tile(a, path, TileOptions(block_size=33))
    old = xr.open_dataset(path, engine="terrastream")  # (nothing read yet)
    first = xr.open_dataset(path, engine="terrastream", cache=False)
    with rasterio.open(a) as ds:
        np.testing.assert_array_equal(first["height"].values, ds.read(1))
    tile(b, path, TileOptions(block_size=33, overwrite=True))
    new = xr.open_dataset(path, engine="terrastream")
    with rasterio.open(b) as ds:
        np.testing.assert_array_equal(new["height"].values, ds.read(1))
    for stale in (old, first):  # opened on the old build: they refuse to read the new one
        with pytest.raises(StoreChangedError):
            stale["height"].values  # noqa: B018


def test_nodata_is_nan_for_rioxarray(store, tmp_path):
    """``rio.nodata`` is NaN (it was None: ``rio.to_raster`` wrote the NaNs untagged)."""
    h = xr.open_dataset(store[0].url, engine="terrastream")["height"]
    assert np.isnan(h.rio.nodata)
    h.rio.to_raster(tmp_path / "h.tif")
    with rasterio.open(tmp_path / "h.tif") as ds:
        assert ds.nodata is not None and np.isnan(ds.nodata)
        assert (~ds.read_masks(1).astype(bool)).sum() == (store[1] == -9999).sum()
