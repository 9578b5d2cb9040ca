"""The session's totals over frames (``streamer.frames.Totals``): what a failed block costs."""

from __future__ import annotations

from streamer.camera import Camera
from streamer.frames import Frame, FrameStats, Totals


def _frame(blocks, failed):
    st = FrameStats(
        frame=0, visible_blocks=len(blocks), prefetch_blocks=0, needed_bytes=0,
        realtime_bytes=0, prefetched_bytes=0, io_ms=0.0, update_ms=0.0, update_cpu_ms=0.0,
        wait_ms=0.0, stalled=False, missing_levels=0, resident_bytes=0, io_errors=1,
        failed_blocks=len(failed),
    )  # fmt: skip
    cam = Camera((0.0, 0.0, 100.0), yaw=0.0, pitch=-30.0)
    return Frame(camera=cam, blocks=blocks, stats=st, failed=frozenset(failed))


def test_a_failed_block_that_has_its_needed_level_costs_the_frame_nothing():
    """A visible block whose read of a level beyond the needed one failed every retry is
    failed (``failed_blocks_ever``), but the frame drew it as it should: not a failed frame
    (it once was). The control: the same block short of its level makes the frame failed."""
    t = Totals()
    t.add(_frame({(0, 0): (3, 3), (0, 1): (3, 3)}, [(0, 0)]))
    assert t.failed_frames == 0 and len(t.failed_ever) == 1
    t.add(_frame({(0, 0): (1, 3), (0, 1): (3, 3)}, [(0, 0)]))
    assert t.failed_frames == 1 and len(t.failed_ever) == 1
    t.add(_frame({(0, 0): (-1, 3)}, [(0, 0)]))  # a hole
    assert t.failed_frames == 2
