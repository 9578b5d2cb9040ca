"""Threads or worker processes for a local tiling: where processes' start-up is repaid.

Usage::

    python bench/executor_choice.py [--sizes 40,1025,2049,4097] [--reps 2] [--kernels numpy]
                                    [--out PATH]

Tiles a synthetic DEM of each size (square, ``tests/demtools.fractal``) with 2 workers on
threads and on processes, alternated ``--reps`` times, each into a fresh store, and reports
the wall time of each and what ``auto`` picks (``tiler.run.choose_executor``). The numpy
kernels are the case where processes could win (the compiled ones release the GIL, and
``auto`` then keeps threads anyway). Prints a table and writes
``bench/results/executor_choice.json``; the sizes' samples set ``tiler.run.PROCESS_MIN_SAMPLES``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from bench.common import RESULTS, WORK, machine_info, portable  # noqa: E402


def block_for(size: int) -> int:
    """A block size giving at least 9 blocks (so ``auto`` considers processes at all)."""
    for b in (1025, 513, 257, 129, 65, 33, 17):
        if (size - 1) // (b - 1) >= 3:
            return b
    return 17


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="40,1025,2049,4097")
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--kernels", default="numpy", choices=["numpy", "numba", "auto"])
    p.add_argument("--out", type=Path, default=RESULTS / "executor_choice.json")
    args = p.parse_args(argv)
    os.environ["TERRASTREAM_KERNELS"] = args.kernels
    from demtools import fractal, write_dem

    from tiler import run
    from tiler.tile import TileOptions, tile

    work = WORK / "executor_choice"
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        src = work / f"d{size}.tif"
        if not src.exists():
            write_dem(src, fractal((size, size), 1))
        block = block_for(size)
        times: dict[str, list[float]] = {"threads": [], "processes": []}
        for _ in range(args.reps):
            for ex in ("threads", "processes"):
                dst = work / f"s{size}_{ex}.zarr"
                shutil.rmtree(dst, ignore_errors=True)
                t = time.perf_counter()
                st = tile(src, dst, TileOptions(block_size=block, workers=2, scheduler=ex))
                times[ex].append(time.perf_counter() - t)
                assert st.tile_summary.executor == ex, st.tile_summary.executor
                shutil.rmtree(dst, ignore_errors=True)
        k = (block - 1).bit_length() - 1
        todo = ((size - 2) // (block - 1) + 1) ** 2
        opts = TileOptions(block_size=block, workers=2)
        auto = run.choose_executor(opts, run.Location(str(work / "x.zarr")), todo,
                                   args.kernels, todo * (1 << k) ** 2)  # fmt: skip
        row = {
            "size": size,
            "block": block,
            "blocks": todo,
            "samples": size * size,
            "threads_s": times["threads"],
            "processes_s": times["processes"],
            "median_ratio_processes_over_threads": statistics.median(times["processes"])
            / statistics.median(times["threads"]),
            "auto": auto,
        }
        rows.append(row)
        print(
            f"{size:>6}² block {block:>5}: threads {min(times['threads']):6.2f}-"
            f"{max(times['threads']):6.2f} s, processes {min(times['processes']):6.2f}-"
            f"{max(times['processes']):6.2f} s (x{row['median_ratio_processes_over_threads']:.2f})"
            f", auto: {auto}",
            flush=True,
        )
    out = {
        "machine": machine_info(),
        "command": " ".join(["python", "bench/executor_choice.py", *(argv or sys.argv[1:])]),
        "kernels": args.kernels,
        "process_min_samples": run.PROCESS_MIN_SAMPLES,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(portable(out), indent=2) + "\n")
    print(f"wrote {portable(str(args.out))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
