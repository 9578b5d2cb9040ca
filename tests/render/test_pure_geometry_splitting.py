"""Pure known-answer tests of ``geometry_splitting`` (no GL: they run without an EGL context)."""

from __future__ import annotations

import numpy as np
import pytest

from render.errors import RenderError
from render.strategies.geometry_splitting import (
    packed_tree,
    projected_error,
    quad_errors,
    roughness,
    stored_tree,
    texture_depth,
    texture_nodes,
)
from streamer.camera import Camera
from tiler.static_error import bound_errors

SIZE = (128, 96)


def _brute_delta(h: np.ndarray, d: int, ok: np.ndarray | None = None) -> np.ndarray:
    """Node errors by explicit loops: every (valid) sample against its quad's two triangles."""
    n = h.shape[0] - 1
    s = n >> d
    out = np.zeros((1 << d, 1 << d))
    for r in range(1 << d):
        for c in range(1 << d):
            a, b = h[r * s, c * s], h[r * s, c * s + s]
            cc, dd = h[r * s + s, c * s], h[r * s + s, c * s + s]
            for j in range(s + 1):
                for i in range(s + 1):
                    u, v = i / s, j / s
                    q = (
                        a + u * (b - a) + v * (dd - b)
                        if u >= v
                        else a + v * (cc - a) + u * (dd - cc)
                    )
                    if ok is None or ok[r * s + j, c * s + i]:
                        out[r, c] = max(out[r, c], abs(h[r * s + j, c * s + i] - q))
    return out


def test_doubling_rule_on_a_known_tree():
    # δ of a 2-depth tree: the centre of the north-west depth-1 node is 8 m off its quad
    sig = roughness([np.array([[8.0]]), np.array([[8.0, 0.0], [0.0, 0.0]])])
    assert sig[1].tolist() == [[8.0, 0.0], [0.0, 0.0]]  # depth k - 1: σ = δ
    assert sig[0].tolist() == [[16.0]]  # the doubling wins over δ_0 = 8
    # rough and curved trees: σ follows the recursion, both branches occur
    rng = np.random.default_rng(5)
    noise = rng.integers(0, 40, (17, 17)).astype(np.float64)
    curved = np.add.outer(np.arange(17.0) ** 2, np.zeros(17)) + rng.integers(0, 2, (17, 17))
    by_delta = by_double = 0
    for g in (noise, curved):
        deltas = [_brute_delta(g, d) for d in range(4)]
        sig = roughness(deltas)
        for d in range(4):
            if d < 3:
                child = 2 * sig[d + 1].reshape(1 << d, 2, 1 << d, 2).max(axis=(1, 3))
                np.testing.assert_array_equal(sig[d], np.maximum(deltas[d], child))
                by_delta += int((deltas[d] > child).sum())
                by_double += int((child > deltas[d]).sum())
            else:
                np.testing.assert_array_equal(sig[d], deltas[d])  # σ_k = 0 below
    assert by_delta > 0 and by_double > 0


@pytest.mark.parametrize("level", [4, 2, 0])
def test_stored_tree_bounds_the_true_errors_and_heights(level):
    # the quadtree texture from the tiler's bound field and the level-R grid: σ >= the exact
    # doubling of the exact δ, σ_l >= 2 σ_(l+1) after float32 rounding, ranges enclose
    g = np.random.default_rng(5).integers(0, 40, (17, 17)).astype(np.float64)
    bound = bound_errors(g, np.ones_like(g, bool), 4)
    assert all((b >= _brute_delta(g, d) - 1e-9).all() for d, b in enumerate(bound))
    tree = stored_tree(bound, g[:: 1 << (4 - level), :: 1 << (4 - level)])
    exact = roughness([_brute_delta(g, d) for d in range(4)])
    for d in range(4):
        assert (tree.sigma[d] >= exact[d]).all()
        if d < 3:
            kids = tree.sigma[d + 1].reshape(1 << d, 2, 1 << d, 2).max(axis=(1, 3))
            assert (tree.sigma[d] >= 2 * kids).all()
        assert (tree.zmin[d] <= _pool(g, d, np.min)).all()
        assert (tree.zmax[d] >= _pool(g, d, np.max)).all()
    # exact δ where the store tiles its values: the brute force, and never looser
    qe = quad_errors(g, None, range(4))
    for d in range(4):
        np.testing.assert_allclose(qe[d], _brute_delta(g, d), rtol=1e-12)
    ok = np.random.default_rng(1).random(g.shape) > 0.2  # masked samples are ignored
    qm = quad_errors(g, ok, range(4))
    for d in range(4):
        np.testing.assert_allclose(qm[d], _brute_delta(g, d, ok), rtol=1e-12)
    tight = stored_tree([np.full_like(b, 1e3) for b in bound], g, {3: qe[3]})
    assert (tight.sigma[3] == _round_up32_ref(qe[3])).all() and (tight.sigma[2] >= 1e3).all()
    # the ranges come from the corners: a flat grid gives exact ranges and σ = 0
    flat = stored_tree([np.zeros((1 << d, 1 << d)) for d in range(4)], np.full((3, 3), 7.0))
    assert all((z == 7.0).all() for z in flat.zmin + flat.zmax)
    assert all((x == 0).all() for x in flat.sigma)
    with pytest.raises(RenderError, match="2\\*\\*R"):
        stored_tree(bound, np.zeros((4, 4)))


def _round_up32_ref(x):
    f = x.astype(np.float32)
    return np.where(f.astype(np.float64) < x, np.nextafter(f, np.float32(np.inf)), f)


def _pool(g, d, fn):
    n = g.shape[0] - 1
    s = n >> d
    return np.array(
        [[fn(g[r * s : r * s + s + 1, c * s : c * s + s + 1]) for c in range(1 << d)]
         for r in range(1 << d)]
    )  # fmt: skip


def test_projected_error_is_the_five_point_projection():
    cam = Camera.look_at((0.0, -3000.0, 1500.0), (0.0, 0.0, 0.0), viewport=SIZE, near=1.0)
    c = np.array([[100.0, 50.0, 20.0]])
    got = projected_error(c - cam.eye, 70.0, 8, cam, 30.0, 30.0)[0]
    want = 0.0
    for ox, oy in ((0, 0), (120, 0), (-120, 0), (0, 120), (0, -120)):
        p = c[0] + [ox, oy, 0.0]
        x0, y0, _ = cam.project(p[None])
        x1, y1, _ = cam.project((p + [0, 0, 70.0])[None])
        want = max(want, float(np.hypot(x1 - x0, y1 - y0)[0]))
    assert got == pytest.approx(want, rel=1e-9) and got > 0.5
    behind = projected_error(
        np.array([[0.0, 0.0, 0.0]]) + [0, -4000.0, -1500.0], 1.0, 8, cam, 30, 30
    )
    assert np.isinf(behind[0])


def _packed_by_stacking(t) -> np.ndarray:
    """The texture's layout as the GLSL reads it, by concatenation (the former ``packed``)."""
    s = np.concatenate([x.ravel() for x in t.sigma]).astype(np.float32).view(np.uint32)
    lo = np.concatenate([x.ravel() for x in t.zmin]).view(np.uint16).astype(np.uint32)
    hi = np.concatenate([x.ravel() for x in t.zmax]).view(np.uint16).astype(np.uint32)
    return np.stack([s, lo | (hi << 16)], 1)


@pytest.mark.parametrize("seed", range(4))
def test_packed_texture_is_sigma_bits_then_packhalf2x16(seed):
    rng = np.random.default_rng(seed)
    h = rng.normal(0, 50, (33, 33)).cumsum(0)
    h[rng.random(h.shape) < 0.01] = -0.0  # (signed zeros and infinities keep their bits)
    t = stored_tree(bound_errors(h, np.ones_like(h, bool), 5), h)
    t.sigma[2][1, 1] = np.inf
    got = t.packed()
    assert got.dtype == np.uint32 and got.shape == (sum(4**d for d in range(5)), 2)
    np.testing.assert_array_equal(got, _packed_by_stacking(t))
    lo = (got[:, 1] & 0xFFFF).astype(np.uint16).view(np.float16)  # unpackHalf2x16(q.y).x
    np.testing.assert_array_equal(lo, np.concatenate([x.ravel() for x in t.zmin]))
    t.zmax[3][0, 0] = np.float16(-1.0)  # control: one changed value is seen
    assert not np.array_equal(t.packed(), got)


def _capped_cases():
    """Stored bounds as a store keeps them (one value per tile below the cap depth), grids at
    every level below full resolution (signed zeros among the heights), with and without
    mixed nodes."""
    rng = np.random.default_rng(11)
    for k, cap in ((3, 1), (5, 2), (5, 4), (6, 3), (6, 5)):
        bound = [(rng.random((1 << min(d, cap),) * 2) * 40).astype(np.float16) for d in range(k)]
        n = (1 << k) + 1
        full = rng.normal(0, 30, (n, n)).cumsum(0)
        full[rng.random(full.shape) < 0.05] = -0.0
        for rr in range(k):
            grid = full[:: 1 << (k - rr), :: 1 << (k - rr)]
            for mixed in (None, [rng.random((1 << d,) * 2) < 0.1 for d in range(k)]):
                yield bound, grid, mixed


def test_packed_tree_is_the_stored_trees_texture_byte_for_byte():
    """Below full resolution the texture is packed without the per-node arrays (σ and δ per
    tile below the cap, ranges per ancestor): the same bytes as ``stored_tree`` with σ = ∞
    at the mixed nodes, then ``packed``. Control: one σ changed is seen."""
    cases = 0
    for bound, grid, mixed in _capped_cases():
        tree = stored_tree(bound, grid)
        for d, sig in enumerate(tree.sigma):
            if mixed is not None:
                sig[mixed[d]] = np.inf
        want = tree.packed()
        got = packed_tree(bound, grid, mixed)
        assert got.dtype == np.uint32 and got.tobytes() == want.tobytes()
        lo = tree.zmin[-1]
        lo[0, 0] = np.nextafter(lo[0, 0], np.float16(-np.inf))  # the control: a half-ulp
        assert tree.packed().tobytes() != got.tobytes()
        if mixed is not None:  # and the mixed nodes are written
            assert packed_tree(bound, grid, None).tobytes() != got.tobytes()
        cases += 1
    assert cases == 2 * (3 + 5 + 5 + 6 + 6)  # every level below full resolution


def _expand(compact: np.ndarray, k: int, top: int, bits: bool = True) -> np.ndarray:
    """A compact texture (:func:`texture_nodes`) in the full layout, read as the shader reads
    it: each node of a depth past ``top`` reads its depth-``top`` ancestor's entry, and its σ
    is ∞ where its bit is set in the bitmask after the entries (``bits=False``: ignored)."""
    rows, off, bit = [], 0, 0
    n = texture_nodes(k, top)
    words = compact[n:].ravel()  # uint32, bit i in word i // 32
    for d in range(k):
        a = min(d, top)
        m = 1 << a
        block = compact[off : off + m * m].reshape(m, m, 2)
        rep = 1 << (d - a)
        full = block.repeat(rep, 0).repeat(rep, 1).reshape(-1, 2).copy()
        if d > top and bits and len(words):
            i = bit + np.arange(full.shape[0])
            on = (words[i >> 5] >> (i & 31).astype(np.uint32)) & 1
            full[on.astype(bool), 0] = np.float32(np.inf).view(np.uint32)
            bit += full.shape[0]
        rows.append(full)
        off += m * m
    assert off == n and len(compact) == texture_nodes(k, top, len(compact) > n)
    return np.concatenate(rows)


def test_texture_nodes_and_depth():
    for k in range(1, 12):
        assert texture_nodes(k, k - 1) == ((1 << (2 * k)) - 1) // 3  # all depths
        assert texture_nodes(k, k - 1, True) == texture_nodes(k, k - 1)  # nothing deeper
        assert all(texture_nodes(k, d) < texture_nodes(k, d + 1) for d in range(k - 1))
    assert texture_nodes(10, 6) == 17_749  # a level-6 texture at 1025²: 142 KB, not 2.8 MB
    assert texture_nodes(10, 6, True) == 17_749 + 5_376  # + 344,064 bits (43 KB)
    assert texture_depth(10, 4, 6) == 6 and texture_depth(10, 8, 6) == 8
    assert texture_depth(10, 10, 6) == 9  # full resolution: exact errors per node
    assert texture_depth(10, 4, 12) == 9 and texture_depth(3, 0, 0) == 0


def test_a_compact_texture_reads_as_the_full_one():
    """Below full resolution, past ``texture_depth`` every depth's values are one per node of
    that depth (σ per cap tile, ranges per grid node) but for the mixed nodes' σ = ∞, which
    the bitmask after the entries carries: read as the shader reads it, the compact texture is
    the full one; ``packed_tree`` gives the same bytes as ``BlockTree.packed``. Control: the
    bitmask ignored, a texture with mixed nodes is not."""
    cases = with_bits = 0
    for bound, grid, mixed in _capped_cases():
        k = len(bound)
        rr = (grid.shape[0] - 1).bit_length() - 1
        cap = next((d for d in range(k) if bound[d].shape[0] < 1 << d), k) - 1
        tree = stored_tree(bound, grid)
        if mixed is not None:
            for d, sig in enumerate(tree.sigma):
                sig[mixed[d]] = np.inf
        top = texture_depth(k, rr, cap)
        got = packed_tree(bound, grid, mixed, depth=top)
        assert got.tobytes() == tree.packed(top).tobytes()
        assert np.array_equal(_expand(got, k, top), tree.packed())
        if top < k - 1:
            cases += 1
            if len(got) > texture_nodes(k, top):
                with_bits += 1
                assert mixed is not None
                assert not np.array_equal(_expand(got, k, top, bits=False), tree.packed())
    assert cases == 22 and with_bits == 11  # (k, cap) (3, 1): rr 0, 1; (5, 2): 0-3; (6, 3): 0-4


def test_a_texture_shallower_than_the_level_or_cap_is_refused():
    rng = np.random.default_rng(2)
    bound = [rng.random((1 << min(d, 2),) * 2).astype(np.float16) for d in range(5)]
    grid = rng.normal(0, 5, (9, 9))  # level 3
    with pytest.raises(RenderError, match="grid's level 3 and the error cap 2"):
        packed_tree(bound, grid, None, depth=2)
    with pytest.raises(RenderError, match="texture depth 7"):
        stored_tree(bound, grid).packed(7)
