"""What every command shares: logging, exit statuses, error reporting, the help's look.

Exit statuses (rio's convention), also printed at the end of every command's ``--help``:

* 0 — success;
* 1 — the command started and failed (an I/O error, a damaged store, a library failure);
* 2 — usage: a bad option or argument value, a missing input, an output that exists without
  ``--overwrite``, a missing capability (no display / OpenGL);
* 130 — interrupted (Ctrl-C); rerunning the same ``tile`` resumes its store;
* 143 — terminated (SIGTERM), handled as a Ctrl-C: outputs cleaned up, ``tile`` resumes.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import click
import typer
from typer.core import TyperArgument, TyperCommand, TyperGroup, TyperOption

from tiler.interrupt import defer_active

EXIT_RUNTIME = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
#: 128 + SIGTERM: a SIGTERM is handled as a Ctrl-C (:func:`route_sigterm`)
EXIT_TERMINATED = 143
#: kept for code written before the 1/2 split: usage errors
EXIT_USER_ERROR = EXIT_USAGE

EXIT_STATUS_HELP = (
    "Exit status: 0 success; 1 the command failed while running (I/O error, damaged store "
    "or unreadable blocks, library failure); 2 usage error (bad value, missing input, existing "
    "output without --overwrite, a view or path that shows no terrain, no display or OpenGL); "
    "130 interrupted (a rerun of `tile` resumes); 143 terminated (SIGTERM), as 130."
)
INTERRUPTED_MESSAGE = "interrupted"
#: ``tile``'s: its store resumes (other commands start again: nothing of theirs resumes)
RESUME_MESSAGE = "interrupted; rerun the same command to resume"

#: the loggers -v/-vv raise (every other library stays at WARNING)
OWN_LOGGERS = ("tiler", "streamer", "render", "cli", "terrastream", "bench")


class UsageError(ValueError):
    """A bad value found while a command runs: printed as ``error: HINT: message``, exit 2."""

    def __init__(self, message: str, hint: str | None = None) -> None:
        super().__init__(f"{hint}: {message}" if hint else message)


class _State:
    verbose = 0
    quiet = False
    #: a SIGTERM arrived (:func:`route_sigterm`): the interrupt is reported as termination
    terminated = False


state = _State()
#: the CLI's names for library parameters an error message may name (render.errors.CAMERA_PARAMS,
#: the ``params`` of tiler.errors.NamedParams)
FLAG_NAMES = {
    "position": "--camera",
    "look_at": "--look-at",
    "yaw": "--yaw",
    "pitch": "--pitch",
    "level_param": "--level",
    "overwrite": "--overwrite",
    "repair": "--repair",
    "precision": "--precision",
    "budget_mb": "--budget-mb",
    "tau": "--tau",
    "resolution": "--resolution",
    "dst_crs": "--dst-crs",
    "dst_crs_auto": "--dst-crs auto",
    "retile": "`terrastream tile {src} DST --dst-crs auto`",
    "more_time": "",  # a session's wait timeouts are not options of the commands
}


def setup_logging(verbose: int, quiet: bool) -> None:
    """``-q``: errors only; default: warnings; ``-v``/``-vv``: terrastream's INFO/DEBUG.

    Only terrastream's own loggers (:data:`OWN_LOGGERS`) are raised: zarr, numcodecs, fsspec,
    rasterio, PIL ... stay at WARNING whatever ``-v`` says.
    """
    state.verbose, state.quiet = verbose, quiet
    base = logging.ERROR if quiet else logging.WARNING
    own = (
        logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    )
    logging.basicConfig(level=base, format="%(levelname)s %(name)s: %(message)s", force=True)
    for name in OWN_LOGGERS:
        logging.getLogger(name).setLevel(own)
    # dask's distributed sets its loggers to INFO when imported (its config), which printed ~30
    # lines per `tile --scheduler dask`, under -q too; its config from the environment is read
    # then, and by the worker processes (a user's own setting wins)
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", logging.getLevelName(base).lower())


def _library_errors() -> tuple[type[BaseException], ...]:
    """Root error classes of the packages (their messages are meant for the user)."""
    import importlib

    out: list[type[BaseException]] = []
    for mod, name in (
        ("tiler.errors", "TilerError"),
        ("streamer.errors", "StreamerError"),
        ("render.errors", "RenderError"),
    ):
        try:
            out.append(getattr(importlib.import_module(mod), name))
        except (ImportError, AttributeError):
            continue
    return tuple(out)


known_errors = _library_errors

#: built-in types that mean "the input is wrong" (the packages' leaves inherit them)
_USAGE_TYPES: tuple[type[BaseException], ...] = (
    ValueError,
    FileNotFoundError,
    FileExistsError,
    NotADirectoryError,
    IsADirectoryError,
)
#: class names of "this machine cannot do that" errors, also usage (exit 2)
_CAPABILITY_ERRORS = ("GLUnavailableError", "ViewerUnavailableError")


def exit_status(exc: BaseException) -> int:
    """1 or 2 for an exception a command raised (see the module docstring)."""
    if isinstance(exc, _USAGE_TYPES) or type(exc).__name__ in _CAPABILITY_ERRORS:
        return EXIT_USAGE
    return EXIT_RUNTIME


_NUMPY_REPR = re.compile(r"np\.(?:float|int|uint|bool_)\w*\(([^()]*)\)")


_PREVIOUS = re.compile(r"\s*See previous exception for details\.?", re.I)
_REMOTE_LINE = re.compile(r"^[\w.]+(?:Error|Exception): (.+)$", re.M)


def root_cause(exc: BaseException) -> str:
    """The message of the first cause of ``exc`` (through a worker process's traceback too)."""
    seen, e, root = 0, exc.__cause__, ""
    while e is not None and seen < 20:
        if type(e).__name__ == "_RemoteTraceback":  # concurrent.futures.process
            lines = [m for m in _REMOTE_LINE.findall(str(e)) if not _PREVIOUS.search(m)]
            return lines[0] if lines else root
        root, e, seen = str(e), e.__cause__, seen + 1
    return root


def one_line(exc: BaseException) -> str:
    """The error as one line: the message of a library error, ``Type: message`` otherwise;
    numpy scalar reprs (``np.float64(1.5)``) shown as their values; a message that only says
    "see previous exception" (rasterio) gets the first cause's message instead."""
    message = getattr(exc, "message", None)  # errors naming library parameters (render)
    raw = message(FLAG_NAMES) if callable(message) else str(exc)
    if _PREVIOUS.search(raw) and (cause := root_cause(exc)):
        raw = _PREVIOUS.sub("", raw).rstrip(". ") + ": " + cause
    text = _NUMPY_REPR.sub(r"\1", " ".join(raw.split())) or type(exc).__name__
    if isinstance(exc, (*_library_errors(), UsageError)):
        return text
    name = type(exc).__name__
    if name.islower():  # struct.error, socket.error...: not "error: error: ..."
        name = f"{type(exc).__module__}.{name}"
    return f"{name}: {text}"


#: Typer's (vendored click's) usage errors and exits, and click's own: handled by the runner
_PASS_THROUGH = (
    typer.TyperException,
    typer.Exit,
    typer.Abort,
    click.exceptions.ClickException,
    click.exceptions.Exit,
    click.exceptions.Abort,
)


def interrupted_exit() -> int:
    """The exit status of an interrupted command: 143 after a SIGTERM, else 130."""
    return EXIT_TERMINATED if state.terminated else EXIT_INTERRUPTED


def interrupted_text(resumable: bool = False, what: str = "") -> str:
    """The word for an interrupt (``interrupted``, or ``terminated (SIGTERM)``), then ``what``,
    then the resume advice when ``resumable``."""
    word = "terminated (SIGTERM)" if state.terminated else "interrupted"
    tail = "; rerun the same command to resume" if resumable else ""
    return f"{word}{what}{tail}"


def _on_sigterm(signum: int, frame: Any) -> None:
    """SIGTERM handled as SIGINT by SIGINT's current handler (Python's, which raises
    ``KeyboardInterrupt``, or :class:`tiler.interrupt.DeferredInterrupt`'s flag), so the
    command cleans up as after a Ctrl-C; with SIGINT ignored, as that handler would."""
    if os.getpid() != _SIGTERM_PID:  # (a forked child: die as it would have)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)
        return
    state.terminated = True
    handler = signal.getsignal(signal.SIGINT)
    if callable(handler):
        handler(signal.SIGINT, frame)
    elif not defer_active():  # SIGINT ignored (`cmd &` from a script): no handler to borrow
        raise KeyboardInterrupt


_SIGTERM_PID = 0


def route_sigterm() -> None:
    """Handle SIGTERM as a Ctrl-C from now on (main thread of the ``terrastream`` process only:
    a SIGTERM used to leave ``export``'s and ``synth``'s temporary files, and cut
    ``flythrough``'s frames.csv mid-line)."""
    global _SIGTERM_PID
    if threading.current_thread() is not threading.main_thread():
        return
    _SIGTERM_PID = os.getpid()
    signal.signal(signal.SIGTERM, _on_sigterm)


@contextmanager
def fail_on_errors(*, resumable: bool = False) -> Iterator[None]:
    """Any error → one ``error: …`` line on stderr and exit 1 or 2; Ctrl-C → exit 130 (with
    "rerun the same command to resume" when the command is ``resumable``).

    The traceback is printed too with ``-vv``. Click's own usage errors pass through.
    """
    try:
        yield
    except _PASS_THROUGH:
        raise
    except KeyboardInterrupt:
        typer.echo(interrupted_text(resumable), err=True)
        raise typer.Exit(interrupted_exit()) from None
    except BrokenPipeError:
        # the reader of our output went away (`| head`): exit 1 without a message, as other
        # tools do; stdout goes to /dev/null so the interpreter's last flush does not fail too
        with contextlib.suppress(OSError, ValueError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        raise typer.Exit(EXIT_RUNTIME) from None
    except Exception as exc:  # noqa: BLE001 - the CLI's last line: one message, no traceback
        if state.verbose >= 2:
            traceback.print_exception(exc, file=sys.stderr)
        expected = isinstance(exc, (*_library_errors(), UsageError))
        hint = "" if state.verbose >= 2 or expected else " (-vv: traceback)"
        typer.echo(f"error: {one_line(exc)}{hint}", err=True)
        raise typer.Exit(exit_status(exc)) from exc


class _Argument(TyperArgument):
    """Arguments shown as ``SRC`` in the usage line and the help table (not ``{src} <str>``)."""

    @property
    def display_name_raw(self) -> str:
        return self.metavar or (self.name or "").upper()

    def _usage_display_name(self) -> str:
        name = self.display_name_raw
        name = name if self.required else f"[{name}]"
        return name + ("..." if self.nargs != 1 and "..." not in name else "")

    def display_type_rich(self, ctx: click.Context) -> str | None:
        return None


def _readable(params: list[click.Parameter]) -> None:
    """Readable metavars: ``SRC`` for arguments, nothing after flags and count flags."""
    for p in params:
        if isinstance(p, TyperArgument) and not isinstance(p, _Argument):
            p.__class__ = _Argument
        elif isinstance(p, TyperOption) and (p.is_flag or p.count) and p.metavar is None:
            p.metavar = ""
            if p.count:
                p.show_default = False


def usage_line(e: Exception) -> str:
    """A usage error as one line, with where to read more when it is not about one value."""
    fmt = getattr(e, "format_message", None)
    text = " ".join((fmt() if fmt else str(e)).split())
    ctx = getattr(e, "ctx", None)
    if ctx is not None and type(e).__name__ != "BadParameter":
        text += f" (see '{ctx.command_path} --help')"
    return text


#: placeholder -> function giving the text, resolved when help is printed (cli.options.Registry)
LAZY_TEXT: dict[str, Callable[[], str]] = {}


def resolve_lazy_text(params: list[click.Parameter]) -> None:
    """Replace registry placeholders in metavars and help texts by the registered names."""
    for p in params:
        for key, text in LAZY_TEXT.items():
            if p.metavar == key:
                p.metavar = text()
            if getattr(p, "help", None) and key in p.help:
                p.help = p.help.replace(key, text().replace("|", ", "))


class _ReadableHelp:
    """``--help`` without a ``<bool>`` after it; registry names filled in."""

    def format_help(self, ctx: click.Context, formatter: Any) -> None:
        resolve_lazy_text(self.params)  # type: ignore[attr-defined]
        return super().format_help(ctx, formatter)  # type: ignore[misc]

    def get_help_option(self, ctx: click.Context) -> click.Option | None:
        opt = super().get_help_option(ctx)  # type: ignore[misc]
        if opt is not None:
            opt.metavar = ""
        return opt


class Command(_ReadableHelp, TyperCommand):
    """A terrastream command: readable help, the exit-status epilog, errors as one line."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs["epilog"] = kwargs.get("epilog") or EXIT_STATUS_HELP
        super().__init__(*args, **kwargs)
        _readable(self.params)

    def invoke(self, ctx: click.Context) -> Any:
        with fail_on_errors():
            return super().invoke(ctx)


class Group(_ReadableHelp, TyperGroup):
    """The ``terrastream`` group: readable help, the exit-status epilog, usage errors as one
    ``error: …`` line (``Invalid value for '--tau': 'nan' is not a finite number; …``)."""

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except (typer.TyperException, click.exceptions.ClickException) as e:
            if type(e).__name__ != "NoArgsIsHelpError":  # that one has printed the help
                typer.echo(f"error: {usage_line(e)}", err=True)
            sys.exit(getattr(e, "exit_code", EXIT_USAGE))
        except (typer.Abort, click.exceptions.Abort):
            typer.echo(INTERRUPTED_MESSAGE, err=True)
            sys.exit(EXIT_INTERRUPTED)
        sys.exit(rv if isinstance(rv, int) else 0)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs["epilog"] = kwargs.get("epilog") or EXIT_STATUS_HELP
        super().__init__(*args, **kwargs)
        _readable(self.params)
