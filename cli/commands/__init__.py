"""One module per ``terrastream`` command; each has a ``register(app)`` function.

:data:`COMMANDS` is the order the commands appear in ``terrastream --help``. A new command is a
new module here with a ``register(app)`` function, added to :data:`COMMANDS`.
"""

from __future__ import annotations

from cli.commands import (
    compare,
    export,
    flythrough,
    info,
    render,
    stream,
    synth,
    tile,
    tradeoff,
    verify,
    view,
)

COMMANDS = (tile, info, verify, synth, export, stream, render, tradeoff, flythrough, view, compare)
