"""Numba kernels for ``geometry-splitting``'s per-block tree (imported lazily by
:mod:`render.strategies.geometry_splitting.kernels`): :func:`quad_errors_depth` repeats
:func:`render.strategies.geometry_splitting.pure.quad_errors`' float64 arithmetic operation by
operation, in the same order (no fastmath: no contraction into fused multiply-adds), and
:func:`corner_ranges` ``stored_tree``'s corner ranges, so their values are the reference's bit
for bit (tested)."""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["corner_ranges", "quad_errors_depth"]


@numba.njit(cache=True, nogil=True)
def _edge_max(vals, ok, start, end, s):
    """The largest distance of the valid ``vals`` (``s + 1`` samples along a block edge) from
    the segment ``start``-``end``."""
    out = 0.0
    for q in range(s + 1):
        if ok[q]:
            t = q / s
            e = abs(vals[q] - (start * (1 - t) + end * t))
            if e > out:
                out = e
    return out


@numba.njit(cache=True, nogil=True)
def quad_errors_depth(h, ok, d, out):
    """``quad_errors(h, ok, [d])[d]`` into ``out`` (float64 ``(2**d, 2**d)``): per node the
    largest vertical distance of a valid sample (its own last row and column included) from
    its quad cut along the a-d diagonal. ``h`` float64 and ``ok`` bool, ``(2**k+1)²``."""
    n = h.shape[0] - 1
    m = 1 << d
    s = n >> d
    ba = np.empty(m)
    ca = np.empty(m)
    aa = np.empty(m)
    qq = np.empty(m)
    top = np.zeros((m, m))  # per node: the max over its first sample row
    left = np.zeros((m, m))  # per node: the max over its first sample column
    node = np.zeros((m, m))
    for i in range(m):
        r0 = i * s
        for j in range(m):
            a = h[r0, j * s]
            b = h[r0, j * s + s]
            c = h[r0 + s, j * s]
            dd = h[r0 + s, j * s + s]
            aa[j] = a
            ba[j] = b - a
            ca[j] = c - a
            qq[j] = b + c - a - dd
        for iv in range(s):
            r = r0 + iv
            v = iv / s
            for j in range(m):
                a = aa[j]
                bj = ba[j]
                cj = ca[j]
                qj = qq[j]
                mx = node[i, j]
                lf = left[i, j]
                tp = 0.0
                for iu in range(s):
                    col = j * s + iu
                    if ok[r, col]:
                        u = iu / s
                        e = h[r, col] - a
                        e = e - u * bj
                        e = e - v * cj
                        e = e + (u if u < v else v) * qj
                        e = abs(e)
                    else:
                        e = 0.0
                    if e > mx:
                        mx = e
                    if iu == 0 and e > lf:
                        lf = e
                    if e > tp:
                        tp = e
                node[i, j] = mx
                left[i, j] = lf
                if iv == 0:
                    top[i, j] = tp
    for i in range(m):
        for j in range(m):
            if i < m - 1:
                south = top[i + 1, j]
            else:  # the block's last row: along the bottom edge c-d
                row = h[n, j * s : j * s + s + 1]
                south = _edge_max(row, ok[n, j * s : j * s + s + 1], row[0], row[s], s)
            if j < m - 1:
                east = left[i, j + 1]
            else:  # the block's last column: along the right edge b-d
                col = h[i * s : i * s + s + 1, n]
                east = _edge_max(col, ok[i * s : i * s + s + 1, n], col[0], col[s], s)
            se = south if south > east else east
            out[i, j] = node[i, j] if node[i, j] > se else se


@numba.njit(cache=True, nogil=True)
def corner_ranges(g, step, delta, lo, hi):
    """``stored_tree``'s height ranges at one depth before rounding, into ``lo`` and ``hi``
    (float64 ``(m, m)``): per node the min (max) of its 4 corners in ``g`` (float64, corners
    ``step`` samples apart) minus (plus) ``delta``. ``np.minimum``/``np.maximum``'s choice
    among equal values (the second: -0.0 against 0.0) is kept, so the values are bit for bit
    the numpy reference's."""
    m = lo.shape[0]
    for i in range(m):
        r0 = i * step
        r1 = r0 + step
        for j in range(m):
            c0 = j * step
            c1 = c0 + step
            c00 = g[r0, c0]
            c01 = g[r0, c1]
            c10 = g[r1, c0]
            c11 = g[r1, c1]
            a = c00 if c00 < c01 else c01
            b = c10 if c10 < c11 else c11
            lo[i, j] = (a if a < b else b) - delta[i, j]
            a = c00 if c00 > c01 else c01
            b = c10 if c10 > c11 else c11
            hi[i, j] = (a if a > b else b) + delta[i, j]
