"""The kernels' on-disk cache is keyed on the sources they depend on (``tiler.jit``).

numba keys a cached function on its own file only: after a change to a kernel it calls from
another module (or to a constant it imports), a fresh process loaded the old machine code.
Each test writes a small package of kernel modules, runs it in fresh processes (the cache on
disk between them), edits one file and runs it again.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("numba")

REPO = Path(__file__).resolve().parents[2]

DEP = """\
from tiler.jit import cached_njit
{decorator}


@_jit
def f():
    return {value}
"""

CONSTS = "K = {value}\n"

MAIN = """\
from kpkg.consts import K
from kpkg.dep_nb import f
from tiler.jit import cached_njit
{decorator}


@_jit
def g():
    return f() + K
"""

RUN = """\
from kpkg.main_nb import g
print(g(), sum(g.stats.cache_hits.values()), sum(g.stats.cache_misses.values()))
"""


def _write(root: Path, plain: bool, dep: int, k: int) -> None:
    deco = "import numba\n_jit = numba.njit(cache=True)" if plain else "_jit = cached_njit()"
    pkg = root / "kpkg"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "dep_nb.py").write_text(DEP.format(decorator=deco, value=dep))
    (pkg / "consts.py").write_text(CONSTS.format(value=k))
    (pkg / "main_nb.py").write_text(MAIN.format(decorator=deco))


def _run(root: Path) -> tuple[int, int, int]:
    """``(g(), cache hits, cache misses)`` of ``kpkg.main_nb.g`` in a fresh process."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), str(REPO)]))
    env.pop("NUMBA_CACHE_DIR", None)  # the cache beside the sources, as a checkout has it
    out = subprocess.run(
        [sys.executable, "-c", RUN], env=env, cwd=root, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-2000:]
    value, hits, misses = (int(v) for v in out.stdout.split())
    return value, hits, misses


def test_a_changed_callee_or_constant_in_another_module_recompiles(tmp_path):
    _write(tmp_path, plain=False, dep=1, k=100)
    assert _run(tmp_path) == (101, 0, 1)  # compiled, then saved
    assert _run(tmp_path) == (101, 1, 0)  # loaded: nothing changed
    _write(tmp_path, plain=False, dep=2, k=100)  # only the callee's module changes
    assert _run(tmp_path) == (102, 0, 1)
    _write(tmp_path, plain=False, dep=2, k=300)  # only the imported constant changes
    assert _run(tmp_path) == (302, 0, 1)
    assert _run(tmp_path) == (302, 1, 0)


def test_positive_control_numba_alone_loads_the_stale_code(tmp_path):
    """With numba's own key (its file only) the same edit is not seen: the test above could
    fail, and the hazard it guards against is real on this numba."""
    _write(tmp_path, plain=True, dep=1, k=100)
    assert _run(tmp_path) == (101, 0, 1)
    _write(tmp_path, plain=True, dep=2, k=300)
    assert _run(tmp_path) == (101, 1, 0)  # the old callee and constant, from the cache


def test_kernel_sources_follow_kernel_modules_only():
    """The project's own kernels: ``assemble``'s key covers the mesh kernels it calls;
    ``_kernels_nb``'s the constants of ``pure.py``; the stitch's the selection and plan kernels
    two modules away; never a module outside the project."""
    from tiler.jit import kernel_sources

    def rel(p: str) -> set[str]:
        return {f.relative_to(REPO).as_posix() for f in kernel_sources(REPO / p)}

    jh = "render/strategies/jung_han/"
    assert rel(jh + "_assemble_nb.py") == {
        jh + "_assemble_nb.py",
        jh + "_mesh_nb.py",
        "tiler/jit.py",
    }
    assert jh + "pure.py" in rel(jh + "_kernels_nb.py")
    assert {"render/_select_nb.py", "streamer/_plan_nb.py"} <= rel("render/_stitch_nb.py")
    # pure.py is followed for its constants, not through its own imports
    assert not any("base" in f or "frustum" in f for f in rel(jh + "_kernels_nb.py"))


def test_the_project_kernels_carry_the_sources_key():
    """Every kernel made by ``cached_njit`` (here the assembly's) caches with the key above."""
    from render.strategies.jung_han import _kernels_nb
    from tiler.jit import _SourcesCache

    assert isinstance(_kernels_nb.assemble._cache, _SourcesCache)
    assert isinstance(_kernels_nb.traverse._cache, _SourcesCache)


def test_without_numba_internals_the_kernels_still_cache(monkeypatch, caplog):
    """Another numba without the caching internals used here: a warning, numba's own key."""
    from numba.core import caching

    import tiler.jit as jit

    monkeypatch.delattr(caching, "_SourceFileBackedLocatorMixin")
    with caplog.at_level("WARNING", logger="tiler.kernels"):
        assert jit._sources_cache_class() is None
    assert "cannot be keyed" in caplog.text
    monkeypatch.setattr(jit, "_SourcesCache", None)
    f = jit.cached_njit()(lambda: 7)
    assert f() == 7 and type(f._cache) is caching.FunctionCache  # cached, numba's way


def test_relative_and_multiline_imports_are_followed(tmp_path):
    pkg = tmp_path / "rp"
    (pkg / "sub").mkdir(parents=True)
    for f in ("__init__.py", "sub/__init__.py", "a_nb.py", "b.py", "sub/c_nb.py", "d.py"):
        (pkg / f).write_text("")
    (pkg / "sub" / "c_nb.py").write_text("from ..d import X\n")
    (pkg / "a_nb.py").write_text(
        textwrap.dedent(
            """\
            import numpy as np
            from . import b
            from .sub import (  # the kernels
                c_nb,
            )
            """
        )
    )
    from tiler.jit import kernel_sources

    got = {f.relative_to(tmp_path).as_posix() for f in kernel_sources(pkg / "a_nb.py")}
    want = {"rp/a_nb.py", "rp/__init__.py", "rp/b.py", "rp/sub/__init__.py", "rp/sub/c_nb.py"}
    assert got == want | {"rp/d.py"}  # d.py: through the kernel module c_nb
