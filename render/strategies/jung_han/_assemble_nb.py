"""Numba kernel of ``jung-han``'s mesh assembly in one call (imported by
:mod:`render.strategies.jung_han._kernels_nb`): ``JungHanSelector._assemble``'s sort by slot,
vertex keys, drawn heights, T-junction search, height adjustment, conforming split and GPU
vertex/index arrays, with the same outputs as the numpy reference.

What it does not repeat: the reference's ``searchsorted`` look-ups of vertex keys. Every corner
carries its vertex id (its place in the sorted unique keys ``uk``): the T-junction search
returns the ids of the edge ends, and :func:`~._mesh_nb._conform` carries the ids through the
split (a split point is a drawn vertex), which is what ``searchsorted(uk, key)`` gives for a
key in ``uk``. Heights are read once per vertex (at its first corner, as the reference's
``h_corner[first]``)."""

from __future__ import annotations

import numpy as np

from render.strategies.jung_han._mesh_nb import (
    _COUNTS,
    _argsort_ws,
    _conform_picked,
    _first_corner_pairs,
    _jit,
    _ranks_sorted,
    _t_junctions_picked,
    _unique_index,
)

_BIG = np.finfo(np.float64).max


def ws_size_assemble(m: int) -> int:
    """Length of the int64 workspace :func:`assemble` needs for ``m`` triangles (with the
    usual splits and ~6 corners a vertex; a frame beyond allocates its own): the largest of its
    users, the vertex keys' de-duplication (a hash table of at most ``2 * 3 m`` and the
    distinct keys, ``2 * 3 m``, then their sort, ``4 nv + _COUNTS``), the sort by slot and the
    GPU vertices' chains (``nv + 2 * 3 m'`` over the ``m'`` split triangles)."""
    n = 3 * (m + m // 4 + 64)
    return 4 * n + _COUNTS


@_jit
def _trailing_zeros(v, cap):
    """``tiler.layout.trailing_zeros`` of one non-negative integer (0 -> ``cap``)."""
    if v == 0:
        return cap
    n = 0
    while not (v >> n) & 1:
        n += 1
    return min(n, cap)


@_jit
def assemble(tri, slot, tl, hh, hoff, lev, r0, c0, wg, k, step, stitching, ws):
    """``JungHanSelector._assemble`` on the frame's triangles ``tri`` (m, 3, 2) with their slots
    and levels: ``(tri, tri_h, slot, level, adjusted, v_slot, v_level, v_cr, v_h, index,
    ok)`` (``ok`` False if the conforming split did not converge). ``ws``: the int64 workspace
    of the sorts, kept by the caller between frames (:func:`ws_size_assemble` of ``m`` or
    more, else they allocate)."""
    m = tri.shape[0]
    order = _argsort_ws(slot, ws)  # a view of the workspace: used up before its next use
    t1 = np.empty((m, 3, 2), np.int64)
    s1 = np.empty(m, np.int64)
    l1 = np.empty(m, np.int64)
    key = np.empty(3 * m, np.int64)
    for i in range(m):
        o = order[i]
        s1[i], l1[i] = slot[o], tl[o]
        for v in range(3):
            t1[i, v, 0], t1[i, v, 1] = tri[o, v, 0], tri[o, v, 1]
            key[3 * i + v] = tri[o, v, 1] * wg + tri[o, v, 0]
    uk, first, inv = _unique_index(key, ws)
    nv = uk.shape[0]
    hv = np.empty(nv)
    vrow = np.empty(nv, np.int64)
    vcol = np.empty(nv, np.int64)
    for u in range(nv):  # (uk // wg, uk % wg) read from the vertex's first corner
        t, v = first[u] // 3, first[u] % 3
        vcol[u], vrow[u] = t1[t, v, 0], t1[t, v, 1]
        s = s1[t]
        sh = k - lev[s]
        flat = ((vrow[u] - r0[s]) >> sh) * ((1 << lev[s]) + 1) + ((vcol[u] - c0[s]) >> sh)
        hv[u] = hh[hoff[s] + flat]
    tid = inv.reshape(m, 3)
    # the vertices are the sorted unique keys, so in row-major order: ranked once, for the
    # T-junction search and the split
    ranks = _ranks_sorted(vcol, vrow, ws)
    # the T-junctions, and in the same pass over the edges the split's first round
    split = stitching and m > 0
    ids, ends, frac, ia, ib, pick, pid = _t_junctions_picked(t1, tid, vcol, vrow, ranks, split)
    na = ids.shape[0] if stitching else 0  # the positive control: no adjustment, no split
    if na:
        vlev = np.empty(na, np.int64)
        for a in range(na):
            v = ids[a]
            tz = min(_trailing_zeros(vcol[v] % step, k), _trailing_zeros(vrow[v] % step, k))
            vlev[a] = k - tz
        new = np.empty(na)
        for lv in range(k + 1):  # coarse levels first; a level reads the heights before it
            for a in range(na):
                if vlev[a] == lv:
                    ha, hb = hv[ia[a]], hv[ib[a]]
                    new[a] = ha + frac[a] * (hb - ha)
            for a in range(na):
                if vlev[a] == lv:
                    old = hv[ids[a]]
                    if np.isfinite(new[a]) and np.isfinite(old):
                        hv[ids[a]] = new[a]
    adjusted = np.empty((na, 2), np.int64)
    for a in range(na):
        adjusted[a, 0], adjusted[a, 1] = vcol[ids[a]], vrow[ids[a]]
    ok = True
    if split:
        t1, tid, s1, l1, ok = _conform_picked(t1, tid, s1, l1, vcol, vrow, ranks, pick, pid)
    m2 = t1.shape[0]
    tri_h = np.empty((m2, 3))
    grp = np.empty(m2, np.int64)
    for t in range(m2):
        for v in range(3):
            tri_h[t, v] = hv[tid[t, v]]
        grp[t] = s1[t] * 16 + l1[t]
    # GPU vertices, one per (slot, drawn level, vertex), in the order of their first corners
    gfirst, ginv = _first_corner_pairs(grp, tid, nv, ws)
    ng = gfirst.shape[0]
    v_slot = np.empty(ng, np.int64)
    v_level = np.empty(ng, np.int64)
    v_cr = np.empty((ng, 2), np.int64)
    v_h = np.empty(ng)
    for g in range(ng):
        t, v = gfirst[g] // 3, gfirst[g] % 3
        vid = tid[t, v]
        v_slot[g], v_level[g] = s1[t], l1[t]
        v_cr[g, 0], v_cr[g, 1] = vcol[vid], vrow[vid]
        h = hv[vid]
        if h != h:  # np.nan_to_num(nan=0.0)
            h = 0.0
        elif h == np.inf:
            h = _BIG
        elif h == -np.inf:
            h = -_BIG
        v_h[g] = h
    return t1, tri_h, s1, l1, adjusted, v_slot, v_level, v_cr, v_h, ginv.reshape(m2, 3), ok
