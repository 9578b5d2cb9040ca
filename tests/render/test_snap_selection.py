"""Snapped edges in the selection (:func:`render.select.stitch` with ``tau``): on a crop of a
real DEM (N44W072, 129² samples, 90 m) ``conservative-view`` with node boxes stays <= tau in
measured screen error on every sampled view; positive control: without the snapping check
(``tau=None``: the stored patch error alone) the same views exceed tau. Pure numpy."""

from __future__ import annotations

import numpy as np
import pytest
from demtools import shared_file

from render import measure
from render.node_boxes import NodeBoxes
from render.select import PatchTable, select_patches, stitch
from streamer.camera import Camera
from tiler.grid import BlockGrid
from tiler.static_error import bound_errors

K, P, TAU = 7, 2, 0.5
GRID = BlockGrid(height=129, width=129, k=K, x0=0.0, y0=129 * 90.0, dx=90.0, dy=90.0)


@pytest.fixture(scope="module")
def crop():
    raw = np.fromfile(shared_file("N44W072.hgt"), dtype=">i2")
    n = int(round(np.sqrt(raw.size)))
    h = raw.reshape(n, n).astype(np.float64)[869 : 869 + 129, 91 : 91 + 129]
    bound = bound_errors(h, np.ones(h.shape, bool), K)
    table = PatchTable(K, P)
    table.add((0, 0), bound)
    boxes = NodeBoxes(K, P)
    boxes.update((0, 0), K, h, bound, (h.min(), h.max()))
    return h, table, boxes


def cameras(h: np.ndarray, n: int = 10) -> list[Camera]:
    rng = np.random.default_rng(3)
    rng.integers(0, 1072, 2)  # the draw that picked the crop (869, 91)
    out = []
    for _ in range(n):
        eye = (rng.uniform(-1500, 13000), rng.uniform(-1500, 13000),
               rng.uniform(h.max() + 100, h.max() + 3000))  # fmt: skip
        target = (rng.uniform(1500, 10000), rng.uniform(1500, 10000), float(h.mean()))
        fov = float(rng.choice([45.0, 90.0, 120.0]))
        out.append(Camera.look_at(eye, target, fov_y=fov, viewport=(128, 96), near=5.0, far=2e5))
    return out


def worst(crop, check: bool) -> list[float]:
    """Measured max screen error / tau per view."""
    h, table, boxes = crop
    zr = np.array([[h.min(), h.max()]])
    kw = {"resident": [K], "zranges": zr, "boxes": boxes}
    out = []
    for cam in cameras(h):
        p = select_patches(GRID, [(0, 0)], table, cam, TAU, "conservative-view", None, **kw)
        p = stitch(p, GRID, table, cam, "conservative-view", tau=TAU if check else None, **kw)
        e = measure.screen_errors(p, GRID, cam, lambda b: h)
        out.append(float(e.max()) / TAU if e.size else 0.0)
    return out


def test_snapped_edges_keep_the_bound(crop):
    w = worst(crop, check=True)
    assert max(w) <= 1.0, w
    assert sum(x > 0.5 for x in w) >= 5, w  # the bound is exercised, not only met


def test_positive_control_without_the_snapping_check_tau_is_exceeded(crop):
    w = worst(crop, check=False)
    assert max(w) > 1.0, w
