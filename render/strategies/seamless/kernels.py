"""``seamless-patches``' compiled selection kernels, chosen like :mod:`tiler.kernels`: numba
when it is installed (the ``fast`` extra), the numpy reference otherwise. ``TERRASTREAM_KERNELS``
(``auto``, ``numba``, ``numpy``) or the strategy's ``kernels`` argument picks the backend; numba
is only imported on the first selection that uses it (importing this module costs nothing)."""

from __future__ import annotations

from functools import cache
from types import ModuleType

from tiler.kernels import pick


@cache
def _load_numba() -> ModuleType | None:
    try:
        from render.strategies.seamless import _resolve_nb
    except ImportError:
        return None
    return _resolve_nb  # it re-exports _kernels_nb's kernels


def resolve(kernels: str | None = None) -> ModuleType | None:
    """The numba kernel module for backend ``kernels`` (default: ``TERRASTREAM_KERNELS``), or
    ``None`` for the numpy reference."""
    return pick(kernels, _load_numba)
