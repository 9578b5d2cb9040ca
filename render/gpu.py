"""OpenGL resources: the headless context and the GPU height pool (the only moderngl users
besides :mod:`render.renderer`).

:class:`HeightPool` keeps each resident block's decoded level sequence (levels ``0..L``
concatenated, float32 metres, masked samples set to :data:`MASKED`) in shader storage buffers
("pages", each at most ``GL_MAX_SHADER_STORAGE_BLOCK_SIZE``). A block owns one slot sized for its
level (``(2**L+1)**2`` floats); slots are recycled through per-level free lists, pages grow by
doubling, and a block that gains levels beyond its slot moves to a bigger one (a GPU-side copy).
Only newly arrived levels are uploaded.
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from render.errors import GLStateError, GLUnavailableError
from tiler.layout import grid_side, level_end, level_start, sequence_index

#: the one masked-height sentinel (GLSL: ``MASKED_HEIGHT``, defined by render/shaders.py)
MASKED = np.float32(-1.0e30)
#: read-back heights at or below this are masked (far below any terrain, far above MASKED)
MASKED_BELOW = -1.0e29
MIN_PAGE_FLOATS = 1 << 20


def create_context() -> moderngl.Context:
    """A headless OpenGL 4.5 context through EGL (Mesa llvmpipe works)."""
    try:
        return moderngl.create_standalone_context(backend="egl", require=450)
    except Exception as exc:  # noqa: BLE001 - any EGL/driver failure means "no GL here"
        raise GLUnavailableError(
            f"cannot create a headless OpenGL 4.5 context through EGL: {exc} "
            "(install Mesa's EGL libraries: make gl-libs)"
        ) from exc


def check_gl(ctx: moderngl.Context, where: str) -> None:
    """Raise :class:`GLStateError` if OpenGL has recorded an error."""
    err = ctx.error
    if err != "GL_NO_ERROR":
        raise GLStateError(f"OpenGL error {err} {where}")


@dataclass
class _Slot:
    page: int
    offset: int  # in floats
    cls: int  # level the slot is sized for
    level: int  # finest level uploaded


class _Page:
    def __init__(self, ctx: moderngl.Context, floats: int) -> None:
        self.buffer = ctx.buffer(reserve=floats * 4)
        self.capacity = floats
        self.used = 0


class HeightPool:
    """Block level sequences on the GPU, addressed by ``(page, base offset)``; heights are
    stored relative to ``zref`` (docs/RENDER.md, "Precision and extremes")."""

    def __init__(
        self,
        ctx: moderngl.Context,
        k: int,
        max_page_floats: int | None = None,
        zref: float = 0.0,
    ) -> None:
        self.ctx = ctx
        self.zref = float(zref)  # heights are stored as float32(h - zref), subtracted in float64
        self.k = k
        limit = int(ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE", 1 << 27)) // 4
        self.max_page = min(limit, max_page_floats or limit)
        self.pages: list[_Page] = []
        self._free: dict[int, list[tuple[int, int]]] = {}
        self.slots: dict[tuple[int, int], _Slot] = {}
        side = grid_side(k)
        self._seq = np.asarray(sequence_index(k)).reshape(side, side)

    @property
    def nbytes(self) -> int:
        """Bytes of GPU buffers allocated."""
        return sum(p.capacity * 4 for p in self.pages)

    @property
    def used_bytes(self) -> int:
        """Bytes of slots owned by blocks."""
        return sum(4 * grid_side(s.cls) ** 2 for s in self.slots.values())

    def level(self, block: tuple[int, int]) -> int:
        """Finest level of ``block`` on the GPU (-1 if none)."""
        s = self.slots.get(block)
        return -1 if s is None else s.level

    def _alloc(self, cls: int) -> tuple[int, int]:
        free = self._free.get(cls)
        if free:
            return free.pop()
        n = grid_side(cls) ** 2
        if n > self.max_page:
            raise GLStateError(f"a level-{cls} block needs {n} floats, over one GPU page")
        for i, p in enumerate(self.pages):
            if p.used + n <= p.capacity:
                p.used += n
                return i, p.used - n
            if p.used + n <= self.max_page and p.capacity < self.max_page:
                self._grow(i, max(p.used + n, min(2 * p.capacity, self.max_page)))
                p = self.pages[i]
                p.used += n
                return i, p.used - n
        self.pages.append(_Page(self.ctx, max(n, min(MIN_PAGE_FLOATS, self.max_page))))
        p = self.pages[-1]
        p.used = n
        return len(self.pages) - 1, 0

    def _grow(self, i: int, floats: int) -> None:
        old = self.pages[i]
        new = _Page(self.ctx, floats)
        if old.used:
            self.ctx.copy_buffer(new.buffer, old.buffer, old.used * 4)
        new.used = old.used
        old.buffer.release()
        self.pages[i] = new

    def upload(
        self, block: tuple[int, int], levels: list[np.ndarray], mask: np.ndarray | None = None
    ) -> int:
        """Make ``levels`` (decoded, sequence order) resident; upload only new ones; return L."""
        top = len(levels) - 1
        slot = self.slots.get(block)
        if top < 0 or (slot is not None and slot.level >= top):
            return -1 if slot is None else slot.level
        if slot is None or slot.cls < top:
            page, off = self._alloc(top)
            new = _Slot(page, off, top, -1)
            if slot is not None:
                n = grid_side(slot.level) ** 2 * 4
                self.ctx.copy_buffer(
                    self.pages[page].buffer,
                    self.pages[slot.page].buffer,
                    n,
                    read_offset=slot.offset * 4,
                    write_offset=off * 4,
                )
                new.level = slot.level
                self._free.setdefault(slot.cls, []).append((slot.page, slot.offset))
            slot = new
            self.slots[block] = slot
        first = slot.level + 1
        data = np.concatenate(
            [(np.asarray(v, dtype=np.float64) - self.zref).astype(np.float32)
             for v in levels[first : top + 1]]
        )  # fmt: skip
        if mask is not None and not mask.all():
            seq_mask = np.ones(self._seq.size, dtype=bool)
            seq_mask[self._seq.ravel()] = mask.ravel()
            data[~seq_mask[level_start(first) : level_end(top) + 1]] = MASKED
        self.pages[slot.page].buffer.write(
            data.tobytes(), offset=(slot.offset + level_start(first)) * 4
        )
        slot.level = top
        return top

    def release(self, block: tuple[int, int]) -> None:
        """Forget a block (its slot is reused)."""
        s = self.slots.pop(block, None)
        if s is not None:
            self._free.setdefault(s.cls, []).append((s.page, s.offset))

    def close(self) -> None:
        """Release the GPU buffers."""
        for p in self.pages:
            p.buffer.release()
        self.pages.clear()
        self.slots.clear()
        self._free.clear()
