"""Nodata boundaries at every τ (issue 12): a node whose closed footprint holds both valid and
masked samples is refined to full resolution, so terrain beside nodata is drawn from its valid
samples and no hole is bridged. The renderer raises the stored errors of such nodes to ``inf``
(:func:`raise_mixed`); the loader hands the session the same errors, so the session streams
the levels the renderer then draws (docs/RENDER.md, "Precision and extremes")."""

from __future__ import annotations

import numpy as np


def mixed_nodes(valid: np.ndarray, k: int) -> list[np.ndarray]:
    """Per depth ``d <= k``, ``(2**d, 2**d)`` booleans: the node's closed footprint (borders
    included) holds both valid and masked samples of the ``(2**k+1)²`` mask ``valid``."""
    v = np.asarray(valid, dtype=bool)
    quad = (v[:-1, :-1], v[1:, :-1], v[:-1, 1:], v[1:, 1:])
    anyv = quad[0] | quad[1] | quad[2] | quad[3]
    anym = ~(quad[0] & quad[1] & quad[2] & quad[3])
    out = [anyv & anym]
    for d in range(k - 1, -1, -1):
        n = 1 << d
        anyv = anyv.reshape(n, 2, n, 2).any(axis=(1, 3))
        anym = anym.reshape(n, 2, n, 2).any(axis=(1, 3))
        out.append(anyv & anym)
    return out[::-1]


def raise_mixed(field: list[np.ndarray], mixed: list[np.ndarray]) -> list[np.ndarray]:
    """``field`` (one array per depth ``0..k-1``, tiled below its cap) with the nodes of
    ``mixed`` at ``inf`` (a tile is raised when any of its nodes is mixed); level ``k`` has no
    stored error, so a mask boundary is drawn at full resolution."""
    out = []
    for d, arr in enumerate(field):
        n, m = arr.shape[0], mixed[d].shape[0]
        tiles = mixed[d].reshape(n, m // n, n, m // n).any(axis=(1, 3))
        out.append(np.where(tiles, np.float32(np.inf), arr).astype(arr.dtype))
    return out


def boundary_errors(store, block: tuple[int, int], field: str) -> list[np.ndarray]:
    """The block's stored error ``field`` with its mask boundaries raised (:func:`raise_mixed`);
    the stored field itself when the block has no nodata or padding."""
    errors = store.read_errors(block)[field]
    if not bool(store.index.has_nodata[block]):
        return errors
    mask = store.read_mask(block)
    if mask.all() or not mask.any():
        return errors
    return raise_mixed(errors, mixed_nodes(mask, store.k))
