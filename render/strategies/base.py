"""The strategy interface and the generic measurement of a drawn triangle mesh.

A strategy (:class:`Strategy`) turns a camera, τ and the resident levels into a *selection*
(whatever it draws from), draws it with a :class:`render.renderer.TerrainRenderer` (same store,
same ``HeightPool`` and level/order-index fetch, same framebuffer) and returns the renderer's
:class:`render.renderer.RenderStats`. For the measured screen error every strategy gives the
drawn surface on the CPU: :meth:`Strategy.screen_errors` (the CLOD patches use the exact CPU twin
in :mod:`render.measure`; other strategies read their drawn triangles back — with transform
feedback when the GPU makes them — and rasterise them on the sample lattice with
:func:`triangle_screen_errors`).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

import moderngl
import numpy as np

from render import measure
from render.errors import RenderError
from render.gpu import check_gl
from render.renderer import RenderStats, TerrainRenderer
from streamer.camera import Camera
from tiler.grid import BlockGrid
from tiler.layout import level_index
from tiler.store import TerrainStore

Block = tuple[int, int]


class Strategy(ABC):
    """One LOD method over a renderer. Subclasses set ``name`` and implement the hooks."""

    name = ""
    #: the session's metric argument is honoured (otherwise the strategy has its own error)
    uses_metric = True

    def __init__(self, renderer: TerrainRenderer) -> None:
        self.r = renderer

    @abstractmethod
    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
    ) -> tuple[Any, float]:
        """The selection at ``tau`` and its CPU ms."""
        ...

    @abstractmethod
    def draw(self, camera: Camera, sel: Any, **kw: Any) -> RenderStats:
        """Draw the selection (``wireframe``, ``lod_colour``, ``clear``, ``selection_ms``)."""
        ...

    @abstractmethod
    def screen_errors(self, camera: Camera, sel: Any) -> np.ndarray:
        """Measured pixel errors of every full-resolution sample under the drawn surface."""
        ...

    @abstractmethod
    def drawn_blocks(self, sel: Any) -> set[Block]:
        """The blocks the selection draws from."""
        ...

    def used_levels(self, camera: Camera, sel: Any) -> dict[Block, int]:
        """The finest store level the drawn surface reads in each block, from the drawn
        triangles (``self.triangles(camera, sel)``; strategies without it override this)."""
        tri, _ = self.triangles(camera, sel)  # type: ignore[attr-defined]
        return block_levels(self.r.grid, tri)

    def own_gpu_bytes(self) -> int:
        """Bytes of GPU buffers the strategy keeps besides the shared ``HeightPool`` (cached
        meshes, quadtree textures); counted in the comparison's GPU bytes."""
        return 0

    def timed_frame(
        self,
        camera: Camera,
        prog: moderngl.Program,
        body: Callable[[], None],
        *,
        clear: tuple[int, int, int] | None,
        lod_colour: bool,
        what: str,
    ) -> float:
        """Begin the renderer's frame for ``prog``, run ``body`` (the draw calls), wait for the
        GPU and check for GL errors; the frame's wall time in ms."""
        r = self.r
        t0 = r.begin_frame(camera, prog, clear=clear, lod_colour=lod_colour)
        body()
        r.ctx.finish()
        ms = (time.perf_counter() - t0) * 1000.0
        check_gl(r.ctx, what)
        return ms

    def read_triangles(
        self,
        camera: Camera,
        prog: moderngl.Program,
        cap: int,
        body: Callable[[], None],
        what: str,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Run ``body`` (draw calls with ``prog``, whose geometry shader is
        :data:`render.shaders.TRIANGLE_PROBE`) with the rasteriser discarded; every triangle's
        global ``(col, row)`` corners ``(m, 3, 2)`` int64 and heights ``(m, 3)`` (-1e30 masked).
        More than ``cap`` triangles is an error."""
        r = self.r
        r.fbo.use()  # an EGL context has no default framebuffer
        r._uniforms(prog, camera)
        r.level_tex.use(1)
        r.order_tex.use(2)
        out = r.ctx.buffer(reserve=16 + max(cap, 1) * 36)
        out.write(np.zeros(4, np.uint32).tobytes())
        out.bind_to_storage_buffer(3)
        prog["cap"].value = cap
        r.ctx.enable(moderngl.RASTERIZER_DISCARD)
        try:
            body()
        finally:
            r.ctx.disable(moderngl.RASTERIZER_DISCARD)
        raw = out.read()
        out.release()
        check_gl(r.ctx, what)
        count = int(np.frombuffer(raw[:4], np.uint32)[0])
        if count > cap:
            raise RenderError(f"{what}: the GPU made {count} triangles, expected at most {cap}")
        a = np.frombuffer(raw[16:], np.float32)[: 9 * count].reshape(-1, 3, 3).astype(np.float64)
        return np.rint(a[..., :2]).astype(np.int64), a[..., 2]

    @abstractmethod
    def surface(self, camera: Camera, sel: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The drawn surface at full-resolution samples: global ``(rows, cols, heights)``
        (used for popping; a sample may appear more than once)."""
        ...


def block_levels(grid: BlockGrid, tri_cr: np.ndarray) -> dict[Block, int]:
    """Per block, the finest level of any corner of the triangles ``(m, 3, 2)`` (global
    ``(col, row)``) lying in it (a triangle belongs to the block holding its centroid; a sample
    belongs to the level that first stores it, :func:`tiler.layout.level_index`)."""
    tri = np.asarray(tri_cr, dtype=np.int64).reshape(-1, 3, 2)
    if not len(tri):
        return {}
    step = grid.step
    cen = tri.sum(axis=1) // 3
    bc = np.clip(cen[:, 0] // step, 0, grid.cols - 1)
    br = np.clip(cen[:, 1] // step, 0, grid.rows - 1)
    li = level_index(grid.k)
    col = np.clip(tri[..., 0] - (bc * step)[:, None], 0, step)
    row = np.clip(tri[..., 1] - (br * step)[:, None], 0, step)
    lv = li[row, col].max(axis=1).astype(np.int64)
    key = br * grid.cols + bc
    out = np.full(grid.rows * grid.cols, -1, np.int64)
    np.maximum.at(out, key, lv)
    return {(int(i // grid.cols), int(i % grid.cols)): int(v) for i, v in enumerate(out) if v >= 0}


class GlobalHeights:
    """Full-resolution heights (float64, NaN where masked) at global ``(row, col)`` samples."""

    def __init__(self, store: TerrainStore) -> None:
        self.store = store
        self.grid = store.grid
        self._cache: dict[Block, np.ndarray] = {}

    def block(self, b: Block) -> np.ndarray:
        """One block's full-resolution grid (cached)."""
        if b not in self._cache:
            g = self.store.read_block(b).astype(np.float64)
            if self.store.index.has_nodata[b]:
                g[~self.store.read_mask(b)] = np.nan
            self._cache[b] = g
        return self._cache[b]

    def __call__(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        g = self.grid
        step = g.step
        br = np.clip(rows // step, 0, g.rows - 1)
        bc = np.clip(cols // step, 0, g.cols - 1)
        out = np.full(rows.shape, np.nan)
        key = br * g.cols + bc
        for kv in np.unique(key).tolist():
            m = key == kv
            b = (kv // g.cols, kv % g.cols)
            out[m] = self.block(b)[rows[m] - b[0] * step, cols[m] - b[1] * step]
        return out


def triangle_screen_errors(
    grid: BlockGrid,
    camera: Camera,
    tri_cr: np.ndarray,
    tri_h: np.ndarray,
    true_h: GlobalHeights,
) -> np.ndarray:
    """The renderer's measured screen error for a triangle mesh given as global integer sample
    ``(col, row)`` corners ``(m, 3, 2)`` and drawn heights ``(m, 3)`` (NaN or <= -1e29: hidden).

    Every lattice sample a triangle covers is evaluated (linear interpolation of the drawn
    heights); a sample covered by two triangles (shared edges) is counted once per triangle,
    which does not change max or p99 noticeably. Same projection and view test as
    :func:`render.measure.screen_errors`.
    """
    h = np.asarray(tri_h, dtype=np.float64)
    ok = np.isfinite(h).all(axis=1) & (h > -1e29).all(axis=1)
    tri = np.asarray(tri_cr, dtype=np.int64)[ok]
    h = h[ok]
    if not len(tri):
        return np.zeros(0)
    rows, cols, hlod = measure.rasterise(tri, h)
    htrue = true_h(rows, cols)
    good = np.isfinite(htrue) & np.isfinite(hlod)
    rows, cols, hlod, htrue = rows[good], cols[good], hlod[good], htrue[good]
    x, y = grid.sample_xy(rows, cols)
    return measure.pixel_errors(camera, x, y, htrue, hlod)
