"""LOD strategies side by side on the same fly-through (issue #5).

Runs :func:`render.strategies.compare.compare` (see its docstring for what is measured) on each
store given, prints the table and writes ``bench/results/lod_compare.json`` and
``bench/results/lod_compare_<store>.png`` (triangles vs measured error: the Pareto front);
``--quick`` writes ``lod_compare_quick*`` instead.

Usage: python bench/lod_compare.py [STORE ...] [--quick] [--taus 0.5,1,2,4]
       [--frames 8] [--size 1024x768] [--lods a,b] [--view default|low] [--pop-steps 8]
       [--metric qiu|conservative|conservative-view]
``--view low``: the default path's cameras lowered to ``--clearance`` (default 150) metres
above the highest terrain within 2 block edges and pitched ``--pitch`` (default -8) degrees: a
low oblique view over rough terrain, where τ changes the selection at every τ listed (the
script prints a ``# unchanged`` line for every strategy and pair of τ where it does not).
Default stores: the synthetic 4097^2 store, the real N44W072 store and Longyearbyen (with
nodata) of BENCHMARKS.md, made on first use (``bench.common.ensure_store``; a store that cannot
be made, e.g. without the shared data, is skipped with a message).
After each store a ``# tau T:`` line per τ sets qiu (the default path, with ``--metric``)
beside the cheapest strategy whose measured max error stays ≤ τ (issue 12). The Markdown tables
of BENCHMARKS.md go to ``lod_compare<tag>.md`` beside the JSON (``--markdown-from JSON`` prints
them again from a run's JSON).
``--quick``: 256x192, 4 frames, taus 1 and 4 (a smoke run; under 2 minutes on a small store).
Same as ``terrastream compare STORE --json ... --plot ...`` per store.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import (  # noqa: E402
    LONGYEARBYEN,
    N44W072_EQC,
    RESULTS,
    S4097,
    ensure_store,
    machine_info,
    portable,
)
from render.strategies.compare import HEADER, compare, plot_pareto  # noqa: E402
from streamer.camera import Camera  # noqa: E402
from streamer.run import make_path, store_height_fn  # noqa: E402
from tiler.store import open_store  # noqa: E402

DEFAULT_STORES = [str(S4097), str(N44W072_EQC), str(LONGYEARBYEN)]


def low_oblique(store, cams: list[Camera], clearance: float, pitch: float) -> list[Camera]:
    """``cams`` moved down to ``clearance`` above the highest terrain near them (the store's
    level k-4 sampled within two block edges), pitched ``pitch`` degrees."""
    g = store.grid
    fn = store_height_fn(store)
    reach = 2 * g.step * g.dx
    out = []
    for c in cams:
        x, y = c.position[0], c.position[1]
        pts = np.linspace(-reach, reach, 9)
        top = max(fn(x + dx, y + dy) for dx in pts for dy in pts)
        z = top + clearance
        out.append(replace(c, position=(x, y, z), pitch=pitch, near=max(0.5, clearance / 50)))
    return out


def unchanged_taus(rows: list[dict], taus: list[float]) -> list[str]:
    """``# unchanged`` lines: per strategy, consecutive τ whose middle view drew the same
    triangle count (the selection did not change)."""
    lines = []
    for name in sorted({r["strategy"] for r in rows}):
        rs = {r["tau"]: r["triangles"] for r in rows if r["strategy"] == name}
        for a, b in zip(taus, taus[1:], strict=False):
            if a in rs and b in rs and rs[a] == rs[b]:
                lines.append(
                    f"# unchanged: {name} draws {rs[a]:,} triangles at tau {a:g} and {b:g}"
                )
    return lines


def cheapest_within(rows: list[dict], default: str = "qiu") -> list[dict]:
    """Per τ: the ``default`` strategy's row beside the cheapest row (fewest middle-view
    triangles) whose measured max error is ≤ τ; ``None`` when no row stays ≤ τ."""
    out = []
    for tau in sorted({r["tau"] for r in rows}):
        at = [r for r in rows if r["tau"] == tau]
        d = next((r for r in at if r["strategy"] == default), None)
        ok = [r for r in at if r["max_screen_error_px"] <= tau]
        best = min(ok, key=lambda r: r["triangles"]) if ok else None
        out.append({"tau": tau, "default": d, "cheapest_within_tau": best})
    return out


def cheapest_lines(summary: list[dict], label: str) -> list[str]:
    """``# default vs cheapest <= tau`` lines for :func:`cheapest_within`'s result."""
    lines = []
    for s in summary:
        d, b = s["default"], s["cheapest_within_tau"]
        left = (
            f"{label} {d['triangles']:,} tris at {d['max_screen_error_px']:.2f} px"
            if d
            else f"{label} not run"
        )
        right = (
            f"cheapest <= tau: {b['strategy']} {b['triangles']:,} tris at "
            f"{b['max_screen_error_px']:.2f} px"
            if b
            else "no strategy stays <= tau"
        )
        lines.append(f"# tau {s['tau']:g}: {left}; {right}")
    return lines


MD_HEAD = (
    "| strategy | τ | tris/frame (mid view) | CPU ms | GPU ms | max / p99 / mean px | cracks "
    "| above | open | gaps | gap m | terrain | nodata | clipped | pop path px (LOD frames) "
    "| pop dolly px (LOD frames) | data MiB | own MiB |"
)


def _pop_md(r: dict, motion: str) -> str:
    px = r[f"popping_{motion}_px"]  # (None: the motion had no pair of frames)
    return (
        f"{'n/a' if px is None else format(px, '.2f')} "
        f"({r[f'popping_{motion}_lod_frames']}/{r[f'popping_{motion}_frames']})"
    )


def markdown(results: dict[str, list[dict]], metric: str = "qiu") -> str:
    """The BENCHMARKS.md tables of a run: one per store, then the default path (qiu with
    ``metric``) beside the cheapest strategy ≤ τ."""
    out = []
    for path, rows in results.items():
        out += [f"`{Path(path).name}`:", "", MD_HEAD, "|" + "---|" * 18]
        for r in rows:
            out.append(
                f"| {r['strategy']} | {r['tau']:g} | {r['fly_triangles']:,.0f} "
                f"({r['triangles']:,}) | {r['fly_cpu_ms']:.2f} | {r['fly_gpu_ms']:.1f} | "
                f"{r['max_screen_error_px']:.2f} / {r['p99_screen_error_px']:.2f} / "
                f"{r['mean_screen_error_px']:.3f} | {r['crack_pixels']} | "
                f"{r['crack_pixels_above']} | {r['open_edges']} | {r['gap_edges']} | "
                f"{r['max_gap_m']:.2f} | {100 * r['terrain_covered']:.1f} % | "
                f"{100 * r['nodata_covered']:.1f} % | {r['near_clipped_samples']} | "
                f"{_pop_md(r, 'path')} | {_pop_md(r, 'dolly')} | "
                f"{r['used_bytes'] / 2**20:.2f} | {r['own_gpu_bytes'] / 2**20:.2f} |"
            )
        out.append("")
        out += [
            line.lstrip("# ") for line in cheapest_lines(cheapest_within(rows), f"qiu ({metric}):")
        ]
        out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stores", nargs="*", default=DEFAULT_STORES)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--taus", default="0.5,1,2,4")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", default="1024x768")
    ap.add_argument("--lods", default=None, help="comma-separated strategies (default: all)")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--view", choices=("default", "low"), default="default")
    ap.add_argument("--clearance", type=float, default=150.0)
    ap.add_argument("--pitch", type=float, default=-8.0)
    ap.add_argument("--pop-steps", type=int, default=8)
    ap.add_argument(
        "--markdown-from",
        default=None,
        metavar="JSON",
        help="only print the Markdown tables of an earlier run's JSON",
    )
    ap.add_argument(
        "--metric",
        default="qiu",
        help="qiu's screen-error metric for every strategy that uses one (qiu, conservative, "
        "conservative-view); the output files get a _<metric> tag unless it is qiu",
    )
    a = ap.parse_args(argv)
    if a.markdown_from:
        print(markdown(json.loads(Path(a.markdown_from).read_text()), a.metric))
        return 0
    from render.strategies import warm_up_kernels

    warm_up_kernels()  # the compiled CPU kernels, as the viewer uses them after warming up
    taus = [1.0, 4.0] if a.quick else [float(t) for t in a.taus.split(",")]
    frames = 4 if a.quick else a.frames
    w, h = (256, 192) if a.quick else tuple(int(v) for v in a.size.split("x"))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    lods = a.lods.split(",") if a.lods else None
    tag = ("_quick" if a.quick else "") + ("_low" if a.view == "low" else "")
    tag += "" if a.metric == "qiu" else f"_{a.metric.replace('-', '_')}"
    for path in a.stores:
        ensure_store(path)  # the default stores are made on first use
        if not Path(path).exists():
            print(f"# skipping {path}: not found (see BENCHMARKS.md for how to make it)")
            continue
        s = open_store(path)
        cams = make_path(s, "default", frames=frames, viewport=(w, h))
        if a.view == "low":
            cams = low_oblique(s, cams, a.clearance, a.pitch)
        print(f"# {path} {w}x{h}, {frames} frames, view {a.view}, pop steps {a.pop_steps}")
        print(f"# middle camera {cams[len(cams) // 2]}")
        print(HEADER)
        t0 = time.perf_counter()
        rows = compare(
            s, cams, taus, strategies=lods, metric=a.metric, pop_steps=a.pop_steps, log=print
        )
        for line in unchanged_taus(rows, taus):
            print(line)
        for line in cheapest_lines(cheapest_within(rows), f"qiu ({a.metric}):"):
            print(line)
        print(f"# {time.perf_counter() - t0:.0f} s")
        name = Path(path).name.split(".")[0]
        plot_pareto(rows, out / f"lod_compare{tag}_{name}.png", title=f"{name} {w}x{h}")
        results[portable(str(path))] = rows  # keys name no machine's paths
    if not results:
        print("error: no store was measured (see the # skipping lines)", file=sys.stderr)
        return 1
    js = out / f"lod_compare{tag}.json"
    js.write_text(json.dumps(portable(results), indent=1))
    (out / f"lod_compare{tag}.md").write_text(markdown(results, a.metric))
    (out / f"lod_compare{tag}_machine.json").write_text(
        json.dumps(portable(machine_info()), indent=1)
    )
    print(f"wrote {js}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
