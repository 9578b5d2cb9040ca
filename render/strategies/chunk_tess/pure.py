"""``chunk-tessellation``, the pure part (no GL): Kim's chunk metric, the tessellator's triangle
count, the outer factors (CPU twin of ``chunk.tesc``) and the draw-call batch size."""

from __future__ import annotations

import numpy as np

from streamer.camera import Camera
from streamer.lod import exact_projected


def kim_metric(delta, centre_xyz, radius, camera: Camera) -> np.ndarray:
    """Pixel distance between the bounding sphere's point nearest the eye and that point raised
    by ``delta`` (inf when the eye is inside the sphere or the point is not in front)."""
    c = np.asarray(centre_xyz, dtype=np.float64)
    rad = np.broadcast_to(np.asarray(radius, dtype=np.float64), c.shape[:-1])
    d = np.broadcast_to(np.asarray(delta, dtype=np.float64), c.shape[:-1])
    to_eye = camera.eye - c
    dist = np.sqrt(np.einsum("...i,...i->...", to_eye, to_eye))
    inside = dist <= rad
    with np.errstate(invalid="ignore", divide="ignore"):
        p = c + to_eye * (rad / np.where(inside, 1.0, dist))[..., None]
        rho = exact_projected(d, p, camera)
    rho = np.where(np.isfinite(rho), rho, np.inf)
    return np.where(d == 0.0, 0.0, np.where(inside, np.inf, rho))


def tess_triangles(cells_log2: np.ndarray, snap: np.ndarray) -> np.ndarray:
    """Triangles the quad tessellator makes per chunk (inner ``2**c``, outer from the snaps)."""
    c = np.asarray(cells_log2, dtype=np.int64)
    n = np.left_shift(1, c)
    outer = np.left_shift(1, c[:, None] - np.asarray(snap, dtype=np.int64)).sum(axis=1)
    return np.where(n == 1, 2, 2 * (n - 2) ** 2 + 4 * (n - 2) + outer)


#: tessellated vertices per draw call that Mesa's llvmpipe hands to a geometry shader intact
#: (beyond 65,536 — 16-bit vertex indices — the GS receives corners of other triangles)
MAX_TESS_VERTICES = 65535


def batch_chunks(chunk_log2: int) -> int:
    """Chunks per draw call so that one call tessellates at most ``MAX_TESS_VERTICES``."""
    return max(1, MAX_TESS_VERTICES // ((1 << chunk_log2) + 1) ** 2)


def outer_factors(cells_log2: int, snap: tuple[int, int, int, int]) -> tuple[int, ...]:
    """GL outer levels ``[u=0 (W), v=0 (N), u=1 (E), v=1 (S)]`` of a chunk (CPU twin of the TCS)."""
    tn, te, ts, tw = snap
    return tuple(1 << (cells_log2 - t) for t in (tw, tn, te, ts))


def start_depth(k: int, chunk_log2: int) -> int:
    """The GPU traversal's first depth where a node may stop: ``max(0, k - 2c)``. Chunks then
    lie at depths ``start..k-c`` (a depth-``d`` chunk has level ``d + c``), so adjacent chunks
    differ by at most ``c`` levels and every outer factor ``2**(c - snap)`` is >= 1 without the
    CPU's restriction splits (:func:`render.select.stitch`)."""
    return max(0, k - 2 * chunk_log2)
