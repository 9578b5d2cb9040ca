"""The store's metadata (the root ``terrastream`` attribute) and its grid index, as Python.

:class:`StoreMeta` parses and validates the root attribute (a newer format raises
:class:`StoreVersionError`, a damaged one :class:`StoreCorruptError`); :func:`read_meta` and
:func:`write_meta` move it between a zarr group and Python; :class:`BlockIndex` holds the arrays
of ``index/``. The reader is :class:`tiler.store.TerrainStore` (docs/FORMAT.md for the layout).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zarr

from tiler.errors import StoreCorruptError, StoreVersionError
from tiler.grid import BlockGrid
from tiler.layout import grid_side
from tiler.schema import ATTR, FORMAT_VERSION, compact_metadata

__all__ = [
    "CHECKSUM_KEY",
    "BlockIndex",
    "StoreMeta",
    "read_meta",
    "sealed",
    "tool_version",
    "write_meta",
]

#: the root attribute's own checksum (format 2 stores written since 0.2; older ones have none)
CHECKSUM_KEY = "metadata_checksum"


def _checksum(d: dict[str, Any]) -> str:
    """``blake2b-128:<hex>`` of the attribute ``d`` without its checksum, as canonical JSON
    (sorted keys, no spaces: the same text for the same values however zarr wrote them)."""
    body = {k: v for k, v in d.items() if k != CHECKSUM_KEY}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return "blake2b-128:" + hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def sealed(meta: StoreMeta) -> dict[str, Any]:
    """The root attribute of ``meta`` as written: JSON-ready, with its checksum, so that an
    edited or damaged geotransform, CRS, nodata or value range is detected on reading."""
    d = json.loads(json.dumps(meta.to_json(), allow_nan=False))
    d[CHECKSUM_KEY] = _checksum(d)
    return d


def tool_version() -> str:
    """The installed terrastream version (or ``0+unknown`` when run from a bare checkout)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("terrastream")
    except PackageNotFoundError:
        return "0+unknown"


@dataclass(frozen=True)
class StoreMeta:
    """The store's metadata (the root ``terrastream`` attribute)."""

    format_version: int
    k: int
    height: int
    width: int
    dtype: str  # source dtype (what read_block returns)
    storage_dtype: str
    encoding: str
    precision: float | None
    nodata: float | None
    crs_wkt: str | None
    geotransform: tuple[float, ...]  # Affine order (a, b, c, d, e, f), pixel corners
    vertical_units: str | None
    source: dict[str, Any]
    tool_version: str
    error_cap: int
    error_fields: tuple[str, ...]
    compressor: dict[str, Any]
    complete: bool = False
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def value_dtype(self) -> np.dtype:
        """dtype of decoded level values (int32 for quantised stores, else the source dtype)."""
        return np.dtype("int32") if self.precision else np.dtype(self.dtype)

    @property
    def generation(self) -> str | None:
        """Id of this build of the store (new for every fresh tiling); None in format 1."""
        return self.extra.get("generation")

    @property
    def checksummed(self) -> bool:
        """True if every chunk carries a crc32c (format 2 and later)."""
        return self.format_version >= 2

    @property
    def levels(self) -> int:
        """Number of levels per block (``k + 1``)."""
        return self.k + 1

    @property
    def block_size(self) -> int:
        """Block edge in samples."""
        return grid_side(self.k)

    @property
    def grid(self) -> BlockGrid:
        """The block grid with world coordinates of sample centres."""
        a, b, c, d, e, f = self.geotransform
        return BlockGrid(
            height=self.height,
            width=self.width,
            k=self.k,
            x0=c + a * 0.5 + b * 0.5,
            y0=f + d * 0.5 + e * 0.5,
            dx=abs(a),
            dy=abs(e),
        )

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict."""
        out = {k: v for k, v in self.__dict__.items() if k != "extra"}
        out["geotransform"] = list(self.geotransform)
        out["error_fields"] = list(self.error_fields)
        out["nodata"] = nodata_json(self.nodata)
        out["levels"] = self.levels
        out["block_size"] = self.block_size
        out.update(self.extra)
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> StoreMeta:
        """Parse (and validate) the root attribute."""
        try:
            version = int(d["format_version"])
        except (KeyError, TypeError, ValueError) as exc:
            raise StoreCorruptError(f"store metadata has no valid format_version: {exc}") from exc
        if version > FORMAT_VERSION:
            raise StoreVersionError(
                f"store format version {version} is newer than this terrastream reads "
                f"({FORMAT_VERSION}); upgrade terrastream."
            )
        want = d.get(CHECKSUM_KEY)
        if want is not None and want != _checksum(d):
            raise StoreCorruptError(
                "the store's root metadata (the 'terrastream' attribute of its zarr.json: "
                "georeferencing, CRS, nodata, value range) does not match its checksum "
                f"({want}): it was edited or damaged after tiling and cannot be trusted; tile "
                "the source again (terrastream tile SRC DST --overwrite)"
            )
        names = {f for f in cls.__dataclass_fields__ if f != "extra"}
        known = {k: v for k, v in d.items() if k in names}
        skip = ("levels", "block_size", CHECKSUM_KEY)
        extra = {k: v for k, v in d.items() if k not in names and k not in skip}
        try:
            known["geotransform"] = tuple(float(x) for x in known["geotransform"])
            known["error_fields"] = tuple(known["error_fields"])
            if known.get("nodata") is not None:
                known["nodata"] = float(known["nodata"])
            return cls(**known, extra=extra)
        except (KeyError, TypeError, ValueError) as exc:
            raise StoreCorruptError(f"store metadata is incomplete or damaged: {exc}") from exc


def nodata_json(value: float | None) -> float | str | None:
    """A nodata value as strict JSON holds it: NaN and ±inf as zarr's ``"NaN"``,
    ``"Infinity"`` and ``"-Infinity"`` (which ``float()`` reads back), others as they are."""
    if value is None or math.isfinite(value):
        return value
    return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")


def write_meta(group: zarr.Group, meta: StoreMeta) -> None:
    """Write the root attribute (``complete`` as given in ``meta``), sealed (:func:`sealed`)."""
    with compact_metadata():
        group.attrs[ATTR] = sealed(meta)


def read_meta(group: zarr.Group) -> StoreMeta:
    """Read and validate the root attribute."""
    d = group.attrs.get(ATTR)
    if not isinstance(d, dict):
        raise StoreCorruptError(
            "not a terrastream store: the root group has no 'terrastream' attribute"
        )
    return StoreMeta.from_json(d)


@dataclass(frozen=True)
class BlockIndex:
    """The grid index: per-block arrays of shape ``(rows, cols)`` (window: ``(rows, cols, 4)``)."""

    exists: np.ndarray
    done: np.ndarray
    has_nodata: np.ndarray
    zmin: np.ndarray
    zmax: np.ndarray
    window: np.ndarray
    digest: np.ndarray
