"""``seamless-patches``' compiled selection (numba) against the numpy reference: every output
array of the layout equal, bit for bit, on rough, nodata and mixed-residency scenes, both forms
of ρ, with and without the spike guard, on every compiled path (the whole selection in one call,
one traversal call, one call per depth, compiled or numpy resolution rounds); positive controls
show the comparison catches a kernel that is off by one ulp, that loses the shared edges, a
leaf or a child, that culls one node, or that is off by one edge level, violation or round."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render.renderer import RenderConfig, TerrainRenderer
from render.strategies import get_strategy
from render.strategies.seamless import kernels as sp_kernels
from streamer.camera import Camera
from tiler.errors import KernelUnavailableError
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
FIELDS = ("blocks", "block", "depth", "row", "col", "edge_level", "eps")
TAUS = (0.0, 0.05, 0.5, 1.0, 4.0, 1e6)


@pytest.fixture(scope="module")
def numba_kernels():
    pytest.importorskip("numba")
    return sp_kernels.resolve("numba")


@pytest.fixture(scope="module")
def renderers(tmp_path_factory):
    n = 129
    hole = rough(n, 5).astype(np.float32)
    hole[30:70, 10:50] = np.nan  # nodata beside terrain
    out = {}
    for name, dem, kw in (("rough", rough(n, 3), {}), ("nodata", hole, {"nodata": np.nan})):
        s = open_store(tile_dem(tmp_path_factory.mktemp(name), dem, 33, **kw))
        r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
        for b in s.blocks():
            r.upload(b, s.read_levels(b, s.k))
        out[name] = r
    yield out
    for r in out.values():
        r.close()


def _cameras(r) -> list[Camera]:
    g = r.grid
    x0, y0, x1, y1 = g.extent
    w = x1 - x0
    zlo, zhi = r.terrain_zrange
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return [
        Camera((cx, cy, zhi + 2 * w), pitch=-90.0, viewport=SIZE, near=5.0, far=1e5),
        Camera.look_at(
            (x0 + 0.15 * w, y1 - 0.1 * w, zhi + 0.4 * w), (cx, cy, zlo), viewport=SIZE, near=5.0
        ),
        Camera((x0 + 0.3 * w, cy, zhi + 2.0), yaw=40.0, pitch=-3.0, viewport=SIZE, near=0.5),
    ]


def differences(a, b) -> list[str]:
    """Names of the layout arrays and counts that differ between ``a`` and ``b``."""
    out = []
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        if x.shape != y.shape or x.dtype != y.dtype or not np.array_equal(x, y, equal_nan=True):
            out.append(f)
    return out + [
        c for c in ("clamped", "violations", "res_log2") if getattr(a, c) != getattr(b, c)
    ]


def _compare(r, resident=None, **opts) -> int:
    ref = get_strategy("seamless-patches", r, kernels="numpy", res_log2=3, **opts)
    fast = get_strategy("seamless-patches", r, kernels="numba", res_log2=3, **opts)
    leaves = 0
    for cam in _cameras(r):
        for tau in TAUS:
            a, _ = ref.select(cam, tau, resident=resident)
            b, _ = fast.select(cam, tau, resident=resident)
            assert differences(a, b) == [], (cam, tau, opts)
            leaves += len(a)
    return leaves


@pytest.mark.parametrize("scene", ["rough", "nodata"])
@pytest.mark.parametrize(
    "opts", [{}, {"rho": "paper"}, {"spike_guard": True}, {"rho": "paper", "spike_guard": True}]
)
def test_compiled_selection_equals_the_numpy_reference(renderers, numba_kernels, scene, opts):
    assert _compare(renderers[scene], **opts) > 0


def test_compiled_selection_equals_the_reference_with_mixed_levels(renderers, numba_kernels):
    r = renderers["rough"]
    k = r.k
    res = {b: k - 1 - (b[0] + b[1]) % 3 for b in r.store.blocks()}
    res[(0, 0)] = 0  # not drawn (no centre sample): clamped
    assert _compare(r, resident=res) > 0


def _select_with(monkeypatch, r, kernel_module):
    monkeypatch.setattr(sp_kernels, "_load_numba", lambda: kernel_module)
    st = get_strategy("seamless-patches", r, kernels="numba", res_log2=3)
    return st.select(_cameras(r)[1], 1.0)[0]


def test_positive_controls_perturbed_kernels_are_caught(renderers, numba_kernels, monkeypatch):
    r = renderers["rough"]
    ref, _ = get_strategy("seamless-patches", r, kernels="numpy", res_log2=3).select(
        _cameras(r)[1], 1.0
    )

    def epsilon(*args):
        out = numba_kernels.epsilon(*args)
        out[len(out) // 2, 1] = np.nextafter(out[len(out) // 2, 1], np.inf)
        return out

    nb = numba_kernels
    off = SimpleNamespace(epsilon=epsilon, edge_groups=nb.edge_groups, disc_meets=nb.disc_meets)
    assert differences(ref, _select_with(monkeypatch, r, off)) == ["eps"]
    unshared = SimpleNamespace(  # every edge its own group: the neighbours no longer agree
        epsilon=nb.epsilon,
        edge_groups=lambda d, *a: np.arange(4 * len(d)).reshape(-1, 4),
        disc_meets=nb.disc_meets,
    )
    assert "edge_level" in differences(ref, _select_with(monkeypatch, r, unshared))

    def one_culled(*args):  # the first node tested at each depth is culled
        out = nb.disc_meets(*args)
        out[:1] = False
        return out

    culled = SimpleNamespace(epsilon=nb.epsilon, edge_groups=nb.edge_groups, disc_meets=one_culled)
    assert "depth" in differences(ref, _select_with(monkeypatch, r, culled))
    monkeypatch.undo()
    assert differences(ref, _select_with(monkeypatch, r, numba_kernels)) == []


def test_positive_controls_the_fused_depth_kernel_is_checked(renderers, numba_kernels, monkeypatch):
    # the production path runs each depth as one call (traverse_depth); break it on purpose
    r = renderers["rough"]
    ref, _ = get_strategy("seamless-patches", r, kernels="numpy", res_log2=3).select(
        _cameras(r)[1], 1.0
    )
    nb = numba_kernels

    def one_ulp(*args):
        leaf, child, clamped, seen = nb.traverse_depth(*args)
        if len(leaf[3]):
            leaf[3][0, 2] = np.nextafter(leaf[3][0, 2], np.inf)
        return leaf, child, clamped, seen

    def lost_child(*args):  # the last child of each depth is not visited
        leaf, child, clamped, seen = nb.traverse_depth(*args)
        return leaf, tuple(c[:-1] for c in child), clamped, seen

    for fault, field in ((one_ulp, "eps"), (lost_child, "depth")):
        mod = SimpleNamespace(
            epsilon=nb.epsilon,
            edge_groups=nb.edge_groups,
            disc_meets=nb.disc_meets,
            traverse_depth=fault,
        )
        assert field in differences(ref, _select_with(monkeypatch, r, mod))
    monkeypatch.undo()
    assert differences(ref, _select_with(monkeypatch, r, numba_kernels)) == []


def _without(nb, *names) -> SimpleNamespace:
    """The kernel module ``nb`` without the kernels ``names`` (the selection then takes the
    paths that call the others from Python)."""
    keep = ("epsilon", "edge_groups", "disc_meets", "traverse_depth", "traverse_all")
    return SimpleNamespace(
        **{n: getattr(nb, n) for n in keep + ("resolve_round",) if n not in names}
    )


@pytest.mark.parametrize(
    "missing", [("select_all",), ("select_all", "traverse_all"), ("select_all", "resolve_round")]
)
def test_each_compiled_path_equals_the_numpy_reference(
    renderers, numba_kernels, monkeypatch, missing
):
    # production takes select_all; the paths below it (one traversal call, one call per
    # depth, the compiled or numpy resolution rounds) give the same layout
    monkeypatch.setattr(sp_kernels, "_load_numba", lambda: _without(numba_kernels, *missing))
    for scene in ("rough", "nodata"):
        assert _compare(renderers[scene]) > 0


def test_positive_controls_the_resolution_kernels_are_checked(
    renderers, numba_kernels, monkeypatch
):
    # select_all (the whole selection), resolve_round (one resolution round) and traverse_all
    # (one traversal) each broken on purpose: the comparison with the reference catches it
    r = renderers["rough"]
    cam = _cameras(r)[1]
    ref, _ = get_strategy("seamless-patches", r, kernels="numpy", res_log2=3).select(cam, 1.0)
    nb = numba_kernels

    def whole_ulp(*args):
        out = nb.select_all(*args)
        out[5][len(out[5]) // 2, 3] = np.nextafter(out[5][len(out[5]) // 2, 3], np.inf)
        return out

    def whole_level(*args):
        out = nb.select_all(*args)
        out[6][0, 0] += 1
        return out

    def whole_violation(*args):
        return (*nb.select_all(*args)[:8], 1)

    for fault, field in (
        (whole_ulp, "eps"),
        (whole_level, "edge_level"),
        (whole_violation, "violations"),
    ):
        mod = SimpleNamespace(**vars(_without(nb)), select_all=fault)
        assert differences(ref, _select_with(monkeypatch, r, mod)) == [field]

    def round_level(*args):
        split, v, level, violations = nb.resolve_round(*args)
        if not split:
            level[-1, 2] -= 1
        return split, v, level, violations

    def round_split_late(*args):  # the first split leaf is left to the next round
        split, v, level, violations = nb.resolve_round(*args)
        return split, (v[1:] if len(v) > 1 else v), level, violations

    def all_lost_leaf(*args):  # the traversal loses its last leaf
        *leaf, clamped = nb.traverse_all(*args)
        return (*(a[:-1] for a in leaf), clamped)

    def all_ulp(*args):
        out = nb.traverse_all(*args)
        if len(out[4]):
            out[4][0, 1] = np.nextafter(out[4][0, 1], -np.inf)
        return out

    base = _without(nb, "select_all")
    for name, fault, field in (
        ("resolve_round", round_level, "edge_level"),
        ("resolve_round", round_split_late, "block"),
        ("traverse_all", all_lost_leaf, "depth"),
        ("traverse_all", all_ulp, "eps"),
    ):
        mod = SimpleNamespace(**{**vars(base), name: fault})
        assert field in differences(ref, _select_with(monkeypatch, r, mod)), name
    monkeypatch.undo()
    assert differences(ref, _select_with(monkeypatch, r, numba_kernels)) == []


def test_resolution_helpers_equal_numpy(numba_kernels):
    # the compiled resolution's own sort, depth list and edge resolution against numpy's
    from render.strategies.seamless._resolve_nb import _argsort, _depths, _edge_resolution
    from render.strategies.seamless.layout import edge_resolution

    rng = np.random.default_rng(5)
    for n in (0, 1, 2, 7, 64, 1000):
        keys = rng.choice(10 * n + 1, n, replace=False).astype(np.int64)
        assert _argsort(keys).tolist() == np.argsort(keys).tolist()
        d = rng.integers(0, 9, n).astype(np.int64)
        assert _depths(d, 8).tolist() == np.unique(d).tolist()
    eps = np.array([0.0, 1e-9, 0.1, 0.125, 0.13, 0.5, 1.0, 3.0, 1e9, np.inf, np.nan])
    for c in (1, 3, 4):
        want = edge_resolution(eps, c).tolist()
        assert [_edge_resolution(float(e), c) for e in eps] == want
    assert len(set(edge_resolution(eps, 4).tolist())) > 2  # the cases span several levels


def test_backend_selection(monkeypatch):
    assert sp_kernels.resolve("numpy") is None
    with pytest.raises(KernelUnavailableError):
        sp_kernels.resolve("fortran")
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numpy")
    assert sp_kernels.resolve() is None  # the environment forces the reference
    monkeypatch.setenv("TERRASTREAM_KERNELS", "auto")
    monkeypatch.setattr(sp_kernels, "_load_numba", lambda: None)  # numba not installed
    assert sp_kernels.resolve() is None
    with pytest.raises(KernelUnavailableError):
        sp_kernels.resolve("numba")
