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
  ``HeightPool`` with ``shaders.FETCH_COMMON``'s ``vertex_at`` (the paper's displacement
  textures), at integer samples: a vertex shared by two patches has the same global sample and
  height on both sides, bit for bit.
* **ε = ρ·l/d per edge** (the paper's Equation 1). ``l`` is the edge length (world units), ``d``
  the distance from the eye to the edge segment (the segment lifted to the z range of the blocks
  on both sides). The paper's ρ is a global precision factor; we make it carry τ and the stored
  roughness so that ε is a screen-space quantity: ``ρ = 2 f δ / (τ 2**c l)`` where ``f`` is the
  focal length in pixels (viewport height, :attr:`Camera.focal_px`) and ``δ`` the larger of the
  stored ``bound`` errors of the two depth-``d`` nodes beside the edge drawn at level ``d + 1``
  (the coarsest tiles; ``PatchTable(k, 1)``). So ``ε 2**c / 2`` is the pixel error of the
  edge's coarsest tile over τ, and with error proportional to cell size (the paper's linear
  rule) ``ε 2**c`` cells meet τ. Split the patch if any edge has ``ε > 1`` (the finest tile would
  not meet τ); otherwise edge resolution = ``ε 2**c`` rounded up to a power of two (the paper's
  "ε R_max rounded up"), at least 2. δ and d depend on the edge's global position only, so both
  patches of an edge compute the same ε without querying each other. τ = 0 gives ε = ∞ wherever
  δ > 0 (full resolution); δ = 0 gives ε = 0 (a flat node is exact at any resolution).
  ``--metric`` does not apply (``uses_metric = False``). A leaf at the bottom depth (or held by
  its resident level) may keep ``ε > 1``; it is drawn at its finest level.
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
* **Triangles** = Σ mesh triangles × instances (``RenderStats.triangles``), checked against a
  read-back: the probe program's geometry shader appends every drawn triangle (global integer
  samples and fetched heights) to a storage buffer under ``RASTERIZER_DISCARD``; the measured
  error rasterises those on the sample lattice (:func:`triangle_screen_errors`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import cache

import moderngl
import numpy as np
from numpy.typing import ArrayLike

from render import measure, shaders
from render.errors import RenderError, SelectionError
from render.gpu import check_gl
from render.renderer import RenderStats, TerrainRenderer
from render.select import PatchTable, _Cull, check_tau
from render.strategies.base import Block, GlobalHeights, Strategy, triangle_screen_errors
from streamer.camera import Camera
from streamer.frustum import frustum_hull

#: edge order N, E, S, W; neighbour offsets (row, col) across each edge
DIRS = ((-1, 0), (0, 1), (1, 0), (0, -1))

VS_HEAD = (
    shaders.FETCH_COMMON
    + """
layout(std430, binding = 4) readonly buffer Inst { ivec4 inst[]; };
uniform int inst0;
uniform int res_log2;
in ivec3 in_uvr;
Vtx seam_vertex() {
    int id = inst0 + gl_InstanceID;
    ivec4 a = inst[2 * id];
    ivec4 b = inst[2 * id + 1];
    int n = 1 << res_log2;
    int u = in_uvr.x, v = in_uvr.y;
    for (int i = 0; i < b.z; i++) { int t = u; u = n - v; v = t; }
    int sh = res_log2 - in_uvr.z;
    return vertex_at(a, ivec4(b.x, b.y - sh, 0, 0), u >> sh, v >> sh);
}
"""
)

VS = VS_HEAD + shaders.EMIT + "void main() { emit(seam_vertex()); }\n"

VS_PROBE = (
    VS_HEAD
    + """
out vec3 t_gh;
void main() {
    Vtx v = seam_vertex();
    t_gh = vec3(vec2(v.g), v.masked > 0.0 ? -1.0e30 : v.h);
    gl_Position = vec4(0.0);
}
"""
)


# -- cached meshes (pure numpy) -------------------------------------------------------------


@cache
def tile_mesh(c: int, r: int) -> np.ndarray:
    """``(n**2/2 - n, 3, 3)`` int32 ``(u, v, r)`` triangles of the north tile of ``n = 2**r``
    cells in a patch of ``2**c`` units (whole cells only; the diagonal half cells are strips')."""
    size, n = 1 << c, 1 << r
    q = size // n
    out = []
    for j in range(n // 2):
        for i in range(j + 1, n - j - 1):
            a, b = (i * q, j * q, r), ((i + 1) * q, j * q, r)
            cc, d = (i * q, (j + 1) * q, r), ((i + 1) * q, (j + 1) * q, r)
            out += [(a, b, d), (a, d, cc)]
    return np.array(out, dtype=np.int32).reshape(-1, 3, 3)


@cache
def strip_mesh(c: int, ra: int, rb: int) -> np.ndarray:
    """``(max(na, nb), 3, 3)`` int32 ``(u, v, r)`` triangles of the strip on the north-east half
    diagonal between the north tile (``na = 2**ra`` cells) and the east tile (``2**rb``)."""
    size = 1 << c

    def diag(t: int, r: int) -> tuple[int, int, int]:
        return (size - t, t, r)

    def north_half(j: int, q: int, r: int):  # off-diagonal corner, diagonal ends
        return ((size - (j + 1) * q, j * q, r), diag(j * q, r), diag((j + 1) * q, r))

    def east_half(j: int, q: int, r: int):
        return ((size - j * q, (j + 1) * q, r), diag(j * q, r), diag((j + 1) * q, r))

    fine_r, coarse_r = max(ra, rb), min(ra, rb)
    qf, qc = size >> fine_r, size >> coarse_r
    fine_half, coarse_half = (north_half, east_half) if ra >= rb else (east_half, north_half)
    out = []
    for j in range(1 << (fine_r - 1)):
        off, d0, d1 = fine_half(j, qf, fine_r)
        out.append((off, d0, d1))
    for j in range(1 << (coarse_r - 1)):
        off, _, _ = coarse_half(j, qc, coarse_r)
        for t in range(j * qc, (j + 1) * qc, qf):
            out.append((off, diag(t, fine_r), diag(t + qf, fine_r)))
    return np.array(out, dtype=np.int32).reshape(-1, 3, 3)


def tile_triangles(r: int) -> int:
    """Triangles of a tile of ``2**r`` cells."""
    n = 1 << r
    return n * n // 2 - n


def strip_triangles(ra: int, rb: int) -> int:
    """Triangles of a strip between tiles of ``2**ra`` and ``2**rb`` cells."""
    return 1 << max(ra, rb)


def rotate(uv: np.ndarray, turns: np.ndarray | int, c: int) -> np.ndarray:
    """``(u, v)`` turned clockwise about the patch centre ``turns`` quarter turns (the vertex
    shader's ``(u, v) -> (C - v, u)``; north goes to east)."""
    size = 1 << c
    t = np.asarray(turns)
    shape = np.broadcast_shapes(uv.shape[:-1], t.shape)
    u, v = np.broadcast_to(uv[..., 0], shape), np.broadcast_to(uv[..., 1], shape)
    t = np.broadcast_to(t, shape)
    for i in range(1, 4):
        m = t >= i
        u, v = np.where(m, size - v, u), np.where(m, u, v)
    return np.stack([u, v], -1)


def mesh_kinds(c: int) -> list[tuple[str, int, int]]:
    """The cached meshes in buffer order: ``("tile", r, 0)`` then ``("strip", ra, rb)``."""
    tiles = [("tile", r, 0) for r in range(1, c + 1)]
    strips = [("strip", a, b) for a in range(1, c + 1) for b in range(1, c + 1)]
    return tiles + strips


def mesh_of(c: int, kind: tuple[str, int, int]) -> np.ndarray:
    """The ``(m, 3, 3)`` canonical triangles of one cached mesh."""
    return tile_mesh(c, kind[1]) if kind[0] == "tile" else strip_mesh(c, kind[1], kind[2])


# -- ε = ρ l / d ----------------------------------------------------------------------------


def precision(
    delta: ArrayLike, length: ArrayLike, tau: float, focal_px: float, res_log2: int
) -> np.ndarray:
    """The edge's precision factor ``ρ = 2 f δ / (τ 2**c l)`` (∞ at τ = 0 unless δ = 0)."""
    delta = np.asarray(delta, dtype=np.float64)
    num = 2.0 * focal_px * delta
    den = float(tau) * float(1 << res_log2) * np.asarray(length, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(num == 0.0, 0.0, num / den)
    return np.where(np.isnan(rho), np.inf, rho)


def edge_epsilon(rho: ArrayLike, length: ArrayLike, dist: ArrayLike) -> np.ndarray:
    """The paper's ``ε = ρ l / d`` (0 when ρ = 0, ∞ when d = 0 < ρ)."""
    rho = np.asarray(rho, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        eps = rho * np.asarray(length, dtype=np.float64) / np.asarray(dist, dtype=np.float64)
    return np.where(rho == 0.0, 0.0, np.where(np.isnan(eps), np.inf, eps))


def edge_resolution(eps: ArrayLike, res_log2: int) -> np.ndarray:
    """log2 of the edge's cells: ``ε 2**c`` rounded up to a power of two, clipped to 1..c."""
    x = np.asarray(eps, dtype=np.float64) * float(1 << res_log2)
    x = np.where(np.isfinite(x), x, float(1 << res_log2))
    m, e = np.frexp(np.maximum(x, 1.0))
    up = np.where(m == 0.5, e - 1, e)
    return np.clip(up, 1, res_log2).astype(np.int64)


# -- selection ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PatchLayout:
    """Leaf patches of one frame and their edge levels (N, E, S, W)."""

    blocks: np.ndarray  # (m, 2) block ids
    block: np.ndarray  # (n,) index into blocks
    depth: np.ndarray
    row: np.ndarray  # node row/col inside the block at its depth
    col: np.ndarray
    edge_level: np.ndarray  # (n, 4) store level of each edge's tile
    eps: np.ndarray  # (n, 4) ε of each edge
    res_log2: int
    clamped: int
    violations: int

    def __len__(self) -> int:
        return len(self.depth)

    @property
    def edge_res(self) -> np.ndarray:
        """``(n, 4)`` log2 cells of each tile."""
        return self.edge_level - self.depth[:, None]


class _Frame:
    """One selection's fixed inputs: blocks, caps, error grids, z ranges, camera, τ."""

    def __init__(
        self, st: SeamlessPatches, camera: Camera, tau: float, resident: dict | None
    ) -> None:
        r = st.r
        self.k, self.c, self.grid = r.k, st.c, r.grid
        self.camera, self.tau = camera, float(tau)
        pairs = r.drawable(resident)
        self.skipped = sum(1 for _, lv in pairs if lv < 1)
        pairs = [(b, lv) for b, lv in pairs if lv >= 1]
        self.blk = np.array([b for b, _ in pairs], dtype=np.int64).reshape(-1, 2)
        self.cap = np.array([lv for _, lv in pairs], dtype=np.int64)
        capd = dict(pairs)
        capn = [min([lv] + [capd[n] for n in _block_nbrs(b) if n in capd]) for b, lv in pairs]
        self.dmax = np.minimum(self.k - self.c, np.array(capn, dtype=np.int64) - 1)
        g = self.grid
        self.zr = st.zr
        self.win = r.store.index.window
        self.table = st.table
        for b in map(tuple, self.blk.tolist()):
            if b not in self.table:
                self.table.add(b, r.store.read_errors(b)["bound"])
        self.slots = self.table.slots(self.blk) if len(self.blk) else np.zeros(0, np.int64)
        keys = self.blk[:, 0] * g.cols + self.blk[:, 1]
        self.border = np.argsort(keys)
        self.bkeys = keys[self.border]
        self.focal = camera.focal_px
        self.eye = camera.eye
        poly = frustum_hull(camera, r.terrain_zrange)
        self.cull = _Cull(poly) if poly is not None and len(poly) else None
        self.diag = math.hypot(g.dx, g.dy)

    def node_delta(self, d: int, gr: np.ndarray, gc: np.ndarray) -> np.ndarray:
        """Stored error (``bound``, level ``d + 1``) of the depth-``d`` nodes at global node
        ``(gr, gc)``; -1 outside the drawn blocks."""
        g, m = self.grid, len(self.blk)
        out = np.full(len(gr), -1.0)
        ok = (gr >= 0) & (gc >= 0) & (gr < g.rows << d) & (gc < g.cols << d)
        if not m or not ok.any():
            return out
        key = (gr[ok] >> d) * g.cols + (gc[ok] >> d)
        pos = np.minimum(np.searchsorted(self.bkeys, key), m - 1)
        hit = self.bkeys[pos] == key
        mask = (1 << d) - 1
        sub = np.flatnonzero(ok)[hit]
        slots = self.slots[self.border[pos[hit]]]
        out[sub] = self.table.delta(slots, d, gr[sub] & mask, gc[sub] & mask)
        return out

    def epsilon(self, idx: np.ndarray, d: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``(n, 4)`` ε of the nodes' edges N, E, S, W."""
        g, k = self.grid, self.k
        size = 1 << (k - d)
        br, bc = self.blk[idx, 0], self.blk[idx, 1]
        gr, gc = (br << d) + rows, (bc << d) + cols
        nr_, nc_ = g.rows << d, g.cols << d
        own = self.node_delta(d, gr, gc)
        ex, ey, ez = self.eye
        out = np.zeros((len(idx), 4))
        corners = (
            (gr, gc, gr, gc + 1),
            (gr, gc + 1, gr + 1, gc + 1),
            (gr + 1, gc, gr + 1, gc + 1),
            (gr, gc, gr + 1, gc),
        )
        for e, (dr, dc) in enumerate(DIRS):
            nr, nc = gr + dr, gc + dc
            inb = (nr >= 0) & (nr < nr_) & (nc >= 0) & (nc < nc_)
            nrc, ncc = np.clip(nr, 0, nr_ - 1), np.clip(nc, 0, nc_ - 1)
            delta = np.maximum(own, self.node_delta(d, nr, nc))
            zo, zn = self.zr[br, bc], self.zr[nrc >> d, ncc >> d]
            zlo = np.where(inb, np.minimum(zo[:, 0], zn[:, 0]), zo[:, 0])
            zhi = np.where(inb, np.maximum(zo[:, 1], zn[:, 1]), zo[:, 1])
            r0, c0, r1, c1 = corners[e]
            xa, ya = g.sample_xy(r0 * size, c0 * size)
            xb, yb = g.sample_xy(r1 * size, c1 * size)
            hx = np.maximum(np.maximum(np.minimum(xa, xb) - ex, 0.0), ex - np.maximum(xa, xb))
            hy = np.maximum(np.maximum(np.minimum(ya, yb) - ey, 0.0), ey - np.maximum(ya, yb))
            v = np.maximum(np.maximum(ez - zhi, zlo - ez), 0.0)
            dist = np.sqrt(hx * hx + hy * hy + v * v)
            length = np.hypot(xb - xa, yb - ya)
            rho = precision(np.maximum(delta, 0.0), length, self.tau, self.focal, self.c)
            out[:, e] = edge_epsilon(rho, length, dist)
        return out

    def visible(self, idx: np.ndarray, d: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Nodes whose bounding circle meets the ground frustum and that are not all padding."""
        g = self.grid
        size = 1 << (self.k - d)
        keep = np.ones(len(idx), dtype=bool)
        if self.win is not None and len(idx):
            w = self.win[self.blk[idx, 0], self.blk[idx, 1]]
            keep &= (rows * size < w[:, 2] - 1) & (cols * size < w[:, 3] - 1)
        if self.cull is not None and len(idx):
            bx0, _, _, by1 = g.block_bounds(self.blk[idx, 0], self.blk[idx, 1])
            cx = bx0 + (cols + 0.5) * (size * g.dx)
            cy = by1 - (rows + 0.5) * (size * g.dy)
            meets, _ = self.cull(cx, cy, 0.5 * size * self.diag)
            keep &= meets
        return keep

    def splittable(self, idx: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Nodes whose children can be drawn and be finer (resident levels, bottom depth)."""
        return (d + 1 <= self.dmax[idx]) & (d + self.c < self.cap[idx])


def _block_nbrs(b: Block) -> list[Block]:
    return [(b[0] + dr, b[1] + dc) for dr, dc in DIRS]


class _Leaves:
    """The growing leaf list (per traversal pass) and the clamped count."""

    def __init__(self) -> None:
        self.parts: list[tuple] = []
        self.clamped = 0


def _traverse(fr: _Frame, seeds: dict[int, tuple], out: _Leaves) -> None:
    """Top-down from ``seeds`` (depth -> (idx, rows, cols)): split while some edge has ε > 1."""
    k, c = fr.k, fr.c
    carry = None
    for d in range(0, k - c + 1):
        parts = [p for p in (carry, seeds.get(d)) if p is not None and len(p[0])]
        carry = None
        if not parts:
            continue
        idx, rows, cols = (np.concatenate([p[i] for p in parts]) for i in range(3))
        keep = fr.visible(idx, d, rows, cols)
        idx, rows, cols = idx[keep], rows[keep], cols[keep]
        if not len(idx):
            continue
        eps = fr.epsilon(idx, d, rows, cols)
        want = (eps > 1.0).any(axis=1)
        can = fr.splittable(idx, np.full(len(idx), d))
        split = want & can
        out.clamped += int(np.count_nonzero(want & ~can & (d < k - c)))
        leaf = ~split
        out.parts.append(
            (idx[leaf], np.full(int(leaf.sum()), d), rows[leaf], cols[leaf], eps[leaf])
        )
        if split.any():
            si, sr, sc = idx[split], rows[split], cols[split]
            carry = _children(si, sr, sc)


def _children(idx, rows, cols):
    return (
        np.repeat(idx, 4),
        (2 * rows[:, None] + np.array([0, 0, 1, 1])).ravel(),
        (2 * cols[:, None] + np.array([0, 1, 0, 1])).ravel(),
    )


def _edge_groups(d: np.ndarray, gr: np.ndarray, gc: np.ndarray) -> np.ndarray:
    """``(n, 4)`` group id (``leaf * 4 + edge`` of the group's coarsest member) of every leaf
    edge: a maximal shared edge is one leaf's edge and the same-size or smaller leaves' edges
    across it. The leaf across each edge is found at every depth with one ``searchsorted``."""
    n = len(d)
    if n == 0:
        return np.zeros((0, 4), np.int64)
    big = int(d.max())
    nr = (int((gr >> d).max()) + 2) << big
    nc = (int((gc >> d).max()) + 2) << big
    keys = (d * nr + gr) * nc + gc
    order = np.argsort(keys)
    sk = keys[order]
    own = np.arange(4 * n).reshape(n, 4)
    out = own.copy()
    for e, (dr, dc) in enumerate(DIRS):
        r, c = gr + dr, gc + dc
        inside = (r >= 0) & (c >= 0)
        r, c = np.maximum(r, 0), np.maximum(c, 0)
        best = np.full(n, -1)
        best_d = np.full(n, -1)
        for dd in np.unique(d).tolist():
            shift = np.maximum(d - dd, 0)
            q = (dd * nr + (r >> shift)) * nc + (c >> shift)
            pos = np.minimum(np.searchsorted(sk, q), n - 1)
            hit = (sk[pos] == q) & inside & (dd <= d) & (dd > best_d)
            best = np.where(hit, order[pos], best)
            best_d = np.where(hit, dd, best_d)
        opp = (e + 2) % 4
        same = best_d == d
        coarse = (best >= 0) & ~same
        j = np.maximum(best, 0) * 4 + opp
        out[:, e] = np.where(same, np.minimum(own[:, e], j), np.where(coarse, j, own[:, e]))
    return out


def _resolve(fr: _Frame, leaves: _Leaves, max_rounds: int = 64) -> PatchLayout:
    """Group every shared edge, split coarse patches that cannot match, assign edge levels."""
    c = fr.c
    for _ in range(max_rounds):
        if leaves.parts:
            idx, d, rows, cols, eps = (
                np.concatenate([p[i] for p in leaves.parts]) for i in range(5)
            )
        else:
            idx = d = rows = cols = np.zeros(0, np.int64)
            eps = np.zeros((0, 4))
        idx, d, rows, cols = (a.astype(np.int64) for a in (idx, d, rows, cols))
        n = len(idx)
        gr = (fr.blk[idx, 0] << d) + rows
        gc = (fr.blk[idx, 1] << d) + cols
        hi = np.minimum(d + c, fr.cap[idx])
        lo = d + 1
        want = np.minimum(d[:, None] + edge_resolution(eps, c), hi[:, None])
        can = fr.splittable(idx, d)
        gid = _edge_groups(d, gr, gc)
        g = gid.ravel()
        lo_e, hi_e = np.repeat(lo, 4), np.repeat(hi, 4)
        lo_g = np.full(4 * n, -(1 << 30))
        hi_g = np.full(4 * n, 1 << 30)
        want_g = np.full(4 * n, -(1 << 30))
        deep_g = np.full(4 * n, -1)
        size_g = np.zeros(4 * n, np.int64)
        np.maximum.at(lo_g, g, lo_e)
        np.minimum.at(hi_g, g, hi_e)
        np.maximum.at(want_g, g, want.ravel())
        np.maximum.at(deep_g, g, np.repeat(d, 4))
        np.add.at(size_g, g, 1)
        shared = size_g > 1
        j = np.arange(4 * n) // 4  # the group's coarsest leaf
        stuck = shared & ((lo_g > hi_g) | (want_g > hi_g))
        split = stuck & (hi[j] == hi_g) & can[j] & (deep_g > d[j])
        if not split.any():
            bad = lo_g[g] > hi_g[g]
            level = np.where(
                bad,
                np.clip(want_g[g], lo_e, hi_e),
                np.clip(want_g[g], lo_g[g], hi_g[g]),
            ).reshape(n, 4)
            return PatchLayout(
                blocks=fr.blk,
                block=idx,
                depth=d,
                row=rows,
                col=cols,
                edge_level=level.astype(np.int64),
                eps=eps,
                res_log2=c,
                clamped=leaves.clamped + fr.skipped,
                violations=int(np.count_nonzero(shared & (lo_g > hi_g))),
            )
        v = np.unique(j[split])
        keep = np.ones(n, dtype=bool)
        keep[v] = False
        leaves.parts = [(idx[keep], d[keep], rows[keep], cols[keep], eps[keep])]
        seeds: dict[int, tuple] = {}
        for dv in np.unique(d[v]).tolist():
            m = v[d[v] == dv]
            seeds[dv + 1] = _children(idx[m], rows[m], cols[m])
        _traverse(fr, seeds, leaves)
    raise SelectionError(f"seamless patches did not settle in {max_rounds} rounds")


# -- the strategy ---------------------------------------------------------------------------


class SeamlessPatches(Strategy):
    """Livny, Kogan & El-Sana: tiles and strips instanced from cached meshes."""

    name = "seamless-patches"
    uses_metric = False

    def __init__(self, renderer: TerrainRenderer, res_log2: int = 5) -> None:
        super().__init__(renderer)
        if not 1 <= res_log2 <= 7:
            raise RenderError(f"res_log2 must be in 1..7 (2..128 cells per tile), got {res_log2}")
        self.c = min(res_log2, renderer.k)
        ctx = renderer.ctx
        key = "bound@1"
        if key not in renderer.tables:
            renderer.tables[key] = PatchTable(renderer.k, 1)
        self.table = renderer.tables[key]
        self.kinds = mesh_kinds(self.c)
        meshes = [mesh_of(self.c, kd) for kd in self.kinds]
        self.tri_count = {kd: len(m) for kd, m in zip(self.kinds, meshes, strict=True)}
        starts = np.cumsum([0] + [len(m) for m in meshes])
        self.first = {kd: int(s) for kd, s in zip(self.kinds, starts[:-1], strict=True)}
        self.kind_id = {kd: i for i, kd in enumerate(self.kinds)}
        self.tile_id = np.zeros(self.c + 1, np.int64)
        self.strip_id = np.zeros((self.c + 1, self.c + 1), np.int64)
        for i, (kind, ra, rb) in enumerate(self.kinds):
            if kind == "tile":
                self.tile_id[ra] = i
            else:
                self.strip_id[ra, rb] = i
        verts = np.concatenate(meshes).reshape(-1, 3).astype("i4")
        self.mesh_vbo = ctx.buffer(verts.tobytes())
        self.prog = ctx.program(vertex_shader=VS, fragment_shader=shaders.FRAGMENT)
        self.wire = ctx.program(
            vertex_shader=VS,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        )
        self.probe_prog = ctx.program(
            vertex_shader=VS_PROBE, geometry_shader=shaders.TRIANGLE_PROBE
        )
        self.vaos = {
            id(p): ctx.vertex_array(p, [(self.mesh_vbo, "3i", "in_uvr")])
            for p in (self.prog, self.wire, self.probe_prog)
        }
        self.heights = GlobalHeights(renderer.store)
        idx = renderer.store.index
        zr = np.stack([idx.zmin, idx.zmax], -1).astype(np.float64)
        self.zr = np.where(np.isfinite(zr), zr, 0.0)  # per block, for the edge distances
        check_gl(ctx, "creating the seamless-patches programs")

    # selection

    def own_gpu_bytes(self) -> int:
        """The cached tile and strip meshes (one vertex buffer)."""
        return self.mesh_vbo.size

    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
    ) -> tuple[PatchLayout, float]:
        """Leaf patches and edge levels at ``tau`` (``metric`` is ignored) and the CPU ms."""
        check_tau(tau)
        t0 = time.perf_counter()
        fr = _Frame(self, camera, tau, resident)
        leaves = _Leaves()
        m = len(fr.blk)
        _traverse(fr, {0: (np.arange(m), np.zeros(m, np.int64), np.zeros(m, np.int64))}, leaves)
        sel = _resolve(fr, leaves)
        return sel, (time.perf_counter() - t0) * 1000.0

    # instances

    def instances(self, sel: PatchLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per tile and strip: mesh kind id ``(q,)``, GPU page ``(q,)`` and the ``(q, 8)`` int32
        instance (block col0, block row0, node col0, node row0, slot base, level of the
        ``2**c`` unit, quarter turns, 0)."""
        k, c = self.r.k, self.c
        n = len(sel)
        blk = sel.blocks[sel.block]
        size = np.left_shift(1, k - sel.depth)
        page = np.empty(n, np.int64)
        base = np.empty(n, np.int64)
        for i, b in enumerate(map(tuple, sel.blocks.tolist())):
            m = sel.block == i
            if m.any():
                s = self.r.pool.slots[b]
                page[m], base[m] = s.page, s.offset
        res = sel.edge_res
        kid, pages, rows = [], [], []
        for e in range(4):
            inst = np.stack(
                [
                    blk[:, 1] << k,
                    blk[:, 0] << k,
                    sel.col * size,
                    sel.row * size,
                    base,
                    sel.depth + c,
                    np.full(n, e),
                    np.zeros(n, np.int64),
                ],
                1,
            )
            t = self.tile_id[res[:, e]]
            s = self.strip_id[res[:, e], res[:, (e + 1) % 4]]
            kid += [t, s]
            pages += [page, page]
            rows += [inst, inst]
        if not n:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 8), np.int32)
        return np.concatenate(kid), np.concatenate(pages), np.concatenate(rows).astype(np.int32)

    def triangle_count(self, sel: PatchLayout) -> int:
        """Σ cached-mesh triangles × instances."""
        kid, _, _ = self.instances(sel)
        counts = np.array([self.tri_count[kd] for kd in self.kinds], np.int64)
        return int(counts[kid].sum()) if len(kid) else 0

    def _render(self, prog: moderngl.Program, sel: PatchLayout) -> None:
        if not len(sel):
            return
        kid, pages, inst = self.instances(sel)
        vao = self.vaos[id(prog)]
        prog["res_log2"].value = self.c
        for p in np.unique(pages).tolist():
            m = pages == p
            order = np.argsort(kid[m], kind="stable")
            kp, ip = kid[m][order], inst[m][order]
            self.r.pool.pages[p].buffer.bind_to_storage_buffer(0)
            buf = self.r.ctx.buffer(np.ascontiguousarray(ip).tobytes())
            buf.bind_to_storage_buffer(4)
            ids, starts, counts = np.unique(kp, return_index=True, return_counts=True)
            for i, s0, cnt in zip(ids.tolist(), starts.tolist(), counts.tolist(), strict=True):
                kd = self.kinds[i]
                if self.tri_count[kd] == 0:
                    continue
                prog["inst0"].value = s0
                vao.render(
                    moderngl.TRIANGLES,
                    vertices=3 * self.tri_count[kd],
                    first=3 * self.first[kd],
                    instances=cnt,
                )
            buf.release()

    def draw(
        self,
        camera: Camera,
        sel: PatchLayout,
        *,
        wireframe: bool = False,
        lod_colour: bool = False,
        clear: tuple[int, int, int] | None = None,
        selection_ms: float = 0.0,
    ) -> RenderStats:
        r = self.r
        prog = self.wire if wireframe else self.prog
        frame_ms = self.timed_frame(
            camera, prog, lambda: self._render(prog, sel), clear=clear,
            lod_colour=lod_colour or wireframe, what="drawing seamless patches",
        )  # fmt: skip
        lv = sel.edge_level
        return RenderStats(
            triangles=self.triangle_count(sel),
            patches=len(sel),
            selection_ms=selection_ms,
            frame_ms=frame_ms,
            gpu_bytes=r.pool.used_bytes,
            clamped=sel.clamped,
            violations=sel.violations,
            max_level=int(lv.max()) if len(sel) else -1,
            min_level=int(lv.min()) if len(sel) else -1,
        )

    # read-back and measurement

    def triangles(self, camera: Camera, sel: PatchLayout) -> tuple[np.ndarray, np.ndarray]:
        """Every drawn triangle read back from the GPU: global ``(col, row)`` corners
        ``(m, 3, 2)`` int64 and fetched heights ``(m, 3)`` (-1e30 where masked)."""
        cap = self.triangle_count(sel)
        prog = self.probe_prog
        tri, h = self.read_triangles(
            camera, prog, cap, lambda: self._render(prog, sel),
            "reading seamless-patch triangles back",
        )  # fmt: skip
        if len(tri) != cap:
            raise RenderError(f"the GPU drew {len(tri)} triangles, expected {cap}")
        return tri, h

    def cpu_triangles(self, sel: PatchLayout) -> np.ndarray:
        """The CPU twin of the vertex shader: global ``(col, row)`` corners ``(m, 3, 2)``."""
        kid, _, inst = self.instances(sel)
        out = []
        for i, kd in enumerate(self.kinds):
            m = kid == i
            if not m.any() or self.tri_count[kd] == 0:
                continue
            mesh = mesh_of(self.c, kd)  # (t, 3, 3)
            a = inst[m].astype(np.int64)
            uv = rotate(mesh[None, :, :, :2].astype(np.int64), a[:, 6, None, None], self.c)
            unit = np.left_shift(1, self.r.k - a[:, 5])[:, None, None, None]
            org = (a[:, None, None, 0:2] + a[:, None, None, 2:4])[:, :, :, :]
            out.append((org + uv * unit).reshape(-1, 3, 2))
        if not out:
            return np.zeros((0, 3, 2), np.int64)
        return np.concatenate(out)

    def screen_errors(self, camera: Camera, sel: PatchLayout) -> np.ndarray:
        """Measured pixel errors of the samples under the read-back triangles."""
        tri, h = self.triangles(camera, sel)
        return triangle_screen_errors(self.r.grid, camera, tri, h, self.heights)

    def drawn_blocks(self, sel: PatchLayout) -> set[Block]:
        """The blocks holding at least one leaf patch."""
        return {tuple(int(v) for v in b) for b in sel.blocks[np.unique(sel.block)]}

    def surface(
        self, camera: Camera, sel: PatchLayout
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The drawn surface at the lattice samples under the read-back triangles."""
        tri, h = self.triangles(camera, sel)
        ok = (h > -1e29).all(axis=1)
        return measure.rasterise(tri[ok], h[ok])
