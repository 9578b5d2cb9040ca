#!/usr/bin/env bash
# The end-to-end demo: generated DEM -> zarr store -> streamed fly-through -> rendered frames
# and statistics. Everything it writes goes to demo-out/.
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
echo "== 3b. check every chunk's checksum and every block's digest against the source"
$TS verify "$OUT/demo.zarr" --source "$OUT/demo.tif"
echo "== 4. export the finest level (a COG whose overviews are the store's levels) and check it"
echo "      is bit-identical to the source"
$TS export "$OUT/demo.zarr" "$OUT/demo-roundtrip.tif" --overwrite
.venv/bin/python - "$OUT/demo.tif" "$OUT/demo-roundtrip.tif" <<'PY'
import sys, numpy as np, rasterio
with rasterio.open(sys.argv[1]) as a, rasterio.open(sys.argv[2]) as b:
    same = np.array_equal(a.read(1), b.read(1)) and a.transform == b.transform and a.crs == b.crs
print("round trip bit-identical:", same)
sys.exit(0 if same else 1)
PY
echo "== 5. stream a 5 s fly-through in real time (20 ms added to every store request)"
$TS stream "$OUT/demo.zarr" --frames 300 --fps 60 --latency-ms 20 --workers 8 \
    --json "$OUT/stream.json" --plot "$OUT/stream.png" --overwrite
echo "== 6. render an overview at tau = 1 px"
$TS render "$OUT/demo.zarr" --size 1024x768 --tau 1 -o "$OUT/view.png" --overwrite
echo "== 7. render 30 frames of the fly-through"
$TS flythrough "$OUT/demo.zarr" --frames 30 --size 640x480 --tau 1 --out "$OUT/frames" --overwrite
echo "== 8. measure the speed/accuracy trade on a low oblique view from 8 km south of the DEM"
echo "      (the overview of step 6 is drawn from the coarsest patches at every tau >= 1)"
LOW=(--camera 530735,4930000,4000 --yaw 0 --pitch -12)
$TS tradeoff "$OUT/demo.zarr" --size 640x480 --taus 0.5,1,2,4,8 "${LOW[@]}" \
    --json "$OUT/tradeoff.json" --plot "$OUT/tradeoff.png" --overwrite
$TS tradeoff "$OUT/demo.zarr" --size 640x480 --taus 0.5,1,2,4,8 --metric conservative \
    "${LOW[@]}" --json "$OUT/tradeoff-conservative.json" --overwrite
echo "== 9. compare the five papers' LOD strategies (and chunk-tessellation-gpu) on the same fly-through (a quick run)"
$TS compare "$OUT/demo.zarr" --quick --json "$OUT/compare.json" --plot "$OUT/compare.png" \
    --overwrite
echo "== done: see $OUT/ (view.png, frames/, stream.png, tradeoff.png, compare.png, *.json)"
