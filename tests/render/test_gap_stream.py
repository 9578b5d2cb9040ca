"""The nodata rule "gap" streams what it draws: a session's planner (a
:class:`streamer.levels.PatchErrorTable` holding gap widths) gives every block exactly the finest
level the selection (:func:`render.select.select_patches` with ``gaps``) draws in it. Positive
controls: a planner without the gap widths gives some block less than is drawn; the rule
``"full"`` gives some block more. Pure: no GL context."""

from __future__ import annotations

import numpy as np
import pytest

from render.select import PatchTable, select_patches
from streamer.camera import Camera
from streamer.levels import PatchErrorTable
from streamer.nodata import gap_widths, mixed_nodes, raise_mixed
from tiler.grid import BlockGrid
from tiler.static_error import make_monotone

K, P, ROWS = 7, 2, 6
GRID = BlockGrid(
    height=ROWS * 128 + 1, width=ROWS * 128 + 1, k=K, x0=0.0, y0=1000.0, dx=1.5, dy=1.5
)
BLOCKS = [(r, c) for r in range(ROWS) for c in range(ROWS)]
CAMERAS = {
    "oblique": Camera((500.0, -200.0, 300.0), yaw=10, pitch=-20, far=5000),
    "low": Camera((600.0, 600.0, 60.0), yaw=200, pitch=-5, far=3000, fov_y=30),
    "down": Camera((576.0, 424.0, 3000.0), yaw=0, pitch=-89, far=20000, fov_y=90),
    "wide": Camera((576.0, 424.0, 1200.0), yaw=30, pitch=-60, far=20000, fov_y=120),
    "far": Camera((576.0, 424.0, 9000.0), yaw=0, pitch=-89, far=50000, fov_y=60),
}
TAUS = [0.0, 0.5, 1.0, 4.0]


def _scene(seed: int = 5):
    """Per block: its stored error field, its validity mask (``None``: no nodata) and the
    blocks' height ranges. A third of the blocks have no nodata, the others a disc or strips."""
    rng = np.random.default_rng(seed)
    n = (1 << K) + 1
    rr, cc = np.mgrid[0:n, 0:n]
    fields, masks = [], []
    for i, _b in enumerate(BLOCKS):
        per = make_monotone([rng.random((1 << d, 1 << d)) * 20.0 / (d + 1) for d in range(K)])
        fields.append([a.astype(np.float32) for a in per])
        kind = i % 3
        if kind == 0:
            masks.append(None)
        elif kind == 1:
            r0, c0, rad = rng.integers(0, n, 2).tolist() + [int(rng.integers(4, 40))]
            masks.append((rr - r0) ** 2 + (cc - c0) ** 2 > rad * rad)
        else:
            masks.append(((cc // int(rng.integers(3, 30))) % 2 == 0) | (rr < n // 2))
    zr = np.stack([rng.random(len(BLOCKS)) * 50, 50 + rng.random(len(BLOCKS)) * 100], axis=1)
    return fields, masks, zr


SCENE = _scene()


def _gaps(mask):
    return None if mask is None else gap_widths(mask, K, GRID.dx, GRID.dy)


def drawn_levels(camera: Camera, tau: float, metric: str) -> np.ndarray:
    """The finest level the selection draws in each block under the rule "gap" (every level
    resident, no culling)."""
    fields, masks, zr = SCENE
    table, gaps = PatchTable(K, P), PatchTable(K, P)
    for b, f, m in zip(BLOCKS, fields, masks, strict=True):
        table.add(b, f)
        g = _gaps(m)
        gaps.add(b, g if g is not None else [np.zeros((1 << d,) * 2, np.float32) for d in range(K)])
    blk = np.array(BLOCKS, np.int64)
    sel = select_patches(GRID, blk, table, camera, tau, metric, None, resident=np.full(len(blk), K),
                         zranges=zr, gaps=gaps)  # fmt: skip
    out = np.full(len(blk), -1, np.int64)
    np.maximum.at(out, sel.block, sel.level)
    return out


def planned_levels(camera: Camera, tau: float, metric: str, rule: str | None) -> np.ndarray:
    """A session planner's needed levels under ``rule`` (``None``: stored errors only)."""
    fields, masks, zr = SCENE
    table = PatchErrorTable(K, P, capacity=4, gaps=rule == "gap")  # grows
    for b, f, m in zip(BLOCKS, fields, masks, strict=True):
        if rule == "full" and m is not None:
            table.add(b, raise_mixed(f, mixed_nodes(m, K)))
        elif rule == "gap":
            table.add(b, f, _gaps(m))
        else:
            table.add(b, f)
    return table.needed_levels(GRID, BLOCKS, camera, tau, metric, zr)[0]


@pytest.fixture(params=["numpy", "numba"])
def kernels(request, monkeypatch):
    """The planner's walk: numpy, or compiled for the blocks without gap widths."""
    if request.param == "numba":
        pytest.importorskip("numba")
    monkeypatch.setenv("TERRASTREAM_KERNELS", request.param)
    return request.param


@pytest.mark.parametrize("metric", ["qiu", "conservative"])
@pytest.mark.parametrize("cam", list(CAMERAS))
@pytest.mark.parametrize("tau", TAUS)
def test_gap_planner_levels_are_the_drawn_levels(kernels, cam, tau, metric):
    camera = CAMERAS[cam]
    drawn = drawn_levels(camera, tau, metric)
    assert (drawn >= 0).all()
    np.testing.assert_array_equal(planned_levels(camera, tau, metric, "gap"), drawn)


def test_positive_controls_without_gaps_too_little_with_full_too_much(kernels):
    """Summed over the views: the stored errors alone plan some block coarser than the gap rule
    draws it (the comparison above would fail); the rule "full" plans some block finer (the
    levels the gap rule does not stream)."""
    short = extra = 0
    for camera in CAMERAS.values():
        for tau in TAUS[1:]:
            drawn = drawn_levels(camera, tau, "qiu")
            short += int((planned_levels(camera, tau, "qiu", None) < drawn).sum())
            full = planned_levels(camera, tau, "qiu", "full")
            assert (full >= drawn).all()
            extra += int((full > drawn).sum())
    assert short > 0 and extra > 0, (short, extra)


def test_gap_widths_need_a_gap_table():
    fields, masks, _ = SCENE
    with pytest.raises(ValueError, match="gaps=True"):
        PatchErrorTable(K, P).add(BLOCKS[1], fields[1], _gaps(masks[1]))
