#!/usr/bin/env bash
# The end-to-end demo on a synthetic scene:
#   synth -> compress (mixed JPEG qualities) -> validate -> inspect-dqt -> manifest -> train (the gsplat
#   baseline and JSGS, at the same Gaussian budget) -> metrics -> a test view side by side.
# Everything lands in demo_out/ (recreated on each run). CPU is fine (about 3 minutes on 2 cores); CUDA
# (gsplat) is used when present. Knobs: DEMO_OUT, DEMO_ITERS (1500), DEMO_DEVICE, DEMO_SIZE (64x48),
# DEMO_BUDGET (2000 Gaussians), DEMO_SCHEDULE (uniform: q = 10, 20, ..., 90 in equal shares).
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
OUT=${DEMO_OUT:-demo_out}
ITERS=${DEMO_ITERS:-1500}
SIZE=${DEMO_SIZE:-64x48}
BUDGET=${DEMO_BUDGET:-2000}
SCHEDULE=${DEMO_SCHEDULE:-uniform}
DEVICE=${DEMO_DEVICE:-$($BIN/python -c 'import torch; print("cuda" if torch.cuda.is_available() else "cpu")')}
# LPIPS needs the AlexNet backbone weights; with none (and no network), LPIPS is reported as null.
if [ -z "${JSGS_LPIPS_WEIGHTS:-}" ] && [ -f ../shared/lpips/alexnet_features.pth ]; then
    export JSGS_LPIPS_WEIGHTS=../shared/lpips/alexnet_features.pth
fi

rm -rf "$OUT"
mkdir -p "$OUT"
echo "== 1. synthetic scene ($SIZE, textures a few hundred Gaussians can learn)"
$BIN/jsgstools synth "$OUT/scene" --size "$SIZE" --views 24 --texture-scale 8
echo "== 2. mixed-quality dataset ($SCHEDULE schedule, seed 0)"
$BIN/jsgstools compress "$OUT/scene" --out "$OUT/data" --schedule "$SCHEDULE" --seed 0
echo "== 3. validate"
$BIN/jsgstools validate "$OUT/data"
echo "== 4. JPEG state of some training views"
$BIN/jsgstools inspect-dqt "$OUT"/data/images/*.jpg | tail -n 5
echo "== 5. manifest"
$BIN/jsgstools manifest "$OUT/data" --out "$OUT/data/manifest.json" --force
# the same budget for both methods (gsplat's MCMC strategy), so that model size does not decide the outcome
echo "{\"strategy\": {\"cap_max\": $BUDGET}}" > "$OUT/budget.json"
for method in gsplat jsgs; do
    echo "== 6. train --method $method ($ITERS steps on $DEVICE, at most $BUDGET Gaussians)"
    $BIN/jsgs train "$OUT/data/manifest.json" --out "$OUT/run_$method" --method "$method" --preset mcmc \
        --config "$OUT/budget.json" --iterations "$ITERS" --eval-at "$ITERS" --device "$DEVICE" --quiet
done
echo "== 7. metrics (test views against their uncompressed references; one seed)"
$BIN/python - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
print(f"{'method':8} {'PSNR':>7} {'SSIM':>7} {'LPIPS':>7} {'#Gauss':>7} {'s/step':>7}")
for method in ("gsplat", "jsgs"):
    m = json.load(open(f"{out}/run_{method}/metrics.json"))
    e = m["evals"][-1]
    lp = "n/a" if e["lpips"] is None else f"{e['lpips']:.4f}"
    print(f"{method:8} {e['psnr']:7.3f} {e['ssim']:7.4f} {lp:>7} {e['num_gaussians']:7d} {e['time_per_iteration_s']:7.3f}")
PY
echo "== 8. a test view side by side"
$BIN/python scripts/demo_panel.py "$OUT/data" "$OUT/run_gsplat" "$OUT/run_jsgs" --out "$OUT/side_by_side.png"
echo "== done: outputs in $OUT/"
