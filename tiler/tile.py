"""Tile a DEM into a store: windowed reads, one pure function per block, parallel, resumable.

``process_block`` is a pure function of a block's source window and the tiling parameters, so
it can be handed to any executor (threads here; a dask cluster later) unchanged. Output is
identical whatever the worker count. A run writes the metadata with ``complete: false`` first,
marks each block done in ``index/done`` after all of its data is written, and sets
``complete: true`` last; a rerun of the same command skips finished blocks.
"""

from __future__ import annotations

import hashlib
import logging
import multiprocessing
import os
import shutil
import threading
import time
from collections.abc import Callable
from concurrent.futures import (
    FIRST_COMPLETED,
    Future,
    ProcessPoolExecutor,
    ThreadPoolExecutor,
    wait,
)
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace

import numpy as np
import rasterio
import rasterio._env
import rasterio.env
import rasterio.errors
import zarr

from tiler import static_error
from tiler.encoding import (
    encode_levels,
    fill_invalid,
    quantise,
)
from tiler.errors import (
    SourceError,
    StoreCorruptError,
    StoreError,
    StoreExistsError,
)
from tiler.grid import BlockGrid
from tiler.layout import grid_side, parse_block_size
from tiler.source import (
    SourceLike,
    _open_source,
    _source_meta,
    check_source_options,
    plan_source,
    read_window,
)
from tiler.store import (
    ATTR,
    SHARD_BLOCKS,
    SHARDED_LEVELS,
    StoreMeta,
    TerrainStore,
    create_layout,
    is_url,
    read_meta,
    write_meta,
)
from tiler.vertical import height_transform

log = logging.getLogger(__name__)
WAIT_TIMEOUT_S = 600.0


@dataclass(frozen=True)
class TileOptions:
    """How to tile: block size, band, lossy precision, workers, overwrite, codec settings."""

    block_size: int = 1025
    band: int = 1
    precision: float | None = None
    workers: int = 0  # 0 = one per CPU core
    overwrite: bool = False
    compression_level: int = 5  # blosc/zstd clevel
    error_cap: int | None = None  # default: k - 4
    gdal_cache_mb: int = 64  # GDAL's block cache (its default, 5 % of RAM, dominates RSS)
    executor: str = "auto"  # "threads", "processes" or "auto" (processes for big local jobs)
    # sources (tiler.source): reproject to this CRS while reading ("auto", "EPSG:...", WKT)
    dst_crs: str | None = None
    resampling: str = "bilinear"
    resolution: float | None = None  # target pixel size, target CRS units (with dst_crs)

    def __post_init__(self) -> None:
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
        if not 1 <= self.compression_level <= 9:
            raise SourceError(f"compression level must be in 1..9, got {self.compression_level}")
        check_source_options(self)

    @property
    def k(self) -> int:
        """``k`` of the block size."""
        return parse_block_size(self.block_size)

    @property
    def n_workers(self) -> int:
        """Worker threads actually used."""
        return self.workers or (os.cpu_count() or 1)


@dataclass(frozen=True)
class BlockParams:
    """Everything ``process_block`` needs besides the window (picklable)."""

    k: int
    dtype: str  # source dtype
    storage_dtype: str
    nodata: float | None
    precision: float | None
    error_cap: int
    z_scale: float = 1.0  # metres = value * z_scale + z_offset (tiler.vertical)
    z_offset: float = 0.0


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


@dataclass(frozen=True)
class TileProgress:
    """Progress report: blocks processed/total, source bytes processed, elapsed seconds.

    A block counts when its data is written; it is marked done in the store (for resuming)
    once the small-level shard it belongs to is written.
    """

    blocks_done: int
    blocks_total: int
    bytes_done: int
    elapsed_s: float
    skipped: int = 0


def valid_mask(data: np.ndarray, nodata: float | None) -> np.ndarray:
    """True where a sample is terrain: not the nodata value and (floats) finite."""
    valid = np.ones(data.shape, dtype=bool)
    if data.dtype.kind == "f":
        valid &= np.isfinite(data)
    if nodata is not None and not np.isnan(nodata):
        valid &= data != np.asarray(nodata).astype(data.dtype)
    return valid


def process_block(window: np.ndarray, params: BlockParams) -> BlockResult:
    """Encode one block from its source window (pure: same input, same output)."""
    k = params.k
    side = grid_side(k)
    dtype = np.dtype(params.dtype)
    data = np.asarray(window, dtype=dtype)
    h, w = data.shape
    digest = int.from_bytes(
        hashlib.blake2b(
            data.tobytes() + np.array([h, w], np.int64).tobytes(), digest_size=8
        ).digest(),
        "little",
    )
    valid = np.zeros((side, side), dtype=bool)
    valid[:h, :w] = valid_mask(data, params.nodata)
    exists = bool(valid.any())
    has_nodata = not bool(valid.all())
    grid = np.zeros((side, side), dtype=dtype)
    grid[:h, :w] = data
    if dtype.kind == "f":
        grid[~valid] = 0  # NaN/inf never enter the arithmetic
    if exists:
        vals = grid[valid]
        zmin, zmax = float(vals.min()), float(vals.max())
        if (params.z_scale, params.z_offset) != (1.0, 0.0):  # heights in metres (tiler.vertical)
            a, b = params.z_scale, params.z_offset
            zmin, zmax = sorted((zmin * a + b, zmax * a + b))
    else:
        zmin = zmax = float("nan")
    if params.precision:
        grid = quantise(grid, params.precision)
    grid = fill_invalid(grid, valid, k)
    levels = encode_levels(grid, k)
    err_grid = grid.astype(np.float64) * params.precision if params.precision else grid
    if params.z_scale != 1.0:  # errors in metres (tiler.vertical)
        err_grid = err_grid.astype(np.float64) * abs(params.z_scale)
    errors = static_error.block_errors(err_grid, valid, k, params.error_cap)
    return BlockResult(
        levels=levels,
        errors=errors,
        mask=valid if has_nodata else None,
        exists=exists,
        has_nodata=has_nodata,
        zmin=zmin,
        zmax=zmax,
        digest=digest,
    )


def _same_job(a: StoreMeta, b: StoreMeta) -> bool:
    keys = ("k", "height", "width", "dtype", "storage_dtype", "precision", "nodata", "error_cap")
    return all(getattr(a, n) == getattr(b, n) for n in keys) and a.compressor == b.compressor


def _prepare_destination(dst: str, meta: StoreMeta, opts: TileOptions) -> tuple[zarr.Group, bool]:
    """Create (or reopen for resuming) the store; returns the group and whether it resumes."""
    exists = _exists(dst)
    if exists and not opts.overwrite:
        try:
            old = read_meta(zarr.open_group(dst, mode="r"))
        except (StoreError, FileNotFoundError, ValueError, KeyError) as exc:
            raise StoreExistsError(
                f"{dst!r} exists and is not a terrastream store ({exc}); choose another "
                "destination (nothing was written)."
            ) from exc
        if old.complete:
            raise StoreExistsError(
                f"{dst!r} already holds a finished store; pass --overwrite to replace it."
            )
        if not _same_job(old, meta):
            raise StoreExistsError(
                f"{dst!r} holds an unfinished store made with other settings; pass --overwrite "
                "to start again, or rerun with the original settings to finish it."
            )
        log.info("resuming unfinished store %s", dst)
        return zarr.open_group(dst, mode="r+"), True
    if exists:
        _remove_store(dst)
    try:
        group = zarr.open_group(dst, mode="w")
    except (OSError, ValueError) as exc:
        raise StoreError(f"cannot create a store at {dst!r}: {exc}") from exc
    write_meta(group, meta)
    create_layout(group, meta, opts.compression_level)
    return group, False


def _exists(dst: str) -> bool:
    if not is_url(dst):
        return os.path.exists(dst)
    import fsspec

    fs, path = fsspec.core.url_to_fs(dst)
    return bool(fs.exists(path))


def _remove_store(dst: str) -> None:
    """Remove an old store for --overwrite; refuses anything that is not a terrastream store."""
    if not is_url(dst):
        if os.path.isdir(dst) and os.listdir(dst):
            try:
                read_meta(zarr.open_group(dst, mode="r"))
            except (StoreError, FileNotFoundError, ValueError, KeyError) as exc:
                raise StoreExistsError(
                    f"refusing to overwrite {dst!r}: it is a non-empty directory that is not a "
                    "terrastream store"
                ) from exc
            shutil.rmtree(dst)
        elif os.path.isfile(dst):
            raise StoreExistsError(f"refusing to overwrite {dst!r}: it is a file, not a store")
        return
    import fsspec

    fs, path = fsspec.core.url_to_fs(dst)
    fs.rm(path, recursive=True)


class _BlockWorker:
    """Reads, encodes and writes blocks for one thread or process (own dataset and arrays)."""

    def __init__(self, src: str, band: int, dst: str, grid: BlockGrid, params: BlockParams):
        self.src, self.band, self.grid, self.params = src, band, grid, params
        self.ds = _open_source(src, band)
        group = zarr.open_group(dst, mode="r+")
        names = [f"levels/{i}" for i in range(SHARDED_LEVELS, params.k + 1)]
        self.arrays = {n: group[n] for n in [*names, "errors", "mask"]}

    def run(self, br: int, bc: int) -> tuple[tuple[int, int], BlockResult]:
        """Encode block ``(br, bc)``, write its big levels, errors and mask; return the rest."""
        res = process_block(read_window(self.ds, self.band, self.grid, br, bc), self.params)
        for i in range(SHARDED_LEVELS, self.params.k + 1):
            self.arrays[f"levels/{i}"][br, bc] = res.levels[i]
        self.arrays["errors"][br, bc] = res.errors
        if res.mask is not None:
            self.arrays["mask"][br, bc] = res.mask
        # keep only what the shard writer needs: the small levels and the index row
        return (br, bc), replace(res, levels=res.levels[:SHARDED_LEVELS], errors=None, mask=None)

    def close(self) -> None:
        """Close the source dataset."""
        self.ds.close()


_PROCESS_WORKER: _BlockWorker | None = None


def _process_init(gdal_cache_mb: int, *args: object) -> None:
    global _PROCESS_WORKER
    rasterio.env.set_gdal_config("GDAL_CACHEMAX", int(gdal_cache_mb))
    _PROCESS_WORKER = _BlockWorker(*args)  # type: ignore[arg-type]


def _process_run(br: int, bc: int) -> tuple[tuple[int, int], BlockResult]:
    assert _PROCESS_WORKER is not None
    return _PROCESS_WORKER.run(br, bc)


def _use_processes(opts: TileOptions, dst: str, todo: int) -> bool:
    """Processes give real parallelism (numpy + codecs hold the GIL too often for threads);
    they need a destination every process can open (not ``memory://``) and enough blocks."""
    if opts.executor != "auto":
        return opts.executor == "processes"
    return opts.n_workers > 1 and todo >= 4 * opts.n_workers and not dst.startswith("memory:")


def tile(
    src: SourceLike,
    dst: str | os.PathLike,
    options: TileOptions | None = None,
    progress: Callable[[TileProgress], None] | None = None,
) -> TerrainStore:
    """Tile ``src`` (anything rasterio opens, or a sequence of them forming one mosaic, see
    tiler.mosaic) into a zarr v3 store at ``dst``, reprojected if ``options.dst_crs``."""
    opts = options or TileOptions()
    dst = str(dst)
    # GDAL sizes its block cache once, on first use: this caps it for a fresh process (the
    # CLI's run, the worker processes); the option is restored afterwards.
    previous = rasterio.env.get_gdal_config("GDAL_CACHEMAX")
    rasterio.env.set_gdal_config("GDAL_CACHEMAX", int(opts.gdal_cache_mb))
    try:
        return _tile(plan_source(src, opts), dst, opts, progress)  # hook: tiler.source
    finally:
        if previous is None:
            rasterio._env.del_gdal_config("GDAL_CACHEMAX")
        else:
            rasterio.env.set_gdal_config("GDAL_CACHEMAX", previous)


def _tile(
    src: str, dst: str, opts: TileOptions, progress: Callable[[TileProgress], None] | None
) -> TerrainStore:
    with _open_source(src, opts.band) as ds:
        meta = _source_meta(ds, src, opts)
    grid = meta.grid
    if _exists(dst) is False and not is_url(dst):
        parent = os.path.dirname(os.path.abspath(dst))
        if not os.path.isdir(parent) or not os.access(parent, os.W_OK):
            raise StoreError(f"cannot write {dst!r}: {parent!r} is not a writable directory")
    group, resuming = _prepare_destination(dst, meta, opts)
    if resuming:
        meta = replace(read_meta(group), complete=False)
    params = BlockParams(
        k=meta.k,
        dtype=meta.dtype,
        storage_dtype=meta.storage_dtype,
        nodata=meta.nodata,
        precision=meta.precision,
        error_cap=meta.error_cap,
        z_scale=height_transform(meta)[0],
        z_offset=height_transform(meta)[1],
    )
    _run_blocks(src, dst, opts, grid, params, group, progress)
    try:
        _finish(group, meta, grid)
    except SourceError:
        _remove_store(dst)  # an all-nodata source: leave nothing that looks like a store
        raise
    return TerrainStore(dst)


def _shard_order(grid: BlockGrid) -> list[list[tuple[int, int]]]:
    """Blocks grouped by the shard of the small levels they belong to, shards row-major."""
    rows, cols = grid.shape
    sr, sc = min(rows, SHARD_BLOCKS), min(cols, SHARD_BLOCKS)
    groups = []
    for r0 in range(0, rows, sr):
        for c0 in range(0, cols, sc):
            groups.append(
                [
                    (r, c)
                    for r in range(r0, min(r0 + sr, rows))
                    for c in range(c0, min(c0 + sc, cols))
                ]
            )
    return groups


def _run_blocks(
    src: str,
    dst: str,
    opts: TileOptions,
    grid: BlockGrid,
    params: BlockParams,
    group: zarr.Group,
    progress: Callable[[TileProgress], None] | None,
) -> None:
    done = group["index/done"][...]
    total = grid.rows * grid.cols
    skipped = int(done.sum())
    itemsize = np.dtype(params.dtype).itemsize
    t0 = time.perf_counter()
    n_done, bytes_done = skipped, 0
    workers = opts.n_workers
    args = (src, opts.band, dst, grid, params)
    local = threading.local()
    thread_workers: list[_BlockWorker] = []

    def thread_run(br: int, bc: int) -> tuple[tuple[int, int], BlockResult]:
        w = getattr(local, "worker", None)
        if w is None:
            w = local.worker = _BlockWorker(*args)
            thread_workers.append(w)
        return w.run(br, bc)

    def report() -> None:
        if progress:
            progress(TileProgress(n_done, total, bytes_done, time.perf_counter() - t0, skipped))

    report()
    if _use_processes(opts, dst, total - skipped):
        pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_process_init,
            initargs=(opts.gdal_cache_mb, *args),
        )
        run = _process_run
    else:
        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="terrastream-tile")
        run = thread_run
    try:
        for shard in _shard_order(grid):
            todo = [b for b in shard if not done[b]]
            if not todo:
                continue
            results: dict[tuple[int, int], BlockResult] = {}
            pending: set[Future] = set()
            it = iter(todo)
            while True:
                while len(pending) < 2 * workers:
                    b = next(it, None)
                    if b is None:
                        break
                    pending.add(pool.submit(run, *b))
                if not pending:
                    break
                finished, pending = wait(
                    pending, timeout=WAIT_TIMEOUT_S, return_when=FIRST_COMPLETED
                )
                if not finished:
                    raise StoreError(f"no block finished within {WAIT_TIMEOUT_S:.0f} s; giving up")
                for fut in finished:
                    try:
                        b, res = fut.result()  # re-raises a worker's exception here
                    except BrokenProcessPool as exc:
                        raise StoreError(
                            "a tiling worker process died (out of memory, killed, or a script "
                            "calling tile() without an `if __name__ == '__main__':` guard; "
                            "executor='threads' avoids processes); rerun to resume"
                        ) from exc
                    results[b] = res
                    r0, c0, h, w = grid.block_window(*b)
                    bytes_done += h * w * itemsize
                    n_done += 1
                    report()
            _write_shard(group, params.k, results)
    except BaseException:
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    finally:
        for w in thread_workers:
            w.close()
    pool.shutdown(wait=True)


def _write_shard(group: zarr.Group, k: int, results: dict[tuple[int, int], BlockResult]) -> None:
    """Write a shard's small levels and index rows, then mark its blocks done (main thread)."""
    rows = [b[0] for b in results]
    cols = [b[1] for b in results]
    r0, r1, c0, c1 = min(rows), max(rows) + 1, min(cols), max(cols) + 1
    for i in range(min(SHARDED_LEVELS, k + 1)):
        arr = group[f"levels/{i}"]
        region = arr[r0:r1, c0:c1]
        for (br, bc), res in results.items():
            region[br - r0, bc - c0] = res.levels[i]
        arr[r0:r1, c0:c1] = region
    sl = (slice(r0, r1), slice(c0, c1))
    cols_ = {
        "exists": lambda r: r.exists,
        "has_nodata": lambda r: r.has_nodata,
        "zmin": lambda r: r.zmin,
        "zmax": lambda r: r.zmax,
        "digest": lambda r: r.digest,
    }
    for name, get in cols_.items():
        arr = group[f"index/{name}"]
        region = arr[sl]
        for (br, bc), res in results.items():
            region[br - r0, bc - c0] = get(res)
        arr[sl] = region
    done = group["index/done"]
    region = done[sl]
    for br, bc in results:
        region[br - r0, bc - c0] = True
    done[sl] = region


def _finish(group: zarr.Group, meta: StoreMeta, grid: BlockGrid) -> None:
    """Check every block is done, write windows and checksums, then mark the store complete."""
    done = group["index/done"][...]
    if not done.all():
        missing = int((~done).sum())
        raise StoreCorruptError(f"{missing} block(s) are not done; the store stays unfinished")
    exists = group["index/exists"][...]
    if not exists.any():
        raise SourceError(
            f"{meta.source.get('path')!r} holds no terrain: every sample is nodata or NaN; "
            "nothing was written"
        )
    win = np.zeros((grid.rows, grid.cols, 4), dtype=np.int32)
    for br, bc in grid.blocks():
        win[br, bc] = grid.block_window(br, bc)
    group["index/window"][...] = win
    digests = group["index/digest"][...]
    checksum = hashlib.blake2b(digests.astype("<u8").tobytes(), digest_size=16).hexdigest()
    zmin = group["index/zmin"][...]
    zmax = group["index/zmax"][...]
    source = dict(meta.source, checksum=f"blake2b-128:{checksum}")
    extra = dict(meta.extra)
    extra["value_range"] = [float(np.nanmin(zmin)), float(np.nanmax(zmax))]
    write_meta(group, replace(meta, source=source, complete=True, extra=extra))
    log.info("store complete: %s", ATTR)
