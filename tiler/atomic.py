"""Files written whole or not at all, as zarr's ``LocalStore`` writes them: the bytes go to a
temporary ``*.partial`` file beside the target, which is then renamed over it. A killed writer
leaves a ``*.partial`` file (``Location.remove_partial_files`` clears them), never half a
target; a failed write removes its temporary file and raises."""

from __future__ import annotations

import contextlib
import os
import uuid
from typing import Any


def partial_name(path: str) -> str:
    """A private temporary name beside ``path`` (``<path>.<random>.partial``)."""
    return f"{path}.{uuid.uuid4().hex}.partial"


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
