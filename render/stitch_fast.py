"""The compiled :func:`render.select.stitch` (incremental rounds; chosen with the kernels of
:mod:`render.select_kernels`): the same rounds, in the same order, giving the same patches bit
for bit (tests/render/test_stitch_fast.py).

Per round one kernel call does the snaps and the restriction (:func:`render._stitch_nb.restrict`)
and one the split (:func:`render._stitch_nb.split`: the leaves, their neighbours, the check
caches and the sorted leaf keys carried over, so no round sorts or searches all leaves again).
What stays numpy is every float operation on heights and metrics, called once per round on
all leaves that need it instead of per depth and edge: the snapped-edge check's strip errors
(:func:`render.snap_error.snap_excess` / :func:`~render.snap_error.snap_exact`, the
reference's functions) and its metric (one call, :func:`box_rho`), and the new leaves'
``rho`` (:func:`render.node_boxes.node_rho` per depth, once after the last round: no round
reads it). The metrics are elementwise, so batching them gives the reference's values."""

from __future__ import annotations

from functools import cache
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from render.errors import SelectionError
from render.node_boxes import NodeBoxes, node_box_slots, node_rho
from render.snap_error import difference_rows, sample_rows, strip_template
from streamer.camera import Camera
from streamer.levels import PatchErrorTable
from streamer.lod import Metric
from tiler.grid import BlockGrid
from tiler.quadtree import block_origins, node_centres_at

if TYPE_CHECKING:
    from render.select import Patches


def box_rho(
    fn: Metric,
    grid: BlockGrid,
    delta: np.ndarray,
    bx0: np.ndarray,
    by1: np.ndarray,
    depth: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    camera: Camera,
) -> np.ndarray:
    """:func:`render.node_boxes.node_rho` with boxes for nodes of mixed depths in one metric
    call: node ``(depth, rows, cols)`` of the block at ``(bx0, by1)``, height range
    ``lo..hi``, error ``delta`` (the same operations per node, so the same values)."""
    span = np.left_shift(1, grid.k - depth).astype(np.float64)
    cx = bx0 + (cols.astype(np.float64) + 0.5) * (span * grid.dx)
    cy = by1 - (rows.astype(np.float64) + 0.5) * (span * grid.dy)
    s = 0.5 * span
    ext = np.stack([s * grid.dx, s * grid.dy, 0.5 * (hi - lo)], 1)
    centres = np.stack([cx, cy, 0.5 * (lo + hi)], axis=1)
    radius = np.linalg.norm(ext, axis=1)
    return np.asarray(fn(delta, centres, radius, camera, half_extent=ext), np.float64)


class _Check:
    """The snapped-edge check (:func:`render.node_boxes.snap_over`) of some leaves, with the
    per-frame parts done once and the strips' bounds from the kernels ``kn``
    (:func:`strip_bounds`)."""

    def __init__(self, kn, blocks, grid, camera, fn, tau, zranges, boxes: NodeBoxes, box_slots):
        self.kn, self.blocks, self.grid, self.camera = kn, blocks, grid, camera
        self.fn, self.tau = fn, tau
        self.zr = np.asarray(zranges, dtype=np.float64)
        self.boxes, self.box_slots = boxes, box_slots
        self.buf, self.off, self.side = boxes.flat(blocks)
        self.lev = np.array([boxes.level((int(x[0]), int(x[1]))) for x in blocks], np.int64)
        self.full = self.lev >= boxes.k
        self.bx0, self.by1 = block_origins(grid, blocks[:, 0], blocks[:, 1])

    def __call__(self, b, d, r, c, lv, delta, snap) -> np.ndarray:
        """``(m, 4)`` whether each snapped edge of the leaves ``(b, d, r, c)`` (levels ``lv``,
        errors ``delta``, snaps ``snap``: every leaf has one, its error finite) fails."""
        kn, boxes = self.kn, self.boxes
        total = strip_bounds(kn, self, b, d, r, c, lv, snap)
        full = self.full[b]
        if full.any():  # full resolution at hand: the strips' exact error at their samples
            f = np.flatnonzero(full)
            total[f] = exact_bounds(kn, self, b[f], d[f], r[f], c[f], lv[f], snap[f])
        lo = np.empty(len(b))
        hi = np.empty(len(b))
        for depth in np.unique(d).tolist():
            m = np.flatnonzero(d == depth)
            bm = b[m]
            sl = (self.box_slots[0][bm], self.box_slots[1][bm])
            lo[m], hi[m] = boxes.zrange(sl, self.zr[bm], depth, r[m], c[m])
        i, e = np.nonzero(snap > 0)
        bi = b[i]
        rho = box_rho(self.fn, self.grid, total[i, e], self.bx0[bi], self.by1[bi], d[i], r[i],
                      c[i], lo[i], hi[i], self.camera)  # fmt: skip
        over = np.zeros(snap.shape, dtype=bool)
        over[i, e] = ~(rho <= self.tau)
        return over


def _c64(a: np.ndarray, dtype=np.int64) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


@cache
def _strips(cells: int, snaps: tuple[int, int, int, int]) -> list:
    """Per edge the strip's triangles ``(tj, ti, box)`` and difference rows ``(W, starts)``
    (:mod:`render.snap_error`'s cached ones, contiguous int64 for the kernels), or None."""
    out = []
    for part, wt in zip(strip_template(cells, snaps), difference_rows(cells, snaps), strict=True):
        if part is None:
            out.append(None)
            continue
        tj, ti, box = part
        out.append((_c64(tj), _c64(ti), _c64(box), wt[0], _c64(wt[1])))
    return out


@cache
def _samples(cells: int, snaps: tuple[int, int, int, int], spacing: int) -> list:
    """:func:`render.snap_error.sample_rows` with the window indices as rows and columns
    (``at_j, at_i, cor_j, cor_i, wts``, contiguous) for the kernels."""
    side = (1 << (cells + spacing)) + 1
    out = []
    for part in sample_rows(cells, snaps, spacing):
        if part is None:
            out.append(None)
            continue
        at, cor, w = (np.asarray(v) for v in part)
        out.append((_c64(at // side), _c64(at % side), _c64(cor // side), _c64(cor % side),
                    _c64(w, np.float64)))  # fmt: skip
    return out


class _Samples:
    """Every strip sample template used so far (:func:`_samples`), back to back, so one kernel
    call takes templates of many groups: per ``(cells, snaps, spacing)`` each edge's
    ``(lo, hi)`` rows (-1 for none)."""

    def __init__(self) -> None:
        self.spans: dict[tuple, np.ndarray] = {}
        self._parts: list[tuple] = []
        self.arrays: tuple[np.ndarray, ...] = ()
        self.size = 0

    def span(self, key: tuple) -> np.ndarray:
        """``(4, 2)`` the rows of ``key``'s edges (``(cells, snaps, spacing)``)."""
        out = self.spans.get(key)
        if out is None:
            out = np.full((4, 2), -1, np.int64)
            for e, part in enumerate(_samples(*key)):
                if part is not None:
                    out[e] = self.size, self.size + len(part[0])
                    self.size += len(part[0])
                    self._parts.append(part)
            cat = [np.concatenate([pt[i] for pt in self._parts]) for i in range(5)]
            self.arrays = tuple(np.ascontiguousarray(a) for a in cat)
            self.spans[key] = out
        return out


_SAMPLES = _Samples()


def exact_bounds(
    kn: ModuleType, ck: _Check, b: np.ndarray, d: np.ndarray, r: np.ndarray, c: np.ndarray,
    lv: np.ndarray, snap: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """:func:`render.snap_error.snap_exact` of leaves ``(b, d, r, c)`` of blocks held at full
    resolution: one call of the kernel ``kn.exact_all`` reading the pooled grids, each leaf's
    edges taking their group's templates (one cell count, spacing and snaps)."""
    k = ck.boxes.k
    cl, sp = lv - d, k - lv
    code = ((((cl * 64 + sp) * 64 + snap[:, 0]) * 64 + snap[:, 1]) * 64 + snap[:, 2]) * 64
    code = code + snap[:, 3]
    uniq, first, inv = np.unique(code, return_index=True, return_inverse=True)
    spans = np.stack([
        _SAMPLES.span((int(cl[i]), tuple(int(t) for t in snap[i]), int(sp[i]))) for i in first
    ])  # fmt: skip
    per = spans[inv.reshape(-1)]  # (m, 4, 2)
    lo, hi = np.ascontiguousarray(per[:, :, 0]), np.ascontiguousarray(per[:, :, 1])
    return kn.exact_all(ck.buf, ck.off, ck.side, b, d, r, c, lo, hi, *_SAMPLES.arrays, k)


def strip_bounds(
    kn: ModuleType, ck: _Check, b: np.ndarray, d: np.ndarray, r: np.ndarray, c: np.ndarray,
    lv: np.ndarray, snap: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """:func:`render.snap_error.snap_excess` with the cells' bounds (as
    :func:`render.node_boxes.snap_over` calls it) of leaves ``(b, d, r, c)``: per group of one
    cell count and snaps, the reference's matrix product, the rest in the kernels ``kn``."""
    cl = lv - d
    out = np.zeros((len(b), 4))
    code = (((cl * 64 + snap[:, 0]) * 64 + snap[:, 1]) * 64 + snap[:, 2]) * 64 + snap[:, 3]
    order = np.argsort(code, kind="stable")
    cuts = np.flatnonzero(np.diff(code[order])) + 1
    for idx in np.split(order, cuts):
        i0 = idx[0]
        cells = int(cl[i0])
        key = (cells, tuple(int(t) for t in snap[i0]))
        strips = _strips(*key)
        n = 1 << cells
        bb, dd, rr, cc, ll = b[idx], d[idx], r[idx], c[idx], lv[idx]
        h, h0, masked, cb = kn.gather_patches(
            ck.buf, ck.off, ck.side, ck.lev, bb, dd, rr, cc, ll, n, ck.boxes.k
        )
        for e, part in enumerate(strips):
            if part is None:
                continue
            tj, ti, box, w, starts = part
            dm = np.abs(h0 @ w.T)
            out[idx, e] = kn.strip_max(dm, starts, box, tj, ti, h, masked, cb, n, True)
    return out


def stitch_compiled(
    kn: ModuleType,
    patches: Patches,
    grid: BlockGrid,
    table: PatchErrorTable,
    camera: Camera,
    fn: Metric,
    *,
    res: np.ndarray,
    zranges: np.ndarray,
    max_rounds: int,
    boxes: NodeBoxes | None,
    tau: float | None,
) -> Patches:
    """:func:`render.select.stitch` (``incremental``) with the kernels ``kn``
    (:mod:`render._stitch_nb`; ``patches`` not empty, ``table`` with at least one depth)."""
    from render.select import Patches

    k, p = grid.k, table.patch_log2
    blocks = patches.blocks
    bk_r = np.ascontiguousarray(blocks[:, 0], dtype=np.int64)
    bk_c = np.ascontiguousarray(blocks[:, 1], dtype=np.int64)
    big = k + 1  # deeper than any leaf
    nr = (int(bk_r.max()) + 2) << big
    nc = (int(bk_c.max()) + 2) << big
    slots = np.ascontiguousarray(table.slots(blocks), dtype=np.int64)
    box_slots = node_box_slots(fn, boxes, blocks, res)
    check = None
    if tau is not None and box_slots is not None:
        check = _Check(kn, blocks, grid, camera, fn, tau, zranges, boxes, box_slots)
    block = patches.block.astype(np.int64)
    depth = patches.depth.astype(np.int64)
    row = patches.row.astype(np.int64)
    col = patches.col.astype(np.int64)
    level = patches.level.astype(np.int64)
    delta = patches.delta.astype(np.float64)
    n = len(depth)
    src = np.arange(n, dtype=np.int64)
    keys = kn.leaf_keys(bk_r, bk_c, block, depth, row, col, big)
    order = np.argsort(keys)
    sk = keys[order]
    nbr = kn.probe(np.arange(n), sk, order, bk_r, bk_c, block, depth, row, col, big, nr, nc)
    c_snap = np.zeros((n, 4), np.int64)
    c_over = np.zeros((n, 4), bool)
    c_known = np.zeros(n, bool)
    for _ in range(max_rounds):
        snap, n_bad, victims = kn.restrict(level, depth, block, nbr, res, k, p)
        extra = 0
        if not victims.size and check is not None:
            cand = kn.over_todo(snap, c_snap, c_over, c_known, delta)
            if cand.size:
                c_over[cand] = check(block[cand], depth[cand], row[cand], col[cand],
                                     level[cand], delta[cand], snap[cand])  # fmt: skip
            victims, extra = kn.over_victims(c_over, nbr, depth, block, res, k, p)
        if not victims.size:
            rho = _rho(patches, grid, camera, fn, zranges, boxes, box_slots, src, block,
                       depth, row, col, delta)  # fmt: skip
            return Patches(
                blocks=blocks, block=block, depth=depth, row=row, col=col, level=level,
                delta=delta, rho=rho, snap=snap, clamped=patches.clamped + extra,
                violations=int(n_bad),
            )  # fmt: skip
        leaves, nbr, redo, caches, sorted_keys = kn.split(
            victims, block, depth, row, col, level, delta, src, nbr, c_snap, c_over, c_known,
            sk, order, keys, res, bk_r, bk_c, big, k, p,
        )  # fmt: skip
        block, depth, row, col, level, delta, src = leaves
        nk = len(depth) - 4 * len(victims)  # the children's errors (as select._split)
        cd = depth[nk:]
        for dd in np.unique(cd).tolist():
            m = nk + np.flatnonzero(cd == dd)
            delta[m] = table.delta(slots[block[m]], dd, row[m], col[m])
        c_snap, c_over, c_known = caches
        sk, order, keys = sorted_keys
        if redo.size:
            nbr[redo] = kn.probe(redo, sk, order, bk_r, bk_c, block, depth, row, col, big, nr, nc)
    raise SelectionError(f"stitching did not settle in {max_rounds} rounds")


def _rho(patches, grid, camera, fn, zranges, boxes, box_slots, src, block, depth, row, col,
         delta) -> np.ndarray:  # fmt: skip
    """The final leaves' ``rho``: the selection's where ``src`` (the row in ``patches``) is
    set, else :func:`render.select._split`'s per-depth :func:`~render.node_boxes.node_rho`."""
    rho = np.empty(len(depth))
    old = src >= 0
    rho[old] = patches.rho[src[old]]
    new = np.flatnonzero(~old)
    if not new.size:
        return rho
    b, d, r, c, dl = block[new], depth[new], row[new], col[new], delta[new]
    blk = patches.blocks[b]
    bx0, by1 = block_origins(grid, blk[:, 0], blk[:, 1])
    zr = np.asarray(zranges, dtype=np.float64)[b]
    if box_slots is not None:  # node boxes: one metric call for every depth
        lo, hi = np.empty(len(b)), np.empty(len(b))
        for dd in np.unique(d).tolist():
            m = np.flatnonzero(d == dd)
            sl = (box_slots[0][b[m]], box_slots[1][b[m]])
            lo[m], hi[m] = boxes.zrange(sl, zr[m], dd, r[m], c[m])
        rho[new] = box_rho(fn, grid, dl, bx0, by1, d, r, c, lo, hi, camera)
        return rho
    for dd in np.unique(d).tolist():
        m = d == dd
        cx, cy = node_centres_at(grid, bx0[m], by1[m], dd, r[m], c[m])
        bx = None if box_slots is None else (boxes, (box_slots[0][b[m]], box_slots[1][b[m]]))
        rho[new[m]] = node_rho(fn, grid, dl[m], cx, cy, dd, zr[m], camera, bx, r[m], c[m])
    return rho


def warm_up(kn: ModuleType) -> None:
    """Load (or compile) every kernel of ``kn`` with a real frame's argument types, on a
    one-leaf stitch (so no frame pays for it)."""
    i1, z1 = np.zeros(1, np.int64), np.zeros(1)
    one = np.ones(1, np.int64)
    keys = kn.leaf_keys(i1, i1, i1, i1, i1, i1, 3)
    nbr = kn.probe(i1, keys, i1, i1, i1, i1, i1, i1, i1, 3, 8, 8)
    snap, _, victims = kn.restrict(one, i1, i1, nbr, one, 2, 1)
    c_snap, c_over, c_known = np.zeros((1, 4), np.int64), np.zeros((1, 4), bool), np.zeros(1, bool)
    kn.over_todo(snap, c_snap, c_over, c_known, z1)
    kn.over_victims(c_over, nbr, i1, i1, one, 2, 1)
    kn.split(i1, i1, i1, i1, i1, one, z1, i1, nbr, c_snap, c_over, c_known, keys, i1, keys, 2 * one,
             i1, i1, 3, 2, 1)  # fmt: skip
    off, side = np.zeros((1, 3), np.int64), np.ones((1, 3), np.int64)
    buf = np.zeros(4)
    h = kn.gather_heights(buf, off, side, i1, i1, i1, i1, i1, i1, 0)
    h, _, _, cb = kn.gather_patches(buf, off, side, i1, i1, i1, i1, i1, i1, 0, 2)
    box = np.zeros((1, 4), np.int64)
    kn.strip_max(h, i1, box, box[:, :3], box[:, :3], h, np.zeros(1, bool), cb, 0, True)
    c3 = np.zeros((1, 3), np.int64)
    lo4 = np.full((1, 4), -1, np.int64)
    kn.exact_all(buf, off, side, i1, i1, i1, i1, lo4, lo4, i1, i1, c3, c3, np.zeros((1, 3)), 0)
