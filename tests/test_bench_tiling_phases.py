"""bench/tiling_phases.py times the tiler's own steps: every phase is seen, they fit inside the
call, and the tiler's functions are put back afterwards."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from demtools import fractal

import tiler.assemble as asm
import tiler.destination as dest
import tiler.run as run
import tiler.tile as tile_mod

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import tiling_phases  # noqa: E402


def test_phases_cover_the_call_and_the_wrappers_are_removed(dem_factory, tmp_path):
    src = dem_factory(fractal((300, 280), 2))  # a 513² block: padded, as the SRTM tile's edges
    before = (dest.create_store, asm.finish, run.BlockWorker.run, tile_mod.TerrainStore)
    out = tmp_path / "p.json"
    res = tiling_phases.main([str(src), "--reps", "2", "--layout-reps", "2", "--out", str(out)])
    assert json.loads(out.read_text())["reps"] == 2
    for row in res["runs_ms"]:
        parts = [row[k] for k in tiling_phases.PHASES]
        assert all(v >= 0 for v in parts), row
        assert all(row[k] > 0 for k in ("create_store", "blocks", "finish", "open_store")), row
        assert sum(parts) <= row["total"] * 1.001  # disjoint (one shard: written after the blocks)
    assert set(res["layout_and_open_median_ms"]) == {
        "layout_memory", "layout_sequential", "open_default", "open_one_by_one",
    }  # fmt: skip
    assert before == (dest.create_store, asm.finish, run.BlockWorker.run, tile_mod.TerrainStore)
