"""What ``geometry-splitting``'s per-block quadtree textures cost the render thread along a
fly-through (issue 14), built in the frame that needs them or on a worker thread
(``Strategy.build_in_background``: a level change keeps the block's texture meanwhile, a new
block is drawn with a level-6 texture first), and what the interim textures do to the picture.

Usage::

    python bench/tree_async.py [STORE] [--frames 120] [--pairs 3] [--tau 1] [--configs ...]
                               [--no-interim] [--out PATH]

**Timing**: ``terrastream flythrough STORE --lod geometry-splitting`` as a user runs it, in
fresh processes, three configurations per round, the order rotated every round: ``render-thread``
(``--render-thread-builds``, the kernels as ``auto`` picks them in a one-shot command:
numpy), ``render-thread-numba`` (the same with ``TERRASTREAM_KERNELS=numba``: what compiled
kernels alone give) and ``background`` (the default: the worker loads the compiled kernels
before its first build). Per run, from ``frames.csv``'s ``build_ms`` (the render thread's ms
building textures in each frame): frames over 2 ms, median of the frames that built, p95, max,
sum; mean triangles and GPU ms. **Interim pictures** (one in-process flight with background
builds): in each frame where a drawn block's texture is not yet its level's, the selection's
triangles and measured max screen error (``screen_errors``) beside those of a second
strategy on the same renderer that builds every texture at once, on the same camera and
resident levels. Default STORE: N44W072 in UTM, 1025² blocks (``bench/tree_build.py``'s).
Prints tables and writes ``bench/results/tree_async.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np  # noqa: E402

from bench.common import REPO, RESULTS, flythrough_rows, machine_info, portable  # noqa: E402
from bench.tree_build import _utm_store  # noqa: E402

CONFIGS = {
    "render-thread": (["--render-thread-builds"], {}),
    "render-thread-numba": (["--render-thread-builds"], {"TERRASTREAM_KERNELS": "numba"}),
    "background": ([], {}),
}


def max_or_none(values) -> float | None:
    """The largest of ``values``, or None when there is none (nothing measured is not 0)."""
    return float(np.max(values)) if len(values) else None


def _ms(v: float | None) -> str:
    return f"{'n/a':>18}" if v is None else f"{v:18.2f}"


def fly(store: str, config: str, frames: int, tau: float) -> dict:
    """One ``terrastream flythrough`` in a fresh process: the per-frame build ms statistics
    (None where no frame was measured: no frame that built, no frame after the first)."""
    flags, env_add = CONFIGS[config]
    env = {k: v for k, v in os.environ.items() if k != "TERRASTREAM_KERNELS"} | env_add
    rows = flythrough_rows(store, "geometry-splitting", frames, tau, env, *flags)
    if not rows:
        raise RuntimeError(f"flythrough ({config}) drew no frame: nothing to measure")
    b = np.array([float(r["build_ms"]) for r in rows])
    built = b[b > 0.05]
    return {
        "config": config,
        "frames": len(rows),
        "frames_over_2ms": int((b > 2.0).sum()),
        "first_frame_ms": float(b[0]),
        "median_building_ms": float(np.median(built)) if len(built) else None,
        "p95_ms": float(np.percentile(b, 95)),
        "max_ms": float(b.max()),
        "max_after_first_ms": max_or_none(b[1:]),
        "sum_ms": float(b.sum()),
        "mean_triangles": float(np.mean([int(r["triangles"]) for r in rows])),
        "mean_gpu_ms": float(np.mean([float(r["gpu_ms"]) for r in rows])),
        "build_ms": [round(x, 3) for x in b.tolist()],
        "triangles": [int(r["triangles"]) for r in rows],
    }


def _median_or_none(values: list[float | None]) -> float | None:
    """The median of the measured ``values`` (None entries left out), or None."""
    got = [v for v in values if v is not None]
    return statistics.median(got) if got else None


def interim(store_path: str, frames: int, tau: float) -> list[dict]:
    """One in-process flight with background builds; the frames drawn with interim textures
    against the same view with every texture built at once."""
    from render.renderer import RenderConfig, TerrainRenderer
    from render.step import frame_step
    from render.strategies import get_strategy
    from streamer.run import make_path
    from streamer.session import open_session
    from tiler.store import open_store

    store = open_store(store_path)
    cams = make_path(store, "default", frames=frames, fps=30.0, viewport=(1024, 768))
    r = TerrainRenderer(store, RenderConfig(size=cams[0].viewport))
    bg, sync = get_strategy("geometry-splitting", r), get_strategy("geometry-splitting", r)
    bg.build_in_background()
    rows = []
    try:
        with open_session(store, budget_mb=256, workers=2, tau=tau, culling="hull") as session:
            for i, cam in enumerate(cams):
                step = frame_step(session, bg, cam, tau, dt=1 / 30, wait=i == 0)
                drawn = r.drawable(step.resident)
                stale = bg.interim_blocks(step.resident)
                if not stale:
                    continue
                ref, _ = sync.select(cam, tau, resident=step.resident)
                e_bg = bg.screen_errors(cam, step.selection)
                e_ref = sync.screen_errors(cam, ref)
                rows.append({
                    "frame": i,
                    "interim_blocks": len(stale),
                    "drawn_blocks": len(drawn),
                    "triangles": bg.counts(step.selection).triangles,
                    "triangles_at_once": sync.counts(ref).triangles,
                    "max_px": max_or_none(e_bg),  # (None: no sample measured)
                    "max_px_at_once": max_or_none(e_ref),
                })  # fmt: skip
    finally:
        bg.close()
        r.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store", nargs="?", type=Path)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--pairs", type=int, default=3, help="rounds of the configurations")
    ap.add_argument("--tau", type=float, default=1.0)
    ap.add_argument(
        "--configs", default=",".join(CONFIGS), help="comma-separated, of: " + ", ".join(CONFIGS)
    )
    ap.add_argument("--no-interim", action="store_true", help="skip the interim-texture flight")
    ap.add_argument("--out", type=Path, default=RESULTS / "tree_async.json")
    a = ap.parse_args(argv)
    store = a.store or _utm_store()
    if store is None:
        print("# the real DEM is not here and no STORE was given: nothing to fly over")
        return 1
    names = [c.strip() for c in a.configs.split(",")]
    if bad := [c for c in names if c not in CONFIGS]:
        ap.error(f"unknown configuration(s) {bad}; choose from {list(CONFIGS)}")
    runs = []
    for rnd in range(a.pairs):
        order = names[rnd % len(names) :] + names[: rnd % len(names)]
        for c in order:
            runs.append(fly(str(store), c, a.frames, a.tau) | {"round": rnd})
    cols = ["frames_over_2ms", "median_building_ms", "p95_ms", "first_frame_ms",
            "max_after_first_ms", "sum_ms", "mean_triangles", "mean_gpu_ms"]  # fmt: skip
    print(f"{'config':22} {'round':>5} " + " ".join(f"{c:>18}" for c in cols))
    for r in sorted(runs, key=lambda r: (names.index(r["config"]), r["round"])):
        print(f"{r['config']:22} {r['round']:5d} " + " ".join(_ms(r[c]) for c in cols))
    rows = [] if a.no_interim else interim(str(store), a.frames, a.tau)
    print(f"\ninterim textures: {len(rows)} frame(s)")
    print(f"{'frame':>5} {'interim':>7} {'drawn':>5} {'triangles':>10} {'at once':>10} "
          f"{'max px':>7} {'at once':>7}")  # fmt: skip
    for x in rows:
        print(f"{x['frame']:5d} {x['interim_blocks']:7d} {x['drawn_blocks']:5d} "
              f"{x['triangles']:10,} {x['triangles_at_once']:10,} {_ms(x['max_px'])[-7:]} "
              f"{_ms(x['max_px_at_once'])[-7:]}")  # fmt: skip
    a.out.parent.mkdir(parents=True, exist_ok=True)
    out = {
        "store": Path(store).name,
        "frames": a.frames,
        "tau": a.tau,
        "runs": runs,
        "interim": rows,
        "summary": {
            c: {
                "frames_over_2ms": [r["frames_over_2ms"] for r in runs if r["config"] == c],
                "max_after_first_ms": _median_or_none(
                    [r["max_after_first_ms"] for r in runs if r["config"] == c]
                ),
            }
            for c in names
        },
        "machine": machine_info(),
    }
    a.out.write_text(json.dumps(portable(out), indent=1))
    print(f"wrote {a.out.relative_to(REPO) if a.out.is_relative_to(REPO) else a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
