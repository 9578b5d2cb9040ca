"""The store layout created at once (concurrently) equals the one created array by array."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import zarr
from demtools import fractal

from tiler import schema
from tiler.store import open_store
from tiler.tile import TileOptions, tile


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def diff_stores(a: Path, b: Path) -> list[str]:
    """Files (metadata and chunks) that differ between two layouts, byte for byte."""
    fa, fb = _files(a), _files(b)
    return sorted(k for k in fa.keys() | fb.keys() if fa.get(k) != fb.get(k))


@pytest.fixture
def meta(dem_factory, tmp_path):
    """A real store's metadata (3 x 3 blocks of 17², 5 levels, padding)."""
    tile(dem_factory(fractal((40, 40), 1)), tmp_path / "s.zarr", TileOptions(block_size=17))
    return open_store(tmp_path / "s.zarr").meta


@pytest.mark.parametrize("version", [1, 2])
def test_concurrent_layout_is_byte_identical(meta, tmp_path, version):
    m = replace(meta, format_version=version)
    for name, concurrent in (("seq", False), ("conc", True)):
        group = zarr.open_group(tmp_path / name, mode="w")
        schema.create_layout(group, m, 3, concurrent=concurrent)
    assert diff_stores(tmp_path / "seq", tmp_path / "conc") == []
    arrays = {p for p, _ in schema.layout_specs(m, 3)}
    assert arrays == set(schema.array_names(m.k))  # every array of the format, each once
    assert (tmp_path / "conc" / "order_index" / "c" / "0" / "0").is_file()  # the tables' data


def test_layout_comparison_sees_a_difference(meta, tmp_path):
    """Positive control: another compression level changes the compared metadata files."""
    schema.create_layout(zarr.open_group(tmp_path / "a", mode="w"), meta, 3, concurrent=False)
    schema.create_layout(zarr.open_group(tmp_path / "b", mode="w"), meta, 4)
    diff = diff_stores(tmp_path / "a", tmp_path / "b")
    assert "levels/0/zarr.json" in diff and "errors/zarr.json" in diff
    assert "order_index/zarr.json" not in diff  # the tables keep their own level


def test_concurrent_layout_refuses_an_existing_array(meta, tmp_path):
    g = zarr.open_group(tmp_path / "x", mode="w")
    schema.create_layout(g, meta, 3)
    with pytest.raises(Exception, match="levels|exists|already"):
        schema.create_layout(g, meta, 3)
