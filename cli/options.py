"""Option definitions and parsers shared by several commands (one place to change them)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from importlib import import_module
from pathlib import Path
from typing import Annotated, Any

import typer

from cli.common import UsageError


class RegistryChoice:
    """Parser: one of a registry's names; an unknown one is refused naming it and the choices."""

    def __init__(self, names: Sequence[str], noun: str) -> None:
        self.choices, self.noun = list(names), noun

    def __call__(self, value: Any) -> Any:
        if value is None or value in self.choices:
            return value
        raise typer.BadParameter(
            f"unknown {self.noun} {value!r}; choose one of {', '.join(self.choices)}"
        )


class FiniteFloat:
    """Parser: a finite number within optional bounds; the message names the value given."""

    def __init__(
        self, min: float | None = None, max: float | None = None, *, min_open: bool = False
    ) -> None:
        self.min, self.max, self.min_open = min, max, min_open

    def describe(self) -> str:
        """``x>0``, ``1<=x<=170`` ... for the help text and messages."""
        lo = "" if self.min is None else f"{self.min:g}{'<' if self.min_open else '<='}"
        hi = "" if self.max is None else f"<={self.max:g}"
        return f"{lo}x{hi}" if lo or hi else "finite"

    def __call__(self, value: Any) -> float | None:
        if value is None:
            return None
        try:
            x = float(value)
        except (TypeError, ValueError):
            raise typer.BadParameter(f"{value!r} is not a number") from None
        if not math.isfinite(x):
            raise typer.BadParameter(
                f"{value!r} is not a finite number; give one in the range {self.describe()}"
            )
        below = self.min is not None and (x <= self.min if self.min_open else x < self.min)
        above = self.max is not None and x > self.max
        if below or above:
            raise typer.BadParameter(f"{value} is not in the range {self.describe()}")
        return x


class BoundedInt:
    """Parser: an integer within optional bounds; the message names the value given."""

    def __init__(self, min: int | None = None, max: int | None = None) -> None:
        self.min, self.max = min, max

    def describe(self) -> str:
        """``x>=1``, ``0<=x<=7`` ..."""
        lo = "" if self.min is None else f"{self.min}<="
        hi = "" if self.max is None else f"<={self.max}"
        return f"{lo}x{hi}" if lo or hi else "any integer"

    def __call__(self, value: Any) -> int | None:
        if value is None or isinstance(value, int):
            x = value
        else:
            try:
                x = int(str(value).strip())
            except ValueError:
                raise typer.BadParameter(f"{value!r} is not an integer") from None
        if x is not None and (
            (self.min is not None and x < self.min) or (self.max is not None and x > self.max)
        ):
            raise typer.BadParameter(f"{value} is not in the range {self.describe()}")
        return x


def integer(flag: str, help: str, *decls: str, **bounds: Any) -> Any:
    """A ``typer.Option`` taking an integer within ``bounds`` (:class:`BoundedInt`)."""
    t = BoundedInt(**bounds)
    return typer.Option(flag, *decls, parser=t, help=f"{help} [{t.describe()}]")


def _names(module: str, attr: str) -> list[str]:
    """The names of a registry ``module.attr`` (a dict, a sequence or a function)."""
    obj = getattr(import_module(module), attr)
    return list(obj() if callable(obj) else obj)


def choice_option(flag: str, names: Sequence[str], noun: str, help: str) -> Any:
    """A ``typer.Option`` whose value must be one of ``names`` (shown in the help)."""
    return typer.Option(
        flag, parser=RegistryChoice(names, noun), metavar="|".join(names), help=help
    )


def number(flag: str, help: str, *decls: str, **bounds: Any) -> Any:
    """A ``typer.Option`` taking a finite float within ``bounds`` (:class:`FiniteFloat`)."""
    t = FiniteFloat(**bounds)
    rng = t.describe()
    return typer.Option(
        flag, *decls, parser=t, help=help + ("" if rng == "finite" else f" [{rng}]")
    )


LOD_NAMES = _names("render.strategies", "strategy_names")
METRIC_NAMES = _names("streamer.lod", "METRICS")
PATH_KINDS = _names("streamer.run", "PATH_KINDS")
DTYPES = _names("tiler.synth", "DTYPES")

CameraOpt = Annotated[
    str | None,
    typer.Option("--camera", metavar="X,Y,Z", help="Eye position x,y,z (world units)."),
]
LookAtOpt = Annotated[
    str | None, typer.Option("--look-at", metavar="X,Y,Z", help="Target point x,y,z.")
]
YawOpt = Annotated[float | None, number("--yaw", "Degrees clockwise from north.")]
PitchOpt = Annotated[float | None, number("--pitch", "Degrees above the horizon.")]
FovOpt = Annotated[float, number("--fov", "Vertical field of view, degrees.", min=1.0, max=170.0)]
SizeOpt = Annotated[str, typer.Option("--size", metavar="WxH", help="Viewport in pixels.")]
MetricOpt = Annotated[
    str,
    choice_option(
        "--metric", METRIC_NAMES, "screen-error metric", "Screen-error metric (streamer.lod)."
    ),
]
LodOpt = Annotated[
    str,
    choice_option("--lod", LOD_NAMES, "LOD strategy", f"LOD strategy ({LOD_NAMES[0]} by default)."),
]
PathKindOpt = Annotated[
    str, choice_option("--path-kind", PATH_KINDS, "path kind", "Built-in camera path.")
]
PathOpt = Annotated[
    Path | None,
    typer.Option("--path", metavar="FILE", help="Keyframes file (.json or .csv)."),
]
PatchOpt = Annotated[int, integer("--patch-log2", "Patch cells per side, log2.", min=0, max=7)]
TauOpt = Annotated[float, number("--tau", "Screen-space error threshold, pixels.", min=0.0)]
BudgetOpt = Annotated[
    float, number("--budget-mb", "Resident byte budget, MiB.", min=0.0, min_open=True)
]


def parse_size(text: str) -> tuple[int, int]:
    """``1024x768`` → ``(1024, 768)``; a clear error otherwise."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(
            f"expected WIDTHxHEIGHT such as 1024x768, got {text!r}", "--size"
        ) from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise UsageError(f"viewport {w}x{h} is outside 1..16384 pixels per side", "--size")
    return w, h


def parse_taus(text: str) -> list[float]:
    """``0.5,1,2`` → ``[0.5, 1.0, 2.0]``; a clear error otherwise."""
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        vals = []
    if not vals or any(not (math.isfinite(v) and v >= 0) for v in vals):
        msg = f"expected comma-separated finite taus >= 0 such as 0.5,1,2, got {text!r}"
        raise UsageError(msg, "--taus")
    return vals
