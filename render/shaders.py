"""GLSL sources: ``.glsl`` files (package data) joined by a small ``#include`` mechanism.

An entry file (``*.vert``, ``*.tesc``, ``*.tese``, ``*.geom``, ``*.frag``) starts with its
``#version`` line; ``#include "name.glsl"`` lines are replaced by that file, looked up first
beside the including file, then in ``render/glsl/``; a file is included once per source (so
``fetch.glsl`` may be included by two includes of one shader). After the ``#version`` line the
loader puts ``#define`` lines: ``MASKED_HEIGHT`` (the one definition of the masked-height
sentinel, :data:`render.gpu.MASKED`) and any ``defines`` the caller gives.

Shared files in ``render/glsl/``:

* ``fetch.glsl`` — the height-pool fetch (Qiu's steps 1-4: level index, order index,
  ``start(level) + order``), the masked test, normals, camera-relative positions from integer
  samples: ``Vtx vertex_at(ivec4 a, ivec4 b, int si, int sj)`` for the instance layout
  ``a = (block col0, block row0, node col0, node row0)``, ``b = (slot base, level, cells_log2,
  snaps N | E<<4 | S<<8 | W<<12)``;
* ``patch_vertex.glsl`` — the CLOD patch grid with edge snapping (``make_vertex``);
* ``emit.glsl`` — the varyings every strategy's last vertex stage hands to the fragment shader;
* ``shade.glsl`` — colour ramp, LOD colours, Lambert shading;
* ``terrain.vert``/``terrain.frag``, ``wire.geom``/``wire.frag`` (wireframe overlay),
  ``probe.vert`` (per-vertex transform feedback), ``triangle_probe.geom`` (triangle read-back
  into the SSBO at binding 3, see :meth:`render.frame.FrameServices.read_triangles`).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

from render.errors import GLStateError
from render.gpu import MASKED

GLSL_DIR = Path(__file__).with_name("glsl")
_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$')
#: the masked-height sentinel as a GLSL literal (``render.gpu.MASKED``)
MASKED_GLSL = f"{float(MASKED):.1e}"


def _find(name: str, here: Path) -> Path:
    for d in (here, GLSL_DIR):
        p = d / name
        if p.is_file():
            return p
    raise GLStateError(f"GLSL include {name!r} not found beside {here} or in {GLSL_DIR}")


def _expand(path: Path, seen: set[Path], stack: tuple[Path, ...], out: list[str]) -> None:
    if path in stack:
        chain = " -> ".join(p.name for p in (*stack, path))
        raise GLStateError(f"GLSL include cycle: {chain}")
    if path in seen:
        return
    seen.add(path)
    for line in path.read_text().splitlines():
        m = _INCLUDE.match(line)
        if m:
            _expand(_find(m.group(1), path.parent), seen, (*stack, path), out)
        elif line.startswith("#version") and stack:
            raise GLStateError(f"{path.name}: only the entry file may have a #version line")
        else:
            out.append(line)


def source(entry: str | Path, defines: Mapping[str, object] | None = None) -> str:
    """The GLSL of ``entry`` (a path, or a file name in ``render/glsl/``) with its includes
    expanded and ``MASKED_HEIGHT`` plus ``defines`` defined after the ``#version`` line."""
    path = Path(entry)
    if not path.is_absolute():
        path = GLSL_DIR / path
    lines: list[str] = []
    _expand(path, set(), (), lines)
    while lines and not lines[0].strip():
        lines.pop(0)
    if not lines or not lines[0].startswith("#version"):
        raise GLStateError(f"{path.name}: a shader entry file starts with its #version line")
    defs = {"MASKED_HEIGHT": MASKED_GLSL, **(defines or {})}
    head = [lines[0]] + [f"#define {k} {v}" for k, v in defs.items()]
    return "\n".join(head + lines[1:]) + "\n"


# The shared programs' stages (Qiu's CLOD patches, the wireframe overlay, the probes).
VERTEX = source("terrain.vert")
PROBE = source("probe.vert")
FRAGMENT = source("terrain.frag")
GEOMETRY = source("wire.geom")
FRAGMENT_WIRE = source("wire.frag")
TRIANGLE_PROBE = source("triangle_probe.geom")
