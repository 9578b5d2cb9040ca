"""Numba kernels of ``seamless-patches``' shared-edge resolution (issue 14): one round of
``selection._resolve`` (edge resolutions, :func:`edge_groups`, the group reductions, the split
rule and the edge levels), the whole top-down traversal of ``selection._traverse`` in one call
(every depth's :func:`traverse_depth`) and the whole selection (traversal, then rounds of
resolution and re-traversal until nothing splits). Each gives exactly the numpy reference's
output: integer work, and the float work is :mod:`._kernels_nb`'s. This module re-exports
:mod:`._kernels_nb`'s kernels, so it is the one kernel module of the selection."""

from __future__ import annotations

import math

import numpy as np

from render.strategies.seamless._kernels_nb import (
    _jit,
    disc_meets,
    edge_groups,
    epsilon,
    traverse_depth,
)

__all__ = [
    "disc_meets",
    "edge_groups",
    "epsilon",
    "resolve_round",
    "select_all",
    "traverse_all",
    "traverse_depth",
]

_LOW = -(1 << 30)
_HIGH = 1 << 30


@_jit
def _edge_resolution(eps, c):
    """``selection.edge_resolution`` of one ε."""
    x = eps * np.float64(1 << c)
    if not math.isfinite(x):
        x = np.float64(1 << c)
    m, e = math.frexp(max(x, 1.0))
    up = e - 1 if m == 0.5 else e
    return min(max(up, 1), c)


@_jit
def _depths(d, big):
    """``np.unique(d)`` of depths in ``0..big`` (a presence table: no sort to compile)."""
    seen = np.zeros(big + 1, np.bool_)
    m = 0
    for x in d:
        if not seen[x]:
            seen[x] = True
            m += 1
    out = np.empty(m, np.int64)
    j = 0
    for x in range(big + 1):
        if seen[x]:
            out[j] = x
            j += 1
    return out


@_jit
def _argsort(keys):
    """``np.argsort`` of distinct keys (bottom-up merge sort: with distinct keys every sort
    gives this order; numba's own sort costs seconds to compile)."""
    n = keys.shape[0]
    a = np.arange(n)
    b = np.empty(n, np.int64)
    w = 1
    while w < n:
        for lo in range(0, n, 2 * w):
            mid = min(lo + w, n)
            hi = min(lo + 2 * w, n)
            i, j = lo, mid
            for t in range(lo, hi):
                if i < mid and (j >= hi or keys[a[i]] <= keys[a[j]]):
                    b[t] = a[i]
                    i += 1
                else:
                    b[t] = a[j]
                    j += 1
        a, b = b, a
        w *= 2
    return a


@_jit
def resolve_round(idx, d, rows, cols, eps, blk, cap, dmax, c):
    """One round of ``_resolve`` over the leaves: ``(split, v, level, violations)`` where
    ``split`` says some coarse leaves must split, ``v`` are those leaves (ascending, as
    ``np.unique``), and otherwise ``level`` is the ``(n, 4)`` edge levels and ``violations``
    the shared edges whose sides cannot meet."""
    n = idx.shape[0]
    level = np.zeros((n, 4), np.int64)
    if n == 0:
        return False, np.zeros(0, np.int64), level, 0
    gr = np.empty(n, np.int64)
    gc = np.empty(n, np.int64)
    hi = np.empty(n, np.int64)
    can = np.empty(n, np.bool_)
    big = 0
    mr = 0
    mc = 0
    for i in range(n):
        b = idx[i]
        gr[i] = (blk[b, 0] << d[i]) + rows[i]
        gc[i] = (blk[b, 1] << d[i]) + cols[i]
        hi[i] = min(d[i] + c, cap[b])
        can[i] = d[i] + 1 <= dmax[b] and d[i] + c < cap[b]
        big = max(big, d[i])
        mr = max(mr, gr[i] >> d[i])
        mc = max(mc, gc[i] >> d[i])
    nr = (mr + 2) << big
    nc = (mc + 2) << big
    keys = (d * nr + gr) * nc + gc
    order = _argsort(keys)  # the keys are distinct: the same order as numpy's sort
    sk = keys[order]
    gid = edge_groups(d, gr, gc, _depths(d, big), order, sk, nr, nc)
    s4 = 4 * n
    lo_g = np.full(s4, _LOW, np.int64)
    hi_g = np.full(s4, _HIGH, np.int64)
    want_g = np.full(s4, _LOW, np.int64)
    deep_g = np.full(s4, -1, np.int64)
    size_g = np.zeros(s4, np.int64)
    for i in range(n):
        for e in range(4):
            g = gid[i, e]
            want = min(d[i] + _edge_resolution(eps[i, e], c), hi[i])
            lo_g[g] = max(lo_g[g], d[i] + 1)
            hi_g[g] = min(hi_g[g], hi[i])
            want_g[g] = max(want_g[g], want)
            deep_g[g] = max(deep_g[g], d[i])
            size_g[g] += 1
    v = np.empty(n, np.int64)
    nv = 0
    for s in range(s4):  # j = s // 4 ascends with s: v comes out sorted and unique
        j = s // 4
        shared = size_g[s] > 1
        stuck = shared and (lo_g[s] > hi_g[s] or want_g[s] > hi_g[s])
        split = stuck and hi[j] == hi_g[s] and can[j] and deep_g[s] > d[j]
        if split and (nv == 0 or v[nv - 1] != j):
            v[nv] = j
            nv += 1
    if nv:
        return True, v[:nv].copy(), level, 0
    violations = 0
    for s in range(s4):
        if size_g[s] > 1 and lo_g[s] > hi_g[s]:
            violations += 1
    for i in range(n):
        for e in range(4):
            g = gid[i, e]
            if lo_g[g] > hi_g[g]:
                lo, up = d[i] + 1, hi[i]
            else:
                lo, up = lo_g[g], hi_g[g]
            level[i, e] = min(max(want_g[g], lo), up)  # np.clip
    return False, v[:0].copy(), level, violations


@_jit
def _room(a, n, need):
    """``a`` (rows ``0..n`` kept) with room for ``need`` rows (doubling)."""
    if need <= a.shape[0]:
        return a
    out = np.empty((max(need, 2 * a.shape[0]),) + a.shape[1:], a.dtype)
    out[:n] = a[:n]
    return out


@_jit
def _with_seeds(carry, seeds, seed_d, d):
    """``carry`` then the seeds of depth ``d`` (``np.concatenate`` of the two)."""
    m = 0
    for x in seed_d:
        if x == d:
            m += 1
    out = np.empty(carry.shape[0] + m, np.int64)
    out[: carry.shape[0]] = carry
    j = carry.shape[0]
    for i in range(seed_d.shape[0]):
        if seed_d[i] == d:
            out[j] = seeds[i]
            j += 1
    return out


@_jit
def traverse_all(
    seed_d, seed_i, seed_r, seed_c, k, c, use_win, win_r, win_c, cull_mode, geo, s_dx, s_dy,
    radius, cull, arrs, has_arr, eps_args, dmax, cap,
):  # fmt: skip
    """``_traverse`` from the seeds ``(seed_d, seed_i, seed_r, seed_c)`` (depth, block index,
    row, col; per depth in their order) by :func:`traverse_depth` at every depth: the leaves
    ``(idx, depth, rows, cols, eps)`` in the reference's order and the clamped count. ``geo``
    = ``(x0, y0, step, dx, dy)``, ``s_dx``/``s_dy``/``radius`` and ``arrs``/``has_arr`` per
    depth (the table's arrays, ``has_arr`` a bool array), ``eps_args`` = :func:`epsilon`'s
    arguments from ``blk`` on without ``k``, the table's array and its flag."""
    x0, y0, step, dx, dy = geo
    (
        blk, bkeys, border, slots, grows, gcols, zr, ex0, ey0, ddx, ddy, ex, ey, ez, focal,
        tau, cc, paper, paper_rho,
    ) = eps_args  # fmt: skip
    size = max(16, 4 * seed_i.shape[0])
    li = np.empty(size, np.int64)
    ld = np.empty(size, np.int64)
    lr = np.empty(size, np.int64)
    lc = np.empty(size, np.int64)
    le = np.empty((size, 4))
    n = 0
    clamped = 0
    ci = seed_i[:0]
    cr = seed_i[:0]
    cl = seed_i[:0]
    for d in range(0, k - c + 1):
        idx = _with_seeds(ci, seed_i, seed_d, d)
        rows = _with_seeds(cr, seed_r, seed_d, d)
        cols = _with_seeds(cl, seed_c, seed_d, d)
        if idx.shape[0] == 0:
            ci, cr, cl = idx, rows, cols
            continue
        leaf, child, cl_d, seen = traverse_depth(
            idx, rows, cols, d, k, c, use_win, win_r, win_c, cull_mode,
            (x0, y0, step, dx, dy, s_dx[d], s_dy[d], radius[d]), cull,
            (k, blk, bkeys, border, slots, arrs[d], has_arr[d], grows, gcols, zr, ex0, ey0,
             ddx, ddy, ex, ey, ez, focal, tau, cc, paper, paper_rho),
            dmax, cap,
        )  # fmt: skip
        if seen:
            clamped += cl_d
            m = leaf[0].shape[0]
            li = _room(li, n, n + m)
            ld = _room(ld, n, n + m)
            lr = _room(lr, n, n + m)
            lc = _room(lc, n, n + m)
            le = _room(le, n, n + m)
            li[n : n + m] = leaf[0]
            ld[n : n + m] = d
            lr[n : n + m] = leaf[1]
            lc[n : n + m] = leaf[2]
            le[n : n + m] = leaf[3]
            n += m
        ci, cr, cl = child
    return li[:n].copy(), ld[:n].copy(), lr[:n].copy(), lc[:n].copy(), le[:n].copy(), clamped


@_jit
def select_all(
    seed_d, seed_i, seed_r, seed_c, k, c, use_win, win_r, win_c, cull_mode, geo, s_dx, s_dy,
    radius, cull, arrs, has_arr, eps_args, dmax, cap, blk, max_rounds,
):  # fmt: skip
    """``select_layout`` after the frame setup: :func:`traverse_all` from the seeds, then up to
    ``max_rounds`` rounds of :func:`resolve_round` and re-traversal of the split leaves'
    children. Returns ``(settled, idx, depth, rows, cols, eps, level, clamped, violations)``."""
    idx, d, rows, cols, eps, clamped = traverse_all(
        seed_d, seed_i, seed_r, seed_c, k, c, use_win, win_r, win_c, cull_mode, geo, s_dx,
        s_dy, radius, cull, arrs, has_arr, eps_args, dmax, cap,
    )  # fmt: skip
    for _ in range(max_rounds):
        split, v, level, violations = resolve_round(idx, d, rows, cols, eps, blk, cap, dmax, c)
        if not split:
            return True, idx, d, rows, cols, eps, level, clamped, violations
        keep = np.ones(idx.shape[0], np.bool_)
        keep[v] = False
        m = v.shape[0]
        sd = np.empty(4 * m, np.int64)
        si = np.empty(4 * m, np.int64)
        sr = np.empty(4 * m, np.int64)
        sc = np.empty(4 * m, np.int64)
        s = 0
        for dv in _depths(d[v], k):  # per depth, in v's order: the reference's seeds
            for j in v:
                if d[j] == dv:
                    for q in range(4):
                        sd[s] = dv + 1
                        si[s] = idx[j]
                        sr[s] = 2 * rows[j] + (q >> 1)
                        sc[s] = 2 * cols[j] + (q & 1)
                        s += 1
        ni, nd, nr, nc, ne, ncl = traverse_all(
            sd, si, sr, sc, k, c, use_win, win_r, win_c, cull_mode, geo, s_dx, s_dy, radius,
            cull, arrs, has_arr, eps_args, dmax, cap,
        )  # fmt: skip
        clamped += ncl
        idx = np.concatenate((idx[keep], ni))
        d = np.concatenate((d[keep], nd))
        rows = np.concatenate((rows[keep], nr))
        cols = np.concatenate((cols[keep], nc))
        eps = np.concatenate((eps[keep], ne))
    return False, idx, d, rows, cols, eps, np.zeros((0, 4), np.int64), clamped, 0
