"""Heights in metres: a band's scale/offset (GDAL/CF) and vertical units, applied on read.

The store keeps the source's integers (lossless) and records ``{"scale", "offset", "units",
"metres_per_unit"}`` under the metadata's ``vertical`` key; heights in metres are
``value * a + b`` with ``a = scale * metres_per_unit`` and ``b = offset * metres_per_unit``,
computed in float64 (:func:`height_transform`), the same everywhere (reads, zmin/zmax, errors).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

# unit names as GDAL/CF/UDUNITS spell them -> metres per unit
UNITS: dict[str, float] = {
    "m": 1.0,
    "metre": 1.0,
    "metres": 1.0,
    "meter": 1.0,
    "meters": 1.0,
    "dm": 0.1,
    "decimetre": 0.1,
    "decimeter": 0.1,
    "decimetres": 0.1,
    "decimeters": 0.1,
    "cm": 0.01,
    "centimetre": 0.01,
    "centimeter": 0.01,
    "centimetres": 0.01,
    "centimeters": 0.01,
    "mm": 0.001,
    "millimetre": 0.001,
    "millimeter": 0.001,
    "millimetres": 0.001,
    "millimeters": 0.001,
    "ft": 0.3048,
    "foot": 0.3048,
    "feet": 0.3048,
    "international foot": 0.3048,
    "us survey foot": 1200.0 / 3937.0,
    "us_survey_foot": 1200.0 / 3937.0,
    "us-ft": 1200.0 / 3937.0,
    "ftus": 1200.0 / 3937.0,
    "survey foot": 1200.0 / 3937.0,
    "us survey feet": 1200.0 / 3937.0,
    "us foot": 1200.0 / 3937.0,
    "us feet": 1200.0 / 3937.0,
    "foot_us": 1200.0 / 3937.0,  # (ESRI's spelling)
    "foot us": 1200.0 / 3937.0,
    "feet_us": 1200.0 / 3937.0,
    "ft_us": 1200.0 / 3937.0,
    "us_ft": 1200.0 / 3937.0,
    "international feet": 0.3048,
    "foot_international": 0.3048,
}


def metres_per_unit(units: str | None) -> float | None:
    """Metres in one vertical unit (``None`` units count as metres; unknown names give None)."""
    if units is None or not str(units).strip():
        return 1.0
    return UNITS.get(str(units).strip().lower())


def vertical_meta(scale: float, offset: float, units: str | None) -> dict[str, Any] | None:
    """The ``vertical`` metadata entry, or None when heights are plain metres already."""
    mpu = metres_per_unit(units)
    if mpu is None:
        log.warning(
            "vertical units %r are not known; heights are taken as metres (known: %s)",
            units,
            ", ".join(sorted({"m", "dm", "cm", "mm", "ft", "US survey foot"})),
        )
        mpu = 1.0
    if scale == 1.0 and offset == 0.0 and mpu == 1.0:
        return None
    if not (np.isfinite(scale) and np.isfinite(offset) and scale != 0):
        from tiler.errors import SourceError

        raise SourceError(f"band scale {scale} / offset {offset} cannot make heights")
    return {"scale": scale, "offset": offset, "units": units, "metres_per_unit": mpu}


def height_transform(meta: Any) -> tuple[float, float]:
    """``(a, b)`` with metres = value * a + b, for a ``StoreMeta`` (``(1, 0)`` when plain)."""
    v = (getattr(meta, "extra", None) or {}).get("vertical")
    if not v:
        return 1.0, 0.0
    mpu = float(v.get("metres_per_unit") or 1.0)
    return float(v["scale"]) * mpu, float(v["offset"]) * mpu


def to_metres(meta: Any, values: np.ndarray) -> np.ndarray:
    """Heights in metres (float64) from stored values of a store with metadata ``meta``."""
    a, b = height_transform(meta)
    if (a, b) == (1.0, 0.0):
        return values
    return np.asarray(values, dtype=np.float64) * a + b


def from_metres(meta: Any, values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Inverse of :func:`to_metres`: the stored values (``dtype``) behind heights in metres;
    exact for values that came from :func:`to_metres` (integers rounded, floats re-cast)."""
    a, b = height_transform(meta)
    if (a, b) == (1.0, 0.0):
        return values
    v = (np.asarray(values, dtype=np.float64) - b) / a
    dtype = np.dtype(dtype)
    return (np.rint(v) if dtype.kind in "iu" else v).astype(dtype)


def height_dtype(meta: Any) -> np.dtype:
    """The dtype of decoded heights: float64 when a scale/offset or non-metre unit applies
    (:func:`to_metres`), else the source dtype."""
    if height_transform(meta) != (1.0, 0.0):
        return np.dtype(np.float64)
    return np.dtype(meta.dtype)


#: metres: a valid sample beyond ±1000 km is not a height (Earth's relief is -11..+9 km, Mars'
#: -8..+21 km) but an undeclared nodata value (float32's -3.4e38) or heights in other units;
#: tiled, it overflowed the error bounds and could not be drawn (``tiler.tile`` refuses such
#: samples, :func:`require_heights` stores tiled before it did)
MAX_HEIGHT_M = 1e6


def height_range_message(count: int, metres: float, raw: str, src: str = "SRC") -> str:
    """Why ``count`` samples, the first ``raw`` as the source holds it (``metres`` as a height),
    are refused, and the declarations that fix it in the source ``src``."""
    return (
        f"{count:,} sample(s) of {metres:g} m: beyond ±{MAX_HEIGHT_M / 1e3:g} km, not a "
        f"height. If {raw} marks nodata, declare it (`gdal_edit.py -a_nodata {raw} {src}`, or "
        "tile a VRT: `gdal_translate -of VRT -a_nodata ...`); if the heights are in other "
        "units, declare the band's scale or units"
    )


def require_heights(meta: Any, where: str, src: str) -> None:
    """Refuse a store whose recorded value range reaches beyond :data:`MAX_HEIGHT_M` (tiled
    before such samples were refused: the draw failed with "argument out of range")."""
    from tiler.errors import StoreHeightsError

    vr = (getattr(meta, "extra", None) or {}).get("value_range")
    if not vr or not all(v == v for v in vr):
        return
    worst = max(vr, key=abs)
    if abs(worst) < MAX_HEIGHT_M:
        return
    raise StoreHeightsError(
        f"{where} holds heights of {worst:g} m, beyond ±{MAX_HEIGHT_M / 1e3:g} km: not "
        "terrain (an undeclared nodata value, or heights in other units), so it cannot be "
        f"streamed or rendered. Declare it in the source (`gdal_edit.py -a_nodata V {src}`) "
        "and tile it again with --overwrite (this version refuses such samples)"
    )
