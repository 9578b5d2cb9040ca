"""The renderer's commands through Typer's CliRunner."""

from __future__ import annotations

import csv
import json

import pytest
from demtools import budget_error_at
from gltools import make_context, rough, tile_dem
from typer.testing import CliRunner

from cli.main import app
from render.strategies import strategy_names

pytestmark = pytest.mark.gl
make_context()
runner = CliRunner()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return str(tile_dem(tmp_path_factory.mktemp("cli"), rough(65, 7), 33))


def test_render_writes_a_png(store, tmp_path):
    out = tmp_path / "v.png"
    res = runner.invoke(
        app, ["render", store, "--size", "96x64", "--patch-log2", "2", "-o", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert out.stat().st_size > 0 and "triangles" in res.output


def test_tradeoff_writes_json_rows(store, tmp_path):
    js, png = tmp_path / "t.json", tmp_path / "t.png"
    res = runner.invoke(
        app,
        [
            "tradeoff",
            store,
            "--size",
            "96x64",
            "--taus",
            "1,4",
            "--patch-log2",
            "2",
            "--repeats",
            "1",
            "--json",
            str(js),
            "--plot",
            str(png),
        ],
    )
    assert res.exit_code == 0, res.output
    rows = json.loads(js.read_text())
    keys = {
        "tau",
        "metric",
        "triangles",
        "selection_ms",
        "frame_ms",
        "reference_frame_ms",
        "max_screen_error_px",
        "p99_screen_error_px",
        "psnr_db",
        "crack_pixels",
        "resident_bytes",
    }
    assert len(rows) == 2 and keys <= set(rows[0]) and png.exists()
    assert all(r["crack_pixels"] == 0 for r in rows)


def test_flythrough_writes_frames_and_csv(store, tmp_path):
    res = runner.invoke(
        app,
        [
            "flythrough",
            store,
            "--size",
            "64x48",
            "--frames",
            "3",
            "--patch-log2",
            "2",
            "--out",
            str(tmp_path / "f"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert (tmp_path / "f" / "frames.csv").read_text().count("\n") == 4
    assert len(list((tmp_path / "f").glob("frame_*.png"))) == 3


@pytest.mark.parametrize("lod", strategy_names())
def test_every_strategy_flies(store, tmp_path, lod):
    """``flythrough`` (and so ``view``, which shares its per-frame figures) with every
    strategy: each reports its render-thread builds and its own GPU buffers. (jung-han, whose
    constructor is its selector's, had no ``build_ms``: the flight failed.)"""
    out = tmp_path / "f"
    args = ["flythrough", store, "--size", "64x48", "--frames", "2", "--lod", lod,
            "--every", "0", "--out", str(out)]  # fmt: skip
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    with (out / "frames.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 and all(float(r["build_ms"]) >= 0.0 for r in rows)
    # the summary's loads are the frames' (reads finished after the last frame apart)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["loaded_mb"] == pytest.approx(sum(float(r["loaded_mb"]) for r in rows))
    assert summary["loaded_mb"] > 0.0 and summary["loaded_after_frames_mb"] >= 0.0
    assert summary["peak_resident_mb"] == max(float(r["resident_mb"]) for r in rows)
    assert all(float(r["build_cpu_ms"]) >= 0.0 for r in rows)
    assert all(float(r["strategy_gpu_mb"]) >= 0.0 and int(r["drawn_px"]) > 0 for r in rows)


@pytest.mark.parametrize("flag", [[], ["--render-thread-builds"]])
def test_a_geometry_splitting_flythrough_reports_its_texture_builds(store, tmp_path, flag):
    import csv
    import json
    import threading

    out = tmp_path / "f"
    args = ["flythrough", store, "--size", "64x48", "--frames", "3", "--lod",
            "geometry-splitting", "--every", "0", "--out", str(out), *flag]  # fmt: skip
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    with (out / "frames.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert float(rows[0]["build_ms"]) > 0.0  # the first frame's blocks are new: built there
    assert float(rows[0]["build_cpu_ms"]) > 0.0  # (the render thread's CPU in it)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["max_build_ms"] == max(float(r["build_ms"]) for r in rows)
    assert summary["max_build_cpu_ms"] == max(float(r["build_cpu_ms"]) for r in rows)
    gpu_mb = [float(r["strategy_gpu_mb"]) for r in rows]  # its texture buffer
    assert min(gpu_mb) > 0.0 and summary["max_strategy_gpu_mb"] == max(gpu_mb)
    assert "builds max" in res.output
    left = [t.name for t in threading.enumerate() if t.name.startswith("terrastream-block")]
    assert left == []  # the worker stopped with the flight


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--camera", "1,2"], "--camera must be three numbers"),
        (["--look-at", "1,2,3"], "need --camera"),
    ],
)
def test_bad_camera_exits_2(store, args, message):
    res = runner.invoke(app, ["render", store, *args])
    assert res.exit_code == 2 and message in res.output


def test_missing_store_exits_2(tmp_path):
    res = runner.invoke(app, ["render", str(tmp_path / "nope.zarr")])
    assert res.exit_code == 2 and "error:" in res.output


def test_a_view_of_no_terrain_is_an_error_not_a_sky_png(store, tmp_path):
    from tiler.store import open_store

    x0, y0, x1, y1 = open_store(store).grid.extent
    out = tmp_path / "sky.png"
    far_away = f"{x1 + 100 * (x1 - x0)},{y1 + 100 * (y1 - y0)},50"  # looking away from the DEM
    res = runner.invoke(
        app,
        ["render", store, "--size", "96x64", "--camera", far_away, "--yaw", "45", "--pitch", "10",
         "-o", str(out)],
    )  # fmt: skip
    assert res.exit_code == 2, res.output
    assert "drew no terrain" in res.output and not out.exists()


def test_terrain_too_sparse_to_draw_is_named_as_a_cause(tmp_path):
    """Valid samples no two of which are neighbours: every triangle has a nodata corner, so
    the overview draws nothing. The error names sparse terrain as a cause (the store has
    nodata); the control, the far-away view of a store without nodata above, does not."""
    import numpy as np

    data = np.full((65, 65), np.nan, dtype=np.float32)
    data[::4, ::4] = rough(65, 3)[::4, ::4]
    sparse = str(tile_dem(tmp_path, data, 33, nodata=float("nan")))
    out = tmp_path / "sparse.png"
    res = runner.invoke(app, ["render", sparse, "--size", "96x64", "-o", str(out)])
    assert res.exit_code == 2, res.output
    assert "too sparse to draw" in res.output and not out.exists()


def test_control_a_store_without_nodata_is_not_called_sparse(store, tmp_path):
    out = tmp_path / "sky.png"
    res = runner.invoke(
        app, ["render", store, "--size", "96x64", *_looking_down(store, 1e7), "-o", str(out)]
    )
    assert res.exit_code == 2, res.output
    assert "drew no terrain pixel" in res.output and "sparse" not in res.output


def _looking_down(store, height):
    from tiler.store import open_store

    x0, y0, x1, y1 = open_store(store).grid.extent
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    return ["--camera", f"{cx},{cy},{height}", "--look-at", f"{cx},{cy + 1},0"]


def test_a_dem_smaller_than_a_pixel_is_an_error_not_a_sky_png(store, tmp_path):
    """Looking straight down from 10,000 km the DEM is far below a pixel: triangles are
    drawn but no pixel is terrain. ``render`` and ``tradeoff`` (once PSNR 100 and 0.00 px
    from sky against sky) fail; the control: from a height where it covers a few pixels,
    both succeed and ``render --json`` counts them."""
    out = tmp_path / "sky.png"
    far = _looking_down(store, 1e7)
    res = runner.invoke(app, ["render", store, "--size", "96x64", *far, "-o", str(out)])
    assert res.exit_code == 2, res.output
    assert "drew no terrain pixel" in res.output and not out.exists()
    tr = ["tradeoff", store, "--size", "96x64", "--taus", "1", "--repeats", "1"]
    res = runner.invoke(app, [*tr, *far])
    assert res.exit_code == 2, res.output
    assert "draws no terrain pixel at full resolution" in res.output
    near = _looking_down(store, 30_000)
    res = runner.invoke(app, ["render", store, "--size", "96x64", *near, "-o", str(out), "--json"])
    assert res.exit_code == 0, res.output
    assert 0 < json.loads(res.output.splitlines()[-1])["drawn_px"] < 96 * 64
    assert runner.invoke(app, [*tr, *near]).exit_code == 0


def _keyframes(tmp_path, rows) -> str:
    p = tmp_path / "k.csv"
    p.write_text("t,x,y,z,yaw,pitch\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return str(p)


def _fly(store, path, out, frames=3):
    return runner.invoke(
        app,
        ["flythrough", store, "--path", path, "--frames", str(frames), "--size", "64x48",
         "--patch-log2", "2", "--out", str(out)],
    )  # fmt: skip


def test_a_flythrough_that_sees_no_terrain_is_an_error_not_blank_frames(store, tmp_path):
    from tiler.store import open_store

    x0, y0, x1, y1 = open_store(store).grid.extent
    away = (x1 + 1e6, y1 + 1e6, 3000, 45, -10)  # beyond the north-east corner, looking away
    res = _fly(store, _keyframes(tmp_path, [(0, *away), (1, *away)]), tmp_path / "f")
    assert res.exit_code == 2, res.output
    assert "--path: none of the 3 frame(s) of the camera path sees the DEM" in res.output
    assert not (tmp_path / "f").exists()  # no blank PNG, no frames.csv, no empty folder
    (tmp_path / "mine").mkdir()  # a folder the user made is left, empty as it was
    res = _fly(store, _keyframes(tmp_path, [(0, *away), (1, *away)]), tmp_path / "mine")
    assert res.exit_code == 2 and (tmp_path / "mine").is_dir()
    # positive control: turning to look at the DEM half way draws, and names the empty frames
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    turn = [(0, cx, cy, 3000, 0, 80), (1, cx, cy, 3000, 0, -89)]
    res = _fly(store, _keyframes(tmp_path, turn), tmp_path / "g", frames=2)
    assert res.exit_code == 0, res.output
    assert "warning: 1 of 2 frames drew no terrain (the first: frame 0)" in res.output
    summary = json.loads((tmp_path / "g" / "summary.json").read_text())
    assert summary["empty_frames"] == 1 and summary["first_empty_frame"] == 0


def _centre(store):
    from tiler.store import open_store

    x0, y0, x1, y1 = open_store(store).grid.extent
    return 0.5 * (x0 + x1), 0.5 * (y0 + y1)


def test_a_flythrough_whose_triangles_cover_no_pixel_is_an_error_not_sky_frames(store, tmp_path):
    """Frames that draw triangles but no terrain pixel (a DEM below a pixel from 10,000 km,
    or terrain too sparse to draw) were written as all-sky PNGs with exit 0 and
    ``empty_frames`` 0. The control: the same path 3 km up draws, and ``frames.csv`` counts
    the terrain pixels of every frame."""
    import numpy as np

    cx, cy = _centre(store)
    far = [(0, cx, cy, 1e7, 0, -89), (1, cx, cy, 1e7, 0, -89)]
    res = _fly(store, _keyframes(tmp_path, far), tmp_path / "far")
    assert res.exit_code == 2, res.output
    assert "none of the 3 frame(s) drew a terrain pixel, though 3 drew triangles" in res.output
    assert not list((tmp_path / "far").glob("*.png"))

    data = np.full((65, 65), np.nan, dtype=np.float32)
    data[::4, ::4] = rough(65, 3)[::4, ::4]  # no two valid samples are neighbours
    (tmp_path / "sp").mkdir()
    sparse = str(tile_dem(tmp_path / "sp", data, 33, nodata=float("nan")))
    near = [(0, cx, cy, 3000, 0, -89), (1, cx, cy, 3000, 0, -89)]
    res = _fly(sparse, _keyframes(tmp_path, near), tmp_path / "sparse")
    assert res.exit_code == 2, res.output
    assert "too sparse to draw" in res.output

    res = _fly(store, _keyframes(tmp_path, near), tmp_path / "near")
    assert res.exit_code == 0, res.output
    with open(tmp_path / "near" / "frames.csv") as f:
        px = [int(row["drawn_px"]) for row in csv.DictReader(f)]
    assert len(px) == 3 and all(0 < p <= 64 * 48 for p in px)
    summary = json.loads((tmp_path / "near" / "summary.json").read_text())
    assert summary["empty_frames"] == 0 and summary["pixelless_frames"] == 0


def test_a_keyframe_flythrough_150_km_up_draws_the_dem(tmp_path):
    """A 192 km DEM (3 km cells) seen from 150 km up fills the view's pixels. (With the
    module's 1.9 km DEM this test once passed on triangles alone: the DEM was below a pixel
    there and every frame was sky.)"""
    (tmp_path / "big").mkdir()
    big = str(tile_dem(tmp_path / "big", rough(65, 7), 33, cell=3000.0))
    cx, cy = _centre(big)
    high = [(0, cx, cy, 150_000, 0, -90), (1, cx, cy, 150_000, 0, -89)]
    res = _fly(big, _keyframes(tmp_path, high), tmp_path / "f", frames=2)
    assert res.exit_code == 0, res.output  # the far plane once stopped at 100 km: no terrain
    with open(tmp_path / "f" / "frames.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2
    assert all(int(r["triangles"]) > 0 and int(r["drawn_px"]) > 64 * 48 // 2 for r in rows)


def test_compare_names_the_middle_frame_it_measures_when_it_sees_no_terrain(store, tmp_path):
    from tiler.store import open_store

    x0, y0, x1, y1 = open_store(store).grid.extent
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    args = ["compare", store, "--frames", "3", "--lods", "qiu", "--taus", "1", "--size", "64x48",
            "--patch-log2", "2", "--path"]  # fmt: skip
    up = [(0, cx, cy, 3000, 0, -89), (1, cx, cy, 3000, 0, 80), (2, cx, cy, 3000, 0, -89)]
    res = runner.invoke(app, [*args, _keyframes(tmp_path, up)])
    assert res.exit_code == 2, res.output
    assert "holds no terrain sample" in res.output and "draws no terrain pixel" in res.output
    assert "compare measures the camera path's middle frame, 1 of 3" in res.output
    # positive control: the same path looking down throughout is measured
    down = [(0, cx, cy, 3000, 0, -89), (1, cx, cy, 3000, 0, -80), (2, cx, cy, 3000, 0, -89)]
    res = runner.invoke(app, [*args, _keyframes(tmp_path, down)])
    assert res.exit_code == 0, res.output


def test_a_flythrough_whose_frames_saw_the_dem_but_drew_nothing_is_an_error(
    store, tmp_path, monkeypatch
):
    import dataclasses

    import render.flythrough as fly
    from render.errors import RenderError
    from render.flythrough import flythrough
    from streamer.run import make_path
    from tiler.store import open_store

    s = open_store(store)
    cams = make_path(s, "default", frames=2, viewport=(64, 48))
    real = fly.frame_step

    def nothing_drawn(*a, **kw):  # the frames see the DEM, the draw puts nothing on screen
        step = real(*a, **kw)
        return dataclasses.replace(step, stats=dataclasses.replace(step.stats, triangles=0))

    monkeypatch.setattr(fly, "frame_step", nothing_drawn)
    with pytest.raises(RenderError, match=r"none of the 2 frame\(s\) drew terrain, though 2 saw"):
        flythrough(s, cams, tmp_path / "f", patch_log2=2)
    assert not (tmp_path / "f").exists()  # no blank PNG, no empty folder it made
    # positive control: drawn for real, the same frames are written
    monkeypatch.setattr(fly, "frame_step", real)
    rows, summary = flythrough(s, cams, tmp_path / "g", patch_log2=2)
    assert summary["empty_frames"] == 0 and all(r.visible_blocks > 0 for r in rows)
    assert len(list((tmp_path / "g").glob("frame_*.png"))) == 2


@pytest.mark.parametrize("only", [None, "/errors/c/0/0"], ids=["every-block", "one-block"])
def test_a_flythrough_over_a_failing_server_exits_1_blaming_the_server(store, tmp_path, only):
    """Block data answered with 503 (every block, or one block's errors): exit 1 naming the
    server, not `verify`; with one block failing the fly-through goes on and writes every
    frame, `frames.csv` and `summary.json` with the verdict. The healthy server is the
    control (exit 0, no verdict in summary.json)."""
    from pathlib import Path

    from rangeserver import LoopbackServer

    root = Path(store).parent
    srv = LoopbackServer(root)
    with srv as url:
        args = ["flythrough", f"{url}/{Path(store).name}", "--size", "64x48", "--frames",
                "3", "--patch-log2", "2", "--out"]  # fmt: skip
        res = runner.invoke(app, [*args, str(tmp_path / "ok")])
        assert res.exit_code == 0, res.output  # the control
        assert json.loads((tmp_path / "ok" / "summary.json").read_text())["problem"] is None
        srv.handler.fail_status, srv.handler.fail_match = 503, only
        res = runner.invoke(app, [*args, str(tmp_path / "bad")])
    assert res.exit_code == 1, res.output
    assert "the server or the network failed, not the store" in res.output
    assert "verify" not in res.output and "503" in res.output
    if only:  # flew on past the failing block: everything written, the verdict in the summary
        assert len(list((tmp_path / "bad").glob("frame_*.png"))) == 3
        assert (tmp_path / "bad" / "frames.csv").is_file()
        summary = json.loads((tmp_path / "bad" / "summary.json").read_text())
        assert "the server or the network failed" in summary["problem"]


def test_a_flythrough_whose_reads_go_unanswered_says_so(tmp_path, monkeypatch):
    """The server stops answering after frame 0 (its reads ahead hang): the frames are drawn
    and written, and the summary's verdict names the unanswered reads. The control: the same
    flight over the healthy server has no verdict."""
    from pathlib import Path

    from rangeserver import LoopbackServer

    import render.flythrough as fly
    from streamer.run import make_path
    from tiler.store import open_store

    monkeypatch.setattr("streamer.run.CLOSE_WAIT_S", 0.5)  # close_for_verdict's wait
    (tmp_path / "big").mkdir()
    big = tile_dem(tmp_path / "big", rough(257, 7), 33)  # 8 x 8 blocks: reads go on ahead
    srv = LoopbackServer(Path(big).parent)
    with srv as url:
        s = open_store(f"{url}/{Path(big).name}")
        cams = make_path(s, "default", frames=4, viewport=(64, 48))
        _, summary = fly.flythrough(s, cams, tmp_path / "ok", patch_log2=2)
        assert summary["problem"] is None  # the control
        s = open_store(f"{url}/{Path(big).name}")
        _, summary = fly.flythrough(
            s, cams, tmp_path / "bad", patch_log2=2, on_frame=lambda row: srv.stall.set()
        )
        srv.release.set()  # the hung reads fail now: let their threads end inside the test
        _join_loaders()
    assert summary["problem"] and "still unanswered" in summary["problem"]
    assert len(list((tmp_path / "bad").glob("frame_*.png"))) == 4


def _join_loaders(timeout_s: float = 10.0) -> None:
    """Wait for session loader threads left running (reads a stalled server released)."""
    import threading
    import time

    deadline = time.monotonic() + timeout_s
    for t in threading.enumerate():
        if t.name.startswith("terrastream-load"):
            t.join(timeout=max(0.0, deadline - time.monotonic()))
    assert not [t for t in threading.enumerate() if t.name.startswith("terrastream-load")]


def test_a_camera_beyond_the_32_bit_cell_index_is_named(store, tmp_path):
    """``--camera 1e11,…`` once ended in ``struct.error`` (exit 1); now exit 2 naming the flag,
    and the API's camera is refused by the renderer with the reason. The control: 1e8 m away
    (well inside 2^31 cells) gets past the check, to the sub-pixel view's own error."""
    from render.errors import RenderError
    from render.pipeline import render_view
    from streamer.camera import Camera
    from tiler.store import open_store

    out = tmp_path / "x.png"
    base = ["render", store, "--size", "96x64", "-o", str(out), "--yaw", "0", "--pitch", "-10"]
    res = runner.invoke(app, [*base, "--camera", "1e11,0,3000"])
    assert res.exit_code == 2, res.output
    assert "--camera 1e11,0,3000 lies more than 2^31 cells" in res.output
    res = runner.invoke(app, [*base, "--camera", "1e8,0,3000"])
    assert res.exit_code == 2 and "2^31" not in res.output, res.output
    s = open_store(store)
    far = Camera((1e11, 0.0, 3000.0), yaw=0, pitch=-10, viewport=(96, 64), far=1e12)
    with pytest.raises(RenderError, match="32-bit cell index"):
        render_view(s, far)


def test_compare_quick_keeps_what_is_given_beside_it(store, tmp_path):
    """``--quick`` once replaced ``--taus``, ``--size`` and ``--frames`` given beside it; the
    control: without ``--taus`` it sweeps its own 1,4."""
    js = tmp_path / "c.json"
    args = ["compare", store, "--quick", "--lods", "qiu", "--patch-log2", "2", "--json", str(js)]
    res = runner.invoke(app, [*args, "--taus", "2"])
    assert res.exit_code == 0, res.output
    assert [r["tau"] for r in json.loads(js.read_text())] == [2.0]
    res = runner.invoke(app, [*args, "--overwrite"])  # (the same --json as above)
    assert res.exit_code == 0, res.output
    assert [r["tau"] for r in json.loads(js.read_text())] == [1.0, 4.0]


def test_a_flythrough_stopped_midway_keeps_its_frames_csv(store, tmp_path, monkeypatch):
    """An error at frame 3 (a budget error raised on purpose) once left PNG frames without
    ``frames.csv``; the frames flown are in ``frames.csv`` and ``summary.json`` says where and
    why it stopped, then the error exits 2. The control: without the error, all 4 frames."""
    args = ["flythrough", store, "--frames", "4", "--size", "64x48", "--patch-log2", "2"]
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    assert len((tmp_path / "a" / "frames.csv").read_text().splitlines()) == 1 + 4
    budget_error_at(monkeypatch, 3)
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "b")])
    assert res.exit_code == 2, res.output
    assert "(on purpose)" in res.output and "(2 of 4 frames)" in res.output
    assert len((tmp_path / "b" / "frames.csv").read_text().splitlines()) == 1 + 2
    stopped = json.loads((tmp_path / "b" / "summary.json").read_text())["stopped"]
    assert stopped["after_frames"] == 2 and "on purpose" in stopped["error"]


@pytest.mark.parametrize("command", ["stream", "compare"])
def test_a_keyframe_path_under_the_ground_is_warned_about_by_stream_and_compare(
    command, store, tmp_path
):
    """``stream`` and ``compare`` with a ``--path`` file whose cameras dip under the terrain
    say so, naming the frame and the depth (``flythrough`` and ``render --camera`` already
    did); the control, the same path 1 m above the ground, is quiet."""
    from streamer.clip import ground_height
    from tiler.store import open_store

    cx, cy = _centre(store)
    ground = ground_height(open_store(store), cx, cy)
    args = {
        "stream": ["stream", store, "--frames", "2", "--size", "64x48", "--no-prefetch"],
        "compare": ["compare", store, "--frames", "2", "--lods", "qiu", "--taus", "1",
                    "--size", "64x48", "--patch-log2", "2"],
    }[command]  # fmt: skip
    under = [(0, cx, cy, ground + 200, 0, -30), (1, cx, cy, ground - 40, 0, -30)]
    res = runner.invoke(app, [*args, "--path", _keyframes(tmp_path, under)])
    assert "1 of the path's 2 frames have the camera below the terrain under it" in res.output
    assert "(the first: frame 1, 40.0 m below" in res.output
    above = [(0, cx, cy, ground + 200, 0, -30), (1, cx, cy, ground + 1, 0, -30)]
    res = runner.invoke(app, [*args, "--path", _keyframes(tmp_path, above)])
    assert res.exit_code == 0, res.output
    assert "below the terrain" not in res.output


def test_a_flythrough_into_an_earlier_one_s_folder_needs_overwrite(store, tmp_path):
    """A second fly-through into the same --out left the first one's extra PNGs beside the new
    frames (20 PNGs, frames.csv of 10 rows, exit 0). It is refused now; --overwrite removes
    the earlier frames first and leaves other files."""
    out = tmp_path / "f"
    base = ["flythrough", store, "--size", "64x48", "--patch-log2", "2", "--out", str(out)]
    assert runner.invoke(app, [*base, "--frames", "4"]).exit_code == 0
    (out / "notes.txt").write_text("mine")
    res = runner.invoke(app, [*base, "--frames", "2"])
    assert res.exit_code == 2 and "holds an earlier fly-through (4 frame PNG(s)" in res.output
    assert len(list(out.glob("frame_*.png"))) == 4  # nothing touched
    res = runner.invoke(app, [*base, "--frames", "2", "--overwrite"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.glob("frame_*.png")) == ["frame_00000.png", "frame_00001.png"]
    assert (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "summary.json").read_text())["frames"] == 2


def test_a_flythrough_stopped_by_ctrl_c_keeps_its_frames_figures(store, tmp_path, monkeypatch):
    """Ctrl-C left the PNGs flown without frames.csv or summary.json (an error kept them);
    now both, `stopped` saying it was interrupted, and exit 130."""
    import render.flythrough as fly

    real, calls = fly.frame_step, []

    def stop_at_third(*a, **kw):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*a, **kw)

    monkeypatch.setattr(fly, "frame_step", stop_at_third)
    out = tmp_path / "f"
    args = ["flythrough", store, "--size", "64x48", "--frames", "5", "--patch-log2", "2",
            "--out", str(out)]  # fmt: skip
    res = runner.invoke(app, args)
    assert res.exit_code == 130, res.output
    assert res.output.strip().endswith("interrupted")
    with (out / "frames.csv").open(newline="") as f:
        assert len(list(csv.DictReader(f))) == 2
    stopped = json.loads((out / "summary.json").read_text())["stopped"]
    assert stopped == {"after_frames": 2, "of_frames": 5, "error": "interrupted"}
