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
