"""LOD strategies side by side on the same fly-through (issue #5).

Runs :func:`render.strategies.compare.compare` (see its docstring for what is measured) on each
store given, prints the table and writes ``bench/results/lod_compare.json`` and
``bench/results/lod_compare_<store>.png`` (triangles vs measured error: the Pareto front);
``--quick`` writes ``lod_compare_quick*`` instead.

Usage: python bench/lod_compare.py [STORE ...] [--quick] [--taus 0.5,1,2,4]
       [--frames 8] [--size 1024x768] [--lods a,b]
Default stores: the synthetic 4097^2 store and the real N44W072 store of BENCHMARKS.md (a
missing one is skipped with a message).
``--quick``: 256x192, 4 frames, taus 1 and 4 (a smoke run; under 2 minutes on a small store).
Same as ``terrastream compare STORE --json ... --plot ...`` per store.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import N44W072_EQC, RESULTS, S4097, machine_info  # noqa: E402
from render.strategies.compare import HEADER, compare, plot_pareto  # noqa: E402
from streamer.run import make_path  # noqa: E402
from tiler.store import open_store  # noqa: E402

DEFAULT_STORES = [str(S4097), str(N44W072_EQC)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stores", nargs="*", default=DEFAULT_STORES)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--taus", default="0.5,1,2,4")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", default="1024x768")
    ap.add_argument("--lods", default=None, help="comma-separated strategies (default: all)")
    ap.add_argument("--out", default=str(RESULTS))
    a = ap.parse_args(argv)
    taus = [1.0, 4.0] if a.quick else [float(t) for t in a.taus.split(",")]
    frames = 4 if a.quick else a.frames
    w, h = (256, 192) if a.quick else tuple(int(v) for v in a.size.split("x"))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    lods = a.lods.split(",") if a.lods else None
    tag = "_quick" if a.quick else ""
    for path in a.stores:
        if not Path(path).exists():
            print(f"# skipping {path}: not found (see BENCHMARKS.md for how to make it)")
            continue
        s = open_store(path)
        cams = make_path(s, "default", frames=frames, viewport=(w, h))
        print(f"# {path} {w}x{h}, {frames} frames")
        print(HEADER)
        t0 = time.perf_counter()
        rows = compare(s, cams, taus, strategies=lods, log=print)
        print(f"# {time.perf_counter() - t0:.0f} s")
        name = Path(path).name.split(".")[0]
        plot_pareto(rows, out / f"lod_compare{tag}_{name}.png", title=f"{name} {w}x{h}")
        results[path] = rows
    js = out / f"lod_compare{tag}.json"
    js.write_text(json.dumps(results, indent=1))
    (out / f"lod_compare{tag}_machine.json").write_text(json.dumps(machine_info(), indent=1))
    print(f"wrote {js}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
