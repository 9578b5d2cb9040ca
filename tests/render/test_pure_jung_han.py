"""Pure known-answer tests of ``jung_han`` (no GL: they run without an EGL context)."""

from __future__ import annotations

import numpy as np
import pytest

from render.strategies.jung_han import (
    NE,
    NW,
    SE,
    SW,
    node_index,
    node_position,
    parent_index,
    projected_bound,
    vertex_deltas,
    vertex_errors,
)
from streamer.camera import Camera

SIZE = (128, 96)


X0, Y0 = 500015.0, 5000000.0 - 15


def _nadir(x, y, h, yaw=0.0) -> Camera:
    return Camera((x, y, h), yaw=yaw, pitch=-90.0, viewport=SIZE, near=5.0, far=5e4)


def _oblique() -> Camera:
    return Camera.look_at(
        (X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0), viewport=SIZE, near=5.0
    )


def test_block_index_is_concatenated_quadrant_codes():
    # the paper's Figure 4: 3rd quadrant of the root (11, NE), then its 2nd quadrant (10, NW)
    assert node_index(0, 2, 2) == 0b1110 == 14
    assert tuple(int(v) for v in node_position(14, 2)) == (0, 2)
    assert parent_index(14) == 0b11 and tuple(int(v) for v in node_position(3, 1)) == (0, 1)
    # Figure 5: lower-left vertex x = sum of second bits * widths, y (up) = first bits * widths
    row, col = node_position(14, 2)
    width = 8  # a depth-2 block of a 32-cell tree
    assert (int(col) * width, (4 - 1 - int(row)) * width) == (16, 24)
    assert [node_index(r, c, 1) for r, c in ((1, 0), (1, 1), (0, 0), (0, 1))] == [SW, SE, NW, NE]
    for depth in (1, 3, 5):
        idx = np.arange(4**depth)
        r, c = node_position(idx, depth)
        assert sorted((r * 2**depth + c).tolist()) == idx.tolist()
        np.testing.assert_array_equal(node_index(r, c, depth), idx)
        pr, pc = node_position(parent_index(idx), depth - 1)
        np.testing.assert_array_equal(pr, r // 2)
        np.testing.assert_array_equal(pc, c // 2)


def test_vertex_deltas_known_values():
    g = np.arange(25, dtype=np.float64).reshape(5, 5) ** 1.5  # R = 2, no linear accidents
    d = vertex_deltas(g)
    assert (d[[0, 0, 4, 4], [0, 4, 0, 4]] == 0).all()  # level-0 corners
    assert d[0, 2] == pytest.approx((g[0, 0] + g[0, 4]) / 2 - g[0, 2])  # level-1 edge midpoint
    assert d[2, 2] == pytest.approx((g[0, 0] + g[4, 4]) / 2 - g[2, 2])  # root centre: NW-SE
    assert d[0, 1] == pytest.approx((g[0, 0] + g[0, 2]) / 2 - g[0, 1])
    assert d[3, 4] == pytest.approx((g[2, 4] + g[4, 4]) / 2 - g[3, 4])
    # centres: quadrants 0 (SW) and 3 (NE) keep the SW-NE diagonal, 1 (SE) and 2 (NW) NW-SE
    assert d[1, 1] == pytest.approx((g[0, 0] + g[2, 2]) / 2 - g[1, 1])  # NW
    assert d[1, 3] == pytest.approx((g[2, 2] + g[0, 4]) / 2 - g[1, 3])  # NE
    assert d[3, 1] == pytest.approx((g[4, 0] + g[2, 2]) / 2 - g[3, 1])  # SW
    assert d[3, 3] == pytest.approx((g[2, 2] + g[4, 4]) / 2 - g[3, 3])  # SE
    m = g.copy()
    m[0, 0:3] = np.nan  # a masked vertex with masked ends: 0; partly masked: never removed
    dm = vertex_deltas(m)
    assert dm[0, 1] == 0.0 and np.isinf(dm[0, 2]) and np.isinf(dm[1, 1])
    assert dm[3, 3] == d[3, 3]


def test_vertex_error_is_the_projected_distance():
    cam = Camera.look_at((0.0, -500.0, 300.0), (0.0, 0.0, 0.0), viewport=SIZE, near=1.0)
    b = np.array([[40.0, 20.0, 10.0], [-30.0, 60.0, 0.0], [0.0, -900.0, 300.0]])
    delta = np.array([5.0, -2.0, 3.0])
    got = vertex_errors(delta, b, cam)
    x0, y0, _ = cam.project(b)
    x1, y1, _ = cam.project(b + np.c_[np.zeros((3, 2)), delta])
    np.testing.assert_allclose(got[:2], np.hypot(x1 - x0, y1 - y0)[:2])
    assert got[0] > 0 and np.isinf(got[2])  # behind the eye: never removed
    assert vertex_errors(np.array([0.0]), b[2:], cam)[0] == 0.0


def test_closed_form_vertex_error_equals_the_two_projections():
    """``vertex_errors``' closed form is the pixel distance of the two projections
    (``exact_projected``) at the extremes: coordinates near 1e7 m, heights from -11 km to
    +9 km, FOV 1-170°, δ from 1 mm to 1 km; ∞ where either point is at or behind the eye."""
    from streamer.lod import exact_projected

    rng = np.random.default_rng(4)
    worst, n_inf = 0.0, 0
    for _ in range(40):
        off = float(rng.choice([0.0, 1e7]))
        eye = (off + rng.uniform(-3e3, 3e3), off + rng.uniform(-3e3, 3e3), rng.uniform(-11e3, 9e3))
        cam = Camera(eye, yaw=rng.uniform(0, 360), pitch=rng.uniform(-90, 30), viewport=SIZE,
                     fov_y=rng.uniform(1, 170), near=0.1)  # fmt: skip
        p = np.c_[off + rng.uniform(-2e4, 2e4, (300, 2)), rng.uniform(-11e3, 9e3, 300)]
        d = rng.choice([-1.0, 1.0], 300) * 10.0 ** rng.uniform(-3, 3, 300)
        got = vertex_errors(d, p, cam)
        with np.errstate(invalid="ignore"):
            want = exact_projected(d, p, cam)
        ok = np.isfinite(want)
        n_inf += int((~ok).sum())
        assert np.all(np.isinf(got[~ok]))
        # the two projections lose up to ~1e-12 px to cancellation: compare in absolute terms
        worst = max(worst, float(np.max(np.abs(got[ok] - want[ok]) / (1.0 + want[ok]))))
        # positive control: 0.1 % more δ is seen
        assert np.any(np.abs(vertex_errors(1.001 * d, p, cam)[ok] - want[ok]) > 1e-4 * want[ok])
    assert worst < 1e-6 and n_inf > 0


def test_pruning_bound_covers_every_exact_error():
    rng = np.random.default_rng(1)
    for cam in (_oblique(), _nadir(X0 + 900, Y0 - 900, 2500.0)):
        n = 400
        x0 = X0 + rng.uniform(-500, 3000, n)
        y0 = Y0 - rng.uniform(-500, 4000, n)
        size = rng.choice([30.0, 120.0, 480.0], n)
        zlo = rng.uniform(500, 900, n)
        zhi = zlo + rng.uniform(0, 200, n)
        dmax = rng.uniform(0, 40, n)
        bound = projected_bound(cam, dmax, x0, x0 + size, y0, y0 + size, zlo, zhi)
        for _ in range(20):
            u = rng.uniform(0, 1, (4, n))
            p = np.stack([x0 + u[0] * size, y0 + u[1] * size, zlo + u[2] * (zhi - zlo)], -1)
            z = p[:, 2] + (u[3] - 0.5) * 2 * dmax  # B + δ inside the box
            ok = (z >= zlo) & (z <= zhi)
            err = vertex_errors(np.where(ok, z - p[:, 2], 0.0), p, cam)
            assert (err <= bound).all()
        assert np.isfinite(bound).any() and (bound[dmax > 0] > 0).all()
