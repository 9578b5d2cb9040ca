"""bench/level_codecs.py's per-block shuffle table reads the stored frames and the sparse rule
as the writer applies them: on a padded store the stored shuffle is what the rule keeps."""

from __future__ import annotations

import sys
from pathlib import Path

from demtools import fractal

from tiler import source
from tiler.tile import TileOptions, tile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.level_codecs import shuffles  # noqa: E402


def _rows(path: Path) -> list[dict]:
    return shuffles(str(path), blocks=9, reps=3)


def test_stored_shuffle_is_what_the_rule_keeps(dem_factory, tmp_path, monkeypatch):
    """Fractal terrain in 129² blocks with padded edges: sparse chunks byte shuffled, full ones
    bit, each as the table's rule column says. Control: a store written with the rule off
    keeps bit everywhere, and the table tells it apart from what the rule would keep."""
    src = dem_factory(fractal((300, 280), 2))
    tile(src, tmp_path / "on.zarr", TileOptions(block_size=129, workers=1))
    rows = _rows(tmp_path / "on.zarr")
    assert len(rows) == 9 * 2  # 3x3 blocks, the two finest levels
    assert all(r["stored_shuffle"] == r["rule_keeps"] for r in rows), rows
    assert {r["stored_shuffle"] for r in rows} == {"bit", "byte"}
    assert all(r["bit_bytes"] > 0 and r["byte_us"] > 0 for r in rows)
    monkeypatch.setattr(source, "sparse_byte_shuffle", lambda encoding, k: None)
    tile(src, tmp_path / "off.zarr", TileOptions(block_size=129, workers=1))
    off = _rows(tmp_path / "off.zarr")
    assert {r["stored_shuffle"] for r in off} == {"bit"}
    assert any(r["stored_shuffle"] != r["rule_keeps"] for r in off)
