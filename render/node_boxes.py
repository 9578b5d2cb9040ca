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

Also the selection's node geometry (:func:`node_rho`: sphere or box per node) and the snapped
edge check of :func:`render.select.stitch` (:func:`snap_over`, with
:func:`render.snap_error.snap_excess` on the level grids kept here).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from render.errors import SelectionError
from render.flat_pool import FlatPool
from render.snap_error import snap_exact, snap_excess
from streamer.camera import Camera
from streamer.levels import PatchErrorTable
from streamer.lod import Metric, takes_box
from tiler.grid import BlockGrid
from tiler.quadtree import (
    block_origins,
    half_diagonal,
    node_centres_at,
    node_height_bounds,
    node_span,
    sphere_radius,
)

if TYPE_CHECKING:
    from render.select import Patches

Block = tuple[int, int]


def _up32(x: np.ndarray) -> np.ndarray:
    """float32 of ``x`` rounded towards +inf (so pooling in float32 never narrows a range)."""
    x = np.asarray(x, dtype=np.float64)
    f = x.astype(np.float32)
    low = f < x  # (float32 promoted to float64 for the comparison)
    if low.any():
        f[low] = np.nextafter(f[low], np.float32(np.inf))
    return f


def _by_block(blocks: np.ndarray) -> list[tuple[Block, np.ndarray]]:
    """The distinct rows of ``(m, 2)`` ``blocks`` and where each occurs."""
    blocks = np.asarray(blocks, dtype=np.int64).reshape(-1, 2)
    if not len(blocks):
        return []
    key = (blocks[:, 0] - blocks[:, 0].min()) * (int(np.ptp(blocks[:, 1])) + 1) + blocks[:, 1]
    order = np.argsort(key, kind="stable")
    cut = np.flatnonzero(np.diff(key[order])) + 1
    return [
        ((int(blocks[g[0], 0]), int(blocks[g[0], 1])), np.sort(g)) for g in np.split(order, cut)
    ]


class NodeBoxes:
    """Per-node height ranges of blocks for one patch size, rebuilt when a block's resident
    level changes (:meth:`update`); blocks leave with :meth:`remove`."""

    def __init__(self, k: int, patch_log2: int) -> None:
        self.k, self.patch_log2 = k, patch_log2
        self._hi = PatchErrorTable(k, patch_log2)
        self._neg_lo = PatchErrorTable(k, patch_log2)
        self._level: dict[Block, int] = {}
        self._zr: dict[Block, tuple[float, float]] = {}
        self._grid: dict[Block, np.ndarray] = {}  # views of _pool: grid then bounds
        self._bound: dict[Block, list[np.ndarray]] = {}
        self._pool = FlatPool()

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
        valid: np.ndarray | None = None,
        cell_bound: Sequence[np.ndarray] | None = None,
    ) -> None:
        """(Re)build ``block``'s ranges from its level-``level`` ``grid``, its ``bound`` field
        (depths ``0..k-1``; mask boundaries ``inf``) and its stored ``(zmin, zmax)``; the grid
        is kept (NaN where ``valid``, the level's validity, is False) for
        :meth:`vertex_heights`. ``cell_bound`` (default ``bound``): the field
        :meth:`cell_bounds` answers from (the snapped-edge check's), e.g. the nodata rule
        ``gap``'s stored errors where ``bound`` has the rule ``full``'s ``inf``."""
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
        g = np.asarray(grid, dtype=np.float64)
        g = g if valid is None else np.where(valid, g, np.nan)
        cells = bound if cell_bound is None else cell_bound
        if self._pool.put(block, [g, *cells]):  # the pool moved: every block's views anew
            for b in self._grid:
                self._grid[b], *self._bound[b] = self._pool.views(b)
        self._grid[block], *self._bound[block] = self._pool.views(block)

    def remove(self, block: Block) -> None:
        """Forget a block."""
        block = (int(block[0]), int(block[1]))
        self._hi.remove(block)
        self._neg_lo.remove(block)
        self._level.pop(block, None)
        self._zr.pop(block, None)
        self._grid.pop(block, None)
        self._bound.pop(block, None)
        self._pool.drop(block)

    def flat(self, blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The pool of grids and bounds (one float64 buffer) and per row of ``(m, 2)``
        ``blocks`` its ``(k + 1)`` arrays' offsets and sides in it: the level grid's first, then
        the bound's of depths ``0..k-1`` (-1 for a block not held; square arrays)."""
        m, k = len(blocks), self.k
        off = np.full((m, k + 1), -1, np.int64)
        side = np.full((m, k + 1), -1, np.int64)
        at = self._pool.at
        for i, (r, c) in enumerate(np.asarray(blocks, dtype=np.int64).reshape(-1, 2).tolist()):
            parts = at.get((r, c))
            if parts is not None:
                off[i] = [o for o, _ in parts]
                side[i] = [sh[0] for _, sh in parts]
        return self._pool.buf, off, side

    def vertex_heights(
        self,
        blocks: np.ndarray,
        depth: np.ndarray,
        row: np.ndarray,
        col: np.ndarray,
        level: np.ndarray,
    ) -> np.ndarray:
        """``(m, n+1, n+1)`` level-``level`` vertex heights ``[row, column]`` of patches (one
        cell count ``n = 2**(level - depth)``) of the ``(m, 2)`` ``blocks`` (NaN: masked)."""
        m = len(depth)
        n = (1 << int(level[0] - depth[0])) if m else 0
        out = np.empty((m, n + 1, n + 1))
        for i, (b, d, r, c, lv) in enumerate(
            zip(map(tuple, blocks.tolist()), depth.tolist(), row.tolist(), col.tolist(),
                level.tolist(), strict=True)
        ):  # fmt: skip
            g, rr = self._grid[b], self._level[b]
            span, step = 1 << (rr - d), 1 << (rr - lv)
            out[i] = g[r * span : (r + 1) * span + 1 : step, c * span : (c + 1) * span + 1 : step]
        return out

    def full_windows(self, blocks: np.ndarray, depth: np.ndarray, row: np.ndarray, col: np.ndarray
                     ) -> np.ndarray:  # fmt: skip
        """``(m, side, side)`` full-resolution heights (NaN: masked) of nodes of one depth of
        blocks held at level ``k`` (``side = 2**(k - depth) + 1``): :meth:`vertex_heights` at
        level ``k``."""
        return self.vertex_heights(blocks, depth, row, col, np.full(len(depth), self.k))

    def cell_bounds(
        self,
        blocks: np.ndarray,
        depth: np.ndarray,
        row: np.ndarray,
        col: np.ndarray,
        level: np.ndarray,
    ) -> np.ndarray:
        """``(m, n, n)`` stored ``bound`` of each level-``level`` cell (a depth-``level`` node;
        0 at full resolution) of patches as :meth:`vertex_heights`."""
        m = len(depth)
        n = (1 << int(level[0] - depth[0])) if m else 0
        out = np.zeros((m, n, n))
        ramp = np.arange(n)
        lv = np.asarray(level, dtype=np.int64)
        for b, sel in _by_block(blocks):
            for v in np.unique(lv[sel]).tolist():
                if v >= self.k:
                    continue
                f = self._bound[b][v]
                at = sel[lv[sel] == v]
                rep = (1 << v) // f.shape[0]  # stored coarser than the depth: one value a tile
                rows = ((row[at] * n)[:, None] + ramp) // rep
                cols = ((col[at] * n)[:, None] + ramp) // rep
                out[at] = f[rows[:, :, None], cols[:, None, :]]
        return out

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


# -- the selection's node geometry (render.select) ------------------------------------------


def node_rho(
    fn: Metric,
    grid: BlockGrid,
    delta: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    depth: int,
    zr: np.ndarray,
    camera: Camera,
    boxes: tuple[NodeBoxes, tuple[np.ndarray, np.ndarray]] | None,
    rows: np.ndarray,
    cols: np.ndarray,
) -> np.ndarray:
    """The metric's pixel errors of depth-``depth`` nodes centred at ``(cx, cy)`` whose blocks'
    ranges are ``zr`` ``(n, 2)``: each node's sphere (half diagonal, the block's height range),
    or with ``boxes`` (the table and the nodes' slots in it) each node's box (footprint times
    its own height range, :mod:`render.node_boxes`)."""
    half = half_diagonal(grid, depth)
    if boxes is None:
        zmid, zhalf = 0.5 * (zr[:, 0] + zr[:, 1]), 0.5 * (zr[:, 1] - zr[:, 0])
        centres = np.stack([cx, cy, zmid], axis=1)
        return np.asarray(fn(delta, centres, sphere_radius(half, zhalf), camera), np.float64)
    table, slots = boxes
    lo, hi = table.zrange(slots, zr, depth, rows, cols)
    s = 0.5 * float(node_span(grid.k, depth))
    n = len(cx)
    ext = np.stack([np.full(n, s * grid.dx), np.full(n, s * grid.dy), 0.5 * (hi - lo)], 1)
    centres = np.stack([cx, cy, 0.5 * (lo + hi)], axis=1)
    radius = np.linalg.norm(ext, axis=1)
    return np.asarray(fn(delta, centres, radius, camera, half_extent=ext), np.float64)


def node_box_slots(
    fn: Metric, boxes: NodeBoxes | None, blk: np.ndarray, res: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The blocks' slots in ``boxes`` when the metric takes boxes (-1 for undrawn blocks)."""
    if not takes_box(fn):
        return None
    if boxes is None:
        raise SelectionError("this metric selects with node boxes: pass boxes= (NodeBoxes)")
    out = (np.full(len(blk), -1, np.int64), np.full(len(blk), -1, np.int64))
    drawn = np.flatnonzero(res >= 0)
    if drawn.size:
        a, b = boxes.slots(blk[drawn])
        out[0][drawn], out[1][drawn] = a, b
    return out


def snap_over(
    cur: Patches,
    snap: np.ndarray,
    grid: BlockGrid,
    camera: Camera,
    fn: Metric,
    tau: float,
    zranges: np.ndarray,
    boxes: NodeBoxes,
    box_slots: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """``(n, 4)`` snapped edges whose strip's error exceeds ``tau``: in a block held at full
    resolution its exact error at the strip's samples (:func:`~render.snap_error.snap_exact`),
    else a bound (per fan triangle: the largest stored error of the cells of its bounding box
    plus its snapping excess)."""
    over = np.zeros(snap.shape, dtype=bool)
    idx = np.flatnonzero((snap.max(axis=1) > 0) & np.isfinite(cur.delta))
    if not idx.size:
        return over
    b, d, r, c = cur.block[idx], cur.depth[idx], cur.row[idx], cur.col[idx]

    def heights(sub: np.ndarray) -> np.ndarray:
        return boxes.vertex_heights(cur.blocks[b[sub]], d[sub], r[sub], c[sub], cur.level[idx[sub]])

    def cells(sub: np.ndarray) -> np.ndarray:
        return boxes.cell_bounds(cur.blocks[b[sub]], d[sub], r[sub], c[sub], cur.level[idx[sub]])

    total = snap_excess(cur.cells_log2[idx], snap[idx], heights, cells)
    full = np.array([boxes.level(tuple(int(v) for v in x)) >= boxes.k for x in cur.blocks])[b]
    if full.any():  # full resolution at hand: the strips' exact error at their samples

        def windows(sub: np.ndarray) -> np.ndarray:
            f = np.flatnonzero(full)[sub]
            return boxes.full_windows(cur.blocks[b[f]], d[f], r[f], c[f])

        f = np.flatnonzero(full)
        total[f] = snap_exact(
            cur.cells_log2[idx[f]], boxes.k - cur.level[idx[f]], snap[idx[f]], windows
        )
    blk = cur.blocks[b]
    bx0, by1 = block_origins(grid, blk[:, 0], blk[:, 1])
    zr = np.asarray(zranges, dtype=np.float64)[b]
    for depth in np.unique(d).tolist():
        m = np.flatnonzero(d == depth)
        cx, cy = node_centres_at(grid, bx0[m], by1[m], depth, r[m], c[m])
        bx = (boxes, (box_slots[0][b[m]], box_slots[1][b[m]]))
        for e in range(4):
            pos = snap[idx[m], e] > 0
            if not pos.any():
                continue
            err = total[m, e]  # the strip's own error bound (cells' bound + excess)
            rho = node_rho(fn, grid, err, cx, cy, depth, zr[m], camera, bx, r[m], c[m])
            over[idx[m], e] = pos & ~(rho <= tau)
    return over
