"""A benchmark that measured nothing fails and writes no result (audit 44).

Before: ``bench/render.py``, ``bench/select_cpu.py`` (both modes), ``bench/remote_reads.py``,
``bench/ablation.py`` and ``bench/prefetch.py`` skipped every missing store with a message, then
wrote an empty JSON over the committed one and exited 0; ``bench/tiling.py`` with no input wrote
``"all_targets_pass": true`` over nothing; a COG without the coarse overview dropped the coarse
read target, so ``all_targets_pass`` could be true without it being measured.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


@pytest.fixture
def missing(tmp_path: Path) -> Path:
    """A store path that does not exist (and that no benchmark knows how to make)."""
    return tmp_path / "absent.zarr"


def _fails_without_writing(code: int | None, out: Path, capsys) -> None:
    assert code == 1, f"exit {code!r} with nothing measured"
    assert not out.exists(), "an empty result was written"
    assert "no store" in capsys.readouterr().err


def test_render_with_no_store_fails(missing, tmp_path, capsys):
    from bench import render

    out = tmp_path / "render.json"
    code = render.main(["--stores", str(missing), "--out", str(out), "--quick"])
    _fails_without_writing(code, out, capsys)


def test_select_cpu_with_no_store_fails(missing, tmp_path, capsys):
    from bench import select_cpu

    out = tmp_path / "select.json"
    code = select_cpu.main([str(missing), "--no-compile", "--out", str(out)])
    _fails_without_writing(code, out, capsys)
    code = select_cpu.main([str(missing), "--metric", "conservative-view", "--out", str(out)])
    _fails_without_writing(code, out, capsys)


def test_remote_reads_with_no_store_fails(missing, tmp_path, capsys):
    from bench import remote_reads

    out = tmp_path / "remote.json"
    _fails_without_writing(remote_reads.main([str(missing), "--out", str(out)]), out, capsys)


def test_flights_without_the_real_dem_fail(tmp_path, monkeypatch, capsys):
    import bench.prefetch_stores as stores
    from bench import ablation, prefetch

    monkeypatch.setattr(stores, "REAL_HGT", tmp_path / "N00W000.hgt")  # (absent)
    out = tmp_path / "ablation.json"
    code = ablation.main(["--stores", "real", "--frames", "4", "--out", str(out)])
    assert code == 1 and not out.exists()
    assert "no store" in capsys.readouterr().err
    out = tmp_path / "prefetch.json"
    _fails_without_writing(prefetch.main(["--stores", "real", "--out", str(out)]), out, capsys)


def test_ablation_refuses_an_unknown_store_name(tmp_path, capsys):
    from bench import ablation

    out = tmp_path / "ablation.json"
    # before: any name but "real" flew the synthetic store, recorded under the typo
    assert ablation.main(["--stores", "sytnh", "--out", str(out)]) == 2
    assert not out.exists() and "sytnh" in capsys.readouterr().err


def test_tiling_with_no_input_fails(tmp_path, capsys):
    from bench import tiling

    out = tmp_path / "tiling.json"
    assert tiling.main(["--sizes", "", "--real", "", "--out", str(out)]) == 1
    assert not out.exists() and "no input" in capsys.readouterr().err


def _reads(cog_overview_ms: float | None) -> dict:
    return {
        "variants": {"store": {}},
        "store_block_ms": 1.0,
        "store_coarse_ms": 1.0,
        "cog_window_ms": 2.0,
        "cog_overview_ms": cog_overview_ms,
        "coarse_decimation": 4,
        "cog_overview_factors": [2],
        "lossless_mismatches": [],
    }


def test_a_coarse_read_without_overview_is_not_met(capsys):
    from bench.tiling_reads import print_targets, read_targets

    coarse = [t for t in read_targets(_reads(None)) if t["target"].startswith("coarse")]
    assert len(coarse) == 1, "the coarse target is dropped when the COG has no overview"
    assert coarse[0]["pass"] is False and coarse[0]["value"] is None
    assert "not measured" in coarse[0]["detail"]
    print_targets([{"name": "x", "targets": coarse}], 4)
    printed = capsys.readouterr().out
    assert "MISS  x    coarse" in printed and ": n/a (not measured" in printed
    # the control: with the overview measured, the same read passes
    coarse = [t for t in read_targets(_reads(2.0)) if t["target"].startswith("coarse")]
    assert [t["pass"] for t in coarse] == [True]


def _one_frame_rows(build_ms: float) -> list[dict[str, str]]:
    return [{"build_ms": str(build_ms), "triangles": "10", "gpu_ms": "1.0"}]


def test_tree_async_reports_no_figure_for_frames_it_did_not_measure(monkeypatch):
    from bench import tree_async

    monkeypatch.setattr(tree_async, "flythrough_rows", lambda *a, **k: _one_frame_rows(0.0))
    run = tree_async.fly("s.zarr", "background", 1, 1.0)
    # before: 0.0 ms "after the first frame" of a one-frame flight, and 0.0 ms as the median
    # of the frames that built when none did
    assert run["max_after_first_ms"] is None and run["median_building_ms"] is None
    assert tree_async.max_or_none([]) is None  # (the interim pictures' max px likewise)
    # the control: measured frames give their figures
    rows = _one_frame_rows(3.0) + _one_frame_rows(0.5)
    monkeypatch.setattr(tree_async, "flythrough_rows", lambda *a, **k: rows)
    run = tree_async.fly("s.zarr", "background", 2, 1.0)
    assert run["max_after_first_ms"] == 0.5 and run["median_building_ms"] == 1.75
    monkeypatch.setattr(tree_async, "flythrough_rows", lambda *a, **k: [])
    with pytest.raises(RuntimeError, match="no frame"):
        tree_async.fly("s.zarr", "background", 0, 1.0)


def test_texture_slots_one_frame_has_no_max_after_the_first(monkeypatch, tmp_path):
    import json
    import subprocess

    from bench import texture_slots

    def fake_run(cmd, **kw):
        doc = {"k": 2, "rows": [[8, 1, 1, 4.0, 10, 1.0]]}
        return subprocess.CompletedProcess(cmd, 0, stdout=json.dumps(doc), stderr="")

    monkeypatch.setattr(texture_slots.subprocess, "run", fake_run)
    got = texture_slots.fly(tmp_path / "s.zarr", "default", 1, (64, 64), 1.0)
    assert got["max_build_ms_after_first"] is None  # before: 0.0
    assert texture_slots._fmt(None, 2) == "-"


def test_ablation_and_sources_write_no_machine_path(tmp_path):
    """Before, ``bench/ablation.py`` wrote its default ``--out`` and the real DEM's path as they
    are (absolute) and ``bench/sources.py`` its default ``--out``."""
    import json

    from bench import ablation, sources
    from bench.common import REAL_HGT, RESULTS

    doc = {
        "args": {"out": str(RESULTS / "x.json")},  # (each script's default --out)
        "stores": {"real": {"note": f"{REAL_HGT} relabelled in metres"}},
    }
    for write in (lambda p: ablation._save(doc, p), lambda p: sources.write_result(p, doc)):
        out = tmp_path / "x.json"
        write(out)
        text = out.read_text()
        assert str(REPO) not in text and str(REAL_HGT.parent) not in text, text
        assert json.loads(text)["args"]["out"] == "./bench/results/x.json"
    # the control: the document itself names this machine's paths
    assert str(REPO) in json.dumps(doc)
