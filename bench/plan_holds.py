"""The planning thread's locked steps one by one (issue 14): thread-CPU µs of each step, by
the generator it advances and the ``yield`` it stopped at.

Flies the 2049² store of ``bench/session_update.py`` (``--block-size 33``: 64×64 blocks, ~590
in view) unpaced with 4 loaders and ``freeze_gc``, with ``PlanThread.stepwise`` timing each
``next()`` under the lock. A generator's ``yield`` sites are numbered by their line, so runs of
different code compare by site (``LevelCache.prefetch_steps``: 1 the resets of the previous
plan's wants, 2 the new wants; ``Loader.reschedule_steps``: 1 the short blocks' keys, 2 the
queue's rebuild; ``end`` the step that finishes the generator). Per site: the first step after
the site before it (``first``) apart from the others (``rest``), since a step that begins a
phase carries its set-up. Prints a table and writes ``bench/results/plan_holds.json``
(``--out`` for runs of other code).

Usage: python bench/plan_holds.py [--block-size 33] [--frames 3000] [--out FILE]
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
from streamer import planthread  # noqa: E402
from streamer.run import make_path  # noqa: E402
from streamer.session import open_session  # noqa: E402


def _probe(rec: dict[tuple[str, int, str], list[float]]):
    """A ``PlanThread.stepwise`` that records each step's thread-CPU seconds in ``rec`` under
    ``(generator, yield line or -1 at the end, "first" or "rest")``."""

    def stepwise(self, steps) -> None:
        name = steps.gi_code.co_name
        prev = None
        while True:
            with self.loader.cv:
                c0 = time.thread_time()
                got = next(steps, planthread._DONE)
                dt = time.thread_time() - c0
                frame = steps.gi_frame
                line = frame.f_lineno if frame is not None else -1
                rec[(name, line, "first" if line != prev else "rest")].append(dt)
                prev = line
                if got is planthread._DONE:
                    return

    return stepwise


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--block-size", type=int, default=33, help="the store's block edge")
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--out", type=Path, default=None, help="the JSON to write")
    a = ap.parse_args(argv)
    store = bench_store(a.block_size)
    cams = make_path(store, "default", frames=a.frames, fps=60)
    rec: dict[tuple[str, int, str], list[float]] = defaultdict(list)
    real = planthread.PlanThread.stepwise
    planthread.PlanThread.stepwise = _probe(rec)
    try:
        with open_session(store, budget_mb=128, workers=4, freeze_gc=True) as s:
            s.warm_up(cams[0])
            rec.clear()
            for cam in cams:
                s.update(cam, 1 / 60)
    finally:
        planthread.PlanThread.stepwise = real
    sites: dict[str, list[int]] = defaultdict(list)
    for name, line, _ in rec:
        if line >= 0 and line not in sites[name]:
            sites[name].append(line)
    rows = []
    print(f"# {a.frames} frames, 4 loaders, 2049² store of {a.block_size}² blocks; µs of CPU")
    print(f"{'generator':18} {'site':>4} {'step':>5} {'steps':>7} {'p50':>6} {'p99':>6} "
          f"{'max':>7} {'>=50':>5} {'sum ms':>7}")  # fmt: skip

    def order(item):
        (name, line, kind), _ = item
        return name, line < 0, line, kind

    for (name, line, kind), vals in sorted(rec.items(), key=order):
        us = np.array(vals) * 1e6
        site = "end" if line < 0 else str(sorted(sites[name]).index(line) + 1)
        row = {
            "generator": name,
            "site": site,
            "step": kind,
            "steps": len(us),
            "p50_us": float(np.percentile(us, 50)),
            "p99_us": float(np.percentile(us, 99)),
            "max_us": float(us.max()),
            "ge_50": int((us >= 50).sum()),
            "sum_ms": float(us.sum() / 1e3),
        }
        rows.append(row)
        print(f"{name:18} {site:>4} {kind:>5} {row['steps']:7d} {row['p50_us']:6.1f} "
              f"{row['p99_us']:6.1f} {row['max_us']:7.1f} {row['ge_50']:5d} "
              f"{row['sum_ms']:7.1f}")  # fmt: skip
    out = a.out or RESULTS / "plan_holds.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            portable(
                {
                    "frames": a.frames,
                    "block_size": a.block_size,
                    "rows": rows,
                    "machine": machine_info(),
                }
            ),
            indent=1,
        )  # fmt: skip
    )
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
