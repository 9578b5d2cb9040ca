"""COG export: valid per rio-cogeo, overviews are the store's own levels, georeferencing known."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from demtools import fractal, shared_file, write_dem
from rio_cogeo.cogeo import cog_validate
from typer.testing import CliRunner

from cli.main import app
from tiler.export import cog_levels, export_cog, export_geotiff
from tiler.store import open_store
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    d = tmp_path_factory.mktemp("cog")
    data = fractal((1300, 1100), seed=12)
    data[100:140, 200:260] = -32768
    src = write_dem(d / "dem.tif", data, nodata=-32768)
    return tile(src, d / "dem.zarr", TileOptions(block_size=257, workers=2)), src, d


def test_cog_is_valid_and_lossless(store, tmp_path):
    s, src, _ = store
    out = tmp_path / "dem_cog.tif"
    levels = export_cog(s, out)
    assert levels == [8, 7, 6]  # 1300 -> 650 -> 325: stops once a level fits a 512 tile
    valid, errors, warnings = cog_validate(str(out), strict=True)  # warnings count as errors
    assert valid and not errors and not warnings, (errors, warnings)
    with rasterio.open(src) as a, rasterio.open(out) as b:
        np.testing.assert_array_equal(b.read(1), a.read(1))
        assert b.transform == a.transform and b.crs == a.crs and b.nodata == a.nodata
        assert b.overviews(1) == [2, 4]


def test_overviews_are_the_store_levels_not_resampled(store, tmp_path):
    s, src, _ = store
    out = tmp_path / "dem_cog.tif"
    export_cog(s, out)
    with rasterio.open(src) as a:
        full = a.read(1)
    for j, lv in enumerate(cog_levels(s, s.k)[1:]):
        step = 1 << (s.k - lv)
        with rasterio.open(out, overview_level=j) as ov:
            got = ov.read(1)
        # bit for bit every step-th source sample: no averaging, no shift in the samples
        np.testing.assert_array_equal(got, full[::step, ::step])
        export_geotiff(s, tmp_path / f"l{lv}.tif", lv, creation={"compress": "none"})
        with rasterio.open(tmp_path / f"l{lv}.tif") as lvl, rasterio.open(out) as cog:
            np.testing.assert_array_equal(lvl.read(1), got)
            # georeferencing: the level export keeps sample centres; GDAL's overview grid
            # puts pixel i (step-1)/2 source pixels further right/down (documented)
            t_level = lvl.transform
            ov_x0 = cog.transform.c  # an overview shares the full raster's corner...
            assert t_level.c == pytest.approx(ov_x0 - (step - 1) / 2 * cog.transform.a)
            x_sample, _ = cog.transform * (0.5, 0.5)  # ...and sample 0's centre is here
            assert (t_level * (0.5, 0.5))[0] == pytest.approx(x_sample)


def test_positive_control_a_plain_geotiff_is_not_a_cog(store, tmp_path):
    s, _, _ = store
    export_geotiff(s, tmp_path / "plain.tif")
    valid, errors, warnings = cog_validate(str(tmp_path / "plain.tif"), strict=True)
    assert not valid and any("overviews" in e for e in errors + warnings)


def test_cli_export_defaults_to_cog_for_tif(store, tmp_path):
    s, _, _ = store
    runner = CliRunner()
    r = runner.invoke(app, ["export", s.url, str(tmp_path / "a.tif")])
    assert r.exit_code == 0, r.output
    assert "COG of level 8 of 8, overviews = levels 7, 6" in r.output
    assert cog_validate(str(tmp_path / "a.tif"), strict=True)[0]
    r = runner.invoke(app, ["export", s.url, str(tmp_path / "b.tif"), "--format", "gtiff"])
    assert r.exit_code == 0, r.output
    assert not cog_validate(str(tmp_path / "b.tif"), strict=True)[0]
    # a level that fits one COG tile has no overview, said in words ("levels none" before)
    r = runner.invoke(app, ["export", s.url, str(tmp_path / "c.tif"), "--level", "5"])
    assert r.exit_code == 0, r.output
    assert "COG of level 5 of 8, no overviews (it fits one 512² tile)" in r.output


@pytest.mark.shared_data
def test_srtm_cog_validates(tmp_path):
    src = shared_file("N44W072.hgt")
    s = tile(src, tmp_path / "n44.zarr", TileOptions(block_size=257, workers=2))
    export_cog(s, tmp_path / "n44.tif")
    assert cog_validate(str(tmp_path / "n44.tif"), strict=True) == (True, [], [])
    with rasterio.open(src) as a, rasterio.open(tmp_path / "n44.tif") as b:
        np.testing.assert_array_equal(a.read(1), b.read(1))


@pytest.mark.parametrize("kind", ["Point", "Area", None])
def test_area_or_point_is_kept(tmp_path, kind):
    """A source whose samples are points (SRTM's AREA_OR_POINT=Point) exports as points, with
    the same geotransform read back; an Area or untagged source stays as it was (the control:
    exported as Area before)."""
    src = write_dem(tmp_path / "p.tif", fractal((300, 280), seed=3))
    if kind is not None:
        with rasterio.open(src, "r+") as ds:
            ds.update_tags(AREA_OR_POINT=kind)
    s = tile(src, tmp_path / "p.zarr", TileOptions(block_size=257))
    export_cog(s, tmp_path / "c.tif")
    export_geotiff(s, tmp_path / "g.tif")
    for out in ("c.tif", "g.tif"):
        with rasterio.open(src) as a, rasterio.open(tmp_path / out) as b:
            assert b.tags().get("AREA_OR_POINT") == (kind or "Area"), out
            assert b.transform == a.transform, out
            np.testing.assert_array_equal(b.read(1), a.read(1))
    assert cog_validate(str(tmp_path / "c.tif"), strict=True)[0]


def _small(tmp_path, name="s.zarr", seed=4):
    src = write_dem(tmp_path / f"{name}.tif", fractal((300, 280), seed=seed))
    return tile(src, tmp_path / name, TileOptions(block_size=129)), src


@pytest.mark.parametrize("fmt", ["gtiff", "cog"])
def test_a_failed_export_leaves_no_raster_and_keeps_the_old_one(tmp_path, fmt):
    """A read error half way (a chunk deleted) leaves no partial raster that looks complete, and
    an ``out`` being replaced keeps its bytes (before, a GeoTIFF with the first block row)."""
    from tiler.errors import StoreError

    s, _ = _small(tmp_path)
    (tmp_path / "s.zarr" / "levels" / "7" / "c" / "1" / "1" / "0").unlink()
    s = open_store(tmp_path / "s.zarr")
    export = export_cog if fmt == "cog" else export_geotiff
    with pytest.raises(StoreError, match="missing"):
        export(s, tmp_path / "new.tif")
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix != ".zarr") == ["s.zarr.tif"]
    (tmp_path / "old.tif").write_bytes(b"the old export")
    with pytest.raises(StoreError, match="missing"):
        export(s, tmp_path / "old.tif")
    assert (tmp_path / "old.tif").read_bytes() == b"the old export"


def test_a_store_replaced_during_an_export_is_an_error_not_a_mixed_raster(tmp_path):
    """The store is tiled again from another DEM once the last block row is read: the final
    check finds it (a remote store is checked at most once a second while reading, so an
    export could finish on a mixed DEM), and no raster is left."""
    from tiler.errors import StoreChangedError

    s, _ = _small(tmp_path)
    other = write_dem(tmp_path / "other.tif", fractal((300, 280), seed=5))

    def swap(done, total):
        if done == total:
            tile(other, tmp_path / "s.zarr", TileOptions(block_size=129, overwrite=True))

    with pytest.raises(StoreChangedError):
        export_geotiff(s, tmp_path / "x.tif", progress=swap)
    assert not (tmp_path / "x.tif").exists()
    export_geotiff(open_store(tmp_path / "s.zarr"), tmp_path / "y.tif")  # (the control)
    with rasterio.open(tmp_path / "y.tif") as a, rasterio.open(other) as b:
        np.testing.assert_array_equal(a.read(1), b.read(1))


def test_export_declares_no_nodata_and_invents_no_crs_a_source_lacks(tmp_path):
    """A float DEM without nodata whose edge blocks hold padding exported with nodata NaN
    (the padding counted as nodata), and a point DEM without a CRS gained GDAL's
    LOCAL_CS["unnamed"] with its AREA_OR_POINT tag, which a re-tiling kept. Controls: a DEM
    with NaN voids exports nodata NaN; a point DEM with a CRS keeps its tag."""
    data = np.round(fractal((300, 280), seed=3).astype(np.float32) * 4) / 4
    src = tmp_path / "f.asc"  # an ASCII grid by its cell centres: points, no CRS
    src.write_text(
        "ncols 280\nnrows 300\nxllcenter 0.5\nyllcenter 0.5\ncellsize 1\n"
        + "\n".join(" ".join(f"{v:g}" for v in row) for row in data)
        + "\n"
    )
    with rasterio.open(src) as ds:
        assert ds.crs is None and ds.tags().get("AREA_OR_POINT") == "Point"
    s = tile(str(src), tmp_path / "f.zarr", TileOptions(block_size=257))  # 2x2, padding
    assert s.index.has_nodata.any()  # (the padding)
    for out, write in (("g.tif", export_geotiff), ("c.tif", export_cog)):
        write(s, tmp_path / out)
        with rasterio.open(tmp_path / out) as b:
            assert b.nodata is None and b.crs is None, out
            np.testing.assert_array_equal(b.read(1), data)
    voids = data.copy()
    voids[10:20, 10:20] = np.nan
    v = tile(write_dem(tmp_path / "v.tif", voids), tmp_path / "v.zarr", TileOptions(257))
    export_geotiff(v, tmp_path / "v_out.tif")
    with rasterio.open(tmp_path / "v_out.tif") as b:
        assert b.nodata is not None and np.isnan(b.nodata)
