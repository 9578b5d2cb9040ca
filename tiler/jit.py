"""numba's ``njit`` with its on-disk cache, for the kernel modules (importing this imports numba).

The compiled code is cached beside the sources (``cache=True``); where that directory is not
writable, a per-user temporary directory is used, and where no cache works at all the kernels
compile in memory (logged). Used by :mod:`tiler._kernels_nb` and the renderer's kernels.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Callable
from typing import Any

import numba

log = logging.getLogger("tiler.kernels")


def cached_njit(**opts: Any) -> Callable[[Callable], Any]:
    """A decorator: ``numba.njit(cache=True, **opts)`` with the module doc's cache fallbacks."""

    def jit(fn: Callable) -> Any:
        try:
            return numba.njit(cache=True, **opts)(fn)
        except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
            fallback = os.path.join(tempfile.gettempdir(), f"terrastream-numba-{os.getuid()}")
            try:
                os.makedirs(fallback, exist_ok=True)
                numba.config.CACHE_DIR = fallback
                return numba.njit(cache=True, **opts)(fn)
            except (OSError, RuntimeError):
                log.warning("numba cannot cache compiled kernels (%s); compiling in memory", exc)
                return numba.njit(cache=False, **opts)(fn)

    return jit
