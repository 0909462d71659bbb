# The checks only a GPU can make, in one call on a machine of 4 GPUs, each part bounded so the call ends
# well inside the device tool's 600 s:
#   GPUs 0-1  the several-GPU tests (gsplat's exchange: gradients and statistics against one GPU; gsplat's
#             exchange against the torch exchange at equal steps), then `scale.sh` on jpeg_mouse;
#   GPU 2     the fused Triton kernels' GPU tests (JO in modes paper and float, DS, the colour conversion)
#             and the footprint attribution's (gsplat against its probe), bench_jpeg_ops.py --fused-jo, then
#             jpeg_mouse's step profile with `gc_attribution` footprint (GPU 3's protocol);
#   GPU 3     equal-budget step profiles (`--preset mcmc`, 6 interleaved pairs after 1,500 steps) of jpeg_mouse
#             at 1440x1920 with the default kernels and with `fused_color` and `gc_every` 4 as well.
# On the CPU first, into a folder that .git/info/exclude ignores (the carry, with the tracked tree, stays under
# 64 MiB: about 23 MiB of tree, 7 of wheels, 10 of jpeg_mouse):
#   bash scripts/gpu_prepare.sh                                   # .whl
#   mkdir -p .gpuK/.gpu3 && cp -r ../shared/scenes/jpeg_mouse .gpuK/.gpu3/ && \
#       .venv/bin/jsgstools manifest .gpuK/.gpu3/jpeg_mouse --out .gpuK/.gpu3/jpeg_mouse/manifest.json --analyze
# then, carrying [".whl", ".gpuK"]:
#   GPU3=.gpuK/.gpu3 bash tools/campaigns/gpu_checks.sh
# The device tool brings back at most 8 files from $OUT: everything comes back as $OUT/gpu_checks.tgz. A
# folder the call does not carry is not kept on a warm machine, /tmp is: the runs go to /tmp/gpu_checks.
set -u
ln -sfn "${GPU3:-.gpuK/.gpu3}" .gpu3
O=/tmp/gpu_checks; rm -rf $O; mkdir -p $O
bash scripts/gpu_run.sh true > $O/build.log 2>&1
P=tools/diagnostics/profile_step.py
(
    export CUDA_VISIBLE_DEVICES=0,1
    timeout 120 bash scripts/gpu_run.sh python3 -m pytest -q -m gpu tests/test_jsgs/train/test_distributed.py \
        -p no:cacheprovider > $O/dist_tests.log 2>&1
    SCENES="jpeg_mouse:300000" ITERS=2000 TL=60 timeout 200 bash scripts/gpu_run.sh bash tools/campaigns/scale.sh \
        > $O/scale.log 2>&1
) &
(
    export CUDA_VISIBLE_DEVICES=2
    timeout 150 bash scripts/gpu_run.sh python3 -m pytest -m "gpu or slow" -s -rs -p no:cacheprovider \
        tests/test_jsgs/kernels/test_triton_jo.py tests/test_jsgs/kernels/test_triton_color.py \
        tests/test_jsgs/method/test_graphed.py::test_gpu_training_with_fused_jo_matches_the_twin \
        tests/test_jsgs/render/test_render_gpu.py::test_footprint_attribution_on_gsplat_matches_its_probe \
        > $O/fused_tests.log 2>&1
    timeout 90 bash scripts/gpu_run.sh python3 benchmarks/bench_jpeg_ops.py --fused-jo --device cuda --repeats 50 \
        --warmup 5 > $O/fused_bench.log 2>&1
    timeout 190 bash scripts/gpu_run.sh python3 $P --manifest .gpu3/jpeg_mouse/manifest.json --device cuda \
        --preset mcmc --warmup 1500 --steps 100 --pairs 6 --no-fresh --jsgs-options '{"gc_attribution":"footprint"}' \
        --out $O/camera_jpeg_mouse_1500_footprint.json > $O/camera_jpeg_mouse_1500_footprint.txt 2>&1
) &
(
    export CUDA_VISIBLE_DEVICES=3
    for v in 'default:{}' 'color_k4:{"speed":{"fused_color":true},"gc_every":4}'; do
        timeout 190 bash scripts/gpu_run.sh python3 $P --manifest .gpu3/jpeg_mouse/manifest.json --device cuda \
            --preset mcmc --warmup 1500 --steps 100 --pairs 6 --no-fresh --jsgs-options "${v#*:}" \
            --out $O/camera_jpeg_mouse_1500_${v%%:*}.json > $O/camera_jpeg_mouse_1500_${v%%:*}.txt 2>&1
    done
) &
wait
mkdir -p $O/scale && cp "${OUT:-.}"/scale.md $O/scale/ 2>/dev/null
(cd .res/scale 2>/dev/null && tar cf - */*/*/metrics.json */*/*/config.json */*/*.log */*/*.settings.json 2>/dev/null) \
    | (cd $O/scale && tar xf - 2>/dev/null)
rm -f "${OUT:-.}"/scale.md "${OUT:-.}"/scale.tgz
tar czf "${OUT:-.}/gpu_checks.tgz" -C $O .
ls -la "${OUT:-.}"
