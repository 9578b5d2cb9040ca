"""The CLI audit's outputs and values (issue 11): no output replaces an existing file without
``--overwrite``, and none ever replaces an input (the store, a ``--path`` file) or another
output; ``flythrough --overwrite`` removes nothing before the store and path are checked;
every JSON is strict; huge ``--budget-mb``/``--frames``/``--cell-size`` are usage errors;
``--latency-ms`` timeouts blame the latency; ``tile --resampling``/``--repair``/``--from-list``
misuses and plain numbers name their values. Each test has its positive control (what the old
code did wrong) beside the normal case."""

from __future__ import annotations

import hashlib
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from demtools import fractal, write_dem
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()
SMALL = ["--size", "64x48", "--patch-log2", "2"]


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def flat(text: str) -> str:
    """Output with rich's boxes and line wrapping removed (for substring checks)."""
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", text).split())


def digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def strict_json(text: str):
    """``json.loads`` refusing NaN/Infinity tokens (as every parser but Python's does)."""

    def refuse(token):
        raise ValueError(f"non-JSON token {token}")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def paths(tmp_path_factory):
    d = tmp_path_factory.mktemp("audit")
    src = write_dem(d / "dem.tif", fractal((65, 65), 5))
    assert run("tile", src, d / "s.zarr", "--block-size", "33").exit_code == 0
    kf = d / "kf.json"
    kf.write_text(
        json.dumps(
            [
                {"t": 0, "x": 500300, "y": 4998500, "z": 1500, "yaw": 45, "pitch": -30},
                {"t": 1, "x": 500900, "y": 4999100, "z": 1500, "yaw": 45, "pitch": -30},
            ]
        )
    )
    return {"tmp": d, "src": src, "store": d / "s.zarr", "kf": kf}


# --- 1. outputs: no silent overwrite, never an input, never twice ----------------------------


@pytest.mark.gl
def test_render_refuses_an_existing_out_and_replaces_it_with_overwrite(paths, tmp_path):
    dem = tmp_path / "dem.tif"
    dem.write_bytes(Path(paths["src"]).read_bytes())
    before = digest(dem)
    r = run("render", paths["store"], "-o", dem, *SMALL)
    assert r.exit_code == 2, r.output
    assert f"{dem} exists; pass --overwrite to replace it" in flat(r.output)
    assert digest(dem) == before  # the positive control: the DEM was replaced by an RGB TIFF
    # the normal case: a new file, then replaced with --overwrite
    out = tmp_path / "v.png"
    assert run("render", paths["store"], "-o", out, *SMALL).exit_code == 0
    r = run("render", paths["store"], "-o", out, *SMALL, "--overwrite")
    assert r.exit_code == 0, r.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob("*.partial"))


@pytest.mark.gl
def test_render_save_that_fails_leaves_no_half_file(paths, tmp_path, monkeypatch):
    from PIL import Image

    def failing_save(self, fp, format=None, **kw):
        half = b"\x89PNG half"
        if isinstance(fp, (str, Path)):
            Path(fp).write_bytes(half)
        else:
            fp.write(half)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", failing_save)
    out = tmp_path / "v.png"
    r = run("render", paths["store"], "-o", out, *SMALL)
    assert r.exit_code == 1, r.output
    assert "No space left on device" in r.output
    assert not out.exists()  # the positive control: a half PNG was left at OUT
    assert list(tmp_path.iterdir()) == []


def test_an_output_inside_the_store_is_refused_even_with_overwrite(paths):
    meta = paths["store"] / "zarr.json"
    before = digest(meta)
    for cmd in (["tradeoff", paths["store"], "--taus", "1"], ["stream", paths["store"]]):
        r = run(*cmd, "--json", meta, "--overwrite")
        assert r.exit_code == 2, r.output
        assert f"'{meta}' is inside the input STORE '{paths['store']}'" in flat(r.output)
        assert "--overwrite never replaces an input" in flat(r.output)
    r = run("render", paths["store"], "-o", paths["store"] / "x.png", "--overwrite")
    assert r.exit_code == 2 and "is inside the input STORE" in flat(r.output)
    assert digest(meta) == before
    assert run("info", paths["store"]).exit_code == 0


def test_the_keyframes_file_is_never_an_output(paths):
    kf = paths["kf"]
    before = digest(kf)
    for cmd in ("stream", "compare"):
        r = run(cmd, paths["store"], "--path", kf, "--json", kf, "--overwrite")
        assert r.exit_code == 2, r.output
        assert f"'{kf}' is the input --path '{kf}'" in flat(r.output)
    assert digest(kf) == before  # the positive control: the keyframes became the flight's JSON


def test_two_outputs_naming_one_file_are_refused(paths, tmp_path):
    same = tmp_path / "same.png"
    for cmd in ("stream", "tradeoff", "compare"):
        r = run(cmd, paths["store"], "--json", same, "--plot", same)
        assert r.exit_code == 2, r.output
        assert f"--json and --plot both name '{same}'" in flat(r.output)
    assert not same.exists()


@pytest.mark.parametrize(
    ("cmd", "opt"),
    [
        (["stream", "--frames", "3"], "--json"),
        (["stream", "--frames", "3"], "--plot"),
        (["tradeoff", "--taus", "1"], "--json"),
        (["tradeoff", "--taus", "1"], "--plot"),
        (["compare", "--quick"], "--json"),
        (["compare", "--quick"], "--plot"),
        (["view", "--frames", "1"], "--screenshot"),
    ],
)
def test_existing_outputs_need_overwrite(paths, tmp_path, cmd, opt):
    out = tmp_path / ("o.png" if opt != "--json" else "o.json")
    out.write_text("mine")
    r = run(cmd[0], paths["store"], *cmd[1:], opt, out)
    assert r.exit_code == 2, r.output
    assert f"{opt}: {out} exists; pass --overwrite to replace it" in flat(r.output)
    assert out.read_text() == "mine"


@pytest.mark.gl
def test_stream_json_with_overwrite_replaces_it(paths, tmp_path):
    js = tmp_path / "s.json"
    js.write_text("old")
    r = run("stream", paths["store"], "--frames", "2", "--size", "64x48", "--json", js,
            "--overwrite")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert strict_json(js.read_text())["summary"]["frames"] == 2


# --- 2. flythrough --overwrite deletes only after the checks; SIGTERM in the summary --------


@pytest.mark.gl
def test_flythrough_overwrite_keeps_the_old_frames_when_the_store_is_a_typo(paths, tmp_path):
    out = tmp_path / "fly"
    args = ["--frames", "2", *SMALL, "--out", out]
    assert run("flythrough", paths["store"], *args).exit_code == 0
    before = sorted(p.name for p in out.iterdir())
    assert "summary.json" in before and "frame_00000.png" in before
    r = run("flythrough", paths["tmp"] / "typo.zarr", *args, "--overwrite")
    assert r.exit_code == 2 and "no store at" in r.output
    assert sorted(p.name for p in out.iterdir()) == before  # the control: fly/ was emptied
    r = run("flythrough", paths["store"], *args, "--overwrite", "--path", tmp_path / "no.json")
    assert r.exit_code == 2 and sorted(p.name for p in out.iterdir()) == before
    # the normal case: replaced
    r = run("flythrough", paths["store"], *args[:-2], "--out", out, "--overwrite", "--every", "0")
    assert r.exit_code == 0, r.output
    assert not list(out.glob("frame_*.png"))  # --every 0: no PNGs, the old ones removed
    assert strict_json((out / "summary.json").read_text())["frames"] == 2


def test_flythrough_out_inside_the_store_is_refused(paths):
    r = run("flythrough", paths["store"], "--out", paths["store"] / "frames", "--overwrite")
    assert r.exit_code == 2 and "is inside the input STORE" in flat(r.output)
    assert not (paths["store"] / "frames").exists()


@pytest.mark.gl
def test_flythrough_summary_after_sigterm_says_terminated(paths, tmp_path, monkeypatch):
    import render.flythrough as fly
    from cli.common import state

    real, calls = fly.frame_step, []

    def stop_at_second(*a, **kw):
        calls.append(1)
        if len(calls) == 2:
            state.terminated = True  # what cli.common's SIGTERM handler sets
            raise KeyboardInterrupt
        return real(*a, **kw)

    monkeypatch.setattr(fly, "frame_step", stop_at_second)
    monkeypatch.setattr(state, "terminated", False)
    out = tmp_path / "f"
    r = run("flythrough", paths["store"], "--frames", "4", *SMALL, "--out", out)
    assert r.exit_code == 143, r.output
    stopped = strict_json((out / "summary.json").read_text())["stopped"]
    assert stopped["error"] == "terminated (SIGTERM)"  # was "interrupted (Ctrl-C)"


# --- 3. strict JSON ---------------------------------------------------------------------------


def test_info_json_of_a_nan_nodata_store_is_strict_json(tmp_path):
    a = fractal((65, 65), 3, "float32")
    a[:5] = np.nan
    src = write_dem(tmp_path / "f.tif", a, nodata=float("nan"))
    assert run("tile", src, tmp_path / "f.zarr", "--block-size", "33").exit_code == 0
    r = run("info", tmp_path / "f.zarr", "--json")
    assert r.exit_code == 0, r.output
    assert "NaN" not in r.output  # the positive control: "nodata": NaN
    d = strict_json(r.output)
    assert d["nodata"] == "nan" and math.isnan(float(d["nodata"]))
    # the normal case: a finite nodata stays a number, none stays null
    i = fractal((65, 65), 3)
    i[:3] = -9999
    src = write_dem(tmp_path / "i.tif", i, nodata=-9999)
    assert run("tile", src, tmp_path / "i.zarr", "--block-size", "33").exit_code == 0
    assert strict_json(run("info", tmp_path / "i.zarr", "--json").output)["nodata"] == -9999


def test_json_text_turns_non_finite_values_into_null():
    from cli.formatters import json_nodata, json_text

    text = json_text({"a": float("nan"), "b": [np.float32("inf"), 1.5, (2, np.int64(3))]})
    assert strict_json(text) == {"a": None, "b": [None, 1.5, [2, 3]]}
    assert [json_nodata(v) for v in (float("nan"), float("-inf"), -9999, None)] == [
        "nan", "-inf", -9999, None
    ]  # fmt: skip


# --- 4., 5. huge --budget-mb and --frames ---------------------------------------------------


@pytest.mark.parametrize("cmd", ["stream", "flythrough", "view"])
def test_huge_budget_is_a_usage_error(paths, tmp_path, cmd):
    r = run(cmd, paths["store"], "--budget-mb", "1e308", "--frames", "1", *SMALL[:2])
    assert r.exit_code == 2, r.output
    assert "1e308 is not in the range" in flat(r.output) and "OverflowError" not in r.output
    assert "1 EiB (2^40 MiB)" in flat(r.output)


def test_session_config_refuses_a_budget_whose_bytes_overflow():
    from streamer.errors import StreamerError
    from streamer.frames import SessionConfig

    with pytest.raises(StreamerError, match=r"invalid budget_mb: 1e\+308 \(from one byte"):
        SessionConfig(budget_mb=1e308)
    assert SessionConfig(budget_mb=256.0).budget_mb == 256.0  # the normal case
    assert SessionConfig(budget_mb=2.0**40).budget_mb == 2.0**40


@pytest.mark.parametrize("cmd", ["stream", "flythrough", "compare", "view"])
@pytest.mark.parametrize("value", ["9223372036854775808", "100000000000"])
def test_huge_frames_is_a_usage_error(paths, cmd, value):
    r = run(cmd, paths["store"], "--frames", value)
    assert r.exit_code == 2, r.output
    assert f"{value} is not in the range 1<=x<=10000000" in flat(r.output)


# --- 6. synth --cell-size --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("1e308", "cell size 1e+308 m makes the 65-sample DEM inf m wide, beyond 4e+07 m"),
        ("1e6", "give a cell size of at most 615385 m for this size"),
        ("1e-300", "1e-300 is not in the range 1e-06<=x"),
    ],
)
def test_synth_refuses_a_cell_size_without_finite_bounds(tmp_path, value, message):
    out = tmp_path / "d.tif"
    r = run("synth", out, "--size", "65", "--cell-size", value)
    assert r.exit_code == 2, r.output
    assert message in flat(r.output)
    assert not out.exists()  # the positive control: a GeoTIFF with ±inf bounds, exit 0


def test_synth_cell_size_normal_and_library_checks(tmp_path):
    import rasterio

    from tiler.errors import SourceError
    from tiler.synth import check_extent, synth_dem

    out = tmp_path / "d.tif"
    assert run("synth", out, "--size", "17", "--cell-size", "0.5").exit_code == 0
    with rasterio.open(out) as ds:
        assert ds.bounds.right == 500000 + 17 * 0.5
    with pytest.raises(SourceError, match="beyond 4e"):
        synth_dem(tmp_path / "x.tif", 17, cell_size=1e308)
    with pytest.raises(SourceError, match="finer than 1e-06 m"):
        synth_dem(tmp_path / "x.tif", 17, cell_size=1e-300)
    assert not (tmp_path / "x.tif").exists()
    assert check_extent(2**20 + 1, 30.0) == 30.0  # the largest size at the default cells


# --- 7. --latency-ms: the waits scale with it, and a timeout blames it -------------------------


def test_stream_waits_scale_with_the_injected_latency():
    from cli.commands.stream import LATENCY_MAX_MS, wait_timeout_s

    assert wait_timeout_s(0) == 30.0
    # a 4 x 4-block store's warm-up took 24 latencies with 4 workers: 10 s needs 240 s
    assert wait_timeout_s(10_000) >= 30 + 24 * 10
    assert wait_timeout_s(LATENCY_MAX_MS) < math.inf


@pytest.mark.gl
def test_stream_timeout_with_latency_names_the_latency(paths, monkeypatch):
    import cli.commands.stream as stream

    monkeypatch.setattr(stream, "WAIT_BASE_S", 0.05)
    monkeypatch.setattr(stream, "WAIT_LATENCIES", 1)
    r = run("stream", paths["store"], "--frames", "2", "--size", "64x48", "--latency-ms", "300")
    assert r.exit_code == 2, r.output
    text = flat(r.output)
    assert "--latency-ms" in text and "the injected latency is the cause" in text
    assert "check the store's server" not in text  # the positive control: blamed the server


# --- 8., 10., 11., 12. tile's options ---------------------------------------------------------


def test_tile_resampling_without_dst_crs_is_refused(paths, tmp_path):
    r = run("tile", paths["src"], tmp_path / "r.zarr", "--resampling", "nearest")
    assert r.exit_code == 2, r.output
    assert "--resampling nearest applies when reprojecting" in flat(r.output)
    assert not (tmp_path / "r.zarr").exists()
    # the normal case: the default resampling without --dst-crs is no error
    r = run("tile", paths["src"], tmp_path / "ok.zarr", "--block-size", "33")
    assert r.exit_code == 0, r.output


def test_tile_repair_of_a_missing_store_is_a_usage_error(paths, tmp_path):
    dst = tmp_path / "new.zarr"
    r = run("tile", paths["src"], dst, "--repair")
    assert r.exit_code == 2, r.output  # was 1, "cannot be repaired (root metadata unreadable"
    assert f"no store at {dst} to repair; tile without --repair" in flat(r.output)
    assert not dst.exists()


def test_tile_from_list_of_a_binary_file_names_it(paths, tmp_path):
    r = run("tile", "--from-list", paths["src"], tmp_path / "l.zarr")
    assert r.exit_code == 2, r.output
    text = flat(r.output)
    assert "UnicodeDecodeError" not in text
    assert f"the source list '{paths['src']}' (--from-list) is not a UTF-8 text file" in text
    # the normal case: a text list
    listing = tmp_path / "list.txt"
    listing.write_text(f"# sources\n{paths['src']}\n")
    r = run("tile", "--from-list", listing, tmp_path / "l.zarr", "--block-size", "33")
    assert r.exit_code == 0, r.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["tile", "{src}", "{tmp}/n.zarr", "--block-size", "nan"], "'nan' is not an integer"),
        (["tile", "{src}", "{tmp}/n.zarr", "--band", "two"], "'two' is not an integer"),
        (["tile", "{src}", "{tmp}/n.zarr", "--band", "0"], "0 is not in the range 1<=x"),
        (["tile", "{src}", "{tmp}/n.zarr", "--workers", "1.5"], "'1.5' is not an integer"),
        (["tile", "{src}", "{tmp}/n.zarr", "--dst-crs", "auto", "--resolution", "nan"],
         "'nan' is not a finite number"),
        (["synth", "{tmp}/n.tif", "--seed", "x1"], "'x1' is not an integer"),
        (["export", "{store}", "{tmp}/n.tif", "--level", "nan"], "'nan' is not an integer"),
    ],
)  # fmt: skip
def test_plain_numbers_name_the_value(paths, args, message):
    r = run(*[a.format(**paths) for a in args])
    assert r.exit_code == 2, r.output
    assert message in flat(r.output)
    assert "unable to parse" not in r.output


def test_synth_seed_still_takes_any_integer(tmp_path):
    r = run("synth", tmp_path / "s.tif", "--size", "17", "--seed", "-18446744073709551617")
    assert r.exit_code == 0, r.output


# --- 9. compare --metric ----------------------------------------------------------------------


def test_compare_refuses_a_metric_no_strategy_compared_uses(paths):
    from cli.common import UsageError
    from cli.options import check_metric_any

    r = run("compare", paths["store"], "--lods", "seamless-patches", "--metric", "conservative")
    assert r.exit_code == 2, r.output
    assert "do not use --metric conservative" in flat(r.output)
    # the normal case: one strategy of those compared uses it, or all are compared
    assert check_metric_any(["qiu", "seamless-patches"], "conservative") == "conservative"
    assert check_metric_any(None, "conservative") == "conservative"
    with pytest.raises(UsageError, match="jung-han select with their own errors"):
        check_metric_any(["seamless-patches", "jung-han"], "conservative")


# --- 13. flythrough --every 0 -----------------------------------------------------------------


def test_flythrough_help_says_every_0_writes_no_pngs():
    r = run("flythrough", "--help")
    assert "0: no PNGs" in flat(r.output)
