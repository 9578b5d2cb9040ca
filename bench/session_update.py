"""The cost of ``Session.update`` on the caller's thread (issue 14): wall and thread-CPU time.

Builds a 2049² synthetic store (blocks of 129²) in ``bench/work`` once, flies the default path
unpaced (``update()`` back to back while 4 loader threads fill behind it) and reports p50/p99/max
of the wall time around each call and of the caller's CPU time (``time.thread_time``), which is
the figure that does not depend on what else the machine runs. ``--locks`` flies the path
once more with the session's lock probed (:mod:`streamer.lockprobe`, which slows every hold a
little) and reports each thread role's lock holds (µs, wall and thread CPU; how many held the
CPU for 20, 50 and 100 µs or more, and the CPU held in all, since a percentile moves with the
number of short holds) and the reads,
decodes or planning found under the lock (0 expected), beside a ``floor`` row: an empty hold of
a probed lock of its own that the caller takes after each update (the probe's clocks and what
the machine adds to any hold at that moment: a hold's length above it is its work).
``TERRASTREAM_KERNELS=numpy`` runs the planning's numpy reference instead of its compiled
kernels. Prints a table and writes
``bench/results/session_update.json``.

The third row, ``plan``, is ``FrameStats.update_cpu_ms``: the caller's CPU without the reads
that ``--workers 0`` makes it do inline, so ``--workers 0`` measures the caller's own planning
with no loader or planning thread beside it (the figure that does not depend on contention).
``--block-size 33`` flies the same DEM tiled in blocks of 33² (64×64 blocks, ~550 in view
against ~40 at 129²: the caller's per-block work) and writes ``session_update_b33.json``.

``--budget-mb`` (default 128: nothing is evicted) flies under a budget smaller than the flight,
where loads must evict and some are refused (the evicted bytes are printed); ``--linger-s``
sets ``SessionConfig.linger_s`` (levels unwanted that long are unloaded by the planning thread);
``--freeze-gc`` sets ``freeze_gc`` (no full collection walks the start-up's objects: the
maxima without the 60–90 ms collections); ``--plan-step N`` sets the planning thread's blocks
per locked step (``streamer.planthread.PLAN_STEP_BLOCKS``);
``--out`` names the JSON (for runs of other code in a worktree).

Usage: python bench/session_update.py [--frames 10000] [--workers 4] [--locks] [--block-size 129]
       [--budget-mb 128] [--linger-s S] [--freeze-gc] [--plan-step N]
       [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import RESULTS, WORK, machine_info, portable  # noqa: E402
from streamer.run import make_path  # noqa: E402
from streamer.session import open_session  # noqa: E402
from tiler.store import open_store  # noqa: E402
from tiler.synth import synth_dem  # noqa: E402
from tiler.tile import TileOptions, tile  # noqa: E402


def bench_store(block_size: int):
    """The 2049² synthetic store of this benchmark in blocks of ``block_size``² (built in
    ``bench/work/session_update`` once; ``bench/plan_steps.py`` flies it too)."""
    root = WORK / "session_update"
    root.mkdir(parents=True, exist_ok=True)
    name = "s.zarr" if block_size == 129 else f"s_b{block_size}.zarr"
    src, dst = root / "dem.tif", root / name
    if not src.exists():
        synth_dem(src, 2049, seed=3)
    if not (dst / "zarr.json").exists():
        tile(src, dst, TileOptions(block_size=block_size, workers=2, executor="threads"))
    return open_store(dst)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--locks", action="store_true", help="also fly with the lock probed")
    ap.add_argument("--block-size", type=int, default=129, help="the store's block edge")
    ap.add_argument("--budget-mb", type=float, default=128.0, help="the session's budget")
    ap.add_argument("--linger-s", type=float, default=None, help="SessionConfig.linger_s")
    ap.add_argument("--freeze-gc", action="store_true", help="SessionConfig.freeze_gc")
    ap.add_argument(
        "--plan-step", type=int, default=None, help="blocks per locked step of the planning thread"
    )
    ap.add_argument("--out", type=Path, default=None, help="the JSON to write")
    a = ap.parse_args(argv)
    b = a.block_size
    if a.plan_step is not None:
        import streamer.planthread as planthread

        planthread.PLAN_STEP_BLOCKS = a.plan_step  # (read at each plan)
    store = bench_store(b)
    cams = make_path(store, "default", frames=a.frames, fps=60)
    wall, cpu = np.zeros(a.frames), np.zeros(a.frames)
    visible = np.zeros(a.frames, np.int64)
    plan = np.zeros(a.frames)
    load0 = os.getloadavg()[0]
    opts = {"linger_s": a.linger_s, "freeze_gc": a.freeze_gc}
    with open_session(store, budget_mb=a.budget_mb, workers=a.workers, **opts) as s:
        s.warm_up(cams[0])
        for i, cam in enumerate(cams):
            t0, c0 = time.perf_counter(), time.thread_time()
            f = s.update(cam, 1 / 60)
            wall[i], cpu[i] = time.perf_counter() - t0, time.thread_time() - c0
            visible[i] = f.stats.visible_blocks
            plan[i] = f.stats.update_cpu_ms / 1e3
        summary = s.summary()
        evicted = s.cache.evicted_bytes
    rows = {}
    print(
        f"# {a.frames} frames, {a.workers} loaders, 2049² store of {b}² blocks, unpaced, "
        f"{int(np.median(visible))} blocks in view (median); budget {a.budget_mb:g} MiB, "
        f"{evicted:,} bytes evicted"
    )
    print(f"{'':6} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    for name, arr in (("wall", wall), ("cpu", cpu), ("plan", plan)):
        ms = arr * 1e3
        rows[name] = {
            "p50_ms": float(np.percentile(ms, 50)),
            "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max()),
        }
        r = rows[name]
        print(f"{name:6} {r['p50_ms']:8.3f} {r['p99_ms']:8.3f} {r['max_ms']:8.3f}")
    locks = _lock_holds(store, cams, a.workers, a.budget_mb, opts) if a.locks else None
    out = a.out or RESULTS / ("session_update.json" if b == 129 else f"session_update_b{b}.json")
    RESULTS.mkdir(parents=True, exist_ok=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            portable(
                {
                    "frames": a.frames,
                    "workers": a.workers,
                    "block_size": b,
                    "budget_mb": a.budget_mb,
                    "linger_s": a.linger_s,
                    "freeze_gc": a.freeze_gc,
                    "plan_step_blocks": a.plan_step,
                    "evicted_bytes": evicted,
                    "visible_blocks_p50": float(np.median(visible)),
                    "update": rows,
                    "stall_frames": summary["stall_frames"],
                    "loaded_bytes": summary["loaded_bytes"],
                    "kernels": os.environ.get("TERRASTREAM_KERNELS", "auto"),
                    "loadavg_start_end": [load0, os.getloadavg()[0]],
                    "lock_holds_us": locks,
                    "machine": machine_info(),
                }
            ),
            indent=1,
        )
    )
    print(f"wrote {out}")
    return 0


def _lock_holds(store, cams, workers: int, budget_mb: float, opts: dict) -> dict:
    """The flight again with the lock probed: per role p50/p99/max hold µs (wall, CPU)."""
    from streamer.lockprobe import ProbeLock, install

    # the probe's floor: an empty hold of a lock of its own, taken by the caller after each
    # update (the clocks' own cost and what the machine adds to any hold meanwhile)
    floor = ProbeLock()
    with open_session(store, budget_mb=budget_mb, workers=workers, **opts) as s:
        probe = install(s)
        s.warm_up(cams[0])
        probe.clear()
        for cam in cams:
            s.update(cam, 1 / 60)
            with floor:
                pass
    out: dict = {"violations": len(probe.violations)}
    print(
        f"# lock holds (µs), probed flight; violations (read/decode/plan under it): "
        f"{len(probe.violations)}"
    )
    print(
        f"{'role':8} {'holds':>8} {'wall p50':>9} {'p99':>8} {'max':>9} {'cpu p50':>8} "
        f"{'p99':>8} {'max':>8} {'>=20':>7} {'>=50':>6} {'>=100':>6} {'sum ms':>8}"
    )
    roles = sorted(probe.by_role().items())
    roles.append(("floor", [(w, c) for _, w, c in floor.holds]))  # (the empty holds)
    for role, holds in roles:
        us = np.array(holds) * 1e6
        row = {"holds": len(us)}
        for j, kind in enumerate(("wall", "cpu")):
            for q in (50, 99):
                row[f"{kind}_p{q}"] = float(np.percentile(us[:, j], q))
            row[f"{kind}_max"] = float(us[:, j].max())
        # a percentile hangs on how many short holds there are: the long ones counted, and
        # the CPU held in all
        for t in (20, 50, 100):
            row[f"cpu_ge_{t}"] = int((us[:, 1] >= t).sum())
        row["cpu_sum_ms"] = float(us[:, 1].sum() / 1e3)
        out[role] = row
        print(
            f"{role:8} {row['holds']:8d} {row['wall_p50']:9.1f} {row['wall_p99']:8.1f} "
            f"{row['wall_max']:9.1f} {row['cpu_p50']:8.1f} {row['cpu_p99']:8.1f} "
            f"{row['cpu_max']:8.1f} {row['cpu_ge_20']:7d} {row['cpu_ge_50']:6d} "
            f"{row['cpu_ge_100']:6d} {row['cpu_sum_ms']:8.1f}"
        )
    out["waits"] = _waits(probe)
    out["sites"] = _sites(probe)
    return out


def _waits(probe) -> dict:
    """Per thread role: the acquisitions that found the lock held (``contended``) and how
    long each acquisition waited for it (wall µs; 0 for a free lock). A contended one also
    waits for the GIL once the lock is released: its wait is not the holder's hold."""
    rows = {}
    print("# waits for the lock (wall µs from asking to holding; 0: found free), by thread role")
    print(
        f"{'role':8} {'acquires':>9} {'contended':>10} {'p99':>7} {'max':>8} {'>=20':>6} "
        f"{'>=100':>6} {'sum ms':>7}"
    )
    for role, waits in sorted(probe.waits_by_role().items()):
        us = np.array(waits) * 1e6
        rows[role] = r = {
            "acquires": len(us),
            "contended": int((us > 0).sum()),
            "p50": float(np.percentile(us, 50)),
            "p99": float(np.percentile(us, 99)),
            "max": float(us.max()),
            "ge_20": int((us >= 20).sum()),
            "ge_100": int((us >= 100).sum()),
            "sum_ms": float(us.sum() / 1e3),
        }
        print(
            f"{role:8} {r['acquires']:9d} {r['contended']:10d} {r['p99']:7.1f} {r['max']:8.1f} "
            f"{r['ge_20']:6d} {r['ge_100']:6d} {r['sum_ms']:7.1f}"
        )
    return rows


def _sites(probe) -> dict:
    """Per function that took the lock: holds, thread-CPU p50/p99/max µs and the CPU held in
    all, the sites with the most CPU held first (printed: those with a hold ≥ 20 µs)."""
    rows = {}
    for site, holds in probe.by_site().items():
        cpu = np.array(holds)[:, 1] * 1e6
        rows[site] = {
            "holds": len(cpu),
            "cpu_p50": float(np.percentile(cpu, 50)),
            "cpu_p99": float(np.percentile(cpu, 99)),
            "cpu_max": float(cpu.max()),
            "cpu_ge_20": int((cpu >= 20).sum()),
            "cpu_sum_ms": float(cpu.sum() / 1e3),
        }
    rows = dict(sorted(rows.items(), key=lambda kv: -kv[1]["cpu_sum_ms"]))
    print("# lock holds (thread-CPU µs) by the function that took the lock")
    print(f"{'site':40} {'holds':>7} {'p50':>7} {'p99':>7} {'max':>8} {'>=20':>6} {'sum ms':>7}")
    for site, r in rows.items():
        if r["cpu_max"] >= 20:
            print(
                f"{site:40} {r['holds']:7d} {r['cpu_p50']:7.1f} {r['cpu_p99']:7.1f} "
                f"{r['cpu_max']:8.1f} {r['cpu_ge_20']:6d} {r['cpu_sum_ms']:7.1f}"
            )
    return rows


if __name__ == "__main__":
    raise SystemExit(main())
