"""LOD strategies side by side on the same fly-through (issue #5).

Runs :func:`render.strategies.compare.compare` (see its docstring for what is measured) on each
store given, prints the table and writes ``bench/results/lod_compare.json`` and
``bench/results/lod_compare_<store>.png`` (triangles vs measured error: the Pareto front).

Usage: python bench/lod_compare.py STORE [STORE ...] [--quick] [--taus 0.5,1,2,4]
       [--frames 8] [--size 1024x768]
``--quick``: 256x192, 4 frames, taus 1 and 4 (a smoke run; under 2 minutes on a small store).
Same as ``terrastream compare STORE --json ... --plot ...`` per store.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from render.strategies.compare import HEADER, compare, plot_pareto  # noqa: E402
from streamer.run import make_path  # noqa: E402
from tiler.store import open_store  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stores", nargs="+")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--taus", default="0.5,1,2,4")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", default="1024x768")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results"))
    a = ap.parse_args(argv)
    taus = [1.0, 4.0] if a.quick else [float(t) for t in a.taus.split(",")]
    frames = 4 if a.quick else a.frames
    w, h = (256, 192) if a.quick else tuple(int(v) for v in a.size.split("x"))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for path in a.stores:
        s = open_store(path)
        cams = make_path(s, "default", frames=frames, viewport=(w, h))
        print(f"# {path} {w}x{h}, {frames} frames")
        print(HEADER)
        rows = compare(s, cams, taus, log=print)
        name = Path(path).name.split(".")[0]
        plot_pareto(rows, out / f"lod_compare_{name}.png", title=f"{name} {w}x{h}")
        results[path] = rows
    (out / "lod_compare.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {out / 'lod_compare.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
