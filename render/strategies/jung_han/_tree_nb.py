"""Numba kernel of ``jung-han``'s per-block tree (imported by
:mod:`render.strategies.jung_han._kernels_nb`): ``pure.BlockTree.build`` of a level grid in one
call — the per-vertex δ (``pure.vertex_deltas``) and, per depth, the index-ordered pyramids of
the largest ``|δ|`` and of the height range — with the numpy reference's values (the same
float64 operations in the same order; ``fmin``/``fmax`` ignore NaN as numpy's do)."""

from __future__ import annotations

import numpy as np

from render.strategies.jung_han._mesh_nb import _jit


@_jit
def _delta(g, vi, vj, ai, aj, bi, bj):
    """``pure.vertex_deltas``' value of vertex ``v`` between ``a`` and ``b``."""
    gv, ga, gb = g[vi, vj], g[ai, aj], g[bi, bj]
    okv, oka, okb = np.isfinite(gv), np.isfinite(ga), np.isfinite(gb)
    if okv and oka and okb:
        return 0.5 * (ga + gb) - gv
    if not (okv or oka or okb):
        return 0.0
    return np.inf


@_jit
def _fmin(a, b):
    """``np.fmin``: the other where one is NaN; the first of two equal values."""
    if a != a or b < a:
        return b
    return a


@_jit
def _fmax(a, b):
    """``np.fmax``."""
    if a != a or b > a:
        return b
    return a


@_jit
def build_tree(h, perm):
    """``(delta, dmax, zlo, zhi)`` of the ``(2**R+1)²`` float64 level grid ``h`` (NaN =
    masked): δ as float32 on the grid, and the pyramids of depths ``0 .. R-1`` concatenated,
    depth ``d`` at ``(4**d - 1) // 3`` in Jung & Han's index order (``perm``: per depth,
    likewise concatenated, the row-major grid position of each index,
    ``pure.index_positions``)."""
    n = h.shape[0]
    rr = 0
    while (1 << (rr + 1)) <= n - 1:
        rr += 1
    out = np.zeros((n, n))
    for lv in range(1, rr + 1):
        s = 1 << (rr - lv)
        t = 2 * s
        for i in range(0, n, t):  # horizontal-edge midpoints
            for j in range(s, n, t):
                out[i, j] = _delta(h, i, j, i, j - s, i, j + s)
        for i in range(s, n, t):  # vertical-edge midpoints
            for j in range(0, n, t):
                out[i, j] = _delta(h, i, j, i - s, j, i + s, j)
        for i in range(s, n, t):  # centres: the diagonal of their quadrant in the parent
            qi = (i - s) // t
            for j in range(s, n, t):
                if (qi & 1) ^ (((j - s) // t) & 1):
                    out[i, j] = _delta(h, i, j, i + s, j - s, i - s, j + s)  # sw-ne
                else:
                    out[i, j] = _delta(h, i, j, i - s, j - s, i + s, j + s)  # nw-se
    delta = np.empty((n, n), np.float32)
    for i in range(n):
        for j in range(n):
            delta[i, j] = np.float32(out[i, j])
    total = ((1 << (2 * rr)) - 1) // 3
    dmax = np.empty(total, np.float32)
    zlo = np.empty(total)
    zhi = np.empty(total)
    for d in range(rr - 1, -1, -1):
        step = 1 << (rr - d)
        half = step >> 1
        side = 1 << d
        at = ((1 << (2 * d)) - 1) // 3
        below = ((1 << (2 * (d + 1))) - 1) // 3
        for x in range(side * side):
            pos = perm[at + x]
            r, c = pos // side, pos % side
            ci, cj = half + r * step, half + c * step
            own = abs(delta[ci, cj])
            own = max(own, abs(delta[r * step, cj]))
            own = max(own, abs(delta[(r + 1) * step, cj]))
            own = max(own, abs(delta[ci, c * step]))
            own = max(own, abs(delta[ci, (c + 1) * step]))
            if d == rr - 1:  # the 3x3 samples of the node, row by row
                lo = h[2 * r, 2 * c]
                hi = lo
                for a in range(3):
                    for b in range(3):
                        if a or b:
                            lo = _fmin(lo, h[2 * r + a, 2 * c + b])
                            hi = _fmax(hi, h[2 * r + a, 2 * c + b])
                dmax[at + x] = own
            else:  # its four children, in index order
                ch = below + 4 * x
                lo, hi, m = zlo[ch], zhi[ch], dmax[ch]
                for q in range(1, 4):
                    lo = _fmin(lo, zlo[ch + q])
                    hi = _fmax(hi, zhi[ch + q])
                    m = max(m, dmax[ch + q])
                dmax[at + x] = max(own, m)
            zlo[at + x], zhi[at + x] = lo, hi
    return delta, dmax, zlo, zhi
