"""``chunk-tessellation``, the GL part: the strategy drawing tessellated chunks (see the
package docstring) selected on the CPU or, ``selection="gpu"``, on the GPU (:mod:`.gpu`);
shaders ``chunk.vert``, ``chunk.tesc``, ``chunk.tese``, ``chunk_probe.tese`` beside this file."""

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
from render.strategies.chunk_tess.gpu import GpuChunks, GpuSelector
from render.strategies.chunk_tess.pure import (
    batch_chunks,
    kim_metric,
    start_depth,
    tess_triangles,
)
from render.strategies.qiu import patch_blocks, patch_levels, select_clod, unstitched
from streamer.camera import Camera

HERE = Path(__file__).parent
SELECTIONS = ("cpu", "gpu")


def _src(name: str) -> str:
    return shaders.source(HERE / name)


class ChunkTessellation(Strategy[Patches | GpuChunks]):
    """Kim, Lee & Shin: tessellated chunks with neighbour-matched outer factors, selected on
    the CPU (``selection="cpu"``, the default) or on the GPU (``"gpu"``, the paper's)."""

    name = "chunk-tessellation"
    uses_metric = False
    what = "drawing tessellated chunks"

    def __init__(
        self, renderer: FrameServices, chunk_log2: int = 5, selection: str = "cpu"
    ) -> None:
        super().__init__(renderer)
        if not 0 <= chunk_log2 <= 6:
            raise RenderError(
                f"chunk_log2 must be in 0..6 (tessellation factor <= 64), got {chunk_log2}"
            )
        if selection not in SELECTIONS:
            raise RenderError(f"selection must be one of {SELECTIONS}, got {selection!r}")
        self.c = min(chunk_log2, renderer.k)
        self.selection = selection
        ctx = renderer.ctx
        self.table = renderer.patch_table(f"bound@chunk{self.c}", self.c)
        self.gpu = GpuSelector(renderer, self.c, self.table) if selection == "gpu" else None
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

    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
    ) -> tuple[Patches | GpuChunks, float]:
        if self.gpu is not None:
            return self.gpu.select(camera, tau, resident=resident, stitching=self.stitching)
        sel, ms = select_clod(
            self.r, camera, tau, kim_metric, resident=resident, table=self.table, field="bound"
        )
        return (sel if self.stitching else unstitched(sel)), ms  # unmatched outer factors

    def select_twin(
        self, camera: Camera, tau: float, resident: dict[Block, int] | None = None
    ) -> Patches:
        """The CPU selection the GPU traversal reproduces: :func:`select_clod` with the
        traversal's start depth (:func:`start_depth`; 0, i.e. the CPU variant itself, when
        ``k <= 2c``)."""
        sel, _ = select_clod(
            self.r, camera, tau, kim_metric, resident=resident, table=self.table, field="bound",
            min_depth=start_depth(self.r.k, self.c),
        )  # fmt: skip
        return sel if self.stitching else unstitched(sel)

    def patches(self, sel: Patches | GpuChunks) -> Patches:
        """The selection's chunks as :class:`Patches` (a GPU selection is read back)."""
        return self.gpu.patches(sel) if isinstance(sel, GpuChunks) else sel

    def _passes(self, prog: moderngl.Program, sel: Patches | GpuChunks):
        """Per height page, in batches of at most :func:`batch_chunks` chunks:
        ``(vao, first, n)``."""
        per = batch_chunks(self.c)
        ctx = self.r.ctx
        if isinstance(sel, GpuChunks):
            pages = [(page, buf, n, False) for page, (buf, n) in sorted(sel.pages.items())]
        else:
            pages = [
                (page, ctx.buffer(np.ascontiguousarray(inst).tobytes()), len(inst), True)
                for page, inst in self.r.instances(sel).items()
            ]
        for page, buf, n, own in pages:
            self.r.bind_heights(page)
            vao = ctx.vertex_array(prog, [(buf, "4i 4i", "in_a", "in_b")])
            for i in range(0, n, per):
                yield vao, i, min(per, n - i)
            vao.release()
            if own:
                buf.release()

    def render(self, prog: moderngl.Program, sel: Patches | GpuChunks) -> None:
        self.r.ctx.patch_vertices = 1
        for vao, first, n in self._passes(prog, sel):
            vao.render(moderngl.PATCHES, vertices=n, first=first)

    def counts(self, sel: Patches | GpuChunks) -> SelectionCounts:
        if isinstance(sel, GpuChunks):
            return SelectionCounts(
                triangles=sel.triangles,
                patches=len(sel),
                clamped=sel.clamped,
                violations=sel.violations,
                max_level=sel.max_level,
                min_level=sel.min_level if len(sel) else -1,
            )
        tris = int(tess_triangles(sel.cells_log2, sel.snap).sum())
        return SelectionCounts.of_levels(tris, len(sel), sel.clamped, sel.violations, sel.level)

    def extra_frame_ms(self, sel: Patches | GpuChunks) -> float:
        """The GPU traversal's passes (timed in :meth:`select`; 0 for a CPU selection)."""
        return sel.gpu_ms if isinstance(sel, GpuChunks) else 0.0

    def own_gpu_bytes(self) -> int:
        """The GPU variant's chunk-error buffer."""
        return self.gpu.gpu_bytes() if self.gpu is not None else 0

    def triangles(self, camera: Camera, sel: Patches | GpuChunks) -> tuple[np.ndarray, np.ndarray]:
        """Every tessellated triangle read back (:meth:`Strategy.read_triangles`): global
        ``(col, row)`` corners ``(m, 3, 2)`` int64 and fetched heights ``(m, 3)``."""
        cap = self.counts(sel).triangles
        prog = self.probe_prog
        return self.read_triangles(
            camera, prog, cap, lambda: self.render(prog, sel), "reading tessellated triangles back"
        )

    def screen_errors(self, camera: Camera, sel: Patches | GpuChunks) -> np.ndarray:
        tri, h = self.triangles(camera, sel)
        return triangle_screen_errors(self.r.grid, camera, tri, h, self.heights)

    def used_levels(self, camera: Camera, sel: Patches | GpuChunks) -> dict[Block, int]:
        """The finest chunk level drawn in each block (tessellated vertices are its samples)."""
        return patch_levels(self.patches(sel))

    def drawn_blocks(self, sel: Patches | GpuChunks) -> set[Block]:
        return patch_blocks(self.patches(sel))

    def surface(
        self, camera: Camera, sel: Patches | GpuChunks
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        tri, h = self.triangles(camera, sel)
        ok = (h > MASKED_BELOW).all(axis=1)
        return measure.rasterise(tri[ok], h[ok])


class ChunkTessellationGpu(ChunkTessellation):
    """``chunk-tessellation`` selecting on the GPU (Kim, Lee & Shin's traversal, 3.1–3.2)."""

    name = "chunk-tessellation-gpu"

    def __init__(self, renderer: FrameServices, chunk_log2: int = 5) -> None:
        super().__init__(renderer, chunk_log2, selection="gpu")
