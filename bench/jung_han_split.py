"""Where ``jung-han``'s CPU selection goes (issue 14): its two numba kernels replayed alone.

Usage::

    python bench/jung_han_split.py [STORE] [--taus 1,2] [--size 1024x768] [--frames 8]
                                   [--reps 30] [--out PATH]

The default fly-through of STORE (default: the N44W072 metre store of ``bench/prefetch.py``),
every block in view streamed at full resolution, as ``bench/select_cpu.py`` does. Per frame and
τ the selection runs once with the numba kernels, its ``traverse`` and ``assemble`` inputs are
captured, then ``select`` and each kernel are timed ``--reps`` times on those inputs (the
kernels' outputs checked equal to the selection's own). Reported: the mean over the frames of
the median ms of the whole selection, of each kernel, and the rest (Python, the hull, the
kernel calls' argument handling). Run it in a checkout of each commit to compare code
versions; prints a table and writes ``bench/results/jung_han_split.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np  # noqa: E402

from bench.common import N44W072_EQC, REPO, RESULTS, machine_info, portable  # noqa: E402
from bench.select_cpu import _frames  # noqa: E402


class _Capture:
    """The jung-han kernel module with ``traverse`` and ``assemble`` recording their inputs."""

    def __init__(self, mod) -> None:
        self.mod, self.calls = mod, {"traverse": [], "assemble": []}

    def __getattr__(self, name):
        return getattr(self.mod, name)

    def traverse(self, *a):
        self.calls["traverse"].append(
            tuple(np.copy(x) if isinstance(x, np.ndarray) else x for x in a)
        )
        return self.mod.traverse(*a)

    def assemble(self, *a):
        self.calls["assemble"].append(
            tuple(np.copy(x) if isinstance(x, np.ndarray) else x for x in a)
        )
        return self.mod.assemble(*a)


def _median_ms(reps: int, fn, *args, **kw) -> float:
    """Median ms of ``reps`` calls ``fn(*args, **kw)``."""
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn(*args, **kw)
        ts.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(ts)


def measure(path: str, size: tuple[int, int], taus: list[float], frames: int, reps: int):
    """Rows ``{tau, frames, triangles, select_ms, traverse_ms, assemble_ms, rest_ms}``."""
    from render.strategies import get_strategy
    from render.strategies.jung_han import kernels as jh_kernels
    from render.strategies.jung_han import selection
    from tiler.store import open_store

    r, views = _frames(open_store(path), size, frames)
    st = get_strategy("jung-han", r, kernels="numba")
    mod = jh_kernels.resolve("numba")
    resolve = jh_kernels.resolve  # (patched while one selection is captured, then put back)
    rows = []
    try:
        for tau in taus:
            per = []
            for cam, res in views:
                st.select(cam, tau, resident=res)  # warm: trees, forest, kernels
                cap = _Capture(mod)
                selection.jh_kernels.resolve = lambda _k, c=cap: c
                try:
                    sel, _ = st.select(cam, tau, resident=res)
                finally:
                    selection.jh_kernels.resolve = resolve
                (ta,), (aa,) = cap.calls["traverse"], cap.calls["assemble"]  # one call each
                # the replayed kernels give what the selection drew (not a different frame)
                if not np.array_equal(mod.assemble(*aa)[0], sel.tri):
                    raise RuntimeError("replayed assembly differs from the selection's")
                sel_ms = _median_ms(reps, st.select, cam, tau, resident=res)
                tr_ms = _median_ms(reps, mod.traverse, *ta)
                as_ms = _median_ms(reps, mod.assemble, *aa)
                per.append((sel_ms, tr_ms, as_ms, len(sel)))
            m = [statistics.mean(p[i] for p in per) for i in range(4)]
            rows.append(
                {
                    "store": Path(path).name,
                    "size": f"{size[0]}x{size[1]}",
                    "tau": tau,
                    "frames": len(per),
                    "triangles": m[3],
                    "select_ms": m[0],
                    "traverse_ms": m[1],
                    "assemble_ms": m[2],
                    "rest_ms": m[0] - m[1] - m[2],
                    "loadavg": os.getloadavg()[0],
                }
            )
    finally:
        r.close()
    return rows


def main() -> None:
    """Measure, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("store", nargs="?", default=str(N44W072_EQC))
    ap.add_argument("--taus", default="1,2")
    ap.add_argument("--size", default="1024x768")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--out", default=str(RESULTS / "jung_han_split.json"))
    a = ap.parse_args()
    if not Path(a.store).exists():
        sys.exit(f"store {a.store} not found: `python bench/prefetch.py` makes the default one")
    size = tuple(int(v) for v in a.size.split("x"))
    rows = measure(a.store, size, [float(t) for t in a.taus.split(",")], a.frames, a.reps)
    print("store size tau triangles select_ms traverse_ms assemble_ms rest_ms load1")
    for w in rows:
        print(
            f"{w['store']} {w['size']} {w['tau']:g} {w['triangles']:.0f} {w['select_ms']:.3f} "
            f"{w['traverse_ms']:.3f} {w['assemble_ms']:.3f} {w['rest_ms']:.3f} {w['loadavg']:.2f}"
        )
    out = Path(a.out)
    out.write_text(json.dumps(portable({"machine": machine_info(), "rows": rows}), indent=1))
    print(f"# wrote {out.relative_to(REPO) if out.is_relative_to(REPO) else out}")


if __name__ == "__main__":
    main()
