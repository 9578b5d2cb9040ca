"""Clipping planes of cameras over a store (streamer.clip) and keyframe paths that use them:
a keyframe camera sees the whole DEM whatever its height, and a path that sees none of it is an
error, not a fly-through of empty frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
from demtools import fractal, write_dem

from streamer.camera import Camera
from streamer.clip import MIN_NEAR, fit_clip, reach, zrange
from streamer.errors import PathOutOfViewError
from streamer.run import make_path, require_view, run_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    d = tmp_path_factory.mktemp("clip")
    src = write_dem(d / "d.tif", fractal((129, 129), 4), cell=30.0)
    return tile(src, d / "s.zarr", TileOptions(block_size=33, executor="threads"))


def corners(store) -> np.ndarray:
    x0, y0, x1, y1 = store.grid.extent
    zlo, zhi = zrange(store)
    return np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (zlo, zhi)])


def centre(store) -> tuple[float, float]:
    x0, y0, x1, y1 = store.grid.extent
    return 0.5 * (x0 + x1), 0.5 * (y0 + y1)


@pytest.mark.parametrize("height", [2.0, 3000.0, 150_000.0, 9_000_000.0])
def test_the_far_plane_reaches_every_corner_and_the_near_plane_clips_no_terrain(store, height):
    cx, cy = centre(store)
    _, zhi = zrange(store)
    cam = fit_clip(store, Camera((cx, cy, zhi + height), yaw=270.0, pitch=-20.0))
    dist = np.linalg.norm(corners(store) - np.array(cam.position), axis=1)
    assert cam.far >= dist.max() and cam.far >= reach(store, tuple(cam.position))
    # the near rectangle's corners stay above the highest block top
    assert cam.position[2] - cam.near * (1 + cam.tan_half_diagonal) > zhi
    assert cam.near >= MIN_NEAR


def test_a_camera_under_the_terrain_gets_the_smallest_near_plane(store):
    cx, cy = centre(store)
    zlo, _ = zrange(store)
    cam = fit_clip(store, Camera((cx, cy, zlo - 50.0), pitch=10.0))
    assert cam.near == MIN_NEAR and math.isfinite(cam.far)


def keyframe_file(tmp_path, rows) -> str:
    p = tmp_path / "k.csv"
    p.write_text("t,x,y,z,yaw,pitch\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return str(p)


def fly(store, cams) -> list[int]:
    """Blocks in view per frame, culled by the frustum hull (what the renderer draws)."""
    with open_session(store, budget_mb=16, workers=1, culling="hull") as s:
        result = run_flythrough(s, cams, realtime=False)
    return [r["visible_blocks"] for r in result.rows]


def test_a_keyframe_camera_150_km_up_sees_the_dem(store, tmp_path):
    cx, cy = centre(store)
    path = keyframe_file(tmp_path, [(0, cx, cy, 150_000, 0, -90), (1, cx, cy, 150_000, 0, -89)])
    cams = make_path(store, path_file=path, frames=2, viewport=(160, 120))
    assert all(c.far > 150_000 for c in cams)
    assert all(n > 0 for n in fly(store, cams))
    # positive control: the fixed 100 km far plane of keyframe cameras saw nothing from there
    fixed = make_path(store, path_file=path, frames=2, viewport=(160, 120), far=100_000.0)
    assert fly(store, fixed) == [0, 0]


def test_a_path_that_sees_none_of_the_dem_is_an_error(store, tmp_path):
    x0, y0, x1, y1 = store.grid.extent
    away = (x1 + 1e6, y1 + 1e6, 3000, 45, -10)  # beyond the north-east corner, looking away
    path = keyframe_file(tmp_path, [(0, *away), (1, *away)])
    cams = make_path(store, path_file=path, frames=3, viewport=(160, 120))
    with open_session(store, budget_mb=16, workers=1) as s:
        result = run_flythrough(s, cams, realtime=False)
    with pytest.raises(PathOutOfViewError, match=r"none of the 3 frame\(s\) .* sees the DEM"):
        require_view(result, store)
    # positive control: a path over the terrain passes
    cx, cy = centre(store)
    path = keyframe_file(tmp_path, [(0, cx, cy, 3000, 0, -45), (1, cx, cy + 100, 3000, 0, -45)])
    cams = make_path(store, path_file=path, frames=3, viewport=(160, 120))
    with open_session(store, budget_mb=16, workers=1) as s:
        require_view(run_flythrough(s, cams, realtime=False), store)


def test_ground_height_is_the_triangulated_surface_under_a_point(tmp_path):
    """Known heights: each sample is ``100 * row + col`` (a plane: both diagonals of a cell
    interpolate it); points inside a cell, on a block's shared border and at the DEM's last
    sample; ``None`` off the DEM and beside nodata. (It was the cell's lowest corner, which let
    a camera tens of metres under the surface pass as above it:
    tests/streamer/test_numeric_audit_streamer.py.)"""
    from streamer.clip import ground_height

    data = (100.0 * np.arange(65)[:, None] + np.arange(65)[None, :]).astype(np.float32)
    data[40:42, 50:52] = np.nan
    src = write_dem(tmp_path / "g.tif", data, cell=10.0, nodata=float("nan"))
    st = tile(src, tmp_path / "g.zarr", TileOptions(block_size=33, executor="threads"))
    g = st.grid

    def at(row: float, col: float) -> float | None:
        x, y = g.sample_xy(row, col)
        return ground_height(st, float(x), float(y))

    assert at(10.5, 20.5) == 100.0 * 10.5 + 20.5  # inside the cell: the surface there
    assert at(32.0, 32.0) == 100.0 * 32 + 32  # a shared block border
    assert at(64.0, 64.0) == 100.0 * 64 + 64  # the last sample: the last cell's corner
    assert at(40.5, 49.5) is None  # a corner is nodata
    assert at(-1.0, 5.0) is None and at(5.0, 64.5) is None  # off the DEM


def test_a_camera_below_the_terrain_is_warned_about(store, caplog):
    """``make_camera`` with an explicit position under the ground logs a warning naming the
    depth; the control, the same point 1 m above the ground, is quiet."""
    from render.views import make_camera
    from streamer.clip import ground_height

    cx, cy = centre(store)
    ground = ground_height(store, cx, cy)
    assert ground is not None
    with caplog.at_level("WARNING", logger="render.views"):
        make_camera(store, (64, 48), position=f"{cx},{cy},{ground - 50}", pitch=-10.0)
    assert "50.0 m below the terrain under it" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="render.views"):
        make_camera(store, (64, 48), position=f"{cx},{cy},{ground + 1}", pitch=-10.0)
    assert "below the terrain" not in caplog.text


def test_depth_below_ground_per_eye_reads_only_blocks_it_may_be_under(store, monkeypatch):
    """Eyes above every block top read nothing; eyes under the ground get their depth, each
    block read once; the control eyes 1 m above the ground get 0."""
    from streamer.clip import depth_below_ground, ground_height

    cx, cy = centre(store)
    reads: list[tuple[int, int]] = []
    real = type(store).read_block

    def counting(self, block, *a, **kw):
        reads.append(tuple(block))
        return real(self, block, *a, **kw)

    monkeypatch.setattr(type(store), "read_block", counting)
    top = zrange(store)[1]
    assert not depth_below_ground(store, [(cx, cy, top + 1), (cx + 10, cy, top + 5)]).any()
    assert reads == []  # above every block's top: nothing read
    g = [ground_height(store, cx + d, cy) for d in (0.0, 10.0, 20.0)]
    reads.clear()
    under = [(cx + d, cy, h - 25.0) for d, h in zip((0.0, 10.0, 20.0), g, strict=True)]
    np.testing.assert_allclose(depth_below_ground(store, under), 25.0)
    assert len(reads) == len(set(reads))  # each block once
    over = [(cx + d, cy, h + 1.0) for d, h in zip((0.0, 10.0, 20.0), g, strict=True)]
    assert not depth_below_ground(store, over).any()


def test_a_flythrough_path_below_the_ground_is_warned_about(store, caplog):
    """``render.flythrough`` warns when frames' cameras are under the terrain, naming the
    first and the depth; the control, the same path 1 m above the ground, is quiet."""
    from render.flythrough import warn_frames_below_ground
    from streamer.clip import ground_height

    cx, cy = centre(store)
    ground = ground_height(store, cx, cy)
    cams = [Camera((cx, cy, z), yaw=0.0, pitch=-10.0) for z in (ground + 500, ground - 30)]
    with caplog.at_level("WARNING", logger="render.flythrough"):
        depth = warn_frames_below_ground(store, cams)
    assert depth[0] == 0 and depth[1] == pytest.approx(30.0)
    assert "1 of the path's 2 frames have the camera below the terrain" in caplog.text
    assert "frame 1, 30.0 m below" in caplog.text
    caplog.clear()
    cams = [Camera((cx, cy, ground + 1), yaw=0.0, pitch=-10.0)] * 2
    with caplog.at_level("WARNING", logger="render.flythrough"):
        assert not warn_frames_below_ground(store, cams).any()
    assert "below the terrain" not in caplog.text


def test_depth_below_ground_is_unknown_where_a_block_cannot_be_read(store, monkeypatch):
    """A failing read (a server down) leaves the depth unknown (0) instead of failing the
    flight before its session starts; the control reads and finds the eye below."""
    from streamer.clip import depth_below_ground, ground_height
    from tiler.errors import StoreUnavailableError

    cx, cy = centre(store)
    eye = [(cx, cy, ground_height(store, cx, cy) - 10.0)]
    assert depth_below_ground(store, eye)[0] == pytest.approx(10.0)

    def down(self, block, *a, **kw):
        raise StoreUnavailableError("the server stopped answering")

    monkeypatch.setattr(type(store), "read_block", down)
    assert depth_below_ground(store, eye)[0] == 0.0
