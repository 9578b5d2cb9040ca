"""The reprojected MosaicSpec stays small (audit 44): the seam fill's rings (a pixel-edge ring
plus three rings per neighbour, as tuples of floats) made a 6x6 grid's spec 30.6 KB per source
instead of 5.7 KB, and a dask run ships the spec with every block task. The spec now names
each source's neighbours by index and MosaicReader builds their rings once per reader."""

from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pytest
from demtools import fractal, write_dem
from rasterio.crs import CRS

import tiler.mosaic as mosaic
import tiler.mosaic_plan as mosaic_plan
from tiler.mosaic import MosaicReader, plan_mosaic

DEG = 1 / 30
#: pickled bytes per source a reprojected spec may take: its sample-centre hull (257 points,
#: ~5 KB) and header; the seam rings the spec carried (4 + 3 per neighbour of 65 points)
#: took 20-30 KB more per source
MAX_BYTES_PER_SOURCE = 8000


@pytest.fixture(scope="module")
def grid3(tmp_path_factory):
    """A 3x3 grid of abutting geographic tiles that share no sample (the middle one meets 8)."""
    root = tmp_path_factory.mktemp("grid3")
    size = 20
    data = fractal((3 * size, 3 * size), seed=11)
    paths = []
    for i in range(3):
        for j in range(3):
            piece = np.ascontiguousarray(data[i * size : (i + 1) * size, j * size : (j + 1) * size])
            at = (10.0 + j * size * DEG, 45.0 - i * size * DEG)
            paths.append(
                str(write_dem(root / f"t{i}{j}.tif", piece, crs="EPSG:4326", origin=at, cell=DEG))
            )
    return paths


def _per_source(spec) -> float:
    return len(pickle.dumps(spec)) / len(spec.sources)


def _old_rings(spec) -> list:
    """What each source carried before: its edge ring and three rings per source it meets,
    each built apart (as the planner did: no ring object shared between sources)."""
    target = CRS.from_wkt(spec.crs_wkt)
    rings = mosaic_plan.seam_rings
    return [
        (rings(s, target)[0], tuple(r for j in s.near for r in rings(spec.sources[j], target)[1]))
        for s in spec.sources
    ]


def test_a_reprojected_specs_pickle_stays_small_per_source(grid3):
    spec = plan_mosaic(grid3, dst_crs="auto")
    assert _per_source(spec) < MAX_BYTES_PER_SOURCE, _per_source(spec)  # (~5.6 KB)
    assert spec.sources[4].near == (0, 1, 2, 3, 5, 6, 7, 8)  # the middle tile meets all 8


def test_a_positive_control_the_rings_in_the_spec_exceed_the_bound(grid3):
    spec = plan_mosaic(grid3, dst_crs="auto")
    old = len(pickle.dumps((spec, _old_rings(spec)))) / len(spec.sources)
    assert old > 2 * MAX_BYTES_PER_SOURCE, old  # (~25 KB: 4 + 3 x 4.4 rings of 65 points)


def test_planning_builds_no_seam_ring_and_a_reader_builds_each_once(grid3, monkeypatch):
    """One hull per source at planning (the rings were built per neighbour: 1 + 3 per neighbour
    each, ~7x the time on a 6x6 grid); a reader builds a source's rings the first time one of
    its seams is filled, then keeps them."""
    hulls = []
    real_hull = mosaic_plan._hull
    monkeypatch.setattr(mosaic_plan, "_hull", lambda *a, **k: hulls.append(1) or real_hull(*a, **k))
    spec = plan_mosaic(grid3, dst_crs="auto")
    assert len(hulls) == len(grid3)
    built = []
    real_rings = mosaic.seam_rings
    monkeypatch.setattr(mosaic, "seam_rings", lambda *a: built.append(1) or real_rings(*a))
    cols = len(range(0, spec.width, 17))
    with MosaicReader(spec) as reader:
        blocks = [
            reader.read_window(r0, c0, min(17, spec.height - r0), min(17, spec.width - c0))
            for r0 in range(0, spec.height, 17)
            for c0 in range(0, spec.width, 17)
        ]
        whole = reader.read_window(0, 0, spec.height, spec.width)
    assert 0 < len(built) <= len(grid3)
    # the rings were used: the seams between the tiles were filled (without the neighbours'
    # indices the reader leaves them nodata)
    bare = replace(spec, sources=tuple(replace(s, near=()) for s in spec.sources))
    with MosaicReader(bare) as reader:
        cut = reader.read_window(0, 0, spec.height, spec.width)
    assert np.array_equal(
        np.block([blocks[k : k + cols] for k in range(0, len(blocks), cols)]), whole
    )
    assert (whole != spec.nodata).sum() > (cut != spec.nodata).sum() + 50
