"""CPU selection per frame (issue 14): ``jung-han`` and ``seamless-patches``, each with the numpy
reference against the numba kernels, interleaved in one run, on the benchmark views.

Usage::

    python bench/select_cpu.py [STORE ...] [--taus 0.5,1,2,4] [--sizes 320x240,1024x768]
                               [--frames 8] [--reps 3] [--no-compile] [--out PATH]

Views: the default fly-through of each store (``make_path(store, "default")``, ``--frames``
cameras, as ``bench/lod_compare.py``), every block in view streamed at full resolution (a τ = 0
session, as ``terrastream compare``). Per store, size, τ and strategy: the mean over the frames
of the median (over ``--reps`` interleaved repetitions) of the selection's wall ms (what
``select`` reports, ``perf_counter``) and of its thread CPU ms (``time.thread_time``). Timings are
warm: the per-block trees are built and the kernels compiled before anything is timed (both
backends share the trees; ``seamless-patches``' two backends share the renderer's error tables).
The compile time (``--no-compile`` skips it) is measured in fresh
processes: the first numba selection minus a warm one, with an empty numba cache (cold: compiles)
and again with that cache filled (warm: loads). Default stores: ``bench/work/s4097.zarr`` and the
N44W072 metre store of ``bench/prefetch.py`` (missing ones are skipped with a message).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import N44W072_EQC, REPO, RESULTS, S4097, machine_info  # noqa: E402

DEFAULT_STORES = [str(S4097), str(N44W072_EQC)]


def _frames(store, size: tuple[int, int], frames: int):
    """The renderer with every block of the path streamed, and per camera its resident map."""
    from render.pipeline import open_render_session
    from render.renderer import RenderConfig, TerrainRenderer
    from render.step import stream_step
    from streamer.run import make_path

    cams = make_path(store, "default", frames=frames, viewport=size)
    r = TerrainRenderer(store, RenderConfig(size=size, patch_log2=4))
    out = []
    with open_render_session(store, 0.0, "qiu", r.p) as sess:
        for c in cams:
            _, res = stream_step(sess, r, c)
            out.append((c, dict(res)))
    return r, out


def _timed(strategy, cam, tau, res) -> tuple[float, float, int]:
    t0 = time.thread_time()
    sel, ms = strategy.select(cam, tau, resident=res)
    return ms, (time.thread_time() - t0) * 1000.0, len(sel)


def measure(path: str, size: tuple[int, int], taus: list[float], frames: int, reps: int):
    """Rows ``{store, size, strategy, backend, tau, wall_ms, cpu_ms, selected}`` (``selected``:
    ``len`` of the selection, jung-han's drawn triangles, seamless-patches' leaf patches)."""
    from render.strategies import get_strategy
    from tiler.store import open_store

    store = open_store(path)
    r, views = _frames(store, size, frames)
    jh = {b: get_strategy("jung-han", r, kernels=b) for b in ("numpy", "numba")}
    jh["numba"]._trees = jh["numpy"]._trees  # shared per-block trees (built once, untimed)
    runs = [("jung-han", "numpy", jh["numpy"]), ("jung-han", "numba", jh["numba"])]
    for b in ("numpy", "numba"):
        runs.append(("seamless-patches", b, get_strategy("seamless-patches", r, kernels=b)))
    for _, _, st in runs:  # warm: trees, packed forest, compiled kernels, tables
        for cam, res in views:
            st.select(cam, 1.0, resident=res)
    rows = []
    for tau in taus:
        acc = {(n, b): [[[], [], 0] for _ in views] for n, b, _ in runs}
        for rep in range(reps):
            order = runs if rep % 2 == 0 else runs[::-1]
            for i, (cam, res) in enumerate(views):
                for n, b, st in order:
                    wall, cpu, tris = _timed(st, cam, tau, res)
                    a = acc[(n, b)][i]
                    a[0].append(wall)
                    a[1].append(cpu)
                    a[2] = tris
        for (n, b), per in acc.items():
            rows.append(
                {
                    "store": Path(path).name,
                    "size": f"{size[0]}x{size[1]}",
                    "strategy": n,
                    "backend": b,
                    "tau": tau,
                    "wall_ms": statistics.mean(statistics.median(p[0]) for p in per),
                    "cpu_ms": statistics.mean(statistics.median(p[1]) for p in per),
                    "wall_ms_max": max(statistics.median(p[0]) for p in per),
                    "selected": statistics.mean(p[2] for p in per),
                    "loadavg": os.getloadavg()[0],
                }
            )
    r.close()
    return rows


_PROBE = """
import sys, time
sys.path.insert(0, {repo!r})
from bench.select_cpu import _frames
from render.strategies import get_strategy
from tiler.store import open_store
r, views = _frames(open_store({path!r}), (320, 240), 1)
cam, res = views[0]
ref = get_strategy("jung-han", r, kernels="numpy")
ref.select(cam, 1.0, resident=res)  # builds the trees
get_strategy("seamless-patches", r, kernels="numpy").select(cam, 1.0, resident=res)  # tables
out = []
for st in (get_strategy("jung-han", r, kernels="numba"),
           get_strategy("seamless-patches", r, kernels="numba")):
    if st.name == "jung-han":
        st._trees = ref._trees
    t0 = time.perf_counter()
    st.select(cam, 1.0, resident=res)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    st.select(cam, 1.0, resident=res)
    out.append(first - (time.perf_counter() - t0))
print(*out)
"""


def compile_times(path: str) -> dict[str, float]:
    """Seconds the first numba selection costs beyond a warm one, empty cache (``cold_s``) and
    filled cache (``warm_s``): ``jung-han`` (keys without prefix) then ``seamless-patches``
    (``seamless_``), in that order in one process (numba's import is charged to jung-han)."""
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for name in ("cold_s", "warm_s"):
            code = _PROBE.format(repo=str(REPO), path=path)
            res = subprocess.run(
                [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
            )
            jh, sp = (float(v) for v in res.stdout.strip().splitlines()[-1].split())
            out[name], out[f"seamless_{name}"] = jh, sp
    return out


def main() -> None:
    """Measure, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stores", nargs="*", default=DEFAULT_STORES)
    ap.add_argument("--taus", default="0.5,1,2,4")
    ap.add_argument("--sizes", default="320x240,1024x768")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument("--out", default=str(RESULTS / "select_cpu.json"))
    a = ap.parse_args()
    taus = [float(t) for t in a.taus.split(",")]
    sizes = [tuple(int(v) for v in s.split("x")) for s in a.sizes.split(",")]
    info = machine_info()
    rows, compile_s = [], {}
    print("store size strategy backend tau wall_ms cpu_ms selected load1")
    for path in a.stores:
        if not Path(path).exists():
            print(f"# skipped {path}: missing (bench/tiling.py / bench/prefetch.py make it)")
            continue
        if not a.no_compile:
            compile_s[Path(path).name] = compile_times(path)
            print(f"# {Path(path).name} numba compile/load s: {compile_s[Path(path).name]}")
        for size in sizes:
            for row in measure(path, size, taus, a.frames, a.reps):
                rows.append(row)
                print(
                    f"{row['store']} {row['size']} {row['strategy']} {row['backend']} "
                    f"{row['tau']:g} {row['wall_ms']:.2f} {row['cpu_ms']:.2f} "
                    f"{row['selected']:.0f} {row['loadavg']:.2f}",
                    flush=True,
                )
    info["loadavg_at_end"] = os.getloadavg()
    Path(a.out).write_text(
        json.dumps({"machine": info, "compile": compile_s, "rows": rows}, indent=1)
    )
    print(f"# wrote {Path(a.out).relative_to(REPO) if Path(a.out).is_relative_to(REPO) else a.out}")


if __name__ == "__main__":
    main()
