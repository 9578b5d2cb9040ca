"""CPU selection per frame (issue 14): ``jung-han`` and ``seamless-patches``, each with the numpy
reference against the numba kernels, interleaved in one run, on the benchmark views; or
(``--metric conservative-view``) ``qiu``'s selection with that metric (node boxes, the stitch's
snapped-edge check) on the ``bench/bound_fov.py`` views.

Usage::

    python bench/select_cpu.py [STORE ...] [--taus 0.5,1,2,4] [--sizes 320x240,1024x768]
                               [--frames 8] [--reps 3] [--no-compile] [--tune-malloc]
                               [--only jung-han:numba] [--drop] [--out PATH]
    python bench/select_cpu.py --metric conservative-view [STORE ...] [--taus 0.5,1,2]
                               [--fovs 5,45,120,170] [--patch-log2 1,4] [--nodata gap]
                               [--sizes 320x240] [--reps 5] [--out PATH]

``--metric conservative-view``: per store (default the two ``bench/bound_fov.py`` stores), patch
size, FOV and τ the middle camera of ``make_path(store, "default")`` with its ``fov_y``
replaced, the data streamed as ``render.pipeline.tradeoff`` does (every block in view on the
GPU at full resolution, the levels a session at τ with the nodata rule would hold), and
``qiu``'s ``select`` (``select_patches`` and ``stitch``) timed with ``TERRASTREAM_KERNELS``
numpy and numba alternated ``--reps`` times (medians of wall and thread CPU ms), after a
warm-up; each row says whether both gave the same patches (every array, clamped, violations).

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

Each row also gives the selecting thread's minor page faults (median per frame): after the
numpy backend's large temporaries are freed, glibc may hand the next selection fresh pages to
zero-fill. ``--tune-malloc`` fixes the allocator's thresholds first (``tiler.malloc``), as a
long-running process whose allocations had settled would see them. ``--only`` times the
listed strategy/backend pairs alone (each repetition still goes through every frame in turn, as a
moving camera does; ``bench/jung_han_split.py`` repeats one frame).

Each strategy's last selection is kept until its next one replaces it, as a renderer keeps the
selection it draws: freed at once (``--drop``, the method before session 40) its ~2 MB of arrays
left free memory at the top of glibc's heap, which trimmed it, and the next selection zero-filled
~420 fresh pages (~0.4 ms at τ = 1 on N44W072 1024×768) that a renderer does not pay.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np  # noqa: E402

from bench.common import (  # noqa: E402
    N44W072_EQC,
    REPO,
    RESULTS,
    S4097,
    WORK,
    ensure_store,
    machine_info,
    portable,
)

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


def _faults() -> int:
    """Minor page faults of the calling thread so far (fresh memory the kernel zero-fills)."""
    return resource.getrusage(resource.RUSAGE_THREAD).ru_minflt


def _timed(strategy, cam, tau, res, kept: dict | None = None) -> tuple[float, float, int, int]:
    """``(wall ms, thread CPU ms, len, minor faults)`` of one ``select``. ``kept``: the
    strategy's last selection stays referenced there until this one replaces it, as a renderer
    keeps the selection it draws (``None``: freed at once, the method before session 40)."""
    f0 = _faults()
    t0 = time.thread_time()
    sel, ms = strategy.select(cam, tau, resident=res)
    out = ms, (time.thread_time() - t0) * 1000.0, len(sel), _faults() - f0
    if kept is not None:
        kept[id(strategy)] = sel
    return out


def measure(
    path: str,
    size: tuple[int, int],
    taus: list[float],
    frames: int,
    reps: int,
    only: set[tuple[str, str]] | None = None,
    drop: bool = False,
):
    """Rows ``{store, size, strategy, backend, tau, wall_ms, cpu_ms, selected, minor_faults}``
    (``selected``: ``len`` of the selection, jung-han's drawn triangles, seamless-patches' leaf
    patches; ``minor_faults``: the selecting thread's minor page faults, median per frame).
    ``only``: the ``(strategy, backend)`` pairs to time (default all four, interleaved);
    ``drop``: free each selection at once instead of keeping it until the strategy's next."""
    from render.strategies import get_strategy
    from tiler.store import open_store

    store = open_store(path)
    r, views = _frames(store, size, frames)
    jh = {b: get_strategy("jung-han", r, kernels=b) for b in ("numpy", "numba")}
    jh["numba"]._trees = jh["numpy"]._trees  # shared per-block trees (built once, untimed)
    runs = [("jung-han", "numpy", jh["numpy"]), ("jung-han", "numba", jh["numba"])]
    for b in ("numpy", "numba"):
        runs.append(("seamless-patches", b, get_strategy("seamless-patches", r, kernels=b)))
    if only:
        runs = [(n, b, st) for n, b, st in runs if (n, b) in only]
    for _, _, st in runs:  # warm: trees, packed forest, compiled kernels, tables
        for cam, res in views:
            st.select(cam, 1.0, resident=res)
    rows = []
    for tau in taus:
        acc = {(n, b): [[[], [], 0, []] for _ in views] for n, b, _ in runs}
        kept: dict | None = None if drop else {}
        for rep in range(reps):
            order = runs if rep % 2 == 0 else runs[::-1]
            for i, (cam, res) in enumerate(views):
                for n, b, st in order:
                    wall, cpu, tris, faults = _timed(st, cam, tau, res, kept)
                    a = acc[(n, b)][i]
                    a[0].append(wall)
                    a[1].append(cpu)
                    a[2] = tris
                    a[3].append(faults)
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
                    "minor_faults": statistics.mean(statistics.median(p[3]) for p in per),
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


BOUND_STORES = [str(WORK / "bound" / "s1025.zarr"), str(WORK / "bound" / "n44w072_auto.zarr")]
_FIELDS = ("block", "depth", "row", "col", "level", "delta", "rho", "snap")


def _same(a, b) -> bool:
    """Every array of two selections bit for bit (and dtype), clamped and violations."""
    arrays = all(
        getattr(a, f).dtype == getattr(b, f).dtype and np.array_equal(getattr(a, f), getattr(b, f))
        for f in _FIELDS
    )
    return arrays and (a.clamped, a.violations) == (b.clamped, b.violations)


def measure_metric(path: str, metric: str, size, p: int, fovs, taus, reps: int, nodata: str):
    """Rows ``{store, size, patch_log2, fov, tau, backend, wall_ms, cpu_ms, patches, same}``:
    ``qiu``'s selection with ``metric``, numpy against numba (module doc)."""
    from dataclasses import replace

    from render import select_kernels
    from render.pipeline import open_render_session
    from render.renderer import RenderConfig, TerrainRenderer
    from render.step import stream_step
    from render.strategies import get_strategy
    from streamer.run import make_path
    from tiler.store import open_store

    select_kernels.warm_up()
    store = open_store(path)
    cams = make_path(store, "default", frames=8, viewport=size)
    base = cams[len(cams) // 2]
    r = TerrainRenderer(store, RenderConfig(size=size, patch_log2=p))
    st = get_strategy("qiu", r, nodata=nodata)
    env = os.environ.get("TERRASTREAM_KERNELS")

    def select(backend, cam, tau, res):
        os.environ["TERRASTREAM_KERNELS"] = backend
        t0 = time.thread_time()
        sel, ms = st.select(cam, tau, metric, resident=res)
        return sel, ms, (time.thread_time() - t0) * 1000.0

    rows = []
    try:
        for fov in fovs:
            cam = replace(base, fov_y=fov)
            with open_render_session(store, 0.0, metric, r.p) as s:
                stream_step(s, r, cam)  # every block in view on the GPU at full resolution
            for tau in taus:
                with open_render_session(store, tau, metric, r.p, nodata=nodata) as s:
                    res = dict(stream_step(s, None, cam)[1])
                out = {b: select(b, cam, tau, res)[0] for b in ("numpy", "numba")}  # warm
                same = _same(out["numpy"], out["numba"])
                acc = {"numpy": ([], []), "numba": ([], [])}
                for rep in range(reps):
                    for b in ("numpy", "numba") if rep % 2 == 0 else ("numba", "numpy"):
                        _, ms, cpu = select(b, cam, tau, res)
                        acc[b][0].append(ms)
                        acc[b][1].append(cpu)
                for b, (wall, cpu) in acc.items():
                    rows.append({
                        "store": Path(path).name, "size": f"{size[0]}x{size[1]}",
                        "metric": metric, "nodata": nodata, "patch_log2": p, "fov": fov,
                        "tau": tau, "backend": b, "wall_ms": statistics.median(wall),
                        "cpu_ms": statistics.median(cpu), "patches": len(out[b]),
                        "same": same, "loadavg": os.getloadavg()[0],
                    })  # fmt: skip
    finally:
        r.close()
        if env is None:
            os.environ.pop("TERRASTREAM_KERNELS", None)
        else:
            os.environ["TERRASTREAM_KERNELS"] = env
    return rows


def main_metric(a) -> int:
    """The ``--metric`` run: table (numpy and numba side by side) and JSON; 1 when no store
    was measured."""
    taus = [float(t) for t in (a.taus or "0.5,1,2").split(",")]
    fovs = [float(f) for f in a.fovs.split(",")]
    sizes = [tuple(int(v) for v in s.split("x")) for s in (a.sizes or "320x240").split(",")]
    info, rows = machine_info(), []
    print("store size p fov tau numpy_ms numba_ms ratio numpy_cpu numba_cpu patches same load1")
    for path in a.stores or BOUND_STORES:
        if not Path(path).exists():
            print(f"# skipped {path}: missing (bench/bound_fov.py makes it)")
            continue
        for size in sizes:
            for p in (int(v) for v in a.patch_log2.split(",")):
                got = measure_metric(path, a.metric, size, p, fovs, taus, a.reps, a.nodata)
                rows += got
                for ref, nb in zip(got[::2], got[1::2], strict=True):
                    print(
                        f"{ref['store']} {ref['size']} {p} {ref['fov']:g} {ref['tau']:g} "
                        f"{ref['wall_ms']:.2f} {nb['wall_ms']:.2f} "
                        f"{ref['wall_ms'] / nb['wall_ms']:.1f} {ref['cpu_ms']:.2f} "
                        f"{nb['cpu_ms']:.2f} {ref['patches']} {ref['same']} {nb['loadavg']:.2f}",
                        flush=True,
                    )
    if not rows:  # (the committed JSON is not replaced by an empty one)
        print("error: no store was measured (see the # skipped lines)", file=sys.stderr)
        return 1
    info["loadavg_at_end"] = os.getloadavg()
    out = Path(a.out or RESULTS / f"select_cpu_{a.metric}.json")
    out.write_text(json.dumps(portable({"machine": info, "rows": rows}), indent=1))
    print(f"# wrote {out.relative_to(REPO) if out.is_relative_to(REPO) else out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Measure, print the table, write the JSON; 1 (no JSON written) when no store was
    measured."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stores", nargs="*")
    ap.add_argument("--taus", default=None, help="default 0.5,1,2,4 (--metric: 0.5,1,2)")
    ap.add_argument("--sizes", default=None, help="default 320x240,1024x768 (--metric: 320x240)")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--reps", type=int, default=None, help="default 3 (--metric: 5)")
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument(
        "--tune-malloc",
        action="store_true",
        help="fix glibc's mmap/trim thresholds first (tiler.malloc), so the numpy backend's "
        "large frees do not leave the numba selections zero-filling fresh pages",
    )
    ap.add_argument(
        "--only",
        default=None,
        help="STRATEGY:BACKEND[,...] to time, e.g. jung-han:numba (alone: each repetition "
        "still cycles through the frames); default every strategy and backend, interleaved",
    )
    ap.add_argument(
        "--drop",
        action="store_true",
        help="free each selection as soon as it is timed (the method before session 40; a "
        "renderer keeps the one it draws until the next replaces it)",
    )
    ap.add_argument("--out", default=None, help="default bench/results/select_cpu[_METRIC].json")
    ap.add_argument("--metric", default=None, help="time qiu's selection with this metric")
    ap.add_argument("--patch-log2", default="1,4", help="--metric: patch sizes (log2 cells)")
    ap.add_argument("--fovs", default="5,45,120,170", help="--metric: vertical FOVs")
    ap.add_argument("--nodata", default="gap", help="--metric: qiu's nodata rule")
    a = ap.parse_args(argv)
    if a.metric is not None:
        a.reps = 5 if a.reps is None else a.reps
        return main_metric(a)
    a.stores = a.stores or DEFAULT_STORES
    if a.tune_malloc:
        from tiler.malloc import tune_allocator

        if not tune_allocator():
            sys.exit("--tune-malloc: glibc's mallopt is not available here")
    only = None
    if a.only:
        pairs = [tuple(v.strip().split(":", 1)) for v in a.only.split(",")]
        known = {(n, b) for n in ("jung-han", "seamless-patches") for b in ("numpy", "numba")}
        bad = [":".join(p) for p in pairs if p not in known]
        if bad:
            ap.error(f"--only {bad[0]!r}: use STRATEGY:BACKEND from {sorted(known)}")
        only = set(pairs)
    a.taus, a.sizes = a.taus or "0.5,1,2,4", a.sizes or "320x240,1024x768"
    a.reps = 3 if a.reps is None else a.reps
    a.out = a.out or str(RESULTS / "select_cpu.json")
    taus = [float(t) for t in a.taus.split(",")]
    sizes = [tuple(int(v) for v in s.split("x")) for s in a.sizes.split(",")]
    info = machine_info()
    info["tune_malloc"] = bool(a.tune_malloc)
    info["only"] = sorted(":".join(p) for p in only) if only else None
    info["drop"] = bool(a.drop)
    rows, compile_s = [], {}
    print("store size strategy backend tau wall_ms cpu_ms selected faults load1")
    for path in a.stores:
        ensure_store(path)  # the default stores are made on first use
        if not Path(path).exists():
            print(f"# skipped {path}: missing (bench/tiling.py / bench/prefetch.py make it)")
            continue
        if not a.no_compile:
            compile_s[Path(path).name] = compile_times(path)
            print(f"# {Path(path).name} numba compile/load s: {compile_s[Path(path).name]}")
        for size in sizes:
            for row in measure(path, size, taus, a.frames, a.reps, only, a.drop):
                rows.append(row)
                print(
                    f"{row['store']} {row['size']} {row['strategy']} {row['backend']} "
                    f"{row['tau']:g} {row['wall_ms']:.2f} {row['cpu_ms']:.2f} "
                    f"{row['selected']:.0f} {row['minor_faults']:.0f} {row['loadavg']:.2f}",
                    flush=True,
                )
    if not rows:  # (the committed JSON is not replaced by an empty one)
        print("error: no store was measured (see the # skipped lines)", file=sys.stderr)
        return 1
    info["loadavg_at_end"] = os.getloadavg()
    Path(a.out).write_text(
        json.dumps(portable({"machine": info, "compile": compile_s, "rows": rows}), indent=1)
    )
    print(f"# wrote {Path(a.out).relative_to(REPO) if Path(a.out).is_relative_to(REPO) else a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
