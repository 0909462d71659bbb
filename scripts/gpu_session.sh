#!/usr/bin/env bash
# GPU side of a session: one device call that builds gsplat, checks the CUDA path against the reference
# rasterizer, times the JPEG operator and the JSGS overhead, and trains llff_flower (gaussian schedule) with
# both methods. Everything it measures is written under $OUT (the device tool brings it back).
#   device run: command "bash scripts/gpu_session.sh", carry [".whl", ".gpu"]
# Needs scripts/gpu_prepare.sh first. ITERS (default 10000) and STAGES (default "tests jpeg overhead train")
# choose how much to do; keep one call under 10 minutes.
set -uo pipefail
OUT=${OUT:-/tmp/jsgs_gpu_out}
mkdir -p "$OUT"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
export TORCH_EXTENSIONS_DIR=$PWD/.torch_ext TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
export JSGS_LPIPS_WEIGHTS=${JSGS_LPIPS_WEIGHTS:-$PWD/.gpu/alexnet_features.pth}
ITERS=${ITERS:-10000}
STAGES=${STAGES:-tests jpeg overhead train}
M=.gpu/llff_flower_gaussian/manifest.json
# the dataset is derived here (Pillow only) from the clean base that scripts/gpu_prepare.sh carries
[ -f "$M" ] || python3 -c "from jsgstools.derive import derive; derive('.gpu/bench/data/llff_flower/clean_s0/manifest.json', '.gpu/llff_flower_gaussian', 'gaussian', seed=0)"
nvidia-smi --query-gpu=name,driver_version --format=csv | tee "$OUT/gpu.txt"
python3 -c "import torch, gsplat; print('torch', torch.__version__, 'gsplat', gsplat.__version__)" | tee -a "$OUT/gpu.txt"
# first use compiles gsplat's CUDA extension
python3 -c "import torch, gsplat; from gsplat.cuda._backend import _C; print('gsplat CUDA ready')" 2>&1 | tail -2
for stage in $STAGES; do
    case $stage in
    tests) JSGS_GPU_MANIFEST=$PWD/$M python3 -m pytest -m gpu tests/test_render_gpu.py tests/test_jsgs_method.py tests/test_lpips.py -q -s 2>&1 | tee "$OUT/gpu_tests.log" | tail -40 ;;
    jpeg) python3 benchmarks/bench_jpeg_ops.py --device cuda --compile 2>&1 | tee "$OUT/bench_jpeg.txt" ;;
    overhead) python3 tools/diagnostics/bench_train_overhead.py --manifest "$M" --iterations 2000 --device cuda \
        --jpeg-modes paper,float,exact --compile off,inductor --out "$OUT/overhead.json" 2>&1 | tee "$OUT/overhead.txt" | tail -30 ;;
    train) for method in gsplat jsgs; do
            python3 -m jsgs.cli train "$M" --out "/tmp/run_$method" --method "$method" --iterations "$ITERS" \
                --device cuda --quiet --force && cp "/tmp/run_$method/metrics.json" "$OUT/flower_$method.json"
        done ;;
    esac
done
