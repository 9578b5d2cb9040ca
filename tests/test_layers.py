"""The package layers and the public API's shape, checked from the source (no imports run):
tiler <- streamer <- render <- cli, moderngl and glfw only in render, the modules docs/RENDER.md
lists as GL-free reach no GL module through their project imports, public functions are typed
(module-level ones documented too), and no module imports another's private names. Each rule
has a positive control: a small tree that breaks it on purpose, which the checker must report."""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("tiler", "streamer", "render", "cli")
#: what each package may import of the others (the layers point one way)
ALLOWED = {
    "tiler": set(),
    "streamer": {"tiler"},
    "render": {"tiler", "streamer"},
    "cli": {"tiler", "streamer", "render"},
}
GL = ("moderngl", "glfw")


def module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def import_base(node: ast.ImportFrom, package: str) -> str:
    """The absolute module a ``from ... import`` names (relative imports resolved)."""
    base = node.module or ""
    if node.level:
        up = package.split(".")
        up = up[: len(up) - (node.level - 1)]
        base = ".".join([*up, base] if base else up)
    return base


def imports(root: Path, path: Path) -> set[str]:
    """Absolute names a module imports (relative imports resolved), at any depth of its code."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    name = module_name(root, path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = import_base(node, package)
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)  # `from pkg import module`
    return out


def modules(root: Path) -> dict[str, Path]:
    return {
        module_name(root, p): p
        for pkg in PACKAGES
        if (root / pkg).is_dir()
        for p in sorted((root / pkg).rglob("*.py"))
    }


def layer_violations(root: Path) -> list[str]:
    """``module imports name`` for every import that points the wrong way or reaches GL
    outside render."""
    found = []
    for name, path in modules(root).items():
        pkg = name.split(".")[0]
        for imp in sorted(imports(root, path)):
            top = imp.split(".")[0]
            if top in PACKAGES and top != pkg and top not in ALLOWED[pkg]:
                found.append(f"{name} imports {imp}")
            if top in GL and pkg != "render":
                found.append(f"{name} imports {imp}")
    return found


@functools.cache
def _import_graph(root: Path) -> tuple[dict[str, Path], dict[str, set[str]]]:
    """The project's modules and what each imports (parsed once a tree)."""
    mods = modules(root)
    return mods, {n: imports(root, p) for n, p in mods.items()}


def gl_reach(root: Path, start: str) -> list[str]:
    """An import chain from module ``start`` to a GL module through project modules ([] if
    none)."""
    mods, edges = _import_graph(root)
    parts = start.split(".")
    first = [".".join(parts[:j]) for j in range(1, len(parts) + 1)]  # its packages run first
    seen = set(first)
    stack = [(m, [m]) for m in first if m in mods]
    while stack:
        n, chain = stack.pop()
        for imp in sorted(edges.get(n, ())):
            if imp.split(".")[0] in GL:
                return [*chain, imp]
            # a module and the packages it sits in run when it is imported
            parts = imp.split(".")
            for j in range(1, len(parts) + 1):
                m = ".".join(parts[:j])
                if m in mods and m not in seen:
                    seen.add(m)
                    stack.append((m, [*chain, m]))
    return []


def gl_free_render_modules() -> list[str]:
    """The render modules docs/RENDER.md's table marks ``no`` in its GL column."""
    text = (ROOT / "docs" / "RENDER.md").read_text(encoding="utf-8")
    names = []
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[1] == "no":
            names += re.findall(r"`([a-z_]+)\.py`", cells[0])
    return [f"render.{n}" for n in names]


def test_the_layers_point_one_way():
    assert layer_violations(ROOT) == []


def test_the_gl_free_render_modules_reach_no_gl():
    names = gl_free_render_modules()
    assert "render.frame_types" in names and "render.mesh" in names  # the table was read
    mods = modules(ROOT)
    reach = {n: gl_reach(ROOT, n) for n in names}
    assert all(n in mods for n in names), [n for n in names if n not in mods]
    assert {n: c for n, c in reach.items() if c} == {}


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text, encoding="utf-8")
    return tmp_path


@pytest.mark.parametrize(
    ("files", "expected"),
    [
        ({"tiler/a.py": "from render.gpu import X\n"}, "tiler.a imports render.gpu"),
        ({"streamer/s.py": "def f():\n    import cli.main\n"}, "streamer.s imports cli.main"),
        (
            {"tiler/b/__init__.py": "from ..c import y\n", "tiler/c.py": "import moderngl\n"},
            "tiler.c imports moderngl",
        ),  # fmt: skip
        ({"render/r.py": "from cli import options\n"}, "render.r imports cli"),
    ],
)
def test_control_a_wrong_way_import_is_reported(tmp_path, files, expected):
    root = _tree(tmp_path, {"render/__init__.py": "", **files})
    assert expected in layer_violations(root)


def test_control_gl_reached_through_a_helper_is_reported(tmp_path):
    root = _tree(
        tmp_path,
        {
            "render/__init__.py": "",
            "render/sub/__init__.py": "from render import gpu\n",
            "render/sub/leaf.py": "x = 1\n",
            "render/pure.py": "from render import helper\n",
            "render/helper.py": "from render.gpu import ctx\n",
            "render/gpu.py": "import moderngl\n",
            "render/clean.py": "import numpy\n",
        },
    )
    assert gl_reach(root, "render.pure") == [
        "render.pure", "render.helper", "render.gpu", "moderngl",
    ]  # fmt: skip
    assert gl_reach(root, "render.clean") == []
    # a module whose own package imports GL reaches it too
    assert gl_reach(root, "render.sub.leaf") == ["render.sub", "render.gpu", "moderngl"]


def _api_problems(node: ast.AST, prefix: str, in_class: bool) -> list[str]:
    """:func:`untyped_or_undocumented` of one module's (or public class's) body."""
    found = []
    for ch in ast.iter_child_nodes(node):
        if isinstance(ch, ast.ClassDef) and not ch.name.startswith("_"):
            found += _api_problems(ch, f"{prefix}.{ch.name}", True)
        if not isinstance(ch, ast.FunctionDef | ast.AsyncFunctionDef) or ch.name.startswith("_"):
            continue
        if any("jit" in ast.unparse(d) for d in ch.decorator_list):
            continue
        args = [*ch.args.posonlyargs, *ch.args.args, *ch.args.kwonlyargs]
        args = [a for a in args if a.arg not in ("self", "cls")]
        if any(a.annotation is None for a in args) or ch.returns is None:
            found.append(f"{prefix}.{ch.name}: not typed")
        if not in_class and not ast.get_docstring(ch):
            found.append(f"{prefix}.{ch.name}: no docstring")
    return found


def untyped_or_undocumented(root: Path) -> list[str]:
    """Public functions and methods (of public classes) with a parameter or return type
    missing, and public module-level functions without a docstring; numba kernels (``*jit``
    decorators: typed by their callers' arrays) are left out."""
    found = []
    for name, path in modules(root).items():
        found += _api_problems(ast.parse(path.read_text(encoding="utf-8")), name, False)
    return found


def test_public_functions_are_typed_and_documented():
    assert untyped_or_undocumented(ROOT) == []


def test_control_an_untyped_or_undocumented_function_is_reported(tmp_path):
    root = _tree(
        tmp_path,
        {
            "tiler/__init__.py": "",
            "tiler/m.py": (
                'def f(a: int) -> int:\n    """Doc."""\n    return a\n'
                'def g(a) -> int:\n    """Doc."""\n    return a\n'
                'def h(a: int):\n    """Doc."""\n    return a\n'
                "def u(a: int) -> int:\n    return a\n"
                "def _private(a):\n    return a\n"
                "class C:\n    def m(self, x) -> None:\n        pass\n"
                "    def __init__(self) -> None:\n        pass\n"
                "@cached_njit\ndef kernel(a):\n    return a\n"
            ),
        },
    )
    assert untyped_or_undocumented(root) == [
        "tiler.m.g: not typed", "tiler.m.h: not typed", "tiler.m.u: no docstring",
        "tiler.m.C.m: not typed",
    ]  # fmt: skip


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_imports(root: Path) -> list[str]:
    """``from M import _x`` of project modules where ``M`` is not itself a private module (the
    numba kernel modules ``_*_nb`` share helpers among themselves) and ``_x`` is not a private
    module of ``M``'s package imported by a module of that package."""
    mods = modules(root)
    found = []
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.ImportFrom):
                continue
            base = import_base(node, package)
            if base.split(".")[0] not in PACKAGES or _is_private(base.rpartition(".")[2]):
                continue
            for a in node.names:
                if not _is_private(a.name):
                    continue
                if f"{base}.{a.name}" in mods and base == package:
                    continue  # a package's own private module
                found.append(f"{name} imports {base}.{a.name}")
    return found


def test_no_module_imports_another_modules_private_names():
    assert private_imports(ROOT) == []


def test_control_a_private_name_imported_across_modules_is_reported(tmp_path):
    root = _tree(
        tmp_path,
        {
            "tiler/__init__.py": "",
            "tiler/a.py": "def _helper():\n    pass\n",
            "tiler/_k_nb.py": "def _jit():\n    pass\n",
            "tiler/b.py": "from tiler.a import _helper\nfrom tiler import _k_nb\n",
            "tiler/c.py": "from ._k_nb import _jit\nfrom .a import __doc__\n",
            "streamer/__init__.py": "",
            "streamer/s.py": "from tiler import _k_nb\nfrom tiler.a import _helper as h\n",
        },
    )
    assert sorted(private_imports(root)) == [
        "streamer.s imports tiler._k_nb", "streamer.s imports tiler.a._helper",
        "tiler.b imports tiler.a._helper",
    ]  # fmt: skip
