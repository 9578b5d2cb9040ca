"""tiler.malloc: fixed allocator thresholds remove the page faults dask's worker environment
(MALLOC_TRIM_THRESHOLD_=65536) adds to every block; the positive control is the same run with
the tuning switched off."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")

PROBE = textwrap.dedent(
    """
    import json, resource, sys
    from tiler.run import worker_setup
    from tiler.synth import synth_array
    from tiler.tile import BlockParams, process_block

    worker_setup(64, "numpy", "int16")
    win = synth_array(slice(0, 513), slice(0, 513), 4097, 0, 2500.0, 200.0, "int16")
    p = BlockParams(k=9, dtype="int16", storage_dtype="int16", nodata=None, precision=None,
                    error_cap=6)
    first = process_block(win, p)
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(3):
        again = process_block(win, p)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / 3
    same = all((a == b).all() for a, b in zip(first.levels, again.levels))
    print(json.dumps({"faults": faults, "same": bool(same)}))
    """
)


def _faults(tune: str) -> dict:
    env = dict(
        os.environ,
        PYTHONPATH=os.getcwd(),
        MALLOC_TRIM_THRESHOLD_="65536",  # what dask's nanny gives its workers
        TERRASTREAM_MALLOC_TUNE=tune,
    )
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=240
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_tuned_worker_reuses_its_heap_under_dasks_environment():
    tuned, untuned = _faults("1"), _faults("0")
    assert tuned["same"] and untuned["same"]
    assert untuned["faults"] > 1000, untuned  # the detector sees the mmap churn ...
    assert tuned["faults"] < 0.1 * untuned["faults"], (tuned, untuned)  # ... and its removal


def test_tune_allocator_is_idempotent_and_can_be_disabled(monkeypatch):
    from tiler import malloc

    monkeypatch.setattr(malloc, "_done", False)
    monkeypatch.setenv(malloc.ENV, "0")
    assert malloc.tune_allocator() is False
    monkeypatch.delenv(malloc.ENV)
    out = subprocess.run(
        [sys.executable, "-c", "from tiler.malloc import tune_allocator as t; print(t(), t())"],
        env=dict(os.environ, PYTHONPATH=os.getcwd()),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.stdout.split() == ["True", "True"], out.stderr
