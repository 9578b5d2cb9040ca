"""Stitching across blocks streamed at very different levels (streamer.restriction): with
2¹-cell patches and a wide field of view, blocks at the side of the view need far fewer levels
than those ahead; the session now plans every block within ``patch_log2`` levels of its edge
neighbours, so the drawn mesh has no open edge. Positive control: the same views planned
without the restriction leave T-junctions (open and gap edges)."""

from __future__ import annotations

from dataclasses import replace

import pytest
from gltools import make_context, rough, tile_dem

import streamer.planner as planner_mod
from render.pipeline import ViewOptions, tradeoff
from streamer.run import make_path
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
VIEWS = [(120.0, 2.0), (170.0, 0.5)]  # (vertical FOV, tau): the control's T-junctions show here


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return open_store(tile_dem(tmp_path_factory.mktemp("joinable"), rough(513, seed=3), 65))


def _rows(store):
    cams = make_path(store, "default", frames=8, viewport=(160, 120))
    opts = ViewOptions("qiu", metric="conservative-view", patch_log2=1)
    out = []
    for fov, tau in VIEWS:
        cam = replace(cams[len(cams) // 2], fov_y=fov)
        out += tradeoff(store, cam, [tau], repeats=1, options=opts)
    return out


def test_blocks_are_planned_joinable_and_the_mesh_is_watertight(store, monkeypatch):
    # what the planner loads, not re-streamed finer (render.pipeline.RESTREAM)
    monkeypatch.setattr("render.pipeline.RESTREAM", ())
    rows = _rows(store)
    assert all(r.open_edges == 0 and r.gap_edges == 0 for r in rows), [
        (r.tau, r.open_edges, r.gap_edges) for r in rows
    ]
    assert all(r.max_screen_error_px <= r.tau for r in rows)
    monkeypatch.setattr(planner_mod.Planner, "_restrict", lambda self, ids, levels: levels)
    control = _rows(store)
    assert sum(r.open_edges for r in control) > 0, "the views need no restriction: shows nothing"
    assert sum(r.gap_edges for r in control) > 0
