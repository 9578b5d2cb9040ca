"""``tiler.read_errors``: a failed read worded as the store's damage, the server's failure or
neither (a bug, raised as it is); pure, no store."""

from __future__ import annotations

import pytest

from tiler.errors import (
    BlockDataError,
    ChunkChecksumError,
    MissingChunkError,
    StoreCorruptError,
    StoreUnavailableError,
)
from tiler.read_errors import missing_chunk, open_error, read_error

URL = "http://example.invalid/s.zarr"


@pytest.mark.parametrize(
    ("exc", "cls", "says"),
    [
        (ValueError("crc32c checksum mismatch"), ChunkChecksumError, "the store is damaged"),
        (OSError("truncated chunk"), BlockDataError, "the store is damaged"),
        (TimeoutError(), StoreUnavailableError, "did not answer in time"),
        (ConnectionRefusedError(), StoreUnavailableError, "not the store"),
    ],
)
def test_read_errors_name_block_level_and_cause(exc, cls, says):
    err = read_error(URL, "levels/3", (1, 2), 3, exc)
    assert type(err) is cls and says in str(err)
    assert (err.array, err.block, err.level) == ("levels/3", (1, 2), 3)
    assert "level 3 of block (1, 2)" in str(err)


def test_a_bug_is_not_a_read_error():  # the control: raised as it is by the caller
    assert read_error(URL, "errors", (0, 0), None, ZeroDivisionError()) is None
    assert open_error(URL, "errors", ZeroDivisionError()) is None


def test_open_errors():
    assert isinstance(open_error(URL, "mask", KeyError("mask")), StoreCorruptError)
    assert "is damaged" in str(open_error(URL, "mask", TypeError("not an object")))
    assert isinstance(open_error(URL, "mask", TimeoutError()), StoreUnavailableError)


def test_missing_chunk_names_what_is_missing():
    err = missing_chunk(URL, "level 10", "levels/10", (3, 4), 10)
    assert isinstance(err, MissingChunkError) and err.block == (3, 4)
    assert str(err).startswith("level 10 of block (3, 4) (array 'levels/10') is missing")


@pytest.mark.parametrize(
    "text",
    ["cannot schedule new futures after shutdown",
     "cannot schedule new futures after interpreter shutdown", "Event loop is closed"],
)  # fmt: skip
def test_a_read_cut_short_by_shutdown_is_not_damage(text):
    """A program that ended without closing its HTTP session: the fsspec loop's RuntimeError
    was worded "the store is damaged: verify it". The control: another RuntimeError from a
    chunk's codec still is damage."""
    err = read_error(URL, "levels/3", (1, 2), 3, RuntimeError(text))
    assert type(err).__name__ == "StoreError"
    assert "shutting down" in str(err) and "close the session" in str(err)
    assert "damaged" not in str(err).replace("not the store's damage", "")
    codec = read_error(URL, "levels/3", (1, 2), 3, RuntimeError("blosc decompression failed"))
    assert isinstance(codec, BlockDataError) and "the store is damaged" in str(codec)
