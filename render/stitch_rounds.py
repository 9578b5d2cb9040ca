"""What :func:`render.select.stitch` carries from one round to the next (pure numpy): the
neighbour of every edge and the snapped-edge check of every edge, updated for the leaves a round
changed instead of recomputed for all (the same answers: tests/render/test_stitch_rounds.py).

A round replaces some leaves (the victims) by their four children, kept leaves first in order,
then the children (:func:`render.select._split`). Leaves partition the covered ground, so an
edge's probe lies in exactly one leaf (or none); it moves to another leaf only when that leaf
was split, and a deeper finest depth moves a probe only within its old probe cell (one finest
node beyond the edge midpoint). So a kept leaf's neighbour is its old one renumbered unless that
one was a victim; those edges and the children's are probed again (:func:`neighbours_of`). A
snapped edge's check (:func:`render.node_boxes.snap_over`) depends only on its patch and the
patch's four snaps, so it is redone only for new patches and patches whose snaps changed
(:class:`OverCache`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from render.select import Patches


def leaf_keys(patches: Patches) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, int]:
    """Global node rows and columns at each leaf's depth, the finest depth and the key ranges."""
    big = int(patches.depth.max())
    blk = patches.blocks[patches.block]
    nr = (int(patches.blocks[:, 0].max()) + 2) << big
    nc = (int(patches.blocks[:, 1].max()) + 2) << big
    d = patches.depth
    return (blk[:, 0] << d) + patches.row, (blk[:, 1] << d) + patches.col, d, big, nr, nc


def neighbours_of(patches: Patches, rows: np.ndarray) -> np.ndarray:
    """``(len(rows), 4)`` index of the leaf across each edge (N, E, S, W) of the leaves ``rows``,
    or -1: each edge's probe (one finest node beyond its midpoint) looked up at every depth
    holding leaves in one ``searchsorted`` over the sorted leaf keys, the deepest hit winning
    (:func:`render.select._neighbours` with all rows)."""
    rows = np.asarray(rows, dtype=np.int64)
    n = len(patches)
    if n == 0 or not rows.size:
        return np.full((len(rows), 4), -1, dtype=np.int64)
    gr, gc, d, big, nr, nc = leaf_keys(patches)
    keys = (d * nr + gr) * nc + gc
    order = np.argsort(keys)
    sk = keys[order]
    dr, gr, gc = d[rows], gr[rows], gc[rows]
    span = np.left_shift(1, big - dr)
    fr0, fc0 = gr << (big - dr), gc << (big - dr)
    mid = span >> 1
    fr = np.concatenate([fr0 - 1, fr0 + mid, fr0 + span, fr0 + mid])
    fc = np.concatenate([fc0 + mid, fc0 + span, fc0 + mid, fc0 - 1])
    inside = (fr >= 0) & (fc >= 0) & (fr < nr) & (fc < nc)
    dd = np.unique(d)[:, None]
    q = (dd * nr + (fr >> (big - dd))) * nc + (fc >> (big - dd))
    pos = np.searchsorted(sk, q)
    np.clip(pos, 0, n - 1, out=pos)
    hit = (sk[pos] == q) & inside
    last = len(dd) - 1 - np.argmax(hit[::-1], axis=0)
    found = hit.any(axis=0)
    out = np.where(found, order[pos[last, np.arange(4 * len(rows))]], -1)
    return out.reshape(4, len(rows)).T.copy()


def renumber(nbr: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """After a split (kept leaves first, then the children): the kept leaves' neighbours in the
    new numbering and which of their edges pointed at a victim (to probe again)."""
    new = np.cumsum(keep) - 1
    old = nbr[keep]
    stale = (old >= 0) & ~keep[np.maximum(old, 0)]
    return np.where((old >= 0) & ~stale, new[np.maximum(old, 0)], -1), stale


def neighbours_after_split(patches: Patches, nbr: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The new leaves' ``(n, 4)`` neighbours from the old ones ``nbr`` and the split's ``keep``
    mask (``patches``: the leaves after the split)."""
    kept, stale = renumber(nbr, keep)
    n_keep = len(kept)
    redo = np.concatenate([np.flatnonzero(stale.any(axis=1)), np.arange(n_keep, len(patches))])
    out = np.concatenate([kept, np.full((len(patches) - n_keep, 4), -1, np.int64)])
    if redo.size:
        out[redo] = neighbours_of(patches, redo)
    return out


class OverCache:
    """Per leaf the snaps its edges were last checked with and the answer
    (:func:`render.node_boxes.snap_over`'s row), kept through splits."""

    def __init__(self, n: int) -> None:
        self.snap = np.zeros((n, 4), dtype=np.int64)
        self.over = np.zeros((n, 4), dtype=bool)
        self.known = np.zeros(n, dtype=bool)

    def over_edges(
        self,
        cur: Patches,
        snap: np.ndarray,
        check: Callable[[Patches, np.ndarray], np.ndarray],
    ) -> np.ndarray:
        """``check(cur, snap)`` (``(n, 4)``), computed only for the leaves whose snaps are new
        (``check`` of a subset of the patches)."""
        todo = ~self.known | (snap != self.snap).any(axis=1)
        cand = todo & (snap.max(axis=1) > 0) & np.isfinite(cur.delta)
        self.over[todo] = False
        if cand.any():
            self.over[cand] = check(cur.subset(cand), snap[cand])
        self.snap[todo] = snap[todo]
        self.known[todo] = True
        return self.over.copy()

    def split(self, keep: np.ndarray, children: int) -> None:
        """Follow a split: the kept leaves' rows first, then ``children`` unknown ones."""
        self.snap = np.concatenate([self.snap[keep], np.zeros((children, 4), np.int64)])
        self.over = np.concatenate([self.over[keep], np.zeros((children, 4), bool)])
        self.known = np.concatenate([self.known[keep], np.zeros(children, bool)])
