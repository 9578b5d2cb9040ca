"""README command lines name what the CLI has: every ``terrastream`` command line of a ```sh
block of README.md parses with the real CLI (subcommand, options and option values; nothing is
run), every ``terrastream <sub> ...`` synopsis in the prose names options that ``<sub>`` has
(and its ``a|b|c`` alternatives are values the option takes), every long option the README
names anywhere belongs to a ``terrastream`` command or to one of the ``bench/`` scripts, and
the defaults the prose states are the CLI's.

Parsing uses the click command of :data:`cli.main.app` (``make_context``: options, types and
registries are checked, the command body is not invoked), so the whole module runs in ~1 s.
Each check has a positive control on a synthetic README with a made-up option.
"""

from __future__ import annotations

import re
import shlex
from functools import cache
from pathlib import Path
from typing import Any

import pytest
import typer

from cli.main import app
from cli.options import LODS, parse_size, parse_taus

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()

SH_FENCE = re.compile(r"^```(?:sh|bash|shell|console)[^\n]*\n(.*?)^```\s*$", re.S | re.M)
ANY_FENCE = re.compile(r"^```[^\n]*\n.*?^```\s*$", re.S | re.M)
CODE_SPAN = re.compile(r"`([^`]+)`")
LONG_OPT = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
#: ``--opt a|b|c`` in a synopsis: the alternatives the option is said to take
ALTERNATIVES = re.compile(r"(--[a-z][a-z0-9-]*)[ =]([\w.:-]+(?:\|[\w.:-]+)+)")
#: ``terrastream``'s own options, given before the subcommand
ROOT_FLAGS = {"-q", "--quiet", "-v", "-vv", "-vvv", "--verbose", "--version", "--help"}


@cache
def commands() -> dict[str, Any]:
    """The click commands of ``terrastream``, by name."""
    return dict(typer.main.get_command(app).commands)


def options_of(cmd: Any) -> set[str]:
    """Every option string ``cmd`` takes (``--out``, ``-o``, ``--help``...)."""
    names = {"--help"}
    for p in cmd.params:
        if p.param_type_name == "option":
            names.update(p.opts, p.secondary_opts)
    return names


def cli_options() -> set[str]:
    """Every option of every command, and the group's own."""
    names = set(ROOT_FLAGS)
    for cmd in commands().values():
        names |= options_of(cmd)
    return names


def bench_options() -> set[str]:
    """Long options the ``bench/`` scripts define (``"--locks"`` in their argparse calls)."""
    names: set[str] = set()
    for f in sorted((ROOT / "bench").glob("*.py")):
        names.update(re.findall(r"""["'](--[a-z][a-z0-9-]*)["']""", f.read_text()))
    return names


def sh_command_lines(text: str) -> list[tuple[int, str]]:
    """``(line number, command)`` of every line of a ```sh block that runs ``terrastream``
    (backslash continuations joined, ``# comments`` dropped)."""
    found = []
    for m in SH_FENCE.finditer(text):
        first = text.count("\n", 0, m.start()) + 2
        logical, start = "", None
        for i, raw in enumerate(m.group(1).split("\n")):
            start = first + i if start is None else start
            if raw.rstrip().endswith("\\"):
                logical += raw.rstrip()[:-1] + " "
                continue
            line = strip_comment(logical + raw).strip()
            if line and "terrastream" in shlex.split(line):
                found.append((start, line))
            logical, start = "", None
    return found


def strip_comment(line: str) -> str:
    """``line`` without a trailing ``# comment`` (shell rules: a ``#`` starting a word)."""
    lex = shlex.shlex(line, posix=True, punctuation_chars=False)
    lex.whitespace_split = True
    lex.commenters = "#"
    words = list(lex)
    # rebuild with quoting so shlex.split gives the same words back
    return " ".join(shlex.quote(w) for w in words)


def split_command(line: str) -> tuple[list[str], str | None, list[str]]:
    """``(root options, subcommand, its arguments)`` of a ``terrastream`` command line
    (``xvfb-run -a terrastream view ...``: what runs before it is dropped)."""
    words = shlex.split(line)
    words = words[words.index("terrastream") + 1 :]
    root: list[str] = []
    while words and words[0].startswith("-"):
        root.append(words.pop(0))
    return root, (words[0] if words else None), words[1:]


def message(exc: Exception) -> str:
    """A click usage error's message (``No such option: --blok-size``), else ``str(exc)``."""
    fmt = getattr(exc, "format_message", None)
    return fmt() if fmt else str(exc)


def check_command_line(line: str) -> list[str]:
    """What is wrong with a README command line: an unknown subcommand, option or option
    value, a bad ``--size``/``--taus``/``--lods``. Empty when the CLI accepts it."""
    root, sub, args = split_command(line)
    problems = [f"unknown option of terrastream: {o}" for o in root if o not in ROOT_FLAGS]
    if sub is None:
        return problems if root else [*problems, "no subcommand"]
    cmd = commands().get(sub)
    if cmd is None:
        return [*problems, f"unknown subcommand {sub!r} (have: {', '.join(sorted(commands()))})"]
    if "--help" in args:
        return problems
    try:
        ctx = cmd.make_context(sub, list(args))
    except Exception as exc:  # noqa: BLE001 - click's usage errors: the message says which
        return [*problems, f"terrastream {sub}: {type(exc).__name__}: {message(exc)}"]
    params = ctx.params
    try:
        if isinstance(params.get("size"), str):
            parse_size(params["size"])
        if isinstance(params.get("taus"), str):
            parse_taus(params["taus"])
    except Exception as exc:  # noqa: BLE001
        problems.append(f"terrastream {sub}: {exc}")
    for name in (params.get("lods") or "").split(","):
        if name.strip() and name.strip() not in LODS.names:
            problems.append(f"terrastream {sub}: --lods names unknown strategy {name.strip()!r}")
    return problems


def prose(text: str) -> str:
    """``text`` without its fenced blocks."""
    return ANY_FENCE.sub("", text)


def synopses(text: str) -> list[str]:
    """Inline code spans of the prose that show a ``terrastream`` command line
    (``terrastream verify STORE [--source SRC] [--json]``; ``render -o``, a subcommand and
    its option, counts as ``terrastream render -o``), whitespace collapsed."""
    found = []
    for span in CODE_SPAN.findall(prose(text)):
        words = span.split()
        if words[:1] == ["terrastream"]:
            found.append(" ".join(words))
        elif len(words) > 1 and words[0] in commands() and words[1].startswith("-"):
            found.append(" ".join(["terrastream", *words]))
    return found


def placeholder_arguments(cmd: Any) -> list[str]:
    """Values for ``cmd``'s required arguments (two for ``SRC... DST``), so that an option can
    be parsed alone."""
    args: list[str] = []
    for p in cmd.params:
        if p.param_type_name == "argument" and p.required:
            args += ["arg.tif", "arg.zarr"] if p.nargs == -1 else ["arg.zarr"] * p.nargs
    return args


def check_synopsis(span: str) -> list[str]:
    """Unknown subcommand or options of a prose synopsis, and ``--opt a|b`` alternatives the
    option refuses (parsing is not attempted: synopses hold placeholders and brackets)."""
    words = span.split()[1:]
    problems = []
    while words and words[0].startswith("-"):
        if words[0] not in ROOT_FLAGS:
            problems.append(f"unknown option of terrastream: {words[0]} (`{span}`)")
        words.pop(0)
    if not words or not re.fullmatch(r"[a-z]+", words[0]):
        return problems
    sub = words[0]
    cmd = commands().get(sub)
    if cmd is None:
        return [*problems, f"unknown subcommand {sub!r} in `{span}`"]
    have = options_of(cmd)
    named = LONG_OPT.findall(span) + [w for w in words if re.fullmatch(r"-[A-Za-z]", w)]
    problems += [f"terrastream {sub} has no option {o} (`{span}`)" for o in named if o not in have]
    for opt, alts in ALTERNATIVES.findall(span):
        if opt not in have:
            continue
        for value in alts.split("|"):
            try:
                cmd.make_context(sub, [*placeholder_arguments(cmd), opt, value])
            except Exception as exc:  # noqa: BLE001 - click's usage errors
                problems.append(f"terrastream {sub} {opt} refuses {value!r}: {message(exc)}")
    return problems


def unknown_options(text: str, known: set[str]) -> list[str]:
    """Long options named anywhere in ``text`` that no command or bench script has."""
    return sorted({o for o in LONG_OPT.findall(text) if o not in known})


# -- the README ------------------------------------------------------------------------------

LINES = sh_command_lines(README)


def test_the_readme_has_command_lines():
    assert len(LINES) >= 10, LINES
    named = {split_command(line)[1] for _, line in LINES}
    assert {"synth", "tile", "info", "verify", "export", "stream"} <= named, named


@pytest.mark.parametrize(("line", "command"), LINES, ids=[f"README.md:{n}" for n, _ in LINES])
def test_readme_command_line_parses(line, command):
    assert check_command_line(command) == [], f"README.md line {line}: {command}"


def test_every_subcommand_is_shown():
    """Each command of the CLI appears in a README command line or synopsis."""
    shown = {split_command(c)[1] for _, c in LINES}
    shown |= {s.split()[1] for s in synopses(README) if len(s.split()) > 1}
    assert set(commands()) - shown == set()


def test_readme_synopses_name_real_options():
    spans = synopses(README)
    assert any(s.startswith("terrastream tile SRC") for s in spans), spans
    problems = [p for s in spans for p in check_synopsis(s)]
    assert problems == []


def test_every_option_named_in_the_readme_exists():
    known = cli_options() | bench_options()
    assert unknown_options(README, known) == []


# -- the README's stated defaults ------------------------------------------------------------

#: (what the README says, as a regex capturing the default; command; option)
STATED_DEFAULTS = [
    (r"`\(2\^k\+1\)²` samples \(default (\d+)", "tile", None),  # tile's DEFAULT_BLOCK_SIZE
    (r"`--resampling` \(default (\w+)\)", "tile", "--resampling"),
    (r"\(`--retries`, default (\d+)\)", "tile", "--retries"),
    (r"Compression is blosc zstd (\d+)", "tile", "--clevel"),
    (r"`--cell-size` metres per sample\s+\(default (\d+)", "synth", "--cell-size"),
    (r"\(every N-th with `--every N`; (\d+), the default", "stream", "--every"),
    (r"`--culling (\w+)`, Qiu's\s+triangle, the default", "stream", "--culling"),
    (r"`--repeats` draws per τ \(default (\d+)\)", "tradeoff", "--repeats"),
    (r"`flythrough --every N` saves every N-th frame's PNG\s+\(default (\d+)", "flythrough",
     "--every"),
    (r"\(1\.\.7, default (\d+)\)", "render", "--patch-log2"),
    (r"`--lod (\w+)` \(the default\)", "render", "--lod"),
    (r"`--nodata-rule (\w+)`, the default", "render", "--nodata-rule"),
]  # fmt: skip


def cli_default(sub: str, opt: str | None) -> str:
    """The default of ``opt`` on ``sub`` as text (enum values by their value)."""
    if opt is None:
        from cli.commands.tile import DEFAULT_BLOCK_SIZE

        return str(DEFAULT_BLOCK_SIZE)
    param = next(p for p in commands()[sub].params if opt in p.opts)
    value = getattr(param.default, "value", param.default)
    return f"{value:g}" if isinstance(value, float) else str(value)


@pytest.mark.parametrize(("pattern", "sub", "opt"), STATED_DEFAULTS)
def test_stated_default_is_the_clis(pattern, sub, opt):
    m = re.search(pattern, README)
    assert m, f"README.md no longer says {pattern!r}: update STATED_DEFAULTS in this test"
    assert m[1] == cli_default(sub, opt), f"README states {opt or 'block size'} default {m[1]}"


def test_shared_defaults_agree_across_commands():
    """The README states one default for options several commands share."""
    for opt in ("--patch-log2", "--lod", "--nodata-rule", "--metric", "--fov"):
        defaults = {
            sub: cli_default(sub, opt) for sub, cmd in commands().items() if opt in options_of(cmd)
        }
        assert len(set(defaults.values())) == 1, (opt, defaults)


# -- positive controls -----------------------------------------------------------------------

FAKE = """intro
```sh
terrastream synth demo.tif --size 257 --seed 1   # fine
terrastream tile demo.tif demo.zarr --blok-size 65
terrastream render demo.zarr --lod qiuu -o x.png
terrastream renderr demo.zarr
xvfb-run -a terrastream view demo.zarr --frames 6 \\
    --screen-shot v.png
terrastream -q compare demo.zarr --lods qiu,nope --size 64by64
```
```python
terrastream = 1  # not a command line
```
A synopsis: `terrastream export STORE OUT.tif [--level L] [--fromat cog|gtiff]` and
`render -o`, `render -x`, `flythrough --every N`, `tradeoff --evry N`,
`terrastream stream STORE [--metric qiu|fast]`, `terrastream --verbos tile`, `terrastream
info STORE [--json]`; prose naming `--no-such-flag` and `--locks` (a bench option).
"""


def test_control_the_extractor_finds_every_command_line():
    got = sh_command_lines(FAKE)
    assert [n for n, _ in got] == [3, 4, 5, 6, 7, 9]
    assert shlex.split(got[4][1])[-2:] == ["--screen-shot", "v.png"]  # continuation joined
    assert "#" not in got[0][1]


def test_control_bad_command_lines_are_flagged():
    found = {n: check_command_line(c) for n, c in sh_command_lines(FAKE)}
    assert found[3] == []
    assert "--blok-size" in " ".join(found[4])
    assert "qiuu" in " ".join(found[5])
    assert "unknown subcommand 'renderr'" in " ".join(found[6])
    assert "--screen-shot" in " ".join(found[7])
    assert "64by64" in " ".join(found[9]) and "'nope'" in " ".join(found[9])


def test_control_bad_synopses_are_flagged():
    problems = " ".join(p for s in synopses(FAKE) for p in check_synopsis(s))
    assert "terrastream export has no option --fromat" in problems
    assert "--metric refuses 'fast'" in problems
    assert "--verbos" in problems
    assert "terrastream render has no option -x" in problems
    assert "terrastream tradeoff has no option --evry" in problems
    assert "info" not in problems and "--json" not in problems
    assert "-o" not in problems and "--every" not in problems


def test_control_an_unknown_option_in_prose_is_flagged():
    known = cli_options() | bench_options()
    assert "--locks" in known
    assert unknown_options(FAKE, known) == [
        "--blok-size",
        "--evry",
        "--fromat",
        "--no-such-flag",
        "--screen-shot",
        "--verbos",
    ]


def test_control_a_wrong_stated_default_is_flagged():
    assert cli_default("tradeoff", "--repeats") == "3"
    assert cli_default("tile", "--resampling") == "bilinear"
    assert cli_default("synth", "--cell-size") == "30"
    m = re.search(STATED_DEFAULTS[7][0], "the fastest of `--repeats` draws per τ (default 5)")
    assert m and m[1] != cli_default("tradeoff", "--repeats")
