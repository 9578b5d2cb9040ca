"""Numba kernel of :meth:`streamer.levels.PatchErrorTable.needed_levels` for Qiu's metric
(imported by :mod:`streamer.levels` only when the compiled kernels are used): each block's
quadtree walked depth first instead of one numpy pass per depth, with :func:`streamer.lod.qiu_eq7`'s
operations in the reference's order on float64 (no fastmath), so the levels and screen errors
are the reference's, bit for bit (tested)."""

from __future__ import annotations

import math

import numpy as np

from tiler.jit import cached_njit

_jit = cached_njit(nogil=True, error_model="numpy")


@_jit
def _fmax(a, b):
    """``np.maximum`` of two floats (NaN if either is NaN)."""
    if a >= b:
        return a
    if b > a:
        return b
    return a + b


@_jit
def _qiu(d, x, y, z, radius, f0, f1, f2, focal, near):
    """``streamer.lod.qiu_eq7`` of one node (``x, y, z``: its centre minus the eye)."""
    h2 = x * x + y * y
    dist = math.sqrt(h2 + z * z)
    if dist == 0.0:
        cos_t = 1.0
        cos_b = 1.0
    else:
        inv = 1.0 / dist
        cos_t = math.sqrt(h2) * inv
        cos_b = (x * f0 + y * f1 + z * f2) * inv
    s = 1.0 - cos_b * cos_b
    if s < 0.0:
        s = 0.0
    elif s > 1.0:
        s = 1.0
    sin_b = math.sqrt(s)
    if cos_b < 0.0:
        sin_b = 1.0
    rho = focal * d * cos_t / (_fmax(dist, near) * (1.0 + sin_b))
    if dist <= radius:
        rho = math.inf
    if d == 0.0:
        rho = 0.0
    return rho


@_jit
def qiu_levels(
    arrays, slots, bx0, by1, zr, halfdiag, k, p, tau, span_dx, span_dy, eye, fwd, focal, near,
    levels, rho_max,
):  # fmt: skip
    """Fill ``levels`` and ``rho_max`` (both ``(m,)``, given filled with the start values) as
    ``needed_levels`` does with ``metric="qiu"``: ``arrays`` the table's per-depth arrays (a
    tuple), ``halfdiag``/``span_dx``/``span_dy`` per depth, ``zr`` the blocks' z ranges."""
    depths = len(arrays)
    m = slots.shape[0]
    ex, ey, ez = eye[0], eye[1], eye[2]
    f0, f1, f2 = fwd[0], fwd[1], fwd[2]
    cap = 3 * depths + 4
    sd = np.empty(cap, np.int64)
    sr = np.empty(cap, np.int64)
    sc = np.empty(cap, np.int64)
    for b in range(m):
        zmid = 0.5 * (zr[b, 0] + zr[b, 1])
        zhalf = 0.5 * (zr[b, 1] - zr[b, 0])
        top = 0
        sd[0], sr[0], sc[0] = 0, 0, 0
        top = 1
        deepest = 0
        bottom_split = False
        best = rho_max[b]
        while top > 0:
            top -= 1
            d, r, c = sd[top], sr[top], sc[top]
            if d > deepest:
                deepest = d
            delta = np.float64(arrays[d][slots[b], r, c])
            cx = bx0[b] + (np.float64(c) + 0.5) * span_dx[d]
            cy = by1[b] - (np.float64(r) + 0.5) * span_dy[d]
            radius = math.hypot(halfdiag[d], zhalf)
            rho = _qiu(delta, cx - ex, cy - ey, zmid - ez, radius, f0, f1, f2, focal, near)
            best = _fmax(best, rho if math.isfinite(rho) else 1e30)
            if not rho <= tau:
                if d + 1 == depths:
                    bottom_split = True
                else:
                    for q in range(4):
                        sd[top] = d + 1
                        sr[top] = 2 * r + (q >> 1)
                        sc[top] = 2 * c + (q & 1)
                        top += 1
        rho_max[b] = best
        levels[b] = k if bottom_split else deepest + p
