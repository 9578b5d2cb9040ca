"""Where a tiling writes: what is at the destination (absent, a store, something else), clearing
it for a rerun, and creating a fresh store's root, arrays and journal (:func:`create_store`)."""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import zarr

from tiler.atomic import is_own_partial
from tiler.errors import StoreError
from tiler.interrupt import DeferredInterrupt
from tiler.lease import LEASE_KEY
from tiler.location import Location
from tiler.meta import StoreMeta, read_meta, sealed, write_meta
from tiler.resume import check_same_job, create_journal, source_of
from tiler.schema import ATTR, compact_metadata, create_layout

if TYPE_CHECKING:
    from tiler.tile import TileOptions

log = logging.getLogger("tiler.tile")


def check_unfinished_is_recreatable(
    loc: Location, old: StoreMeta, job: dict, source: str | None = None
) -> None:
    """An unfinished store without a resumable state: same job (or a layout kill) recreates it
    (``source``: this run's, named when the store's differs)."""
    if old.extra.get("state") == "layout":
        log.info("%s was interrupted while its layout was created: creating it again", loc.url)
        return
    check_same_job(loc.url, old.extra.get("job"), job, sources=(source_of(old.source), source))


def inspect_destination(loc: Location) -> tuple[str, StoreMeta | None, str]:
    """``("absent" | "store" | "foreign", meta, reason)`` of what is stored at ``loc``."""
    if not loc.exists():
        return "absent", None, ""
    if loc.is_local:
        p = loc.path
        if not p.is_dir():
            return "foreign", None, "it is a file"
        names = {c.name for c in p.iterdir() if not is_own_partial(c.name)}
        if not names - {LEASE_KEY}:
            return "absent", None, ""
        if "zarr.json" not in names:
            return "foreign", None, "a non-empty directory without zarr.json"
    elif not loc.key_exists("zarr.json"):
        return "foreign", None, "no zarr.json"
    try:
        return "store", read_meta(loc.open_group("r")), ""
    except (StoreError, FileNotFoundError, ValueError, KeyError) as exc:
        return "foreign", None, str(exc)


def clear_destination(loc: Location) -> None:
    """Remove everything at ``loc`` but the writer lease."""
    if loc.is_local:
        if loc.path.is_dir():
            for child in loc.path.iterdir():
                if child.name != LEASE_KEY:
                    Location(str(child)).remove()
        return
    loc.remove()


def clean_siblings(loc: Location) -> None:
    """Remove leftovers of interrupted overwrites (``<dst>.tmp-*``, ``<dst>.old-*``)."""
    p = loc.path
    for sib in p.parent.glob(p.name + ".tmp-*"):
        Location(str(sib)).remove()
    for sib in p.parent.glob(p.name + ".old-*"):
        Location(str(sib)).remove()


def fresh_group(loc: Location, meta: StoreMeta) -> zarr.Group:
    """Create the root group with the metadata in state ``layout`` (one write)."""
    try:
        return loc.open_group("a", attributes={ATTR: sealed(meta)})
    except (OSError, ValueError) as exc:
        raise StoreError(f"cannot create a store at {loc.url!r}: {exc}") from exc


def create_store(loc: Location, meta: StoreMeta, opts: TileOptions) -> zarr.Group:
    """Create the root, every array and the journal; leave the store in state ``tiling``.

    A Ctrl-C meanwhile is raised once the layout is written (~0.05 s): raised inside zarr's
    synchronous call it left zarr's event loop with pending writes, which logged asyncio
    errors and tracebacks after the CLI's one line (:mod:`tiler.interrupt`)."""
    meta = replace(meta, extra=dict(meta.extra, state="layout"))
    with DeferredInterrupt(), compact_metadata():
        group = fresh_group(loc, meta)
        create_layout(group, meta, opts.compression_level)
        create_journal(group, *meta.grid.shape, meta.k, meta.storage_dtype)
        write_meta(group, replace(meta, extra=dict(meta.extra, state="tiling")))
    return group
