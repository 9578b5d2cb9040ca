"""Running blocks: per-thread/per-process workers, the executor choice, the progress loop.

A worker reads a block's window, encodes it, writes its big levels, errors and mask, and writes
its journal entry last (the per-block commit, see ``tiler.resume``). The main thread only waits,
mirrors finished blocks into ``index/done`` and reports progress.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

import numpy as np
import rasterio.env
import zarr

from tiler import chunkwrite, kernels
from tiler.content import content_digest, fold_parts
from tiler.errors import HeightRangeError, StoreError
from tiler.grid import BlockGrid
from tiler.interrupt import DeferredInterrupt, wait_first
from tiler.location import Location, as_location
from tiler.parent_watch import die_with_parent
from tiler.resume import JOURNAL, JournalEntry, entry_nbytes, pack, small_levels
from tiler.schema import WRITE_CONFIG, index_chunk, is_sparse
from tiler.source import open_source, read_window
from tiler.vertical import height_range_message
from tiler.zarr_batch import open_arrays

log = logging.getLogger("tiler.tile")
WAIT_TIMEOUT_S = 600.0
MIRROR_INTERVAL_S = 0.5
#: ``auto`` uses threads with the compiled kernels up to this many workers (measured on 2 cores:
#: 2 threads within ~5 % of 2 processes; more threads were not measured against processes)
THREADS_SCALE_TO = 2
#: ``auto`` starts worker processes only for jobs of at least this many samples to tile: each
#: process imports and warms up on its own (~1-2 s), which smaller jobs never repay. Measured on
#: 2 cores, 2 workers, numpy kernels (2026-12-08): 40² in blocks of 17, 0.19 s on threads vs
#: 1.4-2.1 s on processes; 2049², 1.5-1.9 vs 5.5-7.3 s; 4097², 5.4-6.7 vs 8.8-9.4 s; 8193²,
#: 18.0 vs 17.2 s (even)
PROCESS_MIN_SAMPLES = 8192 * 8192


def open_for_write(target: Any, name: str) -> zarr.Array:
    """Open one array of a store for writing, writing every chunk (even all-fill ones).

    ``target``: a :class:`Location` (carries storage options), a path/URL or a zarr Store.
    """
    if isinstance(target, Location):
        return target.open_array(name, "r+").with_config(WRITE_CONFIG)
    return zarr.open_array(target, path=name, mode="r+").with_config(WRITE_CONFIG)


#: ``0`` makes block workers write every chunk through zarr (the reference, for comparisons)
DIRECT_WRITES_ENV = "TERRASTREAM_DIRECT_WRITES"


class BlockWorker:
    """Reads, encodes and writes blocks for one thread or process (own dataset and arrays).

    On a local format-2 store a block's level, error and mask chunks are encoded and written
    by :mod:`tiler.chunkwrite` (the bytes zarr would write, without a zarr call each), and so
    is its journal entry, the block's commit, after them (each file written whole, renamed over
    its key). Remote stores, ``TERRASTREAM_DIRECT_WRITES=0`` and arrays whose metadata
    :func:`tiler.chunkwrite.chunk_spec` refuses are written through zarr."""

    def __init__(self, src: str, band: int, target: Any, grid: BlockGrid, params: Any):
        self.src, self.band, self.grid, self.params = src, band, grid, params
        self.ds = open_source(src, band)
        self.small = small_levels(params.k)
        names = [f"levels/{i}" for i in range(self.small, params.k + 1)]
        self.loc = as_location(target)
        every = [*names, "errors", "mask", JOURNAL]  # opened at once (tiler.zarr_batch)
        self.arrays = dict(zip(every, open_arrays(self.loc, every), strict=True))
        self.direct: dict[str, chunkwrite.ChunkSpec] = {}
        self.sparse: dict[str, chunkwrite.ChunkSpec] = {}  # bit-shuffled levels (sparse rule)
        self.root = ""
        direct = self.loc.is_local and os.environ.get(DIRECT_WRITES_ENV, "1").strip() != "0"
        for n in [*names, "errors", "mask", JOURNAL]:
            spec = chunkwrite.chunk_spec(n, self.arrays[n].metadata.to_dict())
            if spec is None:
                continue
            if direct:
                self.direct[n] = spec
            if n in names and spec.byte_codec is not None and params.sparse_byte is not None:
                self.sparse[n] = spec
        if direct:
            self.root = str(self.loc.path)

    def _write(
        self, name: str, block: tuple[int, int], values: np.ndarray, sparse: bool = False
    ) -> None:
        spec = self.sparse.get(name) if sparse else None
        if spec is not None:  # both frames; the bytes go to the store whichever way it is written
            data, _ = chunkwrite.encode_sparse(values, spec, self.params.sparse_byte[1])
            if name in self.direct:
                chunkwrite.write_local_bytes(self.root, spec, block, data)
            else:
                self.loc.put_bytes(spec.key(block), data)
            return
        spec = self.direct.get(name)
        if spec is None:
            self.arrays[name][block] = values
        else:
            chunkwrite.write_local(self.root, spec, block, values)

    def run(self, br: int, bc: int) -> tuple[int, int]:
        """Encode block ``(br, bc)``; write its data, then its journal entry (the commit)."""
        from tiler import tile as tile_mod  # tests patch tile_mod.process_block

        try:
            res = tile_mod.process_block(
                read_window(self.ds, self.band, self.grid, br, bc), self.params
            )
        except HeightRangeError as exc:  # where in the DEM, and which source
            r0, c0, _, _ = self.grid.block_window(br, bc)
            row, col = r0 + exc.row, c0 + exc.col
            srcs = self.ds.spec.sources
            hits = self.ds.sources_for(row, col, 1, 1) or [0]  # (of a mosaic: the sample's)
            name = os.path.basename(srcs[hits[0]].path.rstrip("/"))
            more = " (or a source after it)" if len(hits) > 1 else ""
            grid = "reprojected grid" if self.ds.spec.warp else "DEM"  # (not the source's)
            raise HeightRangeError(
                f"{name}{more}, block {(br, bc)}, first at row {row}, column {col} of the "
                f"{grid}: {height_range_message(exc.count, exc.value, exc.raw, name)}",
                value=exc.value,
                raw=exc.raw,
                count=exc.count,
                row=row,
                col=col,
            ) from None
        rule = self.params.sparse_byte
        sparse = (
            rule is not None
            and res.mask is not None
            and is_sparse(int(np.count_nonzero(res.mask)), res.mask.size, rule[0])
        )
        for i in range(self.small, self.params.k + 1):
            self._write(f"levels/{i}", (br, bc), res.levels[i], sparse)
        self._write("errors", (br, bc), res.errors)
        if res.mask is not None:
            self._write("mask", (br, bc), res.mask)
        journal = self.arrays[JOURNAL]
        # (a journal begun before content digests is resumed without them)
        with_content = journal.shape[-1] == entry_nbytes(self.params.k, self.params.storage_dtype)
        entry = JournalEntry(
            levels=res.levels[: self.small],
            exists=res.exists,
            has_nodata=res.has_nodata,
            zmin=res.zmin,
            zmax=res.zmax,
            digest=res.digest,
            content=content_digest(
                (br, bc),
                fold_parts(res.parts),
                res.exists,
                res.has_nodata,
                res.zmin,
                res.zmax,
                res.digest,
            ),
        )
        # the commit, once the data chunks above are written (direct writes return after the
        # rename: tiler.atomic)
        self._write(JOURNAL, (br, bc), pack(entry, self.params.storage_dtype, with_content))
        return br, bc

    def close(self) -> None:
        """Close the source dataset."""
        self.ds.close()


@dataclass(frozen=True)
class BlockRun:
    """What a block run is given (:func:`run_blocks`), passed to the local and dask runners."""

    src: Any
    loc: Location
    opts: Any
    grid: BlockGrid
    params: Any
    todo: list[tuple[int, int]]
    done: np.ndarray
    report: Callable[[int, int], None]
    lease: Any
    on_done: Callable[[list[tuple[int, int]]], None] | None = None


class BlockProgress:
    """The client side of a run (local pools and dask alike): finished blocks are mirrored into
    ``index/done`` at most every ``MIRROR_INTERVAL_S``, reported to ``run.report`` (blocks,
    bytes) and passed to ``run.on_done``."""

    def __init__(self, target: Any, run: BlockRun) -> None:
        self.done_arr = open_for_write(target, "index/done")
        self.grid, self.done = run.grid, run.done
        self.report, self.on_done = run.report, run.on_done
        self.itemsize = np.dtype(run.params.dtype).itemsize
        self.unmirrored: list[tuple[int, int]] = []
        self.last_mirror = time.monotonic()

    def add(
        self, blocks: list[tuple[int, int]], *, flush: bool = False, final: bool = False
    ) -> None:
        """Record finished ``blocks`` (``final``: the run is ending, ``on_done`` is not called)."""
        self.unmirrored.extend(blocks)
        # index/done mirrors the journal (the journal is what resuming trusts): rewrite its
        # chunks at most every MIRROR_INTERVAL_S
        if flush or time.monotonic() - self.last_mirror > MIRROR_INTERVAL_S:
            self.flush()
        for b in blocks:
            _, _, h, w = self.grid.block_window(*b)
            self.report(1, h * w * self.itemsize)
        if self.on_done is not None and blocks and not final:
            self.on_done(blocks)  # e.g. write a shard whose blocks are all done (main thread)

    def flush(self) -> None:
        """Mirror every recorded block into ``index/done`` now."""
        mark_done(self.done_arr, self.done, self.unmirrored, self.grid)
        self.unmirrored.clear()
        self.last_mirror = time.monotonic()


_PROCESS_WORKER: BlockWorker | None = None


def worker_setup(gdal_cache_mb: int, kernels_backend: str, dtype: str) -> None:
    """Per-process set-up of a tiling worker: allocator thresholds (:mod:`tiler.malloc`), GDAL
    cache cap, kernel backend (warmed up). Never called in the caller's own process."""
    from tiler import kernels
    from tiler.malloc import tune_allocator

    tune_allocator()

    rasterio.env.set_gdal_config("GDAL_CACHEMAX", int(gdal_cache_mb))
    os.environ[kernels.ENV] = kernels_backend
    if kernels_backend == "numba":
        kernels.warm_up(dtype)


def _process_init(gdal_cache_mb: int, kernels_backend: str, parent: int, *args: Any) -> None:
    global _PROCESS_WORKER
    die_with_parent(parent)  # (a killed parent left its workers running: tiler.parent_watch)
    # Ctrl-C reaches the whole process group: the parent reports it once (TilingInterrupted).
    # So does a SIGTERM sent to the group (systemd, `timeout`): the worker died of it and the
    # parent reported a worker "out of memory or killed" instead of the termination. The
    # worker was started with both blocked (see _submit): ignore them, then unblock (a signal
    # that arrived while this process was importing is discarded here). It still dies with
    # its parent (die_with_parent).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    worker_setup(gdal_cache_mb, kernels_backend, args[4].dtype)
    _PROCESS_WORKER = BlockWorker(*args)


def _submit_blocking_sigint(pool: Any, fn: Any, *args: Any) -> Future:
    """``pool.submit`` with SIGINT and SIGTERM blocked in this thread: a worker process the pool
    spawns now inherits the blocked signals, so a Ctrl-C or SIGTERM during its start-up
    (imports, before the initializer ignores them) cannot print a traceback or kill it. Other
    threads still take the signals for the parent, and one pending here is delivered on
    unblocking: none is lost."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        return pool.submit(fn, *args)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _process_run(br: int, bc: int) -> tuple[int, int]:
    assert _PROCESS_WORKER is not None
    return _PROCESS_WORKER.run(br, bc)


_GUARD = re.compile(r"""__name__\s*==\s*['"]__main__['"]""")


def processes_unsafe() -> str | None:
    """Why worker processes cannot be started safely here (None if they can).

    Spawned workers re-import the main script: a script calling ``tile()`` at module level
    without an ``if __name__ == "__main__":`` guard would run again in every worker.
    """
    if multiprocessing.parent_process() is not None:
        return "tile() runs inside a worker process"
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if not path:
        return None  # interactive session or python -c: workers do not re-run it
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read()
    except OSError:  # e.g. '<stdin>' (python - < script.py): a worker could not re-import it
        return f"the main script {path!r} is not a file worker processes can import"
    if _GUARD.search(text):
        return None
    return f"the main script {path!r} has no `if __name__ == '__main__':` guard"


def kernels_for(grid: BlockGrid) -> str:
    """The kernel backend worker processes should use for this DEM (``tiler.kernels.choose``)."""
    return kernels.choose(grid.height * grid.width)


def is_dask_scheduler(spec: str | None) -> bool:
    """True if ``spec`` asks for dask: ``"dask"`` or a scheduler address (``tcp://host:port``)."""
    return bool(spec) and (spec == "dask" or "://" in str(spec))


def choose_executor(
    opts: Any, loc: Location, todo: int, backend: str = "numpy", samples: int | None = None
) -> str:
    """``"processes"`` or ``"threads"`` for this run (logs why processes are not used).

    ``auto``: threads for small jobs (fewer than 4 blocks a worker, or fewer than
    :data:`PROCESS_MIN_SAMPLES` ``samples`` to tile); for larger ones threads too when the
    kernels are compiled (``backend == "numba"``: they release the GIL) and at most
    :data:`THREADS_SCALE_TO` workers run, else processes. Measured on 2 cores (BENCHMARKS.md
    "Tiling"): 2 threads tile 16385² within ~5 % of 2 processes' time with under half the
    memory, and 4097² 1.4 s sooner.
    """
    want = opts.executor
    if getattr(opts, "scheduler", None) in ("threads", "processes"):
        want = opts.scheduler
    if want == "auto":
        enough = samples is None or samples >= PROCESS_MIN_SAMPLES
        big = opts.n_workers > 1 and todo >= 4 * opts.n_workers and enough
        threads_scale = backend == "numba" and opts.n_workers <= THREADS_SCALE_TO
        procs = big and not threads_scale and loc.can_share_with_processes
        want = "processes" if procs else "threads"
    if want == "processes":
        if not loc.can_share_with_processes:
            log.warning("%s cannot be shared with worker processes: using threads", loc.url)
            return "threads"
        why = processes_unsafe()
        if why:
            log.warning("using threads instead of worker processes: %s", why)
            return "threads"
    return want


def process_count(asked: int, todo: int) -> int:
    """Worker processes to start for ``todo`` blocks when ``asked`` for: at most one per block
    and one per core. Each is its own interpreter with its own block buffers (~220 MiB
    measured); beyond the cores they only add memory and start-up (16 on 2 cores: 3.5 GiB and
    3x the time of 2), so a larger request is cut to the cores, with a warning."""
    cores = os.cpu_count() or 1
    n = max(1, min(asked, todo))
    if n > cores:
        log.warning(
            "%d worker processes asked for on %d cores: each holds its own interpreter and block "
            "buffers (~220 MiB), and more than the cores only add memory and start-up; using %d",
            asked, cores, cores,
        )  # fmt: skip
        n = cores
    return n


def run_blocks(
    src: str,
    loc: Location,
    opts: Any,
    grid: BlockGrid,
    params: Any,
    todo: list[tuple[int, int]],
    done: np.ndarray,
    report: Callable[[int, int], None],
    lease: Any,
    on_done: Callable[[list[tuple[int, int]]], None] | None = None,
) -> str:
    """Compute ``todo`` blocks; ``done`` (bool grid) is updated and mirrored to ``index/done``;
    ``on_done`` is called in this thread with each batch of finished blocks.

    Returns the executor used: ``threads``, ``processes`` or ``dask`` (``opts.scheduler``).
    """
    run = BlockRun(src, loc, opts, grid, params, todo, done, report, lease, on_done)
    if is_dask_scheduler(getattr(opts, "scheduler", None)):
        from tiler.dask_run import run_blocks_dask  # distributed is imported only when asked

        return run_blocks_dask(run)
    saved = os.environ.get(kernels.ENV)
    try:
        return _run_local(run)
    finally:
        if saved is None:
            os.environ.pop(kernels.ENV, None)
        else:
            os.environ[kernels.ENV] = saved


def _run_local(run: BlockRun) -> str:
    src, loc, opts, grid, params, todo = run.src, run.loc, run.opts, run.grid, run.params, run.todo
    target = loc.for_workers() if loc.can_share_with_processes else loc.target
    workers = opts.n_workers
    args = (src, opts.band, target, grid, params)
    backend = kernels_for(grid)
    executor = choose_executor(opts, loc, len(todo), backend, len(todo) * (1 << grid.k) ** 2)
    # the job's kernels, for the worker threads and what spawned workers inherit (and warm up);
    # run_blocks restores the caller's setting afterwards
    os.environ[kernels.ENV] = backend
    local = threading.local()
    thread_workers: list[BlockWorker] = []
    progress = BlockProgress(target, run)

    def thread_run(br: int, bc: int) -> tuple[int, int]:
        w = getattr(local, "worker", None)
        if w is None:
            w = local.worker = BlockWorker(*args)
            thread_workers.append(w)
        return w.run(br, bc)

    if executor == "processes":
        workers = process_count(workers, len(todo))
        pool: Any = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_process_init,
            initargs=(opts.gdal_cache_mb, backend, os.getpid(), *args),
        )
        task: Any = _process_run
    else:
        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="terrastream-tile")
        task = thread_run
    pending: set[Future] = set()
    it = iter(todo)

    def collect(finished: set[Future], *, flush: bool = False, final: bool = False) -> None:
        ok = [f.result() for f in finished if not f.cancelled() and f.exception() is None]
        progress.add(ok, flush=flush, final=final)

    def wait(fs: set[Future], timeout: float) -> set[Future]:
        return wait_futures(fs, timeout=timeout, return_when=FIRST_COMPLETED).done

    # a Ctrl-C is raised between waits (tiler.interrupt), never inside the pool's locks
    with DeferredInterrupt() as interrupt:
        try:
            while True:
                while len(pending) < 2 * workers:
                    b = next(it, None)
                    if b is None:
                        break
                    if executor == "processes":
                        pending.add(_submit_blocking_sigint(pool, task, *b))
                    else:
                        pending.add(pool.submit(task, *b))
                if not pending:
                    break
                finished = wait_blocks(wait, pending, interrupt)
                pending -= finished
                collect(finished)
                for fut in finished:
                    try:
                        fut.result()  # re-raises a worker's exception here
                    except BrokenProcessPool as exc:
                        interrupt.check()  # (killed by the signal the run was given)
                        raise StoreError(
                            "a tiling worker process died (out of memory or killed); rerun "
                            "the same call to resume (finished blocks are kept)"
                        ) from exc
                run.lease.check()
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)
            collect({f for f in pending if f.done()}, flush=True, final=True)  # stay done
            raise
        else:
            pool.shutdown(wait=True)
            collect(set(), flush=True)
        finally:
            for w in thread_workers:
                w.close()
    return executor


def wait_blocks(
    wait: Callable[[set[Any], float], set[Any]], pending: set[Any], interrupt: DeferredInterrupt
) -> set[Any]:
    """The first finished of ``pending`` block futures (``wait``: see :func:`wait_first`); a
    Ctrl-C is raised here; :class:`StoreError` if none finished within :data:`WAIT_TIMEOUT_S`."""
    finished = wait_first(wait, pending, WAIT_TIMEOUT_S, interrupt)
    if not finished:
        raise StoreError(f"no block finished within {WAIT_TIMEOUT_S:.0f} s; giving up")
    return finished


def mark_done(
    arr: zarr.Array, done: np.ndarray, blocks: list[tuple[int, int]], grid: BlockGrid
) -> None:
    """Set ``done`` for ``blocks`` and rewrite the touched chunks of ``index/done``."""
    if not blocks:
        return
    ir, ic = index_chunk(*grid.shape)
    chunks = set()
    for br, bc in blocks:
        done[br, bc] = True
        chunks.add((br // ir, bc // ic))
    for cr, cc in chunks:
        sl = (slice(cr * ir, (cr + 1) * ir), slice(cc * ic, (cc + 1) * ic))
        arr[sl] = done[sl]


def progress_reporter(
    total: int, skipped: int, progress: Callable | None
) -> Callable[[int, int], None]:
    """A ``report(n_blocks, n_bytes)`` callable feeding ``TileProgress`` to ``progress``."""
    from tiler.tile import TileProgress

    t0 = time.perf_counter()
    state = {"done": skipped, "bytes": 0}

    def report(n: int, nbytes: int) -> None:
        state["done"] += n
        state["bytes"] += nbytes
        if progress:
            progress(
                TileProgress(
                    state["done"], total, state["bytes"], time.perf_counter() - t0, skipped
                )
            )

    return report
