# The GPU check of JSGS's memory and host-op cuts (their CPU tests stand in for the CUDA parts), in one call
# on a machine of 2 GPUs: the GPU tests of the paths they change and the peak device memory against gsplat's.
# Last run at 835baed with SETTLE=50 on 2 H200s (docs/results/speed/equal_budget: `*_memory_h200`,
# `memory_check_*_h200`; 70 + 3 tests passed). The cuts: the image terms' chain keeps less for its backward
# (the clamp a mask, L1 no difference image, the replicate pads only a shape, the luma plane copied out of
# the YCbCr image for the fused coding pass, the fused SSIM's mean one node given a broadcast upstream, the
# target laid out as the fused SSIM keeps it, r_b without r(p)); the graph's values are its output buffer
# (no copy), a gradient with an upstream of exactly 1 is handed on without the product (the graph's and
# the probe's deferred map), views with equal tables share one tensor that the graph copies only when it
# changes, the probe's objective is a view of a kept zero; and the earlier memory cuts (one buffer set for
# both orientations, r kept as block scores, the step's image read in place, the probe's map made in the
# backward, the five-channel image freed after the render).
#   (a) the GPU tests of the changed paths: first the 2-GPU tests (tests/test_jsgs/train/test_distributed.py
#       -m gpu, on both GPUs, before anything else runs), then on GPU G0 the graphed image terms (the two
#       orientations replaying on shared buffers included), the chain's cuts against the formulation they
#       replace and the graph's calls as the hook makes them against copying ones (test_cuda_cuts.py), the
#       chain's peak against its shape budget (test_chain_memory.py), the JSGS method's gsplat path (r-bar
#       on the carried 960x720 scene: JSGS_GPU_MANIFEST), the controller's and the render's GPU tests (the
#       probe's extra channels, its objective and unit-upstream map on gsplat) and the fused kernels (Triton
#       JO and colour, the SSIM kernels), `-m gpu`;
#   (b) the peak device memory at the points measured before the cuts (docs/results/speed/equal_budget:
#       camera_jpeg_mouse_1500_free_h200.json 811.8 / 948.9 MiB allocated, jpeg_mouse_half_1500_h200.json
#       230.3 / 267.5, jpeg_mouse_half_9300_h200.json 576.2 / 676.7; gsplat / JSGS): profile_step.py
#       --preset mcmc --steps 100 with the recipe as it is, PAIRS (1) interleaved pair(s) besides the plain
#       window (the memory figures are each process's own, exact whatever runs beside it; the step times
#       are not one-job-per-GPU numbers: a GPU test or the other profile may share the host);
#   (c) where JSGS's extra lives: the same profiles with --memory-history TOP (25) --memory-steps MSTEPS
#       (8: two of the controller's steps at gc_every 4) --memory-stacks STACKS (all: C++ frames too, which
#       name a backward's autograd node; TORCH_SYMBOLIZE_MODE=fast): each method resumed once more with the
#       CUDA allocator's history recorded from the run's start, the live allocations at the window's start
#       and peak grouped by the frame that made them, and JSGS's groups minus gsplat's. Read the 300,000-
#       Gaussian profile against the 7,593-Gaussian one at the same 960x720 for the per-Gaussian part
#       (about 155 B a Gaussian that the tensors' shapes do not explain, docs/performance.md).
# In order: the CUDA builds (about 80 s on a fresh machine, at most 200), the 2-GPU tests (78 s on H200s, at
# most 150), then side by side: GPU G0 the GPU tests (at most 150) and jpeg_mouse at 1440x1920 after W0
# (1,500) steps (about 120 s); GPU G1 the 960x720 scene after W1 (9,300: the 300,000 cap; about 220 s) and
# after W0 steps (about 60 s). Every part is bounded by `timeout` to what is left of END (540) seconds, so
# the call ends within about 9 minutes whatever hangs (a part cut short loses only itself: profile_step.py
# prints and writes the memory figures before it records the history). Expected about 8 minutes with
# SETTLE=50 (at 835baed the last part reached its bound, its files written). `timeout -k 15`: the trainer
# takes SIGTERM as "stop after this step, with a checkpoint", so a bare TERM let that part run 52 s past its
# bound; KILL follows 15 s after it.
# On the CPU first (folders that .gitignore's .gpu*/ ignores): the two scenes without their sparse/ folders
# (the manifests hold the cameras and points), 27.8 MB in .gpuMem; the half scene's manifest names its test
# views' references, which loading it checks, so reference/ stays. With the tree (27.0 MB) and the wheels
# (7.0 MB), 61.9 MB = 59.0 MiB of the 64 MiB a call carries (.gpuM and .gpuW whole: 62.3 MiB):
#   mkdir -p .gpuMem/jpeg_mouse .gpuMem/jpeg_mouse_half_gaussian
#   cp -r .gpuM/jpeg_mouse/manifest.json .gpuM/jpeg_mouse/images .gpuMem/jpeg_mouse/
#   cp -r .gpuW/jpeg_mouse_half_gaussian/{manifest.json,compress.json,images,reference} \
#       .gpuMem/jpeg_mouse_half_gaussian/
#   the wheels in .whl (scripts/gpu_prepare.sh's pip download line)
# (.gpuM: warmup_memory.sh's header; .gpuW: wide_profiles.sh's), then one call on kind nvidia-h100-x2,
# carrying [".whl", ".gpuMem"]:
#   bash tools/campaigns/memory_check.sh
# (G0 and G1, default 0 and 1, name the two GPUs, e.g. G0=2 G1=3 beside another campaign on a 4-GPU machine.)
# It brings back $OUT/memory_check.tgz (gpu_tests_2gpu.log, gpu_tests.log, camera_jpeg_mouse_1500.{json,txt},
# jpeg_mouse_half_{9300,1500}.{json,txt}, times.txt, build.log) and prints the tests' last lines, each
# profile's peak memory rows and the memory-history difference tables. The profiles belong in
# docs/results/speed/equal_budget/ (`_memory` beside the names above, with the device suffix).
# SETTLE (50): profile_step.py's --settle. jpeg_mouse's views come in two orientations, each with its image
# terms' graph recorded on the first step that draws it: with 2 the second may be recorded inside the window
# (at fb8623d the 300,000-Gaussian one: its peak was that recording); SETTLE=50 (one epoch of the 49 views)
# records both before the window, at 48 more steps in each resumed run.
# A rehearsal on the CPU (the paths, the manifests, the archive) in a copy of the tree whose
# scripts/gpu_run.sh only runs its command: DEVICE=cpu WARMUPS="2 3" STEPS=2 MSTEPS=1 with OUT set.
set -u
D=${DATA:-.gpuMem} P=tools/diagnostics/profile_step.py L=${LOGS:-/tmp/memory_check_logs}
CAM=$D/jpeg_mouse/manifest.json HALF=$D/jpeg_mouse_half_gaussian/manifest.json
DEVICE=${DEVICE:-cuda} G0=${G0:-0} G1=${G1:-1} END=${END:-540} STEPS=${STEPS:-100} PAIRS=${PAIRS:-1}
SETTLE=${SETTLE:-50}
TOP=${TOP:-25} MSTEPS=${MSTEPS:-8} STACKS=${STACKS:-all}
read -r W0 W1 <<<"${WARMUPS:-1500 9300}"
for f in "$CAM" "$HALF"; do
    [ -f "$f" ] || { echo "memory_check.sh: $f: no manifest (prepare it on the CPU first, see the header)"; exit 2; }
done
rm -rf "$L" && mkdir -p "$L"
left() {  # left CAP: CAP seconds, or what is left of END if less (at least 1)
    local n=$((END - SECONDS))
    if [ "$n" -gt "$1" ]; then echo "$1"; elif [ "$n" -gt 1 ]; then echo "$n"; else echo 1; fi
}
stamp() { echo "$1: exit status $2 at $SECONDS s" >> "$L/times.txt"; }
timeout -k 15 "$(left 200)" bash scripts/gpu_run.sh true > "$L/build.log" 2>&1
stamp build $?
CUDA_VISIBLE_DEVICES=$G0,$G1 timeout -k 15 "$(left 150)" bash scripts/gpu_run.sh python3 -m pytest -m gpu -rs \
    -p no:cacheprovider tests/test_jsgs/train/test_distributed.py > "$L/gpu_tests_2gpu.log" 2>&1
stamp gpu_tests_2gpu $?
profile() {  # profile GPU MANIFEST WARMUP NAME SECONDS: the memory profile and history after WARMUP steps
    CUDA_VISIBLE_DEVICES=$1 TORCH_SYMBOLIZE_MODE=fast timeout -k 15 "$5" bash scripts/gpu_run.sh python3 $P \
        --manifest "$2" --device "$DEVICE" --preset mcmc --cap-max 300000 --warmup "$3" --settle "$SETTLE" \
        --steps "$STEPS" \
        --pairs "$PAIRS" --no-fresh --jsgs-options '{}' --memory-history "$TOP" --memory-steps "$MSTEPS" \
        --memory-stacks "$STACKS" --out "$L/$4.json" > "$L/$4.txt" 2>&1
    stamp "$4" $?
}
(CUDA_VISIBLE_DEVICES=$G0 JSGS_GPU_MANIFEST=$HALF timeout -k 15 "$(left 150)" bash scripts/gpu_run.sh python3 -m \
    pytest -m gpu -rs -p no:cacheprovider tests/test_jsgs/method/test_graphed.py \
    tests/test_jsgs/method/test_jsgs_method.py tests/test_jsgs/method/test_controller_cuda.py \
    tests/test_jsgs/render/test_render_gpu.py tests/test_jsgs/kernels/test_triton_jo.py \
    tests/test_jsgs/kernels/test_triton_color.py tests/test_jsgs/kernels/test_ssim_cuda.py \
    tests/test_jsgs/method/test_cuda_cuts.py tests/test_jsgs/method/test_chain_memory.py \
    > "$L/gpu_tests.log" 2>&1
 stamp gpu_tests $?
 profile "$G0" "$CAM" "$W0" "camera_jpeg_mouse_$W0" "$(left 300)") &
(profile "$G1" "$HALF" "$W1" "jpeg_mouse_half_$W1" "$(left 400)"
 profile "$G1" "$HALF" "$W0" "jpeg_mouse_half_$W0" "$(left 150)") &
wait
for f in gpu_tests_2gpu gpu_tests; do echo "== $f"; tail -n 3 "$L/$f.log"; done
for name in "camera_jpeg_mouse_$W0" "jpeg_mouse_half_$W1" "jpeg_mouse_half_$W0"; do
    echo "== $name"
    grep -E "^\| (gsplat|jsgs) \| (allocated|reserved) \| peak \||^(gsplat|jsgs): [0-9]+ Gaussians; " \
        "$L/$name.txt"
    sed -n "/^jsgs − gsplat: live at the window's peak/,/^jsgs − gsplat: live at the window's start/p" \
        "$L/$name.txt" | head -n 20
done
cat "$L/times.txt"
tar czf "$OUT/memory_check.tgz" -C "$L" .
