"""Option definitions and parsers shared by several commands (one place to change them)."""

from __future__ import annotations

import math
from importlib import import_module
from pathlib import Path
from typing import Annotated, Any

import typer

from cli.common import LAZY_TEXT, UsageError


class Registry:
    """The names of a registry (``module.attr``: a dict, a sequence or a function returning one),
    imported on first use — when a command parses the option or prints its help — so that
    ``terrastream --version`` or ``tile`` does not import the renderer."""

    def __init__(self, module: str, attr: str, noun: str) -> None:
        self.module, self.attr, self.noun = module, attr, noun
        #: stands for the names in metavars and help texts until they are resolved
        self.placeholder = f"<{module}.{attr}>"
        LAZY_TEXT[self.placeholder] = lambda: "|".join(self.names)
        self._names: list[str] | None = None

    @property
    def names(self) -> list[str]:
        """The registered names, in the registry's order."""
        if self._names is None:
            obj = getattr(import_module(self.module), self.attr)
            self._names = [str(n) for n in (obj() if callable(obj) else obj)]
        return self._names

    def __call__(self, value: Any) -> Any:
        """Parser: ``value`` if registered, else a usage error naming it and the choices."""
        if value is None or value in self.names:
            return value
        raise typer.BadParameter(
            f"unknown {self.noun} {value!r}; choose one of {', '.join(self.names)}"
        )


class FiniteFloat:
    """Parser: a finite number within optional bounds; the message names the value given."""

    def __init__(
        self,
        min: float | None = None,
        max: float | None = None,
        *,
        min_open: bool = False,
        max_open: bool = False,
        why: str = "",
    ) -> None:
        self.min, self.max, self.why = min, max, why
        self.min_open, self.max_open = min_open, max_open

    def describe(self) -> str:
        """``x>0``, ``1<=x<=170`` ... for the help text and messages."""
        lo = "" if self.min is None else f"{self.min:g}{'<' if self.min_open else '<='}"
        hi = "" if self.max is None else f"{'<' if self.max_open else '<='}{self.max:g}"
        return f"{lo}x{hi}" if lo or hi else "finite"

    def __call__(self, value: Any) -> float | None:
        if value is None:
            return None
        try:
            x = float(value)
        except (TypeError, ValueError):
            raise typer.BadParameter(f"{value!r} is not a number") from None
        if not math.isfinite(x):
            bounded = self.min is not None or self.max is not None
            where = f" in the range {self.describe()}" if bounded else ""
            raise typer.BadParameter(f"{value!r} is not a finite number; give a finite one{where}")
        below = self.min is not None and (x <= self.min if self.min_open else x < self.min)
        above = self.max is not None and (x >= self.max if self.max_open else x > self.max)
        if below or above:
            why = f" ({self.why})" if self.why else ""
            raise typer.BadParameter(f"{value} is not in the range {self.describe()}{why}")
        return x


class BoundedInt:
    """Parser: an integer within optional bounds; the message names the value given (and
    ``why`` the bounds are what they are, when given)."""

    def __init__(self, min: int | None = None, max: int | None = None, *, why: str = "") -> None:
        self.min, self.max, self.why = min, max, why

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
            why = f" ({self.why})" if self.why else ""
            raise typer.BadParameter(f"{value} is not in the range {self.describe()}{why}")
        return x


def integer(flag: str, help: str, *decls: str, **bounds: Any) -> Any:
    """A ``typer.Option`` taking an integer within ``bounds`` (:class:`BoundedInt`)."""
    t = BoundedInt(**bounds)
    rng = t.describe()
    return typer.Option(
        flag, *decls, parser=t, help=help + ("" if rng == "any integer" else f" [{rng}]")
    )


def choice_option(flag: str, registry: Registry, help: str) -> Any:
    """A ``typer.Option`` whose value must be one of ``registry``'s names (shown in the help)."""
    return typer.Option(flag, parser=registry, metavar=registry.placeholder, help=help)


def number(flag: str, help: str, *decls: str, **bounds: Any) -> Any:
    """A ``typer.Option`` taking a finite float within ``bounds`` (:class:`FiniteFloat`)."""
    t = FiniteFloat(**bounds)
    rng = t.describe()
    return typer.Option(
        flag, *decls, parser=t, help=help + ("" if rng == "finite" else f" [{rng}]")
    )


LODS = Registry("render.strategies", "strategy_names", "LOD strategy")
METRICS = Registry("streamer.lod", "METRICS", "screen-error metric")
PATH_KINDS = Registry("streamer.run", "PATH_KINDS", "path kind")
NODATA_RULES = Registry("streamer.nodata", "NODATA_RULES", "nodata rule")
DTYPES = Registry("tiler.synth", "DTYPES", "sample type")
#: the defaults (render.strategies.DEFAULT, the first of streamer.lod.METRICS, tiler.synth.DTYPES,
#: the first of streamer.nodata.NODATA_RULES)
LOD_DEFAULT, METRIC_DEFAULT, DTYPE_DEFAULT, NODATA_DEFAULT = "qiu", "qiu", "int16", "full"

StoreArg = Annotated[str, typer.Argument(help="Store (directory or fsspec URL).")]
TausOpt = Annotated[
    str, typer.Option("--taus", metavar="T,T,...", help="Comma-separated taus, px.")
]
PlotOpt = Annotated[
    Path | None, typer.Option("--plot", metavar="FILE", help="Write a plot (PNG, SVG, PDF).")
]
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
    choice_option("--metric", METRICS, "Screen-error metric (streamer.lod)."),
]
LodOpt = Annotated[
    str,
    choice_option("--lod", LODS, "LOD strategy (render.strategies)."),
]
NodataRuleOpt = Annotated[
    str,
    choice_option(
        "--nodata-rule",
        NODATA_RULES,
        "Terrain beside nodata: full (full resolution at every tau, every strategy) or gap "
        "(qiu only: refined while a mixed cell can project past min(tau, 1) px); the "
        "streaming session loads the levels the rule draws (streamer.nodata).",
    ),
]
PathKindOpt = Annotated[str, choice_option("--path-kind", PATH_KINDS, "Built-in camera path.")]
PathOpt = Annotated[
    Path | None,
    typer.Option("--path", metavar="FILE", help="Keyframes file (.json or .csv)."),
]
PatchOpt = Annotated[int, integer("--patch-log2", "Patch cells per side, log2.", min=1, max=7)]
TauOpt = Annotated[float, number("--tau", "Screen-space error threshold, pixels.", min=0.0)]
#: ``--budget-mb``'s largest (2^40 MiB = 1 EiB: more than any machine holds, and its bytes
#: still an exact 64-bit integer; 1e308 overflowed the conversion to bytes)
MAX_BUDGET_MB = float(2**40)
BudgetOpt = Annotated[
    float,
    number(
        "--budget-mb",
        "Resident byte budget, MiB.",
        min=2**-20,
        max=MAX_BUDGET_MB,
        why="one byte (2^-20 MiB) to 1 EiB (2^40 MiB)",
    ),
]
#: ``--frames``' largest: ten million frames are 46 h at 60 fps (a run beyond it would only
#: fail late, out of memory, or overflow)
MAX_FRAMES = 10**7


def frames_option(help: str) -> Any:
    """The ``--frames N`` option: 1 to :data:`MAX_FRAMES`."""
    return integer("--frames", help, min=1, max=MAX_FRAMES, why="at most ten million frames")


def check_nodata_rule(lods: list[str] | None, rule: str) -> str:
    """``rule`` when every strategy of ``lods`` (None: all) takes it, else a usage error naming
    ``--nodata-rule``, the rule and the strategies that take it."""
    from render.strategies import NodataRuleError, check_nodata, strategy_names

    try:
        for name in lods or strategy_names():
            check_nodata(name, rule)
    except NodataRuleError as exc:
        raise UsageError(str(exc), "--nodata-rule") from exc
    return rule


def check_metric(lod: str, metric: str) -> str:
    """``metric`` when strategy ``lod`` selects with it (or it is the default), else a usage
    error naming ``--metric``: the strategy has its own error and would silently ignore it."""
    from render.strategies import strategy_class, strategy_names

    if metric == METRIC_DEFAULT or strategy_class(lod).uses_metric:
        return metric
    takers = [n for n in strategy_names() if strategy_class(n).uses_metric]
    raise UsageError(
        f"--lod {lod} selects with its own error and does not use --metric {metric}; drop "
        f"--metric, or use a strategy that takes it: {', '.join(takers)}",
        "--metric",
    )


def check_metric_any(lods: list[str] | None, metric: str) -> str:
    """``metric`` when one strategy of ``lods`` (None: all) selects with it (or it is the
    default), else a usage error naming ``--metric``: every strategy compared would ignore it
    (``compare --lods seamless-patches --metric conservative``)."""
    from render.strategies import strategy_class, strategy_names

    names = lods or strategy_names()
    if metric == METRIC_DEFAULT or any(strategy_class(n).uses_metric for n in names):
        return metric
    takers = [n for n in strategy_names() if strategy_class(n).uses_metric]
    raise UsageError(
        f"--lods {','.join(names)} select with their own errors and do not use --metric "
        f"{metric}; drop --metric, or add a strategy that takes it: {', '.join(takers)}",
        "--metric",
    )


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


StorageOptionsOpt = Annotated[
    str | None,
    typer.Option(
        "--storage-options",
        metavar="JSON",
        help="fsspec storage options for an s3://, gs://... store: a JSON object with keys "
        "such as endpoint_url, key, secret, anon (default: the environment, e.g. "
        "AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY); for http(s):// "
        'stores, the key "timeout": seconds without a byte before a read gives up '
        "(default 30).",
    ),
]

#: ``tile``'s: it writes the store, and an http(s) store is read-only (refused at once)
DstStorageOptionsOpt = Annotated[
    str | None,
    typer.Option(
        "--storage-options",
        metavar="JSON",
        help="fsspec storage options for an s3://, gs://... DST: a JSON object with keys "
        "such as endpoint_url, key, secret, anon (default: the environment, e.g. "
        "AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY).",
    ),
]


def store_location(url: str, storage_options: str | None) -> Any:
    """``url`` itself, or a ``tiler.location.Location`` carrying the parsed storage options.

    Bad JSON, or options for a local path, is a usage error naming ``--storage-options``.
    """
    if storage_options is None or not storage_options.strip():
        return url
    from cli.common import UsageError
    from tiler.errors import StorageOptionsError
    from tiler.location import Location, parse_storage_options

    try:
        return Location(url, parse_storage_options(storage_options))
    except StorageOptionsError as exc:
        raise UsageError(str(exc), "--storage-options") from exc
