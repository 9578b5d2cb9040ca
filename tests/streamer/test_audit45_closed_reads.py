"""A read that fails after its session was closed is not a warning (audit 45).

``close(timeout)`` stops waiting for reads in flight after its timeout; a stalled server that
then drops them made each loader thread warn "reading block … failed … Connection reset" after
the session (and the test, or the command) had ended. Such a failure concerns no frame: it is
logged at debug. A read failing while the session is open is still a warning (the control)."""

from __future__ import annotations

import logging
import time

from demtools import fractal, write_dem
from rangeserver import LoopbackServer

from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.store import TerrainStore
from tiler.tile import TileOptions, tile

LOGGER = "streamer"


def _served(tmp_path):
    src = write_dem(tmp_path / "s.tif", fractal((129, 129), 5), cell=10.0)
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))
    return tmp_path


def _camera(store):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, 1, 60.0, viewport=(160, 120))[0]


def _read_warnings(caplog) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno >= logging.WARNING and r.getMessage().startswith("reading block")
    ]


def _wait_until(cond, timeout_s: float = 10.0) -> bool:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout_s:
            return False
        time.sleep(0.02)
    return True


def test_reads_failing_after_close_are_not_warnings(tmp_path, caplog):
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    root = _served(tmp_path)
    srv = LoopbackServer(root)
    with srv as url:
        st = TerrainStore(f"{url}/s.zarr")
        s = open_session(st, budget_mb=64, workers=2, wait_timeout_s=20.0)
        srv.stall.set()
        s.update(_camera(st), 1 / 60)  # the reads go out and hang
        assert _wait_until(lambda: s.loader._in_flight > 0)
        s.close(0.2)  # gives up on them
    # the server is gone: the hung reads fail now, after the close
    failed = lambda: any(  # noqa: E731
        r.getMessage().startswith("reading block") for r in caplog.records
    )
    assert _wait_until(failed), "no read failed after the server stopped"
    assert _read_warnings(caplog) == []
    assert any(
        r.levelno == logging.DEBUG and r.getMessage().startswith("reading block")
        for r in caplog.records
    )


def test_control_a_read_failing_while_the_session_is_open_is_a_warning(tmp_path, caplog):
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    root = _served(tmp_path)
    srv = LoopbackServer(root)
    srv.handler.fail_status = 500
    with srv as url:
        st = TerrainStore(f"{url}/s.zarr")
        with open_session(st, budget_mb=64, workers=2, wait_timeout_s=5.0) as s:
            s.update(_camera(st), 1 / 60)
            assert _wait_until(lambda: bool(_read_warnings(caplog)))
