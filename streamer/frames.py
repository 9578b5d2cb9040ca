"""Values of streaming sessions: settings, per-frame statistics, what a frame may draw."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from streamer.cache import Block
from streamer.camera import Camera
from streamer.errors import StreamerError
from streamer.lod import get_metric
from streamer.nodata import check_rule

#: Loading schemes (``SessionConfig.scheme``): which of this project's additions to Qiu et al.'s
#: prefetching are on. ``(pose_ahead, lookahead, concurrent_levels)``:
#:
#: * ``"qiu"`` — Qiu's loading as published: blocks of the extended triangle of *this* pose only,
#:   each loaded at the level it needs at ``tau`` (no finer), one level of a block at a time;
#: * ``"qiu+ahead"`` — plus the extension of the pose ``horizon_s`` ahead (ours);
#: * ``"qiu+fine"`` — plus loading at ``tau * lookahead`` (ours);
#: * ``"qiu+ahead+fine"`` — both, still one level of a block at a time;
#: * ``"ours"`` (default) — both, and up to ``PER_BLOCK`` levels of a block read at once.
#:
#: ``prefetch=False`` switches the extension off under any scheme (no prefetching at all).
SCHEMES: dict[str, tuple[bool, bool, bool]] = {
    "qiu": (False, False, False),
    "qiu+ahead": (True, False, False),
    "qiu+fine": (False, True, False),
    "qiu+ahead+fine": (True, True, False),
    "ours": (True, True, True),
}


#: the largest budget a session takes, MiB (2^40: 1 EiB, still an exact 64-bit byte count;
#: a budget of 1e308 MiB passed as finite and overflowed the loader's conversion to bytes)
MAX_BUDGET_MB = 2**40


def budget_ok(budget_mb: float) -> bool:
    """``budget_mb`` in MiB is at least one byte and at most :data:`MAX_BUDGET_MB` (finite:
    its bytes are an integer)."""
    return math.isfinite(budget_mb) and budget_mb * 2**20 >= 1 and budget_mb <= MAX_BUDGET_MB


@dataclass(frozen=True)
class SessionConfig:
    """Streaming settings (all validated)."""

    budget_mb: float = 256.0
    workers: int = 4  # 0: load inline in update() (deterministic, for tests and benchmarks)
    fps: float = 60.0
    tau: float = 1.0  # screen-space error threshold in pixels
    metric: str = "qiu"
    patch_log2: int = 4
    prefetch: bool = True
    lookahead: float = 0.7  # load ahead at tau * lookahead (finer than the frame needs)
    culling: str = "qiu"
    extension_L: float | None = None  # default: one block edge
    latency_ms: float = 0.0  # added to every store request (benchmarks)
    retries: int = 3  # failures in a row before a block is reported failed
    backoff_s: float = 0.05  # first retry delay; doubles per failure in a row
    max_backoff_s: float = 1.0  # retry delay cap (a failed block is retried at this pace)
    heal: bool = True  # keep retrying failed blocks while wanted (False: give up after retries)
    raise_on_failure: bool = True  # update() raises LoadError once when a block fails
    warm_start: bool = False  # the first update() runs warm_up() for its camera first
    wait_timeout_s: float = 30.0
    linger_s: float | None = None  # unload unwanted levels after this long; None: only when
    # the budget needs the room (least recently wanted first)
    horizon_s: float = 0.5  # also plan for where the camera will be this far ahead
    inline_bytes_per_frame: int | None = None  # workers=0: I/O allowance per frame, bytes
    # read (loaded or discarded on arrival; None: all)
    account_hull: bool = False  # culling="qiu": also count stalls over the frustum hull (the
    # set the renderer draws) in FrameStats.hull_stalled (costs a second plan per frame)
    scheme: str = "ours"  # loading scheme, see SCHEMES ("qiu": Qiu et al. as published)
    nodata: str = "full"  # the nodata rule levels are planned with (streamer.nodata.NODATA_RULES:
    # the renderer's rule, so the session streams what it draws)
    freeze_gc: bool = False  # warm_up() ends with streamer.gcfreeze.freeze_heap(): no full
    # garbage collection walks the start-up's objects again (process-wide, see that module)

    def __post_init__(self) -> None:
        for name in ("workers", "patch_log2", "retries"):  # (2.5 workers started 2, then failed)
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise StreamerError(f"invalid {name}: {v!r} (an integer)")
        if self.inline_bytes_per_frame is not None and (
            isinstance(self.inline_bytes_per_frame, bool)
            or not isinstance(self.inline_bytes_per_frame, (int, np.integer))
        ):
            raise StreamerError(f"invalid inline_bytes_per_frame: {self.inline_bytes_per_frame!r}")
        for name in (
            "budget_mb", "fps", "tau", "lookahead", "latency_ms", "backoff_s", "max_backoff_s",
            "wait_timeout_s", "horizon_s",
        ):  # fmt: skip
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise StreamerError(f"invalid {name}: {v!r} (a number)")
        for name in ("extension_L", "linger_s"):
            v = getattr(self, name)
            if v is not None and (
                isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating))
            ):
                raise StreamerError(f"invalid {name}: {v!r} (a number or None)")
        checks = [
            ("budget_mb", budget_ok(self.budget_mb)),
            ("workers", self.workers >= 0 and self.workers <= 64),
            ("fps", self.fps > 0 and math.isfinite(self.fps)),
            ("tau", 0 <= self.tau < math.inf),
            ("patch_log2", 0 <= self.patch_log2 <= 20),
            ("latency_ms", 0 <= self.latency_ms < math.inf),
            ("retries", self.retries >= 1),
            ("backoff_s", self.backoff_s >= 0 and math.isfinite(self.backoff_s)),
            ("max_backoff_s", self.max_backoff_s >= 0 and math.isfinite(self.max_backoff_s)),
            ("wait_timeout_s", 0 < self.wait_timeout_s < math.inf),
            ("linger_s", self.linger_s is None or 0 <= self.linger_s < math.inf),
            ("horizon_s", 0 <= self.horizon_s < math.inf),
            ("extension_L", self.extension_L is None or 0 <= self.extension_L < math.inf),
            ("inline_bytes_per_frame", (self.inline_bytes_per_frame or 0) >= 0),
            ("lookahead", 0 < self.lookahead <= 1),
        ]
        for name, ok in checks:
            if name == "budget_mb" and not ok:
                raise StreamerError(
                    f"invalid budget_mb: {self.budget_mb!r} (from one byte, 2^-20 MiB, to "
                    f"2^{MAX_BUDGET_MB.bit_length() - 1} MiB; give a budget in that range)"
                )
            if not ok:
                raise StreamerError(f"invalid {name}: {getattr(self, name)!r}")
        get_metric(self.metric)
        if self.culling not in ("qiu", "hull"):
            raise StreamerError(f"culling must be 'qiu' or 'hull', got {self.culling!r}")
        try:
            check_rule(self.nodata)
        except ValueError as exc:
            raise StreamerError(f"invalid nodata: {exc}") from None
        if self.scheme not in SCHEMES:
            raise StreamerError(
                f"unknown loading scheme {self.scheme!r}: use one of {', '.join(SCHEMES)}"
            )

    @property
    def plan_horizon_s(self) -> float:
        """The pose-ahead horizon the scheme uses (0 when the scheme has no pose-ahead)."""
        return self.horizon_s if SCHEMES[self.scheme][0] else 0.0

    @property
    def plan_lookahead(self) -> float:
        """The factor on ``tau`` prefetch plans load at (1: the needed level only)."""
        return self.lookahead if SCHEMES[self.scheme][1] else 1.0

    @property
    def concurrent_levels(self) -> bool:
        """Whether several levels of one block may be read at once (else level by level)."""
        return SCHEMES[self.scheme][2]


@dataclass(frozen=True)
class FrameStats:
    """One frame's I/O figures (bytes are decoded level bytes)."""

    frame: int
    visible_blocks: int
    prefetch_blocks: int
    needed_bytes: int
    realtime_bytes: int  # loaded while this frame waited for it or after it was due
    prefetched_bytes: int  # loaded ahead of any frame needing it, since the previous frame
    # (both: a warm-up's loads between the two frames apart, in Totals' warmup figures)
    io_ms: float  # worker time spent reading and decoding since the previous frame
    update_ms: float  # wall time of update() on the caller's thread (excluding waiting)
    update_cpu_ms: float  # CPU time of the caller's thread in update() (excluding waiting)
    wait_ms: float
    stalled: bool
    missing_levels: int
    resident_bytes: int
    io_errors: int
    holes: int = 0  # visible blocks with no resident level (nothing of them can be drawn)
    stall_set: str = "triangle"  # the set stalled/missing_levels/holes count: "triangle"
    # (Qiu's projected view triangle, culling="qiu") or "hull" (Jung & Han's frustum hull,
    # culling="hull": what the renderer draws)
    late_bytes: int = 0  # arrived since the previous frame after the frame that first needed
    # them was due (frame 0 due when update() is called, frame i at frame 0's end + i/fps)
    hull_stalled: bool | None = None  # account_hull: a block of the hull set lacked its level
    # (None: not accounted)
    levels_short: int = 0  # largest (needed - resident) level gap over visible blocks (0: none
    # drawn coarser than needed; a hole counts needed + 1)
    failed_blocks: int = 0  # visible blocks whose reads failed ``retries`` times in a row
    discarded_bytes: int = 0  # read from the store since the previous frame but thrown away on
    # arrival, never cached (in neither realtime_bytes nor prefetched_bytes; Totals.summary)


@dataclass(frozen=True)
class Frame:
    """What a frame may draw: ``blocks[b] = (resident level, needed level)``, and its stats.

    A resident level of -1 is a hole (counted in ``stats.holes``); ``failed`` names the
    visible blocks whose reads keep failing (they are still retried).
    """

    camera: Camera
    blocks: dict[Block, tuple[int, int]]
    stats: FrameStats
    failed: frozenset[Block] = frozenset()


@dataclass
class Totals:
    """Counters a session accumulates over its frames (its ``summary()``)."""

    frames: int = 0
    stall_frames: int = 0
    needed_bytes: int = 0
    realtime_bytes: int = 0
    realtime_bytes_after_first: int = 0
    loaded_bytes: int = 0
    prefetched_bytes: int = 0
    max_update_ms: float = 0.0
    max_update_cpu_ms: float = 0.0
    warmup: dict = field(default_factory=dict)  # all warm-ups': "ms", "bytes",
    # "discarded_bytes" summed, "count" (add_warmup)
    io_errors: int = 0
    cancelled: int = 0
    hole_frames: int = 0
    late_bytes: int = 0
    hull_stall_frames: int | None = None
    coarse_frames: dict = field(default_factory=dict)  # levels short -> frames
    failed_frames: int = 0
    failed_ever: set = field(default_factory=set)
    reloaded_bytes: int = 0  # levels loaded again after they had been evicted
    reloaded_levels: int = 0
    discarded_bytes: int = 0  # levels read from the store but thrown away, never cached: the
    # bytes read are loaded_bytes + discarded_bytes
    discarded_levels: int = 0
    used: dict = field(default_factory=dict)  # block -> finest level a frame has drawn

    def add(self, frame: Frame) -> None:
        """Add one frame's figures."""
        st = frame.stats
        self.needed_bytes += st.needed_bytes
        self.realtime_bytes += st.realtime_bytes
        if self.frames > 0:
            self.realtime_bytes_after_first += st.realtime_bytes
        self.prefetched_bytes += st.prefetched_bytes
        self.stall_frames += int(st.stalled)
        self.hole_frames += int(st.holes > 0)
        self.late_bytes += st.late_bytes
        if st.hull_stalled is not None:
            self.hull_stall_frames = (self.hull_stall_frames or 0) + int(st.hull_stalled)
        if st.levels_short > 0:
            self.coarse_frames[st.levels_short] = self.coarse_frames.get(st.levels_short, 0) + 1
        # frames a failure cost something: a failed block drawn short of its needed level (a
        # failed read beyond it, say a prefetch level, leaves the frame as it should be)
        blocks = frame.blocks
        self.failed_frames += int(any(blocks[b][0] < blocks[b][1] for b in frame.failed))
        self.failed_ever.update(frame.failed)  # blocks a frame needed, failed at some time
        self.max_update_ms = max(self.max_update_ms, st.update_ms)
        self.max_update_cpu_ms = max(self.max_update_cpu_ms, st.update_cpu_ms)
        self.frames += 1

    def add_warmup(self, figures: dict[str, float]) -> None:
        """Add one warm-up's ``{"ms", "bytes", "discarded_bytes"}`` (``Session.warm_up``'s):
        the warm-up figures are every warm-up's, not the latest's."""
        count = self.warmups + 1  # (before the keys below make a mapping without a count)
        w = self.warmup
        for key in ("ms", "bytes", "discarded_bytes"):
            w[key] = w.get(key, 0.0) + float(figures.get(key, 0.0))
        w["count"] = count

    @property
    def warmups(self) -> int:
        """How many warm-ups were counted (a ``warmup`` mapping without a count: one)."""
        return int(self.warmup.get("count", 1 if self.warmup else 0))

    def summary(
        self,
        *,
        used_bytes: int,
        peak_resident_bytes: int,
        peak_held_bytes: int,
        budget_bytes: int,
        stall_set: str,
        failed_now: list[Block],
        failing: dict[str, Any],
    ) -> dict[str, Any]:
        """The ``summary()`` mapping of a session (see :meth:`streamer.session.Session.summary`).

        ``loaded_bytes`` counts the levels added to the cache; ``discarded_bytes`` (over
        ``discarded_levels``) the levels read from the store but thrown away on arrival (the
        block lost the level below meanwhile or is no longer wanted, a level beyond a gap that
        will not be filled, a decode that raised): the bytes read from the store are their sum
        (decoded level bytes, as every figure; errors reads carry none). Discarded bytes are in
        no frame's ``realtime_bytes`` or ``prefetched_bytes``: each frame's
        ``FrameStats.discarded_bytes`` counts those since the previous frame and
        ``warmup_discarded_bytes`` the warm-ups', so that ``discarded_bytes`` is the warm-ups'
        plus the frames' plus those discarded after the last frame; likewise ``loaded_bytes``
        is ``warmup_bytes`` plus the frames' real-time and prefetched bytes plus those loaded
        after the last frame. The warm-up figures (``warmup_ms``, ``warmup_bytes``,
        ``warmup_discarded_bytes``) sum every warm-up's, ``warmups`` of them.
        """
        return {
            "frames": self.frames,
            "stall_frames": self.stall_frames,
            "stall_set": stall_set,
            "stall_frames_hull": self.hull_stall_frames,  # None unless account_hull
            "needed_bytes": self.needed_bytes,
            "realtime_bytes": self.realtime_bytes,
            "realtime_bytes_after_first_frame": self.realtime_bytes_after_first,
            "late_bytes": self.late_bytes,
            "coarse_frames_by_levels": {str(k): v for k, v in sorted(self.coarse_frames.items())},
            "prefetched_bytes": self.prefetched_bytes,
            "loaded_bytes": self.loaded_bytes,
            "used_bytes": used_bytes,
            "wasted_bytes": max(0, self.loaded_bytes - used_bytes),
            "peak_resident_bytes": peak_resident_bytes,  # decoded levels
            "peak_held_bytes": peak_held_bytes,  # + reads in flight: what the budget bounds
            "budget_bytes": budget_bytes,
            "max_update_ms": self.max_update_ms,
            "max_update_cpu_ms": self.max_update_cpu_ms,
            "io_errors": self.io_errors,
            "cancelled_loads": self.cancelled,
            "warmups": self.warmups,  # the warm-up figures below are all of theirs, summed
            "warmup_ms": self.warmup.get("ms", 0.0),
            "warmup_bytes": int(self.warmup.get("bytes", 0)),
            "warmup_discarded_bytes": int(self.warmup.get("discarded_bytes", 0)),
            "hole_frames": self.hole_frames,
            "failed_frames": self.failed_frames,
            "failed_blocks": [list(b) for b in failed_now],
            "failed_blocks_ever": len(self.failed_ever),
            **failing,
            "reloaded_bytes": self.reloaded_bytes,
            "reloaded_levels": self.reloaded_levels,
            "discarded_bytes": self.discarded_bytes,
            "discarded_levels": self.discarded_levels,
        }
