"""An array ``zarr.json`` edited so that it still parses made every read of it wrong with no
error (zarr decodes what it says): a big-endian ``bytes`` codec, ``crc32c`` removed (damage
then read unchecked), a ``.`` key separator (every chunk "missing", read as fill), another data
type. The format's chain is fixed (``tiler.array_check``): such a store is refused on open and
``verify`` names the array as damage ``--repair`` cannot mend. The controls: the pristine store,
and blosc settings changed (frames describe themselves: the same values are read).
"""

from __future__ import annotations

import json
import re
import shutil

import pytest
from demtools import fractal, write_dem

from tiler.errors import StoreCorruptError
from tiler.store import open_store
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    d = tmp_path_factory.mktemp("arrays")
    src = write_dem(d / "a.tif", fractal((129, 129), 4))
    return tile(src, d / "a.zarr", TileOptions(block_size=65, workers=1)).location.path


def _endian_big(md):
    md["codecs"][0]["configuration"]["endian"] = "big"


def _inner_endian_big(md):
    md["codecs"][0]["configuration"]["codecs"][0]["configuration"]["endian"] = "big"


def _no_crc(md):
    md["codecs"] = md["codecs"][:2]


def _dot_keys(md):
    md["chunk_key_encoding"]["configuration"]["separator"] = "."


def _float32(md):
    md["data_type"] = "float32"


def _fill(md):
    md["fill_value"] = 0


def _clevel(md):  # harmless: a blosc frame says how it was compressed
    md["codecs"][1]["configuration"]["clevel"] = 9
    md["codecs"][1]["configuration"]["shuffle"] = "noshuffle"


def _edited(pristine, tmp_path, array, edit):
    s = tmp_path / "s.zarr"
    shutil.copytree(pristine, s)
    f = s / array / "zarr.json"
    md = json.loads(f.read_text())
    edit(md)
    f.write_text(json.dumps(md))
    return s


@pytest.mark.parametrize(("array", "edit", "why"), [
    ("levels/6", _endian_big, "endian 'big'"),
    ("levels/2", _inner_endian_big, "inner bytes codec endian 'big'"),
    ("errors", _endian_big, "endian 'big'"),
    ("index/zmax", _endian_big, "endian 'big'"),
    ("levels/6", _no_crc, "not ['bytes', 'blosc', 'crc32c']"),
    ("levels/6", _dot_keys, "chunk key encoding"),
    ("index/zmin", _float32, "data type 'float32'"),
    ("levels/6", _fill, "fill value 0"),
])  # fmt: skip
def test_an_edited_array_chain_is_refused(pristine, tmp_path, array, edit, why):
    s = _edited(pristine, tmp_path, array, edit)
    with pytest.raises(StoreCorruptError, match=f"{array}.*{re.escape(why)}.*tile the DEM again"):
        open_store(s)
    rep = verify_store(s)
    assert not rep.ok and any(why in u and array in u for u in rep.unrepairable), rep.problems


def test_the_pristine_store_and_other_blosc_settings_are_read(pristine, tmp_path):
    assert verify_store(pristine).ok
    ref = open_store(pristine).read_block((1, 1))
    s = _edited(pristine, tmp_path, "levels/6", _clevel)
    assert verify_store(s).ok
    assert (open_store(s).read_block((1, 1)) == ref).all()


@pytest.mark.parametrize("group", ["levels", "index"])
@pytest.mark.parametrize("damage", ["delete", "garble"])
def test_a_damaged_group_metadata_is_found(pristine, tmp_path, group, damage):
    """``levels/zarr.json`` and ``index/zarr.json`` were never checked: deleted or garbled,
    ``verify`` said ok while ``xarray.open_zarr(store, group="levels")`` failed."""
    s = tmp_path / "s.zarr"
    shutil.copytree(pristine, s)
    f = s / group / "zarr.json"
    if damage == "delete":
        f.unlink()
    else:
        f.write_bytes(b"\x00garbage")
    rep = verify_store(s)
    assert any(f"group {group!r}" in u for u in rep.unrepairable), rep.problems
