"""Errors cross process boundaries (tiling's worker processes, dask's process scheduler,
multiprocessing): each comes back as itself with the fields that name what failed.
``BlockDataError`` could not be unpickled at all (its fields are keyword-only: "__init__()
missing 3 required keyword-only arguments" replaced the checksum error naming the block), and
``StoreUnavailableError`` / ``BlockFailedError`` came back without their block."""

from __future__ import annotations

import pickle

import pytest

from tiler import errors


@pytest.mark.parametrize(
    "exc",
    [
        errors.ChunkChecksumError("crc32c differs", array="levels/6", block=(0, 1), level=6),
        errors.MissingChunkError("chunk absent", array="mask", block=(2, 3), level=None),
        errors.BlockDataError("damaged", array="errors", block=(1, 1), level=None),
        errors.StoreUnavailableError("503", array="levels/2", block=(4, 5), level=2),
        errors.StoreUnavailableError("timed out"),
        errors.BlockFailedError("failed on every retry", (7, 8)),
        errors.HeightRangeError("beyond", value=1e30, raw="1e+30", count=1, row=2, col=3),
    ],
    ids=lambda e: type(e).__name__,
)
def test_errors_come_back_from_a_worker_whole(exc):
    back = pickle.loads(pickle.dumps(exc))
    assert type(back) is type(exc) and str(back) == str(exc)
    for name in ("array", "block", "level", "value", "raw", "count", "row", "col"):
        if hasattr(exc, name):
            assert getattr(back, name) == getattr(exc, name), name


def test_the_control_default_pickling_loses_the_block():
    """What the default ``__reduce__`` does with these classes (the test's premise)."""
    exc = errors.ChunkChecksumError("crc32c differs", array="levels/6", block=(0, 1), level=6)
    with pytest.raises(TypeError, match="keyword-only"):
        Exception.__reduce__(exc)[0](*Exception.__reduce__(exc)[1])
