"""``geometry-splitting``'s quadtree texture buffer along fly-throughs (issue 14): how large it
grows against the blocks on the GPU, and the render thread's texture work in each frame.

Usage::

    python bench/texture_slots.py [STORE] [--paths default,canyon,teleports] [--frames 240]
                                  [--size 640x480] [--tau 1] [--out PATH]

Per path, in a fresh process: ``geometry-splitting`` with its textures built in the background
(as ``terrastream flythrough`` and ``view`` run it), a streaming session (256 MB budget, two
loaders) and ``render.step.frame_step`` each frame, as ``flythrough`` does. Recorded per frame:
the texture buffer's bytes (``own_gpu_bytes``), the blocks on the GPU, and the render thread's
texture ms (``build_ms``). Reported: the largest buffer against the most blocks on the GPU at
once (and as a number of full-resolution textures, ``(4**k - 1) / 3`` 8-byte nodes each), the
frames in which it grew, and the frames over 2 ms of texture work. Run it in a checkout of
each commit to compare versions (it uses nothing newer than ``own_gpu_bytes``). Default
STORE: ``bench/work/s4097.zarr`` (16 blocks of 1025²; made by ``bench/lod_compare.py``).
Writes ``bench/results/texture_slots.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import REPO, RESULTS, git_head, machine_info, portable  # noqa: E402

CHILD = """
import json, os, sys
from render.renderer import RenderConfig, TerrainRenderer
from render.step import frame_step
from render.strategies import get_strategy
from streamer.run import make_path
from streamer.session import open_session
from tiler.store import open_store

store_path, kind, frames, w, h, tau = sys.argv[1:7]
store = open_store(store_path)
cams = make_path(store, kind, frames=int(frames), fps=30.0, viewport=(int(w), int(h)))
r = TerrainRenderer(store, RenderConfig(size=cams[0].viewport))
st = get_strategy("geometry-splitting", r)
st.build_in_background()
ahead = getattr(st, "ahead", None)  # (first textures built ahead: absent before them)
if ahead is not None and os.environ.get("AHEAD_PER_FRAME"):
    ahead.per_frame = int(os.environ["AHEAD_PER_FRAME"])
rows = []
try:
    with open_session(store, budget_mb=256, workers=2, tau=float(tau), culling="hull") as s:
        for i, cam in enumerate(cams):
            step = frame_step(s, st, cam, float(tau), dt=1 / 30, wait=i == 0)
            rows.append((st.own_gpu_bytes(), len(r.pool.slots), len(r.drawable(step.resident)),
                         st.build_ms, step.stats.triangles, getattr(st, "build_cpu_ms", None)))
finally:
    st.close()
    r.close()
print(json.dumps({"k": store.k, "rows": rows,
                  "ahead": None if ahead is None else [ahead.hits, ahead.misses, ahead.dropped],
                  "interims": getattr(ahead, "interims", None)}))
"""


def fly(
    store: Path,
    kind: str,
    frames: int,
    size: tuple[int, int],
    tau: float,
    ahead_per_frame: int | None = None,
) -> dict:
    """One flight in a fresh process; its per-frame records and their summary
    (``ahead_per_frame``: the first textures asked ahead at once, default the strategy's)."""
    cmd = [sys.executable, "-c", CHILD, str(store), kind, str(frames), *map(str, size), str(tau)]
    env = dict(os.environ)
    if ahead_per_frame is not None:
        env["AHEAD_PER_FRAME"] = str(ahead_per_frame)
    res = subprocess.run(cmd, cwd=str(REPO), env=env, capture_output=True, text=True, timeout=3600)
    if res.returncode != 0:
        raise RuntimeError(f"{kind} flight failed (exit {res.returncode}):\n{res.stderr[-3000:]}")
    d = json.loads(res.stdout.strip().splitlines()[-1])
    rows = d["rows"]
    per = ((1 << (2 * d["k"])) - 1) // 3 * 8
    nbytes = [x[0] for x in rows]
    gpu_blocks = [x[1] for x in rows]
    build = [x[3] for x in rows]
    cpu = [x[5] for x in rows if len(x) > 5 and x[5] is not None]  # (none before build_cpu_ms)
    ahead = d.get("ahead")
    return {
        "path": kind,
        "frames": len(rows),
        "texture_bytes_per_block": per,
        "max_texture_mb": max(nbytes) / 2**20,
        "final_texture_mb": nbytes[-1] / 2**20,
        "max_gpu_blocks": max(gpu_blocks),
        "full_textures_in_max": max(nbytes) / per,  # the buffer's size in full-size textures
        "growth_frames": [i for i in range(1, len(rows)) if nbytes[i] != nbytes[i - 1]],
        "frames_over_2ms": [i for i, b in enumerate(build) if b > 2.0],
        "first_build_ms": build[0],
        # (None: one frame, nothing after the first was measured)
        "max_build_ms_after_first": max(build[1:]) if len(build) > 1 else None,
        "build_cpu_ms_after_first": sum(cpu[1:]) if cpu else None,
        "frames_over_1ms_cpu": [i for i, c in enumerate(cpu) if c > 1.0] if cpu else None,
        # first textures taken built ahead / built on the render thread / dropped unused
        "ahead_hits_misses_dropped": ahead,
        # first textures taken ready at another level than drawn, drawn meanwhile (None: the
        # code measured took none of them)
        "ahead_interims": d.get("interims"),
        "mean_triangles": sum(x[4] for x in rows) / len(rows),
        "per_frame": [
            {
                "texture_bytes": x[0],
                "gpu_blocks": x[1],
                "drawn_blocks": x[2],
                "build_ms": round(x[3], 3),
                "build_cpu_ms": round(x[5], 3) if len(x) > 5 and x[5] is not None else None,
            }
            for x in rows
        ],
    }


def _fmt(v: float | None, digits: int = 1) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store", nargs="?", type=Path, default=REPO / "bench/work/s4097.zarr")
    ap.add_argument("--paths", default="default,canyon,teleports")
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--tau", type=float, default=1.0)
    ap.add_argument(
        "--ahead-per-frame",
        type=int,
        default=None,
        help="first textures asked ahead at once (0: none; default: the strategy's)",
    )
    ap.add_argument("--out", type=Path, default=RESULTS / "texture_slots.json")
    a = ap.parse_args(argv)
    if not a.store.exists():
        print(f"# {a.store} is missing: make it with `python bench/lod_compare.py` first")
        return 1
    size = tuple(int(v) for v in a.size.lower().split("x"))
    runs = [
        fly(a.store, kind.strip(), a.frames, size, a.tau, a.ahead_per_frame)
        for kind in a.paths.split(",")
    ]
    head = ("path", "frames", "max GPU blocks", "max texture MB", "full textures in it",
            "growths", "frames > 2 ms", "first frame ms", "max ms after first",
            "CPU ms after first", "frames > 1 ms CPU", "ahead hits/misses/dropped",
            "interims", "mean triangles")  # fmt: skip
    print(" | ".join(head))
    for x in runs:
        print(" | ".join(str(v) for v in (
            x["path"], x["frames"], x["max_gpu_blocks"], f"{x['max_texture_mb']:.1f}",
            f"{x['full_textures_in_max']:.1f}", len(x["growth_frames"]), len(x["frames_over_2ms"]),
            f"{x['first_build_ms']:.1f}", _fmt(x["max_build_ms_after_first"], 2),
            _fmt(x["build_cpu_ms_after_first"]),
            "-" if x["frames_over_1ms_cpu"] is None else len(x["frames_over_1ms_cpu"]),
            "/".join(map(str, x["ahead_hits_misses_dropped"] or ["-"])),
            "-" if x["ahead_interims"] is None else x["ahead_interims"],
            f"{x['mean_triangles']:.0f}",
        )))  # fmt: skip
    a.out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"machine": machine_info(), "store": portable(str(a.store)), "size": list(size),
           "tau": a.tau, "ahead_per_frame": a.ahead_per_frame, "git_head": git_head(),
           "runs": runs}  # fmt: skip
    a.out.write_text(json.dumps(portable(doc), indent=1))
    print(f"# wrote {portable(str(a.out))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
