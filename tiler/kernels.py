"""Compiled kernels for the per-block hot loops, with the numpy code as the reference fallback.

The node-error fields, the residual encode/decode and the nodata fill run as numba kernels when
numba is installed (the ``fast`` extra) and as the numpy reference otherwise; both give
bit-identical results. ``TERRASTREAM_KERNELS`` picks the backend: ``auto`` (default: numba if
importable), ``numba`` (required: an error if missing) or ``numpy``.

numba is imported, and the kernels loaded from its on-disk cache (compiled on the first use
ever), only when a tiling kernel is first called: importing this module costs nothing. Decoding
(the read path) uses the kernels in ``auto`` mode only once they are loaded in the process, so a
reader never waits for numba's import (0.3-1 s) on its first block. Short jobs can skip numba
altogether (:func:`choose`); long ones can load it in the background first (:func:`warm_up`).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from functools import cache
from types import ModuleType

import numpy as np

from tiler.errors import KernelUnavailableError

ENV = "TERRASTREAM_KERNELS"
_NB_MODULE = "tiler._kernels_nb"
# numba's import + loading the cached kernels (~0.3-1 s) against ~60-200 ms saved per 1025^2
# block (bench/kernels.py): below ~8 such blocks numpy finishes first.
MIN_SAMPLES = 8 * 1025 * 1025
BACKENDS = ("auto", "numba", "numpy")
_UINT = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}


@cache
def _load_numba() -> ModuleType | None:
    try:
        from tiler import _kernels_nb
    except ImportError:
        return None
    return _kernels_nb


def requested() -> str:
    """The backend asked for through ``TERRASTREAM_KERNELS`` (validated)."""
    name = os.environ.get(ENV, "auto").strip().lower() or "auto"
    if name not in BACKENDS:
        raise KernelUnavailableError(
            f"{ENV}={name!r} is not a kernel backend; use one of {', '.join(BACKENDS)}."
        )
    return name


def pick(kernels: str | None, load: Callable[[], ModuleType | None]) -> ModuleType | None:
    """The kernel module ``load()`` gives for backend ``kernels`` (default:
    ``TERRASTREAM_KERNELS``), or ``None`` for the numpy reference; numba asked for but not
    importable is an error (the render strategies' ``kernels=`` argument)."""
    name = requested() if kernels is None else kernels.strip().lower()
    if name not in BACKENDS:
        raise KernelUnavailableError(f"kernels={name!r}: use one of {', '.join(BACKENDS)}")
    if name == "numpy":
        return None
    mod = load()
    if mod is None and name == "numba":
        raise KernelUnavailableError(
            f"numba kernels requested ({ENV} or kernels='numba') but numba cannot be imported; "
            "install the 'fast' extra or use 'numpy'."
        )
    return mod


def pick_warm(
    kernels: str | None, load: Callable[[], ModuleType | None], ready: list[bool]
) -> ModuleType | None:
    """As :func:`pick`, but ``auto`` gives the numpy reference until :func:`warm` has filled
    ``ready``, so a one-shot command never waits for numba's import, cache or a compilation
    (the render strategies' kernels: a viewer warms them on a background thread)."""
    name = requested() if kernels is None else kernels.strip().lower()
    if name == "auto" and not ready:
        return None
    return pick(kernels, load)


def warm(load: Callable[[], ModuleType | None], ready: list[bool]) -> bool:
    """Load the kernel module ``load`` gives now and mark ``ready`` (``auto`` then uses it);
    whether it is available (never under ``TERRASTREAM_KERNELS=numpy``)."""
    if requested() == "numpy":
        return False
    mod = load()
    if mod is not None and not ready:
        ready.append(True)
    return mod is not None


def active(load: bool = True) -> ModuleType | None:
    """The numba kernel module if it is to be used, else ``None`` (use numpy).

    ``load=False`` (the read path): in ``auto`` mode, only if numba is already loaded.
    """
    name = requested()
    if name == "numpy":
        return None
    if not load and name == "auto" and _NB_MODULE not in sys.modules:
        return None
    mod = _load_numba()
    if mod is None and name == "numba":
        raise KernelUnavailableError(
            f"{ENV}=numba but numba cannot be imported; install the 'fast' extra "
            "(pip install 'terrastream[fast]') or unset the variable."
        )
    return mod


def backend() -> str:
    """``"numba"`` or ``"numpy"``: the backend the next kernel call will use."""
    return "numpy" if active() is None else "numba"


def choose(samples: int) -> str:
    """Backend for a job of ``samples`` source samples: an explicit ``TERRASTREAM_KERNELS``
    wins; in ``auto`` mode numba only for jobs big enough to repay its start-up (and if
    importable)."""
    name = requested()
    if name != "auto":
        return name
    if samples < MIN_SAMPLES:
        return "numpy"
    return "numba" if _load_numba() is not None else "numpy"


def warm_up(dtype: np.dtype | str = "int16") -> bool:
    """Import numba and load (or compile) the kernels for ``dtype`` now, e.g. in a background
    thread before a pool forks; returns whether the compiled kernels are available."""
    from tiler import encoding, static_error

    if active() is None:
        return False
    g = np.zeros((5, 5), dtype=np.dtype(dtype))
    v = np.ones((5, 5), dtype=bool)
    v[1, 1] = False
    f = encoding.fill_invalid(g, v, 2)
    encoding.decode_grid(encoding.encode_levels(f, 2), g.dtype)
    static_error.block_errors(f, v, 2, 1)
    return True


def _depth_tables(k: int) -> np.ndarray:
    """``t[d, i] = float32(i / s_d)`` for ``s_d = 2**(k-d)`` (the numpy reference's ``t``)."""
    side = (1 << k) + 1
    tt = np.zeros((max(k, 1), side - 1), dtype=np.float32)
    for d in range(k):
        s = 1 << (k - d)
        tt[d, :s] = (np.arange(s) / s).astype(np.float32)
    return tt


_tables = cache(_depth_tables)


def _split_depths(flat: np.ndarray, k: int) -> list[np.ndarray]:
    out, off = [], 0
    for d in range(k):
        n = 1 << d
        out.append(flat[off : off + n * n].reshape(n, n))
        off += n * n
    return out


def split_depths(flat: np.ndarray, k: int) -> list[np.ndarray]:
    """Views ``(2**d, 2**d)`` of a depth-packed field (depths ``0..k-1`` one after another)."""
    return _split_depths(flat, k)


def recentre(mod: ModuleType, grid: np.ndarray, ref: float) -> tuple[np.ndarray, float]:
    """``float32(grid - ref)`` (subtraction in float64) and ``max |grid - ref|``."""
    g = np.ascontiguousarray(grid)
    out = np.empty(g.shape, dtype=np.float32)
    span = mod.recentre(g, float(ref), out) if g.size else 0.0
    return out, float(span)


def bound_flat(mod: ModuleType, f: np.ndarray, valid: np.ndarray, k: int) -> np.ndarray:
    """Depth-packed float32 node maxima of |f - surface| (``f`` float32, re-centred)."""
    out = np.empty(((4**k) - 1) // 3, dtype=np.float32)
    mod.bound_nodes(
        np.ascontiguousarray(f), np.ascontiguousarray(valid, dtype=bool), k, _tables(k), out
    )
    return out


def qiu_flat(mod: ModuleType, grid: np.ndarray, valid: np.ndarray, k: int) -> np.ndarray:
    """Depth-packed float64 Qiu H (before monotonicity)."""
    out = np.empty(((4**k) - 1) // 3, dtype=np.float64)
    mod.qiu_nodes(np.ascontiguousarray(grid), np.ascontiguousarray(valid, dtype=bool), k, out)
    return out


def monotone_pack(mod: ModuleType, flat: np.ndarray, k: int, cap: int, mult: float) -> np.ndarray:
    """Monotone (Eq. 3), times ``mult``, packed with tile maxima beyond ``cap`` (float64).

    ``flat`` (float64, depth-packed) is made monotone in place.
    """
    sizes = [4 ** min(d, cap) for d in range(k)]
    out = np.empty(sum(sizes), dtype=np.float64)
    mod.monotone_pack(flat, k, cap, float(mult), out)
    return out


def fill(mod: ModuleType, grid: np.ndarray, valid: np.ndarray, k: int, value: float) -> np.ndarray:
    """A copy of ``grid`` with invalid vertices filled coarse to fine (corners: ``value``)."""
    g = np.array(grid, order="C", copy=True)
    v = np.ascontiguousarray(valid, dtype=bool)
    if g.dtype.kind == "f":
        mod.fill_float(g, v, k, float(value))
    else:
        mod.fill_int(g, v, k, int(value))
    return g


def encode(mod: ModuleType, grid: np.ndarray, k: int) -> np.ndarray:
    """The whole stored sequence (levels 0..k, unsigned, same size as the dtype)."""
    g = np.ascontiguousarray(grid)
    u = _UINT[g.dtype.itemsize]
    out = np.empty(g.size, dtype=u)
    if g.dtype.kind == "f":
        scratch = np.zeros(1, dtype=g.dtype)
        mod.encode_float(g, g.view(u), k, scratch, scratch.view(u), out)
    else:
        mod.encode_int(g, k, g.dtype.itemsize * 8, out)
    return out


def decode(
    mod: ModuleType,
    seq: np.ndarray,
    g: np.ndarray,
    k: int,
    first: int,
    extent: tuple[int, int] | None = None,
) -> None:
    """Decode levels ``first..k`` into ``g`` (side ``2**k+1``, coarser vertices set) in place;
    with ``extent=(rows, cols)`` only what ``g[:rows, :cols]`` needs (the rest is left unset)."""
    rows, cols = (g.shape[0], g.shape[1]) if extent is None else extent
    u = _UINT[g.dtype.itemsize]
    s = np.ascontiguousarray(seq).view(u)
    if g.dtype.kind == "f":
        scratch = np.empty((2, g.shape[0]), dtype=g.dtype)  # one row's predictions
        mod.decode_float(s, g, g.view(u), k, first, scratch, scratch.view(u), rows, cols)
    else:
        mod.decode_int(s, g, k, first, rows, cols)
