"""``geometry-splitting`` — Lee & Shin (2011): a per-block quadtree expanded on the GPU by
repeated geometry-shader passes with transform feedback, cracks removed on the GPU by
triangle splitting at T-vertices. Per frame the CPU sends the camera uniforms, τ, the root list
(one point per drawn block) and the block table (64 bytes per drawn block: origin, pool slot,
resident cap, neighbours); the quadtree texture is uploaded once per block.

Choices where the paper is open, and GL 4.5 / moderngl in place of DirectX 10:

* **Quadtree**: one per store block (``2**k`` cells). A node at depth ``d`` covers ``2**(k-d)``
  cells and is drawn as one quad of level ``d`` (its 4 corners), cut along the ``a-d`` diagonal
  like :mod:`render.mesh`; depth ``k`` nodes are full-resolution cells. A node may split only
  while ``d < cap`` (the block's resident level, ``select(resident=...)`` or the GPU level).
* **Roughness** ``δ_l`` (the paper's five midpoint errors, precomputed): the store's ``bound``
  field, computed at tiling time — the largest vertical distance of any valid full-resolution
  sample of the node from its quad (either diagonal, float16 rounded up; below the store's cap
  depth one value covers a tile of nodes — when the block is resident at full resolution
  those deepest depths are computed exactly from its heights, :func:`quad_errors`), so it bounds
  what a leaf draws without T-vertices.
  Masked samples are ignored, as for every strategy (docs/RENDER.md, nodata). ``σ_k = 0``,
  ``σ_l = max(δ_l, 2 max σ_(l+1) of the children)`` (:func:`roughness`, Eq. 3 applied
  recursively). The "quadtree texture" is an SSBO per block in depth order holding per node
  ``σ`` (float32 rounded up, which keeps the doubling exact) and the node's height range as
  two halves (rounded outwards): its 4 corners ``∓ δ`` from the block's *resident* level grid
  (:func:`stored_tree`), rebuilt when the resident level changes — nothing finer than the
  session loaded is read; depth ``k`` nodes are not stored (``σ = 0``, parent's range).
* **Split flag** (Eq. 2): bounding sphere centred on the node at its mid height, radius
  ``half diagonal + half height range`` (a child's sphere lies inside its parent's). Eye inside
  and ``σ ≠ 0``: split. Otherwise split iff ``τ <= σ̄``, ``σ̄`` = the largest pixel distance
  between the projections of ``v`` and ``v + (0, 0, σ)`` over the node's centre and 4 edge
  midpoints; the five points sit at the node's mid height (so the expansion reads no heights);
  a point at or behind the eye plane gives ``σ̄ = inf``. At τ = 0 every node with the eye
  outside splits (the full mesh).
* **Culling** ("children culled against the frustum", Sect. 3): a node is dropped when its
  culling sphere lies outside one of the 6 frustum planes. The culling sphere is the node's
  column through the *terrain's* height range (centre at its mid height, radius half diagonal
  + half range), not the tight per-node sphere: per-node spheres cull hills beyond the view's
  top edge while keeping the valleys around them, so a selection seen from another camera
  would show enclosed holes; with the slab the culled ground is the frustum's shadow on the
  terrain slab, as for the CPU strategies. Child spheres lie inside their parent's.
* **Expansion** (vertex splitting): a node is a point ``ivec4(block, depth | done << 8, row,
  col)``; each pass a geometry shader emits the node's visible children when it splits, or the
  node marked done (leaves are carried through later passes). Children are culled (above);
  pass 0 also culls the roots. ``k`` passes. DirectX's stream output + DrawAuto become GL
  transform feedback (``VertexArray.transform``) with the count of each pass read back through
  a ``GL_PRIMITIVES_GENERATED`` query (moderngl exposes no ``glDrawTransformFeedback``): 4
  bytes per pass travel back, the nodes never do (plus 16 bytes of frame statistics: leaves
  whose flag wanted a split their cap refused, ``RenderStats.clamped``, and the depth range).
* **Crack removal** (triangle splitting, Figs. 7–9): a leaf whose same-depth neighbours all do
  not split is drawn as 2 triangles; otherwise as 4 triangles fanned from its centre (the true
  centre sample when level ``d+1`` is resident, else the diagonal's midpoint), one per edge,
  each carrying its edge's neighbour node ``N``. Passes of a second geometry shader (transform
  feedback again) replace a triangle ``ABC`` whose ``N`` splits by ``ATC`` and ``TBC`` at the
  edge midpoint ``T`` with the two children of ``N`` as new neighbours, until a pass adds none.
  "``N`` splits" means ``N`` exists (visible, every ancestor not shared with the leaf split) and
  its flag and cap allow it (as the paper: "if N's flag is 1"), so a leaf's edge gets the
  midpoint of every split node across it: all corners of the leaves across, at any level
  difference (the doubling rule keeps it small), plus, next to culled children only, a
  harmless vertex nothing across needs. Triangles per leaf:
  ``2`` without T-vertices, else ``4 + T-vertices on its edges``.
* **Resident caps / pages**: a T-vertex finer than the leaf's own resident level is fetched from
  the neighbour block (which split there, so holds it). Heights live in ``HeightPool`` pages
  (one SSBO each); when two adjacent blocks sit on different pages, nodes touching their shared
  border may not split below the other block's cap (so every T-vertex is in the own block).
* **Draw**: vertex pulling — the triangle records stay in a GPU buffer and a vertex shader
  builds each corner with ``render/glsl/fetch.glsl``'s ``vertex_at`` (camera-relative, integer
  global sample, bit-identical shared vertices), then ``EMIT``/``FRAGMENT`` or the wireframe
  ``GEOMETRY``/``FRAGMENT_WIRE``; one draw per height page. ``select`` runs the GPU passes for
  its camera; ``draw`` may use another camera. ``RenderStats.triangles`` is the
  transform-feedback count of drawn triangles.
* **Timing**: the CPU's share of a frame (``select``'s ms) is the block table and root list
  only; the expansion and splitting passes are GPU work, timed in ``select`` and added to the
  frame's GPU ms (``RenderStats.frame_ms`` = passes + draw). Building a block's quadtree
  texture (when its resident level changes: one level read and a few numpy passes) is
  load-time work, like decoding, and is left out of both.
"""

from render.strategies.geometry_splitting.gl import NO_CAP, GeometrySplitting, Selection
from render.strategies.geometry_splitting.pure import (
    BlockTree,
    packed_tree,
    projected_error,
    quad_errors,
    roughness,
    stored_tree,
    texture_depth,
    texture_nodes,
)
from render.strategies.geometry_splitting.reference import CULL_MARGIN, expand_reference

__all__ = [
    "CULL_MARGIN",
    "NO_CAP",
    "BlockTree",
    "GeometrySplitting",
    "Selection",
    "expand_reference",
    "packed_tree",
    "projected_error",
    "quad_errors",
    "roughness",
    "stored_tree",
    "texture_depth",
    "texture_nodes",
]
