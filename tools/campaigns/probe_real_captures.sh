# budget probe 3: cup, mouse, fern; mcmc preset; GPU tests after the rasterizer restructuring
# Its JSGS runs trained with the options' own values over the mcmc settings; the mcmc preset gives JSGS a recipe
# (jsgs.method.recipes.RECIPES), so to repeat them run them with --preset paper and the mcmc values
# of the mcmc preset (`jsgs.train.config.PRESETS`) in their config files.
set -u
T0=$(date +%s)
R=/tmp/probe; mkdir -p $R
D=.gpu3/bench/data
for s in llff_fern custom_kwrous_cup custom_myhan_mouse; do
  for sch in clean:0 gaussian:0 uniform:0 descending:0 gaussian:1; do
    python3 -c "from jsgstools.derive import derive; derive('$D/$s/clean_s0/manifest.json', '$R/data_${s}_${sch/:/_s}', '${sch%%:*}', seed=${sch##*:})" >/dev/null
  done
done
python3 -c "from gsplat.cuda._backend import _C; print('gsplat ready', flush=True)" 2>&1 | tail -1
python3 -c "from jsgs.kernels import extension; extension(); print('jsgs kernels ready')" 2>&1 | tail -1
echo "build done at $(( $(date +%s) - T0 )) s"
EV=1000,2000,3000,4000,5000,6000,7000,8000,9000,10000
run() { # gpu scene sched tag method seed settings-json
  echo "$7" > $R/cfg_$2_$3_$4.json
  CUDA_VISIBLE_DEVICES=$1 python3 -m jsgs.cli train $R/data_$2_$3/manifest.json --out $R/run_$2_$3_$4 --method $5 \
     --preset mcmc --config $R/cfg_$2_$3_$4.json --iterations 10000 --eval-at $EV --seed $6 --quiet \
     > $R/log_$2_$3_$4.txt 2>&1 &
}
C='"strategy": {"cap_max": 300000}'
C1='"strategy": {"cap_max": 100000}'
BV='"method_options": {"lambda_obs": 1.0, "base_by_view": true'
g=0
for s in custom_kwrous_cup custom_myhan_mouse; do
  run $g $s clean_s0 clean gsplat 42 "{$C}"
  run $g $s gaussian_s0 gsplat gsplat 42 "{$C}"
  run $g $s gaussian_s0 byview jsgs 42 "{$C, $BV}}"
  run $g $s gaussian_s0 byview4 jsgs 42 "{$C, $BV, \"base_noise_ref\": 4.0}}"
  run $g $s uniform_s0 gsplat gsplat 42 "{$C}"
  run $g $s uniform_s0 byview4 jsgs 42 "{$C, $BV, \"base_noise_ref\": 4.0}}"
  g=1
done
s=llff_fern
run 0 $s uniform_s0 byview4 jsgs 42 "{$C, $BV, \"base_noise_ref\": 4.0}}"
run 0 $s descending_s0 byview4 jsgs 42 "{$C, $BV, \"base_noise_ref\": 4.0}}"
run 1 $s gaussian_s1 byview4 jsgs 43 "{$C, $BV, \"base_noise_ref\": 4.0}}"
run 1 $s clean_s0 clean100k gsplat 42 "{$C1}"
run 0 $s gaussian_s0 gsplat100k gsplat 42 "{$C1}"
run 1 $s gaussian_s0 byview4_100k jsgs 42 "{$C1, $BV, \"base_noise_ref\": 4.0}}"
sleep 2
echo "runs started at $(( $(date +%s) - T0 )) s: $(jobs -r | wc -l)"
JSGS_GPU_MANIFEST=$R/data_llff_fern_gaussian_s0/manifest.json timeout ${TEST_LIMIT:-150} python3 -m pytest -m gpu tests -q -x -p no:cacheprovider 2>&1 | tail -6 > $OUT/gpu_tests.txt
cat $OUT/gpu_tests.txt
while [ $(jobs -r | wc -l) -gt 0 ] && [ $(( $(date +%s) - T0 )) -lt ${DEADLINE:-550} ]; do sleep 5; done
echo "runs still going: $(jobs -r | wc -l) at $(( $(date +%s) - T0 )) s"
for f in $R/log_*.txt; do echo "$(basename $f): $(tail -c 400 $f | tr '\r' '\n' | grep -E 'complete|error|stopped|Error' | tail -1)"; done
cd $R && tar czf $OUT/probe3.tgz run_*/metrics.json run_*/config.json log_*.txt cfg_*.json 2>/dev/null
