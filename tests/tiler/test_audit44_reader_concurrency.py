"""One ``TerrainStore`` shared by many threads (and a forked child) reads what one thread reads.

Each detector has its positive control beside it: the per-thread decode buffers made one
shared buffer (the threads' reads then mix), a forked child using the parent's zarr store, a
read racing a repair seen by another thread without the re-read, a read across a directory
swap without the change check.
"""

from __future__ import annotations

import multiprocessing as mp
import random
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import google_crc32c
import numpy as np
import pytest
from demtools import fractal, write_dem
from rangeserver import LoopbackServer

import tiler.store as store_mod
from tiler import chunkread, kernels, scratch
from tiler.errors import ChunkChecksumError, StoreChangedError
from tiler.store import TerrainStore, open_store
from tiler.tile import TileOptions, tile

THREADS = 16


@pytest.fixture(scope="module")
def stores(tmp_path_factory) -> Path:
    """``int16.zarr`` and ``float32.zarr`` (65², 4x4 blocks of 17², k = 4) in one folder."""
    root = tmp_path_factory.mktemp("audit44_conc")
    for dt in ("int16", "float32"):
        src = write_dem(root / f"{dt}.tif", fractal((65, 65), 5, dtype=dt))
        tile(src, root / f"{dt}.zarr", TileOptions(block_size=17, workers=1))
    return root


def _jobs(s: TerrainStore) -> list[tuple]:
    out = []
    for b in s.blocks():
        for level in range(s.k + 1):
            rows, cols = s.block_extent(b, level)
            out += [("block", b, level), ("extent", b, level, (max(1, rows - 1), cols))]
            out += [("levels", b, level), ("raw", b, level)]
        out += [("mask", b), ("errors", b)]
    return out


def _run(s: TerrainStore, job: tuple):
    """The read ``job`` names, its result kept as returned (no copy: a result that shares
    a reused buffer with a later read shows up as changed)."""
    kind, b = job[0], job[1]
    if kind == "block":
        return s.read_block(b, job[2])
    if kind == "extent":
        return s.read_block(b, job[2], extent=job[3])
    if kind == "levels":
        return s.read_levels(b, job[2])
    if kind == "raw":
        return s.read_level_raw(b, job[2])
    if kind == "mask":
        return s.read_mask(b)
    return s.read_errors(b)


def _same(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[x], b[x]) for x in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)


def _copy(v):
    if isinstance(v, dict):
        return {x: _copy(y) for x, y in v.items()}
    if isinstance(v, list):
        return [_copy(x) for x in v]
    return np.array(v, copy=True)


def _mixed_reads(s: TerrainStore, truth: list, jobs: list[tuple], reps: int = 2) -> list[tuple]:
    """The jobs whose result, read by ``THREADS`` threads at once in random order, differs
    from the one-thread read ``truth``."""
    rng = random.Random(4)
    bad = []
    for _ in range(reps):
        order = list(range(len(jobs)))
        rng.shuffle(order)
        with ThreadPoolExecutor(THREADS, thread_name_prefix="audit44-read") as pool:
            got = list(pool.map(lambda i: (i, _run(s, jobs[i])), order))
        bad += [jobs[i] for i, v in got if not _same(truth[i], v)]
    return bad


def _shared_scratch(monkeypatch) -> None:
    """The positive control: one decode buffer for every thread (not per thread)."""
    seq, grid = {}, {}

    def buffer(n, dtype):
        key = np.dtype(dtype).str
        if key not in seq:
            seq[key] = np.empty(scratch.SCRATCH_MAX_BYTES // np.dtype(dtype).itemsize, dtype)
        return seq[key][:n]

    def square(side, dtype):
        key = np.dtype(dtype).str
        if key not in grid or grid[key].size < side * side:
            grid[key] = np.empty(side * side, dtype)
        return grid[key][: side * side].reshape(side, side)

    monkeypatch.setattr(scratch, "buffer", buffer)
    monkeypatch.setattr(scratch, "square", square)


@pytest.mark.parametrize("where", ["local", "http"])
@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize("dt", ["int16", "float32"])
def test_threads_sharing_a_store_read_what_one_thread_reads(
    stores, monkeypatch, where, backend, dt
):
    monkeypatch.setenv(kernels.ENV, backend)
    if backend == "numba" and kernels.active() is None:
        pytest.skip("numba is not installed")
    local = open_store(stores / f"{dt}.zarr")
    jobs = _jobs(local)
    truth = [_copy(_run(local, j)) for j in jobs]
    if where == "local":
        assert _mixed_reads(open_store(stores / f"{dt}.zarr"), truth, jobs) == []
        return
    with LoopbackServer(stores, latency_s=0.001) as url:
        assert _mixed_reads(open_store(f"{url}/{dt}.zarr"), truth, jobs, reps=1) == []


def test_control_a_shared_decode_buffer_mixes_the_threads_reads(stores, monkeypatch):
    old = sys.getswitchinterval()
    try:
        _shared_scratch(monkeypatch)
        sys.setswitchinterval(1e-5)  # (switch threads often: the mix shows on every run)
        s = open_store(stores / "int16.zarr")
        jobs = [j for j in _jobs(s) if j[0] in ("block", "extent")]
        truth = [_copy(_run(s, j)) for j in jobs]
        assert _mixed_reads(s, truth, jobs, reps=3) != []  # the detector fires
    finally:
        sys.setswitchinterval(old)


def _fork_child(q, s: TerrainStore, blocks: list) -> None:
    try:
        s.check_unchanged(force=True)
        got = [s.read_block(b) for b in blocks] + [s.read_mask(b) for b in blocks]
        q.put(("ok", got))
    except BaseException as exc:  # reported to the parent
        q.put(("error", f"{type(exc).__name__}: {exc}"))


@pytest.mark.parametrize("fixed", [True, False], ids=["reopened", "control-parents-store"])
def test_a_remote_store_used_in_a_forked_child_reads_its_blocks(stores, monkeypatch, fixed):
    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork on this platform")
    if not fixed:
        monkeypatch.setattr(TerrainStore, "_in_process", lambda self: None)
    with LoopbackServer(stores) as url:
        s = open_store(f"{url}/int16.zarr")
        blocks = s.blocks()[:4]
        truth = [s.read_block(b) for b in blocks] + [s.read_mask(b) for b in blocks]
        ctx = mp.get_context("fork")
        q = ctx.Queue()
        p = ctx.Process(target=_fork_child, args=(q, s, blocks), name="audit44-fork")
        p.start()
        try:
            kind, got = q.get(timeout=30)
        finally:
            p.join(timeout=10)
            if p.is_alive():
                p.kill()
    if fixed:
        assert kind == "ok", got
        assert all(_same(a, b) for a, b in zip(truth, got, strict=True))
    else:  # the parent's zarr store in the child: its event loop is gone
        assert kind == "error" and "different loop" in got, got


def _drop_inner_chunk(shard: Path, n_inner: int) -> int:
    """Remove the first inner chunk (on disk) of a shard, compacting the rest (as
    tests/tiler/test_repair_remote_reader.py); returns the next chunk's inner index."""
    data = shard.read_bytes()
    n_idx = n_inner * 16 + 4
    idx = np.frombuffer(data[-n_idx:-4], "<u8").reshape(-1, 2).copy()
    order = [int(i) for i in np.argsort(idx[:, 0])]
    out, new = bytearray(), np.full_like(idx, np.iinfo(np.uint64).max)
    for i in order[1:]:
        off, nb = (int(v) for v in idx[i])
        new[i] = (len(out), nb)
        out += data[off : off + nb]
    body = new.astype("<u8").tobytes()
    shard.write_bytes(bytes(out) + body + google_crc32c.value(body).to_bytes(4, "little"))
    return order[1]


@pytest.mark.parametrize("fixed", [True, False], ids=["read-again", "control-stale-index"])
def test_a_read_across_a_repair_another_thread_saw_is_not_another_blocks(
    tmp_path, monkeypatch, fixed
):
    """Thread A reads block C with the shard index it kept; while its chunk request is under
    way, the store is repaired (block B put back, C's chunk moved) and thread B sees it
    (``check_unchanged``: the kept indexes dropped). A's answer is the chunk now at C's old
    offset: block B's, whose crc32c passes. It must not be returned as C's."""
    src = write_dem(tmp_path / "dem.tif", fractal((65, 65), 3))
    s = tile(src, tmp_path / "s.zarr", TileOptions(block_size=17, workers=1)).location.path
    ref = tmp_path / "ref.zarr"
    tile(src, ref, TileOptions(block_size=17, workers=1))
    rows, cols = open_store(s).grid.shape
    c = divmod(_drop_inner_chunk(s / "levels/0/c/0/0/0", rows * cols), cols)
    truth = open_store(ref).read_level_raw(c, 0)
    monkeypatch.setattr(store_mod, "REMOTE_CHECK_INTERVAL_S", 1e9)  # (checked when asked)
    if not fixed:
        monkeypatch.setattr(TerrainStore, "_unrepaired", lambda self, block, fetch: fetch())
    srv = LoopbackServer(tmp_path)
    with srv as url:
        reader = open_store(f"{url}/s.zarr")
        assert np.array_equal(reader.read_level_raw(c, 0), truth)  # (its index is kept)
        tile(src, s, TileOptions(block_size=17, workers=1, repair=True))
        arrived, go = threading.Event(), threading.Event()
        base = srv.handler._faulty

        def faulty(handler) -> bool:  # hold thread A's chunk request until B has seen it
            if "/levels/0/c/" in handler.path and handler.headers.get("Range", "")[6:7] != "-":
                arrived.set()
                go.wait(timeout=20)
            return base(handler)

        monkeypatch.setattr(srv.handler, "_faulty", faulty)
        got: list = []
        a = threading.Thread(
            target=lambda: got.append(reader.read_level_raw(c, 0)), name="audit44-reader-a"
        )
        a.start()
        assert arrived.wait(timeout=20)
        reader.check_unchanged(force=True)  # thread B sees the repair: indexes dropped
        go.set()
        a.join(timeout=20)
    assert got, "thread A's read did not finish"
    if fixed:
        assert np.array_equal(got[0], truth)
    else:  # the control: A returned the chunk now at C's old offset (block B's)
        assert not np.array_equal(got[0], truth)


def _flip_inner(shard: Path, n_inner: int, inner: int) -> None:
    """Flip a byte in the middle of inner chunk ``inner`` of a shard (its crc32c then fails)."""
    data = bytearray(shard.read_bytes())
    idx = np.frombuffer(bytes(data[-(n_inner * 16 + 4) : -4]), "<u8").reshape(-1, 2)
    off, nbytes = (int(v) for v in idx[inner])
    data[off + nbytes // 2] ^= 0xFF
    shard.write_bytes(bytes(data))


@pytest.mark.parametrize("where", ["local", "http"])
def test_errors_raised_in_threads_name_their_own_block(tmp_path, where):
    """Two damaged chunks (an unsharded level-6 chunk of one block, a sharded level-2 inner
    chunk of another); 16 threads read every block at every level: each damaged read raises
    naming its own block and level, every other read returns the one-thread values."""
    src = write_dem(tmp_path / "dem.tif", fractal((129, 129), 7))
    path = tile(src, tmp_path / "s.zarr", TileOptions(block_size=65, workers=1)).location.path
    s = open_store(path)
    assert s.k == 6 and s.grid.shape == (2, 2)
    truth = {(b, lv): s.read_block(b, lv) for b in s.blocks() for lv in range(s.k + 1)}
    chunk = path / "levels/6/c/0/1/0"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    _flip_inner(path / "levels/2/c/0/0/0", 4, 2)  # block (1, 0)
    damaged = {(0, 1): 6, (1, 0): 2}
    jobs = list(truth) * 6
    random.Random(2).shuffle(jobs)

    def read(job):
        try:
            return job, reader.read_block(*job)
        except ChunkChecksumError as exc:
            return job, exc

    def check() -> list:
        wrong = []
        with ThreadPoolExecutor(THREADS, thread_name_prefix="audit44-read") as pool:
            for (b, lv), got in pool.map(read, jobs):
                bad_level = damaged.get(b)
                if bad_level is not None and lv >= bad_level:
                    ok = isinstance(got, ChunkChecksumError) and (got.block, got.level) == (
                        b,
                        bad_level,
                    )
                    ok = ok and f"block {b}" in str(got)
                else:
                    ok = not isinstance(got, Exception) and np.array_equal(got, truth[(b, lv)])
                if not ok:
                    wrong.append((b, lv, got))
        return wrong

    if where == "local":
        reader = open_store(path)
        assert check() == []
        return
    with LoopbackServer(tmp_path, latency_s=0.001) as url:
        reader = open_store(f"{url}/s.zarr")
        assert check() == []


@pytest.mark.parametrize("fixed", [True, False], ids=["checked", "control-unchecked"])
def test_a_read_across_a_directory_swap_is_old_or_new_whole_or_refused(
    tmp_path, monkeypatch, fixed
):
    """``tile --overwrite`` swaps the store's directory at its end; a read_block whose first
    levels came from the old store and the rest from the new one must raise
    StoreChangedError, never return the mix (the control: without the change check it does)."""
    old = write_dem(tmp_path / "a.tif", fractal((65, 65), 1))
    new = write_dem(tmp_path / "b.tif", fractal((65, 65), 2))
    path = tile(old, tmp_path / "s.zarr", TileOptions(block_size=17, workers=1)).location.path
    other = tile(new, tmp_path / "n.zarr", TileOptions(block_size=17, workers=1)).location.path
    block = (1, 2)
    before, after = open_store(path).read_block(block), open_store(other).read_block(block)
    reader = open_store(path)
    real = chunkread.read_local
    calls = []

    def swapping(root, spec, blk, out=None):  # the swap lands between levels 2 and 3
        if spec.name == "levels/3" and not calls:
            calls.append(1)
            path.rename(tmp_path / "s.old")
            other.rename(path)
        return real(root, spec, blk, out)

    monkeypatch.setattr(chunkread, "read_local", swapping)
    if not fixed:
        monkeypatch.setattr(TerrainStore, "check_unchanged", lambda self, force=False: None)
        got = reader.read_block(block)
        assert not np.array_equal(got, before) and not np.array_equal(got, after)  # a mix
        return
    with pytest.raises(StoreChangedError):
        reader.read_block(block)
    with pytest.raises(StoreChangedError):  # and every later read
        reader.read_block((0, 0))


def test_threads_reading_across_real_overwrites_get_old_or_new_blocks(tmp_path):
    """4 threads read one store while ``tile --overwrite`` replaces it: every block read is
    one build's whole, or a StoreChangedError (then the thread reopens)."""
    dems = [write_dem(tmp_path / f"{i}.tif", fractal((65, 65), 10 + i)) for i in range(2)]
    builds = []
    for i, d in enumerate(dems):
        s = tile(d, tmp_path / f"b{i}.zarr", TileOptions(block_size=17, workers=1))
        builds.append({(b, lv): s.read_block(b, lv) for b in s.blocks() for lv in range(s.k + 1)})
    path = tmp_path / "s.zarr"
    tile(dems[0], path, TileOptions(block_size=17, workers=1))
    keys = list(builds[0])
    stop, wrong, changed, reads = threading.Event(), [], [], [0]

    def reader(i: int) -> None:
        s = open_store(path)
        rng = random.Random(i)
        while not stop.is_set():
            key = rng.choice(keys)
            try:
                got = s.read_block(*key)
            except StoreChangedError:
                changed.append(i)
                s = open_store(path)
                continue
            reads[0] += 1
            if not any(np.array_equal(got, b[key]) for b in builds):
                wrong.append(key)
            time.sleep(0.001)  # (leave the writer some of the GIL)

    threads = [
        threading.Thread(target=reader, args=(i,), name=f"audit44-reader-{i}") for i in range(4)
    ]
    for t in threads:
        t.start()
    try:
        time.sleep(0.1)
        tile(dems[1], path, TileOptions(block_size=17, workers=1, overwrite=True))
        time.sleep(0.1)
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=10)
    assert wrong == []
    assert changed and reads[0] > 0  # (the readers did read across the swaps)


@pytest.mark.parametrize("fixed", [True, False], ids=["its-build", "control-url-now"])
def test_a_dataarray_of_a_rewritten_store_object_is_refused_not_the_new_build(
    tmp_path, monkeypatch, fixed
):
    """``level_dataarray(store)`` (and ``open_dataset(store)``) of a store object whose
    directory ``tile --overwrite`` has rebuilt since: its reads raise StoreChangedError, as
    ``store.read_block`` does; the arrays read the build the object holds, not the new one
    under the object's coordinates (the control: reading what the URL holds now)."""
    import xarray as xr

    import tiler.xarray_backend as xb

    a = write_dem(tmp_path / "a.tif", fractal((65, 65), 1))
    b = write_dem(tmp_path / "b.tif", fractal((65, 65), 2))
    path = tile(a, tmp_path / "s.zarr", TileOptions(block_size=17, workers=1)).location.path
    old = open_store(path)
    tile(b, path, TileOptions(block_size=17, workers=1, overwrite=True))
    if not fixed:
        monkeypatch.setattr(xb, "_build", lambda store: xb._NOW)
        monkeypatch.setattr(xb, "_opened", lambda obj: xb._cached_store(xb._url(obj)))
        got = xb.level_dataarray(old).values  # the new build's heights, no error
        new = open_store(path).read_block((0, 0))
        assert np.array_equal(got[:17, :17], new.astype(got.dtype))
        return
    with pytest.raises(StoreChangedError):
        _ = xb.level_dataarray(old).values
    with pytest.raises(StoreChangedError):
        _ = xr.open_dataset(old, engine="terrastream", chunks={}).height.values


def test_dask_fork_processes_compute_a_remote_level_as_one_thread_does(stores):
    """Dask's process scheduler with fork: the workers inherit the backend's open stores
    (tiler.xarray_backend) and read through them; they equal the synchronous compute."""
    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork on this platform")
    import dask
    import xarray as xr

    with LoopbackServer(stores) as url:
        ds = xr.open_dataset(f"{url}/int16.zarr", engine="terrastream", level=3, chunks={})
        serial = ds.height.compute(scheduler="synchronous").values
        with dask.config.set({"multiprocessing.context": "fork"}):
            forked = ds.height.compute(scheduler="processes", num_workers=2).values
    assert np.array_equal(serial, forked, equal_nan=True)
