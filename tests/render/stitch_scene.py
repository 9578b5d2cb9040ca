"""The multi-block scene the stitch tests share (test_stitch_rounds, test_stitch_fast): 3 × 3
blocks of 33² rough terrain held at mixed levels, with node boxes, and random cameras."""

from __future__ import annotations

import numpy as np

from render.node_boxes import NodeBoxes
from render.select import PatchTable
from streamer.camera import Camera
from tiler.grid import BlockGrid
from tiler.static_error import bound_errors

K = 5
FIELDS = ("block", "depth", "row", "col", "level", "delta", "rho", "snap")
GRID = BlockGrid(height=3 * 32 + 1, width=3 * 32 + 1, k=K, x0=0.0, y0=97 * 30.0, dx=30.0, dy=30.0)
BLOCKS = [(r, c) for r in range(3) for c in range(3)]
RES = [K, K, K - 1, K, K - 2, K, K, K - 1, K]  # resident level of each block


def heights() -> np.ndarray:
    """The scene's 97² heights (smooth hills plus a random walk down the rows)."""
    rng = np.random.default_rng(11)
    y, x = np.mgrid[0:97, 0:97] / 96.0
    return 400 * np.sin(5 * x) * np.cos(4 * y) + 150 * rng.standard_normal((97, 97)).cumsum(0) / 9


def build(p: int, masked: tuple = (), res: list[int] = RES):
    """``(PatchTable, NodeBoxes, zranges)`` of the scene with ``2**p``-cell patches; blocks in
    ``masked`` get two nodata holes (and their boxes the validity of their held level)."""
    h = heights()
    table, boxes, zr = PatchTable(K, p), NodeBoxes(K, p), []
    for (r, c), lv in zip(BLOCKS, res, strict=True):
        g = h[r * 32 : r * 32 + 33, c * 32 : c * 32 + 33]
        valid = np.ones(g.shape, bool)
        if (r, c) in masked:
            valid[5:11, 20:29] = valid[22:25, 3:30] = False
        bound = bound_errors(g, valid, K)
        table.add((r, c), bound)
        step = 1 << (K - lv)
        v = valid[::step, ::step] if (r, c) in masked else None
        boxes.update((r, c), lv, g[::step, ::step], bound, (g.min(), g.max()), v)
        zr.append((g.min(), g.max()))
    return table, boxes, np.array(zr)


def cameras() -> list[Camera]:
    """Eight random oblique cameras over the scene (FOV 45°, 90° or 150°, 160 × 120)."""
    rng = np.random.default_rng(5)
    out = []
    for _ in range(8):
        eye = (rng.uniform(-500, 3400), rng.uniform(-500, 3400), rng.uniform(300, 2500))
        target = (rng.uniform(600, 2300), rng.uniform(600, 2300), 0.0)
        fov = float(rng.choice([45.0, 90.0, 150.0]))
        out.append(Camera.look_at(eye, target, fov_y=fov, viewport=(160, 120), near=2.0, far=2e4))
    return out
