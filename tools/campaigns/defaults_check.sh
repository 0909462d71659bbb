# The measurements that decide the open defaults, on one machine of 4 GPUs over four chained calls (the
# pattern of rule_and_checks.sh: benches detached with setsid from a copy of the tree in /tmp/src, data
# carried in two calls and kept in /tmp, every call bounded well inside 600 s and bringing back one archive):
#   - gc_every 4 and gc_attribution footprint against the exact controller at equal budget (llff_flower,
#     gaussian schedule, 300k Gaussians, 10,000 steps, seeds 0,1,2; gc_every.sh / gc_attribution.sh
#     PART=quality's protocol): benches q1 (K = 1), q4 (K = 4), qf (footprint), one GPU each (0, 1, 2);
#   - the auto rule's retune (docs/results/operating_point/README.md): JSGS at the budgets a pixels bound of
#     30 would give, flower 184k and fern 108k, seeds 0,1, 30,000 steps (operating_point.sh PART=rule):
#     benches rf (GPU 0) and rn (GPU 1);
#   - on GPU 3, one job at a time: the GPU tests of the kernels and of the footprint attribution,
#     bench_jpeg_ops.py --fused-jo, and equal-budget profiles (profile_step.py --preset mcmc, 6 pairs):
#     flower after 1,500 and 6,000 steps and jpeg_mouse at 1440x1920 after 1,500 with the defaults, the
#     mouse with gc_every 4 and with gc_attribution footprint;
#   - PHASE=4, once the benches are done: scale.sh on GPUs 0-1 (jpeg_mouse, gsplat and JSGS, 1 and 2 GPUs) and
#     on GPUs 2-3 the 1,000,000-Gaussian scene (flower, random initial points, gsplat).
# On the CPU first (folders that .gitignore's .gpu*/ ignores):
#   GPU_DIR=.gpuR GPU_SCENES="llff_flower llff_fern" bash scripts/gpu_prepare.sh     # + .whl
#   mkdir -p .gpuM && cp -r ../shared/scenes/jpeg_mouse .gpuM/ && \
#       .venv/bin/jsgstools manifest .gpuM/jpeg_mouse --out .gpuM/jpeg_mouse/manifest.json --analyze
# then four calls, each started within 30 s of the last one's end (kind nvidia-h100-x4):
#   PHASE=1 bash tools/campaigns/defaults_check.sh     # carry [".whl", ".gpuR"]
#   PHASE=2 bash tools/campaigns/defaults_check.sh     # carry [".gpuM"]
#   PHASE=3 bash tools/campaigns/defaults_check.sh
#   PHASE=4 bash tools/campaigns/defaults_check.sh
# Each brings back $OUT/dc_<PHASE>.tgz (logs, profiles, every bench's results.csv, report.md and its runs'
# metrics.json and config.json so far). On the CPU: the bench folders go to tools/results/build_report.py
# (q1/q4/qf into docs/results/speed/gc_quality/{k1,k4,footprint}; rf/rn beside .res/op_rule_a into docs/results/operating_point).
set -u
PHASE=${PHASE:?set PHASE=1, 2, 3 or 4}
S=/tmp/src D=/tmp/gpudata L=/tmp/dc_logs
export TORCH_EXTENSIONS_DIR=/tmp/torch_ext JSGS_LPIPS_WEIGHTS=$D/alexnet_features.pth
R='"lambda_obs":1.0,"base_by_view":true,"base_noise":"pixels","base_noise_ref":2.0,"base_noise_exponent":2.0'
mkdir -p $D $L
detach() {  # detach NAME GPU COMMAND...: run COMMAND from /tmp/src on GPU, past the call's end
    local name=$1 gpu=$2; shift 2
    (cd $S && CUDA_VISIBLE_DEVICES=$gpu setsid nohup bash scripts/gpu_run.sh "$@" > $L/$name.log 2>&1 \
        < /dev/null &)
}
quality() {  # quality NAME GPU OPTIONS: flower, 3 seeds, 10,000 steps at 300k, JSGS with OPTIONS
    local b=/tmp/dc_$1
    mkdir -p $b/data && cp -r $D/bench/data/llff_flower $b/data/
    printf '{"method_options": {%s, %s}}\n' "$R" "$3" > $b/recipe.json
    detach "$1" "$2" python3 -m jsgs.cli bench llff_flower --out $b --strategy mcmc --budgets 300k \
        --iterations 10000 --schedules gaussian --methods jsgs --seeds 0,1,2 --eval-at 7000,10000 \
        --jobs-per-gpu 3 --jsgs-config $b/recipe.json --time-limit 1500 --quiet
}
rule() {  # rule NAME GPU SCENE BUDGET: JSGS seeds 0,1 at BUDGET, 30,000 steps
    mkdir -p /tmp/out_$1
    (cd $S && CUDA_VISIBLE_DEVICES=$2 PART=rule SCENES=$3 RULE_BUDGETS=$4 SEEDS=0,1 JOBS=2 TL=1500 \
        GPU_DIR=$D OUT_DIR=/tmp/dc_$1 OUT=/tmp/out_$1 setsid nohup bash scripts/gpu_run.sh \
        bash tools/campaigns/operating_point.sh > $L/$1.log 2>&1 < /dev/null &)
}
profile() {  # profile MANIFEST WARMUP NAME OPTIONS [TIMEOUT]: 6 interleaved pairs, --preset mcmc, GPU 3
    CUDA_VISIBLE_DEVICES=3 timeout "${5:-190}" bash scripts/gpu_run.sh python3 tools/diagnostics/profile_step.py \
        --manifest "$1" --device cuda --preset mcmc --cap-max 300000 --warmup "$2" --steps 100 --pairs 6 --no-fresh \
        --jsgs-options "$4" --out $L/$3.json > $L/$3.txt 2>&1
}
F=$D/flower_gaussian/manifest.json M=$D/jpeg_mouse/manifest.json
case $PHASE in
  1)
    rm -rf $S && mkdir -p $S && tar cf - --exclude=./.gpuR --exclude=./.res --exclude=./.torch_ext . | tar xf - -C $S
    cp -r .gpuR/alexnet_features.pth .gpuR/bench $D/
    (cd $S && bash scripts/gpu_run.sh true) > $L/build.log 2>&1
    quality q1 0 '"gc_every": 1'
    quality q4 1 '"gc_every": 4'
    quality qf 2 '"gc_attribution": "footprint"'
    rule rf 0 llff_flower 184000
    rule rn 1 llff_fern 108000
    cd $S
    CUDA_VISIBLE_DEVICES=3 timeout 170 bash scripts/gpu_run.sh python3 -m pytest -m "gpu or slow" -s -rs \
        -p no:cacheprovider tests/test_jsgs/kernels tests/test_jsgs/method/test_gc_attribution.py \
        tests/test_jsgs/method/test_graphed.py > $L/gpu_tests.log 2>&1
    CUDA_VISIBLE_DEVICES=3 timeout 90 bash scripts/gpu_run.sh python3 benchmarks/bench_jpeg_ops.py --fused-jo \
        --device cuda --repeats 50 --warmup 5 > $L/fused_bench.log 2>&1
    ;;
  2)
    cp -r .gpuM/jpeg_mouse $D/
    cd $S
    # the flower dataset the quality benches derived (gaussian schedule, seed 0)
    mkdir -p $D/flower_gaussian && cp -r /tmp/dc_q1/data/llff_flower/gaussian_s0/. $D/flower_gaussian/
    profile $M 1500 camera_jpeg_mouse_1500 '{}'
    profile $F 1500 flower_1500 '{}' 170
    ;;
  3)
    cd $S
    profile $M 1500 camera_jpeg_mouse_1500_k4 '{"gc_every": 4}'
    profile $M 1500 camera_jpeg_mouse_1500_footprint '{"gc_attribution": "footprint"}'
    ;;
  4)
    end=$((SECONDS + ${WAIT:-120}))
    while [ $SECONDS -lt $end ] && pgrep -f "jsgs.cli bench" > /dev/null; do sleep 10; done
    cd $S && mkdir -p /tmp/dc_scale && ln -sfn $D .gpu3
    ln -sfn $D/flower_gaussian $D/llff_flower
    (CUDA_VISIBLE_DEVICES=0,1 OUT=/tmp/dc_scale SCENES=jpeg_mouse:300000 ITERS=2000 TL=90 timeout 380 \
        bash scripts/gpu_run.sh bash tools/campaigns/scale.sh > $L/scale_mouse.log 2>&1) &
    (mkdir -p /tmp/src1m && tar cf - --exclude=./.res . | tar xf - -C /tmp/src1m && cd /tmp/src1m && \
        CUDA_VISIBLE_DEVICES=2,3 OUT=/tmp/dc_scale1m SCENES=llff_flower:1000000:random METHODS=gsplat \
        ITERS=2000 TL=150 timeout 380 bash scripts/gpu_run.sh bash tools/campaigns/scale.sh \
        > $L/scale_1m.log 2>&1; mkdir -p $L/scale_1m && cp -r .res/scale/. $L/scale_1m/) &
    wait
    mkdir -p $L/scale_mouse && cp -r $S/.res/scale/. $L/scale_mouse/ 2>/dev/null
    find $L/scale_mouse $L/scale_1m -name '*.ply' -o -name checkpoints -prune -o -name renders -prune \
        | xargs rm -rf 2>/dev/null
    ;;
esac
nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv > $L/smi_$PHASE.txt 2>&1
for b in q1 q4 qf rf rn; do
    [ -d /tmp/dc_$b ] || continue
    (cd /tmp/dc_$b && tar cf - results.csv report.md bench.json runs/*/*/*/*/*/metrics.json \
        runs/*/*/*/*/*/config.json 2>/dev/null) > $L/dc_$b.tar
done
tar czf "$OUT/dc_$PHASE.tgz" -C $L .
ls -la "$OUT"
