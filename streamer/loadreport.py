"""What a loader's state says, for the messages of a wait that ran out and for the session's
summary: where the missing levels stand, where the loads stand, which blocks are failing
(read-only; the caller holds the loader's lock)."""

from __future__ import annotations

from typing import Any

from streamer.cache import Block
from streamer.loader import Loader
from tiler.errors import StoreUnavailableError


def describe_missing(
    ld: Loader, missing: list[tuple[Block, int]], now: float, most: int = 3
) -> str:
    """The first ``most`` missing block levels and where each stands (caller holds ``ld``'s
    lock): resident level, errors read, queued, fetching, failures in a row, next retry,
    and the budget's bytes in use and reserved."""
    q, cache = ld.queue, ld.cache
    parts = []
    for b, lv in missing[:most]:
        retry = q.retry_at.get(b, 0.0) - now
        parts.append(
            f"block {b} level {lv}: resident {cache.level(b)}, errors "
            f"{'read' if b in ld.errors else 'not read'}, "
            f"{'queued' if q.queued_key(b) is not None else 'not queued'}, fetching "
            f"{sorted(ld.fetching.get(b, ()))}, {q.failures.get(b, 0)} failure(s) in a row"
            + (f", retry in {retry:.2f} s" if retry > 0 else "")
        )
    more = f"; {len(missing) - most} more" if len(missing) > most else ""
    budget = f"; budget {cache.nbytes:,} of {cache.budget:,} bytes ({cache.reserved:,} reserved)"
    return "; ".join(parts) + more + budget


def stuck(ld: Loader) -> str:
    """Where ``ld``'s loads stand, for a wait that timed out (caller holds its lock)."""
    reading = sum(len(v) for v in ld.fetching.values())
    text = f"{len(ld.queue)} load(s) queued, {reading} read(s) running"
    if ld.last_error:
        text += f", {len(ld.last_error)} block(s) failing; latest: {ld.latest_error}"
    return text


def failing(ld: Loader) -> dict[str, Any]:
    """The blocks whose latest read failed: how many, how many a frame needed, how many
    for the server's fault (:class:`StoreUnavailableError`), the latest error, and the
    store's change if one ended the loading (caller holds ``ld``'s lock). A frame needed a
    block if a level of it a frame lacked has not arrived since (``Loader.demanded``): a
    failing level never arrives, so its block stays needed after the frame (even once the
    camera moved on: ``Loader.forget_steps`` keeps a failing block's demands); a block whose
    only failing read is of a level read ahead, its frames' levels all arrived, is not."""
    needed = {b for b, _ in ld.demanded}
    errs = ld.last_error
    return {
        "failing_blocks": len(errs),
        "failing_blocks_needed": sum(1 for b in errs if b in needed),
        "failing_blocks_unreachable": sum(
            1 for e in errs.values() if isinstance(e, StoreUnavailableError)
        ),
        "last_read_error": None if ld.latest_error is None else str(ld.latest_error),
        "store_changed": None if ld.fatal is None else str(ld.fatal),
    }
