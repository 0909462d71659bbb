#!/usr/bin/env bash
# The end-to-end demo on the embedded synthetic scene:
#   synth -> compress (mixed qualities) -> validate -> manifest -> train (gsplat baseline and JSGS) -> metrics.
# Everything lands in demo_out/ (recreated on each run). CPU is fine; CUDA is used when present.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
OUT=${DEMO_OUT:-demo_out}
ITERS=${DEMO_ITERS:-600}
DEVICE=${DEMO_DEVICE:-$($BIN/python -c 'import torch; print("cuda" if torch.cuda.is_available() else "cpu")')}

rm -rf "$OUT"
mkdir -p "$OUT"
echo "== 1. synthetic scene"
$BIN/jsgstools synth "$OUT/scene"
echo "== 2. mixed-quality dataset (gaussian schedule, seed 0)"
$BIN/jsgstools compress "$OUT/scene" --out "$OUT/data" --schedule gaussian --seed 0
echo "== 3. validate"
$BIN/jsgstools validate "$OUT/data"
echo "== 4. JPEG state of two training views"
$BIN/jsgstools inspect-dqt $(ls "$OUT"/data/images/*.jpg | head -2)
echo "== 5. manifest"
$BIN/jsgstools manifest "$OUT/data" --out "$OUT/data/manifest.json" --force
if $BIN/jsgs train --help >/dev/null 2>&1; then
    for method in gsplat jsgs; do
        if ! $BIN/jsgs train --help | grep -q -- "--method"; then break; fi
        echo "== 6. train --method $method ($ITERS iterations on $DEVICE)"
        $BIN/jsgs train "$OUT/data/manifest.json" --out "$OUT/run_$method" --method "$method" \
            --iterations "$ITERS" --eval-at "$ITERS" --device "$DEVICE" || {
            echo "(method $method not available yet)"; continue; }
        $BIN/python -c "import json,sys; m=json.load(open(sys.argv[1])); print(json.dumps(m['evals'][-1], indent=1))" \
            "$OUT/run_$method/metrics.json" || true
    done
fi
echo "== done: outputs in $OUT/"
