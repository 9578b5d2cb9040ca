"""What the caller did in the slow frames of ``bench/session_update.py``'s flight (issue 14).

The same flight (2049² store of 129² blocks, 4 loaders, default path, unpaced), each
``update()`` recorded: its thread-CPU time split by phase (``planner.needed``, pinning and
queueing, the frame pass, the rest), the garbage collections run on the caller's thread and
their CPU time (``gc.callbacks``), the wall time spent waiting for the session lock, the
visible and newly visible blocks, the pushes onto the load queue and the queue's length, the
net allocated blocks (``sys.getallocatedblocks``) and the caller's voluntary / involuntary
context switches (``getrusage(RUSAGE_THREAD)``). The wrappers cost a few µs per phase, so the
CPU figures are a little above ``session_update.py``'s. Prints the slowest frames and what the
frames of >= 1 ms had in common; writes ``bench/results/session_tail.json``.

Usage: python bench/session_tail.py [--frames 10000] [--workers 4] [--top 15]
"""

from __future__ import annotations

import argparse
import functools
import gc
import json
import os
import resource
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import RESULTS, WORK, machine_info, portable  # noqa: E402
from streamer.run import make_path  # noqa: E402
from streamer.session import open_session  # noqa: E402
from tiler.store import open_store  # noqa: E402

PHASES = ("needed", "pin_queue", "finish", "other")
FIELDS = (
    "cpu", "gc_cpu", "gc_count", "gc_gen", "lock_wait", "visible", "new_visible", "pushes",
    "queue_len", "alloc", "vol_cs", "invol_cs", *PHASES,
)  # fmt: skip


class _WaitLock:
    """A lock that adds the caller's contended-acquire wall time to ``rec``."""

    def __init__(self, main: int, rec: dict, cur: list[int]) -> None:
        self._lock, self._main, self._rec, self._cur = threading.Lock(), main, rec, cur

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        if threading.get_ident() != self._main or self._cur[0] < 0:
            return self._lock.acquire(blocking, timeout)
        if self._lock.acquire(False):
            return True
        t0 = time.perf_counter()
        ok = self._lock.acquire(blocking, timeout)
        self._rec["lock_wait"][self._cur[0]] += time.perf_counter() - t0
        return ok

    __enter__ = acquire

    def release(self) -> None:
        self._lock.release()

    def __exit__(self, *exc: object) -> None:
        self._lock.release()

    def locked(self) -> bool:
        return self._lock.locked()


def spread(v: np.ndarray, slow: np.ndarray) -> dict[str, float | None]:
    """p50, p99 and max of ``v`` and its mean over the ``slow`` frames: None (JSON null) when
    there are none (a mean of no frames is not 0)."""
    return {
        "p50": float(np.percentile(v, 50)),
        "p99": float(np.percentile(v, 99)),
        "max": float(v.max()),
        "mean_in_slow": float(v[slow].mean()) if slow.any() else None,
    }


def spread_line(name: str, v: dict[str, float | None]) -> str:
    """One printed line of :func:`spread`'s figures (``n/a`` for a mean over no frames)."""
    mean = v["mean_in_slow"]
    return (
        f"{name:10} p50 {v['p50']:.3f} p99 {v['p99']:.3f} max {v['max']:.3f} "
        f"mean in >= 1 ms frames {'n/a' if mean is None else f'{mean:.3f}'}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--top", type=int, default=15)
    a = ap.parse_args(argv)
    dst = WORK / "session_update" / "s.zarr"
    if not (dst / "zarr.json").exists():
        print(f"no store at {dst}: run bench/session_update.py first", file=sys.stderr)
        return 1
    store = open_store(dst)
    cams = make_path(store, "default", frames=a.frames, fps=60)
    n = a.frames
    rec = {k: np.zeros(n) for k in FIELDS}
    main_id = threading.get_ident()
    cur = [-1]
    gc_t0: dict[int, float] = {}

    def on_gc(phase: str, info: dict) -> None:
        if threading.get_ident() != main_id or cur[0] < 0:
            return
        if phase == "start":
            gc_t0[0] = time.thread_time()
        elif 0 in gc_t0:
            i = cur[0]
            rec["gc_cpu"][i] += time.thread_time() - gc_t0.pop(0)
            rec["gc_count"][i] += 1
            rec["gc_gen"][i] = max(rec["gc_gen"][i], info["generation"] + 1)

    def timed(obj: object, name: str, key: str) -> None:
        fn = getattr(obj, name)

        @functools.wraps(fn)
        def wrapped(*args, **kw):
            if threading.get_ident() != main_id or cur[0] < 0:
                return fn(*args, **kw)
            c0 = time.thread_time()
            try:
                return fn(*args, **kw)
            finally:
                rec[key][cur[0]] += time.thread_time() - c0

        setattr(obj, name, wrapped)

    load0 = os.getloadavg()[0]
    gc.callbacks.append(on_gc)
    try:
        with open_session(store, budget_mb=128, workers=a.workers) as s:
            s.loader.cv = s._cv = threading.Condition(_WaitLock(main_id, rec, cur))
            timed(s.planner, "needed", "needed")
            timed(s, "_pin_and_queue", "pin_queue")
            timed(s, "_finish_frame", "finish")
            push = s.loader.push

            def counted_push(b, level=None):
                if threading.get_ident() == main_id and cur[0] >= 0:
                    rec["pushes"][cur[0]] += 1
                return push(b, level)

            s.loader.push = counted_push
            s.warm_up(cams[0])
            prev: set = set()
            for i, cam in enumerate(cams):
                cur[0] = i
                ru0 = resource.getrusage(resource.RUSAGE_THREAD)
                a0 = sys.getallocatedblocks()
                c0 = time.thread_time()
                f = s.update(cam, 1 / 60)
                rec["cpu"][i] = time.thread_time() - c0
                rec["alloc"][i] = sys.getallocatedblocks() - a0
                ru1 = resource.getrusage(resource.RUSAGE_THREAD)
                rec["vol_cs"][i] = ru1.ru_nvcsw - ru0.ru_nvcsw
                rec["invol_cs"][i] = ru1.ru_nivcsw - ru0.ru_nivcsw
                rec["queue_len"][i] = len(s.loader.queue)
                vis = set(f.blocks)
                rec["visible"][i], rec["new_visible"][i] = len(vis), len(vis - prev)
                prev = vis
            cur[0] = -1
    finally:
        gc.callbacks.remove(on_gc)
    rec["other"] = rec["cpu"] - rec["needed"] - rec["pin_queue"] - rec["finish"]
    load1 = os.getloadavg()[0]
    ms = {k: rec[k] * 1e3 for k in ("cpu", "gc_cpu", "lock_wait", *PHASES)}
    cpu = ms["cpu"]
    slow = cpu >= 1.0

    out = {
        "frames": n,
        "workers": a.workers,
        "loadavg_start_end": [load0, load1],
        "ms": {k: spread(v, slow) for k, v in ms.items()},
        "counts": {
            k: spread(rec[k], slow)
            for k in (
                "visible",
                "new_visible",
                "pushes",
                "queue_len",
                "alloc",
                "vol_cs",
                "invol_cs",
            )
        },
        "slow_frames": int(slow.sum()),
        "slow_frames_with_caller_gc": int((slow & (rec["gc_count"] > 0)).sum()),
        "slow_frames_with_preemption": int((slow & (rec["invol_cs"] > 0)).sum()),
        "frames_with_caller_gc": int((rec["gc_count"] > 0).sum()),
        "full_collections_on_caller": int((rec["gc_gen"] == 3).sum()),
        "cpu_mean_by_preemptions": {
            str(k): float(cpu[rec["invol_cs"] == k].mean())
            for k in range(4)
            if (rec["invol_cs"] == k).sum() >= 20
        },
        "top": [],
        "machine": machine_info(),
    }
    print(f"# {n} frames, {a.workers} loaders, load {load0:.1f} -> {load1:.1f}; CPU ms per phase")
    cols = ("cpu", "needed", "pin_queue", "finish", "other", "gc_cpu", "lock_wait")
    counts = ("gc_gen", "visible", "new_visible", "pushes", "queue_len", "vol_cs", "invol_cs")
    print(f"{'frame':>6} " + " ".join(f"{c:>9}" for c in cols) + " " + " ".join(counts))
    for i in np.argsort(cpu)[::-1][: a.top]:
        row = {c: float(ms[c][i]) for c in cols} | {c: int(rec[c][i]) for c in counts}
        out["top"].append({"frame": int(i), **row})
        print(
            f"{i:6d} "
            + " ".join(f"{ms[c][i]:9.3f}" for c in cols)
            + " "
            + " ".join(f"{int(rec[c][i]):>{len(c)}d}" for c in counts)
        )
    print(
        f"frames >= 1 ms: {out['slow_frames']} ({out['slow_frames_with_caller_gc']} with a "
        f"collection on the caller, {out['slow_frames_with_preemption']} preempted); frames "
        f"with a collection: {out['frames_with_caller_gc']}, full: "
        f"{out['full_collections_on_caller']}"
    )
    for k, v in out["ms"].items():
        print(spread_line(k, v))
    print(
        "CPU ms mean by involuntary context switches in the frame:", out["cpu_mean_by_preemptions"]
    )
    path = RESULTS / "session_tail.json"
    path.write_text(json.dumps(portable(out), indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
