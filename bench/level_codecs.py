"""Per level of a store: compressed bytes and the decompression time of one chunk, for the
store's codec and candidates (issue 14, reads): where a whole-block read's blosc time goes.

Usage::

    python bench/level_codecs.py STORE [STORE ...] [--blocks 4] [--reps 200]
                                 [--out bench/results/level_codecs.json]

Per store, the stored values of each level of its first ``--blocks`` blocks
(``TerrainStore.read_levels_raw``) are compressed with each candidate — zstd 3 (the store's
codec), lz4hc 9, lz4 5 — with the store's shuffle for that level (bit shuffle where
``meta.compressor`` says so) and its 1 MiB blosc blocks (``tiler.schema.LEVEL_BLOCKSIZE``, what
``layout_specs`` writes), and decompressed into a kept array ``--reps`` times
(``numcodecs.blosc.decompress``, what the direct reads call; checked equal to the input).
Reported per level: the bytes summed over the blocks and the median µs of one decompression,
averaged over the blocks. Prints a table and writes JSON.

Per block of those, for each bit-shuffled level (``shuffles`` in the JSON, the second table):
the block's terrain fraction (its mask), the shuffle of the stored frame, and the bytes and µs of
zstd 3 with bit and with byte shuffle, and which one the sparse-block rule
(``tiler.schema.is_sparse``, ``keep_byte_frame``) keeps.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np  # noqa: E402
from numcodecs import Blosc  # noqa: E402
from numcodecs import blosc as nblosc  # noqa: E402

from bench.common import RESULTS, machine_info, portable  # noqa: E402

CANDIDATES = (("zstd", 3), ("lz4hc", 9), ("lz4", 5))  # the first is the store's (tiler.schema)


def _median_us(reps: int, fn, *args) -> float:
    """Median µs of ``reps`` calls ``fn(*args)`` after a few warm-up calls."""
    for _ in range(min(20, reps)):
        fn(*args)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn(*args)
        ts.append(time.perf_counter() - t0)
    return 1e6 * statistics.median(ts)


def measure(path: str, blocks: int, reps: int) -> list[dict]:
    """Rows ``{store, level, values, <codec>_bytes, <codec>_us}`` of one store."""
    from tiler.schema import LEVEL_BLOCKSIZE, level_bits
    from tiler.store import open_store

    store = open_store(path)
    picked = list(store.blocks())[:blocks]
    if not picked:
        raise SystemExit(f"{path}: the store has no blocks")
    raws = [[np.array(v) for v in store.read_levels_raw(b, store.k)] for b in picked]
    rows = []
    for level in range(store.k + 1):
        bits = level_bits(store.meta.compressor, level)
        row = {"store": Path(path).name, "level": level, "values": int(raws[0][level].size)}
        for cname, clevel in CANDIDATES:
            codec = Blosc(
                cname=cname,
                clevel=clevel,
                shuffle=Blosc.BITSHUFFLE if bits else Blosc.SHUFFLE,
                blocksize=LEVEL_BLOCKSIZE,
            )
            nbytes, us = 0, []
            for per_block in raws:
                raw = per_block[level]
                frame = codec.encode(raw)
                out = np.empty_like(raw)
                nblosc.decompress(frame, out)
                if not np.array_equal(out, raw):
                    raise RuntimeError(f"{cname} did not give level {level} back")
                nbytes += len(frame)
                us.append(_median_us(_reps_for(raw, reps), nblosc.decompress, frame, out))
            row[f"{cname}{clevel}_bytes"] = nbytes
            row[f"{cname}{clevel}_us"] = statistics.mean(us)
        rows.append(row)
    return rows


def _reps_for(raw: np.ndarray, reps: int) -> int:
    return reps if raw.size < 100_000 else max(10, reps // 8)


def shuffles(path: str, blocks: int, reps: int) -> list[dict]:
    """Per block and bit-shuffled level: terrain fraction, stored shuffle, bit vs byte shuffle
    (bytes, µs of one decompression) and the frame the sparse-block rule keeps."""
    from tiler.chunkread import check_crc
    from tiler.schema import (
        DEFAULT_CLEVEL,
        LEVEL_BLOCKSIZE,
        SPARSE_BYTE_SLACK,
        SPARSE_TERRAIN_MAX,
        is_sparse,
        keep_byte_frame,
    )
    from tiler.store import open_store

    store = open_store(path)
    bits = store.meta.compressor.get("bitshuffle_levels") or []
    rows = []
    for b in list(store.blocks())[:blocks]:
        mask = store.read_mask(b)
        terrain = int(np.count_nonzero(mask))
        raws = store.read_levels_raw(b, store.k)
        sparse = is_sparse(terrain, mask.size, SPARSE_TERRAIN_MAX)
        for level in bits:
            raw = np.ascontiguousarray(raws[level])
            key = f"levels/{level}/c/{b[0]}/{b[1]}/0"
            stored = store.location.get_bytes(key)
            flag = nblosc._cbuffer_metainfo(check_crc(stored, key))[1] if stored else None
            row = {
                "store": Path(path).name,
                "block": list(b),
                "level": level,
                "terrain": terrain / mask.size,
                "stored_shuffle": {1: "byte", 2: "bit"}.get(flag, flag),
            }
            for name, shuffle in (("bit", Blosc.BITSHUFFLE), ("byte", Blosc.SHUFFLE)):
                codec = Blosc("zstd", DEFAULT_CLEVEL, shuffle, LEVEL_BLOCKSIZE)
                frame = codec.encode(raw)
                out = np.empty_like(raw)
                nblosc.decompress(frame, out)
                if not np.array_equal(out, raw):
                    raise RuntimeError(f"{name} shuffle did not give level {level} back")
                row[f"{name}_bytes"] = len(frame)
                row[f"{name}_us"] = _median_us(_reps_for(raw, reps), nblosc.decompress, frame, out)
            keep = sparse and keep_byte_frame(
                row["bit_bytes"], row["byte_bytes"], SPARSE_BYTE_SLACK
            )
            row["rule_keeps"] = "byte" if keep else "bit"
            rows.append(row)
    return rows


def main() -> None:
    """Measure the stores, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stores", nargs="+")
    ap.add_argument("--blocks", type=int, default=4)
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--out", default=str(RESULTS / "level_codecs.json"))
    args = ap.parse_args()
    rows = [r for p in args.stores for r in measure(p, args.blocks, args.reps)]
    names = [f"{c}{lv}" for c, lv in CANDIDATES]
    print("store level values " + " ".join(f"{n}_bytes {n}_us" for n in names))
    for r in rows:
        cells = " ".join(f"{r[n + '_bytes']} {r[n + '_us']:.1f}" for n in names)
        print(f"{r['store']} {r['level']} {r['values']} {cells}")
    per_block = [r for p in args.stores for r in shuffles(p, args.blocks, args.reps)]
    print("store block level terrain stored bit_bytes bit_us byte_bytes byte_us rule_keeps")
    for r in per_block:
        print(
            f"{r['store']} {tuple(r['block'])} {r['level']} {r['terrain']:.3f} "
            f"{r['stored_shuffle']} {r['bit_bytes']} {r['bit_us']:.1f} {r['byte_bytes']} "
            f"{r['byte_us']:.1f} {r['rule_keeps']}"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "machine": machine_info(),
        "args": portable(vars(args)),
        "rows": rows,
        "shuffles": per_block,
    }
    out.write_text(json.dumps(portable(doc), indent=1))
    print(f"# wrote {out}")


if __name__ == "__main__":
    main()
