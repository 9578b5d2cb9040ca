"""``chunk-tessellation`` — Kim, Lee & Shin's GPU chunk LOD: the quadtree traversal stops at
chunks that the hardware tessellator draws; the traversal runs on the CPU or, as in the paper,
on the GPU (``chunk-tessellation-gpu``).

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
* **Selection on the CPU or the GPU** (``ChunkTessellation(r, selection="cpu" | "gpu")``;
  ``chunk-tessellation-gpu`` is the GPU one by name). ``"cpu"`` (the default) is the shared
  breadth-first :func:`render.select.select_patches` plus :func:`render.select.stitch`.
  ``"gpu"`` is the paper's 3.1–3.2 (:mod:`.gpu`, ``traverse.glsl``/``traverse.geom``/
  ``emit.geom``): a node is a point ``(block, depth | done << 8, row, col)`` plus 4 channels
  (the paper's RGBA) holding the levels of the neighbours N, E, S, W; each pass (a geometry
  shader with transform feedback, :func:`render.strategies.feedback.feedback_pass`, the
  machinery of ``geometry-splitting``) makes, for every still unset channel, the virtual
  same-depth neighbour and runs the node's own split test on it — a neighbour that does not
  split is a leaf, its level goes in the channel; a missing one (terrain edge, block not drawn,
  culled, all padding) stores "none". A node that splits emits its visible children, each
  inheriting the channels of the parent's outer edges it lies on; a node that stops fills its
  unset channels with its own level (the neighbour is finer: no snap). One emit pass per height
  page turns the leaves into the tessellation draw's vertices (the CPU layout,
  ``snap_e = clamp(level - channel_e, 0, cells)``, zero with ``stitching`` off) and counts
  triangles, clamped nodes, violations and the level range with atomics (32 bytes back, plus
  4 bytes per pass for the pass counts). The split test is the CPU one on the same inputs:
  ``ε`` from the same ``PatchTable`` (uploaded once per block as float32), the block's height
  range, ``kim_metric`` in camera-relative float32, the same frustum-hull disc cull
  (:class:`render.select.DiscCull`: the hull is a uniform), the same padding rule and resident
  caps (``select(resident=...)``); pages only choose which buffer a chunk fetches from. The
  traversal starts splitting unconditionally down to ``start_depth = max(0, k - 2c)`` (the
  paper starts at depth 2 for 32-cell chunks on its terrains): chunks then lie at depths
  ``start..k-c``, so adjacent chunks differ by at most ``c`` levels, every outer factor is
  ``>= 1`` and the CPU's restriction splits (which the channels cannot express) never occur.
  The GPU result equals :meth:`ChunkTessellation.select_twin` (``select_clod`` with
  ``min_depth = start_depth``; the CPU variant itself when ``k <= 2c``, e.g. 257² blocks at
  ``c = 5``) chunk for chunk and snap for snap (tests; float32 against float64 could differ at
  a τ within rounding of a node's error, not seen in the tests). Per frame the CPU makes the
  block table (64 bytes per drawn block: origin, pool base, cap, ε offset, page, DEM window,
  neighbours, height range), the hull and the uniforms (``select``'s ms); the passes are GPU
  work, timed in ``select`` and added to the frame's GPU ms. The chunks stay on the GPU (read
  back only for the measurements: :meth:`ChunkTessellation.patches`).
* **Heights** are fetched in the tessellation evaluation shader with the renderer's
  level/order-index path (``render/glsl/fetch.glsl``: ``vertex_at``), from the same
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

from render.strategies.chunk_tess.gl import ChunkTessellation, ChunkTessellationGpu
from render.strategies.chunk_tess.gpu import GpuChunks
from render.strategies.chunk_tess.pure import (
    MAX_TESS_VERTICES,
    batch_chunks,
    kim_metric,
    outer_factors,
    start_depth,
    tess_triangles,
)

__all__ = [
    "MAX_TESS_VERTICES",
    "ChunkTessellation",
    "ChunkTessellationGpu",
    "GpuChunks",
    "batch_chunks",
    "kim_metric",
    "outer_factors",
    "start_depth",
    "tess_triangles",
]
