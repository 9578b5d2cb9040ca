"""``geometry-splitting``: first textures built ahead, on a worker thread, for blocks the
streaming session already holds but the GPU does not draw yet (prefetched), so that a block
entering the view gets its first texture without a build on the render thread.

A new block's first texture is the one the render thread would build at once — its level
capped at ``PROVISIONAL_LEVEL`` (``provision.py``) — so the bytes and the drawing are the same
either way; only where the work runs changes. One built for a level the session has changed
since is drawn meanwhile, as an interim texture (as a block on the GPU keeps its texture after
a level change), while the block's own is built. This module is the bookkeeping (no GL, no threads):
which blocks to build ahead, the finished textures (bounded in bytes), and the counts a
benchmark reports.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

Block = tuple[int, int]

#: finished textures kept for blocks not yet drawn, at most (142 KB each at 1025² without
#: nodata, 185 KB with: ~90 blocks)
AHEAD_BYTES = 16 << 20
#: builds asked for and not yet taken back, at most (~1 ms each at 1025², on their own thread)
AHEAD_PER_FRAME = 2


class AheadTextures:
    """First textures of blocks not yet drawn: :meth:`wanted` picks the blocks to build,
    :meth:`put` keeps a finished one, :meth:`take` hands it to the block's first frame."""

    def __init__(self, limit_bytes: int = AHEAD_BYTES, per_frame: int = AHEAD_PER_FRAME) -> None:
        self.limit_bytes = int(limit_bytes)
        self.per_frame = int(per_frame)  # (asked at once: a frame asks for the room left)
        #: block -> (level built for, packed bytes, depth stored node by node)
        self.ready: dict[Block, tuple[int, bytes, int]] = {}
        self.asked: set[Block] = set()  #: builds asked for, not yet :meth:`put`
        #: +1 whenever :attr:`ready` changes (with the session's and the drawn blocks': no
        #: new want without a change)
        self.version = 0
        self.nbytes = 0
        self.hits = 0  #: first textures taken from here (no build on the render thread)
        self.misses = 0  #: first textures the render thread built (nothing ready)
        #: first textures taken ready at another level than the block is drawn at (its own
        #: is then built on the level worker, the block drawn with this one meanwhile)
        self.interims = 0
        #: finished textures dropped unused (the block left the session, or was drawn first)
        self.dropped = 0

    def wanted(
        self,
        held: Mapping[Block, int],
        first_level: Callable[[int], int],
        skip: Callable[[Block], bool],
        nearest: Callable[[list[Block]], list[Block]],
    ) -> list[tuple[Block, int]]:
        """The ``(block, level)`` builds to ask for now (then :meth:`asking` each): blocks of
        ``held`` (the session's finest resident levels) not ``skip``-ped (drawn, or with a
        texture on the GPU) nor asked for already, whose ready texture is missing or not at
        ``first_level(resident level)`` (a negative one: none wanted), the ``nearest`` first,
        as many as keep :attr:`per_frame` asked at once, none while the kept textures reach
        :attr:`limit_bytes`. Drops the ready textures of blocks no longer held or skipped (a
        drawn block's first texture was built without them)."""
        for b in [b for b in self.ready if b not in held or skip(b)]:
            self._drop(b)
            self.dropped += 1
        room = self.per_frame - len(self.asked)
        if room <= 0 or self.nbytes >= self.limit_bytes:
            return []
        want: dict[Block, int] = {}
        for b, top in held.items():
            lv = first_level(top)
            if lv < 0 or b in self.asked or skip(b):
                continue
            got = self.ready.get(b)
            if got is None or got[0] != lv:
                want[b] = lv
        if len(want) > room:
            return [(b, want[b]) for b in nearest(list(want))[:room]]
        return list(want.items())

    def asking(self, b: Block) -> None:
        """A build of ``b``'s first texture was asked for (until its :meth:`put`)."""
        self.asked.add(b)

    def put(self, b: Block, level: int, data: bytes, depth: int) -> None:
        """Keep ``b``'s finished texture (built for ``level``), replacing an older one."""
        self.asked.discard(b)
        self._drop(b)
        self.ready[b] = (int(level), data, int(depth))
        self.nbytes += len(data)
        self.version += 1

    def take(self, b: Block, level: int) -> tuple[int, bytes, int] | None:
        """``b``'s ready texture ``(level built for, bytes, depth)``, handed over (once), or
        None (a miss: the render thread builds it). Built for ``level``, it is a hit; built
        for another level (the session changed the block's level after the build), it is an
        interim texture, drawn until the block's own is built, as after a level change of a
        block on the GPU."""
        got = self.ready.get(b)
        self._drop(b)
        if got is None:
            self.misses += 1
        elif got[0] == level:
            self.hits += 1
        else:
            self.interims += 1
        return got

    def _drop(self, b: Block) -> None:
        got = self.ready.pop(b, None)
        if got is not None:
            self.nbytes -= len(got[1])
            self.version += 1
