"""The root metadata's own checksum (``tiler.meta.sealed``): an edit or a flipped bit in the
georeferencing, CRS, nodata or value range of a store's ``zarr.json`` is reported by every
reader and by ``verify`` (positive controls, one per field), beside an intact store and an older
store without the checksum, which still open and verify."""

from __future__ import annotations

import json

import numpy as np
import pytest
from demtools import fractal
from storetools import chunk_files, flip_bit
from typer.testing import CliRunner

from cli.main import app
from tiler.errors import StoreCorruptError
from tiler.meta import CHECKSUM_KEY
from tiler.schema import ATTR
from tiler.store import open_store
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store


@pytest.fixture
def store(dem_factory, tmp_path):
    dem = fractal((40, 40), 1).astype(np.float32)
    dem[:5, :5] = -9999.0
    path = tmp_path / "s.zarr"
    tile(dem_factory(dem, nodata=-9999.0), path, TileOptions(block_size=17))
    return path


def _edit(path, change) -> None:
    """Apply ``change`` to the root attribute of ``path``'s ``zarr.json`` (checksum kept)."""
    doc_path = path / "zarr.json"
    doc = json.loads(doc_path.read_text())
    change(doc["attributes"][ATTR])
    doc_path.write_text(json.dumps(doc))


def _flip_digit(text: str) -> str:
    """``text`` with its last digit changed (a one-character damage of a number)."""
    i = max(i for i, ch in enumerate(text) if ch.isdigit())
    return text[:i] + str((int(text[i]) + 1) % 10) + text[i + 1 :]


def test_an_intact_store_is_sealed_and_verifies(store):
    attr = json.loads((store / "zarr.json").read_text())["attributes"][ATTR]
    assert attr[CHECKSUM_KEY].startswith("blake2b-128:")
    rep = verify_store(str(store))
    assert rep.ok and rep.metadata_checksummed
    assert open_store(str(store)).meta.nodata == -9999.0


EDITS = {
    "geotransform": lambda a: a["geotransform"].__setitem__(2, a["geotransform"][2] + 10_000.0),
    "nodata": lambda a: a.update(nodata=-9998.0),
    "crs": lambda a: a.update(crs_wkt=_flip_digit(a["crs_wkt"])),
    "value_range": lambda a: a.update(value_range=[a["value_range"][0], a["value_range"][1] + 1]),
    "complete": lambda a: a.update(complete=not a["complete"]),
}


@pytest.mark.parametrize("field", sorted(EDITS))
def test_an_edited_field_is_reported_by_readers_and_verify(store, field):
    _edit(store, EDITS[field])
    with pytest.raises(StoreCorruptError, match="does not match its checksum"):
        open_store(str(store))
    rep = verify_store(str(store))
    assert not rep.ok and "does not match its checksum" in rep.problems[0].message
    res = CliRunner().invoke(app, ["info", str(store)])
    assert res.exit_code == 1 and "does not match its checksum" in res.output


def test_an_older_store_without_the_checksum_still_opens(store):
    _edit(store, lambda a: a.pop(CHECKSUM_KEY))
    s = open_store(str(store))
    assert s.meta.nodata == -9999.0 and CHECKSUM_KEY not in s.meta.extra
    rep = verify_store(str(store))
    assert rep.ok and not rep.metadata_checksummed
    res = CliRunner().invoke(app, ["verify", str(store)])
    assert res.exit_code == 0 and "the root metadata has no checksum" in res.output
    # and without it an edit goes unseen: what the checksum is for (the control)
    _edit(store, EDITS["nodata"])
    assert open_store(str(store)).meta.nodata == -9998.0 and verify_store(str(store)).ok


def test_resealed_on_every_write_of_the_tiler(store, dem_factory, tmp_path):
    """The tiler rewrites the attribute as it goes (states, completion, repair): each write is
    sealed again, so a resumed or repaired store verifies."""
    src = tmp_path / "dem.tif"
    tile(src, store, TileOptions(block_size=17, overwrite=True))
    assert verify_store(str(store)).ok
    flip_bit(chunk_files(store, "levels/4")[0], np.random.default_rng(0))
    assert not verify_store(str(store)).ok  # (the damage the repair mends)
    tile(src, store, TileOptions(block_size=17, repair=True))
    rep = verify_store(str(store))
    assert rep.ok and rep.metadata_checksummed


def test_a_store_replaced_while_verified_is_an_error(store, dem_factory, tmp_path, monkeypatch):
    """Every chunk passes its checksum, but half could be another build's: verify says the
    store changed instead of 'ok' (the control: the same verify without the swap is ok)."""
    import tiler.verify as verify_mod
    from tiler.errors import StoreChangedError

    other = dem_factory(fractal((40, 40), 2).astype(np.float32), name="other.tif")
    real = verify_mod._check_index

    def then_swap(*args, **kw):
        out = real(*args, **kw)
        tile(other, store, TileOptions(block_size=17, overwrite=True))
        return out

    assert verify_store(str(store)).ok
    monkeypatch.setattr(verify_mod, "_check_index", then_swap)
    with pytest.raises(StoreChangedError, match="while it was verified"):
        verify_store(str(store))
