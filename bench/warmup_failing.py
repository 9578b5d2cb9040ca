"""A warm-up over a server that fails every read: how many reads it makes and how long it takes.

Builds a 257×321 synthetic store of 33² blocks in ``bench/work`` once, then warms a session up
(2 workers, ``retries`` 3, backoff 5–20 ms, nothing raised) for the first camera of the default
fly-through while every read fails after ``--read-s`` seconds (a timeout, scaled down: the
scene of ``tests/streamer/test_slow_failures.py``). Reads are counted per block up to the
moment ``warm_up`` returns. Each block must fail ``retries`` times for the warm-up to end, so
``retries`` reads per block is the least it can make. Prints a table and writes
``bench/results/warmup_failing.json``.

Usage: python bench/warmup_failing.py [--runs 3] [--read-s 0.02] [--out FILE]
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import RESULTS, WORK, machine_info, portable  # noqa: E402
from streamer.frames import SessionConfig  # noqa: E402
from streamer.paths import default_flythrough  # noqa: E402
from streamer.session import Session  # noqa: E402
from tiler.store import open_store  # noqa: E402
from tiler.synth import synth_dem  # noqa: E402
from tiler.tile import TileOptions, tile  # noqa: E402

CONFIG = dict(budget_mb=64, workers=2, retries=3, backoff_s=0.005, max_backoff_s=0.02,
              raise_on_failure=False, wait_timeout_s=60.0)  # fmt: skip


def _store():
    root = WORK / "warmup_failing"
    root.mkdir(parents=True, exist_ok=True)
    src, dst = root / "dem.tif", root / "s.zarr"
    if not src.exists():
        synth_dem(src, 321, seed=5)
    if not (dst / "zarr.json").exists():
        tile(src, dst, TileOptions(block_size=33, workers=1, executor="threads"))
    return open_store(dst)


def _run(store, read_s: float) -> dict:
    z0, z1 = store.meta.extra["value_range"]
    cam = default_flythrough(store.grid, z0, z1, 1, 60.0, viewport=(160, 120))[0]
    reads: collections.Counter = collections.Counter()
    lock, counting = threading.Lock(), [True]

    def failing(block, level) -> None:
        with lock:
            if counting[0]:
                reads[block] += 1
        time.sleep(read_s)
        raise OSError("injected failure")

    with Session(store, SessionConfig(**CONFIG), read_hook=failing) as s:
        t0 = time.perf_counter()
        s.warm_up(cam)
        seconds = time.perf_counter() - t0
        with lock:
            counting[0] = False
    per_block = collections.Counter(reads.values())
    return {
        "seconds": seconds,
        "blocks": len(reads),
        "reads": sum(reads.values()),
        "reads_per_block": {str(k): v for k, v in sorted(per_block.items())},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--read-s", type=float, default=0.02, help="seconds before a read fails")
    ap.add_argument("--out", type=Path, default=RESULTS / "warmup_failing.json")
    a = ap.parse_args(argv)
    store = _store()
    runs = [_run(store, a.read_s) for _ in range(a.runs)]
    print(f"# every read fails after {a.read_s:g} s; 2 workers, retries {CONFIG['retries']}")
    print(f"{'run':>3} {'blocks':>6} {'reads':>6} {'s':>6}  reads per block: blocks")
    for i, r in enumerate(runs):
        hist = ", ".join(f"{k}: {v}" for k, v in r["reads_per_block"].items())
        print(f"{i:3d} {r['blocks']:6d} {r['reads']:6d} {r['seconds']:6.2f}  {hist}")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(
        json.dumps(
            portable(
                {"read_s": a.read_s, "config": CONFIG, "runs": runs, "machine": machine_info()}
            ),
            indent=1,
        )
    )
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
