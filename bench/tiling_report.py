"""The tiling benchmark's targets (PASS/MISS per input) and its printed tables.

Pure functions of the result dicts :func:`bench.tiling.bench_input` makes; the read targets are
:func:`bench.tiling_reads.read_targets`. See bench/tiling.py.
"""

from __future__ import annotations

import json
from typing import Any

from bench.tiling_child import MB
from bench.tiling_reads import print_targets, read_targets, target_met

# Targets: issue 14's, which replace issue 2's weaker ones (size <= 0.7 / 0.9, RSS <= 600 MB,
# every input's tiling time <= 0.5x).
T_SIZE_VS_COG_OVR = 0.6
T_SIZE_VS_COG = 0.85
T_TIME_VS_COG_OVR = 0.5  # the synthetic 4097^2 and 16385^2 DEMs
T_TIME_REAL_VS_COG_OVR = 1.0  # a real DEM (the single 1201^2 SRTM tile), start-up included
T_RSS_MB = 400.0
T_RSS_MIN_SIZE = 16385  # the RSS target is stated for the 16385^2 int16 DEM


def time_limit(name: str) -> float:
    """The tiling-time target of input ``name``: the synthetic DEMs' (``synthN``) or a real
    DEM's (the SRTM tile of ``--real``)."""
    return T_TIME_VS_COG_OVR if name.startswith("synth") else T_TIME_REAL_VS_COG_OVR


def check_targets(r: dict[str, Any]) -> list[dict[str, Any]]:
    """PASS/MISS of each target for one input."""
    ratios, reads, tile_ = r["ratios"], r["reads"], r["tile"]
    out = [
        {
            "target": f"stored size <= {T_SIZE_VS_COG_OVR} x COG with overviews",
            "value": ratios["store_vs_cog_ovr"],
            "limit": T_SIZE_VS_COG_OVR,
            "detail": f"{r['store_bytes']['total'] / MB:.2f} MB vs "
            f"{r['cog']['with_overviews']['bytes'] / MB:.2f} MB",
        },
        {
            "target": f"stored size <= {T_SIZE_VS_COG} x COG without overviews",
            "value": ratios["store_vs_cog_no_ovr"],
            "limit": T_SIZE_VS_COG,
            "detail": f"{r['store_bytes']['total'] / MB:.2f} MB vs "
            f"{r['cog']['no_overviews']['bytes'] / MB:.2f} MB",
        },
        {
            "target": f"tiling time <= {time_limit(r['name'])} x COG-with-overviews build time",
            "value": ratios["tile_time_vs_cog_ovr_time"],
            "limit": time_limit(r["name"]),
            "detail": f"{tile_['seconds']:.2f} s vs {r['cog']['with_overviews']['seconds']:.2f} s",
        },
        *read_targets(reads),
    ]
    if r["dtype"] == "int16" and max(r["height"], r["width"]) >= T_RSS_MIN_SIZE:
        peak = max(tile_["peak_rss_mb"], tile_["wait4_maxrss_mb"])
        out.append(
            {
                "target": f"peak RSS tiling {r['height']}^2 int16 <= {T_RSS_MB:.0f} MB",
                "value": peak,
                "limit": T_RSS_MB,
                "detail": f"{peak:.0f} MB (sampled {tile_['peak_rss_mb']:.0f}, "
                f"kernel maxrss {tile_['wait4_maxrss_mb']:.0f})",
            }
        )
    for t in out:
        t["pass"] = target_met(t)
    if reads["lossless_mismatches"]:
        out.append(
            {
                "target": "store read_block == COG window (both lossless)",
                "value": len(reads["lossless_mismatches"]),
                "limit": 0,
                "detail": json.dumps(reads["lossless_mismatches"]),
                "pass": False,
            }
        )
    return out


def print_report(results: list[dict[str, Any]]) -> None:
    cols = [
        ("input", 18, "s"),
        ("tile s", 8, ".2f"),
        ("MB/s", 7, ".1f"),
        ("RSS MB", 7, ".0f"),
        ("store MB", 9, ".2f"),
        ("/COG+ovr", 8, ".3f"),
        ("/COG", 6, ".3f"),
        ("/pyramid", 8, ".3f"),
        ("/raw", 6, ".3f"),
        ("t/COG t", 7, ".3f"),
        ("block ms", 8, ".2f"),
        ("COG win ms", 10, ".2f"),
    ]
    head = " ".join(f"{c:>{w}}" if i else f"{c:<{w}}" for i, (c, w, _) in enumerate(cols))
    print()
    print(head)
    print("-" * len(head))
    for r in results:
        vals = [
            r["name"],
            r["tile"]["seconds"],
            r["tile"]["mb_per_s"],
            r["tile"]["peak_rss_mb"],
            r["store_bytes"]["total"] / MB,
            r["ratios"]["store_vs_cog_ovr"],
            r["ratios"]["store_vs_cog_no_ovr"],
            r["ratios"]["store_vs_pyramid_raw"],
            r["ratios"]["store_vs_raw"],
            r["ratios"]["tile_time_vs_cog_ovr_time"],
            r["reads"]["store_block_ms"],
            r["reads"]["cog_window_ms"],
        ]
        print(
            " ".join(
                f"{v:<{w}{f}}" if i == 0 else f"{v:>{w}{f}}"
                for i, (v, (_, w, f)) in enumerate(zip(vals, cols, strict=True))
            )
        )
    print()
    print(
        f"{'input':<18} {'COG+ovr s':>9} {'COG s':>7} {'COG+ovr MB':>10} {'COG MB':>8} "
        f"{'COG RSS MB':>10} {'coarse ms':>9} {'COG ovr ms':>10} {'warm blk ms':>11}"
    )
    for r in results:
        c, rd = r["cog"], r["reads"]
        ovr = rd["cog_overview_ms"]
        print(
            f"{r['name']:<18} {c['with_overviews']['seconds']:>9.2f} "
            f"{c['no_overviews']['seconds']:>7.2f} {c['with_overviews']['bytes'] / MB:>10.2f} "
            f"{c['no_overviews']['bytes'] / MB:>8.2f} {c['with_overviews']['peak_rss_mb']:>10.0f} "
            f"{rd['store_coarse_ms']:>9.2f} {'n/a' if ovr is None else f'{ovr:.2f}':>10} "
            f"{rd['store_block_warm_ms']:>11.2f}"
        )
    print(
        "  coarse = store levels 0..k-2 vs the COG overview at the same resolution (1/4); "
        "warm blk = read_block on an already-used store object"
    )
    print()
    print("store bytes by component (MB):")
    for r in results:
        b = r["store_bytes"]
        parts = ", ".join(f"{n} {b[n] / MB:.3f}" for n in ("levels", "errors", "mask", "index"))
        print(
            f"  {r['name']:<18} {parts} (of which level/order_index tables "
            f"{r['store_layout_table_bytes'] / MB:.3f}), metadata {b['metadata'] / 1024:.1f} KiB"
        )
    print()
    print_targets(results, 18)
