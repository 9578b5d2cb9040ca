"""The cracks a tradeoff view's own selection shows (:func:`render.pipeline.tradeoff`'s crack
columns): :func:`drawn_cracks`, counted from the view's camera and from above, only where the
reference's surface lies in the view (:func:`in_view`); :func:`nadir_for`, a straight-down
camera over the view's centre. They draw with the renderer (a GL context)."""

from __future__ import annotations

from typing import Any

import numpy as np

from render import cracks, measure
from render.renderer import CLEAR, TerrainRenderer
from streamer.camera import Camera


def nadir_for(camera: Camera, zmid: float) -> Camera:
    """A straight-down camera over the point the view centre looks at (for crack counting)."""
    f = camera.forward
    eye = camera.eye
    t = (zmid - eye[2]) / f[2] if f[2] < -1e-6 else 0.0
    gx, gy = (eye[:2] + t * f[:2]) if t > 0 else eye[:2]
    h = max(abs(eye[2] - zmid), 1.0)
    return Camera(
        (gx, gy, zmid + h),
        pitch=-90.0,
        fov_y=camera.fov_y,
        viewport=camera.viewport,
        near=camera.near,
        far=camera.far,
    )


def drawn_cracks(
    r: TerrainRenderer,
    strat: Any,
    camera: Camera,
    sel: Any,
    ref_p: Any,
    footprint: np.ndarray,
    triangles: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[int, int]:
    """Crack pixels of the view's own selection ``sel``: seen from ``camera`` (inside the
    reference's ``footprint``) and from above (:func:`render.cracks.above_camera` framing the
    drawn triangles — ``triangles``, default ``strat.triangles(camera, sel)`` — inside the
    reference selection ``ref_p`` drawn from there, where the reference's surface lies in
    ``camera``'s view: outside it each selection culls at its own granularity, and where the
    two culled edges pinch below a pixel the gap between them is enclosed, not a crack); from
    above, only pixels whose ray passes below the drawn surface (:func:`render.cracks.rays_below`:
    through a gap, not past a ridge that wide-angle relief folds over the background). On a
    store with nodata, a pixel that the selection covers once its nodata holes are drawn sees a
    hole in the data, not a crack, and is not counted (:func:`render.measure.crack_pixels`'
    ``holes``). From the camera, a clear pixel that only the image border reaches (a crack
    running off the image's edge) counts where its ray passes below the drawn surface
    (:func:`render.cracks.border_only`, :func:`render.cracks.gaps_through`)."""
    nodata = bool(np.asarray(r.store.index.has_nodata).any())

    def seen(cam: Camera, fp: np.ndarray, mesh: tuple | None = None, edge: tuple = ()) -> int:
        strat.draw(cam, sel, clear=CLEAR)
        img = r.image()
        n = measure.crack_pixels(img, fp, CLEAR)
        # edge (the drawn mesh): the clear pixels only the image border reaches count where
        # their ray passes through a gap in it (a crack running off the image's edge)
        off = cracks.border_only(img, fp, CLEAR) if edge else None
        holes = None
        if (n or (off is not None and off.any())) and nodata:  # holes in the data among them?
            strat.draw(cam, sel, clear=CLEAR, holes=True)  # (drawn only when there is a doubt)
            holes = ~measure.is_clear(r.image(), CLEAR)
            n = measure.crack_pixels(img, fp, CLEAR, holes=holes)
        if n and mesh is not None:  # only rays that pass below the drawn surface: a gap
            rows, cols = np.nonzero(measure.crack_mask(img, fp, CLEAR, holes=holes))
            n = int(cracks.rays_below(r.grid, cam, *mesh, np.c_[rows, cols]).sum())
        if off is not None:
            n += cracks.gaps_through(r.grid, cam, edge, off, holes)
        return n

    tri, h = triangles if triangles is not None else strat.triangles(camera, sel)
    here = seen(camera, footprint, edge=(tri, h))
    above = cracks.above_camera(r.grid, camera, tri, h)
    r.draw(above, ref_p, clear=CLEAR)
    fp_above = ~measure.is_clear(r.image(), CLEAR)
    fp_above &= in_view(camera, r.surface_points(above))
    return here, seen(above, fp_above, (tri, h))


def in_view(camera: Camera, points: np.ndarray) -> np.ndarray:
    """Per point of ``points`` (``(..., 3)``, NaN for none): inside ``camera``'s view frustum."""
    flat = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return camera.in_view(flat).reshape(np.shape(points)[:-1])
