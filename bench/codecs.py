"""Which blosc codec for the store's chunks: bytes and encode/decode time, measured in one run.

Usage::

    python bench/codecs.py [--block-size 1025] [--reps 3] [--synth 2049] [--threads 1,2]
                           [--out bench/results/codecs.json] [--quick]

Every input is cut into blocks and run through the tiler's ``process_block`` (the exact chunks a
store holds): per block, each level's residual array (uint16/uint32), the error fields (float16)
and, for blocks with nodata, the mask (bool). Each codec setting compresses every chunk of each
kind (``numcodecs.Blosc``, the library zarr's ``BloscCodec`` runs; ``blocksize=0`` as the store)
and decompresses it back (checked equal: lossless). Reported per input and kind: compressed
bytes, encode and decode time (median of ``--reps``), and over all inputs the totals relative to
the store's current setting (zstd level 5, byte shuffle, blosc's default threads).

Inputs: the real SRTM tiles N44W072.hgt and N42E001.hgt.zip (read through ``/vsizip/``), the
Longyearbyen float32 DEM (with nodata), and synthetic int16/float32 DEMs (``tiler.synth``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import numcodecs.blosc as blosc  # noqa: E402
import numpy as np  # noqa: E402
from numcodecs import Blosc  # noqa: E402

from bench.common import SHARED_DATA as DATA  # noqa: E402  ($TERRASTREAM_SHARED_DATA)
from bench.common import portable  # noqa: E402
from tiler.encoding import encoding_for  # noqa: E402
from tiler.layout import grid_side, parse_block_size  # noqa: E402
from tiler.static_error import default_cap  # noqa: E402
from tiler.synth import synth_array  # noqa: E402
from tiler.tile import BlockParams, process_block  # noqa: E402

DEFAULT_OUT = REPO / "bench" / "results" / "codecs.json"
CURRENT = {
    "levels": ("zstd", 5, "byte", 0),
    "errors": ("zstd", 5, "byte", 0),
    "mask": ("zstd", 5, "bit", 0),
}
SHUFFLE = {"byte": Blosc.SHUFFLE, "bit": Blosc.BITSHUFFLE, "none": Blosc.NOSHUFFLE}


def _inputs(synth: int) -> list[tuple[str, np.ndarray, float | None]]:
    import rasterio

    out = []
    for name, path in (
        ("N44W072", DATA / "N44W072.hgt"),
        ("N42E001", f"/vsizip/{DATA / 'N42E001.hgt.zip'}/N42E001.hgt"),
        ("Longyearbyen", DATA / "xdem_aligned_elev_Longyearbyen.tif"),
    ):
        if isinstance(path, Path) and not path.exists():
            continue
        with rasterio.open(path) as ds:
            out.append((name, ds.read(1), ds.nodata))
    for dt in ("int16", "float32"):
        out.append(
            (
                f"synth{synth}-{dt}",
                synth_array(slice(0, synth), slice(0, synth), synth, dtype=dt),
                None,
            )
        )
    return out


def _chunks(data: np.ndarray, nodata: float | None, k: int) -> dict[str, list[np.ndarray]]:
    """The store's chunks for one input, by kind: ``levels``, ``errors``, ``mask``."""
    side = grid_side(k)
    step = side - 1
    dt = data.dtype
    params = BlockParams(k, dt.name, f"uint{8 * dt.itemsize}", nodata, None, default_cap(k))
    kinds: dict[str, list[np.ndarray]] = {"levels": [], "errors": [], "mask": []}
    for r in range(0, max(1, data.shape[0] - 1), step):
        for c in range(0, max(1, data.shape[1] - 1), step):
            res = process_block(data[r : r + side, c : c + side], params)
            if not res.exists:
                continue
            kinds["levels"] += [np.ascontiguousarray(lv) for lv in res.levels]
            kinds["errors"].append(np.ascontiguousarray(res.errors))
            if res.mask is not None:
                kinds["mask"].append(np.ascontiguousarray(res.mask))
    return kinds


def _settings(quick: bool, only: str | None = None) -> list[tuple[str, int, str, int]]:
    """(codec, clevel, shuffle, blocksize) to try; ``only``: ``codec:level:shuffle:blocksize,...``
    (today's setting is always added)."""
    if only:
        out = [
            (c, int(lv), sh, int(bs)) for c, lv, sh, bs in (x.split(":") for x in only.split(","))
        ]
        return list(dict.fromkeys([*CURRENT.values(), *out]))
    return [(*s, 0) for s in _settings_grid(quick)]


def _settings_grid(quick: bool) -> list[tuple[str, int, str]]:
    if quick:
        return [("zstd", 1, "byte"), ("zstd", 5, "byte"), ("lz4", 5, "byte"), ("zstd", 5, "bit")]
    out = [("zstd", lvl, sh) for lvl in range(1, 10) for sh in ("byte", "bit")]
    out += [("lz4", lvl, sh) for lvl in (1, 5, 9) for sh in ("byte", "bit")]
    out += [("lz4hc", lvl, sh) for lvl in (1, 5, 9) for sh in ("byte", "bit")]
    return out


def _once(chunks: list[np.ndarray], setting: tuple[str, int, str]) -> tuple[int, float, float]:
    """Compress and decompress every chunk once: (bytes, encode s, decode s); lossless check."""
    cname, level, sh, bs = setting
    codecs = {
        ts: Blosc(cname=cname, clevel=level, shuffle=SHUFFLE[sh], blocksize=bs)
        for ts in {c.dtype.itemsize for c in chunks}
    }
    t0 = time.perf_counter()
    packed = [codecs[c.dtype.itemsize].encode(c) for c in chunks]
    t1 = time.perf_counter()
    back = [codecs[c.dtype.itemsize].decode(p) for c, p in zip(chunks, packed, strict=True)]
    t2 = time.perf_counter()
    for c, b in zip(chunks, back, strict=True):
        if bytes(b) != c.tobytes():
            raise AssertionError(f"{setting} is not lossless")
    return sum(len(p) for p in packed), t1 - t0, t2 - t1


def run(
    block_size: int, reps: int, synth: int, threads: list[int], quick: bool, only: str | None
) -> dict:
    """Measure every setting on every input, repetitions interleaved; the JSON-able result."""
    k = parse_block_size(block_size)
    inputs = _inputs(synth)
    encoding = {name: encoding_for(arr.dtype) for name, arr, _ in inputs}
    data = [(name, _chunks(arr, nd, k)) for name, arr, nd in inputs]
    acc: dict[tuple, dict[str, Any]] = {}
    for rep in range(reps):
        for nthreads in threads:
            blosc.set_nthreads(nthreads)
            for setting in _settings(quick, only):
                for name, kinds in data:
                    for kind, chunks in kinds.items():
                        if not chunks:
                            continue
                        nbytes, te, td = _once(chunks, setting)
                        a = acc.setdefault(
                            (name, kind, *setting, nthreads),
                            {
                                "bytes": nbytes,
                                "raw_bytes": sum(c.nbytes for c in chunks),
                                "enc": [],
                                "dec": [],
                            },
                        )
                        a["enc"].append(te)
                        a["dec"].append(td)
        print(f"  repetition {rep + 1}/{reps} done", flush=True)
    rows = []
    for (name, kind, codec, level, sh, bs, th), a in acc.items():
        rows.append(
            {
                "input": name,
                "encoding": encoding[name],
                "kind": kind,
                "codec": codec,
                "level": level,
                "shuffle": sh,
                "blocksize": bs,
                "threads": th,
                "bytes": a["bytes"],
                "raw_bytes": a["raw_bytes"],
                "encode_s": statistics.median(a["enc"]),
                "decode_s": statistics.median(a["dec"]),
            }
        )
    return {"rows": rows, "summary": _summary(rows), "by_encoding": _by_encoding(rows)}


def _by_encoding(rows: list[dict]) -> list[dict]:
    """Per (encoding, kind, setting, threads): bytes and times summed over its inputs."""
    tot: dict[tuple, dict[str, float]] = {}
    for r in rows:
        key = (r["encoding"], r["kind"], r["codec"], r["level"], r["shuffle"], r["blocksize"])
        t = tot.setdefault((*key, r["threads"]), {"bytes": 0, "encode_s": 0.0, "decode_s": 0.0})
        for f in t:
            t[f] += r[f]
    keys = ("encoding", "kind", "codec", "level", "shuffle", "blocksize", "threads")
    return [dict(zip(keys, key, strict=True), **t) for key, t in tot.items()]


def _print_by_encoding(rows: list[dict]) -> None:
    print("\nper encoding (sums over its inputs):")
    print(f"  {'encoding':12s} {'kind':6s} codec  lvl shuf blockKiB thr   bytes    enc_ms  dec_ms")
    for r in sorted(rows, key=lambda r: (r["encoding"], r["kind"], r["bytes"])):
        print(
            f"  {r['encoding']:12s} {r['kind']:6s} {r['codec']:6s} {r['level']:3d} "
            f"{r['shuffle']:4s} {r['blocksize'] // 1024:8d} {r['threads']:3d} {r['bytes']:9d} "
            f"{1e3 * r['encode_s']:8.1f} {1e3 * r['decode_s']:7.1f}"
        )


def _summary(rows: list[dict]) -> list[dict]:
    """Per (setting, threads, kind) totals over all inputs, relative to the current setting."""
    keyf = lambda r: (r["codec"], r["level"], r["shuffle"], r["blocksize"], r["threads"], r["kind"])  # noqa: E731
    tot: dict[tuple, dict[str, float]] = {}
    for r in rows:
        t = tot.setdefault(keyf(r), {"bytes": 0, "raw_bytes": 0, "encode_s": 0.0, "decode_s": 0.0})
        for f in t:
            t[f] += r[f]
    out = []
    for key, t in tot.items():
        codec, level, sh, bs, th, kind = key
        base = tot.get((*CURRENT[kind], th, kind))
        if base is None:
            base = t
        out.append(
            {
                "codec": codec,
                "level": level,
                "shuffle": sh,
                "blocksize": bs,
                "threads": th,
                "kind": kind,
                **t,
                "size_vs_current": t["bytes"] / base["bytes"],
                "encode_vs_current": t["encode_s"] / base["encode_s"],
                "decode_vs_current": t["decode_s"] / base["decode_s"],
                "bytes_x_time_vs_current": (t["bytes"] * (t["encode_s"] + t["decode_s"]))
                / (base["bytes"] * (base["encode_s"] + base["decode_s"])),
            }
        )
    return out


SIZE_SLACK = 1.02  # the store is near its size target (<= 0.6x the COG with overviews)


def recommend(summary: list[dict]) -> dict[str, dict]:
    """Per kind: the fastest (encode + decode) setting no more than 2 % larger than today's."""
    out = {}
    for kind in ("levels", "errors", "mask"):
        ok = [r for r in summary if r["kind"] == kind and r["size_vs_current"] <= SIZE_SLACK]
        if ok:
            out[kind] = min(ok, key=lambda r: r["encode_s"] + r["decode_s"])
    return out


def _print(summary: list[dict]) -> None:
    for kind in ("levels", "errors", "mask"):
        rows = sorted(
            (r for r in summary if r["kind"] == kind), key=lambda r: r["bytes_x_time_vs_current"]
        )
        if not rows:
            continue
        print(
            f"\n{kind}: {'codec':6s} lvl shuf blockKiB thr   MB      size  enc_ms  dec_ms  "
            "enc  dec  BxT"
        )
        for r in rows:
            print(
                f"{'':{len(kind) + 2}s}{r['codec']:6s} {r['level']:3d} {r['shuffle']:4s} "
                f"{r['blocksize'] // 1024:8d} {r['threads']:3d} {r['bytes'] / 2**20:6.2f} "
                f"{r['size_vs_current']:6.3f} "
                f"{1e3 * r['encode_s']:7.1f} {1e3 * r['decode_s']:7.1f} "
                f"{r['encode_vs_current']:4.2f} {r['decode_vs_current']:4.2f} "
                f"{r['bytes_x_time_vs_current']:4.2f}"
            )


def main(argv: list[str] | None = None) -> int:
    """Run, print the tables (sorted by bytes x time), write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--block-size", type=int, default=1025)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--synth", type=int, default=2049)
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--quick", action="store_true", help="4 settings, 1 rep, 513 synth")
    ap.add_argument(
        "--only", help="settings codec:clevel:shuffle:blocksize,... (e.g. zstd:4:byte:0)"
    )
    a = ap.parse_args(argv)
    threads = [int(t) for t in a.threads.split(",")]
    res = run(
        a.block_size,
        1 if a.quick else a.reps,
        513 if a.quick else a.synth,
        threads,
        a.quick,
        a.only,
    )
    _print(res["summary"])
    _print_by_encoding(res["by_encoding"])
    res["recommended"] = recommend(res["summary"])
    print(f"\nfastest setting at most {SIZE_SLACK - 1:.0%} larger than today's, per kind:")
    for kind, r in res["recommended"].items():
        print(
            f"  {kind:7s} {r['codec']} clevel={r['level']} shuffle={r['shuffle']} "
            f"blocksize={r['blocksize']} "
            f"threads={r['threads']}: size x{r['size_vs_current']:.3f}, encode "
            f"x{r['encode_vs_current']:.2f}, decode x{r['decode_vs_current']:.2f}"
        )
    res.update(
        {
            "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
            "command": " ".join(["bench/codecs.py", *(argv if argv is not None else sys.argv[1:])]),
            "block_size": a.block_size,
        }
    )
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(portable(res), indent=1) + "\n")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
