#!/usr/bin/env bash
# The end-to-end demo on the embedded synthetic scene:
#   synth -> compress (mixed qualities) -> validate -> inspect-dqt -> manifest -> train (gsplat baseline and
#   JSGS) -> metrics. Everything lands in demo_out/ (recreated on each run). CPU is fine (a few minutes on 2
#   cores); CUDA (gsplat) is used when present. Knobs: DEMO_OUT, DEMO_ITERS, DEMO_DEVICE, DEMO_SIZE.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
OUT=${DEMO_OUT:-demo_out}
ITERS=${DEMO_ITERS:-500}
SIZE=${DEMO_SIZE:-96x72}
DEVICE=${DEMO_DEVICE:-$($BIN/python -c 'import torch; print("cuda" if torch.cuda.is_available() else "cpu")')}
# LPIPS needs the AlexNet backbone weights; with none, LPIPS is reported as null (never made up).
if [ -z "${JSGS_LPIPS_WEIGHTS:-}" ] && [ -f ../shared/lpips/alexnet_features.pth ]; then
    export JSGS_LPIPS_WEIGHTS=../shared/lpips/alexnet_features.pth
fi

rm -rf "$OUT"
mkdir -p "$OUT"
echo "== 1. synthetic scene ($SIZE)"
$BIN/jsgstools synth "$OUT/scene" --size "$SIZE" --views 24 --point-density 0.3
echo "== 2. mixed-quality dataset (gaussian schedule, seed 0)"
$BIN/jsgstools compress "$OUT/scene" --out "$OUT/data" --schedule gaussian --seed 0
echo "== 3. validate"
$BIN/jsgstools validate "$OUT/data"
echo "== 4. JPEG state of the training views"
$BIN/jsgstools inspect-dqt "$OUT"/data/images/*.jpg | tail -n 12
echo "== 5. manifest"
$BIN/jsgstools manifest "$OUT/data" --out "$OUT/data/manifest.json" --force
for method in gsplat jsgs; do
    echo "== 6. train --method $method ($ITERS iterations on $DEVICE)"
    $BIN/jsgs train "$OUT/data/manifest.json" --out "$OUT/run_$method" --method "$method" \
        --iterations "$ITERS" --eval-at "$ITERS" --device "$DEVICE"
done
echo "== 7. metrics (test views against their uncompressed references)"
$BIN/python - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
print(f"{'method':8} {'PSNR':>7} {'SSIM':>7} {'LPIPS':>7} {'#Gauss':>7} {'s/iter':>7}")
for method in ("gsplat", "jsgs"):
    m = json.load(open(f"{out}/run_{method}/metrics.json"))
    e = m["evals"][-1]
    lp = "n/a" if e["lpips"] is None else f"{e['lpips']:.4f}"
    print(f"{method:8} {e['psnr']:7.3f} {e['ssim']:7.4f} {lp:>7} {e['num_gaussians']:7d} {e['time_per_iteration_s']:7.3f}")
PY
echo "== done: outputs in $OUT/"
