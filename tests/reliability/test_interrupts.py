"""Ctrl-C (SIGINT to the whole process group, as a terminal sends it) to ``terrastream tile`` at
random moments of the run (after it has created the store): every run ends within a bounded time
with exit 130 and the CLI's one line, no traceback, and the rerun gives a byte-identical store.

A KeyboardInterrupt raised inside ``concurrent.futures``' locks once hung the interrupted run
with its workers alive (``tiler.interrupt``; its positive control is in
``tests/tiler/test_interrupt.py``). 4 interrupts in the normal run, 24 with
``TERRASTREAM_RELIABILITY_LONG=1``, alternating worker threads and processes, fixed seed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from demtools import fractal, write_dem
from faults import LONG, SEED, record
from storetools import diff_stores  # after faults (sys.path)

from tiler.tile import TileOptions, tile

pytestmark = pytest.mark.reliability
SHAPE = (200, 200)  # 13 x 13 blocks of 17²
INTERRUPTS = 24 if LONG else 4
#: an interrupted run ends by then (blocks in flight finish: milliseconds here)
END_WITHIN_S = 60


def _cmd(src, dst, executor: str) -> list[str]:
    # the console script users run (not ``python -m cli.main``: with -m, CPython 3.11 exits with
    # the signal itself, -2, once a KeyboardInterrupt has left any exec() of a string, as
    # dataclasses does while a module is imported, even when the CLI caught it)
    exe = Path(sys.executable).with_name("terrastream")
    return [str(exe), "tile", str(src), str(dst), "--block-size", "17", "--workers", "2",
            "--scheduler", executor]  # fmt: skip


def _start(cmd: list[str], env: dict, dst: Path) -> subprocess.Popen:
    """Start ``cmd`` in its own process group; return once it has created ``dst`` (or ended)."""
    p = subprocess.Popen(
        cmd, env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    started = time.monotonic()
    while not (dst / "zarr.json").exists() and p.poll() is None:
        if time.monotonic() - started > 120:
            os.killpg(p.pid, signal.SIGKILL)
            pytest.fail(f"{dst} never appeared: {p.communicate()[1]}")
        time.sleep(0.01)
    return p


def test_random_ctrl_c_exits_130_and_resumes_byte_identical(tmp_path):
    src = write_dem(tmp_path / "dem.tif", fractal(SHAPE, 11))
    ref = tmp_path / "ref.zarr"
    tile(src, ref, TileOptions(block_size=17, workers=2, executor="threads"))
    env = dict(os.environ, PYTHONPATH=os.getcwd(), TERRASTREAM_KERNELS="numpy")
    rng = np.random.default_rng(SEED + 1)
    window: dict[str, float] = {}  # executor -> seconds from the store's creation to the exit
    counts = {"injected": 0, "exit_130": 0, "hung": 0, "identical": 0, "after_finish": 0}
    attempts = 0
    # An interrupt drawn inside the measured window can land after the run finished its work
    # (exit 0) or in its interpreter's teardown, when Python has put back SIGINT's default
    # action (killed by SIGINT: -2 here, 130 in a shell): then the store must be the finished,
    # identical one; it is counted apart and another interrupt is drawn.
    while counts["injected"] < INTERRUPTS and attempts < 3 * INTERRUPTS:
        executor = ("threads", "processes")[attempts % 2]
        dst = tmp_path / f"i{attempts}.zarr"
        attempts += 1
        if executor not in window:
            whole = tmp_path / f"whole-{executor}.zarr"
            p = _start(_cmd(src, whole, executor), env, whole)
            t0 = time.perf_counter()
            _, err = p.communicate(timeout=300)
            window[executor] = time.perf_counter() - t0
            assert p.returncode == 0, err
            assert diff_stores(whole, ref) == []
        delay = float(rng.uniform(0.0, 0.9)) * window[executor]
        p = _start(_cmd(src, dst, executor), env, dst)
        try:
            try:
                p.wait(timeout=delay)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGINT)
            try:
                _, err = p.communicate(timeout=END_WITHIN_S)
            except subprocess.TimeoutExpired:
                counts["hung"] += 1
                continue
        finally:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
        what = f"interrupt {attempts - 1} ({executor}) {delay:.2f} s after the store appeared"
        if p.returncode in (0, -signal.SIGINT) or "was finished" in err:
            # (130 saying the store was finished: the interrupt came after its last write)
            counts["after_finish"] += 1
            assert diff_stores(dst, ref) == [], f"{what}: exit {p.returncode}: {err}"
            continue
        counts["injected"] += 1
        assert p.returncode == 130, f"{what}: exit {p.returncode}: {err}"
        assert "interrupted" in err and "Traceback" not in err, f"{what}: {err}"
        counts["exit_130"] += 1
        tile(src, dst, TileOptions(block_size=17, workers=2, executor="threads"))
        assert diff_stores(dst, ref) == [], what
        counts["identical"] += 1
    record("Ctrl-C + rerun", **counts)
    assert counts["hung"] == 0, counts
    assert counts["identical"] == counts["exit_130"] == counts["injected"] == INTERRUPTS, counts
