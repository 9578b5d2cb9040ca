"""Pure math of the renderer: meshes, snapping, selection, stitching, error measurement."""

from __future__ import annotations

import numpy as np
import pytest

from render import measure
from render.errors import SelectionError
from render.mesh import (
    edge_strip_triangles,
    grid_indices,
    snap_vertices,
    snapped_triangles,
    triangle_count,
    triangle_counts,
)
from render.node_boxes import NodeBoxes
from render.select import Patches, PatchTable, select_patches, stitch
from streamer.camera import Camera
from streamer.lod import conservative_view
from tiler.grid import BlockGrid


def _area(tri: np.ndarray) -> np.ndarray:
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def test_grid_indices_split_along_a_d_diagonal():
    assert grid_indices(1).tolist() == [[0, 1, 3], [0, 3, 2]]


@pytest.mark.parametrize("snaps", [(0, 0, 0, 0), (1, 0, 0, 0), (2, 1, 0, 3), (3, 3, 3, 3)])
def test_snapped_patch_covers_its_square_without_overlap(snaps):
    tri = snapped_triangles(3, snaps)
    assert _area(tri).sum() == 64  # 8x8 cells, exactly covered: no hole, no fold
    n = 8
    v = snap_vertices(np.array([[i, 0] for i in range(n + 1)]), n, snaps)
    assert sorted(set(v[:, 0].tolist())) == list(range(0, n + 1, 1 << snaps[0]))


def test_triangle_counts_drop_degenerate_triangles():
    assert triangle_count(4, (0, 0, 0, 0)) == 512
    assert triangle_count(4, (1, 0, 0, 0)) == 512 - 8
    got = triangle_counts(np.array([4, 4, 2]), np.array([[0, 0, 0, 0], [1, 0, 0, 0], [0] * 4]))
    assert got.tolist() == [512, 504, 32]


def test_edge_strip_is_the_snapped_row():
    tri = edge_strip_triangles(3, (1, 0, 0, 0))
    assert tri[..., 1].max() == 1 and _area(tri).sum() == 8


def _table(k: int, p: int, blocks, value: float = 0.0) -> PatchTable:
    t = PatchTable(k, p)
    for b in blocks:
        t.add(b, [np.full((1 << d, 1 << d), value) for d in range(k)])
    return t


def _grid() -> BlockGrid:
    return BlockGrid(height=129, width=129, k=5, x0=0.0, y0=3840.0, dx=30.0, dy=30.0)


def test_flat_blocks_are_one_patch_each():
    g = _grid()
    blocks = g.blocks()
    cam = Camera((1920.0, 1920.0, 5000.0), pitch=-90.0, viewport=(64, 48))
    p = select_patches(
        g,
        blocks,
        _table(5, 2, blocks),
        cam,
        1.0,
        "qiu",
        None,
        resident=[5] * 16,
        zranges=np.zeros((16, 2)),
    )
    assert len(p) == 16 and (p.depth == 0).all() and (p.level == 2).all()


def test_resident_level_clamps_and_is_counted():
    g = _grid()
    blocks = g.blocks()
    cam = Camera((1920.0, 1920.0, 300.0), pitch=-90.0, viewport=(64, 48))
    p = select_patches(
        g,
        blocks,
        _table(5, 2, blocks, 50.0),
        cam,
        0.5,
        "conservative",
        None,
        resident=[3] * 16,
        zranges=np.zeros((16, 2)),
    )
    assert p.level.max() == 3 and p.clamped > 0


def test_box_metric_needs_boxes_and_uses_them():
    """``conservative-view`` selects with node boxes: without them a clear error; with flat
    boxes (each node's range a metre) fewer patches than its spheres around 400 m of relief."""
    g = _grid()
    blocks = g.blocks()
    cam = Camera((-500.0, 1920.0, 300.0), pitch=-20.0, viewport=(64, 48))
    kw = {"resident": [5] * 16, "zranges": np.tile([0.0, 400.0], (16, 1))}
    table = _table(5, 2, blocks, 2.0)
    with pytest.raises(SelectionError, match="boxes="):
        select_patches(g, blocks, table, cam, 1.0, "conservative-view", None, **kw)
    boxes = NodeBoxes(5, 2)
    flat = [np.full((1 << d,) * 2, 0.5) for d in range(5)]
    for b in blocks:
        boxes.update(b, 5, np.full((33, 33), 200.0), flat, (0.0, 400.0))
    n_box, n_sphere = [], []
    for tau in (0.25, 0.5, 1.0, 2.0, 4.0):
        fine = select_patches(
            g, blocks, table, cam, tau, "conservative-view", None, boxes=boxes, **kw
        )
        n_box.append(len(fine))
        n_sphere.append(len(select_patches(g, blocks, table, cam, tau, sphere_view, None, **kw)))
    assert all(a <= b for a, b in zip(n_box, n_sphere, strict=True)), (n_box, n_sphere)
    assert sum(n_box) < sum(n_sphere), (n_box, n_sphere)


def sphere_view(delta, centre_xyz, radius, camera):
    """``conservative-view`` on spheres (a callable metric without ``takes_box``)."""
    return conservative_view(delta, centre_xyz, radius, camera)


def _patches(depth, row, col, level, k=5) -> Patches:
    n = len(depth)
    arr = lambda v: np.asarray(v, dtype=np.int64)  # noqa: E731
    return Patches(
        blocks=np.array([[0, 0]]),
        block=np.zeros(n, np.int64),
        depth=arr(depth),
        row=arr(row),
        col=arr(col),
        level=arr(level),
        delta=np.zeros(n),
        rho=np.zeros(n),
        snap=np.zeros((n, 4), np.int64),
        clamped=0,
        violations=0,
    )


def test_stitch_snaps_fine_edges_to_the_coarse_neighbour():
    g = BlockGrid(height=33, width=33, k=5)
    # west half split once more (depth 2), east half kept at depth 1: levels 4 vs 3 (P = 2)
    d = [2, 2, 2, 2, 1, 1, 1]
    r = [0, 0, 1, 1, 0, 1, 1]
    c = [0, 1, 0, 1, 1, 0, 1]
    # depth-1 node (0,0) is split into the four depth-2 nodes (rows 0-1, cols 0-1)
    lv = [4, 4, 4, 4, 3, 3, 3]
    p = _patches(d, r, c, lv)
    t = _table(5, 2, [(0, 0)])
    cam = Camera((0.0, 0.0, 1e4), pitch=-90.0, viewport=(64, 48))
    s = stitch(p, g, t, cam, "qiu", resident=[5], zranges=np.zeros((1, 2)))
    # depth-2 node (0,1) touches the depth-1 node (0,1) on its east edge: snap 1
    assert s.snap[1].tolist() == [0, 1, 0, 0]
    # depth-2 node (1,0) touches depth-1 node (1,0) on its south edge
    assert s.snap[2].tolist() == [0, 0, 1, 0]
    assert s.snap[4:].sum() == 0 and s.violations == 0


def test_stitch_splits_neighbours_that_break_the_restriction():
    g = BlockGrid(height=33, width=33, k=5)
    # P = 1: a depth-3 node next to a depth-1 node (spacing 8 > node edge 4) must split it
    d = [1, 1, 1, 2, 2, 2, 3, 3, 3, 3]
    r = [0, 1, 1, 0, 1, 1, 0, 0, 1, 1]
    c = [1, 0, 1, 0, 0, 1, 2, 3, 2, 3]
    lv = [x + 1 for x in d]
    p = _patches(d, r, c, lv)
    cam = Camera((0.0, 0.0, 1e4), pitch=-90.0, viewport=(64, 48))
    s = stitch(p, g, _table(5, 1, [(0, 0)]), cam, "qiu", resident=[5], zranges=np.zeros((1, 2)))
    assert len(s) > len(p) and s.violations == 0
    assert (s.snap <= s.cells_log2[:, None]).all()


def _refined_towards(k: int, deep: int, row: int, col: int) -> Patches:
    """Leaves of one block refined towards the depth-``deep`` node ``(row, col)`` only, every
    other leaf as coarse as it can be: a ripple for the restriction to propagate."""
    d, r, c = [], [], []
    for depth in range(1, deep + 1):
        pr, pc = row >> (deep - depth), col >> (deep - depth)  # the path's node at this depth
        for cr in (pr & ~1, pr | 1):
            for cc in (pc & ~1, pc | 1):
                if depth == deep or (cr, cc) != (pr, pc):
                    d.append(depth)
                    r.append(cr)
                    c.append(cc)
    return _patches(d, r, c, [x + 1 for x in d], k=k)


def test_stitch_runs_until_the_restriction_holds():
    """Balancing a deep node beside coarse ones takes a round per depth of the ripple: a cap
    below that is an error, the default cap settles (the 2^1-cell patches of a synthetic 1025²
    view at 170° took 84 rounds, over the former cap of 64)."""
    k, deep = 9, 8
    g = BlockGrid(height=513, width=513, k=k)
    p = _refined_towards(k, deep, (1 << deep) // 2, (1 << deep) // 2 - 1)  # west of the centre
    cam = Camera((0.0, 0.0, 1e4), pitch=-90.0, viewport=(64, 48))
    kw = dict(resident=[k], zranges=np.zeros((1, 2)))
    with pytest.raises(SelectionError, match="did not settle in 2 rounds"):
        stitch(p, g, _table(k, 1, [(0, 0)]), cam, "qiu", max_rounds=2, **kw)
    s = stitch(p, g, _table(k, 1, [(0, 0)]), cam, "qiu", **kw)
    assert s.violations == 0 and len(s) > len(p)
    assert (s.snap <= s.cells_log2[:, None]).all()


def test_rasterise_includes_edges():
    tri = np.array([[[0, 0], [2, 0], [0, 2]]])
    r, c, h = measure.rasterise(tri, np.array([[0.0, 2.0, 4.0]]))
    pts = sorted(zip(r.tolist(), c.tolist(), h.tolist(), strict=True))
    assert len(pts) == 6 and (1, 1, 3.0) in pts


def test_rasterise_skips_zero_area_triangles():
    tri = np.array([[[0, 0], [2, 0], [0, 2]], [[0, 0], [4, 4], [2, 2]]])  # 2nd: a line
    r, c, h = measure.rasterise(tri, np.array([[0.0, 2.0, 4.0], [1.0, 1.0, 1.0]]))
    assert r.size == 6 and np.isfinite(h).all()


def test_full_resolution_patches_have_zero_error():
    g = BlockGrid(height=33, width=33, k=5, x0=0.0, y0=960.0, dx=30.0, dy=30.0)
    rng = np.random.default_rng(0)
    full = rng.normal(0, 10, (33, 33))
    p = _patches([3] * 64, np.repeat(np.arange(8), 8), np.tile(np.arange(8), 8), [5] * 64)
    cam = Camera.look_at((480.0, -500.0, 800.0), (480.0, 480.0, 0.0), viewport=(64, 48))
    err = measure.screen_errors(p, g, cam, lambda i: full)
    assert err.size > 0 and err.max() < 1e-6


def test_lod_surface_is_linear_in_snapped_cells():
    full = np.add.outer(np.arange(33.0), 2 * np.arange(33.0))  # a plane: exact at any level
    p = _patches([1, 1], [0, 0], [0, 1], [3, 3])
    p = Patches(**{**p.__dict__, "snap": np.array([[1, 0, 2, 1], [0, 0, 0, 0]])})
    for _, rows, cols, h in measure.lod_surface(p, 5, lambda i: full):
        assert np.allclose(h, full[rows, cols])


def test_crack_pixels_ignore_outline_but_count_holes():
    img = np.zeros((20, 20, 3), np.uint8)
    fp = np.zeros((20, 20), bool)
    fp[2:18, 2:18] = True
    img[~fp] = (255, 0, 255)
    img[2, 5:9] = (255, 0, 255)  # outline nibble joined to the background
    img[10, 4:12] = (255, 0, 255)  # a hole
    assert measure.crack_pixels(img, fp, (255, 0, 255)) == 8
    assert measure.psnr(img, img) == 100.0


def test_min_depth_splits_flat_nodes_down_to_it_where_resident():
    # flat blocks (zero error) stop at the root unless min_depth forces them deeper; a block
    # resident at a level too coarse for the forced depth stops there, counted as clamped
    g = _grid()
    blocks = g.blocks()
    cam = Camera((1920.0, 1920.0, 5000.0), pitch=-90.0, viewport=(64, 48))
    res = [5] * 15 + [3]
    kw = dict(resident=res, zranges=np.zeros((16, 2)))
    t = _table(5, 2, blocks)
    p = select_patches(g, blocks, t, cam, 1.0, "qiu", None, min_depth=2, **kw)
    deep = p.block != 15
    assert (p.depth[deep] == 2).all() and (p.level[deep] == 4).all() and deep.sum() == 15 * 16
    assert (p.depth[~deep] == 1).all() and (p.level[~deep] == 3).all() and p.clamped == 4
    assert len(select_patches(g, blocks, t, cam, 1.0, "qiu", None, **kw)) == 16
