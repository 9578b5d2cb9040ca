"""A command whose reader goes away (``terrastream verify STORE | head -1``) exits quietly."""

from __future__ import annotations

import subprocess
import sys

from demtools import fractal

from tiler.tile import TileOptions, tile


def _run_with_closed_stdout(*args: str) -> subprocess.CompletedProcess:
    """Run the CLI with its stdout a pipe whose read end is already closed."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "cli.main", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    proc.stdout.close()  # the reader is gone before the command prints anything
    err = proc.stderr.read()
    proc.stderr.close()
    return subprocess.CompletedProcess(proc.args, proc.wait(timeout=120), "", err)


def test_a_closed_pipe_is_not_an_error_message(dem_factory, tmp_path):
    dst = tmp_path / "s.zarr"
    tile(dem_factory(fractal((40, 40), 3)), dst, TileOptions(block_size=17))
    r = _run_with_closed_stdout("verify", str(dst))
    assert r.returncode == 1, r.stderr
    assert "BrokenPipe" not in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert "Exception ignored" not in r.stderr, r.stderr
    # the control: with a reader, the same command prints its result and exits 0
    ok = subprocess.run(
        [sys.executable, "-m", "cli.main", "verify", str(dst)], capture_output=True, text=True
    )
    assert ok.returncode == 0 and ": ok;" in ok.stdout, ok.stderr
