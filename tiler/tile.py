"""Tile a DEM into a store: windowed reads, one pure function per block, parallel, resumable.

``process_block`` is a pure function of a block's source window and the tiling parameters, so
it can be handed to any executor unchanged; output is identical whatever the worker count. A run
creates the layout (state ``layout``), then every worker writes a block's data and its journal
entry last (``tiler.resume``), so a run killed at any moment and rerun recomputes only the blocks
that were in flight; the finish step builds the shards and the index and marks the store
``complete``. One writer at a time holds the store's lease (``tiler.lease``); ``overwrite`` of a
local store builds next to it and swaps the directories at the end.
"""

from __future__ import annotations

import logging
import math
import os
import uuid
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import rasterio
import rasterio._env
import rasterio.env
import zarr

from tiler import codecs, static_error
from tiler.content import CONTENT_KEY, CONTENT_SCHEME, ERRORS_DTYPE, part_digest
from tiler.destination import (
    check_unfinished_is_recreatable,
    clean_siblings,
    clear_destination,
    inspect_destination,
)
from tiler.encoding import dequantise, fill_invalid, quantise
from tiler.errors import (
    HeightRangeError,
    SchedulerError,
    SourceError,
    StoreError,
    StoreExistsError,
    TilingInterrupted,
)
from tiler.grid import as_index
from tiler.layout import grid_side, parse_block_size
from tiler.lease import DEFAULT_TIMEOUT_S, WriterLease
from tiler.location import Location, as_location, for_writing
from tiler.mosaic import MosaicReader, MosaicSpec
from tiler.resume import (
    TILING_STATES,
    block_digest,
    check_same_job,
    job_identity,
    source_fingerprint,
    source_of,
)
from tiler.schema import (
    DEFAULT_CLEVEL,
    FORMAT_VERSION,
)
from tiler.source import (
    SourceLike,
    check_source_options,
    open_source,
    plan_source,
    read_window,
    source_meta,
)
from tiler.store import TerrainStore
from tiler.transport import server_errors
from tiler.vertical import MAX_HEIGHT_M, height_range_message

__all__ = [
    "BlockParams",
    "BlockResult",
    "TileOptions",
    "TileProgress",
    "TileSummary",
    "process_block",
    "read_window",
    "tile",
    "valid_mask",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TileOptions:
    """How to tile: block size, band, lossy precision, workers, overwrite, codec settings.

    ``repair`` rewrites only the damaged blocks of a finished store from the source;
    ``lease_timeout_s`` is how long a dead writer's lease blocks other writers.
    """

    block_size: int = 1025
    band: int = 1
    precision: float | None = None
    workers: int = 0  # 0 = one per CPU core
    overwrite: bool = False
    compression_level: int = DEFAULT_CLEVEL  # blosc/zstd clevel (tiler.schema)
    error_cap: int | None = None  # default: k - 4
    gdal_cache_mb: int = 64  # GDAL's block cache (its default, 5 % of RAM, dominates RSS)
    executor: str = "auto"  # "threads", "processes" or "auto" (processes for big local jobs)
    # None: ``executor`` decides; "threads"/"processes"; "dask" (a local dask cluster) or the
    # address of a dask scheduler ("tcp://host:port"), see tiler.dask_run
    scheduler: str | None = None
    retries: int = 2  # dask: times a failed block task is retried before the run fails
    repair: bool = False
    lease_timeout_s: float = DEFAULT_TIMEOUT_S
    # sources (tiler.source): reproject to this CRS while reading ("auto", "EPSG:...", WKT)
    dst_crs: str | None = None
    resampling: str = "bilinear"
    resolution: float | None = None  # target pixel size, target CRS units (with dst_crs)

    def __post_init__(self) -> None:
        for name in ("block_size", "band", "workers", "compression_level", "gdal_cache_mb",
                     "retries"):  # fmt: skip
            as_index(getattr(self, name), name)  # (a float or a string failed later, unnamed)
        if self.error_cap is not None:
            as_index(self.error_cap, "error_cap")
        if self.gdal_cache_mb < 1:
            raise SourceError(f"gdal_cache_mb must be >= 1, got {self.gdal_cache_mb}")
        parse_block_size(self.block_size)
        if self.band < 1:
            raise SourceError(f"band must be >= 1, got {self.band}")
        if self.precision is not None and not (np.isfinite(self.precision) and self.precision > 0):
            raise SourceError(
                f"precision must be a positive number of metres, got {self.precision}"
            )
        if self.workers < 0:
            raise SourceError(f"workers must be >= 0 (0 = one per core), got {self.workers}")
        if self.executor not in ("auto", "threads", "processes"):
            raise SourceError(
                f"executor must be 'auto', 'threads' or 'processes', got {self.executor!r}"
            )
        check_scheduler(self.scheduler)
        if self.retries < 0:
            raise SourceError(f"retries must be >= 0, got {self.retries}")
        if not 1 <= self.compression_level <= 9:
            raise SourceError(f"compression level must be in 1..9, got {self.compression_level}")
        if not (math.isfinite(self.lease_timeout_s) and self.lease_timeout_s > 0):
            raise SourceError(f"lease timeout must be > 0 seconds, got {self.lease_timeout_s}")
        if self.repair and self.overwrite:
            raise SourceError("repair and overwrite exclude each other: repair keeps the store")
        check_source_options(self)

    @property
    def k(self) -> int:
        """``k`` of the block size."""
        return parse_block_size(self.block_size)

    @property
    def n_workers(self) -> int:
        """Worker threads actually used."""
        return self.workers or (os.cpu_count() or 1)


def check_scheduler(spec: str | None) -> None:
    """Refuse a scheduler spec other than threads, processes, dask or an address."""
    if spec is None or spec in ("threads", "processes", "dask"):
        return
    if isinstance(spec, str) and "://" in spec and spec.split("://", 1)[1]:
        return
    raise SchedulerError(
        f"scheduler must be 'threads', 'processes', 'dask' (a local dask cluster) or a dask "
        f"scheduler address such as 'tcp://127.0.0.1:8786', got {spec!r}"
    )


@dataclass(frozen=True)
class BlockParams:
    """Everything ``process_block`` needs besides the window (picklable)."""

    k: int
    dtype: str  # source dtype
    storage_dtype: str
    nodata: float | None
    precision: float | None
    error_cap: int
    encoding: str = ""  # level codec name ("" = the default for the value dtype)
    z_scale: float = 1.0  # metres = value * z_scale + z_offset (tiler.vertical)
    z_offset: float = 0.0
    #: the store's sparse-block rule, ``(terrain_max, slack)`` (tiler.schema.sparse_byte_shuffle);
    #: None writes every chunk with its array's codec
    sparse_byte: tuple[float, float] | None = None


@dataclass(frozen=True)
class BlockResult:
    """Encoded block: stored levels, packed errors, valid mask (None if all valid), index row."""

    levels: list[np.ndarray]
    errors: np.ndarray | None
    mask: np.ndarray | None
    exists: bool
    has_nodata: bool
    zmin: float
    zmax: float
    digest: int
    #: :func:`tiler.content.part_digest` of each stored array: levels 0..k, errors, mask
    parts: tuple[int, ...] = ()


@dataclass(frozen=True)
class TileProgress:
    """Progress report: blocks processed/total, source bytes processed, elapsed seconds.

    ``skipped`` (also ``blocks_skipped``) counts blocks a resumed run found finished; a block
    counts as done once its data and journal entry are written.
    """

    blocks_done: int
    blocks_total: int
    bytes_done: int
    elapsed_s: float
    skipped: int = 0

    @property
    def blocks_skipped(self) -> int:
        """Blocks a resumed run did not recompute."""
        return self.skipped


@dataclass
class TileSummary:
    """What a ``tile`` call did (``TerrainStore.tile_summary`` of the returned store)."""

    blocks_total: int = 0
    blocks_skipped: int = 0
    blocks_computed: int = 0
    blocks_repaired: int = 0
    resumed: bool = False
    executor: str = ""
    block_size: int = 0
    notes: list[str] = field(default_factory=list)


def valid_mask(data: np.ndarray, nodata: float | None) -> np.ndarray:
    """True where a sample is terrain: not the nodata value and (floats) not NaN. An infinite
    sample that is not the declared nodata stays "valid" so that the height check refuses it
    (it is no height; it used to become nodata without a word)."""
    valid = np.ones(data.shape, dtype=bool)
    if data.dtype.kind == "f":
        valid &= ~np.isnan(data)
    if nodata is not None and not np.isnan(nodata):
        valid &= data != np.asarray(nodata).astype(data.dtype)
    return valid


def _height_range(data: np.ndarray, valid: np.ndarray, params: BlockParams) -> HeightRangeError:
    """The :class:`HeightRangeError` of the first valid sample of ``data`` beyond
    :data:`MAX_HEIGHT_M` (its row and column in the window, the count of such samples)."""
    metres = data.astype(np.float64) * params.z_scale + params.z_offset
    bad = valid & ~(np.abs(metres) < MAX_HEIGHT_M)
    r, c = (int(v[0]) for v in np.nonzero(bad))
    raw, count = repr(data[r, c].item()), int(bad.sum())
    return HeightRangeError(
        height_range_message(count, float(metres[r, c]), raw),
        value=float(metres[r, c]),
        raw=raw,
        count=count,
        row=r,
        col=c,
    )


def process_block(window: np.ndarray, params: BlockParams) -> BlockResult:
    """Encode one block from its source window (pure: same input, same output)."""
    k = params.k
    side = grid_side(k)
    dtype = np.dtype(params.dtype)
    data = np.asarray(window, dtype=dtype)
    h, w = data.shape
    digest = block_digest(data)
    valid = np.zeros((side, side), dtype=bool)
    valid[:h, :w] = valid_mask(data, params.nodata)
    exists = bool(valid.any())
    has_nodata = not bool(valid.all())
    if dtype.kind == "f" and exists:  # ±inf not declared nodata (0.09 ms a 1025² block)
        inf = np.isinf(data)
        if inf.any() and bool((inf & valid[:h, :w]).any()):
            raise _height_range(data, valid[:h, :w], params)
    grid = np.zeros((side, side), dtype=dtype)
    grid[:h, :w] = data
    if dtype.kind == "f":
        grid[~valid] = 0  # NaN/nodata never enter the arithmetic
    if exists:
        vals = grid if not has_nodata else grid[valid]
        zmin, zmax = float(vals.min()), float(vals.max())
        if params.precision:  # the heights the store holds (and reads return): rounded
            lo_hi = quantise(np.array([zmin, zmax]), params.precision)
            zmin, zmax = (float(v) for v in dequantise(lo_hi, params.precision, dtype))
        if (params.z_scale, params.z_offset) != (1.0, 0.0):  # heights in metres (tiler.vertical)
            a, b = params.z_scale, params.z_offset
            zmin, zmax = sorted((zmin * a + b, zmax * a + b))
        if not max(abs(zmin), abs(zmax)) < MAX_HEIGHT_M:
            raise _height_range(data, valid[:h, :w], params)
    else:
        zmin = zmax = float("nan")
    if params.precision:
        grid = quantise(grid, params.precision)
    grid = fill_invalid(grid, valid, k)
    codec = codecs.get(params.encoding) if params.encoding else codecs.for_dtype(grid.dtype)
    levels = codec.encode(grid, k)
    err_grid = grid.astype(np.float64) * params.precision if params.precision else grid
    if params.z_scale != 1.0:  # errors in metres (tiler.vertical)
        err_grid = err_grid.astype(np.float64) * abs(params.z_scale)
    errors = static_error.block_errors(err_grid, valid, k, params.error_cap)
    mask = valid if has_nodata else None
    parts = (
        *(part_digest(v, params.storage_dtype) for v in levels),
        part_digest(errors, ERRORS_DTYPE),
        part_digest(mask, bool),
    )
    return BlockResult(
        levels=levels,
        errors=errors,
        mask=mask,
        exists=exists,
        has_nodata=has_nodata,
        zmin=zmin,
        zmax=zmax,
        digest=digest,
        parts=parts,
    )


def needed_k(height: int, width: int) -> int:
    """The smallest ``k`` whose block covers a ``height x width`` DEM in one block."""
    n = max(height, width) - 1
    return 1 if n <= 2 else math.ceil(math.log2(n))


def tile(
    src: SourceLike,
    dst: str | os.PathLike | Location | zarr.abc.store.Store,
    options: TileOptions | None = None,
    progress: Callable[[TileProgress], None] | None = None,
) -> TerrainStore:
    """Tile ``src`` (anything rasterio opens, or a sequence of them forming one mosaic, see
    :mod:`tiler.mosaic`) into a zarr v3 store at ``dst``, reprojected if ``options.dst_crs``.

    ``dst`` is a local path, an fsspec URL or a zarr Store. A Ctrl-C raises
    :class:`TilingInterrupted` (a ``KeyboardInterrupt``) and leaves a resumable store.
    """
    opts = options or TileOptions()
    label = str(src) if isinstance(src, str | os.PathLike) else "the mosaic"
    loc = for_writing(as_location(dst))  # (its workers get the same client retries)
    # GDAL sizes its block cache once, on first use: this caps it for a fresh process (the
    # CLI's run, the worker processes); the option is restored afterwards.
    previous = rasterio.env.get_gdal_config("GDAL_CACHEMAX")
    rasterio.env.set_gdal_config("GDAL_CACHEMAX", int(opts.gdal_cache_mb))
    try:
        return _tile(plan_source(src, opts), loc, opts, progress)  # tiler.source plans the mosaic
    except KeyboardInterrupt as exc:
        if isinstance(exc, TilingInterrupted):
            raise
        raise TilingInterrupted(
            f"tiling {label!r} into {loc.url!r} was interrupted; the store is kept unfinished: "
            "run the same tile() call again to resume"
        ) from exc
    finally:
        if previous is None:
            rasterio._env.del_gdal_config("GDAL_CACHEMAX")
        else:
            rasterio.env.set_gdal_config("GDAL_CACHEMAX", previous)


def stored_settings(dst: Any) -> dict[str, Any]:
    """The tiling settings a finished store at ``dst`` was made with (``block_size``,
    ``precision``, and its reprojection's ``dst_crs``, ``resampling``, ``resolution``; empty
    when there is no store or it records none): what ``--repair`` uses when they are not given
    again."""
    loc = as_location(dst)
    if not loc.exists():
        return {}
    kind, meta, _ = inspect_destination(loc)
    job = (meta.extra.get("job") or {}) if kind == "store" and meta is not None else {}
    keys = ("block_size", "precision", "dst_crs", "resampling", "resolution")
    return {k: job[k] for k in keys if k in job}


def finished_generation(dst: Any) -> str | None:
    """The generation of the finished store at ``dst`` (None: none there, or unfinished or
    unreadable): which build a Ctrl-C at the very end of a run left behind."""
    try:
        loc = as_location(dst)
        if not loc.exists():
            return None
        kind, meta, _ = inspect_destination(loc)
    except Exception:  # noqa: BLE001 - asked while a Ctrl-C is handled: no answer is None
        return None
    if kind != "store" or meta is None or not meta.complete:
        return None
    return meta.generation


def _clamp_block_size(ds: MosaicReader, opts: TileOptions, notes: list[str]):
    k = needed_k(ds.height, ds.width)
    if opts.k <= k:
        return opts
    new = grid_side(k)
    msg = (
        f"block size {opts.block_size} is larger than a {ds.height}x{ds.width} DEM needs; "
        f"using {new} (one block covers the DEM; the output is the same up to the block size)"
    )
    log.warning("%s", msg)
    notes.append(msg)
    return replace(opts, block_size=new)


def _tile(
    src: MosaicSpec,
    loc: Location,
    opts: TileOptions,
    progress: Callable[[TileProgress], None] | None,
) -> TerrainStore:
    summary = TileSummary()
    with open_source(src, opts.band) as ds:
        opts = _clamp_block_size(ds, opts, summary.notes)
        meta = source_meta(ds, src, opts)
        fingerprint = source_fingerprint(ds, opts.band)
    meta = replace(meta, format_version=FORMAT_VERSION)
    job = job_identity(fingerprint, opts, meta)
    meta = replace(
        meta,
        extra={
            **meta.extra,
            "generation": uuid.uuid4().hex,
            "job": job,
            CONTENT_KEY: CONTENT_SCHEME,  # (a resumed store keeps what it was begun with)
        },
    )
    summary.block_size = meta.block_size
    # the destination's first contact: a dead endpoint is the server's failure, said so
    with nullcontext() if loc.is_local else server_errors("what is at the destination", loc.url):
        bad_parent = loc.parent_writable()
        if bad_parent is not None and not loc.exists():
            raise StoreError(
                f"cannot write {loc.url!r}: {bad_parent!r} is not a writable directory"
            )
        kind, old, why = inspect_destination(loc)
    unfinished = kind == "store" and old.extra.get("state") in TILING_STATES
    if opts.repair and not unfinished:
        from tiler.repair import repair_store

        return repair_store(src, loc, opts, job, progress, summary)
    if kind == "store" and old.extra.get("state") == "repair" and not opts.overwrite:
        raise StoreExistsError(
            "{url!r} holds an interrupted repair; finish it with the same source and {repair} "
            "(or replace the store with {overwrite})",
            params={"repair": "repair=True", "overwrite": "overwrite=True"},
            url=loc.url,
        )
    if opts.repair:  # an interrupted tiling is finished, as the same command without --repair
        log.info("%s is an unfinished tiling, not a damaged store: finishing it", loc.url)
    if kind == "foreign":
        verb = "overwrite" if opts.overwrite else "write into"
        raise StoreExistsError(
            f"refusing to {verb} {loc.url!r}: it exists and is not a terrastream store ({why}); "
            "choose another destination (nothing was written)."
        )
    if kind == "store" and old.complete and not opts.overwrite:
        raise StoreExistsError(
            "{url!r} already holds a finished store; tile with {overwrite} to replace it.",
            params={"overwrite": "overwrite=True"},
            url=loc.url,
        )
    from tiler.assemble import build

    with WriterLease(loc, opts.lease_timeout_s) as lease:
        if kind == "store" and opts.overwrite and loc.can_rename:
            token = uuid.uuid4().hex[:12]
            tmp = loc.sibling(f".tmp-{token}")
            clean_siblings(loc)
            try:
                build(src, tmp, meta, opts, progress, summary, lease, resume=False)
            except BaseException:
                tmp.remove()
                raise
            lease.stop()
            trash = loc.sibling(f".old-{token}")
            loc.rename_to(trash)
            tmp.rename_to(loc)
            trash.remove()
            log.info("replaced %s with the new store (directory swap)", loc.url)
        elif kind == "store" and opts.overwrite:
            clear_destination(loc)
            lease.reassert()
            build(src, loc, meta, opts, progress, summary, lease, resume=False)
        elif kind == "store" and old.extra.get("state") in ("tiling", "finishing"):
            check_same_job(
                loc.url,
                old.extra.get("job"),
                job,
                sources=(source_of(old.source), source_of(meta.source)),
            )
            log.info("resuming unfinished store %s", loc.url)
            build(src, loc, meta, opts, progress, summary, lease, resume=True)
        else:
            if kind == "store":
                check_unfinished_is_recreatable(loc, old, job, source_of(meta.source))
            clear_destination(loc)
            lease.reassert()
            build(src, loc, meta, opts, progress, summary, lease, resume=False)
    store = TerrainStore(loc)
    store.tile_summary = summary
    return store
