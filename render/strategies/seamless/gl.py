"""``seamless-patches``, the GL part: the strategy instancing the cached tiles and strips (see
the package docstring); shaders ``seamless.vert`` and ``seamless_probe.vert`` beside this file.
:meth:`SeamlessPatches.cpu_triangles` is the CPU reference of the vertex shader."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import moderngl
import numpy as np

from render import measure, shaders
from render.errors import RenderError
from render.frame import FrameServices
from render.gpu import MASKED_BELOW, check_gl
from render.select import check_tau
from render.strategies.base import (
    Block,
    GlobalHeights,
    SelectionCounts,
    Strategy,
    triangle_screen_errors,
)
from render.strategies.seamless.layout import RHO_FORMS, PatchLayout
from render.strategies.seamless.meshes import mesh_kinds, mesh_of, rotate
from render.strategies.seamless.selection import select_layout
from streamer.camera import Camera

HERE = Path(__file__).parent


class SeamlessPatches(Strategy[PatchLayout]):
    """Livny, Kogan & El-Sana: tiles and strips instanced from cached meshes."""

    name = "seamless-patches"
    uses_metric = False
    what = "drawing seamless patches"

    def __init__(
        self,
        renderer: FrameServices,
        res_log2: int = 5,
        *,
        spike_guard: bool = False,
        rho: str = "bound",
        kernels: str | None = None,
    ) -> None:
        super().__init__(renderer)
        if not 1 <= res_log2 <= 7:
            raise RenderError(f"res_log2 must be in 1..7 (2..128 cells per tile), got {res_log2}")
        if rho not in RHO_FORMS:
            raise RenderError(f"rho must be one of {', '.join(RHO_FORMS)}, got {rho!r}")
        #: the form of ρ in ε = ρ l / d: "bound" (ours, the default) or "paper" (Livny et al.'s
        #: global precision factor ρ = f / (τ 2**c); the package docstring)
        self.rho = rho
        #: the selection's kernels: "numba", "numpy" (the reference) or None/"auto"
        #: (``TERRASTREAM_KERNELS``; render/strategies/seamless/kernels.py)
        self.kernels = kernels
        self.c = min(res_log2, renderer.k)
        ctx = renderer.ctx
        self.table = renderer.patch_table("bound@1", 1)
        #: not the paper's: also bound each tile's own stored error (docs/RENDER.md,
        #: "Precision and extremes"); tables of the bound at depth d + r for r = 1..c
        self.spike_guard = spike_guard
        self.tables = [renderer.patch_table(f"bound@{i}", i) for i in range(1, self.c + 1)]
        self.kinds = mesh_kinds(self.c)
        meshes = [mesh_of(self.c, kd) for kd in self.kinds]
        self.tri_count = {kd: len(m) for kd, m in zip(self.kinds, meshes, strict=True)}
        starts = np.cumsum([0] + [len(m) for m in meshes])
        self.first = {kd: int(s) for kd, s in zip(self.kinds, starts[:-1], strict=True)}
        self.kind_id = {kd: i for i, kd in enumerate(self.kinds)}
        self.tile_id = np.zeros(self.c + 1, np.int64)
        self.strip_id = np.zeros((self.c + 1, self.c + 1), np.int64)
        for i, (kind, ra, rb) in enumerate(self.kinds):
            if kind == "tile":
                self.tile_id[ra] = i
            else:
                self.strip_id[ra, rb] = i
        verts = np.concatenate(meshes).reshape(-1, 3).astype("i4")
        self.mesh_vbo = ctx.buffer(verts.tobytes())
        vs = shaders.source(HERE / "seamless.vert")
        self.prog = ctx.program(vertex_shader=vs, fragment_shader=shaders.FRAGMENT)
        self.wire = ctx.program(
            vertex_shader=vs,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        )
        self.probe_prog = ctx.program(
            vertex_shader=shaders.source(HERE / "seamless_probe.vert"),
            geometry_shader=shaders.TRIANGLE_PROBE,
        )
        self.vaos = {
            id(p): ctx.vertex_array(p, [(self.mesh_vbo, "3i", "in_uvr")])
            for p in (self.prog, self.wire, self.probe_prog)
        }
        self.heights = GlobalHeights(renderer.store)
        idx = renderer.store.index
        # the renderer's rule (0 where not finite), not tiler.quadtree's (figures are the contract)
        zr = np.stack([idx.zmin, idx.zmax], -1).astype(np.float64)
        self.zr = np.where(np.isfinite(zr), zr, 0.0)  # per block, for the edge distances
        check_gl(ctx, "creating the seamless-patches programs")

    # selection

    def warm_up_args(self) -> dict[str, Any]:
        """Its compiled kernel's signature depends on the block and tile sizes."""
        return {"seamless_shape": (self.r.k, self.c)}

    def own_gpu_bytes(self) -> int:
        """The cached tile and strip meshes (one vertex buffer)."""
        return self.mesh_vbo.size

    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
    ) -> tuple[PatchLayout, float]:
        """Leaf patches and edge levels at ``tau`` (``metric`` is ignored) and the CPU ms."""
        check_tau(tau)
        t0 = time.perf_counter()
        sel = select_layout(self, camera, tau, resident)
        if not self.stitching:  # each patch at one resolution of its own: no agreed edges
            own = sel.edge_level.min(axis=1, keepdims=True) + np.zeros_like(sel.edge_level)
            sel = dataclasses.replace(sel, edge_level=own)
        return sel, (time.perf_counter() - t0) * 1000.0

    # instances

    def instances(self, sel: PatchLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per tile and strip: mesh kind id ``(q,)``, GPU page ``(q,)`` and the ``(q, 8)`` int32
        instance (block col0, block row0, node col0, node row0, slot base, level of the
        ``2**c`` unit, quarter turns, 0)."""
        k, c = self.r.k, self.c
        n = len(sel)
        blk = sel.blocks[sel.block]
        size = np.left_shift(1, k - sel.depth)
        page = np.empty(n, np.int64)
        base = np.empty(n, np.int64)
        for i, b in enumerate(map(tuple, sel.blocks.tolist())):
            m = sel.block == i
            if m.any():
                s = self.r.slot(b)
                page[m], base[m] = s.page, s.offset
        res = sel.edge_res
        kid, pages, rows = [], [], []
        for e in range(4):
            inst = np.stack(
                [
                    blk[:, 1] << k,
                    blk[:, 0] << k,
                    sel.col * size,
                    sel.row * size,
                    base,
                    sel.depth + c,
                    np.full(n, e),
                    np.zeros(n, np.int64),
                ],
                1,
            )
            t = self.tile_id[res[:, e]]
            s = self.strip_id[res[:, e], res[:, (e + 1) % 4]]
            kid += [t, s]
            pages += [page, page]
            rows += [inst, inst]
        if not n:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 8), np.int32)
        return np.concatenate(kid), np.concatenate(pages), np.concatenate(rows).astype(np.int32)

    def triangle_count(self, sel: PatchLayout) -> int:
        """Σ cached-mesh triangles × instances."""
        kid, _, _ = self.instances(sel)
        counts = np.array([self.tri_count[kd] for kd in self.kinds], np.int64)
        return int(counts[kid].sum()) if len(kid) else 0

    def render(self, prog: moderngl.Program, sel: PatchLayout) -> None:
        if not len(sel):
            return
        kid, pages, inst = self.instances(sel)
        vao = self.vaos[id(prog)]
        prog["res_log2"].value = self.c
        for p in np.unique(pages).tolist():
            m = pages == p
            order = np.argsort(kid[m], kind="stable")
            kp, ip = kid[m][order], inst[m][order]
            self.r.bind_heights(p)
            buf = self.r.ctx.buffer(np.ascontiguousarray(ip).tobytes())
            buf.bind_to_storage_buffer(4)
            ids, starts, counts = np.unique(kp, return_index=True, return_counts=True)
            for i, s0, cnt in zip(ids.tolist(), starts.tolist(), counts.tolist(), strict=True):
                kd = self.kinds[i]
                if self.tri_count[kd] == 0:
                    continue
                prog["inst0"].value = s0
                vao.render(
                    moderngl.TRIANGLES,
                    vertices=3 * self.tri_count[kd],
                    first=3 * self.first[kd],
                    instances=cnt,
                )
            buf.release()

    def counts(self, sel: PatchLayout) -> SelectionCounts:
        return SelectionCounts.of_levels(
            self.triangle_count(sel), len(sel), sel.clamped, sel.violations, sel.edge_level
        )

    # read-back and measurement

    def triangles(self, camera: Camera, sel: PatchLayout) -> tuple[np.ndarray, np.ndarray]:
        """Every drawn triangle read back from the GPU: global ``(col, row)`` corners
        ``(m, 3, 2)`` int64 and fetched heights ``(m, 3)`` (:data:`render.gpu.MASKED` where
        masked)."""
        cap = self.triangle_count(sel)
        prog = self.probe_prog
        tri, h = self.read_triangles(
            camera, prog, cap, lambda: self.render(prog, sel),
            "reading seamless-patch triangles back",
        )  # fmt: skip
        if len(tri) != cap:
            raise RenderError(f"the GPU drew {len(tri)} triangles, expected {cap}")
        return tri, h

    def cpu_triangles(self, sel: PatchLayout) -> np.ndarray:
        """The CPU twin of the vertex shader: global ``(col, row)`` corners ``(m, 3, 2)``."""
        kid, _, inst = self.instances(sel)
        out = []
        for i, kd in enumerate(self.kinds):
            m = kid == i
            if not m.any() or self.tri_count[kd] == 0:
                continue
            mesh = mesh_of(self.c, kd)  # (t, 3, 3)
            a = inst[m].astype(np.int64)
            uv = rotate(mesh[None, :, :, :2].astype(np.int64), a[:, 6, None, None], self.c)
            unit = np.left_shift(1, self.r.k - a[:, 5])[:, None, None, None]
            org = (a[:, None, None, 0:2] + a[:, None, None, 2:4])[:, :, :, :]
            out.append((org + uv * unit).reshape(-1, 3, 2))
        if not out:
            return np.zeros((0, 3, 2), np.int64)
        return np.concatenate(out)

    def screen_errors(self, camera: Camera, sel: PatchLayout) -> np.ndarray:
        """Measured pixel errors of the samples under the read-back triangles."""
        tri, h = self.triangles(camera, sel)
        return triangle_screen_errors(self.r.grid, camera, tri, h, self.heights)

    def drawn_blocks(self, sel: PatchLayout) -> set[Block]:
        """The blocks holding at least one leaf patch."""
        return {tuple(int(v) for v in b) for b in sel.blocks[np.unique(sel.block)]}

    def surface(
        self, camera: Camera, sel: PatchLayout
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The drawn surface at the lattice samples under the read-back triangles."""
        tri, h = self.triangles(camera, sel)
        ok = (h > MASKED_BELOW).all(axis=1)
        return measure.rasterise(tri[ok], h[ok])
