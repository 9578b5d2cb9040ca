"""Exact resume: the per-block journal and the job identity checked before a run continues.

Each worker writes a block's big levels, errors and mask, then the block's *journal entry* last:
one chunk (crc32c-checked) of the ``journal`` array holding the block's small levels (the sharded
levels 0..5) and its index row. A block is done exactly when its journal entry reads back
intact, so a run killed at any moment loses only the blocks in flight (an entry whose read the
store's transport fails is neither: read again, then the run stops, :func:`read_journal_region`).
When every block is done the finish step builds the shards and the index from the journal,
deletes the journal and marks the store complete; the result is byte-identical to an
uninterrupted run.

The run's state is ``meta.extra["state"]``: ``"layout"`` (arrays being created: a rerun starts
again), ``"tiling"`` (resumable), ``"finishing"`` (journal consumed: a rerun only finishes).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from dataclasses import astuple, dataclass, fields, replace
from typing import Any

import numpy as np
import zarr
from rasterio.windows import Window

from tiler.errors import JobMismatchError

# the journal's reading, moved to tiler.journal_reads: its names are importable from here too
# (a test setting JOURNAL_RETRY_WAIT_S sets it on tiler.journal_reads, where it is read)
from tiler.journal_reads import JOURNAL as JOURNAL
from tiler.journal_reads import JOURNAL_READ_RETRIES as JOURNAL_READ_RETRIES
from tiler.journal_reads import JOURNAL_RETRY_WAIT_S as JOURNAL_RETRY_WAIT_S
from tiler.journal_reads import done_blocks as done_blocks
from tiler.journal_reads import listed_journal_blocks as listed_journal_blocks
from tiler.journal_reads import read_journal_blocks as read_journal_blocks
from tiler.journal_reads import read_journal_region as read_journal_region
from tiler.layout import level_size
from tiler.meta import nodata_json
from tiler.schema import FORMAT_VERSION, SHARDED_LEVELS, WRITE_CONFIG, codecs

_ROW = np.dtype([("exists", "u1"), ("has_nodata", "u1"), ("zmin", "<f8"), ("zmax", "<f8"),
                 ("digest", "<u8"), ("content", "<u8"), ("mark", "u1")])  # fmt: skip
#: the row of a journal begun before content digests (resumed as it was begun)
_ROW_NO_CONTENT = np.dtype([("exists", "u1"), ("has_nodata", "u1"), ("zmin", "<f8"),
                            ("zmax", "<f8"), ("digest", "<u8"), ("mark", "u1")])  # fmt: skip


@dataclass(frozen=True)
class JournalEntry:
    """A block's small levels and index row."""

    levels: list[np.ndarray]
    exists: bool
    has_nodata: bool
    zmin: float
    zmax: float
    digest: int
    #: the block's :func:`tiler.content.content_digest` (None: a journal begun without them)
    content: int | None = None


def small_levels(k: int) -> int:
    """How many levels are sharded (and journaled): ``min(6, k + 1)``."""
    return min(SHARDED_LEVELS, k + 1)


def entry_nbytes(k: int, storage_dtype: str, content: bool = True) -> int:
    """Bytes of one journal entry (``content``: with the content digest, as journals are
    begun now)."""
    n = sum(level_size(i) for i in range(small_levels(k)))
    row = _ROW if content else _ROW_NO_CONTENT
    return n * np.dtype(storage_dtype).itemsize + row.itemsize


#: a store's ``state`` while a tiling run has not finished it (``tiler.tile``,
#: ``tiler.assemble``): rerunning the same command finishes it; ``repair`` is not one of them
TILING_STATES = ("layout", "tiling", "finishing")


def create_journal(group: zarr.Group, rows: int, cols: int, k: int, storage_dtype: str) -> None:
    """Create the (empty) journal array."""
    n = entry_nbytes(k, storage_dtype)
    group.create_array(
        JOURNAL,
        shape=(rows, cols, n),
        chunks=(1, 1, n),
        dtype="uint8",
        fill_value=0,
        compressors=codecs(FORMAT_VERSION, 5, 1),
        config=WRITE_CONFIG,
        chunk_key_encoding={"name": "default", "separator": "."},  # one flat directory
        overwrite=True,
    )


def pack(entry: JournalEntry, storage_dtype: str, content: bool = True) -> np.ndarray:
    """The entry as the bytes of one journal chunk (last byte 1 marks a written entry);
    ``content`` False: the row of a journal begun without content digests."""
    dt = np.dtype(storage_dtype).newbyteorder("<")
    parts = [np.ascontiguousarray(v, dtype=dt).view(np.uint8) for v in entry.levels]
    row = np.zeros(1, _ROW if content else _ROW_NO_CONTENT)
    row["exists"], row["has_nodata"] = entry.exists, entry.has_nodata
    row["zmin"], row["zmax"], row["digest"], row["mark"] = (
        entry.zmin,
        entry.zmax,
        entry.digest,
        1,
    )
    if content:
        row["content"] = entry.content or 0
    return np.concatenate([*parts, row.view(np.uint8)])


def unpack(raw: np.ndarray, k: int, storage_dtype: str) -> JournalEntry | None:
    """Inverse of :func:`pack`; None for an unwritten entry."""
    raw = np.asarray(raw, dtype=np.uint8)
    if raw[-1] != 1:
        return None
    dt = np.dtype(storage_dtype).newbyteorder("<")
    levels, off = [], 0
    for i in range(small_levels(k)):
        n = level_size(i) * dt.itemsize
        levels.append(raw[off : off + n].view(dt).astype(np.dtype(storage_dtype)))
        off += n
    content = raw.size - off == _ROW.itemsize
    row = raw[off:].view(_ROW if content else _ROW_NO_CONTENT)[0]
    return JournalEntry(
        levels=levels,
        exists=bool(row["exists"]),
        has_nodata=bool(row["has_nodata"]),
        zmin=float(row["zmin"]),
        zmax=float(row["zmax"]),
        digest=int(row["digest"]),
        content=int(row["content"]) if content else None,
    )


def block_digest(data: np.ndarray) -> int:
    """A block's source samples as a 64-bit digest (blake2b of the samples and their shape): the
    per-block digest of the index and the journal."""
    hasher = hashlib.blake2b(np.ascontiguousarray(data), digest_size=8)  # no copy of the window
    hasher.update(np.array(data.shape, np.int64).tobytes())
    return int.from_bytes(hasher.digest(), "little")


def changed_done_blocks(
    ds: Any,
    band: int,
    grid: Any,
    journal: np.ndarray,
    done: np.ndarray,
    meta: Any,
    origin: tuple[int, int] = (0, 0),
) -> list[tuple[int, int]]:
    """The done blocks of an unfinished store whose source samples no longer match their
    journal digest: the source was edited in place since (same size, same header, same three
    fingerprint windows), and resuming would mix two DEMs. Reads every done block's window
    again (no encoding: about the cost of reading them).

    ``journal``: the raw entries already read (:func:`read_journal_region`,
    :func:`read_journal_blocks`), those of the blocks from ``origin`` on, as ``done`` is."""
    from tiler.source import read_window

    dtype = np.dtype(meta.dtype)
    changed = []
    for i, j in zip(*(v.tolist() for v in np.nonzero(done)), strict=True):
        entry = unpack(journal[i, j], meta.k, meta.storage_dtype)
        if entry is None:
            continue
        br, bc = origin[0] + i, origin[1] + j
        data = np.asarray(read_window(ds, band, grid, br, bc), dtype=dtype)
        if block_digest(data) != entry.digest:
            changed.append((br, bc))
    return changed


def changed_blocks_by_index(
    ds: Any, band: int, grid: Any, digests: np.ndarray, blocks: list, meta: Any
) -> list[tuple[int, int]]:
    """Of ``blocks``, those whose source samples no longer match the store's recorded digest
    (``digests``: ``index/digest``, 0 where unknown): what a repair would rebuild from a
    source edited since the store was tiled (same size, header and fingerprint windows)."""
    from tiler.source import read_window

    dtype = np.dtype(meta.dtype)
    changed = []
    for br, bc in blocks:
        want = int(digests[br, bc])
        if want == 0:  # (a damaged index chunk, or a block never recorded: nothing to compare)
            continue
        data = np.asarray(read_window(ds, band, grid, br, bc), dtype=dtype)
        if block_digest(data) != want:
            changed.append((br, bc))
    return changed


def _masked_at(info: Any) -> int:
    """The position of ``masked`` among a ``SourceInfo``'s fields (those before it, the path
    aside, are the source's part of the fingerprint)."""
    return [f.name for f in fields(info)].index("masked")


class SourceFingerprint(str):
    """:func:`source_fingerprint`'s value: the hex digest a job compares, carrying ``parts``
    (:func:`source_parts`), which :func:`job_identity` stores beside it so that a differing
    fingerprint can be said file by file (None: a reader without a mosaic spec)."""

    parts: dict[str, Any] | None = None


def source_fingerprint(ds: Any, band: int) -> str:
    """blake2b-128 of the source's shape, dtype, georeferencing, nodata and three sample windows.

    Cheap (three reads of at most 256x256) yet it tells two different DEMs of the same size
    apart; the per-block digests of the finished store cover every sample. Of a mosaic reader
    (one with a ``spec``) it is a :class:`SourceFingerprint` whose ``parts`` say each source's
    share of it.
    """
    h = hashlib.blake2b(digest_size=16)
    spec = getattr(ds, "spec", None)  # a tiler.mosaic.MosaicReader: every source and the warp
    if spec is not None:
        # (``masked``, added later, only when True: an unmasked source keeps the fingerprint
        # of the stores tiled before it existed, so they still resume and repair; the fields
        # after it, how the samples are labelled, are not the data and are left out)
        parts = [
            (os.path.basename(s.path), *astuple(s)[1 : _masked_at(s)])
            + ((True,) if s.masked else ())
            for s in spec.sources
        ]
        h.update(repr((astuple(replace(spec, sources=())), parts)).encode())
    else:
        h.update(repr((ds.height, ds.width, ds.dtypes[band - 1], tuple(ds.transform)[:6])).encode())
        h.update(repr((ds.crs.to_wkt() if ds.crs else None, ds.nodatavals[band - 1])).encode())
    n = 256
    windows = []
    for r, c in ((0, 0), (ds.height // 2, ds.width // 2), (ds.height - 1, ds.width - 1)):
        r0, c0 = max(0, min(r, ds.height - n)), max(0, min(c, ds.width - n))
        win = Window(c0, r0, min(n, ds.width - c0), min(n, ds.height - r0))
        data = np.ascontiguousarray(ds.read(band, window=win))
        h.update(data.tobytes())
        windows.append((r0, c0, data))
    if spec is None:
        return h.hexdigest()
    out = SourceFingerprint(h.hexdigest())
    out.parts = source_parts(spec, windows)
    return out


def _digest(*values: Any) -> str:
    """A short (64-bit) hex digest of ``values``' repr."""
    return hashlib.blake2b(repr(values).encode(), digest_size=8).hexdigest()


def source_parts(spec: Any, windows: Sequence[tuple[int, int, np.ndarray]] = ()) -> dict[str, Any]:
    """Each source's share of the fingerprint, to name the one that changed: its file name,
    size, a digest of its own header and one of the fingerprint ``windows`` (``(row, col,
    samples)`` on the target grid) within its footprint; with a digest of the target grid,
    without which the samples do not compare. (No modification time: the store's metadata
    would differ between two tilings of the same files.)"""
    fps = [tuple(int(v) for v in s.footprint) for s in spec.sources]
    files = []
    for s, (fr0, fc0, fr1, fc1) in zip(spec.sources, fps, strict=True):
        cut = []
        for r0, c0, data in windows:
            h, w = data.shape
            ir0, ir1, ic0, ic1 = max(r0, fr0), min(r0 + h, fr1), max(c0, fc0), min(c0 + w, fc1)
            if ir0 < ir1 and ic0 < ic1:
                sub = data[ir0 - r0 : ir1 - r0, ic0 - c0 : ic1 - c0]
                cut.append((ir0, ic0, hashlib.blake2b(sub.tobytes(), digest_size=8).hexdigest()))
        own = astuple(replace(s, path="", size_bytes=None, footprint=(0, 0, 0, 0), hull=()))
        files.append(
            {
                "name": os.path.basename(s.path.rstrip("/")),
                "size": s.size_bytes,
                "header": _digest(own[: _masked_at(s) + 1]),
                "samples": _digest(cut) if cut else None,
            }
        )
    return {"grid": _digest(astuple(replace(spec, sources=())), fps), "files": files}


def job_identity(fingerprint: str, opts: Any, meta: Any) -> dict[str, Any]:
    """What must match for a rerun to continue an unfinished store."""
    return {
        "source_fingerprint": fingerprint,
        "height": meta.height,
        "width": meta.width,
        "dtype": meta.dtype,
        "nodata": nodata_json(meta.nodata),
        "block_size": meta.block_size,
        "band": opts.band,
        "precision": meta.precision,
        "error_cap": meta.error_cap,
        "compression_level": opts.compression_level,
        "encoding": meta.encoding,
        "format_version": meta.format_version,
        # the reprojection asked for (its effect is also in the fingerprint, which names no
        # option): a rerun with another is refused naming it
        **_reprojection_items(opts),
        # (not compared: they say which source a differing fingerprint comes from)
        **({SOURCE_PARTS: fingerprint.parts} if getattr(fingerprint, "parts", None) else {}),
    }


def _reprojection_items(opts: Any) -> dict[str, Any]:
    """``dst_crs``, ``resampling`` and ``resolution`` as a job compares them: spelled one way
    (``"auto"``, ``EPSG:n`` or a PROJ string; lower-case; a float), JSON values (a CRS object
    given is named, not stored); all None without a target CRS."""
    from tiler.crs import AUTO, crs_name, parse_dst_crs

    dst = getattr(opts, "dst_crs", None)
    if dst is None:
        return {"dst_crs": None, "resampling": None, "resolution": None}
    parsed = parse_dst_crs(dst)
    res = getattr(opts, "resolution", None)
    return {
        "dst_crs": AUTO if parsed == AUTO else crs_name(parsed),
        "resampling": str(getattr(opts, "resampling", "") or "").lower() or None,
        "resolution": None if res is None else float(res),
    }


#: job items added after stores were begun without them: absent from a store's job, they match
_LATER_ITEMS = ("dst_crs", "resampling", "resolution")
#: the job item holding :func:`source_parts` (a store begun before it has none)
SOURCE_PARTS = "source_parts"
#: job items not compared one by one: the fingerprint, and what explains a differing one
_EXPLAINED = ("source_fingerprint", SOURCE_PARTS)


def source_of(label: dict | None) -> str | None:
    """A store metadata's ``source`` entry as :func:`check_same_job` names it: the path, or
    the mosaic's name (its first file and how many more)."""
    if not label:
        return None
    return label.get("name") if label.get("paths") else label.get("path")


def _source_diff(was: Any, now: Any) -> str:
    """The differing source, by name when they are known (its fingerprint after)."""
    if was and now and str(was) != str(now):
        return f"source: store was tiled from {str(was)!r}, this run reads {str(now)!r}"
    if was or now:
        name = str(was or now)
        return (
            f"source: {name!r} is not the file the store was tiled from as it was then (its "
            "size, georeferencing, nodata or samples differ: edited or replaced since?)"
        )
    return "source: another file, or the same one changed (its fingerprint differs)"


def source_change(was: dict[str, Any], now: dict[str, Any], samples: bool = True) -> str | None:
    """What differs between two :func:`source_parts` file entries of the same file: its size,
    its header, its samples (``samples``: they compare, the target grid being the same); None
    when nothing tells them apart."""
    what = []
    if was.get("size") is not None and now.get("size") is not None and was["size"] != now["size"]:
        what.append(f"its size ({was['size']} bytes then, {now['size']} now)")
    if was.get("header") != now.get("header"):
        what.append("its header (dimensions, georeferencing, data type, nodata or mask)")
    elif samples and was.get("samples") != now.get("samples"):
        what.append("its samples")
    if not what:
        return None
    plural = len(what) > 1 or what == ["its samples"]
    return " and ".join(what) + (" differ" if plural else " differs")


def _changed_sources(was: Any, now: Any) -> str | None:
    """The sources that differ between a store's job and this run's, file by file, from their
    :func:`source_parts` (None: a store begun without them, or nothing they tell)."""
    if not isinstance(was, dict) or not isinstance(now, dict):
        return None
    old, new = was.get("files") or [], now.get("files") or []
    if not old or not new:
        return None
    names = [f.get("name") for f in old], [f.get("name") for f in new]
    n = len(new)
    if names[0] != names[1]:
        if len(old) == n == 1:
            return None  # (the store's and this run's labels name both files in full)
        if len(old) != n:
            shown = [
                ", ".join(repr(x) for x in v[:5]) + (", ..." if len(v) > 5 else "") for v in names
            ]
            return (
                f"sources: store was tiled from {len(old)} ({shown[0]}), this run reads {n} "
                f"({shown[1]})"
            )
        swapped = [
            f"source {i + 1} of {n}: store was tiled from {a!r}, this run reads {b!r}"
            for i, (a, b) in enumerate(zip(*names, strict=True))
            if a != b
        ]
        return "; ".join(swapped)
    grid = was.get("grid") is not None and was.get("grid") == now.get("grid")
    changed = []
    for i, (a, b) in enumerate(zip(old, new, strict=True)):
        why = source_change(a, b, samples=grid)
        if why is not None:
            which = f" (source {i + 1} of {n})" if n > 1 else ""
            changed.append(
                f"source: {b.get('name')!r}{which} is not the file the store was tiled from "
                f"as it was then: {why}"
            )
    return "; ".join(changed) or None


def check_same_job(
    url: str,
    old: dict[str, Any] | None,
    new: dict[str, Any],
    *,
    repair: bool = False,
    sources: tuple[Any, Any] = (None, None),
) -> None:
    """Raise JobMismatchError naming every differing item and both of its values (``repair``:
    the store is a finished one being repaired, not an unfinished one being resumed;
    ``sources``: the store's and this run's source names, said beside a differing
    fingerprint, which alone names no file)."""
    store = "a store" if repair else "an unfinished store"
    then = "repair it" if repair else "finish it"
    if old is None:
        raise JobMismatchError(
            "{url!r} holds {store} from an older terrastream (no job identity); it cannot be "
            "{done}: remove it or tile with {overwrite} to start again.",
            params={"overwrite": "overwrite=True"},
            url=url,
            store=store,
            done="repaired" if repair else "resumed",
        )
    diffs = [
        f"{key}: store has {old.get(key)!r}, this run has {value!r}"
        for key, value in new.items()
        if old.get(key) != value
        and key not in _EXPLAINED
        and (key in old or key not in _LATER_ITEMS)
    ]
    warp = any(d.split(":")[0] in _LATER_ITEMS for d in diffs)  # (it explains the samples)
    if old.get("source_fingerprint") != new.get("source_fingerprint") and not warp:
        was, now = sources
        which = _changed_sources(old.get(SOURCE_PARTS), new.get(SOURCE_PARTS))
        diffs.insert(0, which or _source_diff(was, now))
    if diffs:
        raise JobMismatchError(
            "{url!r} holds {store} of another job ({diffs}); rerun with the original source "
            "and settings to {then}, or tile with {overwrite} to start again.",
            params={"overwrite": "overwrite=True"},
            url=url,
            store=store,
            diffs="; ".join(diffs),
            then=then,
        )
