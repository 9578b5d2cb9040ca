"""``jung-han``, the selection (CPU, no GL): per-block trees built from the resident level, the
top-down culling and bottom-up simplification at τ, the crack removal and the mesh assembly
(:class:`JungHanSelector`, the selecting half of :class:`render.strategies.jung_han.JungHan`).
It reads the frame services' store, masks, drawable blocks and GPU levels, nothing on the GPU."""

from __future__ import annotations

import time

import numpy as np

from render.select import check_tau
from render.strategies.jung_han import kernels as jh_kernels
from render.strategies.jung_han.pure import (
    BITS,
    EDGE_QUADS,
    FAN_EDGE,
    FAN_QUAD,
    OWN,
    TEMPLATE,
    BlockTree,
    JHSelection,
    LevelNodes,
    conform,
    corners_inside,
    gather,
    projected_bound,
    t_junctions,
    vertex_errors,
)
from streamer.camera import Camera
from streamer.frustum import as_polygon, frustum_hull, polygon_meets_rects
from tiler.layout import trailing_zeros

Block = tuple[int, int]


def _cat(parts: list[np.ndarray], empty: np.ndarray) -> np.ndarray:
    """``np.concatenate(parts)`` without copying a single part (``empty`` if none)."""
    if not parts:
        return empty
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


class JungHanSelector:
    """The CPU half of ``jung-han``: ``select`` over the frame services ``r``."""

    stitching = True  # False: no height adjustment nor split (crack positive control)

    def __init__(
        self,
        renderer,
        prune: bool = True,
        culled_collapse: bool = True,
        kernels: str | None = None,
    ) -> None:
        self.r = renderer
        self.prune = prune
        self.culled_collapse = culled_collapse
        #: backend of the traversal: None = ``TERRASTREAM_KERNELS`` (auto), "numba", "numpy"
        self.kernels = kernels
        self._trees: dict[Block, BlockTree] = {}
        self._forest: jh_kernels.Forest | None = None
        self._hoff = np.zeros(0, np.int64)  # the frame's trees' height offsets in the forest
        self._ws = np.zeros(0, np.int64)  # the compiled assembly's sort workspace, kept
        self._nd = [np.zeros((0, 8), np.int64), np.zeros(0, np.int64)]  # the traversal's nodes
        self._mod = None

    # -- per-block data ----------------------------------------------------------------------

    def tree(self, block: Block, level: int) -> BlockTree:
        """The block's quadtree data at resident level ``level`` (cached; rebuilt on change)."""
        t = self._trees.get(block)
        if t is None or t.level != level:
            h = self.r.block_grid(block, level).astype(np.float64)
            mask = self.r.mask(block)
            if mask is not None:
                s = 1 << (self.r.k - level)
                h[~mask[::s, ::s]] = np.nan
            mod = jh_kernels.resolve(self.kernels)
            tree = BlockTree.build(h) if mod is None else jh_kernels.build_tree(mod, h)
            t = self._trees[block] = tree
        return t

    def _resident(self, resident: dict[Block, int] | None) -> list[tuple[Block, int]]:
        for b in [b for b in self._trees if self.r.gpu_level(b) < 0]:
            del self._trees[b]  # released from the GPU
        return self.r.drawable(resident)

    # -- selection ---------------------------------------------------------------------------

    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
    ) -> tuple[JHSelection, float]:
        """Cull, simplify bottom-up at ``tau`` (``metric`` is ignored: δ_s is the paper's),
        remove cracks and build the mesh; returns it and the CPU ms."""
        t0 = time.perf_counter()
        r, g, k = self.r, self.r.grid, self.r.k
        tau = check_tau(tau)
        poly = frustum_hull(camera, r.terrain_zrange)
        pairs = self._resident(resident)
        blocks = [b for b, _ in pairs]
        lev = np.array([lv for _, lv in pairs], dtype=np.int64)
        trees = [self.tree(b, lv) for b, lv in pairs]
        blk = np.array(blocks, dtype=np.int64).reshape(-1, 2)
        r0, c0 = blk[:, 0] * g.step, blk[:, 1] * g.step
        mod = self._mod = jh_kernels.resolve(self.kernels)
        if mod is None:
            box = self._box(r0, c0, 1 << k)
            meets = polygon_meets_rects(poly, *box)
            inside = corners_inside(poly, *box)
            parts = self._traverse(camera, tau, poly, trees, lev, r0, c0, meets, inside)
        else:
            pa = self._poly_args(poly)
            r0, c0 = r0.astype(np.int64), c0.astype(np.int64)
            if len(pa[-1]):  # the blocks' hull tests compiled (the same as the two above)
                gg = (float(g.x0), float(g.y0), float(g.dx), float(g.dy))
                meets, inside = mod.block_hits(r0, c0, 1 << k, *pa, *gg)
            else:  # an empty hull meets nothing
                meets = inside = np.zeros(len(r0), dtype=bool)
            args = (camera, tau, pa, pairs, lev, r0, c0, meets, inside)
            parts = self._traverse_nb(mod, *args)
        tris, tslot, tlev, nodes, flags, clamped = parts
        corner = np.flatnonzero(meets & (lev == 0))
        if len(corner):
            s = 1 << k
            quad = np.array([[(0, 0), (s, 0), (s, s)], [(0, 0), (s, s), (0, s)]], dtype=np.int64)
            org = np.stack([c0[corner], r0[corner]], -1)[:, None, None, :]
            tris.append((org + quad[None]).reshape(-1, 3, 2))
            tslot.append(np.repeat(corner, 2))
            tlev.append(np.zeros(2 * len(corner), dtype=np.int64))
            clamped += int(k > 0) * len(corner)
        sel = self._assemble(blocks, lev, trees, r0, c0, tris, tslot, tlev, nodes, flags)
        sel.corner_blocks = len(corner)
        sel.clamped = clamped
        sel.evaluated = self._evaluated
        return sel, (time.perf_counter() - t0) * 1000.0

    def _box(self, r0, c0, size):
        """World ``(xmin, ymin, xmax, ymax)`` of squares of ``size`` samples at global origins."""
        g = self.r.grid
        xmin = g.x0 + np.asarray(c0, dtype=np.float64) * g.dx
        ymax = g.y0 - np.asarray(r0, dtype=np.float64) * g.dy
        return xmin, ymax - size * g.dy, xmin + size * g.dx, ymax

    def _own(self, camera, trees, lev, r0, c0, nodes: LevelNodes, sel: np.ndarray, d: int):
        """``(n, 5)`` δ_s of the C, T, B, L, R vertices of the selected blocks of a depth."""
        k, g = self.r.k, self.r.grid
        size = 1 << (k - d)
        half = size >> 1
        slot = np.repeat(nodes.slot[sel], 5)
        lr = (np.repeat(nodes.row[sel] * size, 5) + np.tile(OWN[:, 1], len(sel)) * half).ravel()
        lc = (np.repeat(nodes.col[sel] * size, 5) + np.tile(OWN[:, 0], len(sel)) * half).ravel()
        sh = k - lev[slot]
        flat = (lr >> sh) * ((1 << lev[slot]) + 1) + (lc >> sh)
        h = gather([t.heights for t in trees], slot, flat)
        dl = gather([t.delta for t in trees], slot, flat)
        x, y = g.sample_xy(r0[slot] + lr, c0[slot] + lc)
        return vertex_errors(dl, np.stack([x, y, h], -1), camera).reshape(-1, 5)

    def _traverse(self, camera, tau, poly, trees, lev, r0, c0, meets, inside):
        k = self.r.k
        roots = np.flatnonzero(meets & (lev >= 1))
        z = np.zeros(len(roots), dtype=np.int64)
        cur = LevelNodes(roots, z, z, z, inside[roots], z - 1, z - 1)
        levels: list[LevelNodes] = []
        d = 0
        while len(cur.slot):
            size = 1 << (k - d)
            cur.leaf = lev[cur.slot] - 1 == d
            cur.pruned = np.zeros(len(cur.slot), dtype=bool)
            if self.prune and d >= 1:
                cand = np.flatnonzero(cur.inside | self.culled_collapse)
                if len(cand):
                    s, i = cur.slot[cand], cur.idx[cand]
                    xmin, ymin, xmax, ymax = self._box(
                        r0[s] + cur.row[cand] * size, c0[s] + cur.col[cand] * size, size
                    )
                    b = projected_bound(
                        camera,
                        gather([t.dmax[d] if d < t.level else None for t in trees], s, i),
                        xmin,
                        xmax,
                        ymin,
                        ymax,
                        gather([t.zlo[d] if d < t.level else None for t in trees], s, i),
                        gather([t.zhi[d] if d < t.level else None for t in trees], s, i),
                    )
                    cur.pruned[cand] = b < tau
            levels.append(cur)
            exp = np.flatnonzero(~cur.pruned & ~cur.leaf)
            if not len(exp):
                break
            par = np.repeat(exp, 4)
            q = np.tile(np.arange(4, dtype=np.int64), len(exp))
            slot = cur.slot[par]
            row = 2 * cur.row[par] + 1 - (q >> 1)
            col = 2 * cur.col[par] + (q & 1)
            half = size >> 1
            ins = cur.inside[par].copy()
            hit = ins.copy()
            test = np.flatnonzero(~ins)
            if len(test):
                bx = self._box(
                    r0[slot[test]] + row[test] * half, c0[slot[test]] + col[test] * half, half
                )
                hit[test] = polygon_meets_rects(poly, *bx)
                ins[test] = hit[test] & corners_inside(poly, *bx)
            keep = np.flatnonzero(hit)
            cur = LevelNodes(
                slot[keep],
                4 * cur.idx[par[keep]] + q[keep],
                row[keep],
                col[keep],
                ins[keep],
                par[keep],
                q[keep],
            )
            d += 1
        tris, tslot, tlev, nodes, flags = [], [], [], [], []
        clamped = 0
        self._evaluated = 0
        below = None
        for d in range(len(levels) - 1, -1, -1):
            cur = levels[d]
            m = len(cur.slot)
            size = 1 << (k - d)
            cm = np.zeros((m, 4), dtype=np.int8)  # 0: culled (or none: a leaf)
            if below is not None:
                cm[below.ppos, below.quad] = below.state
            culled = ~cur.leaf[:, None] & (cm == 0)
            present = cur.leaf[:, None] | (cm == 2) | (culled & self.culled_collapse)
            act = np.flatnonzero(~cur.pruned)
            ds = np.full((m, 5), np.inf)
            self._evaluated += len(act)
            if len(act):
                ds[act] = self._own(camera, trees, lev, r0, c0, cur, act, d)
            removed = (
                present[:, EDGE_QUADS[:, 0]] & present[:, EDGE_QUADS[:, 1]] & (ds[:, 1:] < tau)
            )
            coll = (d >= 1) & removed.all(axis=1) & (ds[:, 0] < tau)
            cur.state = np.where(cur.pruned | coll, 2, 1).astype(np.int8)
            below = cur
            drawn = np.flatnonzero(cur.state == 1)
            fl = np.concatenate(
                [
                    present[drawn][:, FAN_QUAD]
                    & ~removed[drawn][:, FAN_EDGE]
                    & ~culled[drawn][:, FAN_QUAD],  # (culled_collapse: off screen, not drawn)
                    removed[drawn],
                ],
                1,
            )
            bits = fl.astype(np.int64) @ BITS
            has = bits != 0
            drawn, fl, bits = drawn[has], fl[has], bits[has]
            nodes.append(np.stack([cur.slot[drawn], np.full(len(drawn), d), cur.idx[drawn]], -1))
            flags.append(bits)
            clamped += int((cur.leaf[drawn] & (lev[cur.slot[drawn]] < k)).sum())
            j, t = np.nonzero(fl)
            j = drawn[j]
            org = np.stack(
                [c0[cur.slot[j]] + cur.col[j] * size, r0[cur.slot[j]] + cur.row[j] * size], -1
            )
            tris.append(org[:, None, :] + TEMPLATE[t] * (size >> 1))
            tslot.append(cur.slot[j])
            tlev.append(np.full(len(j), d + 1, dtype=np.int64))
        return tris, tslot, tlev, nodes, flags, clamped

    @staticmethod
    def _poly_args(poly) -> tuple:
        """The hull as the compiled tests take it: ``(o, extents, normals, pmin, pmax, q, e)``
        (``q``: the vertices minus ``o``, none for an empty hull; as ``polygon_meets_rects``
        and ``corners_inside`` compute them)."""
        p = as_polygon(poly)
        o = p[0] if len(p) else np.zeros(2)
        pp = p - o
        ext = np.zeros(4)
        normals = np.zeros((0, 2))
        pmin = pmax = np.zeros(0)
        # the edges, as np.roll(pp, -1, axis=0) - pp (computed once, for both tests)
        e = np.concatenate((pp[1:], pp[:1])) - pp
        if len(pp):
            lo, hi = pp.min(axis=0), pp.max(axis=0)
            ext = np.array([lo[0], hi[0], lo[1], hi[1]])
        if len(pp) >= 2:  # as polygon_meets_rects
            normals = np.empty_like(e)
            normals[:, 0], normals[:, 1] = -e[:, 1], e[:, 0]
            proj = pp @ normals.T
            pmin, pmax = proj.min(axis=0), proj.max(axis=0)
        return (
            np.ascontiguousarray(o, dtype=np.float64),
            ext,
            normals,
            np.ascontiguousarray(pmin),
            np.ascontiguousarray(pmax),
            np.ascontiguousarray(pp),
            e,
        )

    def _traverse_nb(self, mod, camera, tau, pa, pairs, lev, r0, c0, meets, inside):
        """``_traverse`` by the compiled kernel (same outputs, see ``_kernels_nb``); ``pa``:
        :meth:`_poly_args` of the hull."""
        # every cached tree in the forest's flat arrays: only the trees built, rebuilt or
        # dropped since the last frame are copied in or freed
        if self._forest is None:
            self._forest = jh_kernels.Forest()
        f = self._forest
        f.sync(self._trees)
        hoff, poff = f.offsets([b for b, _ in pairs])
        self._hoff = hoff  # for the compiled assembly
        g = self.r.grid
        roots = np.flatnonzero(meets & (lev >= 1)).astype(np.int64)
        tri, ts, tl, nodes, flags, clamped, self._evaluated, *self._nd = mod.traverse(
            f.heights, f.delta, f.pyramid, hoff, poff,
            lev, r0, c0, roots, inside[roots].astype(np.int64), *pa,
            np.stack([camera.right, camera.up, camera.forward]), camera.eye, float(camera.focal_px),
            float(tau),
            float(g.x0), float(g.y0), float(g.dx), float(g.dy), int(self.r.k),
            bool(self.prune), bool(self.culled_collapse), *self._nd,
        )  # fmt: skip
        return [tri], [ts], [tl], [nodes], [flags], int(clamped)

    def _unique(self, key: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sorted unique keys, first occurrences, inverse (``np.unique``)."""
        uk, first, inv = np.unique(key, return_index=True, return_inverse=True)
        return uk, first, inv.ravel()

    def _assemble_nb(self, blocks, lev, r0, c0, tri, slot, tl, node_arr, flag_arr, wg):
        """``_assemble`` by the compiled kernel (same outputs, see ``_assemble_nb``)."""
        g = self.r.grid
        jh_count = len(tri)
        need = self._mod.ws_size_assemble(len(tri))
        if len(self._ws) < need:
            self._ws = np.empty(need + need // 4, np.int64)
        out = self._mod.assemble(  # the traversal packed the forest and set _hoff this frame
            np.ascontiguousarray(tri, dtype=np.int64), slot, tl, self._forest.heights,
            np.ascontiguousarray(self._hoff, dtype=np.int64), lev, r0.astype(np.int64),
            c0.astype(np.int64), int(wg), int(self.r.k), int(g.step), bool(self.stitching),
            self._ws,
        )  # fmt: skip
        tri, tri_h, slot, tl, adjusted, v_slot, v_level, v_cr, v_h, index, ok = out
        if not ok:
            raise RuntimeError("conforming split did not converge")
        return JHSelection(
            blocks=blocks,
            levels=lev,
            tri=tri,
            tri_h=tri_h,
            jh_triangles=jh_count,
            tri_slot=slot,
            tri_level=tl,
            nodes=node_arr,
            flags=flag_arr,
            adjusted=adjusted,
            corner_blocks=0,
            clamped=0,
            v_slot=v_slot,
            v_level=v_level,
            v_cr=v_cr,
            v_h=v_h,
            index=index,
        )

    def _assemble(self, blocks, lev, trees, r0, c0, tris, tslot, tlev, nodes, flags):
        """Drawn heights, the crack pass, and the GPU vertex/index arrays."""
        k, g = self.r.k, self.r.grid
        e2 = np.zeros((0, 3, 2), dtype=np.int64)
        tri = _cat(tris, e2)
        slot = _cat(tslot, np.zeros(0, np.int64)).astype(np.int64, copy=False)
        tl = _cat(tlev, np.zeros(0, np.int64)).astype(np.int64, copy=False)
        node_arr = _cat(nodes, np.zeros((0, 3), np.int64))
        flag_arr = _cat(flags, np.zeros(0, np.int64))
        wg = g.cols * g.step + 1
        if self._mod is not None:
            return self._assemble_nb(blocks, lev, r0, c0, tri, slot, tl, node_arr, flag_arr, wg)
        order = np.argsort(slot, kind="stable")
        tri, slot, tl = tri[order], slot[order], tl[order]
        cs, rs = tri[..., 0].ravel(), tri[..., 1].ravel()
        key = rs * wg + cs
        uk, first, inv = self._unique(key)
        s3 = np.repeat(slot, 3)
        sh = k - lev[s3]
        flat = ((rs - r0[s3]) >> sh) * ((1 << lev[s3]) + 1) + ((cs - c0[s3]) >> sh)
        h_corner = gather([t.heights for t in trees], s3, flat)
        hv = h_corner[first]
        vrow, vcol = uk // wg, uk % wg
        ids, ends, frac = t_junctions(tri, vcol, vrow)
        if not self.stitching:  # the positive control: no height adjustment, no split
            ids = ids[:0]
        if len(ids):
            step = g.step
            tz = np.minimum(
                trailing_zeros(vcol[ids] % step, k), trailing_zeros(vrow[ids] % step, k)
            )
            vlev = k - tz
            ia = np.searchsorted(uk, ends[:, 0, 1] * wg + ends[:, 0, 0])
            ib = np.searchsorted(uk, ends[:, 1, 1] * wg + ends[:, 1, 0])
            for lv in np.unique(vlev):
                w = vlev == lv
                ha, hb = hv[ia[w]], hv[ib[w]]
                new = ha + frac[w] * (hb - ha)
                old = hv[ids[w]]
                hv[ids[w]] = np.where(np.isfinite(new) & np.isfinite(old), new, old)
        adjusted = np.stack([vcol[ids], vrow[ids]], -1)
        jh_count = len(tri)
        if self.stitching:
            tri, slot, tl = conform(tri, slot, tl, vcol, vrow)
        tkey = tri[..., 1] * wg + tri[..., 0]
        inv = np.searchsorted(uk, tkey.ravel())
        tri_h = hv[inv].reshape(-1, 3)
        s3 = np.repeat(slot, 3)
        # GPU vertices: one per (slot, drawn level, sample), in the order of their first corners
        nv = len(uk)
        gk = (s3 * 16 + np.repeat(tl, 3)) * max(nv, 1) + inv
        _, gfirst, ginv = self._unique(gk)
        order = np.argsort(gfirst)
        gfirst = gfirst[order]
        ginv = np.argsort(order)[ginv]
        vid = inv[gfirst]
        return JHSelection(
            blocks=blocks,
            levels=lev,
            tri=tri,
            tri_h=tri_h,
            jh_triangles=jh_count,
            tri_slot=slot,
            tri_level=tl,
            nodes=node_arr,
            flags=flag_arr,
            adjusted=adjusted,
            corner_blocks=0,
            clamped=0,
            v_slot=s3[gfirst],
            v_level=np.repeat(tl, 3)[gfirst],
            v_cr=np.stack([vcol[vid], vrow[vid]], -1),
            v_h=np.nan_to_num(hv[vid], nan=0.0).astype(np.float64),
            index=ginv.reshape(-1, 3).astype(np.int64),
        )
