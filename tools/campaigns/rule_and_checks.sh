# The operating point's auto-rule runs (operating_point.sh PART=rule: JSGS seed 0 at 100k, 300k and 1M
# Gaussians, 30,000 steps) beside the GPU-only checks, on one machine of 4 GPUs held over three chained calls.
# The clean bases of the four scenes do not fit one call's 64 MiB with the tree, so they come in two calls and
# wait in /tmp; the rule benches run detached (setsid) from a copy of the tree in /tmp/src and go on between
# calls while the machine stays warm:
#   PHASE=1  carry .whl, .gpuR (LPIPS weights + llff_flower, llff_fern bases): copies the tree to /tmp/src,
#            builds, starts bench A (flower, fern) on GPUs 0-2, then on GPU 3 the fused Triton kernels' GPU
#            tests and bench_jpeg_ops.py --fused-jo, then the several-GPU tests on GPUs 2-3 (correctness only:
#            they share GPU 2 with bench A);
#   PHASE=2  carry .gpuS (custom_kwrous_cup, custom_myhan_mouse bases, jpeg_mouse with its manifest): starts
#            bench B (cup, mouse) on GPUs 0-2, then on GPU 3 equal-budget profiles of jpeg_mouse at
#            1440x1920 (6 interleaved pairs after 1,500 steps), default kernels and fused_color + gc_every 4;
#   PHASE=3  on GPU 3 equal-budget profiles of llff_flower (gaussian schedule, the dataset bench A derived)
#            after 1,500 and 6,000 steps from the current checkout, then waits for the benches up to WAIT
#            seconds (60) and brings back what they have;
#   PHASE=4  waits for the benches up to WAIT seconds and brings back what they have.
# Every call brings back $OUT/rc_<PHASE>.tgz: logs, profiles, and each bench's results.csv, report.md and its
# runs' metrics.json and config.json so far (never checkpoints). On the CPU, extract them and gather with
#   .venv/bin/python tools/results/build_report.py docs/results/operating_point .res/op_time ... .res/op_rule_a .res/op_rule_b
set -u
PHASE=${PHASE:?set PHASE=1, 2 or 3}
S=/tmp/src D=/tmp/gpudata L=/tmp/rc_logs
export TORCH_EXTENSIONS_DIR=/tmp/torch_ext JSGS_LPIPS_WEIGHTS=$D/alexnet_features.pth
mkdir -p $D $L
rule() {  # rule NAME "SCENES": bench NAME (/tmp/op_rule_NAME) detached on GPUs 0-2, two runs per GPU
    mkdir -p /tmp/out_$1
    (cd $S && CUDA_VISIBLE_DEVICES=0,1,2 PART=rule SCENES="$2" JOBS=2 TL=${TL:-1500} GPU_DIR=$D \
        OUT_DIR=/tmp/op_rule_$1 OUT=/tmp/out_$1 setsid nohup bash scripts/gpu_run.sh \
        bash tools/campaigns/operating_point.sh > $L/bench_$1.log 2>&1 < /dev/null &)
}
profile() {  # profile MANIFEST WARMUP NAME OPTIONS: 6 interleaved pairs, --preset mcmc, on GPU 3
    CUDA_VISIBLE_DEVICES=3 timeout "${PT:-190}" bash scripts/gpu_run.sh python3 tools/diagnostics/profile_step.py \
        --manifest "$1" --device cuda --preset mcmc --cap-max 300000 --warmup "$2" --steps 100 --pairs 6 --no-fresh \
        --jsgs-options "$4" --out $L/$3.json > $L/$3.txt 2>&1
}
case $PHASE in
  1)
    rm -rf $S && mkdir -p $S && tar cf - --exclude=./.gpuR --exclude=./.res --exclude=./.torch_ext . | tar xf - -C $S
    cp -r .gpuR/alexnet_features.pth .gpuR/bench $D/
    (cd $S && bash scripts/gpu_run.sh true) > $L/build.log 2>&1
    rule a "llff_flower llff_fern"
    cd $S
    CUDA_VISIBLE_DEVICES=3 timeout 150 bash scripts/gpu_run.sh python3 -m pytest -m "gpu or slow" -s -rs \
        -p no:cacheprovider tests/test_jsgs/kernels/test_triton_jo.py tests/test_jsgs/kernels/test_triton_color.py \
        tests/test_jsgs/method/test_graphed.py::test_gpu_training_with_fused_jo_matches_the_twin \
        > $L/fused_tests.log 2>&1
    CUDA_VISIBLE_DEVICES=3 timeout 90 bash scripts/gpu_run.sh python3 benchmarks/bench_jpeg_ops.py --fused-jo \
        --device cuda --repeats 50 --warmup 5 > $L/fused_bench.log 2>&1
    CUDA_VISIBLE_DEVICES=2,3 timeout 150 bash scripts/gpu_run.sh python3 -m pytest -q -m gpu -rs \
        -p no:cacheprovider tests/test_jsgs/train/test_distributed.py > $L/dist_tests.log 2>&1
    ;;
  2)
    cp -r .gpuS/bench .gpuS/jpeg_mouse $D/
    rule b "custom_kwrous_cup custom_myhan_mouse"
    cd $S
    profile $D/jpeg_mouse/manifest.json 1500 camera_jpeg_mouse_1500 '{}'
    profile $D/jpeg_mouse/manifest.json 1500 camera_jpeg_mouse_1500_color_k4 \
        '{"speed":{"fused_color":true},"gc_every":4}'
    ;;
  4) end=$((SECONDS + ${WAIT:-500}))
    while [ $SECONDS -lt $end ] && pgrep -f "jsgs.cli bench" > /dev/null; do sleep 10; done
    ;;
  3)
    F=/tmp/op_rule_a/data/llff_flower/gaussian_s0/manifest.json
    bash scripts/gpu_run.sh true > $L/build3.log 2>&1
    PT=170 profile $F 1500 llff_flower_1500 '{}'
    PT=230 profile $F 6000 llff_flower_6000 '{}'
    end=$((SECONDS + ${WAIT:-60}))
    while [ $SECONDS -lt $end ] && pgrep -f "jsgs.cli bench" > /dev/null; do sleep 10; done
    ;;
esac
nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv > $L/smi_$PHASE.txt 2>&1
for b in a b; do
    [ -d /tmp/op_rule_$b ] || continue
    (cd /tmp/op_rule_$b && tar cf - results.csv report.md bench.json runs/*/*/*/*/*/metrics.json \
        runs/*/*/*/*/*/config.json runs/*/*/*/*/*/*.log 2>/dev/null) > $L/op_rule_$b.tar
done
tar czf "$OUT/rc_$PHASE.tgz" -C $L .
ls -la "$OUT"
