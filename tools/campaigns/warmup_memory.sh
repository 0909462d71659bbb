# Peak device memory at camera resolution with and without `method_options.speed.cuda_graph_free_warmup`:
# jpeg_mouse (1440x1920), profile_step.py --preset mcmc (JSGS with its recipe), 3 interleaved pairs after
# 1,500 steps, the release on (the default, `free`) and off (`keep`) as two processes side by side on one
# GPU, so that the call (about 80 s of CUDA builds first, then each profile bounded by `timeout`) stays within
# 300 s. The memory figures are each process's own (torch's allocator statistics), exact whatever runs beside
# it; the step times share the GPU, so compare the two ratios with each other, not with one-job-per-GPU
# profiles (docs/results/speed/equal_budget/camera_jpeg_mouse_1500*.json: the release off, 6 pairs, alone).
# On the CPU first (the .gpu*/ folders are ignored):
#   mkdir -p .gpuM && cp -r ../shared/scenes/jpeg_mouse .gpuM/ && \
#       .venv/bin/jsgstools manifest .gpuM/jpeg_mouse --out .gpuM/jpeg_mouse/manifest.json --analyze
#   bash scripts/gpu_prepare.sh     # the wheels in .whl
# then on one lent GPU, carrying [".whl", ".gpuM"]:
#   bash tools/campaigns/warmup_memory.sh
# It writes $OUT/camera_jpeg_mouse_<WARMUP>_{free,keep}.{json,txt} and $OUT/build.log, and prints each
# profile's peak memory rows and paired step times.
set -u
M=${MANIFEST:-.gpuM/jpeg_mouse/manifest.json} P=tools/diagnostics/profile_step.py
WARMUP=${WARMUP:-1500} PAIRS=${PAIRS:-3} TL=${TL:-190}
bash scripts/gpu_run.sh true > "$OUT/build.log" 2>&1
for v in free:true keep:false; do
    name=camera_jpeg_mouse_${WARMUP}_${v%%:*}
    timeout "$TL" bash scripts/gpu_run.sh python3 $P --manifest "$M" --device cuda --preset mcmc \
        --warmup "$WARMUP" --steps 100 --pairs "$PAIRS" --no-fresh \
        --jsgs-options "{\"speed\": {\"cuda_graph_free_warmup\": ${v#*:}}}" \
        --out "$OUT/$name.json" > "$OUT/$name.txt" 2>&1 &
done
wait
for v in free keep; do
    name=camera_jpeg_mouse_${WARMUP}_$v
    echo "== $name"
    grep -E "^\| (gsplat|jsgs) \| (allocated|reserved) \| peak \||^\| (gsplat|jsgs) \| [0-9.]+, " "$OUT/$name.txt"
done
