"""Pure known-answer tests of ``chunk_tess`` (no GL: they run without an EGL context)."""

from __future__ import annotations

import numpy as np
import pytest

from render.strategies.chunk_tess import kim_metric, outer_factors, tess_triangles
from streamer.camera import Camera

SIZE = (128, 96)


def test_outer_factors_follow_the_neighbour_levels():
    # 8 cells; north neighbour 2x coarser, east same, south 4x coarser, west same
    assert outer_factors(3, (1, 0, 2, 0)) == (8, 4, 8, 2)  # (W, N, E, S) = GL outer 0..3
    assert tess_triangles(np.array([3]), np.array([[1, 0, 2, 0]]))[0] == 2 * 36 + 24 + 22
    # unsnapped: the same count as the 2 n^2 grid
    n = tess_triangles(np.arange(0, 7), np.zeros((7, 4), np.int64))
    assert n.tolist() == [2 * 4**c for c in range(7)]


def test_kim_metric_projects_the_nearest_sphere_point():
    cam = Camera((0.0, 0.0, 1000.0), pitch=-90.0, viewport=SIZE, near=1.0, far=1e5)
    # sphere of radius 100 straight below: nearest point (0, 0, 100) at 900 m
    rho = kim_metric(np.array([10.0]), np.array([[0.0, 0.0, 0.0]]), np.array([100.0]), cam)
    assert rho[0] == 0.0  # seen from straight above a vertical error does not move the point
    off = np.array([[300.0, 0.0, 0.0]])
    got = kim_metric(np.array([10.0]), off, np.array([100.0]), cam)[0]
    to_eye = cam.eye - off[0]
    p = off[0] + 100.0 * to_eye / np.linalg.norm(to_eye)
    x0, y0, _ = cam.project(p[None])
    x1, y1, _ = cam.project((p + [0, 0, 10.0])[None])
    assert got == pytest.approx(float(np.hypot(x1 - x0, y1 - y0)[0])) and got > 0
    inside = kim_metric(np.array([1.0]), np.array([[0.0, 0.0, 950.0]]), np.array([100.0]), cam)
    assert np.isinf(inside[0])


def test_kim_metric_is_exact_projected_of_the_nearest_point():
    # the component-wise camera coordinates against Camera.project's matrix product
    from streamer.lod import exact_projected

    rng = np.random.default_rng(0)
    n = 4000
    for yaw in (0.0, 75.0, 190.0, 300.0):
        cam = Camera((5e5, 5e6, 900.0), yaw=yaw, pitch=-10.0, viewport=(1024, 768), far=5e4)
        c = np.stack(
            [rng.uniform(4.9e5, 5.1e5, n), rng.uniform(4.99e6, 5.01e6, n), rng.uniform(0, 1500, n)],
            1,
        )
        r, d = rng.uniform(10, 3000, n), rng.gamma(1.0, 5.0, n)
        d[::50] = 0.0
        to_eye = cam.eye - c
        dist = np.linalg.norm(to_eye, axis=1)
        inside = dist <= r
        p = c + to_eye * (r / np.where(inside, 1.0, dist))[:, None]
        with np.errstate(invalid="ignore"):
            want = exact_projected(d, p, cam)
        want = np.where(d == 0, 0.0, np.where(inside | ~np.isfinite(want), np.inf, want))
        got = kim_metric(d, c, r, cam)
        fin = np.isfinite(want)
        assert np.array_equal(fin, np.isfinite(got)) and np.array_equal(got[~fin], want[~fin])
        # the pixel difference cancels: rounding shows at ~1e-13 px (relative up to ~1e-8)
        np.testing.assert_allclose(got[fin], want[fin], rtol=1e-7, atol=1e-9)
        assert fin.sum() > n // 4 and (~fin).sum() > 0  # both kinds occur


def test_start_depth_bounds_the_level_difference_of_chunks():
    from render.strategies.chunk_tess import start_depth

    for k in range(0, 15):
        for c in range(0, 7):
            s = start_depth(k, c)
            # chunks lie at depths s..max(s, k - c); adjacent ones differ by at most c levels
            assert s >= 0 and max(0, k - c) - s <= c and (s == 0 or k - c - s == c)
    assert start_depth(12, 5) == 2 and start_depth(10, 5) == 0  # the paper's 2 at k = 12
