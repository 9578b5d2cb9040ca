"""Shared fixtures: small DEM files, the shared real-data folder, tmp stores."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

SHARED_DATA = Path(
    os.environ.get(
        "TERRASTREAM_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"
    )
)


def shared_file(name: str) -> Path:
    """Path of a real DEM in ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"real DEM {name} not found in {SHARED_DATA} (set TERRASTREAM_SHARED_DATA)")
    return path


def write_dem(
    path: Path,
    data: np.ndarray,
    *,
    nodata: float | None = None,
    crs: str | None = "EPSG:32633",
    origin: tuple[float, float] = (500000.0, 5000000.0),
    cell: float = 30.0,
) -> Path:
    """Write a single-band GeoTIFF with the given samples."""
    h, w = data.shape
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=w,
        height=h,
        count=1,
        dtype=data.dtype,
        crs=crs,
        transform=from_origin(origin[0], origin[1], cell, cell),
        nodata=nodata,
    ) as dst:
        dst.write(data, 1)
    return path


def fractal(shape: tuple[int, int], seed: int = 0, dtype: str = "int16") -> np.ndarray:
    """A cheap rough test surface (random walk in 2-D), deterministic."""
    rng = np.random.default_rng(seed)
    g = np.cumsum(np.cumsum(rng.integers(-3, 4, shape), axis=0), axis=1) / 4.0 + 500.0
    if np.dtype(dtype).kind == "f":
        return g.astype(dtype)
    return np.rint(g).astype(dtype)


@pytest.fixture
def dem_factory(tmp_path):
    """Make GeoTIFF DEMs in tmp_path: ``dem_factory(array, name=..., nodata=...)``."""

    def make(data: np.ndarray, name: str = "dem.tif", **kw) -> Path:
        return write_dem(tmp_path / name, data, **kw)

    return make


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
