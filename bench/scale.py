"""Scaling: one big synthetic DEM tiled with local processes, a LocalCluster and a cluster of
separately started ``dask scheduler`` / ``dask worker`` processes on loopback.

    python bench/scale.py                      # 32769^2 int16 (2.1 GB source), 2 workers
    python bench/scale.py --size 16385 --workers 1,2

Each run is a child process (``--one MODE``) running ``tiler.tile.tile``; the parent samples
the RSS of every process of the run (client, pool/dask workers, scheduler) every 0.2 s and
reads the client's ``/proc/<pid>/io`` (bytes read/written by the client through any file or
socket: source metadata, dask messages, the finish step) at the end. Linux adds a reaped
child's counters to its parent's, so only the ``external`` mode (workers are not the client's
children) measures the client alone; for ``processes`` and ``localcluster`` the counters
include the worker processes (``client_io_includes_workers``). Writes
``bench/results/scale.json`` and ``bench/results/scale.png`` (time and peak RSS per worker vs
workers). Work files go to ``bench/work/scale`` (git-ignored).

    python bench/scale.py --malloc 20          # the allocator probe (bench/results/malloc.json)
    python bench/scale.py --malloc-tune 0 --modes localcluster --append   # tiler.malloc off

``--malloc ROUNDS`` times one 1025² block's ``process_block`` in fresh processes: a plain one,
one with dask's worker environment (``MALLOC_TRIM_THRESHOLD_=65536``) and ``tiler.malloc`` off,
and the same with it on, for both kernel back-ends (minor page faults, CPU and wall ms per
block). ``--malloc-tune 0`` runs the tiling with ``TERRASTREAM_MALLOC_TUNE=0`` (every run
records the setting and the load average before and after it).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import RESULTS, WORK, machine_info, portable  # noqa: E402

MODES = ("processes", "localcluster", "external")
PY = sys.executable


def _io(pid: int) -> dict[str, int]:
    out = {}
    with open(f"/proc/{pid}/io") as f:
        for line in f:
            k, v = line.split(":")
            out[k.strip()] = int(v)
    return out


def one(mode: str, src: str, dst: str, workers: int, block: int, address: str | None) -> None:
    """Child: tile once, print a JSON line (time, summary, client I/O bytes)."""
    # import now what the run imports, so the client's I/O counters see the run, not imports
    import tiler.assemble  # noqa: F401
    from tiler.tile import TileOptions, tile

    if mode != "processes":
        import distributed  # noqa: F401

        import tiler.dask_run  # noqa: F401
    if mode == "processes":
        opts = TileOptions(block_size=block, workers=workers, scheduler="processes")
    elif mode == "localcluster":
        opts = TileOptions(block_size=block, workers=workers, scheduler="dask")
    else:
        opts = TileOptions(block_size=block, workers=workers, scheduler=address)
    io0 = _io(os.getpid())
    t0 = time.perf_counter()
    store = tile(src, dst, opts)
    elapsed = time.perf_counter() - t0
    io1 = _io(os.getpid())
    s = store.tile_summary
    print(
        json.dumps(
            {
                "elapsed_s": elapsed,
                "blocks": s.blocks_total,
                "executor": s.executor,
                "client_rchar": io1["rchar"] - io0["rchar"],
                "client_wchar": io1["wchar"] - io0["wchar"],
                "client_read_bytes": io1["read_bytes"] - io0["read_bytes"],
                "client_write_bytes": io1["write_bytes"] - io0["write_bytes"],
            }
        ),
        flush=True,
    )


class RssSampler:
    """Max RSS per process of the given root pids' trees, sampled every ``interval`` s."""

    def __init__(self, roots: list[int], interval: float = 0.2) -> None:
        import psutil

        self.psutil = psutil
        self.roots = list(roots)
        self.peak: dict[int, int] = {}
        self.cmd: dict[int, str] = {}
        self.stop = threading.Event()
        self.t = threading.Thread(target=self._loop, name="bench-rss", daemon=True)
        self.t.start()

    def _loop(self) -> None:
        ps = self.psutil
        while not self.stop.is_set():
            for root in self.roots:
                try:
                    p = ps.Process(root)
                    procs = [p, *p.children(recursive=True)]
                except ps.NoSuchProcess:
                    continue
                for q in procs:
                    try:
                        rss = q.memory_info().rss
                        if q.pid not in self.cmd:
                            self.cmd[q.pid] = " ".join(q.cmdline())
                    except (ps.NoSuchProcess, ps.AccessDenied):
                        continue
                    self.peak[q.pid] = max(self.peak.get(q.pid, 0), rss)
            self.stop.wait(0.2)

    def close(self) -> dict[int, tuple[int, str]]:
        self.stop.set()
        self.t.join(5)
        return {pid: (rss, self.cmd.get(pid, "")) for pid, rss in self.peak.items()}


def _is_worker(cmd: str) -> bool:
    return "spawn_main" in cmd and "resource_tracker" not in cmd


def start_cluster(workers: int, env: dict, tmp: Path) -> tuple[list, str]:
    """``dask scheduler`` + ``dask worker`` processes on 127.0.0.1 (returns procs, address)."""
    sched_file = tmp / "scheduler.json"
    dask = str(Path(PY).with_name("dask"))
    sched = subprocess.Popen(
        [dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
         "--scheduler-file", str(sched_file)],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.monotonic() + 60
    while not sched_file.exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    address = json.loads(sched_file.read_text())["address"]
    worker = subprocess.Popen(
        [dask, "worker", "--scheduler-file", str(sched_file), "--nworkers", str(workers),
         "--nthreads", "1", "--host", "127.0.0.1", "--no-dashboard", "--memory-limit", "0"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    import distributed

    with distributed.Client(address, timeout="60s") as c:
        c.wait_for_workers(workers, timeout=120)
    return [sched, worker], address


def stop_cluster(procs: list) -> None:
    """Terminate (then kill) the cluster processes started by :func:`start_cluster`."""
    for p in reversed(procs):
        p.terminate()
    for p in reversed(procs):
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)


def run_mode(mode: str, src: Path, work: Path, workers: int, block: int, tune: str = "1") -> dict:
    """One measured run in a child process (and its cluster for ``external``)."""
    dst = work / f"{mode}-w{workers}.zarr"
    if dst.exists():
        shutil.rmtree(dst)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    env["TERRASTREAM_MALLOC_TUNE"] = tune
    load0 = os.getloadavg()
    cluster: list = []
    address = None
    with tempfile.TemporaryDirectory(prefix="scale-") as tmp:
        if mode == "external":
            cluster, address = start_cluster(workers, env, Path(tmp))
        cmd = [PY, __file__, "--one", mode, "--src", str(src), "--dst", str(dst),
               "--workers", str(workers), "--block", str(block)]  # fmt: skip
        if address:
            cmd += ["--address", address]
        child = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True)
        sampler = RssSampler([child.pid, *(p.pid for p in cluster)])
        out, _ = child.communicate()
        peaks = sampler.close()
        if mode == "external":
            stop_cluster(cluster)
    if child.returncode != 0:
        raise SystemExit(f"{mode} run failed ({child.returncode})")
    res = json.loads(out.strip().splitlines()[-1])
    worker_rss = [rss for pid, (rss, cmd) in peaks.items() if _is_worker(cmd)]
    res.update(
        client_io_includes_workers=mode != "external",
        mode=mode,
        workers=workers,
        worker_processes=len(worker_rss),
        peak_rss_worker_mib=round(max(worker_rss, default=0) / 2**20, 1),
        peak_rss_client_mib=round(peaks.get(child.pid, (0, ""))[0] / 2**20, 1),
        peak_rss_scheduler_mib=(
            round(peaks[cluster[0].pid][0] / 2**20, 1) if cluster and cluster[0].pid in peaks
            else None
        ),
        store_bytes=sum(p.stat().st_size for p in dst.rglob("*") if p.is_file()),
    )  # fmt: skip
    res["blocks_per_s"] = res["blocks"] / res["elapsed_s"]
    res.update(malloc_tune=tune == "1", loadavg_before=load0, loadavg_after=os.getloadavg())
    shutil.rmtree(dst, ignore_errors=True)
    return res


MALLOC_PROBE = """
import json, os, resource, sys, time
import numpy as np
from tiler.run import worker_setup
from tiler.synth import synth_array
from tiler.tile import BlockParams, process_block
worker_setup(256, sys.argv[1], "int16")
win = synth_array(slice(0, 1025), slice(0, 1025), 16385, 0, 2500.0, 200.0, "int16")
p = BlockParams(k=10, dtype="int16", storage_dtype="int16", nodata=None, precision=None,
                error_cap=6)
process_block(win, p)
ts, cs = [], []
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(int(sys.argv[2])):
    t0, c0 = time.perf_counter(), time.process_time()
    process_block(win, p)
    ts.append(time.perf_counter() - t0)
    cs.append(time.process_time() - c0)
n = int(sys.argv[2])
print(json.dumps({
    "minflt_per_block": (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / n,
    "cpu_ms": 1e3 * float(np.median(cs)), "wall_ms": 1e3 * float(np.median(ts)),
    "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""
MALLOC_CASES = {  # name: (MALLOC_TRIM_THRESHOLD_ or None, TERRASTREAM_MALLOC_TUNE)
    "plain process, tuning off": (None, "0"),
    "dask worker env, tuning off": ("65536", "0"),
    "dask worker env, tuning on": ("65536", "1"),
    "plain process, tuning on": (None, "1"),
}


def malloc_probe(rounds: int, out: Path) -> dict:
    """Per-block page faults and CPU of ``process_block`` under each allocator setting
    (fresh process per case; the cases interleave twice so they share the machine's load)."""
    base = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    base.pop("MALLOC_TRIM_THRESHOLD_", None)
    rows: dict[str, list[dict]] = {}
    for _ in range(2):
        for backend in ("numba", "numpy"):
            for name, (trim, tune) in MALLOC_CASES.items():
                env = dict(base, TERRASTREAM_MALLOC_TUNE=tune)
                if trim is not None:
                    env["MALLOC_TRIM_THRESHOLD_"] = trim
                n = rounds if backend == "numba" else max(3, rounds // 4)
                got = subprocess.run(
                    [PY, "-c", MALLOC_PROBE, backend, str(n)], env=env, capture_output=True,
                    text=True, check=True,
                )  # fmt: skip
                rows.setdefault(f"{backend}: {name}", []).append(
                    json.loads(got.stdout.strip().splitlines()[-1])
                )
    table = {
        key: {m: round(min(r[m] for r in runs), 1) for m in runs[0]} for key, runs in rows.items()
    }
    print("| kernels: case | minor faults/block | CPU ms/block | wall ms/block |")
    print("|---|---:|---:|---:|")
    for key, r in table.items():
        print(f"| {key} | {r['minflt_per_block']:,.0f} | {r['cpu_ms']:.1f} | {r['wall_ms']:.1f} |")
    doc = {
        "command": f"python bench/scale.py --malloc {rounds}",
        "block": "1025^2 int16 synthetic (process_block only: no read, no write)",
        "statistic": "min over 2 interleaved processes of the per-process median",
        "table": table,
        "runs": rows,
        "machine": machine_info(),
    }
    out.write_text(json.dumps(portable(doc), indent=1))
    print(f"wrote {out}")
    return doc


def _load(r: dict, key: str) -> str:
    return f"{r[key][0]:.1f}" if key in r else "?"


def plot(results: list[dict], path: Path) -> None:
    """Time and peak RSS per worker vs workers, one line per mode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for mode in MODES:
        rows = sorted((r for r in results if r["mode"] == mode), key=lambda r: r["workers"])
        if not rows:
            continue
        w = [r["workers"] for r in rows]
        ax[0].plot(w, [r["elapsed_s"] for r in rows], "o-", label=mode)
        ax[1].plot(w, [r["peak_rss_worker_mib"] for r in rows], "o-", label=mode)
    ax[0].set(xlabel="workers", ylabel="time (s)", title="tiling time")
    ax[1].set(xlabel="workers", ylabel="MiB", title="peak RSS per worker")
    for a in ax:
        a.legend()
        a.set_ylim(bottom=0)
        a.set_xticks(sorted({r["workers"] for r in results}))
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def s3_reads(rounds: int, out: Path) -> dict:
    """fsspec (s3fs) vs obstore zarr stores for the streamer's reads on a loopback S3 server,
    each with the chunks read directly (``tiler.chunkread_remote``) and through zarr
    (``-zarr``, ``direct_reads=False``).

    A 2049^2 int16 synthetic tiled with 257^2 blocks into moto's S3 server; per round and per
    backend (interleaved): open the store, first view (session opened, first camera's blocks
    all loaded), the latency of one level read per level over 24 blocks, and of a whole block
    (``read_levels_raw``) over 8.
    """
    import logging
    import statistics

    import numpy as np
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    endpoint = f"http://{host}:{port}"
    os.environ.update(
        AWS_ACCESS_KEY_ID="testing", AWS_SECRET_ACCESS_KEY="testing",
        AWS_DEFAULT_REGION="us-east-1", AWS_ENDPOINT_URL=endpoint,
    )  # fmt: skip
    import s3fs

    from streamer.run import make_path
    from streamer.session import open_session
    from tiler.location import Location
    from tiler.s3_reader import S3_READER_ENV
    from tiler.store import TerrainStore
    from tiler.synth import synth_dem
    from tiler.tile import TileOptions, tile

    s3fs.S3FileSystem().mkdir("bench")
    work = WORK / "scale"
    work.mkdir(parents=True, exist_ok=True)
    src = work / "synth-2049-int16.tif"
    if not src.exists():
        synth_dem(src, 2049, seed=0)
    url = "s3://bench/s2049.zarr"
    tile(src, url, TileOptions(block_size=257, workers=2))

    def opener(reader: str, direct: bool = True):
        def go() -> TerrainStore:
            os.environ[S3_READER_ENV] = reader
            store = TerrainStore(Location(url), direct_reads=direct)
            # the group's zarr store: FsspecStore or ObjectStore
            kind = type(store._group.store).__name__
            assert kind == {"fsspec": "FsspecStore", "obstore": "ObjectStore"}[reader], kind
            assert store.direct_reads is direct
            return store

        return go

    # each reader with the chunks read directly (tiler.chunkread_remote, the default) and
    # through zarr's arrays (the code before it)
    backends = {"fsspec": opener("fsspec"), "obstore": opener("obstore"),
                "fsspec-zarr": opener("fsspec", False),
                "obstore-zarr": opener("obstore", False)}  # fmt: skip
    rng = np.random.default_rng(0)
    rows: dict[str, dict[str, list[float]]] = {b: {} for b in backends}
    for _ in range(rounds):
        for name, opener in backends.items():
            r = rows[name]
            t0 = time.perf_counter()
            store = opener()
            t1 = time.perf_counter()
            cams = make_path(store, "default", frames=2, fps=30.0, viewport=(640, 480))
            with open_session(store, budget_mb=128, workers=4) as session:
                t2 = time.perf_counter()
                session.update(cams[0], 1 / 30, wait=True)
                t3 = time.perf_counter()
            r.setdefault("open_ms", []).append((t1 - t0) * 1e3)
            r.setdefault("first_view_ms", []).append((t3 - t2 + t1 - t0) * 1e3)
            blocks = list(store.blocks())
            pick = [blocks[i] for i in rng.choice(len(blocks), 24, replace=False)]
            for level in range(store.k + 1):
                ts = []
                for b in pick:
                    t = time.perf_counter()
                    store.read_level_raw(b, level)
                    ts.append((time.perf_counter() - t) * 1e3)
                r.setdefault(f"level{level}_ms", []).append(statistics.median(ts))
            ts = []
            for b in pick[:8]:
                t = time.perf_counter()
                store.read_levels_raw(b, store.k)
                ts.append((time.perf_counter() - t) * 1e3)
            r.setdefault("block_ms", []).append(statistics.median(ts))
    server.stop()
    summary = {
        name: {key: round(statistics.median(v), 2) for key, v in r.items()}
        for name, r in rows.items()
    }
    doc = {
        "command": "python bench/scale.py --s3-reads",
        "rounds": rounds,
        "store": "2049^2 int16 synthetic, 257^2 blocks, moto S3 server on 127.0.0.1",
        "medians": summary,
        "machine": machine_info(),
    }
    out.write_text(json.dumps(portable(doc), indent=1))
    keys = list(next(iter(summary.values())))
    print("| read | " + " | ".join(summary) + " |\n|---|" + "---:|" * len(summary))
    for k in keys:
        print(f"| {k} | " + " | ".join(f"{summary[b][k]:.1f}" for b in summary) + " |")
    print(f"wrote {out}")
    return doc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=32769)
    ap.add_argument("--block", type=int, default=1025)
    ap.add_argument("--workers", default="2", help="comma-separated worker counts")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--out", default=str(RESULTS / "scale.json"))
    ap.add_argument("--append", action="store_true", help="add to the runs already in --out")
    ap.add_argument(
        "--s3-reads",
        type=int,
        default=0,
        metavar="ROUNDS",
        help="measure fsspec vs obstore reads (direct and through zarr) on a loopback S3 "
        "server instead",
    )
    ap.add_argument(
        "--malloc", type=int, default=0, metavar="ROUNDS",
        help="measure the allocator probe (tiler.malloc) instead",
    )  # fmt: skip
    ap.add_argument(
        "--malloc-tune", choices=("0", "1"), default="1",
        help="TERRASTREAM_MALLOC_TUNE for the runs (0: tiler.malloc off)",
    )  # fmt: skip
    ap.add_argument("--one", choices=MODES, help=argparse.SUPPRESS)
    ap.add_argument("--src", help=argparse.SUPPRESS)
    ap.add_argument("--dst", help=argparse.SUPPRESS)
    ap.add_argument("--address", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.s3_reads:
        s3_reads(a.s3_reads, RESULTS / "s3_reads.json")
        return
    if a.malloc:
        malloc_probe(a.malloc, RESULTS / "malloc.json")
        return
    if a.one:
        one(a.one, a.src, a.dst, int(a.workers), a.block, a.address)
        return
    from tiler.synth import synth_dem

    work = WORK / "scale"
    work.mkdir(parents=True, exist_ok=True)
    src = work / f"synth-{a.size}-int16.tif"
    need = a.size * a.size * 2 * 2  # raw source + about as much for the store
    free = shutil.disk_usage(work).free
    if not src.exists():
        if free < need:
            raise SystemExit(f"{free / 2**30:.1f} GiB free in {work}, need ~{need / 2**30:.1f}")
        t0 = time.perf_counter()
        synth_dem(src, a.size, seed=0, dtype="int16", window=2048)
        print(f"wrote {src} in {time.perf_counter() - t0:.0f} s", flush=True)
    out = Path(a.out)
    results = []
    if a.append and out.exists():
        results = [r for r in json.loads(out.read_text())["runs"]]
    for w in (int(x) for x in a.workers.split(",")):
        for mode in a.modes.split(","):
            r = run_mode(mode, src, work, w, a.block, a.malloc_tune)
            results.append(r)
            print(
                f"{mode:>12} w={w}: {r['elapsed_s']:7.1f} s  {r['blocks_per_s']:.2f} blocks/s  "
                f"worker RSS {r['peak_rss_worker_mib']:.0f} MiB  client RSS "
                f"{r['peak_rss_client_mib']:.0f} MiB  client I/O "
                f"{(r['client_rchar'] + r['client_wchar']) / 2**20:.1f} MiB",
                flush=True,
            )
    header = (
        "| mode | workers | malloc tuned | time s | blocks/s | peak RSS/worker MiB | "
        "client RSS MiB | client I/O MiB | store MiB | load before/after |\n"
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---|"
    )
    print(header)
    for r in results:
        print(
            f"| {r['mode']} | {r['workers']} | {r.get('malloc_tune', '?')} | "
            f"{r['elapsed_s']:.1f} | {r['blocks_per_s']:.2f} | "
            f"{r['peak_rss_worker_mib']:.0f} | {r['peak_rss_client_mib']:.0f} | "
            f"{(r['client_rchar'] + r['client_wchar']) / 2**20:.1f} | "
            f"{r['store_bytes'] / 2**20:.0f} | "
            f"{_load(r, 'loadavg_before')} / {_load(r, 'loadavg_after')} |"
        )
    doc = {
        "commands": (
            (json.loads(out.read_text()).get("commands", []) if a.append and out.exists() else [])
            + ["python bench/scale.py " + " ".join(sys.argv[1:])]
        ),
        "size": a.size,
        "block_size": a.block,
        "source_bytes": a.size * a.size * 2,
        "machine": machine_info(),
        "runs": results,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(portable(doc), indent=1))
    plot(results, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
