"""What a block's arrival costs the caller: ``qiu``'s first selection after new blocks became
resident (per block the node boxes of ``conservative-view``, the patch tables, the nodata rule's
gap widths) against the next selection of the same view.

For each store: the overview camera of ``render``/``tradeoff`` (1024x768, 45°), every block in
view streamed to the GPU at full resolution, then, ``--reps`` times, a fresh strategy selects
twice at τ (the first selection builds the per-block data, the second reuses it). Thread CPU
ms (``time.thread_time``) with the numba kernels warm. Prints a table and writes
``bench/results/block_arrival.json``::

    python bench/block_arrival.py STORE [STORE ...] [--metric conservative-view]
        [--patch-log2 1] [--nodata gap] [--tau 1] [--reps 3]

Stores as ``terrastream tile SRC DST`` makes them (e.g. ``terrastream synth s.tif --size 4097
--seed 1``; ``N44W072.hgt`` with ``--dst-crs auto``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import RESULTS, git_head, machine_info, portable  # noqa: E402


def measure(path: str, metric: str, p: int, nodata: str, tau: float, reps: int) -> dict:
    """First and second selection CPU ms of ``reps`` fresh strategies on one store's view."""
    from render import select_kernels
    from render.pipeline import open_render_session
    from render.renderer import RenderConfig, TerrainRenderer
    from render.step import stream_step
    from render.strategies import get_strategy
    from render.views import overview_camera
    from tiler.store import open_store

    select_kernels.warm_up()
    store = open_store(path)
    size = (1024, 768)
    cam = overview_camera(store, size)
    first, second, patches = [], [], 0
    for _ in range(reps):
        r = TerrainRenderer(store, RenderConfig(size=size, patch_log2=p))  # no block data yet
        try:
            with open_render_session(store, 0.0, metric, r.p) as s:
                stream_step(s, r, cam)  # every block in view on the GPU at full resolution
            with open_render_session(store, tau, metric, r.p, nodata=nodata) as s:
                res = dict(stream_step(s, None, cam)[1])
            st = get_strategy("qiu", r, nodata=nodata)
            for out in (first, second):
                t0 = time.thread_time()
                sel, _ = st.select(cam, tau, metric, resident=res)
                out.append((time.thread_time() - t0) * 1e3)
            patches = len(sel)
        finally:
            r.close()
    if not patches:
        raise SystemExit(f"{path}: the view selected no patch; nothing was measured")
    return {
        "store": portable(path),
        "blocks": len(res),
        "patches": patches,
        "first_cpu_ms": first,
        "second_cpu_ms": second,
        "first_median_ms": statistics.median(first),
        "second_median_ms": statistics.median(second),
    }


def main() -> int:
    """Command line: measure each store, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stores", nargs="+")
    ap.add_argument("--metric", default="conservative-view")
    ap.add_argument("--patch-log2", type=int, default=1)
    ap.add_argument("--nodata", default="gap")
    ap.add_argument("--tau", type=float, default=1.0)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", default=str(RESULTS / "block_arrival.json"))
    a = ap.parse_args()
    os.environ.setdefault("TERRASTREAM_KERNELS", "numba")
    rows = [measure(s, a.metric, a.patch_log2, a.nodata, a.tau, a.reps) for s in a.stores]
    print(f"{'store':<28} {'blocks':>6} {'patches':>8} {'first ms':>9} {'next ms':>8}")
    for r in rows:
        print(
            f"{Path(r['store']).name:<28} {r['blocks']:>6} {r['patches']:>8} "
            f"{r['first_median_ms']:>9.1f} {r['second_median_ms']:>8.1f}"
        )
    doc = {
        "benchmark": "block_arrival",
        "args": portable({k: v for k, v in vars(a).items() if k != "out"}),
        "git_head": git_head(),
        "machine": machine_info(),
        "load_average": list(os.getloadavg()),
        "rows": rows,
    }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(portable(doc), indent=1) + "\n")
    print(f"wrote {portable(str(out))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
