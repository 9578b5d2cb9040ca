"""Numba kernels of :func:`render.select.stitch`'s rounds (driven by :mod:`render.stitch_fast`):
the restriction and snaps of every edge (:func:`restrict`), the snapped-edge check's
bookkeeping (:func:`over_todo`, :func:`over_victims`, as :class:`render.stitch_rounds.OverCache`),
and a round's split (:func:`split`: kept leaves first, then each victim's four children, with
the carried neighbours and checks, and the sorted leaf keys updated in place of a new sort).
Leaf keys are Z-order codes at a fixed finest depth (any depth at least every leaf's: a probe
one finest node beyond an edge midpoint lies in the same leaf whatever the finest depth,
:mod:`render.stitch_rounds`), so kept leaves keep their keys from round to round and one binary
search finds the leaf holding a probe. Integer work only: the same values as the numpy
reference."""

from __future__ import annotations

import numpy as np

from render._select_nb import edge_probe
from render._snap_nb import (  # noqa: F401 (the check's kernels, used through this module)
    exact_all,
    gather_cells,
    gather_heights,
    gather_patches,
    strip_max,
)
from tiler.jit import cached_njit

_jit = cached_njit(nogil=True, error_model="numpy")


@_jit
def _spread(x):
    """The bits of ``x`` (< 2**31) at the even positions."""
    x &= 0x7FFFFFFF
    x = (x | (x << 16)) & 0x0000FFFF0000FFFF
    x = (x | (x << 8)) & 0x00FF00FF00FF00FF
    x = (x | (x << 4)) & 0x0F0F0F0F0F0F0F0F
    x = (x | (x << 2)) & 0x3333333333333333
    return (x | (x << 1)) & 0x5555555555555555


@_jit
def _zkey(d, gr, gc, big):
    """The Z-order code of the depth-``big`` corner of node ``(gr, gc)`` of depth ``d``."""
    return (_spread(gr << (big - d)) << 1) | _spread(gc << (big - d))


@_jit
def leaf_keys(bk_r, bk_c, block, depth, row, col, big):
    """Each leaf's key: the Z-order code of its corner at depth ``big`` (global node rows and
    columns; ``bk_r``/``bk_c`` the blocks' ids). A leaf's depth-``big`` nodes are the codes
    ``key .. key + 4**(big - d) - 1``, so the leaf holding a point is its code's predecessor."""
    n = depth.shape[0]
    out = np.empty(n, np.int64)
    for i in range(n):
        d = depth[i]
        out[i] = _zkey(d, (bk_r[block[i]] << d) + row[i], (bk_c[block[i]] << d) + col[i], big)
    return out


@_jit
def _upper(keys, x):
    """``np.searchsorted(keys, x, side="right")`` for a scalar ``x``."""
    lo, hi = 0, keys.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] <= x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@_jit
def probe(rows, sk, order, bk_r, bk_c, block, depth, row, col, big, nr, nc):
    """``(len(rows), 4)`` the leaf across each edge (N, E, S, W) of the leaves ``rows``, -1 for
    none: the leaf (keys ``sk`` sorted, ``order`` their leaves) holding the probe one
    depth-``big`` node beyond the edge midpoint (``render.stitch_rounds.neighbours_of``'s
    probe; ``nr``/``nc`` the depth-``big`` node rows and columns the probes may reach)."""
    m = rows.shape[0]
    out = np.full((m, 4), -1, np.int64)
    for a in range(m):
        i = rows[a]
        d = depth[i]
        sh = big - d
        span = np.int64(1) << sh
        fr0 = ((bk_r[block[i]] << d) + row[i]) << sh
        fc0 = ((bk_c[block[i]] << d) + col[i]) << sh
        for e in range(4):
            fr, fc = edge_probe(fr0, fc0, span, e)
            if fr < 0 or fc < 0 or fr >= nr or fc >= nc:
                continue
            z = (_spread(fr) << 1) | _spread(fc)
            pos = _upper(sk, z) - 1
            if pos < 0:
                continue
            j = order[pos]
            if z - sk[pos] < np.int64(1) << (2 * (big - depth[j])):
                out[a, e] = j
    return out


@_jit
def _victims(mark, depth, block, res, k, p):
    """The marked leaves that may split (ascending: their patch is finer than neither the
    block nor the resident level allows) and the count of marked ones that may not."""
    n = depth.shape[0]
    nv = 0
    extra = 0
    for j in range(n):
        if mark[j]:
            if depth[j] + p < min(k, res[block[j]]):
                nv += 1
            else:
                extra += 1
    victims = np.empty(nv, np.int64)
    a = 0
    for j in range(n):
        if mark[j] and depth[j] + p < min(k, res[block[j]]):
            victims[a] = j
            a += 1
    return victims, extra


@_jit
def restrict(level, depth, block, nbr, res, k, p):
    """One round's snaps ``(n, 4)``, its count of edges breaking the restriction
    ``2**s_n <= node edge``, and the splittable leaves across them (ascending); with none,
    the snaps clipped to each patch's cells (the round's answer)."""
    n = depth.shape[0]
    snap = np.zeros((n, 4), np.int64)
    mark = np.zeros(n, np.bool_)
    n_bad = 0
    for i in range(n):
        sp = k - level[i]
        edge = k - depth[i]
        for e in range(4):
            j = nbr[i, e]
            if j < 0:
                continue
            sn = k - level[j]
            t = sn - sp
            snap[i, e] = t if t > 0 else 0
            if sn > edge:
                n_bad += 1
                mark[j] = True
    victims, _ = _victims(mark, depth, block, res, k, p)
    if victims.shape[0] == 0:
        for i in range(n):
            cells = level[i] - depth[i]
            for e in range(4):
                if snap[i, e] > cells:
                    snap[i, e] = cells
    return snap, n_bad, victims


@_jit
def over_todo(snap, c_snap, c_over, c_known, delta):
    """:meth:`render.stitch_rounds.OverCache.over_edges`' bookkeeping: forget the checks of
    leaves whose snaps are new (recording them) and return those to check again (a snapped
    edge, a finite error), ascending."""
    n = snap.shape[0]
    cand = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        todo = not c_known[i]
        if not todo:
            for e in range(4):
                if snap[i, e] != c_snap[i, e]:
                    todo = True
                    break
        if not todo:
            continue
        smax = 0
        for e in range(4):
            c_over[i, e] = False
            c_snap[i, e] = snap[i, e]
            if snap[i, e] > smax:
                smax = snap[i, e]
        c_known[i] = True
        if smax > 0 and np.isfinite(delta[i]):
            cand[m] = i
            m += 1
    return cand[:m]


@_jit
def over_victims(c_over, nbr, depth, block, res, k, p):
    """The splittable leaves across edges that failed the check (ascending) and the count of
    those that may not split (clamped)."""
    n = depth.shape[0]
    mark = np.zeros(n, np.bool_)
    for i in range(n):
        for e in range(4):
            if c_over[i, e]:
                mark[nbr[i, e]] = True
    return _victims(mark, depth, block, res, k, p)


@_jit
def split(
    victims, block, depth, row, col, level, delta, src, nbr, c_snap, c_over, c_known,
    sk, order, keys, res, bk_r, bk_c, big, k, p,
):  # fmt: skip
    """Replace the leaves ``victims`` (ascending) by their four children (kept leaves first in
    order, then the children, as :func:`render.select._split`): the new leaf arrays, their
    neighbours (``-1`` where to probe again) and the rows to probe again, the check caches,
    and the sorted keys (``sk``, ``order``, per leaf ``keys``: :func:`leaf_keys` at ``big``).
    The children's errors are left NaN (the caller looks them up); ``src`` is each leaf's row
    in the selection, -1 for a new one (its ``rho`` is still to be computed)."""
    n = depth.shape[0]
    nv = victims.shape[0]
    keep = np.ones(n, np.bool_)
    for v in range(nv):
        keep[victims[v]] = False
    new = np.empty(n, np.int64)
    nk = 0
    for i in range(n):
        new[i] = nk if keep[i] else -1
        if keep[i]:
            nk += 1
    m = nk + 4 * nv
    o_block = np.empty(m, np.int64)
    o_depth = np.empty(m, np.int64)
    o_row = np.empty(m, np.int64)
    o_col = np.empty(m, np.int64)
    o_level = np.empty(m, np.int64)
    o_delta = np.empty(m, np.float64)
    o_src = np.empty(m, np.int64)
    o_nbr = np.full((m, 4), -1, np.int64)
    o_snap = np.zeros((m, 4), np.int64)
    o_over = np.zeros((m, 4), np.bool_)
    o_known = np.zeros(m, np.bool_)
    o_keys = np.empty(m, np.int64)
    redo = np.empty(m, np.int64)
    nr_redo = 0
    for i in range(n):
        if not keep[i]:
            continue
        a = new[i]
        o_block[a] = block[i]
        o_depth[a] = depth[i]
        o_row[a] = row[i]
        o_col[a] = col[i]
        o_level[a] = level[i]
        o_delta[a] = delta[i]
        o_src[a] = src[i]
        o_keys[a] = keys[i]
        o_known[a] = c_known[i]
        stale = False
        for e in range(4):
            o_snap[a, e] = c_snap[i, e]
            o_over[a, e] = c_over[i, e]
            j = nbr[i, e]
            if j >= 0:
                if keep[j]:
                    o_nbr[a, e] = new[j]
                else:
                    stale = True
        if stale:
            redo[nr_redo] = a
            nr_redo += 1
    ck = np.empty(4 * nv, np.int64)
    for v in range(nv):
        i = victims[v]
        b = block[i]
        d = depth[i] + 1
        lv = min(min(k, d + p), res[b])
        for q in range(4):
            a = nk + 4 * v + q
            r = 2 * row[i] + (q >> 1)
            c = 2 * col[i] + (q & 1)
            o_block[a] = b
            o_depth[a] = d
            o_row[a] = r
            o_col[a] = c
            o_level[a] = lv
            o_delta[a] = np.nan
            o_src[a] = -1
            key = _zkey(d, (bk_r[b] << d) + r, (bk_c[b] << d) + c, big)
            o_keys[a] = key
            ck[4 * v + q] = key
            redo[nr_redo] = a
            nr_redo += 1
    # the sorted keys: drop the victims', renumber, merge the children's in
    co = np.argsort(ck)
    o_sk = np.empty(m, np.int64)
    o_order = np.empty(m, np.int64)
    a = 0
    c = 0
    for s in range(sk.shape[0]):
        j = order[s]
        if not keep[j]:
            continue
        while c < 4 * nv and ck[co[c]] < sk[s]:
            o_sk[a] = ck[co[c]]
            o_order[a] = nk + co[c]
            a += 1
            c += 1
        o_sk[a] = sk[s]
        o_order[a] = new[j]
        a += 1
    while c < 4 * nv:
        o_sk[a] = ck[co[c]]
        o_order[a] = nk + co[c]
        a += 1
        c += 1
    leaves = (o_block, o_depth, o_row, o_col, o_level, o_delta, o_src)
    return leaves, o_nbr, redo[:nr_redo], (o_snap, o_over, o_known), (o_sk, o_order, o_keys)
