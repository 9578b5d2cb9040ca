"""The longer kill/resume cases (``@pytest.mark.long_series``) leave `make test` for
`make reliability`: deselected without TERRASTREAM_RELIABILITY_LONG=1, run with it, and the
reliability target selects them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FILE = "tests/cli/test_cli_sigterm.py"  # two of its six tests are long_series


def _collected(long: bool) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k != "TERRASTREAM_RELIABILITY_LONG"}
    if long:
        env["TERRASTREAM_RELIABILITY_LONG"] = "1"
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-n", "0", "--collect-only",
         "-q", FILE],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    return [line for line in r.stdout.splitlines() if "::" in line]


def test_long_series_are_deselected_from_the_suite_and_run_by_make_reliability():
    short, full = _collected(False), _collected(True)
    left = sorted(set(full) - set(short))
    # the control: with the variable set they are collected, so the difference is the marker's
    assert len(full) == len(short) + 2 and len(left) == 2, (short, full)
    assert any("sigint-ignored" in n for n in left)
    assert any("worker_processes" in n for n in left)
    assert any(n.endswith("[sigint]") for n in short)  # the short sibling stays in the suite


def test_the_reliability_target_runs_the_long_series():
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    target = text.split("\nreliability:", 1)[1].split("\n\n", 1)[0]
    assert "TERRASTREAM_RELIABILITY_LONG=1" in target and "-m long_series tests" in target
