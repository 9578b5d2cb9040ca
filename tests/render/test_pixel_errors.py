"""Screen error of a sample whose drawn point the depth range clips (no GL): counted, as the
viewport's diagonal, never projected through the eye nor dropped. Seen by an audit on a
−11 km..+9 km DEM: a drawn point 1.6 m in front of the eye (inside the 100 m near plane) read as a
45,483 px popping jump at 256x192, and drawn points behind the eye counted as nothing."""

from __future__ import annotations

import numpy as np

from render.measure import clipped_px, pixel_errors
from streamer.camera import Camera

SIZE = (256, 192)


def _camera() -> Camera:
    """At the origin, 100 m up, looking north (+y) and slightly down; near plane 10 m."""
    return Camera.look_at((0.0, 0.0, 100.0), (0.0, 1000.0, 90.0), viewport=SIZE, near=10.0)


def test_drawn_points_on_screen_keep_their_distance():
    cam = _camera()
    x, y = np.zeros(3), np.array([500.0, 800.0, 1000.0])
    ht = np.array([95.0, 92.0, 90.0])
    err = pixel_errors(cam, x, y, ht, ht + 1.0)
    assert err.shape == (3,) and np.all((err > 0) & (err < clipped_px(cam)))


def test_a_drawn_point_nearer_than_the_near_plane_or_behind_the_eye_counts_the_diagonal():
    cam = _camera()
    x, y, ht = np.zeros(3), np.full(3, 500.0), np.full(3, 95.0)
    # the drawn surface raised so the drawn point lies 5 m in front of the eye (depth < near),
    # level with it, and 50 m behind it
    c = cam.to_camera(np.array([[0.0, 500.0, 95.0]]))[0]
    fwd = cam.to_camera(np.array([[0.0, 500.0, 96.0]]))[0] - c  # depth per metre of height
    lift = (np.array([5.0, 0.0, -50.0]) - c[2]) / fwd[2]
    err, idx = pixel_errors(cam, x, y, ht, ht + lift, with_index=True)
    assert len(idx) == 3  # none dropped (the ones behind the eye were)
    np.testing.assert_allclose(err, clipped_px(cam))
    assert clipped_px(cam) == np.hypot(*SIZE)
    # lifted 1 m only, the same drawn points stay beyond the near plane and measure as usual
    small = pixel_errors(cam, x, y, ht, ht + 1.0)
    assert np.all(small < clipped_px(cam))
