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
  builds each corner with ``shaders.FETCH_COMMON``'s ``vertex_at`` (camera-relative, integer
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

from __future__ import annotations

import math
import time
import weakref
from dataclasses import dataclass, field

import moderngl
import numpy as np

from render import measure, shaders
from render.errors import RenderError
from render.gpu import check_gl
from render.renderer import RenderStats, TerrainRenderer
from render.select import check_tau
from render.strategies.base import Block, GlobalHeights, Strategy, triangle_screen_errors
from streamer.camera import Camera

NO_CAP = 99  # border cap meaning "no restriction"
CULL_MARGIN = 1e-4  # relative sphere margin of the frustum test (float32 safety)

QT_LIB = (
    shaders.FETCH_COMMON
    + """
layout(std430, binding = 4) readonly buffer Blocks { ivec4 blk[]; };
layout(std430, binding = 5) readonly buffer Quadtree { uvec2 qt[]; };
uniform float tau;
uniform vec2 viewport;
uniform vec2 slab;  // the terrain's (zmin, zmax)
// blk[4b] = (origin col, origin row, pool base, cap); blk[4b+1] = (quadtree offset, page, 0, 0);
// blk[4b+2] = neighbour block N, E, S, W (-1 none); blk[4b+3] = border caps N, E, S, W.

struct Sphere { vec3 c; float r; float sigma; };

Sphere node_sphere(ivec4 n) {
    int d = n.y;
    int dd = min(d, k - 1);
    int i = blk[4 * n.x + 1].x + ((1 << (2 * dd)) - 1) / 3 + ((n.z >> (d - dd)) << dd)
            + (n.w >> (d - dd));
    uvec2 q = qt[i];
    vec2 z = unpackHalf2x16(q.y);
    int s = 1 << (k - d);
    ivec2 g0 = blk[4 * n.x].xy + ivec2(n.w, n.z) * s;
    Sphere o;
    o.c = vec3((float(g0.x - cam_cell.x) + 0.5 * float(s)) * spacing.x - cam_frac.x,
               -(float(g0.y - cam_cell.y) + 0.5 * float(s)) * spacing.y - cam_frac.y,
               0.5 * (z.x + z.y) - cam_frac.z);
    o.r = 0.5 * float(s) * length(spacing) + 0.5 * (z.y - z.x);
    o.sigma = d < k ? uintBitsToFloat(q.x) : 0.0;
    return o;
}

// Culling sphere: the node's column through the terrain's height range.
Sphere cull_sphere(ivec4 n) {
    int s = 1 << (k - n.y);
    ivec2 g0 = blk[4 * n.x].xy + ivec2(n.w, n.z) * s;
    Sphere o;
    o.c = vec3((float(g0.x - cam_cell.x) + 0.5 * float(s)) * spacing.x - cam_frac.x,
               -(float(g0.y - cam_cell.y) + 0.5 * float(s)) * spacing.y - cam_frac.y,
               0.5 * (slab.x + slab.y) - cam_frac.z);
    o.r = 0.5 * float(s) * length(spacing) + 0.5 * (slab.y - slab.x);
    o.sigma = 0.0;
    return o;
}

bool visible(ivec4 n) {
    Sphere o = cull_sphere(n);
    vec4 w = vec4(mvp[0][3], mvp[1][3], mvp[2][3], mvp[3][3]);
    for (int i = 0; i < 3; i++) {
        vec4 a = vec4(mvp[0][i], mvp[1][i], mvp[2][i], mvp[3][i]);
        for (int sg = -1; sg <= 1; sg += 2) {
            vec4 p = w + float(sg) * a;
            float dist = (dot(p.xyz, o.c) + p.w) / length(p.xyz);
            if (dist < -o.r * (1.0 + CULL_MARGIN)) return false;
        }
    }
    return true;
}

float projected(Sphere o, int d) {
    float h = 0.5 * float(1 << (k - d));
    vec2 off[5] = vec2[5](vec2(0.0), vec2(h, 0.0), vec2(-h, 0.0), vec2(0.0, h), vec2(0.0, -h));
    float rho = 0.0;
    for (int i = 0; i < 5; i++) {
        vec3 p = o.c + vec3(off[i] * spacing, 0.0);
        vec4 a = mvp * vec4(p, 1.0);
        vec4 b = mvp * vec4(p + vec3(0.0, 0.0, o.sigma), 1.0);
        if (a.w <= 0.0 || b.w <= 0.0) return uintBitsToFloat(0x7f800000u);
        rho = max(rho, length(viewport * (b.xy / b.w - a.xy / a.w)));
    }
    return rho;
}

bool flag(Sphere o, int d) {
    if (length(o.c) - o.r < 0.0) return o.sigma != 0.0;
    return tau <= projected(o, d);
}

int lead(int v, int d, bool ones) {
    int x = (ones ? ~v : v) & ((1 << d) - 1);
    return x == 0 ? d : d - 1 - findMSB(x);
}

bool allowed(ivec4 n) {
    int d = n.y;
    if (d >= blk[4 * n.x].w) return false;
    ivec4 bc = blk[4 * n.x + 3];
    return lead(n.z, d, false) < bc.x && lead(n.w, d, true) < bc.y
        && lead(n.z, d, true) < bc.z && lead(n.w, d, false) < bc.w;
}

bool splits(ivec4 n) { return allowed(n) && flag(node_sphere(n), n.y); }

// The depth-e node across edge dir of leaf L next to the edge sample s (from L's corner).
ivec4 beside(ivec4 L, int dir, int s, int e) {
    int S = 1 << (k - L.y);
    ivec2 p0 = ivec2(L.w, L.z) * S;
    ivec2 q = dir == 0 ? p0 + ivec2(s, -1) : dir == 1 ? p0 + ivec2(S, s)
            : dir == 2 ? p0 + ivec2(s, S) : p0 + ivec2(-1, s);
    int sh = k - e, m = (1 << e) - 1;
    int c = q.x >> sh, r = q.y >> sh;
    int b = L.x;
    if (r < 0 || r > m || c < 0 || c > m) {
        b = blk[4 * L.x + 2][dir];
        r &= m;
        c &= m;
    }
    return ivec4(b, e, r, c);
}

// N (same depth as leaf L) is a node of the expanded tree.
bool exists_beside(ivec4 N, ivec4 L) {
    if (N.x < 0 || !visible(N)) return false;
    for (int j = N.y - 1; j >= 0; j--) {
        int sh = N.y - j;
        ivec4 a = ivec4(N.x, j, N.z >> sh, N.w >> sh);
        if (N.x == L.x && a.z == (L.z >> sh) && a.w == (L.w >> sh)) return true;
        if (!splits(a)) return false;
    }
    return true;
}
""".replace("CULL_MARGIN", f"{CULL_MARGIN:.6f}")
)

VS_NODE = """
#version 450
in ivec4 in_a;
flat out ivec4 v_a;
void main() { v_a = in_a; }
"""

VS_TRI = """
#version 450
in ivec4 in_a;
in ivec4 in_b;
flat out ivec4 v_a;
flat out ivec4 v_b;
void main() { v_a = in_a; v_b = in_b; }
"""

GS_EXPAND = (
    QT_LIB
    + """
layout(points) in;
layout(points, max_vertices = 4) out;
uniform int cull_input;
flat in ivec4 v_a[];
flat out ivec4 o_node;
void main() {
    ivec4 n = v_a[0];
    int d = n.y & 255;
    ivec4 m = ivec4(n.x, d, n.z, n.w);
    if (cull_input != 0 && !visible(m)) return;
    if ((n.y >> 8) == 0 && splits(m)) {
        for (int i = 0; i < 4; i++) {
            ivec4 c = ivec4(n.x, d + 1, 2 * n.z + (i >> 1), 2 * n.w + (i & 1));
            if (visible(c)) { o_node = c; EmitVertex(); EndPrimitive(); }
        }
    } else {
        o_node = ivec4(n.x, d | 256, n.z, n.w);
        EmitVertex();
        EndPrimitive();
    }
}
"""
)

GS_QUAD = (
    QT_LIB
    + """
layout(points) in;
layout(points, max_vertices = 4) out;
layout(std430, binding = 7) buffer Stats { int stats[4]; };
flat in ivec4 v_a[];
flat out ivec4 o_leaf;
flat out ivec4 o_tri;
void main() {
    ivec4 L = ivec4(v_a[0].x, v_a[0].y & 255, v_a[0].z, v_a[0].w);
    int d = L.y;
    if (d < k && !allowed(L) && flag(node_sphere(L), d)) atomicAdd(stats[0], 1);
    atomicMax(stats[1], d);
    atomicMin(stats[2], d);
    bool fine[4];
    bool any = false;
    for (int dir = 0; dir < 4; dir++) {
        ivec4 N = beside(L, dir, 0, d);
        fine[dir] = d < k && exists_beside(N, L) && splits(N);
        any = any || fine[dir];
    }
    o_leaf = L;
    if (!any) {
        o_tri = ivec4(4, 0, d, 0); EmitVertex(); EndPrimitive();
        o_tri = ivec4(5, 0, d, 0); EmitVertex(); EndPrimitive();
    } else {
        for (int dir = 0; dir < 4; dir++) {
            o_tri = ivec4(dir | (fine[dir] ? 16 : 0), 0, d, 0);
            EmitVertex();
            EndPrimitive();
        }
    }
}
"""
)

GS_SPLIT = (
    QT_LIB
    + """
layout(points) in;
layout(points, max_vertices = 2) out;
flat in ivec4 v_a[];
flat in ivec4 v_b[];
flat out ivec4 o_leaf;
flat out ivec4 o_tri;
void main() {
    ivec4 L = v_a[0], t = v_b[0];
    o_leaf = L;
    if ((t.x & 16) == 0) { o_tri = t; EmitVertex(); EndPrimitive(); return; }
    int dir = t.x & 15, e = t.z + 1, half_len = 1 << (k - e);
    for (int h = 0; h < 2; h++) {
        int s = t.y + h * half_len;
        ivec4 N = beside(L, dir, s, e);
        bool p = N.x >= 0 && visible(N) && splits(N);
        o_tri = ivec4(dir | (p ? 16 : 0), s, e, 0);
        EmitVertex();
        EndPrimitive();
    }
}
"""
)

# Vertex pulling: triangle i = records 2i (leaf) and 2i+1 (kind | pending, seg start, seg depth).
PULL = (
    QT_LIB
    + """
layout(std430, binding = 6) readonly buffer Tris { ivec4 tris[]; };
uniform int page;

Vtx fetch_vertex(int b, ivec2 p, int lv) {
    // p: block-local sample of block b on the level-lv grid
    int sh = k - lv;
    ivec4 a = ivec4(blk[4 * b].xy, 0, 0);
    return vertex_at(a, ivec4(blk[4 * b].z, lv, 0, 0), p.x >> sh, p.y >> sh);
}

Vtx pull(out bool ok) {
    int id = gl_VertexID / 3, j = gl_VertexID % 3;
    ivec4 L = tris[2 * id], t = tris[2 * id + 1];
    int b = L.x, d = L.y, kind = t.x & 15;
    ok = blk[4 * b + 1].y == page;
    int S = 1 << (k - d);
    ivec2 p0 = ivec2(L.w, L.z) * S;
    int cap = blk[4 * b].w;
    Vtx v;
    if (kind >= 4) {
        ivec2 c[3] = kind == 4 ? ivec2[3](ivec2(0, 0), ivec2(S, 0), ivec2(S, S))
                               : ivec2[3](ivec2(0, 0), ivec2(S, S), ivec2(0, S));
        v = fetch_vertex(b, p0 + c[j], d);
    } else if (j == 2) {
        if (d + 1 <= cap) {
            v = fetch_vertex(b, p0 + ivec2(S / 2), d + 1);
        } else {
            Vtx va = fetch_vertex(b, p0, d), vd = fetch_vertex(b, p0 + ivec2(S), d);
            v = va;
            v.rel = 0.5 * (va.rel + vd.rel);
            v.h = 0.5 * (va.h + vd.h);
            v.masked = max(va.masked, vd.masked);
            v.normal = normalize(va.normal + vd.normal);
            v.g = (va.g + vd.g) / 2;
        }
    } else {
        int e = t.z;
        int s = t.y + j * (1 << (k - e));
        ivec2 q = kind == 0 ? ivec2(s, 0) : kind == 1 ? ivec2(S, s)
                : kind == 2 ? ivec2(s, S) : ivec2(0, s);
        ivec2 p = p0 + q;
        if (e <= cap) {
            v = fetch_vertex(b, p, e);
        } else {
            int nb = blk[4 * b + 2][kind];
            v = fetch_vertex(nb, p + blk[4 * b].xy - blk[4 * nb].xy, e);
        }
    }
    v.level = d;
    return v;
}
"""
)

VS_DRAW = (
    PULL
    + shaders.EMIT
    + """
void main() {
    bool ok;
    Vtx v = pull(ok);
    emit(v);
    if (!ok) gl_Position = vec4(0.0, 0.0, 0.0, 1.0);
}
"""
)

VS_PROBE = (
    PULL
    + """
out vec4 t_out;
void main() {
    bool ok;
    Vtx v = pull(ok);
    t_out = vec4(vec2(v.g), v.masked > 0.0 ? -1.0e30 : v.h, ok ? 1.0 : 0.0);
    gl_Position = vec4(0.0);
}
"""
)


# --- the quadtree texture (CPU, once per block) -----------------------------------------------


def roughness(deltas: list[np.ndarray]) -> list[np.ndarray]:
    """Lee & Shin's Eq. 3, recursively: ``σ_l = max(δ_l, 2 max σ_(l+1))`` (``σ_k = 0``)."""
    sig = [np.asarray(x, dtype=np.float64) for x in deltas]
    for d in range(len(sig) - 2, -1, -1):
        m = 1 << d
        child = sig[d + 1].reshape(m, 2, m, 2).max(axis=(1, 3))
        sig[d] = np.maximum(sig[d], 2.0 * child)
    return sig


def _round_up32(x: np.ndarray) -> np.ndarray:
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)


def _half(x: np.ndarray, up: bool) -> np.ndarray:
    f = x.astype(np.float16)
    if up:
        return np.where(f.astype(np.float64) < x, np.nextafter(f, np.float16(np.inf)), f)
    return np.where(f.astype(np.float64) > x, np.nextafter(f, np.float16(-np.inf)), f)


@dataclass
class BlockTree:
    """One block's quadtree texture as the GPU sees it (per depth ``0..k-1``)."""

    sigma: list[np.ndarray]  # float32, rounded up
    zmin: list[np.ndarray]  # float16, rounded down
    zmax: list[np.ndarray]  # float16, rounded up

    def packed(self) -> np.ndarray:
        """``(nodes, 2)`` uint32 in depth order: σ bits, ``packHalf2x16(zmin, zmax)``."""
        s = np.concatenate([x.ravel() for x in self.sigma]).astype(np.float32).view(np.uint32)
        lo = np.concatenate([x.ravel() for x in self.zmin]).view(np.uint16).astype(np.uint32)
        hi = np.concatenate([x.ravel() for x in self.zmax]).view(np.uint16).astype(np.uint32)
        return np.stack([s, lo | (hi << 16)], 1)


def quad_errors(h: np.ndarray, valid: np.ndarray | None, depths) -> dict[int, np.ndarray]:
    """``δ`` per depth in ``depths`` of a full-resolution ``(2**k+1)²`` grid: the largest
    vertical distance of a valid sample (its own last row and column included) from the node's
    quad, cut along its a-d diagonal (samples x nodes arrays, vectorised over the nodes)."""
    h = np.asarray(h, dtype=np.float64)
    n = h.shape[0] - 1
    ok = np.ones(h.shape, bool) if valid is None else np.asarray(valid, dtype=bool)
    out = {}
    for d in depths:
        m, s = 1 << d, n >> d
        a, b, c, dd = h[:n:s, :n:s], h[:n:s, s::s], h[s::s, :n:s], h[s::s, s::s]
        t = np.arange(s) / s
        v, u = t[:, None, None, None], t[None, :, None, None]
        # (sample row, sample col, node row, node col): the long axes innermost
        err = np.ascontiguousarray(h[:n, :n].reshape(m, s, m, s).transpose(1, 3, 0, 2))
        # the a-d triangulation is L - q min(u, v), L = a + u (b - a) + v (c - a),
        # q = b + c - a - d (as tiler.static_error), updated in place
        err -= a
        err -= u * (b - a)
        err -= v * (c - a)
        err += np.minimum(u, v) * (b + c - a - dd)
        np.abs(err, out=err)
        err[~ok[:n, :n].reshape(m, s, m, s).transpose(1, 3, 0, 2)] = 0.0
        node = err.max(axis=(0, 1))
        # a node's south (east) edge is the next node's north (west) edge: same samples, same
        # segment, same errors; only the block's last row (column) is computed apart
        t1 = np.arange(s + 1) / s
        along = np.arange(m)[:, None] * s + np.arange(s + 1)[None, :]  # (m, s + 1) samples
        south = np.empty((m, m))
        south[:-1] = err[0, :, 1:, :].max(axis=0)
        last = np.abs(h[n][along] - (c[-1][:, None] * (1 - t1) + dd[-1][:, None] * t1))
        south[-1] = np.where(ok[n][along], last, 0.0).max(axis=1)
        east = np.empty((m, m))
        east[:, :-1] = err[:, 0, :, 1:].max(axis=0)
        last = np.abs(h[:, n][along] - (b[:, -1][:, None] * (1 - t1) + dd[:, -1][:, None] * t1))
        east[:, -1] = np.where(ok[:, n][along], last, 0.0).max(axis=1)
        out[d] = np.maximum(node, np.maximum(south, east))
    return out


def _per_node(arr: np.ndarray, d: int) -> np.ndarray:
    """A stored per-depth field ``(2**min(d, cap))²`` at every depth-``d`` node ``(2**d)²``
    (beyond the store's cap one value covers a tile of nodes)."""
    rep = (1 << d) // arr.shape[0]
    return np.repeat(np.repeat(np.asarray(arr, dtype=np.float64), rep, 0), rep, 1)


def stored_tree(
    bound: list[np.ndarray], grid: np.ndarray, exact: dict[int, np.ndarray] | None = None
) -> BlockTree:
    """One block's quadtree texture from what the store already holds: ``bound`` (the tiler's
    per-node error field, depths ``0..k-1``: the largest vertical distance of any valid
    full-resolution sample from the node's quad, either diagonal, rounded up) as ``δ``, and the
    block's level-``R`` grid ``(2**R+1)²`` (its resident level) for the height ranges: a node of
    depth ``d <= R`` spans ``[min, max]`` of its 4 corners ``∓ δ`` (every sample lies within
    ``δ`` of the quad, which lies between its corners); deeper nodes take their depth-``R``
    ancestor's range (they cannot split there). ``exact`` replaces ``δ`` at some depths (the
    store keeps one value per tile of nodes below its cap depth, see :func:`quad_errors`)."""
    k = len(bound)
    g = np.asarray(grid, dtype=np.float64)
    rr = (g.shape[0] - 1).bit_length() - 1
    if g.shape != ((1 << rr) + 1,) * 2 or not 0 <= rr <= k:
        raise RenderError(f"expected a (2**R+1)² grid with R <= {k}, got {g.shape}")
    deltas = [_per_node(bound[d], d) for d in range(k)]
    for d, e in (exact or {}).items():
        deltas[d] = np.minimum(deltas[d], e)  # both bound the quad's error; keep the tighter
    sig = roughness(deltas)
    zmin, zmax = [], []
    for d in range(k):
        a = min(d, rr, k - 1)  # the depth whose corners bound this node
        c = g[:: 1 << (rr - a), :: 1 << (rr - a)] if a <= rr else g
        quad = np.stack([c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]])
        lo, hi = quad.min(axis=0) - deltas[a], quad.max(axis=0) + deltas[a]
        rep = 1 << (d - a)
        zmin.append(np.repeat(np.repeat(lo, rep, 0), rep, 1))
        zmax.append(np.repeat(np.repeat(hi, rep, 0), rep, 1))
    return BlockTree(
        sigma=[_round_up32(x) for x in sig],
        zmin=[_half(z, False) for z in zmin],
        zmax=[_half(z, True) for z in zmax],
    )


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


class GeometrySplitting(Strategy):
    """Lee & Shin: GPU quadtree expansion and triangle splitting."""

    name = "geometry-splitting"
    uses_metric = False

    def __init__(self, renderer: TerrainRenderer) -> None:
        super().__init__(renderer)
        ctx = renderer.ctx
        self.k = renderer.k
        self.expand_prog = ctx.program(
            vertex_shader=VS_NODE, geometry_shader=GS_EXPAND, varyings=["o_node"]
        )
        self.quad_prog = ctx.program(
            vertex_shader=VS_NODE, geometry_shader=GS_QUAD, varyings=["o_leaf", "o_tri"]
        )
        self.split_prog = ctx.program(
            vertex_shader=VS_TRI, geometry_shader=GS_SPLIT, varyings=["o_leaf", "o_tri"]
        )
        self.prog = ctx.program(vertex_shader=VS_DRAW, fragment_shader=shaders.FRAGMENT)
        self.wire = ctx.program(
            vertex_shader=VS_DRAW,
            geometry_shader=shaders.GEOMETRY,
            fragment_shader=shaders.FRAGMENT_WIRE,
        )
        self.probe_prog = ctx.program(vertex_shader=VS_PROBE, varyings=["t_out"])
        self.trees: dict[Block, BlockTree] = {}
        self._tree_level: dict[Block, int] = {}  # the resident level each tree was built for
        self._qt_level: dict[Block, int] = {}  # ... and each uploaded texture
        self._qt_offset: dict[Block, int] = {}
        self._qt_buf: moderngl.Buffer | None = None
        self._qt_used = 0
        self.heights = GlobalHeights(renderer.store)
        check_gl(ctx, "creating the geometry-splitting programs")

    def own_gpu_bytes(self) -> int:
        """The quadtree texture buffer (σ and height ranges of every resident block)."""
        return self._qt_buf.size if self._qt_buf is not None else 0

    # -- quadtree texture --------------------------------------------------------------------

    def tree(self, b: Block, level: int | None = None) -> BlockTree:
        """The block's quadtree texture for its resident ``level`` (default: the GPU's), from
        the stored errors and that level's grid (:func:`stored_tree`; rebuilt when the level
        changes)."""
        lv = self.r.pool.level(b) if level is None else int(level)
        if self._tree_level.get(b) != lv or b not in self.trees:
            store = self.r.store
            grid = store.read_block(b, max_level=max(lv, 0))
            exact = None
            deep = range(store.meta.error_cap + 1, self.k)
            if lv == self.k and len(deep):  # full resolution resident: exact δ where tiled
                valid = store.read_mask(b) if store.index.has_nodata[b] else None
                exact = quad_errors(grid, valid, deep)
            self.trees[b] = stored_tree(store.read_errors(b)["bound"], grid, exact)
            self._tree_level[b] = lv
        return self.trees[b]

    def _upload_trees(self, pairs: list[tuple[Block, int]]) -> None:
        blocks = [b for b, _ in pairs]
        per = ((1 << (2 * self.k)) - 1) // 3
        for b, lv in pairs:  # resident level changed: rewrite the block's texture in place
            if b in self._qt_offset and self._qt_level.get(b) != lv:
                data = self.tree(b, lv).packed().tobytes()
                self._qt_buf.write(data, offset=self._qt_offset[b] * 8)
                self._qt_level[b] = lv
        new = [b for b in blocks if b not in self._qt_offset]
        if not new:
            return
        level = dict(pairs)
        cap = 0 if self._qt_buf is None else self._qt_buf.size // 8
        if self._qt_used + per * len(new) > cap:
            keep = [b for b in self._qt_offset if b in self.r.pool.slots or b in blocks]
            keep += [b for b in new if b not in keep]
            size = max(2 * cap, per * len(keep), per)
            if self._qt_buf is not None:
                self._qt_buf.release()
            self._qt_buf = self.r.ctx.buffer(reserve=size * 8)
            self._qt_offset, self._qt_used = {}, 0
            self.trees = {b: t for b, t in self.trees.items() if b in keep}
            self._tree_level = {b: v for b, v in self._tree_level.items() if b in keep}
            self._qt_level = {b: v for b, v in self._qt_level.items() if b in keep}
            new = keep
        for b in new:
            lv = level.get(b, self._qt_level.get(b, self.r.pool.level(b)))
            self._qt_buf.write(self.tree(b, lv).packed().tobytes(), offset=self._qt_used * 8)
            self._qt_level[b] = lv
            self._qt_offset[b] = self._qt_used
            self._qt_used += per

    def block_table(
        self, resident: dict[Block, int] | None = None
    ) -> tuple[list[Block], np.ndarray]:
        """The drawn blocks (sorted) and their ``(m, 16)`` int32 table (see ``QT_LIB``)."""
        pool = self.r.pool
        pairs = self.r.drawable(resident)
        blocks = [b for b, _ in pairs]
        index = {b: i for i, b in enumerate(blocks)}
        k = self.k
        t = np.zeros((len(blocks), 16), dtype=np.int64)
        for i, (b, lv) in enumerate(pairs):
            s = pool.slots[b]
            t[i, 0:4] = (b[1] << k, b[0] << k, s.offset, lv)
            t[i, 4:6] = (self._qt_offset.get(b, 0), s.page)
            for dr, (rr, cc) in enumerate(((-1, 0), (0, 1), (1, 0), (0, -1))):
                j = index.get((b[0] + rr, b[1] + cc), -1)
                t[i, 8 + dr] = j
                cross = j >= 0 and pool.slots[blocks[j]].page != s.page
                t[i, 12 + dr] = pairs[j][1] if cross else NO_CAP
        return blocks, t.astype(np.int32)

    # -- selection ---------------------------------------------------------------------------

    def _bind(self, prog: moderngl.Program, camera: Camera, tau: float, block_buf) -> None:
        self.r.fbo.use()
        self.r._uniforms(prog, camera)
        if "tau" in prog:
            prog["tau"].value = float(tau)
        if "slab" in prog:
            prog["slab"].value = self.r.terrain_zrange
        block_buf.bind_to_storage_buffer(4)
        if self._qt_buf is not None:
            self._qt_buf.bind_to_storage_buffer(5)

    def _pass(self, prog, src, fmt, names, n, out_per, rec_bytes) -> tuple[moderngl.Buffer, int]:
        ctx = self.r.ctx
        out = ctx.buffer(reserve=max(1, n * out_per) * rec_bytes)
        vao = ctx.vertex_array(prog, [(src, fmt, *names)])
        q = ctx.query(primitives=True)
        with q:
            vao.transform(out, moderngl.POINTS, vertices=n)
        m = int(q.primitives)
        vao.release()
        if m > n * out_per:
            raise RenderError(f"a splitting pass emitted {m} records for {n} inputs")
        return out, m

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
        tb = time.perf_counter()
        self._upload_trees(self.r.drawable(resident))
        build_ms = (time.perf_counter() - tb) * 1000.0
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
            for _ in range(self.k):
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

    def draw(
        self,
        camera: Camera,
        sel: Selection,
        *,
        wireframe: bool = False,
        lod_colour: bool = False,
        clear: tuple[int, int, int] | None = None,
        selection_ms: float = 0.0,
    ) -> RenderStats:
        r = self.r
        prog = self.wire if wireframe else self.prog

        def body() -> None:
            if not sel.triangles:
                return
            sel.block_buf.bind_to_storage_buffer(4)
            sel.tri_buf.bind_to_storage_buffer(6)
            vao = r.ctx.vertex_array(prog, [])
            for page in self._pages(sel):
                r.pool.pages[page].buffer.bind_to_storage_buffer(0)
                prog["page"].value = page
                vao.render(moderngl.TRIANGLES, vertices=3 * sel.triangles)
            vao.release()

        frame_ms = sel.gpu_ms + self.timed_frame(
            camera, prog, body, clear=clear, lod_colour=lod_colour or wireframe,
            what="drawing split geometry",
        )  # fmt: skip
        return RenderStats(
            triangles=sel.triangles,
            patches=sel.leaves,
            selection_ms=selection_ms,
            frame_ms=frame_ms,
            gpu_bytes=r.pool.used_bytes + (self._qt_buf.size if self._qt_buf else 0),
            clamped=sel.clamped,
            violations=0,
            max_level=sel.max_depth,
            min_level=sel.min_depth,
        )

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
        heights ``(m, 3)`` (-1e30 where masked), read back with transform feedback."""
        r = self.r
        if not sel.triangles:
            return np.zeros((0, 3, 2), np.int64), np.zeros((0, 3))
        r.fbo.use()
        r._uniforms(self.probe_prog, camera)
        r.level_tex.use(1)
        r.order_tex.use(2)
        sel.block_buf.bind_to_storage_buffer(4)
        sel.tri_buf.bind_to_storage_buffer(6)
        vao = r.ctx.vertex_array(self.probe_prog, [])
        out = r.ctx.buffer(reserve=sel.triangles * 3 * 16)
        parts = []
        for page in self._pages(sel):
            r.pool.pages[page].buffer.bind_to_storage_buffer(0)
            self.probe_prog["page"].value = page
            vao.transform(out, moderngl.POINTS, vertices=3 * sel.triangles)
            a = np.frombuffer(out.read(), np.float32).reshape(-1, 3, 4)
            parts.append(a[(a[..., 3] > 0.5).all(axis=1)])
        vao.release()
        out.release()
        check_gl(r.ctx, "reading split triangles back")
        a = np.concatenate(parts).astype(np.float64)
        return np.rint(a[..., :2]).astype(np.int64), a[..., 2]

    def screen_errors(self, camera: Camera, sel: Selection) -> np.ndarray:
        tri, h = self.triangles(camera, sel)
        return triangle_screen_errors(self.r.grid, camera, tri, h, self.heights)

    def drawn_blocks(self, sel: Selection) -> set[Block]:
        idx = np.unique(self.leaf_nodes(sel)[:, 0])
        return {sel.blocks[int(i)] for i in idx}

    def surface(self, camera: Camera, sel: Selection):
        tri, h = self.triangles(camera, sel)
        ok = (h > -1e29).all(axis=1)
        return measure.rasterise(tri[ok], h[ok])

    # -- CPU twin ----------------------------------------------------------------------------

    def expand_reference(
        self, camera: Camera, tau: float, resident: dict[Block, int] | None = None
    ) -> tuple[list[int], np.ndarray, np.ndarray]:
        """CPU twin (float64) of the expansion: node counts after each pass, the leaves and the
        nodes that split, both ``(block index, depth, row, col)`` sorted."""
        blocks, t = self.block_table(resident)
        k, g = self.k, self.r.grid
        trees = [self.tree(b, int(t[i, 3])) for i, b in enumerate(blocks)]
        mvp = camera.projection_matrix() @ camera.view_matrix()
        planes = []
        for i in range(3):
            for sg in (-1.0, 1.0):
                p = mvp[3] + sg * mvp[i]
                planes.append(p / np.linalg.norm(p[:3]))
        planes = np.array(planes)

        zlo_t, zhi_t = self.r.terrain_zrange

        def cull(b, d, row, col):
            s = np.left_shift(1, k - d).astype(np.float64)
            x, y = g.sample_xy(t[b, 1] + row * s + 0.5 * s, t[b, 0] + col * s + 0.5 * s)
            c = np.stack([x, y, np.full(len(b), 0.5 * (zlo_t + zhi_t))], 1) - camera.eye
            return c, 0.5 * s * math.hypot(g.dx, g.dy) + 0.5 * (zhi_t - zlo_t)

        def sphere(b, d, row, col):
            dd = np.minimum(d, k - 1)
            sh = d - dd
            sig = np.zeros(len(b))
            zlo, zhi = np.zeros(len(b)), np.zeros(len(b))
            for i in range(len(b)):
                tr = trees[b[i]]
                rr, cc = row[i] >> sh[i], col[i] >> sh[i]
                sig[i] = tr.sigma[dd[i]][rr, cc] if d[i] < k else 0.0
                zlo[i], zhi[i] = tr.zmin[dd[i]][rr, cc], tr.zmax[dd[i]][rr, cc]
            s = np.left_shift(1, k - d).astype(np.float64)
            gx = t[b, 0] + col * s + 0.5 * s
            gy = t[b, 1] + row * s + 0.5 * s
            x, y = g.sample_xy(gy, gx)
            c = np.stack([x, y, 0.5 * (zlo + zhi)], 1) - camera.eye
            rad = 0.5 * s * math.hypot(g.dx, g.dy) + 0.5 * (zhi - zlo)
            return c, rad, sig, s

        def visible(c, rad):
            dist = c @ planes[:, :3].T + planes[:, 3]
            return (dist >= -rad[:, None] * (1.0 + CULL_MARGIN)).all(axis=1)

        def splits(b, d, row, col):
            c, rad, sig, s = sphere(b, d, row, col)
            cap = t[b, 3]
            ok = d < cap
            for dr, (v, ones) in enumerate(((row, False), (col, True), (row, True), (col, False))):
                m = np.left_shift(1, d) - 1
                x = (~v if ones else v) & m
                lead = np.where(x == 0, d, d - 1 - np.floor(np.log2(np.maximum(x, 1))))
                ok &= lead < t[b, 12 + dr]
            rho = projected_error(c, sig, s, camera, g.dx, g.dy)
            inside = np.linalg.norm(c, axis=1) - rad < 0.0
            fl = np.where(inside, sig != 0.0, tau <= rho)
            return ok & fl

        n = len(blocks)
        b = np.arange(n)
        d = np.zeros(n, np.int64)
        row = np.zeros(n, np.int64)
        col = np.zeros(n, np.int64)
        done = np.zeros(n, bool)
        keep = visible(*cull(b, d, row, col))
        b, d, row, col, done = b[keep], d[keep], row[keep], col[keep], done[keep]
        counts, split = [], []
        for _ in range(k):
            sp = ~done & splits(b, d, row, col)
            split.append(np.stack([b[sp], d[sp], row[sp], col[sp]], 1))
            cb = np.repeat(b[sp], 4)
            cd = np.repeat(d[sp] + 1, 4)
            cr = (2 * row[sp][:, None] + np.array([0, 0, 1, 1])).ravel()
            cc = (2 * col[sp][:, None] + np.array([0, 1, 0, 1])).ravel()
            v = visible(*cull(cb, cd, cr, cc))
            b = np.concatenate([b[~sp], cb[v]])
            d = np.concatenate([d[~sp], cd[v]])
            row = np.concatenate([row[~sp], cr[v]])
            col = np.concatenate([col[~sp], cc[v]])
            done = np.concatenate([np.ones(int((~sp).sum()), bool), np.zeros(int(v.sum()), bool)])
            counts.append(len(b))
            if not len(b):
                break
        leaves = np.stack([b, d, row, col], 1)
        split = np.concatenate(split) if split else np.zeros((0, 4), np.int64)
        return counts, leaves[np.lexsort(leaves.T[::-1])], split[np.lexsort(split.T[::-1])]


def projected_error(
    centre_rel: np.ndarray,
    sigma: np.ndarray,
    size: np.ndarray,
    camera: Camera,
    dx: float,
    dy: float,
) -> np.ndarray:
    """Eq. 1's ``max σ̄``: the largest pixel distance between the projections of ``v`` and
    ``v + (0, 0, σ)`` over a node's centre and 4 edge midpoints (camera-relative centres
    ``(m, 3)``, node edge ``size`` in samples); ``inf`` when a point is at or behind the eye."""
    c = np.asarray(centre_rel, dtype=np.float64)
    sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), c.shape[:1])
    h = 0.5 * np.broadcast_to(np.asarray(size, dtype=np.float64), c.shape[:1])
    mvp = camera.projection_matrix() @ camera.view_matrix()
    vp = np.array(camera.viewport, np.float64) / 2.0
    z = np.zeros_like(h)
    rho = np.zeros(len(c))
    for ox, oy in ((z, z), (h, z), (-h, z), (z, h), (z, -h)):
        p = c + np.stack([ox * dx, oy * dy, z], 1)
        q = p + np.stack([z, z, sig], 1)
        a = np.c_[p, np.ones(len(p))] @ mvp.T
        b = np.c_[q, np.ones(len(q))] @ mvp.T
        behind = (a[:, 3] <= 0.0) | (b[:, 3] <= 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = np.hypot(*(vp[:, None] * (b[:, :2] / b[:, 3:] - a[:, :2] / a[:, 3:]).T))
        rho = np.maximum(rho, np.where(behind, np.inf, dist))
    return rho
