"""Frame services: what every LOD strategy draws with (docs/RENDER.md, "Frame services").

:class:`FrameServices` owns one store's GPU state and offers it through a small, typed, public
interface; no strategy reaches into it otherwise:

* the **framebuffer** (:meth:`~FrameServices.begin_frame`, :meth:`~FrameServices.timed_frame`,
  :meth:`~FrameServices.image`);
* the **height pool** (:meth:`~FrameServices.sync`, :meth:`~FrameServices.upload`,
  :meth:`~FrameServices.bind_heights`, :meth:`~FrameServices.slot`,
  :meth:`~FrameServices.drawable`);
* the **index textures** and **camera uniforms** (:meth:`~FrameServices.set_camera`: integer
  camera cell, fraction, MVP, spacing, sun, z range, viewport, and the level/order textures);
* **triangle read-back** (:meth:`~FrameServices.read_triangles`, transform feedback into an SSBO
  with the rasteriser off);
* **block data** (:meth:`~FrameServices.block_grid`, :meth:`~FrameServices.stored_errors`,
  :meth:`~FrameServices.mask`): from the synced session while it holds them, else the store
  (:mod:`render.block_source`);
* **patch tables** (:meth:`~FrameServices.patch_table`, :meth:`~FrameServices.fill_table`:
  pooled stored errors per node size, dropped with their blocks), **patch instances**
  (:meth:`~FrameServices.instances`: the instance layout of ``render/glsl/fetch.glsl``) and a
  per-renderer cache of shared programs and meshes (:meth:`~FrameServices.shared`).

Positions are computed on the GPU relative to the camera from integer sample indices (see
docs/RENDER.md), so shared vertices are bit-identical and far-from-origin scenes keep their
precision. Qiu's CLOD itself lives in :mod:`render.strategies.qiu`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

import moderngl
import numpy as np

from render.block_source import BlockSource
from render.errors import RenderError
from render.frame_types import (  # noqa: F401  (CLEAR, RenderStats: re-exported)
    CLEAR,
    RenderConfig,
    RenderStats,
    Slot,
    ramp_map,
)
from render.gpu import MASKED_BELOW, HeightPool, check_gl, create_context
from render.node_boxes import NodeBoxes
from render.select import Patches, PatchTable, check_drawable
from render.views import CAMERA_CELL_LIMIT
from streamer.camera import Camera
from streamer.nodata import check_rule, gap_widths, raise_all
from tiler.crs import require_projected
from tiler.layout import level_index, order_index
from tiler.store import TerrainStore

if TYPE_CHECKING:
    from streamer.session import Session

Block = tuple[int, int]
T = TypeVar("T")
#: binding points of the shared buffers and textures (render/glsl/*.glsl)
HEIGHTS_BINDING, LEVEL_TEX_UNIT, ORDER_TEX_UNIT, TRIANGLES_BINDING = 0, 1, 2, 3
#: OpenGL's enum of the first user clip distance (``render/glsl/emit.glsl``'s nodata clip)
GL_CLIP_DISTANCE0 = 0x3000


class FrameServices:
    """One store's GPU state: framebuffer, height pool, index textures, camera uniforms,
    triangle read-back, patch tables and programs (the interface every strategy uses)."""

    def __init__(
        self,
        store: TerrainStore,
        config: RenderConfig | None = None,
        *,
        ctx: moderngl.Context | None = None,
    ) -> None:
        require_projected(store)  # x/y in degrees beside heights in metres draws streaks
        self.store = store
        self.config = config or RenderConfig()
        self.grid = store.grid
        self.k = store.k
        self.p = min(self.config.patch_log2, self.k)
        self._own_ctx = ctx is None  # made here: released by close()
        self.ctx = ctx or create_context()
        self.make_current()  # every GL object of the renderer is made in its own context
        ctx = self.ctx
        w, h = self.config.size
        self.fbo = ctx.framebuffer(
            color_attachments=[ctx.renderbuffer((w, h), 4)],
            depth_attachment=ctx.depth_renderbuffer((w, h)),
        )
        self.fbo.use()
        li = np.ascontiguousarray(level_index(self.k), dtype=np.uint8)
        oi = np.ascontiguousarray(order_index(self.k), dtype=np.int32)
        side = li.shape[0]
        self.level_tex = ctx.texture((side, side), 1, li.tobytes(), dtype="u1")
        self.order_tex = ctx.texture((side, side), 1, oi.tobytes(), dtype="i4")
        for t in (self.level_tex, self.order_tex):
            t.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._tables: dict[str, PatchTable | NodeBoxes] = {}
        self._shared: dict[str, Any] = {}
        self.source = BlockSource(store)  # grids, errors, masks: the session's, else the store's
        self._seen: dict[Block, int] = {}
        self._frame = 0
        idx = store.index
        self._zr = np.stack([idx.zmin, idx.zmax], axis=-1)
        vr = store.meta.extra.get("value_range")
        zmin, zmax = (float(np.nanmin(idx.zmin)), float(np.nanmax(idx.zmax)))
        self.zrange = (float(vr[0]), float(vr[1])) if vr else (zmin, zmax)
        self.terrain_zrange = (zmin, zmax)
        mid = 0.5 * (zmin + zmax)
        #: the store's reference height: the pool holds float32(h - zref) (subtracted in
        #: float64), the shaders get the camera's height above it; an integer, so integer DEMs
        #: stay exact in float32
        self.zref = float(round(mid)) if math.isfinite(mid) else 0.0
        self.pool = HeightPool(ctx, self.k, zref=self.zref)
        check_gl(ctx, "creating the renderer")

    def make_current(self) -> None:
        """Make the renderer's GL context current (about 1 µs): its GL objects live there, and
        their names mean other objects, or none, in another context that other code (a renderer
        made without ``ctx``, the CLI) may have made current in between."""
        self.ctx.__enter__()  # moderngl: eglMakeCurrent; nothing to undo

    # -- height pool ---------------------------------------------------------------------------

    def mask(self, block: Block) -> np.ndarray | None:
        """The block's validity mask, None without nodata or padding
        (:mod:`render.block_source`)."""
        return self.source.mask(block)

    def mixed_nodes(self, block: Block) -> list[np.ndarray] | None:
        """Per depth ``0..k-1`` the block's nodes holding both terrain and nodata, None
        without a mask boundary (:mod:`render.block_source`)."""
        return self.source.mixed(block)

    def mixed_nodes_later(self, block: Block) -> Callable[[], list[np.ndarray] | None]:
        """:meth:`mixed_nodes` as a function to call later, on any thread
        (:meth:`render.block_source.BlockSource.mixed_later`)."""
        return self.source.mixed_later(block)

    def stored_errors(self, block: Block) -> dict[str, list[np.ndarray]]:
        """The block's stored error fields (``TerrainStore.read_errors``; from the synced
        session when its loaders kept them: :mod:`render.block_source`)."""
        return self.source.errors(block)

    def upload(self, block: Block, levels: list[np.ndarray]) -> int:
        """Put a block's decoded levels on the GPU (only the new ones); return its GPU level."""
        self._seen[block] = self._frame
        mask = self.mask(block)
        self.make_current()
        return self.pool.upload(block, levels, mask)

    def block_grid(self, block: Block, level: int) -> np.ndarray:
        """The block's level-``level`` grid in the source dtype (``TerrainStore.read_block``'s
        values; from the synced session's levels while it holds them:
        :mod:`render.block_source`)."""
        return self.source.grid(block, level)

    def block_grid_later(self, block: Block, level: int) -> Callable[[], np.ndarray]:
        """:meth:`block_grid` as a function to call later, on any thread (the session's levels
        taken now: :meth:`render.block_source.BlockSource.grid_later`)."""
        return self.source.grid_later(block, level)

    def sync(self, frame_blocks: dict[Block, tuple[int, int]], session: Session) -> None:
        """Upload what a streaming frame holds (``Frame.blocks``) and drop long-gone blocks."""
        self._frame += 1
        self.source.attach(session)
        for b, (res, _need) in frame_blocks.items():
            self._seen[b] = self._frame
            if res > self.pool.level(b):
                self.upload(b, session.levels(b)[: res + 1])
        for b in list(self.pool.slots):
            if self._frame - self._seen.get(b, -(10**9)) > self.config.linger_frames:
                self.pool.release(b)
                self._seen.pop(b, None)
                self.source.forget(b)  # (its mask: kept only while on the GPU)
                for t in self._tables.values():
                    t.remove(b)

    def slot(self, block: Block) -> Slot:
        """The block's place in the height pool (KeyError if it is not on the GPU)."""
        s = self.pool.slots[block]
        return Slot(page=s.page, offset=s.offset, level=s.level)

    def gpu_level(self, block: Block) -> int:
        """The finest level of ``block`` in the height pool (-1 when it is not on the GPU)."""
        return self.pool.level(block)

    @property
    def height_bytes(self) -> int:
        """Bytes of heights in the pool's pages (the GPU bytes every frame reports)."""
        return self.pool.used_bytes

    def bind_heights(self, page: int) -> None:
        """Bind height-pool page ``page`` as the ``Heights`` buffer (binding 0)."""
        self.pool.pages[page].buffer.bind_to_storage_buffer(HEIGHTS_BINDING)

    def drawable(self, resident: dict[Block, int] | None = None) -> list[tuple[Block, int]]:
        """``(block, level)`` sorted: the blocks a frame may draw and the finest level of each —
        the lower of the cap in ``resident`` (default: what the GPU holds) and the GPU's level;
        a block is drawn when both are >= 0."""
        pool = self.pool
        levels = resident if resident is not None else {b: s.level for b, s in pool.slots.items()}
        pairs = sorted(
            (tuple(b), min(int(lv), pool.level(b))) for b, lv in levels.items() if lv >= 0
        )
        return [(b, lv) for b, lv in pairs if lv >= 0]

    def block_zranges(self, blocks: np.ndarray) -> np.ndarray:
        """``(n, 2)`` stored ``(zmin, zmax)`` of the ``(n, 2)`` blocks, 0 where not finite."""
        # not tiler.quadtree.block_zranges: its store-range rule for blocks without terrain
        # would change those blocks' spheres and so the figures (the figures are the contract)
        blk = np.asarray(blocks, dtype=np.int64).reshape(-1, 2)
        zr = self._zr[(blk[:, 0], blk[:, 1])]
        return np.where(np.isfinite(zr), zr, 0.0)

    # -- patch tables and programs -------------------------------------------------------------

    def patch_table(self, name: str, patch_log2: int | None = None) -> PatchTable:
        """The renderer's pooled patch-error table ``name`` for nodes of ``2**patch_log2``
        cells (default: the renderer's patch size), made on first use; blocks leaving the GPU
        leave every table."""
        t = self._tables.get(name)
        if t is None:
            size = self.p if patch_log2 is None else patch_log2
            t = self._tables[name] = PatchTable(self.k, size)
        return t

    def node_boxes(
        self, pairs: list[tuple[Block, int]], patch_log2: int | None = None, nodata: str = "full"
    ) -> NodeBoxes:
        """The renderer's per-node boxes (:mod:`render.node_boxes`) for nodes of
        ``2**patch_log2`` cells (default: the renderer's patch size), holding every
        ``(block, level)`` of ``pairs``: a block is (re)built from its level-``level`` grid
        (:meth:`block_grid`) when that level changed (nothing finer is read); blocks leaving
        the GPU leave it. The boxes' ranges take the rule ``full``'s bound (a mixed
        node's box is its block's height range); the snapped-edge check's cell bounds take the
        nodata rule ``nodata``'s, the errors the selection itself uses."""
        size = self.p if patch_log2 is None else patch_log2
        rule = check_rule(nodata)
        key = f"node-boxes/{size}/{rule}"
        boxes = self._tables.get(key)
        if boxes is None:
            boxes = self._tables[key] = NodeBoxes(self.k, size)
        for b, lv in pairs:
            if boxes.level(b) != lv:
                grid = self.block_grid(b, lv)
                zr = self.block_zranges(np.array([b]))[0]
                mask = self.mask(b)
                step = 1 << (self.k - lv)
                valid = None if mask is None else mask[::step, ::step]
                bound = self.read_errors(b)["bound"]
                cells = None if rule == "full" else self.read_errors(b, rule)["bound"]
                boxes.update(b, lv, grid, bound, (zr[0], zr[1]), valid, cells)
        return boxes

    def fill_table(
        self, table: PatchTable, blocks: list[Block], field: str, nodata: str = "full"
    ) -> None:
        """Add the error ``field`` (:meth:`read_errors` with the nodata rule ``nodata``) of the
        ``blocks`` not yet in ``table``; the field ``"gap"`` is :meth:`gap_field`."""
        for b in blocks:
            if b not in table:
                gap = field == "gap"
                table.add(b, self.gap_field(b) if gap else self.read_errors(b, nodata)[field])

    def gap_field(self, block: Block) -> list[np.ndarray]:
        """Per depth ``0..k-1`` the diagonal in metres of each mixed cell, 0 elsewhere
        (:func:`streamer.nodata.gap_widths`; all 0 without a mask boundary)."""
        k = self.k
        mixed = self.mixed_nodes(block)
        if mixed is None:
            return [np.zeros((1 << d, 1 << d), np.float32) for d in range(k)]
        return gap_widths(self.mask(block), k, self.grid.dx, self.grid.dy, mixed)

    def read_errors(self, block: Block, nodata: str = "full") -> dict[str, list[np.ndarray]]:
        """The block's stored error fields; with the nodata rule ``"full"`` every node
        (depths ``0..k-1``) whose closed footprint holds both valid and masked samples is
        raised to ``inf`` (docs/RENDER.md, "Precision and extremes"): a mask boundary is
        refined to full resolution at every τ, so terrain beside nodata is drawn from its valid
        samples and no hole is bridged. With ``"gap"`` the stored fields (the selection then
        refines mixed cells by :meth:`gap_field`)."""
        if check_rule(nodata) == "full":
            full = self.source.full_errors(block)  # (the session's loaders derived them)
            if full is not None:
                return full
        errors = self.stored_errors(block)
        return errors if nodata == "gap" else raise_all(errors, self.mask(block), self.k)

    def shared(self, key: str, make: Callable[[FrameServices], T]) -> T:
        """The object (programs, meshes) cached under ``key`` on this renderer, built by
        ``make(self)`` on first use and shared by every strategy instance drawing with it."""
        obj = self._shared.get(key)
        if obj is None:
            self.make_current()
            obj = self._shared[key] = make(self)
            check_gl(self.ctx, f"building {key!r}")
        return obj

    # -- camera, frames, read-back ---------------------------------------------------------------

    def set_camera(self, prog: moderngl.Program, camera: Camera) -> None:
        """Set ``prog``'s camera and terrain uniforms (those it declares) and bind the level and
        order index textures (units 1 and 2)."""
        g = self.grid
        cx, cy, cz = camera.position
        ci = math.floor((cx - g.x0) / g.dx)
        ri = math.floor((g.y0 - cy) / g.dy)
        if max(abs(ci), abs(ri)) >= CAMERA_CELL_LIMIT:
            raise RenderError(
                f"the camera at ({cx:.6g}, {cy:.6g}) lies {max(abs(ci), abs(ri)):.3g} cells "
                "from the DEM's origin, beyond the renderer's 32-bit cell index (2^31 "
                "cells); bring the camera closer to the DEM"
            )
        fx = cx - (g.x0 + ci * g.dx)
        fy = cy - (g.y0 - ri * g.dy)
        mvp = camera.projection_matrix() @ camera.view_matrix()
        values = {
            "k": self.k,
            "patch_log2": self.p,
            "cam_cell": (ci, ri),
            "cam_frac": (fx, fy, cz),
            "spacing": (g.dx, g.dy),
            "mvp": mvp.T.astype("f4").tobytes(),
            "depth_log": (camera.near, 1.0 / math.log2(camera.far / camera.near)),
            "sun": self.config.sun,
            "zrange": self.zrange,
            "cam_z": cz - self.zref,
            "ramp_map": ramp_map(self.zrange, self.zref),
            "viewport": (self.config.size[0] / 2, self.config.size[1] / 2),
        }
        for name, v in values.items():
            if name in prog:
                if isinstance(v, bytes):
                    prog[name].write(v)
                else:
                    prog[name].value = v
        self.level_tex.use(LEVEL_TEX_UNIT)
        self.order_tex.use(ORDER_TEX_UNIT)

    def instances(self, patches: Patches) -> dict[int, np.ndarray]:
        """Per height-pool page, the ``(n, 8)`` int32 instance attributes of its patches (block
        origin, node origin, slot base, level, cells_log2, packed snaps: ``fetch.glsl``)."""
        k = self.k
        blk = patches.blocks[patches.block]
        e = np.left_shift(1, k - patches.depth)
        pages = np.empty(len(patches), dtype=np.int64)
        base = np.empty(len(patches), dtype=np.int64)
        held = np.empty(len(patches), dtype=np.int64)
        for i, b in enumerate(map(tuple, patches.blocks.tolist())):
            m = patches.block == i
            s = self.pool.slots.get(b)
            if s is None and m.any():
                raise RenderError(f"patches of block {b}, which is not on the GPU")
            if s is not None:
                pages[m], base[m], held[m] = s.page, s.offset, s.level
        check_drawable(patches, held)
        sn = patches.snap
        packed = sn[:, 0] | (sn[:, 1] << 4) | (sn[:, 2] << 8) | (sn[:, 3] << 12)
        inst = np.stack(
            [
                blk[:, 1] << k,
                blk[:, 0] << k,
                patches.col * e,
                patches.row * e,
                base,
                patches.level,
                patches.cells_log2,
                packed,
            ],
            1,
        ).astype(np.int32)
        return {int(p): inst[pages == p] for p in np.unique(pages)}

    def begin_frame(
        self,
        camera: Camera,
        prog: moderngl.Program,
        *,
        clear: tuple[int, int, int] | None = None,
        lod_colour: bool = False,
        holes: bool = False,
    ) -> float:
        """Bind and clear the framebuffer, set the camera uniforms and the index textures for
        ``prog`` (``holes``: draw the triangles of nodata holes instead of discarding them);
        returns the frame's start time (``perf_counter``)."""
        if tuple(camera.viewport) != tuple(self.config.size):
            raise RenderError(
                f"camera viewport {camera.viewport} differs from the renderer's {self.config.size}"
            )
        ctx = self.ctx
        self.make_current()
        self.fbo.use()
        t0 = time.perf_counter()
        c = clear or self.config.clear
        self.fbo.clear(c[0] / 255, c[1] / 255, c[2] / 255, 1.0, depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        self.set_camera(prog, camera)
        if "lod_colour" in prog:
            prog["lod_colour"].value = int(lod_colour)
        if "show_holes" in prog:
            prog["show_holes"].value = int(holes)
        return t0

    def timed_frame(
        self,
        camera: Camera,
        prog: moderngl.Program,
        body: Callable[[], None],
        *,
        clear: tuple[int, int, int] | None,
        lod_colour: bool,
        what: str,
        holes: bool = False,
    ) -> float:
        """Begin the frame for ``prog``, run ``body`` (the draw calls), wait for the GPU and
        check for GL errors; the frame's wall time in ms."""
        t0 = self.begin_frame(camera, prog, clear=clear, lod_colour=lod_colour, holes=holes)
        self.ctx.enable_direct(GL_CLIP_DISTANCE0)  # a triangle with a masked corner is not
        try:  # drawn at all (render/glsl/emit.glsl; with ``holes`` its distances are all 0)
            body()
        finally:
            self.ctx.disable_direct(GL_CLIP_DISTANCE0)  # (other programs do not write it)
        self.ctx.finish()
        ms = (time.perf_counter() - t0) * 1000.0
        check_gl(self.ctx, what)
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
        ``triangle_probe.geom``) with the rasteriser discarded; every triangle's global
        ``(col, row)`` corners ``(m, 3, 2)`` int64 and heights ``(m, 3)``
        (:data:`render.gpu.MASKED` where masked). More than ``cap`` triangles is an error."""
        self.make_current()
        self.fbo.use()  # an EGL context has no default framebuffer
        self.set_camera(prog, camera)
        out = self.ctx.buffer(reserve=16 + max(cap, 1) * 36)
        out.write(np.zeros(4, np.uint32).tobytes())
        out.bind_to_storage_buffer(TRIANGLES_BINDING)
        prog["cap"].value = cap
        self.ctx.enable(moderngl.RASTERIZER_DISCARD)
        try:
            body()
        finally:
            self.ctx.disable(moderngl.RASTERIZER_DISCARD)
        raw = out.read()
        out.release()
        check_gl(self.ctx, what)
        count = int(np.frombuffer(raw[:4], np.uint32)[0])
        if count > cap:
            raise RenderError(f"{what}: the GPU made {count} triangles, expected at most {cap}")
        a = np.frombuffer(raw[16:], np.float32)[: 9 * count].reshape(-1, 3, 3).astype(np.float64)
        return np.rint(a[..., :2]).astype(np.int64), self.absolute(a[..., 2])

    def absolute(self, h: np.ndarray) -> np.ndarray:
        """Heights read back from the GPU (relative to :attr:`zref`) as float64 world heights;
        masked ones stay :data:`render.gpu.MASKED`."""
        h = np.asarray(h, dtype=np.float64)
        return np.where(h > MASKED_BELOW, h + self.zref, h)

    def drawn_pixels(self) -> int:
        """How many pixels the last draw covered with terrain (depth written below the clear
        depth 1.0), whatever their colour: 0 for a view of sky only."""
        w, h = self.config.size
        self.make_current()
        depth = np.frombuffer(self.fbo.read(attachment=-1, dtype="f4"), dtype=np.float32)
        return int(np.count_nonzero(depth[: w * h] < 1.0))

    def surface_points(self, camera: Camera) -> np.ndarray:
        """Where the last draw (from ``camera``) met terrain: per pixel, top row first, the world
        point ``(x, y, z)`` on the pixel centre's ray at the depth written (the logarithmic
        depth inverted), NaN where nothing was drawn."""
        w, h = self.config.size
        self.make_current()
        raw = np.frombuffer(self.fbo.read(attachment=-1, dtype="f4"), dtype=np.float32)
        d = raw[: w * h].reshape(h, w)[::-1].astype(np.float64)
        dist = camera.near * np.exp2(d * math.log2(camera.far / camera.near))  # along forward
        dist[d >= 1.0] = np.nan
        u = (np.arange(w) + 0.5 - w / 2.0) / camera.focal_px
        v = (h / 2.0 - (np.arange(h) + 0.5)) / camera.focal_px
        ray = (
            camera.forward[None, None, :]
            + u[None, :, None] * camera.right[None, None, :]
            + v[:, None, None] * camera.up[None, None, :]
        )
        return camera.eye[None, None, :] + dist[..., None] * ray

    def image(self) -> np.ndarray:
        """The framebuffer as an ``(h, w, 3)`` uint8 array, top row first."""
        w, h = self.config.size
        self.make_current()
        data = self.fbo.read(components=3, alignment=1)
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3)[::-1].copy()

    def close(self) -> None:
        """Release the height pool's GPU buffers, and the GL context when the renderer made it
        (unbound first: EGL keeps a released context current until it is unbound)."""
        if not self.pool.pages and not self._own_ctx:
            return
        self.make_current()
        self.pool.close()
        if self._own_ctx:
            self._own_ctx = False
            self.ctx.__exit__(None, None, None)  # eglMakeCurrent(EGL_NO_CONTEXT)
            self.ctx.release()
