"""Renderer benchmark: LOD vs full-resolution frames along a fly-through, per tau.

For each store (the 4097^2 and 16385^2 synthetic stores and a real DEM, when present), 1024x768
cameras along the default fly-through; per tau: triangles, CPU selection ms, GPU frame ms of
the LOD render and of the full-resolution render of the same view (same run, llvmpipe), and the
measured max/p99 screen error (each sample once) and the exact watertightness of the drawn
mesh (open edges, largest gap: ``render.cracks``). Prints a table and writes
bench/results/render.json.

Usage: python bench/render.py [--quick] [--stores a.zarr,b.zarr] [--metric qiu]
Make the stores first: terrastream synth X.tif --size 4097 && terrastream tile X.tif X.zarr
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import (  # noqa: E402
    N44W072_EQC,
    RESULTS,
    S4097,
    S16385,
    ensure_store,
    machine_info,
    portable,
)
from render import cracks, measure  # noqa: E402
from render.measure import heights_fn  # noqa: E402
from render.pipeline import draw_timed, open_render_session  # noqa: E402
from render.renderer import RenderConfig, TerrainRenderer  # noqa: E402
from render.step import stream_step  # noqa: E402
from streamer.run import make_path  # noqa: E402
from tiler.store import open_store  # noqa: E402

DEFAULT_STORES = [str(S4097), str(S16385), str(N44W072_EQC)]
PAPERS = (
    "Qiu et al. Table 2 (Puget Sound 4097^2, 1024x768): 98 k triangles at tau=1, 33 k at tau=2; "
    "Lee & Shin: 152 k at tau=1."
)


def bench_store(path: str, taus, metric: str, frames: int, size, measure_err: bool) -> list[dict]:
    """One store: rows per (frame, tau)."""
    store = open_store(path)
    cams = make_path(store, "default", frames=max(frames * 20, 40), fps=30.0, viewport=size)
    cams = cams[:: max(1, len(cams) // frames)][:frames]
    r = TerrainRenderer(store, RenderConfig(size=size))
    rows = []
    for fi, cam in enumerate(cams):
        with open_render_session(store, 0.0, metric, r.p) as s:
            ref_res = stream_step(s, r, cam)[1]
        ref_p, _ = r.select(cam, 0.0, metric, resident=ref_res, full=True)
        ref = draw_timed(r, cam, ref_p, 2)
        ref_img = r.image()
        for tau in taus:
            with open_render_session(store, tau, metric, r.p) as s:
                res = stream_step(s, None, cam)[1]  # the levels a tau session holds
            sel = []
            for _ in range(3):
                p, ms = r.select(cam, tau, metric, resident=res)
                sel.append(ms)
            st = draw_timed(r, cam, p, 2)
            img = r.image()
            err = measure.ErrorStats(float("nan"), float("nan"), float("nan"), 0)
            hf = heights_fn(store, p)
            if measure_err:
                e = measure.screen_errors(p, r.grid, cam, hf)
                err = measure.error_stats(e)
            wt = cracks.watertight(r.grid, *measure.patch_triangles(p, r.grid, hf))
            rows.append(
                {
                    "store": Path(path).name,
                    "frame": fi,
                    "tau": tau,
                    "metric": metric,
                    "triangles": st.triangles,
                    "patches": st.patches,
                    "selection_ms": float(np.min(sel)),
                    "frame_ms": st.frame_ms,
                    "reference_frame_ms": ref.frame_ms,
                    "reference_triangles": ref.triangles,
                    "max_screen_error_px": err.max_px,
                    "p99_screen_error_px": err.p99_px,
                    "psnr_db": measure.psnr(img, ref_img),
                    "clamped": st.clamped,
                    "open_edges": wt.open_edges,
                    "gap_edges": wt.gap_edges,
                    "max_gap_m": wt.max_gap_m,
                }
            )
            print(
                f"{Path(path).name:>14} {fi:>3} {tau:>4g} {st.triangles:>9,} "
                f"{np.min(sel):>7.2f} {st.frame_ms:>8.1f} {ref.frame_ms:>8.1f} "
                f"{ref.triangles:>10,} {err.max_px:>7.2f} {err.p99_px:>7.2f} "
                f"{wt.open_edges:>5} {wt.max_gap_m:>6.2f}",
                flush=True,
            )
    r.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; 1 (and no JSON written) when no store was measured."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 frames, 2 taus (1 and 4)")
    ap.add_argument("--stores", default=",".join(DEFAULT_STORES))
    ap.add_argument("--metric", default="qiu")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--no-error", action="store_true", help="skip the measured error")
    ap.add_argument("--out", default=str(RESULTS / "render.json"))
    a = ap.parse_args(argv)
    taus = [1.0, 4.0] if a.quick else [0.5, 1.0, 2.0, 4.0]
    frames = 2 if a.quick else a.frames
    size = (1024, 768)
    print(
        f"{'store':>14} {'fr':>3} {'tau':>4} {'triangles':>9} {'sel ms':>7} {'LOD ms':>8} "
        f"{'full ms':>8} {'full tris':>10} {'max px':>7} {'p99 px':>7} {'open':>5} {'gap m':>6}"
    )
    rows = []
    t0 = time.time()
    for path in a.stores.split(","):
        ensure_store(path)  # s4097 and the N44W072 metre store are made on first use
        if not Path(path).exists():
            print(f"skipping {path}: not found")
            continue
        rows += bench_store(path, taus, a.metric, frames, size, not a.no_error)
    if not rows:  # (the committed JSON is not replaced by an empty one)
        print("error: no store was measured (see the skipping lines)", file=sys.stderr)
        return 1
    summary = []
    for store in sorted({r["store"] for r in rows}):
        for tau in taus:
            rs = [r for r in rows if r["store"] == store and r["tau"] == tau]
            if not rs:
                continue
            summary.append(
                {
                    "store": store,
                    "tau": tau,
                    "mean_triangles": float(np.mean([r["triangles"] for r in rs])),
                    "max_triangles": int(np.max([r["triangles"] for r in rs])),
                    "mean_selection_ms": float(np.mean([r["selection_ms"] for r in rs])),
                    "frame_ratio": float(
                        np.mean([r["frame_ms"] / r["reference_frame_ms"] for r in rs])
                    ),
                    "max_screen_error_px": float(np.max([r["max_screen_error_px"] for r in rs])),
                    "p99_screen_error_px": float(np.max([r["p99_screen_error_px"] for r in rs])),
                }
            )
    print("\nsummary (mean over frames; frame ratio = LOD ms / full-res ms)")
    for s in summary:
        print(
            f"{s['store']:>14} tau {s['tau']:>4g}: {s['mean_triangles']:>10,.0f} tris "
            f"(max {s['max_triangles']:,}), sel {s['mean_selection_ms']:.2f} ms, ratio "
            f"{s['frame_ratio']:.3f}, error max {s['max_screen_error_px']:.2f} / p99 "
            f"{s['p99_screen_error_px']:.2f} px"
        )
    print(PAPERS)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            portable(
                {
                    "rows": rows,
                    "summary": summary,
                    "papers": PAPERS,
                    "seconds": time.time() - t0,
                    "machine": machine_info(),
                }
            ),
            indent=1,
        )
    )
    print(f"wrote {out} in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
