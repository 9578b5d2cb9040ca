"""Numba kernels of ``jung-han``'s mesh assembly (imported by
:mod:`render.strategies.jung_han._kernels_nb`): a stable radix sort, the T-junction search, the
conforming split and ``np.unique`` of the vertex keys, each giving exactly the numpy
reference's output (integer work only, plus ``pure.t_junctions``' one division). The search and
the split take each triangle corner's vertex id, so they look vertices up by their rank along a
row or column instead of searching sorted keys."""

from __future__ import annotations

import numpy as np

from tiler.jit import cached_njit

# error_model="numpy": float division by 0 gives ±∞/NaN as in numpy (no ZeroDivisionError)
_OPTS = {"nogil": True, "error_model": "numpy"}


_jit = cached_njit(**_OPTS)  # as tiler._kernels_nb, without its fastmath flags


#: radix digits: 11 bits, so at most 6 passes for int64 keys; counts per pass
_COUNTS = 6 * 2049


@_jit
def _argsort_ws(keys, ws):
    """``np.argsort(keys, kind="stable")`` for non-negative int64 keys (LSD radix sort,
    11-bit digits: linear time, stable, so the same permutation). The keys move with their
    indices, so every pass reads its input in order. Its buffers are carved from the int64
    workspace ``ws`` (a fresh one if shorter than ``4 n + _COUNTS``): the order returned is a view
    of ``ws``, valid until ``ws`` is used again. (A persistent workspace: fresh memory is
    faulted in and zeroed by the OS on every frame, which cost more than the sorts.)"""
    n = keys.shape[0]
    if ws.shape[0] < 4 * n + _COUNTS:
        ws = np.empty(4 * n + _COUNTS, np.int64)
    order = ws[0:n]
    tmp = ws[n : 2 * n]
    for i in range(n):
        order[i] = i
    if n < 2:
        return order
    top = 0
    for i in range(n):
        top = max(top, keys[i])
    passes = 0
    while passes < 6 and (top >> (11 * passes)) > 0:  # (a shift by >= 64 is undefined)
        passes += 1
    kin = ws[2 * n : 3 * n]
    kout = ws[3 * n : 4 * n]
    count = ws[4 * n : 4 * n + passes * 2049]
    count[:] = 0
    for i in range(n):  # every pass's histogram in one read
        kin[i] = keys[i]
        for p in range(passes):
            count[p * 2049 + ((keys[i] >> (11 * p)) & 2047) + 1] += 1
    for p in range(passes):
        c = count[p * 2049 : (p + 1) * 2049]
        for b in range(2048):
            c[b + 1] += c[b]
        shift = 11 * p
        for i in range(n):
            dg = (kin[i] >> shift) & 2047
            w = c[dg]
            tmp[w] = order[i]
            kout[w] = kin[i]
            c[dg] = w + 1
        order, tmp = tmp, order
        kin, kout = kout, kin
    return order


@_jit
def _ranks(vcol, vrow, ws):
    """Each vertex's position along rows (row-major: ``vrow * big + vcol`` sorted) and along
    columns (column-major), with the two orders: ``(rank_h, perm_h, rank_v, perm_v)``."""
    nv = vcol.shape[0]
    big = 0
    for i in range(nv):
        big = max(big, vcol[i], vrow[i])
    big += 2
    perm_h = _argsort_ws(vrow * big + vcol, ws).copy()
    perm_v = _argsort_ws(vcol * big + vrow, ws).copy()
    rank_h = np.empty(nv, np.int64)
    rank_v = np.empty(nv, np.int64)
    for i in range(nv):
        rank_h[perm_h[i]] = i
        rank_v[perm_v[i]] = i
    return rank_h, perm_h, rank_v, perm_v


@_jit
def _ranks_sorted(vcol, vrow, ws):
    """:func:`_ranks` of vertices already in row-major order (sorted by ``(vrow, vcol)``, as
    the assembly's sorted unique keys ``row * wg + col`` are): the row order is the identity,
    so only the column order is sorted."""
    nv = vcol.shape[0]
    big = 0
    for i in range(nv):
        big = max(big, vcol[i], vrow[i])
    big += 2
    ident = np.arange(nv)
    perm_v = _argsort_ws(vcol * big + vrow, ws).copy()
    rank_v = np.empty(nv, np.int64)
    for i in range(nv):
        rank_v[perm_v[i]] = i
    return ident, ident, rank_v, perm_v


@_jit
def _t_junctions(tri, tid, vcol, vrow, ws):
    """:func:`_t_junctions_ranked` with the vertices' :func:`_ranks`."""
    return _t_junctions_ranked(tri, tid, vcol, vrow, _ranks(vcol, vrow, ws))


@_jit
def _t_junctions_ranked(tri, tid, vcol, vrow, ranks):
    """:func:`_t_junctions_picked` without the split's picks."""
    ids, ends, frac, ia, ib, _, _ = _t_junctions_picked(tri, tid, vcol, vrow, ranks, False)
    return ids, ends, frac, ia, ib


@_jit
def _t_junctions_picked(tri, tid, vcol, vrow, ranks, picks):
    """``pure.t_junctions`` with the corners' vertex ids ``tid`` (m, 3) (indices into
    ``vcol``/``vrow``, the drawn vertices, all distinct): ``(ids, ends (a, 2, 2), frac, ia,
    ib, pick, pid)`` in the reference's order, ``ia``/``ib`` the ids of the ends; with
    ``picks``, ``pick``/``pid`` are the conforming split's first round (:func:`_picks` of
    ``tri``, found in the same pass over the edges), else empty.

    Per group (axis, side) an edge's sort key ``line * big + lo`` is the key of its ``lo``
    end, a drawn vertex, so the edge the reference's ``searchsorted(key, vertex key) - 1``
    picks is, in the vertices' order along that axis, the last edge (in edge order, as the
    stable sort keeps ties) starting at the nearest vertex before. So only the vertices after
    an edge's start are tested against it, in that order, until one lies past it (a later
    line, or at or beyond its far end: so does every later one) or another edge of the group
    starts there (it takes over after that vertex). An edge whose ends are adjacent in that
    order has no vertex inside and finds nothing: only the starts of the others are walked."""
    m = tri.shape[0]
    nv = vcol.shape[0]
    rank_h, perm_h, rank_v, perm_v = ranks  # (see _ranks)
    found = np.full(nv, -1, np.int64)
    ends = np.empty((nv, 2, 2), np.int64)  # (these four: only the found vertices' are read)
    frac = np.empty(nv)
    e_lo = np.empty(nv, np.int64)  # id of the lo / hi end of the vertex's edge
    e_hi = np.empty(nv, np.int64)
    # best[g, r]: the last edge (3 t + j) of group g (0/1 horizontal, opposite vertex above/
    # below; 2/3 vertical) starting at the vertex of rank r along the group's axis, in the
    # reference's edge order (j major, then t); walk: the starts of edges with a vertex inside
    best = np.full((4, nv), -1, np.int64)
    walk = np.empty((4, nv), np.int64)
    nwalk = np.zeros(4, np.int64)
    inwalk = np.zeros((4, nv), np.bool_)
    mp = m if picks else 0
    pick = np.full(mp, -1, np.int64)
    pid = np.zeros(mp, np.int64)
    for j in range(3):  # edges in the reference's order (j major, then t)
        j1 = j + 1 if j < 2 else 0
        j2 = j1 + 1 if j1 < 2 else 0
        for t in range(m):
            pc, pr_ = tri[t, j, 0], tri[t, j, 1]
            qc, qr = tri[t, j1, 0], tri[t, j1, 1]
            # both tests without short-circuits (fewer mispredicted branches)
            hz = (pr_ == qr) & (abs(pc - qc) >= 2)
            vt = (not hz) & (pc == qc) & (abs(pr_ - qr) >= 2)
            if hz | vt:
                rank = rank_h if hz else rank_v
                ra, rb = rank[tid[t, j]], rank[tid[t, j1]]
                lo, hi = min(ra, rb), max(ra, rb)
                if picks and hi - lo > 1 and pick[t] < 0:  # the split's first edge: j order
                    perm = perm_h if hz else perm_v
                    pick[t], pid[t] = j, perm[(lo + 1 + hi) // 2]
                oc, orr = tri[t, j2, 0], tri[t, j2, 1]
                if hz:
                    if orr == pr_:  # a degenerate triangle: no side
                        continue
                    g = 0 if orr < pr_ else 1
                else:
                    if oc == pc:
                        continue
                    g = 2 if oc < pc else 3
                best[g, lo] = 3 * t + j
                if hi - lo > 1 and not inwalk[g, lo]:
                    inwalk[g, lo] = True
                    walk[g, nwalk[g]] = lo
                    nwalk[g] += 1
    for g in range(4):
        axis = 1 if g < 2 else 0
        other = 1 - axis
        perm = perm_h if axis == 1 else perm_v
        for i in range(nwalk[g]):
            s = walk[g, i]
            e = best[g, s]  # the last edge starting there (it may have no vertex inside)
            t = e // 3  # a division by a constant: cheap
            j = e - 3 * t
            j1 = j + 1 if j < 2 else 0
            a, b = tri[t, j, other], tri[t, j1, other]
            lo, hi = min(a, b), max(a, b)
            ln = tri[t, j, axis]
            for r in range(s + 1, nv):
                v = perm[r]
                if found[v] < 0:
                    lv = vrow[v] if axis == 1 else vcol[v]
                    pv = vcol[v] if axis == 1 else vrow[v]
                    if not (ln == lv and hi > pv):
                        break  # past the edge: so is every later vertex in this order
                    found[v] = 1
                    ends[v, 0, axis], ends[v, 1, axis] = lv, lv
                    ends[v, 0, other], ends[v, 1, other] = lo, hi
                    frac[v] = (pv - lo) / (hi - lo)
                    e_lo[v], e_hi[v] = (tid[t, j], tid[t, j1]) if a < b else (tid[t, j1], tid[t, j])
                if best[g, r] >= 0:
                    break  # the edge starting here takes over from the next vertex
    c = 0
    for v in range(nv):
        c += found[v] >= 0
    ids = np.empty(c, np.int64)
    c = 0
    for v in range(nv):
        if found[v] >= 0:
            ids[c] = v
            c += 1
    return ids, ends[ids], frac[ids], e_lo[ids], e_hi[ids], pick, pid


@_jit
def _conform(tri, tid, slot, level, vcol, vrow, ws):
    """:func:`_conform_ranked` with the vertices' :func:`_ranks`."""
    return _conform_ranked(tri, tid, slot, level, vcol, vrow, _ranks(vcol, vrow, ws))


@_jit
def _picks(tri, tid, ranks):
    """One round of the conforming split's choices: per triangle the first edge (``j``
    order) with a drawn vertex inside, -1 for none, and the vertex half-way between its ends
    in the order along the edge's line (``(pick, pid)``; see :func:`_conform_ranked`)."""
    rank_h, perm_h, rank_v, perm_v = ranks  # (see _ranks)
    m = tri.shape[0]
    pick = np.full(m, -1, np.int64)
    pid = np.zeros(m, np.int64)
    for t in range(m):  # the first edge (j, then axis 1 before 0) with a vertex inside
        for j in range(3):
            j1 = j + 1 if j < 2 else 0
            for axis in range(1, -1, -1):
                other = 1 - axis
                if tri[t, j, axis] != tri[t, j1, axis]:
                    continue
                if abs(tri[t, j, other] - tri[t, j1, other]) < 2:
                    continue
                rank = rank_h if axis == 1 else rank_v
                ra, rb = rank[tid[t, j]], rank[tid[t, j1]]
                lo, hi = min(ra, rb), max(ra, rb)
                if hi - lo > 1:
                    perm = perm_h if axis == 1 else perm_v
                    pid[t] = perm[(lo + 1 + hi) // 2]
                    pick[t] = j
                    break
            if pick[t] >= 0:
                break
    return pick, pid


@_jit
def _conform_ranked(tri, tid, slot, level, vcol, vrow, ranks):
    """``pure.conform`` (same triangles in the same order), carrying each corner's vertex id
    (``tid`` (m, 3): index into ``vcol``/``vrow``, the drawn vertices, all distinct; a split
    point gets the id of the vertex it is); ``(tri, tid, slot, level, ok)``, ``ok`` False if it
    did not converge. An edge's ends are drawn vertices, so the reference's two
    ``searchsorted`` calls over the vertices sorted along the edge's line are the ends' ranks
    in that order: some vertex lies inside iff they are more than 1 apart, and the split point
    is the vertex half-way between."""
    pick, pid = _picks(tri, tid, ranks)
    return _conform_picked(tri, tid, slot, level, vcol, vrow, ranks, pick, pid)


@_jit
def _conform_picked(tri, tid, slot, level, vcol, vrow, ranks, pick, pid):
    """:func:`_conform_ranked` with its first round's :func:`_picks` of ``tri`` given (the
    T-junction search finds them in its pass over the edges)."""
    n_out = 0
    cap = tri.shape[0] + tri.shape[0] // 4 + 64  # room for the usual splits: rarely grown
    out_t = np.empty((cap, 3, 2), np.int64)
    out_s = np.empty(cap, np.int64)
    out_l = np.empty(cap, np.int64)
    out_i = np.empty((cap, 3), np.int64)
    ok = False
    for rnd in range(64):
        m = tri.shape[0]
        if m == 0:
            ok = True
            break
        if rnd:
            pick, pid = _picks(tri, tid, ranks)
        nk = 0
        for t in range(m):
            nk += pick[t] < 0
        if n_out + nk > out_t.shape[0]:  # grow by doubling: O(total) copies over all rounds
            cap = max(2 * out_t.shape[0], n_out + nk)
            nt = np.empty((cap, 3, 2), np.int64)
            ns = np.empty(cap, np.int64)
            nl = np.empty(cap, np.int64)
            ni = np.empty((cap, 3), np.int64)
            nt[:n_out], ns[:n_out], nl[:n_out] = out_t[:n_out], out_s[:n_out], out_l[:n_out]
            ni[:n_out] = out_i[:n_out]
            out_t, out_s, out_l, out_i = nt, ns, nl, ni
        for t in range(m):
            if pick[t] < 0:
                for v in range(3):
                    out_t[n_out, v, 0], out_t[n_out, v, 1] = tri[t, v, 0], tri[t, v, 1]
                    out_i[n_out, v] = tid[t, v]
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
        i2 = np.empty((2 * ns_, 3), np.int64)
        c = 0
        for t in range(m):
            if pick[t] < 0:
                continue
            j = pick[t]
            for ax in range(2):
                v0, v1, v2 = tri[t, j, ax], tri[t, (j + 1) % 3, ax], tri[t, (j + 2) % 3, ax]
                pt = vcol[pid[t]] if ax == 0 else vrow[pid[t]]
                t2[c, 0, ax], t2[c, 1, ax], t2[c, 2, ax] = v0, pt, v2
                t2[ns_ + c, 0, ax], t2[ns_ + c, 1, ax], t2[ns_ + c, 2, ax] = pt, v1, v2
            i0_, i1_, i2_ = tid[t, j], tid[t, (j + 1) % 3], tid[t, (j + 2) % 3]
            i2[c, 0], i2[c, 1], i2[c, 2] = i0_, pid[t], i2_
            i2[ns_ + c, 0], i2[ns_ + c, 1], i2[ns_ + c, 2] = pid[t], i1_, i2_
            s2[c], s2[ns_ + c] = slot[t], slot[t]
            l2[c], l2[ns_ + c] = level[t], level[t]
            c += 1
        tri, tid, slot, level = t2, i2, s2, l2
    n = n_out
    # views, not copies: a copy is fresh memory the OS must fault in and zero on every frame
    return out_t[:n], out_i[:n], out_s[:n], out_l[:n], ok


@_jit
def _hash_insert(keys, tab, bits, inv, tfirst, tkey):
    """Each key's place among the distinct keys in first-occurrence order (``inv``), each
    distinct key and its first index (``tkey``, ``tfirst``), through an open-addressing table
    of ``2**bits`` (key, place) pairs in ``tab`` (linear probing, Fibonacci hashing): the number
    of distinct keys, or -1 once they would fill more than half the table (the caller doubles
    it and starts again)."""
    size = 1 << bits
    mask = size - 1
    for h in range(2 * size):
        tab[h] = -1  # (keys are >= 0)
    m = 0
    for i in range(keys.shape[0]):
        kk = keys[i]
        h = ((kk * -7046029254386353131) >> (64 - bits)) & mask  # the product's top bits
        while True:
            c = tab[2 * h]
            if c == kk:
                inv[i] = tab[2 * h + 1]
                break
            if c == -1:
                if 2 * (m + 1) > size:
                    return -1
                tab[2 * h], tab[2 * h + 1] = kk, m
                tfirst[m], tkey[m], inv[i] = i, kk, m
                m += 1
                break
            h = (h + 1) & mask
    return m


@_jit
def _unique_index(keys, ws):
    """``np.unique(keys, return_index=True, return_inverse=True)`` for non-negative int64.

    The distinct keys are found by hashing, in first-occurrence order, and only they are sorted
    (a mesh's corners hold each vertex ~6 times: the radix sort of every key cost twice as
    much). The table and the distinct keys are carved from the end of the int64 workspace
    ``ws``, the sort's buffers from its start (fresh ones where it is too short)."""
    n = keys.shape[0]
    bits = 4
    while (1 << bits) < n // 2:  # half the keys distinct at most, as a start
        bits += 1
    inv = np.empty(n, np.int64)
    while True:
        need = (2 << bits) + 2 * n
        wsx = ws if ws.shape[0] >= need else np.empty(need, np.int64)
        top = wsx.shape[0]
        tab = wsx[top - (2 << bits) : top]
        tfirst = wsx[top - need : top - need + n]
        tkey = wsx[top - need + n : top - (2 << bits)]
        m = _hash_insert(keys, tab, bits, inv, tfirst, tkey)
        if m >= 0:
            break
        bits += 1
    # the sort's buffers (4 m + _COUNTS) from the workspace's start, if they fit before tfirst
    front = wsx[0 : top - need] if wsx is ws else np.empty(0, np.int64)
    order = _argsort_ws(tkey[:m], front)  # (distinct keys: the order is the sorted one)
    uk = np.empty(m, np.int64)
    first = np.empty(m, np.int64)
    rank = np.empty(m, np.int64)
    for u in range(m):
        o = order[u]
        rank[o] = u
        uk[u] = tkey[o]
        first[u] = tfirst[o]  # the first occurrence: the place's first key
    for i in range(n):
        inv[i] = rank[inv[i]]
    return uk, first, inv


@_jit
def _first_corner_pairs(grp, tid, nv, ws):
    """The distinct (group, vertex) pairs of the corners ``(grp[t], tid[t, v])`` (``grp >=
    0``, ``0 <= tid < nv``) in the order of their first corners: ``(first, inv)``, the first
    corner ``3 t + v`` of each pair and each corner's pair. A vertex lies in few groups, so
    each corner finds its pair along its vertex's chain of pairs (no sort). The chains are
    carved from the end of the int64 workspace ``ws`` (a fresh one if shorter than ``nv + 2 *
    3 m``)."""
    m = tid.shape[0]
    n = 3 * m
    nvx = max(nv, 1)
    if ws.shape[0] < nv + 2 * n:
        ws = np.empty(nv + 2 * n, np.int64)
    top = ws.shape[0]
    head = ws[top - nv : top]  # per vertex: its latest pair, -1 for none
    ekey = ws[top - nv - n : top - nv]  # per pair: its key, the vertex's previous pair
    enext = ws[top - nv - 2 * n : top - nv - n]
    for v in range(nv):
        head[v] = -1
    inv = np.empty(n, np.int64)
    first = np.empty(n, np.int64)
    ne = 0
    for t in range(m):
        gk = grp[t] * nvx
        for c in range(3):
            v = tid[t, c]
            key = gk + v
            e = head[v]
            while e >= 0 and ekey[e] != key:
                e = enext[e]
            if e < 0:  # a new pair: this is its first corner
                e = ne
                ekey[e], enext[e], first[e] = key, head[v], 3 * t + c
                head[v] = e
                ne += 1
            inv[3 * t + c] = e
    return first[:ne], inv


# The entry points called from Python: thin wrappers, so that a kernel compiled (and cached) as
# another kernel's callee is never also called from Python (numba's cache can then load it
# without what boxing its result arrays needs: "'descr' is NULL").


@_jit
def argsort_stable(keys):
    """:func:`_argsort_ws` into a fresh array (``np.argsort(keys, kind="stable")``)."""
    return _argsort_ws(keys, np.empty(0, np.int64)).copy()


@_jit
def t_junctions(tri, tid, vcol, vrow):
    """:func:`_t_junctions`."""
    return _t_junctions(tri, tid, vcol, vrow, np.empty(0, np.int64))


@_jit
def conform(tri, tid, slot, level, vcol, vrow):
    """:func:`_conform`."""
    return _conform(tri, tid, slot, level, vcol, vrow, np.empty(0, np.int64))


@_jit
def unique_index(keys):
    """:func:`_unique_index`."""
    return _unique_index(keys, np.empty(0, np.int64))


@_jit
def unique_index_ws(keys, ws):
    """:func:`_unique_index` with the workspace ``ws`` (as the assembly calls it)."""
    return _unique_index(keys, ws)


@_jit
def ranks(vcol, vrow):
    """:func:`_ranks` (copies, so the tests may compare the two orders)."""
    rh, ph, rv, pv = _ranks(vcol, vrow, np.empty(0, np.int64))
    return rh.copy(), ph.copy(), rv.copy(), pv.copy()


@_jit
def ranks_sorted(vcol, vrow):
    """:func:`_ranks_sorted` (copies)."""
    rh, ph, rv, pv = _ranks_sorted(vcol, vrow, np.empty(0, np.int64))
    return rh.copy(), ph.copy(), rv.copy(), pv.copy()


@_jit
def first_corner_pairs(grp, tid, nv):
    """:func:`_first_corner_pairs` (copies)."""
    first, inv = _first_corner_pairs(grp, tid, nv, np.empty(0, np.int64))
    return first.copy(), inv


@_jit
def t_junction_picks(tri, tid, vcol, vrow):
    """The conforming split's first-round choices as :func:`_t_junctions_picked` finds them
    beside the T-junctions, and as :func:`_picks` finds them alone: ``(pick, pid, pick, pid)``."""
    rk = _ranks(vcol, vrow, np.empty(0, np.int64))
    out = _t_junctions_picked(tri, tid, vcol, vrow, rk, True)
    pick, pid = _picks(tri, tid, rk)
    return out[5], out[6], pick, pid
