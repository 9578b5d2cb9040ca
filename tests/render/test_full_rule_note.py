"""``tradeoff`` says so when nodata pinned the mesh: under the nodata rule ``full`` scattered
voids put every node at full resolution, so τ changes nothing; the note names the ``gap``
rule's count. Controls: the ``gap`` rule, and the same DEM without voids, are not noted."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render.pipeline import ViewOptions, tradeoff
from render.renderer import RenderConfig, TerrainRenderer
from render.views import make_camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
SIZE = (128, 96)
NOTE = "note: τ changed nothing here"


def _sweep(tmp, voids: bool, rule: str = "full") -> list[str]:
    tmp.mkdir(parents=True, exist_ok=True)
    dem = rough(257, 3, amp=20.0).astype(np.float32)
    if voids:
        dem[4::9, 4::9] = np.nan  # one-sample voids everywhere: every node is mixed
    s = open_store(tile_dem(tmp, dem, 65, nodata=np.nan))
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=make_context())
    lines: list[str] = []
    try:
        cam = make_camera(s, SIZE)
        rows = tradeoff(s, cam, [1.0, 8.0], repeats=1, renderer=r, log=lines.append,
                        options=ViewOptions(nodata=rule, patch_log2=2))  # fmt: skip
    finally:
        r.close()
    if voids and rule == "full":
        assert rows[0].triangles == rows[1].triangles  # the scene the note is about
    return lines


def test_a_sweep_pinned_by_nodata_says_so(tmp_path):
    lines = _sweep(tmp_path, voids=True)
    note = [x for x in lines if x.startswith(NOTE)]
    assert len(note) == 1 and "--nodata-rule gap would draw at most" in note[0]
    assert "at τ = 8" in note[0]


def test_the_gap_rule_and_a_dem_without_voids_are_not_noted(tmp_path):
    assert not any(x.startswith(NOTE) for x in _sweep(tmp_path / "gap", True, "gap"))
    assert not any(x.startswith(NOTE) for x in _sweep(tmp_path / "plain", voids=False))
