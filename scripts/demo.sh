#!/usr/bin/env bash
# The end-to-end demo on a synthetic scene:
#   synth -> compress (every training view a JPEG at quality 10) -> validate -> inspect-dqt -> manifest ->
#   train (the gsplat baseline and JSGS, at the same Gaussian budget) -> metrics -> a test view side by side.
# Everything lands in demo_out/ (recreated on each run). CPU is fine (a few minutes on 2 idle cores); CUDA
# (gsplat) is used when present. Training shows its progress on stderr; what stdout shows is also written
# into README.md between its demo-output markers (DEMO_README=0: not), with the side-by-side image as
# docs/images/demo_side_by_side.png, so the README shows the output of the code as it is.
# JSGS runs the mcmc preset's recipe with DEMO_JSGS_OPTIONS (method_options, JSON) over it: by default
# base_noise_ref 16 instead of the preset's 2, which the demo says where it trains (README: why).
# Knobs: DEMO_OUT, DEMO_SEED (0: the scene, the quality assignment and training), DEMO_ITERS, DEMO_DEVICE,
# DEMO_SIZE, DEMO_TEXTURE, DEMO_BUDGET (Gaussians), DEMO_SCHEDULE (a compress schedule), DEMO_QUALITY (the
# quality of DEMO_SCHEDULE fixed), DEMO_JSGS_OPTIONS ('{}': the preset's recipe unchanged), DEMO_PARALLEL
# (1: train both methods at once, the default with two or more cores; 0: one after the other).
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${DEMO_BIN:-.venv/bin}
OUT=${DEMO_OUT:-demo_out}
SEED=${DEMO_SEED:-0}
ITERS=${DEMO_ITERS:-1500}
SIZE=${DEMO_SIZE:-64x48}
TEXTURE=${DEMO_TEXTURE:-8}
BUDGET=${DEMO_BUDGET:-2000}
SCHEDULE=${DEMO_SCHEDULE:-fixed}
QUALITY=${DEMO_QUALITY:-10}
JSGS_OPTIONS=${DEMO_JSGS_OPTIONS:-'{"base_noise_ref": 16}'}
README=${DEMO_README:-1}
PARALLEL=${DEMO_PARALLEL:-$([ "$(nproc)" -ge 2 ] && echo 1 || echo 0)}
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
LOAD=$(cut -d' ' -f1 /proc/loadavg 2>/dev/null || echo n/a)
echo "== 1. synthetic scene ($SIZE, texture scale $TEXTURE, seed $SEED)"
$BIN/jsgstools synth "$OUT/scene" --size "$SIZE" --views 24 --texture-scale "$TEXTURE" --seed "$SEED" \
    | show '^synth:'
if [ "$SCHEDULE" = fixed ]; then
    echo "== 2. JPEG dataset (every training view at quality $QUALITY)"
    QOPT=(--quality "$QUALITY")
else
    echo "== 2. mixed-quality dataset ($SCHEDULE schedule, seed $SEED)"
    QOPT=()
fi
$BIN/jsgstools compress "$OUT/scene" --out "$OUT/data" --schedule "$SCHEDULE" "${QOPT[@]}" --seed "$SEED" \
    | show '^  (quality|views) '
echo "== 3. validate"
$BIN/jsgstools validate "$OUT/data" | show '^(split|ok)'
echo "== 4. JPEG state of the training views"
$BIN/jsgstools inspect-dqt "$OUT"/data/images/*.jpg | show '^  (IJG quality|sampling) '
echo "== 5. manifest"
$BIN/jsgstools manifest "$OUT/data" --out "$OUT/data/manifest.json" --force | show '^manifest:'
# the same budget for both methods (gsplat's MCMC strategy), so that model size does not decide the outcome;
# preset and length pinned here, whatever jsgs train's defaults are; JSGS's method options over the preset's
# from a config file. With two or more cores both train at once, one thread each (the results are the same
# as one after the other); their progress lines go to stderr, marked [gsplat] and [jsgs].
printf '{"method_options": %s}\n' "$JSGS_OPTIONS" > "$OUT/jsgs_options.json"
if [ "$PARALLEL" = 1 ]; then HOW="both at once, one thread each"; else HOW="one after the other"; fi
echo "== 6. train gsplat and JSGS ($ITERS steps each on $DEVICE, at most $BUDGET Gaussians; $HOW)"
if [ "$JSGS_OPTIONS" = '{}' ]; then
    echo "JSGS's recipe: the mcmc preset's, unchanged"
else
    echo "JSGS's recipe: NOT the default: the mcmc preset's with method_options $JSGS_OPTIONS over it"
fi
train() { # method [options]
    local method=$1
    shift
    $BIN/jsgs train "$OUT/data/manifest.json" --out "$OUT/run_$method" --method "$method" --preset mcmc \
        "$@" --cap-max "$BUDGET" --iterations "$ITERS" --eval-at "$ITERS" --device "$DEVICE" --seed "$SEED" \
        > "$OUT/train_$method.log" 2> >(tee "$OUT/train_$method.err" | sed -u "s/^/[$method] /" >&2)
}
if [ "$PARALLEL" = 1 ]; then
    OMP_NUM_THREADS=1 train gsplat &
    G=$!
    OMP_NUM_THREADS=1 train jsgs --config "$OUT/jsgs_options.json" &
    J=$!
    wait $G
    wait $J
else
    train gsplat
    train jsgs --config "$OUT/jsgs_options.json"
fi
for method in gsplat jsgs; do
    cat "$OUT/train_$method.err" "$OUT/train_$method.log" | show '^(note: base_by_view|complete)' \
        | sed "s/^/$method: /"
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
print(f"JSGS against gsplat: {lp}, PSNR {j['psnr'] - g['psnr']:+.3f} dB, SSIM {j['ssim'] - g['ssim']:+.4f}")
if None not in (g["lpips"], j["lpips"]):
    met = j["lpips"] <= 0.95 * g["lpips"] and j["psnr"] >= g["psnr"]
    print(f"target (LPIPS at least 5 % lower, PSNR not lower): {'met' if met else 'NOT met'}")
PY
echo "== 8. a test view side by side"
$BIN/python scripts/demo_panel.py "$OUT/data" "$OUT/run_gsplat" "$OUT/run_jsgs" --out "$OUT/side_by_side.png"
T=$((SECONDS - START))
echo "== done in $((T / 60)) min $((T % 60)) s on $DEVICE ($(nproc) cores, load $LOAD at the start): outputs in $OUT/"
}

demo | tee "$OUT/demo_output.txt"
if [ "$README" = 1 ] && grep -q '<!-- demo-output -->' README.md 2>/dev/null; then
    if $BIN/python scripts/demo_readme.py "$OUT/demo_output.txt" README.md; then
        cp "$OUT/side_by_side.png" docs/images/demo_side_by_side.png
        echo "README.md: its demo output and docs/images/demo_side_by_side.png are this run's" >&2
    fi
fi
echo "The commands are in .venv/bin: 'source .venv/bin/activate' puts jsgs and jsgstools on PATH." >&2
