"""Per-thread scratch buffers: ``TerrainStore.read_block`` decompresses a block's stored level
sequence into one reused array per thread and dtype instead of a fresh one per read (a fresh
2 MiB array costs ~0.5-1 ms of page faults per 1025² block), and a windowed decode into one
reused square grid."""

from __future__ import annotations

import threading

import numpy as np

#: read_block decompresses a block's levels into a per-thread buffer up to this size
SCRATCH_MAX_BYTES = 16 << 20
_SCRATCH = threading.local()


def buffer(n: int, dtype: np.dtype) -> np.ndarray | None:
    """This thread's buffer for ``n`` values of ``dtype``, shared by the thread's stores; None
    above :data:`SCRATCH_MAX_BYTES`."""
    if n * dtype.itemsize > SCRATCH_MAX_BYTES:
        return None
    # one owner array per dtype, so the level views share it as their base (a view of a
    # view of another dtype would not, and encoding.joined would copy the sequence)
    bufs = _SCRATCH.__dict__.setdefault("seq", {})
    buf = bufs.get(dtype.str)
    if buf is None or buf.size < n:
        buf = bufs[dtype.str] = np.empty(SCRATCH_MAX_BYTES // dtype.itemsize, dtype=dtype)
    return buf[:n]


def square(side: int, dtype: np.dtype) -> np.ndarray | None:
    """This thread's ``(side, side)`` grid of ``dtype`` (a windowed decode's work grid: a fresh
    2 MiB grid costs its page faults on every read); None above :data:`SCRATCH_MAX_BYTES`."""
    if side * side * dtype.itemsize > SCRATCH_MAX_BYTES:
        return None
    bufs = _SCRATCH.__dict__.setdefault("grid", {})
    buf = bufs.get(dtype.str)
    if buf is None or buf.size < side * side:
        buf = bufs[dtype.str] = np.empty(side * side, dtype=dtype)
    return buf[: side * side].reshape(side, side)
