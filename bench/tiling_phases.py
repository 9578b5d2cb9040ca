"""Where a small tiling's time goes outside its blocks (issue 14): the store's fixed costs.

Usage::

    python bench/tiling_phases.py [SRC] [--reps 3] [--layout-reps 15] [--out PATH]

SRC (default: N44W072.hgt of the shared data) is tiled in this process ``--reps`` times (1025²
blocks, 2 workers), each call's phases timed by wrapping the tiler's own steps: creating the
store, until the first block starts, the blocks, the small levels' shards, finishing, and
opening the finished store (disjoint for a one-shard store such as an SRTM tile's; a larger
store writes shards while blocks run, so those two phases overlap). The first call pays each
library's first use in the process (the CLI's case); the median of the others is the warm
figure. Then, alternated ``--layout-reps`` times in this process: ``create_layout`` with
``method="memory"`` against ``"sequential"`` (where the code has both), and ``TerrainStore``
opening its arrays its own way (``open_default``: at once where the code batches them) against
one by one (where it has both). Prints a table and writes ``bench/results/tiling_phases.json``.
Run it in a checkout of each commit to compare versions.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import REAL_HGT, REPO, RESULTS, machine_info, portable  # noqa: E402

PHASES = ("before_store", "create_store", "to_first_block", "blocks", "small_levels",
          "finish", "open_store")  # fmt: skip


def _marks() -> tuple[list[tuple[float, str]], object]:
    """Wrap the tiler's steps so each call records ``(time, event)``; returns the list and an
    undo function."""
    import tiler.assemble as asm
    import tiler.destination as dest
    import tiler.run as run
    import tiler.tile as tile_mod

    ev: list[tuple[float, str]] = []
    lock = threading.Lock()

    def mark(what: str) -> None:
        with lock:
            ev.append((time.perf_counter(), what))

    saved = []

    def wrap(mod, name, tag):
        real = getattr(mod, name)

        def f(*a, **k):
            mark(tag + ">")
            try:
                return real(*a, **k)
            finally:
                mark(tag + "<")

        saved.append((mod, name, real))
        setattr(mod, name, f)

    wrap(dest, "create_store", "create")
    wrap(asm, "write_small_levels", "small")
    wrap(asm, "finish", "finish")
    wrap(tile_mod, "TerrainStore", "open")
    real_run = run.BlockWorker.run

    def block_run(self, br, bc):
        mark("block>")
        try:
            return real_run(self, br, bc)
        finally:
            mark("block<")

    run.BlockWorker.run = block_run

    def undo() -> None:
        for mod, name, real in saved:
            setattr(mod, name, real)
        run.BlockWorker.run = real_run

    return ev, undo


def _phases(ev: list[tuple[float, str]], t0: float, t1: float) -> dict[str, float]:
    """ms per phase from the marks of one tiling call (``t0``..``t1``)."""

    def first(tag: str) -> float:
        return min(t for t, w in ev if w == tag)

    def last(tag: str) -> float:
        return max(t for t, w in ev if w == tag)

    def total(tag: str) -> float:
        starts = sorted(t for t, w in ev if w == tag + ">")
        ends = sorted(t for t, w in ev if w == tag + "<")
        return sum(e - s for s, e in zip(starts, ends, strict=True))

    ms = {
        "before_store": first("create>") - t0,
        "create_store": total("create"),
        "to_first_block": first("block>") - last("create<"),
        "blocks": last("block<") - first("block>"),
        "small_levels": total("small"),
        "finish": total("finish"),
        "open_store": total("open"),
    }
    ms = {k: 1000.0 * v for k, v in ms.items()}
    ms["total"] = 1000.0 * (t1 - t0)
    return ms


def tile_phases(src: str, reps: int, work: Path) -> list[dict[str, float]]:
    """The phases of ``reps`` tiling calls of ``src`` in this process."""
    from tiler.tile import TileOptions, tile

    ev, undo = _marks()
    rows = []
    try:
        for i in range(reps):
            dst = work / f"t{i}.zarr"
            ev.clear()
            t0 = time.perf_counter()
            tile(src, str(dst), TileOptions(block_size=1025, workers=2))
            rows.append(_phases(ev, t0, time.perf_counter()))
    finally:
        undo()
    return rows


def layout_and_open(store_path: Path, reps: int, work: Path) -> dict[str, list[float]]:
    """Alternated ms of the layout methods and of the two ways to open the store's arrays."""
    import inspect

    import zarr

    from tiler import schema
    from tiler.store import TerrainStore

    meta = TerrainStore(store_path).meta
    out: dict[str, list[float]] = {}
    methods = []
    if "method" in inspect.signature(schema.create_layout).parameters:
        methods = ["memory", "sequential"]
    one_by_one = None
    if hasattr(TerrainStore, "_open_arrays"):
        batched = TerrainStore._open_arrays

        def one_by_one(self, names):  # the reference: the arrays one after another
            for n in names:
                self._array(n)

    with schema.compact_metadata():
        for _ in range(reps):
            for m in methods:
                d = work / f"layout-{m}.zarr"
                shutil.rmtree(d, ignore_errors=True)
                g = zarr.open_group(d, mode="w")
                t = time.perf_counter()
                schema.create_layout(g, meta, schema.DEFAULT_CLEVEL, method=m)
                out.setdefault(f"layout_{m}", []).append(1000.0 * (time.perf_counter() - t))
            for how in ("default", "one_by_one"):
                if how == "one_by_one" and one_by_one is not None:
                    TerrainStore._open_arrays = one_by_one
                try:
                    t = time.perf_counter()
                    TerrainStore(store_path)
                    out.setdefault(f"open_{how}", []).append(1000.0 * (time.perf_counter() - t))
                finally:
                    if one_by_one is not None:
                        TerrainStore._open_arrays = batched
                if one_by_one is None:
                    break  # code before the batched opens: one way only
    return out


def main(argv: list[str] | None = None) -> dict:
    """Measure, print the table, write the JSON; returns it."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("src", nargs="?", default=None)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--layout-reps", type=int, default=15)
    ap.add_argument("--out", default=str(RESULTS / "tiling_phases.json"))
    a = ap.parse_args(argv)
    src = a.src or str(REAL_HGT)
    if not Path(src).exists():
        sys.exit(f"source {src} not found (set TERRASTREAM_SHARED_DATA or give SRC)")
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        rows = tile_phases(src, a.reps, work)
        layout = layout_and_open(work / "t0.zarr", a.layout_reps, work)
    warm = rows[1:] or rows
    table = {
        "first_call_ms": rows[0],
        "warm_median_ms": {k: statistics.median(r[k] for r in warm) for k in rows[0]},
        "layout_and_open_median_ms": {k: statistics.median(v) for k, v in layout.items()},
    }
    print(f"{'phase':<16}{'first call ms':>15}{'warm median ms':>16}")
    for k in (*PHASES, "total"):
        print(f"{k:<16}{rows[0][k]:>15.1f}{table['warm_median_ms'][k]:>16.1f}")
    for k, v in table["layout_and_open_median_ms"].items():
        print(f"{k:<16}{'':>15}{v:>16.1f}")
    result = portable(
        {
            "benchmark": "tiling_phases",
            "source": src,
            "reps": a.reps,
            "layout_reps": a.layout_reps,
            "machine": machine_info(),
            **table,
            "runs_ms": rows,
            "layout_and_open_ms": layout,
        }
    )
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"# wrote {out.relative_to(REPO) if out.is_relative_to(REPO) else out}")
    return result


if __name__ == "__main__":
    main()
