"""The prefetch benchmark's stores (tiled once, reused) and its loopback HTTP server.

``synth`` is the 16385^2 synthetic DEM with 1025^2 blocks, ``real`` SRTM N44W072 relabelled in
metres with 257^2 blocks, ``real-deg`` the same tile as EPSG:4326; :func:`http_server` serves a
folder over loopback HTTP with a delay per request. See bench/prefetch.py.
"""

from __future__ import annotations

import contextlib
import math
import subprocess
import sys
import time
from pathlib import Path

from bench.common import REAL_HGT, REPO, WORK

PWORK = WORK / "prefetch"
TERRASTREAM = str(Path(sys.executable).with_name("terrastream"))


def log(msg: str) -> None:
    print(msg, flush=True)


# --------------------------------------------------------------------------- stores


def _store_ok(path: Path) -> bool:
    """A complete store: ``terrastream info`` succeeds."""
    if not path.exists():
        return False
    r = subprocess.run([TERRASTREAM, "-q", "info", str(path)], capture_output=True, text=True)
    return r.returncode == 0


def _tile(src: Path, dst: Path, block_size: int) -> None:
    if _store_ok(dst):
        log(f"  reusing {dst.relative_to(REPO)}")
        return
    log(f"  tiling {src} -> {dst} (--block-size {block_size}) ...")
    t0 = time.perf_counter()
    cmd = [TERRASTREAM, "tile", str(src), str(dst), "--block-size", str(block_size)]
    subprocess.run([*cmd, "--overwrite"], check=True)
    log(f"  tiled in {time.perf_counter() - t0:.1f} s")


def _synth_available() -> bool:
    try:
        from tiler.synth import synth_dem  # noqa: F401
    except ImportError:
        return False
    return True


def prepare_synth() -> tuple[Path, str]:
    """The 16385^2 synthetic store and a note on its source."""
    if _synth_available():
        src = WORK / "s16385.tif"
        if not src.exists():
            log("  terrastream synth (16385^2, seed 1) ...")
            cmd = [TERRASTREAM, "synth", str(src), "--size", "16385", "--seed", "1"]
            subprocess.run(cmd, check=True)
        dst = WORK / "s16385.zarr"
        note = "terrastream synth --size 16385 --seed 1 (tiler.synth.synth_dem)"
    else:
        for seed in (0, 999):
            src = WORK / f"synth_16385_seed{seed}_int16.tif"
            if src.exists():
                break
        else:
            raise SystemExit("no synthetic 16385^2 source: tiler.synth.synth_dem is missing")
        dst = PWORK / f"synth16385_seed{seed}.zarr"
        note = (
            f"{src.relative_to(REPO)} (tiler.synth.synth_dem not available: the existing "
            f"seed-{seed} int16 source written by synth_array)"
        )
    _tile(src, dst, 1025)
    return dst, note


def prepare_real(metric: bool) -> tuple[Path, str] | None:
    """SRTM N44W072 with 257^2 blocks: metric relabelling (``metric``) or as-is EPSG:4326."""
    if not REAL_HGT.exists():
        return None
    if not metric:
        dst = PWORK / "n44w072_b257.zarr"
        _tile(REAL_HGT, dst, 257)
        return dst, f"{REAL_HGT} as tiled (EPSG:4326: x/y in degrees, z in metres)"
    import rasterio
    from rasterio.crs import CRS
    from rasterio.transform import Affine

    src = PWORK / "N44W072_eqc_m.tif"
    if not src.exists():
        with rasterio.open(REAL_HGT) as ds:
            arr, t, nodata = ds.read(1), ds.transform, ds.nodata
        a = 6378137.0
        lat_ts = round(t.f + t.e * ds.height / 2, 6)
        lon0 = round(t.c + t.a * ds.width / 2, 6)
        kx = a * math.cos(math.radians(lat_ts)) * math.pi / 180
        ky = a * math.pi / 180
        tr = Affine(t.a * kx, 0.0, (t.c - lon0) * kx, 0.0, t.e * ky, t.f * ky)
        crs = CRS.from_proj4(
            f"+proj=eqc +lat_ts={lat_ts} +lon_0={lon0} +lat_0=0 +datum=WGS84 +units=m +no_defs"
        )
        prof = dict(
            driver="GTiff",
            dtype=arr.dtype.name,
            width=arr.shape[1],
            height=arr.shape[0],
            count=1,
            crs=crs,
            transform=tr,
            nodata=nodata,
        )
        PWORK.mkdir(parents=True, exist_ok=True)
        with rasterio.open(src, "w", **prof) as out:
            out.write(arr, 1)
    dst = PWORK / "n44w072_eqc_b257.zarr"
    _tile(src, dst, 257)
    return dst, (
        f"{REAL_HGT} relabelled in metres (equirectangular at the tile's middle latitude, same "
        "samples, 66.2 m x 92.8 m), 257^2 blocks"
    )


# --------------------------------------------------------------------------- HTTP server


@contextlib.contextmanager
def http_server(directory: Path, latency_s: float):
    """``tests/rangeserver.LoopbackServer`` in a child process; yields its URL."""
    code = (
        "import sys, time\n"
        f"sys.path.insert(0, {str(REPO / 'tests')!r})\n"
        "from rangeserver import LoopbackServer\n"
        f"with LoopbackServer({str(directory)!r}, {latency_s!r}) as url:\n"
        "    print(url, flush=True)\n"
        "    sys.stdin.read()\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        url = proc.stdout.readline().strip()
        if not url.startswith("http://"):
            raise RuntimeError(f"loopback server did not start (got {url!r})")
        yield url
    finally:
        with contextlib.suppress(Exception):
            proc.stdin.close()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
