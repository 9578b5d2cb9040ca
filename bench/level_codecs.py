"""Per level of a store: compressed bytes and the decompression time of one chunk, for the
store's codec and candidates (issue 14, reads): where a whole-block read's blosc time goes.

Usage::

    python bench/level_codecs.py STORE [STORE ...] [--blocks 4] [--reps 200]
                                 [--out bench/results/level_codecs.json]

Per store, the stored values of each level of its first ``--blocks`` blocks
(``TerrainStore.read_levels_raw``) are compressed with each candidate — zstd 3 (the store's
codec), lz4hc 9, lz4 5 — with the store's shuffle for that level (bit shuffle where
``meta.compressor`` says so, 1 MiB blosc blocks otherwise, as ``tiler.schema.compressor``), and
decompressed into a kept array ``--reps`` times (``numcodecs.blosc.decompress``, what the direct
reads call; checked equal to the input). Reported per level: the bytes summed over the blocks and
the median µs of one decompression, averaged over the blocks. Prints a table and writes JSON.
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
                blocksize=0 if bits else LEVEL_BLOCKSIZE,
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
                us.append(_median_us(reps if raw.size < 100_000 else max(10, reps // 8),
                                     nblosc.decompress, frame, out))  # fmt: skip
            row[f"{cname}{clevel}_bytes"] = nbytes
            row[f"{cname}{clevel}_us"] = statistics.mean(us)
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
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"machine": machine_info(), "args": portable(vars(args)), "rows": rows}
    out.write_text(json.dumps(doc, indent=1))
    print(f"# wrote {out}")


if __name__ == "__main__":
    main()
