"""Qiu's triangle for a camera looking above the horizon: it reaches the ground only where the
frustum does (a camera looking at the sky sees no block)."""

from __future__ import annotations

import numpy as np
import pytest

from streamer.camera import Camera
from streamer.frustum import frustum_hull, qiu_reach, view_triangle, visible_sets
from tiler.grid import BlockGrid

GRID = BlockGrid(height=1025, width=1025, k=7, x0=0.0, y0=1024.0 * 30, dx=30.0, dy=30.0)
ZRANGE = (294.0, 2575.0)  # the heights of the terrain under the camera
MID = (512 * 30.0, 512 * 30.0)


def cam(z: float, pitch: float, **kw) -> Camera:
    """A camera above the middle of GRID, looking north."""
    return Camera((*MID, z), pitch=pitch, fov_y=60, viewport=(256, 192), far=70_000, **kw)


@pytest.mark.parametrize("pitch", [90.0, 60.0, 31.0])
def test_a_camera_looking_at_the_sky_sees_no_block(pitch):
    """Pitched up with its whole frustum above the horizon, 8 km up: no ground, no block."""
    c = cam(8000.0, pitch)
    m, _ = visible_sets(c, GRID, zrange=ZRANGE)
    assert len(m) == 0
    assert len(frustum_hull(c, ZRANGE)) == 0  # the hull agrees
    assert len(view_triangle(c, zrange=ZRANGE)) == 0

    from streamer.frustum import ground_reach

    assert ground_reach(c, ZRANGE) == 0.0


def brute_reach(c: Camera, zrange: tuple[float, float], n: int = 41) -> float:
    """The farthest point ahead of a dense sample of the frustum volume inside the slab."""
    s = np.linspace(-1.0, 1.0, n)
    d = np.geomspace(c.near, c.far, 50 * n)
    sx, sy, dd = np.meshgrid(s * c.tan_half_x, s * c.tan_half_y, d, indexing="ij")
    r, u, f = c.right, c.up, c.forward
    dirs = f + sx[..., None] * r + sy[..., None] * u
    pts = dd[..., None] * dirs
    z = pts[..., 2] + c.position[2]
    inside = (z >= zrange[0]) & (z <= zrange[1])
    ahead = pts[..., 0] * c.heading[0] + pts[..., 1] * c.heading[1]
    return float(ahead[inside].max()) if inside.any() else 0.0


@pytest.mark.parametrize(("z", "pitch"), [(8000.0, 20.0), (8000.0, 5.0), (1500.0, 60.0)])
def test_a_camera_looking_up_reaches_the_ground_where_its_frustum_does(z, pitch):
    """Positive control: a camera pitched up whose lower rays meet the terrain (or that is
    inside the terrain's heights) keeps a triangle, as long as the frustum's part in the slab."""
    from streamer.frustum import ground_reach

    c = cam(z, pitch)
    reach = ground_reach(c, ZRANGE)
    brute = brute_reach(c, ZRANGE)
    assert reach > 0.0
    assert brute <= reach * (1 + 1e-9)
    assert reach <= brute * 1.02  # the sample comes within 2 % of it
    tri = view_triangle(c, zrange=ZRANGE)
    assert len(tri) == 3
    np.testing.assert_allclose(
        np.hypot(*(tri[1:] - tri[0]).T), reach / np.cos(np.arctan(c.tan_half_x))
    )
    assert len(visible_sets(c, GRID, zrange=ZRANGE)[0]) > 0


@pytest.mark.parametrize("pitch", [0.0, -10.0, -45.0, -89.0])
def test_a_camera_looking_down_keeps_qius_triangle(pitch):
    """Positive control: at or below the horizon the triangle is Qiu's as published, heights
    given or not (blocks in view, the same with or without the terrain's heights)."""
    c = cam(8000.0, pitch)
    with_heights, _ = visible_sets(c, GRID, zrange=ZRANGE)
    assert len(with_heights) > 0
    np.testing.assert_array_equal(with_heights, visible_sets(c, GRID)[0])


def test_the_reach_with_heights_is_qius_below_the_horizon():
    """The triangle's legs given the heights are Qiu's at or below the horizon."""
    for pitch in (0.0, -30.0, -89.0):
        c = cam(8000.0, pitch)
        np.testing.assert_array_equal(view_triangle(c, zrange=ZRANGE), view_triangle(c))
        assert qiu_reach(c, ZRANGE) == qiu_reach(c)
