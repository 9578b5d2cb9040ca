"""Numerical extremes (the numerics audit), the streamer's part: the ground under a camera is
the triangulated surface (not the cell's lowest corner), a camera closer to the ground than its
near plane reaches is told, a subnormal FOV and a huge yaw, a mixed node straight below the
eye, and a tau that is not finite."""

from __future__ import annotations

import logging
import math
import warnings

import numpy as np
import pytest
from demtools import write_dem

from streamer.camera import MIN_FOV_Y, Camera
from streamer.clip import (
    cell_surface,
    clipped_by_near,
    depth_below_ground,
    ground_clearance,
    ground_height,
    near_reach,
    warn_path_below_ground,
)
from streamer.errors import CameraError, LodError
from streamer.lod import check_finite_tau, gap_scale, qiu_eq7
from tiler.tile import TileOptions, tile

#: the audit's cell (rows 47-48, cols 50-51 of its store): NW 1697, NE 1775, SW 1789, SE 1907
CELL = np.array([[1697.0, 1775.0], [1789.0, 1907.0]])


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 65² DEM at 1800 m (10 m cells) holding :data:`CELL` at rows 20-21, cols 30-31, and a
    flat corner at 0 m (rows and cols 50..64)."""
    d = tmp_path_factory.mktemp("audit")
    data = np.full((65, 65), 1800.0, np.float32)
    data[20:22, 30:32] = CELL
    data[50:, 50:] = 0.0
    src = write_dem(d / "d.tif", data, cell=10.0)
    return tile(src, d / "s.zarr", TileOptions(block_size=33, executor="threads"))


def _xy(store, row: float, col: float) -> tuple[float, float]:
    x, y = store.grid.sample_xy(row, col)
    return float(x), float(y)


# -- 1. the ground under the camera ------------------------------------------------------------


def test_cell_surface_is_each_diagonals_interpolant():
    assert cell_surface(CELL, 0.5, 0.5) == (1802.0, 1782.0)  # (NW + SE) / 2, (NE + SW) / 2
    for u, v, h in ((0, 0, 1697.0), (1, 0, 1775.0), (0, 1, 1789.0), (1, 1, 1907.0)):
        assert cell_surface(CELL, u, v) == (h, h)  # the corners: both cuts agree
    plane = np.array([[0.0, 1.0], [100.0, 101.0]])  # 100 * row + col: both cuts are the plane
    assert cell_surface(plane, 0.25, 0.75) == (75.25, 75.25)


def test_a_camera_under_the_surface_but_above_the_lowest_corner_is_below(store):
    """The audit's case: 42 m under the surface at the cell's centre (1782 m by the NE-SW cut,
    1802 by the NW-SE one), 43 m above its lowest corner (1697): the lowest corner called it
    above the ground; the triangulated surface (the lower cut, a bound) finds it 42 m below.
    The control, 1 m above the higher cut, is not below."""
    x, y = _xy(store, 20.5, 30.5)
    assert ground_height(store, x, y) == pytest.approx(1782.0)
    assert depth_below_ground(store, [(x, y, 1740.0)])[0] == pytest.approx(42.0)
    assert depth_below_ground(store, [(x, y, 1803.0)])[0] == 0.0
    assert ground_clearance(store, [(x, y, 1803.0)])[0] == pytest.approx(21.0)


def test_ground_clearance_reads_nothing_high_above_and_knows_nothing_off_the_dem(store):
    x, y = _xy(store, 40.0, 10.0)  # block (1, 0): its top is 1800 m
    c = ground_clearance(store, [(x, y, 1900.0), (x, y, 1800.5), (-1e3, -1e3, 0.0)], within=1.0)
    assert c[0] == math.inf and c[1] == pytest.approx(0.5) and math.isnan(c[2])


def test_a_camera_closer_than_its_near_plane_reaches_is_warned_about(store, caplog):
    """A camera 1 mm above a flat ground with a 1 cm near plane: its near plane clips the
    ground in front of it (the audit's picture: ground only at the horizon). Warned, naming
    the clearance; the control 5 cm above is quiet (as the old code was for both)."""
    x, y = _xy(store, 57.0, 57.0)
    cams = [Camera((x, y, z), pitch=-10.0, fov_y=45.0, viewport=(128, 96), near=0.01)
            for z in (0.05, 0.001, 0.0)]  # fmt: skip
    assert near_reach(cams[0]) == pytest.approx(0.01 * math.hypot(1, cams[0].tan_half_diagonal))
    c = ground_clearance(store, [cam.position for cam in cams], within=1.0)
    assert clipped_by_near(c, cams).tolist() == [False, True, True]
    log = logging.getLogger("audit")
    with caplog.at_level("WARNING", logger="audit"):
        depth = warn_path_below_ground(store, cams, "effect", log)
    assert not depth.any()
    assert "2 of the path's 3 frames have the camera on or just above the terrain" in caplog.text
    assert "frame 1, 0.001 m above the ground" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="audit"):
        warn_path_below_ground(store, cams[:1], "effect", log)
    assert caplog.text == ""


def test_a_camera_on_or_near_the_ground_is_warned_about_by_make_camera(store, caplog):
    from render.views import ground_note, make_camera

    x, y = _xy(store, 57.0, 57.0)
    for z, said in ((0.0, "is on the terrain"), (0.001, "only 0.001 m above the terrain")):
        caplog.clear()
        with caplog.at_level("WARNING", logger="render.views"):
            cam = make_camera(store, (128, 96), position=f"{x},{y},{z}", pitch=-10.0)
        assert said in caplog.text and "near plane clips the ground" in caplog.text
        assert "near plane clips the ground" in ground_note(store, cam)
    caplog.clear()
    with caplog.at_level("WARNING", logger="render.views"):
        cam = make_camera(store, (128, 96), position=f"{x},{y},0.05", pitch=-10.0)
    assert caplog.text == "" and ground_note(store, cam) == ""
    x, y = _xy(store, 20.5, 30.5)
    with caplog.at_level("WARNING", logger="render.views"):
        cam = make_camera(store, (128, 96), position=f"{x},{y},1740", pitch=-20.0)
    assert "42.0 m below the terrain under it" in caplog.text
    assert "42 m below the terrain" in ground_note(store, cam)


# -- 5. camera and metric extremes -------------------------------------------------------------


@pytest.mark.parametrize("fov", [1e-300, 1e-320, 5e-324, 1e-4])
def test_a_subnormal_or_tiny_fov_is_refused_by_name(fov):
    with pytest.raises(CameraError, match=r"fov_y must be in \[0.001, 180\) degrees, got"):
        Camera((0.0, 0.0, 100.0), fov_y=fov, viewport=(128, 96))


def test_the_narrowest_fov_projects_finitely():
    cam = Camera((0.0, 0.0, 100.0), pitch=-10.0, fov_y=MIN_FOV_Y, viewport=(128, 96))
    assert math.isfinite(cam.focal_px)
    px, py, _ = cam.project(np.array([[0.0, 1000.0, 100.0 - 1000.0 * math.tan(0.1745329)]]))
    assert np.isfinite(px).all() and np.isfinite(py).all()


def test_a_huge_yaw_is_reduced_in_degrees():
    """1e20° is 280° exactly (fmod); converted to radians first it was another heading."""
    a = Camera((0.0, 0.0, 5000.0), yaw=1e20, pitch=-60.0, roll=1e20 + 2**40)
    b = Camera((0.0, 0.0, 5000.0), yaw=math.fmod(1e20, 360.0), pitch=-60.0,
               roll=math.fmod(1e20 + 2**40, 360.0))  # fmt: skip
    assert math.fmod(1e20, 360.0) == 280.0
    assert (
        np.stack([a.right, a.up, a.forward]).tobytes()
        == np.stack([b.right, b.up, b.forward]).tobytes()
    )
    assert a.heading.tobytes() == b.heading.tobytes()
    # the control: within +-360 the angle is used as it is (the same bits as before)
    c = Camera((0.0, 0.0, 5000.0), yaw=-10.0, pitch=-60.0)
    y = math.radians(-10.0)
    assert c.heading.tolist() == [math.sin(y), math.cos(y)]


def test_a_mixed_node_straight_below_the_eye_warns_nothing():
    """δ = inf straight below the eye: cos θ = 0, ``inf * 0`` leaked a RuntimeWarning; the
    result is unchanged (NaN, as the compiled twin's: not <= tau, the node splits)."""
    cam = Camera((0.0, 0.0, 100.0), pitch=-90.0, fov_y=45.0, viewport=(128, 96))
    delta = np.array([np.inf, 2.0, np.inf])
    centres = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 500.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rho = qiu_eq7(delta, centres, np.ones(3), cam)
    assert math.isnan(rho[0]) and rho[1] == 0.0 and rho[2] == math.inf


# -- 4. tau must be finite ---------------------------------------------------------------------


@pytest.mark.parametrize("bad", [math.inf, -math.inf, math.nan, -1.0, "x", None])
def test_a_tau_that_is_not_finite_is_refused_by_name(bad):
    with pytest.raises(LodError, match="tau must be a finite"):
        check_finite_tau(bad)
    with pytest.raises(LodError, match="tau"):
        gap_scale(bad)


def test_gap_scale_of_finite_taus():
    assert (gap_scale(0.0), gap_scale(0.5), gap_scale(1.0), gap_scale(4.0)) == (0, 1, 1, 4)
    assert gap_scale(1e300) == 1e300 and check_finite_tau(2) == 2.0


def test_the_streamer_level_walk_refuses_tau_inf(store):
    """``PatchErrorTable.needed_levels`` at tau = inf would leave mixed nodes (error inf)
    unsplit and make the gap rule's ``0 * inf`` NaN; it is refused as the selection refuses
    it. The control, a huge finite tau, plans."""
    from streamer.session import open_session

    x, y = _xy(store, 32.0, 32.0)
    cam = Camera((x, y, 3000.0), pitch=-60.0, viewport=(64, 48), near=1.0)
    with open_session(store, budget_mb=16, workers=1) as s:
        s.update(cam, wait=True)  # the blocks' errors are known once loaded
        assert s.planner.needed(cam, tau=1e300)
        with pytest.raises(LodError, match="tau must be a finite pixel threshold >= 0, got inf"):
            s.planner.needed(cam, tau=math.inf)
