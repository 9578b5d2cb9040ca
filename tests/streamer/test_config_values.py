"""Session settings and stores a session refuses at once, naming the value: ``budget_mb=inf``
raised an OverflowError, ``latency_ms``/``wait_timeout_s=inf`` an OverflowError from
``update()``, ``workers=2.5`` started two loaders and failed in a finaliser, ``patch_log2=2.5``
a TypeError, ``extension_L=-5`` failed as "prefetch planning failed" at the first frame; and a
store opened with ``allow_incomplete`` streamed frames that saw nothing and reported no hole.
Controls: numpy numbers and a finished store."""

from __future__ import annotations

import numpy as np
import pytest
from demtools import fractal, write_dem

from streamer.errors import StreamerError
from streamer.frames import SessionConfig
from streamer.session import Session
from tiler.errors import StoreIncompleteError
from tiler.store import open_store
from tiler.tile import TileOptions, tile

INF, NAN = float("inf"), float("nan")


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("budget_mb", INF), ("budget_mb", "64"), ("latency_ms", INF), ("wait_timeout_s", INF),
        ("workers", 2.5), ("workers", "2"), ("workers", True), ("patch_log2", 2.5),
        ("patch_log2", 50), ("extension_L", -5.0), ("extension_L", NAN), ("retries", 1.5),
        ("horizon_s", INF), ("linger_s", INF), ("tau", INF),
    ],
)  # fmt: skip
def test_a_setting_that_cannot_work_is_refused_naming_it(field, value):
    with pytest.raises(StreamerError, match=f"invalid {field}: "):
        SessionConfig(**{field: value})


def test_numpy_numbers_are_settings_too():
    c = SessionConfig(workers=np.int64(2), budget_mb=np.float32(3.0), extension_L=np.float64(5))
    assert c.workers == 2 and c.extension_L == 5.0


def test_a_session_refuses_an_unfinished_store(tmp_path):
    src = write_dem(tmp_path / "d.tif", fractal((200, 200), 3))
    calls = []

    def stop(progress) -> None:
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        tile(
            src, tmp_path / "s.zarr", TileOptions(65, workers=1, executor="threads"), progress=stop
        )
    unfinished = open_store(tmp_path / "s.zarr", allow_incomplete=True)
    with pytest.raises(StoreIncompleteError, match="not finished: a session streams finished"):
        Session(unfinished)
    tile(src, tmp_path / "s.zarr", TileOptions(65, workers=1, executor="threads"))
    Session(open_store(tmp_path / "s.zarr")).close()  # the control: finished, it streams


def _store(tmp_path):
    return tile(
        write_dem(tmp_path / "d.tif", fractal((257, 257), 3)), tmp_path / "s.zarr", TileOptions(65)
    )


def test_a_path_fitted_to_the_dem_says_when_it_flies_slower_than_asked(tmp_path, caplog):
    """`--path-kind circle --speed 100` flew at 6,029 units/s (one loop, its radius at least a
    quarter block edge) and `line` was capped at the DEM's diagonal, silently; they say the
    speed they fly at now. Controls: a speed they can fly says nothing, and a line flies it
    exactly (frames - 1 steps)."""
    from streamer.run import make_path

    s = _store(tmp_path)
    with caplog.at_level("WARNING", logger="streamer.run"):
        make_path(s, "circle", frames=60, fps=30, speed=1.0)
    assert "the circle path flies at" in caplog.text and "not the --speed 1 asked" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="streamer.run"):
        make_path(s, "line", frames=60, fps=30, speed=1e6)
    assert "capped at the DEM's diagonal" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="streamer.run"):
        cams = make_path(s, "line", frames=31, fps=30, speed=50.0)
    assert caplog.text == ""
    step = np.linalg.norm(np.subtract(cams[1].position, cams[0].position))
    assert step * 30 == pytest.approx(50.0)


def test_a_keyframe_file_says_the_kind_and_speed_given_are_not_used(tmp_path, caplog):
    from streamer.run import make_path

    s = _store(tmp_path)
    x0, y0, x1, y1 = s.grid.extent
    f = tmp_path / "k.csv"
    f.write_text(f"t,x,y,z,yaw,pitch\n0,{x0},{y0},3000,45,-30\n1,{x1},{y1},3000,45,-30\n")
    with caplog.at_level("WARNING", logger="streamer.run"):
        make_path(s, "circle", frames=3, speed=5.0, path_file=f)
    assert "sets the path and its speed: the path kind 'circle' and speed 5" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="streamer.run"):
        make_path(s, frames=3, path_file=f)  # the control: nothing else given
    assert caplog.text == ""


def test_update_and_warm_up_name_a_bad_camera_or_timeout(tmp_path):
    """``update(None)`` raised an AttributeError about ``pitch`` from inside the planner;
    ``warm_up(cam, timeout_s=0)`` waited the default 30 s instead, and a negative timeout
    passed. Control: a camera and a timeout work."""
    from streamer.errors import CameraError
    from streamer.run import make_path

    s = _store(tmp_path)
    cam = make_path(s, frames=1)[0]
    with Session(s) as session:
        with pytest.raises(CameraError, match="needs a streamer.camera.Camera, got None"):
            session.update(None)
        for bad in (0, -1.0, float("nan"), "5"):
            with pytest.raises(StreamerError, match="timeout_s must be a finite number"):
                session.warm_up(cam, timeout_s=bad)
        assert session.warm_up(cam, timeout_s=30)["bytes"] > 0
        assert session.update(cam).stats.visible_blocks > 0
