"""``qiu`` — Qiu et al.'s CLOD (3.3), the default strategy: quadtree patches of
``2**patch_log2`` cells selected on the CPU (:mod:`render.select`), stitched by edge snapping
against coarser neighbours, and drawn as instanced grids whose heights the vertex shader fetches
from the height pool (displacement mapping, the paper's steps 1-4; ``render/glsl/``).

Per frame only the patch layout travels to the GPU: per instance the block origin, the node's
origin, the slot base, the level, the cells and the four edge snaps
(:meth:`render.frame.FrameServices.instances`). :func:`select_clod` is also the selection of
``chunk-tessellation`` (with its own metric, node size and error field).
"""

from __future__ import annotations

import dataclasses
import time

import moderngl
import numpy as np

from render import measure, shaders
from render.frame import FrameServices
from render.gpu import check_gl
from render.mesh import grid_indices, grid_vertices, triangle_counts
from render.select import Patches, PatchTable, select_patches, stitch
from render.strategies.base import Block, SelectionCounts, Strategy
from streamer.camera import Camera
from streamer.frustum import frustum_hull
from streamer.lod import FIELD_FOR_METRIC, get_metric, takes_box
from streamer.nodata import check_rule


def field_for(metric: str) -> str:
    """The stored error field a metric selects with (a callable metric: ``bound``)."""
    return FIELD_FOR_METRIC.get(metric, "qiu") if isinstance(metric, str) else "bound"


def metric_table(r: FrameServices, metric: str) -> PatchTable:
    """The renderer's pooled patch errors for the metric's error field."""
    return r.patch_table(field_for(metric))


def always_split(
    delta: np.ndarray, centre_xyz: np.ndarray, radius: np.ndarray, camera: Camera
) -> np.ndarray:
    """A metric that splits every node (full-resolution reference)."""
    return np.full(np.shape(delta), np.inf)


def select_clod(
    r: FrameServices,
    camera: Camera,
    tau: float,
    metric: str = "qiu",
    *,
    resident: dict[Block, int] | None = None,
    full: bool = False,
    table: PatchTable | None = None,
    field: str | None = None,
    min_depth: int = 0,
    nodata: str = "full",
) -> tuple[Patches, float]:
    """Stitched patches of the drawable blocks at ``tau`` and the CPU time in ms.

    ``resident`` caps each block's level (default: what is on the GPU); ``full`` draws every
    visible node at full resolution (the reference mesh). ``metric`` may be a callable
    (:data:`streamer.lod.Metric`); ``table`` (another node size) and ``field`` (the stored error
    field it is filled from) let a strategy select its own node sizes; nodes shallower than
    ``min_depth`` always split (where resident). A metric that
    :func:`~streamer.lod.takes_box` gets each node's box (:meth:`FrameServices.node_boxes`).
    ``nodata`` is the mask-boundary rule (:data:`streamer.nodata.NODATA_RULES`; ``"gap"``
    only with the metric's own table).
    """
    t0 = time.perf_counter()
    get_metric(metric)
    gap = check_rule(nodata) == "gap" and not full
    if gap and table is not None:
        raise ValueError("nodata='gap' selects with the metric's own table: pass no table=")
    poly = frustum_hull(camera, r.terrain_zrange)
    pairs = r.drawable(resident)
    blocks = [b for b, _ in pairs]
    res = np.array([lv for _, lv in pairs], dtype=np.int64)
    name = field if field is not None else field_for(metric)
    if table is None:
        table = r.patch_table(f"{name}/gap") if gap else metric_table(r, metric)
    r.fill_table(table, blocks, name, "gap" if gap else "full")
    gaps = None
    if gap:
        gaps = r.patch_table(f"gap/{table.patch_log2}", table.patch_log2)
        r.fill_table(gaps, blocks, "gap")
    blk = np.array(blocks, dtype=np.int64).reshape(-1, 2)
    zr = r.block_zranges(blk)
    win = r.store.index.window[(blk[:, 0], blk[:, 1])] if blocks else None
    tau_used = 0.0 if full else tau
    fn = always_split if full else metric
    rule = "gap" if gap else "full"
    boxes = r.node_boxes(pairs, table.patch_log2, rule) if takes_box(fn) else None
    patches = select_patches(
        r.grid, blk, table, camera, tau_used, fn, poly, resident=res, zranges=zr, windows=win,
        min_depth=min_depth, boxes=boxes, gaps=gaps,
    )  # fmt: skip
    patches = stitch(
        patches, r.grid, table, camera, fn, resident=res, zranges=zr, boxes=boxes, tau=tau_used
    )
    return patches, (time.perf_counter() - t0) * 1000.0


def _programs(ctx: moderngl.Context) -> dict[str, moderngl.Program]:
    return {
        "prog": ctx.program(vertex_shader=shaders.VERTEX, fragment_shader=shaders.FRAGMENT),
        "wire": ctx.program(
            vertex_shader=shaders.VERTEX,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        ),
        "probe": ctx.program(vertex_shader=shaders.PROBE, varyings=["out_h", "out_g"]),
        "tri_probe": ctx.program(
            vertex_shader=shaders.source("patch_probe.vert"),
            geometry_shader=shaders.TRIANGLE_PROBE,
        ),
    }


class PatchGrid:
    """The renderer's instanced patch mesh and Qiu's programs (one per renderer)."""

    def __init__(self, r: FrameServices) -> None:
        ctx = r.ctx
        n = 1 << r.p
        self.r = r
        self.vbo = ctx.buffer(grid_vertices(n).astype("i4").tobytes())
        self.ibo = ctx.buffer(grid_indices(n).astype("i4").tobytes())
        self.vertices = (n + 1) ** 2
        progs = _programs(ctx)
        self.prog, self.wire, self.probe_prog = progs["prog"], progs["wire"], progs["probe"]
        self.tri_probe = progs["tri_probe"]
        self.cells = n

    def vao(
        self, prog: moderngl.Program, inst: np.ndarray, indexed: bool = True
    ) -> moderngl.VertexArray:
        """A vertex array of the patch mesh with ``inst`` as per-instance attributes."""
        ctx = self.r.ctx
        buf = ctx.buffer(np.ascontiguousarray(inst).tobytes())
        vao = ctx.vertex_array(
            prog,
            [(self.vbo, "2i", "in_grid"), (buf, "4i 4i/i", "in_a", "in_b")],
            index_buffer=self.ibo if indexed else None,
        )
        return vao, buf

    def render(self, prog: moderngl.Program, patches: Patches) -> None:
        """The instanced draw calls, one per height-pool page."""
        if not len(patches):
            return
        for page, inst in self.r.instances(patches).items():
            self.r.bind_heights(page)
            vao, buf = self.vao(prog, inst)
            vao.render(moderngl.TRIANGLES, instances=len(inst))
            vao.release()
            buf.release()

    def probe(self, camera: Camera, patches: Patches) -> tuple[np.ndarray, np.ndarray]:
        """Transform feedback: the height each patch vertex fetched on the GPU and its global
        ``(col, row)`` sample, ``(n_vertices,)`` and ``(n_vertices, 2)``."""
        r = self.r
        r.make_current()
        r.fbo.use()
        r.set_camera(self.probe_prog, camera)
        hs, gs = [], []
        for page, inst in r.instances(patches).items():
            r.bind_heights(page)
            vao, buf = self.vao(self.probe_prog, inst, indexed=False)
            n = self.vertices * len(inst)
            out = r.ctx.buffer(reserve=n * 12)
            vao.transform(out, moderngl.POINTS, vertices=self.vertices, instances=len(inst))
            arr = np.frombuffer(out.read(), dtype=np.float32).reshape(-1, 3)
            hs.append(r.absolute(arr[:, 0]))
            gs.append(arr[:, 1:].astype(np.int64))
            for o in (vao, buf, out):
                o.release()
        check_gl(r.ctx, "probing heights")
        if not hs:
            return np.zeros(0, np.float64), np.zeros((0, 2), np.int64)
        return np.concatenate(hs), np.concatenate(gs)


def unstitched(sel: Patches) -> Patches:
    """``sel`` with every edge snap zeroed (the crack detectors' positive control)."""
    return dataclasses.replace(sel, snap=np.zeros_like(sel.snap))


def patch_grid(r: FrameServices) -> PatchGrid:
    """The renderer's :class:`PatchGrid` (made once per renderer)."""
    return r.shared("qiu.patch_grid", PatchGrid)


def patch_counts(sel: Patches) -> SelectionCounts:
    """Triangles (snapped patch grids), patches, clamped, violations, level range."""
    tris = int(triangle_counts(sel.cells_log2, sel.snap).sum())
    return SelectionCounts.of_levels(tris, len(sel), sel.clamped, sel.violations, sel.level)


def patch_levels(sel: Patches) -> dict[Block, int]:
    """The finest level of any patch in each block."""
    out = np.full(len(sel.blocks), -1, np.int64)
    np.maximum.at(out, sel.block, sel.level)
    return {
        tuple(int(v) for v in b): int(lv) for b, lv in zip(sel.blocks, out, strict=True) if lv >= 0
    }


def patch_blocks(sel: Patches) -> set[Block]:
    """The blocks holding at least one patch."""
    return {tuple(int(v) for v in b) for b in sel.blocks[np.unique(sel.block)]}


class QiuStrategy(Strategy[Patches]):
    """Qiu's CLOD patches (the default)."""

    name = "qiu"
    nodata_rules = ("full", "gap")

    def __init__(self, renderer: FrameServices, nodata: str = "full") -> None:
        """``nodata``: the mask-boundary rule (:data:`streamer.nodata.NODATA_RULES`)."""
        super().__init__(renderer)
        self.nodata = check_rule(nodata)
        self.grid = patch_grid(renderer)
        self.prog, self.wire = self.grid.prog, self.grid.wire

    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
    ) -> tuple[Patches, float]:
        sel, ms = select_clod(self.r, camera, tau, metric, resident=resident, nodata=self.nodata)
        return (sel if self.stitching else unstitched(sel)), ms

    def select_full(
        self, camera: Camera, resident: dict[Block, int] | None = None
    ) -> tuple[Patches, float]:
        """Every visible node at full resolution (the reference mesh)."""
        return select_clod(self.r, camera, 0.0, "qiu", resident=resident, full=True)

    def render(self, prog: moderngl.Program, sel: Patches) -> None:
        self.grid.render(prog, sel)

    def counts(self, sel: Patches) -> SelectionCounts:
        return patch_counts(sel)

    def probe(self, camera: Camera, sel: Patches) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`PatchGrid.probe`: the heights the GPU fetched per patch vertex."""
        return self.grid.probe(camera, sel)

    def screen_errors(self, camera: Camera, sel: Patches) -> np.ndarray:
        heights = measure.heights_fn(self.r.store, sel)
        return measure.screen_errors(sel, self.r.grid, camera, heights)

    def triangles(self, camera: Camera, sel: Patches) -> tuple[np.ndarray, np.ndarray]:
        """The drawn triangles (the CPU twin of the instanced, snapped patch grids): global
        ``(col, row)`` corners ``(m, 3, 2)`` and heights ``(m, 3)`` (NaN where masked)."""
        heights = measure.heights_fn(self.r.store, sel)
        return measure.patch_triangles(sel, self.r.grid, heights)

    def used_levels(self, camera: Camera, sel: Patches) -> dict[Block, int]:
        """The finest patch level drawn in each block."""
        return patch_levels(sel)

    def drawn_blocks(self, sel: Patches) -> set[Block]:
        return patch_blocks(sel)

    def gpu_triangles(self, camera: Camera, sel: Patches) -> tuple[np.ndarray, np.ndarray]:
        """Every drawn triangle read back from the GPU (snapped ones included): global
        ``(col, row)`` corners ``(m, 3, 2)`` and fetched heights ``(m, 3)`` (``MASKED`` where
        a corner is masked: that triangle is not drawn)."""
        cap = len(sel) * 2 * self.grid.cells**2
        prog = self.grid.tri_probe
        return self.r.read_triangles(
            camera, prog, cap, lambda: self.render(prog, sel), "reading patch triangles back"
        )

    def surface(self, camera: Camera, sel: Patches) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        step = self.r.grid.step
        rs, cs, hs = [], [], []
        heights = measure.heights_fn(self.r.store, sel)
        for b, rows, cols, h in measure.lod_surface(sel, self.r.k, heights):
            br, bc = (int(v) for v in sel.blocks[b])
            rs.append(br * step + rows)
            cs.append(bc * step + cols)
            hs.append(h)
        if not rs:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        return np.concatenate(rs), np.concatenate(cs), np.concatenate(hs)
