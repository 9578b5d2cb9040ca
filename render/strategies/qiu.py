"""``qiu`` — the renderer's own CLOD (Qiu et al. 3.3): quadtree patches of ``2**patch_log2``
cells drawn as instanced grids, edge snapping against coarser neighbours. This module only
adapts :class:`render.renderer.TerrainRenderer` to the strategy interface; behaviour is the
renderer's (docs/RENDER.md)."""

from __future__ import annotations

from typing import Any

import numpy as np

from render import measure
from render.renderer import RenderStats
from render.select import Patches
from render.strategies.base import Block, Strategy
from streamer.camera import Camera


def patch_levels(sel: Patches) -> dict[Block, int]:
    """The finest level of any patch in each block."""
    out = np.full(len(sel.blocks), -1, np.int64)
    np.maximum.at(out, sel.block, sel.level)
    return {
        tuple(int(v) for v in b): int(lv) for b, lv in zip(sel.blocks, out, strict=True) if lv >= 0
    }


class QiuStrategy(Strategy):
    """Qiu's CLOD patches (the default)."""

    name = "qiu"

    def select(self, camera, tau, metric="qiu", *, resident=None) -> tuple[Patches, float]:
        return self.r.select(camera, tau, metric, resident=resident)

    def draw(self, camera: Camera, sel: Patches, **kw: Any) -> RenderStats:
        return self.r.draw(camera, sel, **kw)

    def screen_errors(self, camera: Camera, sel: Patches) -> np.ndarray:
        from render.pipeline import heights_fn  # pipeline imports the strategies

        return measure.screen_errors(sel, self.r.grid, camera, heights_fn(self.r.store, sel))

    def used_levels(self, camera: Camera, sel: Patches) -> dict[Block, int]:
        """The finest patch level drawn in each block."""
        return patch_levels(sel)

    def drawn_blocks(self, sel: Patches) -> set[Block]:
        return {tuple(int(v) for v in b) for b in sel.blocks[np.unique(sel.block)]}

    def surface(self, camera: Camera, sel: Patches):
        from render.pipeline import heights_fn

        step = self.r.grid.step
        rs, cs, hs = [], [], []
        for b, rows, cols, h in measure.lod_surface(sel, self.r.k, heights_fn(self.r.store, sel)):
            br, bc = (int(v) for v in sel.blocks[b])
            rs.append(br * step + rows)
            cs.append(bc * step + cols)
            hs.append(h)
        if not rs:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        return np.concatenate(rs), np.concatenate(cs), np.concatenate(hs)
