"""``jung-han`` — Jung & Han (2002): 3×3-vertex blocks in a pointer-free quadtree, simplified
bottom-up on the CPU with an exact projected vertex error, cracks removed by height adjustment.

* **Quadtree.** One tree per store block (the store is a forest of them): the root block has
  3×3 vertices of spacing ``2**(k-1)`` samples and covers the whole store block; a block at depth
  ``d`` covers ``2**(k-d)`` cells; the leaves (depth ``R-1``) are 2×2 cells of the block's
  *resident* level ``R`` (the finest level of the tree; ``resident`` caps it, default what the
  ``HeightPool`` holds, as in :func:`render.strategies.qiu.select_clod`). A block's **index** is the
  concatenation of its 2-bit quadrant codes from the root down, ``code = 2*ybit + xbit`` with
  the paper's y axis pointing *up* (north): 0 = SW, 1 = SE, 2 = NW, 3 = NE; the parent is
  ``index >> 2`` and the children are ``4*index + code`` (:func:`node_index`,
  :func:`node_position`, :func:`parent_index`). Per depth the per-block data (``dmax``, ``zlo``,
  ``zhi`` of :class:`BlockTree`) are arrays indexed by that index — the paper's ``P[l] + i``.
* **Culling** (paper §4): the convex hull of the 8 frustum corners projected on the ground
  (:func:`streamer.frustum.frustum_hull`, clipped to the terrain's height range), tested
  top-down against the blocks' closed footprints; a leaf meeting it is *visible*.
* **δ** (§5.1), per vertex and precomputed per block (:func:`vertex_deltas`):
  ``δ = (mean of the two vertices the removal interpolates between) − h``, so ``B + δ`` is the
  vertex moved onto the coarser surface. An edge midpoint interpolates between the ends of its
  edge; a block centre between the ends of the diagonal its block's collapse keeps: the
  diagonal through the parent's centre (paper: quadrants 0 and 3 → SW–NE, 1 and 2 → NW–SE).
  *Choice:* the root centre (no parent) uses NW–SE; it is never removed (the paper's coarsest
  mesh keeps the 9 root vertices), so its δ only enters nothing but the ``dmax`` pyramid.
  Level-0 corners have δ = 0 and are never removed. *Choice (nodata):* δ = 0 when the vertex
  and both ends are masked (every triangle touched is hidden before and after), ∞ when some
  but not all are (removal would change what is hidden).
* **Error** (§5.1): ``δ_s`` = pixel distance between the projections of ``B`` and ``B + δ``
  (in float64, like ``gluProject``; :func:`vertex_errors` writes the difference of the two
  projections as one fraction, ``f |δ| |c_z u_xy - c_xy u_z| / (c_z (c_z + δ u_z))``, which
  equals :func:`streamer.lod.exact_projected` up to rounding without its cancellation); removal
  iff ``δ_s < τ`` (strict, so τ = 0 removes nothing). ``δ = 0`` gives ``δ_s = 0``; a point at
  or behind the eye's depth (undefined projection) gives ∞.
* **Bottom-up simplification** (§5.2), with the 12 triangle flags of the paper's ``Block``
  (bit order TL, TR, BL, BR, LT, LB, RT, RB, T, B, L, R): a visible leaf starts with its 8
  triangles; an edge vertex (T, B, L, R) is removed iff *both* triangles sharing it are present
  in the block and ``δ_s < τ`` (then e.g. TL + TR → T); the centre iff all four are removed and
  ``δ_s < τ``, and the block's two triangles move to its parent (quadrant 0 → LB, BL; 1 → BR,
  RB; 2 → LT, TL; 3 → TR, RT). The ``check``/``important`` flags only avoid computing a shared
  vertex's ``δ_s`` twice; the result does not depend on them (a shared vertex gets the same
  ``δ_s`` from both blocks), so it is not kept. Consequence of the paper's rules: a block with a
  culled leaf never collapses, so the mesh stays fine along the hull's border (on the 4097²
  benchmark view 3,995 triangles at τ = 1 instead of 275, and 3,895 remain at τ = ∞). *Default,
  not the paper:* ``culled_collapse=True`` counts a culled block as collapsed (its parent's
  triangles then cover it, off screen), which removes that band;
  ``JungHan(r, culled_collapse=False)`` is the literal reading.
* **Vectorised equivalent of the bottom-up pass.** Unrolling the rules, a block collapses iff
  every leaf under it is visible and every vertex of its closed footprint except its 4 corners
  has ``δ_s < τ`` (with ``culled_collapse``: every vertex of its non-culled blocks, a subset
  of those). The traversal is therefore top-down over arrays of blocks, one numpy pass per
  depth, and a block lying inside the hull whose *bound* on those ``δ_s`` is below τ is
  collapsed without visiting its subtree (with ``culled_collapse`` the hull test is not
  needed); every other block is resolved bottom-up exactly as
  the paper does. The bound: ``max|δ|`` over the footprint (``dmax``) times
  ``f · max_c |u_xy − q_c u_z| / z_min`` over the 8 corners ``c`` of the footprint's box with
  the footprint's height range (``u`` = world up in camera coordinates, ``q_c`` = corner's
  ``(x/z, y/z)``, ``z_min`` = smallest depth; ∞ if ``z_min <= 0``): the projected speed of a
  point moving vertically is ``(f/z)|u_xy − q u_z|`` and the box's image is convex. It is an
  upper bound (with a ``1e-9`` relative + ``1e-9`` px margin for rounding), so the mesh is the
  one of the pure bottom-up pass (``JungHan(r, prune=False)`` runs that pass; the tests check
  both give the same triangles).
* **Cracks** (§5.3): a vertex that is drawn but lies inside an edge of a drawn triangle (a
  T-junction, e.g. a vertex removed on one side of a block edge and kept on the other because
  the both-triangles rule held it) is lowered to the mean of its two neighbours along that edge,
  coarse levels first, so chains of T-junctions land on the long edge; no forced splits.
  Implemented as the linear interpolation between the ends of the drawn edge containing it
  (adjusted first), which is that mean when the neighbours are drawn, and still the right
  height when one is not (e.g. a culled block next to the hull's border). The
  same rule joins store blocks of different resident levels (the finer side's extra vertices
  are lowered; they may then err by more than τ, like the CLOD patches' snapped edges).
  T-junctions are found on the drawn mesh itself (every axis-aligned edge against every drawn
  vertex, by sorting), so culled neighbours adjust nothing.
* **GL difference — conforming split:** a lowered T-junction vertex lies on the long edge
  mathematically, but GL rasterisers are only watertight along edges shared whole (vertices
  are snapped to sub-pixel grids independently; llvmpipe drops pixel centres within ~1/256 px
  of such an edge). So after the height adjustment every triangle with a drawn vertex inside
  an edge is split at that vertex (:func:`conform`). No vertex is added and the surface is the
  same plane by plane, unlike the forced splits the paper avoids (which add the neighbour's
  detail); it costs one triangle per T-junction. ``RenderStats.triangles`` counts the drawn
  (split) triangles, ``JHSelection.jh_triangles`` the paper's.
* **GL 4.5 instead of the paper's immediate mode:** the mesh is built on the CPU and drawn as
  one indexed triangle list per ``HeightPool`` page. Per vertex: the block origin and the
  in-block sample (integers, like the renderer's instances), the slot base, the drawn block's
  level and the drawn (possibly adjusted) height. The vertex shader calls
  ``render/glsl/fetch.glsl``'s ``vertex_at`` (same fetch, mask, normal at the drawn level and
  camera-relative integer-sample position path as every strategy) and replaces the height by
  the drawn one; shared vertices are bit-identical. Masked samples keep ``v_masked`` and are
  discarded by the shared fragment shader; the normals ignore height adjustments. The paper
  resets the flags after each frame; here each ``select`` starts from scratch.
* **Compiled kernels** (:mod:`render.strategies.jung_han.kernels`): with numba, the traversal
  runs compiled over the trees held flat
  (:class:`~render.strategies.jung_han.kernels.Forest`, which copies in only the trees built or
  rebuilt since the last frame; each tree is built compiled too) and the whole mesh assembly (vertex
  keys, heights, T-junction search, height adjustment, conforming split, GPU arrays) in one
  more kernel call, which finds vertices by their rank along a row or column instead of
  searching sorted keys; the traversal tries two cheap bounds from the box's centre and half
  extents in camera axes (above and below the exact one where finite) before the exact one,
  so the pruning is the same; their node buffers and sort workspace are kept between frames;
  ``kernels="numpy"`` (or ``TERRASTREAM_KERNELS=numpy``) runs the numpy reference, which the
  tests compare exactly.
* **Stats:** ``patches`` = drawn JH blocks (with at least one triangle), ``max/min_level`` =
  their levels ``depth + 1`` (0 for a block resident at level 0, drawn as its 2 corner
  triangles, NW–SE), ``clamped`` = drawn blocks at the finest depth of a tree whose resident
  level is below ``k`` (they could have wanted finer data), ``violations`` = 0.
"""

from render.strategies.jung_han.gl import JungHan
from render.strategies.jung_han.pure import (
    BITS,
    EDGE_QUADS,
    FAN_EDGE,
    FAN_QUAD,
    NE,
    NW,
    OWN,
    SE,
    SW,
    TEMPLATE,
    TRIANGLES,
    BlockTree,
    JHSelection,
    LevelNodes,
    conform,
    corners_inside,
    flag_names,
    gather,
    node_index,
    node_position,
    parent_index,
    projected_bound,
    t_junctions,
    vertex_deltas,
    vertex_errors,
)
from render.strategies.jung_han.selection import JungHanSelector

__all__ = [
    "JungHan",
    "JungHanSelector",
    "TRIANGLES",
    "TEMPLATE",
    "OWN",
    "EDGE_QUADS",
    "FAN_QUAD",
    "FAN_EDGE",
    "BITS",
    "SW",
    "SE",
    "NW",
    "NE",
    "node_index",
    "node_position",
    "parent_index",
    "vertex_deltas",
    "BlockTree",
    "vertex_errors",
    "projected_bound",
    "corners_inside",
    "JHSelection",
    "flag_names",
    "LevelNodes",
    "gather",
    "t_junctions",
    "conform",
]
