"""Full garbage collections in a flight, with and without ``SessionConfig(freeze_gc=True)``.

Usage::

    python bench/gc_freeze.py [--frames 6000] [--reps 2] [--out PATH]

Builds a 2049² synthetic store of 33² blocks (64×64 blocks, ~550 in view) in ``bench/work``
once, then flies its default path unpaced (``update()`` back to back, 4 loaders) in a fresh
child process per run, alternating ``freeze_gc`` off and on (a freeze is process-wide, so
the two cannot share a process). Per run: the collections of each generation on any thread
(``gc.callbacks``, wall ms), the objects a full pass walks after the warm-up, and the caller's
``update`` wall and CPU time (p50 / p99 / p99.9 / max). Prints a table and writes
``bench/results/gc_freeze.json``.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np  # noqa: E402

from bench.common import RESULTS, WORK, machine_info, portable  # noqa: E402

STORE = WORK / "gc_freeze" / "s.zarr"


def _store():
    from tiler.store import open_store
    from tiler.synth import synth_dem
    from tiler.tile import TileOptions, tile

    src = STORE.parent / "dem.tif"
    STORE.parent.mkdir(parents=True, exist_ok=True)
    if not src.exists():
        synth_dem(src, 2049, seed=3)
    if not (STORE / "zarr.json").exists():
        tile(src, STORE, TileOptions(block_size=33, workers=2, executor="threads"))
    return open_store(STORE)


def _q(a: np.ndarray) -> dict:
    ms = np.asarray(a) * 1e3
    return {
        "p50": float(np.percentile(ms, 50)),
        "p99": float(np.percentile(ms, 99)),
        "p99_9": float(np.percentile(ms, 99.9)),
        "max": float(ms.max()),
    }


def fly(freeze: bool, frames: int) -> dict:
    """One flight in this process: the run's row (see the module doc)."""
    from streamer.gcfreeze import tracked_in_passes
    from streamer.run import make_path
    from streamer.session import open_session

    store = _store()
    cams = make_path(store, "default", frames=frames, fps=60)
    colls: list[tuple[int, float, str]] = []
    start: dict[int, float] = {}

    def on_gc(phase: str, info: dict) -> None:
        tid = threading.get_ident()
        if phase == "start":
            start[tid] = time.perf_counter()
        elif tid in start:
            name = threading.current_thread().name
            colls.append((info["generation"], time.perf_counter() - start.pop(tid), name))

    wall, cpu = np.zeros(frames), np.zeros(frames)
    load0 = os.getloadavg()[0]
    with open_session(store, budget_mb=256, workers=4, freeze_gc=freeze) as s:
        s.warm_up(cams[0])
        walked = tracked_in_passes()
        gc.callbacks.append(on_gc)
        try:
            for i, cam in enumerate(cams):
                t0, c0 = time.perf_counter(), time.thread_time()
                s.update(cam, 1 / 60)
                wall[i], cpu[i] = time.perf_counter() - t0, time.thread_time() - c0
        finally:
            gc.callbacks.remove(on_gc)
    gens = {}
    for g in range(3):
        ms = [d * 1e3 for gen, d, _ in colls if gen == g]
        gens[str(g)] = {"n": len(ms), "max_ms": max(ms, default=0.0), "sum_ms": sum(ms)}
    full_threads = sorted({n for gen, _, n in colls if gen == 2})
    return {
        "freeze_gc": freeze,
        "frames": frames,
        "walked_after_warm_up": walked,
        "frozen": gc.get_freeze_count(),
        "collections": gens,
        "full_collection_threads": full_threads,
        "update_wall_ms": _q(wall),
        "update_cpu_ms": _q(cpu),
        "frames_over_20ms_wall": int((wall > 0.020).sum()),
        "loadavg_start_end": [load0, os.getloadavg()[0]],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6000)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--out", default=str(RESULTS / "gc_freeze.json"))
    ap.add_argument("--child", choices=["on", "off"], help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(fly(a.child == "on", a.frames)))
        return 0
    _store()
    runs = []
    for rep in range(a.reps):
        for mode in ("off", "on"):
            out = subprocess.run(
                [sys.executable, __file__, "--child", mode, "--frames", str(a.frames)],
                capture_output=True, text=True, check=True,
            )  # fmt: skip
            row = json.loads(out.stdout.strip().splitlines()[-1])
            row["rep"] = rep
            runs.append(row)
            c2, w = row["collections"]["2"], row["update_wall_ms"]
            print(
                f"rep {rep} freeze {mode:3}: walked {row['walked_after_warm_up']:>7,} "
                f"full GCs {c2['n']:>2} (max {c2['max_ms']:6.1f} ms) "
                f"gen0/1 {row['collections']['0']['n']}/{row['collections']['1']['n']}  "
                f"update wall p99 {w['p99']:.2f} p99.9 {w['p99_9']:.2f} max {w['max']:6.1f} ms"
                f"  cpu p99 {row['update_cpu_ms']['p99']:.2f} max "
                f"{row['update_cpu_ms']['max']:.2f}  >20ms {row['frames_over_20ms_wall']}",
                flush=True,
            )
    out_path = Path(a.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(
        json.dumps(
            portable({"store": str(STORE), "runs": runs, "machine": machine_info()}), indent=1
        )
    )
    print(f"wrote {portable(out_path)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
