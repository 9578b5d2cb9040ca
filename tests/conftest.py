"""Shared fixtures: small DEM files (helpers in ``demtools``), the GL context, the GL tally."""

from __future__ import annotations

import gc
import logging
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from demtools import write_dem

#: ``make reliability`` (and anyone setting it) runs the long fault-injection series: the
#: longer versions of some tests, and the tests marked ``long_series``
LONG = os.environ.get("TERRASTREAM_RELIABILITY_LONG") == "1"
_LONG_LEFT: list[str] = []


def pytest_collection_modifyitems(config, items) -> None:
    """Without :data:`LONG`, leave the ``long_series`` tests (longer kill/resume cases, each
    with a shorter sibling in the suite) to ``make reliability``: deselected, and counted in
    the run's last lines."""
    if LONG:
        return
    keep, left = [], []
    for item in items:
        (left if item.get_closest_marker("long_series") else keep).append(item)
    if left:
        config.hook.pytest_deselected(items=left)
        items[:] = keep
        _LONG_LEFT[:] = [i.nodeid for i in left]


def pytest_sessionfinish(session) -> None:
    """An xdist worker hands its count of deselected long tests to the controller."""
    out = getattr(session.config, "workeroutput", None)
    if out is not None:
        out["long_left"] = list(_LONG_LEFT)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error) -> None:
    """(xdist controller) each worker collected every test: any one's count is the run's."""
    left = getattr(node, "workeroutput", {}).get("long_left")
    if left and not _LONG_LEFT:
        _LONG_LEFT[:] = left


def pytest_configure(config):
    """Ctrl-C as a terminal sends it, whatever started the run: a shell starts a background
    command without job control (``( cmd & )``, ``nohup`` in scripts) with SIGINT ignored, and
    the ignored disposition passes to every child, so the Ctrl-C tests (ours in-process, the
    CLI's in children) saw nothing to catch. With a handler here, children start with the
    default again and install Python's own."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def dem_factory(tmp_path):
    """Make GeoTIFF DEMs in tmp_path: ``dem_factory(array, name=..., nodata=...)``."""

    def make(data: np.ndarray, name: str = "dem.tif", **kw) -> Path:
        return write_dem(tmp_path / name, data, **kw)

    return make


@pytest.fixture(autouse=True)
def _unfreeze_gc():
    """A test that froze the collector's heap (``freeze_gc``, the ``stream`` command) gives
    it back, so the rest of the run collects as it would have."""
    yield
    if gc.get_freeze_count():
        gc.unfreeze()


@pytest.fixture(autouse=True)
def _no_cli_log_handler_outlives_its_test():
    """The CLI run in-process (``setup_logging``: ``logging.basicConfig(force=True)``) gives
    the root logger a handler on the test's captured stderr, closed after the test; a thread
    that outlived it (dask's event loop saying "Close client connection") then printed
    "--- Logging error --- ValueError: I/O operation on closed file" in the middle of the run.
    Such handlers (plain ``StreamHandler``s, not pytest's own) go with their test."""
    root = logging.getLogger()
    before = set(root.handlers)
    yield
    for h in list(root.handlers):
        if type(h) is logging.StreamHandler and h not in before:
            root.removeHandler(h)


@pytest.fixture(scope="session")
def gl_context():
    """A headless EGL context, or skip (fail when ``CI=true``: CI always has GL)."""
    moderngl = pytest.importorskip("moderngl")
    try:
        ctx = moderngl.create_standalone_context(require=450, backend="egl")
    except Exception as exc:  # noqa: BLE001 - any driver failure means "no GL here"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"CI=true but no headless OpenGL 4.5 context: {exc}")
        pytest.skip(f"no headless OpenGL 4.5 context (EGL + Mesa): {exc}")
    yield ctx
    ctx.release()


# --- how many GL tests ran: a line at the end of every run (issue 10 item 8) ------------------


class GLTally:
    """Outcomes of the tests marked ``gl``: passed, failed, skipped (with one skip reason)."""

    def __init__(self) -> None:
        self.passed = self.failed = self.skipped = self.xfailed = 0
        self.reason = ""

    def add(self, report: pytest.TestReport) -> None:
        """Count one phase report of a ``gl`` test (each test counted once); an expected
        failure ran on GL (it is counted as run, not as skipped)."""
        if report.when == "call" and hasattr(report, "wasxfail"):
            self.xfailed += 1
        elif report.when == "call" and report.passed:
            self.passed += 1
        elif report.failed:
            self.failed += 1
        elif report.skipped and report.when in ("setup", "call"):
            self.skipped += 1
            if not self.reason and isinstance(report.longrepr, tuple):
                self.reason = str(report.longrepr[2])

    def line(self) -> str:
        """``GL tests: 240 ran (240 passed, 0 failed), 3 skipped``."""
        ran = self.passed + self.failed + self.xfailed
        xf = f", {self.xfailed} xfailed" if self.xfailed else ""
        text = f"GL tests: {ran} ran ({self.passed} passed, {self.failed} failed{xf}), "
        text += f"{self.skipped} skipped"
        return text + (f" (e.g. {self.reason})" if self.skipped and self.reason else "")


_GL = GLTally()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if "gl" in report.keywords:
        _GL.add(report)


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    terminalreporter.write_sep("-", _GL.line())
    if _LONG_LEFT:
        terminalreporter.write_line(
            f"{len(_LONG_LEFT)} long kill/resume test(s) deselected: `make reliability` runs them"
        )
