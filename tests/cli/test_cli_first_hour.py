"""A new user's first hour (issue 13 item 7): version, exit statuses, readable help, registry
choices, logging levels, units, info in GDAL order, non-TTY progress, ``--json``."""

from __future__ import annotations

import io
import json
import logging
import re

import pytest
from demtools import budget_error_at, fractal
from typer.testing import CliRunner

from cli import progress as progress_mod
from cli.main import app, version

runner = CliRunner()
COMMANDS = ["tile", "info", "synth", "export", "stream", "render", "tradeoff", "flythrough",
            "view", "compare"]  # fmt: skip


def run(*args, **kw):
    return runner.invoke(app, [str(a) for a in args], **kw)


def flat(text: str) -> str:
    """Output with rich's boxes and line wrapping removed (for substring checks)."""
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", text).split())


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 70 x 90 (width x height) store of 3 x 3 blocks."""
    from demtools import write_dem

    d = tmp_path_factory.mktemp("fh")
    src = write_dem(d / "dem.tif", fractal((90, 70), 11))
    r = run("tile", src, d / "s.zarr", "--block-size", "33")
    assert r.exit_code == 0, r.output
    return d / "s.zarr"


def test_version():
    r = run("--version")
    assert r.exit_code == 0 and r.output.strip() == f"terrastream {version()}"
    assert re.fullmatch(r"\d+\.\d+.*", version())


@pytest.mark.parametrize("command", [None, *COMMANDS], ids=["root", *COMMANDS])
def test_help_is_readable_and_documents_exit_statuses(command):
    r = run(*([command] if command else []), "--help", env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    text = r.output
    assert "{" not in text.split("\n\n")[0] + text.split("Usage:")[1].split("\n")[0]
    assert "<bool>" not in text
    assert "Exit status: 0 success; 1 " in flat(text) and "2 usage error" in flat(text)
    if command is None:
        assert "<int>" not in text  # -v is a count flag
        assert "--version" in text


def test_usage_line_shows_argument_names():
    r = run("tile", "--help", env={"COLUMNS": "200"})
    assert "tile [OPTIONS] SRC... DST" in r.output and "{src}" not in r.output


def test_choices_come_from_the_registries():
    from render.strategies import strategy_names
    from streamer.lod import METRICS
    from streamer.run import PATH_KINDS
    from tiler.synth import DTYPES

    render_help = flat(run("render", "--help", env={"COLUMNS": "250"}).output)
    stream_help = flat(run("stream", "--help", env={"COLUMNS": "250"}).output)
    synth_help = flat(run("synth", "--help", env={"COLUMNS": "250"}).output)
    assert "|".join(strategy_names()).replace("|", "") in render_help.replace("|", "").replace(
        " ", ""
    )
    for text in (render_help, stream_help):  # one metric choice list in render and stream
        assert "|".join(METRICS) in text
    assert "|".join(PATH_KINDS) in stream_help
    assert "|".join(DTYPES) in synth_help


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["stream", "S", "--metric", "nope"], "unknown screen-error metric 'nope'; choose one of"),
        (["render", "S", "--metric", "nope"], "unknown screen-error metric 'nope'; choose one of"),
        (["stream", "S", "--path-kind", "spiral"], "unknown path kind 'spiral'; choose one of"),
        (["synth", "x.tif", "--dtype", "int8"], "unknown sample type 'int8'; choose one of"),
        (["render", "S", "--lod", "nope"], "unknown LOD strategy 'nope'; choose one of"),
    ],
    ids=["stream-metric", "render-metric", "path-kind", "dtype", "lod"],
)
def test_unknown_choice_exits_2_naming_value_and_choices(args, message):
    r = run(*args)
    assert r.exit_code == 2
    assert message in flat(r.output)


def test_verbose_raises_only_terrastreams_loggers(store):
    for flag, level in (("-v", logging.INFO), ("-vv", logging.DEBUG)):
        assert run(flag, "info", store).exit_code == 0
        for name in ("tiler", "streamer", "render", "cli"):
            assert logging.getLogger(name).getEffectiveLevel() == level
        for name in ("numcodecs", "zarr", "fsspec", "rasterio", "PIL"):
            assert logging.getLogger(name).getEffectiveLevel() >= logging.WARNING
    assert run("-q", "info", store).exit_code == 0
    assert logging.getLogger("tiler").getEffectiveLevel() == logging.ERROR
    assert run("info", store).exit_code == 0
    assert logging.getLogger("tiler").getEffectiveLevel() == logging.WARNING


def test_info_prints_width_by_height_and_nodata_none(store):
    r = run("info", store)
    assert r.exit_code == 0, r.output
    assert "samples        70 x 90 int16 (width x height)" in r.output
    assert "nodata         none" in r.output and "None" not in r.output


def test_tile_json_summary_and_progress_lines(tmp_path, dem_factory, monkeypatch):
    monkeypatch.setenv("TERRASTREAM_PROGRESS_S", "0")
    src = dem_factory(fractal((90, 70), 3))
    r = run("tile", src, tmp_path / "s.zarr", "--block-size", "33", "--json")
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert (d["width"], d["height"], d["block_cols"], d["block_rows"]) == (70, 90, 3, 3)
    assert d["levels"] == 6 and d["blocks_total"] == 9 and d["source_bytes"] > 0
    assert "tiling: 100.0 % (9/9 blocks)" in r.stderr and "MiB/s" in r.stderr
    assert "MB/s" not in r.stderr


def test_synth_progress_lines_on_a_non_tty(tmp_path, monkeypatch):
    monkeypatch.setenv("TERRASTREAM_PROGRESS_S", "0")
    r = run("synth", tmp_path / "d.tif", "--size", "65")
    assert r.exit_code == 0, r.output
    assert re.search(r"synth: 100\.0 % \(4225/4225 samples\), [\d.]+ M samples/s", r.stderr)
    r = run("-q", "synth", tmp_path / "e.tif", "--size", "65")
    assert r.exit_code == 0 and "synth:" not in r.stderr


def test_progress_lines_are_periodic(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(progress_mod.time, "monotonic", lambda: now[0])
    monkeypatch.setenv("TERRASTREAM_PROGRESS_S", "5")
    out = io.StringIO()
    p = progress_mod.Progress("tiling", "block", stream=out, quiet=False)
    for i in range(1, 101):
        now[0] += 0.5  # 50 s in all: a line at 0.5 s, then every 5 s, then the final one
        p.update(i, 100, "1.0 MiB/s")
    p.close()
    lines = out.getvalue().splitlines()
    assert 10 <= len(lines) <= 12, lines
    quiet = io.StringIO()
    q = progress_mod.Progress("tiling", "block", stream=quiet, quiet=True)
    q.update(1, 2)
    q.close()
    assert quiet.getvalue() == ""
    assert lines[0].startswith("tiling: 1.0 % (1/100 blocks), 1.0 MiB/s")
    assert lines[-1].startswith("tiling: 100.0 % (100/100 blocks)")
    assert "~" in lines[1] and "s left" in lines[1]


def test_stream_sizes_are_mib(store):
    r = run("stream", store, "--frames", "3", "--fps", "200", "--size", "64x48")
    assert r.exit_code == 0, r.output
    assert "needed MiB" in r.stdout and "MiB budget" in r.stdout
    assert not re.search(r"\bMB\b", r.stdout)
    # a budget under 1 MiB is printed as it is, not rounded to "0 MiB" below the peak
    r = run("stream", store, "--frames", "3", "--fps", "200", "--size", "64x48",
            "--budget-mb", "0.2")  # fmt: skip
    assert r.exit_code == 0, r.output
    peak, budget = re.search(
        r"peak resident ([\d.]+) MiB of a ([\d.]+) MiB budget", r.stdout
    ).groups()
    assert budget == "0.20" and float(peak) <= float(budget)


@pytest.mark.gl
def test_render_json_stats(store, tmp_path, gl_context):
    out = tmp_path / "v.png"
    r = run("render", store, "--size", "64x48", "--patch-log2", "2", "-o", out, "--json")
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["triangles"] > 0 and d["viewport"] == [64, 48] and d["lod"] == "qiu"
    assert d["metric"] == "qiu" and out.stat().st_size > 0
    # a strategy with its own error does not record Eq. 7 as what τ bounded
    again = ["--overwrite"]  # (the same -o as above)
    r = run("render", store, "--size", "64x48", "--lod", "jung-han", "-o", out, "--json", *again)
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["lod"] == "jung-han" and d["metric"] == "own"


def test_registry_defaults_and_lazy_imports():
    import subprocess
    import sys

    from cli.options import DTYPE_DEFAULT, LOD_DEFAULT, METRIC_DEFAULT, METRICS
    from render.strategies import DEFAULT
    from tiler.synth import DTYPES

    assert LOD_DEFAULT == DEFAULT and METRIC_DEFAULT in METRICS.names
    assert DTYPE_DEFAULT in DTYPES
    code = "import sys, cli.main; print(sorted(m for m in ('render.strategies', 'moderngl', "
    code += "'zarr', 'streamer.run') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"  # `terrastream --version` / `tile` start fast


def test_stream_keeps_going_on_read_errors_and_fails_when_blocks_stay_unreadable(store, tmp_path):
    import shutil

    r = run("stream", store, "--frames", "20", "--fps", "100", "--size", "64x48")
    assert r.exit_code == 0, r.output  # the quiet case
    assert "io errors 0" in r.stdout and "blocks failed at the end 0" in r.stdout
    broken = tmp_path / "broken.zarr"
    shutil.copytree(store, broken)
    shutil.rmtree(broken / "levels" / "0" / "c")  # the positive control: every block's level 0
    r = run("stream", broken, "--frames", "20", "--fps", "100", "--size", "64x48")
    assert r.exit_code == 1, r.output
    assert "frames 20" in r.stdout  # it flew the whole path and printed its summary
    assert "a frame needed could not be read by the end" in r.output
    assert "terrastream verify" in r.output and "MissingChunkError" not in r.output


@pytest.mark.parametrize("fault", ["503", "stall", "stall-all"])
def test_stream_over_a_failing_server_blames_the_server_not_the_store(store, fault):
    """A server answering 503 for block data, or not answering one block's reads, or any:
    exit 1 naming the server (not `verify`); the same flight over the healthy server is the
    control (exit 0). With every read stalled the warm-up once ran into its 30 s deadline
    (failed blocks kept the workers); it now ends when they have failed their retries."""
    from rangeserver import LoopbackServer

    srv = LoopbackServer(store.parent)
    with srv as url:
        args = ("stream", f"{url}/{store.name}", "--frames", "60", "--fps", "60", "--size",
                "64x48")  # fmt: skip
        r = run(*args)
        assert r.exit_code == 0, r.output  # the control
        # a stalled read gives up soon (not sooner: a loaded machine connects slowly)
        args += ("--storage-options", '{"timeout": 1}')
        if fault == "503":
            srv.handler.fail_status = 503
        else:  # one block's reads hang, or every block's
            srv.handler.fail_match = "/errors/c/0/0" if fault == "stall" else None
            srv.stall.set()
        r = run(*args)
    assert r.exit_code == 1, r.output
    assert "warm-up did not finish" not in r.output
    assert "the server or the network failed, not the store" in r.output
    assert "verify" not in r.output.split("incomplete:")[-1]
    assert ("503" if fault == "503" else "did not answer in time") in r.output
    if fault == "stall-all":
        assert "frames 60" in r.stdout  # it flew and printed its summary


def test_a_flight_stopped_midway_still_writes_its_json_and_plot(store, tmp_path, monkeypatch):
    """A budget error at frame 6 (raised on purpose) once left no ``--json`` or ``--plot`` of
    the 5 frames flown; they are written, saying where and why the flight stopped, then the
    error exits 2. The control: the same flight without the error writes all 12 frames and
    no ``stopped``."""
    import json

    js, png = tmp_path / "f.json", tmp_path / "f.png"
    args = ("stream", store, "--frames", "12", "--fps", "200", "--size", "64x48",
            "--json", js, "--plot", png)  # fmt: skip
    r = run(*args)
    assert r.exit_code == 0, r.output
    d = json.loads(js.read_text())
    assert len(d["frames"]) == 12 and "stopped" not in d["summary"]
    js.unlink()
    png.unlink()
    budget_error_at(monkeypatch, 6)
    r = run(*args)
    assert r.exit_code == 2, r.output
    assert "(on purpose)" in r.output and "the 5 of 12 frames flown" in r.output
    d = json.loads(js.read_text())
    assert len(d["frames"]) == 5 and png.stat().st_size > 0
    assert (
        d["summary"]["stopped"]["after_frames"] == 5
        and "on purpose" in d["summary"]["stopped"]["error"]
    )


def test_a_store_change_seen_at_close_is_the_verdict_not_a_lost_report(
    store, tmp_path, monkeypatch
):
    """A store replaced after the last frame is seen by a read during ``close()``'s wait, and
    ``close()`` raises it: ``stream`` then exited 1 without its ``--json``. It exits 1 with
    the JSON written and the replacement as the verdict. The control: ``close()`` itself
    still raises the change to a Python caller who never saw it."""
    import json

    import pytest

    from streamer.session import Session
    from tiler.errors import StoreChangedError

    close = Session.close
    changed = StoreChangedError("store 's.zarr' was replaced or rewritten while it was open")

    def close_seeing_a_change(self, timeout_s=10.0):
        with self._cv:
            self.loader.fatal = changed  # what a read during the wait sets
        return close(self, timeout_s)

    monkeypatch.setattr(Session, "close", close_seeing_a_change)
    with pytest.raises(StoreChangedError):  # the control: the library raises it
        Session(str(store)).close()
    js = tmp_path / "c.json"
    r = run("stream", store, "--frames", "3", "--fps", "200", "--size", "64x48", "--json", js)
    assert r.exit_code == 1, r.output
    problem = json.loads(js.read_text())["summary"]["at_close"]["problem"]
    assert problem.startswith("the store was replaced or rewritten while it was streamed")
    assert "replaced or rewritten while it was streamed" in r.output


def test_stream_freezes_the_collectors_heap_after_its_warm_up(store):
    import gc

    assert gc.get_freeze_count() == 0
    r = run("stream", store, "--frames", "3", "--fps", "200", "--size", "64x48")
    assert r.exit_code == 0, r.output
    assert gc.get_freeze_count() > 10_000  # streamer.gcfreeze: no full pass walks them again
