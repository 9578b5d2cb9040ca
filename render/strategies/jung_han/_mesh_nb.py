"""Numba kernels of ``jung-han``'s mesh assembly (imported by
:mod:`render.strategies.jung_han._kernels_nb`): a stable radix sort, the T-junction search, the
conforming split and ``np.unique`` of the vertex keys, each giving exactly the numpy
reference's output (integer work only, plus ``pure.t_junctions``' one division)."""

from __future__ import annotations

import numpy as np

from tiler.jit import cached_njit

# error_model="numpy": float division by 0 gives ±∞/NaN as in numpy (no ZeroDivisionError)
_OPTS = {"nogil": True, "error_model": "numpy"}


_jit = cached_njit(**_OPTS)  # as tiler._kernels_nb, without its fastmath flags


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
