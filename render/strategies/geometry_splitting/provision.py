"""``geometry-splitting``'s quadtree textures, what is built and where: a block's tree for its
resident level, packed for the GPU (``textures.TextureStore``), at once or on a worker thread
(``Strategy.build_in_background``: a level change keeps the block's texture until its new one is
built; a new block gets its first texture at :data:`PROVISIONAL_LEVEL`, built ahead on the
worker when the session held it before it was drawn, ``ahead.py``). No GL calls here but the
texture store's writes; :class:`TextureProvision` is the part of
:class:`~render.strategies.geometry_splitting.gl.GeometrySplitting` that provides them."""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial

import numpy as np

from render.builds import BackgroundBuilds
from render.frame import FrameServices
from render.strategies.base import Block
from render.strategies.geometry_splitting.ahead import AheadTextures
from render.strategies.geometry_splitting.kernels import (
    packed_tree,
    quad_errors,
    stored_tree,
    warm_up,
)
from render.strategies.geometry_splitting.pure import BlockTree, texture_depth
from render.strategies.geometry_splitting.textures import TextureStore, Write
from streamer.camera import Camera

_WARM_UP = ("kernels",)  # the background builds' first job
#: with background builds, a new block's first texture is built at once from this level's
#: grid (~2 ms at 1025²: its ranges from 65² corners, no exact errors), the texture of its
#: resident level on the worker thread
PROVISIONAL_LEVEL = 6


def build_tree(
    grid_of: Callable[[], np.ndarray],
    bound: list[np.ndarray],
    mask: np.ndarray | None,
    deep: range,
    mixed_of: Callable[[], list[np.ndarray] | None],
) -> BlockTree:
    """One block's quadtree texture (:func:`stored_tree`) from its level grid (``grid_of()``),
    stored ``bound`` errors, the exact errors at ``deep`` depths (full resolution, ``mask``'s
    samples) and σ = ∞ at the ``mixed_of()`` nodes (mask boundaries: refined). No GL: any
    thread."""
    grid = grid_of()
    exact = quad_errors(grid, mask, deep) if len(deep) else None
    tree = stored_tree(bound, grid, exact)
    mixed = mixed_of()
    if mixed is not None:
        for d, sig in enumerate(tree.sigma):
            sig[mixed[d]] = np.inf
    return tree


def _packed(job: Callable[[], BlockTree], depth: int) -> tuple[BlockTree, bytes, int]:
    tree = job()
    return tree, tree.packed(depth).tobytes(), depth


def _packed_texture(
    grid_of: Callable[[], np.ndarray],
    bound: list[np.ndarray],
    mixed_of: Callable[[], list[np.ndarray] | None],
    depth: int,
) -> tuple[bytes, int]:
    """A texture below full resolution and its depth, without the per-node arrays
    (:func:`packed_tree`), on any thread: the render thread's and the ones built ahead."""
    return packed_tree(bound, grid_of(), mixed_of(), depth=depth).tobytes(), depth


class TextureProvision:
    """The blocks' quadtree textures for :class:`GeometrySplitting` (its renderer ``r``, ``k``,
    texture store ``_tex`` and trees, set by its constructor)."""

    r: FrameServices
    k: int
    _tex: TextureStore
    trees: dict[Block, BlockTree]
    _tree_level: dict[Block, int]
    _builds: BackgroundBuilds[tuple[BlockTree, bytes, int]] | None
    _ahead_builds: BackgroundBuilds[tuple[bytes, int]] | None
    ahead: AheadTextures
    _ahead_key: tuple | None
    build_ms: float  # (Strategy's)
    build_cpu_ms: float

    def tree(self, b: Block, level: int | None = None) -> BlockTree:
        """The block's quadtree texture for its resident ``level`` (default: the GPU's), from
        the stored errors and that level's grid (:func:`build_tree`; rebuilt when the level
        changes)."""
        lv = self.r.gpu_level(b) if level is None else int(level)
        if self._tree_level.get(b) != lv or b not in self.trees:
            self.trees[b] = self._tree_job(b, lv)()
            self._tree_level[b] = lv
        return self.trees[b]

    def gpu_tree(self, b: Block, level: int) -> BlockTree:
        """The tree of the texture the GPU holds for ``b`` (drawn at ``level``): built for
        ``level``, or for the level before while its rebuild runs in the background."""
        return self.tree(b, self._tex.level.get(b, level) if self._builds else level)

    def _tree_job(self, b: Block, lv: int) -> Callable[[], BlockTree]:
        """Building ``b``'s tree for level ``lv``: its inputs gathered now, on the render
        thread (the session's arrays), the work left to the function (any thread)."""
        deep = range(self.r.store.meta.error_cap + 1, self.k) if lv == self.k else range(0)
        return partial(
            build_tree,
            self.r.block_grid_later(b, max(lv, 0)),
            self.r.stored_errors(b)["bound"],
            self.r.mask(b) if len(deep) else None,
            deep,
            self.r.mixed_nodes_later(b),  # (the session's loaders derived them)
        )

    def _depth(self, b: Block, lv: int) -> int:
        """The depth ``b``'s texture for level ``lv`` stores node by node
        (:func:`~render.strategies.geometry_splitting.pure.texture_depth`; a block with nodata
        adds the bitmask of its deeper nodes whose σ is ∞)."""
        return texture_depth(self.k, max(lv, 0), self.r.store.meta.error_cap)

    def _texture(self, b: Block, lv: int) -> tuple[bytes, int]:
        """The packed texture of ``b`` for level ``lv``, built now, and its depth: below full
        resolution without the per-node arrays (:func:`packed_tree`, the same bytes;
        :meth:`tree` builds them if asked), at full resolution from :meth:`tree` (its exact
        errors)."""
        depth = self._depth(b, lv)
        if lv >= self.k or self._tree_level.get(b) == lv:
            return self.tree(b, lv).packed(depth).tobytes(), depth
        grid_of, bound = self.r.block_grid_later(b, max(lv, 0)), self.r.stored_errors(b)["bound"]
        return _packed_texture(grid_of, bound, self.r.mixed_nodes_later(b), depth)

    def build_in_background(self) -> bool:
        """A block whose level changes keeps its texture until a worker thread has built the
        new one; a new block finer than :data:`PROVISIONAL_LEVEL` is drawn with the texture
        of that level (built at once) until then. Either texture bounds the block's terrain
        (σ from the stored errors, ranges around every sample) but Lee & Shin's projected
        error is evaluated at a range's mid-height, so the selection differs meanwhile."""
        if self._builds is None:
            self._builds = BackgroundBuilds("a geometry-splitting quadtree texture")
            # the compiled kernels loaded by the worker, before its first build (not the
            # render thread: ``auto`` then uses them in both)
            self._builds.want(_WARM_UP, 0, warm_up, "loading the compiled tree kernels (numba)")
            # first textures built ahead on a thread of their own: ~1 ms each, they would
            # wait behind a full-resolution tree's ~11 ms on the first
            self._ahead_builds = BackgroundBuilds("a geometry-splitting first texture", "ahead")
        return True

    def close(self) -> None:
        builds, ahead = self._builds, self._ahead_builds
        self._builds = self._ahead_builds = None
        try:
            if builds is not None:
                builds.close()
        finally:
            if ahead is not None:
                ahead.close()

    def interim_blocks(self, resident: dict[Block, int] | None = None) -> list[Block]:
        """The drawn blocks whose texture is not yet their drawn level's (its build runs in
        the background)."""
        return [b for b, lv in self.r.drawable(resident) if self._tex.level.get(b, lv) != lv]

    def settle(self, timeout: float = 30.0) -> None:
        """Wait for the background builds asked for so far (:meth:`build_in_background`);
        the next :meth:`select` uploads them."""
        for builds in (self._builds, self._ahead_builds):
            if builds is not None:
                builds.wait(timeout)

    def _take_built(self, level: dict[Block, int]) -> list[Write]:
        """The background builds that finished, where the block still has its texture and the
        level they were built for: to write."""
        out = []
        ahead, builds = self._ahead_builds, self._builds
        for b, lv, data_depth in ahead.done() if ahead is not None and self.ahead.asked else ():
            self.ahead.put(b, lv, *data_depth)
        for b, lv, built in builds.done() if builds is not None and len(builds) else ():
            if b == _WARM_UP:
                continue
            tree, data, depth = built
            if b in self._tex.offset and level.get(b, self.r.gpu_level(b)) == lv:
                out.append((b, lv, data, depth))
                self.trees[b], self._tree_level[b] = tree, lv
        return out

    def _upload_trees(self, pairs: list[tuple[Block, int]], camera: Camera | None = None) -> None:
        later: list[tuple[Block, int]] = []  # background builds, asked for after the frame's
        try:  # own (a worker started at once takes the GIL from them: 6-36 ms, not ~1.5)
            self._place_textures(pairs, later)
        finally:
            for b, lv in later:
                job = partial(_packed, self._tree_job(b, lv), self._depth(b, lv))
                self._builds.want(b, lv, job)
        if self._ahead_builds is not None and camera is not None:
            self._build_ahead(dict(pairs), camera)

    def _first_level(self, level: int) -> int:
        """The level of a new block's first texture with background builds (capped at
        :data:`PROVISIONAL_LEVEL`); -1 at full resolution (not built ahead: its texture
        needs the exact errors and is the block's tree)."""
        lv = min(int(level), PROVISIONAL_LEVEL)
        return lv if 0 <= lv < self.k else -1

    def _build_ahead(self, drawn: dict[Block, int], camera: Camera) -> None:
        """Ask the worker for the first textures of blocks the session holds but the GPU
        does not draw (``ahead.py``): the nearest to the camera first, a few at a time."""
        # the same session levels, drawn blocks, textures held and builds as last time:
        # nothing new to want (the scan below is ~0.1 ms with a few hundred blocks held)
        ahead, tex = self.ahead, self._tex
        key = (self.r.source.held_version(), tuple(drawn.items()), len(tex.level),
               ahead.version, len(ahead.asked))  # fmt: skip
        if key == self._ahead_key:
            return
        self._ahead_key = key
        held = self.r.source.held()
        if not held and not ahead.ready and not ahead.asked:
            return
        g, step = self.r.grid, self.r.grid.step

        def skip(b: Block) -> bool:
            return b in drawn or tex.holds(b)

        def nearest(blocks: list[Block]) -> list[Block]:
            blk = np.array(blocks, dtype=np.float64)
            x, y = g.sample_xy((blk[:, 0] + 0.5) * step, (blk[:, 1] + 0.5) * step)
            d2 = (x - camera.eye[0]) ** 2 + (y - camera.eye[1]) ** 2
            return [blocks[i] for i in np.argsort(d2, kind="stable")]

        for b, lv in ahead.wanted(held, self._first_level, skip, nearest):
            inputs = self.r.source.held_later(b, lv)
            if inputs is not None:
                grid_of, errors, mixed_of = inputs
                job = partial(
                    _packed_texture, grid_of, errors["bound"], mixed_of, self._depth(b, lv)
                )
                self._ahead_builds.want(b, lv, job, f"building the first texture of {b}")
                ahead.asking(b)

    def _place_textures(self, pairs: list[tuple[Block, int]], later: list) -> None:
        """Write the textures ``pairs`` need now; append those left to the worker to
        ``later``."""
        level = dict(pairs)
        tex = self._tex
        tex.keep([b for b in tex.offset if b in level or self.r.gpu_level(b) >= 0])
        for b in [b for b in self.trees if not tex.holds(b)]:  # (no texture, no heights)
            if b not in level and self.r.gpu_level(b) < 0:
                self._forget(b)
        for b, _ in pairs:  # back on the GPU before its slot was taken: its texture is there
            if b not in tex.offset:
                tex.revive(b)
        writes = self._take_built(level)
        fresh = {b for b, *_ in writes}
        for b, lv in pairs:
            if b in fresh or (b in tex.offset and tex.level[b] == lv):  # (its texture is there)
                continue
            if b in tex.offset and self._builds is not None:  # later: it keeps its texture
                later.append((b, lv))
                continue
            if b not in tex.offset and self._builds is not None:  # a new block
                first = min(lv, PROVISIONAL_LEVEL)
                got = self.ahead.take(b, first) if first < self.k else None
                if lv > first or (got is not None and got[0] != first):
                    later.append((b, lv))  # its own texture later (the worker's)
                if got is not None:  # built ahead, on the worker (for another level: interim)
                    writes.append((b, *got))
                    continue
                lv = first
            writes.append((b, lv, *self._texture(b, lv)))
        for b in tex.write(writes):
            self._forget(b)

    def _forget(self, b: Block) -> None:
        """Drop ``b``'s tree (its texture has gone, or it never had one)."""
        self.trees.pop(b, None)
        self._tree_level.pop(b, None)

    def upload_textures(self, pairs: list[tuple[Block, int]], camera: Camera) -> float:
        """Put the textures of the drawn ``pairs`` on the GPU (what this frame needs now; the
        rest asked of the worker); the wall ms, also kept with the CPU ms in ``build_ms`` and
        ``build_cpu_ms``."""
        tb, cb = time.perf_counter(), time.thread_time()
        self._upload_trees(pairs, camera)
        self.build_ms = (time.perf_counter() - tb) * 1000.0
        self.build_cpu_ms = (time.thread_time() - cb) * 1000.0  # (the render thread's CPU)
        return self.build_ms
