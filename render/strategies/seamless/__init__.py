"""``seamless-patches`` — Livny, Kogan & El-Sana's seamless patches: rectangular patches made of
four triangular tiles (cut by the diagonals) at power-of-two resolutions, stitched by strips.

* **Patches** are quadtree nodes of the store blocks (the paper's implicit hierarchy; its root is
  a block). A patch at depth ``d`` has edge ``E = 2**(k-d)`` samples. Its four tiles (N, E, S, W)
  each span one patch edge and the centre; a tile of resolution ``2**r`` has ``2**r`` cells along
  its edge, drawn from store level ``d + r``. Resolutions are ``2, 4, …, 2**c`` (``c =
  res_log2``, default 5: tiles of up to 32 cells; 2 is the least that has the centre vertex), so
  every tile and strip vertex is a sample of the level grid it is drawn from. Leaves go no deeper
  than ``k - c`` (there ``2**c`` cells are full resolution).
* **Tiles and strips** (cached meshes). A tile of ``n`` cells keeps its whole cells; the half
  cells cut by the two diagonals belong to the **strips**, one per half diagonal (N-E, E-S, S-W,
  W-N). The strip between tiles of ``na >= nb`` cells holds the finer tile's half cells as they
  are and splits each half cell of the coarser tile into a fan from its off-diagonal corner to
  the finer tile's diagonal vertices, so both tiles' vertices on the diagonal are shared and
  there is no T-junction and no zero-area triangle. Counts: a tile ``n**2/2 - n`` (none for
  ``n = 2``), a strip ``max(na, nb)``; four equal tiles and their strips give ``2 n**2`` (the
  full grid). The paper needs ``R (R + 1) / 2`` strips for ``R`` resolutions (it mirrors
  them); we cache every *ordered* pair (``c**2`` strips, one canonical orientation each) and
  ``c`` tiles. The selection (:class:`PatchLayout`) is only the leaves and their edge levels.
* **Rotation** (GL difference): the paper stores four orientations of every mesh; we store one
  (the north tile, the north-east strip) and the vertex shader rotates the integer ``(u, v)``
  by the instance's quarter turns (``(u, v) -> (C - v, u)``, exact integers).
* **Instancing**: all meshes live in one vertex buffer ``(u, v, r)`` (``u, v`` in units of
  ``2**-c`` patch edges, ``r`` the resolution the vertex belongs to). Per frame only the layout
  travels: per tile or strip one instance (the renderer's 32-byte layout: block origin, node
  origin, pool slot base, level of the ``2**c`` unit, rotation) in a storage buffer, sorted by
  mesh; each mesh is drawn instanced (``vao.render(first, vertices, instances)``), reading its
  instances at ``inst0 + gl_InstanceID`` (GL 4.5 has no base instance without 4.6 draw
  parameters, hence the uniform offset). Heights are fetched in the vertex shader from the
  ``HeightPool`` with ``render/glsl/fetch.glsl``'s ``vertex_at`` (the paper's displacement
  textures), at integer samples: a vertex shared by two patches has the same global sample and
  height on both sides, bit for bit.
* **ε = ρ·l/d per edge** (the paper's Equation 1). ``l`` is the edge length (world units), ``d``
  the distance from the eye to the edge segment (the segment lifted to the z range of the blocks
  on both sides). The paper's ρ is a global precision factor; by default (``rho="bound"``,
  ours) we make it carry τ and the stored roughness so that ε is a screen-space quantity:
  ``ρ = 2 f δ / (τ 2**c l)`` where ``f`` is the focal length in pixels (viewport height,
  :attr:`Camera.focal_px`) and ``δ`` the larger of the stored ``bound`` errors of the two
  depth-``d`` nodes beside the edge drawn at level ``d + 1`` (the coarsest tiles;
  ``PatchTable(k, 1)``). So ``ε 2**c / 2`` is the pixel error of the
  edge's coarsest tile over τ, and with error proportional to cell size (the paper's linear
  rule) ``ε 2**c`` cells meet τ. Split the patch if any edge has ``ε > 1`` (the finest tile would
  not meet τ); otherwise edge resolution = ``ε 2**c`` rounded up to a power of two (the paper's
  "ε R_max rounded up"), at least 2. δ and d depend on the edge's global position only, so both
  patches of an edge compute the same ε without querying each other. τ = 0 gives ε = ∞ wherever
  δ > 0 (full resolution); δ = 0 gives ε = 0 (a flat node is exact at any resolution).
  ``--metric`` does not apply (``uses_metric = False``). A leaf at the bottom depth (or held by
  its resident level) may keep ``ε > 1``; it is drawn at its finest level.
* **ρ as published** (``SeamlessPatches(r, rho="paper")``; the default ``rho="bound"`` is the
  form above, ours). Section 3, "Level of Detail": "The resolution of an edge is computed based
  on its length l and the distance d from the viewpoint by using Equation 1, where ρ is a
  precision factor"; Section 5 (Table 1, Figures 8-9) runs it at ``ρ_0`` and ``2 ρ_0``: one
  global factor for the whole frame, read from nothing in the data (no roughness, no stored
  error, no slope), and the paper gives no value for ``ρ_0`` and has no τ. The literal reading
  keeps ρ a constant and only names ``ρ_0`` in our units: ``ρ = f / (τ 2**c)``, so τ is the
  largest *projected cell* (sample spacing) in pixels: an edge given ``ε R_max`` cells (rounded
  up) has cells of at most ``l / (ε 2**c)`` world units at distance ``d``, i.e. at most
  ``f l / (d ε 2**c) = f / (ρ 2**c) = τ`` px. ``2 ρ_0`` is τ/2. The split (any edge ``ε > 1``)
  and the edge resolution (``ε R_max`` rounded up; Claim 1's ``R1`` for ``ε ≤ 0.5``, ``R2`` for
  ``(0.5, 1]``) are the same for both forms, and so are ``l``, ``d`` and the shared-edge
  resolution below. So with the paper's ρ a flat patch is refined exactly as a rough one, and
  the measured height error is not bounded by τ (BENCHMARKS.md, "Seamless patches: ρ as
  published"). ``spike_guard`` combines with either form. One thing of ours stays in the
  paper's form: an edge beside a node that mixes terrain and nodata (stored error ∞, the
  project's nodata rule, docs/RENDER.md "Precision and extremes") gets ρ = ∞, so mask
  boundaries are drawn at full resolution; without it the paper's coarse tiles dropped
  0.1-1.8 % of the in-view terrain samples of N44W072 (reprojected, padded) at τ = 0.5-4.
* **Patches of different sizes** (the paper's Claim 1 is proved only for two resolutions, and
  its "branching factor = ratio of resolutions"): a coarse edge of ``2**(k-d)`` samples and the
  finer patches' edges along it must use one sample spacing ``2**(k-L)``. The levels a patch can
  use are ``d + 1 .. min(d + c, resident)``; we keep the quadtree (branching 2) and restrict it
  instead: after selection, every maximal shared edge (one coarse edge and the leaves across it)
  takes the finest level any of them wants, clipped to the levels all of them can draw; when
  there is none (depth difference ``>= c``) or the finer side wants more than the coarse patch
  can give, the coarse patch is split (and its children traversed as usual) until it settles.
  So neighbours agree on every shared edge: no cracks, no degenerate triangles.
* **Resident levels** (streaming): a block is drawn at levels ``<=`` its resident level
  (``resident``, default what is on the GPU); its leaves go no deeper than ``cap' - 1`` where
  ``cap'`` is the least resident level of it and its drawn edge neighbours (a shared edge
  needs a level both sides hold). A node that wants to split but whose children could not be
  finer counts as ``clamped``; a block with only level 0 is not drawn (no centre sample) and also
  counts as clamped. An edge whose sides cannot agree (not seen with whole-level residency)
  counts as a ``violation``.
* **Compiled kernels** (:mod:`render.strategies.seamless.kernels`): with numba, the per-depth
  edge ε, the nodes' frustum test, the shared-edge grouping and resolution run compiled — the
  whole selection in one call without the spike guard (the guard's term stays numpy);
  ``kernels="numpy"`` (or ``TERRASTREAM_KERNELS=numpy``) runs the numpy reference, which the
  tests compare exactly.
* **Triangles** = Σ mesh triangles × instances (``RenderStats.triangles``), checked against a
  read-back: the probe program's geometry shader appends every drawn triangle (global integer
  samples and fetched heights) to a storage buffer under ``RASTERIZER_DISCARD``; the measured
  error rasterises those on the sample lattice (:func:`triangle_screen_errors`).
"""

from render.strategies.seamless.gl import SeamlessPatches
from render.strategies.seamless.layout import (
    RHO_FORMS,
    PatchLayout,
    edge_epsilon,
    edge_resolution,
    paper_precision,
    precision,
)
from render.strategies.seamless.meshes import (
    DIRS,
    mesh_kinds,
    mesh_of,
    rotate,
    strip_mesh,
    strip_triangles,
    tile_mesh,
    tile_triangles,
)
from render.strategies.seamless.selection import select_layout

__all__ = [
    "DIRS",
    "PatchLayout",
    "RHO_FORMS",
    "SeamlessPatches",
    "edge_epsilon",
    "edge_resolution",
    "mesh_kinds",
    "mesh_of",
    "paper_precision",
    "precision",
    "rotate",
    "select_layout",
    "strip_mesh",
    "strip_triangles",
    "tile_mesh",
    "tile_triangles",
]
