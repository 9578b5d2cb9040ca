"""Human-readable output of the commands (tables and summaries); no I/O."""

from __future__ import annotations

import json
import math
from typing import Any


def json_safe(obj: Any) -> Any:
    """``obj`` with every non-finite float (NaN, ±inf; numpy's too) replaced by ``None``, numpy
    scalars by Python numbers and tuples by lists: what strict JSON can hold."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, (str, int)):
        return obj
    if hasattr(obj, "item") and callable(obj.item) and getattr(obj, "shape", None) == ():
        return json_safe(obj.item())  # a numpy scalar
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    return obj


def json_nodata(value: Any) -> Any:
    """A nodata value for JSON: a finite number as is, a non-finite one as the string
    ``"nan"``, ``"inf"`` or ``"-inf"`` (what ``float()`` reads back; null means no nodata)."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        return value
    return value if math.isfinite(x) else repr(x)


def json_text(obj: Any, indent: int | None = None) -> str:
    """``obj`` as strict JSON (:func:`json_safe`, then ``allow_nan=False``): no ``NaN`` or
    ``Infinity`` token, which JSON parsers other than Python's refuse. Every JSON the command
    line prints or writes goes through it."""
    return json.dumps(json_safe(obj), indent=indent, allow_nan=False)


def _box(box: list[float], d: dict[str, Any]) -> str:
    """``x xmin .. xmax, y ymin .. ymax``: millimetres in metres, ~0.1 m in degrees."""
    f = ".6f" if d.get("crs_geographic") else ".3f"
    return f"x {box[0]:{f}} .. {box[2]:{f}}, y {box[1]:{f}} .. {box[3]:{f}}"


def human_bytes(n: float) -> str:
    """``1536`` → ``1.5 KiB``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def _blocks_text(d: dict[str, Any]) -> str:
    """The blocks line's counts: e.g. ``4 with terrain, of which 4 with nodata; 12 without
    terrain, not stored`` (the nodata count is a part of the terrain count, not beside it)."""
    total = d["block_cols"] * d["block_rows"]
    t, n = d["blocks_with_terrain"], d["blocks_with_nodata"]
    text = f"{t} with terrain, of which {n} with nodata"
    return text + (f"; {total - t} without terrain, not stored" if total > t else "")


def _crs_note(d: dict) -> str:
    """How the CRS came about, or why the store cannot be viewed."""
    rep = d.get("reprojection")
    if rep:
        return f" (reprojected from {d.get('source_crs')}, {rep['requested']}, {rep['resampling']})"
    if d.get("crs_geographic"):
        return " (geographic: tiles losslessly, but to stream or render retile with --dst-crs auto)"
    if d.get("crs_unit"):
        return (
            f" (x/y in {d['crs_unit']}: tiles losslessly, but to stream or render retile with "
            "--dst-crs auto)"
        )
    return ""


def _vertical_note(d: dict) -> str:
    """The stored integers behind heights in metres (band scale/offset, feet)."""
    v, raw = d.get("vertical"), d.get("value_range_stored")
    if not v:
        return ""
    stored = f"{raw[0]:g} .. {raw[1]:g} " if raw else ""
    return (
        f" (stored {stored}{d['dtype']} x {v['scale']:g} + {v['offset']:g} "
        f"{v.get('units') or 'm'}, {v.get('metres_per_unit') or 1:g} m per unit)"
    )


def format_info(d: dict) -> str:
    """The human-readable ``info`` table."""
    lines = [
        f"store          {d['url']}",
        f"format         v{d['format_version']}, written by terrastream {d['tool_version']}",
        f"source         {d['source']} ({d['checksum']})",
        f"samples        {d['width']} x {d['height']} {d['dtype']} (width x height)"
        + (f", quantised to {d['precision']} m" if d["precision"] else ", lossless"),
        f"blocks         {d['block_cols']} x {d['block_rows']} of {d['block_size']}^2 "
        f"({_blocks_text(d)})",
        f"levels         {d['levels']} (encoding {d['encoding']}, {d['compressor']})",
        f"nodata         {'none' if d['nodata'] is None else format(d['nodata'], 'g')}",
        f"checksums      {d.get('checksums', 'none')}",
        f"crs            {d['crs'] or 'none'}" + _crs_note(d),
        f"extent         {_box(d['extent'], d)} (sample centres)",
        f"bounds         {_box(d['bounds'], d)} (pixel edges, as GDAL)",
        f"values         {d['value_range'][0]:g} .. {d['value_range'][1]:g}"
        + (" m" if d.get("vertical") else f" {d['vertical_units']}" if d["vertical_units"] else "")
        + _vertical_note(d),
        "",
        "level  values/block      stored     share",
    ]
    b = d["bytes"]
    if b is None:  # (an http(s) server lists no files: the sizes are unknown, not 0)
        lines[-1] = "level  values/block"
        lines += [f"{r['level']:>5}  {r['values_per_block']:>12}" for r in d["bytes_per_level"]]
        lines += [
            "",
            "stored bytes unknown: an http(s) server cannot list the store's files (info on "
            "a local or object-store copy gives them)",
        ]
        return "\n".join(lines)
    total = b["total"]
    for row in d["bytes_per_level"]:
        lines.append(
            f"{row['level']:>5}  {row['values_per_block']:>12}  {human_bytes(row['bytes']):>10}"
            f"  {100 * row['bytes'] / max(total, 1):6.2f} %"
        )
    lines += [
        "",
        f"levels {human_bytes(b['levels'])}, errors {human_bytes(b['errors'])}, "
        f"mask {human_bytes(b['mask'])}, index {human_bytes(b['index'])}, "
        f"metadata {human_bytes(b['metadata'])}",
        f"total {human_bytes(total)} = {d['ratio_to_raw']:.3f} x raw "
        f"({human_bytes(d['raw_bytes'])})",
    ]
    return "\n".join(lines)


def warmup_line(d: dict, mb: float) -> str:
    """The summary's warm-up line: one warm-up before frame 0 as before; several (a session
    warmed up again, ``warmups``) say how many, their figures summed."""
    n = int(d.get("warmups", 1))
    what = "warm-up before frame 0" if n <= 1 else f"{n} warm-ups (summed)"
    return f"{what}: {d['warmup_bytes'] * mb:.2f} MiB in {d['warmup_ms']:.0f} ms"


def format_summary(d: dict) -> str:
    """The stream summary block."""
    mb = 1 / 2**20
    needed = max(d["needed_bytes"], 1)
    used = max(d["used_bytes"], 1)
    after = d.get("discarded_after_frames_bytes")  # (streamer.run.frames_summary's cut)
    where = (
        "in the session"
        if after is None
        else f"in the warm-up and the frames; {after * mb:.2f} MiB more after the last frame"
    )
    return "\n".join(
        [
            f"frames {d['frames']}, stall frames {d['stall_frames']} (over the "
            f"{d.get('stall_set', 'triangle')} set), io errors {d['io_errors']}, "
            f"frames with holes {d.get('hole_frames', 0)}, "
            f"blocks failed at the end {len(d.get('failed_blocks', []))} (failing "
            f"{d.get('failing_blocks', 0)}, of which needed by a frame "
            f"{d.get('failing_blocks_needed', 0)})",
            f"late bytes {d.get('late_bytes', 0) * mb:.3f} MiB (after their frame was due); "
            f"frames drawn coarser than needed, by levels: {d.get('coarse_frames_by_levels', {})}",
            warmup_line(d, mb),
            f"needed {d['needed_bytes'] * mb:.1f} MiB over all frames; real-time loaded "
            f"{d['realtime_bytes'] * mb:.3f} MiB "
            f"({100 * d['realtime_bytes_after_first_frame'] / needed:.3f} % of needed after "
            "frame 1)",
            f"loaded {d['loaded_bytes'] * mb:.2f} MiB, used {d['used_bytes'] * mb:.2f} MiB "
            f"(loaded/used {d['loaded_bytes'] / used:.2f}), "
            f"wasted {d['wasted_bytes'] * mb:.2f} MiB; read but discarded on arrival "
            f"{d.get('discarded_bytes', 0) * mb:.2f} MiB ({where})",
            f"peak resident {d['peak_resident_bytes'] * mb:.2f} MiB of a "
            f"{d['budget_bytes'] * mb:.2f} MiB budget; max update {d['max_update_ms']:.2f} ms "
            f"(CPU {d['max_update_cpu_ms']:.2f} ms)",
        ]
    )
