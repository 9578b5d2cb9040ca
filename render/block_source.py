"""Where a renderer reads what it builds per block — a level's grid, the stored error fields
(also with mask boundaries raised: the nodata rule "full"), the validity mask and its mixed
nodes: from the
streaming session it last synced with while that holds them (no store read, no decode, no
derivation on the render thread; over a remote store a round trip per new block), else from
the store. The values are the same either way (tested)."""

from __future__ import annotations

import weakref
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from streamer.nodata import has_boundary, mixed_nodes, unpack_mixed
from tiler.layout import reconstruct
from tiler.store import TerrainStore

if TYPE_CHECKING:
    from streamer.blockside import Side
    from streamer.session import Session

Block = tuple[int, int]
Errors = dict[str, list[np.ndarray]]


class BlockSource:
    """A block's grid, errors and mask for one store's renderer (masks kept per block until
    :meth:`forget`)."""

    def __init__(self, store: TerrainStore) -> None:
        self.store = store
        self._session: weakref.ref[Session] | None = None  # the last synced (not kept alive)
        self._masks: dict[Block, np.ndarray | None] = {}

    def attach(self, session: Session) -> None:
        """Take from ``session`` from now on (a weak reference: a closed, dropped session is
        not kept alive, and then the store is read)."""
        self._session = weakref.ref(session)

    def _live(self) -> Session | None:
        return self._session() if self._session is not None else None

    def grid(self, block: Block, level: int) -> np.ndarray:
        """The level-``level`` grid in the source dtype (``TerrainStore.read_block``'s values):
        gathered from the session's decoded levels while it holds them (nothing kept)."""
        session = self._live()
        if session is not None:
            levels = session.levels(block)
            if len(levels) > level >= 0:
                return reconstruct(levels, level)
        return self.store.read_block(block, max_level=level)

    def grid_later(self, block: Block, level: int) -> Callable[[], np.ndarray]:
        """:meth:`grid` as a function to call later, on any thread: the session's decoded
        levels are taken now (it may drop them meanwhile), the store is read when called."""
        session = self._live()
        if session is not None:
            levels = session.levels(block)
            if len(levels) > level >= 0:
                return partial(reconstruct, levels, level)
        return partial(self.store.read_block, block, max_level=level)

    def errors(self, block: Block) -> dict[str, list[np.ndarray]]:
        """The stored error fields (``TerrainStore.read_errors``; the session's are
        read-only)."""
        side = self._side(block)
        return self.store.read_errors(block) if side is None else side.errors

    def full_errors(self, block: Block) -> dict[str, list[np.ndarray]] | None:
        """The stored fields with the mask boundaries raised (the nodata rule "full"), as the
        session's loaders derived them; None when the session does not hold them."""
        side = self._side(block)
        return None if side is None else side.full

    def mask(self, block: Block) -> np.ndarray | None:
        """The validity mask, None without nodata or padding (kept; the session's is
        read-only)."""
        if block not in self._masks:
            mask = None
            if bool(self.store.index.has_nodata[block]):
                side = self._side(block)
                mask = self.store.read_mask(block) if side is None else side.mask
            self._masks[block] = mask
        return self._masks[block]

    def mixed(self, block: Block) -> list[np.ndarray] | None:
        """Per depth ``0..k-1`` the nodes whose footprint holds both terrain and nodata
        (:func:`streamer.nodata.mixed_nodes`), None without a mask boundary: the session
        loaders' (unpacked, ~0.04 ms at 1025²) if held, else derived from the mask (~2 ms)."""
        side = self._side(block)
        if side is not None:
            return None if side.mixed is None else unpack_mixed(side.mixed)
        mask = self.mask(block)
        return mixed_nodes(mask, self.store.k)[: self.store.k] if has_boundary(mask) else None

    def mixed_later(self, block: Block) -> Callable[[], list[np.ndarray] | None]:
        """:meth:`mixed` as a function to call later, on any thread (what the session holds
        taken now, unpacked or derived when called)."""
        side = self._side(block)
        if side is not None:
            return (lambda: None) if side.mixed is None else partial(unpack_mixed, side.mixed)
        mask, k = self.mask(block), self.store.k
        if mask is None or not has_boundary(mask):
            return lambda: None
        return lambda: mixed_nodes(mask, k)[:k]

    def held(self) -> dict[Block, int]:
        """The synced session's finest resident level of every block it holds
        (:meth:`streamer.session.Session.resident_levels`; empty without a session)."""
        session = self._live()
        return {} if session is None else session.resident_levels()

    def held_version(self) -> int | None:
        """:meth:`streamer.session.Session.resident_version` of the synced session (None
        without one): :meth:`held` is unchanged while it is."""
        session = self._live()
        return None if session is None else session.resident_version()

    def held_later(
        self, block: Block, level: int
    ) -> tuple[Callable[[], np.ndarray], Errors, Callable[[], list[np.ndarray] | None]] | None:
        """``(grid_later, stored errors, mixed_later)`` of a block the session holds to
        ``level`` with its side data, for a build on another thread; None when it does not
        (then nothing is read: a block not yet drawn is not worth a store read)."""
        session = self._live()
        side = None if session is None else session.block_side(block)
        if side is None:
            return None
        levels = session.levels(block)
        if not len(levels) > level >= 0:
            return None
        mixed = side.mixed
        later = (lambda: None) if mixed is None else partial(unpack_mixed, mixed)
        return partial(reconstruct, levels, level), side.errors, later

    def forget(self, block: Block) -> None:
        """Drop what is kept of ``block`` (it left the GPU; read again if it comes back)."""
        self._masks.pop(block, None)

    def masks_held(self) -> int:
        """Blocks whose mask is kept."""
        return len(self._masks)

    def _side(self, block: Block) -> Side | None:
        session = self._live()
        return None if session is None else session.block_side(block)
