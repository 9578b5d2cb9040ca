"""What the render thread pays when ``auto`` switches a CPU strategy to its compiled kernels
(issue 14): the viewer draws its first frames with the numpy reference while a background
thread runs ``warm_up_kernels(**strategy.warm_up_args())``; the first compiled selection
after it may still load kernels from numba's cache or build compiled-only state (jung-han's
flat forest).

Usage::

    python bench/kernel_switch.py [STORE] [--lods qiu,jung-han,seamless-patches] [--runs 3]
                                  [--out PATH]

Per strategy and run, in a fresh process (the numba cache already filled): every block of
STORE uploaded at full resolution, the overview camera at 1024×768, τ = 1; one numpy
selection, then the viewer's warm-up (timed), then three selections: the first compiled one
and the third (steady state). Reported: the first compiled selection's ms and its excess
over the third. Default STORE: the N44W072 metre store of ``bench/prefetch.py``. Prints a
table and writes ``bench/results/kernel_switch.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import N44W072_EQC, REPO, RESULTS, ensure_store, machine_info, portable  # noqa: E402

CHILD = """
import json, os, sys, time
from tiler.store import open_store
from render.renderer import RenderConfig, TerrainRenderer
from render.strategies import get_strategy, warm_up_kernels
from render.views import overview_camera
s = open_store(sys.argv[1])
r = TerrainRenderer(s, RenderConfig(size=(1024, 768)))
for b in s.blocks():
    r.upload(b, s.read_levels(b, s.k))
st = get_strategy(sys.argv[2], r)
cam = overview_camera(s, (1024, 768))
def ms():
    t = time.perf_counter(); st.select(cam, 1.0); return (time.perf_counter() - t) * 1e3
numpy_ms = ms()
kw = getattr(st, "warm_up_args", dict)()  # as the viewer passes them (older code: none)
t = time.perf_counter(); warm_up_kernels(**kw); warm_ms = (time.perf_counter() - t) * 1e3
after = [ms() for _ in range(3)]
r.close()
print(json.dumps({"numpy_ms": numpy_ms, "warm_up_ms": warm_ms, "compiled_ms": after}))
"""


def run(store: Path, lod: str) -> dict:
    """One fresh process: the numpy selection, the warm-up, three compiled selections."""
    env = {k: v for k, v in os.environ.items() if k != "TERRASTREAM_KERNELS"}
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(store), lod],
        cwd=str(REPO), env=env, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    if out.returncode != 0:
        raise RuntimeError(f"{lod} failed (exit {out.returncode}):\n{out.stderr[-3000:]}")
    d = json.loads(out.stdout.strip().splitlines()[-1])
    first, steady = d["compiled_ms"][0], d["compiled_ms"][2]
    return d | {"lod": lod, "first_ms": first, "steady_ms": steady, "excess_ms": first - steady}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store", nargs="?", type=Path, default=N44W072_EQC)
    ap.add_argument("--lods", default="qiu,jung-han,seamless-patches")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS / "kernel_switch.json")
    a = ap.parse_args(argv)
    if not ensure_store(a.store):
        print(f"# {a.store} is missing and cannot be made here (the real DEM is absent)")
        return 1
    lods = [x.strip() for x in a.lods.split(",")]
    rows = [run(a.store, lod) for _ in range(a.runs) for lod in lods]
    head = ("strategy", "warm-up ms", "1st compiled ms", "steady ms", "excess ms")
    print(f"{head[0]:18} {head[1]:>10} {head[2]:>15} {head[3]:>9} {head[4]:>9}")
    for r in rows:
        print(f"{r['lod']:18} {r['warm_up_ms']:10.1f} {r['first_ms']:15.1f} "
              f"{r['steady_ms']:9.2f} {r['excess_ms']:9.1f}")  # fmt: skip
    a.out.parent.mkdir(parents=True, exist_ok=True)
    out = {"store": a.store.name, "rows": rows, "machine": machine_info()}
    a.out.write_text(json.dumps(portable(out), indent=1))
    print(f"wrote {a.out.relative_to(REPO) if a.out.is_relative_to(REPO) else a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
