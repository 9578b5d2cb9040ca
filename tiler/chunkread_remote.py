"""Direct reads of a remote format-2 store's block chunks: :mod:`tiler.chunkread`'s checks and
decoding over the zarr store's own byte-range requests, without a zarr array call per chunk.

Through zarr, an inner chunk of a sharded level (levels ``0..SHARDED_LEVELS-1``) costs two
dependent requests — the shard's index, then the chunk — so a level read waits two round
trips; and a whole block's levels went through a pool of 8 threads, 11 levels in two waves.
Here a shard's encoded index is kept once read (:class:`IndexCache`, bounded: 16 bytes per
block of the shard), so a level is one request, and :func:`fetch_chunks` asks for a block's
levels at once on zarr's event loop: one round trip for the block. The loop only fetches and
checks the bytes; the calling thread decompresses them (as a local read does), so the session's
loaders decompress side by side.

The bytes are checked as :mod:`tiler.chunkread` checks them (the index's and the chunk's
crc32c, the blosc frame's size). A kept index that does not match its shard any more — the
store rewritten under the reader, which :meth:`TerrainStore.check_unchanged` reports within a
second — fails those checks, or finds no chunk where there was one: it is fetched again once,
and only a fresh index's failure is the store's damage.
"""

from __future__ import annotations

import asyncio
import threading
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np
from zarr.abc.store import RangeByteRequest, SuffixByteRequest
from zarr.core.buffer import default_buffer_prototype

from tiler.chunkread import (
    ChecksumMismatch,
    ChunkDecodeError,
    LevelSpec,
    check_chunk,
    decompress,
    shard_entry,
)
from tiler.errors import RemoteStoreError

__all__ = ["IndexCache", "decoded", "fetch_chunk", "fetch_chunks"]

#: shard indexes kept per store, at most (a 16×16-block shard's is 4 KiB: 2 MiB in all)
INDEX_ENTRIES = 512


class IndexCache:
    """Encoded shard indexes by store key, the ``max_entries`` most recently used (thread
    safe: the session's loader threads share a store); ``fetches`` counts the indexes read."""

    def __init__(self, max_entries: int = INDEX_ENTRIES) -> None:
        self.max_entries = int(max_entries)
        self._lock = threading.Lock()
        self._entries: OrderedDict[str, bytes] = OrderedDict()
        self.fetches = 0
        #: how many times the cache was cleared: an index read begun before a clear is not
        #: kept after it (it may predate the rewrite the clear is for)
        self.epoch = 0
        #: (epoch, shard key) -> the read of its index under way (event-loop side only:
        #: concurrent reads of one shard's index in one epoch share a request)
        self.inflight: dict[tuple[int, str], asyncio.Future] = {}

    def fetched(self) -> None:
        """Count one index read from the store."""
        with self._lock:
            self.fetches += 1

    def get(self, key: str) -> bytes | None:
        """The kept index of shard ``key`` (now the most recently used), or None."""
        with self._lock:
            index = self._entries.get(key)
            if index is not None:
                self._entries.move_to_end(key)
            return index

    def put(self, key: str, index: bytes, epoch: int | None = None) -> None:
        """Keep ``index`` for shard ``key`` (the least recently used go past the bound), unless
        it was read in an ``epoch`` before the last :meth:`clear`."""
        with self._lock:
            if epoch is not None and epoch != self.epoch:
                return
            self._entries[key] = index
            self._entries.move_to_end(key)
            while len(self._entries) > self.max_entries:
                self._entries.popitem(last=False)

    def clear(self) -> None:
        """Forget every kept index (the store was rewritten: ``TerrainStore.check_unchanged``)."""
        with self._lock:
            self._entries.clear()
            self.epoch += 1

    def drop(self, key: str) -> None:
        """Forget shard ``key``'s index (it no longer matched the shard)."""
        with self._lock:
            self._entries.pop(key, None)

    def __len__(self) -> int:
        return len(self._entries)


async def fetch_chunk(
    store: Any, spec: LevelSpec, block: tuple[int, int], cache: IndexCache | None = None
) -> np.ndarray | None:
    """``block``'s chunk of one array from zarr store ``store``: its blosc frame, checked
    (:func:`tiler.chunkread.check_chunk`; the caller's thread decompresses it, so the event
    loop only waits for bytes), or None if the store holds no such chunk. Raises
    :class:`~tiler.chunkread.ChecksumMismatch` / :class:`~tiler.chunkread.ChunkDecodeError`
    for damage, and the store's own errors for a failed request."""
    proto = default_buffer_prototype()
    key = spec.key(block)
    if spec.shard is None:
        buf = await store.get(key, proto)
        return None if buf is None else check_chunk(buf.to_bytes(), spec)
    inner = spec.inner(block)
    for fresh in (False, True):
        epoch = 0 if cache is None else cache.epoch  # (read before the index is)
        index = None if fresh or cache is None else cache.get(key)
        kept = index is not None
        if index is None:
            index = await _shared_index(store, key, spec, cache, epoch)
            if index is None:
                return None  # no such shard
            entry = shard_entry(index, spec, inner)  # (checked before it is kept)
            if cache is not None:
                cache.put(key, index, epoch)
        else:
            entry = shard_entry(index, spec, inner)
        if entry is None:
            if kept:
                continue  # a kept index may predate the chunk: ask the shard again
            return None
        off, nbytes = entry
        buf = await store.get(key, proto, RangeByteRequest(off, off + nbytes))
        try:
            data = b"" if buf is None else buf.to_bytes()
            if len(data) > nbytes:
                raise _range_ignored(len(data), nbytes, f"chunk at {off} of {key}")
            if len(data) != nbytes:
                raise ChunkDecodeError(
                    f"the store answered {len(data)} bytes for the {nbytes}-byte chunk at "
                    f"{off} of a shard of {spec.name} (its index points past its data?)"
                )
            return check_chunk(data, spec)
        except (ChecksumMismatch, ChunkDecodeError):
            if not kept:
                raise
            assert cache is not None
            cache.drop(key)  # the kept index no longer matches the shard: ask it again
    raise AssertionError("unreachable: the second pass reads a fresh index")  # pragma: no cover


def _range_ignored(got: int, asked: int, what: str) -> RemoteStoreError:
    """More bytes than a range asked for: no store can cause that, its server (or a proxy
    between) answered the whole object; named as such, not as damage to verify."""
    return RemoteStoreError(
        f"the server answered {got} bytes for the {asked}-byte {what}: it, or a proxy between, "
        "ignored the byte range for this key (a store read in ranges needs them on every key); "
        "serve the store with range support, or copy it to a local directory"
    )


_FAILED = object()  # a shared index read that raised: each waiter reads for itself


async def _read_index(store: Any, key: str, spec: LevelSpec) -> bytes | None:
    """Shard ``key``'s encoded index, from the end of the shard (None: no such shard)."""
    buf = await store.get(key, default_buffer_prototype(), SuffixByteRequest(spec.index_nbytes))
    if buf is None:
        return None
    index = buf.to_bytes()
    if len(index) > spec.index_nbytes:
        raise _range_ignored(len(index), spec.index_nbytes, f"index at the end of {key}")
    if len(index) != spec.index_nbytes:
        raise ChunkDecodeError(
            f"the store answered {len(index)} bytes for the {spec.index_nbytes}-byte "
            f"index at the end of a shard of {spec.name}"
        )
    return index


async def _shared_index(
    store: Any, key: str, spec: LevelSpec, cache: IndexCache | None, epoch: int = 0
) -> bytes | None:
    """:func:`_read_index`, one request for the reads of one shard's index under way at
    once in one ``epoch`` of ``cache`` (a session's loaders starting on blocks of one shard;
    a read begun before a clear is not shared after it); counted in ``cache``."""
    if cache is None:
        return await _read_index(store, key, spec)
    slot = (epoch, key)
    pending = cache.inflight.get(slot)
    if pending is not None:
        got = await asyncio.shield(pending)
        return await _read_index(store, key, spec) if got is _FAILED else got
    fut = asyncio.get_running_loop().create_future()
    cache.inflight[slot] = fut
    try:
        got = await _read_index(store, key, spec)
    except BaseException:
        fut.set_result(_FAILED)
        raise
    finally:
        if cache.inflight.get(slot) is fut:
            del cache.inflight[slot]
    cache.fetched()
    fut.set_result(got)
    return got


def decoded(frame: Any, spec: LevelSpec, out: np.ndarray | None = None) -> Any:
    """A :func:`fetch_chunk` result made values on the calling thread: its frame decompressed
    into ``out`` if given (:func:`tiler.chunkread.decompress`), in the chunk's shape; or what
    came instead of a frame (None: no chunk; the exception the read raised), and the
    exception a decompression raises, returned, not raised (the caller names it)."""
    if not isinstance(frame, np.ndarray):
        return frame
    try:
        got = decompress(frame, spec, out)
    except Exception as exc:
        return exc
    return got.reshape(spec.shape) if len(spec.shape) > 1 else got


async def fetch_chunks(
    store: Any,
    reads: Sequence[tuple[LevelSpec, tuple[int, int]]],
    cache: IndexCache | None = None,
) -> list[np.ndarray | None | BaseException]:
    """:func:`fetch_chunk` of every ``(spec, block)`` at once (one gather on the loop): each
    frame, or the exception its read raised, in order."""
    return await asyncio.gather(
        *(fetch_chunk(store, spec, block, cache) for spec, block in reads),
        return_exceptions=True,
    )
