"""The terrain renderer: patches selected on the CPU, drawn as instanced grids whose heights the
vertex shader fetches from the GPU height pool (displacement mapping, Qiu's steps 1-4).

Per frame only the patch layout travels to the GPU: per instance the block origin, the node's
origin, the slot base, the level, the cells and the four edge snaps. Positions are computed on
the GPU relative to the camera from integer sample indices (see docs/RENDER.md), so shared
vertices are bit-identical in every patch and far-from-origin scenes keep their precision.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import moderngl
import numpy as np

from render import shaders
from render.errors import RenderError
from render.gpu import HeightPool, check_gl, create_context
from render.mesh import grid_indices, grid_vertices, triangle_counts
from render.select import Patches, PatchTable, select_patches, stitch
from streamer.camera import Camera
from streamer.frustum import frustum_hull
from streamer.lod import FIELD_FOR_METRIC, get_metric
from tiler.layout import level_index, order_index
from tiler.store import TerrainStore

Block = tuple[int, int]
CLEAR = (255, 0, 255)  # magenta: contrasts with every terrain colour


@dataclass(frozen=True)
class RenderConfig:
    """Renderer settings."""

    size: tuple[int, int] = (1024, 768)
    patch_log2: int = 4
    clear: tuple[int, int, int] = (135, 170, 210)
    sun: tuple[float, float, float] = (-0.5, 0.6, 0.65)
    linger_frames: int = 30  # keep blocks that left the view this long on the GPU

    def __post_init__(self) -> None:
        w, h = self.size
        if not (1 <= w <= 16384 and 1 <= h <= 16384):
            raise RenderError(f"viewport {w}x{h} is outside 1..16384 pixels per side")
        if not 0 <= self.patch_log2 <= 7:
            raise RenderError(f"patch_log2 must be in 0..7, got {self.patch_log2}")


@dataclass(frozen=True)
class RenderStats:
    """One rendered frame's figures."""

    triangles: int
    patches: int
    selection_ms: float
    frame_ms: float
    gpu_bytes: int
    clamped: int  # nodes drawn coarser than wanted because the level was not resident
    violations: int
    max_level: int
    min_level: int


class TerrainRenderer:
    """Draws one store's resident blocks into an offscreen framebuffer."""

    def __init__(
        self,
        store: TerrainStore,
        config: RenderConfig | None = None,
        *,
        ctx: moderngl.Context | None = None,
    ) -> None:
        self.store = store
        self.config = config or RenderConfig()
        self.grid = store.grid
        self.k = store.k
        self.p = min(self.config.patch_log2, self.k)
        self.ctx = ctx or create_context()
        ctx = self.ctx
        w, h = self.config.size
        self.fbo = ctx.framebuffer(
            color_attachments=[ctx.renderbuffer((w, h), 4)],
            depth_attachment=ctx.depth_renderbuffer((w, h)),
        )
        self.fbo.use()
        self.prog = ctx.program(vertex_shader=shaders.VERTEX, fragment_shader=shaders.FRAGMENT)
        self.wire = ctx.program(
            vertex_shader=shaders.VERTEX,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        )
        self.probe_prog = ctx.program(vertex_shader=shaders.PROBE, varyings=["out_h", "out_g"])
        n = 1 << self.p
        self.mesh_vbo = ctx.buffer(grid_vertices(n).astype("i4").tobytes())
        self.mesh_ibo = ctx.buffer(grid_indices(n).astype("i4").tobytes())
        self.mesh_vertices = (n + 1) ** 2
        li = np.ascontiguousarray(level_index(self.k), dtype=np.uint8)
        oi = np.ascontiguousarray(order_index(self.k), dtype=np.int32)
        side = li.shape[0]
        self.level_tex = ctx.texture((side, side), 1, li.tobytes(), dtype="u1")
        self.order_tex = ctx.texture((side, side), 1, oi.tobytes(), dtype="i4")
        for t in (self.level_tex, self.order_tex):
            t.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.pool = HeightPool(ctx, self.k)
        self.tables: dict[str, PatchTable] = {}
        self._masks: dict[Block, np.ndarray | None] = {}
        self._seen: dict[Block, int] = {}
        self._frame = 0
        idx = store.index
        self._zr = np.stack([idx.zmin, idx.zmax], axis=-1)
        vr = store.meta.extra.get("value_range")
        zmin, zmax = (float(np.nanmin(idx.zmin)), float(np.nanmax(idx.zmax)))
        self.zrange = (float(vr[0]), float(vr[1])) if vr else (zmin, zmax)
        self.terrain_zrange = (zmin, zmax)
        check_gl(ctx, "creating the renderer")

    # -- data --------------------------------------------------------------------------------

    def mask(self, block: Block) -> np.ndarray | None:
        """The block's validity mask (None when it has no nodata or padding)."""
        if block not in self._masks:
            has = bool(self.store.index.has_nodata[block])
            self._masks[block] = self.store.read_mask(block) if has else None
        return self._masks[block]

    def upload(self, block: Block, levels: list[np.ndarray]) -> int:
        """Put a block's decoded levels on the GPU (only the new ones); return its GPU level."""
        self._seen[block] = self._frame
        return self.pool.upload(block, levels, self.mask(block))

    def sync(self, frame_blocks: dict[Block, tuple[int, int]], session) -> None:
        """Upload what a streaming frame holds (``Frame.blocks``) and drop long-gone blocks."""
        self._frame += 1
        for b, (res, _need) in frame_blocks.items():
            self._seen[b] = self._frame
            if res > self.pool.level(b):
                self.upload(b, session.levels(b)[: res + 1])
        for b in list(self.pool.slots):
            if self._frame - self._seen.get(b, -(10**9)) > self.config.linger_frames:
                self.pool.release(b)
                self._seen.pop(b, None)
                for t in self.tables.values():
                    t.remove(b)

    def table(self, metric: str) -> PatchTable:
        """The pooled patch errors for the metric's error field."""
        name = FIELD_FOR_METRIC.get(metric, "qiu") if isinstance(metric, str) else "bound"
        t = self.tables.get(name)
        if t is None:
            t = self.tables[name] = PatchTable(self.k, self.p)
        return t

    # -- selection ---------------------------------------------------------------------------

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

    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
        full: bool = False,
        table: PatchTable | None = None,
        field: str | None = None,
    ) -> tuple[Patches, float]:
        """Stitched patches of the resident blocks at ``tau`` and the CPU time in ms.

        ``resident`` caps each block's level (default: what is on the GPU); ``full`` draws
        every visible node at full resolution (the reference mesh). ``metric`` may be a
        callable (:data:`streamer.lod.Metric`); ``table`` (another patch size) and ``field``
        (the stored error field it is filled from) let a strategy select its own node sizes.
        """
        t0 = time.perf_counter()
        get_metric(metric)
        poly = frustum_hull(camera, self.terrain_zrange)
        pairs = self.drawable(resident)
        blocks = [b for b, _ in pairs]
        res = np.array([lv for _, lv in pairs], dtype=np.int64)
        table = table if table is not None else self.table(metric)
        if field is None:
            field = FIELD_FOR_METRIC.get(metric, "qiu") if isinstance(metric, str) else "bound"
        name = field
        for b in blocks:
            if b not in table:
                table.add(b, self.store.read_errors(b)[name])
        blk = np.array(blocks, dtype=np.int64).reshape(-1, 2)
        at = (blk[:, 0], blk[:, 1])
        zr = np.where(np.isfinite(zr := self._zr[at]), zr, 0.0)
        win = self.store.index.window[at] if blocks else None
        tau_used = 0.0 if full else tau
        fn = _always_split if full else metric
        patches = select_patches(
            self.grid,
            blk,
            table,
            camera,
            tau_used,
            fn,
            poly,
            resident=res,
            zranges=zr,
            windows=win,
        )
        patches = stitch(patches, self.grid, table, camera, fn, resident=res, zranges=zr)
        return patches, (time.perf_counter() - t0) * 1000.0

    # -- drawing -----------------------------------------------------------------------------

    def _uniforms(self, prog: moderngl.Program, camera: Camera) -> None:
        g = self.grid
        cx, cy, cz = camera.position
        ci = math.floor((cx - g.x0) / g.dx)
        ri = math.floor((g.y0 - cy) / g.dy)
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
            "sun": self.config.sun,
            "zrange": self.zrange,
            "viewport": (self.config.size[0] / 2, self.config.size[1] / 2),
        }
        for name, v in values.items():
            if name in prog:
                if isinstance(v, bytes):
                    prog[name].write(v)
                else:
                    prog[name].value = v

    def _instances(self, patches: Patches) -> dict[int, np.ndarray]:
        """Per GPU page, the ``(n, 8)`` int32 instance attributes of its patches."""
        k = self.k
        blk = patches.blocks[patches.block]
        e = np.left_shift(1, k - patches.depth)
        pages = np.empty(len(patches), dtype=np.int64)
        base = np.empty(len(patches), dtype=np.int64)
        for i, b in enumerate(map(tuple, patches.blocks.tolist())):
            m = patches.block == i
            s = self.pool.slots[b]
            pages[m], base[m] = s.page, s.offset
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

    def _vaos(self, prog: moderngl.Program, inst: np.ndarray, indexed: bool = True):
        buf = self.ctx.buffer(np.ascontiguousarray(inst).tobytes())
        vao = self.ctx.vertex_array(
            prog,
            [(self.mesh_vbo, "2i", "in_grid"), (buf, "4i 4i/i", "in_a", "in_b")],
            index_buffer=self.mesh_ibo if indexed else None,
        )
        return vao, buf

    def begin_frame(
        self,
        camera: Camera,
        prog: moderngl.Program,
        *,
        clear: tuple[int, int, int] | None = None,
        lod_colour: bool = False,
    ) -> float:
        """Bind and clear the framebuffer, set the camera uniforms and the index textures for
        ``prog``; returns the frame's start time (``perf_counter``). Shared by all strategies."""
        if tuple(camera.viewport) != tuple(self.config.size):
            raise RenderError(
                f"camera viewport {camera.viewport} differs from the renderer's {self.config.size}"
            )
        ctx = self.ctx
        self.fbo.use()
        t0 = time.perf_counter()
        c = clear or self.config.clear
        self.fbo.clear(c[0] / 255, c[1] / 255, c[2] / 255, 1.0, depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        self._uniforms(prog, camera)
        if "lod_colour" in prog:
            prog["lod_colour"].value = int(lod_colour)
        self.level_tex.use(1)
        self.order_tex.use(2)
        return t0

    def draw(
        self,
        camera: Camera,
        patches: Patches,
        *,
        wireframe: bool = False,
        lod_colour: bool = False,
        clear: tuple[int, int, int] | None = None,
        selection_ms: float = 0.0,
    ) -> RenderStats:
        """Draw the patches; return the stats (frame ms = GPU time until ``ctx.finish()``)."""
        ctx = self.ctx
        prog = self.wire if wireframe else self.prog
        t0 = self.begin_frame(camera, prog, clear=clear, lod_colour=lod_colour or wireframe)
        if len(patches):
            for page, inst in self._instances(patches).items():
                self.pool.pages[page].buffer.bind_to_storage_buffer(0)
                vao, buf = self._vaos(prog, inst)
                vao.render(moderngl.TRIANGLES, instances=len(inst))
                vao.release()
                buf.release()
        ctx.finish()
        frame_ms = (time.perf_counter() - t0) * 1000.0
        check_gl(ctx, "drawing a frame")
        tris = int(triangle_counts(patches.cells_log2, patches.snap).sum())
        return RenderStats(
            triangles=tris,
            patches=len(patches),
            selection_ms=selection_ms,
            frame_ms=frame_ms,
            gpu_bytes=self.pool.used_bytes,
            clamped=patches.clamped,
            violations=patches.violations,
            max_level=int(patches.level.max()) if len(patches) else -1,
            min_level=int(patches.level.min()) if len(patches) else -1,
        )

    def image(self) -> np.ndarray:
        """The framebuffer as an ``(h, w, 3)`` uint8 array, top row first."""
        w, h = self.config.size
        data = self.fbo.read(components=3, alignment=1)
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3)[::-1].copy()

    def probe(self, camera: Camera, patches: Patches) -> tuple[np.ndarray, np.ndarray]:
        """Transform feedback: the height each patch vertex fetched on the GPU and its global
        ``(col, row)`` sample, ``(n_vertices,)`` and ``(n_vertices, 2)``."""
        self.fbo.use()
        self._uniforms(self.probe_prog, camera)
        self.level_tex.use(1)
        self.order_tex.use(2)
        hs, gs = [], []
        for page, inst in self._instances(patches).items():
            self.pool.pages[page].buffer.bind_to_storage_buffer(0)
            vao, buf = self._vaos(self.probe_prog, inst, indexed=False)
            n = self.mesh_vertices * len(inst)
            out = self.ctx.buffer(reserve=n * 12)
            vao.transform(out, moderngl.POINTS, vertices=self.mesh_vertices, instances=len(inst))
            arr = np.frombuffer(out.read(), dtype=np.float32).reshape(-1, 3)
            hs.append(arr[:, 0])
            gs.append(arr[:, 1:].astype(np.int64))
            for o in (vao, buf, out):
                o.release()
        check_gl(self.ctx, "probing heights")
        if not hs:
            return np.zeros(0, np.float32), np.zeros((0, 2), np.int64)
        return np.concatenate(hs), np.concatenate(gs)

    def close(self) -> None:
        """Release GL resources (the context too if the renderer created it)."""
        self.pool.close()


def _always_split(delta, centre_xyz, radius, camera) -> np.ndarray:
    """A metric that splits every node (full-resolution reference)."""
    return np.full(np.shape(delta), np.inf)
