"""``jung-han``, the GL part: the strategy (CPU selection over the pure quadtree of
:mod:`render.strategies.jung_han.pure`, drawing with ``jung_han.vert`` beside this file). The
drawn triangles are kept on the CPU (:attr:`JHSelection.tri`), so the measured error needs no
read-back."""

from __future__ import annotations

from pathlib import Path

import moderngl
import numpy as np

from render import measure, shaders
from render.frame import FrameServices
from render.gpu import check_gl
from render.strategies.base import (
    Block,
    GlobalHeights,
    SelectionCounts,
    Strategy,
    triangle_screen_errors,
)
from render.strategies.jung_han.pure import (
    JHSelection,
)
from render.strategies.jung_han.selection import JungHanSelector
from streamer.camera import Camera


class JungHan(JungHanSelector, Strategy[JHSelection]):
    """Jung & Han: CPU bottom-up simplification of 3×3-vertex blocks, height-adjusted cracks."""

    name = "jung-han"
    uses_metric = False
    what = "drawing jung-han blocks"

    def __init__(
        self,
        renderer: FrameServices,
        prune: bool = True,
        culled_collapse: bool = True,
        kernels: str | None = None,
    ) -> None:
        Strategy.__init__(self, renderer)  # (the base's state: build_ms)
        JungHanSelector.__init__(self, renderer, prune, culled_collapse, kernels)
        ctx = renderer.ctx
        vs = shaders.source(Path(__file__).with_name("jung_han.vert"))
        self.prog = ctx.program(vertex_shader=vs, fragment_shader=shaders.FRAGMENT)
        self.wire = ctx.program(
            vertex_shader=vs,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        )
        self.heights = GlobalHeights(renderer.store)
        check_gl(ctx, "creating the jung-han programs")

    # -- drawing -----------------------------------------------------------------------------

    def _batches(self, sel: JHSelection):
        """Per GPU page: ``(page, vertex bytes, index bytes, index count)``."""
        r = self.r
        step = r.grid.step
        if not len(sel):
            return
        slots = [r.slot(b) for b in sel.blocks]
        page = np.array([s.page for s in slots], dtype=np.int64)
        base = np.array([s.offset for s in slots], dtype=np.int64)
        blk = np.array(sel.blocks, dtype=np.int64).reshape(-1, 2)
        vs = sel.v_slot
        org_c, org_r = blk[vs, 1] * step, blk[vs, 0] * step
        attr = np.zeros((len(vs), 9), dtype=np.int32)
        attr[:, 0], attr[:, 1] = org_c, org_r
        attr[:, 2], attr[:, 3] = sel.v_cr[:, 0] - org_c, sel.v_cr[:, 1] - org_r
        attr[:, 4], attr[:, 5] = base[vs], sel.v_level
        rel = np.asarray(sel.v_h, dtype=np.float64) - r.zref  # in float64, then float32
        attr[:, 8] = rel.astype(np.float32).view(np.int32)
        tpage = page[sel.tri_slot]
        for p in np.unique(tpage).tolist():
            vm = page[vs] == p
            remap = np.cumsum(vm) - 1
            idx = remap[sel.index[tpage == p]].astype(np.int32)
            yield p, np.ascontiguousarray(attr[vm]).tobytes(), idx.tobytes(), idx.size

    def render(self, prog: moderngl.Program, sel: JHSelection) -> None:
        """The selection's triangles, one indexed draw per ``HeightPool`` page."""
        r = self.r
        ctx = r.ctx
        for page, vb, ib, n in self._batches(sel):
            r.bind_heights(page)
            vbo, ibo = ctx.buffer(vb), ctx.buffer(ib)
            vao = ctx.vertex_array(
                prog,
                [(vbo, "4i 4i f", "in_a", "in_b", "in_h")],
                index_buffer=ibo,
                index_element_size=4,
            )
            vao.render(moderngl.TRIANGLES, vertices=n)
            for o in (vao, vbo, ibo):
                o.release()

    def counts(self, sel: JHSelection) -> SelectionCounts:
        lv = np.concatenate([sel.nodes[:, 1] + 1, np.zeros(sel.corner_blocks, np.int64)])
        return SelectionCounts.of_levels(
            len(sel), len(sel.nodes) + sel.corner_blocks, sel.clamped, 0, lv
        )

    # -- measuring ---------------------------------------------------------------------------

    def triangles(self, camera: Camera, sel: JHSelection) -> tuple[np.ndarray, np.ndarray]:
        """The drawn triangles: global ``(col, row)`` corners ``(m, 3, 2)``, drawn heights."""
        return sel.tri, sel.tri_h

    def screen_errors(self, camera: Camera, sel: JHSelection) -> np.ndarray:
        """Measured pixel errors of the drawn (height-adjusted) triangles."""
        return triangle_screen_errors(self.r.grid, camera, sel.tri, sel.tri_h, self.heights)

    def drawn_blocks(self, sel: JHSelection) -> set[Block]:
        """Store blocks with at least one drawn triangle."""
        return {sel.blocks[int(s)] for s in np.unique(sel.tri_slot)}

    def surface(
        self, camera: Camera, sel: JHSelection
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The drawn surface rasterised on the sample lattice (hidden triangles left out)."""
        ok = np.isfinite(sel.tri_h).all(axis=1)
        return measure.rasterise(sel.tri[ok], sel.tri_h[ok])
