#!/usr/bin/env bash
# The end-to-end demo on a synthetic scene:
#   synth -> compress (mixed JPEG qualities) -> validate -> inspect-dqt -> manifest -> train (the gsplat
#   baseline and JSGS, at the same Gaussian budget) -> metrics -> a test view side by side.
# Everything lands in demo_out/ (recreated on each run). CPU is fine (a few minutes on 2 idle cores); CUDA
# (gsplat) is used when present. Training shows its progress on stderr; what stdout shows is also written
# into README.md between its demo-output markers (DEMO_README=0: not), with the side-by-side image as
# docs/images/demo_side_by_side.png, so the README shows the output of the code as it is.
# Knobs: DEMO_OUT, DEMO_SEED (0: the scene, the quality assignment and training), DEMO_ITERS, DEMO_DEVICE,
# DEMO_SIZE, DEMO_TEXTURE, DEMO_BUDGET (Gaussians), DEMO_SCHEDULE (a compress schedule).
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${DEMO_BIN:-.venv/bin}
OUT=${DEMO_OUT:-demo_out}
SEED=${DEMO_SEED:-0}
ITERS=${DEMO_ITERS:-1500}
SIZE=${DEMO_SIZE:-64x48}
TEXTURE=${DEMO_TEXTURE:-8}
BUDGET=${DEMO_BUDGET:-2000}
SCHEDULE=${DEMO_SCHEDULE:-uniform}
README=${DEMO_README:-1}
DEVICE=${DEMO_DEVICE:-$($BIN/python -c 'import torch; print("cuda" if torch.cuda.is_available() else "cpu")')}
# LPIPS needs the AlexNet backbone weights; with none (and no network), LPIPS is reported as null.
if [ -z "${JSGS_LPIPS_WEIGHTS:-}" ] && [ -f ../shared/lpips/alexnet_features.pth ]; then
    export JSGS_LPIPS_WEIGHTS=../shared/lpips/alexnet_features.pth
fi

# demo_out/ is recreated, but only when it is the demo's own (or empty): nothing else is deleted
if [ -n "$(ls -A "$OUT" 2>/dev/null)" ] && [ ! -f "$OUT/demo_output.txt" ] && [ ! -f "$OUT/scene/.jsgstools.json" ]; then
    echo "error: $OUT: not a folder of this demo (no demo_output.txt); name another with DEMO_OUT" >&2
    exit 1
fi
rm -rf "$OUT"
mkdir -p "$OUT"

# the lines of a tool's output worth showing (pattern $1); all of it goes to $OUT/tools.log
show() { tee -a "$OUT/tools.log" | { grep -E "$1" || true; }; }

demo() {
START=$SECONDS
echo "== 1. synthetic scene ($SIZE, texture scale $TEXTURE, seed $SEED)"
$BIN/jsgstools synth "$OUT/scene" --size "$SIZE" --views 24 --texture-scale "$TEXTURE" --seed "$SEED" \
    | show '^synth:'
echo "== 2. mixed-quality dataset ($SCHEDULE schedule, seed $SEED)"
$BIN/jsgstools compress "$OUT/scene" --out "$OUT/data" --schedule "$SCHEDULE" --seed "$SEED" \
    | show '^  (quality|views) '
echo "== 3. validate"
$BIN/jsgstools validate "$OUT/data" | show '^(split|ok)'
echo "== 4. JPEG state of the training views"
$BIN/jsgstools inspect-dqt "$OUT"/data/images/*.jpg | show '^  (IJG quality|sampling) '
echo "== 5. manifest"
$BIN/jsgstools manifest "$OUT/data" --out "$OUT/data/manifest.json" --force | show '^manifest:'
# the same budget for both methods (gsplat's MCMC strategy), so that model size does not decide the outcome;
# preset and length pinned here, whatever jsgs train's defaults are
for method in gsplat jsgs; do
    echo "== 6. train --method $method ($ITERS steps on $DEVICE, at most $BUDGET Gaussians)"
    $BIN/jsgs train "$OUT/data/manifest.json" --out "$OUT/run_$method" --method "$method" --preset mcmc \
        --cap-max "$BUDGET" --iterations "$ITERS" --eval-at "$ITERS" --device "$DEVICE" --seed "$SEED" \
        | show '^complete'
done
echo "== 7. metrics (test views against their uncompressed references)"
$BIN/python - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
e = {m: json.load(open(f"{out}/run_{m}/metrics.json"))["evals"][-1] for m in ("gsplat", "jsgs")}
print(f"{'method':8} {'PSNR':>7} {'SSIM':>7} {'LPIPS':>7} {'#Gauss':>7} {'s/step':>7}")
for m, x in e.items():
    lp = "n/a" if x["lpips"] is None else f"{x['lpips']:.4f}"
    print(f"{m:8} {x['psnr']:7.3f} {x['ssim']:7.4f} {lp:>7} {x['num_gaussians']:7d} {x['time_per_iteration_s']:7.3f}")
g, j = e["gsplat"], e["jsgs"]
lp = "LPIPS n/a" if None in (g["lpips"], j["lpips"]) else f"LPIPS {100 * (j['lpips'] / g['lpips'] - 1):+.1f} %"
print(f"JSGS against gsplat: {lp}, PSNR {j['psnr'] - g['psnr']:+.2f} dB, SSIM {j['ssim'] - g['ssim']:+.4f}")
PY
echo "== 8. a test view side by side"
$BIN/python scripts/demo_panel.py "$OUT/data" "$OUT/run_gsplat" "$OUT/run_jsgs" --out "$OUT/side_by_side.png"
T=$((SECONDS - START))
echo "== done in $((T / 60)) min $((T % 60)) s on $DEVICE ($(nproc) cores): outputs in $OUT/"
}

demo | tee "$OUT/demo_output.txt"
if [ "$README" = 1 ] && grep -q '<!-- demo-output -->' README.md 2>/dev/null; then
    $BIN/python scripts/demo_readme.py "$OUT/demo_output.txt" README.md
    cp "$OUT/side_by_side.png" docs/images/demo_side_by_side.png
    echo "README.md: its demo output and docs/images/demo_side_by_side.png are this run's" >&2
fi
echo "The commands are in .venv/bin: 'source .venv/bin/activate' puts jsgs and jsgstools on PATH." >&2
