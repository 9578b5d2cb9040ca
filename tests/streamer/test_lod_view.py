"""``conservative-view``: a per-node bound on the pixel shift, checked against exact projection.

A seeded sampler draws cameras (FOV 1-170 degrees, near/far extremes, a camera at the ground)
and spheres; in each sphere it draws points ``B`` with ``B`` and ``B + delta*up`` both inside
the sphere and in view (so the segment between them is too: sphere and frustum are convex),
projects both with :meth:`Camera.project` and compares the pixel distance with the metric.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from streamer.camera import Camera
from streamer.lod import (
    FIELD_FOR_METRIC,
    METRICS,
    conservative,
    conservative_view,
    exact_projected,
    get_metric,
    takes_box,
)

FOVS = (1.0, 45.0, 120.0, 170.0)
SCENES = ("mid", "near", "far", "ground")
UP = np.array([0.0, 0.0, 1.0])


def _camera(rng: np.random.Generator, fov: float, scene: str) -> Camera:
    """A random camera for one scene: depths ~1e3 (mid), ~1e-2 (near), ~1e6 (far)."""
    near, far = {"mid": (0.5, 5e3), "near": (1e-3, 1.0), "far": (10.0, 1e7), "ground": (0.5, 5e3)}[
        scene
    ]
    pitch = rng.uniform(-3.0, 3.0) if scene == "ground" else rng.uniform(-90.0, 90.0)
    origin = np.array([1e7, -1e7, 0.0]) if rng.random() < 0.5 else np.zeros(3)
    z = 0.0 if scene == "ground" else rng.uniform(-50.0, 2e3)
    return Camera(
        tuple(origin + [rng.uniform(-1e3, 1e3), rng.uniform(-1e3, 1e3), z]),
        yaw=rng.uniform(0.0, 360.0),
        pitch=pitch,
        roll=rng.uniform(-180.0, 180.0) if rng.random() < 0.5 else 0.0,
        fov_y=fov,
        viewport=(int(rng.integers(1, 2000)), int(rng.integers(1, 2000))),
        near=near,
        far=far,
    )


def sample(
    seed: int, fov: float, scene: str, cameras: int = 40, spheres: int = 30, points: int = 40
) -> list[tuple[Camera, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per camera: ``(camera, delta, B, centre, radius)`` of the sampled in-view segments."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(cameras):
        cam = _camera(rng, fov, scene)
        depth = np.exp(rng.uniform(math.log(cam.near), math.log(cam.far), spheres))
        a = rng.uniform(-1.3, 1.3, (spheres, 1)) * cam.tan_half_x
        b = rng.uniform(-1.3, 1.3, (spheres, 1)) * cam.tan_half_y
        rel = depth[:, None] * (cam.forward + a * cam.right + b * cam.up)
        centre = cam.eye + rel
        radius = depth * np.exp(rng.uniform(math.log(1e-3), math.log(3.0), spheres))
        if scene == "ground":  # spheres around the eye's height: terrain seen from the ground
            centre[:, 2] = cam.eye[2] + rng.uniform(-1.0, 0.5, spheres) * radius
        # points uniform in each sphere, then the largest upward move that stays inside it
        e = rng.normal(size=(spheres, points, 3))
        e *= (radius[:, None] * rng.random((spheres, points)) ** (1 / 3))[
            ..., None
        ] / np.linalg.norm(e, axis=-1, keepdims=True)
        eu = e[..., 2]
        t_max = -eu + np.sqrt(np.maximum(eu * eu - (e * e).sum(-1) + radius[:, None] ** 2, 0.0))
        delta = rng.random((spheres, points)) * t_max
        pts = centre[:, None, :] + e
        ok = cam.in_view(pts) & cam.in_view(pts + delta[..., None] * UP) & (delta > 0)
        s, _ = np.nonzero(ok)
        out.append((cam, delta[ok], pts[ok], centre[s], radius[s]))
    return out


def too_small(
    delta: np.ndarray, centre_xyz: np.ndarray, radius: np.ndarray, camera: Camera
) -> np.ndarray:
    """The positive control: gain ``f`` as if ``q = 0`` everywhere (not a bound)."""
    rel = np.asarray(centre_xyz, float) - camera.eye
    z_min = rel @ camera.forward - radius
    return np.where(z_min > camera.near, camera.focal_px * delta / z_min, np.inf)


def violations(metric, seed: int, fov: float, scene: str) -> tuple[int, int]:
    """(points where ``metric`` < the exact shift, points checked)."""
    bad = n = 0
    for cam, delta, pts, centre, radius in sample(seed, fov, scene):
        if len(delta) == 0:
            continue
        exact = exact_projected(delta, pts, cam)
        bound = metric(delta, centre, radius, cam)
        bad += int((bound < exact * (1 - 1e-9) - 1e-9).sum())
        n += len(delta)
    return bad, n


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("fov", FOVS)
def test_conservative_view_bounds_exact(fov, scene):
    bad, n = violations(conservative_view, 11, fov, scene)
    assert n > 2000, n  # enough in-view segments were drawn
    assert bad == 0, (bad, n)


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("fov", FOVS)
def test_conservative_bounds_exact_same_sampler(fov, scene):
    assert violations(conservative, 11, fov, scene)[0] == 0


@pytest.mark.parametrize("fov", [45.0, 120.0, 170.0])
def test_positive_control_too_small_bound_is_violated(fov):
    """The sampler finds the points a gain of ``f`` misses (off-axis, camera tilted)."""
    bad, n = violations(too_small, 11, fov, "mid")
    assert bad > 0, n


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("fov", FOVS)
def test_conservative_view_never_above_conservative(fov, scene):
    for cam, _, _, centre, radius in sample(5, fov, scene, cameras=20):
        if len(centre) == 0:
            continue
        d = np.ones(len(centre))
        new, old = conservative_view(d, centre, radius, cam), conservative(d, centre, radius, cam)
        finite = np.isfinite(old)
        assert (np.isinf(new) == np.isinf(old)).all()
        assert (new[finite] <= old[finite] * (1 + 1e-12)).all()


def test_conservative_view_tighter_at_wide_fov():
    """Tighter where the old bound was loose: median ratio to the old bound at 170 degrees."""
    ratios = []
    for cam, _, _, centre, radius in sample(5, 170.0, "ground", cameras=20):
        d = np.ones(len(centre))
        new, old = conservative_view(d, centre, radius, cam), conservative(d, centre, radius, cam)
        ok = np.isfinite(old) & (old > 0)
        ratios.append(new[ok] / old[ok])
    assert np.median(np.concatenate(ratios)) < 0.2


def test_conservative_view_known():
    """A level camera (``u_z = 0``): gain f whatever the FOV; straight down: the centre's rate."""
    for fov in (5.0, 170.0):
        cam = Camera((0, 0, 0), fov_y=fov, viewport=(600, 600), near=1, far=1e5)
        rho = conservative_view(np.array([2.0]), np.array([[30.0, 100, 5]]), np.array([10.0]), cam)
        assert rho[0] == pytest.approx(cam.focal_px * 2 / 90)
    down = Camera((0, 0, 100), pitch=-90, fov_y=90, viewport=(600, 600), near=1, far=1e5)
    rho = conservative_view(np.array([2.0]), np.array([[0.0, 0, 0]]), np.array([10.0]), down)
    # u = (0, 0, -1) in camera coordinates: g1 = 0 + 10/90, g2 = 0 + 100 * 10 / (100 * 90)
    assert rho[0] == pytest.approx(300 * 2 * (10 / 90) / 90)
    cases = np.array([[0, 100, 0], [0, 5, 0], [0, -100, 0], [0, 2e5, 0]], float)
    cam = Camera((0, 0, 0), fov_y=90, viewport=(600, 600), near=1, far=1e5)
    rho = conservative_view(np.full(4, 2.0), cases, np.array([99.5, 10.0, 10.0, 10.0]), cam)
    assert rho[0] == np.inf and rho[1] == np.inf  # reaches before near; eye inside
    assert rho[2] == 0.0 and rho[3] == 0.0  # wholly behind; beyond far
    assert conservative_view(np.array([0.0]), cases[1:2], np.array([10.0]), cam)[0] == 0.0


def test_registry_has_conservative_view():
    assert get_metric("conservative-view") is conservative_view
    assert takes_box("conservative-view") and not takes_box("qiu") and not takes_box(conservative)
    assert FIELD_FOR_METRIC["conservative-view"] == "bound"
    assert next(iter(METRICS)) == "qiu"  # the default metric is unchanged


@settings(max_examples=300, deadline=None)
@given(
    pos=st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(-50, 2e3)),
    yaw=st.floats(0, 360),
    pitch=st.floats(-90, 90),
    roll=st.floats(-180, 180),
    fov=st.floats(1, 170),
    viewport=st.tuples(st.integers(1, 2000), st.integers(1, 2000)),
    uvw=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0, 1)),
    frac=st.floats(0, 1),
    slack=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.floats(0, 200)),
)
def test_conservative_view_bounds_exact_hypothesis(
    pos, yaw, pitch, roll, fov, viewport, uvw, frac, slack
):
    """As test_lod's check of ``conservative``: a sphere holding B and B + delta*up (in view)."""
    cam = Camera(pos, yaw=yaw, pitch=pitch, roll=roll, fov_y=fov, viewport=viewport, near=0.5,
                 far=5000.0)  # fmt: skip
    u, v, w = uvw
    depth = cam.near + w * (cam.far - cam.near)
    b = cam.eye + depth * (
        cam.forward + u * cam.tan_half_x * cam.right + v * cam.tan_half_y * cam.up
    )
    assume(cam.in_view(b)[()])
    top = b + frac * 500.0 * UP
    assume(cam.in_view(top)[()])
    delta = float(top[2] - b[2])
    sx, sy, sz, extra = slack
    centre = 0.5 * (b + top) + np.array([sx, sy, sz]) * 20.0
    radius = max(np.linalg.norm(centre - b), np.linalg.norm(centre - top)) + extra
    exact = exact_projected(np.array([delta]), b[None], cam)[0]
    bound = conservative_view(np.array([delta]), centre[None], np.array([radius]), cam)[0]
    assert bound >= exact * (1 - 1e-9) - 1e-9


# --- node boxes (half_extent=): the selection's per-node height ranges ------------------------


def sample_boxes(
    seed: int, fov: float, scene: str, cameras: int = 40, boxes: int = 30, points: int = 40
) -> list[tuple[Camera, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """As :func:`sample` for world-axis boxes: ``(camera, delta, B, centre, half_extent)``,
    ``B`` uniform in the box and ``B + delta*up`` below its top, both in view."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(cameras):
        cam = _camera(rng, fov, scene)
        depth = np.exp(rng.uniform(math.log(cam.near), math.log(cam.far), boxes))
        a = rng.uniform(-1.3, 1.3, (boxes, 1)) * cam.tan_half_x
        b = rng.uniform(-1.3, 1.3, (boxes, 1)) * cam.tan_half_y
        centre = cam.eye + depth[:, None] * (cam.forward + a * cam.right + b * cam.up)
        half = depth[:, None] * np.exp(rng.uniform(math.log(1e-3), math.log(2.0), (boxes, 3)))
        if scene == "ground":  # flat boxes around the eye's height
            half[:, 2] *= 0.1
            centre[:, 2] = cam.eye[2] + rng.uniform(-1.0, 0.5, boxes) * half[:, 2]
        e = rng.uniform(-1.0, 1.0, (boxes, points, 3)) * half[:, None, :]
        delta = rng.random((boxes, points)) * (half[:, None, 2] - e[..., 2])
        pts = centre[:, None, :] + e
        ok = cam.in_view(pts) & cam.in_view(pts + delta[..., None] * UP) & (delta > 0)
        s, _ = np.nonzero(ok)
        out.append((cam, delta[ok], pts[ok], centre[s], half[s]))
    return out


def box_violations(metric, seed: int, fov: float, scene: str) -> tuple[int, int]:
    """(points where ``metric(..., half_extent=)`` < the exact shift, points checked)."""
    bad = n = 0
    for cam, delta, pts, centre, half in sample_boxes(seed, fov, scene):
        if len(delta) == 0:
            continue
        exact = exact_projected(delta, pts, cam)
        bound = metric(delta, centre, np.linalg.norm(half, axis=1), cam, half_extent=half)
        bad += int((bound < exact * (1 - 1e-9) - 1e-9).sum())
        n += len(delta)
    return bad, n


def too_small_box(delta, centre_xyz, radius, camera, half_extent):
    """The positive control for boxes: the box's nearest depth with a gain of ``f``."""
    basis = np.stack([camera.right, camera.up, camera.forward])
    c = (np.asarray(centre_xyz, float) - camera.eye) @ basis.T
    z_min = c[:, 2] - np.abs(half_extent) @ np.abs(basis[2])
    return np.where(z_min > camera.near, camera.focal_px * delta / z_min, np.inf)


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("fov", FOVS)
def test_conservative_view_box_bounds_exact(fov, scene):
    bad, n = box_violations(conservative_view, 13, fov, scene)
    assert n > 1000, n  # enough in-view segments were drawn
    assert bad == 0, (bad, n)


@pytest.mark.parametrize("fov", [45.0, 120.0, 170.0])
def test_positive_control_too_small_box_bound_is_violated(fov):
    bad, n = box_violations(too_small_box, 13, fov, "mid")
    assert bad > 0, n


@pytest.mark.parametrize("fov", FOVS)
def test_box_never_above_the_sphere_around_it(fov):
    """``w_i <= |h|`` (rows of a rotation are unit): the box's bound is at most its sphere's."""
    for cam, _, _, centre, half in sample_boxes(7, fov, "mid", cameras=20):
        if len(centre) == 0:
            continue
        d, r = np.ones(len(centre)), np.linalg.norm(half, axis=1)
        box = conservative_view(d, centre, r, cam, half_extent=half)
        sphere = conservative_view(d, centre, r, cam)
        finite = np.isfinite(sphere)
        assert (box[finite] <= sphere[finite] * (1 + 1e-12)).all()
        assert (box[~finite] >= 0).all()


def test_flat_box_much_tighter_than_its_sphere():
    """A wide, flat node seen obliquely: the box's nearest point is far deeper than the
    sphere's, which reaches half a diagonal towards the eye."""
    cam = Camera((0, 0, 300), pitch=-20, fov_y=60, viewport=(600, 400), near=1, far=1e5)
    centre = np.array([[0.0, 1000.0, 0.0]])
    half = np.array([[400.0, 400.0, 5.0]])
    r = np.linalg.norm(half, axis=1)
    box = conservative_view(np.ones(1), centre, r, cam, half_extent=half)[0]
    sphere = conservative_view(np.ones(1), centre, r, cam)[0]
    assert box < 0.7 * sphere


@settings(max_examples=300, deadline=None)
@given(
    pos=st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(-50, 2e3)),
    yaw=st.floats(0, 360),
    pitch=st.floats(-90, 90),
    roll=st.floats(-180, 180),
    fov=st.floats(1, 170),
    uvw=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0, 1)),
    frac=st.floats(0, 1),
    slack=st.tuples(st.floats(0, 1), st.floats(0, 1), st.floats(0, 1), st.floats(0, 1)),
    half_xy=st.tuples(st.floats(0, 300), st.floats(0, 300)),
)
def test_conservative_view_box_bounds_exact_hypothesis(
    pos, yaw, pitch, roll, fov, uvw, frac, slack, half_xy
):
    """A box holding B and B + delta*up (in view), B anywhere inside its footprint."""
    cam = Camera(pos, yaw=yaw, pitch=pitch, roll=roll, fov_y=fov, viewport=(640, 480),
                 near=0.5, far=5000.0)  # fmt: skip
    u, v, w = uvw
    depth = cam.near + w * (cam.far - cam.near)
    b = cam.eye + depth * (
        cam.forward + u * cam.tan_half_x * cam.right + v * cam.tan_half_y * cam.up
    )
    assume(cam.in_view(b)[()])
    top = b + frac * 500.0 * UP
    assume(cam.in_view(top)[()])
    delta = float(top[2] - b[2])
    sx, sy, below, above = slack
    hx, hy = half_xy
    centre_xy = b[:2] + (2 * np.array([sx, sy]) - 1) * np.array([hx, hy])
    lo, hi = b[2] - below * 100.0, top[2] + above * 100.0
    centre = np.array([*centre_xy, 0.5 * (lo + hi)])
    half = np.array([hx, hy, 0.5 * (hi - lo)])
    exact = exact_projected(np.array([delta]), b[None], cam)[0]
    r = np.array([np.linalg.norm(half)])
    bound = conservative_view(np.array([delta]), centre[None], r, cam, half_extent=half[None])[0]
    assert bound >= exact * (1 - 1e-9) - 1e-9
