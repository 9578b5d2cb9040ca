"""Selection on a low oblique view over the 16385² store (issue 10 item 7, issue 14): a scene
where τ changes every strategy's selection, so the CPU selection figures are measured where the
selection does work.

Usage::

    python bench/low_view.py [STORE ...] [--taus 0.5,1,2,4] [--size 1024x768] [--frames 8]
                             [--clearance 150] [--pitch -8] [--reps 3] [--lods a,b]
                             [--out bench/results/low_view.json]

Default stores: ``r16385`` — rough terrain at 16385²: the real SRTM tile N44W072 (1201², 3″)
mirror-tiled (``numpy.pad(mode="symmetric")``, so no seams) to 16385² samples and labelled
EPSG:32619 at 90 m, blocks of 1025² (made on first use in ``bench/work``; needs the shared
data) — and the synthetic ``s16385`` of ``bench/prefetch.py`` for comparison (smooth: its
2 km of relief spread over 491 km, every visible node is one patch at every τ).

The view is ``bench/lod_compare.py --view low``: the default path's cameras lowered to
``--clearance`` metres above the highest terrain within two block edges and pitched ``--pitch``
degrees. Every block the frustum hull sees is streamed at full resolution (a τ = 0 session, as
``terrastream compare``), so no strategy is held back by what Qiu's metric would load. Per
strategy and τ, over the frames: triangles drawn (mean, min, max), the thread CPU ms of
``select()`` on the caller's thread (median of ``--reps`` repetitions per frame, then mean and
max over frames), the ms ``select()`` reports (``select ms``: for ``geometry-splitting`` and
``chunk-tessellation-gpu`` only the CPU share — block table, uniforms — since their passes are
GPU work) and the draw's GPU ms (llvmpipe wall to ``finish()``). On llvmpipe the vertex and
geometry stages of the GPU passes run on the calling thread, so the thread CPU of the two GPU-
selecting strategies includes their "GPU" traversal; on a real GPU it would not. Measured screen
error is not computed here: the full-resolution reference of a low view over 268 M samples does
not fit this benchmark's time (``bench/lod_compare.py`` measures errors on the 4097² and real
stores). A ``# unchanged`` line is printed for every strategy and pair of consecutive τ whose
mean triangle count is equal.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import REAL_HGT, RESULTS, S16385, WORK, machine_info, portable  # noqa: E402
from bench.lod_compare import low_oblique  # noqa: E402

R16385 = WORK / "r16385.zarr"


def prepare_rough(size: int = 16385) -> Path | None:
    """The ``r16385`` store (see the module docstring); None without the shared data."""
    import subprocess

    if (R16385 / "zarr.json").exists() and _complete(R16385):
        return R16385
    if not REAL_HGT.exists():
        print(f"# skipping r16385: {REAL_HGT} not found (set TERRASTREAM_SHARED_DATA)")
        return None
    import rasterio
    from rasterio.crs import CRS
    from rasterio.transform import Affine

    src = WORK / "r16385.tif"
    if not src.exists():
        with rasterio.open(REAL_HGT) as ds:
            arr = ds.read(1)
        n = arr.shape[0]
        reps = -(-size // n)
        big = np.pad(arr, ((0, reps * n - n), (0, reps * n - n)), mode="symmetric")[:size, :size]
        prof = dict(
            driver="GTiff",
            dtype=big.dtype.name,
            width=size,
            height=size,
            count=1,
            crs=CRS.from_epsg(32619),
            transform=Affine(90.0, 0.0, 300000.0, 0.0, -90.0, 5000000.0),
            tiled=True,
            blockxsize=512,
            blockysize=512,
            compress="deflate",
        )
        WORK.mkdir(parents=True, exist_ok=True)
        with rasterio.open(src, "w", **prof) as out:
            out.write(big, 1)
    exe = str(Path(sys.executable).with_name("terrastream"))
    cmd = [exe, "tile", str(src), str(R16385), "--block-size", "1025", "--overwrite"]
    subprocess.run(cmd, check=True)
    return R16385


def _complete(path: Path) -> bool:
    from tiler.store import open_store

    try:
        open_store(str(path))
    except Exception:  # noqa: BLE001 - any failure means "make it again"
        return False
    return True


def measure(
    path: str,
    size: tuple[int, int],
    taus: list[float],
    frames: int,
    reps: int,
    clearance: float,
    pitch: float,
    lods: list[str] | None,
) -> list[dict]:
    """One row per strategy and τ over the low oblique path of ``path``."""
    from render.pipeline import open_render_session
    from render.renderer import RenderConfig, TerrainRenderer
    from render.step import stream_step
    from render.strategies import get_strategy, strategy_names
    from render.strategies.base import DrawOptions
    from streamer.run import make_path
    from tiler.store import open_store

    store = open_store(path)
    cams = low_oblique(
        store, make_path(store, "default", frames=frames, viewport=size), clearance, pitch
    )
    r = TerrainRenderer(store, RenderConfig(size=size, patch_log2=4))
    names = lods or list(strategy_names())
    acc: dict[tuple[str, float], dict[str, list[float]]] = {}
    strategies = {n: get_strategy(n, r) for n in names}
    t_stream = 0.0
    with open_render_session(store, 0.0, "qiu", r.p) as sess:
        for i, cam in enumerate(cams):
            t0 = time.perf_counter()
            _, res = stream_step(sess, r, cam)
            t_stream += time.perf_counter() - t0
            print(
                f"# frame {i}: {len(res)} blocks resident, "
                f"streamed in {time.perf_counter() - t0:.1f} s"
            )
            for name, strat in strategies.items():
                for tau in taus:
                    strat.select(cam, tau, "qiu", resident=res)  # warm (trees, kernels)
                    cpu, rep = [], []
                    for _ in range(reps):
                        c0 = time.thread_time()
                        sel, ms = strat.select(cam, tau, "qiu", resident=res)
                        cpu.append((time.thread_time() - c0) * 1000.0)
                        rep.append(ms)
                    st = strat.draw(cam, sel, DrawOptions())
                    a = acc.setdefault((name, tau), {"tris": [], "cpu": [], "rep": [], "gpu": []})
                    a["tris"].append(st.triangles)
                    a["cpu"].append(statistics.median(cpu))
                    a["rep"].append(statistics.median(rep))
                    a["gpu"].append(st.frame_ms)
    r.close()
    rows = []
    for (name, tau), a in acc.items():
        rows.append(
            {
                "strategy": name,
                "tau": tau,
                "triangles_mean": float(np.mean(a["tris"])),
                "triangles_min": int(min(a["tris"])),
                "triangles_max": int(max(a["tris"])),
                "cpu_ms_mean": float(np.mean(a["cpu"])),
                "cpu_ms_max": float(max(a["cpu"])),
                "reported_ms_mean": float(np.mean(a["rep"])),
                "gpu_ms_mean": float(np.mean(a["gpu"])),
                "frames": len(a["tris"]),
            }
        )
    print(f"# streaming {t_stream:.1f} s")
    return rows


def table(rows: list[dict]) -> str:
    """The printed table."""
    head = (
        f"{'strategy':>20} {'tau':>5} {'tris mean (min-max)':>26} "
        f"{'CPU ms mean/max':>16} {'select ms':>9} {'GPU ms':>8}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        tri = f"{r['triangles_mean']:,.0f} ({r['triangles_min']:,}-{r['triangles_max']:,})"
        lines.append(
            f"{r['strategy']:>20} {r['tau']:>5g} {tri:>26} "
            f"{r['cpu_ms_mean']:>7.2f}/{r['cpu_ms_max']:<8.2f} {r['reported_ms_mean']:>9.2f} "
            f"{r['gpu_ms_mean']:>8.1f}"
        )
    for name in dict.fromkeys(r["strategy"] for r in rows):
        rs = [r for r in rows if r["strategy"] == name]
        for a, b in zip(rs, rs[1:], strict=False):
            if a["triangles_mean"] == b["triangles_mean"]:
                lines.append(f"# unchanged: {name} at tau {a['tau']:g} and {b['tau']:g}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stores", nargs="*", help="default: r16385 (made on first use) and s16385")
    ap.add_argument("--taus", default="0.5,1,2,4")
    ap.add_argument("--size", default="1024x768")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--clearance", type=float, default=150.0)
    ap.add_argument("--pitch", type=float, default=-8.0)
    ap.add_argument("--lods", default=None, help="comma-separated strategies (default: all)")
    ap.add_argument("--out", default=str(RESULTS / "low_view.json"))
    a = ap.parse_args(argv)
    from render.strategies import warm_up_kernels

    warm_up_kernels()  # the compiled CPU kernels, as the viewer uses them after warming up
    stores = a.stores or [str(p) for p in (prepare_rough(), S16385) if p is not None]
    size = tuple(int(v) for v in a.size.split("x"))
    taus = [float(t) for t in a.taus.split(",")]
    lods = a.lods.split(",") if a.lods else None
    rec: dict = {
        "size": list(size),
        "frames": a.frames,
        "clearance_m": a.clearance,
        "pitch_deg": a.pitch,
        "stores": {},
        "machine": machine_info(),
    }
    for path in stores:
        if not Path(path).exists():
            print(f"# skipping {path}: not found (bench/prefetch.py makes s16385)")
            continue
        print(f"# {path} {size[0]}x{size[1]}, {a.frames} frames, low view")
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        rows = measure(path, size, taus, a.frames, a.reps, a.clearance, a.pitch, lods)
        print(table(rows))
        rec["stores"][portable(path)] = {
            "wall_s": time.perf_counter() - t0,
            "loadavg_before": load0,
            "loadavg_after": os.getloadavg(),
            "rows": rows,
        }
    if not rec["stores"]:
        print("error: no store was measured (see the # skipping lines)", file=sys.stderr)
        return 1
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(portable(rec), indent=1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
