"""Prefetch benchmark: real-time fly-throughs with frustum-extension prefetching on and off.

Usage::

    python bench/prefetch.py [--quick] [--frames 10000] [--short-frames 1200]
                             [--speeds 0.5,1,2] [--latencies 0,20] [--stores synth,real,real-deg]
                             [--workers 16] [--compare-workers 4] [--no-http]
                             [--budget-mb 256] [--tau 1]
                             [--no-plot] [--out bench/results/prefetch.json]

Each run flies ``streamer.run.make_path(store, "default", speed=edge * speed)`` (``edge`` = one
block edge in world units, so ``--speeds`` are block edges per second) at 60 fps in real time
through a :class:`streamer.session.Session` and records the session summary plus figures derived
from the per-frame :class:`~streamer.session.FrameStats`.

The matrix: for every store, the *headline* configurations (speed 1 edge/s, 20 ms latency,
prefetch on and off) fly ``--frames`` frames; every other (speed, latency, prefetch) combination
flies ``--short-frames``. Latency is ``SessionConfig.latency_ms`` (a sleep in the loader thread
before every store request); in addition one headline run reads the synthetic store over HTTP
from a loopback server (``tests/rangeserver.py``, run in a child process so it does not share
this process's GIL) that sleeps 20 ms before answering every request, and one short run repeats
the synthetic headline configuration with ``--compare-workers`` loader threads.

Stores: ``synth`` is the 16385^2 int16 synthetic DEM (``terrastream synth --seed 1`` when
``tiler.synth.synth_dem`` exists, else the existing ``bench/work/synth_16385_seed0_int16.tif``)
tiled with 1025^2 blocks; ``real`` is SRTM N44W072 (1201^2, 3 arc-seconds) tiled with 257^2
blocks after relabelling its lon/lat grid in metres (an equirectangular projection at its middle
latitude: the same samples, no resampling, 66.2 m x 92.8 m spacing), because the streamer treats
x/y and z as one unit and the EPSG:4326 store has degrees across and metres up; ``real-deg`` is
that EPSG:4326 store as tiled, for comparison (one short run by default).

Pacing is ``run_flythrough``'s: ``Session.warm_up(cameras[0])`` (loads what the plan for the
first pose wants, reported as warm-up ms / bytes: Qiu's "frame 1"), then frame ``i`` is due
``i / fps`` after the warm-up and frame 0 waits for its data. The loop is re-implemented here
(same calls) to see each ``Frame.blocks`` and the cache between frames.

Bytes are decoded level bytes (the session's unit). "needed" is the sum over frames of each
frame's needed bytes (``summary()['needed_bytes']``, what ``terrastream stream`` reports);
"used" is the distinct (block, level) bytes frames drew (``summary()['used_bytes']``), so
``loaded / used`` also counts levels evicted and loaded again on a later pass over the same
ground; :class:`LoadLedger` watches the cache after every frame and reports ``loaded / bytes of
loads drawn before their eviction`` as well (both are checked). Stalled blocks are classified
(new in view or refining; within one block edge of the eye or not), and Python garbage
collections during ``update`` are counted against frames whose update CPU exceeds 2 ms.

Stalls are counted over Qiu's triangle (the session's ``culling="qiu"``) and, with
``account_hull=True``, over the frustum hull the renderer draws (a second plan per frame, which
the update CPU figures include; ``bench/session_update.py`` measures the caller without it).
Two figures independent of stalls: ``late_bytes`` (bytes that arrived after the frame that first
needed them was due) and ``coarse_frames`` (frames drawn coarser than needed, by levels in the
JSON). ``discarded_bytes`` (the ``discMB`` column) counts the bytes read from the store but
thrown away on arrival (the block had moved on), in no loaded figure: the bytes read are
``loaded_bytes + discarded_bytes``; the per-frame rows have it as ``discarded_bytes``.

Timings on a shared 2-core machine are noisy: compare ratios within one run of this script.
MB = MiB.

The parts live beside this script: the stores and the HTTP server in ``bench/prefetch_stores.py``,
one fly-through and its metrics in ``bench/prefetch_fly.py``, the tables in
``bench/prefetch_report.py``; this file keeps the targets, one run, the matrix and the command line.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import REAL_HGT, REPO, RESULTS, git_head, machine_info, portable  # noqa: E402

# (names marked F401 are not used here: the stores, the fly-through and the tables moved out
# of this file, and stay importable from it)
from bench.prefetch_fly import (  # noqa: E402
    FPS,
    T_UPDATE_MS,
    LoadLedger,  # noqa: F401
    derive,
    fly,
)
from bench.prefetch_report import (  # noqa: E402
    FRAME_COLUMNS,  # noqa: F401
    MB,  # noqa: F401
    QIU_TABLE3,
    _compact_rows,
    qiu_table,
    table,
)
from bench.prefetch_stores import (  # noqa: E402
    PWORK,
    TERRASTREAM,  # noqa: F401
    http_server,
    log,
    prepare_real,
    prepare_synth,
)
from streamer.run import RunResult, make_path, plot_run  # noqa: E402
from streamer.session import Session, SessionConfig  # noqa: E402
from tiler.store import open_store  # noqa: E402

DEFAULT_OUT = RESULTS / "prefetch.json"
VIEWPORT = (1024, 768)

# Targets (issue #3), stated for prefetch on, 20 ms latency, speed <= 1 block edge/s (and
# T_UPDATE_MS, 2 ms of update CPU, from bench/prefetch_fly.py, which counts the frames over it).
T_STALLS_PER_10K = 1.0
T_REALTIME_PCT = 1.0
T_LOADED_PER_USED = 1.5
HEADLINE_SPEED = 1.0
HEADLINE_LATENCY = 20.0


def checks(m: dict[str, Any]) -> dict[str, bool]:
    """PASS (True) / MISS (False) per target."""
    return {
        "stalls": m["stalls_per_10k"] <= T_STALLS_PER_10K,
        "realtime": m["realtime_pct_of_needed"] <= T_REALTIME_PCT,
        "realtime_strict": m["realtime_pct_of_used"] <= T_REALTIME_PCT,
        "loaded_vs_used": m["loaded_per_used"] <= T_LOADED_PER_USED,
        "loaded_vs_used_per_load": m["loaded_per_used_load"] <= T_LOADED_PER_USED,
        "budget": m["peak_resident_bytes"] <= m["budget_bytes"],
        "update_cpu": m["max_update_cpu_ms"] <= T_UPDATE_MS,
        "update_wall": m["max_update_ms"] <= T_UPDATE_MS,
    }


def run_one(spec: dict[str, Any], args: argparse.Namespace, stores: dict) -> dict[str, Any]:
    """Fly one configuration; returns its record (rows kept under ``_rows`` for headlines)."""
    path, _note = stores[spec["store"]]
    cfg = dict(
        budget_mb=args.budget_mb,
        workers=spec["workers"],
        fps=FPS,
        tau=args.tau,
        prefetch=spec["prefetch"],
        latency_ms=0.0 if spec["transport"] == "http" else spec["latency_ms"],
        account_hull=True,
    )
    ctx = (
        http_server(path.parent, spec["latency_ms"] / 1000.0)
        if spec["transport"] == "http"
        else contextlib.nullcontext(None)
    )
    load0 = os.getloadavg()
    with ctx as url:
        store = open_store(f"{url}/{path.name}" if url else str(path))
        edge = store.grid.step * store.grid.dx
        cams = make_path(
            store,
            "default",
            frames=spec["frames"],
            fps=FPS,
            speed=edge * spec["speed"],
            viewport=VIEWPORT,
        )
        t0 = time.perf_counter()
        with Session(store, SessionConfig(**cfg)) as session:
            out = fly(session, cams)
            summary = session.summary()
        wall = time.perf_counter() - t0
    m = derive(out["rows"], summary, cams, out)
    rec = {
        **spec,
        "session_config": cfg,
        "block_edge_world": edge,
        "speed_world_per_s": edge * spec["speed"],
        "wall_s": wall,
        "loadavg_before": load0,
        "loadavg_after": os.getloadavg(),
        "metrics": m,
        "checks": checks(m),
        "summary": summary,
    }
    if spec["headline"]:
        rec["_rows"] = out["rows"]
    return rec


# --------------------------------------------------------------------------- matrix


def build_matrix(args: argparse.Namespace, stores: dict) -> list[dict[str, Any]]:
    specs: list[dict[str, Any]] = []

    def add(store, speed, lat, pf, frames, headline, transport="sleep", workers=None):
        w = args.workers if workers is None else workers
        name = (
            f"{store}-v{speed:g}-l{lat:g}{'-http' if transport == 'http' else ''}-"
            f"{'pf' if pf else 'nopf'}-w{w}"
        )
        specs.append(
            dict(
                name=name,
                store=store,
                speed=speed,
                latency_ms=lat,
                transport=transport,
                prefetch=pf,
                workers=w,
                frames=frames,
                headline=headline,
                in_target_scope=bool(pf and lat >= HEADLINE_LATENCY and speed <= HEADLINE_SPEED),
            )
        )

    main = [s for s in args.stores if s != "real-deg" and s in stores]
    for store in main:
        for pf in (True, False):
            add(store, HEADLINE_SPEED, HEADLINE_LATENCY, pf, args.frames, True)
    if args.http and "synth" in stores:
        add("synth", HEADLINE_SPEED, HEADLINE_LATENCY, True, args.frames, True, transport="http")
    for store in main:
        for speed in args.speeds:
            for lat in args.latencies:
                for pf in (True, False):
                    if speed == HEADLINE_SPEED and lat == HEADLINE_LATENCY:
                        continue
                    add(store, speed, lat, pf, args.short_frames, False)
    if "synth" in stores:
        for w in args.compare_workers:
            if w != args.workers:
                v, lat, n = HEADLINE_SPEED, HEADLINE_LATENCY, args.short_frames
                add("synth", v, lat, True, n, False, workers=w)
    if "real-deg" in stores:
        add("real-deg", HEADLINE_SPEED, HEADLINE_LATENCY, True, args.short_frames, False)
    return specs


def _code_mtimes() -> dict[str, float]:
    """Modification times of the code a run imports (to flag edits during a long run)."""
    out = {}
    for pkg in ("streamer", "tiler"):
        for f in sorted((REPO / pkg).glob("*.py")):
            out[str(f.relative_to(REPO))] = f.stat().st_mtime
    return out


# --------------------------------------------------------------------------- main


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=10000, help="frames of headline runs")
    p.add_argument("--short-frames", type=int, default=1200, help="frames of other runs")
    p.add_argument("--speeds", default="0.5,1,2", help="block edges per second")
    p.add_argument("--latencies", default="0,20", help="ms per store request")
    p.add_argument("--stores", default="synth,real,real-deg", help="synth, real, real-deg")
    p.add_argument("--workers", type=int, default=16, help="loader threads")
    p.add_argument("--compare-workers", default="4", help="extra short synth headline runs")
    p.add_argument("--no-http", dest="http", action="store_false", help="skip the HTTP run")
    p.add_argument("--budget-mb", type=float, default=256.0)
    p.add_argument("--tau", type=float, default=1.0)
    p.add_argument("--quick", action="store_true", help="~2 minute smoke run")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--no-plot", dest="plot", action="store_false")
    a = p.parse_args(argv)
    if a.quick:
        a.frames, a.short_frames = min(a.frames, 900), min(a.short_frames, 240)
        a.speeds, a.latencies = "1,2", "20"
        a.stores = "synth,real"
        a.compare_workers = ""
    a.speeds = _floats(a.speeds)
    a.latencies = _floats(a.latencies)
    a.stores = [s.strip() for s in a.stores.split(",") if s.strip()]
    a.compare_workers = [int(v) for v in _floats(a.compare_workers)]
    bad = set(a.stores) - {"synth", "real", "real-deg"}
    if bad:
        p.error(f"unknown store(s): {', '.join(sorted(bad))}")
    return a


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    started = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    machine = machine_info()
    mtimes = _code_mtimes()
    RESULTS.mkdir(parents=True, exist_ok=True)
    PWORK.mkdir(parents=True, exist_ok=True)
    log("preparing stores ...")
    stores: dict[str, tuple[Path, str]] = {}
    notes: dict[str, str] = {}
    if "synth" in args.stores:
        stores["synth"] = prepare_synth()
    for name, metric in (("real", True), ("real-deg", False)):
        if name in args.stores:
            got = prepare_real(metric)
            if got is None:
                notes[name] = f"skipped: {REAL_HGT} is absent"
                log(f"  {name}: {notes[name]}")
            else:
                stores[name] = got
    if not stores:  # (the committed JSON is not replaced by an empty one)
        print("error: no store to fly over (see the skipped lines)", file=sys.stderr)
        return 1
    specs = build_matrix(args, stores)
    est = sum(s["frames"] for s in specs) / FPS
    log(f"{len(specs)} runs, ~{est / 60:.1f} min of frames (plus frame-0 waits)")
    records = []
    for i, spec in enumerate(specs, 1):
        log(f"[{i}/{len(specs)}] {spec['name']} ({spec['frames']} frames) ...")
        rec = run_one(spec, args, stores)
        m = rec["metrics"]
        log(
            f"    stalls {m['stall_frames']} ({m['stalls_in_first_second']} in the first second),"
            f" rt {m['realtime_pct_of_needed']:.4f} % of needed, loaded/used "
            f"{m['loaded_per_used']:.2f} (per load {m['loaded_per_used_load']:.2f}), "
            f"discarded {m['discarded_bytes'] / 2**20:.3f} MiB, "
            f"max update CPU {m['max_update_cpu_ms']:.2f} ms "
            f"(wall {m['max_update_ms']:.1f}), late frames {m['late_frames']}, "
            f"{rec['wall_s']:.0f} s"
        )
        if m["ledger_skipped_frames"]:
            log(
                f"    WARNING: the load ledger could not account {m['ledger_skipped_frames']} "
                "frame(s) (the cache kept changing while listed): its per-load figures "
                "(loaded_per_used_load, never_used_load_bytes) undercount their draws"
            )
        records.append(rec)
    tab = table(records)
    qtab, qdata = qiu_table(records)
    log("")
    log(tab)
    log("")
    log("Side by side with Qiu et al., Table 3 (MB, ms):")
    log(qtab)

    frames_files = {}
    folder = args.out.parent  # (beside --out: a run written elsewhere leaves results/ alone)
    folder.mkdir(parents=True, exist_ok=True)
    for r in records:
        rows = r.pop("_rows", None)
        if rows is None:
            continue
        fname = folder / f"prefetch_frames_{r['name']}.json"
        fname.write_text(json.dumps(portable(_compact_rows(rows)), separators=(",", ":")))
        frames_files[r["name"]] = fname.name  # (beside the JSON that names it)
        r["frames_file"] = frames_files[r["name"]]
        if args.plot and r["store"] == "synth" and r["prefetch"] and r["transport"] == "sleep":
            png = folder / "prefetch_synth.png"
            plot_run(RunResult(rows=rows, summary=r["summary"]), png, title=r["name"])
            r["plot"] = png.name
            log(f"wrote {png}")
    doc = {
        "benchmark": "prefetch",
        "started_utc": started,
        "finished_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "machine": {**machine, "git_head_at_end": git_head()},
        "code_changed_during_run": [f for f, t in _code_mtimes().items() if mtimes.get(f) != t],
        "settings": {
            "fps": FPS,
            "viewport": VIEWPORT,
            "path": "streamer.run.make_path(store, 'default', speed=edge*speed)",
            "frames": args.frames,
            "short_frames": args.short_frames,
            "speeds_edges_per_s": args.speeds,
            "latencies_ms": args.latencies,
            "workers": args.workers,
            "compare_workers": args.compare_workers,
            "budget_mb": args.budget_mb,
            "tau": args.tau,
            "pacing": "run_flythrough: warm_up(cameras[0]), frame i due i/fps later",
        },
        "targets": {
            "stalls_per_10k": T_STALLS_PER_10K,
            "realtime_pct_of_needed": T_REALTIME_PCT,
            "loaded_per_used": T_LOADED_PER_USED,
            "peak_resident": "<= budget_bytes",
            "max_update_cpu_ms": T_UPDATE_MS,
            "scope": "prefetch on, 20 ms latency, speed <= 1 block edge/s",
        },
        "stores": {k: {"path": str(v[0]), "note": v[1]} for k, v in stores.items()},
        "store_notes": notes,
        "runs": records,
        "qiu_table3": {"tau": 2, "data": QIU_TABLE3, "side_by_side": qdata},
        "table": tab,
        "frames_files": frames_files,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(portable(doc), indent=1, default=str))
    log(f"wrote {args.out}")
    if doc["code_changed_during_run"]:
        log(f"NOTE: edited while this ran: {', '.join(doc['code_changed_during_run'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
