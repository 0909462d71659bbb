#!/usr/bin/env bash
# Installs jsgs the way a user or a container does (a built wheel, not the checkout) and runs every dataset
# command and a 30-step CPU training from a folder outside the checkout, so that anything the programs read
# at run time and the wheel lacks fails here.
#   bash scripts/wheel_smoke.sh            (CI runs it after the test suite)
# Knobs: PYTHON (python3), SMOKE_DIR (a fresh temporary folder, removed at the end unless SMOKE_KEEP=1).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
PY=${PYTHON:-python3}
WORK=${SMOKE_DIR:-$(mktemp -d -t jsgs-wheel-smoke.XXXXXX)}
[ "${SMOKE_KEEP:-0}" = 1 ] || trap 'rm -rf "$WORK"' EXIT
t0=$(date +%s)
step() { echo "wheel smoke [$(( $(date +%s) - t0 )) s]: $*"; }

step "building the wheel"
"$PY" -m pip wheel -q --no-deps -w "$WORK/dist" "$ROOT" 2>&1 | grep -v "is ignored" || true
WHEEL=$(ls "$WORK"/dist/jsgs-*.whl)
step "built $(basename "$WHEEL"); package data in it:"
"$PY" - "$WHEEL" <<'PY'
import sys, zipfile
names = zipfile.ZipFile(sys.argv[1]).namelist()
for pattern in ("jsgs/schemas/manifest.schema.json", "jsgs/kernels/csrc/ssim.cu", "jsgs/metrics/weights/lpips_v0.1_alex.pth"):
    if pattern not in names:
        sys.exit(f"wheel smoke: {pattern} is missing from the wheel")
if any(n.startswith("cli/") for n in names):
    sys.exit("wheel smoke: the wheel installs a top-level 'cli' package")
print(f"  {sum(n.startswith('jsgs/schemas/') for n in names)} schemas, CUDA sources, LPIPS heads; no top-level cli")
PY
step "fresh venv: CPU torch first, then the wheel"
"$PY" -m venv "$WORK/venv"
V="$WORK/venv/bin"
"$V/python" -m pip install -q --upgrade pip 2>&1 | grep -v "is ignored" || true
if "$PY" -c 'import torch; assert torch.cuda.is_available()' 2>/dev/null; then
    "$V/python" -m pip install -q torch 2>&1 | grep -v "is ignored" || true
else
    "$V/python" -m pip install -q torch==2.13.0 2>&1 | grep -v "is ignored" || true
fi
"$V/python" -m pip install -q "$WHEEL" 2>&1 | grep -v "is ignored" || true

cd "$WORK"   # nothing of the checkout is importable from here
"$V/python" -c "import jsgs, sys; assert '$ROOT' not in jsgs.__file__, jsgs.__file__; print('  jsgs from', jsgs.__file__)"
step "jsgstools synth"
"$V/jsgstools" synth scene --size 64x48 --views 10 --point-density 0.3 --seed 0 > synth.log
step "jsgstools compress"
"$V/jsgstools" compress scene --out data --schedule gaussian --seed 0 --test-every 5 > compress.log
step "jsgstools validate"
"$V/jsgstools" validate data > validate.log
step "jsgstools manifest"
"$V/jsgstools" manifest data --out manifest.json > manifest.log
step "jsgstools inspect-dqt --json"
"$V/jsgstools" inspect-dqt --json data/images/*.jpg > dqt.json
"$V/python" -c "import json; d = json.load(open('dqt.json')); print('  inspect-dqt:', len(d['files']), 'files')"
step "jsgs train (30 steps, CPU, JSGS)"
"$V/jsgs" train manifest.json --out run --method jsgs --iterations 30 --eval-at 30 --device cpu --quiet
"$V/python" - <<'PY'
import json
m = json.load(open("run/metrics.json"))
e = m["evals"][-1]
assert m["status"] == "complete", m["status"]
print(f"  metrics.json: status {m['status']}, step {e['step']}, PSNR {e['psnr']:.2f}, {e['num_gaussians']} Gaussians")
PY
step "ok"
