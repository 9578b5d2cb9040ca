"""``seamless-patches``' compiled selection kernels, chosen like :mod:`tiler.kernels`: numba
when it is installed (the ``fast`` extra), the numpy reference otherwise. ``TERRASTREAM_KERNELS``
(``auto``, ``numba``, ``numpy``) or the strategy's ``kernels`` argument picks the backend; ``auto``
uses numba only after :func:`warm_up` (a one-shot command never waits for it; importing this
module costs nothing)."""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from types import ModuleType

from tiler.kernels import pick_warm, requested, warm


@cache
def _load_numba() -> ModuleType | None:
    try:
        from render.strategies.seamless import _resolve_nb
    except ImportError:
        return None
    return _resolve_nb  # it re-exports _kernels_nb's kernels


_READY: list[bool] = []  # filled by warm_up(): ``auto`` may use the compiled kernels


def resolve(kernels: str | None = None) -> ModuleType | None:
    """The numba kernel module for backend ``kernels`` (default: ``TERRASTREAM_KERNELS``), or
    ``None`` for the numpy reference; ``auto`` only after :func:`warm_up`."""
    return pick_warm(kernels, _load_numba, _READY)


def warm_up(run: Callable[[], object] | None = None) -> bool:
    """Import numba and seamless-patches' kernels now, after which ``auto`` uses them; ``run``
    (:func:`render.strategies.seamless.warm.warm_up_selection` for the store's shape) calls
    them once first, so they load from numba's cache (or compile) here and not in the render
    thread's first compiled selection (~28 ms). Whether they are available."""
    if run is not None and requested() != "numpy" and _load_numba() is not None:
        run()
    return warm(_load_numba, _READY)
