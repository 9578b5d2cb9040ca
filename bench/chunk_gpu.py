"""Kim, Lee & Shin's speed claim on their mechanism: ``chunk-tessellation`` with the chunk
traversal on the GPU (``chunk-tessellation-gpu``) against the same chunks selected on the CPU
and against ``geometry-splitting`` (Lee & Shin), same store, path and τ.

Per strategy and τ the fly-through is drawn once to stream and warm up, then ``--repeats``
times measured; per frame: CPU ms (the strategy's ``select``: for the GPU variants the block
table and uniforms only), GPU ms of the selection passes (traversal + emit, or expansion +
splitting; wall time, synchronised by the pass-count queries), draw ms (``RenderStats``), and
the frame = CPU + selection passes + draw; and for the GPU selections the traversal passes and
the node records they wrote (the paper's argument: a shallower tree, fewer traversal vertices;
``split_records``: geometry-splitting's crack-removal passes). On llvmpipe the "GPU" runs on
the same CPU cores, so a frame's parts add up rather than overlap.

Usage: python bench/chunk_gpu.py [STORE] [--size 640x480] [--taus 0.5,1,2,4] [--frames 8]
       [--repeats 3] [--lods a,b] [--out bench/results/chunk_gpu.json]
Default store: the real N44W072 store of BENCHMARKS.md (bench/prefetch.py's
``prepare_real(metric=True)``). Writes ``bench/results/chunk_gpu.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import N44W072_EQC, RESULTS, machine_info, portable  # noqa: E402
from render.pipeline import open_render_session  # noqa: E402
from render.renderer import RenderConfig, TerrainRenderer  # noqa: E402
from render.step import frame_step  # noqa: E402
from render.strategies import get_strategy  # noqa: E402
from streamer.run import make_path  # noqa: E402
from tiler.store import open_store  # noqa: E402

LODS = ("chunk-tessellation", "chunk-tessellation-gpu", "geometry-splitting")


def run(store, cams, name: str, tau: float, repeats: int, r: TerrainRenderer) -> dict:
    """One strategy at one τ: per-frame means over the measured repeats."""
    st = get_strategy(name, r)
    keys = ("cpu", "sel_gpu", "draw", "tris", "nodes", "passes", "trav_records", "split_records")
    rec: dict[str, list[float]] = {k: [] for k in keys}
    with open_render_session(store, 0.0, "qiu", r.p) as s:
        for cam in cams:  # stream and warm up
            frame_step(s, st, cam, tau)
        for _ in range(repeats):
            for cam in cams:
                step = frame_step(s, st, cam, tau)
                extra = st.extra_frame_ms(step.selection)
                rec["cpu"].append(step.selection_ms)
                rec["sel_gpu"].append(extra)
                rec["draw"].append(step.stats.frame_ms - extra)
                rec["tris"].append(step.stats.triangles)
                rec["nodes"].append(step.stats.patches)
                sel = step.selection  # traversal passes and the records they wrote (GPU ones)
                rec["passes"].append(len(getattr(sel, "pass_counts", [])))
                rec["trav_records"].append(sum(getattr(sel, "pass_counts", [])))
                rec["split_records"].append(sum(getattr(sel, "split_counts", [])))
    m = {k: float(np.mean(v)) for k, v in rec.items()}
    m["frame"] = m["cpu"] + m["sel_gpu"] + m["draw"]
    m["frame_p90"] = float(
        np.percentile(np.add(np.add(rec["cpu"], rec["sel_gpu"]), rec["draw"]), 90)
    )
    return {"strategy": name, "tau": tau, "frames": len(rec["cpu"]), **m}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store", nargs="?", default=str(N44W072_EQC))
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--taus", default="0.5,1,2,4")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--lods", default=",".join(LODS))
    ap.add_argument("--out", default=str(RESULTS / "chunk_gpu.json"))
    a = ap.parse_args(argv)
    if not Path(a.store).exists():
        print(f"# {a.store} not found: make it with bench/prefetch.py (BENCHMARKS.md)")
        return 1
    w, h = (int(v) for v in a.size.split("x"))
    taus = [float(t) for t in a.taus.split(",")]
    store = open_store(a.store)
    cams = make_path(store, "default", frames=a.frames, viewport=(w, h))
    r = TerrainRenderer(store, RenderConfig(size=(w, h)))
    load = os.getloadavg()
    print(f"# {a.store} {w}x{h}, {a.frames} frames x {a.repeats}, load {load[0]:.2f}")
    head = (
        f"{'strategy':>24} {'tau':>4} {'tris':>9} {'nodes':>7} {'CPU ms':>7} "
        f"{'sel GPU':>8} {'draw ms':>8} {'frame ms':>9} {'p90':>7} {'passes':>6} {'trav rec':>9} "
        f"{'split rec':>9}"
    )
    print(head)
    rows = []
    for tau in taus:
        for name in a.lods.split(","):
            row = run(store, cams, name, tau, a.repeats, r)
            rows.append(row)
            print(
                f"{name:>24} {tau:>4g} {row['tris']:>9,.0f} {row['nodes']:>7,.0f} "
                f"{row['cpu']:>7.2f} {row['sel_gpu']:>8.2f} {row['draw']:>8.2f} "
                f"{row['frame']:>9.2f} {row['frame_p90']:>7.2f} {row['passes']:>6.1f} "
                f"{row['trav_records']:>9,.0f} {row['split_records']:>9,.0f}"
            )
    r.close()
    info = machine_info() | {"load_before": load[0], "load_after": os.getloadavg()[0]}
    out = {"store": a.store, "size": [w, h], "frames": a.frames, "repeats": a.repeats}
    out |= {"rows": rows, "machine": info}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(portable(out), indent=1))
    print(f"# load after {info['load_after']:.2f}; wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
