"""Loading ``jung-han``'s compiled kernels off the render thread: one selection of a small
synthetic scene through the compiled path, which passes every kernel the argument types a
real selection passes, so numba loads (or compiles) them here. Without it the render
thread's first compiled selection after the viewer's warm-up spent ~80 ms loading them."""

from __future__ import annotations

import numpy as np

from render.strategies.jung_han.selection import JungHanSelector
from streamer.camera import Camera
from tiler.grid import BlockGrid

Block = tuple[int, int]


class _Scene:
    """The frame services a jung-han selection reads, for 2×2 blocks of ``2**k + 1`` samples
    of rough synthetic terrain (one block at a coarser level, one with a nodata hole)."""

    def __init__(self, k: int = 4) -> None:
        self.k = k
        n = 2 * (1 << k) + 1
        rng = np.random.default_rng(0)
        self.heights = rng.normal(0.0, 20.0, (n, n)).cumsum(0).cumsum(1) / n + 100.0
        self.grid = BlockGrid(height=n, width=n, k=k, x0=0.0, y0=float(n - 1), dx=1.0, dy=1.0)
        self.terrain_zrange = (float(self.heights.min()), float(self.heights.max()))
        self.levels = {(0, 0): k, (0, 1): k - 1, (1, 0): k, (1, 1): k}
        hole = np.ones(((1 << k) + 1,) * 2, bool)
        hole[3:6, 3:6] = False
        self.masks: dict[Block, np.ndarray | None] = {(1, 1): hole}

    def block_grid(self, block: Block, level: int) -> np.ndarray:
        s, st = 1 << self.k, 1 << (self.k - level)
        r, c = block[0] * s, block[1] * s
        return self.heights[r : r + s + 1 : st, c : c + s + 1 : st].copy()

    def mask(self, block: Block) -> np.ndarray | None:
        return self.masks.get(block)

    def gpu_level(self, block: Block) -> int:
        return self.levels.get(block, -1)

    def drawable(self, resident: dict[Block, int] | None = None) -> list[tuple[Block, int]]:
        return sorted(self.levels.items())


def warm_up_selection() -> int:
    """Run one compiled selection of the synthetic scene (numba's kernels load here); its
    triangle count (> 0)."""
    scene = _Scene()
    n = scene.grid.width - 1
    camera = Camera.look_at(
        (0.3 * n, -0.6 * n, 3.0 * scene.terrain_zrange[1]),
        (0.5 * n, 0.5 * n, scene.terrain_zrange[0]),
        viewport=(64, 48),
        near=0.5,
    )
    sel, _ = JungHanSelector(scene, kernels="numba").select(camera, 0.5)
    return len(sel.tri)
