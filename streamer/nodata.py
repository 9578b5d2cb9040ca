"""Nodata boundaries at every τ (issue 12): a node whose closed footprint holds both valid and
masked samples is refined to full resolution, so terrain beside nodata is drawn from its valid
samples and no hole is bridged. The renderer raises the stored errors of such nodes to ``inf``
(:func:`raise_mixed`); the loader hands the session the same errors, so the session streams
the levels the renderer then draws (docs/RENDER.md, "Precision and extremes").

Two rules (:data:`NODATA_RULES`): ``"full"`` is the one above (issue 12 item 2, every
strategy). ``"gap"`` (``qiu`` only) keeps the stored errors and gives each
mixed cell its horizontal extent instead (:func:`gap_widths`): the selection refines it only
while that extent can project to more than ``min(τ, 1)`` px, so every valid sample the level
drops, and every hole it bridges, lies in a cell no wider than that on screen
(:func:`render.select.select_patches`). A streaming session plans with the rule of its
``SessionConfig.nodata`` (:func:`rule_errors`, :class:`streamer.levels.PatchErrorTable`), so
under ``"gap"`` it streams only the levels that rule draws."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tiler.quadtree import max_pool

if TYPE_CHECKING:
    from tiler.store import TerrainStore


def mixed_nodes(valid: np.ndarray, k: int) -> list[np.ndarray]:
    """Per depth ``d <= k``, ``(2**d, 2**d)`` booleans: the node's closed footprint (borders
    included) holds both valid and masked samples of the ``(2**k+1)²`` mask ``valid``."""
    v = np.asarray(valid, dtype=bool)
    quad = (v[:-1, :-1], v[1:, :-1], v[:-1, 1:], v[1:, 1:])
    anyv = quad[0] | quad[1] | quad[2] | quad[3]
    anym = ~(quad[0] & quad[1] & quad[2] & quad[3])
    out = [anyv & anym]
    for _ in range(k):
        anyv = max_pool(anyv, 2)  # any over each 2x2
        anym = max_pool(anym, 2)
        out.append(anyv & anym)
    return out[::-1]


#: ``"full"``: a mixed node is refined to full resolution at every τ; ``"gap"``: only while its
#: cell's horizontal extent projects to more than ``min(τ, 1)`` px (a session follows the rule of
#: its ``SessionConfig.nodata``, so it streams the levels the renderer draws with that rule)
NODATA_RULES = ("full", "gap")


def check_rule(rule: str) -> str:
    """``rule`` when it is one of :data:`NODATA_RULES`, else a ``ValueError`` naming them."""
    if rule not in NODATA_RULES:
        raise ValueError(f"unknown nodata rule {rule!r}; choose one of {list(NODATA_RULES)}")
    return rule


def pack_mixed(mixed: list[np.ndarray], k: int) -> list[np.ndarray]:
    """Depths ``0..k-1`` of :func:`mixed_nodes`' answer, each row bit-packed
    (``np.packbits``): what a session keeps for its renderer (at 1025² blocks ~44 KiB instead of
    ~1.4 MB of booleans)."""
    return [np.packbits(mixed[d], axis=-1) for d in range(k)]


def unpack_mixed(packed: list[np.ndarray]) -> list[np.ndarray]:
    """:func:`pack_mixed`'s depths back as ``(2**d, 2**d)`` booleans."""
    return [np.unpackbits(a, axis=-1, count=1 << d).astype(bool) for d, a in enumerate(packed)]


def gap_widths(
    valid: np.ndarray, k: int, dx: float, dy: float, mixed: list[np.ndarray] | None = None
) -> list[np.ndarray]:
    """Per depth ``0..k-1``, ``(2**d, 2**d)`` float32: the diagonal in metres of a level-``d``
    cell (``2**(k-d)`` samples of ``dx`` × ``dy``) where the cell is mixed
    (:func:`mixed_nodes`, or ``mixed`` if given), 0 elsewhere. Drawn at level ``d``, a mixed
    cell can drop valid samples or bridge masked ones only inside itself, so this is the widest
    horizontal gap it can leave; level ``k`` (full resolution) leaves none."""
    if mixed is None:
        mixed = mixed_nodes(valid, k)
    return [
        np.where(mixed[d], np.float32((1 << (k - d)) * np.hypot(dx, dy)), np.float32(0.0))
        for d in range(k)
    ]


def raise_mixed(field: list[np.ndarray], mixed: list[np.ndarray]) -> list[np.ndarray]:
    """``field`` (one array per depth ``0..k-1``, tiled below its cap) with the nodes of
    ``mixed`` at ``inf`` (a tile is raised when any of its nodes is mixed); level ``k`` has no
    stored error, so a mask boundary is drawn at full resolution."""
    out = []
    for d, arr in enumerate(field):
        n, m = arr.shape[0], mixed[d].shape[0]
        tiles = max_pool(mixed[d], m // n)  # any over each tile
        out.append(np.where(tiles, np.float32(np.inf), arr).astype(arr.dtype))
    return out


def raise_all(
    errors: dict[str, list[np.ndarray]],
    mask: np.ndarray | None,
    k: int,
    mixed: list[np.ndarray] | None = None,
) -> dict[str, list[np.ndarray]]:
    """Every field of ``errors`` under the rule "full" (:func:`raise_mixed` at the ``mask``'s
    :func:`mixed_nodes`, or ``mixed`` if known); ``errors`` itself without a mask boundary."""
    if not has_boundary(mask):
        return errors
    if mixed is None:
        mixed = mixed_nodes(mask, k)
    return {name: raise_mixed(field, mixed) for name, field in errors.items()}


def boundary_errors(store: TerrainStore, block: tuple[int, int], field: str) -> list[np.ndarray]:
    """The block's stored error ``field`` with its mask boundaries raised (:func:`raise_mixed`);
    the stored field itself when the block has no nodata or padding."""
    return rule_errors(store, block, field, "full")[0]


def read_side(
    store: TerrainStore, block: tuple[int, int]
) -> tuple[dict[str, list[np.ndarray]], np.ndarray | None]:
    """The block's stored error fields and its validity mask (None for a block without nodata
    or padding): the reads of :func:`rule_errors`."""
    errors = store.read_errors(block)
    return errors, store.read_mask(block) if bool(store.index.has_nodata[block]) else None


def rule_errors_of(
    field: list[np.ndarray],
    mask: np.ndarray | None,
    k: int,
    dx: float,
    dy: float,
    rule: str,
    mixed: list[np.ndarray] | None = None,
) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
    """:func:`rule_errors` from a block's stored error ``field`` and ``mask``
    (:func:`read_side`) in a store of ``2**k+1`` blocks of ``dx`` × ``dy`` samples
    (``mixed``: the mask's :func:`mixed_nodes`, if already known)."""
    full = check_rule(rule) == "full"
    if not has_boundary(mask):
        return field, None
    if mixed is None:
        mixed = mixed_nodes(mask, k)
    if full:
        return raise_mixed(field, mixed), None
    return field, gap_widths(mask, k, dx, dy, mixed)


def has_boundary(mask: np.ndarray | None) -> bool:
    """Whether a block's ``mask`` (None: no nodata) holds both terrain and nodata."""
    return mask is not None and bool(mask.any()) and not bool(mask.all())


def rule_errors(
    store: TerrainStore, block: tuple[int, int], field: str, rule: str = "full"
) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
    """What a session plans the block with under the nodata ``rule``: ``"full"`` its
    :func:`boundary_errors` and no gap widths; ``"gap"`` the stored field and its
    :func:`gap_widths` (``None`` when the block has no mask boundary)."""
    check_rule(rule)
    errors, mask = read_side(store, block)
    return rule_errors_of(errors[field], mask, store.k, store.grid.dx, store.grid.dy, rule)
