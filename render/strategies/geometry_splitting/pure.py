"""``geometry-splitting``, the pure part (no GL): the quadtree texture (σ roughness per Eq. 3,
exact deepest-depth errors, height ranges; :func:`stored_tree`) and Eq. 1's projected error."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import as_strided

from render.errors import RenderError
from streamer.camera import Camera
from tiler.quadtree import max_pool

# --- the quadtree texture (CPU, once per block) -----------------------------------------------


def roughness(deltas: list[np.ndarray]) -> list[np.ndarray]:
    """Lee & Shin's Eq. 3, recursively: ``σ_l = max(δ_l, 2 max σ_(l+1))`` (``σ_k = 0``)."""
    sig = [np.asarray(x, dtype=np.float64) for x in deltas]
    for d in range(len(sig) - 2, -1, -1):
        sig[d] = np.maximum(sig[d], 2.0 * max_pool(sig[d + 1], 2))
    return sig


def _round_up32(x: np.ndarray) -> np.ndarray:
    """``x`` (float64) as float32, rounded up where the nearest float32 lies below it."""
    f = x.astype(np.float32)
    low = f < x  # (compared in float64: exact)
    if low.any():  # (only those moved: most values are exact or rounded up already)
        f[low] = np.nextafter(f[low], np.float32(np.inf))
    return f


def _half(x: np.ndarray, up: bool) -> np.ndarray:
    """``x`` (float64) as float16, rounded up (``up``) or down where the nearest is not."""
    f = x.astype(np.float16)
    off = f < x if up else f > x  # (compared in float64: exact)
    if off.any():
        f[off] = np.nextafter(f[off], np.float16(np.inf if up else -np.inf))
    return f


@dataclass
class BlockTree:
    """One block's quadtree texture as the GPU sees it (per depth ``0..k-1``)."""

    sigma: list[np.ndarray]  # float32, rounded up
    zmin: list[np.ndarray]  # float16, rounded down
    zmax: list[np.ndarray]  # float16, rounded up

    def packed(self, depth: int | None = None) -> np.ndarray:
        """``(nodes, 2)`` uint32 in depth order: σ bits, ``packHalf2x16(zmin, zmax)``; with
        ``depth`` (:func:`texture_depth`) the compact layout of :func:`texture_nodes` (each
        deeper depth's σ the least of its nodes' in each depth-``depth`` node, its ranges the
        first's), followed, where a node of those depths has σ = ∞, by the bitmask of them."""
        k = len(self.sigma)
        top = k - 1 if depth is None else int(depth)
        if not 0 <= top <= k - 1:
            raise RenderError(f"texture depth {depth} is not in 0..{k - 1}")
        parts = [
            (_least(sig, d, top), _coarse(lo, d, top), _coarse(hi, d, top))
            for d, (sig, lo, hi) in enumerate(zip(self.sigma, self.zmin, self.zmax, strict=True))
        ]
        inf = [np.isinf(self.sigma[d]) for d in range(top + 1, k)]
        if any(x.any() for x in inf):
            return np.concatenate([self._pack(parts), infinite_bits(inf)])
        return self._pack(parts)

    @staticmethod
    def _pack(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
        if sys.byteorder == "little":  # written in place: zmin the low half (0.4 vs 1.1 ms)
            n = sum(sig.size for sig, _, _ in parts)
            out = np.empty((n, 2), np.uint32)
            half = out.view(np.uint16).reshape(n, 4)
            o = 0
            for sig, lo, hi in parts:
                m = sig.size
                out[o : o + m, 0] = np.asarray(sig, np.float32).ravel().view(np.uint32)
                half[o : o + m, 2] = np.asarray(lo, np.float16).ravel().view(np.uint16)
                half[o : o + m, 3] = np.asarray(hi, np.float16).ravel().view(np.uint16)
                o += m
            return out
        s = np.concatenate([x[0].ravel() for x in parts]).astype(np.float32).view(np.uint32)
        lo = np.concatenate([x[1].ravel() for x in parts]).view(np.uint16).astype(np.uint32)
        hi = np.concatenate([x[2].ravel() for x in parts]).view(np.uint16).astype(np.uint32)
        return np.stack([s, lo | (hi << 16)], 1)


def _least(a: np.ndarray, d: int, top: int) -> np.ndarray:
    """Depth ``d``'s σ at one value per depth-``top`` node: the least of its nodes' (the tile's
    own where some node there is not ∞; ``d > top``)."""
    if d <= top:
        return a
    m = 1 << top
    return np.asarray(a).reshape(m, a.shape[0] // m, m, a.shape[1] // m).min(axis=(1, 3))


def _coarse(a: np.ndarray, d: int, top: int) -> np.ndarray:
    """Depth ``d``'s per-node array at one value per depth-``top`` node (``d > top``)."""
    if d <= top:
        return a
    s = 1 << (d - top)
    return np.asarray(a)[::s, ::s]


def texture_depth(k: int, level: int, cap: int) -> int:
    """The deepest depth a block's texture stores node by node. Below the store's error cap
    σ is one value per cap tile and below the grid's ``level`` the ranges are its nodes', so
    past ``max(level, cap)`` one entry per node of that depth serves each deeper depth
    (:func:`texture_nodes`; a block with nodata adds a bitmask of the nodes there whose σ is
    ∞). All depths (``k − 1``) at full resolution (exact errors per node)."""
    if level >= k:
        return k - 1
    return min(k - 1, max(level, cap, 0))


def texture_nodes(k: int, depth: int, bits: bool = False) -> int:
    """Entries (8 bytes) of a texture that stores depths ``0..depth`` node by node (row-major
    per depth, as the GPU indexes them) and each depth ``depth+1..k-1`` as one entry per
    depth-``depth`` node: ``(4**(depth+1) − 1) / 3 + (k − 1 − depth) · 4**depth``; with
    ``bits``, then one bit per node of those deeper depths, set where its σ is ∞ (nodes mixing
    terrain and nodata), 64 to an entry (:func:`infinite_bits`)."""
    n = ((1 << (2 * (depth + 1))) - 1) // 3 + (k - 1 - depth) * (1 << (2 * depth))
    if bits and depth < k - 1:
        n += (((1 << (2 * k)) - (1 << (2 * (depth + 1)))) // 3 + 63) // 64
    return n


def infinite_bits(inf: list[np.ndarray]) -> np.ndarray:
    """The bitmask of :func:`texture_nodes` from per-depth ``(2**d, 2**d)`` booleans (the
    depths past the compact one, in order): bit ``i`` of the row-major stream in uint32 word
    ``i // 32`` at bit ``i % 32``, as ``(entries, 2)`` uint32."""
    flat = np.concatenate([np.asarray(a, bool).ravel() for a in inf])
    words = np.packbits(flat, bitorder="little")
    words = np.concatenate([words, np.zeros(-len(words) % 8, np.uint8)])
    return words.view("<u4").astype(np.uint32).reshape(-1, 2)


def quad_errors(
    h: np.ndarray, valid: np.ndarray | None, depths: Iterable[int]
) -> dict[int, np.ndarray]:
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
    (beyond the store's cap one value covers a tile of nodes), float64."""
    a = np.asarray(arr, dtype=np.float64)
    rep = (1 << d) // a.shape[0]
    return np.repeat(np.repeat(a, rep, 0), rep, 1) if rep > 1 else a


def corner_ranges(g: np.ndarray, step: int, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per node of the depth whose corners lie ``step`` samples apart in ``g``: the min and the
    max of its 4 corners, minus and plus ``delta`` (float64, before rounding)."""
    c = g[::step, ::step]
    c00, c01, c10, c11 = c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]
    lo = np.minimum(np.minimum(c00, c01), np.minimum(c10, c11)) - delta
    hi = np.maximum(np.maximum(c00, c01), np.maximum(c10, c11)) + delta
    return lo, hi


def stored_tree(
    bound: list[np.ndarray],
    grid: np.ndarray,
    exact: dict[int, np.ndarray] | None = None,
    corners: Callable[[np.ndarray, int, np.ndarray], tuple[np.ndarray, np.ndarray]] = (
        corner_ranges
    ),
) -> BlockTree:
    """One block's quadtree texture from what the store already holds: ``bound`` (the tiler's
    per-node error field, depths ``0..k-1``: the largest vertical distance of any valid
    full-resolution sample from the node's quad, either diagonal, rounded up) as ``δ``, and the
    block's level-``R`` grid ``(2**R+1)²`` (its resident level) for the height ranges: a node of
    depth ``d <= R`` spans ``[min, max]`` of its 4 corners ``∓ δ`` (every sample lies within
    ``δ`` of the quad, which lies between its corners); deeper nodes take their depth-``R``
    ancestor's range (they cannot split there). ``exact`` replaces ``δ`` at some depths (the
    store keeps one value per tile of nodes below its cap depth, see :func:`quad_errors`).
    ``corners``: :func:`corner_ranges` or a function giving the same values (a kernel)."""
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
    ranges: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for d in range(k):
        a = min(d, rr, k - 1)  # the depth whose corners bound this node
        if a not in ranges:  # (rounded before the repeat: the same values, fewer of them)
            lo, hi = corners(g, 1 << (rr - a), deltas[a])
            ranges[a] = (_half(lo, False), _half(hi, True))
        lo, hi = ranges[a]
        rep = 1 << (d - a)
        zmin.append(np.repeat(np.repeat(lo, rep, 0), rep, 1) if rep > 1 else lo)
        zmax.append(np.repeat(np.repeat(hi, rep, 0), rep, 1) if rep > 1 else hi)
    return BlockTree(sigma=[_round_up32(x) for x in sig], zmin=zmin, zmax=zmax)


def _spread(dst: np.ndarray, small: np.ndarray) -> None:
    """Write the ``(m, m)`` per-tile values ``small`` into the flat per-node ``dst`` of
    ``(m * rep)²`` nodes (row-major), each tile's value to its ``rep × rep`` nodes."""
    m = small.shape[0]
    rep = int(round((dst.size // (m * m)) ** 0.5))
    if rep == 1:
        dst[:] = small.ravel()
        return
    st = dst.strides[0]  # (a view of dst: written in place, no temporary)
    view = as_strided(dst, (m, rep, m, rep), (rep * m * rep * st, m * rep * st, rep * st, st))
    view[...] = small[:, None, :, None]


def packed_tree(
    bound: list[np.ndarray],
    grid: np.ndarray,
    mixed: list[np.ndarray] | None = None,
    corners: Callable[[np.ndarray, int, np.ndarray], tuple[np.ndarray, np.ndarray]] = (
        corner_ranges
    ),
    depth: int | None = None,
) -> np.ndarray:
    """``stored_tree(bound, grid)`` with σ = ∞ at the ``mixed`` nodes, as
    :meth:`BlockTree.packed` gives it (the same bytes, with ``depth`` too, the bitmask of the
    ∞ σ nodes past it included), without the per-node arrays: below the store's cap depth σ
    and δ are one value per tile and the ranges below the grid's level its ancestors', so each
    is computed per tile and only spread when packed (a texture below full resolution, no
    exact errors: ~1 ms instead of ~2.5 at 1025²)."""
    k = len(bound)
    g = np.asarray(grid, dtype=np.float64)
    rr = (g.shape[0] - 1).bit_length() - 1
    if g.shape != ((1 << rr) + 1,) * 2 or not 0 <= rr <= k:
        raise RenderError(f"expected a (2**R+1)² grid with R <= {k}, got {g.shape}")
    top = k - 1 if depth is None else int(depth)
    cap = next((d for d in range(k) if bound[d].shape[0] < 1 << d), k) - 1
    if top < max(min(rr, k - 1), min(cap, k - 1)):
        raise RenderError(
            f"a texture stored node by node to depth {top} needs a depth of at least the "
            f"grid's level {rr} and the error cap {cap}: use texture_depth"
        )
    deltas = [np.asarray(x, dtype=np.float64) for x in bound]  # one value per tile
    sig = list(deltas)
    for d in range(k - 2, -1, -1):
        child = sig[d + 1]
        pooled = max_pool(child, 2) if child.shape[0] > sig[d].shape[0] else child
        sig[d] = np.maximum(sig[d], 2.0 * pooled)
    n = texture_nodes(k, top)
    inf: list[np.ndarray | None] = []  # per depth past top, the nodes whose σ is ∞ (None: none)
    out = np.empty((n, 2), np.uint32)
    half = out.view(np.uint16).reshape(n, 4)
    big = sys.byteorder != "little"
    ranges: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    off = 0
    for d in range(k):
        m = 1 << (2 * min(d, top))
        tile = _round_up32(sig[d])
        if d > top:  # the nodes whose σ is ∞ (the tree's isinf per node), for the bitmask
            rd = (1 << d) // tile.shape[0]
            spread = None
            if np.isinf(tile).any():
                spread = np.repeat(np.repeat(np.isinf(tile), rd, axis=0), rd, axis=1)
            if mixed is not None:  # and ∞ where every node of a depth-top node mixes
                every = np.asarray(mixed[d], bool)
                spread = every if spread is None else every | spread
                t = 1 << top
                every = every.reshape(t, every.shape[0] // t, t, -1).all(axis=(1, 3))
                r = t // tile.shape[0]
                tile = np.where(every, np.float32(np.inf), np.repeat(np.repeat(tile, r, 0), r, 1))
            inf.append(spread)
        _spread(out[off : off + m, 0], tile.view(np.uint32))
        a = min(d, rr, k - 1)
        if a not in ranges:
            delta = _per_node(deltas[a], a)
            lo, hi = corners(g, 1 << (rr - a), delta)
            ranges[a] = (_half(lo, False).view(np.uint16), _half(hi, True).view(np.uint16))
        lo, hi = ranges[a]
        if big:  # (packHalf2x16: zmin in the low 16 bits of the word)
            col = lo.astype(np.uint32) | (hi.astype(np.uint32) << 16)
            _spread(out[off : off + m, 1], col)
        else:
            _spread(half[off : off + m, 2], lo)
            _spread(half[off : off + m, 3], hi)
        if mixed is not None and d <= top:
            out[off : off + m, 0][np.asarray(mixed[d]).ravel()] = np.float32(np.inf).view(np.uint32)
        off += m
    if any(x is not None and x.any() for x in inf):
        full = [np.zeros((1 << (top + 1 + i),) * 2, bool) if x is None else x
                for i, x in enumerate(inf)]  # fmt: skip
        return np.concatenate([out, infinite_bits(full)])
    return out


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
