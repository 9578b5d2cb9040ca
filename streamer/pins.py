"""Pinning a frame's levels: what to queue, the pins, and the error when they exceed the budget.

Each frame pins the levels its visible blocks need in the cache (pinned levels are never
evicted) and queues the blocks that lack one (:func:`pin_and_queue`, found by
:func:`to_queue` before the caller takes the lock). When the pins exceed the byte budget the
cache says "raise the budget or the error threshold τ"; when no τ can help — the view's
visible blocks need more than the budget even at the levels an unbounded τ still asks for (the
patch level; beside nodata, what the nodata rule keeps) — the advice would mislead, and
:func:`budget_error` words one that gives that floor instead: the smallest budget that fits.
"""

from __future__ import annotations

import logging

import numpy as np

from streamer.cache import Block, PinChanges, mib_text
from streamer.camera import Camera
from streamer.errors import BudgetError
from streamer.loader import READ_ERRORS, Loader
from streamer.planner import Planner

#: (the session's logger: its messages kept their name when this module was split from it)
log = logging.getLogger("streamer.session")

#: the τ a budget error plans with to find the least a view needs (any larger changes nothing)
UNBOUNDED_TAU = 1e30


def to_queue(
    loader: Loader, needed: dict[Block, int], levels: np.ndarray | None = None
) -> list[Block]:
    """The blocks of ``needed`` (a frame's visible blocks and levels) that lack a level and
    are not queued as visible yet (no lock needed: single dict reads; a block loaded meanwhile
    is re-checked when taken). ``levels``: ``needed``'s values as an array, if the caller has
    it."""
    blocks = list(needed)
    lv = levels_of(needed) if levels is None else levels
    unknown = loader.errors.lookup(blocks) < 0
    short = np.flatnonzero(unknown | (loader.cache.levels_array(blocks) < lv))
    queued = loader.queue.queued_key
    out = []
    for i in short.tolist():
        b = blocks[i]
        # a visible block's key starts (0 if its errors are unknown else 1, 0): one already
        # queued at least that urgently is not pushed again (no key computed)
        best = queued(b)
        if best is not None and best[1] == 0 and best[0] <= (0 if unknown[i] else 1):
            continue
        out.append(b)
    return out


def pin_and_queue(
    loader: Loader,
    planner: Planner,
    needed: dict[Block, int],
    cum_bytes: list[int],
    todo: list[Block] | None = None,
    need: int | None = None,
    changes: PinChanges | None = None,
    *,
    camera: Camera | None,
) -> int:
    """Pin a frame's levels ``needed`` and queue the missing ones; how many were queued
    (``todo``: :func:`to_queue`'s answer, ``changes``: ``LevelCache.pin_changes``', both found
    before taking the lock; ``need``: the pinned bytes, if summed; ``camera``: the pose they
    are for, to word a :func:`budget_error`; caller holds the loader's lock)."""
    try:
        loader.cache.set_pins(needed, loader.level_bytes, need, changes)
    except BudgetError as exc:
        raise budget_error(exc, needed, camera, planner, loader, cum_bytes) from None
    if todo is None:
        todo = to_queue(loader, needed)
    push = loader.push
    for b in todo:
        push(b)
    return len(todo)


def levels_of(needed: dict[Block, int]) -> np.ndarray:
    """A needed mapping's levels as an int64 array (in its order)."""
    return np.fromiter(needed.values(), dtype=np.int64, count=len(needed))


def budget_error(
    exc: BudgetError,
    needed: dict[Block, int],
    camera: Camera | None,
    planner: Planner,
    loader: Loader,
    cum_bytes: list[int],
) -> BudgetError:
    """``exc`` (the pins ``needed`` exceed the budget), or, when no τ can help, an error saying
    so and giving the smallest budget that fits the view from ``camera`` (``cum_bytes[L]``: the
    decoded bytes of levels ``0..L`` of a block)."""
    if exc.template is None or camera is None or not needed:
        return exc
    # the levels a block needs at any τ come from its error table: a block whose table is not
    # read yet (the first frame's, during warm-up) would count at the patch level, a floor
    # that fails again once the table arrives; read them now (an error's path)
    unread = read_error_tables(loader, planner.visible(camera))
    least = planner.needed(camera, tau=UNBOUNDED_TAU)
    floor = sum(cum_bytes[lv] for lv in least.values() if lv >= 0)
    if floor <= loader.cache.budget:
        return exc  # a larger τ fits: the advice holds
    # the need counted blocks whose error tables were not read at their coarsest levels (the
    # warm-up's first frame): said beside the floor, it read less than the least a view needs
    # at any τ ("need 0.0044 MiB ... at any tau at least 0.0059 MiB")
    values = dict(exc.values)
    before = sum(cum_bytes[lv] for lv in needed.values() if lv >= 0)
    now = sum(cum_bytes[lv] for lv in planner.needed(camera).values() if lv >= 0)
    if now > before:
        values["need"] = mib_text(now)
    has = loader.store.index.has_nodata
    rule = loader.config.nodata
    n, holes = len(least), sum(1 for b in least if has[b])
    who = "it" if n == 1 else f"{holes} of them"
    hold, stay = ("holds", "stays") if who == "it" or holes == 1 else ("hold", "stay")
    why = ""
    if holes and rule == "full":
        why = (
            f" ({who} {hold} nodata beside terrain and {stay} at full resolution under the "
            "nodata rule 'full')"
        )
    elif holes:
        why = (
            f" ({who} {hold} nodata beside terrain, which the nodata rule "
            f"'{rule}' refines while its cells span more than a pixel)"
        )
    if unread:
        why += (
            f" ({unread} of them counted at their coarsest levels: their error tables could"
            " not be read, so they may need more)"
        )
    return BudgetError(
        "the visible blocks need {need} at their levels but the budget is {budget}; at "
        "any {tau} {visible} at least {floor}" + why + ": raise {budget_mb} to at least that",
        params=exc.params,
        **values,
        visible="the visible block needs" if n == 1 else f"the {n} visible blocks need",
        floor=mib_text(floor),
    )


def read_error_tables(loader: Loader, blocks: list[Block]) -> int:
    """Read, on the caller's thread, the error tables of those of ``blocks`` ``loader`` has not
    read yet, as its loaders do (for a budget error's floor); the number that could not be
    read (each logged)."""
    unread = 0
    for b, slot in zip(blocks, loader.errors.lookup(blocks).tolist(), strict=True):
        if slot >= 0:
            continue
        try:
            data = loader.read_errors(b)
        except READ_ERRORS as exc:
            log.warning("reading the error table of block %s failed: %s", b, exc)
            unread += 1
            continue
        loader.errors.add(b, *data)
    return unread
