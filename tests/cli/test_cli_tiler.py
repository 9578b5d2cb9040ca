"""The tiler commands through Typer's runner: exit codes and messages."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from demtools import fractal
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()


def run(*args: str):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture
def src(dem_factory):
    return dem_factory(fractal((90, 70), 11))


def test_tile_info_export_round_trip(src, tmp_path):
    r = run("tile", src, tmp_path / "s.zarr", "--block-size", "33", "--workers", "2")
    assert r.exit_code == 0, r.output
    assert "3x3 blocks, 6 levels" in r.output
    r = run("info", tmp_path / "s.zarr")
    assert r.exit_code == 0, r.output
    for needle in ("70 x 90 int16", "EPSG:32633", "x raw", "blocks         3 x 3 of 33^2"):
        assert needle in r.output
    r = run("info", tmp_path / "s.zarr", "--json")
    d = json.loads(r.output)
    assert d["levels"] == 6 and d["bytes"]["total"] > 0 and len(d["bytes_per_level"]) == 6
    r = run("export", tmp_path / "s.zarr", tmp_path / "out.tif")
    assert r.exit_code == 0, r.output
    with rasterio.open(src) as a, rasterio.open(tmp_path / "out.tif") as b:
        np.testing.assert_array_equal(a.read(1), b.read(1))


def test_info_counts_blocks_with_nodata_as_a_part_of_those_with_terrain(dem_factory, tmp_path):
    data = fractal((129, 129), 3).astype("float32")
    data[:, :100] = np.nan  # block columns 0-2 all nodata, column 3 part nodata
    src = dem_factory(data, nodata=float("nan"))
    assert run("tile", src, tmp_path / "s.zarr", "--block-size", "33").exit_code == 0
    r = run("info", tmp_path / "s.zarr")
    assert (
        "4 x 4 of 33^2 (4 with terrain, of which 4 with nodata; 12 without terrain, not "
        in r.output
    )
    # the control: a DEM without nodata says so
    assert run("tile", dem_factory(fractal((129, 129), 3), "b.tif"), tmp_path / "b.zarr",
               "--block-size", "33").exit_code == 0  # fmt: skip
    r = run("info", tmp_path / "b.zarr")
    assert "4 x 4 of 33^2 (16 with terrain, of which 0 with nodata)" in r.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["tile", "{tmp}/missing.tif", "{tmp}/s.zarr"], "does not exist"),
        (["tile", "{src}", "{tmp}/s.zarr", "--block-size", "100"], "got 100"),
        (["tile", "{src}", "{tmp}/s.zarr", "--workers", "-1"], "workers must be >= 0"),
        (["tile", "{src}", "{tmp}/s.zarr", "--precision", "0.1"], "Drop --precision"),
        (["info", "{tmp}/nothing.zarr"], "no store at"),
        (["export", "{tmp}/nothing.zarr", "{tmp}/o.tif"], "no store at"),
    ],
    ids=["missing-src", "block-size", "workers", "precision-int", "info-missing", "export-missing"],
)
def test_bad_arguments_exit_nonzero_with_message(src, tmp_path, args, message):
    r = run(*[a.format(tmp=tmp_path, src=src) for a in args])
    assert r.exit_code != 0
    assert message in r.output
    assert "Traceback" not in r.output


def test_existing_store_and_export_level_bounds(src, tmp_path):
    assert run("tile", src, tmp_path / "s.zarr", "--block-size", "33").exit_code == 0
    r = run("tile", src, tmp_path / "s.zarr", "--block-size", "33")
    assert r.exit_code == 2 and "--overwrite" in r.output
    r = run("export", tmp_path / "s.zarr", tmp_path / "o.tif", "--level", "9")
    assert r.exit_code == 2 and "--level must be in 0..5" in r.output
    assert not (tmp_path / "o.tif").exists()
