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


@pytest.mark.parametrize(
    ("samples", "want"),
    [
        (4096 * 4096, "threads"),  # start-up not repaid: 8.8-9.4 s on processes vs 5.4-6.7
        (run.PROCESS_MIN_SAMPLES - 1, "threads"),
        (run.PROCESS_MIN_SAMPLES, "processes"),  # the control: a large numpy job spawns
        (None, "processes"),  # (no size given: by the block count alone)
    ],
)
def test_auto_spawns_only_for_jobs_that_repay_the_start_up(loc, samples, want):
    opts = TileOptions(block_size=1025, workers=2)
    assert run.choose_executor(opts, loc, 256, "numpy", samples) == want


def test_a_small_tiling_runs_on_threads(loc, tmp_path):
    """The real run: 9 blocks of a 40² DEM with 2 workers started 2 processes (1.4-2.1 s for
    a 0.2 s job); they run on threads now (a script that may spawn: ``loc`` fixture)."""
    from demtools import fractal, write_dem

    from tiler.tile import tile

    src = write_dem(tmp_path / "d.tif", fractal((40, 40), 5))
    st = tile(src, tmp_path / "a.zarr", TileOptions(block_size=17, workers=2))
    assert st.meta.complete and st.tile_summary.executor == "threads"


def test_explicit_executor_wins(loc):
    opts = TileOptions(block_size=17, workers=2, scheduler="processes")
    assert run.choose_executor(opts, loc, 256, "numba") == "processes"
    assert Location("memory://x/y").can_share_with_processes is False
    mem = Location("memory://exec-test/s.zarr")
    assert run.choose_executor(opts, mem, 256, "numpy") == "threads"  # cannot share: threads


@pytest.mark.parametrize(
    ("asked", "todo", "want", "warned"),
    [
        (2, 256, 2, False),  # the control: as many as the cores
        (16, 256, 2, True),  # 16 processes on 2 cores measured 3.5 GiB and 3x the time
        (1000, 256, 2, True),
        (8, 3, 2, True),  # no more than the blocks, then no more than the cores
        (2, 1, 1, False),  # one block: one process
        (1, 0, 1, False),
    ],
)
def test_worker_processes_are_capped_at_the_cores_and_blocks(
    monkeypatch, caplog, asked, todo, want, warned
):
    monkeypatch.setattr(run.os, "cpu_count", lambda: 2)
    with caplog.at_level("WARNING", logger="tiler.tile"):
        assert run.process_count(asked, todo) == want
    assert (f"{asked} worker processes asked for on 2 cores" in caplog.text) is warned


def test_a_tiling_asked_for_more_processes_than_cores_starts_the_cores(
    monkeypatch, caplog, tmp_path
):
    """The real run: ``workers=8`` with worker processes starts a pool of 2 on 2 cores, warns,
    and the store is complete; the control asks for 2 and is not warned."""
    from demtools import fractal, write_dem

    from tiler.tile import tile

    monkeypatch.setattr(run, "processes_unsafe", lambda: None)
    monkeypatch.setattr(run.os, "cpu_count", lambda: 2)
    sizes: list[int] = []

    class Recording(run.ProcessPoolExecutor):
        def __init__(self, max_workers: int, **kw) -> None:
            sizes.append(max_workers)
            super().__init__(max_workers=max_workers, **kw)

    monkeypatch.setattr(run, "ProcessPoolExecutor", Recording)
    src = write_dem(tmp_path / "d.tif", fractal((65, 65), 5))
    for workers, name in ((8, "a.zarr"), (2, "b.zarr")):
        caplog.clear()
        with caplog.at_level("WARNING", logger="tiler.tile"):
            st = tile(src, tmp_path / name, TileOptions(block_size=17, workers=workers,
                                                        scheduler="processes"))  # fmt: skip
        assert st.meta.complete and st.tile_summary.executor == "processes"
        assert ("8 worker processes asked for" in caplog.text) is (workers == 8)
    assert sizes == [2, 2]
