"""``verify --source`` reads the source as the store was tiled from it: the job's band, the
store's reprojection, every source of a mosaic. Each clean case has a positive control (one
sample of the source changed, or the wrong sources given) that the comparison must report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from demtools import fractal, write_dem
from rasterio.transform import from_origin
from typer.testing import CliRunner

from cli.main import app
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

runner = CliRunner()


def _two_band(path: Path, b1: np.ndarray, b2: np.ndarray) -> Path:
    h, w = b1.shape
    with rasterio.open(
        path, "w", driver="GTiff", width=w, height=h, count=2, dtype=b1.dtype,
        crs="EPSG:32633", transform=from_origin(500000.0, 5000000.0, 30.0, 30.0),
    ) as dst:  # fmt: skip
        dst.write(b1, 1)
        dst.write(b2, 2)
    return path


def test_a_band_2_store_verifies_against_band_2(tmp_path):
    b1, b2 = fractal((70, 60), 1), fractal((70, 60), 2)
    src = _two_band(tmp_path / "two.tif", b1, b2)
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, band=2, workers=1))
    rep = verify_store(tmp_path / "s.zarr", source=src)
    assert rep.ok and rep.source_checked, rep.problems  # (band 1 was read before: 6 blocks "bad")
    # the positive control: one sample of band 2 changed is found in its block only
    b2[40, 50] += 1
    changed = _two_band(tmp_path / "changed.tif", b1, b2)
    rep = verify_store(tmp_path / "s.zarr", source=changed)
    assert rep.bad_blocks == {(1, 1)} and rep.problems[0].kind == "source", rep.problems


def test_a_reprojected_store_verifies_against_its_source(tmp_path):
    data = fractal((60, 50), 3)
    src = write_dem(tmp_path / "dem.tif", data)
    opts = TileOptions(block_size=33, dst_crs="EPSG:3857", resampling="nearest", workers=1)
    tile(src, tmp_path / "s.zarr", opts)
    rep = verify_store(tmp_path / "s.zarr", source=src)
    assert rep.ok and rep.source_checked, rep.problems  # (unreprojected: "60x50, store 6?x5?")
    data[:, :] += 1  # the control: every sample changed
    rep = verify_store(tmp_path / "s.zarr", source=write_dem(tmp_path / "other.tif", data))
    assert rep.bad_blocks and all(p.kind == "source" for p in rep.problems), rep.problems


def test_a_mosaic_verifies_against_its_sources_and_names_a_missing_one(tmp_path):
    a = write_dem(tmp_path / "a.tif", fractal((40, 30), 4))
    b = write_dem(tmp_path / "b.tif", fractal((40, 30), 5), origin=(500000.0 + 30 * 30, 5e6))
    tile([a, b], tmp_path / "s.zarr", TileOptions(block_size=17, workers=1))
    assert verify_store(tmp_path / "s.zarr", source=[a, b]).ok
    rep = verify_store(tmp_path / "s.zarr", source=a)  # the control: one of the two
    assert not rep.ok and not rep.bad_blocks
    msg = rep.problems[0].message
    assert "40x30 samples, the store 40x60" in msg and "tiled from 2 sources" in msg, msg


def test_cli_verify_of_another_dem_does_not_advise_repair(tmp_path):
    src = write_dem(tmp_path / "dem.tif", fractal((50, 40), 6))
    other = write_dem(tmp_path / "other.tif", fractal((50, 40), 7))
    dst = tmp_path / "s.zarr"
    assert runner.invoke(app, ["tile", str(src), str(dst), "--block-size", "33"]).exit_code == 0
    r = runner.invoke(app, ["verify", str(dst), "--source", str(src)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["verify", str(dst), "--source", str(other)])
    assert r.exit_code == 1, r.output
    # the store is intact: `--repair` would find nothing to recompute, so it is not the advice
    assert "is intact but" in r.output and "--overwrite" in r.output, r.output
    assert "--repair" not in r.output, r.output
    mosaic = runner.invoke(app, ["verify", str(dst), "--source", str(src), "--source", str(src)])
    assert mosaic.exit_code == 0, mosaic.output  # (the same DEM twice: the first wins everywhere)


def test_repair_with_another_band_is_refused_as_a_finished_stores_repair(tmp_path):
    """`tile --repair` of a finished store with another band said it "holds an unfinished
    store of another job ... to finish it"; it names the repair now (the resume of an
    unfinished store keeps its wording: tests/tiler/test_store_v2.py)."""
    import pytest

    from tiler.errors import JobMismatchError

    b1, b2 = fractal((70, 60), 1), fractal((70, 60), 2)
    src = _two_band(tmp_path / "two.tif", b1, b2)
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, band=2, workers=1))
    with pytest.raises(JobMismatchError) as e:
        tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, band=1, repair=True))
    msg = str(e.value)
    assert "holds a store of another job" in msg and "band: store has 2, this run has 1" in msg
    assert "to repair it" in msg and "unfinished" not in msg, msg
    # the control: the same band repairs (nothing to do on an intact store)
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, band=2, repair=True))
