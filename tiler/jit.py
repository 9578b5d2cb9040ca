"""numba's ``njit`` with its on-disk cache, for the kernel modules (importing this imports numba).

The compiled code is cached beside the sources (``cache=True``); where that directory is not
writable, a per-user temporary directory is used, and where no cache works at all the kernels
compile in memory (logged). Used by :mod:`tiler._kernels_nb` and the renderer's kernels.

numba keys a function's cache on its own source file only, yet the compiled code also holds the
kernels it calls from other modules and the constants it reads from them: after a change to
``_mesh_nb.py`` alone, ``_assemble_nb.assemble`` loaded its old machine code, old callee
included (a checkout or an editable install that updates some files, not all). Here the key
also covers the project modules a kernel module imports from (:func:`kernel_sources`: followed
on through the other kernel modules, ``*_nb.py``), so any change to them compiles it afresh.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import logging
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
from numba.core import caching

log = logging.getLogger("tiler.kernels")
#: a module-level import statement: ``from BASE import NAMES`` (NAMES maybe in parentheses over
#: several lines, with comments) or ``import MODS``
_IMPORT = re.compile(
    r"^(?:from[ \t]+(?P<base>\.*[\w.]*)[ \t]+import[ \t]+(?P<names>\([^)]*\)|[^\n]*)"
    r"|import[ \t]+(?P<mods>[^\n#]*))",
    re.MULTILINE,
)


@functools.cache
def _imported_files(path: Path, root: Path) -> list[Path]:
    """The ``.py`` files under ``root`` of the modules ``path`` imports at module level
    (absolute or relative ``import`` / ``from ... import`` statements at the start of a line:
    nothing is imported here). A module ``a.b`` is ``root/a/b.py`` or ``root/a/b/__init__.py`` (the
    project's layout); others (numpy, numba, the standard library) are not under ``root``."""
    pkg = ".".join(path.relative_to(root).with_suffix("").parts[:-1])
    names: list[str] = []
    for m in _IMPORT.finditer(path.read_text(encoding="utf-8")):
        if m["base"] is None:  # import a.b, c as d
            names += [n.split()[0] for n in m["mods"].split(",") if n.strip()]
            continue
        base = m["base"]
        if base.startswith("."):
            dots = len(base) - len(base.lstrip("."))
            base = importlib.util.resolve_name("." * dots + base[dots:], pkg or "_")
        names.append(base)
        listed = re.sub(r"#[^\n]*", "", m["names"]).strip("()").replace("\\", " ")
        for n in listed.split(","):  # (a submodule imported by name)
            if n.split():
                names.append(f"{base}.{n.split()[0]}")
    out = []
    for name in dict.fromkeys(names):
        where = root.joinpath(*name.split("."))
        for f in (where.with_suffix(".py"), where / "__init__.py"):
            if f.is_file():
                out.append(f.resolve())
                break
    return out


def _root_of(path: Path) -> Path:
    """The directory holding the top-level package of the module at ``path``."""
    d = path.parent
    while (d / "__init__.py").exists():
        d = d.parent
    return d


def kernel_sources(path: Path) -> list[Path]:
    """The files whose change must recompile the kernels of the module at ``path``: itself, the
    project modules it imports from, and on through those that are kernel modules
    (``*_nb.py``: their kernels are compiled into its own), sorted."""
    path = Path(path).resolve()
    root = _root_of(path)
    seen, todo = {path}, [path]
    while todo:
        for f in _imported_files(todo.pop(), root):
            if f not in seen:
                seen.add(f)
                if f.stem.endswith("_nb"):
                    todo.append(f)
    return sorted(seen)


@functools.cache
def sources_stamp(path: str) -> bytes:
    """sha256 over :func:`kernel_sources` of ``path`` (their paths from the project's root and
    contents), which the kernels' cache key adds to numba's; once per module and process."""
    p = Path(path).resolve()
    root = _root_of(p)
    h = hashlib.sha256()
    for f in kernel_sources(p):
        h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes() + b"\0")
    return h.digest()


def _with_sources(cls: type) -> type:
    """numba's locator ``cls`` with :func:`sources_stamp` added to its source stamp."""

    def get_source_stamp(self: Any) -> Any:
        return (cls.get_source_stamp(self), sources_stamp(self._py_file))

    return type(f"Sources{cls.__name__}", (cls,), {"get_source_stamp": get_source_stamp})


def _sources_cache_class() -> type | None:
    """numba's function cache class keyed also on :func:`kernel_sources`, built on numba's
    caching internals (``numba.core.caching``); None, logged, where they are not as expected
    (another numba version): the kernels then cache with numba's own key."""
    try:
        backed = caching._SourceFileBackedLocatorMixin

        class _SourcesImpl(caching.CompileResultCacheImpl):
            _locator_classes = [
                _with_sources(c) if issubclass(c, backed) else c
                for c in caching.CompileResultCacheImpl._locator_classes
            ]

        class _SourcesCache(caching.FunctionCache):
            """numba's function cache, keyed also on the kernel module's imported sources."""

            _impl_class = _SourcesImpl

        return _SourcesCache
    except (AttributeError, TypeError) as exc:
        log.warning(
            "numba %s: its cache cannot be keyed on the kernels' imported sources (%s); a "
            "change to a kernel module may need its __pycache__ cleared",
            numba.__version__,
            exc,
        )
        return None


_SourcesCache = _sources_cache_class()


def _cached(fn: Callable, opts: dict[str, Any]) -> Any:
    """``numba.njit(cache=True, **opts)(fn)`` with :data:`_SourcesCache` as its cache (what
    ``cache=True`` does, ``Dispatcher.enable_caching``, with the key of the module doc); raises
    numba's ``RuntimeError`` where no cache directory works."""
    if _SourcesCache is None:
        return numba.njit(cache=True, **opts)(fn)
    disp = numba.njit(cache=False, **opts)(fn)
    if hasattr(disp, "_cache"):  # (not NUMBA_DISABLE_JIT's plain function)
        disp._cache = _SourcesCache(disp.py_func)
    return disp


def cached_njit(**opts: Any) -> Callable[[Callable], Any]:
    """A decorator: ``numba.njit(cache=True, **opts)``, its cache keyed also on the sources it
    depends on, with the module doc's cache fallbacks."""

    def jit(fn: Callable) -> Any:
        try:
            return _cached(fn, opts)
        except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
            fallback = os.path.join(tempfile.gettempdir(), f"terrastream-numba-{os.getuid()}")
            try:
                os.makedirs(fallback, exist_ok=True)
                numba.config.CACHE_DIR = fallback
                return _cached(fn, opts)
            except (OSError, RuntimeError):
                log.warning("numba cannot cache compiled kernels (%s); compiling in memory", exc)
                return numba.njit(cache=False, **opts)(fn)

    return jit
