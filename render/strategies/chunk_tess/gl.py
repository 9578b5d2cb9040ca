"""``chunk-tessellation``, the GL part: the strategy drawing tessellated chunks (see the
package docstring); shaders ``chunk.vert``, ``chunk.tesc``, ``chunk.tese``,
``chunk_probe.tese`` beside this file."""

from __future__ import annotations

from pathlib import Path

import moderngl
import numpy as np

from render import measure, shaders
from render.errors import RenderError
from render.frame import FrameServices
from render.gpu import MASKED_BELOW, check_gl
from render.select import Patches
from render.strategies.base import (
    Block,
    GlobalHeights,
    SelectionCounts,
    Strategy,
    triangle_screen_errors,
)
from render.strategies.chunk_tess.pure import batch_chunks, kim_metric, tess_triangles
from render.strategies.qiu import patch_blocks, patch_levels, select_clod, unstitched
from streamer.camera import Camera

HERE = Path(__file__).parent


def _src(name: str) -> str:
    return shaders.source(HERE / name)


class ChunkTessellation(Strategy[Patches]):
    """Kim, Lee & Shin: tessellated chunks with neighbour-matched outer factors."""

    name = "chunk-tessellation"
    uses_metric = False
    what = "drawing tessellated chunks"

    def __init__(self, renderer: FrameServices, chunk_log2: int = 5) -> None:
        super().__init__(renderer)
        if not 0 <= chunk_log2 <= 6:
            raise RenderError(
                f"chunk_log2 must be in 0..6 (tessellation factor <= 64), got {chunk_log2}"
            )
        self.c = min(chunk_log2, renderer.k)
        ctx = renderer.ctx
        self.table = renderer.patch_table(f"bound@chunk{self.c}", self.c)
        vs, tcs, tes = _src("chunk.vert"), _src("chunk.tesc"), _src("chunk.tese")
        self.prog = ctx.program(
            vertex_shader=vs,
            tess_control_shader=tcs,
            tess_evaluation_shader=tes,
            fragment_shader=shaders.FRAGMENT,
        )
        self.wire = ctx.program(
            vertex_shader=vs,
            tess_control_shader=tcs,
            tess_evaluation_shader=tes,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        )
        self.probe_prog = ctx.program(
            vertex_shader=vs,
            tess_control_shader=tcs,
            tess_evaluation_shader=_src("chunk_probe.tese"),
            geometry_shader=shaders.TRIANGLE_PROBE,
        )
        self.heights = GlobalHeights(renderer.store)
        check_gl(ctx, "creating the chunk-tessellation programs")

    def select(self, camera, tau, metric="qiu", *, resident=None) -> tuple[Patches, float]:
        sel, ms = select_clod(
            self.r, camera, tau, kim_metric, resident=resident, table=self.table, field="bound"
        )
        return (sel if self.stitching else unstitched(sel)), ms  # unmatched outer factors

    def _passes(self, prog: moderngl.Program, patches: Patches):
        """Per height page, in batches of at most :func:`batch_chunks` chunks: ``(vao, n)``."""
        per = batch_chunks(self.c)
        for page, inst in self.r.instances(patches).items():
            self.r.bind_heights(page)
            for i in range(0, len(inst), per):
                part = np.ascontiguousarray(inst[i : i + per])
                buf = self.r.ctx.buffer(part.tobytes())
                vao = self.r.ctx.vertex_array(prog, [(buf, "4i 4i", "in_a", "in_b")])
                yield vao, len(part)
                vao.release()
                buf.release()

    def render(self, prog: moderngl.Program, sel: Patches) -> None:
        self.r.ctx.patch_vertices = 1
        for vao, n in self._passes(prog, sel):
            vao.render(moderngl.PATCHES, vertices=n)

    def counts(self, sel: Patches) -> SelectionCounts:
        tris = int(tess_triangles(sel.cells_log2, sel.snap).sum())
        return SelectionCounts.of_levels(tris, len(sel), sel.clamped, sel.violations, sel.level)

    def triangles(self, camera: Camera, sel: Patches) -> tuple[np.ndarray, np.ndarray]:
        """Every tessellated triangle read back (:meth:`Strategy.read_triangles`): global
        ``(col, row)`` corners ``(m, 3, 2)`` int64 and fetched heights ``(m, 3)``."""
        cap = int(tess_triangles(sel.cells_log2, sel.snap).sum())
        prog = self.probe_prog
        return self.read_triangles(
            camera, prog, cap, lambda: self.render(prog, sel), "reading tessellated triangles back"
        )

    def screen_errors(self, camera: Camera, sel: Patches) -> np.ndarray:
        tri, h = self.triangles(camera, sel)
        return triangle_screen_errors(self.r.grid, camera, tri, h, self.heights)

    def used_levels(self, camera: Camera, sel: Patches) -> dict[Block, int]:
        """The finest chunk level drawn in each block (tessellated vertices are its samples)."""
        return patch_levels(sel)

    def drawn_blocks(self, sel: Patches) -> set[Block]:
        return patch_blocks(sel)

    def surface(self, camera: Camera, sel: Patches):
        tri, h = self.triangles(camera, sel)
        ok = (h > MASKED_BELOW).all(axis=1)
        return measure.rasterise(tri[ok], h[ok])
