"""Tiling with the workers' direct chunk writes against zarr's writes, alternated in one run.

    python bench/tiling_writes.py [--pairs 3] [--sizes 4097,16385] [--real PATH] [--workers 2]

Each pair tiles the same input twice in fresh child processes (``bench/tiling.py --child``,
the benchmark's own measured child), once with ``tiler.chunkwrite`` (the default) and once
with ``TERRASTREAM_DIRECT_WRITES=0`` (every chunk through zarr), in alternating order, and
checks that both stores hold the same chunk bytes. Inputs are the synthetic DEMs that
``bench/tiling.py`` makes (``bench/work``) and the real SRTM tile. Writes
``bench/results/tiling_writes.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.common import REAL_HGT, RESULTS, WORK, machine_info, portable  # noqa: E402
from bench.tiling_child import run_child  # noqa: E402

OUT = RESULTS / "tiling_writes.json"
ENV = "TERRASTREAM_DIRECT_WRITES"


def _chunk_bytes(root: Path) -> dict[str, bytes]:
    out = {}
    for top in ("levels", "errors", "mask"):
        for p in (root / top).rglob("*"):
            if p.is_file() and p.name != "zarr.json":
                out[str(p.relative_to(root))] = p.read_bytes()
    return out


def _tile(src: Path, dst: Path, workers: int, direct: bool) -> float:
    task = {"kind": "tile", "src": str(src), "dst": str(dst), "block_size": 1025}
    task["workers"] = workers
    old = os.environ.get(ENV)
    os.environ[ENV] = "1" if direct else "0"
    try:
        return float(run_child(task)["seconds"])
    finally:
        if old is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = old


def bench_input(name: str, src: Path, pairs: int, workers: int) -> dict[str, Any]:
    """``pairs`` alternated (direct, zarr) tilings of ``src``; seconds and the byte check."""
    times: dict[str, list[float]] = {"direct": [], "zarr": []}
    dst = {v: WORK / f"writes_{name}_{v}.zarr" for v in times}
    for i in range(pairs):
        order = ("direct", "zarr") if i % 2 == 0 else ("zarr", "direct")
        for v in order:
            times[v].append(_tile(src, dst[v], workers, v == "direct"))
            print(f"  [{name}] pair {i + 1} {v}: {times[v][-1]:.2f} s", flush=True)
    same = _chunk_bytes(dst["direct"]) == _chunk_bytes(dst["zarr"])
    med = {v: statistics.median(t) for v, t in times.items()}
    return {
        "name": name,
        "source": str(src),
        "seconds": times,
        "median_s": med,
        "ratio_direct_vs_zarr": med["direct"] / med["zarr"],
        "chunks_identical": same,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--pairs", type=int, default=3)
    p.add_argument("--sizes", default="4097,16385")
    p.add_argument("--real", default=str(REAL_HGT))
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", default=str(OUT))
    args = p.parse_args(argv)
    sizes = [n for n in args.sizes.split(",") if n]
    inputs = [(f"synth{n}", WORK / f"synth_{n}_seed0_int16.tif") for n in sizes]
    if args.real:
        inputs.append((Path(args.real).stem, Path(args.real)))
    rows = []
    for name, src in inputs:
        if not src.exists():
            print(f"skip {name}: {src} is absent (bench/tiling.py makes the synthetic ones)")
            continue
        rows.append(bench_input(name, src, args.pairs, args.workers))
    if not rows:
        print("error: no input was measured (see the skip lines)", file=sys.stderr)
        return 1
    print(f"\n{'input':<12} {'direct s':>9} {'zarr s':>8} {'ratio':>6}  chunks identical")
    for r in rows:
        m = r["median_s"]
        print(
            f"{r['name']:<12} {m['direct']:9.2f} {m['zarr']:8.2f} "
            f"{r['ratio_direct_vs_zarr']:6.3f}  {r['chunks_identical']}"
        )
    out = {"benchmark": "tiling_writes", "args": vars(args), "machine": machine_info()}
    out["inputs"] = rows
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(portable(out), indent=2))
    print(f"wrote {portable(str(args.out))}")
    return 0 if all(r["chunks_identical"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
