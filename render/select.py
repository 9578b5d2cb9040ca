"""CLOD patch selection and stitching levels (pure numpy, no GL; Qiu et al. 3.3).

:func:`select_patches` walks the quadtrees of all blocks at once, breadth-first, one numpy pass
per depth over every block's live nodes: a node whose bounding circle (diameter = node diagonal)
misses the ground polygon is culled, one lying wholly in padding is dropped, and a node is split
while ``metric(delta) > tau``. A node at depth ``d`` is drawn as a patch from level
``min(k, d + patch_log2)`` (the streamer's convention, :mod:`streamer.lod`); its ``delta`` is the
largest stored error of its descendants at depth ``d + patch_log2``. A block whose finest
*resident* level ``R`` is coarser than that is not split beyond depth ``R - patch_log2`` and is
drawn at level ``R``: counted as clamped when it wanted to split; a leaf that stopped at its
error but is drawn below its own level is not (``delta`` then does not bound it):
:func:`uncounted_clamps` counts those.

:class:`PatchTable` keeps those pooled patch errors of every known block in one
``(slots, 2**d, 2**d)`` array per depth (like :class:`streamer.levels.PatchErrorTable`), so a
pass looks all its nodes' errors up with one fancy index and nothing is stacked per frame. The
circle test is :func:`streamer.frustum.polygon_meets_circles`'s arithmetic with the polygon's
part computed once per frame (:class:`DiscCull`).

:func:`stitch` then gives every patch edge the snap ``t = max(0, s_n - s)`` where ``s`` and
``s_n`` are the log2 cell spacings of the patch and of the leaf across that edge (same or
adjacent block), and enforces the restriction ``2**s_n <= node edge`` by splitting the coarse
neighbour (repeatedly); see docs/RENDER.md. All edges' probes at all depths are one
``searchsorted``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from render import select_kernels, stitch_fast
from render import stitch_rounds as rounds
from render.errors import RenderError, SelectionError
from render.node_boxes import NodeBoxes, node_box_slots, node_rho, snap_over
from streamer.camera import Camera
from streamer.errors import LodError
from streamer.frustum import as_polygon
from streamer.levels import PatchErrorTable
from streamer.lod import Metric, check_finite_tau, get_metric, horizontal_px
from streamer.lod import gap_scale as lod_gap_scale
from tiler.grid import BlockGrid
from tiler.quadtree import (
    block_origins,
    half_diagonal,
    node_centres_at,
    node_span,
)

Block = tuple[int, int]
_CHILD_R = np.array([0, 0, 1, 1])
_CHILD_C = np.array([0, 1, 0, 1])


PatchTable = PatchErrorTable  # the streamer's table: the same pooled patch errors


class DiscCull:
    """:func:`streamer.frustum.polygon_meets_circles` for one polygon and many calls: the same
    arithmetic (so the same answers), with the polygon's part done once."""

    def __init__(self, polygon: np.ndarray) -> None:
        poly = as_polygon(polygon)
        self.empty = len(poly) == 0
        if self.empty:
            return
        self.o = poly[0]
        p = poly - self.o
        e = np.roll(p, -1, axis=0) - p
        self.px, self.py = p[:, 0], p[:, 1]
        self.ex, self.ey = e[:, 0], e[:, 1]
        self.ee = e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1]
        self.ok = self.ee > 0.0
        self.all_ok = bool(self.ok.all())
        self.ee_safe = np.where(self.ok, self.ee, 1.0)
        area2 = np.sum(p[:-1, 0] * p[1:, 1] - p[1:, 0] * p[:-1, 1])  # frustum._area2
        self.ccw = len(p) >= 3 and float(area2) > 0.0

    def __call__(self, cx: np.ndarray, cy: np.ndarray, radius) -> tuple[np.ndarray, np.ndarray]:
        """``(meets, inside)``: the disc meets the polygon; it lies strictly inside it (then so
        do its descendants' discs, which :func:`select_patches` then does not test)."""
        if self.empty:
            return np.zeros(len(cx), dtype=bool), np.zeros(len(cx), dtype=bool)
        ax = (cx - self.o[0])[:, None] - self.px  # (n, edges)
        ay = (cy - self.o[1])[:, None] - self.py
        t = (ax * self.ex + ay * self.ey) / self.ee_safe
        if not self.all_ok:
            t = np.where(self.ok, t, 0.0)
        np.clip(t, 0.0, 1.0, out=t)
        dx = ax - t * self.ex
        dy = ay - t * self.ey
        dist2 = (dx * dx + dy * dy).min(axis=1)
        near = dist2 <= radius * radius
        if not self.ccw:
            return near, np.zeros(len(cx), dtype=bool)
        centre_in = (self.ex * ay - self.ey * ax >= 0.0).all(axis=1)
        return near | centre_in, centre_in & ~near


@dataclass(frozen=True, eq=False)
class Patches:
    """Leaf patches of one frame: per patch its block (index into ``blocks``), node, level."""

    blocks: np.ndarray  # (m, 2) int64 block ids
    block: np.ndarray  # (n,) index into blocks
    depth: np.ndarray
    row: np.ndarray
    col: np.ndarray
    level: np.ndarray
    delta: np.ndarray
    rho: np.ndarray
    snap: np.ndarray  # (n, 4) int64 snap log2 per edge N, E, S, W
    clamped: int  # nodes that wanted a level that is not resident
    violations: int  # edges whose restriction could not be met (snap clipped)

    def __len__(self) -> int:
        return len(self.depth)

    @property
    def cells_log2(self) -> np.ndarray:
        """log2 of cells per patch side (``level - depth``)."""
        return self.level - self.depth

    def subset(self, keep: np.ndarray) -> Patches:
        """The patches where ``keep`` is True."""
        f = {n: getattr(self, n)[keep] for n in ("block", "depth", "row", "col", "level")}
        return Patches(
            blocks=self.blocks,
            delta=self.delta[keep],
            rho=self.rho[keep],
            snap=self.snap[keep],
            clamped=self.clamped,
            violations=self.violations,
            **f,
        )


def coarse_leaves(patches: Patches, k: int, patch_log2: int) -> np.ndarray:
    """Per leaf: drawn from a level coarser than its own, ``min(k, depth + patch_log2)`` (its
    block's resident level capped it, so its ``delta`` does not bound what is drawn)."""
    return patches.level < np.minimum(k, patches.depth + patch_log2)


def uncounted_clamps(
    patches: Patches, k: int, patch_log2: int, tau: float, min_depth: int = 0
) -> int:
    """Leaves drawn coarser than their own level (:func:`coarse_leaves`) that
    ``patches.clamped`` leaves out: it counts the nodes that wanted to split (``rho > tau``, or
    shallower than ``min_depth``), not those that stopped at their error but were capped below
    their own level by the resident one (a NaN ``rho`` counts as wanting)."""
    want = ~(patches.rho <= tau) | (patches.depth < min_depth)
    return int(np.count_nonzero(coarse_leaves(patches, k, patch_log2) & ~want))


def check_drawable(patches: Patches, held: np.ndarray) -> None:
    """Raise :class:`render.errors.RenderError` naming the first patch the vertex shader would
    fetch outside its block's slot or block (``held``: per patch its block's level on the GPU):
    a level not held reads the next slot or past the page; a node outside ``2**depth``, a
    level above its depth missing or a snap past its 4 bits reads past the block."""
    c, lv, d, row, col = patches.cells_log2, patches.level, patches.depth, patches.row, patches.col
    side = np.left_shift(1, np.maximum(d, 0))
    bad = (lv > held) | (d < 0) | (c < 0)
    bad |= (col < 0) | (col >= side) | (row < 0) | (row >= side)
    bad |= ((patches.snap < 0) | (patches.snap > 15)).any(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        b = tuple(int(v) for v in patches.blocks[patches.block[i]])
        raise RenderError(
            f"patch {i} of block {b} (depth {d[i]}, row {row[i]}, col {col[i]}, level {lv[i]}, "
            f"snaps {patches.snap[i].tolist()}) is outside what the GPU holds: level "
            f"{held[i]} of the block"
        )


def check_tau(tau: float) -> float:
    """``tau`` as a float, or :class:`SelectionError` unless it is a finite number >= 0.

    Infinity is refused (as the CLI refuses it): a mixed terrain/nodata node splits because its
    error, inf, exceeds tau, which ``inf > inf`` does not (terrain beside nodata would be
    dropped), and the gap rule's ``tau / min(tau, 1)`` scale would make ``0 * inf = nan``. The
    largest finite taus (``1e300``) are taken: every finite error then stays unrefined
    (:func:`streamer.lod.check_finite_tau`, the planner's check)."""
    try:
        return check_finite_tau(tau)
    except LodError:
        raise SelectionError(
            f"tau must be a finite pixel threshold >= 0 (for no refinement give a large finite "
            f"one, e.g. 1e300), got {tau!r}"
        ) from None


def select_patches(
    grid: BlockGrid,
    blocks: np.ndarray | Sequence[Block],
    table: PatchTable,
    camera: Camera,
    tau: float,
    metric: str | Metric,
    polygon: np.ndarray | None,
    *,
    resident: Sequence[int] | np.ndarray,
    zranges: np.ndarray,
    windows: np.ndarray | None = None,
    min_depth: int = 0,
    boxes: NodeBoxes | None = None,
    kernels: str | None = None,
    gaps: PatchTable | None = None,
) -> Patches:
    """Leaves of all blocks' quadtrees at ``tau`` (not yet stitched: ``snap`` is zero).

    ``resident[i]`` is the finest resident level of ``blocks[i]`` (-1: none, not drawn);
    ``zranges[i]`` its (zmin, zmax); ``windows[i]`` its ``(row0, col0, nrows, ncols)`` inside the
    DEM (nodes wholly in padding are dropped). Nodes shallower than ``min_depth`` split
    whatever their error (where the resident level allows; ``chunk-tessellation``'s start
    depth, which bounds the depth difference of adjacent leaves). ``boxes`` (required for a
    metric that :func:`~streamer.lod.takes_box`, holding every drawn block) gives each node its
    own box. ``kernels`` (``auto``, ``numba``, ``numpy``; default ``TERRASTREAM_KERNELS``)
    picks the compiled walk (:mod:`render.select_kernels`, the same patches) or this numpy one.
    ``gaps`` (the nodata rule ``"gap"``: per node the widest mixed cell of its level,
    :meth:`render.frame.FrameServices.gap_field`, holding every drawn block) also splits a
    node while that cell can project to more than ``min(tau, 1)`` px
    (:func:`streamer.lod.horizontal_px`).
    """
    check_tau(tau)
    fn = get_metric(metric)
    k, p = grid.k, table.patch_log2
    blk = np.asarray(blocks, dtype=np.int64).reshape(-1, 2)
    m = len(blk)
    res = np.asarray(resident, dtype=np.int64).reshape(m)
    zr = np.asarray(zranges, dtype=np.float64).reshape(m, 2)
    zr = np.where(np.isfinite(zr), zr, 0.0)
    win = None if windows is None else np.asarray(windows, dtype=np.int64).reshape(m, 4)
    outside = (
        (blk[:, 0] < 0) | (blk[:, 0] >= grid.rows) | (blk[:, 1] < 0) | (blk[:, 1] >= grid.cols)
    )
    if outside.any():
        grid.check_block(*(int(v) for v in blk[int(np.argmax(outside))]))
    slots = table.slots(blk)
    box_slots = node_box_slots(fn, boxes, blk, res)
    gap_slots = None if gaps is None else gaps.slots(blk[res >= 0])
    gap_of = np.full(m, -1, np.int64)
    if gap_slots is not None:
        gap_of[res >= 0] = gap_slots
    gap_scale = lod_gap_scale(tau)
    bx0, by1 = block_origins(grid, blk[:, 0], blk[:, 1]) if m else (np.zeros(0),) * 2
    cull = DiscCull(polygon) if polygon is not None and len(polygon) else None
    if win is not None and m and (win[:, 2:] > 1 << k).all():
        win = None  # whole blocks: no node lies in padding (rows * size < 2**k always)
    idx = np.flatnonzero(res >= 0)
    nb = select_kernels.resolve(kernels)
    if nb is not None:
        gap = None if gaps is None or gap_scale <= 0 else (gaps, gap_of, gap_scale)
        parts, clamped = select_kernels.walk(
            nb, grid, table, slots, fn, camera, float(tau), idx=idx, res=res, zr=zr, win=win,
            bx0=bx0, by1=by1, cull=cull, min_depth=min_depth, boxes=boxes, box_slots=box_slots,
            gap=gap,
        )  # fmt: skip
        return _assemble(blk, parts, clamped)
    parts: list[tuple] = []
    clamped = 0
    rows = np.zeros(len(idx), dtype=np.int64)
    cols = np.zeros(len(idx), dtype=np.int64)
    inside = np.zeros(len(idx), dtype=bool)  # disc wholly inside the polygon: no test
    depth = 0
    while idx.size:
        size = node_span(k, depth)
        half = half_diagonal(grid, depth)
        cx, cy = node_centres_at(grid, bx0[idx], by1[idx], depth, rows, cols)
        keep = None
        if win is not None:
            keep = (rows * size < win[idx, 2] - 1) & (cols * size < win[idx, 3] - 1)
        if cull is not None and not inside.all():
            test = np.flatnonzero(~inside)
            if len(test) == len(idx):
                meets, inside = cull(cx, cy, half)
            else:
                meets = np.ones(len(idx), dtype=bool)
                meets[test], inside[test] = cull(cx[test], cy[test], half)
            keep = meets if keep is None else keep & meets
        if keep is not None and not keep.all():
            idx, rows, cols, cx, cy = idx[keep], rows[keep], cols[keep], cx[keep], cy[keep]
            inside = inside[keep]
            if not idx.size:
                break
        delta = table.delta(slots[idx], depth, rows, cols)
        bx = None if box_slots is None else (boxes, (box_slots[0][idx], box_slots[1][idx]))
        rho = node_rho(fn, grid, delta, cx, cy, depth, zr[idx], camera, bx, rows, cols)
        if gaps is not None and gap_scale > 0:
            w = gaps.delta(gap_of[idx], depth, rows, cols)
            if (w > 0).any():  # rho > tau also when the gap projects past min(tau, 1) px
                g = node_rho(horizontal_px, grid, w, cx, cy, depth, zr[idx], camera, bx, rows, cols)
                rho = np.maximum(rho, g * gap_scale)
        r_idx = res[idx]
        level = np.minimum(min(k, depth + p), r_idx)
        if depth + p >= k:
            parts.append((idx, depth, rows, cols, level, delta, rho))
            break
        want = ~(rho <= tau) | (depth < min_depth)
        split = want & (depth + p < r_idx)
        n_split = int(np.count_nonzero(split))
        clamped += int(np.count_nonzero(want)) - n_split
        if n_split == 0:
            parts.append((idx, depth, rows, cols, level, delta, rho))
            break
        if n_split < len(idx):
            leaf = ~split
            parts.append(
                (idx[leaf], depth, rows[leaf], cols[leaf], level[leaf], delta[leaf], rho[leaf])
            )
        idx = np.repeat(idx[split], 4)
        inside = np.repeat(inside[split], 4)
        rows = (2 * rows[split][:, None] + _CHILD_R).ravel()
        cols = (2 * cols[split][:, None] + _CHILD_C).ravel()
        depth += 1
    return _assemble(blk, parts, clamped)


def _assemble(blk: np.ndarray, parts: list[tuple], clamped: int) -> Patches:
    """Concatenate the per-depth leaves."""
    if not parts:
        z = np.zeros(0, np.int64)
        return Patches(
            blk, z, z, z, z, z, np.zeros(0), np.zeros(0), np.zeros((0, 4), np.int64), clamped, 0
        )
    block, row, col, level, delta, rho = (
        np.concatenate([pt[i] for pt in parts]) for i in (0, 2, 3, 4, 5, 6)
    )
    depth = np.repeat(
        np.array([pt[1] for pt in parts], dtype=np.int64), [len(pt[0]) for pt in parts]
    )
    n = len(depth)
    return Patches(
        blocks=blk,
        block=block.astype(np.int64),
        depth=depth,
        row=row.astype(np.int64),
        col=col.astype(np.int64),
        level=level.astype(np.int64),
        delta=delta.astype(np.float64),
        rho=rho,
        snap=np.zeros((n, 4), dtype=np.int64),
        clamped=clamped,
        violations=0,
    )


def _neighbours(patches: Patches, k: int, nb=None) -> np.ndarray:
    """``(n, 4)`` index of the leaf across each edge (N, E, S, W) at the edge midpoint, or -1.

    Every edge's probe (one finest node beyond the edge midpoint) is looked up at every depth
    in one ``searchsorted`` over the sorted leaf keys; the deepest hit wins. ``nb``: the
    compiled kernels (:mod:`render.select_kernels`; the same answer, one binary search per
    probe).
    """
    n = len(patches)
    if n == 0:
        return np.zeros((0, 4), dtype=np.int64)
    if nb is None:
        return rounds.neighbours_of(patches, np.arange(n))
    gr, gc, d, big, nr, nc = rounds.leaf_keys(patches)
    keys = (d * nr + gr) * nc + gc
    order = np.argsort(keys)
    return nb.neighbours(keys[order], order, d, gr, gc, big, nr, nc, np.unique(d))


def stitch(
    patches: Patches,
    grid: BlockGrid,
    table: PatchTable,
    camera: Camera,
    metric: str | Metric,
    *,
    resident: Sequence[int] | np.ndarray,
    zranges: np.ndarray,
    max_rounds: int = 1024,
    boxes: NodeBoxes | None = None,
    tau: float | None = None,
    kernels: str | None = None,
    incremental: bool = True,
) -> Patches:
    """Snap levels per edge; split coarse neighbours until ``2**s_n <= node edge`` everywhere
    (new nodes' errors with the same node geometry as :func:`select_patches`: ``boxes``).

    With ``tau`` and a metric that takes boxes, a snapped edge also splits its coarser
    neighbour while the metric of the patch's error plus the edge's snapping excess
    (:func:`render.snap_error.snap_excess`) exceeds ``tau``; such an edge whose neighbour may
    not split (its resident level) counts as clamped. ``kernels``: as :func:`select_patches`'
    (the compiled rounds, :mod:`render.stitch_fast`, when ``incremental``; else the neighbour
    search). ``incremental`` (default) carries the edges' neighbours and
    snapped-edge checks from round to round, redoing them only where a round changed leaves
    (:mod:`render.stitch_rounds`; the same patches as ``False``, which redoes all every round)."""
    k = grid.k
    nb = select_kernels.resolve(kernels)
    fn = get_metric(metric)
    box_slots = None
    res = np.asarray(resident, dtype=np.int64)
    kn = select_kernels.stitch_kernels(nb) if incremental else None
    if kn is not None and len(patches) and table.depths > 0:
        return stitch_fast.stitch_compiled(
            kn, patches, grid, table, camera, fn, res=np.ascontiguousarray(res),
            zranges=zranges, max_rounds=max_rounds, boxes=boxes, tau=tau,
        )  # fmt: skip
    cur = patches
    slots = None
    nbr = None
    cache = rounds.OverCache(len(cur)) if incremental else None
    for _ in range(max_rounds):
        if nbr is None or not incremental:
            nbr = _neighbours(cur, k, nb)
        spacing = k - cur.level
        has = nbr >= 0
        s_n = np.where(has, spacing[np.maximum(nbr, 0)], 0)
        snap = np.where(has, np.maximum(s_n - spacing[:, None], 0), 0)
        edge = k - cur.depth  # log2 node edge in samples
        bad = has & (s_n > edge[:, None])
        victims = np.unique(nbr[bad]) if bad.any() else nbr[bad]
        if victims.size:
            splittable = cur.depth[victims] + table.patch_log2 < np.minimum(
                k, res[cur.block[victims]]
            )
            victims = victims[splittable]
        if slots is None:
            slots = table.slots(cur.blocks)
            box_slots = node_box_slots(fn, boxes, cur.blocks, res)
        extra = 0
        if not victims.size:
            snap = np.minimum(snap, cur.cells_log2[:, None])
            if tau is not None and box_slots is not None:

                def check(sub: Patches, sn: np.ndarray, bs=box_slots) -> np.ndarray:
                    return snap_over(sub, sn, grid, camera, fn, tau, zranges, boxes, bs)

                over = check(cur, snap) if cache is None else cache.over_edges(cur, snap, check)
                victims = np.unique(nbr[over])
                if victims.size:
                    keep = cur.depth[victims] + table.patch_log2 < np.minimum(
                        k, res[cur.block[victims]]
                    )
                    extra = int(np.count_nonzero(~keep))
                    victims = victims[keep]
        if not victims.size:
            return Patches(
                blocks=cur.blocks,
                block=cur.block,
                depth=cur.depth,
                row=cur.row,
                col=cur.col,
                level=cur.level,
                delta=cur.delta,
                rho=cur.rho,
                snap=snap.astype(np.int64),
                clamped=cur.clamped + extra,
                violations=int(np.count_nonzero(bad)),
            )
        keep = np.ones(len(cur), dtype=bool)
        keep[victims] = False
        cur = _split(
            cur, victims, grid, table, slots, camera, metric, res, zranges, boxes, box_slots
        )
        if cache is not None:
            cache.split(keep, 4 * len(victims))
            nbr = rounds.neighbours_after_split(cur, nbr, keep)
    raise SelectionError(f"stitching did not settle in {max_rounds} rounds")


def _split(
    cur: Patches,
    victims: np.ndarray,
    grid: BlockGrid,
    table: PatchTable,
    slots: np.ndarray,
    camera: Camera,
    metric: str | Metric,
    res: np.ndarray,
    zranges: np.ndarray,
    boxes: NodeBoxes | None = None,
    box_slots: tuple[np.ndarray, np.ndarray] | None = None,
) -> Patches:
    """Replace the leaves ``victims`` by their four children."""
    k, p = grid.k, table.patch_log2
    keep = np.ones(len(cur), dtype=bool)
    keep[victims] = False
    b = np.repeat(cur.block[victims], 4)
    d = np.repeat(cur.depth[victims] + 1, 4)
    r = (2 * cur.row[victims][:, None] + _CHILD_R).ravel()
    c = (2 * cur.col[victims][:, None] + _CHILD_C).ravel()
    level = np.minimum(np.minimum(k, d + p), res[b])
    blk = cur.blocks[b]
    bx0, by1 = block_origins(grid, blk[:, 0], blk[:, 1])
    zr = np.asarray(zranges, dtype=np.float64)[b]
    fn = get_metric(metric)
    delta, rho = np.zeros(len(b)), np.zeros(len(b))
    for depth in np.unique(d).tolist():
        m = d == depth
        delta[m] = table.delta(slots[b[m]], depth, r[m], c[m])
        cx, cy = node_centres_at(grid, bx0[m], by1[m], depth, r[m], c[m])
        bx = None if box_slots is None else (boxes, (box_slots[0][b[m]], box_slots[1][b[m]]))
        rho[m] = node_rho(fn, grid, delta[m], cx, cy, depth, zr[m], camera, bx, r[m], c[m])
    return Patches(
        blocks=cur.blocks,
        block=np.concatenate([cur.block[keep], b]),
        depth=np.concatenate([cur.depth[keep], d]),
        row=np.concatenate([cur.row[keep], r]),
        col=np.concatenate([cur.col[keep], c]),
        level=np.concatenate([cur.level[keep], level]),
        delta=np.concatenate([cur.delta[keep], delta]),
        rho=np.concatenate([cur.rho[keep], rho]),
        snap=np.zeros((int(keep.sum()) + len(b), 4), dtype=np.int64),
        clamped=cur.clamped,
        violations=0,
    )
