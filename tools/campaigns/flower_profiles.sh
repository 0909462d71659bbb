# The equal-budget step profiles of llff_flower with the current defaults: profile_step.py --preset mcmc
# (JSGS with the preset's recipe as it is, gc_every 4 included; the fused kernels at their launch settings;
# the image terms as one CUDA graph), 6 interleaved pairs of 100-step windows after 1,500 steps (40k
# Gaussians) and after 6,000 (the full budget, 300k), one profile per GPU on one machine of 2 GPUs, side by
# side, in one call (about 80 s of CUDA builds, then each profile bounded by `timeout`). The GPU tests of
# the graphed image terms and of the kernels run after the 1,500-step profile, on its GPU (they read their
# own numbers; the 6,000-step profile shares the host with them for its last minutes).
# On the CPU first (.gpuF/ is ignored, as every .gpu*/ folder):
#   bash scripts/gpu_prepare.sh      # the wheels in .whl
#   .venv/bin/jsgstools compress ../shared/scenes/llff_flower --out .gpuF/flower_gaussian --schedule gaussian \
#       --seed 0
# then one call on kind nvidia-h100-x2, carrying [".whl", ".gpuF"]:
#   bash tools/campaigns/flower_profiles.sh
# It writes $OUT/flower_{1500,6000}.{json,txt}, $OUT/gpu_tests.log and $OUT/build.log, and prints each
# profile's paired rows. The profiles belong in docs/results/speed/equal_budget/ (whose flower_*.json ran
# with gc_every 1 and 32 blocks / 4 warps per program in the coding pass).
set -u
F=${MANIFEST:-.gpuF/flower_gaussian/manifest.json} P=tools/diagnostics/profile_step.py
PAIRS=${PAIRS:-6} TL=${TL:-240}
bash scripts/gpu_run.sh true > "$OUT/build.log" 2>&1
profile() {  # profile GPU WARMUP: the profile after WARMUP steps on GPU
    CUDA_VISIBLE_DEVICES=$1 timeout "$TL" bash scripts/gpu_run.sh python3 $P --manifest "$F" --device cuda \
        --preset mcmc --warmup "$2" --steps 100 --pairs "$PAIRS" --no-fresh --jsgs-options '{}' \
        --out "$OUT/flower_$2.json" > "$OUT/flower_$2.txt" 2>&1
}
(profile 0 1500; CUDA_VISIBLE_DEVICES=0 timeout 200 bash scripts/gpu_run.sh python3 -m pytest -m "gpu or slow" \
    -rs -p no:cacheprovider tests/test_jsgs/method/test_graphed.py tests/test_jsgs/kernels/test_triton_jo.py \
    > "$OUT/gpu_tests.log" 2>&1) &
profile 1 6000 &
wait
for w in 1500 6000; do
    echo "== flower_$w"
    grep -E "^\| (gsplat|jsgs) \| [0-9.]+, " "$OUT/flower_$w.txt"
done
tail -n 3 "$OUT/gpu_tests.log"
