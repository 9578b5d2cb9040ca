"""``seamless-patches``, one selection's frame (pure numpy, no GL): the camera, τ and the drawn
blocks' stored errors and z ranges, with the per-node figures the traversal asks for (stored
node errors, the paper's edge ε = ρ·l/d with the spike guard, node distances, the frustum
disc test) and the compiled kernels' argument tuples. :mod:`.selection` traverses with it."""

from __future__ import annotations

import numpy as np

from render.errors import SelectionError
from render.select import DiscCull
from render.strategies.seamless import kernels as sp_kernels
from render.strategies.seamless.layout import (
    RHO_FORMS,
    edge_epsilon,
    paper_precision,
    precision,
)
from render.strategies.seamless.meshes import DIRS
from streamer.camera import Camera
from streamer.frustum import frustum_hull
from streamer.levels import PatchErrorTable
from tiler.quadtree import block_origins, half_diagonal, node_centres_at, node_span

Block = tuple[int, int]


def neighbour_caps(blk: np.ndarray, cap: np.ndarray) -> np.ndarray:
    """Per drawn block (``(m, 2)`` distinct ids) the lowest cap of it and its drawn N, E, S, W
    neighbours, by a dense window over the blocks' bounding box with a margin of one."""
    if not len(blk):
        return cap.copy()
    r = blk[:, 0] - blk[:, 0].min() + 1
    c = blk[:, 1] - blk[:, 1].min() + 1
    win = np.full((int(r.max()) + 2, int(c.max()) + 2), np.iinfo(np.int64).max)
    win[r, c] = cap
    return np.minimum.reduce([cap, win[r - 1, c], win[r, c + 1], win[r + 1, c], win[r, c - 1]])


class SelectionFrame:
    """One selection's fixed inputs: blocks, caps, error grids, z ranges, camera, τ."""

    def __init__(self, st, camera: Camera, tau: float, resident: dict | None) -> None:
        r = st.r
        self.k, self.c, self.grid = r.k, st.c, r.grid
        self.camera, self.tau = camera, float(tau)
        pairs = r.drawable(resident)
        self.skipped = sum(1 for _, lv in pairs if lv < 1)
        pairs = [(b, lv) for b, lv in pairs if lv >= 1]
        self.blk = np.array([b for b, _ in pairs], dtype=np.int64).reshape(-1, 2)
        self.cap = np.array([lv for _, lv in pairs], dtype=np.int64)
        g = self.grid
        self.dmax = np.minimum(self.k - self.c, neighbour_caps(self.blk, self.cap) - 1)
        self.zr = st.zr
        win = r.store.index.window
        self.win = win
        if win is not None:  # per drawn block: the last node row/column start inside the DEM
            self.win_r = win[self.blk[:, 0], self.blk[:, 1], 2] - 1
            self.win_c = win[self.blk[:, 0], self.blk[:, 1], 3] - 1
        self.table = st.table
        drawn = [tuple(b) for b in self.blk.tolist()]
        r.fill_table(self.table, drawn, "bound")
        self.guard = bool(getattr(st, "spike_guard", False))
        self.rho_form = getattr(st, "rho", "bound")
        if self.rho_form not in RHO_FORMS:
            raise SelectionError(f"rho must be one of {RHO_FORMS}, got {self.rho_form!r}")
        self.tables = st.tables if self.guard else []
        for t in self.tables:
            r.fill_table(t, drawn, "bound")
        self.slots = self.table.slots(self.blk) if len(self.blk) else np.zeros(0, np.int64)
        keys = self.blk[:, 0] * g.cols + self.blk[:, 1]
        self.border = np.argsort(keys)
        self.bkeys = keys[self.border]
        self.focal = camera.focal_px
        self.eye = camera.eye
        #: the numba kernel module, or None for the numpy reference (``st.kernels``)
        self.nb = sp_kernels.resolve(getattr(st, "kernels", None))
        poly = frustum_hull(camera, r.terrain_zrange)
        self.cull = DiscCull(poly) if poly is not None and len(poly) else None
        #: one kernel call per depth (:meth:`fused_depth`; not with the spike guard, nor for a
        #: kernel module without it: the per-step kernels' positive controls)
        self.fused = self.nb is not None and not self.guard and hasattr(self.nb, "traverse_depth")
        #: the whole selection in one kernel call (:meth:`whole_args`), and each round of
        #: :func:`_resolve` in one (the guard's path); not for a kernel module without them
        self.whole = self.fused and hasattr(self.nb, "select_all")
        self.rounds = self.nb is not None and hasattr(self.nb, "resolve_round")
        self._whole_args: tuple | None = None

    def node_delta(
        self, d: int, gr: np.ndarray, gc: np.ndarray, table: PatchErrorTable | None = None
    ) -> np.ndarray:
        """Stored error (``bound``, level ``d + 1``; level ``d + r`` from ``table`` =
        ``tables[r - 1]``) of the depth-``d`` nodes at global node ``(gr, gc)``; -1 outside the
        drawn blocks."""
        table = self.table if table is None else table
        g, m = self.grid, len(self.blk)
        out = np.full(len(gr), -1.0)
        ok = (gr >= 0) & (gc >= 0) & (gr < g.rows << d) & (gc < g.cols << d)
        if not m or not ok.any():
            return out
        key = (gr[ok] >> d) * g.cols + (gc[ok] >> d)
        pos = np.minimum(np.searchsorted(self.bkeys, key), m - 1)
        hit = self.bkeys[pos] == key
        mask = (1 << d) - 1
        sub = np.flatnonzero(ok)[hit]
        slots = self.slots[self.border[pos[hit]]]
        out[sub] = table.delta(slots, d, gr[sub] & mask, gc[sub] & mask)
        return out

    def epsilon(self, idx: np.ndarray, d: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``(n, 4)`` ε of the nodes' edges N, E, S, W."""
        if self.nb is not None:
            return self._epsilon_nb(idx, d, rows, cols)
        g, k = self.grid, self.k
        size = 1 << (k - d)
        br, bc = self.blk[idx, 0], self.blk[idx, 1]
        gr, gc = (br << d) + rows, (bc << d) + cols
        nr_, nc_ = g.rows << d, g.cols << d
        own = self.node_delta(d, gr, gc)
        node_dist = self.node_distance(d, gr, gc, self.zr[br, bc]) if self.guard else None
        ex, ey, ez = self.eye
        out = np.zeros((len(idx), 4))
        corners = (
            (gr, gc, gr, gc + 1),
            (gr, gc + 1, gr + 1, gc + 1),
            (gr + 1, gc, gr + 1, gc + 1),
            (gr, gc, gr + 1, gc),
        )
        for e, (dr, dc) in enumerate(DIRS):
            nr, nc = gr + dr, gc + dc
            inb = (nr >= 0) & (nr < nr_) & (nc >= 0) & (nc < nc_)
            nrc, ncc = np.clip(nr, 0, nr_ - 1), np.clip(nc, 0, nc_ - 1)
            delta = np.maximum(own, self.node_delta(d, nr, nc))
            zo, zn = self.zr[br, bc], self.zr[nrc >> d, ncc >> d]
            zlo = np.where(inb, np.minimum(zo[:, 0], zn[:, 0]), zo[:, 0])
            zhi = np.where(inb, np.maximum(zo[:, 1], zn[:, 1]), zo[:, 1])
            r0, c0, r1, c1 = corners[e]
            xa, ya = g.sample_xy(r0 * size, c0 * size)
            xb, yb = g.sample_xy(r1 * size, c1 * size)
            hx = np.maximum(np.maximum(np.minimum(xa, xb) - ex, 0.0), ex - np.maximum(xa, xb))
            hy = np.maximum(np.maximum(np.minimum(ya, yb) - ey, 0.0), ey - np.maximum(ya, yb))
            v = np.maximum(np.maximum(ez - zhi, zlo - ez), 0.0)
            dist = np.sqrt(hx * hx + hy * hy + v * v)
            length = np.hypot(xb - xa, yb - ya)
            if self.rho_form == "paper":  # one factor for every edge; δ only for nodata
                rho = np.where(  # a mixed node's δ is ∞ (docs/RENDER.md, nodata): ours
                    np.isinf(delta), np.inf, paper_precision(self.tau, self.focal, self.c)
                )
            else:
                rho = precision(np.maximum(delta, 0.0), length, self.tau, self.focal, self.c)
            out[:, e] = edge_epsilon(rho, length, dist)
            if self.guard:
                out[:, e] = np.maximum(out[:, e], self._guard(d, gr, gc, nr, nc, node_dist))
        return out

    def _epsilon_nb(self, idx, d: int, rows, cols) -> np.ndarray:
        """:meth:`epsilon` by the compiled kernel (the same values; the guard stays numpy)."""
        g = self.grid
        arr = self.table.depth_array(d)
        paper = self.rho_form == "paper"
        prho = paper_precision(self.tau, self.focal, self.c) if paper else 0.0
        ex, ey, ez = (float(v) for v in self.eye)
        out = self.nb.epsilon(
            idx, rows, cols, d, self.k, self.blk, self.bkeys, self.border, self.slots,
            _NO_ARRAY if arr is None else arr, arr is not None, g.rows, g.cols, self.zr,
            float(g.x0), float(g.y0), float(g.dx), float(g.dy), ex, ey, ez,
            float(self.focal), self.tau, self.c, paper, prho,
        )  # fmt: skip
        if self.guard:
            br, bc = self.blk[idx, 0], self.blk[idx, 1]
            gr, gc = (br << d) + rows, (bc << d) + cols
            node_dist = self.node_distance(d, gr, gc, self.zr[br, bc])
            for e, (dr, dc) in enumerate(DIRS):
                guard = self._guard(d, gr, gc, gr + dr, gc + dc, node_dist)
                out[:, e] = np.maximum(out[:, e], guard)
        return out

    def node_distance(self, d: int, gr: np.ndarray, gc: np.ndarray, zo: np.ndarray) -> np.ndarray:
        """Distance from the eye to the nearest point of the depth-``d`` nodes' boxes."""
        g, size = self.grid, 1 << (self.k - d)
        ex, ey, ez = self.eye
        xa, ya = g.sample_xy(gr * size, gc * size)
        xb, yb = g.sample_xy((gr + 1) * size, (gc + 1) * size)
        hx = np.maximum(np.maximum(np.minimum(xa, xb) - ex, 0.0), ex - np.maximum(xa, xb))
        hy = np.maximum(np.maximum(np.minimum(ya, yb) - ey, 0.0), ey - np.maximum(ya, yb))
        v = np.maximum(np.maximum(ez - zo[:, 1], zo[:, 0] - ez), 0.0)
        return np.sqrt(hx * hx + hy * hy + v * v)

    def _guard(self, d, gr, gc, nr, nc, dist) -> np.ndarray:
        """The smallest ε that gives the edge a tile whose own stored error (the bound at its
        level ``d + r``, both sides) projects to ≤ τ at the node's nearest point (2, i.e.
        split, when even ``r = c`` does not): the paper's linear error-vs-cell model
        underestimates isolated spikes, whose error does not shrink with the cell."""
        need = np.full(len(gr), self.c + 1)
        for r in range(self.c, 0, -1):
            t = self.tables[r - 1]
            delta = np.maximum(self.node_delta(d, gr, gc, t), self.node_delta(d, nr, nc, t))
            with np.errstate(divide="ignore", invalid="ignore"):
                px = np.where(delta <= 0.0, 0.0, self.focal * delta / dist)
            need = np.where(px <= self.tau, r, need)
        return np.where(need > self.c, 2.0, np.ldexp(1.0, need - self.c))

    def visible(self, idx: np.ndarray, d: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Nodes whose bounding circle meets the ground frustum and that are not all padding."""
        g = self.grid
        size = node_span(self.k, d)
        keep = np.ones(len(idx), dtype=bool)
        if self.win is not None and len(idx):
            keep &= (rows * size < self.win_r[idx]) & (cols * size < self.win_c[idx])
        if self.cull is not None and len(idx) and self.nb is not None and not self.cull.empty:
            c = self.cull
            s = float(node_span(g.k, d))  # node_centres_at's span
            args = (c.o, c.px, c.py, c.ex, c.ey, c.ee_safe, c.ok, c.all_ok, c.ccw)
            keep &= self.nb.disc_meets(
                idx, rows, cols, self.blk, float(g.x0), float(g.y0), int(g.step), float(g.dx),
                float(g.dy), s * g.dx, s * g.dy, half_diagonal(g, d), args,
            )  # fmt: skip
        elif self.cull is not None and len(idx):
            bx0, by1 = block_origins(g, self.blk[idx, 0], self.blk[idx, 1])
            cx, cy = node_centres_at(g, bx0, by1, d, rows, cols)
            meets, _ = self.cull(cx, cy, half_diagonal(g, d))
            keep &= meets
        return keep

    def fused_depth(
        self, idx: np.ndarray, d: int, rows: np.ndarray, cols: np.ndarray
    ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...], int, bool]:
        """:meth:`visible`, :meth:`epsilon` and the split rule of one depth in one kernel call
        (numba, no spike guard): ``(leaves (idx, rows, cols, eps), children, clamped, any
        visible)``; the same values as the numpy steps of :func:`_traverse`."""
        g, k = self.grid, self.k
        mode, cull = self._cull_args()
        s = float(node_span(g.k, d))
        geo = (float(g.x0), float(g.y0), int(g.step), float(g.dx), float(g.dy), s * g.dx,
               s * g.dy, half_diagonal(g, d))  # fmt: skip
        arr = self.table.depth_array(d)
        paper = self.rho_form == "paper"
        prho = paper_precision(self.tau, self.focal, self.c) if paper else 0.0
        ex, ey, ez = (float(v) for v in self.eye)
        eps_args = (
            k, self.blk, self.bkeys, self.border, self.slots,
            _NO_ARRAY if arr is None else arr, arr is not None, g.rows, g.cols, self.zr,
            float(g.x0), float(g.y0), float(g.dx), float(g.dy), ex, ey, ez,
            float(self.focal), self.tau, self.c, paper, prho,
        )  # fmt: skip
        use_win = self.win is not None
        wr, wc = (self.win_r, self.win_c) if use_win else (_NO_INT, _NO_INT)
        return self.nb.traverse_depth(
            idx, rows, cols, d, k, self.c, use_win, wr, wc, mode, geo, cull, eps_args,
            self.dmax, self.cap,
        )  # fmt: skip

    def _cull_args(self) -> tuple:
        """The kernels' cull mode (0 none, 1 disc test, 2 nothing meets: an empty hull) and
        :class:`DiscCull` arrays."""
        if self.cull is None:
            return 0, _NO_CULL
        if self.cull.empty:
            return 2, _NO_CULL
        c = self.cull
        return 1, (c.o, c.px, c.py, c.ex, c.ey, c.ee_safe, c.ok, c.all_ok, c.ccw)

    def whole_args(self) -> tuple:
        """The arguments of the kernels' ``traverse_all`` after the seeds: :meth:`fused_depth`'s
        for every depth at once (made once per frame)."""
        if self._whole_args is None:
            self._whole_args = self._make_whole_args()
        return self._whole_args

    def _make_whole_args(self) -> tuple:
        g, k = self.grid, self.k
        mode, cull = self._cull_args()
        depths = range(0, k - self.c + 1)
        span = [float(node_span(g.k, d)) for d in depths]
        s_dx = np.array([s * g.dx for s in span])
        s_dy = np.array([s * g.dy for s in span])
        radius = np.array([half_diagonal(g, d) for d in depths], dtype=np.float64)
        arrs = [self.table.depth_array(d) for d in depths]
        has_arr = np.array([a is not None for a in arrs])
        arrs = tuple(_NO_ARRAY if a is None else a for a in arrs)
        paper = self.rho_form == "paper"
        prho = paper_precision(self.tau, self.focal, self.c) if paper else 0.0
        ex, ey, ez = (float(v) for v in self.eye)
        eps_args = (
            self.blk, self.bkeys, self.border, self.slots, g.rows, g.cols, self.zr,
            float(g.x0), float(g.y0), float(g.dx), float(g.dy), ex, ey, ez,
            float(self.focal), self.tau, self.c, paper, prho,
        )  # fmt: skip
        geo = (float(g.x0), float(g.y0), int(g.step), float(g.dx), float(g.dy))
        use_win = self.win is not None
        wr, wc = (self.win_r, self.win_c) if use_win else (_NO_INT, _NO_INT)
        return (
            k, self.c, use_win, wr, wc, mode, geo, s_dx, s_dy, radius, cull, arrs, has_arr,
            eps_args, self.dmax, self.cap,
        )  # fmt: skip

    def splittable(self, idx: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Nodes whose children can be drawn and be finer (resident levels, bottom depth)."""
        return (d + 1 <= self.dmax[idx]) & (d + self.c < self.cap[idx])


_NO_ARRAY = np.zeros((1, 1, 1), np.float32)  # the kernel's stand-in where a table has no depth
_NO_INT = np.zeros(0, np.int64)
_F0 = np.zeros(0)
_NO_CULL = (np.zeros(2), _F0, _F0, _F0, _F0, _F0, np.zeros(0, np.bool_), True, False)
