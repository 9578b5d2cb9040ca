"""Rasters written whole or not at all (``export``, ``synth``): a full disk left a GeoTIFF cut
short at OUT with exit 0 (GDAL reports the failed flush on stderr only), an interrupted
``synth`` a complete-looking DEM whose unwritten tiles GDAL filled with 0, and every export
was mode 0600. Controls: the same writes, whole, land at OUT with the umask's mode."""

from __future__ import annotations

import os

import numpy as np
import pytest
import rasterio
from demtools import fractal, write_dem

from tiler.atomic import raster_written_whole
from tiler.errors import OutputError
from tiler.export import export_geotiff
from tiler.synth import synth_dem
from tiler.tile import TileOptions, tile


def _write(path: str, n: int = 600) -> None:
    data = fractal((n, n), 1)
    with rasterio.open(
        path, "w", driver="GTiff", width=n, height=n, count=1, dtype=data.dtype, tiled=True,
        blockxsize=256, blockysize=256, compress="deflate",
    ) as d:  # fmt: skip
        d.write(data, 1)


def test_a_raster_cut_short_is_refused_and_leaves_nothing(tmp_path):
    out = tmp_path / "o.tif"

    def cut_short() -> None:
        with raster_written_whole(out) as tmp:
            _write(tmp)
            os.truncate(tmp, os.path.getsize(tmp) * 2 // 3)  # as a full disk leaves it

    with pytest.raises(OutputError, match=r"could not be read back whole.*disk full"):
        cut_short()
    assert not out.exists() and os.listdir(tmp_path) == []
    old = os.umask(0o027)
    try:
        with raster_written_whole(out) as tmp:  # the control: whole
            _write(tmp)
    finally:
        os.umask(old)
    assert out.exists() and (out.stat().st_mode & 0o777) == 0o640


def test_an_export_s_file_has_the_mode_a_new_file_gets(tmp_path):
    s = tile(
        write_dem(tmp_path / "d.tif", fractal((100, 100), 3)), tmp_path / "s.zarr", TileOptions(65)
    )
    old = os.umask(0o022)
    try:
        export_geotiff(s, tmp_path / "e.tif")
    finally:
        os.umask(old)
    assert ((tmp_path / "e.tif").stat().st_mode & 0o777) == 0o644


def test_an_interrupted_synth_leaves_no_dem(tmp_path):
    calls = []

    def stop(done: int, total: int) -> None:
        calls.append(done)
        if len(calls) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        synth_dem(tmp_path / "s.tif", 1025, seed=3, window=256, progress=stop)
    assert os.listdir(tmp_path) == []
    synth_dem(tmp_path / "s.tif", 1025, seed=3, window=256)  # the control: whole
    with rasterio.open(tmp_path / "s.tif") as d:
        assert d.shape == (1025, 1025) and int(np.count_nonzero(d.read(1) == 0)) == 0
