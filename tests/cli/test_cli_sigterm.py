"""SIGTERM (what ``kill``, ``timeout``, systemd and container runtimes send) is handled as a
Ctrl-C: the command cleans up what it had begun and exits 143 saying so.

It used to end the process on the spot: ``synth`` and ``export`` left their ``*.partial.tif``
beside OUT, and ``flythrough`` cut its ``frames.csv`` mid-line. The control runs the same CLI
without the handler (``app()`` rather than ``main()``) and sees the leftovers.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from demtools import fractal

from tiler.tile import TileOptions, tile

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tiler"))
from storetools import diff_stores  # noqa: E402

#: the console script users run (as tests/reliability/test_interrupts.py explains)
EXE = str(Path(sys.executable).with_name("terrastream"))
#: the CLI without its SIGTERM handler: the old behaviour, for the control
BARE = [sys.executable, "-c", "import sys; from cli.main import app; sys.argv[0] = 'x'; app()"]


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # as `cmd &` from a script starts it


def _term_when(
    cmd: list[str],
    ready,
    timeout_s: float = 120.0,
    sigint_ignored: bool = False,
    group: bool = False,
    after_s: float = 0.0,
) -> subprocess.CompletedProcess:
    """Run ``cmd``; send it SIGTERM ``after_s`` after ``ready()`` is true (to its whole
    process group with ``group``, as systemd and ``timeout`` do); return its result."""
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    p = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=_ignore_sigint if sigint_ignored else None, start_new_session=group,
    )  # fmt: skip
    try:
        t0 = time.monotonic()
        while not ready() and p.poll() is None:
            if time.monotonic() - t0 > timeout_s:
                pytest.fail(f"{cmd[1:3]} never got under way")
            time.sleep(0.005)
        time.sleep(after_s)
        assert p.poll() is None, f"the command ended before the signal: {p.communicate()}"
        if group:
            os.killpg(p.pid, signal.SIGTERM)
        else:
            p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    return subprocess.CompletedProcess(cmd, p.returncode, out, err)


def _partials(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if ".partial" in p.name)


@pytest.mark.parametrize(
    ("handled", "sigint_ignored"),
    [(True, False), (True, True), (False, False)],
    ids=["cli", "cli-sigint-ignored", "control-without-handler"],
)
def test_sigterm_during_synth_leaves_nothing(tmp_path, handled, sigint_ignored):
    out = tmp_path / "dem.tif"
    cmd = [EXE] if handled else BARE
    res = _term_when(
        [*cmd, "synth", str(out), "--size", "8193"], lambda: _partials(tmp_path),
        sigint_ignored=sigint_ignored,
    )  # fmt: skip
    if handled:
        assert res.returncode == 143, res.stderr
        assert "terminated (SIGTERM)" in res.stderr and "Traceback" not in res.stderr
        assert _partials(tmp_path) == [] and not out.exists()
    else:  # the control: killed on the spot, its temporary file left behind
        assert res.returncode == -signal.SIGTERM
        assert _partials(tmp_path)


@pytest.mark.parametrize(
    "sigint_ignored",
    [False, pytest.param(True, marks=pytest.mark.long_series)],
    ids=["sigint", "sigint-ignored"],
)  # (with SIGINT ignored: `make reliability`; synth's case above runs in the suite)
def test_sigterm_during_tile_resumes(dem_factory, tmp_path, sigint_ignored):
    """With SIGINT ignored the block run's deferred interrupt still takes the SIGTERM (a
    KeyboardInterrupt raised inside the pool's locks could hang it: tiler.interrupt)."""
    src = dem_factory(fractal((300, 300), 5))
    ref, dst = tmp_path / "ref.zarr", tmp_path / "s.zarr"
    tile(src, ref, TileOptions(block_size=17))
    res = _term_when(
        [EXE, "tile", str(src), str(dst), "--block-size", "17", "--workers", "2"],
        lambda: (dst / "zarr.json").exists(), sigint_ignored=sigint_ignored,
    )  # fmt: skip
    if res.returncode == 0:  # (the signal came once the store was finished: rare)
        pytest.skip("the run finished before the signal")
    assert res.returncode == 143, res.stderr
    assert "terminated (SIGTERM)" in res.stderr and "rerun the same command" in res.stderr
    tile(src, dst, TileOptions(block_size=17))
    assert diff_stores(dst, ref) == []


@pytest.mark.long_series  # (the suite's sibling: test_dask's SIGINT to a group with workers)
def test_sigterm_to_the_group_of_a_tile_with_worker_processes_resumes(dem_factory, tmp_path):
    """SIGTERM to the whole process group reached the worker processes too, which died of it:
    the run said "a tiling worker process died (out of memory or killed)", exit 1. The workers
    now ignore it (they still die with their parent) and the run ends as terminated."""
    src = dem_factory(fractal((400, 400), 6))
    ref, dst = tmp_path / "ref.zarr", tmp_path / "s.zarr"
    tile(src, ref, TileOptions(block_size=17))
    res = _term_when(
        [EXE, "tile", str(src), str(dst), "--block-size", "17", "--workers", "2",
         "--scheduler", "processes"],
        lambda: (dst / "journal").exists(), group=True, after_s=1.0,
    )  # fmt: skip
    if res.returncode == 0:
        pytest.skip("the run finished before the signal")
    assert res.returncode == 143, res.stderr
    assert "terminated (SIGTERM)" in res.stderr and "worker process died" not in res.stderr
    tile(src, dst, TileOptions(block_size=17))
    assert diff_stores(dst, ref) == []
