"""The compiled walk of ``select_patches`` (numba, :mod:`render.select_kernels`) against the
numpy one: every array of the patches equal, bit for bit, over cameras, polygons (none, hull,
triangle, degenerate), windows, partial residency, ``min_depth`` and metrics (Qiu's and Kim's
compiled, the others through ``node_rho``), stitched too; positive controls show the comparison
catches a kernel one ulp off (Qiu's or Kim's metric), one that drops a node, one that splits one
node too few and one that loses a neighbour."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from test_select_vectorised import FIELDS, _cameras, _fields, _grid, _inputs

from render import select_kernels
from render.select import PatchTable, select_patches, stitch
from render.strategies.chunk_tess.pure import kim_metric
from streamer.frustum import frustum_hull, view_triangle
from tiler.errors import KernelUnavailableError


@pytest.fixture(scope="module")
def nb():
    pytest.importorskip("numba")
    return select_kernels.resolve("numba")


def _always(delta, centre_xyz, radius, camera):
    return np.full(np.shape(delta), np.inf)


def _table(g, p, seed):
    t = PatchTable(g.k, p, capacity=2)
    for b, f in _fields(g, seed).items():
        t.add(b, f)
    return t


def differences(a, b) -> list[str]:
    """Names of the patch arrays and counts that differ between ``a`` and ``b``."""
    out = []
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        if x.shape != y.shape or x.dtype != y.dtype or not np.array_equal(x, y, equal_nan=True):
            out.append(f)
    return out + [c for c in ("clamped", "violations") if getattr(a, c) != getattr(b, c)]


def _scenes(g, metric_names=("qiu", "conservative", "kim", "always")):
    blocks, res, zr, win = _inputs(g, seed=7)
    for cam in _cameras(g):
        polys = [None, frustum_hull(cam, (0.0, 300.0)), view_triangle(cam), np.zeros((0, 2))]
        for poly in polys:
            for name in metric_names:
                fn = {"kim": kim_metric, "always": _always}.get(name, name)
                for tau in (0.0,) if name == "always" else (0.0, 0.5, 1.0, 4.0):
                    for w in (win, None):
                        for min_depth in (0, 2):
                            kw = dict(resident=res, zranges=zr, windows=w, min_depth=min_depth)
                            yield (blocks, cam, tau, fn, poly), kw


def _diff_count(g, t, kernels_b, metric_names=("qiu",), stitched=False) -> tuple[int, int]:
    """(scenes that differ, patches compared) between the numpy walk and ``kernels_b``."""
    bad = n = 0
    for (blocks, cam, tau, fn, poly), kw in _scenes(g, metric_names):
        a = select_patches(g, blocks, t, cam, tau, fn, poly, kernels="numpy", **kw)
        b = select_patches(g, blocks, t, cam, tau, fn, poly, kernels=kernels_b, **kw)
        if stitched:
            skw = dict(resident=kw["resident"], zranges=kw["zranges"])
            a = stitch(a, g, t, cam, fn, kernels="numpy", **skw)
            b = stitch(b, g, t, cam, fn, kernels=kernels_b, **skw)
        bad += bool(differences(a, b))
        n += len(a)
    return bad, n


@pytest.mark.parametrize("p", [1, 2, 3])
def test_compiled_walk_equals_numpy(nb, p):
    g = _grid()
    t = _table(g, p, seed=p)
    bad, n = _diff_count(g, t, "numba", ("qiu", "conservative", "kim", "always"))
    assert bad == 0
    assert n > 5000  # the scenes do select something


def test_compiled_walk_equals_numpy_stitched(nb):
    g = _grid()
    t = _table(g, 2, seed=4)
    bad, n = _diff_count(g, t, "numba", ("qiu", "kim"), stitched=True)
    assert bad == 0 and n > 1000


def _perturbed(nb, **fns):
    names = ("visit", "split", "qiu_rho", "kim_rho", "neighbours")
    mod = SimpleNamespace(**{n: getattr(nb, n) for n in names})
    for name, f in fns.items():
        setattr(mod, name, f)
    return mod


@pytest.mark.parametrize("fault", ["ulp", "kim_ulp", "drop", "nosplit", "lonely"])
def test_the_comparison_catches_a_wrong_kernel(nb, monkeypatch, fault):
    def ulp(*a):
        rho = nb.qiu_rho(*a)
        fin = np.flatnonzero(np.isfinite(rho) & (rho > 0))
        if fin.size:
            rho[fin[0]] = np.nextafter(rho[fin[0]], np.inf)
        return rho

    def kim_ulp(*a):
        rho = nb.kim_rho(*a)
        fin = np.flatnonzero(np.isfinite(rho) & (rho > 0))
        if fin.size:
            rho[fin[-1]] = np.nextafter(rho[fin[-1]], 0.0)
        return rho

    def drop(*a):
        out = nb.visit(*a)
        return tuple(v[1:] for v in out) if len(out[0]) > 3 else out

    def nosplit(*a):
        leaf, child, want = nb.split(*a)
        if len(child[0]) < 8:
            return leaf, child, want
        a = list(a)
        over = np.flatnonzero(~(a[5] <= a[9]))
        if a[7] < a[10] or not over.size:  # min_depth splits whatever rho says
            return leaf, child, want
        a[5] = a[5].copy()
        a[5][over[-1]] = a[9]  # the last node over tau stays a leaf
        return nb.split(*a)

    def lonely(*a):
        out = nb.neighbours(*a)
        out[np.argmax((out >= 0).all(axis=1))] = -1  # one leaf loses its neighbours
        return out

    faults = {"ulp": ulp, "kim_ulp": kim_ulp, "drop": drop, "nosplit": nosplit, "lonely": lonely}
    name = {"ulp": "qiu_rho", "kim_ulp": "kim_rho", "drop": "visit", "nosplit": "split"}
    name = name.get(fault, "neighbours")
    bad_mod = _perturbed(nb, **{name: faults[fault]})
    monkeypatch.setattr(select_kernels, "resolve", lambda k=None: None if k == "numpy" else bad_mod)
    g = _grid()
    t = _table(g, 2, seed=2)
    metrics = ("kim",) if fault == "kim_ulp" else ("qiu",)
    bad, _ = _diff_count(g, t, "numba", metrics, stitched=fault == "lonely")
    assert bad > 0
    if fault.endswith("ulp"):  # one ulp of rho shows in rho itself, whatever the selection does
        assert bad > 10


def test_backend_names():
    assert select_kernels.resolve("numpy") is None
    with pytest.raises(KernelUnavailableError, match="kernels="):
        select_kernels.resolve("fortran")


@pytest.mark.parametrize("which", ["select", "jung-han", "seamless-patches"])
def test_auto_uses_compiled_kernels_only_after_warm_up(monkeypatch, which):
    """A one-shot command never waits for numba: ``auto`` is the numpy reference until
    ``warm_up``; explicit backends are unaffected (and ``numpy`` never warms)."""
    pytest.importorskip("numba")
    from render.strategies.jung_han import kernels as jh_kernels
    from render.strategies.seamless import kernels as sp_kernels

    mod = {"select": select_kernels, "jung-han": jh_kernels, "seamless-patches": sp_kernels}[which]
    nb = mod.resolve("numba")
    assert nb is not None
    monkeypatch.setattr(mod, "_READY", [])
    monkeypatch.setenv("TERRASTREAM_KERNELS", "auto")
    assert mod.resolve() is None
    assert mod.resolve("auto") is None
    assert mod.resolve("numba") is nb  # explicit: no warm-up needed
    assert mod.warm_up() is True
    assert mod.resolve() is nb and mod.resolve("auto") is nb
    monkeypatch.setattr(mod, "_READY", [])
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numpy")
    assert mod.warm_up() is False
    assert mod.resolve() is None and mod._READY == []


def test_warm_up_kernels_warms_every_strategy(monkeypatch):
    pytest.importorskip("numba")
    from render.strategies import jung_han, seamless, warm_up_kernels  # noqa: F401
    from render.strategies.jung_han import kernels as jh_kernels
    from render.strategies.seamless import kernels as sp_kernels

    for mod in (select_kernels, jh_kernels, sp_kernels):
        monkeypatch.setattr(mod, "_READY", [])
    monkeypatch.setenv("TERRASTREAM_KERNELS", "auto")
    assert all(warm_up_kernels().values())
    assert all(m.resolve() is not None for m in (select_kernels, jh_kernels, sp_kernels))
