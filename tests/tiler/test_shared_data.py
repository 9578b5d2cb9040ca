"""Every real DEM in ../shared/data tiles and round-trips exactly (skipped when absent)."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from demtools import shared_file, write_dem
from test_tile import assert_store_matches

from tiler.export import export_geotiff
from tiler.tile import TileOptions, tile

pytestmark = pytest.mark.shared_data

CASES = [
    ("N44W072.hgt", None, 257),
    ("N42E001.hgt.zip", "/vsizip/{path}/N42E001.hgt", 257),
    ("N10W110.hgt.zip", "/vsizip/{path}/N10W110.hgt", 257),
    ("xdem_aligned_elev_Longyearbyen.tif", None, 257),
    ("landlab_zSW3.asc", None, 129),
    ("gzcommon_dem_nodata_nan.nc", None, 33),
    ("gzcommon_dem_squared.tif", None, 129),
    ("whitebox_DEM.tif", None, 65),
]


@pytest.mark.parametrize(("name", "pattern", "block"), CASES, ids=[c[0] for c in CASES])
def test_real_dem_round_trip(tmp_path, name, pattern, block):
    path = shared_file(name)
    src = pattern.format(path=path) if pattern else str(path)
    with rasterio.open(src) as ds:
        data = ds.read(1)
        nodata = ds.nodata
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=block, workers=2))
    assert_store_matches(store, data, nodata)
    out = tmp_path / "out.tif"
    export_geotiff(store, out)
    with rasterio.open(out) as ex:
        back = ex.read(1)
    same = (
        (back == data) | (np.isnan(back) & np.isnan(data))
        if data.dtype.kind == "f"
        else back == data
    )
    assert same.all()
    if name.startswith("N10W110"):  # almost flat: errors are tiny
        e = store.read_errors((0, 0))
        assert float(e["bound"][0].max()) <= 9


def test_topobathy_negative_heights(tmp_path):
    data = np.load(shared_file("topobathy.npz"))["topo"].astype(np.float32)
    src = write_dem(tmp_path / "tb.tif", data)
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=33))
    assert_store_matches(store, data)
    assert store.meta.extra["value_range"][0] < -1000
