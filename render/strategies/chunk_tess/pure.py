"""``chunk-tessellation``, the pure part (no GL): Kim's chunk metric, the tessellator's triangle
count, the outer factors (CPU twin of ``chunk.tesc``) and the draw-call batch size."""

from __future__ import annotations

import numpy as np

from streamer.camera import Camera


def kim_metric(
    delta: np.ndarray, centre_xyz: np.ndarray, radius: np.ndarray, camera: Camera
) -> np.ndarray:
    """Pixel distance between the bounding sphere's point nearest the eye and that point raised
    by ``delta`` (inf when the eye is inside the sphere or the point is not in front).

    :func:`streamer.lod.exact_projected` with the camera coordinates written out component by
    component (no matrix product, whose rounding is the BLAS library's), so the compiled twin
    (``render._select_nb.kim_rho``) gives the same bits."""
    c = np.asarray(centre_xyz, dtype=np.float64)
    rad = np.broadcast_to(np.asarray(radius, dtype=np.float64), c.shape[:-1])
    d = np.broadcast_to(np.asarray(delta, dtype=np.float64), c.shape[:-1])
    e = camera.eye
    tx, ty, tz = e[0] - c[..., 0], e[1] - c[..., 1], e[2] - c[..., 2]
    dist = np.sqrt(tx * tx + ty * ty + tz * tz)
    inside = dist <= rad
    w, h = camera.viewport
    cr, cu, cf = camera.right, camera.up, camera.forward
    with np.errstate(invalid="ignore", divide="ignore"):
        s = rad / np.where(inside, 1.0, dist)
        px, py, pz = c[..., 0] + tx * s, c[..., 1] + ty * s, c[..., 2] + tz * s
        rx, ry = px - e[0], py - e[1]
        xy = []
        for z in (pz, pz + d):  # the point, then the point raised by delta
            rz = z - e[2]
            depth = rx * cf[0] + ry * cf[1] + rz * cf[2]
            f = np.where(depth > 0.0, camera.focal_px / depth, np.nan)
            xr = rx * cr[0] + ry * cr[1] + rz * cr[2]
            yu = rx * cu[0] + ry * cu[1] + rz * cu[2]
            xy.append((w / 2.0 + xr * f, h / 2.0 - yu * f))
        rho = np.hypot(xy[1][0] - xy[0][0], xy[1][1] - xy[0][1])
    rho = np.where(np.isfinite(rho), rho, np.inf)
    return np.where(d == 0.0, 0.0, np.where(inside, np.inf, rho))


kim_metric.select_kernel = "kim_rho"  # render.select_kernels: compiled as _select_nb.kim_rho


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
