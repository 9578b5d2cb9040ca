"""LOD strategies over the renderer (``--lod NAME``): every strategy draws from the same store,
streaming session, ``HeightPool`` and level/order-index fetch, returns the renderer's
``RenderStats`` and is measured the same way (docs/RENDER.md, "Strategies").

Registered here only when complete and tested:

* ``qiu`` (default) — :mod:`render.strategies.qiu`, the renderer's CLOD patches;
* ``chunk-tessellation`` — :mod:`render.strategies.chunk_tess`, Kim, Lee & Shin.
"""

from __future__ import annotations

from render.errors import RenderError
from render.strategies.base import Strategy
from render.strategies.chunk_tess import ChunkTessellation
from render.strategies.qiu import QiuStrategy

DEFAULT = "qiu"
STRATEGIES: dict[str, type[Strategy]] = {
    QiuStrategy.name: QiuStrategy,
    ChunkTessellation.name: ChunkTessellation,
}


class UnknownStrategyError(RenderError):
    """``--lod NAME`` names no registered strategy."""


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


def get_strategy(name: str, renderer, **options) -> Strategy:
    """An instance of strategy ``name`` drawing with ``renderer``."""
    return STRATEGIES[check_name(name)](renderer, **options)


__all__ = [
    "DEFAULT",
    "STRATEGIES",
    "Strategy",
    "UnknownStrategyError",
    "check_name",
    "get_strategy",
    "strategy_names",
]
