"""Arrays of many keys in one float64 buffer (pure numpy), so a compiled kernel can read any of
them by offset (:mod:`render._stitch_nb`'s gathers of :class:`render.node_boxes.NodeBoxes`'
grids and bounds) while Python code keeps per-key views. Keys are replaced or dropped; the
buffer grows by doubling and is repacked when half of it is dead, after which the owner takes
new views (:meth:`FlatPool.put`'s answer says when)."""

from __future__ import annotations

from collections.abc import Hashable, Sequence

import numpy as np


class FlatPool:
    """Per key a list of float64 arrays, stored back to back in :attr:`buf`."""

    def __init__(self, capacity: int = 1 << 16) -> None:
        self.buf = np.zeros(max(1, capacity))
        self.end = 0  # first free element
        self.live = 0  # elements of live entries
        self.at: dict[Hashable, list[tuple[int, tuple[int, ...]]]] = {}

    def put(self, key: Hashable, arrays: Sequence[np.ndarray]) -> bool:
        """Store ``arrays`` (as float64) under ``key``, replacing what it held; whether the
        buffer moved (every key's old views are then stale: take :meth:`views` again)."""
        self.drop(key)
        arrs = [np.asarray(a, dtype=np.float64) for a in arrays]
        need = sum(a.size for a in arrs)
        moved = self.end + need > len(self.buf)
        if moved:
            self._repack(need)
        parts = []
        for a in arrs:
            self.buf[self.end : self.end + a.size] = a.ravel()
            parts.append((self.end, a.shape))
            self.end += a.size
        self.at[key] = parts
        self.live += need
        return moved

    def views(self, key: Hashable) -> list[np.ndarray]:
        """The arrays stored under ``key``, as views of :attr:`buf`."""
        return [self.buf[o : o + _size(sh)].reshape(sh) for o, sh in self.at[key]]

    def drop(self, key: Hashable) -> None:
        """Forget ``key`` (its elements are dead until a repack)."""
        parts = self.at.pop(key, None)
        if parts:
            self.live -= sum(_size(sh) for _, sh in parts)

    def _repack(self, need: int) -> None:
        """A buffer holding the live entries back to back with room for ``need`` more."""
        cap = len(self.buf)
        while cap < 2 * (self.live + need):
            cap *= 2
        new = np.zeros(cap)
        end = 0
        for key, parts in self.at.items():
            moved = []
            for o, sh in parts:
                s = _size(sh)
                new[end : end + s] = self.buf[o : o + s]
                moved.append((end, sh))
                end += s
            self.at[key] = moved
        self.buf, self.end = new, end


def _size(shape: tuple[int, ...]) -> int:
    n = 1
    for v in shape:
        n *= int(v)
    return n
