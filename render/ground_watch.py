"""Where the interactive viewer's camera is against the ground under it (:class:`GroundWatch`):
checked every frame, warned about once per descent, the ground found from blocks read on a
worker thread so that a remote store's read never stalls a frame."""

from __future__ import annotations

import logging
import math

from render.views import clearance_note
from streamer.camera import Camera
from streamer.clip import ground_height, near_reach
from streamer.pool import DaemonPool
from tiler.errors import StoreError
from tiler.store import TerrainStore

log = logging.getLogger("render.viewer")  # (the viewer's warnings, under its logger)


class GroundWatch:
    """Where the viewer's camera is against the ground under it, checked every frame: a
    warning is logged once per descent (flying below the terrain, or so close to it that the
    near plane clips it: :func:`render.views.clearance_note`), not every frame; it is said
    again only after the camera has been clear of the ground. Blocks read to find the ground
    are kept (at most :attr:`KEEP`) for the next frames. With ``background`` a block is read
    on a worker thread (``terrastream-ground``), not the render thread (a remote store's read
    would stall the frame): until it arrives the clearance there is unknown; :meth:`close`
    stops the worker."""

    KEEP = 16
    CLEAR, CLIPPED, BELOW = 0, 1, 2
    WAIT_S = 30.0  # the longest :meth:`check` with ``wait`` waits for a block

    def __init__(self, store: TerrainStore, *, background: bool = False) -> None:
        self.store = store
        self.cache: dict = {}
        self.unreadable: set = set()  # blocks whose read failed (the session reports them)
        self.pending: dict = {}  # block -> (the worker's read of it, the dict it fills)
        # (daemon threads: a read that hangs does not hold the process's exit, as a
        # ThreadPoolExecutor's, joined at exit, would: 8 s after the viewer closed)
        self.pool = DaemonPool(1, "terrastream-ground") if background else None
        self.warned = self.CLEAR  # the deepest state said since the camera was last clear
        self.level = self.CLEAR
        self.note = ""  # the last camera's clause ("" when clear or unknown)

    def close(self) -> None:
        """Stop the worker: a read in flight is left to finish (nothing waits for it)."""
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)

    def _has(self, block: tuple[int, int], x: float, y: float, wait: bool) -> bool:
        """Whether ``block`` is kept (read on the worker when ``background``; ``wait``: up to
        :attr:`WAIT_S` for it); False while it is on its way, or could not be read."""
        if block in self.cache or self.pool is None:
            return True
        if block in self.unreadable:
            return False
        if block not in self.pending:
            found: dict = {}  # the worker's own cache: ground_height keeps the block there
            self.pending[block] = (self.pool.submit(ground_height, self.store, x, y, found), found)
        fut, found = self.pending[block]
        if wait:
            from concurrent.futures import wait as wait_for

            wait_for([fut], timeout=self.WAIT_S)
        if not fut.done():
            return False
        del self.pending[block]
        try:
            fut.result()  # (any error but a failed read is the viewer's: raised here)
        except (OSError, StoreError):
            self.unreadable.add(block)
            return False
        if len(self.cache) >= self.KEEP:
            self.cache.clear()
        self.cache.update(found)
        return True

    def clearance(self, camera: Camera, *, wait: bool = False) -> float:
        """Height of ``camera`` above the terrain under it (negative below; ``inf`` high
        above its block's top plus its near plane's reach, NaN unknown: off the DEM, nodata,
        a block that cannot be read, or, in the background, not read yet unless ``wait``)."""
        g, (x, y, z) = self.store.grid, (float(v) for v in camera.position)
        row, col = (float(v) for v in g.world_to_sample(x, y))
        if not (0.0 <= row <= g.height - 1 and 0.0 <= col <= g.width - 1):
            return math.nan
        r0, c0 = min(int(math.floor(row)), g.height - 2), min(int(math.floor(col)), g.width - 2)
        block = tuple(int(v) for v in g.block_of_sample(max(r0, 0), max(c0, 0)))
        top = float(self.store.index.zmax[block])
        if not math.isfinite(top):
            return math.nan
        if not z < top + near_reach(camera):
            return math.inf
        if not self._has(block, x, y, wait):
            return math.nan
        if self.pool is None and len(self.cache) >= self.KEEP and block not in self.cache:
            self.cache.clear()
        try:
            ground = ground_height(self.store, x, y, self.cache)
        except (OSError, StoreError):  # the session reports a block that cannot be read
            return math.nan
        return math.nan if ground is None else z - ground

    def check(self, camera: Camera, *, quiet: bool = False, wait: bool = False) -> str:
        """``camera``'s clause (:func:`render.views.clearance_note`, ``""`` when clear or
        unknown), logging a warning when it has gone deeper than said since it was last clear
        (``quiet``: counted as said, not logged: the start camera, which its maker warns
        about, as :func:`render.views.make_camera` does; ``wait``: for a block on its way)."""
        c = self.clearance(camera, wait=wait)
        if math.isnan(c):  # unknown (off the DEM): neither a descent nor clear of the ground
            self.note = ""
            return ""
        self.note = clearance_note(camera, c)
        self.level = self.BELOW if c < 0 else self.CLIPPED if self.note else self.CLEAR
        if self.level == self.CLEAR:
            self.warned = self.CLEAR
        elif self.level > self.warned:
            self.warned = self.level
            if quiet:
                return self.note
            x, y, z = camera.position
            log.warning("the viewer's camera at x %.1f, y %.1f, z %.1f m: %s", x, y, z, self.note)
        return self.note

    def status(self) -> str:
        """A short tag for the status line (``""`` when the camera is clear of the ground)."""
        if not self.note:
            return ""
        return " | BELOW THE GROUND" if self.level == self.BELOW else " | near plane clips ground"
