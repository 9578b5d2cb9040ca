"""``verify`` and ``tile --repair`` through the CLI: quiet on a good store, loud on a bad one."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from demtools import fractal
from typer.testing import CliRunner

from cli.main import app

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tiler"))
from storetools import chunk_files, flip_bit  # noqa: E402

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture
def store(dem_factory, tmp_path):
    src = dem_factory(fractal((90, 70), 5))
    dst = tmp_path / "s.zarr"
    r = run("tile", src, dst, "--block-size", "129", "--workers", "1")
    assert r.exit_code == 0, r.output
    return src, dst


def test_verify_is_quiet_on_a_good_store(store):
    src, dst = store
    r = run("verify", dst, "--source", src)
    assert r.exit_code == 0, r.output
    assert ": ok;" in r.output and "crc32c checksums" in r.output and "source digests" in r.output


def test_verify_names_a_flipped_bit_and_repair_mends_it(store):
    src, dst = store
    chunk = chunk_files(dst, "levels/6")[0]  # unsharded from level 6: one chunk per block
    before = chunk.read_bytes()
    flip_bit(chunk, np.random.default_rng(1))  # the positive control: break one chunk
    r = run("verify", dst)
    assert r.exit_code == 1, r.output
    assert "checksum" in r.output and "levels/6" in r.output and "--repair" in r.output
    r = run("verify", dst, "--json")
    assert r.exit_code == 1 and len(json.loads(r.output)["bad_blocks"]) == 1
    r = run("tile", src, dst, "--block-size", "129", "--repair")
    assert r.exit_code == 0, r.output
    assert chunk.read_bytes() == before  # recomputed byte for byte
    assert run("verify", dst).exit_code == 0


def test_repair_takes_the_store_s_block_size_when_not_given(dem_factory, tmp_path):
    """`tile SRC STORE --repair` of a store tiled with `--block-size 33` was refused as
    "another job (block_size: store has 33, this run has 129)"; the repair takes the store's
    size when none is given. Control: another size given is still refused."""
    src = str(dem_factory(fractal((90, 70), 5)))
    dst = tmp_path / "b.zarr"
    assert run("tile", src, dst, "--block-size", "33").exit_code == 0
    chunk = chunk_files(dst, "levels/5")[0]
    before = chunk.read_bytes()
    flip_bit(chunk, np.random.default_rng(2))
    r = run("tile", src, dst, "--repair", "--block-size", "65")
    assert r.exit_code == 2 and "block_size: store has 33" in r.output, r.output
    r = run("tile", src, dst, "--repair")
    assert r.exit_code == 0, r.output
    assert chunk.read_bytes() == before and run("verify", dst).exit_code == 0


def test_verify_of_a_missing_store_is_a_usage_error(tmp_path):
    r = run("verify", tmp_path / "nope.zarr")
    assert r.exit_code == 2 and "nope.zarr" in r.output


def test_verify_does_not_advise_a_repair_that_refuses(store):
    """Damaged array metadata is beyond --repair (it refuses, naming it): verify says to tile
    again with --overwrite instead; the bad-chunk case above is the control (it says --repair)."""
    src, dst = store
    (dst / "levels" / "3" / "zarr.json").write_text("[1, 2]")
    r = run("verify", dst)
    assert r.exit_code == 1, r.output
    assert "levels/3" in r.output and "--overwrite" in r.output and "--repair`" not in r.output
    assert "problem(s) --repair cannot mend" in r.output
    r = run("tile", src, dst, "--block-size", "129", "--repair")
    assert r.exit_code == 1 and "cannot be repaired" in r.output
    r = run("tile", src, dst, "--block-size", "129", "--overwrite")
    assert r.exit_code == 0, r.output
    assert run("verify", dst).exit_code == 0


def test_verify_counts_a_damaged_table_and_repair_rewrites_it(store):
    src, dst = store
    table = dst / "order_index" / "c" / "0" / "0"
    before = table.read_bytes()
    table.unlink()
    r = run("verify", dst)
    assert r.exit_code == 1 and "1 damaged index table(s)" in r.output and "--repair" in r.output
    r = run("tile", src, dst, "--block-size", "129", "--repair")
    assert r.exit_code == 0, r.output
    assert table.read_bytes() == before
    r = run("verify", dst)
    assert r.exit_code == 0 and "damaged index table" not in r.output


def test_verify_of_an_interrupted_store_says_to_finish_it(dem_factory, tmp_path, monkeypatch):
    """An interrupted tiling is unfinished, not damaged: verify says to rerun the same command
    (not --repair) and does not report the index the finishing step has not written yet as
    wrong windows; the advice works. (The finished stores above are the control.)"""
    import tiler.tile as tile_mod
    from tiler.errors import TilingInterrupted
    from tiler.tile import TileOptions, tile

    src, dst = dem_factory(fractal((90, 70), 5)), tmp_path / "u.zarr"
    real, count = tile_mod.process_block, [0]

    def interrupted(window, params):
        count[0] += 1
        if count[0] > 2:
            raise KeyboardInterrupt("simulated Ctrl-C")
        return real(window, params)

    monkeypatch.setattr(tile_mod, "process_block", interrupted)
    with pytest.raises(TilingInterrupted):
        tile(src, dst, TileOptions(block_size=33, workers=1, executor="threads"))
    monkeypatch.undo()
    r = run("verify", dst)
    assert r.exit_code == 1, r.output
    assert "unfinished (tiling)" in r.output and "rerun the same" in r.output
    assert "--repair" not in r.output and "wrong window" not in r.output
    assert json.loads(run("verify", dst, "--json").output)["state"] == "tiling"
    # the written chunks are still checked: a flipped bit in one is named (the control)
    damaged = tmp_path / "damaged.zarr"
    shutil.copytree(dst, damaged)
    flip_bit(chunk_files(damaged, "errors")[0], np.random.default_rng(2))
    r = run("verify", damaged)
    assert r.exit_code == 1 and "checksum: errors block" in r.output, r.output
    assert "1 bad block(s)" in r.output and "then `--repair`" in r.output
    # --repair of an unfinished tiling finishes it as the same command would (resumes)
    resumed = tmp_path / "resumed.zarr"
    shutil.copytree(dst, resumed)
    r = run("tile", src, resumed, "--block-size", "33", "--workers", "1", "--repair", "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.output.strip().splitlines()[-1])["blocks_resumed"] == 2
    assert run("verify", resumed).exit_code == 0
    r = run("tile", src, dst, "--block-size", "33", "--workers", "1")
    assert r.exit_code == 0, r.output
    assert run("verify", dst).exit_code == 0
    files = {  # the two finished stores, byte for byte (both resumed the same run)
        d: {str(f.relative_to(d)): f.read_bytes() for f in d.rglob("*") if f.is_file()}
        for d in (dst, resumed)
    }
    assert files[dst] == files[resumed] and len(files[dst]) > 20
