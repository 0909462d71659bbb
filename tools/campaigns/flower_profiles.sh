# The equal-budget step profiles of llff_flower with the current defaults: profile_step.py --preset mcmc
# (JSGS with the preset's recipe as it is, gc_every 4 included; the fused kernels at their launch settings;
# the image terms as one CUDA graph), 6 interleaved pairs of 100-step windows after 1,500 steps (40k
# Gaussians) and after 6,000 (the full budget, 300k), one profile per GPU on one machine of 2 GPUs, side by
# side, in one call (about 80 s of CUDA builds on a fresh machine, then every part bounded by `timeout`).
# The full budget's profile gets TL6 (420) seconds: on an H200 sharing its host with three other profiles,
# 240 s was not enough for 2 x 6,000 warm-up steps and the resumed copies. GPU 0, after its profile: a
# Chrome trace of a 40-step window after 1,500 steps (profile_step.py --trace) and trace_gaps.py on it:
# where the device waits for the host in each method's step (read it as shares, not wall times: it shares
# the host with GPU 1's profile); with CHECKS=1 then also the GPU tests of the graphed image terms and of the
# kernels (~70 s) and the coding pass's kernels timed on the step's own launches (bench_jpeg_ops.py
# --fused-jo --coding-launches: flower's and jpeg_mouse's luma and chroma launches and the benchmark's
# three-plane one, at 16 and 32 blocks per program, with each binary's registers and spills; ~60 s).
# On the CPU first (.gpuF/ is ignored, as every .gpu*/ folder):
#   bash scripts/gpu_prepare.sh      # the wheels in .whl
#   .venv/bin/jsgstools compress ../shared/scenes/llff_flower --out .gpuF/flower_gaussian --schedule gaussian \
#       --seed 0
# then one call on kind nvidia-h100-x2, carrying [".whl", ".gpuF"]:
#   bash tools/campaigns/flower_profiles.sh
# (G0 and G1, default 0 and 1, name the two GPUs, e.g. G0=2 G1=3 beside another campaign on a 4-GPU machine.)
# It brings back $OUT/flower_profiles.tgz (flower_{1500,6000}.{json,txt}, trace_1500.{json,txt}, gaps_1500.txt,
# build.log, with CHECKS=1 gpu_tests.log and coding_launches.txt; not the traces themselves) and prints each
# profile's paired rows (and the coding-launch rows). The profiles belong in docs/results/speed/equal_budget/ (whose
# flower_*.json ran with gc_every 1 and 32 blocks / 4 warps per program in the coding pass, where flower's luma
# launch compiles to a backward binary spilling ~11.7 KB per thread; compare `_paper_backward` there).
set -u
F=${MANIFEST:-.gpuF/flower_gaussian/manifest.json} P=tools/diagnostics/profile_step.py
PAIRS=${PAIRS:-6} TL=${TL:-240} TL6=${TL6:-420} L=/tmp/flower_logs T=/tmp/flower_traces G0=${G0:-0} G1=${G1:-1}
mkdir -p $L $T
bash scripts/gpu_run.sh true > $L/build.log 2>&1
profile() {  # profile GPU WARMUP SECONDS: the profile after WARMUP steps on GPU
    CUDA_VISIBLE_DEVICES=$1 timeout "$3" bash scripts/gpu_run.sh python3 $P --manifest "$F" --device cuda \
        --preset mcmc --cap-max 300000 --warmup "$2" --steps 100 --pairs "$PAIRS" --no-fresh --jsgs-options '{}' \
        --out $L/flower_$2.json > $L/flower_$2.txt 2>&1
}
(profile $G0 1500 "$TL"; CUDA_VISIBLE_DEVICES=$G0 timeout 170 bash scripts/gpu_run.sh python3 $P --manifest "$F" \
    --device cuda --preset mcmc --cap-max 300000 --warmup 1500 --steps 40 --python-top 40 --trace $T \
    --out $L/trace_1500.json \
    > $L/trace_1500.txt 2>&1; timeout 60 python3 tools/diagnostics/trace_gaps.py $T/gsplat.trace.json \
    $T/jsgs.trace.json --steps 40 --top 30 > $L/gaps_1500.txt 2>&1
 if [ "${CHECKS:-0}" = 1 ]; then
    CUDA_VISIBLE_DEVICES=$G0 timeout 150 bash scripts/gpu_run.sh python3 -m pytest -m "gpu or slow" -rs \
        -p no:cacheprovider tests/test_jsgs/method/test_graphed.py tests/test_jsgs/kernels/test_triton_jo.py \
        > $L/gpu_tests.log 2>&1; CUDA_VISIBLE_DEVICES=$G0 timeout 90 bash scripts/gpu_run.sh python3 \
        benchmarks/bench_jpeg_ops.py --fused-jo --coding-launches --device cuda --repeats 50 \
        --sizes 504x378,1440x1920 > $L/coding_launches.txt 2>&1
 fi) &
profile $G1 6000 "$TL6" &
wait
for w in 1500 6000; do
    echo "== flower_$w"
    grep -E "^\| (gsplat|jsgs) \| [0-9.]+, " $L/flower_$w.txt
done
[ -f $L/gpu_tests.log ] && tail -n 3 $L/gpu_tests.log
[ -f $L/coding_launches.txt ] && grep -E "^\| (16|32)/4 \| " $L/coding_launches.txt
head -n 4 $L/gaps_1500.txt
tar czf "$OUT/flower_profiles.tgz" -C $L .
