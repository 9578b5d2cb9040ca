"""Per-block kernel timings: numba kernels vs the numpy reference, in one run, plus CLI start-up.

Usage::

    python bench/kernels.py [--reps 15] [--sizes 257,1025] [--out bench/results/kernels.json]
                            [--no-startup] [--quick] [--ops decode_grid,encode_levels]
                            [--dtypes float32]

For each block (synthetic int16 and float32 blocks from ``tiler.synth.synth_array``, and a
1025² window of the real SRTM tile when present) and each hot operation (``fill_invalid`` on the
block with ~10 % nodata, ``encode_levels``, ``decode_grid`` of all levels and of levels
``0..k-2``, ``qiu_errors``, ``bound_errors``, ``block_errors``, and the tiler's whole
``process_block``) it alternates numpy and numba calls ``--reps`` times (``TERRASTREAM_KERNELS``
switched between calls) and reports medians and the numpy/numba ratio. The machine may be
shared: medians of interleaved repetitions keep the ratio honest even when absolute times move.

Start-up (``--no-startup`` skips it, ``--startup-only`` runs only it): ``python -m cli.main
info`` on a small store (and on a ``--compare-tree`` checkout, alternately; medians of 7), and
the first kernel call in a fresh process with an empty numba cache (compiles), with the cache
filled (loads), and with the numpy backend.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from tiler import encoding, kernels, static_error  # noqa: E402
from tiler.layout import parse_block_size  # noqa: E402
from tiler.synth import synth_array  # noqa: E402

DEFAULT_OUT = REPO / "bench" / "results" / "kernels.json"
from bench.common import REAL_HGT as REAL  # noqa: E402  ($TERRASTREAM_SHARED_DATA)
from bench.common import portable  # noqa: E402

#: another checkout to compare `terrastream info` start-up with (--compare-tree; none by default)
OTHER_TREE: Path | None = None


def _blocks(sizes: list[int], dtypes: tuple[str, ...] = ("int16", "float32")):
    """Named test blocks: synthetic ones of each size and dtype, the SRTM window (int16)."""
    out: list[tuple[str, np.ndarray]] = []
    for side in sizes:
        for dt in dtypes:
            g = synth_array(slice(0, side), slice(0, side), side, seed=3, dtype=dt)
            out.append((f"synth-{side}-{dt}", g))
    if REAL.exists() and 1025 in sizes and "int16" in dtypes:
        import rasterio
        from rasterio.windows import Window

        with rasterio.open(REAL) as ds:
            out.append(("N44W072-1025-int16", ds.read(1, window=Window(100, 100, 1025, 1025))))
    return out


def _nodata_mask(side: int) -> np.ndarray:
    """~10 % invalid: a disc and a band of scattered samples (covers corners of some nodes)."""
    yy, xx = np.mgrid[0:side, 0:side]
    valid = (yy - side * 0.3) ** 2 + (xx - side * 0.6) ** 2 > (side * 0.15) ** 2
    rng = np.random.default_rng(1)
    valid &= rng.random((side, side)) > 0.03
    return valid


def _ops(grid: np.ndarray, k: int) -> dict[str, Any]:
    from tiler.tile import BlockParams, process_block

    side = grid.shape[0]
    valid_all = np.ones_like(grid, dtype=bool)
    valid = _nodata_mask(side)
    holes = grid.copy()
    if grid.dtype.kind == "f":
        holes[~valid] = np.nan
        filled_src = np.where(valid, grid, 0).astype(grid.dtype)
    else:
        holes[~valid] = -32768
        filled_src = holes
    filled = encoding.fill_invalid_numpy(filled_src, valid, k)
    stored = encoding.encode_levels_numpy(filled, k)
    cap = static_error.default_cap(k)
    nodata = None if grid.dtype.kind == "f" else -32768.0
    params = BlockParams(
        k, grid.dtype.name, "uint16" if grid.dtype.itemsize == 2 else "uint32", nodata, None, cap
    )
    return {
        "fill_invalid": lambda: encoding.fill_invalid(filled_src, valid, k),
        "encode_levels": lambda: encoding.encode_levels(grid, k),
        "decode_grid": lambda: encoding.decode_grid(stored, grid.dtype),
        "decode_grid_coarse": lambda: encoding.decode_grid(stored, grid.dtype, k - 2),
        "qiu_errors": lambda: static_error.qiu_errors(grid, valid_all, k),
        "bound_errors": lambda: static_error.bound_errors(grid, valid_all, k),
        "block_errors": lambda: static_error.block_errors(grid, valid_all, k, cap),
        "process_block": lambda: process_block(grid, params),
        "process_block_nodata": lambda: process_block(holes, params),
    }


def _time(fn, mode: str) -> float:
    os.environ[kernels.ENV] = mode
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def bench_kernels(
    sizes: list[int], reps: int, ops: set[str] | None = None, dtypes: tuple[str, ...] = ()
) -> list[dict[str, Any]]:
    """Interleaved numpy/numba medians (and the numba best) for every op (or ``ops``) and
    block (of ``dtypes``, default int16 and float32)."""
    rows = []
    for name, grid in _blocks(sizes, dtypes or ("int16", "float32")):
        k = parse_block_size(grid.shape[0])
        table = _ops(grid, k)
        if ops and not ops <= table.keys():
            raise SystemExit(f"unknown --ops {sorted(ops - table.keys())}; known: {list(table)}")
        for op, fn in table.items():
            if ops and op not in ops:
                continue
            _time(fn, "numba")  # compile / load from the cache outside the timed region
            _time(fn, "numpy")
            tn, tb = [], []
            for _ in range(reps):
                tn.append(_time(fn, "numpy"))
                tb.append(_time(fn, "numba"))
            row = {
                "block": name,
                "op": op,
                "numpy_ms": 1e3 * statistics.median(tn),
                "numba_ms": 1e3 * statistics.median(tb),
                "numba_best_ms": 1e3 * min(tb),
                "reps": reps,
            }
            row["speedup"] = row["numpy_ms"] / row["numba_ms"]
            rows.append(row)
            print(
                f"{name:22s} {op:22s} numpy {row['numpy_ms']:8.2f} ms  numba "
                f"{row['numba_ms']:8.2f} ms (best {row['numba_best_ms']:.2f})  "
                f"x{row['speedup']:6.1f}",
                flush=True,
            )
    os.environ.pop(kernels.ENV, None)
    return rows


def breakdown(grid: np.ndarray, reps: int) -> dict[str, float]:
    """Median ms of each step of ``process_block`` (numba backend) for one block, and of
    compressing its levels with today's codec and the recommended one (bench/codecs.py)."""
    from numcodecs import Blosc

    from tiler.tile import BlockParams, process_block

    os.environ[kernels.ENV] = "numba"
    mod = kernels.active()
    k = parse_block_size(grid.shape[0])
    cap = static_error.default_cap(k)
    valid = np.ones(grid.shape, bool)
    params = BlockParams(k, grid.dtype.name, f"uint{8 * grid.dtype.itemsize}", None, None, cap)
    levels = encoding.encode_levels(grid, k)
    ts = grid.dtype.itemsize
    now = Blosc(cname="zstd", clevel=5, shuffle=Blosc.SHUFFLE, blocksize=0, typesize=ts)
    rec = Blosc(cname="zstd", clevel=3, shuffle=Blosc.SHUFFLE, blocksize=1 << 20, typesize=ts)
    qflat = kernels.qiu_flat(mod, grid, valid, k)
    f, margin = static_error._recentre(grid, valid, mod)
    node = kernels.bound_flat(mod, f, valid, k)
    steps = {
        "process_block (total)": lambda: process_block(grid, params),
        "encode_levels": lambda: encoding.encode_levels(grid, k),
        "qiu kernel": lambda: kernels.qiu_flat(mod, grid, valid, k),
        "median + recentre": lambda: static_error._recentre(grid, valid, mod),
        "bound kernel": lambda: kernels.bound_flat(mod, f, valid, k),
        "bound float64 + margin": lambda: np.where(node > 0, node.astype(np.float64) + margin, 0),
        "monotone + pack + f16 (x2)": lambda: [
            static_error.round_up_f16(kernels.monotone_pack(mod, qflat.copy(), k, cap, 1.0))
            for _ in range(2)
        ],
        "digest (blake2b)": lambda: __import__("hashlib").blake2b(grid.tobytes(), digest_size=8),
        "blosc levels zstd5 (today)": lambda: [now.encode(lv) for lv in levels],
        "blosc levels zstd3 1MiB (rec.)": lambda: [rec.encode(lv) for lv in levels],
    }
    times: dict[str, list[float]] = {name: [] for name in steps}
    for _ in range(reps):
        for name, fn in steps.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    os.environ.pop(kernels.ENV, None)
    out = {name: 1e3 * statistics.median(v) for name, v in times.items()}
    for name, ms in out.items():
        print(f"  {name:32s} {ms:8.2f} ms")
    return out


_FIRST_CALL = """
import time, numpy as np
t0 = time.perf_counter()
from tiler import encoding, static_error
g = (np.arange(65 * 65, dtype=np.int16) % 97).reshape(65, 65)
v = np.ones((65, 65), bool)
t1 = time.perf_counter()
encoding.encode_levels(encoding.fill_invalid(g, v, 6), 6)
static_error.block_errors(g, v, 6, 2)
t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def _run(cmd: list[str], env: dict[str, str], cwd: Path) -> float:
    t = time.perf_counter()
    subprocess.run(cmd, env=env, cwd=cwd, check=True, capture_output=True)
    return time.perf_counter() - t


def bench_startup(runs: int = 7) -> dict[str, Any]:
    """`info` wall time (this tree vs main) and first-kernel latency cold/warm/numpy."""
    from tiler.synth import synth_dem
    from tiler.tile import TileOptions, tile

    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "s.tif"
        synth_dem(src, 513)
        store = Path(tmp) / "s.zarr"
        tile(src, store, TileOptions(block_size=257, workers=1))
        base = {k: v for k, v in os.environ.items() if k not in (kernels.ENV, "PYTHONPATH")}
        cmd = [sys.executable, "-m", "cli.main", "info", str(store)]
        pairs = [("this_tree", REPO)] + ([("other_tree", OTHER_TREE)] if OTHER_TREE else [])
        trees = [(lbl, t) for lbl, t in pairs if t.exists()]
        times: dict[str, list[float]] = {lbl: [] for lbl, _ in trees}
        for i in range(runs + 1):  # alternate the trees; the first round warms the page cache
            for lbl, tree in trees:
                t = _run(cmd, {**base, "PYTHONPATH": str(tree)}, tree)
                if i:
                    times[lbl].append(t)
        for lbl, ts in times.items():
            out[f"info_{lbl}_s"] = statistics.median(ts)
        env = {**base, "PYTHONPATH": str(REPO), "NUMBA_CACHE_DIR": str(Path(tmp) / "nbcache")}
        probe = [sys.executable, "-c", _FIRST_CALL]
        for label, extra in (
            ("cold_cache", {}),
            ("warm_cache", {}),
            ("numpy", {kernels.ENV: "numpy"}),
        ):
            t = time.perf_counter()
            r = subprocess.run(
                probe, env={**env, **extra}, cwd=REPO, check=True, capture_output=True, text=True
            )
            wall = time.perf_counter() - t
            imp, first = (float(x) for x in r.stdout.split())
            out[f"first_call_{label}"] = {"wall_s": wall, "import_s": imp, "first_block_s": first}
        env_i = {**base, "PYTHONPATH": str(REPO)}
        r = subprocess.run(
            [sys.executable, "-X", "importtime", "-m", "cli.main", "info", str(store)],
            env=env_i,
            cwd=REPO,
            capture_output=True,
            text=True,
            check=True,
        )
        out["info_imports_numba"] = "numba" in r.stderr
    for key, val in out.items():
        print(f"{key:28s} {val}")
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument(
        "--compare-tree", type=Path, default=None, help="another checkout: time its `info` too"
    )
    ap.add_argument("--sizes", default="257,1025")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--no-startup", action="store_true")
    ap.add_argument("--startup-only", action="store_true", help="only the start-up section")
    ap.add_argument(
        "--breakdown", action="store_true", help="only the per-step profile of a 1025^2 block"
    )
    ap.add_argument("--quick", action="store_true", help="257 only, 3 reps, no start-up")
    ap.add_argument("--ops", default="", help="comma-separated ops to time (default: all)")
    ap.add_argument("--dtypes", default="int16,float32", help="synthetic block dtypes")
    a = ap.parse_args(argv)
    global OTHER_TREE
    OTHER_TREE = a.compare_tree
    if kernels.active() is None:
        print("numba is not importable: nothing to compare", file=sys.stderr)
        return 1
    sizes = [257] if a.quick else [int(s) for s in a.sizes.split(",")]
    reps = 3 if a.quick else a.reps
    ops = {o for o in a.ops.split(",") if o}
    result: dict[str, Any] = {
        "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
        },
        "command": " ".join([Path(sys.argv[0]).name, *(argv or sys.argv[1:])]),
        "kernels": []
        if (a.startup_only or a.breakdown)
        else bench_kernels(sizes, reps, ops, tuple(a.dtypes.split(","))),
    }
    if not (a.quick or a.no_startup or a.breakdown):
        result["startup"] = bench_startup()
    if a.breakdown:
        for name, grid in _blocks([1025]):
            if grid.dtype == np.int16:
                print(name)
                result.setdefault("breakdown", {})[name] = breakdown(grid, max(reps, 5))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(portable(result), indent=2) + "\n")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
