"""``terrastream stream`` end to end on a small store: a path that sees no terrain, the set
stalls are counted over, the figures of its ``--json``."""

from __future__ import annotations

import json

import pytest
from demtools import fractal, write_dem
from typer.testing import CliRunner

from cli.main import app
from tiler.tile import TileOptions, tile

runner = CliRunner()


def run(*args):
    """Invoke the CLI with ``args`` (stringified)."""
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 257 x 257 store of 4 x 4 blocks of 65 samples, 10 m cells, heights near 500 m."""
    tmp = tmp_path_factory.mktemp("streamcmd")
    src = write_dem(tmp / "d.tif", fractal((257, 257), 5), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=65, workers=1))


def keyframes(tmp_path, store, z: float, pitch: float, name: str = "p.csv"):
    """A two-keyframe CSV path above the middle of ``store`` at height ``z`` and ``pitch``."""
    x0, y0, x1, y1 = store.grid.extent
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    p = tmp_path / name
    p.write_text(f"t,x,y,z,yaw,pitch\n0,{cx},{cy},{z},0,{pitch}\n1,{cx},{cy},{z + 500},0,{pitch}\n")
    return p


@pytest.mark.parametrize("pitch", [90, 60])
def test_a_path_looking_at_the_sky_is_refused(tmp_path, store, pitch):
    """A camera 8 km up looking above the horizon sees no terrain: exit 2, nothing written."""
    out = tmp_path / "s.json"
    path = keyframes(tmp_path, store, 8000.0, pitch)
    r = run("stream", store.url, "--path", path, "--frames", 6, "--size", "64x48", "--json", out)
    assert r.exit_code == 2, r.output
    assert "sees the DEM" in r.output
    assert not out.exists()


def test_a_path_looking_at_the_ground_streams(tmp_path, store):
    """Positive control: the same path looking down streams and writes its --json."""
    out = tmp_path / "s.json"
    path = keyframes(tmp_path, store, 8000.0, -60)
    r = run("stream", store.url, "--path", path, "--frames", 6, "--size", "64x48", "--json", out)
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    assert all(row["visible_blocks"] > 0 for row in d["frames"])


def nadir_path(tmp_path, store):
    """A camera hovering 3 km above the middle of ``store`` looking (almost) straight down:
    its view holds the whole store; Qiu's triangle, its apex under the camera, half of it."""
    x0, y0, x1, y1 = store.grid.extent
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    p = tmp_path / "nadir.csv"
    p.write_text(f"t,x,y,z,yaw,pitch\n0,{cx},{cy},3000,0,-89\n1,{cx},{cy},3000,0,-89\n")
    return p


def test_stream_counts_the_hull_under_qius_triangle(tmp_path, store):
    """Under Qiu's triangle (the default) the blocks behind the apex are never loaded: the
    frames the renderer would draw have holes, and stream says so beside the triangle's 0."""
    out = tmp_path / "s.json"
    args = ["--frames", 8, "--fps", 30, "--size", "64x48", "--json", out]
    r = run("stream", store.url, "--path", nadir_path(tmp_path, store), *args)
    assert r.exit_code == 0, r.output
    s = json.loads(out.read_text())["summary"]
    assert s["stall_set"] == "triangle"
    assert s["hole_frames"] == 0
    assert s["stall_frames_hull"] == s["hole_frames_hull"] == 8
    assert "over the frustum hull the renderer draws: stall frames 8, frames with holes 8" in (
        r.output
    )
    assert "--culling hull streams what is drawn" in r.output


def test_stream_culling_hull_streams_what_is_drawn(tmp_path, store):
    """Positive control: under ``--culling hull`` the same hovering camera waits for the whole
    view on frame 0 and nothing is missing after; no warning."""
    out = tmp_path / "s.json"
    args = ["--frames", 8, "--fps", 30, "--size", "64x48", "--json", out, "--culling", "hull"]
    r = run("stream", store.url, "--path", nadir_path(tmp_path, store), *args)
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    assert d["summary"]["stall_set"] == "hull"
    assert d["summary"]["stall_frames"] == d["summary"]["hole_frames"] == 0
    assert all(row["visible_blocks"] == 16 for row in d["frames"])
    assert "warning" not in r.output
