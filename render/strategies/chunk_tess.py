"""``chunk-tessellation`` — Kim, Lee & Shin's GPU chunk LOD: the quadtree traversal stops at
chunks that the hardware tessellator draws.

* **Chunks** are quadtree nodes of a block drawn from one level as ``2**c`` cells per side
  (``c = chunk_log2``, default 5: Kim's 32×32 cells; GL's ``GL_MAX_TESS_GEN_LEVEL`` is 64, so
  ``c <= 6``). A node at depth ``d`` uses level ``min(k, d + c)``, i.e. the *cells of the
  store's level grid*; near the bottom of the tree (level ``k``) a chunk has ``2**(k-d)`` cells.
* **Chunk error** ``ε`` = the largest cell error of the chunk = the stored ``bound`` field
  (the largest vertical distance of any full-resolution sample from the cell drawn unsplit) at
  depth ``d + c``, pooled over the chunk (``PatchTable``). The paper says "max cell error"
  without fixing the cell error; we take the true vertical bound rather than Qiu's midpoint
  error, so ``--metric`` does not apply to this strategy.
* **Screen error**: the point ``P`` of the chunk's bounding sphere nearest the eye and
  ``P + (0, 0, ε)`` are projected; their pixel distance (``streamer.lod.exact_projected``) is
  compared with τ, split if ``>= τ``. Eye inside the sphere, or ``P`` behind the eye: split.
  (The paper's test is "≥ τ"; we split on ``> τ`` only through the shared selection's
  ``not rho <= tau``, which is the same except at exact equality.)
* **Cracks**: each chunk carries its 4 neighbours' levels (the stitching pass of
  :func:`render.select.stitch`, which finds the leaf across each edge and restricts the tree so
  that a neighbour's cell spacing never exceeds a chunk's edge); the tessellation control
  shader sets the outer factor of edge ``e`` to ``2**(cells - snap_e)`` where
  ``snap_e = max(0, s_neighbour - s)`` (``s`` = log2 cell spacing), so a shared edge has the
  vertices of the coarser side on both sides. Equal spacing with power-of-two factors puts the
  tessellated vertices exactly on the lattice (``gl_TessCoord * 2**c`` is an exact integer), so
  shared vertices are bit-identical (same integer-sample position path as the renderer). No
  skirts, no extra geometry. GL quad outer levels: ``[0]`` u=0 (west), ``[1]`` v=0 (north),
  ``[2]`` u=1 (east), ``[3]`` v=1 (south).
* **Heights** are fetched in the tessellation evaluation shader with the renderer's
  level/order-index path (``shaders.FETCH_COMMON``: ``vertex_at``), from the same
  ``HeightPool``. Per frame one vertex (32 bytes, the renderer's instance layout) per chunk is
  sent; patches of one control point (``GL_PATCH_VERTICES = 1``).
* **Triangles**: a quad domain with inner factor ``N`` and outer factors ``o_e`` gives
  ``2(N-2)² + 4(N-2) + Σ o_e`` triangles (``2`` for ``N = 1``); the stats use that formula,
  checked against a transform-feedback read-back in the tests. The inner triangulation's
  diagonal direction is the implementation's, so the measured error reads the tessellated
  triangles back with transform feedback (a pass-through geometry shader emits each triangle's
  3 corners as points: integer global sample and fetched height) and rasterises them on the
  sample lattice.
* **Batches** (a Mesa llvmpipe limit found by the read-back): when one draw call tessellates
  more than 65,536 vertices, the geometry shader receives triangles whose corners belong to
  other triangles (16-bit vertex indices wrapping; the plain draw without a geometry shader is
  unaffected). Every pass is therefore issued in batches of ``batch_chunks(c)`` chunks
  (60 at ``c = 5``); the test reads back 198 chunks and checks their area.
"""

from __future__ import annotations

import moderngl
import numpy as np

from render import measure, shaders
from render.errors import RenderError
from render.gpu import check_gl
from render.renderer import RenderStats, TerrainRenderer
from render.select import Patches, PatchTable
from render.strategies.base import Block, GlobalHeights, Strategy, triangle_screen_errors
from render.strategies.qiu import patch_levels
from streamer.camera import Camera
from streamer.lod import exact_projected

VS = """
#version 450
in ivec4 in_a;
in ivec4 in_b;
flat out ivec4 c_a;
flat out ivec4 c_b;
void main() { c_a = in_a; c_b = in_b; }
"""

TCS = """
#version 450
layout(vertices = 1) out;
flat in ivec4 c_a[];
flat in ivec4 c_b[];
patch out ivec4 p_a;
patch out ivec4 p_b;
void main() {
    p_a = c_a[0];
    p_b = c_b[0];
    int c = c_b[0].z, w = c_b[0].w;
    int tn = w & 15, te = (w >> 4) & 15, ts = (w >> 8) & 15, tw = (w >> 12) & 15;
    float n = float(1 << c);
    gl_TessLevelInner[0] = n;
    gl_TessLevelInner[1] = n;
    gl_TessLevelOuter[0] = float(1 << (c - tw));   // u = 0: west
    gl_TessLevelOuter[1] = float(1 << (c - tn));   // v = 0: north
    gl_TessLevelOuter[2] = float(1 << (c - te));   // u = 1: east
    gl_TessLevelOuter[3] = float(1 << (c - ts));   // v = 1: south
}
"""

TES_HEAD = (
    shaders.FETCH_COMMON
    + """
layout(quads, equal_spacing, ccw) in;
patch in ivec4 p_a;
patch in ivec4 p_b;
Vtx tess_vertex() {
    float n = float(1 << p_b.z);
    int si = int(round(gl_TessCoord.x * n));
    int sj = int(round(gl_TessCoord.y * n));
    return vertex_at(p_a, p_b, si, sj);
}
"""
)

TES = TES_HEAD + shaders.EMIT + "void main() { emit(tess_vertex()); }\n"

TES_PROBE = (
    TES_HEAD
    + """
out vec3 t_gh;
void main() {
    Vtx v = tess_vertex();
    t_gh = vec3(vec2(v.g), v.masked > 0.0 ? -1.0e30 : v.h);
    gl_Position = vec4(0.0);
}
"""
)


def kim_metric(delta, centre_xyz, radius, camera: Camera) -> np.ndarray:
    """Pixel distance between the bounding sphere's point nearest the eye and that point raised
    by ``delta`` (inf when the eye is inside the sphere or the point is not in front)."""
    c = np.asarray(centre_xyz, dtype=np.float64)
    rad = np.broadcast_to(np.asarray(radius, dtype=np.float64), c.shape[:-1])
    d = np.broadcast_to(np.asarray(delta, dtype=np.float64), c.shape[:-1])
    to_eye = camera.eye - c
    dist = np.sqrt(np.einsum("...i,...i->...", to_eye, to_eye))
    inside = dist <= rad
    with np.errstate(invalid="ignore", divide="ignore"):
        p = c + to_eye * (rad / np.where(inside, 1.0, dist))[..., None]
        rho = exact_projected(d, p, camera)
    rho = np.where(np.isfinite(rho), rho, np.inf)
    return np.where(d == 0.0, 0.0, np.where(inside, np.inf, rho))


def tess_triangles(cells_log2: np.ndarray, snap: np.ndarray) -> np.ndarray:
    """Triangles the quad tessellator makes per chunk (inner ``2**c``, outer from the snaps)."""
    c = np.asarray(cells_log2, dtype=np.int64)
    n = np.left_shift(1, c)
    outer = np.left_shift(1, c[:, None] - np.asarray(snap, dtype=np.int64)).sum(axis=1)
    return np.where(n == 1, 2, 2 * (n - 2) ** 2 + 4 * (n - 2) + outer)


#: tessellated vertices per draw call that Mesa's llvmpipe hands to a geometry shader intact
#: (beyond 65,536 — 16-bit vertex indices — the GS receives corners of other triangles)
MAX_TESS_VERTICES = 65535


def batch_chunks(chunk_log2: int) -> int:
    """Chunks per draw call so that one call tessellates at most ``MAX_TESS_VERTICES``."""
    return max(1, MAX_TESS_VERTICES // ((1 << chunk_log2) + 1) ** 2)


def outer_factors(cells_log2: int, snap: tuple[int, int, int, int]) -> tuple[int, ...]:
    """GL outer levels ``[u=0 (W), v=0 (N), u=1 (E), v=1 (S)]`` of a chunk (CPU twin of the TCS)."""
    tn, te, ts, tw = snap
    return tuple(1 << (cells_log2 - t) for t in (tw, tn, te, ts))


class ChunkTessellation(Strategy):
    """Kim, Lee & Shin: tessellated chunks with neighbour-matched outer factors."""

    name = "chunk-tessellation"
    uses_metric = False

    def __init__(self, renderer: TerrainRenderer, chunk_log2: int = 5) -> None:
        super().__init__(renderer)
        if not 0 <= chunk_log2 <= 6:
            raise RenderError(
                f"chunk_log2 must be in 0..6 (tessellation factor <= 64), got {chunk_log2}"
            )
        self.c = min(chunk_log2, renderer.k)
        ctx = renderer.ctx
        key = f"bound@chunk{self.c}"
        if key not in renderer.tables:
            renderer.tables[key] = PatchTable(renderer.k, self.c)
        self.table = renderer.tables[key]
        self.prog = ctx.program(
            vertex_shader=VS,
            tess_control_shader=TCS,
            tess_evaluation_shader=TES,
            fragment_shader=shaders.FRAGMENT,
        )
        self.wire = ctx.program(
            vertex_shader=VS,
            tess_control_shader=TCS,
            tess_evaluation_shader=TES,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        )
        self.probe_prog = ctx.program(
            vertex_shader=VS,
            tess_control_shader=TCS,
            tess_evaluation_shader=TES_PROBE,
            geometry_shader=shaders.TRIANGLE_PROBE,
        )
        self.heights = GlobalHeights(renderer.store)
        check_gl(ctx, "creating the chunk-tessellation programs")

    def select(self, camera, tau, metric="qiu", *, resident=None) -> tuple[Patches, float]:
        return self.r.select(
            camera, tau, kim_metric, resident=resident, table=self.table, field="bound"
        )

    def _passes(self, prog: moderngl.Program, patches: Patches):
        """Per height page, in batches of at most :func:`batch_chunks` chunks: ``(vao, n)``."""
        per = batch_chunks(self.c)
        for page, inst in self.r._instances(patches).items():
            self.r.pool.pages[page].buffer.bind_to_storage_buffer(0)
            for i in range(0, len(inst), per):
                part = np.ascontiguousarray(inst[i : i + per])
                buf = self.r.ctx.buffer(part.tobytes())
                vao = self.r.ctx.vertex_array(prog, [(buf, "4i 4i", "in_a", "in_b")])
                yield vao, len(part)
                vao.release()
                buf.release()

    def _run(self, prog: moderngl.Program, sel: Patches) -> None:
        self.r.ctx.patch_vertices = 1
        for vao, n in self._passes(prog, sel):
            vao.render(moderngl.PATCHES, vertices=n)

    def draw(
        self,
        camera: Camera,
        sel: Patches,
        *,
        wireframe: bool = False,
        lod_colour: bool = False,
        clear: tuple[int, int, int] | None = None,
        selection_ms: float = 0.0,
    ) -> RenderStats:
        r = self.r
        prog = self.wire if wireframe else self.prog
        frame_ms = self.timed_frame(
            camera, prog, lambda: self._run(prog, sel), clear=clear,
            lod_colour=lod_colour or wireframe, what="drawing tessellated chunks",
        )  # fmt: skip
        return RenderStats(
            triangles=int(tess_triangles(sel.cells_log2, sel.snap).sum()),
            patches=len(sel),
            selection_ms=selection_ms,
            frame_ms=frame_ms,
            gpu_bytes=r.pool.used_bytes,
            clamped=sel.clamped,
            violations=sel.violations,
            max_level=int(sel.level.max()) if len(sel) else -1,
            min_level=int(sel.level.min()) if len(sel) else -1,
        )

    def triangles(self, camera: Camera, sel: Patches) -> tuple[np.ndarray, np.ndarray]:
        """Every tessellated triangle read back (:meth:`Strategy.read_triangles`): global
        ``(col, row)`` corners ``(m, 3, 2)`` int64 and fetched heights ``(m, 3)``."""
        cap = int(tess_triangles(sel.cells_log2, sel.snap).sum())
        prog = self.probe_prog
        return self.read_triangles(
            camera, prog, cap, lambda: self._run(prog, sel), "reading tessellated triangles back"
        )

    def screen_errors(self, camera: Camera, sel: Patches) -> np.ndarray:
        tri, h = self.triangles(camera, sel)
        return triangle_screen_errors(self.r.grid, camera, tri, h, self.heights)

    def used_levels(self, camera: Camera, sel: Patches) -> dict[Block, int]:
        """The finest chunk level drawn in each block (tessellated vertices are its samples)."""
        return patch_levels(sel)

    def drawn_blocks(self, sel: Patches) -> set[Block]:
        return {tuple(int(v) for v in b) for b in sel.blocks[np.unique(sel.block)]}

    def surface(self, camera: Camera, sel: Patches):
        tri, h = self.triangles(camera, sel)
        ok = (h > -1e29).all(axis=1)
        return measure.rasterise(tri[ok], h[ok])
