"""``terrastream verify``: check every chunk and the metadata of a store."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.checks import input_file, is_local, not_a_store, open_store_arg
from cli.common import EXIT_RUNTIME, fail_on_errors
from cli.formatters import json_text
from cli.options import StorageOptionsOpt, store_location

MAX_LISTED = 20  # problems printed one per line; the rest are counted (all are in --json)


def verify(
    store: Annotated[str, typer.Argument(help="A terrastream store (path or URL).")],
    source: Annotated[
        list[str] | None,
        typer.Option(
            "--source",
            metavar="SRC",
            help="Also recompute every block's digest from this source DEM (read with the "
            "store's band and reprojection); repeat it for each source of a mosaic, in order.",
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the report as JSON.")] = False,
    storage_options: StorageOptionsOpt = None,
) -> None:
    """Check every chunk's checksum, the index and the metadata; exit 1 if anything is wrong.

    A damaged store is mended from its source with ``terrastream tile SRC STORE --repair``.

    Example: terrastream verify n44.zarr --source N44W072.hgt
    """
    from tiler.remote import is_http
    from tiler.source_header import is_file_path
    from tiler.verify import verify_store

    with fail_on_errors():
        if is_local(store) and not Path(store).exists():
            open_store_arg(store)  # the usage error
        not_a_store(store)
        for path in source or []:  # (a URL, /vsi... path or subdataset is checked on open)
            if is_file_path(path):
                input_file(Path(path), "--source")
        rep = verify_store(store_location(store, storage_options), source=source or None)
        if as_json:
            typer.echo(json_text(rep.to_json(), indent=2))
        else:
            for p in rep.problems[:MAX_LISTED]:
                where = f" block {p.block}" if p.block is not None else ""
                level = f" level {p.level}" if p.level is not None else ""
                typer.echo(f"{p.kind}: {p.array or 'store'}{where}{level}: {p.message}")
            if len(rep.problems) > MAX_LISTED:
                typer.echo(f"... and {len(rep.problems) - MAX_LISTED} more (--json lists all)")
            checks = "crc32c checksums" if rep.checksummed else "no checksums (format 1)"
            if rep.format_version is None:
                checks = "the root metadata is unreadable"
            if rep.format_version is not None and not rep.metadata_checksummed:
                checks += "; the root metadata has no checksum (an older store)"
            if rep.checksummed and rep.complete and not rep.content_checked and rep.ok:
                checks += "; content digests: none (an older store: tile it again to add them)"
            elif rep.content_checked:
                checks += ", content digests"
            status = "ok" if rep.ok else f"{len(rep.bad_blocks)} bad block(s)"
            if not rep.ok and not rep.bad_blocks and all(p.kind == "source" for p in rep.problems):
                status = "the source does not match"
            if rep.unfinished:
                status = f"unfinished ({rep.state}), {status}"
            if rep.bad_tables:
                status += f", {len(rep.bad_tables)} damaged index table(s)"
            if rep.unrepairable:
                status += f", {len(rep.unrepairable)} problem(s) --repair cannot mend"
            typer.echo(
                f"{store}: {status}; {rep.chunks_checked} chunks checked ({checks}), "
                f"{rep.blocks_total} blocks"
                + (", source digests compared" if rep.source_checked else "")
            )
        if not rep.ok:
            if not as_json and rep.unfinished and rep.writer is not None:
                typer.echo(
                    f"error: {store} is being written now by {rep.writer}; verify it once "
                    "that tiling finishes",
                    err=True,
                )
            elif not as_json and rep.unfinished:
                then = " (then `--repair` the bad blocks listed)" if rep.bad_blocks else ""
                typer.echo(
                    f"error: {store} is unfinished (an interrupted tiling); rerun the same "
                    f"`terrastream tile SRC {store}` command to finish it{then}",
                    err=True,
                )
            elif not as_json and rep.unrepairable:  # (what `tile --repair` refuses)
                typer.echo(
                    f"error: {store} is damaged beyond what --repair mends "
                    f"({rep.unrepairable[0]}); tile the DEM again with --overwrite",
                    err=True,
                )
            elif not as_json and all(p.kind == "source" for p in rep.problems):
                # the store's own checks passed: `--repair` (which mends what they find) has
                # nothing to recompute, so it is not the advice
                n = len(rep.bad_blocks)
                what = f"{n} block(s) differ from" if n else "the store does not match"
                typer.echo(
                    f"error: {store} is intact but {what} the source given: it is not the DEM "
                    "this store was tiled from (or it changed since, or the sources differ from "
                    "the tiling's). To store it, tile it again with --overwrite",
                    err=True,
                )
            elif not as_json and is_http(store):
                typer.echo(  # (an http(s) store is read-only: mended where it is written)
                    f"error: {store} is damaged; run `terrastream tile SRC STORE --repair` on the "
                    "store it is served from (a local directory or object store) to recompute "
                    "the bad blocks from the source",
                    err=True,
                )
            elif not as_json:
                typer.echo(
                    f"error: {store} is damaged; rerun `terrastream tile SRC {store} --repair` "
                    "to recompute the bad blocks from the source (and rewrite damaged tables)",
                    err=True,
                )
            raise typer.Exit(EXIT_RUNTIME)


def register(app: typer.Typer) -> None:
    """Add ``verify`` to ``app``."""
    app.command("verify")(verify)
