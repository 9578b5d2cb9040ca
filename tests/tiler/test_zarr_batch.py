"""zarr calls issued at once (tiler.zarr_batch) give what the same calls one by one give."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

from tiler.location import Location
from tiler.run import open_for_write
from tiler.zarr_batch import open_arrays, read_all, write_all

NAMES = ["a", "b", "sharded"]


def _make(root: Path) -> Location:
    g = zarr.open_group(root, mode="w")
    g.create_array("a", shape=(4, 5), chunks=(2, 5), dtype="int16", fill_value=-1)
    g.create_array("b", shape=(3,), chunks=(3,), dtype="float64", fill_value=np.nan)
    g.create_array("sharded", shape=(4, 4, 6), chunks=(1, 1, 6), shards=(2, 2, 6), dtype="uint16")
    return Location(str(root))


def _values(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "a": rng.integers(-100, 100, (4, 5)).astype(np.int16),
        "b": rng.random(3),
        "sharded": rng.integers(0, 1000, (4, 4, 6)).astype(np.uint16),
    }


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.mark.parametrize("zeros", [False, True])
def test_batched_writes_equal_one_by_one(tmp_path, zeros):
    """The same files, byte for byte, as ``open_for_write(loc, name)[...] = values`` each;
    all-fill chunks are written too (``WRITE_CONFIG``), as by ``open_for_write``."""
    values = _values(1)
    if zeros:
        values["a"] = np.full((4, 5), -1, np.int16)
    one, many = _make(tmp_path / "one"), _make(tmp_path / "many")
    for name in NAMES:
        open_for_write(one, name)[...] = values[name]
    arrays = open_arrays(many, NAMES)
    write_all([(arr, ..., values[n]) for arr, n in zip(arrays, NAMES, strict=True)])
    assert _files(tmp_path / "one") == _files(tmp_path / "many")
    assert (tmp_path / "many" / "a" / "c" / "0" / "0").is_file()  # an all-fill chunk: written


def test_the_file_comparison_sees_a_difference(tmp_path):
    """Positive control: other values give other files."""
    one, many = _make(tmp_path / "one"), _make(tmp_path / "many")
    for loc, seed in ((one, 1), (many, 2)):
        arrays = open_arrays(loc, NAMES)
        write_all([(arr, ..., _values(seed)[n]) for arr, n in zip(arrays, NAMES, strict=True)])
    assert _files(tmp_path / "one") != _files(tmp_path / "many")


def test_partial_selections_and_reads(tmp_path):
    loc = _make(tmp_path / "s")
    v = _values(3)
    (arr,) = open_arrays(loc, ["sharded"])
    write_all([(arr, (slice(0, 2), slice(2, 4)), v["sharded"][:2, 2:])])
    a, s = read_all(loc, ["a", "sharded"])
    assert (a == -1).all()  # never written: the fill value
    assert np.array_equal(s[:2, 2:], v["sharded"][:2, 2:]) and (s[2:] == 0).all()
    g = zarr.open_group(tmp_path / "s", mode="r")
    assert np.array_equal(s, g["sharded"][...])


def test_a_missing_array_is_an_error(tmp_path):
    loc = _make(tmp_path / "s")
    with pytest.raises(Exception, match="nope"):
        open_arrays(loc, ["a", "nope"])
    with pytest.raises(Exception, match="nope"):
        read_all(loc, ["nope"])
