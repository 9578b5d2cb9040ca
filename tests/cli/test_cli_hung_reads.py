"""A read the server never answers does not keep ``terrastream`` alive after the command has
reported it: :func:`cli.main.leave_hung_reads` ends the process with the command's status
instead of letting the interpreter wait out each read's timeout at exit. Nor does it keep a
plain Python program alive: the loader's threads are daemons (:mod:`streamer.pool`). The
control runs the same session on a ``ThreadPoolExecutor`` (joined at exit, the loader's pool
before) and waits for the timeout."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from demtools import fractal, write_dem
from rangeserver import LoopbackServer

from cli import main as cli_main
from tiler.tile import TileOptions, tile

READ_TIMEOUT_S = 8.0  # the hung reads' timeout: what the control waits for at exit

SCRIPT = textwrap.dedent(
    """
    import sys, time
    from cli.main import leave_hung_reads
    from streamer.paths import default_flythrough
    from streamer.session import open_session
    from tiler.location import Location
    from tiler.store import TerrainStore

    url, timeout, mode = sys.argv[1], float(sys.argv[2]), sys.argv[3]
    if mode == "joined":  # the control: the pool the loader had, joined at interpreter exit
        from concurrent.futures import ThreadPoolExecutor
        import streamer.loader

        class Joined(ThreadPoolExecutor):
            def __init__(self, workers, prefix):
                super().__init__(workers, thread_name_prefix=prefix)

            @property
            def threads(self):
                return list(self._threads)

        streamer.loader.DaemonPool = Joined
    store = TerrainStore(Location(url, {"timeout": timeout}))
    s = open_session(store, budget_mb=64, workers=2, raise_on_failure=False)
    print("open", flush=True)  # the test stalls the server's block reads now
    sys.stdin.readline()
    z0, z1 = store.meta.extra["value_range"]
    for cam in default_flythrough(s.grid, z0, z1, 5, 60.0, viewport=(160, 120)):
        s.update(cam)
    time.sleep(0.3)
    print("unfinished", s.close(0.2), time.monotonic(), flush=True)
    if mode == "leave":
        leave_hung_reads(1)
    sys.exit(1)
    """
)


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("hung")
    src = write_dem(d / "d.tif", fractal((129, 129), 3), cell=10.0)
    tile(src, d / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))
    return d


def _run(root: Path, mode: str) -> tuple[int, float, str]:
    """Exit status, seconds from the session's close to the process's end, and the line the
    script printed after closing."""
    srv = LoopbackServer(root)
    with srv as url, subprocess.Popen(
        [sys.executable, "-c", SCRIPT, f"{url}/s.zarr", str(READ_TIMEOUT_S),
         mode],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    ) as p:  # fmt: skip
        try:
            assert p.stdout.readline().strip() == "open"
            srv.stall.set()  # every block read from now on hangs until its timeout
            p.stdin.write("\n")
            p.stdin.flush()
            line = p.stdout.readline()
            closed = float(line.split()[-1])
            rc = p.wait(timeout=60)
            return rc, time.monotonic() - closed, line
        finally:
            if p.poll() is None:
                p.kill()


@pytest.mark.parametrize("mode", ["leave", "plain"])
def test_the_process_ends_when_the_command_does_not_at_the_reads_timeout(root, mode):
    """``leave``: the CLI's exit path; ``plain``: a Python program that just ends."""
    rc, after, line = _run(root, mode)
    assert "terrastream-load" in line  # reads were still hanging when the session closed
    assert rc == 1
    assert after < READ_TIMEOUT_S / 2, f"the process lingered {after:.1f} s after closing"


def test_control_with_a_joined_pool_the_interpreter_waits_for_the_hung_reads(root):
    rc, after, line = _run(root, "joined")
    assert "terrastream-load" in line
    assert rc == 1
    assert after > READ_TIMEOUT_S / 2, f"the process ended {after:.1f} s after closing"


class _Exited(Exception):
    pass


@pytest.mark.parametrize("hung", [["terrastream-load_0"], []])
def test_main_leaves_hung_reads_only(monkeypatch, hung):
    """``main`` ends the process itself (with the command's status) only while loader threads
    are alive; otherwise ``SystemExit`` goes on as usual."""
    from streamer import loader

    codes: list[int] = []

    def fake_exit(code: int) -> None:
        codes.append(code)
        raise _Exited

    monkeypatch.setattr(loader, "threads_alive", lambda: hung)
    monkeypatch.setattr(cli_main.os, "_exit", fake_exit)
    monkeypatch.setattr(cli_main.logging, "shutdown", lambda: None)
    monkeypatch.setattr(sys, "argv", ["terrastream", "info", "/nonexistent/store.zarr"])
    with pytest.raises(_Exited if hung else SystemExit) as exc:
        cli_main.main()
    if hung:
        assert codes == [2]  # info's status for a missing store (a usage error)
    else:
        assert codes == [] and exc.value.code == 2
