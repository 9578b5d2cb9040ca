"""Streaming ablation: Qiu et al.'s loading as published beside each of this project's additions.

Usage::

    python bench/ablation.py [--frames 900] [--speeds 0.5,1,2] [--latencies 0,20]
                             [--stores real,synth] [--workers 8] [--budget-mb 256] [--tau 1]
                             [--no-evict] [--out bench/results/ablation.json]

Variants (``SessionConfig.scheme``, see ``streamer.frames.SCHEMES``):

* ``none`` — no prefetching at all (``prefetch=False``): the positive control, it must stall;
* ``qiu`` — Qiu's loading as published: the extended triangle of the current pose only (L = one
  block edge, S = V cos a / f), each block loaded level by level up to the level it needs at tau;
* ``qiu+ahead`` — plus the extension of the pose ``horizon_s`` (0.5 s) ahead (ours);
* ``qiu+fine`` — plus loading at 0.7 tau (ours);
* ``ours`` — both, and up to 4 levels of a block read at once (the default session);
* ``qiu+ahead+fine`` — both additions, still level by level (headline speed/latency only: it
  isolates reading levels of a block concurrently).

Every variant flies the same ``make_path(store, "default", speed=edge * speed)`` (``--speeds`` in
block edges per second) for ``--frames`` frames at 60 fps in real time (warm-up for the first
pose, frame i due i/60 s later, frame 0 waits), with ``culling="qiu"`` (stalls over Qiu's
triangle) and ``account_hull=True`` (stalls over the frustum hull the renderer draws, too).
The variants of one (store, speed, latency) fly back to back, so they share the machine's load.

Eviction (issue 10 item 7): for each store, ``none``, ``qiu`` and ``ours`` fly the headline path
out and back (``frames/2`` out, the same poses in reverse) under a budget of half the peak
resident bytes the ``ours`` headline flight reached, so levels are evicted on the way out and
loaded again on the way back (``reloaded_bytes``).

Stores: ``real`` is SRTM N44W072 relabelled in metres, 257^2 blocks (``bench/prefetch.py``'s
``prepare_real``); ``synth`` is ``terrastream synth --size 4097 --seed 1`` tiled with 257^2 blocks.
Bytes are decoded level bytes; MB = MiB.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import REPO, RESULTS, WORK, machine_info, portable  # noqa: E402
from streamer.errors import BudgetError  # noqa: E402
from streamer.run import make_path  # noqa: E402
from streamer.session import Session, SessionConfig  # noqa: E402
from tiler.store import open_store  # noqa: E402

FPS = 60.0
VIEWPORT = (1024, 768)
MB = float(1 << 20)
AWORK = WORK / "ablation"
DEFAULT_OUT = RESULTS / "ablation.json"
HEADLINE = (1.0, 20.0)
#: variant -> SessionConfig overrides
VARIANTS: dict[str, dict[str, Any]] = {
    "none": {"prefetch": False, "scheme": "qiu"},
    "qiu": {"scheme": "qiu"},
    "qiu+ahead": {"scheme": "qiu+ahead"},
    "qiu+fine": {"scheme": "qiu+fine"},
    "ours": {"scheme": "ours"},
}
HEADLINE_ONLY = {"qiu+ahead+fine": {"scheme": "qiu+ahead+fine"}}
EVICT_VARIANTS = ("none", "qiu", "ours")


def log(msg: str) -> None:
    print(msg, flush=True)


def prepare_synth() -> tuple[Path, str]:
    """The 4097^2 synthetic store (257^2 blocks), made with the CLI when missing."""
    src, dst = AWORK / "s4097_seed1.tif", AWORK / "s4097_b257.zarr"
    AWORK.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-m", "cli.main"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    if not src.exists():
        cmd = [*cli, "synth", str(src), "--size", "4097", "--seed", "1"]
        subprocess.run(cmd, check=True, env=env)
    if not (dst / "zarr.json").exists():
        cmd = [*cli, "tile", str(src), str(dst), "--block-size", "257", "--overwrite"]
        subprocess.run(cmd, check=True, env=env)
    return dst, "terrastream synth --size 4097 --seed 1, tiled with --block-size 257"


def prepare_real() -> tuple[Path, str] | None:
    """N44W072 relabelled in metres, 257^2 blocks (bench/prefetch.py's store)."""
    from bench.prefetch import prepare_real as _real

    return _real(True)


def fly(session: Session, cameras: list) -> dict[str, Any]:
    """Warm up for the first pose, then show frame i at i/fps (frame 0 waits); late frames."""
    session.warm_up(cameras[0])
    t0 = time.perf_counter()
    late = 0
    for i, cam in enumerate(cameras):
        delay = t0 + i / FPS - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        elif delay < -1.0 / FPS:
            late += 1
        session.update(cam, 1.0 / FPS, wait=i == 0)
    return {"frames_started_late": late}


def metrics(summary: dict[str, Any]) -> dict[str, Any]:
    """The figures of the ablation table from a session summary."""
    used = summary["used_bytes"]
    return {
        "stalls": summary["stall_frames"],
        "stalls_hull": summary["stall_frames_hull"],
        "realtime_mb": summary["realtime_bytes_after_first_frame"] / MB,
        "realtime_pct": 100.0 * summary["realtime_bytes"] / max(1, summary["loaded_bytes"]),
        "late_mb": summary["late_bytes"] / MB,
        "coarse_frames": summary["coarse_frames_by_levels"],
        "hole_frames": summary["hole_frames"],
        "loaded_mb": summary["loaded_bytes"] / MB,
        "used_mb": used / MB,
        "loaded_per_used": summary["loaded_bytes"] / used if used else None,
        "reloaded_mb": summary["reloaded_bytes"] / MB,
        "peak_resident_mb": summary["peak_resident_bytes"] / MB,
        "budget_mb": summary["budget_bytes"] / MB,
        "warmup_mb": summary["warmup_bytes"] / MB,
        "cancelled_loads": summary["cancelled_loads"],
    }


def run_one(
    store,
    variant: str,
    overrides: dict,
    speed: float,
    latency: float,
    args,
    *,
    frames: int,
    budget_mb: float,
    out_and_back: bool = False,
) -> dict[str, Any]:
    """Fly one variant; its record."""
    edge = store.grid.step * store.grid.dx
    n = frames // 2 if out_and_back else frames
    cams = make_path(store, "default", frames=n, fps=FPS, speed=edge * speed, viewport=VIEWPORT)
    if out_and_back:
        cams = cams + cams[::-1]
    cfg = dict(
        budget_mb=budget_mb,
        workers=args.workers,
        fps=FPS,
        tau=args.tau,
        latency_ms=latency,
        culling="qiu",
        account_hull=True,
        **overrides,
    )
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    with Session(store, SessionConfig(**cfg)) as session:
        extra = fly(session, cams)
        summary = session.summary()
    rec = {
        "variant": variant,
        "speed_edges_per_s": speed,
        "latency_ms": latency,
        "frames": len(cams),
        "out_and_back": out_and_back,
        "session_config": cfg,
        "wall_s": time.perf_counter() - t0,
        "loadavg_before": load0,
        "loadavg_after": os.getloadavg(),
        **extra,
        "metrics": metrics(summary),
        "summary": summary,
    }
    m = rec["metrics"]
    log(
        f"  {variant:>15} {speed:>4} e/s {latency:>3.0f} ms: stalls {m['stalls']:>4} "
        f"(hull {m['stalls_hull']}), RT {m['realtime_mb']:.2f} MB, late {m['late_mb']:.2f} MB, "
        f"loaded/used {m['loaded_per_used'] or 0:.2f}, reloaded {m['reloaded_mb']:.2f} MB, "
        f"load {load0[0]:.1f}"
    )
    return rec


def table(records: list[dict[str, Any]]) -> str:
    """Markdown: one row per flight."""
    head = (
        "| store | flight | speed (edges/s) | latency (ms) | variant | stalls (triangle) | "
        "stalls (hull) | real-time MB | late MB | coarse frames | loaded MB | loaded/used | "
        "reloaded MB | budget MB |"
    )
    lines = [head, "|" + "---|" * 14]
    for r in records:
        m = r["metrics"]
        coarse = sum(m["coarse_frames"].values())
        lpu = f"{m['loaded_per_used']:.2f}" if m["loaded_per_used"] else "-"
        lines.append(
            f"| {r['store']} | {'out+back' if r['out_and_back'] else 'default'} | "
            f"{r['speed_edges_per_s']:g} | {r['latency_ms']:g} | {r['variant']} | {m['stalls']} | "
            f"{m['stalls_hull']} | {m['realtime_mb']:.2f} | {m['late_mb']:.2f} | {coarse} | "
            f"{m['loaded_mb']:.1f} | {lpu} | {m['reloaded_mb']:.2f} | {m['budget_mb']:.1f} |"
        )
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=900)
    p.add_argument("--speeds", default="0.5,1,2")
    p.add_argument("--latencies", default="0,20")
    p.add_argument("--stores", default="real,synth")
    p.add_argument("--workers", type=int, default=8)
    p.add_argument("--budget-mb", type=float, default=256.0)
    p.add_argument("--tau", type=float, default=1.0)
    p.add_argument("--no-evict", action="store_true")
    p.add_argument(
        "--variants",
        default="",
        help="comma-separated subset of the variants to fly (default: all), e.g. none,qiu",
    )
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    speeds = [float(s) for s in args.speeds.split(",")]
    lats = [float(s) for s in args.latencies.split(",")]
    out: dict[str, Any] = {
        "machine": machine_info(),
        "args": {k: str(v) for k, v in vars(args).items()},
        "command": " ".join(["python", "bench/ablation.py", *(argv or sys.argv[1:])]),
        "stores": {},
        "records": [],
    }
    t_start = time.perf_counter()
    names = [n.strip() for n in args.stores.split(",") if n.strip()]
    chosen = {v.strip() for v in args.variants.split(",") if v.strip()}
    known = {*VARIANTS, *HEADLINE_ONLY}
    if unknown := sorted(chosen - known):
        print(
            f"error: --variants {','.join(unknown)}: choose among {', '.join(sorted(known))}",
            file=sys.stderr,
        )
        return 2
    if bad := [n for n in names if n not in ("real", "synth")]:
        print(f"error: --stores {','.join(bad)}: use real and/or synth", file=sys.stderr)
        return 2
    for name in names:
        prep = prepare_real() if name == "real" else prepare_synth()
        if prep is None:
            log(f"store {name}: source missing, skipped")
            continue
        path, note = prep
        store = open_store(str(path))
        out["stores"][name] = {"path": str(path.relative_to(REPO)), "note": note}
        log(f"store {name}: {path}")
        peak = None
        for speed in speeds:
            for lat in lats:
                variants = dict(VARIANTS)
                if (speed, lat) == HEADLINE:
                    variants.update(HEADLINE_ONLY)
                if chosen:
                    variants = {v: ov for v, ov in variants.items() if v in chosen}
                for v, ov in variants.items():
                    rec = run_one(
                        store, v, ov, speed, lat, args, frames=args.frames, budget_mb=args.budget_mb
                    )
                    rec["store"] = name
                    out["records"].append(rec)
                    if v == "ours" and (speed, lat) == HEADLINE:
                        peak = rec["metrics"]["peak_resident_mb"]
                    _save(out, args.out)
        if args.no_evict or peak is None:
            continue
        budget = round(peak / 2, 2)
        for v in [v for v in EVICT_VARIANTS if not chosen or v in chosen]:
            # one budget for all: raised until no variant's pins fail
            for _ in range(4):
                try:
                    rec = run_one(
                        store,
                        v,
                        VARIANTS[v],
                        *HEADLINE,
                        args,
                        frames=args.frames,
                        budget_mb=budget,
                        out_and_back=True,
                    )
                    break
                except BudgetError as exc:
                    log(f"  budget {budget} MB too small ({exc}); x1.5")
                    budget = round(budget * 1.5, 2)
            else:
                continue
            rec["store"] = name
            out["records"].append(rec)
            _save(out, args.out)
    if not out["records"]:  # (the committed JSON is not replaced by an empty one)
        print("error: no store was flown (see the skipped lines)", file=sys.stderr)
        return 1
    out["wall_s"] = time.perf_counter() - t_start
    out["table"] = table(out["records"])
    _save(out, args.out)
    log(out["table"])
    return 0


def _save(out: dict[str, Any], path: Path) -> None:
    """Write ``out`` as JSON, naming no machine's paths (``--out``, the real DEM's path)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(portable(out), indent=1, default=str))


if __name__ == "__main__":
    raise SystemExit(main())
