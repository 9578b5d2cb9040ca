"""Where a ``qiu`` selection's patches go (issue 12 item 5): per depth, how many there are,
how many straddle a mask boundary (terrain and nodata or padding in their footprint), and how
many unmixed ones have a mixed parent (the siblings the boundary's refinement forces).

Usage::

    python bench/patch_census.py STORE [--metric conservative-view] [--patch-log2 1]
                                 [--nodata gap] [--tau 1] [--size 1024x768] [--out PATH]

The camera is ``tradeoff``'s default (``render.views.overview_camera``), the data streamed as
``render.pipeline.tradeoff`` streams it (every block in view on the GPU at full resolution, the
levels a session at τ with the nodata rule holds). Prints a table and writes
``bench/results/patch_census.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np  # noqa: E402

from bench.common import REPO, RESULTS, machine_info, portable  # noqa: E402


def _mixed(mask: np.ndarray | None, k: int, depth: int, row: int, col: int) -> bool:
    """Whether node ``(depth, row, col)``'s closed footprint holds terrain and nodata."""
    if mask is None:
        return False
    s = 1 << (k - depth)
    w = mask[row * s : row * s + s + 1, col * s : col * s + s + 1]
    return bool(w.any() and not w.all())


def census(path: str, metric: str, patch_log2: int, nodata: str, tau: float, size) -> dict:
    """Per depth: patches, mixed ones, unmixed ones with a mixed parent, median ρ."""
    from render.pipeline import ViewOptions, open_render_session
    from render.renderer import RenderConfig, TerrainRenderer
    from render.step import stream_step
    from render.strategies import get_strategy, stream_metric
    from render.views import overview_camera
    from tiler.store import open_store

    store = open_store(path)
    cam = overview_camera(store, size)
    o = ViewOptions(lod="qiu", metric=metric, patch_log2=patch_log2, nodata=nodata)
    r = TerrainRenderer(store, RenderConfig(size=cam.viewport, patch_log2=o.patch_log2))
    try:
        strat = get_strategy("qiu", r, **o.strategy_options())
        with open_render_session(store, tau, stream_metric("qiu", metric), r.p, nodata=nodata) as s:
            _, res = stream_step(s, r, cam)
        p, _ = strat.select(cam, tau, metric, resident=res)
    finally:
        r.close()
    if not len(p):
        raise SystemExit(f"no patches selected on {path}: the view holds no terrain")
    k = store.k
    blocks = [tuple(int(v) for v in b) for b in p.blocks]
    masks = {
        b: store.read_mask(b) if bool(store.index.has_nodata[b]) else None for b in set(blocks)
    }
    rows = []
    for d in np.unique(p.depth):
        idx = np.flatnonzero(p.depth == d)
        mixed = [_mixed(masks[blocks[p.block[i]]], k, d, p.row[i], p.col[i]) for i in idx]
        parent = [
            not m
            and d > 0
            and _mixed(masks[blocks[p.block[i]]], k, d - 1, p.row[i] // 2, p.col[i] // 2)
            for i, m in zip(idx, mixed, strict=True)
        ]
        rows.append(
            {
                "depth": int(d),
                "levels": sorted({int(v) for v in p.level[idx]}),
                "patches": len(idx),
                "mixed": int(sum(mixed)),
                "unmixed_with_mixed_parent": int(sum(parent)),
                "median_rho_px": float(np.median(p.rho[idx])),
            }
        )
    return {"store": Path(path).name, "metric": metric, "patch_log2": patch_log2,
            "nodata": nodata, "tau": tau, "size": list(size), "patches": len(p),
            "triangles_before_masking": 2 * len(p) * 4**patch_log2, "depths": rows}  # fmt: skip


def main() -> None:
    """Count, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("store")
    ap.add_argument("--metric", default="conservative-view")
    ap.add_argument("--patch-log2", type=int, default=1)
    ap.add_argument("--nodata", default="gap")
    ap.add_argument("--tau", type=float, default=1.0)
    ap.add_argument("--size", default="1024x768")
    ap.add_argument("--out", default=str(RESULTS / "patch_census.json"))
    a = ap.parse_args()
    if not Path(a.store).exists():
        sys.exit(f"store {a.store} not found")
    size = tuple(int(v) for v in a.size.split("x"))
    c = census(a.store, a.metric, a.patch_log2, a.nodata, a.tau, size)
    print(f"# {c['store']} {c['metric']} 2^{c['patch_log2']} {c['nodata']} tau {c['tau']:g}: "
          f"{c['patches']} patches")  # fmt: skip
    print("depth levels patches mixed unmixed_with_mixed_parent median_rho_px")
    for w in c["depths"]:
        print(f"{w['depth']} {w['levels']} {w['patches']} {w['mixed']} "
              f"{w['unmixed_with_mixed_parent']} {w['median_rho_px']:.3f}")  # fmt: skip
    out = Path(a.out)
    out.write_text(json.dumps(portable({"machine": machine_info(), **c}), indent=1))
    print(f"# wrote {out.relative_to(REPO) if out.is_relative_to(REPO) else out}")


if __name__ == "__main__":
    main()
