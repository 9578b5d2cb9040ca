"""Tiling end to end: round trips at every level, stores, resumption, bad input."""

from __future__ import annotations

import json
import os
import threading

import numpy as np
import pytest
import rasterio
import zarr
from demtools import fractal, write_dem
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rangeserver import LoopbackServer

import tiler.tile as tile_mod
from tiler.errors import (
    LayoutError,
    SourceError,
    SourceNotFoundError,
    StoreError,
    StoreExistsError,
    StoreIncompleteError,
    StoreVersionError,
)
from tiler.export import export_geotiff
from tiler.lease import WriterLease
from tiler.location import Location
from tiler.store import ATTR, open_store
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store


def assert_store_matches(store, data: np.ndarray, nodata=None, tol: float = 0.0):
    """Every level of every block equals the source's samples (exactly, or within tol)."""
    grid = store.grid
    valid_src = np.ones(data.shape, bool)
    if data.dtype.kind == "f":
        valid_src &= np.isfinite(data)
    if nodata is not None and not np.isnan(nodata):
        valid_src &= data != np.asarray(nodata).astype(data.dtype)
    for br, bc in grid.blocks():
        r0, c0, h, w = grid.block_window(br, bc)
        src = data[r0 : r0 + h, c0 : c0 + w]
        vs = valid_src[r0 : r0 + h, c0 : c0 + w]
        mask = store.read_mask((br, bc))
        np.testing.assert_array_equal(mask[:h, :w], vs)
        assert not mask[h:, :].any() and not mask[:, w:].any()
        for level in range(store.k + 1):
            step = 1 << (store.k - level)
            got = store.read_block((br, bc), level)
            sub = src[::step, ::step]
            m = vs[::step, ::step]
            g = got[: sub.shape[0], : sub.shape[1]]
            assert g.dtype == data.dtype
            if tol:
                assert np.all(np.abs(g[m].astype(np.float64) - sub[m]) <= tol)
            else:
                np.testing.assert_array_equal(g[m], sub[m])
            assert np.all(np.isfinite(got)) if got.dtype.kind == "f" else True


@settings(
    max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    h=st.integers(2, 70),
    w=st.integers(2, 70),
    dtype=st.sampled_from(["int16", "uint16", "int32", "float32", "float64"]),
    block=st.sampled_from([3, 5, 17, 33]),
    holes=st.booleans(),
    seed=st.integers(0, 1000),
)
def test_round_trip_any_shape_dtype_block(tmp_path_factory, h, w, dtype, block, holes, seed):
    tmp = tmp_path_factory.mktemp("rt")
    data = fractal((h, w), seed, dtype)
    nodata = None
    if holes:
        rng = np.random.default_rng(seed)
        nodata = -9999 if np.dtype(dtype).kind != "u" else 65535
        data[rng.random((h, w)) < 0.2] = nodata
    src = write_dem(tmp / "d.tif", data, nodata=nodata)
    store = tile(src, tmp / "d.zarr", TileOptions(block_size=block, workers=2))
    assert_store_matches(store, data, nodata)


def test_float_nan_nodata_and_extreme_heights(dem_factory, tmp_path):
    data = np.linspace(-11000, 9000, 40 * 37, dtype=np.float32).reshape(40, 37)
    data[5:9, 5:9] = np.nan
    src = dem_factory(data, nodata=float("nan"))
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    assert_store_matches(store, data, float("nan"))
    zmin, zmax = store.meta.extra["value_range"]
    assert zmin == pytest.approx(-11000) and zmax == pytest.approx(9000)


def test_coordinates_near_1e7(dem_factory, tmp_path):
    data = fractal((50, 50), 3)
    src = dem_factory(data, origin=(1.0e7, 1.0e7), cell=1.0)
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    assert store.grid.x0 == pytest.approx(1.0e7 + 0.5)
    assert_store_matches(store, data)


@pytest.mark.parametrize("step", [0.01, 0.5])
def test_precision_bound(dem_factory, tmp_path, step):
    data = (fractal((60, 45), 4, "float64") * 1.37).astype(np.float32)
    src = dem_factory(data)
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, precision=step))
    assert store.meta.encoding == "int-residual" and store.meta.storage_dtype == "uint32"
    # step/2 plus float32 rounding of the output
    assert_store_matches(store, data, tol=step / 2 + 1e-3)


@pytest.mark.parametrize("executor", ["threads", "processes"])
def test_worker_count_does_not_change_output(dem_factory, tmp_path, executor):
    data = fractal((150, 130), 5)
    src = dem_factory(data)
    a = tile(src, tmp_path / "a.zarr", TileOptions(block_size=33, workers=1))
    b = tile(src, tmp_path / "b.zarr", TileOptions(block_size=33, workers=2, executor=executor))
    ga, gb = (
        zarr.open_group(tmp_path / "a.zarr", mode="r"),
        zarr.open_group(tmp_path / "b.zarr", mode="r"),
    )
    for name in ["errors", "mask", *[f"levels/{i}" for i in range(a.k + 1)]]:
        np.testing.assert_array_equal(ga[name][...], gb[name][...])
    assert a.meta.source["checksum"] == b.meta.source["checksum"]


def test_store_opens_in_plain_zarr(dem_factory, tmp_path):
    src = dem_factory(fractal((40, 40), 6))
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    g = zarr.open_group(tmp_path / "s.zarr", mode="r")
    meta = g.attrs[ATTR]
    assert meta["format_version"] == 2 and meta["k"] == 4 and meta["complete"] is True
    assert g["levels/4"].shape == (3, 3, 17**2 - 9**2)
    assert g["level_index"][3, 3] == 4 and g["order_index"].shape == (17, 17)


def test_export_bit_identical_and_coarse_levels(dem_factory, tmp_path):
    data = fractal((70, 90), 7)
    data[3:6, 3:6] = -32768
    src = dem_factory(data, nodata=-32768)
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=33))
    export_geotiff(store, tmp_path / "out.tif")
    with rasterio.open(src) as a, rasterio.open(tmp_path / "out.tif") as b:
        np.testing.assert_array_equal(a.read(1), b.read(1))
        assert a.transform == b.transform and a.crs == b.crs and a.nodata == b.nodata
    export_geotiff(store, tmp_path / "l3.tif", level=3)
    with rasterio.open(tmp_path / "l3.tif") as c:
        np.testing.assert_array_equal(c.read(1), data[::4, ::4])
        with rasterio.open(src) as a:
            # sample (1, 1) of level 3 sits where source sample (4, 4) sits
            assert c.xy(1, 1) == pytest.approx(a.xy(4, 4))


def test_memory_url_store(dem_factory):
    data = fractal((40, 40), 8)
    store = tile(dem_factory(data), "memory://ts-test/s.zarr", TileOptions(block_size=17))
    assert_store_matches(open_store("memory://ts-test/s.zarr"), data)
    assert store.nbytes()["total"] > 0


@pytest.fixture
def http_server(tmp_path):
    with LoopbackServer(tmp_path) as url:
        yield url


def test_http_store(dem_factory, tmp_path, http_server):
    data = fractal((40, 40), 9)
    tile(dem_factory(data), tmp_path / "s.zarr", TileOptions(block_size=17))
    store = open_store(f"{http_server}/s.zarr")
    assert_store_matches(store, data)


def _interrupt_after(monkeypatch, n: int):
    real = tile_mod.process_block
    count = {"n": 0}
    lock = threading.Lock()

    def flaky(window, params):
        with lock:
            count["n"] += 1
            if count["n"] > n:
                raise KeyboardInterrupt("simulated kill")
        return real(window, params)

    monkeypatch.setattr(tile_mod, "process_block", flaky)


def test_interrupted_run_resumes_to_identical_store(dem_factory, tmp_path, monkeypatch):
    data = fractal((300, 300), 10)
    src = dem_factory(data)
    opts = TileOptions(block_size=17, workers=2, executor="threads")  # the patch is in-process
    # 19x19 blocks; the small levels are written per 16x16 shard, so interrupt mid-way
    _interrupt_after(monkeypatch, 300)
    with pytest.raises(KeyboardInterrupt):
        tile(src, tmp_path / "s.zarr", opts)
    with pytest.raises(StoreIncompleteError, match="run the same"):
        open_store(tmp_path / "s.zarr")
    # while a writer holds the store it is not called interrupted (a rerun would be refused)
    with WriterLease(Location(str(tmp_path / "s.zarr"))):
        with pytest.raises(
            StoreIncompleteError, match=rf"being written now by process {os.getpid()}"
        ):
            open_store(tmp_path / "s.zarr")
        rep = verify_store(tmp_path / "s.zarr")
        assert "being written now" in rep.problems[0].message and str(os.getpid()) in rep.writer
    assert verify_store(tmp_path / "s.zarr").writer is None  # released: interrupted again
    done = zarr.open_group(tmp_path / "s.zarr", mode="r")["index/done"][...]
    assert 0 < done.sum() < done.size
    monkeypatch.undo()
    seen = []
    resumed = tile(src, tmp_path / "s.zarr", opts, progress=seen.append)
    assert seen[-1].skipped == int(done.sum())
    fresh = tile(src, tmp_path / "fresh.zarr", opts)
    ga = zarr.open_group(tmp_path / "s.zarr", mode="r")
    gb = zarr.open_group(tmp_path / "fresh.zarr", mode="r")
    for name in [
        "errors",
        "mask",
        "index/digest",
        "index/zmin",
        *[f"levels/{i}" for i in range(5)],
    ]:
        np.testing.assert_array_equal(ga[name][...], gb[name][...])
    assert resumed.meta.source["checksum"] == fresh.meta.source["checksum"]


# ---- bad input -------------------------------------------------------------------------------


def test_missing_source(tmp_path):
    with pytest.raises(SourceNotFoundError, match="does not exist"):
        tile(tmp_path / "nope.tif", tmp_path / "s.zarr")
    assert not (tmp_path / "s.zarr").exists()


def test_not_a_raster(tmp_path):
    p = tmp_path / "notes.tif"
    p.write_text("this is not a raster")
    with pytest.raises(SourceError, match="cannot open .* as a raster"):
        tile(p, tmp_path / "s.zarr")
    assert not (tmp_path / "s.zarr").exists()


def test_one_by_one_raster(dem_factory, tmp_path):
    src = dem_factory(np.array([[5]], np.int16))
    with pytest.raises(SourceError, match="1x1 samples"):
        tile(src, tmp_path / "s.zarr")


def test_all_nodata_raster(dem_factory, tmp_path):
    src = dem_factory(np.full((20, 20), -9999, np.int16), nodata=-9999)
    with pytest.raises(SourceError, match="holds no terrain"):
        tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    assert not (tmp_path / "s.zarr").exists()


def test_bad_block_size():
    with pytest.raises(LayoutError, match="got 1000"):
        TileOptions(block_size=1000)


def test_existing_output_needs_overwrite(dem_factory, tmp_path):
    src = dem_factory(fractal((20, 20)))
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    with pytest.raises(StoreExistsError, match="overwrite=True to replace it"):
        tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=17, overwrite=True))


def test_overwrite_refuses_foreign_directory(dem_factory, tmp_path):
    src = dem_factory(fractal((20, 20)))
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "thesis.txt").write_text("do not delete")
    with pytest.raises(StoreExistsError):
        tile(src, tmp_path / "precious", TileOptions(block_size=17, overwrite=True))
    assert (tmp_path / "precious" / "thesis.txt").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_destination_non_root(dem_factory, tmp_path):
    src = dem_factory(fractal((20, 20)))
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    with pytest.raises(StoreError, match="not a writable directory"):
        tile(src, ro / "s.zarr")


def test_unwritable_destination(dem_factory, tmp_path):
    src = dem_factory(fractal((20, 20)))
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(StoreError, match="not a writable directory"):
        tile(src, blocker / "s.zarr")


def test_newer_format_version_refused(dem_factory, tmp_path):
    tile(dem_factory(fractal((20, 20))), tmp_path / "s.zarr", TileOptions(block_size=17))
    meta_path = tmp_path / "s.zarr" / "zarr.json"
    doc = json.loads(meta_path.read_text())
    doc["attributes"][ATTR]["format_version"] = 99
    meta_path.write_text(json.dumps(doc))
    with pytest.raises(StoreVersionError, match="version 99 is newer"):
        open_store(tmp_path / "s.zarr")


def test_band_out_of_range(dem_factory, tmp_path):
    src = dem_factory(fractal((20, 20)))
    with pytest.raises(SourceError, match="band 3 does not exist"):
        tile(src, tmp_path / "s.zarr", TileOptions(band=3))


def test_precision_on_integer_dem_refused(dem_factory, tmp_path):
    src = dem_factory(fractal((20, 20)))
    with pytest.raises(SourceError, match="Drop precision"):
        tile(src, tmp_path / "s.zarr", TileOptions(precision=0.1))


def test_a_source_edited_in_place_is_not_resumed(tmp_path, monkeypatch):
    """An interrupted tiling whose source is then edited in place, in a block already done and
    outside the fingerprint's windows (same size, same header): the rerun is refused naming the
    changed blocks (it resumed, exit 0, to a store mixing the two DEMs); the control: the same
    rerun on the unedited source resumes."""
    from tiler.errors import JobMismatchError

    data = fractal((600, 600), 11).astype(np.int16)
    src = tmp_path / "u.tif"
    at = rasterio.transform.from_origin(5e5, 5e6, 30, 30)
    profile = dict(driver="GTiff", width=600, height=600, count=1, dtype="int16")
    profile.update(crs="EPSG:32633", transform=at)
    with rasterio.open(src, "w", **profile) as ds:  # uncompressed: an edit keeps the size
        ds.write(data, 1)
    opts = TileOptions(block_size=33, workers=2, executor="threads")
    _interrupt_after(monkeypatch, 60)  # the first row of blocks (19 a row) is done
    with pytest.raises(KeyboardInterrupt):
        tile(src, tmp_path / "s.zarr", opts)
    monkeypatch.undo()
    size = src.stat().st_size
    with rasterio.open(src, "r+") as ds:  # rows 20..29, columns 270..284: block (0, 8)
        ds.write(data[20:30, 270:285] + 100, 1, window=rasterio.windows.Window(270, 20, 15, 10))
    assert src.stat().st_size == size
    with pytest.raises(JobMismatchError, match=r"source changed since .* 1 block\(s\).*\(0, 8\)"):
        tile(src, tmp_path / "s.zarr", opts)
    with rasterio.open(src, "r+") as ds:  # (the control: the original samples back)
        ds.write(data[20:30, 270:285], 1, window=rasterio.windows.Window(270, 20, 15, 10))
    s = tile(src, tmp_path / "s.zarr", opts)
    assert s.tile_summary.resumed and verify_store(tmp_path / "s.zarr", source=src).ok
