"""What a session's loaders read of a block besides its levels — its stored error fields and
its validity mask — kept in a byte-bounded LRU (no threads; its own short lock), so a renderer
drawing the session's blocks takes them from memory instead of reading the store again on its
own thread (over a remote store, a round trip per new block in the frame's selection).

Entries are read-only arrays (a consumer that wrote into one would change every later
reader's copy: it raises instead). A miss is not an error: the caller reads the store.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

Block = tuple[int, int]
Errors = dict[str, list[np.ndarray]]

__all__ = ["BlockSide", "side_bytes"]


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
        self._entries: OrderedDict[Block, tuple[Errors, np.ndarray | None, int]] = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    @property
    def nbytes(self) -> int:
        """Bytes held."""
        return self._bytes

    def put(self, block: Block, errors: Errors, mask: np.ndarray | None) -> None:
        """Keep ``block``'s stored error fields (``TerrainStore.read_errors``) and its mask
        (``TerrainStore.read_mask``, None for a block without nodata); both made read-only."""
        for arrays in errors.values():
            for a in arrays:
                a.setflags(write=False)
        if mask is not None:
            mask.setflags(write=False)
        n = sum(a.nbytes for arrays in errors.values() for a in arrays)
        n += 0 if mask is None else mask.nbytes
        with self._lock:
            old = self._entries.pop(block, None)
            if old is not None:
                self._bytes -= old[2]
            if n > self.max_bytes:
                return
            self._entries[block] = (errors, mask, n)
            self._bytes += n
            while self._bytes > self.max_bytes:
                _, (_, _, m) = self._entries.popitem(last=False)
                self._bytes -= m

    def get(self, block: Block) -> tuple[Errors, np.ndarray | None] | None:
        """``(errors, mask)`` of ``block`` if kept (now the most recently used), else None."""
        with self._lock:
            e = self._entries.get(block)
            if e is None:
                self.misses += 1
                return None
            self._entries.move_to_end(block)
            self.hits += 1
            return e[0], e[1]
