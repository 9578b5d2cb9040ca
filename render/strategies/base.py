"""The strategy interface and the generic measurement of a drawn triangle mesh.

A strategy (:class:`Strategy`, generic over its selection type ``S``) turns a camera, τ and the
resident levels into a *selection* (whatever it draws from) and draws it through the frame
services (:class:`render.frame.FrameServices`: same store, ``HeightPool``, level/order-index
fetch and framebuffer). :meth:`Strategy.draw` is shared: it runs the strategy's draw calls
(:meth:`Strategy.render`) in one timed frame and assembles :class:`render.frame.RenderStats`
from the selection's :class:`SelectionCounts` (:func:`frame_stats`). For the measured screen
error every strategy gives the drawn surface on the CPU: :meth:`Strategy.screen_errors` (the
CLOD patches use the exact CPU twin in :mod:`render.measure`; other strategies read their drawn
triangles back — with transform feedback when the GPU makes them — and rasterise them on the
sample lattice with :func:`triangle_screen_errors`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import moderngl
import numpy as np

from render import measure
from render.frame import FrameServices, RenderStats
from render.gpu import MASKED_BELOW
from streamer.camera import Camera
from tiler.grid import BlockGrid
from tiler.layout import level_index
from tiler.store import TerrainStore

Block = tuple[int, int]
S = TypeVar("S")


@dataclass(frozen=True)
class DrawOptions:
    """How a selection is drawn: wireframe overlay, LOD colours, the clear colour (default:
    the renderer's), the selection's CPU ms to report in the stats, and ``holes``: the triangles
    of nodata holes drawn instead of discarded (for the crack count, which must tell a hole in
    the data from a crack: :func:`render.pipeline.drawn_cracks`)."""

    wireframe: bool = False
    lod_colour: bool = False
    clear: tuple[int, int, int] | None = None
    selection_ms: float = 0.0
    holes: bool = False

    @classmethod
    def of(cls, options: DrawOptions | None = None, **kw: Any) -> DrawOptions:
        """``options`` (default: the defaults) with the keyword fields ``kw`` replaced."""
        base = options or cls()
        return cls(**{**base.__dict__, **kw}) if kw else base


@dataclass(frozen=True)
class SelectionCounts:
    """A selection's figures for :class:`render.frame.RenderStats`."""

    triangles: int
    patches: int
    clamped: int
    violations: int
    max_level: int
    min_level: int

    @classmethod
    def of_levels(
        cls, triangles: int, patches: int, clamped: int, violations: int, levels: np.ndarray
    ) -> SelectionCounts:
        """Counts with the level range of ``levels`` (-1, -1 when empty)."""
        lv = np.asarray(levels)
        return cls(
            triangles=int(triangles),
            patches=int(patches),
            clamped=int(clamped),
            violations=int(violations),
            max_level=int(lv.max()) if lv.size else -1,
            min_level=int(lv.min()) if lv.size else -1,
        )


def frame_stats(
    services: FrameServices,
    counts: SelectionCounts,
    frame_ms: float,
    options: DrawOptions,
    extra_gpu_bytes: int = 0,
) -> RenderStats:
    """The one assembly of a drawn frame's :class:`RenderStats` (GPU bytes = the height pool's
    plus ``extra_gpu_bytes``)."""
    return RenderStats(
        triangles=counts.triangles,
        patches=counts.patches,
        selection_ms=options.selection_ms,
        frame_ms=frame_ms,
        gpu_bytes=services.height_bytes + extra_gpu_bytes,
        clamped=counts.clamped,
        violations=counts.violations,
        max_level=counts.max_level,
        min_level=counts.min_level,
    )


class Strategy(ABC, Generic[S]):
    """One LOD method over the frame services ``r``. Subclasses set ``name`` (and ``what``,
    the GL-error context of a draw), build ``prog``/``wire`` and implement the hooks."""

    name = ""
    #: the session's metric argument is honoured (otherwise the strategy has its own error)
    uses_metric = True
    #: what a draw is doing, for GL error messages
    what = "drawing a frame"
    #: the strategy's crack removal is on (False only for the crack detectors' positive
    #: controls: qiu/chunk edge snaps zeroed, jung-han heights unadjusted and unsplit,
    #: geometry-splitting without its splitting passes, seamless tiles without edge strips)
    stitching = True
    #: the nodata rules (:data:`streamer.nodata.NODATA_RULES`) its ``nodata=`` option takes
    #: (only ``"full"``: the option is not taken at all)
    nodata_rules: tuple[str, ...] = ("full",)
    prog: moderngl.Program
    wire: moderngl.Program

    def __init__(self, renderer: FrameServices) -> None:
        self.r = renderer
        #: ms the last :meth:`select` spent on the render thread building per-block data
        #: (quadtree textures, ε tables) outside its selection ms
        self.build_ms = 0.0
        #: the render thread's CPU ms in that work (``time.thread_time``; ``build_ms`` is wall)
        self.build_cpu_ms = 0.0

    def build_in_background(self) -> bool:
        """Build per-block data that can wait (a level change's) on a worker thread from now
        on, drawing with the data it replaces until it is ready; whether the strategy does
        (default: it has none). Call :meth:`close` when done."""
        return False

    def close(self) -> None:
        """Stop what :meth:`build_in_background` started (the GL objects stay the
        renderer's)."""

    def warm_up_args(self) -> dict[str, Any]:
        """Keyword arguments of :func:`render.strategies.warm_up_kernels` for this strategy's
        kernels on this store (default: none needed)."""
        return {}

    @abstractmethod
    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
    ) -> tuple[S, float]:
        """The selection at ``tau`` and its CPU ms."""
        ...

    @abstractmethod
    def render(self, prog: moderngl.Program, sel: S) -> None:
        """Issue the draw calls of ``sel`` with ``prog`` (the frame is begun and timed by
        :meth:`draw`; ``prog`` is ``self.prog``, ``self.wire`` or a read-back program)."""
        ...

    @abstractmethod
    def counts(self, sel: S) -> SelectionCounts:
        """Triangles, patches, clamped nodes, violations and level range of ``sel``."""
        ...

    def extra_frame_ms(self, sel: S) -> float:
        """GPU ms spent on ``sel`` outside the draw (e.g. a GPU selection), added to it."""
        return 0.0

    def draw_gpu_bytes(self) -> int:
        """GPU bytes a drawn frame reports besides the height pool's: the strategy's own
        buffers (:meth:`own_gpu_bytes`), as ``tradeoff`` and ``compare`` count them."""
        return self.own_gpu_bytes()

    def draw(
        self, camera: Camera, sel: S, options: DrawOptions | None = None, **kw: Any
    ) -> RenderStats:
        """Draw the selection in one timed frame; ``options`` (:class:`DrawOptions`) or its
        fields as keywords (``wireframe``, ``lod_colour``, ``clear``, ``selection_ms``)."""
        o = DrawOptions.of(options, **kw)
        prog = self.wire if o.wireframe else self.prog
        ms = self.r.timed_frame(
            camera, prog, lambda: self.render(prog, sel), clear=o.clear,
            lod_colour=o.lod_colour or o.wireframe, what=self.what, holes=o.holes,
        )  # fmt: skip
        return frame_stats(
            self.r, self.counts(sel), self.extra_frame_ms(sel) + ms, o, self.draw_gpu_bytes()
        )

    @abstractmethod
    def screen_errors(self, camera: Camera, sel: S) -> np.ndarray:
        """Measured pixel errors of every full-resolution sample under the drawn surface."""
        ...

    @abstractmethod
    def drawn_blocks(self, sel: S) -> set[Block]:
        """The blocks the selection draws from."""
        ...

    def triangles(self, camera: Camera, sel: S) -> tuple[np.ndarray, np.ndarray]:
        """The drawn triangles: global ``(col, row)`` corners ``(m, 3, 2)`` int64 and drawn
        heights ``(m, 3)`` (NaN or :data:`render.gpu.MASKED` where hidden); the cracks,
        coverage and watertightness figures are taken from them."""
        raise NotImplementedError(f"strategy {self.name!r} does not give its drawn triangles")

    def used_levels(self, camera: Camera, sel: S) -> dict[Block, int]:
        """The finest store level the drawn surface reads in each block, from the drawn
        triangles (``self.triangles(camera, sel)``; strategies without it override this)."""
        tri, _ = self.triangles(camera, sel)
        return block_levels(self.r.grid, tri)

    def own_gpu_bytes(self) -> int:
        """Bytes of GPU buffers the strategy keeps besides the shared ``HeightPool`` (cached
        meshes, quadtree textures); counted in the comparison's GPU bytes."""
        return 0

    def read_triangles(
        self,
        camera: Camera,
        prog: moderngl.Program,
        cap: int,
        body: Callable[[], None],
        what: str,
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`render.frame.FrameServices.read_triangles` (kept for the strategies)."""
        return self.r.read_triangles(camera, prog, cap, body, what)

    @abstractmethod
    def surface(self, camera: Camera, sel: S) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    ``(col, row)`` corners ``(m, 3, 2)`` and drawn heights ``(m, 3)`` (NaN or <=
    :data:`render.gpu.MASKED_BELOW`: hidden).

    Every lattice sample a triangle covers is evaluated (linear interpolation of the drawn
    heights); a sample covered by several triangles (shared edges) is counted once, with its
    largest error (:func:`render.measure.sample_errors`), as :func:`render.measure.screen_errors`
    does, so max, p99 and mean compare across strategies.
    """
    h = np.asarray(tri_h, dtype=np.float64)
    ok = np.isfinite(h).all(axis=1) & (h > MASKED_BELOW).all(axis=1)
    tri = np.asarray(tri_cr, dtype=np.int64)[ok]
    h = h[ok]
    if not len(tri):
        return np.zeros(0)
    rows, cols, hlod = measure.rasterise(tri, h)
    htrue = true_h(rows, cols)
    good = np.isfinite(htrue) & np.isfinite(hlod)
    rows, cols, hlod, htrue = rows[good], cols[good], hlod[good], htrue[good]
    return measure.sample_errors(grid, camera, rows, cols, htrue, hlod)
