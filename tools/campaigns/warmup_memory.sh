# Peak device memory at camera resolution with and without `method_options.speed.cuda_graph_free_warmup`:
# jpeg_mouse (1440x1920), profile_step.py --preset mcmc (JSGS with its recipe), 3 interleaved pairs after
# 1,500 steps, the release on (the default, `free`) and off (`keep`) as two processes side by side on one
# GPU, so that the call (about 80 s of CUDA builds first, then each profile bounded by `timeout`) stays within
# 300 s (the phase peaks below add about 100 s). The memory figures are each process's own (torch's allocator
# statistics), exact whatever runs beside it; the step times share the GPU, so compare the two ratios with each other, not with one-job-per-GPU
# profiles (docs/results/speed/equal_budget/camera_jpeg_mouse_1500*.json: the release off, 6 pairs, alone).
# On the CPU first (the .gpu*/ folders are ignored):
#   mkdir -p .gpuM && cp -r ../shared/scenes/jpeg_mouse .gpuM/ && \
#       .venv/bin/jsgstools manifest .gpuM/jpeg_mouse --out .gpuM/jpeg_mouse/manifest.json --analyze
#   bash scripts/gpu_prepare.sh     # the wheels in .whl
# then on one lent GPU, carrying [".whl", ".gpuM"]:
#   bash tools/campaigns/warmup_memory.sh
# It writes $OUT/camera_jpeg_mouse_<WARMUP>_{free,keep}.{json,txt} and $OUT/build.log, and prints each
# profile's peak memory rows and paired step times. Their allocated peaks, against the same protocol on the
# code before the probe's map was made at each call (docs/results/speed/equal_budget/camera_jpeg_mouse_1500
# .json: gsplat 809.2, JSGS 949.6 MiB), measure that saving (docs/results/speed/memory: 21 MiB at 1440x1920
# if the peak falls before the hook, none if in the backward).
# Then where in a step the peak falls: `jsgs train --profile` from scratch, STEPS steps each of gsplat, JSGS
# (its recipe, gc_every 4) and JSGS with the controller on every step, one after another; each phase's
# peak allocated MiB over the steps (metrics.json profile_peak_memory_bytes) into $OUT/phase_peaks.txt. The
# "hook" phase's includes the graph's recording (its first step); render, loss and backward do not.
set -u
M=${MANIFEST:-.gpuM/jpeg_mouse/manifest.json} P=tools/diagnostics/profile_step.py
WARMUP=${WARMUP:-1500} PAIRS=${PAIRS:-3} TL=${TL:-190}
bash scripts/gpu_run.sh true > "$OUT/build.log" 2>&1
for v in free:true keep:false; do
    name=camera_jpeg_mouse_${WARMUP}_${v%%:*}
    timeout "$TL" bash scripts/gpu_run.sh python3 $P --manifest "$M" --device cuda --preset mcmc --cap-max 300000 \
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
STEPS=${STEPS:-40} R=$(mktemp -d)
echo '{"method_options": {"gc_every": 1}}' > "$R/gc1.json"
for v in gsplat:gsplat:none jsgs:jsgs:none jsgs_gc1:jsgs:gc1; do
    IFS=: read -r name method cfg <<< "$v"
    extra=(); [ "$cfg" = none ] || extra=(--config "$R/$cfg.json")
    timeout "$TL" bash scripts/gpu_run.sh python3 -m jsgs.cli train "$M" --out "$R/$name" --method "$method" \
        --preset mcmc --cap-max 300000 --device cuda --iterations "$STEPS" --eval-at '' --profile --quiet \
        ${extra[@]+"${extra[@]}"} \
        > "$R/$name.log" 2>&1 || { echo "== $name failed:"; tail -3 "$R/$name.log"; }
done
python3 - "$R" > "$OUT/phase_peaks.txt" <<'PY'
import json, sys
from pathlib import Path
print("peak allocated MiB by phase (jsgs train --profile, max over the steps)")
for name in ("gsplat", "jsgs", "jsgs_gc1"):
    m = Path(sys.argv[1], name, "metrics.json")
    peaks = json.loads(m.read_text()).get("profile_peak_memory_bytes") if m.is_file() else None
    print(name, {k: round(v / 2**20, 1) for k, v in (peaks or {}).items()})
PY
cat "$OUT/phase_peaks.txt"
