# One scene on several GPUs, the whole target in two chained calls on one machine of 4 GPUs (the pattern of
# rule_and_checks.sh: the runs go detached with setsid from a copy of the tree in /tmp/src, the calls start,
# wait and collect, every part is bounded with timeout, each call brings back one archive):
#   - the several-GPU GPU tests (GPUs 0-1): gsplat's exchange against one GPU, and gsplat's exchange against
#     the torch exchange at equal steps (the torch exchange's reduce-scatter and SH bands on NCCL);
#   - scale.sh on jpeg_mouse at camera resolution (ITERS 4000: 1, 2 and 4 GPUs, gsplat and JSGS) and on flower
#     at 1,000,000 random Gaussians (ITERS 2000: 1, 2 and 4 GPUs, gsplat and JSGS on the torch exchange, the
#     default, and gsplat on its own exchange, `gsplat:gsplat`, on 2 GPUs), each run evaluated after a fifth
#     of its steps and at its end (views/s over the whole run and after the first evaluation).
# Runs on disjoint GPUs go side by side (each table row says which GPUs its run had; the GPUs it did not
# use may have run another run); every 4-GPU run has the machine to itself. In order:
#   GPUs 0-1 the GPU tests | GPU 2 mouse gsplat g1 and GPU 3 mouse JSGS g1, then GPUs 2-3 mouse gsplat g2,
#     then mouse JSGS g2
#   all 4: mouse gsplat g4, mouse JSGS g4
#   GPU 0 1M JSGS g1 | GPU 1 1M gsplat g1 | GPUs 2-3 1M JSGS g2
#   GPUs 0-1 1M gsplat g2 (gsplat's exchange) | GPUs 2-3 1M gsplat g2 (torch exchange)
#   all 4: 1M JSGS g4, 1M gsplat g4 (torch exchange; gsplat's exchange on 4 GPUs: docs/results/scale)
# about 12 minutes in all (a 1M run's setup, the exact nearest neighbours of 1,000,000 points on every
# process, takes 55-85 s).
# On the CPU first (folders that .gitignore's .gpu*/ ignores; about 45 MiB with the wheels):
#   mkdir -p .gpuScale && cp -r ../shared/scenes/jpeg_mouse .gpuScale/ && \
#       .venv/bin/jsgstools manifest .gpuScale/jpeg_mouse --out .gpuScale/jpeg_mouse/manifest.json --analyze
#   .venv/bin/jsgstools compress ../shared/scenes/llff_flower --out .gpuScale/llff_flower --schedule gaussian \
#       --seed 0 && rm -rf .gpuScale/llff_flower/sparse
#   cp ../shared/lpips/alexnet_features.pth .gpuScale/
#   mkdir -p .gpuScale2 && mv .gpuScale/llff_flower .gpuScale2/
#   the wheels in .whl (scripts/gpu_prepare.sh's pip download line)
# (the tree, the wheels and both scenes are over the 64 MiB a call carries: the flower, needed only after the
# mouse's runs, comes with the second call, and the driver waits for it), then two calls, the second started
# within 30 s of the first one's end (kind nvidia-h100-x4):
#   PHASE=1 bash tools/campaigns/scale_check.sh     # carry [".whl", ".gpuScale"]
#   PHASE=2 bash tools/campaigns/scale_check.sh     # carry [".gpuScale2"]
# (PHASE=2 again, with no carry, while the driver has not ended.)
# (SRC, DATA, LOGS, SCALE_RES, MOUSE, BIG, MOUSE_ITERS and BIG_ITERS change the folders in /tmp, the two scenes'
# specs, as scale.sh's SCENES, and their ITERS.) Each brings back $OUT/scale_<PHASE>.tgz: the logs, scale.md (the table of every run finished so far) and
# every run's metrics.json, config.json, settings and log (no models, renders or checkpoints).
set -u
PHASE=${PHASE:?set PHASE=1 or 2}
export S=${SRC:-/tmp/src} L=${LOGS:-/tmp/scale_logs} RES=${SCALE_RES:-/tmp/scale_res}
export M=${MOUSE:-jpeg_mouse:300000} MI=${MOUSE_ITERS:-4000}
export F=${BIG:-llff_flower:1000000:random} FI=${BIG_ITERS:-2000}
export D=${DATA:-/tmp/scaledata}
export TORCH_EXTENSIONS_DIR=/tmp/torch_ext JSGS_LPIPS_WEIGHTS=$D/alexnet_features.pth
mkdir -p $L
case $PHASE in
  1)
    rm -rf $S $D $RES && mkdir -p $S $D $RES
    tar cf - --exclude=./.gpuScale --exclude=./.res --exclude=./.torch_ext . | tar xf - -C $S
    cp -r .gpuScale/. $D/
    cd $S && ln -sfn $D .gpu3
    (bash scripts/gpu_run.sh true) > $L/build.log 2>&1
    cat > $L/driver.sh <<'EOF'
set -u
cd $S
scale() {  # scale GPUS SCENE METHOD N ITERS TL: one scale.sh run on the GPUs GPUS
    CUDA_VISIBLE_DEVICES=$1 RES=$RES SCENES=$2 METHODS=$3 GPUS=$4 ITERS=$5 TL=$6 OUT=$L/out \
        timeout $(($6 + 30)) bash scripts/gpu_run.sh bash tools/campaigns/scale.sh >> $L/scale_runs.log 2>&1
}
date +%T > $L/driver_start
(CUDA_VISIBLE_DEVICES=0,1 timeout 240 bash scripts/gpu_run.sh python3 -m pytest -m gpu -s -rs \
    -p no:cacheprovider tests/test_jsgs/train/test_distributed.py > $L/gpu_tests.log 2>&1) &
scale 2 $M gsplat 1 $MI 150 & a=$!
scale 3 $M jsgs 1 $MI 150 & b=$!
wait $a $b
scale 2,3 $M gsplat 2 $MI 120
scale 2,3 $M jsgs 2 $MI 120
wait
scale 0,1,2,3 $M gsplat 4 $MI 100
scale 0,1,2,3 $M jsgs 4 $MI 100
i=0; while [ ! -f $D/${F%%:*}/manifest.json ] && [ $i -lt 120 ]; do sleep 5; i=$((i + 1)); done
(scale 0 $F jsgs 1 $FI 200) & (scale 1 $F gsplat 1 $FI 200) & (scale 2,3 $F jsgs 2 $FI 200) &
wait
(scale 0,1 $F gsplat:gsplat 2 $FI 200) & (scale 2,3 $F gsplat 2 $FI 200) &
wait
scale 0,1,2,3 $F jsgs 4 $FI 200
scale 0,1,2,3 $F gsplat 4 $FI 200
date +%T > $L/driver_end
EOF
    (setsid nohup bash $L/driver.sh > $L/driver.log 2>&1 < /dev/null &)
    end=$((SECONDS + ${WAIT:-400}))
    while [ $SECONDS -lt $end ] && [ ! -f $L/driver_end ]; do sleep 10; done
    ;;
  2)
    if [ -d .gpuScale2 ]; then  # the second scene: whole folders moved in, so the driver never sees half a copy
        rm -rf $D/.in && cp -r .gpuScale2 $D/.in && mv $D/.in/* $D/ && rmdir $D/.in
    fi
    end=$((SECONDS + ${WAIT:-500}))
    while [ $SECONDS -lt $end ] && [ ! -f $L/driver_end ]; do sleep 10; done
    ;;
esac
cd $S 2>/dev/null && python3 tools/results/scale_table.py $RES > $L/scale.md 2>&1
nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv > $L/smi_$PHASE.txt 2>&1
(cd $RES && tar cf - */*/*/metrics.json */*/*/config.json */*/*.log */*/*.settings.json 2>/dev/null) > $L/runs.tar
tar czf "$OUT/scale_$PHASE.tgz" -C $L --exclude=./out .
ls -la "$OUT"
