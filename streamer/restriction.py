"""Levels that stitching can join (pure numpy, no I/O).

The renderer stitches neighbouring patches by snapping a patch's edge to a coarser neighbour,
or by splitting that neighbour when its vertex spacing is wider than the patch's whole edge
(:func:`render.select.stitch`). A neighbour held at its block's resident level cannot split:
with patches of ``2**p`` cells the deepest patch of a block at level ``L`` has depth ``L - p``,
so every edge neighbour must be able to reach level ``L - p``, or their border keeps
T-junctions (open edges and cracks; seen with ``p = 1`` at wide fields of view, where a block
at the side of the view needs far less than the block beside it).

:func:`restrict_levels` raises each block's planned level to at least ``p`` below each edge
neighbour's, so the session loads what the border needs."""

from __future__ import annotations

from types import ModuleType

import numpy as np


def restrict_levels(
    ids: np.ndarray, levels: np.ndarray, p: int, kernels: ModuleType | None = None
) -> np.ndarray:
    """``levels`` (one per row of the ``(m, 2)`` block ids) raised so that no block is more
    than ``p`` levels below an edge-adjacent block of ``ids`` (the least raise: values only
    grow, to a fixpoint, and never above the largest input level). ``kernels``: the compiled
    planning kernels (:func:`streamer.levels.kernels`), else this numpy reference."""
    lv = np.ascontiguousarray(levels, dtype=np.int64)
    blk = np.asarray(ids, dtype=np.int64).reshape(-1, 2)
    if len(blk) < 2:
        return lv.copy()
    if kernels is not None:
        out = np.empty(len(lv), dtype=np.int64)
        kernels.restrict_levels(
            np.ascontiguousarray(blk[:, 0]), np.ascontiguousarray(blk[:, 1]), lv, int(p), out
        )
        return out
    lo = blk.min(axis=0)
    rr, cc = blk[:, 0] - lo[0] + 1, blk[:, 1] - lo[1] + 1
    shape = tuple((blk.max(axis=0) - lo + 3).tolist())
    floor = int(lv.min()) - p - 1  # below anything: absent blocks raise nothing
    g = np.full(shape, floor, dtype=np.int64)
    g[rr, cc] = lv
    inside = np.zeros(shape, dtype=bool)
    inside[rr, cc] = True
    for _ in range(len(blk)):  # a raise travels at most one block per pass
        nb = np.maximum(
            np.maximum(g[:-2, 1:-1], g[2:, 1:-1]), np.maximum(g[1:-1, :-2], g[1:-1, 2:])
        )
        want = np.where(inside[1:-1, 1:-1], np.maximum(g[1:-1, 1:-1], nb - p), floor)
        if np.array_equal(want, g[1:-1, 1:-1]):
            break
        g[1:-1, 1:-1] = want
    return g[rr, cc]
