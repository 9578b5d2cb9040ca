"""Audit 44b: benchmark records that claimed more than they measured.

* ``bench/session_tail.py``: a mean over no slow frames is null (``n/a``), not 0;
* ``bench/prefetch_fly.LoadLedger``: a frame it could not account is counted, never dropped;
* ``bench.common.machine_info``: ``dirty`` and ``dirty_files`` beside ``git_head``;
* ``bench/bound_fov.py`` / ``bench/seamless_rho.py`` / ``ensure_store``: a half-written store
  (an interrupted ``tile``) is made again, not measured;
* every ``bench/*.py`` writes its JSON through ``bench.common.portable``.
"""

from __future__ import annotations

import ast
import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench import common  # noqa: E402

# --------------------------------------------------------------- 1. session_tail mean_in_slow


def test_session_tail_mean_over_no_slow_frames_is_null():
    from bench.session_tail import spread, spread_line

    v = np.array([0.2, 0.4, 0.3])
    got = spread(v, v >= 1.0)  # no frame of >= 1 ms
    assert got["mean_in_slow"] is None
    assert '"mean_in_slow": null' in json.dumps(got)
    assert spread_line("cpu", got).endswith("mean in >= 1 ms frames n/a")


def test_session_tail_mean_over_slow_frames_is_their_mean():
    from bench.session_tail import spread, spread_line

    v = np.array([0.2, 1.5, 2.5])
    got = spread(v, v >= 1.0)
    assert got["mean_in_slow"] == pytest.approx(2.0)
    assert got["max"] == 2.5
    assert spread_line("cpu", got).endswith("mean in >= 1 ms frames 2.000")


# --------------------------------------------------------------- 2. LoadLedger skipped frames


class _Cache:
    """A LevelCache stand-in: ``blocks()`` raises (a loader changed it) ``fails`` times."""

    def __init__(self, levels: dict, fails: int) -> None:
        self.levels, self.fails = levels, fails

    def blocks(self) -> list:
        if self.fails:
            self.fails -= 1
            raise RuntimeError("dictionary changed size during iteration")
        return list(self.levels)

    def level(self, b) -> int:
        return self.levels[b]


class _Session:
    def __init__(self, cache: _Cache) -> None:
        self.cache = cache


def test_ledger_counts_a_frame_it_could_not_account():
    from bench.prefetch_fly import LoadLedger

    ledger = LoadLedger([10, 20, 40])
    ledger.frame(_Session(_Cache({(0, 0): 1}, fails=10**6)), {(0, 0): (1, 1)})  # never settles
    res = ledger.result()
    assert res["ledger_skipped_frames"] == 1  # before the fix: not in the result at all
    assert res["observed_loaded_bytes"] == 0  # (that frame was not accounted)


def test_ledger_retries_and_accounts_when_the_cache_settles():
    from bench.prefetch_fly import LoadLedger

    ledger = LoadLedger([10, 20, 40])
    ledger.frame(_Session(_Cache({(0, 0): 1}, fails=1)), {(0, 0): (1, 1)})
    res = ledger.result()
    assert res["ledger_skipped_frames"] == 0
    assert res["observed_loaded_bytes"] == 30
    assert res["used_load_bytes"] == 30


# --------------------------------------------------------------- 3. machine_info dirty flag


def _git(repo: Path, *args: str) -> None:
    subprocess.run(
        ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args],
        check=True,
        capture_output=True,
    )


@pytest.fixture
def tiny_repo(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    repo = tmp_path / "repo"
    for rel in ("tiler/a.py", "bench/results/x.json", "docs/d.md"):
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        (repo / rel).write_text("0\n")
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "commit", "-q", "-m", "c")
    return repo


def test_git_dirty_names_changed_code(tiny_repo):
    (tiny_repo / "tiler" / "a.py").write_text("1\n")
    assert common.git_dirty(tiny_repo) == (True, ["tiler/a.py"])


def test_git_dirty_quiet_on_a_clean_tree_and_on_data_docs_untracked(tiny_repo):
    assert common.git_dirty(tiny_repo) == (False, [])
    (tiny_repo / "bench" / "results" / "x.json").write_text("1\n")  # results, not code
    (tiny_repo / "docs" / "d.md").write_text("1\n")  # outside the code folders
    (tiny_repo / "render").mkdir()
    (tiny_repo / "render" / "new.py").write_text("1\n")  # untracked
    assert common.git_dirty(tiny_repo) == (False, [])


def test_git_dirty_unknown_outside_a_repository(tmp_path):
    assert common.git_dirty(tmp_path) == (None, None)


def test_machine_info_records_dirty_beside_the_head():
    info = common.machine_info()
    assert "git_head" in info
    assert info["dirty"] in (True, False, None)
    assert info["dirty"] is None or isinstance(info["dirty_files"], list)


# --------------------------------------------------------------- 4. half-written stores


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """A complete store and a half-written one (a ``tile`` killed after its layout: root
    metadata only, ``complete`` false), as tests/tiler/test_store_v2.py makes it."""
    from demtools import fractal, write_dem

    import tiler.destination as dest
    from tiler.store import Location, open_store
    from tiler.tile import TileOptions, tile

    tmp_path = tmp_path_factory.mktemp("stores")
    done = tmp_path / "done.zarr"
    tile(write_dem(tmp_path / "dem.tif", fractal((40, 40), 13)), done, TileOptions(block_size=17))
    meta = open_store(done).meta
    half = tmp_path / "half.zarr"
    dest.fresh_group(
        Location(half), replace(meta, complete=False, extra=dict(meta.extra, state="layout"))
    )
    assert (half / "zarr.json").exists()
    return done, half


def test_store_complete(stores, tmp_path):
    done, half = stores
    assert common.store_complete(done)
    assert not common.store_complete(half)
    assert not common.store_complete(tmp_path / "absent.zarr")
    (tmp_path / "empty.zarr").mkdir()
    assert not common.store_complete(tmp_path / "empty.zarr")


def test_ensure_store_does_not_pass_a_half_written_store(stores):
    done, half = stores
    assert common.ensure_store(done)  # (not a store it makes: only checked)
    assert not common.ensure_store(half)  # before the fix: True (zarr.json exists)


def _prepare_calls(module: str, stores, tmp_path, monkeypatch, kind: str) -> list[tuple]:
    """The CLI calls ``bench/<module>.py``'s ``prepare`` makes with a ``kind`` store in each
    place it looks (the calls recorded, not run)."""
    import importlib

    mod = importlib.import_module(f"bench.{module}")
    done, half = stores
    work = tmp_path / "work"
    work.mkdir()
    names = {"bound_fov": "s1025.zarr", "seamless_rho": "s2049.zarr"}
    for name in (names[module], "n44w072_auto.zarr"):
        shutil.copytree(done if kind == "done" else half, work / name)
    calls: list[tuple] = []
    monkeypatch.setattr(mod, "_cli", lambda *a: calls.append(a))
    if module == "bound_fov":
        got = mod.prepare(work)
    else:
        monkeypatch.setattr(mod, "RWORK", work)
        got = mod.prepare()
    assert set(got.values()) == {work / names[module], work / "n44w072_auto.zarr"}
    return calls


@pytest.mark.parametrize("module", ["bound_fov", "seamless_rho"])
def test_prepare_makes_a_half_written_store_again(module, stores, tmp_path, monkeypatch):
    calls = _prepare_calls(module, stores, tmp_path, monkeypatch, "half")
    tiles = [c for c in calls if c[0] == "tile"]
    assert [c[0] for c in calls] == ["synth", "tile", "tile"], calls  # before: [] (reused)
    assert all("--overwrite" in c for c in tiles), tiles


@pytest.mark.parametrize("module", ["bound_fov", "seamless_rho"])
def test_prepare_reuses_complete_stores(module, stores, tmp_path, monkeypatch):
    assert _prepare_calls(module, stores, tmp_path, monkeypatch, "done") == []


# --------------------------------------------------------------- 5. JSON through portable()

#: json.dump(s) calls in bench/*.py whose text goes to no results file, or holds no path:
#: (file, text on the call's line) -> why
EXEMPT = {
    ("tiling.py", "stamp.write_text(json.dumps("): "the synthetic DEM's stamp in bench/work: "
    "size, seed, dtype and writer, no path",
    ("tiling_report.py", '"detail": json.dumps('): "a field of the targets, which "
    "bench/tiling.py writes with tiling_reads.write_result (portable(doc), text included)",
    ("sources.py", "json.dumps([srcs, str(dst), workers, dst_crs])"): "a child's argv",
    ("tiling_child.py", '"--child", json.dumps(task)'): "a child's argv",
}


def _is_portable_call(node: ast.AST) -> bool:
    return (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name | ast.Attribute)
        and (node.func.id if isinstance(node.func, ast.Name) else node.func.attr) == "portable"
    )


def unportable_json(text: str) -> list[int]:
    """Lines of ``text`` (a Python script) with a ``json.dump``/``json.dumps`` whose document
    is neither ``portable(...)`` nor a name only ever assigned ``portable(...)``; a call
    printed to stdout (a child's answer to its parent) is not a file write."""
    tree = ast.parse(text)
    parent = {c: n for n in ast.walk(tree) for c in ast.iter_child_nodes(n)}
    assigned: dict[str, list[bool]] = {}
    for n in ast.walk(tree):
        targets = n.targets if isinstance(n, ast.Assign) else []
        if isinstance(n, ast.AnnAssign | ast.AugAssign):
            targets = [n.target]
        for t in targets:
            if isinstance(t, ast.Name):
                ok = isinstance(n, ast.Assign | ast.AnnAssign) and _is_portable_call(n.value)
                assigned.setdefault(t.id, []).append(ok)
    bad = []
    for n in ast.walk(tree):
        if not (
            isinstance(n, ast.Call)
            and isinstance(n.func, ast.Attribute)
            and n.func.attr in ("dump", "dumps")
            and isinstance(n.func.value, ast.Name)
            and n.func.value.id == "json"
        ):
            continue
        up = parent.get(n)
        if isinstance(up, ast.Call) and isinstance(up.func, ast.Name) and up.func.id == "print":
            continue
        doc = n.args[0] if n.args else None
        if _is_portable_call(doc):
            continue
        if isinstance(doc, ast.Name) and all(assigned.get(doc.id, [False])):
            continue
        bad.append(n.lineno)
    return bad


BAD_SCRIPT = """
import json
from bench.common import RESULTS, WORK, machine_info
doc = {"machine": machine_info(), "store": str(WORK / "s.zarr")}
(RESULTS / "x.json").write_text(json.dumps(doc, indent=1))
with open(RESULTS / "y.json", "w") as f:
    json.dump({"rows": []}, f)
"""

GOOD_SCRIPT = """
import json
from bench.common import RESULTS, WORK, portable
doc = {"store": str(WORK / "s.zarr")}
(RESULTS / "x.json").write_text(json.dumps(portable(doc), indent=1))
out = portable(doc)
(RESULTS / "y.json").write_text(json.dumps(out) + "\\n")
print(json.dumps({"child": 1}))
"""


def test_the_static_check_flags_json_written_without_portable():
    assert unportable_json(BAD_SCRIPT) == [5, 7]
    # a name also assigned something else is not known to be portable
    assert unportable_json(GOOD_SCRIPT + "out = {}\n") == [7]


def test_the_static_check_passes_portable_documents_and_child_output():
    assert unportable_json(GOOD_SCRIPT) == []


def test_every_bench_script_writes_json_through_portable():
    bad, used = [], set()
    for path in sorted((REPO / "bench").glob("*.py")):
        lines = path.read_text().splitlines()
        for ln in unportable_json(path.read_text()):
            key = next((k for k in EXEMPT if k[0] == path.name and k[1] in lines[ln - 1]), None)
            if key is None:
                bad.append(f"bench/{path.name}:{ln}: {lines[ln - 1].strip()}")
            used.add(key)
    assert not bad, "JSON written without bench.common.portable():\n" + "\n".join(bad)
    assert set(EXEMPT) <= used, f"stale exemptions: {set(EXEMPT) - used}"
