"""Heights in metres: band scale/offset and feet applied exactly on read, integers kept."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from demtools import fractal, write_dem

from tiler.errors import SourceError
from tiler.export import export_geotiff
from tiler.info import store_info
from tiler.tile import TileOptions, tile
from tiler.vertical import metres_per_unit, to_metres, vertical_meta


def scaled_dem(path, data, scale=1.0, offset=0.0, units=None, nodata=None):
    write_dem(path, data, nodata=nodata)
    with rasterio.open(path, "r+") as ds:
        ds.scales = (scale,)
        ds.offsets = (offset,)
        if units:
            ds.units = (units,)
    return path


@pytest.mark.parametrize(
    ("dtype", "scale", "offset", "units", "factor"),
    [
        ("int16", 0.1, 0.0, "m", 1.0),  # decimetres in int16
        ("int16", 1.0, 100.0, None, 1.0),  # an offset only
        ("float32", 1.0, 0.0, "ft", 0.3048),  # feet
        ("int32", 0.01, -50.0, "US survey foot", 1200 / 3937),  # all three
    ],
    ids=["dm-scale", "offset", "feet", "scale-offset-ftUS"],
)
def test_heights_come_back_in_metres_exactly(tmp_path, dtype, scale, offset, units, factor):
    data = fractal((50, 40), seed=7, dtype=dtype)
    src = scaled_dem(tmp_path / "s.tif", data, scale, offset, units, nodata=-9999)
    data[3, 4] = -9999
    with rasterio.open(src, "r+") as ds:
        ds.write(data, 1)
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    v = store.meta.extra["vertical"]
    assert (v["scale"], v["offset"]) == (scale, offset) and v["metres_per_unit"] == factor
    metres = data.astype(np.float64) * (scale * factor) + offset * factor  # tiler.vertical
    valid = data != -9999
    for br, bc in store.grid.blocks():
        r0, c0, h, w = store.grid.block_window(br, bc)
        got = store.read_block((br, bc))[:h, :w]
        m = store.read_mask((br, bc))[:h, :w]
        assert got.dtype == np.float64
        np.testing.assert_array_equal(got[m], metres[r0 : r0 + h, c0 : c0 + w][m])
        assert store.index.zmin[br, bc] == metres[r0 : r0 + h, c0 : c0 + w][m].min()
    assert store.meta.extra["value_range"] == [metres[valid].min(), metres[valid].max()]
    # the integers are kept: the export is the source, scale and offset included
    export_geotiff(store, tmp_path / "out.tif")
    with rasterio.open(tmp_path / "out.tif") as out:
        np.testing.assert_array_equal(out.read(1), data)
        assert out.scales == (scale,) and out.offsets == (offset,)
    info = store_info(tmp_path / "s.zarr")
    assert info["vertical"] == v
    lo, hi = info["value_range_stored"]
    assert lo == pytest.approx(data[valid].min()) and hi == pytest.approx(data[valid].max())


def test_static_errors_are_in_metres(tmp_path):
    data = fractal((33, 33), seed=8)
    plain = tile(write_dem(tmp_path / "p.tif", data), tmp_path / "p.zarr", TileOptions(33))
    feet = scaled_dem(tmp_path / "f.tif", data, units="ft")
    scaled = tile(feet, tmp_path / "f.zarr", TileOptions(block_size=33))
    for name in ("qiu", "bound"):
        e_plain = np.concatenate([x.ravel() for x in plain.read_errors((0, 0))[name]])
        e_feet = np.concatenate([x.ravel() for x in scaled.read_errors((0, 0))[name]])
        assert e_plain.max() > 0
        np.testing.assert_allclose(e_feet, e_plain * 0.3048, rtol=2e-3)  # float16 storage


def test_plain_metres_record_nothing_and_unknown_units_are_flagged(caplog):
    assert vertical_meta(1.0, 0.0, "m") is None and vertical_meta(1.0, 0.0, None) is None
    assert metres_per_unit("Feet") == 0.3048 and metres_per_unit("furlong") is None
    assert vertical_meta(1.0, 0.0, "furlong") is None  # taken as metres...
    assert "furlong" in caplog.text  # ...but said so

    class Meta:
        extra = {"vertical": {"scale": 2.0, "offset": 1.0, "metres_per_unit": 0.5}}

    np.testing.assert_array_equal(to_metres(Meta, np.array([0, 3], np.int16)), [0.5, 3.5])


@pytest.mark.parametrize(
    ("dtype", "scale", "units"), [("int16", 0.1, "m"), ("float32", 1.0, "ft")], ids=["dm", "ft"]
)
def test_incremental_decode_from_metres(tmp_path, dtype, scale, units):
    """The streamer decodes level L from cached heights (metres) and the raw level L."""
    data = fractal((33, 33), seed=10, dtype=dtype)
    src = scaled_dem(tmp_path / "s.tif", data, scale=scale, units=units)
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=33))
    full = store.read_levels((0, 0), store.k)
    for level in range(1, store.k + 1):
        raw = store.read_level_raw((0, 0), level)
        got = store.to_heights(store.decode_next(full[:level], raw))
        np.testing.assert_array_equal(got, full[level])


def test_precision_with_a_vertical_scale_is_refused(tmp_path):
    src = scaled_dem(tmp_path / "f.tif", fractal((20, 20), dtype="float32"), units="ft")
    with pytest.raises(SourceError, match="precision with a band scale"):
        tile(src, tmp_path / "f.zarr", TileOptions(block_size=17, precision=0.01))


def test_feet_declared_only_by_a_compound_crs_are_feet(tmp_path):
    """A DEM in EPSG:32633+8228 (NAVD88 height in ft) whose band declares no unit was tiled as
    metres (3.28x too tall, exit 0): the vertical CRS's unit now applies when the band gives
    none. Control: the same samples in EPSG:32633+5703 (metres) stay as they are."""
    data = fractal((40, 30), seed=9, dtype="float32") + 300.0
    base = write_dem(tmp_path / "d.tif", data)
    with rasterio.open(base) as ds:
        gt = ", ".join(repr(v) for v in ds.transform.to_gdal())
    for crs, factor in (("EPSG:32633+8228", 0.3048), ("EPSG:32633+5703", 1.0)):
        # a VRT: a GeoTIFF would also write the unit as the band's (GDAL reads it back so)
        wkt = rasterio.crs.CRS.from_user_input(crs).to_wkt().replace('"', "&quot;")
        path = tmp_path / f"{factor}.vrt"
        path.write_text(
            f'<VRTDataset rasterXSize="30" rasterYSize="40"><SRS>{wkt}</SRS>'
            f'<GeoTransform>{gt}</GeoTransform><VRTRasterBand dataType="Float32" band="1">'
            '<SimpleSource><SourceFilename relativeToVRT="1">d.tif</SourceFilename>'
            "<SourceBand>1</SourceBand></SimpleSource></VRTRasterBand></VRTDataset>"
        )
        with rasterio.open(path) as ds:
            assert not ds.units[0]  # no unit on the band: only the CRS says feet
        s = tile(str(path), tmp_path / f"{factor}.zarr", TileOptions(block_size=65))
        got = s.read_block((0, 0))[:40, :30]
        np.testing.assert_allclose(got, data.astype(np.float64) * factor, rtol=1e-12)


def test_esri_and_us_spellings_of_the_survey_foot_are_known():
    for name in ("Foot_US", "US survey feet", "ft_US", "us foot"):
        assert metres_per_unit(name) == pytest.approx(1200 / 3937), name
    assert metres_per_unit("foot_international") == 0.3048
