"""The one frame step every command, the viewer and the benchmarks run:
``session.update -> renderer.sync -> strategy.select -> strategy.draw``.

:func:`stream_step` is its first half (the data: update the streaming session for the camera and
upload what arrived), :func:`frame_step` the whole step. Callers that select or draw more than
once per streamed pose (the trade-off sweep, the popping walk) use :func:`stream_step` and the
strategy directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from render.frame import Block, FrameServices, RenderStats
from render.strategies.base import DrawOptions, Strategy
from streamer.camera import Camera
from streamer.session import Frame, Session

S = TypeVar("S")


def resident_levels(frame: Frame) -> dict[Block, int]:
    """The finest resident level of each visible block of a streaming frame."""
    return {b: res for b, (res, _need) in frame.blocks.items() if res >= 0}


def stream_step(
    session: Session,
    renderer: FrameServices | None,
    camera: Camera,
    dt: float | None = None,
    *,
    wait: bool = True,
) -> tuple[Frame, dict[Block, int]]:
    """Update ``session`` for ``camera`` (``dt`` since the previous pose, ``wait`` for the
    needed levels) and, unless ``renderer`` is None, upload what the frame holds; the frame and
    its resident levels."""
    frame = session.update(camera, dt, wait=wait)
    if renderer is not None:
        renderer.sync(frame.blocks, session)
    return frame, resident_levels(frame)


@dataclass(frozen=True)
class Step(Generic[S]):
    """One drawn frame: the streaming frame, the levels it held, the selection and the stats."""

    frame: Frame
    resident: dict[Block, int]
    selection: Any
    selection_ms: float
    stats: RenderStats


def frame_step(
    session: Session,
    strategy: Strategy[S],
    camera: Camera,
    tau: float,
    metric: str = "qiu",
    *,
    dt: float | None = None,
    wait: bool = True,
    options: DrawOptions | None = None,
) -> Step[S]:
    """Stream ``camera`` into ``strategy``'s renderer, select at ``tau`` with the resident
    levels and draw (``options``; the selection's ms is filled in)."""
    frame, res = stream_step(session, strategy.r, camera, dt, wait=wait)
    sel, ms = strategy.select(camera, tau, metric, resident=res)
    st = strategy.draw(camera, sel, DrawOptions.of(options, selection_ms=ms))
    return Step(frame=frame, resident=res, selection=sel, selection_ms=ms, stats=st)
