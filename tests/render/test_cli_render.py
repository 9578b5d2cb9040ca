"""The renderer's commands through Typer's CliRunner."""

from __future__ import annotations

import json

import pytest
from gltools import make_context, rough, tile_dem
from typer.testing import CliRunner

from cli.main import app

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
