# The Gaussian Controller on every k-th step only (method_options.gc_every = K, weighted K·λ_fro there; the
# steps between render RGB without the probe's two channels) against every step (K = 1, the default), at
# equal budget (the mcmc preset, 300,000 Gaussians, JSGS with the preset's recipe), to decide whether K > 1
# can become the default: it must take JSGS's step nearer gsplat's and keep the quality.
#
# PART=speed: profile_step.py --pairs 6 (gsplat / JSGS windows of 100 steps resumed from one checkpoint,
#   interleaved; medians and the median ratio with its interval), one job at a time on GPU 0, for each K in
#   $KS: llff_flower (gaussian schedule) after 1,500 and 6,000 steps, jpeg_mouse (1440×1920) after 1,500.
#   Windows of 100 steps from step 1,502 hold exactly 100/K controller steps for K = 1, 2, 4.
#   Tables in $OUT/speed_K<K>_<scene>_<warmup>.txt, numbers in the .json beside.
# PART=quality: jsgs bench --strategy mcmc on llff_flower, gaussian schedule, seeds 0,1,2, 10,000 steps,
#   JSGS only, one bench folder per K (.res/gc_every<K>); decide on the final LPIPS / PSNR / SSIM of K against
#   K = 1 (within the seed spread). Repeat the call until every run is complete (the bench resumes); metrics
#   come back in $OUT/gc_every<K>.tgz and tools/results/build_report.py gathers them on the CPU.
#
# PART=toy (on the CPU, no GPU): the demo's synthetic scene (make demo: 64x48, uniform schedule), 1,500 steps
#   of the mcmc preset at 2,000 Gaussians, seeds 0,1,2, JSGS with K in $KS and without the controller
#   (gc false), one run at a time; logs in .res/gc_every_toy/. Run after `make demo`, about 35 minutes.
#
# On the CPU first, as speed_pairs.sh and speed_profile_camera.sh say (.gpu4/flower_gaussian and
# .gpu3/jpeg_mouse; `--preset mcmc` gives both methods the mcmc preset); the quality part reads llff_flower from $GPU_DIR/bench/data (made by
# scripts/gpu_prepare.sh), as confirm.sh does. Then on a lent GPU machine, carrying .whl, .gpu3 and .gpu4:
#   PART=speed KS="1 2 4" bash tools/campaigns/gc_every.sh
#   PART=quality KS=4 TL=540 bash scripts/gpu_run.sh bash tools/campaigns/gc_every.sh
# (one K per call: each bench call stops after TL seconds; K = 1 the same way if .res/gc_every1 is not there)
set -u
R='"lambda_obs":1.0,"base_by_view":true,"base_noise":"pixels","base_noise_ref":2.0,"base_noise_exponent":2.0'
KS=${KS:-1 2 4}
if [ "${PART:-speed}" = toy ]; then
    export OMP_NUM_THREADS=1
    [ -z "${JSGS_LPIPS_WEIGHTS:-}" ] && [ -f ../shared/lpips/alexnet_features.pth ] && \
        export JSGS_LPIPS_WEIGHTS=$PWD/../shared/lpips/alexnet_features.pth
    T=.res/gc_every_toy; mkdir -p $T
    for seed in 0 1 2; do
        for k in $KS off; do
            if [ $k = off ]; then o='"gc": false'; else o="\"gc_every\": $k"; fi
            echo "{\"method_options\": {$o}}" > $T/k$k.json
            .venv/bin/jsgs train demo_out/data/manifest.json --out $T/k${k}_s$seed --method jsgs --preset mcmc \
                --cap-max 2000 --config $T/k$k.json --iterations 1500 --eval-at 500,1500 --device cpu --quiet \
                --force --seed $seed > $T/k${k}_s$seed.log 2>&1
        done
    done
    grep -H "eval @ 1500" $T/*.log
elif [ "${PART:-speed}" = speed ]; then
    P=tools/diagnostics/profile_step.py
    export CUDA_VISIBLE_DEVICES=0
    bash scripts/gpu_run.sh true
    for k in $KS; do
        for job in flower_gaussian:.gpu4:1500 flower_gaussian:.gpu4:6000 jpeg_mouse:.gpu3:1500; do
            s=${job%%:*}; rest=${job#*:}; d=${rest%%:*}; w=${rest#*:}
            timeout 560 bash scripts/gpu_run.sh python3 $P --manifest $d/$s/manifest.json --device cuda \
                --preset mcmc --cap-max 300000 --jsgs-options "{$R,\"gc_every\":$k}" --warmup $w --steps 100 \
                --pairs 6 --no-fresh --out $OUT/speed_K${k}_${s}_$w.json > $OUT/speed_K${k}_${s}_$w.txt 2>&1
        done
    done
    grep -h -A4 "each window" $OUT/speed_K*.txt
else
    for k in $KS; do
        B=.res/gc_every$k
        mkdir -p $B/data
        [ -d $B/data/llff_flower ] || cp -r ${GPU_DIR:-.gpu}/bench/data/llff_flower $B/data/
        printf '{"method_options": {%s, "gc_every": %s}}\n' "$R" "$k" > $B/recipe.json
        python3 -m jsgs.cli bench llff_flower --out $B --strategy mcmc --budgets 300k --iterations 10000 \
            --schedules gaussian --methods jsgs --seeds 0,1,2 --eval-at 7000,10000 \
            --jobs-per-gpu "${JOBS:-3}" --jsgs-config $B/recipe.json --time-limit "${TL:-540}" --quiet 2>&1 | tail -8
        (cd $B && tar czf $OUT/gc_every$k.tgz results.csv report.md bench.json \
            $(ls runs/*/*/*/*/*/metrics.json runs/*/*/*/*/*/config.json 2>/dev/null) 2>/dev/null)
    done
    ls -la $OUT
fi
