"""Building a store end to end: create or resume, run the blocks, assemble the shards and index.

``build`` runs one job into a location the caller holds the writer lease of; ``finish`` turns a
store whose every block has a journal entry into a complete store (shards of the small levels and
the index built from the journal, the journal deleted, ``complete: true`` written last).
``repair_store``, which recomputes only the blocks ``verify_store`` reports damaged, is in
:mod:`tiler.repair` (still importable from here).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import os
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import zarr
from zarr.core.sync import sync

from tiler.errors import (
    HeightRangeError,
    JobMismatchError,
    SchedulerError,
    SourceError,
    StoreCorruptError,
)
from tiler.grid import BlockGrid
from tiler.interrupt import DeferredInterrupt
from tiler.location import Location
from tiler.resume import (
    JOURNAL,
    JournalEntry,
    done_blocks,
    small_levels,
    unpack,
)
from tiler.run import progress_reporter, run_blocks
from tiler.schema import chunk_key, index_dtypes, shard_shape
from tiler.store import StoreMeta, read_meta, write_meta
from tiler.vertical import height_transform
from tiler.zarr_batch import open_arrays, read_all, write_all

log = logging.getLogger("tiler.tile")


def block_params(meta: StoreMeta) -> Any:
    """The ``BlockParams`` of a store's metadata."""
    from tiler.tile import BlockParams
    from tiler.vertical import height_transform

    a, b = height_transform(meta)
    rule = (meta.compressor or {}).get("sparse_byte_shuffle")
    return BlockParams(
        k=meta.k,
        dtype=meta.dtype,
        storage_dtype=meta.storage_dtype,
        nodata=meta.nodata,
        precision=meta.precision,
        error_cap=meta.error_cap,
        encoding=meta.encoding,
        z_scale=a,
        z_offset=b,
        sparse_byte=(float(rule["terrain_max"]), float(rule["slack"])) if rule else None,
    )


def build(
    src: str,
    loc: Location,
    meta: StoreMeta,
    opts: Any,
    progress: Callable | None,
    summary: Any,
    lease: Any,
    *,
    resume: bool,
) -> None:
    """Create (or resume) the store at ``loc`` and run it to completion."""
    from tiler.destination import create_store

    if resume:
        group = loc.open_group("r+")
        old = read_meta(group)
        meta = replace(meta, extra={k: v for k, v in old.extra.items() if k != "state"})
        n = loc.remove_partial_files()
        if n:
            log.info("removed %d leftover temporary file(s) of the interrupted run", n)
        summary.resumed = True
        if old.extra.get("state") == "finishing":  # shards and index are final already
            loc.delete_prefix(JOURNAL)  # (what is left of it)
            complete(group, meta)
            summary.blocks_total = summary.blocks_skipped = meta.grid.rows * meta.grid.cols
            return
    else:
        group = create_store(loc, meta, opts)
    grid = meta.grid
    asm = ShardAssembler(group, loc, meta, np.zeros(grid.shape, dtype=bool))
    # a store just created has an empty journal: nothing to read back
    done = _resume_journal(src, opts.band, meta, loc, asm) if resume else np.zeros(grid.shape, bool)
    todo = [b for b in grid.blocks() if not done[b]]
    total = grid.rows * grid.cols
    skipped = total - len(todo)
    if resume:
        log.info(
            "resuming: %d of %d block(s) already done, %d to compute", skipped, total, len(todo)
        )
    summary.blocks_total, summary.blocks_skipped, summary.blocks_computed = (
        total,
        skipped,
        len(todo),
    )
    report = progress_reporter(total, skipped, progress)
    report(0, 0)
    try:
        summary.executor = run_blocks(
            src, loc, opts, grid, block_params(meta), todo, done, report, lease, asm.blocks_done
        )
    except SchedulerError:
        if not resume and not done.any():  # (an unreachable scheduler: nothing was computed)
            loc.remove()  # leave no unfinished store that a rerun would be told to resume
        raise
    except HeightRangeError:
        # samples no rerun can tile: the source must change first, and the changed source is
        # another job; a store this run began is removed rather than left to be "resumed"
        if not resume:
            loc.remove()
        raise
    # a Ctrl-C during the final writes (zarr's synchronous calls: raised inside them it left
    # writes pending on zarr's loop) waits for them; once they are done the store is complete
    # and the run ends as finished
    with DeferredInterrupt(raise_on_exit=False) as late:
        try:
            finish(group, loc, meta, asm)
        except SourceError:
            loc.remove()  # an all-nodata source: leave nothing that looks like a store
            raise
    if late.interrupted:
        log.warning("Ctrl-C during the final writes: they were completed, the store is finished")


def _resume_journal(
    src: Any, band: int, meta: StoreMeta, loc: Any, asm: ShardAssembler
) -> np.ndarray:
    """Read a resumed store's journal once: the entries its listing shows
    (:func:`listed_journal_blocks`: the keys absent, the blocks not done, are not asked for), a
    shard's fetched together; where the store cannot list, every entry, a shard region at a
    time. Return the blocks done (an entry damaged, its crc32c failing: not done, computed
    again; a transport failure stops the resume, :class:`StoreUnavailableError`, rather than
    compute its blocks again) and hand their entries to ``asm``, made with no block done (a
    shard all done is written now). Refuse to resume when the source's samples of blocks
    already done changed since (a source edited in place passes the job's fingerprint: the
    same size, header and three sample windows), naming the blocks: the store would mix two
    DEMs."""
    from tiler.journal_reads import listed_journal_blocks, read_journal_blocks, read_journal_region
    from tiler.resume import changed_done_blocks
    from tiler.source import open_source

    done = np.zeros(meta.grid.shape, dtype=bool)
    changed: list[tuple[int, int]] = []
    listed = listed_journal_blocks(loc, asm.jarr, loc.url)
    by_shard: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for b in listed or ():
        by_shard.setdefault((b[0] // asm.sr, b[1] // asm.sc), []).append(b)
    with contextlib.ExitStack() as stack:
        ds = None
        for r0, r1, c0, c1 in asm.regions():
            if listed is None:  # (a store that cannot list: every entry of the region read)
                raw = read_journal_region(asm.jarr, r0, r1, c0, c1, loc.url)
            else:
                blocks = by_shard.get((r0 // asm.sr, c0 // asm.sc))
                if not blocks:
                    continue  # (no entry written: no block of it done)
                raw = np.zeros((r1 - r0, c1 - c0, asm.jarr.shape[2]), dtype=np.uint8)
                rows = read_journal_blocks(asm.jarr, blocks, loc.url)  # (damaged: left zero)
                for (br, bc), row in zip(blocks, rows, strict=True):
                    raw[br - r0, bc - c0] = row
            region = done[r0:r1, c0:c1]
            region[...] = raw[:, :, -1] == 1
            if not region.any():
                continue
            if ds is None:  # (opened once, and only when a block is done)
                ds = stack.enter_context(open_source(src, band))
            changed += changed_done_blocks(ds, band, meta.grid, raw, region, meta, (r0, c0))
            if not changed:  # (a refused resume hands nothing on)
                entries = {
                    (r0 + i, c0 + j): unpack(raw[i, j], meta.k, meta.storage_dtype)
                    for i, j in zip(*np.nonzero(region), strict=True)
                }
                # a shard all done is written now: a Ctrl-C waits for its writes (zarr's
                # synchronous calls, as in run_blocks and finish) and is raised after them
                with DeferredInterrupt():
                    asm.resumed((r0 // asm.sr, c0 // asm.sc), entries)
    if changed:
        raise source_changed_error(
            "{url!r} holds an unfinished store whose source changed since it was started: the "
            "samples of {n} block(s) already done differ ({shown}); rerun with the original "
            "source to finish it, or tile with {overwrite} to start again",
            loc,
            sorted(changed),
        )
    return done


def source_changed_error(template: str, loc: Any, changed: list) -> JobMismatchError:
    """The refusal ``template`` (``{url}``, ``{n}``, ``{shown}``, ``{overwrite}``) naming the
    first blocks of ``changed`` whose source samples differ from what was recorded."""
    shown = ", ".join(map(str, changed[:5])) + (", ..." if len(changed) > 5 else "")
    return JobMismatchError(
        template,
        params={"overwrite": "overwrite=True"},
        url=loc.url,
        n=len(changed),
        shown=shown,
    )


def _region_entries(
    jarr: zarr.Array,
    r0: int,
    r1: int,
    c0: int,
    c1: int,
    meta: StoreMeta,
    known: dict[tuple[int, int], JournalEntry] | None = None,
    url: str | None = None,
) -> dict[tuple[int, int], JournalEntry]:
    """The journal entries of blocks ``[r0:r1, c0:c1]``, all done; those of ``known`` (read
    already) are not read again. An entry damaged (its crc32c failing): :class:`StoreCorruptError`
    naming its block, and to rerun (resuming computes it again); a read the transport fails is
    tried again, then :class:`StoreUnavailableError` naming the store (``url``)."""
    from tiler.journal_reads import read_journal_blocks, read_journal_region

    known = known or {}
    blocks = [(br, bc) for br in range(r0, r1) for bc in range(c0, c1) if (br, bc) not in known]
    damaged: list[tuple[int, int]] = []
    if len(blocks) == (r1 - r0) * (c1 - c0):
        raw = read_journal_region(jarr, r0, r1, c0, c1, url, damaged).reshape(len(blocks), -1)
    else:  # (the chunks of these blocks only, fetched together)
        raw = read_journal_blocks(jarr, blocks, url, damaged)
    if damaged:
        shown = ", ".join(map(str, damaged[:5])) + (", ..." if len(damaged) > 5 else "")
        what = f"block {shown}" if len(damaged) == 1 else f"{len(damaged)} blocks ({shown})"
        raise StoreCorruptError(
            f"the journal entry of {what} of {url or str(jarr.store)!r}, written when the block "
            "was done, reads back damaged (its crc32c fails): the storage did not keep what "
            "was written. The store stays unfinished: rerun the same command to compute "
            f"{'it' if len(damaged) == 1 else 'them'} again (the other blocks done are kept); "
            "if it happens again, check the disk or bucket"
        )
    out = dict(known)
    for (br, bc), row in zip(blocks, raw, strict=True):
        e = unpack(row, meta.k, meta.storage_dtype)
        if e is None:
            raise StoreCorruptError(f"block ({br}, {bc}) has no journal entry")
        out[br, bc] = e
    return {b: out[b] for b in sorted(out)}


def _read_clean_blocks(
    arrays: list[zarr.Array], region: tuple[int, int, int, int], clean: list[tuple[int, int]]
) -> list[np.ndarray]:
    """The stored values of blocks ``clean`` (of shard ``region``) in each of ``arrays`` (one
    ``(len(clean), n)`` array each): each array's shard fetched whole, once, all arrays at once
    (one GET each on S3, where a read a block was two: the shard index, then the chunk), and
    only ``clean``'s chunks decoded (another block's may be damaged: it is being rebuilt)."""
    from zarr.core.buffer import default_buffer_prototype
    from zarr.storage import MemoryStore, StorePath

    r0, _, c0, _ = region
    rows, cols = (np.array(v, dtype=np.intp)[:, None] for v in zip(*clean, strict=True))

    async def one(arr: zarr.Array) -> np.ndarray:
        a = arr.async_array
        sr, sc = a.metadata.chunk_grid.chunk_shape[:2]  # (the shard's blocks)
        key = a.metadata.encode_chunk_key((r0 // sr, c0 // sc, 0))
        shard = await (a.store_path / key).get(prototype=default_buffer_prototype())
        copy = zarr.AsyncArray(metadata=a.metadata, store_path=StorePath(MemoryStore()))
        if shard is not None:  # (absent: every block reads as the fill value, as from the store)
            await copy.store_path.store.set(key, shard)
        return np.asarray(await copy.vindex.getitem((rows, cols, np.arange(a.shape[2])[None, :])))

    async def go() -> list[np.ndarray]:
        return list(await asyncio.gather(*(one(arr) for arr in arrays)))

    return sync(go())


def write_small_levels(
    loc: Location,
    meta: StoreMeta,
    entries: dict[tuple[int, int], JournalEntry],
    region: tuple[int, int, int, int],
) -> None:
    """Write the small levels of one shard region from journal entries (other blocks: kept,
    read back a level at a time: :func:`_read_clean_blocks`).

    The levels' arrays are opened, and their shards written, all at once
    (:mod:`tiler.zarr_batch`)."""
    r0, r1, c0, c1 = region
    names = [f"levels/{i}" for i in range(small_levels(meta.k))]
    arrays = open_arrays(loc, names)
    # repair: the blocks that are fine (they verified clean) are read back
    clean = [(br, bc) for br in range(r0, r1) for bc in range(c0, c1) if (br, bc) not in entries]
    kept = _read_clean_blocks(arrays, region, clean) if clean else [None] * len(arrays)
    writes = []
    for i, (arr, old) in enumerate(zip(arrays, kept, strict=True)):
        data = np.empty((r1 - r0, c1 - c0, arr.shape[2]), dtype=arr.dtype)
        if old is not None:
            for (br, bc), row in zip(clean, old, strict=True):
                data[br - r0, bc - c0] = row
        for (br, bc), e in entries.items():
            data[br - r0, bc - c0] = e.levels[i]
        writes.append((arr, (slice(r0, r1), slice(c0, c1)), data))
    # the region is one whole shard: drop the old one first, so a damaged shard index is never
    # read back for a partial update (the store is unfinished meanwhile: tiling or repair)
    for name in names:
        loc.delete_key(chunk_key(name, (r0, c0), *meta.grid.shape))
    write_all(writes)


class ShardAssembler:
    """Writes each shard of the small levels from the journal once all its blocks are done.

    Called from the tiling loop's thread, so shard writes overlap the workers' computing; it
    also gathers the index rows. Shards already complete when a run resumes are written by
    :meth:`finish_all`.
    """

    def __init__(self, group: zarr.Group, loc: Location, meta: StoreMeta, done: np.ndarray):
        self.loc, self.meta, self.jarr = loc, meta, group[JOURNAL]
        rows, cols = meta.grid.shape
        self.sr, self.sc = shard_shape(rows, cols)
        self.rows, self.cols = rows, cols
        self.remaining = {}
        for r0 in range(0, rows, self.sr):
            for c0 in range(0, cols, self.sc):
                region = done[r0 : r0 + self.sr, c0 : c0 + self.sc]
                self.remaining[r0 // self.sr, c0 // self.sc] = int((~region).sum())
        self.flushed: set[tuple[int, int]] = set()
        #: the entries of the blocks a resumed run found done, of shards not all done yet
        self.known: dict[tuple[int, int], dict[tuple[int, int], JournalEntry]] = {}
        self.index = {
            n: np.full((rows, cols), fv, dtype=dt) for n, (dt, fv) in index_dtypes(meta).items()
        }

    def regions(self) -> list[tuple[int, int, int, int]]:
        """Every shard's blocks ``(r0, r1, c0, c1)``, row-major."""
        return [
            (r0, min(r0 + self.sr, self.rows), c0, min(c0 + self.sc, self.cols))
            for r0 in range(0, self.rows, self.sr)
            for c0 in range(0, self.cols, self.sc)
        ]

    def resumed(self, s: tuple[int, int], entries: dict[tuple[int, int], JournalEntry]) -> None:
        """Take the entries of shard ``s``'s blocks done before a resume (counted as done):
        write the shard now if they are all of it, else keep them for when it is."""
        self.remaining[s] -= len(entries)
        if self.remaining[s] == 0:
            self.flush(s, entries)
        else:
            self.known[s] = entries

    def blocks_done(self, blocks: list[tuple[int, int]]) -> None:
        """Count finished blocks; write every shard that became complete."""
        touched = set()
        for br, bc in blocks:
            s = (br // self.sr, bc // self.sc)
            self.remaining[s] -= 1
            touched.add(s)
        for s in touched:
            if self.remaining[s] == 0 and s not in self.flushed:
                self.flush(s)

    def flush(
        self, s: tuple[int, int], known: dict[tuple[int, int], JournalEntry] | None = None
    ) -> None:
        """Write shard ``s`` of levels 0..5 and record its blocks' index rows (``known``, or
        those kept by :meth:`resumed`: entries read already)."""
        r0, c0 = s[0] * self.sr, s[1] * self.sc
        r1, c1 = min(r0 + self.sr, self.rows), min(c0 + self.sc, self.cols)
        known = known if known is not None else self.known.pop(s, None)
        entries = _region_entries(self.jarr, r0, r1, c0, c1, self.meta, known, self.loc.url)
        write_small_levels(self.loc, self.meta, entries, (r0, r1, c0, c1))
        for b, e in entries.items():
            put_index_row(self.index, b, e, self.meta)
        self.flushed.add(s)

    def finish_all(self) -> None:
        """Write every shard not written yet."""
        for s in self.remaining:
            if s not in self.flushed:
                self.flush(s)


def put_index_row(
    index: dict[str, np.ndarray], b: tuple[int, int], e: Any, meta: StoreMeta
) -> None:
    """Put journal entry ``e``'s index row into ``index`` at block ``b``."""
    for name in ("exists", "has_nodata", "zmin", "zmax", "digest"):
        index[name][b] = getattr(e, name)
    if "content" in index:
        if e.content is None:  # (a store keeping them is journaled with them)
            raise StoreCorruptError(f"the journal entry of block {b} has no content digest")
        index["content"][b] = e.content


def finish(
    group: zarr.Group, loc: Location, meta: StoreMeta, asm: ShardAssembler | None = None
) -> None:
    """Assemble shards and index from the journal, drop it, then mark the store complete."""
    grid = meta.grid
    if JOURNAL in group:
        if asm is None or any(asm.remaining.values()):
            done = done_blocks(group[JOURNAL], loc.url)
            if not done.all():
                missing = int((~done).sum())
                raise StoreCorruptError(
                    f"{missing} block(s) are not done; the store stays unfinished"
                )
            asm = asm or ShardAssembler(group, loc, meta, done)
        # (each shard's journal entries are checked again when it is written)
        asm.finish_all()
        index = asm.index
        index["done"][...] = True
        if not index["exists"].any():
            raise SourceError(
                f"{meta.source.get('path')!r} holds no terrain: every sample is nodata, NaN or "
                "masked; nothing was written"
            )
        write_index(loc, grid, index)
        write_meta(group, replace(meta, extra=dict(meta.extra, state="finishing")))
        loc.delete_prefix(JOURNAL)
        complete(group, meta, index)
        return
    complete(group, meta)


def write_index(loc: Location, grid: BlockGrid, index: dict[str, np.ndarray]) -> None:
    """Write the index arrays and the block windows (opened and written at once)."""
    win = np.zeros((grid.rows, grid.cols, 4), dtype=np.int32)
    for br, bc in grid.blocks():
        win[br, bc] = grid.block_window(br, bc)
    values = {**index, "window": win}
    arrays = open_arrays(loc, [f"index/{name}" for name in values])
    write_all([(arr, ..., v) for arr, v in zip(arrays, values.values(), strict=True)])


def _warn_type_minimum(meta: StoreMeta, lowest_m: float) -> None:
    """Warn when a signed integer DEM without a nodata value reaches its type's minimum
    (SRTM's voids are -32768): likely an undeclared nodata value, tiled as heights."""
    dtype = np.dtype(meta.dtype)
    if meta.nodata is not None or dtype.kind != "i" or not np.isfinite(lowest_m):
        return
    a, b = height_transform(meta)
    lowest = (lowest_m - b) / a
    if round(lowest) == np.iinfo(dtype).min:
        name = meta.source.get("name") or "the source"
        path = os.path.basename(str(meta.source.get("path") or "SRC").rstrip("/"))
        low = int(np.iinfo(dtype).min)
        log.warning(
            "%s reaches %d, the %s minimum, and declares no nodata value: its samples of %d "
            "are tiled as heights (%g m). If they mark voids, declare it (`gdal_edit.py "
            "-a_nodata %d %s`) and tile again with --overwrite",
            name, low, dtype.name, low, lowest_m, low, path,
        )  # fmt: skip


def complete(
    group: zarr.Group, meta: StoreMeta, index: dict[str, np.ndarray] | None = None
) -> None:
    """Write the source checksum and value range, and ``complete: true`` (last). ``index``:
    the index just written (else ``digest``, ``zmin`` and ``zmax`` are read from the store)."""
    if index is not None:
        digests, zmin, zmax = index["digest"], index["zmin"], index["zmax"]
    else:
        names = ["index/digest", "index/zmin", "index/zmax"]
        digests, zmin, zmax = read_all(Location(group.store), names)
    checksum = hashlib.blake2b(digests.astype("<u8").tobytes(), digest_size=16).hexdigest()
    source = dict(meta.source, checksum=f"blake2b-128:{checksum}")
    extra = {k: v for k, v in meta.extra.items() if k != "state"}
    extra["value_range"] = [float(np.nanmin(zmin)), float(np.nanmax(zmax))]
    _warn_type_minimum(meta, extra["value_range"][0])
    write_meta(group, replace(meta, source=source, complete=True, extra=extra))
    log.info("store complete: %s", group.store)


def __getattr__(name: str) -> Any:
    """``repair_store``, moved to :mod:`tiler.repair`, importable from here as before (looked
    up when asked for: :mod:`tiler.repair` imports this module)."""
    if name == "repair_store":
        from tiler.repair import repair_store

        return repair_store
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
