"""``tile`` with several sources, a source list and a target CRS, through Typer's runner."""

from __future__ import annotations

import numpy as np
from demtools import fractal, write_dem
from typer.testing import CliRunner

from cli.commands.tile import Resampling
from cli.main import app
from tiler.crs import RESAMPLINGS, crs_name
from tiler.store import open_store

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def pieces(tmp_path):
    data = fractal((40, 60), seed=2)
    a = write_dem(tmp_path / "a.tif", np.ascontiguousarray(data[:, :31]))
    b = write_dem(tmp_path / "b.tif", np.ascontiguousarray(data[:, 30:]), origin=(500900.0, 5e6))
    return data, a, b


def test_tile_several_sources_and_a_list(tmp_path):
    data, a, b = pieces(tmp_path)
    r = run("tile", a, b, tmp_path / "m.zarr", "--block-size", "17")
    assert r.exit_code == 0, r.output
    s = open_store(tmp_path / "m.zarr")
    assert (s.meta.height, s.meta.width) == data.shape
    np.testing.assert_array_equal(s.read_block((0, 1))[:17, :17], data[:17, 16:33])
    lst = tmp_path / "list.txt"
    lst.write_text("b.tif\n")
    r = run("tile", a, tmp_path / "l.zarr", "--from-list", lst, "--block-size", "17")
    assert r.exit_code == 0, r.output
    assert open_store(tmp_path / "l.zarr").meta.source["paths"] == [str(a), str(tmp_path / "b.tif")]


def test_tile_needs_a_source(tmp_path):
    r = run("tile", tmp_path / "only.zarr")
    assert r.exit_code == 2
    assert "at least one source" in r.output


def test_tile_dst_crs_auto_and_bad_values(tmp_path):
    src = write_dem(
        tmp_path / "geo.tif",
        fractal((30, 30), seed=1),
        crs="EPSG:4326",
        origin=(11.2, 49.6),
        cell=1 / 120,
    )
    r = run("tile", src, tmp_path / "g.zarr", "--dst-crs", "auto", "--block-size", "17")
    assert r.exit_code == 0, r.output
    assert "reprojected from EPSG:4326 to EPSG:32632 (auto)" in r.output
    assert crs_name(open_store(tmp_path / "g.zarr").meta.crs_wkt) == "EPSG:32632"
    r = run("tile", src, tmp_path / "x.zarr", "--dst-crs", "EPSG:0")
    assert r.exit_code != 0 and "'EPSG:0' is not understood" in r.output
    r = run("tile", src, tmp_path / "y.zarr", "--resampling", "sinc")
    assert r.exit_code == 2


def test_resampling_choices_are_the_library_registry():
    assert tuple(m.value for m in Resampling) == RESAMPLINGS
