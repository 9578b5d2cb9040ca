"""Ground culling shapes: Qiu's triangle and extension, Jung & Han's hull, exact tests."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from streamer.camera import Camera
from streamer.errors import FrustumError
from streamer.frustum import (
    block_edge,
    blocks_meeting,
    convex_hull,
    extension_push,
    extension_triangle,
    frustum_hull,
    polygon_meets_circles,
    polygon_meets_rects,
    qiu_reach,
    view_triangle,
    visible_sets,
)
from tiler.grid import BlockGrid

R2 = math.sqrt(2.0)


def same_polygon(a: np.ndarray, b: np.ndarray, atol: float = 1e-9) -> bool:
    """Same vertex cycle, up to the starting vertex."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape:
        return False
    return any(np.allclose(np.roll(a, s, axis=0), b, atol=atol) for s in range(len(a)))


def signed_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


# --- Qiu's triangle ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("cam", "expected"),
    [
        (
            Camera((100, 200, 50), fov_y=90, viewport=(100, 100), far=100),
            [(100, 200), (200, 300), (0, 300)],
        ),
        (
            Camera((0, 0, 10), yaw=90, fov_y=90, viewport=(100, 100), far=100),
            [(0, 0), (100, -100), (100, 100)],
        ),
        (
            # pitch -45: far plane reaches far*(cos45 + tan45*sin45) = 100*sqrt(2) along the axis
            Camera((0, 0, 10), pitch=-45, fov_y=90, viewport=(100, 100), far=100),
            [(0, 0), (100 * R2, 100 * R2), (-100 * R2, 100 * R2)],
        ),
        (
            # looking straight down: the far plane's half height, far*tan(45) = 50, sets the reach
            Camera((0, 0, 10), yaw=180, pitch=-90, fov_y=90, viewport=(200, 100), far=50),
            [(0, 0), (-100, -50), (100, -50)],
        ),
    ],
    ids=["north-level", "east-level", "pitch-45", "straight-down-wide"],
)
def test_view_triangle_known(cam, expected):
    tri = view_triangle(cam)
    assert same_polygon(tri, expected)
    assert signed_area(tri) > 0
    legs = np.hypot(*(tri[1:] - tri[0]).T)
    np.testing.assert_allclose(legs, qiu_reach(cam))


def test_view_triangle_contains_level_frustum_trace():
    cam = Camera((3, 4, 0), yaw=33, fov_y=50, viewport=(300, 200), near=1, far=80)
    corners = cam.frustum_corners()[:, :2]
    # at pitch 0 the triangle is exactly the horizontal trace: corners lie inside or on it
    tri = view_triangle(cam)
    assert polygon_meets_circles(tri, corners[:, 0], corners[:, 1], 1e-9).all()
    assert polygon_meets_circles(tri, *tri[1], 0.0)


def test_view_triangle_explicit_reach():
    cam = Camera((0, 0, 0), fov_y=90, viewport=(10, 10))
    tri = view_triangle(cam, reach=R2)
    assert same_polygon(tri, [(0, 0), (1, 1), (-1, 1)])
    with pytest.raises(FrustumError, match="reach"):
        view_triangle(cam, reach=-1.0)


# --- Jung & Han's hull ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("cam", "zrange", "expected"),
    [
        (
            Camera((0, 0, 0), fov_y=90, viewport=(100, 100), near=1, far=100),
            None,
            [(-1, 1), (1, 1), (100, 100), (-100, 100)],
        ),
        (
            Camera((0, 0, 100), pitch=-90, fov_y=90, viewport=(100, 100), near=1, far=1000),
            None,
            [(-1000, -1000), (1000, -1000), (1000, 1000), (-1000, 1000)],
        ),
        (
            # clipped to the slab 0..10 below the eye at 100: the z=0 section, half-size 100
            Camera((0, 0, 100), pitch=-90, fov_y=90, viewport=(100, 100), near=1, far=1000),
            (0.0, 10.0),
            [(-100, -100), (100, -100), (100, 100), (-100, 100)],
        ),
        (
            Camera((5e6, 1e7, 100), pitch=-90, fov_y=90, viewport=(100, 100), near=1, far=1000),
            (0.0, 10.0),
            [
                (5e6 - 100, 1e7 - 100),
                (5e6 + 100, 1e7 - 100),
                (5e6 + 100, 1e7 + 100),
                (5e6 - 100, 1e7 + 100),
            ],
        ),
        (
            # level camera at z=0, slab 0..50: the far-side section is cut at the top corners
            Camera((0, 0, 0), fov_y=90, viewport=(100, 100), near=1, far=100),
            (0.0, 50.0),
            [(-1, 1), (1, 1), (100, 100), (-100, 100)],
        ),
    ],
    ids=["level", "straight-down", "straight-down-slab", "far-from-origin", "level-slab"],
)
def test_frustum_hull_known(cam, zrange, expected):
    hull = frustum_hull(cam, zrange)
    assert same_polygon(hull, expected, atol=1e-6)
    assert signed_area(hull) > 0


def test_frustum_hull_misses_slab():
    cam = Camera((0, 0, 100), pitch=10, near=1, far=50)  # looking up, far above the slab
    assert frustum_hull(cam, (0.0, 10.0)).shape == (0, 2)
    with pytest.raises(FrustumError, match="zrange"):
        frustum_hull(cam, (10.0, 0.0))


@settings(max_examples=60, deadline=None)
@given(
    yaw=st.floats(0, 360),
    pitch=st.floats(-90, 30),
    roll=st.floats(-45, 45),
    fov=st.floats(10, 120),
    u=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0, 1)),
)
def test_hull_contains_every_frustum_point(yaw, pitch, roll, fov, u):
    cam = Camera((1e6, 2e6, 300), yaw=yaw, pitch=pitch, roll=roll, fov_y=fov, near=1, far=2000)
    x, y, t = u
    d = cam.near + t * (cam.far - cam.near)
    p = cam.eye + d * (cam.forward + x * cam.tan_half_x * cam.right + y * cam.tan_half_y * cam.up)
    hull = frustum_hull(cam)
    assert polygon_meets_circles(hull, p[0], p[1], 1e-6)
    if 0.0 <= p[2] <= 200.0:
        assert polygon_meets_circles(frustum_hull(cam, (0.0, 200.0)), p[0], p[1], 1e-6)


def test_convex_hull_degenerate():
    assert convex_hull(np.zeros((0, 2))).shape == (0, 2)
    np.testing.assert_array_equal(convex_hull([[1, 2], [1, 2]]), [[1, 2]])
    np.testing.assert_array_equal(convex_hull([[0, 0], [1, 1], [2, 2]]), [[0, 0], [2, 2]])
    sq = convex_hull([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5], [1, 0.5]])
    assert same_polygon(sq, [(0, 0), (1, 0), (1, 1), (0, 1)])


def _numpy_scalar_hull(points, tol: float = 1e-12) -> np.ndarray:
    """The monotone chain on numpy scalars after ``np.unique(axis=0)`` (``convex_hull`` before
    it moved to Python floats; ``tol`` the collinearity tolerance, changed only by the positive
    control)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    origin = pts.min(axis=0)
    rel = np.unique(pts - origin, axis=0)
    if len(rel) <= 2:
        return rel + origin

    def left(o, a, b):
        ax, ay, bx, by = a[0] - o[0], a[1] - o[1], b[0] - o[0], b[1] - o[1]
        return ax * by - ay * bx > tol * math.hypot(ax, ay) * math.hypot(bx, by)

    lower, upper = [], []
    for chain, seq in ((lower, rel), (upper, rel[::-1])):
        for p in seq:
            while len(chain) >= 2 and not left(chain[-2], chain[-1], p):
                chain.pop()
            chain.append(p)
    return np.array(lower[:-1] + upper[:-1]) + origin


def test_convex_hull_is_the_numpy_scalar_chain_bit_for_bit():
    rng = np.random.default_rng(3)
    sets = [rng.normal(0, 1e4, (n, 2)) + 5e5 for n in (3, 5, 12, 40)]
    t = rng.uniform(0, 1, 30)  # near-collinear: a segment with sub-tolerance wiggles
    sets.append(np.stack([t, 2 * t + rng.normal(0, 1e-14, 30)], 1) * 1e3 + 4e6)
    sets.append(np.repeat(rng.normal(0, 10, (6, 2)), 3, axis=0))  # duplicates
    sets += [np.repeat([[3.0, -2.0]], 3, axis=0), [[1.0, 5.0], [1.0, 5.0], [-4.0, 5.0]]]
    sets.append([[0.0, 1.0], [0.0, -1.0], [-0.0, 0.5], [2.0, 0.0]])  # equal x, signed zero
    for yaw in (0.0, 33.0, 200.0):
        cam = Camera((5e5, 5e6, 900.0), yaw=yaw, pitch=-12.0, far=3e4)
        sets.append(cam.frustum_corners()[:, :2])
    for pts in sets:
        got, want = convex_hull(pts), _numpy_scalar_hull(pts)
        assert got.dtype == want.dtype and np.array_equal(got, want)
    # positive control: the comparison sees a changed collinearity rule on the near-collinear set
    assert not np.array_equal(convex_hull(sets[4]), _numpy_scalar_hull(sets[4], tol=-1.0))
    assert convex_hull([[0.0, 0.0]] * 3).shape == (1, 2)


def _numpy_frustum_hull(camera: Camera, zrange=None, far_scale: float = 1.0) -> np.ndarray:
    """``frustum_hull`` before it moved to Python floats: the corners and the slab clipping as
    numpy arrays (``far_scale`` moves the far plane: the positive control only)."""
    sx = np.array([-1.0, 1.0, 1.0, -1.0]) * camera.tan_half_x  # the corners as numpy did them
    sy = np.array([-1.0, -1.0, 1.0, 1.0]) * camera.tan_half_y
    rel = np.concatenate(
        [d * (camera.forward + sx[:, None] * camera.right + sy[:, None] * camera.up)
         for d in (camera.near, camera.far)]
    )  # fmt: skip
    rel[4:] *= far_scale
    pts = rel
    if zrange is not None:
        zlo, zhi = (float(z) - camera.position[2] for z in zrange)
        z = rel[:, 2]
        keep = [rel[(z >= zlo) & (z <= zhi)]]
        edges = np.array([(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4),
                          (0, 4), (1, 5), (2, 6), (3, 7)])  # fmt: skip
        a, b = rel[edges[:, 0]], rel[edges[:, 1]]
        for z0 in (zlo, zhi):
            da, db = a[:, 2] - z0, b[:, 2] - z0
            cross = da * db < 0.0
            t = da[cross] / (da[cross] - db[cross])
            keep.append(a[cross] + t[:, None] * (b[cross] - a[cross]))
        pts = np.concatenate(keep)
    return convex_hull(pts[:, :2]) + camera.eye[:2]


def test_frustum_hull_is_the_numpy_one_bit_for_bit():
    """The Python-float corners and clipping give the numpy version's hull exactly, at the
    extremes (coordinates near 1e7 m, heights -11 to +9 km, FOV 1-170 deg, a slab of zero
    thickness at the eye, a frustum that misses the slab)."""
    rng = np.random.default_rng(7)
    n_empty = 0
    for _ in range(400):
        z = float(rng.choice([0.0, 0.5, 300.0, 8848.0, -11000.0]))
        pos = (rng.uniform(-1e7, 1e7), rng.uniform(-1e7, 1e7), z)
        cam = Camera(
            pos, yaw=rng.uniform(0, 360), pitch=rng.uniform(-90, 90), roll=rng.uniform(-45, 45),
            fov_y=rng.uniform(1, 170), near=float(rng.choice([0.1, 1.0])),
            far=float(rng.choice([100.0, 1e5, 1e6])),
        )  # fmt: skip
        for zr in (None, (0.0, 10.0), (-11000.0, 8848.0), (z, z), (z - 1.0, z + 1.0)):
            got, want = frustum_hull(cam, zr), _numpy_frustum_hull(cam, zr)
            assert got.shape == want.shape and np.array_equal(got, want)
            n_empty += len(got) == 0
    assert n_empty > 0  # the empty case was exercised
    # positive control: the comparison sees a far plane moved by one part in 1e12
    cam = Camera((5e5, 5e6, 900.0), yaw=30.0, pitch=-12.0, far=3e4)
    assert not np.array_equal(frustum_hull(cam), _numpy_frustum_hull(cam, None, 1.0 + 1e-12))


# --- Qiu's extension --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("angle", "expected"),
    [(0.0, 1.0), (45.0, math.sqrt(0.5)), (90.0, 0.0), (135.0, 0.0), (180.0, 0.0)],
    ids=["0deg", "45deg", "90deg", "135deg", "180deg"],
)
def test_extension_push(angle, expected):
    # V = 10 m/s, f = 10 fps -> S = cos(a) m per frame when a < 90 degrees
    cam = Camera((0, 0, 100), yaw=30, pitch=-20)
    heading = math.radians(30 + angle)
    v = (10 * math.sin(heading), 10 * math.cos(heading), -3.0)
    assert extension_push(cam, v, 10.0) == pytest.approx(expected, abs=1e-12)


def test_extension_push_still_and_vertical():
    cam = Camera((0, 0, 100))
    assert extension_push(cam, (0, 0, 0), 30) == 0.0
    assert extension_push(cam, (0, 0, -50), 30) == 0.0
    with pytest.raises(FrustumError, match="fps"):
        extension_push(cam, (1, 0, 0), 0.0)
    with pytest.raises(FrustumError, match="velocity"):
        extension_push(cam, (1, float("nan"), 0), 30.0)


@pytest.mark.parametrize(
    ("velocity", "expected"),
    [
        # height 100 (legs 100*sqrt2), L = 10, no push: apex (0,-10), height 110
        ((0, 0, 0), [(0, -10), (110, 100), (-110, 100)]),
        # forward at 50 m/s, 10 fps: S = 5 -> height 115
        ((0, 50, 0), [(0, -10), (115, 105), (-115, 105)]),
        # backwards: S = 0
        ((0, -50, 0), [(0, -10), (110, 100), (-110, 100)]),
    ],
    ids=["still", "forward", "backward"],
)
def test_extension_triangle_known(velocity, expected):
    cam = Camera((0, 0, 10), fov_y=90, viewport=(100, 100), far=100)
    ext = extension_triangle(cam, 10.0, velocity=velocity, fps=10.0)
    assert same_polygon(ext, expected)
    tri = view_triangle(cam)
    assert polygon_meets_circles(ext, tri[:, 0], tri[:, 1], 1e-9).all()


def test_extension_rejects_bad_length():
    with pytest.raises(FrustumError, match="L must"):
        extension_triangle(Camera((0, 0, 0)), -1.0)


# --- exact intersection tests -----------------------------------------------------------------

TRI = np.array([(0.0, 0.0), (10.0, 0.0), (0.0, 10.0)])


@pytest.mark.parametrize(
    ("rect", "expected"),
    [
        ((1, 1, 2, 2), True),  # inside
        ((-5, -5, 20, 20), True),  # contains the polygon
        ((6, 6, 9, 9), False),  # inside the bbox, beyond the hypotenuse
        ((4.9, 4.9, 6, 6), True),  # corner just across the hypotenuse
        ((5, 5, 6, 6), True),  # touches the hypotenuse at a point
        ((10, -1, 11, 1), True),  # touches a vertex
        ((10.01, -1, 11, 1), False),  # just past a vertex
        ((-3, -3, -1, -1), False),  # far away
        ((2, -1, 3, 11), True),  # straddles
    ],
    ids=[
        "inside",
        "contains",
        "beyond-hypotenuse",
        "across-hypotenuse",
        "touch-edge",
        "touch-vertex",
        "past-vertex",
        "far",
        "straddle",
    ],
)
def test_polygon_meets_rect_known(rect, expected):
    assert bool(polygon_meets_rects(TRI, *rect)) is expected
    assert bool(polygon_meets_rects(TRI[::-1], *rect)) is expected  # orientation-free


@pytest.mark.parametrize(
    ("circle", "expected"),
    [
        ((1, 1, 0.1), True),  # centre inside
        ((6, 6, 1.0), False),  # distance to hypotenuse sqrt(2) > 1
        ((6, 6, 1.5), True),
        ((-1, -1, 1.4), False),  # vertex at distance sqrt(2)
        ((-1, -1, 1.42), True),
        ((5, -2, 2.0), True),  # touches the bottom edge
        ((50, 50, 63), False),  # hypotenuse at 90/sqrt(2) = 63.64
        ((50, 50, 70), True),  # huge circle swallowing it
    ],
    ids=[
        "inside",
        "near-miss",
        "hit",
        "vertex-miss",
        "vertex-hit",
        "touch",
        "huge-miss",
        "swallow",
    ],
)
def test_polygon_meets_circle_known(circle, expected):
    assert bool(polygon_meets_circles(TRI, *circle)) is expected


def _reference_meets_rect(poly, rect) -> bool:
    """Slow reference: vertex containment either way or a proper edge crossing."""
    x0, y0, x1, y1 = rect
    box = np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)])

    def inside(p, q):
        e = np.roll(q, -1, axis=0) - q
        c = e[:, 0] * (p[1] - q[:, 1]) - e[:, 1] * (p[0] - q[:, 0])
        return (c >= 0).all() or (c <= 0).all()

    if any(x0 <= p[0] <= x1 and y0 <= p[1] <= y1 for p in poly):
        return True
    if any(inside(b, poly) for b in box):
        return True

    def cross(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        for j in range(4):
            c, d = box[j], box[(j + 1) % 4]
            if cross(a, b, c) * cross(a, b, d) < 0 and cross(c, d, a) * cross(c, d, b) < 0:
                return True
    return False


coords = st.floats(-100, 100, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(
    pts=st.lists(st.tuples(coords, coords), min_size=3, max_size=9),
    rect=st.tuples(coords, coords, st.floats(0.1, 80), st.floats(0.1, 80)),
    offset=st.sampled_from([0.0, 1e7]),
)
def test_sat_matches_reference(pts, rect, offset):
    poly = convex_hull(np.array(pts))
    if len(poly) < 3 or abs(signed_area(poly)) < 1e-3:
        return
    x, y, w, h = rect
    r = (x, y, x + w, y + h)
    expected = _reference_meets_rect(poly, r)
    eps = 1e-6
    grown = _reference_meets_rect(poly, (x - eps, y - eps, x + w + eps, y + h + eps))
    shrunk = _reference_meets_rect(poly, (x + eps, y + eps, x + w - eps, y + h - eps))
    if grown != shrunk:  # touching within rounding: either answer is right
        return
    got = polygon_meets_rects(poly + offset, *(np.array(r) + offset))
    assert bool(got) is expected


@settings(max_examples=150, deadline=None)
@given(
    pts=st.lists(st.tuples(coords, coords), min_size=3, max_size=9),
    c=st.tuples(coords, coords, st.floats(0.01, 60)),
)
def test_circle_matches_dense_reference(pts, c):
    poly = convex_hull(np.array(pts))
    if len(poly) < 3 or abs(signed_area(poly)) < 1e-3:
        return
    cx, cy, r = c
    # exact distance from the centre to the polygon (0 inside), via edge projections
    e = np.roll(poly, -1, axis=0) - poly
    q = np.array([cx, cy]) - poly
    ee = np.sum(e * e, axis=1)  # a zero-length edge (hull points 1e-227 apart): its start
    t = np.clip(np.divide(np.sum(q * e, axis=1), ee, out=np.zeros_like(ee), where=ee > 0), 0, 1)
    dist = np.min(np.hypot(*(q - t[:, None] * e).T))
    inside = (e[:, 0] * q[:, 1] - e[:, 1] * q[:, 0] >= 0).all()
    if abs(dist - r) < 1e-9 and not inside:
        return
    assert bool(polygon_meets_circles(poly, cx, cy, r)) is bool(inside or dist <= r)


def test_vectorised_shapes():
    xs = np.arange(-5.0, 15.0)
    hit = polygon_meets_rects(TRI, xs, 0.5, xs + 0.5, 1.0)
    assert hit.shape == xs.shape
    np.testing.assert_array_equal(hit, (xs + 0.5 >= 0) & (xs <= 9.5))
    assert polygon_meets_circles(np.zeros((0, 2)), xs, xs, 1.0).shape == xs.shape
    assert not polygon_meets_rects(np.zeros((0, 2)), 0, 0, 1, 1)


def test_degenerate_polygons():
    seg = np.array([(0.0, 0.0), (10.0, 10.0)])
    assert polygon_meets_rects(seg, 4, 4, 6, 6)
    assert not polygon_meets_rects(seg, 6, 0, 9, 3)
    assert polygon_meets_circles(seg, 5, 6, 0.75)
    assert not polygon_meets_circles(seg, 5, 6, 0.7)
    pt = np.array([(1.0, 1.0)])
    assert polygon_meets_circles(pt, 1.0, 2.0, 1.0)
    assert not polygon_meets_rects(pt, 1.5, 0, 2, 2)
    with pytest.raises(FrustumError, match="shape"):
        polygon_meets_rects(np.zeros((3, 3)), 0, 0, 1, 1)
    with pytest.raises(FrustumError, match="finite"):
        polygon_meets_circles(np.array([(0, 0), (1, np.nan), (0, 1)]), 0, 0, 1)


# --- blocks -----------------------------------------------------------------------------------

# k=2: blocks of 5x5 samples, 4 sample steps; dx=dy=1 -> block edge 4 m.
# 21x41 samples -> 5 block rows x 10 block columns over x in [0, 40], y in [-20, 0].
GRID = BlockGrid(height=21, width=41, k=2)


@pytest.mark.parametrize(
    ("poly", "expected"),
    [
        ([(1, -1), (2, -1), (1, -2)], [(0, 0)]),
        ([(5, -5), (10.5, -5), (5, -10.5)], [(1, 1), (1, 2), (2, 1)]),
        ([(5, -5), (11, -5), (5, -11)], [(1, 1), (1, 2), (2, 1), (2, 2)]),  # touches (2, 2)
        ([(5, -5), (13, -5), (5, -13)], [(1, 1), (1, 2), (1, 3), (2, 1), (2, 2), (3, 1)]),
        ([(-10, 10), (-5, 10), (-10, 5)], []),
        ([(-100, 100), (100, 100), (0, -100)], None),
        ([(38, -18), (60, -18), (38, -40)], [(4, 9)]),
    ],
    ids=["one", "three", "touching-corner", "staircase", "outside", "everything", "last-corner"],
)
def test_blocks_meeting_known(poly, expected):
    got = blocks_meeting(np.array(poly, float), GRID)
    if expected is None:
        expected = GRID.blocks()
    assert got.dtype == np.int64
    assert [tuple(r) for r in got.tolist()] == sorted(expected)


def test_blocks_meeting_far_from_origin_same():
    far = BlockGrid(height=21, width=41, k=2, x0=1e7, y0=-1e7, dx=1.0, dy=1.0)
    for poly in ([(5, -5), (13, -5), (5, -13)], [(0.3, -0.2), (39.1, -3.3), (17.7, -19.9)]):
        p = np.array(poly, float)
        near_blocks = blocks_meeting(p, GRID)
        far_blocks = blocks_meeting(p + np.array([1e7, -1e7]), far)
        np.testing.assert_array_equal(near_blocks, far_blocks)


def test_visible_sets():
    grid = BlockGrid(height=257, width=257, k=4)  # 16 x 16 blocks of 16 m
    assert block_edge(grid) == 16.0
    cam = Camera((128, -128, 30), yaw=45, pitch=-20, fov_y=40, far=60)
    m, n = visible_sets(cam, grid, velocity=(20, 20, 0), fps=2)
    ms, ns = {tuple(b) for b in m.tolist()}, {tuple(b) for b in n.tolist()}
    assert ms
    assert ms < ns
    mh, nh = visible_sets(cam, grid, culling="hull", zrange=(0, 10))
    assert {tuple(b) for b in mh.tolist()} <= {tuple(b) for b in nh.tolist()}
    assert len(mh) > 0
    with pytest.raises(FrustumError, match="culling"):
        visible_sets(cam, grid, culling="sphere")
