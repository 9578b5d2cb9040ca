"""The viewer's warm-up loads the compiled CLOD walk's kernels (``render.select_warm``) and
``seamless-patches``' (``seamless.warm``, for the store's shape) so the render thread's first
compiled ``qiu``, ``chunk-tessellation`` or ``seamless-patches`` selection loads none (it spent
~12 and ~28 ms doing so): in a fresh process, real selections after it add no kernel
signature. Controls: with the warm-ups that only import the kernels (the former ones), they
load them. (jung-han's: tests/render/test_jung_han_kernels.py.)"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

pytestmark = pytest.mark.gl
CTX = make_context()

_FIRST_USE = """
import numba
from render import _select_nb, select_kernels
from render.renderer import RenderConfig, TerrainRenderer
from render.select_warm import warm_up_walk
from render.strategies import get_strategy
from render.views import overview_camera
from tiler.store import open_store

def loaded():
    return sum(len(getattr(_select_nb, n).signatures) for n in dir(_select_nb)
               if isinstance(getattr(_select_nb, n), numba.core.registry.CPUDispatcher))

select_kernels.warm_up(warm_up_walk if {warm} else None)
assert select_kernels.resolve() is not None  # auto: the compiled walk from now on
before = loaded()
s = open_store({path!r})
r = TerrainRenderer(s, RenderConfig(size=(96, 64)))
for b in s.blocks():
    r.upload(b, s.read_levels(b, s.k - (b[0] + b[1]) % 2))
cam = overview_camera(s, (96, 64))
for lod in ("qiu", "chunk-tessellation"):
    sel, _ = get_strategy(lod, r).select(cam, 1.0)
    assert len(sel.patches.depth if hasattr(sel, "patches") else sel.depth) > 0
r.close()
print(before, loaded())
"""


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    pytest.importorskip("numba")
    dem = rough(129, 4).astype(np.float32)
    dem[:20, :30] = np.nan  # nodata beside terrain: the windows and masks of a real store
    return tile_dem(tmp_path_factory.mktemp("warm"), dem, 65)


def _signatures(code: str) -> tuple[int, int]:
    """Run ``code`` in a fresh process (``auto`` kernels); the kernel signatures it prints
    before and after the real selection."""
    env = {k: v for k, v in os.environ.items() if k != "TERRASTREAM_KERNELS"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600, env=env
    )
    assert out.returncode == 0, out.stderr[-3000:]
    before, after = (int(v) for v in out.stdout.split()[-2:])
    return before, after


@pytest.mark.parametrize("warm", [True, False])
def test_warm_up_loads_every_kernel_a_real_selection_calls(store, warm):
    before, after = _signatures(_FIRST_USE.format(warm=warm, path=str(store)))
    if warm:
        assert before >= 4 and after == before  # visit, split, qiu_rho, kim_rho
    else:
        assert before == 0 and after >= 4


_SEAMLESS = """
import numba
from render.renderer import RenderConfig, TerrainRenderer
from render.strategies import get_strategy, warm_up_kernels
from render.strategies.seamless import _resolve_nb
from render.views import overview_camera
from tiler.store import open_store

def loaded():
    return sum(len(getattr(_resolve_nb, n).signatures) for n in dir(_resolve_nb)
               if isinstance(getattr(_resolve_nb, n), numba.core.registry.CPUDispatcher))

s = open_store({path!r})
r = TerrainRenderer(s, RenderConfig(size=(96, 64)))
for b in s.blocks():
    r.upload(b, s.read_levels(b, s.k - (b[0] + b[1]) % 2))
st = get_strategy("seamless-patches", r, res_log2=3)
assert st.warm_up_args() == {{"seamless_shape": (s.k, 3)}}
warm_up_kernels(**(st.warm_up_args() if {warm} else {{}}))
before = loaded()
sel, _ = st.select(overview_camera(s, (96, 64)), 1.0)
assert len(sel.depth) > 0
r.close()
print(before, loaded())
"""


@pytest.mark.parametrize("warm", [True, False])
def test_the_seamless_warm_up_loads_the_kernel_a_real_selection_calls(store, warm):
    before, after = _signatures(_SEAMLESS.format(warm=warm, path=str(store)))
    if warm:
        assert before >= 1 and after == before
    else:
        assert before == 0 and after >= 1
