"""``terrastream render``: one view of a store to a PNG."""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    import numpy as np

from cli.checks import image_suffixes, open_store_arg, output_file
from cli.common import UsageError, fail_on_errors
from cli.formatters import json_text
from cli.options import (
    LOD_DEFAULT,
    METRIC_DEFAULT,
    NODATA_DEFAULT,
    CameraOpt,
    FovOpt,
    LodOpt,
    LookAtOpt,
    MetricOpt,
    NodataRuleOpt,
    PatchOpt,
    PitchOpt,
    SizeOpt,
    StorageOptionsOpt,
    StoreArg,
    TauOpt,
    YawOpt,
    check_metric,
    check_nodata_rule,
    parse_size,
    store_location,
)


def render(
    store: StoreArg,
    storage_options: StorageOptionsOpt = None,
    out: Annotated[
        Path,
        typer.Option("-o", "--out", metavar="FILE", help="Output image (.png, .jpg, .tif ...)."),
    ] = Path("view.png"),
    camera: CameraOpt = None,
    look_at: LookAtOpt = None,
    yaw: YawOpt = None,
    pitch: PitchOpt = None,
    fov: FovOpt = 45.0,
    size: SizeOpt = "1024x768",
    tau: TauOpt = 1.0,
    metric: MetricOpt = METRIC_DEFAULT,
    patch_log2: PatchOpt = 4,
    wireframe: Annotated[bool, typer.Option("--wireframe", help="Overlay edges.")] = False,
    lod_colour: Annotated[bool, typer.Option("--lod-colour", help="Tint by level.")] = False,
    lod: LodOpt = LOD_DEFAULT,
    nodata_rule: NodataRuleOpt = NODATA_DEFAULT,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print the frame's statistics as JSON.")
    ] = False,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace OUT if it exists.")
    ] = False,
) -> None:
    """Render one view of a store to a PNG (default: an oblique overview of the whole DEM).

    Example: terrastream render demo.zarr --camera 500000,4990000,3000 --look-at
    505000,4995000,500 --tau 1 -o view.png
    """
    from render.pipeline import ViewOptions, render_view
    from render.strategies import error_label
    from render.views import ground_note, make_camera, no_pixel_cause

    with fail_on_errors():
        viewport = parse_size(size)
        rule = check_nodata_rule([lod], nodata_rule)
        check_metric(lod, metric)
        opts = ViewOptions(lod, tau, metric, patch_log2, wireframe, lod_colour, nodata=rule)
        output_file(
            out, "--out", suffixes=image_suffixes(), overwrite=overwrite, inputs=[("STORE", store)]
        )
        image_format(out, "--out")  # (an .xbm, a .pbm: refused before drawing)
        s = open_store_arg(store_location(store, storage_options), projected=True)
        cam = make_camera(
            s, viewport, position=camera, look_at=look_at, yaw=yaw, pitch=pitch, fov=fov
        )
        img, st = render_view(s, cam, options=opts)
        if st.triangles == 0:  # nothing drawn: never a picture of sky with exit 0
            raise UsageError(
                f"the view of {store!r} drew no terrain (0 triangles): the camera sees none of "
                "the DEM, or no level could be loaded; point it at the terrain (--camera, "
                "--look-at, --pitch) or run `terrastream verify` on the store",
                hint="--camera",
            )
        if st.drawn_px == 0 and ground_note(s, cam):  # on or under the ground: the reason
            raise UsageError(
                f"the view of {store!r} drew no terrain pixel ({st.triangles:,} triangles): "
                f"{ground_note(s, cam)}",
                hint="--camera",
            )
        if st.drawn_px == 0:  # triangles, but none covers a pixel: the cause, when known
            kind, cause = no_pixel_cause(s, cam)
            if kind:
                raise UsageError(
                    f"the view of {store!r} drew no terrain pixel ({st.triangles:,} "
                    f"triangles): {cause}",
                    hint=_CAUSE_HINTS[kind],
                )
        if st.drawn_px == 0:  # triangles, but none covers a pixel: a picture of sky
            sparse = (
                ", or its terrain is too sparse to draw (a triangle with a nodata corner is "
                "not drawn: `terrastream info` counts the blocks with nodata)"
                if s.index.has_nodata.any()
                else ""
            )
            raise UsageError(
                f"the view of {store!r} drew no terrain pixel ({st.triangles:,} triangles, "
                f"none covering a pixel centre of the {size} view): the terrain in view is "
                f"too small to be seen{sparse}; move the camera closer (--camera, --look-at)",
                hint="--camera",
            )
        save_image(img, out)
        if as_json:
            d = {
                "out": str(out),
                "tau": tau,
                "metric": error_label(lod, metric),
                "lod": lod,
                "nodata_rule": rule,
            }
            d.update(asdict(st))
            d["viewport"] = list(viewport)
            typer.echo(json_text(d))
            return
        typer.echo(
            f"wrote {out}: {st.triangles:,} triangles in {st.patches} patches (levels "
            f"{st.min_level}..{st.max_level}), selection {st.selection_ms:.2f} ms, GPU "
            f"{st.frame_ms:.1f} ms, {st.gpu_bytes / 2**20:.1f} MiB on the GPU (heights and the "
            "strategy's own buffers)"
            + (f", {st.clamped} nodes clamped to resident levels" if st.clamped else "")
        )


#: the option a "no terrain pixel" cause (render.views.no_pixel_cause) points at
_CAUSE_HINTS = {
    "nodata": "STORE",
    "size": "--size",
    "steep": "--camera",
    "far": "--camera",
    "outside": "--camera",
}


def image_format(path: Path, hint: str) -> None:
    """Refuse (a usage error naming ``hint``) an image file whose extension's format cannot
    hold an RGB picture (:func:`render.flythrough.encode_image` on a tiny one): said before
    anything is drawn, not after."""
    import numpy as np

    from render.flythrough import ImageFormatError, encode_image

    try:
        encode_image(np.zeros((2, 3, 3), np.uint8), path)
    except ImageFormatError as exc:
        if exc.resized is not None:  # (not the size of the tiny picture tried)
            raise UsageError(
                f"{path.suffix} files do not keep a picture's size (one of 3x2 became "
                f"{exc.resized[0]}x{exc.resized[1]}); use .png (lossless), .jpg or .tif",
                hint=hint,
            ) from None
        raise UsageError(str(exc), hint=hint) from None


def save_image(img: np.ndarray, out: Path) -> None:
    """Save the RGB picture ``img`` to ``out`` whole or not at all: encoded in memory (the
    format from OUT's extension; a format that cannot hold it as it is, e.g. an .ico of more
    than 256 pixels a side, is a usage error naming --out), written beside OUT and renamed
    over it (``tiler.atomic.write_atomic``), so a failed save (a full disk, Ctrl-C) leaves
    neither half an image nor a damaged earlier OUT."""
    from render.flythrough import ImageFormatError, encode_image
    from tiler.atomic import write_atomic

    try:
        data = encode_image(img, out)
    except ImageFormatError as exc:
        raise UsageError(str(exc), hint="--out") from None
    write_atomic(os.path.abspath(out), data)


def register(app: typer.Typer) -> None:
    """Add ``render`` to ``app``."""
    app.command("render")(render)
