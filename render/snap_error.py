"""The extra error of snapped patch edges (pure numpy; docs/RENDER.md "Precision and extremes").

A patch drawn at level ``L`` has a stored error ``delta`` (the largest distance of a valid
full-resolution sample from the unsnapped level-``L`` surface ``S``). An edge snapped by ``t``
(:func:`render.mesh.snap_vertices`) draws the cells along it as fans over the coarser
neighbour's vertices, which are level-``L`` vertices too. In such a triangle ``T`` the drawn
height is the linear interpolant ``I`` of ``S`` at ``T``'s corners, so at a sample ``x`` of it

    ``|h(x) - I(x)| <= |h(x) - S(x)| + |S(x) - I(x)| <= delta + e_T``,
    ``e_T = max over T of |I - S|``,

computed exactly: ``I - S`` is linear on each piece of the overlay of ``T`` with the cells'
triangles, so its largest magnitude is at the overlay's vertices (``T``'s edges cut by the
cell lines ``i = m``, ``j = m``, ``i - j = m``, and the grid vertices in ``T``), each a fixed
linear combination of the patch's vertex heights (:func:`difference_rows`, one matrix per
cell count and snaps, cached). A patch with a masked vertex uses the looser
``max(max_box S - min_T h, max_T h - min_box S)`` (``min_T``/``max_T`` over ``T``'s valid
corners, ``I`` lies between them; ``min_box``/``max_box`` over the valid level-``L`` vertices
of ``T``'s bounding box, where ``S`` lies). A triangle no vertex of which moved is a cell
triangle of ``S`` (``e_T = 0``). :func:`snap_excess` gives, per patch and edge, the largest
``e_T`` of the triangles of that edge's strip of cells: the patch's error on samples there is
at most ``delta`` plus it (:func:`render.select.stitch` splits the coarser neighbour across an
edge while the metric of that sum exceeds τ).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

import numpy as np

from render.mesh import grid_indices, grid_vertices, snap_vertices


@cache
def strip_template(cells_log2: int, snaps: tuple[int, int, int, int]) -> list:
    """Per edge (N, E, S, W) the moved triangles of its strip of cells: corner ``(j, i)`` index
    arrays ``(m, 3)`` each and bounding boxes ``(m, 4)`` ``(j0, j1, i0, i1)`` inclusive."""
    n = 1 << cells_log2
    v0 = grid_vertices(n)
    v = snap_vertices(v0, n, snaps)
    tri = grid_indices(n).reshape(n, n, 2, 3)  # (row j, col i, half, corner)
    strips = (tri[0], tri[:, n - 1], tri[n - 1], tri[:, 0])
    out = []
    for e, strip in enumerate(strips):
        if snaps[e] <= 0:
            out.append(None)
            continue
        t = strip.reshape(-1, 3)
        ij = v[t]  # (m, 3, 2) snapped (i, j)
        moved = (v[t] != v0[t]).any(axis=(1, 2))
        a, b, c = ij[:, 0], ij[:, 1], ij[:, 2]
        area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (
            c[:, 0] - a[:, 0]
        )
        keep = moved & (area2 != 0)
        ij = ij[keep]
        if not len(ij):
            out.append(None)
            continue
        box = np.stack(
            [ij[..., 1].min(1), ij[..., 1].max(1), ij[..., 0].min(1), ij[..., 0].max(1)], 1
        )
        out.append((ij[..., 1], ij[..., 0], box))
    return out


def _surface_weights(n: int, i: float, j: float) -> dict[int, float]:
    """``S`` at patch point ``(i, j)`` as weights on vertex ids ``j*(n+1)+i`` (a-d cut)."""
    i0, j0 = min(int(np.floor(i)), n - 1), min(int(np.floor(j)), n - 1)
    u, v = i - i0, j - j0
    a = j0 * (n + 1) + i0
    b, c, d = a + 1, a + n + 1, a + n + 2
    # triangle (a, b, d): a + u (b - a) + v (d - b); (a, d, c): a + u (d - c) + v (c - a)
    return {a: 1.0 - u, b: u - v, d: v} if u >= v else {a: 1.0 - v, c: v - u, d: u}


@cache
def difference_rows(cells_log2: int, snaps: tuple[int, int, int, int]) -> list:
    """Per edge: a matrix ``W`` ``(points, (n+1)**2)`` (and the first row of each triangle)
    with ``W @ h`` = ``I - S`` at every
    vertex of the overlay of each moved triangle ``T`` of the strip with the cell
    triangulation (``T``'s edges cut by the lines ``i = m``, ``j = m`` and ``i - j = m``, and
    the grid vertices in ``T``): ``I - S`` is linear on each overlay piece, so its largest
    magnitude over ``T`` is at those points."""
    n = 1 << cells_log2
    out = []
    for part in strip_template(cells_log2, snaps):
        if part is None:
            out.append(None)
            continue
        tj, ti, box = part
        rows: list[np.ndarray] = []
        starts = []
        for t in range(len(tj)):
            starts.append(len(rows))
            corners = np.stack([ti[t], tj[t]], 1).astype(np.float64)  # (3, 2) (i, j)
            pts = []
            for e in range(3):
                p0, p1 = corners[e], corners[(e + 1) % 3]
                for f0, f1 in ((p0[0], p1[0]), (p0[1], p1[1]), (p0[0] - p0[1], p1[0] - p1[1])):
                    if f1 == f0:  # lines i = m, j = m, i - j = m parallel to this edge
                        continue
                    for m in range(int(np.ceil(min(f0, f1))), int(np.floor(max(f0, f1))) + 1):
                        pts.append(p0 + (m - f0) / (f1 - f0) * (p1 - p0))
            j0, j1, i0, i1 = box[t]
            for jj in range(j0, j1 + 1):
                for ii in range(i0, i1 + 1):
                    pts.append(np.array([ii, jj], np.float64))
            inv = np.linalg.inv((corners[1:] - corners[0]).T)
            ids = [int(corners[q, 1]) * (n + 1) + int(corners[q, 0]) for q in range(3)]
            for q in pts:
                lam = inv @ (q - corners[0])
                bary = np.array([1.0 - lam.sum(), lam[0], lam[1]])
                if (bary < -1e-9).any():
                    continue  # a grid vertex of the box outside T
                row = np.zeros((n + 1) ** 2)
                for vid, w in zip(ids, bary, strict=True):
                    row[vid] += w
                for vid, w in _surface_weights(n, float(q[0]), float(q[1])).items():
                    row[vid] -= w
                rows.append(row)
        out.append((np.array(rows), np.array(starts, dtype=np.int64)))
    return out


def snap_excess(
    cells_log2: np.ndarray,
    snap: np.ndarray,
    heights: Callable[[np.ndarray], np.ndarray],
    cell_bounds: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """``(m, 4)`` the largest ``e_T`` (module doc) of each patch's snapped strip per edge
    (0 where the edge is not snapped). ``heights(idx)`` returns the ``(len(idx), n+1, n+1)``
    level-``L`` vertex heights ``[row j, column i]`` of patches ``idx`` (all of one cell
    count); NaN heights (masked vertices) are ignored. With ``cell_bounds(idx)`` (``(len(idx),
    n, n)``: each level-``L`` cell's stored error, a bound on ``|h - S|`` in it) each triangle
    adds the largest of the cells of its bounding box: the result is then a bound on the whole
    error ``|h - I|`` of the strip's samples, not the excess over the patch's error."""
    cells = np.asarray(cells_log2, dtype=np.int64)
    sn = np.asarray(snap, dtype=np.int64).reshape(-1, 4)
    out = np.zeros((len(cells), 4))
    todo = np.flatnonzero(sn.max(axis=1) > 0)
    if not todo.size:
        return out
    key = np.concatenate([cells[todo, None], sn[todo]], 1)
    for grp in np.unique(key, axis=0):
        idx = todo[(key == grp).all(axis=1)]
        key_t = (int(grp[0]), tuple(int(t) for t in grp[1:]))
        tmpl = strip_template(*key_t)
        weights = difference_rows(*key_t)
        h = np.asarray(heights(idx), dtype=np.float64)
        cb = None if cell_bounds is None else np.asarray(cell_bounds(idx), dtype=np.float64)
        flat = h.reshape(len(idx), -1)
        masked = np.isnan(flat).any(axis=1)
        for e, part in enumerate(tmpl):
            if part is None:
                continue
            tj, ti, box = part
            w, starts = weights[e]
            d = np.abs(np.where(masked[:, None], 0.0, flat) @ w.T)  # (P, points)
            per_tri = np.maximum.reduceat(d, starts, axis=1)  # (P, triangles)
            if masked.any():
                corners = h[:, tj, ti]  # (P, m, 3)
                lo_t, hi_t = np.fmin.reduce(corners, axis=2), np.fmax.reduce(corners, axis=2)
            for u, (j0, j1, i0, i1) in enumerate(box.tolist()):
                if masked.any():
                    win = h[:, j0 : j1 + 1, i0 : i1 + 1].reshape(len(idx), -1)
                    lo_b, hi_b = np.fmin.reduce(win, axis=1), np.fmax.reduce(win, axis=1)
                    e_t = np.fmax(hi_b - lo_t[:, u], hi_t[:, u] - lo_b)
                    e_t = np.where(np.isfinite(e_t), e_t, 0.0)
                    per_tri[:, u] = np.where(masked, e_t, per_tri[:, u])
                if cb is not None:
                    per_tri[:, u] += cb[:, j0:j1, i0:i1].reshape(len(idx), -1).max(axis=1)
            out[idx, e] = per_tri.max(axis=1)
    return out


@cache
def sample_rows(cells_log2: int, snaps: tuple[int, int, int, int], spacing_log2: int) -> list:
    """Per edge: the full-resolution samples of the moved triangles of its strip, as flat
    indices into the patch's ``(n*2**s+1)**2`` sample window and, per sample, its triangle's 3
    corner indices and barycentric weights (``(q,)``, ``(q, 3)``, ``(q, 3)``)."""
    s = 1 << spacing_log2
    side = (1 << cells_log2) * s + 1
    out = []
    for part in strip_template(cells_log2, snaps):
        if part is None:
            out.append(None)
            continue
        tj, ti, box = part
        idx, cor, wts = [], [], []
        for t in range(len(tj)):
            cj, ci = tj[t] * s, ti[t] * s  # corners in sample coordinates
            a = np.array([ci[0], cj[0]], np.float64)
            inv = np.linalg.inv(np.array([[ci[1] - ci[0], ci[2] - ci[0]],
                                          [cj[1] - cj[0], cj[2] - cj[0]]], np.float64))  # fmt: skip
            j0, j1, i0, i1 = (int(v) * s for v in box[t])
            jj, ii = np.mgrid[j0 : j1 + 1, i0 : i1 + 1]
            lam = inv @ (np.stack([ii.ravel(), jj.ravel()]) - a[:, None])
            bary = np.stack([1.0 - lam.sum(0), lam[0], lam[1]], 1)
            inside = (bary >= -1e-12).all(axis=1)
            idx.append(jj.ravel()[inside] * side + ii.ravel()[inside])
            cor.append(np.broadcast_to(cj * side + ci, (int(inside.sum()), 3)))
            wts.append(bary[inside])
        out.append((np.concatenate(idx), np.concatenate(cor), np.concatenate(wts)))
    return out


def snap_exact(
    cells_log2: np.ndarray,
    spacing_log2: np.ndarray,
    snap: np.ndarray,
    windows: Callable[[np.ndarray], np.ndarray],
) -> np.ndarray:
    """``(m, 4)`` the exact largest ``|h - I|`` over the full-resolution samples of each
    patch's moved strip triangles per snapped edge (what the measurement sees there), from
    ``windows(idx)``: the ``(len(idx), side, side)`` full-resolution heights of patches ``idx``
    (one cell count and spacing; NaN = masked, ignored: such triangles are not drawn)."""
    cells = np.asarray(cells_log2, dtype=np.int64)
    sp = np.asarray(spacing_log2, dtype=np.int64)
    sn = np.asarray(snap, dtype=np.int64).reshape(-1, 4)
    out = np.zeros((len(cells), 4))
    todo = np.flatnonzero(sn.max(axis=1) > 0)
    if not todo.size:
        return out
    key = np.concatenate([cells[todo, None], sp[todo, None], sn[todo]], 1)
    for grp in np.unique(key, axis=0):
        idx = todo[(key == grp).all(axis=1)]
        rows = sample_rows(int(grp[0]), tuple(int(t) for t in grp[2:]), int(grp[1]))
        flat = np.asarray(windows(idx), dtype=np.float64).reshape(len(idx), -1)
        for e, part in enumerate(rows):
            if part is None:
                continue
            at, cor, w = part
            interp = (flat[:, cor] * w).sum(axis=2)
            d = np.abs(flat[:, at] - interp)
            worst = np.fmax.reduce(d, axis=1)
            out[idx, e] = np.where(np.isfinite(worst), worst, 0.0)
    return out
