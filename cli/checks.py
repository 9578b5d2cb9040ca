"""Checks of the command line's paths made before any long run starts (exit 2, naming the path).

A run that would only fail at its end (``stream --json`` into a missing directory) fails here,
in the first second, instead.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from cli.common import UsageError


def is_local(url: str | os.PathLike) -> bool:
    """True for a plain filesystem path (not ``memory://``, ``s3://``, ``http://`` ...)."""
    text = str(url)
    return "://" not in text and not text.startswith("memory:")


def open_store_arg(url: Any, hint: str = "STORE", *, projected: bool = False) -> Any:
    """The store at ``url`` opened; a local path that does not exist is a usage error.

    ``projected``: the command streams or renders, so a geographic store (x/y in degrees) is
    refused before any camera or session is made (``tiler.crs.require_projected``).
    """
    from tiler.store import open_store

    if is_local(url) and not Path(str(url)).exists():
        raise UsageError(
            f"no store at {str(url)!r}: the path does not exist (make one with terrastream tile)",
            hint=hint,
        )
    not_a_store(url, hint)
    store = open_store(url)
    if projected:
        from tiler.crs import require_projected

        require_projected(store)
    return store


def not_a_store(url: Any, hint: str = "STORE") -> None:
    """A usage error when a local ``url`` is a file (a store is a directory): often the DEM
    itself, given where its store was meant ("Not a directory: 'dem.tif/zarr.json'"); or a
    directory with no zarr metadata at all (one with arrays but no root ``zarr.json`` is a
    damaged store: opening it says so, exit 1)."""
    path = Path(str(url))
    if is_local(url) and path.is_file():
        raise UsageError(
            f"{str(url)!r} is a file, not a store (a directory `terrastream tile` makes); if it "
            f"is a DEM, tile it first: terrastream tile {url} {path.with_suffix('.zarr')}",
            hint=hint,
        )
    if (
        is_local(url)
        and path.is_dir()
        and not (path / "zarr.json").exists()
        and not any(path.glob("*/zarr.json"))
    ):
        raise UsageError(
            f"{str(url)!r} is a directory but not a store (no zarr.json, no arrays): give "
            "the directory `terrastream tile` wrote",
            hint=hint,
        )


def input_file(path: Path | None, hint: str) -> Path | None:
    """``path`` if it names an existing regular file (``None`` passes)."""
    if path is None:
        return None
    if not path.exists():
        raise UsageError(f"{str(path)!r} does not exist", hint=hint)
    if path.is_dir():
        raise UsageError(f"{str(path)!r} is a directory, not a file", hint=hint)
    return path


def _probe_dir(directory: Path, hint: str, what: str) -> None:
    """Create and delete a scratch file in ``directory``: the only test that is never wrong."""
    if not directory.exists():
        raise UsageError(
            f"the directory {str(directory)!r} for {what} does not exist; create it first",
            hint=hint,
        )
    if not directory.is_dir():
        raise UsageError(f"{str(directory)!r} is not a directory", hint=hint)
    try:
        with tempfile.NamedTemporaryFile(dir=directory, prefix=".terrastream-probe-"):
            pass
    except OSError as exc:
        raise UsageError(
            f"cannot write in {str(directory)!r}: {exc.strerror or exc}", hint=hint
        ) from None


def _real(path: Any) -> Path:
    """``path`` made absolute with its symbolic links resolved (it need not exist)."""
    return Path(os.path.realpath(os.path.expanduser(str(path))))


def _same_file(a: Path, b: Path) -> bool:
    """``a`` and ``b`` name one file (by resolved path, or by device and inode: a hard link)."""
    if _real(a) == _real(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def not_an_input(path: Path | None, hint: str, inputs: Iterable[tuple[str, Any]]) -> None:
    """A usage error when the output ``path`` is one of the command's ``inputs`` — pairs of
    the option naming it and its value: a store (``STORE``: the directory and everything in
    it) or a file (``--path``). Refused with ``--overwrite`` too: it never replaces an input
    (``tradeoff s.zarr --json s.zarr/zarr.json`` destroyed the store it measured)."""
    if path is None:
        return
    out = _real(path)
    for what, value in inputs:
        if value is None or not is_local(value):
            continue
        src = Path(str(value))
        inside = _real(src) in out.parents and (src.is_dir() or not src.exists())
        if _same_file(path, src) or inside:
            where = "is inside" if inside else "is"
            raise UsageError(
                f"{str(path)!r} {where} the input {what} {str(value)!r} this command reads; "
                "give another file (--overwrite never replaces an input)",
                hint=hint,
            )


def distinct_outputs(*outputs: tuple[str, Path | None]) -> None:
    """A usage error when two output options (pairs of option and value; ``None`` skipped)
    name the same file: the second would overwrite the first."""
    given = [(hint, p) for hint, p in outputs if p is not None]
    for i, (hint, p) in enumerate(given):
        for other, q in given[:i]:
            if _same_file(p, q):
                raise UsageError(
                    f"{other} and {hint} both name {str(p)!r}; give each its own file",
                    hint=hint,
                )


def json_and_plot(
    json_out: Path | None, plot: Path | None, overwrite: bool, inputs: list[tuple[str, Any]]
) -> None:
    """The ``--json`` and ``--plot`` outputs of a measuring command (:func:`output_file` each,
    and not the same file)."""
    output_file(json_out, "--json", overwrite=overwrite, inputs=inputs)
    output_file(
        plot,
        "--plot",
        suffixes=plot_suffixes() if plot else None,
        overwrite=overwrite,
        inputs=inputs,
    )
    distinct_outputs(("--json", json_out), ("--plot", plot))


def output_file(
    path: Path | None,
    hint: str,
    *,
    suffixes: Iterable[str] | None = None,
    overwrite: bool | None = None,
    inputs: Iterable[tuple[str, Any]] = (),
) -> Path | None:
    """``path`` if a file can be written there (``None`` passes): its directory exists and is
    writable, it is not a directory, its extension is one of ``suffixes`` (when given), it
    does not exist unless ``overwrite`` is true (when given), and it is none of ``inputs``
    (:func:`not_an_input`: refused whatever ``overwrite`` says)."""
    if path is None:
        return None
    not_an_input(path, hint, inputs)
    if path.is_dir():
        raise UsageError(f"{str(path)!r} is a directory; give a file name", hint=hint)
    if suffixes is not None:
        allowed = sorted({s.lower() for s in suffixes})
        if path.suffix.lower() not in allowed:
            raise UsageError(
                f"cannot tell the file format of {str(path)!r} from its extension "
                f"{path.suffix or '(none)'!r}; use one of {', '.join(allowed)}",
                hint=hint,
            )
    if overwrite is False and path.exists():
        raise UsageError(f"{path} exists; pass --overwrite to replace it", hint=hint)
    _probe_dir(path.parent if str(path.parent) else Path("."), hint, str(path))
    return path


def output_dir(path: Path, hint: str) -> Path:
    """``path`` created if needed (a directory the command writes files into)."""
    if path.exists() and not path.is_dir():
        raise UsageError(f"{str(path)!r} exists and is not a directory", hint=hint)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(
            f"cannot create the directory {str(path)!r}: {exc.strerror or exc}", hint=hint
        ) from None
    _probe_dir(path, hint, "the output files")
    return path


def remove_if_left_empty(path: Path, made: bool) -> None:
    """Remove the directory ``path`` when this run made it (``made``) and left it empty (a
    command that failed before writing anything leaves no empty output folder behind)."""
    if made and path.is_dir() and not any(path.iterdir()):
        path.rmdir()


def store_destination(url: str, hint: str = "DST") -> str:
    """``url`` if a store can be made there: for a local path, its parent directory exists
    and is writable; an ``http(s)://`` URL is read-only (other locations are checked by the
    tiler)."""
    from tiler.remote import is_http

    if is_http(url):
        raise UsageError(
            f"{url!r} is an http(s) store, which is read-only here: tile (or --repair) a local "
            "directory or an object store (s3://...) and serve that",
            hint,
        )
    if is_local(url):
        path = Path(url)
        if path.exists() and not path.is_dir():
            raise UsageError(f"{url!r} exists and is a file, not a store directory", hint)
        _probe_dir(path.parent if str(path.parent) else Path("."), hint, url)
    return url


def image_suffixes() -> set[str]:
    """File extensions Pillow can write."""
    from PIL import Image

    Image.init()
    return {ext for ext, fmt in Image.registered_extensions().items() if fmt in Image.SAVE}


def plot_suffixes() -> set[str]:
    """File extensions matplotlib can write."""
    from matplotlib.figure import Figure

    return {"." + ext for ext in Figure().canvas.get_supported_filetypes()}
