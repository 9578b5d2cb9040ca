"""Tiling on a dask cluster: byte-identical to the local run, retries, a killed worker, resume.

Every cluster is started and stopped inside the test, on loopback only.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.demtools import fractal, write_dem
from tests.tiler.storetools import diff_stores
from tiler import tile as tile_mod
from tiler.errors import BlockFailedError, SchedulerError
from tiler.tile import TileOptions, tile

distributed = pytest.importorskip("distributed")
import dask  # noqa: E402  (installed with distributed)

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _dem(tmp_path: Path, shape=(150, 170), nodata=True) -> Path:
    data = fractal(shape, seed=7)
    if nodata:
        data[10:40, 60:95] = -9999  # a hole across block borders
        data[-5:, :7] = -9999
    return write_dem(tmp_path / "dem.tif", data, nodata=-9999 if nodata else None)


def _reference(src: Path, dst: Path, block: int) -> Path:
    tile(src, dst, TileOptions(block_size=block, workers=1, executor="threads"))
    return dst


@pytest.fixture(scope="module")
def thread_cluster():
    """An in-process cluster (2 workers x 2 threads, loopback)."""
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=2,
        processes=False,
        protocol="tcp",
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    ) as cluster:
        yield cluster


@pytest.mark.parametrize("block", [17, 33])
def test_dask_equals_local_run(tmp_path, thread_cluster, block):
    src = _dem(tmp_path)
    ref = _reference(src, tmp_path / "ref.zarr", block)
    out = tmp_path / "dask.zarr"
    seen = []
    store = tile(
        src,
        out,
        TileOptions(block_size=block, scheduler=thread_cluster.scheduler_address),
        progress=seen.append,
    )
    assert store.tile_summary.executor == "dask"
    assert diff_stores(ref, out) == []
    total = store.grid.rows * store.grid.cols
    assert seen[-1].blocks_done == seen[-1].blocks_total == total
    assert [p.blocks_done for p in seen] == sorted(p.blocks_done for p in seen)
    assert store.meta.complete


def test_dask_worker_processes_equal_local_run(tmp_path):
    """Real worker processes (spawned, own source datasets), float DEM with NaN holes."""
    data = fractal((90, 120), seed=3, dtype="float32")
    data[5:30, 40:70] = np.nan
    src = write_dem(tmp_path / "f.tif", data, nodata=float("nan"))
    ref = _reference(src, tmp_path / "ref.zarr", 33)
    out = tmp_path / "dask.zarr"
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    ) as cluster:
        store = tile(src, out, TileOptions(block_size=33, scheduler=cluster.scheduler_address))
    assert store.tile_summary.executor == "dask"
    assert diff_stores(ref, out) == []


_FAILED_ONCE: set[tuple[int, int]] = set()
_FAIL_LOCK = threading.Lock()


def _fail_once(window, params):
    """process_block that raises the first time it sees each block of row 1."""
    key = (int(window.sum()), window.shape)
    with _FAIL_LOCK:
        first = key not in _FAILED_ONCE
        _FAILED_ONCE.add(key)
    if first and int(window[0, 0]) % 2 == 0:
        raise OSError(f"transient read error (test) {key}")
    return _ORIGINAL(window, params)


_ORIGINAL = tile_mod.process_block


def test_failed_task_is_retried(tmp_path, thread_cluster, monkeypatch):
    src = _dem(tmp_path, nodata=False)
    ref = _reference(src, tmp_path / "ref.zarr", 33)
    _FAILED_ONCE.clear()
    monkeypatch.setattr(tile_mod, "process_block", _fail_once)
    out = tmp_path / "dask.zarr"
    tile(src, out, TileOptions(block_size=33, scheduler=thread_cluster.scheduler_address))
    assert _FAILED_ONCE, "the fault was never injected"
    assert diff_stores(ref, out) == []


def test_persistent_failure_names_the_block(tmp_path, thread_cluster, monkeypatch):
    src = _dem(tmp_path, nodata=False)
    calls = []

    def always_fail_block_1_2(window, params):
        if window.shape == (33, 33) and len(calls) < 1000:
            calls.append(1)
        raise OSError("disk on fire (test)")

    monkeypatch.setattr(tile_mod, "process_block", always_fail_block_1_2)
    opts = TileOptions(block_size=33, scheduler=thread_cluster.scheduler_address, retries=1)
    with pytest.raises(BlockFailedError, match=r"block \(\d+, \d+\) failed on every try") as ei:
        tile(src, tmp_path / "dask.zarr", opts)
    assert "disk on fire" in str(ei.value) and ei.value.block is not None
    assert len(calls) >= 2  # one try and one retry at least
    from tiler.location import Location
    from tiler.store import read_meta

    meta = read_meta(Location(str(tmp_path / "dask.zarr")).open_group("r"))
    assert not meta.complete and meta.extra["state"] == "tiling"


def _journal_entries(store: Path) -> int:
    """Journal entries written whole: chunk files ``c.<row>.<col>.0``, not the
    ``c.<row>.<col>.<uuid>.partial`` temporary file zarr leaves when a worker is killed in the
    middle of its write (``pathlib.Path.with_suffix`` of the key)."""
    from tiler.resume import JOURNAL

    base = store / JOURNAL
    if not base.exists():
        return 0
    return sum(
        1 for p in base.iterdir() if p.is_file() and re.fullmatch(r"c\.\d+\.\d+\.\d+", p.name)
    )


@pytest.mark.long_series  # (the suite's siblings: the Ctrl-C resumes below, reliability kills)
def test_killed_worker_then_rerun_is_identical_and_skips_finished(tmp_path):
    """SIGKILL a worker process mid-run (no retry of lost tasks: allowed-failures=0), so the
    run fails naming a block; the rerun computes only the unfinished blocks, byte-identical."""
    data = fractal((300, 300), seed=11)
    src = write_dem(tmp_path / "dem.tif", data)
    ref = _reference(src, tmp_path / "ref.zarr", 17)
    out = tmp_path / "dask.zarr"
    with (
        dask.config.set({"distributed.scheduler.allowed-failures": 0}),
        distributed.LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address="127.0.0.1:0",
        ) as cluster,
    ):
        with distributed.Client(cluster) as c:
            pid_of = c.run(os.getpid)  # worker address -> pid
        killed, done = threading.Event(), threading.Event()

        def killer() -> None:
            """Once 12 blocks are journalled, SIGKILL a worker that is processing a block (an
            idle one fails nothing: its next task just goes elsewhere); again, another one, if
            its task had finished in between and the run goes on."""
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and _journal_entries(out) < 12:
                time.sleep(0.02)
            sched = cluster.scheduler  # in this process (the workers are not)
            while pid_of and not done.is_set() and time.monotonic() < deadline:
                try:  # the scheduler's own state, read from this thread: retry a torn read
                    busy = [a for a, w in list(sched.workers.items()) if w.processing]
                except RuntimeError:
                    continue
                busy = [a for a in busy if a in pid_of]
                if not busy:
                    time.sleep(0.005)
                    continue
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid_of.pop(busy[0]), signal.SIGKILL)
                killed.set()
                done.wait(2.0)

        t = threading.Thread(target=killer, name="test-killer", daemon=True)
        t.start()
        try:
            with pytest.raises(BlockFailedError, match="KilledWorker|failed on every try"):
                tile(src, out, TileOptions(block_size=17, scheduler=cluster.scheduler_address))
        finally:
            done.set()
        t.join(timeout=10)
        assert killed.is_set()
    at_failure = _journal_entries(out)
    assert at_failure >= 12
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    ) as cluster:
        store = tile(src, out, TileOptions(block_size=17, scheduler=cluster.scheduler_address))
    s = store.tile_summary
    assert s.resumed and s.blocks_skipped >= at_failure > 0
    assert s.blocks_computed == s.blocks_total - s.blocks_skipped
    assert diff_stores(ref, out) == []


def test_scheduler_spec_checked(tmp_path):
    with pytest.raises(SchedulerError, match="'fast'"):
        TileOptions(scheduler="fast")
    src = _dem(tmp_path)
    with pytest.raises(SchedulerError, match="cannot be written|cannot write"):
        tile(src, "memory://x.zarr", TileOptions(block_size=33, scheduler="inproc://nowhere"))


def test_unreachable_scheduler_is_a_clear_error(tmp_path, monkeypatch):
    from tiler import dask_run

    monkeypatch.setattr(dask_run, "CONNECT_TIMEOUT_S", 2.0)  # (20 s for users)
    src = _dem(tmp_path)
    with pytest.raises(SchedulerError, match="cannot reach the dask scheduler"):
        tile(src, tmp_path / "o.zarr", TileOptions(block_size=33, scheduler="tcp://127.0.0.1:9"))
    # nothing was computed: no unfinished store is left that a rerun would be told to resume
    # (it was, in state 'tiling')
    assert not (tmp_path / "o.zarr").exists()


def test_distributed_not_imported_for_local_runs(tmp_path):
    import subprocess

    src = _dem(tmp_path)
    code = (
        "import sys; from tiler.tile import tile, TileOptions; "
        f"tile({str(src)!r}, {str(tmp_path / 'l.zarr')!r}, TileOptions(block_size=33, "
        "workers=1)); print('distributed' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip().splitlines()[-1] == "False"


def test_cli_scheduler_option(tmp_path, thread_cluster):
    from typer.testing import CliRunner

    from cli.main import app

    src = _dem(tmp_path)
    ref = _reference(src, tmp_path / "ref.zarr", 33)
    out = tmp_path / "cli.zarr"
    args = ["tile", str(src), str(out), "--block-size", "33", "--json"]
    r = CliRunner().invoke(app, [*args, "--scheduler", thread_cluster.scheduler_address])
    assert r.exit_code == 0, r.output
    assert diff_stores(ref, out) == []
    r = CliRunner().invoke(app, [*args[:2], str(tmp_path / "x.zarr"), "--scheduler", "fast"])
    assert r.exit_code == 2 and "'fast'" in r.output


def test_ctrl_c_with_worker_processes_prints_one_line(tmp_path):
    """SIGINT to the whole process group (what a terminal's Ctrl-C does): worker processes
    ignore it, so the run ends with the CLI's one line and exit 130, no worker tracebacks."""
    import subprocess

    data = fractal((400, 400), seed=2)
    src = write_dem(tmp_path / "dem.tif", data)
    out = tmp_path / "o.zarr"
    env = dict(os.environ, PYTHONPATH=os.getcwd(), TERRASTREAM_KERNELS="numpy")
    # the console script (see tests/reliability/test_interrupts.py for why not python -m)
    cmd = [str(Path(sys.executable).with_name("terrastream")), "tile", str(src), str(out)]
    cmd += ["--block-size", "17"]
    cmd += ["--workers", "2", "--scheduler", "processes"]
    p = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and _journal_entries(out) < 5 and p.poll() is None:
            time.sleep(0.05)
        assert p.poll() is None, "the run ended before it could be interrupted"
        os.killpg(p.pid, signal.SIGINT)
        try:
            _, err = p.communicate(timeout=60)
        except subprocess.TimeoutExpired as exc:
            pytest.fail(f"still running 60 s after Ctrl-C (hung); stderr: {exc.stderr!r}")
    finally:  # a hung run must not leak its processes into the next tests
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    assert p.returncode == 130, err
    assert "interrupted" in err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err


def test_scheduler_dask_starts_and_stops_a_local_cluster(tmp_path):
    import psutil

    def workers() -> set:
        return {p for p in psutil.Process().children(recursive=True) if "spawn_main" in " ".join(
            p.cmdline())}  # fmt: skip

    before = workers()  # (not this test's: a worker left by another test is its own failure)
    src = _dem(tmp_path)
    ref = _reference(src, tmp_path / "ref.zarr", 65)
    out = tmp_path / "d.zarr"
    store = tile(src, out, TileOptions(block_size=65, workers=1, scheduler="dask"))
    assert store.tile_summary.executor == "dask"
    assert diff_stores(ref, out) == []
    left = list(workers() - before)
    _, alive = psutil.wait_procs(left, timeout=30)  # the cluster's worker processes exit
    assert not alive


@pytest.mark.parametrize("scheduler", ["threads", "dask"])
def test_ctrl_c_in_process_raises_tiling_interrupted_and_resumes(
    tmp_path, thread_cluster, scheduler
):
    """SIGINT to this process while tile() waits for its workers (tiler.interrupt): it raises
    TilingInterrupted between waits, the workers stop, SIGINT's handler is put back, and the
    rerun gives the uninterrupted store (worker threads and a dask cluster)."""
    from tiler.errors import TilingInterrupted

    src = _dem(tmp_path, shape=(200, 200), nodata=False)  # 13 x 13 blocks
    ref = _reference(src, tmp_path / "ref.zarr", 17)
    out = tmp_path / "o.zarr"
    spec = thread_cluster.scheduler_address if scheduler == "dask" else "threads"
    opts = TileOptions(block_size=17, workers=2, scheduler=spec)
    stop = threading.Event()

    def ctrl_c() -> None:
        while not stop.is_set() and _journal_entries(out) < 3:
            time.sleep(0.01)
        if not stop.is_set():
            os.kill(os.getpid(), signal.SIGINT)

    t = threading.Thread(target=ctrl_c, name="test-ctrl-c")
    t.start()
    try:
        with pytest.raises(TilingInterrupted):
            tile(src, out, opts)
    finally:
        stop.set()
        t.join(10)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert 3 <= _journal_entries(out) < 169
    tile(src, out, opts)
    assert diff_stores(ref, out) == []


@pytest.mark.parametrize("scheduler", ["threads", "dask"])
def test_no_block_finished_within_the_timeout_is_a_store_error(
    tmp_path, thread_cluster, scheduler, monkeypatch
):
    """Workers that never finish a block: a StoreError naming the timeout (with dask too, whose
    wait raises TimeoutError where concurrent.futures returns no future)."""
    from tiler import dask_run
    from tiler import run as run_mod
    from tiler.errors import StoreError

    def stuck(*args):
        time.sleep(3)  # 3 x the timeout; then the pool can shut down
        raise RuntimeError("a block slower than the timeout")

    monkeypatch.setattr(run_mod, "WAIT_TIMEOUT_S", 1.0)
    monkeypatch.setattr(dask_run, "run_block_task", stuck)
    monkeypatch.setattr(run_mod.BlockWorker, "run", stuck)
    spec = thread_cluster.scheduler_address if scheduler == "dask" else "threads"
    src = _dem(tmp_path, shape=(60, 60), nodata=False)
    with pytest.raises(StoreError, match="no block finished within 1 s"):
        tile(src, tmp_path / "o.zarr", TileOptions(block_size=17, workers=2, scheduler=spec))


@pytest.mark.parametrize("user_level", [None, "info"])
def test_the_cli_keeps_dask_quiet_unless_asked(tmp_path, user_level):
    """`tile --scheduler dask` printed ~30 "INFO distributed..." lines, under -q too; the
    control: a user's DASK_LOGGING__DISTRIBUTED=info still gets them (so the check can fire)."""
    import subprocess

    src = _dem(tmp_path, shape=(60, 50))
    env = {k: v for k, v in os.environ.items() if k != "DASK_LOGGING__DISTRIBUTED"}
    if user_level:
        env["DASK_LOGGING__DISTRIBUTED"] = user_level
    args = ["-q", "tile", str(src), str(tmp_path / "s.zarr"), "--block-size", "33"]
    run = subprocess.run(
        [sys.executable, "-m", "cli.main", *args, "--scheduler", "dask", "--workers", "1"],
        capture_output=True, text=True, timeout=240, env=env,
        cwd=Path(__file__).resolve().parents[2],
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    noisy = "INFO distributed" in run.stderr
    assert noisy == bool(user_level), run.stderr[-2000:]


def test_a_source_error_in_a_task_is_raised_as_itself(tmp_path):
    """A block whose source samples are refused (HeightRangeError) failed as "block (0, 0)
    failed on every try ... rerun to resume", which a rerun cannot; the source's own error is
    raised now (the control, a task failure of another kind, stays a BlockFailedError: above)."""
    from tiler.errors import HeightRangeError

    data = fractal((60, 50), 3, dtype="float32")
    data[20, 30] = -3.4e38
    src = write_dem(tmp_path / "und.tif", data)
    opts = TileOptions(block_size=33, scheduler="dask", workers=1, retries=0)
    with pytest.raises(HeightRangeError, match=r"und\.tif, block \(0, 0\), first at row 20"):
        tile(src, tmp_path / "s.zarr", opts)
