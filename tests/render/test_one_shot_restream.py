"""A one-shot view (``render``, ``tradeoff``) draws what its strategy selects, not a clamped
version: seamless-patches', geometry-splitting's and jung-han's own rules can want levels the
session streamed with :func:`render.strategies.stream_metric` did not load, so the view is
streamed again at a finer tau (:data:`render.pipeline.RESTREAM`) until nothing is clamped.
The control: without the re-streaming the same view clamps."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, tile_dem

import render.pipeline as pipeline
from render.pipeline import ViewOptions, render_view, restream_taus, tradeoff
from render.views import make_camera
from tiler.store import open_store
from tiler.synth import synth_array

pytestmark = pytest.mark.gl
make_context()
VIEW = (160, 120)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """513² of the synthetic DEM 5 km below sea level, in 4 x 4 blocks of 129²."""
    d = synth_array(slice(0, 513), slice(0, 513), 1025) - 5000.0
    return open_store(tile_dem(tmp_path_factory.mktemp("restream"), d, 129, cell=30.0))


def test_restream_taus():
    assert restream_taus(1.0) == [1.0, 0.5, 0.25, 0.0]
    assert restream_taus(0.0) == [0.0]  # full resolution already: nothing finer


@pytest.mark.parametrize("lod", ["seamless-patches", "jung-han"])
def test_a_one_shot_view_loads_what_its_strategy_selects(store, lod, monkeypatch):
    cam = make_camera(store, VIEW)
    _, st = render_view(store, cam, options=ViewOptions(lod, 0.1))
    assert st.clamped == 0 and st.triangles > 0
    monkeypatch.setattr(pipeline, "RESTREAM", ())  # the control: one session at tau
    _, clamped = render_view(store, cam, options=ViewOptions(lod, 0.1))
    assert clamped.clamped > 0


def test_tradeoff_says_which_stream_tau_supplied_the_levels(store, monkeypatch):
    cam = make_camera(store, VIEW)
    rows = tradeoff(store, cam, [0.1, 1.0], repeats=1, lod="seamless-patches")
    assert [r.clamped for r in rows] == [0, 0]
    assert rows[0].stream_tau < 0.1 and rows[1].stream_tau == 1.0
    monkeypatch.setattr(pipeline, "RESTREAM", ())
    control = tradeoff(store, cam, [0.1], repeats=1, lod="seamless-patches")
    assert control[0].clamped > 0 and control[0].stream_tau == 0.1
    assert control[0].loaded_bytes < rows[0].loaded_bytes
    assert np.isfinite(rows[0].max_screen_error_px)
