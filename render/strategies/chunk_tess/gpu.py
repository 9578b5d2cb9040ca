"""``chunk-tessellation`` with ``selection="gpu"``: Kim, Lee & Shin's traversal on the GPU
(see the package docstring). Shaders ``traverse.glsl``, ``traverse.geom``, ``emit.geom``
beside this file; the pass machinery is :mod:`render.strategies.feedback`'s (shared with
``geometry-splitting``)."""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import moderngl
import numpy as np

from render import shaders
from render.errors import RenderError
from render.frame import FrameServices
from render.gpu import check_gl
from render.select import Patches, PatchTable, check_tau
from render.strategies.base import Block
from render.strategies.chunk_tess.pure import start_depth
from render.strategies.feedback import block_neighbours, feedback_pass
from streamer.camera import Camera
from streamer.frustum import frustum_hull

HERE = Path(__file__).parent
GS = HERE.parent / "geometry_splitting"
UNSET = -2  # a node channel whose neighbour level is not known yet (traverse.glsl)
MAX_HULL = 32  # vertices of the frustum's ground hull the shaders take
#: the largest tau the traversal's float32 uniform holds (a larger finite tau splits the same
#: nodes: their errors, float32 too, are either finite and below it or inf)
TAU_MAX = float(np.finfo(np.float32).max)


@dataclass(eq=False)
class GpuChunks:
    """GPU-made chunks of one frame: per height page a buffer of draw vertices (the
    :meth:`FrameServices.instances` layout); only the statistics are read back."""

    blocks: list[Block]
    table: np.ndarray  # (m, 16) int32 block table
    pass_counts: list[int]  # nodes after each traversal pass
    pages: dict[int, tuple[moderngl.Buffer, int]]  # page -> (vertices, chunks)
    clamped: int = 0
    violations: int = 0
    triangles: int = 0
    max_level: int = -1
    min_level: int = -1
    gpu_ms: float = 0.0  # wall time of the traversal and emit passes (GPU work)
    leaf_buf: moderngl.Buffer | None = None
    _cache: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return sum(n for _, n in self.pages.values())


def _release(bufs) -> None:
    for b in bufs:
        if b is not None:
            b.release()


def hull_uniforms(camera: Camera, zrange: tuple[float, float]) -> tuple[np.ndarray, bool]:
    """The frustum's ground hull (:func:`streamer.frustum.frustum_hull`, what the CPU variant
    culls with) relative to the eye as ``(MAX_HULL, 2)`` float32, its vertex count and whether
    it is counter-clockwise with positive area (:class:`render.select.DiscCull`)."""
    poly = frustum_hull(camera, zrange)
    if len(poly) > MAX_HULL:
        raise RenderError(f"the frustum hull has {len(poly)} vertices, more than {MAX_HULL}")
    p = poly - poly[0] if len(poly) else poly
    area2 = float(np.sum(p[:-1, 0] * p[1:, 1] - p[1:, 0] * p[:-1, 1])) if len(p) else 0.0
    out = np.zeros((MAX_HULL, 2), np.float32)
    out[: len(poly)] = poly - np.asarray(camera.eye, np.float64)[:2]
    return out, len(poly), len(poly) >= 3 and area2 > 0.0


class GpuSelector:
    """The GPU traversal's programs, chunk-error buffer and block table for one strategy."""

    def __init__(self, r: FrameServices, chunk_log2: int, table: PatchTable) -> None:
        self.r, self.c, self.table = r, chunk_log2, table
        self.start = start_depth(r.k, chunk_log2)
        ctx = r.ctx
        vs = shaders.source(GS / "tri.vert")  # in_a, in_b -> v_a, v_b (geometry-splitting's)
        self.traverse = ctx.program(
            vertex_shader=vs,
            geometry_shader=shaders.source(HERE / "traverse.geom"),
            varyings=["o_a", "o_b"],
        )
        self.emit = ctx.program(
            vertex_shader=vs,
            geometry_shader=shaders.source(HERE / "emit.geom"),
            varyings=["o_a", "o_b"],
        )
        self._offset: dict[Block, int] = {}
        self._buf: moderngl.Buffer | None = None
        check_gl(ctx, "creating the chunk traversal programs")

    def gpu_bytes(self) -> int:
        """The chunk-error buffer."""
        return self._buf.size if self._buf is not None else 0

    def _upload(self, blocks: list[Block]) -> None:
        """Every drawn block's pooled chunk errors ``ε`` (the CPU variant's ``PatchTable``,
        depths ``0..k-c-1`` in depth order) in one float32 buffer; rebuilt when a block is new
        (load-time work, like geometry-splitting's quadtree texture)."""
        if all(b in self._offset and b in self.table for b in blocks):
            return
        keep = sorted(set(blocks) | {b for b in self._offset if b in self.table})
        self.r.fill_table(self.table, keep, "bound")
        depths = self.table.depths
        parts, self._offset, used = [], {}, 0
        for b in keep:
            slot = self.table.slots([b])
            for d in range(depths):
                rr, cc = np.indices((1 << d, 1 << d)).reshape(2, -1)
                parts.append(self.table.delta(np.repeat(slot, rr.size), d, rr, cc))
            self._offset[b] = used
            used += ((1 << (2 * depths)) - 1) // 3
        data = np.concatenate(parts).astype(np.float32) if parts else np.zeros(1, np.float32)
        if self._buf is not None:
            self._buf.release()
        self._buf = self.r.ctx.buffer(data.tobytes() or bytes(4))

    def block_table(self, pairs: list[tuple[Block, int]]) -> np.ndarray:
        """``(m, 16)`` int32 (see ``traverse.glsl``): origin, pool base, cap; ε offset, page,
        DEM window size; neighbours; the block's height range (float32 bits)."""
        r, k = self.r, self.r.k
        blocks = [b for b, _ in pairs]
        t = np.zeros((len(blocks), 16), dtype=np.int64)
        if not blocks:
            return t.astype(np.int32)
        blk = np.array(blocks, dtype=np.int64)
        win = r.store.index.window[(blk[:, 0], blk[:, 1])]
        zr = r.block_zranges(blk).astype(np.float32).view(np.int32)
        for i, (b, lv) in enumerate(pairs):
            s = r.slot(b)
            t[i, 0:4] = (b[1] << k, b[0] << k, s.offset, lv)
            t[i, 4:8] = (self._offset[b], s.page, win[i, 2], win[i, 3])
        t[:, 8:12] = block_neighbours(blocks)
        t[:, 12:14] = zr
        return t.astype(np.int32)

    def _bind(self, prog: moderngl.Program, camera: Camera, tau: float, hull, block_buf) -> None:
        self.r.fbo.use()
        self.r.set_camera(prog, camera)
        poly, n_poly, ccw = hull
        # a float32 uniform: a finite tau beyond float32's range would read +inf (and the
        # traversal's ``!(inf <= inf)`` would stop splitting mixed nodes, error inf)
        values = {"tau": min(float(tau), TAU_MAX), "chunk": self.c, "start_depth": self.start}
        values |= {"n_poly": n_poly, "poly_ccw": int(ccw)}
        for name, v in values.items():
            if name in prog:
                prog[name].value = v
        if "poly" in prog:
            prog["poly"].write(poly.tobytes())
        block_buf.bind_to_storage_buffer(4)
        self._buf.bind_to_storage_buffer(5)

    def select(
        self,
        camera: Camera,
        tau: float,
        *,
        resident: dict[Block, int] | None = None,
        stitching: bool = True,
    ) -> tuple[GpuChunks, float]:
        """The traversal passes and the emit pass for ``camera`` at ``tau``; the CPU ms (block
        table and uniforms; the ε upload is load-time work, left out)."""
        check_tau(tau)
        r, ctx = self.r, self.r.ctx
        r.make_current()  # the passes make and use GL objects of the renderer's context
        t0 = time.perf_counter()
        pairs = r.drawable(resident)
        blocks = [b for b, _ in pairs]
        tb = time.perf_counter()
        self._upload(blocks)
        build_ms = (time.perf_counter() - tb) * 1000.0
        table = self.block_table(pairs)
        hull = hull_uniforms(camera, r.terrain_zrange)
        block_buf = ctx.buffer(np.ascontiguousarray(table).tobytes() or bytes(64))
        stats = ctx.buffer(np.array([0, 0, 0, -1, 1 << 30, 0, 0, 0], np.int32).tobytes())
        sel = GpuChunks(blocks, table, [], {})
        tg = time.perf_counter()
        n = len(blocks)
        if n:
            roots = np.zeros((n, 8), np.int32)
            roots[:, 0] = np.arange(n)
            roots[:, 4:] = UNSET
            src = ctx.buffer(roots.tobytes())
            stats.bind_to_storage_buffer(7)
            for p in range(max(0, r.k - self.c) + 1):
                self._bind(self.traverse, camera, tau, hull, block_buf)
                self.traverse["cull_input"].value = int(p == 0)
                out, n = feedback_pass(ctx, self.traverse, src, "4i 4i", ["in_a", "in_b"], n, 4, 32)
                src.release()
                src = out
                sel.pass_counts.append(n)
                if n == 0:
                    break
            sel.leaf_buf = src
        if sel.pass_counts and sel.pass_counts[-1]:
            self._bind(self.emit, camera, tau, hull, block_buf)
            self.emit["stitch"].value = int(stitching)
            stats.bind_to_storage_buffer(7)
            for page in sorted({int(p) for p in table[:, 5]}):
                self.emit["page"].value = page
                buf, m = feedback_pass(
                    ctx, self.emit, sel.leaf_buf, "4i 4i", ["in_a", "in_b"], n, 1, 32
                )
                if m:
                    sel.pages[page] = (buf, m)
                else:
                    buf.release()
            st = np.frombuffer(stats.read(), np.int32).tolist()
            sel.clamped, sel.violations, sel.triangles = st[0], st[1], st[2]
            sel.max_level, sel.min_level = st[3], st[4]
        stats.release()
        block_buf.release()
        check_gl(ctx, "traversing the chunk quadtree")
        sel.gpu_ms = (time.perf_counter() - tg) * 1000.0
        bufs = [sel.leaf_buf] + [b for b, _ in sel.pages.values()]
        weakref.finalize(sel, _release, bufs)
        return sel, (tg - t0) * 1000.0 - build_ms

    def patches(self, sel: GpuChunks) -> Patches:
        """The drawn chunks read back from the emitted vertices as :class:`Patches`, sorted by
        ``(block, depth, row, col)`` (``delta`` from the ε table, ``rho`` not kept: NaN)."""
        if "patches" in sel._cache:
            return sel._cache["patches"]
        k = self.r.k
        parts = [
            np.frombuffer(buf.read(size=32 * m), np.int32).reshape(-1, 8)
            for buf, m in sel.pages.values()
        ]
        a = np.concatenate(parts).astype(np.int64) if parts else np.zeros((0, 8), np.int64)
        blocks = np.array(sel.blocks, dtype=np.int64).reshape(-1, 2)
        index = {b: i for i, b in enumerate(sel.blocks)}
        block = np.array([index[(int(r_) >> k, int(c_) >> k)] for c_, r_ in a[:, :2]], np.int64)
        level, cells = a[:, 5], a[:, 6]
        depth = level - cells
        row, col = a[:, 3] >> (k - depth), a[:, 2] >> (k - depth)
        snap = np.stack([(a[:, 7] >> (4 * e)) & 15 for e in range(4)], 1)
        order = np.lexsort((col, row, depth, block))
        block, depth, row, col = block[order], depth[order], row[order], col[order]
        delta = np.zeros(len(order))
        if len(order):
            slots = self.table.slots(blocks)
            for d in np.unique(depth).tolist():
                m = depth == d
                delta[m] = self.table.delta(slots[block[m]], d, row[m], col[m])
        p = Patches(
            blocks=blocks,
            block=block,
            depth=depth,
            row=row,
            col=col,
            level=level[order],
            delta=delta,
            rho=np.full(len(order), np.nan),
            snap=snap[order],
            clamped=sel.clamped,
            violations=sel.violations,
        )
        sel._cache["patches"] = p
        return p
