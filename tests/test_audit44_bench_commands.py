"""Every ``python bench/X.py`` command BENCHMARKS.md quotes names a script that exists and only
options that script defines (audit 44): a renamed or dropped option would make a quoted command
fail as written."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: a command in backticks on one line, or a line of a ```sh block
_INLINE = re.compile(r"`python (bench/\w+\.py)([^`\n]*)`")
_FENCE = re.compile(r"```sh\n(.*?)```", re.S)
_FLAG = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")


def quoted_commands(text: str) -> list[tuple[str, list[str]]]:
    """``(script, options)`` of each command quoted in ``text`` (comments after ``#`` left
    out: they list options in brackets that are checked too)."""
    out = []
    for script, rest in _INLINE.findall(text):
        out.append((script, _FLAG.findall(rest)))
    for block in _FENCE.findall(text):
        for line in block.splitlines():
            m = re.match(r"\s*python (bench/\w+\.py)(.*)", line)
            if m:
                out.append((m.group(1), _FLAG.findall(m.group(2))))
    return out


def problems(text: str, repo: Path = REPO) -> list[str]:
    """The quoted commands whose script is missing or whose options it does not define."""
    bad = []
    for script, flags in quoted_commands(text):
        path = repo / script
        if not path.exists():
            bad.append(f"{script}: no such script")
            continue
        src = path.read_text()
        bad += [f"{script} {f}: not an option" for f in flags if f'"{f}"' not in src]
    return sorted(set(bad))


def test_quoted_benchmark_commands_exist():
    text = (REPO / "BENCHMARKS.md").read_text()
    assert len(quoted_commands(text)) > 40  # (the parser finds the commands)
    assert problems(text) == []


def test_the_check_fires_on_a_wrong_command():
    text = (
        "Run `python bench/tiling.py --sizes 4097 --no-such-option` and\n"
        "```sh\npython bench/no_such_bench.py --frames 3\n```\n"
    )
    assert problems(text) == [
        "bench/no_such_bench.py: no such script",
        "bench/tiling.py --no-such-option: not an option",
    ]
