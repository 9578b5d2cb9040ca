"""The fast per-frame needed levels equal the reference selection's."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from lod_reference import select_many

from streamer.camera import Camera
from streamer.levels import PatchErrorTable
from tiler.errors import KernelUnavailableError
from tiler.grid import BlockGrid
from tiler.static_error import make_monotone


def _field(rng, k, cap):
    per = make_monotone([rng.random((1 << d, 1 << d)) * 40.0 / (d + 1) for d in range(k)])
    out = []
    for d, a in enumerate(per):
        if d > cap:
            n = 1 << cap
            r = a.shape[0] // n
            a = a.reshape(n, r, n, r).max(axis=(1, 3))
        out.append(a.astype(np.float32))
    return out


CAMERAS = [
    Camera((500.0, -200.0, 300.0), yaw=10, pitch=-20, far=5000),
    Camera((1000.0, 1000.0, 50.0), yaw=200, pitch=-5, far=3000, fov_y=30),
    Camera((100.0, 100.0, 5000.0), yaw=0, pitch=-89, far=20000, fov_y=90),
    Camera((1e7 + 500.0, 1e7 - 200.0, 300.0), yaw=10, pitch=-20, far=5000),
]


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
@pytest.mark.parametrize("cam_i", range(len(CAMERAS)), ids=["oblique", "low", "down", "far-1e7"])
@pytest.mark.parametrize("tau", [0.0, 0.5, 2.0, 1e9])
def test_table_matches_select_many(metric, cam_i, tau):
    rng = np.random.default_rng(cam_i)
    k, cap, p = 7, 4, 2
    cam = CAMERAS[cam_i]
    x0 = 1e7 if cam.position[0] > 1e6 else 0.0
    grid = BlockGrid(
        height=8 * 128 + 1, width=8 * 128 + 1, k=k, x0=x0, y0=x0 + 1000.0, dx=1.5, dy=1.5
    )
    blocks = [(r, c) for r in range(8) for c in range(8)]
    fields = [_field(rng, k, cap) for _ in blocks]
    zr = np.stack([rng.random(len(blocks)) * 50, 50 + rng.random(len(blocks)) * 100], axis=1)
    table = PatchErrorTable(k, p, capacity=4)  # grows
    for b, f in zip(blocks, fields, strict=True):
        table.add(b, f)
    levels, _ = table.needed_levels(grid, blocks, cam, tau, metric, zr)
    ref = select_many(grid, blocks, fields, cam, tau, metric, None, p, zranges=zr)
    np.testing.assert_array_equal(levels, [s.needed_level for s in ref])


def test_remove_reuses_slots():
    t = PatchErrorTable(4, 1, capacity=1)
    f = [np.zeros((1 << min(d, 2),) * 2, np.float32) for d in range(4)]
    t.add((0, 0), f)
    t.add((0, 1), f)
    t.remove((0, 0))
    t.add((5, 5), f)
    assert len(t) == 2 and (5, 5) in t and (0, 0) not in t


def test_depth_array_is_what_delta_indexes():
    rng = np.random.default_rng(3)
    t = PatchErrorTable(5, 2, capacity=1)  # grows: the arrays are replaced
    for b in ((0, 0), (0, 1), (2, 3)):
        t.add(b, _field(rng, 5, 4))
    slots = t.slots([(2, 3), (0, 0)])
    for d in range(t.depths):
        rows = rng.integers(0, 1 << d, 2)
        cols = rng.integers(0, 1 << d, 2)
        got = t.depth_array(d)[slots, rows, cols].astype(np.float64)
        np.testing.assert_array_equal(got, t.delta(slots, d, rows, cols))
    assert t.depth_array(t.depths) is None  # full resolution: delta is 0 there
    assert not t.delta(slots, t.depths, np.zeros(2, int), np.zeros(2, int)).any()


def _table_and_grid(seed: int, x0: float, k: int = 7, cap: int = 4, p: int = 2):
    rng = np.random.default_rng(seed)
    grid = BlockGrid(
        height=8 * 128 + 1, width=8 * 128 + 1, k=k, x0=x0, y0=x0 + 1000.0, dx=1.5, dy=1.5
    )
    blocks = [(r, c) for r in range(8) for c in range(8)]
    table = PatchErrorTable(k, p, capacity=4)
    for b in blocks:
        f = _field(rng, k, cap)
        if b == (3, 3):
            f = [np.zeros_like(a) for a in f]  # flat: delta 0 everywhere
        if b == (4, 4):
            f[0][:] = np.inf  # a mixed (nodata) node
        table.add(b, f)
    zr = np.stack([rng.random(len(blocks)) * 50, 50 + rng.random(len(blocks)) * 100], axis=1)
    return grid, blocks, table, zr


@pytest.fixture(scope="module")
def levels_nb():
    pytest.importorskip("numba")
    from streamer import levels

    mod = levels._load_numba()
    assert mod is not None
    return mod


@pytest.mark.parametrize("cam_i", range(len(CAMERAS)), ids=["oblique", "low", "down", "far-1e7"])
@pytest.mark.parametrize("tau", [0.0, 0.5, 2.0, 1e9])
def test_compiled_needed_levels_equal_the_numpy_reference(levels_nb, monkeypatch, cam_i, tau):
    cam = CAMERAS[cam_i]
    grid, blocks, table, zr = _table_and_grid(cam_i, 1e7 if cam.position[0] > 1e6 else 0.0)
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numpy")
    ref = table.needed_levels(grid, blocks, cam, tau, "qiu", zr)
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numba")
    got = table.needed_levels(grid, blocks, cam, tau, "qiu", zr)
    for a, b in zip(ref, got, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)  # bit for bit
    lv, rho = table.needed_levels(grid, blocks, cam, tau, "qiu", zr, with_rho=False)
    assert np.array_equal(lv, ref[0]) and not rho.any()


def test_compiled_needed_levels_positive_control(levels_nb, monkeypatch):
    """A kernel whose eye is one ulp off is caught by the same comparison."""
    from streamer import levels

    cam = CAMERAS[0]
    grid, blocks, table, zr = _table_and_grid(0, 0.0)
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numpy")
    ref = table.needed_levels(grid, blocks, cam, 0.5, "qiu", zr)
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numba")

    def off(*args):
        args = list(args)
        args[11] = np.nextafter(args[11], np.inf)  # the eye
        return levels_nb.qiu_levels(*args)

    monkeypatch.setattr(levels, "_load_numba", lambda: SimpleNamespace(qiu_levels=off))
    got = table.needed_levels(grid, blocks, cam, 0.5, "qiu", zr)
    assert np.array_equal(ref[0], got[0]) and not np.array_equal(ref[1], got[1])
    monkeypatch.setattr(levels, "_load_numba", lambda: levels_nb)
    assert np.array_equal(ref[1], table.needed_levels(grid, blocks, cam, 0.5, "qiu", zr)[1])


def test_auto_uses_the_kernel_only_once_warmed_up(levels_nb, monkeypatch):
    from streamer import levels

    monkeypatch.setenv("TERRASTREAM_KERNELS", "auto")
    monkeypatch.setattr(levels, "_READY", [])
    assert levels.kernels() is None  # the caller never waits for numba's import
    assert levels.warm_up(PatchErrorTable(7, 2)) and levels.kernels() is levels_nb
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numpy")
    assert levels.kernels() is None and not levels.warm_up(PatchErrorTable(7, 2))
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numba")
    monkeypatch.setattr(levels, "_load_numba", lambda: None)
    with pytest.raises(KernelUnavailableError):
        levels.kernels()
