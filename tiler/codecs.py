"""Level-codec registry: the store's ``meta.encoding`` names the codec that encodes and decodes.

A :class:`LevelCodec` bundles ``encode`` (a filled block grid to its stored levels), ``decode``
(stored levels to decoded values per level), ``decode_next`` (one more level from the decoded
ones), ``decode_grid`` (stored levels to a level's grid) and ``to_heights`` (decoded values to
the source dtype, dequantising ``precision`` stores). The tiler encodes with
``for_meta(meta).encode``; readers decode with the same object. Adding a codec is one module
that calls :func:`register` (see docs/FORMAT.md, "Level codecs").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from tiler import encoding
from tiler.errors import StoreVersionError


@dataclass(frozen=True)
class LevelCodec:
    """One level encoding. Every function is pure; ``value_dtype`` is the decoded dtype."""

    name: str
    encode: Callable[[np.ndarray, int], list[np.ndarray]]
    decode: Callable[[list[np.ndarray], np.dtype], list[np.ndarray]]
    decode_next: Callable[[list[np.ndarray], np.ndarray, np.dtype], np.ndarray]
    decode_grid: Callable[[list[np.ndarray], np.dtype, int | None], np.ndarray]
    #: ``(raws, value_dtype, level, extent, work)``: the grid's top-left ``extent`` decoded
    #: alone (see :func:`tiler.encoding.decode_grid`); None: decode the grid, then crop
    decode_window: Callable[..., np.ndarray] | None = None


@dataclass(frozen=True)
class BoundCodec:
    """A codec bound to one store's dtypes and precision (what readers call)."""

    codec: LevelCodec
    value_dtype: np.dtype
    dtype: np.dtype
    precision: float | None

    @property
    def name(self) -> str:
        """The codec's registry name (``meta.encoding``)."""
        return self.codec.name

    def encode(self, grid: np.ndarray, k: int) -> list[np.ndarray]:
        """Stored levels of a filled ``2**k+1`` grid (of the value dtype)."""
        return self.codec.encode(grid, k)

    def decode(self, raws: list[np.ndarray]) -> list[np.ndarray]:
        """Decoded values (value dtype) of stored levels ``0..L``."""
        return self.codec.decode(raws, self.value_dtype)

    def decode_next(self, levels: list[np.ndarray], raw: np.ndarray) -> np.ndarray:
        """Decoded values of level ``len(levels)`` from its stored values."""
        return self.codec.decode_next(levels, raw, self.value_dtype)

    def decode_grid(
        self,
        raws: list[np.ndarray],
        level: int | None = None,
        extent: tuple[int, int] | None = None,
        work: np.ndarray | None = None,
    ) -> np.ndarray:
        """The level-``level`` grid (value dtype) from stored levels ``0..level``; with
        ``extent=(rows, cols)`` only its top-left part, as a new array (``work``: scratch)."""
        if extent is None:
            return self.codec.decode_grid(raws, self.value_dtype, level)
        if self.codec.decode_window is not None:
            return self.codec.decode_window(raws, self.value_dtype, level, extent, work)
        g = self.codec.decode_grid(raws, self.value_dtype, level)
        ext = encoding.window_extent(extent, g.shape[0])
        return g if ext is None else g[: ext[0], : ext[1]].copy()

    def to_heights(self, values: np.ndarray) -> np.ndarray:
        """Decoded values as heights in the source dtype (dequantised for precision stores)."""
        if self.precision:
            return encoding.dequantise(values, self.precision, self.dtype)
        return values.astype(self.dtype, copy=False)


_REGISTRY: dict[str, LevelCodec] = {}


def register(codec: LevelCodec) -> None:
    """Add a codec under its name (replacing one of the same name)."""
    _REGISTRY[codec.name] = codec


def names() -> tuple[str, ...]:
    """Registered codec names."""
    return tuple(sorted(_REGISTRY))


def get(name: str) -> LevelCodec:
    """The codec called ``name``; raises StoreVersionError naming the known ones."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise StoreVersionError(
            f"level encoding {name!r} is unknown to this terrastream (it knows "
            f"{', '.join(names())}); upgrade terrastream."
        ) from None


def for_meta(meta: Any) -> BoundCodec:
    """The codec of a store's metadata (``StoreMeta``), bound to its dtypes and precision."""
    value = np.dtype("int32") if meta.precision else np.dtype(meta.dtype)
    return BoundCodec(get(meta.encoding), value, np.dtype(meta.dtype), meta.precision)


def for_dtype(value_dtype: np.dtype) -> LevelCodec:
    """The codec the tiler uses for values of ``value_dtype``."""
    return get(encoding.encoding_for(np.dtype(value_dtype)))


for _name in (encoding.INT_RESIDUAL, encoding.FLOAT_XOR):
    register(
        LevelCodec(
            name=_name,
            encode=encoding.encode_levels,
            decode=encoding.decode_levels,
            decode_next=encoding.decode_next_level,
            decode_grid=encoding.decode_grid,
            decode_window=encoding.decode_grid,
        )
    )
