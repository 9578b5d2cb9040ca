"""Benchmark results name no machine's absolute paths (bench.common.portable)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.common import portable  # noqa: E402

#: an absolute path under a directory that only exists on some machine
MACHINE_PATH = re.compile(r"(?<![\w.$])/(?:work|home|tmp|root|Users|mnt|var/folders)/")


def _hits(text: str) -> list[str]:
    return [m.group(0) for m in MACHINE_PATH.finditer(text)]


def test_portable_rewrites_the_checkout_inside_text():
    raw = {"store": str(REPO / "bench" / "work" / "s.zarr"), "profile": f"x {REPO}/tiler/a.py:3"}
    out = portable(raw)
    assert out == {"store": "./bench/work/s.zarr", "profile": "x ./tiler/a.py:3"}
    assert str(REPO) in raw["profile"]  # the control: without portable the path is there


def test_the_detector_fires_on_a_machine_path():
    assert _hits('{"path": "/tmp/kg/lc/x.json"}') == ["/tmp/"]
    assert _hits('{"path": "/home/u/x"}') == ["/home/"]
    assert _hits('{"path": "./bench/work/x", "s": "bench/work/y"}') == []


def test_committed_results_name_no_machine_path():
    bad = {}
    for p in sorted((REPO / "bench" / "results").rglob("*")):
        if p.suffix in {".json", ".txt", ".md"}:
            hits = _hits(p.read_text(errors="replace"))
            if hits:
                bad[str(p.relative_to(REPO))] = hits[:3]
    assert not bad, f"machine paths in benchmark results (write them through portable): {bad}"
