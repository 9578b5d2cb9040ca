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
* read time: ``store.read_block`` (all levels, decoded) vs a rasterio window read of the same
  area of the COG, and a coarse view (levels ``0..k-2``) vs the COG's overview at the same
  resolution; fresh store / dataset per repetition, opened outside the timed region. The store
  is read five ways in the same loop (``READ_VARIANTS``): the block's samples inside the DEM
  (``extent=store.block_extent(...)``: the same area as the COG window) with direct chunk reads
  and the numpy decode (``store``, what a fresh reader process does) or the numba decode
  (``store_numba``, a process that loaded numba, e.g. a streamer session after ``warm_up``);
  and, as references, the whole ``2**k+1`` grid with its padding (``store_grid``,
  ``store_numba_grid``: the reads before the windowed decode) and through zarr
  (``store_zarr``, the read path before issue 14).

``--reads-only STORE=SOURCE`` skips tiling: it builds a COG (with overviews) of SOURCE in
``--work-dir`` and times only the reads (``bench/results/tiling_reads.json``).

It prints a table and PASS/MISS for each target and writes every number to a JSON file. Sizes in
MB are MiB (2**20 bytes). Work files live in ``bench/work`` (git-ignored); synthetic sources are
kept for reuse, stores and COGs are deleted after measuring (``--keep`` keeps them).

The parts live beside this script: the measured child processes in ``bench/tiling_child.py``,
the read timings and ``--reads-only`` in ``bench/tiling_reads.py``, the targets and tables in
``bench/tiling_report.py``; this file keeps the inputs, one input's run and the command line.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import json
import os
import pstats
import sys
import time
import warnings
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import REAL_HGT, WORK, machine_info  # noqa: E402

# (names marked F401 are not used here: the child processes, read timing and report moved out
# of this file, and stay importable from it)
from bench.tiling_child import (  # noqa: E402
    MB,
    SAMPLE_S,  # noqa: F401
    _child_main,
    _rss_mb,
    run_child,
)
from bench.tiling_reads import (  # noqa: E402
    DEFAULT_OUT,
    DEFAULT_READS_OUT,  # noqa: F401
    READ_VARIANTS,  # noqa: F401
    REFERENCE_VARIANTS,  # noqa: F401
    _remove,
    bench_reads_only,  # noqa: F401
    busy_notes,
    main_reads_only,
    print_reads_report,  # noqa: F401
    read_targets,  # noqa: F401
    spread_blocks,  # noqa: F401
    tiler_sources_digest,
    time_reads,
    write_result,
)
from bench.tiling_report import (  # noqa: E402
    T_RSS_MB,  # noqa: F401
    T_RSS_MIN_SIZE,  # noqa: F401
    T_SIZE_VS_COG,  # noqa: F401
    T_SIZE_VS_COG_OVR,  # noqa: F401
    T_TIME_REAL_VS_COG_OVR,  # noqa: F401
    T_TIME_VS_COG_OVR,  # noqa: F401
    check_targets,
    print_report,
)

DEFAULT_REAL = REAL_HGT
SEED = 0


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


def _dir_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


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

    if not inputs:  # (no result is written: "all targets pass" over nothing would be vacuous)
        print("error: no input to tile (--sizes is empty and no real DEM)", file=sys.stderr)
        return 1
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
    notes.extend(busy_notes(load_start, load_end))
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
        # the tiler's switches as this run saw them (unset: the defaults, direct writes on)
        "environment": {
            v: os.environ.get(v) for v in ("TERRASTREAM_KERNELS", "TERRASTREAM_DIRECT_WRITES")
        },
        "load_average": {"start": list(load_start), "end": list(load_end)},
        "units": {"MB": "2**20 bytes", "ms": "median milliseconds"},
        "inputs": results,
        "process_block_profile": profile,
        "all_targets_pass": all(t["pass"] for r in results for t in r["targets"]),
        "run_seconds": time.perf_counter() - t_start,
    }
    write_result(out, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
