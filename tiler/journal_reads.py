"""Reading the journal back: its entries, damage told from a transport failure.

A block is done exactly when its journal entry (:mod:`tiler.resume`) reads back intact. An
entry whose crc32c fails (damaged, torn) reads as not done: its block is computed again. A read
the store's transport fails is not damage: it is tried again (:data:`JOURNAL_READ_RETRIES`),
then the run stops with :class:`StoreUnavailableError` naming the store, the journal kept. The
entries are read a shard region at a time (:func:`read_journal_region`), a list of blocks at
once (:func:`read_journal_blocks`), or only those the journal's listing shows
(:func:`listed_journal_blocks`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import zarr

from tiler.errors import StoreUnavailableError
from tiler.transport import describe, is_transport_error, unavailable

log = logging.getLogger("tiler.tile")

#: the journal array's name in a store (its keys ``journal/c.<r>.<c>.0``)
JOURNAL = "journal"

#: what reading a damaged journal entry raises (its crc32c failing, a torn chunk): the entry is
#: not done and its block is computed again. A transport failure (an ``OSError``, a dropped
#: connection...) is not damage: the read is tried again, then :func:`_journal_unavailable`.
_DAMAGED = (ValueError, RuntimeError)
#: times a journal read that the transport failed is tried again (after the client's own
#: retries, :mod:`tiler.transport`), :data:`JOURNAL_RETRY_WAIT_S` apart, before the run stops
JOURNAL_READ_RETRIES = 1
JOURNAL_RETRY_WAIT_S = 0.5


def _journal_unavailable(
    subject: str, arr: zarr.Array, url: str | None, exc: BaseException, **where: Any
) -> StoreUnavailableError:
    """The error for a transport failure ``exc`` reading ``subject`` of the journal ``arr`` of
    the store at ``url`` (None: the array's store): the entries are not taken for not done
    (their blocks would be computed again, hours on a big job); the run stops, to be rerun."""
    err = unavailable(subject, url or str(arr.store), exc)
    n = JOURNAL_READ_RETRIES + 1
    tries = "once" if n == 1 else "twice" if n == 2 else f"{n} times"
    return StoreUnavailableError(
        f"{err} (tried {tries}; the blocks done so far are kept: rerun the same command to "
        "go on from them)",
        array=JOURNAL,
        **where,
    )


def _with_retries(
    call: Callable[[], Any], subject: str, arr: zarr.Array, url: str | None, **where: Any
) -> Any:
    """``call()``; a transport failure is tried again (:data:`JOURNAL_READ_RETRIES`), then
    raises :func:`_journal_unavailable`'s error; any other error is raised as it is."""
    for attempt in range(JOURNAL_READ_RETRIES + 1):
        try:
            return call()
        except Exception as exc:
            if not (isinstance(exc, OSError) or is_transport_error(exc)):
                raise
            if attempt == JOURNAL_READ_RETRIES:
                raise _journal_unavailable(subject, arr, url, exc, **where) from exc
            log.warning(
                "reading %s of %s failed (%s); trying again",
                subject, url or arr.store, describe(exc),
            )  # fmt: skip
            time.sleep(JOURNAL_RETRY_WAIT_S)
    raise AssertionError("unreachable")


def _read_or_damaged(
    read: Callable[[], Any], subject: str, arr: zarr.Array, url: str | None, **where: Any
) -> np.ndarray | None:
    """``read()`` as uint8; None when an entry read is damaged; a transport failure is tried
    again (:data:`JOURNAL_READ_RETRIES`), then raises :func:`_journal_unavailable`'s error."""
    try:
        return _with_retries(lambda: np.asarray(read(), dtype=np.uint8), subject, arr, url, **where)
    except _DAMAGED:
        return None


def read_journal_region(
    arr: zarr.Array,
    r0: int,
    r1: int,
    c0: int,
    c1: int,
    url: str | None = None,
    damaged: list[tuple[int, int]] | None = None,
) -> np.ndarray:
    """The raw journal entries of blocks ``[r0:r1, c0:c1]`` (uint8, one entry a block), read at
    once; when one is damaged (its crc32c fails) they are read one by one and a damaged one is
    left zero: not done (its block is computed again), and appended to ``damaged`` (if given).
    A transport failure raises :class:`StoreUnavailableError` naming the store (``url``)."""
    subject = f"the journal entries of blocks ({r0}..{r1 - 1}, {c0}..{c1 - 1})"
    raw = _read_or_damaged(lambda: arr[r0:r1, c0:c1], subject, arr, url)
    if raw is not None:
        return raw
    out = np.zeros((r1 - r0, c1 - c0, arr.shape[2]), dtype=np.uint8)
    for br in range(r0, r1):
        for bc in range(c0, c1):
            one = _read_entry(arr, br, bc, url)
            if one is not None:
                out[br - r0, bc - c0] = one
            elif damaged is not None:
                damaged.append((br, bc))
    return out


def read_journal_blocks(
    arr: zarr.Array,
    blocks: Sequence[tuple[int, int]],
    url: str | None = None,
    damaged: list[tuple[int, int]] | None = None,
) -> np.ndarray:
    """The raw journal entries of ``blocks`` (``(len(blocks), n)`` uint8), their chunks fetched
    together (one zarr call, not one a block); damaged ones left zero (and appended to
    ``damaged``) and transport failures raised, as :func:`read_journal_region`."""
    n = arr.shape[2]
    if not blocks:
        return np.zeros((0, n), dtype=np.uint8)
    rows, cols = (np.array(v, dtype=np.intp)[:, None] for v in zip(*blocks, strict=True))
    subject = f"the journal entries of {len(blocks)} block(s) from {tuple(blocks[0])} on"
    raw = _read_or_damaged(lambda: arr.vindex[rows, cols, np.arange(n)[None, :]], subject, arr, url)
    if raw is not None:
        return raw
    out = np.zeros((len(blocks), n), dtype=np.uint8)
    for i, (br, bc) in enumerate(blocks):
        one = _read_entry(arr, br, bc, url)
        if one is not None:
            out[i] = one
        elif damaged is not None:
            damaged.append((br, bc))
    return out


def _read_entry(arr: zarr.Array, br: int, bc: int, url: str | None) -> np.ndarray | None:
    """Block ``(br, bc)``'s raw journal entry; None when damaged."""
    subject = f"the journal entry of block ({br}, {bc})"
    return _read_or_damaged(lambda: arr[br, bc], subject, arr, url, block=(br, bc))


def listed_journal_blocks(
    loc: Any, arr: zarr.Array, url: str | None = None
) -> list[tuple[int, int]] | None:
    """The blocks that have a journal entry key, from one listing of the journal's prefix (on
    S3 a LIST a thousand keys, where reading every entry is a GET a block, a 404 for each block
    without one), row-major; None where the store cannot list (then every entry is read). A
    transport failure is tried again, then raises :class:`StoreUnavailableError` naming the
    store (``url``), as reading the entries does. A key missing from the listing only has its
    block recomputed if it is still bad: a listing never makes a block done."""
    rows, cols, _ = arr.shape
    sep = getattr(arr.metadata.chunk_key_encoding, "separator", ".")
    head = f"{JOURNAL}/c{sep}"
    try:
        keys = _with_retries(lambda: loc.list_keys(JOURNAL), "the journal's keys", arr, url)
    except NotImplementedError:
        return None
    blocks = set()
    for key in keys:
        if not key.startswith(head):
            continue  # (zarr.json, a leftover temporary file)
        parts = key[len(head) :].split(sep)
        if len(parts) != 3 or not all(p.isdigit() for p in parts) or parts[2] != "0":
            continue
        br, bc = int(parts[0]), int(parts[1])
        if br < rows and bc < cols:
            blocks.add((br, bc))
    return sorted(blocks)


def done_blocks(arr: zarr.Array, url: str | None = None) -> np.ndarray:
    """``(rows, cols)`` bool: blocks whose journal entry is written and intact. A transport
    failure raises :class:`StoreUnavailableError` naming the store (``url``)."""
    rows, cols, _ = arr.shape
    marks = _read_or_damaged(lambda: arr[:, :, -1], "the journal", arr, url)
    if marks is not None:
        return marks == 1
    out = np.zeros((rows, cols), bool)  # a torn or damaged entry: check block by block
    for br in range(rows):
        for bc in range(cols):
            one = _read_entry(arr, br, bc, url)
            out[br, bc] = one is not None and one[-1] == 1
    return out
