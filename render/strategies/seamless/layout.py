"""``seamless-patches``' pure pieces of the selection: the paper's ε = ρ·l/d per edge (both
forms of ρ), the edge resolution and :class:`PatchLayout`, what a selection returns (no I/O)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

# -- ε = ρ l / d ----------------------------------------------------------------------------

#: the forms of ρ: ``"bound"`` (ours, the stored error over τ) and ``"paper"`` (Livny et al.'s
#: global precision factor, Section 3 "Level of Detail"); see the package docstring
RHO_FORMS = ("bound", "paper")


def paper_precision(tau: float, focal_px: float, res_log2: int) -> float:
    """Livny et al.'s ρ as published, one global factor: ``ρ = f / (τ 2**c)`` (∞ at τ = 0)."""
    if tau < 0:
        raise ValueError(f"tau must be >= 0, got {tau}")
    if tau == 0:
        return float("inf")
    return float(focal_px) / (float(tau) * float(1 << res_log2))


def precision(
    delta: ArrayLike, length: ArrayLike, tau: float, focal_px: float, res_log2: int
) -> np.ndarray:
    """The edge's precision factor ``ρ = 2 f δ / (τ 2**c l)`` (∞ at τ = 0 unless δ = 0)."""
    delta = np.asarray(delta, dtype=np.float64)
    num = 2.0 * focal_px * delta
    den = float(tau) * float(1 << res_log2) * np.asarray(length, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(num == 0.0, 0.0, num / den)
    return np.where(np.isnan(rho), np.inf, rho)


def edge_epsilon(rho: ArrayLike, length: ArrayLike, dist: ArrayLike) -> np.ndarray:
    """The paper's ``ε = ρ l / d`` (0 when ρ = 0, ∞ when d = 0 < ρ)."""
    rho = np.asarray(rho, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        eps = rho * np.asarray(length, dtype=np.float64) / np.asarray(dist, dtype=np.float64)
    return np.where(rho == 0.0, 0.0, np.where(np.isnan(eps), np.inf, eps))


def edge_resolution(eps: ArrayLike, res_log2: int) -> np.ndarray:
    """log2 of the edge's cells: ``ε 2**c`` rounded up to a power of two, clipped to 1..c."""
    x = np.asarray(eps, dtype=np.float64) * float(1 << res_log2)
    x = np.where(np.isfinite(x), x, float(1 << res_log2))
    m, e = np.frexp(np.maximum(x, 1.0))
    up = np.where(m == 0.5, e - 1, e)
    return np.clip(up, 1, res_log2).astype(np.int64)


@dataclass(frozen=True, eq=False)
class PatchLayout:
    """Leaf patches of one frame and their edge levels (N, E, S, W)."""

    blocks: np.ndarray  # (m, 2) block ids
    block: np.ndarray  # (n,) index into blocks
    depth: np.ndarray
    row: np.ndarray  # node row/col inside the block at its depth
    col: np.ndarray
    edge_level: np.ndarray  # (n, 4) store level of each edge's tile
    eps: np.ndarray  # (n, 4) ε of each edge
    res_log2: int
    clamped: int
    violations: int

    def __len__(self) -> int:
        return len(self.depth)

    @property
    def edge_res(self) -> np.ndarray:
        """``(n, 4)`` log2 cells of each tile."""
        return self.edge_level - self.depth[:, None]
