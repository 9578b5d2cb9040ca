"""The selection as it was before vectorisation (block-by-block error lookups): a slow reference.

Kept verbatim (renamed) so ``test_select_vectorised.py`` can check that the vectorised
:func:`render.select.select_patches` / :func:`render.select.stitch` give identical patches.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from render.errors import SelectionError
from render.select import Patches
from streamer.camera import Camera
from streamer.frustum import polygon_meets_circles
from streamer.lod import Metric, get_metric
from tiler.grid import BlockGrid

Block = tuple[int, int]
_CHILD_R = np.array([0, 0, 1, 1])
_CHILD_C = np.array([0, 1, 0, 1])


class RefPatchTable:
    """Per block and refinable depth ``d``, the max error of descendants at ``d + patch_log2``."""

    def __init__(self, k: int, patch_log2: int) -> None:
        if not patch_log2 >= 0:
            raise SelectionError(f"patch_log2 must be >= 0, got {patch_log2}")
        self.k, self.patch_log2 = k, patch_log2
        self.depths = max(0, k - patch_log2)
        self._rows: dict[Block, list[np.ndarray]] = {}

    def __contains__(self, block: Block) -> bool:
        return block in self._rows

    def add(self, block: Block, field: Sequence[np.ndarray]) -> None:
        """Pool one block's unpacked error field (one array per depth ``0..k-1``)."""
        if len(field) != self.k:
            raise SelectionError(f"error field must hold {self.k} depths, got {len(field)}")
        pooled = []
        for d in range(self.depths):
            src = np.asarray(field[d + self.patch_log2], dtype=np.float64)
            n, nd = src.shape[0], 1 << d
            if n >= nd:
                r = n // nd
                pooled.append(src.reshape(nd, r, nd, r).max(axis=(1, 3)))
            else:
                pooled.append(np.repeat(np.repeat(src, nd // n, 0), nd // n, 1))
        self._rows[block] = pooled

    def delta(self, blocks: Sequence[Block], idx: np.ndarray, depth: int, rows, cols) -> np.ndarray:
        """Patch errors of nodes ``(depth, rows, cols)`` of ``blocks[idx]`` (0 at full res)."""
        if depth >= self.depths:
            return np.zeros(len(idx))
        out = np.empty(len(idx))
        for u in np.unique(idx):
            m = idx == u
            out[m] = self._rows[blocks[int(u)]][depth][rows[m], cols[m]]
        return out


def ref_select_patches(
    grid: BlockGrid,
    blocks: Sequence[Block],
    table: RefPatchTable,
    camera: Camera,
    tau: float,
    metric: str | Metric,
    polygon: np.ndarray | None,
    *,
    resident: Sequence[int],
    zranges: np.ndarray,
    windows: np.ndarray | None = None,
) -> Patches:
    """Leaves of all blocks' quadtrees at ``tau`` (not yet stitched: ``snap`` is zero).

    ``resident[i]`` is the finest resident level of ``blocks[i]`` (-1: none, not drawn);
    ``zranges[i]`` its (zmin, zmax); ``windows[i]`` its ``(row0, col0, nrows, ncols)`` inside the
    DEM (nodes wholly in padding are dropped).
    """
    try:
        ok = float(tau) >= 0.0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise SelectionError(f"tau must be a pixel threshold >= 0, got {tau!r}")
    fn = get_metric(metric)
    k, p = grid.k, table.patch_log2
    blocks = [tuple(int(v) for v in b) for b in blocks]
    m = len(blocks)
    res = np.asarray(resident, dtype=np.int64).reshape(m)
    zr = np.asarray(zranges, dtype=np.float64).reshape(m, 2)
    zr = np.where(np.isfinite(zr), zr, 0.0)
    win = None if windows is None else np.asarray(windows, dtype=np.int64).reshape(m, 4)
    for b in blocks:
        grid.check_block(*b)
        if b not in table:
            raise SelectionError(f"block {b} has no errors in the patch table")
    blk = np.asarray(blocks, dtype=np.int64).reshape(m, 2)
    zmid, zhalf = 0.5 * (zr[:, 0] + zr[:, 1]), 0.5 * (zr[:, 1] - zr[:, 0])
    bx0, _, _, by1 = grid.block_bounds(blk[:, 0], blk[:, 1]) if m else (np.zeros(0),) * 4
    diag = math.hypot(grid.dx, grid.dy)
    out: dict[str, list[np.ndarray]] = {n: [] for n in ("block", "depth", "row", "col", "level")}
    out_d: list[np.ndarray] = []
    out_r: list[np.ndarray] = []
    clamped = 0
    idx = np.flatnonzero(res >= 0)
    rows = np.zeros(len(idx), dtype=np.int64)
    cols = np.zeros(len(idx), dtype=np.int64)
    depth = 0
    while idx.size:
        size = 1 << (k - depth)
        keep = np.ones(len(idx), dtype=bool)
        if win is not None:
            keep &= (rows * size < win[idx, 2] - 1) & (cols * size < win[idx, 3] - 1)
        cx = bx0[idx] + (cols + 0.5) * (size * grid.dx)
        cy = by1[idx] - (rows + 0.5) * (size * grid.dy)
        half = 0.5 * size * diag
        if polygon is not None and len(polygon):
            keep &= polygon_meets_circles(polygon, cx, cy, half)
        idx, rows, cols, cx, cy = idx[keep], rows[keep], cols[keep], cx[keep], cy[keep]
        if not idx.size:
            break
        delta = table.delta(blocks, idx, depth, rows, cols)
        centres = np.stack([cx, cy, zmid[idx]], axis=1)
        rho = np.asarray(fn(delta, centres, np.hypot(half, zhalf[idx]), camera), np.float64)
        want = ~(rho <= tau) & (depth + p < k)
        can = depth + p < res[idx]
        split = want & can
        clamped += int((want & ~can).sum())
        leaf = ~split
        out["block"].append(idx[leaf])
        out["depth"].append(np.full(int(leaf.sum()), depth, dtype=np.int64))
        out["row"].append(rows[leaf])
        out["col"].append(cols[leaf])
        out["level"].append(np.minimum(np.minimum(k, depth + p), res[idx[leaf]]))
        out_d.append(delta[leaf])
        out_r.append(rho[leaf])
        idx = np.repeat(idx[split], 4)
        rows = (2 * rows[split][:, None] + _CHILD_R).ravel()
        cols = (2 * cols[split][:, None] + _CHILD_C).ravel()
        depth += 1
    cat = {n: np.concatenate(v) if v else np.zeros(0, np.int64) for n, v in out.items()}
    n = len(cat["depth"])
    return Patches(
        blocks=blk,
        delta=np.concatenate(out_d) if out_d else np.zeros(0),
        rho=np.concatenate(out_r) if out_r else np.zeros(0),
        snap=np.zeros((n, 4), dtype=np.int64),
        clamped=clamped,
        violations=0,
        **{n_: v.astype(np.int64) for n_, v in cat.items()},
    )


def _neighbours(patches: Patches, k: int) -> np.ndarray:
    """``(n, 4)`` index of the leaf across each edge (N, E, S, W) at the edge midpoint, or -1."""
    n = len(patches)
    if n == 0:
        return np.zeros((0, 4), dtype=np.int64)
    big = int(patches.depth.max())
    blk = patches.blocks[patches.block]
    rows_b = int(patches.blocks[:, 0].max()) + 2
    cols_b = int(patches.blocks[:, 1].max()) + 2
    nr, nc = rows_b << big, cols_b << big

    def key(d: np.ndarray, gr: np.ndarray, gc: np.ndarray) -> np.ndarray:
        return (d * nr + gr) * nc + gc

    d = patches.depth
    gr = (blk[:, 0] << d) + patches.row
    gc = (blk[:, 1] << d) + patches.col
    keys = key(d, gr, gc)
    order = np.argsort(keys)
    sk = keys[order]
    span = np.left_shift(1, big - d)
    fr0, fc0 = gr << (big - d), gc << (big - d)
    mid = span >> 1
    probes = [
        (fr0 - 1, fc0 + mid),
        (fr0 + mid, fc0 + span),
        (fr0 + span, fc0 + mid),
        (fr0 + mid, fc0 - 1),
    ]
    out = np.full((n, 4), -1, dtype=np.int64)
    for e, (fr, fc) in enumerate(probes):
        inside = (fr >= 0) & (fc >= 0) & (fr < nr) & (fc < nc)
        for depth in range(big + 1):
            q = key(np.full(n, depth), fr >> (big - depth), fc >> (big - depth))
            pos = np.clip(np.searchsorted(sk, q), 0, n - 1)
            hit = inside & (sk[pos] == q)
            out[hit, e] = order[pos[hit]]
    return out


def ref_stitch(
    patches: Patches,
    grid: BlockGrid,
    table: RefPatchTable,
    camera: Camera,
    metric: str | Metric,
    *,
    resident: Sequence[int],
    zranges: np.ndarray,
    max_rounds: int = 16,
) -> Patches:
    """Snap levels per edge; split coarse neighbours until ``2**s_n <= node edge`` everywhere."""
    k = grid.k
    res = np.asarray(resident, dtype=np.int64)
    cur = patches
    for _ in range(max_rounds):
        nb = _neighbours(cur, k)
        spacing = k - cur.level
        s_n = np.where(nb >= 0, spacing[np.maximum(nb, 0)], 0)
        snap = np.where(nb >= 0, np.maximum(s_n - spacing[:, None], 0), 0)
        edge = k - cur.depth  # log2 node edge in samples
        bad = (nb >= 0) & (s_n > edge[:, None])
        victims = np.unique(nb[bad])
        if victims.size:
            splittable = cur.depth[victims] + table.patch_log2 < np.minimum(
                k, res[cur.block[victims]]
            )
            victims = victims[splittable]
        if not victims.size:
            viol = int(bad.sum())
            cells = cur.cells_log2[:, None]
            snap = np.minimum(snap, cells)
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
                clamped=cur.clamped,
                violations=viol,
            )
        cur = _split(cur, victims, grid, table, camera, metric, res, zranges)
    raise SelectionError(f"stitching did not settle in {max_rounds} rounds")


def _split(
    cur: Patches,
    victims: np.ndarray,
    grid: BlockGrid,
    table: RefPatchTable,
    camera: Camera,
    metric: str | Metric,
    res: np.ndarray,
    zranges: np.ndarray,
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
    blocks = [tuple(int(v) for v in x) for x in cur.blocks]
    delta = np.zeros(len(b))
    for depth in np.unique(d):
        m = d == depth
        delta[m] = table.delta(blocks, b[m], int(depth), r[m], c[m])
    blk = cur.blocks[b]
    bx0, _, _, by1 = grid.block_bounds(blk[:, 0], blk[:, 1])
    size = np.left_shift(1, k - d).astype(np.float64)
    zr = np.asarray(zranges, dtype=np.float64)[b]
    cen = np.stack(
        [bx0 + (c + 0.5) * size * grid.dx, by1 - (r + 0.5) * size * grid.dy, zr.mean(1)], 1
    )
    rad = np.hypot(0.5 * size * math.hypot(grid.dx, grid.dy), 0.5 * (zr[:, 1] - zr[:, 0]))
    rho = np.asarray(get_metric(metric)(delta, cen, rad, camera), np.float64)
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
