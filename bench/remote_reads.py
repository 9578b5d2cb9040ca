"""Reads of a remote store (issue 14, "one request per block"): zarr's reads against the
direct ones (``tiler.chunkread_remote``: shard indexes kept, a block's levels asked for at once).

Usage::

    python bench/remote_reads.py [STORE ...] [--latency-ms 20] [--blocks 8] [--rounds 3]
                                 [--frames 30] [--out PATH]

Each STORE (default: ``bench/work/prefetch/n44w072_eqc_b257.zarr`` and ``bench/work/s4097.zarr``)
is served by a loopback HTTP server in a child process that answers every request after
``--latency-ms`` (a network's round trip). In one process, alternating each round, a reader
through zarr (``TerrainStore(..., direct_reads=False)``, the code before) and the direct one
read ``--blocks`` blocks: a whole block (``read_levels_raw(b, k)``), the coarse levels
(``k - 2``), the finest level alone, each timed (median ms) and its requests counted (every
``get`` of the zarr store: exact); each reader is opened afresh per round, so its first block
also reads its shards' indexes. Then a streaming session over each reader warms up for the
first camera of the default fly-through and flies ``--frames`` frames waiting for each
(seconds, requests). Prints a table and writes ``bench/results/remote_reads.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import (  # noqa: E402
    RESULTS,
    WORK,
    count_requests,
    ensure_store,
    git_head,
    machine_info,
    portable,
)
from bench.prefetch_stores import http_server  # noqa: E402

DEFAULT_STORES = [WORK / "prefetch" / "n44w072_eqc_b257.zarr", WORK / "s4097.zarr"]


def _reads(url: str, direct: bool, n_blocks: int) -> dict:
    from tiler.store import TerrainStore

    s = TerrainStore(url, direct_reads=direct)
    assert s.direct_reads is direct
    keys = count_requests(s)
    blocks = list(s.blocks())[:n_blocks]
    out = {}
    for what, fn in (
        ("block", lambda b: s.read_levels_raw(b, s.k)),
        ("coarse", lambda b: s.read_levels_raw(b, s.k - 2)),
        ("finest", lambda b: s.read_level_raw(b, s.k)),
    ):
        ms, reqs = [], []
        for b in blocks:
            n0, t0 = len(keys), time.perf_counter()
            fn(b)
            ms.append((time.perf_counter() - t0) * 1e3)
            reqs.append(len(keys) - n0)
        out[what] = {"ms": ms, "median_ms": statistics.median(ms), "requests": reqs}
    return out


def _session(url: str, direct: bool, frames: int) -> dict:
    from streamer.run import make_path
    from streamer.session import open_session
    from tiler.store import TerrainStore

    s = TerrainStore(url, direct_reads=direct)
    keys = count_requests(s)
    cams = make_path(s, "default", frames=frames, viewport=(640, 480))
    with open_session(s, budget_mb=256, workers=4) as sess:
        t0 = time.perf_counter()
        sess.warm_up(cams[0])
        warm = time.perf_counter() - t0
        n_warm = len(keys)
        t0 = time.perf_counter()
        for cam in cams:
            sess.update(cam, wait=True)
        fly = time.perf_counter() - t0
    return {"warm_up_s": warm, "warm_up_requests": n_warm, "flight_s": fly,
            "flight_requests": len(keys) - n_warm}  # fmt: skip


def _line(row: dict, frames: int) -> str:
    reads = " ".join(
        f"{w} {row[w]['median_ms']:6.1f} ms/{statistics.median(row[w]['requests']):3.0f} req"
        for w in ("block", "coarse", "finest")
    )
    return (
        f"{row['store']:24} r{row['round']} {'direct' if row['direct'] else 'zarr  '} {reads}"
        f" | warm-up {row['warm_up_s']:5.2f} s/{row['warm_up_requests']} req, {frames} frames"
        f" {row['flight_s']:5.2f} s/{row['flight_requests']} req"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stores", nargs="*", type=Path, default=DEFAULT_STORES)
    ap.add_argument("--latency-ms", type=float, default=20.0)
    ap.add_argument("--blocks", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--out", type=Path, default=RESULTS / "remote_reads.json")
    a = ap.parse_args(argv)
    rows = []
    for store in a.stores:
        ensure_store(store)  # the default stores are made on first use
        if not store.exists():
            print(f"# {portable(str(store))} is missing: skipped (bench/prefetch.py makes it)")
            continue
        store = store.resolve()
        with http_server(store.parent, a.latency_ms / 1000.0) as base:
            url = f"{base}/{store.name}"
            for rnd in range(a.rounds):
                order = (False, True) if rnd % 2 == 0 else (True, False)
                for direct in order:
                    row = {"store": store.name, "round": rnd + 1, "direct": direct}
                    row |= _reads(url, direct, a.blocks) | _session(url, direct, a.frames)
                    rows.append(row)
                    print(_line(row, a.frames), flush=True)
    if not rows:  # (the committed JSON is not replaced by an empty one)
        print("error: no store was measured (see the # ... skipped lines)", file=sys.stderr)
        return 1
    a.out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"machine": machine_info(), "git_head": git_head(), "latency_ms": a.latency_ms,
           "blocks": a.blocks, "frames": a.frames, "rows": rows}  # fmt: skip
    a.out.write_text(json.dumps(portable(doc), indent=1))
    print(f"# wrote {portable(str(a.out))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
