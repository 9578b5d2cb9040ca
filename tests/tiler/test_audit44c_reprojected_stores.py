"""The rest of the tool on stores built with the day's new tiling features (audit 44c):
multi-CRS `--dst-crs` mosaics, sources on both sides of / past the antimeridian, and a ±inf
nodata value. Each store is checked through `info`, `verify --source`, `--repair`, an
interrupted tile and its resume, `export` and the xarray backend."""

from __future__ import annotations

import math

import numpy as np
import pytest
import rasterio
from demtools import fractal, write_dem
from rasterio.crs import CRS
from storetools import chunk_files, diff_stores

from tiler.accuracy import store_array
from tiler.errors import TilingInterrupted
from tiler.info import store_info
from tiler.store import open_store
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

DEG = 1 / 30


def _mixed(tmp_path):
    """A geographic tile and a UTM one (different CRSs) to mosaic onto EPSG:32632."""
    geo = write_dem(tmp_path / "geo.tif", fractal((61, 61), seed=5), crs="EPSG:4326",
                    origin=(10.0, 45.0), cell=1 / 60)  # fmt: skip
    utm = write_dem(tmp_path / "utm.tif", fractal((61, 61), seed=6), crs="EPSG:32632",
                    origin=(655000.0, 4990000.0), cell=600.0)  # fmt: skip
    return [geo, utm]


def _antimeridian(tmp_path):
    """Tiles on 179..180°E and -180..-179°."""
    data = fractal((61, 61), seed=3)
    west = write_dem(tmp_path / "w.tif", np.ascontiguousarray(data[:, :31]), crs="EPSG:4326",
                     origin=(179.0, -16.0), cell=DEG)  # fmt: skip
    east = write_dem(tmp_path / "e.tif", np.ascontiguousarray(data[:, 30:]), crs="EPSG:4326",
                     origin=(-180.0, -16.0), cell=DEG)  # fmt: skip
    return [west, east]


def _past_180(tmp_path):
    """One geographic source on 179..181°E (its CRS is wrapped when planned)."""
    data = fractal((61, 61), seed=3)
    return [write_dem(tmp_path / "am.tif", data, crs="EPSG:4326", origin=(179.0, -16.0), cell=DEG)]


def _inf_nodata(tmp_path):
    """A float DEM whose nodata value is +inf, with a hole of it."""
    data = fractal((61, 61), seed=7, dtype="float32")
    data[10:20, 10:20] = np.inf
    return [write_dem(tmp_path / "inf.tif", data, nodata=math.inf)]


def _abutting(tmp_path):
    """2x2 geographic tiles that share no sample (the seam fill between them)."""
    data = fractal((60, 60), seed=3)
    paths = []
    for r0 in (0, 30):
        for c0 in (0, 30):
            piece = np.ascontiguousarray(data[r0 : r0 + 30, c0 : c0 + 30])
            at = (10.0 + c0 * DEG, 45.0 - r0 * DEG)
            path = tmp_path / f"p{r0}_{c0}.tif"
            paths.append(write_dem(path, piece, crs="EPSG:4326", origin=at, cell=DEG))
    return paths


KINDS = {
    "abutting": (_abutting, "auto"),
    "mixed_crs": (_mixed, "auto"),
    "antimeridian": (_antimeridian, "auto"),
    "past_180": (_past_180, "auto"),
    "inf_nodata": (_inf_nodata, None),
}


def _build(tmp_path, kind, name="s.zarr", **kw):
    make, dst_crs = KINDS[kind]
    paths = make(tmp_path)
    opts = TileOptions(block_size=33, dst_crs=dst_crs, workers=1, executor="threads", **kw)
    return paths, opts, tile(paths if len(paths) > 1 else paths[0], tmp_path / name, opts)


def test_info_names_the_source_crss_and_inf_nodata(tmp_path):
    _, _, _ = _build(tmp_path, "mixed_crs", "mix.zarr")
    info = store_info(tmp_path / "mix.zarr")
    assert info["crs"] == "EPSG:32632" and info["source_crs"] == "EPSG:4326 + EPSG:32632"
    assert info["sources"] == 2
    m = open_store(tmp_path / "mix.zarr").meta
    t = m.geotransform
    assert info["bounds"] == [t[2], t[5] + t[4] * m.height, t[2] + t[0] * m.width, t[5]]
    _, _, _ = _build(tmp_path, "antimeridian", "am.zarr")
    info = store_info(tmp_path / "am.zarr")
    assert info["crs"] == "EPSG:32701" and info["source_crs"] == "EPSG:4326"
    assert info["extent"][2] - info["extent"][0] < 300_000  # one small grid, not the globe
    _, _, _ = _build(tmp_path, "inf_nodata", "inf.zarr")
    nodata = store_info(tmp_path / "inf.zarr")["nodata"]  # (`info --json` prints "inf")
    assert math.isinf(nodata) and nodata > 0


@pytest.mark.parametrize("kind", list(KINDS))
def test_verify_with_the_sources_passes_and_a_changed_source_is_reported(tmp_path, kind):
    paths, _, _ = _build(tmp_path, kind)
    rep = verify_store(tmp_path / "s.zarr", source=[str(p) for p in paths])
    assert rep.ok and rep.source_checked, rep.problems
    # the control: one sample of the last source changed by 7 m is a bad block
    with rasterio.open(paths[-1], "r+") as ds:
        a = ds.read(1)
        a[a.shape[0] // 2, a.shape[1] // 4] += 7
        ds.write(a, 1)
    rep = verify_store(tmp_path / "s.zarr", source=[str(p) for p in paths])
    assert not rep.ok and rep.bad_blocks, rep.problems


@pytest.mark.parametrize("kind", list(KINDS))
def test_repair_of_a_deleted_level_chunk_is_byte_identical(tmp_path, kind):
    paths, opts, _ = _build(tmp_path, kind)
    _build(tmp_path, kind, "ref.zarr")
    victim = chunk_files(tmp_path / "s.zarr", "levels/5")[0]
    victim.unlink()
    assert not verify_store(tmp_path / "s.zarr").ok
    src = paths if len(paths) > 1 else paths[0]
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, dst_crs=opts.dst_crs, repair=True))
    assert verify_store(tmp_path / "s.zarr").ok
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []


def _interrupt(monkeypatch, n):
    import tiler.tile as tile_mod

    real = tile_mod.process_block
    count = {"n": 0}

    def flaky(window, params):
        count["n"] += 1
        if count["n"] > n:
            raise KeyboardInterrupt("simulated Ctrl-C")
        return real(window, params)

    monkeypatch.setattr(tile_mod, "process_block", flaky)


@pytest.mark.parametrize("kind", list(KINDS))
def test_an_interrupted_tile_resumes_to_the_uninterrupted_store(tmp_path, monkeypatch, kind):
    make, dst_crs = KINDS[kind]
    paths = make(tmp_path)
    src = paths if len(paths) > 1 else paths[0]
    opts = TileOptions(block_size=33, dst_crs=dst_crs, workers=1, executor="threads")
    _interrupt(monkeypatch, 2)
    with pytest.raises(TilingInterrupted):
        tile(src, tmp_path / "s.zarr", opts)
    monkeypatch.undo()
    s = tile(src, tmp_path / "s.zarr", opts)
    assert s.tile_summary.blocks_skipped == 2
    tile(src, tmp_path / "ref.zarr", opts)
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []


def _export_mismatches(store, tif) -> list[str]:
    """What of the GeoTIFF ``tif`` differs from ``store``: crs, transform, nodata, mask,
    values (empty: it holds the store)."""
    m = store.meta
    heights, valid = store_array(store)
    with rasterio.open(tif) as ds:
        out = []
        if ds.crs != CRS.from_wkt(m.crs_wkt):
            out.append("crs")
        if tuple(ds.transform)[:6] != tuple(m.geotransform):
            out.append("transform")
        a = ds.read(1).astype(np.float64)
        nodata = ds.nodata
    if nodata != m.nodata:
        out.append("nodata")
    if a.shape != valid.shape or not np.array_equal(a != nodata, valid):
        out.append("mask")
    elif not np.array_equal(a[valid], heights[valid]):
        out.append("values")
    return out


@pytest.mark.parametrize("kind", list(KINDS))
def test_export_holds_the_stores_grid_crs_and_values(tmp_path, kind):
    from tiler.export import export_cog

    _, _, store = _build(tmp_path, kind)
    export_cog(store, tmp_path / "out.tif")
    assert _export_mismatches(store, tmp_path / "out.tif") == []


def test_a_positive_control_the_comparisons_fire(tmp_path):
    """An export of another store (the same sources, nearest resampling) is caught by the
    export comparison, and its store by diff_stores."""
    from tiler.export import export_cog

    paths, opts, store = _build(tmp_path, "mixed_crs")
    other = tile(paths, tmp_path / "near.zarr",
                 TileOptions(block_size=33, dst_crs="auto", resampling="nearest"))  # fmt: skip
    export_cog(other, tmp_path / "near.tif")
    assert "values" in _export_mismatches(store, tmp_path / "near.tif")
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "near.zarr") != []


@pytest.mark.parametrize("kind", list(KINDS))
def test_the_xarray_backend_holds_the_stores_grid_and_crs(tmp_path, kind):
    xr = pytest.importorskip("xarray")
    pytest.importorskip("rioxarray")
    _, _, store = _build(tmp_path, kind)
    m = store.meta
    heights, valid = store_array(store)
    ds = xr.open_dataset(tmp_path / "s.zarr", engine="terrastream")
    # every source is named (a mosaic's attribute held its first path only)
    assert all(str(p) in ds.attrs["source"] for p in m.source.get("paths") or [m.source["path"]])
    da = ds["height"]
    assert da.rio.crs == CRS.from_wkt(m.crs_wkt)
    assert tuple(da.rio.transform())[:6] == pytest.approx(tuple(m.geotransform))
    t = m.geotransform
    assert float(da.x[0]) == pytest.approx(t[2] + t[0] / 2)
    assert float(da.y[0]) == pytest.approx(t[5] + t[4] / 2)
    a = da.values
    assert np.array_equal(np.isfinite(a), valid)
    assert np.array_equal(a[valid], heights[valid])


def test_verify_reports_a_changed_sample_on_a_tiles_seam_edge(tmp_path):
    """The seam fill between abutting tiles holds the edge samples: a change of the east
    column of the first tile (by its neighbour's seam) is a bad block too."""
    paths, _, _ = _build(tmp_path, "abutting")
    with rasterio.open(paths[0], "r+") as ds:
        a = ds.read(1)
        a[a.shape[0] // 2, -1] += 9
        ds.write(a, 1)
    rep = verify_store(tmp_path / "s.zarr", source=[str(p) for p in paths])
    assert not rep.ok and rep.bad_blocks, rep.problems


CHILD = """
import sys, time
import tiler.tile as tm
real = tm.process_block
def slow(window, params):
    out = real(window, params)
    print("BLOCK", flush=True)
    time.sleep(0.2)
    return out
tm.process_block = slow
from cli.main import app
sys.argv = ["terrastream"] + sys.argv[1:]
app()
"""


def test_a_real_ctrl_c_of_a_multi_crs_mosaic_exits_130_and_resumes_identically(tmp_path):
    """`terrastream tile` of a mosaic of two CRSs, sent SIGINT after 3 blocks: exit 130, the
    store is unfinished, and the same command again gives the uninterrupted store's bytes."""
    import os
    import signal
    import subprocess
    import sys

    paths = _mixed(tmp_path)
    child = tmp_path / "child.py"
    child.write_text(CHILD)
    args = ["-q", "tile", *map(str, paths), str(tmp_path / "s.zarr"), "--dst-crs", "auto",
            "--block-size", "33", "--workers", "1"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    p = subprocess.Popen([sys.executable, str(child), *args], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=env)  # fmt: skip
    seen = 0
    for line in p.stdout:
        seen += line.startswith("BLOCK")
        if seen == 3:
            p.send_signal(signal.SIGINT)
            break
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert not verify_store(tmp_path / "s.zarr").complete
    opts = TileOptions(block_size=33, dst_crs="auto", workers=1, executor="threads")
    s = tile(paths, tmp_path / "s.zarr", opts)
    assert s.tile_summary.blocks_skipped >= 3
    tile(paths, tmp_path / "ref.zarr", opts)
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []


@pytest.mark.parametrize("extra", ["duplicate", "western_half"])
def test_a_redundant_overlapping_source_adds_no_sample(tmp_path, extra):
    """A source listed twice, or a piece of it listed after it (wholly covered: first-valid
    takes nothing from it), must give the store of the source alone. The seam fill took the
    rim between the source's outer sample centres and its pixel edges as a 'seam' beside the
    overlapping neighbour: +178 / +99 valid samples of 4996 invented (exit 0), and `verify
    --source` of a store against such a list reports blocks that differ."""
    data = fractal((61, 61), seed=3)
    whole = write_dem(tmp_path / "whole.tif", data, crs="EPSG:4326", origin=(10.0, 45.0),
                      cell=DEG)  # fmt: skip
    piece = write_dem(tmp_path / "piece.tif", np.ascontiguousarray(data[:, :31]),
                      crs="EPSG:4326", origin=(10.0, 45.0), cell=DEG)  # fmt: skip
    opts = TileOptions(block_size=33, dst_crs="auto", workers=1, executor="threads")
    one = tile(whole, tmp_path / "one.zarr", opts)
    two = tile([whole, whole if extra == "duplicate" else piece], tmp_path / "two.zarr", opts)
    assert one.meta.geotransform == two.meta.geotransform
    vo, vt = store_array(one)[1], store_array(two)[1]
    assert (vt & ~vo).sum() == 0, f"{(vt & ~vo).sum()} samples invented of {vo.sum()}"
