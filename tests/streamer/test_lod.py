"""Screen-error metrics and the patch-based LOD selection of one block."""

from __future__ import annotations

import math
from dataclasses import replace
from functools import cache

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from lod_reference import (
    needed_level,
    needed_levels,
    node_centres,
    select_many,
    select_nodes,
    subtree_errors,
)

from streamer.camera import Camera
from streamer.errors import LodError, StreamerError
from streamer.frustum import frustum_hull, view_triangle
from streamer.lod import (
    FIELD_FOR_METRIC,
    METRICS,
    conservative,
    exact_projected,
    get_metric,
    qiu_eq7,
)
from tiler.grid import BlockGrid
from tiler.static_error import block_errors, subtree_error, unpack_field

K, CAP = 6, 2
# 2 x 2 blocks of 65 x 65 samples, 10 m apart: blocks of 640 m, x in [0, 1280], y in [-1280, 0].
GRID = BlockGrid(height=129, width=129, k=K, dx=10.0, dy=10.0)


@cache
def terrain() -> tuple[np.ndarray, dict[str, list[np.ndarray]], tuple[float, float]]:
    """A smooth 65 x 65 block with noise (errors > 0 everywhere), its fields and z range."""
    rng = np.random.default_rng(7)
    x = np.linspace(0.0, 1.0, 65)
    h = 20 * np.sin(7 * x[:, None] + 1) * np.cos(5 * x[None, :]) + 40
    h = h + rng.normal(0.0, 0.5, h.shape)
    q, b = block_errors(h, np.ones(h.shape, bool), K, CAP)
    fields = {"qiu": unpack_field(q, K, CAP), "bound": unpack_field(b, K, CAP)}
    return h, fields, (float(h.min()), float(h.max()))


def field_for(metric: str) -> list[np.ndarray]:
    return terrain()[1][FIELD_FOR_METRIC[metric]]


def zrange() -> tuple[float, float]:
    return terrain()[2]


def flat_field(k: int = K, cap: int = CAP) -> list[np.ndarray]:
    return [np.zeros((1 << min(d, cap),) * 2, np.float32) for d in range(k)]


def block_centre(block=(0, 0), grid=GRID) -> np.ndarray:
    cx, cy, _ = node_centres(grid, block, 0, np.array([0]), np.array([0]))
    return np.array([cx[0], cy[0], sum(zrange()) / 2])


# --- metrics: known answers -------------------------------------------------------------------

CAM = Camera((0, 0, 0), fov_y=90, viewport=(800, 600), near=1, far=1e5)  # focal 300 px


@pytest.mark.parametrize(
    ("centre", "expected"),
    [
        ((0, 100, 0), 300 * 2 / 100),  # D 100, theta 0, beta 0
        ((0, 100, -100), 300 * 2 * math.sqrt(0.5) / (100 * math.sqrt(2) * (1 + math.sqrt(0.5)))),
        ((100, 0, 0), 300 * 2 / (100 * 2)),  # beta 90 -> halved
        ((0, -100, 0), 300 * 2 / (100 * 2)),  # behind: beta clamped to 90
        ((0, 0, -100), 0.0),  # straight below: cos(theta) = 0
    ],
    ids=["ahead", "ahead-below-45", "side", "behind", "below"],
)
def test_qiu_known(centre, expected):
    rho = qiu_eq7(np.array([2.0]), np.array([centre], float), np.array([1.0]), CAM)
    assert rho[0] == pytest.approx(expected, rel=1e-12, abs=1e-12)


def test_qiu_guards():
    centres = np.array([[0, 0, 0], [0, 5, 0], [0, 50, 0], [0, 50, 0]], float)
    rho = qiu_eq7(np.array([1.0, 1.0, 1.0, 0.0]), centres, np.array([1.0, 10.0, 10.0, 100.0]), CAM)
    assert rho[0] == np.inf  # eye inside the bounding sphere
    assert rho[1] == np.inf
    assert np.isfinite(rho[2])
    assert rho[3] == 0.0  # no error, no split, even with the eye inside


def test_conservative_known():
    cam = Camera((0, 0, 0), fov_y=90, viewport=(600, 600), near=1, far=1e5)  # focal 300
    gain = 300 * math.sqrt(1 + 1 + 1)  # tan_half_x = tan_half_y = 1
    centres = np.array([[0, 100, 0], [0, 100, 0], [0, 5, 0], [0, -100, 0], [0, 2e5, 0]], float)
    radius = np.array([10.0, 99.5, 10.0, 10.0, 10.0])
    rho = conservative(np.array([2.0, 2.0, 2.0, 2.0, 2.0]), centres, radius, cam)
    assert rho[0] == pytest.approx(gain * 2 / 90)
    assert rho[1] == np.inf  # sphere reaches in front of the near plane
    assert rho[2] == np.inf  # eye inside
    assert rho[3] == 0.0  # wholly behind
    assert rho[4] == 0.0  # beyond far
    assert conservative(np.array([0.0]), centres[2:3], radius[2:3], cam)[0] == 0.0


def test_exact_projected_known():
    rho = exact_projected(np.array([2.5, 1.0]), np.array([[0, 10, 0], [0, -10, 0]], float), CAM)
    assert rho[0] == pytest.approx(75.0)  # 300 px * 2.5 m / 10 m
    assert np.isnan(rho[1])


def test_metric_registry():
    assert set(METRICS) == {"qiu", "conservative", "conservative-view"} == set(FIELD_FOR_METRIC)
    assert get_metric("qiu") is qiu_eq7
    assert get_metric(conservative) is conservative
    with pytest.raises(LodError, match="nope"):
        get_metric("nope")


# --- conservative is a bound ------------------------------------------------------------------


def _max_up(cam: Camera, b: np.ndarray) -> float:
    """Largest t <= 500 with B + t*up still in view (an interval from 0: the frustum is convex)."""
    lo, hi = 0.0, 500.0
    if cam.in_view(b + hi * np.array([0, 0, 1.0]))[()]:
        return hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if cam.in_view(b + mid * np.array([0, 0, 1.0]))[()]:
            lo = mid
        else:
            hi = mid
    return lo


@settings(max_examples=300, deadline=None)
@given(
    pos=st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(-50, 2e3)),
    far_origin=st.booleans(),
    yaw=st.floats(0, 360),
    pitch=st.floats(-90, 90),
    roll=st.floats(-180, 180),
    fov=st.floats(1, 170),
    viewport=st.tuples(st.integers(1, 2000), st.integers(1, 2000)),
    uvw=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0, 1)),
    frac=st.floats(0, 1),
    slack=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.floats(0, 200)),
)
def test_conservative_bounds_exact(
    pos, far_origin, yaw, pitch, roll, fov, viewport, uvw, frac, slack
):
    origin = np.array([1e7, -1e7, 0.0]) if far_origin else np.zeros(3)
    cam = Camera(
        tuple(origin + pos),
        yaw=yaw,
        pitch=pitch,
        roll=roll,
        fov_y=fov,
        viewport=viewport,
        near=0.5,
        far=5000.0,
    )
    u, v, w = uvw
    depth = cam.near + w * (cam.far - cam.near)
    b = cam.eye + depth * (
        cam.forward + u * cam.tan_half_x * cam.right + v * cam.tan_half_y * cam.up
    )
    assume(cam.in_view(b)[()])
    delta = frac * _max_up(cam, b)
    top = b + np.array([0, 0, delta])
    # a sphere holding B and B + delta*up, centred anywhere near them
    sx, sy, sz, extra = slack
    centre = 0.5 * (b + top) + np.array([sx, sy, sz]) * 20.0
    radius = max(np.linalg.norm(centre - b), np.linalg.norm(centre - top)) + extra
    exact = exact_projected(np.array([delta]), b[None], cam)[0]
    bound = conservative(np.array([delta]), centre[None], np.array([radius]), cam)[0]
    assert bound >= exact * (1 - 1e-9) - 1e-9


def test_qiu_is_not_a_bound():
    """Straight down, the node under the eye gets 0 from Qiu while its corners do move."""
    cam = Camera((0, 0, 1000), pitch=-90, fov_y=60, viewport=(1024, 768))
    centre = np.array([[0.0, 0.0, 0.0]])
    corner = np.array([[300.0, 300.0, 0.0]])
    assert qiu_eq7(np.array([5.0]), centre, np.array([430.0]), cam)[0] == 0.0
    assert exact_projected(np.array([5.0]), corner, cam)[0] > 1.0


# --- error fields -----------------------------------------------------------------------------


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
def test_subtree_errors_match_scalar(metric):
    field = field_for(metric)
    rng = np.random.default_rng(3)
    for depth in range(K):
        for below in range(K - depth):
            n = 1 << depth
            rows, cols = rng.integers(0, n, 20), rng.integers(0, n, 20)
            got = subtree_errors(field, depth, rows, cols, below)
            want = [
                subtree_error(field, depth, int(r), int(c), below)
                for r, c in zip(rows, cols, strict=True)
            ]
            np.testing.assert_array_equal(got, want)


# --- selection: a slow reference --------------------------------------------------------------


def reference_select(grid, block, field, cam, tau, metric, polygon, p, zr):
    """Recursive, one node at a time: the rule of Qiu's Sect. 3.3 as written."""
    from streamer.frustum import polygon_meets_circles

    fn = METRICS[metric]
    out = []

    def visit(d, r, c):
        cx, cy, hd = node_centres(grid, block, d, np.array([r]), np.array([c]))
        if polygon is not None and not polygon_meets_circles(polygon, cx, cy, hd)[0]:
            return
        delta = subtree_error(field, d, r, c, p) if d + p < grid.k else 0.0
        centre = np.array([[cx[0], cy[0], (zr[0] + zr[1]) / 2]])
        radius = np.array([math.hypot(hd, (zr[1] - zr[0]) / 2)])
        rho = fn(np.array([delta]), centre, radius, cam)[0]
        if rho > tau and d + p < grid.k:
            for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):
                visit(d + 1, 2 * r + dr, 2 * c + dc)
        else:
            out.append((d, r, c, min(grid.k, d + p)))

    visit(0, 0, 0)
    return sorted(out)


CAMERAS = {
    "oblique": Camera((640, -2000, 300), yaw=10, pitch=-15, far=5000),
    "inside-low": Camera((300, -300, 70), yaw=200, pitch=-30, far=5000),
    "far-side": Camera((1500, -1500, 500), yaw=300, pitch=-20, far=5000),
    "wide-roll": Camera((200, -900, 120), yaw=40, pitch=-5, roll=20, fov_y=120, far=3000),
}


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
@pytest.mark.parametrize("culling", ["triangle", "hull", "none"])
@pytest.mark.parametrize("cam_id", sorted(CAMERAS))
@pytest.mark.parametrize("patch_log2", [2, 4])
def test_select_matches_reference(metric, culling, cam_id, patch_log2):
    cam = CAMERAS[cam_id]
    polygon = {
        "triangle": view_triangle(cam),
        "hull": frustum_hull(cam, zrange()),
        "none": None,
    }[culling]
    field = field_for(metric)
    for block in GRID.blocks():
        sel = select_nodes(
            GRID, block, field, cam, 1.0, metric, polygon, patch_log2, zrange=zrange()
        )
        got = sorted(
            zip(
                sel.depth.tolist(),
                sel.row.tolist(),
                sel.col.tolist(),
                sel.level.tolist(),
                strict=True,
            )
        )
        assert got == reference_select(
            GRID, block, field, cam, 1.0, metric, polygon, patch_log2, zrange()
        )


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
def test_select_matches_reference_single_cells(metric):
    cam = CAMERAS["far-side"]
    polygon = view_triangle(cam)
    sel = select_nodes(
        GRID, (1, 1), field_for(metric), cam, 2.0, metric, polygon, 0, zrange=zrange()
    )
    got = sorted(
        zip(sel.depth.tolist(), sel.row.tolist(), sel.col.tolist(), sel.level.tolist(), strict=True)
    )
    want = reference_select(GRID, (1, 1), field_for(metric), cam, 2.0, metric, polygon, 0, zrange())
    assert got == want
    assert len(got) > 16


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
def test_select_many_matches_per_block(metric):
    """Batched over blocks with their own fields and z ranges = one block at a time."""
    base = field_for(metric)
    fields = [[a * s for a in base] for s in (1.0, 0.25, 3.0, 0.0)]
    zranges = [(0.0, 60.0), (10.0, 20.0), (-30.0, 90.0), (40.0, 40.0)]
    blocks = GRID.blocks()
    for cam in CAMERAS.values():
        poly = frustum_hull(cam, (-30.0, 90.0))
        many = select_many(GRID, blocks, fields, cam, 1.0, metric, poly, 2, zranges=zranges)
        assert len(many) == len(blocks)
        for blk, f, zr, got in zip(blocks, fields, zranges, many, strict=True):
            want = select_nodes(GRID, blk, f, cam, 1.0, metric, poly, 2, zrange=zr)
            for name in ("depth", "row", "col", "level", "delta", "rho"):
                np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
        levels = needed_levels(GRID, blocks, fields, cam, 1.0, metric, poly, 2, zranges=zranges)
        np.testing.assert_array_equal(levels, [s.needed_level for s in many])
        assert levels[3] in (0, 2)  # the flat block is coarsest or culled


def test_select_many_validation():
    cam = CAMERAS["oblique"]
    assert select_many(GRID, [], [], cam, 1.0, "qiu", None, zranges=np.zeros((0, 2))) == []
    with pytest.raises(LodError, match="2 fields for 1 blocks"):
        select_many(GRID, [(0, 0)], [field_for("qiu")] * 2, cam, 1.0, "qiu", None, zranges=(0, 1))
    other_cap = unpack_field(np.zeros(sum(4 ** min(d, 1) for d in range(K))), K, 1)
    with pytest.raises(LodError, match="one cap"):
        select_many(
            GRID,
            [(0, 0), (0, 1)],
            [field_for("qiu"), other_cap],
            cam,
            1.0,
            "qiu",
            None,
            zranges=(0, 1),
        )
    with pytest.raises(LodError, match="zranges"):
        select_many(GRID, [(0, 0)], [field_for("qiu")], cam, 1.0, "qiu", None, zranges=[(0, 1)] * 2)


# --- selection: the extremes ------------------------------------------------------------------


def level(cam, metric="conservative", tau=1.0, p=2, block=(0, 0), polygon="hull", field=None):
    poly = {"hull": frustum_hull(cam, zrange()), "triangle": view_triangle(cam), None: None}[
        polygon
    ]
    f = field_for(metric) if field is None else field
    return needed_level(GRID, block, f, cam, tau, metric, poly, p, zrange=zrange())


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
@pytest.mark.parametrize(
    ("cam", "polygon", "expected"),
    [
        (Camera((320, -320, 20), yaw=0, pitch=0, far=5000), "triangle", K),
        (Camera((320, -320, 1e7), pitch=-90, near=10, far=2e7), "hull", 2),
        (Camera((320, -320, 150), pitch=-90, far=5000), "hull", K),
        (Camera((320, -900, 70), yaw=0, pitch=-2, far=5000), "triangle", K),
        (Camera((320, 3000, 70), yaw=0, pitch=-2, far=5000), "triangle", 0),
    ],
    ids=["on-the-ground", "1e7-up", "straight-down-low", "grazing", "looking-away"],
)
def test_needed_level_extremes(metric, cam, polygon, expected):
    assert level(cam, metric, polygon=polygon) == expected


def test_straight_down_qiu_keeps_the_block_coarse():
    """Qiu's cos(theta) is 0 under the eye: high above a block's centre it never splits."""
    cam = Camera((320, -320, 1000), pitch=-90, far=5000)
    assert level(cam, "qiu") == 2
    assert level(cam, "conservative") == K


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
def test_fov_extremes(metric):
    target = block_centre()
    eye = target + np.array([0.0, -2500.0, 500.0])
    cams = {fov: Camera.look_at(eye, target, fov_y=fov, far=5000) for fov in (1, 60, 170)}
    levels = {fov: level(c, metric) for fov, c in cams.items()}
    assert levels[1] == K
    assert levels[1] >= levels[60] >= 2
    assert 2 <= levels[170] <= K
    if metric == "qiu":
        assert levels[60] >= levels[170]


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
@pytest.mark.parametrize(("p", "expected"), [(0, 0), (2, 2), (4, 4), (6, 6), (8, 6)])
def test_flat_block_is_coarsest(metric, p, expected):
    cam = Camera((320, -320, 45), yaw=0, pitch=-30, far=5000)
    sel = select_nodes(GRID, (0, 0), flat_field(), cam, 0.0, metric, None, p, zrange=(40.0, 40.0))
    assert len(sel) == 1
    assert (sel.depth[0], sel.row[0], sel.col[0]) == (0, 0, 0)
    assert sel.needed_level == expected


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
@pytest.mark.parametrize("p", [0, 1, 2, 4])
def test_tau_to_zero_is_full_resolution(metric, p):
    cam = CAMERAS["oblique"]
    sel = select_nodes(
        GRID,
        (1, 0),
        field_for(metric),
        cam,
        1e-12,
        metric,
        frustum_hull(cam, zrange()),
        p,
        zrange=zrange(),
    )
    assert len(sel) > 0
    assert (sel.level == K).all()
    assert (sel.depth == K - p).all()  # errors are > 0 everywhere: split until delta = 0
    assert (sel.delta == 0).all()


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
@pytest.mark.parametrize(("p", "expected"), [(0, 0), (2, 2), (4, 4), (7, 6)])
def test_tau_huge_is_coarsest(metric, p, expected):
    for cam_id in ("oblique", "far-side"):  # eyes outside every node's bounding sphere
        cam = CAMERAS[cam_id]
        for block in GRID.blocks():
            got = level(cam, metric, tau=1e15, p=p, block=block, polygon=None)
            assert got == expected <= p


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
def test_eye_inside_a_node_splits_whatever_tau(metric):
    cam = CAMERAS["inside-low"]  # inside block (0, 0)'s bounding sphere
    sel = select_nodes(GRID, (0, 0), field_for(metric), cam, 1e15, metric, None, 2, zrange=zrange())
    assert sel.needed_level > 2
    assert np.isfinite(sel.rho).all()  # the nodes left do not contain the eye


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
def test_needed_level_never_rises_with_tau(metric):
    for cam in CAMERAS.values():
        for block in GRID.blocks():
            levels = [level(cam, metric, tau=t, block=block) for t in (0.25, 0.5, 1, 2, 4, 16)]
            assert levels == sorted(levels, reverse=True)


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
@pytest.mark.parametrize("polygon", ["triangle", "hull"])
def test_far_from_origin_same_selection(metric, polygon):
    far = replace(GRID, x0=1e7, y0=1e7)
    shift = np.array([1e7, 1e7, 0.0])
    for cam in CAMERAS.values():
        moved = replace(cam, position=tuple(np.array(cam.position) + shift))
        for block in GRID.blocks():
            args = (field_for(metric), 0.8, metric)
            poly_a = view_triangle(cam) if polygon == "triangle" else frustum_hull(cam, zrange())
            poly_b = (
                view_triangle(moved) if polygon == "triangle" else frustum_hull(moved, zrange())
            )
            a = select_nodes(GRID, block, *args[:1], cam, *args[1:], poly_a, 2, zrange=zrange())
            b = select_nodes(far, block, *args[:1], moved, *args[1:], poly_b, 2, zrange=zrange())
            for name in ("depth", "row", "col", "level"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
            np.testing.assert_allclose(a.rho, b.rho, rtol=1e-6)


def test_culled_block():
    cam = Camera((320, -320, 100), yaw=0, pitch=-10, far=300)  # sees only part of block (0, 0)
    poly = view_triangle(cam)
    sel = select_nodes(GRID, (1, 1), field_for("qiu"), cam, 1.0, "qiu", poly, zrange=zrange())
    assert len(sel) == 0
    assert sel.needed_level == 0


def test_custom_metric_is_pluggable():
    def always(delta, centre, radius, camera):
        return np.where(delta > 0, 1e9, 0.0)

    sel = select_nodes(
        GRID, (0, 0), field_for("qiu"), CAMERAS["oblique"], 1.0, always, None, 2, zrange=zrange()
    )
    assert len(sel) == 4 ** (K - 2)
    assert (sel.level == K).all()


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"tau": -1.0}, "tau.*-1.0"),
        ({"tau": float("nan")}, "tau"),
        ({"patch_log2": -1}, "patch_log2.*-1"),
        ({"patch_log2": 1.5}, "patch_log2.*1.5"),
        ({"metric": "nope"}, "nope"),
        ({"block": (2, 0)}, r"block \(2, 0\)"),
        ({"zrange": (5.0, 1.0)}, "zrange"),
        ({"field": flat_field(k=5)}, "depth 0..5"),
        ({"field": [np.zeros((2, 2))] + flat_field()[1:]}, r"field\[0\]"),
    ],
    ids=[
        "tau-negative",
        "tau-nan",
        "patch-negative",
        "patch-float",
        "metric",
        "block",
        "zrange",
        "field-depths",
        "field-shape",
    ],
)
def test_invalid_selection(kw, match):
    args = {
        "grid": GRID,
        "block": (0, 0),
        "field": field_for("qiu"),
        "camera": CAMERAS["oblique"],
        "tau": 1.0,
        "metric": "qiu",
        "polygon": None,
        "patch_log2": 2,
        "zrange": zrange(),
        **kw,
    }
    with pytest.raises(LodError, match=match) as info:
        select_nodes(**args)
    assert isinstance(info.value, ValueError)
    assert isinstance(info.value, StreamerError)
