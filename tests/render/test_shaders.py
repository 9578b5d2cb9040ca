"""The GLSL loader (pure): includes resolved once each, beside the file then in render/glsl/,
cycles and misplaced #version refused, the masked sentinel defined once."""

from __future__ import annotations

import numpy as np
import pytest

from render import gpu, shaders
from render.errors import GLStateError


def _write(tmp_path, files: dict[str, str]):
    for name, text in files.items():
        (tmp_path / name).write_text(text)


def test_includes_are_expanded_once_and_defines_follow_version(tmp_path):
    _write(tmp_path, {
        "a.vert": '#version 450\n#include "b.glsl"\n#include "c.glsl"\nvoid main() {}\n',
        "b.glsl": '#include "c.glsl"\nfloat b() { return c(); }\n',
        "c.glsl": "float c() { return 1.0; }\n",
    })  # fmt: skip
    src = shaders.source(tmp_path / "a.vert", {"X": 3})
    lines = src.splitlines()
    assert lines[0] == "#version 450"
    assert lines[1] == f"#define MASKED_HEIGHT {shaders.MASKED_GLSL}" and lines[2] == "#define X 3"
    assert src.count("float c()") == 1 and src.index("float c()") < src.index("float b()")


def test_shared_files_are_found_in_render_glsl(tmp_path):
    _write(tmp_path, {"a.vert": '#version 450\n#include "emit.glsl"\nvoid main() {}\n'})
    assert "void emit(Vtx v)" in shaders.source(tmp_path / "a.vert")


@pytest.mark.parametrize(
    ("files", "message"),
    [
        ({"a.vert": '#version 450\n#include "b.glsl"\n', "b.glsl": '#include "a.vert"\n'},
         "include cycle: a.vert -> b.glsl -> a.vert"),
        ({"a.vert": '#version 450\n#include "nope.glsl"\n'}, "'nope.glsl' not found"),
        ({"a.vert": '#version 450\n#include "b.glsl"\n', "b.glsl": "#version 450\n"},
         "only the entry file may have a #version line"),
        ({"a.vert": "void main() {}\n"}, "starts with its #version line"),
    ],
)  # fmt: skip
def test_loader_errors_say_what_is_wrong(tmp_path, files, message):
    _write(tmp_path, files)
    with pytest.raises(GLStateError, match=message):
        shaders.source(tmp_path / "a.vert")


def test_one_masked_sentinel():
    assert np.float32(float(shaders.MASKED_GLSL)) == gpu.MASKED
    assert gpu.MASKED < gpu.MASKED_BELOW < -1e20
    for src in (shaders.VERTEX, shaders.PROBE):  # the literal is not spelled in the sources
        assert "1.0e30" not in src.replace(shaders.MASKED_GLSL, "")
    assert "const float MASKED = MASKED_HEIGHT;" in shaders.VERTEX
