"""Per-node boxes for the metrics that take them (:data:`streamer.lod.BOX_METRICS`; pure numpy).

A node's box is its ground footprint times its own height range, in place of the sphere around
the footprint and the *block's* height range. The range of a node drawn as a patch at depth
``d`` comes from its descendants at depth ``L = min(d + patch_log2, R)`` (``R`` = the block's
resident level): each one's 4 level-``L`` corners ``∓`` its stored ``bound``
(:func:`tiler.quadtree.node_height_bounds`), pooled over the node — so every valid
full-resolution sample of the node's closed footprint lies in it (the bound is the largest
vertical distance of a valid sample from its quad, which lies between its corners), and so does
every vertex the patch draws (level-``L`` samples, snapped edges included: a coarser
neighbour's vertices are level-``L`` positions too), intersected with the block's stored range
(which holds both as well). Non-finite ranges (a mask boundary's ``inf`` bound, nodata) fall
back to the block's range. Pooled in two :class:`streamer.levels.PatchErrorTable` (``hi`` and
``-lo``, rounded outwards to float32), so one fancy index per pass looks many blocks up.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from streamer.levels import PatchErrorTable
from tiler.quadtree import node_height_bounds

Block = tuple[int, int]


def _up32(x: np.ndarray) -> np.ndarray:
    """float32 of ``x`` rounded towards +inf (so pooling in float32 never narrows a range)."""
    f = np.asarray(x, dtype=np.float64).astype(np.float32)
    return np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)


class NodeBoxes:
    """Per-node height ranges of blocks for one patch size, rebuilt when a block's resident
    level changes (:meth:`update`); blocks leave with :meth:`remove`."""

    def __init__(self, k: int, patch_log2: int) -> None:
        self.k, self.patch_log2 = k, patch_log2
        self._hi = PatchErrorTable(k, patch_log2)
        self._neg_lo = PatchErrorTable(k, patch_log2)
        self._level: dict[Block, int] = {}
        self._zr: dict[Block, tuple[float, float]] = {}

    def __contains__(self, block: Block) -> bool:
        return block in self._level

    def level(self, block: Block) -> int:
        """The resident level the block's ranges were built from (-1: none)."""
        return self._level.get(block, -1)

    def update(
        self,
        block: Block,
        level: int,
        grid: np.ndarray,
        bound: Sequence[np.ndarray],
        zrange: tuple[float, float],
    ) -> None:
        """(Re)build ``block``'s ranges from its level-``level`` ``grid``, its ``bound`` field
        (depths ``0..k-1``; mask boundaries ``inf``) and its stored ``(zmin, zmax)``."""
        block = (int(block[0]), int(block[1]))
        self.remove(block)
        z0, z1 = (float(v) for v in zrange)
        los, his = node_height_bounds(grid, list(bound))
        lo_f, hi_f = [], []
        for lo, hi in zip(los, his, strict=True):
            ok = np.isfinite(lo) & np.isfinite(hi)
            lo_f.append(_up32(-np.where(ok, np.maximum(lo, z0), z0)))
            hi_f.append(_up32(np.where(ok, np.minimum(hi, z1), z1)))
        self._hi.add(block, hi_f)
        self._neg_lo.add(block, lo_f)
        self._level[block], self._zr[block] = int(level), (z0, z1)

    def remove(self, block: Block) -> None:
        """Forget a block."""
        block = (int(block[0]), int(block[1]))
        self._hi.remove(block)
        self._neg_lo.remove(block)
        self._level.pop(block, None)
        self._zr.pop(block, None)

    def slots(self, blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The blocks' slots in the two tables (every block must have been updated)."""
        return self._hi.slots(blocks), self._neg_lo.slots(blocks)

    def zrange(
        self,
        slots: tuple[np.ndarray, np.ndarray],
        fallback: np.ndarray,
        depth: int,
        rows: np.ndarray,
        cols: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` of nodes ``(depth, rows, cols)`` of the blocks at ``slots`` (from
        :meth:`slots`, one entry per node); at full resolution (``depth + patch_log2 >= k``,
        where the error is 0) the nodes' ``fallback`` ``(n, 2)`` block ranges."""
        if depth + self.patch_log2 >= self.k:
            return fallback[:, 0].copy(), fallback[:, 1].copy()
        hi = self._hi.delta(slots[0], depth, rows, cols)
        lo = -self._neg_lo.delta(slots[1], depth, rows, cols)
        return lo, hi
