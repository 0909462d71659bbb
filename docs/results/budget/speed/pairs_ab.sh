# Two versions of the code, each timed with the protocol on the same machine in one call: the
# checkout (A) and another commit's jsgs package (B, in .gpu4/base), each with profile_step.py --pairs
# (interleaved gsplat / JSGS windows resumed from one checkpoint; medians and the median ratio), 100-step
# windows, llff_flower, gaussian schedule, the mcmc preset, JSGS with the default recipe. B runs this
# checkout's profile_step.py against its own jsgs package. On the CPU first (as for pairs.sh, then):
#   mkdir -p .gpu4/base && git archive COMMIT jsgs scripts | tar -x -C .gpu4/base && cp -r tools .gpu4/base/
# then on a lent 2-GPU machine, carrying .whl and .gpu4:
#   bash docs/results/budget/speed/pairs_ab.sh
# A on GPU 0 and B on GPU 1, side by side: the window after 6,000 steps (the 300,000 budget reached), then
# the one after 1,500 (about 38,000 Gaussians), 5 pairs each; then GPU 0 runs the checkout's GPU tests (the
# CUDA paths of the code being timed; $OUT/gpu_tests.txt). Tables in $OUT/{a,b}_pairs_*.txt, numbers in the
# .json beside.
set -u
O='{"lambda_obs":1.0,"base_by_view":true,"base_noise":"pixels","base_noise_ref":2.0,"base_noise_exponent":2.0}'
R=$PWD; export TORCH_EXTENSIONS_DIR=$R/.torch_ext
bash scripts/gpu_run.sh true
# B builds jsgs's kernels from its own path into its own folder (a shared one would rebuild at every switch);
# gsplat's build is the same for both and is copied
B=$R/.gpu4/base/.torch_ext; mkdir -p $B && cp -r $TORCH_EXTENSIONS_DIR/gsplat_cuda $B/
(cd .gpu4/base && TORCH_EXTENSIONS_DIR=$B bash scripts/gpu_run.sh true)
one() {  # one VERSION GPU: both windows of one version on one GPU
    if [ $1 = a ]; then d=.; e=$TORCH_EXTENSIONS_DIR; else d=.gpu4/base; e=$B; fi
    for w in 6000 1500; do
        (cd $d && CUDA_VISIBLE_DEVICES=$2 TORCH_EXTENSIONS_DIR=$e timeout 240 bash scripts/gpu_run.sh python3 \
            tools/diagnostics/profile_step.py --manifest "$R/.gpu4/flower_gaussian/manifest.json" \
            --device cuda --config "$R/.gpu4/mcmc.json" --jsgs-options "$O" --warmup $w --steps 100 \
            --pairs 5 --no-fresh --out $OUT/$1_pairs_$w.json > $OUT/$1_pairs_$w.txt 2>&1)
    done
}
one b 1 &
one a 0
CUDA_VISIBLE_DEVICES=0 JSGS_GPU_MANIFEST=$R/.gpu4/flower_gaussian/manifest.json timeout 150 \
    bash scripts/gpu_run.sh python3 -m pytest -m gpu tests -q -x -p no:cacheprovider 2>&1 | tail -15 \
    > $OUT/gpu_tests.txt
wait
