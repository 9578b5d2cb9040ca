"""``seamless-patches``, the cached meshes (pure numpy): the north tile of every resolution and
the north-east strip of every ordered pair of resolutions, rotated by quarter turns."""

from __future__ import annotations

from functools import cache

import numpy as np

#: edge order N, E, S, W; neighbour offsets (row, col) across each edge
DIRS = ((-1, 0), (0, 1), (1, 0), (0, -1))


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
