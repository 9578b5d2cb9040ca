"""Rendering with a streaming session: single views and the tau trade-off sweep (fly-throughs:
:mod:`render.flythrough`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from render import coverage, cracks, measure
from render.errors import EmptyViewError, RenderError
from render.frame_types import check_patch_log2
from render.measure import heights_fn as heights_fn  # re-exported (moved there)
from render.renderer import CLEAR, RenderConfig, RenderStats, TerrainRenderer
from render.select import Patches, check_tau, coarse_leaves, uncounted_clamps
from render.step import frame_step, stream_step
from render.step import resident_levels as resident_levels  # re-exported
from render.strategies import (
    DEFAULT,
    check_name,
    check_nodata,
    error_label,
    get_strategy,
    nodata_options,
    stream_metric,
)
from render.strategies.base import DrawOptions
from render.strategies.chunk_tess import ChunkTessellation, GpuChunks, start_depth
from render.strategies.qiu import QiuStrategy, patch_counts, select_clod
from render.views import ground_note, no_pixel_cause, terrain_cells
from streamer.camera import Camera
from streamer.lod import get_metric
from streamer.session import Session, open_session
from tiler.layout import grid_side, level_size
from tiler.store import TerrainStore

Block = tuple[int, int]


def _budget_mb(store: TerrainStore) -> float:
    """A budget that holds every block at full resolution (the reference needs that)."""
    per = sum(level_size(i) for i in range(store.k + 1)) * store.dtype.itemsize
    return max(64.0, 1.2 * per * len(store.blocks()) / 2**20)


def open_render_session(
    store: TerrainStore,
    tau: float,
    metric: str,
    patch_log2: int,
    *,
    workers: int = 0,
    budget_mb: float | None = None,
    prefetch: bool = False,
    nodata: str = "full",
) -> Session:
    """A session that loads what the renderer's frustum-hull culling sees, planned with the
    renderer's nodata rule (:data:`streamer.nodata.NODATA_RULES`)."""
    return open_session(
        store,
        budget_mb=budget_mb or _budget_mb(store),
        workers=workers,
        tau=tau,
        metric=metric,
        patch_log2=patch_log2,
        culling="hull",
        prefetch=prefetch,
        nodata=nodata,
    )


@dataclass(frozen=True)
class ViewOptions:
    """What the rendering commands pass down as one value (instead of keyword relays): the
    strategy, τ and metric it selects with, the patch size, how frames are drawn, and the
    nodata rule (:data:`streamer.nodata.NODATA_RULES`: the strategy's and its session's; a
    strategy that does not take it is a :class:`render.strategies.NodataRuleError`)."""

    lod: str = DEFAULT
    tau: float = 1.0
    metric: str = "qiu"
    patch_log2: int = 4
    wireframe: bool = False
    lod_colour: bool = False
    nodata: str = "full"

    def __post_init__(self) -> None:
        check_name(self.lod)
        check_nodata(self.lod, self.nodata)
        # (a bad value failed later, in the selection or the shaders, unnamed)
        tau = self.tau
        if isinstance(tau, bool) or not isinstance(tau, (int, float, np.integer, np.floating)):
            raise RenderError(f"tau must be a number of pixels, got {tau!r}")
        if not (math.isfinite(tau) and tau >= 0):
            raise RenderError(f"tau must be a finite number of pixels >= 0, got {tau!r}")
        get_metric(self.metric)  # (StreamerError naming the metric and the known ones)
        check_patch_log2(self.patch_log2)

    def strategy_options(self) -> dict[str, str]:
        """The strategy's constructor options these imply (the nodata rule)."""
        return nodata_options(self.lod, self.nodata)

    def draw_options(self) -> DrawOptions:
        """The :class:`DrawOptions` of these options."""
        return DrawOptions(wireframe=self.wireframe, lod_colour=self.lod_colour)


def draw_timed(
    renderer: Any, camera: Camera, patches: Any, repeats: int = 1, **kw: Any
) -> RenderStats:
    """Draw ``repeats`` times and keep the fastest frame time (llvmpipe timings are noisy).

    ``renderer`` is a :class:`TerrainRenderer` or a strategy (anything with ``draw``)."""
    best = None
    for _ in range(max(1, repeats)):
        st = renderer.draw(camera, patches, **kw)
        if best is None or st.frame_ms < best.frame_ms:
            best = st
    assert best is not None
    return best


#: a one-shot view whose strategy clamps (wants levels the session streamed with
#: :func:`render.strategies.stream_metric` did not load: seamless-patches' and
#: geometry-splitting's own split rules, jung-han's) is streamed again at these fractions of its
#: stream tau; the last (0) loads every block in view at full resolution
RESTREAM = (0.5, 0.25, 0.0)


def session_patch_log2(strategy: Any, renderer: TerrainRenderer) -> int:
    """The node size a view's session plans levels with: a chunk-tessellation strategy's
    chunks (``2**c`` cells; the renderer's smaller patches would load levels coarser than its
    chunks, which it would then draw below their own level), else the renderer's patches."""
    if isinstance(strategy, ChunkTessellation):
        return int(strategy.c)
    return int(renderer.p)


def unmet_leaves(
    strategy: Any, camera: Camera, tau: float, sel: Any, resident: Mapping[Block, int]
) -> int:
    """Leaves of ``sel`` drawn from a level coarser than their own node level that the
    strategy's clamped count leaves out (:func:`render.select.uncounted_clamps`; the patches of
    ``qiu`` and ``chunk-tessellation``, 0 for the other strategies)."""
    k = strategy.r.k
    if isinstance(strategy, ChunkTessellation):
        pt, p, md = strategy.patches(sel), strategy.c, 0
        if isinstance(sel, GpuChunks) and coarse_leaves(pt, k, p).any():
            # the read-back has no rho: the CPU twin's (the same chunks) at the GPU's start
            pt, md = strategy.select_twin(camera, tau, dict(resident)), start_depth(k, p)
    elif isinstance(strategy, QiuStrategy) and isinstance(sel, Patches):
        pt, p, md = sel, strategy.r.p, 0
    else:
        return 0
    return uncounted_clamps(pt, k, p, tau, md)


def restream_taus(tau: float) -> list[float]:
    """The stream taus a one-shot view tries in turn: ``tau``, then :data:`RESTREAM`'s
    fractions of it while the strategy still clamps."""
    return [tau] + [f * tau for f in RESTREAM if tau > 0]


def render_view(
    store: TerrainStore,
    camera: Camera,
    *,
    tau: float = 1.0,
    metric: str = "qiu",
    patch_log2: int = 4,
    wireframe: bool = False,
    lod_colour: bool = False,
    renderer: TerrainRenderer | None = None,
    lod: str = DEFAULT,
    options: ViewOptions | None = None,
) -> tuple[np.ndarray, RenderStats]:
    """Stream what the view needs (waiting for it) and render it once with strategy ``lod``
    (``options``, when given, replaces the keyword settings)."""
    o = options or ViewOptions(lod, tau, metric, patch_log2, wireframe, lod_colour)
    if renderer is None:  # made here, so closed here (else its context stays current)
        r = TerrainRenderer(store, RenderConfig(size=camera.viewport, patch_log2=o.patch_log2))
        try:
            return render_view(store, camera, renderer=r, options=o)
        finally:
            r.close()
    r = renderer
    strat = get_strategy(o.lod, r, **o.strategy_options())
    metric = stream_metric(o.lod, o.metric)
    p = session_patch_log2(strat, r)
    for st_tau in restream_taus(o.tau):  # once, unless the strategy wants unloaded levels
        with open_render_session(store, st_tau, metric, p, nodata=o.nodata) as session:
            step = frame_step(session, strat, camera, o.tau, o.metric, options=o.draw_options())
        clamped = step.stats.clamped + unmet_leaves(
            strat, camera, o.tau, step.selection, step.resident
        )
        if not clamped:
            break
    return r.image(), replace(step.stats, drawn_px=r.drawn_pixels(), clamped=clamped)


def nadir_for(camera: Camera, zmid: float) -> Camera:
    """A straight-down camera over the point the view centre looks at (for crack counting)."""
    f = camera.forward
    eye = camera.eye
    t = (zmid - eye[2]) / f[2] if f[2] < -1e-6 else 0.0
    gx, gy = (eye[:2] + t * f[:2]) if t > 0 else eye[:2]
    h = max(abs(eye[2] - zmid), 1.0)
    return Camera(
        (gx, gy, zmid + h),
        pitch=-90.0,
        fov_y=camera.fov_y,
        viewport=camera.viewport,
        near=camera.near,
        far=camera.far,
    )


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
    #: the stream tau whose session supplied the levels (:func:`restream_taus`: a fraction of
    #: the row's when its strategy wanted levels the first session did not load)
    stream_tau: float | None = None


def tradeoff(
    store: TerrainStore,
    camera: Camera,
    taus: Sequence[float],
    *,
    metric: str = "qiu",
    patch_log2: int = 4,
    repeats: int = 3,
    renderer: TerrainRenderer | None = None,
    log: Callable[[str], None] | None = None,
    lod: str = DEFAULT,
    stream_tau: float | None = None,
    options: ViewOptions | None = None,
    lod_options: Mapping[str, Any] | None = None,
) -> list[TradeoffRow]:
    """Render the view at every tau with strategy ``lod`` and at full resolution (the CLOD
    reference mesh); measure cost, error (each sample once), cracks of the view's own selection
    (from the camera and from above), the drawn mesh's watertightness and coverage
    (docs/RENDER.md, "Measurements"; :class:`render.errors.EmptyViewError` for a view without
    terrain). The data is streamed by the renderer's session at
    ``stream_tau`` (default: each tau; 0 loads every block in view at full resolution) with
    :func:`render.strategies.stream_metric`. ``options``, when given, supplies ``lod``,
    ``metric``, ``patch_log2`` and the nodata rule (its ``tau`` is not used: ``taus`` are
    swept); ``lod_options`` are the strategy's other constructor options (e.g.
    ``{"rho": "paper"}``)."""
    o = options or ViewOptions(lod=lod, metric=metric, patch_log2=patch_log2)
    lod, metric = o.lod, o.metric
    for t in taus:  # before the reference's work: finite taus only (check_tau says why)
        check_tau(t)
    if renderer is None:  # made here, so closed here (else its context stays current)
        r = TerrainRenderer(store, RenderConfig(size=camera.viewport, patch_log2=o.patch_log2))
        try:
            return tradeoff(store, camera, taus, repeats=repeats, renderer=r, log=log,
                            stream_tau=stream_tau, options=o, lod_options=lod_options)  # fmt: skip
        finally:
            r.close()
    r = renderer
    # planned with nodes of the whole block (patch_log2 = k): every block in view at level k,
    # whatever its stored errors (a tau-0 plan stops where they are 0)
    with open_render_session(store, 0.0, metric, r.k) as ref_session:
        ref_res = stream_step(ref_session, r, camera)[1]
    ref_p, _ = r.select(camera, 0.0, metric, resident=ref_res, full=True)
    if ref_p.clamped:
        raise RenderError(
            f"the full-resolution reference is not: {ref_p.clamped:,} of its nodes are capped "
            "by the levels its session loaded"
        )
    ref_st = draw_timed(r, camera, ref_p, repeats)
    ref_img = r.image()
    r.draw(camera, ref_p, clear=CLEAR)
    footprint = ~measure.is_clear(r.image(), CLEAR)
    if not footprint.any():  # every figure would compare sky with sky
        where = ground_note(store, camera)  # on or under the ground: that is why
        if not where and not terrain_cells(store):  # (too sparse: no cell can be drawn)
            where = no_pixel_cause(store, camera)[1]
        raise EmptyViewError(
            f"the view from ({camera.position[0]:.1f}, {camera.position[1]:.1f}, "
            f"{camera.position[2]:.1f}) draws no terrain pixel at full resolution "
            f"({ref_st.triangles:,} triangles in the {camera.viewport[0]}x"
            f"{camera.viewport[1]} view): "
            + (where or "it holds no terrain sample, or the DEM is smaller than a pixel from "
               "there; its error, PSNR and crack figures would be vacuous: aim the camera at "
               "the terrain, closer")
        )  # fmt: skip
    ref_heights = measure.heights_fn(store, ref_p)
    if "nodata" in (lod_options or {}):
        raise ValueError("pass the nodata rule as options=ViewOptions(nodata=...): it also plans "
                         "the session")  # fmt: skip
    strat = get_strategy(lod, r, **o.strategy_options(), **(lod_options or {}))
    sp = session_patch_log2(strat, r)
    rows = []
    near = coverage.near_clipped_samples(store, camera)  # (the camera's, whatever the τ)
    for tau in taus:
        sm = stream_metric(lod, metric)
        for st_tau in restream_taus(tau if stream_tau is None else stream_tau):
            with open_render_session(store, st_tau, sm, sp, nodata=o.nodata) as s:
                # the levels each tau's session would hold (the data is on the GPU already)
                frame, res = stream_step(s, None, camera)
                loaded = s.summary()["loaded_bytes"]
            patches, sel_ms = strat.select(camera, tau, metric, resident=res)
            unmet = unmet_leaves(strat, camera, tau, patches, res)
            if not strat.counts(patches).clamped + unmet:  # else it wants levels not loaded
                break
        for _ in range(max(0, repeats - 1)):
            patches, ms = strat.select(camera, tau, metric, resident=res)
            sel_ms = min(sel_ms, ms)
        st = draw_timed(strat, camera, patches, repeats)
        img = r.image()
        err = measure.error_stats(strat.screen_errors(camera, patches))
        tri, tri_h = strat.triangles(camera, patches)
        seen = drawn_cracks(r, strat, camera, patches, ref_p, footprint, (tri, tri_h))
        cov = coverage.coverage(r.grid, camera, ref_p, ref_heights, tri, tri_h, near_clipped=near)
        wt = cracks.watertight(r.grid, tri, tri_h)
        drawn = strat.drawn_blocks(patches)
        own = strat.own_gpu_bytes()
        gpu = sum(4 * grid_side(res[b]) ** 2 for b in drawn) + own
        used = sum(4 * grid_side(lv) ** 2 for lv in strat.used_levels(camera, patches).values())
        row = TradeoffRow(
            tau=float(tau),
            metric=error_label(lod, metric),
            triangles=st.triangles,
            patches=st.patches,
            selection_ms=sel_ms,
            frame_ms=st.frame_ms,
            reference_frame_ms=ref_st.frame_ms,
            reference_triangles=ref_st.triangles,
            max_screen_error_px=err.max_px,
            p99_screen_error_px=err.p99_px,
            mean_screen_error_px=err.mean_px,
            samples_in_view=err.samples,
            psnr_db=measure.psnr(img, ref_img),
            changed_share=measure.changed_share(img, ref_img),
            crack_pixels=seen[0],
            resident_bytes=int(frame.stats.resident_bytes),
            loaded_bytes=int(loaded),
            gpu_bytes=gpu,
            clamped=st.clamped + unmet,
            strategy=lod,
            nodata=o.nodata,
            used_bytes=int(used),
            own_gpu_bytes=int(own),
            crack_pixels_above=seen[1],
            open_edges=wt.open_edges,
            gap_edges=wt.gap_edges,
            max_gap_m=wt.max_gap_m,
            longest_gap_m=wt.longest_gap_m,
            terrain_covered=cov.terrain_covered,
            nodata_covered=cov.nodata_covered,
            uncovered_px=cov.uncovered_px,
            terrain_in_view=cov.terrain_in_view,
            nodata_in_view=cov.nodata_in_view,
            near_clipped_samples=cov.near_clipped,
            undrawable_samples=cov.undrawable,
            stream_tau=float(st_tau),
        )
        rows.append(row)
        if log:
            log(format_row(row))
    note = full_rule_note(r, camera, rows, res, o) if log else None  # a selection: only if read
    if note:
        log(note)
    return rows


def full_rule_note(
    r: TerrainRenderer,
    camera: Camera,
    rows: Sequence[TradeoffRow],
    resident: Mapping[Any, int],
    o: ViewOptions,
) -> str | None:
    """A note for a sweep whose τ changed nothing because nodata pinned the mesh: ``qiu``
    under the nodata rule ``full`` on a store with nodata, the same triangles at every τ, and
    the ``gap`` rule's selection at the largest τ (with the levels held, so at most what a
    ``gap`` session would draw) at least a fifth smaller; None otherwise."""
    if o.lod != "qiu" or o.nodata != "full" or len(rows) < 2:
        return None
    if len({row.triangles for row in rows}) != 1:
        return None
    if not bool(np.asarray(r.store.index.has_nodata).any()):
        return None
    top = max(row.tau for row in rows)
    gap, _ = select_clod(r, camera, top, o.metric, resident=dict(resident), nodata="gap")
    n = patch_counts(gap).triangles
    if n > 0.8 * rows[0].triangles:
        return None
    return (
        f"note: τ changed nothing here ({rows[0].triangles:,} triangles at every τ): under "
        "--nodata-rule full every node holding both terrain and nodata is drawn at full "
        f"resolution; --nodata-rule gap would draw at most {n:,} at τ = {top:g} (it refines "
        "such a node only while its cells span more than min(τ, 1) px)"
    )


def drawn_cracks(
    r: TerrainRenderer,
    strat: Any,
    camera: Camera,
    sel: Any,
    ref_p: Any,
    footprint: np.ndarray,
    triangles: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[int, int]:
    """Crack pixels of the view's own selection ``sel``: seen from ``camera`` (inside the
    reference's ``footprint``) and from above (:func:`render.cracks.above_camera` framing the
    drawn triangles — ``triangles``, default ``strat.triangles(camera, sel)`` — inside the
    reference selection ``ref_p`` drawn from there, where the reference's surface lies in
    ``camera``'s view: outside it each selection culls at its own granularity, and where the
    two culled edges pinch below a pixel the gap between them is enclosed, not a crack); from
    above, only pixels whose ray passes below the drawn surface (:func:`render.cracks.rays_below`:
    through a gap, not past a ridge that wide-angle relief folds over the background). On a
    store with nodata, a pixel that the selection covers once its nodata holes are drawn sees a
    hole in the data, not a crack, and is not counted (:func:`render.measure.crack_pixels`'
    ``holes``). From the camera, a clear pixel that only the image border reaches (a crack
    running off the image's edge) counts where its ray passes below the drawn surface
    (:func:`render.cracks.border_only`, :func:`render.cracks.gaps_through`)."""
    nodata = bool(np.asarray(r.store.index.has_nodata).any())

    def seen(cam: Camera, fp: np.ndarray, mesh: tuple | None = None, edge: tuple = ()) -> int:
        strat.draw(cam, sel, clear=CLEAR)
        img = r.image()
        n = measure.crack_pixels(img, fp, CLEAR)
        # edge (the drawn mesh): the clear pixels only the image border reaches count where
        # their ray passes through a gap in it (a crack running off the image's edge)
        off = cracks.border_only(img, fp, CLEAR) if edge else None
        holes = None
        if (n or (off is not None and off.any())) and nodata:  # holes in the data among them?
            strat.draw(cam, sel, clear=CLEAR, holes=True)  # (drawn only when there is a doubt)
            holes = ~measure.is_clear(r.image(), CLEAR)
            n = measure.crack_pixels(img, fp, CLEAR, holes=holes)
        if n and mesh is not None:  # only rays that pass below the drawn surface: a gap
            rows, cols = np.nonzero(measure.crack_mask(img, fp, CLEAR, holes=holes))
            n = int(cracks.rays_below(r.grid, cam, *mesh, np.c_[rows, cols]).sum())
        if off is not None:
            n += cracks.gaps_through(r.grid, cam, edge, off, holes)
        return n

    tri, h = triangles if triangles is not None else strat.triangles(camera, sel)
    here = seen(camera, footprint, edge=(tri, h))
    above = cracks.above_camera(r.grid, camera, tri, h)
    r.draw(above, ref_p, clear=CLEAR)
    fp_above = ~measure.is_clear(r.image(), CLEAR)
    fp_above &= in_view(camera, r.surface_points(above))
    return here, seen(above, fp_above, (tri, h))


def in_view(camera: Camera, points: np.ndarray) -> np.ndarray:
    """Per point of ``points`` (``(..., 3)``, NaN for none): inside ``camera``'s view frustum."""
    flat = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return camera.in_view(flat).reshape(np.shape(points)[:-1])


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
