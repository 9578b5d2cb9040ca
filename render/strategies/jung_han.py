"""``jung-han`` — Jung & Han (2002): 3×3-vertex blocks in a pointer-free quadtree, simplified
bottom-up on the CPU with an exact projected vertex error, cracks removed by height adjustment.

* **Quadtree.** One tree per store block (the store is a forest of them): the root block has
  3×3 vertices of spacing ``2**(k-1)`` samples and covers the whole store block; a block at depth
  ``d`` covers ``2**(k-d)`` cells; the leaves (depth ``R-1``) are 2×2 cells of the block's
  *resident* level ``R`` (the finest level of the tree; ``resident`` caps it, default what the
  ``HeightPool`` holds, as in :meth:`TerrainRenderer.select`). A block's **index** is the
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
  (:func:`streamer.lod.exact_projected`, the float64 twin of ``gluProject``); removal iff
  ``δ_s < τ`` (strict, so τ = 0 removes nothing). ``δ = 0`` gives ``δ_s = 0``; a point behind
  the eye (undefined projection) gives ∞.
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
  ``shaders.FETCH_COMMON.vertex_at`` (same fetch, mask, normal at the drawn level and
  camera-relative integer-sample position path as every strategy) and replaces the height by
  the drawn one; shared vertices are bit-identical. Masked samples keep ``v_masked`` and are
  discarded by the shared fragment shader; the normals ignore height adjustments. The paper
  resets the flags after each frame; here each ``select`` starts from scratch.
* **Stats:** ``patches`` = drawn JH blocks (with at least one triangle), ``max/min_level`` =
  their levels ``depth + 1`` (0 for a block resident at level 0, drawn as its 2 corner
  triangles, NW–SE), ``clamped`` = drawn blocks at the finest depth of a tree whose resident
  level is below ``k`` (they could have wanted finer data), ``violations`` = 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cache

import moderngl
import numpy as np

from render import measure, shaders
from render.gpu import check_gl
from render.renderer import RenderStats, TerrainRenderer
from render.select import check_tau
from render.strategies.base import Block, GlobalHeights, Strategy, triangle_screen_errors
from streamer.camera import Camera
from streamer.frustum import as_polygon, frustum_hull, polygon_meets_rects
from streamer.lod import exact_projected
from tiler.layout import trailing_zeros

#: the paper's 12 triangles, in the bit order of its ``Block`` structure
TRIANGLES = ("TL", "TR", "BL", "BR", "LT", "LB", "RT", "RB", "T", "B", "L", "R")
#: quadrant codes (first bit: y up = north, second bit: x = east)
SW, SE, NW, NE = 0, 1, 2, 3
_PT = {
    "C": (1, 1), "NW": (0, 0), "NE": (2, 0), "SW": (0, 2), "SE": (2, 2),
    "T": (1, 0), "B": (1, 2), "L": (0, 1), "R": (2, 1),
}  # fmt: skip
_TRI = {
    "TL": ("C", "NW", "T"), "TR": ("C", "T", "NE"), "BL": ("C", "SW", "B"),
    "BR": ("C", "B", "SE"), "LT": ("C", "NW", "L"), "LB": ("C", "L", "SW"),
    "RT": ("C", "NE", "R"), "RB": ("C", "R", "SE"), "T": ("C", "NW", "NE"),
    "B": ("C", "SW", "SE"), "L": ("C", "NW", "SW"), "R": ("C", "NE", "SE"),
}  # fmt: skip
#: ``(12, 3, 2)`` triangle corners ``(col, row)`` in half-block units from the NW corner
TEMPLATE = np.array([[_PT[p] for p in _TRI[t]] for t in TRIANGLES], dtype=np.int64)
#: the block's own vertices C, T, B, L, R as ``(col, row)`` half-block offsets
OWN = np.array([_PT[p] for p in ("C", "T", "B", "L", "R")], dtype=np.int64)
#: per edge T, B, L, R: the two quadrants whose triangles share its midpoint
EDGE_QUADS = np.array([[NW, NE], [SW, SE], [NW, SW], [NE, SE]])
#: per fan triangle TL..RB: its quadrant and its edge (0..3 = T, B, L, R)
FAN_QUAD = np.array([NW, NE, SW, SE, NW, SW, NE, SE])
FAN_EDGE = np.array([0, 0, 1, 1, 2, 2, 3, 3])
_BITS = 1 << np.arange(12, dtype=np.int64)

VS = (
    shaders.FETCH_COMMON
    + """
in ivec4 in_a;   // block origin (global col, row), vertex (col, row) in the block
in ivec4 in_b;   // slot base, drawn level, 0, 0
in float in_h;   // drawn (possibly height-adjusted) height
Vtx jh_vertex() {
    Vtx v = vertex_at(in_a, in_b, 0, 0);
    if (v.masked == 0.0) {
        v.h = in_h;
        v.rel.z = in_h - cam_frac.z;
    }
    return v;
}
"""
    + shaders.EMIT
    + "void main() { emit(jh_vertex()); }\n"
)


# --- the pointer-free quadtree ----------------------------------------------------------------


def node_index(row: np.ndarray, col: np.ndarray, depth: int) -> np.ndarray:
    """Jung & Han's index of the depth-``depth`` block at ``(row, col)`` of its tree's
    ``2**depth`` square grid (row 0 = north): the concatenated 2-bit quadrant codes."""
    row = np.asarray(row, dtype=np.int64)
    col = np.asarray(col, dtype=np.int64)
    yup = (1 << depth) - 1 - row
    idx = np.zeros(np.broadcast(row, col).shape, dtype=np.int64)
    for j in range(depth - 1, -1, -1):
        idx = (idx << 2) | (((yup >> j) & 1) << 1) | ((col >> j) & 1)
    return idx


def node_position(index: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray]:
    """``(row, col)`` (row 0 = north) of the depth-``depth`` block with Jung & Han's ``index``
    (the paper's Figure 5: x from the second bits, y from the first bits, scaled per level)."""
    idx = np.asarray(index, dtype=np.int64)
    col = np.zeros(idx.shape, dtype=np.int64)
    yup = np.zeros(idx.shape, dtype=np.int64)
    for j in range(depth):
        code = (idx >> (2 * (depth - 1 - j))) & 3
        w = 1 << (depth - 1 - j)
        col += (code & 1) * w
        yup += (code >> 1) * w
    return (1 << depth) - 1 - yup, col


def parent_index(index: np.ndarray) -> np.ndarray:
    """The parent's index: ``index >> 2``."""
    return np.asarray(index, dtype=np.int64) >> 2


@cache
def _perm(depth: int) -> np.ndarray:
    """Row-major grid position of every index of a depth (index order -> grid order)."""
    r, c = node_position(np.arange(1 << (2 * depth), dtype=np.int64), depth)
    return r * (1 << depth) + c


def vertex_deltas(heights: np.ndarray) -> np.ndarray:
    """Per-vertex δ of a ``(2**R+1)²`` level grid (NaN = masked): mean of the two vertices its
    removal interpolates between minus its height (0 at the corners; see the module notes)."""
    g = np.asarray(heights, dtype=np.float64)
    n = g.shape[0]
    big = n - 1
    if g.shape != (n, n) or big < 1 or big & (big - 1):
        raise ValueError(f"expected a (2**R+1)² grid, got shape {g.shape}")
    rr = big.bit_length() - 1
    valid = np.isfinite(g)
    out = np.zeros(g.shape)

    def value(v, a, b):
        d = 0.5 * (g[a] + g[b]) - g[v]
        ok = valid[v] & valid[a] & valid[b]
        none = ~(valid[v] | valid[a] | valid[b])
        return np.where(ok, d, np.where(none, 0.0, np.inf))

    for lv in range(1, rr + 1):
        s = 1 << (rr - lv)
        t = 2 * s
        even, odd, lo, hi = slice(0, n, t), slice(s, n, t), slice(0, n - s, t), slice(t, n, t)
        out[even, odd] = value((even, odd), (even, lo), (even, hi))  # horizontal-edge midpoints
        out[odd, even] = value((odd, even), (lo, even), (hi, even))  # vertical-edge midpoints
        nwse = value((odd, odd), (lo, lo), (hi, hi))
        swne = value((odd, odd), (hi, lo), (lo, hi))
        m = 1 << (lv - 1)
        a = np.arange(m)
        xor = ((a[:, None] & 1) ^ (a[None, :] & 1)).astype(bool)  # quadrant 0 or 3 in parent
        out[odd, odd] = np.where(xor, swne, nwse)
    return out


@dataclass
class BlockTree:
    """One store block's quadtree data at its resident level ``level``: heights and δ on the
    level grid, and per depth ``d < level``, in index order, the largest ``|δ|`` of the closed
    footprint without its corners (``dmax``) and the footprint's height range."""

    level: int
    heights: np.ndarray  # (2**level+1)² float32, NaN where masked
    delta: np.ndarray  # same shape, float32
    dmax: list[np.ndarray] = field(default_factory=list)
    zlo: list[np.ndarray] = field(default_factory=list)
    zhi: list[np.ndarray] = field(default_factory=list)

    @classmethod
    def build(cls, heights: np.ndarray) -> BlockTree:
        """δ and the index-ordered pyramids of a level grid."""
        h = np.asarray(heights, dtype=np.float32)
        n = h.shape[0]
        rr = (n - 1).bit_length() - 1
        delta = vertex_deltas(h).astype(np.float32)
        tree = cls(rr, h, delta, [None] * rr, [None] * rr, [None] * rr)  # type: ignore[list-item]
        ad = np.abs(delta)
        for d in range(rr - 1, -1, -1):
            step = 1 << (rr - d)
            half = step >> 1
            c, e0, e1 = slice(half, n, step), slice(0, n - 1, step), slice(step, n, step)
            own = np.maximum.reduce([ad[c, c], ad[e0, c], ad[e1, c], ad[c, e0], ad[c, e1]])
            own = own.ravel()[_perm(d)]
            if d == rr - 1:
                wins = [h[i : n - 2 + i : 2, j : n - 2 + j : 2] for i in range(3) for j in range(3)]
                tree.zlo[d] = np.fmin.reduce(wins).ravel()[_perm(d)]
                tree.zhi[d] = np.fmax.reduce(wins).ravel()[_perm(d)]
                tree.dmax[d] = own
            else:
                tree.zlo[d] = np.fmin.reduce(tree.zlo[d + 1].reshape(-1, 4), axis=1)
                tree.zhi[d] = np.fmax.reduce(tree.zhi[d + 1].reshape(-1, 4), axis=1)
                tree.dmax[d] = np.maximum(own, tree.dmax[d + 1].reshape(-1, 4).max(axis=1))
        return tree


# --- errors and culling -----------------------------------------------------------------------


def vertex_errors(delta: np.ndarray, points: np.ndarray, camera: Camera) -> np.ndarray:
    """``δ_s``: pixel distance between the projections of ``B`` and ``B + δ`` (0 for δ = 0,
    ∞ where undefined, e.g. behind the eye)."""
    d = np.asarray(delta, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        rho = exact_projected(d, points, camera)
    return np.where(d == 0.0, 0.0, np.where(np.isfinite(rho), rho, np.inf))


def projected_bound(
    camera: Camera,
    dmax: np.ndarray,
    xmin: np.ndarray,
    xmax: np.ndarray,
    ymin: np.ndarray,
    ymax: np.ndarray,
    zlo: np.ndarray,
    zhi: np.ndarray,
) -> np.ndarray:
    """Upper bound on ``δ_s`` of any vertical move by at most ``dmax`` inside each box."""
    xs = np.stack([xmin, xmax], -1)[:, :, None, None]
    ys = np.stack([ymin, ymax], -1)[:, None, :, None]
    zs = np.stack([zlo, zhi], -1)[:, None, None, :]
    pts = np.stack(np.broadcast_arrays(xs, ys, zs), -1).reshape(len(xmin), 8, 3)
    cam = camera.to_camera(pts)
    z = cam[..., 2]
    zmin = z.min(axis=1)
    u = np.array([camera.right[2], camera.up[2], camera.forward[2]])
    with np.errstate(divide="ignore", invalid="ignore"):
        qx, qy = cam[..., 0] / z, cam[..., 1] / z
        gain = np.hypot(u[0] - qx * u[2], u[1] - qy * u[2]).max(axis=1)
        b = camera.focal_px * np.asarray(dmax, dtype=np.float64) * gain / zmin
    b = np.where(zmin > 0.0, b, np.inf)
    b = np.where(np.asarray(dmax) == 0.0, 0.0, b)
    return b * (1.0 + 1e-9) + 1e-9


def corners_inside(
    poly: np.ndarray, xmin: np.ndarray, ymin: np.ndarray, xmax: np.ndarray, ymax: np.ndarray
) -> np.ndarray:
    """Boolean per rectangle: all 4 corners lie in the closed convex polygon."""
    p = as_polygon(poly)
    xmin = np.asarray(xmin, dtype=np.float64)
    if len(p) < 3:
        return np.zeros(xmin.shape, dtype=bool)
    o = p[0]
    q = p - o
    e = np.roll(q, -1, axis=0) - q
    ok = np.ones(xmin.shape, dtype=bool)
    for x, y in ((xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)):
        dx = (np.asarray(x) - o[0])[..., None] - q[:, 0]
        dy = (np.asarray(y) - o[1])[..., None] - q[:, 1]
        ok &= (e[:, 0] * dy - e[:, 1] * dx >= 0.0).all(axis=-1)
    return ok


# --- the selection ----------------------------------------------------------------------------


@dataclass
class JHSelection:
    """What one frame draws: triangles with global ``(col, row)`` corners and drawn heights,
    the drawn JH blocks with their triangle flags, and the GPU vertex/index arrays."""

    blocks: list[Block]  # slot -> store block
    levels: np.ndarray  # slot -> resident level of its tree
    tri: np.ndarray  # (m, 3, 2) int64 global (col, row), drawn (after the conforming split)
    tri_h: np.ndarray  # (m, 3) float64 drawn heights (NaN where masked)
    tri_slot: np.ndarray  # (m,)
    tri_level: np.ndarray  # (m,) level (depth + 1) of the drawing block
    nodes: np.ndarray  # (p, 3) drawn JH blocks: slot, depth, index
    flags: np.ndarray  # (p,) their 12 triangle flags (bit i = TRIANGLES[i])
    adjusted: np.ndarray  # (a, 2) global (col, row) of the height-adjusted vertices
    corner_blocks: int  # store blocks drawn as their 2 level-0 triangles
    clamped: int
    evaluated: int = 0  # JH blocks whose own 5 vertices' δ_s were computed
    jh_triangles: int = 0  # the paper's triangles, before the conforming split
    v_slot: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, np.int64))
    v_level: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, np.int64))
    v_cr: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 2), np.int64))
    v_h: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, np.float32))
    index: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 3), np.int64))

    def __len__(self) -> int:
        return len(self.tri)

    def node_flags(self, block: Block, depth: int, index: int) -> int | None:
        """The triangle flags of a drawn JH block (None if it draws nothing itself)."""
        if block not in self.blocks:
            return None
        s = self.blocks.index(block)
        m = (self.nodes[:, 0] == s) & (self.nodes[:, 1] == depth) & (self.nodes[:, 2] == index)
        return int(self.flags[m][0]) if m.any() else None


def flag_names(flags: int) -> set[str]:
    """The triangle names set in a 12-bit flag word."""
    return {t for i, t in enumerate(TRIANGLES) if flags >> i & 1}


@dataclass
class _Level:
    slot: np.ndarray
    idx: np.ndarray
    row: np.ndarray
    col: np.ndarray
    inside: np.ndarray
    ppos: np.ndarray
    quad: np.ndarray
    leaf: np.ndarray | None = None
    pruned: np.ndarray | None = None
    state: np.ndarray | None = None  # 1 drawn by itself / its subtree, 2 collapsed


def _gather(arrays: list[np.ndarray], slot: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """``arrays[slot[i]].ravel()[flat[i]]`` for ``slot`` sorted ascending."""
    out = np.empty(len(slot), dtype=np.float64)
    if not len(slot):
        return out
    cut = np.flatnonzero(np.diff(slot)) + 1
    for a, b in zip(np.r_[0, cut], np.r_[cut, len(slot)], strict=True):
        out[a:b] = arrays[int(slot[a])].ravel()[flat[a:b]]
    return out


def t_junctions(
    tri: np.ndarray, vcol: np.ndarray, vrow: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drawn vertices ``(vcol, vrow)`` lying strictly inside an axis-aligned edge of a triangle
    ``tri`` ``(m, 3, 2)``: ``(vertex ids, edge ends (a, 2, 2) as (col, row), fraction along)``."""
    p = np.concatenate([tri[:, 0], tri[:, 1], tri[:, 2]])
    q = np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]])
    o = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]])
    big = int(max(vcol.max(initial=0), vrow.max(initial=0))) + 2
    found = np.full(len(vcol), -1, dtype=np.int64)
    ends = np.zeros((len(vcol), 2, 2), dtype=np.int64)
    frac = np.zeros(len(vcol))
    for axis in (1, 0):  # 1: horizontal edges (same row), 0: vertical (same col)
        other = 1 - axis
        line_v = vrow if axis == 1 else vcol
        pos_v = vcol if axis == 1 else vrow
        on = (p[:, axis] == q[:, axis]) & (np.abs(p[:, other] - q[:, other]) >= 2)
        side = np.sign(o[:, axis] - p[:, axis])
        for sd in (-1, 1):
            m = on & (side == sd)
            line = p[m, axis]
            lo = np.minimum(p[m, other], q[m, other])
            hi = np.maximum(p[m, other], q[m, other])
            key = line * big + lo
            order = np.argsort(key, kind="stable")
            key, line, lo, hi = key[order], line[order], lo[order], hi[order]
            i = np.searchsorted(key, line_v * big + pos_v, side="left") - 1
            ok = i >= 0
            i = np.clip(i, 0, None)
            if len(key):
                ok &= (line[i] == line_v) & (hi[i] > pos_v) & (found < 0)
            else:
                ok[:] = False
            w = np.flatnonzero(ok)
            found[w] = 1
            e0 = np.empty((len(w), 2), dtype=np.int64)
            e1 = np.empty((len(w), 2), dtype=np.int64)
            e0[:, axis], e1[:, axis] = line_v[w], line_v[w]
            e0[:, other], e1[:, other] = lo[i[w]], hi[i[w]]
            ends[w, 0], ends[w, 1] = e0, e1
            frac[w] = (pos_v[w] - lo[i[w]]) / (hi[i[w]] - lo[i[w]])
    ids = np.flatnonzero(found >= 0)
    return ids, ends[ids], frac[ids]


def conform(
    tri: np.ndarray, slot: np.ndarray, level: np.ndarray, vcol: np.ndarray, vrow: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split triangles at drawn vertices ``(vcol, vrow)`` strictly inside their edges (middle
    first) until none is left: the same surface, every edge shared whole."""
    if not len(tri):
        return tri, slot, level
    big = int(max(vcol.max(initial=0), vrow.max(initial=0))) + 2
    along = {1: np.sort(vrow * big + vcol), 0: np.sort(vcol * big + vrow)}
    done_t, done_s, done_l = [], [], []
    for _ in range(64):
        if not len(tri):
            break
        pick = np.full(len(tri), -1, dtype=np.int64)
        point = np.zeros((len(tri), 2), dtype=np.int64)
        for j in range(3):
            a, b = tri[:, j], tri[:, (j + 1) % 3]
            for axis in (1, 0):
                other = 1 - axis
                on = (a[:, axis] == b[:, axis]) & (np.abs(a[:, other] - b[:, other]) >= 2)
                on &= pick < 0
                w = np.flatnonzero(on)
                if not len(w):
                    continue
                line = a[w, axis]
                lo = np.minimum(a[w, other], b[w, other])
                hi = np.maximum(a[w, other], b[w, other])
                keys = along[axis]
                i0 = np.searchsorted(keys, line * big + lo + 1)
                i1 = np.searchsorted(keys, line * big + hi)
                hit = i1 > i0
                w, mid = w[hit], keys[(i0[hit] + i1[hit]) // 2]
                pick[w] = j
                point[w, axis] = mid // big
                point[w, other] = mid % big
        keep = pick < 0
        done_t.append(tri[keep])
        done_s.append(slot[keep])
        done_l.append(level[keep])
        w = np.flatnonzero(~keep)
        if not len(w):
            tri = tri[:0]
            break
        j = pick[w]
        v0 = tri[w, j]
        v1 = tri[w, (j + 1) % 3]
        v2 = tri[w, (j + 2) % 3]
        p = point[w]
        tri = np.concatenate([np.stack([v0, p, v2], 1), np.stack([p, v1, v2], 1)])
        slot = np.concatenate([slot[w], slot[w]])
        level = np.concatenate([level[w], level[w]])
    if len(tri):
        raise RuntimeError("conforming split did not converge")
    return np.concatenate(done_t), np.concatenate(done_s), np.concatenate(done_l)


class JungHan(Strategy):
    """Jung & Han: CPU bottom-up simplification of 3×3-vertex blocks, height-adjusted cracks."""

    name = "jung-han"
    uses_metric = False

    def __init__(
        self, renderer: TerrainRenderer, prune: bool = True, culled_collapse: bool = True
    ) -> None:
        super().__init__(renderer)
        self.prune = prune
        self.culled_collapse = culled_collapse
        ctx = renderer.ctx
        self.prog = ctx.program(vertex_shader=VS, fragment_shader=shaders.FRAGMENT)
        self.wire = ctx.program(
            vertex_shader=VS,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        )
        self.heights = GlobalHeights(renderer.store)
        self._trees: dict[Block, BlockTree] = {}
        check_gl(ctx, "creating the jung-han programs")

    # -- per-block data ----------------------------------------------------------------------

    def tree(self, block: Block, level: int) -> BlockTree:
        """The block's quadtree data at resident level ``level`` (cached; rebuilt on change)."""
        t = self._trees.get(block)
        if t is None or t.level != level:
            h = self.r.store.read_block(block, level).astype(np.float32)
            mask = self.r.mask(block)
            if mask is not None:
                s = 1 << (self.r.k - level)
                h[~mask[::s, ::s]] = np.nan
            t = self._trees[block] = BlockTree.build(h)
        return t

    def _resident(self, resident: dict[Block, int] | None) -> list[tuple[Block, int]]:
        pool = self.r.pool
        for b in [b for b in self._trees if b not in pool.slots]:
            del self._trees[b]  # released from the GPU
        return self.r.drawable(resident)

    # -- selection ---------------------------------------------------------------------------

    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
    ) -> tuple[JHSelection, float]:
        """Cull, simplify bottom-up at ``tau`` (``metric`` is ignored: δ_s is the paper's),
        remove cracks and build the mesh; returns it and the CPU ms."""
        t0 = time.perf_counter()
        r, g, k = self.r, self.r.grid, self.r.k
        tau = check_tau(tau)
        poly = frustum_hull(camera, r.terrain_zrange)
        pairs = self._resident(resident)
        blocks = [b for b, _ in pairs]
        lev = np.array([lv for _, lv in pairs], dtype=np.int64)
        trees = [self.tree(b, lv) for b, lv in pairs]
        blk = np.array(blocks, dtype=np.int64).reshape(-1, 2)
        r0, c0 = blk[:, 0] * g.step, blk[:, 1] * g.step
        box = self._box(r0, c0, 1 << k)
        meets = polygon_meets_rects(poly, *box)
        inside = corners_inside(poly, *box)
        parts = self._traverse(camera, tau, poly, trees, lev, r0, c0, meets, inside)
        tris, tslot, tlev, nodes, flags, clamped = parts
        corner = np.flatnonzero(meets & (lev == 0))
        if len(corner):
            s = 1 << k
            quad = np.array([[(0, 0), (s, 0), (s, s)], [(0, 0), (s, s), (0, s)]], dtype=np.int64)
            org = np.stack([c0[corner], r0[corner]], -1)[:, None, None, :]
            tris.append((org + quad[None]).reshape(-1, 3, 2))
            tslot.append(np.repeat(corner, 2))
            tlev.append(np.zeros(2 * len(corner), dtype=np.int64))
            clamped += int(k > 0) * len(corner)
        sel = self._assemble(blocks, lev, trees, r0, c0, tris, tslot, tlev, nodes, flags)
        sel.corner_blocks = len(corner)
        sel.clamped = clamped
        sel.evaluated = self._evaluated
        return sel, (time.perf_counter() - t0) * 1000.0

    def _box(self, r0, c0, size):
        """World ``(xmin, ymin, xmax, ymax)`` of squares of ``size`` samples at global origins."""
        g = self.r.grid
        xmin = g.x0 + np.asarray(c0, dtype=np.float64) * g.dx
        ymax = g.y0 - np.asarray(r0, dtype=np.float64) * g.dy
        return xmin, ymax - size * g.dy, xmin + size * g.dx, ymax

    def _own(self, camera, trees, lev, r0, c0, nodes: _Level, sel: np.ndarray, d: int):
        """``(n, 5)`` δ_s of the C, T, B, L, R vertices of the selected blocks of a depth."""
        k, g = self.r.k, self.r.grid
        size = 1 << (k - d)
        half = size >> 1
        slot = np.repeat(nodes.slot[sel], 5)
        lr = (np.repeat(nodes.row[sel] * size, 5) + np.tile(OWN[:, 1], len(sel)) * half).ravel()
        lc = (np.repeat(nodes.col[sel] * size, 5) + np.tile(OWN[:, 0], len(sel)) * half).ravel()
        sh = k - lev[slot]
        flat = (lr >> sh) * ((1 << lev[slot]) + 1) + (lc >> sh)
        h = _gather([t.heights for t in trees], slot, flat)
        dl = _gather([t.delta for t in trees], slot, flat)
        x, y = g.sample_xy(r0[slot] + lr, c0[slot] + lc)
        return vertex_errors(dl, np.stack([x, y, h], -1), camera).reshape(-1, 5)

    def _traverse(self, camera, tau, poly, trees, lev, r0, c0, meets, inside):
        k = self.r.k
        roots = np.flatnonzero(meets & (lev >= 1))
        z = np.zeros(len(roots), dtype=np.int64)
        cur = _Level(roots, z, z, z, inside[roots], z - 1, z - 1)
        levels: list[_Level] = []
        d = 0
        while len(cur.slot):
            size = 1 << (k - d)
            cur.leaf = lev[cur.slot] - 1 == d
            cur.pruned = np.zeros(len(cur.slot), dtype=bool)
            if self.prune and d >= 1:
                cand = np.flatnonzero(cur.inside | self.culled_collapse)
                if len(cand):
                    s, i = cur.slot[cand], cur.idx[cand]
                    xmin, ymin, xmax, ymax = self._box(
                        r0[s] + cur.row[cand] * size, c0[s] + cur.col[cand] * size, size
                    )
                    b = projected_bound(
                        camera,
                        _gather([t.dmax[d] if d < t.level else None for t in trees], s, i),
                        xmin,
                        xmax,
                        ymin,
                        ymax,
                        _gather([t.zlo[d] if d < t.level else None for t in trees], s, i),
                        _gather([t.zhi[d] if d < t.level else None for t in trees], s, i),
                    )
                    cur.pruned[cand] = b < tau
            levels.append(cur)
            exp = np.flatnonzero(~cur.pruned & ~cur.leaf)
            if not len(exp):
                break
            par = np.repeat(exp, 4)
            q = np.tile(np.arange(4, dtype=np.int64), len(exp))
            slot = cur.slot[par]
            row = 2 * cur.row[par] + 1 - (q >> 1)
            col = 2 * cur.col[par] + (q & 1)
            half = size >> 1
            ins = cur.inside[par].copy()
            hit = ins.copy()
            test = np.flatnonzero(~ins)
            if len(test):
                bx = self._box(
                    r0[slot[test]] + row[test] * half, c0[slot[test]] + col[test] * half, half
                )
                hit[test] = polygon_meets_rects(poly, *bx)
                ins[test] = hit[test] & corners_inside(poly, *bx)
            keep = np.flatnonzero(hit)
            cur = _Level(
                slot[keep],
                4 * cur.idx[par[keep]] + q[keep],
                row[keep],
                col[keep],
                ins[keep],
                par[keep],
                q[keep],
            )
            d += 1
        tris, tslot, tlev, nodes, flags = [], [], [], [], []
        clamped = 0
        self._evaluated = 0
        below = None
        for d in range(len(levels) - 1, -1, -1):
            cur = levels[d]
            m = len(cur.slot)
            size = 1 << (k - d)
            cm = np.zeros((m, 4), dtype=np.int8)  # 0: culled (or none: a leaf)
            if below is not None:
                cm[below.ppos, below.quad] = below.state
            culled = ~cur.leaf[:, None] & (cm == 0)
            present = cur.leaf[:, None] | (cm == 2) | (culled & self.culled_collapse)
            act = np.flatnonzero(~cur.pruned)
            ds = np.full((m, 5), np.inf)
            self._evaluated += len(act)
            if len(act):
                ds[act] = self._own(camera, trees, lev, r0, c0, cur, act, d)
            removed = (
                present[:, EDGE_QUADS[:, 0]] & present[:, EDGE_QUADS[:, 1]] & (ds[:, 1:] < tau)
            )
            coll = (d >= 1) & removed.all(axis=1) & (ds[:, 0] < tau)
            cur.state = np.where(cur.pruned | coll, 2, 1).astype(np.int8)
            below = cur
            drawn = np.flatnonzero(cur.state == 1)
            fl = np.concatenate(
                [
                    present[drawn][:, FAN_QUAD]
                    & ~removed[drawn][:, FAN_EDGE]
                    & ~culled[drawn][:, FAN_QUAD],  # (culled_collapse: off screen, not drawn)
                    removed[drawn],
                ],
                1,
            )
            bits = fl.astype(np.int64) @ _BITS
            has = bits != 0
            drawn, fl, bits = drawn[has], fl[has], bits[has]
            nodes.append(np.stack([cur.slot[drawn], np.full(len(drawn), d), cur.idx[drawn]], -1))
            flags.append(bits)
            clamped += int((cur.leaf[drawn] & (lev[cur.slot[drawn]] < k)).sum())
            j, t = np.nonzero(fl)
            j = drawn[j]
            org = np.stack(
                [c0[cur.slot[j]] + cur.col[j] * size, r0[cur.slot[j]] + cur.row[j] * size], -1
            )
            tris.append(org[:, None, :] + TEMPLATE[t] * (size >> 1))
            tslot.append(cur.slot[j])
            tlev.append(np.full(len(j), d + 1, dtype=np.int64))
        return tris, tslot, tlev, nodes, flags, clamped

    def _assemble(self, blocks, lev, trees, r0, c0, tris, tslot, tlev, nodes, flags):
        """Drawn heights, the crack pass, and the GPU vertex/index arrays."""
        k, g = self.r.k, self.r.grid
        e2 = np.zeros((0, 3, 2), dtype=np.int64)
        tri = np.concatenate(tris) if tris else e2
        slot = np.concatenate(tslot).astype(np.int64) if tslot else np.zeros(0, np.int64)
        tl = np.concatenate(tlev).astype(np.int64) if tlev else np.zeros(0, np.int64)
        order = np.argsort(slot, kind="stable")
        tri, slot, tl = tri[order], slot[order], tl[order]
        node_arr = np.concatenate(nodes) if nodes else np.zeros((0, 3), np.int64)
        flag_arr = np.concatenate(flags) if flags else np.zeros(0, np.int64)
        wg = g.cols * g.step + 1
        cs, rs = tri[..., 0].ravel(), tri[..., 1].ravel()
        key = rs * wg + cs
        uk, first, inv = np.unique(key, return_index=True, return_inverse=True)
        inv = inv.ravel()
        s3 = np.repeat(slot, 3)
        sh = k - lev[s3]
        flat = ((rs - r0[s3]) >> sh) * ((1 << lev[s3]) + 1) + ((cs - c0[s3]) >> sh)
        h_corner = _gather([t.heights for t in trees], s3, flat)
        hv = h_corner[first]
        vrow, vcol = uk // wg, uk % wg
        ids, ends, frac = t_junctions(tri, vcol, vrow)
        if len(ids):
            step = g.step
            tz = np.minimum(
                trailing_zeros(vcol[ids] % step, k), trailing_zeros(vrow[ids] % step, k)
            )
            vlev = k - tz
            ia = np.searchsorted(uk, ends[:, 0, 1] * wg + ends[:, 0, 0])
            ib = np.searchsorted(uk, ends[:, 1, 1] * wg + ends[:, 1, 0])
            for lv in np.unique(vlev):
                w = vlev == lv
                ha, hb = hv[ia[w]], hv[ib[w]]
                new = ha + frac[w] * (hb - ha)
                old = hv[ids[w]]
                hv[ids[w]] = np.where(np.isfinite(new) & np.isfinite(old), new, old)
        adjusted = np.stack([vcol[ids], vrow[ids]], -1)
        jh_count = len(tri)
        tri, slot, tl = conform(tri, slot, tl, vcol, vrow)
        tkey = tri[..., 1] * wg + tri[..., 0]
        inv = np.searchsorted(uk, tkey.ravel())
        tri_h = hv[inv].reshape(-1, 3)
        s3 = np.repeat(slot, 3)
        # GPU vertices: one per (slot, drawn level, sample)
        nv = len(uk)
        gk = (s3 * 16 + np.repeat(tl, 3)) * max(nv, 1) + inv
        guk, gfirst, ginv = np.unique(gk, return_index=True, return_inverse=True)
        vid = inv[gfirst]
        return JHSelection(
            blocks=blocks,
            levels=lev,
            tri=tri,
            tri_h=tri_h,
            jh_triangles=jh_count,
            tri_slot=slot,
            tri_level=tl,
            nodes=node_arr,
            flags=flag_arr,
            adjusted=adjusted,
            corner_blocks=0,
            clamped=0,
            v_slot=s3[gfirst],
            v_level=np.repeat(tl, 3)[gfirst],
            v_cr=np.stack([vcol[vid], vrow[vid]], -1),
            v_h=np.nan_to_num(hv[vid], nan=0.0).astype(np.float32),
            index=ginv.reshape(-1, 3).astype(np.int64),
        )

    # -- drawing -----------------------------------------------------------------------------

    def _batches(self, sel: JHSelection):
        """Per GPU page: ``(page, vertex bytes, index bytes, index count)``."""
        r = self.r
        step = r.grid.step
        if not len(sel):
            return
        slots = [r.pool.slots[b] for b in sel.blocks]
        page = np.array([s.page for s in slots], dtype=np.int64)
        base = np.array([s.offset for s in slots], dtype=np.int64)
        blk = np.array(sel.blocks, dtype=np.int64).reshape(-1, 2)
        vs = sel.v_slot
        org_c, org_r = blk[vs, 1] * step, blk[vs, 0] * step
        attr = np.zeros((len(vs), 9), dtype=np.int32)
        attr[:, 0], attr[:, 1] = org_c, org_r
        attr[:, 2], attr[:, 3] = sel.v_cr[:, 0] - org_c, sel.v_cr[:, 1] - org_r
        attr[:, 4], attr[:, 5] = base[vs], sel.v_level
        attr[:, 8] = sel.v_h.view(np.int32)
        tpage = page[sel.tri_slot]
        for p in np.unique(tpage).tolist():
            vm = page[vs] == p
            remap = np.cumsum(vm) - 1
            idx = remap[sel.index[tpage == p]].astype(np.int32)
            yield p, np.ascontiguousarray(attr[vm]).tobytes(), idx.tobytes(), idx.size

    def draw(
        self,
        camera: Camera,
        sel: JHSelection,
        *,
        wireframe: bool = False,
        lod_colour: bool = False,
        clear: tuple[int, int, int] | None = None,
        selection_ms: float = 0.0,
    ) -> RenderStats:
        """Draw the selection's triangles, one indexed draw per ``HeightPool`` page."""
        r = self.r
        ctx = r.ctx
        prog = self.wire if wireframe else self.prog

        def body() -> None:
            for page, vb, ib, n in self._batches(sel):
                r.pool.pages[page].buffer.bind_to_storage_buffer(0)
                vbo, ibo = ctx.buffer(vb), ctx.buffer(ib)
                vao = ctx.vertex_array(
                    prog,
                    [(vbo, "4i 4i f", "in_a", "in_b", "in_h")],
                    index_buffer=ibo,
                    index_element_size=4,
                )
                vao.render(moderngl.TRIANGLES, vertices=n)
                for o in (vao, vbo, ibo):
                    o.release()

        frame_ms = self.timed_frame(
            camera, prog, body, clear=clear, lod_colour=lod_colour or wireframe,
            what="drawing jung-han blocks",
        )  # fmt: skip
        lv = np.concatenate([sel.nodes[:, 1] + 1, np.zeros(sel.corner_blocks, np.int64)])
        return RenderStats(
            triangles=len(sel),
            patches=len(sel.nodes) + sel.corner_blocks,
            selection_ms=selection_ms,
            frame_ms=frame_ms,
            gpu_bytes=r.pool.used_bytes,
            clamped=sel.clamped,
            violations=0,
            max_level=int(lv.max()) if len(lv) else -1,
            min_level=int(lv.min()) if len(lv) else -1,
        )

    # -- measuring ---------------------------------------------------------------------------

    def triangles(self, camera: Camera, sel: JHSelection) -> tuple[np.ndarray, np.ndarray]:
        """The drawn triangles: global ``(col, row)`` corners ``(m, 3, 2)``, drawn heights."""
        return sel.tri, sel.tri_h

    def screen_errors(self, camera: Camera, sel: JHSelection) -> np.ndarray:
        """Measured pixel errors of the drawn (height-adjusted) triangles."""
        return triangle_screen_errors(self.r.grid, camera, sel.tri, sel.tri_h, self.heights)

    def drawn_blocks(self, sel: JHSelection) -> set[Block]:
        """Store blocks with at least one drawn triangle."""
        return {sel.blocks[int(s)] for s in np.unique(sel.tri_slot)}

    def surface(
        self, camera: Camera, sel: JHSelection
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The drawn surface rasterised on the sample lattice (hidden triangles left out)."""
        ok = np.isfinite(sel.tri_h).all(axis=1)
        return measure.rasterise(sel.tri[ok], sel.tri_h[ok])
