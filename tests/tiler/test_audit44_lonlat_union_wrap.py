"""lonlat_union with a box that straddles 0° longitude (its arc runs past 360° on the circle)
and reaches further east than every other box: the union lost that box's eastern part, and a
same-CRS mosaic's grid (tiler.mosaic_plan._extent_in) was cut there (exit 0)."""

from __future__ import annotations

from demtools import fractal, write_dem
from rasterio.crs import CRS
from rasterio.warp import transform_bounds

from tiler.crs import lonlat_union
from tiler.mosaic import plan_mosaic


def test_a_box_across_greenwich_keeps_its_east_when_another_lies_inside_it():
    assert lonlat_union([(-1, 0, 1, 1), (0, 0, 0.5, 1)]) == (-1, 0, 1, 1)
    assert lonlat_union([(-10, 40, 30, 60), (2, 48, 3, 49)]) == (-10, 40, 30, 60)
    assert lonlat_union([(-10, 0, 10, 1), (175, 0, 180, 1)]) == (-10, 0, 180, 1)


def test_control_the_short_way_round_still_holds():
    assert lonlat_union([(179, -18, 180, -16), (-180, -18, -179, -16)]) == (179, -18, 181, -16)
    assert lonlat_union([(170, 0, -170, 1), (0, 0, 1, 1)]) == (0, 0, 190, 1)
    assert lonlat_union([(-1, 0, 0, 1), (0, 0, 1, 1)]) == (-1, 0, 1, 1)


def test_a_patch_inside_a_base_across_greenwich_keeps_the_whole_base(tmp_path):
    base = write_dem(tmp_path / "base.tif", fractal((61, 61), seed=1) + 100, crs="EPSG:4326",
                     origin=(-0.5, 50.0), cell=2 / 60)  # fmt: skip
    patch = write_dem(tmp_path / "patch.tif", fractal((31, 31), seed=2) + 100,
                      crs="EPSG:4326", origin=(0.1, 49.5), cell=0.2 / 30)  # fmt: skip

    def east(paths):
        spec = plan_mosaic([str(p) for p in paths], dst_crs="EPSG:32631", resolution=1000)
        a = spec.affine
        box = (a.c, a.f + spec.height * a.e, a.c + spec.width * a.a, a.f)
        return transform_bounds(CRS.from_wkt(spec.crs_wkt), "EPSG:4326", *box)[2]

    alone = east([base])
    assert alone > 1.5  # the base reaches 1.5°E
    assert east([base, patch]) >= alone - 1e-6  # (was 0.41°E: 58 % of the base lost)
    assert east([patch, base]) >= alone - 1e-6
