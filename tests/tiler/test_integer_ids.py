"""Block ids, levels and extents must be integers: ``int()`` truncated 1.7 and read "1", and
``read_block((1.7, 0))`` returned block (1, 0), ``read_block(b, 2.7)`` level 2, the xarray
backend and ``export`` level 2 for 2.5, with no error (negative and too large values were
already refused). Controls: Python and numpy integers read the same data."""

from __future__ import annotations

import numpy as np
import pytest
from demtools import fractal, write_dem

from tiler.errors import LayoutError
from tiler.export import export_geotiff
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    d = tmp_path_factory.mktemp("ids")
    return tile(write_dem(d / "d.tif", fractal((100, 100), 3)), d / "s.zarr", TileOptions(65))


@pytest.mark.parametrize(
    "block", [(1.7, 0), (True, 0), ("1", 0), (1, 0, 5), (1,), "10", (np.float64(1.0), 0)]
)
def test_a_block_id_that_is_not_two_integers_is_refused(store, block):
    with pytest.raises(LayoutError, match="block"):
        store.read_block(block)
    with pytest.raises(LayoutError, match="block"):
        store.read_errors(block)


@pytest.mark.parametrize("level", [2.7, 2.0, "3", True, np.float32(3)])
def test_a_level_that_is_not_an_integer_is_refused(store, level, tmp_path):
    with pytest.raises(LayoutError, match=r"level must be an integer"):
        store.read_block((0, 0), level)
    with pytest.raises(LayoutError, match=r"level must be an integer"):
        store.read_level_raw((0, 0), level)
    with pytest.raises(LayoutError, match=r"level must be an integer"):
        store.block_extent((0, 0), level)
    with pytest.raises(LayoutError, match=r"level must be an integer"):
        export_geotiff(store, tmp_path / "e.tif", level=level)
    assert not (tmp_path / "e.tif").exists()


def test_an_extent_that_is_not_integers_is_refused(store):
    with pytest.raises(LayoutError, match=r"extent rows must be an integer, got 2.5"):
        store.read_block((0, 0), extent=(2.5, 3))


def test_python_and_numpy_integers_read_the_same(store):
    a = store.read_block((1, 0), 3)
    b = store.read_block((np.int64(1), np.uint8(0)), np.int32(3))
    np.testing.assert_array_equal(a, b)
    assert store.read_block((0, 0), extent=(np.int64(5), 3)).shape == (5, 3)


def test_the_xarray_backend_refuses_a_fractional_level(store):
    xr = pytest.importorskip("xarray")
    with pytest.raises(LayoutError, match=r"level must be an integer, got 2.7"):
        xr.open_dataset(store.url, engine="terrastream", level=2.7)
    assert xr.open_dataset(store.url, engine="terrastream", level=np.int64(2)).sizes


def test_a_store_removed_or_replaced_while_open_is_said_so_not_damaged(tmp_path):
    """Reads of a store deleted (or tiled again) under an open reader raised "missing ... the
    store is damaged: verify it and repair it" (or a shard "shorter than its index"): the
    wrong diagnosis. They raise StoreChangedError now. The control: a chunk deleted from the
    store itself is damage, as before."""
    import shutil

    from tiler.errors import MissingChunkError, StoreChangedError
    from tiler.store import open_store

    src = write_dem(tmp_path / "d.tif", fractal((100, 100), 3))
    tile(src, tmp_path / "s.zarr", TileOptions(65))
    s = open_store(tmp_path / "s.zarr")
    shutil.rmtree(tmp_path / "s.zarr")
    with pytest.raises(StoreChangedError, match="replaced or rewritten while it was open"):
        s.read_block((1, 1))
    tile(src, tmp_path / "s.zarr", TileOptions(65))
    s = open_store(tmp_path / "s.zarr")
    tile(src, tmp_path / "s.zarr", TileOptions(129, overwrite=True))
    with pytest.raises(StoreChangedError):
        s.read_block((1, 1))
    s = open_store(tmp_path / "s.zarr")  # the control: damage in place is damage
    (tmp_path / "s.zarr" / "levels" / "7" / "c" / "0" / "0" / "0").unlink()
    with pytest.raises(MissingChunkError, match="damaged"):
        s.read_block((0, 0))


def test_a_store_opened_by_a_relative_path_survives_a_chdir(tmp_path, monkeypatch):
    """A store (and an xarray dataset) opened by a relative path read the new working
    directory after ``os.chdir`` and blamed replacement or damage; the path is kept absolute,
    and shown as given."""
    import os

    from tiler.store import open_store

    tile(
        write_dem(tmp_path / "d.tif", fractal((100, 100), 3)), tmp_path / "s.zarr", TileOptions(65)
    )
    monkeypatch.chdir(tmp_path)
    s = open_store("s.zarr")
    want = s.read_block((1, 1))
    (tmp_path / "elsewhere").mkdir()
    os.chdir(tmp_path / "elsewhere")
    np.testing.assert_array_equal(
        s.read_block((1, 0)), open_store(tmp_path / "s.zarr").read_block((1, 0))
    )
    np.testing.assert_array_equal(s.read_block((1, 1)), want)
    assert s.url == "s.zarr"  # (messages name it as given)


def test_info_names_a_crs_without_an_epsg_code_whole(tmp_path):
    """`info` cut a CRS without an EPSG code to its WKT's first 80 characters (unparseable,
    in --json too) and printed `crs None` without one; now the whole PROJ string, and
    "none". Control: an EPSG CRS is `EPSG:n`."""
    from rasterio.crs import CRS
    from typer.testing import CliRunner

    from cli.main import app
    from tiler.info import store_info

    src = write_dem(tmp_path / "d.tif", fractal((100, 100), 3))
    laea = "+proj=laea +lat_0=45 +lon_0=15 +datum=WGS84"
    tile(src, tmp_path / "l.zarr", TileOptions(65, dst_crs=laea, resolution=30.0))
    got = store_info(tmp_path / "l.zarr")["crs"]
    assert CRS.from_user_input(got) == CRS.from_user_input(laea), got
    tile(src, tmp_path / "u.zarr", TileOptions(65))
    assert store_info(tmp_path / "u.zarr")["crs"] == "EPSG:32633"
    tile(
        write_dem(tmp_path / "n.tif", fractal((100, 100), 3), crs=None),
        tmp_path / "n.zarr",
        TileOptions(65),
    )
    r = CliRunner().invoke(app, ["info", str(tmp_path / "n.zarr")])
    assert r.exit_code == 0 and "crs            none" in r.output, r.output


@pytest.mark.parametrize(
    "kw",
    [dict(compression_level=2.5), dict(error_cap=1.5), dict(band="1"), dict(workers=1.5),
     dict(block_size=65.0), dict(gdal_cache_mb=-5)],
)  # fmt: skip
def test_tile_options_that_are_not_integers_are_refused_naming_them(kw):
    """``compression_level=2.5`` failed inside zarr, ``error_cap=1.5`` as "Expected an
    iterable of integers", ``band="1"`` as a TypeError; ``gdal_cache_mb=-5`` and
    ``workers=1.5`` were accepted. The control: numpy integers are options too."""
    from tiler.errors import TilerError

    with pytest.raises(TilerError, match=next(iter(kw))):
        TileOptions(**kw)
    TileOptions(block_size=np.int64(65), band=np.int32(1), workers=np.uint8(2))


def test_block_of_sample_refuses_a_sample_outside_the_dem():
    """``block_of_sample(-1, -1)`` gave block (-1, -1), which numpy indexing reads as the last
    block: another block's heights, no error. The control: the DEM's corners (the shared
    borders go to the lower-right block, the last row and column to the last block)."""
    from tiler.grid import BlockGrid

    g = BlockGrid(100, 100, 6)  # 2x2 blocks of step 64
    for row, col in [(-1, -1), (0, -1), (100, 0), (np.array([0, 99]), np.array([5, 100]))]:
        with pytest.raises(LayoutError, match=r"outside the 100x100 DEM"):
            g.block_of_sample(row, col)
    assert [int(v) for v in g.block_of_sample(0, 0)] == [0, 0]
    assert [int(v) for v in g.block_of_sample(64, 99)] == [1, 1]
    r, c = g.block_of_sample(np.array([0, 63, 99]), np.array([99, 0, 99]))
    assert r.tolist() == [0, 0, 1] and c.tolist() == [1, 0, 1]
