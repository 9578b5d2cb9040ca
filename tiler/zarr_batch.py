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


def _store_kwargs(loc: Location) -> dict[str, Any]:
    return {"storage_options": loc.storage_options} if loc.storage_options else {}


async def _open(loc: Location, names: Sequence[str], mode: str) -> list[zarr.AsyncArray]:
    kw = {**_store_kwargs(loc), "mode": mode, "zarr_format": 3}  # (terrastream stores are v3)
    opens = (zasync.open_array(store=loc.target, path=n, **kw) for n in names)
    arrays = await asyncio.gather(*opens)
    return [a.with_config(WRITE_CONFIG) if mode != "r" else a for a in arrays]


def open_arrays(loc: Location, names: Sequence[str], mode: str = "r+") -> list[zarr.Array]:
    """The arrays ``names`` of the store at ``loc``, opened concurrently (for writing, every
    chunk written: ``WRITE_CONFIG``, as :func:`tiler.run.open_for_write`)."""
    return [zarr.Array(a) for a in sync(_open(loc, names, mode))]


def open_each(store: Any, names: Sequence[str]) -> list[zarr.Array | BaseException]:
    """The arrays ``names`` of zarr store ``store``, opened for reading concurrently; where
    one cannot be opened, the exception instead (``zarr.errors.ArrayNotFoundError`` if
    absent; the caller decides)."""

    async def go() -> list[Any]:
        opens = (zasync.open_array(store=store, path=n, mode="r", zarr_format=3) for n in names)
        return await asyncio.gather(*opens, return_exceptions=True)

    return [a if isinstance(a, BaseException) else zarr.Array(a) for a in sync(go())]


def write_all(writes: Sequence[tuple[zarr.Array, Any, np.ndarray]]) -> None:
    """``array[selection] = values`` for every ``(array, selection, values)``, concurrently
    (arrays distinct, or selections in distinct chunks)."""

    async def go() -> None:
        await asyncio.gather(*(a.async_array.setitem(sel, v) for a, sel, v in writes))

    sync(go())


def read_all(loc: Location, names: Sequence[str]) -> list[np.ndarray]:
    """The whole of each array ``names`` at ``loc``, opened and read concurrently."""

    async def go() -> list[np.ndarray]:
        arrays = await _open(loc, names, "r")
        return list(await asyncio.gather(*(a.getitem(...) for a in arrays)))

    return [np.asarray(v) for v in sync(go())]
