"""``geometry-splitting``, the GL part: the strategy expanding the quadtree and splitting
triangles on the GPU (see the package docstring). Shaders beside this file: ``quadtree.glsl``
(node spheres, culling, split flag, neighbours), ``expand.geom``, ``quad.geom``, ``split.geom``,
``pull.glsl`` + ``draw.vert``/``probe.vert`` (vertex pulling)."""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import moderngl
import numpy as np

from render import measure, shaders
from render.builds import BackgroundBuilds
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
from render.strategies.feedback import block_neighbours, feedback_pass
from render.strategies.geometry_splitting.ahead import AheadTextures
from render.strategies.geometry_splitting.provision import (  # noqa: F401 (re-exported)
    PROVISIONAL_LEVEL,
    TextureProvision,
    build_tree,
)
from render.strategies.geometry_splitting.pure import BlockTree
from render.strategies.geometry_splitting.reference import CULL_MARGIN, expand_reference
from render.strategies.geometry_splitting.textures import TextureStore
from streamer.camera import Camera

NO_CAP = 99  # border cap meaning "no restriction"
#: the texture buffer grows up to this size (or the store's blocks) to keep the textures of
#: blocks that left the GPU, for when they come back; past it the oldest gives way (a buffer
#: with more live blocks than this grows for them: ``slots.SlotTable``)
TEXTURE_CACHE_BYTES = 64 << 20
#: the first texture buffer's size, at least (or every block's full texture, if less): each
#: growth is a new buffer (zero-filled: ~0.45 ms a MiB on llvmpipe) and a copy
TEXTURE_MIN_BYTES = 16 << 20
HERE = Path(__file__).parent


def _src(name: str) -> str:
    return shaders.source(HERE / name, {"CULL_MARGIN": f"{CULL_MARGIN:.6f}"})


# --- the selection ----------------------------------------------------------------------------


@dataclass(eq=False)
class Selection:
    """GPU-made leaves and triangles of one frame (buffers stay on the GPU)."""

    blocks: list[Block]
    table: np.ndarray  # (m, 16) int32 block table
    camera: Camera
    tau: float
    pass_counts: list[int]  # nodes after each expansion pass
    split_counts: list[int]  # triangles after the leaf pass and each splitting pass
    clamped: int
    max_depth: int
    min_depth: int
    gpu_ms: float = 0.0  # wall time of the expansion and splitting passes (GPU work)
    leaf_buf: moderngl.Buffer | None = None
    tri_buf: moderngl.Buffer | None = None
    block_buf: moderngl.Buffer | None = None
    _cache: dict = field(default_factory=dict)

    @property
    def leaves(self) -> int:
        """Number of leaves drawn."""
        return self.pass_counts[-1] if self.pass_counts else 0

    @property
    def triangles(self) -> int:
        """Number of triangles drawn."""
        return self.split_counts[-1] if self.split_counts else 0

    def __len__(self) -> int:
        return self.leaves


def _release(*bufs) -> None:
    for b in bufs:
        if b is not None:
            b.release()


class GeometrySplitting(TextureProvision, Strategy[Selection]):
    """Lee & Shin: GPU quadtree expansion and triangle splitting."""

    name = "geometry-splitting"
    uses_metric = False
    what = "drawing split geometry"

    def __init__(self, renderer: FrameServices) -> None:
        super().__init__(renderer)
        ctx = renderer.ctx
        self.k = renderer.k
        vs_node, vs_draw = _src("node.vert"), _src("draw.vert")
        self.expand_prog = ctx.program(
            vertex_shader=vs_node, geometry_shader=_src("expand.geom"), varyings=["o_node"]
        )
        self.quad_prog = ctx.program(
            vertex_shader=vs_node, geometry_shader=_src("quad.geom"), varyings=["o_leaf", "o_tri"]
        )
        self.split_prog = ctx.program(
            vertex_shader=_src("tri.vert"),
            geometry_shader=_src("split.geom"),
            varyings=["o_leaf", "o_tri"],
        )
        self.prog = ctx.program(vertex_shader=vs_draw, fragment_shader=shaders.FRAGMENT)
        self.wire = ctx.program(
            vertex_shader=vs_draw,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        )
        self.probe_prog = ctx.program(vertex_shader=_src("probe.vert"), varyings=["t_out"])
        self.trees: dict[Block, BlockTree] = {}
        self._tree_level: dict[Block, int] = {}  # the resident level each tree was built for
        g = renderer.grid  # the textures on the GPU (their levels and depths)
        self._tex = TextureStore(
            ctx, self.k, g.rows * g.cols, TEXTURE_CACHE_BYTES, TEXTURE_MIN_BYTES
        )
        self.heights = GlobalHeights(renderer.store)
        self._builds: BackgroundBuilds[tuple[BlockTree, bytes, int]] | None = None
        self._ahead_builds: BackgroundBuilds[tuple[bytes, int]] | None = None
        #: first textures built ahead for the session's blocks not yet drawn (with
        #: :meth:`build_in_background`; ``ahead.py``)
        self.ahead = AheadTextures()
        self._ahead_key: tuple | None = None  # what the last want was made from
        check_gl(ctx, "creating the geometry-splitting programs")

    def own_gpu_bytes(self) -> int:
        """The quadtree texture buffer (σ and height ranges of every resident block)."""
        return self._tex.nbytes

    def block_table(
        self, resident: dict[Block, int] | None = None
    ) -> tuple[list[Block], np.ndarray]:
        """The drawn blocks (sorted) and their ``(m, 16)`` int32 table (see ``QT_LIB``)."""
        pairs = self.r.drawable(resident)
        blocks = [b for b, _ in pairs]
        nb = block_neighbours(blocks)
        k = self.k
        t = np.zeros((len(blocks), 16), dtype=np.int64)
        for i, (b, lv) in enumerate(pairs):
            s = self.r.slot(b)
            t[i, 0:4] = (b[1] << k, b[0] << k, s.offset, lv)
            tex = self._tex
            t[i, 4:8] = (tex.offset.get(b, 0), s.page, tex.depth.get(b, k - 1), tex.bits(b))
            t[i, 8:12] = nb[i]
            for dr, j in enumerate(nb[i].tolist()):
                cross = j >= 0 and self.r.slot(blocks[j]).page != s.page
                t[i, 12 + dr] = pairs[j][1] if cross else NO_CAP
        return blocks, t.astype(np.int32)

    # -- selection ---------------------------------------------------------------------------

    def _bind(self, prog: moderngl.Program, camera: Camera, tau: float, block_buf) -> None:
        self.r.fbo.use()
        self.r.set_camera(prog, camera)
        if "tau" in prog:
            prog["tau"].value = float(tau)
        if "slab" in prog:
            prog["slab"].value = self.r.terrain_zrange
        block_buf.bind_to_storage_buffer(4)
        self._tex.bind(5)

    def _pass(self, prog, src, fmt, names, n, out_per, rec_bytes) -> tuple[moderngl.Buffer, int]:
        return feedback_pass(self.r.ctx, prog, src, fmt, names, n, out_per, rec_bytes)

    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
    ) -> tuple[Selection, float]:
        check_tau(tau)
        t0 = time.perf_counter()
        ctx = self.r.ctx
        self.r.make_current()  # the passes make and use GL objects of the renderer's context
        build_ms = self.upload_textures(self.r.drawable(resident), camera)
        blocks, table = self.block_table(resident)
        block_buf = ctx.buffer(np.ascontiguousarray(table).tobytes() or bytes(64))
        stats = ctx.buffer(np.array([0, -1, 1 << 30, 0], np.int32).tobytes())
        sel = Selection(blocks, table, camera, float(tau), [], [], 0, -1, -1, block_buf=block_buf)
        n = len(blocks)
        tg = time.perf_counter()
        if n:
            roots = np.zeros((n, 4), np.int32)
            roots[:, 0] = np.arange(n)
            src = ctx.buffer(roots.tobytes())
            for p in range(self.k):
                self._bind(self.expand_prog, camera, tau, block_buf)
                self.expand_prog["cull_input"].value = int(p == 0)
                out, n = self._pass(self.expand_prog, src, "4i", ["in_a"], n, 4, 16)
                src.release()
                src = out
                sel.pass_counts.append(n)
                if n == 0:
                    break
            sel.leaf_buf = src
        if sel.leaves:
            self._bind(self.quad_prog, camera, tau, block_buf)
            stats.bind_to_storage_buffer(7)
            tri, m = self._pass(self.quad_prog, sel.leaf_buf, "4i", ["in_a"], sel.leaves, 4, 32)
            sel.split_counts.append(m)
            for _ in range(self.k if self.stitching else 0):
                self._bind(self.split_prog, camera, tau, block_buf)
                out, m2 = self._pass(self.split_prog, tri, "4i 4i", ["in_a", "in_b"], m, 2, 32)
                if m2 == m:
                    out.release()
                    break
                tri.release()
                tri, m = out, m2
                sel.split_counts.append(m)
            sel.tri_buf = tri
            cl, mx, mn, _ = np.frombuffer(stats.read(), np.int32).tolist()
            sel.clamped, sel.max_depth, sel.min_depth = cl, mx, mn
        stats.release()
        check_gl(ctx, "expanding the quadtree")
        t1 = time.perf_counter()
        sel.gpu_ms = (t1 - tg) * 1000.0
        weakref.finalize(sel, _release, sel.leaf_buf, sel.tri_buf, sel.block_buf)
        return sel, (tg - t0) * 1000.0 - build_ms

    # -- drawing -----------------------------------------------------------------------------

    def _pages(self, sel: Selection) -> list[int]:
        return sorted({int(p) for p in sel.table[:, 5]}) if len(sel.table) else []

    def render(self, prog: moderngl.Program, sel: Selection) -> None:
        if not sel.triangles:
            return
        r = self.r
        sel.block_buf.bind_to_storage_buffer(4)
        sel.tri_buf.bind_to_storage_buffer(6)
        vao = r.ctx.vertex_array(prog, [])
        for page in self._pages(sel):
            r.bind_heights(page)
            prog["page"].value = page
            vao.render(moderngl.TRIANGLES, vertices=3 * sel.triangles)
        vao.release()

    def counts(self, sel: Selection) -> SelectionCounts:
        return SelectionCounts(
            triangles=sel.triangles,
            patches=sel.leaves,
            clamped=sel.clamped,
            violations=0,
            max_level=sel.max_depth,
            min_level=sel.min_depth,
        )

    def extra_frame_ms(self, sel: Selection) -> float:
        """The expansion and splitting passes (GPU work timed in :meth:`select`)."""
        return sel.gpu_ms

    def draw_gpu_bytes(self) -> int:
        return self._tex.nbytes

    # -- read-backs --------------------------------------------------------------------------

    def leaf_nodes(self, sel: Selection) -> np.ndarray:
        """``(n, 4)`` int64 leaves ``(block index, depth, row, col)`` read back from the GPU."""
        if "leaves" not in sel._cache:
            if not sel.leaves:
                sel._cache["leaves"] = np.zeros((0, 4), np.int64)
            else:
                a = np.frombuffer(sel.leaf_buf.read(size=16 * sel.leaves), np.int32).reshape(-1, 4)
                a = a.astype(np.int64)
                a[:, 1] &= 255
                sel._cache["leaves"] = a
        return sel._cache["leaves"]

    def triangle_records(self, sel: Selection) -> np.ndarray:
        """``(m, 8)`` int64 triangle records: leaf ``(block, depth, row, col)``, ``kind``
        (0–3 fan on edge N/E/S/W, 4–5 the two quad halves), segment start, segment depth, 0."""
        if not sel.triangles:
            return np.zeros((0, 8), np.int64)
        a = np.frombuffer(sel.tri_buf.read(size=32 * sel.triangles), np.int32).reshape(-1, 8)
        a = a.astype(np.int64)
        a[:, 4] &= 15
        return a

    def triangles(self, camera: Camera, sel: Selection) -> tuple[np.ndarray, np.ndarray]:
        """Every drawn triangle's global ``(col, row)`` corners ``(m, 3, 2)`` int64 and fetched
        heights ``(m, 3)`` (:data:`render.gpu.MASKED` where masked), read back with transform
        feedback."""
        r = self.r
        if not sel.triangles:
            return np.zeros((0, 3, 2), np.int64), np.zeros((0, 3))
        r.make_current()
        r.fbo.use()
        r.set_camera(self.probe_prog, camera)
        sel.block_buf.bind_to_storage_buffer(4)
        sel.tri_buf.bind_to_storage_buffer(6)
        vao = r.ctx.vertex_array(self.probe_prog, [])
        out = r.ctx.buffer(reserve=sel.triangles * 3 * 16)
        parts = []
        for page in self._pages(sel):
            r.bind_heights(page)
            self.probe_prog["page"].value = page
            vao.transform(out, moderngl.POINTS, vertices=3 * sel.triangles)
            a = np.frombuffer(out.read(), np.float32).reshape(-1, 3, 4)
            parts.append(a[(a[..., 3] > 0.5).all(axis=1)])
        vao.release()
        out.release()
        check_gl(r.ctx, "reading split triangles back")
        a = np.concatenate(parts).astype(np.float64)
        return np.rint(a[..., :2]).astype(np.int64), r.absolute(a[..., 2])

    def screen_errors(self, camera: Camera, sel: Selection) -> np.ndarray:
        tri, h = self.triangles(camera, sel)
        return triangle_screen_errors(self.r.grid, camera, tri, h, self.heights)

    def drawn_blocks(self, sel: Selection) -> set[Block]:
        idx = np.unique(self.leaf_nodes(sel)[:, 0])
        return {sel.blocks[int(i)] for i in idx}

    def surface(self, camera: Camera, sel: Selection) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        tri, h = self.triangles(camera, sel)
        ok = (h > MASKED_BELOW).all(axis=1)
        return measure.rasterise(tri[ok], h[ok])

    def expand_reference(
        self, camera: Camera, tau: float, resident: dict[Block, int] | None = None
    ) -> tuple[list[int], np.ndarray, np.ndarray]:
        """:func:`render.strategies.geometry_splitting.reference.expand_reference`: the CPU twin
        (float64) of the expansion — node counts after each pass, the leaves and the nodes that
        split, both ``(block index, depth, row, col)`` sorted."""
        return expand_reference(self, camera, tau, resident)
