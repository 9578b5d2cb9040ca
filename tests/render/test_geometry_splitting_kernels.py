"""``geometry-splitting``'s tree build on the render thread (issue 14): the compiled exact
errors (:mod:`render.strategies.geometry_splitting._tree_nb`) equal the numpy reference bit for
bit, and the quadtree texture built with fewer passes equals the one built before (kept here as
the reference, 705d042). No GL."""

from __future__ import annotations

import numpy as np
import pytest

from render.errors import RenderError
from render.strategies.geometry_splitting import kernels
from render.strategies.geometry_splitting.pure import (
    BlockTree,
    _half,
    _round_up32,
    packed_tree,
    quad_errors,
    stored_tree,
    texture_depth,
)


def _scenes():
    """Grids of 2**k+1 with heights from -11 km to +9 km, flat and rough, with and without
    masks (holes, a masked border, all masked but a corner)."""
    rng = np.random.default_rng(7)
    for k in (1, 2, 4, 6):
        n = (1 << k) + 1
        rough = rng.normal(0.0, 300.0, (n, n)).cumsum(0).cumsum(1) / n - 11_000.0 * rng.random()
        spikes = np.where(rng.random((n, n)) < 0.02, 9_000.0, 0.0) + rng.random((n, n))
        for h in (rough, spikes, np.full((n, n), 8_848.0)):
            holes = rng.random((n, n)) > 0.3
            border = np.ones((n, n), bool)
            border[:, -1] = border[-1, :] = False
            corner = np.zeros((n, n), bool)
            corner[0, 0] = True
            for valid in (None, holes, border, corner):
                yield k, h, valid


try:
    import numba  # noqa: F401
except ImportError:
    numba = None
needs_numba = pytest.mark.skipif(
    numba is None, reason="the compiled kernels need numba (the fast extra)"
)


@needs_numba
def test_the_compiled_exact_errors_are_the_references_bit_for_bit():
    scenes = 0
    for k, h, valid in _scenes():
        ref = quad_errors(h, valid, range(k))
        got = kernels.quad_errors(h, valid, range(k), kernels="numba")
        assert got.keys() == ref.keys()
        for d in ref:
            assert got[d].dtype == np.float64 and got[d].shape == ref[d].shape
            np.testing.assert_array_equal(got[d], ref[d])
        scenes += 1
    assert scenes == 48


@needs_numba
def test_positive_control_the_comparison_sees_one_sample_moved():
    """The same comparison tells apart the errors of a grid (k >= 4) with every other sample
    of every other row raised by 1 mm."""
    told = 0
    for k, h, valid in _scenes():
        if k < 4 or valid is not None:
            continue
        moved = h.copy()
        moved[1::2, 1::2] += 1e-3
        ref = quad_errors(h, valid, range(k))
        got = kernels.quad_errors(moved, valid, range(k), kernels="numba")
        told += any(not np.array_equal(got[d], ref[d]) for d in ref)
    assert told == 6


def _stored_tree_before(bound, grid, exact=None) -> BlockTree:
    """``stored_tree`` as it was (705d042): per-node fields by two repeats, the corners
    stacked, every depth's ranges rounded after their repeat."""
    k = len(bound)
    g = np.asarray(grid, dtype=np.float64)
    rr = (g.shape[0] - 1).bit_length() - 1
    if g.shape != ((1 << rr) + 1,) * 2 or not 0 <= rr <= k:
        raise RenderError("bad grid")

    def per_node(arr, d):
        rep = (1 << d) // arr.shape[0]
        return np.repeat(np.repeat(np.asarray(arr, dtype=np.float64), rep, 0), rep, 1)

    deltas = [per_node(bound[d], d) for d in range(k)]
    for d, e in (exact or {}).items():
        deltas[d] = np.minimum(deltas[d], e)
    sig = [np.asarray(x, dtype=np.float64) for x in deltas]
    for d in range(len(sig) - 2, -1, -1):
        m = 1 << d
        sig[d] = np.maximum(sig[d], 2.0 * sig[d + 1].reshape(m, 2, m, 2).max(axis=(1, 3)))
    zmin, zmax = [], []
    for d in range(k):
        a = min(d, rr, k - 1)
        c = g[:: 1 << (rr - a), :: 1 << (rr - a)] if a <= rr else g
        quad = np.stack([c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]])
        lo, hi = quad.min(axis=0) - deltas[a], quad.max(axis=0) + deltas[a]
        rep = 1 << (d - a)
        zmin.append(np.repeat(np.repeat(lo, rep, 0), rep, 1))
        zmax.append(np.repeat(np.repeat(hi, rep, 0), rep, 1))
    return BlockTree(
        sigma=[_round_up32(x) for x in sig],
        zmin=[_half(z, False) for z in zmin],
        zmax=[_half(z, True) for z in zmax],
    )


def _trees_equal(a: BlockTree, b: BlockTree) -> bool:
    return all(
        x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y)
        for f in ("sigma", "zmin", "zmax")
        for x, y in zip(getattr(a, f), getattr(b, f), strict=True)
    )


def _tree_cases():
    rng = np.random.default_rng(11)
    for k, h, valid in _scenes():
        if k < 2 or valid is not None and not valid.any():
            continue
        cap = max(0, k - 2)  # the store keeps one value per tile below its cap depth
        bound = [
            np.abs(rng.normal(0, 50.0, (1 << min(d, cap),) * 2)).astype(np.float16)
            for d in range(k)
        ]
        exact = quad_errors(h, valid, range(cap + 1, k))
        for rr in (k, k - 1, 0):
            step = 1 << (k - rr)
            yield bound, h[::step, ::step], exact if rr == k else None


def test_the_tree_is_the_one_built_before():
    cases = 0
    for bound, grid, exact in _tree_cases():
        assert _trees_equal(
            stored_tree(bound, grid, exact), _stored_tree_before(bound, grid, exact)
        )
        cases += 1
    assert cases >= 60


def test_positive_control_the_comparison_sees_a_range_an_ulp_off():
    told = cases = 0
    for bound, grid, exact in _tree_cases():
        ref = _stored_tree_before(bound, grid, exact)
        tree = stored_tree(bound, grid, exact)
        tree.zmin[-1] = np.nextafter(tree.zmin[-1], np.float16(np.inf))  # one half-ulp up
        told += not _trees_equal(tree, ref)
        cases += 1
    assert told == cases >= 60


@needs_numba
def test_warm_up_loads_the_kernel_off_the_render_thread():
    """``warm_up`` (the viewer runs it on a background thread) calls the kernel once, so its
    machine code is loaded there and not at the first tree the render thread builds; in a
    fresh process the kernel has no compiled signature before it (the control)."""
    words = _fresh_process(
        "from render.strategies.geometry_splitting import _tree_nb, kernels\n"
        "before = len(_tree_nb.quad_errors_depth.signatures)\n"
        "ok = kernels.warm_up()\n"
        "print(before, len(_tree_nb.quad_errors_depth.signatures), ok)\n"
    )
    assert words == ["0", "1", "True"], words


@needs_numba
def test_auto_uses_the_kernels_only_once_warm_up_has_loaded_them():
    """A render thread that picked the kernels while the warm-up thread was still loading
    them would wait for numba's compiler lock (a 40-150 ms first tree on a flight): ``auto``
    switches only after both kernels have run (control: before ``warm_up``, numpy)."""
    words = _fresh_process(
        "import os\n"
        "os.environ.pop('TERRASTREAM_KERNELS', None)\n"
        "from render.strategies.geometry_splitting import _tree_nb, kernels\n"
        "seen = []\n"
        "real = _tree_nb.corner_ranges\n"
        "def spy(*a):\n"
        "    seen.append(kernels.resolve() is not None)\n"
        "    return real(*a)\n"
        "_tree_nb.corner_ranges = spy\n"
        "before = kernels.resolve() is None\n"
        "kernels.warm_up()\n"
        "print(before, seen, kernels.resolve() is not None)\n"
    )
    assert words == ["True", "[False]", "True"], words


@needs_numba
def test_the_compiled_packed_texture_is_the_numpy_ones_byte_for_byte():
    """``kernels.packed_tree`` with the compiled corner ranges: the numpy reference's bytes
    below full resolution (signed zeros among the heights, mixed nodes or not)."""
    from test_pure_geometry_splitting import _capped_cases

    cases = 0
    for bound, grid, mixed in _capped_cases():
        want = packed_tree(bound, grid, mixed)
        got = kernels.packed_tree(bound, grid, mixed, kernels="numba")
        assert got.tobytes() == want.tobytes()
        # and the compact layout (pure.texture_depth), with the bitmask where mixed
        k, rr = len(bound), (grid.shape[0] - 1).bit_length() - 1
        cap = next((d for d in range(k) if bound[d].shape[0] < 1 << d), k) - 1
        top = texture_depth(k, rr, cap)
        got = kernels.packed_tree(bound, grid, mixed, kernels="numba", depth=top)
        assert got.tobytes() == packed_tree(bound, grid, mixed, depth=top).tobytes()
        cases += 1
    assert cases == 50


def _bits(a: BlockTree) -> list[bytes]:
    return [x.tobytes() for f in ("sigma", "zmin", "zmax") for x in getattr(a, f)]


def _signed_zero_cases():
    """Flat ground at 0 m with -0.0 among the heights and δ = 0: the ranges' min and max
    meet equal values of opposite signs."""
    rng = np.random.default_rng(3)
    for k in (2, 4, 5):
        n = (1 << k) + 1
        g = np.where(rng.random((n, n)) < 0.5, -0.0, 0.0)
        bound = [np.zeros((1 << d, 1 << d), np.float16) for d in range(k)]
        for rr in (k, 1):
            yield bound, g[:: 1 << (k - rr), :: 1 << (k - rr)], None


@needs_numba
def test_the_compiled_tree_is_the_numpy_ones_bit_for_bit():
    """With the corner ranges by the kernel, every array of the tree has the numpy
    reference's bytes (signed zeros included: ``np.minimum`` keeps the second of two equal
    values)."""
    cases = 0
    for bound, grid, exact in [*_tree_cases(), *_signed_zero_cases()]:
        ref = stored_tree(bound, grid, exact)
        got = kernels.stored_tree(bound, grid, exact, kernels="numba")
        assert _bits(got) == _bits(ref)
        cases += 1
    assert cases >= 66


def test_positive_control_the_bitwise_comparison_sees_a_signed_zero():
    """The comparison is of bytes: a tree with its -0.0 ranges made +0.0 (equal values)
    differs."""
    told = negative = 0
    for bound, grid, exact in _signed_zero_cases():
        ref = stored_tree(bound, grid, exact)
        flipped = stored_tree(bound, grid, exact)
        flipped.zmin = [z + np.float16(0.0) for z in flipped.zmin]  # -0.0 + 0.0 = +0.0
        assert _trees_equal(flipped, ref)
        told += _bits(flipped) != _bits(ref)
        negative += any(np.signbit(z).any() for z in ref.zmin)
    assert told == negative >= 4


@needs_numba
def test_a_read_only_mask_uses_the_warmed_kernel():
    """A session's masks are read-only; the kernel is called with a writable copy, so it
    runs the signature ``warm_up`` loaded instead of loading (or compiling) another on the
    render thread. Control: the kernel called with the read-only mask itself adds one."""
    words = _fresh_process(
        "import numpy as np\n"
        "from render.strategies.geometry_splitting import _tree_nb, kernels\n"
        "kernels.warm_up()\n"
        "n = lambda: len(_tree_nb.quad_errors_depth.signatures)\n"
        "h = np.random.default_rng(0).random((17, 17))\n"
        "ok = np.ones((17, 17), bool); ok[3:9, 2:5] = False; ok.setflags(write=False)\n"
        "a = n(); kernels.quad_errors(h, ok, range(4)); b = n()\n"
        "_tree_nb.quad_errors_depth(h, ok, 2, np.empty((4, 4))); c = n()\n"
        "print(a, b, c)\n"
    )
    assert words == ["1", "1", "2"], words


def _fresh_process(code: str) -> list[str]:
    """The words ``code`` prints, run in a fresh Python (no kernel loaded yet; the backend
    left to ``auto``)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "TERRASTREAM_KERNELS"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300,
        env=env,
    )  # fmt: skip
    return out.stdout.split()
