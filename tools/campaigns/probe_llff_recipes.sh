# budget probe: flower + fern, gaussian schedule seed 0, mcmc preset cap 300k, 10k steps; 6 runs per GPU
# Its JSGS runs trained with the options' own values over the mcmc settings; the mcmc preset gives JSGS a recipe
# (jsgs.method.recipes.RECIPES), so to repeat them run them with --preset paper and the mcmc values
# of the mcmc preset (`jsgs.train.config.PRESETS`) in their config files.
set -u
T0=$(date +%s)
R=/tmp/probe; mkdir -p $R
for s in llff_flower llff_fern; do
  python3 -c "from jsgstools.derive import derive; derive('.gpu/bench/data/$s/clean_s0/manifest.json', '$R/data_$s', 'gaussian', seed=0)" >/dev/null
done
python3 -c "from gsplat.cuda._backend import _C; print('gsplat ready', flush=True)" 2>&1 | tail -1
python3 -c "from jsgs.kernels import extension; extension(); print('jsgs kernels ready')" 2>&1 | tail -1
echo "build done at $(( $(date +%s) - T0 )) s"
run() { # gpu scene name method manifest settings-json
  echo "$6" > $R/cfg_$2_$3.json
  CUDA_VISIBLE_DEVICES=$1 python3 -m jsgs.cli train $5 --out $R/run_$2_$3 --method $4 --preset mcmc \
     --config $R/cfg_$2_$3.json --iterations ${ITERS:-10000} --quiet > $R/log_$2_$3.txt 2>&1 &
}
C='"strategy": {"cap_max": 300000}'
g=0
for s in llff_flower llff_fern; do
  M=$R/data_$s/manifest.json
  run $g $s clean gsplat .gpu/bench/data/$s/clean_s0/manifest.json "{$C}"
  run $g $s gsplat gsplat $M "{$C}"
  run $g $s paper jsgs $M "{$C}"
  run $g $s joonly jsgs $M "{$C, \"loss\": {\"base_weight\": 0.0}, \"method_options\": {\"lambda_obs\": 1.0}}"
  run $g $s byview jsgs $M "{$C, \"method_options\": {\"lambda_obs\": 1.0, \"base_by_view\": true}}"
  run $g $s b05o2 jsgs $M "{$C, \"loss\": {\"base_weight\": 0.5}, \"method_options\": {\"lambda_obs\": 2.0}}"
  g=1
done
sleep 5
echo "runs started at $(( $(date +%s) - T0 )) s"
JSGS_GPU_MANIFEST=$R/data_llff_flower/manifest.json timeout ${TEST_LIMIT:-200} python3 -m pytest -m gpu tests -q -x -p no:cacheprovider 2>&1 | tail -15 > $OUT/gpu_tests.txt
cat $OUT/gpu_tests.txt
echo "tests done at $(( $(date +%s) - T0 )) s"
while [ $(jobs -r | wc -l) -gt 0 ] && [ $(( $(date +%s) - T0 )) -lt ${DEADLINE:-560} ]; do sleep 5; done
echo "runs still going: $(jobs -r | wc -l) at $(( $(date +%s) - T0 )) s"
for f in $R/log_*.txt; do echo "$f: $(tail -c 300 $f | tr '\r' '\n' | tail -2)"; done
cd $R && tar czf $OUT/probe.tgz run_*/metrics.json run_*/config.json log_*.txt cfg_*.json 2>/dev/null
ls -la $OUT
