"""The tiling benchmark's read timings, and its ``--reads-only`` mode (no tiling).

:func:`time_reads` times ``store.read_block`` (all levels, and the coarse view ``0..k-2``) against
a rasterio window read of the same area of the COG and its overview at the same resolution, for
each way of reading the store (``READ_VARIANTS``); :func:`read_targets` turns that into PASS/MISS.
``python bench/tiling.py --reads-only STORE=SOURCE`` (:func:`main_reads_only`) builds a COG of
SOURCE and times only the reads (``bench/results/tiling_reads.json``). See bench/tiling.py.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import statistics
import subprocess
import time
import warnings
from pathlib import Path
from typing import Any

from bench.common import REPO, RESULTS, machine_info, portable
from bench.tiling_child import run_child

DEFAULT_OUT = RESULTS / "tiling.json"
DEFAULT_READS_OUT = RESULTS / "tiling_reads.json"


def spread_blocks(blocks: list[tuple[int, int]], n: int = 8) -> list[tuple[int, int]]:
    """Up to ``n`` blocks spread evenly over the row-major list."""
    if len(blocks) <= n:
        return list(blocks)
    idx = sorted({round(i * (len(blocks) - 1) / (n - 1)) for i in range(n)})
    return [blocks[i] for i in idx]


def _median_ms(values: list[float]) -> float:
    return statistics.median(values) * 1e3


#: How the store is read, each timed in the same loop (A/B in one run): ``direct_reads``, the
#: decode backend (``TERRASTREAM_KERNELS``) and ``extent``: True reads the block's samples inside
#: the DEM (``read_block(..., extent=store.block_extent(...))``, what the xarray backend, export
#: and ``accuracy`` read; the same area as the COG window), False the whole ``2**L+1`` grid,
#: padding included (the read before the windowed decode). "store" is what a fresh reader process
#: does (direct reads; numpy decode, since the read path loads numba only if the process already
#: has it); "store_zarr" is the read path before issue 14 (one zarr call per level).
READ_VARIANTS: dict[str, dict[str, Any]] = {
    "store": {"direct_reads": True, "kernels": "numpy", "extent": True},
    "store_numba": {"direct_reads": True, "kernels": "numba", "extent": True},
    "store_grid": {"direct_reads": True, "kernels": "numpy", "extent": False},
    "store_numba_grid": {"direct_reads": True, "kernels": "numba", "extent": False},
    "store_zarr": {"direct_reads": False, "kernels": "numpy", "extent": False},
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
            out = {v: cfg for v, cfg in out.items() if cfg["kernels"] != "numba"}
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
        ext = store.block_extent(b, level) if variants[v]["extent"] else None
        with _kernels_env(variants[v]["kernels"]):
            t0 = time.perf_counter()
            s.read_block(b, level, extent=ext)
            return time.perf_counter() - t0

    for b in blocks:
        r0, c0, h, w = store.grid.block_window(*b)
        win = Window(c0, r0, w, h)
        # Correctness (untimed): both formats are lossless, the samples must be identical.
        with rasterio.open(cog_path) as ds:
            ref = ds.read(1, window=win)
        for v, cfg in variants.items():
            ext = store.block_extent(b) if cfg["extent"] else None
            with _kernels_env(cfg["kernels"]):
                got = TerrainStore(store_path, direct_reads=cfg["direct_reads"])
                got = got.read_block(b, extent=ext)
            if got.shape != ((h, w) if ext else (store.grid.side,) * 2):
                mismatches.append({"block": list(b), "variant": v, "shape": list(got.shape)})
            elif not np.array_equal(got[:h, :w], ref):
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
        ext = store.block_extent(b)
        with _kernels_env(variants["store"]["kernels"]):
            s.read_block(b, extent=ext)
            for _ in range(repeat):
                t0 = time.perf_counter()
                s.read_block(b, extent=ext)
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


#: read variants that are references, not candidates for the targets (the code before)
REFERENCE_VARIANTS = ("store_zarr", "store_grid", "store_numba_grid")


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
        coarse_target = f"coarse read (levels <= k-2) <= COG overview read{tag}"
        if reads["cog_overview_ms"]:
            out.append(
                {
                    "target": coarse_target,
                    "value": crs / reads["cog_overview_ms"],
                    "limit": 1.0,
                    "detail": f"{crs:.2f} ms vs {reads['cog_overview_ms']:.2f} ms",
                }
            )
        else:  # nothing to compare with: listed as not measured, never as met
            factor = reads.get("coarse_decimation")
            out.append(
                {
                    "target": coarse_target,
                    "value": None,
                    "limit": 1.0,
                    "detail": f"not measured: the COG has no 1/{factor} overview "
                    f"(overview factors {reads.get('cog_overview_factors')})",
                }
            )
    for t in out:
        t["pass"] = target_met(t)
    return out


def target_met(t: dict[str, Any]) -> bool:
    """Whether target ``t`` was measured (``value`` not None) and is within its limit."""
    return t["value"] is not None and bool(t["value"] <= t["limit"])


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
    print_targets(results, 14)


def print_targets(results: list[dict[str, Any]], width: int) -> None:
    """The ``targets:`` list: PASS/MISS, input name (``width`` wide), target, value, detail."""
    print("targets:")
    for r in results:
        for t in r["targets"]:
            mark = "PASS" if t["pass"] else "MISS"
            value = "n/a" if t["value"] is None else f"{t['value']:.3f}"
            print(f"  {mark}  {r['name']:<{width}} {t['target']}: {value} ({t['detail']})")


def main_reads_only(args: argparse.Namespace) -> int:
    """``--reads-only``: no tiling, only the read timings of existing stores."""
    warnings.simplefilter("ignore")
    t_start = time.perf_counter()
    load_start = os.getloadavg()
    uptime_start = _uptime()
    results = [bench_reads_only(pair, args) for pair in args.reads_only]
    print_reads_report(results)
    load_end = os.getloadavg()
    notes = busy_notes(load_start, load_end)
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
    write_result(out, doc)
    return 0


def busy_notes(load_start: tuple[float, ...], load_end: tuple[float, ...]) -> list[str]:
    """A note when the 1-min load average at start or end exceeds half the CPUs (+0.5)."""
    if max(load_start[0], load_end[0]) > 0.5 * (os.cpu_count() or 1) + 0.5:
        return [
            f"machine busy: 1-min load average {load_start[0]:.1f} at start, "
            f"{load_end[0]:.1f} at end ({os.cpu_count()} CPUs); timings may be inflated"
        ]
    return []


def write_result(out: Path, doc: dict[str, Any]) -> None:
    """Write ``doc`` (paths made portable) as the benchmark's JSON and say so."""
    out.write_text(json.dumps(portable(doc), indent=2, allow_nan=False) + "\n")
    print(f"\nwrote {out} (run took {doc['run_seconds']:.0f} s)")


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


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
