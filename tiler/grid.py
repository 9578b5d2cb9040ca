"""The grid of blocks over a DEM and its world coordinates (pure, no I/O).

Blocks are ``side = 2**k + 1`` samples wide and neighbours share their border row/column, so
block ``(br, bc)`` covers sample rows ``br*(side-1) .. br*(side-1) + side - 1`` (inclusive) and
likewise for columns. A DEM of ``H x W`` samples needs ``ceil((H-1)/(side-1))`` block rows (at
least one); samples beyond the DEM are padding (masked, never terrain).

World frame: ``x`` east, ``y`` north, ``z`` up, metres (or the CRS's units), float64. Sample
``(row, col)`` sits at the centre of its pixel: ``x = x0 + col*dx``, ``y = y0 - row*dy`` with
``(x0, y0)`` the centre of sample ``(0, 0)`` and ``dx, dy > 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tiler.errors import LayoutError
from tiler.layout import grid_side, parse_block_size


def as_index(value: object, what: str) -> int:
    """``value`` as an int if it is an integer (Python's or numpy's, not a bool); else a
    ``LayoutError`` naming ``what``: ``int()`` would truncate 1.7 or read ``"1"``, and return
    another block or level than asked for, silently."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        return int(value)
    raise LayoutError(f"{what} must be an integer, got {value!r}")


def as_block(block: object) -> tuple[int, int]:
    """A block id ``(row, col)`` of integers (:func:`as_index`), or a ``LayoutError``."""
    try:
        n = len(block)  # type: ignore[arg-type]
    except TypeError:
        n = -1
    if n != 2 or isinstance(block, (str, bytes)):
        raise LayoutError(f"a block is (row, col), got {block!r}")
    return as_index(block[0], "a block row"), as_index(block[1], "a block column")  # type: ignore[index]


@dataclass(frozen=True)
class BlockGrid:
    """Block layout of one DEM: sizes, block count and the sample-to-world mapping."""

    height: int  # DEM rows (samples)
    width: int  # DEM columns (samples)
    k: int
    x0: float = 0.0
    y0: float = 0.0
    dx: float = 1.0
    dy: float = 1.0

    def __post_init__(self) -> None:
        if self.height < 2 or self.width < 2:
            raise LayoutError(
                f"A DEM needs at least 2x2 samples to make a block, got {self.height}x{self.width}."
            )
        if not (1 <= self.k <= 15):
            raise LayoutError(f"k must be in 1..15, got {self.k}")
        for name in ("dx", "dy"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise LayoutError(f"{name} must be a positive finite spacing, got {v}")
        for name in ("x0", "y0"):
            if not math.isfinite(getattr(self, name)):
                raise LayoutError(f"{name} must be finite, got {getattr(self, name)}")

    @classmethod
    def for_block_size(cls, height: int, width: int, block_size: int, **kw: float) -> BlockGrid:
        """Build from a block edge in samples (``2**k + 1``), validating it."""
        return cls(height=height, width=width, k=parse_block_size(block_size), **kw)

    @property
    def side(self) -> int:
        """Block edge in samples (``2**k + 1``)."""
        return grid_side(self.k)

    @property
    def step(self) -> int:
        """Samples between the first rows of neighbouring blocks (``2**k``)."""
        return self.side - 1

    @property
    def rows(self) -> int:
        """Number of block rows."""
        return max(1, -(-(self.height - 1) // self.step))

    @property
    def cols(self) -> int:
        """Number of block columns."""
        return max(1, -(-(self.width - 1) // self.step))

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of blocks."""
        return self.rows, self.cols

    def blocks(self) -> list[tuple[int, int]]:
        """All block ids, row-major."""
        return [(r, c) for r in range(self.rows) for c in range(self.cols)]

    def check_block(self, br: int, bc: int) -> None:
        """Raise ``LayoutError`` if ``(br, bc)`` is not a block of this grid."""
        if not (0 <= br < self.rows and 0 <= bc < self.cols):
            raise LayoutError(f"block ({br}, {bc}) is outside the {self.rows}x{self.cols} grid")

    def block_window(self, br: int, bc: int) -> tuple[int, int, int, int]:
        """``(row0, col0, nrows, ncols)`` of the block's samples that lie inside the DEM."""
        self.check_block(br, bc)
        r0, c0 = br * self.step, bc * self.step
        return r0, c0, min(self.side, self.height - r0), min(self.side, self.width - c0)

    def block_of_sample(self, row: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Block containing each sample (shared borders go to the lower-right block);
        ``LayoutError`` naming the first sample outside the DEM (it gave negative ids, which
        numpy indexing takes as another block)."""
        row, col = np.asarray(row), np.asarray(col)
        out = (row < 0) | (row > self.height - 1) | (col < 0) | (col > self.width - 1)
        if out.any():
            i = int(np.flatnonzero(out.ravel())[0])  # (out has the broadcast shape)
            r0, c0 = np.broadcast_arrays(row, col)
            raise LayoutError(
                f"sample (row {r0.ravel()[i]}, column {c0.ravel()[i]}) is outside the "
                f"{self.height}x{self.width} DEM (rows 0..{self.height - 1}, columns "
                f"0..{self.width - 1})"
            )
        r = np.minimum(row // self.step, self.rows - 1)
        c = np.minimum(col // self.step, self.cols - 1)
        return r, c

    def block_bounds(self, br: np.ndarray, bc: np.ndarray) -> tuple[np.ndarray, ...]:
        """World ``(xmin, ymin, xmax, ymax)`` of blocks (vectorised; includes padding)."""
        br = np.asarray(br, dtype=np.float64)
        bc = np.asarray(bc, dtype=np.float64)
        xmin = self.x0 + bc * self.step * self.dx
        xmax = xmin + self.step * self.dx
        ymax = self.y0 - br * self.step * self.dy
        ymin = ymax - self.step * self.dy
        return xmin, ymin, xmax, ymax

    def sample_xy(self, row: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World ``(x, y)`` of samples (float64)."""
        return (
            self.x0 + np.asarray(col, dtype=np.float64) * self.dx,
            self.y0 - np.asarray(row, dtype=np.float64) * self.dy,
        )

    def world_to_sample(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional ``(row, col)`` of world points (float64)."""
        return (self.y0 - np.asarray(y, dtype=np.float64)) / self.dy, (
            np.asarray(x, dtype=np.float64) - self.x0
        ) / self.dx

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """World ``(xmin, ymin, xmax, ymax)`` of the DEM's sample centres."""
        return (
            self.x0,
            self.y0 - (self.height - 1) * self.dy,
            self.x0 + (self.width - 1) * self.dx,
            self.y0,
        )
