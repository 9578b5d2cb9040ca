"""GPU quadtree machinery shared by the strategies that traverse on the GPU
(``geometry-splitting``, ``chunk-tessellation`` with ``selection="gpu"``): one transform-feedback
pass over point records with its output count read back, and the drawn blocks' neighbours."""

from __future__ import annotations

import moderngl
import numpy as np

from render.errors import RenderError

Block = tuple[int, int]
#: (row, col) steps to the neighbour across edge N, E, S, W
EDGE_STEPS = ((-1, 0), (0, 1), (1, 0), (0, -1))


def feedback_pass(
    ctx: moderngl.Context,
    prog: moderngl.Program,
    src: moderngl.Buffer,
    fmt: str,
    names: list[str],
    n: int,
    out_per: int,
    rec_bytes: int,
) -> tuple[moderngl.Buffer, int]:
    """Run ``prog`` (a geometry shader emitting points) over ``n`` point records of ``src``
    with transform feedback into a new buffer (room for ``out_per`` records of ``rec_bytes``
    per input); return it and the records written (a ``GL_PRIMITIVES_GENERATED`` query, the
    4 bytes that travel back: moderngl exposes no ``glDrawTransformFeedback``)."""
    out = ctx.buffer(reserve=max(1, n * out_per) * rec_bytes)
    vao = ctx.vertex_array(prog, [(src, fmt, *names)])
    q = ctx.query(primitives=True)
    with q:
        vao.transform(out, moderngl.POINTS, vertices=n)
    m = int(q.primitives)
    vao.release()
    if m > n * out_per:
        raise RenderError(f"a transform-feedback pass emitted {m} records for {n} inputs")
    return out, m


def block_neighbours(blocks: list[Block]) -> np.ndarray:
    """``(m, 4)`` int64: the index in ``blocks`` of each block's neighbour across edge N, E, S,
    W (-1 where that block is not in the list)."""
    index = {b: i for i, b in enumerate(blocks)}
    out = np.full((len(blocks), 4), -1, dtype=np.int64)
    for i, b in enumerate(blocks):
        for e, (dr, dc) in enumerate(EDGE_STEPS):
            out[i, e] = index.get((b[0] + dr, b[1] + dc), -1)
    return out
