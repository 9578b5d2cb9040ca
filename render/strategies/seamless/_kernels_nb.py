"""Numba kernels of ``seamless-patches``' selection (re-exported by :mod:`._resolve_nb`, the
module :mod:`.kernels` loads): the per-depth edge ε of ``SelectionFrame.epsilon`` (with its
``node_delta`` look-ups), the frustum disc test of ``SelectionFrame.visible``, one depth of the
traversal and the shared-edge grouping of ``_edge_groups``, each giving exactly the numpy
reference's output. The float work is the reference's operations in the reference's order on
float64 (no fastmath), so the results are the same bits."""

from __future__ import annotations

import math

import numpy as np

from tiler.jit import cached_njit

# error_model="numpy": float division by 0 gives ±∞/NaN as in numpy (no ZeroDivisionError)
_jit = cached_njit(nogil=True, error_model="numpy")

# DIRS of meshes.py: N, E, S, W as (row, col) steps
_DR = (-1, 0, 1, 0)
_DC = (0, 1, 0, -1)


@_jit
def _fmax(a, b):
    """``np.maximum`` of two floats (NaN if either is NaN)."""
    if a >= b:
        return a
    if b > a:
        return b
    return a + b


@_jit
def _fmin(a, b):
    """``np.minimum`` of two floats (NaN if either is NaN)."""
    if a <= b:
        return a
    if b < a:
        return b
    return a + b


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
def _node_delta(d, gr, gc, grows, gcols, bkeys, border, slots, arr, has_arr):
    """``SelectionFrame.node_delta`` of one node: its stored error, -1 outside the drawn blocks."""
    m = bkeys.shape[0]
    if m == 0 or gr < 0 or gc < 0 or gr >= (grows << d) or gc >= (gcols << d):
        return -1.0
    key = (gr >> d) * gcols + (gc >> d)
    pos = min(_lower(bkeys, key), m - 1)
    if bkeys[pos] != key:
        return -1.0
    if not has_arr:  # full resolution at this depth: the table's delta is 0
        return 0.0
    mask = (1 << d) - 1
    return np.float64(arr[slots[border[pos]], gr & mask, gc & mask])


@_jit
def epsilon(
    idx, rows, cols, d, k, blk, bkeys, border, slots, arr, has_arr, grows, gcols, zr,
    x0, y0, dx, dy, ex, ey, ez, focal, tau, c, paper, paper_rho,
):  # fmt: skip
    """``SelectionFrame.epsilon`` without the spike guard: ``(n, 4)`` ε of the nodes' edges N, E,
    S, W (``arr`` = the table's depth-``d`` array, ``has_arr`` False where the table has none;
    ``paper``: ρ is ``paper_rho``, ∞ beside a node of infinite δ)."""
    n = idx.shape[0]
    out = np.zeros((n, 4))
    size = 1 << (k - d)
    nr_ = grows << d
    nc_ = gcols << d
    cc = np.float64(1 << c)
    for i in range(n):
        br = blk[idx[i], 0]
        bc = blk[idx[i], 1]
        gr = (br << d) + rows[i]
        gc = (bc << d) + cols[i]
        own = _node_delta(d, gr, gc, grows, gcols, bkeys, border, slots, arr, has_arr)
        zo0 = zr[br, bc, 0]
        zo1 = zr[br, bc, 1]
        for e in range(4):
            nr = gr + _DR[e]
            nc = gc + _DC[e]
            inb = nr >= 0 and nr < nr_ and nc >= 0 and nc < nc_
            nrc = min(max(nr, 0), nr_ - 1)
            ncc = min(max(nc, 0), nc_ - 1)
            other = _node_delta(d, nr, nc, grows, gcols, bkeys, border, slots, arr, has_arr)
            delta = _fmax(own, other)
            if inb:
                zlo = _fmin(zo0, zr[nrc >> d, ncc >> d, 0])
                zhi = _fmax(zo1, zr[nrc >> d, ncc >> d, 1])
            else:
                zlo = zo0
                zhi = zo1
            if e == 0:
                r0, c0, r1, c1 = gr, gc, gr, gc + 1
            elif e == 1:
                r0, c0, r1, c1 = gr, gc + 1, gr + 1, gc + 1
            elif e == 2:
                r0, c0, r1, c1 = gr + 1, gc, gr + 1, gc + 1
            else:
                r0, c0, r1, c1 = gr, gc, gr + 1, gc
            xa = x0 + np.float64(c0 * size) * dx
            ya = y0 - np.float64(r0 * size) * dy
            xb = x0 + np.float64(c1 * size) * dx
            yb = y0 - np.float64(r1 * size) * dy
            hx = _fmax(_fmax(_fmin(xa, xb) - ex, 0.0), ex - _fmax(xa, xb))
            hy = _fmax(_fmax(_fmin(ya, yb) - ey, 0.0), ey - _fmax(ya, yb))
            v = _fmax(_fmax(ez - zhi, zlo - ez), 0.0)
            dist = math.sqrt(hx * hx + hy * hy + v * v)
            length = math.hypot(xb - xa, yb - ya)
            if paper:
                rho = math.inf if math.isinf(delta) else paper_rho
            else:
                num = 2.0 * focal * _fmax(delta, 0.0)
                den = tau * cc * length
                rho = 0.0 if num == 0.0 else num / den
                if math.isnan(rho):
                    rho = math.inf
            if rho == 0.0:
                eps = 0.0
            else:
                eps = rho * length / dist
                if math.isnan(eps):
                    eps = math.inf
            out[i, e] = eps
    return out


@_jit
def edge_groups(d, gr, gc, depths, order, sk, nr, nc):
    """``_edge_groups`` given its sorted keys ``sk`` (order ``order``) and grid sizes
    ``nr``/``nc``; ``depths`` = ``np.unique(d)`` (ascending)."""
    n = d.shape[0]
    out = np.empty((n, 4), np.int64)
    for i in range(n):
        for e in range(4):
            own = 4 * i + e
            r = gr[i] + _DR[e]
            c = gc[i] + _DC[e]
            inside = r >= 0 and c >= 0
            r = max(r, 0)
            c = max(c, 0)
            best = -1
            best_d = -1
            if inside:
                for dd in depths:
                    if dd > d[i]:
                        break
                    shift = d[i] - dd
                    q = (dd * nr + (r >> shift)) * nc + (c >> shift)
                    pos = min(_lower(sk, q), n - 1)
                    if sk[pos] == q and dd > best_d:
                        best = order[pos]
                        best_d = dd
            j = max(best, 0) * 4 + (e + 2) % 4
            if best_d == d[i]:
                out[i, e] = min(own, j)
            elif best >= 0:
                out[i, e] = j
            else:
                out[i, e] = own
    return out


@_jit
def disc_meets(idx, rows, cols, blk, x0, y0, step, dx, dy, s_dx, s_dy, radius, cull):
    """``DiscCull(poly)(cx, cy, radius)[0]`` of the nodes' centres (``SelectionFrame.visible``'s
    ``node_centres_at`` arithmetic): ``cull`` = ``(o, px, py, ex, ey, ee_safe, ok, all_ok, ccw)``
    of the :class:`render.select.DiscCull`."""
    o, px, py, ex, ey, ee_safe, ok, all_ok, ccw = cull
    n = idx.shape[0]
    out = np.zeros(n, np.bool_)
    r2 = radius * radius
    for i in range(n):
        xmin = x0 + np.float64(blk[idx[i], 1]) * step * dx
        ymax = y0 - np.float64(blk[idx[i], 0]) * step * dy
        cx = xmin + (np.float64(cols[i]) + 0.5) * s_dx
        cy = ymax - (np.float64(rows[i]) + 0.5) * s_dy
        dist2 = math.inf
        inside = True
        for j in range(px.shape[0]):
            ax = (cx - o[0]) - px[j]
            ay = (cy - o[1]) - py[j]
            t = (ax * ex[j] + ay * ey[j]) / ee_safe[j]
            if not all_ok and not ok[j]:
                t = 0.0
            if t < 0.0:
                t = 0.0
            elif t > 1.0:
                t = 1.0
            ddx = ax - t * ex[j]
            ddy = ay - t * ey[j]
            d2 = ddx * ddx + ddy * ddy
            if d2 < dist2:
                dist2 = d2
            if not ex[j] * ay - ey[j] * ax >= 0.0:
                inside = False
        out[i] = dist2 <= r2 or (ccw and inside)
    return out


@_jit
def traverse_depth(
    idx, rows, cols, d, k, c, use_win, win_r, win_c, cull_mode, cull_geo, cull, eps_args,
    dmax, cap,
):  # fmt: skip
    """One depth of ``_traverse`` without the spike guard: ``SelectionFrame.visible`` (window rule,
    then :func:`disc_meets` where ``cull_mode`` is 1, nothing meets where it is 2: an empty hull),
    :func:`epsilon` of the visible nodes, the split rule and the children. Returns the visible
    nodes' leaves ``(idx, rows, cols, eps)``, the children ``(idx, rows, cols)``, the clamped
    count and whether any node was visible. ``cull_geo`` = ``disc_meets``' ``(x0, y0, step, dx,
    dy, s_dx, s_dy, radius)``, ``eps_args`` = :func:`epsilon`'s arguments after ``d``."""
    n = idx.shape[0]
    size = 1 << (k - d)
    keep = np.ones(n, np.bool_)
    if use_win:
        for i in range(n):
            keep[i] = rows[i] * size < win_r[idx[i]] and cols[i] * size < win_c[idx[i]]
    if cull_mode == 2:
        keep[:] = False
    elif cull_mode == 1:
        blk = eps_args[1]
        x0, y0, step, dx, dy, s_dx, s_dy, radius = cull_geo
        keep &= disc_meets(idx, rows, cols, blk, x0, y0, step, dx, dy, s_dx, s_dy, radius, cull)
    vi = idx[keep]
    vr = rows[keep]
    vc = cols[keep]
    m = vi.shape[0]
    (
        kk, blk, bkeys, border, slots, arr, has_arr, grows, gcols, zr,
        x0, y0, dx, dy, ex, ey, ez, focal, tau, cc, paper, paper_rho,
    ) = eps_args  # fmt: skip
    eps = epsilon(
        vi, vr, vc, d, kk, blk, bkeys, border, slots, arr, has_arr, grows, gcols, zr,
        x0, y0, dx, dy, ex, ey, ez, focal, tau, cc, paper, paper_rho,
    )  # fmt: skip
    split = np.zeros(m, np.bool_)
    clamped = 0
    n_split = 0
    for i in range(m):
        want = False
        for e in range(4):
            if eps[i, e] > 1.0:
                want = True
        can = d + 1 <= dmax[vi[i]] and d + c < cap[vi[i]]
        split[i] = want and can
        if split[i]:
            n_split += 1
        elif want and d < k - c:
            clamped += 1
    leaf = ~split
    ci = np.empty(4 * n_split, np.int64)
    cr = np.empty(4 * n_split, np.int64)
    cc2 = np.empty(4 * n_split, np.int64)
    s = 0
    for i in range(m):
        if split[i]:
            for q in range(4):
                ci[s] = vi[i]
                cr[s] = 2 * vr[i] + (q >> 1)
                cc2[s] = 2 * vc[i] + (q & 1)
                s += 1
    return (vi[leaf], vr[leaf], vc[leaf], eps[leaf]), (ci, cr, cc2), clamped, m > 0
