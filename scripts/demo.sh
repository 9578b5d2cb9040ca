#!/usr/bin/env bash
# The end-to-end demo: generated DEM -> zarr store -> info (and, as the project grows,
# streamed fly-through -> rendered frames and statistics). Outputs go to demo-out/.
set -euo pipefail
cd "$(dirname "$0")/.."
TS=.venv/bin/terrastream
OUT=demo-out
mkdir -p "$OUT"
echo "== 1. generate a 2049 x 2049 fractal DEM (int16, seed 7)"
$TS synth "$OUT/demo.tif" --size 2049 --seed 7 --overwrite
echo "== 2. tile it into a non-redundant zarr store (blocks of 513^2)"
$TS tile "$OUT/demo.tif" "$OUT/demo.zarr" --block-size 513 --overwrite
echo "== 3. describe the store"
$TS info "$OUT/demo.zarr"
echo "== 4. export level 9 of 9 and check it is bit-identical to the source"
$TS export "$OUT/demo.zarr" "$OUT/demo-roundtrip.tif" --overwrite
.venv/bin/python - "$OUT/demo.tif" "$OUT/demo-roundtrip.tif" <<'PY'
import sys, numpy as np, rasterio
a, b = (rasterio.open(p) for p in sys.argv[1:3])
same = np.array_equal(a.read(1), b.read(1)) and a.transform == b.transform and a.crs == b.crs
print("round trip bit-identical:", same)
sys.exit(0 if same else 1)
PY
