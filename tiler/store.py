"""The zarr v3 store's thread-safe reader, :class:`TerrainStore`, and :func:`open_store`.

The metadata and grid index types live in :mod:`tiler.meta` and the array layout in
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
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from functools import cached_property
from typing import Any

import numpy as np
import zarr
from zarr.core.sync import sync

from tiler import chunkread, codecs, scratch, static_error
from tiler.array_check import array_problem
from tiler.chunkread_remote import IndexCache, decoded, fetch_chunk, fetch_chunks
from tiler.errors import (
    MissingChunkError,
    StoreChangedError,
    StoreCorruptError,
    StoreError,
    StoreIncompleteError,
    StoreUnavailableError,
    StoreVersionError,
)
from tiler.grid import as_block, as_index
from tiler.interrupt import DeferredInterrupt
from tiler.layout import level_end, level_start
from tiler.lease import live_writer
from tiler.location import Location, as_location, is_url
from tiler.meta import BlockIndex, StoreMeta, read_meta, tool_version, write_meta
from tiler.read_errors import READ_ERRORS, is_fill, missing_chunk, open_error, read_error
from tiler.schema import (
    ATTR,
    DEFAULT_CLEVEL,
    FORMAT_VERSION,
    INDEX_CHUNK,
    INDEX_NAMES,
    SHARD_BLOCKS,
    SHARDED_LEVELS,
    array_names,
    chunk_key,
    compressor,
    create_layout,
    index_chunk,
    level_fill,
)
from tiler.transport import is_transport_error, server_errors, unavailable
from tiler.vertical import from_metres, to_metres
from tiler.zarr_batch import open_each

__all__ = [
    "ATTR",
    "DEFAULT_CLEVEL",
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
#: remote reads of one block tried again when a repair is seen while they are under way
#: (their kept shard indexes may be the old ones), at most
EPOCH_RETRIES = 4
#: a store first read in a forked child reopens its zarr store under this lock (its event
#: loop and connections are the parent's); a new lock in each child
_FORK_LOCK = threading.Lock()


def _new_fork_lock() -> None:
    global _FORK_LOCK
    _FORK_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_new_fork_lock)


class TerrainStore:
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

    def _check_before_read(self) -> None:
        """:meth:`check_unchanged` before a remote read; a server failure is left to the read
        itself, which names the block it could not read."""
        with contextlib.suppress(StoreUnavailableError):
            self.check_unchanged()

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

    def _read(
        self,
        name: str,
        block: tuple[int, int],
        level: int | None,
        into: np.ndarray | None = None,
    ) -> np.ndarray:
        """One block of one array, with checksum and missing-chunk errors naming the block
        (a direct level read decompresses into ``into`` when given)."""
        if self._changed is not None:
            raise StoreChangedError(self._changed)
        self._in_process()
        spec = self._direct.get(name)
        if self._remote is not None:  # (rate-limited) a repair seen drops kept shard indexes
            self._check_before_read()  # before they are used, not after
        try:
            if spec is None:
                out = self._array(name)[block]
            elif self._remote is None:
                out = chunkread.read_local(self._root, spec, block, into)
            else:
                remote, sp = self._remote, spec
                frame = self._unrepaired(
                    block, lambda: sync(fetch_chunk(remote, sp, block, self.shard_indexes))
                )
                out = decoded(frame, spec, into)
        except StoreChangedError:  # (a read raced with repairs: not the block's damage)
            raise
        except Exception as exc:
            out = exc
        return self._checked(name, block, level, out)

    def _unrepaired(self, block: tuple[int, int], fetch: Any) -> Any:
        """``fetch()`` (a remote read of ``block``'s chunks), again while a repair of the
        store was seen by another thread during it (:meth:`check_unchanged` cleared the kept
        shard indexes: the read may have used the old ones, which point at other blocks'
        chunks of the repaired shard, whose crc32c passes)."""
        for _ in range(EPOCH_RETRIES):
            epoch = self.shard_indexes.epoch
            try:
                got = fetch()
            except (chunkread.ChecksumMismatch, chunkread.ChunkDecodeError):
                if self.shard_indexes.epoch == epoch:
                    raise  # damage: no repair was seen meanwhile
                continue  # (an old index's range over the rewritten shard: not damage)
            if self.shard_indexes.epoch == epoch:
                return got
        raise StoreChangedError(
            f"store {self.url!r} was repaired {EPOCH_RETRIES} times while block {block} was "
            "read; read it again"
        )

    def _remote_levels(self, block: tuple[int, int], views: list[np.ndarray]) -> list[np.ndarray]:
        """Levels ``0..len(views)-1`` of ``block`` from a remote store, asked for at once (one
        round trip: :func:`tiler.chunkread_remote.fetch_chunks`), decompressed into ``views``
        here."""
        if self._changed is not None:
            raise StoreChangedError(self._changed)
        self._in_process()
        self._check_before_read()  # (as in _read: before the kept shard indexes are used)
        specs = [self._direct[f"levels/{i}"] for i in range(len(views))]
        reads = [(sp, block) for sp in specs]
        remote = self._remote
        got = self._unrepaired(block, lambda: sync(fetch_chunks(remote, reads, self.shard_indexes)))
        return [self._checked(f"levels/{i}", block, i, decoded(f, sp, v))
                for i, (sp, f, v) in enumerate(zip(specs, got, views, strict=True))]  # fmt: skip

    def _checked(
        self, name: str, block: tuple[int, int], level: int | None, out: Any
    ) -> np.ndarray:
        """What a read of ``block`` of array ``name`` gave (``out``: its values, None for no
        chunk, or the exception it raised), with checksum and missing-chunk errors naming the
        block."""
        what = f"level {level}" if level is not None else name
        if isinstance(out, BaseException):
            err = (
                read_error(self.url, name, block, level, out)
                if isinstance(out, Exception)
                else None
            )
            if err is None:
                raise out
            if not isinstance(err, StoreUnavailableError):  # (a server's failure is not damage)
                self._not_replaced()
            raise err from out
        spec = self._direct.get(name)
        if spec is not None:  # what zarr's reader makes of it: see _looks_missing
            if out is None and name == "mask" and not self.index.has_nodata[block]:
                return np.ones(spec.shape, dtype=bool)  # zarr's fill: such blocks write none
            if out is None or (
                spec.shard is not None and out[0] == self._fill and np.all(out == self._fill)
            ):
                self._not_replaced()
                raise self._missing(what, name, block, level)
            return out
        if self.checksummed and self._looks_missing(name, block, out):
            self._not_replaced()
            raise self._missing(what, name, block, level)
        return out

    def _not_replaced(self) -> None:
        """Before a read failure is called damage: raise ``StoreChangedError`` if the store
        was removed, replaced or rewritten since it was opened (its chunks are gone or
        another store's, not damaged: reopen it, do not repair it). A check the server does
        not answer leaves the read's own error to be raised."""
        with contextlib.suppress(StoreUnavailableError):
            self.check_unchanged(force=True)

    def _missing(
        self, what: str, name: str, block: tuple[int, int], level: int | None
    ) -> MissingChunkError:
        return missing_chunk(self.url, what, name, block, level)

    def _looks_missing(self, name: str, block: tuple[int, int], out: np.ndarray) -> bool:
        nodata = name == "mask" and bool(self.index.has_nodata[block])
        if not is_fill(name, out, self._fill, nodata):
            return False
        key = chunk_key(name, block, *self.grid.shape)
        sharded = name.startswith("levels/") and int(name.split("/")[1]) < SHARDED_LEVELS
        if sharded:
            return True
        with server_errors(f"whether chunk {key!r} exists", self.url):
            return not self.location.key_exists(key)

    @cached_property
    def index(self) -> BlockIndex:
        """The grid index (read once; damaged or missing index chunks raise)."""
        out = {}
        for n in INDEX_NAMES:
            try:
                with server_errors(f"the block index 'index/{n}'", self.url):
                    out[n] = self._array(f"index/{n}")[...]
            except StoreUnavailableError:
                raise
            except READ_ERRORS as exc:
                self._not_replaced()
                raise StoreCorruptError(
                    f"the block index 'index/{n}' of {self.url!r} is damaged ({exc}); the store "
                    "is damaged: verify it and repair it from the source"
                ) from exc
        if self.checksummed and self.meta.complete:
            rows, cols = self.grid.shape
            ir, ic = index_chunk(rows, cols)
            for n in INDEX_NAMES:
                for br in range(0, rows, ir):
                    for bc in range(0, cols, ic):
                        key = chunk_key(f"index/{n}", (br, bc), rows, cols)
                        with server_errors(f"whether chunk {key!r} exists", self.url):
                            found = self.location.key_exists(key)
                        if not found:
                            raise MissingChunkError(
                                f"chunk {key!r} of the block index is missing from {self.url!r}; "
                                "the store is damaged: verify it and repair it from the source",
                                array=f"index/{n}",
                                block=(br, bc),
                                level=None,
                            )
        return BlockIndex(**out)

    def check_block(self, block: tuple[int, int]) -> tuple[int, int]:
        """Validate a block id (two integers inside the grid) and return it as ints."""
        br, bc = as_block(block)
        self.grid.check_block(br, bc)
        return br, bc

    def read_level_raw(self, block: tuple[int, int], level: int) -> np.ndarray:
        """One block's one stored level, as stored (residuals): exactly one chunk read."""
        br, bc = self.check_block(block)
        level = as_index(level, "level")
        if not 0 <= level <= self.k:
            raise StoreError(f"level {level} is outside 0..{self.k}")
        out = self._read(f"levels/{level}", (br, bc), level)
        self.check_unchanged()
        return out

    def read_levels_raw(self, block: tuple[int, int], max_level: int) -> list[np.ndarray]:
        """Stored levels ``0..max_level`` of a block (one chunk each; concurrent for remote).

        Read directly (:mod:`tiler.chunkread`), the levels are consecutive views of one array:
        the block's sequence, which the decoders then use without a copy.
        """
        br, bc = self.check_block(block)
        max_level = as_index(max_level, "level")
        if not 0 <= max_level <= self.k:
            raise StoreError(f"level {max_level} is outside 0..{self.k}")
        out = self._levels_raw((br, bc), max_level, None)
        self.check_unchanged()
        return out

    def _levels_raw(
        self, block: tuple[int, int], max_level: int, seq: np.ndarray | None
    ) -> list[np.ndarray]:
        levels = range(max_level + 1)
        if self.direct_reads:
            n = level_end(max_level) + 1
            if seq is None:
                seq = np.empty(n, dtype=self.meta.storage_dtype)
            views = [seq[level_start(i) : level_end(i) + 1] for i in levels]
            if self._remote is not None:
                return self._remote_levels(block, views)
            return [self._read(f"levels/{i}", block, i, views[i]) for i in levels]
        if self.location.is_local or self.location.is_memory or max_level == 0:
            return [self._read(f"levels/{i}", block, i) for i in levels]
        # a Ctrl-C is raised once the pool has stopped, never inside its locks (tiler.interrupt)
        with (
            DeferredInterrupt(),
            ThreadPoolExecutor(
                max_workers=min(8, max_level + 1), thread_name_prefix="terrastream-read"
            ) as pool,
        ):
            return list(pool.map(lambda i: self._read(f"levels/{i}", block, i), levels))

    def _scratch(self, n: int) -> np.ndarray | None:
        """This thread's reusable buffer for ``n`` stored values (:func:`tiler.scratch.buffer`)."""
        return scratch.buffer(n, np.dtype(self.meta.storage_dtype))

    def decode_next(self, levels: list[np.ndarray], raw: np.ndarray) -> np.ndarray:
        """Decode the next level from its raw values and the decoded levels ``0..L-1``
        (metres of a scaled store are taken back to its stored values first)."""
        levels = [from_metres(self.meta, v, self._value_dtype) for v in levels]  # tiler.vertical
        return self.codec.decode_next(levels, raw)

    def to_heights(self, values: np.ndarray) -> np.ndarray:
        """Convert decoded storage values to the source dtype (dequantises ``--precision``);
        to float64 metres when the store records a band scale/offset or non-metre units."""
        return to_metres(self.meta, self.codec.to_heights(values))  # identity for plain metres

    def read_levels(self, block: tuple[int, int], max_level: int) -> list[np.ndarray]:
        """Decoded heights of levels ``0..max_level`` of a block (sequence order, source dtype)."""
        raws = self.read_levels_raw(block, max_level)
        return [self.to_heights(v) for v in self.codec.decode(raws)]

    def read_block(
        self,
        block: tuple[int, int],
        max_level: int | None = None,
        *,
        extent: tuple[int, int] | None = None,
    ) -> np.ndarray:
        """The ``2**L+1`` grid of a block at level ``L`` (default finest), in the source dtype.
        Samples that are not terrain (nodata, padding, every sample of a block without
        terrain) hold filler values, not the nodata value: :meth:`read_mask` tells them.

        ``extent=(rows, cols)``: only the grid's top-left ``rows x cols``, decoded alone (an
        edge block's samples inside the DEM: :meth:`block_extent`; the padding is not decoded).
        """
        level = self.k if max_level is None else as_index(max_level, "level")
        if not 0 <= level <= self.k:
            raise StoreError(f"level {level} is outside 0..{self.k}")
        br, bc = self.check_block(block)
        if extent is not None:
            extent = (as_index(extent[0], "extent rows"), as_index(extent[1], "extent columns"))
        seq = self._scratch(level_end(level) + 1) if self.direct_reads else None
        raws = self._levels_raw((br, bc), level, seq)
        self.check_unchanged()
        if extent is None:
            return self.to_heights(self.codec.decode_grid(raws, level))
        work = self._work_grid(level) if self.direct_reads else None
        return self.to_heights(self.codec.decode_grid(raws, level, extent, work))

    def block_extent(self, block: tuple[int, int], level: int | None = None) -> tuple[int, int]:
        """``(rows, cols)`` of a block's level-``level`` grid that lie inside the DEM (its
        shared last row and column included): the ``extent`` that drops only padding."""
        level = self.k if level is None else as_index(level, "level")
        if not 0 <= level <= self.k:
            raise StoreError(f"level {level} is outside 0..{self.k}")
        _, _, h, w = self.grid.block_window(*self.check_block(block))
        step = 1 << (self.k - level)
        return (h - 1) // step + 1, (w - 1) // step + 1

    def _work_grid(self, level: int) -> np.ndarray | None:
        """This thread's reusable ``2**level+1`` square of the decoded dtype, a windowed
        decode's scratch (:func:`tiler.scratch.square`)."""
        return scratch.square((1 << level) + 1, np.dtype(self.codec.value_dtype))

    def read_mask(self, block: tuple[int, int]) -> np.ndarray:
        """``(side, side)`` bool, True where the block has terrain (not nodata, not padding)."""
        br, bc = self.check_block(block)
        out = self._read("mask", (br, bc), None)
        self.check_unchanged()
        return out

    def read_errors(self, block: tuple[int, int]) -> dict[str, list[np.ndarray]]:
        """The block's monotone error fields, unpacked per depth (see tiler.static_error)."""
        br, bc = self.check_block(block)
        packed = self._read("errors", (br, bc), None)
        self.check_unchanged()
        return {
            name: static_error.unpack_field(packed[i], self.k, self.meta.error_cap)
            for i, name in enumerate(self.meta.error_fields)
        }

    def level_nbytes(self) -> list[int]:
        """Stored (compressed) bytes of each level array, summed over blocks."""
        return [self.location.total_size(f"levels/{i}") for i in range(self.k + 1)]

    def nbytes(self) -> dict[str, int]:
        """Stored bytes by component: levels, errors, mask, index, metadata, total."""
        size = self.location.total_size
        parts = {
            "levels": sum(self.level_nbytes()),
            "errors": size("errors"),
            "mask": size("mask"),
            "index": size("index") + size("level_index") + size("order_index"),
        }
        total = size("")
        parts["metadata"] = total - sum(parts.values())
        parts["total"] = total
        return parts

    def blocks(self) -> Iterable[tuple[int, int]]:
        """Ids of blocks that hold terrain."""
        rr, cc = np.nonzero(self.index.exists)
        return list(zip(rr.tolist(), cc.tolist(), strict=True))


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
