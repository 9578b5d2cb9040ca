"""`view` flown under the ground: the viewer said nothing (``render`` warns, naming the depth);
now a warning once per descent (not every frame), a status-line tag, and a screenshot taken
from below the ground says so. Controls: a camera flying clear of the ground stays quiet."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from gltools import rough, tile_dem

from render.ground_watch import GroundWatch
from render.viewer import Pose, camera_at
from streamer.clip import ground_height
from tiler.store import open_store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return open_store(tile_dem(tmp_path_factory.mktemp("ground"), rough(65, 7), 33))


def _cams(store, heights):
    """Cameras at the DEM's centre at these heights above (negative: below) the ground."""
    x0, y0, x1, y1 = store.grid.extent
    x, y = 0.5 * (x0 + x1) + 7.0, 0.5 * (y0 + y1) - 5.0
    g = ground_height(store, x, y)
    return [camera_at(Pose(x, y, g + h, 30.0, -20.0), store, (64, 48)) for h in heights]


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "render.viewer"]


def test_a_descent_is_said_once_and_again_after_climbing_out(store, caplog):
    caplog.set_level(logging.WARNING, logger="render.viewer")
    watch = GroundWatch(store)
    notes = [watch.check(c) for c in _cams(store, [500, -40, -41, -60, -45])]
    said = _warnings(caplog)
    assert len(said) == 1, said  # once for the descent, not once per frame under the ground
    assert "40 m below the terrain" in said[0] and "raise it above the ground" in said[0]
    assert notes[0] == "" and all("below the terrain" in n for n in notes[1:])
    assert watch.status() == " | BELOW THE GROUND"
    up, down = (watch.check(c) for c in _cams(store, [300, -30]))  # climb out, down again
    assert up == "" and "30 m below" in down and watch.note == down
    assert len(_warnings(caplog)) == 2 and "30 m below" in _warnings(caplog)[1]


def test_flying_clear_of_the_ground_is_quiet(store, caplog):
    caplog.set_level(logging.WARNING, logger="render.viewer")
    watch = GroundWatch(store)
    for c in _cams(store, [2000, 500, 50, 20, 500]):
        assert watch.check(c) == ""
    assert _warnings(caplog) == [] and watch.status() == "" and watch.note == ""


def test_the_ground_under_a_low_camera_is_read_once(store, monkeypatch):
    """A camera under its block's top reads the block to find the ground: once, not every
    frame (the viewer checks every frame)."""
    cams = _cams(store, [-5, -6, -7, -8, 3, 2])
    reads = []
    real = type(store).read_block

    def counted(self, block, *a, **k):
        reads.append(block)
        return real(self, block, *a, **k)

    monkeypatch.setattr(type(store), "read_block", counted)
    watch = GroundWatch(store)
    for c in cams:
        watch.check(c)
    assert len(reads) == 1, reads


# --- the CLI, in a real window (Xvfb) ---------------------------------------------------------

import test_viewer as tv  # noqa: E402  (its Xvfb fixture and subprocess helpers)

display = tv.display  # an X display: the viewer tests' own Xvfb, else $DISPLAY, else skip


@pytest.fixture(scope="module")
def store_path(tmp_path_factory) -> Path:
    pytest.importorskip("glfw", reason="the viewer's window library is missing: pip install glfw")
    return tile_dem(tmp_path_factory.mktemp("viewground"), rough(65, 7), 33)


@pytest.mark.gl
def test_a_screenshot_from_under_the_ground_says_so(store_path, display, tmp_path):
    s = open_store(store_path)
    x0, y0, x1, y1 = s.grid.extent
    x, y = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    z = ground_height(s, x, y) - 50.0
    shot = tmp_path / "under.png"
    res = tv._view(store_path, display, "--size", "96x64", "--frames", "2", "--workers", "1",
                   "--camera", f"{x},{y},{z}", "--pitch", "-10",
                   "--screenshot", str(shot))  # fmt: skip
    tv._skip_without_gl_window(res)
    assert res.returncode == 0, res.stderr
    assert f"the screenshot {str(shot)!r} was taken where the camera is" in res.stderr
    assert "below the terrain under it" in res.stderr
    # the start camera is warned about once (by make_camera), not again by the viewer
    assert res.stderr.count("below the terrain under it") == 2, res.stderr  # + the screenshot
    assert "the viewer's camera at" not in res.stderr, res.stderr
    # control: the default view, high above the terrain, says nothing of the ground
    ok = tv._view(store_path, display, "--size", "96x64", "--frames", "2", "--workers", "1",
                  "--screenshot", str(tmp_path / "over.png"))  # fmt: skip
    assert ok.returncode == 0, ok.stderr
    assert "was taken where" not in ok.stderr and "below the terrain" not in ok.stderr


# A scripted flight (the viewer's `fly` replaced by a list of heights above the ground) that
# dives under the ground, stays there, climbs out and dives again: two warnings, one per dive.
_DIVE_DRIVER = """
import json, logging, sys
import render.viewer as V
from render.views import make_camera
from streamer.clip import ground_height
from tiler.store import open_store

logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
store, heights = open_store(sys.argv[1]), json.loads(sys.argv[2])
x0, y0, x1, y1 = store.grid.extent
x, y = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
ground = ground_height(store, x, y)
poses = iter(heights)
V.fly = lambda pose, *a, **k: V.Pose(x, y, ground + next(poses), 0.0, -20.0)
check = V.GroundWatch.check  # (every frame waits for its block: the test is not a race)
V.GroundWatch.check = lambda self, cam, **k: check(self, cam, **{**k, "wait": True})
res = V.run_viewer(store, make_camera(store, (64, 48)), frames=len(heights), workers=1)
print(json.dumps({"frames": res.frames, "ground": res.ground}))
"""


def _dive(store: Path, display: str, heights: list[float]):
    import json
    import subprocess
    import sys

    cmd = [sys.executable, "-c", _DIVE_DRIVER, str(store), json.dumps(heights)]
    res = subprocess.run(
        cmd, cwd=tv.ROOT, env=tv._env(display), capture_output=True, text=True, timeout=240
    )
    tv._skip_without_gl_window(res)
    assert res.returncode == 0, res.stderr
    return res.stderr, json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.gl
def test_the_viewer_warns_once_per_dive_under_the_ground(store_path, display):
    said, got = _dive(store_path, display, [400, -30, -35, -40, 300, 300, -20, -25])
    warnings = [ln for ln in said.splitlines() if ln.startswith("render.viewer:")]
    assert len(warnings) == 2, said
    assert "30 m below the terrain" in warnings[0] and "20 m below" in warnings[1]
    assert got["frames"] == 8 and "25 m below the terrain" in got["ground"]
    # control: the same flight kept above the ground says nothing
    said, got = _dive(store_path, display, [400, 30, 35, 40, 300, 300, 20, 25])
    assert "render.viewer:" not in said and got["ground"] == "", said


def test_in_the_background_the_render_thread_reads_nothing(store, monkeypatch, caplog):
    """The viewer's watch reads the block under a low camera on its worker thread (a remote
    store's read would stall the frame): the frame it is asked for the clearance there is
    unknown (quiet), and a later frame, once it arrived, warns; a read that fails stays
    unknown (the session reports it), with no warning and no error."""
    import threading

    caplog.set_level(logging.WARNING, logger="render.viewer")
    cams = _cams(store, [-30, -31, -32])
    readers = []
    real = type(store).read_block

    def slow(self, block, *a, **k):
        readers.append(threading.current_thread().name)
        gate.wait(5.0)
        return real(self, block, *a, **k)

    gate = threading.Event()
    monkeypatch.setattr(type(store), "read_block", slow)
    watch = GroundWatch(store, background=True)
    try:
        assert watch.check(cams[0]) == "" and _warnings(caplog) == []  # on its way
        gate.set()
        assert "31 m below" in watch.check(cams[1], wait=True)
        assert len(_warnings(caplog)) == 1
        assert "32 m below" in watch.check(cams[2])  # kept: not read again
    finally:
        watch.close()
    assert readers == ["terrastream-ground_0"], readers

    def failing(self, block, *a, **k):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(type(store), "read_block", failing)
    caplog.clear()
    watch = GroundWatch(store, background=True)
    try:
        assert watch.check(cams[0], wait=True) == "" and watch.check(cams[1]) == ""
    finally:
        watch.close()
    assert _warnings(caplog) == []


def test_a_hung_ground_read_does_not_hold_the_process_at_exit(store):
    """The ground reads ran on a ThreadPoolExecutor, whose threads Python joins at exit: a read
    the server never answers held ``view``'s exit after its window closed (8.7 s for an 8 s
    read). Daemon threads (``streamer.pool.DaemonPool``) let it end. The control: the worker
    is the named ``terrastream-ground`` thread and a read that returns is still used."""
    import subprocess
    import sys
    import time

    script = (
        "import time, render.ground_watch as gw\n"
        "from tiler.store import open_store\n"
        f"w = gw.GroundWatch(open_store({str(store.url)!r}), background=True)\n"
        "w.pool.submit(time.sleep, 20)\n"
        "time.sleep(0.2)\n"
        "w.close()\n"
    )
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-c", script], check=True, timeout=60)
    assert time.monotonic() - t0 < 12, "the process waited for the hung read"
    watch = GroundWatch(store, background=True)
    try:
        assert watch.pool.submit(lambda: 1).result(timeout=10) == 1
        assert any(t.name.startswith("terrastream-ground") for t in watch.pool.threads)
        cam = _cams(store, [-30.0])[0]
        assert "below" in watch.check(cam, wait=True)  # (read on the worker, then used)
    finally:
        watch.close()
