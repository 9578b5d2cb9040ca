"""Running blocks on a dask cluster (``TileOptions(scheduler="dask" | "tcp://host:port")``).

Every block is one task. A task runs on a dask worker: it opens the source (a picklable
:class:`~tiler.mosaic.MosaicSpec` or path) and the destination (a path on a shared file system
or an object-store URL with its storage options), reads its window, encodes it and writes its
chunks and its journal entry itself (the per-block commit of ``tiler.resume``). A task returns
only its block id, so no block's data passes through the client; the client mirrors finished
blocks, feeds the progress callback and, after every task succeeded, the caller finishes the
store (shards, index, ``complete``). dask retries a failed task ``opts.retries`` times; a task
that still fails ends the run with :class:`BlockFailedError` naming the block, and the store
stays resumable (rerun: only blocks without a journal entry are computed again).

``distributed`` is imported only here, i.e. only when a dask scheduler is asked for.
"""

from __future__ import annotations

import logging
import threading
import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from tiler.errors import BlockFailedError, SchedulerError, SourceError
from tiler.grid import BlockGrid
from tiler.interrupt import DeferredInterrupt
from tiler.location import Location

if TYPE_CHECKING:
    from tiler.run import BlockRun

log = logging.getLogger("tiler.tile")
IN_FLIGHT_PER_THREAD = 3  # tasks queued per worker thread (keeps workers busy, memory bounded)
#: seconds a scheduler address is tried (distributed retries a refused connection) before
#: :class:`SchedulerError` says it cannot be reached
CONNECT_TIMEOUT_S = 20.0


@dataclass(frozen=True)
class DaskJob:
    """What a task needs besides its block id (pickled once per task: a few hundred bytes)."""

    token: str
    src: Any
    band: int
    target: Location
    grid: BlockGrid
    params: Any
    gdal_cache_mb: int
    kernels_backend: str


_LOCAL = threading.local()
_SETUP_LOCK = threading.Lock()
_SETUP_DONE: set[tuple[int, str, str]] = set()


def run_block_task(job: DaskJob, br: int, bc: int) -> tuple[int, int]:
    """The dask task: compute block ``(br, bc)`` and write it to the destination (worker side).

    Each worker thread keeps one :class:`~tiler.run.BlockWorker` (open source and arrays) per
    job, so a dataset is opened once per thread, not once per block.
    """
    from tiler.run import BlockWorker, worker_setup

    key = (job.gdal_cache_mb, job.kernels_backend, str(job.params.dtype))
    with _SETUP_LOCK:
        if key not in _SETUP_DONE:
            worker_setup(*key)
            _SETUP_DONE.add(key)
    cached = getattr(_LOCAL, "worker", None)
    if cached is None or cached[0] != job.token:
        if cached is not None:
            cached[1].close()
        cached = _LOCAL.worker = (
            job.token,
            BlockWorker(job.src, job.band, job.target, job.grid, job.params),
        )
    return cached[1].run(br, bc)


def _connect(spec: str, n_workers: int) -> tuple[Any, Any]:
    """A ``(client, cluster_or_None)``: a new loopback LocalCluster for ``"dask"``, else the
    scheduler at the address ``spec``."""
    try:
        import distributed
    except ImportError as exc:
        raise SchedulerError(
            f"scheduler {spec!r} needs dask's 'distributed' package: "
            "pip install 'terrastream[dask]'"
        ) from exc
    if spec == "dask":
        cluster = distributed.LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address="127.0.0.1:0",
        )
        log.info("started a local dask cluster: %d worker process(es)", n_workers)
        return distributed.Client(cluster), cluster
    try:
        return distributed.Client(spec, timeout=f"{CONNECT_TIMEOUT_S}s"), None
    except (OSError, TimeoutError) as exc:
        raise SchedulerError(
            f"cannot reach the dask scheduler at {spec!r}: {exc}; start one "
            "(dask-scheduler, dask-worker ADDRESS) or use 'dask' for a local cluster"
        ) from exc


def run_blocks_dask(run: BlockRun) -> str:
    """Compute ``run.todo`` blocks as dask tasks (see the module doc); returns ``"dask"``."""
    from tiler.run import BlockProgress, kernels_for, wait_blocks

    loc, opts, grid, params = run.loc, run.opts, run.grid, run.params
    if not loc.can_share_with_processes:
        raise SchedulerError(
            f"dask workers cannot write into {loc.url!r} (process memory or a Store object); "
            "use a path on a file system every worker sees, or an object-store URL"
        )
    import distributed

    from tiler.run import process_count  # (tiler.run imports this module lazily too)

    n = process_count(opts.n_workers, len(run.todo)) if opts.scheduler == "dask" else 0
    client, cluster = _connect(opts.scheduler, n)
    job = DaskJob(
        token=uuid.uuid4().hex,
        src=run.src,
        band=opts.band,
        target=loc.for_workers(),
        grid=grid,
        params=params,
        gdal_cache_mb=opts.gdal_cache_mb,
        kernels_backend=kernels_for(grid),
    )
    progress = BlockProgress(loc.for_workers(), run)
    pending: set[Any] = set()
    block_of: dict[str, tuple[int, int]] = {}
    it = iter(run.todo)

    def submit_more() -> None:
        threads = max(1, sum(client.nthreads().values()))
        while len(pending) < IN_FLIGHT_PER_THREAD * threads:
            b = next(it, None)
            if b is None:
                return
            fut = client.submit(
                run_block_task,
                job,
                *b,
                key=f"terrastream-block-{b[0]}-{b[1]}-{job.token}",
                retries=opts.retries,
                pure=False,
            )
            block_of[fut.key] = b
            pending.add(fut)

    def collect(finished: set[Any], *, final: bool = False) -> None:
        progress.add([block_of[f.key] for f in finished if f.status == "finished"], final=final)

    def wait(fs: set[Any], timeout: float) -> set[Any]:
        try:
            return set(distributed.wait(fs, timeout=timeout, return_when="FIRST_COMPLETED").done)
        except TimeoutError:  # distributed.wait raises where concurrent.futures returns none
            return set()

    with DeferredInterrupt() as interrupt:  # Ctrl-C is raised between waits (tiler.interrupt)
        try:
            submit_more()
            while pending:
                finished = wait_blocks(wait, pending, interrupt)
                pending -= finished
                collect(finished)
                for fut in finished:
                    if fut.status != "finished":
                        br, bc = block_of[fut.key]
                        exc = fut.exception() if fut.status == "error" else None
                        if isinstance(exc, SourceError):  # the source's data: a rerun fails alike
                            raise exc
                        why = f"{type(exc).__name__}: {exc}" if exc is not None else fut.status
                        raise BlockFailedError(
                            f"block ({br}, {bc}) failed on every try ({opts.retries} "
                            f"retries): {why}; the store is kept unfinished: rerun to resume "
                            "(finished blocks are kept)",
                            (br, bc),
                        ) from exc
                submit_more()
                run.lease.check()
        except BaseException:
            if pending:
                client.cancel(list(pending))
            collect({f for f in pending if f.status == "finished"}, final=True)  # stay done
            raise
        finally:
            progress.flush()
            client.close()
            if cluster is not None:
                cluster.close()
    return "dask"
