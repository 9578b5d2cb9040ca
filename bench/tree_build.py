"""What ``geometry-splitting`` spends building a block's quadtree texture on the render thread
(issue 14): the exact deepest-depth errors (``quad_errors``: numpy and the numba kernel, checked
equal), the texture itself (``stored_tree``: numpy, and with its corner ranges compiled) and
the mask's mixed nodes (derived, or unpacked
from what a session's loaders kept), per block and resident level; below full resolution also
the packed texture the former way (``stored_tree``, σ = ∞ at the mixed nodes, ``packed``)
against ``packed_tree`` (the same bytes, checked) and its compact layout, as deep as the
level needs (``depth=texture_depth``: what the GPU holds now).

Usage::

    python bench/tree_build.py [STORE ...] [--levels full,7,3] [--reps 5] [--out PATH]

Default stores: N44W072 reprojected to UTM in 1025² blocks (``terrastream tile N44W072.hgt …
--dst-crs auto --block-size 1025``, made in ``bench/work`` if the real DEM is there; nodata at
its edges) and the 4097² synthetic store of 1025² blocks. Reported: the median ms over the
blocks of each part's median of ``--reps`` calls. The numba kernels are loaded (and their
outputs compared with numpy's, the tree's bytes too) before timing. Run it in a checkout of
each commit to compare code versions; prints a table and writes ``bench/results/tree_build.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np  # noqa: E402

from bench.common import (  # noqa: E402
    REAL_HGT,
    REPO,
    RESULTS,
    S4097,
    WORK,
    ensure_store,
    machine_info,
    portable,
)
from render.strategies.geometry_splitting import pure  # noqa: E402
from render.strategies.geometry_splitting.pure import quad_errors, stored_tree  # noqa: E402
from streamer.nodata import has_boundary, mixed_nodes  # noqa: E402
from tiler.store import open_store  # noqa: E402

N44W072_UTM = WORK / "n44w072_utm_b1025.zarr"


def _utm_store() -> Path | None:
    if not (N44W072_UTM / "zarr.json").exists():
        if not REAL_HGT.exists():
            return None
        exe = str(Path(sys.executable).with_name("terrastream"))
        cmd = [exe, "tile", str(REAL_HGT), str(N44W072_UTM), "--dst-crs", "auto"]
        subprocess.run([*cmd, "--block-size", "1025"], check=True)
    return N44W072_UTM


def _ms(reps: int, fn, *args) -> float:
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn(*args)
        ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts)


def _kernel():
    try:
        from render.strategies.geometry_splitting import kernels
    except ImportError:  # (a checkout before the kernel)
        return None
    return kernels if kernels.warm_up() else None


def _unpacked(mixed, k):
    try:
        from streamer.nodata import pack_mixed, unpack_mixed
    except ImportError:  # (a checkout before the packed mixed nodes)
        return None
    packed = pack_mixed(mixed, k)
    return lambda: unpack_mixed(packed)


def _bytes(tree) -> list[bytes]:
    return [x.tobytes() for f in ("sigma", "zmin", "zmax") for x in getattr(tree, f)]


def _texture_via_tree(bound, grid, mixed, depth=None) -> np.ndarray:
    """The packed texture the former way: the per-node tree, σ = ∞ at the mixed nodes
    (``depth``: its compact layout)."""
    tree = stored_tree(bound, grid)
    for d, sig in enumerate(tree.sigma):
        if mixed is not None:
            sig[mixed[d]] = np.inf
    return tree.packed() if depth is None else tree.packed(depth)


def measure(path: Path, levels: list[str], reps: int) -> list[dict]:
    """Per resident level: the median over the blocks of each part's median ms."""
    s = open_store(path)
    k, cap = s.k, s.meta.error_cap
    kern = _kernel()
    rows = []
    for name in levels:
        lv = k if name == "full" else int(name)
        parts: dict[str, list[float]] = {}
        for b in s.blocks():
            grid = s.read_block(b, max_level=lv)
            mask = s.read_mask(b) if s.index.has_nodata[b] else None
            bound = s.read_errors(b)["bound"]
            deep = range(cap + 1, k) if lv == k else range(0)
            exact = quad_errors(grid, mask, deep) if len(deep) else None
            if len(deep):
                parts.setdefault("quad_errors numpy", []).append(
                    _ms(reps, quad_errors, grid, mask, deep)
                )
                if kern is not None:
                    got = kern.quad_errors(grid, mask, deep, kernels="numba")
                    assert all(np.array_equal(got[d], exact[d]) for d in deep)
                    parts.setdefault("quad_errors numba", []).append(
                        _ms(reps, kern.quad_errors, grid, mask, deep, "numba")
                    )
            parts.setdefault("stored_tree", []).append(_ms(reps, stored_tree, bound, grid, exact))
            if kern is not None and hasattr(kern, "stored_tree"):
                ref = stored_tree(bound, grid, exact)
                got = kern.stored_tree(bound, grid, exact, "numba")
                assert _bytes(got) == _bytes(ref), f"block {b}: the compiled tree differs"
                parts.setdefault("stored_tree numba", []).append(
                    _ms(reps, kern.stored_tree, bound, grid, exact, "numba")
                )
            if lv < k and hasattr(pure, "packed_tree"):  # the texture below full resolution
                mixed = mixed_nodes(mask, k)[:k] if has_boundary(mask) else None
                via = partial(_texture_via_tree, bound, grid, mixed)
                assert pure.packed_tree(bound, grid, mixed).tobytes() == via().tobytes()
                parts.setdefault("texture via stored_tree", []).append(_ms(reps, via))
                parts.setdefault("texture packed_tree", []).append(
                    _ms(reps, pure.packed_tree, bound, grid, mixed)
                )
                if hasattr(pure, "texture_depth"):  # as deep as the level needs (the GPU's)
                    top = pure.texture_depth(k, lv, cap)
                    compact = partial(pure.packed_tree, bound, grid, mixed, depth=top)
                    want = _texture_via_tree(bound, grid, mixed, top).tobytes()
                    assert compact().tobytes() == want, f"block {b}: the compact texture differs"
                    parts.setdefault("texture compact", []).append(_ms(reps, compact))
            if has_boundary(mask):
                parts.setdefault("mixed nodes derived", []).append(_ms(reps, mixed_nodes, mask, k))
                unpack = _unpacked(mixed_nodes(mask, k), k)
                if unpack is not None:
                    parts.setdefault("mixed nodes unpacked", []).append(_ms(reps, unpack))
        row = {"store": path.name, "level": name, "blocks": len(list(s.blocks()))}
        row.update({p: statistics.median(v) for p, v in parts.items()})
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stores", nargs="*", type=Path)
    ap.add_argument("--levels", default="full,7,3", help="resident levels ('full' = k)")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--out", type=Path, default=RESULTS / "tree_build.json")
    a = ap.parse_args(argv)
    stores = a.stores
    if not stores:
        utm = _utm_store()
        if utm is None:
            print(f"# {REAL_HGT.name} not found: the UTM store is skipped")
        stores = [p for p in (utm, S4097) if p is not None and ensure_store(p)]
    rows = []
    for path in stores:
        rows += measure(path, a.levels.split(","), a.reps)
    cols = ["quad_errors numpy", "quad_errors numba", "stored_tree", "stored_tree numba",
            "texture via stored_tree", "texture packed_tree", "texture compact",
            "mixed nodes derived",
            "mixed nodes unpacked"]  # fmt: skip
    print(f"{'store':28} {'level':>5} " + " ".join(f"{c:>21}" for c in cols))
    for r in rows:
        vals = " ".join(f"{r[c]:21.2f}" if c in r else f"{'—':>21}" for c in cols)
        print(f"{r['store']:28} {r['level']:>5} {vals}")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    out = {"reps": a.reps, "rows": rows, "machine": machine_info()}
    a.out.write_text(json.dumps(portable(out), indent=1))
    print(f"wrote {a.out.relative_to(REPO) if a.out.is_relative_to(REPO) else a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
