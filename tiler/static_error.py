"""Static (object-space) errors of a block's quadtree nodes (pure numpy, no I/O).

A node at depth ``d`` (``0 <= d < k``) of a ``2**k+1`` block covers ``2**(k-d)`` sample
intervals; drawn unsplit it uses the level-``d`` grid. Two error fields are computed per node:

* ``qiu`` — Qiu et al.'s Eq. 3–5: ``H`` = the largest ``|f(v) - f'(v)|`` over the node's four
  edge midpoints and its centre (the centre interpolated along each diagonal), made monotone:
  a node's value is at least every descendant's.
* ``bound`` — the largest vertical distance between any full-resolution sample inside the node
  and the node's level-``d`` surface, under either diagonal triangulation, also made monotone.
  It is a true bound on what drawing the node costs in object space, for conservative metrics.

Invalid (nodata, padding) samples are never counted. Fields are stored as float16 rounded *up*
(never down), and at depths finer than ``cap`` only as the maximum over ``2**(k-cap)``-sample
cells: one value per depth per cell. A node at depth ``d <= cap`` asking for the maximum over its
descendants at any depth therefore gets the exact value.
"""

from __future__ import annotations

import numpy as np

from tiler import kernels
from tiler.layout import subgrid

FIELDS = ("qiu", "bound")
_MARGIN = 1.0 + 1e-9


def default_cap(k: int) -> int:
    """Finest depth stored at full node resolution: cells of 16 samples (``k - 4``), at least 0."""
    return max(0, k - 4)


def _node_max(d: np.ndarray, n: int) -> np.ndarray:
    """Max of a ``(n*s+1)**2`` sample field over each of the ``n x n`` nodes (borders shared)."""
    s = (d.shape[0] - 1) // n
    inner = d[:-1, :-1].reshape(n, s, n, s).max(axis=(1, 3))
    bottom = d[s::s, :-1].reshape(n, n, s).max(axis=2)
    right = d[:-1, s::s].reshape(n, s, n).max(axis=1)
    corner = d[s::s, s::s]
    return np.maximum(np.maximum(inner, bottom), np.maximum(right, corner))


def qiu_errors(grid: np.ndarray, valid: np.ndarray, k: int) -> list[np.ndarray]:
    """Qiu's ``H`` (Eq. 4) for every node, depth ``0..k-1``, as ``(2**d, 2**d)`` float64 arrays.

    Compiled when numba is available (:mod:`tiler.kernels`), identical to :func:`qiu_errors_numpy`.
    """
    mod = kernels.active()
    if mod is None or not _finite(grid):
        return qiu_errors_numpy(grid, valid, k)
    return kernels.split_depths(kernels.qiu_flat(mod, grid, valid, k), k)


def _finite(grid: np.ndarray) -> bool:
    """Kernels assume finite heights (NaN ordering differs); the numpy path handles the rest."""
    return grid.dtype.kind != "f" or bool(np.isfinite(grid).all())


def valid_extent(valid: np.ndarray) -> tuple[int, int] | None:
    """The last row and column holding a valid sample, or ``None`` when none is valid: a node
    that starts below or right of them holds no valid sample, so its errors are 0."""
    rows = np.flatnonzero(valid.any(axis=1))
    if not len(rows):
        return None
    cols = np.flatnonzero(valid.any(axis=0))
    return int(rows[-1]), int(cols[-1])


def _node_span(extent: tuple[int, int] | None, n: int, s: int) -> tuple[int, int]:
    """How many node rows and columns (of ``n``, ``s`` samples each) hold a valid sample."""
    if extent is None:
        return 0, 0
    return min(n, extent[0] // s + 1), min(n, extent[1] // s + 1)


def qiu_errors_numpy(
    grid: np.ndarray, valid: np.ndarray, k: int, crop: bool = True
) -> list[np.ndarray]:
    """Reference (numpy) form of :func:`qiu_errors`. ``crop`` computes only the nodes up to
    the last valid row and column (:func:`valid_extent`; padding costs nothing), with the
    same values as ``crop=False`` for finite grids."""
    crop = crop and _finite(grid)
    extent = valid_extent(valid) if crop else (grid.shape[0] - 1, grid.shape[1] - 1)
    side = grid.shape[0]
    out = []
    for depth in range(k):
        n = 1 << depth
        nr, nc = _node_span(extent, n, (side - 1) // n)
        node = np.zeros((n, n), dtype=np.float64)
        if nr and nc:
            c = subgrid(grid, k, depth)[: nr + 1, : nc + 1].astype(np.float64)
            f = subgrid(grid, k, depth + 1)[: 2 * nr + 1, : 2 * nc + 1].astype(np.float64)
            ok = subgrid(valid, k, depth + 1)[: 2 * nr + 1, : 2 * nc + 1]
            top = np.abs(f[:-1:2, 1::2] - (c[:-1, :-1] + c[:-1, 1:]) * 0.5) * ok[:-1:2, 1::2]
            bot = np.abs(f[2::2, 1::2] - (c[1:, :-1] + c[1:, 1:]) * 0.5) * ok[2::2, 1::2]
            left = np.abs(f[1::2, :-1:2] - (c[:-1, :-1] + c[1:, :-1]) * 0.5) * ok[1::2, :-1:2]
            right = np.abs(f[1::2, 2::2] - (c[:-1, 1:] + c[1:, 1:]) * 0.5) * ok[1::2, 2::2]
            centre = f[1::2, 1::2]
            d1 = np.abs(centre - (c[:-1, :-1] + c[1:, 1:]) * 0.5)
            d2 = np.abs(centre - (c[:-1, 1:] + c[1:, :-1]) * 0.5)
            mid = np.maximum(d1, d2) * ok[1::2, 1::2]
            node[:nr, :nc] = np.maximum.reduce([top, bot, left, right, mid])
        out.append(node)
    return out


def bound_errors_reference(grid: np.ndarray, valid: np.ndarray, k: int) -> list[np.ndarray]:
    """Slow, direct form of :func:`bound_errors` (for tests): interpolate every sample."""
    side = grid.shape[0]
    f = grid.astype(np.float64)
    out = []
    for depth in range(k):
        n = 1 << depth
        s = (side - 1) // n
        c = subgrid(grid, k, depth).astype(np.float64)
        pos = np.arange(side)
        cell = np.minimum(pos // s, n - 1)
        t = (pos - cell * s) / s
        u, v = t[None, :], t[:, None]
        ri, ci = cell[:, None], cell[None, :]
        a, b, cc, dd = c[ri, ci], c[ri, ci + 1], c[ri + 1, ci], c[ri + 1, ci + 1]
        za = np.where(u >= v, a + u * (b - a) + v * (dd - b), a + v * (cc - a) + u * (dd - cc))
        zb = np.where(
            (u + v) <= 1.0,
            a + u * (b - a) + v * (cc - a),
            dd + (1.0 - u) * (cc - dd) + (1.0 - v) * (b - dd),
        )
        dev = np.maximum(np.abs(f - za), np.abs(f - zb))
        dev[~valid] = 0.0
        out.append(_node_max(dev, n))
    return out


def _surface_dev(f4, a, b, c, d, u, v):
    """max |f - z| over the two diagonal triangulations of each node (broadcast 4-D, float32).

    With ``L = a + u (b - a) + v (c - a)`` and ``q = b + c - a - d``, the a-d triangulation is
    ``L - q min(u, v)`` and the b-c one ``L + q min(1 - u - v, 0)``: two multiply-adds on top
    of a shared ``f - L``, and no branch.
    """
    g = f4 - a
    g -= u * (b - a)
    g -= v * (c - a)
    q = b + c - a - d
    m1 = np.minimum(u, v)
    m2 = np.minimum(1.0 - u - v, 0.0).astype(f4.dtype)
    dev_a = np.abs(g + q * m1)
    g -= q * m2
    np.abs(g, out=g)
    np.maximum(dev_a, g, out=g)
    return g


_BROADCAST_MIN = 16  # node size (samples) above which 4-D broadcasting beats offset loops
#: ... and at or below it, the node count per ``s**2`` up to which broadcasting still beats the
#: ``s**2`` offset passes (each a few numpy calls of ~10-20 us): a 17-sample block's depth 0 took
#: 5.7 ms in 256 passes against 0.1 ms broadcast. Measured (offset / broadcast time): 1.26 at
#: 48² nodes of s = 16 but 0.84 at 64² (a 1025² block's depth 6), 2.5 at 24² of s = 8, 1.3 at
#: 12² of s = 4, 1.4 at 6² of s = 2 (both paths give the same float32 values)
_BROADCAST_NODES_PER_S2 = 12


def broadcast_nodes(nr: int, nc: int, s: int) -> bool:
    """Whether :func:`_depth_nodes` broadcasts ``(nr, nc)`` nodes of ``s`` samples in 4-D (else
    one pass per in-node offset): for large nodes, and for few small ones."""
    return s > _BROADCAST_MIN or nr * nc <= _BROADCAST_NODES_PER_S2 * s * s


def _offset_dev(
    f: np.ndarray, c: np.ndarray, inval: np.ndarray, nr: int, nc: int, s: int, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Node maxima for small nodes: one ``(nr, nc)`` pass per in-node offset ``(iv, iu)``, so
    numpy's inner loops run over nodes, not ``s`` samples. Returns the max over the
    node's interior+top+left samples, over its top row, over its left column, and its corner."""
    a, b, cc, d = c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]
    ba, ca = b - a, cc - a
    q = b + cc - a - d
    inner = np.zeros((nr, nc), dtype=f.dtype)
    top = np.zeros((nr, nc), dtype=f.dtype)
    left = np.zeros((nr, nc), dtype=f.dtype)
    corner = None
    for iv in range(s):
        v = t[iv]
        for iu in range(s):
            u = t[iu]
            g = f[iv : iv + nr * s : s, iu : iu + nc * s : s] - a
            g -= u * ba
            g -= v * ca
            m1, m2 = min(u, v), min(1.0 - u - v, 0.0)
            out = np.abs(g + m1 * q)
            g -= m2 * q
            np.abs(g, out=g)
            np.maximum(out, g, out=out)
            out[inval[iv : iv + nr * s : s, iu : iu + nc * s : s]] = 0.0
            np.maximum(inner, out, out=inner)
            if iv == 0:
                np.maximum(top, out, out=top)
            if iu == 0:
                np.maximum(left, out, out=left)
            if iu == 0 and iv == 0:
                corner = out.copy()
    return inner, top, left, corner


def _edge_dev(f_edge: np.ndarray, c_edge: np.ndarray, t: np.ndarray) -> np.ndarray:
    """|f - linear interpolation| along a block border (the last row or column)."""
    interp = (c_edge[:-1, None] * (1.0 - t) + c_edge[1:, None] * t).ravel()
    return np.abs(f_edge - np.append(interp, c_edge[-1]))


def _recentre(grid: np.ndarray, valid: np.ndarray, mod=None) -> tuple[np.ndarray, float]:
    """float32 heights relative to the valid samples' mid-range, and a margin covering their
    rounding (the mid-range gives the smallest largest |height - ref|, hence the smallest margin,
    in two reductions instead of a median's partition)."""
    if not grid.size or not valid.any():
        ref = 0.0
    elif valid.all():
        ref = 0.5 * (float(grid.min()) + float(grid.max()))
    else:
        vals = grid[valid]
        ref = 0.5 * (float(vals.min()) + float(vals.max()))
    if mod is not None:
        f, span = kernels.recentre(mod, grid, ref)
        return f, 64.0 * np.finfo(np.float32).eps * span
    f64 = grid.astype(np.float64) - ref
    span = float(np.max(np.abs(f64))) if f64.size else 0.0
    return f64.astype(np.float32), 64.0 * np.finfo(np.float32).eps * span


def _bound_flat(mod, grid: np.ndarray, valid: np.ndarray, k: int) -> np.ndarray:
    """Depth-packed float64 bound field (compiled path), before monotonicity."""
    f, margin = _recentre(grid, valid, mod)
    node = kernels.bound_flat(mod, f, valid, k)
    return np.where(node > 0, node.astype(np.float64) + margin, 0.0)


def bound_errors(grid: np.ndarray, valid: np.ndarray, k: int) -> list[np.ndarray]:
    """Largest |sample - level-d surface| per node (either diagonal), depth ``0..k-1``.

    Compiled (one pass over the block for all depths) when numba is available, identical to
    :func:`bound_errors_numpy`.
    """
    mod = kernels.active()
    if mod is None or not _finite(grid):
        return bound_errors_numpy(grid, valid, k)
    return kernels.split_depths(_bound_flat(mod, grid, valid, k), k)


def bound_errors_numpy(
    grid: np.ndarray, valid: np.ndarray, k: int, crop: bool = True
) -> list[np.ndarray]:
    """Reference (numpy) form of :func:`bound_errors`.

    Nodes are viewed as ``(n, s, n, s)`` blocks of the grid (no gathers); the block's last row
    and column, and the edges nodes share, are added afterwards. ``crop`` computes only the
    nodes up to the last valid row and column (:func:`valid_extent`), with the same values as
    ``crop=False`` for finite grids: a node beyond them, and its edges, hold no valid sample.
    """
    side = grid.shape[0]
    f, margin = _recentre(grid, valid)
    inval = ~valid
    crop = crop and _finite(grid)
    extent = valid_extent(valid) if crop else (side - 1, side - 1)
    out = []
    for depth in range(k):
        n = 1 << depth
        s = (side - 1) // n
        nr, nc = _node_span(extent, n, s)
        node = np.zeros((n, n), dtype=np.float32)
        if nr and nc:
            c = subgrid(f, k, depth)[: nr + 1, : nc + 1]
            box = np.s_[: nr * s + 1, : nc * s + 1]
            # one node row (column): only its offsets up to the last valid row (column) count
            rs = s if nr > 1 else min(s, extent[0] + 1)
            cs = s if nc > 1 else min(s, extent[1] + 1)
            node[:nr, :nc] = _depth_nodes(f[box], c, inval[box], s, rs, cs)
        out.append(np.where(node > 0, node.astype(np.float64) + margin, 0.0))
    return out


def _depth_nodes(
    f: np.ndarray, c: np.ndarray, inval: np.ndarray, s: int, rs: int, cs: int
) -> np.ndarray:
    """float32 max |f - surface| of each node of ``s`` samples over the ``(nr*s+1, nc*s+1)``
    heights ``f`` (``c``: the node corners; ``inval`` samples count 0). Only the first ``rs``
    rows and ``cs`` columns of each node are visited, besides its borders: the rest must be
    invalid (on the broadcast path; the offset passes visit all)."""
    nr, nc = c.shape[0] - 1, c.shape[1] - 1
    t = (np.arange(s) / s).astype(np.float32)
    if broadcast_nodes(nr, nc, s):
        f4 = f[:-1, :-1].reshape(nr, s, nc, s)[:, :rs, :, :cs]
        quad = (c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:])
        corners = [q[:, None, :, None] for q in quad]
        dev = _surface_dev(f4, *corners, t[None, None, None, :cs], t[None, :rs, None, None])
        dev[inval[:-1, :-1].reshape(nr, s, nc, s)[:, :rs, :, :cs]] = 0.0
        inner = dev.max(axis=1).max(axis=2)  # axis by axis: ~5x faster, same maxima
        top = dev[:, 0, :, :].max(axis=2)
        left = dev[:, :, :, 0].max(axis=1)
        tl = dev[:, 0, :, 0]
    else:
        inner, top, left, tl = _offset_dev(f, c, inval, nr, nc, s, t)
    lastrow = _edge_dev(f[-1, :], c[-1, :], t)
    lastcol = _edge_dev(f[:, -1], c[:, -1], t)
    lastrow[inval[-1, :]] = 0.0
    lastcol[inval[:, -1]] = 0.0
    bottom = np.vstack([top[1:], lastrow[:-1].reshape(nc, s).max(axis=1)[None]])
    right = np.hstack([left[:, 1:], lastcol[:-1].reshape(nr, s).max(axis=1)[:, None]])
    corner = np.empty((nr, nc), dtype=np.float32)
    corner[:-1, :-1] = tl[1:, 1:]
    corner[-1, :] = lastrow[s::s]
    corner[:, -1] = lastcol[s::s]
    return np.maximum.reduce([inner, bottom, right, corner])


def make_monotone(per_depth: list[np.ndarray]) -> list[np.ndarray]:
    """Qiu's Eq. 3: each node's value becomes the max of itself and all its descendants."""
    out = [a.copy() for a in per_depth]
    for depth in range(len(out) - 1, 0, -1):
        c = out[depth]  # the max of each 2x2 children, as four strided maxima (exact)
        parent_of_children = np.maximum(
            np.maximum(c[0::2, 0::2], c[1::2, 0::2]), np.maximum(c[0::2, 1::2], c[1::2, 1::2])
        )
        np.maximum(out[depth - 1], parent_of_children, out=out[depth - 1])
    return out


def round_up_f16(values: np.ndarray) -> np.ndarray:
    """float16 values that are never below the float64 inputs (``inf`` when too large)."""
    v = np.asarray(values, dtype=np.float64)
    with np.errstate(over="ignore"):  # above 65504 becomes inf: still an upper bound
        h = v.astype(np.float16)
    low = h.astype(np.float64) < v
    if low.any():
        h[low] = np.nextafter(h[low], np.float16(np.inf))
    return h


def field_sizes(k: int, cap: int) -> list[int]:
    """Number of stored values for each depth ``0..k-1``."""
    return [4 ** min(depth, cap) for depth in range(k)]


def pack_field(per_depth: list[np.ndarray], cap: int) -> np.ndarray:
    """Flatten a monotone field depth by depth (row-major; tile max beyond ``cap``), f16 up."""
    parts = []
    for depth, arr in enumerate(per_depth):
        if depth > cap:
            n = 1 << cap
            r = arr.shape[0] // n
            arr = arr.reshape(n, r, n, r).max(axis=1).max(axis=2)
        parts.append(arr.ravel())
    return round_up_f16(np.concatenate(parts)) if parts else np.zeros(0, np.float16)


def unpack_field(flat: np.ndarray, k: int, cap: int) -> list[np.ndarray]:
    """Inverse of :func:`pack_field`: ``(2**min(d,cap))**2`` arrays per depth, as float32."""
    out = []
    pos = 0
    for depth, size in enumerate(field_sizes(k, cap)):
        n = 1 << min(depth, cap)
        out.append(np.asarray(flat[pos : pos + size], dtype=np.float32).reshape(n, n))
        pos += size
    return out


def node_error(field: list[np.ndarray], depth: int, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Stored error of nodes ``(depth, row, col)`` (vectorised) from an unpacked field."""
    arr = field[depth]
    shift = depth - int(np.log2(arr.shape[0]))
    return arr[np.asarray(row) >> shift, np.asarray(col) >> shift]


def subtree_error(field: list[np.ndarray], depth: int, row: int, col: int, below: int) -> float:
    """Max stored error of the descendants ``below`` depths under node ``(depth, row, col)``."""
    target = depth + below
    arr = field[target]
    n = arr.shape[0]
    scale = n / (1 << depth)
    if scale >= 1:
        r0, r1 = int(row * scale), int((row + 1) * scale)
        c0, c1 = int(col * scale), int((col + 1) * scale)
        return float(arr[r0:r1, c0:c1].max())
    shift = depth - int(np.log2(n))
    return float(arr[row >> shift, col >> shift])


def block_errors(grid: np.ndarray, valid: np.ndarray, k: int, cap: int) -> np.ndarray:
    """Both packed monotone fields of one block: a ``(2, total)`` float16 array (qiu, bound)."""
    mod = kernels.active()
    if mod is not None and _finite(grid):
        q = kernels.monotone_pack(mod, kernels.qiu_flat(mod, grid, valid, k), k, cap, _MARGIN)
        b = kernels.monotone_pack(mod, _bound_flat(mod, grid, valid, k), k, cap, _MARGIN)
        return np.stack([round_up_f16(q), round_up_f16(b)])
    # a relative 1e-9 margin covers float64 rounding in the arithmetic before the f16 round-up
    q = pack_field([e * _MARGIN for e in make_monotone(qiu_errors(grid, valid, k))], cap)
    b = pack_field([e * _MARGIN for e in make_monotone(bound_errors(grid, valid, k))], cap)
    return np.stack([q, b])
