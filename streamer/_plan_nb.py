"""Numba kernels of a session's planning (imported by :mod:`streamer.levels` only when the
compiled kernels are used): :meth:`streamer.levels.PatchErrorTable.needed_levels` for Qiu's
metric (each block's quadtree walked depth first instead of one numpy pass per depth, with
:func:`streamer.lod.qiu_eq7`'s operations in the reference's order on float64, no fastmath) and
the rectangle half of :func:`streamer.frustum.blocks_meeting` (its separating-axis test per
block, the polygon's part computed by numpy as in the reference). Both give the reference's
results bit for bit (tested)."""

from __future__ import annotations

import math

import numpy as np

from tiler.jit import cached_njit

#: the GIL is kept: these kernels run 10-100 µs, and releasing the GIL for that long hands it to
#: a loader thread, which the caller then waits behind (up to the 5 ms switch interval) and
#: switches back from with cold caches (bench/session_update.py, 4 alternating pairs at load
#: 4-7: CPU p99 0.81-1.19 ms kept vs 0.98-1.23 released, max 2.0-20 vs 3.0-36 ms)
_jit = cached_njit(nogil=False, error_model="numpy")


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


@_jit
def blocks_meeting(
    r0, r1, c0, c1, x0, y0, step, dx, dy, o, pbox, normals, pmin, pmax, exists,
):  # fmt: skip
    """``(n, 2)`` blocks ``(br, bc)`` of rows ``r0..r1`` and columns ``c0..c1`` (row-major)
    whose bounds meet the polygon and that exist: ``frustum.blocks_meeting``'s test (``o`` the
    polygon's first vertex, ``pbox`` its x/y min/max relative to ``o``, ``normals`` its edge
    normals with the vertices' projections ``pmin``/``pmax`` on them; no normals: fewer than
    2 vertices)."""
    n = (r1 - r0 + 1) * (c1 - c0 + 1)
    out = np.empty((max(n, 0), 2), np.int64)
    m = 0
    wx = step * dx
    wy = step * dy
    for br in range(r0, r1 + 1):
        ymax = y0 - np.float64(br) * step * dy
        ymin = ymax - wy
        for bc in range(c0, c1 + 1):
            if not exists[br, bc]:
                continue
            xmin = x0 + np.float64(bc) * step * dx
            xmax = xmin + wx
            hit = (
                xmin - o[0] <= pbox[1]
                and xmax - o[0] >= pbox[0]
                and ymin - o[1] <= pbox[3]
                and ymax - o[1] >= pbox[2]
            )
            if hit:
                cx = ((xmin - o[0]) + (xmax - o[0])) * 0.5
                cy = ((ymin - o[1]) + (ymax - o[1])) * 0.5
                hx = (xmax - xmin) * 0.5
                hy = (ymax - ymin) * 0.5
                for j in range(normals.shape[0]):
                    c = cx * normals[j, 0] + cy * normals[j, 1]
                    r = hx * abs(normals[j, 0]) + hy * abs(normals[j, 1])
                    if not (c - r <= pmax[j] and c + r >= pmin[j]):
                        hit = False
                        break
            if hit:
                out[m, 0] = br
                out[m, 1] = bc
                m += 1
    return out[:m]


@_jit
def restrict_levels(rows, cols, lv, p, out):
    """:func:`streamer.restriction.restrict_levels` into ``out`` (the same least fixpoint,
    reached in place, row by row, instead of one whole-grid pass at a time)."""
    m = lv.shape[0]
    r0, r1, c0, c1 = rows[0], rows[0], cols[0], cols[0]
    lo = lv[0]
    for i in range(m):
        r0, r1 = min(r0, rows[i]), max(r1, rows[i])
        c0, c1 = min(c0, cols[i]), max(c1, cols[i])
        lo = min(lo, lv[i])
    absent = lo - p - 1
    g = np.full((r1 - r0 + 1, c1 - c0 + 1), absent, np.int64)
    for i in range(m):
        g[rows[i] - r0, cols[i] - c0] = lv[i]
    nr, nc = g.shape
    for _ in range(m):
        changed = False
        for r in range(nr):
            for c in range(nc):
                v = g[r, c]
                if v == absent:
                    continue
                best = v
                if r > 0 and g[r - 1, c] - p > best:
                    best = g[r - 1, c] - p
                if r + 1 < nr and g[r + 1, c] - p > best:
                    best = g[r + 1, c] - p
                if c > 0 and g[r, c - 1] - p > best:
                    best = g[r, c - 1] - p
                if c + 1 < nc and g[r, c + 1] - p > best:
                    best = g[r, c + 1] - p
                if best > v:
                    g[r, c] = best
                    changed = True
        if not changed:
            break
    for i in range(m):
        out[i] = g[rows[i] - r0, cols[i] - c0]
