"""The trade-off sweep's rows and how they are shown: :class:`TradeoffRow` (one τ of
:func:`render.pipeline.tradeoff`, the ``--json`` row), the table (:data:`TABLE_HEADER`,
:func:`format_row`) and the figure (:func:`plot_tradeoff`, :func:`tradeoff_figure`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from render import coverage
from render.strategies import DEFAULT


@dataclass(frozen=True)
class TradeoffRow:
    """One tau of the trade-off sweep (the ``--json`` row)."""

    tau: float
    metric: str
    triangles: int
    patches: int
    selection_ms: float
    frame_ms: float
    reference_frame_ms: float
    reference_triangles: int
    max_screen_error_px: float
    p99_screen_error_px: float
    mean_screen_error_px: float
    samples_in_view: int
    psnr_db: float
    changed_share: float
    crack_pixels: int  # the view's own selection, seen from the camera
    resident_bytes: int
    loaded_bytes: int
    gpu_bytes: int
    clamped: int
    strategy: str = DEFAULT
    nodata: str = "full"  # the nodata rule the view was drawn and streamed with
    used_bytes: int = 0  # level data (float32) the drawn surface reads, per block up to its level
    own_gpu_bytes: int = 0  # the strategy's own GPU buffers (meshes, quadtree textures)
    crack_pixels_above: int = 0  # the view's own selection seen from a nadir camera
    open_edges: int = 0  # drawn edges unshared and not on the outer boundary (render.cracks)
    gap_edges: int = 0  # of those, the ones whose two sides do not meet in 3-D
    max_gap_m: float = 0.0  # largest vertical opening of the drawn mesh, metres
    longest_gap_m: float = 0.0  # longest gap edge, metres
    terrain_covered: float = 1.0  # share of in-view terrain samples the drawn surface covers
    nodata_covered: float = 0.0  # share of in-view nodata samples it covers
    uncovered_px: float = 0.0  # screen distance of an uncovered terrain sample to drawn terrain
    terrain_in_view: int = 0  # in-view terrain samples (render.coverage)
    nodata_in_view: int = 0
    near_clipped_samples: int = 0  # terrain samples in the lateral view nearer than near
    #: in-view terrain samples neither the drawn nor the reference's triangles cover (isolated
    #: beside nodata): left out of terrain_in_view, terrain_covered and uncovered_px
    undrawable_samples: int = 0
    #: the stream tau whose session supplied the levels (:func:`render.pipeline.restream_taus`:
    #: a fraction of the row's when its strategy wanted levels the first session did not load)
    stream_tau: float | None = None


TABLE_HEADER = (
    f"{'tau':>5} {'metric':>12} {'triangles':>10} {'sel ms':>7} {'GPU ms':>7} {'ref ms':>7} "
    f"{'max px':>7} {'p99 px':>7} {'PSNR':>6} {'changed':>8} {'cracks':>6} {'above':>6} "
    f"{'open':>5} {'gaps':>5} {'gap m':>7} {'terrain':>7} {'nodata':>6} {'undrawn px':>10} "
    f"{'clipped':>7} {'resident MiB':>12}"
)


def format_row(r: TradeoffRow) -> str:
    """One line of the trade-off table (cracks seen from the camera and from above, open and
    gap edges, largest gap, coverage of terrain and nodata, how far undrawn terrain lies from
    drawn terrain on screen, near-clipped samples)."""
    return (
        f"{r.tau:>5g} {r.metric:>12} {r.triangles:>10,} {r.selection_ms:>7.2f} "
        f"{r.frame_ms:>7.1f} {r.reference_frame_ms:>7.1f} {r.max_screen_error_px:>7.2f} "
        f"{r.p99_screen_error_px:>7.2f} {r.psnr_db:>6.1f} {100 * r.changed_share:>7.2f}% "
        f"{r.crack_pixels:>6} {r.crack_pixels_above:>6} {r.open_edges:>5} {r.gap_edges:>5} "
        f"{r.max_gap_m:>7.2f} {coverage.percent(r.terrain_covered):>7} "
        f"{coverage.percent(r.nodata_covered):>6} "
        f"{r.uncovered_px:>10.2f} {r.near_clipped_samples:>7} {r.resident_bytes / 2**20:>12.2f}"
    )


ERROR_PANEL = "measured screen error px"


def plot_tradeoff(rows: Sequence[TradeoffRow], out: str | Path, title: str = "") -> None:
    """tau vs triangles, times, bytes, measured error and PSNR, as a PNG."""
    import matplotlib.pyplot as plt

    fig = tradeoff_figure(rows, title)
    fig.savefig(out, dpi=100)
    plt.close(fig)


def tradeoff_figure(rows: Sequence[TradeoffRow], title: str = "") -> Any:
    """The matplotlib figure of :func:`plot_tradeoff` (six panels; the error panel carries
    the ``y = tau`` line the measured error is read against)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 3, figsize=(13, 7))
    for metric in sorted({r.metric for r in rows}):
        rs = sorted((r for r in rows if r.metric == metric), key=lambda r: r.tau)
        t = [r.tau for r in rs]
        panels = [
            ("triangles", [r.triangles for r in rs]),
            ("CPU selection ms", [r.selection_ms for r in rs]),
            ("GPU frame ms (LOD)", [r.frame_ms for r in rs]),
            ("resident MiB", [r.resident_bytes / 2**20 for r in rs]),
            (ERROR_PANEL, [r.max_screen_error_px for r in rs]),
            ("PSNR dB vs full res", [r.psnr_db for r in rs]),
        ]
        for a, (name, ys) in zip(ax.ravel(), panels, strict=True):
            a.plot(t, ys, "o-", label=f"{metric}" + (" max" if "error" in name else ""))
            if "error" in name:
                a.plot(t, [r.p99_screen_error_px for r in rs], "s--", label=f"{metric} p99")
            a.set_xscale("log", base=2)
            a.set_xlabel("tau (px)")
            a.set_title(name)
    taus = sorted({r.tau for r in rows})
    for a in ax.ravel():
        if a.get_title() == ERROR_PANEL:  # the bound the measured error is read against
            a.plot(taus, taus, "k:", label="tau")
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.suptitle(title or "speed / accuracy trade-off")
    fig.tight_layout()
    return fig


def finite(x: float) -> float | None:
    """JSON-safe float (None for NaN/inf)."""
    return x if math.isfinite(x) else None
