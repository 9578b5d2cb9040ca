"""``horizontal_px`` (the nodata rule ``"gap"``): a bound on the projected length of any segment
inside a node's box or sphere, checked against exact projection with the seeded camera sampler
of ``test_lod_view``; positive control: the gain ``f`` without the ``sqrt(1 + Q²)`` slope."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_lod_view import FOVS, SCENES, _camera

from streamer.camera import Camera
from streamer.lod import horizontal_px


def segments(seed: int, fov: float, scene: str, cameras: int = 40, boxes: int = 30, n: int = 40):
    """Per camera: ``(camera, a, b, centre, half_extent)``: segment ends uniform in world-axis
    boxes (flat ones, like terrain nodes, half of the time), both in view."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(cameras):
        cam = _camera(rng, fov, scene)
        depth = np.exp(rng.uniform(math.log(cam.near), math.log(cam.far), boxes))
        u = rng.uniform(-1.3, 1.3, (boxes, 1)) * cam.tan_half_x
        v = rng.uniform(-1.3, 1.3, (boxes, 1)) * cam.tan_half_y
        centre = cam.eye + depth[:, None] * (cam.forward + u * cam.right + v * cam.up)
        half = depth[:, None] * np.exp(rng.uniform(math.log(1e-3), math.log(2.0), (boxes, 3)))
        half[::2, 2] *= 1e-3
        a = centre[:, None, :] + rng.uniform(-1, 1, (boxes, n, 3)) * half[:, None, :]
        b = centre[:, None, :] + rng.uniform(-1, 1, (boxes, n, 3)) * half[:, None, :]
        if scene == "ground":
            b[..., 2] = a[..., 2]  # horizontal segments at the eye's height
        ok = cam.in_view(a) & cam.in_view(b)
        s, _ = np.nonzero(ok)
        out.append((cam, a[ok], b[ok], centre[s], half[s]))
    return out


def _exact(cam: Camera, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    xa, ya, _ = cam.project(a)
    xb, yb, _ = cam.project(b)
    return np.hypot(xb - xa, yb - ya)


def gap_violations(metric, seed: int, fov: float, scene: str, box: bool) -> tuple[int, int]:
    """(segments whose projected length exceeds ``metric``, segments checked)."""
    bad = total = 0
    for cam, a, b, centre, half in segments(seed, fov, scene):
        if not len(a):
            continue
        width = np.linalg.norm(b - a, axis=1)
        radius = np.linalg.norm(half, axis=1)
        bound = metric(width, centre, radius, cam, half_extent=half if box else None)
        bad += int((bound < _exact(cam, a, b) * (1 - 1e-9) - 1e-9).sum())
        total += len(a)
    return bad, total


def too_small(width, centre_xyz, radius, camera, half_extent=None):
    """The positive control: the box's nearest depth with a gain of ``f`` (no slope)."""
    basis = np.stack([camera.right, camera.up, camera.forward])
    c = (np.asarray(centre_xyz, float) - camera.eye) @ basis.T
    wz = radius if half_extent is None else np.abs(half_extent) @ np.abs(basis[2])
    z_min = c[:, 2] - wz
    return np.where(z_min > camera.near, camera.focal_px * width / z_min, np.inf)


@pytest.mark.parametrize("box", [True, False], ids=["box", "sphere"])
@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("fov", FOVS)
def test_horizontal_px_bounds_the_projected_segment(fov, scene, box):
    bad, n = gap_violations(horizontal_px, 11, fov, scene, box)
    assert n > 1000 and bad == 0, (bad, n)


@pytest.mark.parametrize("fov", [120.0, 170.0])
def test_positive_control_no_slope_is_violated(fov):
    bad, n = gap_violations(too_small, 11, fov, "mid", True)
    assert n > 1000 and bad > 0, (bad, n)


def test_horizontal_px_known_answer():
    """Straight down at a flat node under the eye: ``f w / z`` (``q = 0`` at the centre, so
    the slope term is ``sqrt(1 + (half diagonal / z)^2)``)."""
    cam = Camera((0.0, 0.0, 1000.0), pitch=-90.0, viewport=(200, 200), fov_y=90.0, near=1.0)
    half = np.array([[10.0, 10.0, 0.0]])
    got = horizontal_px(np.array([5.0]), np.array([[0.0, 0.0, 0.0]]), np.array([0.0]), cam, half)
    q = math.hypot(10.0, 10.0) / 1000.0
    assert got[0] == pytest.approx(cam.focal_px * 5.0 * math.sqrt(1 + q * q) / 1000.0)
    zero = horizontal_px(np.array([0.0]), np.array([[0.0, 0.0, 0.0]]), np.array([1.0]), cam)
    assert zero[0] == 0.0
