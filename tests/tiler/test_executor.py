"""tiler.run.choose_executor: which local pool ``auto`` picks (pure: no tiling)."""

from __future__ import annotations

import pytest

from tiler import run
from tiler.location import Location
from tiler.tile import TileOptions


@pytest.fixture
def loc(tmp_path, monkeypatch):
    monkeypatch.setattr(run, "processes_unsafe", lambda: None)  # as under a __main__ guard
    return Location(tmp_path / "s.zarr")


@pytest.mark.parametrize(
    ("workers", "todo", "backend", "want"),
    [
        (2, 256, "numba", "threads"),  # compiled kernels release the GIL: threads, no spawning
        (2, 256, "numpy", "processes"),  # the numpy kernels hold the GIL: processes
        (4, 256, "numba", "processes"),  # more threads than measured: processes
        (2, 4, "numpy", "threads"),  # a small job never spawns
        (1, 256, "numpy", "threads"),
    ],
)
def test_auto_executor(loc, workers, todo, backend, want):
    opts = TileOptions(block_size=17, workers=workers)
    assert run.choose_executor(opts, loc, todo, backend) == want


def test_explicit_executor_wins(loc):
    opts = TileOptions(block_size=17, workers=2, scheduler="processes")
    assert run.choose_executor(opts, loc, 256, "numba") == "processes"
    assert Location("memory://x/y").can_share_with_processes is False
    mem = Location("memory://exec-test/s.zarr")
    assert run.choose_executor(opts, mem, 256, "numpy") == "threads"  # cannot share: threads
