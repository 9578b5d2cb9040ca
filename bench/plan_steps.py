"""The planning thread's cost per plan, by part (issue 14): the prefetch plan itself
(``Planner.prefetch``), writing its wants into the cache (``LevelCache.prefetch_steps``), the
load queue's rebuild (``Loader.reschedule_steps``) and the whole plan (``PlanThread.plan``),
thread-CPU ms per plan.

Flies the 2049² store of ``bench/session_update.py`` (built there; ``--block-size 33``: 64×64
blocks, ~590 in view) unpaced with ``--workers 0`` by default, so every plan runs on the
caller's thread with nothing beside it (the figures that do not depend on contention; with
workers the planning thread shares the 2 cores with the loaders and costs more). Prints a
table and writes ``bench/results/plan_steps.json`` (``--out`` for runs of other code).

Usage: python bench/plan_steps.py [--block-size 33] [--frames 2000] [--workers 0]
       [--budget-mb 128] [--plan-step N] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import RESULTS, machine_info, portable  # noqa: E402
from bench.session_update import bench_store  # noqa: E402
from streamer.cache import LevelCache  # noqa: E402
from streamer.loader import Loader  # noqa: E402
from streamer.planner import Planner  # noqa: E402
from streamer.run import make_path  # noqa: E402
from streamer.session import open_session  # noqa: E402


def _timed(spent: dict[str, list[float]], name: str, fn):
    def run(*args, **kwargs):
        c0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            spent[name].append(time.thread_time() - c0)

    return run


def _timed_steps(spent: dict[str, list[float]], name: str, fn):
    """A generator method timed over all its steps (the time between them not counted)."""

    def run(*args, **kwargs):
        gen, total = fn(*args, **kwargs), 0.0
        while True:
            c0 = time.thread_time()
            try:
                item = next(gen)
            except StopIteration:
                spent[name].append(total + time.thread_time() - c0)
                return
            total += time.thread_time() - c0
            yield item

    return run


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--block-size", type=int, default=33)
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--workers", type=int, default=0)
    ap.add_argument("--budget-mb", type=float, default=128.0)
    ap.add_argument("--plan-step", type=int, default=None, help="blocks per locked step")
    ap.add_argument("--out", type=Path, default=RESULTS / "plan_steps.json")
    a = ap.parse_args(argv)
    if a.plan_step is not None:
        import streamer.planthread as planthread

        planthread.PLAN_STEP_BLOCKS = a.plan_step  # (read at each plan)
    b = a.block_size
    store = bench_store(b)
    cams = make_path(store, "default", frames=a.frames, fps=60)
    spent: dict[str, list[float]] = defaultdict(list)
    from streamer.session import Session

    if hasattr(Session, "_plan_prefetch"):  # code before streamer.planthread (A/B runs)
        whole = (Session, "_plan_prefetch", _timed)
    else:
        from streamer.planthread import PlanThread

        whole = (PlanThread, "plan", _timed)
    parts = {
        "prefetch plan": (Planner, "prefetch", _timed),
        "cache wants (steps)": (LevelCache, "prefetch_steps", _timed_steps),
        "queue rebuild (steps)": (Loader, "reschedule_steps", _timed_steps),
        "whole plan": whole,
    }
    saved = [(cls, name, getattr(cls, name)) for cls, name, _ in parts.values()]
    for label, (cls, name, wrap) in parts.items():
        setattr(cls, name, wrap(spent, label, getattr(cls, name)))
    try:
        with open_session(store, budget_mb=a.budget_mb, workers=a.workers) as s:
            s.warm_up(cams[0])
            spent.clear()
            for cam in cams:
                s.update(cam, 1 / 60)
            entries = len(s.cache._entries)
    finally:
        for cls, name, fn in saved:
            setattr(cls, name, fn)
    print(f"# {a.frames} frames, {a.workers} loaders, {b}² blocks, {entries} cache entries")
    print(f"{'part':24} {'plans':>6} {'p50 ms':>8} {'mean ms':>8} {'p99 ms':>8}")
    rows = {}
    for label in parts:
        ms = np.array(spent[label]) * 1e3
        rows[label] = {
            "plans": len(ms),
            "p50_ms": float(np.median(ms)),
            "mean_ms": float(ms.mean()),
            "p99_ms": float(np.percentile(ms, 99)),
        }
        r = rows[label]
        print(
            f"{label:24} {r['plans']:6d} {r['p50_ms']:8.3f} {r['mean_ms']:8.3f} {r['p99_ms']:8.3f}"
        )
    out = {
        "frames": a.frames,
        "workers": a.workers,
        "block_size": b,
        "budget_mb": a.budget_mb,
        "plan_step_blocks": a.plan_step,
        "cache_entries": entries,
        "parts": rows,
        "machine": machine_info(),
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(portable(out), indent=1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
