"""``verify_store``: read every chunk of a store and report each damaged or missing block.

Checks, in order: the root metadata; every array's presence, shape and dtype; every chunk of the
index, the levels, the errors and the masks of blocks with nodata (crc32c in format 2, and
missing chunks, which zarr would otherwise return as fill values); the ``level_index`` and
``order_index`` tables against their definition; the source checksum against the block digests;
and, with ``source``, every block's digest recomputed from the source raster.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zarr

from tiler.array_check import array_problem
from tiler.content import (
    CONTENT_KEY,
    ERRORS_DTYPE,
    FOLD_SEED,
    content_digest,
    fold,
    part_digest,
)
from tiler.errors import StoreChangedError, StoreError
from tiler.layout import level_size
from tiler.lease import live_writer
from tiler.location import Location, as_location
from tiler.meta import CHECKSUM_KEY
from tiler.resume import SOURCE_PARTS, TILING_STATES, source_change, source_parts
from tiler.schema import (
    ATTR,
    INDEX_NAMES,
    SHARDED_LEVELS,
    chunk_key,
    expected_table,
    index_chunk,
    level_fill,
    shard_shape,
)
from tiler.store import StoreMeta, read_meta
from tiler.transport import is_transport_error, unavailable

_READ_ERRORS = (ValueError, OSError, RuntimeError, KeyError)


@dataclass(frozen=True)
class Problem:
    """One finding: ``kind`` is checksum, missing, mismatch, metadata or source."""

    kind: str
    array: str
    block: tuple[int, int] | None
    level: int | None
    message: str


@dataclass
class VerifyReport:
    """The result of :func:`verify_store`; ``ok`` is True when nothing was found."""

    location: str
    format_version: int | None = None
    checksummed: bool = False
    #: the root metadata carries its own checksum (and matched it: else it is a problem)
    metadata_checksummed: bool = False
    complete: bool = False
    chunks_checked: int = 0
    blocks_total: int = 0
    source_checked: bool = False
    #: every block's content digest was recomputed (stores tiled before them have none)
    content_checked: bool = False
    problems: list[Problem] = field(default_factory=list)
    bad_blocks: set[tuple[int, int]] = field(default_factory=set)
    bad_tables: list[str] = field(default_factory=list)
    unrepairable: list[str] = field(default_factory=list)
    #: the store's state while unfinished (``layout``, ``tiling``, ``finishing``, ``repair``)
    state: str | None = None
    #: who is writing the unfinished store now (a live writer lease), None if nobody is
    writer: str | None = None

    @property
    def unfinished(self) -> bool:
        """An interrupted tiling (not a repair): rerunning the same ``tile`` finishes it."""
        return self.state in TILING_STATES

    @property
    def ok(self) -> bool:
        """True when no problem was found."""
        return not self.problems

    def add(self, kind: str, array: str, block: Any, level: int | None, msg: str) -> None:
        """Record a problem (and its block as bad)."""
        b = None if block is None else (int(block[0]), int(block[1]))
        self.problems.append(Problem(kind, array, b, level, msg))
        if b is not None:
            self.bad_blocks.add(b)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (blocks as lists)."""
        return {
            "location": self.location,
            "ok": self.ok,
            "format_version": self.format_version,
            "checksummed": self.checksummed,
            "metadata_checksummed": self.metadata_checksummed,
            "complete": self.complete,
            "state": self.state,
            "writer": self.writer,
            "chunks_checked": self.chunks_checked,
            "blocks_total": self.blocks_total,
            "source_checked": self.source_checked,
            "content_checked": self.content_checked,
            "bad_blocks": sorted([list(b) for b in self.bad_blocks]),
            "bad_tables": self.bad_tables,
            "unrepairable": self.unrepairable,
            "problems": [
                {
                    "kind": p.kind,
                    "array": p.array,
                    "block": None if p.block is None else list(p.block),
                    "level": p.level,
                    "message": p.message,
                }
                for p in self.problems
            ],
        }


def verify_store(
    location: str | os.PathLike | Location | Any,
    *,
    source: str | os.PathLike | list[str | os.PathLike] | None = None,
) -> VerifyReport:
    """Check every chunk and the metadata of a store (and, given ``source`` — one DEM or the
    mosaic's list — the block digests, read with the store's band and reprojection)."""
    loc = as_location(location)
    rep = VerifyReport(location=loc.url)
    try:
        group = loc.open_group("r")
        meta = read_meta(group)
    except Exception as exc:
        if is_transport_error(exc):
            raise unavailable("the root metadata (verify concluded nothing)", loc.url, exc) from exc
        if not isinstance(exc, StoreError | FileNotFoundError | ValueError | KeyError):
            raise
        rep.add("metadata", "", None, None, f"root metadata unreadable: {exc}")
        rep.unrepairable.append(f"root metadata unreadable: {exc}")
        return rep
    rep.format_version, rep.checksummed, rep.complete = (
        meta.format_version,
        meta.checksummed,
        meta.complete,
    )
    rep.metadata_checksummed = CHECKSUM_KEY in (group.attrs.get(ATTR) or {})
    grid = meta.grid
    rows, cols = grid.shape
    rep.blocks_total = rows * cols
    if not meta.complete:
        rep.state = str(meta.extra.get("state") or "tiling")
    if rep.state == "repair":  # (its chunks are checked below: a repair rewrites few)
        rep.add(
            "unfinished",
            "",
            None,
            None,
            "the store's repair was interrupted (state 'repair'); rerun `terrastream tile SRC "
            f"{loc.url} --repair` to finish it",
        )
    if rep.unfinished:  # its written chunks are still checked below, its missing ones not
        writer = rep.writer = live_writer(loc)
        rep.add(
            "unfinished",
            "",
            None,
            None,
            f"the store is unfinished (state {rep.state!r}): it is being written now by "
            f"{writer}; verify it once that tiling finishes"
            if writer is not None
            else f"the store is unfinished (state {rep.state!r}: an interrupted tiling); rerun "
            "the same `terrastream tile` command to finish it",
        )
    arrays = _open_arrays(group, meta, rep)
    idx = _check_index(arrays, loc, meta, rep)
    parts = Parts(meta)
    for i in range(meta.levels):
        if f"levels/{i}" in arrays:
            _check_level(arrays[f"levels/{i}"], i, loc, meta, rep, parts)
    if "errors" in arrays:
        _check_blocks(arrays["errors"], "errors", loc, meta, rep, grid.blocks(), parts=parts)
    if "mask" in arrays and "has_nodata" in idx:
        need = [b for b in grid.blocks() if idx["has_nodata"][b]]
        _check_blocks(arrays["mask"], "mask", loc, meta, rep, need, has_nodata=True, parts=parts)
    if meta.extra.get(CONTENT_KEY) and not rep.unfinished and "has_nodata" in idx:
        parts.no_masks(idx["has_nodata"])
        _check_content(meta, idx, parts, rep)
    for name in ("level_index", "order_index"):
        if name not in arrays:
            continue
        rep.chunks_checked += 1
        try:
            ok = np.array_equal(arrays[name][...], expected_table(name, meta.k))
        except Exception as exc:
            ok, why = False, str(_damage(exc, f"table {name!r}", rep))
        else:
            why = "content differs from its definition"
        if not ok:
            rep.add("mismatch", name, None, None, f"table {name!r} is damaged: {why}")
            rep.bad_tables.append(name)
    if "digest" in idx and meta.complete:
        checksum = hashlib.blake2b(idx["digest"].astype("<u8").tobytes(), digest_size=16)
        want = meta.source.get("checksum")
        if want and want != f"blake2b-128:{checksum.hexdigest()}":
            rep.add(
                "metadata",
                "index/digest",
                None,
                None,
                "the source checksum in the metadata does not match the block digests",
            )
    if source is not None and "digest" in idx:
        paths = [str(source)] if isinstance(source, str | os.PathLike) else [str(p) for p in source]
        _check_source(paths, meta, idx["digest"], rep)
    _check_same_store(loc, meta)
    return rep


def _check_same_store(loc: Location, meta: StoreMeta) -> None:
    """Raise :class:`StoreChangedError` if the store was replaced while it was verified (its
    chunks could then come from two builds, each passing its checksum)."""
    try:
        now = read_meta(loc.open_group("r")).generation
    except Exception as exc:
        if is_transport_error(exc):
            raise unavailable("the root metadata (verify concluded nothing)", loc.url, exc) from exc
        if not isinstance(exc, StoreError | FileNotFoundError | ValueError | KeyError):
            raise
        now = None
    if now != meta.generation:
        raise StoreChangedError(
            f"store {loc.url!r} was replaced or rewritten while it was verified (generation "
            f"{meta.generation!r} -> {now!r}); verify it again"
        )


def _open_arrays(group: Any, meta: StoreMeta, rep: VerifyReport) -> dict[str, Any]:
    rows, cols = meta.grid.shape
    side = meta.block_size
    want: dict[str, tuple] = {
        f"levels/{i}": (rows, cols, level_size(i)) for i in range(meta.levels)
    }
    want["errors"] = None  # type: ignore[assignment]
    want["mask"] = (rows, cols, side, side)
    for n in _index_names(meta):
        want[f"index/{n}"] = (rows, cols, 4) if n == "window" else (rows, cols)
    want["level_index"] = want["order_index"] = (side, side)
    for name in ("levels", "index"):  # (xarray.open_zarr(store, group="levels") needs them)
        try:
            ok = isinstance(group[name], zarr.Group)
            exc: Exception | None = None
        except Exception as e:
            _damage(e, f"the metadata of group {name!r}", rep)
            ok, exc = False, e
        if not ok:
            msg = f"group {name!r} is missing or its metadata is damaged" + (
                f": {exc}" if exc is not None else " (it is not a group)"
            )
            rep.add("metadata", name, None, None, msg)
            rep.unrepairable.append(msg)
    out = {}
    for name, shape in want.items():
        try:
            arr = group[name]
        except Exception as exc:
            _damage(exc, f"the metadata of array {name!r}", rep)
            msg = f"array {name!r} is missing or its metadata is damaged: {exc}"
            rep.add("metadata", name, None, None, msg)
            rep.unrepairable.append(msg)
            continue
        if shape is not None and tuple(arr.shape) != shape:
            msg = f"array {name!r} has shape {tuple(arr.shape)}, expected {shape}"
            rep.add("metadata", name, None, None, msg)
            rep.unrepairable.append(msg)
            continue
        why = array_problem(name, arr.metadata.to_dict(), meta) if meta.checksummed else None
        if why is not None:  # (zarr would decode it, wrongly: nothing read from it is checked)
            msg = f"array {name!r} has metadata no terrastream store has ({why})"
            rep.add("metadata", name, None, None, msg)
            rep.unrepairable.append(msg)
            continue
        out[name] = arr
    return out


def _check_index(arrays: dict, loc: Location, meta: StoreMeta, rep: VerifyReport) -> dict:
    rows, cols = meta.grid.shape
    ir, ic = index_chunk(rows, cols)
    out = {}
    for n in _index_names(meta):
        arr = arrays.get(f"index/{n}")
        if arr is None:
            continue
        vals = None
        for r0 in range(0, rows, ir):
            for c0 in range(0, cols, ic):
                rep.chunks_checked += 1
                sl = (slice(r0, r0 + ir), slice(c0, c0 + ic))
                blocks = [
                    (r, c)
                    for r in range(r0, min(r0 + ir, rows))
                    for c in range(c0, min(c0 + ic, cols))
                ]
                key = chunk_key(f"index/{n}", (r0, c0), rows, cols)
                try:
                    part = arr[sl]
                except Exception as exc:
                    _damage(exc, f"chunk {key!r}", rep)
                    _bad_all(rep, "checksum", f"index/{n}", blocks, f"chunk {key!r}: {exc}")
                    continue
                if meta.checksummed and meta.complete and not loc.key_exists(key):
                    _bad_all(rep, "missing", f"index/{n}", blocks, f"chunk {key!r} is missing")
                    continue
                if vals is None:
                    vals = np.empty(arr.shape, dtype=arr.dtype)
                vals[sl] = part
        if vals is not None:
            out[n] = vals
    if meta.complete and "done" in out:
        for b in zip(*np.nonzero(~out["done"]), strict=True):
            rep.add("mismatch", "index/done", b, None, f"block {b} is not marked done")
    if "window" in out and (meta.complete or meta.extra.get("state") == "repair"):
        grid = meta.grid  # (an unfinished tiling writes the index when it finishes)
        for b in grid.blocks():
            if tuple(out["window"][b]) != grid.block_window(*b):
                rep.add("mismatch", "index/window", b, None, f"block {b} has a wrong window")
    return out


def _damage(exc: Exception, subject: str, rep: VerifyReport) -> Exception:
    """``exc``, a read failure to report as damage; a failure of the server or the network is
    raised instead (verify cannot conclude anything from it), and anything else re-raised."""
    if is_transport_error(exc):
        raise unavailable(
            f"{subject} (verify stopped: nothing was concluded about the store)", rep.location, exc
        ) from exc
    if not isinstance(exc, _READ_ERRORS):
        raise exc
    return exc


def _bad_all(rep: VerifyReport, kind: str, array: str, blocks: list, msg: str) -> None:
    rep.problems.append(Problem(kind, array, None, None, f"{array}: {msg}"))
    rep.bad_blocks.update(blocks)


def _index_names(meta: StoreMeta) -> tuple[str, ...]:
    """The index arrays ``meta``'s store has (``content`` when it keeps content digests)."""
    return (*INDEX_NAMES, "content") if meta.extra.get(CONTENT_KEY) else INDEX_NAMES


class Parts:
    """The running fold (:func:`tiler.content.fold`) of the part digests of every block's
    stored arrays as they are read — levels 0..k, then errors, then mask (0: not stored) —
    one uint64 and a count a block, for :func:`_check_content`."""

    def __init__(self, meta: StoreMeta) -> None:
        rows, cols = meta.grid.shape
        self.n = meta.levels + 2
        self.acc = np.full((rows, cols), FOLD_SEED, np.uint64)
        self.count = np.zeros((rows, cols), np.uint8 if self.n < 256 else np.uint16)
        self.dtypes = [np.dtype(meta.storage_dtype)] * meta.levels + [ERRORS_DTYPE, np.bool_]

    def add(self, b: tuple[int, int], i: int, v: np.ndarray | None) -> None:
        """Fold part ``i`` (a level, ``-2`` errors, ``-1`` mask; ``v`` None: not stored) of
        block ``b`` in (in the order the parts are read: levels, errors, mask)."""
        part = part_digest(v, self.dtypes[i])
        self.acc[b] = np.uint64(fold(int(self.acc[b]), part))
        self.count[b] += 1

    def no_masks(self, has_nodata: np.ndarray) -> None:
        """Fold the mask part (0) of every block without nodata (their masks are not read)."""
        for b in zip(*np.nonzero(~has_nodata), strict=True):
            self.add((int(b[0]), int(b[1])), -1, None)

    def complete(self, b: tuple[int, int]) -> bool:
        """Every part of ``b`` was read."""
        return int(self.count[b]) == self.n


def _check_content(meta: StoreMeta, idx: dict, parts: Parts, rep: VerifyReport) -> None:
    """Compare every block's content digest, recomputed from the chunks read and its index
    row, with ``index/content``: a chunk moved to another block or copied from another store
    passes its crc32c but not this."""
    need = ("content", "exists", "has_nodata", "zmin", "zmax", "digest")
    if not all(n in idx for n in need):
        return  # (an index array already reported)
    rep.content_checked = True
    for b in meta.grid.blocks():
        if b in rep.bad_blocks or not parts.complete(b):
            continue
        got = content_digest(b, int(parts.acc[b]), idx["exists"][b],
                             idx["has_nodata"][b], idx["zmin"][b], idx["zmax"][b],
                             idx["digest"][b])  # fmt: skip
        if got != int(idx["content"][b]):
            rep.add(
                "mismatch",
                "index/content",
                b,
                None,
                "its chunks or its index row are not the ones tiled for it (a valid chunk "
                "moved from another block or copied from another store, or an index value "
                "changed): its content digest differs",
            )


def _check_level(
    arr: Any, level: int, loc: Location, meta: StoreMeta, rep: VerifyReport, parts: Parts
) -> None:
    rows, cols = meta.grid.shape
    if level >= SHARDED_LEVELS:
        blocks = meta.grid.blocks()
        _check_blocks(arr, f"levels/{level}", loc, meta, rep, blocks, level=level, parts=parts)
        return
    sr, sc = shard_shape(rows, cols)
    fill = level_fill(meta.storage_dtype)
    for r0 in range(0, rows, sr):
        for c0 in range(0, cols, sc):
            r1, c1 = min(r0 + sr, rows), min(c0 + sc, cols)
            rep.chunks_checked += 1
            try:
                region = arr[r0:r1, c0:c1]
            except Exception as exc:
                _damage(exc, f"level {level} of blocks {(r0, c0)}..{(r1 - 1, c1 - 1)}", rep)
                region = None  # read block by block below, to name the damaged ones
            for br in range(r0, r1):
                for bc in range(c0, c1):
                    if region is None:
                        try:
                            v = arr[br, bc]
                        except Exception as exc:
                            _damage(exc, f"level {level} of block {(br, bc)}", rep)
                            rep.add(
                                "checksum",
                                f"levels/{level}",
                                (br, bc),
                                level,
                                f"level {level} of block {(br, bc)}: {exc}",
                            )
                            continue
                    else:
                        v = region[br - r0, bc - c0]
                    parts.add((br, bc), level, v)
                    if meta.checksummed and not rep.unfinished and np.all(v == fill):
                        rep.add(
                            "missing",
                            f"levels/{level}",
                            (br, bc),
                            level,
                            f"level {level} of block {(br, bc)} is missing",
                        )


def _check_blocks(
    arr: Any,
    name: str,
    loc: Location,
    meta: StoreMeta,
    rep: VerifyReport,
    blocks: list,
    level: int | None = None,
    has_nodata: bool = False,
    parts: Parts | None = None,
) -> None:
    rows, cols = meta.grid.shape
    part = level if level is not None else (-1 if name == "mask" else -2)
    fill = level_fill(meta.storage_dtype) if name.startswith("levels/") else None
    what = f"level {level}" if level is not None else name
    for b in blocks:
        rep.chunks_checked += 1
        try:
            v = arr[b]
        except Exception as exc:
            _damage(exc, f"{what} of block {b}", rep)
            rep.add("checksum", name, b, level, f"{what} of block {b}: {exc}")
            continue
        if parts is not None:
            parts.add(b, part, v)
        if (not meta.checksummed and not has_nodata) or rep.unfinished:
            continue  # (an unfinished tiling lacks what its rerun writes: not damage)
        if fill is not None:
            suspect = bool(np.all(v == fill))
        elif name == "errors":
            suspect = bool(np.all(np.isnan(v)))
        else:
            suspect = bool(v.all())  # a mask of a block with nodata has a False somewhere
        if suspect and (has_nodata or not loc.key_exists(chunk_key(name, b, rows, cols))):
            rep.add("missing", name, b, level, f"{what} of block {b} is missing")


def source_plan(paths: list[str], meta: StoreMeta) -> Any:
    """The :class:`~tiler.mosaic.MosaicSpec` of ``paths`` as ``meta``'s store was tiled from
    them: the job's band and, for a reprojected store, its CRS, resolution and resampling."""
    from tiler.mosaic import plan_mosaic

    band = int((meta.extra.get("job") or {}).get("band") or 1)
    rp = meta.extra.get("reprojection")
    if not rp:
        return plan_mosaic(paths, band=band)
    res = rp.get("resolution")
    return plan_mosaic(
        paths,
        band=band,
        dst_crs=meta.crs_wkt,
        resolution=(float(res[0]), float(res[1])) if res else None,
        resampling=str(rp.get("resampling") or "bilinear"),
    )


def _same_grid(spec: Any, meta: StoreMeta) -> str | None:
    """Why ``spec``'s grid is not the store's (size, then geotransform), or None."""
    if (spec.height, spec.width) != (meta.height, meta.width):
        return f"{spec.height}x{spec.width} samples, the store {meta.height}x{meta.width}"
    a, b = np.asarray(spec.transform, float), np.asarray(meta.geotransform, float)[:6]
    if not np.allclose(a, b, rtol=1e-9, atol=1e-9 * max(1.0, float(np.abs(a[:2]).max()))):
        return f"geotransform {tuple(a.tolist())}, the store {tuple(b.tolist())}"
    return None


def _changed_sources(meta: StoreMeta, spec: Any) -> list[str | None]:
    """Per source of ``spec``: how it differs from the file of the same name the store was
    tiled from (size or header, from the job's :func:`~tiler.resume.source_parts`), or None
    (the same, or not known: a store tiled before them, or other files)."""
    old = ((meta.extra.get("job") or {}).get(SOURCE_PARTS) or {}).get("files") or []
    new = source_parts(spec)["files"]
    if [f.get("name") for f in old] != [f["name"] for f in new]:
        return [None] * len(new)
    return [source_change(a, b, samples=False) for a, b in zip(old, new, strict=True)]


def _block_sources(ds: Any, grid: Any, b: tuple[int, int], changed: list[str | None]) -> str:
    """Which sources block ``b``'s samples come from, for its message: of a mosaic, the files
    whose footprint meets it, and of those any known to have changed since the tiling."""
    n = len(ds.spec.sources)
    hits = ds.sources_for(*grid.block_window(*b))
    known = [i for i in hits if changed[i] is not None]
    name = [repr(os.path.basename(s.path.rstrip("/"))) for s in ds.spec.sources]
    if known:
        return "; " + "; ".join(
            f"{name[i]}{f' (source {i + 1} of {n})' if n > 1 else ''}, which the block's "
            f"samples come from, is not the file the store was tiled from: {changed[i]}"
            for i in known
        )
    if n == 1 or not hits:
        return ""
    shown = [name[i] for i in hits[:3]] + ([f"{len(hits) - 3} more"] if len(hits) > 3 else [])
    return f" (its samples come from {' or '.join(shown)})"


def _check_source(
    paths: list[str], meta: StoreMeta, digests: np.ndarray, rep: VerifyReport
) -> None:
    from tiler.mosaic import MosaicReader
    from tiler.source import read_window

    rep.source_checked = True
    grid = meta.grid
    src = paths[0] if len(paths) == 1 else f"{paths[0]} + {len(paths) - 1} more"
    n_store = len(meta.source.get("paths") or [meta.source.get("path")])
    with MosaicReader(source_plan(paths, meta)) as ds:
        band = ds.spec.band
        why = _same_grid(ds.spec, meta)
        if why is not None:
            more = (
                f"; the store was tiled from {n_store} sources: give each (in the tiling's order)"
                if n_store != len(paths)
                else ""
            )
            rep.add(
                "source",
                "index/digest",
                None,
                None,
                f"source {src!r} (band {band}{', reprojected' if ds.spec.warp else ''}) plans "
                f"onto {why}: not the DEM this store was tiled from{more}",
            )
            return
        changed = _changed_sources(meta, ds.spec)
        for b in grid.blocks():
            data = np.asarray(read_window(ds, band, grid, *b), dtype=np.dtype(meta.dtype))
            h, w = data.shape
            d = hashlib.blake2b(
                data.tobytes() + np.array([h, w], np.int64).tobytes(), digest_size=8
            ).digest()
            if int.from_bytes(d, "little") != int(digests[b]):
                rep.add(
                    "source",
                    "index/digest",
                    b,
                    None,
                    f"block {b} differs from the source {src!r}"
                    + _block_sources(ds, grid, b, changed),
                )
