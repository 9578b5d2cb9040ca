"""What an outage costs the load queue and the session's lock: blocks in backoff asleep on their
own heap (now) against the pop that took each of them out and put it back (before, 4606c39).

Two parts, both run on the code of the checkout with the old pop patched in for "before":

* ``queue``: a :class:`~streamer.loadqueue.LoadQueue` of ``n`` blocks that all failed just now
  (n = 100 … 20,000): ms of ``rebuild`` and the median ms of a ``pop`` that finds nothing due.
* ``session``: a store of 64×64 blocks (2049² samples, blocks of 33²) flown unpaced for
  ``--frames`` frames by a session with 2 loaders whose every read fails (a ``read_hook``
  raising ``ConnectionError``: a server gone; no warm-up can finish, so only its compiled
  planner is loaded); the lock probed (:mod:`streamer.lockprobe`).
  Reported: the caller's CPU per ``update`` and the lock holds of each thread role, p50 /
  p99 / max (µs), the caller's waits for the lock (how often it found the lock held, and
  for how long: a contended acquisition waits for the GIL too) and the queue's length at
  the end.

The session part alternates before and after ``--reps`` times (timings are noisy; compare
within a run). The largest ``update`` (tens of ms, both ways) is the collector's: its cost
lands in whichever call allocates when a full collection is due.

Usage: python bench/outage_queue.py [--frames 600] [--reps 3] [--out PATH]
Prints two tables and writes ``bench/results/outage_queue.json``.
"""

from __future__ import annotations

import argparse
import heapq
import json
import logging
import statistics
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import REPO, RESULTS, WORK, machine_info, portable  # noqa: E402
from streamer.loadqueue import LoadQueue  # noqa: E402


def old_pop(self, now, take, probe=True):
    """``LoadQueue.pop`` before blocks in backoff slept apart (4606c39)."""
    waiting, found, best = [], None, self._best
    heaps = (self._failed, self._heap) if probe else (self._heap, self._failed)
    for heap in heaps:
        failed_heap = heap is self._failed
        while heap:
            entry, b = heapq.heappop(heap)
            key = entry[-1] if failed_heap else entry
            if best.get(b) == key:
                del best[b]
            if not self.retryable(b):
                continue
            if self.backing_off(b, now) or (not failed_heap and self.is_failed(b)):
                waiting.append((key, b))
                continue
            job = take(b)
            if job is not None:
                found = (b, job)
                break
        if found is not None:
            break
    for key, b in waiting:
        self._enqueue(key, b)
        if b not in best or key < best[b]:
            best[b] = key
    return found


@contextmanager
def before():
    """The old queue: its pop, and a rebuild that puts nothing to sleep."""
    pop, rebuild = LoadQueue.pop, LoadQueue.rebuild
    LoadQueue.pop = old_pop
    LoadQueue.rebuild = lambda self, items, now=None: rebuild(self, items)
    try:
        yield
    finally:
        LoadQueue.pop, LoadQueue.rebuild = pop, rebuild


def queue_row(n: int) -> dict:
    """ms of a rebuild of ``n`` blocks failed just now, and the median ms of 30 pops."""
    q = LoadQueue(retries=3, backoff_s=0.1, max_backoff_s=1.0)
    items = []
    for i in range(n):
        b = (i // 256, i % 256)
        for _ in range(3):
            q.failed_read(b, 100.0)
        items.append(((0, 0, float(i)), b))
    t0 = time.perf_counter()
    q.rebuild(items, 100.0)
    rebuild_ms = (time.perf_counter() - t0) * 1e3
    pops = []
    for _ in range(30):
        t0 = time.perf_counter()
        if q.pop(100.2, lambda b: b) is not None:
            raise RuntimeError("a block in backoff was popped")
        pops.append((time.perf_counter() - t0) * 1e3)
    return {"n": n, "rebuild_ms": rebuild_ms, "pop_ms": statistics.median(pops), "len": len(q)}


def _store():
    from tiler.synth import synth_dem
    from tiler.tile import TileOptions, tile

    root = WORK / "outage_queue"
    root.mkdir(parents=True, exist_ok=True)
    src, dst = root / "dem.tif", root / "s.zarr"
    if not src.exists():
        synth_dem(src, 2049, seed=5)
    if not (dst / "zarr.json").exists():
        tile(src, dst, TileOptions(block_size=33, workers=2, executor="threads"))
    return dst


def _gone(block, level) -> None:
    raise ConnectionError(f"server gone (reading {block} level {level})")


def _pct(a) -> dict:
    a = np.asarray(a, dtype=np.float64)
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max())}  # fmt: skip


def session_row(dst, frames: int) -> dict:
    """The caller's CPU per update and the lock holds by role (µs) over a flight in an outage."""
    from streamer.levels import warm_up as kernels_warm_up
    from streamer.lockprobe import install
    from streamer.run import make_path
    from streamer.session import Session, SessionConfig
    from tiler.store import open_store

    store = open_store(dst)
    cams = make_path(store, "default", frames=frames, fps=60)
    cpu = []
    cfg = SessionConfig(budget_mb=256, workers=2, raise_on_failure=False)
    with Session(store, cfg, read_hook=_gone) as s:
        probe = install(s)
        kernels_warm_up(s.loader.errors)  # the compiled planner, as `warm_up` loads it
        for cam in cams:
            c0 = time.thread_time()
            s.update(cam, 1 / 60)
            cpu.append((time.thread_time() - c0) * 1e6)
        queued = len(s.loader.queue)
        failed = len(s.loader.queue.failed_blocks())
    roles = {r: _pct([h[0] * 1e6 for h in hs]) for r, hs in probe.by_role().items()}
    waits = np.array(probe.waits_by_role().get("caller", [0.0])) * 1e6
    caller = {**_pct(waits), "acquires": len(waits), "contended": int((waits > 0).sum()),
              "sum_ms": float(waits.sum() / 1e3)}  # fmt: skip
    return {"update_cpu_us": _pct(cpu), "lock_hold_wall_us": roles, "queued_at_end": queued,
            "failed_at_end": failed, "caller_waits_us": caller}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", default=str(RESULTS / "outage_queue.json"))
    a = ap.parse_args(argv)
    logging.getLogger("streamer").setLevel(logging.ERROR)  # (a warning per failed read)
    sizes = (100, 1000, 5000, 20000)
    out: dict = {"machine": machine_info(), "queue": {}, "session": {}}
    for name in ("before", "after"):
        if name == "before":
            with before():
                out["queue"][name] = [queue_row(n) for n in sizes]
        else:
            out["queue"][name] = [queue_row(n) for n in sizes]
    print("# queue of n blocks all in backoff: rebuild ms, median pop ms (before -> after)")
    print(f"{'n':>6} {'rebuild before':>15} {'after':>8} {'pop before':>11} {'after':>8}")
    for b, f in zip(out["queue"]["before"], out["queue"]["after"], strict=True):
        print(f"{b['n']:6d} {b['rebuild_ms']:15.3f} {f['rebuild_ms']:8.3f} "
              f"{b['pop_ms']:11.3f} {f['pop_ms']:8.3f}")  # fmt: skip
    dst = _store()
    out["session"] = {"before": [], "after": []}
    for _ in range(a.reps):
        with before():
            out["session"]["before"].append(session_row(dst, a.frames))
        out["session"]["after"].append(session_row(dst, a.frames))
    print(f"# {a.frames} frames unpaced over 64x64 blocks, every read failing, 2 loaders (µs)")
    print(f"{'':7} {'what':22} {'p50':>9} {'p99':>9} {'max':>10}")
    for rep in range(a.reps):
        for name in ("before", "after"):
            row = out["session"][name][rep]
            lines = [("update CPU", row["update_cpu_us"])]
            lines += [(f"lock hold {r}", v) for r, v in sorted(row["lock_hold_wall_us"].items())]
            lines += [("caller's waits", row["caller_waits_us"])]
            for what, v in lines:
                print(f"{name:7} {what:22} {v['p50']:9.1f} {v['p99']:9.1f} {v['max']:10.1f}")
            w = row["caller_waits_us"]
            print(f"{name:7} caller found the lock held {w['contended']} of {w['acquires']} "
                  f"times, waited {w['sum_ms']:.1f} ms in all")  # fmt: skip
            print(f"{name:7} queued at the end {row['queued_at_end']}, "
                  f"failed {row['failed_at_end']}")  # fmt: skip
    path = Path(a.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(portable(out), indent=1))
    print(f"# wrote {path.relative_to(REPO) if path.is_relative_to(REPO) else path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
