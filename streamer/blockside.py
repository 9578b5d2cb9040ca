"""What a session's loaders read of a block besides its levels — its stored error fields and
its validity mask, with the fields under the nodata rule "full" and the mask's mixed nodes
derived from them once — kept
in a byte-bounded LRU (no threads; its own short lock), so a renderer drawing the session's
blocks takes them from memory instead of reading the store again, or deriving them again, on
its own thread (over a remote store, a round trip per new block in the frame's selection).

Entries are read-only arrays (a consumer that wrote into one would change every later
reader's copy: it raises instead). A miss is not an error: the caller reads the store.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import NamedTuple

import numpy as np

Block = tuple[int, int]
Errors = dict[str, list[np.ndarray]]

__all__ = ["BlockSide", "Side", "side_bytes"]


class Side(NamedTuple):
    """What the loaders read of a block, and what they derived from it once."""

    errors: Errors  #: the stored error fields (``TerrainStore.read_errors``)
    mask: np.ndarray | None  #: the validity mask (``read_mask``), None without nodata
    #: the fields under the nodata rule "full" (mask boundaries raised,
    #: :func:`streamer.nodata.raise_mixed`): ``errors`` itself without a mask boundary
    full: Errors
    #: the mask's mixed nodes at depths ``0..k-1``, bit-packed
    #: (:func:`streamer.nodata.pack_mixed`); None without a mask boundary
    mixed: list[np.ndarray] | None


def side_bytes(budget_bytes: int) -> int:
    """The side data's own bound for a session of ``budget_bytes`` of levels: an eighth of it,
    at least 4 MiB (error fields are a few KiB a block; a mask is a byte per sample)."""
    return max(4 << 20, int(budget_bytes) // 8)


class BlockSide:
    """Error fields and masks of recently read blocks, at most ``max_bytes`` (least recently
    used dropped first; an entry larger than the bound is not kept)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self._lock = threading.Lock()
        self._entries: OrderedDict[Block, tuple[Side, int]] = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    @property
    def nbytes(self) -> int:
        """Bytes held."""
        return self._bytes

    def put(self, block: Block, side: Side) -> None:
        """Keep ``block``'s :class:`Side` (its arrays made read-only)."""
        arrays = [a for f in (side.errors, side.full) for v in f.values() for a in v]
        if side.mask is not None:
            arrays.append(side.mask)
        arrays += side.mixed or []
        seen: set[int] = set()
        n = 0
        for a in arrays:
            a.setflags(write=False)
            if id(a) not in seen:  # (full shares errors' arrays where nothing is raised)
                seen.add(id(a))
                n += a.nbytes
        with self._lock:
            old = self._entries.pop(block, None)
            if old is not None:
                self._bytes -= old[1]
            if n > self.max_bytes:
                return
            self._entries[block] = (side, n)
            self._bytes += n
            while self._bytes > self.max_bytes:
                _, (_, m) = self._entries.popitem(last=False)
                self._bytes -= m

    def get(self, block: Block) -> Side | None:
        """``block``'s :class:`Side` if kept (now the most recently used), else None."""
        with self._lock:
            e = self._entries.get(block)
            if e is None:
                self.misses += 1
                return None
            self._entries.move_to_end(block)
            self.hits += 1
            return e[0]
