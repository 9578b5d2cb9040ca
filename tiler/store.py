"""The zarr v3 store's thread-safe reader, :class:`TerrainStore`, and :func:`open_store`.

Here: opening a store, its zarr handles (reopened in a forked child) and whether it was
replaced or rewritten since it was opened. Its block reads (the checked chunk reads and their
decoding) are :class:`tiler.store_reads.StoreReads`, which :class:`TerrainStore` inherits. The
metadata and grid index types live in :mod:`tiler.meta` and the array layout in
:mod:`tiler.schema` (their public names are re-exported here); the direct chunk reads are
:mod:`tiler.chunkread`.

Layout (see docs/FORMAT.md for the full description)::

    zarr.json                  root group; attribute "terrastream" holds the metadata
    levels/<i>                 (rows, cols, level_size(i)) stored level values, 1 chunk per block
    errors                     (rows, cols, 2, E) float16, monotone node errors (qiu, bound)
    mask                       (rows, cols, side, side) bool, True = valid (nodata blocks only)
    index/{exists,done,has_nodata,zmin,zmax,window,digest}   the grid index
    level_index, order_index   (side, side) the shared per-vertex level and order indices

The root attribute ``terrastream.complete`` is written last; a store without it is unfinished.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
import time
from typing import Any

import numpy as np
import zarr

from tiler import chunkread, codecs
from tiler.array_check import array_problem
from tiler.chunkread_remote import IndexCache
from tiler.errors import (
    StoreChangedError,
    StoreCorruptError,
    StoreError,
    StoreIncompleteError,
    StoreUnavailableError,
    StoreVersionError,
)
from tiler.lease import live_writer
from tiler.location import Location, as_location, is_url
from tiler.meta import BlockIndex, StoreMeta, read_meta, tool_version, write_meta
from tiler.read_errors import open_error
from tiler.schema import (
    ATTR,
    DEFAULT_CLEVEL,
    FORMAT_VERSION,
    INDEX_CHUNK,
    SHARD_BLOCKS,
    SHARDED_LEVELS,
    array_names,
    compressor,
    create_layout,
    level_fill,
)
from tiler.store_reads import EPOCH_RETRIES, StoreReads
from tiler.transport import is_transport_error, server_errors, unavailable
from tiler.zarr_batch import open_each

__all__ = [
    "ATTR",
    "DEFAULT_CLEVEL",
    "EPOCH_RETRIES",
    "FORMAT_VERSION",
    "INDEX_CHUNK",
    "SHARD_BLOCKS",
    "SHARDED_LEVELS",
    "BlockIndex",
    "StoreMeta",
    "TerrainStore",
    "compressor",
    "create_layout",
    "is_url",
    "open_store",
    "read_meta",
    "tool_version",
    "write_meta",
]


REMOTE_CHECK_INTERVAL_S = 1.0
#: a store first read in a forked child reopens its zarr store under this lock (its event
#: loop and connections are the parent's); a new lock in each child
_FORK_LOCK = threading.Lock()


def _new_fork_lock() -> None:
    global _FORK_LOCK
    _FORK_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_new_fork_lock)


class TerrainStore(StoreReads):
    """Read access to a finished store; safe to share between threads.

    Format-2 stores are checked on every read: a chunk whose crc32c does not match raises
    :class:`ChunkChecksumError`, a chunk the index says was written but is absent raises
    :class:`MissingChunkError` (both name array, block and level), and a store replaced or
    rewritten since it was opened raises :class:`StoreChangedError` (checked after each read
    batch; at most once a second for remote stores, so reads in the second before it is seen
    may return the new store's chunks, or a block mixing the old and new store's). Once seen,
    the change is final: every later read raises it; a remote read under way when another
    thread sees a repair is read again (its kept shard indexes may be the old ones).

    A store opened before a ``fork`` reopens its zarr store in the child on first use there.

    Level chunks of a format-2 store are read and decoded by :mod:`tiler.chunkread` (same
    checks, no zarr call per chunk; a remote store's one request each, its shard indexes kept
    and a block's levels asked for at once: :mod:`tiler.chunkread_remote`);
    ``direct_reads=False`` reads them through zarr.
    """

    def __init__(
        self,
        url: str | os.PathLike | Location | Any,
        *,
        allow_incomplete: bool = False,
        direct_reads: bool = True,
    ) -> None:
        self.location = as_location(url)
        self.url = self.location.url
        with server_errors("the store's metadata", self.url):
            self._token = self.location.change_token()
            try:
                self._group = self.location.open_group("r")
            except (FileNotFoundError, zarr.errors.GroupNotFoundError) as exc:
                raise StoreError(f"no terrastream store at {self.url!r}: {exc}") from exc
            except (ValueError, KeyError, json.JSONDecodeError) as exc:
                msg = f"cannot open {self.url!r} as a zarr store: {exc}"
                raise StoreCorruptError(msg) from exc
            self.meta = read_meta(self._group)
        if not self.meta.complete and not allow_incomplete:
            writer = live_writer(self.location)
            if writer is not None:  # not interrupted: still being written
                raise StoreIncompleteError(
                    f"store {self.url!r} is being written now by {writer}; wait until that "
                    "'terrastream tile' finishes (it refuses a second writer meanwhile)"
                )
            raise StoreIncompleteError(
                f"store {self.url!r} was never finished (interrupted tiling?); run the same "
                "'terrastream tile' command again to complete it."
            )
        if np.dtype(self.meta.storage_dtype).kind != "u":
            raise StoreVersionError(
                f"store {self.url!r} was written by a pre-release terrastream (signed storage "
                f"dtype {self.meta.storage_dtype}); tile the DEM again"
            )
        self.grid = self.meta.grid
        self.k = self.meta.k
        self.dtype = np.dtype(self.meta.dtype)
        self.codec = codecs.for_meta(self.meta)
        self._value_dtype = self.codec.value_dtype
        self.checksummed = self.meta.format_version >= 2
        self._fill = level_fill(self.meta.storage_dtype) if self.checksummed else None
        self._lock = threading.Lock()
        #: the process the zarr store was opened in (a forked child reopens it: _in_process;
        #: set before the arrays are first opened, which asks it)
        self._pid = os.getpid()
        self._arrays: dict[str, zarr.Array] = {}
        self._last_check = time.monotonic()
        #: the change :meth:`check_unchanged` saw: every later read raises it (a reader never
        #: goes on mixing the old store's data with the new one's)
        self._changed: str | None = None
        if self.meta.complete:  # a missing array is damage, not an empty one
            self._open_arrays(array_names(self.k))
            if self.checksummed:
                self._check_array_metadata()
        remote = not (self.location.is_local or self.location.is_memory)
        direct = direct_reads and self.checksummed and self.meta.complete
        self._direct = chunkread.direct_specs(self._arrays, self.k) if direct else {}
        if self.location.is_memory:  # (a memory store is read through zarr)
            self._direct = {}
        self._root = str(self.location.path) if self._direct and not remote else ""
        #: a remote store's zarr store, its chunks read directly (tiler.chunkread_remote),
        #: and the shard indexes read from it
        self._remote = self._group.store if self._direct and remote else None
        self.shard_indexes = IndexCache()

    @property
    def direct_reads(self) -> bool:
        """Whether every level is read by :mod:`tiler.chunkread` (else zarr reads some)."""
        return all(f"levels/{i}" in self._direct for i in range(self.k + 1))

    def __repr__(self) -> str:
        m = self.meta
        return f"TerrainStore({self.url!r}, {m.height}x{m.width} {m.dtype}, k={m.k})"

    def _open_error(self, name: str, exc: BaseException) -> StoreError | None:
        """The error opening array ``name`` failed with (:func:`tiler.read_errors.open_error`)."""
        return open_error(self.url, name, exc)

    def _in_process(self) -> None:
        """Reopen the zarr store in a forked child before its first read there: the parent's
        is bound to the parent's event loop and connections (a remote read then failed as
        "the store is damaged"), its locks and in-flight index reads may be held by threads
        the child does not have."""
        if self._pid == os.getpid():
            return
        with _FORK_LOCK:
            if self._pid == os.getpid():
                return
            self._lock = threading.Lock()
            with server_errors("the store's metadata", self.url):
                try:
                    group = self.location.open_group("r")
                except (FileNotFoundError, zarr.errors.GroupNotFoundError) as exc:
                    self._changed = (
                        f"store {self.url!r} was removed or replaced while it was open (its "
                        f"root metadata is gone: {exc}); reopen it to read the new store"
                    )
                    raise StoreChangedError(self._changed) from exc
            self._group = group
            self._arrays = {}
            if self._remote is not None:
                self._remote = group.store
            self.shard_indexes = IndexCache(self.shard_indexes.max_entries)
            self._pid = os.getpid()

    def _array(self, name: str) -> zarr.Array:
        self._in_process()
        with self._lock:
            arr = self._arrays.get(name)
            if arr is None:
                try:
                    arr = self._group[name]
                except Exception as exc:
                    err = self._open_error(name, exc)
                    if err is None:
                        raise
                    raise err from exc
                self._arrays[name] = arr
            return arr

    def _open_arrays(self, names: list[str]) -> None:
        """Open ``names`` at once (:func:`tiler.zarr_batch.open_each`: one round trip's
        latency on a remote store instead of one per array; ~0.75x the time for the 22
        arrays of a local ``k = 10`` store, ``bench/tiling_phases.py``); the first failure in
        ``names``' order is raised as :meth:`_array` raises it (a group where an array belongs:
        damaged metadata)."""
        found = open_each(self._group.store, names)
        for name, obj in zip(names, found, strict=True):
            if isinstance(obj, BaseException):
                err = self._open_error(name, obj)
                if err is None:
                    raise obj
                raise err from obj
        with self._lock:
            for name, arr in zip(names, found, strict=True):
                self._arrays.setdefault(name, arr)

    def _check_array_metadata(self) -> None:
        """Refuse an array whose ``zarr.json`` departs from the format's fixed chain
        (:mod:`tiler.array_check`): zarr would decode it, wrongly, with no error."""
        for name, arr in list(self._arrays.items()):
            why = array_problem(name, arr.metadata.to_dict(), self.meta)
            if why is not None:
                self._not_replaced()
                raise StoreCorruptError(
                    f"array {name!r} of {self.url!r} has metadata no terrastream store has "
                    f"({why}): read by it, its values would be wrong. The store is damaged; "
                    "tile the DEM again with --overwrite"
                )

    def check_unchanged(self, *, force: bool = False) -> None:
        """Raise StoreChangedError if the store was replaced or rewritten since it was opened
        (once seen, on every later call and read: the change is final for this reader)."""
        if self._changed is not None:
            raise StoreChangedError(self._changed)
        self._in_process()
        if not self.location.is_local and not self.location.is_memory and not force:
            now = time.monotonic()
            if now - self._last_check < REMOTE_CHECK_INTERVAL_S:
                return
            self._last_check = now
        try:
            token = self.location.change_token()
        except Exception as exc:
            if not is_transport_error(exc):
                raise
            raise unavailable("the root metadata (was the store replaced?)", self.url, exc) from exc
        if token == self._token:
            return
        gen = None
        with contextlib.suppress(StoreError, FileNotFoundError, ValueError, KeyError):
            gen = read_meta(self.location.open_group("r")).generation
        if gen is None or gen != self.meta.generation:
            self._changed = (
                f"store {self.url!r} was replaced or rewritten while it was open (generation "
                f"{self.meta.generation!r} -> {gen!r}); reopen it to read the new store"
            )
            raise StoreChangedError(self._changed)
        # the same store, its metadata rewritten (a repair: blocks rebuilt, so their chunks
        # moved within the shards): kept shard indexes may point at other blocks' chunks
        self.shard_indexes.clear()
        self._token = token

    def _not_replaced(self) -> None:
        """Before a read failure is called damage: raise ``StoreChangedError`` if the store
        was removed, replaced or rewritten since it was opened (its chunks are gone or
        another store's, not damaged: reopen it, do not repair it). A check the server does
        not answer leaves the read's own error to be raised."""
        with contextlib.suppress(StoreUnavailableError):
            self.check_unchanged(force=True)


def open_store(
    url: str | os.PathLike | Location | Any, *, allow_incomplete: bool = False
) -> TerrainStore:
    """Open a finished store (local path, fsspec URL such as ``http://``, or a zarr Store)."""
    loc = as_location(url)
    if loc.is_local and not os.path.exists(loc.path):
        raise StoreError(f"no store at {loc.url!r}: the path does not exist")
    if loc.is_local and os.path.isfile(loc.path):  # (a DEM where its store was meant)
        raise StoreError(
            f"{loc.url!r} is a file, not a store (a directory tiler.tile.tile makes); if it is "
            "a DEM, tile it first"
        )
    from tiler.remote import check_range_support

    check_range_support(loc.url, loc.storage_options)  # HTTP servers must serve byte ranges
    return TerrainStore(loc, allow_incomplete=allow_incomplete)
