"""Prefetch benchmark: real-time fly-throughs with frustum-extension prefetching on and off.

Usage::

    python bench/prefetch.py [--quick] [--frames 10000] [--short-frames 1200]
                             [--speeds 0.5,1,2] [--latencies 0,20] [--stores synth,real,real-deg]
                             [--workers 16] [--compare-workers 4] [--no-http]
                             [--budget-mb 256] [--tau 1]
                             [--no-plot] [--out bench/results/prefetch.json]

Each run flies ``streamer.run.make_path(store, "default", speed=edge * speed)`` (``edge`` = one
block edge in world units, so ``--speeds`` are block edges per second) at 60 fps in real time
through a :class:`streamer.session.Session` and records the session summary plus figures derived
from the per-frame :class:`~streamer.session.FrameStats`.

The matrix: for every store, the *headline* configurations (speed 1 edge/s, 20 ms latency,
prefetch on and off) fly ``--frames`` frames; every other (speed, latency, prefetch) combination
flies ``--short-frames``. Latency is ``SessionConfig.latency_ms`` (a sleep in the loader thread
before every store request); in addition one headline run reads the synthetic store over HTTP
from a loopback server (``tests/rangeserver.py``, run in a child process so it does not share
this process's GIL) that sleeps 20 ms before answering every request, and one short run repeats
the synthetic headline configuration with ``--compare-workers`` loader threads.

Stores: ``synth`` is the 16385^2 int16 synthetic DEM (``terrastream synth --seed 1`` when
``tiler.synth.synth_dem`` exists, else the existing ``bench/work/synth_16385_seed0_int16.tif``)
tiled with 1025^2 blocks; ``real`` is SRTM N44W072 (1201^2, 3 arc-seconds) tiled with 257^2
blocks after relabelling its lon/lat grid in metres (an equirectangular projection at its middle
latitude: the same samples, no resampling, 66.2 m x 92.8 m spacing), because the streamer treats
x/y and z as one unit and the EPSG:4326 store has degrees across and metres up; ``real-deg`` is
that EPSG:4326 store as tiled, for comparison (one short run by default).

Pacing is ``run_flythrough``'s: ``Session.warm_up(cameras[0])`` (loads what the plan for the
first pose wants, reported as warm-up ms / bytes: Qiu's "frame 1"), then frame ``i`` is due
``i / fps`` after the warm-up and frame 0 waits for its data. The loop is re-implemented here
(same calls) to see each ``Frame.blocks`` and the cache between frames.

Bytes are decoded level bytes (the session's unit). "needed" is the sum over frames of each
frame's needed bytes (``summary()['needed_bytes']``, what ``terrastream stream`` reports);
"used" is the distinct (block, level) bytes frames drew (``summary()['used_bytes']``), so
``loaded / used`` also counts levels evicted and loaded again on a later pass over the same
ground; :class:`LoadLedger` watches the cache after every frame and reports ``loaded / bytes of
loads drawn before their eviction`` as well (both are checked). Stalled blocks are classified
(new in view or refining; within one block edge of the eye or not), and Python garbage
collections during ``update`` are counted against frames whose update CPU exceeds 2 ms.

Stalls are counted over Qiu's triangle (the session's ``culling="qiu"``) and, with
``account_hull=True``, over the frustum hull the renderer draws (a second plan per frame, which
the update CPU figures include; ``bench/session_update.py`` measures the caller without it).
Two figures independent of stalls: ``late_bytes`` (bytes that arrived after the frame that first
needed them was due) and ``coarse_frames`` (frames drawn coarser than needed, by levels in the
JSON).

Timings on a shared 2-core machine are noisy: compare ratios within one run of this script.
MB = MiB.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import gc
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import REAL_HGT, REPO, RESULTS, WORK, git_head, machine_info, portable  # noqa: E402
from streamer.run import RunResult, make_path, plot_run  # noqa: E402
from streamer.session import Session, SessionConfig  # noqa: E402
from tiler.store import open_store  # noqa: E402

PWORK = WORK / "prefetch"
DEFAULT_OUT = RESULTS / "prefetch.json"
TERRASTREAM = str(Path(sys.executable).with_name("terrastream"))
MB = float(1 << 20)
FPS = 60.0
VIEWPORT = (1024, 768)

# Targets (issue #3), stated for prefetch on, 20 ms latency, speed <= 1 block edge/s.
T_STALLS_PER_10K = 1.0
T_REALTIME_PCT = 1.0
T_LOADED_PER_USED = 1.5
T_UPDATE_MS = 2.0
HEADLINE_SPEED = 1.0
HEADLINE_LATENCY = 20.0

# Qiu et al., Table 3 (tau = 2): frame -> (needed MB, real-time loaded MB, I/O ms) per dataset.
QIU_TABLE3 = {
    "Grand Canyon": {
        1: (1.193, 1.193, 20.2),
        162: (1.578, 0.376, 3.88),
        388: (1.297, 0.094, 1.18),
        4509: (1.372, 0.372, 3.38),
        5330: (1.446, 0.024, 0.67),
        7374: (1.508, 0.094, 0.70),
        8208: (1.384, 0.366, 3.31),
        10000: (1.203, 0.019, 0.41),
    },
    "Puget Sound": {
        1: (1.307, 1.307, 21.3),
        162: (1.975, 0.032, 0.59),
        388: (2.445, 0.034, 0.97),
        4509: (1.284, 0.007, 0.19),
        5330: (1.719, 0.007, 0.16),
        7374: (1.113, 0.008, 0.23),
        8208: (2.267, 0.024, 0.30),
        10000: (1.132, 0.014, 0.29),
    },
    "Southeast of China": {
        1: (1.425, 1.425, 30.9),
        162: (0.390, 0.012, 0.24),
        388: (1.975, 0.032, 0.90),
        4509: (1.472, 0.085, 0.07),
        5330: (1.769, 0.125, 1.10),
        7374: (1.267, 0.126, 1.15),
        8208: (0.272, 0.024, 0.46),
        10000: (1.132, 0.113, 1.09),
    },
}

FRAME_COLUMNS = (
    "needed_bytes",
    "realtime_bytes",
    "prefetched_bytes",
    "io_ms",
    "update_ms",
    "update_cpu_ms",
    "wait_ms",
    "stalled",
    "missing_levels",
    "resident_bytes",
    "visible_blocks",
    "prefetch_blocks",
    "late_ms",
)


def log(msg: str) -> None:
    print(msg, flush=True)


# --------------------------------------------------------------------------- stores


def _store_ok(path: Path) -> bool:
    """A complete store: ``terrastream info`` succeeds."""
    if not path.exists():
        return False
    r = subprocess.run([TERRASTREAM, "-q", "info", str(path)], capture_output=True, text=True)
    return r.returncode == 0


def _tile(src: Path, dst: Path, block_size: int) -> None:
    if _store_ok(dst):
        log(f"  reusing {dst.relative_to(REPO)}")
        return
    log(f"  tiling {src} -> {dst} (--block-size {block_size}) ...")
    t0 = time.perf_counter()
    cmd = [TERRASTREAM, "tile", str(src), str(dst), "--block-size", str(block_size)]
    subprocess.run([*cmd, "--overwrite"], check=True)
    log(f"  tiled in {time.perf_counter() - t0:.1f} s")


def _synth_available() -> bool:
    try:
        from tiler.synth import synth_dem  # noqa: F401
    except ImportError:
        return False
    return True


def prepare_synth() -> tuple[Path, str]:
    """The 16385^2 synthetic store and a note on its source."""
    if _synth_available():
        src = WORK / "s16385.tif"
        if not src.exists():
            log("  terrastream synth (16385^2, seed 1) ...")
            cmd = [TERRASTREAM, "synth", str(src), "--size", "16385", "--seed", "1"]
            subprocess.run(cmd, check=True)
        dst = WORK / "s16385.zarr"
        note = "terrastream synth --size 16385 --seed 1 (tiler.synth.synth_dem)"
    else:
        for seed in (0, 999):
            src = WORK / f"synth_16385_seed{seed}_int16.tif"
            if src.exists():
                break
        else:
            raise SystemExit("no synthetic 16385^2 source: tiler.synth.synth_dem is missing")
        dst = PWORK / f"synth16385_seed{seed}.zarr"
        note = (
            f"{src.relative_to(REPO)} (tiler.synth.synth_dem not available: the existing "
            f"seed-{seed} int16 source written by synth_array)"
        )
    _tile(src, dst, 1025)
    return dst, note


def prepare_real(metric: bool) -> tuple[Path, str] | None:
    """SRTM N44W072 with 257^2 blocks: metric relabelling (``metric``) or as-is EPSG:4326."""
    if not REAL_HGT.exists():
        return None
    if not metric:
        dst = PWORK / "n44w072_b257.zarr"
        _tile(REAL_HGT, dst, 257)
        return dst, f"{REAL_HGT} as tiled (EPSG:4326: x/y in degrees, z in metres)"
    import rasterio
    from rasterio.crs import CRS
    from rasterio.transform import Affine

    src = PWORK / "N44W072_eqc_m.tif"
    if not src.exists():
        with rasterio.open(REAL_HGT) as ds:
            arr, t, nodata = ds.read(1), ds.transform, ds.nodata
        a = 6378137.0
        lat_ts = round(t.f + t.e * ds.height / 2, 6)
        lon0 = round(t.c + t.a * ds.width / 2, 6)
        kx = a * math.cos(math.radians(lat_ts)) * math.pi / 180
        ky = a * math.pi / 180
        tr = Affine(t.a * kx, 0.0, (t.c - lon0) * kx, 0.0, t.e * ky, t.f * ky)
        crs = CRS.from_proj4(
            f"+proj=eqc +lat_ts={lat_ts} +lon_0={lon0} +lat_0=0 +datum=WGS84 +units=m +no_defs"
        )
        prof = dict(
            driver="GTiff",
            dtype=arr.dtype.name,
            width=arr.shape[1],
            height=arr.shape[0],
            count=1,
            crs=crs,
            transform=tr,
            nodata=nodata,
        )
        PWORK.mkdir(parents=True, exist_ok=True)
        with rasterio.open(src, "w", **prof) as out:
            out.write(arr, 1)
    dst = PWORK / "n44w072_eqc_b257.zarr"
    _tile(src, dst, 257)
    return dst, (
        f"{REAL_HGT} relabelled in metres (equirectangular at the tile's middle latitude, same "
        "samples, 66.2 m x 92.8 m), 257^2 blocks"
    )


# --------------------------------------------------------------------------- HTTP server


@contextlib.contextmanager
def http_server(directory: Path, latency_s: float):
    """``tests/rangeserver.LoopbackServer`` in a child process; yields its URL."""
    code = (
        "import sys, time\n"
        f"sys.path.insert(0, {str(REPO / 'tests')!r})\n"
        "from rangeserver import LoopbackServer\n"
        f"with LoopbackServer({str(directory)!r}, {latency_s!r}) as url:\n"
        "    print(url, flush=True)\n"
        "    sys.stdin.read()\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        url = proc.stdout.readline().strip()
        if not url.startswith("http://"):
            raise RuntimeError(f"loopback server did not start (got {url!r})")
        yield url
    finally:
        with contextlib.suppress(Exception):
            proc.stdin.close()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# --------------------------------------------------------------------------- one run


class LoadLedger:
    """Per-load accounting, observed from outside the session after every frame.

    The session's ``used_bytes`` counts each (block, level) once however often it is evicted
    and loaded again, so on a path that passes the same ground twice ``loaded / used`` also
    counts re-loads. Here the resident level of every cached block (the public
    ``LevelCache.blocks`` / ``level``) is compared with the previous frame's: a rise is a load
    of each new level, a fall an eviction. A load is *used* once a frame draws it (a visible
    block's levels ``0..min(resident, needed)``) before it is evicted; an evicted load that no
    frame drew is wasted. Loads evicted within one frame are not seen (rare).
    """

    def __init__(self, level_bytes: list[int]) -> None:
        self.level_bytes = level_bytes
        self.drawn: dict[tuple[int, int], list[bool]] = {}  # per resident level: drawn yet?
        self.loaded = 0
        self.used = 0
        self.evicted_unused = 0
        self.evicted_used = 0

    def frame(self, session: Session, blocks: dict) -> None:
        cache = session.cache
        for _ in range(10):
            try:
                cached = cache.blocks()
                break
            except RuntimeError:  # a loader thread changed the cache meanwhile: look again
                continue
        else:
            return
        now = {b: cache.level(b) for b in cached}
        for b in set(self.drawn) | set(now):
            flags = self.drawn.setdefault(b, [])
            top = now.get(b, -1)
            while len(flags) - 1 > top:  # evicted
                lv = len(flags) - 1
                if flags.pop():
                    self.evicted_used += self.level_bytes[lv]
                else:
                    self.evicted_unused += self.level_bytes[lv]
            while len(flags) - 1 < top:  # loaded
                self.loaded += self.level_bytes[len(flags)]
                flags.append(False)
            if not flags:
                del self.drawn[b]
        for b, (have, need) in blocks.items():
            flags = self.drawn.get(b)
            if not flags:
                continue
            for lv in range(min(have, need, len(flags) - 1) + 1):
                if not flags[lv]:
                    flags[lv] = True
                    self.used += self.level_bytes[lv]

    def result(self) -> dict[str, int]:
        resident_unused = sum(
            self.level_bytes[lv] for f in self.drawn.values() for lv, d in enumerate(f) if not d
        )
        return {
            "observed_loaded_bytes": self.loaded,
            "used_load_bytes": self.used,
            "evicted_unused_bytes": self.evicted_unused,
            "evicted_used_bytes": self.evicted_used,
            "resident_unused_bytes_at_end": resident_unused,
        }


def fly(session: Session, cameras: list) -> dict[str, Any]:
    """Fly ``cameras`` through ``session`` as ``streamer.run.run_flythrough`` does (warm-up for
    the first pose, frame ``i`` due ``i / fps`` later, frame 0 waits); per-frame rows.

    ``late_ms`` is how late a frame's update started (0 when on time).
    """
    fps = session.config.fps
    grid = session.grid
    rows: list[dict[str, Any]] = []
    causes = {
        "new_block": 0,  # not visible in the previous frame
        "refine": 0,  # visible before, now needs a finer level
        "nothing_resident": 0,
        "near_camera": 0,  # the eye is over the block or within one block edge of it
        "away_from_camera": 0,
    }
    edge = grid.step * grid.dx
    stall_frames: list[int] = []
    prev_blocks: set = set()
    ledger = LoadLedger(session.level_bytes)
    gc_log: list[tuple[str, int, float]] = []

    def on_gc(phase: str, info: dict) -> None:
        gc_log.append((phase, info["generation"], time.perf_counter()))

    gc.callbacks.append(on_gc)
    gc_frames = {"any": 0, "gen2": 0, "slow_cpu_with_gc": 0, "slow_cpu": 0}
    if cameras:
        session.warm_up(cameras[0])
    t0 = time.perf_counter()
    for i, cam in enumerate(cameras):
        late = 0.0
        delay = t0 + i / fps - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        else:
            late = -delay
        n_gc = len(gc_log)
        try:
            frame = session.update(cam, 1.0 / fps, wait=i == 0)
        except BaseException:
            gc.callbacks.remove(on_gc)
            raise
        gcs = [g for g in gc_log[n_gc:] if g[0] == "start"]
        gc_log.clear()
        slow = frame.stats.update_cpu_ms > T_UPDATE_MS
        gc_frames["any"] += bool(gcs)
        gc_frames["gen2"] += any(g[1] == 2 for g in gcs)
        gc_frames["slow_cpu"] += slow
        gc_frames["slow_cpu_with_gc"] += slow and bool(gcs)
        row = asdict(frame.stats)
        row["late_ms"] = late * 1000.0
        rows.append(row)
        if frame.stats.stalled:
            stall_frames.append(i)
            for b, (have, need) in frame.blocks.items():
                if have < need:
                    if have < 0:
                        causes["nothing_resident"] += 1
                    causes["new_block" if b not in prev_blocks else "refine"] += 1
                    x0, y0, x1, y1 = (float(v) for v in grid.block_bounds(b[0], b[1]))
                    cx, cy = float(cam.position[0]), float(cam.position[1])
                    gap = math.hypot(max(x0 - cx, 0.0, cx - x1), max(y0 - cy, 0.0, cy - y1))
                    causes["near_camera" if gap <= edge else "away_from_camera"] += 1
        prev_blocks = set(frame.blocks)
        ledger.frame(session, frame.blocks)
    gc.callbacks.remove(on_gc)
    return {
        "gc_during_update": gc_frames,
        "rows": rows,
        "stall_frames": stall_frames,
        "stall_block_causes": causes,
        "ledger": ledger.result(),
    }


def _yaw_rates(cameras: list) -> np.ndarray:
    """Degrees per second of heading change at each frame."""
    yaw = np.array([c.yaw for c in cameras])
    d = np.abs((np.diff(yaw, prepend=yaw[0]) + 180.0) % 360.0 - 180.0)
    return d * FPS


def derive(rows: list[dict], summary: dict, cameras: list, out: dict) -> dict[str, Any]:
    """Per-run figures beyond the session summary."""
    n = len(rows)
    rest = rows[1:] or rows
    rt_rest = np.array([r["realtime_bytes"] for r in rest], dtype=np.float64)
    upd = np.array([r["update_ms"] for r in rows])
    cpu = np.array([r["update_cpu_ms"] for r in rows])
    io = np.array([r["io_ms"] for r in rest])
    late = np.array([r["late_ms"] for r in rows])
    needed = max(summary["needed_bytes"], 1)
    used = max(summary["used_bytes"], 1)
    stalls = out["stall_frames"]
    yaw_rate = _yaw_rates(cameras)
    startup = [i for i in stalls if i <= int(FPS)]
    f0 = rows[0]
    return {
        "frames": n,
        "stall_frames": summary["stall_frames"],
        # over the frustum hull the renderer draws (account_hull), beside Qiu's triangle
        "stall_frames_hull": summary["stall_frames_hull"],
        # independent of stalls: bytes that arrived after the frame that first needed them was
        # due, and frames drawn coarser than needed (by how many levels)
        "late_bytes": summary["late_bytes"],
        "coarse_frames_by_levels": summary["coarse_frames_by_levels"],
        "coarse_frames": int(sum(summary["coarse_frames_by_levels"].values())),
        "stalls_per_10k": 1e4 * summary["stall_frames"] / n,
        "stall_frame_list": stalls[:200],
        "stalls_in_first_second": len(startup),
        "stall_block_causes": out["stall_block_causes"],
        "stall_yaw_rate_deg_s_mean": float(yaw_rate[stalls].mean()) if stalls else None,
        "path_yaw_rate_deg_s_mean": float(yaw_rate[1:].mean()) if n > 1 else 0.0,
        "needed_bytes": summary["needed_bytes"],
        "needed_bytes_per_frame_mean": summary["needed_bytes"] / n,
        "realtime_bytes_after_first_frame": summary["realtime_bytes_after_first_frame"],
        "realtime_pct_of_needed": 100.0 * summary["realtime_bytes_after_first_frame"] / needed,
        "realtime_pct_of_used": 100.0 * summary["realtime_bytes_after_first_frame"] / used,
        "warmup_ms": summary.get("warmup_ms", 0.0),
        "warmup_bytes": summary.get("warmup_bytes", 0),
        "frame0_loaded_bytes": f0["realtime_bytes"] + f0["prefetched_bytes"],
        "frame0_io_ms": f0["io_ms"],
        "frame0_wait_ms": f0["wait_ms"],
        # Qiu's "frame 1": the warm-up plus frame 0
        "first_frame_loaded_bytes": summary.get("warmup_bytes", 0)
        + f0["realtime_bytes"]
        + f0["prefetched_bytes"],
        "first_frame_needed_bytes": f0["needed_bytes"],
        "first_frame_ms": summary.get("warmup_ms", 0.0) + f0["wait_ms"],
        "realtime_bytes_per_frame_mean": float(rt_rest.mean()),
        "realtime_bytes_per_frame_max": int(rt_rest.max()),
        "frames_with_realtime_loads": int((rt_rest > 0).sum()),
        "prefetched_bytes": summary["prefetched_bytes"],
        "loaded_bytes": summary["loaded_bytes"],
        "used_bytes": summary["used_bytes"],
        "loaded_per_used": summary["loaded_bytes"] / used,
        "wasted_bytes": summary["wasted_bytes"],
        **out["ledger"],
        "loaded_per_used_load": summary["loaded_bytes"] / max(out["ledger"]["used_load_bytes"], 1),
        "never_used_load_bytes": out["ledger"]["evicted_unused_bytes"]
        + out["ledger"]["resident_unused_bytes_at_end"],
        "peak_resident_bytes": summary["peak_resident_bytes"],
        "budget_bytes": summary["budget_bytes"],
        "max_update_ms": float(upd.max()),
        "max_update_ms_after_first": float(upd[1:].max()) if n > 1 else float(upd.max()),
        "p99_update_ms": float(np.percentile(upd, 99)),
        "max_update_cpu_ms": float(cpu.max()),
        "max_update_cpu_ms_after_first": float(cpu[1:].max()) if n > 1 else float(cpu.max()),
        "p99_update_cpu_ms": float(np.percentile(cpu, 99)),
        "frames_update_cpu_over_2ms": int((cpu > T_UPDATE_MS).sum()),
        "io_ms_per_frame_mean": float(io.mean()),
        "io_ms_per_frame_max": float(io.max()),
        "late_frames": int((late > 1000.0 / FPS).sum()),
        "max_late_ms": float(late.max()),
        "gc_during_update": out["gc_during_update"],
        "io_errors": summary["io_errors"],
        "cancelled_loads": summary["cancelled_loads"],
    }


def checks(m: dict[str, Any]) -> dict[str, bool]:
    """PASS (True) / MISS (False) per target."""
    return {
        "stalls": m["stalls_per_10k"] <= T_STALLS_PER_10K,
        "realtime": m["realtime_pct_of_needed"] <= T_REALTIME_PCT,
        "realtime_strict": m["realtime_pct_of_used"] <= T_REALTIME_PCT,
        "loaded_vs_used": m["loaded_per_used"] <= T_LOADED_PER_USED,
        "loaded_vs_used_per_load": m["loaded_per_used_load"] <= T_LOADED_PER_USED,
        "budget": m["peak_resident_bytes"] <= m["budget_bytes"],
        "update_cpu": m["max_update_cpu_ms"] <= T_UPDATE_MS,
        "update_wall": m["max_update_ms"] <= T_UPDATE_MS,
    }


def run_one(spec: dict[str, Any], args: argparse.Namespace, stores: dict) -> dict[str, Any]:
    """Fly one configuration; returns its record (rows kept under ``_rows`` for headlines)."""
    path, _note = stores[spec["store"]]
    cfg = dict(
        budget_mb=args.budget_mb,
        workers=spec["workers"],
        fps=FPS,
        tau=args.tau,
        prefetch=spec["prefetch"],
        latency_ms=0.0 if spec["transport"] == "http" else spec["latency_ms"],
        account_hull=True,
    )
    ctx = (
        http_server(path.parent, spec["latency_ms"] / 1000.0)
        if spec["transport"] == "http"
        else contextlib.nullcontext(None)
    )
    load0 = os.getloadavg()
    with ctx as url:
        store = open_store(f"{url}/{path.name}" if url else str(path))
        edge = store.grid.step * store.grid.dx
        cams = make_path(
            store,
            "default",
            frames=spec["frames"],
            fps=FPS,
            speed=edge * spec["speed"],
            viewport=VIEWPORT,
        )
        t0 = time.perf_counter()
        with Session(store, SessionConfig(**cfg)) as session:
            out = fly(session, cams)
            summary = session.summary()
        wall = time.perf_counter() - t0
    m = derive(out["rows"], summary, cams, out)
    rec = {
        **spec,
        "session_config": cfg,
        "block_edge_world": edge,
        "speed_world_per_s": edge * spec["speed"],
        "wall_s": wall,
        "loadavg_before": load0,
        "loadavg_after": os.getloadavg(),
        "metrics": m,
        "checks": checks(m),
        "summary": summary,
    }
    if spec["headline"]:
        rec["_rows"] = out["rows"]
    return rec


# --------------------------------------------------------------------------- matrix


def build_matrix(args: argparse.Namespace, stores: dict) -> list[dict[str, Any]]:
    specs: list[dict[str, Any]] = []

    def add(store, speed, lat, pf, frames, headline, transport="sleep", workers=None):
        w = args.workers if workers is None else workers
        name = (
            f"{store}-v{speed:g}-l{lat:g}{'-http' if transport == 'http' else ''}-"
            f"{'pf' if pf else 'nopf'}-w{w}"
        )
        specs.append(
            dict(
                name=name,
                store=store,
                speed=speed,
                latency_ms=lat,
                transport=transport,
                prefetch=pf,
                workers=w,
                frames=frames,
                headline=headline,
                in_target_scope=bool(pf and lat >= HEADLINE_LATENCY and speed <= HEADLINE_SPEED),
            )
        )

    main = [s for s in args.stores if s != "real-deg" and s in stores]
    for store in main:
        for pf in (True, False):
            add(store, HEADLINE_SPEED, HEADLINE_LATENCY, pf, args.frames, True)
    if args.http and "synth" in stores:
        add("synth", HEADLINE_SPEED, HEADLINE_LATENCY, True, args.frames, True, transport="http")
    for store in main:
        for speed in args.speeds:
            for lat in args.latencies:
                for pf in (True, False):
                    if speed == HEADLINE_SPEED and lat == HEADLINE_LATENCY:
                        continue
                    add(store, speed, lat, pf, args.short_frames, False)
    if "synth" in stores:
        for w in args.compare_workers:
            if w != args.workers:
                v, lat, n = HEADLINE_SPEED, HEADLINE_LATENCY, args.short_frames
                add("synth", v, lat, True, n, False, workers=w)
    if "real-deg" in stores:
        add("real-deg", HEADLINE_SPEED, HEADLINE_LATENCY, True, args.short_frames, False)
    return specs


# --------------------------------------------------------------------------- reporting


def _pf(ok: bool) -> str:
    return "PASS" if ok else "MISS"


def table(records: list[dict[str, Any]]) -> str:
    head = (
        f"{'configuration':<30} {'frames':>6} {'stall':>5} {'hull':>5} {'/10k':>7} {'lateMB':>7} "
        f"{'coarse':>6} {'rt%need':>8} "
        f"{'rt%used':>8} {'ld/used':>7} {'ld/load':>7} {'peakMB':>7} {'updCPU':>7} {'p99CPU':>7} "
        f"{'updWall':>7} {'io ms/f':>7} {'f1 MB':>6} {'f1 ms':>6} {'late':>5}  "
        "stall rt   ld   ld2  budg upd"
    )
    lines = [head, "-" * len(head)]
    for r in records:
        m, c = r["metrics"], r["checks"]
        scope = "*" if r["in_target_scope"] else " "
        lines.append(
            f"{scope}{r['name']:<29} {m['frames']:>6} {m['stall_frames']:>5} "
            f"{m['stall_frames_hull']:>5} {m['stalls_per_10k']:>7.1f} "
            f"{m['late_bytes'] / MB:>7.3f} {m['coarse_frames']:>6} "
            f"{m['realtime_pct_of_needed']:>8.4f} "
            f"{m['realtime_pct_of_used']:>8.2f} {m['loaded_per_used']:>7.2f} "
            f"{m['loaded_per_used_load']:>7.2f} "
            f"{m['peak_resident_bytes'] / MB:>7.1f} {m['max_update_cpu_ms']:>7.2f} "
            f"{m['p99_update_cpu_ms']:>7.2f} {m['max_update_ms']:>7.1f} "
            f"{m['io_ms_per_frame_mean']:>7.2f} {m['first_frame_loaded_bytes'] / MB:>6.2f} "
            f"{m['first_frame_ms']:>6.0f} {m['late_frames']:>5}  "
            f"{_pf(c['stalls'])} {_pf(c['realtime'])} {_pf(c['loaded_vs_used'])} "
            f"{_pf(c['loaded_vs_used_per_load'])} "
            f"{_pf(c['budget'])} {_pf(c['update_cpu'])}"
        )
    lines.append(
        "* = in the targets' scope (prefetch on, 20 ms latency, <= 1 block edge/s). stall = "
        "frames that lacked a needed level over Qiu's triangle, hull = over the frustum hull the "
        "renderer draws; lateMB = bytes that arrived after the frame that first needed them was "
        "due (independent of stalls); coarse = frames drawn coarser than needed. rt%need = "
        "real-time bytes after frame 1 / sum of per-frame needed bytes (target <= 1 %); rt%used ="
        " the same / distinct bytes drawn (stricter, not a target); ld/used = loaded / distinct "
        "(block, level) bytes drawn (the session's used_bytes; re-loads on a second pass count as"
        " waste) <= 1.5 (check 'ld'); ld/load = loaded / bytes of loads that a frame drew before "
        "their eviction (check 'ld2'); peak resident"
        " <= budget; updCPU = max caller-thread CPU ms of update() (target <= 2 ms), updWall = its"
        " wall ms; io ms/f = mean loader-thread ms per frame after frame 1 (includes the latency "
        "sleeps); f1 = warm-up + frame 0: loaded MB and wall ms; late = frames started > 1 "
        "period late."
    )
    return "\n".join(lines)


def qiu_table(records: list[dict[str, Any]]) -> tuple[str, list[dict[str, Any]]]:
    """Needed / real-time MB and I/O ms at Qiu's frame numbers: Qiu (tau 2) and ours."""
    ours = [r for r in records if r["headline"] and r["prefetch"] and "_rows" in r]
    cols = []
    head = f"{'frame':>6}"
    for name in QIU_TABLE3:
        head += f" | {name[:18]:^22}"
        cols.append(("qiu", name))
    for r in ours:
        head += f" | {r['name'][:22]:^22}"
        cols.append(("ours", r))
    sub = f"{'':>6}" + " | need MB  rt MB  I/O ms" * len(cols)
    lines = [head, sub, "-" * len(sub)]
    data = []
    for f in QIU_TABLE3["Grand Canyon"]:
        line = f"{f:>6}"
        row: dict[str, Any] = {"frame": f}
        for kind, c in cols:
            if kind == "qiu":
                need, rt, io = QIU_TABLE3[c][f]
                row[f"qiu:{c}"] = [need, rt, io]
            else:
                rows = c["_rows"]
                if f - 1 >= len(rows):
                    line += f" | {'-':^22}"
                    continue
                x = rows[f - 1]
                need, rt, io = x["needed_bytes"] / MB, x["realtime_bytes"] / MB, x["io_ms"]
                if f == 1:  # the warm-up and frame 0 load what Qiu's frame 1 loads
                    m = c["metrics"]
                    rt, io = m["first_frame_loaded_bytes"] / MB, m["first_frame_ms"]
                row[c["name"]] = [need, rt, io]
            line += f" | {need:>7.3f} {rt:>6.3f} {io:>7.2f}"
        lines.append(line)
        data.append(row)
    for label, fn in (("mean>1", np.mean), ("max>1", np.max)):
        line = f"{label:>6}"
        for kind, c in cols:
            if kind == "qiu":
                v = np.array([x for f, x in QIU_TABLE3[c].items() if f > 1])
            else:
                v = np.array(
                    [
                        [x["needed_bytes"] / MB, x["realtime_bytes"] / MB, x["io_ms"]]
                        for x in c["_rows"][1:]
                    ]
                )
            need, rt, io = fn(v, axis=0)
            line += f" | {need:>7.3f} {rt:>6.3f} {io:>7.2f}"
        lines.append(line)
    lines.append(
        "Qiu: tau = 2, frame 1 loads everything (20-31 ms of I/O); later frames load <= 0.38 MB "
        "in real time. Ours: tau = 1, decoded level bytes; frame 1 = warm-up + our frame 0, its "
        "'rt MB' = all bytes loaded and 'I/O ms' = wall ms; other frames: I/O ms = summed "
        "loader-thread time since the previous frame (latency sleeps and GIL waits included, "
        "over all loader threads); mean>1 / max>1 over frames after frame 1 (Qiu: over the 7 "
        "frames listed)."
    )
    return "\n".join(lines), data


def _code_mtimes() -> dict[str, float]:
    """Modification times of the code a run imports (to flag edits during a long run)."""
    out = {}
    for pkg in ("streamer", "tiler"):
        for f in sorted((REPO / pkg).glob("*.py")):
            out[str(f.relative_to(REPO))] = f.stat().st_mtime
    return out


def _compact_rows(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out = []
    for r in rows:
        vals = []
        for k in FRAME_COLUMNS:
            v = r[k]
            if isinstance(v, bool):
                v = int(v)
            elif isinstance(v, float):
                v = round(v, 3)
            vals.append(v)
        out.append(vals)
    return {"columns": ["frame", *FRAME_COLUMNS], "rows": [[i, *v] for i, v in enumerate(out)]}


# --------------------------------------------------------------------------- main


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=10000, help="frames of headline runs")
    p.add_argument("--short-frames", type=int, default=1200, help="frames of other runs")
    p.add_argument("--speeds", default="0.5,1,2", help="block edges per second")
    p.add_argument("--latencies", default="0,20", help="ms per store request")
    p.add_argument("--stores", default="synth,real,real-deg", help="synth, real, real-deg")
    p.add_argument("--workers", type=int, default=16, help="loader threads")
    p.add_argument("--compare-workers", default="4", help="extra short synth headline runs")
    p.add_argument("--no-http", dest="http", action="store_false", help="skip the HTTP run")
    p.add_argument("--budget-mb", type=float, default=256.0)
    p.add_argument("--tau", type=float, default=1.0)
    p.add_argument("--quick", action="store_true", help="~2 minute smoke run")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--no-plot", dest="plot", action="store_false")
    a = p.parse_args(argv)
    if a.quick:
        a.frames, a.short_frames = min(a.frames, 900), min(a.short_frames, 240)
        a.speeds, a.latencies = "1,2", "20"
        a.stores = "synth,real"
        a.compare_workers = ""
    a.speeds = _floats(a.speeds)
    a.latencies = _floats(a.latencies)
    a.stores = [s.strip() for s in a.stores.split(",") if s.strip()]
    a.compare_workers = [int(v) for v in _floats(a.compare_workers)]
    bad = set(a.stores) - {"synth", "real", "real-deg"}
    if bad:
        p.error(f"unknown store(s): {', '.join(sorted(bad))}")
    return a


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    started = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    machine = machine_info()
    mtimes = _code_mtimes()
    RESULTS.mkdir(parents=True, exist_ok=True)
    PWORK.mkdir(parents=True, exist_ok=True)
    log("preparing stores ...")
    stores: dict[str, tuple[Path, str]] = {}
    notes: dict[str, str] = {}
    if "synth" in args.stores:
        stores["synth"] = prepare_synth()
    for name, metric in (("real", True), ("real-deg", False)):
        if name in args.stores:
            got = prepare_real(metric)
            if got is None:
                notes[name] = f"skipped: {REAL_HGT} is absent"
                log(f"  {name}: {notes[name]}")
            else:
                stores[name] = got
    specs = build_matrix(args, stores)
    est = sum(s["frames"] for s in specs) / FPS
    log(f"{len(specs)} runs, ~{est / 60:.1f} min of frames (plus frame-0 waits)")
    records = []
    for i, spec in enumerate(specs, 1):
        log(f"[{i}/{len(specs)}] {spec['name']} ({spec['frames']} frames) ...")
        rec = run_one(spec, args, stores)
        m = rec["metrics"]
        log(
            f"    stalls {m['stall_frames']} ({m['stalls_in_first_second']} in the first second),"
            f" rt {m['realtime_pct_of_needed']:.4f} % of needed, loaded/used "
            f"{m['loaded_per_used']:.2f} (per load {m['loaded_per_used_load']:.2f}), "
            f"max update CPU {m['max_update_cpu_ms']:.2f} ms "
            f"(wall {m['max_update_ms']:.1f}), late frames {m['late_frames']}, "
            f"{rec['wall_s']:.0f} s"
        )
        records.append(rec)
    tab = table(records)
    qtab, qdata = qiu_table(records)
    log("")
    log(tab)
    log("")
    log("Side by side with Qiu et al., Table 3 (MB, ms):")
    log(qtab)

    frames_files = {}
    for r in records:
        rows = r.pop("_rows", None)
        if rows is None:
            continue
        fname = RESULTS / f"prefetch_frames_{r['name']}.json"
        fname.write_text(json.dumps(_compact_rows(rows), separators=(",", ":")))
        frames_files[r["name"]] = str(fname.relative_to(REPO))
        r["frames_file"] = frames_files[r["name"]]
        if args.plot and r["store"] == "synth" and r["prefetch"] and r["transport"] == "sleep":
            png = RESULTS / "prefetch_synth.png"
            plot_run(RunResult(rows=rows, summary=r["summary"]), png, title=r["name"])
            r["plot"] = str(png.relative_to(REPO))
            log(f"wrote {png.relative_to(REPO)}")
    doc = {
        "benchmark": "prefetch",
        "started_utc": started,
        "finished_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "machine": {**machine, "git_head_at_end": git_head()},
        "code_changed_during_run": [f for f, t in _code_mtimes().items() if mtimes.get(f) != t],
        "settings": {
            "fps": FPS,
            "viewport": VIEWPORT,
            "path": "streamer.run.make_path(store, 'default', speed=edge*speed)",
            "frames": args.frames,
            "short_frames": args.short_frames,
            "speeds_edges_per_s": args.speeds,
            "latencies_ms": args.latencies,
            "workers": args.workers,
            "compare_workers": args.compare_workers,
            "budget_mb": args.budget_mb,
            "tau": args.tau,
            "pacing": "run_flythrough: warm_up(cameras[0]), frame i due i/fps later",
        },
        "targets": {
            "stalls_per_10k": T_STALLS_PER_10K,
            "realtime_pct_of_needed": T_REALTIME_PCT,
            "loaded_per_used": T_LOADED_PER_USED,
            "peak_resident": "<= budget_bytes",
            "max_update_cpu_ms": T_UPDATE_MS,
            "scope": "prefetch on, 20 ms latency, speed <= 1 block edge/s",
        },
        "stores": {k: {"path": str(v[0]), "note": v[1]} for k, v in stores.items()},
        "store_notes": notes,
        "runs": records,
        "qiu_table3": {"tau": 2, "data": QIU_TABLE3, "side_by_side": qdata},
        "table": tab,
        "frames_files": frames_files,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(portable(doc), indent=1, default=str))
    log(f"wrote {args.out}")
    if doc["code_changed_during_run"]:
        log(f"NOTE: edited while this ran: {', '.join(doc['code_changed_during_run'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
