"""Quadtree node geometry of blocks (pure numpy, no store, no thread).

A block of ``(2**k + 1)**2`` samples is the root of a quadtree; a node at depth ``d`` spans
``2**(k - d)`` sample steps. These helpers give node centres in world coordinates, node half
diagonals, bounding-sphere radii and the per-block height ranges those spheres are built from,
so every caller (streamer planning, renderer selection) uses one rule; and per-node height
ranges from a block's stored grid and error field (:func:`node_height_bounds`, the boxes of
:mod:`render.node_boxes`).

The height-range rule (:func:`block_zranges`): a block's ``(zmin, zmax)`` from the grid index;
a block without terrain (NaN in the index) gets the range of the whole store, so a sphere
around it is never smaller than the terrain it might hold and never NaN.
"""

from __future__ import annotations

import math

import numpy as np

from tiler.errors import LayoutError
from tiler.grid import BlockGrid


def node_span(k: int, depth: int) -> int:
    """Sample steps spanned by one edge of a depth-``depth`` node of a ``2**k`` block."""
    return 1 << (k - depth)


def half_diagonal(grid: BlockGrid, depth: int) -> float:
    """Half the ground diagonal of a node at ``depth`` (world units)."""
    return 0.5 * float(node_span(grid.k, depth)) * math.hypot(grid.dx, grid.dy)


def block_origins(
    grid: BlockGrid, block_rows: np.ndarray, block_cols: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World ``(xmin, ymax)`` corners of blocks (the corner of sample ``(0, 0)``)."""
    xmin, _, _, ymax = grid.block_bounds(block_rows, block_cols)
    return xmin, ymax


def node_centres_at(
    grid: BlockGrid,
    xmin: np.ndarray,
    ymax: np.ndarray,
    depth: int,
    rows: np.ndarray,
    cols: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """World ``(x, y)`` centres of nodes of blocks whose :func:`block_origins` are given."""
    s = float(node_span(grid.k, depth))
    cx = xmin + (np.asarray(cols, dtype=np.float64) + 0.5) * (s * grid.dx)
    cy = ymax - (np.asarray(rows, dtype=np.float64) + 0.5) * (s * grid.dy)
    return cx, cy


def node_centres(
    grid: BlockGrid,
    block_rows: np.ndarray,
    block_cols: np.ndarray,
    depth: int,
    rows: np.ndarray,
    cols: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """World ``(x, y)`` centres of nodes ``(depth, rows, cols)`` of blocks (vectorised)."""
    xmin, ymax = block_origins(grid, block_rows, block_cols)
    return node_centres_at(grid, xmin, ymax, depth, rows, cols)


def sphere_radius(half_diag: float | np.ndarray, zhalf: np.ndarray) -> np.ndarray:
    """Radius of the sphere around a node: its half diagonal and half its height range."""
    return np.hypot(half_diag, zhalf)


def block_zranges(
    zmin: np.ndarray, zmax: np.ndarray, blocks: np.ndarray | None = None
) -> np.ndarray:
    """``(..., 2)`` float64 ``(zmin, zmax)`` of blocks from the index arrays (see module doc).

    ``blocks`` ``(n, 2)`` selects blocks (default: the whole grid, shape ``(rows, cols, 2)``).
    """
    lo = np.asarray(zmin, dtype=np.float64)
    hi = np.asarray(zmax, dtype=np.float64)
    finite = np.isfinite(lo) & np.isfinite(hi)
    g0 = float(lo[finite].min()) if finite.any() else 0.0
    g1 = float(hi[finite].max()) if finite.any() else 0.0
    zr = np.stack([np.where(finite, lo, g0), np.where(finite, hi, g1)], axis=-1)
    if blocks is None:
        return zr
    b = np.asarray(blocks, dtype=np.int64).reshape(-1, 2)
    return zr[b[:, 0], b[:, 1]]


def split_children(
    idx: np.ndarray, rows: np.ndarray, cols: np.ndarray, split: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The four children ``(owner, rows, cols)`` of the nodes where ``split`` is True."""
    owner = np.repeat(idx[split], 4)
    r = (2 * rows[split][:, None] + np.array([0, 0, 1, 1])).ravel()
    c = (2 * cols[split][:, None] + np.array([0, 1, 0, 1])).ravel()
    return owner, r, c


def _per_node(arr: np.ndarray, depth: int) -> np.ndarray:
    """A stored per-depth field ``(2**min(depth, cap))²`` at every depth-``depth`` node."""
    a = np.asarray(arr, dtype=np.float64)
    rep = (1 << depth) // a.shape[0]
    return np.repeat(np.repeat(a, rep, 0), rep, 1) if rep > 1 else a


def node_height_bounds(
    grid: np.ndarray, bound: list[np.ndarray]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per depth ``0..k-1``, ``(lo, hi)`` ``(2**d, 2**d)`` of each node of one block: the range
    of its 4 corners at level ``d`` ``∓`` its ``bound`` (the tiler's per-node error field: the
    largest vertical distance of a valid full-resolution sample from the node's quad, which
    lies between its corners), so every valid sample of the node's closed footprint lies in
    it, and so does any surface drawn from samples there. ``grid`` is the block's ``(2**R+1)²``
    level-``R`` grid; a node deeper than ``R`` takes its depth-``R`` ancestor's range (nothing
    finer is read). Non-finite corners or bounds give non-finite ranges (callers fall back)."""
    k = len(bound)
    g = np.asarray(grid, dtype=np.float64)
    rr = (g.shape[0] - 1).bit_length() - 1
    if g.shape != ((1 << rr) + 1,) * 2 or not 0 <= rr <= k:
        raise LayoutError(f"expected a (2**R+1)² grid with R <= {k}, got shape {g.shape}")
    los, his = [], []
    for d in range(k):
        a = min(d, rr)
        c = g[:: 1 << (rr - a), :: 1 << (rr - a)]
        q = (c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:])
        b = _per_node(bound[a], a)
        # the corners' min and max in the order a reduction over their stack takes (so NaN
        # and signed zeros come out as before), without the stack's copy
        lo = np.minimum(np.minimum(np.minimum(q[0], q[1]), q[2]), q[3]) - b
        hi = np.maximum(np.maximum(np.maximum(q[0], q[1]), q[2]), q[3]) + b
        rep = 1 << (d - a)
        los.append(np.repeat(np.repeat(lo, rep, 0), rep, 1) if rep > 1 else lo)
        his.append(np.repeat(np.repeat(hi, rep, 0), rep, 1) if rep > 1 else hi)
    return los, his


#: at most this many values, one reduction costs less than the halvings' several calls
SMALL_POOL = 1 << 14


def max_pool(a: np.ndarray, r: int) -> np.ndarray:
    """The max of square ``a`` over each ``r x r`` tile (``a``'s side a multiple of ``r``; for
    booleans: any).

    A power-of-two ``r`` pools in halvings, each the maximum of four strided views: the same
    values as ``a.reshape(n, r, n, r).max(axis=(1, 3))`` (a maximum is exact in any order) at a
    fraction of its time (a reduction over two short strided axes is ~15 ns a value)."""
    if r & (r - 1) or a.size <= SMALL_POOL:
        n = a.shape[0] // r
        return a.reshape(n, r, n, r).max(axis=(1, 3))
    while r > 1:
        a = np.maximum(
            np.maximum(a[0::2, 0::2], a[0::2, 1::2]), np.maximum(a[1::2, 0::2], a[1::2, 1::2])
        )
        r >>= 1
    return a if a.base is None else a.copy()
