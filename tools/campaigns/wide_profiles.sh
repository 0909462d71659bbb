# The equal-budget step profiles of a scene at least 900 px wide, with the current defaults:
# profile_step.py --preset mcmc (JSGS with the preset's recipe as it is), 6 interleaved pairs of 100-step
# windows after 1,500 steps on GPU 0 and at the full budget on GPU 1, one profile per GPU on one machine of
# 2 GPUs, side by side, in one call.
# The scene is jpeg_mouse downscaled by 2 (`jsgstools downscale`, whose factors are 2, 3, 4 and 8: 2 is the
# only one that leaves it at least 900 px wide) and compressed as flower is (gaussian schedule, seed 0):
# 960x720 (35 training views) and 720x960 (14), 691,200 pixels a view, 3.6x flower's. Its SfM model has 4,443
# points, so MCMC's 5 % additions every 100 steps from step 600 reach the preset's 300,000 Gaussians at the
# 87th, step 9,200 (7,593 Gaussians after 1,500 steps, as at camera resolution): WARMUP 9,300 is the full
# budget grown from the SfM points, as flower's 6,000 is (its cap at step 5,800); a random start at the cap
# (scale.sh's `:random`) would be quicker but is not the model a run holds.
# About 80 s of CUDA builds, then both profiles at once, the full budget's bounded by `timeout` to what is
# left of END (570) seconds; expected about 300 s for the full budget (2 x 9,300 warm-up steps and 14
# resumed copies), about 120 s for 1,500 steps.
# On the CPU first (.gpuH/ and .gpuW/ are ignored, as every .gpu*/ folder; only .gpuW is carried, 21 MB):
#   bash scripts/gpu_prepare.sh      # the wheels in .whl
#   .venv/bin/jsgstools downscale ../shared/scenes/jpeg_mouse --out .gpuH/jpeg_mouse_half --factor 2
#   .venv/bin/jsgstools compress .gpuH/jpeg_mouse_half --out .gpuW/jpeg_mouse_half_gaussian \
#       --schedule gaussian --seed 0
# then one call on kind nvidia-h100-x2, carrying [".whl", ".gpuW"]:
#   bash tools/campaigns/wide_profiles.sh
# (G0 and G1, default 0 and 1, name the two GPUs, e.g. G0=2 G1=3 beside another campaign on a 4-GPU machine.)
# It brings back $OUT/wide_profiles.tgz (jpeg_mouse_half_{1500,9300}.{json,txt}, build.log) and prints each
# profile's paired rows. The profiles belong in docs/results/speed/equal_budget/.
# A rehearsal on the CPU (the paths, the manifest, the archive) in a copy of the tree whose
# scripts/gpu_run.sh only runs its command: DEVICE=cpu WARMUPS="2 3" STEPS=2 PAIRS=1 with OUT set.
set -u
F=${MANIFEST:-.gpuW/jpeg_mouse_half_gaussian/manifest.json} P=tools/diagnostics/profile_step.py
PAIRS=${PAIRS:-6} STEPS=${STEPS:-100} DEVICE=${DEVICE:-cuda} END=${END:-570} L=/tmp/wide_logs
read -r W0 W1 <<<"${WARMUPS:-1500 9300}"
[ -f "$F" ] || { echo "wide_profiles.sh: $F: no manifest (prepare it on the CPU first, see the header)"; exit 2; }
rm -rf $L && mkdir -p $L
timeout 200 bash scripts/gpu_run.sh true > $L/build.log 2>&1
profile() {  # profile GPU WARMUP SECONDS: the profile after WARMUP steps on GPU
    CUDA_VISIBLE_DEVICES=$1 timeout "$3" bash scripts/gpu_run.sh python3 $P --manifest "$F" --device "$DEVICE" \
        --preset mcmc --cap-max 300000 --warmup "$2" --steps "$STEPS" --pairs "$PAIRS" --no-fresh --jsgs-options '{}' \
        --out $L/jpeg_mouse_half_$2.json > $L/jpeg_mouse_half_$2.txt 2>&1
    echo "exit status $? after $SECONDS s" >> $L/jpeg_mouse_half_$2.txt
}
left=$((END - SECONDS))
profile "${G0:-0}" "$W0" $((left < 300 ? left : 300)) &
profile "${G1:-1}" "$W1" "$left" &
wait
for w in $W0 $W1; do
    echo "== jpeg_mouse_half_$w"
    grep -E "^\| (gsplat|jsgs) \| [0-9.]+ \| |^\| (gsplat|jsgs) \| [0-9.]+, |^exit status" $L/jpeg_mouse_half_$w.txt
done
tar czf "$OUT/wide_profiles.tgz" -C $L .
