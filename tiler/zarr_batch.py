"""Many zarr calls at once: one gather on zarr's event loop instead of a round trip each.

zarr's synchronous API hands every call to its event-loop thread and waits for it (~1-2 ms
per open or write of a small array on a local disk, a network latency each on a remote
store). The store's finishing writes open and write a dozen small arrays; issued together the
opens overlap and so do the writes' I/O (the encoding still runs one after another on zarr's
loop). The results are those of the same calls made one by one (tested).
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from typing import Any

import numpy as np
import zarr
from zarr.api import asynchronous as zasync
from zarr.core.sync import sync

from tiler.location import Location
from tiler.schema import WRITE_CONFIG

__all__ = ["open_arrays", "open_each", "read_all", "write_all"]


async def _open(
    store: Any, names: Sequence[str], mode: str, kw: dict[str, Any], errors: bool = False
) -> list[Any]:
    """The arrays ``names`` of ``store`` (zarr format 3: terrastream stores are v3), opened
    concurrently; for writing with ``WRITE_CONFIG``; ``errors``: a failed open's exception
    in its place instead of raised."""
    opens = (zasync.open_array(store=store, path=n, mode=mode, zarr_format=3, **kw) for n in names)
    found = await asyncio.gather(*opens, return_exceptions=errors)
    if mode == "r":
        return list(found)
    return [a if isinstance(a, BaseException) else a.with_config(WRITE_CONFIG) for a in found]


def open_arrays(loc: Location, names: Sequence[str], mode: str = "r+") -> list[zarr.Array]:
    """The arrays ``names`` of the store at ``loc``, opened concurrently (for writing, every
    chunk written: ``WRITE_CONFIG``, as :func:`tiler.run.open_for_write`)."""
    store, kw = loc.zarr_args(mode)
    return [zarr.Array(a) for a in sync(_open(store, names, mode, kw))]


def open_each(store: Any, names: Sequence[str]) -> list[zarr.Array | BaseException]:
    """The arrays ``names`` of zarr store ``store``, opened for reading concurrently; where
    one cannot be opened, the exception instead (``zarr.errors.ArrayNotFoundError`` if
    absent; the caller decides)."""
    found = sync(_open(store, names, "r", {}, errors=True))
    return [a if isinstance(a, BaseException) else zarr.Array(a) for a in found]


def write_all(writes: Sequence[tuple[zarr.Array, Any, np.ndarray]]) -> None:
    """``array[selection] = values`` for every ``(array, selection, values)``, concurrently
    (arrays distinct, or selections in distinct chunks)."""

    async def go() -> None:
        await asyncio.gather(*(a.async_array.setitem(sel, v) for a, sel, v in writes))

    sync(go())


def read_all(loc: Location, names: Sequence[str]) -> list[np.ndarray]:
    """The whole of each array ``names`` at ``loc``, opened and read concurrently."""

    store, kw = loc.zarr_args("r")

    async def go() -> list[np.ndarray]:
        arrays = await _open(store, names, "r", kw)
        return list(await asyncio.gather(*(a.getitem(...) for a in arrays)))

    return [np.asarray(v) for v in sync(go())]
