"""Shared benchmark helpers: where the data is and what machine ran the benchmark.

Every ``bench/*.py`` puts the repository first on ``sys.path`` and imports this module as
``bench.common`` (``bench/render.py`` would shadow the ``render`` package otherwise); it takes its
paths from here, so no script names a machine's absolute path:

* ``SHARED_DATA`` — real DEMs (``N44W072.hgt``): ``$TERRASTREAM_SHARED_DATA``, default
  ``../shared/data`` beside the repository (the same rule as ``tests/conftest.py``);
* ``WORK`` — generated sources and stores (``bench/work``, git-ignored), ``RESULTS`` — the
  committed JSON and plots (``bench/results``).

:func:`machine_info` is the one machine record every benchmark writes beside its figures.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import sys
from importlib import import_module
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]

#: the environment variable naming the folder of real DEMs
DATA_ENV = "TERRASTREAM_SHARED_DATA"
SHARED_DATA = Path(os.environ.get(DATA_ENV, REPO.parent / "shared" / "data"))
WORK = REPO / "bench" / "work"
RESULTS = REPO / "bench" / "results"
#: the real SRTM tile of BENCHMARKS.md
REAL_HGT = SHARED_DATA / "N44W072.hgt"
#: the stores of the rendering and LOD benchmarks (made by bench/tiling.py / bench/prefetch.py)
S4097 = WORK / "s4097.zarr"
S16385 = WORK / "s16385.zarr"
N44W072_EQC = WORK / "prefetch" / "n44w072_eqc_b257.zarr"
#: the real DEM with nodata of "LOD strategies" (xdem's Longyearbyen, EPSG:32633, 257² blocks)
LONGYEARBYEN = WORK / "longyearbyen_b257.zarr"

_VERSIONS = ("numpy", "zarr", "rasterio", "rio_cogeo", "moderngl", "numba")


def portable(obj: Any) -> Any:
    """``obj`` (JSON-like) with this machine's paths replaced: the repository by ``.`` and the
    real-data folder by ``$TERRASTREAM_SHARED_DATA`` (result files name no machine's paths)."""
    if isinstance(obj, dict):
        return {k: portable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [portable(v) for v in obj]
    if isinstance(obj, str):
        for prefix, name in ((str(SHARED_DATA), f"${DATA_ENV}"), (str(REPO), ".")):
            if obj == prefix:
                return name
            obj = obj.replace(prefix + os.sep, name + os.sep)  # also inside text (profiles)
    return obj


def machine_info() -> dict[str, Any]:
    """Date, CPUs, memory, platform, Python and the versions of the libraries that matter
    (a library that is not installed is left out)."""
    info: dict[str, Any] = {
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": sys.version.split()[0],
    }
    try:
        import psutil

        info["memory_gb"] = round(psutil.virtual_memory().total / 2**30, 1)
    except ImportError:
        pass
    for name in _VERSIONS:
        try:
            info[name] = import_module(name).__version__
        except (ImportError, AttributeError):
            continue
    try:
        import rasterio

        info["gdal"] = rasterio.__gdal_version__
    except ImportError:
        pass
    if hasattr(os, "getloadavg"):
        info["loadavg_at_start"] = os.getloadavg()  # timings are only comparable within a run
    info["git_head"] = git_head()
    info["dirty"], info["dirty_files"] = git_dirty()
    return info


def git_head() -> str | None:
    """The commit the benchmark ran on (read from .git, no subprocess), or None."""
    try:
        head = (REPO / ".git" / "HEAD").read_text().strip()
        ref = head.split(" ", 1)[1] if head.startswith("ref:") else None
        return (REPO / ".git" / ref).read_text().strip() if ref else head
    except (OSError, IndexError):
        return None


#: the code folders whose uncommitted changes make a measurement not the commit it names
CODE_DIRS = ("tiler", "streamer", "render", "cli", "bench")
#: how many changed files :func:`git_dirty` names (the flag counts them all)
DIRTY_LIST_MAX = 20


def git_dirty(repo: Path = REPO) -> tuple[bool | None, list[str] | None]:
    """Whether tracked files under :data:`CODE_DIRS` differ from HEAD (staged or not) and the
    first :data:`DIRTY_LIST_MAX` of them (``+N more`` last when there are more); ``(None,
    None)`` when git cannot tell. ``bench/results`` (data) and untracked files are left out."""
    import subprocess

    cmd = [
        "git", "--no-optional-locks", "-C", str(repo), "status", "--porcelain=v1",
        "--untracked-files=no", "--", *CODE_DIRS, ":(exclude)bench/results",
    ]  # fmt: skip
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None, None
    if res.returncode != 0:
        return None, None
    files = sorted(line[3:] for line in res.stdout.splitlines() if len(line) > 3)
    shown = files[:DIRTY_LIST_MAX]
    if len(files) > DIRTY_LIST_MAX:
        shown.append(f"+{len(files) - DIRTY_LIST_MAX} more")
    return bool(files), shown


def store_complete(path: str | Path) -> bool:
    """Whether ``path`` holds a finished store (:func:`tiler.store.open_store` opens it and its
    ``meta.complete`` is set): a folder an interrupted run left half-written is not one."""
    from tiler.errors import StoreError
    from tiler.store import open_store

    try:
        return bool(open_store(path).meta.complete)
    except StoreError:
        return False


def ensure_store(path: str | Path) -> bool:
    """Make the benchmark store ``path`` if it is one this module names and is missing or
    unfinished (:func:`store_complete`; ``tile`` run again resumes it) (``S4097``:
    ``terrastream synth --size 4097 --seed 0``, blocks of 1025²; ``N44W072_EQC``:
    ``bench/prefetch.py``'s metre relabelling; ``LONGYEARBYEN``); whether it is complete now."""
    import subprocess

    path = Path(path).resolve()
    if store_complete(path):
        return True
    exe = str(Path(sys.executable).with_name("terrastream"))
    if path == S4097:
        src = WORK / "s4097.tif"
        if not src.exists():
            WORK.mkdir(parents=True, exist_ok=True)
            subprocess.run([exe, "synth", str(src), "--size", "4097", "--seed", "0"], check=True)
        subprocess.run([exe, "tile", str(src), str(path), "--block-size", "1025"], check=True)
    elif path == N44W072_EQC:
        from bench.prefetch import prepare_real

        if prepare_real(metric=True) is None:
            return False
    elif path == LONGYEARBYEN:
        src = SHARED_DATA / "xdem_aligned_elev_Longyearbyen.tif"
        if not src.exists():
            return False
        subprocess.run([exe, "tile", str(src), str(path), "--block-size", "257"], check=True)
    return store_complete(path)


def flythrough_rows(
    store: str, lod: str, frames: int, tau: float, env: dict[str, str], *flags: str
) -> list[dict[str, str]]:
    """``terrastream flythrough STORE --lod LOD`` as a user runs it, in a fresh process with
    ``env`` (no PNGs); its ``frames.csv`` rows. A failed flight raises with its stderr."""
    import csv
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as out:
        cmd = [
            sys.executable, "-c", "from cli.main import main; main()", "flythrough", store,
            "--lod", lod, "--frames", str(frames), "--tau", str(tau), "--every", "0",
            "--out", out, *flags,
        ]  # fmt: skip
        res = subprocess.run(cmd, cwd=str(REPO), env=env, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"flythrough failed (exit {res.returncode}):\n{res.stderr[-3000:]}")
        with open(Path(out) / "frames.csv", newline="") as f:
            return list(csv.DictReader(f))


def count_requests(store: Any) -> list[str]:
    """The keys of every request a ``TerrainStore`` makes of its zarr store from now on (its
    ``get`` wrapped: exact, whichever reader asks)."""
    zstore = store._group.store
    real, keys = zstore.get, []

    async def get(key: str, prototype: Any, byte_range: Any = None) -> Any:
        keys.append(key)
        return await real(key, prototype, byte_range)

    zstore.get = get
    return keys
