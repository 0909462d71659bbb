#!/usr/bin/env bash
# Issue 5's GPU checks in one device call on a single GPU: the GPU tests, the per-iteration overhead of
# --method jsgs against --method gsplat (tools/diagnostics/bench_train_overhead.py) and the kernel-level profile of
# a training step (tools/diagnostics/profile_step.py), on llff_flower's gaussian schedule (seed 0).
#
#   here:   .venv/bin/python -m jsgs.cli bench llff_flower --out .gpuD --schedules gaussian --fixed= \
#               --seeds 0 --prepare-only      (after copying a clean base into .gpuD/data/llff_flower/)
#   device: command "bash scripts/gpu_speed.sh", carry [".whlmin", ".gpuD"], kind nvidia-h200
#
# Knobs (environment): STAGES ("tests overhead profile"; "ssim": benchmarks/bench_ssim.py; "graphhost":
# tools/diagnostics/bench_graph_host.py; "full" trains
# the FULL_RUNS ("jsgs gsplat"; a name may repeat; METHOD_eager: JSGS without CUDA graphs; METHOD_torchssim:
# the torch SSIM instead of the fused kernel; METHOD_torchgc: the GC's torch twin, graphed) one after the other for FULL_ITERS (10000) steps each,
# evaluated at 3000 / 7000 / 10000), ITERS (2000, overhead), GRAPHS (off,jo,on),
# MODES (paper), WHL (.whlmin), DATA (.gpuD/data; LPIPS weights in .gpuD/alexnet_features.pth). Results in
# $OUT: gpu_tests.log, ssim.txt, overhead.{txt,json}, profile.{txt,json}, full_<i>_<run>.{json,log} (metrics.json).
set -uo pipefail
T0=$(date +%s)
OUT=${OUT:-/tmp/jsgs_gpu_out}
mkdir -p "$OUT"
WHL=${WHL:-.whlmin}
. scripts/gpu_env.sh
[ -f "${DATA:-.gpuD/data}/../alexnet_features.pth" ] && export JSGS_LPIPS_WEIGHTS=$PWD/${DATA:-.gpuD/data}/../alexnet_features.pth
M=${DATA:-.gpuD/data}/llff_flower/gaussian_s0/manifest.json
{
    nvidia-smi --query-gpu=index,name,memory.total,driver_version,utilization.gpu --format=csv,noheader
    python3 -c "import torch, gsplat; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'gsplat', gsplat.__version__)"
    t=$(date +%s)
    python3 -c "from gsplat.cuda._backend import _C; print('gsplat CUDA ready')" 2>&1 | tail -1
    echo "gsplat build/load: $(($(date +%s) - t)) s"
} 2>&1 | tee "$OUT/log.txt"
for stage in ${STAGES:-tests overhead profile}; do
    t=$(date +%s)
    case $stage in
    tests) JSGS_GPU_MANIFEST=$M python3 -m pytest -m gpu -p no:cacheprovider -q -s -p no:warnings \
        tests/test_graphed.py tests/test_render_gpu.py tests/test_jsgs_method.py tests/test_ssim_cuda.py \
        tests/test_controller_cuda.py \
        > "$OUT/gpu_tests.log" 2>&1
        tail -n 3 "$OUT/gpu_tests.log" ;;
    ssim) python3 benchmarks/bench_ssim.py > "$OUT/ssim.txt" 2>&1; tail -n 12 "$OUT/ssim.txt" ;;
    graphhost) python3 tools/diagnostics/bench_graph_host.py > "$OUT/graph_host.txt" 2>&1
        tail -n 8 "$OUT/graph_host.txt" ;;
    overhead) python3 tools/diagnostics/bench_train_overhead.py --manifest "$M" --iterations "${ITERS:-2000}" \
        --repeats 1 --device cuda --jpeg-modes "${MODES:-paper}" --cuda-graph "${GRAPHS:-off,jo,on}" \
        --out "$OUT/overhead.json" > "$OUT/overhead.txt" 2>&1
        tail -n 16 "$OUT/overhead.txt" ;;
    full) echo '{"method_options": {"speed": {"cuda_graph": false}}}' > /tmp/eager.json
        echo '{"speed": {"ssim_kernel": "torch"}}' > /tmp/torchssim.json
        echo '{"method_options": {"speed": {"gc_kernel": "torch"}}}' > /tmp/torchgc.json
        i=0
        for m in ${FULL_RUNS:-jsgs gsplat}; do  # METHOD[_eager|_torchssim], in this order; repeats allowed
            i=$((i + 1))
            cfg=(); case $m in *_eager) cfg=(--config /tmp/eager.json) ;; *_torchssim) cfg=(--config /tmp/torchssim.json) ;;
                *_torchgc) cfg=(--config /tmp/torchgc.json) ;; esac
            python3 -m jsgs.cli train "$M" --out "/tmp/full_$m" --method "${m%%_*}" "${cfg[@]}" \
                --iterations "${FULL_ITERS:-10000}" --eval-at 3000,7000,10000 --device cuda --quiet --force \
                > "$OUT/full_${i}_$m.log" 2>&1
            cp "/tmp/full_$m/metrics.json" "$OUT/full_${i}_$m.json"
            echo "$i $m: $(tail -n 2 "$OUT/full_${i}_$m.log" | head -n 1)"
            python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(f\"  {d['time_per_iteration_s']*1e3:.2f} ms/it\")" "$OUT/full_${i}_$m.json"
        done ;;
    profile) python3 tools/diagnostics/profile_step.py --manifest "$M" --device cuda --out "$OUT/profile.json" \
        > "$OUT/profile.txt" 2>&1
        tail -n 45 "$OUT/profile.txt" ;;
    esac
    echo "stage $stage: $(($(date +%s) - t)) s" | tee -a "$OUT/log.txt"
done
echo "call total: $(($(date +%s) - T0)) s" | tee -a "$OUT/log.txt"
