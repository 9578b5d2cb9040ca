"""Numba kernels of ``jung-han``'s per-frame selection (imported lazily by
:mod:`render.strategies.jung_han.kernels`; the numpy code in ``selection.py`` / ``pure.py`` is
the reference).

:func:`traverse` is ``JungHanSelector._traverse`` in one compiled pass: the same top-down
breadth-first traversal (hull tests, pruning bound, leaves), the same bottom-up pass (12 flags,
both-triangles rule, collapse) and the triangles, nodes and flags in the same order. Every
operation repeats the numpy expression in the same order and precision, except the camera
transform: numpy's ``rel @ basis.T`` goes through BLAS, whose rounding (FMA, blocking) depends on
the batch size, so camera coordinates may differ from the reference's in the last bit; a result
can only change where a ``δ_s`` or a bound lies within a few ulps of τ (the tests compare both
paths exactly on several scenes). No fastmath (NaN and ∞ are meaningful here).
"""

from __future__ import annotations

import logging
import math
import os
import tempfile

import numba
import numpy as np

from render.strategies.jung_han.pure import EDGE_QUADS, FAN_EDGE, FAN_QUAD, OWN, TEMPLATE

log = logging.getLogger(__name__)
# error_model="numpy": float division by 0 gives ±∞/NaN as in numpy (no ZeroDivisionError)
_OPTS = {"nogil": True, "error_model": "numpy"}
_OWN = OWN.astype(np.int64)
_EQ = EDGE_QUADS.astype(np.int64)
_FQ = FAN_QUAD.astype(np.int64)
_FE = FAN_EDGE.astype(np.int64)
_TEMPLATE = TEMPLATE.astype(np.int64)


def _jit(fn):
    """``njit(cache=True)``; if no cache directory is writable, a per-user temp one, else none
    (as :func:`tiler._kernels_nb._jit`, without its fastmath flags)."""
    try:
        return numba.njit(cache=True, **_OPTS)(fn)
    except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
        fallback = os.path.join(tempfile.gettempdir(), f"terrastream-numba-{os.getuid()}")
        try:
            os.makedirs(fallback, exist_ok=True)
            numba.config.CACHE_DIR = fallback
            return numba.njit(cache=True, **_OPTS)(fn)
        except (OSError, RuntimeError):
            log.warning("numba cannot cache compiled kernels (%s); compiling in memory", exc)
            return numba.njit(cache=False, **_OPTS)(fn)


@_jit
def _cam(basis, eye, x, y, z):
    rx, ry, rz = x - eye[0], y - eye[1], z - eye[2]
    c0 = rx * basis[0, 0] + ry * basis[0, 1] + rz * basis[0, 2]
    c1 = rx * basis[1, 0] + ry * basis[1, 1] + rz * basis[1, 2]
    c2 = rx * basis[2, 0] + ry * basis[2, 1] + rz * basis[2, 2]
    return c0, c1, c2


@_jit
def _project(basis, eye, focal, vw, vh, x, y, z):
    c0, c1, c2 = _cam(basis, eye, x, y, z)
    s = focal / c2 if c2 > 0.0 else np.nan
    return vw / 2.0 + c0 * s, vh / 2.0 - c1 * s


@_jit
def _vertex_error(basis, eye, focal, vw, vh, d, x, y, h):
    """``vertex_errors`` of one vertex (``exact_projected``, 0 for δ = 0, ∞ if undefined)."""
    if d == 0.0:
        return 0.0
    x0, y0 = _project(basis, eye, focal, vw, vh, x, y, h)
    x1, y1 = _project(basis, eye, focal, vw, vh, x, y, h + d)
    rho = math.hypot(x1 - x0, y1 - y0)
    return rho if math.isfinite(rho) else np.inf


@_jit
def _own_error(
    nd, j, v, size, half, k, lev, hoff, r0, c0, hh, dl,
    basis, eye, focal, vw, vh, x0, y0, dx, dy,
):  # fmt: skip
    """δ_s of own vertex ``v`` (C, T, B, L, R) of node ``j`` (``JungHanSelector._own``)."""
    s = nd[j, 0]
    sh = k - lev[s]
    lr = nd[j, 2] * size + _OWN[v, 1] * half
    lc = nd[j, 3] * size + _OWN[v, 0] * half
    flat = hoff[s] + (lr >> sh) * ((1 << lev[s]) + 1) + (lc >> sh)
    x = x0 + float(c0[s] + lc) * dx
    y = y0 - float(r0[s] + lr) * dy
    return _vertex_error(basis, eye, focal, vw, vh, float(dl[flat]), x, y, hh[flat])


@_jit
def _nanmax(a, b):
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@_jit
def _nanmin(a, b):
    if a != a or b != b:
        return np.nan
    return a if a <= b else b


@_jit
def _bound(basis, eye, focal, dmax, xmin, xmax, ymin, ymax, zlo, zhi):
    """``projected_bound`` of one box."""
    u0, u1, u2 = basis[0, 2], basis[1, 2], basis[2, 2]
    zmin = np.inf
    gain = -np.inf
    for i in range(8):
        x = xmax if (i >> 2) & 1 else xmin
        y = ymax if (i >> 1) & 1 else ymin
        z = zhi if i & 1 else zlo
        c0, c1, c2 = _cam(basis, eye, x, y, z)
        zmin = _nanmin(zmin, c2) if i else c2
        qx, qy = c0 / c2, c1 / c2
        g = math.hypot(u0 - qx * u2, u1 - qy * u2)
        gain = _nanmax(gain, g) if i else g
    b = focal * dmax * gain / zmin
    if not zmin > 0.0:
        b = np.inf
    if dmax == 0.0:
        b = 0.0
    return b * (1.0 + 1e-9) + 1e-9


@_jit
def _meets(o, pmin_x, pmax_x, pmin_y, pmax_y, normals, pmin, pmax, xmin, ymin, xmax, ymax):
    """``polygon_meets_rects`` of one rectangle (SAT; per-axis extents precomputed)."""
    if not (
        (xmin - o[0] <= pmax_x)
        and (xmax - o[0] >= pmin_x)
        and (ymin - o[1] <= pmax_y)
        and (ymax - o[1] >= pmin_y)
    ):
        return False
    cx = ((xmin - o[0]) + (xmax - o[0])) * 0.5
    cy = ((ymin - o[1]) + (ymax - o[1])) * 0.5
    hx = (xmax - xmin) * 0.5
    hy = (ymax - ymin) * 0.5
    for i in range(normals.shape[0]):
        c = cx * normals[i, 0] + cy * normals[i, 1]
        r = hx * abs(normals[i, 0]) + hy * abs(normals[i, 1])
        if not ((c - r <= pmax[i]) and (c + r >= pmin[i])):
            return False
    return True


@_jit
def _inside(o, q, e, xmin, ymin, xmax, ymax):
    """``corners_inside`` of one rectangle (``q``/``e``: polygon minus ``o`` and its edges)."""
    if q.shape[0] < 3:
        return False
    for c in range(4):
        x = xmin if c == 0 or c == 3 else xmax
        y = ymin if c < 2 else ymax
        for i in range(q.shape[0]):
            dx = (x - o[0]) - q[i, 0]
            dy = (y - o[1]) - q[i, 1]
            if not (e[i, 0] * dy - e[i, 1] * dx >= 0.0):
                return False
    return True


@_jit
def _grow2(a):
    out = np.empty((2 * a.shape[0], a.shape[1]), a.dtype)
    out[: a.shape[0]] = a
    return out


@_jit
def _grow1(a):
    out = np.zeros(2 * a.shape[0], a.dtype)
    out[: a.shape[0]] = a
    return out


@_jit
def traverse(
    hh, dl, dmx, zlo, zhi, hoff, poff, lev, r0, c0, roots, root_inside,
    o, pext, normals, pmin, pmax, q, e,
    basis, eye, focal, vw, vh, tau, x0, y0, dx, dy, k, prune, culled_collapse,
):  # fmt: skip
    """The pruned top-down + bottom-up pass of one frame: ``(tri, tslot, tlev, nodes, flags,
    clamped, evaluated)`` in the numpy reference's order (see the module notes)."""
    cap = max(64, 4 * roots.shape[0])
    nd = np.empty((cap, 8), np.int64)  # slot, idx, row, col, inside, parent, quad, depth
    pr = np.zeros(cap, np.bool_)  # pruned
    nr = roots.shape[0]
    for i in range(nr):
        nd[i, 0], nd[i, 1], nd[i, 2], nd[i, 3] = roots[i], 0, 0, 0
        nd[i, 4], nd[i, 5], nd[i, 6], nd[i, 7] = root_inside[i], -1, -1, 0
    starts = [0]
    lo, hi, d = 0, nr, 0
    while hi > lo:
        size = 1 << (k - d)
        half = size >> 1
        n_new = hi
        for j in range(lo, hi):
            s = nd[j, 0]
            leaf = lev[s] - 1 == d
            if prune and d >= 1 and (nd[j, 4] or culled_collapse):
                ii = poff[s] + ((1 << (2 * d)) - 1) // 3 + nd[j, 1]
                xmin = x0 + float(c0[s] + nd[j, 3] * size) * dx
                ymax = y0 - float(r0[s] + nd[j, 2] * size) * dy
                b = _bound(
                    basis, eye, focal, float(dmx[ii]), xmin, xmin + size * dx,
                    ymax - size * dy, ymax, zlo[ii], zhi[ii],
                )  # fmt: skip
                pr[j] = b < tau
            if pr[j] or leaf:
                continue
            for qd in range(4):
                row = 2 * nd[j, 2] + 1 - (qd >> 1)
                col = 2 * nd[j, 3] + (qd & 1)
                ins = nd[j, 4] != 0
                hit = ins
                if not ins:
                    xmin = x0 + float(c0[s] + col * half) * dx
                    ymax = y0 - float(r0[s] + row * half) * dy
                    xmax, ymin = xmin + half * dx, ymax - half * dy
                    hit = _meets(
                        o, pext[0], pext[1], pext[2], pext[3], normals, pmin, pmax,
                        xmin, ymin, xmax, ymax,
                    )  # fmt: skip
                    ins = hit and _inside(o, q, e, xmin, ymin, xmax, ymax)
                if not hit:
                    continue
                if n_new >= nd.shape[0]:
                    nd = _grow2(nd)
                    pr = _grow1(pr)
                nd[n_new, 0], nd[n_new, 1] = s, 4 * nd[j, 1] + qd
                nd[n_new, 2], nd[n_new, 3], nd[n_new, 4] = row, col, ins
                nd[n_new, 5], nd[n_new, 6], nd[n_new, 7] = j, qd, d + 1
                pr[n_new] = False
                n_new += 1
        lo, hi = hi, n_new
        if hi > lo:
            starts.append(lo)
            d += 1
    total = hi
    starts.append(total)
    cm = np.zeros((total, 4), np.int8)
    state = np.zeros(total, np.int8)
    bits = np.zeros(total, np.int64)
    evaluated = 0
    clamped = 0
    for dd_ in range(len(starts) - 2, -1, -1):
        size = 1 << (k - dd_)
        half = size >> 1
        for j in range(starts[dd_], starts[dd_ + 1]):
            s = nd[j, 0]
            leaf = lev[s] - 1 == dd_
            present = 0  # bit q: quadrant q present / culled
            culled = 0
            for qd in range(4):
                cu = (not leaf) and cm[j, qd] == 0
                if cu:
                    culled |= 1 << qd
                if leaf or cm[j, qd] == 2 or (cu and culled_collapse):
                    present |= 1 << qd
            if pr[j]:
                st = 2
            else:
                evaluated += 1
                # a vertex's δ_s is only computed where the decision reads it (the edge
                # midpoint: both triangles present; the centre: every edge removed, d >= 1)
                allrem = True
                fl = 0
                for ed in range(4):
                    both = (present >> _EQ[ed, 0]) & (present >> _EQ[ed, 1]) & 1
                    rem = both == 1 and _own_error(
                        nd, j, 1 + ed, size, half, k, lev, hoff, r0, c0, hh, dl,
                        basis, eye, focal, vw, vh, x0, y0, dx, dy,
                    ) < tau  # fmt: skip
                    allrem = allrem and rem
                    if rem:
                        fl |= 1 << (8 + ed)
                st = 1
                if dd_ >= 1 and allrem:
                    e0 = _own_error(
                        nd, j, 0, size, half, k, lev, hoff, r0, c0, hh, dl,
                        basis, eye, focal, vw, vh, x0, y0, dx, dy,
                    )  # fmt: skip
                    if e0 < tau:
                        st = 2
                if st == 1:
                    for t in range(8):
                        qd = _FQ[t]
                        pq, cq = (present >> qd) & 1, (culled >> qd) & 1
                        if pq and not (fl >> (8 + _FE[t])) & 1 and not cq:
                            fl |= 1 << t
                    bits[j] = fl
                    if fl != 0 and leaf and lev[s] < k:
                        clamped += 1
            state[j] = st
            if nd[j, 5] >= 0:
                cm[nd[j, 5], nd[j, 6]] = st
    ntri = 0
    nnode = 0
    for j in range(total):
        if bits[j] != 0:
            nnode += 1
            for t in range(12):
                ntri += (bits[j] >> t) & 1
    tri = np.empty((ntri, 3, 2), np.int64)
    tslot = np.empty(ntri, np.int64)
    tlev = np.empty(ntri, np.int64)
    nodes = np.empty((nnode, 3), np.int64)
    flags = np.empty(nnode, np.int64)
    it = 0
    ino = 0
    for dd_ in range(len(starts) - 2, -1, -1):
        size = 1 << (k - dd_)
        half = size >> 1
        for j in range(starts[dd_], starts[dd_ + 1]):
            fl = bits[j]
            if fl == 0:
                continue
            s = nd[j, 0]
            nodes[ino, 0], nodes[ino, 1], nodes[ino, 2] = s, dd_, nd[j, 1]
            flags[ino] = fl
            ino += 1
            oc = c0[s] + nd[j, 3] * size
            orr = r0[s] + nd[j, 2] * size
            for t in range(12):
                if (fl >> t) & 1:
                    for v in range(3):
                        tri[it, v, 0] = oc + _TEMPLATE[t, v, 0] * half
                        tri[it, v, 1] = orr + _TEMPLATE[t, v, 1] * half
                    tslot[it] = s
                    tlev[it] = dd_ + 1
                    it += 1
    return tri, tslot, tlev, nodes, flags, clamped, evaluated


@_jit
def _argsort_stable(keys):
    """``np.argsort(keys, kind="stable")`` for non-negative int64 keys (LSD radix sort,
    11-bit digits: linear time, stable, so the same permutation)."""
    n = keys.shape[0]
    order = np.arange(n)
    if n < 2:
        return order
    top = 0
    for i in range(n):
        top = max(top, keys[i])
    tmp = np.empty(n, np.int64)
    count = np.empty(2049, np.int64)
    shift = 0
    while (top >> shift) > 0:
        count[:] = 0
        for i in range(n):
            count[((keys[order[i]] >> shift) & 2047) + 1] += 1
        for b in range(2048):
            count[b + 1] += count[b]
        for i in range(n):
            dg = (keys[order[i]] >> shift) & 2047
            tmp[count[dg]] = order[i]
            count[dg] += 1
        order, tmp = tmp, order
        shift += 11
    return order


@_jit
def _lower(keys, x, lo=0, hi=-1):
    """``np.searchsorted(keys, x, side="left")`` for a scalar ``x`` known to land in
    ``[lo, hi]`` (default: anywhere)."""
    if hi < 0:
        hi = keys.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@_jit
def _sorted_order(keys):
    """A stable ascending order of ``keys`` (the identity when already sorted)."""
    for i in range(1, keys.shape[0]):
        if keys[i] < keys[i - 1]:
            return _argsort_stable(keys)
    return np.arange(keys.shape[0])


@_jit
def t_junctions(tri, vcol, vrow):
    """``pure.t_junctions``: ``(ids, ends (a, 2, 2), frac)`` in the reference's order. Per group
    (axis, side) the edges are sorted stably by ``line * big + lo`` like the reference's and
    merged with the vertices in key order: the edge each vertex checks is the reference's
    ``searchsorted(key, vertex key) - 1``."""
    m = tri.shape[0]
    nv = vcol.shape[0]
    big = 0
    for i in range(nv):
        big = max(big, vcol[i], vrow[i])
    big += 2
    # group of each edge (j, t): 0/1 horizontal side -1/+1, 2/3 vertical side -1/+1, -1 none
    grp = np.full(3 * m, -1, np.int64)
    cnt = np.zeros(4, np.int64)
    for j in range(3):
        for t in range(m):
            pc, pr_ = tri[t, j, 0], tri[t, j, 1]
            qc, qr = tri[t, (j + 1) % 3, 0], tri[t, (j + 1) % 3, 1]
            oc, orr = tri[t, (j + 2) % 3, 0], tri[t, (j + 2) % 3, 1]
            g = -1
            if pr_ == qr and abs(pc - qc) >= 2 and orr != pr_:
                g = 0 if orr < pr_ else 1
            elif pc == qc and abs(pr_ - qr) >= 2 and oc != pc:
                g = 2 if oc < pc else 3
            grp[j * m + t] = g
            if g >= 0:
                cnt[g] += 1
    found = np.full(nv, -1, np.int64)
    ends = np.zeros((nv, 2, 2), np.int64)
    frac = np.zeros(nv)
    for g in range(4):
        axis = 1 if g < 2 else 0
        other = 1 - axis
        n = cnt[g]
        if n == 0:
            continue
        line = np.empty(n, np.int64)
        lo = np.empty(n, np.int64)
        hi = np.empty(n, np.int64)
        key = np.empty(n, np.int64)
        a = 0
        for e in range(3 * m):  # edges in the reference's order (j major, then t)
            if grp[e] != g:
                continue
            j, t = e // m, e % m
            p0, p1 = tri[t, j, axis], tri[t, j, other]
            q1 = tri[t, (j + 1) % 3, other]
            line[a], lo[a], hi[a] = p0, min(p1, q1), max(p1, q1)
            key[a] = p0 * big + lo[a]
            a += 1
        order = _argsort_stable(key)
        key, line, lo, hi = key[order], line[order], lo[order], hi[order]
        vk = np.empty(nv, np.int64)
        for v in range(nv):
            vk[v] = vrow[v] * big + vcol[v] if axis == 1 else vcol[v] * big + vrow[v]
        vo = _sorted_order(vk)
        i = -1
        for r in range(nv):
            v = vo[r]
            while i + 1 < n and key[i + 1] < vk[v]:
                i += 1
            if i < 0 or found[v] >= 0:
                continue
            lv = vrow[v] if axis == 1 else vcol[v]
            pv = vcol[v] if axis == 1 else vrow[v]
            if line[i] == lv and hi[i] > pv:
                found[v] = 1
                ends[v, 0, axis], ends[v, 1, axis] = lv, lv
                ends[v, 0, other], ends[v, 1, other] = lo[i], hi[i]
                frac[v] = (pv - lo[i]) / (hi[i] - lo[i])
    c = 0
    for v in range(nv):
        c += found[v] >= 0
    ids = np.empty(c, np.int64)
    c = 0
    for v in range(nv):
        if found[v] >= 0:
            ids[c] = v
            c += 1
    return ids, ends[ids], frac[ids]


@_jit
def conform(tri, slot, level, vcol, vrow):
    """``pure.conform`` (same triangles in the same order); ``ok`` False if it did not
    converge."""
    nv = vcol.shape[0]
    big = 0
    for i in range(nv):
        big = max(big, vcol[i], vrow[i])
    big += 2
    kh = vrow * big + vcol
    kv = vcol * big + vrow
    keys_h = kh[_argsort_stable(kh)]  # axis 1: along rows (np.sort)
    keys_v = kv[_argsort_stable(kv)]  # axis 0: along columns
    # first key of each line: a search on line L lands in [start[L], start[L + 1]]
    start_h = np.empty(big + 1, np.int64)
    start_v = np.empty(big + 1, np.int64)
    for keys, start in ((keys_h, start_h), (keys_v, start_v)):
        i = 0
        for line in range(big + 1):
            while i < keys.shape[0] and keys[i] < line * big:
                i += 1
            start[line] = i
    n_out = 0
    out_t = np.empty((tri.shape[0], 3, 2), np.int64)
    out_s = np.empty(tri.shape[0], np.int64)
    out_l = np.empty(tri.shape[0], np.int64)
    ok = False
    for _ in range(64):
        m = tri.shape[0]
        if m == 0:
            ok = True
            break
        pick = np.full(m, -1, np.int64)
        point = np.zeros((m, 2), np.int64)
        for j in range(3):
            for axis in (1, 0):
                other = 1 - axis
                keys = keys_h if axis == 1 else keys_v
                for t in range(m):
                    if pick[t] >= 0:
                        continue
                    a0, a1 = tri[t, j, axis], tri[t, j, other]
                    b0, b1 = tri[t, (j + 1) % 3, axis], tri[t, (j + 1) % 3, other]
                    if a0 != b0 or abs(a1 - b1) < 2:
                        continue
                    lo, hi = min(a1, b1), max(a1, b1)
                    start = start_h if axis == 1 else start_v
                    s0, s1 = start[a0], start[a0 + 1]
                    i0 = _lower(keys, a0 * big + lo + 1, s0, s1)
                    if i0 < keys.shape[0] and keys[i0] < a0 * big + hi:  # some vertex inside
                        i1 = _lower(keys, a0 * big + hi, i0, s1)
                        mid = keys[(i0 + i1) // 2]
                        pick[t] = j
                        point[t, axis] = mid // big
                        point[t, other] = mid % big
        nk = 0
        for t in range(m):
            nk += pick[t] < 0
        if n_out + nk > out_t.shape[0]:  # grow by doubling: O(total) copies over all rounds
            cap = max(2 * out_t.shape[0], n_out + nk)
            nt = np.empty((cap, 3, 2), np.int64)
            ns = np.empty(cap, np.int64)
            nl = np.empty(cap, np.int64)
            nt[:n_out], ns[:n_out], nl[:n_out] = out_t[:n_out], out_s[:n_out], out_l[:n_out]
            out_t, out_s, out_l = nt, ns, nl
        for t in range(m):
            if pick[t] < 0:
                for v in range(3):
                    out_t[n_out, v, 0], out_t[n_out, v, 1] = tri[t, v, 0], tri[t, v, 1]
                out_s[n_out], out_l[n_out] = slot[t], level[t]
                n_out += 1
        ns_ = m - nk
        if ns_ == 0:
            ok = True
            tri = tri[:0]
            break
        t2 = np.empty((2 * ns_, 3, 2), np.int64)
        s2 = np.empty(2 * ns_, np.int64)
        l2 = np.empty(2 * ns_, np.int64)
        c = 0
        for t in range(m):
            if pick[t] < 0:
                continue
            j = pick[t]
            for ax in range(2):
                v0, v1, v2 = tri[t, j, ax], tri[t, (j + 1) % 3, ax], tri[t, (j + 2) % 3, ax]
                t2[c, 0, ax], t2[c, 1, ax], t2[c, 2, ax] = v0, point[t, ax], v2
                t2[ns_ + c, 0, ax], t2[ns_ + c, 1, ax], t2[ns_ + c, 2, ax] = point[t, ax], v1, v2
            s2[c], s2[ns_ + c] = slot[t], slot[t]
            l2[c], l2[ns_ + c] = level[t], level[t]
            c += 1
        tri, slot, level = t2, s2, l2
    return out_t[:n_out].copy(), out_s[:n_out].copy(), out_l[:n_out].copy(), ok


@_jit
def unique_index(keys):
    """``np.unique(keys, return_index=True, return_inverse=True)`` for non-negative int64."""
    n = keys.shape[0]
    order = _argsort_stable(keys)
    inv = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        if i == 0 or keys[order[i]] != keys[order[i - 1]]:
            m += 1
    uk = np.empty(m, np.int64)
    first = np.empty(m, np.int64)
    u = -1
    for i in range(n):
        o = order[i]
        if i == 0 or keys[o] != keys[order[i - 1]]:
            u += 1
            uk[u] = keys[o]
            first[u] = o  # stable: the first occurrence
        inv[o] = u
    return uk, first, inv
