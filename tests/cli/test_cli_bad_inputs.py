"""Every bad input a message (issue 11 item 5): one line naming the value, exit 1 or 2, no
traceback; checks of output paths happen before any long run; Ctrl-C exits 130."""

from __future__ import annotations

import re
import time

import pytest
from demtools import fractal, write_dem
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def flat(text: str) -> str:
    """Output with rich's boxes and line wrapping removed (for substring checks)."""
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", text).split())


@pytest.fixture(scope="module")
def paths(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    src = write_dem(d / "dem.tif", fractal((65, 65), 5))
    assert run("tile", src, d / "s.zarr", "--block-size", "33").exit_code == 0
    (d / "adir").mkdir()
    return {"tmp": d, "src": src, "store": d / "s.zarr", "dir": d / "adir"}


# (arguments, exit status, message): {tmp}, {src}, {store}, {dir} are filled in
CASES = {
    "path-missing": (["stream", "{store}", "--path", "{tmp}/nope.json"], 2,
                     "error: --path: '{tmp}/nope.json' does not exist"),
    "path-is-dir": (["stream", "{store}", "--path", "{dir}"], 2, "is a directory, not a file"),
    "flythrough-path-missing": (["flythrough", "{store}", "--path", "{tmp}/k.csv",
                                 "--out", "{tmp}/f"], 2, "'{tmp}/k.csv' does not exist"),
    "resolution-units": (["tile", "{src}", "{tmp}/r.zarr", "--dst-crs", "EPSG:32633",
                          "--resolution", "0.0003"], 2,
                         "error: --resolution 0.0003 is 100,000x finer than the source's pixels "
                         "(~30 m in the target CRS)"),
    "synth-size-huge": (["synth", "{tmp}/huge.tif", "--size", "100000000"], 2,
                        "error: size 100,000,000 is beyond the 1,048,577 samples per side synth "
                        "writes (1e+16 samples)"),
    "budget-inf": (["stream", "{store}", "--budget-mb", "inf"], 2,
                   "'inf' is not a finite number; give a finite one in the range 9.53674e-07<=x"),
    "budget-nan": (["flythrough", "{store}", "--budget-mb", "nan"], 2,
                   "'nan' is not a finite number"),
    "budget-zero": (["stream", "{store}", "--budget-mb", "0"], 2,
                    "0 is not in the range 9.53674e-07<=x<=1.09951e+12 (one byte"),
    "stream-json-missing-dir": (["stream", "{store}", "--json", "{tmp}/no/s.json"], 2,
                                "the directory '{tmp}/no' for {tmp}/no/s.json does not exist"),
    "stream-plot-extension": (["stream", "{store}", "--plot", "{tmp}/p.xyz"], 2,
                              "cannot tell the file format of '{tmp}/p.xyz'"),
    "tradeoff-json-missing-dir": (["tradeoff", "{store}", "--json", "{tmp}/no/t.json"], 2,
                                  "the directory '{tmp}/no' for {tmp}/no/t.json does not exist"),
    "compare-plot-missing-dir": (["compare", "{store}", "--plot", "{tmp}/no/c.png"], 2,
                                 "the directory '{tmp}/no'"),
    "render-out-missing-dir": (["render", "{store}", "-o", "{tmp}/no/v.png"], 2,
                               "the directory '{tmp}/no' for {tmp}/no/v.png does not exist"),
    "render-out-extension": (["render", "{store}", "-o", "{tmp}/v.xyz"], 2,
                             "cannot tell the file format of '{tmp}/v.xyz' from its extension "
                             "'.xyz'; use one of"),
    "render-out-no-extension": (["render", "{store}", "-o", "{tmp}/view"], 2,
                                "from its extension '(none)'"),
    "view-screenshot-extension": (["view", "{store}", "--frames", "1", "--screenshot",
                                   "{tmp}/s.abc"], 2, "cannot tell the file format"),
    "synth-missing-dir": (["synth", "{tmp}/no/d.tif", "--size", "65"], 2,
                          "the directory '{tmp}/no' for {tmp}/no/d.tif does not exist"),
    "synth-out-is-dir": (["synth", "{dir}", "--size", "65"], 2, "is a directory; give a file name"),
    "export-missing-dir": (["export", "{store}", "{tmp}/no/e.tif"], 2, "the directory '{tmp}/no'"),
    # both wrote a GeoTIFF under any name (e.png held a TIFF)
    "synth-out-extension": (["synth", "{tmp}/d.png", "--size", "65"], 2,
                            "from its extension '.png'; use one of .tif, .tiff"),
    "export-out-extension": (["export", "{store}", "{tmp}/e.png"], 2,
                             "from its extension '.png'; use one of .tif, .tiff"),
    "tile-dst-http": (["tile", "{src}", "http://127.0.0.1:9/s.zarr"], 2,
                      "DST: 'http://127.0.0.1:9/s.zarr' is an http(s) store, which is read-only"),
    "tile-dst-missing-parent": (["tile", "{src}", "{tmp}/no/s.zarr", "--block-size", "33"], 2,
                                "the directory '{tmp}/no' for {tmp}/no/s.zarr does not exist"),
    "tile-dst-is-file": (["tile", "{src}", "{src}", "--block-size", "33"], 2,
                         "exists and is a file, not a store directory"),
    # the DEM given where its store belongs: "NotADirectoryError: ... 'dem.tif/zarr.json'", and
    # verify called it "damaged beyond what --repair mends"
    "render-store-is-file": (["render", "{src}", "-o", "{tmp}/v.png"], 2,
                             "is a file, not a store (a directory `terrastream tile` makes)"),
    "info-store-is-file": (["info", "{src}"], 2, "if it is a DEM, tile it first: terrastream tile"),
    "verify-store-is-file": (["verify", "{src}"], 2, "is a file, not a store"),
    # --metric was silently ignored by strategies with their own error (and echoed in JSON)
    "render-metric-unused": (["render", "{store}", "--lod", "seamless-patches", "--metric",
                              "conservative", "-o", "{tmp}/v.png"], 2,
                             "--lod seamless-patches selects with its own error and does not "
                             "use --metric conservative"),
    "tradeoff-metric-unused": (["tradeoff", "{store}", "--lod", "jung-han", "--metric",
                                "conservative-view"], 2, "does not use --metric"),
    # "budget must be a positive number of bytes, got 0" named no flag
    "stream-budget-below-a-byte": (["stream", "{store}", "--budget-mb", "1e-7"], 2,
                                   "'--budget-mb': 1e-7 is not in the range"),
    # a warm-up that could never finish was blamed on the store's server
    "stream-latency-beyond-the-wait": (["stream", "{store}", "--latency-ms", "40000"], 2,
                                       "'--latency-ms': 40000 is not in the range 0<=x<30000"),
    # an empty directory given as the store: "No group found in store" with exit 1
    "info-store-is-empty-dir": (["info", "{dir}"], 2, "is a directory but not a store"),
    "render-store-is-empty-dir": (["render", "{dir}", "-o", "{tmp}/v.png"], 2,
                                  "is a directory but not a store (no zarr.json, no arrays)"),
    "flythrough-out-proc": (["flythrough", "{store}", "--out", "/proc/terrastream-frames"], 2,
                            "cannot create the directory '/proc/terrastream-frames'"),
    "flythrough-out-is-file": (["flythrough", "{store}", "--out", "{src}"], 2,
                               "exists and is not a directory"),
    "frames-zero": (["stream", "{store}", "--frames", "0"], 2,
                    "Invalid value for '--frames': 0 is not in the range 1<=x"),
    "frames-text": (["flythrough", "{store}", "--frames", "many"], 2,
                    "'many' is not an integer"),
    "tau-nan": (["render", "{store}", "--tau", "nan"], 2,
                "Invalid value for '--tau': 'nan' is not a finite number; give a finite one in "
                "the range 0<=x"),
    "tau-negative": (["stream", "{store}", "--tau", "-1"], 2, "-1 is not in the range 0<=x"),
    "fov-nan": (["render", "{store}", "--fov", "nan"], 2,
                "'nan' is not a finite number; give a finite one in the range 1<=x<=170"),
    "pitch-nan": (["render", "{store}", "--pitch", "nan"], 2,  # (unbounded: no range said)
                  "Invalid value for '--pitch': 'nan' is not a finite number; give a finite one"),
    "fov-large": (["tradeoff", "{store}", "--fov", "200"], 2, "200 is not in the range 1<=x<=170"),
    "fps-inf": (["stream", "{store}", "--fps", "inf"], 2, "'inf' is not a finite number"),
    "speed-negative": (["stream", "{store}", "--speed", "-3"], 2, "-3 is not in the range 0<x"),
    "latency-nan": (["stream", "{store}", "--latency-ms", "nan"], 2, "'nan' is not a finite"),
    "precision-nan": (["tile", "{src}", "{tmp}/p.zarr", "--precision", "nan"], 2,
                      "'nan' is not a finite number"),
    "patch-log2": (["render", "{store}", "--patch-log2", "9"], 2, "9 is not in the range 1<=x<=7"),
    "patch-log2-0": (["tradeoff", "{store}", "--patch-log2", "0"], 2,
                     "0 is not in the range 1<=x<=7"),
    "taus-nan": (["tradeoff", "{store}", "--taus", "1,nan"], 2,
                 "error: --taus: expected comma-separated finite taus >= 0 such as 0.5,1,2, "
                 "got '1,nan'"),
    "size": (["render", "{store}", "--size", "0x5"], 2,
             "error: --size: viewport 0x5 is outside 1..16384 pixels per side"),
    "size-text": (["stream", "{store}", "--size", "big"], 2, "got 'big'"),
    "lods": (["compare", "{store}", "--lods", "qiu,nope"], 2,
             "error: --lods: unknown LOD strategy 'nope'; choose from qiu"),
    "store-missing": (["stream", "{tmp}/none.zarr"], 2,
                      "error: STORE: no store at '{tmp}/none.zarr': the path does not exist"),
    "store-missing-render": (["render", "{tmp}/none.zarr"], 2, "no store at '{tmp}/none.zarr'"),
    "export-level": (["export", "{store}", "{tmp}/l.tif", "--level", "7"], 2,
                     "--level must be in 0..5 for this store, got 7"),
}  # fmt: skip


@pytest.mark.parametrize(("args", "status", "message"), CASES.values(), ids=CASES.keys())
def test_bad_input_gives_one_message(paths, args, status, message):
    r = run(*[a.format(**paths) for a in args])
    assert r.exit_code == status, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output  # one line
    assert message.format(**paths) in lines[0]
    assert "Traceback" not in r.output and "np.float64" not in r.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["render"], "error: Missing argument 'STORE'. (see 'terrastream render --help')"),
        (["render", "S", "--bogus"], "error: No such option: --bogus"),
        (["rendr", "S"], "error: No such command 'rendr'."),
    ],
    ids=["missing-argument", "unknown-option", "unknown-command"],
)
def test_usage_errors_are_one_line_exit_2(args, message):
    r = run(*args)
    assert r.exit_code == 2 and r.output.startswith(message) and len(r.output.splitlines()) == 1


def test_output_paths_are_checked_before_the_run(paths, monkeypatch):
    import streamer.run

    ran = []
    monkeypatch.setattr(streamer.run, "run_flythrough", lambda *a, **k: ran.append(1))
    t0 = time.monotonic()
    r = run("stream", paths["store"], "--frames", "100000", "--fps", "1",
            "--json", paths["tmp"] / "missing" / "s.json")  # fmt: skip
    assert r.exit_code == 2 and "does not exist; create it first" in flat(r.output)
    assert ran == [] and time.monotonic() - t0 < 30


def test_library_error_is_one_line_exit_1(paths, tmp_path):
    import shutil

    bad = tmp_path / "bad.zarr"
    shutil.copytree(paths["store"], bad)
    (bad / "zarr.json").write_text("{ not json")
    r = run("info", bad)
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(bad) in lines[0]


def test_unexpected_error_is_one_line_exit_1_and_traceback_with_vv(paths, monkeypatch):
    import tiler.info

    def boom(url):
        raise RuntimeError(f"something broke at {url}")

    monkeypatch.setattr(tiler.info, "store_info", boom)
    r = run("info", paths["store"])
    assert r.exit_code == 1
    assert r.output.strip() == (
        f"error: RuntimeError: something broke at {paths['store']} (-vv: traceback)"
    )
    r = run("-vv", "info", paths["store"])
    assert r.exit_code == 1 and "Traceback" in r.output and "something broke" in r.output


@pytest.mark.parametrize("where", ["info", "tile"])
def test_ctrl_c_exits_130_with_one_line(paths, monkeypatch, where, tmp_path):
    import tiler.info
    import tiler.tile

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(tiler.info, "store_info", interrupted)
    monkeypatch.setattr(tiler.tile, "tile", interrupted)
    args = ["info", paths["store"]] if where == "info" else ["tile", paths["src"], tmp_path / "t"]
    r = run(*args)
    assert r.exit_code == 130
    # only a tile resumes; a rerun of anything else starts again (and says nothing else)
    want = "interrupted; rerun the same command to resume" if where == "tile" else "interrupted"
    assert r.output.strip() == want


def test_a_ctrl_c_after_the_store_was_finished_says_so(paths, monkeypatch, tmp_path):
    """A Ctrl-C landing after `tile` finished the store (while it printed its summary) said
    "rerun the same command to resume", and the rerun was refused: the store is finished. It
    says so now (exit 130). The control, an interrupt before the end: the test above."""
    import tiler.tile

    real = tiler.tile.tile

    def finished_then_interrupted(*a, **k):
        real(*a, **k)
        raise KeyboardInterrupt

    monkeypatch.setattr(tiler.tile, "tile", finished_then_interrupted)
    r = run("tile", paths["src"], tmp_path / "t.zarr")
    assert r.exit_code == 130
    assert "was finished: the store is complete, nothing to resume" in r.output, r.output
    assert "rerun" not in r.output


def test_numpy_reprs_are_shown_as_values():
    import numpy as np

    from cli.common import one_line
    from tiler.errors import LayoutError

    exc = LayoutError(f"bad extent {np.float64(1.5)!r} .. {np.int64(7)!r}")
    assert one_line(exc) == "bad extent 1.5 .. 7"


def test_a_lowercase_exception_type_is_named_with_its_module():
    """struct.error printed as "error: error: argument out of range"."""
    import struct

    from cli.common import one_line

    assert one_line(struct.error("argument out of range")) == "struct.error: argument out of range"
    assert one_line(KeyError("k")) == "KeyError: 'k'"  # the control: a class name as it is


def _damaged(tmp_path, how: str):
    import numpy as np
    import rasterio
    from rasterio.transform import from_origin

    path = tmp_path / f"{how}.tif"
    data = fractal((257, 257), 2)
    with rasterio.open(path, "w", driver="GTiff", width=257, height=257, count=1,
                       dtype=data.dtype, crs="EPSG:32633", compress="deflate",
                       transform=from_origin(500000, 5000000, 30, 30)) as dst:  # fmt: skip
        dst.write(data, 1)
    raw = bytearray(path.read_bytes())
    if how == "truncated":
        raw = raw[: len(raw) // 4]
    else:  # a corrupted strip: garbage in the middle of the compressed data
        mid = len(raw) // 2
        raw[mid : mid + 2000] = np.full(2000, 0xFF, np.uint8).tobytes()
    path.write_bytes(bytes(raw))
    return path


@pytest.mark.parametrize(("how", "cause"), [("truncated", "Read error"), ("corrupt", "error")])
@pytest.mark.parametrize("workers", ["1", "2"])
def test_damaged_geotiff_is_one_line_exit_1_with_the_cause(tmp_path, how, cause, workers):
    src = _damaged(tmp_path, how)
    r = run("-q", "tile", src, tmp_path / "s.zarr", "--block-size", "33", "--workers", workers)
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    assert cause in lines[0] and "See previous exception" not in lines[0]
    assert "Traceback" not in r.output


def test_a_stream_path_that_sees_none_of_the_dem_is_exit_2_and_writes_nothing(paths):
    from tiler.store import open_store

    d = paths["tmp"]
    x0, y0, x1, y1 = open_store(paths["store"]).grid.extent
    kf = d / "away.csv"
    away = f"{x1 + 1e6},{y1 + 1e6},3000,45,-10"  # beyond the north-east corner, looking away
    kf.write_text(f"t,x,y,z,yaw,pitch\n0,{away}\n1,{away}\n")
    r = run("stream", paths["store"], "--path", kf, "--frames", "3", "--json", d / "away.json")
    assert r.exit_code == 2, r.output
    assert "error: --path: none of the 3 frame(s) of the camera path sees the DEM" in r.output
    assert "no level could be loaded" not in r.output and not (d / "away.json").exists()
    # positive control: the same flight over the DEM's centre streams and writes its JSON
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    kf.write_text(f"t,x,y,z,yaw,pitch\n0,{cx},{cy},3000,0,-45\n1,{cx},{cy + 50},3000,0,-45\n")
    r = run("stream", paths["store"], "--path", kf, "--frames", "3", "--json", d / "over.json")
    assert r.exit_code == 0, r.output
    assert (d / "over.json").exists()


def test_a_store_missing_its_root_metadata_is_damage_not_a_usage_error(paths, tmp_path):
    """The control of ``*-store-is-empty-dir``: a directory with arrays but no root
    ``zarr.json`` is a damaged store (exit 1), not "not a store"."""
    import shutil

    dmg = tmp_path / "d.zarr"
    shutil.copytree(paths["store"], dmg)
    (dmg / "zarr.json").unlink()
    res = run("info", dmg)
    assert res.exit_code == 1, res.output
    assert "not a store" not in res.output and "no terrastream store" in res.output


def test_the_latency_bound_is_the_sessions_wait():
    from cli.commands.stream import LATENCY_MAX_MS
    from streamer.frames import SessionConfig

    assert 1000 * SessionConfig().wait_timeout_s == LATENCY_MAX_MS
