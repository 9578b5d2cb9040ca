"""SIGKILL ``tile`` at random moments; every rerun gives a byte-identical store and skips the
blocks that were finished at the kill (their journal entries), recomputing only the rest.

3 kills in the normal run, 24 with ``TERRASTREAM_RELIABILITY_LONG=1`` (half of them with worker
processes, killed with their whole process group), fixed seed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import zarr
from demtools import fractal, write_dem
from faults import LONG, SEED, record
from storetools import diff_stores  # after faults (sys.path)

from tiler.resume import JOURNAL, done_blocks
from tiler.store import read_meta
from tiler.tile import TileOptions, tile

pytestmark = pytest.mark.reliability
SHAPE = (200, 200)  # 13 x 13 blocks of 17²
KILLS = 24 if LONG else 3

SCRIPT = textwrap.dedent(
    """
    import sys
    from tiler.tile import TileOptions, tile

    if __name__ == "__main__":
        tile(sys.argv[1], sys.argv[2],
             TileOptions(block_size=17, workers=2, executor=sys.argv[3]))
    """
)


def _journal_done(path) -> tuple[str, int]:
    """(state, blocks whose journal entry is intact) of a killed store."""
    if not (path / "zarr.json").exists():
        return "absent", 0
    try:
        g = zarr.open_group(path, mode="r")
        meta = read_meta(g)
    except Exception:  # noqa: BLE001 - a half-created root: recreated by the rerun
        return "damaged", 0
    state = meta.extra.get("state", "complete" if meta.complete else "?")
    if state == "tiling" and JOURNAL in g:
        return state, int(done_blocks(g[JOURNAL]).sum())
    return state, 0


def _run_whole(script, src, dst, executor, env) -> float:
    """Seconds one uninterrupted tiling subprocess takes, start-up included (the kill window)."""
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, str(script), str(src), str(dst), executor],
        env=env,
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        timeout=300,
    )
    return time.perf_counter() - t0


def test_random_kills_resume_byte_identical(tmp_path):
    src = write_dem(tmp_path / "dem.tif", fractal(SHAPE, 7))
    ref = tmp_path / "ref.zarr"
    tile(src, ref, TileOptions(block_size=17, workers=2, executor="threads"))
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    rng = np.random.default_rng(SEED)
    total = 13 * 13
    counts = {"injected": 0, "identical": 0, "lost": 0, "blocks_saved": 0, "blocks_redone": 0}
    window: dict[str, float] = {}  # executor -> measured whole-run seconds
    attempts = 0
    # A kill drawn inside the measured run time can still land after the store was finished (the
    # process tearing down, or a faster run): that is counted apart and another kill is drawn.
    while counts["injected"] < KILLS and attempts < 3 * KILLS:
        i = attempts
        attempts += 1
        dst = tmp_path / f"k{i}.zarr"
        executor = "processes" if LONG and i % 2 else "threads"
        if executor not in window:
            whole = tmp_path / f"whole-{executor}.zarr"
            window[executor] = _run_whole(script, src, whole, executor, env)
            assert diff_stores(whole, ref) == []
        delay = float(rng.uniform(0.1, 0.9)) * window[executor]
        proc = subprocess.Popen(
            [sys.executable, str(script), str(src), str(dst), executor],
            env=env,
            start_new_session=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            proc.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)
        else:
            counts["finished_before_kill"] = counts.get("finished_before_kill", 0) + 1
            assert diff_stores(dst, ref) == []
            continue
        state, saved = _journal_done(dst)
        if state == "complete":  # killed after the store was finished: nothing to resume
            counts["finished_before_kill"] = counts.get("finished_before_kill", 0) + 1
            assert diff_stores(dst, ref) == []
            continue
        counts["injected"] += 1
        resumed = tile(src, dst, TileOptions(block_size=17, workers=2, executor="threads"))
        s = resumed.tile_summary
        diff = diff_stores(dst, ref)
        assert diff == [], f"kill {i} at {delay:.2f} s ({state}): differs in {diff[:5]}"
        counts["identical"] += 1
        if state == "tiling":
            assert s.blocks_skipped == saved, (i, state, s)
            assert s.blocks_computed == total - saved
        counts["blocks_saved"] += s.blocks_skipped
        counts["blocks_redone"] += s.blocks_computed
    record("SIGKILL + rerun", **counts)
    assert counts["identical"] == counts["injected"] == KILLS, counts


def test_workers_end_with_a_killed_parent(tmp_path):
    """SIGKILL of a tiling with worker processes (the parent only, not its group): the workers
    end within seconds (they ran on for ever, reparented, blocked on their task pipe, ~100 MB
    each; ``tiler.parent_watch``). The control: they were running before the kill."""
    import psutil

    src = write_dem(tmp_path / "d.tif", fractal((1025, 1025), 4))
    script = tmp_path / "run.py"
    script.write_text(SCRIPT.replace("block_size=17", "block_size=65"))
    env = dict(os.environ, TERRASTREAM_KERNELS="numpy")  # (slow blocks: time to see them)
    p = subprocess.Popen([sys.executable, str(script), str(src), str(tmp_path / "s.zarr"),
                          "processes"], env=env, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        workers: list = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(workers) < 2:
            time.sleep(0.2)
            kids = psutil.Process(p.pid).children(recursive=True)
            workers = [c for c in kids if "spawn_main" in " ".join(c.cmdline())]
        assert len(workers) >= 2, "the tiling's worker processes did not start"
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=30)
    gone, alive = psutil.wait_procs(workers, timeout=10)
    for w in alive:  # (do not leak them when the check fails)
        w.kill()
    assert not alive, [w.pid for w in alive]
