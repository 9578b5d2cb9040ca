"""Numba kernels of :func:`render.select.select_patches` (imported by :mod:`render.select_kernels`):
one depth of the breadth-first walk in two calls — :func:`visit` (window rule, the
:class:`render.select.DiscCull` test, the surviving nodes' centres and patch errors) and
:func:`split` (the leaves and the children) — and :func:`qiu_rho`, Qiu's metric of the
surviving nodes' spheres. The float work is the reference's operations in the reference's
order on float64 (no fastmath), so the results are the same bits (tested)."""

from __future__ import annotations

import math

import numpy as np

from streamer._plan_nb import _qiu
from tiler.jit import cached_njit

# error_model="numpy": float division by 0 gives ±∞/NaN as in numpy (no ZeroDivisionError)
_jit = cached_njit(nogil=True, error_model="numpy")


@_jit
def edge_probe(fr0, fc0, span, e):
    """The finest-grid sample one step beyond the midpoint of edge ``e`` (0 top, 1 right,
    2 bottom, 3 left) of the node whose top-left finest sample is ``(fr0, fc0)`` and whose side
    is ``span`` samples: the probe that finds the neighbour across that edge."""
    mid = span >> 1
    if e == 0:
        return fr0 - 1, fc0 + mid
    if e == 1:
        return fr0 + mid, fc0 + span
    if e == 2:
        return fr0 + span, fc0 + mid
    return fr0 + mid, fc0 - 1


@_jit
def _fmin(a, b):
    """``np.minimum`` of two floats (NaN if either is NaN)."""
    if a <= b:
        return a
    if b < a:
        return b
    return a + b


@_jit
def visit(
    idx, rows, cols, inside, bx0, by1, sdx, sdy, size, use_win, win,
    cull, empty, o, px, py, ex, ey, ee_safe, ok, all_ok, ccw, half,
    arr, has_arr, slots,
):  # fmt: skip
    """The nodes of one depth that survive the window and disc tests, in order:
    ``(idx, rows, cols, inside, cx, cy, delta)``. ``sdx``/``sdy`` the node span times dx/dy,
    ``cull`` whether there is a polygon (``empty``: a degenerate one, which meets nothing; the
    rest :class:`DiscCull`'s fields), ``arr`` the patch table's depth array (``has_arr``
    False at full resolution: delta 0)."""
    n = idx.shape[0]
    o_idx = np.empty(n, np.int64)
    o_rows = np.empty(n, np.int64)
    o_cols = np.empty(n, np.int64)
    o_in = np.empty(n, np.bool_)
    o_cx = np.empty(n, np.float64)
    o_cy = np.empty(n, np.float64)
    o_d = np.empty(n, np.float64)
    ne = px.shape[0]
    r2 = half * half
    m = 0
    for i in range(n):
        b = idx[i]
        r, c = rows[i], cols[i]
        cx = bx0[b] + (np.float64(c) + 0.5) * sdx
        cy = by1[b] - (np.float64(r) + 0.5) * sdy
        if use_win and not (r * size < win[b, 2] - 1 and c * size < win[b, 3] - 1):
            continue
        ins = inside[i]
        if cull and not ins:
            if empty:
                continue
            axo = cx - o[0]
            ayo = cy - o[1]
            dist2 = math.inf
            first = True
            centre_in = True
            for j in range(ne):
                ax = axo - px[j]
                ay = ayo - py[j]
                t = (ax * ex[j] + ay * ey[j]) / ee_safe[j]
                if not all_ok and not ok[j]:
                    t = 0.0
                if t < 0.0:
                    t = 0.0
                elif t > 1.0:
                    t = 1.0
                dx = ax - t * ex[j]
                dy = ay - t * ey[j]
                d2 = dx * dx + dy * dy
                dist2 = d2 if first else _fmin(dist2, d2)
                first = False
                if not (ex[j] * ay - ey[j] * ax >= 0.0):
                    centre_in = False
            near = dist2 <= r2
            if ccw:
                if not (near or centre_in):
                    continue
                ins = centre_in and not near
            elif not near:
                continue
        o_idx[m] = b
        o_rows[m] = r
        o_cols[m] = c
        o_in[m] = ins
        o_cx[m] = cx
        o_cy[m] = cy
        o_d[m] = np.float64(arr[slots[b], r, c]) if has_arr else 0.0
        m += 1
    return o_idx[:m], o_rows[:m], o_cols[:m], o_in[:m], o_cx[:m], o_cy[:m], o_d[:m]


@_jit
def qiu_rho(delta, cx, cy, bz, zr, half, eye, fwd, focal, near):
    """:func:`streamer.lod.qiu_eq7` of the nodes' spheres (``render.node_boxes.node_rho``
    without boxes): centre ``(cx, cy, zmid)`` and radius ``hypot(half, zhalf)`` of the block
    ``bz`` ranges ``zr``."""
    n = delta.shape[0]
    out = np.empty(n, np.float64)
    ex, ey, ez = eye[0], eye[1], eye[2]
    f0, f1, f2 = fwd[0], fwd[1], fwd[2]
    for i in range(n):
        b = bz[i]
        zmid = 0.5 * (zr[b, 0] + zr[b, 1])
        zhalf = 0.5 * (zr[b, 1] - zr[b, 0])
        radius = math.hypot(half, zhalf)
        out[i] = _qiu(delta[i], cx[i] - ex, cy[i] - ey, zmid - ez, radius, f0, f1, f2, focal, near)
    return out


@_jit
def split(idx, rows, cols, inside, delta, rho, res, depth, top, tau, min_depth):
    """The leaves ``(idx, rows, cols, level, delta, rho)`` and children ``(idx, rows, cols,
    inside)`` of one depth's nodes, and the count of nodes that wanted to split (``top`` is
    ``depth + patch_log2``, below ``k``; a node splits where ``top < res`` of its block)."""
    n = idx.shape[0]
    n_split = 0
    n_want = 0
    for i in range(n):
        want = (not rho[i] <= tau) or depth < min_depth
        if want:
            n_want += 1
            if top < res[idx[i]]:
                n_split += 1
    nl = n - n_split
    l_idx = np.empty(nl, np.int64)
    l_rows = np.empty(nl, np.int64)
    l_cols = np.empty(nl, np.int64)
    l_lev = np.empty(nl, np.int64)
    l_d = np.empty(nl, np.float64)
    l_rho = np.empty(nl, np.float64)
    c_idx = np.empty(4 * n_split, np.int64)
    c_rows = np.empty(4 * n_split, np.int64)
    c_cols = np.empty(4 * n_split, np.int64)
    c_in = np.empty(4 * n_split, np.bool_)
    a = 0
    s = 0
    for i in range(n):
        b = idx[i]
        want = (not rho[i] <= tau) or depth < min_depth
        if want and top < res[b]:
            for q in range(4):
                c_idx[s] = b
                c_rows[s] = 2 * rows[i] + (q >> 1)
                c_cols[s] = 2 * cols[i] + (q & 1)
                c_in[s] = inside[i]
                s += 1
        else:
            l_idx[a] = b
            l_rows[a] = rows[i]
            l_cols[a] = cols[i]
            l_lev[a] = min(top, res[b])
            l_d[a] = delta[i]
            l_rho[a] = rho[i]
            a += 1
    return (l_idx, l_rows, l_cols, l_lev, l_d, l_rho), (c_idx, c_rows, c_cols, c_in), n_want


@_jit
def _lower(keys, x):
    """``np.searchsorted(keys, x)`` (side left) for a scalar ``x``."""
    lo, hi = 0, keys.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@_jit
def neighbours(sk, order, d, gr, gc, big, nr, nc, dd):
    """``render.select._neighbours``' ``(n, 4)`` leaf across each edge (N, E, S, W), -1 for
    none: ``sk`` the sorted leaf keys, ``order`` their leaves, ``gr``/``gc`` the leaves' global
    node row/column at their depth ``d``, ``dd`` the depths holding leaves (ascending); the
    deepest leaf holding the probe beyond the edge midpoint wins."""
    n = d.shape[0]
    out = np.full((n, 4), -1, np.int64)
    for i in range(n):
        sh = big - d[i]
        span = np.int64(1) << sh
        fr0 = gr[i] << sh
        fc0 = gc[i] << sh
        for e in range(4):
            fr, fc = edge_probe(fr0, fc0, span, e)
            if fr < 0 or fc < 0 or fr >= nr or fc >= nc:
                continue
            for j in range(dd.shape[0] - 1, -1, -1):
                s = big - dd[j]
                q = (dd[j] * nr + (fr >> s)) * nc + (fc >> s)
                pos = _lower(sk, q)
                if pos > n - 1:
                    pos = n - 1
                if sk[pos] == q:
                    out[i, e] = order[pos]
                    break
    return out


@_jit
def kim_rho(delta, cx, cy, bz, zr, half, eye, right, up, fwd, focal, w2, h2):
    """``render.strategies.chunk_tess.pure.kim_metric`` of the nodes' spheres (as
    :func:`qiu_rho`); ``w2``/``h2`` half the viewport."""
    n = delta.shape[0]
    out = np.empty(n, np.float64)
    e0, e1, e2 = eye[0], eye[1], eye[2]
    for i in range(n):
        b = bz[i]
        zmid = 0.5 * (zr[b, 0] + zr[b, 1])
        zhalf = 0.5 * (zr[b, 1] - zr[b, 0])
        rad = math.hypot(half, zhalf)
        d = delta[i]
        tx, ty, tz = e0 - cx[i], e1 - cy[i], e2 - zmid
        dist = math.sqrt(tx * tx + ty * ty + tz * tz)
        inside = dist <= rad
        s = rad / (1.0 if inside else dist)
        px, py, pz = cx[i] + tx * s, cy[i] + ty * s, zmid + tz * s
        rx, ry = px - e0, py - e1
        xs = np.empty(2)
        ys = np.empty(2)
        for j in range(2):
            z = pz if j == 0 else pz + d
            rz = z - e2
            depth = rx * fwd[0] + ry * fwd[1] + rz * fwd[2]
            f = focal / depth if depth > 0.0 else math.nan
            xr = rx * right[0] + ry * right[1] + rz * right[2]
            yu = rx * up[0] + ry * up[1] + rz * up[2]
            xs[j] = w2 + xr * f
            ys[j] = h2 - yu * f
        rho = math.hypot(xs[1] - xs[0], ys[1] - ys[0])
        if not math.isfinite(rho):
            rho = math.inf
        if d == 0.0:
            rho = 0.0
        elif inside:
            rho = math.inf
        out[i] = rho
    return out
