"""What share of the terrain in view the drawn surface covers (pure numpy, no GL).

The *in-view samples* of a camera are the full-resolution samples of every node the reference
selection (every visible node at full resolution) holds whose position projects into the
viewport and depth range: terrain samples at their true height, nodata samples at the middle of
the terrain's height range. :func:`coverage` gives the share of in-view terrain samples the
drawn triangles cover, the share of in-view nodata samples they cover (a hole drawn over), and
the terrain samples that lie in the lateral view in front of the camera but nearer than its near
plane (clipped by it, so not measured as error). A view with no terrain sample in it is an error
(:class:`render.errors.EmptyViewError`), not a perfect row.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from render import cracks, measure
from render.errors import EmptyViewError
from render.select import Patches

__all__ = ["Coverage", "EmptyViewError", "coverage", "in_view_samples"]
from streamer.camera import Camera
from tiler.grid import BlockGrid


@dataclass(frozen=True)
class Coverage:
    """Coverage figures of one drawn view (see the module doc)."""

    terrain_in_view: int
    nodata_in_view: int
    terrain_covered: float  # share of in-view terrain samples under the drawn surface
    nodata_covered: float  # share of in-view nodata samples under it (0 when none in view)
    near_clipped: int  # terrain samples in the lateral view nearer than the near plane


def in_view_samples(
    ref: Patches, grid: BlockGrid, camera: Camera, heights: Callable[[int], np.ndarray]
) -> tuple[np.ndarray, np.ndarray, int]:
    """Global keys (``row * (cols * step + 1) + col``) of the in-view terrain samples and
    in-view nodata samples of the reference selection ``ref``, and the near-clipped count."""
    wg = grid.cols * grid.step + 1
    terrain, nodata, clipped = [], [], []
    zs = []
    for b, rows, cols, _ in measure.lod_surface(ref, grid.k, heights):
        h = heights(b)[rows, cols]
        br, bc = (int(v) for v in ref.blocks[b])
        gr, gc = br * grid.step + rows, bc * grid.step + cols
        ok = np.isfinite(h)
        x, y = grid.sample_xy(gr, gc)
        _, _, _, keep = measure.project_in_view(camera, x[ok], y[ok], h[ok])
        terrain.append((gr[ok] * wg + gc[ok])[keep])
        if ok.any():
            zs.append((float(h[ok].min()), float(h[ok].max())))
        clipped.append((gr[ok] * wg + gc[ok])[_near_clipped(camera, x[ok], y[ok], h[ok])])
        if (~ok).any():
            nodata.append((gr[~ok], gc[~ok], x[~ok], y[~ok]))
    zmid = 0.5 * (min(z[0] for z in zs) + max(z[1] for z in zs)) if zs else 0.0
    nd = []
    for gr, gc, x, y in nodata:
        _, _, _, keep = measure.project_in_view(camera, x, y, np.full(x.shape, zmid))
        nd.append((gr * wg + gc)[keep])
    cat = lambda parts: np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)  # noqa: E731
    return cat(terrain), cat(nd), len(cat(clipped))


def _near_clipped(camera: Camera, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Mask of the points in the lateral view (inside the viewport's sides) in front of the
    camera but nearer than its near plane."""
    if not len(x):
        return np.zeros(0, bool)
    w, h = camera.viewport
    px, py, d = camera.project(np.stack([x, y, z], -1))
    with np.errstate(invalid="ignore"):
        lat = (px >= 0) & (px <= w) & (py >= 0) & (py <= h)
        return lat & (d > 0) & (d < camera.near)


def coverage(
    grid: BlockGrid,
    camera: Camera,
    ref: Patches,
    heights: Callable[[int], np.ndarray],
    tri_cr: np.ndarray,
    tri_h: np.ndarray,
) -> Coverage:
    """Coverage of the drawn triangles (global ``(col, row)`` corners, drawn heights) over
    the in-view samples of the reference selection ``ref``; :class:`EmptyViewError` when the
    view holds no terrain sample."""
    terrain, nodata, clipped = in_view_samples(ref, grid, camera, heights)
    if not len(terrain):
        raise EmptyViewError(
            f"the view from {tuple(round(v, 1) for v in camera.position)} (yaw {camera.yaw:g}, "
            f"pitch {camera.pitch:g}) holds no terrain sample ({len(nodata)} nodata samples, "
            f"{clipped} terrain samples nearer than the near plane {camera.near:g}): "
            "its error, crack and coverage figures would be vacuous; aim the camera at the "
            "terrain"
        )
    tri, h = cracks.drawn(tri_cr, tri_h)
    rows, cols, _ = measure.rasterise(tri, h) if len(tri) else (np.zeros(0, np.int64),) * 3
    wg = grid.cols * grid.step + 1
    covered = np.unique(np.asarray(rows, np.int64) * wg + np.asarray(cols, np.int64))
    t = float(np.isin(terrain, covered, assume_unique=True).mean())
    n = float(np.isin(nodata, covered, assume_unique=True).mean()) if len(nodata) else 0.0
    return Coverage(len(terrain), len(nodata), t, n, clipped)
