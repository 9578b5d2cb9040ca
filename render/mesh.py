"""Patch meshes and edge snapping (pure numpy, no GL): the CPU twin of the vertex shader.

A patch is a node of a block's quadtree drawn from one level: ``n = 2**cells_log2`` cells per
side, each cell ``spacing = 2**(k - level)`` samples. Cell ``(i, j)`` (column, row; rows grow
south) has corners ``a = (i, j)``, ``b = (i+1, j)``, ``c = (i, j+1)``, ``d = (i+1, j+1)`` and is
cut along the ``a-d`` diagonal into triangles ``(a, b, d)`` and ``(a, d, c)``; the GPU index
buffer and the CPU evaluation use exactly this split.

Edge snapping: edge ``e`` (0 north = row 0, 1 east = column n, 2 south = row n, 3 west =
column 0) with snap ``t > 0`` moves its vertices to the multiple of ``2**t`` at or below them
(``floor``), so they land on the vertices of a neighbour drawn ``2**t`` times coarser: the snapped
cells become degenerate triangles and fans, with no T-junction. Corners never move.
"""

from __future__ import annotations

from functools import cache

import numpy as np

NORTH, EAST, SOUTH, WEST = 0, 1, 2, 3


def grid_indices(cells: int) -> np.ndarray:
    """``(2 cells^2, 3)`` int32 triangles of a ``cells`` grid (vertex id ``j*(cells+1)+i``)."""
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="xy")
    n1 = cells + 1
    a = (j * n1 + i).ravel()
    b, c = a + 1, a + n1
    d = c + 1
    tri = np.stack([np.stack([a, b, d], 1), np.stack([a, d, c], 1)], 1)
    return tri.reshape(-1, 3).astype(np.int32)


def grid_vertices(cells: int) -> np.ndarray:
    """``((cells+1)^2, 2)`` int32 ``(i, j)`` vertex coordinates, row-major (``j`` slowest)."""
    j, i = np.mgrid[0 : cells + 1, 0 : cells + 1]
    return np.stack([i.ravel(), j.ravel()], 1).astype(np.int32)


def snap_vertices(ij: np.ndarray, cells: int, snaps: tuple[int, int, int, int]) -> np.ndarray:
    """Snapped ``(i, j)`` of vertices of a ``cells`` grid (the vertex shader's rule)."""
    i, j = ij[..., 0].copy(), ij[..., 1].copy()
    tn, te, ts, tw = (int(t) for t in snaps)
    on_n, on_s, on_w, on_e = j == 0, j == cells, i == 0, i == cells
    for on, t in ((on_n, tn), (on_s, ts)):
        if t > 0:
            i = np.where(on, (i >> t) << t, i)
    for on, t in ((on_w, tw), (on_e, te)):
        if t > 0:
            j = np.where(on, (j >> t) << t, j)
    return np.stack([i, j], -1)


def snapped_triangles(cells_log2: int, snaps: tuple[int, int, int, int]) -> np.ndarray:
    """``(m, 3, 2)`` int ``(i, j)`` of the non-degenerate triangles of a snapped patch."""
    n = 1 << cells_log2
    v = snap_vertices(grid_vertices(n), n, snaps)
    tri = v[grid_indices(n)]
    return tri[~_degenerate(tri)]


def _degenerate(tri: np.ndarray) -> np.ndarray:
    """True for triangles with zero area (two coinciding vertices or collinear)."""
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    return (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) == 0


@cache
def triangle_count(cells_log2: int, snaps: tuple[int, int, int, int]) -> int:
    """Non-degenerate triangles of a patch with these cells and edge snaps."""
    return int(len(snapped_triangles(cells_log2, snaps)))


def triangle_counts(cells_log2: np.ndarray, snaps: np.ndarray) -> np.ndarray:
    """Vectorised :func:`triangle_count` over patches (``snaps`` is ``(m, 4)``)."""
    if len(cells_log2) == 0:
        return np.zeros(0, dtype=np.int64)
    keys = np.concatenate([np.asarray(cells_log2)[:, None], np.asarray(snaps)], 1).astype(np.int64)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    counts = np.array([triangle_count(int(u[0]), tuple(int(x) for x in u[1:])) for u in uniq])
    return counts[inv.ravel()]


def edge_strip_triangles(cells_log2: int, snaps: tuple[int, int, int, int]) -> np.ndarray:
    """``(m, 3, 2)`` non-degenerate snapped triangles of the cells along the snapped edges."""
    n = 1 << cells_log2
    v = snap_vertices(grid_vertices(n), n, snaps)
    idx = grid_indices(n)
    cell = np.repeat(np.arange(n * n), 2)
    ci, cj = cell % n, cell // n
    keep = np.zeros(len(idx), dtype=bool)
    for e, t in enumerate(snaps):
        if t > 0:
            keep |= (cj == 0, ci == n - 1, cj == n - 1, ci == 0)[e]
    tri = v[idx[keep]]
    return tri[~_degenerate(tri)]
