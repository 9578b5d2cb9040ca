"""``run_flythrough``'s summaries agree with their rows, when a flight ends and when an error
stops it, though the loaders went on reading after the last frame."""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import pytest

from streamer.errors import BudgetError, LoadError
from streamer.frames import Frame, FrameStats, Totals
from streamer.run import run_flythrough

WARMUP = 1000
AFTER = 777  # bytes the loaders bring in after the last frame


def stats(i: int) -> FrameStats:
    """Frame ``i``'s figures: 10 real-time and 5 prefetched bytes."""
    return FrameStats(
        frame=i, visible_blocks=1, prefetch_blocks=0, needed_bytes=100, realtime_bytes=10,
        prefetched_bytes=5, io_ms=0.0, update_ms=0.1, update_cpu_ms=0.1, wait_ms=0.0,
        stalled=False, missing_levels=0, resident_bytes=50, io_errors=0,
    )  # fmt: skip


@dataclass
class FakeSession:
    """What ``run_flythrough`` uses of a session; ``fail_at``: the update that raises
    (``counted``: after counting its frame, as a LoadError does)."""

    fail_at: int | None = None
    counted: bool = False
    after: int = AFTER

    def __post_init__(self) -> None:
        self.config = SimpleNamespace(fps=1000.0)
        self.totals = Totals(warmup={"ms": 1.0, "bytes": WARMUP})
        self.totals.loaded_bytes = WARMUP

    def warm_up(self, camera) -> dict[str, float]:
        """Nothing to load."""
        return self.totals.warmup

    def update(self, camera, dt: float, *, wait: bool = False) -> Frame:
        """Count a frame (its loads), then the loaders read on; raise at ``fail_at``."""
        i = self.totals.frames
        frame = Frame(camera=camera, blocks={}, stats=stats(i))
        if i == self.fail_at and not self.counted:
            self.totals.loaded_bytes += self.after
            raise BudgetError("the view outgrew the budget")
        self.totals.add(frame)
        self.totals.loaded_bytes += 15
        if i == self.fail_at:
            self.totals.loaded_bytes += self.after
            err = LoadError("block (0, 0) could not be read")
            err.frame = frame  # type: ignore[attr-defined]
            raise err
        return frame

    def summary(self) -> dict:
        """The totals, with the loaders' bytes after the last frame in ``loaded_bytes``."""
        t = self.totals
        out = t.summary(
            used_bytes=0, peak_resident_bytes=50, peak_held_bytes=50, budget_bytes=100,
            stall_set="triangle", failed_now=[], failing={},
        )  # fmt: skip
        out["loaded_bytes"] += self.after if self.fail_at is None else 0
        return out


def agrees(summary: dict, rows: list[dict], after: int = AFTER) -> None:
    """The summary's loads are the warm-up's and the rows'; the rest arrived after them."""
    assert summary["frames"] == len(rows)
    in_rows = sum(r["realtime_bytes"] + r["prefetched_bytes"] for r in rows)
    assert summary["loaded_bytes"] == summary["warmup_bytes"] + in_rows
    assert summary.get("loaded_after_frames_bytes", 0) == after
    assert summary["wasted_bytes"] == summary["loaded_bytes"] - summary["used_bytes"]


@pytest.mark.parametrize("counted", [False, True], ids=["budget-error", "load-error"])
def test_a_stopped_flights_summary_agrees_with_its_rows(counted):
    s = FakeSession(fail_at=3, counted=counted)
    with pytest.raises((BudgetError, LoadError)) as err:
        run_flythrough(s, list(range(6)), realtime=False)
    partial = err.value.partial
    assert len(partial.rows) == (4 if counted else 3)
    agrees(partial.summary, partial.rows)


def test_a_stopped_flight_with_nothing_read_after_it():
    """Positive control: with nothing read after the last frame the figures agreed already."""
    s = FakeSession(fail_at=3, after=0)
    with pytest.raises(BudgetError) as err:
        run_flythrough(s, list(range(6)), realtime=False)
    agrees(err.value.partial.summary, err.value.partial.rows, after=0)


def test_a_finished_flights_summary_agrees_with_its_rows():
    """The same split for a flight that ended."""
    result = run_flythrough(FakeSession(), list(range(6)), realtime=False)
    assert len(result.rows) == 6
    assert result.summary["frames"] == 6
    agrees(result.summary, result.rows)
