"""One fly-through of the prefetch benchmark and the figures derived from its frames.

:func:`fly` paces a session as ``streamer.run.run_flythrough`` does and keeps every frame's row;
:class:`LoadLedger` accounts each load from outside the session; :func:`derive` turns the rows
and the session summary into the run's metrics. See bench/prefetch.py.
"""

from __future__ import annotations

import gc
import math
import time
from dataclasses import asdict
from typing import Any

import numpy as np

from streamer.session import Session

FPS = 60.0
#: the update-CPU target (ms): frames over it are counted here and checked in bench/prefetch.py
T_UPDATE_MS = 2.0


class LoadLedger:
    """Per-load accounting, observed from outside the session after every frame.

    The session's ``used_bytes`` counts each (block, level) once however often it is evicted
    and loaded again, so on a path that passes the same ground twice ``loaded / used`` also
    counts re-loads. Here the resident level of every cached block (the public
    ``LevelCache.blocks`` / ``level``) is compared with the previous frame's: a rise is a load
    of each new level, a fall an eviction. A load is *used* once a frame draws it (a visible
    block's levels ``0..min(resident, needed)``) before it is evicted; an evicted load that no
    frame drew is wasted. Loads evicted within one frame are not seen (rare). A frame whose
    cache could not be listed (loaders changing it throughout :data:`RETRIES` tries) is not
    accounted: it is counted in ``ledger_skipped_frames`` (its draws are then missing from
    ``used_load_bytes``; its loads and evictions are seen at the next frame).
    """

    #: tries to list the cache while loader threads change it, per frame
    RETRIES = 10

    def __init__(self, level_bytes: list[int]) -> None:
        self.level_bytes = level_bytes
        self.drawn: dict[tuple[int, int], list[bool]] = {}  # per resident level: drawn yet?
        self.loaded = 0
        self.used = 0
        self.evicted_unused = 0
        self.evicted_used = 0
        self.skipped_frames = 0

    def frame(self, session: Session, blocks: dict) -> None:
        cache = session.cache
        for _ in range(self.RETRIES):
            try:
                cached = cache.blocks()
                break
            except RuntimeError:  # a loader thread changed the cache meanwhile: look again
                continue
        else:
            self.skipped_frames += 1  # (reported in result(): never dropped silently)
            return
        now = {b: cache.level(b) for b in cached}
        for b in set(self.drawn) | set(now):
            flags = self.drawn.setdefault(b, [])
            top = now.get(b, -1)
            while len(flags) - 1 > top:  # evicted
                lv = len(flags) - 1
                if flags.pop():
                    self.evicted_used += self.level_bytes[lv]
                else:
                    self.evicted_unused += self.level_bytes[lv]
            while len(flags) - 1 < top:  # loaded
                self.loaded += self.level_bytes[len(flags)]
                flags.append(False)
            if not flags:
                del self.drawn[b]
        for b, (have, need) in blocks.items():
            flags = self.drawn.get(b)
            if not flags:
                continue
            for lv in range(min(have, need, len(flags) - 1) + 1):
                if not flags[lv]:
                    flags[lv] = True
                    self.used += self.level_bytes[lv]

    def result(self) -> dict[str, int]:
        resident_unused = sum(
            self.level_bytes[lv] for f in self.drawn.values() for lv, d in enumerate(f) if not d
        )
        return {
            "observed_loaded_bytes": self.loaded,
            "used_load_bytes": self.used,
            "evicted_unused_bytes": self.evicted_unused,
            "evicted_used_bytes": self.evicted_used,
            "resident_unused_bytes_at_end": resident_unused,
            "ledger_skipped_frames": self.skipped_frames,
        }


def fly(session: Session, cameras: list) -> dict[str, Any]:
    """Fly ``cameras`` through ``session`` as ``streamer.run.run_flythrough`` does (warm-up for
    the first pose, frame ``i`` due ``i / fps`` later, frame 0 waits); per-frame rows.

    ``late_ms`` is how late a frame's update started (0 when on time).
    """
    fps = session.config.fps
    grid = session.grid
    rows: list[dict[str, Any]] = []
    causes = {
        "new_block": 0,  # not visible in the previous frame
        "refine": 0,  # visible before, now needs a finer level
        "nothing_resident": 0,
        "near_camera": 0,  # the eye is over the block or within one block edge of it
        "away_from_camera": 0,
    }
    edge = grid.step * grid.dx
    stall_frames: list[int] = []
    prev_blocks: set = set()
    ledger = LoadLedger(session.level_bytes)
    gc_log: list[tuple[str, int, float]] = []

    def on_gc(phase: str, info: dict) -> None:
        gc_log.append((phase, info["generation"], time.perf_counter()))

    gc.callbacks.append(on_gc)
    gc_frames = {"any": 0, "gen2": 0, "slow_cpu_with_gc": 0, "slow_cpu": 0}
    if cameras:
        session.warm_up(cameras[0])
    t0 = time.perf_counter()
    for i, cam in enumerate(cameras):
        late = 0.0
        delay = t0 + i / fps - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        else:
            late = -delay
        n_gc = len(gc_log)
        try:
            frame = session.update(cam, 1.0 / fps, wait=i == 0)
        except BaseException:
            gc.callbacks.remove(on_gc)
            raise
        gcs = [g for g in gc_log[n_gc:] if g[0] == "start"]
        gc_log.clear()
        slow = frame.stats.update_cpu_ms > T_UPDATE_MS
        gc_frames["any"] += bool(gcs)
        gc_frames["gen2"] += any(g[1] == 2 for g in gcs)
        gc_frames["slow_cpu"] += slow
        gc_frames["slow_cpu_with_gc"] += slow and bool(gcs)
        row = asdict(frame.stats)
        row["late_ms"] = late * 1000.0
        rows.append(row)
        if frame.stats.stalled:
            stall_frames.append(i)
            for b, (have, need) in frame.blocks.items():
                if have < need:
                    if have < 0:
                        causes["nothing_resident"] += 1
                    causes["new_block" if b not in prev_blocks else "refine"] += 1
                    x0, y0, x1, y1 = (float(v) for v in grid.block_bounds(b[0], b[1]))
                    cx, cy = float(cam.position[0]), float(cam.position[1])
                    gap = math.hypot(max(x0 - cx, 0.0, cx - x1), max(y0 - cy, 0.0, cy - y1))
                    causes["near_camera" if gap <= edge else "away_from_camera"] += 1
        prev_blocks = set(frame.blocks)
        ledger.frame(session, frame.blocks)
    gc.callbacks.remove(on_gc)
    return {
        "gc_during_update": gc_frames,
        "rows": rows,
        "stall_frames": stall_frames,
        "stall_block_causes": causes,
        "ledger": ledger.result(),
    }


def _yaw_rates(cameras: list) -> np.ndarray:
    """Degrees per second of heading change at each frame."""
    yaw = np.array([c.yaw for c in cameras])
    d = np.abs((np.diff(yaw, prepend=yaw[0]) + 180.0) % 360.0 - 180.0)
    return d * FPS


def derive(rows: list[dict], summary: dict, cameras: list, out: dict) -> dict[str, Any]:
    """Per-run figures beyond the session summary."""
    n = len(rows)
    rest = rows[1:] or rows
    rt_rest = np.array([r["realtime_bytes"] for r in rest], dtype=np.float64)
    upd = np.array([r["update_ms"] for r in rows])
    cpu = np.array([r["update_cpu_ms"] for r in rows])
    io = np.array([r["io_ms"] for r in rest])
    late = np.array([r["late_ms"] for r in rows])
    needed = max(summary["needed_bytes"], 1)
    used = max(summary["used_bytes"], 1)
    stalls = out["stall_frames"]
    yaw_rate = _yaw_rates(cameras)
    startup = [i for i in stalls if i <= int(FPS)]
    f0 = rows[0]
    # read but thrown away on arrival (the block had moved on): session-wide, as loaded_bytes
    # here; the rows' per-frame figures beside them (the warm-up's apart)
    discarded = int(summary["discarded_bytes"])
    disc_rows = np.array([r["discarded_bytes"] for r in rows], dtype=np.int64)
    return {
        "frames": n,
        "stall_frames": summary["stall_frames"],
        # over the frustum hull the renderer draws (account_hull), beside Qiu's triangle
        "stall_frames_hull": summary["stall_frames_hull"],
        # independent of stalls: bytes that arrived after the frame that first needed them was
        # due, and frames drawn coarser than needed (by how many levels)
        "late_bytes": summary["late_bytes"],
        "coarse_frames_by_levels": summary["coarse_frames_by_levels"],
        "coarse_frames": int(sum(summary["coarse_frames_by_levels"].values())),
        "stalls_per_10k": 1e4 * summary["stall_frames"] / n,
        "stall_frame_list": stalls[:200],
        "stalls_in_first_second": len(startup),
        "stall_block_causes": out["stall_block_causes"],
        "stall_yaw_rate_deg_s_mean": float(yaw_rate[stalls].mean()) if stalls else None,
        "path_yaw_rate_deg_s_mean": float(yaw_rate[1:].mean()) if n > 1 else 0.0,
        "needed_bytes": summary["needed_bytes"],
        "needed_bytes_per_frame_mean": summary["needed_bytes"] / n,
        "realtime_bytes_after_first_frame": summary["realtime_bytes_after_first_frame"],
        "realtime_pct_of_needed": 100.0 * summary["realtime_bytes_after_first_frame"] / needed,
        "realtime_pct_of_used": 100.0 * summary["realtime_bytes_after_first_frame"] / used,
        "warmup_ms": summary.get("warmup_ms", 0.0),
        "warmup_bytes": summary.get("warmup_bytes", 0),
        "frame0_loaded_bytes": f0["realtime_bytes"] + f0["prefetched_bytes"],
        "frame0_io_ms": f0["io_ms"],
        "frame0_wait_ms": f0["wait_ms"],
        # Qiu's "frame 1": the warm-up plus frame 0
        "first_frame_loaded_bytes": summary.get("warmup_bytes", 0)
        + f0["realtime_bytes"]
        + f0["prefetched_bytes"],
        "first_frame_needed_bytes": f0["needed_bytes"],
        "first_frame_ms": summary.get("warmup_ms", 0.0) + f0["wait_ms"],
        "realtime_bytes_per_frame_mean": float(rt_rest.mean()),
        "realtime_bytes_per_frame_max": int(rt_rest.max()),
        "frames_with_realtime_loads": int((rt_rest > 0).sum()),
        "prefetched_bytes": summary["prefetched_bytes"],
        "loaded_bytes": summary["loaded_bytes"],
        "used_bytes": summary["used_bytes"],
        "loaded_per_used": summary["loaded_bytes"] / used,
        "wasted_bytes": summary["wasted_bytes"],
        "discarded_bytes": discarded,
        "discarded_levels": int(summary["discarded_levels"]),
        "discarded_pct_of_read": 100.0 * discarded / max(summary["loaded_bytes"] + discarded, 1),
        "warmup_discarded_bytes": int(summary["warmup_discarded_bytes"]),
        "frames_discarded_bytes": int(disc_rows.sum()),
        "frames_with_discards": int((disc_rows > 0).sum()),
        **out["ledger"],
        "loaded_per_used_load": summary["loaded_bytes"] / max(out["ledger"]["used_load_bytes"], 1),
        "never_used_load_bytes": out["ledger"]["evicted_unused_bytes"]
        + out["ledger"]["resident_unused_bytes_at_end"],
        "peak_resident_bytes": summary["peak_resident_bytes"],
        "budget_bytes": summary["budget_bytes"],
        "max_update_ms": float(upd.max()),
        "max_update_ms_after_first": float(upd[1:].max()) if n > 1 else float(upd.max()),
        "p99_update_ms": float(np.percentile(upd, 99)),
        "max_update_cpu_ms": float(cpu.max()),
        "max_update_cpu_ms_after_first": float(cpu[1:].max()) if n > 1 else float(cpu.max()),
        "p99_update_cpu_ms": float(np.percentile(cpu, 99)),
        "frames_update_cpu_over_2ms": int((cpu > T_UPDATE_MS).sum()),
        "io_ms_per_frame_mean": float(io.mean()),
        "io_ms_per_frame_max": float(io.max()),
        "late_frames": int((late > 1000.0 / FPS).sum()),
        "max_late_ms": float(late.max()),
        "gc_during_update": out["gc_during_update"],
        "io_errors": summary["io_errors"],
        "cancelled_loads": summary["cancelled_loads"],
    }
