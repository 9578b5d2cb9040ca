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
paths exactly on several scenes). The pruning tries :func:`_quick_bounds` before
:func:`_bound`; they bracket it, so they change no decision. No fastmath (NaN
and ∞ are meaningful here). The mesh
assembly's kernels (T-junctions, conforming split, sorts) live in ``_mesh_nb``, the whole
assembly in one call in ``_assemble_nb``; they are re-exported here.
"""

from __future__ import annotations

import math

import numpy as np

from render.strategies.jung_han._assemble_nb import (  # noqa: F401  (re-exported)
    assemble,
    ws_size_assemble,
)
from render.strategies.jung_han._mesh_nb import (  # noqa: F401  (the mesh kernels, re-exported)
    _jit,
    argsort_stable,
    conform,
    first_corner_pairs,
    ranks,
    ranks_sorted,
    t_junction_picks,
    t_junctions,
    unique_index,
    unique_index_ws,
)
from render.strategies.jung_han._tree_nb import build_tree  # noqa: F401  (re-exported)
from render.strategies.jung_han.pure import EDGE_QUADS, FAN_EDGE, FAN_QUAD, OWN, TEMPLATE

_OWN = OWN.astype(np.int64)
_EQ = EDGE_QUADS.astype(np.int64)
_FQ = FAN_QUAD.astype(np.int64)
_FE = FAN_EDGE.astype(np.int64)
_TEMPLATE = TEMPLATE.astype(np.int64)


@_jit
def _cam(basis, eye, x, y, z):
    rx, ry, rz = x - eye[0], y - eye[1], z - eye[2]
    c0 = rx * basis[0, 0] + ry * basis[0, 1] + rz * basis[0, 2]
    c1 = rx * basis[1, 0] + ry * basis[1, 1] + rz * basis[1, 2]
    c2 = rx * basis[2, 0] + ry * basis[2, 1] + rz * basis[2, 2]
    return c0, c1, c2


@_jit
def _vertex_error(basis, eye, focal, d, x, y, h):
    """``vertex_errors`` of one vertex (0 for δ = 0, ∞ if undefined): the same closed form in
    the same order (one camera transform, no difference of projections)."""
    if d == 0.0:
        return 0.0
    c0, c1, c2 = _cam(basis, eye, x, y, h)
    u0, u1, u2 = basis[0, 2], basis[1, 2], basis[2, 2]
    z1 = c2 + d * u2
    if not (c2 > 0.0 and z1 > 0.0):
        return np.inf
    g0, g1 = c2 * u0 - c0 * u2, c2 * u1 - c1 * u2
    rho = focal * abs(d) * math.sqrt(g0 * g0 + g1 * g1) / (c2 * z1)  # (as the reference)
    return rho if math.isfinite(rho) else np.inf


@_jit
def _own_error(
    nd, j, v, size, half, k, lev, hoff, r0, c0, hh, dl,
    basis, eye, focal, x0, y0, dx, dy,
):  # fmt: skip
    """δ_s of own vertex ``v`` (C, T, B, L, R) of node ``j`` (``JungHanSelector._own``)."""
    s = nd[j, 0]
    sh = k - lev[s]
    lr = nd[j, 2] * size + _OWN[v, 1] * half
    lc = nd[j, 3] * size + _OWN[v, 0] * half
    flat = hoff[s] + (lr >> sh) * ((1 << lev[s]) + 1) + (lc >> sh)
    x = x0 + float(c0[s] + lc) * dx
    y = y0 - float(r0[s] + lr) * dy
    return _vertex_error(basis, eye, focal, float(dl[flat]), x, y, hh[flat])


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
def _bound(basis, eye, focal, dmax, xmin, xmax, ymin, ymax, zlo, zhi, wk):
    """``projected_bound`` of one box (``wk``: (8, 5) scratch). The corners' camera coordinates
    are ``_cam``'s products and sums in the same order (each product computed once). The gain's
    ``hypot`` is only evaluated at corners whose squared gain is within a relative ``1e-9`` of
    the largest: ``hypot`` is within an ulp of the exact norm, so any other corner's is smaller
    and the maximum is the same number (all corners when a square is not finite)."""
    if dmax == 0.0:
        return 0.0 * (1.0 + 1e-9) + 1e-9
    rx0, rx1 = xmin - eye[0], xmax - eye[0]
    ry0, ry1 = ymin - eye[1], ymax - eye[1]
    rz0, rz1 = zlo - eye[2], zhi - eye[2]
    for a in range(3):
        px0, px1 = rx0 * basis[a, 0], rx1 * basis[a, 0]
        py0, py1 = ry0 * basis[a, 1], ry1 * basis[a, 1]
        pz0, pz1 = rz0 * basis[a, 2], rz1 * basis[a, 2]
        for i in range(8):
            px = px1 if (i >> 2) & 1 else px0
            py = py1 if (i >> 1) & 1 else py0
            pz = pz1 if i & 1 else pz0
            wk[i, a] = px + py + pz
    zmin = wk[0, 2]
    for i in range(1, 8):
        zmin = _nanmin(zmin, wk[i, 2])
    if not zmin > 0.0:
        return np.inf * (1.0 + 1e-9) + 1e-9
    u0, u1, u2 = basis[0, 2], basis[1, 2], basis[2, 2]
    smax = -1.0
    finite = True
    for i in range(8):
        c2 = wk[i, 2]
        qx, qy = wk[i, 0] / c2, wk[i, 1] / c2
        gx, gy = u0 - qx * u2, u1 - qy * u2
        sq = gx * gx + gy * gy
        wk[i, 3], wk[i, 4] = gx, gy
        if not math.isfinite(sq):
            finite = False
        elif sq > smax:
            smax = sq
        wk[i, 2] = sq
    if finite:
        thr = smax * (1.0 - 1e-9)
        gain = -np.inf
        for i in range(8):
            if wk[i, 2] >= thr:
                gain = max(gain, math.hypot(wk[i, 3], wk[i, 4]))
    else:
        gain = math.hypot(wk[0, 3], wk[0, 4])
        for i in range(1, 8):
            gain = _nanmax(gain, math.hypot(wk[i, 3], wk[i, 4]))
    b = focal * dmax * gain / zmin
    return b * (1.0 + 1e-9) + 1e-9


@_jit
def _quick_bounds(basis, eye, focal, pf, dmax, xmin, ymin, hx, hy, w0, w1, w2, zlo, zhi):
    """Cheap bounds ``(lo, hi)`` on :func:`_bound`'s value for the same box (``xmin``,
    ``xmin + 2 hx``, ``ymin``, ``ymin + 2 hy``, ``zlo``, ``zhi``): ``lo <= _bound <= hi``, or
    ``(-∞, ∞)`` where they are not safe (a box whose depth comes within ``1e-6`` of its
    coordinates' magnitude of the eye, NaN or ∞ inputs). ``pf``: :func:`_quick_frame` of the
    camera; ``w0..w2``: the box's half extents along the camera axes from ``hx``, ``hy``
    (``sum_j |R_ij| h_j``, j = x, y).

    From the box's centre ``c`` and half extents ``W = (W_x, W_y, W_z)`` in camera coordinates,
    its nearest depth ``z = c_z - W_z`` (``_bound``'s ``z_min``: the corners' smallest depth)
    and the gain ``g(q) = |u_xy - q u_z|`` at the centre's image ``q_c = c_xy / c_z``:

    * ``lo``: the box's image is the convex hull of its corners' (a perspective map of a box in
      front of the eye), ``q_c`` lies in it and ``g`` is convex, so the corners' largest gain is
      at least ``g(q_c)``: ``f dmax g(q_c) / z`` is at most ``_bound``.
    * ``hi``: a point ``p`` of the box has ``|p_xy - c_xy| <= |W_xy|`` and ``p_z >= z``, so its
      image is within ``r = |W_xy| / z + |c_xy| W_z / (z c_z)`` of ``q_c`` and its gain at most
      ``g(q_c) + |u_z| r``: ``f dmax (g(q_c) + |u_z| r) / z`` is at least ``_bound``.

    The margins (``1e-6`` relative, and absolute on ``hi``, against ``_bound``'s ``1e-9``) are
    orders of magnitude above either computation's rounding while the depth stays above
    ``1e-6`` of the coordinates' magnitude, so ``hi < τ`` implies ``_bound < τ`` and ``lo >= τ``
    implies ``_bound >= τ``: the pruning, hence every output, is unchanged; they spare
    ``_bound``'s eight projected corners where they decide."""
    if not dmax > 0.0:
        return -np.inf, np.inf
    hz = 0.5 * abs(zhi - zlo)
    rx = xmin + hx - eye[0]
    ry = ymin + hy - eye[1]
    rz = 0.5 * (zlo + zhi) - eye[2]
    cx = rx * basis[0, 0] + ry * basis[0, 1] + rz * basis[0, 2]
    cy = rx * basis[1, 0] + ry * basis[1, 1] + rz * basis[1, 2]
    cz = rx * basis[2, 0] + ry * basis[2, 1] + rz * basis[2, 2]
    wz = w2 + hz * pf[3]
    z = cz - wz
    scale = pf[0] + abs(xmin) + abs(ymin) + 2.0 * (hx + hy) + abs(zlo) + abs(zhi)
    if not z > 1e-6 * scale:  # (NaN too)
        return -np.inf, np.inf
    wx = w0 + hz * pf[1]
    wy = w1 + hz * pf[2]
    u2 = pf[4]
    icz, iz = 1.0 / cz, 1.0 / z  # (two divisions: rounding far inside the margins)
    gx, gy = pf[5] - cx * icz * u2, pf[6] - cy * icz * u2
    g = math.sqrt(gx * gx + gy * gy)
    r = (math.sqrt(wx * wx + wy * wy) + math.sqrt(cx * cx + cy * cy) * wz * icz) * iz
    k = focal * dmax * iz
    return k * g * (1.0 - 1e-6), k * (g + pf[3] * r) * (1.0 + 1e-6) + 1e-6


@_jit
def _quick_frame(basis, eye):
    """:func:`_quick_bounds`' per-camera values: the eye's magnitude ``|e_x| + |e_y| + |e_z|``,
    ``|R_iz|`` (i = 0, 1, 2; ``|R_2z| = |u_z|``), then ``u_z``, ``u_x``, ``u_y``; ``u`` = world
    up in camera axes."""
    u0, u1, u2 = basis[0, 2], basis[1, 2], basis[2, 2]
    pf = np.empty(7)
    pf[0] = abs(eye[0]) + abs(eye[1]) + abs(eye[2])
    pf[1], pf[2], pf[3] = abs(u0), abs(u1), abs(u2)
    pf[4], pf[5], pf[6] = u2, u0, u1
    return pf


@_jit
def _quick_extents(basis, hx, hy):
    """Half extents along the camera axes of ``hx``, ``hy`` (:func:`_quick_bounds`' ``w``)."""
    w0 = hx * abs(basis[0, 0]) + hy * abs(basis[0, 1])
    w1 = hx * abs(basis[1, 0]) + hy * abs(basis[1, 1])
    w2 = hx * abs(basis[2, 0]) + hy * abs(basis[2, 1])
    return w0, w1, w2


@_jit
def bounds_pair(basis, eye, focal, dmax, xmin, xmax, ymin, ymax, zlo, zhi):
    """``(lo, hi, exact)``: :func:`_quick_bounds` and :func:`_bound` of each box (the tests'
    entry point; ``xmax - xmin`` and ``ymax - ymin`` are the boxes' sizes)."""
    n = dmax.shape[0]
    lo, hi, exact = np.empty(n), np.empty(n), np.empty(n)
    pf = _quick_frame(basis, eye)
    wk = np.empty((8, 5))
    for i in range(n):
        hx, hy = 0.5 * (xmax[i] - xmin[i]), 0.5 * (ymax[i] - ymin[i])
        w0, w1, w2 = _quick_extents(basis, hx, hy)
        lo[i], hi[i] = _quick_bounds(
            basis, eye, focal, pf, dmax[i], xmin[i], ymin[i], hx, hy, w0, w1, w2, zlo[i], zhi[i]
        )
        exact[i] = _bound(
            basis, eye, focal, dmax[i], xmin[i], xmax[i], ymin[i], ymax[i], zlo[i], zhi[i], wk
        )
    return lo, hi, exact


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
def block_hits(r0, c0, size, o, pext, normals, pmin, pmax, q, e, x0, y0, dx, dy):
    """``polygon_meets_rects`` and ``corners_inside`` of the store blocks' squares of ``size``
    samples at global origins ``(r0, c0)`` (``JungHanSelector._box``), for a polygon of at
    least one vertex (``_meets``/``_inside``'s arguments)."""
    n = r0.shape[0]
    meets = np.zeros(n, np.bool_)
    inside = np.zeros(n, np.bool_)
    for s in range(n):
        xmin = x0 + float(c0[s]) * dx
        ymax = y0 - float(r0[s]) * dy
        xmax, ymin = xmin + size * dx, ymax - size * dy
        meets[s] = _meets(
            o, pext[0], pext[1], pext[2], pext[3], normals, pmin, pmax, xmin, ymin, xmax, ymax
        )
        inside[s] = _inside(o, q, e, xmin, ymin, xmax, ymax)
    return meets, inside


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
    hh, dl, pyr, hoff, poff, lev, r0, c0, roots, root_inside,
    o, pext, normals, pmin, pmax, q, e,
    basis, eye, focal, tau, x0, y0, dx, dy, k, prune, culled_collapse, nd, pm,
):  # fmt: skip
    """The pruned top-down + bottom-up pass of one frame: ``(tri, tslot, tlev, nodes, flags,
    clamped, evaluated, nd, pm)`` in the numpy reference's order (see the module notes);
    ``nd``/``pm`` the node buffers (the ones passed in, or larger), for the next frame.

    A child the pruning bound collapses is decided when its parent expands (the reference
    decides it when it visits the child, with the same operands): it is recorded as a bit of
    its parent's ``pm`` (a collapsed quadrant, state 2) and never becomes a node, so neither
    pass spends time on the ~70 % of nodes that are pruned."""
    # nd: slot, idx, row, col, inside, parent, quad, depth; pm: pruned children (bit per
    # quadrant). Both are the caller's buffers from the last frame (grown here when short,
    # returned), so a frame's nodes do not land in fresh memory
    cap = max(64, 4 * roots.shape[0])
    if nd.shape[0] < cap or pm.shape[0] != nd.shape[0]:
        nd = np.empty((cap, 8), np.int64)
        pm = np.zeros(cap, np.int64)
    wk = np.empty((8, 5))  # _bound's scratch
    pf = _quick_frame(basis, eye)
    nr = roots.shape[0]
    for i in range(nr):
        nd[i, 0], nd[i, 1], nd[i, 2], nd[i, 3] = roots[i], 0, 0, 0
        nd[i, 4], nd[i, 5], nd[i, 6], nd[i, 7] = root_inside[i], -1, -1, 0
        pm[i] = 0
    starts = [0]
    lo, hi, d = 0, nr, 0
    while hi > lo:
        size = 1 << (k - d)
        half = size >> 1  # the children's size
        hx, hy = 0.5 * half * abs(dx), 0.5 * half * abs(dy)
        w0, w1, w2 = _quick_extents(basis, hx, hy)
        base = ((1 << (2 * (d + 1))) - 1) // 3  # the children's first pyramid index
        n_new = hi
        for j in range(lo, hi):
            s = nd[j, 0]
            if lev[s] - 1 == d:  # a leaf
                continue
            for qd in range(4):
                row = 2 * nd[j, 2] + 1 - (qd >> 1)
                col = 2 * nd[j, 3] + (qd & 1)
                xmin = x0 + float(c0[s] + col * half) * dx
                ymax = y0 - float(r0[s] + row * half) * dy
                xmax, ymin = xmin + half * dx, ymax - half * dy
                ins = nd[j, 4] != 0
                hit = ins
                if not ins:
                    hit = _meets(
                        o, pext[0], pext[1], pext[2], pext[3], normals, pmin, pmax,
                        xmin, ymin, xmax, ymax,
                    )  # fmt: skip
                    ins = hit and _inside(o, q, e, xmin, ymin, xmax, ymax)
                if not hit:
                    continue
                idx = 4 * nd[j, 1] + qd
                if prune and (ins or culled_collapse):  # (a child's depth is >= 1)
                    ii = poff[s] + base + idx
                    dm, zl, zh = pyr[ii, 0], pyr[ii, 1], pyr[ii, 2]
                    # the cheap bounds first: where they decide, _bound decides the same
                    qlo, qhi = _quick_bounds(
                        basis, eye, focal, pf, dm, min(xmin, xmax), min(ymin, ymax),
                        hx, hy, w0, w1, w2, zl, zh,
                    )  # fmt: skip
                    if qhi < tau:
                        pruned = True
                    elif qlo >= tau:
                        pruned = False
                    else:
                        b = _bound(basis, eye, focal, dm, xmin, xmax, ymin, ymax, zl, zh, wk)
                        pruned = b < tau
                    if pruned:
                        pm[j] |= 1 << qd
                        continue
                if n_new >= nd.shape[0]:
                    nd = _grow2(nd)
                    pm = _grow1(pm)
                nd[n_new, 0], nd[n_new, 1] = s, idx
                nd[n_new, 2], nd[n_new, 3], nd[n_new, 4] = row, col, ins
                nd[n_new, 5], nd[n_new, 6], nd[n_new, 7] = j, qd, d + 1
                pm[n_new] = 0
                n_new += 1
        lo, hi = hi, n_new
        if hi > lo:
            starts.append(lo)
            d += 1
    total = hi
    starts.append(total)
    cm = np.zeros((total, 4), np.int8)
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
                c = 2 if (pm[j] >> qd) & 1 else cm[j, qd]  # a pruned child: collapsed
                cu = (not leaf) and c == 0
                if cu:
                    culled |= 1 << qd
                if leaf or c == 2 or (cu and culled_collapse):
                    present |= 1 << qd
            evaluated += 1  # (every node here: the pruned ones never became nodes)
            # a vertex's δ_s is only computed where the decision reads it (the edge
            # midpoint: both triangles present; the centre: every edge removed, d >= 1)
            allrem = True
            fl = 0
            for ed in range(4):
                both = (present >> _EQ[ed, 0]) & (present >> _EQ[ed, 1]) & 1
                rem = both == 1 and _own_error(
                    nd, j, 1 + ed, size, half, k, lev, hoff, r0, c0, hh, dl,
                    basis, eye, focal, x0, y0, dx, dy,
                ) < tau  # fmt: skip
                allrem = allrem and rem
                if rem:
                    fl |= 1 << (8 + ed)
            st = 1
            if dd_ >= 1 and allrem:
                e0 = _own_error(
                    nd, j, 0, size, half, k, lev, hoff, r0, c0, hh, dl,
                    basis, eye, focal, x0, y0, dx, dy,
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
    return tri, tslot, tlev, nodes, flags, clamped, evaluated, nd, pm
