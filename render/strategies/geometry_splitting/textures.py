"""``geometry-splitting``'s quadtree textures on the GPU: one shader storage buffer, a slot per
block as large as its texture (:class:`~render.strategies.geometry_splitting.slots.SlotTable`),
written in one batch per frame, grown by GPU-to-GPU copies (nothing rebuilt)."""

from __future__ import annotations

from collections.abc import Iterable

import moderngl

from render.strategies.geometry_splitting.pure import texture_nodes
from render.strategies.geometry_splitting.slots import SlotTable

Block = tuple[int, int]
#: a texture to write: the block, the level it was built for, its bytes, the depth to which it
#: is stored node by node (``pure.texture_depth``)
Write = tuple[Block, int, bytes, int]


class TextureStore:
    """The blocks' textures in one buffer; :attr:`level` and :attr:`depth` of each texture
    held (live or idle)."""

    def __init__(
        self, ctx: moderngl.Context, k: int, blocks: int, cache_bytes: int, min_bytes: int = 0
    ) -> None:
        self.ctx = ctx
        self.k = k
        full = texture_nodes(k, k - 1)
        self.slots = SlotTable(limit=blocks * full, cache=cache_bytes // 8, minimum=min_bytes // 8)
        #: every slot a full texture's when the first buffer holds the whole store's anyway
        #: (a texture changing size then never moves, nothing fragments)
        self.slot_size = full if blocks * full * 8 <= min_bytes else None
        self.buf: moderngl.Buffer | None = None
        self.level: dict[Block, int] = {}
        self.depth: dict[Block, int] = {}
        self._length: dict[Block, int] = {}  # each texture's nodes

    @property
    def offset(self) -> dict[Block, int]:
        """Each live block's slot (first 8-byte node)."""
        return self.slots.offset

    @property
    def nbytes(self) -> int:
        """Bytes of the GPU buffer."""
        return self.buf.size if self.buf is not None else 0

    def keep(self, live: Iterable[Block]) -> None:
        """Release the slots of the live blocks not in ``live`` (their textures stay, idle,
        until a new texture needs the room)."""
        self.slots.release_all_but(live)

    def holds(self, b: Block) -> bool:
        """Whether ``b`` has a texture here (live or idle)."""
        return b in self.level

    def revive(self, b: Block) -> bool:
        """Make ``b``'s idle texture live again, if its slot has not been taken."""
        return self.slots.revive(b)

    def write(self, writes: list[Write]) -> list[Block]:
        """Write each texture into its block's slot (growing the buffer first if they do not
        fit); the blocks whose idle textures gave way."""
        if not writes:
            return []
        for b, *_ in writes:  # (a batch must not evict one of its own blocks: none idle)
            if b not in self.offset:
                self.slots.revive(b)
        wants = [(b, self.slot_size or len(data) // 8) for b, _, data, _ in writes]
        cap = self.slots.grow_to(wants)
        gone: list[Block] = []
        if cap is not None:  # a new buffer, the kept textures copied GPU to GPU
            old = self.buf
            self.buf = self.ctx.buffer(reserve=cap * 8)
            moves, gone = self.slots.compact(cap, keep_free=sum(n for _, n in wants))
            for b, src, dst in moves:
                n = self.slots.size_of[b] * 8
                self.ctx.copy_buffer(self.buf, old, n, read_offset=src * 8, write_offset=dst * 8)
            if old is not None:
                old.release()
        for (b, lv, data, depth), (_, size) in zip(writes, wants, strict=True):
            off, evicted = self.slots.reserve(b, size)
            if evicted is not None:
                gone.append(evicted)
            self.buf.write(data, offset=off * 8)
            self.level[b], self.depth[b], self._length[b] = lv, depth, len(data) // 8
        for b in gone:
            self.level.pop(b, None)
            self.depth.pop(b, None)
            self._length.pop(b, None)
        return gone

    def bits(self, b: Block) -> bool:
        """Whether ``b``'s texture ends with the bitmask of its deeper nodes whose σ is ∞
        (``pure.texture_nodes``; False for a block without a texture)."""
        n = self._length.get(b)
        return n is not None and n > texture_nodes(self.k, self.depth[b])

    def read(self, b: Block) -> bytes:
        """The texture the GPU holds for live block ``b``."""
        return self.buf.read(self._length[b] * 8, offset=self.offset[b] * 8)

    def bind(self, binding: int) -> None:
        """Bind the buffer as shader storage ``binding`` (nothing before the first write)."""
        if self.buf is not None:
            self.buf.bind_to_storage_buffer(binding)
