"""Rendering with a streaming session: single views and the tau trade-off sweep (fly-throughs:
:mod:`render.flythrough`).

The sweep's rows, table and figure are :mod:`render.tradeoff_report`'s, the cracks of a view's
own selection :mod:`render.view_cracks`'; their names are re-exported here."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
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
from render.tradeoff_report import ERROR_PANEL as ERROR_PANEL  # re-exported (moved there)
from render.tradeoff_report import TABLE_HEADER as TABLE_HEADER  # re-exported
from render.tradeoff_report import TradeoffRow, format_row
from render.tradeoff_report import finite as finite  # re-exported
from render.tradeoff_report import plot_tradeoff as plot_tradeoff  # re-exported
from render.tradeoff_report import tradeoff_figure as tradeoff_figure  # re-exported
from render.view_cracks import drawn_cracks
from render.view_cracks import in_view as in_view  # re-exported (moved there)
from render.view_cracks import nadir_for as nadir_for  # re-exported
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
