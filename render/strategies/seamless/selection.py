"""``seamless-patches``, the selection (pure numpy, no GL): the paper's ε = ρ·l/d per edge
(:mod:`.layout`) of every node, the top-down traversal and the resolution of shared edges into
:class:`PatchLayout`. The per-frame figures come from :class:`.frame.SelectionFrame`, which
reads the frame services' store, drawable blocks and terrain z range (``st.r``) and nothing on
the GPU."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from render.errors import SelectionError
from render.strategies.seamless.frame import SelectionFrame
from render.strategies.seamless.layout import (
    PatchLayout,
    edge_resolution,
)
from render.strategies.seamless.meshes import DIRS
from streamer.camera import Camera

Block = tuple[int, int]

if TYPE_CHECKING:
    from render.strategies.seamless.gl import SeamlessPatches


class _Leaves:
    """The growing leaf list (per traversal pass) and the clamped count."""

    def __init__(self) -> None:
        self.parts: list[tuple] = []
        self.clamped = 0


def _traverse(fr: SelectionFrame, seeds: dict[int, tuple], out: _Leaves) -> None:
    """Top-down from ``seeds`` (depth -> (idx, rows, cols)): split while some edge has ε > 1."""
    k, c = fr.k, fr.c
    if fr.fused and hasattr(fr.nb, "traverse_all"):  # every depth in one call: the same leaves
        if not seeds:
            return
        ds = sorted(seeds)
        sd = np.concatenate([np.full(len(seeds[d][0]), d, np.int64) for d in ds])
        si, sr, sc = (np.concatenate([seeds[d][i] for d in ds]).astype(np.int64) for i in range(3))
        *leaf, clamped = fr.nb.traverse_all(sd, si, sr, sc, *fr.whole_args())
        out.clamped += int(clamped)
        out.parts.append(tuple(leaf))
        return
    carry = None
    for d in range(0, k - c + 1):
        parts = [p for p in (carry, seeds.get(d)) if p is not None and len(p[0])]
        carry = None
        if not parts:
            continue
        idx, rows, cols = (np.concatenate([p[i] for p in parts]) for i in range(3))
        if fr.fused:  # the compiled depth in one call: the same leaves
            leaf, carry, clamped, seen = fr.fused_depth(idx, d, rows, cols)
            if seen:
                out.clamped += clamped
                out.parts.append((leaf[0], np.full(len(leaf[0]), d), *leaf[1:]))
                if not len(carry[0]):
                    carry = None
            else:
                carry = None
            continue
        keep = fr.visible(idx, d, rows, cols)
        idx, rows, cols = idx[keep], rows[keep], cols[keep]
        if not len(idx):
            continue
        eps = fr.epsilon(idx, d, rows, cols)
        want = (eps > 1.0).any(axis=1)
        can = fr.splittable(idx, np.full(len(idx), d))
        split = want & can
        out.clamped += int(np.count_nonzero(want & ~can & (d < k - c)))
        leaf = ~split
        out.parts.append(
            (idx[leaf], np.full(int(leaf.sum()), d), rows[leaf], cols[leaf], eps[leaf])
        )
        if split.any():
            si, sr, sc = idx[split], rows[split], cols[split]
            carry = _children(si, sr, sc)


def _children(idx, rows, cols):
    return (
        np.repeat(idx, 4),
        (2 * rows[:, None] + np.array([0, 0, 1, 1])).ravel(),
        (2 * cols[:, None] + np.array([0, 1, 0, 1])).ravel(),
    )


def _edge_groups(d: np.ndarray, gr: np.ndarray, gc: np.ndarray, nb=None) -> np.ndarray:
    """``(n, 4)`` group id (``leaf * 4 + edge`` of the group's coarsest member) of every leaf
    edge: a maximal shared edge is one leaf's edge and the same-size or smaller leaves' edges
    across it. The leaf across each edge is found at every depth with one ``searchsorted``."""
    n = len(d)
    if n == 0:
        return np.zeros((0, 4), np.int64)
    big = int(d.max())
    nr = (int((gr >> d).max()) + 2) << big
    nc = (int((gc >> d).max()) + 2) << big
    keys = (d * nr + gr) * nc + gc
    order = np.argsort(keys)
    sk = keys[order]
    if nb is not None:  # the compiled loops (``nb``: the kernel module), the same groups
        return nb.edge_groups(d, gr, gc, np.unique(d), order, sk, nr, nc)
    own = np.arange(4 * n).reshape(n, 4)
    out = own.copy()
    for e, (dr, dc) in enumerate(DIRS):
        r, c = gr + dr, gc + dc
        inside = (r >= 0) & (c >= 0)
        r, c = np.maximum(r, 0), np.maximum(c, 0)
        best = np.full(n, -1)
        best_d = np.full(n, -1)
        for dd in np.unique(d).tolist():
            shift = np.maximum(d - dd, 0)
            q = (dd * nr + (r >> shift)) * nc + (c >> shift)
            pos = np.minimum(np.searchsorted(sk, q), n - 1)
            hit = (sk[pos] == q) & inside & (dd <= d) & (dd > best_d)
            best = np.where(hit, order[pos], best)
            best_d = np.where(hit, dd, best_d)
        opp = (e + 2) % 4
        same = best_d == d
        coarse = (best >= 0) & ~same
        j = np.maximum(best, 0) * 4 + opp
        out[:, e] = np.where(same, np.minimum(own[:, e], j), np.where(coarse, j, own[:, e]))
    return out


_ROUNDS = 64  # resolution rounds before a selection is declared unsettled


def _resolve(fr: SelectionFrame, leaves: _Leaves, max_rounds: int = _ROUNDS) -> PatchLayout:
    """Group every shared edge, split coarse patches that cannot match, assign edge levels."""
    c = fr.c
    for _ in range(max_rounds):
        if leaves.parts:
            idx, d, rows, cols, eps = (
                np.concatenate([p[i] for p in leaves.parts]) for i in range(5)
            )
        else:
            idx = d = rows = cols = np.zeros(0, np.int64)
            eps = np.zeros((0, 4))
        idx, d, rows, cols = (a.astype(np.int64) for a in (idx, d, rows, cols))
        n = len(idx)
        if fr.rounds:  # the compiled round: the same split leaves, levels and violations
            split_any, v, level, violations = fr.nb.resolve_round(
                idx, d, rows, cols, eps, fr.blk, fr.cap, fr.dmax, c
            )
            if not split_any:
                return _layout(fr, idx, d, rows, cols, eps, level, leaves.clamped, violations)
            _resplit(fr, leaves, v, idx, d, rows, cols, eps)
            continue
        gr = (fr.blk[idx, 0] << d) + rows
        gc = (fr.blk[idx, 1] << d) + cols
        hi = np.minimum(d + c, fr.cap[idx])
        lo = d + 1
        want = np.minimum(d[:, None] + edge_resolution(eps, c), hi[:, None])
        can = fr.splittable(idx, d)
        gid = _edge_groups(d, gr, gc, fr.nb)
        g = gid.ravel()
        lo_e, hi_e = np.repeat(lo, 4), np.repeat(hi, 4)
        lo_g = np.full(4 * n, -(1 << 30))
        hi_g = np.full(4 * n, 1 << 30)
        want_g = np.full(4 * n, -(1 << 30))
        deep_g = np.full(4 * n, -1)
        size_g = np.zeros(4 * n, np.int64)
        np.maximum.at(lo_g, g, lo_e)
        np.minimum.at(hi_g, g, hi_e)
        np.maximum.at(want_g, g, want.ravel())
        np.maximum.at(deep_g, g, np.repeat(d, 4))
        np.add.at(size_g, g, 1)
        shared = size_g > 1
        j = np.arange(4 * n) // 4  # the group's coarsest leaf
        stuck = shared & ((lo_g > hi_g) | (want_g > hi_g))
        split = stuck & (hi[j] == hi_g) & can[j] & (deep_g > d[j])
        if not split.any():
            bad = lo_g[g] > hi_g[g]
            level = np.where(
                bad,
                np.clip(want_g[g], lo_e, hi_e),
                np.clip(want_g[g], lo_g[g], hi_g[g]),
            ).reshape(n, 4)
            violations = int(np.count_nonzero(shared & (lo_g > hi_g)))
            return _layout(fr, idx, d, rows, cols, eps, level, leaves.clamped, violations)
        _resplit(fr, leaves, np.unique(j[split]), idx, d, rows, cols, eps)
    raise SelectionError(f"seamless patches did not settle in {max_rounds} rounds")


def _resplit(fr: SelectionFrame, leaves: _Leaves, v, idx, d, rows, cols, eps) -> None:
    """Replace the leaves ``v`` (ascending) by their children, traversed down."""
    keep = np.ones(len(idx), dtype=bool)
    keep[v] = False
    leaves.parts = [(idx[keep], d[keep], rows[keep], cols[keep], eps[keep])]
    seeds: dict[int, tuple] = {}
    for dv in np.unique(d[v]).tolist():
        m = v[d[v] == dv]
        seeds[dv + 1] = _children(idx[m], rows[m], cols[m])
    _traverse(fr, seeds, leaves)


def _layout(fr: SelectionFrame, idx, d, rows, cols, eps, level, clamped: int, violations: int):
    return PatchLayout(
        blocks=fr.blk,
        block=idx,
        depth=d,
        row=rows,
        col=cols,
        edge_level=level.reshape(len(idx), 4).astype(np.int64),
        eps=eps,
        res_log2=fr.c,
        clamped=int(clamped) + fr.skipped,
        violations=int(violations),
    )


def select_layout(
    st: SeamlessPatches, camera: Camera, tau: float, resident: dict[Block, int] | None
) -> PatchLayout:
    """The leaf patches and edge levels of strategy ``st`` (its frame services ``st.r``, tile
    resolutions ``st.c``, error table ``st.table`` and block z ranges ``st.zr``) at ``tau``."""
    fr = SelectionFrame(st, camera, tau, resident)
    leaves = _Leaves()
    m = len(fr.blk)
    if fr.whole:  # one kernel call: the same layout
        zero = np.zeros(m, np.int64)
        out = fr.nb.select_all(
            zero, np.arange(m, dtype=np.int64), zero, zero, *fr.whole_args(), fr.blk, _ROUNDS
        )
        if not out[0]:
            raise SelectionError(f"seamless patches did not settle in {_ROUNDS} rounds")
        return _layout(fr, *out[1:])
    _traverse(fr, {0: (np.arange(m), np.zeros(m, np.int64), np.zeros(m, np.int64))}, leaves)
    return _resolve(fr, leaves)
