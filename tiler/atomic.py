"""Files written whole or not at all, as zarr's ``LocalStore`` writes them: the bytes go to a
temporary ``*.partial`` file beside the target, which is then renamed over it. A killed writer
leaves a ``*.partial`` file (``Location.remove_partial_files`` clears them), never half a
target; a failed write removes its temporary file and raises."""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
import uuid
from collections.abc import Callable, Iterator
from typing import Any


def partial_name(path: str) -> str:
    """A private temporary name beside ``path`` (``<path>.<random>.partial``)."""
    return f"{path}.{uuid.uuid4().hex}.partial"


_OWN_PARTIAL = re.compile(r"\.[0-9a-f]{32}\.partial$")


def is_own_partial(name: str) -> bool:
    """True for a name :func:`partial_name` makes (a leftover of an interrupted write), not
    any file that happens to end in ``.partial``."""
    return _OWN_PARTIAL.search(name) is not None


def write_atomic(path: str, *pieces: Any) -> int:
    """Write ``pieces`` (bytes-like, one after another) to the file ``path`` atomically,
    creating its directory if needed; returns the bytes written."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = partial_name(path)
    try:
        with open(tmp, "wb") as f:
            n = sum(f.write(p) for p in pieces)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return n


def _umask() -> int:
    """The process's umask: from ``/proc/self/status`` (Linux), else read by setting it and
    setting it back (a brief window in which another thread's new files would get 022)."""
    with contextlib.suppress(OSError, ValueError), open("/proc/self/status") as f:
        for line in f:
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def readable_whole(path: str, out: str) -> None:
    """Read every block of the raster just written at ``path`` back: GDAL reports a write that
    failed when its cache is flushed (a full disk: "No space left on device") only on
    stderr, and the file it leaves is cut short. :class:`tiler.errors.OutputError` naming
    ``out`` if any block cannot be read."""
    import rasterio
    import rasterio.errors

    from tiler.errors import OutputError

    try:
        with rasterio.open(path) as ds:
            for _, window in ds.block_windows(1):
                ds.read(window=window)
    except rasterio.errors.RasterioError as exc:
        raise OutputError(
            f"cannot write {out!r}: the raster written could not be read back whole ({exc}); "
            "is the disk full? Nothing was written there"
        ) from exc


@contextlib.contextmanager
def raster_written_whole(
    out: str | os.PathLike, before_rename: Callable[[], None] | None = None
) -> Iterator[str]:
    """A temporary path beside ``out`` to write a raster to; once written, read back whole
    (:func:`readable_whole`) and ``before_rename`` passed, it is renamed to ``out`` (with the
    mode a new file gets), else removed: a partial raster (an error, a full disk, Ctrl-C)
    never looks complete, and an ``out`` being replaced stays as it was until then."""
    out = os.path.abspath(os.fspath(out))
    where, name = os.path.split(out)
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".partial.tif", dir=where)
    os.close(fd)
    try:
        yield tmp
        readable_whole(tmp, out)
        if before_rename is not None:
            before_rename()
        os.chmod(tmp, 0o666 & ~_umask())  # (mkstemp's file is 0600)
        os.replace(tmp, out)
    except BaseException:
        for leftover in (tmp, tmp + ".aux.xml"):
            with contextlib.suppress(OSError):
                os.unlink(leftover)
        raise
