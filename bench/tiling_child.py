"""The tiling benchmark's measured child processes: a tiling or a COG build in a fresh Python.

:func:`run_child` starts ``python bench/tiling.py --child TASK`` (whose ``main`` hands the task
to :func:`_child_main`) and samples the child's RSS every 20 ms until it exits; the kernel's
``ru_maxrss`` from ``os.wait4`` and ``getrusage(RUSAGE_CHILDREN)`` are the cross-checks.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

from bench.common import REPO

#: the script the child runs (``--child``): the benchmark's own command line
TILING = Path(__file__).resolve().with_name("tiling.py")
MB = float(1 << 20)
SAMPLE_S = 0.02


def _child_main(task: dict[str, Any]) -> dict[str, Any]:
    """Run one measured task inside the child process; return its JSON-ready result."""
    import psutil

    warnings.simplefilter("ignore")
    kind = task["kind"]
    if kind == "tile":
        from tiler.tile import TileOptions, tile

        rss0 = psutil.Process().memory_info().rss
        opts = TileOptions(block_size=task["block_size"], workers=task["workers"], overwrite=True)
        t0 = time.perf_counter()
        tile(task["src"], task["dst"], opts)
        seconds = time.perf_counter() - t0
    elif kind == "cog":
        from rio_cogeo.cogeo import cog_translate
        from rio_cogeo.profiles import cog_profiles

        rss0 = psutil.Process().memory_info().rss
        profile = cog_profiles.get("zstd")
        profile.update(predictor=2)
        t0 = time.perf_counter()
        cog_translate(
            task["src"],
            task["dst"],
            profile,
            overview_level=task["overview_level"],
            quiet=True,
            config=task["config"],
        )
        seconds = time.perf_counter() - t0
    else:
        raise ValueError(f"unknown child task {kind!r}")
    self_maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"seconds": seconds, "rss_before_task": rss0, "self_maxrss": self_maxrss}


def run_child(task: dict[str, Any]) -> dict[str, Any]:
    """Run ``task`` in a fresh Python process; sample its RSS every 20 ms until it exits."""
    import psutil

    cmd = [sys.executable, str(TILING), "--child", json.dumps(task)]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        wall0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, text=True, cwd=str(REPO))
        ps = psutil.Process(proc.pid)
        peak, samples = 0, 0
        while True:
            with contextlib.suppress(psutil.Error):
                # the task's own RSS plus its worker processes' (the tiler may spawn some)
                rss = ps.memory_info().rss
                for child in ps.children(recursive=True):
                    with contextlib.suppress(psutil.Error):
                        rss += child.memory_info().rss
                peak = max(peak, rss)
                samples += 1
            pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            time.sleep(SAMPLE_S)
        wall = time.perf_counter() - wall0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if proc.returncode != 0:
        raise RuntimeError(
            f"child task {task['kind']} failed (exit {proc.returncode}):\n{stderr[-4000:]}"
        )
    result = json.loads(stdout.strip().splitlines()[-1])
    result.update(
        peak_rss_sampled=peak,
        rss_samples=samples,
        wait4_maxrss=ru.ru_maxrss * 1024,
        rusage_children_maxrss=resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024,
        process_wall_s=wall,
    )
    return result


def _rss_mb(res: dict[str, Any]) -> dict[str, float]:
    return {
        "peak_rss_mb": res["peak_rss_sampled"] / MB,
        "wait4_maxrss_mb": res["wait4_maxrss"] / MB,
        "self_maxrss_mb": res["self_maxrss"] / MB,
        "rusage_children_maxrss_mb": res["rusage_children_maxrss"] / MB,
        "rss_before_task_mb": res["rss_before_task"] / MB,
    }
