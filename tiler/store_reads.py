"""Reading a :class:`tiler.store.TerrainStore`'s blocks: :class:`StoreReads`, the methods that
read its chunks with the format's checks and decode them into levels, grids, masks and errors.

The checks: a chunk whose crc32c does not match, or that the index says was written but is
absent, raises naming array, block and level (:mod:`tiler.read_errors`); a remote read under
way when another thread sees a repair is read again (:data:`EPOCH_RETRIES`). Opening the store,
its zarr handles in a forked child and whether it was replaced (``check_unchanged``) are
:mod:`tiler.store`'s.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from functools import cached_property
from typing import Any

import numpy as np
from zarr.core.sync import sync

from tiler import chunkread, scratch, static_error
from tiler.chunkread_remote import IndexCache, decoded, fetch_chunk, fetch_chunks
from tiler.codecs import BoundCodec
from tiler.errors import (
    MissingChunkError,
    StoreChangedError,
    StoreCorruptError,
    StoreError,
    StoreUnavailableError,
)
from tiler.grid import BlockGrid, as_block, as_index
from tiler.interrupt import DeferredInterrupt
from tiler.layout import level_end, level_start
from tiler.location import Location
from tiler.meta import BlockIndex, StoreMeta
from tiler.read_errors import READ_ERRORS, is_fill, missing_chunk, read_error
from tiler.schema import INDEX_NAMES, SHARDED_LEVELS, chunk_key, index_chunk
from tiler.transport import server_errors
from tiler.vertical import from_metres, to_metres

#: remote reads of one block tried again when a repair is seen while they are under way
#: (their kept shard indexes may be the old ones), at most
EPOCH_RETRIES = 4


class StoreReads:
    """The block reads of :class:`tiler.store.TerrainStore` (its only user, which sets the
    attributes below and provides ``_in_process``, ``_array``, ``check_unchanged``,
    ``_not_replaced`` and ``direct_reads``)."""

    url: str
    location: Location
    meta: StoreMeta
    grid: BlockGrid
    k: int
    codec: BoundCodec
    checksummed: bool
    shard_indexes: IndexCache
    _value_dtype: np.dtype
    _fill: Any
    _changed: str | None
    _direct: dict[str, chunkread.LevelSpec]
    _root: str
    _remote: Any

    def _check_before_read(self) -> None:
        """:meth:`check_unchanged` before a remote read; a server failure is left to the read
        itself, which names the block it could not read."""
        with contextlib.suppress(StoreUnavailableError):
            self.check_unchanged()

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
