"""``jung-han``, the pure part (no GL): the pointer-free quadtree (node indices and positions),
per-vertex deltas, the projected vertex error and its bound, corner tests, the selection record
and the crack removal (T-junctions, height adjustment ``conform``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import numpy as np

from streamer.camera import Camera
from streamer.frustum import as_polygon

Block = tuple[int, int]

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
BITS = 1 << np.arange(12, dtype=np.int64)

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
def index_positions(depth: int) -> np.ndarray:
    """Row-major grid position of every index of a depth (index order -> grid order)."""
    r, c = node_position(np.arange(1 << (2 * depth), dtype=np.int64), depth)
    return r * (1 << depth) + c


def grid_level(shape: tuple[int, ...]) -> int:
    """``R`` of a ``(2**R+1)²`` level grid's ``shape`` (a ValueError naming it otherwise)."""
    n = shape[0] if len(shape) else 0
    big = n - 1
    if tuple(shape) != (n, n) or big < 1 or big & (big - 1):
        raise ValueError(f"expected a (2**R+1)² grid, got shape {tuple(shape)}")
    return big.bit_length() - 1


def vertex_deltas(heights: np.ndarray) -> np.ndarray:
    """Per-vertex δ of a ``(2**R+1)²`` level grid (NaN = masked): mean of the two vertices its
    removal interpolates between minus its height (0 at the corners; see the module notes)."""
    g = np.asarray(heights, dtype=np.float64)
    n = g.shape[0]
    rr = grid_level(g.shape)
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
    heights: np.ndarray  # (2**level+1)² float64 (precision far from 0), NaN where masked
    delta: np.ndarray  # same shape, float32
    dmax: list[np.ndarray] = field(default_factory=list)
    zlo: list[np.ndarray] = field(default_factory=list)
    zhi: list[np.ndarray] = field(default_factory=list)

    @classmethod
    def build(cls, heights: np.ndarray) -> BlockTree:
        """δ and the index-ordered pyramids of a level grid."""
        h = np.asarray(heights, dtype=np.float64)
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
            own = own.ravel()[index_positions(d)]
            if d == rr - 1:
                wins = [h[i : n - 2 + i : 2, j : n - 2 + j : 2] for i in range(3) for j in range(3)]
                tree.zlo[d] = np.fmin.reduce(wins).ravel()[index_positions(d)]
                tree.zhi[d] = np.fmax.reduce(wins).ravel()[index_positions(d)]
                tree.dmax[d] = own
            else:
                tree.zlo[d] = np.fmin.reduce(tree.zlo[d + 1].reshape(-1, 4), axis=1)
                tree.zhi[d] = np.fmax.reduce(tree.zhi[d + 1].reshape(-1, 4), axis=1)
                tree.dmax[d] = np.maximum(own, tree.dmax[d + 1].reshape(-1, 4).max(axis=1))
        return tree


# --- errors and culling -----------------------------------------------------------------------


def vertex_errors(delta: np.ndarray, points: np.ndarray, camera: Camera) -> np.ndarray:
    """``δ_s``: pixel distance between the projections of ``B`` and ``B + δ`` (0 for δ = 0,
    ∞ where undefined: either point at or behind the eye's depth).

    In closed form rather than as the difference of two projections
    (:func:`streamer.lod.exact_projected`, which it equals up to rounding): with ``c`` the
    camera coordinates of ``B`` and ``u`` the world up in camera axes, moving ``B`` by ``δ``
    moves its projection by ``f |δ| |c_z u_xy - c_xy u_z| / (c_z (c_z + δ u_z))``: one camera
    transform and no cancellation of nearly equal screen coordinates."""
    d = np.asarray(delta, dtype=np.float64)
    c = camera.to_camera(points)
    c0, c1, c2 = c[..., 0], c[..., 1], c[..., 2]
    u0, u1, u2 = camera.right[2], camera.up[2], camera.forward[2]
    z1 = c2 + d * u2
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        # |g| as sqrt(g0² + g1²), not hypot (a libm call per vertex in the compiled twin, which
        # repeats this): camera-relative components (≪ 1e150) do not overflow, and the two
        # differ by about an ulp
        g0, g1 = c2 * u0 - c0 * u2, c2 * u1 - c1 * u2
        rho = camera.focal_px * np.abs(d) * np.sqrt(g0 * g0 + g1 * g1) / (c2 * z1)
    rho = np.where((c2 > 0.0) & (z1 > 0.0), rho, np.inf)
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
    v_h: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, np.float64))
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
class LevelNodes:
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


def gather(arrays: list[np.ndarray], slot: np.ndarray, flat: np.ndarray) -> np.ndarray:
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
