"""Option definitions and parsers shared by several commands (one place to change them)."""

from __future__ import annotations

from enum import StrEnum
from typing import Annotated

import typer


class PathKind(StrEnum):
    """Built-in fly-through paths."""

    default = "default"
    line = "line"
    circle = "circle"
    canyon = "canyon"
    teleports = "teleports"


class Metric(StrEnum):
    """Screen-error metrics (streamer.lod.METRICS)."""

    qiu = "qiu"
    conservative = "conservative"


CameraOpt = Annotated[
    str | None, typer.Option("--camera", help="Eye position x,y,z (world units).")
]
LookAtOpt = Annotated[str | None, typer.Option("--look-at", help="Target point x,y,z.")]
YawOpt = Annotated[float | None, typer.Option("--yaw", help="Degrees clockwise from north.")]
PitchOpt = Annotated[float | None, typer.Option("--pitch", help="Degrees above the horizon.")]
FovOpt = Annotated[float, typer.Option("--fov", min=1.0, max=170.0, help="Vertical FOV, deg.")]
SizeOpt = Annotated[str, typer.Option("--size", help="Viewport WxH in pixels.")]
MetricOpt = Annotated[Metric, typer.Option("--metric", help="Screen-error metric.")]
LodOpt = Annotated[
    str,
    typer.Option(
        "--lod", help="LOD strategy: qiu (default) or chunk-tessellation (render.strategies)."
    ),
]
PatchOpt = Annotated[
    int, typer.Option("--patch-log2", min=0, max=7, help="Patch cells per side, log2.")
]


def parse_size(text: str) -> tuple[int, int]:
    """``1024x768`` → ``(1024, 768)``; a clear error otherwise."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"expected WIDTHxHEIGHT such as 1024x768, got {text!r}") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise typer.BadParameter(f"viewport {w}x{h} is outside 1..16384 pixels per side")
    return w, h


def parse_taus(text: str) -> list[float]:
    """``0.5,1,2`` → ``[0.5, 1.0, 2.0]``; a clear error otherwise."""
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        vals = []
    if not vals or any(not v >= 0 for v in vals):
        raise typer.BadParameter(
            f"expected comma-separated taus >= 0 such as 0.5,1,2, got {text!r}"
        )
    return vals
