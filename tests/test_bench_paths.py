"""Benchmark results name no machine's absolute paths (bench.common.portable)."""

from __future__ import annotations

import json
import re
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.common import portable  # noqa: E402

#: an absolute path under a directory that only exists on some machine (the usual ones and this
#: machine's own home and temporary folders)
_ROOTS = ["work", "home", "tmp", "root", "Users", "mnt", "var/folders"] + [
    re.escape(str(p).strip("/")) for p in (Path.home(), Path(tempfile.gettempdir()))
]
MACHINE_PATH = re.compile(r"(?<![\w.$])/(?:" + "|".join(_ROOTS) + ")/")


def _hits(text: str) -> list[str]:
    return [m.group(0) for m in MACHINE_PATH.finditer(text)]


def test_portable_rewrites_the_checkout_inside_text():
    raw = {"store": str(REPO / "bench" / "work" / "s.zarr"), "profile": f"x {REPO}/tiler/a.py:3"}
    out = portable(raw)
    assert out == {"store": "./bench/work/s.zarr", "profile": "x ./tiler/a.py:3"}
    assert str(REPO) in raw["profile"]  # the control: without portable the path is there


def test_the_detector_fires_on_a_machine_path():
    # this machine's own temporary and home folders, as a benchmark could have written them
    for folder in (Path(tempfile.gettempdir()), Path.home()):
        text = json.dumps({"path": str(folder / "run" / "x.json")})
        assert _hits(text), f"the detector misses {folder}"
    assert _hits(json.dumps({"path": "./bench/work/x", "s": "bench/work/y"})) == []


def test_committed_results_name_no_machine_path():
    bad = {}
    for p in sorted((REPO / "bench" / "results").rglob("*")):
        if p.suffix in {".json", ".txt", ".md"}:
            hits = _hits(p.read_text(errors="replace"))
            if hits:
                bad[str(p.relative_to(REPO))] = hits[:3]
    assert not bad, f"machine paths in benchmark results (write them through portable): {bad}"
