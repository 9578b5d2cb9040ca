"""Camera: orientation conventions, matrices, exact projection, validation."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from streamer.camera import Camera
from streamer.errors import CameraError, StreamerError

S = math.sqrt(0.5)


@pytest.mark.parametrize(
    ("yaw", "pitch", "roll", "forward", "right", "up"),
    [
        (0, 0, 0, (0, 1, 0), (1, 0, 0), (0, 0, 1)),
        (90, 0, 0, (1, 0, 0), (0, -1, 0), (0, 0, 1)),
        (180, 0, 0, (0, -1, 0), (-1, 0, 0), (0, 0, 1)),
        (270, 0, 0, (-1, 0, 0), (0, 1, 0), (0, 0, 1)),
        (0, -90, 0, (0, 0, -1), (1, 0, 0), (0, 1, 0)),
        (90, -90, 0, (0, 0, -1), (0, -1, 0), (1, 0, 0)),
        (0, 90, 0, (0, 0, 1), (1, 0, 0), (0, -1, 0)),
        (0, -45, 0, (0, S, -S), (1, 0, 0), (0, S, S)),
        (0, 0, 90, (0, 1, 0), (0, 0, -1), (1, 0, 0)),
        (0, 0, -90, (0, 1, 0), (0, 0, 1), (-1, 0, 0)),
    ],
    ids=[
        "north",
        "east",
        "south",
        "west",
        "down-north-up",
        "down-yaw90",
        "straight-up",
        "pitch-45",
        "roll+90-banks-right",
        "roll-90",
    ],
)
def test_orientation_vectors(yaw, pitch, roll, forward, right, up):
    cam = Camera((0, 0, 0), yaw=yaw, pitch=pitch, roll=roll)
    np.testing.assert_allclose(cam.forward, forward, atol=1e-12)
    np.testing.assert_allclose(cam.right, right, atol=1e-12)
    np.testing.assert_allclose(cam.up, up, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    yaw=st.floats(-720, 720),
    pitch=st.floats(-90, 90),
    roll=st.floats(-180, 180),
)
def test_basis_orthonormal_right_handed(yaw, pitch, roll):
    cam = Camera((1, 2, 3), yaw=yaw, pitch=pitch, roll=roll)
    b = np.stack([cam.right, cam.up, cam.forward])
    np.testing.assert_allclose(b @ b.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.cross(cam.right, cam.up), -cam.forward, atol=1e-12)


def _numpy_basis(cam: Camera) -> np.ndarray:
    """The basis as numpy computed it before it became float arithmetic (the reference); yaw
    and roll reduced in degrees first (``math.fmod``: a huge yaw keeps its heading)."""
    yaw, roll = math.fmod(cam.yaw, 360.0), math.fmod(cam.roll, 360.0)
    y, p, r = (math.radians(a) for a in (yaw, cam.pitch, roll))
    f = np.array([math.sin(y) * math.cos(p), math.cos(y) * math.cos(p), math.sin(p)])
    r0 = np.array([math.cos(y), -math.sin(y), 0.0])
    u0 = np.cross(r0, f)
    right = math.cos(r) * r0 - math.sin(r) * u0
    up = math.cos(r) * u0 + math.sin(r) * r0
    return np.stack([right, up, f])


@settings(max_examples=200, deadline=None)
@given(yaw=st.floats(-720, 720), pitch=st.floats(-90, 90), roll=st.floats(-180, 180))
def test_basis_is_the_numpy_reference_bit_for_bit(yaw, pitch, roll):
    cam = Camera((1, 2, 3), yaw=yaw, pitch=pitch, roll=roll)
    ref = _numpy_basis(cam)
    got = np.stack([cam.right, cam.up, cam.forward])
    assert got.tobytes() == ref.tobytes()
    assert not cam.forward.flags.writeable


@pytest.mark.parametrize(
    ("points", "expected"),
    [
        ([0, 10, 0], (400.0, 300.0, 10.0)),
        ([5, 10, 2.5], (550.0, 225.0, 10.0)),
        ([-10, 10, -7.5], (100.0, 525.0, 10.0)),
        ([0, 20, 20], (400.0, 0.0, 20.0)),
    ],
    ids=["centre", "right-up", "left-down", "top-edge"],
)
def test_project_known_pixels(points, expected):
    # fov_y = 90 and height 600 -> focal 300 px; camera at the origin looking north.
    cam = Camera((0, 0, 0), fov_y=90, viewport=(800, 600))
    assert cam.focal_px == pytest.approx(300.0)
    px, py, depth = cam.project(np.array([points], dtype=float))
    np.testing.assert_allclose([px[0], py[0], depth[0]], expected, atol=1e-9)


def test_project_behind_is_nan():
    cam = Camera((0, 0, 0))
    px, py, depth = cam.project(np.array([[0.0, -5.0, 0.0], [0.0, 0.0, 1.0]]))
    assert np.isnan(px).all()
    assert np.isnan(py).all()
    np.testing.assert_allclose(depth, [-5.0, 0.0])


def test_project_far_from_origin_keeps_precision():
    """A camera and points near 1e7 m project like the same scene at the origin."""
    offsets = np.array([[1.25, 80.0, -3.0], [-40.0, 500.0, 12.5], [0.001, 2.0, -0.002]])
    base = np.array([1e7, -1e7, 250.0])
    a = Camera(tuple(base), yaw=12.0, pitch=-20.0, roll=3.0)
    b = replace(a, position=(0.0, 0.0, 250.0))
    pa = np.array(a.project(base + offsets))
    pb = np.array(b.project(np.array([0.0, 0.0, 250.0]) + offsets))
    np.testing.assert_allclose(pa, pb, atol=1e-4)


@settings(max_examples=50, deadline=None)
@given(
    yaw=st.floats(0, 360),
    pitch=st.floats(-89, 89),
    roll=st.floats(-90, 90),
    fov=st.floats(5, 150),
    rel=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(2, 500)),
)
def test_project_matches_opengl_matrices(yaw, pitch, roll, fov, rel):
    cam = Camera((1e6, 2e6, 100.0), yaw=yaw, pitch=pitch, roll=roll, fov_y=fov, viewport=(640, 480))
    x, y, d = rel
    p = cam.eye + d * (cam.forward + x * cam.tan_half_x * cam.right + y * cam.tan_half_y * cam.up)
    clip = cam.projection_matrix() @ cam.view_matrix() @ np.append(p - cam.eye, 1.0)
    ndc = clip[:3] / clip[3]
    px, py, depth = cam.project(p[None])
    w, h = cam.viewport
    np.testing.assert_allclose(
        [px[0], py[0]], [(ndc[0] + 1) / 2 * w, (1 - ndc[1]) / 2 * h], rtol=1e-9, atol=1e-6
    )
    assert depth[0] == pytest.approx(d, rel=1e-9)
    absolute = cam.view_matrix(absolute=True) @ np.append(p, 1.0)
    relative = cam.view_matrix() @ np.append(p - cam.eye, 1.0)
    np.testing.assert_allclose(absolute, relative, atol=1e-6)


def test_view_matrix_is_camera_relative():
    cam = Camera((5e6, 4e6, 900.0), yaw=30, pitch=-10)
    v = cam.view_matrix()
    np.testing.assert_array_equal(v[:3, 3], 0.0)
    np.testing.assert_array_equal(v[3], [0, 0, 0, 1])
    np.testing.assert_allclose(v[:3, :3] @ cam.forward, [0, 0, -1], atol=1e-12)


def test_projection_matrix_depth_range():
    cam = Camera((0, 0, 0), near=2.0, far=50.0)
    p = cam.projection_matrix()
    for d, ndc_z in ((2.0, -1.0), (50.0, 1.0)):
        clip = p @ np.array([0.0, 0.0, -d, 1.0])
        assert clip[2] / clip[3] == pytest.approx(ndc_z)


def test_frustum_corners_project_to_viewport_corners():
    cam = Camera((10, 20, 30), yaw=40, pitch=-30, roll=10, viewport=(320, 200), near=2, far=90)
    corners = cam.frustum_corners()
    px, py, depth = cam.project(corners)
    expected_px = [0, 320, 320, 0] * 2
    expected_py = [200, 200, 0, 0] * 2
    np.testing.assert_allclose(px, expected_px, atol=1e-9)
    np.testing.assert_allclose(py, expected_py, atol=1e-9)
    np.testing.assert_allclose(depth, [2] * 4 + [90] * 4)


@pytest.mark.parametrize(
    ("target", "up", "yaw", "pitch", "roll"),
    [
        ((0, 10, 0), (0, 0, 1), 0.0, 0.0, 0.0),
        ((10, 0, -10), (0, 0, 1), 90.0, -45.0, 0.0),
        ((0, 0, -10), (0, 0, 1), 0.0, -90.0, 0.0),
        ((0, 10, 0), (1, 0, 0), 0.0, 0.0, 90.0),
        ((0, -10, 0), (0, 0, -1), 180.0, 0.0, 180.0),
    ],
    ids=["north", "east-down", "straight-down", "up-east-rolls", "upside-down"],
)
def test_look_at(target, up, yaw, pitch, roll):
    cam = Camera.look_at((0, 0, 0), target, up=up, fov_y=50)
    assert cam.yaw == pytest.approx(yaw, abs=1e-9)
    assert cam.pitch == pytest.approx(pitch, abs=1e-9)
    assert abs((cam.roll - roll + 180) % 360 - 180) < 1e-9
    assert cam.fov_y == 50
    d = np.asarray(target, float) / np.linalg.norm(target)
    np.testing.assert_allclose(cam.forward, d, atol=1e-12)


def test_velocity_from():
    a = Camera((0, 0, 100))
    b = Camera((3, 4, 98))
    np.testing.assert_allclose(b.velocity_from(a, 0.5), [6, 8, -4])
    with pytest.raises(CameraError, match="dt"):
        b.velocity_from(a, 0.0)


def test_derived_intrinsics():
    cam = Camera((0, 0, 0), fov_y=90, viewport=(200, 100))
    assert cam.aspect == 2.0
    assert cam.tan_half_x == pytest.approx(2.0)
    assert cam.fov_x == pytest.approx(2 * math.degrees(math.atan(2.0)))
    assert cam.tan_half_diagonal == pytest.approx(math.sqrt(5.0))
    assert cam.focal_px == pytest.approx(50.0)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"fov_y": 0.0}, "fov_y.*0.0"),
        ({"fov_y": 180.0}, "fov_y.*180"),
        ({"fov_y": float("nan")}, "fov_y"),
        ({"viewport": (0, 10)}, r"viewport.*\(0, 10\)"),
        ({"viewport": (10.5, 10)}, "viewport.*10.5"),
        ({"viewport": (640,)}, "viewport"),
        ({"viewport": (float("inf"), 10)}, "viewport.*inf"),
        ({"viewport": (True, 10)}, "viewport.*True"),
        ({"near": 0.0}, "near.*0.0"),
        ({"near": 5.0, "far": 5.0}, "far.*5.0"),
        ({"near": 1e-40}, "near must be at least 1e-06 m.*1e-40"),  # rendered blank
        ({"far": 1e300}, "far must be at most 1e.15 m.*1e.300"),  # rendered blank
        ({"pitch": 91.0}, "pitch.*91"),
        ({"yaw": float("inf")}, "yaw"),
        ({"position": (0, float("nan"), 0)}, r"position\[1\]"),
        ({"position": (0, 0)}, "position"),
    ],
    ids=lambda v: str(v) if isinstance(v, dict) else None,
)
def test_invalid_camera(kw, match):
    args = {"position": (0.0, 0.0, 0.0), **kw}
    with pytest.raises(CameraError, match=match) as info:
        Camera(**args)
    assert isinstance(info.value, ValueError)
    assert isinstance(info.value, StreamerError)


def test_look_at_rejects_same_point():
    with pytest.raises(CameraError, match="target"):
        Camera.look_at((1, 2, 3), (1, 2, 3))


def test_camera_is_frozen_and_hashable():
    cam = Camera((1, 2, 3))
    with pytest.raises(AttributeError):
        cam.yaw = 3.0  # type: ignore[misc]
    assert hash(cam) == hash(Camera((1.0, 2.0, 3.0)))
    assert cam.position == (1.0, 2.0, 3.0)
