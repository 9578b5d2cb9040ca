"""The terrain renderer: the frame services (:mod:`render.frame`) plus Qiu's CLOD
(:mod:`render.strategies.qiu`, the default strategy) as convenience methods.

``TerrainRenderer(store, RenderConfig(...))`` is what the pipeline, the viewer, the benchmarks
and the tests make; strategies draw through its :class:`render.frame.FrameServices` interface.
:meth:`TerrainRenderer.select`, :meth:`~TerrainRenderer.draw` and
:meth:`~TerrainRenderer.probe` are :func:`render.strategies.qiu.select_clod` and the ``qiu``
strategy's draw and probe on this renderer.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from render.frame import CLEAR, Block, FrameServices, RenderConfig, RenderStats
from render.select import Patches, PatchTable
from render.strategies.base import DrawOptions
from render.strategies.qiu import QiuStrategy, metric_table, select_clod
from streamer.camera import Camera

__all__ = ["CLEAR", "RenderConfig", "RenderStats", "TerrainRenderer"]


class TerrainRenderer(FrameServices):
    """Draws one store's resident blocks into an offscreen framebuffer (frame services +
    Qiu's CLOD)."""

    def table(self, metric: str) -> PatchTable:
        """The pooled patch errors for the metric's error field."""
        return metric_table(self, metric)

    def select(
        self,
        camera: Camera,
        tau: float,
        metric: str = "qiu",
        *,
        resident: dict[Block, int] | None = None,
        full: bool = False,
        table: PatchTable | None = None,
        field: str | None = None,
    ) -> tuple[Patches, float]:
        """:func:`render.strategies.qiu.select_clod` on this renderer."""
        return select_clod(
            self, camera, tau, metric, resident=resident, full=full, table=table, field=field
        )

    def _qiu(self) -> QiuStrategy:
        return self.shared("qiu.strategy", QiuStrategy)

    def draw(
        self, camera: Camera, patches: Patches, options: DrawOptions | None = None, **kw: Any
    ) -> RenderStats:
        """Draw CLOD patches (``options`` or ``wireframe``, ``lod_colour``, ``clear``,
        ``selection_ms``); frame ms = GPU time until ``ctx.finish()``."""
        return self._qiu().draw(camera, patches, options, **kw)

    def probe(self, camera: Camera, patches: Patches) -> tuple[np.ndarray, np.ndarray]:
        """The height each patch vertex fetched on the GPU and its global ``(col, row)``."""
        return self._qiu().probe(camera, patches)
