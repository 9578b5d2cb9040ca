"""The snapped-edge check under the nodata rule ``gap`` bounds a coarse neighbour's cells with
the rule's own (stored) errors, as the selection does: beside nodata a held neighbour is no
longer asked to split for an infinite bound, so no edge is clamped and the bound still holds.
Positive control: the ``full`` rule's bounds (infinite on mixed cells) in the check clamp
edges on the same views."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render.frame import FrameServices
from render.pipeline import ViewOptions, tradeoff
from streamer.run import make_path
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
TAUS = [0.5, 1.0, 2.0]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """257² rough DEM with a disc of nodata, blocks of 65²."""
    n = 257
    d = rough(n, seed=3)
    yy, xx = np.mgrid[:n, :n]
    d[(yy - n * 0.45) ** 2 + (xx - n * 0.55) ** 2 < (n * 0.18) ** 2] = -9999
    return open_store(tile_dem(tmp_path_factory.mktemp("gapsnap"), d, 65, nodata=-9999))


def _rows(store):
    cams = make_path(store, "default", frames=8, viewport=(160, 120))
    cam = replace(cams[len(cams) // 2], fov_y=170.0)
    opts = ViewOptions("qiu", metric="conservative-view", patch_log2=1, nodata="gap")
    return tradeoff(store, cam, TAUS, repeats=1, options=opts)


def test_gap_views_clamp_no_edge_and_stay_within_tau(store, monkeypatch):
    # the session's own loading, not re-streamed finer (render.pipeline.RESTREAM)
    monkeypatch.setattr("render.pipeline.RESTREAM", ())
    rows = _rows(store)
    assert [r.clamped for r in rows] == [0, 0, 0]
    assert all(r.max_screen_error_px <= r.tau for r in rows), [r.max_screen_error_px for r in rows]
    orig = FrameServices.node_boxes

    def full_rule(self, pairs, patch_log2=None, nodata="full"):
        return orig(self, pairs, patch_log2, "full")

    monkeypatch.setattr(FrameServices, "node_boxes", full_rule)
    control = _rows(store)
    assert sum(r.clamped for r in control) > 0, "the views clamp nothing: shows nothing"
    assert sum(r.triangles for r in control) > sum(r.triangles for r in rows)
