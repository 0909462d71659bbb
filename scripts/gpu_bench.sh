#!/usr/bin/env bash
# GPU side of the reproduction bench (`jsgs bench`) on a lent multi-GPU machine, in device calls of < 10
# minutes that a warm machine chains: results accumulate in .res/ (git-ignored and never carried, so it stays
# on the machine between calls and reruns skip or resume what is there), and every call brings back what it
# has as $OUT/results_<TAG>.tgz (metrics.json, config.json and log of every run, bench.json, results.csv,
# report.md, plots; no PLYs, renders or checkpoints).
#
#   here:   GPU_SCENES="llff_flower llff_fern" bash scripts/gpu_prepare.sh
#   device: command "TAG=a bash scripts/gpu_bench.sh", carry [".whl", ".gpu"], kind nvidia-h200-x4
#
# Two benches run side by side, each on its own GPUs: S0 (every scene carried so far, seed 0: the mixed
# schedules, clean, fixed 30/50 and the ablation on llff_flower) and S1 (seed 1: mixed schedules and clean).
# Knobs (environment): OVERHEAD_ITERS (1000) and OVERHEAD_COMPILE (off,inductor) of PRE=overhead, GPU_DIR (.gpu), WHL (.whl), S0_GPUS / S1_GPUS (comma lists; empty: that bench does not run), JOBS_PER_GPU (4),
# END (seconds after the start by which the benches stop, 520), COMPILE (auto | off | inductor: auto trains
# 300 JSGS steps with and without torch.compile first and takes the faster that works), PRE (stages on the
# PRE_GPU, by default the first of S1_GPUS, before S1 starts there: "tests overhead"), SWEEP=1 (also a
# sweep: one bench per config of SWEEP_CONFIGS (benchmarks/weight_sweep; benchmarks/densify_control is the
# next one) on the gaussian schedule of SWEEP_SCENES (llff_flower), seeds SWEEP_SEEDS (0), on SWEEP_GPUS with
# SWEEP_JOBS (1) jobs per GPU each; configs named gsplat_* train the baseline).
set -uo pipefail
T0=$(date +%s)
OUT=${OUT:-/tmp/jsgs_gpu_out}
mkdir -p "$OUT"
TAG=${TAG:-x}
S0_GPUS=${S0_GPUS-1,2,3}
S1_GPUS=${S1_GPUS-0}
JOBS_PER_GPU=${JOBS_PER_GPU:-4}
END=${END:-520}
COMPILE=${COMPILE:-auto}
PRE=${PRE:-}
PRE_GPU=${PRE_GPU:-${S1_GPUS%%,*}}
WHL=${WHL:-.whl}
. scripts/gpu_env.sh
R0=$PWD/.res/bench_s0
R1=$PWD/.res/bench_s1
mkdir -p "$R0/data" "$R1/data"
# the carried clean bases join those of earlier calls
G=${GPU_DIR:-.gpu}  # what gpu_prepare.sh made: clean bases, LPIPS weights, prior runs
for base in "$G"/bench/data/*/clean_s0; do
    [ -d "$base" ] || continue
    s=$(basename "$(dirname "$base")")
    for r in "$R0" "$R1"; do
        [ -f "$r/data/$s/clean_s0/manifest.json" ] || { mkdir -p "$r/data/$s" && cp -r "$base" "$r/data/$s/"; }
    done
done
[ -f "$G/alexnet_features.pth" ] && [ ! -f .res/alexnet_features.pth ] && cp "$G/alexnet_features.pth" .res/
# runs finished on an earlier machine (their metrics.json and config.json, from a results_<TAG>.tgz) count
# as done: the bench skips them
[ -d "$G/prior" ] && cp -rn "$G/prior/." .res/
export JSGS_LPIPS_WEIGHTS=$PWD/.res/alexnet_features.pth
SCENES=$(ls "$R0/data")
echo "scenes: $SCENES" | tee "$OUT/log_$TAG.txt"
{
    nvidia-smi --query-gpu=index,name,memory.total,driver_version --format=csv,noheader
    python3 -c "import torch, gsplat; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'gsplat', gsplat.__version__)"
} 2>&1 | tee -a "$OUT/log_$TAG.txt"
t=$(date +%s)
python3 -c "from gsplat.cuda._backend import _C; print('gsplat CUDA ready')" 2>&1 | tail -1
echo "gsplat build/load: $(($(date +%s) - t)) s" | tee -a "$OUT/log_$TAG.txt"

JSGS="python3 -m jsgs.cli"
ABL=""
[ -d "$R0/data/llff_flower" ] && ABL="--ablation llff_flower"
S0_ARGS="--seeds 0 --schedules uniform,gaussian,descending,clean --fixed=${S0_FIXED-30,50} $ABL"
S1_ARGS="--seeds 1 --schedules uniform,gaussian,descending,clean --fixed="
# shellcheck disable=SC2086
$JSGS bench $(cd "$R0/data" && echo *) --out "$R0" $S0_ARGS --prepare-only --quiet 2>&1 | tail -1
# shellcheck disable=SC2086
$JSGS bench $(cd "$R1/data" && echo *) --out "$R1" $S1_ARGS --prepare-only --quiet 2>&1 | tail -1
echo "datasets ready: $(($(date +%s) - T0)) s" | tee -a "$OUT/log_$TAG.txt"

M=$R0/data/llff_flower/gaussian_s0/manifest.json
if [ "$COMPILE" = auto ]; then
    # the same 300 JSGS steps on llff_flower with and without torch.compile, side by side on two GPUs
    for c in inductor off; do
        g=0; [ $c = off ] && g=1
        CUDA_VISIBLE_DEVICES=$g $JSGS train "$M" --out "/tmp/pre_$c" --method jsgs --iterations 300 \
            --eval-at 300 --compile $c --device cuda --quiet --force > "$OUT/preflight_$c.log" 2>&1 &
    done
    wait
    COMPILE=$(python3 - <<'EOF'
import json
t = {}
for c in ("inductor", "off"):
    try:
        d = json.load(open(f"/tmp/pre_{c}/metrics.json"))
        t[c] = d["evals"][-1]["time_per_iteration_s"] if d["status"] == "complete" else None
    except Exception:
        t[c] = None
print("inductor" if t["inductor"] and (not t["off"] or t["inductor"] < t["off"]) else "off")
EOF
)
    echo "preflight (300 JSGS steps, s/it): $(grep -ho 'time_per_iteration_s": [0-9.e-]*' /tmp/pre_*/metrics.json | tr '\n' ' ') -> --compile $COMPILE" | tee -a "$OUT/log_$TAG.txt"
fi

LEFT=$((T0 + END - $(date +%s)))
pids=()
SW=$(basename "${SWEEP_CONFIGS:-benchmarks/weight_sweep}")  # results in .res/$SW/<config name>
if [ -n "${SWEEP:-}" ]; then
    # the sweep: one `jsgs bench` per config of $SWEEP_CONFIGS (a config named gsplat_* trains the baseline,
    # the others JSGS) on the gaussian schedule of $SWEEP_SCENES, seeds $SWEEP_SEEDS, spread round-robin over
    # SWEEP_GPUS (summarise here with benchmarks/weight_sweep.py .res/$SW --configs $SWEEP_CONFIGS)
    IFS=, read -r -a gl <<< "${SWEEP_GPUS:-0,1,2,3}"
    i=0
    for cfg in "${SWEEP_CONFIGS:-benchmarks/weight_sweep}"/*.json; do
        name=$(basename "$cfg" .json)
        m=jsgs; case $name in gsplat_*) m=gsplat ;; esac
        mkdir -p ".res/$SW/$name/data"
        for s in ${SWEEP_SCENES:-llff_flower}; do
            [ -d ".res/$SW/$name/data/$s" ] || cp -r "$R0/data/$s" ".res/$SW/$name/data/"
        done
        # shellcheck disable=SC2086
        CUDA_VISIBLE_DEVICES=${gl[$((i % ${#gl[@]}))]} $JSGS bench ${SWEEP_SCENES:-llff_flower} --out ".res/$SW/$name" \
            --methods $m --schedules gaussian --fixed= --seeds "${SWEEP_SEEDS:-0}" --config "$cfg" --device cuda \
            --jobs-per-gpu "${SWEEP_JOBS:-1}" --compile "$COMPILE" --time-limit "$LEFT" --quiet \
            > "$OUT/sweep_$name.log" 2>&1 &
        pids+=($!)
        i=$((i + 1))
    done
fi
if [ -n "$S0_GPUS" ]; then
    # shellcheck disable=SC2086
    CUDA_VISIBLE_DEVICES=$S0_GPUS $JSGS bench $(cd "$R0/data" && echo *) --out "$R0" $S0_ARGS \
        --jobs-per-gpu "$JOBS_PER_GPU" --device cuda --compile "$COMPILE" --time-limit "$LEFT" --quiet \
        > "$OUT/bench_s0_$TAG.log" 2>&1 &
    pids+=($!)
fi
if [ -n "$S1_GPUS$PRE" ]; then
    (
        g=$PRE_GPU
        for stage in $PRE; do
            case $stage in
            tests) CUDA_VISIBLE_DEVICES=$g JSGS_GPU_MANIFEST=$M python3 -m pytest -m gpu -p no:cacheprovider \
                tests/test_render_gpu.py tests/test_jsgs_method.py tests/test_lpips.py tests/test_graphed.py -q -s \
                > "$OUT/gpu_tests.log" 2>&1 ;;
            overhead) CUDA_VISIBLE_DEVICES=$g python3 tools/diagnostics/bench_train_overhead.py --manifest "$M" \
                --iterations "${OVERHEAD_ITERS:-1000}" --repeats 1 --device cuda --jpeg-modes ${OVERHEAD_MODES:-paper} --compile ${OVERHEAD_COMPILE:-off,inductor} --cuda-graph off,on \
                --out "$OUT/overhead.json" > "$OUT/overhead.txt" 2>&1 ;;
            esac
        done
        left=$((T0 + END - $(date +%s)))
        # shellcheck disable=SC2086
        [ -n "$S1_GPUS" ] && [ $left -gt 60 ] && CUDA_VISIBLE_DEVICES=$S1_GPUS $JSGS bench $(cd "$R1/data" && echo *) --out "$R1" \
            $S1_ARGS --jobs-per-gpu "$JOBS_PER_GPU" --device cuda --compile "$COMPILE" --time-limit "$left" \
            --quiet > "$OUT/bench_s1_$TAG.log" 2>&1
    ) &
    pids+=($!)
fi
wait "${pids[@]}"
echo "benches done: $(($(date +%s) - T0)) s" | tee -a "$OUT/log_$TAG.txt"
tail -n 3 "$OUT"/bench_s*_"$TAG".log 2>/dev/null
tail -n 3 "$OUT/gpu_tests.log" 2>/dev/null
tail -n 25 "$OUT/overhead.txt" 2>/dev/null
(cd .res && tar czf "$OUT/results_$TAG.tgz" --exclude='*.ply' --exclude='*.pt' --exclude='renders' \
    --exclude='data' bench_s0 bench_s1 $([ -d "$SW" ] && echo "$SW"))
python3 - <<'EOF'
import json, pathlib
for r in (".res/bench_s0", ".res/bench_s1"):
    done = sorted(str(p.parent.relative_to(r)) for p in pathlib.Path(r).glob("runs/*/*/*/*/metrics.json")
                  if json.loads(p.read_text()).get("status") == "complete")
    print(r, len(done), "complete:", " ".join(done))
EOF
echo "call total: $(($(date +%s) - T0)) s"
