"""Values that cannot be heights: beyond ±1000 km (an undeclared nodata value such as float32's
-3.4e38, heights in millimetres) are refused naming the file, the block, the first sample and
the declaration that fixes it (they overflowed the error bounds, then `render` failed with
"argument out of range"); a signed integer DEM reaching its type's minimum without a nodata
value (SRTM's -32768 voids) is tiled with a warning. Controls: the same DEMs with nodata
declared, and real extremes (-11 km, +9 km)."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
from demtools import fractal, write_dem

from tiler.errors import HeightRangeError
from tiler.store import open_store
from tiler.tile import BlockParams, TileOptions, process_block, tile

F32_MIN = float(np.finfo(np.float32).min)


def _dem(value: float, dtype: str = "float32") -> np.ndarray:
    data = fractal((70, 60), 1, dtype=dtype)
    data[40:45, 50:55] = value
    return data


@pytest.mark.parametrize("executor", ["threads", "processes"])
def test_an_undeclared_float_sentinel_is_refused_naming_where(tmp_path, executor):
    src = write_dem(tmp_path / "und.tif", _dem(F32_MIN))
    opts = TileOptions(block_size=33, executor=executor, workers=2)
    with pytest.raises(HeightRangeError) as e:
        tile(src, tmp_path / "s.zarr", opts)
    msg = str(e.value)
    assert msg.startswith("und.tif, block (1, 1), first at row 40, column 50 of the DEM"), msg
    assert "25 sample(s) of -3.40282e+38 m" in msg and "-a_nodata" in msg and "und.tif`" in msg
    assert (e.value.row, e.value.col, e.value.count) == (40, 50, 25)
    # no unfinished store is left that readers would call interrupted and a rerun could never
    # finish (the source must change first: another job)
    assert not (tmp_path / "s.zarr").exists()
    # the control: declared, the same samples are nodata and the store is complete
    ok = write_dem(tmp_path / "ok.tif", _dem(F32_MIN), nodata=F32_MIN)
    s = tile(ok, tmp_path / "ok.zarr", opts)
    assert s.meta.complete and s.meta.extra["value_range"][0] > -1e4
    # and a finished store that the refused source was to replace is kept as it was
    with pytest.raises(HeightRangeError):
        tile(src, tmp_path / "ok.zarr", dataclasses.replace(opts, overwrite=True))
    assert open_store(tmp_path / "ok.zarr").meta.complete


def test_heights_in_millimetres_are_refused_and_real_extremes_are_not(tmp_path):
    mm = (fractal((40, 30), 2, dtype="float64") * 1000 + 8_000_000).astype(np.int32)
    with pytest.raises(HeightRangeError, match="other units, declare the band's scale"):
        tile(write_dem(tmp_path / "mm.tif", mm), tmp_path / "mm.zarr", TileOptions(33))
    # the controls: a trench at -11 km beside a peak at +9 km (and float32), tiled as heights
    ext = fractal((40, 30), 3)
    ext[5, 5], ext[30, 20] = -11_000, 9_000
    s = tile(write_dem(tmp_path / "ext.tif", ext), tmp_path / "ext.zarr", TileOptions(33))
    assert s.meta.extra["value_range"] == [-11000.0, 9000.0]
    f = ext.astype(np.float32)
    s = tile(write_dem(tmp_path / "f.tif", f), tmp_path / "f.zarr", TileOptions(33))
    assert s.meta.complete


def test_process_block_refuses_through_the_api_too():
    data = _dem(-1e30)[:33, :33].copy()
    data[3, 4] = 1e30
    params = BlockParams(k=5, dtype="float32", storage_dtype="uint32", nodata=None,
                         precision=None, error_cap=4)  # fmt: skip
    with pytest.raises(HeightRangeError, match=r"1 sample\(s\) of 1e\+30 m"):
        process_block(data, params)


def test_the_int16_minimum_without_nodata_is_tiled_with_a_warning(tmp_path, caplog):
    voids = fractal((40, 30), 4)
    voids[10:15, 10:15] = -32768
    with caplog.at_level(logging.WARNING, logger="tiler.tile"):
        s = tile(write_dem(tmp_path / "v.tif", voids), tmp_path / "v.zarr", TileOptions(33))
    assert s.meta.complete and s.meta.extra["value_range"][0] == -32768
    assert "v.tif reaches -32768, the int16 minimum, and declares no nodata value" in caplog.text
    assert "`gdal_edit.py -a_nodata -32768 v.tif`" in caplog.text
    # the controls: declared, or not reached, no warning
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="tiler.tile"):
        tile(write_dem(tmp_path / "d.tif", voids, nodata=-32768), tmp_path / "d.zarr",
             TileOptions(33))  # fmt: skip
        voids[10:15, 10:15] = -32767
        tile(write_dem(tmp_path / "n.tif", voids), tmp_path / "n.zarr", TileOptions(33))
    assert "minimum" not in caplog.text


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # (the overflow the refusal now spares)
def test_a_store_tiled_with_such_values_before_is_refused_by_the_viewers(tmp_path, monkeypatch):
    """Stores tiled before the refusal may hold -3.4e38 "heights": every viewer refuses them
    naming the value (`render` failed with "struct.error: argument out of range")."""
    from typer.testing import CliRunner

    import tiler.tile as tile_mod
    from cli.main import app
    from streamer.session import open_session
    from tiler.errors import StoreHeightsError

    src = write_dem(tmp_path / "und.tif", _dem(F32_MIN))
    monkeypatch.setattr(tile_mod, "MAX_HEIGHT_M", float("inf"))  # as tiled before
    tile(src, tmp_path / "old.zarr", TileOptions(block_size=33, workers=1))
    monkeypatch.undo()
    with pytest.raises(StoreHeightsError, match=r"heights of -3\.40282e\+38 m"):
        open_session(str(tmp_path / "old.zarr"))
    r = CliRunner().invoke(
        app, ["render", str(tmp_path / "old.zarr"), "-o", str(tmp_path / "o.png")]
    )
    assert r.exit_code == 2 and "beyond ±1000 km" in r.output and "und.tif" in r.output, r.output
    # the control: the same DEM declared opens
    ok = write_dem(tmp_path / "ok.tif", _dem(F32_MIN), nodata=F32_MIN)
    tile(ok, tmp_path / "ok.zarr", TileOptions(block_size=33, workers=1))
    with open_session(str(tmp_path / "ok.zarr")) as s:
        assert s.store.meta.complete


def test_in_a_mosaic_the_source_holding_the_sample_is_named(tmp_path):
    west = write_dem(tmp_path / "west.tif", fractal((40, 30), 5, dtype="float32"))
    east_data = fractal((40, 30), 6, dtype="float32")
    east_data[10, 12] = F32_MIN
    east = write_dem(tmp_path / "east.tif", east_data, origin=(500000.0 + 30 * 30, 5e6))
    with pytest.raises(HeightRangeError) as e:
        tile([west, east], tmp_path / "m.zarr", TileOptions(block_size=33, workers=1))
    msg = str(e.value)  # (the control, west's name, would be the mosaic's first source)
    assert msg.startswith("east.tif, block (0, 1), first at row 10, column 42"), msg
    assert "`gdal_edit.py -a_nodata -3.4028234663852886e+38 east.tif`" in msg, msg


@pytest.mark.parametrize("value", [float("inf"), float("-inf")])
def test_infinite_samples_are_refused_not_dropped_as_nodata(tmp_path, value):
    """±inf is no height: it was made nodata without a count (a DEM of 2,100 samples tiled
    25 holes with exit 0). It is now refused like any value beyond ±1000 km, in one source and
    in a mosaic; declared as the nodata value it is nodata (the control), and NaN stays
    nodata."""
    src = write_dem(tmp_path / "inf.tif", _dem(value))
    with pytest.raises(HeightRangeError) as e:
        tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, workers=1))
    msg = str(e.value)
    assert msg.startswith("inf.tif, block (1, 1), first at row 40, column 50"), msg
    assert f"25 sample(s) of {value:g} m" in msg and f"-a_nodata {value!r}" in msg, msg
    assert not (tmp_path / "s.zarr").exists()
    west = write_dem(tmp_path / "west.tif", fractal((70, 60), 5, dtype="float32"))
    with pytest.raises(HeightRangeError, match=r"^inf\.tif"):  # over another source
        tile([src, west], tmp_path / "m.zarr", TileOptions(block_size=33, workers=1))
    # the controls: declared nodata, the same samples are holes; NaN is nodata as before
    ok = write_dem(tmp_path / "ok.tif", _dem(value), nodata=value)
    s = tile(ok, tmp_path / "ok.zarr", TileOptions(block_size=33, workers=1))
    assert s.meta.complete and np.isfinite(s.meta.extra["value_range"]).all()
    # (a nodata of ±inf could not be written at all: "Out of range float values are not JSON
    # compliant"; it is now "Infinity" in the metadata, read back as the same value)
    from tiler.verify import verify_store

    assert open_store(tmp_path / "ok.zarr").meta.nodata == value
    assert verify_store(tmp_path / "ok.zarr").ok
    nan = write_dem(tmp_path / "nan.tif", _dem(float("nan")))
    assert tile(nan, tmp_path / "nan.zarr", TileOptions(block_size=33, workers=1)).meta.complete


def test_a_reprojected_sources_refusal_says_the_place_is_on_the_reprojected_grid(tmp_path):
    """Warped, the row and column named are the target grid's, not the source's: the message
    said "of the DEM" (read as the source's own row 30 when it was the grid's 43). The control:
    unwarped, "of the DEM" (they are the same)."""
    data = fractal((61, 61), 2, dtype="float32")
    data[30, 30] = np.inf
    src = write_dem(tmp_path / "g.tif", data, crs="EPSG:4326", origin=(10.0, 45.0), cell=1 / 30)
    opts = TileOptions(block_size=33, workers=1, dst_crs="auto")
    with pytest.raises(HeightRangeError, match=r"of the reprojected grid: "):
        tile(src, tmp_path / "w.zarr", opts)
    with pytest.raises(HeightRangeError, match=r"row 30, column 30 of the DEM: "):
        tile(src, tmp_path / "p.zarr", TileOptions(block_size=33, workers=1))
