"""DEM helpers shared by the tests: small GeoTIFFs, a rough surface, the real-data folder.

A plainly named module (not ``conftest``: ``tests/render/conftest.py`` would shadow that name),
imported by the conftests and the tests: ``from demtools import fractal, write_dem``.
"""

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


def budget_error_at(monkeypatch: pytest.MonkeyPatch, call: int) -> None:
    """Make the ``call``-th ``Session.update`` from now raise a ``BudgetError`` (a flight
    outgrowing its budget mid-way); the other calls run as usual."""
    from streamer.errors import BudgetError
    from streamer.session import Session

    update, calls = Session.update, []

    def failing(self, *a, **kw):
        calls.append(1)
        if len(calls) == call:
            raise BudgetError("the visible blocks need more than the budget (on purpose)")
        return update(self, *a, **kw)

    monkeypatch.setattr(Session, "update", failing)
