"""A fly-through stopped while a frame is written: its PNG was left cut short (Ctrl-C during
the encoder's write), or whole but beyond the frames that frames.csv and summary.json count
(Ctrl-C just after it); either looked like a frame of the flight. Now each PNG is written whole
or not at all and the stopped frame's is removed: the PNGs left are exactly the frames flown.
The control: the same flight, not stopped, keeps all its frames."""

from __future__ import annotations

import csv
import json

import pytest
from gltools import make_context, rough, tile_dem
from PIL import Image
from typer.testing import CliRunner

from cli.main import app

pytestmark = pytest.mark.gl
make_context()
runner = CliRunner()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return str(tile_dem(tmp_path_factory.mktemp("fly44"), rough(65, 7), 33))


def _args(store, out):
    return ["flythrough", store, "--size", "64x48", "--frames", "5", "--patch-log2", "2",
            "--out", str(out)]  # fmt: skip


def _whole_pngs(out) -> list[str]:
    names = sorted(p.name for p in out.glob("frame_*.png"))
    for n in names:
        with Image.open(out / n) as im:
            im.load()  # a cut-short PNG raises here
    return names


def _stop_in_third_save(monkeypatch):
    """Ctrl-C while the third frame's PNG is being written: half of it is out."""
    real, calls = Image.Image.save, []

    def save(self, fp, *a, **kw):
        if "frame_" not in str(fp) and not hasattr(fp, "getvalue"):
            return real(self, fp, *a, **kw)
        calls.append(1)
        real(self, fp, *a, **kw)
        if len(calls) == 3:
            if hasattr(fp, "getvalue"):  # an in-memory buffer: cut it short too
                fp.truncate(len(fp.getvalue()) // 2)
            else:
                with open(fp, "r+b") as f:
                    f.truncate(f.seek(0, 2) // 2)
            raise KeyboardInterrupt
        return None

    monkeypatch.setattr(Image.Image, "save", save)


def _stop_after_third_save(monkeypatch):
    """Ctrl-C once the third frame's PNG is written, before its figures are."""
    from render.renderer import TerrainRenderer

    real, calls = TerrainRenderer.drawn_pixels, []

    def drawn(self, *a, **kw):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(self, *a, **kw)

    monkeypatch.setattr(TerrainRenderer, "drawn_pixels", drawn)


@pytest.mark.parametrize("stop", [_stop_in_third_save, _stop_after_third_save])
def test_a_stopped_flythrough_leaves_only_the_frames_it_flew(store, tmp_path, monkeypatch, stop):
    stop(monkeypatch)
    out = tmp_path / "f"
    res = runner.invoke(app, _args(store, out))
    assert res.exit_code == 130, res.output
    stopped = json.loads((out / "summary.json").read_text())["stopped"]
    assert stopped["after_frames"] == 2
    with (out / "frames.csv").open(newline="") as f:
        assert [r["frame"] for r in csv.DictReader(f)] == ["0", "1"]
    assert _whole_pngs(out) == ["frame_00000.png", "frame_00001.png"]
    assert not list(out.glob("*.partial"))


def test_a_whole_flythrough_keeps_every_frame(store, tmp_path):
    out = tmp_path / "f"
    res = runner.invoke(app, _args(store, out))
    assert res.exit_code == 0, res.output
    assert _whole_pngs(out) == [f"frame_{i:05d}.png" for i in range(5)]
    assert json.loads((out / "summary.json").read_text())["frames"] == 5


def _keyframes(tmp_path, x: float, z: float) -> str:
    p = tmp_path / "path.csv"
    p.write_text(f"t,x,y,z,yaw,pitch\n0,{x},4996500,{z},0,-30\n1,{x},4996600,{z},0,-30\n")
    return str(p)


def test_a_keyframe_path_beyond_the_cell_index_is_refused_before_flying(store, tmp_path):
    """A keyframe 1e11 m east of the DEM stopped the flight at its first frame with exit 1
    ("bring the camera closer"), after the output folder was made; now a usage error naming
    --path and the frame, nothing written. A keyframe at 1e300 m named neither the file nor
    --path. The control: a path over the DEM flies."""
    out = tmp_path / "f"
    base = ["flythrough", store, "--size", "64x48", "--frames", "3", "--patch-log2", "2"]
    res = runner.invoke(app, [*base, "--out", str(out), "--path", _keyframes(tmp_path, 1e11, 3000)])
    assert res.exit_code == 2, res.output
    assert "--path: frame 0 of the path in" in res.output and "2^31 cells" in res.output
    assert not out.exists()
    res = runner.invoke(
        app, [*base, "--out", str(out), "--path", _keyframes(tmp_path, 1e300, 3000)]
    )
    assert res.exit_code == 2, res.output
    assert "--path: a camera of the path in" in res.output and "path.csv" in res.output
    assert not out.exists()
    res = runner.invoke(
        app, [*base, "--out", str(out), "--path", _keyframes(tmp_path, 500900, 2000)]
    )
    assert res.exit_code == 0, res.output
    assert _whole_pngs(out) == [f"frame_{i:05d}.png" for i in range(3)]
