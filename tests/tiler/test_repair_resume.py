"""A repair interrupted part-way is finished by rerunning ``tile --repair``; ``verify`` reports
it as unfinished. Before, a repair killed once its blocks were recomputed left the store in
state ``repair`` which every later ``--repair`` refused ("never finished ... run the same
command again"), while ``verify`` said ok (exit 0). And a destination holding a user's
``*.partial`` file was taken for empty and cleared.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from demtools import fractal, write_dem

import tiler.repair as repair
from tiler.errors import StoreExistsError
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

sys.path.insert(0, str(Path(__file__).resolve().parent))
from storetools import chunk_files, diff_stores  # noqa: E402


def _opts(**kw) -> TileOptions:
    return TileOptions(block_size=65, workers=1, executor="threads", **kw)


class Killed(Exception):
    """Stands for a SIGKILL: the run stops where it is, its lease and files left."""


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    d = tmp_path_factory.mktemp("repair")
    src = write_dem(d / "dem.tif", fractal((200, 200), 7))
    ref = tile(src, d / "ref.zarr", _opts()).location.path
    return src, ref


@pytest.mark.parametrize("where", ["_patch", "complete"])
def test_an_interrupted_repair_is_reported_and_finished(made, tmp_path, monkeypatch, where):
    src, ref = made
    s = tile(src, tmp_path / "s.zarr", _opts()).location.path
    for f in (chunk_files(s, "levels/6")[4], chunk_files(s, "errors")[1]):
        f.write_bytes(f.read_bytes()[:-3] + b"xyz")  # (two blocks damaged)
    real = getattr(repair, where)

    def killed(*a, **k):
        raise Killed(where)

    monkeypatch.setattr(repair, where, killed)
    with pytest.raises(Killed):
        tile(src, s, _opts(repair=True))
    monkeypatch.setattr(repair, where, real)
    rep = verify_store(s)
    assert not rep.ok and rep.state == "repair"
    assert any(p.kind == "unfinished" and "--repair" in p.message for p in rep.problems)
    with pytest.raises(StoreExistsError, match="interrupted repair"):
        tile(src, s, _opts())  # (it is not a tiling to resume: the repair finishes it)
    done = tile(src, s, _opts(repair=True))
    assert verify_store(s).ok
    assert diff_stores(s, ref) == []
    assert done.tile_summary.blocks_repaired >= 2 or where == "complete"


def test_an_uninterrupted_repair_still_runs_once(made, tmp_path):
    """The control: a repair without interruption recomputes the damaged blocks only."""
    src, ref = made
    s = tile(src, tmp_path / "s.zarr", _opts()).location.path
    chunk_files(s, "levels/6")[2].unlink()
    done = tile(src, s, _opts(repair=True))
    assert done.tile_summary.blocks_computed == 1
    assert verify_store(s).ok and diff_stores(s, ref) == []


def test_a_users_partial_file_is_not_cleared(made, tmp_path):
    src, _ = made
    d = tmp_path / "out"
    d.mkdir()
    mine = d / "ubuntu.iso.partial"
    mine.write_text("my download, 3 hours in")
    with pytest.raises(StoreExistsError, match="not a terrastream store"):
        tile(src, d, _opts())
    assert mine.read_text() == "my download, 3 hours in"


def test_our_own_partial_leftover_is_still_cleared(made, tmp_path):
    """The control: an interrupted first write leaves ``zarr.json.<hex>.partial``; the
    directory is then taken as empty, as before."""
    src, ref = made
    d = tmp_path / "out"
    d.mkdir()
    (d / ("zarr.json." + "ab" * 16 + ".partial")).write_text("{")
    tile(src, d, _opts())
    assert diff_stores(d, ref) == []


def _interrupted_geo_tiling(tmp_path, monkeypatch, opts: TileOptions):
    """A geographic DEM whose tiling into ``tmp_path/s.zarr`` with ``opts`` was killed after
    5 blocks (an unfinished store); returns the DEM's path."""
    import tiler.tile as tile_mod

    src = write_dem(tmp_path / "geo.tif", fractal((120, 120), 3), crs="EPSG:4326",
                    origin=(10.0, 45.0), cell=0.0005)  # fmt: skip
    real = tile_mod.process_block
    n = {"blocks": 0}

    def dies(window, params):
        n["blocks"] += 1
        if n["blocks"] > 5:
            raise KeyboardInterrupt("simulated kill")
        return real(window, params)

    monkeypatch.setattr(tile_mod, "process_block", dies)
    with pytest.raises(KeyboardInterrupt):
        tile(src, tmp_path / "s.zarr", opts)
    monkeypatch.setattr(tile_mod, "process_block", real)
    return src


@pytest.mark.parametrize(("change", "named"), [
    ({"resampling": "cubic"}, "resampling: store has 'bilinear', this run has 'cubic'"),
    ({"resolution": 20.0}, "resolution: store has None, this run has 20.0"),
])  # fmt: skip
def test_a_resume_with_other_reprojection_options_names_them(tmp_path, monkeypatch, change,
                                                             named):  # fmt: skip
    """A rerun with another ``--resampling`` or ``--resolution`` was refused as "source:
    'geo.tif' is not the file the store was tiled from" (the options only fed the source's
    fingerprint); it now names the option and both values. The control: the same options
    resume."""
    from tiler.errors import JobMismatchError

    opts = dict(block_size=17, workers=1, executor="threads", dst_crs="auto")
    src = _interrupted_geo_tiling(tmp_path, monkeypatch, TileOptions(**opts))
    with pytest.raises(JobMismatchError) as info:
        tile(src, tmp_path / "s.zarr", TileOptions(**opts, **change))
    assert named in str(info.value) and "not the file" not in str(info.value)
    assert verify_store(tile(src, tmp_path / "s.zarr", TileOptions(**opts)).location).ok


def test_a_reprojected_store_is_repaired_with_its_own_reprojection(tmp_path):
    """``tile SRC STORE --repair`` of a store tiled with ``--dst-crs auto`` was refused (the
    source "is not the file the store was tiled from") unless the reprojection was given again;
    it now takes the store's, as it takes its block size."""
    from typer.testing import CliRunner

    from cli.main import app

    src = write_dem(tmp_path / "geo.tif", fractal((120, 120), 3), crs="EPSG:4326",
                    origin=(10.0, 45.0), cell=0.0005)  # fmt: skip
    s = tile(src, tmp_path / "s.zarr", TileOptions(block_size=17, workers=1, dst_crs="auto",
                                                   resampling="cubic")).location.path  # fmt: skip
    ref = tmp_path / "ref.zarr"
    tile(src, ref, TileOptions(block_size=17, workers=1, dst_crs="auto", resampling="cubic"))
    chunk_files(s, "errors")[3].unlink()
    res = CliRunner().invoke(app, ["tile", str(src), str(s), "--repair"])
    assert res.exit_code == 0, res.output
    assert verify_store(s).ok and diff_stores(s, ref) == []
    chunk_files(s, "errors")[2].unlink()  # given again, the store's resampling is accepted
    res = CliRunner().invoke(app, ["tile", str(src), str(s), "--repair", "--resampling", "cubic"])
    assert res.exit_code == 0, res.output
    assert verify_store(s).ok and diff_stores(s, ref) == []
    plain = tmp_path / "plain.zarr"  # the control: a store not reprojected refuses it
    flat = write_dem(tmp_path / "flat.tif", fractal((40, 40), 1))
    tile(flat, plain, TileOptions(block_size=17, workers=1))
    res = CliRunner().invoke(app, ["tile", str(flat), str(plain), "--repair",
                                   "--resampling", "cubic"])  # fmt: skip
    assert res.exit_code == 2 and "was not reprojected" in res.output, res.output


def test_reprojection_items_are_compared_as_spelled_one_way(tmp_path, monkeypatch):
    """The job kept the options as given: a rasterio CRS object made the metadata unwritable
    (TypeError, not JSON) and ``epsg:32632`` then ``EPSG:32632`` (or ``Cubic``/``cubic``) was
    refused as another job. Both now resume; another CRS is still refused (the control)."""
    from rasterio.crs import CRS

    from tiler.errors import JobMismatchError

    base = dict(block_size=17, workers=1, executor="threads")
    first = TileOptions(**base, dst_crs=CRS.from_epsg(32632), resampling="Cubic")
    src = _interrupted_geo_tiling(tmp_path, monkeypatch, first)
    with pytest.raises(JobMismatchError, match="dst_crs: store has 'EPSG:32632', this run has"):
        tile(src, tmp_path / "s.zarr", TileOptions(**base, dst_crs="EPSG:32633"))
    s = tile(src, tmp_path / "s.zarr", TileOptions(**base, dst_crs="epsg:32632",
                                                   resampling="cubic"))  # fmt: skip
    assert s.tile_summary.blocks_skipped >= 1 and verify_store(s.location).ok
