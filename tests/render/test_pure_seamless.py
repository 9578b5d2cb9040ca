"""Pure known-answer tests of ``seamless`` (no GL: they run without an EGL context)."""

from __future__ import annotations

import itertools
import math
from collections import Counter

import numpy as np
import pytest

from render.strategies.seamless import (
    edge_epsilon,
    edge_resolution,
    mesh_kinds,
    mesh_of,
    paper_precision,
    precision,
    rotate,
    strip_mesh,
    strip_triangles,
    tile_mesh,
    tile_triangles,
)


def _patch(c: int, res: tuple[int, int, int, int]) -> np.ndarray:
    """All ``(u, v)`` triangles of one patch with tile resolutions ``res`` (N, E, S, W)."""
    parts = []
    for e in range(4):
        for m in (tile_mesh(c, res[e]), strip_mesh(c, res[e], res[(e + 1) % 4])):
            parts.append(rotate(m[..., :2].astype(np.int64), e, c))
    return np.concatenate(parts)


def _area2(t: np.ndarray) -> np.ndarray:
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    return e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]


def _edge_use(tri: np.ndarray) -> Counter:
    use: Counter = Counter()
    for t in tri.tolist():
        for i in range(3):
            a, b = tuple(t[i]), tuple(t[(i + 1) % 3])
            use[(a, b) if a < b else (b, a)] += 1
    return use


def test_tile_and_strip_triangle_counts_per_resolution_pair():
    c = 5
    assert [len(tile_mesh(c, r)) for r in range(1, 6)] == [0, 4, 24, 112, 480]
    assert [tile_triangles(r) for r in range(1, 6)] == [0, 4, 24, 112, 480]
    for ra, rb in itertools.product(range(1, c + 1), repeat=2):
        assert len(strip_mesh(c, ra, rb)) == strip_triangles(ra, rb) == 2 ** max(ra, rb)
    # four equal tiles and their four strips are the full 2 n^2 grid
    for r in range(1, c + 1):
        assert len(_patch(c, (r, r, r, r))) == 2 * 4**r
    # mixed: 4 + 24 + 112 + 480 tiles; strips N-E 8, E-S 16, S-W 32, W-N 32
    assert len(_patch(c, (2, 3, 4, 5))) == 620 + 8 + 16 + 32 + 32
    assert len(mesh_kinds(c)) == c + c * c


def test_cached_meshes_have_no_degenerate_triangles():
    c = 5
    size = 1 << c
    for kind in mesh_kinds(c):
        m = mesh_of(c, kind)
        if not len(m):
            continue
        uv, r = m[..., :2].astype(np.int64), m[..., 2]
        assert (_area2(uv) != 0).all(), kind
        # every vertex is a sample of the lattice of the resolution it is tagged with
        q = size >> r
        assert ((uv[..., 0] % q == 0) & (uv[..., 1] % q == 0)).all(), kind
        # the north tile / north-east strip lies in the north triangle / around its diagonal
        u, v = uv[..., 0], uv[..., 1]
        if kind[0] == "tile":
            assert ((v <= u) & (v <= size - u)).all()
        else:
            assert ((u >= size // 2) & (v <= size // 2)).all()


@pytest.mark.parametrize("c", [2, 3])
def test_every_patch_is_a_watertight_triangulation_of_its_square(c):
    size = 1 << c
    for res in itertools.product(range(1, c + 1), repeat=4):
        tri = _patch(c, res)
        area = _area2(tri)
        assert (area != 0).all() and np.abs(area).sum() == 2 * size * size, res
        use = _edge_use(tri)
        border: dict[int, set] = {0: set(), 1: set(), 2: set(), 3: set()}
        for (a, b), n in use.items():
            on = [
                a[1] == b[1] == 0,
                a[0] == b[0] == size,
                a[1] == b[1] == size,
                a[0] == b[0] == 0,
            ]
            assert n == (1 if any(on) else 2), (res, a, b, n)  # no T-junction, no hole
            for e in range(4):
                if on[e]:
                    border[e] |= {a, b}
        # a patch edge's vertices depend only on that edge's resolution
        for e, r in enumerate(res):
            t = np.arange(0, size + 1, size >> r)
            full = [(x, 0) for x in t], [(size, x) for x in t], [(x, size) for x in t]
            want = (*full, [(0, x) for x in t])[e]
            assert border[e] == set(want), (res, e)


def test_rotation_sends_north_to_east():
    c = 3
    pts = np.array([[0, 0], [8, 0], [4, 0], [4, 4], [2, 1]])
    np.testing.assert_array_equal(rotate(pts, 1, c), [[8, 0], [8, 8], [8, 4], [4, 4], [7, 2]])
    np.testing.assert_array_equal(rotate(pts, 0, c), pts)
    np.testing.assert_array_equal(rotate(rotate(pts, 2, c), 2, c), pts)


def test_epsilon_and_edge_resolution_known_answers():
    # ρ = 2 f δ / (τ 2^c l): f = 500 px, δ = 2 m, τ = 1 px, c = 5, l = 100 m
    rho = precision(2.0, 100.0, 1.0, 500.0, 5)
    assert rho == pytest.approx(2 * 500 * 2 / (32 * 100))  # 0.625
    assert edge_epsilon(rho, 100.0, 50.0) == pytest.approx(1.25)  # > 1: split
    assert edge_epsilon(rho, 100.0, 250.0) == pytest.approx(0.25)
    # ε 2^c rounded up to a power of two, at least 2 cells, at most 2^c
    eps = np.array([0.0, 0.01, 0.1, 0.25, 0.2501, 0.5, 1.0, 3.0, np.inf])
    assert edge_resolution(eps, 5).tolist() == [1, 1, 2, 3, 4, 4, 5, 5, 5]
    # τ = 0: infinite precision unless the edge is exact; the eye on the edge: ε = ∞
    assert np.isinf(precision(1.0, 10.0, 0.0, 500.0, 5))
    assert precision(0.0, 10.0, 0.0, 500.0, 5) == 0.0
    assert np.isinf(edge_epsilon(0.1, 10.0, 0.0)) and edge_epsilon(0.0, 10.0, 0.0) == 0.0


# -- ρ as published (Livny et al., Section 3 "Level of Detail": one global precision factor) --


def test_paper_rho_known_answers():
    # ρ = f / (τ 2^c): f = 500 px, c = 5
    assert paper_precision(1.0, 500.0, 5) == pytest.approx(500 / 32)  # 15.625
    assert paper_precision(2.0, 500.0, 5) == pytest.approx(500 / 64)  # 2 ρ_0 is τ / 2
    assert paper_precision(0.5, 240.0, 3) == pytest.approx(60.0)
    assert math.isinf(paper_precision(0.0, 500.0, 5))
    with pytest.raises(ValueError, match="tau"):
        paper_precision(-1.0, 500.0, 5)
    # an edge of 100 m at 2 km: ε = 15.625 · 100 / 2000 = 0.78 -> 25 cells -> 32 (r = 5)
    eps = edge_epsilon(paper_precision(1.0, 500.0, 5), 100.0, 2000.0)
    assert eps == pytest.approx(0.78125) and edge_resolution(eps, 5) == 5
    # at 4 km: ε = 0.39 (Claim 1's R1 range [0, 0.5]) -> 12.5 cells -> 16 (r = 4)
    assert edge_resolution(edge_epsilon(paper_precision(1.0, 500.0, 5), 100.0, 4000.0), 5) == 4


def test_paper_rho_is_the_flat_limit_and_ignores_roughness():
    f, tau, c, length = 500.0, 1.0, 5, 100.0
    deltas = np.array([0.0, 0.01, 0.5, 2.0, 10.0, 100.0])  # flat -> rough
    ours = precision(deltas, length, tau, f, c)
    paper = paper_precision(tau, f, c)
    # ours: 0 on flat terrain (never split), strictly increasing with the stored error
    assert ours[0] == 0.0 and (np.diff(ours) > 0).all()
    # the paper's: the same factor on flat and rough terrain (nothing is read from the data),
    # so non-decreasing in roughness; the two coincide where the stored error is half the edge
    assert paper > 0.0 and np.isfinite(paper)
    assert precision(length / 2, length, tau, f, c) == pytest.approx(paper)
    assert ours[deltas < length / 2].max() < paper < ours[deltas > length / 2].min()


def test_paper_rho_tau_is_the_projected_cell_in_pixels():
    # with ε <= 1 the edge's cells (ε 2^c rounded up) project to at most τ px at distance d;
    # ε > 1 (split) exactly when even the finest tile's cells would project to more than τ
    rng = np.random.default_rng(0)
    f, c = 480.0, 5
    for tau in (0.5, 1.0, 2.0, 4.0):
        length = rng.uniform(10.0, 5000.0, 2000)
        dist = rng.uniform(1.0, 1e5, 2000)
        eps = edge_epsilon(paper_precision(tau, f, c), length, dist)
        cells = np.left_shift(1, edge_resolution(eps, c))
        cell_px = f * length / (dist * cells)
        ok = eps <= 1.0
        assert ok.any() and (~ok).any()
        assert (cell_px[ok] <= tau * (1 + 1e-9)).all()
        assert (f * length[~ok] / (dist[~ok] * 2**c) > tau).all()


def test_neighbour_caps_are_the_lowest_drawn_cap_around_each_block():
    from render.strategies.seamless.frame import neighbour_caps

    rng = np.random.default_rng(3)
    drawn = sorted(rng.choice(20, 13, replace=False).tolist())
    blk = np.array([(b // 5, b % 5) for b in drawn], np.int64)
    cap = rng.integers(1, 9, len(blk)).astype(np.int64)
    caps = {tuple(b): int(v) for b, v in zip(blk.tolist(), cap, strict=True)}
    want = [
        min([caps[b]] + [caps[n] for n in ((b[0] + dr, b[1] + dc) for dr, dc in
             ((-1, 0), (0, 1), (1, 0), (0, -1))) if n in caps])
        for b in map(tuple, blk.tolist())
    ]  # fmt: skip
    got = neighbour_caps(blk, cap)
    assert got.tolist() == want
    assert got.tolist() != cap.tolist()  # some neighbour is lower: the rule does something
    # positive control: a block at the row's end is not the next row's first block's neighbour
    edge = np.array([(0, 4), (1, 0)], np.int64)
    assert neighbour_caps(edge, np.array([1, 7])).tolist() == [1, 7]
