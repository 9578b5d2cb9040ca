"""LOD strategies over the renderer, chosen by name: every strategy draws from the same store,
streaming session, ``HeightPool`` and level/order-index fetch, returns the renderer's
``RenderStats`` and is measured the same way (docs/RENDER.md, "Strategies"). A strategy is a
:class:`Strategy` over :class:`render.frame.FrameServices`; to add one see docs/RENDER.md,
"Adding a strategy" (its package, one line in :data:`STRATEGIES`).

* ``qiu`` (default) — :mod:`render.strategies.qiu`, Qiu et al.'s CLOD patches;
* ``jung-han`` — :mod:`render.strategies.jung_han`, 3×3-vertex blocks, CPU simplification;
* ``geometry-splitting`` — :mod:`render.strategies.geometry_splitting`, Lee & Shin, quadtree
  expanded on the GPU with transform feedback;
* ``chunk-tessellation`` — :mod:`render.strategies.chunk_tess`, Kim, Lee & Shin (chunks
  selected on the CPU); ``chunk-tessellation-gpu`` the same chunks selected on the GPU as the
  paper does;
* ``seamless-patches`` — :mod:`render.strategies.seamless`, Livny, Kogan & El-Sana.

Strategy packages are imported on first use (each compiles its own shaders).
"""

from __future__ import annotations

from functools import partial
from importlib import import_module
from typing import TYPE_CHECKING, Any

from render.errors import RenderError
from render.strategies.base import Strategy
from streamer.nodata import check_rule

if TYPE_CHECKING:
    from render.frame import FrameServices

DEFAULT = "qiu"
#: name -> "module:Class"
STRATEGIES: dict[str, str] = {
    "qiu": "render.strategies.qiu:QiuStrategy",
    "jung-han": "render.strategies.jung_han:JungHan",
    "geometry-splitting": "render.strategies.geometry_splitting:GeometrySplitting",
    "chunk-tessellation": "render.strategies.chunk_tess:ChunkTessellation",
    "chunk-tessellation-gpu": "render.strategies.chunk_tess:ChunkTessellationGpu",
    "seamless-patches": "render.strategies.seamless:SeamlessPatches",
}


def warm_up_kernels(seamless_shape: tuple[int, int] | None = None) -> dict[str, bool]:
    """Import numba and every strategy's compiled CPU kernels now, after which
    ``TERRASTREAM_KERNELS=auto`` uses them (until then ``auto`` is the numpy reference, so a
    one-shot command never waits ~1 s for numba); the viewer runs it on a background thread
    (with :meth:`Strategy.warm_up_args` of its strategy). Kernels load from numba's cache (or
    compile, the first time ever on a machine) when first called: here, on small synthetic
    scenes, for the CLOD walk, jung-han and, given ``seamless_shape`` (the store's block and
    tile log2 sizes ``(k, c)``, on which its kernel's signature depends), seamless-patches.
    Returns which are available, by name."""
    from render import select_kernels
    from render.select_warm import warm_up_walk
    from render.strategies.geometry_splitting import kernels as gs_kernels
    from render.strategies.jung_han import kernels as jh_kernels
    from render.strategies.jung_han.warm import warm_up_selection
    from render.strategies.seamless import kernels as sp_kernels
    from render.strategies.seamless.warm import warm_up_selection as sp_selection

    return {
        "qiu/chunk-tessellation walk": select_kernels.warm_up(warm_up_walk),
        "jung-han": jh_kernels.warm_up(warm_up_selection),
        "seamless-patches": sp_kernels.warm_up(
            None if seamless_shape is None else partial(sp_selection, *seamless_shape)
        ),
        "geometry-splitting trees": gs_kernels.warm_up(),
    }


class UnknownStrategyError(RenderError):
    """A strategy name that is not registered."""


def strategy_names() -> list[str]:
    """The registered strategy names, default first."""
    return [DEFAULT] + sorted(n for n in STRATEGIES if n != DEFAULT)


def check_name(name: str) -> str:
    """``name`` if registered, else :class:`UnknownStrategyError` listing the choices."""
    if name not in STRATEGIES:
        raise UnknownStrategyError(
            f"unknown LOD strategy {name!r}; choose one of {', '.join(strategy_names())}"
        )
    return name


def strategy_class(name: str) -> type[Strategy]:
    """The class registered as ``name``."""
    module, cls = STRATEGIES[check_name(name)].split(":")
    return getattr(import_module(module), cls)


class NodataRuleError(RenderError, ValueError):
    """A nodata rule the chosen LOD strategy does not take."""


def nodata_strategies(rule: str) -> list[str]:
    """The registered strategies that take the nodata ``rule`` (imports every strategy)."""
    return [n for n in strategy_names() if rule in strategy_class(n).nodata_rules]


def check_nodata(name: str, rule: str) -> str:
    """``rule`` if strategy ``name`` takes it (:attr:`Strategy.nodata_rules`), else
    :class:`NodataRuleError` naming the rule and the strategies that take it."""
    check_rule(rule)
    if rule not in strategy_class(name).nodata_rules:
        raise NodataRuleError(
            f"LOD strategy {name!r} does not take the nodata rule {rule!r}; the strategies "
            f"that do: {', '.join(nodata_strategies(rule))}"
        )
    return rule


def nodata_options(name: str, rule: str) -> dict[str, str]:
    """The constructor options of strategy ``name`` for the nodata ``rule`` (none for
    ``"full"``, every strategy's rule; checked with :func:`check_nodata`)."""
    return {} if check_nodata(name, rule) == "full" else {"nodata": rule}


def stream_metric(name: str, metric: str) -> str:
    """The metric the streaming session should load levels with for strategy ``name``: the
    given one when the strategy selects with it, else ``"conservative"`` (a bound on the
    patches' error, so a strategy with its own error is not held back by Eq. 7's loading)."""
    return metric if strategy_class(name).uses_metric else "conservative"


#: the ``metric`` a table or JSON row records for a strategy that selects with its own screen
#: error (``uses_metric`` False: ``--metric`` does not apply to it)
OWN_ERROR = "own"


def error_label(name: str, metric: str) -> str:
    """What τ bounds in strategy ``name``'s selection, for tables and JSON rows: ``metric``
    when the strategy selects with it, else :data:`OWN_ERROR` (its own error, not Eq. 7's)."""
    return metric if strategy_class(name).uses_metric else OWN_ERROR


def get_strategy(name: str, renderer: FrameServices, **options: Any) -> Strategy:
    """An instance of strategy ``name`` drawing with ``renderer``."""
    return strategy_class(name)(renderer, **options)


__all__ = [
    "DEFAULT",
    "OWN_ERROR",
    "STRATEGIES",
    "NodataRuleError",
    "Strategy",
    "UnknownStrategyError",
    "check_name",
    "check_nodata",
    "error_label",
    "get_strategy",
    "nodata_options",
    "nodata_strategies",
    "strategy_class",
    "strategy_names",
    "stream_metric",
]
