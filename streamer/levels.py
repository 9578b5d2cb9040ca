"""Fast per-frame needed levels: the patch errors of many blocks kept in slot arrays (pure).

:func:`streamer.lod.select_many` returns every leaf node; a streamer only needs each block's
needed level, every frame, for many blocks. :class:`PatchErrorTable` keeps, per refinable depth
``d`` (``d + patch_log2 < k``), the max stored error of each depth-``d`` node's descendants at
depth ``d + patch_log2`` (the error of drawing that node as a patch), for every block that has
its errors, in one ``(slots, 2**d, 2**d)`` float32 array. A frame's levels are then one
vectorised breadth-first pass per depth over all blocks' nodes, with no per-block Python work.
The result equals ``select_many(..., polygon=None)``'s ``needed_level`` (tested).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from streamer.camera import Camera
from streamer.errors import LodError
from streamer.lod import Metric, get_metric
from tiler.grid import BlockGrid

Block = tuple[int, int]


class PatchErrorTable:
    """Pooled patch errors of blocks, addressable by block, growing as blocks are added."""

    def __init__(self, k: int, patch_log2: int, capacity: int = 64) -> None:
        if patch_log2 < 0:
            raise LodError(f"patch_log2 must be >= 0, got {patch_log2}")
        self.k = k
        self.patch_log2 = patch_log2
        self.depths = max(0, k - patch_log2)  # refinable depths 0..depths-1
        self._cap = max(1, capacity)
        self._arrays = [
            np.zeros((self._cap, 1 << d, 1 << d), np.float32) for d in range(self.depths)
        ]
        self._slot: dict[Block, int] = {}
        self._free: list[int] = list(range(self._cap - 1, -1, -1))

    def __contains__(self, block: Block) -> bool:
        return block in self._slot

    def __len__(self) -> int:
        return len(self._slot)

    def add(self, block: Block, field: Sequence[np.ndarray]) -> None:
        """Store a block's unpacked error field (one array per depth ``0..k-1``)."""
        if len(field) != self.k:
            raise LodError(f"field must hold {self.k} depths, got {len(field)}")
        block = (int(block[0]), int(block[1]))
        if block in self._slot:
            return
        if not self._free:
            self._grow()
        s = self._free.pop()
        self._slot[block] = s
        p = self.patch_log2
        for d in range(self.depths):
            src = np.asarray(field[d + p], dtype=np.float32)
            n, nd = src.shape[0], 1 << d
            if n >= nd:
                r = n // nd
                pooled = src.reshape(nd, r, nd, r).max(axis=(1, 3))
            else:  # stored at a coarser resolution (beyond the cap): repeat
                pooled = np.repeat(np.repeat(src, nd // n, axis=0), nd // n, axis=1)
            self._arrays[d][s] = pooled

    def remove(self, block: Block) -> None:
        """Forget a block (its slot is reused)."""
        s = self._slot.pop((int(block[0]), int(block[1])), None)
        if s is not None:
            self._free.append(s)

    def slots(self, blocks: Sequence[Block] | np.ndarray) -> np.ndarray:
        """Slot of each block (``LodError`` for a block whose errors were never added)."""
        get = self._slot.get
        keys = np.asarray(blocks, dtype=np.int64).reshape(-1, 2).tolist()
        arr = np.fromiter((get(tuple(b), -1) for b in keys), np.int64, len(keys))
        if (arr < 0).any():
            b = keys[int(np.argmin(arr))]
            raise LodError(f"block {tuple(b)} has no errors in the patch table")
        return arr

    def delta(
        self, slots: np.ndarray, depth: int, rows: np.ndarray, cols: np.ndarray
    ) -> np.ndarray:
        """Patch errors (float64) of nodes ``(depth, rows, cols)`` of the blocks in ``slots``;
        0 at full resolution (``depth + patch_log2 >= k``)."""
        if depth >= self.depths:
            return np.zeros(len(slots))
        return self._arrays[depth][slots, rows, cols].astype(np.float64)

    def _grow(self) -> None:
        old = self._cap
        self._cap *= 2
        self._arrays = [
            np.concatenate([a, np.zeros((old, *a.shape[1:]), np.float32)]) for a in self._arrays
        ]
        self._free.extend(range(self._cap - 1, old - 1, -1))

    def needed_levels(
        self,
        grid: BlockGrid,
        blocks: Sequence[Block],
        camera: Camera,
        tau: float,
        metric: str | Metric,
        zranges: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Needed level of each block (all must be in the table) and its largest screen error."""
        fn = get_metric(metric)
        k, p = self.k, self.patch_log2
        m = len(blocks)
        levels = np.full(m, min(k, p), dtype=np.int64)
        rho_max = np.zeros(m)
        if m == 0 or self.depths == 0:
            return levels, rho_max
        blk = np.asarray(blocks, dtype=np.int64).reshape(-1, 2)
        slots = self.slots(blk)
        zr = np.asarray(zranges, dtype=np.float64).reshape(m, 2)
        zmid, zhalf = 0.5 * (zr[:, 0] + zr[:, 1]), 0.5 * (zr[:, 1] - zr[:, 0])
        bx0, _, _, by1 = grid.block_bounds(blk[:, 0], blk[:, 1])
        diag = math.hypot(grid.dx, grid.dy)
        idx = np.arange(m)
        rows = np.zeros(m, dtype=np.int64)
        cols = np.zeros(m, dtype=np.int64)
        child_r = np.array([0, 0, 1, 1])
        child_c = np.array([0, 1, 0, 1])
        for d in range(self.depths):
            size = float(1 << (k - d))
            levels[idx] = d + p  # every block still holding nodes reaches this depth
            delta = self.delta(slots[idx], d, rows, cols)
            cx = bx0[idx] + (cols + 0.5) * (size * grid.dx)
            cy = by1[idx] - (rows + 0.5) * (size * grid.dy)
            half = 0.5 * size * diag
            centres = np.stack([cx, cy, zmid[idx]], axis=1)
            rho = np.asarray(fn(delta, centres, np.hypot(half, zhalf[idx]), camera))
            np.maximum.at(rho_max, idx, np.where(np.isfinite(rho), rho, 1e30))
            split = ~(rho <= tau)
            if not split.any():
                break
            idx = np.repeat(idx[split], 4)
            rows = (2 * rows[split][:, None] + child_r).ravel()
            cols = (2 * cols[split][:, None] + child_c).ravel()
        else:
            levels[idx] = k  # nodes split down to full resolution
        return levels, rho_max
