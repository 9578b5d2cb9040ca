"""Compiled kernels against the numpy reference: bit for bit (encoders), exactly (errors)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tiler import encoding, kernels, static_error
from tiler.errors import KernelUnavailableError
from tiler.layout import grid_side

pytest.importorskip("numba")

REPO = Path(__file__).resolve().parents[2]
DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64"]
CASES = ["terrain", "holes", "flat", "extreme", "full-range", "nan-holes", "all-invalid"]


def _block(case: str, k: int, dtype: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A grid (of ``dtype``) and its valid mask for one test case."""
    rng = np.random.default_rng(seed)
    side = grid_side(k)
    dt = np.dtype(dtype)
    valid = np.ones((side, side), bool)
    walk = rng.standard_normal((side, side)).cumsum(0).cumsum(1)
    if case == "full-range":
        if dt.kind == "f":
            z = rng.standard_normal((side, side)) * 1e6
        else:
            info = np.iinfo(dt)
            return rng.integers(info.min, info.max, (side, side), endpoint=True).astype(dt), valid
    elif case == "flat":
        z = np.full((side, side), 7.0 if dt.kind == "u" else -3.0)
    elif case == "extreme":  # -11 km to +9 km where the dtype holds it
        lo, hi = -11000.0, 9000.0
        if dt.kind != "f":
            info = np.iinfo(dt)
            lo, hi = max(lo, info.min), min(hi, info.max)
        z = np.where(rng.random((side, side)) < 0.5, lo, hi)
        z[:: max(1, side // 3)] = (lo + hi) / 2
    else:
        z = walk * 3.0 + (100.0 if dt.kind == "u" else 0.0)
    if dt.kind != "f":
        info = np.iinfo(dt)
        z = np.clip(np.rint(z), info.min, info.max)
    else:
        z = z + rng.random((side, side)) * 1e-3  # fractional bits
    grid = z.astype(dt)
    if case in ("holes", "nan-holes"):
        valid = rng.random((side, side)) > 0.3
        valid[0, 0] = False  # an invalid corner: level 0 takes the mean
    if case == "all-invalid":
        valid[:] = False
    if case == "nan-holes" and dt.kind == "f":
        grid[~valid] = np.nan
    return grid, valid


def _with_numpy(fn, *args):
    """``fn(*args)`` with the numpy backend (then back to numba)."""
    os.environ[kernels.ENV] = "numpy"
    try:
        return fn(*args)
    finally:
        os.environ[kernels.ENV] = "numba"


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("k", [1, 2, 5, 7])
def test_kernels_equal_numpy(numba_backend, k, case, dtype):
    grid, valid = _block(case, k, dtype, seed=k * 100 + CASES.index(case))
    filled = encoding.fill_invalid(grid, valid, k)
    assert _same_bits(filled, encoding.fill_invalid_numpy(grid, valid, k))
    assert not np.isnan(filled).any()
    stored = encoding.encode_levels(filled, k)
    ref = encoding.encode_levels_numpy(filled, k)
    assert len(stored) == len(ref) and all(map(_same_bits, stored, ref))
    for level in range(k + 1):
        assert _same_bits(
            encoding.decode_grid(ref, dtype, level), encoding.decode_grid_numpy(ref, dtype, level)
        )
    assert _same_bits(encoding.decode_grid(ref, dtype), filled)
    decoded = encoding.decode_levels(ref, dtype)
    assert all(map(_same_bits, decoded, encoding.decode_levels_numpy(ref, dtype)))
    for n in range(k + 1):
        got = encoding.decode_next_level(decoded[:n], ref[n], dtype)
        assert _same_bits(got, encoding.decode_next_level_numpy(decoded[:n], ref[n], dtype))
    for fast, slow in (
        (static_error.qiu_errors, static_error.qiu_errors_numpy),
        (static_error.bound_errors, static_error.bound_errors_numpy),
    ):
        a, b = fast(filled, valid, k), slow(filled, valid, k)
        assert len(a) == len(b) == k
        for depth in range(k):
            assert a[depth].dtype == b[depth].dtype == np.float64
            np.testing.assert_array_equal(a[depth], b[depth], err_msg=f"{fast.__name__} d={depth}")
    for cap in sorted({0, k // 2, k - 1}):
        got = static_error.block_errors(filled, valid, k, cap)
        assert _same_bits(got, _with_numpy(static_error.block_errors, filled, valid, k, cap))


@pytest.mark.parametrize("dtype", ["int16", "float32"])
def test_kernels_equal_numpy_1025(numba_backend, dtype):
    """The production block size, with nodata: the whole per-block pipeline is identical."""
    from tiler.synth import synth_array

    k = 10
    grid = synth_array(slice(0, 1025), slice(0, 1025), 1025, seed=5, dtype=dtype)
    valid = np.random.default_rng(2).random(grid.shape) > 0.05
    filled = encoding.fill_invalid(grid, valid, k)
    assert _same_bits(filled, encoding.fill_invalid_numpy(grid, valid, k))
    assert all(
        map(_same_bits, encoding.encode_levels(filled, k), encoding.encode_levels_numpy(filled, k))
    )
    got = static_error.block_errors(filled, valid, k, 6)
    assert _same_bits(got, _with_numpy(static_error.block_errors, filled, valid, k, 6))


@pytest.mark.parametrize("dtype", ["int8", "uint8", "uint16", "int16", "uint32", "int32"])
@pytest.mark.parametrize("k", [0, 1, 2, 3, 6])
def test_int_decode_of_arbitrary_residuals_equals_numpy(numba_backend, k, dtype):
    """Any stored bits (not only an encoder's): sums that wrap the dtype, every partial start
    level; the per-level decode loops agree with the numpy reference bit for bit."""
    rng = np.random.default_rng(k * 31 + DTYPES.index(dtype))
    u = np.dtype(dtype.replace("u", "")).str.replace("i", "u")  # the unsigned twin
    bits = np.iinfo(np.dtype(u)).max
    stored = [
        rng.integers(0, bits, size=encoding.level_size(i), endpoint=True, dtype=u)
        for i in range(k + 1)
    ]
    stored[-1][-1] = bits  # an extreme residual in the last slot (the last column's centre)
    for level in range(k + 1):
        want = encoding.decode_grid_numpy(stored, dtype, level)
        assert _same_bits(encoding.decode_grid(stored, dtype, level), want)
    levels = encoding.decode_levels_numpy(stored, dtype)
    for n in range(k + 1):
        got = encoding.decode_next_level(levels[:n], stored[n], dtype)
        assert _same_bits(got, levels[n])
    if k:  # positive control: one stored bit changed is seen
        flipped = [s.copy() for s in stored]
        flipped[k][-1] ^= 1
        assert not _same_bits(encoding.decode_grid(flipped, dtype), want)


def test_exactness_checks_see_one_ulp_and_one_bit(numba_backend):
    """Positive control: the comparisons above fail for a one-ulp or one-bit difference."""
    k = 5
    grid, valid = _block("terrain", k, "float32", seed=9)
    nudged = np.nextafter(grid, np.float32(np.inf))  # every sample one ulp up
    a = static_error.bound_errors(grid, valid, k)
    b = static_error.bound_errors_numpy(nudged, valid, k)
    assert any(not np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    stored = encoding.encode_levels(grid, k)
    flipped = [s.copy() for s in stored]
    flipped[k][3] ^= 1
    assert not _same_bits(encoding.decode_grid(flipped, "float32"), grid)


def test_kernels_release_the_gil_and_cache():
    """Every kernel is nogil (a loader thread's decode never stalls the caller's thread)."""
    from numba.core.caching import FunctionCache
    from numba.core.registry import CPUDispatcher

    from tiler import _codec_nb, _kernels_nb

    mods = (_kernels_nb, _codec_nb)
    found = {id(v): v for m in mods for v in vars(m).values() if isinstance(v, CPUDispatcher)}
    found = list(found.values())
    assert len(found) >= 16
    for disp in found:
        assert disp.targetoptions.get("nogil") is True, disp.__name__
        assert isinstance(disp._cache, FunctionCache), disp.__name__  # on disk (tiler.jit's key)


def test_backend_selection(monkeypatch):
    monkeypatch.setenv(kernels.ENV, "numpy")
    assert kernels.backend() == "numpy" and kernels.active() is None
    monkeypatch.setenv(kernels.ENV, "fortran")
    with pytest.raises(KernelUnavailableError, match="fortran"):
        kernels.backend()
    monkeypatch.setattr(kernels, "_load_numba", lambda: None)
    monkeypatch.setenv(kernels.ENV, "numba")
    with pytest.raises(KernelUnavailableError, match="fast"):
        kernels.active()
    monkeypatch.setenv(kernels.ENV, "auto")
    assert kernels.backend() == "numpy"  # auto falls back when numba is missing
    grid, valid = _block("holes", 4, "int16", seed=1)
    filled = encoding.fill_invalid(grid, valid, 4)  # the numpy path, through the public API
    assert _same_bits(filled, encoding.fill_invalid_numpy(grid, valid, 4))


def test_non_finite_grids_take_the_numpy_path(numba_backend):
    """NaN left in a grid (not filled) gives the numpy result, not a kernel's NaN ordering."""
    grid, valid = _block("nan-holes", 4, "float64", seed=3)
    a = static_error.bound_errors(grid, valid, 4)
    b = static_error.bound_errors_numpy(grid, valid, 4)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


def _run(code: str, **env: str) -> subprocess.CompletedProcess:
    full = {**os.environ, "PYTHONPATH": str(REPO), **env}
    full.pop(kernels.ENV, None)
    return subprocess.run(
        [sys.executable, "-c", code],
        env=full,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=240,
    )


def test_numba_is_not_imported_until_a_kernel_runs():
    code = (
        "import sys, numpy as np\n"
        "import cli.main, tiler.store, tiler.info, tiler.encoding, tiler.static_error\n"
        "print('numba' in sys.modules)\n"
        "s = tiler.encoding.encode_levels_numpy(np.arange(9, dtype=np.int16).reshape(3, 3), 1)\n"
        "tiler.encoding.decode_grid(s, 'int16')  # the read path never loads numba itself\n"
        "print('numba' in sys.modules)\n"
        "tiler.encoding.encode_levels(np.zeros((3, 3), np.int16), 1)\n"
        "print('numba' in sys.modules)\n"
    )
    r = _run(code)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["False", "False", "True"]


def test_choose_and_warm_up(monkeypatch):
    monkeypatch.setenv(kernels.ENV, "auto")
    assert kernels.choose(1201 * 1201) == "numpy"  # one SRTM tile: numba's start-up costs more
    assert kernels.choose(16385 * 16385) == "numba"
    monkeypatch.setenv(kernels.ENV, "numba")
    assert kernels.choose(10) == "numba"
    assert kernels.warm_up("float32") is True
    monkeypatch.setenv(kernels.ENV, "numpy")
    assert kernels.choose(16385 * 16385) == "numpy"
    assert kernels.warm_up() is False


def test_unwritable_cache_dir_still_runs(tmp_path):
    """NUMBA_CACHE_DIR under a regular file cannot be created: the kernels still compile."""
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    code = (
        "import numpy as np\n"
        "from tiler import encoding\n"
        "g = (np.arange(81, dtype=np.int16) % 7).reshape(9, 9)\n"
        "s = encoding.encode_levels(g, 3)\n"
        "assert (encoding.decode_grid(s, 'int16') == g).all()\n"
        "print('ok')\n"
    )
    r = _run(code, NUMBA_CACHE_DIR=str(blocker / "cache"), TERRASTREAM_KERNELS="numba")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok"
