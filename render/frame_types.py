"""The frame's plain data, no GL: the renderer's settings (:class:`RenderConfig`), a frame's
figures (:class:`RenderStats`), a block's place in the height pool (:class:`Slot`), the clear
colour of measured frames and the colour ramp's parameters (:func:`ramp_map`). Re-exported by
:mod:`render.frame`, whose :class:`~render.frame.FrameServices` uses them."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from render.errors import RenderError

CLEAR = (255, 0, 255)  # magenta: contrasts with every terrain colour


def ramp_map(zrange: tuple[float, float], zref: float = 0.0) -> tuple[float, float, float, float]:
    """The colour ramp's ``(offset, scale, sea_scale)`` for heights stored relative to
    ``zref``: hypsometric ``t = (h - offset) * scale`` over ``zrange``; when the range crosses
    0, land is ``[0, zmax]`` and the sea ramp ``-h * sea_scale`` covers ``[zmin, 0)``; a
    constant range has scale 0 (one colour); the fourth value is sea level (0) minus ``zref``."""
    lo, hi = (float(v) for v in zrange)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return 0.0, 0.0, 0.0, -zref
    if lo < 0.0 < hi:
        return -zref, 1.0 / hi, 1.0 / -lo, -zref
    return lo - zref, (1.0 / (hi - lo) if hi > lo else 0.0), 0.0, -zref


@dataclass(frozen=True)
class RenderConfig:
    """Renderer settings; ``patch_log2`` is the patch size of the renderer and of the session
    streaming for it (:func:`render.pipeline.open_render_session` takes it from here), but for
    chunk-tessellation, whose sessions plan with its chunks
    (:func:`render.pipeline.session_patch_log2`)."""

    size: tuple[int, int] = (1024, 768)
    patch_log2: int = 4
    clear: tuple[int, int, int] = (135, 170, 210)
    sun: tuple[float, float, float] = (-0.5, 0.6, 0.65)
    linger_frames: int = 30  # keep blocks that left the view this long on the GPU

    def __post_init__(self) -> None:
        w, h = self.size
        if not (1 <= w <= 16384 and 1 <= h <= 16384):
            raise RenderError(f"viewport {w}x{h} is outside 1..16384 pixels per side")
        check_patch_log2(self.patch_log2)


def check_patch_log2(value: object) -> int:
    """``value`` if it is a patch size the renderer draws (an integer in 1..7), else a
    :class:`RenderError` naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise RenderError(f"patch_log2 must be an integer in 1..7, got {value!r}")
    if value == 0:
        # a 1-cell patch cannot snap an edge to a coarser neighbour, so stitching would
        # split every neighbour to one level across the whole view (render.select.stitch)
        raise RenderError(
            "patch_log2 must be in 1..7, got 0: patches of one cell cannot be stitched to "
            "coarser neighbours; use 1 for the finest patches"
        )
    if not 1 <= value <= 7:
        raise RenderError(f"patch_log2 must be in 1..7, got {value}")
    return int(value)


@dataclass(frozen=True)
class RenderStats:
    """One rendered frame's figures."""

    triangles: int
    patches: int
    selection_ms: float
    frame_ms: float
    gpu_bytes: int
    clamped: int  # nodes drawn coarser than wanted because the level was not resident
    violations: int
    max_level: int
    min_level: int
    #: pixels covered with terrain (:meth:`FrameServices.drawn_pixels`); None: not counted
    drawn_px: int | None = None


@dataclass(frozen=True)
class Slot:
    """Where a block's level sequence lives in the height pool."""

    page: int  # the pool page (bind it with :meth:`FrameServices.bind_heights`)
    offset: int  # base of the block's sequence in the page, in floats
    level: int  # finest level uploaded
