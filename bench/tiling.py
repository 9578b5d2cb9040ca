"""Tiling benchmark: terrastream store vs a rio-cogeo COG of the same DEM, same run.

Usage::

    python bench/tiling.py [--sizes 4097,16385] [--real PATH] [--block-size 1025] [--workers 2]
                           [--repeat-reads 20] [--out bench/results/tiling.json] [--quick]
    python bench/tiling.py --reads-only STORE.zarr=SOURCE.tif [--reads-only ...]
                           [--work-dir DIR] [--repeat-reads 20]   # reads of existing stores

For each input (synthetic ``size x size`` int16 DEMs from ``tiler.synth.synth_dem`` and the real
SRTM tile) it measures:

* tiling (``tiler.tile.tile``) in a separate child process: wall time, MB/s of raw source, peak
  RSS (psutil samples of the child every 20 ms; the kernel's ``ru_maxrss`` of that child from
  ``os.wait4`` and ``getrusage(RUSAGE_CHILDREN)`` as cross-checks);
* stored bytes by component (``TerrainStore.nbytes()``) vs the raw source, vs a full 2x2 raw
  pyramid of the same depth, and vs two COGs built in the same run, each in a child process
  measured the same way: ``rio_cogeo`` zstd + predictor 2 with internal overviews, and without;
* read time: ``store.read_block`` (all levels, decoded grid) vs a rasterio window read of the same
  area of the COG, and a coarse view (levels ``0..k-2``) vs the COG's overview at the same
  resolution; fresh store / dataset per repetition, opened outside the timed region. The store
  is read three ways in the same loop (``READ_VARIANTS``): direct chunk reads with the numpy
  decode (``store``, what a fresh reader process does), with the numba decode
  (``store_numba``, a process that loaded numba, e.g. a streamer session after ``warm_up``),
  and through zarr (``store_zarr``, the read path before issue 14).

``--reads-only STORE=SOURCE`` skips tiling: it builds a COG (with overviews) of SOURCE in
``--work-dir`` and times only the reads (``bench/results/tiling_reads.json``).

It prints a table and PASS/MISS for each target and writes every number to a JSON file. Sizes in
MB are MiB (2**20 bytes). Work files live in ``bench/work`` (git-ignored); synthetic sources are
kept for reuse, stores and COGs are deleted after measuring (``--keep`` keeps them).
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import json
import os
import pstats
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import REAL_HGT, REPO, RESULTS, WORK, machine_info, portable  # noqa: E402

DEFAULT_OUT = RESULTS / "tiling.json"
DEFAULT_READS_OUT = RESULTS / "tiling_reads.json"
DEFAULT_REAL = REAL_HGT
MB = float(1 << 20)
SAMPLE_S = 0.02
SEED = 0

# Targets (from the benchmark spec).
T_SIZE_VS_COG_OVR = 0.7
T_SIZE_VS_COG = 0.9
T_TIME_VS_COG_OVR = 0.5
T_RSS_MB = 600.0
T_RSS_MIN_SIZE = 16385  # the RSS target is stated for the 16385^2 int16 DEM


# --------------------------------------------------------------------------- child processes


def _child_main(task: dict[str, Any]) -> dict[str, Any]:
    """Run one measured task inside the child process; return its JSON-ready result."""
    import psutil

    warnings.simplefilter("ignore")
    kind = task["kind"]
    if kind == "tile":
        from tiler.tile import TileOptions, tile

        rss0 = psutil.Process().memory_info().rss
        opts = TileOptions(block_size=task["block_size"], workers=task["workers"], overwrite=True)
        t0 = time.perf_counter()
        tile(task["src"], task["dst"], opts)
        seconds = time.perf_counter() - t0
    elif kind == "cog":
        from rio_cogeo.cogeo import cog_translate
        from rio_cogeo.profiles import cog_profiles

        rss0 = psutil.Process().memory_info().rss
        profile = cog_profiles.get("zstd")
        profile.update(predictor=2)
        t0 = time.perf_counter()
        cog_translate(
            task["src"],
            task["dst"],
            profile,
            overview_level=task["overview_level"],
            quiet=True,
            config=task["config"],
        )
        seconds = time.perf_counter() - t0
    else:
        raise ValueError(f"unknown child task {kind!r}")
    self_maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"seconds": seconds, "rss_before_task": rss0, "self_maxrss": self_maxrss}


def run_child(task: dict[str, Any]) -> dict[str, Any]:
    """Run ``task`` in a fresh Python process; sample its RSS every 20 ms until it exits."""
    import psutil

    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(task)]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        wall0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, text=True, cwd=str(REPO))
        ps = psutil.Process(proc.pid)
        peak, samples = 0, 0
        while True:
            with contextlib.suppress(psutil.Error):
                # the task's own RSS plus its worker processes' (the tiler may spawn some)
                rss = ps.memory_info().rss
                for child in ps.children(recursive=True):
                    with contextlib.suppress(psutil.Error):
                        rss += child.memory_info().rss
                peak = max(peak, rss)
                samples += 1
            pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            time.sleep(SAMPLE_S)
        wall = time.perf_counter() - wall0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if proc.returncode != 0:
        raise RuntimeError(
            f"child task {task['kind']} failed (exit {proc.returncode}):\n{stderr[-4000:]}"
        )
    result = json.loads(stdout.strip().splitlines()[-1])
    result.update(
        peak_rss_sampled=peak,
        rss_samples=samples,
        wait4_maxrss=ru.ru_maxrss * 1024,
        rusage_children_maxrss=resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024,
        process_wall_s=wall,
    )
    return result


# --------------------------------------------------------------------------- inputs


def _synth_fallback(path: Path, size: int, seed: int) -> None:
    """Write the DEM from ``tiler.synth.synth_array`` strip by strip (if synth_dem is missing)."""
    import rasterio
    from rasterio.transform import from_origin
    from rasterio.windows import Window

    from tiler.synth import synth_array

    profile = {
        "driver": "GTiff",
        "width": size,
        "height": size,
        "count": 1,
        "dtype": "int16",
        "crs": "EPSG:32633",
        "transform": from_origin(500000.0, 5000000.0, 30.0, 30.0),
        "tiled": True,
        "blockxsize": 512,
        "blockysize": 512,
    }
    with rasterio.open(path, "w", **profile) as dst:
        for r0 in range(0, size, 512):
            n = min(512, size - r0)
            data = synth_array(slice(r0, r0 + n), slice(0, size), size, seed=seed, dtype="int16")
            dst.write(data, 1, window=Window(0, r0, size, n))


def synth_source(size: int, seed: int) -> tuple[Path, float | None, str]:
    """The ``size``^2 int16 synthetic DEM in bench/work, made once.

    Returns ``(path, seconds to make it or None if reused, writer)``. The writer is
    ``tiler.synth.synth_dem``; while that is not available, the same samples are written from
    ``synth_array`` (recorded as such, and remade by ``synth_dem`` once it exists).
    """
    import rasterio

    try:
        from tiler.synth import synth_dem
    except ImportError:
        synth_dem = None
    writer = "synth_dem" if synth_dem else "synth_array-fallback"
    path = WORK / f"synth_{size}_seed{seed}_int16.tif"
    stamp = path.with_suffix(".json")
    want = {"size": size, "seed": seed, "dtype": "int16"}
    if path.exists() and stamp.exists():
        with contextlib.suppress(ValueError, OSError, KeyError):
            have = json.loads(stamp.read_text())
            ok = {k: have[k] for k in want} == want and (
                have.get("writer") == writer or synth_dem is None
            )
            with rasterio.open(path) as ds:
                ok = ok and ds.shape == (size, size) and ds.dtypes[0] == "int16"
            if ok:
                return path, None, have.get("writer", "synth_dem")
    for p in (path, stamp):
        p.unlink(missing_ok=True)
    tmp = path.with_name(path.stem + ".partial.tif")
    tmp.unlink(missing_ok=True)
    t0 = time.perf_counter()
    if synth_dem is not None:
        synth_dem(tmp, size, seed, "int16")
    else:
        print("  NOTE: tiler.synth.synth_dem is not available; writing synth_array samples")
        _synth_fallback(tmp, size, seed)
    seconds = time.perf_counter() - t0
    tmp.rename(path)
    stamp.write_text(json.dumps({**want, "writer": writer}))
    return path, seconds, writer


def pyramid_bytes(height: int, width: int, k: int, itemsize: int) -> int:
    """Raw bytes of a full 2x2 pyramid of the same depth as the store (levels k .. 0).

    Level ``j`` below full resolution keeps every ``2**j``-th sample including both edges, i.e. a
    ``((H-1)//2**j + 1) x ((W-1)//2**j + 1)`` grid, down to ``j = k`` (the block corners).
    """
    return itemsize * sum(
        (((height - 1) >> j) + 1) * (((width - 1) >> j) + 1) for j in range(k + 1)
    )


def spread_blocks(blocks: list[tuple[int, int]], n: int = 8) -> list[tuple[int, int]]:
    """Up to ``n`` blocks spread evenly over the row-major list."""
    if len(blocks) <= n:
        return list(blocks)
    idx = sorted({round(i * (len(blocks) - 1) / (n - 1)) for i in range(n)})
    return [blocks[i] for i in idx]


# --------------------------------------------------------------------------- read timing


def _median_ms(values: list[float]) -> float:
    return statistics.median(values) * 1e3


#: How the store is read, each timed in the same loop (A/B in one run): ``direct_reads`` and
#: the decode backend (``TERRASTREAM_KERNELS``). "store" is what a fresh reader process does
#: (direct reads; numpy decode, since the read path loads numba only if the process already
#: has it); "store_zarr" is the read path before issue 14 (one zarr call per level).
READ_VARIANTS: dict[str, dict[str, Any]] = {
    "store": {"direct_reads": True, "kernels": "numpy"},
    "store_numba": {"direct_reads": True, "kernels": "numba"},
    "store_zarr": {"direct_reads": False, "kernels": "numpy"},
}


@contextlib.contextmanager
def _kernels_env(name: str):
    from tiler.kernels import ENV

    old = os.environ.get(ENV)
    os.environ[ENV] = name
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = old


def _variants() -> dict[str, dict[str, Any]]:
    """READ_VARIANTS, without the numba one where numba is not installed."""
    from tiler import kernels

    out = dict(READ_VARIANTS)
    with _kernels_env("auto"):
        if not kernels.warm_up("int16"):
            out.pop("store_numba")
    return out


def time_reads(store_path: Path, cog_path: Path, repeat: int) -> dict[str, Any]:
    """Median ms of full-block and coarse reads: store vs COG window / COG overview."""
    import numpy as np
    import rasterio
    from rasterio.windows import Window

    from tiler.store import TerrainStore

    variants = _variants()
    store = TerrainStore(store_path)
    k = store.k
    coarse = k - 2
    factor = 1 << (k - coarse)
    blocks = spread_blocks(list(store.blocks()))
    with rasterio.open(cog_path) as ds:
        overviews = ds.overviews(1)
        ovr_shape = None
    ovr_level = overviews.index(factor) if factor in overviews else None
    if ovr_level is not None:
        with rasterio.open(cog_path, overview_level=ovr_level) as ds:
            ovr_shape = ds.shape
    per_block = []
    keys = [*variants, "cog", *(f"{v}_coarse" for v in variants), "cog_ovr", "store_warm"]
    all_s: dict[str, list[float]] = {key: [] for key in keys}
    mismatches = []

    def timed(v: str, b: tuple[int, int], level: int | None) -> float:
        s = TerrainStore(store_path, direct_reads=variants[v]["direct_reads"])
        with _kernels_env(variants[v]["kernels"]):
            t0 = time.perf_counter()
            s.read_block(b, level)
            return time.perf_counter() - t0

    for b in blocks:
        r0, c0, h, w = store.grid.block_window(*b)
        win = Window(c0, r0, w, h)
        # Correctness (untimed): both formats are lossless, the samples must be identical.
        with rasterio.open(cog_path) as ds:
            ref = ds.read(1, window=win)
        for v, cfg in variants.items():
            with _kernels_env(cfg["kernels"]):
                got = TerrainStore(store_path, direct_reads=cfg["direct_reads"]).read_block(b)
            if not np.array_equal(got[:h, :w], ref):
                n_diff = int((got[:h, :w] != ref).sum())
                mismatches.append({"block": list(b), "variant": v, "n_diff": n_diff})
        if ovr_level is not None:
            orow, ocol = r0 // factor, c0 // factor
            ow = min((w - 1) // factor + 1, ovr_shape[1] - ocol)
            oh = min((h - 1) // factor + 1, ovr_shape[0] - orow)
            owin = Window(ocol, orow, ow, oh)
        times: dict[str, list[float]] = {key: [] for key in all_s}
        for _ in range(repeat):
            for v in variants:
                times[v].append(timed(v, b, None))
            with rasterio.open(cog_path) as ds:
                t0 = time.perf_counter()
                ds.read(1, window=win)
                times["cog"].append(time.perf_counter() - t0)
            for v in variants:
                times[f"{v}_coarse"].append(timed(v, b, coarse))
            if ovr_level is not None:
                with rasterio.open(cog_path, overview_level=ovr_level) as ds:
                    t0 = time.perf_counter()
                    ds.read(1, window=owin)
                    times["cog_ovr"].append(time.perf_counter() - t0)
        # Informational: the same store object re-reading (zarr arrays already opened; zarr
        # keeps no chunk cache, so this still reads and decodes every chunk).
        s = TerrainStore(store_path)
        with _kernels_env(variants["store"]["kernels"]):
            s.read_block(b)
            for _ in range(repeat):
                t0 = time.perf_counter()
                s.read_block(b)
                times["store_warm"].append(time.perf_counter() - t0)
        row = {"block": list(b), "window": [r0, c0, h, w]}
        for key, vals in times.items():
            all_s[key].extend(vals)
            row[f"{key}_ms"] = _median_ms(vals) if vals else None
        per_block.append(row)
    out = {
        "blocks": [list(b) for b in blocks],
        "repeat": repeat,
        "variants": variants,
        "coarse_level": coarse,
        "coarse_decimation": factor,
        "cog_overview_factors": overviews,
        "cog_overview_level_used": ovr_level,
        "store_block_ms": _median_ms(all_s["store"]),
        "cog_window_ms": _median_ms(all_s["cog"]),
        "store_coarse_ms": _median_ms(all_s["store_coarse"]),
        "cog_overview_ms": _median_ms(all_s["cog_ovr"]) if all_s["cog_ovr"] else None,
        "store_block_warm_ms": _median_ms(all_s["store_warm"]),
        "per_block": per_block,
        "lossless_mismatches": mismatches,
    }
    for v in variants:
        if v != "store":
            out[f"{v}_block_ms"] = _median_ms(all_s[v])
            out[f"{v}_coarse_ms"] = _median_ms(all_s[f"{v}_coarse"])
    return out


def profile_block(src: Path, block_size: int, top: int = 15) -> dict[str, Any]:
    """cProfile of ``process_block`` on block (0, 0) of ``src``, plus per-step wall times."""
    import rasterio

    from tiler import static_error
    from tiler.grid import BlockGrid
    from tiler.layout import parse_block_size
    from tiler.tile import BlockParams, process_block, read_window

    k = parse_block_size(block_size)
    with rasterio.open(src) as ds:
        grid = BlockGrid(height=ds.height, width=ds.width, k=k)
        t0 = time.perf_counter()
        window = read_window(ds, 1, grid, 0, 0)
        read_s = time.perf_counter() - t0
        nodata = ds.nodata
        dtype = ds.dtypes[0]
    params = BlockParams(
        k=k,
        dtype=dtype,
        storage_dtype=dtype,
        nodata=nodata,
        precision=None,
        error_cap=static_error.default_cap(k),
    )
    process_block(window, params)  # warm caches (lru_cache'd layouts)
    walls = []
    for _ in range(3):
        t0 = time.perf_counter()
        process_block(window, params)
        walls.append(time.perf_counter() - t0)
    prof = cProfile.Profile()
    prof.enable()
    process_block(window, params)
    prof.disable()
    stats = pstats.Stats(prof)
    rows = []
    for (fname, line, func), (_cc, nc, tt, ct, _callers) in stats.stats.items():
        where = f"{Path(fname).name}:{line}({func})" if line else func
        rows.append({"function": where, "ncalls": nc, "tottime_s": tt, "cumtime_s": ct})
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(top)
    return {
        "source": str(src),
        "block": [0, 0],
        "read_window_s": read_s,
        "process_block_s": min(walls),
        "top_tottime": sorted(rows, key=lambda r: -r["tottime_s"])[:top],
        "top_cumtime": sorted(rows, key=lambda r: -r["cumtime_s"])[:top],
        "text": buf.getvalue(),
    }


# --------------------------------------------------------------------------- one input


def _rss_mb(res: dict[str, Any]) -> dict[str, float]:
    return {
        "peak_rss_mb": res["peak_rss_sampled"] / MB,
        "wait4_maxrss_mb": res["wait4_maxrss"] / MB,
        "self_maxrss_mb": res["self_maxrss"] / MB,
        "rusage_children_maxrss_mb": res["rusage_children_maxrss"] / MB,
        "rss_before_task_mb": res["rss_before_task"] / MB,
    }


def _dir_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def bench_input(name: str, src: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Tile ``src``, build both COGs, compare sizes, times, RSS and reads."""
    import numpy as np
    import rasterio

    from tiler.layout import parse_block_size
    from tiler.store import TerrainStore

    k = parse_block_size(args.block_size)
    with rasterio.open(src) as ds:
        height, width, dtype = ds.height, ds.width, ds.dtypes[0]
    itemsize = np.dtype(dtype).itemsize
    raw = height * width * itemsize
    store_path = WORK / f"{name}.zarr"
    cog_ovr = WORK / f"{name}.cog_ovr.tif"
    cog_plain = WORK / f"{name}.cog_noovr.tif"
    for p in (store_path, cog_ovr, cog_plain):
        _remove(p)

    print(f"[{name}] tiling {height}x{width} {dtype} ...", flush=True)
    tile_res = run_child(
        {
            "kind": "tile",
            "src": str(src),
            "dst": str(store_path),
            "block_size": args.block_size,
            "workers": args.workers,
        }
    )
    store = TerrainStore(store_path)
    nbytes = store.nbytes()
    level_nbytes = store.level_nbytes()
    tables = sum(_dir_bytes(store_path / t) for t in ("level_index", "order_index"))
    n_blocks = store.grid.rows * store.grid.cols
    print(f"[{name}] tiled in {tile_res['seconds']:.1f} s; building COGs ...", flush=True)

    config = {"GDAL_NUM_THREADS": str(args.workers)}
    cog = {}
    for key, path, level in (("with_overviews", cog_ovr, None), ("no_overviews", cog_plain, 0)):
        res = run_child(
            {
                "kind": "cog",
                "src": str(src),
                "dst": str(path),
                "overview_level": level,
                "config": config,
            }
        )
        cog[key] = {"seconds": res["seconds"], "bytes": path.stat().st_size, **_rss_mb(res)}
        cog[key]["process_wall_s"] = res["process_wall_s"]
    secs = cog["with_overviews"]["seconds"]
    print(f"[{name}] COG+ovr built in {secs:.1f} s; timing reads ...", flush=True)

    reads = time_reads(store_path, cog_ovr, args.repeat_reads)
    if not args.keep:
        for p in (store_path, cog_ovr, cog_plain):
            _remove(p)

    total = nbytes["total"]
    pyr = pyramid_bytes(height, width, k, itemsize)
    return {
        "name": name,
        "source": str(src),
        "height": height,
        "width": width,
        "dtype": dtype,
        "k": k,
        "blocks": n_blocks,
        "raw_bytes": raw,
        "pyramid_raw_bytes": pyr,
        "store_raw_bytes": n_blocks * (2**k + 1) ** 2 * itemsize,
        "tile": {
            "seconds": tile_res["seconds"],
            "process_wall_s": tile_res["process_wall_s"],
            "mb_per_s": raw / MB / tile_res["seconds"],
            "workers": args.workers,
            "rss_samples": tile_res["rss_samples"],
            **_rss_mb(tile_res),
        },
        "store_bytes": nbytes,
        "store_level_bytes": level_nbytes,
        "store_layout_table_bytes": tables,
        "cog": cog,
        "cog_settings": {
            "profile": "rio_cogeo zstd (GDAL ZSTD_LEVEL default 9), predictor=2, 512x512 tiles",
            "overview_resampling": "nearest",
            "config": config,
        },
        "ratios": {
            "store_vs_raw": total / raw,
            "store_vs_pyramid_raw": total / pyr,
            "store_vs_cog_ovr": total / cog["with_overviews"]["bytes"],
            "store_vs_cog_no_ovr": total / cog["no_overviews"]["bytes"],
            "cog_ovr_vs_raw": cog["with_overviews"]["bytes"] / raw,
            "store_excl_layout_tables_vs_cog_ovr": (total - tables)
            / cog["with_overviews"]["bytes"],
            "store_excl_layout_tables_vs_cog_no_ovr": (total - tables)
            / cog["no_overviews"]["bytes"],
            "tile_time_vs_cog_ovr_time": tile_res["seconds"] / cog["with_overviews"]["seconds"],
        },
        "reads": reads,
    }


# --------------------------------------------------------------------------- report


#: read variants that are references, not candidates for the targets (the code before)
REFERENCE_VARIANTS = ("store_zarr",)


def read_targets(reads: dict[str, Any]) -> list[dict[str, Any]]:
    """The two read targets, for each read variant but the references (``store`` first)."""
    out = []
    for v in reads.get("variants") or {"store": {}}:
        if v in REFERENCE_VARIANTS:
            continue
        blk = reads["store_block_ms" if v == "store" else f"{v}_block_ms"]
        crs = reads["store_coarse_ms" if v == "store" else f"{v}_coarse_ms"]
        tag = "" if v == "store" else f" [{v}]"
        out.append(
            {
                "target": f"block read (all levels) <= COG window read of the same area{tag}",
                "value": blk / reads["cog_window_ms"],
                "limit": 1.0,
                "detail": f"{blk:.2f} ms vs {reads['cog_window_ms']:.2f} ms",
            }
        )
        if reads["cog_overview_ms"]:
            out.append(
                {
                    "target": f"coarse read (levels <= k-2) <= COG overview read{tag}",
                    "value": crs / reads["cog_overview_ms"],
                    "limit": 1.0,
                    "detail": f"{crs:.2f} ms vs {reads['cog_overview_ms']:.2f} ms",
                }
            )
    for t in out:
        t["pass"] = bool(t["value"] <= t["limit"])
    return out


def check_targets(r: dict[str, Any]) -> list[dict[str, Any]]:
    """PASS/MISS of each target for one input."""
    ratios, reads, tile_ = r["ratios"], r["reads"], r["tile"]
    out = [
        {
            "target": f"stored size <= {T_SIZE_VS_COG_OVR} x COG with overviews",
            "value": ratios["store_vs_cog_ovr"],
            "limit": T_SIZE_VS_COG_OVR,
            "detail": f"{r['store_bytes']['total'] / MB:.2f} MB vs "
            f"{r['cog']['with_overviews']['bytes'] / MB:.2f} MB",
        },
        {
            "target": f"stored size <= {T_SIZE_VS_COG} x COG without overviews",
            "value": ratios["store_vs_cog_no_ovr"],
            "limit": T_SIZE_VS_COG,
            "detail": f"{r['store_bytes']['total'] / MB:.2f} MB vs "
            f"{r['cog']['no_overviews']['bytes'] / MB:.2f} MB",
        },
        {
            "target": f"tiling time <= {T_TIME_VS_COG_OVR} x COG-with-overviews build time",
            "value": ratios["tile_time_vs_cog_ovr_time"],
            "limit": T_TIME_VS_COG_OVR,
            "detail": f"{tile_['seconds']:.2f} s vs {r['cog']['with_overviews']['seconds']:.2f} s",
        },
        *read_targets(reads),
    ]
    if r["dtype"] == "int16" and max(r["height"], r["width"]) >= T_RSS_MIN_SIZE:
        peak = max(tile_["peak_rss_mb"], tile_["wait4_maxrss_mb"])
        out.append(
            {
                "target": f"peak RSS tiling {r['height']}^2 int16 <= {T_RSS_MB:.0f} MB",
                "value": peak,
                "limit": T_RSS_MB,
                "detail": f"{peak:.0f} MB (sampled {tile_['peak_rss_mb']:.0f}, "
                f"kernel maxrss {tile_['wait4_maxrss_mb']:.0f})",
            }
        )
    for t in out:
        t["pass"] = bool(t["value"] <= t["limit"])
    if reads["lossless_mismatches"]:
        out.append(
            {
                "target": "store read_block == COG window (both lossless)",
                "value": len(reads["lossless_mismatches"]),
                "limit": 0,
                "detail": json.dumps(reads["lossless_mismatches"]),
                "pass": False,
            }
        )
    return out


def print_report(results: list[dict[str, Any]]) -> None:
    cols = [
        ("input", 18, "s"),
        ("tile s", 8, ".2f"),
        ("MB/s", 7, ".1f"),
        ("RSS MB", 7, ".0f"),
        ("store MB", 9, ".2f"),
        ("/COG+ovr", 8, ".3f"),
        ("/COG", 6, ".3f"),
        ("/pyramid", 8, ".3f"),
        ("/raw", 6, ".3f"),
        ("t/COG t", 7, ".3f"),
        ("block ms", 8, ".2f"),
        ("COG win ms", 10, ".2f"),
    ]
    head = " ".join(f"{c:>{w}}" if i else f"{c:<{w}}" for i, (c, w, _) in enumerate(cols))
    print()
    print(head)
    print("-" * len(head))
    for r in results:
        vals = [
            r["name"],
            r["tile"]["seconds"],
            r["tile"]["mb_per_s"],
            r["tile"]["peak_rss_mb"],
            r["store_bytes"]["total"] / MB,
            r["ratios"]["store_vs_cog_ovr"],
            r["ratios"]["store_vs_cog_no_ovr"],
            r["ratios"]["store_vs_pyramid_raw"],
            r["ratios"]["store_vs_raw"],
            r["ratios"]["tile_time_vs_cog_ovr_time"],
            r["reads"]["store_block_ms"],
            r["reads"]["cog_window_ms"],
        ]
        print(
            " ".join(
                f"{v:<{w}{f}}" if i == 0 else f"{v:>{w}{f}}"
                for i, (v, (_, w, f)) in enumerate(zip(vals, cols, strict=True))
            )
        )
    print()
    print(
        f"{'input':<18} {'COG+ovr s':>9} {'COG s':>7} {'COG+ovr MB':>10} {'COG MB':>8} "
        f"{'COG RSS MB':>10} {'coarse ms':>9} {'COG ovr ms':>10} {'warm blk ms':>11}"
    )
    for r in results:
        c, rd = r["cog"], r["reads"]
        ovr = rd["cog_overview_ms"]
        print(
            f"{r['name']:<18} {c['with_overviews']['seconds']:>9.2f} "
            f"{c['no_overviews']['seconds']:>7.2f} {c['with_overviews']['bytes'] / MB:>10.2f} "
            f"{c['no_overviews']['bytes'] / MB:>8.2f} {c['with_overviews']['peak_rss_mb']:>10.0f} "
            f"{rd['store_coarse_ms']:>9.2f} {'n/a' if ovr is None else f'{ovr:.2f}':>10} "
            f"{rd['store_block_warm_ms']:>11.2f}"
        )
    print(
        "  coarse = store levels 0..k-2 vs the COG overview at the same resolution (1/4); "
        "warm blk = read_block on an already-used store object"
    )
    print()
    print("store bytes by component (MB):")
    for r in results:
        b = r["store_bytes"]
        parts = ", ".join(f"{n} {b[n] / MB:.3f}" for n in ("levels", "errors", "mask", "index"))
        print(
            f"  {r['name']:<18} {parts} (of which level/order_index tables "
            f"{r['store_layout_table_bytes'] / MB:.3f}), metadata {b['metadata'] / 1024:.1f} KiB"
        )
    print()
    print("targets:")
    for r in results:
        for t in r["targets"]:
            mark = "PASS" if t["pass"] else "MISS"
            print(f"  {mark}  {r['name']:<18} {t['target']}: {t['value']:.3f} ({t['detail']})")


def tiler_sources_digest() -> str:
    """Digest of tiler/*.py, to tell whether the code under test changed during the run."""
    import hashlib

    h = hashlib.blake2b(digest_size=8)
    for f in sorted((REPO / "tiler").glob("*.py")):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


# --------------------------------------------------------------------------- reads only


def bench_reads_only(pair: str, args: argparse.Namespace) -> dict[str, Any]:
    """Time reads of an existing store (``STORE=SOURCE``) against a COG of SOURCE built now."""
    from tiler.store import TerrainStore

    store_s, sep, src_s = pair.partition("=")
    store_path, src = Path(store_s), Path(src_s)
    if not sep or not store_path.is_dir() or not src.is_file():
        raise SystemExit(
            f"--reads-only {pair!r}: expected STORE.zarr=SOURCE.tif naming an existing store "
            "and its source DEM"
        )
    name = store_path.stem
    work = Path(args.work_dir)
    work.mkdir(parents=True, exist_ok=True)
    cog = work / f"{name}.reads_cog_ovr.tif"
    print(f"[{name}] building the COG (with overviews) of {src} ...", flush=True)
    res = run_child(
        {
            "kind": "cog",
            "src": str(src),
            "dst": str(cog),
            "overview_level": None,
            "config": {"GDAL_NUM_THREADS": str(args.workers)},
        }
    )
    store = TerrainStore(store_path)
    print(f"[{name}] timing reads ({args.repeat_reads} repetitions) ...", flush=True)
    load0 = os.getloadavg()
    reads = time_reads(store_path, cog, args.repeat_reads)
    load1 = os.getloadavg()
    if not args.keep:
        _remove(cog)
    return {
        "name": name,
        "store": _shown(store_path),
        "source": _shown(src),
        "height": store.meta.height,
        "width": store.meta.width,
        "dtype": store.meta.dtype,
        "k": store.k,
        "cog_seconds": res["seconds"],
        "load_average": {"start": list(load0), "end": list(load1)},
        "reads": reads,
        "targets": read_targets(reads),
    }


def print_reads_report(results: list[dict[str, Any]]) -> None:
    """The reads-only table: ms per variant and COG, ratios."""
    variants = list(results[0]["reads"]["variants"]) if results else []
    print()
    print(f"{'input':<14} {'read':<7} " + " ".join(f"{v:>12}" for v in variants) + f" {'COG':>8}")
    for r in results:
        rd = r["reads"]
        for kind, cog_key in (("block", "cog_window_ms"), ("coarse", "cog_overview_ms")):
            ms = [rd[f"store_{kind}_ms" if v == "store" else f"{v}_{kind}_ms"] for v in variants]
            cog = rd[cog_key]
            print(
                f"{r['name']:<14} {kind:<7} "
                + " ".join(f"{m:>12.2f}" for m in ms)
                + (f" {cog:>8.2f}" if cog else f" {'n/a':>8}")
            )
            if cog:
                print(f"{'':<14} {'ratio':<7} " + " ".join(f"{m / cog:>12.2f}" for m in ms))
    print("  ms are medians; ratio = store / COG (window read for block, overview for coarse)")
    print()
    print("targets:")
    for r in results:
        for t in r["targets"]:
            mark = "PASS" if t["pass"] else "MISS"
            print(f"  {mark}  {r['name']:<14} {t['target']}: {t['value']:.3f} ({t['detail']})")


def main_reads_only(args: argparse.Namespace) -> int:
    """``--reads-only``: no tiling, only the read timings of existing stores."""
    warnings.simplefilter("ignore")
    t_start = time.perf_counter()
    load_start = os.getloadavg()
    uptime_start = _uptime()
    results = [bench_reads_only(pair, args) for pair in args.reads_only]
    print_reads_report(results)
    load_end = os.getloadavg()
    notes = []
    if max(load_start[0], load_end[0]) > 0.5 * (os.cpu_count() or 1) + 0.5:
        notes.append(
            f"machine busy: 1-min load average {load_start[0]:.1f} at start, "
            f"{load_end[0]:.1f} at end ({os.cpu_count()} CPUs); timings may be inflated"
        )
    for note in notes:
        print(f"NOTE: {note}")
    out = Path(args.out if args.out != str(DEFAULT_OUT) else DEFAULT_READS_OUT)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "benchmark": "tiling --reads-only",
        "args": {
            **{k: v for k, v in vars(args).items() if k not in ("child", "reads_only", "work_dir")},
            "reads_only": [
                "=".join(_shown(Path(p)) for p in pair.split("=", 1)) for pair in args.reads_only
            ],
            "work_dir": _shown(Path(args.work_dir)),
            "out": str(out),
        },
        "machine": machine_info(),
        "notes": notes,
        "tiler_sources_digest": tiler_sources_digest(),
        "load_average": {"start": list(load_start), "end": list(load_end)},
        "uptime": {"start": uptime_start, "end": _uptime()},
        "units": {"ms": "median milliseconds"},
        "inputs": results,
        "all_targets_pass": all(t["pass"] for r in results for t in r["targets"]),
        "run_seconds": time.perf_counter() - t_start,
    }
    out.write_text(json.dumps(portable(doc), indent=2, allow_nan=False) + "\n")
    print(f"\nwrote {out} (run took {doc['run_seconds']:.0f} s)")
    return 0


def _shown(path: Path) -> str:
    """A path for the JSON: relative ones and those under the checkout or the shared data as
    they are (``portable`` rewrites the latter), any other folder as ``<elsewhere>/NAME``."""
    from bench.common import SHARED_DATA

    if not path.is_absolute():
        return str(path)
    for root in (REPO, SHARED_DATA):
        with contextlib.suppress(ValueError):
            path.relative_to(root)
            return str(path)
    return f"<elsewhere>/{path.name}"


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


# --------------------------------------------------------------------------- main


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", default="4097,16385", help="synthetic DEM sizes (comma-separated)")
    p.add_argument("--real", default=str(DEFAULT_REAL), help="real DEM ('' to skip)")
    p.add_argument("--block-size", type=int, default=1025)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--repeat-reads", type=int, default=20)
    p.add_argument("--seed", type=int, default=SEED)
    p.add_argument("--out", default=str(DEFAULT_OUT))
    p.add_argument("--quick", action="store_true", help="2049^2 synthetic only (smoke run)")
    p.add_argument("--keep", action="store_true", help="keep stores and COGs in bench/work")
    p.add_argument("--no-profile", action="store_true", help="skip the process_block cProfile")
    p.add_argument(
        "--reads-only",
        action="append",
        metavar="STORE=SOURCE",
        help="skip tiling: time reads of an existing store against a COG of its source built "
        "now (repeatable); writes bench/results/tiling_reads.json unless --out is given",
    )
    p.add_argument(
        "--work-dir",
        default=str(WORK),
        help="where --reads-only builds its COGs (default bench/work)",
    )
    p.add_argument("--child", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.child:
        print(json.dumps(_child_main(json.loads(args.child))), flush=True)
        return 0
    if args.reads_only:
        return main_reads_only(args)
    warnings.simplefilter("ignore")
    WORK.mkdir(parents=True, exist_ok=True)
    sizes = [2049] if args.quick else [int(s) for s in args.sizes.split(",") if s.strip()]
    real = None if args.quick or not args.real else Path(args.real)
    t_start = time.perf_counter()
    digest_start = tiler_sources_digest()
    load_start = os.getloadavg()
    inputs: list[tuple[str, Path]] = []
    notes: list[str] = []
    synth_s: dict[str, float | None] = {}
    writers: dict[str, str] = {}
    for size in sizes:
        print(f"synthetic {size}^2 int16 (seed {args.seed}) ...", flush=True)
        path, secs, writer = synth_source(size, args.seed)
        name = f"synth{size}"
        synth_s[name] = secs
        writers[name] = writer
        if writer != "synth_dem":
            notes.append(f"{name}: tiler.synth.synth_dem missing; written from synth_array")
        print(f"  {path} ({'reused' if secs is None else f'made in {secs:.1f} s'})", flush=True)
        inputs.append((name, path))
    if real is not None:
        if real.exists():
            inputs.append((real.stem, real))
        else:
            note = f"real DEM {real} not found; skipped"
            print(f"NOTE: {note}", flush=True)
            notes.append(note)

    results = []
    for name, src in inputs:
        r = bench_input(name, src, args)
        r["synth_seconds"] = synth_s.get(name)
        r["synth_writer"] = writers.get(name)
        r["targets"] = check_targets(r)
        results.append(r)

    profile = None
    if not args.no_profile and inputs:
        profile = profile_block(inputs[0][1], args.block_size)

    print_report(results)
    if profile:
        print()
        print(
            f"process_block on block (0,0) of {inputs[0][0]}: {profile['process_block_s']:.3f} s "
            f"(window read {profile['read_window_s'] * 1e3:.1f} ms); top by own time:"
        )
        for row in profile["top_tottime"][:8]:
            print(f"  {row['tottime_s']:7.3f} s  {row['ncalls']:5d}x  {row['function']}")
        for r in results:
            est = r["blocks"] * profile["process_block_s"] / r["tile"]["workers"]
            r["tile"]["compute_estimate_s"] = est
            print(
                f"  {r['name']}: {r['blocks']} blocks x {profile['process_block_s']:.3f} s / "
                f"{r['tile']['workers']} workers = {est:.1f} s of {r['tile']['seconds']:.1f} s "
                "tiling wall time"
            )

    digest_end = tiler_sources_digest()
    load_end = os.getloadavg()
    if max(load_start[0], load_end[0]) > 0.5 * (os.cpu_count() or 1) + 0.5:
        notes.append(
            f"machine busy: 1-min load average {load_start[0]:.1f} at start, "
            f"{load_end[0]:.1f} at end ({os.cpu_count()} CPUs); timings may be inflated"
        )
    if digest_end != digest_start:
        notes.append("tiler/*.py changed during the run: inputs may have used different code")
    for note in notes:
        print(f"NOTE: {note}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "benchmark": "tiling",
        "args": {k: v for k, v in vars(args).items() if k != "child"},
        "machine": machine_info(),
        "notes": notes,
        "tiler_sources_digest": {"start": digest_start, "end": digest_end},
        "load_average": {"start": list(load_start), "end": list(load_end)},
        "units": {"MB": "2**20 bytes", "ms": "median milliseconds"},
        "inputs": results,
        "process_block_profile": profile,
        "all_targets_pass": all(t["pass"] for r in results for t in r["targets"]),
        "run_seconds": time.perf_counter() - t_start,
    }
    out.write_text(json.dumps(portable(doc), indent=2, allow_nan=False) + "\n")
    print(f"\nwrote {out} (run took {doc['run_seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
