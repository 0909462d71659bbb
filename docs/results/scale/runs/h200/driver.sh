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
(scale 0,1 $F gsplat 2 $FI 200) & (scale 2,3 $F gsplat:torch 2 $FI 200) &
wait
scale 0,1,2,3 $F jsgs 4 $FI 200
scale 0,1,2,3 $F gsplat 4 $FI 200
date +%T > $L/driver_end
