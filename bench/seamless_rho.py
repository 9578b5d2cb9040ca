"""Seamless patches: Livny et al.'s ρ as published beside ours, in one run (issue 10 item 6).

Usage::

    python bench/seamless_rho.py [--taus 0.5,1,2,4] [--size 320x240] [--frames 8]
                                 [--out bench/results/seamless_rho.json]

For each store and each form of ρ in ε = ρ·l/d (``SeamlessPatches(r, rho=...)``):

* ``bound`` — ours (the default): ``ρ = 2 f δ / (τ 2**c l)``, δ the stored ``bound`` error of
  the nodes beside the edge;
* ``paper`` — the paper's global precision factor (Section 3, "Level of Detail"; Table 1's
  ``ρ_0``), read literally as ``ρ = f / (τ 2**c)``: nothing from the data.

Per τ: :func:`render.pipeline.tradeoff` on the middle camera of ``make_path(store, "default")``
(the camera ``terrastream compare`` measures), data streamed at full resolution
(``stream_tau=0``): triangles, measured max/p99/mean screen error against the full-resolution
render, crack pixels (camera / above), open and gap edges, terrain coverage.

Stores (made under ``bench/work/rho`` when missing, with the CLI): ``synth`` is
``terrastream synth --size 2049 --seed 1`` tiled with ``--block-size 257``; ``real`` is
``N44W072.hgt`` (``$TERRASTREAM_SHARED_DATA``) tiled with ``--dst-crs auto --block-size 257``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import REAL_HGT, REPO, RESULTS, WORK, machine_info, portable, store_complete  # noqa: E402
from render.pipeline import tradeoff  # noqa: E402
from render.renderer import RenderConfig, TerrainRenderer  # noqa: E402
from streamer.run import make_path  # noqa: E402
from tiler.store import open_store  # noqa: E402

RWORK = WORK / "rho"
FORMS = ("bound", "paper")
DEFAULT_OUT = RESULTS / "seamless_rho.json"


def _cli(*args: str) -> None:
    """Run ``python -m cli.main ARGS`` from the repository."""
    subprocess.run([sys.executable, "-m", "cli.main", *args], cwd=REPO, check=True)


def prepare() -> dict[str, Path]:
    """The two stores, made when missing."""
    RWORK.mkdir(parents=True, exist_ok=True)
    synth, tif = RWORK / "s2049.zarr", RWORK / "s2049.tif"
    if not store_complete(synth):  # (a folder an interrupted run left is made again)
        _cli("synth", str(tif), "--size", "2049", "--seed", "1", "--overwrite")
        _cli("tile", str(tif), str(synth), "--block-size", "257", "--workers", "1", "--overwrite")
    real = RWORK / "n44w072_auto.zarr"
    if not store_complete(real):
        _cli("tile", str(REAL_HGT), str(real), "--dst-crs", "auto", "--block-size", "257",
             "--overwrite")  # fmt: skip
    return {"synth": synth, "real": real}


HEADER = (
    f"{'store':>6} {'rho':>6} {'tau':>4} {'triangles':>10} {'max px':>8} {'p99 px':>7} "
    f"{'mean px':>8} {'cracks':>6} {'above':>6} {'open':>5} {'gaps':>5} {'terrain':>8}"
)


def fmt(store: str, r: dict[str, Any]) -> str:
    """One table line."""
    return (
        f"{store:>6} {r['rho']:>6} {r['tau']:>4g} {r['triangles']:>10,} "
        f"{r['max_screen_error_px']:>8.2f} {r['p99_screen_error_px']:>7.2f} "
        f"{r['mean_screen_error_px']:>8.3f} {r['crack_pixels']:>6} {r['crack_pixels_above']:>6} "
        f"{r['open_edges']:>5} {r['gap_edges']:>5} {100 * r['terrain_covered']:>7.1f}%"
    )


def run(path: Path, taus: list[float], size: tuple[int, int], frames: int) -> list[dict]:
    """Rows for every form of ρ and τ on the store at ``path`` (one renderer, one camera)."""
    store = open_store(path)
    cams = make_path(store, "default", frames=frames, viewport=size)
    cam = cams[len(cams) // 2]
    r = TerrainRenderer(store, RenderConfig(size=size))
    rows = []
    try:
        for form in FORMS:
            for tr in tradeoff(
                store, cam, taus, renderer=r, repeats=1, lod="seamless-patches",
                stream_tau=0.0, lod_options={"rho": form},
            ):  # fmt: skip
                rows.append(dict(asdict(tr), rho=form))
    finally:
        r.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    """Print the table and write the JSON (rows per store, the machine record)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--taus", default="0.5,1,2,4")
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--out", default=str(DEFAULT_OUT))
    a = ap.parse_args(argv)
    taus = [float(t) for t in a.taus.split(",")]
    w, h = (int(v) for v in a.size.split("x"))
    stores = prepare()
    results: dict[str, Any] = {"machine": machine_info(), "size": [w, h], "taus": taus}
    print(HEADER)
    for name, path in stores.items():
        t0 = time.perf_counter()
        rows = run(path, taus, (w, h), a.frames)
        for row in rows:
            print(fmt(name, row))
        print(f"# {name}: {time.perf_counter() - t0:.0f} s")
        results[name] = {"store": str(path.relative_to(REPO)), "rows": rows}
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(portable(results), indent=1))
    print(f"wrote {out.name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
