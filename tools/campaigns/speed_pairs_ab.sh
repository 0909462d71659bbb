# Two versions of the code timed with the protocol on one GPU: the checkout (a) and another commit's
# jsgs package (b, in .gpu4/base), each with profile_step.py --pairs (interleaved gsplat / JSGS windows
# resumed from one checkpoint; medians and the median ratio), 100-step windows, llff_flower, gaussian
# schedule, the mcmc preset, JSGS with the default recipe. b runs this checkout's profile_step.py against its
# own jsgs package. The jobs run one after another, each alone on GPU 0, in the order given:
#   bash tools/campaigns/speed_pairs_ab.sh a:1500 b:1500 b:6000 a:6000
# VERSION:WARMUP: the window after 1,500 steps (about 38,000 Gaussians) or 6,000 (the 300,000 budget
# reached); PAIRS (default 5) interleaved pairs each; with GPU_TESTS=1, then the checkout's GPU tests (the
# CUDA paths of the code being timed; $OUT/gpu_tests.txt). Tables in $OUT/VERSION_pairs_WARMUP.txt, numbers
# in the .json beside. On the CPU first (as for speed_pairs.sh, then):
#   mkdir -p .gpu4/base && git archive COMMIT jsgs scripts | tar -x -C .gpu4/base && cp -r tools .gpu4/base/
# then on a lent GPU machine, carrying .whl and .gpu4. Chained calls on a warm machine reuse the builds.
set -u
O='{"lambda_obs":1.0,"base_by_view":true,"base_noise":"pixels","base_noise_ref":2.0,"base_noise_exponent":2.0}'
R=$PWD; export TORCH_EXTENSIONS_DIR=$R/.torch_ext CUDA_VISIBLE_DEVICES=0
bash scripts/gpu_run.sh true
# b builds jsgs's kernels from its own path into its own folder (a shared one would rebuild at every switch),
# outside the carried folders so that a warm machine keeps it; gsplat's build is the same for both, copied
B=/tmp/torch_ext_b
case " $* " in *" b:"*)
    [ -d $B/gsplat_cuda ] || { mkdir -p $B && cp -r $TORCH_EXTENSIONS_DIR/gsplat_cuda $B/; }
    (cd .gpu4/base && TORCH_EXTENSIONS_DIR=$B bash scripts/gpu_run.sh true) ;;
esac
for job in "$@"; do
    v=${job%%:*}; w=${job##*:}
    if [ $v = a ]; then d=.; e=$TORCH_EXTENSIONS_DIR; else d=.gpu4/base; e=$B; fi
    (cd $d && TORCH_EXTENSIONS_DIR=$e timeout 240 bash scripts/gpu_run.sh python3 \
        tools/diagnostics/profile_step.py --manifest "$R/.gpu4/flower_gaussian/manifest.json" --device cuda \
        --preset mcmc --cap-max 300000 --jsgs-options "$O" --warmup $w --steps 100 --pairs ${PAIRS:-5} \
        --no-fresh --out $OUT/${v}_pairs_$w.json > $OUT/${v}_pairs_$w.txt 2>&1)
done
if [ -n "${GPU_TESTS:-}" ]; then
    JSGS_GPU_MANIFEST=$R/.gpu4/flower_gaussian/manifest.json timeout 150 bash scripts/gpu_run.sh \
        python3 -m pytest -m gpu tests -q -x -p no:cacheprovider > $OUT/gpu_tests.txt 2>&1
    tail -15 $OUT/gpu_tests.txt
fi
