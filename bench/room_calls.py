"""How long a loader's room question takes under a tight budget (issue 14's lock holds).

Flies ``bench/session_update.py``'s flight (the 2049² store in 33² blocks, 4 loaders, 3,000
frames unpaced) with a budget just above what the view pins (default 0.45 MiB: the pins alone
need ~0.40), so that loads are refused for lack of room, and times every
``LevelCache._room_possible`` call (the question a loader's take asks under the session's lock)
in thread-CPU µs. A refusal that finds too little walks every cache entry; the calls over
100 µs are mostly those walks; ``index_builds`` counts the walks that went to the end and
built the index the next questions read (``LevelCache._keep_free``; -1 for code without it).
Prints a table and writes ``bench/results/room_calls.json`` (``--out`` for runs of other code
in a worktree).

Usage: python bench/room_calls.py [--budget-mb 0.45] [--frames 3000] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import RESULTS, machine_info, portable  # noqa: E402
from bench.session_update import main as fly  # noqa: E402
from streamer.cache import LevelCache  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget-mb", type=float, default=0.45)
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--out", type=Path, default=RESULTS / "room_calls.json")
    a = ap.parse_args(argv)
    spent: list[float] = []
    builds = [0]
    real = LevelCache._room_possible
    real_keep = getattr(LevelCache, "_keep_free", None)  # (absent in the code before it)

    def timed(self, block, nbytes):
        c0 = time.thread_time()
        try:
            return real(self, block, nbytes)
        finally:
            spent.append(time.thread_time() - c0)

    def kept(self, stale, held):
        builds[0] += 1
        return real_keep(self, stale, held)

    LevelCache._room_possible = timed
    if real_keep is not None:
        LevelCache._keep_free = kept
    flight = a.out.with_name(a.out.stem + "_flight.json")
    try:
        fly(["--block-size", "33", "--budget-mb", str(a.budget_mb), "--frames", str(a.frames),
             "--out", str(flight)])  # fmt: skip
        flown = json.loads(flight.read_text())
    finally:
        LevelCache._room_possible = real
        if real_keep is not None:
            LevelCache._keep_free = real_keep
        flight.unlink(missing_ok=True)
    us = np.array(spent) * 1e6
    long = us[us > 100]
    row = {
        "calls": int(len(us)),
        "p50_us": float(np.percentile(us, 50)),
        "p99_us": float(np.percentile(us, 99)),
        "p999_us": float(np.percentile(us, 99.9)),
        "max_us": float(us.max()),
        "over_100us": int(len(long)),
        "over_100us_mean_us": float(long.mean()) if len(long) else 0.0,
        "total_ms": float(us.sum() / 1e3),
        "index_builds": builds[0] if real_keep is not None else -1,
    }
    print(f"# room questions, thread-CPU µs, budget {a.budget_mb:g} MiB, {a.frames} frames")
    print(" ".join(f"{k:>18}" for k in row))
    print(" ".join(f"{v:18.1f}" if isinstance(v, float) else f"{v:18d}" for v in row.values()))
    out = {"budget_mb": a.budget_mb, "frames": a.frames, "room": row,
           "evicted_bytes": flown["evicted_bytes"], "machine": machine_info()}  # fmt: skip
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(portable(out), indent=1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
