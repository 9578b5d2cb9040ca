"""Sources benchmark: a mosaic of many tiles vs one file, and reprojection while tiling.

Usage::

    python bench/sources.py [--tiles 4] [--tile-size 1201] [--workers 2]
                            [--out bench/results/sources.json]

Inputs (written once into ``bench/work/sources``, git-ignored) are cut from one synthetic
``n x n`` int16 DEM (``tiler.synth.synth_array``, ``n = tiles*(tile_size-1)+1``) in the SRTM
layout: ``tiles x tiles`` files of ``tile_size``² samples on a 1/(tile_size-1)-degree grid in
EPSG:4326, neighbours sharing their edge row/column; plus the same samples as one geographic
file, and as one projected file (EPSG:32619, 30 m). Each tiling runs in a child process
(``executor="threads"`` so one process holds everything) and reports wall time and the
child's peak RSS (``ru_maxrss`` from ``os.wait4``). Runs:

* ``mosaic``: the tiles as one mosaic (no reprojection) vs ``single``: the one geographic file;
* ``auto``: the one geographic file with ``dst_crs="auto"`` vs ``projected``: the projected
  file of the same size, plus the resampling error of ``auto`` measured at the source's own
  samples (``tiler.accuracy.resampling_error``, every 4th sample).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import rasterio  # noqa: E402
from rasterio.transform import from_origin  # noqa: E402

from bench.common import portable  # noqa: E402
from tiler.synth import synth_array  # noqa: E402

WORK = REPO / "bench" / "work" / "sources"

CHILD = """
import json, sys, time
from tiler.tile import TileOptions, tile
srcs, dst, workers, dst_crs = json.loads(sys.argv[1])
t = time.perf_counter()
s = tile(srcs, dst, TileOptions(workers=workers, executor="threads", overwrite=True,
                                dst_crs=dst_crs))
print(json.dumps({"seconds": time.perf_counter() - t, "height": s.meta.height,
                  "width": s.meta.width, "bytes": s.nbytes()["total"]}))
"""


def write(path: Path, data: np.ndarray, crs: str, transform) -> Path:
    """One int16 GeoTIFF (tiled, deflate), written once."""
    if path.exists():
        return path
    h, w = data.shape
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=w,
        height=h,
        count=1,
        dtype="int16",
        crs=crs,
        transform=transform,
        tiled=True,
        compress="deflate",
        nodata=-32768,
    ) as dst:
        dst.write(data, 1)
    return path


def inputs(tiles: int, tile_size: int) -> dict:
    """The tiles, the geographic single file and the projected single file."""
    WORK.mkdir(parents=True, exist_ok=True)
    step = tile_size - 1
    n = tiles * step + 1
    deg = 1.0 / step
    lon0, lat0 = -72.0, 44.0 + tiles  # SRTM-style: N44W072 is the south-west tile
    data = synth_array(slice(0, n), slice(0, n), n, seed=7, dtype="int16")
    half = deg / 2
    paths = []
    for i in range(tiles):
        for j in range(tiles):
            r0, c0 = i * step, j * step
            t = from_origin(lon0 + c0 * deg - half, lat0 - r0 * deg + half, deg, deg)
            p = WORK / f"tile_{tiles}_{i}_{j}.tif"
            paths.append(
                str(write(p, data[r0 : r0 + tile_size, c0 : c0 + tile_size], "EPSG:4326", t))
            )
    single = write(
        WORK / f"single_{n}.tif", data, "EPSG:4326", from_origin(lon0 - half, lat0 + half, deg, deg)
    )
    projected = write(
        WORK / f"projected_{n}.tif",
        data,
        "EPSG:32619",
        from_origin(300000.0, 4900000.0, 30.0, 30.0),
    )
    return {"tiles": paths, "single": str(single), "projected": str(projected), "n": n}


def run(srcs, dst: Path, workers: int, dst_crs: str | None) -> dict:
    """Tile in a child process; wall time inside it and its peak RSS."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, json.dumps([srcs, str(dst), workers, dst_crs])],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        env=env,
        cwd=REPO,
    )
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    if status != 0:
        raise RuntimeError(f"tiling {srcs!r} failed with status {status}")
    res = json.loads(out)
    res["peak_rss_mib"] = usage.ru_maxrss / 1024  # Linux: KiB
    return res


def write_result(path: Path, doc: dict) -> None:
    """Write ``doc`` as the benchmark's JSON, naming no machine's paths (``--out``)."""
    path.write_text(json.dumps(portable(doc), indent=2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tiles", type=int, default=4, help="tiles per side (4 -> 16 files)")
    ap.add_argument("--tile-size", type=int, default=1201)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "sources.json"))
    a = ap.parse_args()
    t = time.perf_counter()
    inp = inputs(a.tiles, a.tile_size)
    print(
        f"inputs ready in {time.perf_counter() - t:.1f} s: {len(inp['tiles'])} tiles, "
        f"{inp['n']}^2 samples"
    )
    rows = {}
    rows["single"] = run(inp["single"], WORK / "single.zarr", a.workers, None)
    rows["mosaic"] = run(inp["tiles"], WORK / "mosaic.zarr", a.workers, None)
    rows["projected"] = run(inp["projected"], WORK / "projected.zarr", a.workers, None)
    rows["auto"] = run(inp["single"], WORK / "auto.zarr", a.workers, "auto")
    from tiler.accuracy import resampling_error
    from tiler.crs import crs_name
    from tiler.store import open_store

    auto = open_store(WORK / "auto.zarr")
    rows["auto"]["crs"] = crs_name(auto.meta.crs_wkt)
    rows["auto"]["resolution_m"] = auto.meta.geotransform[0]
    rows["auto"]["error_m"] = resampling_error(auto, inp["single"], stride=4)
    a_single, a_mosaic = open_store(WORK / "single.zarr"), open_store(WORK / "mosaic.zarr")
    same = all(
        np.array_equal(a_single.read_block(b), a_mosaic.read_block(b))
        for b in a_single.grid.blocks()
    )
    rows["mosaic"]["equal_to_single"] = bool(same)
    print(f"{'run':<10} {'samples':>13} {'time s':>8} {'peak RSS MiB':>13} {'store MiB':>10}")
    for name, r in rows.items():
        print(
            f"{name:<10} {r['height']:>6}x{r['width']:<6} {r['seconds']:>8.1f} "
            f"{r['peak_rss_mib']:>13.0f} {r['bytes'] / 2**20:>10.1f}"
        )
    e = rows["auto"]["error_m"]
    print(
        f"auto -> {rows['auto']['crs']} at {rows['auto']['resolution_m']} m; resampling error "
        f"at source samples: rms {e['rms']:.2f} m, p99 {e['p99']:.2f} m, max {e['max']:.1f} m"
    )
    print(f"mosaic store equal to the single-file store: {same}")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    write_result(Path(a.out), {"args": vars(a), "runs": rows})


if __name__ == "__main__":
    main()
