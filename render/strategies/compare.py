"""Side-by-side comparison of the registered LOD strategies (``terrastream compare``,
``bench/lod_compare.py``).

For each strategy and τ: the renderer's trade-off row (:func:`render.pipeline.tradeoff`) for
the *middle* camera of the fly-through (measured max/p99 screen error against the
full-resolution reference, each sample once; PSNR; crack pixels of the view's own selection from
the camera and from above; open/gap edges of the drawn mesh; terrain/nodata coverage; bytes
resident / on the GPU; docs/RENDER.md "Measurements"), plus
fly-through means over every camera of the path (triangles, CPU selection ms, GPU ms; every
frame's data is waited for, so all strategies see the same resident levels) and **popping**.
The data is streamed at full resolution (a τ = 0 session: every block in view at level ``k``)
so that no strategy is held back by the levels Qiu's metric would have loaded; ``used_bytes``
is what each strategy's drawn surface actually reads (per block the level data up to the
finest level it draws, :meth:`Strategy.used_levels`), ``own_gpu_bytes`` its own GPU buffers.
Popping (:func:`popping`) over camera moves that cross LOD changes: ``path`` — consecutive
cameras of the fly-through itself around its middle (forward motion at the fly-through speed),
and ``dolly`` — the middle camera moved slowly forward along its view direction across a
quarter of the depth of the view centre (nodes split on the way: Eq. 7's split distance is
proportional to the distance). Per motion, ``popping_<motion>_px`` is the largest screen
displacement (seen from the later camera) of the drawn surface at any full-resolution sample
drawn in both frames, i.e. the jump caused by the LOD change alone (None, "n/a" in the table,
for a motion with no pair of frames: a one-camera path), and
``popping_<motion>_lod_frames`` how many of the frames changed the drawn surface's height at a
sample drawn in both and in the later camera's view (a LOD change on screen; samples entering
or leaving the view, and changes off screen, do not count; a row with 0 LOD frames says
nothing about popping). ``popping_px`` is the larger of the two measured. The table shows the
middle camera's ``triangles`` (``mid tris``) beside its errors and the fly-through means
(``fly tris``, ``fly CPU ms``, ``fly GPU ms``) in their own columns; the JSON rows' and the
Pareto plot's ``triangles`` are the middle camera's too.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from render import coverage, measure
from render.errors import EmptyViewError
from render.pipeline import ViewOptions, open_render_session, session_patch_log2, tradeoff
from render.renderer import RenderConfig, TerrainRenderer
from render.step import frame_step, stream_step
from render.strategies import check_nodata, get_strategy, nodata_options, strategy_names
from render.strategies.base import Strategy
from streamer.camera import Camera
from streamer.clip import warn_path_below_ground
from tiler.store import TerrainStore

_log = logging.getLogger(__name__)


def shifted(camera: Camera, depth: float) -> Camera:
    """The camera moved along its right vector by one pixel's worth at ``depth``."""
    step = depth / camera.focal_px
    pos = np.asarray(camera.position, dtype=np.float64) + step * camera.right
    return replace(camera, position=tuple(float(v) for v in pos))


def dolly(camera: Camera, distance: float, steps: int) -> list[Camera]:
    """``steps + 1`` cameras from ``camera`` moving ``distance`` forward along its view."""
    f = np.asarray(camera.forward, dtype=np.float64)
    p0 = np.asarray(camera.position, dtype=np.float64)
    return [
        replace(camera, position=tuple(float(v) for v in p0 + (distance * i / steps) * f))
        for i in range(steps + 1)
    ]


@dataclass(frozen=True)
class Popping:
    """Popping over a camera motion: the largest surface jump (px per frame; None when the
    motion has no pair of frames to compare), the frames whose drawn surface changed
    (``lod_frames``) and the frames compared."""

    max_px: float | None
    lod_frames: int
    frames: int


def popping(
    strat: Strategy,
    cams: Sequence[Camera],
    tau: float,
    metric: str,
    prepare: Callable[[Camera], None] | None = None,
) -> Popping:
    """Largest screen displacement (px, seen by the later camera) of the drawn surface at
    samples drawn in both frames, over consecutive pairs of ``cams``, and how many pairs
    changed the drawn height at a sample drawn in both and in the later camera's view (culling
    alone and changes off screen do not count).
    ``prepare(cam)`` runs before each selection (e.g. streaming its data in). With fewer than
    two cameras nothing is compared: ``max_px`` is None, not a measured 0."""
    prev = None
    worst, changed = 0.0, 0
    for cam in cams:
        if prepare:
            prepare(cam)
        sel, _ = strat.select(cam, tau, metric)
        surf = strat.surface(cam, sel)
        if prev is not None and not _same(prev, surf):
            rows, cols, ha, hb = common_samples(prev, surf)
            moved = ha != hb  # equal drawn heights do not move on screen
            # only a sample drawn in both frames at another height, in the later camera's
            # view, is a LOD change: samples entering or leaving the view (culling) are not,
            # nor are changes off screen (pixel_errors keeps the samples in view)
            x, y = strat.r.grid.sample_xy(rows[moved], cols[moved])
            d = measure.pixel_errors(cam, x, y, ha[moved], hb[moved])
            changed += int(d.size > 0)
            if d.size:
                worst = max(worst, float(d.max()))
        prev = surf
    pairs = max(0, len(cams) - 1)
    return Popping(worst if pairs else None, changed, pairs)


def _same(a, b) -> bool:
    """The two surfaces are the same arrays (the usual case when no LOD changed)."""
    return all(x.shape == y.shape for x, y in zip(a, b, strict=True)) and all(
        np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b, strict=True)
    )


#: above this many samples in the surfaces' bounding box, samples are matched by sorting
DENSE_LIMIT = 1 << 26


def common_samples(
    a: tuple[np.ndarray, np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, height in a, height in b)`` at the samples two surfaces (``(rows, cols,
    heights)``, see :meth:`Strategy.surface`) both draw; NaN heights are not drawn."""
    (r0, c0, h0), (r1, c1, h1) = a, b
    ok0, ok1 = np.isfinite(h0), np.isfinite(h1)
    r0, c0, h0, r1, c1, h1 = r0[ok0], c0[ok0], h0[ok0], r1[ok1], c1[ok1], h1[ok1]
    if not (r0.size and r1.size):
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros(0), np.zeros(0)
    rmin, cmin = min(r0.min(), r1.min()), min(c0.min(), c1.min())
    nr = int(max(r0.max(), r1.max()) - rmin + 1)
    nc = int(max(c0.max(), c1.max()) - cmin + 1)
    k0 = (r0 - rmin) * nc + (c0 - cmin)
    k1 = (r1 - rmin) * nc + (c1 - cmin)
    if nr * nc <= DENSE_LIMIT:
        dense = np.full(nr * nc, np.nan)
        dense[k0] = h0
        ha = dense[k1]
        both = np.isfinite(ha)  # a sample drawn twice in b is kept twice (max is unchanged)
        keys, ha, hb = k1[both], ha[both], h1[both]
    else:
        keys0, i0 = np.unique(k0, return_index=True)
        keys1, i1 = np.unique(k1, return_index=True)
        keys, a0, a1 = np.intersect1d(keys0, keys1, assume_unique=True, return_indices=True)
        ha, hb = h0[i0[a0]], h1[i1[a1]]
    return keys // nc + rmin, keys % nc + cmin, ha, hb


def compare(
    store: TerrainStore,
    cameras: Sequence[Camera],
    taus: Sequence[float],
    *,
    strategies: Sequence[str] | None = None,
    metric: str = "qiu",
    patch_log2: int = 4,
    repeats: int = 1,
    pop_steps: int = 8,
    log: Callable[[str], None] | None = None,
    options: ViewOptions | None = None,
) -> list[dict[str, Any]]:
    """One row per strategy and τ (the tradeoff keys plus fly-through means and popping);
    ``options``, when given, supplies ``metric``, ``patch_log2`` and the nodata rule, which
    every strategy compared must take (its ``lod`` and ``tau`` are not used: ``strategies``
    and ``taus`` are swept)."""
    o = options or ViewOptions(metric=metric, patch_log2=patch_log2)
    metric = o.metric
    names = list(strategies or strategy_names())
    for name in names:
        check_nodata(name, o.nodata)
    warn_path_below_ground(store, cameras, "they show the terrain from below", _log)
    r = TerrainRenderer(store, RenderConfig(size=cameras[0].viewport, patch_log2=o.patch_log2))
    i_mid = len(cameras) // 2
    mid = cameras[i_mid]
    zlo, zhi = r.terrain_zrange
    f = mid.forward
    t = (0.5 * (zlo + zhi) - mid.eye[2]) / f[2] if f[2] < -1e-6 else 1000.0
    depth = max(float(t), mid.near)
    lo = max(0, min(i_mid - pop_steps // 2, len(cameras) - pop_steps - 1))
    motions = {
        "path": list(cameras[lo : lo + pop_steps + 1]),
        "dolly": dolly(mid, 0.25 * depth, pop_steps),
    }
    rows: list[dict[str, Any]] = []
    for name in names:
        strat = get_strategy(name, r, **nodata_options(name, o.nodata))
        for tau in taus:
            try:
                tr = tradeoff(
                    store, mid, [tau], renderer=r, repeats=repeats, stream_tau=0.0,
                    options=replace(o, lod=name),
                )  # fmt: skip
            except EmptyViewError as exc:
                raise EmptyViewError(
                    f"{exc} (compare measures the camera path's middle frame, {i_mid} of "
                    f"{len(cameras)}: give a path whose middle frame sees the DEM)"
                ) from None
            row = asdict(tr[0])
            tri, cpu, gpu = [], [], []
            sp = session_patch_log2(strat, r)  # (chunk-tessellation: its chunks)
            with open_render_session(store, 0.0, metric, sp, nodata=o.nodata) as s:
                for cam in cameras:
                    step = frame_step(s, strat, cam, tau, metric)
                    tri.append(step.stats.triangles)
                    cpu.append(step.selection_ms)
                    gpu.append(step.stats.frame_ms)

                def prepare(cam: Camera, s=s) -> None:
                    stream_step(s, r, cam)

                pops = {m: popping(strat, c, tau, metric, prepare) for m, c in motions.items()}
            for m, pop in pops.items():
                row[f"popping_{m}_px"] = pop.max_px
                row[f"popping_{m}_lod_frames"] = pop.lod_frames
                row[f"popping_{m}_frames"] = pop.frames
            measured = [p.max_px for p in pops.values() if p.max_px is not None]
            row.update(
                strategy=name,
                popping_px=max(measured) if measured else None,
                popping_steps=pop_steps,
                fly_frames=len(cameras),
                fly_triangles=float(np.mean(tri)),
                fly_cpu_ms=float(np.mean(cpu)),
                fly_gpu_ms=float(np.mean(gpu)),
            )
            rows.append(row)
            if log:
                log(format_row(row))
    r.close()
    return rows


#: the table's columns, (label, width): ``mid tris`` to ``clipped`` are the middle camera's
#: (the JSON row's ``triangles`` and tradeoff figures, which the plot shows too), ``fly tris``,
#: ``fly CPU ms`` and ``fly GPU ms`` the means over every camera of the fly-through
#: (``fly_triangles``, ``fly_cpu_ms``, ``fly_gpu_ms``), then popping and bytes
COLUMNS: tuple[tuple[str, int], ...] = (
    ("strategy", 20), ("tau", 5), ("mid tris", 9), ("max px", 7), ("p99 px", 7),
    ("mean px", 7), ("cracks", 6), ("above", 6), ("open", 5), ("gaps", 5), ("gap m", 7),
    ("terrain", 7), ("nodata", 6), ("undrawn px", 10), ("clipped", 7), ("fly tris", 9),
    ("fly CPU ms", 10), ("fly GPU ms", 10), ("pop path", 13), ("pop dolly", 13),
    ("data MiB", 8), ("own MiB", 7),
)  # fmt: skip

HEADER = " ".join(f"{label:>{w}}" for label, w in COLUMNS)


def _pop(row: dict[str, Any], m: str) -> str:
    """``px (LOD frames/frames)`` of motion ``m``; ``n/a`` for the px of a motion with no
    pair of frames (nothing was measured)."""
    px = row.get(f"popping_{m}_px")
    shown = "n/a" if px is None else f"{px:.2f}"
    return f"{shown} ({row.get(f'popping_{m}_lod_frames', 0)}/{row.get(f'popping_{m}_frames', 0)})"


def table_cells(row: dict[str, Any]) -> dict[str, str]:
    """The table's cells of one row, by :data:`COLUMNS` label (unpadded)."""
    cells = (
        row["strategy"], f"{row['tau']:g}", f"{row['triangles']:,}",
        f"{row['max_screen_error_px']:.2f}", f"{row['p99_screen_error_px']:.2f}",
        f"{row['mean_screen_error_px']:.3f}", f"{row['crack_pixels']}",
        f"{row['crack_pixels_above']}", f"{row['open_edges']}", f"{row['gap_edges']}",
        f"{row['max_gap_m']:.2f}", coverage.percent(row["terrain_covered"]),
        coverage.percent(row["nodata_covered"]), f"{row.get('uncovered_px', 0.0):.2f}",
        f"{row['near_clipped_samples']}", f"{row['fly_triangles']:,.0f}",
        f"{row['fly_cpu_ms']:.2f}", f"{row['fly_gpu_ms']:.1f}", _pop(row, "path"),
        _pop(row, "dolly"), f"{row['used_bytes'] / 2**20:.2f}",
        f"{row['own_gpu_bytes'] / 2**20:.2f}",
    )  # fmt: skip
    return dict(zip((label for label, _ in COLUMNS), cells, strict=True))


def format_row(row: dict[str, Any]) -> str:
    """One line of the comparison table: the middle camera's triangles beside its errors, the
    fly-through means in their own columns (popping: largest jump px (LOD-changing frames /
    frames) per motion, ``n/a`` px for a motion with no pair of frames)."""
    cells = table_cells(row)
    return " ".join(f"{cells[label]:>{w}}" for label, w in COLUMNS)


def pareto_front(points: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points ``(error, triangles)`` no other point beats on both (fewer or equal triangles
    at lower or equal error), sorted by error; a point with no error measured (NaN: nothing
    drawn in view) is on no front."""
    front: list[tuple[float, float]] = []
    for e, t in sorted(p for p in points if p[0] == p[0]):
        if not front or t < front[-1][1]:
            front.append((e, t))
    return front


#: one marker per strategy in :func:`plot_pareto`
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def plot_pareto(rows: Sequence[dict[str, Any]], out: str | Path, title: str = "") -> None:
    """Triangles of the middle camera (the JSON rows' ``triangles``, the table's ``mid
    tris``) vs its measured max and p99 error, per strategy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
    for i, name in enumerate(sorted({r["strategy"] for r in rows})):
        rs = sorted((r for r in rows if r["strategy"] == name), key=lambda r: r["tau"])
        # a marker each, open and shrinking: strategies that select alike (chunk-tessellation
        # and its GPU selection) stay visible where their points coincide
        style = {"marker": MARKERS[i % len(MARKERS)], "ms": max(4, 10 - i), "mfc": "none"}
        for a, key in zip(ax, ("max_screen_error_px", "p99_screen_error_px"), strict=True):
            a.plot([r[key] for r in rs], [r["triangles"] for r in rs], "-", label=name, **style)
            for r in rs:
                a.annotate(f"τ={r['tau']:g}", (r[key], r["triangles"]), fontsize=7)
    for a, key in zip(ax, ("max_screen_error_px", "p99_screen_error_px"), strict=True):
        front = pareto_front([(r[key], r["triangles"]) for r in rows])
        if front:
            xs, ys = zip(*front, strict=True)
            a.step(xs, ys, "k--", where="post", lw=1, alpha=0.5, label="Pareto front")
    for a, lab in zip(ax, ("measured max error px", "measured p99 error px"), strict=True):
        a.set_xlabel(lab)
        a.set_ylabel("triangles (middle camera)")
        a.set_yscale("log")
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle(title or "triangles vs measured screen error (lower left is better)")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
