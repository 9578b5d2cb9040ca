"""Repairing a store: recompute only the blocks ``verify_store`` reports damaged.

``repair_store`` recomputes the damaged blocks from the source (refused when the source's samples
of them changed since: :func:`_check_repair_source`), writes their journal entries, then patches
their small levels and index rows into the store (:func:`_patch`) and marks it complete with a
new revision. A repair interrupted (state ``repair``) is finished by running it again: the blocks
its journal holds (:func:`_journal_entries`) are patched in, not recomputed.
"""

from __future__ import annotations

import contextlib
import logging
import uuid
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import zarr

from tiler.assemble import (
    block_params,
    complete,
    put_index_row,
    source_changed_error,
    write_index,
    write_small_levels,
)
from tiler.errors import StoreCorruptError
from tiler.location import Location
from tiler.resume import JOURNAL, JournalEntry, create_journal, unpack
from tiler.run import open_for_write, progress_reporter, run_blocks
from tiler.schema import expected_table, index_chunk, index_dtypes, shard_shape
from tiler.store import StoreMeta, read_meta, write_meta

log = logging.getLogger("tiler.tile")


def repair_store(
    src: str, loc: Location, opts: Any, job: dict, progress: Callable | None, summary: Any
) -> Any:
    """Recompute the blocks ``verify_store`` finds damaged, from ``src``; return the store."""
    from tiler.lease import WriterLease
    from tiler.resume import check_same_job, source_of
    from tiler.source import source_label
    from tiler.store import TerrainStore
    from tiler.verify import verify_store

    report = verify_store(loc)
    if report.unrepairable:
        raise StoreCorruptError(
            "{url!r} cannot be repaired ({why}); tile the DEM again with {overwrite}",
            params={"overwrite": "overwrite=True"},
            url=loc.url,
            why="; ".join(report.unrepairable),
        )
    with WriterLease(loc, opts.lease_timeout_s) as lease:
        group = loc.open_group("r+")
        meta = read_meta(group)
        old_job = dict(meta.extra.get("job") or {})
        check_same_job(
            loc.url,
            old_job,
            {
                **job,
                "compression_level": old_job.get("compression_level", job["compression_level"]),
            },
            repair=True,
            sources=(source_of(meta.source), source_of(source_label(src))),
        )
        # an interrupted repair (state "repair"): the blocks its journal holds were
        # recomputed (their big levels are written); they are patched in, not recomputed
        resuming = not meta.complete and meta.extra.get("state") == "repair"
        prior: dict[tuple[int, int], JournalEntry] = {}
        if resuming and JOURNAL in group:
            prior = _journal_entries(group[JOURNAL], meta, loc)
        bad = sorted(report.bad_blocks - prior.keys())
        damage = [p for p in report.problems if p.kind != "unfinished"]
        if damage and not bad and not prior and not report.bad_tables and not resuming:
            raise StoreCorruptError(
                "{url!r} is damaged in a way no block rebuild repairs ({why}); tile the DEM "
                "again with {overwrite}",
                params={"overwrite": "overwrite=True"},
                url=loc.url,
                why="; ".join(p.message for p in damage),
            )
        for name in report.bad_tables:
            open_for_write(loc, name)[...] = expected_table(name, meta.k)
        summary.blocks_total = meta.grid.rows * meta.grid.cols
        summary.blocks_repaired = len(bad) + len(prior)
        summary.blocks_computed = len(bad)
        summary.blocks_skipped = len(prior)
        if bad or resuming:
            where = getattr(src, "label", src)  # a MosaicSpec: its paths, not its repr
            if bad:
                _check_repair_source(src, opts.band, meta, group, bad, loc)
                log.warning("repairing %d damaged block(s) of %s from %s", len(bad), loc.url, where)
            if resuming:
                log.warning(
                    "finishing the interrupted repair of %s (%d block(s) recomputed before)",
                    loc.url, len(prior),
                )  # fmt: skip
            else:
                write_meta(
                    group, replace(meta, complete=False, extra=dict(meta.extra, state="repair"))
                )
            if bad and (not resuming or JOURNAL not in group):
                create_journal(group, *meta.grid.shape, meta.k, meta.storage_dtype)
            grid = meta.grid
            if bad:
                done = np.ones(grid.shape, bool)
                for b in bad:
                    done[b] = False
                report_fn = progress_reporter(len(bad), 0, progress)
                summary.executor = run_blocks(
                    src, loc, opts, grid, block_params(meta), bad, done, report_fn, lease
                )
            if bad or prior:
                _patch(group, loc, meta, bad, prior)
            loc.delete_prefix(JOURNAL)
            # a new revision: the root metadata changes, so remote readers that kept shard
            # indexes of the old blocks drop them (TerrainStore.check_unchanged)
            extra = {k: v for k, v in meta.extra.items() if k != "state"}
            complete(group, replace(meta, extra=dict(extra, revision=uuid.uuid4().hex)))
    store = TerrainStore(loc)
    store.tile_summary = summary
    return store


def _journal_entries(
    jarr: zarr.Array, meta: StoreMeta, loc: Location
) -> dict[tuple[int, int], JournalEntry]:
    """The entries an interrupted repair's journal holds, read once: those its listing shows
    (:func:`listed_journal_blocks`: the keys absent, most of them, are not asked for), a
    shard's fetched together; where the store cannot list, every entry, a shard region at a
    time. A damaged one: not held, its block repaired again if still bad; a transport
    failure: :class:`StoreUnavailableError`, the repair stopped to be rerun."""
    from tiler.journal_reads import listed_journal_blocks, read_journal_blocks, read_journal_region

    rows, cols = meta.grid.shape
    sr, sc = shard_shape(rows, cols)
    listed = listed_journal_blocks(loc, jarr, loc.url)
    found: list[tuple[tuple[int, int], np.ndarray]] = []
    if listed is not None:
        by_shard: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for b in listed:
            by_shard.setdefault((b[0] // sr, b[1] // sc), []).append(b)
        for blocks in by_shard.values():
            found += zip(blocks, read_journal_blocks(jarr, blocks, loc.url), strict=True)
    else:
        for r0 in range(0, rows, sr):
            for c0 in range(0, cols, sc):
                r1, c1 = min(r0 + sr, rows), min(c0 + sc, cols)
                raw = read_journal_region(jarr, r0, r1, c0, c1, loc.url)
                for i, j in zip(*np.nonzero(raw[:, :, -1] == 1), strict=True):
                    found.append(((r0 + int(i), c0 + int(j)), raw[i, j]))
    entries = {}
    for b, row in found:
        e = unpack(row, meta.k, meta.storage_dtype)
        if e is not None:  # (a damaged entry reads as zeros: not written)
            entries[b] = e
    return entries


def _patch(
    group: zarr.Group,
    loc: Location,
    meta: StoreMeta,
    bad: list[tuple[int, int]],
    known: dict[tuple[int, int], JournalEntry] | None = None,
) -> None:
    """Write the repaired blocks' small levels and index rows (other blocks kept): those of
    ``bad``, their journal entries read a shard at a time (their chunks fetched together), and
    those of ``known`` (entries read already)."""
    from tiler.journal_reads import read_journal_blocks

    grid = meta.grid
    rows, cols = grid.shape
    sr, sc = shard_shape(rows, cols)
    jarr = group[JOURNAL]
    by_shard: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for b in sorted(bad):
        by_shard.setdefault((b[0] // sr, b[1] // sc), []).append(b)
    read: dict[tuple[int, int], JournalEntry | None] = dict(known or {})
    for blocks in by_shard.values():
        raw = read_journal_blocks(jarr, blocks, loc.url)
        for b, row in zip(blocks, raw, strict=True):
            read[b] = unpack(row, meta.k, meta.storage_dtype)
    entries = {}
    for b in sorted(read):
        e = read[b]
        if e is None:
            raise StoreCorruptError(
                f"the journal entry of block {b} of {loc.url!r}, written by this repair, reads "
                "back missing or damaged: the storage did not keep what was written. The store "
                "stays in state 'repair': rerun the same command to finish it (an entry still "
                "missing then is computed again); if it happens again, check the disk or bucket"
            )
        entries[b] = e
    shards: dict[tuple[int, int], dict] = {}
    for b, e in entries.items():
        shards.setdefault((b[0] // sr, b[1] // sc), {})[b] = e
    for (s0, s1), ents in shards.items():
        r0, c0 = s0 * sr, s1 * sc
        write_small_levels(loc, meta, ents, (r0, min(r0 + sr, rows), c0, min(c0 + sc, cols)))
    index = {}
    ir, ic = index_chunk(rows, cols)
    for name, (dt, fv) in index_dtypes(meta).items():
        arr = group[f"index/{name}"]
        index[name] = np.full((rows, cols), fv, dtype=dt)
        for r0 in range(0, rows, ir):
            for c0 in range(0, cols, ic):
                sl = (slice(r0, r0 + ir), slice(c0, c0 + ic))
                with contextlib.suppress(ValueError, OSError, RuntimeError):
                    index[name][sl] = arr[sl]  # a damaged chunk's blocks are all repaired
    for b, e in entries.items():
        put_index_row(index, b, e, meta)
    index["done"][...] = True
    write_index(loc, grid, index)


def _check_repair_source(
    src: Any, band: int, meta: StoreMeta, group: zarr.Group, bad: list, loc: Any
) -> None:
    """Refuse a repair from a source whose samples of the bad blocks differ from what the
    store recorded (their ``index/digest``): the job's fingerprint lets a same-size edit
    through, and the repaired blocks would hold another DEM than the rest."""
    from tiler.resume import changed_blocks_by_index
    from tiler.source import open_source

    digests = np.zeros(meta.grid.shape, dtype=np.uint64)
    try:
        digests[...] = group["index/digest"][...]
    except (ValueError, OSError, RuntimeError, KeyError):
        return  # a damaged digest table: repaired itself, nothing to compare against
    with open_source(src, band) as ds:
        changed = changed_blocks_by_index(ds, band, meta.grid, digests, bad, meta)
    if changed:
        raise source_changed_error(
            "cannot repair {url!r} from this source: its samples of {n} damaged block(s) differ "
            "from what the store recorded ({shown}), so it changed since the store was tiled "
            "and the repaired blocks would hold another DEM; repair from the original source, "
            "or tile with {overwrite} to start again",
            loc,
            changed,
        )
