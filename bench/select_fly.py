"""CPU selection per frame along a real fly-through (issue 14): ``terrastream flythrough`` as a
user runs it, the selection's ms of every frame from its ``frames.csv``.

Usage::

    python bench/select_fly.py [STORE] [--lods jung-han] [--frames 300] [--runs 2]
                               [--skip 10] [--tau 1] [--latency-ms 0] [--out PATH]

Unlike ``bench/select_cpu.py`` (fixed views, every block streamed beforehand, each selection
repeated), the frames here stream as they fly: blocks arrive and change level, so the
selection also builds the trees of those blocks (and, for ``jung-han``, places them in its
flat forest), and the GPU draws between selections. Per run, the command runs in a fresh
process from this checkout (``TERRASTREAM_KERNELS=numba``: compiled selections, loaded from
numba's cache); the first ``--skip`` frames (the first data's arrival, the kernels' first
calls) are left out. Reported per strategy and run: median, mean, p95, p99 and max of the
selection's wall ms (what ``select`` reports), the frames whose selection took at least
``--latency-ms`` (20 ms without it), and the frames' mean triangles. Default STORE:
the N44W072 metre store of ``bench/prefetch.py``. ``--latency-ms``: fly over the store served by
a loopback HTTP server answering each request after that delay (what a remote store costs a
selection that reads on the render thread). Prints a table and writes
``bench/results/select_fly.json``. Run it in a checkout of each commit to compare versions.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np  # noqa: E402

from bench.common import N44W072_EQC, REPO, RESULTS, flythrough_rows, machine_info, portable  # noqa: E402


def fly(store: str, lod: str, frames: int, tau: float, skip: int, slow_ms: float) -> dict:
    """One ``terrastream flythrough`` in a fresh process: the selection ms statistics."""
    env = dict(os.environ, TERRASTREAM_KERNELS="numba")
    rows = flythrough_rows(store, lod, frames, tau, env)
    ms = np.array([float(r["selection_ms"]) for r in rows[skip:]])
    tris = [int(r["triangles"]) for r in rows[skip:]]
    return {
        "lod": lod,
        "frames": len(ms),
        "median_ms": float(np.median(ms)),
        "mean_ms": float(ms.mean()),
        "p95_ms": float(np.percentile(ms, 95)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
        "slow_ms": slow_ms,
        "slow_frames": int((ms >= slow_ms).sum()),
        "mean_triangles": statistics.mean(tris),
        "loadavg": os.getloadavg()[0],
    }


def main() -> None:
    """Fly, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("store", nargs="?", default=str(N44W072_EQC))
    ap.add_argument("--lods", default="jung-han")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--skip", type=int, default=10)
    ap.add_argument("--tau", type=float, default=1.0)
    ap.add_argument("--latency-ms", type=float, default=0.0, help="serve the store over HTTP")
    ap.add_argument("--out", default=str(RESULTS / "select_fly.json"))
    a = ap.parse_args()
    if not Path(a.store).exists():
        sys.exit(f"store {a.store} not found: `python bench/prefetch.py` makes the default one")
    if a.frames <= a.skip:
        sys.exit(f"--frames {a.frames} must exceed --skip {a.skip}")
    rows = []
    slow = a.latency_ms if a.latency_ms > 0 else 20.0
    print(
        f"lod run frames median_ms mean_ms p95_ms p99_ms max_ms frames>={slow:g}ms "
        "mean_triangles load1"
    )
    with contextlib.ExitStack() as stack:
        store = a.store
        if a.latency_ms > 0:
            from bench.prefetch_stores import http_server

            root = Path(a.store).resolve()
            url = stack.enter_context(http_server(root.parent, a.latency_ms / 1000.0))
            store = f"{url}/{root.name}"
        for run in range(1, a.runs + 1):
            for lod in a.lods.split(","):
                w = fly(store, lod, a.frames, a.tau, a.skip, slow) | {"run": run}
                rows.append(w)
                print(
                    f"{lod} {run} {w['frames']} {w['median_ms']:.2f} {w['mean_ms']:.2f} "
                    f"{w['p95_ms']:.2f} {w['p99_ms']:.2f} {w['max_ms']:.2f} {w['slow_frames']} "
                    f"{w['mean_triangles']:.0f} {w['loadavg']:.2f}",
                    flush=True,
                )
    out = Path(a.out)
    info = machine_info() | {"store": Path(a.store).name, "tau": a.tau, "latency_ms": a.latency_ms}
    out.write_text(json.dumps(portable({"machine": info, "rows": rows}), indent=1))
    print(f"# wrote {out.relative_to(REPO) if out.is_relative_to(REPO) else out}")


if __name__ == "__main__":
    main()
